"""Stage 5b — the compiled CPU kernel: the damped Newton solve and the Newton step, per element.

The same iteration as the eager kernel (:mod:`torchpvs.newton`: Jacobi-scaled
Levenberg–Marquardt damping, the trusted pure-Newton phase, the Armijo line search, the saddle
test and escape, the stability verdict), written as plain loops over one element's coordinates
and compiled by numba (``@njit(cache=True)``: machine code cached in a directory named by a
hash of this module's and :mod:`torchpvs.compiled_load`'s sources,
:func:`torchpvs.compiled_load.cache_dir`, so only the first process of a version compiles).
Each batch element runs on its own, in parallel across ``torch.get_num_threads()`` threads for
batches of 8 or more. One element's gradient and
exact Hessian (the node sums of :func:`torchpvs.mechanics.elastic_grad_hess`), its
factorization and the line-search energies cost a few microseconds; the eager kernel spends
about a millisecond per iteration on operator dispatch at small batches.

What it covers: float32 and float64 CPU tensors, unloaded or under a dead tip force (its work
``F . p_tip`` and that work's exact gradient and Hessian through the Magnus chain:
:mod:`torchpvs.compiled_load`; a dead tip moment, non-conservative, falls back to
:data:`torchpvs.kernel.EAGER` for the whole call), ``method`` ``"minimize"`` and ``"root"``. A
``deadline`` is checked once, on entry (past it, the eager kernel takes its single evaluation).
Differences from the eager kernel, all at rounding level or in rare branches: sums are taken in
another order (coordinates agree to ~1e-15 relative, iterations and verdicts are the same on
the test scenes) and the 8-escape cap of the saddle escape counts per element (the eager kernel
counts per batch). The energy at the solution is left to the driver (eager, bit for bit).

:data:`COMPILED` (``SolverOptions(kernel="compiled")``) is the eager kernel with ``solve`` and
``step`` replaced; :func:`available` says whether numba is importable here.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch

from .clock import work_clock
from .compiled_load import cached_jit, load_work, mat4
from .mechanics import compact_q, expand_q
from .newton import NewtonResult, Problem, tolerance

try:
    import numba
    from numba import prange
except ImportError:      # pragma: no cover - numba is a dependency; this is the fallback
    numba = None         # (cached_jit then leaves the functions below plain Python)
    prange = range

__all__ = ["available", "partials", "pose", "section_step", "solve", "step", "stiffness_rows",
           "tip_partials"]

# Batches from this size run in parallel (a parallel launch costs ~10 us: a serial loop over a
# few elements is faster).
_PARALLEL_FROM = 8

# Below this imaginary part, cosh(b) rounds to 1 and sinh(b) to b in float64.
_TINY_IMAG = 1e-9

# Constant orders (evaluate, total) and components (horner) passed as int64, not as Python
# ints: numba compiles a function called with an int literal once per value, and once more
# where the same argument is a variable (evaluate at orders 0, 2 and 3 was compiled three
# times, about 4 s each, on first use; numba's compile events). Global numpy ints are typed
# int64, one specialization for all.
_E0, _E2, _E3 = np.int64(0), np.int64(2), np.int64(3)
_C0, _C1, _C2 = np.int64(0), np.int64(1), np.int64(2)


def cos_sin(x):
    """``(cos x, sin x)`` of a real or complex ``x``. In compiled code a complex ``x = a + ib``
    of the complex step (``|b| <= 1e-9``) takes two real calls, ``cos a - i b sin a`` and
    ``sin a + i b cos a``, instead of numba's eight (``cosh b``, ``sinh b`` and both again for
    the second function): the same values bit for bit, since ``cosh b`` rounds to 1 and
    ``sinh b`` to ``b`` there (``tests/test_compiled.py``)."""
    return np.cos(x), np.sin(x)


if numba is not None:
    from numba.extending import overload

    @overload(cos_sin)
    def _cos_sin_compiled(x):
        if isinstance(x, numba.types.Complex):
            def impl(x):
                a, b = x.real, x.imag
                if abs(b) > _TINY_IMAG:
                    return np.cos(x), np.sin(x)
                ca, sa = math.cos(a), math.sin(a)
                return complex(ca, -(sa * b)), complex(sa, ca * b)
            return impl

        def impl_real(x):
            return math.cos(x), math.sin(x)
        return impl_real


def available() -> bool:
    """Whether the compiled kernel can run here (numba imports)."""
    return numba is not None


def _get(maps, key):
    return maps[key] if isinstance(maps, dict) else getattr(maps, key)


def _applicable(q: torch.Tensor, prob: Problem) -> bool:
    if q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64):
        return False
    if numba is None:
        # (Python's default filter shows this once per process)
        warnings.warn("torchpvs: numba is not importable, so the compiled kernel runs the "
                      "eager one (SolverOptions(kernel='newton')); pip install numba",
                      RuntimeWarning, stacklevel=4)
        return False
    if prob.with_load:   # a dead tip moment (non-conservative) keeps the eager kernel
        return not bool((prob.lay.moment != 0).any())
    return True


def _arrays(prob: Problem, dtype: torch.dtype):
    """The maps a compiled evaluation reads, as contiguous numpy arrays of ``dtype``."""
    m = prob.maps

    def a(key):
        return _numpy(_get(m, key), dtype)

    return (a("qmask"), a("psi0"), a("bvec"), a("h"), a("ustar"), a("EIw"), a("EIws"),
            a("GJw"), a("H_sections"), a("guide"), a("guide_const"), a("phi"), a("Qb"))


def _load_arrays(prob: Problem, dtype: torch.dtype, B: int) -> tuple | None:
    """What :func:`torchpvs.compiled_load.load_work` reads, batched: the compact index of every
    padded coordinate, the padded mask, the pose constants, the tip force and the Magnus
    tables; None without a load. None is a type of its own to numba, whose branch pruning then
    removes the load terms from the unloaded specializations: they are compiled only once a
    loaded problem comes (the first use of the default, unloaded solve does not pay for them)."""
    if not prob.with_load:
        return None
    lay, const, tab = prob.lay, prob.maps.pose, prob.tab
    cidx = _get(prob.maps, "cidx")
    nq = lay.qmask.shape[-1]
    inv = torch.full((B, nq), -1, dtype=torch.long).scatter_(
        1, cidx, torch.arange(cidx.shape[-1]).expand_as(cidx).contiguous())

    def a(t):
        return _numpy(t, dtype)

    return (_numpy(inv), a(lay.qmask), a(lay.psi0), a(lay.D),
            _numpy(_get(const, "sec")),
            *(a(_get(const, k)) for k in ("h", "presc_inc", "ustar_held", "presc_local")),
            a(lay.force.expand(B, 3)), a(_get(tab, "phi_m")), a(_get(tab, "Q_m")))


def _numpy(t: torch.Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    """``t`` (converted to ``dtype`` where given) as a C-contiguous numpy array, sharing its
    memory where it can. Detaches and converts only where needed: at B = 1 a solve passes a
    few hundred arrays to the compiled functions, and each unneeded ``detach``/``to`` is a
    dispatched torch op (about a fifth of a warm solve's ops before this)."""
    if t.requires_grad:
        t = t.detach()
    if dtype is not None and t.dtype != dtype:
        t = t.to(dtype)
    a = t.numpy()
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def _set_threads(B: int) -> bool:
    if B < _PARALLEL_FROM:
        return False
    n = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if n <= 1:
        # Not even set_num_threads(1): it launches numba's thread pool, whose OpenMP worker
        # then spins a second core for as long as the process runs (measured: a one-thread
        # training loop used 1.8 cores).
        return False
    numba.set_num_threads(n)
    return True


def solve(q: torch.Tensor, prob: Problem, L_char: torch.Tensor, *, method: str, tol: float,
          max_iter: int, deadline: float | None = None) -> NewtonResult | None:
    """:func:`torchpvs.newton.newton`'s contract (same arguments and :class:`NewtonResult`),
    compiled; None where the compiled kernel does not apply (see the module docstring: the
    caller then runs the eager kernel)."""
    if (not _applicable(q, prob) or method not in ("minimize", "root")
            or (deadline is not None and work_clock() > deadline)):
        return None
    dtype = q.dtype
    npt = np.float64 if dtype == torch.float64 else np.float32
    B, nq = q.shape
    cidx = _get(prob.maps, "cidx")
    qc = _numpy(compact_q(q, cidx), dtype)
    nc = qc.shape[1]
    arrs = _arrays(prob, dtype)
    Lc = _numpy(L_char, dtype)
    H = np.empty((B, nc, nc), dtype=npt)
    g = np.empty((B, nc), dtype=npt)
    U = np.empty(B, dtype=npt)
    res = np.empty(B, dtype=npt)
    it = np.zeros(B, dtype=np.int64)
    conv = np.zeros(B, dtype=np.bool_)
    verdict = np.empty(B, dtype=np.int8)
    eps = float(torch.finfo(dtype).eps)
    consts = np.array([tolerance(tol, dtype), 0.01 * eps ** 0.5, eps,
                       float(torch.finfo(dtype).tiny)], dtype=npt)
    run = _newton_parallel if _set_threads(B) else _newton_serial
    run(qc, *arrs, _load_arrays(prob, dtype, B), Lc, consts, method == "minimize", max_iter, H,
        g, U, res, it, conv, verdict)
    t = torch.from_numpy
    # energy None: the driver evaluates it with the eager energy, so that Equilibrium.energy is
    # bit for bit mechanics.elastic_energy_maps at the returned q (the compiled sums round
    # differently)
    return NewtonResult(expand_q(t(qc), cidx, nq), t(H), expand_q(t(g), cidx, nq), t(conv),
                        t(res), t(it), t(verdict), None)


def step(q: torch.Tensor, prob: Problem) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`torchpvs.kernel.newton_step`'s contract, compiled; None where the compiled
    kernel does not apply."""
    if not _applicable(q, prob):
        return None
    dtype = q.dtype
    npt = np.float64 if dtype == torch.float64 else np.float32
    nq = q.shape[-1]
    cidx = _get(prob.maps, "cidx")
    qc = _numpy(compact_q(q, cidx), dtype)
    ok = np.zeros(qc.shape[0], dtype=np.bool_)
    eps = float(torch.finfo(dtype).eps)
    consts = np.array([0.0, 0.0, eps, float(torch.finfo(dtype).tiny)], dtype=npt)
    run = _step_parallel if _set_threads(qc.shape[0]) else _step_serial
    run(qc, *_arrays(prob, dtype), _load_arrays(prob, dtype, qc.shape[0]), consts, ok)
    okt = torch.from_numpy(ok)
    q1 = expand_q(torch.from_numpy(qc), cidx, nq)
    return torch.where(okt[:, None], q1, q), okt


def section_step(q: torch.Tensor, prob: Problem, new: torch.Tensor,
                 hmax: float) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`torchpvs.kernel.new_section_step` compiled (the same block, the same conditions;
    ``hmax`` [m] the longest section that counts as vanishing); None where the compiled kernel
    does not apply."""
    if not _applicable(q, prob) or prob.with_load:
        return None
    dtype = q.dtype
    nq = q.shape[-1]
    cidx = _get(prob.maps, "cidx")
    qc = _numpy(compact_q(q, cidx), dtype)
    newc = _numpy(torch.gather(new, 1, cidx))
    ok = np.zeros(qc.shape[0], dtype=np.bool_)
    run = _section_parallel if _set_threads(qc.shape[0]) else _section_serial
    run(qc, *_arrays(prob, dtype), newc, hmax, ok)
    okt = torch.from_numpy(ok)
    q1 = expand_q(torch.from_numpy(qc), cidx, nq)
    return torch.where(okt[:, None], q1, q), okt


def _layout_arrays(q: torch.Tensor, lay, tubes, tab) -> tuple | None:
    """The arguments of :func:`partials_one` after ``q``'s (numpy, ``q``'s dtype), or None
    where the compiled kernel does not apply (a tensor that requires grad, not CPU)."""
    if (numba is None or q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64)
            or torch.is_grad_enabled() and (q.requires_grad or lay.D.requires_grad
                                            or lay.alpha.requires_grad)):
        return None
    dtype = q.dtype
    B, N = lay.D.shape

    def a(t, shape=None):
        return _numpy(t if shape is None or t.shape == shape else t.expand(shape), dtype)

    return (a(lay.qmask), a(lay.D), a(tubes.length, (B, N)), a(tubes.straight, (B, N)),
            a(lay.EI), a(lay.GJ), a(lay.coef), a(lay.tau), a(lay.psi0), a(lay.start), a(lay.h),
            a(lay.present), a(lay.curved), a(lay.active), a(lay.presc), a(lay.W),
            a(_get(tab, "xq")), a(_get(tab, "wq")), a(_get(tab, "phi_q")), a(_get(tab, "Q_q")))


