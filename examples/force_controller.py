"""A gradient-based torque controller: drive the tip to a target with ``d tip / d tau``.

The Fig. 3 robot of Renda et al. 2021 (insertions held at D = (95, 208.5) mm, the outer tube
1.5 mm off the scene's D_1 = Ls_1 kink, where every solve would add two one-sided force solves)
carries a dead tip load ``F = (0, -0.3, 0) N`` (it breaks the zero-stiffness common rotation,
so both rotations can be torque-controlled). Both rotation torques
``tau = (tau_alpha1, tau_alpha2)`` are commanded; each iteration solves the force-controlled
equilibrium (``torchpvs.solve_force_controlled``, warm-started) and updates the command with
the damped pseudo-inverse of the force-control Jacobian ``J_tau = d tip / d tau`` (3 x 2,
from ``torchpvs.force_control.commanded_force_jacobian``)::

    tau <- tau + J_tau^T (J_tau J_tau^T + lambda^2 I)^-1 (target - tip),   |dtau| capped.

The target is the tip of an independent position solve at ``alpha = (-0.5, 1.5) rad``, so it
is reachable; the controller does not know that actuation. Saves
``force_controller.png`` (tip error vs iteration, tip path) into ``--out`` (default
``examples_out/``; ``--out docs/figures`` regenerates the documentation's figure). Usage::

    python examples/force_controller.py [--iterations 15] [--out DIR]
"""

from __future__ import annotations

import math
import time

import torch
from _common import figure, parse_args, save

import torchpvs as tp
from torchpvs.force_control import commanded_force_jacobian


def main() -> None:
    args = parse_args(__doc__, extra=lambda ap: ap.add_argument("--iterations", type=int,
                                                                 default=15))
    t0 = time.perf_counter()
    scene = tp.load_scene("renda2021_fig3").with_actuation(insertion=[0.095, 0.2085])
    opts = tp.SolverOptions(order=4, n_magnus=16)
    load = {"tip_force": [0.0, -0.3, 0.0]}
    alpha_goal = [-0.5, 1.5]
    goal = tp.solve(scene, rotation=alpha_goal, options=opts, **load)
    target = goal.tip_position[0]
    print(f"target tip {[round(1e3 * float(v), 2) for v in target]} mm (position solve at "
          f"alpha = {alpha_goal} rad; holding torques "
          f"{[round(float(v), 5) for v in goal.actuation_torques[0]]} N m)")

    tau = torch.zeros(2, dtype=torch.float64)          # start: both torques zero (hanging)
    res = tp.solve_force_controlled(scene, torques=tau, rotation=[0.0, 0.0], options=opts,
                                    on_failure="raise", **load)
    damping, cap = 2e-3, 0.02                          # lambda [m/(N m)], |dtau| cap [N m]
    errors, tips, stable = [], [], []
    for k in range(args.iterations + 1):
        tip = res.equilibrium.tip_position[0]
        err = float((target - tip).norm())
        errors.append(err)
        tips.append(tip.tolist())
        stable.append(bool(res.stable[0]))
        print(f"iter {k:2d}: tau = ({float(tau[0]):+.5f}, {float(tau[1]):+.5f}) N m, alpha = "
              f"({float(res.rotation[0, 0]):+.4f}, {float(res.rotation[0, 1]):+.4f}) rad, "
              f"|tip error| = {1e3 * err:.3e} mm, stable under torque control: {stable[-1]}")
        if err < 1e-9 or k == args.iterations:
            break
        J = commanded_force_jacobian(res)[0, :3][:, 2:]               # (3, 2) m/(N m)
        dtau = J.T @ torch.linalg.solve(J @ J.T + damping**2 * torch.eye(3, dtype=J.dtype),
                                        target - tip)
        dtau = dtau / max(1.0, float(dtau.abs().max()) / cap)
        tau = tau + dtau
        res = tp.solve_force_controlled(scene, torques=tau, rotation=res.rotation,
                                        initial=res.equilibrium, options=opts,
                                        on_failure="raise", **load)
    print(f"final torques {[round(float(v), 6) for v in tau]} N m vs the target's holding "
          f"torques {[round(float(v), 6) for v in goal.actuation_torques[0]]} N m; final "
          f"rotation {[round(float(v), 6) for v in res.rotation[0]]} rad vs {alpha_goal} "
          f"({time.perf_counter() - t0:.1f} s)")

    fig = figure((10, 4))
    ax1, ax2 = fig.add_subplot(121), fig.add_subplot(122)
    ax1.semilogy(range(len(errors)), [1e3 * max(e, 1e-12) for e in errors], "o-")
    ax1.set(xlabel="controller iteration", ylabel="|tip - target| [mm]",
            title="torque control via d tip / d tau")
    ax1.grid(True, which="both", alpha=0.3)
    xs = [1e3 * p[0] for p in tips]
    ys = [1e3 * p[1] for p in tips]
    ax2.plot(xs, ys, "o-", ms=3, label="tip, iterations")
    ax2.plot([1e3 * float(target[0])], [1e3 * float(target[1])], "r*", ms=12, label="target")
    ax2.annotate("start", (xs[0], ys[0]))
    ax2.set(xlabel="tip x [mm]", ylabel="tip y [mm]",
            title="tip path (tip load 0.3 N along -y)")
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.legend()
    save(fig, args.out, "force_controller.png")
    if not math.isfinite(errors[-1]):
        raise SystemExit("controller diverged")


if __name__ == "__main__":
    main()
