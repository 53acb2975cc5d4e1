"""Gradient-based design: choose the precurvatures of a two-tube robot so that its tip passes
through given targets at given actuations, with gradients from the implicit-function backward
(``torchpvs.CTR(...).learnable("precurvature")``; never backpropagated through Newton).

Targets are the tips of a hidden "true" design; the optimisation starts from another design and
minimises the mean squared tip distance with L-BFGS. Prints the loss per iteration and saves
``design_optimization.png`` into ``--out`` (default ``examples_out/``; ``--out docs/figures``
regenerates the documentation's figure). Usage::

    python examples/design_optimization.py [--iters 15] [--out DIR]
"""

from __future__ import annotations

import math
import time

import torch
from _common import figure, parse_args, save

import torchpvs as tp


def main() -> None:
    args = parse_args(__doc__, threads=None,
                      extra=lambda ap: ap.add_argument("--iters", type=int, default=15))
    torch.manual_seed(0)
    scene = tp.load_scene("renda2021_fig3")
    opts = tp.SolverOptions(order=3, n_magnus=16, compute_forces=False)
    # Actuations at which the tip must pass through the targets (full and partial overlap).
    rot = torch.tensor([[0.0, a] for a in (0.0, 0.6, 1.2, 1.8)], dtype=torch.float64)
    ins = torch.tensor([[93.5e-3, 208.5e-3], [93.5e-3, 190.0e-3], [93.5e-3, 200.0e-3],
                        [93.5e-3, 180.0e-3]], dtype=torch.float64)
    true = tp.CTR(scene, opts)
    with torch.no_grad():
        true.precurvature[:, 1, 0] = torch.tensor([12.0, 16.0], dtype=torch.float64)
        targets = true(ins, rot).tip_position
    robot = tp.CTR(scene, opts).learnable("precurvature")       # starts at 9.9, 13.8 1/m
    opt = torch.optim.LBFGS(robot.parameters(), lr=1.0, max_iter=1,
                            line_search_fn="strong_wolfe")
    mask = torch.zeros_like(robot.precurvature)
    mask[:, 1, 0] = 1.0      # only the constant in-plane precurvatures are designed here
    history = []
    t0 = time.perf_counter()
    state = {"q": None}

    def closure():
        opt.zero_grad()
        eq = robot(ins, rot, initial=state["q"])
        state["q"] = eq.q.detach()
        loss = (1e3 * (eq.tip_position - targets)).square().sum(-1).mean()   # [mm^2]
        loss.backward()
        robot.precurvature.grad *= mask
        return loss

    for it in range(args.iters):
        loss = float(opt.step(closure).detach())
        history.append(1e-3 * math.sqrt(loss))
        k = robot.precurvature[:, 1, 0].detach().tolist()
        print(f"iter {it:3d}  rms tip error {1e3 * history[-1]:10.5f} mm  "
              f"kappa = ({k[0]:.4f}, {k[1]:.4f}) 1/m")
        if history[-1] < 1e-8:
            break
    print(f"{len(history)} iterations in {time.perf_counter() - t0:.1f} s; true kappa = (12, 16)")

    fig = figure((10, 4))
    ax1, ax2 = fig.add_subplot(121), fig.add_subplot(122)
    ax1.semilogy([1e3 * h for h in history], "o-", ms=3)
    ax1.set(xlabel="iteration", ylabel="rms tip error [mm]", title="design loss (L-BFGS)")
    with torch.no_grad():
        final = robot(ins, rot)
        bb = final.backbone(60)
    for b in range(ins.shape[0]):
        ax2.plot(1e3 * bb[b, :, 0], 1e3 * bb[b, :, 2], color=f"C{b}")
        ax2.plot(1e3 * float(targets[b, 0]), 1e3 * float(targets[b, 2]), "x", color=f"C{b}",
                 ms=10)
    ax2.set(xlabel="x [mm]", ylabel="z [mm]", title="optimised backbones (x: targets)")
    ax2.set_aspect("equal")
    save(fig, args.out, "design_optimization.png")


if __name__ == "__main__":
    main()
