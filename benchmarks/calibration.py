"""Calibration study: parameter error and held-out tip error against the number of
measurements and the measurement noise.

    MPLBACKEND=Agg python benchmarks/calibration.py [--quick] [--seeds 3] [--out DIR]

Each seed draws a "real" Fig. 3 robot that differs from its datasheet: each tube's precurvature,
E and G scaled by U(0.9, 1.1), both insertion carriages' zeros 1 mm off. Its tips are computed
by the independent standard model (``torchpvs.reference``, shooting on the Kirchhoff rod: no
code shared with the PVS solver but the scene) at seeded feasible actuations
(``torchpvs.testing.feasible_actuations``), then Gaussian noise (per axis) and 5 % outliers
(5 mm per axis) are added. ``torchpvs.calibrate`` fits the precurvatures, E[1], G and the
insertion offsets on the PVS model (E[0] held: tips fix stiffness ratios only) with a Huber
scale of 3x the noise; held-out error is the RMS distance to 60 noise-free reference tips at
other actuations. One torch thread.

Prints one row per (measurements, noise): precurvature error (max over tubes, %), insertion
offset error (max, mm), held-out RMS before and after (mm), how many parameters lie within 3
standard deviations of the truth, and the fit's wall time; writes ``calibration.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import torchpvs
from torchpvs.testing import feasible_actuations, one_thread, scaled_tubes, standard_tips

PARAMS = ("precurvature", "E[1]", "G", "insertion_offset")
OFFSET = np.array([1e-3, 1e-3])


def robot(seed: int):
    """A perturbed Fig. 3 robot and its reference measurements (pool and held-out)."""
    rng = np.random.default_rng(seed)
    nominal = torchpvs.load_scene("renda2021_fig3")
    f = rng.uniform(0.9, 1.1, (3, 2))
    truth = scaled_tubes(nominal, precurvature=f[0], E=f[1], G=f[2])
    D, A = feasible_actuations(rng, 120)
    Dh, Ah = feasible_actuations(rng, 60)
    return dict(nominal=nominal, f=f, D=D, A=A, tips=standard_tips(truth, D + OFFSET, A),
                Dh=Dh, Ah=Ah, held=standard_tips(truth, Dh + OFFSET, Ah), rng=rng)


def truth_values(r) -> dict[str, float]:
    """The fitted parameters' true values (moduli relative to E[0]'s nominal/true ratio)."""
    f, sc = r["f"], r["nominal"]
    ratio = 1.0 / f[1, 0]
    return {"precurvature[0]": f[0, 0], "precurvature[1]": f[0, 1],
            "E[1]": sc.tubes[1].E * f[1, 1] * ratio, "G[0]": sc.tubes[0].G * f[2, 0] * ratio,
            "G[1]": sc.tubes[1].G * f[2, 1] * ratio,
            "insertion_offset[0]": OFFSET[0], "insertion_offset[1]": OFFSET[1]}


def held_rms(tips, held) -> float:
    return float(np.sqrt(np.mean(np.sum((tips - held) ** 2, -1))))


def fit(r, m: int, noise: float, seed: int):
    rng = np.random.default_rng(1000 + seed)
    T = r["tips"][:m] + rng.normal(0.0, noise, (m, 3))
    out = rng.random(m) < 0.05
    T[out] += rng.normal(0.0, 5e-3, (int(out.sum()), 3))
    t0 = time.perf_counter()
    cal = torchpvs.calibrate(r["nominal"], r["D"][:m], r["A"][:m], T, params=PARAMS,
                             huber_scale=3 * noise)
    wall = time.perf_counter() - t0
    truth = truth_values(r)
    err = {n: cal[n] - v for n, v in truth.items()}
    within = sum(abs(err[n]) <= 3 * cal.std[cal.names.index(n)] for n in truth)
    return dict(m=m, noise=noise, converged=cal.converged, wall=wall,
                k_err=max(abs(err[f"precurvature[{j}]"]) / truth[f"precurvature[{j}]"]
                          for j in range(2)),
                off_err=max(abs(err[f"insertion_offset[{j}]"]) for j in range(2)),
                after=held_rms(cal.predict(r["Dh"], r["Ah"]), r["held"]),
                within=within, n_params=len(truth), outliers=int(out.sum()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one seed, fewer conditions")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", default="bench_out/calibration",
                    help="figure folder (docs/figures/calibration regenerates the docs' one)")
    args = ap.parse_args(argv)
    ms = (10, 30, 60) if args.quick else (10, 20, 40, 60, 120)
    noises = (1e-4,) if args.quick else (5e-5, 1e-4, 2e-4, 5e-4)
    seeds = range(1 if args.quick else args.seeds)
    rows = []
    with one_thread():
        for seed in seeds:
            t0 = time.perf_counter()
            r = robot(seed)
            nom = torchpvs.solve(r["nominal"], insertion=torch.tensor(r["Dh"]),
                                 rotation=torch.tensor(r["Ah"]))
            before = held_rms(nom.tip_position.numpy(), r["held"])
            print(f"seed {seed}: factors precurvature {np.round(r['f'][0], 3)}, E "
                  f"{np.round(r['f'][1], 3)}, G {np.round(r['f'][2], 3)}; reference data "
                  f"{time.perf_counter() - t0:.1f} s; held-out RMS of the datasheet model "
                  f"{before * 1e3:.2f} mm", flush=True)
            for m in ms:
                for noise in noises:
                    row = fit(r, m, noise, seed) | {"seed": seed, "before": before}
                    rows.append(row)
    print("\n| measurements | noise [mm] | precurvature err [%] | offset err [mm] | held-out "
          "RMS before -> after [mm] | truth within 3 sigma | fit time [s] |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for m in ms:
        for noise in noises:
            sel = [r for r in rows if r["m"] == m and r["noise"] == noise]
            k = max(r["k_err"] for r in sel) * 100
            o = max(r["off_err"] for r in sel) * 1e3
            b = np.mean([r["before"] for r in sel]) * 1e3
            a = max(r["after"] for r in sel) * 1e3
            w = sum(r["within"] for r in sel)
            n = sum(r["n_params"] for r in sel)
            t = np.median([r["wall"] for r in sel])
            bad = sum(not r["converged"] for r in sel)
            print(f"| {m} | {noise * 1e3:g} | {k:.2f} | {o:.3f} | {b:.2f} -> {a:.3f} | "
                  f"{w}/{n} | {t:.2f} |" + (f" ({bad} not converged)" if bad else ""))
    print(f"\n(worst over {len(seeds)} seed(s); each fit: {', '.join(PARAMS)})")
    _figure(rows, ms, noises, Path(args.out))
    return 0


def _figure(rows, ms, noises, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for noise in noises:
        k = [np.median([r["k_err"] * 100 for r in rows if r["m"] == m and r["noise"] == noise])
             for m in ms]
        a = [np.median([r["after"] * 1e3 for r in rows if r["m"] == m and r["noise"] == noise])
             for m in ms]
        ax[0].loglog(ms, k, "o-", label=f"noise {noise * 1e3:g} mm")
        ax[1].loglog(ms, a, "o-", label=f"noise {noise * 1e3:g} mm")
    before = np.mean([r["before"] for r in rows]) * 1e3
    ax[1].axhline(before, color="k", ls="--", lw=1, label="datasheet model")
    ax[0].set(xlabel="measurements", ylabel="precurvature error [%] (median)",
              title="parameter error")
    ax[1].set(xlabel="measurements", ylabel="held-out tip RMS [mm] (median)",
              title="prediction on new actuations")
    for a_ in ax:
        a_.grid(True, which="both", alpha=0.3)
        a_.legend(fontsize=8)
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "calibration.png", dpi=120)
    print(f"figure: {out / 'calibration.png'}")


if __name__ == "__main__":
    raise SystemExit(main())
