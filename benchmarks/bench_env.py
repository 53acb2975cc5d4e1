"""Environment throughput: robot-steps per second of the reaching envs.

Times, side by side in one run and on the same seeded random actions,

* the single Gymnasium env (``gymnasium.make``, force and joint actions),
* SB3's ``DummyVecEnv`` of ``B`` single envs (``B`` sequential solves per step),
* the natively batched ``CTRReachVecEnv`` (one batched solve per substep) for ``B`` in
  ``--batches``,

and prints robot-steps/s, ms per ``step`` call, mean substeps, and the batched/sequential ratio.
Episodes auto-reset as in training (reset cost included). Usage::

    python benchmarks/bench_env.py [--robot fig3_two_tube] [--batches 1 16 64] [--steps 40]
                                   [--threads 1]

One torch thread is the default because it is what training uses (2 threads on a 2-core
machine contend with the learner).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def _time_steps(step, n_steps: int, n_robots: int, action_shape, rng, warmup: int = 3):
    for _ in range(warmup):
        step(rng.uniform(-1, 1, action_shape).astype(np.float32))
    t0 = time.perf_counter()
    for _ in range(n_steps):
        step(rng.uniform(-1, 1, action_shape).astype(np.float32))
    dt = time.perf_counter() - t0
    return n_steps * n_robots / dt, 1e3 * dt / n_steps


def bench_single(robot: str, control: str, n_steps: int):
    import gymnasium as gym

    import envs
    env_id = {v: k for k, v in envs.ENV_IDS.items()}[control]
    env = gym.make(env_id, robot=robot)
    env.reset(seed=0)
    rng = np.random.default_rng(0)

    def step(a):
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return _time_steps(step, n_steps, 1, env.action_space.shape, rng)


def bench_dummy(robot: str, control: str, B: int, n_steps: int):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    import envs
    env_id = {v: k for k, v in envs.ENV_IDS.items()}[control]
    venv = DummyVecEnv([lambda: gym.make(env_id, robot=robot) for _ in range(B)])
    venv.seed(0)
    venv.reset()
    rng = np.random.default_rng(0)
    return _time_steps(venv.step, n_steps, B, (B, venv.action_space.shape[0]), rng)


def bench_batched(robot: str, control: str, B: int, n_steps: int):
    import envs
    venv = envs.CTRReachVecEnv(B, robot=robot, control=control)
    venv.seed(0)
    venv.reset()
    rng = np.random.default_rng(0)
    substeps = []

    def step(a):
        _, _, _, infos = venv.step(a)
        substeps.append(np.mean([i.get("substeps", 1) for i in infos]))
    rate, ms = _time_steps(step, n_steps, B, (B, venv.action_space.shape[0]), rng)
    return rate, ms, float(np.mean(substeps))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="fig3_two_tube")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--steps", type=int, default=40, help="timed step calls per configuration")
    ap.add_argument("--dummy", type=int, default=16, help="B of the DummyVecEnv comparison")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"robot {args.robot}, torch {torch.__version__}, {args.threads} thread(s), "
          f"{args.steps} timed steps per row")
    print(f"{'env':<34}{'B':>5}{'robot-steps/s':>15}{'ms/step call':>14}{'substeps':>10}")
    for control in ("force", "joint"):
        rate1, ms1 = bench_single(args.robot, control, args.steps)
        print(f"{'gym.make single (' + control + ')':<34}{1:>5}{rate1:>15.1f}{ms1:>14.2f}"
              f"{'':>10}")
        rated, msd = bench_dummy(args.robot, control, args.dummy, max(5, args.steps // 4))
        print(f"{'DummyVecEnv (' + control + ')':<34}{args.dummy:>5}{rated:>15.1f}{msd:>14.2f}"
              f"{'':>10}")
        for B in args.batches:
            rate, ms, sub = bench_batched(args.robot, control, B, args.steps)
            print(f"{'CTRReachVecEnv (' + control + ')':<34}{B:>5}{rate:>15.1f}{ms:>14.2f}"
                  f"{sub:>10.2f}")
            if B == args.dummy:
                print(f"{'':<34}{'':>5}  batched / DummyVecEnv at B={B}: {rate / rated:.1f}x")
        print(f"{'':<34}{'':>5}  batched at B={args.batches[-1]} / single env: "
              f"{rate / rate1:.1f}x")


if __name__ == "__main__":
    main()
