"""Train an SB3 / sb3-contrib agent on a torchpvs reaching env from the rl-zoo hyperparameters.

    python -m training.train --algo sac --env torchpvs/CTRReachForce-v0 \
        [--env-kwargs robot:rvim_three_tube] [--hyperparams n_envs:64 gamma:0.99] \
        [--residual base:pts scale:0.3] [-n 100000] [--seed 0] [--max-minutes 55]

Hyperparameters come from ``training/hyperparams/<algo>.yml`` (or ``--conf-file``), the entry
keyed by the env id, in rl-baselines3-zoo's format: the same files run unchanged with
``python -m rl_zoo3.train --algo sac --env torchpvs/CTRReachForce-v0 --gym-packages envs
--conf-file training/hyperparams/sac.yml`` (see docs/training.md). What this script adds to
the zoo's:

* the ``n_envs`` robots are ONE :class:`envs.CTRReachVecEnv` (one batched solve per substep)
  instead of a ``DummyVecEnv`` of ``n_envs`` single envs (``n_envs`` separate solves);
* ``--residual``: a residual agent on a model-based controller (:mod:`training.residual`;
  the zoo equivalent is a ``vec_env_wrapper`` entry, which this script reads too);
* ``--max-minutes``: a wall-clock budget; evaluation on ``--eval-episodes`` seeded episodes of
  one batched env;
* a run folder with everything needed to reproduce and evaluate the run.

Overrides: ``--env-kwargs`` and ``--hyperparams`` take ``key:value`` pairs (values are Python
literals; a bare word is a string), merged into the entry (rl_zoo3's ``--env-kwargs``
replaces the whole ``env_kwargs`` mapping instead). Keys of the entry: ``n_timesteps``,
``policy``, ``n_envs``, ``env_kwargs``, ``normalize``, ``monitor_kwargs``, ``callback``,
``vec_env_wrapper``, ``noise_type``/``noise_std`` (TD3/TQC/SAC action noise),
``replay_buffer_class``/``replay_buffer_kwargs``/``policy_kwargs`` (Python strings, as in the
zoo) and any keyword of the algorithm's class; anything else is refused by name.

Each run folder (``<out>/<algo>_<env>_s<seed>_<time>/``) keeps ``hyperparams.yml`` (the
resolved entry), ``command.txt``, TensorBoard logs, checkpoints (one per evaluation),
``evaluations.npz`` and ``best_model.zip`` from the evaluation callback, the final
``model.zip``, ``model.json`` (the algorithm, env id and kwargs, residual spec: what
:mod:`training.evaluate` needs to load it) and ``train.log``.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import yaml

__all__ = ["ALGOS", "HYPERPARAMS_DIR", "load_hyperparams", "parse_pairs", "make_venv",
           "make_model", "train", "main"]

HYPERPARAMS_DIR = Path(__file__).resolve().parent / "hyperparams"
ALGOS = ("sac", "tqc", "td3", "ppo")

# Keys of a zoo entry that are not keywords of the algorithm's class.
ZOO_KEYS = {"n_timesteps", "n_envs", "env_kwargs", "normalize", "monitor_kwargs", "callback",
            "vec_env_wrapper", "env_wrapper", "noise_type", "noise_std", "frame_stack"}


def algo_class(algo: str):
    """The SB3 / sb3-contrib class of ``algo`` (one of :data:`ALGOS`)."""
    if algo == "tqc":
        from sb3_contrib import TQC
        return TQC
    from stable_baselines3 import PPO, SAC, TD3
    try:
        return {"sac": SAC, "td3": TD3, "ppo": PPO}[algo]
    except KeyError:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}") from None


def load_hyperparams(algo: str, env_id: str, conf_file: str | Path | None = None) -> dict:
    """The entry for ``env_id`` of ``conf_file`` (default ``training/hyperparams/<algo>.yml``),
    checked: ``env_id`` registered, every key known to rl_zoo3 or to the algorithm's class."""
    import envs

    if env_id not in envs.ENV_IDS:
        raise ValueError(f"env must be one of {sorted(envs.ENV_IDS)}, got {env_id!r}")
    path = Path(conf_file) if conf_file else HYPERPARAMS_DIR / f"{algo}.yml"
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path}: a hyperparameter file is a mapping from env id to entry")
    if env_id not in data:
        raise ValueError(f"{path}: no entry for env {env_id!r} (entries: {sorted(data)})")
    entry = dict(data[env_id])
    check_entry(entry, algo, f"{path} [{env_id}]")
    return entry


