"""``state()``: the one documented way for controllers to read the robots."""

from __future__ import annotations

import dataclasses
import math

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


def test_state_stiffness_is_the_unclipped_actuator_stiffness(on_fold_branch):
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
    h = np.radians(0.05)
    signs = {}
    for deg, x, eq in on_fold_branch(env):
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


def test_relative_rotation_stiffness_against_an_independent_basis():
    """``relative_rotation_stiffness`` is the smallest eigenvalue of the rotation block on the
    complement of the common rotation: checked against ``scipy.linalg.null_space``'s basis of
    that complement (eigenvalues do not depend on the basis), its closed form ``v^T R v`` for
    two tubes, and its invariances (the insertion block and a common-rotation stiffness
    ``c 1 1^T`` do not change it)."""
    from scipy.linalg import null_space

    from envs.task import relative_rotation_stiffness
    rng = np.random.default_rng(5)
    for N in (2, 3, 4):
        A = rng.normal(size=(6, 2 * N, 2 * N))
        K = A + np.swapaxes(A, -1, -2)
        P = null_space(np.ones((1, N)))                   # (N, N - 1)
        ref = [np.linalg.eigvalsh(P.T @ k[N:, N:] @ P).min() for k in K]
        got = relative_rotation_stiffness(K)
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
        K2 = K.copy()
        K2[:, N:, N:] += 3.7 * np.ones((N, N))
        K2[:, :N, :N] = 0.0
        np.testing.assert_allclose(relative_rotation_stiffness(K2), ref, rtol=1e-12,
                                   atol=1e-12)
        if N == 2:
            v = np.array([1.0, -1.0]) / math.sqrt(2.0)
            np.testing.assert_allclose(got, [v @ k[2:, 2:] @ v for k in K], rtol=1e-12)
    K = np.zeros((3, 4, 4))
    K[1, 2, 3] = np.nan
    out = relative_rotation_stiffness(K)
    assert np.isnan(out[1]) and np.isfinite(out[[0, 2]]).all()
    np.testing.assert_array_equal(relative_rotation_stiffness(np.ones((2, 2, 2))), 0.0)
    with pytest.raises(ValueError, match=r"K must be \(B, 2N, 2N\)"):
        relative_rotation_stiffness(np.zeros((2, 3, 3)))


def test_the_stiffness_observation_entry_follows_the_torque_along_a_branch(on_fold_branch):
    """``observe_stiffness=True`` appends ``tanh(k_rel / stiffness_scale)`` to the
    observation. Reference: for an unloaded two-tube robot ``k_rel = 2 dtau_2/dalpha_2`` (the
    common rotation is rigid, so ``K_aa (1, 1) = 0``), taken by finite differences of the
    torque along the branch on the Fig. 3 robot: positive at 150 deg, negative at 176 deg,
    past the torque's maximum, where the force agent's snaps begin."""
    from envs.task import stiffness_scale
    plain = CTRReachEnv(compensation=True)
    env = CTRReachEnv(compensation=True, observe_stiffness=True)
    env.reset(seed=0)
    plain.reset(seed=0)
    n = plain.observation_space["observation"].shape[0]
    assert env.observation_space["observation"].shape == (n + 1,)
    robot = env.robot
    scale = stiffness_scale(robot)
    assert scale == pytest.approx(0.25 * np.mean(robot.torque_scale))
    h, seen = np.radians(0.05), {}
    for deg, x, eq in on_fold_branch(env):
        tau = [float(solve_batch(robot, x + [[0, 0, 0, d]], initial=eq.q).actuation_torques[0, 1])
               for d in (-h, h)]
        k_rel = 2.0 * (tau[1] - tau[0]) / (2 * h)
        obs = env.task.observations()["observation"][0]
        np.testing.assert_allclose(obs[-1], np.tanh(k_rel / scale), rtol=2e-4, atol=1e-6)
        seen[deg] = float(np.sign(obs[-1]))
    assert seen == {150: 1.0, 176: -1.0}


def test_observe_stiffness_is_checked_by_name():
    with pytest.raises(ValueError, match="observe_stiffness must be True or False"):
        CTRReachEnv(observe_stiffness="yes")
    with pytest.raises(ValueError, match="observe_stiffness=True needs control='force'"):
        CTRReachEnv(control="joint", observe_stiffness=True)
