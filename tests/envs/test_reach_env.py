"""The reaching environments (envs/): API conformance, physics of a step, limits, batching."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import envs
from envs import CarriageModel, CTRReachEnv, CTRReachVecEnv, RobotBatch, fig3_two_tube
from envs.robots import measure_force_scales, rvim_three_tube, solve_batch
from envs.task import OBS_BOUND


@pytest.mark.parametrize("env_id", sorted(envs.ENV_IDS))
def test_registered_env_passes_the_gymnasium_and_sb3_checkers(env_id):
    env = gym.make(env_id)
    assert env.spec.max_episode_steps == {"torchpvs/CTRReachForceRobust-v0": 150,
                                          "torchpvs/CTRReachJoint-v0": 200}.get(env_id, 100)
    gym_check_env(env.unwrapped, skip_render_check=True)
    sb3_check_env(env.unwrapped, warn=False)
    assert env.action_space == gym.spaces.Box(-1, 1, (4,), np.float32)


def test_seeded_reset_is_deterministic_and_seeds_differ():
    e1, e2 = CTRReachEnv(), CTRReachEnv()
    o1, _ = e1.reset(seed=7)
    o2, _ = e2.reset(seed=7)
    for k in o1:
        np.testing.assert_array_equal(o1[k], o2[k])
    o3, _ = e2.reset(seed=8)
    assert not np.allclose(o1["desired_goal"], o3["desired_goal"])


def test_holding_the_elastic_force_keeps_the_robot_at_rest():
    """Physics of a step: b xdot = tau - g(x); with tau = g(x) nothing moves."""
    env = CTRReachEnv()
    env.reset(seed=3)
    x0, g = env.actuation, env.elastic_forces
    action = g / env.robot.action_scale
    assert np.abs(action).max() < 1.0
    obs, *_ = env.step(action.astype(np.float32))
    np.testing.assert_allclose(env.actuation, x0, atol=1e-6)  # float32 action rounding


def test_force_moves_the_carriage_at_the_damping_speed():
    """Against a constant extra force f along one insertion, the first-order carriage moves
    about dx = h f / (b + h k) per step (b = scale / 20 mm/s): compare with that closed form of
    the linearly implicit step, using the stiffness from a finite difference of g."""
    robot = fig3_two_tube()
    model = CarriageModel()
    rb = RobotBatch(robot, model, 1)
    x0 = np.array([[0.05, 0.12, 0.3, -0.4]])
    rb.set_state(np.array([0]), x0)
    g0 = rb.g.copy()
    extra = 0.2 * robot.force_scale[1]
    tau = g0.copy()
    tau[0, 1] += extra
    rb.step_force(tau)
    dx = rb.x[0, 1] - x0[0, 1]
    b = robot.force_scale[1] / model.insertion_speed
    assert 0 < dx <= model.control_period * extra / b * (1 + 1e-9)
    # an upper bound from zero stiffness and a lower bound from the measured stiffness
    e = 1e-5
    gp = solve_batch(robot, x0 + np.array([[0, e, 0, 0]])).actuation_forces[0, 1].item()
    gm = solve_batch(robot, x0 - np.array([[0, e, 0, 0]])).actuation_forces[0, 1].item()
    k = (gp - gm) / (2 * e)
    h = model.control_period
    assert dx == pytest.approx(h * extra / (b + h * max(k, 0.0)), rel=0.05)


def test_stroke_limits_are_inelastic_stops():
    """Pulling the outer tube back beyond its stroke stops it at the limit with zero velocity
    and raises the at_limit flag; the nesting rules of docs/conventions.md hold throughout."""
    robot = fig3_two_tube()
    rb = RobotBatch(robot, CarriageModel(kind="second_order"), 1)
    rb.set_state(np.array([0]), np.array([[0.002, 0.1, 0.0, 0.0]]))
    tau = rb.g.copy()
    tau[0, 0] -= robot.force_scale[0]  # push the outer tube in, towards D1 = 0
    for _ in range(5):
        rb.step_force(tau)
        D = rb.x[0, :2]
        assert D[0] >= 0.0 and D[1] >= D[0]
        L = robot.lengths
        assert L[1] - D[1] >= L[0] - D[0] - 1e-12
    assert rb.x[0, 0] == 0.0 and rb.at_lower[0, 0] and rb.v[0, 0] == 0.0


def test_projection_enforces_the_feasible_set():
    robot = rvim_three_tube()
    rng = np.random.default_rng(0)
    D = rng.uniform(-0.1, 0.4, size=(200, 3))
    P, lo, hi = robot.project(D)
    L = robot.lengths
    assert (P[:, 0] >= 0).all() and (np.diff(P, axis=1) >= 0).all()
    assert (L[1:] - P[:, 1:] >= L[:-1] - P[:, :-1] - 1e-12).all()
    P2, _, _ = robot.project(P)
    np.testing.assert_array_equal(P, P2)  # a projection is idempotent
    inside = robot.sample_actuation(rng, 100)[:, :3]
    np.testing.assert_array_equal(robot.project(inside)[0], inside)


def test_observations_are_finite_float32_within_bounds_and_rewards_match():
    env = CTRReachEnv(reward="dense")
    obs, _ = env.reset(seed=1)
    for _ in range(10):
        obs, r, term, trunc, info = env.step(env.action_space.sample())
        assert obs["observation"].dtype == np.float32
        assert np.isfinite(obs["observation"]).all()
        assert np.abs(obs["observation"]).max() <= OBS_BOUND
        expected = -info["distance"] / 0.01 + (info["distance"] <= 1e-3)
        assert r == pytest.approx(expected, rel=1e-5)
        if term or trunc:
            break


def test_compute_reward_is_vectorized_and_follows_the_tolerance():
    env = CTRReachEnv()
    env.reset(seed=0)
    ag = np.zeros((5, 3))
    dg = np.zeros((5, 3))
    dg[:, 0] = [0.0, 0.5e-3, 1.5e-3, 4e-3, 20e-3]
    np.testing.assert_array_equal(env.compute_reward(ag, dg, {}), [0, 0, -1, -1, -1])
    env.set_tolerance(5e-3)
    np.testing.assert_array_equal(env.compute_reward(ag, dg, [{}] * 5), [0, 0, 0, 0, -1])
    with pytest.raises(ValueError, match="tolerance"):
        env.set_tolerance(-1.0)


def test_bad_options_name_the_field():
    with pytest.raises(ValueError, match="control"):
        CTRReachEnv(control="velocity")
    with pytest.raises(ValueError, match="CarriageModel.control_period"):
        CTRReachEnv(carriage={"control_period": 0.0})
    with pytest.raises(ValueError, match="snap_mode"):
        CTRReachEnv(snap_mode="ignore")
    with pytest.raises(ValueError, match="render_mode"):
        CTRReachEnv(render_mode="video")


def test_joint_env_moves_at_most_one_mm_and_five_degrees():
    env = gym.make("torchpvs/CTRReachJoint-v0")
    env.reset(seed=2)
    x0 = env.unwrapped.actuation
    env.step(np.ones(4, np.float32))
    dx = np.abs(env.unwrapped.actuation - x0)
    assert dx[:2].max() <= 1e-3 + 1e-12 and dx[2:].max() <= math.radians(5) + 1e-12


def test_vec_env_autoreset_and_sb3_contract():
    venv = CTRReachVecEnv(2, max_episode_steps=3)
    venv.seed(0)
    venv.reset()
    for _ in range(3):
        obs, r, dones, infos = venv.step(np.zeros((2, 4), np.float32))
    assert dones.all()
    assert all(i["TimeLimit.truncated"] for i in infos)
    assert set(infos[0]["terminal_observation"]) == {"observation", "achieved_goal",
                                                      "desired_goal"}
    # HER relabelling path
    rew = venv.env_method("compute_reward", obs["achieved_goal"], obs["desired_goal"],
                          [{}, {}], indices=[0])
    assert len(rew) == 1 and rew[0].shape == (2,)
    venv.env_method("set_tolerance", 0.02)
    assert venv.get_attr("tolerance") == [0.02, 0.02]


def test_rgb_render():
    env = CTRReachEnv(render_mode="rgb_array")
    env.reset(seed=0)
    img = env.render()
    assert img.ndim == 3 and img.shape[-1] == 3 and img.dtype == np.uint8 and img.std() > 0
    env.close()


def test_three_tube_preset_steps():
    env = CTRReachEnv(robot="rvim_three_tube")
    obs, _ = env.reset(seed=0)
    assert env.action_space.shape == (6,)
    obs, r, *_ = env.step(env.action_space.sample())
    assert np.isfinite(obs["observation"]).all()


@pytest.mark.parametrize("make", [fig3_two_tube, rvim_three_tube])
def test_stored_force_scales_match_a_fresh_measurement(make):
    """The presets' force/torque scales are 1.5 x p99 |dU*/dx| over the workspace; a fresh,
    smaller, differently seeded sample must agree within 30 %."""
    robot = make()
    torch.manual_seed(0)
    f, t, m = measure_force_scales(robot, n=160, seed=5)
    np.testing.assert_allclose(f, robot.force_scale, rtol=0.3)
    np.testing.assert_allclose(t, robot.torque_scale, rtol=0.3)
    assert 0.3 < m / robot.margin_scale < 3


def _energy_rollout(control_period: float, seconds: float = 1.5) -> np.ndarray:
    """Stored energy U* ``(steps + 1, 4)`` of 4 robots relaxing with tau_cmd = 0."""
    robot = fig3_two_tube()
    rb = RobotBatch(robot, CarriageModel(control_period=control_period), 4)
    rb.set_state(np.arange(4), robot.sample_actuation(np.random.default_rng(4), 4))
    energy = [solve_batch(robot, rb.x, initial=rb.q).energy.numpy()]
    for _ in range(int(round(seconds / control_period))):
        rb.step_force(np.zeros((4, 4)))
        energy.append(solve_batch(robot, rb.x, initial=rb.q).energy.numpy())
    return np.array(energy)


def test_relaxation_dissipates_energy_even_at_kinks():
    """tau_cmd = 0 with damping: b xdot = -g = -dU*/dx is a gradient flow, so U* must not grow.
    The linearly implicit step alone overshoots where U*(x) has a kink (a straight-to-curved
    transition crossing a tube end, docs/physics.md "sliding section boundaries"): an O(h) rise, up
    to 8.6e-4 J per step on these robots. The Armijo acceptance of envs/dynamics.py
    rejects such steps, so U* never rises beyond round-off, at either period, and every
    robot's energy drops overall."""
    e1, e2 = _energy_rollout(0.1), _energy_rollout(0.05)
    scale = np.abs(e1).max()
    for e in (e1, e2):
        assert (e[-1] <= e[0] + 1e-12).all()
        assert np.diff(e, axis=0).max() <= 1e-10 * scale


