"""Stage 7 — outputs: the :class:`Equilibrium` returned by :func:`torchpvs.solve`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from .lie import magnus4_step
from .mechanics import (
    elastic_energy_maps,
    node_fields,
    potential,
    section_start_poses,
    tip_pose,
)
from .newton import active_index, compact_scaled
from .sections import build_layout

__all__ = ["Equilibrium", "actuation"]


def _failure_reason(res, opts, b: int) -> str:
    text = (f"residual {float(res['residual'][b]):.3g} > tol after {int(res['iterations'][b])} "
            f"iterations at order {res['order']}")
    ramp = res.get("ramp")
    if ramp is not None and not math.isnan(float(ramp[b])):
        text += (f"; the load ramp ({opts.load_steps} steps) reached {float(ramp[b]):.0%} of "
                 f"the tip load")
    if res.get("work_exhausted"):
        text += f"; work limit max_total_iter={opts.max_total_iter} reached"
    return text + "; try method='minimize', more max_iter, or a different initial guess"


def _scaled_stiffness(H: torch.Tensor, qmask: torch.Tensor):
    """``S H S`` with ``S = diag(|H_ii|^-1/2)`` on the active coordinates, gathered to each
    element's active coordinates (:func:`torchpvs.newton.compact`, ``(B, nA, nA)``; padding rows
    are identity rows), and the gathered active mask ``(B, nA)`` as float."""
    d = H.diagonal(dim1=-2, dim2=-1).abs()
    active = qmask * (d > 0)
    S = torch.where(active > 0, d.clamp(min=torch.finfo(H.dtype).tiny) ** -0.5,
                    torch.ones_like(d))
    act = active_index(qmask)
    return compact_scaled(H, S, act)[0], torch.gather(active, 1, act)


def _stability_threshold(dtype: torch.dtype) -> float:
    return 0.01 * torch.finfo(dtype).eps ** 0.5


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
            (decided on its nondimensional form, see ``min_stiffness_eigenvalue``).
        min_stiffness_eigenvalue: ``(B,)`` smallest eigenvalue of the Jacobi-scaled
            (dimensionless) Hessian; computed on first access.
        dofs: ``(B,)`` number of active generalized coordinates.
        order: basis degree used; ``error_estimate``: ``(B,)`` [m] a posteriori tip error: the
            tip change from the previous order (automatic order selection) plus the tip change
            from doubling the Magnus steps (automatic ``n_magnus``); NaN when the order is fixed.
        accuracy_met: ``(B,)`` bool, ``error_estimate <= options.accuracy``; False where no
            estimate exists (a fixed order). An automatic solve that cannot meet the request
            (``max_order`` or the Magnus cap reached) also warns.
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
    dofs: torch.Tensor
    order: int
    error_estimate: torch.Tensor
    accuracy_met: torch.Tensor
    solve_time_s: float
    reason: tuple[str, ...]
    _ctx: dict[str, Any] = field(repr=False, default_factory=dict)

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
        ev = self._ctx.get("min_eig")
        if ev is None:
            info = self._ctx["implicit_info"]
            with torch.no_grad():
                Hs, active = _scaled_stiffness(info["H"], info["qmask"])
                # Inactive rows (identity) are pushed above the spectrum: never the minimum.
                ev = torch.linalg.eigvalsh(Hs + torch.diag_embed(1.0 - active) * 10.0)[:, 0]
                # No coordinates (a robot entirely in the guide): no stiffness to speak of.
                ev = torch.where(active.sum(-1) > 0, ev, torch.full_like(ev, float("nan")))
            self._ctx["min_eig"] = ev
        return ev

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def batch_size(self) -> int:
        return self.q.shape[0]

    # ------------------------------------------------------------------------------------------
    @classmethod
    def _from_solution(cls, scene, tubes, res, opts, elapsed: float,
                       diff: dict | None = None, plan=None, resolve=None,
                       resolve_all=None) -> Equilibrium:
        """Outputs of a converged solve ``res``. Re-solves are handed in by the solver, so that
        this module never imports it: ``resolve(D, rows) -> state`` (a solution dict with ``q``,
        ``D``, ``alpha``, ``F``, ``M``, ``loaded``) at insertions ``D`` for batch rows ``rows``,
        near this equilibrium (the one-sided forces at kinks), and
        ``resolve_all(options, initial) -> Equilibrium`` for the same inputs with other options
        (kept in ``_ctx["resolve"]`` for :mod:`torchpvs.jacobians`)."""
        q, lay, tab, H = res["q"], res["lay"], res["tab"], res["H"]
        B = q.shape[0]
        qmask = lay["qmask"]
        with torch.no_grad():
            # Angles at section ends do not depend on the evaluation points: one point will do.
            f = node_fields(q, lay, tab["xq"][:1], tab["phi_q"][:1], tab["Q_q"][:1])
            psi_l1 = f["psi0"] + (f["inc"] * lay["before_l1"][..., None]).sum(-2)
            rel = _wrap(psi_l1[:, 1:] - psi_l1[:, :1])
            # Stability on the nondimensional stiffness (see min_stiffness_eigenvalue): positive
            # definite beyond a threshold set by the precision alone -- one Cholesky; the
            # eigenvalue itself is computed only when asked for.
            Hs, active = _scaled_stiffness(H, qmask)
            tau = _stability_threshold(H.dtype)
            stable = torch.linalg.cholesky_ex(Hs - tau * torch.diag_embed(active))[1] == 0
            dofs = qmask.sum(-1).long()
            energy = elastic_energy_maps(q, res["maps"])
            if res["with_load"]:
                energy = energy - (lay["force"] * res["tip"]).sum(-1)
        forces = torques = insert_side = None
        kink = torch.zeros_like(res["D"], dtype=torch.bool)
        paper = opts.compute_forces and getattr(opts, "force_model", "energy") == "paper"
        if paper:
            forces, torques = _paper_actuation(tubes, res)
            insert_side = forces.clone()
        elif opts.compute_forces:
            forces, torques, insert_side, kink = _forces(tubes, res, resolve)
        conv = res["converged"]
        conv_list = conv.tolist()
        reason = tuple("converged" if conv_list[b] else _failure_reason(res, opts, b)
                       for b in range(B))
        err = res.get("error_estimate", torch.full((B,), float("nan"), dtype=q.dtype,
                                                   device=q.device))
        ctx = {"scene": scene, "tubes": tubes, "lay": lay, "tab": tab, "disc": res["disc"],
               "D": res["D"], "alpha": res["alpha"], "F": res["F"], "M": res["M"],
               "implicit_info": res["implicit_info"], "options": opts, "plan": plan,
               "resolve": resolve_all}
        tip, R = res["tip"], res["R"]
        if diff is not None:  # differentiable versions of the same values (implicit backward)
            q, tip, R, energy = diff["q"], diff["tip"], diff["R"], diff["energy"]
            rel = _wrap(diff["rel_unwrapped"])
            if not paper:
                torques = diff["torques"]
            if forces is not None and not paper:  # keep the one-sided value (no gradient) at kinks
                forces = torch.where(kink, forces, diff["forces"])
        return cls(q=q, tip_position=tip, tip_rotation=R,
                   relative_rotation_at_outer_tip=rel, energy=energy, actuation_forces=forces,
                   actuation_torques=torques, actuation_forces_insertion=insert_side,
                   force_kink=kink, converged=conv, residual_norm=res["residual"],
                   iterations=res["iterations"], stable=stable,
                   dofs=dofs, order=res["order"], error_estimate=err,
                   accuracy_met=err <= opts.accuracy, solve_time_s=elapsed,
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


def actuation(tubes, res):
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


def paper_scope_check(tubes, D: torch.Tensor, loaded: torch.Tensor, tol: float = 1e-12) -> None:
    """Raise ``ValueError`` (naming the field) where the paper's eq. (41) does not apply."""
    B, N = D.shape
    if N > 2:
        raise ValueError(f"force_model='paper' (the paper's eq. 41) is defined for one or two "
                         f"tubes; this scene has {N} (use force_model='energy')")
    if bool(loaded.any()):
        raise ValueError("force_model='paper' (eq. 41) is derived without external load: "
                         "load.tip_force and load.tip_moment must be zero")
    L = tubes.length.expand(B, N)
    Ls = tubes.straight.expand(B, N)
    coef = tubes.coef.expand(B, N, 3, tubes.coef.shape[-1])
    curved = coef[..., :2, :].abs().sum((-1, -2)) > 0
    ell = (L - D).clamp(min=0.0)
    for j in range(N):
        bad = curved[:, j] & (Ls[:, j] - D[:, j] > tol) & (ell[:, j] > tol)
        if bool(bad.any()):
            b = int(bad.nonzero()[0])
            raise ValueError(
                f"force_model='paper': tubes[{j}].straight_length ({float(Ls[b, j]):.6g} m) "
                f"exceeds the insertion D_{j + 1} ({float(D[b, j]):.6g} m) in element {b}: the "
                f"straight-to-curved transition lies beyond the orifice, which eq. (41) omits")
        if bool((ell[:, j] <= tol).any()):
            raise ValueError(f"force_model='paper': tube {j + 1} lies entirely inside the guide "
                             f"(insertion >= tubes[{j}] length)")
    if N == 2 and bool((ell[:, 0] > ell[:, 1] + tol).any()):
        raise ValueError("force_model='paper': the outer tube must end before the inner one "
                         "(L_1 - D_1 <= L_2 - D_2), as in the paper's Fig. 3")


