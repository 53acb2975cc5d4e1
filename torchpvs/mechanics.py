"""Stage 4 — strains, energy and the total potential of the discrete PVS model.

The equilibrium is a stationary point of the total potential (docs/physics.md): the paper's
projected
equations (26)/(33)/(35), generalized to N tubes, are its gradient. With the backbone bending
``u`` in a twist-free frame and tube angles ``psi_j`` about the tangent, tube ``j`` has bending
``Rz(psi_j)^T u`` and torsion ``psi_j'``, so

    U = sum_j int_free 1/2 EI_j |u - Rz(psi_j) u*_j|^2 + 1/2 GJ_j (psi_j' - u*_jz)^2 ds
      + sum_j 1/2 GJ_j D_j w_j^2  +  (stored energy of precurved material held in the guide)
      - F . p_tip  -  (virtual work of the tip moment)

All functions here are batch-agnostic (``...`` leading dims) so that they run on a batch directly
and per element under ``torch.func.vmap`` (for exact Hessians).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import torch

from .lie import exp_se3, rot_z
from .sections import build_layout, tube_rows

if TYPE_CHECKING:
    from .sections import Discretization, Layout, Tables

__all__ = ["Maps", "NodeConstants", "NodeFields", "PoseConstants", "angle_offsets",
           "compact_hessian", "compact_q", "elastic_energy", "expand_hessian", "expand_q",
           "magnus_twists", "node_constants", "node_fields", "poly", "pose_constants",
           "pose_node_constants", "potential", "section_start_poses", "split_q", "start_angles",
           "sum_dim", "tip_partials", "tip_pose", "tip_twist"]


def sum_dim(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x.sum(dim)``, by explicit adds when the dimension is short (tubes, components): torch's
    CPU reduction over a dimension of size 2-4 is 10-50x slower than an add of its slices
    (float64, torch 2.13: a size-2 sum over 150k elements took 2.3 ms, the add 7 us)."""
    n = x.shape[dim]
    if n > 4 or n < 2:
        return x.sum(dim)
    parts = x.unbind(dim)
    out = parts[0] + parts[1]
    for p in parts[2:]:
        out = out + p
    return out


