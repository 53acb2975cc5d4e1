"""The compiled kernel against the eager one, side by side in one process.

    python benchmarks/compiled_kernel.py [--robots fig3 three_tube fig3_loaded] [--configs 32]
                                         [--batches 1 64 1024] [--repeat 3] [--env-steps 20]
                                         [--first-use] [--json out.json]

Per robot (the paper's Fig. 3 scene, the three-tube preset, and ``fig3_loaded``: the Fig. 3 scene
under a dead tip force of 0.3 N, the load the robust environment's plants carry at most),
``--configs`` configurations
(the last tube's rotation over [0, 250] deg), one torch thread, default options except the
kernel (``SolverOptions(kernel="newton")``, the eager reference, against ``"compiled"``):

* B = 1 warm (each configuration from the equilibrium 1 deg away: a control step) and cold;
* B = 64 and B = 1024 (the configurations tiled), warm and cold, per solve;
* the force environment at B = 64 and the robust one (``CTRReachForceRobust-v0``: every plant
  carries a tip force) at B = 16 (robot-steps/s, random actions).

Rounds alternate the kernels (eager, compiled, eager, ...) and each figure is the best of
``--repeat``: ratios are measured side by side. Printed: ms per solve for both, their ratio,
and the largest tip and force differences and whether the iteration counts are equal.
``--first-use``: also the cost of the first compiled solve in a fresh process with an empty
numba cache (compilation), and with the cache warm (the cost every later process pays).

``--ablate FIELD [FIELD ...]``: what one compiled function buys. A third kernel joins the
rounds, the compiled one with those :class:`torchpvs.kernel.Kernel` fields set back to the
eager functions (registered for this process only as ``"compiled-without-..."``), and its
times are printed beside the compiled kernel's, e.g. the compiled layout and maps in the
environments, where every step moves the carriages::

    python benchmarks/compiled_kernel.py --robots fig3 --batches 64 --ablate layout
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch
from fast_path import bench_scene, best_time  # a sibling script (run from benchmarks/)

import torchpvs

KERNELS = ["newton", "compiled"]       # (extended by --ablate)


def register_ablation(fields) -> str:
    """Register the compiled kernel with ``fields`` set back to the eager functions (in this
    process's :data:`torchpvs.kernel.KERNELS`); its name, appended to :data:`KERNELS`."""
    from torchpvs import kernel
    bad = [f for f in fields if f not in kernel.Kernel._fields]
    if bad:
        raise SystemExit(f"--ablate: {bad} are not Kernel fields {kernel.Kernel._fields}")
    name = "compiled-without-" + "+".join(fields)
    kernel.KERNELS[name] = kernel.COMPILED._replace(
        **{f: getattr(kernel.EAGER, f) for f in fields})
    KERNELS.append(name)
    return name


def _configs(scene, n: int, B: int):
    N = len(scene.tubes)
    rot = torch.zeros(n, N, dtype=torch.float64)
    rot[:, -1] = torch.tensor(np.radians(np.linspace(0.0, 250.0, n)))
    reps = max(1, B // n)
    rot = rot.repeat(reps, 1)[:B]
    ins = torch.tensor(scene.actuation.insertion, dtype=torch.float64).expand(rot.shape[0], N)
    return ins.contiguous(), rot


TIP_FORCE = [0.2, -0.2, 0.1]      # [N], 0.3 N


def _scene(name: str):
    if name == "fig3_loaded":
        return bench_scene("fig3").with_load(tip_force=TIP_FORCE)
    return bench_scene(name)


def bench_robot(name: str, configs: int, repeat: int, batches=(1, 64, 1024)) -> dict:
    scene = _scene(name)
    out = {"robot": name, "batches": list(batches)}
    for B in batches:
        ins, rot = _configs(scene, configs, configs if B == 1 else B)
        opts = {k: torchpvs.SolverOptions(kernel=k) for k in KERNELS}
        step = math.radians(1.0)
        if B == 1:
            prev = {k: [torchpvs.solve(scene, insertion=ins[i:i + 1],
                                       rotation=rot[i:i + 1] - step, options=opts[k])
                        for i in range(configs)] for k in KERNELS}

            def warm(k):
                for i in range(configs):
                    torchpvs.solve(scene, insertion=ins[i:i + 1], rotation=rot[i:i + 1],
                                   initial=prev[k][i], options=opts[k])

            def cold(k):
                for i in range(configs):
                    torchpvs.solve(scene, insertion=ins[i:i + 1], rotation=rot[i:i + 1],
                                   options=opts[k])
            n_solves = configs
        else:
            prev = {k: torchpvs.solve(scene, insertion=ins, rotation=rot - step,
                                      options=opts[k]) for k in KERNELS}

            def warm(k):
                torchpvs.solve(scene, insertion=ins, rotation=rot, initial=prev[k],
                               options=opts[k])

            def cold(k):
                torchpvs.solve(scene, insertion=ins, rotation=rot, options=opts[k])
            n_solves = B
        for case, fn in (("warm", warm), ("cold", cold)):
            t = {k: math.inf for k in KERNELS}
            for _ in range(repeat):
                for k in KERNELS:
                    t[k] = min(t[k], best_time(lambda k=k: fn(k), 1))
            out[f"B{B}_{case}"] = {k: t[k] / n_solves * 1e3 for k in KERNELS}
        a, b = (torchpvs.solve(scene, insertion=ins, rotation=rot, options=opts[k])
                for k in KERNELS[:2])
        out[f"B{B}_agreement"] = {
            "tip_m": float((a.tip_position - b.tip_position).abs().max()),
            "force": float((a.actuation_forces - b.actuation_forces).nan_to_num().abs().max()),
            "same_iterations": bool(torch.equal(a.iterations, b.iterations)),
            "same_stability": bool(torch.equal(a.stable, b.stable))}
    return out


def bench_env(steps: int, B: int = 64, env_id: str | None = None) -> dict:
    import envs
    import envs.plant as plant
    import envs.robots as robots
    base = robots.ENV_SOLVER_OPTIONS
    kwargs = envs.env_kwargs(env_id) if env_id else {"control": "force"}
    rates = {}
    try:
        for k in KERNELS:
            # (the plant module holds its own reference: the robust env's perturbed plants)
            robots.ENV_SOLVER_OPTIONS = plant.ENV_SOLVER_OPTIONS = dataclasses.replace(
                base, kernel=k)
            venv = envs.CTRReachVecEnv(B, robot="fig3_two_tube", **kwargs)
            venv.seed(0)
            venv.reset()
            rng = np.random.default_rng(0)
            acts = rng.uniform(-1, 1, (steps + 3, B, venv.action_space.shape[0]))
            for a in acts[:3]:
                venv.step(a)
            t0 = time.perf_counter()
            for a in acts[3:]:
                venv.step(a)
            rates[k] = steps * B / (time.perf_counter() - t0)
    finally:
        robots.ENV_SOLVER_OPTIONS = plant.ENV_SOLVER_OPTIONS = base
    return rates


def _ablated_rate(rates: dict, ablated: str | None) -> str:
    if not ablated:
        return ""
    return (f"; {ablated} {rates[ablated]:.0f} (compiled / it: "
            f"{rates['compiled'] / rates[ablated]:.2f}x)")


_FIRST = ("import time; t = time.perf_counter(); import torchpvs; "
          "torchpvs.solve(torchpvs.load_scene('renda2021_fig3'), "
          "options=torchpvs.SolverOptions(kernel='compiled')); "
          "print(time.perf_counter() - t)")


def first_use() -> dict:
    """[s] import + first compiled solve in a fresh process: empty numba cache, then warm."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, OMP_NUM_THREADS="1")
        runs = [float(subprocess.run([sys.executable, "-c", _FIRST], env=env, check=True,
                                     capture_output=True, text=True).stdout.split()[-1])
                for _ in range(2)]
    return {"empty_cache_s": runs[0], "warm_cache_s": runs[1]}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["fig3", "three_tube"])
    ap.add_argument("--configs", type=int, default=32)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--env-steps", type=int, default=20)
    ap.add_argument("--first-use", action="store_true")
    ap.add_argument("--ablate", nargs="+", default=None, metavar="FIELD",
                    help="also time the compiled kernel with these Kernel fields eager")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    ablated = register_ablation(args.ablate) if args.ablate else None
    results = {"robots": [bench_robot(r, args.configs, args.repeat, args.batches)
                          for r in args.robots]}
    for r in results["robots"]:
        print(f"\n{r['robot']}: ms per solve (best of {args.repeat}, alternating rounds)")
        extra = f"{'ablated':>10}{'ablated/compiled':>18}" if ablated else ""
        print(f"{'case':<14}{'eager':>10}{'compiled':>10}{'eager/compiled':>16}{extra}")
        for key, t in r.items():
            if isinstance(t, dict) and "newton" in t:
                extra = (f"{t[ablated]:>10.3f}{t[ablated] / t['compiled']:>17.2f}x"
                         if ablated else "")
                print(f"{key:<14}{t['newton']:>10.3f}{t['compiled']:>10.3f}"
                      f"{t['newton'] / t['compiled']:>15.2f}x{extra}")
        for B in r["batches"]:
            print(f"B = {B} agreement: {r[f'B{B}_agreement']}")
    if args.env_steps:
        rates = bench_env(args.env_steps)
        results["env_B64_robot_steps_per_s"] = rates
        print(f"\nforce env, B = 64: eager {rates['newton']:.0f}, compiled "
              f"{rates['compiled']:.0f} robot-steps/s ({rates['compiled'] / rates['newton']:.2f}x)"
              + _ablated_rate(rates, ablated))
        rates = bench_env(max(1, args.env_steps // 2), 16, "torchpvs/CTRReachForceRobust-v0")
        results["robust_env_B16_robot_steps_per_s"] = rates
        print(f"robust env (tip-loaded plants), B = 16: eager {rates['newton']:.0f}, compiled "
              f"{rates['compiled']:.0f} robot-steps/s ({rates['compiled'] / rates['newton']:.2f}x)"
              + _ablated_rate(rates, ablated))
    if args.first_use:
        results["first_use"] = first_use()
        print(f"first compiled solve in a fresh process: {results['first_use']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    main()