def partials(q: torch.Tensor, lay, tubes, tab) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`torchpvs.forces.closed_form_partials` compiled (``q (B, nq)`` on the layout
    ``lay``, the tube rows ``tubes``): ``(dU/dD, dU/dalpha)`` ``(B, N)``; None where the
    compiled kernel does not apply (a tensor that requires grad, not CPU)."""
    args = _layout_arrays(q, lay, tubes, tab)
    if args is None:
        return None
    qa = _numpy(q, q.dtype)
    B, N = lay.D.shape
    tau_D = np.empty((B, N), dtype=qa.dtype)
    tau_A = np.empty((B, N), dtype=qa.dtype)
    run = _partials_parallel if _set_threads(B) else _partials_serial
    run(qa, *args, tau_D, tau_A)
    return torch.from_numpy(tau_D), torch.from_numpy(tau_A)


def stiffness_rows(q: torch.Tensor, lay, tubes, tab, rotations: bool = False) -> tuple | None:
    """Rows of the unloaded energy's Hessian at fixed ``q (B, nq)`` on the layout ``lay``:
    ``(U_xq (B, m, nq), U_xD (B, m, N), U_xalpha (B, m, N))`` for ``x`` the insertions
    (``m = N``) or, with ``rotations``, the insertions then the rotations (``m = 2N``), zero on
    the inactive coordinates — what :func:`torchpvs.forces.actuation_rows` differentiates
    :func:`~torchpvs.forces.closed_form_partials` for, by a complex step per actuator
    (:func:`stiffness_rows_one`, exact to rounding; ``U_xq = (dg/dx)^T`` by the symmetry of
    second derivatives). None where the compiled kernel does not apply (a tensor that requires
    grad, not CPU). Computed in float64 (complex128), returned in ``q``'s dtype."""
    args = _layout_arrays(q, lay, tubes, tab)
    if args is None:
        return None
    f64 = tuple(x.astype(np.float64, copy=False) for x in args)
    qa = _numpy(q, torch.float64)
    B, nq = qa.shape
    N = lay.D.shape[1]
    m = 2 * N if rotations else N
    Gq = np.empty((B, m, nq))
    X = np.empty((B, m, 2 * N))
    run = _stiffness_parallel if _set_threads(B) else _stiffness_serial
    run(qa, *f64, Gq, X)
    t = torch.from_numpy
    Xt = t(X)[:, :, :m].transpose(1, 2)              # (B, m rows, m directions)
    # U_Dalpha without the rotation directions: d tau_alpha / dD by symmetry
    UxA = Xt[:, :, N:] if rotations else t(X)[:, :, N:]
    return t(Gq).to(q.dtype), Xt[:, :, :N].to(q.dtype), UxA.to(q.dtype)


def _pose_arrays(q: torch.Tensor, lay, tubes, tab) -> tuple | None:
    """``(q, arrays)`` in float64 for the tip functions (:func:`tip_partials_one`'s arguments
    from ``qmask`` to ``Qb``), or None where the compiled kernel does not apply."""
    args = _layout_arrays(q, lay, tubes, tab)
    if args is None:
        return None
    (qmask, D, L, Ls, _, _, coef, tau, psi0, start, h, present, curved, _, presc,
     *_) = (x.astype(np.float64, copy=False) for x in args)
    B, N = D.shape
    f64 = torch.float64
    return _numpy(q, f64), (qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                            _numpy(lay.tip_tube.expand(B, N), f64), _numpy(tab.xm, f64),
                            _numpy(tab.phi_m, f64), _numpy(tab.Q_m, f64))


def tip_partials(q: torch.Tensor, lay, tubes, tab) -> tuple | None:
    """The tip's partials at fixed ``q (B, nq)`` on the layout ``lay`` (the tube rows
    ``tubes``): ``(P_q (B, 6, nq), P_D (B, 6, N), P_alpha (B, 6, N))``, rows the tip position
    [m] and spatial rotation [rad] (:func:`torchpvs.mechanics.tip_partials`), zero on the
    inactive coordinates: ``P_q`` through the Magnus chain, ``P_D`` and ``P_alpha`` by a complex
    step of the pose per actuator (:func:`tip_partials_one`). None where the compiled kernel
    does not apply (a tensor that requires grad, not CPU). Computed in float64 (complex128),
    returned in ``q``'s dtype."""
    args = _pose_arrays(q, lay, tubes, tab)
    if args is None:
        return None
    qa, arrays = args
    (B, nq), N = qa.shape, lay.D.shape[1]
    Pq = np.empty((B, 6, nq))
    Px = np.empty((B, 6, 2 * N))
    run = _tip_parallel if _set_threads(B) else _tip_serial
    run(qa, *arrays, Pq, Px)
    t = torch.from_numpy
    return (t(Pq).to(q.dtype), t(Px[:, :, :N]).to(q.dtype), t(Px[:, :, N:]).to(q.dtype))


def load_rows(q: torch.Tensor, lay, tubes, tab, force: torch.Tensor,
              rotations: bool = False) -> tuple | None:
    """Rows of a dead tip force's potential ``-F . p`` at fixed ``q (B, nq)`` on the layout
    ``lay`` (``force (B, 3)`` [N], base frame): ``(U_xq (B, m, nq), U_xD (B, m, N), U_xalpha
    (B, m, N))`` for ``x`` the insertions (``m = N``) or, with ``rotations``, the insertions
    then the rotations — what :func:`stiffness_rows` gives for the elastic energy, here for the
    load's work (:func:`load_rows_one`: a fourth-order central difference of the exact tip
    partials at layouts moved along the slopes, steps ``5e-4`` of the longest tube and
    ``1e-4`` rad; about 3e-13 of the largest entry on the Fig. 3 robot). None where the
    compiled kernel does not apply. Computed in float64, returned in ``q``'s dtype."""
    args = _pose_arrays(q, lay, tubes, tab)
    if args is None:
        return None
    qa, arrays = args
    (B, nq), N = qa.shape, lay.D.shape[1]
    m = 2 * N if rotations else N
    Gq = np.empty((B, m, nq))
    X = np.empty((B, m, 2 * N))
    L = arrays[2]
    dD = 5e-4 * float(L.max()) if L.size else 1e-4
    run = _load_rows_parallel if _set_threads(B) else _load_rows_serial
    run(qa, _numpy(force.expand(B, 3), torch.float64), *arrays, dD, 1e-4, Gq, X)
    t = torch.from_numpy
    return (t(Gq).to(q.dtype), t(X[:, :, :N]).to(q.dtype), t(X[:, :, N:]).to(q.dtype))


def pose(q: torch.Tensor, lay, tab, const) -> tuple | None:
    """:func:`torchpvs.mechanics.tip_pose`'s contract with the pose constants ``const`` (``q
    (..., B, nq)``), compiled: ``(tip (..., B, 3), R (..., B, 3, 3), psi_tip (..., B, N))``;
    None where the compiled kernel does not apply (a tensor that requires grad, not CPU)."""
    if (numba is None or q.device.type != "cpu" or q.dtype not in (torch.float32, torch.float64)
            or q.requires_grad or lay.qmask.requires_grad):
        return None
    dtype = q.dtype
    lead = q.shape[:-1]
    B, nq = lay.qmask.shape
    qf = _numpy(q.reshape(-1, B, nq), dtype)
    N = lay.psi0.shape[-1]
    S = lay.h.shape[-1]

    def a(t):
        return _numpy(t, dtype)

    phi, Qb = _get(tab, "phi_m"), _get(tab, "Q_m")
    tip = np.empty(qf.shape[:2] + (3,), dtype=qf.dtype)
    R = np.empty(qf.shape[:2] + (3, 3), dtype=qf.dtype)
    psi_tip = np.empty(qf.shape[:2] + (N,), dtype=qf.dtype)
    small = 1e-6 if dtype == torch.float64 else 1e-3
    run = _pose_parallel if _set_threads(qf.shape[0] * B) else _pose_serial
    sec = _numpy(_get(const, "sec"))
    per_section = (a(_get(const, k)) for k in ("h", "presc_inc", "ustar_held", "presc_local"))
    run(qf, a(lay.qmask), a(lay.psi0), a(lay.D), a(lay.tip_tube), sec, *per_section, a(phi),
        a(Qb), S, small, tip, R, psi_tip)
    t = torch.from_numpy
    return (t(tip).reshape(lead + (3,)), t(R).reshape(lead + (3, 3)),
            t(psi_tip).reshape(lead + (N,)))


# ---------------------------------------------------------------------------------------------
# Compiled functions. One element: q (nc,) compact coordinates; the maps of mechanics.build_maps
# at that element: qmask (nc,), psi0 (N,), bvec (S, N, nc), h (S,), ustar (S, Q, N, 3),
# EIw/GJw (S, Q, N), EIws (S, Q), H_sections (S, C, n, C, n), guide (nc,), guide_const (),
# and the shared tables phi, Qb (Q, n). C = 2 + N; section s's coordinates start at N + s C n.

_jit = cached_jit(nogil=True)

