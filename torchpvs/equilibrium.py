"""Stage 7 — outputs: the :class:`Equilibrium` returned by :func:`torchpvs.solve`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from .basis import legendre_basis
from .batch_linalg import active_index, compact_scaled, take
from .forces import ForceState, equilibrium_forces, paper_actuation
from .jacobians import control_jacobians
from .kernel import KERNELS
from .lie import exp_se3
from .mechanics import (
    angle_offsets,
    compact_q,
    elastic_energy_maps,
    magnus_twists,
    node_fields,
    section_start_poses,
    split_q,
)
from .newton import stability_threshold

if TYPE_CHECKING:
    from .fused import FusedSolve
    from .implicit import DifferentiableOutputs, ImplicitContext
    from .options import SolverOptions
    from .order_control import SolveState
    from .plan import Plan
    from .scene import Scene
    from .sections import Discretization, Layout, Tables, TubeTensors

__all__ = ["Equilibrium", "SolveContext"]


def _failure_reason(res: SolveState, opts, b: int) -> str:
    text = (f"residual {float(res.residual[b]):.3g} > tol after {int(res.iterations[b])} "
            f"iterations at order {res.order}")
    ramp = res.ramp
    if ramp is not None and not math.isnan(float(ramp[b])):
        text += (f"; the load ramp ({opts.load_steps} steps) reached {float(ramp[b]):.0%} of "
                 f"the tip load")
    if res.timed_out:
        text += f"; time limit time_limit={opts.time_limit:g} s reached"
    elif res.work_exhausted:
        text += f"; work limit max_total_iter={opts.max_total_iter} reached"
    return text + "; try method='minimize', more max_iter, or a different initial guess"


def _scaled_stiffness(H: torch.Tensor, qmask: torch.Tensor):
    """``S H S`` of a Hessian ``H (B, n, n)`` with its active mask ``qmask (B, n)`` (on the
    padded or the kernel's compact coordinates), ``S = diag(|H_ii|^-1/2)`` on the active
    coordinates, gathered to each element's active coordinates
    (:func:`torchpvs.batch_linalg.compact`, ``(B, nA, nA)``; padding rows are identity rows),
    and the
    gathered active mask ``(B, nA)`` as float."""
    d = H.diagonal(dim1=-2, dim2=-1).abs()
    active = qmask * (d > 0)
    S = torch.where(active > 0, d.clamp(min=torch.finfo(H.dtype).tiny) ** -0.5,
                    torch.ones_like(d))
    act = active_index(qmask)
    return compact_scaled(H, S, act)[0], take(active, act)


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    """Wrap to ``(-pi, pi]``."""
    return math.pi - torch.remainder(math.pi - angle, 2 * math.pi)


class Resolver(Protocol):
    """The solves an :class:`Equilibrium` calls back into, near its own solution. The solver
    gives one (:class:`torchpvs.solver.SolutionResolver`), so that this module and
    :mod:`torchpvs.forces` never import the driver."""

    def near(self, insertion: torch.Tensor, rows: torch.Tensor) -> ForceState:
        """The equilibria at insertions ``insertion (k, N)`` [m] of batch rows ``rows (k,)``,
        a distance ~1e-7 m from the solution (the one-sided forces at kinks), as a
        :class:`~torchpvs.forces.ForceState` of ``k`` rows (its ``lay`` the layout at
        ``insertion``, or ``None``)."""
        ...

    def again(self, options: SolverOptions, initial: Any = None) -> Equilibrium:
        """The same robot, actuation and load solved with other ``options``."""
        ...

    def control_blocks(self, eq: Equilibrium) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(actuator stiffness (B, 2N, 2N), tip Jacobian (B, 6, 2N))`` of ``eq`` (this
        solve's equilibrium) by a compiled path where one applies, else None
        (:mod:`torchpvs.jacobians` then takes its torch closed forms)."""
        ...

    def at(self, insertion: torch.Tensor, rows: torch.Tensor, initial: torch.Tensor,
           options: SolverOptions) -> Equilibrium:
        """Batch rows ``rows (k,)`` solved at other insertions ``insertion (k, N)`` [m] (same
        rotations and load) with ``options``, warm from coordinates ``initial (k, nq)``: the
        one-sided control Jacobians at kinks (:mod:`torchpvs.jacobians`)."""
        ...


@dataclass(frozen=True, eq=False)
class SolveContext:
    """What an :class:`Equilibrium`'s solve used, which its methods (backbone, Jacobians,
    stability) and later solves (warm starts, re-solves) work from. ``B`` elements, ``N``
    tubes, ``nq`` coordinates; tensors on the solve's device, without gradient.

    Attributes:
        scene: the robot (its tubes) the equilibrium was solved for.
        tubes: the tube properties as tensors (:class:`~torchpvs.sections.TubeTensors`,
            ``(1, N)`` or ``(B, N)``; ``coef (., N, 3, P)``).
        layout: the sections at the solution's insertions
            (:class:`~torchpvs.sections.Layout`, every field with the leading ``B``).
        tables: the quadrature and basis tables of ``discretization``
            (:class:`~torchpvs.sections.Tables`).
        discretization: the basis size, quadrature and Magnus step count of the solution.
        insertion, rotation: ``(B, N)`` [m, rad] the actuation solved at (the rotation
            reduced by whole turns, as solved).
        tip_force, tip_moment: ``(B, 3)`` [N, N·m] the tip load, base frame.
        implicit: the stiffness at the solution and what the implicit backward needs
            (:class:`~torchpvs.implicit.ImplicitContext`, with its adjoint factorization
            cached on first use).
        options: the ``SolverOptions`` of the solve.
        plan: the robot plan it reused (:class:`~torchpvs.plan.Plan`) or ``None``.
        resolver: the re-solves near this solution (:class:`Resolver`, given by the solver;
            see :meth:`Equilibrium.solve_again`), or ``None``.
    """

    scene: Scene
    tubes: TubeTensors
    layout: Layout
    tables: Tables
    discretization: Discretization
    insertion: torch.Tensor
    rotation: torch.Tensor
    tip_force: torch.Tensor
    tip_moment: torch.Tensor
    implicit: ImplicitContext
    options: SolverOptions
    plan: Plan | None = None
    resolver: Resolver | None = None

    @property
    def actuation_and_load(self) -> tuple[torch.Tensor, ...]:
        """``(insertion, rotation, tip_force, tip_moment)``, the inputs of the solve in the
        order the mechanics functions take them (``D, alpha, F, M``)."""
        return self.insertion, self.rotation, self.tip_force, self.tip_moment

    def map_tensors(self, fn) -> SolveContext:
        """A copy with ``fn`` applied to every per-solve tensor (layout, actuation, load and
        the implicit context; the tube tensors and tables, shared between solves, as they
        are)."""
        return replace(self, layout=type(self.layout)(*map(fn, self.layout)),
                       implicit=self.implicit.map_tensors(fn),
                       insertion=fn(self.insertion), rotation=fn(self.rotation),
                       tip_force=fn(self.tip_force), tip_moment=fn(self.tip_moment))


@dataclass(frozen=True, eq=False)
class Equilibrium:
    """A batch of equilibria (``B`` elements, ``N`` tubes), all tensors on the solve's device.

    Attributes:
        q: ``(B, nq)`` generalized coordinates (strains [1/m]; inactive ones are 0).
        tip_position: ``(B, 3)`` [m], base frame.
        tip_rotation: ``(B, 3, 3)`` material frame of the tube forming the tip, base frame.
        relative_rotation_at_outer_tip: ``(B, N-1)`` [rad] ``theta_j(l_1) = psi_j - psi_1`` at the
            outer tube's distal end, wrapped to ``(-pi, pi]``.
        energy: ``(B,)`` [J] stored elastic energy minus the potential of the tip force.
        actuation_forces: ``(B, N)`` [N] ``dU*/dD_j`` along increasing ``D_j`` (retraction;
            positive = the actuator pulls back), docs/conventions.md.
        actuation_forces_insertion: ``(B, N)`` [N] the derivative for decreasing ``D_j``
            (insertion). Equal to ``actuation_forces`` where ``U*(D)`` is smooth; different where
            it has a kink; NaN where insertion is impossible (``D_j = 0`` or ``D_j = D_{j-1}``).
        force_kink: ``(B, N)`` bool, ``U*(D_j)`` has a kink here (a tube's base, straight-to-
            curved transition or end at the orifice): the two one-sided forces differ.
        actuation_torques: ``(B, N)`` [N·m] ``dU*/dalpha_j``.
        converged: ``(B,)`` bool; ``reason``: per-element text ("converged" or why not).
        residual_norm: ``(B,)`` scaled residual (see ``SolverOptions.tol``).
        iterations: ``(B,)`` Newton iterations (at the final order).
        stable: ``(B,)`` bool, the Hessian over the active coordinates is positive definite
            (decided on its nondimensional form, see ``min_stiffness_eigenvalue``). False where
            the solve did not converge (no equilibrium to judge; ``as_contract`` gives null).
        min_stiffness_eigenvalue: ``(B,)`` smallest eigenvalue of the Jacobi-scaled
            (dimensionless) Hessian; computed on first access.
        dofs: ``(B,)`` number of active generalized coordinates.
        order: basis degree used; ``error_estimate``: ``(B,)`` [m] a posteriori tip error: the
            tip change of one Newton step of the next order (automatic order selection) plus
            the tip change from halving the Magnus steps, or from doubling them where the count
            was refined (automatic ``n_magnus``); NaN when the order is fixed.
        accuracy_met: ``(B,)`` bool, ``error_estimate <= options.accuracy``; False where no
            estimate exists (a fixed order). An automatic solve that cannot meet the request
            (``max_order`` or the Magnus cap reached) also warns.
        solve_time_s: wall time of the solve [s].
        context: the :class:`SolveContext` of the solve (what it used; see there).
    """

    q: torch.Tensor
    tip_position: torch.Tensor
    tip_rotation: torch.Tensor
    relative_rotation_at_outer_tip: torch.Tensor
    energy: torch.Tensor
    actuation_forces: torch.Tensor | None
    actuation_torques: torch.Tensor | None
    actuation_forces_insertion: torch.Tensor | None
    force_kink: torch.Tensor
    converged: torch.Tensor
    residual_norm: torch.Tensor
    iterations: torch.Tensor
    stable: torch.Tensor
    dofs: torch.Tensor
    order: int
    error_estimate: torch.Tensor
    accuracy_met: torch.Tensor
    solve_time_s: float
    reason: tuple[str, ...]
    context: SolveContext | None = field(repr=False, default=None)
    _min_eig: torch.Tensor | None = field(repr=False, default=None)

    @property
    def min_stiffness_eigenvalue(self) -> torch.Tensor:
        """``(B,)`` smallest eigenvalue of the nondimensional stiffness ``S H S`` over the active
        coordinates, ``S = diag(H_ii^-1/2)`` (dimensionless, computed on first access).

        The scaling is a congruence, so the sign pattern (stable or not) is that of ``H``
        itself (Sylvester's law of inertia), but the value no longer depends on units, on the
        robot's physical scale, or on near-empty sections whose coordinates carry stiffness in
        proportion to their length. ``stable`` is ``min_stiffness_eigenvalue > tau`` with
        ``tau = 0.01 sqrt(eps)`` of the dtype (1.5e-10 in float64). NaN without coordinates.
        """
        ev = self._min_eig
        if ev is None:
            info = self.context.implicit
            with torch.no_grad():
                Hs, active = _scaled_stiffness(info.Hc, info.qmask_c)
                # Inactive rows (identity) are pushed above the spectrum: never the minimum.
                ev = torch.linalg.eigvalsh(Hs + torch.diag_embed(1.0 - active) * 10.0)[:, 0]
                # No coordinates (a robot entirely in the guide): no stiffness to speak of.
                ev = torch.where(active.sum(-1) > 0, ev, torch.full_like(ev, float("nan")))
            object.__setattr__(self, "_min_eig", ev)   # a cache: frozen otherwise
        return ev

    def solve_again(self, options: SolverOptions, initial: Any = None) -> Equilibrium:
        """The same robot, actuation and load solved with other ``options`` (warm from
        ``initial``, e.g. this equilibrium; cold when ``None``): how
        :func:`torchpvs.jacobians.control_jacobians` gets the load coordinates of an unloaded
        solve."""
        if self.context is None or self.context.resolver is None:
            raise ValueError("Equilibrium.solve_again: this equilibrium carries no solve to "
                             "repeat")
        return self.context.resolver.again(options, initial)

    def released(self) -> Equilibrium:
        """This equilibrium with every inference-mode tensor (its fields and its context)
        cloned to an ordinary tensor, so that callers can modify the outputs in place and use
        them in autograd graphs (inference tensors allow neither outside inference mode); the
        solver returns it so. The containers are walked by hand: a generic pytree map cost
        0.3 ms per call, 5% of a single solve."""
        def out(x):
            return x.clone() if isinstance(x, torch.Tensor) and x.is_inference() else x

        changes = {f.name: out(getattr(self, f.name)) for f in fields(self)
                   if f.name != "context"}
        ctx = None if self.context is None else self.context.map_tensors(out)
        return replace(self, **changes, context=ctx)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def batch_size(self) -> int:
        return self.q.shape[0]

    # ------------------------------------------------------------------------------------------
    @classmethod
    def from_solution(cls, scene, tubes, res: SolveState, opts, elapsed: float,
                      diff: DifferentiableOutputs | None = None, plan=None,
                      resolver: Resolver | None = None,
                      outputs: FusedSolve | None = None) -> Equilibrium:
        """The solver's constructor: outputs of a converged solve ``res``
        (:class:`~torchpvs.order_control.SolveState`; ``diff``: the same outputs as
        differentiable functions of the inputs, when a gradient is wanted). Re-solves are
        handed in by the solver as a :class:`Resolver`, so that this module never imports
        it (kept as ``context.resolver``). ``outputs``: the forces and relative rotations
        where the fused path (:mod:`torchpvs.fused`) computed them already."""
        q, lay, tab = res.q, res.lay, res.tab
        B = q.shape[0]
        qmask = lay.qmask
        with torch.no_grad():
            # Tube angles at the outer tube's end: no node math needed (the prescribed sections'
            # twist is a constant of the layout, kept with the maps).
            if outputs is not None:
                rel = outputs.rel
            else:
                w, _, c = split_q(q, lay)
                psi0, inc = angle_offsets(w, c, lay, res.maps.presc_inc)
                psi_l1 = psi0 + (inc * lay.before_l1[..., None]).sum(-2)
                rel = _wrap(psi_l1[:, 1:] - psi_l1[:, :1])
            # Stability on the nondimensional stiffness (see min_stiffness_eigenvalue): positive
            # definite beyond a threshold set by the precision alone. The kernel's saddle test
            # factored exactly that at convergence (its verdict); one Cholesky for the elements
            # without one. The eigenvalue itself is computed only when asked for.
            verdict = res.verdict
            if verdict is None:
                verdict = torch.full((B,), -1, dtype=torch.int8, device=q.device)
            if outputs is not None:
                stable, todo = outputs.stable, ()
            else:
                stable = verdict == 1
                todo = (verdict < 0).nonzero().flatten()
            if len(todo):
                # (on the kernel's compact coordinates: the padding ones carry no stiffness)
                Hs, active = _scaled_stiffness(res.Hc[todo], res.maps.qmask[todo])
                tau = stability_threshold(Hs.dtype)
                stable[todo] = torch.linalg.cholesky_ex(
                    Hs - tau * torch.diag_embed(active))[1] == 0
            dofs = qmask.sum(-1).long() if outputs is None else outputs.dofs
            # the kernel's last evaluation at q made it already (bit for bit), where it did
            energy = res.energy
            if energy is None or not (np.isfinite(energy.numpy()).all() if outputs is not None
                                      else bool(torch.isfinite(energy).all())):
                energy = elastic_energy_maps(compact_q(q, res.maps.cidx), res.maps)
            if res.with_load:
                energy = energy - (lay.force * res.tip).sum(-1)
        forces = torques = insert_side = kink = None
        paper = opts.compute_forces and getattr(opts, "force_model", "energy") == "paper"
        if opts.compute_forces and (outputs is None or outputs.forces is None):
            state = ForceState(q=q, D=res.D, alpha=res.alpha, F=res.F, M=res.M,
                               loaded=res.loaded, lay=lay, tab=tab, disc=res.disc,
                               with_load=res.with_load, has_moment=res.has_moment)
        if outputs is not None and outputs.forces is not None:
            forces, torques, insert_side, kink = outputs.forces
        elif paper:
            forces, torques = paper_actuation(tubes, state)
            insert_side = forces.clone()
        elif opts.compute_forces:
            cache = None if plan is None else (
                lambda name, compute: plan.cached(res.disc, lay, name, compute))
            forces, torques, insert_side, kink = equilibrium_forces(
                tubes, state, resolver.near, cache=cache,
                partials=KERNELS[opts.kernel].partials,
                tip_partials=KERNELS[opts.kernel].tip_partials)
        if kink is None:
            kink = torch.zeros_like(res.D, dtype=torch.bool)
        conv = res.converged
        # A verdict needs an equilibrium: where the solve did not converge, the state is not
        # one, and its Hessian's sign says nothing about stability (a precurvature of 1e6 1/m
        # reported converged=False, stable=True).
        conv_list = conv.tolist()
        reason = tuple("converged" if conv_list[b] else _failure_reason(res, opts, b)
                       for b in range(B))
        err = res.error_estimate
        if err is None:
            err = torch.full((B,), float("nan"), dtype=q.dtype, device=q.device)
        ctx = SolveContext(scene=scene, tubes=tubes, layout=lay, tables=tab,
                           discretization=res.disc, insertion=res.D, rotation=res.alpha,
                           tip_force=res.F, tip_moment=res.M, implicit=res.implicit_info,
                           options=opts, plan=plan, resolver=resolver)
        tip, R = res.tip, res.R
        if diff is not None:  # differentiable versions of the same values (implicit backward)
            q, tip, R, energy = diff.q, diff.tip, diff.R, diff.energy
            rel = _wrap(diff.rel_unwrapped)
            if not paper:
                torques = diff.torques
            if forces is not None and not paper:  # keep the one-sided value (no gradient) at kinks
                forces = torch.where(kink, forces, diff.forces)
        return cls(q=q, tip_position=tip, tip_rotation=R,
                   relative_rotation_at_outer_tip=rel, energy=energy, actuation_forces=forces,
                   actuation_torques=torques, actuation_forces_insertion=insert_side,
                   force_kink=kink, converged=conv, residual_norm=res.residual,
                   iterations=res.iterations, stable=stable & conv,
                   dofs=dofs, order=res.order, error_estimate=err,
                   accuracy_met=err <= opts.accuracy, solve_time_s=elapsed,
                   reason=reason, context=ctx)

    # ------------------------------------------------------------------------------------------
    def backbone(self, points: int = 100) -> torch.Tensor:
        """Backbone positions ``(B, points, 3)`` [m], uniformly spaced in arc length from the
        orifice (``s = 0``) to the tip, integrated with the same Magnus scheme as the tip."""
        if not isinstance(points, int) or points < 2:
            raise ValueError(f"points must be an integer >= 2, got {points!r}")
        lay, tab = self.context.layout, self.context.tables
        q = self.q.detach()
        B = q.shape[0]
        m = self.context.discretization.n_magnus
        with torch.no_grad():
            poses, _ = section_start_poses(q, lay, tab)                  # (B, S+1, 4, 4)
            s_tip = lay.s_tip
            frac = torch.linspace(0.0, 1.0, points, dtype=q.dtype, device=q.device)
            s = s_tip[:, None] * frac                                     # (B, K)
            ends = lay.start + lay.h
            k = torch.searchsorted(ends.contiguous(), s.contiguous(), right=False)
            k = k.clamp(max=lay.h.shape[-1] - 1)
            start = torch.gather(lay.start, 1, k)
            h = torch.gather(lay.h, 1, k)
            x = (s - start).clamp(min=0.0)
            # Gauss points of m equal Magnus steps over [0, x], in section coordinates.
            centers = (torch.arange(m, dtype=q.dtype, device=q.device) + 0.5) / m
            off = (0.5 / m) / 3.0**0.5
            loc = torch.stack([centers - off, centers + off], -1).reshape(-1)   # (2m,) in [0,1]
            hs = h.clamp(min=torch.finfo(h.dtype).tiny)       # (1e-300 is 0 in float32)
            xi = -1.0 + 2.0 * (x[..., None] * loc) / hs[..., None]             # (B, K, 2m)
            xi_all = xi.reshape(B, 1, -1).expand(B, lay.h.shape[-1], -1)   # (B, S, K*2m)
            phi, Qb = legendre_basis(xi_all, self.context.discretization.n_basis)
            f = node_fields(q, lay, xi_all, phi, Qb)
            u = f.u.reshape(B, -1, points, 2 * m, 2)                        # (B, S, K, 2m, 2)
            u = torch.gather(u, 1, k[:, None, :, None, None].expand(B, 1, points, 2 * m, 2))[:, 0]
            steps = exp_se3(magnus_twists(u.reshape(B, points, m, 2, 2), x / m))
            g = torch.gather(poses, 1, k[..., None, None].expand(B, points, 4, 4))
            for i in range(m):
                g = g @ steps[:, :, i]
        return g[..., :3, 3]

    def jacobians(self, *, compliance: bool = True):
        """Actuator stiffness, tip Jacobian, force-control Jacobian and tip compliance
        (:func:`torchpvs.jacobians.control_jacobians`; ``compliance=False`` skips the
        compliance, which an unloaded equilibrium gets from one extra solve)."""
        return control_jacobians(self, compliance=compliance)

    # ------------------------------------------------------------------------------------------
    def as_contract(self, index: int = 0, backbone_points: int | None = None) -> dict[str, Any]:
        """The ``torchpvs solve --json`` object of docs/conventions.md for batch element
        ``index``."""
        b = index

        def flt(x) -> float | None:
            v = float(x)
            return v if math.isfinite(v) else None

        def lst(t) -> list:
            return [flt(v) for v in t.detach().cpu().reshape(-1)]

        out: dict[str, Any] = {
            "model": "pvs",
            "converged": bool(self.converged[b]),
            "tip_position": lst(self.tip_position[b]),
            "tip_rotation": [lst(r) for r in self.tip_rotation[b]],
            "relative_rotation_at_outer_tip": lst(self.relative_rotation_at_outer_tip[b]),
            "actuation_forces": lst(self.actuation_forces[b]) if self.actuation_forces is not None
            else None,
            "actuation_torques": lst(self.actuation_torques[b])
            if self.actuation_torques is not None else None,
            # Extensions of the contract: the insertion-side force where U*(D) has a kink.
            "actuation_forces_insertion": lst(self.actuation_forces_insertion[b])
            if self.actuation_forces_insertion is not None else None,
            "force_kink": [bool(k) for k in self.force_kink[b]],
            # ... and the a posteriori tip error [m] with whether it meets options.accuracy.
            "error_estimate": flt(self.error_estimate[b]),
            "accuracy_met": bool(self.accuracy_met[b]),
            "energy": flt(self.energy[b]),
            "stable": bool(self.stable[b]) if bool(self.converged[b]) else None,
            "min_stiffness_eigenvalue": flt(self.min_stiffness_eigenvalue[b]),
            "residual_norm": flt(self.residual_norm[b]),
            "iterations": int(self.iterations[b]),
            "dofs": int(self.dofs[b]),
            "solve_time_s": float(self.solve_time_s),
        }
        if backbone_points is not None:
            out["backbone"] = [lst(p) for p in self.backbone(backbone_points)[b]]
        return out