def check_entry(entry: dict, algo: str, where: str) -> None:
    """Refuse keys that are neither zoo keys nor keywords of ``algo``'s class."""
    params = set(inspect.signature(algo_class(algo).__init__).parameters) - {"self", "env"}
    unknown = set(entry) - ZOO_KEYS - params
    if unknown:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)} (neither rl_zoo3 keys "
                         f"{sorted(ZOO_KEYS)} nor keywords of {algo_class(algo).__name__})")
    if "n_timesteps" not in entry:
        raise ValueError(f"{where}: n_timesteps is required")


def parse_pairs(pairs: list[str] | None, flag: str) -> dict:
    """``["key:value", ...]`` -> dict; values are Python literals, else strings."""
    out = {}
    for item in pairs or []:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"{flag} takes key:value pairs, got {item!r}")
        try:
            out[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            out[key] = value
    return out


def _eval_str(value, name: str):
    """The zoo writes ``policy_kwargs`` etc. as Python strings: evaluate them with only
    ``dict``, ``torch.nn`` and ``importlib`` in scope (the zoo names classes of other packages
    as ``importlib.import_module('envs.her').GoalConsistentHerReplayBuffer``)."""
    if not isinstance(value, str):
        return value
    import torch.nn as nn
    try:
        return eval(value, {"__builtins__": {}},  # noqa: S307
                    {"dict": dict, "nn": nn, "importlib": importlib})
    except Exception as e:  # noqa: BLE001 - report which entry
        raise ValueError(f"{name}: cannot evaluate {value!r}: {e}") from None


def _import(dotted: str):
    module, _, name = dotted.rpartition(".")
    if not module:
        raise ValueError(f"expected a dotted path module.Name, got {dotted!r}")
    return getattr(importlib.import_module(module), name)


def _named_list(spec, key: str) -> list[tuple[type, dict]]:
    """The zoo's ``callback``/``vec_env_wrapper`` entries: a dotted name, a one-key mapping
    ``{name: kwargs}``, or a list of these -> ``[(class, kwargs)]``."""
    if spec is None:
        return []
    out = []
    for item in spec if isinstance(spec, list) else [spec]:
        if isinstance(item, dict):
            if len(item) != 1:
                raise ValueError(f"{key}: each entry is a name or a one-key mapping "
                                 f"{{name: kwargs}}, got {item!r}")
            (name, kw), = item.items()
        else:
            name, kw = item, {}
        out.append((_import(name), dict(kw or {})))
    return out


def make_venv(env_id: str, hp: dict, n_envs: int | None = None):
    """One batched :class:`envs.CTRReachVecEnv` of ``n_envs`` (default ``hp["n_envs"]``)
    robots with ``hp["env_kwargs"]``, wrapped in the entry's ``vec_env_wrapper`` list."""
    import envs
    kw = dict(hp.get("env_kwargs") or {})
    if "control" in kw:
        raise ValueError("env_kwargs: 'control' is set by the env id (CTRReachForce/Joint)")
    venv = envs.CTRReachVecEnv(int(n_envs or hp.get("n_envs", 1)),
                               **{**envs.env_kwargs(env_id), **kw})
    for cls, kwargs in _named_list(hp.get("vec_env_wrapper"), "vec_env_wrapper"):
        venv = cls(venv, **kwargs)
    return venv


def residual_spec(hp: dict) -> dict | None:
    """The :class:`training.residual.ResidualVecEnv` keywords in the entry, if any."""
    from .residual import ResidualVecEnv
    for cls, kwargs in _named_list(hp.get("vec_env_wrapper"), "vec_env_wrapper"):
        if cls is ResidualVecEnv:
            return {**dict(kwargs.pop("spec", None) or {}), **kwargs}
    return None


def make_model(algo: str, hp: dict, venv, seed: int, log_dir: Path | None):
    """The algorithm's model on ``venv`` with the entry's keywords (zoo keys resolved)."""
    cls = algo_class(algo)
    kw = {k: v for k, v in hp.items() if k not in ZOO_KEYS}
    for name in ("policy_kwargs", "replay_buffer_kwargs"):
        if name in kw:
            kw[name] = _eval_str(kw[name], name)
    from stable_baselines3 import HerReplayBuffer
    rb = kw.get("replay_buffer_class")
    if isinstance(rb, str):
        kw["replay_buffer_class"] = (HerReplayBuffer if rb == "HerReplayBuffer" else
                                     _eval_str(rb, "replay_buffer_class") if "(" in rb else
                                     _import(rb))
    if isinstance(kw.get("replay_buffer_class"), type) and issubclass(
            kw["replay_buffer_class"], HerReplayBuffer):
        res = residual_spec(hp)
        if res is not None:
            from .residual import needs_plain_replay
            if needs_plain_replay(res):
                raise ValueError(
                    "residual plan_obs or penalty with HerReplayBuffer: the plan in the "
                    "observation belongs to the episode's goal and HER's compute_reward does "
                    "not know the penalty; use a plain replay buffer (--hyperparams "
                    "replay_buffer_class:stable_baselines3.common.buffers.DictReplayBuffer "
                    "replay_buffer_kwargs:None)")
        # HER samples only from finished episodes: SB3 fails mid-run otherwise.
        steps = int(getattr(venv, "max_episode_steps", 0) or 0)
        need = venv.num_envs * steps
        if int(kw.get("learning_starts", 100)) < need:
            raise ValueError(
                f"learning_starts={kw.get('learning_starts', 100)} is below n_envs x "
                f"max_episode_steps = {venv.num_envs} x {steps} = {need}: HER cannot sample "
                f"before the first episodes end; set learning_starts >= {need} "
                f"(e.g. --hyperparams learning_starts:{need})")
    for name in ("learning_rate", "clip_range"):
        v = kw.get(name)
        if isinstance(v, str) and v.startswith("lin_"):   # the zoo's linear schedule
            v0 = float(v[4:])
            kw[name] = lambda p, v0=v0: p * v0
    if isinstance(kw.get("train_freq"), list):
        kw["train_freq"] = tuple(kw["train_freq"])
    if hp.get("noise_type"):
        from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
        n = venv.action_space.shape[0]
        std = float(hp.get("noise_std", 0.1))
        noise = {"normal": NormalActionNoise,
                 "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}.get(hp["noise_type"])
        if noise is None:
            raise ValueError(f"noise_type must be 'normal' or 'ornstein-uhlenbeck', got "
                             f"{hp['noise_type']!r}")
        kw["action_noise"] = noise(np.zeros(n), std * np.ones(n))
    base = dict(policy="MultiInputPolicy", seed=seed, verbose=0, device="cpu",
                tensorboard_log=str(log_dir / "tb") if log_dir is not None else None)
    return cls(env=venv, **{**base, **kw})


def _normalize_kwargs(hp: dict) -> dict | None:
    v = hp.get("normalize")
    if not v:
        return None
    kw = _eval_str(v, "normalize") if isinstance(v, str) else v
    kw = dict(kw) if isinstance(kw, dict) else {}
    kw.setdefault("gamma", float(hp.get("gamma", 0.99)))
    return kw


def _callbacks(algo, env_id, hp, venv_train, run_dir: Path, seed: int, total: int,
               eval_freq: int, eval_episodes: int, progress: bool, max_minutes: float | None):
    from stable_baselines3.common.callbacks import (
        CallbackList,
        CheckpointCallback,
        EvalCallback,
        ProgressBarCallback,
    )
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    from .callbacks import WallClockLimit

    cbs = [cls(**kw) for cls, kw in _named_list(hp.get("callback"), "callback")]
    if max_minutes:
        cbs.append(WallClockLimit(max_minutes))
    if eval_freq > 0 and eval_episodes > 0:
        eval_env = VecMonitor(make_venv(env_id, hp, n_envs=min(50, eval_episodes)))
        eval_env.seed(10_000 + seed)
        nk = _normalize_kwargs(hp)
        if nk is not None:
            eval_env = VecNormalize(eval_env, training=False, norm_reward=False,
                                    **{k: v for k, v in nk.items()
                                       if k not in ("training", "norm_reward")})
        cbs.append(EvalCallback(eval_env, n_eval_episodes=eval_episodes,
                                eval_freq=max(1, eval_freq // venv_train.num_envs),
                                log_path=str(run_dir), best_model_save_path=str(run_dir),
                                deterministic=True, verbose=0))
    # a checkpoint at every evaluation, so the one chosen on the selection episodes exists
    # (EvalCallback keeps only the best mean return); every fifth of the run without them
    every = (eval_freq if eval_freq > 0 and eval_episodes > 0 else total // 5)
    cbs.append(CheckpointCallback(save_freq=max(1, every // venv_train.num_envs),
                                  save_path=str(run_dir / "checkpoints"), name_prefix="model"))
    if progress:
        cbs.append(ProgressBarCallback())
    return CallbackList(cbs)


def train(algo: str, env_id: str, hp: dict, *, steps: int | None = None, seed: int = 0,
          out: str | Path = "runs", progress: bool = True, threads: int = 1,
          eval_freq: int = 20_000, eval_episodes: int = 200, max_minutes: float | None = None,
          argv: list[str] | None = None, init_from: str | Path | None = None,
          widen: bool = False) -> Path:
    """Train ``algo`` on ``env_id`` with the (checked, overridden) entry ``hp``; returns the
    run folder. ``init_from``: a saved model (``.zip`` of the same algorithm, observation and
    action spaces) whose networks start the run (fine-tuning on another task; the replay
    buffer starts empty). ``widen``: the entry's networks are wider than ``init_from``'s, or its
    observation has entries appended; start from its function, widened (Net2WiderNet and zero
    weights for the new inputs, :mod:`training.widen`)."""
    import torch
    from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

    check_entry(hp, algo, "hyperparams")
    torch.set_num_threads(threads)
    total = int(steps or float(hp["n_timesteps"]))
    tag = env_id.split("/")[-1]
    res = residual_spec(hp)
    if res is not None:
        tag += f"_residual-{res.get('base', 'pts')}"
    stem = Path(out) / f"{algo}_{tag}_s{seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    Path(out).mkdir(parents=True, exist_ok=True)
    for k in range(1, 1000):  # two runs started in the same second get distinct folders
        run_dir = stem if k == 1 else stem.with_name(f"{stem.name}-{k}")
        try:
            run_dir.mkdir()
            break
        except FileExistsError:
            continue
    (run_dir / "hyperparams.yml").write_text(yaml.safe_dump({env_id: hp}, sort_keys=False))
    cmd = "python -m training.train " + " ".join(shlex.quote(a) for a in (argv or []))
    (run_dir / "command.txt").write_text(cmd + "\n")
    venv = make_venv(env_id, hp)
    venv.seed(seed)
    mk = _eval_str(hp.get("monitor_kwargs") or {}, "monitor_kwargs")
    venv = VecMonitor(venv, filename=str(run_dir / "monitor.csv"), **mk)
    nk = _normalize_kwargs(hp)
    if nk is not None:
        venv = VecNormalize(venv, **nk)
    model = make_model(algo, hp, venv, seed, run_dir)
    if init_from is not None:
        try:
            if widen:
                from .widen import widen_into
                widen_into(model, init_from, seed=seed)
            else:
                model.set_parameters(str(init_from), exact_match=True, device="cpu")
            _load_tensor_variables(model, init_from)
        except (OSError, ValueError, RuntimeError, KeyError) as e:
            raise ValueError(f"--init-from {init_from}: cannot load its networks into a "
                             f"{algo} model of this env ({e})") from None
    if res is not None:
        from .residual import zero_residual_head
        zero_residual_head(model)
    cb = _callbacks(algo, env_id, hp, venv, run_dir, seed, total, eval_freq, eval_episodes,
                    progress, max_minutes)
    t0 = time.perf_counter()
    model.learn(total_timesteps=total, callback=cb, tb_log_name="tb")
    wall = time.perf_counter() - t0
    done = int(model.num_timesteps)
    model.save(run_dir / "model.zip")
    meta = {"algo": algo, "env_id": env_id, "env_kwargs": hp.get("env_kwargs") or {},
            "steps": done, "steps_requested": total, "seed": seed, "wall_s": round(wall, 1),
            "command": cmd}
    if res is not None:
        meta["residual"] = res
    if init_from is not None:
        meta["init_from"] = str(init_from)
        if widen:
            meta["widened"] = True
    (run_dir / "model.json").write_text(json.dumps(meta, indent=2))
    if (run_dir / "best_model.zip").exists():  # the eval callback's best: same algo/env/residual
        (run_dir / "best_model.json").write_text(json.dumps(meta, indent=2))
    if nk is not None:
        venv.save(str(run_dir / "vecnormalize.pkl"))
    with open(run_dir / "train.log", "a") as f:
        f.write(f"trained {done} steps in {wall:.1f} s ({done / wall:.1f} steps/s)\n")
    print(f"trained {done} steps in {wall:.1f} s -> {run_dir}", flush=True)
    return run_dir


def _load_tensor_variables(model, path) -> None:
    """The saved model's tensor variables (SAC/TQC's ``log_ent_coef``) into ``model``.
    ``set_parameters`` loads state dicts only, so a fine-tune restarted the entropy coefficient
    at its initial 1.0 (the force agent had learned 0.02): a 45x entropy bonus under the sparse
    reward, which drove the policy away from the one it started from (a robust fine-tune
    evaluated 0/100 after 40k steps, from 0.75 zero-shot)."""
    import torch
    from stable_baselines3.common.save_util import load_from_zip_file

    _, _, tensors = load_from_zip_file(str(path), device="cpu", load_data=False)
    for name, value in (tensors or {}).items():
        target = getattr(model, name, None)
        if not isinstance(target, type(value)) or target.shape != value.shape:
            raise ValueError(f"tensor variable {name!r} does not match this model")
        with torch.no_grad():
            target.copy_(value)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="python -m training.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algo", required=True, choices=ALGOS)
    p.add_argument("--env", default="torchpvs/CTRReachForce-v0", help="env id")
    p.add_argument("--conf-file", default=None,
                   help="hyperparameter YAML (default training/hyperparams/<algo>.yml)")
    p.add_argument("--env-kwargs", nargs="*", metavar="KEY:VALUE",
                   help="merged into the entry's env_kwargs (e.g. robot:rvim_three_tube)")
    p.add_argument("-params", "--hyperparams", nargs="*", metavar="KEY:VALUE",
                   help="override entry keys (e.g. n_envs:64 learning_rate:3e-4)")
    p.add_argument("--residual", nargs="*", metavar="KEY:VALUE",
                   help="learn a residual on a model-based controller: base:pts|osc, "
                        "scale, gate_radius and the controller's gains (training/residual.py)")
    p.add_argument("-n", "--n-timesteps", type=int, default=None, help="override n_timesteps")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-freq", type=int, default=20_000,
                   help="evaluate every this many env steps (<= 0: never)")
    p.add_argument("--eval-episodes", type=int, default=200,
                   help="episodes per evaluation (a success rate's sampling error is about "
                   "+-0.03 at 200, +-0.016 at 500: late checkpoints that differ by 1-3 points "
                   "need 500, or a separate training.evaluate --seed run, to be ranked)")
    p.add_argument("--out", default="runs", help="parent folder of the run folder")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest here)")
    p.add_argument("--max-minutes", type=float, default=None,
                   help="stop after this much wall time (the model so far is saved)")
    p.add_argument("--init-from", default=None, metavar="MODEL_ZIP",
                   help="start from this saved model's networks (fine-tuning)")
    p.add_argument("--widen", action="store_true",
                   help="with --init-from: this run's net_arch is wider than the model's, or "
                        "its observation has entries appended (e.g. observe_stiffness:True); "
                        "start from its function, widened (Net2WiderNet, training/widen.py)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.widen and args.init_from is None:
        p.error("--widen: needs --init-from (the model to widen)")
    try:
        hp = load_hyperparams(args.algo, args.env, args.conf_file)
        hp.update(parse_pairs(args.hyperparams, "--hyperparams"))
        env_kwargs = {**dict(hp.get("env_kwargs") or {}),
                      **parse_pairs(args.env_kwargs, "--env-kwargs")}
        if env_kwargs:
            hp["env_kwargs"] = env_kwargs
        if args.residual is not None:
            import envs
            if envs.ENV_IDS[args.env] != "force":
                raise ValueError("--residual: the base controllers command forces; use "
                                 "torchpvs/CTRReachForce-v0")
            hp["vec_env_wrapper"] = [{"training.residual.ResidualVecEnv":
                                      parse_pairs(args.residual, "--residual")}]
        check_entry(hp, args.algo, "--hyperparams")
    except (OSError, ValueError) as e:
        p.error(str(e))
    train(args.algo, args.env, hp, steps=args.n_timesteps, seed=args.seed, out=args.out,
          progress=not args.no_progress and sys.stderr.isatty(), threads=args.threads,
          eval_freq=args.eval_freq, eval_episodes=args.eval_episodes,
          max_minutes=args.max_minutes, argv=argv, init_from=args.init_from,
          widen=args.widen)
    return 0


if __name__ == "__main__":
    sys.exit(main())