@_jit
def evaluate(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
             order, g, H):
    """The elastic energy (returned); with order >= 1 its gradient into g, with order 2
    its Hessian into H (mechanics.elastic_grad_hess, term by term); with order 3 only the
    Hessian's within-section blocks, without the terms through the angle bases and the guide
    diagonal (mechanics.section_grad_block's blocks, in place in H)."""
    N = psi0.shape[0]
    Q, n = phi.shape
    C = 2 + N
    Cn = C * n
    nc = q.shape[0]
    # the sections whose coordinates q holds: all of them, or the leading ones where
    # newton_one drops trailing sections that add nothing (active_extent)
    S = min(h.shape[0], (nc - N) // Cn)
    U = 0.0
    if order >= 1:
        g[:] = 0.0
    if order >= 2:
        H[:, :] = 0.0
    base = np.empty(N, dtype=q.dtype)
    dp = np.empty(N, dtype=q.dtype)
    loc = np.empty(N, dtype=q.dtype)
    Rx = np.empty(N, dtype=q.dtype)
    Ry = np.empty(N, dtype=q.dtype)
    gpsi_sum = np.zeros((S, N), dtype=q.dtype)
    gX = np.zeros((C, n), dtype=q.dtype)
    alpha = np.zeros((S, N), dtype=q.dtype)
    beta = np.zeros((N, n), dtype=q.dtype)
    mu = np.zeros((N, 2, n), dtype=q.dtype)
    gq = np.zeros((N, n, n), dtype=q.dtype)
    nqt = np.zeros((N, 2, n, n), dtype=q.dtype)
    big = nc if order == 2 else 1
    V = np.zeros((S * N, big), dtype=q.dtype)
    G = np.zeros((big, big), dtype=q.dtype)
    X = np.empty((C, n), dtype=q.dtype)
    for s in range(S):
        hh = 0.5 * h[s]
        off = N + s * Cn
        for c in range(C):
            for p in range(n):
                X[c, p] = q[off + c * n + p] * qm[off + c * n + p]
        for j in range(N):
            acc = 0.0
            for i in range(nc):
                acc += bvec[s, j, i] * q[i]
            base[j] = psi0[j] + acc
        if order >= 1:
            gX[:, :] = 0.0
        if order >= 2:
            beta[:, :] = 0.0
            mu[:, :, :] = 0.0
            gq[:, :, :] = 0.0
            nqt[:, :, :, :] = 0.0
        for k in range(Q):
            ux = 0.0
            uy = 0.0
            for p in range(n):
                ux += X[0, p] * phi[k, p]
                uy += X[1, p] * phi[k, p]
            for j in range(N):
                a = 0.0
                b = 0.0
                for p in range(n):
                    a += X[2 + j, p] * phi[k, p]
                    b += X[2 + j, p] * Qb[k, p]
                dp[j] = a
                loc[j] = b
            sERx = 0.0
            sERy = 0.0
            for j in range(N):
                psi = base[j] + hh * loc[j]
                cs = math.cos(psi)
                sn = math.sin(psi)
                usx = us[s, k, j, 0]
                usy = us[s, k, j, 1]
                Rx[j] = cs * usx - sn * usy
                Ry[j] = sn * usx + cs * usy
                dx = ux - Rx[j]
                dy = uy - Ry[j]
                tors = dp[j] - us[s, k, j, 2]
                U += 0.5 * (EIw[s, k, j] * (dx * dx + dy * dy) + GJw[s, k, j] * tors * tors)
                sERx += EIw[s, k, j] * Rx[j]
                sERy += EIw[s, k, j] * Ry[j]
            if order == 0:
                continue
            gux = EIws[s, k] * ux - sERx
            guy = EIws[s, k] * uy - sERy
            for p in range(n):
                gX[0, p] += gux * phi[k, p]
                gX[1, p] += guy * phi[k, p]
            for j in range(N):
                ERx = EIw[s, k, j] * Rx[j]
                ERy = EIw[s, k, j] * Ry[j]
                gpsi = ERy * ux - ERx * uy
                gdp = GJw[s, k, j] * (dp[j] - us[s, k, j, 2])
                gpsi_sum[s, j] += gpsi
                for p in range(n):
                    gX[2 + j, p] += gdp * phi[k, p] + hh * gpsi * Qb[k, p]
                if order >= 2:
                    hpp = ERx * ux + ERy * uy
                    alpha[s, j] += hpp
                    for p in range(n):
                        beta[j, p] += hpp * Qb[k, p]
                        mu[j, 0, p] += ERy * phi[k, p]
                        mu[j, 1, p] -= ERx * phi[k, p]
                        for r in range(n):
                            gq[j, p, r] += hpp * Qb[k, p] * Qb[k, r]
                            nqt[j, 0, p, r] += ERy * phi[k, p] * Qb[k, r]
                            nqt[j, 1, p, r] -= ERx * phi[k, p] * Qb[k, r]
        if order >= 1:
            for c in range(C):
                for p in range(n):
                    g[off + c * n + p] += gX[c, p] * qm[off + c * n + p]
        if order == 2:
            # V rows (s, j): alpha b / 2, plus beta at (j's torsion) and mu at the bending
            # coefficients of section s; the within-section blocks go straight into H.
            for j in range(N):
                r0 = s * N + j
                for i in range(nc):
                    V[r0, i] = 0.5 * alpha[s, j] * bvec[s, j, i]
                for p in range(n):
                    V[r0, off + (2 + j) * n + p] += hh * beta[j, p]
                    V[r0, off + p] += mu[j, 0, p]
                    V[r0, off + n + p] += mu[j, 1, p]
        if order >= 2:
            for c in range(C):
                for p in range(n):
                    for c2 in range(C):
                        for r in range(n):
                            H[off + c * n + p, off + c2 * n + r] += Hsec[s, c, p, c2, r]
            for j in range(N):
                tj = off + (2 + j) * n
                for p in range(n):
                    for r in range(n):
                        H[tj + p, tj + r] += hh * hh * gq[j, p, r]
                        for a in range(2):
                            v = hh * nqt[j, a, p, r]
                            H[off + a * n + p, tj + r] += v
                            H[tj + r, off + a * n + p] += v
    for i in range(nc):
        U += 0.5 * guide[i] * q[i] * q[i]
    U += gconst
    if order >= 1:
        for s in range(S):
            for j in range(N):
                w = gpsi_sum[s, j]
                for i in range(nc):
                    g[i] += w * bvec[s, j, i]
        for i in range(nc):
            g[i] += guide[i] * q[i]
    if order == 2:
        # b^T V + V^T b (symmetric: the upper triangle, mirrored), and the guide diagonal
        for r in range(S * N):
            sr = r // N
            jr = r % N
            for i in range(nc):
                bi = bvec[sr, jr, i]
                vi = V[r, i]
                if bi == 0.0 and vi == 0.0:
                    continue
                for l in range(i, nc):
                    G[i, l] += bi * V[r, l] + vi * bvec[sr, jr, l]
        for i in range(nc):
            H[i, i] += G[i, i] + guide[i]
            for l in range(i + 1, nc):
                H[i, l] += G[i, l]
                H[l, i] += G[i, l]
    return U

@_jit
def total(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld, order,
          g, H):
    """:func:`evaluate` (orders 0-2) plus the potential ``-F . p_tip`` of the element's dead tip
    force and its derivatives (``ld``: :func:`element` of :func:`_load_arrays`;
    :func:`torchpvs.compiled_load.load_work`); nothing is added for a zero force or ``ld``
    None."""
    U = evaluate(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, order,
                 g, H)
    if ld is None:
        return U
    F = ld[9]
    if F[0] == 0.0 and F[1] == 0.0 and F[2] == 0.0:
        return U
    nc = q.shape[0]
    gW = np.empty(nc, dtype=q.dtype)
    HW = np.empty((nc, nc) if order >= 2 else (1, 1), dtype=q.dtype)
    W = load_work(q, ld[0], ld[1], ld[2], ld[3], ld[4], ld[5], ld[6], ld[7], ld[8], F, ld[10],
                  ld[11], order, gW, HW)
    if order >= 1:
        for i in range(nc):
            g[i] -= gW[i]
    if order >= 2:
        for i in range(nc):
            for k in range(nc):
                H[i, k] -= HW[i, k]
    return U - W


@_jit
def element(LD, b):
    """Element ``b`` of the batched load arrays (:func:`_load_arrays`)."""
    return (LD[0][b], LD[1][b], LD[2][b], LD[3][b], LD[4][b], LD[5][b], LD[6][b], LD[7][b],
            LD[8][b], LD[9][b], LD[10], LD[11])


@_jit
def cholesky(A, L):
    """Lower Cholesky factor of A into L; False where A is not positive definite."""
    n = A.shape[0]
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d -= L[j, k] * L[j, k]
        if not d > 0.0:         # (also NaN)
            return False
        d = math.sqrt(d)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True

@_jit
def leading_extent(H, qm, lo):
    """``n_e >= lo``: the rows of a symmetric ``H`` after the first ``n_e`` are inactive
    (``qm`` zero) and decoupled (zero off the diagonal), the identity-like block a batch's
    padding leaves (:func:`newton_one`); a factorization of the leading block and those
    diagonal entries is the full one, bit for bit, at a fraction of the cost."""
    n = H.shape[0]
    for i in range(n - 1, lo - 1, -1):
        if qm[i] > 0:
            return i + 1
        for k in range(n):
            if k != i and H[i, k] != 0.0:
                return i + 1
    return lo


@_jit
def factor_leading(H, qm, lo):
    """``(L, ok)``: the Cholesky factor ``L (n_e, n_e)`` of ``H``'s leading block
    (:func:`leading_extent`); ``ok`` False where ``H`` is not positive definite. With
    :func:`solve_leading`, what :func:`cholesky` and :func:`cho_solve` on the full ``H``
    give, bit for bit."""
    n = H.shape[0]
    ne = leading_extent(H, qm, lo)
    He = np.empty((ne, ne), dtype=H.dtype)
    for i in range(ne):
        for k in range(ne):
            He[i, k] = H[i, k]
    L = np.empty((ne, ne), dtype=H.dtype)
    ok = cholesky(He, L)
    for i in range(ne, n):
        ok = ok and H[i, i] > 0.0
    return L, ok


@_jit
def solve_leading(H, L, b, x):
    """``x (n,) = H^-1 b`` from :func:`factor_leading`'s ``L``: the leading block by
    substitution, the decoupled rows after it by their diagonal (as the full factor's
    substitutions divide twice by its square root)."""
    cho_solve(L, b, x)
    for i in range(L.shape[0], H.shape[0]):
        r = math.sqrt(H[i, i])
        x[i] = (b[i] / r) / r


@_jit
def cho_solve(L, b, x):
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]

@_jit
def lu_solve(A, b, x):
    """Gaussian elimination with partial pivoting (A and b overwritten); False on a zero
    pivot (LAPACK getrf's info != 0)."""
    n = A.shape[0]
    for j in range(n):
        p = j
        big = abs(A[j, j])
        for i in range(j + 1, n):
            if abs(A[i, j]) > big:
                big = abs(A[i, j])
                p = i
        if big == 0.0:
            return False
        if p != j:
            for k in range(n):
                A[j, k], A[p, k] = A[p, k], A[j, k]
            b[j], b[p] = b[p], b[j]
        for i in range(j + 1, n):
            f = A[i, j] / A[j, j]
            for k in range(j + 1, n):
                A[i, k] -= f * A[j, k]
            b[i] -= f * b[j]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= A[i, k] * x[k]
        x[i] = s / A[i, i]
    return True

@_jit
def scaled_residual(g, H, Lc, tiny, sc):
    nc = g.shape[0]
    res = 0.0
    finite = True
    for i in range(nc):
        d = H[i, i]
        if not math.isfinite(d) or not math.isfinite(g[i]):
            finite = False
        sc[i] = max(abs(d), tiny) ** -0.5
        r = abs(g[i]) * (sc[i] * sc[i])
        if r > res or r != r:
            res = r
    res *= Lc
    if not finite or not math.isfinite(res):
        return math.inf
    return res

@_jit
def jacobi_scaled(H, sc, A):
    """A <- S H S with S = diag(sc) (A may be H)."""
    n = H.shape[0]
    for i in range(n):
        for k in range(n):
            A[i, k] = sc[i] * H[i, k] * sc[k]


@_jit
def armijo(f, f0, t, slope, eps, tiny):
    resolution = 8 * eps * max(abs(f0), tiny)
    return ((f <= f0 + 1e-4 * t * slope) or (-slope * t <= resolution)
            or (f - f0 <= resolution)) and math.isfinite(f)

@_jit
def all_finite(v):
    for x in v:
        if not math.isfinite(x):
            return False
    return True

@_jit
def active_extent(qm, EIw, EIws, GJw, Hsec, N, Cn):
    """The length of the leading part of an element's compact coordinates that matters:
    ``N + s * Cn`` for the first ``s`` sections, where every later section has no active
    coordinate and no stiffness (zero weights and section block: a shorter element of a
    batch padded to its longest). Such sections add exactly zero to the energy, its gradient
    and its Hessian (:func:`evaluate`), and their coordinates form an identity block of the
    Newton matrix, so the solve on the leading part is bit for bit the padded one."""
    S = EIw.shape[0]
    nc = qm.shape[0]
    used = 0
    for s in range(S):
        keep = False
        for i in range(N + s * Cn, min(N + (s + 1) * Cn, nc)):
            if qm[i] > 0:
                keep = True
        if not keep:
            keep = EIws[s].any() or EIw[s].any() or GJw[s].any() or Hsec[s].any()
        if keep:
            used = s + 1
    return min(N + used * Cn, nc)


# Thin wrappers (the Newton's two, the step's, the partials' and the tip partials') are
# inlined into their callers by numba (``inline="always"``: at numba's IR, before typing, so no
# compiled function of their own): numba optimizes and emits the machine code of each compiled
# function together with everything it calls, so every wrapper level cost its whole tree again
# on first use (3.5-6 s a level around the Newton, numba's compile events).
_inline = cached_jit(nogil=True, inline="always")


@_inline
def newton_one(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld,
               Lc, consts, minimize, max_iter, H, g, out):
    """One element's damped Newton (newton._newton). q and H, g are overwritten with the
    solution and the Hessian and gradient at it; out = (U, residual, iterations,
    converged, verdict). Unloaded, on the coordinates of the sections that matter
    (:func:`active_extent`; the Cholesky factorizations' cost goes with the cube of their
    number): the trailing ones keep the identity block and zero gradient the padded solve
    gives them."""
    nc = q.shape[0]
    ne = nc
    if ld is None:        # (a tip load's work reads the full coordinates)
        N = psi0.shape[0]
        ne = active_extent(qm, EIw, EIws, GJw, Hsec, N, (2 + N) * phi.shape[1])
    if ne == nc:
        qe, qme, He, ge = q, qm, H, g
    else:
        qe, qme = q[:ne].copy(), qm[:ne].copy()
        He = np.empty((ne, ne), dtype=q.dtype)
        ge = np.empty(ne, dtype=q.dtype)
    # (one call site: numba compiles and optimizes the Newton once per caller)
    _newton_core(qe, qme, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                 ld, Lc, consts, minimize, max_iter, He, ge, out)
    if ne == nc:
        return
    for i in range(ne):
        q[i] = qe[i]
        g[i] = ge[i]
        for k in range(ne):
            H[i, k] = He[i, k]
    moved = out[2] > 0      # (an iteration sets the inactive coordinates to trial * 0)
    for i in range(ne, nc):
        if moved:
            q[i] = 0.0 * q[i]
        g[i] = guide[i] * q[i]
        for k in range(nc):
            H[i, k] = 0.0
            H[k, i] = 0.0
        H[i, i] = guide[i] + (1.0 - qm[i])


