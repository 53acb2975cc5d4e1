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

from typing import NamedTuple

import torch

from .basis import gauss_legendre, legendre_basis
from .mechanics import (
    NodeConstants,
    node_constants,
    node_fields,
    poly,
    potential,
    sum_dim,
    tip_pose,
)
from .sections import Discretization, Layout, Tables, build_layout, tube_rows

__all__ = ["KINK_DELTA", "KINK_TOL", "ForceState", "closed_form_partials", "envelope_forces",
           "envelope_forces_autograd", "envelope_forces_closed_form", "equilibrium_forces",
           "actuation_rows", "kink_mask", "kink_plan", "paper_actuation", "paper_scope_check"]


class ForceState(NamedTuple):
    """What the force functions read of an equilibrium (or of any coordinates at an actuation
    and load: the envelope partials hold at fixed ``q``): ``B`` elements, ``N`` tubes, ``nq``
    padded coordinates. :meth:`torchpvs.Equilibrium.from_solution` makes one of the solve's
    :class:`~torchpvs.order_control.SolveState`, the solver's re-solves near it
    (:meth:`torchpvs.solver.SolutionResolver.near`) one per kink side.

    Attributes:
        q: ``(B, nq)`` [1/m] the coordinates.
        D, alpha: ``(B, N)`` [m, rad] the insertions and base rotations.
        F, M: ``(B, 3)`` [N, N·m] the tip load, base frame.
        loaded: ``(B,)`` bool, elements with load coordinates.
        lay: the :class:`~torchpvs.sections.Layout` at ``D`` where known, else ``None`` (or a
            layout of other insertions: then it is built again).
        tab: the :class:`~torchpvs.sections.Tables` of ``disc``.
        disc: the :class:`~torchpvs.sections.Discretization` of ``q``.
        with_load: the potential includes the tip load's work (the reverse pass is used).
        has_moment: a tip moment is modelled.
        node_constants: the layout's :class:`~torchpvs.mechanics.NodeConstants` at
            ``tab.xq`` where known (kept with the plan's layout), else ``None``.
    """

    q: torch.Tensor
    D: torch.Tensor
    alpha: torch.Tensor
    F: torch.Tensor
    M: torch.Tensor
    loaded: torch.Tensor
    lay: Layout | None
    tab: Tables
    disc: Discretization
    with_load: bool
    has_moment: bool
    node_constants: NodeConstants | None = None


def envelope_forces(tubes, res: ForceState, partials=None, tip_partials=None):
    """``tau_D = dU*/dD``, ``tau_alpha = dU*/dalpha`` by the envelope theorem: at an equilibrium
    the total derivative equals the partial derivative at fixed coordinates ``q`` (the sections
    move with ``D``, the coordinates are strains on the normalized section coordinate).

    Without tip load the partial derivative is evaluated in closed form
    (:func:`envelope_forces_closed_form`); with a load, whose work moves with ``D`` through the
    whole Magnus chain, by a reverse pass through the layout and the potential
    (:func:`envelope_forces_autograd`, the reference the closed form is tested against), or,
    for a dead tip force given ``tip_partials``, as the closed form of the elastic energy minus
    the force's work along the tip's partials (:func:`envelope_forces_tip_force`).
    ``partials``: the closed form's implementation, ``partials(q, lay, tubes, tab, disc,
    const) -> (tau_D, tau_alpha)`` (a kernel's :attr:`~torchpvs.kernel.Kernel.partials`;
    default :func:`closed_form_partials`); ``tip_partials``: a kernel's
    :attr:`~torchpvs.kernel.Kernel.tip_partials`."""
    if res.with_load:
        if res.has_moment or tip_partials is None:
            return envelope_forces_autograd(tubes, res)
        return envelope_forces_tip_force(tubes, res, partials, tip_partials)
    return envelope_forces_closed_form(tubes, res, partials)


