"""Control quantities at an equilibrium: actuator stiffness, tip Jacobians, tip compliance.

With actuator coordinates ``x = (D_1..D_N, alpha_1..alpha_N)`` and generalized forces
``tau(x) = dU*/dx`` (docs/conventions.md), at an equilibrium ``q*(x)``:

* actuator stiffness ``K_x = dtau/dx = U_xx - U_xq U_qq^-1 U_qx`` — the Schur complement of the
  full Hessian: the stiffness the actuators feel. It is singular along the common rotation
  ``(0, .., 0, 1, .., 1)`` (rotating every tube together costs no energy) when the tip is
  unloaded, and non-symmetric under a dead tip moment (a non-conservative load).
* tip Jacobian ``J_x = d(tip)/dx``, rows ``(p_x, p_y, p_z, omega_x, omega_y, omega_z)``:
  position [m] and spatial angular velocity [rad] of the tip frame per unit actuation.
* force-control Jacobian ``J_tau = d(tip)/dtau = J_x K_x^+``: how the tip moves per unit actuator
  force/torque when every actuator is force-controlled (pseudo-inverse: the free common
  rotation is a zero-stiffness mode; ``force_rank`` reports the numerical rank of ``K_x``).
* tip compliance ``C = d(tip)/d(F, M)`` (6 x 6) under the current load at fixed actuation.

All are exact derivatives of the discrete model (implicit-function theorem), batched over the
equilibrium's elements. Without a tip moment they are closed forms in the equilibrium's own
factorization of the stiffness ``H``: ``K_x = U_xx - U_xq H^-1 U_qx``, ``J_x = P_x - P_q H^-1
U_qx`` and ``C = P_q H^-1 P_q^T`` (``P`` the tip twist, subscripts partial derivatives at fixed
``q`` or ``x``), with the partials from one reverse pass each over the batch repeated per output
row. Under a dead tip moment (non-conservative) ``K_x`` and ``J_x`` go through the implicit
backward of :mod:`torchpvs.implicit` instead.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from .forces import KINK_DELTA, closed_form_partials, kink_mask
from .implicit import adjoint_factor, differentiable_outputs
from .kernel import EAGER, KERNELS
from .mechanics import potential, skew_vee, tip_twist
from .sections import TubeTensors, build_layout, tube_rows

__all__ = ["ControlJacobians", "actuator_stiffness", "control_jacobians", "tip_jacobian"]


@dataclass(frozen=True)
class ControlJacobians:
    """See the module docstring. Shapes: ``actuator_stiffness (B, 2N, 2N)``,
    ``tip_jacobian (B, 6, 2N)``, ``force_jacobian (B, 6, 2N)``, ``tip_compliance (B, 6, 6)``,
    ``force_rank (B,)``. Units follow ``x = (D [m], alpha [rad])``, ``tau = (N, N·m)``.
    ``tip_compliance`` is ``None`` when it was not asked for (``compliance=False``)."""

    actuator_stiffness: torch.Tensor
    tip_jacobian: torch.Tensor
    force_jacobian: torch.Tensor
    tip_compliance: torch.Tensor | None
    force_rank: torch.Tensor


def _adjoint_rows(eq, rows: torch.Tensor):
    """The :class:`~torchpvs.implicit.AdjointFactors` of batch ``rows`` of the equilibrium:
    indexed from the cached one, or (first use) computed for the whole batch and cached, or for
    a subset of rows only (not cached: the cache is per batch)."""
    ctx = eq.context
    info = ctx.implicit
    tubes: TubeTensors = ctx.tubes
    q = eq.q.detach()
    D, A, F, M = (t.detach() for t in ctx.actuation_and_load)
    factors = info.adjoint
    if factors is None and len(rows) == q.shape[0]:
        factors = info.adjoint = adjoint_factor(q, info, D, A, F, M, tubes)
    if factors is None:
        sub = info.rows(rows, H=info.hessian()[rows])
        return adjoint_factor(q[rows], sub, D[rows], A[rows], F[rows], M[rows], tubes)
    return factors.rows(rows)


def _replicated(eq, m: int, rows: torch.Tensor, D=None):
    """The equilibrium's coordinates, inputs and implicit context for batch ``rows``, every
    element repeated ``m`` times (rows ``r * m + i``), without the adjoint factors; with the
    insertions ``D (len(rows), N)`` instead of the equilibrium's where given (a kink's side).

    Jacobian rows by ONE reverse pass: replica ``i`` of element ``r`` back-propagates only its
    output ``i`` (elements are independent), instead of ``m`` reverse passes over the batch. The
    flops are the same; the torch op count (what bounds small and medium batches on a CPU)
    falls ``m``-fold."""
    ctx = eq.context
    idx = rows.repeat_interleave(m)
    rep = ctx.implicit.rows(idx)
    inputs = tuple(t.detach()[idx] for t in ctx.actuation_and_load)
    if D is not None:
        inputs = (D.detach().repeat_interleave(m, 0), *inputs[1:])
    return eq.q.detach()[idx], rep, inputs, tube_rows(ctx.tubes, idx)


def _rows_of(eq, rows) -> torch.Tensor:
    q0 = eq.q
    return (torch.arange(q0.shape[0], device=q0.device) if rows is None
            else torch.as_tensor(rows, device=q0.device).long())


def actuator_stiffness(eq, rows=None) -> torch.Tensor:
    """``K_x = dtau/dx`` ``(B, 2N, 2N)`` [N/m, N, N·m] at an :class:`~torchpvs.Equilibrium`
    (``(len(rows), 2N, 2N)`` for the batch rows ``rows`` only, when given) —
    the first block of :func:`control_jacobians` alone. The cheap path for time stepping
    (torchpvs environments).

    Without a tip moment, as the Schur complement ``U_xx - U_xq H^-1 U_qx``: the mixed and
    actuator blocks of the energy's Hessian by one double-backward pass over the batch repeated
    ``2N`` times (:func:`_replicated`; ``N`` times where every tube's base lies inside the
    guide, the rotation rows then coming from ``H``: :func:`_rotation_rows_from_hessian`), and
    ``H^-1 U_qx`` from the equilibrium's adjoint
    factorization (shared with the implicit backward). Under a tip moment (non-conservative)
    through the implicit backward, in one reverse pass over the repeated batch."""
    return _one_sided(eq, _rows_of(eq, rows), _stiffness_block)[0]


def _stiffness_block(eq, rows: torch.Tensor, D=None):
    """``(K, None, qmask)``: :func:`_schur`'s stiffness in :func:`_one_sided`'s protocol."""
    K, _, _, qm = _schur(eq, rows, D=D)
    return K, None, qm


def _one_sided(eq, rows: torch.Tensor, blocks):
    """``(K (k, 2N, 2N), J (k, 6, 2N) or None)`` of batch ``rows`` from ``blocks(eq, rows, D)
    -> (K, J or None, qmask or None)``, one-sided where an insertion sits at a kink of
    ``U*(D_j)`` (:func:`torchpvs.forces.kink_mask`: a tube's base, straight-to-curved
    transition or end at the orifice, or cuts of two tubes meeting). There the derivatives in
    ``D_j`` differ for insertion and retraction, and the layout's own derivative (torch's rule
    for a tie in ``sort``, ``clamp`` or ``minimum``) is neither. Such rows are evaluated
    ``KINK_DELTA`` (1e-7 m) away on the retraction side (every kinked ``D_j`` increased; the
    insertion side where the tube's end is at the orifice and it cannot retract further), the
    side ``actuation_forces`` reports: the partials at the side's insertions with this
    equilibrium's ``q`` and factorization (no solve) where the sections there have the same
    coordinates (``blocks`` reports the layout's ``qmask``); where a coordinate appears (a base
    leaving the orifice) or under a tip moment (the implicit-backward path), at the side's own
    equilibrium (one solve). Every entry of such a row is then off by O(delta), as the
    one-sided forces are: 1e-7 to 8e-6 relative in the entries that are smooth at the kink
    (Fig. 3 robot)."""
    ctx = eq.context
    opts = ctx.options
    D = ctx.insertion.detach()[rows]
    tubes = tube_rows(ctx.tubes, rows)
    if opts.compute_forces and opts.force_model == "energy":
        kink = eq.force_kink[rows]          # the solve's own analysis (the same mask)
    else:
        kink = kink_mask(tubes, D)
    kink = kink & eq.converged.detach()[rows, None]
    at = kink.any(-1).nonzero().flatten()
    if at.numel() == 0:
        return blocks(eq, rows, None)[:2]
    L = tubes.length.expand_as(D)[at]
    sign = torch.where((L - D[at]).abs() <= KINK_DELTA / 2, -1.0, 1.0).to(D.dtype)
    Dn = D[at] + KINK_DELTA * sign * kink[at].to(D.dtype)
    # a base moved past the next one's would break the nesting: move them together
    Dn = torch.cummax(Dn, -1).values
    info = ctx.implicit
    r_at = rows[at]
    groups = []
    moved = torch.ones(len(at), dtype=torch.bool, device=at.device)
    if not info.has_moment:
        K, J, qm = blocks(eq, r_at, Dn)
        moved = (qm != info.qmask[r_at]).any(-1)
        groups.append((at, (K, J)))
    if bool(moved.any()):
        if ctx.resolver is None:
            raise ValueError("control Jacobians: an insertion sits at a kink of U*(D) and this "
                             "equilibrium carries no solve to take the one-sided side from")
        disc = ctx.discretization
        side = ctx.resolver.at(Dn[moved], r_at[moved], eq.q.detach()[r_at[moved]],
                               replace(opts, order=eq.order, n_quad=disc.n_quad,
                                       n_magnus=disc.n_magnus, compute_forces=False))
        k = int(moved.sum())
        groups.append((at[moved], blocks(side, torch.arange(k, device=at.device), None)[:2]))
    if len(at) < len(rows):
        smooth = (~kink.any(-1)).nonzero().flatten()
        groups.insert(0, (smooth, blocks(eq, rows[smooth], None)[:2]))
    out = [None if p is None else p.new_empty((len(rows), *p.shape[1:]))
           for p in groups[0][1]]
    for idx, parts in groups:       # later groups overwrite: the side solves come last
        for full, p in zip(out, parts, strict=True):
            if full is not None:
                full[idx] = p
    return tuple(out)


def _schur(eq, rows: torch.Tensor, tip: bool = False, D=None):
    """``(K (B, 2N, 2N), Z (B, nq, 2N) or None, tip partials or None, qmask (B, nq) or
    None)``: the actuator stiffness
    of batch ``rows`` and, for a conservative load, ``Z = H^-1 U_qx`` (so ``dq*/dx = -Z``; zero
    on the inactive coordinates). ``Z`` is ``None`` under a tip moment (the stiffness then comes
    from the implicit backward). With ``tip``, the tip partials ``(P_q, P_x)`` of
    :func:`_tip_partials` come from the stiffness's own reverse pass where its rotation rows are
    read off ``H`` (one pass instead of two), else ``None``. ``D (B, N)``: the partials at
    these insertions instead of the equilibrium's (at fixed ``q`` and ``H``: a kink's side,
    :func:`_one_sided`); ``qmask`` is then the active coordinates of the layout there (where
    they differ from the equilibrium's, the result is not that side's), else ``None``."""
    q0 = eq.q
    B, m = len(rows), 2 * eq.context.insertion.shape[1]
    if B == 0:
        return (torch.zeros(0, m, m, dtype=q0.dtype, device=q0.device),
                torch.zeros(0, q0.shape[-1], m, dtype=q0.dtype, device=q0.device), None, None)
    ctx = eq.context
    if ctx.implicit.has_moment:
        return _implicit_rows(eq, rows, stiffness=True, tip=False), None, None, None
    factors = _adjoint_rows(eq, rows)
    qmask = ctx.implicit.qmask[rows]                                      # (B, nq)
    N = m // 2
    D0 = ctx.insertion.detach()[rows] if D is None else D
    partials = None
    if bool((qmask[:, :N] > 0).all()) and bool((D0 > 0).all()):
        Uxq, Uxx, partials, lay_mask = _rotation_rows_from_hessian(eq, rows, D0, tip,
                                                                   own=D is None)
    elif (out := _rows_without_graph(eq, rows, D0, D is None, True)) is not None:
        # every row from the kernel (compiled: a complex step per actuator, no graph)
        Uxq, UxD, UxA, lay_mask, _ = out
        Uxx = torch.cat([UxD, UxA], -1)
    else:
        q, info, (D, A, F, M), tubes = _replicated(eq, m, rows, D)
        D.requires_grad_(True)
        A.requires_grad_(True)
        pick = torch.eye(m, dtype=q.dtype, device=q.device).repeat(B, 1)    # (B m, 2N)
        q = q.requires_grad_(True)
        with torch.enable_grad():
            lay = build_layout(tubes, D, A, F, M, info.loaded, info.disc)
            U = potential(q, lay, info.tab, None, info.with_load)
            tau = torch.cat(torch.autograd.grad(U.sum(), (D, A), create_graph=True), -1)
            Uxq, UxD, UxA = torch.autograd.grad((tau * pick).sum(), (q, D, A))
        Uxx = torch.cat([UxD, UxA], -1).reshape(B, m, m)
        lay_mask = lay.qmask.reshape(B, m, -1)[:, 0]
    Uqx = (Uxq.reshape(B, m, -1) * qmask[:, None]).transpose(1, 2)          # (B, nq, 2N)
    Z = factors.solve(Uqx, tangent=True) * qmask[..., None]
    K = Uxx - Uqx.transpose(1, 2) @ Z
    return 0.5 * (K + K.transpose(1, 2)), Z, partials, (None if D is None else lay_mask)


def _tip_partials(eq, rows: torch.Tensor, D=None, layout=None):
    """``(P_q (B, 6, nq), P_x (B, 6, 2N))``: the tip twist (position [m], spatial rotation
    [rad]) per coordinate and per actuator at fixed ``q``, zero on the inactive coordinates,
    from the equilibrium's kernel (:attr:`~torchpvs.kernel.Kernel.tip_partials`: compiled,
    the Magnus chain in ``q`` and a complex step per actuator; eager, one reverse pass over the
    batch repeated 6 times), at
    the insertions ``D (B, N)`` instead of the equilibrium's where given (a kink's side);
    ``layout``: the layout there where the caller has it (:func:`_layout_at`)."""
    ctx = eq.context
    info = ctx.implicit
    own = D is None
    D0 = ctx.insertion.detach()[rows] if own else D
    if layout is None and own:
        layout = _own_layout(eq, rows)
    Pq, PD, PA = KERNELS[ctx.options.kernel].tip_partials(
        eq.q.detach()[rows], tube_rows(ctx.tubes, rows), D0, ctx.rotation.detach()[rows],
        info.loaded[rows], info.tab, info.disc, layout)
    return _tip_rows(eq, rows, Pq, PD, PA)


def _tip_rows(eq, rows, Pq, PD, PA):
    """``(P_q (B, 6, nq), P_x (B, 6, 2N))`` from the partials in ``q``, ``D`` and ``alpha``."""
    B = len(rows)
    qmask = eq.context.implicit.qmask[rows]
    return (Pq.reshape(B, 6, -1) * qmask[:, None],
            torch.cat([PD, PA], -1).reshape(B, 6, -1))


def tip_jacobian(eq, rows=None) -> torch.Tensor:
    """``J_x = d(tip)/dx`` ``(B, 6, 2N)`` at an :class:`~torchpvs.Equilibrium` (batch ``rows``
    only, when given): rows ``(p_x, p_y, p_z, omega_x, omega_y, omega_z)`` [m, rad] per unit
    actuation ``x = (D [m], alpha [rad])``, the second block of :func:`control_jacobians`.

    Without a tip moment in closed form, ``J_x = P_x - P_q H^-1 U_qx``: the tip's partials at
    fixed ``q`` (:func:`_tip_partials`) and ``H^-1 U_qx`` from the actuator stiffness's own
    solve with the equilibrium's factorization — no re-solve and no reverse pass through the
    implicit backward. Under a tip moment through the implicit backward, one reverse pass over
    the batch repeated 6 times."""
    return _control_blocks(eq, _rows_of(eq, rows))[1]


def _control_blocks(eq, rows: torch.Tensor):
    """``(K (B, 2N, 2N), J_x (B, 6, 2N))`` of batch ``rows``, one-sided at kinks
    (:func:`_one_sided`); of the whole batch in one compiled call where the solve's resolver
    has one (:func:`torchpvs.fused.control_blocks`: the same closed forms per element)."""
    resolver = eq.context.resolver
    if resolver is not None and len(rows) == len(eq):
        out = resolver.control_blocks(eq)
        if out is not None:
            return out
    return _one_sided(eq, rows, _control_blocks_here)


def _control_blocks_here(eq, rows: torch.Tensor, D=None):
    """``(K, J_x, qmask)`` of batch ``rows`` by the layout's own derivatives (at insertions
    ``D`` where given, see :func:`_schur`)."""
    K, Z, partials, qm = _schur(eq, rows, tip=True, D=D)
    if Z is None:   # a tip moment: through the implicit backward
        return K, _implicit_rows(eq, rows, stiffness=False, tip=True), qm
    Pq, Px = partials if partials is not None else _tip_partials(eq, rows, D)
    return K, Px - Pq @ Z, qm


def _implicit_rows(eq, rows: torch.Tensor, *, stiffness: bool, tip: bool) -> torch.Tensor:
    """Rows ``d(outputs)/dx`` ``(B, m, 2N)`` through the implicit backward (the path for a dead
    tip moment, whose tangent is not a Hessian): outputs the actuation forces and torques
    (``stiffness``, 2N rows) then the tip twist (``tip``, 6 rows), in one reverse pass over the
    batch repeated once per row (:func:`_replicated`)."""
    B, n = len(rows), 2 * eq.context.insertion.shape[1]
    m = n * stiffness + 6 * tip
    factors = _adjoint_rows(eq, rows)
    q, info, (D, A, F, M), tubes = _replicated(eq, m, rows)
    D.requires_grad_(True)
    A.requires_grad_(True)
    info.adjoint = factors.rows(torch.arange(B, device=q.device).repeat_interleave(m))
    pick = torch.eye(m, dtype=q.dtype, device=q.device).repeat(B, 1)        # (B m, m)
    with torch.enable_grad():
        out = differentiable_outputs(q, info, D, A, F, M, tubes)
        parts = [torch.cat([out.forces, out.torques], -1)] if stiffness else []
        if tip:
            R0 = out.R.detach()
            parts.append(torch.cat([out.tip, skew_vee(out.R @ R0.transpose(-1, -2))], -1))
        GD, GA = torch.autograd.grad((torch.cat(parts, -1) * pick).sum(), (D, A))
    return torch.cat([GD, GA], -1).reshape(B, m, n)


def _own_layout(eq, rows):
    """The layout of batch ``rows`` at the equilibrium's own insertions where the solve's plan
    still holds it (unloaded, :meth:`~torchpvs.plan.Plan.reused_layout`), else None."""
    ctx = eq.context
    if ctx.plan is None:
        return None
    full = ctx.plan.reused_layout(ctx.tubes, ctx.insertion.detach(), ctx.rotation.detach(),
                                  ctx.implicit.loaded, ctx.implicit.disc)
    return None if full is None else type(full)._make(t[rows] for t in full)


def _layout_at(eq, rows, D0, own: bool):
    """The unloaded layout of batch ``rows`` at insertions ``D0`` (``own``: the
    equilibrium's), for the kernel's actuator rows and tip partials to share: the plan's where
    it holds it, else built once without a graph. None on the eager kernel, whose reverse
    passes build their own from inputs that require grad."""
    ctx = eq.context
    if KERNELS[ctx.options.kernel] is EAGER:
        return None
    info = ctx.implicit
    A, loaded, tubes = ctx.rotation.detach()[rows], info.loaded[rows], tube_rows(ctx.tubes, rows)
    lay = _own_layout(eq, rows) if own else (
        None if ctx.plan is None else ctx.plan.reused_layout(tubes, D0, A, loaded, info.disc))
    if lay is None:
        with torch.no_grad():
            zero = torch.zeros(len(rows), 3, dtype=D0.dtype, device=D0.device)
            lay = build_layout(tubes, D0, A, zero, zero, loaded, info.disc)
    return lay


def _kernel_rows(eq, rows, D0, layout, rotations: bool):
    """The equilibrium's kernel's :attr:`~torchpvs.kernel.Kernel.actuation_rows` of batch
    ``rows`` at insertions ``D0`` on their ``layout`` (:func:`_layout_at`), unloaded."""
    ctx = eq.context
    info = ctx.implicit
    return KERNELS[ctx.options.kernel].actuation_rows(
        eq.q.detach()[rows], tube_rows(ctx.tubes, rows), D0, ctx.rotation.detach()[rows],
        info.loaded[rows], info.tab, info.disc, rotations, layout)


def _rows_without_graph(eq, rows, D0, own: bool, rotations: bool):
    """``(U_xq, U_xD, U_xalpha, qmask, layout)`` of batch ``rows`` at insertions ``D0`` from the
    kernel (:func:`_kernel_rows` on the layout of :func:`_layout_at`, returned for the tip
    partials to share), plus under a dead tip force the
    kernel's ``load_rows`` (compiled: a central difference of the exact tip partials); None
    where the kernel has no load rows (the caller then differentiates the loaded potential
    twice by autograd)."""
    ctx = eq.context
    info = ctx.implicit
    kernel = KERNELS[ctx.options.kernel]
    if info.with_load and kernel.load_rows is EAGER.load_rows:
        return None
    lay = _layout_at(eq, rows, D0, own)
    load = None
    if info.with_load:
        F = ctx.actuation_and_load[2].detach()[rows]
        load = kernel.load_rows(eq.q.detach()[rows], tube_rows(ctx.tubes, rows), D0,
                                ctx.rotation.detach()[rows], info.loaded[rows], info.tab,
                                info.disc, F, rotations, lay)
        if load is None:
            return None
    Uxq, UxD, UxA, qmask = _kernel_rows(eq, rows, D0, lay, rotations)
    if load is not None:
        Uxq, UxD, UxA = Uxq + load[0], UxD + load[1], UxA + load[2]
    return Uxq, UxD, UxA, qmask, lay


def _rotation_rows_from_hessian(eq, rows, D0, tip: bool = False, own: bool = False):
    """``(U_xq (B, 2N, nq), U_xx (B, 2N, 2N), tip partials or None, the layout's qmask
    (B, nq))`` with the insertion rows from the kernel (:func:`_kernel_rows`: the compiled
    kernel's complex step, no graph) for an unloaded energy, else by one double-backward pass
    over the batch repeated ``N`` times (not ``2N``), and the rotation rows read off the
    equilibrium's Hessian (``own``: ``D0`` is the equilibrium's insertion, not a kink's side):
    the potential depends on ``alpha_j`` and
    the guide twist ``w_j`` only through ``alpha_j + D_j w_j`` (plus the guide's
    ``1/2 GJ_j D_j w_j^2``), so where every ``D_j > 0`` (``w_j`` a coordinate)
    ``U_{alpha_j .} = (H[w_j, .] - GJ_j D_j e_{w_j}) / D_j`` and
    ``U_{alpha_j alpha_k} = (H[w_j, w_k] - delta_jk GJ_j D_j) / (D_j D_k)``.

    With ``tip`` the tip partials ``(P_q, P_x)`` of :func:`_tip_partials` too: on the eager
    kernel (or under a load) the same pass repeats the batch ``N + 6`` times, one layout and
    one reverse pass for the whole control step (the op count, not the flops, bounds it at
    small batches); with compiled rows they take their own 6-row pass."""
    B, N = D0.shape
    ctx = eq.context
    kernel = KERNELS[ctx.options.kernel]
    # the kernel's rows (compiled: a complex step per insertion, no graph); the tip partials
    # then by their own reverse pass (6 rows), which is cheaper than one pass through both
    # graphs only when the rows' graph is not needed
    if (not tip or kernel.actuation_rows is not EAGER.actuation_rows) and (
            out := _rows_without_graph(eq, rows, D0, own, False)) is not None:
        UDq, UDD, UDA, lay_mask, lay = out
        partials = _tip_partials(eq, rows, None if own else D0, lay) if tip else None
        return (*_with_rotation_rows(eq, rows, D0, UDq, UDD, UDA), partials, lay_mask)
    m = N + 6 * tip
    q, info, (D, A, F, M), tubes = _replicated(eq, m, rows, D0)
    pick = torch.eye(m, dtype=q.dtype, device=q.device).repeat(B, 1)        # (B m, m)
    D, A, q = (t.requires_grad_(True) for t in (D, A, q))
    with torch.enable_grad():
        lay = build_layout(tubes, D, A, F, M, info.loaded, info.disc)
        if info.with_load:
            U = potential(q, lay, info.tab, None, True)
            tau_D = torch.autograd.grad(U.sum(), D, create_graph=True)[0]
        else:
            # the closed-form dU/dD (forces.closed_form_partials) differentiated once, instead
            # of a double backward through the energy
            tau_D = closed_form_partials(q, lay, tubes, info.tab, info.disc)[0]
        out = torch.cat([tau_D, tip_twist(q, lay, info.tab)], -1) if tip else tau_D
        Gq, GD, GA = (g.reshape(B, m, -1) for g in
                      torch.autograd.grad((out * pick).sum(), (q, D, A)))
    partials = (_tip_rows(eq, rows, *(g[:, N:] for g in (Gq, GD, GA))) if tip else None)
    UDq, UDD, UDA = (g[:, :N] for g in (Gq, GD, GA))
    Uxq, Uxx = _with_rotation_rows(eq, rows, D0, UDq, UDD, UDA)
    return Uxq, Uxx, partials, lay.qmask.reshape(B, m, -1)[:, 0]


def _with_rotation_rows(eq, rows, D0, UDq, UDD, UDA):
    """``(U_xq (B, 2N, nq), U_xx (B, 2N, 2N))`` from the insertion rows and the rotation rows
    read off the equilibrium's Hessian (:func:`_rotation_rows_from_hessian`)."""
    B, N = D0.shape
    Hw = eq.context.implicit.hessian()[rows, :N]            # (B, N, nq): the guide twists' rows
    GJ = tube_rows(eq.context.tubes, rows).GJ.detach().expand(B, N)
    GJD = torch.diag_embed(GJ * D0)                                         # (B, N, N)
    UAq = Hw.clone()
    UAq[:, :, :N] -= GJD
    UAq = UAq / D0[:, :, None]
    UAA = (Hw[:, :, :N] - GJD) / (D0[:, :, None] * D0[:, None, :])
    Uxq = torch.cat([UDq, UAq], 1)
    Uxx = torch.cat([torch.cat([UDD, UDA], -1),
                     torch.cat([UDA.transpose(1, 2), UAA], -1)], 1)
    return Uxq, Uxx


def control_jacobians(eq, *, compliance: bool = True,
                      rank_tol: float = 1e-9) -> ControlJacobians:
    """:class:`ControlJacobians` of an :class:`~torchpvs.Equilibrium` (all elements).

    The actuator stiffness and tip Jacobian come from the equilibrium's own factorization
    (:func:`actuator_stiffness`, :func:`tip_jacobian`). The tip compliance
    ``C = P_q T^-1 P_q^T`` (``T`` the tangent, ``P_q`` the tip twist per coordinate: a dead load
    ``w = (F, M)`` enters the residual as ``-P_q^T w``) needs coordinates on the distal
    single-tube sections, which an unloaded solve leaves out (they are exact there without a
    load): for an unloaded equilibrium it re-solves once with ``load_coordinates=True``, warm
    from this one. ``compliance=False`` skips it (``tip_compliance`` is then ``None``): the
    control step of a servo loop."""
    rows = _rows_of(eq, None)
    K, J = _control_blocks(eq, rows)
    K, J = K.detach(), J.detach()
    C = None
    if compliance:
        eqc = eq
        if not eq.context.implicit.with_load:
            # forces are not needed here, and the loaded forces (a reverse pass through
            # the pose chain) were 13 of the re-solve's 15 ms
            opts = replace(eq.context.options, load_coordinates=True, order=eq.order,
                           compute_forces=False)
            eqc = eq.solve_again(opts, eq)
        Pq = _tip_partials(eqc, rows)[0]
        C = (Pq @ _adjoint_rows(eqc, rows).solve(Pq.transpose(1, 2), tangent=True)).detach()
    # one SVD for the rank and the pseudo-inverse (pinv would take its own)
    U, sv, Vh = torch.linalg.svd(K, full_matrices=False)
    keep = sv > rank_tol * sv[:, :1]
    rank = keep.sum(-1)
    Kp = Vh.transpose(-2, -1) @ (torch.where(keep, 1.0 / sv, 0.0)[..., None]
                                 * U.transpose(-2, -1))
    return ControlJacobians(actuator_stiffness=K, tip_jacobian=J, force_jacobian=J @ Kp,
                            tip_compliance=C, force_rank=rank)