@_jit
def _newton_core(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld,
                 Lc, consts, minimize, max_iter, H, g, out):
    """:func:`newton_one` on the coordinates given (``q``, ``qm``, ``H``, ``g`` of one
    length; the layout's arrays may be longer)."""
    tol, thr, eps, tiny = consts[0], consts[1], consts[2], consts[3]
    nc = q.shape[0]
    dt = q.dtype
    sc = np.empty(nc, dtype=dt)
    L = np.zeros((nc, nc), dtype=dt)
    A = np.empty((nc, nc), dtype=dt)
    step = np.empty(nc, dtype=dt)
    rhs = np.empty(nc, dtype=dt)
    trial = np.empty(nc, dtype=dt)
    best = np.empty(nc, dtype=dt)
    dummy_g = np.empty(1, dtype=dt)
    dummy_H = np.empty((1, 1), dtype=dt)
    lam = 0.0
    tested = False
    escapes = 0
    iterations = 0
    verdict = -1
    U_out = math.nan
    residual = math.inf
    converged = False
    for _ in range(max_iter + 1):
        U = total(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld,
                  _E2, g, H)
        U_known = minimize
        for i in range(nc):
            H[i, i] += 1.0 - qm[i]
        res = scaled_residual(g, H, Lc, tiny, sc)
        conv = res < tol
        residual = res
        if minimize and escapes < 8 and conv and not tested:
            # the saddle test: S H S - thr I positive definite, without forming S H S
            for i in range(nc):
                for k in range(nc):
                    A[i, k] = H[i, k]
                A[i, i] -= thr * abs(H[i, i])
            pd = cholesky(A, L)
            left = False
            if not pd:
                jacobi_scaled(H, sc, A)
                ev, vec = np.linalg.eigh(A)
                if ev[0] < -1e-8:
                    slope = 0.0
                    vmax = 0.0
                    for i in range(nc):
                        step[i] = vec[i, 0] * sc[i] * qm[i]
                        slope += g[i] * step[i]
                        vmax = max(vmax, abs(step[i]))
                    sign = -1.0 if slope > 0 else 1.0
                    den = max(vmax * Lc, 1e-30)
                    f0 = total(q, qm, psi0, bvec, h, us, EIw, EIws, GJw,
                               Hsec, guide, gconst, phi, Qb, ld, _E0, dummy_g, dummy_H)
                    t = 1.0
                    for _k in range(40):
                        for i in range(nc):
                            trial[i] = q[i] + t * (sign * step[i] / den)
                        f = total(trial, qm, psi0, bvec, h, us, EIw, EIws, GJw,
                                  Hsec, guide, gconst, phi, Qb, ld, _E0, dummy_g, dummy_H)
                        if f < f0:
                            left = True
                            break
                        t = 0.5 * t
                    if left:
                        for i in range(nc):     # (a loop: no shape-checked copy to compile)
                            q[i] = trial[i]
                        escapes += 1
                        U_known = False
            if not left:
                verdict = 1 if pd else 0
                tested = True
            conv = conv and not left
        converged = conv
        if conv or not all_finite(q):
            if U_known:
                U_out = U
            break
        if not minimize:
            jacobi_scaled(H, sc, A)
            for i in range(nc):
                A[i, i] += 1e-14
                rhs[i] = -sc[i] * g[i]
            if lu_solve(A, rhs, step):
                cap = 0.0
                for i in range(nc):
                    step[i] *= sc[i]
                    cap = max(cap, abs(step[i]))
                cap = max(cap * Lc, 1.0)
                for i in range(nc):
                    trial[i] = q[i] + step[i] / cap
            else:
                trial[:] = math.nan
        else:
            # Levenberg–Marquardt-damped step (newton._damped_step)
            for i in range(nc):
                for k in range(nc):
                    A[i, k] = H[i, k]
                A[i, i] += lam / (sc[i] * sc[i])
                rhs[i] = -g[i]
            if not cholesky(A, L):
                jacobi_scaled(H, sc, A)
                ev0 = np.linalg.eigvalsh(A)[0]
                lam = max(-ev0, 0.0) * 1.1 + 1e-3 + lam
                for i in range(nc):
                    for k in range(nc):
                        A[i, k] = H[i, k]
                    A[i, i] += lam / (sc[i] * sc[i])
                if not cholesky(A, L):
                    L[:, :] = math.nan
            cho_solve(L, rhs, step)
            smax = 0.0
            slope = 0.0
            for i in range(nc):
                smax = max(smax, abs(step[i]))
                slope += g[i] * step[i]
            if smax != smax:
                smax = math.inf
            trust = lam == 0.0 and smax * Lc < 1e-3
            for i in range(nc):
                trial[i] = q[i] + step[i]
            accepted = True
            if not trust:
                f0 = U if U_known else total(q, qm, psi0, bvec, h, us, EIw, EIws, GJw,
                                             Hsec, guide, gconst, phi, Qb, ld, _E0, dummy_g,
                                             dummy_H)
                f = total(trial, qm, psi0, bvec, h, us, EIw, EIws, GJw,
                          Hsec, guide, gconst, phi, Qb, ld, _E0, dummy_g, dummy_H)
                accepted = armijo(f, f0, 1.0, slope, eps, tiny)
                if not accepted:
                    t = 0.5
                    done = False
                    for _k in range(29):
                        for i in range(nc):
                            best[i] = q[i] + t * step[i]
                        f = total(best, qm, psi0, bvec, h, us, EIw, EIws, GJw,
                                  Hsec, guide, gconst, phi, Qb, ld, _E0, dummy_g, dummy_H)
                        if armijo(f, f0, t, slope, eps, tiny):
                            done = True
                            break
                        t = 0.5 * t
                    if not done:
                        for i in range(nc):
                            best[i] = q[i] + t * step[i]
                    for i in range(nc):
                        trial[i] = best[i]
            if accepted:
                lam = lam * 0.1
                if lam < 1e-2:
                    lam = 0.0
            else:
                lam = min(lam * 4 + 1e-6, 1e6)
        if all_finite(trial):
            for i in range(nc):
                q[i] = trial[i] * qm[i]
        iterations += 1
    out[0] = U_out
    out[1] = residual
    out[2] = iterations
    out[3] = 1.0 if converged else 0.0
    out[4] = verdict

@_jit
def step_one(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld, tiny):
    """One element's undamped Newton step (kernel.newton_step), q overwritten where it
    succeeds; returns the success flag."""
    nc = q.shape[0]
    dt = q.dtype
    g = np.empty(nc, dtype=dt)
    H = np.empty((nc, nc), dtype=dt)
    L = np.zeros((nc, nc), dtype=dt)
    x = np.empty(nc, dtype=dt)
    rhs = np.empty(nc, dtype=dt)
    sc = np.empty(nc, dtype=dt)
    total(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, ld, _E2, g, H)
    for i in range(nc):
        H[i, i] += 1.0 - qm[i]
        rhs[i] = -g[i]
    good = cholesky(H, L)
    if good:
        cho_solve(L, rhs, x)
    else:
        # indefinite (an unstable equilibrium): LU on the Jacobi-scaled system
        scaled_residual(g, H, 1.0, tiny, sc)
        jacobi_scaled(H, sc, H)
        for i in range(nc):
            rhs[i] = sc[i] * rhs[i]
        good = lu_solve(H, rhs, x)
        for i in range(nc):
            x[i] *= sc[i]
    for i in range(nc):
        x[i] = q[i] + x[i] * qm[i]
    good = good and all_finite(x)
    if good:
        for i in range(nc):
            q[i] = x[i]
    return good


@_jit
def section_step_one(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                     new, hmax):
    """One element's new-section step (kernel.new_section_step): the coordinates ``new`` of
    one vanishing compact section solved for, the rest held, by one Newton step on their
    block; q overwritten where it applies; returns whether it did."""
    nc = q.shape[0]
    N = psi0.shape[0]
    S = h.shape[0]
    n = phi.shape[1]
    Cn = (2 + N) * n
    for i in range(N):
        if new[i]:
            return False       # a guide twist appearing: not a section's coordinates
    sec = -1
    for s in range(S):
        for i in range(Cn):
            if new[N + s * Cn + i]:
                if sec >= 0 and sec != s:
                    return False
                sec = s
                break
    if sec < 0 or not h[sec] <= hmax:
        return False
    dt = q.dtype
    g = np.empty(nc, dtype=dt)
    H = np.empty((nc, nc), dtype=dt)
    evaluate(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, _E3, g, H)
    off = N + sec * Cn
    A = np.zeros((Cn, Cn), dtype=dt)
    L = np.zeros((Cn, Cn), dtype=dt)
    rhs = np.empty(Cn, dtype=dt)
    x = np.empty(Cn, dtype=dt)
    for i in range(Cn):
        mi = 1.0 if new[off + i] else 0.0
        rhs[i] = -g[off + i] * mi
        for k in range(Cn):
            mk = 1.0 if new[off + k] else 0.0
            A[i, k] = H[off + i, off + k] * mi * mk
        A[i, i] += 1.0 - mi
    if not cholesky(A, L):
        return False
    cho_solve(L, rhs, x)
    for i in range(Cn):
        if new[off + i]:
            x[i] = q[off + i] + x[i]
        else:
            x[i] = q[off + i]
    if not all_finite(x):
        return False
    for i in range(Cn):
        q[off + i] = x[i]
    return True


@cached_jit(nogil=True)
def _section_serial(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                    new, hmax, ok):
    for b in range(q.shape[0]):
        ok[b] = section_step_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b],
                                 GJw[b], Hsec[b], guide[b], gconst[b], phi, Qb, new[b], hmax)


@cached_jit(nogil=True, parallel=True)
def _section_parallel(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                      new, hmax, ok):
    for b in prange(q.shape[0]):
        ok[b] = section_step_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b],
                                 GJw[b], Hsec[b], guide[b], gconst[b], phi, Qb, new[b], hmax)


@_inline
def newton_into(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, LD,
                Lc, consts, minimize, max_iter, H, g, U, res, it, conv, verdict):
    out = np.empty(5, dtype=q.dtype)
    # two call sites, not an optional value: numba prunes the one a None LD cannot take
    if LD is None:
        newton_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b], GJw[b],
                   Hsec[b], guide[b], gconst[b], phi, Qb, None, Lc[b], consts, minimize,
                   max_iter, H[b], g[b], out)
    else:
        newton_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b], GJw[b],
                   Hsec[b], guide[b], gconst[b], phi, Qb, element(LD, b), Lc[b], consts,
                   minimize, max_iter, H[b], g[b], out)
    U[b] = out[0]
    res[b] = out[1]
    it[b] = int(out[2])
    conv[b] = out[3] > 0.5
    verdict[b] = int(out[4])


@_inline
def step_at(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, LD, tiny):
    if LD is None:     # (see newton_into)
        return step_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b], GJw[b],
                        Hsec[b], guide[b], gconst[b], phi, Qb, None, tiny)
    return step_one(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b], GJw[b],
                    Hsec[b], guide[b], gconst[b], phi, Qb, element(LD, b), tiny)


# The batch loops: serial, and across numba's threads (prange) for larger batches.
@cached_jit(nogil=True)
def _newton_serial(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, LD,
                   Lc, consts, minimize, max_iter, H, g, U, res, it, conv, verdict):
    for b in range(q.shape[0]):
        newton_into(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                    LD, Lc, consts, minimize, max_iter, H, g, U, res, it, conv, verdict)


@cached_jit(nogil=True, parallel=True)
def _newton_parallel(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                     LD, Lc, consts, minimize, max_iter, H, g, U, res, it, conv, verdict):
    for b in prange(q.shape[0]):
        newton_into(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                    LD, Lc, consts, minimize, max_iter, H, g, U, res, it, conv, verdict)


@cached_jit(nogil=True)
def _step_serial(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                 LD, consts, ok):
    for b in range(q.shape[0]):
        ok[b] = step_at(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi,
                        Qb, LD, consts[3])


@cached_jit(nogil=True, parallel=True)
def _step_parallel(q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb,
                   LD, consts, ok):
    for b in prange(q.shape[0]):
        ok[b] = step_at(b, q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi,
                        Qb, LD, consts[3])


@_jit
def horner(coef, j, c, t):
    """``mechanics.poly`` of tube j's component c at t (coef (N, 3, P))."""
    P = coef.shape[2]
    out = coef[j, c, P - 1]
    for p in range(P - 2, -1, -1):
        out = out * t + coef[j, c, p]
    return out


@_jit
def horner_derivative(coef, j, c, t):
    """d/dt of :func:`horner`."""
    P = coef.shape[2]
    if P < 2:
        return 0.0 * t
    out = (P - 1) * coef[j, c, P - 1]
    for p in range(P - 2, 0, -1):
        out = out * t + p * coef[j, c, p]
    return out


