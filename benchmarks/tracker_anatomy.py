"""Where a `Tracker` step's time goes at B = 1: the Python step against its compiled call, and
the compiled call with its parts switched off one at a time, timed in one process.

    python benchmarks/tracker_anatomy.py [--scene renda2021_fig3] [--calls 4000]

The step is the peer benchmark's (benchmarks/peer_cpp.py): the scene's actuation with the last
tube turned by 1 deg, warm from the scene's equilibrium (restored before every call). The
compiled call's arguments are captured from that step and the same arrays are then timed:
the whole control step (tip Jacobian and actuator stiffness, the kink's one side where the
insertions sit at a kink), the same at the equilibrium's own sections (no side), the
stiffness alone, the plain step (no rows), and the layout alone (its 32 arrays returned to
Python). Differences between consecutive rows are the parts' costs. Every figure is the
minimum and the 10th percentile over ``--calls`` single calls (microseconds): the minimum of
a short call is robust to a busy machine, where means are not.
"""

from __future__ import annotations

import argparse
import inspect
import math
import time

import numpy as np
import torch


def times(f, args=(), calls: int = 4000) -> tuple[float, float]:
    """``(min, p10)`` [us] of ``calls`` single calls of ``f(*args)``."""
    ts = np.empty(calls)
    clock = time.perf_counter_ns
    for i in range(calls):
        t0 = clock()
        f(*args)
        ts[i] = clock() - t0
    return float(ts.min() / 1e3), float(np.percentile(ts, 10) / 1e3)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", default="renda2021_fig3")
    p.add_argument("--calls", type=int, default=4000)
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    import torchpvs
    from torchpvs import tracker as T
    from torchpvs.compiled_layout import layout_maps_arrays

    scene = torchpvs.load_scene(args.scene)
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64)[None]
    ins = np.array(scene.actuation.insertion)
    tr = torchpvs.Tracker(scene, rotation=rot, initial=torchpvs.solve(scene, rotation=rot))
    snap = tr.snapshot()
    r1 = rot.numpy()[0].copy()
    r1[-1] += math.radians(1.0)

    def step(jacobians: bool):
        tr.restore(snap)
        return tr.step(ins, r1, jacobians=jacobians)

    call = T.layout_and_track
    captured = {}

    def spy(*a):
        captured["args"] = a
        return call(*a)

    T.layout_and_track = spy
    try:
        step(True)
    finally:
        T.layout_and_track = call
    names = list(inspect.signature(call.py_func).parameters)
    at = {k: i for i, k in enumerate(names)}
    base = captured["args"]

    def with_(**kw):
        a = [np.copy(v) if isinstance(v, np.ndarray) else v for v in base]
        for k, v in kw.items():
            a[at[k]] = v
        return tuple(a)

    B = base[at["D"]].shape[0]
    no_side = np.zeros(B, dtype=np.int8)
    lay_args = [base[at[k]] for k in ("EI", "GJ", "L", "Ls", "coef", "D", "A", "unloaded")]
    lay_args += [1e-12] + [base[at[k]] for k in ("xg", "wg", "xq", "wq", "xm", "phi", "n")]
    rows = [
        ("Tracker.step(jacobians=True)", lambda: step(True), ()),
        ("Tracker.step()", lambda: step(False), ()),
        ("compiled call: control step", call, with_()),
        ("  at the equilibrium's own sections (no kink side)", call, with_(side=no_side)),
        ("  stiffness alone (no tip Jacobian)", call, with_(side=no_side, want_J=False)),
        ("compiled call: plain step (no rows)", call, with_(jac=False, want_J=False)),
        ("layout alone (32 arrays returned)", layout_maps_arrays, tuple(lay_args)),
    ]
    print(f"{args.scene}, B = {B}, {int(base[at['it']][0])} Newton iteration(s), kink side "
          f"{int(base[at['side']][0])}; {args.calls} calls each, one thread")
    print(f"{'':52s} {'min us':>8s} {'p10 us':>8s}")
    for name, f, a in rows:
        lo, p10 = times(f, a, args.calls)
        print(f"{name:52s} {lo:8.1f} {p10:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
