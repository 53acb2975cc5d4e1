"""Shared fixtures of the environment tests."""

from __future__ import annotations

import numpy as np
import pytest

from envs.robots import solve_batch


@pytest.fixture
def on_fold_branch():
    """``place(env, degrees=(150, 176))``: robot 0 of a Fig. 3 ``env`` placed at rest on the
    branch at ``D = (98.7, 164.5) mm``, outer tube at 0, the inner tube turned to each of
    ``degrees`` in turn (followed from 120 deg in 2 deg steps, each solve warm from the last);
    yields ``(deg, x (1, 4), eq)``. The inner tube's rotation stiffness ``dtau_2/dalpha_2``
    turns negative near 163 deg on this branch (a torque-controlled robot is unstable past it)
    and the branch ends in a snap near 186 deg."""
    def place(env, degrees=(150, 176)):
        rb, robot = env.task.robots, env.robot
        eq = None
        for deg in range(120, max(degrees) + 1, 2):
            x = np.array([[0.0987, 0.1645, 0.0, np.radians(deg)]])
            eq = solve_batch(robot, x, initial=None if eq is None else eq.q)
            if deg in degrees:
                rb.set_state(np.array([0]), x, eq=eq, rows=np.array([0]))
                yield deg, x, eq
    return place