@_jit
def horner_integral(coef, j, t):
    """``int_0^t`` of tube j's z-polynomial (mechanics._poly_int)."""
    P = coef.shape[2]
    out = coef[j, 2, P - 1] / P * t
    for p in range(P - 2, -1, -1):
        out = (out + coef[j, 2, p] / (p + 1)) * t
    return out


@_inline
def partials_one(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                 active, presc, W, xq, wq, phi, Qb, tau_D, tau_A):
    """One element's ``(dU/dD, dU/dalpha)`` at fixed q into tau_D, tau_A (N,)
    (forces.closed_form_partials term by term, on the layout's S sections, prescribed ones
    included; the node fields of mechanics.node_fields)."""
    # tau_A, zeroed, doubles as the zero rotation step: partials_core reads dA[j] before it
    # writes tau_A[j], and never after (no allocation on this hot path)
    tau_A[:] = 0.0
    partials_core(q, D, tau_A, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present,
                  curved, active, presc, W, xq, wq, phi, Qb, False, tau_D, tau_D, tau_A)


@_jit
def cut_slopes(D, L, Ls, S):
    """``(dh, dstart)`` ``(S, N)``: the slopes in ``D`` of the layout's section lengths and
    starts (build_layout's cut order; the layout's fields are piecewise linear in ``D``)."""
    N = D.shape[0]
    rt = D.dtype
    # d(cut)/dD of the cuts in build_layout's sorted order (a stable sort, as torch.sort's)
    cut = np.empty(2 * N, dtype=rt)
    dsrc = np.empty(2 * N, dtype=rt)
    for j in range(N):
        ell_raw = L[j] - D[j]
        t_raw = Ls[j] - D[j]
        dell = -1.0 if ell_raw >= 0 else 0.0
        ell = max(ell_raw, 0.0)
        tau0 = max(t_raw, 0.0)
        dtau0 = -1.0 if t_raw >= 0 else 0.0
        if tau0 < ell:
            dtau = dtau0
        elif tau0 > ell:
            dtau = dell
        else:
            dtau = 0.5 * (dtau0 + dell)
        cut[j] = ell
        cut[N + j] = min(tau0, ell)
        dsrc[j] = dell
        dsrc[N + j] = dtau
    perm = np.arange(2 * N)
    for i in range(1, 2 * N):
        k = perm[i]
        m = i - 1
        while m >= 0 and cut[perm[m]] > cut[k]:
            perm[m + 1] = perm[m]
            m -= 1
        perm[m + 1] = k
    dh = np.zeros((S, N), dtype=rt)
    dstart = np.zeros((S, N), dtype=rt)
    for k in range(S):
        l = perm[k] % N
        dh[k, l] += dsrc[perm[k]]
        if k + 1 < S:
            dstart[k + 1, l] = dsrc[perm[k]]
            dh[k + 1, l] -= dsrc[perm[k]]
    return dh, dstart


@_jit
def guide_curved(D, L, Ls, Dc, j):
    """``(tg, tg_r, dtg)``: the length of tube ``j``'s curved part held in the guide at the
    insertion ``Dc[j]`` (moved along its slope ``dtg`` from the layout's ``tg_r`` at ``D``)."""
    Dm = min(D[j], L[j])
    dmin = 1.0 if D[j] < L[j] else (0.0 if D[j] > L[j] else 0.5)
    dtg = dmin if Dm - Ls[j] >= 0 else 0.0
    tg_r = max(Dm - Ls[j], 0.0)
    return tg_r + dtg * (Dc[j] - D[j]), tg_r, dtg


@_jit
def section_moved(start, h, dstart, dh, k, Dc, D):
    """Section ``k``'s start and length at the insertions ``Dc`` (along the cut slopes)."""
    sk = start[k] + 0.0 * Dc[0]
    hk = h[k] + 0.0 * Dc[0]
    for l in range(D.shape[0]):
        sk += dstart[k, l] * (Dc[l] - D[l])
        hk += dh[k, l] * (Dc[l] - D[l])
    return sk, hk


@_jit
def partials_core(q, Dc, dA, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present,
                  curved, active, presc, W, xq, wq, phi, Qb, want_g, g, tau_D, tau_A):
    """:func:`partials_one` at the insertions ``Dc`` (N,) near the layout's ``D`` and the
    rotations moved by ``dA`` (N,), and with
    ``want_g`` the energy's gradient in the full coordinates ``q`` into ``g`` (nq,), zero on
    the inactive ones (the gradient of mechanics.potential without load).

    The layout's fields are piecewise linear in ``D`` with the slopes this function derives
    (``dh``, ``dstart``: the cut order; ``-1`` for the transitions ``tau``; ``dtg`` for the
    curved length in the guide), so at ``Dc = D + i eps e_l`` (complex, the layout's sections
    and masks unchanged) every output is its value plus ``i eps`` times its ``D_l``-derivative
    along those slopes, and at ``dA = i eps e_l`` its ``alpha_l``-derivative: the complex step
    that gives the stiffness's rows (:func:`stiffness_rows_one`). ``Dc = D`` and ``dA = 0``
    (real) is :func:`partials_one`."""
    N = D.shape[0]
    S = h.shape[0]
    Q, n = phi.shape
    Cn = (2 + N) * n
    rt = D.dtype
    vt = Dc.dtype
    dh, dstart = cut_slopes(D, L, Ls, S)
    # the layout at Dc: starts, lengths and transitions moved along their slopes, each
    # computed where it is used (tau_j - (Dc_j - D_j), section_moved) to allocate nothing
    if want_g:
        for m in range(g.shape[0]):
            g[m] = 0.0
    # guide: twist and bending energy held straight; g0 the own-tube angle shift per D
    g0 = np.empty(N, dtype=vt)
    psi_start = np.empty(N, dtype=vt)
    for j in range(N):
        w = q[j] * qmask[j]
        tg, tg_r, dtg = guide_curved(D, L, Ls, Dc, j)
        ugx = horner(coef, j, _C0, tg)
        ugy = horner(coef, j, _C1, tg)
        tau_D[j] = 0.5 * GJ[j] * w * w + 0.5 * EI[j] * (ugx * ugx + ugy * ugy) * dtg
        g0[j] = w + horner(coef, j, _C2, tg) * dtg
        psi_start[j] = (psi0[j] + dA[j] + horner_integral(coef, j, tg)
                        - horner_integral(coef, j, tg_r) + Dc[j] * w)
        tau_A[j] = 0.0
        if want_g:
            g[j] = GJ[j] * Dc[j] * w
    before = np.zeros((N, N), dtype=rt)       # (j, l): sum over k' < k of dh_k'l c_k'j0
    # g only: Gp of every section, and in the last row the sum of Gp over the later sections
    Gps = np.zeros((S + 1, N), dtype=vt)
    ntau = np.empty(N, dtype=vt)              # -tau_j at Dc
    for j in range(N):
        ntau[j] = (Dc[j] - D[j]) - tau[j]
    a = np.empty((2, n), dtype=rt)
    c = np.empty((N, n), dtype=rt)
    Rx = np.empty(N, dtype=vt)
    Ry = np.empty(N, dtype=vt)
    us = np.empty((N, 3), dtype=vt)
    dp = np.empty(N, dtype=vt)
    cs = np.empty(N, dtype=vt)
    sn = np.empty(N, dtype=vt)
    locq = np.empty(N, dtype=rt)
    Gp = np.empty(N, dtype=vt)
    Z0 = np.empty(N, dtype=vt)
    pm = np.empty(N, dtype=rt)
    for k in range(S):
        off = N + k * Cn
        sk, hk = section_moved(start, h, dstart, dh, k, Dc, D)
        dWk = 0.5 * active[k] * (hk - h[k])
        for p in range(n):
            a[0, p] = q[off + p] * qmask[off + p]
            a[1, p] = q[off + n + p] * qmask[off + n + p]
        for j in range(N):
            for p in range(n):
                c[j, p] = q[off + (2 + j) * n + p] * qmask[off + (2 + j) * n + p]
            pm[j] = curved[k, j] * presc[k]
            Z0[j] = horner_integral(coef, j, sk + ntau[j])
            Gp[j] = 0.0
        s_loc = 0.0 * hk
        for i in range(Q):
            s_node = sk + 0.5 * (xq[i] + 1.0) * hk
            frac = 0.5 * (xq[i] + 1.0)
            Wki = W[k, i] + wq[i] * dWk
            ux = 0.0 * hk
            uy = 0.0 * hk
            for p in range(n):
                ux += a[0, p] * phi[i, p]
                uy += a[1, p] * phi[i, p]
            for j in range(N):
                t = s_node + ntau[j]
                for cc in range(3):
                    us[j, cc] = horner(coef, j, cc, t) * curved[k, j]
                lq = 0.0
                d1 = 0.0
                for p in range(n):
                    lq += c[j, p] * Qb[i, p]
                    d1 += c[j, p] * phi[i, p]
                locq[j] = lq
                ps = (psi_start[j] + 0.5 * hk * lq
                      + (horner_integral(coef, j, t) - Z0[j]) * pm[j])
                cs[j], sn[j] = cos_sin(ps)
                Rx[j] = cs[j] * us[j, 0] - sn[j] * us[j, 1]
                Ry[j] = sn[j] * us[j, 0] + cs[j] * us[j, 1]
                dp[j] = d1 + pm[j] * us[j, 2]
            for j in range(N):        # a prescribed section's strain: its precurvature
                held = presc[k] * present[k, j]
                ux += held * Rx[j]
                uy += held * Ry[j]
            dens = 0.0 * hk
            gsum = 0.0 * hk
            Gx = 0.0 * hk
            Gy = 0.0 * hk
            for j in range(N):
                EIp = EI[j] * present[k, j]
                GJp = GJ[j] * present[k, j]
                ex = ux - Rx[j]
                ey = uy - Ry[j]
                tors = dp[j] - us[j, 2]
                dens += 0.5 * EIp * (ex * ex + ey * ey) + 0.5 * GJp * tors * tors
                gpsi = Wki * EIp * (Ry[j] * ux - Rx[j] * uy)
                Gp[j] += gpsi
                s_loc += gpsi * 0.5 * locq[j]
                t = s_node + ntau[j]
                dx = horner_derivative(coef, j, _C0, t) * curved[k, j]
                dy = horner_derivative(coef, j, _C1, t) * curved[k, j]
                dz = horner_derivative(coef, j, _C2, t) * curved[k, j]
                px = cs[j] * dx - sn[j] * dy
                py = sn[j] * dx + cs[j] * dy
                gstar = -Wki * (EIp * (ex * px + ey * py) + GJp * tors * dz)
                gsum += gstar
                tau_D[j] += gstar
                if want_g:
                    Gx += EIp * ex
                    Gy += EIp * ey
                    base = off + (2 + j) * n
                    for p in range(n):
                        g[base + p] += (gpsi * 0.5 * hk * Qb[i, p]
                                        + Wki * GJp * tors * phi[i, p]) * qmask[base + p]
            for l in range(N):
                tau_D[l] += (dens * 0.5 * wq[i] * dh[k, l] * active[k]
                             + gsum * (dstart[k, l] + frac * dh[k, l]))
            if want_g:
                for p in range(n):
                    g[off + p] += Wki * Gx * phi[i, p] * qmask[off + p]
                    g[off + n + p] += Wki * Gy * phi[i, p] * qmask[off + n + p]
        for l in range(N):
            acc = s_loc * dh[k, l] + g0[l] * Gp[l]
            for j in range(N):
                acc += Gp[j] * before[j, l]
            tau_D[l] += acc
            tau_A[l] += Gp[l]
        for j in range(N):
            Gps[k, j] = Gp[j]
            for l in range(N):
                before[j, l] += dh[k, l] * c[j, 0]
            psi_start[j] += hk * c[j, 0] + (horner_integral(coef, j, sk + ntau[j] + hk)
                                            - Z0[j]) * pm[j]
    if want_g:
        # the angles of section k carry D_j w_j and h_k' c_k'j0 of every earlier section k'
        for k in range(S - 1, -1, -1):
            off = N + k * Cn
            hk = section_moved(start, h, dstart, dh, k, Dc, D)[1]
            for j in range(N):
                g[off + (2 + j) * n] += hk * Gps[S, j] * qmask[off + (2 + j) * n]
                Gps[S, j] += Gps[k, j]
        for j in range(N):
            g[j] = (g[j] + Dc[j] * Gps[S, j]) * qmask[j]


