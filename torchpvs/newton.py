"""Stage 5a — damped Newton: one fixed discretization, a batch of elements, ``q -> q*``.

The eager kernel's iteration (:data:`torchpvs.kernel.EAGER`'s ``solve``); the driver
(:mod:`torchpvs.solver`) reaches it only through :mod:`torchpvs.kernel`. It is lean where a
batch spends its time:

* the gradient and exact Hessian come from :func:`torchpvs.mechanics.elastic_grad_hess` (GEMMs
  and strided block writes, already zero on inactive coordinates: no dense mask pass);
* one LAPACK Cholesky per iteration on the Jacobi-scaled, Levenberg–Marquardt-damped Hessian;
  an eigenvalue shift only for the elements whose factorization fails;
* the saddle test runs once per element, when it converges: a Cholesky of the undamped scaled
  Hessian, and ``eigh`` only where that fails (a saddle, left along negative curvature);
* the line search re-evaluates only the elements that rejected the full step;
* converged elements leave the working batch (it is compacted when it shrinks by a quarter).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch

from .batch_linalg import active_index, chunked, compact, compact_scaled, expand, take
from .clock import work_clock
from .mechanics import (
    Maps,
    compact_q,
    elastic_energy_maps,
    elastic_grad_hess,
    expand_q,
    skew_vee,
    tip_pose,
)

if TYPE_CHECKING:
    from .sections import Layout, Tables

__all__ = ["NewtonResult", "Problem", "derivatives", "merit", "newton", "scaled_residual",
           "stability_threshold", "tolerance"]


class NewtonResult(NamedTuple):
    """Kernel output for a batch of ``B`` elements with ``nq`` (padded) coordinates."""

    q: torch.Tensor            # (B, nq) solution (inactive coordinates 0)
    # (B, nc, nc) Hessian at q on the compact coordinates prob.maps.cidx (identity on their
    # inactive rows; mechanics.expand_hessian gives the padded (B, nq, nq) one)
    H: torch.Tensor
    g: torch.Tensor            # (B, nq) gradient at q
    converged: torch.Tensor    # (B,) bool
    residual: torch.Tensor     # (B,) scaled residual (SolverOptions.tol)
    iterations: torch.Tensor   # (B,) long
    # (B,) int8 stability verdict at q where the kernel made one (the saddle test's
    # factorization): 1 the Jacobi-scaled Hessian exceeds stability_threshold on the active
    # coordinates, 0 it does not, -1 no verdict (the caller tests)
    verdict: torch.Tensor | None = None
    # (B,) [J] the elastic energy at q where the kernel evaluated it there (bit for bit
    # mechanics.elastic_energy_maps; NaN where it did not: a tip load, method "root", an
    # element moved off a saddle); None when the kernel reports none
    energy: torch.Tensor | None = None


# Maps fields without a batch dim (shared by every row, never indexed)
_SHARED = frozenset(("phi", "Qb", "values_T", "Q_QQ", "phi_PQ"))
# Maps fields the merit reads without a tip load (mechanics.elastic_energy_maps), and with one
_MERIT = frozenset(("bvec", "qmask", "psi0", "h", "ustar", "EIw", "GJw", "guide", "guide_const"))
_MERIT_LOADED = _MERIT | {"cidx", "pose"}
# per field of Maps: 0 shared (kept as is), 1 per row (indexed), 2 the pose constants (each
# of their fields indexed)
_KIND = tuple(0 if k in _SHARED else 2 if k == "pose" else 1 for k in Maps._fields)


class Problem(NamedTuple):
    """What a kernel needs: the layout, quadrature tables and precomputed maps of one batch.

    Attributes:
        lay: the :class:`~torchpvs.sections.Layout` (``None`` in an unloaded subset: unused
            there, see :meth:`subset`).
        tab: the discretization's :class:`~torchpvs.sections.Tables`.
        maps: the :class:`~torchpvs.mechanics.Maps` of the layout.
        with_load: the potential includes the tip load's work (some element is loaded).
        has_moment: a tip moment is modelled (its virtual work enters the potential).
    """

    lay: Layout | None
    tab: Tables
    maps: Maps
    with_load: bool
    has_moment: bool

    def subset(self, idx: torch.Tensor | slice, merit_only: bool = False) -> Problem:
        """The problem restricted to batch rows ``idx`` (indices, or a slice for views without a
        copy). Only what is read is copied: the layout only with a tip load (the elastic terms
        live in the maps; without load the subset's ``lay`` is None), and for ``merit_only`` only
        the energy's maps fields (and the pose's, with a load; the others are ``None``). The
        shared fields (no batch dim) are kept as they are."""
        lay = type(self.lay)(*(v[idx] for v in self.lay)) if self.with_load else None
        wanted = None if not merit_only else _MERIT_LOADED if self.with_load else _MERIT
        maps = Maps._make(
            v if kind == 0 or v is None
            else None if wanted is not None and name not in wanted
            else v[idx] if kind == 1
            else type(v)._make(t[idx] for t in v)
            for name, kind, v in zip(Maps._fields, _KIND, self.maps, strict=True))
        return self._replace(lay=lay, maps=maps)


def derivatives(q: torch.Tensor, prob: Problem, energy: bool = False):
    """Gradient ``(B, nq)`` and Hessian ``(B, nq, nq)`` of the total potential: analytic for the
    elastic energy, autograd (``vmap(jacfwd(grad))``) only for the tip-load term, which needs the
    Magnus chain. ``energy=True``: also the potential ``(B,)`` as :func:`merit` gives it, where
    it comes free with the derivatives (no tip load), else ``None``."""
    if energy:
        g, H, U = elastic_grad_hess(q, prob.maps, energy=True)
        if prob.with_load:
            U = None
        return (*_with_load_terms(q, prob, g, H), U)
    g, H = elastic_grad_hess(q, prob.maps)
    return _with_load_terms(q, prob, g, H)


def _with_load_terms(q, prob: Problem, g, H):
    """``(g, H)`` plus the tip load's terms where the problem has a load. A batch whose loads
    are all zero (coordinates kept for a load: ``SolverOptions.load_coordinates``) skips them:
    the terms are then exactly zero, and their Hessian is most of a solve."""
    if prob.with_load and bool((prob.lay.force != 0).any() | (prob.lay.moment != 0).any()):
        Hl, gl = _load_hessian(q, prob)
        g = g + gl
        H = H + 0.5 * (Hl + Hl.transpose(-1, -2))
    return g, H


def _load_hessian(q: torch.Tensor, prob: Problem):
    """``(H (B, nq_c, nq_c), g (B, nq_c))`` of minus the tip load's work on the compact
    coordinates, through the Magnus pose chain: the batch repeated ``nq_c`` times, one reverse
    pass for the gradient (with its graph) and ONE more for every Hessian row at once (row ``i``
    of element ``b`` from replica ``b nq_c + i``; elements are independent). The flops of
    ``vmap(jacfwd(grad))``, without vmap's per-op overhead: about 2x faster for the Fig. 3
    robot at B = 8 (1.4x with a tip moment), identical to rounding."""
    B, nc = q.shape
    lay = prob.lay
    nq = lay.qmask.shape[-1]

    def rep(t):   # every layout field and pose constant has the leading batch dim
        return t.repeat_interleave(nc, 0)

    # Autograd also inside the solver's inference mode: the copies made here are ordinary
    # tensors (inference tensors cannot be saved for backward).
    with torch.inference_mode(False), torch.enable_grad():
        lay_r = type(lay)(*(rep(v) for v in lay))
        const = type(prob.maps.pose)._make(rep(v) for v in prob.maps.pose)
        cidx = rep(prob.maps.cidx)
        tab = type(prob.tab)._make(v.clone() for v in prob.tab)
        qr = q.detach().repeat_interleave(nc, 0).requires_grad_(True)
        p, R, _ = tip_pose(expand_q(qr, cidx, nq), lay_r, tab, const)
        work = (lay_r.force * p).sum(-1)
        if prob.has_moment:
            # the moment's virtual work about the current frame (its reference is not
            # differentiated)
            work = work + (lay_r.moment * skew_vee(R @ R.detach().transpose(-1, -2))).sum(-1)
        (gr,) = torch.autograd.grad(-work.sum(), qr, create_graph=True)
        pick = torch.eye(nc, dtype=q.dtype, device=q.device).repeat(B, 1)      # (B nc, nc)
        (Hr,) = torch.autograd.grad((gr * pick).sum(), qr)
    return Hr.reshape(B, nc, nc), gr.detach()[::nc]


@torch.no_grad()
def merit(q: torch.Tensor, prob: Problem, q_ref: torch.Tensor) -> torch.Tensor:
    """Total potential ``(B,)`` [J] at compact coordinates ``q (B, nq_c)`` (the moment's
    virtual work taken about ``q_ref``)."""
    U = elastic_energy_maps(q, prob.maps)
    if prob.with_load:
        lay, tab, const = prob.lay, prob.tab, prob.maps.pose
        nq, cidx = lay.qmask.shape[-1], prob.maps.cidx
        p, R, _ = tip_pose(expand_q(q, cidx, nq), lay, tab, const)
        U = U - (lay.force * p).sum(-1)
        if prob.has_moment:
            _, R0, _ = tip_pose(expand_q(q_ref, cidx, nq), lay, tab, const)
            U = U - (lay.moment * skew_vee(R @ R0.transpose(-1, -2))).sum(-1)
    return U


def stability_threshold(dtype: torch.dtype) -> float:
    """The smallest eigenvalue of the Jacobi-scaled stiffness that counts as stable: set by the
    precision alone (``0.01 sqrt(eps)``, 1.5e-10 in float64)."""
    return 0.01 * torch.finfo(dtype).eps ** 0.5


def tolerance(tol: float, dtype: torch.dtype) -> float:
    # float32 cannot resolve residuals below ~1e-6 of the strain scale.
    return max(tol, 1e-5) if dtype == torch.float32 else tol


def scaled_residual(g: torch.Tensor, H: torch.Tensor, L_char: torch.Tensor):
    """``max_i |g_i| / H_ii * L`` and the Jacobi scale ``|H_ii|^-1/2``."""
    diag = H.diagonal(dim1=-2, dim2=-1)
    scale = diag.abs().clamp(min=torch.finfo(H.dtype).tiny) ** -0.5
    res = (g.abs() * scale**2).amax(-1) * L_char
    # An overflowed gradient or stiffness (inf / inf, or a zero scale) is not a small residual.
    finite = torch.isfinite(res) & torch.isfinite(g).all(-1) & torch.isfinite(diag).all(-1)
    res = torch.where(finite, res, torch.full_like(res, float("inf")))
    return res, scale


def newton(q: torch.Tensor, prob: Problem, L_char: torch.Tensor, *, method: str, tol: float,
           max_iter: int, deadline: float | None = None) -> NewtonResult:
    """Batched Newton on the total potential from ``q (B, nq)``; see the module docstring.

    ``method="minimize"``: damped Newton with a line search and saddle escapes (returns a local
    minimum whenever the iteration can reach one); ``"root"``: plain Newton on the gradient
    (capped steps), converging to the nearest stationary point, stable or not.

    A batch whose Hessians exceed ``CHUNK_BYTES`` is solved in cache-sized chunks (:func:`chunked`).
    ``deadline``: a :func:`~torchpvs.clock.work_clock` time after which no further step is
    taken (the elements not converged by then are returned as such, with their residual).
    """
    nq, cidx = q.shape[-1], prob.maps.cidx
    qc, H, g, *rest = chunked(_newton, compact_q(q, cidx), prob, L_char, method=method,
                              tol=tol, max_iter=max_iter, deadline=deadline)
    # The Hessian stays compact: expanding it (and releasing the padded copy from inference
    # mode) was ~10 % of a B = 1024 call, for the few callers that need it (implicit backward,
    # actuator stiffness: implicit.full_hessian).
    return NewtonResult(expand_q(qc, cidx, nq), H, expand_q(g, cidx, nq), *rest)


def _newton(q: torch.Tensor, prob: Problem, L_char: torch.Tensor, *, method: str, tol: float,
            max_iter: int, deadline: float | None = None) -> NewtonResult:
    B, nq = q.shape
    dtype, device = q.dtype, q.device
    tol = tolerance(tol, dtype)
    eye = torch.eye(nq, dtype=dtype, device=device)
    q_out = q.clone()
    # Hessian and gradient rows are stored only when elements leave the working batch (and at
    # the end): an (nq x nq) copy per element per iteration is a full pass over memory.
    H_out = g_out = None
    U_out = torch.full((B,), float("nan"), dtype=dtype, device=device)
    residual = torch.full((B,), float("inf"), dtype=dtype, device=device)
    iterations = torch.zeros(B, dtype=torch.long, device=device)
    converged = torch.zeros(B, dtype=torch.bool, device=device)
    verdict = torch.full((B,), -1, dtype=torch.int8, device=device)

    idx = torch.arange(B, device=device)              # working set -> rows of the outputs
    sub, Lc = prob, L_char
    lam = torch.zeros(B, dtype=dtype, device=device)
    tested = torch.zeros(B, dtype=torch.bool, device=device)   # passed the saddle test
    escapes = 0
    act = active_index(prob.maps.qmask)
    for _ in range(max_iter + 1):
        qmask = sub.maps.qmask
        if method == "minimize":   # the energy at q comes free: the line search's reference
            g, H, U = derivatives(q, sub, energy=True)
        else:
            (g, H), U = derivatives(q, sub), None
        H.diagonal(dim1=-2, dim2=-1).add_(1.0 - qmask)
        res, scale = scaled_residual(g, H, Lc)
        conv = res < tol
        residual[idx] = res
        if method == "minimize" and escapes < 8:
            new = conv & ~tested
            if bool(new.any()):
                q, left, pd = _saddle_test(q, H, g, scale, new, sub, Lc, act)
                verdict[idx] = torch.where(new & ~left, pd, verdict[idx])
                tested = tested | (new & ~left)
                conv = conv & ~left
                if bool(left.any()):
                    escapes += 1
                    q_out[idx] = q
                    U = None          # moved off the saddle: the energy there is not U
        converged[idx] = conv
        todo = ~conv & torch.isfinite(q).all(-1)
        n_todo = int(todo.sum())
        if n_todo == 0 or (deadline is not None and work_clock() > deadline):
            # (past the deadline: no further step; the state, residual and flags are this
            # iteration's, as at max_iter)
            if U is not None:
                U_out[idx] = U
            break
        if n_todo <= 0.75 * idx.shape[0]:
            # Converged (or non-finite) elements leave the working batch.
            if H_out is None:
                H_out = torch.empty(B, nq, nq, dtype=dtype, device=device)
                g_out = torch.empty(B, nq, dtype=dtype, device=device)
            out = (~todo).nonzero().flatten()
            H_out[idx[out]], g_out[idx[out]] = H[out], g[out]
            if U is not None:
                U_out[idx[out]] = U[out]
            keep = todo.nonzero().flatten()
            idx, q, g, H, scale, lam, tested, Lc = (t[keep] for t in
                                                    (idx, q, g, H, scale, lam, tested, Lc))
            U = None if U is None else U[keep]
            sub = sub.subset(keep)
            todo = torch.ones_like(lam, dtype=torch.bool)
            qmask = sub.maps.qmask
            act = active_index(qmask)
        if method == "minimize":
            Hc = compact(H, act)
            step, lam = _damped_step(Hc, take(g, act), take(scale, act), lam,
                                     eye[:Hc.shape[-1], :Hc.shape[-1]])
            step = expand(step, act, nq)
            # Pure Newton phase: an undamped step (positive definite Hessian) that changes no
            # strain by more than 1e-3 rad over the robot's length is accepted without an energy
            # evaluation -- the quadratic model's relative error is O(1e-3) there, far inside
            # Armijo's margin (the decrease is -g.s/2 against the 1e-4 g.s asked for).
            trust = (lam == 0) & (step.abs().amax(-1) * Lc < 1e-3)
            q_new, accepted = _line_search(q, step, g, sub, todo, trust, U)
            # Accepted steps shrink the damping 10x (4x took about 10 % more cold iterations,
            # with the same branches: docs/performance.md); damping below 1e-2 (of the
            # unit-diagonal scaled Hessian) is dropped: the pure Newton phase converges
            # quadratically and skips the energy check.
            relaxed = lam * 0.1
            relaxed = torch.where(relaxed < 1e-2, torch.zeros_like(relaxed), relaxed)
            lam = torch.where(accepted, relaxed, torch.clamp(lam * 4 + 1e-6, max=1e6))
        else:
            Hs, sc = compact_scaled(H, scale, act)
            gs = sc * take(g, act)
            nA = Hs.shape[-1]
            sol, _ = torch.linalg.solve_ex(Hs + 1e-14 * eye[:nA, :nA],
                                           -gs[..., None])
            step = expand(sc * sol[..., 0], act, nq)
            # Cap the step at 1 rad of strain x length to stay in Newton's basin.
            cap = (step.abs().amax(-1) * Lc).clamp(min=1.0)
            q_new = q + step / cap[:, None]
        q_new = torch.where(torch.isfinite(q_new).all(-1, keepdim=True), q_new, q)
        q = torch.where(todo[:, None], q_new * qmask, q)
        iterations[idx] += todo.long()
        q_out[idx] = q
    if H_out is None:          # the working batch never shrank: it is the whole batch
        H_out, g_out = H, g
    else:
        H_out[idx], g_out[idx] = H, g
    return NewtonResult(q_out, H_out, g_out, converged, residual, iterations, verdict, U_out)


def _saddle_test(q, H, g, scale, new, prob: Problem, L_char, act):
    """Elements of ``new`` (just converged) whose undamped scaled Hessian is not positive
    definite and has a negative eigenvalue are moved off the saddle (:func:`_escape`). Returns
    the coordinates, the mask of elements that left, and the stability verdict of the elements
    of ``new`` (int8: 1 where the scaled Hessian exceeds :func:`stability_threshold`, else 0; -1
    outside ``new``), which the solver's outputs reuse. ``act``: :func:`active_index` rows."""
    sel = new.nonzero().flatten()
    a = None if act is None else act[sel]
    # One factorization for both questions: S H S - tau I positive definite (stable), and if
    # not, is there a negative eigenvalue (a saddle)? Without forming S H S:
    # S (H - tau diag|H_ii|) S is congruent to it (diag|H_ii| = S^-2 on the active rows; the
    # inactive ones are identity rows and stay positive).
    whole = a is None and len(sel) == H.shape[0]
    Hc = H if whole else compact(H[sel], a)   # no copy of the whole batch's Hessians:
    diag = Hc.diagonal(dim1=-2, dim2=-1)      # shift the diagonal in place, restore it exactly
    d0 = diag.clone() if whole else None
    diag.sub_(stability_threshold(H.dtype) * diag.abs())
    _, info = torch.linalg.cholesky_ex(Hc)
    if whole:
        diag.copy_(d0)
    bad = info != 0
    left = torch.zeros_like(new)
    pd = torch.full(new.shape, -1, dtype=torch.int8, device=new.device)
    pd[sel] = (~bad).to(torch.int8)
    if not bool(bad.any()):
        return q, left, pd
    sel = sel[bad]
    a = None if a is None else a[bad]
    Hs, sc = compact_scaled(H[sel], scale[sel], a)
    ev, vec = torch.linalg.eigh(Hs)
    neg = ev[:, 0] < -1e-8
    if not bool(neg.any()):
        return q, left, pd
    sel, v = sel[neg], expand(vec[neg][:, :, 0] * sc[neg], None if a is None else a[neg],
                              q.shape[-1])
    sub = prob.subset(sel, merit_only=True)
    v = v * sub.maps.qmask
    sign = torch.where((g[sel] * v).sum(-1) > 0, -1.0, 1.0).to(v.dtype)
    v = sign[:, None] * v / (v.abs().amax(-1, keepdim=True) * L_char[sel, None]).clamp(min=1e-30)
    q0 = q[sel]
    f0 = merit(q0, sub, q0)
    t = torch.ones_like(f0)
    new_q = q0.clone()
    ok_all = torch.zeros_like(f0, dtype=torch.bool)
    for _ in range(40):
        trial = q0 + t[:, None] * v
        ok = (merit(trial, sub, q0) < f0) & ~ok_all
        new_q = torch.where(ok[:, None], trial, new_q)
        ok_all = ok_all | ok
        if bool(ok_all.all()):
            break
        t = torch.where(ok_all, t, 0.5 * t)
    q = q.clone()
    q[sel] = new_q
    left[sel] = ok_all
    return q, left, pd


