"""Backward/forward time ratio of the implicit-function backward (torchpvs/implicit.py).

For batch sizes B in (1, 64) on the paper's Fig. 3 robot (random rotations and insertions),
times the forward solve (with inputs requiring grad: the solve plus the differentiable outputs)
and ``loss.backward()`` (adjoint solves with the stiffness at the solution) of
``loss = tip_position.sum() + actuation_torques.sum()``, for gradients w.r.t. insertion, rotation
and the precurvature. Prints a table (median of ``--repeats``). Usage::

    python benchmarks/bench_backward.py [--repeats 3] [--threads 2]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import torchpvs as tp


def run(batch: int, options: tp.SolverOptions, repeats: int) -> tuple[float, float]:
    g = torch.Generator().manual_seed(batch)
    robot = tp.CTR("renda2021_fig3", options).learnable("precurvature")
    D = torch.tensor([93.5e-3, 170.5e-3], dtype=torch.float64) \
        + torch.rand(batch, 2, generator=g, dtype=torch.float64) * torch.tensor([0.0, 38e-3],
                                                                                 dtype=torch.float64)
    A = torch.zeros(batch, 2, dtype=torch.float64)
    A[:, 1] = torch.rand(batch, generator=g, dtype=torch.float64) * 2.0
    fwd, bwd = [], []
    for _ in range(repeats + 1):                      # first round warms caches up
        Dg, Ag = D.clone().requires_grad_(True), A.clone().requires_grad_(True)
        robot.zero_grad()
        t0 = time.perf_counter()
        eq = robot(Dg, Ag)
        t1 = time.perf_counter()
        loss = eq.tip_position.sum() + eq.actuation_torques.sum()
        loss.backward()
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    return statistics.median(fwd[1:]), statistics.median(bwd[1:])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads, float64, CPU")
    print(f"{'options':<22} {'B':>4} {'forward [s]':>12} {'backward [s]':>13} {'ratio':>7}")
    for name, opts in (("order=3, n_magnus=16", tp.SolverOptions(order=3, n_magnus=16)),
                       ("default (auto order)", tp.SolverOptions())):
        for batch in (1, 64):
            f, b = run(batch, opts, args.repeats)
            print(f"{name:<22} {batch:>4} {f:>12.4f} {b:>13.4f} {b / f:>7.3f}")


if __name__ == "__main__":
    main()