@_jit
def stiffness_rows_one(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                       active, presc, W, xq, wq, phi, Qb, Gq, X):
    """One element's rows of the unloaded energy's Hessian at fixed q along the ``m =
    Gq.shape[0]`` directions ``D_1..D_N`` then (``m = 2N``) ``alpha_1..alpha_N``: ``Gq[d]
    (nq,)`` the gradient's derivative (zero on inactive coordinates; ``U_qx`` column ``d``)
    and ``X[d] (2N,)`` that of ``(tau_D, tau_alpha)`` (``U_xx`` column ``d``), by a complex
    step of :func:`partials_core` per direction (exact to rounding: no difference is taken)."""
    N = D.shape[0]
    nq = q.shape[0]
    eps = 1e-20
    Dc = np.empty(N, dtype=np.complex128)
    dA = np.empty(N, dtype=np.complex128)
    g = np.empty(nq, dtype=np.complex128)
    tD = np.empty(N, dtype=np.complex128)
    tA = np.empty(N, dtype=np.complex128)
    for d in range(Gq.shape[0]):
        for j in range(N):
            Dc[j] = D[j]
            dA[j] = 0.0
        if d < N:
            Dc[d] = D[d] + 1j * eps
        else:
            dA[d - N] = 1j * eps
        partials_core(q, Dc, dA, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present,
                      curved, active, presc, W, xq, wq, phi, Qb, True, g, tD, tA)
        for m in range(nq):
            Gq[d, m] = g[m].imag / eps
        for j in range(N):
            X[d, j] = tD[j].imag / eps
            X[d, N + j] = tA[j].imag / eps


@cached_jit(nogil=True)
def _partials_serial(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                     active, presc, W, xq, wq, phi, Qb, tau_D, tau_A):
    for b in range(q.shape[0]):
        partials_one(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau[b], psi0[b],
                     start[b], h[b], present[b], curved[b], active[b], presc[b], W[b], xq, wq,
                     phi, Qb, tau_D[b], tau_A[b])


@cached_jit(nogil=True, parallel=True)
def _partials_parallel(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                       active, presc, W, xq, wq, phi, Qb, tau_D, tau_A):
    for b in prange(q.shape[0]):
        partials_one(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau[b], psi0[b],
                     start[b], h[b], present[b], curved[b], active[b], presc[b], W[b], xq, wq,
                     phi, Qb, tau_D[b], tau_A[b])


@cached_jit(nogil=True)
def _stiffness_serial(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                      active, presc, W, xq, wq, phi, Qb, Gq, X):
    for b in range(q.shape[0]):
        stiffness_rows_one(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau[b],
                           psi0[b], start[b], h[b], present[b], curved[b], active[b], presc[b],
                           W[b], xq, wq, phi, Qb, Gq[b], X[b])


@cached_jit(nogil=True, parallel=True)
def _stiffness_parallel(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                        active, presc, W, xq, wq, phi, Qb, Gq, X):
    for b in prange(q.shape[0]):
        stiffness_rows_one(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau[b],
                           psi0[b], start[b], h[b], present[b], curved[b], active[b], presc[b],
                           W[b], xq, wq, phi, Qb, Gq[b], X[b])


@_jit
def se3_coefficients(t2, small):
    """lie._coefficients: sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 of t^2, real or
    complex (the complex step of :func:`tip_partials_one`: the branches are taken on the real
    part, and both are analytic, so the complex step through them is exact)."""
    if t2.real < small:
        a = 1 - t2 / 6 + t2 * t2 / 120
        half = 0.5 - t2 / 48 + t2 * t2 / 3840
    else:
        t = np.sqrt(t2)
        a = np.sin(t) / t
        half = np.sin(0.5 * t) / t
    b = 2 * half * half
    if t2.real < 0.1:
        c = (1.0 / 6 - t2 / 120 + t2 * t2 / 5040 - t2 ** 3 / 362880 + t2 ** 4 / 39916800)
    else:
        t = np.sqrt(t2)
        c = (t - np.sin(t)) / (t * t * t)
    return a, b, c


@_jit
def magnus_twist(u, i, hs, kq, om):
    """Magnus step ``i``'s 4th-order twist into ``om (6,)`` from the bending ``u (G, 2)`` at its
    two Gauss nodes (``hs`` the step length, ``kq = sqrt(3)/12 hs^2``)."""
    u1x, u1y = u[2 * i, 0], u[2 * i, 1]
    u2x, u2y = u[2 * i + 1, 0], u[2 * i + 1, 1]
    om[0] = 0.5 * hs * (u1x + u2x)
    om[1] = 0.5 * hs * (u1y + u2y)
    om[2] = kq * (u1x * u2y - u1y * u2x)
    om[3] = kq * (u1y - u2y)
    om[4] = -kq * (u1x - u2x)
    om[5] = hs


@_jit
def tip_frame(g, angle, tip, R):
    """The tip position ``tip (3,)`` and the tip tube's frame ``R (3, 3)``: the backbone frame
    ``g (4, 4)`` turned by the tube's ``angle`` about its ``z``."""
    ca, sa = cos_sin(angle)
    for i in range(3):
        tip[i] = g[i, 3]
        R[i, 0] = g[i, 0] * ca + g[i, 1] * sa
        R[i, 1] = -g[i, 0] * sa + g[i, 1] * ca
        R[i, 2] = g[i, 2]


@_jit
def pose_one(q, qm, psi0_base, D, tip_tube, sec, h, presc_inc, us_held, presc_local, phi, Qb,
             S, small, tip, R, psi_tip):
    """One element's tip pose (mechanics._tip_frame and tip_pose): the 4th-order Magnus steps
    of every nonempty section, multiplied along the backbone."""
    N = psi0_base.shape[0]
    Sp = sec.shape[0]
    G, n = phi.shape
    m = G // 2
    C = 2 + N
    dt = q.dtype
    psi0 = np.empty(N, dtype=dt)
    for j in range(N):
        psi0[j] = psi0_base[j] + D[j] * (q[j] * qm[j])
    g = np.eye(4, dtype=dt)
    E = np.empty((4, 4), dtype=dt)
    tmp = np.empty((4, 4), dtype=dt)
    om = np.empty(6, dtype=dt)
    start = psi0.copy()
    u = np.empty((G, 2), dtype=dt)
    k3 = 3.0 ** 0.5 / 12.0
    for kk in range(Sp):
        off = N + sec[kk] * C * n
        hk = h[kk]
        for gg in range(G):
            ux = 0.0
            uy = 0.0
            for p in range(n):
                ux += q[off + p] * qm[off + p] * phi[gg, p]
                uy += q[off + n + p] * qm[off + n + p] * phi[gg, p]
            for j in range(N):
                loc = 0.0
                for p in range(n):
                    loc += q[off + (2 + j) * n + p] * qm[off + (2 + j) * n + p] * Qb[gg, p]
                psi = start[j] + 0.5 * hk * loc + presc_local[kk, gg, j]
                cs = math.cos(psi)
                sn = math.sin(psi)
                hx = us_held[kk, gg, j, 0]
                hy = us_held[kk, gg, j, 1]
                ux += cs * hx - sn * hy
                uy += sn * hx + cs * hy
            u[gg, 0] = ux
            u[gg, 1] = uy
        hs = hk / m
        kq = k3 * hs * hs
        for i in range(m):
            magnus_twist(u, i, hs, kq, om)
            exp_right_any(g, om, small, E, tmp)
        for j in range(N):
            c0 = q[off + (2 + j) * n] * qm[off + (2 + j) * n]
            start[j] += hk * c0 + presc_inc[kk, j]
    angle = 0.0
    for j in range(N):
        psi_tip[j] = start[j]
        angle += start[j] * tip_tube[j]
    tip_frame(g, angle, tip, R)


@cached_jit(nogil=True)
def _pose_serial(q, qm, psi0, D, tip_tube, sec, h, presc_inc, us_held, presc_local, phi, Qb,
                 S, small, tip, R, psi_tip):
    L, B = q.shape[0], q.shape[1]
    for r in range(L * B):
        i, b = r // B, r % B
        pose_one(q[i, b], qm[b], psi0[b], D[b], tip_tube[b], sec[b], h[b], presc_inc[b],
                 us_held[b], presc_local[b], phi, Qb, S, small, tip[i, b], R[i, b],
                 psi_tip[i, b])


@cached_jit(nogil=True, parallel=True)
def _pose_parallel(q, qm, psi0, D, tip_tube, sec, h, presc_inc, us_held, presc_local, phi, Qb,
                   S, small, tip, R, psi_tip):
    L, B = q.shape[0], q.shape[1]
    for r in prange(L * B):
        i, b = r // B, r % B
        pose_one(q[i, b], qm[b], psi0[b], D[b], tip_tube[b], sec[b], h[b], presc_inc[b],
                 us_held[b], presc_local[b], phi, Qb, S, small, tip[i, b], R[i, b],
                 psi_tip[i, b])


@_jit
def exp_right_any(g, om, small, E, tmp):
    """``g <- g exp(om)`` (4 x 4) for a twist ``om = (omega, v)`` (lie.exp_se3, entry by entry),
    real or complex (:func:`se3_coefficients`); ``E``, ``tmp``: 4 x 4 scratch of ``g``'s
    dtype. The product skips the exponential's last row ``(0, 0, 0, 1)``."""
    wx, wy, wz, vx, vy, vz = om[0], om[1], om[2], om[3], om[4], om[5]
    t2 = wx * wx + wy * wy + wz * wz
    a, b, c = se3_coefficients(t2, small)
    d = 1 - b * t2
    e = 1 - c * t2
    cwv = c * (wx * vx + wy * vy + wz * vz)
    E[0, 0] = d + b * wx * wx
    E[0, 1] = b * wx * wy - a * wz
    E[0, 2] = b * wx * wz + a * wy
    E[1, 0] = b * wx * wy + a * wz
    E[1, 1] = d + b * wy * wy
    E[1, 2] = b * wy * wz - a * wx
    E[2, 0] = b * wx * wz - a * wy
    E[2, 1] = b * wy * wz + a * wx
    E[2, 2] = d + b * wz * wz
    E[0, 3] = e * vx + b * (wy * vz - wz * vy) + cwv * wx
    E[1, 3] = e * vy + b * (wz * vx - wx * vz) + cwv * wy
    E[2, 3] = e * vz + b * (wx * vy - wy * vx) + cwv * wz
    for i in range(4):
        for j in range(4):
            acc = g[i, 0] * E[0, j]
            for k in range(1, 3):
                acc += g[i, k] * E[k, j]
            if j == 3:
                acc += g[i, 3]
            tmp[i, j] = acc
    # (element by element: an array assignment compiles numba's shape check and its error
    # message, about 1.5 s of first use)
    for i in range(4):
        for j in range(4):
            g[i, j] = tmp[i, j]