def envelope_forces_tip_force(tubes, res: ForceState, partials, tip_partials):
    """:func:`envelope_forces` under a dead tip force ``F`` (no moment): the potential is
    ``U = E - F . p_tip``, so at fixed ``q`` ``dU/dx = dE/dx - F . dp_tip/dx``: the elastic
    closed form (:func:`closed_form_partials`, on the loaded layout) and the tip position's
    partials ``P_D``, ``P_alpha`` of the kernel's ``tip_partials`` (compiled: a complex step of
    the pose; eager: a reverse pass). Returns ``(tau_D, tau_alpha)``, ``(B, N)`` [N, N·m]."""
    tau_D, tau_A = envelope_forces_closed_form(tubes, res, partials)
    _, PD, PA = tip_partials(res.q.detach(), tubes, res.D.detach(), res.alpha.detach(),
                             res.loaded, res.tab, res.disc, None)
    F = res.F.detach()[:, :, None]
    return tau_D - (F * PD[:, :3]).sum(1), tau_A - (F * PA[:, :3]).sum(1)


def envelope_forces_autograd(tubes, res: ForceState):
    """:func:`envelope_forces` by reverse-mode autograd through ``build_layout`` and the
    potential (any load)."""
    # A reverse pass needs ordinary tensors: the solve may run in inference mode, whose tensors
    # autograd cannot save (clones made outside it are ordinary).
    with torch.inference_mode(False), torch.enable_grad():
        q, F, M, loaded = (t.detach().clone() for t in (res.q, res.F, res.M, res.loaded))
        # (tube rows of a batch of robots may have been indexed in inference mode)
        tubes = tubes.map(lambda t: t.detach().clone())
        D = res.D.detach().clone().requires_grad_(True)
        A = res.alpha.detach().clone().requires_grad_(True)
        lay = build_layout(tubes, D, A, F, M, loaded, res.disc)
        R0 = tip_pose(q, lay, res.tab)[1].detach() if res.has_moment else None
        U = potential(q, lay, res.tab, R0, res.with_load)
        gD, gA = torch.autograd.grad(U.sum(), (D, A))
    return gD.detach(), gA.detach()


def envelope_forces_closed_form(tubes, res: ForceState, partials=None):
    """:func:`envelope_forces` for elements without tip load, in closed form: the partial
    derivatives at fixed ``q`` of the stored energy (docs/physics.md)

        U = sum_k int_k e(u, psi, psi', u*) ds + sum_j 1/2 GJ_j D_j w_j^2 + G(D)

    ``D_l`` moves the section cuts (tube ends ``L_j - D_j`` and transitions ``Ls_j - D_j``,
    sorted), hence the section lengths ``h_k`` (the quadrature weights), the arc length of every
    node, the precurvature there (``u*_j(s - Ls_j + D_j)``) and the tube angles (through
    ``D_j w_j``, the twist of the curved material held in the guide, and the mean torsions
    integrated over the moved lengths); ``G`` is the bending energy of the curved material held
    straight in the guide. ``alpha_l`` enters only through the angles of tube ``l``. The masks
    (which tube is present or curved where) are piecewise constant, and where two cuts coincide
    (a kink) the derivative follows torch's rules for ``sort``, ``clamp`` and ``minimum``, as the
    reverse pass does. Returns ``(tau_D, tau_alpha)``, ``(B, N)`` [N, N·m]."""
    with torch.no_grad():
        D = res.D
        lay = res.lay
        if lay is None or lay.D.shape != D.shape or not torch.equal(lay.D, D):
            lay = build_layout(tubes, D, res.alpha, res.F, res.M, res.loaded, res.disc)
        return (partials or closed_form_partials)(res.q, lay, tubes, res.tab, res.disc,
                                                  res.node_constants)


