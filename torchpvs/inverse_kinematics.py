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
and seeded random actuations. A start that stalls (its error has not fallen by 10 % in
``_PATIENCE`` iterations while still beyond ``tol``) is replaced by a fresh seeded random start of
the same goal, up to ``restarts`` times per goal; its best point is kept. Which start of a goal
succeeds is sensitive to rounding (a step lands on one branch or another), so the restarts are
what makes a reachable goal's success not hinge on one trajectory. A start counts as a solution
when its equilibrium is converged, stable and within ``tol`` of the goal; of the solutions, the
one with the least actuator travel from the initial actuation is returned.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import torch

from .clock import work_clock
from .inputs import check_actuation
from .jacobians import tip_jacobian
from .options import SolverOptions, check_time_limit, within_deadline
from .scene import Scene, load_scene
from .solver import solve

__all__ = ["IKResult", "inverse_kinematics"]

# A start is replaced after this many iterations without a 10 % fall of its error; restarts
# stop this many iterations before max_iter (a random start needs them to converge).
_PATIENCE = 8


@dataclass(frozen=True)
class IKResult:
    """Per goal ``(G, ...)``: ``insertion``/``rotation`` ``(G, N)`` [m], [rad]; ``tip`` ``(G, 3)``
    [m] at that actuation; ``error`` ``(G,)`` [m] to the goal; ``solved`` ``(G,)`` converged,
    stable and within ``tol``; ``travel`` ``(G,)`` ``sum |dD| + travel_scale sum |dalpha|`` from
    the initial actuation [m]; ``starts_solved`` ``(G,)`` how many starts reached the goal;
    ``timed_out`` whether ``time_limit`` stopped the iterations (the best actuations found by
    then are returned, ``solved`` says which meet ``tol``)."""

    insertion: torch.Tensor
    rotation: torch.Tensor
    tip: torch.Tensor
    error: torch.Tensor
    solved: torch.Tensor
    travel: torch.Tensor
    starts_solved: torch.Tensor
    timed_out: bool = False


