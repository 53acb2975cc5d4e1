"""Stage 5a — the kernel seam: what the driver asks of a kernel, and the registry of kernels.

The driver (:mod:`torchpvs.solver` with :mod:`torchpvs.order_control` and
:mod:`torchpvs.predictor`) chooses discretizations, ramps loads, keeps layouts and maps (the
plan), and assembles the outputs; every computation it makes *per batch element* goes through
one :class:`Kernel`: the layout and maps at new insertions, the cold-start guess, the Newton
solve, the single Newton steps of the order estimate and the kink re-solves, the new-section
step of the one-sided forces, the tip pose, the closed-form partials of the actuation forces,
the rows of the actuator stiffness and the tip's partials of the control Jacobians, and the
SPD solves of the rotation predictor. A
kernel is a :class:`Kernel` of plain functions registered in :data:`KERNELS` under a name
(``SolverOptions(kernel=name)``), in the spirit of torchdiffeq's ``SOLVERS``; adding one (a
compiled CPU kernel, a fused GPU kernel) touches no driver code, and a kernel that implements
only some functions reuses the eager ones for the rest (``EAGER._replace(solve=my_solve)``).

:data:`EAGER` (``"newton"``) is the reference: batched eager torch, on any device
(:mod:`torchpvs.newton` for the damped iteration, :mod:`torchpvs.batch_linalg` for the
per-element linear algebra, :mod:`torchpvs.mechanics` for energies and poses).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

from . import compiled, compiled_layout
from .batch_linalg import active_index, chunked, compact, compact_scaled, expand, spd_solve, take
from .forces import actuation_rows, closed_form_partials
from .mechanics import (
    Maps,
    build_layout_and_maps,
    compact_q,
    expand_q,
    section_grad_block,
    start_angles,
    sum_dim,
    tip_partials,
    tip_pose,
)
from .newton import NewtonResult, Problem, derivatives, newton, scaled_residual
from .sections import Discretization, Layout, Tables, build_layout, n_coordinates

__all__ = ["COMPILED", "EAGER", "KERNELS", "Kernel", "default_guess", "new_section_step",
           "newton_step", "no_load_rows"]


class Kernel(NamedTuple):
    """The per-element computations of a solve (``B`` elements, ``nq`` padded coordinates, a
    :class:`~torchpvs.newton.Problem` ``prob`` of one discretization). Every function is
    batched and returns a success mask where it can fail; rows that fail are returned
    unchanged, never NaN.

    Attributes:
        layout: ``layout(tubes, D, A, F, M, loaded, disc, nq) -> (lay, maps)``: the
            :class:`~torchpvs.sections.Layout` and :class:`~torchpvs.mechanics.Maps` of a batch
            at insertions ``D (B, N)``, rotations ``A``, tip load ``F, M (B, 3)`` (the
            arguments of :func:`torchpvs.sections.build_layout`; ``nq`` the padded coordinate
            count of ``disc``), which :meth:`torchpvs.plan.Plan.layout` keeps while the
            insertions stay; differentiable where an input requires grad.
        guess: ``guess(lay, maps, tab, disc, N) -> q0 (B, nq)``, the cold-start coordinates
            (:class:`~torchpvs.sections.Layout`, :class:`~torchpvs.mechanics.Maps`,
            :class:`~torchpvs.sections.Tables`).
        solve: ``solve(q0, prob, L_char, *, method, tol, max_iter, deadline) ->``
            :class:`~torchpvs.newton.NewtonResult`: the equilibrium from ``q0`` (``L_char
            (B,)`` [m] the residual's length scale, ``SolverOptions.tol``).
        step: ``step(q, prob) -> (q1, ok)``: one undamped Newton step (the order estimate
            and the re-solves of the one-sided forces).
        section_step: ``section_step(q, prob, new (B, nq) bool, length) -> (q1, ok)``: the
            coordinates ``new`` of a vanishing section solved for with the rest held.
        pose: ``pose(q, lay, tab, constants) -> (tip (.., B, 3), R (.., B, 3, 3), extra)``:
            the tip pose of :func:`torchpvs.mechanics.tip_pose` (``q`` may carry leading
            dims; ``constants`` the :class:`~torchpvs.mechanics.PoseConstants` of
            ``maps.pose`` or of finer Magnus nodes).
        spd_solve: ``spd_solve(H (B, n, n), rhs (B, n)) -> (x, ok)``: ``H^-1 rhs`` for the
            stiffness at a solution (the rotation predictor).
        partials: ``partials(q, lay, tubes, tab, disc, constants) -> (tau_D, tau_alpha)``
            ``(B, N)`` [N, N·m]: the envelope partials of the unloaded energy at fixed ``q``
            (:func:`torchpvs.forces.closed_form_partials`; ``constants`` its node constants
            or None), for the actuation forces and their one-sided values at kinks.
        actuation_rows: ``actuation_rows(q, tubes, D, alpha, loaded, tab, disc, rotations,
            layout) -> (U_xq (B, m, nq), U_xD (B, m, N), U_xalpha (B, m, N), qmask (B, nq))``
            (``layout``: the :class:`~torchpvs.sections.Layout` at ``D`` where known): the
            insertions' (``m = N``) or all actuators' (``rotations``, ``m = 2N``) rows of the
            unloaded energy's Hessian at fixed ``q`` and the layout's coordinate mask at ``D``
            (:func:`torchpvs.forces.actuation_rows`), for the actuator stiffness
            (:func:`torchpvs.jacobians.actuator_stiffness`).
        tip_partials: ``tip_partials(q, tubes, D, alpha, loaded, tab, disc, layout) -> (P_q
            (B, 6, nq), P_D (B, 6, N), P_alpha (B, 6, N))``: the tip twist's partials at fixed
            ``q`` (position [m], spatial rotation [rad]; :func:`torchpvs.mechanics.tip_partials`),
            for the closed-form tip Jacobian and compliance (:mod:`torchpvs.jacobians`).
        load_rows: ``load_rows(q, tubes, D, alpha, loaded, tab, disc, force, rotations,
            layout) -> (U_xq, U_xD, U_xalpha)`` (shapes of ``actuation_rows``) or None: the
            same rows of a dead tip force's potential ``-F . p`` (``force (B, 3)`` [N], base
            frame), which the actuator stiffness adds to ``actuation_rows``' on a loaded layout.
            None where the kernel has none: the stiffness then takes a loaded robot's rows by
            one double-backward pass through the loaded potential (the eager reference).
    """

    layout: Callable[..., tuple[Layout, Maps]]
    guess: Callable[..., torch.Tensor]
    solve: Callable[..., NewtonResult]
    step: Callable[[torch.Tensor, Problem], tuple[torch.Tensor, torch.Tensor]]
    section_step: Callable[..., tuple[torch.Tensor, torch.Tensor]]
    pose: Callable[..., tuple]
    spd_solve: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
    partials: Callable[..., tuple[torch.Tensor, torch.Tensor]]
    actuation_rows: Callable[..., tuple]
    tip_partials: Callable[..., tuple]
    load_rows: Callable[..., tuple | None]


def no_load_rows(q, tubes, D, alpha, loaded, tab, disc, force, rotations=False, layout=None):
    """The eager kernel's ``load_rows``: none (the actuator stiffness differentiates the loaded
    potential twice by autograd instead, :mod:`torchpvs.jacobians`)."""
    return None


def newton_step(q: torch.Tensor, prob: Problem) -> tuple[torch.Tensor, torch.Tensor]:
    """One undamped Newton step (Jacobi-scaled; Cholesky, and LU where the Hessian is indefinite,
    as at an unstable equilibrium). Returns the new coordinates (``q`` where the step failed)
    and the success mask. The step runs on the compact coordinates (mechanics.build_maps);
    large batches go in cache-sized chunks of them (see batch_linalg.CHUNK_BYTES)."""
    cidx = prob.maps.cidx
    qc, ok = chunked(_one_newton_step, compact_q(q, cidx), prob)
    return torch.where(ok[:, None], expand_q(qc, cidx, q.shape[-1]), q), ok


def _one_newton_step(q, prob: Problem):
    qmask = prob.maps.qmask
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


#: A section this short (x the longest tube) counts as vanishing for the new-section step.
VANISHING = 1e-5


def new_section_step(q: torch.Tensor, prob: Problem, new: torch.Tensor,
                     length: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The coordinates ``new (B, nq)`` (bool), those of a section of vanishing length ``h`` that
    appears at a one-sided equilibrium, solved for with the others held: one Newton step on
    their block of the elastic energy (:func:`torchpvs.mechanics.section_grad_block`). Held
    coordinates are off by ``O(h)`` (the new section's pull on the rest), and the block's terms
    through the angle bases are ``O(h)`` of it, so the result is ``O(h)`` accurate, like the
    one-sided forces evaluated there, at the cost of a gradient, not a Hessian and its
    factorization. Unloaded problems only (a tip load's work moves with the section's strains
    at the same order). Returns the coordinates and the rows where it applied (new coordinates
    in one compact section, no guide twist among them, the section shorter than
    ``VANISHING x length``, its block positive definite); other rows are returned unchanged."""
    maps = prob.maps
    cidx = maps.cidx
    B, nq = q.shape
    N = maps.bvec.shape[2]
    S = maps.h.shape[1]
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
          & (maps.h[rows, sec] <= VANISHING * length))
    X = qc[:, N:].reshape(B, S, cn)
    X[rows, sec] = X[rows, sec] + d
    q1 = expand_q(torch.cat([qc[:, :N], X.reshape(B, -1)], -1), cidx, nq)
    return torch.where(ok[:, None], q1, q), ok


