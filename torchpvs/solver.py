"""Stage 5 — the batched Newton solve: ``torchpvs.solve(scene, ...) -> Equilibrium``.

One entry point in the spirit of ``torchdiffeq.odeint``: the scene gives the robot, keyword tensors
override its actuation and load (and batch it), ``options`` picks accuracy and method.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace

import torch

from .equilibrium import Equilibrium
from .implicit import differentiable_outputs
from .mechanics import (
    _skew_vee,
    build_maps,
    elastic_energy,
    elastic_energy_maps,
    elastic_grad_hess,
    tip_pose,
)
from .scene import Scene, load_scene
from .sections import Discretization, TubeTensors, build_layout, n_coordinates

__all__ = ["SolverOptions", "SolverError", "solve", "tube_tensors"]

_METHODS = ("minimize", "root")
_MAGNUS_START, _MAGNUS_MAX = 8, 256
_ON_FAILURE = ("warn", "raise", "ignore")
_FORCE_MODELS = ("energy", "paper")


class SolverError(RuntimeError):
    """Raised when ``options.on_failure == "raise"`` and some element did not converge."""


@dataclass(frozen=True)
class SolverOptions:
    """Options of :func:`solve`.

    Attributes:
        accuracy: target tip-position accuracy [m]. With ``order=None`` the basis order is raised
            (2, 3, ...) until two successive orders agree on every tip within ``accuracy``
            (an a posteriori estimate); the chosen order is reported in ``Equilibrium.order``.
        order: polynomial degree of every strain basis (``n = order + 1`` functions per strain
            per section; the paper's "quadratic" is 2). ``None`` = automatic from ``accuracy``.
        max_order: ceiling of the automatic choice.
        method: ``"minimize"`` (default): damped Newton on the energy with a line search, which
            returns a *stable* equilibrium (local minimum) whenever the iteration can reach one;
            ``"root"``: plain Newton on the gradient, which converges to the stationary point
            nearest the initial guess, stable or not (use it with ``initial=`` to reach unstable
            equilibria of multi-stable scenes).
        tol: convergence threshold on the scaled residual ``max_i |g_i| / H_ii * L`` (dimensionless:
            a strain correction times the robot length, i.e. radians).
        max_iter: Newton iterations per order.
        n_quad: Gauss points per section (default ``2 (order + 1) + 4``).
        n_magnus: 4th-order Magnus steps per section for the backbone pose. ``None``
            (default) = automatic: starting from 8, the tip is recomputed with twice the steps and
            the count doubled (and the equilibrium re-solved) until the two agree within
            ``accuracy / 2``; that difference is added to ``Equilibrium.error_estimate``.
        dtype: ``torch.float64`` (default for physics) or ``torch.float32``; ``None`` = from the
            given tensors, else float64.
        device: torch device; ``None`` = from the given tensors, else CPU.
        on_failure: ``"warn"`` (default), ``"raise"`` (:class:`SolverError`) or ``"ignore"`` when
            an element does not converge. Status is always in ``Equilibrium.converged``/``reason``.
        compute_forces: also compute ``actuation_forces``/``actuation_torques`` (one backward pass).
        force_model: ``"energy"`` (default): ``tau = dU*/d(D, alpha)``, the energy-consistent
            forces of conventions.md (they include the configurational force of precurved
            material entering or leaving the guide); ``"paper"``: the projection of the paper's
            eq. (41) (Renda et al. 2021), which omits the guide's stored bending energy — for
            reproducing the paper's Table II (docs/actuation-forces.md). Defined as the paper
            defines it: two tubes (or one), no tip load, no straight-to-curved transition
            beyond the orifice, the outer tube ending before the inner one; other scenes raise
            ``ValueError``. Its forces/torques carry no gradient and no one-sided kink values.
        backward_ridge: Tikhonov shift added to the (Jacobi-scaled) stiffness in the adjoint
            solve of the implicit backward; 0 = exact gradients. Use a small value (1e-6) to
            regularize gradients at folds.
        load_coordinates: give distal single-tube sections coordinates even without a tip
            load (they are exact without; needed for the tip compliance at zero load and for
            gradients w.r.t. a load that is zero).
        singular_tol: the implicit backward warns (:class:`NearSingularStiffnessWarning`) for
            elements whose scaled stiffness has an eigenvalue below this in magnitude.
    """

    accuracy: float = 1e-5
    order: int | None = None
    max_order: int = 7
    method: str = "minimize"
    tol: float = 1e-10
    max_iter: int = 60
    n_quad: int | None = None
    n_magnus: int | None = None
    dtype: torch.dtype | None = None
    device: torch.device | str | None = None
    on_failure: str = "warn"
    compute_forces: bool = True
    force_model: str = "energy"
    backward_ridge: float = 0.0
    singular_tol: float = 1e-10
    load_coordinates: bool = False

    def __post_init__(self) -> None:
        if not (isinstance(self.accuracy, (int, float)) and self.accuracy > 0
                and math.isfinite(self.accuracy)):
            raise ValueError(
                f"options.accuracy must be a positive length [m], got {self.accuracy!r}")
        if self.order is not None and (not isinstance(self.order, int) or self.order < 0):
            raise ValueError(f"options.order must be an integer >= 0 or None, got {self.order!r}")
        if not isinstance(self.max_order, int) or self.max_order < 1:
            raise ValueError(f"options.max_order must be an integer >= 1, got {self.max_order!r}")
        if self.method not in _METHODS:
            raise ValueError(f"options.method must be one of {_METHODS}, got {self.method!r}")
        if self.force_model not in _FORCE_MODELS:
            raise ValueError(f"options.force_model must be one of {_FORCE_MODELS}, "
                             f"got {self.force_model!r}")
        if self.on_failure not in _ON_FAILURE:
            raise ValueError(f"options.on_failure must be one of {_ON_FAILURE}, "
                             f"got {self.on_failure!r}")
        if not (self.tol > 0):
            raise ValueError(f"options.tol must be > 0, got {self.tol!r}")
        if not isinstance(self.max_iter, int) or self.max_iter < 1:
            raise ValueError(f"options.max_iter must be an integer >= 1, got {self.max_iter!r}")
        if self.n_quad is not None and (not isinstance(self.n_quad, int) or self.n_quad < 2):
            raise ValueError(f"options.n_quad must be an integer >= 2 or None, got {self.n_quad!r}")
        if self.n_magnus is not None and (not isinstance(self.n_magnus, int)
                                          or self.n_magnus < 1):
            raise ValueError(
                f"options.n_magnus must be an integer >= 1 or None, got {self.n_magnus!r}")
        if not (self.backward_ridge >= 0 and math.isfinite(self.backward_ridge)):
            raise ValueError(f"options.backward_ridge must be >= 0, got {self.backward_ridge!r}")
        if self.dtype not in (None, torch.float32, torch.float64):
            raise ValueError(f"options.dtype must be torch.float32, torch.float64 or None, "
                             f"got {self.dtype!r}")

    def discretization(self, order: int) -> Discretization:
        n = order + 1
        return Discretization(n_basis=n, n_quad=self.n_quad or 2 * n + 4,
                              n_magnus=self.n_magnus or _MAGNUS_START)


def tube_tensors(scene: Scene, dtype: torch.dtype, device: torch.device) -> TubeTensors:
    """The scene's tube properties as ``(1, N)`` tensors (``coef``: ``(1, N, 3, P)``)."""
    P = max(1, max(len(ax) for t in scene.tubes for ax in t.precurvature))
    coef = torch.zeros(1, scene.n_tubes, 3, P, dtype=dtype, device=device)
    for j, t in enumerate(scene.tubes):
        for d, ax in enumerate(t.precurvature):
            if ax:
                coef[0, j, d, :len(ax)] = torch.tensor(ax, dtype=dtype, device=device)

    def row(values):
        return torch.tensor([values], dtype=dtype, device=device)

    return TubeTensors(
        EI=row([t.bending_stiffness for t in scene.tubes]),
        GJ=row([t.torsional_stiffness for t in scene.tubes]),
        length=row([t.length for t in scene.tubes]),
        straight=row([t.straight_length for t in scene.tubes]),
        coef=coef,
    )


def _as_batch(x, n: int, name: str, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2 or t.shape[-1] != n:
        raise ValueError(f"{name} must have shape ({n},) or (B, {n}), got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    return t


def _check_actuation(D: torch.Tensor, scene: Scene) -> None:
    if (D < 0).any():
        raise ValueError("insertion: every D_j must be >= 0 (conventions.md)")
    if scene.n_tubes > 1 and (D[:, 1:] < D[:, :-1]).any():
        raise ValueError("insertion: D_j must be >= D_{j-1} for every batch element "
                         "(an inner tube's base lies behind the outer one's)")


def solve(scene: Scene | str, *, insertion=None, rotation=None, tip_force=None, tip_moment=None,
          options: SolverOptions | None = None, initial: Equilibrium | torch.Tensor | None = None,
          ) -> Equilibrium:
    """Equilibrium of the PVS model of a concentric tube robot (batched).

    Args:
        scene: a :class:`~torchpvs.Scene` or a built-in scene name / file path.
        insertion: ``(N,)`` or ``(B, N)`` insertions ``D_j`` [m]; default the scene's.
        rotation: ``(N,)`` or ``(B, N)`` base rotations ``alpha_j`` [rad]; default the scene's.
        tip_force: ``(3,)`` or ``(B, 3)`` [N], base frame; default the scene's load.
        tip_moment: ``(3,)`` or ``(B, 3)`` [N·m], base frame; default the scene's load.
        options: :class:`SolverOptions`.
        initial: a previous :class:`Equilibrium` (warm start, same batch size) or a tensor of
            coordinates ``(B, nq)``.

    Returns:
        :class:`~torchpvs.Equilibrium` with batched tensors (batch ``B`` = the largest batch
        among the keyword tensors, 1 if none is batched).
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    opts = options or SolverOptions()
    ref = next((x for x in (insertion, rotation, tip_force, tip_moment)
                if isinstance(x, torch.Tensor)), None)
    dtype = opts.dtype or (ref.dtype if ref is not None and ref.is_floating_point()
                           else torch.float64)
    device = torch.device(opts.device) if opts.device is not None else (
        ref.device if ref is not None else torch.device("cpu"))
    N = scene.n_tubes
    D = _as_batch(scene.actuation.insertion if insertion is None else insertion, N,
                  "insertion", dtype, device)
    A = _as_batch(scene.actuation.rotation if rotation is None else rotation, N,
                  "rotation", dtype, device)
    F = _as_batch(scene.load.tip_force if tip_force is None else tip_force, 3,
                  "tip_force", dtype, device)
    M = _as_batch(scene.load.tip_moment if tip_moment is None else tip_moment, 3,
                  "tip_moment", dtype, device)
    B = max(D.shape[0], A.shape[0], F.shape[0], M.shape[0])
    for name, t in (("insertion", D), ("rotation", A), ("tip_force", F), ("tip_moment", M)):
        if t.shape[0] not in (1, B):
            raise ValueError(f"{name} has batch size {t.shape[0]}, expected 1 or {B}")
    D, A, F, M = (t.expand(B, -1).contiguous() for t in (D, A, F, M))
    _check_actuation(D, scene)
    if opts.force_model == "paper" and opts.compute_forces:
        from .equilibrium import paper_scope_check
        loaded = (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0)
        paper_scope_check(tube_tensors(scene, dtype, device), D, loaded)
    return _solve(scene, tube_tensors(scene, dtype, device), D, A, F, M, opts, initial)


def _solve(scene: Scene, tubes: TubeTensors, D, A, F, M, opts: SolverOptions, initial):
    """The solve proper, on canonical ``(B, ...)`` tensors; differentiable through the implicit
    backward when any input requires grad."""
    B = D.shape[0]
    t0 = time.perf_counter()
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (D, A, F, M, tubes.EI, tubes.GJ, tubes.length, tubes.straight,
                                  tubes.coef))
    D_in, A_in, F_in, M_in, tubes_in = D, A, F, M, tubes
    D, A, F, M = (t.detach() for t in (D, A, F, M))
    tubes = TubeTensors(*(t.detach() for t in (tubes.EI, tubes.GJ, tubes.length,
                                               tubes.straight, tubes.coef)))
    orders = [opts.order] if opts.order is not None else list(range(2, opts.max_order + 1))
    q_init = _initial_q(initial, B)
    prev = None
    for order in orders:
        res = _solve_order(scene, tubes, D, A, F, M, order, opts, q_init)
        if opts.order is not None:
            break
        if prev is not None:
            err = (res["tip"] - prev["tip"]).norm(dim=-1)
            res["error_estimate"] = err
            if bool((err <= opts.accuracy).all()):
                break
        prev = res
        q_init = res["q"]
    if opts.n_magnus is None:
        res = _refine_magnus(scene, tubes, D, A, F, M, res, opts)
    diff = None
    info = {"H": res["H"], "qmask": res["lay"]["qmask"], "ridge": opts.backward_ridge,
            "singular_tol": opts.singular_tol, "loaded": res["loaded"], "disc": res["disc"],
            "tab": res["tab"], "with_load": res["with_load"], "has_moment": res["has_moment"]}
    res["implicit_info"] = info
    if needs_grad:
        diff = differentiable_outputs(res["q"], info, D_in, A_in, F_in, M_in, tubes_in)
    elapsed = time.perf_counter() - t0
    eq = Equilibrium._from_solution(scene, tubes, res, opts, elapsed, diff)
    failed = (~eq.converged).nonzero().flatten().tolist()
    if failed and opts.on_failure != "ignore":
        msg = (f"torchpvs.solve: {len(failed)} of {B} element(s) did not converge "
               f"(first: element {failed[0]}: {eq.reason[failed[0]]})")
        if opts.on_failure == "raise":
            raise SolverError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
    return eq


def _refine_magnus(scene, tubes, D, A, F, M, res, opts: SolverOptions):
    """Double the Magnus steps until the tip moves less than ``accuracy / 2`` (4th order: the
    remaining error of the finer count is ~1/15 of that change). The equilibrium coordinates do
    not depend on the pose integration unless a tip load is applied, so the check is a tip
    recomputation; only a refinement re-solves (warm, usually one Newton step)."""
    m = res["disc"].n_magnus
    order_err = res.get("error_estimate")  # a fixed order has no basis estimate: stays NaN
    while True:
        fine = replace(res["disc"], n_magnus=2 * m)
        tip_fine, _, _ = tip_pose(res["q"], res["lay"], fine.tables(D.dtype, D.device))
        est = (tip_fine - res["tip"]).norm(dim=-1)
        if bool((est <= opts.accuracy / 2).all()) or 2 * m > _MAGNUS_MAX:
            break
        m *= 2
        res = _solve_order(scene, tubes, D, A, F, M, res["order"], replace(opts, n_magnus=m),
                           res["q"])
    if order_err is not None:
        res["error_estimate"] = order_err + est
    res["magnus_estimate"] = est
    return res


def _initial_q(initial, B: int) -> torch.Tensor | None:
    if initial is None:
        return None
    q = initial.q if isinstance(initial, Equilibrium) else torch.as_tensor(initial)
    if q.ndim == 1:
        q = q[None]
    if q.shape[0] not in (1, B):
        raise ValueError(f"initial has batch size {q.shape[0]}, expected 1 or {B}")
    return q.expand(B, -1)


def _resize_q(q: torch.Tensor, N: int, n_from: int, n_to: int) -> torch.Tensor:
    """Map coordinates between basis sizes (the Legendre basis is hierarchical: pad/truncate)."""
    B = q.shape[0]
    w = q[:, :N]
    X = q[:, N:].reshape(B, 2 * N, 2 + N, n_from)
    if n_to >= n_from:
        X = torch.nn.functional.pad(X, (0, n_to - n_from))
    else:
        X = X[..., :n_to]
    return torch.cat([w, X.reshape(B, -1)], -1)


def _solve_order(scene, tubes, D, A, F, M, order, opts, q_init):
    disc = opts.discretization(order)
    N = scene.n_tubes
    B = D.shape[0]
    dtype, device = D.dtype, D.device
    loaded = (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0) | opts.load_coordinates
    lay = build_layout(tubes, D, A, F, M, loaded, disc)
    tab = disc.tables(dtype, device)
    nq = n_coordinates(N, disc.n_basis)
    with_load = bool(loaded.any())
    has_moment = bool((M.abs().sum(-1) > 0).any()) or opts.load_coordinates

    if q_init is not None:
        n_from = (q_init.shape[-1] - N) // (2 * N * (2 + N))
        if n_coordinates(N, n_from) != q_init.shape[-1]:
            raise ValueError(f"initial has {q_init.shape[-1]} coordinates, which matches no basis "
                             f"size for {N} tubes")
        q = _resize_q(q_init.to(dtype=dtype, device=device), N, n_from, disc.n_basis)
    else:
        q = _default_guess(lay, tab, disc, N)
    qmask = lay["qmask"]
    q = q * qmask

    L_char = (lay["ell"].amax(-1) + D.amax(-1)).clamp(min=1e-6)           # (B,)
    maps = build_maps(lay, tab, nq)
    derivs = _derivative_fn(tab, maps, with_load, has_moment)
    merit = _merit_fn(tab, maps, with_load, has_moment)

    converged = torch.zeros(B, dtype=torch.bool, device=device)
    residual = torch.full((B,), float("inf"), dtype=dtype, device=device)
    iterations = torch.zeros(B, dtype=torch.long, device=device)
    lam = torch.zeros(B, dtype=dtype, device=device)
    eye = torch.eye(nq, dtype=dtype, device=device)
    H = g = None
    escapes = 0
    for _ in range(opts.max_iter + 1):
        g, H = derivs(q, lay)
        g, H = _mask(g, H, qmask, eye)
        diag = H.diagonal(dim1=-2, dim2=-1)
        scale = diag.abs().clamp(min=torch.finfo(dtype).tiny) ** -0.5
        residual = ((g.abs() * scale**2).amax(-1) * L_char)
        residual = torch.where(torch.isfinite(residual), residual,
                               torch.full_like(residual, float("inf")))
        converged = residual < _tol(opts.tol, dtype)
        if opts.method == "minimize" and escapes < 8 and bool(converged.any()):
            # A converged saddle is not a minimum: leave it along negative curvature.
            q, left = _escape_saddles(q, H, g, scale, converged, qmask, lay, merit, L_char)
            converged = converged & ~left
            escapes += int(bool(left.any()))
        todo = ~converged & torch.isfinite(q).all(-1)
        if not bool(todo.any()):
            break
        Hs = scale[:, :, None] * H * scale[:, None, :]
        gs = scale * g
        if opts.method == "minimize":
            step, lam = _damped_step(Hs, gs, lam, eye)
            step = scale * step
            q_new, accepted = _line_search(merit, q, step, g, lay, todo)
            lam = torch.where(accepted, lam * 0.25, torch.clamp(lam * 4 + 1e-6, max=1e6))
        else:
            step = scale * torch.linalg.solve(Hs + 1e-14 * eye, -gs[..., None])[..., 0]
            # Cap the step at 1 rad of strain x length to stay in Newton's basin.
            cap = (step.abs().amax(-1) * L_char).clamp(min=1.0)
            q_new = q + step / cap[:, None]
        q_new = torch.where(torch.isfinite(q_new).all(-1, keepdim=True), q_new, q)
        q = torch.where(todo[:, None], q_new * qmask, q)
        iterations = iterations + todo.long()

    p, R, _ = tip_pose(q, lay, tab)
    return {"q": q, "lay": lay, "tab": tab, "disc": disc, "order": order, "H": H, "g": g,
            "converged": converged & torch.isfinite(p).all(-1), "residual": residual,
            "iterations": iterations, "tip": p, "R": R, "D": D, "alpha": A, "F": F, "M": M,
            "loaded": loaded, "with_load": with_load, "has_moment": has_moment}


def _escape_saddles(q, H, g, scale, converged, qmask, lay, merit, L_char):
    """For converged elements whose Hessian has a negative eigenvalue, step along the
    eigenvector (sign chosen downhill) with a backtracking search on the energy. Returns the new
    coordinates and the mask of elements that left a saddle."""
    idx = converged.nonzero().flatten()
    Hs = scale[idx, :, None] * H[idx] * scale[idx, None, :]
    big = 10.0 * Hs.diagonal(dim1=-2, dim2=-1).abs().amax(-1) + 1.0
    Hs = Hs + torch.diag_embed((1.0 - qmask[idx]) * big[:, None])
    ev, vec = torch.linalg.eigh(Hs)
    neg = ev[:, 0] < -1e-8
    left = torch.zeros_like(converged)
    if not bool(neg.any()):
        return q, left
    idx, v = idx[neg], vec[neg][:, :, 0] * scale[idx[neg]]
    v = v * qmask[idx]
    sign = torch.where((g[idx] * v).sum(-1) > 0, -1.0, 1.0).to(v.dtype)
    v = sign[:, None] * v / (v.abs().amax(-1, keepdim=True) * L_char[idx, None]).clamp(min=1e-30)
    lay_i = {k: t[idx] for k, t in lay.items()}
    f0 = merit(q[idx], lay_i, q[idx])
    t = torch.ones_like(f0)
    new = q[idx].clone()
    ok_all = torch.zeros_like(f0, dtype=torch.bool)
    for _ in range(40):
        trial = q[idx] + t[:, None] * v
        ok = (merit(trial, lay_i, q[idx]) < f0) & ~ok_all
        new = torch.where(ok[:, None], trial, new)
        ok_all = ok_all | ok
        if bool(ok_all.all()):
            break
        t = torch.where(ok_all, t, 0.5 * t)
    q = q.clone()
    q[idx] = new
    left[idx] = ok_all
    return q, left


def _tol(tol: float, dtype: torch.dtype) -> float:
    # float32 cannot resolve residuals below ~1e-6 of the strain scale.
    return max(tol, 1e-5) if dtype == torch.float32 else tol


def _mask(g, H, qmask, eye):
    g = g * qmask
    outer = qmask[:, :, None] * qmask[:, None, :]
    H = H * outer + eye * (1.0 - qmask)[:, None, :]
    return g, H


def _damped_step(Hs, gs, lam, eye):
    """Levenberg–Marquardt-damped Newton step on the Jacobi-scaled system; indefinite Hessians
    are shifted to be positive definite so the step is a descent direction."""
    A = Hs + lam[:, None, None] * eye
    L, info = torch.linalg.cholesky_ex(A)
    bad = info != 0
    if bool(bad.any()):
        ev = torch.linalg.eigvalsh(Hs[bad])[:, 0]
        shift = torch.clamp(-ev, min=0.0) * 1.1 + 1e-3 + lam[bad]
        lam = lam.clone()
        lam[bad] = shift
        A = Hs + lam[:, None, None] * eye
        L, info = torch.linalg.cholesky_ex(A)
    step = torch.cholesky_solve(-gs[..., None], L)[..., 0]
    return step, lam


def _line_search(merit, q, step, g, lay, todo, max_halvings: int = 30):
    """Backtracking (Armijo) on the potential, per element."""
    f0 = merit(q, lay, q)
    slope = (g * step).sum(-1)
    t = torch.ones_like(f0)
    accepted_full = torch.zeros_like(todo)
    done = ~todo
    q_new = q.clone()
    for i in range(max_halvings):
        trial = q + t[:, None] * step
        f = merit(trial, lay, q)
        # Below the energy's rounding level the Armijo test is noise: accept the step then
        # (the residual test, not the energy, decides convergence).
        resolution = 8 * torch.finfo(f0.dtype).eps * f0.abs().clamp(min=1e-300)
        ok = ((f <= f0 + 1e-4 * t * slope) | (-slope * t <= resolution)
              | (f - f0 <= resolution)) & torch.isfinite(f) & ~done
        q_new = torch.where(ok[:, None], trial, q_new)
        if i == 0:
            accepted_full = ok.clone()
        done = done | ok
        if bool(done.all()):
            break
        t = torch.where(done, t, 0.5 * t)
    # Elements whose line search failed keep a tiny step along the direction (progress guard).
    q_new = torch.where(done[:, None], q_new, q + t[:, None] * step)
    return q_new, accepted_full


def _derivative_fn(tab, maps, with_load: bool, has_moment: bool):
    """Gradient and exact Hessian: analytic for the elastic energy (precomputed linear maps),
    autograd (``vmap(jacfwd(grad))``) only for the tip-load term, which needs the Magnus chain."""
    def load_only(q, lay, q_ref):
        p, R, _ = tip_pose(q, lay, tab)
        work = (lay["force"] * p).sum(-1)
        if has_moment:
            with torch.no_grad():
                _, R0, _ = tip_pose(q_ref, lay, tab)
            work = work + (lay["moment"] * _skew_vee(R @ R0.transpose(-1, -2))).sum(-1)
        return -work

    def grad_and_grad(q, lay, q_ref):
        g = torch.func.grad(load_only)(q, lay, q_ref)
        return g, g

    load_hess = torch.func.vmap(torch.func.jacfwd(grad_and_grad, has_aux=True))

    def derivs(q, lay):
        g, H = elastic_grad_hess(q, maps)
        if with_load:
            Hl, gl = load_hess(q, lay, q.detach())
            g = g + gl
            H = H + 0.5 * (Hl + Hl.transpose(-1, -2))
        return g, H

    return derivs


def _merit_fn(tab, maps, with_load: bool, has_moment: bool):
    def merit(q, lay, q_ref):
        with torch.no_grad():
            same_batch = maps is not None and q.shape[0] == maps["W"].shape[0]
            U = elastic_energy_maps(q, maps) if same_batch else elastic_energy(q, lay, tab)
            if with_load:
                p, R, _ = tip_pose(q, lay, tab)
                U = U - (lay["force"] * p).sum(-1)
                if has_moment:
                    _, R0, _ = tip_pose(q_ref, lay, tab)
                    U = U - (lay["moment"] * _skew_vee(R @ R0.transpose(-1, -2))).sum(-1)
            return U
    return merit


def _default_guess(lay, tab, disc, N):
    """Torsionless guess: tubes keep their base angles, the backbone bends with the
    stiffness-weighted average of the rotated precurvatures (exact without torsion, eq. 31)."""
    from .mechanics import node_fields

    B = lay["h"].shape[0]
    nq = n_coordinates(N, disc.n_basis)
    q0 = torch.zeros(B, nq, dtype=lay["h"].dtype, device=lay["h"].device)
    f = node_fields(q0, lay, tab["xq"], tab["phi_q"], tab["Q_q"])
    EI = lay["EI"][:, None, None, :] * lay["present"][:, :, None, :]
    u_avg = (EI[..., None] * f["Ru"]).sum(-2) / EI.sum(-1, keepdim=True).clamp(min=1e-30)
    a = 0.5 * torch.einsum("bsgd,gp,g->bsdp", u_avg, tab["phi_q"], tab["wq"])
    X = torch.zeros(B, 2 * N, 2 + N, disc.n_basis, dtype=q0.dtype, device=q0.device)
    X[:, :, :2, :] = a
    q0[:, N:] = X.reshape(B, -1)
    return q0


def with_options(options: SolverOptions | None, **changes) -> SolverOptions:
    """A copy of ``options`` (or the defaults) with fields changed."""
    return replace(options or SolverOptions(), **changes)
