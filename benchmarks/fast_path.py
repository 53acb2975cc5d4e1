"""Fast-path figures: PVS speed as ratios to the standard-model reference, measured in one run.

    python benchmarks/fast_path.py [--robots fig3 three_tube] [--configs 32] [--repeat 3]
                                   [--batches 1 64 1024] [--env] [--json out.json]

Workload (per robot): ``--configs`` configurations with the last tube's rotation spread over
[0, 250] deg (the rest as in the robot's scene), each solved WARM from the equilibrium 1 deg
away (a control step) or COLD (default initial guess); one torch thread. Reference:
``torchpvs.reference.solve_standard(tol=1e-6, compute_forces=False, compute_stability=False)``
warm from the neighbouring reference solution. PVS: default options (accuracy 1e-5 m, forces,
stability: what a user gets) and a fixed ``order=2, n_magnus=8`` solve, single calls (B = 1)
and one batched call per B (the configurations repeated). Printed: ms/solve, the ratio to the
reference, the cost of default options relative to order 2, torch ops and host syncs per call,
and (``--env``) the force environment's robot-steps/s at B = 64 against the reference's
solves/s. Timings are the best of ``--repeat`` runs. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings

import torch
from torch.utils._python_dispatch import TorchDispatchMode

import torchpvs
from torchpvs.reference import solve_standard

TARGETS = {"single_default": 10.0, "batch1024_warm_default": 200.0,
           "batch1024_cold_default": 100.0, "default_over_order2": 1.5, "env_over_ref": 20.0}


class _OpCounter(TorchDispatchMode):
    """Counts aten ops and host synchronisations (``item``/``bool``/``nonzero``)."""

    def __init__(self):
        super().__init__()
        self.ops = 0
        self.syncs = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        name = func.__name__
        if "_local_scalar_dense" in name or name.startswith("nonzero") or "is_nonzero" in name:
            self.syncs += 1
        return func(*args, **(kwargs or {}))


def best_time(fn, repeat: int) -> float:
    """[s] the best of ``repeat`` timed calls of ``fn`` after one untimed warm-up call."""
    fn()
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_scene(name: str):
    """The benchmark robots: ``"fig3"`` (the paper's Fig. 3 scene) or the three-tube preset."""
    if name == "fig3":
        return torchpvs.load_scene("renda2021_fig3")
    from envs.robots import rvim_three_tube
    return rvim_three_tube().scene


def bench_robot(name: str, configs: int, batches, repeat: int) -> dict:
    scene = bench_scene(name)
    N = scene.n_tubes
    step = math.radians(1.0)
    base = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    alphas = torch.linspace(0, math.radians(250), configs, dtype=torch.float64)
    rot0 = base.repeat(configs, 1)
    rot0[:, -1] = alphas - step
    rot1 = rot0.clone()
    rot1[:, -1] += step
    out = {"robot": name, "tubes": N}

    # Reference: follow the branch from the first configuration, warm.
    kw = dict(tol=1e-6, compute_forces=False, compute_stability=False)
    prev, ref0 = None, []
    for r in rot0:
        prev = solve_standard(scene.with_actuation(rotation=r.tolist()), initial=prev, **kw)
        ref0.append(prev)
    scenes1 = [scene.with_actuation(rotation=r.tolist()) for r in rot1]

    def ref_run():
        for s, p in zip(scenes1, ref0, strict=True):
            solve_standard(s, initial=p, **kw)

    t_ref = best_time(ref_run, repeat) / configs
    out["reference_ms"] = 1e3 * t_ref

    opts = {"default": torchpvs.SolverOptions(),
            "order2": torchpvs.SolverOptions(order=2, n_magnus=8)}
    for label, o in opts.items():
        prev, eq0 = None, []
        for r in rot0:
            prev = torchpvs.solve(scene, rotation=r[None], initial=prev, options=o)
            eq0.append(prev)

        def single():
            for r, e in zip(rot1, eq0, strict=True):
                torchpvs.solve(scene, rotation=r[None], initial=e, options=o)

        t1 = best_time(single, repeat) / configs
        out[f"single_{label}_ms"] = 1e3 * t1
        out[f"single_{label}_ratio"] = t_ref / t1
        for B in batches:
            reps = max(1, B // configs)
            R0, R1 = rot0.repeat(reps, 1)[:B], rot1.repeat(reps, 1)[:B]
            E0 = torchpvs.solve(scene, rotation=R0, options=o,
                                initial=torch.cat([e.q for e in eq0]).repeat(reps, 1)[:B]
                                if len({e.q.shape[-1] for e in eq0}) == 1 else None)
            Bn = R1.shape[0]
            tw = best_time(lambda: torchpvs.solve(scene, rotation=R1, initial=E0, options=o),
                       repeat) / Bn
            tc = best_time(lambda: torchpvs.solve(scene, rotation=R1, options=o), repeat) / Bn
            out[f"b{B}_warm_{label}_ms"] = 1e3 * tw
            out[f"b{B}_cold_{label}_ms"] = 1e3 * tc
            out[f"b{B}_warm_{label}_ratio"] = t_ref / tw
            out[f"b{B}_cold_{label}_ratio"] = t_ref / tc
            with _OpCounter() as c:
                torchpvs.solve(scene, rotation=R1, initial=E0, options=o)
            out[f"b{B}_warm_{label}_ops"] = c.ops
            out[f"b{B}_warm_{label}_syncs"] = c.syncs
    return out


def bench_env(t_ref_ms: float, repeat: int, steps: int = 20) -> dict:
    """The force env at B = 64 on its default (compiled) solver and on ``solver="torch"``
    (``torchpvs.solve`` for every equilibrium), the same actions, interleaved rounds."""
    import numpy as np

    from envs.vec_env import CTRReachVecEnv
    rng = np.random.default_rng(0)
    envs_ = {}
    for solver in ("auto", "torch"):
        env = CTRReachVecEnv(64, solver=solver)
        env.seed(0)
        env.reset()
        envs_[solver] = env
    acts = [rng.uniform(-1, 1, size=(64,) + envs_["auto"].action_space.shape)
            .astype(np.float32) for _ in range(steps)]

    def run(env):
        return lambda: [env.step(a) for a in acts]

    t = {s: float("inf") for s in envs_}
    for _ in range(repeat):          # interleaved: both see the same machine state
        for s, env in envs_.items():
            t[s] = min(t[s], best_time(run(env), 1) / (steps * 64))
    for env in envs_.values():
        env.close()
    return {"env_steps_per_s": 1.0 / t["auto"], "env_over_ref": (1.0 / t["auto"]) /
            (1e3 / t_ref_ms), "env_torch_steps_per_s": 1.0 / t["torch"],
            "env_threads": torch.get_num_threads()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["fig3", "three_tube"])
    ap.add_argument("--configs", type=int, default=32)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--env", action="store_true", help="also the force env's robot-steps/s")
    ap.add_argument("--env-threads", type=int, default=1,
                    help="torch threads for the env's timing (its compiled solves split the "
                         "batch across them; the solver figures stay on one thread)")
    ap.add_argument("--json", help="write the figures to this JSON file")
    ap.add_argument("--markdown", metavar="JSON",
                    help="print the markdown tables of a saved run (no measurement)")
    args = ap.parse_args(argv)
    if args.markdown:
        with open(args.markdown) as f:
            print(markdown(json.load(f)))
        return {}
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    results = []
    for name in args.robots:
        r = bench_robot(name, args.configs, args.batches, args.repeat)
        if args.env and name == "fig3":
            torch.set_num_threads(args.env_threads)
            r.update(bench_env(r["reference_ms"], args.repeat))
            torch.set_num_threads(1)
        results.append(r)
        _print(r, args.batches)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return {"results": results}


def _print(r: dict, batches) -> None:
    ref = r["reference_ms"]
    print(f"\n== {r['robot']} ({r['tubes']} tubes): reference warm {ref:.2f} ms/solve "
          f"({1e3 / ref:.0f} solves/s)")
    print(f"{'case':<26}{'default ms':>12}{'x ref':>9}{'order2 ms':>12}{'x ref':>9}"
          f"{'dflt/o2':>9}{'ops/call':>10}{'syncs':>7}")
    rows = [("single B=1 warm", "single_{}")] + [
        (f"batch B={B} {m}", f"b{B}_{m}_{{}}") for B in batches for m in ("warm", "cold")]
    for label, key in rows:
        d, o = r[key.format("default") + "_ms"], r[key.format("order2") + "_ms"]
        ops = r.get(key.format("default") + "_ops", "")
        syncs = r.get(key.format("default") + "_syncs", "")
        print(f"{label:<26}{d:>12.4f}{ref / d:>9.1f}{o:>12.4f}{ref / o:>9.1f}{d / o:>9.2f}"
              f"{ops!s:>10}{syncs!s:>7}")
    big = max(batches)
    print(f"ratios to the reference: single default {r['single_default_ratio']:.1f}x; "
          f"B={big} warm default {r[f'b{big}_warm_default_ratio']:.0f}x; "
          f"B={big} cold default {r[f'b{big}_cold_default_ratio']:.0f}x; "
          f"default/order-2 at B={big} warm "
          f"{r[f'b{big}_warm_default_ms'] / r[f'b{big}_warm_order2_ms']:.2f}")
    if "env_steps_per_s" in r:
        print(f"force env B=64: {r['env_steps_per_s']:.0f} robot-steps/s = "
              f"{r['env_over_ref']:.1f}x the reference's warm solves/s "
              f"({r['env_threads']} thread(s); target >= 10,000 on an idle 2-core machine: "
              f"{r['env_steps_per_s'] / 1e4:.2f}x of it); on solver='torch' "
              f"{r['env_torch_steps_per_s']:.0f} (the compiled env solver "
              f"{r['env_steps_per_s'] / r['env_torch_steps_per_s']:.2f}x)")


def markdown(results: list[dict]) -> str:
    """The tables of docs/performance.md and docs/results.md from saved results: every case,
    then the headline ratios."""
    out = ["| robot | case | default ms/solve | x reference | order 2 ms/solve | x reference "
           "| default / order 2 | torch ops per call |", "|---|---|---|---|---|---|---|---|"]
    ratios = ["| robot | headline figure | measured |", "|---|---|---|"]
    for r in results:
        batches = sorted({int(k[1:].split("_")[0]) for k in r if k[0] == "b" and k[1].isdigit()})
        ref = r["reference_ms"]
        name = f"{r['robot']} ({r['tubes']} tubes; reference {ref:.1f} ms warm)"
        rows = [("single call, warm", "single_{}")] + [
            (f"B = {B}, {m}", f"b{B}_{m}_{{}}") for B in batches for m in ("warm", "cold")]
        for label, key in rows:
            d, o = r[key.format("default") + "_ms"], r[key.format("order2") + "_ms"]
            ops = r.get(key.format("default") + "_ops", "")
            out.append(f"| {name} | {label} | {d:.3f} | {ref / d:.1f}x | {o:.3f} | "
                       f"{ref / o:.1f}x | {d / o:.2f} | {ops} |")
            name = ""
        big = max(batches)
        tr = [("single warm solve, default: x reference", f"{r['single_default_ratio']:.1f}x"),
              (f"B = {big} warm, default: x reference per solve",
               f"{r[f'b{big}_warm_default_ratio']:.0f}x"),
              (f"B = {big} cold, default: x reference per solve",
               f"{r[f'b{big}_cold_default_ratio']:.0f}x"),
              (f"default / order 2 (B = {big} warm)",
               f"{r[f'b{big}_warm_default_ms'] / r[f'b{big}_warm_order2_ms']:.2f}x")]
        if "env_steps_per_s" in r:
            tr.append(("force env B = 64: robot-steps/s, x the reference's warm solves/s",
                       f"{r['env_steps_per_s']:.0f} robot-steps/s = {r['env_over_ref']:.1f}x"))
        for i, (t, m) in enumerate(tr):
            ratios.append(f"| {r['robot'] if i == 0 else ''} | {t} | {m} |")
    return "\n".join(out) + "\n\n" + "\n".join(ratios)


if __name__ == "__main__":
    main()
