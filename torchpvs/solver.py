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
from .implicit import ImplicitContext, differentiable_outputs
from .mechanics import (
    compact_hessian,
    compact_q,
    expand_hessian,
    expand_q,
    pose_constants,
    pose_node_constants,
    section_grad_block,
    start_angles,
    sum_dim,
    tip_pose,
)
from .newton import (
    CHUNK_BYTES,
    KERNELS,
    Problem,
    active_index,
    chunked,
    compact,
    compact_scaled,
    derivatives,
    expand,
    scaled_residual,
    subset,
    take,
)
from .plan import MAGNUS_START, ORDER_START, Plan, plan_for, tube_tensors
from .scene import Scene, load_scene
from .sections import Discretization, TubeTensors, n_coordinates, tube_rows

__all__ = ["AccuracyWarning", "SolverOptions", "SolverError", "solve", "tube_tensors"]

_METHODS = ("minimize", "root")
_MAGNUS_MAX = 256
_ON_FAILURE = ("warn", "raise", "ignore")
_FORCE_MODELS = ("energy", "paper")


class SolverError(RuntimeError):
    """Raised when ``options.on_failure == "raise"`` and some element did not converge."""


class AccuracyWarning(RuntimeWarning):
    """An automatic solve converged but its error estimate exceeds ``options.accuracy``."""


@dataclass(frozen=True)
class SolverOptions:
    """Options of :func:`solve`.

    Attributes:
        accuracy: target tip-position accuracy [m]. With ``order=None`` the basis order is
            chosen automatically: the solve starts at the order of the warm start (``initial``,
            an Equilibrium or coordinates of a basis size) or at 2, estimates the tip error
            by one Newton step of the next order from the solution (its tip change), and raises
            the order until that estimate is within ``accuracy``; the chosen order is reported
            in ``Equilibrium.order``, the estimate in ``Equilibrium.error_estimate``.
        order: polynomial degree of every strain basis (``n = order + 1`` functions per strain
            per section; the paper's "quadratic" is 2). ``None`` = automatic from ``accuracy``.
        max_order: ceiling of the automatic choice.
        method: ``"minimize"`` (default): damped Newton on the energy with a line search, which
            returns a *stable* equilibrium (local minimum) whenever the iteration can reach one;
            ``"root"``: plain Newton on the gradient, which converges to the stationary point
            nearest the initial guess, stable or not (use it with ``initial=`` to reach unstable
            equilibria of multi-stable scenes).
        tol: convergence threshold on the scaled residual ``max_i |g_i| / H_ii * L`` (dimensionless:
            a strain correction times the robot length, i.e. radians). The kernel uses
            ``min(tol, accuracy / (100 L))`` with ``L`` the longest tube, so that the residual
            never limits the requested accuracy. At the default 1e-9 the tip moves by at most
            3e-12 m, and the forces by 2e-10 N, against solves at 1e-12 (Fig. 3 robot, 1024 warm
            configurations: docs/performance.md); 1e-10 cost a second Newton iteration on 2/3
            of warm 1 deg steps there.
        max_iter: Newton iterations per order.
        n_quad: Gauss points per section (default ``2 (order + 1) + 4``).
        n_magnus: 4th-order Magnus steps per section for the backbone pose. ``None``
            (default) = automatic: the warm start's count (else 8) is kept if the tip moves
            less than ``accuracy / 2`` when recomputed with half the steps; otherwise the tip
            is recomputed with twice the steps and the count doubled (and the equilibrium
            re-solved) until the two agree within ``accuracy / 2``. The last tip change is
            added to ``Equilibrium.error_estimate``.
        dtype: ``torch.float64`` (default for physics) or ``torch.float32``; ``None`` = from the
            given tensors, else float64.
        device: torch device; ``None`` = from the given tensors, else CPU.
        on_failure: ``"warn"`` (default), ``"raise"`` (:class:`SolverError`) or ``"ignore"`` when
            an element does not converge. Status is always in ``Equilibrium.converged``/``reason``.
        compute_forces: also compute ``actuation_forces``/``actuation_torques`` (one backward pass).
        force_model: ``"energy"`` (default): ``tau = dU*/d(D, alpha)``, the energy-consistent
            forces of docs/conventions.md (they include the configurational force of precurved
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
        kernel: name of the Newton kernel in :data:`torchpvs.newton.KERNELS` (``"newton"``).
        load_steps: load continuation for loaded elements that do not converge from the
            initial guess: the tip load is ramped up in this many equal steps, each warm-started
            from the last (1 = no ramp). ``Equilibrium.reason`` says how far a failed ramp got.
        max_total_iter: bound on the Newton iterations of one call over every order, Magnus
            refinement and load step (``max_iter`` bounds one kernel call). When it is reached
            the solve stops where it is: unfinished elements are not converged, and converged
            ones whose estimate exceeds ``accuracy`` say so (``accuracy_met``).
        singular_tol: the implicit backward warns (:class:`NearSingularStiffnessWarning`) for
            elements whose scaled stiffness has an eigenvalue below this in magnitude.
        time_limit: [s] wall-clock bound on the Newton iterations of one call (every order,
            load step and Magnus refinement; ``None`` = no bound). Checked before every Newton
            step, so a call overshoots by at most one iteration plus the outputs (forces,
            pose). When it is reached the solve stops like ``max_total_iter``: unfinished
            elements are not converged and their reason says so.
    """

    accuracy: float = 1e-5
    order: int | None = None
    max_order: int = 7
    method: str = "minimize"
    tol: float = 1e-9
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
    kernel: str = "newton"
    load_steps: int = 8
    max_total_iter: int = 200
    time_limit: float | None = 30.0

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
        if not isinstance(self.load_steps, int) or self.load_steps < 1:
            raise ValueError(f"options.load_steps must be an integer >= 1, got {self.load_steps!r}")
        if not isinstance(self.max_total_iter, int) or self.max_total_iter < 1:
            raise ValueError(f"options.max_total_iter must be an integer >= 1, "
                             f"got {self.max_total_iter!r}")
        if self.time_limit is not None and not (
                isinstance(self.time_limit, (int, float)) and not isinstance(self.time_limit, bool)
                and self.time_limit > 0 and math.isfinite(self.time_limit)):
            raise ValueError(f"options.time_limit must be a positive number of seconds or None, "
                             f"got {self.time_limit!r}")
        if self.n_quad is not None and (not isinstance(self.n_quad, int) or self.n_quad < 2):
            raise ValueError(f"options.n_quad must be an integer >= 2 or None, got {self.n_quad!r}")
        if self.n_magnus is not None and (not isinstance(self.n_magnus, int)
                                          or self.n_magnus < 1):
            raise ValueError(
                f"options.n_magnus must be an integer >= 1 or None, got {self.n_magnus!r}")
        if not (self.backward_ridge >= 0 and math.isfinite(self.backward_ridge)):
            raise ValueError(f"options.backward_ridge must be >= 0, got {self.backward_ridge!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"options.kernel must be one of {tuple(KERNELS)}, "
                             f"got {self.kernel!r}")
        if self.dtype not in (None, torch.float32, torch.float64):
            raise ValueError(f"options.dtype must be torch.float32, torch.float64 or None, "
                             f"got {self.dtype!r}")

    def discretization(self, order: int) -> Discretization:
        n = order + 1
        return Discretization(n_basis=n, n_quad=self.n_quad or 2 * n + 4,
                              n_magnus=self.n_magnus or MAGNUS_START)