def poly(coef: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``coef (..., N, 3, P)``, ``t (..., N)`` -> ``(..., N, 3)``."""
    P = coef.shape[-1]
    out = coef[..., P - 1].expand(t.shape + (3,))    # Horner from the leading coefficient
    for p in range(P - 2, -1, -1):
        out = out * t[..., None] + coef[..., p]
    return out


def _poly_int(coef: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``int_0^t`` of the z-polynomial: ``coef (..., N, P)``, ``t (..., N)`` -> ``(..., N)``."""
    P = coef.shape[-1]
    out = coef[..., P - 1] / P * t
    for p in range(P - 2, -1, -1):
        out = (out + coef[..., p] / (p + 1)) * t
    return out


def split_q(q: torch.Tensor, lay: Layout):
    """``q (..., nq)`` -> guide twists ``w (..., N)``, bending ``a (..., S, 2, n)``,
    torsion ``c (..., S, N, n)``; inactive coordinates are zeroed by the mask."""
    N = lay.EI.shape[-1]
    S = lay.h.shape[-1]
    q = q * lay.qmask
    w = q[..., :N]
    X = q[..., N:].reshape(q.shape[:-1] + (S, 2 + N, -1))
    return w, X[..., :2, :], X[..., 2:, :]


class NodeConstants(NamedTuple):
    """The ``q``-independent part of :func:`node_fields` at ``G`` normalized points of every
    section (:func:`node_constants`; ``S`` section slots, ``N`` tubes).

    Attributes:
        s: ``(..., S, G)`` [m] arc length of the points.
        ustar: ``(..., S, G, N, 3)`` [1/m] the tubes' precurvatures there, in their material
            frames (zero where a tube is absent or straight).
        presc_local: ``(..., S, G, N)`` [rad] the twist of a prescribed (single-tube) section
            from its start to the point (zero elsewhere).
        presc_inc: ``(..., S, N)`` [rad] a prescribed section's whole twist.
        pmask: ``(..., S, N)`` float 0/1, the tube of a prescribed section where it is curved.
    """

    s: torch.Tensor
    ustar: torch.Tensor
    presc_local: torch.Tensor
    presc_inc: torch.Tensor
    pmask: torch.Tensor


class NodeFields(NamedTuple):
    """Strains and angles at ``G`` normalized points of every section (:func:`node_fields`;
    ``S`` section slots, ``N`` tubes).

    Attributes:
        s: ``(..., S, G)`` [m] arc length of the points.
        u: ``(..., S, G, 2)`` [1/m] backbone bending in the twist-free frame.
        psi: ``(..., S, G, N)`` [rad] tube angles about the tangent.
        dpsi: ``(..., S, G, N)`` [1/m] tube torsions ``psi'``.
        ustar: ``(..., S, G, N, 3)`` [1/m] precurvatures in the tube frames.
        Ru: ``(..., S, G, N, 2)`` [1/m] ``Rz(psi) u*_xy``, the precurvatures in the backbone
            frame.
        inc: ``(..., S, N)`` [rad] each section's angle increment (:func:`angle_offsets`).
        psi_start: ``(..., S, N)`` [rad] the angles at each section's start.
        psi0: ``(..., N)`` [rad] the angles at the orifice.
    """

    s: torch.Tensor
    u: torch.Tensor
    psi: torch.Tensor
    dpsi: torch.Tensor
    ustar: torch.Tensor
    Ru: torch.Tensor
    inc: torch.Tensor
    psi_start: torch.Tensor
    psi0: torch.Tensor


class PoseConstants(NamedTuple):
    """What :func:`tip_pose` needs of a layout at the Magnus points, on its *nonempty*
    sections only (:func:`pose_node_constants`; ``S_p`` the batch's most nonempty sections,
    ``G`` Magnus points, ``N`` tubes). Every field has the leading batch dim ``B``.

    Attributes:
        sec: ``(B, S_p)`` long, the section slots kept, in backbone order, padded with empty
            ones.
        h: ``(B, S_p)`` [m] their lengths.
        presc_inc: ``(B, S_p, N)`` [rad] a prescribed section's whole twist.
        ustar_held: ``(B, S_p, G, N, 2)`` [1/m] the in-plane precurvature of the tube of a
            prescribed (single-tube) section, zero elsewhere.
        presc_local: ``(B, S_p, G, N)`` [rad] a prescribed section's twist up to each point.
    """

    sec: torch.Tensor
    h: torch.Tensor
    presc_inc: torch.Tensor
    ustar_held: torch.Tensor
    presc_local: torch.Tensor


def node_constants(lay: Layout, xi: torch.Tensor) -> NodeConstants:
    """The ``q``-independent part of :func:`node_fields` at normalized points ``xi (G,)``
    (:class:`NodeConstants`). It depends on the insertions only, so a solve that keeps them
    computes it once per layout (:func:`build_maps` stores it for the Magnus nodes)."""
    h, start = lay.h, lay.start
    curved, presc = lay.curved, lay.presc
    s = start[..., None] + 0.5 * (xi + 1.0) * h[..., None]                 # (..., S, G)
    t = s[..., None] - lay.tau[..., None, None, :]                      # (..., S, G, N)
    coef = lay.coef[..., None, None, :, :, :]                           # (..., 1, 1, N, 3, P)
    ustar = poly(coef, t) * curved[..., None, :, None]
    # Prescribed sections: strain = precurvature (twist u*_z integrated exactly).
    zc = lay.coef[..., 2, :][..., None, :, :]                           # (..., 1, N, P)
    t0 = start[..., None] - lay.tau[..., None, :]                       # (..., S, N)
    Z0 = _poly_int(zc, t0)
    pmask = curved * presc[..., None]                                      # (..., S, N)
    Zt = _poly_int(zc[..., None, :, :], t)
    presc_local = (Zt - Z0[..., None, :]) * pmask[..., None, :]
    presc_inc = (_poly_int(zc, t0 + h[..., None]) - Z0) * pmask
    return NodeConstants(s=s, ustar=ustar, presc_local=presc_local, presc_inc=presc_inc,
                         pmask=pmask)


def pose_node_constants(lay: Layout, xi: torch.Tensor) -> PoseConstants:
    """What :func:`tip_pose` needs of the layout at the Magnus points ``xi (G,)``, on the
    *nonempty* sections only (:class:`PoseConstants`).

    An empty section is an identity step of the pose and adds no angle, so leaving it out
    changes nothing (the product over the other sections keeps its order); it saves the node
    math, exponentials and products of the empty slots (half of the six of the three-tube
    preset, a quarter of the Fig. 3 robot's four). Built once per layout (a host sync for
    ``S_p``): :func:`build_maps` keeps it for the solver."""
    return _pose_sections(lay, node_constants(lay, xi))


def _pose_sections(lay: Layout, c: NodeConstants) -> PoseConstants:
    """:func:`pose_node_constants` from the layout's :func:`node_constants` ``c``."""
    B, S = lay.h.shape
    nonempty = lay.h > 0
    Sp = max(1, int(nonempty.sum(-1).amax()))
    sec = torch.argsort((~nonempty).to(torch.int8), dim=-1, stable=True)[:, :Sp]

    def take_sections(t):                      # (B, S, ...) -> (B, S_p, ...)
        return torch.gather(t, 1, sec.reshape((B, Sp) + (1,) * (t.ndim - 2)).expand(
            (B, Sp) + t.shape[2:]))

    held = (lay.presc[..., None] * lay.present)[:, :, None, :, None]     # (B, S, 1, N, 1)
    return PoseConstants(sec=sec, h=take_sections(lay.h),
                         presc_inc=take_sections(c.presc_inc),
                         ustar_held=take_sections(c.ustar[..., :2] * held),
                         presc_local=take_sections(c.presc_local))


def angle_offsets(w: torch.Tensor, c: torch.Tensor, lay: Layout, presc_inc: torch.Tensor,
                  h: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Tube angles at the orifice ``psi0 (..., N)`` = base rotation, twist of the curved material
    held in the guide and ``D_j w_j``, and each section's angle increment ``inc (..., S, N)`` =
    ``h_k`` times its mean torsion (plus a prescribed section's twist ``presc_inc``, from
    :func:`node_constants`). ``w``, ``c``: the guide twists and torsion coefficients of
    :func:`split_q`; ``h``: the section lengths of ``c``'s sections (default the layout's; a
    subset of them for :func:`pose_node_constants`). The angle at the start of section ``k`` is
    ``psi0`` plus the increments of the sections before it (:func:`start_angles`), whatever the
    evaluation points."""
    h = lay.h if h is None else h
    return lay.psi0 + lay.D * w, h[..., None] * c[..., 0] + presc_inc


def start_angles(psi0: torch.Tensor, inc: torch.Tensor) -> torch.Tensor:
    """``(..., S, N)``: the tube angles at the start of every section, ``psi0 (..., N)`` plus the
    increments ``inc (..., S, N)`` of the sections before it (:func:`angle_offsets`)."""
    return psi0[..., None, :] + torch.cumsum(inc, -2) - inc


def node_fields(q: torch.Tensor, lay: Layout, xi: torch.Tensor,
                phi: torch.Tensor, Qb: torch.Tensor,
                const: NodeConstants | None = None) -> NodeFields:
    """Strains and angles at normalized points ``xi (G,)`` of every section
    (:class:`NodeFields`). ``phi``, ``Qb``: the basis and its integrals at ``xi`` (``(G, n)``
    or ``(..., S, G, n)``). ``const``: :func:`node_constants` of the same layout and points
    (computed when ``None``; pass it only where no gradient with respect to the layout is
    wanted).
    """
    if const is None:
        const = node_constants(lay, xi)
    w, a, c = split_q(q, lay)
    h, present, presc = lay.h, lay.present, lay.presc
    ustar, pmask = const.ustar, const.pmask
    # phi/Qb are (G, n) or (..., S, G, n): matmul broadcasts over both.
    u = (a @ phi.transpose(-1, -2)).transpose(-1, -2)                    # (..., S, G, 2)
    dpsi = (c @ phi.transpose(-1, -2)).transpose(-1, -2)                 # (..., S, G, N)
    psi0, inc = angle_offsets(w, c, lay, const.presc_inc)
    psi_start = start_angles(psi0, inc)
    psi = (psi_start[..., None, :] + 0.5 * h[..., None, None] *
           (c @ Qb.transpose(-1, -2)).transpose(-1, -2) + const.presc_local)
    cs, sn = torch.cos(psi), torch.sin(psi)
    ux, uy = ustar[..., 0], ustar[..., 1]
    Rx, Ry = cs * ux - sn * uy, sn * ux + cs * uy
    Ru = torch.stack([Rx, Ry], -1)
    held = (presc[..., None] * present)[..., None, :]                    # (..., S, 1, N)
    u = u + torch.stack([sum_dim(Rx * held, -1), sum_dim(Ry * held, -1)], -1)
    dpsi = dpsi + pmask[..., None, :] * ustar[..., 2]
    return NodeFields(s=const.s, u=u, psi=psi, dpsi=dpsi, ustar=ustar, Ru=Ru, inc=inc,
                      psi_start=psi_start, psi0=psi0)


def elastic_energy(q: torch.Tensor, lay: Layout, tab: Tables) -> torch.Tensor:
    """Stored elastic energy ``(...,)`` [J] of the whole robot, guide included."""
    f = node_fields(q, lay, tab.xq, tab.phi_q, tab.Q_q)
    EI, GJ = lay.EI[..., None, None, :], lay.GJ[..., None, None, :]
    Rx, Ry = f.Ru.unbind(-1)
    ux, uy = f.u.unbind(-1)
    dx, dy = ux[..., None] - Rx, uy[..., None] - Ry
    bend = 0.5 * EI * (dx * dx + dy * dy)
    tors = 0.5 * GJ * (f.dpsi - f.ustar[..., 2]) ** 2
    dens = sum_dim((bend + tors) * lay.present[..., None, :], -1)       # (..., S, Q)
    w, _, _ = split_q(q, lay)
    guide = sum_dim(0.5 * lay.GJ * lay.D * w**2, -1)
    return (dens * lay.W).sum((-1, -2)) + guide + lay.guide_const


def magnus_twists(u: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The 4th-order Magnus exponents ``Omega (..., m, 6)`` of the backbone for the twists
    ``xi = ((ux, uy, 0), e3)`` at the two Gauss points of each of ``m`` steps of length
    ``h (...,)`` (``u (..., m, 2, 2)``: step, Gauss point, component). The general formula
    (:func:`torchpvs.lie.magnus4_step`) reduces to closed form: ``[xi1, xi2]`` has the angular
    part ``(0, 0, u1 x u2)`` and the linear part ``(u1 - u2) x e3``."""
    u1, u2 = u[..., 0, :], u[..., 1, :]
    h = h[..., None]
    k = (3.0**0.5 / 12.0) * h * h
    mid = 0.5 * h[..., None] * (u1 + u2)
    du = k[..., None] * (u1 - u2)
    cross = k * (u1[..., 0] * u2[..., 1] - u1[..., 1] * u2[..., 0])
    return torch.stack([mid[..., 0], mid[..., 1], cross, du[..., 1], -du[..., 0],
                        h.expand_as(cross)], -1)


def section_start_poses(q: torch.Tensor, lay: Layout, tab: Tables,
                        const: NodeConstants | None = None
                        ) -> tuple[torch.Tensor, NodeFields]:
    """Poses ``(..., S + 1, 4, 4)`` of the backbone frame at every cut (orifice first, tip last),
    by the 4th-order Magnus scheme with ``n_magnus`` steps per section. ``const``: the
    :func:`node_constants` of the Magnus nodes (see :func:`node_fields`); the second return
    value is the :class:`NodeFields` there."""
    f = node_fields(q, lay, tab.xm, tab.phi_m, tab.Q_m, const)
    u = f.u                                                             # (..., S, 2m, 2)
    m = u.shape[-2] // 2
    omega = magnus_twists(u.reshape(u.shape[:-2] + (m, 2, 2)), lay.h / m)  # (..., S, m, 6)
    steps = exp_se3(omega)                                                 # (..., S, m, 4, 4)
    # Product of the m steps of every section by pairwise (tree) reduction: log2(m) batched
    # matmuls instead of m sequential ones (op count, not flops, bounds small batches).
    sec = _ordered_product(steps)                                          # (..., S, 4, 4)
    S = sec.shape[-3]
    g = torch.eye(4, dtype=q.dtype, device=q.device).expand(sec.shape[:-3] + (4, 4))
    poses = [g]
    for k in range(S):
        g = g @ sec[..., k, :, :]
        poses.append(g)
    return torch.stack(poses, -3), f


def _tip_frame(q: torch.Tensor, lay: Layout, tab: Tables, const: PoseConstants):
    """The backbone frame at the tip ``(..., 4, 4)``, the tube angles at the orifice
    ``(..., N)`` and the angle increments of the nonempty sections ``(..., S_p, N)``, from the
    :func:`pose_node_constants` ``const``: :func:`section_start_poses` restricted to what the
    tip needs. Bending: the coefficients of active sections, plus ``Rz(psi) u*`` of the tube
    of a prescribed one (``ustar_held``; only there are the tube angles at the nodes needed)."""
    w, a, c = split_q(q, lay)
    sec, h = const.sec, const.h                   # (..., S_p): also per element (vmap)
    Sp = sec.shape[-1]
    # (q may carry leading dims beyond the layout's: several coordinate sets per element)
    a = torch.gather(a, -3, sec[..., None, None].expand(a.shape[:-3] + (Sp,) + a.shape[-2:]))
    c = torch.gather(c, -3, sec[..., None, None].expand(c.shape[:-3] + (Sp,) + c.shape[-2:]))
    phi, Qb = tab.phi_m, tab.Q_m
    psi0, inc = angle_offsets(w, c, lay, const.presc_inc, h)       # the kept sections
    psi_start = start_angles(psi0, inc)
    psi = (psi_start[..., None, :] + 0.5 * h[..., None, None] *
           (c @ Qb.transpose(-1, -2)).transpose(-1, -2) + const.presc_local)
    cs, sn = torch.cos(psi), torch.sin(psi)
    us = const.ustar_held
    ux, uy = us[..., 0], us[..., 1]
    u = (a @ phi.transpose(-1, -2)).transpose(-1, -2)                    # (B, S_p, G, 2)
    u = u + torch.stack([sum_dim(cs * ux - sn * uy, -1), sum_dim(sn * ux + cs * uy, -1)], -1)
    m = u.shape[-2] // 2
    sec_g = _ordered_product(exp_se3(magnus_twists(u.reshape(u.shape[:-2] + (m, 2, 2)),
                                                   h / m)))                # (..., S_p, 4, 4)
    g = sec_g[..., 0, :, :]
    for k in range(1, Sp):
        g = g @ sec_g[..., k, :, :]
    return g, psi0, inc


def _ordered_product(mats: torch.Tensor) -> torch.Tensor:
    """``mats[..., 0, :, :] @ mats[..., 1, :, :] @ ... `` over dim -3, by pairwise reduction."""
    while mats.shape[-3] > 1:
        k = mats.shape[-3]
        if k % 2:
            mats, last = mats[..., :-1, :, :], mats[..., -1:, :, :]
        else:
            last = None
        mats = mats[..., 0::2, :, :] @ mats[..., 1::2, :, :]
        if last is not None:
            mats = torch.cat([mats[..., :-1, :, :], mats[..., -1:, :, :] @ last], -3)
    return mats[..., 0, :, :]


def tip_pose(q: torch.Tensor, lay: Layout, tab: Tables, const: PoseConstants | None = None):
    """Tip position ``(..., 3)`` and the material frame ``(..., 3, 3)`` of the tube forming the
    tip (base frame), plus the tube angles at the tip ``(..., N)``. ``const``: the
    :func:`pose_node_constants` of the Magnus nodes (:func:`pose_constants`; the nonempty
    sections only), or ``None`` (every section; differentiable with respect to the layout)."""
    if const is None:
        poses, f = section_start_poses(q, lay, tab)
        g = poses[..., -1, :, :]
        psi0, inc = f.psi0, f.inc
    else:
        g, psi0, inc = _tip_frame(q, lay, tab, const)
    psi_tip = psi0 + sum_dim(inc, -2)                                       # (..., N)
    angle = sum_dim(psi_tip * lay.tip_tube, -1)
    R = g[..., :3, :3] @ rot_z(angle)
    return g[..., :3, 3], R, psi_tip


def tip_twist(q: torch.Tensor, lay: Layout, tab: Tables) -> torch.Tensor:
    """``(..., 6)`` the tip position and the rotation ``vee(skew(R R0^T))`` (``R0`` the
    detached rotation): its first derivatives are the tip twist's (position [m], spatial
    rotation [rad])."""
    p, R, _ = tip_pose(q, lay, tab)
    return torch.cat([p, skew_vee(R @ R.detach().transpose(-1, -2))], -1)


def tip_partials(q: torch.Tensor, tubes, D: torch.Tensor, alpha: torch.Tensor,
                 loaded: torch.Tensor, tab: Tables, disc: Discretization,
                 layout: Layout | None = None):
    """The tip twist's partials at fixed ``q (B, nq)``: ``(P_q (B, 6, nq), P_D (B, 6, N),
    P_alpha (B, 6, N))``, rows the tip position [m] and spatial rotation [rad] (a kernel's
    :attr:`~torchpvs.kernel.Kernel.tip_partials`, for the closed-form tip Jacobian and
    compliance of :mod:`torchpvs.jacobians`). ONE reverse pass through a fresh layout and
    :func:`tip_pose` over the batch repeated 6 times (replica ``r`` of an element
    back-propagates its row ``r``). ``tubes`` broadcastable to ``(B, N)``; ``loaded (B,)`` the
    layout's load flags; ``layout``: unused here (the pass needs its own, built from inputs
    that require grad). Callable in inference mode (a solve's forces under a tip force): the
    pass runs on ordinary copies."""
    B = q.shape[0]
    with torch.inference_mode(False), torch.enable_grad():
        idx = torch.arange(B, device=q.device).repeat_interleave(6)
        # indexing outside inference mode makes ordinary tensors; shared tube rows are cloned
        # where they are inference tensors (autograd cannot save those)
        tb = tube_rows(tubes, idx).map(lambda t: t.clone() if t.is_inference() else t)
        qr, Dr, Ar = (t.detach()[idx].requires_grad_(True) for t in (q, D, alpha))
        zero = torch.zeros(B * 6, 3, dtype=q.dtype, device=q.device)
        pick = torch.eye(6, dtype=q.dtype, device=q.device).repeat(B, 1)    # (B 6, 6)
        lay = build_layout(tb, Dr, Ar, zero, zero, loaded[idx], disc)
        return tuple(g.reshape(B, 6, -1) for g in torch.autograd.grad(
            (tip_twist(qr, lay, tab) * pick).sum(), (qr, Dr, Ar)))


def skew_vee(A: torch.Tensor) -> torch.Tensor:
    """``vee((A - A^T) / 2)``: the rotation vector of ``A`` to first order near identity."""
    return 0.5 * torch.stack([A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0],
                              A[..., 1, 0] - A[..., 0, 1]], -1)


