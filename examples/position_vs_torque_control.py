"""Position control vs torque control through the snap of the section III-B robot.

The paper (Renda et al. 2021) argues that torque-controlled CTRs can enhance elastic stability.
This example measures it on the snapping robot of section III-B (fully curved tubes, bases at
the orifice), rotating the inner tube (alpha_1 = 0 held, insertions held):

* **position control** — alpha_2 prescribed and swept from 0 with ``torchpvs.continuation``.
  An equilibrium is stable iff the shape Hessian is positive definite (margin =
  ``Equilibrium.min_stiffness_eigenvalue``); the branch ends at a fold where it stops being so.
* **torque control** — the torque tau_alpha2 is commanded and raised from 0, alpha_2 is free
  (``torchpvs.solve_force_controlled``). Now alpha_2 is a coordinate of the energy
  ``U(q, alpha_2) - tau alpha_2`` and stability needs the full Hessian over ``(q, alpha_2)``
  positive definite: the shape Hessian PD *and* its Schur complement, the actuator stiffness
  ``dtau/dalpha_2``, positive. It is lost where tau_alpha2 peaks along the branch.

Printed: where each loses stability, cross-checks (the peak of tau along the position sweep vs
the largest torque the torque-controlled solve can balance; the sign change of dtau/dalpha_2),
and what lies beyond. Saves ``position_vs_torque.png`` into ``--out`` (default
``examples_out/``; ``--out docs/figures`` regenerates the documentation's figure). Usage::

    python examples/position_vs_torque_control.py [--out DIR]
"""

from __future__ import annotations

import math
import time

import torch
from _common import NAN, figure, parse_args, save

import torchpvs as tp
from torchpvs.jacobians import actuator_stiffness