def default_guess(lay: Layout, maps: Maps, tab: Tables, disc: Discretization,
                  N: int) -> torch.Tensor:
    """Torsionless guess: tubes keep their base angles, the backbone bends with the
    stiffness-weighted average of the rotated precurvatures (exact without torsion, eq. 31).
    Built on the kernel's compact sections (``maps``, :func:`torchpvs.mechanics.build_maps`):
    only they carry coordinates; the tube angles there are the base angles plus the twist of
    the prescribed sections before them."""
    B = lay.h.shape[0]
    nq = n_coordinates(N, disc.n_basis)
    cidx = maps.cidx
    S = maps.h.shape[1]
    n = disc.n_basis
    start = start_angles(lay.psi0, maps.presc_inc)                 # (B, S_full, N), q = 0
    sec = torch.div(cidx[:, N::(2 + N) * n] - N, (2 + N) * n, rounding_mode="floor")
    psi = torch.gather(start, 1, sec[:, :, None].expand(B, S, N))[:, :, None, :]
    us = maps.ustar                                                # (B, S, Q, N, 3)
    cs, sn = torch.cos(psi), torch.sin(psi)
    Rx = cs * us[..., 0] - sn * us[..., 1]
    Ry = sn * us[..., 0] + cs * us[..., 1]
    # stiffness-weighted (present tubes): EIw / EIws, the node weights cancel. Padded compact
    # sections have EIws = 0: the clamp must be representable in the dtype (1e-300 is 0 in
    # float32, and 0 / 0 made the whole guess NaN).
    wgt = maps.EIw / maps.EIws[..., None].clamp(min=torch.finfo(maps.EIws.dtype).tiny)
    u_avg = torch.stack([sum_dim(wgt * Rx, -1), sum_dim(wgt * Ry, -1)], -1)   # (B, S, Q, 2)
    a = 0.5 * torch.einsum("bsgd,gp,g->bsdp", u_avg, tab.phi_q, tab.wq)
    X = torch.zeros(B, S, 2 + N, n, dtype=a.dtype, device=a.device)
    X[:, :, :2, :] = a
    qc = torch.cat([torch.zeros(B, N, dtype=a.dtype, device=a.device), X.reshape(B, -1)], -1)
    return expand_q(qc, cidx, nq)