def potential(q: torch.Tensor, lay: Layout, tab: Tables,
              ref_rotation: torch.Tensor | None = None, with_load: bool = True) -> torch.Tensor:
    """Total potential ``(...,)`` [J]: elastic energy minus the work of the tip load.

    A dead tip force has the potential ``-F . p_tip``. A dead moment is not conservative in 3D;
    its virtual work ``M . delta theta`` (spatial rotation) is represented by
    ``M . vee(skew(R(q) R_ref^T))`` with ``R_ref`` the tip rotation at the same state, passed as
    ``ref_rotation``: differentiated through ``R(q)`` only, its gradient is exactly
    ``J_theta^T M``. Callers that need exact *second* derivatives keep ``R_ref`` attached to the
    graph (a second slot, see :mod:`torchpvs.implicit`); the Newton tangent detaches it and so
    uses the symmetric part of the load stiffness. ``ref_rotation=None`` ignores the moment.
    """
    U = elastic_energy(q, lay, tab)
    if not with_load:
        return U
    p, R, _ = tip_pose(q, lay, tab)
    work = (lay.force * p).sum(-1)
    if ref_rotation is not None:
        work = work + (lay.moment * skew_vee(R @ ref_rotation.transpose(-1, -2))).sum(-1)
    return U - work


# ---------------------------------------------------------------------------------------------
# Exact gradient and Hessian of the elastic energy without autograd.
#
# At every quadrature node (section k, node i) the local fields are *linear* in q:
#   u_ki = sum_p phi_ip a_{k,:,p},   psi'_kij = sum_p phi_ip c_{k,j,p},
#   psi_kij = psi0_j + b_kj . q + (h_k / 2) sum_p Q_ip c_{k,j,p}
# with b_kj = d(psi_j at the start of section k)/dq (D_j on w_j, h_k' on c_{k',j,0}, k' < k).
# With the node density e = sum_j 1/2 EI_j |u - Ru_j|^2 + 1/2 GJ_j (psi_j' - u*_jz)^2,
# Ru_j = Rz(psi_j) u*_j and J = [[0, -1], [1, 0]]:
#   de/du = sum_j EI_j (u - Ru_j),  de/dpsi_j = -EI_j (Ru_j x u),
#   de/dpsi_j' = GJ_j (psi_j' - u*_jz)
#   d2e/du2 = sum_j EI_j I,  d2e/du dpsi_j = -EI_j J Ru_j,  d2e/dpsi_j2 = EI_j u . Ru_j,
#   d2e/dpsi_j'2 = GJ_j.
# Node sums are reduced per (section, tube) first and then placed as small blocks, so no dense
# node-by-coordinate map is ever formed (memory traffic, not flops, bounds large batches). The
# u-u and psi'-psi' blocks do not depend on q and are assembled once per solve.

