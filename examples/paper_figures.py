"""Regenerate the validation figures of Renda et al., RA-L 2021, with torchpvs.

Figures (PNG, written to ``--out``: default ``examples_out/``, ``--out docs/figures`` regenerates
the documentation's figures):

* ``fig2_section3b_equilibria.png`` -- paper Fig. 2: the three equilibria of the section III-B
  robot (two fully curved tubes, inner tube rotated by 180 deg at the orifice): two stable mirror
  configurations and the unstable symmetric one, PVS (solid) over the standard model (dashed).
* ``fig4_sweeps.png`` -- paper Fig. 4: the Fig. 3 robot with the inner tube rotated through
  ``alpha_2 = 0..280 deg`` (full overlap, ``D_2 = 208.5 mm``) and ``0..200 deg`` (partial overlap,
  ``D_2 = 170.5 mm``), following the branch continuously from ``alpha_2 = 0`` (warm starts in both
  solvers). PVS with the paper's quadratic basis (``--sweep-order``, default 2).
* ``order_convergence.png`` -- PVS tip error against the standard model (shooting, tol 1e-12)
  versus the polynomial order of the strain bases, with the number of generalized coordinates.

Every number a figure shows is also printed. Usage::

    python examples/paper_figures.py [--out DIR] [--quick]
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
from _common import figure, parser, save  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

import torchpvs  # noqa: E402
from torchpvs.plotting import backbone_owners  # noqa: E402
from torchpvs.reference import solve_standard  # noqa: E402

try:
    from tqdm import tqdm
except ImportError:  # printed progress only
    tqdm = None

MM = 1e3
DPI = 120
POINTS = 120                     # backbone samples per curve
D1_FIG3 = 93.5e-3                # [m] outer tube insertion of the Fig. 3 robot
D2_FULL, D2_PARTIAL = 208.5e-3, 170.5e-3
PAPER_FIG4 = {"full": (0.48, 0.44), "partial": (0.89, 0.72)}   # max, mean tip error [mm]


# ---------------------------------------------------------------------------------------------
# helpers

def progress(items, desc: str):
    items = list(items)
    if tqdm is not None:
        return tqdm(items, desc=desc, leave=False, ncols=80)
    print(f"[{desc}] {len(items)} steps ...", flush=True)
    return items


def set_equal_3d(ax, clouds: list[np.ndarray], pad: float = 0.04, zoom: float = 1.0) -> None:
    """Equal data aspect (one mm is as long along x, y and z) from all drawn points [mm]."""
    pts = np.concatenate([np.asarray(c, float).reshape(-1, 3) for c in clouds], 0)
    lo, hi = pts.min(0), pts.max(0)
    span = float((hi - lo).max()) or 1.0
    half = np.maximum(0.5 * (hi - lo), 0.06 * span) + pad * span
    c = 0.5 * (lo + hi)
    ax.set_xlim(c[0] - half[0], c[0] + half[0])
    ax.set_ylim(c[1] - half[1], c[1] + half[1])
    ax.set_zlim(c[2] - half[2], c[2] + half[2])
    ax.set_box_aspect(tuple(2 * half), zoom=zoom)
    for axis, h in zip((ax.xaxis, ax.yaxis, ax.zaxis), half, strict=True):
        nbins = max(2, int(round(6 * h / half.max())))   # fewer ticks on short axes
        axis.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))


def draw_backbone(ax, scene, pts_mm: np.ndarray, color, *, widths=(3.0, 1.6), **kw) -> None:
    """Solid backbone, thicker where the outer tube is present (tube segments by width)."""
    owners = backbone_owners(scene, len(pts_mm))
    seg_owner = owners[:-1]
    start = 0
    for k in range(1, len(seg_owner) + 1):
        if k == len(seg_owner) or seg_owner[k] != seg_owner[start]:
            p = pts_mm[start:k + 1]
            lw = widths[min(int(seg_owner[start]), len(widths) - 1)]
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=color, linewidth=lw,
                    solid_capstyle="round", **kw)
            start = k


def draw_dashed(ax, pts_mm: np.ndarray, color="k", lw=1.0) -> None:
    ax.plot(pts_mm[:, 0], pts_mm[:, 1], pts_mm[:, 2], color=color, linestyle=(0, (3, 2)),
            linewidth=lw)


def orifice(ax) -> None:
    ax.scatter([0], [0], [0], color="0.3", marker="s", s=18, depthshade=False)


def pvs_points(eq) -> np.ndarray:
    return eq.backbone(POINTS)[0].detach().cpu().numpy() * MM


def tip_err_mm(eq, ref) -> float:
    return float(np.linalg.norm(eq.tip_position[0].detach().cpu().numpy() - ref.tip_position)) * MM


def theta_deg(x) -> float:
    """theta_2(L_1) [deg] from an Equilibrium's (1, 1) tensor or a StandardSolution's (1,) array."""
    v = x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x)
    return math.degrees(float(np.asarray(v).ravel()[0]))


# ---------------------------------------------------------------------------------------------
# Fig. 2

def figure2(out: Path) -> None:
    print("\n=== Fig. 2: section III-B robot, alpha_2 = 180 deg: three equilibria ===")
    scene = torchpvs.load_scene("renda2021_section3b")
    pi = scene.actuation.rotation[1]
    root = torchpvs.SolverOptions(method="root")

    def approach(delta: float):
        """Solve at alpha_2 = pi + delta, then warm start from it at alpha_2 = pi."""
        return torchpvs.solve(scene, initial=torchpvs.solve(scene, rotation=[0.0, pi + delta]))

    pvs, refs = {}, {}
    tasks = [
        # Stable branches: approach alpha_2 = pi from below / from above, then warm start at pi.
        ("a", lambda: approach(-0.3)),
        ("b", lambda: approach(+0.3)),
        # Unstable symmetric equilibrium: plain Newton from the torsionless default guess.
        ("u", lambda: torchpvs.solve(scene, options=root)),
        # Standard model: the initial torsional moments m_j(0) [N m] pick the branch.
        ("ref a", lambda: solve_standard(scene, tol=1e-10, initial=[-0.1, 0.1])),
        ("ref b", lambda: solve_standard(scene, tol=1e-10, initial=[0.1, -0.1])),
        ("ref u", lambda: solve_standard(scene, tol=1e-10)),
    ]
    for name, fn in progress(tasks, "Fig. 2 solves"):
        if name.startswith("ref "):
            refs[name[4:]] = fn()
        else:
            pvs[name] = fn()

    # Pair each PVS equilibrium with the standard one of the same branch (sign of theta_2).
    for key in ("a", "b"):
        if np.sign(theta_deg(pvs[key].relative_rotation_at_outer_tip)) != np.sign(
                theta_deg(refs[key].relative_rotation_at_outer_tip)):
            refs["a"], refs["b"] = refs["b"], refs["a"]
            break

    colors = {"a": "tab:blue", "b": "tab:orange", "u": "tab:red"}
    fig = figure((6.6, 7.6))
    ax = fig.add_axes([0.0, 0.21, 1.0, 0.75], projection="3d")
    clouds = []
    handles = []
    print(f"  {'':9s} {'PVS theta2(L1)':>15s} {'std theta2(L1)':>15s} {'PVS stable':>10s} "
          f"{'std stable':>10s} {'PVS order/dofs':>14s} {'tip err [mm]':>12s}  PVS tip [mm]")
    for key in ("a", "b", "u"):
        eq, ref = pvs[key], refs[key]
        p, r = pvs_points(eq), ref.backbone(POINTS) * MM
        clouds += [p, r]
        draw_backbone(ax, scene, p, colors[key])
        draw_dashed(ax, r)
        th_p = theta_deg(eq.relative_rotation_at_outer_tip)
        th_r = theta_deg(ref.relative_rotation_at_outer_tip)
        st = "stable" if bool(eq.stable[0]) else "unstable"
        err = tip_err_mm(eq, ref)
        tip = eq.tip_position[0].numpy() * MM
        print(f"  {st:9s} {th_p:+14.2f}° {th_r:+14.2f}° {str(bool(eq.stable[0])):>10s} "
              f"{str(ref.stable):>10s} {eq.order:>8d}/{int(eq.dofs[0]):<5d} {err:12.2e}  "
              f"({tip[0]:.2f}, {tip[1]:.2f}, {tip[2]:.2f})")
        if not (bool(eq.converged[0]) and ref.converged):
            print(f"  WARNING: {key}: PVS converged={bool(eq.converged[0])}, "
                  f"standard converged={ref.converged}")
        handles.append(Line2D([], [], color=colors[key], lw=2.5,
                              label=f"{st}: $\\theta_2(L_1)$ = {th_p:+.2f}° PVS, "
                                    f"{th_r:+.2f}° standard"))
    orifice(ax)
    handles += [Line2D([], [], color="0.4", lw=2.5, label="PVS (solid; thick: both tubes)"),
                Line2D([], [], color="k", lw=1.0, ls=(0, (3, 2)), label="standard model (dashed)")]
    set_equal_3d(ax, clouds, zoom=1.0)
    ax.view_init(elev=20, azim=-50)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    fig.suptitle("Section III-B robot, $\\alpha_2$ = 180°: three equilibria", fontsize=11,
                 y=0.98)
    fig.legend(handles=handles, loc="lower center", fontsize=8.5, ncol=1, frameon=False,
               bbox_to_anchor=(0.5, 0.0))
    print("  paper: theta_2(L1) = ±84.4° (standard), ±85.5° (linear PVS)")
    save(fig, out, "fig2_section3b_equilibria.png", dpi=DPI, tight=False)


# ---------------------------------------------------------------------------------------------
# Fig. 4

def sweep(scene, d2: float, angles_deg, order: int, label: str):
    """Follow the branch from alpha_2 = 0 with warm starts; returns per-step records."""
    s2 = scene.with_actuation(insertion=[D1_FIG3, d2])
    opts = torchpvs.SolverOptions(order=order)
    prev_eq = prev_auto = prev_ref = None
    rows = []
    for a in progress(angles_deg, f"Fig. 4 {label}"):
        rot = [0.0, math.radians(a)]
        eq = torchpvs.solve(s2, rotation=rot, options=opts, initial=prev_eq)
        auto = torchpvs.solve(s2, rotation=rot, initial=prev_auto)   # default accuracy 1e-5 m
        ref = solve_standard(s2.with_actuation(rotation=rot), tol=1e-10, initial=prev_ref,
                             compute_forces=False)
        rows.append({"alpha": a, "eq": eq, "auto": auto, "ref": ref, "scene": s2,
                     "err": tip_err_mm(eq, ref), "err_auto": tip_err_mm(auto, ref)})
        prev_eq, prev_auto, prev_ref = eq, auto, ref
    return rows


def figure4(out: Path, step: int, order: int) -> None:
    print(f"\n=== Fig. 4: Fig. 3 robot, inner tube rotated (D1 = 93.5 mm, alpha1 = 0), "
          f"PVS order {order} ===")
    scene = torchpvs.load_scene("renda2021_fig3")
    cases = (("full", D2_FULL, 280), ("partial", D2_PARTIAL, 200))
    fig = figure((9.6, 6.6))
    cmap = matplotlib.colormaps["viridis"]
    summary = []
    for i, (name, d2, amax) in enumerate(cases):
        angles = list(range(0, amax + 1, step))
        rows = sweep(scene, d2, angles, order, name)
        print(f"  {name} overlap, D2 = {d2 * MM:.1f} mm:")
        print(f"    {'a2[deg]':>7s} {'th2 PVS':>9s} {'th2 std':>9s} {'stable P/S':>11s} "
              f"{'err o' + str(order) + ' [mm]':>13s} {'err auto [mm]':>13s} (auto order)  "
              f"PVS tip [mm]")
        ax = fig.add_axes([-0.02 + 0.54 * i, 0.08, 0.5, 0.8], projection="3d")
        clouds = []
        for r in rows:
            eq, ref = r["eq"], r["ref"]
            col = cmap(r["alpha"] / 280.0 * 0.92)
            p, q = pvs_points(eq), ref.backbone(POINTS) * MM
            clouds += [p, q]
            draw_backbone(ax, r["scene"], p, col, widths=(2.4, 1.3))
            draw_dashed(ax, q, lw=0.8)
            th_p = theta_deg(eq.relative_rotation_at_outer_tip)
            th_r = theta_deg(ref.relative_rotation_at_outer_tip)
            tip = eq.tip_position[0].numpy() * MM
            flags = f"{'Y' if bool(eq.stable[0]) else 'N'}/{'Y' if ref.stable else 'N'}"
            print(f"    {r['alpha']:7d} {th_p:+9.3f} {th_r:+9.3f} {flags:>11s} "
                  f"{r['err']:13.3e} {r['err_auto']:13.3e} ({r['auto'].order})  "
                  f"({tip[0]:7.2f}, {tip[1]:7.2f}, {tip[2]:7.2f})")
            if not (bool(eq.converged[0]) and bool(r["auto"].converged[0]) and ref.converged):
                print("    WARNING: a solve did not converge at this step")
            if abs(th_p - th_r) > 5.0:
                print("    WARNING: PVS and standard on different branches at this step")
        errs = np.array([r["err"] for r in rows])
        errs_auto = np.array([r["err_auto"] for r in rows])
        pmax, pmean = PAPER_FIG4[name]
        print(f"    tip error PVS order {order} vs standard: max {errs.max():.3e} mm, "
              f"mean {errs.mean():.3e} mm   (paper, quadratic PVS: max {pmax} mm, "
              f"mean {pmean} mm)")
        print(f"    tip error PVS default accuracy (1e-5 m) vs standard: "
              f"max {errs_auto.max():.3e} mm, mean {errs_auto.mean():.3e} mm")
        summary.append((name, errs.max(), errs.mean()))
        orifice(ax)
        set_equal_3d(ax, clouds, zoom=1.05)
        ax.view_init(elev=22, azim=-35)
        ax.set_xlabel("x [mm]", fontsize=8)
        ax.set_ylabel("y [mm]", fontsize=8)
        ax.set_zlabel("z [mm]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"{name} overlap, $D_2$ = {d2 * MM:.1f} mm, $\\alpha_2$ = 0..{amax}° "
                     f"by {step}°\ntip error: max {errs.max():.1e} mm, mean {errs.mean():.1e} mm",
                     fontsize=9.5)
    sm = matplotlib.cm.ScalarMappable(cmap=matplotlib.colors.ListedColormap(
        cmap(np.linspace(0, 0.92, 256))), norm=matplotlib.colors.Normalize(0, 280))
    cax = fig.add_axes([0.5, 0.3, 0.013, 0.45])
    cb = fig.colorbar(sm, cax=cax, orientation="vertical")
    cax.set_title("$\\alpha_2$ [deg]", fontsize=9)
    cb.set_ticks(range(0, 281, 40))
    cb.ax.tick_params(labelsize=8)
    handles = [Line2D([], [], color="0.3", lw=2.2,
                      label=f"PVS, order {order}\n(thick: both tubes)"),
               Line2D([], [], color="k", lw=0.9, ls=(0, (3, 2)), label="standard model")]
    fig.legend(handles=handles, loc="upper center", ncol=1, fontsize=8.5, frameon=False,
               bbox_to_anchor=(0.505, 0.27))
    fig.suptitle("Fig. 3 robot ($D_1$ = 93.5 mm, $\\alpha_1$ = 0): inner tube rotation, "
                 "branch followed from $\\alpha_2$ = 0", fontsize=11, y=0.985)
    save(fig, out, "fig4_sweeps.png", dpi=DPI, tight=False)


# ---------------------------------------------------------------------------------------------
# order convergence

def order_convergence(out: Path, orders, fine_magnus: int = 64) -> None:
    print("\n=== Order convergence: PVS tip error vs standard model (tol 1e-12) ===")
    s3b = torchpvs.load_scene("renda2021_section3b")
    fig3 = torchpvs.load_scene("renda2021_fig3")          # alpha_2 = 80 deg by default
    # section III-B: the stable branch with theta_2(L1) > 0 (approached from alpha_2 < pi)
    start = torchpvs.solve(s3b, rotation=[0.0, math.pi - 0.3])
    ref3b = solve_standard(s3b, tol=1e-12, initial=[-0.1, 0.1], compute_forces=False)
    ref3 = solve_standard(fig3, tol=1e-12, compute_forces=False)
    cases = [("III-B, stable branch", s3b, start, ref3b, "tab:blue", "o"),
             ("Fig. 3, $\\alpha_2$ = 80°", fig3, None, ref3, "tab:green", "s")]
    magnus = (8, fine_magnus)    # default Magnus steps per section for the tip pose, and finer

    fig = figure((7.0, 4.8))
    ax = fig.add_subplot()
    ax2 = ax.twinx()
    for label, scene, init, ref, col, mk in cases:
        rows = []
        prev = init
        for k in progress(orders, "orders " + label.split(",")[0].replace("$", "")):
            res = {}
            for nm in magnus:   # n_magnus changes only the pose integration, not q
                res[nm] = torchpvs.solve(scene, initial=res.get(magnus[0], prev),
                                         options=torchpvs.SolverOptions(order=k, n_magnus=nm))
            prev = res[magnus[0]]
            rows.append((k, res))
        plain = label.replace("$", "").replace("\\", "")
        print(f"  {plain}: reference theta_2(L1) = "
              f"{theta_deg(ref.relative_rotation_at_outer_tip):+.4f}°, tip "
              f"{np.array2string(ref.tip_position * MM, precision=3)} mm")
        print(f"    {'order':>5s} {'dofs':>5s} {'err [mm] n_magnus=8':>20s} "
              f"{f'err [mm] n_magnus={fine_magnus}':>21s} {'theta2(L1)':>11s} {'stable':>6s} "
              f"{'conv':>5s}")
        errs = {nm: [] for nm in magnus}
        dofs = []
        for k, res in rows:
            for nm in magnus:
                errs[nm].append(tip_err_mm(res[nm], ref))
            eq = res[magnus[0]]
            dofs.append(int(eq.dofs[0]))
            conv = all(bool(e.converged[0]) for e in res.values())
            print(f"    {k:5d} {dofs[-1]:5d} {errs[8][-1]:20.3e} {errs[fine_magnus][-1]:21.3e} "
                  f"{theta_deg(eq.relative_rotation_at_outer_tip):+10.4f}° "
                  f"{str(bool(eq.stable[0])):>6s} {str(conv):>5s}")
        ax.semilogy(orders, np.maximum(errs[fine_magnus], 1e-12), color=col, marker=mk, lw=1.8,
                    label=f"{label}: tip error, {fine_magnus} Magnus steps")
        ax.semilogy(orders, np.maximum(errs[8], 1e-12), color=col, marker=mk, ms=4, lw=1.0,
                    ls="--", alpha=0.55, label=f"{label}: tip error, 8 (default)")
        ax2.plot(orders, dofs, color=col, marker=mk, mfc="none", ls=":", lw=1.0,
                 label=f"{label}: dofs (right)")
    ax.set_xlabel("polynomial order of the strain bases")
    ax.set_ylabel("PVS tip error vs standard model [mm]")
    ax2.set_ylabel("generalized coordinates (dofs), dotted")
    ax.set_xticks(list(orders))
    ax.grid(True, which="major", alpha=0.4)
    ax.grid(True, which="minor", alpha=0.12)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    fig.legend(h1 + h2, l1 + l2, loc="lower center", fontsize=7.5, ncol=2, frameon=False)
    ax.set_title("PVS convergence with basis order (reference: shooting, tol 1e-12)",
                 fontsize=10)
    fig.subplots_adjust(left=0.12, right=0.89, top=0.93, bottom=0.3)
    save(fig, out, "order_convergence.png", dpi=DPI, tight=False)


# ---------------------------------------------------------------------------------------------

def main(argv=None) -> None:
    ap = parser(__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="fewer steps: 40 deg sweeps, orders 1..5")
    ap.add_argument("--sweep-order", type=int, default=2,
                    help="PVS basis order of the Fig. 4 sweeps (default 2, the paper's quadratic)")
    args = ap.parse_args(argv)
    warnings.simplefilter("default")
    t0 = time.perf_counter()
    figure2(args.out)
    figure4(args.out, step=40 if args.quick else 20, order=args.sweep_order)
    order_convergence(args.out, list(range(1, 6 if args.quick else 8)))
    print(f"\ndone in {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