def closed_form_partials(q, lay: Layout, tubes, tab: Tables, disc: Discretization,
                         const: NodeConstants | None = None):
    """The body of :func:`envelope_forces_closed_form` on a layout ``lay`` of the insertions:
    ``(dU/dD, dU/dalpha)`` at ``q``, elastic energy only. Differentiable: with ``lay`` built
    from insertions and rotations that require grad (and ``q`` too), one reverse pass gives the
    second derivatives ``U_Dq``, ``U_DD``, ``U_Dalpha``
    (:func:`torchpvs.jacobians.actuator_stiffness`). ``const``: the layout's
    :func:`~torchpvs.mechanics.node_constants` at the quadrature nodes, where known (no
    gradient with respect to the layout then flows through them)."""
    D = lay.D
    B, N = D.shape
    f = node_fields(q, lay, tab.xq, tab.phi_q, tab.Q_q, const)
    dt, dev = q.dtype, q.device
    L, Ls = tubes.length.expand(B, N), tubes.straight.expand(B, N)
    coef = lay.coef                                                   # (B, N, 3, P)
    P = coef.shape[-1]
    w = q[:, :N] * lay.qmask[:, :N]
    # d(cut)/dD of the unsorted cuts [ell, tau_clip] (each moves with its own tube only).
    ell_raw, tau = L - D, Ls - D
    dell = -(ell_raw >= 0).to(dt)
    tau0, ell = tau.clamp(min=0.0), ell_raw.clamp(min=0.0)
    dtau0 = -(tau >= 0).to(dt)
    dtau = torch.where(tau0 < ell, dtau0, torch.where(tau0 > ell, dell, 0.5 * (dtau0 + dell)))
    _, perm = torch.sort(torch.cat([ell, tau0.minimum(ell)], -1), dim=-1)  # as build_layout
    dsrc = torch.cat([dell, dtau], -1)
    tube_of = perm % N                                               # (B, S)
    onehot = (tube_of[..., None] == torch.arange(N, device=dev)).to(dt)
    dcut = onehot * torch.gather(dsrc, 1, perm)[..., None]           # (B, S, N): d cut_k/dD_l
    dstart = torch.cat([torch.zeros_like(dcut[:, :1]), dcut[:, :-1]], 1)
    dh = dcut - dstart
    # Guide: t_guide = clamp(min(D, L) - Ls, 0), d/dD as torch's rules give it.
    Dm = torch.minimum(D, L)
    dmin = torch.where(D < L, 1.0, torch.where(D > L, 0.0, 0.5)).to(dt)
    dtg = dmin * (Dm - Ls >= 0).to(dt)
    tg = (Dm - Ls).clamp(min=0.0)
    u_g = poly(coef, tg)                                             # (B, N, 3) at t_guide
    # Node quantities (B, S, Q, ...): weights, densities and partial derivatives.
    xq, wq = tab.xq, tab.wq
    W = lay.W                                                        # (B, S, Q)
    EIp = lay.EI[:, None, None, :] * lay.present[:, :, None, :]      # (B, S, 1, N)
    GJp = lay.GJ[:, None, None, :] * lay.present[:, :, None, :]
    ux, uy = f.u.unbind(-1)
    Rx, Ry = f.Ru.unbind(-1)
    ex, ey = ux[..., None] - Rx, uy[..., None] - Ry                  # (B, S, Q, N)
    tors = f.dpsi - f.ustar[..., 2]
    dens = sum_dim(0.5 * EIp * (ex * ex + ey * ey) + 0.5 * GJp * tors * tors, -1)
    gpsi = W[..., None] * EIp * (Ry * ux[..., None] - Rx * uy[..., None])   # W de/dpsi
    # de/du*_j . du*_j/dt, with du*/dt the derivative of the precurvature polynomial.
    if P > 1:
        dcoef = coef[..., 1:] * torch.arange(1, P, dtype=dt, device=dev)
        t = f.s[..., None] - lay.tau[:, None, None, :]               # (B, S, Q, N)
        dus = poly(dcoef[:, None, None], t) * lay.curved[:, :, None, :, None]
        cs, sn = torch.cos(f.psi), torch.sin(f.psi)
        px, py = cs * dus[..., 0] - sn * dus[..., 1], sn * dus[..., 0] + cs * dus[..., 1]
        gstar = -W[..., None] * (EIp * (ex * px + ey * py) + GJp * tors * dus[..., 2])
    else:
        gstar = torch.zeros_like(gpsi)
    # d s_node / dD_l = dstart_k + (xi + 1)/2 dh_k; the precurvature argument s - Ls_j + D_j
    # moves by that plus delta_jl.
    frac = 0.5 * (xq + 1.0)                                          # (Q,)
    ds = dstart[:, :, None, :] + frac[:, None] * dh[:, :, None, :]   # (B, S, Q, N_l)
    # Angles: psi_kij = psi0_j + D_j w_j + sum_{k'<k} h_k' c_k'j0 + h_k/2 sum_p Q_ip c_kjp.
    n = disc.n_basis
    c = (q[:, N:] * lay.qmask[:, N:]).reshape(B, -1, 2 + N, n)[:, :, 2:, :]   # (B, S, N, n)
    loc = 0.5 * (c @ tab.Q_q.transpose(-1, -2)).transpose(-1, -2)  # (B, S, Q, N): /h
    step = dh[:, :, None, :] * c[:, :, :, :1]                           # (B, S, N_j, N_l)
    before = torch.cumsum(step, 1) - step           # sum over k' < k of dh_k'l c_k'j0
    g0 = w + u_g[..., 2] * dtg                                       # (B, N)
    # guide twist energy and the bending energy held straight in the guide
    tau_D = 0.5 * lay.GJ * w * w + 0.5 * lay.EI * (u_g[..., 0] ** 2 + u_g[..., 1] ** 2) * dtg
    # quadrature weights W = h/2 w_i (active sections)
    tau_D = tau_D + torch.einsum("bsq,q,bsl->bl", dens, 0.5 * wq,
                                 dh * lay.active[..., None])
    # angles: own-tube shift, earlier sections' mean torsion, this section's local term
    Gp = gpsi.sum(2)                                                 # (B, S, N_j)
    tau_D = tau_D + g0 * Gp.sum(1)
    tau_D = tau_D + torch.einsum("bsj,bsjl->bl", Gp, before)
    tau_D = tau_D + torch.einsum("bsqj,bsl->bl", gpsi * loc, dh)
    # precurvature arguments
    tau_D = tau_D + torch.einsum("bsqj,bsql->bl", gstar, ds) + gstar.sum((1, 2))
    tau_A = Gp.sum(1)
    return tau_D, tau_A


