"""A search of a goal's whole solution set for the fastest plan, and plan-then-servo with it.

Plan-then-servo (:class:`training.controllers.PlanThenServoController`) plans with a few IK
starts per goal. :func:`best_plans` searches the solution set of each goal instead: the
relative rotations of tubes 2..N to tube 1 are put on a grid (``theta_step`` degrees), the
insertions are solved for the goal's radius and height by Gauss-Newton (least norm for N > 2)
from ``starts`` fractions of each insertion's stroke, and the common rotation turns the tip onto
the goal's azimuth in closed form (a rotation of every tube turns the tip exactly about z). Of
the stable solutions within 0.02 mm whose relative rotations stay off +-180 deg by the
controller's margin, the one with the least loaded travel time
(:func:`training.controllers.travel_time`) is the goal's best plan. :class:`BestPlanServo` is
plan-then-servo with its slow plans replaced by those. ``benchmarks/reach_ceiling.py`` measures
what they are worth on the evaluation goals (docs/results.md).
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import torch

from envs.robots import solve_batch
from training.controllers import (
    PlanThenServoController,
    read_state,
    safe_rotation_target,
    tip_jacobian,
    travel_time,
)

__all__ = ["best_plans", "BestPlanServo"]


def best_plans(robot, x0, g0, goal, scale, damping, h, *, theta_step=10.0, starts=2, iters=15,
               margin=None):
    """Search the solution set of each goal ``(G, 3)`` [m] for the least loaded travel time
    from ``x0 (G, 2N)`` (loads ``g0``). Returns ``(x (G, 2N), g (G, 2N), steps (G,))``: the best
    plan found, its elastic load and its travel time in control periods (``inf`` where no
    solution was found). ``margin`` [rad]: relative rotations must end this far from
    +-180 deg (default the controller's 20 deg)."""
    N, G = robot.n_tubes, len(goal)
    margin = math.radians(20.0) if margin is None else margin
    grid = np.radians(np.arange(-180.0, 180.0, theta_step))
    thetas = np.array(list(itertools.product(grid, repeat=N - 1)))          # (T, N-1)
    fracs = np.array(list(itertools.product(np.linspace(0.1, 0.9, starts), repeat=N)))
    T, K = len(thetas), len(fracs)
    gi = np.repeat(np.arange(G), T * K)
    th = np.tile(np.repeat(thetas, K, 0), (G, 1))                          # (M, N-1)
    fr = np.tile(fracs, (G * T, 1))                                         # (M, N)
    D = np.zeros((len(gi), N))
    prev = np.zeros(len(gi))
    for j in range(N):                    # the stroke fractions through the box map
        lo, hi = robot.bounds(prev, j)
        D[:, j] = prev = lo + fr[:, j] * (hi - lo)
    rg = np.hypot(goal[gi, 0], goal[gi, 1])
    zg = goal[gi, 2]
    alpha = np.concatenate([np.zeros((len(gi), 1)), th], -1)
    for _ in range(iters):
        tip, J = tip_jacobian(robot, np.concatenate([D, alpha], -1))
        r = np.maximum(np.hypot(tip[:, 0], tip[:, 1]), 1e-9)
        dr = (tip[:, :1] * J[:, 0, :N] + tip[:, 1:2] * J[:, 1, :N]) / r[:, None]
        Jr = np.stack([dr, J[:, 2, :N]], 1)                                 # d(r, z)/dD
        res = np.stack([rg - r, zg - tip[:, 2]], -1)
        # least-norm Gauss-Newton step, lightly damped, at most 10 mm per insertion
        A = Jr @ Jr.transpose(0, 2, 1) + 1e-9 * np.eye(2)
        step = np.einsum("bij,bi->bj", Jr, np.linalg.solve(A, res[..., None])[..., 0])
        step /= np.maximum(1.0, np.abs(step).max(-1) / 10e-3)[:, None]
        D = robot.project(D + step)[0]
    x = np.concatenate([D, alpha], -1)
    eq = solve_batch(robot, x)
    tip = eq.tip_position.numpy()
    ok = ((np.hypot(np.hypot(tip[:, 0], tip[:, 1]) - rg, tip[:, 2] - zg) < 2e-5)
          & eq.stable.numpy() & eq.converged.numpy())
    x[:, N:] += (np.arctan2(goal[gi, 1], goal[gi, 0]) - np.arctan2(tip[:, 1], tip[:, 0]))[:, None]
    x[:, N:] = safe_rotation_target(x0[gi, N:], x[:, N:])
    j, k = np.triu_indices(N, 1)
    rel = np.angle(np.exp(1j * (x[:, N + k] - x[:, N + j])))             # wrapped
    ok &= (np.abs(rel) < np.pi - margin).all(-1)
    g1 = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
    steps = np.where(ok, travel_time(x0[gi], x, g0[gi], g1, scale, damping) / h, np.inf)
    best = np.array([np.flatnonzero(gi == i)[np.argmin(steps[gi == i])] for i in range(G)])
    return x[best], g1[best], steps[best]


class BestPlanServo:
    """Plan-then-servo whose slow plans (more than ``threshold`` periods) are replaced by the
    best plan of :func:`best_plans` where that is faster. Records both travel times per goal."""

    def __init__(self, venv, threshold: float, **search):
        self.pts, self.venv, self.threshold, self.search = (
            PlanThenServoController(venv), venv, threshold, search)
        self.plan_steps: list[np.ndarray] = []
        self.best_steps: list[np.ndarray] = []
        self.search_s = 0.0
        self.goal = np.full((venv.num_envs, 3), np.nan)

    def __call__(self, obs):
        st, p = read_state(self.venv), self.pts
        new = np.flatnonzero(np.any(st.goal != self.goal, -1))    # as p.replan sees them
        self.goal = st.goal.copy()
        p.replan(st)
        if len(new):
            h = st.control_period
            steps = travel_time(st.x, p.target, st.g, p.g_target, st.action_scale,
                                st.damping)[new] / h
            best = steps.copy()
            slow = np.flatnonzero(steps > self.threshold)
            if len(slow):
                t0 = time.perf_counter()
                i = new[slow]
                x, g, s = best_plans(p.robot, st.x[i], st.g[i], st.goal[i], st.action_scale,
                                     st.damping, h, margin=p.rotation_margin,
                                     **self.search)
                self.search_s += time.perf_counter() - t0
                faster = s < steps[slow]
                p.target[i[faster]], p.g_target[i[faster]] = x[faster], g[faster]
                best[slow] = np.minimum(s, steps[slow])
            self.plan_steps.append(steps)
            self.best_steps.append(best)
        return p(obs)