def _paper_actuation(tubes, res, tol: float = 1e-12):
    """The paper's eq. (41) (Renda et al., RA-L 2021) evaluated on the equilibrium, for
    ``N <= 2`` tubes without tip load (``force_model="paper"``; docs/actuation-forces.md).

    In the twist-free frame (``u``: backbone bending, ``Ru_j = Rz(psi_j) u*_j``, ``psi_2'`` the
    torsion of tube 2), integrating the paper's ``(xi_k1' + ad xi_1 xi_k1)^T Ad xi*_k2 = u' . Ru_2``
    by parts over the free overlap ``[0, l_1]``::

        tau_D2 / EI_2 = 1/2 |u(0)|^2 - 1/2 |u(l_1-)|^2
                        + int_0^l1 (psi_2' u . J Ru_2 + u . Rz(psi_2) du*_2/dsigma) ds
                        + (u . (u - Ru_2))(l_1+)
        tau_D1 = sum_j EI_j u . (u - Ru_j) at s = 0+  -  tau_D2     (eq. 43)
        tau_alpha2 = EI_2 int_0^l1 (u x Ru_2)_z ds = -tau_alpha1

    (``J`` = rotation by +90 deg about the tangent.) Without load the internal moment vanishes
    on the free part, so ``u`` is evaluated as ``sum_j EI_j Ru_j / sum_j EI_j`` (which makes
    ``tau_D1 = -tau_D2``, the paper's eq. 43, exact). The precurvature is the scene's polynomial
    (measured from the start of the curved part). Returns ``(forces, torques)``, ``(B, N)``.
    """
    from .basis import gauss_legendre, legendre_basis
    from .mechanics import _poly

    q, lay, disc = res["q"].detach(), res["lay"], res["disc"]
    D = res["D"]
    B, N = D.shape
    paper_scope_check(tubes, D, (res["F"].abs().sum(-1) > 0) | (res["M"].abs().sum(-1) > 0),
                      tol)
    coef = tubes.coef.expand(B, N, 3, tubes.coef.shape[-1])

    n_q = disc.n_basis * 2 + coef.shape[-1] + 6
    xg, wg = gauss_legendre(n_q, dtype=q.dtype, device=q.device)
    ends = torch.tensor([-1.0, 1.0], dtype=q.dtype, device=q.device)
    x_all = torch.cat([xg, ends])
    phi, Qb = legendre_basis(x_all, disc.n_basis)
    with torch.no_grad():
        f = node_fields(q, lay, x_all, phi, Qb)
        Ru, dpsi, psi = f["Ru"], f["dpsi"], f["psi"]                  # (B, S, G+2, ...)
        G = xg.shape[0]
        present = lay["present"] > 0.5                                 # (B, S, N)
        # Unloaded: the internal moment vanishes on the whole free part, so the bending is the
        # stiffness-weighted average of the rotated precurvatures (the closure of the exact
        # solution; more accurate at the section ends than the bending polynomial itself).
        EIp = lay["EI"][:, None, None, :] * present[:, :, None, :]
        u = (EIp[..., None] * Ru).sum(-2) / EIp.sum(-1, keepdim=True).clamp(min=1e-300)
        S = present.shape[1]
        first = present[..., 0].float().argmax(-1)                     # first free section
        ar = torch.arange(B, device=q.device)
        u0 = u[ar, first, G]                                            # (B, 2) at s = 0+
        m0 = (lay["EI"][:, :, None] * (u0[:, None, :] - Ru[ar, first, G])
              * present[ar, first][..., None]).sum(1)                  # (B, 2) total moment
        k_m0 = (u0 * m0).sum(-1)
        forces = torch.zeros(B, N, dtype=q.dtype, device=q.device)
        torques = torch.zeros(B, N, dtype=q.dtype, device=q.device)
        if N == 1:
            forces[:, 0] = k_m0
            return forces, torques
        ov = present[..., 0] & present[..., 1]                         # (B, S) free overlap
        last = (S - 1) - ov.flip(-1).float().argmax(-1)
        u_end = u[ar, last, G + 1]
        # derivative of the inner precurvature along its material, rotated by psi_2
        P = coef.shape[-1]
        dcoef = coef[:, 1, :, 1:] * torch.arange(1, P, dtype=q.dtype, device=q.device) \
            if P > 1 else torch.zeros_like(coef[:, 1, :, :1])
        t = f["s"][..., :G] - lay["tau"][:, None, None, 1]            # (B, S, G)
        dk = _poly(dcoef[:, None, None, None], t[..., None])[..., 0, :2]   # (B, S, G, 2)
        c, sn = torch.cos(psi[..., :G, 1]), torch.sin(psi[..., :G, 1])
        Rdk = torch.stack([c * dk[..., 0] - sn * dk[..., 1], sn * dk[..., 0] + c * dk[..., 1]],
                          -1)
        ug, R2 = u[..., :G, :], Ru[..., :G, 1, :]
        JR2 = torch.stack([-R2[..., 1], R2[..., 0]], -1)
        dens = dpsi[..., :G, 1] * (ug * JR2).sum(-1) + (ug * Rdk).sum(-1)   # (B, S, G)
        cross = ug[..., 0] * R2[..., 1] - ug[..., 1] * R2[..., 0]
        w = 0.5 * lay["h"][..., None] * wg * ov[..., None]
        integral = (dens * w).sum((-1, -2))
        tors = (cross * w).sum((-1, -2))
        # beyond the outer tube's end: the inner tube alone (strain = precurvature if unloaded)
        nxt = (last + 1).clamp(max=S - 1)
        after = present[ar, nxt, 1] & ~present[ar, nxt, 0] & (last + 1 < S)
        ua, Ra = u[ar, nxt, G], Ru[ar, nxt, G, 1]
        tail = torch.where(after, (ua * (ua - Ra)).sum(-1), torch.zeros_like(integral))
        EI2 = lay["EI"][:, 1]
        tau_D2 = EI2 * (0.5 * (u0**2).sum(-1) - 0.5 * (u_end**2).sum(-1) + integral + tail)
        forces[:, 1] = tau_D2
        forces[:, 0] = k_m0 - tau_D2
        torques[:, 1] = EI2 * tors
        torques[:, 0] = -EI2 * tors
    return forces, torques