def main() -> None:
    args = parse_args(__doc__)
    t_start = time.perf_counter()
    scene = tp.load_scene("renda2021_section3b")
    opts = tp.SolverOptions(order=4, n_magnus=16)

    # --- position control: continuation locates the fold -----------------------------------
    path = {"rotation": [[0.0, 0.0], [0.0, 2 * math.pi]]}
    fwd = tp.continuation(scene, path, options=opts, max_step=5 / 360)
    bwd = tp.continuation(scene, path, options=opts, max_step=5 / 360, s_span=(1.0, 0.0))
    fold = fwd.folds[0]
    a_pos = float(fold.rotation[1])
    # every stable equilibrium met on both sweeps (both branches): the largest torque any of
    # them needs
    tau_all = torch.cat([fwd.actuation_torques[:, 1], bwd.actuation_torques[:, 1]])
    print(f"position control: fold (loss of shape stability) at alpha_2 = "
          f"{math.degrees(a_pos):.2f} deg, margin before {fold.margin_before:.2e}, tip "
          f"jump {1e3 * fold.tip_jump:.1f} mm")

    # dense position sweep along the branch with the actuator stiffness dtau/dalpha_2
    alphas = torch.linspace(0.0, a_pos - 1e-3, 120, dtype=torch.float64)
    prev, rows = None, []
    for a in alphas:
        e = tp.solve(scene, rotation=torch.stack([torch.zeros((), dtype=a.dtype), a]),
                     options=opts, initial=prev)
        K = actuator_stiffness(e)
        rows.append((float(a), float(e.actuation_torques[0, 1]), float(K[0, 3, 3]),
                     float(e.min_stiffness_eigenvalue[0])))
        prev = e
    a_p = [r[0] for r in rows]
    tau_p = [r[1] for r in rows]
    k_p = [r[2] for r in rows]
    m_p = [r[3] for r in rows]
    i = max(range(len(rows)), key=lambda k: tau_p[k])
    # sign change of dtau/dalpha_2 along the position branch (linear interpolation)
    j = next(k for k in range(1, len(rows)) if k_p[k] <= 0 < k_p[k - 1])
    a_k0 = a_p[j - 1] + (a_p[j] - a_p[j - 1]) * k_p[j - 1] / (k_p[j - 1] - k_p[j])
    print(f"position sweep: tau_alpha2 peaks at {tau_p[i]:.5f} N m near alpha_2 = "
          f"{math.degrees(a_p[i]):.1f} deg; dtau/dalpha_2 changes sign at "
          f"{math.degrees(a_k0):.2f} deg; at the fold dtau/dalpha_2 = {k_p[-1]:.3g} N m/rad")

    # --- torque control: raise the commanded torque, alpha_2 free -----------------------------
    tau_c, a_c, k_c, m_c = [], [], [], []
    res = tp.solve_force_controlled(scene, torques=[NAN, 0.0], rotation=[0.0, 0.0],
                                    options=opts, on_failure="ignore")
    step, tau, last, fail_reason = 0.01, 0.0, res, ""
    while step > 1e-7:
        if bool(res.converged[0]) and bool(res.stable[0]):
            last = res
            tau_c.append(tau)
            a_c.append(float(res.rotation[0, 1]))
            k_c.append(float(res.actuator_stiffness[0, 3, 3]))
            m_c.append(float(res.equilibrium.min_stiffness_eigenvalue[0]))
            tau += step
        else:
            if not bool(res.converged[0]):
                fail_reason = res.reason[0]
            tau -= step            # back to the last balanced torque, smaller increment
            step *= 0.5
            tau += step
        res = tp.solve_force_controlled(
            scene, torques=[NAN, tau], rotation=last.rotation, options=opts,
            initial=last.equilibrium, on_failure="ignore", max_iter=25)
    tau_max, a_tc = tau_c[-1], a_c[-1]
    print(f"torque control: largest torque balanced stably {tau_max:.5f} N m at alpha_2 = "
          f"{math.degrees(a_tc):.2f} deg (dtau/dalpha_2 = {k_c[-1]:.2e} N m/rad, shape margin "
          f"{m_c[-1]:.2e}); beyond it: {fail_reason}")
    print(f"  cross-check: peak of tau along the position sweep {tau_p[i]:.5f} N m; largest "
          f"torque of any stable equilibrium on both position sweeps {float(tau_all.max()):.5f} "
          f"N m")
    # the equilibria between the torque peak and the fold: stable under position control,
    # unstable under torque control (the force-controlled solve still finds them as roots)
    a_mid = 0.5 * (a_tc + a_pos)
    e_mid = tp.solve(scene, rotation=[0.0, a_mid], options=opts)
    r_mid = tp.solve_force_controlled(
        scene, torques=[NAN, float(e_mid.actuation_torques[0, 1])],
        rotation=[0.0, a_mid + 0.02], options=opts, initial=e_mid, on_failure="ignore")
    print(f"  at alpha_2 = {math.degrees(a_mid):.1f} deg: shape-stable {bool(e_mid.stable[0])}"
          f" (margin {float(e_mid.min_stiffness_eigenvalue[0]):.2e}); under torque control "
          f"converged {bool(r_mid.converged[0])} to alpha_2 = "
          f"{math.degrees(float(r_mid.rotation[0, 1])):.2f} deg, dtau/dalpha_2 = "
          f"{float(r_mid.actuator_stiffness[0, 3, 3]):.3g} N m/rad -> stable "
          f"{bool(r_mid.stable[0])}")
    lost = math.degrees(a_pos - a_tc)
    print(f"RESULT: torque control loses stability {lost:.1f} deg of inner-tube rotation "
          f"EARLIER than position control ({math.degrees(a_tc):.1f} vs "
          f"{math.degrees(a_pos):.1f} deg); relative rotation theta_2(L_1) reachable stably: "
          f"position control up to {math.degrees(float(fold_theta(fwd, fold))):.1f} deg, "
          f"torque control up to {math.degrees(theta_at(scene, opts, a_tc, last)):.1f} deg")

    # --- figure -------------------------------------------------------------------------------
    fig = figure((13, 4))
    ax1, ax2, ax3 = fig.add_subplot(131), fig.add_subplot(132), fig.add_subplot(133)
    deg = [math.degrees(a) for a in a_p]
    ax1.plot(deg, tau_p, "C0-", label="position control (branch from 0)")
    ax1.plot([math.degrees(a) for a in a_c], tau_c, "C1.", ms=4, label="torque control")
    ax1.axvline(math.degrees(a_tc), color="C1", ls="--", lw=1,
                label=f"torque control unstable ({math.degrees(a_tc):.1f} deg)")
    ax1.axvline(math.degrees(a_pos), color="C0", ls="--", lw=1,
                label=f"position-control fold ({math.degrees(a_pos):.1f} deg)")
    ax1.set(xlabel="alpha_2 [deg]", ylabel="tau_alpha2 [N m]", title="actuator torque")
    ax1.legend(fontsize=7, loc="lower left")
    ax2.plot(deg, m_p, "C0-")
    ax2.axhline(0, color="0.5", lw=0.6)
    ax2.axvline(math.degrees(a_pos), color="C0", ls="--", lw=1)
    ax2.set(xlabel="alpha_2 [deg]", ylabel="smallest scaled shape-Hessian eigenvalue",
            title="position control: shape stability margin")
    ax3.plot(deg, k_p, "C1-", label="dtau/dalpha_2 along the branch")
    ax3.axhline(0, color="0.5", lw=0.6)
    ax3.axvline(math.degrees(a_tc), color="C1", ls="--", lw=1)
    ax3.axvline(math.degrees(a_pos), color="C0", ls="--", lw=1)
    ax3.set_ylim(min(-0.5, min(k_p[:-3])), 1.2 * max(k_p))
    ax3.set(xlabel="alpha_2 [deg]", ylabel="actuator stiffness [N m/rad]",
            title="torque control: actuator stiffness")
    ax3.legend(fontsize=7)
    save(fig, args.out, "position_vs_torque.png",
         note=f" ({time.perf_counter() - t_start:.1f} s)")


def fold_theta(cont, fold) -> float:
    """theta_2(L_1) [rad] on the lost branch just before the fold."""
    return float(cont.relative_rotation_at_outer_tip[fold.index - 1, 0])


def theta_at(scene, opts, alpha2: float, near) -> float:
    e = tp.solve(scene, rotation=[0.0, alpha2], options=opts, initial=near.equilibrium)
    return float(e.relative_rotation_at_outer_tip[0, 0])


if __name__ == "__main__":
    main()
