"""A 1 kHz resolved-rate loop on ``torchpvs.Tracker``: the Fig. 3 tip traces a circle.

Every control period (1 ms of robot time) the loop takes one tracker step with the control
step's Jacobians at the commanded actuation ``x = (D_1, D_2, alpha_1, alpha_2)``, then commands
the actuator rates with the damped least-squares inverse of the tip position Jacobian
``J = d(tip)/dx`` (3 x 4, the tracker's closed form)::

    xdot = J^T (J J^T + lambda^2 I)^-1 (v_ref + k (p_ref - tip)),   x <- x + xdot dt,

where ``p_ref`` runs around a circle of ``--radius`` (default 5 mm) in the plane normal to the
base's z axis through the start tip, once in ``--seconds`` (default 2 s). The insertions are kept
nested and inside the robot (``0 <= D_1 <= D_2``, each tube exposed). Near t = 1.77 s the
outer carriage reaches ``D_1 = Ls_1`` (93.5 mm), where the tip has a kink in ``D_1``: the
Jacobian there is one-sided (the retracting side, as ``Equilibrium.jacobians``), its insertion
column jumps as the carriage crosses, and the rate loop chatters at the kink until the
target moves on (the error peaks at about 2.5 mm): the robot's own non-smoothness, which a
real controller has to handle (e.g. by planning across it). Printed: the wall-clock
time per control step (solve and Jacobian) and the tracking error; saved
``control_loop.png`` (target and tip paths, tracking error over time, step times) into
``--out`` (default ``examples_out/``). Usage::

    python examples/control_loop.py [--seconds 2] [--radius 0.005] [--out DIR]
"""

from __future__ import annotations

import math
import time

import numpy as np
from _common import figure, parse_args, save

import torchpvs as tp


def main() -> None:
    def extra(ap):
        ap.add_argument("--seconds", type=float, default=2.0)
        ap.add_argument("--radius", type=float, default=0.005)

    args = parse_args(__doc__, extra=extra)
    # 1.5 mm of the outer tube's curved part inside the guide: off the scene's D_1 = Ls_1 kink,
    # where the one-sided insertion derivatives differ and a rate loop crossing it chatters
    scene = tp.load_scene("renda2021_fig3").with_actuation(insertion=[0.095, 0.2085])
    dt, lam, gain = 1e-3, 1e-3, 50.0
    L = np.array([t.length for t in scene.tubes])
    x = np.array([*scene.actuation.insertion, *scene.actuation.rotation])
    tr = tp.Tracker(scene, insertion=x[:2], rotation=x[2:])
    p0 = tr.state.tip[0].copy()
    steps = int(round(args.seconds / dt))
    w = 2 * math.pi / args.seconds
    tips, refs, times, ok = [], [], [], []
    for k in range(steps):
        t = k * dt
        # the circle starts at the tip: p_ref(0) = p0
        p_ref = p0 + args.radius * np.array([math.cos(w * t) - 1.0, math.sin(w * t), 0.0])
        v_ref = args.radius * w * np.array([-math.sin(w * t), math.cos(w * t), 0.0])
        t0 = time.perf_counter()
        s = tr.step(x[:2], x[2:], jacobians=True)
        times.append(time.perf_counter() - t0)
        ok.append(bool(s.converged[0]))
        tip, J = s.tip[0], s.tip_jacobian[0, :3]
        e = v_ref + gain * (p_ref - tip)
        xdot = J.T @ np.linalg.solve(J @ J.T + lam ** 2 * np.eye(3), e)
        x = x + xdot * dt
        # keep the tubes nested and every tube exposed (0 <= D_1 <= D_2 < L_j)
        x[0] = min(max(x[0], 0.0), L[0] - 1e-3)
        x[1] = min(max(x[1], x[0]), L[1] - 1e-3)
        tips.append(tip)
        refs.append(p_ref)
    tips, refs, times = np.array(tips), np.array(refs), np.array(times)
    err = np.linalg.norm(tips - refs, axis=1)
    print(f"{steps} control steps of {dt * 1e3:g} ms (order {tr.order}, {tr.n_magnus} Magnus "
          f"steps): converged {np.mean(ok):.3f}; wall time per step (solve + Jacobians) "
          f"median {np.median(times) * 1e3:.3f} ms, p95 {np.quantile(times, 0.95) * 1e3:.3f} ms")
    print(f"tracking error: median {np.median(err) * 1e3:.3f} mm, max after the first 0.1 s "
          f"{err[100:].max() * 1e3:.3f} mm (circle radius {args.radius * 1e3:g} mm)")

    fig = figure((13, 4))
    ax = fig.add_subplot(1, 3, 1)
    ax.plot(refs[:, 0] * 1e3, refs[:, 1] * 1e3, "k--", label="target")
    ax.plot(tips[:, 0] * 1e3, tips[:, 1] * 1e3, label="tip")
    ax.set(xlabel="x [mm]", ylabel="y [mm]", title="tip path (base frame)", aspect="equal")
    ax.legend()
    ax = fig.add_subplot(1, 3, 2)
    ax.semilogy(np.arange(steps) * dt, np.maximum(err, 1e-9) * 1e3)
    ax.set(xlabel="time [s]", ylabel="tracking error [mm]", title="error")
    ax = fig.add_subplot(1, 3, 3)
    # (the first step also loads the compiled code; the histogram shows the rest)
    ax.hist(times[1:] * 1e3, bins=50, range=(0, np.quantile(times[1:], 0.99) * 1e3))
    ax.set(xlabel="wall time per control step [ms]", ylabel="steps",
           title="Tracker.step(..., jacobians=True)")
    save(fig, args.out, "control_loop.png")


if __name__ == "__main__":
    main()
