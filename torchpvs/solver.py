"""Stage 5 — the batched solve: ``torchpvs.solve(scene, ...) -> Equilibrium``.

One entry point in the spirit of ``torchdiffeq.odeint``: the scene gives the robot, keyword tensors
override its actuation and load (and batch it), ``options`` picks accuracy and method. The
driver: inputs (:mod:`torchpvs.inputs`), where to start (:mod:`torchpvs.predictor`), the order
and Magnus loop (:mod:`torchpvs.order_control`), the load ramp and the re-solves of the
one-sided forces (here), every per-element computation through the kernel of
``options.kernel`` (:mod:`torchpvs.kernel`).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace

import numpy as np
import torch

from .equilibrium import Equilibrium
from .forces import ForceState, paper_scope_check
from .fused import control_blocks, fused_solve
from .implicit import ImplicitContext, differentiable_outputs
from .inputs import scene_inputs
from .kernel import KERNELS
from .mechanics import compact_hessian, expand_hessian
from .newton import Problem
from .options import AccuracyWarning, SolverError, SolverOptions
from .order_control import (
    SolveState,
    Work,
    loaded_rows,
    order_estimate,
    refine_magnus,
    solve_order,
)
from .plan import MAGNUS_START, ORDER_START, Plan, plan_for, tube_tensors
from .predictor import initial_q, rotation_predictor
from .scene import Scene, load_scene
from .sections import TubeTensors, tube_rows

__all__ = ["solve", "solve_tensors"]


# (frozen: one shared instance; building and validating it cost ~30 us a call)
_DEFAULT_OPTIONS = SolverOptions()


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
    opts = options or _DEFAULT_OPTIONS
    D, A, F, M, dtype, device = scene_inputs(scene, insertion, rotation, tip_force, tip_moment,
                                             dtype=opts.dtype, device=opts.device)
    if opts.force_model == "paper" and opts.compute_forces:
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
    needs_grad = torch.is_grad_enabled() and (
        D.requires_grad or A.requires_grad or F.requires_grad or M.requires_grad
        or any(t.requires_grad for t in tubes.tensors()))
    # U*(alpha) is 2 pi-periodic in every base rotation and q holds no absolute angle: solving
    # at alpha - 2 pi k (k constant, no gradient) keeps cos/sin accurate for large angles.
    # (k is 0 for every angle within +-pi: nothing to subtract, checked in numpy on the CPU)
    if not (A.device.type == "cpu" and not A.requires_grad
            and bool(np.abs(A.numpy()).max() <= math.pi)):
        A = A - (2 * math.pi) * torch.round(A.detach() / (2 * math.pi))
    D_in, A_in, F_in, M_in, tubes_in = D, A, F, M, tubes
    # Owned copies: the plan keeps layouts that refer to them (a caller may reuse its buffers).
    D, A, F, M = (t.detach().clone() for t in (D, A, F, M))
    if needs_grad:
        tubes = tubes.map(torch.Tensor.detach)
    # The common case (warm or cold, no load, every check passing at the first order) in two
    # compiled calls (torchpvs.fused); None where it does not apply: the rounds below.
    fused = None if needs_grad else fused_solve(scene, tubes, D, A, F, M, opts, initial,
                                                plan)
    if fused is not None:
        res = fused.res
    else:
        res = _rounds(scene, tubes, D, A, F, M, opts, initial, plan, needs_grad)
    diff = None
    # The Hessian is kept on the kernel's compact coordinates (implicit.full_hessian pads it).
    info = ImplicitContext(
        qmask=res.lay.qmask, loaded=res.loaded, disc=res.disc, tab=res.tab,
        with_load=res.with_load, has_moment=res.has_moment, ridge=opts.backward_ridge,
        singular_tol=opts.singular_tol, Hc=res.Hc, cidx=res.maps.cidx, qmask_c=res.maps.qmask)
    res.implicit_info = info
    if needs_grad:
        diff = differentiable_outputs(res.q, info, D_in, A_in, F_in, M_in, tubes_in)
    elapsed = time.perf_counter() - t0

    resolver = SolutionResolver(scene, tubes, D, A, F, M, res, opts, plan)
    # (the fused path's few outputs are built outside inference mode: nothing to release
    # unless its layout came from a plan entry the rounds made in inference mode)
    if fused is not None:
        eq = Equilibrium.from_solution(scene, tubes, res, opts, elapsed, diff, plan, resolver,
                                       outputs=fused)
    else:
        with torch.inference_mode(not needs_grad):
            eq = Equilibrium.from_solution(scene, tubes, res, opts, elapsed, diff, plan,
                                           resolver)
    if not needs_grad and (fused is None or res.lay.qmask.is_inference()
                           or res.maps.cidx.is_inference()):
        eq = eq.released()
    # (the checks below in numpy where the flags are CPU tensors: a single solve's glue)
    cpu = eq.converged.device.type == "cpu"
    conv = eq.converged.numpy() if cpu else eq.converged
    if opts.order is None and opts.on_failure != "ignore":
        short = conv & ~(eq.accuracy_met.numpy() if cpu else eq.accuracy_met)
        if bool(short.any()):
            b = int(short.nonzero()[0][0]) if cpu else int(short.nonzero()[0])
            warnings.warn(
                f"torchpvs.solve: requested accuracy {opts.accuracy:g} m not reached for "
                f"{int(short.sum())} of {B} element(s) (first: element {b}, error estimate "
                f"{float(eq.error_estimate[b]):.3g} m at order {eq.order} "
                f"(max_order={opts.max_order}), {res.disc.n_magnus} Magnus steps); see "
                f"Equilibrium.accuracy_met", AccuracyWarning, stacklevel=2)
    if opts.on_failure != "ignore":
        n_failed = int((~conv).sum())
        if n_failed:
            first = int((~eq.converged).nonzero()[0])
            msg = (f"torchpvs.solve: {n_failed} of {B} element(s) did not converge "
                   f"(first: element {first}: {eq.reason[first]})")
            if opts.on_failure == "raise":
                raise SolverError(msg)
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
    return eq


def _rounds(scene, tubes, D, A, F, M, opts: SolverOptions, initial, plan: Plan,
            needs_grad: bool):
    """The driver's rounds: predictor, Newton, the order check, the load ramp, the Magnus
    check; the final :class:`~torchpvs.order_control.SolveState` with its work flags."""
    B = D.shape[0]
    # Without a gradient to carry, the solve runs in inference mode (no autograd bookkeeping:
    # ~20% less time per torch op, which bounds small batches); what it returns is released
    # to ordinary tensors (Equilibrium.released).
    with torch.inference_mode(not needs_grad):
        q_init, init_order, init_magnus = initial_q(initial, B, scene.n_tubes)
        q_init = rotation_predictor(initial, q_init, scene, tubes, D, A, F, M, opts)
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
        work = Work(opts.max_total_iter, opts.time_limit)
        prev = None
        while True:
            # With the automatic order and no load (no load ramp), the solution's tip pose is
            # made by the order check, together with the next order's (one pose call).
            joint = opts.order is None and not bool(loaded_rows(F, M, opts).any())
            res = solve_order(scene, tubes, D, A, F, M, order, n_magnus, opts, q_init, plan,
                               pose=not joint, deadline=work.deadline)
            work.spend(res)
            if prev is None:
                res = _load_ramp(scene, tubes, D, A, F, M, res, opts, plan, q_init, work)
            elif bool((prev.converged & ~res.converged).any()):
                # A higher order lost an equilibrium the lower one had: keep the lower order's
                # batch (its estimate then says the accuracy is not met) rather than a failure.
                res = prev
                break
            if opts.order is not None:
                break
            est, q_next = order_estimate(scene, tubes, D, A, F, M, res, opts, plan)
            res.error_estimate = est
            # Elements that did not converge are reported as such; a higher order won't help.
            if bool(((est <= budget) | ~res.converged).all()) or order >= opts.max_order \
                    or work.exhausted:
                break
            order += 1
            q_init = q_next
            prev = res
        if opts.n_magnus is None:
            res = refine_magnus(scene, tubes, D, A, F, M, res, opts, plan, work)
    res.work_exhausted = work.exhausted
    res.timed_out = work.timed_out
    return res


# The per-element fields of a SolveState that a load ramp's rows replace.
_RAMP_MERGED = ("q", "g", "converged", "residual", "iterations", "tip", "R", "verdict")


def _load_ramp(scene, tubes, D, A, F, M, res: SolveState, opts: SolverOptions, plan: Plan,
               q_init, work: Work) -> SolveState:
    """Load continuation for the loaded elements that did not converge: the tip load is applied
    in ``options.load_steps`` equal steps, each solve warm-started from the last, from the
    initial guess. Rows that converge at the full load replace the failed ones (on a copy of
    ``res``); ``ramp`` records for each element how far its ramp got (fraction of the load;
    NaN: no ramp)."""
    B = D.shape[0]
    res.ramp = torch.full((B,), float("nan"), dtype=D.dtype, device=D.device)
    loaded = (F.abs().sum(-1) > 0) | (M.abs().sum(-1) > 0)
    rows = (~res.converged & loaded).nonzero().flatten()
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
        sub = solve_order(scene, tube_rows(tubes, rows), Dr, Ar, Fr * t, Mr * t, res.order,
                          res.disc.n_magnus, opts, q, plan, deadline=work.deadline)
        work.spend(sub)
        alive = alive & sub.converged
        reached = torch.where(alive, torch.full_like(reached, t), reached)
        # Elements whose step failed keep their last converged state (their ramp ends there).
        q = sub.q if q is None else torch.where(alive[:, None], sub.q, q)
        if not bool(alive.any()) or (work.exhausted and k < n):
            break
    res = replace(res, ramp=res.ramp.clone())
    res.ramp[rows] = reached
    done = alive & (reached == 1.0)
    if sub is not None and bool(done.any()) and sub.q.shape[-1] == res.q.shape[-1]:
        keep = rows[done]
        for name in _RAMP_MERGED:
            mine, theirs = getattr(res, name), getattr(sub, name)
            if mine is None or theirs is None:    # a kernel without stability verdicts
                setattr(res, name, None)
                continue
            merged = mine.clone()
            merged[keep] = theirs[done]
            setattr(res, name, merged)
        # The compact Hessians of the two solves may sit on different compact coordinates
        # (compaction depends on the batch): move the ramp's onto the solution's.
        nq = res.q.shape[-1]
        merged = res.Hc.clone()
        merged[keep] = compact_hessian(
            expand_hessian(sub.Hc[done], sub.maps.cidx[done], nq), res.maps.cidx[keep])
        res.Hc = merged
    return res


@dataclass(frozen=True, eq=False)
class SolutionResolver:
    """The re-solves near one solve's solution (:class:`torchpvs.equilibrium.Resolver`): what
    the one-sided forces and :meth:`Equilibrium.solve_again` call back into. ``res`` is the
    solve's :class:`~torchpvs.order_control.SolveState` (its ``q``, layout, tables,
    discretization and load flags)."""

    scene: Scene
    tubes: TubeTensors
    D: torch.Tensor
    A: torch.Tensor
    F: torch.Tensor
    M: torch.Tensor
    res: SolveState
    options: SolverOptions
    plan: Plan

    def near(self, Dn: torch.Tensor, sel: torch.Tensor) -> ForceState:
        """See :meth:`torchpvs.equilibrium.Resolver.near`."""
        # Forces at equilibria a distance delta ~ 1e-7 m away (insertions Dn, rows sel of the
        # batch). Where the section structure there equals this one (same active
        # coordinates), q* moves by O(delta) and dU*/dD = dU/dD at fixed q to O(delta)
        # (envelope theorem): no solve. Where a section of length delta appears, its
        # coordinates are solved for with the others held (the kernel's section_step:
        # O(delta), like the rest), or where that does not apply (a tip load, a guide twist
        # appearing), by ONE Newton step from q.
        res, opts, tubes = self.res, self.options, self.tubes
        kernel = KERNELS[opts.kernel]
        An, Fn, Mn, q0 = self.A[sel], self.F[sel], self.M[sel], res.q[sel]
        disc = res.disc
        nq = q0.shape[-1]
        loaded = loaded_rows(Fn, Mn, opts)
        lay, maps = self.plan.layout(tube_rows(tubes, sel), Dn, An, Fn, Mn, loaded, disc, nq,
                                     kernel.layout)
        q1 = q0 * lay.qmask
        moved = (lay.qmask != res.lay.qmask[sel]).any(-1).nonzero().flatten()
        if moved.numel():
            first, k = int(moved[0]), moved.numel()
            if int(moved[-1]) - first + 1 == k:      # usually one run of rows: views, no copy
                moved = slice(first, first + k)
            prob = Problem(lay, res.tab, maps, res.with_load, res.has_moment).subset(moved)
            q1 = q1.clone()
            qm, ok = q1[moved], torch.zeros(q1[moved].shape[0], dtype=torch.bool,
                                            device=q1.device)
            if not res.with_load:
                new = (lay.qmask[moved] > 0) & ~(res.lay.qmask[sel][moved] > 0)
                qm, ok = kernel.section_step(qm, prob, new, float(tubes.length.max()))
            rest = (~ok).nonzero().flatten()
            if rest.numel():
                qm = qm.clone()
                qm[rest] = kernel.step(qm[rest], prob.subset(rest))[0]
            q1[moved] = qm
        return ForceState(q=q1, D=Dn, alpha=An, F=Fn, M=Mn, loaded=loaded, lay=lay, tab=res.tab,
                          disc=disc, with_load=res.with_load, has_moment=res.has_moment)

    def control_blocks(self, eq: Equilibrium):
        """See :meth:`torchpvs.equilibrium.Resolver.control_blocks`."""
        return control_blocks(eq)

    def again(self, options: SolverOptions, initial=None) -> Equilibrium:
        """See :meth:`torchpvs.equilibrium.Resolver.again`."""
        return solve_tensors(self.scene, self.tubes, self.D, self.A, self.F, self.M, options,
                             initial, self.plan)

    def at(self, insertion: torch.Tensor, rows: torch.Tensor, initial: torch.Tensor,
           options: SolverOptions) -> Equilibrium:
        """See :meth:`torchpvs.equilibrium.Resolver.at`."""
        # a private plan: the side's insertions must not evict this solve's layout from the
        # shared plan (the next control step at these insertions would rebuild it)
        return solve_tensors(self.scene, tube_rows(self.tubes, rows), insertion, self.A[rows],
                             self.F[rows], self.M[rows], options, initial, None)
