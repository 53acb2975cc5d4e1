"""The ceiling of every registered reaching task: how many goals can be reached in time at all.

    python benchmarks/env_ceilings.py [--goals 500] [--seed 12345]

For each env id, ``envs.ceilings.travel_ceiling`` resets ``--goals`` seeded episodes (the
seeds of ``training.evaluate``: episode ``k`` seeded ``seed + k``) and counts the travel from
each start to the goal's sampled preimage in control periods at the actuators' largest step
per period (joint increments at action +-1, or the carriages' unloaded full-scale speeds).
Prints the share within the id's episode length and the median and 95th percentile of the
travel: an optimistic ceiling (unloaded speeds, rotations the short way even across +-180 deg;
``benchmarks/reach_ceiling.py`` searches the whole solution set with loaded speeds for the
force task) and a necessary condition only (a goal whose sampled preimage is out of reach may
have a nearer one).
"""

from __future__ import annotations

import argparse

import torch

import envs
from envs.ceilings import travel_ceiling


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--goals", type=int, default=500)
    ap.add_argument("--seed", type=int, default=12345)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    print("| env id | episode steps | goals' preimages within reach | travel median / p95 "
          "[steps] |")
    print("| --- | --- | --- | --- |")
    for env_id in envs.ENV_IDS:
        c = travel_ceiling(env_id, args.goals, args.seed)
        print(f"| `{env_id}` | {c.steps} | {c.within:.1%} | {c.median:.0f} / {c.p95:.0f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
