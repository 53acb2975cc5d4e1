"""Evaluate agents and baselines on the same fixed, seeded goals.

    python -m training.evaluate --policy agent=runs/<run>/best_model.zip \
        --baselines pts osc zero random --episodes 500 --out runs/eval
    python -m training.evaluate --policy logs/tqc/torchpvs-CTRReachForce-v0_1   # rl_zoo3 run

Every policy runs on a :class:`envs.CTRReachVecEnv` seeded identically, so episode ``k`` has the
same start state and goal for every policy. Metrics (per policy): success at 1/2/5 mm (final
distance), median, IQR and 95th percentile of the final error, steps to the first hit and to
settle (within 1 mm until the end) with the fraction that settles, effort ``sum ||tau||^2 dt``
and peak ``|tau|``, fraction of saturated action components, snap and solver-failure rates.
Writes ``metrics.json`` and figures (error histogram, workspace error map, trajectories with
force traces, learning curve when a run folder with ``evaluations.npz`` is given).

Policies: a model trained by ``training.train`` (its ``model.zip``/``best_model.zip``; the
sibling ``.json`` names the algorithm, env and residual base), or an rl_zoo3 run (its folder
``logs/<algo>/<env>_<n>/``, or a ``.zip`` in it: the algorithm, env kwargs, residual wrapper
and normalization are read from the run's ``<env>/args.yml`` and ``config.yml``). Baselines:
``pts`` (plan-then-servo), ``osc`` (operational-space), ``zero``, ``random``
(:mod:`training.controllers`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import yaml

__all__ = ["rollout", "summarize", "load_policy", "policy_meta", "policy_env",
           "markdown_table", "main"]

TOLERANCES = (1e-3, 2e-3, 5e-3)

# Env kwargs of a training run that define the task, not the policy: every policy is evaluated
# with the defaults, so all meet the same goals and the same episode rules. The others (the
# action/observation options, the carriage model) are the policy's and are kept.
TASK_NOT_POLICY = ("reward", "dense_scale", "tolerance", "snap_penalty", "snap_mode",
                   "goal_min_distance", "max_episode_steps", "render_mode", "plant_scale",
                   "tip_force", "tip_noise", "stiffness_penalty", "stiffness_hazard", "solver")


def rollout(policy, venv, n_episodes: int, seed: int = 12345, progress: bool = True,
            keep_traces: int = 4) -> dict[str, np.ndarray]:
    """Run ``n_episodes`` full episodes (``venv.max_episode_steps`` steps each, no early stop)
    in batches of ``venv.num_envs``. Episode ``k`` is seeded ``seed + k`` (batch ``b`` is
    ``venv.seed(seed + b * num_envs)``, whose robot ``i`` gets ``seed + b * num_envs + i``: the
    start and goal of ``gym.make(id).reset(seed=seed + k)``), so every policy meets the same
    starts and goals and no two episodes share a seed. Returns per-episode arrays and
    traces."""
    B, T = venv.num_envs, venv.max_episode_steps
    n_batches = -(-n_episodes // B)
    keys = ("final_error", "first_hit", "settle", "effort", "peak_tau", "saturation", "snap",
            "failure", "goal", "start_tip", "travel_steps")
    out: dict[str, list] = {k: [] for k in keys}
    traces = []
    bar = None
    if progress:
        try:
            from tqdm import tqdm
            bar = tqdm(total=n_batches * T, desc="evaluate", unit="step", leave=False,
                       disable=not sys.stderr.isatty())
        except ImportError:  # pragma: no cover
            bar = None
    for b in range(n_batches):
        venv.seed(seed + b * B)
        obs = venv.reset()
        venv.elapsed[:] = 0
        dist = np.zeros((T, B))
        effort = np.zeros(B)
        peak = np.zeros(B)
        sat = np.zeros(B)
        snap = np.zeros(B, dtype=bool)
        fail = np.zeros(B, dtype=bool)
        alive = np.ones(B, dtype=bool)
        st = venv.state()
        goal, start_tip = st.goal, st.tip
        travel = venv.task.travel_steps()
        tr_tip, tr_tau = [], []
        for t in range(T):
            action = policy(obs)
            obs, _, dones, infos = venv.step(action)
            d = np.array([i["distance"] for i in infos])
            tau = np.stack([i["tau"] for i in infos])
            # an episode that ended early (snap/failure) keeps its last distance
            dist[t] = np.where(alive, d, dist[t - 1] if t else d)
            effort += alive * np.array([i["effort"] for i in infos])
            peak = np.maximum(peak, alive * np.abs(tau).max(-1))
            sat += alive * np.array([i["saturated"] for i in infos])
            snap |= alive & np.array([i["snap_terminated"] for i in infos])
            fail |= alive & np.array([i["solver_failure"] for i in infos])
            alive &= ~(dones & (t < T - 1))
            if len(traces) + 0 < keep_traces:
                # achieved_goal = (tip [m], snap flag): the tip is its first three entries
                tr_tip.append(np.array([i["terminal_observation"]["achieved_goal"][:3]
                                        if "terminal_observation" in i else o[:3]
                                        for i, o in zip(infos, obs["achieved_goal"],
                                                        strict=True)]))
                tr_tau.append(tau)
            if bar is not None:
                bar.update(1)
        inside = dist <= TOLERANCES[0]
        first = np.where(inside.any(0), inside.argmax(0) + 1, -1)
        # settle: first step after which the tip stays within 1 mm to the end
        outside_after = np.flip(np.cumsum(np.flip(~inside, 0), 0), 0)
        settled = (outside_after == 0)
        settle = np.where(settled.any(0), settled.argmax(0) + 1, -1)
        out["final_error"].append(dist[-1])
        out["first_hit"].append(first)
        out["settle"].append(settle)
        out["effort"].append(effort)
        out["peak_tau"].append(peak)
        out["saturation"].append(sat / T)
        out["snap"].append(snap)
        out["failure"].append(fail)
        out["goal"].append(goal)
        out["start_tip"].append(start_tip)
        out["travel_steps"].append(travel)
        if len(traces) < keep_traces and tr_tip:
            traces.append({"tip": np.stack(tr_tip, 1)[0], "tau": np.stack(tr_tau, 1)[0],
                           "goal": goal[0]})
    if bar is not None:
        bar.close()
    res = {k: np.concatenate(v)[:n_episodes] for k, v in out.items()}
    res["traces"] = traces
    res["episode_steps"] = T
    return res


def summarize(res: dict[str, np.ndarray]) -> dict[str, float]:
    e = res["final_error"] * 1e3
    hit = res["first_hit"][res["first_hit"] > 0]
    settle = res["settle"][res["settle"] > 0]
    s = {f"success@{int(t * 1e3)}mm": float((res["final_error"] <= t).mean())
         for t in TOLERANCES}
    s.update({
        "episodes": int(len(e)),
        "median_error_mm": float(np.median(e)),
        "iqr_error_mm": float(np.subtract(*np.percentile(e, [75, 25]))),
        "p95_error_mm": float(np.percentile(e, 95)),
        "mean_error_mm": float(e.mean()),
        "steps_to_first_hit_median": float(np.median(hit)) if len(hit) else None,
        "steps_to_settle_median": float(np.median(settle)) if len(settle) else None,
        "steps_to_settle_p95": float(np.percentile(settle, 95)) if len(settle) else None,
        "settled_fraction": float((res["settle"] > 0).mean()),
        "effort_median_N2s": float(np.median(res["effort"])),
        "peak_tau_median": float(np.median(res["peak_tau"])),
        "saturation_fraction": float(res["saturation"].mean()),
        "snap_rate": float(res["snap"].mean()),
        "solver_failure_rate": float(res["failure"].mean()),
    })
    # goals whose sampled preimage the carriages can reach within the episode at full speed:
    # optimistic (unloaded speeds, rotations the short way even across +-180 deg); see
    # benchmarks/reach_ceiling.py for the loaded, snap-safe search of the solution set
    T = res.get("episode_steps", 100)
    ok = res["travel_steps"] <= T
    s["reachable_in_time_fraction"] = float(ok.mean())
    s["success@1mm_reachable_in_time"] = (float((res["final_error"][ok] <= TOLERANCES[0]).mean())
                                          if ok.any() else None)
    s.update(miss_breakdown(res))
    return s


def miss_breakdown(res: dict[str, np.ndarray]) -> dict[str, float]:
    """How the episodes that end outside 1 mm miss, as fractions of all episodes (the first
    four add up to the miss rate): ``miss_snapped`` (ended by a snap), ``miss_left_after_hit``
    (within 1 mm at some step, outside at the end), ``miss_within_5mm`` and
    ``miss_beyond_5mm`` (never within 1 mm; final error up to / beyond 5 mm), and, across
    those, ``miss_not_reachable_in_time`` (the goal's sampled preimage is more travel steps
    away than the episode has: see ``reachable_in_time_fraction``)."""
    miss = res["final_error"] > TOLERANCES[0]
    snap = res["snap"].astype(bool)
    hit = res["first_hit"] > 0
    near = res["final_error"] <= TOLERANCES[-1]
    late = res["travel_steps"] > res.get("episode_steps", 100)
    return {"miss_snapped": float((miss & snap).mean()),
            "miss_left_after_hit": float((miss & ~snap & hit).mean()),
            "miss_within_5mm": float((miss & ~snap & ~hit & near).mean()),
            "miss_beyond_5mm": float((miss & ~snap & ~hit & ~near).mean()),
            "miss_not_reachable_in_time": float((miss & late).mean())}


def markdown_table(metrics: list[dict[str, dict]]) -> str:
    """One markdown row per policy of ``metrics.json`` mappings (in order): success at 1/2/5 mm,
    median and p95 final error, median steps to settle and the settled fraction, median
    effort, saturation and snap rates, episodes."""
    head = ("| policy | success @1 / 2 / 5 mm | median / p95 error [mm] | steps to settle "
            "(median; settled) | effort Σ‖τ‖²Δt (median) | saturation | snaps | episodes |\n"
            "|---|---|---|---|---|---|---|---|")

    def f(v, spec):
        return "—" if v is None else format(v, spec)

    rows = [head]
    for m in metrics:
        for name, s in m.items():
            rows.append(
                f"| {name} | {s['success@1mm']:.3f} / {s['success@2mm']:.3f} / "
                f"{s['success@5mm']:.3f} | {f(s['median_error_mm'], '.3g')} / "
                f"{f(s['p95_error_mm'], '.3g')} | {f(s['steps_to_settle_median'], '.0f')}; "
                f"{s['settled_fraction']:.2f} | {f(s['effort_median_N2s'], '.3g')} | "
                f"{s['saturation_fraction']:.3f} | {s['snap_rate']:.3f} | {s['episodes']} |")
    return "\n".join(rows)


def _wall_clock(run_dir: Path):
    """``(minutes, cumulative env steps)`` at each finished training episode, from the run's
    ``monitor.csv`` (SB3 Monitor: episode length ``l`` and wall time ``t`` since the start);
    ``(None, None)`` without one."""
    path = run_dir / "monitor.csv"
    if not path.exists():
        return None, None
    rows = np.genfromtxt(path, delimiter=",", names=True, skip_header=1, dtype=None,
                         encoding="utf-8")
    if rows.size < 2:
        return None, None
    return np.asarray(rows["t"], float) / 60.0, np.cumsum(np.asarray(rows["l"], float))


def _figures(results: dict, out: Path, run_dirs: list[Path]) -> list[Path]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    paths = []

    def save(fig, name):
        FigureCanvasAgg(fig)
        fig.tight_layout()
        p = out / name
        fig.savefig(p, dpi=110)
        paths.append(p)

    if not results:                       # learning curves of run folders only
        _learning_curves(out, run_dirs, save, Figure)
        return paths
    # final error histogram
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    bins = np.logspace(-2, 2.5, 40)
    for name, r in results.items():
        ax.hist(np.clip(r["final_error"] * 1e3, 1e-2, None), bins=bins, histtype="step",
                label=name, linewidth=1.5)
    ax.axvline(1.0, color="k", linestyle="--", linewidth=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("final tip error [mm]")
    ax.set_ylabel("episodes")
    ax.legend(fontsize=8)
    save(fig, "error_histogram.png")
    # workspace error map per policy (goal x-z, colour = final error)
    n = len(results)
    fig = Figure(figsize=(4 * n, 3.8))
    for k, (name, r) in enumerate(results.items()):
        ax = fig.add_subplot(1, n, k + 1)
        g = r["goal"] * 1e3
        sc = ax.scatter(np.hypot(g[:, 0], g[:, 1]), g[:, 2], c=np.log10(
            np.clip(r["final_error"] * 1e3, 1e-2, None)), cmap="viridis", s=8, vmin=-1, vmax=2)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("goal radial distance [mm]")
        ax.set_ylabel("goal z [mm]")
        ax.set_aspect("equal")
    fig.colorbar(sc, ax=fig.axes, label="log10 final error [mm]")
    FigureCanvasAgg(fig)
    p = out / "workspace_error_map.png"
    fig.savefig(p, dpi=110)
    paths.append(p)
    # trajectories with force traces (first policy with traces)
    for name, r in results.items():
        if not r["traces"]:
            continue
        fig = Figure(figsize=(9, 3.2 * len(r["traces"])))
        for k, tr in enumerate(r["traces"]):
            ax = fig.add_subplot(len(r["traces"]), 2, 2 * k + 1)
            d = np.linalg.norm(tr["tip"] - tr["goal"], axis=-1) * 1e3
            ax.semilogy(np.maximum(d, 1e-3))
            ax.axhline(1.0, color="k", linestyle="--", linewidth=0.8)
            ax.set_ylabel("tip error [mm]")
            ax.set_xlabel("step")
            ax2 = fig.add_subplot(len(r["traces"]), 2, 2 * k + 2)
            N = tr["tau"].shape[-1] // 2
            for j in range(N):
                ax2.plot(tr["tau"][:, j], label=f"F{j + 1} [N]")
                ax2.plot(tr["tau"][:, N + j] * 10, linestyle=":", label=f"10·T{j + 1} [N·m]")
            ax2.set_xlabel("step")
            ax2.legend(fontsize=6, ncol=2)
        fig.suptitle(f"{name}: tip error and actuator forces/torques")
        save(fig, f"trajectories_{name}.png")
    _learning_curves(out, run_dirs, save, Figure)
    return paths


def _learning_curves(out: Path, run_dirs: list[Path], save, Figure) -> bool:
    """Learning curves against steps and wall-clock time (what a 2-core budget buys) of the
    run folders that have ``evaluations.npz``; whether there were any."""
    runs = [d for d in run_dirs if (d / "evaluations.npz").exists()]
    if runs:
        fig = Figure(figsize=(11, 3.8))
        ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
        episodes = set()
        for d in runs:
            t_min, steps_at = _wall_clock(d)
            data = np.load(d / "evaluations.npz")
            x = np.asarray(data["timesteps"], float)
            y = (np.asarray(data["successes"]).mean(-1) if "successes" in data
                 and len(data["successes"]) else np.asarray(data["results"]).mean(-1))
            episodes.add(np.asarray(data["results"]).shape[-1])
            label = d.name
            ax1.plot(x / 1e3, y, marker="o", label=label)
            if t_min is not None:
                ax2.plot(np.interp(x, steps_at, t_min), y, marker="o", label=label)
        ax1.set_xlabel("environment steps [thousands]")
        ax2.set_xlabel("wall-clock time [min] (2 shared CPU cores)")
        for ax in (ax1, ax2):
            ax.set_ylabel("eval success within 1 mm")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        # the episodes per evaluation as the runs' own evaluations.npz hold them
        n = "/".join(str(e) for e in sorted(episodes))
        fig.suptitle(f"learning curves (evaluation callback: {n} seeded selection episodes, "
                     "success within 1 mm)", fontsize=9)
        save(fig, "learning_curve.png")
    return bool(runs)


def _zoo_yaml(path: Path) -> dict:
    """An rl_zoo3 ``config.yml``/``args.yml``: an OrderedDict dumped by PyYAML, read with a
    safe loader that knows only that tag (no arbitrary Python objects)."""
    class Loader(yaml.SafeLoader):
        pass

    def ordered(loader, node):
        return dict(tuple(pair) for pair in loader.construct_sequence(node.value[0], deep=True))

    Loader.add_constructor("tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
                           ordered)
    return yaml.load(path.read_text(), Loader=Loader)  # noqa: S506 - SafeLoader subclass


def policy_meta(path: str | Path) -> tuple[Path, dict]:
    """``(model .zip, meta)`` for a training.train model or an rl_zoo3 run. ``meta`` holds
    ``algo``, ``env_id``, ``env_kwargs``, ``residual`` (the residual spec or None) and
    ``vecnormalize`` (the statistics file or None). Raises ``ValueError`` naming what is
    missing."""
    path = Path(path)
    if path.is_dir() or not path.with_suffix(".json").exists():
        # an rl_zoo3 run: <run>/<env-name>.zip, best_model.zip, <env-name>/{args,config}.yml
        run = path if path.is_dir() else path.parent
        args_files = sorted(run.glob("*/args.yml"))
        if not args_files:
            raise ValueError(f"{path}: neither a training.train model (no "
                             f"{path.with_suffix('.json').name} beside it) nor an rl_zoo3 run "
                             f"folder (no <env>/args.yml in {run})")
        params = args_files[0].parent
        args, config = _zoo_yaml(params / "args.yml"), _zoo_yaml(params / "config.yml")
        if path.is_dir():
            best = run / "best_model.zip"
            path = best if best.exists() else run / f"{params.name}.zip"
        if not path.exists():
            raise ValueError(f"{run}: no model .zip found")
        from .train import residual_spec
        stats = params / "vecnormalize.pkl"
        return path, {"algo": args["algo"], "env_id": args["env"],
                      "env_kwargs": config.get("env_kwargs") or {},
                      "residual": residual_spec(config),
                      "vecnormalize": stats if stats.exists() else None}
    info = json.loads(path.with_suffix(".json").read_text())
    stats = [p for p in (path.with_name("vecnormalize.pkl"),
                         path.with_name(path.stem + "_vecnormalize.pkl")) if p.exists()]
    return path, {"algo": info.get("algo"), "env_id": info.get("env_id"),
                  "env_kwargs": info.get("env_kwargs") or {}, "residual": info.get("residual"),
                  "vecnormalize": stats[0] if stats else None}


def policy_env(path: str | Path | None, batch: int, *, robot: str = "fig3_two_tube",
               env_id: str | None = None, extra: dict | None = None):
    """``(venv, env id)``: the :class:`envs.CTRReachVecEnv` of ``batch`` robots that the
    policy at ``path`` is evaluated on (``None``: a baseline). ``env_id`` defaults to the
    policy's training env (``torchpvs/CTRReachForce-v0`` for a baseline); of its training env
    kwargs only those that shape the policy's action and observation are kept
    (:data:`TASK_NOT_POLICY` are the task's, left at their defaults), then ``extra`` is merged
    last. Raises ``ValueError`` if the policy was trained on another robot."""
    import envs

    kwargs = {}
    env = env_id or "torchpvs/CTRReachForce-v0"
    if path is not None:
        _, meta = policy_meta(path)
        env = env_id or meta["env_id"] or env
        kwargs = {k: v for k, v in meta["env_kwargs"].items() if k not in TASK_NOT_POLICY}
        trained_on = kwargs.pop("robot", robot)
        if trained_on != robot:
            raise ValueError(f"{path} was trained on robot {trained_on!r}; evaluate it with "
                             f"--robot {trained_on} (got --robot {robot})")
    venv = envs.CTRReachVecEnv(batch, robot=robot,
                               **{**envs.env_kwargs(env), **kwargs, **(extra or {})})
    return venv, env


def load_policy(path: str, venv):
    """A trained model (see :func:`policy_meta`) as a batched, deterministic policy on
    ``venv`` (a :class:`envs.CTRReachVecEnv`), with its residual base and its observation
    normalization applied as in training."""
    from .train import ALGOS, algo_class

    path, meta = policy_meta(path)
    algo = meta["algo"]
    if algo not in ALGOS:
        raise ValueError(f"{path}: algo must be one of {ALGOS}, got {algo!r}")
    seen = venv   # the env whose observations the network reads
    if (meta["residual"] or {}).get("plan_obs"):
        from .residual import ResidualVecEnv
        seen = ResidualVecEnv(venv, meta["residual"])   # its observation space has the plan
    try:
        model = algo_class(algo).load(path, env=seen, device="cpu")  # HER needs the env
    except Exception as e:  # noqa: BLE001 - name the file and the algorithm
        raise ValueError(f"cannot load {path} as {algo}: {e}") from e
    norm = None
    if meta["vecnormalize"] is not None:
        from stable_baselines3.common.vec_env import VecNormalize
        norm = VecNormalize.load(str(meta["vecnormalize"]), seen)
        norm.training = False

    def policy(obs):
        o = norm.normalize_obs(obs) if norm is not None else obs
        return model.predict(o, deterministic=True)[0]
    if meta["residual"] is not None:
        from .residual import residual_policy
        return residual_policy(policy, venv, meta["residual"])
    return policy


def main(argv: list[str] | None = None) -> int:
    import torch

    from training.controllers import CONTROLLERS

    p = argparse.ArgumentParser(prog="python -m training.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", action="append", default=[], metavar="[NAME=]PATH",
                   help="a training.train model .zip, or an rl_zoo3 run folder or .zip in it; "
                        "repeatable")
    p.add_argument("--baselines", nargs="*", default=[], choices=sorted(CONTROLLERS))
    p.add_argument("--env", default=None,
                   help="environment id to evaluate on (default: a policy's own training env, "
                        "torchpvs/CTRReachForce-v0 for the baselines); every policy and "
                        "baseline of the call runs on it when given")
    p.add_argument("--robot", default="fig3_two_tube")
    p.add_argument("--env-kwargs", nargs="*", metavar="KEY:VALUE",
                   help="task options merged last into every policy's and baseline's env "
                        "(e.g. kink_compensation:True), as training.train's --env-kwargs")
    p.add_argument("--episodes", type=int, default=500)
    p.add_argument("--batch", type=int, default=50, help="robots stepped together")
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--run-dir", action="append", default=[],
                   help="training run folder (learning curves; repeat for several runs)")
    p.add_argument("--out", default="runs/eval")
    p.add_argument("--per-episode", action="store_true",
                   help="also write OUT/episodes.json: every episode's final error [m], first "
                        "hit and settle steps, snap and failure flags, goal and start tip [m], "
                        "travel steps, saturation and effort, per policy (episode k is seed + k)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--table", nargs="+", metavar="METRICS_JSON",
                   help="print the markdown table of saved metrics.json files and exit")
    args = p.parse_args(argv)
    if args.table:
        print(markdown_table([json.loads(Path(f).read_text()) for f in args.table]))
        return 0
    torch.set_num_threads(args.threads)

    import envs

    if args.env is not None and args.env not in envs.ENV_IDS:
        p.error(f"--env must be one of {sorted(envs.ENV_IDS)}, got {args.env!r}")
    from .train import parse_pairs
    try:
        extra = parse_pairs(args.env_kwargs, "--env-kwargs")
    except ValueError as e:
        p.error(str(e))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results, summary = {}, {}
    jobs = []
    for spec in args.policy:
        name, _, path = spec.rpartition("=")
        jobs.append((name or Path(path).stem, path))
    jobs += [(b, None) for b in args.baselines]
    if not jobs and not args.run_dir:
        p.error("give at least one --policy, --baselines or --run-dir")
    if not jobs:                 # learning curves of the run folders alone
        paths = _figures({}, out, [Path(d) for d in args.run_dir])
        if not paths:
            p.error("no --run-dir holds an evaluations.npz (the runs' evaluation callback)")
        print("wrote " + ", ".join(str(q) for q in paths))
        return 0
    for name, path in jobs:
        try:
            venv, env_id = policy_env(path, args.batch, robot=args.robot, env_id=args.env,
                                      extra=extra)
        except ValueError as e:
            p.error(str(e))
        policy = load_policy(path, venv) if path is not None else CONTROLLERS[name](venv)
        t0 = time.perf_counter()
        res = rollout(policy, venv, args.episodes, seed=args.seed)
        s = summarize(res)
        s["env"] = env_id
        s["wall_s"] = round(time.perf_counter() - t0, 1)
        results[name], summary[name] = res, s
        print(f"{name:>14s}: " + ", ".join(
            f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in s.items()),
            flush=True)
    (out / "metrics.json").write_text(json.dumps(summary, indent=2))
    if args.per_episode:
        (out / "episodes.json").write_text(json.dumps(
            {"seed": args.seed, **{name: {k: np.asarray(v).tolist() for k, v in res.items()
                                          if k not in ("traces", "episode_steps")}
                                   for name, res in results.items()}}))
    paths = _figures(results, out, [Path(d) for d in args.run_dir])
    print(f"wrote {out / 'metrics.json'} and " + ", ".join(str(p) for p in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
