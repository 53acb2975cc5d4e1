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

``--torch-solver`` adds, beside each batched env, the same env on ``torchpvs.solve``
(``solver="torch"``: every equilibrium through the full solver, as before the compiled env
solver) and the ratio, measured side by side on the same actions.

``--breakdown`` instead splits one batched force-env step (``CTRReachVecEnv``, the largest of
``--batches``) into its stages, from a ``cProfile`` of ``--steps`` steps: the solves, the
actuator stiffness (for the linearly implicit step and the substep count), the stability
margin, and within the solves the fused path (torchpvs/fused.py), the layout, the maps, the
compiled Newton and pose calls and the forces (the last ones where the fused path declines).
The profiler's per-call cost inflates the Python-heavy stages, so read the shares, not the
absolute times (which the table mode gives without a profiler)::

    python benchmarks/bench_env.py --breakdown --batches 64 --steps 30
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


def bench_batched(robot: str, control: str, B: int, n_steps: int, solver: str = "auto"):
    import envs
    venv = envs.CTRReachVecEnv(B, robot=robot, control=control, solver=solver)
    venv.seed(0)
    venv.reset()
    rng = np.random.default_rng(0)
    substeps = []

    def step(a):
        _, _, _, infos = venv.step(a)
        substeps.append(np.mean([i.get("substeps", 1) for i in infos]))
    rate, ms = _time_steps(step, n_steps, B, (B, venv.action_space.shape[0]), rng)
    return rate, ms, float(np.mean(substeps))


def warmed_env(B: int, **kwargs):
    """``(venv, rng, action shape)``: a seeded, reset ``envs.CTRReachVecEnv(B, **kwargs)``
    after three steps of seeded random actions (the first steps' one-off costs left out)."""
    import envs
    venv = envs.CTRReachVecEnv(B, **kwargs)
    venv.seed(0)
    venv.reset()
    rng = np.random.default_rng(0)
    shape = (B, venv.action_space.shape[0])
    for _ in range(3):
        venv.step(rng.uniform(-1, 1, shape).astype(np.float32))
    return venv, rng, shape


# (label, module, qualified name) of the stages --breakdown reports, outermost first, for each
# env solver (envs.plant.SOLVERS): torchpvs' solve, and the compiled warm solve
_STEP = (("step (all)", "envs.dynamics", "RobotBatch.step_force"),
         ("  solves", "envs.plant", "Plants.warm"))
_ENV = (("  substep count", "envs.dynamics", "RobotBatch.n_substeps"),
        ("  contact", "envs.dynamics", "RobotBatch._contact"))
_STAGES = {
    "torch": _STEP + (
        ("    fused path (two compiled calls)", "torchpvs.fused", "fused_solve"),
        ("    layout + maps, compiled", "torchpvs.compiled_layout", "layout_and_maps"),
        ("    layout (eager build_layout)", "torchpvs.sections", "build_layout"),
        ("    maps (eager build_maps)", "torchpvs.mechanics", "build_maps"),
        ("    compiled Newton", "torchpvs.compiled", "solve"),
        ("    compiled pose", "torchpvs.compiled", "pose"),
        ("    actuation forces", "torchpvs.forces", "equilibrium_forces"),
        ("    order estimate", "torchpvs.order_control", "order_estimate"),
        ("  actuator stiffness", "torchpvs.jacobians", "actuator_stiffness"),
        ("    its factorization", "torchpvs.implicit", "adjoint_factor"),
        ("  stability margin", "torchpvs.equilibrium", "Equilibrium.min_stiffness_eigenvalue"),
    ) + _ENV,
    "auto": _STEP + (
        ("    one compiled call each", "torchpvs.tracker", "Tracker._run"),
        ("  actuator stiffness (its rows)", "envs.dynamics", "RobotBatch._stiffness_of"),
    ) + _ENV,
}