def angle_bases(lay: Layout, nq: int) -> torch.Tensor:
    """``b_kj = d(psi_j at the start of section k)/dq``: ``(B, S, N, nq)``, i.e. ``D_j`` on the
    guide twist ``w_j`` and ``h_k'`` on the mean torsion ``c_{k',j,0}`` of every earlier section."""
    h = lay.h.detach()
    B, S = h.shape
    N = lay.EI.shape[-1]
    n = (nq - N) // (S * (2 + N))
    dtype, device = h.dtype, h.device
    qmask = lay.qmask.detach()
    lower = torch.tril(torch.ones(S, S, dtype=dtype, device=device), -1)
    eyeN = torch.eye(N, dtype=dtype, device=device)
    X = torch.zeros(B, S, N, S, 2 + N, n, dtype=dtype, device=device)
    X[..., 2:, 0] = torch.einsum("kl,bl,je->bkjle", lower, h, eyeN)
    w = (lay.D.detach()[:, None, None, :] * eyeN).expand(B, S, N, N)
    b = torch.cat([w, X.reshape(B, S, N, -1)], -1)
    return b * qmask[:, None, None, :]


class Maps(NamedTuple):
    """The ``q``-independent structure of one batch's energy, gradient and Hessian on the
    kernel's *compact* coordinates (:func:`build_maps`): ``B`` elements, ``N`` tubes, ``S``
    compact sections (the batch's most active ones; an element's active sections first, in
    backbone order, then padding sections of zero weight), ``Q`` quadrature nodes, ``n`` basis
    functions, ``C = 2 + N`` strain components per section, ``nq_c = N + S C n`` compact
    coordinates. The coordinates are strains [1/m] (the guide twists first), so a Hessian
    entry is in J·m² = N·m³. Every field has the leading batch dim ``B`` except the shared
    tables ``phi``, ``Qb``, ``values_T``, ``Q_QQ``, ``phi_PQ``. A row subset made for a merit
    evaluation (:meth:`torchpvs.newton.Problem.subset`) sets the fields it does not need to
    ``None``.

    Attributes:
        ustar: ``(B, S, Q, N, 3)`` [1/m] precurvatures at the quadrature nodes, tube frames.
        EIw: ``(B, S, Q, N)`` [N·m³] quadrature weight [m] times ``EI`` of the tubes present.
        EIws: ``(B, S, Q)`` [N·m³] ``EIw`` summed over the tubes.
        GJw: ``(B, S, Q, N)`` [N·m³] quadrature weight times ``GJ`` of the tubes present.
        H_sections: ``(B, S, C, n, C, n)`` [N·m³] the ``q``-independent section blocks of the
            Hessian (bending ``A (x) I_2``, torsion ``T_kj``).
        guide: ``(B, nq_c)`` [N·m³] the guide-twist diagonal ``GJ_j D_j`` (zero on the section
            coordinates).
        guide_const: ``(B,)`` [J] the bending energy of the curved material held in the guide.
        h: ``(B, S)`` [m] the compact sections' lengths.
        qmask: ``(B, nq_c)`` float 0/1, the active compact coordinates.
        psi0: ``(B, N)`` [rad] the tube angles at the orifice (the one field that changes with
            the base rotations: :meth:`torchpvs.plan.Plan.layout` replaces it).
        bvec: ``(B, S, N, nq_c)`` [m] the angle bases ``b_kj = d psi_j(start of k) / dq``
            (:func:`angle_bases`) on the compact coordinates.
        cidx: ``(B, nq_c)`` long, each compact coordinate's index in the padded ``q``
            (:func:`compact_q`, :func:`expand_q`).
        presc_inc: ``(B, S_full, N)`` [rad] the prescribed twist of every section slot of the
            layout (``S_full = 2N``; for the tube angles of the outputs).
        phi, Qb: ``(Q, n)`` the basis and its integrals at the quadrature nodes
            (``Tables.phi_q``, ``Tables.Q_q``; shared).
        values_T: ``(n, 2Q)`` basis and integral values from coefficients in one product
            (shared).
        Q_QQ, phi_PQ: ``(Q, n + n^2)`` node sums ``sum_q f_q Q_qp`` with ``sum_q f_q Q_qp Q_qr``
            (and the ``phi`` analogue) in one product (shared).
        pose: the :class:`PoseConstants` of the layout's Magnus nodes (every nonempty
            section, for :func:`tip_pose`).
    """

    ustar: torch.Tensor
    EIw: torch.Tensor
    EIws: torch.Tensor | None
    GJw: torch.Tensor
    H_sections: torch.Tensor | None
    guide: torch.Tensor
    guide_const: torch.Tensor
    h: torch.Tensor
    qmask: torch.Tensor
    psi0: torch.Tensor
    bvec: torch.Tensor
    cidx: torch.Tensor | None
    presc_inc: torch.Tensor | None
    phi: torch.Tensor
    Qb: torch.Tensor
    values_T: torch.Tensor
    Q_QQ: torch.Tensor
    phi_PQ: torch.Tensor
    pose: PoseConstants | None


