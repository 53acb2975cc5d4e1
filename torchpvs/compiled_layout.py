"""Stage 5b (part) — the layout and the maps of a batch, compiled.

:func:`torchpvs.sections.build_layout` (the sections, masks and fixed quantities at given
insertions) and :func:`torchpvs.mechanics.build_maps` (the ``q``-independent structure of the
energy on the compact coordinates, and the pose constants) are about 120 small torch ops
together. Wherever the insertions change between solves (every step of a force-controlled
environment, the two sides of a kink, a cold solve at new insertions) they cost more than the
compiled Newton solve itself: 20 % of a batched force-env step at ``B = 64``. Here both are one
numba call per batch, with plain loops over each element's sections, tubes and nodes.

The same quantities, in the same fields (:class:`~torchpvs.sections.Layout`,
:class:`~torchpvs.mechanics.Maps`), computed by the same formulas: elementwise results are the
eager ones bit for bit (the same IEEE operations in the same order, no fast-math); sums over
quadrature nodes (the energy blocks and the guide's stored energy) are taken in another order
and agree to rounding. ``tests/test_compiled_layout.py`` compares every field with the eager
builders.

Where it applies: no gradient (a layout that must carry a graph to the insertions, rotations
or tube properties is built by the eager functions), CPU float64 tensors, numba importable.
Float32 stays eager: numba evaluates a float32 array's arithmetic with Python-float constants
in double precision, so a mask taken on a near-tie (a transition at the orifice) could differ
from the eager float32 one. :func:`layout_and_maps` returns None elsewhere and the caller
builds them eagerly.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from .basis import gauss_legendre
from .compiled import horner
from .compiled_load import cached_jit
from .mechanics import Maps, PoseConstants, node_tables
from .sections import Discretization, Layout, TubeTensors

try:
    import numba
except ImportError:      # pragma: no cover - numba is a dependency; see torchpvs.compiled
    numba = None

__all__ = ["layout_and_maps", "layout_and_maps_of", "layout_maps_arrays"]

_jit = cached_jit(nogil=True)
# components as int64, not int literals: one compiled specialization (see compiled's _C0)
_C0, _C1 = np.int64(0), np.int64(1)


@_jit
def _poly_antiderivative(coef, j, c, t):
    """``int_0^t sum_p coef[j, c, p] x^p dx`` (sections._poly_antiderivative_value's order)."""
    P = coef.shape[-1]
    out = t * 0.0
    for p in range(P - 1, -1, -1):
        out = (out + coef[j, c, p] / (p + 1)) * t
    return out


@_jit
def _poly_int(coef, j, t):
    """The z-polynomial's integral from 0 to ``t`` (mechanics._poly_int's order)."""
    P = coef.shape[-1]
    out = coef[j, 2, P - 1] / P * t
    for p in range(P - 2, -1, -1):
        out = (out + coef[j, 2, p] / (p + 1)) * t
    return out


@_jit
def _partition(keep, out):
    """``out[:] =`` the indices where ``keep`` holds, in order, then the others (a stable
    argsort of ``~keep``), as many as ``out`` holds."""
    i = 0
    for k in range(keep.shape[0]):
        if keep[k] and i < out.shape[0]:
            out[i] = k
            i += 1
    for k in range(keep.shape[0]):
        if not keep[k] and i < out.shape[0]:
            out[i] = k
            i += 1


@_jit
def _horner_zero(coef, j, c, t):
    """``sum_p coef[j, c, p] t^p``, Horner from zero (sections._poly_eval's order)."""
    P = coef.shape[-1]
    out = t * 0.0
    for p in range(P - 1, -1, -1):
        out = out * t + coef[j, c, p]
    return out


@_jit
def _layout_one(b, EI, GJ, L, Ls, coef, D, A, loaded, min_section, xg, wg, wq, n,
                ell, tau, start, h, present, curved, active, presc, qmask, psi0, gconst, W,
                tip_tube, s_tip, before_l1):
    """Element ``b`` of :func:`torchpvs.sections.build_layout` into the layout arrays."""
    N = D.shape[1]
    S = 2 * N
    C = 2 + N
    Q = wq.shape[0]
    G = xg.shape[0]
    cuts = np.empty(S, dtype=D.dtype)
    for j in range(N):
        e = L[b, j] - D[b, j]
        ell[b, j] = e if e > 0.0 else 0.0
        tau[b, j] = Ls[b, j] - D[b, j]
        tc = tau[b, j] if tau[b, j] > 0.0 else 0.0
        cuts[j] = ell[b, j]
        cuts[N + j] = tc if tc < ell[b, j] else ell[b, j]
    cuts.sort()
    for k in range(S):
        start[b, k] = 0.0 if k == 0 else cuts[k - 1]
        h[b, k] = cuts[k] - start[b, k]
        nonempty = h[b, k] > min_section
        mid = start[b, k] + 0.5 * h[b, k]
        n_present = 0
        for j in range(N):
            pr = (mid < ell[b, j]) and nonempty
            present[b, k, j] = 1.0 if pr else 0.0
            curved[b, k, j] = 1.0 if (pr and mid > tau[b, j]) else 0.0
            n_present += pr
        act = nonempty and (n_present >= 2 or loaded[b])
        active[b, k] = 1.0 if act else 0.0
        presc[b, k] = 1.0 if (nonempty and not act and n_present == 1) else 0.0
        for q in range(Q):
            W[b, k, q] = 0.5 * h[b, k] * wq[q] * active[b, k]
        for c in range(C):
            on = act and (c < 2 or present[b, k, c - 2] > 0.0)
            base = N + (k * C + c) * n
            for p in range(n):
                qmask[b, base + p] = 1.0 if on else 0.0
        before_l1[b, k] = 1.0 if cuts[k] <= ell[b, 0] + 1e-12 else 0.0
    total = 0.0
    emax = ell[b, 0]
    for j in range(N):
        qmask[b, j] = 1.0 if (D[b, j] > 0.0 and ell[b, j] > 0.0) else 0.0
        guided = D[b, j] if D[b, j] < L[b, j] else L[b, j]
        tg = guided - Ls[b, j]
        tg = tg if tg > 0.0 else 0.0
        psi0[b, j] = A[b, j] + _poly_antiderivative(coef[b], j, 2, tg)
        acc = 0.0
        for g in range(G):
            t = 0.5 * (xg[g] + 1.0) * tg
            ux = _horner_zero(coef[b], j, _C0, t)
            uy = _horner_zero(coef[b], j, _C1, t)
            acc += (ux * ux + uy * uy) * wg[g]
        total += 0.5 * EI[b, j] * (0.5 * tg) * acc
        if ell[b, j] > emax:
            emax = ell[b, j]
    gconst[b] = total
    s_tip[b] = emax
    # the tube forming the tip: the largest exposed length, ties -> innermost (the eager
    # score, 1e-9 of the longest exposed length per tube index)
    best = 0
    best_score = ell[b, 0]
    for j in range(1, N):
        score = ell[b, j] + 1e-9 * j * (emax + 1e-12)
        if score > best_score:
            best, best_score = j, score
    for j in range(N):
        tip_tube[b, j] = 1.0 if j == best else 0.0


@_jit
def _maps_one(b, EI, GJ, coef, D, n, xq, xm, phi, tau, start, h, present, curved, active,
              presc, qmask, W, sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide, bvec,
              qmask_c, h_c, presc_inc, p_h, p_inc, p_held, p_local):
    """Element ``b`` of :func:`torchpvs.mechanics.build_maps` into the maps arrays."""
    N = D.shape[1]
    S_full = 2 * N
    C = 2 + N
    S = sec.shape[1]
    Sp = psec.shape[1]
    Q = xq.shape[0]
    G = xm.shape[0]
    nc = cidx.shape[1]
    # compact sections: the active ones in backbone order, then the others; the pose's: the
    # nonempty ones, then the others
    _partition(active[b] > 0.5, sec[b])
    _partition(h[b] > 0.0, psec[b])
    for j in range(N):
        cidx[b, j] = j
    for i in range(S):
        for m in range(C * n):
            cidx[b, N + i * C * n + m] = N + sec[b, i] * (C * n) + m
    for m in range(nc):
        qmask_c[b, m] = qmask[b, cidx[b, m]]
    for j in range(N):
        guide[b, j] = GJ[b, j] * D[b, j] * qmask_c[b, j]
    # every slot's prescribed twist (node-independent)
    for k in range(S_full):
        for j in range(N):
            pm = curved[b, k, j] * presc[b, k]
            t0 = start[b, k] - tau[b, j]
            Z0 = _poly_int(coef[b], j, t0)
            presc_inc[b, k, j] = (_poly_int(coef[b], j, t0 + h[b, k]) - Z0) * pm
    for i in range(S):
        k = sec[b, i]
        h_c[b, i] = h[b, k]
        for q in range(Q):
            s = start[b, k] + 0.5 * (xq[q] + 1.0) * h[b, k]
            acc = 0.0
            for j in range(N):
                t = s - tau[b, j]
                for c in range(3):
                    ustar[b, i, q, j, c] = horner(coef[b], j, c, t) * curved[b, k, j]
                EIw[b, i, q, j] = W[b, k, q] * (EI[b, j] * present[b, k, j])
                GJw[b, i, q, j] = W[b, k, q] * (GJ[b, j] * present[b, k, j])
                acc = EIw[b, i, q, j] if j == 0 else acc + EIw[b, i, q, j]
            EIws[b, i, q] = acc
        # the q-independent section blocks: bending A (x) I_2 (the tubes' EI summed, as the
        # eager sum_dim), torsion T_kj (GJw's node weights)
        eis = 0.0
        for j in range(N):
            eis += EI[b, j] * present[b, k, j]
        for p in range(n):
            for r in range(n):
                a = 0.0
                for q in range(Q):
                    a += W[b, k, q] * eis * phi[q, p] * phi[q, r]
                Hsec[b, i, 0, p, 0, r] = a
                Hsec[b, i, 1, p, 1, r] = a
                for j in range(N):
                    t_ = 0.0
                    for q in range(Q):
                        t_ += GJw[b, i, q, j] * phi[q, p] * phi[q, r]
                    Hsec[b, i, 2 + j, p, 2 + j, r] = t_
        # angle bases b_kj = d psi_j(start of k) / dq on the compact coordinates: D_j on the
        # guide twist w_j, h_l on the mean torsion of tube j in every earlier section l
        for j in range(N):
            for m in range(nc):
                f = cidx[b, m]
                v = 0.0
                if f < N:
                    if f == j:
                        v = D[b, j]
                else:
                    rel = f - N
                    sl = rel // (C * n)
                    rem = rel - sl * (C * n)
                    if sl < k and rem == (2 + j) * n:
                        v = h[b, sl]
                bvec[b, i, j, m] = v * qmask[b, f]
    # pose constants at the Magnus nodes, on the nonempty sections
    for i in range(Sp):
        k = psec[b, i]
        p_h[b, i] = h[b, k]
        for j in range(N):
            p_inc[b, i, j] = presc_inc[b, k, j]
            held = presc[b, k] * present[b, k, j]
            pm = curved[b, k, j] * presc[b, k]
            t0 = start[b, k] - tau[b, j]
            Z0 = _poly_int(coef[b], j, t0)
            for g in range(G):
                s = start[b, k] + 0.5 * (xm[g] + 1.0) * h[b, k]
                t = s - tau[b, j]
                for c in range(2):
                    p_held[b, i, g, j, c] = horner(coef[b], j, c, t) * curved[b, k, j] * held
                p_local[b, i, g, j] = (_poly_int(coef[b], j, t) - Z0) * pm


@_jit
def layout_maps_arrays(EI, GJ, L, Ls, coef, D, A, loaded, min_section, xg, wg, xq, wq, xm, phi, n):
    """The layout arrays, then the maps arrays of the whole batch (the compact section count
    is the batch's largest), as numpy arrays in the order :func:`layout_and_maps` unpacks
    them; callable from other compiled code (:mod:`torchpvs.tracker`)."""
    B, N = D.shape
    S_full = 2 * N
    C = 2 + N
    Q = xq.shape[0]
    G = xm.shape[0]
    nq = N + S_full * C * n
    dt = D.dtype
    ell = np.empty((B, N), dtype=dt)
    tau = np.empty((B, N), dtype=dt)
    start = np.empty((B, S_full), dtype=dt)
    h = np.empty((B, S_full), dtype=dt)
    present = np.empty((B, S_full, N), dtype=dt)
    curved = np.empty((B, S_full, N), dtype=dt)
    active = np.empty((B, S_full), dtype=dt)
    presc = np.empty((B, S_full), dtype=dt)
    qmask = np.empty((B, nq), dtype=dt)
    psi0 = np.empty((B, N), dtype=dt)
    gconst = np.empty(B, dtype=dt)
    W = np.empty((B, S_full, Q), dtype=dt)
    tip_tube = np.empty((B, N), dtype=dt)
    s_tip = np.empty(B, dtype=dt)
    before_l1 = np.empty((B, S_full), dtype=dt)
    for b in range(B):
        _layout_one(b, EI, GJ, L, Ls, coef, D, A, loaded, min_section, xg, wg, wq, n,
                    ell, tau, start, h, present, curved, active, presc, qmask, psi0, gconst,
                    W, tip_tube, s_tip, before_l1)
    S = 1
    Sp = 1
    for b in range(B):
        na = 0
        ne = 0
        for k in range(S_full):
            na += active[b, k] > 0.5
            ne += h[b, k] > 0.0
        S = max(S, na)
        Sp = max(Sp, ne)
    nc = N + S * C * n
    sec = np.empty((B, S), dtype=np.int64)
    psec = np.empty((B, Sp), dtype=np.int64)
    cidx = np.empty((B, nc), dtype=np.int64)
    ustar = np.empty((B, S, Q, N, 3), dtype=dt)
    EIw = np.empty((B, S, Q, N), dtype=dt)
    EIws = np.empty((B, S, Q), dtype=dt)
    GJw = np.empty((B, S, Q, N), dtype=dt)
    Hsec = np.zeros((B, S, C, n, C, n), dtype=dt)
    guide = np.zeros((B, nc), dtype=dt)
    bvec = np.empty((B, S, N, nc), dtype=dt)
    qmask_c = np.empty((B, nc), dtype=dt)
    h_c = np.empty((B, S), dtype=dt)
    presc_inc = np.empty((B, S_full, N), dtype=dt)
    p_h = np.empty((B, Sp), dtype=dt)
    p_inc = np.empty((B, Sp, N), dtype=dt)
    p_held = np.empty((B, Sp, G, N, 2), dtype=dt)
    p_local = np.empty((B, Sp, G, N), dtype=dt)
    for b in range(B):
        _maps_one(b, EI, GJ, coef, D, n, xq, xm, phi, tau, start, h, present, curved, active,
                  presc, qmask, W, sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide, bvec,
                  qmask_c, h_c, presc_inc, p_h, p_inc, p_held, p_local)
    return (ell, tau, start, h, present, curved, active, presc, qmask, psi0, gconst, W,
            tip_tube, s_tip, before_l1, sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide,
            bvec, qmask_c, h_c, presc_inc, p_h, p_inc, p_held, p_local)


@functools.lru_cache(maxsize=64)
def _constants(disc: Discretization, P: int, dtype: torch.dtype):
    """The tables a compiled layout reads (numpy, ``dtype``) and the shared torch tables of
    the maps, per discretization and precurvature degree."""
    tab = disc.tables(dtype, torch.device("cpu"))
    xg, wg = gauss_legendre(max(2, P + 1), dtype=dtype)
    values_T, Q_QQ, phi_PQ = node_tables(tab.phi_q, tab.Q_q)
    arrays = tuple(t.numpy() for t in (xg, wg, tab.xq, tab.wq, tab.xm, tab.phi_q))
    return tab, arrays, (values_T, Q_QQ, phi_PQ)


def _numpy(t: torch.Tensor, shape) -> np.ndarray:
    a = t.expand(shape).numpy()
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def layout_and_maps(tubes: TubeTensors, D: torch.Tensor, A: torch.Tensor, F: torch.Tensor,
                    M: torch.Tensor, loaded: torch.Tensor, disc: Discretization,
                    nq: int) -> tuple[Layout, Maps] | None:
    """``(build_layout(tubes, D, A, F, M, loaded, disc), build_maps(that, tables, nq))``
    compiled (the arguments of :func:`torchpvs.sections.build_layout`; ``nq`` the padded
    coordinate count of ``disc``). None where it does not apply (see the module docstring):
    the caller then builds both eagerly."""
    dtype = D.dtype
    if (numba is None or D.device.type != "cpu" or dtype != torch.float64
            or torch.is_grad_enabled() and any(
                t.requires_grad for t in (D, A, F, M, *tubes.tensors()))):
        return None
    B, N = D.shape
    P = tubes.coef.shape[-1]
    tab, (xg, wg, xq, wq, xm, phi), shared = _constants(disc, P, dtype)
    n = disc.n_basis
    if nq != N + 2 * N * (2 + N) * n:
        return None
    Dn = D.detach()
    out = layout_maps_arrays(
        _numpy(tubes.EI.detach().to(dtype), (B, N)), _numpy(tubes.GJ.detach().to(dtype), (B, N)),
        _numpy(tubes.length.detach().to(dtype), (B, N)),
        _numpy(tubes.straight.detach().to(dtype), (B, N)),
        _numpy(tubes.coef.detach().to(dtype), (B, N, 3, P)), _numpy(Dn, (B, N)),
        _numpy(A.detach(), (B, N)), _numpy(loaded, (B,)), 1e-12, xg, wg, xq, wq, xm, phi, n)
    return layout_and_maps_of(out, tubes, D, A, F, M, loaded, disc)


def layout_and_maps_of(out: tuple, tubes: TubeTensors, D: torch.Tensor, A: torch.Tensor,
                       F: torch.Tensor, M: torch.Tensor, loaded: torch.Tensor,
                       disc: Discretization) -> tuple[Layout, Maps]:
    """``(lay, maps)`` of :func:`layout_maps_arrays`'s arrays ``out`` for the arguments of
    :func:`layout_and_maps` (float64 CPU; the minimum section 1e-12 and ``disc``'s tables):
    what it returns, without computing them again where a compiled caller already did
    (torchpvs.fused)."""
    B, N = D.shape
    P = tubes.coef.shape[-1]
    tab, _, shared = _constants(disc, P, D.dtype)
    (ell, tau, start, h, present, curved, active, presc, qmask, psi0, gconst, W, tip_tube,
     s_tip, before_l1, sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide, bvec, qmask_c,
     h_c, presc_inc, p_h, p_inc, p_held, p_local) = (torch.from_numpy(x) for x in out)
    dtype = D.dtype
    lay = Layout(EI=tubes.EI.expand(B, N), GJ=tubes.GJ.expand(B, N), D=D, alpha=A,
                 coef=tubes.coef.expand(B, N, 3, P), tau=tau, ell=ell, start=start, h=h,
                 present=present, curved=curved, active=active, presc=presc, qmask=qmask,
                 psi0=psi0, guide_const=gconst, W=W, force=F, moment=M, tip_tube=tip_tube,
                 s_tip=s_tip, before_l1=before_l1, loaded=loaded.to(dtype))
    values_T, Q_QQ, phi_PQ = shared
    maps = Maps(ustar=ustar, EIw=EIw, EIws=EIws, GJw=GJw, H_sections=Hsec, guide=guide,
                guide_const=gconst, h=h_c, qmask=qmask_c, psi0=psi0,
                bvec=bvec, cidx=cidx, presc_inc=presc_inc, phi=tab.phi_q, Qb=tab.Q_q,
                values_T=values_T, Q_QQ=Q_QQ, phi_PQ=phi_PQ,
                pose=PoseConstants(sec=psec, h=p_h, presc_inc=p_inc, ustar_held=p_held,
                                   presc_local=p_local))
    return lay, maps