def check_time_limit(time_limit, name: str = "time_limit") -> float | None:
    """A wall-clock bound [s]: a positive finite number or ``None`` (no bound)."""
    if time_limit is not None and not (isinstance(time_limit, (int, float))
                                       and not isinstance(time_limit, bool)
                                       and time_limit > 0 and math.isfinite(time_limit)):
        raise ValueError(f"{name} must be a positive number of seconds or None, got "
                         f"{time_limit!r}")
    return time_limit


def within_deadline(opts: SolverOptions, deadline: float | None) -> SolverOptions:
    """``opts`` with its ``time_limit`` cut to what is left before ``deadline`` (a
    ``time.perf_counter()`` value; ``None``: unchanged), so that a call made of many solves
    keeps its own bound. At least 1 ms, so that an expired call still returns a verdict."""
    if deadline is None:
        return opts
    left = max(deadline - time.perf_counter(), 1e-3)
    limit = left if opts.time_limit is None else min(opts.time_limit, left)
    return replace(opts, time_limit=limit)


def as_batch(x, n: int, name: str, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2 or t.shape[-1] != n:
        raise ValueError(f"{name} must have shape ({n},) or (B, {n}), got {tuple(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must be finite")
    return t


def check_actuation(D: torch.Tensor, scene: Scene) -> None:
    if (D < 0).any():
        raise ValueError("insertion: every D_j must be >= 0 (docs/conventions.md)")
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
    if options is not None and not isinstance(options, SolverOptions):
        raise TypeError(f"options must be a torchpvs.SolverOptions (e.g. SolverOptions(**d) "
                        f"for a dict d), got {type(options).__name__}")
    opts = options or SolverOptions()
    for name, x in (("insertion", insertion), ("rotation", rotation), ("tip_force", tip_force),
                    ("tip_moment", tip_moment)):
        if isinstance(x, torch.Tensor) and x.dtype not in (torch.float32, torch.float64) \
                and (x.is_floating_point() or x.is_complex()):
            raise ValueError(f"{name}: dtype {x.dtype} is not supported; the solver runs in "
                             f"torch.float32 or torch.float64 (convert the input, or set "
                             f"SolverOptions(dtype=...))")
    ref = next((x for x in (insertion, rotation, tip_force, tip_moment)
                if isinstance(x, torch.Tensor)), None)
    dtype = opts.dtype or (ref.dtype if ref is not None
                           and ref.dtype in (torch.float32, torch.float64) else torch.float64)
    device = torch.device(opts.device) if opts.device is not None else (
        ref.device if ref is not None else torch.device("cpu"))
    N = scene.n_tubes
    D = as_batch(scene.actuation.insertion if insertion is None else insertion, N,
                  "insertion", dtype, device)
    A = as_batch(scene.actuation.rotation if rotation is None else rotation, N,
                  "rotation", dtype, device)
    F = as_batch(scene.load.tip_force if tip_force is None else tip_force, 3,
                  "tip_force", dtype, device)
    M = as_batch(scene.load.tip_moment if tip_moment is None else tip_moment, 3,
                  "tip_moment", dtype, device)
    B = max(D.shape[0], A.shape[0], F.shape[0], M.shape[0])
    if min(D.shape[0], A.shape[0], F.shape[0], M.shape[0]) == 0:
        raise ValueError("insertion, rotation, tip_force, tip_moment: batch size 0; give at least "
                         "one row (shape (B, ...) with B >= 1)")
    for name, t in (("insertion", D), ("rotation", A), ("tip_force", F), ("tip_moment", M)):
        if t.shape[0] not in (1, B):
            raise ValueError(f"{name} has batch size {t.shape[0]}, expected 1 or {B}")
    D, A, F, M = (t.expand(B, -1).contiguous() for t in (D, A, F, M))
    check_actuation(D, scene)
    if opts.force_model == "paper" and opts.compute_forces:
        from .forces import paper_scope_check
        loaded = (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0)
        paper_scope_check(tube_tensors(scene, dtype, device), D, loaded)
    plan = plan_for(scene, dtype, device)
    return solve_tensors(scene, plan.tubes, D, A, F, M, opts, initial, plan)


def solve_tensors(scene: Scene, tubes: TubeTensors, D, A, F, M, opts: SolverOptions, initial,
                  plan: Plan | None = None):
    """The solve proper, on canonical ``(B, ...)`` tensors; differentiable through the implicit
    backward when any input requires grad. ``plan`` carries reuse between calls (a private
    one-off plan when ``None``)."""
    B = D.shape[0]
    t0 = time.perf_counter()
    plan = plan if plan is not None else Plan(tubes)
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (D, A, F, M, *tubes.tensors()))
    # U*(alpha) is 2 pi-periodic in every base rotation and q holds no absolute angle: solving
    # at alpha - 2 pi k (k constant, no gradient) keeps cos/sin accurate for large angles.
    A = A - (2 * math.pi) * torch.round(A.detach() / (2 * math.pi))
    D_in, A_in, F_in, M_in, tubes_in = D, A, F, M, tubes
    # Owned copies: the plan keeps layouts that refer to them (a caller may reuse its buffers).
    D, A, F, M = (t.detach().clone() for t in (D, A, F, M))
    if needs_grad:
        tubes = tubes.map(torch.Tensor.detach)
    # Without a gradient to carry, the solve runs in inference mode (no autograd bookkeeping:
    # ~20% less time per torch op, which bounds small batches); what it returns is released
    # to ordinary tensors (Equilibrium.released).
    with torch.inference_mode(not needs_grad):
        q_init, init_order, init_magnus = _initial_q(initial, B, scene.n_tubes)
        q_init = _rotation_predictor(initial, q_init, scene, tubes, D, A, F, M, opts)
        # Automatic choices start at the warm start's discretization (so a continuation keeps
        # the model whose branch it follows), else at order 2 and 8 Magnus steps.
        if opts.order is not None:
            order = opts.order
        else:
            order = min(init_order if init_order is not None else ORDER_START, opts.max_order)
        n_magnus = opts.n_magnus or init_magnus or MAGNUS_START
        # The accuracy is shared between the basis and the pose integration when both are
        # automatic.
        budget = opts.accuracy / 2 if opts.n_magnus is None else opts.accuracy
        work = _Work(opts.max_total_iter, opts.time_limit)
        prev = None
        while True:
            # With the automatic order and no load (no load ramp), the solution's tip pose is
            # made by the order check, together with the next order's (one pose call).
            joint = opts.order is None and not bool(_loaded(F, M, opts).any())
            res = _solve_order(scene, tubes, D, A, F, M, order, n_magnus, opts, q_init, plan,
                               pose=not joint, deadline=work.deadline)
            work.spend(res)
            if prev is None:
                res = _load_ramp(scene, tubes, D, A, F, M, res, opts, plan, q_init, work)
            elif bool((prev["converged"] & ~res["converged"]).any()):
                # A higher order lost an equilibrium the lower one had: keep the lower order's
                # batch (its estimate then says the accuracy is not met) rather than a failure.
                res = prev
                break
            if opts.order is not None:
                break
            est, q_next = _order_estimate(scene, tubes, D, A, F, M, res, opts, plan)
            res["error_estimate"] = est
            # Elements that did not converge are reported as such; a higher order won't help.
            if bool(((est <= budget) | ~res["converged"]).all()) or order >= opts.max_order \
                    or work.exhausted:
                break
            order += 1
            q_init = q_next
            prev = res
        if opts.n_magnus is None:
            res = _refine_magnus(scene, tubes, D, A, F, M, res, opts, plan, work)
    res["work_exhausted"] = work.exhausted
    res["timed_out"] = work.timed_out
    diff = None
    # The Hessian is kept on the kernel's compact coordinates (implicit.full_hessian pads it).
    info = ImplicitContext(
        qmask=res["lay"].qmask, loaded=res["loaded"], disc=res["disc"], tab=res["tab"],
        with_load=res["with_load"], has_moment=res["has_moment"], ridge=opts.backward_ridge,
        singular_tol=opts.singular_tol, Hc=res["Hc"], cidx=res["maps"]["cidx"],
        qmask_c=res["maps"]["qmask"])
    res["implicit_info"] = info
    if needs_grad:
        diff = differentiable_outputs(res["q"], info, D_in, A_in, F_in, M_in, tubes_in)
    elapsed = time.perf_counter() - t0

    def resolve(Dn, sel):
        # Forces at equilibria a distance delta ~ 1e-7 m away (insertions Dn, rows sel of the
        # batch). Where the section structure there equals this one (same active coordinates),
        # q* moves by O(delta) and dU*/dD = dU/dD at fixed q to O(delta) (envelope theorem):
        # no solve. Where a section of length delta appears, its coordinates are solved for
        # with the others held (_new_section_step: O(delta), like the rest), or where that does
        # not apply (a tip load, a guide twist appearing), by ONE Newton step from q.
        An, Fn, Mn, q0 = A[sel], F[sel], M[sel], res["q"][sel]
        disc = res["disc"]
        nq = q0.shape[-1]
        loaded = _loaded(Fn, Mn, opts)
        lay, maps = plan.layout(tube_rows(tubes, sel), Dn, An, Fn, Mn, loaded, disc, nq)
        q1 = q0 * lay.qmask
        moved = (lay.qmask != res["lay"].qmask[sel]).any(-1).nonzero().flatten()
        if moved.numel():
            first, k = int(moved[0]), moved.numel()
            if int(moved[-1]) - first + 1 == k:      # usually one run of rows: views, no copy
                moved = slice(first, first + k)
            prob = subset(Problem(lay, res["tab"], maps, res["with_load"], res["has_moment"]),
                           moved)
            q1 = q1.clone()
            qm, ok = q1[moved], torch.zeros(q1[moved].shape[0], dtype=torch.bool,
                                            device=q1.device)
            if not res["with_load"]:
                new = (lay.qmask[moved] > 0) & ~(res["lay"].qmask[sel][moved] > 0)
                qm, ok = _new_section_step(qm, prob, new, float(tubes.length.max()))
            rest = (~ok).nonzero().flatten()
            if rest.numel():
                qm = qm.clone()
                qm[rest] = _newton_step(qm[rest], subset(prob, rest))[0]
            q1[moved] = qm
        return {"q": q1, "D": Dn, "alpha": An, "F": Fn, "M": Mn, "loaded": loaded, "lay": lay}

    def resolve_all(options, initial_):
        return solve_tensors(scene, tubes, D, A, F, M, options, initial_, plan)

    with torch.inference_mode(not needs_grad):
        eq = Equilibrium.from_solution(scene, tubes, res, opts, elapsed, diff, plan, resolve,
                                       resolve_all)
    if not needs_grad:
        eq = eq.released()
    if opts.order is None and opts.on_failure != "ignore":
        short = eq.converged & ~eq.accuracy_met
        if bool(short.any()):
            b = int(short.nonzero()[0])
            warnings.warn(
                f"torchpvs.solve: requested accuracy {opts.accuracy:g} m not reached for "
                f"{int(short.sum())} of {B} element(s) (first: element {b}, error estimate "
                f"{float(eq.error_estimate[b]):.3g} m at order {eq.order} "
                f"(max_order={opts.max_order}), {res['disc'].n_magnus} Magnus steps); see "
                f"Equilibrium.accuracy_met", AccuracyWarning, stacklevel=2)
    if opts.on_failure != "ignore":
        n_failed = int((~eq.converged).sum())
        if n_failed:
            first = int((~eq.converged).nonzero()[0])
            msg = (f"torchpvs.solve: {n_failed} of {B} element(s) did not converge "
                   f"(first: element {first}: {eq.reason[first]})")
            if opts.on_failure == "raise":
                raise SolverError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
    return eq