#: The reference kernel: batched eager torch on any device.
EAGER = Kernel(layout=build_layout_and_maps, guess=default_guess, solve=newton, step=newton_step,
               section_step=new_section_step, pose=tip_pose, spd_solve=spd_solve,
               partials=closed_form_partials, actuation_rows=actuation_rows,
               tip_partials=tip_partials, load_rows=no_load_rows)


def _compiled_layout(tubes, D, A, F, M, loaded, disc, nq):
    out = compiled_layout.layout_and_maps(tubes, D, A, F, M, loaded, disc, nq)
    return build_layout_and_maps(tubes, D, A, F, M, loaded, disc, nq) if out is None else out


def _compiled_solve(q, prob, L_char, **kwargs):
    out = compiled.solve(q, prob, L_char, **kwargs)
    return newton(q, prob, L_char, **kwargs) if out is None else out


def _compiled_step(q, prob):
    out = compiled.step(q, prob)
    return newton_step(q, prob) if out is None else out


def _compiled_section_step(q, prob, new, length):
    out = compiled.section_step(q, prob, new, VANISHING * length)
    return new_section_step(q, prob, new, length) if out is None else out


def _compiled_partials(q, lay, tubes, tab, disc, constants=None):
    out = compiled.partials(q, lay, tubes, tab)
    return closed_form_partials(q, lay, tubes, tab, disc, constants) if out is None else out


