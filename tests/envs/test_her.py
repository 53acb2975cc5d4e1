"""HER keeps the snap penalty (issue 13, item 1): the snap flag rides in ``achieved_goal``, so
SB3's HerReplayBuffer with its defaults (``copy_info_dict=False``) relabels a snap step with
its penalty; all three env faces compute the same rewards."""

from __future__ import annotations

import numpy as np
import pytest
from stable_baselines3 import HerReplayBuffer
from stable_baselines3.common.vec_env import DummyVecEnv

import envs
from envs import CTRReachEnv, CTRReachVectorEnv


@pytest.fixture(scope="module")
def snap_episode():
    """A real episode ending in a snap: the three-tube robot (seed 2) with its outer and
    middle tubes twisted against each other at full torque snaps within a few steps."""
    env = CTRReachEnv(robot="rvim_three_tube")
    obs, _ = env.reset(seed=2)
    action = np.array([0, 0, 0, -1, 1, 0], np.float32)
    episode = []
    for _ in range(20):
        nxt, r, term, trunc, info = env.step(action)
        episode.append((obs, nxt, action, r, term or trunc, info))
        obs = nxt
        if term or trunc:
            break
    assert episode[-1][5]["snap_terminated"], "the scenario must end in a snap"
    return env, episode


def test_the_snap_flag_is_in_the_achieved_goal(snap_episode):
    env, episode = snap_episode
    *_, (obs, nxt, _, r, done, info) = episode
    assert nxt["achieved_goal"][3] == 1.0 and obs["achieved_goal"][3] == 0.0
    assert nxt["desired_goal"][3] == 0.0
    assert r == pytest.approx(-1.0 + env.config.snap_penalty)
    np.testing.assert_allclose(nxt["achieved_goal"][:3], env.state().tip[0], atol=1e-7)
    obs, _ = env.reset(seed=0)                            # a new episode clears the flag
    assert obs["achieved_goal"][3] == 0.0


@pytest.mark.parametrize("face", ["single", "sb3_vec"])
def test_her_relabelled_snap_steps_keep_their_penalty(snap_episode, face):
    env, episode = snap_episode
    venv = (DummyVecEnv([lambda: CTRReachEnv(robot="rvim_three_tube")]) if face == "single"
            else envs.CTRReachVecEnv(1, robot="rvim_three_tube"))
    buffer = HerReplayBuffer(100, env.observation_space, env.action_space, env=venv,
                             device="cpu", n_sampled_goal=4, goal_selection_strategy="future")
    assert buffer.copy_info_dict is False                 # SB3's default: no infos
    for obs, nxt, a, r, done, info in episode:
        buffer.add({k: v[None] for k, v in obs.items()}, {k: v[None] for k, v in nxt.items()},
                   a[None], np.array([r]), np.array([done]), [info])
    np.random.seed(0)
    data = buffer.sample(512)
    n_virtual = int(buffer.her_ratio * 512)
    flag = data.next_observations["achieved_goal"][-n_virtual:, 3].numpy() > 0.5
    rewards = data.rewards[-n_virtual:, 0].numpy()
    penalty = env.config.snap_penalty
    assert flag.sum() > 20
    # every relabelled snap step carries the penalty; relabelled with the goal it reached
    # (reward 0 without the penalty) it reads exactly the penalty
    assert (rewards[flag] <= penalty + 1e-6).all()
    assert np.isclose(rewards[flag], penalty).any()
    assert (rewards[~flag] > penalty).all()               # the other steps never do
    np.testing.assert_array_equal(data.dones[-n_virtual:, 0].numpy()[flag], 1.0)


def test_the_three_faces_compute_the_same_rewards():
    """Vectorized over any leading shape, the same numbers from the single env, the
    Gymnasium vector env and the SB3 adapter, with the flag and with info-carried snaps."""
    faces = [CTRReachEnv().compute_reward, CTRReachVectorEnv(2).compute_reward,
             lambda ag, dg, info: envs.CTRReachVecEnv(2).env_method(
                 "compute_reward", ag, dg, info, indices=[0])[0]]
    rng = np.random.default_rng(0)
    ag = np.concatenate([rng.normal(size=(2, 5, 3)) * 1e-3, (rng.random((2, 5, 1)) < 0.3)], -1)
    dg = np.concatenate([ag[..., :3] + rng.normal(size=(2, 5, 3)) * 1e-3,
                         rng.random((2, 5, 1)) < 0.5], -1)   # a relabelled flag: ignored
    d = np.linalg.norm(ag[..., :3] - dg[..., :3], axis=-1)
    expected = -1.0 * (d > 1e-3) - 60.0 * ag[..., 3]          # the default snap_penalty
    infos = np.array([[{"snap_terminated": bool(f)} for f in row] for row in ag[..., 3]])
    for compute in faces:
        np.testing.assert_array_equal(compute(ag, dg, {}), expected.astype(np.float32))
        no_flag = ag.copy()
        no_flag[..., 3] = 0
        np.testing.assert_array_equal(compute(no_flag, dg, infos), expected.astype(np.float32))
        assert compute(ag[..., :3], dg[..., :3], {}).shape == (2, 5)    # positions only
