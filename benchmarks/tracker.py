"""The control loop's fused step (``torchpvs.Tracker``) against ``torchpvs.solve``, side by side.

    python benchmarks/tracker.py [--robots fig3 three] [--configs 8] [--batch 64]
                                 [--repeat 5] [--json out.json]

Per robot (the paper's Fig. 3 scene; the three-tube preset of ``envs.robots``), ``--configs``
configurations with the last tube's rotation spread over [0, 170] deg, each reached by
following the branch from 0 in 1 deg steps; every timed call is a warm step 1 deg further,
one torch thread, rounds interleaved, best of ``--repeat``, ms per solve:

* ``solve`` warm, default options (automatic order and Magnus checks, actuation forces);
* ``solve`` warm at the tracker's fixed discretization, tip only
  (``SolverOptions(order=k, n_magnus=m, compute_forces=False)``: what the tracker computes);
* ``Tracker.step`` (restored to the warm state before each step; the restore is timed too),
  and with ``forces=True`` (the actuation forces the default solve computes, one-sided at
  kinks);
* control step: ``solve(...).jacobians(compliance=False)`` against
  ``Tracker.step(..., jacobians=True)``;
* a batch of ``--batch`` (the configurations repeated): one batched ``solve`` against one
  ``Tracker.step``, per solve.

Printed with the ratios and the largest tip and Jacobian differences between the two.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from fast_path import bench_scene  # noqa: E402

import torchpvs  # noqa: E402


def best_of(cases: dict, repeat: int) -> dict:
    """Best time [s] of each zero-argument call: one untimed call each, then ``repeat`` rounds
    that time every case in turn."""
    for fn in cases.values():
        fn()
    best = dict.fromkeys(cases, math.inf)
    for _ in range(repeat):
        for k, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            best[k] = min(best[k], time.perf_counter() - t0)
    return best


def bench(name: str, configs: int, batch: int, repeat: int) -> dict:
    scene = bench_scene(name)
    N = scene.n_tubes
    step = math.radians(1.0)
    base = np.array(scene.actuation.rotation)
    ins = np.array(scene.actuation.insertion)
    targets = np.linspace(0, math.radians(170), configs) - step
    warm, rot0 = [], []
    eq, angle = None, 0.0
    for t in targets:
        for a in np.linspace(angle, t, max(1, math.ceil(abs(t - angle) / step - 1e-9)) + 1)[1:]:
            r = base.copy()
            r[-1] = a
            eq = torchpvs.solve(scene, rotation=torch.tensor(r[None]), initial=eq)
        angle = t
        warm.append(eq)
        rot0.append(r.copy())
    rot0 = np.array(rot0)
    rot1 = rot0.copy()
    rot1[:, -1] += step
    trackers = [torchpvs.Tracker(scene, rotation=r[None], initial=e)
                for r, e in zip(rot0, warm, strict=True)]
    snaps = [t.snapshot() for t in trackers]
    fixed = trackers[0].options
    fixed_warm = [torchpvs.solve(scene, rotation=torch.tensor(r[None]), initial=e, options=fixed)
                  for r, e in zip(rot0, warm, strict=True)]
    r1 = [torch.tensor(r[None]) for r in rot1]
    reps = -(-batch // configs)
    R0, R1 = np.tile(rot0, (reps, 1))[:batch], np.tile(rot1, (reps, 1))[:batch]
    E0 = torchpvs.solve(scene, rotation=torch.tensor(R0),
                        initial=torch.cat([e.q for e in warm]).repeat(reps, 1)[:batch])
    big = torchpvs.Tracker(scene, rotation=R0, initial=E0)
    big_snap = big.snapshot()
    ins_B = np.repeat(ins[None], batch, 0)

    def steps(jac=False, forces=False):
        out = []
        for t, s, r in zip(trackers, snaps, rot1, strict=True):
            t.restore(s)
            out.append(t.step(ins, r, jacobians=jac, forces=forces))
        return out

    def big_step():
        big.restore(big_snap)
        return big.step(ins_B, R1)

    cases = {
        "solve_default": lambda: [torchpvs.solve(scene, rotation=r, initial=e)
                                  for r, e in zip(r1, warm, strict=True)],
        "solve_fixed_tip": lambda: [torchpvs.solve(scene, rotation=r, initial=e, options=fixed)
                                    for r, e in zip(r1, fixed_warm, strict=True)],
        "tracker": steps,
        "tracker_forces": lambda: steps(forces=True),
        "solve_control": lambda: [torchpvs.solve(scene, rotation=r, initial=e)
                                  .jacobians(compliance=False)
                                  for r, e in zip(r1, warm, strict=True)],
        "tracker_control": lambda: steps(True),
        "solve_batch": lambda: torchpvs.solve(scene, rotation=torch.tensor(R1), initial=E0),
        "tracker_batch": big_step,
    }
    best = best_of(cases, repeat)
    ms = {k: 1e3 * v / (batch if k.endswith("batch") else configs) for k, v in best.items()}
    # agreement with the solver at the tracker's discretization (its reference)
    st = steps(True)
    eqs = [torchpvs.solve(scene, rotation=r, initial=e, options=fixed)
           for r, e in zip(r1, fixed_warm, strict=True)]
    tip_diff = max(float(np.abs(s.tip - e.tip_position.numpy()).max())
                   for s, e in zip(st, eqs, strict=True))
    jac_diff = max(float(np.abs(s.tip_jacobian - e.jacobians(compliance=False).tip_jacobian
                               .numpy()).max()) for s, e in zip(st, eqs, strict=True))
    return {"robot": name, "tubes": N, "configs": configs, "batch": batch, "repeat": repeat,
            "order": fixed.order, "n_magnus": fixed.n_magnus, "ms": ms,
            "tip_diff_m": tip_diff, "jacobian_diff": jac_diff}


def report(r: dict) -> None:
    ms = r["ms"]
    print(f"\n== {r['robot']} ({r['tubes']} tubes), {r['configs']} configurations, one thread, "
          f"best of {r['repeat']}; tracker at order {r['order']}, {r['n_magnus']} Magnus steps")
    rows = [("warm B=1, default solve (forces) / Tracker forces=True", "solve_default",
             "tracker_forces"),
            ("warm B=1, default solve / Tracker tip only", "solve_default", "tracker"),
            ("warm B=1, solve at the tracker's discretization, tip only", "solve_fixed_tip",
             "tracker"),
            ("control step B=1 (jacobians)", "solve_control", "tracker_control"),
            (f"warm B={r['batch']}, per solve", "solve_batch", "tracker_batch")]
    print(f"{'case':<58}{'solve ms':>10}{'Tracker ms':>12}{'speed-up':>10}")
    for label, a, b in rows:
        print(f"{label:<58}{ms[a]:>10.4f}{ms[b]:>12.4f}{ms[a] / ms[b]:>9.1f}x")
    print(f"tips vs the solve at the tracker's discretization: {r['tip_diff_m']:.1e} m; "
          f"tip Jacobians: {r['jacobian_diff']:.1e}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", nargs="+", default=["fig3", "three"], choices=["fig3", "three"])
    p.add_argument("--configs", type=int, default=8)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    out = [bench(name, args.configs, args.batch, args.repeat) for name in args.robots]
    for r in out:
        report(r)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