def _on_layout(compiled_fn, q, tubes, D, alpha, loaded, disc, layout, *args):
    """``(compiled_fn(q, lay, tubes, *args), lay)`` on the layout at ``D`` (``layout`` where
    the caller has it, else built without a graph); ``(None, None)`` where the compiled kernel
    cannot run (not built, not a CPU tensor) or does not apply."""
    if not (compiled.available() and q.device.type == "cpu"):
        return None, None
    with torch.no_grad():
        lay = layout
        if lay is None:
            zero = torch.zeros(D.shape[0], 3, dtype=q.dtype, device=q.device)
            lay = build_layout(tubes, D.detach(), alpha.detach(), zero, zero, loaded, disc)
        return compiled_fn(q.detach(), lay, tubes.map(torch.Tensor.detach), *args), lay


def _compiled_actuation_rows(q, tubes, D, alpha, loaded, tab, disc, rotations=False,
                             layout=None):
    out, lay = _on_layout(compiled.stiffness_rows, q, tubes, D, alpha, loaded, disc, layout,
                          tab, rotations)
    if out is not None:
        return (*out, lay.qmask)
    return actuation_rows(q, tubes, D, alpha, loaded, tab, disc, rotations)


def _compiled_tip_partials(q, tubes, D, alpha, loaded, tab, disc, layout=None):
    out, _ = _on_layout(compiled.tip_partials, q, tubes, D, alpha, loaded, disc, layout, tab)
    return tip_partials(q, tubes, D, alpha, loaded, tab, disc) if out is None else out


def _compiled_load_rows(q, tubes, D, alpha, loaded, tab, disc, force, rotations=False,
                        layout=None):
    out, _ = _on_layout(compiled.load_rows, q, tubes, D, alpha, loaded, disc, layout, tab,
                        force.detach(), rotations)
    return out


def _compiled_pose(q, lay, tab, constants):
    out = compiled.pose(q, lay, tab, constants)
    return tip_pose(q, lay, tab, constants) if out is None else out


#: The compiled CPU kernel (:mod:`torchpvs.compiled`, numba): the layout and maps
#: (:mod:`torchpvs.compiled_layout`), the Newton solve and step, the new-section step, the tip
#: pose, the closed-form force partials, the stiffness's actuator rows (a complex step of the
#: partials) and the tip partials (the Magnus chain in ``q``, a complex step of the pose in the
#: actuators) per element; the eager kernel wherever it does not apply (GPU tensors; a tip
#: moment for the solve and step, a tip load for the new-section step; layouts and partials
#: that must carry a graph; float32 layouts).
COMPILED = EAGER._replace(layout=_compiled_layout, solve=_compiled_solve, step=_compiled_step,
                          section_step=_compiled_section_step, pose=_compiled_pose,
                          partials=_compiled_partials, actuation_rows=_compiled_actuation_rows,
                          tip_partials=_compiled_tip_partials, load_rows=_compiled_load_rows)

#: Kernels by name (``SolverOptions.kernel``).
KERNELS: dict[str, Kernel] = {"newton": EAGER, "compiled": COMPILED}
