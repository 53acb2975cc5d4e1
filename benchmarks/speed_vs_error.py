"""Speed against error: the PVS solver at each accuracy setting / basis order and the
standard-model reference at each integration tolerance, measured side by side in one run.

    MPLBACKEND=Agg python benchmarks/speed_vs_error.py [--quick] [--out docs/figures]

Configurations: the paper's Fig. 3 sweeps (Renda et al. 2021, section III-C: full overlap
alpha2 = 0..280 deg, partial overlap 0..200 deg, by 20 deg, on the branch reached by rotating
from 0) and seeded random 2- and 3-tube scenes (the generator of tests/test_pvs_vs_reference.py,
torchpvs.testing.random_scene).

Ground truth per configuration: the reference at tol 1e-12 on the branch of PVS at order 7 with
64 Magnus steps per section; the two are cross-checked (the largest disagreement is printed) and
configurations where no reference equilibrium lies within 1 mm of PVS's are dropped (counted).

Timings (median of ``--repeat`` runs of the whole set, divided by the number of solves), one
torch thread, float64, no actuation forces in either solver:
* cold: default initial guess (PVS: torsionless eq. (31) guess; reference: zero torsion);
* warm: Fig. 3: started from the previous sweep step (20 deg away, the branch following of the
  paper); random scenes: started from the equilibrium at alpha_N - 0.02 rad;
* batched (PVS only): all Fig. 3 configurations replicated to B = 208 in one cold call.
Tip error: max and median over configurations of |tip - truth|, from the warm solves on Fig. 3
and from the cold solves on random scenes; solves on another equilibrium of these multi-stable
robots (> 5 mm away) are counted as "branch misses" and excluded from the error statistics.

Prints a markdown table and the frontier (fastest setting reaching 1, 0.1, 0.01 mm max error)
and writes a log-log Pareto figure ``speed_vs_error.png``.
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import torchpvs as tp
from torchpvs.reference import solve_standard
from torchpvs.testing import SWEEPS, fig3, matched_reference, random_scene

ROOT = Path(__file__).resolve().parents[1]

MISS = 5e-3          # [m] a cold solve this far from the truth reached another equilibrium


def pvs_settings(quick: bool):
    out = [(f"order {k}, 8 Magnus", tp.SolverOptions(order=k, n_magnus=8, compute_forces=False))
           for k in ([1, 2, 3, 5] if quick else [1, 2, 3, 4, 5, 6])]
    out += [(f"order {k}, 32 Magnus", tp.SolverOptions(order=k, n_magnus=32,
                                                       compute_forces=False))
            for k in ([5] if quick else [3, 5, 7])]
    out += [(f"auto, accuracy {a:.0e}", tp.SolverOptions(accuracy=a, compute_forces=False))
            for a in ([1e-3, 1e-5, 1e-7] if quick else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8])]
    return out


def ref_tols(quick: bool):
    return [1e-3, 1e-6, 1e-10] if quick else [1e-3, 1e-4, 1e-6, 1e-8, 1e-10]


# ---------------------------------------------------------------------------------------------
# configurations and ground truth

def build_configs(quick: bool, n_random: int):
    """List of dicts: scene, group, warm-start predecessor index (Fig. 3) or scene at a nearby
    actuation (random)."""
    cfgs = []
    for case, (D2, alphas) in SWEEPS.items():
        alphas = alphas[::2] if quick else alphas
        for i, a in enumerate(alphas):
            cfgs.append({"scene": fig3(D2, a), "group": f"fig3-{case}", "label": f"{case} {a}",
                         "prev": len(cfgs) - 1 if i > 0 else None})
    for seed in range(n_random):
        sc = random_scene(seed)
        rot = list(sc.actuation.rotation)
        rot[-1] -= 0.02
        cfgs.append({"scene": sc, "group": "random", "label": f"seed {seed}", "prev": None,
                     "near": sc.with_actuation(rotation=rot)})
    return cfgs


def ground_truth(cfgs):
    fine = tp.SolverOptions(order=7, n_magnus=64)
    keep, cross = [], 0.0
    prev_p, prev_r = {}, {}
    for i, c in enumerate(cfgs):
        init_p = prev_p.get(c["prev"])
        p = tp.solve(c["scene"], initial=init_p, options=fine)
        if c["group"].startswith("fig3"):
            r = solve_standard(c["scene"], tol=1e-12, initial=prev_r.get(c["prev"]),
                               compute_forces=False, compute_stability=False)
            r = r if r.converged else None
        else:
            r = matched_reference(c["scene"], p, tol=1e-12, seed=i, compute_stability=False,
                                  compute_forces=False)
        prev_p[i], prev_r[i] = p, r
        if r is None or not bool(p.converged[0]):
            continue
        t_ref = np.asarray(r.tip_position)
        cross = max(cross, float(np.linalg.norm(p.tip_position[0].numpy() - t_ref)))
        c["truth"] = t_ref
        c["ref_guess"] = r if c["group"].startswith("fig3") else None
        keep.append(i)
    return keep, cross


# ---------------------------------------------------------------------------------------------
# measurement

def timed(fn, repeat: int):
    fn()                                    # warm-up (allocations, caches)
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), out


def measure_pvs(cfgs, keep, opts, repeat):
    n = len(keep)
    # warm-start sources, solved untimed with the same options
    near = {i: tp.solve(cfgs[i]["near"], options=opts) for i in keep if "near" in cfgs[i]}

    def cold():
        return {i: tp.solve(cfgs[i]["scene"], options=opts) for i in keep}

    def warm():
        out = {}
        for i in range(len(cfgs)):                       # sweeps in order (branch following)
            c = cfgs[i]
            if c["group"].startswith("fig3"):
                out[i] = tp.solve(c["scene"], initial=out.get(c["prev"]), options=opts)
            elif i in keep:
                out[i] = tp.solve(c["scene"], initial=near[i], options=opts)
        return out

    t_cold, res_cold = timed(cold, repeat)
    t_warm, res_warm = timed(warm, repeat)
    n_warm = len(cfgs) - sum(1 for c in cfgs if c["group"] == "random") + len(near)
    errs, misses = tip_errors(cfgs, keep, res_cold, res_warm,
                              lambda x: x.tip_position[0].numpy())
    dofs = [int(res_cold[i].dofs[0]) for i in keep]
    orders = {res_warm[i].order for i in keep} | {res_cold[i].order for i in keep}
    # batched: the Fig. 3 configurations, replicated to B = 8 x 26, one cold call
    fig = [i for i in keep if cfgs[i]["group"].startswith("fig3")]
    D = torch.tensor([list(cfgs[i]["scene"].actuation.insertion) for i in fig] * 8,
                     dtype=torch.float64)
    A = torch.tensor([list(cfgs[i]["scene"].actuation.rotation) for i in fig] * 8,
                     dtype=torch.float64)
    t_b, _ = timed(lambda: tp.solve(cfgs[fig[0]]["scene"], insertion=D, rotation=A,
                                    options=opts), max(1, repeat // 2 + 1))
    return {"err": np.array(errs or [np.nan]), "cold": t_cold / n, "warm": t_warm / n_warm,
            "batched": t_b / len(D), "misses": misses, "dofs": int(np.median(dofs)),
            "orders": sorted(orders), "B": len(D)}


def measure_ref(cfgs, keep, tol, repeat):
    n = len(keep)

    def run(initials):
        return {i: solve_standard(cfgs[i]["scene"], tol=tol, initial=initials(i),
                                  compute_forces=False, compute_stability=False) for i in keep}

    near = {i: solve_standard(cfgs[i]["near"], tol=tol, initial=_ref_branch_guess(cfgs[i]),
                              compute_forces=False, compute_stability=False)
            for i in keep if "near" in cfgs[i]}
    t_cold, res_cold = timed(lambda: run(lambda i: None), repeat)

    def warm():
        out = {}
        for i in range(len(cfgs)):
            c = cfgs[i]
            if c["group"].startswith("fig3"):
                out[i] = solve_standard(c["scene"], tol=tol, initial=out.get(c["prev"]),
                                        compute_forces=False, compute_stability=False)
            elif i in keep:
                out[i] = solve_standard(c["scene"], tol=tol, initial=near[i],
                                        compute_forces=False, compute_stability=False)
        return out

    t_warm, res_warm = timed(warm, repeat)
    n_warm = len(cfgs) - sum(1 for c in cfgs if c["group"] == "random") + len(near)
    errs, misses = tip_errors(cfgs, keep, res_cold, res_warm, lambda x: x.tip_position)
    dofs = [res_cold[i].dofs for i in keep]
    return {"err": np.array(errs or [np.nan]), "cold": t_cold / n, "warm": t_warm / n_warm,
            "batched": float("nan"), "misses": misses, "dofs": int(np.median(dofs)),
            "orders": [], "B": 1}


def tip_errors(cfgs, keep, res_cold, res_warm, tip_of):
    """Tip errors [m] over the kept configurations — warm solves on the Fig. 3 sweeps (the
    paper's branch), cold solves on random scenes — and the branch misses ``(cold, warm)``:
    solves ending more than ``MISS`` from the truth, i.e. on another equilibrium of a
    multi-stable robot (or a failed solve). A miss is excluded from the error statistics; the
    other solve of the same configuration is used in its place when it is on the branch."""
    errs, miss_c, miss_w = [], 0, 0
    for i in keep:
        truth = cfgs[i]["truth"]
        e_c = float(np.linalg.norm(tip_of(res_cold[i]) - truth))
        e_w = float(np.linalg.norm(tip_of(res_warm[i]) - truth))
        miss_c += not e_c <= MISS
        miss_w += not e_w <= MISS
        first, second = (e_w, e_c) if cfgs[i]["group"].startswith("fig3") else (e_c, e_w)
        e = first if first <= MISS else second
        if e <= MISS:
            errs.append(e)
    return errs, (miss_c, miss_w)


def _ref_branch_guess(c):
    """Warm-start source of a random scene's reference: the truth's branch (its orifice
    torsion), so that warm solves measure the speed on the right branch."""
    return c.get("truth_ref")


# ---------------------------------------------------------------------------------------------
# output

THRESHOLDS = (1e-3, 1e-4, 1e-5, 1e-6, 1e-7)


def frontier(rows, key: str, thresholds=THRESHOLDS):
    out = {}
    for thr in thresholds:
        ok = [r for r in rows if r["err"].max() <= thr]
        out[thr] = min(ok, key=lambda r: r[key]) if ok else None
    return out


def plot(rows_pvs, rows_ref, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.6))
    FigureCanvasAgg(fig)
    for k, (stat, name) in enumerate((("max", "max"), ("median", "median"))):
        ax = fig.add_subplot(1, 2, k + 1)
        series = [
            ("PVS fixed order, warm", [r for r in rows_pvs if "8 Magnus" in r["name"]], "warm",
             "C0", "o-"),
            ("PVS fixed order, cold", [r for r in rows_pvs if "8 Magnus" in r["name"]], "cold",
             "C0", "o--"),
            ("PVS auto accuracy, warm", [r for r in rows_pvs if "auto" in r["name"]], "warm",
             "C2", "s-"),
            ("PVS auto accuracy, cold", [r for r in rows_pvs if "auto" in r["name"]], "cold",
             "C2", "s--"),
            ("PVS fixed order, batched", [r for r in rows_pvs if "8 Magnus" in r["name"]],
             "batched", "C4", "^:"),
            ("PVS order 3/5/7, 32 Magnus, warm",
             [r for r in rows_pvs if "32 Magnus" in r["name"]], "warm", "C1", "v-"),
            ("reference, warm", rows_ref, "warm", "C3", "D-"),
            ("reference, cold", rows_ref, "cold", "C3", "D--"),
        ]
        for label, rs, key, color, style in series:
            if not rs:
                continue
            rs = sorted(rs, key=lambda r: -getattr(np, stat)(r["err"]))
            x = [max(getattr(np, stat)(r["err"]) * 1e3, 1e-9) for r in rs]
            y = [r[key] * 1e3 for r in rs]
            ax.loglog(x, y, style, color=color, label=label, ms=4,
                      mfc="none" if "cold" in label else color)
        for thr in (1.0, 0.1, 0.01):
            ax.axvline(thr, color="0.85", lw=0.8, zorder=0)
        ax.set_xlabel(f"{name} tip error vs converged reference [mm]")
        ax.set_ylabel("time per solve [ms]")
        ax.grid(True, which="major", alpha=0.3)
        if k == 0:
            ax.legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def selection_table(cfgs, keep, quick: bool) -> None:
    """How the automatic order and Magnus selection behave: chosen orders and Magnus step
    counts, and the true error against the requested accuracy and the reported estimate."""
    print("\nAutomatic selection (order=None, n_magnus=None), same configurations:\n")
    print("| accuracy [m] | orders chosen (count) | Magnus steps (count) | max error [m] | "
          "max error / accuracy | error <= error_estimate | max error / estimate (worst case) |")
    print("|---|---|---|---|---|---|---|")
    from collections import Counter
    for acc in ([1e-3, 1e-5, 1e-7] if quick else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]):
        opts = tp.SolverOptions(accuracy=acc, compute_forces=False)
        orders, mag, errs, ests = Counter(), Counter(), [], []
        prev = {}
        for i in range(len(cfgs)):
            c = cfgs[i]
            if not (c["group"].startswith("fig3") or i in keep):
                continue
            eq = tp.solve(c["scene"], options=opts,
                          initial=prev.get(c["prev"]) if c["group"].startswith("fig3") else None)
            prev[i] = eq
            if i not in keep:
                continue
            e = float(np.linalg.norm(eq.tip_position[0].numpy() - c["truth"]))
            if e > MISS:
                continue
            orders[eq.order] += 1
            mag[eq.context.discretization.n_magnus] += 1
            errs.append(e)
            ests.append(float(eq.error_estimate[0]))
        errs, ests = np.array(errs), np.array(ests)
        ratio = errs / np.maximum(ests, 1e-300)
        w = int(ratio.argmax())
        fmt = lambda cnt: ", ".join(f"{k}: {v}" for k, v in sorted(cnt.items()))  # noqa: E731
        print(f"| {acc:.0e} | {fmt(orders)} | {fmt(mag)} | {errs.max():.2e} | "
              f"{errs.max() / acc:.2g} | {int((errs <= ests).sum())}/{len(errs)} | "
              f"{ratio[w]:.2g} ({errs[w]:.1e} m at estimate {ests[w]:.1e} m) |", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer configurations and settings")
    ap.add_argument("--random", type=int, default=None, help="number of random scenes")
    ap.add_argument("--repeat", type=int, default=None)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    args = ap.parse_args(argv)
    n_random = args.random if args.random is not None else (6 if args.quick else 16)
    repeat = args.repeat or (1 if args.quick else 3)
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", RuntimeWarning)
    t_start = time.perf_counter()

    cfgs = build_configs(args.quick, n_random)
    keep, cross = ground_truth(cfgs)
    for i in keep:  # reference warm-start source of random scenes: the truth's branch
        if cfgs[i]["group"] == "random":
            p = tp.solve(cfgs[i]["near"], options=tp.SolverOptions(order=5))
            r = matched_reference(cfgs[i]["near"], p, tol=1e-10, compute_stability=False,
                                  compute_forces=False)
            cfgs[i]["truth_ref"] = r
    n_fig = sum(1 for i in keep if cfgs[i]["group"].startswith("fig3"))
    print(f"# speed vs error — {platform.processor() or platform.machine()}, 1 torch thread, "
          f"torch {torch.__version__}, float64{' (--quick)' if args.quick else ''}")
    print(f"\n{len(keep)} configurations: {n_fig} Fig. 3 sweep steps + "
          f"{len(keep) - n_fig} random scenes ({n_random - (len(keep) - n_fig)} random scenes "
          f"dropped: no reference equilibrium within 1 mm of PVS's). Truth: reference tol 1e-12;"
          f" cross-check vs PVS order 7 + 64 Magnus steps: max {cross:.1e} m.\n")

    rows_pvs, rows_ref = [], []
    for name, opts in pvs_settings(args.quick):
        r = measure_pvs(cfgs, keep, opts, repeat)
        r["name"] = name
        rows_pvs.append(r)
        print(f"  measured PVS {name}", file=sys.stderr, flush=True)
    for tol in ref_tols(args.quick):
        r = measure_ref(cfgs, keep, tol, repeat)
        r["name"] = f"tol {tol:.0e}"
        rows_ref.append(r)
        print(f"  measured reference tol {tol:.0e}", file=sys.stderr, flush=True)

    B = rows_pvs[0]["B"]
    print("| solver | setting | dofs (median) | orders | max tip error [mm] | median [mm] | "
          f"cold [ms/solve] | warm [ms/solve] | batched B={B} [ms/solve] | "
          "branch misses cold/warm |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for solver, rows in (("PVS", rows_pvs), ("reference", rows_ref)):
        for r in rows:
            b = "—" if math.isnan(r["batched"]) else f"{r['batched'] * 1e3:.3f}"
            print(f"| {solver} | {r['name']} | {r['dofs']} | "
                  f"{','.join(map(str, r['orders'])) or '—'} | {r['err'].max() * 1e3:.2e} | "
                  f"{np.median(r['err']) * 1e3:.2e} | {r['cold'] * 1e3:.2f} | "
                  f"{r['warm'] * 1e3:.2f} | {b} | {r['misses'][0]}/{r['misses'][1]} |")

    print("\nFrontier: fastest setting whose MAX tip error is below the threshold "
          "(time per solve [ms], setting)\n")
    print("| max error ≤ | PVS cold | PVS warm | PVS batched | reference cold | reference warm |")
    print("|---|---|---|---|---|---|")
    fr = {(s, k): frontier(rows, k) for s, rows in (("pvs", rows_pvs), ("ref", rows_ref))
          for k in ("cold", "warm", "batched")}
    for thr in THRESHOLDS:
        cells = []
        for s, k in (("pvs", "cold"), ("pvs", "warm"), ("pvs", "batched"), ("ref", "cold"),
                     ("ref", "warm")):
            r = fr[(s, k)][thr]
            cells.append("not reached" if r is None else f"{r[k] * 1e3:.2f} ({r['name']})")
        print(f"| {thr * 1e3:g} mm | " + " | ".join(cells) + " |")
    print(f"\n(errors below ~{10 * cross * 1e3:.0e} mm are at the truth's own accuracy; a "
          "branch miss is a solve on another equilibrium, excluded from the error statistics)")

    selection_table(cfgs, keep, args.quick)

    title = (f"torchpvs: time per solve vs tip error, Fig. 3 sweeps + random 2/3-tube scenes "
             f"({len(keep)} configurations), 1 CPU thread, float64")
    path = args.out / "speed_vs_error.png"
    plot(rows_pvs, rows_ref, path, title)
    print(f"\nfigure: {path}  (total {time.perf_counter() - t_start:.0f} s)")


if __name__ == "__main__":
    main()