def actuation_rows(q: torch.Tensor, tubes, D: torch.Tensor, alpha: torch.Tensor,
                   loaded: torch.Tensor, tab: Tables, disc: Discretization,
                   rotations: bool = False, layout: Layout | None = None):
    """Rows of the unloaded energy's Hessian at fixed ``q (B, nq)`` for the actuators ``x`` =
    the insertions (``m = N`` rows) or, with ``rotations``, the insertions then the rotations
    (``m = 2N``): ``(U_xq (B, m, nq), U_xD (B, m, N), U_xalpha (B, m, N), qmask (B, nq))``,
    ``qmask`` the active coordinates of the layout at ``D`` (a kernel's
    :attr:`~torchpvs.kernel.Kernel.actuation_rows`, for the actuator stiffness
    :func:`torchpvs.jacobians.actuator_stiffness`). :func:`closed_form_partials`
    differentiated once, in ONE reverse pass over the batch repeated ``m`` times (replica ``r``
    of an element back-propagates its ``tau_x[r]``): the torch op count, not the flops, bounds
    it at small batches. ``tubes`` broadcastable to ``(B, N)``; ``loaded (B,)`` the layout's
    load flags; ``layout``: the layout at ``D`` and ``alpha`` where the caller has it (unused
    here: the reverse pass needs its own, built from inputs that require grad)."""
    B, N = D.shape
    m = 2 * N if rotations else N
    idx = torch.arange(B, device=D.device).repeat_interleave(m)
    tb = tube_rows(tubes, idx)
    qr, Dr, Ar = (t.detach()[idx].requires_grad_(True) for t in (q, D, alpha))
    zero = torch.zeros(B * m, 3, dtype=q.dtype, device=q.device)
    pick = torch.eye(m, dtype=q.dtype, device=q.device).repeat(B, 1)        # (B m, m)
    with torch.enable_grad():
        lay = build_layout(tb, Dr, Ar, zero, zero, loaded[idx], disc)
        tau = closed_form_partials(qr, lay, tb, tab, disc)
        tau = torch.cat(tau, -1) if rotations else tau[0]
        Gq, GD, GA = (g.reshape(B, m, -1) for g in
                      torch.autograd.grad((tau * pick).sum(), (qr, Dr, Ar)))
    return Gq, GD, GA, lay.qmask.detach().reshape(B, m, -1)[:, 0]


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


