"""Scaling of the PVS solver: time and degrees of freedom against the number of tubes (2..6),
the basis order and the batch size (1..4096), measured in one run.

    MPLBACKEND=Agg python benchmarks/scaling.py [--quick] [--out docs/figures]

* tubes: valid nested robots from ``torchpvs.testing.nested_scene`` (outermost OD 4 mm,
  each tube's precurved part partly exposed beyond the one around it), 4 seeds per count, fixed
  order 3 with 8 Magnus steps per section (and the default automatic settings), cold solves;
  batched: 256 copies of seed 0 with the rotations perturbed by up to 0.05 rad;
* order: the paper's Fig. 3 robot (2 tubes) and a 4-tube robot, order 1..7, 8 Magnus steps;
* batch: the Fig. 3 robot at B random actuations (alpha2 in [0, 140] deg, on the stable branch
  from 0), one cold call, order 3, 8 Magnus steps.

The paper (Renda et al. 2021) claims the cost grows linearly with the number of tubes and of
dofs; this script fits power laws ``time ~ x^p`` (least squares in log-log) and prints the
slopes p (p = 1: linear). One torch thread, float64, CPU; CUDA is not measured here (the
``--device cuda`` flag runs the same on a GPU when one is present).
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import torchpvs as tp
from torchpvs.sections import n_coordinates
from torchpvs.testing import nested_scene

ROOT = Path(__file__).resolve().parents[1]

def timed(fn, repeat: int) -> tuple[float, object]:
    out = fn()  # warm-up
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def slope(x, y) -> float:
    """Least-squares exponent p of y ~ x^p."""
    return float(np.polyfit(np.log(np.asarray(x, float)), np.log(np.asarray(y, float)), 1)[0])


def linear_fit(x, y) -> tuple[float, float, float]:
    """y = a + b x: (a, b, R^2)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    b, a = np.polyfit(x, y, 1)
    r2 = 1 - ((y - a - b * x) ** 2).sum() / ((y - y.mean()) ** 2).sum()
    return float(a), float(b), float(r2)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="batch up to 1024, fewer repeats")
    ap.add_argument("--repeat", type=int, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    args = ap.parse_args(argv)
    repeat = args.repeat or (1 if args.quick else 3)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    dev = torch.device(args.device)
    t_start = time.perf_counter()
    print(f"# PVS scaling — {platform.processor() or platform.machine()}, 1 torch thread, torch "
          f"{torch.__version__}, float64, device {dev}"
          f"{' (--quick)' if args.quick else ''}")
    if dev.type == "cpu":
        print("CUDA: not measured (no GPU available to this run).")

    # ---- tubes ---------------------------------------------------------------------------
    print("\n## Number of tubes (4 seeds each, cold single solves)\n")
    print("| tubes | active dofs (mean) | allocated coordinates | order 3 [ms] | "
          "default auto [ms] (orders) | order 3, batch 256 [ms/solve] |")
    print("|---|---|---|---|---|---|")
    fixed = tp.SolverOptions(order=3, n_magnus=8, compute_forces=False, device=dev)
    auto = tp.SolverOptions(compute_forces=False, device=dev)
    tubes_rows = []
    for n in range(2, 7):
        t_fix, t_auto, t_b, dofs, orders = [], [], [], [], set()
        for seed in range(4):
            sc = nested_scene(n, seed)
            t, eq = timed(lambda: tp.solve(sc, options=fixed), repeat)
            t_fix.append(t)
            dofs.append(int(eq.dofs[0]))
            t, eq = timed(lambda: tp.solve(sc, options=auto), repeat)
            t_auto.append(t)
            orders.add(eq.order)
            if seed == 0:
                g = torch.Generator().manual_seed(n)
                # the scene's own actuation, rotations perturbed by up to +-0.05 rad (the same
                # work per element as the single solve: batching efficiency, not harder cases)
                rot = torch.tensor(sc.actuation.rotation, dtype=torch.float64) + 0.05 * (
                    torch.rand(256, n, generator=g, dtype=torch.float64) * 2 - 1)
                t, _ = timed(lambda: tp.solve(sc, rotation=rot.to(dev), options=fixed),
                             max(1, repeat - 1))
                t_b.append(t / 256)
        row = {"n": n, "dofs": float(np.mean(dofs)), "nq": n_coordinates(n, 4),
               "fixed": float(np.mean(t_fix)), "auto": float(np.mean(t_auto)),
               "batch": float(np.mean(t_b))}
        tubes_rows.append(row)
        print(f"| {n} | {row['dofs']:.0f} | {row['nq']} | {row['fixed'] * 1e3:.2f} | "
              f"{row['auto'] * 1e3:.2f} ({','.join(map(str, sorted(orders)))}) | "
              f"{row['batch'] * 1e3:.3f} |", flush=True)
    ns = [r["n"] for r in tubes_rows]
    fits = {k: slope(ns, [r[k] for r in tubes_rows]) for k in ("fixed", "auto", "batch", "dofs")}
    fits_dofs = {k: slope([r["dofs"] for r in tubes_rows], [r[k] for r in tubes_rows])
                 for k in ("fixed", "batch")}
    lin = linear_fit(ns, [r["fixed"] for r in tubes_rows])
    print(f"\nPower-law fits over 2..6 tubes: dofs ~ N^{fits['dofs']:.2f}; time (order 3) ~ "
          f"N^{fits['fixed']:.2f}, (auto) ~ N^{fits['auto']:.2f}, (batch 256, per solve) ~ "
          f"N^{fits['batch']:.2f}; time vs dofs: single ~ dofs^{fits_dofs['fixed']:.2f}, "
          f"batched ~ dofs^{fits_dofs['batch']:.2f}. Linear fit time = a + b N (order 3): "
          f"a = {lin[0] * 1e3:.2f} ms, b = {lin[1] * 1e3:.2f} ms/tube, R^2 = {lin[2]:.3f}.")

    # ---- order ---------------------------------------------------------------------------
    print("\n## Basis order (cold single solves; batch 256 per solve)\n")
    print("| robot | order | active dofs | single [ms] | batch 256 [ms/solve] |")
    print("|---|---|---|---|---|")
    order_rows = {}
    for label, sc in (("Fig. 3 (2 tubes)", tp.load_scene("renda2021_fig3")),
                      ("4 tubes", nested_scene(4, 0))):
        rows = []
        g = torch.Generator().manual_seed(0)
        rot = torch.zeros(256, sc.n_tubes, dtype=torch.float64)
        rot[:, -1] = torch.rand(256, generator=g, dtype=torch.float64) * math.radians(140)
        for k in range(1, 8):
            opts = tp.SolverOptions(order=k, n_magnus=8, compute_forces=False, device=dev)
            t, eq = timed(lambda: tp.solve(sc, options=opts), repeat)
            tb, _ = timed(lambda: tp.solve(sc, rotation=rot.to(dev), options=opts),
                          max(1, repeat - 1))
            rows.append({"order": k, "dofs": int(eq.dofs[0]), "single": t, "batch": tb / 256})
            print(f"| {label} | {k} | {int(eq.dofs[0])} | {t * 1e3:.2f} | "
                  f"{tb / 256 * 1e3:.3f} |", flush=True)
        order_rows[label] = rows
    for label, rows in order_rows.items():
        d = [r["dofs"] for r in rows]
        print(f"{label}: single ~ dofs^{slope(d, [r['single'] for r in rows]):.2f}, batched ~ "
              f"dofs^{slope(d, [r['batch'] for r in rows]):.2f} (orders 1..7)")

    # ---- batch ---------------------------------------------------------------------------
    Bs = [1, 4, 16, 64, 256, 1024] + ([] if args.quick else [4096])
    print("\n## Batch size (Fig. 3 robot, order 3, 8 Magnus steps, one cold call)\n")
    print("| B | total [ms] | per solve [ms] | solves/s | converged |")
    print("|---|---|---|---|---|")
    sc = tp.load_scene("renda2021_fig3")
    opts = tp.SolverOptions(order=3, n_magnus=8, compute_forces=False, device=dev)
    batch_rows = []
    for B in Bs:
        g = torch.Generator().manual_seed(B)
        alpha = torch.rand(B, generator=g, dtype=torch.float64) * math.radians(140)
        rot = torch.stack([torch.zeros_like(alpha), alpha], -1).to(dev)
        t, eq = timed(lambda: tp.solve(sc, rotation=rot, options=opts),
                      1 if B >= 1024 else repeat)
        batch_rows.append({"B": B, "t": t})
        print(f"| {B} | {t * 1e3:.1f} | {t / B * 1e3:.3f} | {B / t:,.0f} | "
              f"{int(eq.converged.sum())}/{B} |", flush=True)
    big = [r for r in batch_rows if r["B"] >= 64]
    print(f"\nTotal time ~ B^{slope([r['B'] for r in big], [r['t'] for r in big]):.2f} for "
          f"B >= 64; per-solve time at B = {Bs[-1]} is "
          f"{batch_rows[0]['t'] / (batch_rows[-1]['t'] / Bs[-1]):.1f}x below B = 1.")

    # ---- figure --------------------------------------------------------------------------
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 4.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 3, 1)
    ax.loglog(ns, [r["fixed"] * 1e3 for r in tubes_rows], "o-", label="single, order 3")
    ax.loglog(ns, [r["auto"] * 1e3 for r in tubes_rows], "s-", label="single, automatic")
    ax.loglog(ns, [r["batch"] * 1e3 for r in tubes_rows], "^-", label="batch 256, per solve")
    ref = tubes_rows[0]["fixed"] * 1e3
    ax.loglog(ns, [ref * n / 2 for n in ns], "k:", lw=0.8, label="linear in N")
    ax.set_xlabel("number of tubes N")
    ax.set_ylabel("time per solve [ms]")
    ax.set_xticks(ns, [str(n) for n in ns])
    ax2 = ax.twinx()
    ax2.loglog(ns, [r["dofs"] for r in tubes_rows], "x--", color="0.5")
    ax2.set_ylabel("active dofs (order 3, grey)")
    ax.set_title(f"tubes: time ~ N^{fits['fixed']:.2f} (single), dofs ~ N^{fits['dofs']:.2f}",
                 fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 3, 2)
    for (label, rows), m in zip(order_rows.items(), "oD", strict=True):
        d = [r["dofs"] for r in rows]
        ax.loglog(d, [r["single"] * 1e3 for r in rows], m + "-", label=f"{label}, single")
        ax.loglog(d, [r["batch"] * 1e3 for r in rows], m + "--", label=f"{label}, batch 256")
    ax.set_xlabel("active dofs (basis order 1..7)")
    ax.set_ylabel("time per solve [ms]")
    ax.set_title("basis order", fontsize=9)
    ax.legend(fontsize=7)
    ax = fig.add_subplot(1, 3, 3)
    ax.loglog([r["B"] for r in batch_rows], [r["t"] / r["B"] * 1e3 for r in batch_rows], "o-")
    ax.set_xlabel("batch size B")
    ax.set_ylabel("time per solve [ms]")
    ax.set_title("batch (Fig. 3 robot, order 3)", fontsize=9)
    for a in fig.axes:
        a.grid(True, which="major", alpha=0.3)
    fig.suptitle(f"torchpvs scaling — CPU, 1 thread, float64 (device {dev}; CUDA not measured)"
                 if dev.type == "cpu" else f"torchpvs scaling — {dev}", fontsize=9)
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "scaling.png"
    fig.savefig(path, dpi=120)
    print(f"\nfigure: {path}  (total {time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
