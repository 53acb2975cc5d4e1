"""The robot plan (torchpvs/plan.py): what a solve reuses from one call to the next."""

from __future__ import annotations

import torch

import torchpvs as tp
from torchpvs.plan import plan_for
from torchpvs.sections import n_coordinates


def test_plan_cache_keeps_constants_per_reused_layout_only():
    """Plan.cached computes once per reused layout (warm calls at the same insertions) and
    afresh for a layout the plan did not return (another insertion state); a cached value is
    the computed one."""
    scene = tp.load_scene("renda2021_fig3")
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    disc = tp.SolverOptions().discretization(2)
    D = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    Z = torch.zeros(1, 3, dtype=torch.float64)
    off = torch.zeros(1, dtype=torch.bool)
    nq = n_coordinates(2, disc.n_basis)
    calls = []

    def compute():
        calls.append(1)
        return torch.tensor(float(len(calls)))

    with torch.no_grad():
        lay1, _ = plan.layout(plan.tubes, D, torch.zeros(1, 2, dtype=torch.float64), Z, Z, off,
                              disc, nq)
        assert float(plan.cached(disc, lay1, "x", compute)) == 1.0
        lay2, _ = plan.layout(plan.tubes, D, torch.ones(1, 2, dtype=torch.float64), Z, Z, off,
                              disc, nq)                    # rotation only: the layout is reused
        assert float(plan.cached(disc, lay2, "x", compute)) == 1.0 and len(calls) == 1
        lay3, _ = plan.layout(plan.tubes, D * 0.9, torch.ones(1, 2, dtype=torch.float64), Z, Z,
                              off, disc, nq)               # new insertions: a new layout
        assert float(plan.cached(disc, lay3, "x", compute)) == 2.0
        assert float(plan.cached(disc, lay1, "x", compute)) == 3.0   # no longer the plan's


def test_warm_solves_with_cached_pose_constants_match_a_fresh_plan():
    """The step-count check's constants cached on the plan give the same equilibrium, error
    estimate and tip as a solve on a fresh (private) plan."""
    from torchpvs.plan import Plan
    from torchpvs.solver import solve_tensors

    scene = tp.load_scene("renda2021_fig3")
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    eq = tp.solve(scene, rotation=rot)
    for k in range(3):
        eq = tp.solve(scene, rotation=rot + 0.05 * (k + 1), initial=eq)
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    D = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    Z = torch.zeros(1, 3, dtype=torch.float64)
    fresh = solve_tensors(scene, plan.tubes, D, (rot + 0.15)[None], Z, Z, tp.SolverOptions(),
                          None, Plan(plan.tubes))
    assert torch.allclose(eq.tip_position, fresh.tip_position, rtol=0, atol=1e-9)
    assert torch.allclose(eq.error_estimate, fresh.error_estimate, rtol=1e-3, atol=1e-12)