def _damped_step(H, g, sc, lam, eye):
    """Levenberg–Marquardt-damped Newton step ``(H + lam diag|H_ii|) s = -g`` (``sc =
    |H_ii|^-1/2``, ``H (B, n, n)``, ``g``, ``sc (B, n)``): the step of the Jacobi-scaled system
    ``(S H S + lam I) y = -S g``, ``s = S y``, without forming ``S H S`` (two passes and a
    fresh ``(B, n, n)`` tensor per iteration; a Cholesky factorization is invariant under the
    diagonal scaling). Indefinite Hessians are shifted to be positive definite, from the scaled
    spectrum, so the step is a descent direction. ``H``'s diagonal is restored exactly."""
    A = H.diagonal(dim1=-2, dim2=-1)
    damped = bool((lam > 0).any())
    if damped:
        A0 = A.clone()
        A.add_(lam[:, None] / (sc * sc))
    L, info = torch.linalg.cholesky_ex(H)
    if damped:
        A.copy_(A0)
    bad = info != 0
    if bool(bad.any()):
        Hb, sb = H[bad], sc[bad]
        ev = torch.linalg.eigvalsh(sb[:, :, None] * Hb * sb[:, None, :])[:, 0]
        lam = lam.clone()
        lam[bad] = torch.clamp(-ev, min=0.0) * 1.1 + 1e-3 + lam[bad]
        Lb, _ = torch.linalg.cholesky_ex(Hb + torch.diag_embed(lam[bad, None] / (sb * sb)))
        L = L.clone()
        L[bad] = Lb
    step = torch.cholesky_solve(-g[..., None], L)[..., 0]
    return step, lam


