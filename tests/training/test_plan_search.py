"""training/plan_search.py: the solution-set search behind the reaching task's headroom figure
(docs/results.md, ``benchmarks/reach_ceiling.py``). Reference: a goal made as the tip of a known
actuation, so a plan with (almost) no travel exists from that actuation."""

from __future__ import annotations

import numpy as np
import torch

import envs
from envs.robots import solve_batch
from training.plan_search import best_plans


def test_best_plan_finds_the_goal_s_own_actuation_nearby():
    """From the actuation whose tip is the goal, the best plan found ends on the goal and needs
    at most the travel of half a grid step in relative rotation (5 deg at 1.57 rad/s: under a
    control period), far less than from a distant start; its load is the equilibrium's."""
    venv = envs.CTRReachVecEnv(2, robot="fig3_two_tube", control="force")
    venv.seed(3)
    venv.reset()
    st = venv.state()
    robot = venv.robot
    x_goal = np.array([[0.08, 0.16, 0.3, 1.2]])
    goal = solve_batch(robot, x_goal).tip_position.numpy()
    eq0 = solve_batch(robot, x_goal)
    g0 = torch.cat([eq0.actuation_forces, eq0.actuation_torques], -1).numpy()
    far = np.array([[0.0, 0.02, -2.0, 0.5]])
    eqf = solve_batch(robot, far)
    gf = torch.cat([eqf.actuation_forces, eqf.actuation_torques], -1).numpy()
    args = dict(scale=st.action_scale, damping=st.damping, h=st.control_period)
    x, g, steps = best_plans(robot, np.concatenate([x_goal, far]), np.concatenate([g0, gf]),
                          np.concatenate([goal, goal]), **args)
    tips = solve_batch(robot, x).tip_position.numpy()
    assert np.all(np.linalg.norm(tips - goal, axis=-1) < 2e-5), tips - goal
    assert steps[0] < 1.0 and steps[1] > 10 * steps[0] + 5, steps
    eq = solve_batch(robot, x)
    want = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
    np.testing.assert_allclose(g, want, rtol=1e-9, atol=1e-12)
