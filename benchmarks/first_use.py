"""First use: what numba's compiling costs a fresh process, for one or two checkouts at once.

    python benchmarks/first_use.py [CHECKOUT ...] [--profile] [--json out.json]

Each checkout (default: this one; e.g. an older tree from ``git worktree add /tmp/old REV``)
runs one fresh process with an empty numba cache (``NUMBA_CACHE_DIR`` a new temporary folder),
one torch thread, all of them at the same time (two checkouts on the two cores: side by side),
and times, one after the other in that process: the import, the first default
``torchpvs.solve`` of the Fig. 3 scene, its ``jacobians()`` (the default compliance re-solves
with the load's coordinates: the loaded Newton), then a force environment of 4 robots reset and
stepped 3 times (the tracker's compiled call). ``--profile``: also numba's compile events
(``numba.core.event``, kind ``numba:compile``): the slowest top-level compilations and every
function compiled for more than one signature (each one compiles its whole call tree again).
Not run in CI (minutes per checkout); docs/performance.md, *First use*, quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

_CHILD = r'''
import json, sys, time
t0 = time.perf_counter()
profile = sys.argv[1] == "1"
if profile:
    from collections import defaultdict
    from numba.core import event
    rec = event.RecordingListener()
    event.register("numba:compile", rec)
import numpy as np
import torch
torch.set_num_threads(1)
import torchpvs
out = {"import_s": time.perf_counter() - t0}
t = time.perf_counter()
eq = torchpvs.solve(torchpvs.load_scene("renda2021_fig3"))
out["first_solve_s"] = time.perf_counter() - t
t = time.perf_counter()
eq.jacobians()
out["jacobians_s"] = time.perf_counter() - t
import envs
t = time.perf_counter()
venv = envs.CTRReachVecEnv(4, robot="fig3_two_tube",
                           **envs.env_kwargs("torchpvs/CTRReachForce-v0"))
venv.seed(0)
venv.reset()
for _ in range(3):
    venv.step(np.zeros((4, 4)))
out["env_s"] = time.perf_counter() - t
out["total_s"] = time.perf_counter() - t0
if profile:
    starts, top, sigs, depth = {}, [], defaultdict(set), 0
    for ts, ev in rec.buffer:
        name = ev.data["dispatcher"].py_func.__qualname__
        key = (name, str(ev.data.get("args")))
        if ev.is_start:
            starts[key] = (ts, depth)
            depth += 1
            sigs[name].add(key[1])
        else:
            depth -= 1
            s, d = starts.pop(key)
            if d == 0:
                top.append((round(ts - s, 1), name))
    out["top_compiles"] = sorted(top, reverse=True)[:10]
    out["compiled_more_than_once"] = {k: len(v) for k, v in sigs.items()
                                      if len(v) > 1 and "<locals>" not in k}
print("RESULT " + json.dumps(out))
'''


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkouts", nargs="*", default=[str(Path(__file__).resolve().parents[1])])
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        procs = []
        for i, c in enumerate(args.checkouts):
            root = Path(c).resolve()
            if not (root / "torchpvs" / "__init__.py").is_file():
                ap.error(f"{c}: not a torchpvs checkout (no torchpvs/__init__.py)")
            cache = Path(tmp) / f"cache{i}"
            cache.mkdir()
            env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), OMP_NUM_THREADS="1",
                       PYTHONPATH=str(root))
            procs.append(subprocess.Popen(
                [sys.executable, "-c", _CHILD, "1" if args.profile else "0"], cwd=tmp,
                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        results = {}
        for c, p in zip(args.checkouts, procs, strict=True):
            stdout, stderr = p.communicate()
            line = [s for s in stdout.splitlines() if s.startswith("RESULT ")]
            if p.returncode != 0 or not line:
                sys.exit(f"{c}: the first-use run failed:\n{stderr[-3000:]}")
            results[c] = json.loads(line[-1][len("RESULT "):])
    print(f"first use, empty numba cache, {len(results)} checkout(s) at once, one thread each [s]")
    keys = ("import_s", "first_solve_s", "jacobians_s", "env_s", "total_s")
    print(f"{'checkout':<40}" + "".join(f"{k[:-2]:>13}" for k in keys))
    for c, r in results.items():
        print(f"{c[-40:]:<40}" + "".join(f"{r[k]:>13.1f}" for k in keys))
        if args.profile:
            print("  slowest top-level compilations:", r["top_compiles"])
            print("  compiled for more than one signature:", r["compiled_more_than_once"])
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
