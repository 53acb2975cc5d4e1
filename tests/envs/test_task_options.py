"""Task options: compensated force actions, the squashed error entry of the
observation, continuing after a snap, and Gymnasium's checker on every option combination."""

from __future__ import annotations

import math

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import envs
from envs import CarriageModel, CTRReachEnv, CTRReachVectorEnv, RobotBatch


@pytest.mark.parametrize("robot", ["fig3_two_tube", "rvim_three_tube"])
@pytest.mark.parametrize("control,compensation", [("force", False), ("force", True),
                                                  ("joint", False)])
@pytest.mark.parametrize("snap_mode", ["terminate", "continue"])
def test_check_env_passes_for_every_option(robot, control, compensation, snap_mode):
    env = CTRReachEnv(robot=robot, control=control, compensation=compensation,
                      snap_mode=snap_mode)
    gym_check_env(env, skip_render_check=True)
    N = env.robot.n_tubes
    assert env.observation_space["observation"].shape == (2 * N + N + 4 * N + 10 + 2 * N,)
    assert env.observation_space["achieved_goal"].shape == (4,)


def test_vector_env_checks_with_the_options():
    v = CTRReachVectorEnv(2, compensation=True, snap_mode="continue")
    obs, _ = v.reset(seed=0)
    assert v.observation_space.contains(obs)
    obs, *_ = v.step(np.zeros((2, 4), np.float32))
    assert v.observation_space.contains(obs)
    assert v.single_observation_space == CTRReachEnv(compensation=True).observation_space


def test_compensated_zero_action_holds_still_and_offsets_add_to_the_load():
    """tau = g(x) + scale * a: action 0 is rest (b xdot = tau - g = 0) exactly, where raw
    force actions would need g / scale to float32 precision; a nonzero action moves the
    robot exactly as the raw force g + scale * a does on a separate RobotBatch."""
    env = CTRReachEnv(compensation=True)
    env.reset(seed=3)
    x0 = env.state().x
    _, _, _, _, info = env.step(np.zeros(4, np.float32))
    np.testing.assert_array_equal(env.state().x, x0)
    np.testing.assert_allclose(info["tau"], env.state().g[0], rtol=1e-12)
    a = np.array([0.0, 0.2, -0.1, 0.0], np.float32)
    s = env.state()
    rb = RobotBatch(env.robot, CarriageModel(), 1)
    rb.set_state(np.array([0]), s.x)
    rb.step_force(s.g + a.astype(np.float64) * s.action_scale)
    env.step(a)
    np.testing.assert_allclose(env.state().x, rb.x, rtol=0, atol=1e-12)
    assert np.abs(env.state().x - x0).max() > 1e-4


def test_compensation_is_for_force_control_only():
    with pytest.raises(ValueError, match="compensation=True needs control='force'"):
        CTRReachEnv(control="joint", compensation=True)
    with pytest.raises(ValueError, match="compensation must be True or False"):
        CTRReachEnv(compensation="yes")
    with pytest.raises(ValueError, match="error_scale"):
        CTRReachEnv(error_scale=0.0)


