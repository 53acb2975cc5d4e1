"""Demonstrations from a controller, for :class:`training.callbacks.DemoCloning`.

A controller of ``training.controllers`` (plan-then-servo by default) drives a batched env
whose observation and action are a trained policy's; every step's observation and action is
recorded, and the episodes it finishes within the 1 mm tolerance without a snap are kept::

    python -m training.demos --like training/policies/tqc_force.zip --episodes 1000 \\
        --seed 100000 --out runs/demos/pts.npz

The file holds ``observation``, ``achieved_goal``, ``desired_goal`` (each ``(M, ...)``,
float32, as the env emits them), ``action (M, A)`` in the env's action units, ``episode (M,)``
(the episode index), and the command's settings. Episode ``k`` is seeded ``seed + k`` as in
:func:`training.evaluate.rollout`; choose seeds no evaluation uses (those of docs/results.md:
10000+, 12345+, 20000-21499, 40000-41499, 70000-70499).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .evaluate import TOLERANCES, policy_env, rollout

KEYS = ("observation", "achieved_goal", "desired_goal")


class _Recorder:
    """Wraps a batched policy; keeps each step's observation and action, batch by batch."""

    def __init__(self, policy):
        self.policy = policy
        self.steps: list[tuple[dict[str, np.ndarray], np.ndarray]] = []

    def __call__(self, obs):
        action = np.asarray(self.policy(obs))
        self.steps.append(({k: np.array(obs[k]) for k in KEYS}, action.copy()))
        return action


def collect(controller: str, venv, episodes: int, seed: int) -> dict[str, np.ndarray]:
    """Run ``controller`` (a name of ``training.controllers.CONTROLLERS``) for ``episodes``
    episodes of ``venv`` (a :class:`envs.CTRReachVecEnv`) and return the steps of the episodes
    that end within :data:`TOLERANCES[0]` without a snap or solver failure, as flat arrays
    ``(M, ...)`` with ``episode (M,)``; ``kept`` and ``episodes`` count them."""
    from .controllers import CONTROLLERS

    if controller not in CONTROLLERS:
        raise ValueError(f"controller must be one of {sorted(CONTROLLERS)}, got {controller!r}")
    rec = _Recorder(CONTROLLERS[controller](venv))
    res = rollout(rec, venv, episodes, seed=seed, progress=True, keep_traces=0)
    B, T = venv.num_envs, venv.max_episode_steps
    good = (res["final_error"] <= TOLERANCES[0]) & ~res["snap"] & ~res["failure"]
    out: dict[str, list] = {k: [] for k in (*KEYS, "action", "episode")}
    for b in range(-(-episodes // B)):
        batch = rec.steps[b * T:(b + 1) * T]
        for i in range(B):
            k = b * B + i
            if k >= episodes or not good[k]:
                continue
            for key in KEYS:
                out[key].append(np.stack([o[key][i] for o, _ in batch]))
            out["action"].append(np.stack([a[i] for _, a in batch]))
            out["episode"].append(np.full(T, k))
    if not out["action"]:
        raise RuntimeError(f"{controller}: none of {episodes} episodes ended within "
                           f"{TOLERANCES[0] * 1e3:g} mm without a snap; no demonstrations")
    data = {k: np.concatenate(v) for k, v in out.items()}
    data["kept"] = np.array(int(good.sum()))
    data["episodes"] = np.array(episodes)
    return data


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.demos", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--like", required=True,
                   help="a trained policy (.zip with its .json) whose env observation and "
                        "action the demonstrations use")
    p.add_argument("--controller", default="pts")
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--seed", type=int, default=100000)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if args.episodes < 1 or args.batch < 1:
        p.error("--episodes and --batch must be >= 1")
    venv, env_id = policy_env(args.like, args.batch)
    data = collect(args.controller, venv, args.episodes, args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"controller": args.controller, "like": str(args.like), "env_id": env_id,
            "episodes": args.episodes, "seed": args.seed, "command": " ".join(sys.argv)}
    np.savez_compressed(args.out, **data, meta=np.array(json.dumps(meta)))
    print(f"{args.out}: {int(data['kept'])} of {args.episodes} {args.controller} episodes "
          f"kept, {len(data['action'])} steps")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