def build_maps(lay: Layout, tab: Tables, nq: int) -> Maps:
    """Everything the fast energy/gradient/Hessian needs that does not change with ``q``, on
    the *compact* coordinates (:class:`Maps`): the guide twists and the sections that carry
    coordinates (``S_c`` = the most active sections of an element in the batch), active ones
    first in their order along the backbone. Only active sections store ``q``-dependent
    energy (the others have zero weight), so nothing is lost, and the dense per-element
    algebra shrinks from ``nq`` to ``nq_c = N + S_c (2 + N) n`` coordinates (Fig. 3 robot at
    order 2: 50 -> 26). ``maps.cidx (B, nq_c)`` gives each compact coordinate's index in ``q``
    (:func:`compact_q`, :func:`expand_q`). The pose constants (``maps.pose``,
    :func:`pose_node_constants`) keep every nonempty section, ``presc_inc (B, S, N)`` every
    section's prescribed twist (for the tube angles of the outputs)."""
    h_full = lay.h.detach()
    B, S_full = h_full.shape
    N = lay.EI.shape[-1]
    phi = tab.phi_q
    Q, n = phi.shape
    C = 2 + N
    dtype, device = h_full.dtype, h_full.device
    active = lay.active.detach() > 0.5
    S = max(1, int(active.sum(-1).amax()))
    sec = torch.argsort((~active).to(torch.int8), dim=-1, stable=True)[:, :S]    # (B, S)
    cidx = torch.cat([torch.arange(N, device=device).expand(B, N),
                      (N + (sec * (C * n))[:, :, None]
                       + torch.arange(C * n, device=device)).reshape(B, S * C * n)], -1)
    nc = cidx.shape[-1]

    def sections(t):        # (B, S_full, ...) -> (B, S, ...)
        return torch.gather(t, 1, sec.reshape((B, S) + (1,) * (t.ndim - 2)).expand(
            (B, S) + t.shape[2:]))

    qmask = torch.gather(lay.qmask.detach(), 1, cidx)
    with torch.no_grad():
        ustar = sections(node_constants(lay, tab.xq).ustar)
        full = node_constants(lay, tab.xm)
        pose = PoseConstants._make(v.detach() for v in _pose_sections(lay, full))
        b_full = sections(angle_bases(lay, nq))                              # (B, S, N, nq)
        bvec = torch.gather(b_full, 3, cidx[:, None, None, :].expand(B, S, N, nc))
    W = sections(lay.W.detach())                                           # (B, S, Q)
    h = sections(h_full)
    Pn = sections(lay.present.detach())[:, :, None, :].expand(B, S, Q, N)
    EIp = lay.EI.detach()[:, None, None, :] * Pn
    GJp = lay.GJ.detach()[:, None, None, :] * Pn
    A = torch.einsum("bsq,qp,qr->bspr", W * sum_dim(EIp, -1), phi, phi)     # bending blocks
    T = torch.einsum("bsqj,qp,qr->bsjpr", W[..., None] * GJp, phi, phi)     # torsion blocks
    guide = torch.zeros(B, nc, dtype=dtype, device=device)
    guide[:, :N] = lay.GJ.detach() * lay.D.detach() * qmask[:, :N]
    # The q-independent Hessian is the guide diagonal plus section-diagonal blocks, kept as
    # whole section blocks (B, S, C, n, C, n) (no dense (nq, nq) copy): A (x) I_2 on the bending
    # coefficients, T_kj on tube j's torsion coefficients. elastic_grad_hess adds the
    # q-dependent block terms to a copy and writes H's block diagonal in ONE strided pass. Both
    # vanish on inactive coordinates (zero weight W or zero stiffness of an absent tube).
    blocks = torch.zeros(B, S, C, n, C, n, dtype=dtype, device=device)
    diag = blocks.diagonal(dim1=2, dim2=4)                                 # (B, S, n, n, C)
    diag[..., :2] = A[..., None]
    diag[..., 2:] = T.permute(0, 1, 3, 4, 2)
    EIw = W[..., None] * EIp                      # node weights x stiffness (B, S, Q, N)
    values_T, Q_QQ, phi_PQ = node_tables(phi, tab.Q_q)
    return Maps(ustar=ustar.detach(), EIw=EIw, EIws=sum_dim(EIw, -1), GJw=W[..., None] * GJp,
                H_sections=blocks, guide=guide, guide_const=lay.guide_const.detach(), h=h,
                qmask=qmask, psi0=lay.psi0.detach(), bvec=bvec, cidx=cidx,
                presc_inc=full.presc_inc.detach(), phi=phi, Qb=tab.Q_q, values_T=values_T,
                Q_QQ=Q_QQ, phi_PQ=phi_PQ, pose=pose)