@_jit
def tip_twist_core(q, Dc, dA, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                   presc, tip_tube, xm, phi, Qb, small, tip, R):
    """The tip pose (mechanics.tip_pose on every section, as a function of the layout) into
    ``tip (3,)`` and ``R (3, 3)`` at the coordinates ``q (nq,)``, the insertions ``Dc (N,)``
    near the layout's ``D`` and the rotations moved by ``dA (N,)``: real, or complex for the
    complex step of :func:`tip_partials_one` (the layout's fields move along their slopes in
    ``D``, :func:`cut_slopes`, with its sections and masks unchanged, as in
    :func:`partials_core`). ``xm, phi, Qb``: the Magnus points and the basis and its integrals
    there."""
    N = D.shape[0]
    S = h.shape[0]
    G, n = phi.shape
    m = G // 2
    Cn = (2 + N) * n
    vt = tip.dtype
    dh, dstart = cut_slopes(D, L, Ls, S)
    psi = np.empty(N, dtype=vt)          # the tube angles at the current section's start
    ntau = np.empty(N, dtype=vt)         # -tau_j at Dc
    Z0 = np.empty(N, dtype=vt)
    for j in range(N):
        tg, tg_r, _ = guide_curved(D, L, Ls, Dc, j)
        psi[j] = (psi0[j] + dA[j] + horner_integral(coef, j, tg)
                  - horner_integral(coef, j, tg_r) + Dc[j] * (q[j] * qmask[j]))
        ntau[j] = (Dc[j] - D[j]) - tau[j]
    g = np.eye(4, dtype=vt)
    E = np.empty((4, 4), dtype=vt)
    tmp = np.empty((4, 4), dtype=vt)
    om = np.empty(6, dtype=vt)
    u = np.empty((G, 2), dtype=vt)
    k3 = 3.0 ** 0.5 / 12.0
    for k in range(S):
        moves = False
        for l in range(N):
            if dh[k, l] != 0.0:
                moves = True
        if h[k] == 0.0 and not moves:      # an identity step that adds no angle
            continue
        off = N + k * Cn
        sk, hk = section_moved(start, h, dstart, dh, k, Dc, D)
        for j in range(N):
            Z0[j] = horner_integral(coef, j, sk + ntau[j])
        for gg in range(G):
            s_node = sk + 0.5 * (xm[gg] + 1.0) * hk
            ux = 0.0 * hk
            uy = 0.0 * hk
            for p in range(n):
                ux += q[off + p] * qmask[off + p] * phi[gg, p]
                uy += q[off + n + p] * qmask[off + n + p] * phi[gg, p]
            for j in range(N):       # a prescribed section's strain: its precurvature
                held = presc[k] * present[k, j]
                if held == 0.0:
                    continue
                t = s_node + ntau[j]
                lq = 0.0 * hk
                for p in range(n):
                    f = off + (2 + j) * n + p
                    lq += q[f] * qmask[f] * Qb[gg, p]
                ps = (psi[j] + 0.5 * hk * lq
                      + (horner_integral(coef, j, t) - Z0[j]) * curved[k, j] * presc[k])
                usx = horner(coef, j, _C0, t) * curved[k, j]
                usy = horner(coef, j, _C1, t) * curved[k, j]
                cs, sn = cos_sin(ps)
                ux += held * (cs * usx - sn * usy)
                uy += held * (sn * usx + cs * usy)
            u[gg, 0] = ux
            u[gg, 1] = uy
        hs = hk / m
        kq = k3 * hs * hs
        for i in range(m):
            magnus_twist(u, i, hs, kq, om)
            exp_right_any(g, om, small, E, tmp)
        for j in range(N):
            f = off + (2 + j) * n
            psi[j] += (hk * q[f] * qmask[f] + (horner_integral(coef, j, sk + ntau[j] + hk)
                                               - Z0[j]) * curved[k, j] * presc[k])
    angle = 0.0 * psi[0]
    for j in range(N):
        angle += psi[j] * tip_tube[j]
    tip_frame(g, angle, tip, R)


@_inline
def tip_partials_one(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                     tip_tube, xm, phi, Qb, Pq, Px):
    """One element's tip partials at fixed ``q``: ``Pq (6, nq)`` per coordinate (zero on the
    inactive ones; through the Magnus chain, :func:`tip_partials_q_one`) and ``Px (6, 2N)`` per
    insertion then rotation (:func:`tip_actuator_partials`); rows the tip position [m] and the
    spatial rotation ``vee(skew(dR R^T))`` [rad]."""
    N = D.shape[0]
    zero = np.zeros(N)
    tip_partials_q_one(q, qmask, D, coef, tau, psi0, start, h, present, curved, presc, tip_tube,
                       xm, phi, Qb, Pq)
    tip_actuator_partials(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                          presc, tip_tube, xm, phi, Qb, zero, zero, Px)


@_inline
def tip_actuator_partials(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                          presc, tip_tube, xm, phi, Qb, Ds, As, Px):
    """``Px (6, 2N)``: the tip twist's partials per insertion then rotation at the insertions
    ``D + Ds`` and rotations moved by ``As`` (real shifts along the layout's slopes, its
    sections and masks unchanged; zero: the layout's own), by a complex step of
    :func:`tip_twist_core` per actuator (exact to rounding: no difference is taken)."""
    tip_directional(q, None, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                    presc, tip_tube, xm, phi, Qb, Ds, As, Px)


@_jit
def tip_directional(q, dq, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                    presc, tip_tube, xm, phi, Qb, Ds, As, Px):
    """:func:`tip_actuator_partials` (``dq`` None) or, with ``dq (nq, 2N)``, the tip twist's
    derivative along each actuator ``d`` with the coordinates moving by ``dq[:, d]`` per unit
    actuation: ``Px[:, d] + P_q dq[:, d]`` in one complex step of the pose (the total
    derivative ``d(tip)/dx`` where ``dq = dq*/dx``, without forming ``P_q``)."""
    N = D.shape[0]
    eps = 1e-20
    Dc = np.empty(N, dtype=np.complex128)
    dA = np.empty(N, dtype=np.complex128)
    tip = np.empty(3, dtype=np.complex128)
    R = np.empty((3, 3), dtype=np.complex128)
    W = np.empty((3, 3))
    qz = np.empty(q.shape[0], dtype=np.complex128)
    for d in range(2 * N):          # the insertions, then the rotations
        for j in range(N):
            Dc[j] = D[j] + Ds[j]
            dA[j] = As[j]
        if d < N:
            Dc[d] += 1j * eps
        else:
            dA[d - N] += 1j * eps
        # two call sites, not an optional value: numba prunes the one a None dq cannot take
        if dq is None:
            tip_twist_core(q, Dc, dA, qmask, D, L, Ls, coef, tau, psi0, start, h, present,
                           curved, presc, tip_tube, xm, phi, Qb, 1e-6, tip, R)
        else:
            for i in range(q.shape[0]):
                qz[i] = q[i] + 1j * eps * dq[i, d]
            tip_twist_core(qz, Dc, dA, qmask, D, L, Ls, coef, tau, psi0, start, h, present,
                           curved, presc, tip_tube, xm, phi, Qb, 1e-6, tip, R)
        col = Px[:, d]
        for i in range(3):
            col[i] = tip[i].imag / eps
        # spatial rotation: vee of the skew part of dR R^T
        for i in range(3):
            for k in range(3):
                acc = 0.0
                for l in range(3):
                    acc += R[i, l].imag * R[k, l].real
                W[i, k] = acc / eps
        col[3] = 0.5 * (W[2, 1] - W[1, 2])
        col[4] = 0.5 * (W[0, 2] - W[2, 0])
        col[5] = 0.5 * (W[1, 0] - W[0, 1])


@_jit
def moved_layout(D, L, Ls, coef, tau, psi0, start, h, Ds, As, D2, tau2, psi02, start2, h2):
    """The layout's fields that :func:`tip_partials_q_one` reads, at the insertions ``D + Ds``
    and the rotations moved by ``As`` (real shifts along the slopes of :func:`cut_slopes` and
    :func:`guide_curved`, the sections and masks unchanged, as :func:`tip_twist_core` moves
    them), into ``D2, tau2, psi02 (N,)`` and ``start2, h2 (S,)``."""
    N = D.shape[0]
    S = h.shape[0]
    dh, dstart = cut_slopes(D, L, Ls, S)
    Dc = np.empty(N)
    for j in range(N):
        Dc[j] = D[j] + Ds[j]
    for j in range(N):
        tg, tg_r, _ = guide_curved(D, L, Ls, Dc, j)
        psi02[j] = (psi0[j] + As[j] + horner_integral(coef, j, tg)
                    - horner_integral(coef, j, tg_r))
        tau2[j] = tau[j] - Ds[j]
        D2[j] = Dc[j]
    for k in range(S):
        start2[k], h2[k] = section_moved(start, h, dstart, dh, k, Dc, D)


#: The fourth-order central difference of :func:`load_rows_one`: offsets and weights (/ 12).
_STENCIL = np.array([-2.0, -1.0, 1.0, 2.0])
_WEIGHTS = np.array([1.0, -8.0, 8.0, -1.0])


@_jit
def load_rows_one(q, F, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                  tip_tube, xm, phi, Qb, dD, dA, Gq, X):
    """One element's rows of a dead tip force's potential ``-F . p`` at fixed ``q`` along
    ``m = Gq.shape[0]`` directions ``D_1..D_N`` then (``m = 2N``) ``alpha_1..alpha_N``:
    ``Gq[d] (nq,) = -d(F . P_q)/dx_d`` and ``X[d] (2N,) = -d(F . (P_D, P_alpha))/dx_d`` (the
    rows of ``U_xq`` and ``U_xx``; zero on inactive coordinates). Each is a fourth-order central
    difference, steps ``dD`` [m] and ``dA`` [rad], of the exact partials (the Magnus chain and
    the complex step) at layouts moved along the slopes: the difference runs on the analytic
    continuation of the layout's structure at ``D``, so it is the one-sided derivative that
    the structure stands for even where a step crosses a cut (a kink's side)."""
    N = D.shape[0]
    nq = q.shape[0]
    S = h.shape[0]
    Ds = np.zeros(N)
    As = np.zeros(N)
    D2 = np.empty(N)
    tau2 = np.empty(N)
    psi02 = np.empty(N)
    start2 = np.empty(S)
    h2 = np.empty(S)
    gq = np.empty(nq)
    Px = np.empty((6, 2 * N))
    F0, F1, F2 = F[0], F[1], F[2]
    if F0 == 0.0 and F1 == 0.0 and F2 == 0.0:     # an unloaded element of a loaded batch
        Gq[:, :] = 0.0
        X[:, :] = 0.0
        return
    for d in range(Gq.shape[0]):
        Gq[d, :] = 0.0
        X[d, :] = 0.0
        step = dD if d < N else dA
        for s in range(4):
            Ds[:] = 0.0
            As[:] = 0.0
            if d < N:
                Ds[d] = _STENCIL[s] * step
            else:
                As[d - N] = _STENCIL[s] * step
            moved_layout(D, L, Ls, coef, tau, psi0, start, h, Ds, As, D2, tau2, psi02, start2,
                         h2)
            tip_force_partials_q_one(q, qmask, D2, coef, tau2, psi02, start2, h2, present,
                                     curved, presc, xm, phi, Qb, F, gq)
            tip_actuator_partials(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present,
                                  curved, presc, tip_tube, xm, phi, Qb, Ds, As, Px)
            c = -_WEIGHTS[s] / (12.0 * step)
            for col in range(nq):
                Gq[d, col] += c * gq[col]
            for col in range(2 * N):
                X[d, col] += c * (F0 * Px[0, col] + F1 * Px[1, col] + F2 * Px[2, col])


@cached_jit(nogil=True)
def _load_rows_serial(q, F, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                      tip_tube, xm, phi, Qb, dD, dA, Gq, X):
    for b in range(q.shape[0]):
        load_rows_one(q[b], F[b], qmask[b], D[b], L[b], Ls[b], coef[b], tau[b], psi0[b],
                      start[b], h[b], present[b], curved[b], presc[b], tip_tube[b], xm, phi, Qb,
                      dD, dA, Gq[b], X[b])


@cached_jit(nogil=True, parallel=True)
def _load_rows_parallel(q, F, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                        presc, tip_tube, xm, phi, Qb, dD, dA, Gq, X):
    for b in prange(q.shape[0]):
        load_rows_one(q[b], F[b], qmask[b], D[b], L[b], Ls[b], coef[b], tau[b], psi0[b],
                      start[b], h[b], present[b], curved[b], presc[b], tip_tube[b], xm, phi, Qb,
                      dD, dA, Gq[b], X[b])


@cached_jit(nogil=True)
def _tip_serial(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                tip_tube, xm, phi, Qb, Pq, Px):
    for b in range(q.shape[0]):
        tip_partials_one(q[b], qmask[b], D[b], L[b], Ls[b], coef[b], tau[b], psi0[b],
                         start[b], h[b], present[b], curved[b], presc[b], tip_tube[b], xm,
                         phi, Qb, Pq[b], Px[b])


@cached_jit(nogil=True, parallel=True)
def _tip_parallel(q, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                  tip_tube, xm, phi, Qb, Pq, Px):
    for b in prange(q.shape[0]):
        tip_partials_one(q[b], qmask[b], D[b], L[b], Ls[b], coef[b], tau[b], psi0[b],
                         start[b], h[b], present[b], curved[b], presc[b], tip_tube[b], xm,
                         phi, Qb, Pq[b], Px[b])


@_jit
def hat3(x, o, M):
    """``M <- [x]x`` of the 3-vector ``x[o:o+3]``."""
    M[0, 0] = 0.0
    M[0, 1] = -x[o + 2]
    M[0, 2] = x[o + 1]
    M[1, 0] = x[o + 2]
    M[1, 1] = 0.0
    M[1, 2] = -x[o]
    M[2, 0] = -x[o + 1]
    M[2, 1] = x[o]
    M[2, 2] = 0.0


