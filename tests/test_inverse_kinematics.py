"""Inverse kinematics (torchpvs/inverse_kinematics.py): goals that are tips of known stable
equilibria are reached; every returned actuation is checked by an independent forward solve."""

from __future__ import annotations

import math

import pytest
import torch

import torchpvs as tp

SC = tp.load_scene("renda2021_fig3")
OPTS = tp.SolverOptions(order=2, n_magnus=8, compute_forces=False)


def _reachable_goals(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    D2 = 0.12 + torch.rand(n, generator=g, dtype=torch.float64) * 0.15
    D1 = torch.minimum(torch.rand(n, generator=g, dtype=torch.float64) * 0.15, D2)
    A = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * 2.0
    eq = tp.solve(SC, insertion=torch.stack([D1, D2], -1), rotation=A, options=OPTS)
    assert bool(eq.stable.all() & eq.converged.all())
    return eq.tip_position


def test_reaches_the_tips_of_known_equilibria():
    goals = _reachable_goals(6, seed=3)
    res = tp.inverse_kinematics(SC, goals, tol=1e-4)
    assert bool(res.solved.all()), (res.error, res.starts_solved)
    # independent check: a fresh forward solve at the returned actuations
    chk = tp.solve(SC, insertion=res.insertion, rotation=res.rotation, options=OPTS)
    assert float((chk.tip_position - goals).norm(dim=-1).max()) < 1e-4
    assert bool(chk.stable.all())
    D = res.insertion
    assert bool((D >= 0).all() & (D[:, 1] >= D[:, 0]).all())
    lengths = torch.tensor([t.length for t in SC.tubes], dtype=torch.float64)
    assert bool((lengths - D >= 5e-3 - 1e-12).all())       # min_exposed


def test_the_current_tip_needs_no_travel():
    eq = tp.solve(SC, insertion=[0.05, 0.2], rotation=[0.3, 1.0], options=OPTS)
    res = tp.inverse_kinematics(SC, eq.tip_position[0], initial_insertion=[0.05, 0.2],
                                initial_rotation=[0.3, 1.0])
    assert bool(res.solved[0]) and float(res.travel[0]) < 1e-12


def test_an_unreachable_goal_is_reported_not_raised():
    res = tp.inverse_kinematics(SC, [1.0, 0.0, 0.0], starts=3, max_iter=15)
    assert not bool(res.solved[0]) and float(res.error[0]) > 0.5
    assert int(res.starts_solved[0]) == 0


@pytest.mark.parametrize("kwargs, match", [
    (dict(goal=[0.0, 0.1]), "goal"), (dict(goal=[math.nan, 0.0, 0.1]), "goal"),
    (dict(goal=[0.0, 0.0, 0.1], starts=0), "starts"),
    (dict(goal=[0.0, 0.0, 0.1], tol=-1.0), "tol"),
    (dict(goal=[0.0, 0.0, 0.1], min_exposed=10.0), "min_exposed"),
])
def test_bad_arguments_name_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tp.inverse_kinematics(SC, **kwargs)