def _order_estimate(scene, tubes, D, A, F, M, res, opts: SolverOptions, plan: Plan):
    """A posteriori tip error of ``res`` at its order: one Newton step of the next order from
    the solution (the Legendre basis is hierarchical, so the solution pads exactly), and the
    tip change it makes. Newton converges quadratically from there, so the step lands within
    the square of the truncation error of the next order's solution: the estimate costs one
    gradient/Hessian evaluation, one factorization and one tip pose instead of a full solve.
    Returns ``(estimate (B,), coordinates at order + 1 to warm-start it)``. Also sets
    ``res["tip_coarse"]``, the solution's tip with half the Magnus steps, which the step-count
    check (:func:`_refine_magnus`) compares with first."""
    N = scene.n_tubes
    order = res["order"] + 1
    disc = replace(opts.discretization(order), n_magnus=res["disc"].n_magnus)
    n_from = res["disc"].n_basis
    nq = n_coordinates(N, disc.n_basis)
    lay, maps = plan.layout(tubes, D, A, F, M, res["loaded"], disc, nq)
    tab = disc.tables(D.dtype, D.device)
    prob = Problem(lay, tab, maps, res["with_load"], res["has_moment"])
    q = _resize_q(res["q"], N, n_from, disc.n_basis) * lay.qmask
    q1, ok = _newton_step(q, prob)
    if "tip" in res:
        tip1, _, _ = tip_pose(q1, lay, tab, pose_constants(maps))
    else:
        # The solution's own pose too (_solve_order(pose=False)), in the same call: padded to
        # the next order, its strain field is the same (the Legendre basis is hierarchical).
        both, R, _ = tip_pose(torch.stack([q, q1]), lay, tab, pose_constants(maps))
        tip1 = both[1]
        res["tip"], res["R"] = both[0], R[0]
        res["converged"] = res["converged"] & torch.isfinite(both[0]).all(-1)
    # (The tip change is measured with the solve's own steps: with half of them, the pose
    # error of the new coefficients' finer strain variation dominated it below ~1e-8 m.)
    res["tip_coarse"] = _coarse_tips(q, disc, lay, maps, plan)
    est = (tip1 - res["tip"]).norm(dim=-1)
    est = torch.where(ok & torch.isfinite(est), est, torch.full_like(est, float("inf")))
    return est, q1