@_jit
def mat3(A, B, out):
    """out = A @ B for 3 x 3 arrays (out must not alias A or B)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@_jit
def se3_right_jacobian(om, small, Jw, Q):
    """The right Jacobian of the SE(3) exponential at ``om = (omega, v)``: ``d exp(om + t e_a)
    / dt = exp(om) [J_r e_a]^``, with ``J_r = [[Jw, 0], [Q, Jw]]`` (rows and columns
    ``(omega, v)``), into ``Jw (3, 3)`` and ``Q (3, 3)``. ``J_r(om) = J_l(-om)``, the left
    Jacobian of Barfoot and Furgale ("Associating uncertainty with three-dimensional poses",
    T-RO 2014, eqs. 100-102): ``J_l = I + b W + c W^2`` and
    ``Q_l = v^/2 + c (W v^ + v^ W + W v^ W) - d (W^2 v^ + v^ W^2 - 3 W v^ W)
    - e (W v^ W^2 + W^2 v^ W)`` with ``W = [omega]x``, ``b, c`` of
    :func:`se3_coefficients`, ``d = (1 - t^2/2 - cos t) / t^4``,
    ``e = (d - 3 (t - sin t - t^3/6) / t^5) / 2`` (series below ``t^2 = 0.1``)."""
    m = np.empty(6)
    for i in range(6):
        m[i] = -om[i]
    t2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    _, b, c = se3_coefficients(t2, small)
    if t2 < 0.1:
        d = (-1.0 / 24 + t2 / 720 - t2 * t2 / 40320 + t2 ** 3 / 3628800
             - t2 ** 4 / 479001600)
        f = (-1.0 / 120 + t2 / 5040 - t2 * t2 / 362880 + t2 ** 3 / 39916800
             - t2 ** 4 / 6227020800)
    else:
        d = (b - 0.5) / t2
        f = (c - 1.0 / 6) / t2
    e = 0.5 * (d - 3.0 * f)
    W = np.empty((3, 3))
    V = np.empty((3, 3))
    WV = np.empty((3, 3))
    VW = np.empty((3, 3))
    WVW = np.empty((3, 3))
    WW = np.empty((3, 3))
    WWV = np.empty((3, 3))
    VWW = np.empty((3, 3))
    X = np.empty((3, 3))
    Y = np.empty((3, 3))
    hat3(m, 0, W)
    hat3(m, 3, V)
    mat3(W, V, WV)
    mat3(V, W, VW)
    mat3(WV, W, WVW)
    mat3(W, W, WW)
    mat3(W, WV, WWV)
    mat3(VW, W, VWW)
    mat3(WVW, W, X)          # W v^ W^2
    mat3(W, WVW, Y)          # W^2 v^ W
    for i in range(3):
        for j in range(3):
            Jw[i, j] = (1.0 if i == j else 0.0) + b * W[i, j] + c * WW[i, j]
            Q[i, j] = (0.5 * V[i, j] + c * (WV[i, j] + VW[i, j] + WVW[i, j])
                       - d * (WWV[i, j] + VWW[i, j] - 3.0 * WVW[i, j])
                       - e * (X[i, j] + Y[i, j]))


@_jit
def tip_partials_q_one(q, qmask, D, coef, tau, psi0, start, h, present, curved, presc,
                       tip_tube, xm, phi, Qb, Pq):
    """One element's ``Pq (6, nq)``, the tip twist per coordinate at fixed actuation (zero on
    the inactive coordinates), through the Magnus chain ``P = E_1 ... E_K``: each step's twist
    ``Om_k`` and its derivative in ``q`` (bilinear in the bending at the step's two nodes,
    which is linear in the section's coefficients plus ``Rz(psi_j) u*_j`` of a held tube),
    ``dp/dOm_ka = R_{k-1} (dE_k/dOm_ka r_k)`` (``r_k`` the tip in frame ``k``) and the spatial
    rotation ``R_{k-1} vee(dR_k R_k^T)``, plus the tip tube's angle about the last frame's
    ``z``. The layout's fields are real here (no insertion or rotation moves): the same
    nodes and sections as :func:`tip_twist_core`."""
    N = D.shape[0]
    nq = q.shape[0]
    Zs, dOm, dpsi, P = _tip_chain_q(q, qmask, D, coef, tau, psi0, start, h, present, curved,
                                    presc, xm, phi, Qb)
    Pq[:, :] = 0.0
    for k in range(Zs.shape[0]):
        for a in range(6):
            for c in range(nq):
                d = dOm[k, a, c]
                if d != 0.0:
                    for i in range(6):
                        Pq[i, c] += Zs[k, a, i] * d
    # the tip tube's angle about the last frame's z
    for j in range(N):
        if tip_tube[j] != 0.0:
            for c in range(nq):
                d = tip_tube[j] * dpsi[j, c]
                if d != 0.0:
                    for i in range(3):
                        Pq[3 + i, c] += P[i, 2] * d


@_jit
def tip_force_partials_q_one(q, qmask, D, coef, tau, psi0, start, h, present, curved, presc,
                             xm, phi, Qb, F, g):
    """``g (nq,) = F . P_q[:3]``: :func:`tip_partials_q_one`'s position rows contracted with a
    force ``F (3,)`` [N] (the gradient of the dead load's work ``F . p`` at fixed actuation,
    what :func:`load_rows_one` differences), each step's sensitivity contracted before it meets
    the ``nq`` coordinate derivatives (a sixth of the products; the rotation rows, the tip
    tube's angle included, are not formed)."""
    nq = q.shape[0]
    Zs, dOm, _, _ = _tip_chain_q(q, qmask, D, coef, tau, psi0, start, h, present, curved, presc,
                                 xm, phi, Qb)
    g[:] = 0.0
    for k in range(Zs.shape[0]):
        for a in range(6):
            w = F[0] * Zs[k, a, 0] + F[1] * Zs[k, a, 1] + F[2] * Zs[k, a, 2]
            for c in range(nq):
                g[c] += w * dOm[k, a, c]


@_jit
def _tip_chain_q(q, qmask, D, coef, tau, psi0, start, h, present, curved, presc, xm, phi, Qb):
    """The Magnus chain of :func:`tip_partials_q_one`: ``(Zs, dOm, dpsi, P)``, each step's
    twist sensitivities ``Zs (K, 6, 6)`` (:func:`_step_sensitivity`), the step twists'
    derivatives in the coordinates ``dOm (K, 6, nq)``, the angles' derivatives ``dpsi (N,
    nq)`` at the chain's end and the tip frame ``P (4, 4)``."""
    N = D.shape[0]
    S = h.shape[0]
    G, n = phi.shape
    m = G // 2
    Cn = (2 + N) * n
    nq = q.shape[0]
    Sp = 0
    for k in range(S):
        if h[k] != 0.0:
            Sp += 1
    K = Sp * m
    psi = np.empty(N)
    dpsi = np.zeros((N, nq))               # the angles' derivatives at the section's start
    for j in range(N):
        psi[j] = psi0[j] + D[j] * q[j] * qmask[j]
        dpsi[j, j] = D[j] * qmask[j]
    Om = np.empty((K, 6))
    dOm = np.zeros((K, 6, nq))
    u = np.empty((G, 2))
    du = np.zeros((G, 2, nq))
    dps = np.empty(nq)
    Z0 = np.empty(N)
    k3 = 3.0 ** 0.5 / 12.0
    ks = 0
    for k in range(S):
        hk = h[k]
        if hk == 0.0:           # an identity step that adds no angle
            continue
        off = N + k * Cn
        sk = start[k]
        for j in range(N):
            Z0[j] = horner_integral(coef, j, sk - tau[j])
        du[:, :, :] = 0.0
        for gg in range(G):
            s_node = sk + 0.5 * (xm[gg] + 1.0) * hk
            ux = 0.0
            uy = 0.0
            for p in range(n):
                ux += q[off + p] * qmask[off + p] * phi[gg, p]
                uy += q[off + n + p] * qmask[off + n + p] * phi[gg, p]
                du[gg, 0, off + p] += qmask[off + p] * phi[gg, p]
                du[gg, 1, off + n + p] += qmask[off + n + p] * phi[gg, p]
            for j in range(N):
                held = presc[k] * present[k, j]
                if held == 0.0:
                    continue
                t = s_node - tau[j]
                for c in range(nq):
                    dps[c] = dpsi[j, c]
                lq = 0.0
                for p in range(n):
                    f = off + (2 + j) * n + p
                    lq += q[f] * qmask[f] * Qb[gg, p]
                    dps[f] += 0.5 * hk * Qb[gg, p] * qmask[f]
                ps = (psi[j] + 0.5 * hk * lq
                      + (horner_integral(coef, j, t) - Z0[j]) * curved[k, j] * presc[k])
                usx = horner(coef, j, _C0, t) * curved[k, j]
                usy = horner(coef, j, _C1, t) * curved[k, j]
                cs = math.cos(ps)
                sn = math.sin(ps)
                rx = held * (cs * usx - sn * usy)
                ry = held * (sn * usx + cs * usy)
                ux += rx
                uy += ry
                for c in range(nq):
                    du[gg, 0, c] -= ry * dps[c]
                    du[gg, 1, c] += rx * dps[c]
            u[gg, 0] = ux
            u[gg, 1] = uy
        hs = hk / m
        kq = k3 * hs * hs
        for i in range(m):
            magnus_twist(u, i, hs, kq, Om[ks])
            u1x, u1y = u[2 * i, 0], u[2 * i, 1]
            u2x, u2y = u[2 * i + 1, 0], u[2 * i + 1, 1]
            for c in range(nq):
                d1x, d1y = du[2 * i, 0, c], du[2 * i, 1, c]
                d2x, d2y = du[2 * i + 1, 0, c], du[2 * i + 1, 1, c]
                dOm[ks, 0, c] = 0.5 * hs * (d1x + d2x)
                dOm[ks, 1, c] = 0.5 * hs * (d1y + d2y)
                dOm[ks, 2, c] = kq * (d1x * u2y + u1x * d2y - d1y * u2x - u1y * d2x)
                dOm[ks, 3, c] = kq * (d1y - d2y)
                dOm[ks, 4, c] = -kq * (d1x - d2x)
            ks += 1
        for j in range(N):
            f = off + (2 + j) * n
            psi[j] += (hk * q[f] * qmask[f] + (horner_integral(coef, j, sk - tau[j] + hk)
                                               - Z0[j]) * curved[k, j] * presc[k])
            dpsi[j, f] += hk * qmask[f]
    # the chain: frames before each step and the exponentials
    Pprev = np.empty((K, 4, 4))
    E = np.empty((K, 4, 4))
    Es = np.empty((4, 4))
    tmp = np.empty((4, 4))
    P = np.eye(4)
    for k in range(K):
        Pprev[k] = P
        E[k] = np.eye(4)
        exp_right_any(E[k], Om[k], 1e-6, Es, tmp)
        mat4(Pprev[k], E[k], P)
    Zs = np.empty((K, 6, 6))
    Pk = np.empty((4, 4))
    r = np.empty(3)
    Jw = np.empty((3, 3))
    Qv = np.empty((3, 3))
    for k in range(K):
        mat4(Pprev[k], E[k], Pk)
        _step_sensitivity(Pk, P, Om[k], Jw, Qv, r, Zs[k])
    return Zs, dOm, dpsi, P


@_jit
def _step_sensitivity(Pk, P, Omk, Jw, Qv, r, zs):
    """Step ``k``'s twist sensitivities ``zs (6, 6)``: row ``a`` the tip's displacement
    (``[:3]``) and rotation (``[3:]``) per unit of the step's twist component ``a``, ``Pk`` the
    frame after the step, ``P`` the tip frame. An exponential's derivative in its twist is
    exp(Om) [J_r e_a]^ (se3_right_jacobian): with ``(w_a, v_a) = J_r e_a`` the tip moves by
    ``R (w_a x r + v_a)`` and turns by ``R w_a`` (``R`` the frame after the step, ``r`` the tip
    in it)."""
    for i in range(3):
        acc = 0.0
        for l in range(3):
            acc += Pk[l, i] * (P[l, 3] - Pk[l, 3])
        r[i] = acc
    se3_right_jacobian(Omk, 1e-6, Jw, Qv)
    for a in range(6):
        if a < 3:
            w0, w1, w2 = Jw[0, a], Jw[1, a], Jw[2, a]
            v0, v1, v2 = Qv[0, a], Qv[1, a], Qv[2, a]
        else:
            w0, w1, w2 = 0.0, 0.0, 0.0
            v0, v1, v2 = Jw[0, a - 3], Jw[1, a - 3], Jw[2, a - 3]
        y0 = w1 * r[2] - w2 * r[1] + v0
        y1 = w2 * r[0] - w0 * r[2] + v1
        y2 = w0 * r[1] - w1 * r[0] + v2
        for i in range(3):
            zs[a, i] = Pk[i, 0] * y0 + Pk[i, 1] * y1 + Pk[i, 2] * y2
            zs[a, 3 + i] = Pk[i, 0] * w0 + Pk[i, 1] * w1 + Pk[i, 2] * w2