def paper_actuation(tubes, res: ForceState, tol: float = 1e-12):
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

    q, lay, disc = res.q.detach(), res.lay, res.disc
    D = res.D
    B, N = D.shape
    paper_scope_check(tubes, D, (res.F.abs().sum(-1) > 0) | (res.M.abs().sum(-1) > 0), tol)
    coef = tubes.coef.expand(B, N, 3, tubes.coef.shape[-1])

    n_q = disc.n_basis * 2 + coef.shape[-1] + 6
    xg, wg = gauss_legendre(n_q, dtype=q.dtype, device=q.device)
    ends = torch.tensor([-1.0, 1.0], dtype=q.dtype, device=q.device)
    x_all = torch.cat([xg, ends])
    phi, Qb = legendre_basis(x_all, disc.n_basis)
    with torch.no_grad():
        f = node_fields(q, lay, x_all, phi, Qb)
        Ru, dpsi, psi = f.Ru, f.dpsi, f.psi                           # (B, S, G+2, ...)
        G = xg.shape[0]
        present = lay.present > 0.5                                 # (B, S, N)
        # Unloaded: the internal moment vanishes on the whole free part, so the bending is the
        # stiffness-weighted average of the rotated precurvatures (the closure of the exact
        # solution; more accurate at the section ends than the bending polynomial itself).
        EIp = lay.EI[:, None, None, :] * present[:, :, None, :]
        u = (EIp[..., None] * Ru).sum(-2) / EIp.sum(-1, keepdim=True).clamp(
            min=torch.finfo(EIp.dtype).tiny)                 # (1e-300 is 0 in float32)
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
        t = f.s[..., :G] - lay.tau[:, None, None, 1]               # (B, S, G)
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


class KinkPlan(NamedTuple):
    """Where ``U*(D)`` has a kink and the one-sided states to evaluate (:func:`kink_plan`):
    ``kink``, ``blocked`` ``(B, N)`` masks; for the kinks, batch rows and tubes ``rows_b``,
    ``rows_j``, the rows of the one-sided states ``sel`` (every kink's retraction side, then the
    insertion sides that can move) with their tube ``sj`` and insertions ``Dn``. ``sel`` is
    None without kinks."""

    kink: torch.Tensor
    blocked: torch.Tensor
    rows_b: torch.Tensor | None
    rows_j: torch.Tensor | None
    sel: torch.Tensor | None
    sj: torch.Tensor | None
    Dn: torch.Tensor | None


KINK_DELTA = 1e-7
"""[m] how far from a kink of ``U*(D)`` its one-sided values are taken (the error is O(delta))."""
KINK_TOL = 1e-9
"""[m] an insertion this close to a tube's base, transition or end at the orifice is at it."""


def kink_mask(tubes, D: torch.Tensor, tol: float = KINK_TOL) -> torch.Tensor:
    """``(B, N)`` bool: ``U*(D_j)`` has a kink at insertions ``D (B, N)`` [m] (a tube's base,
    straight-to-curved transition or end at the orifice, or a moving cut meeting another
    tube's), so that derivatives in ``D_j`` are one-sided there."""
    B, N = D.shape
    L = tubes.length.expand(B, N)
    Ls = tubes.straight.expand(B, N)
    curved = tubes.coef.abs().sum((-1, -2)).expand(B, N) > 0
    exposed = L - D > tol
    return ((D <= tol) & exposed) | (((Ls - D).abs() <= tol) & curved & (L > Ls)) \
        | ((L - D).abs() <= tol) | _coinciding_cuts(L, Ls, D, curved, tol)


def kink_plan(tubes, D: torch.Tensor, delta: float, tol: float) -> KinkPlan:
    """:class:`KinkPlan` of insertions ``D (B, N)``: it depends on the insertions and the tubes
    only, so a solve that keeps them reuses it (``equilibrium_forces(cache=...)``)."""
    kink = kink_mask(tubes, D, tol)
    prev = torch.cat([torch.zeros_like(D[:, :1]), D[:, :-1]], -1)
    blocked = D - delta < prev
    idx = kink.nonzero()
    if idx.numel() == 0:
        return KinkPlan(kink, blocked, None, None, None, None, None)
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
    return KinkPlan(kink, blocked, rows_b, rows_j, sel, sj, Dn)