def breakdown(robot: str, B: int, n_steps: int, solver: str = "auto") -> None:
    """Print the share of a batched force-env step spent in each of :data:`_STAGES` of the
    env solver ``solver`` (the compiled one computes the forces, the margin and the stiffness
    inside its one call per solve)."""
    import cProfile
    import importlib
    import inspect
    import pstats

    venv, rng, shape = warmed_env(B, robot=robot, solver=solver)
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(n_steps):
        venv.step(rng.uniform(-1, 1, shape).astype(np.float32))
    prof.disable()
    stats = pstats.Stats(prof).stats       # (file, line, name) -> (cc, nc, tt, ct, callers)
    rows = []
    for label, module, qual in _STAGES[solver]:
        obj = importlib.import_module(module)
        for part in qual.split("."):
            obj = getattr(obj, part)
        fn = obj.fget if isinstance(obj, property) else obj
        code = inspect.unwrap(fn).__code__
        key = (code.co_filename, code.co_firstlineno, code.co_name)
        calls, cum = (stats[key][1], stats[key][3]) if key in stats else (0, 0.0)
        rows.append((label, calls, cum))
    total = rows[0][2]
    print(f"force env, B = {B}, solver {solver!r}, {n_steps} profiled steps: "
          f"{1e3 * total / n_steps:.1f} ms per step under the profiler")
    print(f"{'stage':<30}{'calls/step':>11}{'ms/step':>9}{'share':>8}")
    for label, calls, cum in rows:
        print(f"{label:<30}{calls / n_steps:>11.2f}{1e3 * cum / n_steps:>9.2f}"
              f"{cum / total:>8.0%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="fig3_two_tube")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--steps", type=int, default=40, help="timed step calls per configuration")
    ap.add_argument("--dummy", type=int, default=16,
                    help="B of the DummyVecEnv comparison (0: none)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--breakdown", action="store_true",
                    help="split one force-env step into its stages instead (see above)")
    ap.add_argument("--solver", default="auto", choices=("auto", "torch"),
                    help="--breakdown: the env solver to profile (envs.plant.SOLVERS)")
    ap.add_argument("--torch-solver", action="store_true",
                    help="also time each batched env on torchpvs' solve (solver='torch'), "
                         "side by side, and print the compiled env solver's ratio")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.breakdown:
        breakdown(args.robot, args.batches[-1], args.steps, args.solver)
        return
    print(f"robot {args.robot}, torch {torch.__version__}, {args.threads} thread(s), "
          f"{args.steps} timed steps per row")
    print(f"{'env':<34}{'B':>5}{'robot-steps/s':>15}{'ms/step call':>14}{'substeps':>10}")
    for control in ("force", "joint"):
        rate1, ms1 = bench_single(args.robot, control, args.steps)
        print(f"{'gym.make single (' + control + ')':<34}{1:>5}{rate1:>15.1f}{ms1:>14.2f}"
              f"{'':>10}")
        if args.dummy > 0:       # (--dummy 0: no DummyVecEnv row)
            rated, msd = bench_dummy(args.robot, control, args.dummy, max(5, args.steps // 4))
            print(f"{'DummyVecEnv (' + control + ')':<34}{args.dummy:>5}{rated:>15.1f}"
                  f"{msd:>14.2f}{'':>10}")
        for B in args.batches:
            if args.torch_solver:
                rate_t, ms_t, sub_t = bench_batched(args.robot, control, B, args.steps, "torch")
                print(f"{'CTRReachVecEnv (' + control + ', torch solver)':<34}{B:>5}"
                      f"{rate_t:>15.1f}{ms_t:>14.2f}{sub_t:>10.2f}")
            rate, ms, sub = bench_batched(args.robot, control, B, args.steps)
            print(f"{'CTRReachVecEnv (' + control + ')':<34}{B:>5}{rate:>15.1f}{ms:>14.2f}"
                  f"{sub:>10.2f}")
            if args.torch_solver:
                print(f"{'':<34}{'':>5}  compiled env solver / torch solver at B={B}: "
                      f"{rate / rate_t:.2f}x")
            if B == args.dummy:
                print(f"{'':<34}{'':>5}  batched / DummyVecEnv at B={B}: {rate / rated:.1f}x")
        print(f"{'':<34}{'':>5}  batched at B={args.batches[-1]} / single env: "
              f"{rate / rate1:.1f}x")


if __name__ == "__main__":
    main()
