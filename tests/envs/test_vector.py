"""The Gymnasium-native batched environment (envs/vector.py): registration through
``vector_entry_point``, Gymnasium's vector contract (spaces, SAME_STEP autoreset with
``final_obs``/``final_info``, vector info format, seeding), and equality with single envs."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import envs
from envs import CTRReachEnv, CTRReachVectorEnv

ID = "torchpvs/CTRReachForce-v0"


def test_import_needs_no_stable_baselines3():
    code = ("import sys, envs, gymnasium as gym; "
            "assert 'stable_baselines3' not in sys.modules, 'imported sb3'; "
            "envs.CTRReachVecEnv; assert 'stable_baselines3' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("env_id", list(envs.ENV_IDS))
def test_make_vec_returns_the_batched_env(env_id):
    v = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point")
    assert isinstance(v, CTRReachVectorEnv) and v.num_envs == 3
    assert v.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert v.config.control == envs.ENV_IDS[env_id]
    obs, info = v.reset(seed=0)
    assert v.observation_space.contains(obs) and isinstance(info, dict)
    for _ in range(2):
        obs, rew, term, trunc, info = v.step(v.action_space.sample())
        assert v.observation_space.contains(obs)
        assert rew.shape == term.shape == trunc.shape == (3,)
        assert term.dtype == bool and trunc.dtype == bool and np.isfinite(rew).all()
        for key, value in info.items():          # Gymnasium's vector info format
            if not key.startswith("_"):
                assert len(value) == 3 and info[f"_{key}"].shape == (3,)
    v.close()


def _seeded_batch(kind: str, B: int, seed: int):
    """``(first observation, step(actions) -> observation)`` of a batch of kind ``kind``."""
    if kind == "gymnasium":
        v = CTRReachVectorEnv(B)
        obs, _ = v.reset(seed=seed)
    else:
        v = envs.CTRReachVecEnv(B)
        v.seed(seed)
        obs = v.reset()
    return obs, lambda a: v.step(a)[0]


@pytest.mark.parametrize("kind", ["gymnasium", "sb3"])
def test_batch_equals_single_envs_seeded_the_same_way(kind):
    """Robot i of a batch seeded with s (Gymnasium ``reset(seed=s)``, SB3 ``seed(s)``) is the
    single env whose generator is the i-th child of SeedSequence(s): same goal, and the same
    trajectory under the same actions (up to the solver's tolerance: batched and single solves
    stop at different iterations)."""
    B = 3
    obs, step = _seeded_batch(kind, B, 11)
    singles = []
    for i, ss in enumerate(np.random.SeedSequence(11).spawn(B)):
        e = CTRReachEnv()
        e.reset(seed=0)
        e.task.rngs = [np.random.default_rng(ss)]
        e.task.reset(np.array([0]))
        singles.append(e)
        np.testing.assert_allclose(e._obs()["desired_goal"], obs["desired_goal"][i], atol=1e-6)
    rng = np.random.default_rng(0)
    for _ in range(3):
        a = rng.uniform(-1, 1, (B, 4)).astype(np.float32)
        obs = step(a)
        for i, e in enumerate(singles):
            o, *_ = e.step(a[i])
            np.testing.assert_allclose(o["achieved_goal"], obs["achieved_goal"][i], atol=1e-6)


def test_same_step_autoreset_reports_the_final_observation():
    v = CTRReachVectorEnv(2, max_episode_steps=3)
    v.reset(seed=0)
    for _ in range(2):
        obs, _, term, trunc, info = v.step(np.zeros((2, 4), np.float32))
        assert not (term | trunc).any() and "final_obs" not in info
    last_goal = obs["desired_goal"].copy()
    obs, _, term, trunc, info = v.step(np.zeros((2, 4), np.float32))
    assert trunc.all() and info["_final_obs"].all() and info["_final_info"].all()
    for i in range(2):
        final = info["final_obs"][i]
        assert set(final) == {"observation", "achieved_goal", "desired_goal"}
        np.testing.assert_array_equal(final["desired_goal"], last_goal[i])
        assert "distance" in info["final_info"][i]
    # the returned observation starts the next episode: new goals were drawn
    assert not np.allclose(obs["desired_goal"], last_goal)
    assert (v.elapsed == 0).all()


def test_reset_is_deterministic_and_data_is_not_reused():
    v = CTRReachVectorEnv(2)
    a, _ = v.reset(seed=5)
    b, _ = v.reset(seed=5)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        assert a[k] is not b[k]
    o1, *_ = v.step(np.zeros((2, 4), np.float32))
    o2, *_ = v.step(np.zeros((2, 4), np.float32))
    assert all(o1[k] is not o2[k] for k in o1)


def test_bad_actions_raise():
    v = CTRReachVectorEnv(2)
    v.reset(seed=0)
    with pytest.raises(ValueError):
        v.step(np.full((2, 4), np.nan, np.float32))
    with pytest.raises(ValueError):
        v.step(np.zeros((1, 2, 4), np.float32))


def test_compute_reward_matches_the_single_env():
    v = CTRReachVectorEnv(2)
    e = CTRReachEnv()
    rng = np.random.default_rng(1)
    ag, dg = rng.normal(size=(5, 3)) * 0.01, rng.normal(size=(5, 3)) * 0.01
    np.testing.assert_array_equal(v.compute_reward(ag, dg, {}), e.compute_reward(ag, dg, {}))
