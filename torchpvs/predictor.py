"""Stage 5 (driver) — where a warm solve starts: the warm-start coordinates and the rotation
predictor that moves them along the equilibrium branch."""

from __future__ import annotations

import math

import numpy as np
import torch

from .equilibrium import Equilibrium
from .kernel import KERNELS
from .mechanics import expand_q
from .options import SolverOptions
from .sections import n_coordinates

__all__ = ["PREDICTOR_TRUST", "initial_q", "rotation_predictor"]


def initial_q(initial, B: int, N: int):
    """Warm-start coordinates ``(B, nq)`` (or None) and the basis order and Magnus count they
    came from (None when unknown)."""
    if initial is None:
        return None, None, None
    q = initial.q if isinstance(initial, Equilibrium) else torch.as_tensor(initial)
    if q.ndim == 1:
        q = q[None]
    if not (q.is_floating_point() and (np.isfinite(q.detach().numpy()).all()
                                       if q.device.type == "cpu" and q.dtype != torch.bfloat16
                                       else bool(torch.isfinite(q).all()))):
        raise ValueError("initial: the warm-start coordinates must be finite floating-point "
                         "numbers (an Equilibrium or a (B, nq) tensor)")
    if q.shape[0] not in (1, B):
        raise ValueError(f"initial has batch size {q.shape[0]}, expected 1 or {B}")
    n_from = (q.shape[-1] - N) // (2 * N * (2 + N))
    order = n_from - 1 if n_coordinates(N, n_from) == q.shape[-1] and n_from >= 1 else None
    magnus = (initial.context.discretization.n_magnus if isinstance(initial, Equilibrium)
              else None)
    q = q.detach()
    return (q if q.shape[0] == B else q.expand(B, -1)), order, magnus


# Largest predicted change of a strain coordinate x the robot's length [rad] that the rotation
# predictor may make; beyond it (near a fold, or after a large step) the warm start is used as
# it is, and Newton's damping and line search take over.
PREDICTOR_TRUST = 0.1


def rotation_predictor(initial, q_init, scene, tubes, D, A, F, M, opts: SolverOptions):
    """The warm start moved along the equilibrium branch to the new base rotations: a first-
    order (Euler) predictor ``dq = -H^-1 U_q,alpha dalpha`` from the warm-start equilibrium's
    own Hessian, for a call that changes only rotations (same robot, insertions and batch, no
    tip load). The potential depends on ``alpha_j`` and the guide twist ``w_j`` only through
    ``alpha_j + D_j w_j`` plus the guide's ``1/2 GJ_j D_j w_j^2``, so ``U_q,alpha_j =
    (H[:, w_j] - GJ_j D_j e_wj) / D_j`` and the predictor is ``dw = -dalpha / D`` plus
    ``H^-1 (GJ dalpha)`` on the guide twists: one factorization, no derivative evaluation.
    Its error is ``O(dalpha^2)``, so Newton starts closer (a warm 1 deg step: one iteration
    fewer). Elements whose base sits at the orifice (no guide twist), whose Hessian is not
    positive definite, or whose predicted step exceeds :data:`PREDICTOR_TRUST` keep the warm
    start as it is. It changes where Newton starts, not what it converges to."""
    if not isinstance(initial, Equilibrium) or q_init is None:
        return q_init
    ctx = initial.context
    if ctx is None:
        return q_init
    info = ctx.implicit
    Hc = info.Hc
    B, N = D.shape
    if (Hc is None or Hc.shape[0] != B or info.with_load or opts.load_coordinates
            or ctx.scene.tubes != scene.tubes or ctx.insertion.shape != D.shape
            or bool((F != 0).any() | (M != 0).any()) or not torch.equal(ctx.insertion, D)):
        return q_init
    qmask_c, cidx = info.qmask_c, info.cidx
    dA = A - ctx.rotation.to(A.dtype)
    dA = dA - (2 * math.pi) * torch.round(dA / (2 * math.pi))
    rhs = torch.zeros_like(qmask_c)
    rhs[:, :N] = tubes.GJ.expand(B, N) * dA
    x, solved = KERNELS[opts.kernel].spd_solve(Hc, rhs)
    x[:, :N] -= dA / torch.where(D > 0, D, torch.ones_like(D))
    dq = expand_q(x * qmask_c, cidx, q_init.shape[-1])
    length = float(tubes.length.max())
    ok = (solved & (qmask_c[:, :N] > 0).all(-1) & torch.isfinite(dq).all(-1)
          & (dq.abs().amax(-1) * length < PREDICTOR_TRUST))
    return torch.where(ok[:, None], q_init + dq, q_init)
