"""Stage 7 — outputs: the :class:`Equilibrium` returned by :func:`torchpvs.solve`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from .lie import magnus4_step
from .mechanics import node_fields, potential, section_start_poses, tip_pose
from .sections import build_layout

__all__ = ["Equilibrium"]


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    """Wrap to ``(-pi, pi]``."""
    return math.pi - torch.remainder(math.pi - angle, 2 * math.pi)


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
            positive = the actuator pulls back), conventions.md.
        actuation_forces_insertion: ``(B, N)`` [N] the derivative for decreasing ``D_j``
            (insertion). Equal to ``actuation_forces`` where ``U*(D)`` is smooth; different where
            it has a kink; NaN where insertion is impossible (``D_j = 0`` or ``D_j = D_{j-1}``).
        force_kink: ``(B, N)`` bool, ``U*(D_j)`` has a kink here (a tube's base, straight-to-
            curved transition or end at the orifice): the two one-sided forces differ.
        actuation_torques: ``(B, N)`` [N·m] ``dU*/dalpha_j``.
        converged: ``(B,)`` bool; ``reason``: per-element text ("converged" or why not).
        residual_norm: ``(B,)`` scaled residual (see ``SolverOptions.tol``).
        iterations: ``(B,)`` Newton iterations (at the final order).
        stable: ``(B,)`` bool, the Hessian over the active coordinates is positive definite.
        min_stiffness_eigenvalue: ``(B,)`` [J·m²] smallest eigenvalue of that Hessian.
        dofs: ``(B,)`` number of active generalized coordinates.
        order: basis degree used; ``error_estimate``: ``(B,)`` [m] a posteriori tip error: the
            tip change from the previous order (automatic order selection) plus the tip change
            from doubling the Magnus steps (automatic ``n_magnus``); NaN when the order is fixed.
        solve_time_s: wall time of the solve [s].
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
    min_stiffness_eigenvalue: torch.Tensor
    dofs: torch.Tensor
    order: int
    error_estimate: torch.Tensor
    solve_time_s: float
    reason: tuple[str, ...]
    _ctx: dict[str, Any] = field(repr=False, default_factory=dict)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def batch_size(self) -> int:
        return self.q.shape[0]

    # ------------------------------------------------------------------------------------------
    @classmethod
    def _from_solution(cls, scene, tubes, res, opts, elapsed: float,
                       diff: dict | None = None) -> Equilibrium:
        q, lay, tab, H = res["q"], res["lay"], res["tab"], res["H"]
        B = q.shape[0]
        qmask = lay["qmask"]
        with torch.no_grad():
            f = node_fields(q, lay, tab["xq"], tab["phi_q"], tab["Q_q"])
            psi_l1 = f["psi0"] + (f["inc"] * lay["before_l1"][..., None]).sum(-2)
            rel = _wrap(psi_l1[:, 1:] - psi_l1[:, :1])
            # Stability: eigenvalues of the Hessian restricted to active coordinates; inactive
            # rows are pushed far above the spectrum so they never become the minimum.
            big = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1) * 10 + 1.0
            Hr = H + torch.diag_embed((1.0 - qmask) * big[:, None])
            ev = torch.linalg.eigvalsh(Hr)[:, 0]
            tiny = 1e-10 * H.diagonal(dim1=-2, dim2=-1).abs().amax(-1)
            stable = ev > tiny
            dofs = qmask.sum(-1).long()
            energy = potential(q, lay, tab, None, res["with_load"])
        forces = torques = insert_side = None
        kink = torch.zeros_like(res["D"], dtype=torch.bool)
        if opts.compute_forces:
            forces, torques = _actuation(scene, tubes, res)
            forces, insert_side, kink = _one_sided_forces(scene, tubes, res, opts, forces)
        conv = res["converged"]
        reason = tuple(
            "converged" if bool(conv[b]) else
            (f"residual {float(res['residual'][b]):.3g} > tol after {int(res['iterations'][b])} "
             f"iterations; try method='minimize', more max_iter, or a different initial guess")
            for b in range(B))
        err = res.get("error_estimate", torch.full((B,), float("nan"), dtype=q.dtype,
                                                   device=q.device))
        ctx = {"scene": scene, "tubes": tubes, "lay": lay, "tab": tab, "disc": res["disc"],
               "D": res["D"], "alpha": res["alpha"], "F": res["F"], "M": res["M"],
               "implicit_info": res["implicit_info"], "options": opts}
        tip, R = res["tip"], res["R"]
        if diff is not None:  # differentiable versions of the same values (implicit backward)
            q, tip, R, energy = diff["q"], diff["tip"], diff["R"], diff["energy"]
            rel = _wrap(diff["rel_unwrapped"])
            torques = diff["torques"]
            if forces is not None:  # keep the one-sided value (no gradient) at kinks
                forces = torch.where(kink, forces, diff["forces"])
        return cls(q=q, tip_position=tip, tip_rotation=R,
                   relative_rotation_at_outer_tip=rel, energy=energy, actuation_forces=forces,
                   actuation_torques=torques, actuation_forces_insertion=insert_side,
                   force_kink=kink, converged=conv, residual_norm=res["residual"],
                   iterations=res["iterations"], stable=stable, min_stiffness_eigenvalue=ev,
                   dofs=dofs, order=res["order"], error_estimate=err, solve_time_s=elapsed,
                   reason=reason, _ctx=ctx)

    # ------------------------------------------------------------------------------------------
    def backbone(self, points: int = 100) -> torch.Tensor:
        """Backbone positions ``(B, points, 3)`` [m], uniformly spaced in arc length from the
        orifice (``s = 0``) to the tip, integrated with the same Magnus scheme as the tip."""
        if not isinstance(points, int) or points < 2:
            raise ValueError(f"points must be an integer >= 2, got {points!r}")
        lay, tab = self._ctx["lay"], self._ctx["tab"]
        q = self.q.detach()
        B = q.shape[0]
        m = self._ctx["disc"].n_magnus
        with torch.no_grad():
            poses, _ = section_start_poses(q, lay, tab)                  # (B, S+1, 4, 4)
            s_tip = lay["s_tip"]
            frac = torch.linspace(0.0, 1.0, points, dtype=q.dtype, device=q.device)
            s = s_tip[:, None] * frac                                     # (B, K)
            ends = lay["start"] + lay["h"]
            k = torch.searchsorted(ends.contiguous(), s.contiguous(), right=False)
            k = k.clamp(max=lay["h"].shape[-1] - 1)
            start = torch.gather(lay["start"], 1, k)
            h = torch.gather(lay["h"], 1, k)
            x = (s - start).clamp(min=0.0)
            # Gauss points of m equal Magnus steps over [0, x], in section coordinates.
            centers = (torch.arange(m, dtype=q.dtype, device=q.device) + 0.5) / m
            off = (0.5 / m) / 3.0**0.5
            loc = torch.stack([centers - off, centers + off], -1).reshape(-1)   # (2m,) in [0,1]
            hs = h.clamp(min=1e-300)
            xi = -1.0 + 2.0 * (x[..., None] * loc) / hs[..., None]             # (B, K, 2m)
            xi_all = xi.reshape(B, 1, -1).expand(B, lay["h"].shape[-1], -1)   # (B, S, K*2m)
            from .basis import legendre_basis
            phi, Qb = legendre_basis(xi_all, self._ctx["disc"].n_basis)
            f = node_fields(q, lay, xi_all, phi, Qb)
            u = f["u"].reshape(B, -1, points, 2 * m, 2)                        # (B, S, K, 2m, 2)
            u = torch.gather(u, 1, k[:, None, :, None, None].expand(B, 1, points, 2 * m, 2))[:, 0]
            zero = torch.zeros_like(u[..., :1])
            tw = torch.cat([u, zero, zero, zero, torch.ones_like(zero)], -1)
            tw = tw.reshape(B, points, m, 2, 6)
            hs = (x / m)[..., None].expand(B, points, m)
            steps = magnus4_step(tw[..., 0, :], tw[..., 1, :], hs)
            g = torch.gather(poses, 1, k[..., None, None].expand(B, points, 4, 4))
            for i in range(m):
                g = g @ steps[:, :, i]
        return g[..., :3, 3]

    def jacobians(self):
        """Actuator stiffness, tip Jacobian, force-control Jacobian and tip compliance
        (:func:`torchpvs.jacobians.control_jacobians`)."""
        from .jacobians import control_jacobians
        return control_jacobians(self)

    # ------------------------------------------------------------------------------------------
    def as_contract(self, index: int = 0, backbone_points: int | None = None) -> dict[str, Any]:
        """The ``torchpvs solve --json`` object of conventions.md for batch element ``index``."""
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
            "energy": flt(self.energy[b]),
            "stable": bool(self.stable[b]),
            "min_stiffness_eigenvalue": flt(self.min_stiffness_eigenvalue[b]),
            "residual_norm": flt(self.residual_norm[b]),
            "iterations": int(self.iterations[b]),
            "dofs": int(self.dofs[b]),
            "solve_time_s": float(self.solve_time_s),
        }
        if backbone_points is not None:
            out["backbone"] = [lst(p) for p in self.backbone(backbone_points)[b]]
        return out


def _actuation(scene, tubes, res):
    """``tau_D = dU*/dD``, ``tau_alpha = dU*/dalpha`` by the envelope theorem: at an equilibrium
    the total derivative equals the partial derivative at fixed coordinates ``q`` (the sections
    move with ``D``, the coordinates are strains on the normalized section coordinate)."""
    q = res["q"].detach()
    D = res["D"].detach().clone().requires_grad_(True)
    A = res["alpha"].detach().clone().requires_grad_(True)
    with torch.enable_grad():
        lay = build_layout(tubes, D, A, res["F"], res["M"], res["loaded"], res["disc"])
        R0 = tip_pose(q, lay, res["tab"])[1].detach() if res["has_moment"] else None
        U = potential(q, lay, res["tab"], R0, res["with_load"])
        gD, gA = torch.autograd.grad(U.sum(), (D, A))
    return gD.detach(), gA.detach()


def _one_sided_forces(scene, tubes, res, opts, forces, delta: float = 1e-7, tol: float = 1e-9):
    """Where ``U*(D_j)`` has a kink — material of tube ``j`` changing kind exactly at the
    orifice: its base (``D_j = 0``: the guide torsion appears), its straight-to-curved transition
    (``D_j = Ls_j``: curvature enters the guide) or its end (``D_j = L_j``) — the derivative
    differs for insertion and retraction. Each side is computed at an equilibrium ``delta`` away
    on that side (where ``U*`` is smooth), warm-started; the error is ``O(delta)``.

    Returns ``(retraction side, insertion side, kink mask)``, all ``(B, N)``.
    """
    from .solver import _solve

    D = res["D"]
    B, N = D.shape
    L = tubes.length.expand(B, N)
    Ls = tubes.straight.expand(B, N)
    curved = tubes.coef.abs().sum((-1, -2)).expand(B, N) > 0
    exposed = L - D > tol
    kink = ((D <= tol) & exposed) | (((Ls - D).abs() <= tol) & curved & (L > Ls)) \
        | ((L - D).abs() <= tol)
    insertion = forces.clone()
    prev = torch.cat([torch.zeros_like(D[:, :1]), D[:, :-1]], -1)
    blocked = D - delta < prev
    insertion[blocked] = float("nan")
    if not bool(kink.any()):
        return forces, insertion, kink
    idx = kink.nonzero()
    rows_b, rows_j = idx[:, 0], idx[:, 1]
    step = torch.zeros(len(idx), N, dtype=D.dtype, device=D.device)
    step[torch.arange(len(idx)), rows_j] = delta
    sides = [("retract", step)]
    can_insert = ~blocked[rows_b, rows_j]
    if bool(can_insert.any()):
        sides.append(("insert", -step[can_insert]))
    sub_opts = replace(opts, order=res["order"], on_failure="ignore")
    retract = forces.clone()
    for name, st in sides:
        sel = rows_b if name == "retract" else rows_b[can_insert]
        sj = rows_j if name == "retract" else rows_j[can_insert]
        Dn = D[sel] + st
        # Moving a base past the next one's would break the ordering: move them together.
        Dn = torch.cummax(Dn, -1).values
        eq = _solve(scene, tubes, Dn, res["alpha"][sel], res["F"][sel], res["M"][sel],
                    sub_opts, res["q"][sel])
        vals = eq.actuation_forces[torch.arange(len(sel)), sj]
        if name == "retract":
            retract[sel, sj] = vals
        else:
            insertion[sel, sj] = vals
    return retract, insertion, kink
