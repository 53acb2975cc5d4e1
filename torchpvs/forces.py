"""Stage 7a — actuation forces and torques at an equilibrium (the paper's new result).

``tau = dU*/dx`` at an equilibrium of the reduced energy ``U*(x) = min_q U(q; x)``, ``x = (D,
alpha)``: by the envelope theorem, the partial derivative at fixed coordinates
(:func:`envelope_forces`); one-sided values where a section cut crosses a tube end or a
straight-to-curved transition (:func:`equilibrium_forces`); and the projection of the paper's
eq. (41) (Renda et al. 2021) for reproducing its Table II (:func:`paper_actuation`,
:func:`paper_scope_check`). :class:`torchpvs.Equilibrium` calls these; the solver hands in the
re-solve they need at kinks, so this module never imports it.
"""

from __future__ import annotations

import torch

from .mechanics import node_fields, potential, tip_pose
from .sections import build_layout

__all__ = ["envelope_forces", "equilibrium_forces", "paper_actuation", "paper_scope_check"]

def envelope_forces(tubes, res):
    """``tau_D = dU*/dD``, ``tau_alpha = dU*/dalpha`` by the envelope theorem: at an equilibrium
    the total derivative equals the partial derivative at fixed coordinates ``q`` (the sections
    move with ``D``, the coordinates are strains on the normalized section coordinate)."""
    # A reverse pass needs ordinary tensors: the solve may run in inference mode, whose tensors
    # autograd cannot save (clones made outside it are ordinary).
    with torch.inference_mode(False), torch.enable_grad():
        q, F, M, loaded = (res[k].detach().clone() for k in ("q", "F", "M", "loaded"))
        D = res["D"].detach().clone().requires_grad_(True)
        A = res["alpha"].detach().clone().requires_grad_(True)
        lay = build_layout(tubes, D, A, F, M, loaded, res["disc"])
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


def paper_actuation(tubes, res, tol: float = 1e-12):
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
    from .mechanics import poly

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
        present = lay.present > 0.5                                 # (B, S, N)
        # Unloaded: the internal moment vanishes on the whole free part, so the bending is the
        # stiffness-weighted average of the rotated precurvatures (the closure of the exact
        # solution; more accurate at the section ends than the bending polynomial itself).
        EIp = lay.EI[:, None, None, :] * present[:, :, None, :]
        u = (EIp[..., None] * Ru).sum(-2) / EIp.sum(-1, keepdim=True).clamp(min=1e-300)
        S = present.shape[1]
        first = present[..., 0].float().argmax(-1)                     # first free section
        ar = torch.arange(B, device=q.device)
        u0 = u[ar, first, G]                                            # (B, 2) at s = 0+
        m0 = (lay.EI[:, :, None] * (u0[:, None, :] - Ru[ar, first, G])
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
        t = f["s"][..., :G] - lay.tau[:, None, None, 1]            # (B, S, G)
        dk = poly(dcoef[:, None, None, None], t[..., None])[..., 0, :2]   # (B, S, G, 2)
        c, sn = torch.cos(psi[..., :G, 1]), torch.sin(psi[..., :G, 1])
        Rdk = torch.stack([c * dk[..., 0] - sn * dk[..., 1], sn * dk[..., 0] + c * dk[..., 1]],
                          -1)
        ug, R2 = u[..., :G, :], Ru[..., :G, 1, :]
        JR2 = torch.stack([-R2[..., 1], R2[..., 0]], -1)
        dens = dpsi[..., :G, 1] * (ug * JR2).sum(-1) + (ug * Rdk).sum(-1)   # (B, S, G)
        cross = ug[..., 0] * R2[..., 1] - ug[..., 1] * R2[..., 0]
        w = 0.5 * lay.h[..., None] * wg * ov[..., None]
        integral = (dens * w).sum((-1, -2))
        tors = (cross * w).sum((-1, -2))
        # beyond the outer tube's end: the inner tube alone (strain = precurvature if unloaded)
        nxt = (last + 1).clamp(max=S - 1)
        after = present[ar, nxt, 1] & ~present[ar, nxt, 0] & (last + 1 < S)
        ua, Ra = u[ar, nxt, G], Ru[ar, nxt, G, 1]
        tail = torch.where(after, (ua * (ua - Ra)).sum(-1), torch.zeros_like(integral))
        EI2 = lay.EI[:, 1]
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


def equilibrium_forces(tubes, res, resolve, delta: float = 1e-7, tol: float = 1e-9):
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
        forces, torques = envelope_forces(tubes, res)
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
    allf, allt = envelope_forces(tubes, both)
    forces, torques, vals = allf[:B], allt[:B], allf[B:][torch.arange(len(sel)), sj]
    insertion = forces.clone()
    insertion[blocked] = float("nan")
    n_r = len(rows_b)
    retract = forces.clone()
    retract[rows_b, rows_j] = vals[:n_r]
    insertion[sel[n_r:], sj[n_r:]] = vals[n_r:]
    return retract, torques, insertion, kink