def inverse_kinematics(scene: Scene | str, goal, *, starts: int = 8, tol: float = 1e-4,
                       max_iter: int = 60, initial_insertion=None, initial_rotation=None,
                       min_exposed: float = 5e-3, max_step: tuple[float, float] = (5e-3, 0.3),
                       travel_scale: float = 0.05, seed: int = 0, restarts: int | None = None,
                       options: SolverOptions | None = None,
                       time_limit: float | None = 120.0) -> IKResult:
    """Stable actuations that put the tip at ``goal`` ``(3,)`` or ``(G, 3)`` [m] (base frame).

    Args:
        scene: the robot; its actuation is the default initial actuation.
        starts: starts per goal (>= 1): the initial actuation, the same actuation turned to the
            goal's azimuth, and ``starts - 2`` seeded random actuations.
        tol: [m] the tip must end this close to the goal.
        max_iter: Levenberg–Marquardt iterations (each one batched solve).
        initial_insertion, initial_rotation: ``(N,)`` or ``(G, N)``; default the scene's. The
            insertions must obey the rules of :func:`torchpvs.solve` (``0 <= D_1 <= D_2 <=
            ...``); one deeper than ``length - min_exposed`` starts on that bound.
        min_exposed: [m] (>= 0) every tube keeps at least this much beyond the orifice.
        max_step: the largest insertion [m] and rotation [rad] change per iteration.
        travel_scale: [m/rad] weight of rotations against insertions, in the step's metric and
            in the travel that ranks solutions.
        seed: seed of the random starts. Each goal's starts are drawn from ``seed`` and the
            values of its own row (goal, initial actuation), so a goal gets the same answer
            wherever it sits in the batch.
        restarts: fresh seeded random starts per goal for starts that stall (default
            ``starts``; 0: none).
        options: solver options of the equilibria (default ``order=2, n_magnus=8``, no forces).
            The solves run on ``options.device`` if set, else on the goal's device (a CUDA
            ``goal`` tensor solves on the GPU); the result's tensors are on that device.
        time_limit: [s] wall-clock bound on the whole call (default 120 s; ``None``: none):
            checked before every iteration, and every solve is bounded by what is left.
    """
    t_start = work_clock()
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    check_time_limit(time_limit)
    if not (isinstance(starts, int) and starts >= 1):
        raise ValueError(f"starts must be an integer >= 1, got {starts!r}")
    if not (isinstance(tol, (int, float)) and tol > 0 and math.isfinite(tol)):
        raise ValueError(f"tol must be a positive length [m], got {tol!r}")
    if not (isinstance(max_iter, int) and not isinstance(max_iter, bool) and max_iter >= 0):
        raise ValueError(f"max_iter must be an integer >= 0, got {max_iter!r}")
    if not (isinstance(min_exposed, (int, float)) and math.isfinite(min_exposed)
            and min_exposed >= 0):
        # A negative value would let a tube's base pass the orifice (D_j > length_j).
        raise ValueError(f"min_exposed must be a length >= 0 [m] (what every tube keeps beyond "
                         f"the orifice), got {min_exposed!r}")
    if not (isinstance(max_step, (tuple, list)) and len(max_step) == 2
            and all(isinstance(v, (int, float)) and v > 0 and math.isfinite(v)
                    for v in max_step)):
        raise ValueError(f"max_step must be (insertion [m] > 0, rotation [rad] > 0), got "
                         f"{max_step!r}")
    if not (isinstance(travel_scale, (int, float)) and travel_scale > 0
            and math.isfinite(travel_scale)):
        raise ValueError(f"travel_scale must be a positive number [m/rad], got "
                         f"{travel_scale!r}")
    if not (isinstance(seed, int) and not isinstance(seed, bool)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    restarts = starts if restarts is None else restarts
    if not (isinstance(restarts, int) and not isinstance(restarts, bool) and restarts >= 0):
        raise ValueError(f"restarts must be an integer >= 0, got {restarts!r}")
    dt = torch.float64
    # The device: the options' if set, else the goal's (a CUDA goal solves on CUDA).
    dev = torch.device(options.device) if options is not None and options.device is not None \
        else (goal.device if isinstance(goal, torch.Tensor) else torch.device("cpu"))
    goal = torch.as_tensor(goal, dtype=dt, device=dev)
    goal = goal[None] if goal.ndim == 1 else goal
    if goal.ndim != 2 or goal.shape[-1] != 3 or not bool(torch.isfinite(goal).all()):
        raise ValueError(f"goal must be finite with shape (3,) or (G, 3), got "
                         f"{tuple(goal.shape)}")
    if goal.shape[0] == 0:
        raise ValueError("goal must hold at least one goal: shape (3,) or (G, 3) with G >= 1, "
                         "got (0, 3)")
    G, N, K = goal.shape[0], scene.n_tubes, starts
    opts = options or SolverOptions(order=2, n_magnus=8, compute_forces=False,
                                    on_failure="ignore", device=dev)
    D_max = torch.tensor([t.length for t in scene.tubes], dtype=dt, device=dev) - min_exposed
    if bool((D_max < 0).any()):
        raise ValueError(f"min_exposed ({min_exposed} m) exceeds a tube's length")

    def rows(x, name, field):
        t = torch.as_tensor(x if x is not None else getattr(scene.actuation, name), dtype=dt,
                            device=dev)
        t = t[None] if t.ndim == 1 else t
        if t.ndim != 2 or t.shape[-1] != N or t.shape[0] not in (1, G):
            raise ValueError(f"{field} must have shape ({N},) or ({G}, {N}) (one row per "
                             f"goal), got {tuple(t.shape)}")
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{field} must be finite")
        return t.expand(G, N)

    D_init = rows(initial_insertion, "insertion", "initial_insertion")
    try:
        check_actuation(D_init, scene)    # the rules solve() applies (docs/conventions.md)
    except ValueError as err:
        rule = str(err).removeprefix("insertion: ")
        raise ValueError(f"initial_insertion: {rule}, got {D_init.tolist()}") from None
    # Within the rules, a start deeper than length - min_exposed is moved onto that bound.
    D0 = _project(D_init, D_max)
    A0 = rows(initial_rotation, "rotation", "initial_rotation")
    D = D0[:, None].repeat(1, K, 1)
    A = A0[:, None].repeat(1, K, 1)
    if K > 1:
        tip0 = solve(scene, insertion=D0, rotation=A0, options=opts).tip_position
        turn = torch.atan2(goal[:, 1], goal[:, 0]) - torch.atan2(tip0[:, 1], tip0[:, 0])
        A[:, 1] = A0 + turn[:, None]
    if K > 2:
        # The same seeded starts for every goal: a goal's answer must not depend on where it
        # sits in the batch (drawn per batch, goal g got rows g of a (G, K - 2, N) draw, so
        # [A] and [A, A] returned different actuations for A).
        u, a = _random_starts(seed, goal, D0, A0, K - 2)
        D[:, 2:] = _project(torch.cummax(u * D_max, -1).values, D_max)
        A[:, 2:] = (a * 2 - 1) * math.pi
    B = G * K
    D, A = D.reshape(B, N), A.reshape(B, N)
    if restarts:
        # the restart pool: seeded like the random starts, from another stream
        u, a = _random_starts(seed + 1, goal, D0, A0, restarts)
        pool_D = _project(torch.cummax(u * D_max, -1).values, D_max)
        pool_A = (a * 2 - 1) * math.pi
    used = [0] * G                                         # restarts drawn per goal
    stall = torch.zeros(B, dtype=torch.long, device=dev)   # iterations without a 10 % fall
    mark = torch.full((B,), math.inf, dtype=dt, device=dev)  # the error that last fell 10 %
    kD, kA = D.clone(), A.clone()                          # best point of a replaced start
    kerr = torch.full((B,), math.inf, dtype=dt, device=dev)
    target = goal[:, None].expand(G, K, 3).reshape(B, 3)
    s = torch.cat([torch.ones(N, dtype=dt, device=dev),
                   torch.full((N,), travel_scale, dtype=dt, device=dev)])
    lam = torch.full((B,), 1e-3, dtype=dt, device=dev)
    q = None
    err = torch.full((B,), math.inf, dtype=dt, device=dev)
    J = torch.zeros(B, 3, 2 * N, dtype=dt, device=dev)
    r = torch.zeros(B, 3, dtype=dt, device=dev)
    xD, xA = D, A                                       # accepted actuations
    deadline = None if time_limit is None else t_start + time_limit
    timed_out = False
    for it in range(max_iter + 1):
        if deadline is not None and work_clock() > deadline:
            timed_out = True
            break
        # Solve at the trial actuations.
        eq = solve(scene, insertion=D, rotation=A, options=within_deadline(opts, deadline),
                   initial=q)
        p = eq.tip_position
        r_new = target - p.detach()
        e_new = r_new.norm(dim=-1)
        ok = eq.converged & (e_new < err)                # accept: the error fell
        # closed form from the solve's own factorization (torchpvs.jacobians)
        J_new = tip_jacobian(eq)[:, :3]
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
            * torch.eye(3, dtype=dt, device=dev) + 1e-18 * torch.eye(3, dtype=dt, device=dev)
        step = s * (Js.transpose(1, 2) @ torch.linalg.solve(JJ, r[..., None]))[..., 0]
        dD, dA = step[:, :N], step[:, N:]
        cap = torch.maximum(dD.abs().amax(-1) / max_step[0],
                            dA.abs().amax(-1) / max_step[1]).clamp(min=1.0)
        done = (err < tol)[:, None]
        D = torch.where(done, xD, _project(xD + dD / cap[:, None], D_max))
        A = torch.where(done, xA, xA + dA / cap[:, None])
        fell = err < 0.9 * mark
        mark = torch.where(fell, err, mark)
        stall = torch.where(fell, 0, stall + 1)
        if restarts and it < max_iter - 2 * _PATIENCE:
            q = _restart(scene, opts, deadline, (stall >= _PATIENCE) & (err >= tol), K, used,
                         restarts, (pool_D, pool_A), (D, A, q),
                         (xD, xA, err, lam, mark, stall), (kD, kA, kerr))
    worse = kerr < err                                     # a replaced start did better before
    xD, xA = torch.where(worse[:, None], kD, xD), torch.where(worse[:, None], kA, xA)
    final = solve(scene, insertion=xD, rotation=xA,
                  options=within_deadline(opts, None if deadline is None
                                          else max(deadline, work_clock())
                                          + 0.1 * time_limit))
    err = (target - final.tip_position).norm(dim=-1)
    ok = (err < tol) & final.converged & final.stable
    travel = ((xD.reshape(G, K, N) - D0[:, None]).abs().sum(-1)
              + travel_scale * (xA.reshape(G, K, N) - A0[:, None]).abs().sum(-1))
    score = torch.where(ok.reshape(G, K), travel, 1e6 * (1 + err.reshape(G, K)))
    best = score.argmin(-1)
    goals = torch.arange(G, device=dev)
    idx = goals * K + best
    return IKResult(insertion=xD[idx], rotation=xA[idx], tip=final.tip_position[idx],
                    error=err[idx], solved=ok[idx], travel=travel[goals, best],
                    starts_solved=ok.reshape(G, K).sum(-1), timed_out=timed_out)


def _restart(scene, opts, deadline, stalled, K, used, restarts, pool, trial, state, kept):
    """Replace the ``stalled`` ``(B,)`` starts (rows ``g K + k`` of goal ``g``) by their goal's
    next pool start while the goal has one: in place on the trial actuations ``(D, A)``, the
    accepted state ``(xD, xA, err, lam, mark, stall)`` and the kept best ``(kD, kA, kerr)``.
    Returns the warm start for the next solve, with the replaced rows' coordinates from a cold
    solve at their new actuations (a stale warm start could land them on another branch)."""
    D, A, q = trial
    xD, xA, err, lam, mark, stall = state
    kD, kA, kerr = kept
    rows = []
    for r in stalled.nonzero().flatten().tolist():      # few rows: a loop keeps the pool order
        g = r // K
        if used[g] < restarts:
            rows.append((r, g, used[g]))
            used[g] += 1
    if not rows:
        return q
    r_idx = torch.tensor([r for r, _, _ in rows], device=err.device)
    better = err[r_idx] < kerr[r_idx]
    kD[r_idx] = torch.where(better[:, None], xD[r_idx], kD[r_idx])
    kA[r_idx] = torch.where(better[:, None], xA[r_idx], kA[r_idx])
    kerr[r_idx] = torch.minimum(err[r_idx], kerr[r_idx])
    g_idx = torch.tensor([g for _, g, _ in rows], device=err.device)
    p_idx = torch.tensor([p for _, _, p in rows], device=err.device)
    D[r_idx] = xD[r_idx] = pool[0][g_idx, p_idx]
    A[r_idx] = xA[r_idx] = pool[1][g_idx, p_idx]
    err[r_idx] = math.inf
    mark[r_idx] = math.inf
    lam[r_idx] = 1e-3
    stall[r_idx] = 0
    if q is not None:
        q = q.clone()
        for r in r_idx.tolist():
            # one row per solve: a batched solve rounds differently with the batch's
            # composition, and a goal's answer must not depend on its neighbours
            cold = solve(scene, insertion=D[r:r + 1], rotation=A[r:r + 1],
                         options=within_deadline(opts, deadline))
            q[r] = cold.q.detach()[0]
    return q


def _random_starts(seed: int, goal: torch.Tensor, D0: torch.Tensor, A0: torch.Tensor,
                   m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Uniform ``[0, 1)`` draws ``(G, m, N)`` for the insertions and rotations of the random
    starts. Goal ``g``'s draws come from a generator seeded with ``seed`` and the values of its
    own row (goal, initial insertion and rotation): equal rows get equal starts wherever they
    sit in the batch, and different rows (e.g. one goal from several initial actuations)
    independent ones."""
    G, N = D0.shape
    u = torch.empty(G, m, N, dtype=D0.dtype)
    a = torch.empty(G, m, N, dtype=D0.dtype)
    # (+ 0.0 turns -0.0 into 0.0: the same values give the same bytes)
    rows = (torch.cat([goal, D0, A0], -1) + 0.0).cpu().numpy()
    for g in range(G):
        digest = hashlib.blake2b(rows[g].tobytes(), digest_size=8,
                                 key=str(seed).encode()).digest()
        gen = torch.Generator().manual_seed(int.from_bytes(digest, "little") >> 1)
        u[g] = torch.rand(m, N, generator=gen, dtype=D0.dtype)
        a[g] = torch.rand(m, N, generator=gen, dtype=D0.dtype)
    # drawn on the CPU's generator on every device: the same starts wherever the solve runs
    return u.to(D0.device), a.to(D0.device)


def _project(D: torch.Tensor, D_max: torch.Tensor) -> torch.Tensor:
    """Insertions onto ``0 <= D_1 <= D_2 <= ...`` and ``D_j <= D_max_j``."""
    D = torch.minimum(D.clamp(min=0.0), D_max)
    return torch.minimum(torch.cummax(D, -1).values, D_max)
