"""Where a policy's episodes take the relative rotation stiffness ``k_rel``: the numbers behind
``ReachConfig.stiffness_hazard``.

    python benchmarks/stiffness_hazard.py --policy training/policies/tqc_force.zip \
        [--episodes 300] [--seed 20000] [--batch 50]

Runs the policy greedily on the episodes of ``python -m training.evaluate`` with the same
seed and batch (the same starts and goals) and records, after every step, ``k_rel / s``:
:func:`envs.task.relative_rotation_stiffness` of the unclipped actuator stiffness in units
of the robot's :func:`envs.task.stiffness_scale` ``s``. Printed: how many successful episodes
END below a few thresholds (such a goal is held by feedback in a torque-unstable state, so a
penalty at that threshold taxes holding it at every remaining step), the minimum ``k_rel / s``
before each snap, and quantiles of the minimum over the episodes without a snap. A threshold
below the successes' final states and above the snaps' minima penalizes the approach to a
snap without taxing the goals.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    import torch

    from envs.task import relative_rotation_stiffness
    from training.evaluate import load_policy, policy_env

    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", required=True)
    p.add_argument("--episodes", type=int, default=300)
    p.add_argument("--seed", type=int, default=20000)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    # observe_stiffness makes the env compute the unclipped stiffness K_unclipped each step
    venv, _ = policy_env(args.policy, args.batch)
    policy = load_policy(args.policy, venv)
    scale = venv.task.stiffness_scale
    B, T = venv.num_envs, venv.max_episode_steps
    final_d, snapped, k_final, k_min = [], [], [], []
    for b in range(-(-args.episodes // B)):
        venv.seed(args.seed + b * B)
        obs = venv.reset()
        venv.elapsed[:] = 0
        alive = np.ones(B, dtype=bool)
        snap = np.zeros(B, dtype=bool)
        d = np.zeros(B)
        k_last = np.zeros(B)
        k_lo = np.full(B, np.inf)
        for _ in range(T):
            obs, _, dones, infos = venv.step(policy(obs))
            k = relative_rotation_stiffness(venv.task.robots.K_unclipped) / scale
            # an episode that ended (snap) keeps its values from its last step
            k_last = np.where(alive, k, k_last)
            k_lo = np.where(alive, np.minimum(k_lo, k), k_lo)
            d = np.where(alive, [i["distance"] for i in infos], d)
            snap |= alive & np.array([i["snap_terminated"] for i in infos])
            alive &= ~dones
        final_d.append(d)
        snapped.append(snap)
        k_final.append(k_last)
        k_min.append(k_lo)
    n = args.episodes
    d, snap = np.concatenate(final_d)[:n], np.concatenate(snapped)[:n]
    kf, km = np.concatenate(k_final)[:n], np.concatenate(k_min)[:n]
    ok = (d <= 1e-3) & ~snap
    print(f"{args.policy}: {n} episodes from seed {args.seed}: success within 1 mm "
          f"{ok.mean():.3f}, snaps {snap.sum()} ({snap.mean():.1%}); stiffness_scale "
          f"{scale:.4f} N·m/rad")
    for h in (-0.01, -0.3, -1.0, -2.5):
        print(f"  successes ending with k_rel / s < {h:6.2f}: {(kf[ok] < h).mean():.3f}   "
              f"episodes ever below: {(km < h).mean():.3f}")
    print("  final k_rel / s of the successes, quantiles 1/5/10/50 %:",
          np.round(np.quantile(kf[ok], [0.01, 0.05, 0.1, 0.5]), 3) if ok.any() else "-")
    print("  minimum k_rel / s before each snap:", np.round(np.sort(km[snap]), 2))
    print("  minimum k_rel / s of the episodes without a snap, quantiles 1/5/10/50 %:",
          np.round(np.quantile(km[~snap], [0.01, 0.05, 0.1, 0.5]), 3))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
