"""Control-step cost: one warm solve plus what a controller needs from it, measured side by side.

    python benchmarks/control_step.py [--robots fig3 three_tube] [--configs 16] [--repeat 5]
                                      [--json out.json]

Per robot, ``--configs`` configurations (the last tube's rotation spread over [0, 250] deg),
each solved warm from the equilibrium 1 deg away, single calls (B = 1), one torch thread,
default options. Cases:

* ``solve``: ``torchpvs.solve`` alone;
* ``solve + stiffness``: and :func:`torchpvs.jacobians.actuator_stiffness` (what an environment
  step needs);
* ``control step``: and ``eq.jacobians(compliance=False)`` — the actuator stiffness, the 6 x 2N
  tip Jacobian and the force-control Jacobian in closed form from the solve's factorization;
* ``+ compliance``: ``eq.jacobians()``, which adds the 6 x 6 tip compliance (one re-solve with
  load coordinates for an unloaded robot);
* ``autograd Jacobian``: the tip-position Jacobian and the stiffness by reverse passes through
  the implicit backward (``torch.autograd.grad`` of the forces and tip position of a solve
  whose inputs require grad, one pass per row: what a user without the closed forms writes).

Printed: ms per call (best of ``--repeat``), each case's ratio to the solve alone and the
closed form's speed-up over the autograd rows, plus the largest difference between the two
Jacobians (a check that both compute the same thing; on the Fig. 3 robot they differ in the
``D_1`` column by design: its scene's ``D_1`` puts the outer tube's straight-to-curved
transition exactly at the orifice, a kink of ``U*(D_1)`` where the closed form reports the
retracting side's one-sided derivative and autograd the layout's own tie rule, which is
neither; docs/actuation-forces.md). Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import math
import warnings

import torch
from fast_path import bench_scene, best_time  # a sibling script (run from benchmarks/)

import torchpvs
from torchpvs.jacobians import actuator_stiffness


def _autograd_rows(scene, rot, initial):
    """Tip-position Jacobian ``(1, 3, 2N)`` and stiffness ``(1, 2N, 2N)`` by reverse passes."""
    N = scene.n_tubes
    x = torch.tensor([*scene.actuation.insertion], dtype=torch.float64)[None]
    X = torch.cat([x, rot], -1).requires_grad_(True)
    eq = torchpvs.solve(scene, insertion=X[:, :N], rotation=X[:, N:], initial=initial)
    out = torch.cat([eq.tip_position, eq.actuation_forces, eq.actuation_torques], -1)
    G = torch.stack([torch.autograd.grad(out[:, i].sum(), X, retain_graph=True)[0]
                     for i in range(out.shape[-1])], 1)
    return G[:, :3], G[:, 3:]


def bench_robot(name: str, configs: int, repeat: int) -> dict:
    scene = bench_scene(name)
    step = math.radians(1.0)
    base = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    rot0 = base.repeat(configs, 1)
    rot0[:, -1] = torch.linspace(0, math.radians(250), configs, dtype=torch.float64) - step
    rot1 = rot0.clone()
    rot1[:, -1] += step
    warm = [torchpvs.solve(scene, rotation=r[None]) for r in rot0]
    pairs = list(zip(rot1, warm, strict=True))

    def solve(r, e):
        return torchpvs.solve(scene, rotation=r[None], initial=e)

    cases = {
        "solve": lambda: [solve(r, e) for r, e in pairs],
        "solve + stiffness": lambda: [actuator_stiffness(solve(r, e)) for r, e in pairs],
        "control step": lambda: [solve(r, e).jacobians(compliance=False) for r, e in pairs],
        "+ compliance": lambda: [solve(r, e).jacobians() for r, e in pairs],
        "autograd Jacobian": lambda: [_autograd_rows(scene, r[None], e) for r, e in pairs],
    }
    out = {"robot": name, "tubes": scene.n_tubes, "configs": configs}
    for label, fn in cases.items():
        out[label] = 1e3 * best_time(fn, repeat) / configs
    diff, scale = 0.0, 0.0
    for r, e in pairs:
        J = solve(r, e).jacobians(compliance=False).tip_jacobian[:, :3]
        J_ref, _ = _autograd_rows(scene, r[None], e)
        diff = max(diff, float((J - J_ref).abs().max()))
        scale = max(scale, float(J_ref.abs().max()))
    out["jacobian_max_difference"], out["jacobian_scale"] = diff, scale
    return out


def _print(r: dict) -> None:
    s = r["solve"]
    print(f"\n== {r['robot']} ({r['tubes']} tubes), B = 1 warm, {r['configs']} configurations")
    print(f"{'case':<20}{'ms/call':>10}{'x solve':>9}")
    for k in ("solve", "solve + stiffness", "control step", "+ compliance",
              "autograd Jacobian"):
        print(f"{k:<20}{r[k]:>10.2f}{r[k] / s:>9.2f}")
    speedup = r["autograd Jacobian"] / r["control step"]
    print(f"control step (closed form) vs autograd rows: {speedup:.1f}x faster; "
          f"tip Jacobians differ by {r['jacobian_max_difference']:.1e} "
          f"(largest entry {r['jacobian_scale']:.2f})")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", nargs="+", default=["fig3", "three_tube"])
    ap.add_argument("--configs", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    results = []
    for name in args.robots:
        r = bench_robot(name, args.configs, args.repeat)
        _print(r)
        results.append(r)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    main()