def build_layout_and_maps(tubes, D: torch.Tensor, A: torch.Tensor, F: torch.Tensor,
                          M: torch.Tensor, loaded: torch.Tensor, disc, nq: int
                          ) -> tuple[Layout, Maps]:
    """``(lay, maps)``: :func:`torchpvs.sections.build_layout` of the batch (its arguments) and
    :func:`build_maps` of that layout (``nq`` the padded coordinate count of ``disc``): the
    eager kernel's ``layout`` (:class:`torchpvs.kernel.Kernel`), differentiable through the
    layout."""
    lay = build_layout(tubes, D, A, F, M, loaded, disc)
    return lay, build_maps(lay, disc.tables(D.dtype, D.device), nq)


def compact_q(q: torch.Tensor, cidx: torch.Tensor) -> torch.Tensor:
    """``(..., nq) -> (..., nq_c)``: the coordinates ``cidx = maps.cidx`` that
    :func:`build_maps` keeps."""
    return torch.gather(q, -1, cidx.expand(q.shape[:-1] + cidx.shape[-1:]))


def expand_q(qc: torch.Tensor, cidx: torch.Tensor, nq: int) -> torch.Tensor:
    """``(..., nq_c) -> (..., nq)``, zero on the coordinates left out (all inactive)."""
    return torch.zeros(qc.shape[:-1] + (nq,), dtype=qc.dtype, device=qc.device).scatter(
        -1, cidx.expand(qc.shape), qc)


def expand_hessian(Hc: torch.Tensor, cidx: torch.Tensor, nq: int) -> torch.Tensor:
    """``(B, nq_c, nq_c) -> (B, nq, nq)``, identity on the coordinates left out."""
    B, nc, _ = Hc.shape
    H = torch.zeros(B, nq * nq, dtype=Hc.dtype, device=Hc.device)
    flat = (cidx[:, :, None] * nq + cidx[:, None, :]).reshape(B, nc * nc)
    H.scatter_(1, flat, Hc.reshape(B, nc * nc))
    H = H.view(B, nq, nq)
    left_out = torch.ones(B, nq, dtype=Hc.dtype, device=Hc.device).scatter_(1, cidx, 0.0)
    H.diagonal(dim1=-2, dim2=-1).add_(left_out)
    return H