@given(seed=st.integers(0, 2**31 - 1), control=st.sampled_from(["force", "joint"]))
@settings(max_examples=6, deadline=None)
def test_limits_never_violated_under_random_actions(seed, control):
    """docs/conventions.md nesting rules and the strokes hold for every state of a random
    rollout."""
    venv = CTRReachVecEnv(4, control=control, max_episode_steps=8)
    venv.seed(seed)
    venv.reset()
    rng = np.random.default_rng(seed)
    robot = venv.robot
    L = robot.lengths
    for _ in range(8):
        venv.step(rng.uniform(-1, 1, (4, 4)))
        D = venv.task.robots.x[:, :2]
        assert (D >= np.array(robot.insertion_min) - 1e-12).all()
        assert (D <= np.array(robot.insertion_max) + 1e-12).all()
        assert (D[:, 1] >= D[:, 0]).all()
        assert (L[1] - D[:, 1] >= L[0] - D[:, 0] - 1e-12).all()
        assert (L - D >= robot.min_exposed - 1e-12).all()


@pytest.mark.parametrize("robot", ["fig3_two_tube", "rvim_three_tube",
                                   "renda2021_section3b"])
@pytest.mark.parametrize("n_env,steps", [
    (15, 40),
    pytest.param(50, 67, marks=pytest.mark.slow),  # 10,000 robot-steps over the 3 robots
])
def test_no_nan_over_many_random_steps(robot, n_env, steps):
    """Random actions on the presets and the section III-B robot (the snapping hard case of
    docs/physics.md): observations and rewards always finite, through snaps and resets."""
    venv = CTRReachVecEnv(n_env, robot=robot, max_episode_steps=30, snap_mode="continue")
    venv.seed(1)
    obs = venv.reset()
    rng = np.random.default_rng(1)
    k = venv.action_space.shape[0]
    for _ in range(steps):
        obs, r, d, infos = venv.step(rng.uniform(-1, 1, (n_env, k)))
        assert np.isfinite(r).all()
        for v in obs.values():
            assert np.isfinite(v).all()