def _coarse_tips(q, disc, lay, maps, plan: Plan):
    """Tip positions ``(..., B, 3)`` of coordinates ``q (..., B, nq)`` with half of
    ``disc.n_magnus`` Magnus steps per section (``None`` when that count is odd)."""
    m = disc.n_magnus
    return None if m % 2 else _tips_with_steps(q, disc, lay, plan, m // 2)


def _tips_with_steps(q, disc, lay, plan: Plan, m: int):
    """Tip positions of ``q`` on the layout ``lay`` of ``disc`` with ``m`` Magnus steps per
    section; the pose constants of those nodes are kept with the layout (:meth:`Plan.cached`)."""
    tab = replace(disc, n_magnus=m).tables(q.dtype, q.device)
    const = plan.cached(disc, lay, f"pose_constants_{m}",
                        lambda: pose_node_constants(lay, tab["xm"]))
    return tip_pose(q, lay, tab, const)[0]


def _newton_step(q, prob: Problem):
    """One undamped Newton step (Jacobi-scaled; Cholesky, and LU where the Hessian is indefinite,
    as at an unstable equilibrium). Returns the new coordinates (``q`` where the step failed)
    and the success mask. The step runs on the compact coordinates (mechanics.build_maps);
    large batches go in cache-sized chunks of them (see newton.CHUNK_BYTES)."""
    cidx = prob.maps["cidx"]
    qc, ok = chunked(_one_newton_step, compact_q(q, cidx), prob)
    return torch.where(ok[:, None], expand_q(qc, cidx, q.shape[-1]), q), ok


def _one_newton_step(q, prob: Problem):
    qmask = prob.maps["qmask"]
    g, H = derivatives(q, prob)
    H.diagonal(dim1=-2, dim2=-1).add_(1.0 - qmask)
    act = active_index(qmask)
    # Cholesky on H itself (invariant under the Jacobi scaling); the LU fallback for an
    # indefinite H (an unstable equilibrium) pivots, so it gets the scaled system.
    rhs = -take(g, act)[..., None]
    L, info = torch.linalg.cholesky_ex(compact(H, act))
    sol = torch.cholesky_solve(rhs, L)
    indefinite = (info != 0).nonzero().flatten()
    if indefinite.numel():
        _, scale = scaled_residual(g[indefinite], H[indefinite],
                                   torch.ones_like(g[indefinite, 0]))
        a = None if act is None else act[indefinite]
        Hs, sc = compact_scaled(H[indefinite], scale, a)
        sol_lu, info_lu = torch.linalg.solve_ex(Hs, sc[..., None] * rhs[indefinite])
        sol[indefinite], info[indefinite] = sc[..., None] * sol_lu, info_lu
    q1 = q + expand(sol[..., 0], act, q.shape[-1]) * qmask
    ok = (info == 0) & torch.isfinite(q1).all(-1)
    return torch.where(ok[:, None], q1, q), ok


# A section this short (x the longest tube) counts as vanishing for _new_section_step.
_VANISHING = 1e-5


def _new_section_step(q, prob: Problem, new: torch.Tensor, length: float):
    """The coordinates ``new (B, nq)`` (bool), those of a section of vanishing length ``h`` that
    appears at a one-sided equilibrium, solved for with the others held: one Newton step on
    their block of the elastic energy (:func:`torchpvs.mechanics.section_grad_block`). Held
    coordinates are off by ``O(h)`` (the new section's pull on the rest), and the block's terms
    through the angle bases are ``O(h)`` of it, so the result is ``O(h)`` accurate, like the
    one-sided forces evaluated there, at the cost of a gradient, not a Hessian and its
    factorization. Unloaded problems only (a tip load's work moves with the section's strains
    at the same order). Returns the coordinates and the rows where it applied (new coordinates
    in one compact section, no guide twist among them, the section shorter than
    ``_VANISHING x length``, its block positive definite); other rows are returned unchanged."""
    maps = prob.maps
    cidx = maps["cidx"]
    B, nq = q.shape
    N = maps["bvec"].shape[2]
    S = maps["h"].shape[1]
    qc = compact_q(q, cidx)
    cn = (qc.shape[-1] - N) // S
    newc = torch.gather(new, 1, cidx)
    has = newc[:, N:].reshape(B, S, cn).any(-1)                           # (B, S)
    sec = has.to(torch.int8).argmax(-1)
    rows = torch.arange(B, device=q.device)
    g, blk = section_grad_block(qc, maps, sec)
    m = newc[:, N:].reshape(B, S, cn)[rows, sec].to(q.dtype)            # (B, C n)
    gs = g[:, N:].reshape(B, S, cn)[rows, sec] * m
    A = blk * m[:, :, None] * m[:, None, :] + torch.diag_embed(1.0 - m)
    L, info = torch.linalg.cholesky_ex(A)
    d = -torch.cholesky_solve(gs[..., None], L)[..., 0] * m
    ok = ((has.sum(-1) == 1) & ~newc[:, :N].any(-1) & (info == 0) & torch.isfinite(d).all(-1)
          & (maps["h"][rows, sec] <= _VANISHING * length))
    X = qc[:, N:].reshape(B, S, cn)
    X[rows, sec] = X[rows, sec] + d
    q1 = expand_q(torch.cat([qc[:, :N], X.reshape(B, -1)], -1), cidx, nq)
    return torch.where(ok[:, None], q1, q), ok


def _loaded(F, M, opts: SolverOptions) -> torch.Tensor:
    """``(B,)`` elements with a tip load (or forced load coordinates)."""
    return (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0) | opts.load_coordinates


class _Work:
    """Newton iterations spent by one call (the slowest element of each kernel call) and its
    wall-clock deadline (``time.perf_counter()`` time, or None)."""

    def __init__(self, limit: int, time_limit: float | None = None):
        self.limit, self.spent = limit, 0
        self.deadline = None if time_limit is None else time.perf_counter() + time_limit

    def spend(self, res) -> None:
        self.spent += int(res["iterations"].max()) if res["iterations"].numel() else 0

    @property
    def timed_out(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    @property
    def exhausted(self) -> bool:
        return self.spent >= self.limit or self.timed_out


def _load_ramp(scene, tubes, D, A, F, M, res, opts: SolverOptions, plan: Plan, q_init,
               work: _Work):
    """Load continuation for the loaded elements that did not converge: the tip load is applied
    in ``options.load_steps`` equal steps, each solve warm-started from the last, from the
    initial guess. Rows that converge at the full load replace the failed ones; ``res["ramp"]``
    records for each element how far its ramp got (fraction of the load; NaN: no ramp)."""
    B = D.shape[0]
    res["ramp"] = torch.full((B,), float("nan"), dtype=D.dtype, device=D.device)
    loaded = (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0)
    rows = (~res["converged"] & loaded).nonzero().flatten()
    n = opts.load_steps
    if rows.numel() == 0 or n < 2 or work.exhausted:
        return res
    Dr, Ar, Fr, Mr = D[rows], A[rows], F[rows], M[rows]
    q = None if q_init is None else q_init[rows]
    reached = torch.zeros(len(rows), dtype=D.dtype, device=D.device)
    alive = torch.ones(len(rows), dtype=torch.bool, device=D.device)
    sub = None
    for k in range(1, n + 1):
        t = k / n
        sub = _solve_order(scene, tube_rows(tubes, rows), Dr, Ar, Fr * t, Mr * t, res["order"],
                           res["disc"].n_magnus, opts, q, plan, deadline=work.deadline)
        work.spend(sub)
        alive = alive & sub["converged"]
        reached = torch.where(alive, torch.full_like(reached, t), reached)
        # Elements whose step failed keep their last converged state (their ramp ends there).
        q = sub["q"] if q is None else torch.where(alive[:, None], sub["q"], q)
        if not bool(alive.any()) or (work.exhausted and k < n):
            break
    res = dict(res)
    res["ramp"] = res["ramp"].clone()
    res["ramp"][rows] = reached
    done = alive & (reached == 1.0)
    if sub is not None and bool(done.any()) and sub["q"].shape[-1] == res["q"].shape[-1]:
        keep = rows[done]
        for key in ("q", "g", "converged", "residual", "iterations", "tip", "R", "verdict"):
            if res[key] is None or sub[key] is None:    # a kernel without stability verdicts
                res[key] = None
                continue
            merged = res[key].clone()
            merged[keep] = sub[key][done]
            res[key] = merged
        # The compact Hessians of the two solves may sit on different compact coordinates
        # (compaction depends on the batch): move the ramp's onto the solution's.
        nq = res["q"].shape[-1]
        merged = res["Hc"].clone()
        merged[keep] = compact_hessian(
            expand_hessian(sub["Hc"][done], sub["maps"]["cidx"][done], nq),
            res["maps"]["cidx"][keep])
        res["Hc"] = merged
    return res


def _refine_magnus(scene, tubes, D, A, F, M, res, opts: SolverOptions, plan: Plan,
                   work: _Work | None = None):
    """Choose the Magnus step count: ``m`` steps are kept when the tip moves less than
    ``accuracy / 2`` from half as many, and that change is the estimate reported (an upper
    one: where the 4th order holds, the m-step error is ~1/15 of it; one half-cost pose,
    usually already made by :func:`_order_estimate`); otherwise the steps are doubled until
    the tip moves less than ``accuracy / 2`` when they double again (the remaining error of
    the finer count is ~1/15 of that change). The equilibrium coordinates do not depend on the
    pose integration unless a tip load is applied, so the checks are tip recomputations; only
    a refinement re-solves (warm, usually one Newton step)."""
    m = res["disc"].n_magnus
    order_err = res.get("error_estimate")  # a fixed order has no basis estimate: stays NaN
    coarse = res.get("tip_coarse")
    if coarse is None:
        coarse = _coarse_tips(res["q"], res["disc"], res["lay"], res["maps"], plan)
    est = None if coarse is None else (coarse - res["tip"]).norm(dim=-1)
    if est is None or not bool((est <= opts.accuracy / 2).all()):
        while True:
            tip_fine = _tips_with_steps(res["q"], res["disc"], res["lay"], plan, 2 * m)
            est = (tip_fine - res["tip"]).norm(dim=-1)
            if bool((est <= opts.accuracy / 2).all()) or 2 * m > _MAGNUS_MAX \
                    or (work is not None and work.exhausted):
                break
            m *= 2
            ramp = res.get("ramp")
            res = _solve_order(scene, tubes, D, A, F, M, res["order"], m, opts, res["q"], plan,
                               deadline=None if work is None else work.deadline)
            if work is not None:
                work.spend(res)
            if ramp is not None:
                res["ramp"] = ramp
    if order_err is not None:
        res["error_estimate"] = order_err + est
    res["magnus_estimate"] = est
    return res


def _initial_q(initial, B: int, N: int):
    """Warm-start coordinates ``(B, nq)`` (or None) and the basis order and Magnus count they
    came from (None when unknown)."""
    if initial is None:
        return None, None, None
    q = initial.q if isinstance(initial, Equilibrium) else torch.as_tensor(initial)
    if q.ndim == 1:
        q = q[None]
    if not (q.is_floating_point() and bool(torch.isfinite(q).all())):
        raise ValueError("initial: the warm-start coordinates must be finite floating-point "
                         "numbers (an Equilibrium or a (B, nq) tensor)")
    if q.shape[0] not in (1, B):
        raise ValueError(f"initial has batch size {q.shape[0]}, expected 1 or {B}")
    n_from = (q.shape[-1] - N) // (2 * N * (2 + N))
    order = n_from - 1 if n_coordinates(N, n_from) == q.shape[-1] and n_from >= 1 else None
    magnus = (initial.context.discretization.n_magnus if isinstance(initial, Equilibrium)
              else None)
    return q.detach().expand(B, -1), order, magnus


# Largest predicted change of a strain coordinate x the robot's length [rad] that the rotation
# predictor may make; beyond it (near a fold, or after a large step) the warm start is used as
# it is, and Newton's damping and line search take over.
PREDICTOR_TRUST = 0.1


def _rotation_predictor(initial, q_init, scene, tubes, D, A, F, M, opts):
    """The warm start moved along the equilibrium branch to the new base rotations: a first-
    order (Euler) predictor ``dq = -H^-1 U_q,alpha dalpha`` from the warm-start equilibrium's
    own Hessian, for a call that changes only rotations (same robot, insertions and batch, no
    tip load). The potential depends on ``alpha_j`` and the guide twist ``w_j`` only through
    ``alpha_j + D_j w_j`` plus the guide's ``1/2 GJ_j D_j w_j^2``, so ``U_q,alpha_j =
    (H[:, w_j] - GJ_j D_j e_wj) / D_j`` and the predictor is ``dw = -dalpha / D`` plus
    ``H^-1 (GJ dalpha)`` on the guide twists: one factorization, no derivative evaluation.
    Its error is ``O(dalpha^2)``, so Newton starts closer (a warm 1 deg step: one iteration
    fewer). Elements whose base sits at the orifice (no guide twist), whose Hessian is not
    positive definite, or whose predicted step exceeds :data:`PREDICTOR_TRUST` keep the warm
    start as it is. It changes where Newton starts, not what it converges to."""
    if not isinstance(initial, Equilibrium) or q_init is None:
        return q_init
    ctx = initial.context
    if ctx is None:
        return q_init
    info = ctx.implicit
    Hc = info.Hc
    B, N = D.shape
    if (Hc is None or Hc.shape[0] != B or info.with_load or opts.load_coordinates
            or ctx.scene.tubes != scene.tubes or ctx.insertion.shape != D.shape
            or bool((F != 0).any() | (M != 0).any()) or not torch.equal(ctx.insertion, D)):
        return q_init
    qmask_c, cidx = info.qmask_c, info.cidx
    dA = A - ctx.rotation.to(A.dtype)
    dA = dA - (2 * math.pi) * torch.round(dA / (2 * math.pi))
    rhs = torch.zeros_like(qmask_c)
    rhs[:, :N] = tubes.GJ.expand(B, N) * dA
    # (in cache-sized row chunks, as the kernel: one factorization of a large batch at once
    # is slower)
    n = Hc.shape[-1]
    chunk = max(16, CHUNK_BYTES // (n * n * Hc.element_size()))
    x = torch.empty_like(rhs)
    fail = torch.empty(B, dtype=torch.int32, device=D.device)
    for s in range(0, B, chunk):
        L, fail[s:s + chunk] = torch.linalg.cholesky_ex(Hc[s:s + chunk])
        x[s:s + chunk] = torch.cholesky_solve(rhs[s:s + chunk, :, None], L)[..., 0]
    x[:, :N] -= dA / torch.where(D > 0, D, torch.ones_like(D))
    dq = expand_q(x * qmask_c, cidx, q_init.shape[-1])
    length = float(tubes.length.max())
    ok = ((fail == 0) & (qmask_c[:, :N] > 0).all(-1) & torch.isfinite(dq).all(-1)
          & (dq.abs().amax(-1) * length < PREDICTOR_TRUST))
    return torch.where(ok[:, None], q_init + dq, q_init)


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


def _solve_order(scene, tubes, D, A, F, M, order, n_magnus, opts, q_init, plan: Plan,
                 pose: bool = True, deadline: float | None = None):
    """Newton at one discretization. ``pose=False``: without the tip pose (``tip``, ``R``) and
    its finiteness in ``converged``; :func:`_order_estimate` then adds them. ``deadline``: a
    ``time.perf_counter()`` time after which the kernel takes no further step."""
    disc = replace(opts.discretization(order), n_magnus=n_magnus)
    N = scene.n_tubes
    dtype, device = D.dtype, D.device
    loaded = _loaded(F, M, opts)
    nq = n_coordinates(N, disc.n_basis)
    lay, maps = plan.layout(tubes, D, A, F, M, loaded, disc, nq)
    tab = disc.tables(dtype, device)
    with_load = bool(loaded.any())
    has_moment = bool((M.abs().sum(-1) > 0).any()) or opts.load_coordinates

    if q_init is not None:
        n_from = (q_init.shape[-1] - N) // (2 * N * (2 + N))
        if n_coordinates(N, n_from) != q_init.shape[-1]:
            raise ValueError(f"initial has {q_init.shape[-1]} coordinates, which matches no basis "
                             f"size for {N} tubes")
        q = _resize_q(q_init.to(dtype=dtype, device=device), N, n_from, disc.n_basis)
    else:
        q = _default_guess(lay, maps, tab, disc, N)
    q = q * lay.qmask
    L_char = (lay.ell.amax(-1) + D.amax(-1)).clamp(min=1e-6)           # (B,)
    prob = Problem(lay, tab, maps, with_load, has_moment)
    out = KERNELS[opts.kernel](q, prob, L_char, method=opts.method, tol=_newton_tol(scene, opts),
                               max_iter=opts.max_iter, deadline=deadline)
    res = {"q": out.q, "lay": lay, "tab": tab, "disc": disc, "order": order, "Hc": out.H,
           "g": out.g, "converged": out.converged, "verdict": out.verdict,
           "residual": out.residual, "iterations": out.iterations, "energy": out.energy,
           "D": D, "alpha": A, "F": F,
           "M": M, "loaded": loaded, "with_load": with_load, "has_moment": has_moment,
           "maps": maps}
    if pose:
        p, R, _ = tip_pose(out.q, lay, tab, pose_constants(maps))
        res.update(tip=p, R=R, converged=out.converged & torch.isfinite(p).all(-1))
    return res


def _newton_tol(scene: Scene, opts: SolverOptions) -> float:
    """The kernel's threshold on the scaled residual: ``options.tol``, tightened to ``accuracy
    / (100 L)`` (``L`` the longest tube [m]) where that is smaller. The residual is a strain
    correction times the robot length; its effect on the tip measured far below ``tol x L``
    (docs/performance.md), so the tightened value keeps it at least 100x inside the accuracy."""
    return min(opts.tol, opts.accuracy / (100.0 * max(t.length for t in scene.tubes)))


def _default_guess(lay, maps, tab, disc, N):
    """Torsionless guess: tubes keep their base angles, the backbone bends with the
    stiffness-weighted average of the rotated precurvatures (exact without torsion, eq. 31).
    Built on the kernel's compact sections (``maps``, :func:`torchpvs.mechanics.build_maps`):
    only they carry coordinates; the tube angles there are the base angles plus the twist of
    the prescribed sections before them."""
    B = lay.h.shape[0]
    nq = n_coordinates(N, disc.n_basis)
    cidx = maps["cidx"]
    S = maps["h"].shape[1]
    n = disc.n_basis
    start = start_angles(lay.psi0, maps["presc_inc"])                 # (B, S_full, N), q = 0
    sec = torch.div(cidx[:, N::(2 + N) * n] - N, (2 + N) * n, rounding_mode="floor")
    psi = torch.gather(start, 1, sec[:, :, None].expand(B, S, N))[:, :, None, :]
    us = maps["ustar"]                                                # (B, S, Q, N, 3)
    cs, sn = torch.cos(psi), torch.sin(psi)
    Rx = cs * us[..., 0] - sn * us[..., 1]
    Ry = sn * us[..., 0] + cs * us[..., 1]
    # stiffness-weighted (present tubes): EIw / EIws, the node weights cancel. Padded compact
    # sections have EIws = 0: the clamp must be representable in the dtype (1e-300 is 0 in
    # float32, and 0 / 0 made the whole guess NaN).
    wgt = maps["EIw"] / maps["EIws"][..., None].clamp(min=torch.finfo(maps["EIws"].dtype).tiny)
    u_avg = torch.stack([sum_dim(wgt * Rx, -1), sum_dim(wgt * Ry, -1)], -1)   # (B, S, Q, 2)
    a = 0.5 * torch.einsum("bsgd,gp,g->bsdp", u_avg, tab["phi_q"], tab["wq"])
    X = torch.zeros(B, S, 2 + N, n, dtype=a.dtype, device=a.device)
    X[:, :, :2, :] = a
    qc = torch.cat([torch.zeros(B, N, dtype=a.dtype, device=a.device), X.reshape(B, -1)], -1)
    return expand_q(qc, cidx, nq)


def with_options(options: SolverOptions | None, **changes) -> SolverOptions:
    """A copy of ``options`` (or the defaults) with fields changed."""
    return replace(options or SolverOptions(), **changes)