def _coinciding_cuts(L, Ls, D, curved, tol: float) -> torch.Tensor:
    """``(B, N)``: a cut that moves with ``D_j`` (tube j's distal end, or its straight-to-curved
    transition beyond the orifice) coincides with a cut of another tube. Moving ``D_j`` then
    changes which material lies on either side of the cut, so ``U*(D_j)`` has a kink (e.g. the
    inner tip retracting past the outer tip releases the overlap's energy density)."""
    B, N = D.shape
    ell = (L - D).clamp(min=0.0)
    tau = Ls - D
    cuts = torch.stack([ell, tau], -1)                                     # (B, N, 2)
    valid = torch.stack([ell > tol, curved & (tau > tol) & (tau < ell - tol)], -1)
    close = (cuts[:, :, :, None, None] - cuts[:, None, None, :, :]).abs() <= tol
    both = valid[:, :, :, None, None] & valid[:, None, None, :, :]
    other = ~torch.eye(N, dtype=torch.bool, device=D.device)[None, :, None, :, None]
    return (close & both & other).flatten(2).any(-1)


def _forces(tubes, res, resolve, delta: float = 1e-7, tol: float = 1e-9):
    """Actuation forces and torques ``(B, N)`` at the equilibrium ``res`` (:func:`actuation`),
    with one-sided insertion forces where ``U*(D_j)`` has a kink: material of tube ``j`` changing
    kind exactly at the orifice -- its base (``D_j = 0``: the guide torsion appears), its
    straight-to-curved transition (``D_j = Ls_j``: curvature enters the guide) or its end
    (``D_j = L_j``) -- or a cut that moves with ``D_j`` meeting another tube's. There the
    derivative differs for insertion and retraction. Each side is taken at an equilibrium
    ``delta`` away on that side (where ``U*`` is smooth), from ``resolve`` (usually no solve, at
    most one Newton step); the error is ``O(delta)``. The equilibrium and every kink side go
    through ONE envelope-theorem evaluation (one layout, one reverse pass).

    Returns ``(forces = retraction side, torques, insertion side, kink mask)``, all ``(B, N)``;
    the insertion side is NaN where the carriage cannot move in (blocked by the next base).
    """
    D = res["D"]
    B, N = D.shape
    L = tubes.length.expand(B, N)
    Ls = tubes.straight.expand(B, N)
    curved = tubes.coef.abs().sum((-1, -2)).expand(B, N) > 0
    exposed = L - D > tol
    kink = ((D <= tol) & exposed) | (((Ls - D).abs() <= tol) & curved & (L > Ls)) \
        | ((L - D).abs() <= tol) | _coinciding_cuts(L, Ls, D, curved, tol)
    prev = torch.cat([torch.zeros_like(D[:, :1]), D[:, :-1]], -1)
    blocked = D - delta < prev
    idx = kink.nonzero()
    if idx.numel() == 0:
        forces, torques = actuation(tubes, res)
        insertion = forces.clone()
        insertion[blocked] = float("nan")
        return forces, torques, insertion, kink
    rows_b, rows_j = idx[:, 0], idx[:, 1]
    can_insert = ~blocked[rows_b, rows_j]
    # Rows: every kink on the retraction side, then those that can move on the insertion side.
    sel = torch.cat([rows_b, rows_b[can_insert]])
    sj = torch.cat([rows_j, rows_j[can_insert]])
    sign = torch.cat([torch.ones_like(rows_j), -torch.ones_like(rows_j[can_insert])])
    Dn = D[sel].clone()
    Dn[torch.arange(len(sel)), sj] += delta * sign.to(D.dtype)
    # Moving a base past the next one's would break the ordering: move them together.
    Dn = torch.cummax(Dn, -1).values
    side = resolve(Dn, sel)
    both = dict(res, **{k: torch.cat([res[k], side[k]]) for k in
                        ("q", "D", "alpha", "F", "M", "loaded")})
    allf, allt = actuation(tubes, both)
    forces, torques, vals = allf[:B], allt[:B], allf[B:][torch.arange(len(sel)), sj]
    insertion = forces.clone()
    insertion[blocked] = float("nan")
    n_r = len(rows_b)
    retract = forces.clone()
    retract[rows_b, rows_j] = vals[:n_r]
    insertion[sel[n_r:], sj[n_r:]] = vals[n_r:]
    return retract, torques, insertion, kink