@pytest.mark.parametrize("kind", ["overdamped", "second_order"])
def test_the_error_entry_resolves_a_millimetre(kind):
    """Observation entries after the tip and the workspace-scaled error hold
    tanh((goal - tip) / 10 mm): 1 mm reads tanh(0.1) = 0.0997 (it read 1/303.5 = 0.0033 in
    the workspace-scaled entry)."""
    env = CTRReachEnv(carriage={"kind": kind})
    obs, _ = env.reset(seed=1)
    N = 2
    start = 7 * N + (2 * N if kind == "second_order" else 0) + 6
    s = env.state()
    err = s.goal[0] - s.tip[0]
    np.testing.assert_allclose(obs["observation"][start:start + 3], np.tanh(err / 0.01),
                               rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(obs["observation"][start - 3:start], err / env.robot.reach,
                               rtol=1e-6, atol=1e-7)
    # a goal 1 mm away along x, by moving the goal (the entry is a function of the error)
    env.task.goal[0] = s.tip[0] + [1e-3, 0.0, 0.0]
    o = env._obs()["observation"]
    assert o[start] == pytest.approx(math.tanh(0.1), rel=1e-6)


def test_continue_mode_settles_on_the_new_branch_and_goes_on():
    """Twisting the outer and middle tubes of the three-tube robot against each other snaps
    it (seed 2, second step). With snap_mode="continue" the episode goes on without the
    penalty, the robot lands on a stable equilibrium of the other branch (the tip jumped by
    far more than the carriages explain) and, held with action 0 (compensated), stays there."""
    env = CTRReachEnv(robot="rvim_three_tube", snap_mode="continue", compensation=True)
    env.reset(seed=2)
    twist = np.array([0, 0, 0, -1, 1, 0], np.float32)
    for _ in range(5):
        tip0 = env.state().tip[0]
        obs, r, term, trunc, info = env.step(twist)
        if info["snapped"]:
            break
    assert info["snapped"] and not info["snap_terminated"] and not (term or trunc)
    assert r == -1.0 and obs["achieved_goal"][3] == 0.0       # no penalty in continue mode
    s = env.state()
    assert np.linalg.norm(s.tip[0] - tip0) > 0.05 and s.margin[0] > 0
    settled = None
    for k in range(4):
        obs, r, term, trunc, info = env.step(np.zeros(6, np.float32))
        assert not (term or trunc or info["snapped"])
        assert env.state().margin[0] > 0
        if k == 1:
            settled = env.state().tip[0]
    # after the substeps of the snap period have finished moving it, it is at rest
    np.testing.assert_allclose(env.state().tip[0], settled, atol=1e-9)


def test_terminate_stays_the_default():
    assert envs.ReachConfig().snap_mode == "terminate"
    assert envs.ReachConfig().compensation is False


# -- the step reward is compute_reward of the float32 goals ------------------
FIG3_COMBINATIONS = [(control, compensation, reward, snap_mode)
                     for control, compensation in [("force", False), ("force", True),
                                                   ("joint", False)]
                     for reward in ("sparse", "dense", "shaped")
                     for snap_mode in ("terminate", "continue")]


@pytest.mark.parametrize("control,compensation,reward,snap_mode", FIG3_COMBINATIONS)
def test_sb3_check_env_passes_on_every_fig3_combination(control, compensation, reward,
                                                        snap_mode):
    """SB3's checker compares the step reward with ``compute_reward(obs["achieved_goal"],
    obs["desired_goal"], info)`` for EQUALITY. The reward used to come from the float64 tip
    and goal, compute_reward from the float32 observation: dense rewards differed by up to
    2.8e-7 relative (3 of 8 fig3 combinations failed)."""
    import warnings

    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = CTRReachEnv(control=control, compensation=compensation, reward=reward,
                      snap_mode=snap_mode)
    # the checker's step follows reset(seed=0); the action seeds 0, 1 and 4 each failed
    # one or more of the dense combinations before (force 1; compensated 0, 4; joint 4)
    for seed in (0, 1, 4):
        env.reset(seed=seed)
        env.action_space.seed(seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sb3_check_env(env, warn=False)


@pytest.mark.parametrize("control,compensation", [("force", False), ("force", True),
                                                  ("joint", False)])
def test_dense_step_reward_is_compute_reward_of_the_observation_bit_for_bit(control,
                                                                            compensation):
    """Over 30 random steps of three seeded episodes: reward == compute_reward of the returned
    float32 goals exactly, and is_success is the reward's own inside test."""
    env = CTRReachEnv(control=control, compensation=compensation, reward="dense")
    rng = np.random.default_rng(0)
    n = 0
    for seed in range(3):
        env.reset(seed=seed)
        for _ in range(10):
            obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
            assert r == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
            n += 1
            if term or trunc:
                break
    assert n >= 10


def test_info_carries_the_reward_terms_and_they_sum_to_the_reward():
    """info["reward_distance"] + info["reward_snap"] is the step reward to the bit (dense
    random steps), and a terminating snap puts snap_penalty into the snap term alone (the
    snap of test_continue_mode_settles_on_the_new_branch_and_goes_on, in terminate mode)."""
    env = CTRReachEnv(reward="dense")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(5):
        _, r, _, _, info = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        assert r == np.float32(info["reward_distance"] + info["reward_snap"])
        assert info["reward_snap"] == 0.0
    env = CTRReachEnv(robot="rvim_three_tube", compensation=True)
    env.reset(seed=2)
    for _ in range(5):
        _, r, term, _, info = env.step(np.array([0, 0, 0, -1, 1, 0], np.float32))
        if term:
            break
    assert info["snap_terminated"]
    assert info["reward_snap"] == env.config.snap_penalty and info["reward_distance"] == -1.0
    assert r == np.float32(info["reward_distance"] + info["reward_snap"])


def test_shaped_reward_is_the_sparse_reward_plus_a_bounded_pull():
    """``reward="shaped"``: -1 outside the tolerance, 0 inside, minus ``shaping_weight *
    min(d / dense_scale, 1)``. Values by hand at 1 mm tolerance, 3 mm scale, weight 0.5:
    0 mm -> 0; 0.6 mm -> -0.1; 1.5 mm -> -1.25; 3 mm and 50 mm -> -1.5 (the cap: far away it
    is the sparse reward scaled by 1.5)."""
    env = CTRReachEnv(compensation=True, reward="shaped", dense_scale=0.003)
    d = np.array([0.0, 0.6e-3, 1.5e-3, 3e-3, 50e-3])
    goal = np.array([0.01, -0.02, 0.1, 0.0])
    ag = np.tile(goal, (5, 1))
    ag[:, 0] += d
    dg = np.tile(goal, (5, 1))
    np.testing.assert_allclose(env.compute_reward(ag, dg, {}), [0.0, -0.1, -1.25, -1.5, -1.5],
                               rtol=0, atol=1e-6)
    heavier = CTRReachEnv(compensation=True, reward="shaped", dense_scale=0.003,
                          shaping_weight=2.0)
    np.testing.assert_allclose(heavier.compute_reward(ag, dg, {}), [0, -0.4, -2.0, -3.0, -3.0],
                               rtol=0, atol=1e-6)


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), "0.5"])
def test_shaping_weight_is_checked_by_name(bad):
    with pytest.raises(ValueError, match="shaping_weight"):
        envs.ReachConfig(reward="shaped", shaping_weight=bad)


