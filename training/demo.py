"""The README's main job: a torque-controlled reach with the shipped policies.

    python -m training.demo [--policy training/policies/tqc_force.zip ...] [--goals 20]

Loads the shipped TQC policies for the force/torque-action environment (the paper's Fig. 3
robot): the model-free agent (``tqc_force.zip``, compensated force actions, TQC + HER) and the
residual agent on plan-then-servo (``tqc_residual_pts.zip``, raw force actions, see
``training/residual.py``), each on the action convention it was trained on, evaluates them on
seeded goals next to the model-based controllers (plan-then-servo and operational-space),
prints the success rates and final errors, and saves
``demo_out/reach.png``: on the first seeded goal the first policy reaches, the tip paths of every
policy (top and side views), their tip error over time, and the first policy's actuator forces
and torques. Without a policy file it loads, it demos the controllers alone and says so.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

POLICIES = Path(__file__).resolve().parent / "policies"
DEFAULT_POLICIES = (POLICIES / "tqc_force.zip", POLICIES / "tqc_residual_pts.zip")


def _episodes(policy, venv, seed: int) -> dict[str, np.ndarray]:
    """One seeded batch of full episodes (the goals and starts of ``rollout`` with the same seed):
    tip ``(B, T+1, 3)``, distance ``(B, T)`` [m], commanded forces/torques ``(B, T, 2N)``."""
    venv.seed(seed)
    obs = venv.reset()
    # achieved_goal = (tip [m], snap flag): the tip is its first three entries
    tips, dist, tau = [obs["achieved_goal"][:, :3].copy()], [], []
    goal = venv.state().goal
    for _ in range(venv.max_episode_steps):
        obs, _, _, infos = venv.step(policy(obs))
        tips.append(np.array([i.get("terminal_observation", {}).get("achieved_goal", o)[:3]
                              for i, o in zip(infos, obs["achieved_goal"], strict=True)]))
        dist.append([i["distance"] for i in infos])
        tau.append(np.stack([i["tau"] for i in infos]))
    return {"tip": np.stack(tips, 1), "dist": np.array(dist).T, "tau": np.stack(tau, 1),
            "goal": goal}


def _figure(runs: dict[str, dict], k: int, robot, path: Path, dt: float) -> None:
    """Episode ``k`` of every policy: tip paths (top and side views), tip error over time, and
    the first policy's actuator commands as fractions of full scale."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12, 6.6))
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(2, 2, width_ratios=[1, 1.35])
    styles = [dict(color="tab:blue", lw=2.2), dict(color="tab:red", lw=1.8, ls="-."),
              dict(color="tab:orange", lw=1.8, ls="--"), dict(color="tab:purple", lw=1.5, ls=":")]
    first = next(iter(runs.values()))
    goal, start = first["goal"][k] * 1e3, first["tip"][k, 0] * 1e3
    for row, (i, j, view) in enumerate(((0, 1, "top view"), (0, 2, "side view"))):
        ax = fig.add_subplot(gs[row, 0])
        for (name, r), st in zip(runs.items(), styles, strict=False):
            ax.plot(r["tip"][k, :, i] * 1e3, r["tip"][k, :, j] * 1e3, label=name, **st)
        ax.plot(*start[[i, j]], "o", color="k", ms=7, label="start")
        ax.plot(*goal[[i, j]], "*", color="tab:green", ms=16, label="goal")
        ax.set(xlabel=f"{'xyz'[i]} [mm]", ylabel=f"{'xyz'[j]} [mm]", title=f"tip path, {view}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        if row == 0:
            ax.legend(fontsize=8, loc="best")
    ax = fig.add_subplot(gs[0, 1])
    for (name, r), st in zip(runs.items(), styles, strict=False):
        t = np.arange(1, r["dist"].shape[1] + 1) * dt
        ax.semilogy(t, np.maximum(r["dist"][k] * 1e3, 1e-10), label=name, **st)
    ax.axhline(1.0, color="gray", ls=":", lw=1)
    ax.text(0.2, 1.2, "1 mm", color="gray", fontsize=8)
    ax.set(xlabel="time [s]", ylabel="tip error [mm]", title="distance to the goal")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[1, 1])
    N = robot.n_tubes
    scale = np.asarray(robot.action_scale)
    t = np.arange(1, first["tau"].shape[1] + 1) * dt
    for c in range(2 * N):
        kind = "force on carriage" if c < N else "torque on rotation stage"
        ax.plot(t, first["tau"][k, :, c] / scale[c], lw=1.5,
                label=f"{kind} {c % N + 1} (full scale {scale[c]:.3g} "
                      f"{'N' if c < N else 'N·m'})")
    ax.set(xlabel="time [s]", ylabel="command / full scale", ylim=(-1.05, 1.05),
           title=f"actuator commands: {next(iter(runs))}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Torque-controlled reaching, {robot.name}: seeded goal {k + 1} "
                 f"(the first goal of the set that the first policy reaches within 1 mm)",
                 fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(prog="python -m training.demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", action="append", default=None,
                   help="a policy .zip (repeatable; default the shipped model-free and "
                        "residual agents)")
    p.add_argument("--goals", type=int, default=20)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("-o", "--output-dir", default="demo_out")
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    import envs
    from training.controllers import OperationalSpaceController, PlanThenServoController
    from training.evaluate import load_policy, policy_env, rollout, summarize

    out = Path(args.output_dir)
    venv = envs.CTRReachVecEnv(args.goals, control="force")
    # each policy on the action convention it was trained on (the same seeded goals: the
    # action options do not change how starts and goals are drawn)
    policies: dict[str, tuple] = {}
    for path in args.policy or [str(p) for p in DEFAULT_POLICIES]:
        if not Path(path).exists():
            print(f"no policy at {path}: skipped (train one: docs/training.md)")
            continue
        meta = Path(path).with_suffix(".json")
        info = json.loads(meta.read_text()) if meta.exists() else {}
        residual, algo = info.get("residual"), str(info.get("algo", "agent")).upper()
        comp = bool((info.get("env_kwargs") or {}).get("compensation", False))
        label = (f"{algo} residual on {residual.get('base', 'osc').upper()}" if residual
                 else f"{algo}+HER, model-free" + (" (compensated)" if comp else ""))
        try:
            # the options that shape its actions and observation (compensation,
            # observe_stiffness, ...) from its .json, as training.evaluate does
            own = policy_env(path, args.goals)[0] if meta.exists() else venv
            policies[label] = (load_policy(path, own), own)
        except ValueError as e:  # e.g. trained on an older observation layout
            print(f"cannot load {path} ({str(e).splitlines()[0][:200]}): skipped")
    if not policies:
        print("no shipped policy loaded: demo of the model-based controllers only")
    policies["plan-then-servo"] = (PlanThenServoController(venv), venv)
    policies["operational-space controller"] = (OperationalSpaceController(venv), venv)
    print(f"torque-controlled reaching, {venv.robot.name}: actions are actuator forces "
          f"(+-{venv.robot.force_scale} N) and torques (+-{venv.robot.torque_scale} N·m); "
          f"{args.goals} seeded goals, 100 steps of 0.1 s")
    for name, (pol, env) in policies.items():
        s = summarize(rollout(pol, env, args.goals, seed=args.seed, progress=False))
        print(f"  {name:>30s}: success@1mm {s['success@1mm']:.2f}, @5mm {s['success@5mm']:.2f}, "
              f"median final error {s['median_error_mm']:.3g} mm, snaps {s['snap_rate']:.2f}")
    # The figure: every policy on the same seeded goals; the first goal the first policy
    # reaches (episode 0 if it reaches none) is drawn, with its tip error and commands.
    runs = {name: _episodes(pol, env, args.seed) for name, (pol, env) in policies.items()}
    first = next(iter(runs.values()))
    hits = np.flatnonzero(first["dist"][:, -1] <= 1e-3)
    k = int(hits[0]) if len(hits) else 0
    _figure(runs, k, venv.robot, out / "reach.png", venv.carriage.control_period)
    print(f"saved {out / 'reach.png'} (goal {k + 1} of {args.goals}; final errors: "
          + ", ".join(f"{n} {r['dist'][k, -1] * 1e3:.3g} mm" for n, r in runs.items()) + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
