"""Inverse kinematics (torchpvs/inverse_kinematics.py): goals that are tips of known stable
equilibria are reached; every returned actuation is checked by an independent forward solve."""

from __future__ import annotations

import math

import pytest
import torch

import torchpvs as tp
from torchpvs.inverse_kinematics import _random_starts

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


def test_stalled_starts_are_replaced():
    # Goals (tips of stable equilibria) that all 8 starts missed without restarts (0.2-21 mm
    # after 60 iterations); the restarts reach each one. Checked by a fresh forward solve.
    goals = torch.cat([_reachable_goals(20, seed=4)[[10, 11]], _reachable_goals(20, seed=5)[[12]]])
    res = tp.inverse_kinematics(SC, goals, tol=1e-4)
    assert bool(res.solved.all()), res.error
    chk = tp.solve(SC, insertion=res.insertion, rotation=res.rotation, options=OPTS)
    assert float((chk.tip_position - goals).norm(dim=-1).max()) < 1e-4
    assert bool(chk.stable.all())


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
    (dict(goal=[0.0, 0.0, 0.1], restarts=-1), "restarts must be an integer >= 0"),
    (dict(goal=[0.0, 0.0, 0.1], min_exposed=10.0), "min_exposed"),
    # these used to be accepted (or fail inside the solver)
    (dict(goal=[0.0, 0.0, 0.1], min_exposed=-1.0), "min_exposed must be a length >= 0"),
    (dict(goal=[0.0, 0.0, 0.1], initial_insertion=[0.2, 0.1]),
     r"initial_insertion: D_j must be >= D_\{j-1\}"),
    (dict(goal=[0.0, 0.0, 0.1], initial_insertion=[-0.01, 0.1]),
     "initial_insertion: every D_j must be >= 0"),
    (dict(goal=[[0.0, 0.0, 0.1]] * 2, initial_insertion=[[0.0, 0.1]] * 3),
     "initial_insertion must have shape"),
    (dict(goal=[0.0, 0.0, 0.1], initial_rotation=[0.0, math.inf]),
     "initial_rotation must be finite"),
    (dict(goal=torch.zeros(0, 3)), "goal must hold at least one goal"),
    (dict(goal=[0.0, 0.0, 0.1], max_iter=-1), "max_iter"),
    (dict(goal=[0.0, 0.0, 0.1], max_step=(0.0, 0.3)), "max_step"),
    (dict(goal=[0.0, 0.0, 0.1], travel_scale=math.nan), "travel_scale"),
    (dict(goal=[0.0, 0.0, 0.1], seed=1.5), "seed"),
])
def test_bad_arguments_name_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        tp.inverse_kinematics(SC, **kwargs)


GOAL_A = [0.03, 0.02, 0.09]


def test_a_goal_gets_the_same_answer_wherever_it_sits_in_the_batch():
    """Regression: the random starts were drawn per batch, so goal A alone, as both rows
    of [A, A] and as row 1 of [U, A] (U unreachable) got travels 0.152, 0.127 / 0.256 and
    0.256. Reference: the solo answer; every copy must equal it exactly."""
    solo = tp.inverse_kinematics(SC, GOAL_A)
    assert bool(solo.solved[0])
    for goals, rows in (([GOAL_A, GOAL_A], [0, 1]), ([[1.0, 0.0, 0.0], GOAL_A], [1])):
        res = tp.inverse_kinematics(SC, goals)
        for i in rows:
            assert torch.equal(res.insertion[i], solo.insertion[0])
            assert torch.equal(res.rotation[i], solo.rotation[0])
            assert float(res.travel[i]) == float(solo.travel[0])
    # the starts follow the row's values: one goal from two initial actuations (as
    # training/controllers.py asks) gets independent random starts, equal rows equal ones
    goal = torch.tensor([GOAL_A] * 3, dtype=torch.float64)
    D0 = torch.tensor([[0.05, 0.2], [0.06, 0.2], [0.05, 0.2]], dtype=torch.float64)
    u, a = _random_starts(0, goal, D0, torch.zeros(3, 2, dtype=torch.float64), 4)
    assert torch.equal(u[0], u[2]) and torch.equal(a[0], a[2])
    assert not torch.equal(u[0], u[1]) and not torch.equal(a[0], a[1])


@pytest.mark.parametrize("goal", [GOAL_A, [0.04, 0.01, 0.08]])
def test_float32_solves_reach_the_goal(goal):
    """Regression: with SolverOptions(dtype=float32) these goals raised LinAlgError from
    the implicit backward (eigh on NaN stiffnesses): the cold start of a batch element with
    fewer sections than the others was NaN (a 1e-300 clamp is 0 in float32). Reference: an
    independent float64 solve at the returned actuation."""
    res = tp.inverse_kinematics(SC, goal, options=tp.SolverOptions(dtype=torch.float32))
    assert bool(res.solved[0]), (res.error, res.starts_solved)
    chk = tp.solve(SC, insertion=res.insertion, rotation=res.rotation, options=OPTS)
    assert bool(chk.converged[0] & chk.stable[0])
    # float32 tips agree with float64 to ~1e-6 m here (tests/hard/test_precision.py: 1e-4)
    assert float((chk.tip_position[0] - torch.tensor(goal, dtype=torch.float64)).norm()) < 2e-4
