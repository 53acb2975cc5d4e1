"""How close is plan-then-servo to the best any controller can reach on the evaluation goals?

The reaching task gives a policy 100 control periods, and every carriage has a top speed: at
full actuation a carriage with ``b xdot = tau - g`` moves at ``(scale - sign(dx) g) / b``. A goal
can only be reached in time if some stable actuation that puts the tip on it lies within that
travel time of the start. Plan-then-servo (``training.controllers``) plans with a few IK starts
per goal; this script searches the whole solution set of the goals whose plan is slow and
measures what the best plan found is worth.

For each evaluation goal (the seeds of ``training.evaluate``) whose plan-then-servo plan needs
more than ``--threshold`` periods (:func:`training.controllers.travel_time`, with the elastic
load), the search of :mod:`training.plan_search`: the relative rotations of tubes 2..N to tube
1 are put on a grid (``--theta-step`` degrees), the insertions are solved for the goal's radius
and height by Gauss-Newton (least norm for N > 2) from ``--starts`` fractions of each
insertion's stroke, and the common rotation turns the tip onto the goal's azimuth in closed
form (a rotation of every tube turns the tip exactly about z). Of the stable solutions within
0.02 mm whose relative rotations stay off +-180 deg by the controller's margin, the one with
the least loaded travel time is the goal's best plan. Prints:

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
import json
import time

import numpy as np
import torch

from training.plan_search import BestPlanServo


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
