"""Two checkouts of torchpvs side by side: the default (compiled) solve of each, rounds alternating.

    python benchmarks/compare_checkouts.py OLD_TREE NEW_TREE [--rounds 3]

e.g. ``git worktree add /tmp/old <commit>`` then
``python benchmarks/compare_checkouts.py /tmp/old .``. Each round runs this script's probe in a
fresh process per checkout (``PYTHONPATH=<tree>``, one torch thread), old then new: Fig. 3 and
the three-tube robot, 32 configurations (the last tube's rotation over [0, 250] deg), B = 1
warm from the equilibrium 1 deg away, warm from the equilibrium 0.1 mm away in the last
tube's insertion (every call at new insertions) and cold, the control step
(``solve(...).jacobians(compliance=False)``, 8 configurations), ``Tracker`` steps of 1 deg
(B = 1: the step, the control step ``jacobians=True`` and ``stiffness=True``, what the
environments take each substep), the kernel's tip partials
alone (``Kernel.tip_partials`` on a solve's layout, B = 1, where both trees have them) and
B = 1024 warm; each figure the best of 5 passes, in ms per solve (per call). ``--loaded``
adds the same cases for ``fig3_loaded``, the Fig. 3 robot under a dead tip force of 0.3 N
(``benchmarks/compiled_kernel.py``'s, the most a robust plant carries). With ``--envs``
also the force environment at B = 64 and the robust one (``CTRReachForceRobust-v0``: a tip
force and perturbed tubes on every plant) at B = 16, seeded random actions, best of 5 x 8
steps, in ms per robot-step (``--envs-only``: those alone). Printed: every round, then the
best over rounds and the ratio old / new. A change's speed-up is measured as a ratio in one
run, never against a figure from another day.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path


def env_probe(out: dict) -> None:
    """ms per robot-step of the force env at B = 64 and the robust env at B = 16."""
    import numpy as np
    from bench_env import warmed_env  # a sibling script

    import envs
    for label, env_id, B in (("force env B64", "torchpvs/CTRReachForce-v0", 64),
                             ("robust env B16", "torchpvs/CTRReachForceRobust-v0", 16)):
        venv, rng, shape = warmed_env(B, **envs.env_kwargs(env_id))
        best = math.inf
        for _ in range(5):
            t = time.perf_counter()
            for _ in range(8):
                venv.step(rng.uniform(-1, 1, shape).astype(np.float32))
            best = min(best, time.perf_counter() - t)
        out[f"{label} (per robot-step)"] = best / (8 * B) * 1e3


def probe(with_envs: bool = False, solves: bool = True, loaded: bool = False) -> dict:
    import numpy as np
    import torch
    torch.set_num_threads(1)
    import torchpvs
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from fast_path import bench_scene  # a sibling script: the benchmark robots
    opts = torchpvs.SolverOptions()
    out = {}
    names = ("fig3", "three_tube") + (("fig3_loaded",) if loaded else ())
    for name in names if solves else ():
        sc = (bench_scene("fig3").with_load(tip_force=[0.2, -0.2, 0.1]) if name == "fig3_loaded"
              else bench_scene(name))
        N, n = len(sc.tubes), 32
        rot = torch.zeros(n, N, dtype=torch.float64)
        rot[:, -1] = torch.tensor(np.radians(np.linspace(0, 250, n)))
        ins = torch.tensor(sc.actuation.insertion, dtype=torch.float64).expand(n, N).contiguous()
        prev = [torchpvs.solve(sc, insertion=ins[i:i + 1], rotation=rot[i:i + 1] - math.radians(1),
                               options=opts) for i in range(n)]

        def warm():
            for i in range(n):
                torchpvs.solve(sc, insertion=ins[i:i + 1], rotation=rot[i:i + 1],
                               initial=prev[i], options=opts)

        # insertion steps: each configuration's last tube 0.1 mm further in than its warm
        # start, every call at insertions the call before did not have (no kept layout)
        ins_s = ins.clone()
        ins_s[:, -1] -= 1e-4 * torch.arange(1, n + 1, dtype=torch.float64)
        prev_s = [torchpvs.solve(sc, insertion=ins_s[i:i + 1] - torch.tensor([0.0] * (N - 1)
                                                                               + [1e-4]),
                                 rotation=rot[i:i + 1], options=opts) for i in range(n)]

        def warm_insertion():
            for i in range(n):
                torchpvs.solve(sc, insertion=ins_s[i:i + 1], rotation=rot[i:i + 1],
                               initial=prev_s[i], options=opts)

        def cold():
            for i in range(n):
                torchpvs.solve(sc, insertion=ins[i:i + 1], rotation=rot[i:i + 1], options=opts)

        def control():
            for i in range(8):
                torchpvs.solve(sc, insertion=ins[i:i + 1], rotation=rot[i:i + 1],
                               initial=prev[i], options=opts).jacobians(compliance=False)

        ins_b, rot_b = ins.repeat(32, 1), rot.repeat(32, 1)
        prev_b = torchpvs.solve(sc, insertion=ins_b, rotation=rot_b - math.radians(1),
                                options=opts)

        def warm_b():
            torchpvs.solve(sc, insertion=ins_b, rotation=rot_b, initial=prev_b, options=opts)

        cases = [("B1 warm", warm, n), ("B1 warm insertion step", warm_insertion, n),
                 ("B1 cold", cold, n), ("control step", control, 8),
                 ("B1024 warm", warm_b, 1024)]
        if name != "fig3_loaded" and hasattr(torchpvs, "Tracker"):
            # the control loop: Tracker steps of 1 deg in the last tube's rotation, B = 1,
            # walking 0 -> 150 deg (on one branch: the Fig. 3 robot is bistable above ~180)
            # and starting over
            tr = torchpvs.Tracker(sc, insertion=ins[:1], rotation=rot[:1])
            last = torch.zeros(1, N, dtype=torch.float64)
            last[0, -1] = 1.0
            path = [(rot[:1] + math.radians(k) * last).numpy() for k in range(151)]
            D1 = ins[:1].numpy()
            where = [0]

            def tracker_steps(**kw):
                def run():
                    for _ in range(n):
                        k = where[0] % 150
                        if k == 0:
                            tr.restore(start)
                        tr.step(D1, path[k + 1], **kw)
                        where[0] += 1
                return run

            start = tr.snapshot()
            cases += [("Tracker.step", tracker_steps(), n),
                      ("Tracker control step", tracker_steps(jacobians=True), n),
                      ("Tracker step + stiffness", tracker_steps(stiffness=True), n)]
        from torchpvs.kernel import KERNELS
        eq = prev[0]
        ctx, info = eq.context, eq.context.implicit
        kernel = KERNELS[ctx.options.kernel]
        if hasattr(kernel, "tip_partials"):       # trees before the seam field lack it
            lay = ctx.plan.reused_layout(ctx.tubes, ctx.insertion, ctx.rotation, info.loaded,
                                         info.disc)
            args = (eq.q, ctx.tubes, ctx.insertion, ctx.rotation, info.loaded, info.tab,
                    info.disc, lay)

            def tip_partials():
                for _ in range(8):
                    kernel.tip_partials(*args)
            cases.append(("tip partials", tip_partials, 8))
        for key, fn, count in cases:
            fn()
            best = math.inf
            for _ in range(5):
                t = time.perf_counter()
                fn()
                best = min(best, time.perf_counter() - t)
            out[f"{name}: {key}"] = best / count * 1e3
    if with_envs:
        env_probe(out)
    return out


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--probe":
        print(json.dumps(probe(with_envs="--envs" in sys.argv or "--envs-only" in sys.argv,
                               solves="--envs-only" not in sys.argv,
                               loaded="--loaded" in sys.argv)))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--envs", action="store_true",
                    help="also the force env (B = 64) and the robust env (B = 16)")
    ap.add_argument("--envs-only", action="store_true", help="the two environments alone")
    ap.add_argument("--loaded", action="store_true",
                    help="also the Fig. 3 robot under a 0.3 N dead tip force (fig3_loaded)")
    args = ap.parse_args()
    trees = {"old": Path(args.old).resolve(), "new": Path(args.new).resolve()}
    for tag, tree in trees.items():
        if not (tree / "torchpvs" / "__init__.py").is_file():
            raise SystemExit(f"{tag}: {tree} holds no torchpvs/ package")
    best: dict[str, dict[str, float]] = {"old": {}, "new": {}}
    for r in range(args.rounds):
        for tag, tree in trees.items():
            env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
            res = json.loads(subprocess.run(
                [sys.executable, __file__, "--probe"] + (["--envs"] if args.envs else [])
                + (["--envs-only"] if args.envs_only else [])
                + (["--loaded"] if args.loaded else []),
                env=env, check=True, text=True,
                capture_output=True, cwd=tree).stdout.splitlines()[-1])
            print(f"round {r + 1} {tag}: " + ", ".join(f"{k} {v:.3f}" for k, v in res.items()),
                  flush=True)
            for k, v in res.items():
                best[tag][k] = min(v, best[tag].get(k, math.inf))
    print(f"\nms per solve, best of {args.rounds} rounds: old / new (old/new)")
    for k in best["old"]:
        if k not in best["new"]:
            continue
        o, n = best["old"][k], best["new"][k]
        print(f"  {k:<34} {o:8.3f} / {n:8.3f}  ({o / n:.2f}x)")


if __name__ == "__main__":
    main()
