"""``state()``: the one documented way for controllers to read the robots."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import envs
from envs import CTRReachEnv, CTRReachVectorEnv, RobotState
from envs.robots import solve_batch


def _envs(robot):
    single = CTRReachEnv(robot=robot)
    single.reset(seed=3)
    gym_vec = CTRReachVectorEnv(2, robot=robot)
    gym_vec.reset(seed=3)
    sb3_vec = envs.CTRReachVecEnv(2, robot=robot)
    sb3_vec.seed(3)
    sb3_vec.reset()
    return [(single, 1), (gym_vec, 2), (sb3_vec, 2)]


@pytest.mark.parametrize("robot", ["fig3_two_tube", "rvim_three_tube"])
def test_state_has_documented_shapes_and_matches_an_independent_solve(robot):
    for env, B in _envs(robot):
        s = env.state()
        assert isinstance(s, RobotState)
        N = env.robot.n_tubes
        shapes = {"x": (B, 2 * N), "v": (B, 2 * N), "g": (B, 2 * N), "tip": (B, 3),
                  "goal": (B, 3), "margin": (B,), "damping": (2 * N,),
                  "action_scale": (2 * N,)}
        for name, shape in shapes.items():
            value = getattr(s, name)
            assert value.shape == shape and value.dtype == np.float64, name
        assert s.q.shape[0] == B and isinstance(s.control_period, float)
        # the values are the physics: a fresh cold solve at x gives the same g, tip, margin
        eq = solve_batch(env.robot, s.x)
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
        np.testing.assert_allclose(s.g, g, atol=1e-6 * np.abs(g).max())
        np.testing.assert_allclose(s.tip, eq.tip_position.numpy(), atol=1e-8)
        np.testing.assert_array_equal(s.action_scale, env.robot.action_scale)
        # damping from the documented target speeds: full-scale force -> 20 mm/s, 90 deg/s
        np.testing.assert_allclose(s.action_scale[:N] / s.damping[:N], 0.02)
        np.testing.assert_allclose(s.action_scale[N:] / s.damping[N:], np.pi / 2)
        # q warm-starts a solve at the same x: it converges to the same tip
        warm = solve_batch(env.robot, s.x, initial=s.q)
        np.testing.assert_allclose(warm.tip_position.numpy(), s.tip, atol=1e-8)
        obs = env.task.observations()
        np.testing.assert_allclose(s.goal, obs["desired_goal"].reshape(B, 4)[:, :3], atol=1e-7)


def test_state_is_frozen_and_holds_copies():
    env = CTRReachEnv()
    env.reset(seed=0)
    s = env.state()
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.x = s.x  # type: ignore[misc]
    before = {f.name: np.copy(getattr(s, f.name)) for f in dataclasses.fields(s)}
    for f in dataclasses.fields(s):             # scribbling on the copies changes nothing
        value = getattr(s, f.name)
        if isinstance(value, np.ndarray):
            value[...] = 123.0
    s2 = env.state()
    for name, value in before.items():
        np.testing.assert_array_equal(getattr(s2, name), value)
    env.step(np.ones(4, np.float32))            # and stepping does not change an old state
    s3 = env.state()
    assert not np.array_equal(s3.x, s2.x)
    np.testing.assert_array_equal(s2.x, before["x"])


def test_state_stiffness_is_the_unclipped_actuator_stiffness():
    """``state().stiffness`` is ``dtau/dx`` of the robot's equilibrium, negative directions
    kept. References: finite differences of the actuation torque along the branch, and the
    rotation invariance of an unloaded robot (turning every tube together stores no energy, so
    ``K (0, 0, 1, 1) = 0``). On the Fig. 3 robot the inner tube's rotation stiffness
    ``dtau_2/dalpha_2`` is positive at 150 deg and negative at 176 deg, past the torque's
    maximum on the branch followed from 0 (a torque-controlled robot is unstable there), while
    the margin of the coordinates' Hessian is still large."""
    env = CTRReachEnv()
    env.reset(seed=0)
    rb, robot = env.task.robots, env.robot
    D = [0.0987, 0.1645]
    h = np.radians(0.05)
    eq = None
    signs = {}
    for deg in range(120, 177, 2):       # follow the branch from 120 deg
        x = np.array([[*D, 0.0, np.radians(deg)]])
        eq = solve_batch(robot, x, initial=None if eq is None else eq.q)
        if deg not in (150, 176):
            continue
        rb.set_state(np.array([0]), x, eq=eq, rows=np.array([0]))
        s = env.state()
        K = s.stiffness[0]
        assert K.shape == (4, 4) and np.allclose(K, K.T)
        np.testing.assert_allclose(K @ [0.0, 0.0, 1.0, 1.0], 0.0, atol=1e-9 * np.abs(K).max())
        tau = [float(solve_batch(robot, x + [[0, 0, 0, d]], initial=eq.q).actuation_torques[0, 1])
               for d in (-h, h)]
        fd = (tau[1] - tau[0]) / (2 * h)
        np.testing.assert_allclose(K[3, 3], fd, rtol=1e-4, atol=1e-7)
        assert s.margin[0] > 0.2
        signs[deg] = np.sign(K[3, 3])
        # the clipped stiffness of the carriage dynamics is its positive part
        w = np.linalg.eigvalsh(rb.K[0])
        assert w.min() > -1e-12
    assert signs == {150: 1.0, 176: -1.0}
