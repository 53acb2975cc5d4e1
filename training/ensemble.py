"""Action ensembles of trained agents: K actors act together, no model of the robot.

    python -m training.ensemble --mode qsel --models training/policies/tqc_force.zip \
        runs/soup19/B.zip runs/soup21/B.zip --seed 20000 --episodes 1500 --out runs/ens

Each member's actor proposes its deterministic action; ``mean`` takes their average,
``qsel`` the proposal that the members' critics together rate highest (for each proposal the
sum over members of the mean of the critic's estimates: TQC's quantiles, SAC's twin values),
the critic-selection of ensemble RL; ``switch`` (two members, NEAR then FAR) takes FAR's action
while the observed tip is farther than ``switch_distance`` from the goal, NEAR's within it
(e.g. an agent that travels well and one that is precise). Members must be off-policy
agents with a critic (TQC, SAC) trained on the same observation and action spaces, without a
residual base or observation normalization (each would need its own). Scored with
:func:`training.evaluate.rollout` on the same seeded goals as every other policy; writes
``metrics.json`` as ``training.evaluate`` does. docs/results.md (stage 22) has what it
measured on the force task.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

__all__ = ["MODES", "ensemble_policy", "main"]

MODES = ("mean", "qsel", "switch")


def ensemble_policy(paths: list[str], venv, mode: str = "qsel",
                    switch_distance: float | None = None):
    """A batched deterministic policy ``obs -> action (B, A)`` of the agents at ``paths``
    (``training.train`` models with their sibling ``.json``) acting on ``venv`` (an
    :class:`envs.CTRReachVecEnv`) together by ``mode`` (:data:`MODES`; ``switch``: exactly
    two paths, near then far, and ``switch_distance`` [m] > 0, compared with the distance
    between the observation's ``achieved_goal`` and ``desired_goal`` tips). Raises
    ``ValueError`` naming the member or field and the rule it breaks."""
    import torch

    from .callbacks import critic_mean
    from .evaluate import policy_meta
    from .train import algo_class

    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if len(paths) < 1:
        raise ValueError("paths: give at least one member")
    if mode == "switch":
        if len(paths) != 2:
            raise ValueError(f"mode 'switch' takes exactly two members (near, far), got "
                             f"{len(paths)}")
        if not (isinstance(switch_distance, (int, float)) and not isinstance(switch_distance, bool)
                and math.isfinite(switch_distance) and switch_distance > 0):
            raise ValueError(f"switch_distance must be a finite distance > 0 [m] with mode "
                             f"'switch', got {switch_distance!r}")
    elif switch_distance is not None:
        raise ValueError(f"switch_distance applies to mode 'switch' only (mode {mode!r})")
    models = []
    for p in paths:
        path, meta = policy_meta(p)
        if meta["algo"] not in ("tqc", "sac"):
            raise ValueError(f"{p}: ensemble members must be TQC or SAC agents (a critic per "
                             f"member), got algo {meta['algo']!r}")
        if meta["residual"] is not None or meta["vecnormalize"] is not None:
            raise ValueError(f"{p}: ensemble members must act on the env's own observations "
                             f"(no residual base, no observation normalization)")
        try:
            m = algo_class(meta["algo"]).load(path, env=venv, device="cpu")  # HER: the env
        except ValueError as e:       # SB3's space check
            raise ValueError(f"{p}: its observation or action space is not the env's "
                             f"(trained with other env kwargs than the first member): {e}"
                             ) from e
        m.policy.set_training_mode(False)
        models.append(m)
    def policy(obs):
        with torch.no_grad():
            o, _ = models[0].policy.obs_to_tensor(obs)
            # each actor's squashed action in [-1, 1], where the critics were trained
            acts = torch.stack([m.policy.actor(o, deterministic=True) for m in models])
            if mode == "mean":
                a = acts.mean(0)
            elif mode == "switch":
                # (the goal entries' first three are the tip / goal position [m])
                d = np.linalg.norm(obs["achieved_goal"][:, :3] - obs["desired_goal"][:, :3],
                                   axis=-1)
                far = torch.as_tensor(d > switch_distance)
                a = torch.where(far[:, None], acts[1], acts[0])
            else:
                score = torch.stack([sum(critic_mean(m.policy.critic, o, a_k) for m in models)
                                     for a_k in acts])            # (K, B)
                a = acts[score.argmax(0), torch.arange(acts.shape[1])]
        return models[0].policy.unscale_action(a.numpy())   # as SB3's predict does

    return policy


def main(argv: list[str] | None = None) -> int:
    import torch

    from .evaluate import policy_env, rollout, summarize

    p = argparse.ArgumentParser(prog="python -m training.ensemble", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", required=True, help="member models (.zip)")
    p.add_argument("--mode", choices=MODES, default="qsel")
    p.add_argument("--switch-distance", type=float, default=None, metavar="METRES",
                   help="--mode switch: FAR (the second model) acts beyond this distance")
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--batch", type=int, default=50)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--name", default=None, help="the key in metrics.json (default: the mode)")
    p.add_argument("--out", default="runs/ensemble")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        venv, env_id = policy_env(args.models[0], args.batch)
        policy = ensemble_policy(args.models, venv, args.mode, args.switch_distance)
    except ValueError as e:
        p.error(str(e))
    t0 = time.perf_counter()
    s = summarize(rollout(policy, venv, args.episodes, seed=args.seed))
    s.update(env=env_id, mode=args.mode, members=args.models,
             switch_distance=args.switch_distance,
             wall_s=round(time.perf_counter() - t0, 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = args.name or args.mode
    (out / "metrics.json").write_text(json.dumps({name: s}, indent=2))
    print(f"{name}: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                  for k, v in s.items() if k != "members"))
    print(f"wrote {out / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
