"""Stage 6 — implicit-function backward: gradients of an equilibrium without unrolling Newton.

The equilibrium ``q*(theta)`` solves ``g(q*, theta) = dPi/dq = 0`` for the inputs
``theta = (D, alpha, F, M, EI, GJ, L, Ls, coef)``. Differentiating the identity
``g(q*(theta), theta) = 0`` gives ``H dq*/dtheta = -dg/dtheta`` with ``H = dg/dq`` the stiffness
at the solution. For a loss ``l(q*)`` with ``v = dl/dq*`` the vector-Jacobian product is therefore

    dl/dtheta = -lambda^T dg/dtheta,       H^T lambda = v                       (adjoint system)

one linear solve with the (already factorizable) stiffness, and one reverse pass through the
gradient ``g`` — never through the Newton iterations. ``lambda^T dg/dtheta`` is obtained with
autograd as the gradient w.r.t. ``theta`` of the scalar ``lambda . g(q*, theta)``.

Outputs that depend on ``theta`` directly as well (tip pose, energy, forces) are then recomputed
from ``q*`` and ``theta`` with ordinary autograd, so every ``Equilibrium`` field is differentiable.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import torch

from .batch_linalg import active_index, compact
from .lie import hat
from .mechanics import expand_hessian, node_fields, potential, skew_vee, tip_pose
from .sections import Discretization, Tables, TubeTensors, build_layout

__all__ = ["DifferentiableOutputs", "ImplicitContext", "ImplicitEquilibrium",
           "NearSingularStiffnessWarning", "full_hessian"]


class NearSingularStiffnessWarning(RuntimeWarning):
    """The stiffness at an equilibrium is (nearly) singular: gradients there are unreliable."""


@dataclass(eq=False)
class ImplicitContext:
    """What the implicit backward needs of one solve besides the differentiable inputs
    (``B`` elements, ``nq`` padded coordinates, ``nc`` the kernel's compact ones).

    Attributes:
        qmask: ``(B, nq)`` float 0/1, the active coordinates.
        loaded: ``(B,)`` bool, elements with a tip load (they have coordinates on the distal
            single-tube sections).
        disc: the discretization of the solution; ``tab``: its quadrature and basis tables
            (:meth:`torchpvs.sections.Discretization.tables`).
        with_load: any element loaded (the potential includes the load's work).
        has_moment: a tip moment is modelled (its reference rotation enters the potential).
        ridge, singular_tol: ``SolverOptions.backward_ridge`` and ``singular_tol``.
        Hc: ``(B, nc, nc)`` the kernel's Hessian at the solution on its compact coordinates
            ``cidx (B, nc)`` (index into ``q``), with their mask ``qmask_c (B, nc)``; ``None``
            on a replicated context that carries ``H`` or the adjoint factors instead.
        H: cache, ``(B, nq, nq)`` the Hessian on the padded coordinates (identity on the
            inactive ones), from ``Hc`` on first use (:meth:`hessian`).
        adjoint: cache, the :class:`AdjointFactors` of the tangent (:func:`adjoint_factor`),
            computed by the first backward and reused by every later one through the same
            solve.
    """

    qmask: torch.Tensor
    loaded: torch.Tensor
    disc: Discretization
    tab: Tables
    with_load: bool
    has_moment: bool
    ridge: float
    singular_tol: float
    Hc: torch.Tensor | None = None
    cidx: torch.Tensor | None = None
    qmask_c: torch.Tensor | None = None
    H: torch.Tensor | None = None
    adjoint: AdjointFactors | None = None

    def hessian(self) -> torch.Tensor:
        """``H`` ``(B, nq, nq)``, expanded from ``Hc`` on first use and cached."""
        if self.H is None:
            self.H = expand_hessian(self.Hc, self.cidx, self.qmask.shape[-1])
        return self.H

    def rows(self, idx: torch.Tensor, **changes) -> ImplicitContext:
        """The context of batch rows ``idx`` (``qmask``, ``loaded`` indexed) without the
        whole-batch stiffness and caches (``Hc``, ``cidx``, ``qmask_c``, ``H``, ``adjoint``),
        which ``changes`` may set for the rows."""
        base = {"Hc": None, "cidx": None, "qmask_c": None, "H": None, "adjoint": None}
        return replace(self, qmask=self.qmask[idx], loaded=self.loaded[idx],
                       **{**base, **changes})

    def map_tensors(self, fn) -> ImplicitContext:
        """A copy with ``fn`` applied to every tensor field (``tab`` and the caches' tuples
        as they are)."""
        return replace(self, **{f.name: fn(v) for f in fields(self)
                                for v in (getattr(self, f.name),)
                                if isinstance(v, torch.Tensor)})


class ImplicitEquilibrium(torch.autograd.Function):
    """``q* = ImplicitEquilibrium.apply(q_star, info, D, alpha, F, M, *tubes.tensors())``.

    ``q_star`` is the converged solution (detached), ``info`` the :class:`ImplicitContext`
    (layout choices, quadrature tables and the stiffness ``H`` at the solution). The
    differentiable inputs are passed one by one (never inside a container), as autograd
    requires: the tube properties as ``TubeTensors.tensors()`` (field order), turned back into
    a :class:`~torchpvs.sections.TubeTensors` by name inside (the way torchdiffeq's adjoint
    takes ``adjoint_params``). Use :func:`differentiable_outputs`, which does both.
    """

    @staticmethod
    def forward(ctx, q_star, info, D, alpha, F, M, *tube_params):  # noqa: N805
        ctx.info = info
        ctx.save_for_backward(q_star, D, alpha, F, M, *tube_params)
        return q_star.clone()

    @staticmethod
    def backward(ctx, grad_q):  # noqa: N805
        if torch.is_grad_enabled():
            # create_graph=True: a second derivative would need d(H^-1)/dtheta, which this
            # backward does not provide; failing loudly beats a silently partial Hessian.
            raise RuntimeError(
                "torchpvs: second derivatives through an equilibrium (grad of grad, "
                "create_graph=True) are not supported; differentiate once, or use finite "
                "differences of first-order gradients")
        return _backward(ctx, grad_q)


def _backward(ctx, grad_q):
    """The adjoint solve and the reverse pass through ``g`` (see the module docstring)."""
    # Adjoint: H lambda = grad_q on the active coordinates (H is symmetric: the tangent
    # of a potential; the tip-moment load stiffness is symmetrized as in the solve).
    q_star, D, alpha, F, M, *tube_params = ctx.saved_tensors
    info: ImplicitContext = ctx.info
    qmask = info.qmask
    # One factorization per equilibrium: every reverse pass through the same solve (e.g. the
    # 2N rows of the actuator stiffness) reuses it, and the singularity check runs once.
    # (info belongs to one solve: its H, q*, actuation and load never change.)
    cached = info.adjoint
    if cached is None:
        cached = adjoint_factor(q_star, info, D, alpha, F, M,
                                TubeTensors.from_tensors(tube_params))
        info.adjoint = cached
    lam = cached.solve((grad_q * qmask)[..., None])[..., 0] * qmask
    needs = ctx.needs_input_grad[2:]
    inputs = [t.detach().requires_grad_(bool(nd)) for t, nd in
              zip((D, alpha, F, M, *tube_params), needs, strict=True)]
    with torch.enable_grad():
        q = q_star.detach().requires_grad_(True)
        lay = build_layout(TubeTensors.from_tensors(inputs[4:]), inputs[0], inputs[1],
                           inputs[2], inputs[3], info.loaded, info.disc)
        # Second slot: the moment's reference rotation stays attached to theta (not to q).
        R0 = tip_pose(q.detach(), lay, info.tab)[1] if info.has_moment else None
        P = potential(q, lay, info.tab, R0, info.with_load)
        (g,) = torch.autograd.grad(P.sum(), q, create_graph=True)
        wanted = [t for t in inputs if t.requires_grad]
        grads = torch.autograd.grad((g * lam).sum(), wanted, allow_unused=True) \
            if wanted else []
    it = iter(grads)
    out = []
    for t in inputs:
        if t.requires_grad:
            gt = next(it)
            out.append(None if gt is None else -gt)
        else:
            out.append(None)
    return (None, None, *out)


def full_hessian(info: ImplicitContext) -> torch.Tensor:
    """The equilibrium's Hessian ``(B, nq, nq)`` on the padded coordinates (identity on the
    inactive ones), expanded from the kernel's compact one (``info.Hc`` on the coordinates
    ``info.cidx``) on first use and kept in ``info.H`` (:meth:`ImplicitContext.hessian`)."""
    return info.hessian()


class AdjointFactors(NamedTuple):
    """The LU factorization of one solve's Jacobi-scaled tangent (:func:`adjoint_factor`), on
    each element's active coordinates only (:func:`torchpvs.batch_linalg.active_index`:
    ``nA`` = the most active coordinates of the batch, about 3/4 of the padded ``nq`` on the
    Fig. 3 robot, so the factorization costs about 2.3x fewer flops than on all of them).

    Attributes:
        lu, pivots: ``(B, nA, nA)``, ``(B, nA)``: ``torch.linalg.lu_factor`` of ``A^T``,
            ``A = S T S + ridge I`` (``T`` the tangent on the active coordinates,
            ``S = diag(scale)^-1/2``).
        scale: ``(B, nA)`` the diagonal's magnitudes (clamped to the dtype's tiny).
        act: ``(B, nA)`` the padded coordinates of the rows (padding rows are inactive ones,
            identity rows of ``A``), or None when every coordinate is active.
    """

    lu: torch.Tensor
    pivots: torch.Tensor
    scale: torch.Tensor
    act: torch.Tensor | None

    def rows(self, idx: torch.Tensor) -> AdjointFactors:
        """The factors of batch rows ``idx``."""
        return AdjointFactors(*(None if t is None else t[idx] for t in self))

    def solve(self, rhs: torch.Tensor, *, tangent: bool = False) -> torch.Tensor:
        """``T^-T rhs`` (the adjoint system; ``T^-1 rhs`` with ``tangent``) for ``rhs (B, nq,
        k)`` on the padded coordinates; zero on the inactive ones (``rhs`` must be zero there)."""
        B, nq, k = rhs.shape
        s = self.scale.sqrt()[..., None]
        r = rhs if self.act is None else torch.gather(
            rhs, 1, self.act[:, :, None].expand(B, self.act.shape[1], k))
        x = torch.linalg.lu_solve(self.lu, self.pivots, r / s, adjoint=tangent) / s
        if self.act is None:
            return x
        return rhs.new_zeros(B, nq, k).scatter_(1, self.act[:, :, None].expand_as(x), x)


def adjoint_factor(q_star, info: ImplicitContext, D, alpha, F, M,
                   tubes: TubeTensors) -> AdjointFactors:
    """:class:`AdjointFactors` of the tangent ``K^T`` of the adjoint system, on each element's
    active coordinates; warns once if the stiffness is nearly singular."""
    H = info.hessian()
    qmask = info.qmask
    act = active_index(qmask)
    # The active block (inactive coordinates are identity rows of H: they decouple and stay
    # identity rows among the padding of act).
    Ha = compact(H, act)
    scale = Ha.diagonal(dim1=-2, dim2=-1).abs().clamp(min=torch.finfo(H.dtype).tiny)
    Hs = Ha / torch.sqrt(scale[:, :, None] * scale[:, None, :])
    # The spectrum on the active coordinates (padding rows are identity rows, eigenvalue 1):
    # a Cholesky of Hs - tol I proves every eigenvalue above tol (the stable case); eigvalsh
    # only for the elements where it fails.
    tol = info.singular_tol
    eye = torch.eye(Hs.shape[-1], dtype=H.dtype, device=H.device)
    # A non-finite stiffness (an element whose solve overflowed: not converged) has no
    # spectrum; LAPACK's eigh raises on it, so it is reported on its own.
    finite = torch.isfinite(Hs).flatten(1).all(-1)
    maybe = (torch.linalg.cholesky_ex(Hs - tol * eye)[1] != 0) & finite
    near = torch.zeros_like(maybe)
    if bool(maybe.any()):
        near[maybe] = torch.linalg.eigvalsh(Hs[maybe]).abs().amin(-1) < tol
    if not bool(finite.all()):
        bad = (~finite).nonzero().flatten().tolist()
        warnings.warn(
            f"torchpvs: stiffness not finite at {len(bad)} element(s) {bad[:8]} (no equilibrium "
            "there: see Equilibrium.converged): their implicit gradients are NaN.",
            NearSingularStiffnessWarning, stacklevel=4)
    if bool(near.any()):
        warnings.warn(
            f"torchpvs: stiffness nearly singular at {int(near.sum())} element(s) "
            f"{near.nonzero().flatten().tolist()[:8]} (a fold/snap point): implicit gradients "
            "there are unreliable; SolverOptions(backward_ridge=...) regularizes them.",
            NearSingularStiffnessWarning, stacklevel=4)
    A = Hs + info.ridge * eye
    if info.has_moment and bool((M != 0).any()):
        # A dead tip moment is not conservative: the exact tangent adds the antisymmetric
        # K_ab = 1/2 M . (theta_a x theta_b) = -1/2 J_theta^T [M]x J_theta (see mechanics).
        Jt = _rotation_jacobian(q_star, info, D, alpha, F, M, tubes)
        K = -0.5 * Jt.transpose(1, 2) @ hat(M) @ Jt
        K = compact(K * qmask[:, :, None] * qmask[:, None, :], act)
        A = A + K / torch.sqrt(scale[:, :, None] * scale[:, None, :])
    # Adjoint of the (possibly non-symmetric) tangent: K^T lambda = v.
    lu, pivots = torch.linalg.lu_factor(A.transpose(1, 2))
    return AdjointFactors(lu, pivots, scale, act)


def _rotation_jacobian(q_star, info: ImplicitContext, D, alpha, F, M,
                       tubes: TubeTensors) -> torch.Tensor:
    """``J_theta (B, 3, nq)``: spatial angular velocity of the tip frame per coordinate."""
    lay = build_layout(tubes, D, alpha, F, M, info.loaded, info.disc)
    tab = info.tab

    def rotvec(q, lay_b, q0):
        _, R, _ = tip_pose(q, lay_b, tab)
        with torch.no_grad():
            _, R0, _ = tip_pose(q0, lay_b, tab)
        return skew_vee(R @ R0.transpose(-1, -2))

    q = q_star.detach()
    lay = type(lay)(*(v.detach() for v in lay))
    return torch.func.vmap(torch.func.jacrev(rotvec))(q, lay, q)


class DifferentiableOutputs(NamedTuple):
    """The outputs of a solve as differentiable functions of its inputs
    (:func:`differentiable_outputs`; ``B`` elements, ``N`` tubes, ``nq`` coordinates).

    Attributes:
        q: ``(B, nq)`` [1/m] the equilibrium coordinates (the implicit ``q*``).
        tip: ``(B, 3)`` [m] the tip position; ``R``: ``(B, 3, 3)`` the tip frame.
        energy: ``(B,)`` [J] stored elastic energy minus the potential of the tip force.
        forces: ``(B, N)`` [N] ``dU*/dD``; ``torques``: ``(B, N)`` [N·m] ``dU*/dalpha``.
        rel_unwrapped: ``(B, N-1)`` [rad] the tube angles relative to the outer tube's at its
            distal end, not wrapped.
    """

    q: torch.Tensor
    tip: torch.Tensor
    R: torch.Tensor
    energy: torch.Tensor
    forces: torch.Tensor
    torques: torch.Tensor
    rel_unwrapped: torch.Tensor


def differentiable_outputs(q_star: torch.Tensor, info: ImplicitContext, D, alpha, F, M,
                           tubes: TubeTensors) -> DifferentiableOutputs:
    """Every output as a differentiable function of the inputs, through the implicit ``q*``."""
    q = ImplicitEquilibrium.apply(q_star.detach(), info, D, alpha, F, M, *tubes.tensors())
    dD = torch.zeros_like(D, requires_grad=True)
    dA = torch.zeros_like(alpha, requires_grad=True)
    lay = build_layout(tubes, D + dD, alpha + dA, F, M, info.loaded, info.disc)
    tab = info.tab
    p, R, _ = tip_pose(q, lay, tab)
    R0 = None
    if info.has_moment:
        # Reference slot: same state, but not differentiated by the forces' d/d(dD, dA).
        lay0 = build_layout(tubes, D, alpha, F, M, info.loaded, info.disc)
        R0 = tip_pose(q, lay0, tab)[1]
    U = potential(q, lay, tab, R0, info.with_load)
    energy = potential(q, lay, tab, None, info.with_load)
    tau_D, tau_A = torch.autograd.grad(U.sum(), (dD, dA), create_graph=True)
    f = node_fields(q, lay, tab.xq, tab.phi_q, tab.Q_q)
    psi_l1 = f.psi0 + (f.inc * lay.before_l1[..., None]).sum(-2)
    rel = psi_l1[:, 1:] - psi_l1[:, :1]
    return DifferentiableOutputs(q=q, tip=p, R=R, energy=energy, forces=tau_D, torques=tau_A,
                                 rel_unwrapped=rel)
