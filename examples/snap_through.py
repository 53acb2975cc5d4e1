"""Snap-through of the section III-B robot (Renda et al. 2021; docs/physics.md hard cases).

The inner tube is rotated at the orifice from 0 to 360 deg and back with
``torchpvs.continuation``: the followed stable branch ends at a fold past 180 deg, where the
robot snaps to the mirror branch; the backward sweep snaps at the mirror angle (hysteresis).
Saves ``snap_through.png`` into ``--out`` (default ``examples_out/``; ``--out docs/figures``
regenerates the documentation's figure): stability margin and relative rotation theta_2(L_1)
along both sweeps, and the tip before/after the forward snap. Usage::

    python examples/snap_through.py [--out DIR]
"""

from __future__ import annotations

import math
import time

from _common import figure, parse_args, save

import torchpvs as tp


def main() -> None:
    args = parse_args(__doc__, threads=None)
    scene = tp.load_scene("renda2021_section3b")
    path = {"rotation": [[0.0, 0.0], [0.0, 2 * math.pi]]}
    opts = tp.SolverOptions(order=4, n_magnus=16)
    t0 = time.perf_counter()
    fwd = tp.continuation(scene, path, options=opts, max_step=5 / 360)
    bwd = tp.continuation(scene, path, options=opts, max_step=5 / 360, s_span=(1.0, 0.0))
    print(f"two sweeps: {len(fwd) + len(bwd)} points, {fwd.n_solves + bwd.n_solves} solves, "
          f"{time.perf_counter() - t0:.1f} s")
    for name, res in (("forward", fwd), ("backward", bwd)):
        for f in res.folds:
            print(f"{name}: fold at alpha_2 = {math.degrees(float(f.rotation[1])):.3f} deg "
                  f"({f.kind}), tip jump {1e3 * f.tip_jump:.1f} mm, margin before "
                  f"{f.margin_before:.2e} -> after {f.margin_after:.2e} (dimensionless)")

    fig = figure((12, 4))
    ax1, ax2, ax3 = fig.add_subplot(131), fig.add_subplot(132), fig.add_subplot(133)
    for res, style, label in ((fwd, "-", "0 -> 360 deg"), (bwd, "--", "360 -> 0 deg")):
        a = [math.degrees(float(v)) for v in res.rotation[:, 1]]
        for b in sorted(set(res.branch.tolist())):
            idx = [i for i in range(len(res)) if int(res.branch[i]) == b]
            kw = {"label": label} if b == 0 else {}
            color = "C0" if style == "-" else "C1"
            ax1.plot([a[i] for i in idx], [float(res.stability_margin[i]) for i in idx],
                     style, color=color, **kw)
            ax2.plot([a[i] for i in idx],
                     [math.degrees(float(res.relative_rotation_at_outer_tip[i, 0]))
                      for i in idx], style, color=color, **kw)
        for f in res.folds:
            ax1.axvline(math.degrees(float(f.rotation[1])), color="0.6", lw=0.8, ls=style)
    ax1.set(xlabel="alpha_2 [deg]", ylabel="stability margin (scaled eigenvalue)",
            title="smallest stiffness eigenvalue")
    ax2.set(xlabel="alpha_2 [deg]", ylabel="theta_2(L_1) [deg]", title="relative rotation")
    ax1.legend()
    ax2.legend()
    f = fwd.folds[0]
    i = f.index
    for k, (lab, col) in ((i - 1, ("before snap", "C2")), (i, ("after snap", "C3"))):
        p = fwd.tip_position[k]
        ax3.plot([0, 1e3 * float(p[0])], [0, 1e3 * float(p[1])], "o-", color=col, label=lab)
    ax3.set(xlabel="tip x [mm]", ylabel="tip y [mm]",
            title=f"forward snap at {math.degrees(float(f.rotation[1])):.1f} deg: "
                  f"{1e3 * f.tip_jump:.0f} mm")
    ax3.set_aspect("equal")
    ax3.legend()
    save(fig, args.out, "snap_through.png")


if __name__ == "__main__":
    main()
