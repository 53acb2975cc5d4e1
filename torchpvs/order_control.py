"""Stage 5 (driver) — the discretization of a solve: Newton at one basis order and Magnus step
count (:func:`solve_order`), the a posteriori order estimate that raises the order
(:func:`order_estimate`), the Magnus step-count check (:func:`refine_magnus`) and the
iteration and time budget they share (:class:`Work`). The per-element computations are the
kernel's (:mod:`torchpvs.kernel`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from .clock import work_clock
from .kernel import EAGER, KERNELS, Kernel
from .mechanics import Maps, pose_node_constants
from .newton import Problem
from .options import SolverOptions
from .plan import Plan
from .scene import Scene
from .sections import Discretization, Layout, Tables, n_coordinates

if TYPE_CHECKING:
    from .implicit import ImplicitContext

__all__ = ["MAGNUS_MAX", "SolveState", "Work", "coarse_tips", "loaded_rows", "newton_tol",
           "order_estimate", "refine_magnus", "resize_q", "solve_order", "tips_with_steps"]

MAGNUS_MAX = 256


@dataclass(eq=False)
class SolveState:
    """One solve of a batch at one discretization (:func:`solve_order` makes it, the only
    place one is made; ``B`` elements, ``N`` tubes, ``nq`` padded and ``nq_c`` compact
    coordinates, all tensors on the solve's device). The driver then fills in the fields
    after ``tip`` as it learns them, in place (or on a copy, :func:`dataclasses.replace`).

    Attributes:
        q: ``(B, nq)`` [1/m] the Newton solution (inactive coordinates 0).
        lay: the :class:`~torchpvs.sections.Layout` at ``D``.
        tab: the :class:`~torchpvs.sections.Tables` of ``disc``.
        disc: the :class:`~torchpvs.sections.Discretization` (basis size, quadrature, Magnus
            steps).
        order: the basis degree of ``disc``.
        maps: the :class:`~torchpvs.mechanics.Maps` of ``lay`` (compact coordinates).
        Hc: ``(B, nq_c, nq_c)`` [N·m³] the Hessian at ``q`` on the compact coordinates
            ``maps.cidx`` (identity on their inactive rows).
        g: ``(B, nq)`` [N·m²] the gradient of the potential at ``q``.
        converged: ``(B,)`` bool, Newton converged (and the tip pose is finite, once made).
        verdict: ``(B,)`` int8 stability verdict of the kernel (1 stable, 0 not, -1 none) or
            ``None`` (:class:`~torchpvs.newton.NewtonResult`).
        residual: ``(B,)`` the scaled residual (``SolverOptions.tol``).
        iterations: ``(B,)`` long, Newton iterations.
        energy: ``(B,)`` [J] the elastic energy at ``q`` where the kernel evaluated it (NaN
            elsewhere) or ``None``.
        D, alpha: ``(B, N)`` [m, rad] the insertions and base rotations solved at.
        F, M: ``(B, 3)`` [N, N·m] the tip load, base frame.
        loaded: ``(B,)`` bool, elements with load coordinates
            (:func:`loaded_rows`).
        with_load: some element is loaded (the potential includes the load's work).
        has_moment: a tip moment is modelled.
        tip: ``(B, 3)`` [m] the tip position and ``R`` ``(B, 3, 3)`` the tip frame, ``None``
            until the pose is made (``solve_order(pose=False)``: then by
            :func:`order_estimate`).
        tip_coarse: ``(B, 3)`` [m] the tip with half the Magnus steps (:func:`order_estimate`;
            ``None`` when not made or the step count is odd).
        error_estimate: ``(B,)`` [m] the a posteriori tip error, ``None`` at a fixed order.
        magnus_estimate: ``(B,)`` [m] the Magnus step-count check's tip change
            (:func:`refine_magnus`) or ``None``.
        ramp: ``(B,)`` the fraction of the tip load the load ramp reached (NaN: no ramp), or
            ``None`` where no ramp was considered (``torchpvs.solver``).
        work_exhausted, timed_out: the solve's iteration or time budget ran out
            (:class:`Work`).
        implicit_info: what the implicit backward needs
            (:class:`~torchpvs.implicit.ImplicitContext`), set last by the solver.
    """

    q: torch.Tensor
    lay: Layout
    tab: Tables
    disc: Discretization
    order: int
    maps: Maps
    Hc: torch.Tensor
    g: torch.Tensor
    converged: torch.Tensor
    verdict: torch.Tensor | None
    residual: torch.Tensor
    iterations: torch.Tensor
    energy: torch.Tensor | None
    D: torch.Tensor
    alpha: torch.Tensor
    F: torch.Tensor
    M: torch.Tensor
    loaded: torch.Tensor
    with_load: bool
    has_moment: bool
    tip: torch.Tensor | None = None
    R: torch.Tensor | None = None
    tip_coarse: torch.Tensor | None = None
    error_estimate: torch.Tensor | None = None
    magnus_estimate: torch.Tensor | None = None
    ramp: torch.Tensor | None = None
    work_exhausted: bool = False
    timed_out: bool = False
    implicit_info: ImplicitContext | None = None


def solve_order(scene, tubes, D, A, F, M, order, n_magnus, opts, q_init, plan: Plan,
                pose: bool = True, deadline: float | None = None) -> SolveState:
    """Newton at one discretization: its :class:`SolveState`. ``pose=False``: without the tip
    pose (``tip``, ``R``) and its finiteness in ``converged``; :func:`order_estimate` then adds
    them. ``deadline``: a :func:`~torchpvs.clock.work_clock` time after which the kernel takes
    no further step."""
    kernel = KERNELS[opts.kernel]
    disc = replace(opts.discretization(order), n_magnus=n_magnus)
    N = scene.n_tubes
    dtype, device = D.dtype, D.device
    loaded = loaded_rows(F, M, opts)
    nq = n_coordinates(N, disc.n_basis)
    lay, maps = plan.layout(tubes, D, A, F, M, loaded, disc, nq, kernel.layout)
    tab = disc.tables(dtype, device)
    with_load = bool(loaded.any())
    has_moment = bool((M.abs().sum(-1) > 0).any()) or opts.load_coordinates

    if q_init is not None:
        n_from = (q_init.shape[-1] - N) // (2 * N * (2 + N))
        if n_coordinates(N, n_from) != q_init.shape[-1]:
            raise ValueError(f"initial has {q_init.shape[-1]} coordinates, which matches no basis "
                             f"size for {N} tubes")
        q = resize_q(q_init.to(dtype=dtype, device=device), N, n_from, disc.n_basis)
    else:
        q = kernel.guess(lay, maps, tab, disc, N)
    q = q * lay.qmask
    L_char = (lay.ell.amax(-1) + D.amax(-1)).clamp(min=1e-6)           # (B,)
    prob = Problem(lay, tab, maps, with_load, has_moment)
    out = kernel.solve(q, prob, L_char, method=opts.method, tol=newton_tol(scene, opts),
                               max_iter=opts.max_iter, deadline=deadline)
    converged, tip, R = out.converged, None, None
    if pose:
        tip, R, _ = kernel.pose(out.q, lay, tab, maps.pose)
        converged = out.converged & torch.isfinite(tip).all(-1)
    return SolveState(q=out.q, lay=lay, tab=tab, disc=disc, order=order, maps=maps, Hc=out.H,
                      g=out.g, converged=converged, verdict=out.verdict, residual=out.residual,
                      iterations=out.iterations, energy=out.energy, D=D, alpha=A, F=F, M=M,
                      loaded=loaded, with_load=with_load, has_moment=has_moment, tip=tip, R=R)

def newton_tol(scene: Scene, opts: SolverOptions) -> float:
    """The kernel's threshold on the scaled residual: ``options.tol``, tightened to ``accuracy
    / (100 L)`` (``L`` the longest tube [m]) where that is smaller. The residual is a strain
    correction times the robot length; its effect on the tip measured far below ``tol x L``
    (docs/performance.md), so the tightened value keeps it at least 100x inside the accuracy."""
    return min(opts.tol, opts.accuracy / (100.0 * max(t.length for t in scene.tubes)))

def order_estimate(scene, tubes, D, A, F, M, res: SolveState, opts: SolverOptions,
                   plan: Plan):
    """A posteriori tip error of ``res`` at its order: one Newton step of the next order from
    the solution (the Legendre basis is hierarchical, so the solution pads exactly), and the
    tip change it makes. Newton converges quadratically from there, so the step lands within
    the square of the truncation error of the next order's solution: the estimate costs one
    gradient/Hessian evaluation, one factorization and one tip pose instead of a full solve.
    Returns ``(estimate (B,), coordinates at order + 1 to warm-start it)``. Also sets
    ``res.tip_coarse``, the solution's tip with half the Magnus steps, which the step-count
    check (:func:`refine_magnus`) compares with first (and ``res.tip``, ``res.R`` where the
    solve made no pose)."""
    kernel = KERNELS[opts.kernel]
    N = scene.n_tubes
    order = res.order + 1
    disc = replace(opts.discretization(order), n_magnus=res.disc.n_magnus)
    n_from = res.disc.n_basis
    nq = n_coordinates(N, disc.n_basis)
    lay, maps = plan.layout(tubes, D, A, F, M, res.loaded, disc, nq, kernel.layout)
    tab = disc.tables(D.dtype, D.device)
    prob = Problem(lay, tab, maps, res.with_load, res.has_moment)
    q = resize_q(res.q, N, n_from, disc.n_basis) * lay.qmask
    q1, ok = kernel.step(q, prob)
    if res.tip is not None:
        tip1, _, _ = kernel.pose(q1, lay, tab, maps.pose)
    else:
        # The solution's own pose too (solve_order(pose=False)), in the same call: padded to
        # the next order, its strain field is the same (the Legendre basis is hierarchical).
        both, R, _ = kernel.pose(torch.stack([q, q1]), lay, tab, maps.pose)
        tip1 = both[1]
        res.tip, res.R = both[0], R[0]
        res.converged = res.converged & torch.isfinite(both[0]).all(-1)
    # (The tip change is measured with the solve's own steps: with half of them, the pose
    # error of the new coefficients' finer strain variation dominated it below ~1e-8 m.)
    res.tip_coarse = coarse_tips(q, disc, lay, maps, plan, kernel)
    est = (tip1 - res.tip).norm(dim=-1)
    est = torch.where(ok & torch.isfinite(est), est, torch.full_like(est, float("inf")))
    return est, q1


def coarse_tips(q, disc, lay, maps, plan: Plan, kernel: Kernel = EAGER):
    """Tip positions ``(..., B, 3)`` of coordinates ``q (..., B, nq)`` with half of
    ``disc.n_magnus`` Magnus steps per section (``None`` when that count is odd)."""
    m = disc.n_magnus
    return None if m % 2 else tips_with_steps(q, disc, lay, plan, m // 2, kernel)


def tips_with_steps(q, disc, lay, plan: Plan, m: int, kernel: Kernel = EAGER):
    """Tip positions of ``q`` on the layout ``lay`` of ``disc`` with ``m`` Magnus steps per
    section; the pose constants of those nodes are kept with the layout (:meth:`Plan.cached`)."""
    tab = replace(disc, n_magnus=m).tables(q.dtype, q.device)
    const = plan.cached(disc, lay, ("pose_constants", m),
                        lambda: pose_node_constants(lay, tab.xm))
    return kernel.pose(q, lay, tab, const)[0]

def refine_magnus(scene, tubes, D, A, F, M, res: SolveState, opts: SolverOptions, plan: Plan,
                  work: Work | None = None) -> SolveState:
    """Choose the Magnus step count: ``m`` steps are kept when the tip moves less than
    ``accuracy / 2`` from half as many, and that change is the estimate reported (an upper
    one: where the 4th order holds, the m-step error is ~1/15 of it; one half-cost pose,
    usually already made by :func:`order_estimate`); otherwise the steps are doubled until
    the tip moves less than ``accuracy / 2`` when they double again (the remaining error of
    the finer count is ~1/15 of that change). The equilibrium coordinates do not depend on the
    pose integration unless a tip load is applied, so the checks are tip recomputations; only
    a refinement re-solves (warm, usually one Newton step)."""
    kernel = KERNELS[opts.kernel]
    m = res.disc.n_magnus
    order_err = res.error_estimate  # a fixed order has no basis estimate: stays NaN
    coarse = res.tip_coarse
    if coarse is None:
        coarse = coarse_tips(res.q, res.disc, res.lay, res.maps, plan, kernel)
    est = None if coarse is None else (coarse - res.tip).norm(dim=-1)
    if est is None or not bool((est <= opts.accuracy / 2).all()):
        while True:
            tip_fine = tips_with_steps(res.q, res.disc, res.lay, plan, 2 * m, kernel)
            est = (tip_fine - res.tip).norm(dim=-1)
            if bool((est <= opts.accuracy / 2).all()) or 2 * m > MAGNUS_MAX \
                    or (work is not None and work.exhausted):
                break
            m *= 2
            ramp = res.ramp
            res = solve_order(scene, tubes, D, A, F, M, res.order, m, opts, res.q, plan,
                              deadline=None if work is None else work.deadline)
            if work is not None:
                work.spend(res)
            if ramp is not None:
                res.ramp = ramp
    if order_err is not None:
        res.error_estimate = order_err + est
    res.magnus_estimate = est
    return res

def resize_q(q: torch.Tensor, N: int, n_from: int, n_to: int) -> torch.Tensor:
    """Map coordinates between basis sizes (the Legendre basis is hierarchical: pad/truncate)."""
    B = q.shape[0]
    w = q[:, :N]
    X = q[:, N:].reshape(B, 2 * N, 2 + N, n_from)
    if n_to >= n_from:
        X = torch.nn.functional.pad(X, (0, n_to - n_from))
    else:
        X = X[..., :n_to]
    return torch.cat([w, X.reshape(B, -1)], -1)

def loaded_rows(F, M, opts: SolverOptions) -> torch.Tensor:
    """``(B,)`` elements with a tip load (or forced load coordinates)."""
    return (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0) | opts.load_coordinates


class Work:
    """Newton iterations spent by one call (the slowest element of each kernel call) and its
    wall-clock deadline (a :func:`torchpvs.clock.work_clock` time, or None)."""

    def __init__(self, limit: int, time_limit: float | None = None):
        self.limit, self.spent = limit, 0
        self.deadline = None if time_limit is None else work_clock() + time_limit

    def spend(self, res: SolveState) -> None:
        self.spent += int(res.iterations.max()) if res.iterations.numel() else 0

    @property
    def timed_out(self) -> bool:
        return self.deadline is not None and work_clock() > self.deadline

    @property
    def exhausted(self) -> bool:
        return self.spent >= self.limit or self.timed_out
