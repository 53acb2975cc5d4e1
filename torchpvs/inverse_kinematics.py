"""Inverse kinematics: actuations ``(D, alpha)`` whose stable equilibrium puts the tip at a goal.

:func:`inverse_kinematics` runs a batched, multi-start Levenberg–Marquardt on the tip position
over the actuator coordinates ``x = (D, alpha)``. Each iteration is one warm-started batched
solve at the trial actuations and, for the elements that accept it, the tip Jacobian
``d tip / dx`` through the implicit backward (three reverse passes sharing one factorization).
A trial that does not reduce the tip error is rejected and the damping raised. Steps are capped,
and insertions are projected onto their rules: ``0 <= D_1 <= D_2 <= ...`` with every tube at least
``min_exposed`` beyond the orifice.

Starts for each goal: the initial actuation, the same actuation turned about the axis so that the
tip azimuth matches the goal's (a common rotation of every tube turns the tip exactly about z),
and seeded random actuations. A start counts as a solution when its equilibrium is converged,
stable and within ``tol`` of the goal; of the solutions, the one with the least actuator travel
from the initial actuation is returned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .scene import Scene, load_scene
from .solver import SolverOptions, solve

__all__ = ["IKResult", "inverse_kinematics"]


@dataclass(frozen=True)
class IKResult:
    """Per goal ``(G, ...)``: ``insertion``/``rotation`` ``(G, N)`` [m], [rad]; ``tip`` ``(G, 3)``
    [m] at that actuation; ``error`` ``(G,)`` [m] to the goal; ``solved`` ``(G,)`` converged,
    stable and within ``tol``; ``travel`` ``(G,)`` ``sum |dD| + travel_scale sum |dalpha|`` from
    the initial actuation [m]; ``starts_solved`` ``(G,)`` how many starts reached the goal."""

    insertion: torch.Tensor
    rotation: torch.Tensor
    tip: torch.Tensor
    error: torch.Tensor
    solved: torch.Tensor
    travel: torch.Tensor
    starts_solved: torch.Tensor


def inverse_kinematics(scene: Scene | str, goal, *, starts: int = 8, tol: float = 1e-4,
                       max_iter: int = 60, initial_insertion=None, initial_rotation=None,
                       min_exposed: float = 5e-3, max_step: tuple[float, float] = (5e-3, 0.3),
                       travel_scale: float = 0.05, seed: int = 0,
                       options: SolverOptions | None = None) -> IKResult:
    """Stable actuations that put the tip at ``goal`` ``(3,)`` or ``(G, 3)`` [m] (base frame).

    Args:
        scene: the robot; its actuation is the default initial actuation.
        starts: starts per goal (>= 1): the initial actuation, the same actuation turned to the
            goal's azimuth, and ``starts - 2`` seeded random actuations.
        tol: [m] the tip must end this close to the goal.
        max_iter: Levenberg–Marquardt iterations (each one batched solve).
        initial_insertion, initial_rotation: ``(N,)`` or ``(G, N)``; default the scene's.
        min_exposed: [m] every tube keeps at least this much beyond the orifice.
        max_step: the largest insertion [m] and rotation [rad] change per iteration.
        travel_scale: [m/rad] weight of rotations against insertions, in the step's metric and
            in the travel that ranks solutions.
        seed: seed of the random starts.
        options: solver options of the equilibria (default ``order=2, n_magnus=8``, no forces).
    """
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    if not (isinstance(starts, int) and starts >= 1):
        raise ValueError(f"starts must be an integer >= 1, got {starts!r}")
    if not (isinstance(tol, (int, float)) and tol > 0 and math.isfinite(tol)):
        raise ValueError(f"tol must be a positive length [m], got {tol!r}")
    dt = torch.float64
    goal = torch.as_tensor(goal, dtype=dt)
    goal = goal[None] if goal.ndim == 1 else goal
    if goal.ndim != 2 or goal.shape[-1] != 3 or not bool(torch.isfinite(goal).all()):
        raise ValueError(f"goal must be finite with shape (3,) or (G, 3), got "
                         f"{tuple(goal.shape)}")
    G, N, K = goal.shape[0], scene.n_tubes, starts
    opts = options or SolverOptions(order=2, n_magnus=8, compute_forces=False,
                                    on_failure="ignore")
    D_max = torch.tensor([t.length for t in scene.tubes], dtype=dt) - min_exposed
    if bool((D_max < 0).any()):
        raise ValueError(f"min_exposed ({min_exposed} m) exceeds a tube's length")

    def rows(x, name):
        t = torch.as_tensor(x if x is not None else getattr(scene.actuation, name), dtype=dt)
        return (t[None] if t.ndim == 1 else t).expand(G, N)

    D0 = _project(rows(initial_insertion, "insertion"), D_max)
    A0 = rows(initial_rotation, "rotation")
    D = D0[:, None].repeat(1, K, 1)
    A = A0[:, None].repeat(1, K, 1)
    if K > 1:
        tip0 = solve(scene, insertion=D0, rotation=A0, options=opts).tip_position
        turn = torch.atan2(goal[:, 1], goal[:, 0]) - torch.atan2(tip0[:, 1], tip0[:, 0])
        A[:, 1] = A0 + turn[:, None]
    if K > 2:
        gen = torch.Generator().manual_seed(seed)
        u = torch.rand(G, K - 2, N, generator=gen, dtype=dt)
        D[:, 2:] = _project(torch.cummax(u * D_max, -1).values, D_max)
        A[:, 2:] = (torch.rand(G, K - 2, N, generator=gen, dtype=dt) * 2 - 1) * math.pi
    B = G * K
    D, A = D.reshape(B, N), A.reshape(B, N)
    target = goal[:, None].expand(G, K, 3).reshape(B, 3)
    s = torch.cat([torch.ones(N, dtype=dt), torch.full((N,), travel_scale, dtype=dt)])
    lam = torch.full((B,), 1e-3, dtype=dt)
    q = None
    err = torch.full((B,), math.inf, dtype=dt)
    J = torch.zeros(B, 3, 2 * N, dtype=dt)
    r = torch.zeros(B, 3, dtype=dt)
    xD, xA = D, A                                       # accepted actuations
    for _ in range(max_iter + 1):
        # Solve at the trial actuations (with the tip Jacobian on the way).
        Dg, Ag = D.clone().requires_grad_(True), A.clone().requires_grad_(True)
        eq = solve(scene, insertion=Dg, rotation=Ag, options=opts, initial=q)
        p = eq.tip_position
        r_new = target - p.detach()
        e_new = r_new.norm(dim=-1)
        ok = eq.converged & (e_new < err)                # accept: the error fell
        J_new = torch.stack([torch.cat(torch.autograd.grad(p[:, i].sum(), (Dg, Ag),
                                                           retain_graph=i < 2), -1)
                             for i in range(3)], 1)
        keep = ok[:, None]
        xD, xA = torch.where(keep, D, xD), torch.where(keep, A, xA)
        r = torch.where(keep, r_new, r)
        J = torch.where(keep[..., None], J_new, J)
        err = torch.where(ok, e_new, err)
        lam = torch.where(ok, lam / 3, lam * 4).clamp(1e-12, 1e6)
        q = eq.q.detach()
        if bool((err < tol).all()):
            break
        # Levenberg–Marquardt step from the accepted point, in metres (rotations x travel_scale).
        Js = J * s
        JJ = Js @ Js.transpose(1, 2)
        JJ = JJ + lam[:, None, None] * JJ.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] \
            * torch.eye(3, dtype=dt) + 1e-18 * torch.eye(3, dtype=dt)
        step = s * (Js.transpose(1, 2) @ torch.linalg.solve(JJ, r[..., None]))[..., 0]
        dD, dA = step[:, :N], step[:, N:]
        cap = torch.maximum(dD.abs().amax(-1) / max_step[0],
                            dA.abs().amax(-1) / max_step[1]).clamp(min=1.0)
        done = (err < tol)[:, None]
        D = torch.where(done, xD, _project(xD + dD / cap[:, None], D_max))
        A = torch.where(done, xA, xA + dA / cap[:, None])
    final = solve(scene, insertion=xD, rotation=xA, options=opts)
    err = (target - final.tip_position).norm(dim=-1)
    ok = (err < tol) & final.converged & final.stable
    travel = ((xD.reshape(G, K, N) - D0[:, None]).abs().sum(-1)
              + travel_scale * (xA.reshape(G, K, N) - A0[:, None]).abs().sum(-1))
    score = torch.where(ok.reshape(G, K), travel, 1e6 * (1 + err.reshape(G, K)))
    best = score.argmin(-1)
    idx = torch.arange(G) * K + best
    return IKResult(insertion=xD[idx], rotation=xA[idx], tip=final.tip_position[idx],
                    error=err[idx], solved=ok[idx], travel=travel[torch.arange(G), best],
                    starts_solved=ok.reshape(G, K).sum(-1))


def _project(D: torch.Tensor, D_max: torch.Tensor) -> torch.Tensor:
    """Insertions onto ``0 <= D_1 <= D_2 <= ...`` and ``D_j <= D_max_j``."""
    D = torch.minimum(D.clamp(min=0.0), D_max)
    return torch.minimum(torch.cummax(D, -1).values, D_max)
