"""How close is plan-then-servo to the best any controller can reach on the evaluation goals?

The reaching task gives a policy 100 control periods, and every carriage has a top speed: at
full actuation a carriage with ``b xdot = tau - g`` moves at ``(scale - sign(dx) g) / b``. A goal
can only be reached in time if some stable actuation that puts the tip on it lies within that
travel time of the start. Plan-then-servo (``training.controllers``) plans with a few IK starts
per goal; this script searches the whole solution set of the goals whose plan is slow and
measures what the best plan found is worth.

For each evaluation goal (the seeds of ``training.evaluate``) whose plan-then-servo plan needs
more than ``--threshold`` periods (:func:`training.controllers.travel_time`, with the elastic
load): the relative rotations of tubes 2..N to tube 1 are put on a grid (``--theta-step``
degrees), the insertions are solved for the goal's radius and height by Gauss-Newton (least
norm for N > 2) from ``--starts`` fractions of each insertion's stroke, and the common rotation
turns the tip onto the goal's azimuth in closed form (a rotation of every tube turns the tip
exactly about z). Of the stable solutions within 0.02 mm whose relative rotations stay off
+-180 deg by the controller's margin, the one with the least loaded travel time is the goal's
best plan. Prints:

* the count of goals by travel time of their best plan: a solution set searched this finely
  bounds from below how many goals no plan reaches in time (a solution the grid missed could
  still be faster, and the mean-load travel time is an estimate);
* success at 1 mm of plan-then-servo as it is and with the best plans, on the same goals
  (``rollout``), and the goals each wins that the other misses.

Usage::

    python benchmarks/reach_ceiling.py [--robot fig3_two_tube] [--episodes 500] [--batch 50]
        [--theta-step 10] [--starts 2] [--iters 15] [--threshold 85] [--json FILE]

About 3.5 min for the default fig3 run on one core (the finer ``--theta-step 5 --starts 3
--iters 25``: 7.5 min).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time

import numpy as np
import torch


def best_plans(robot, x0, g0, goal, scale, damping, h, *, theta_step=10.0, starts=2, iters=15,
               margin=None):
    """Search the solution set of each goal ``(G, 3)`` [m] for the least loaded travel time
    from ``x0 (G, 2N)`` (loads ``g0``). Returns ``(x (G, 2N), g (G, 2N), steps (G,))``: the best
    plan found, its elastic load and its travel time in control periods (``inf`` where no
    solution was found). ``margin`` [rad]: relative rotations must end this far from
    +-180 deg (default the controller's 20 deg)."""
    from envs.robots import solve_batch
    from training.controllers import safe_rotation_target, tip_jacobian, travel_time

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
        from training.controllers import PlanThenServoController
        self.pts, self.venv, self.threshold, self.search = (
            PlanThenServoController(venv), venv, threshold, search)
        self.plan_steps: list[np.ndarray] = []
        self.best_steps: list[np.ndarray] = []
        self.search_s = 0.0
        self.goal = np.full((venv.num_envs, 3), np.nan)

    def __call__(self, obs):
        from training.controllers import read_state, travel_time
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--robot", default="fig3_two_tube")
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--theta-step", type=float, default=10.0, help="[deg] relative-rotation grid")
    p.add_argument("--starts", type=int, default=2, help="stroke fractions per insertion")
    p.add_argument("--iters", type=int, default=15, help="Gauss-Newton iterations")
    p.add_argument("--threshold", type=float, default=85.0,
                   help="[control periods] plans slower than this are searched")
    p.add_argument("--json", help="write the per-goal figures here")
    a = p.parse_args(argv)
    torch.set_num_threads(1)

    import envs
    from training.controllers import PlanThenServoController
    from training.evaluate import rollout

    venv = envs.CTRReachVecEnv(a.batch, robot=a.robot, control="force")
    T = venv.max_episode_steps
    t0 = time.perf_counter()
    base = rollout(PlanThenServoController(venv), venv, a.episodes, seed=a.seed,
                   progress=False)["final_error"]
    t_base = time.perf_counter() - t0
    pol = BestPlanServo(venv, a.threshold, theta_step=a.theta_step, starts=a.starts,
                        iters=a.iters)
    t0 = time.perf_counter()
    best = rollout(pol, venv, a.episodes, seed=a.seed, progress=False)["final_error"]
    t_best = time.perf_counter() - t0
    plan = np.concatenate(pol.plan_steps)[:a.episodes]
    bound = np.concatenate(pol.best_steps)[:a.episodes]
    hit0, hit1 = base <= 1e-3, best <= 1e-3
    print(f"{a.robot}, {a.episodes} evaluation goals (seed {a.seed}), {T} periods per episode; "
          f"searched: {int((plan > a.threshold).sum())} goals whose plan needs > "
          f"{a.threshold:g} periods (grid {a.theta_step:g} deg, {a.starts} starts per "
          f"insertion, {a.iters} iterations; {pol.search_s:.0f} s)")
    for lim in (T - 5, T):
        print(f"  goals whose plan needs > {lim} periods: plan-then-servo's "
              f"{int((plan > lim).sum())}, best plan found {int((bound > lim).sum())}")
    print(f"  success at 1 mm: plan-then-servo {hit0.mean():.3f} ({t_base:.0f} s), with the best "
          f"plans {hit1.mean():.3f} ({t_best:.0f} s); goals only the first reaches "
          f"{int((hit0 & ~hit1).sum())}, only the second {int((hit1 & ~hit0).sum())}")
    print(f"  upper estimate of what a plan-and-servo controller can reach: "
          f"{(bound <= T).mean():.3f} (best plan within {T} periods), "
          f"{(bound <= T - 5).mean():.3f} (within {T - 5})")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"args": vars(a), "plan_steps": plan.tolist(), "best_steps": bound.tolist(),
                       "final_error_pts": base.tolist(), "final_error_best": best.tolist()}, f)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