def equilibrium_forces(tubes, res: ForceState, resolve, delta: float = KINK_DELTA,
                       tol: float = KINK_TOL, cache=None, partials=None, tip_partials=None):
    """Actuation forces and torques ``(B, N)`` at the equilibrium ``res``,
    with one-sided insertion forces where ``U*(D_j)`` has a kink: material of tube ``j`` changing
    kind exactly at the orifice -- its base (``D_j = 0``: the guide torsion appears), its
    straight-to-curved transition (``D_j = Ls_j``: curvature enters the guide) or its end
    (``D_j = L_j``) -- or a cut that moves with ``D_j`` meeting another tube's. There the
    derivative differs for insertion and retraction. Each side is taken at an equilibrium
    ``delta`` away on that side (where ``U*`` is smooth), from ``resolve(insertions, rows) ->``
    :class:`ForceState` (usually no solve; a
    step for the coordinates of a section of length ``delta`` that appears, or at most one
    Newton step); the error is ``O(delta)``. The equilibrium and every kink side go
    through ONE envelope-theorem evaluation (in closed form without tip load, else one reverse
    pass).

    ``cache(key, compute)``: where given, the kink analysis (:func:`kink_plan`) is kept with
    the solve's layout (``torchpvs.plan.Plan.cached``) and reused while the insertions are.
    ``partials``, ``tip_partials``: the kernel's closed form and tip partials
    (:func:`envelope_forces`).

    Returns ``(forces = retraction side, torques, insertion side, kink mask)``, all ``(B, N)``;
    the insertion side is NaN where the carriage cannot move in (blocked by the next base).
    """
    D = res.D
    B = D.shape[0]

    def analyse():
        return kink_plan(tubes, D, delta, tol)

    kp = analyse() if cache is None else cache(("kinks", delta, tol), analyse)
    kink, blocked = kp.kink.clone(), kp.blocked      # the cached mask is not handed out

    def with_constants(state: ForceState, name: str) -> ForceState:
        # The closed form's node constants depend on the layouts only, which the cache keeps
        # (the sides' layout follows from the solve's: same insertions, same kink plan).
        if cache is None or state.with_load or state.lay.D.shape != state.D.shape:
            return state
        xq = state.tab.xq
        return state._replace(node_constants=cache(
            (name, delta, tol), lambda: node_constants(state.lay, xq)))

    if kp.sel is None:
        forces, torques = envelope_forces(tubes, with_constants(res, "force_nodes"), partials,
                                          tip_partials)
        insertion = forces.clone()
        insertion[blocked] = float("nan")
        return forces, torques, insertion, kink
    rows_b, rows_j, sel, sj, Dn = kp.rows_b, kp.rows_j, kp.sel, kp.sj, kp.Dn
    side = resolve(Dn, sel)
    both = res._replace(q=torch.cat([res.q, side.q]), D=torch.cat([res.D, side.D]),
                        alpha=torch.cat([res.alpha, side.alpha]), F=torch.cat([res.F, side.F]),
                        M=torch.cat([res.M, side.M]),
                        loaded=torch.cat([res.loaded, side.loaded]), node_constants=None)
    if side.lay is not None:     # the sides' layout, built by the re-solve: no second build
        both = both._replace(lay=type(res.lay)(*(torch.cat(pair) for pair in
                                                 zip(res.lay, side.lay, strict=True))))
    tubes_both = tube_rows(tubes, torch.cat([torch.arange(B, device=sel.device), sel]))
    allf, allt = envelope_forces(tubes_both, with_constants(both, "force_nodes_sides"),
                                 partials, tip_partials)
    forces, torques, vals = allf[:B], allt[:B], allf[B:][torch.arange(len(sel)), sj]
    insertion = forces.clone()
    insertion[blocked] = float("nan")
    n_r = len(rows_b)
    retract = forces.clone()
    retract[rows_b, rows_j] = vals[:n_r]
    insertion[sel[n_r:], sj[n_r:]] = vals[n_r:]
    return retract, torques, insertion, kink
