"""The README's main job: a torque-controlled reach with the shipped policy.

    python -m training.demo [--policy training/policies/sac_her_force.zip] [--goals 20]

Loads the shipped SAC+HER policy for the force/torque-action environment (the paper's Fig. 3
robot; a residual agent on the operational-space controller, see ``training/residual.py``),
evaluates it on seeded goals next to the model-based operational-space controller,
prints the success rates and final errors, and saves a rendered rollout (a strip of frames with
the actuator forces) to ``demo_out/rollout.png``. Without a policy file it demos the controller
alone and says so.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

DEFAULT_POLICY = Path(__file__).resolve().parent / "policies" / "sac_her_force.zip"


def _strip(frames: list[np.ndarray], path: Path, titles: list[str]) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3.2 * len(frames), 3.0))
    FigureCanvasAgg(fig)
    for k, (img, t) in enumerate(zip(frames, titles, strict=True)):
        ax = fig.add_subplot(1, len(frames), k + 1)
        ax.imshow(img)
        ax.set_title(t, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    import torch

    p = argparse.ArgumentParser(prog="python -m training.demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--policy", default=str(DEFAULT_POLICY))
    p.add_argument("--goals", type=int, default=20)
    p.add_argument("--seed", type=int, default=2026)
    p.add_argument("-o", "--output-dir", default="demo_out")
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    import envs
    from training.controllers import OperationalSpaceController
    from training.evaluate import load_policy, rollout, summarize

    out = Path(args.output_dir)
    venv = envs.CTRReachVecEnv(args.goals, control="force")
    policies = {}
    if Path(args.policy).exists():
        meta = Path(args.policy).with_suffix(".json")
        residual = meta.exists() and "residual" in json.loads(meta.read_text())
        label = "SAC+HER residual on OSC" if residual else "SAC+HER (force actions)"
        policies[label] = load_policy(args.policy, venv)
    else:
        print(f"no policy at {args.policy}: demo of the model-based controller only "
              f"(train one with: python -m training.train --config "
              f"training/configs/sac_her_force.yaml)")
    policies["operational-space controller"] = OperationalSpaceController(venv)
    print(f"torque-controlled reaching, {venv.robot.name}: actions are actuator forces "
          f"(+-{venv.robot.force_scale} N) and torques (+-{venv.robot.torque_scale} N·m); "
          f"{args.goals} seeded goals, 100 steps of 0.1 s")
    for name, pol in policies.items():
        s = summarize(rollout(pol, venv, args.goals, seed=args.seed, progress=False))
        print(f"  {name:>30s}: success@1mm {s['success@1mm']:.2f}, @5mm {s['success@5mm']:.2f}, "
              f"median final error {s['median_error_mm']:.3g} mm, snaps {s['snap_rate']:.2f}")
    # a rendered rollout of the first policy on one goal
    name, pol = next(iter(policies.items()))
    env1 = envs.CTRReachVecEnv(1, control="force", snap_mode="continue")
    env1.seed(args.seed)
    obs = env1.reset()
    from envs.render import ReachRenderer
    r = ReachRenderer(env1.robot)
    frames, titles = [r.draw(env1.task, 0)], ["t = 0 s"]
    if name.startswith("SAC"):
        pol = load_policy(args.policy, env1)
    else:
        pol = OperationalSpaceController(env1)
    for t in range(1, 61):
        obs, _, _, infos = env1.step(pol(obs))
        if t in (5, 15, 30, 60):
            frames.append(r.draw(env1.task, 0))
            titles.append(f"t = {t * 0.1:.1f} s, error {infos[0]['distance'] * 1e3:.2f} mm")
    _strip(frames, out / "rollout.png", titles)
    print(f"saved {out / 'rollout.png'} ({name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
