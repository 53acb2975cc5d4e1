"""Train an SB3 agent on a torchpvs reaching environment from a YAML config.

    python -m training.train --config training/configs/sac_her_force.yaml [--steps N] [--seed S]

Configs are keyed like rl-baselines3-zoo's (see ``training/configs/``)::

    env_id: torchpvs/CTRReachForce-v0     # or torchpvs/CTRReachJoint-v0
    env_kwargs: {robot: fig3_two_tube, reward: sparse}
    n_envs: 8                              # robots stepped together (one batched solve)
    algo: sac                              # sac | td3 | ppo (HER for sac/td3 when her: given)
    n_timesteps: 300000
    her: {n_sampled_goal: 4, goal_selection_strategy: future}
    normalize: false                       # VecNormalize (PPO)
    curriculum: {start: 0.01, end: 0.001, fraction: 0.5}   # tolerance [m], exponential
    residual: {scale: 0.3, gain: 0.7}      # optional: learn a residual on the model-based
                                           # controller (training/residual.py)
    eval: {freq: 20000, episodes: 50}
    hyperparams: {learning_rate: 1e-3, gamma: 0.95, ...}   # passed to the SB3 class

Each run folder (``runs/<config>_s<seed>_<time>/``) keeps the config, the arguments, the exact
command, TensorBoard logs, checkpoints, ``evaluations.npz`` from the eval callback, the final
model (``model.zip`` + ``model.json`` with the algorithm and env id) and ``train.log``.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import yaml

__all__ = ["load_config", "make_model", "train", "main"]

ALGOS = ("sac", "td3", "ppo")


def load_config(path: str | Path) -> dict:
    cfg = yaml.safe_load(Path(path).read_text())
    if not isinstance(cfg, dict):
        raise ValueError(f"{path}: a config is a YAML mapping")
    known = {"env_id", "env_kwargs", "n_envs", "algo", "n_timesteps", "her", "normalize",
             "curriculum", "eval", "hyperparams", "policy", "max_episode_steps", "notes",
             "residual"}
    unknown = set(cfg) - known
    if unknown:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)} (known: {sorted(known)})")
    if cfg.get("algo") not in ALGOS:
        raise ValueError(f"{path}: algo must be one of {ALGOS}, got {cfg.get('algo')!r}")
    import envs
    if cfg.get("env_id") not in envs.ENV_IDS:
        raise ValueError(f"{path}: env_id must be one of {sorted(envs.ENV_IDS)}, "
                         f"got {cfg.get('env_id')!r}")
    return cfg


def make_venv(cfg: dict, n_envs: int | None = None):
    """The batched env of ``cfg`` (wrapped in :class:`training.residual.ResidualVecEnv` when
    the config has a ``residual`` entry)."""
    import envs
    venv = envs.CTRReachVecEnv(n_envs or cfg.get("n_envs", 8),
                               control=envs.ENV_IDS[cfg["env_id"]],
                               max_episode_steps=cfg.get("max_episode_steps", 100),
                               **cfg.get("env_kwargs", {}))
    if cfg.get("residual") is not None:
        from .residual import ResidualVecEnv
        if envs.ENV_IDS[cfg["env_id"]] != "force":
            raise ValueError("residual: the base controller commands forces; use the force env")
        venv = ResidualVecEnv(venv, _floats(dict(cfg["residual"])))
    return venv


def _floats(d: dict) -> dict:
    """YAML 1.1 reads ``1e-3`` as a string; accept it as a number."""
    out = {}
    for k, v in d.items():
        if isinstance(v, str):
            try:
                v = float(v)
            except ValueError:
                pass
        out[k] = _floats(v) if isinstance(v, dict) else v
    return out


def make_model(cfg: dict, venv, seed: int, log_dir: Path | None):
    from stable_baselines3 import PPO, SAC, TD3
    from stable_baselines3.common.noise import NormalActionNoise
    from stable_baselines3.her.her_replay_buffer import HerReplayBuffer

    hp = _floats(dict(cfg.get("hyperparams", {})))
    algo = cfg["algo"]
    kwargs = dict(policy=cfg.get("policy", "MultiInputPolicy"), env=venv, seed=seed,
                  verbose=0, device="cpu",
                  tensorboard_log=str(log_dir / "tb") if log_dir is not None else None)
    if algo in ("sac", "td3") and cfg.get("her"):
        kwargs["replay_buffer_class"] = HerReplayBuffer
        kwargs["replay_buffer_kwargs"] = dict(cfg["her"])
    if algo == "td3":
        sigma = hp.pop("action_noise_sigma", 0.1)
        n = venv.action_space.shape[0]
        kwargs["action_noise"] = NormalActionNoise(np.zeros(n), sigma * np.ones(n))
    cls = {"sac": SAC, "td3": TD3, "ppo": PPO}[algo]
    return cls(**kwargs, **hp)


def _callbacks(cfg, venv_train, run_dir: Path, seed: int, total: int, progress: bool,
               max_minutes: float | None = None):
    from stable_baselines3.common.callbacks import (
        BaseCallback,
        CallbackList,
        CheckpointCallback,
        EvalCallback,
        ProgressBarCallback,
    )

    class ToleranceCurriculum(BaseCallback):
        """Exponential decay of the success tolerance from ``start`` to ``end`` [m] over the
        first ``fraction`` of training (``env_method("set_tolerance")``), then ``end``."""

        def __init__(self, start: float, end: float, fraction: float):
            super().__init__()
            self.start, self.end, self.fraction = start, end, fraction

        def tolerance(self, t: int) -> float:
            p = min(1.0, t / max(1.0, self.fraction * total))
            return math.exp(math.log(self.start) + p * (math.log(self.end) - math.log(self.start)))

        def _on_step(self) -> bool:
            tol = self.tolerance(self.num_timesteps)
            self.training_env.env_method("set_tolerance", tol, indices=[0])
            self.logger.record("curriculum/tolerance_mm", tol * 1e3)
            return True

    class WallClockLimit(BaseCallback):
        """Stop training after ``minutes`` of wall time (the run keeps what it learned)."""

        def __init__(self, minutes: float):
            super().__init__()
            self.deadline = time.perf_counter() + 60.0 * minutes

        def _on_step(self) -> bool:
            return time.perf_counter() < self.deadline

    cbs = []
    if max_minutes:
        cbs.append(WallClockLimit(max_minutes))
    cur = cfg.get("curriculum")
    if cur:
        cbs.append(ToleranceCurriculum(float(cur["start"]), float(cur["end"]),
                                       float(cur.get("fraction", 0.5))))
    ev = cfg.get("eval", {})
    if ev.get("freq"):
        eval_env = make_venv(cfg, n_envs=min(10, int(ev.get("episodes", 50))))
        eval_env.seed(10_000 + seed)
        n_envs = venv_train.num_envs
        from stable_baselines3.common.vec_env import VecMonitor
        eval_env = VecMonitor(eval_env)
        if cfg.get("normalize"):
            from stable_baselines3.common.vec_env import VecNormalize
            eval_env = VecNormalize(eval_env, training=False, norm_reward=False)
        cbs.append(EvalCallback(eval_env, n_eval_episodes=int(ev.get("episodes", 50)),
                                eval_freq=max(1, int(ev["freq"]) // n_envs),
                                log_path=str(run_dir), best_model_save_path=str(run_dir),
                                deterministic=True, verbose=0))
    cbs.append(CheckpointCallback(save_freq=max(1, total // 5 // venv_train.num_envs),
                                  save_path=str(run_dir / "checkpoints"), name_prefix="model"))
    if progress:
        cbs.append(ProgressBarCallback())
    return CallbackList(cbs)


def train(cfg: dict, *, steps: int | None = None, seed: int = 0, out: str | Path = "runs",
          name: str = "run", progress: bool = True, threads: int = 1,
          max_minutes: float | None = None, argv: list[str] | None = None) -> Path:
    """Train per ``cfg``; returns the run folder."""
    import torch
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    torch.set_num_threads(threads)
    total = int(steps or cfg["n_timesteps"])
    run_dir = Path(out) / f"{name}_s{seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    run_dir.mkdir(parents=True, exist_ok=False)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    (run_dir / "args.json").write_text(json.dumps({"steps": total, "seed": seed,
                                                   "threads": threads}, indent=2))
    cmd = "python -m training.train " + " ".join(shlex.quote(a) for a in (argv or []))
    (run_dir / "command.txt").write_text(cmd + "\n")
    venv = make_venv(cfg)
    venv.seed(seed)
    venv = VecMonitor(venv, filename=str(run_dir / "monitor.csv"),
                      info_keywords=("is_success",))
    if cfg.get("normalize"):
        venv = VecNormalize(venv, norm_obs_keys=["observation"], gamma=float(
            _floats(cfg.get("hyperparams", {})).get("gamma", 0.99)))
    model = make_model(cfg, venv, seed, run_dir)
    cb = _callbacks(cfg, venv, run_dir, seed, total, progress, max_minutes)
    t0 = time.perf_counter()
    model.learn(total_timesteps=total, callback=cb, tb_log_name="tb")
    wall = time.perf_counter() - t0
    done = int(model.num_timesteps)
    model.save(run_dir / "model.zip")
    meta = {"algo": cfg["algo"], "env_id": cfg["env_id"], "env_kwargs": cfg.get("env_kwargs", {}),
            "steps": done, "steps_requested": total, "seed": seed, "wall_s": round(wall, 1),
            "command": cmd}
    if cfg.get("residual") is not None:
        meta["residual"] = _floats(dict(cfg["residual"]))
    (run_dir / "model.json").write_text(json.dumps(meta, indent=2))
    if (run_dir / "best_model.zip").exists():  # the eval callback's best: same algo/env/residual
        (run_dir / "best_model.json").write_text(json.dumps(meta, indent=2))
    if cfg.get("normalize"):
        import pickle
        with open(run_dir / "model_vecnormalize.pkl", "wb") as f:
            pickle.dump(venv, f)
    with open(run_dir / "train.log", "a") as f:
        f.write(f"trained {done} steps in {wall:.1f} s ({done / wall:.1f} steps/s)\n")
    print(f"trained {done} steps in {wall:.1f} s -> {run_dir}", flush=True)
    return run_dir


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="python -m training.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", required=True, help="YAML config (training/configs/*.yaml)")
    p.add_argument("--steps", type=int, default=None, help="override n_timesteps")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs", help="parent folder of the run folder")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest here)")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this much wall time (the model so far is saved)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    try:
        cfg = load_config(args.config)
    except (OSError, ValueError) as e:
        p.error(str(e))
    train(cfg, steps=args.steps, seed=args.seed, out=args.out, name=Path(args.config).stem,
          progress=not args.no_progress and sys.stderr.isatty(), threads=args.threads,
          max_minutes=args.max_minutes, argv=argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