def compact_hessian(H: torch.Tensor, cidx: torch.Tensor) -> torch.Tensor:
    """``(B, nq, nq) -> (B, nq_c, nq_c)``: the rows and columns ``cidx (B, nq_c)`` (the inverse
    of :func:`expand_hessian` on the coordinates kept)."""
    nq = H.shape[-1]
    nc = cidx.shape[-1]
    rows = H.gather(1, cidx[:, :, None].expand(-1, nc, nq))
    return rows.gather(2, cidx[:, None, :].expand(-1, nc, nc))


def pose_constants(maps: Maps) -> PoseConstants:
    """The :func:`pose_node_constants` of the Magnus nodes stored by :func:`build_maps`
    (``maps.pose``; for :func:`tip_pose` in solves that need no gradient with respect to the
    layout)."""
    return maps.pose



def node_tables(phi: torch.Tensor, Qb: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Contraction tables over the quadrature nodes, so that each node sum is one matmul:
    ``values_T (n, 2Q)`` gives phi and Q values from coefficients; ``Q_QQ (Q, n + n^2)`` and
    ``phi_PQ (Q, n + n^2)`` give ``sum_q f_q Q_qp`` with ``sum_q f_q Q_qp Q_qr`` (and the phi
    analogues) in one product. Returns ``(values_T, Q_QQ, phi_PQ)``."""
    Q, n = phi.shape
    QQ = (Qb[:, :, None] * Qb[:, None, :]).reshape(Q, n * n)
    PQ = (phi[:, :, None] * Qb[:, None, :]).reshape(Q, n * n)
    return (torch.cat([phi, Qb], 0).T.contiguous(), torch.cat([Qb, QQ], -1).contiguous(),
            torch.cat([phi, PQ], -1).contiguous())


def _local(q: torch.Tensor, maps: Maps):
    """Node fields on the compact coordinates: backbone bending ``ux, uy (B, S, Q)``, torsions
    ``dp (B, S, Q, N)``, ``Rz(psi) u*_xy`` as ``Rx, Ry (B, S, Q, N)`` and the precurvatures
    ``us (B, S, Q, N, 3)``. Components are kept apart: reductions over a size-2 dimension are
    slow (:func:`sum_dim`)."""
    bvec = maps.bvec
    B, S, N, _ = bvec.shape
    Q = maps.phi.shape[0]
    X = (q[:, N:] * maps.qmask[:, N:]).reshape(B, S, 2 + N, -1)
    Y = (X @ maps.values_T).transpose(-1, -2)                          # (B, S, 2Q, C)
    ux, uy, dp, loc = Y[:, :, :Q, 0], Y[:, :, :Q, 1], Y[:, :, :Q, 2:], Y[:, :, Q:, 2:]
    base = maps.psi0[:, None, :] + (bvec.reshape(B, S * N, -1) @ q[:, :, None]).reshape(B, S, N)
    psi = base[:, :, None, :] + 0.5 * maps.h[:, :, None, None] * loc
    us = maps.ustar
    cs, sn = torch.cos(psi), torch.sin(psi)
    usx, usy = us[..., 0], us[..., 1]
    return ux, uy, dp, cs * usx - sn * usy, sn * usx + cs * usy, us


def elastic_energy_maps(q: torch.Tensor, maps: Maps) -> torch.Tensor:
    """Same value as :func:`elastic_energy`, through the precomputed structure (``q (B, nq)``)."""
    return _energy_from_fields(q, maps, *_local(q, maps))


def _energy_from_fields(q, maps, ux, uy, dp, Rx, Ry, us):
    dx, dy = ux[..., None] - Rx, uy[..., None] - Ry
    tors = dp - us[..., 2]
    dens = 0.5 * sum_dim(maps.EIw * (dx * dx + dy * dy) + maps.GJw * tors * tors, -1)
    guide = 0.5 * (maps.guide * q**2).sum(-1)
    return dens.sum((-1, -2)) + guide + maps.guide_const


class _ElasticTerms(NamedTuple):
    """Node sums of one evaluation of the elastic energy's derivatives (see
    :func:`elastic_grad_hess`): the gradient ``(B, nq)``, the energy ``(B,)`` (or None), the
    angle bases ``bflat (B, S N, nq)``, and the Hessian's node sums per section and tube:
    ``alpha (B, S, N)``, ``beta (B, S, N, n)``, ``mu (B, S, N, 2, n)``; the within-section
    terms ``gamma = hh^2 gq`` and ``nu = hh nq`` with ``hh (B, S)`` half the section lengths,
    ``gq (B, S, N, n, n)`` and ``nq (B, S, N, 2, n, n)`` (views: each consumer scales only the
    entries it uses, in the layout it writes)."""

    grad: torch.Tensor
    energy: torch.Tensor | None
    bflat: torch.Tensor
    alpha: torch.Tensor
    beta: torch.Tensor
    mu: torch.Tensor
    hh: torch.Tensor
    gq: torch.Tensor
    nq: torch.Tensor


def _elastic_terms(q: torch.Tensor, maps: Maps,
                   energy: bool = False) -> _ElasticTerms:
    ux, uy, dp, Rx, Ry, us = _local(q, maps)
    U = _energy_from_fields(q, maps, ux, uy, dp, Rx, Ry, us) if energy else None
    B, nq = q.shape
    bvec, phi, Qb = maps.bvec, maps.phi, maps.Qb
    _, S, N, _ = bvec.shape
    n = phi.shape[-1]
    EIw, EIs = maps.EIw, maps.EIws                                    # (B, S, Q, N), sum
    ERx, ERy = EIw * Rx, EIw * Ry
    gu = torch.stack([EIs * ux - sum_dim(ERx, -1), EIs * uy - sum_dim(ERy, -1)], -2)
    gpsi = ERy * ux[..., None] - ERx * uy[..., None]                        # (B, S, Q, N)
    gdp = maps.GJw * (dp - us[..., 2])
    hh = 0.5 * maps.h[:, :, None, None]
    gX = torch.cat([gu @ phi,
                    gdp.transpose(-1, -2) @ phi + hh * (gpsi.transpose(-1, -2) @ Qb)],
                   2)                                                       # (B, S, C, n)
    bflat = bvec.reshape(B, S * N, nq)
    grad = (gpsi.sum(2).reshape(B, 1, S * N) @ bflat)[:, 0] + maps.guide * q
    grad[:, N:] += gX.reshape(B, -1) * maps.qmask[:, N:]
    # Angle terms of the Hessian, reduced over nodes per (section, tube).
    hpp = ERx * ux[..., None] + ERy * uy[..., None]                         # (B, S, Q, N)
    HQ = hpp.transpose(-1, -2) @ maps.Q_QQ                               # (B, S, N, n + n^2)
    # d2e/du dpsi_j = -EI_j J Ru_j = EI_j (Ry, -Rx), laid out (B, S, N, 2, Q) for one product.
    hup = torch.stack([ERy.transpose(-1, -2), -ERx.transpose(-1, -2)], -2)
    MP = hup @ maps.phi_PQ                                               # (B, S, N, 2, n+n^2)
    return _ElasticTerms(
        grad, U, bflat, alpha=hpp.sum(2), beta=hh * HQ[..., :n], mu=MP[..., :n],
        hh=hh[:, :, 0, 0], gq=HQ[..., n:].reshape(B, S, N, n, n),
        nq=MP[..., n:].reshape(B, S, N, 2, n, n))


def elastic_grad_hess(q: torch.Tensor, maps: Maps, energy: bool = False):
    """Exact gradient ``(B, nq)`` and Hessian ``(B, nq, nq)`` of the elastic energy; with
    ``energy=True`` also the energy ``(B,)`` itself, bit for bit :func:`elastic_energy_maps`
    (from the same node fields: a line search's energy at the iterate costs no extra pass).

    The Hessian is assembled as ``b^T V + V^T b`` (one batched GEMM over twice the ``S N`` angle
    bases) plus the guide diagonal and the within-section blocks (assembled per section, then
    added to H's block diagonal in one strided pass): every term vanishes on inactive
    coordinates by construction (zero quadrature weight or zero stiffness), so no dense mask
    pass is made."""
    t = _elastic_terms(q, maps, energy)
    bflat = t.bflat
    B, SN, nq = bflat.shape
    n = maps.phi.shape[-1]
    N = maps.bvec.shape[2]
    S, C = SN // N, 2 + N
    # H = b^T V + V^T b + (guide diagonal and within-section blocks), with V = alpha b / 2 plus
    # beta at (kj, c_kj) and mu at (kj, a_k): b^T V + V^T b is ONE GEMM, [b; V]^T [V; b], that
    # writes H once and reads no dense constant (the passes over (B, nq, nq), not the
    # arithmetic, bound large batches); the rest is written through strided views.
    V = 0.5 * t.alpha.reshape(B, -1, 1) * bflat                             # (B, S N, nq)
    Vc = V[:, :, N:].view(B, S, N, S, C, n).diagonal(dim1=1, dim2=3)        # (B, N, C, n, S)
    Vc[:, :, 2:].diagonal(dim1=1, dim2=2).add_(t.beta.permute(0, 3, 1, 2))  # (B, n, S, N)
    Vc[:, :, :2] += t.mu.permute(0, 2, 3, 4, 1)                             # (B, N, 2, n, S)
    H = torch.bmm(torch.cat([bflat, V], 1).transpose(1, 2), torch.cat([V, bflat], 1))
    H.diagonal(dim1=-2, dim2=-1).add_(maps.guide)
    # Blocks within a section, assembled in a contiguous copy of the constant ones (gamma on
    # the (c_kj, c_kj) blocks, nu on (a_k, c_kj) and its transpose), then added to H's block
    # diagonal in one pass: strided adds of each term straight into H cost 3x more.
    Cn = C * n
    blk = maps.H_sections.clone()                                       # (B, S, C, n, C, n)
    hh = t.hh.reshape(B, S, 1, 1, 1)
    blk[:, :, 2:, :, 2:].diagonal(dim1=2, dim2=4).addcmul_(hh * hh, t.gq.permute(0, 1, 3, 4, 2))
    upper = blk[:, :, :2, :, 2:]                                           # (B, S, 2, n, N, n)
    upper.addcmul_(hh[..., None], t.nq.permute(0, 1, 3, 4, 2, 5))         # (no out=: autograd)
    blk[:, :, 2:, :, :2] = upper.permute(0, 1, 4, 5, 2, 3)
    H[:, N:, N:].view(B, S, Cn, S, Cn).diagonal(dim1=1, dim2=3).add_(
        blk.view(B, S, Cn, Cn).permute(0, 2, 3, 1))
    return (t.grad, H, t.energy) if energy else (t.grad, H)


def section_grad_block(q: torch.Tensor, maps: Maps, sec: torch.Tensor):
    """The elastic energy's gradient ``(B, nq)`` and the block ``(B, C n, C n)`` of its Hessian
    on the coordinates of compact section ``sec (B,)`` (one per element; ``C = 2 + N``), without
    the terms through the angle bases: those couple the section's mean torsions through the
    angles of the sections after it and are ``O(h^2)`` for a section of length ``h``, against
    ``O(h)`` for the block. For a section of vanishing length (the one-sided equilibria of
    :func:`torchpvs.forces.equilibrium_forces`) the block is thus exact to relative ``O(h)``,
    with no ``(nq, nq)`` Hessian made."""
    t = _elastic_terms(q, maps)
    B = q.shape[0]
    n = maps.phi.shape[-1]
    N = maps.bvec.shape[2]
    C = 2 + N
    rows = torch.arange(B, device=q.device)
    blk = maps.H_sections[rows, sec]                                    # (B, C, n, C, n)
    hh = t.hh[rows, sec].reshape(B, 1, 1, 1)
    blk[:, 2:, :, 2:].diagonal(dim1=1, dim2=3).addcmul_(
        hh * hh, t.gq[rows, sec].permute(0, 2, 3, 1))
    upper = blk[:, :2, :, 2:]                                              # (B, 2, n, N, n)
    upper.addcmul_(hh[..., None], t.nq[rows, sec].permute(0, 2, 3, 1, 4))
    blk[:, 2:, :, :2] = upper.permute(0, 3, 4, 1, 2)
    return t.grad, blk.reshape(B, C * n, C * n)