def test_stiffness_penalty_marks_unstable_steps_and_her_recomputes_it(on_fold_branch):
    """``stiffness_penalty``: a step that ends with the relative rotation stiffness below
    ``STIFFNESS_HAZARD * stiffness_scale`` adds the penalty, flags ``achieved_goal[3] = 0.5``
    and ``compute_reward`` of the returned goals gives the step reward (what HER recomputes).
    Reference state: the Fig. 3 robot at ``D = (98.7, 164.5) mm`` with the inner tube turned
    176 deg along the branch from 120 deg, where ``dtau_2/dalpha_2 < 0`` (finite differences
    in tests/envs/test_state.py); at 150 deg it is stable and nothing is added."""
    from envs.task import STIFFNESS_HAZARD, UNSTABLE_FLAG, relative_rotation_stiffness
    env = CTRReachEnv(compensation=True, reward="shaped", dense_scale=3e-3,
                      stiffness_penalty=-2.0)
    env.reset(seed=0)
    seen = {}
    for deg, _, _ in on_fold_branch(env):
        obs, r, term, trunc, info = env.step(np.zeros(4, np.float32))
        k = relative_rotation_stiffness(env.state().stiffness)[0]
        unstable = k < STIFFNESS_HAZARD * env.task.stiffness_scale
        assert bool(info["unstable"]) == unstable and not info["snapped"]
        assert obs["achieved_goal"][3] == (UNSTABLE_FLAG if unstable else 0.0)
        assert info["reward_stiffness"] == (-2.0 if unstable else 0.0)
        assert r == pytest.approx(info["reward_distance"] + info["reward_snap"]
                                  + info["reward_stiffness"], abs=1e-6)
        assert r == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
        seen[deg] = unstable
    assert seen == {150: False, 176: True}
    # the flag alone carries it (HER relabels goals, not infos); a snap is not also penalized
    ag = np.array([[0.0, 0.0, 0.1, 0.0], [0.0, 0.0, 0.1, UNSTABLE_FLAG], [0.0, 0.0, 0.1, 1.0]])
    dg = np.array([[0.0, 0.0, 0.1, 0.0]] * 3)
    np.testing.assert_allclose(env.compute_reward(ag, dg, {}), [0.0, -2.0, -60.0])
    off = CTRReachEnv(compensation=True)
    np.testing.assert_allclose(off.compute_reward(ag, dg, {}), [0.0, 0.0, -60.0])
    with pytest.raises(ValueError, match="stiffness_penalty must be a finite number <= 0"):
        CTRReachEnv(stiffness_penalty=1.0)
    with pytest.raises(ValueError, match="stiffness_penalty needs control='force'"):
        CTRReachEnv(control="joint", stiffness_penalty=-1.0)


def test_stiffness_hazard_moves_the_threshold(on_fold_branch):
    """``stiffness_hazard`` is the threshold on ``k_rel / stiffness_scale``: at the unstable
    reference state of the fold branch (176 deg, see above) a hazard just above its measured
    ``k_rel / stiffness_scale`` flags the step and one just below does not; bad values name
    the field."""
    from envs.task import relative_rotation_stiffness

    def last_step(hazard):
        env = CTRReachEnv(compensation=True, reward="shaped", stiffness_penalty=-1.0,
                          stiffness_hazard=hazard)
        env.reset(seed=0)
        degrees = []
        for deg, _, _ in on_fold_branch(env):
            degrees.append(deg)
            _, _, _, _, info = env.step(np.zeros(4, np.float32))
        assert degrees[-1] == 176
        return relative_rotation_stiffness(env.state().stiffness)[0] \
            / env.task.stiffness_scale, info

    ratio, _ = last_step(-0.01)
    assert ratio < -0.01
    assert last_step(0.9 * ratio)[1]["unstable"]
    _, info = last_step(1.1 * ratio)
    assert not info["unstable"] and info["reward_stiffness"] == 0.0
    for bad in (0.0, 0.5, float("nan")):
        with pytest.raises(ValueError, match="stiffness_hazard must be a finite number < 0"):
            envs.ReachConfig(stiffness_hazard=bad)