def _armijo(f, f0, t, slope):
    # Below the energy's rounding level the Armijo test is noise: accept the step then
    # (the residual test, not the energy, decides convergence).
    resolution = 8 * torch.finfo(f0.dtype).eps * f0.abs().clamp(min=torch.finfo(f0.dtype).tiny)
    return ((f <= f0 + 1e-4 * t * slope) | (-slope * t <= resolution)
            | (f - f0 <= resolution)) & torch.isfinite(f)


def _line_search(q, step, g, prob: Problem, todo, trust, f_q=None, max_halvings: int = 30):
    """Backtracking (Armijo) on the potential, per element, for the elements of ``todo`` not in
    ``trust`` (those take the full step unchecked); after the full step only the elements that
    rejected it are re-evaluated. ``f_q``: the potential at ``q`` where known (``(B,)``, as
    :func:`merit`). Returns the new coordinates and the mask of elements that accepted the full
    step."""
    check = todo & ~trust
    rows = check.nonzero().flatten()
    q_new = torch.where(todo[:, None], q + step, q)
    accepted = todo.clone()
    if rows.numel() == 0:
        return q_new, accepted
    whole = rows.numel() == q.shape[0]
    sub = prob if whole else prob.subset(rows, merit_only=True)
    qc, sc = (q, step) if whole else (q[rows], step[rows])
    f0 = merit(qc, sub, qc) if f_q is None else (f_q if whole else f_q[rows])
    slope = (g[rows] * sc).sum(-1)
    ok = _armijo(merit(qc + sc, sub, qc), f0, 1.0, slope)
    accepted[rows] = ok
    rej_local = (~ok).nonzero().flatten()
    if rej_local.numel() == 0:
        return q_new, accepted
    rej = rows[rej_local]
    sub = sub.subset(rej_local, merit_only=True)
    qr, sr, f0r, slr = qc[rej_local], sc[rej_local], f0[rej_local], slope[rej_local]
    t = torch.full_like(f0r, 0.5)
    done = torch.zeros_like(f0r, dtype=torch.bool)
    out = qr + t[:, None] * sr
    todo_r = torch.arange(len(rej), device=q.device)  # rows still halving (the rest accepted)
    sub_r = sub
    for _ in range(max_halvings - 1):
        trial = qr[todo_r] + t[todo_r, None] * sr[todo_r]
        ok = _armijo(merit(trial, sub_r, qr[todo_r]), f0r[todo_r], t[todo_r], slr[todo_r])
        acc = todo_r[ok]
        out[acc] = trial[ok]
        done[acc] = True
        if bool(done.all()):
            break
        t = torch.where(done, t, 0.5 * t)
        if bool(ok.any()):   # only the rows still rejecting are evaluated again
            keep = (~ok).nonzero().flatten()
            todo_r, sub_r = todo_r[keep], sub_r.subset(keep, merit_only=True)
    # Elements whose line search failed keep a tiny step along the direction (progress guard).
    out = torch.where(done[:, None], out, qr + t[:, None] * sr)
    q_new[rej] = out
    return q_new, accepted

