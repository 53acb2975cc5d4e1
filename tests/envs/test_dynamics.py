"""envs.dynamics at a kink of the elastic energy: a force-controlled carriage pushed across a
convex corner of ``U*(D)``.

Reference: the solver's two one-sided insertion forces at the kink (``actuation_forces`` and
``actuation_forces_insertion``, independent of the carriage dynamics). For the overdamped flow
``b xdot = tau - g(x)`` a carriage pushed by ``tau`` with ``g(x-) < tau < g(x+)`` has the kink
as its equilibrium (the subgradient of ``U*`` there contains ``tau``). That is the stall of the
compensated force actions at ~93.5 mm on the Fig. 3 robot (the outer tube's straight-to-curved
transition at the orifice, a force jump of about 1.6 N): with the near side's load compensated
a small push parks at the corner, and ``kink_compensation`` holds against the far side's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchpvs
from envs.dynamics import CarriageModel, RobotBatch
from envs.robots import fig3_two_tube
from envs.task import ReachConfig

pytestmark = pytest.mark.usefixtures("one_thread")


def _kink(robot):
    Ls1 = robot.scene.tubes[0].straight_length                      # 93.5 mm
    eq = torchpvs.solve(robot.scene, insertion=torch.tensor([[Ls1, 0.150]], dtype=torch.float64),
                        rotation=torch.zeros(1, 2, dtype=torch.float64))
    assert bool(eq.force_kink[0, 0])
    return Ls1, float(eq.actuation_forces_insertion[0, 0]), float(eq.actuation_forces[0, 0])


def test_a_small_compensated_push_parks_at_a_convex_kink_and_crosses_with_the_far_side():
    robot = fig3_two_tube()
    Ls1, near, far = _kink(robot)
    jump = far - near
    assert jump > 0.5                       # a convex corner: more force needed past it
    bat = RobotBatch(robot, CarriageModel(), 2)
    bat.set_state(np.arange(2), np.tile([Ls1 - 30e-6, 0.150, 0.0, 0.0], (2, 1)))
    assert np.allclose(bat.g[:, 0], near, rtol=0.05)       # the near side's force
    push = np.array([0.05 * jump, 0.05 * jump])
    direction = np.tile([1.0, 0.0, 0.0, 0.0], (2, 1))
    for k in range(12):
        # robot 0: the near side's g(x) compensated; robot 1: from the fifth period on, the
        # far side's where parked (RobotBatch.compensation)
        g = bat.compensation(direction) if k >= 4 else bat.g.copy()
        g[0] = bat.g[0]
        tau = g.copy()
        tau[:, 0] += push
        bat.step_force(tau)
        if k == 3:   # both parked at the corner, below it
            assert np.all((bat.x[:, 0] >= Ls1 - 30e-6) & (bat.x[:, 0] <= Ls1))
            assert np.allclose(bat.compensation(direction)[:, 0], far, rtol=0.2)
            assert np.allclose(bat.compensation(-direction)[:, 0], bat.g[:, 0])
    parked, crossed = bat.x[:, 0]
    assert Ls1 - 30e-6 <= parked <= Ls1 + 1e-9
    assert crossed > Ls1 + 20e-6
    assert bat.g[1, 0] == pytest.approx(far, rel=0.2)      # it now feels the far side


def test_kink_compensation_needs_compensation():
    with pytest.raises(ValueError, match="kink_compensation"):
        ReachConfig(control="force", kink_compensation=True)
    with pytest.raises(ValueError, match="kink_compensation"):
        ReachConfig(control="force", compensation=True, kink_compensation=1)
