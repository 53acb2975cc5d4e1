"""Speed of the PVS solver on the paper's Fig. 3 robot, measured side by side in one run.

    python benchmarks/bench_solver.py [--orders 2 3] [--batches 1 64 1024] [--repeat 5]

Prints a table: cold and warm-started single solves, batched throughput (warm: every element
starts from the solution 1 degree away on its own branch; cold: default initial guess), and the
standard-model reference solver (shooting, numpy/scipy) at a tolerance giving matched accuracy.
Timings are medians over ``--repeat`` runs; speed-ups are ratios measured in this same run.
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time

import torch

import torchpvs as tp


def _median_time(fn, repeat: int) -> float:
    fn()  # warm-up (allocations, caches)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--orders", type=int, nargs="+", default=[2, 3, 4])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    scene = tp.load_scene("renda2021_fig3")
    print(f"# torchpvs solver benchmark — {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads, torch {torch.__version__}, float64, scene "
          f"renda2021_fig3 (alpha2 sampled in [0, 140] deg on the stable branch from 0)")

    # Reference accuracy: PVS at a high order is the converged reference for the tip.
    rng = torch.Generator().manual_seed(0)
    print("\n| order | dofs | tip error vs order 8 [m] | cold single [ms] | warm single [ms] |"
          + "".join(f" B={b} warm [solves/s] | B={b} cold [solves/s] |" for b in args.batches))
    print("|---" * (5 + 2 * len(args.batches)) + "|")
    fine = tp.solve(scene, options=tp.SolverOptions(order=8))
    for order in args.orders:
        opts = tp.SolverOptions(order=order)
        eq = tp.solve(scene, options=opts)
        err = float((eq.tip_position - fine.tip_position).norm())
        cold = _median_time(lambda: tp.solve(scene, options=opts), args.repeat)
        nxt = [0.0, scene.actuation.rotation[1] + math.radians(1.0)]
        warm = _median_time(lambda: tp.solve(scene, rotation=nxt, options=opts, initial=eq),
                            args.repeat)
        row = f"| {order} | {int(eq.dofs[0])} | {err:.2e} | {cold * 1e3:.2f} | {warm * 1e3:.2f} |"
        for B in args.batches:
            alpha = torch.rand(B, generator=rng, dtype=torch.float64) * math.radians(140)
            rot = torch.stack([torch.zeros_like(alpha), alpha], -1)
            base = tp.solve(scene, rotation=rot, options=opts)
            rot2 = rot + torch.tensor([0.0, math.radians(1.0)], dtype=torch.float64)
            tw = _median_time(lambda: tp.solve(scene, rotation=rot2, options=opts,
                                               initial=base), max(1, args.repeat // 2))
            tc = _median_time(lambda: tp.solve(scene, rotation=rot2, options=opts),
                              max(1, args.repeat // 2))
            row += f" {B / tw:,.0f} | {B / tc:,.0f} |"
        print(row, flush=True)

    try:
        from torchpvs.reference import solve_standard
    except ImportError:
        print("\n(reference solver not available: skipped)")
        return
    print("\n| reference tol | tip error vs PVS order 8 [m] | single solve [ms] |")
    print("|---|---|---|")
    for tol in (1e-4, 1e-6, 1e-8, 1e-10):
        sol = solve_standard(scene, tol=tol, compute_forces=False, compute_stability=False)
        err = float((torch.as_tensor(sol.tip_position) - fine.tip_position[0]).norm())
        t = _median_time(lambda: solve_standard(scene, tol=tol, compute_forces=False,
                                                compute_stability=False), args.repeat)
        print(f"| {tol:.0e} | {err:.2e} | {t * 1e3:.2f} |", flush=True)


if __name__ == "__main__":
    main()
