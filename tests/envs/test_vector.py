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
    single env reset with seed s + i (Gymnasium's SyncVectorEnv and SB3's DummyVecEnv rule;
    earlier it was the i-th child of SeedSequence(s), which no single env reproduced):
    same goal, and the same trajectory under the same actions (up to the solver's tolerance:
    batched and single solves stop at different iterations)."""
    B = 3
    obs, step = _seeded_batch(kind, B, 11)
    singles = []
    for i in range(B):
        e = CTRReachEnv()
        o, _ = e.reset(seed=11 + i)
        singles.append(e)
        np.testing.assert_allclose(o["desired_goal"], obs["desired_goal"][i], atol=1e-6)
        np.testing.assert_allclose(o["achieved_goal"], obs["achieved_goal"][i], atol=1e-6)
    rng = np.random.default_rng(0)
    for _ in range(3):
        a = rng.uniform(-1, 1, (B, 4)).astype(np.float32)
        obs = step(a)
        for i, e in enumerate(singles):
            o, *_ = e.step(a[i])
            np.testing.assert_allclose(o["achieved_goal"], obs["achieved_goal"][i], atol=1e-6)


def test_robot_zero_of_a_batch_is_the_single_env_with_the_same_seed():
    """Regression: ``reset(seed=7)`` of robot 0 and ``gym.make(id).reset(seed=7)``
    gave different goals."""
    v = gym.make_vec(ID, num_envs=2, vectorization_mode="vector_entry_point")
    ov, _ = v.reset(seed=7)
    o, _ = gym.make(ID).reset(seed=7)
    np.testing.assert_allclose(ov["desired_goal"][0], o["desired_goal"], atol=1e-6)


# rl_zoo3.gym_patches (imported by other tests in the same session) replaces Gymnasium's
# TimeLimit with one that adds "TimeLimit.truncated" to the info of the last step
_ZOO_KEYS = {"TimeLimit.truncated", "_TimeLimit.truncated"}


def _assert_same_infos(a: dict, b: dict, where: str) -> None:
    """Gymnasium vector infos ``a`` (SyncVectorEnv) and ``b`` (ours): same keys, masks and
    dtypes; values equal where masked (floats to the solver's round-off)."""
    a = {k: v for k, v in a.items() if k not in _ZOO_KEYS}
    assert set(a) == set(b), f"{where}: keys {sorted(set(a) ^ set(b))} differ"
    for key in a:
        if key.startswith("_"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{where}: mask {key}")
            assert a[key].dtype == b[key].dtype == np.bool_
        elif isinstance(a[key], dict):
            _assert_same_infos(a[key], b[key], f"{where}/{key}")
        elif key == "final_obs":
            for i in np.flatnonzero(a["_final_obs"]):
                for k in a[key][i]:
                    np.testing.assert_allclose(a[key][i][k], b[key][i][k], atol=1e-6,
                                               err_msg=f"{where}: final_obs[{i}][{k}]")
            assert all(b[key][i] is None for i in np.flatnonzero(~b["_final_obs"]))
        else:
            assert a[key].dtype == b[key].dtype and a[key].shape == b[key].shape, \
                f"{where}: {key} {a[key].dtype}{a[key].shape} vs {b[key].dtype}{b[key].shape}"
            m = a[f"_{key}"]
            if a[key].dtype.kind == "f":
                np.testing.assert_allclose(a[key][m], b[key][m], rtol=1e-5, atol=1e-6,
                                           err_msg=f"{where}: {key}")
                assert (b[key][~m] == 0).all()
            else:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{where}: {key}")


@pytest.mark.parametrize("env_id", list(envs.ENV_IDS))
def test_matches_sync_vector_env_of_the_single_env(env_id):
    """Regression: ``vector_entry_point`` and ``SyncVectorEnv`` of the single env (same
    SAME_STEP autoreset) give the same infos (keys, ``_key`` masks, dtypes, ``final_obs`` and a
    ``final_info`` dict of arrays), the same autoreset steps and the same episodes for the same
    seed, also when the robots' episodes end at different steps (a ``reset_mask`` reset of
    robot 1 shifts its time limit)."""
    B, T = 3, 4
    sync = gym.make_vec(env_id, num_envs=B, vectorization_mode="sync", max_episode_steps=T,
                        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})
    ours = gym.make_vec(env_id, num_envs=B, vectorization_mode="vector_entry_point",
                        max_episode_steps=T)
    assert ours.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"]
    (os_, is_), (ov, iv) = sync.reset(seed=3), ours.reset(seed=3)
    _assert_same_infos(is_, iv, "reset")
    for k in os_:
        np.testing.assert_allclose(os_[k], ov[k], atol=1e-6)
    rng = np.random.default_rng(0)
    ended = []
    for t in range(2 * T + 2):
        if t == 2:
            mask = np.array([False, True, False])
            (os_, is_), (ov, iv) = (e.reset(seed=[None, 40, None], options={"reset_mask": mask})
                                    for e in (sync, ours))
            _assert_same_infos(is_, iv, "masked reset")
        a = rng.uniform(-1, 1, (B, 4)).astype(np.float32)
        rs, rv = sync.step(a), ours.step(a)
        for k in rs[0]:
            np.testing.assert_allclose(rs[0][k], rv[0][k], atol=1e-6, err_msg=f"step {t} {k}")
        np.testing.assert_allclose(rs[1], rv[1], atol=1e-6)
        assert rs[1].dtype == rv[1].dtype == np.float64
        np.testing.assert_array_equal(rs[2], rv[2])
        np.testing.assert_array_equal(rs[3], rv[3])
        _assert_same_infos(rs[4], rv[4], f"step {t}")
        ended.append(tuple(rs[2] | rs[3]))
    # episodes ended at different steps: robot 1's was restarted at t = 2
    assert any(any(e) and not all(e) for e in ended)
    sync.close()
    ours.close()


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
    # Gymnasium's format: final_info is a dict of arrays with masks, not per-env dicts
    fi = info["final_info"]
    assert isinstance(fi, dict) and fi["distance"].shape == (2,) and fi["_distance"].all()
    assert fi["is_success"].dtype == bool and fi["tau"].shape == (2, 4)
    # the top level holds the reset infos of the new episodes (as SyncVectorEnv)
    assert set(k for k in info if not k.startswith("_")) == {
        "final_obs", "final_info", "is_success", "distance", "snapped", "solver_failure"}
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


def test_info_list_is_info_of_for_every_robot():
    """The VecEnv's per-step infos, converted once per key (ReachBatch.info_list), are each
    robot's info_of: the same keys, values and Python types."""
    import envs
    venv = envs.CTRReachVecEnv(5)
    venv.seed(2)
    venv.reset()
    _, _, _, batched = venv.task.step_checked(np.zeros((5, 4), dtype=np.float32))
    fast = venv.task.info_list(batched, 5)
    for i in range(5):
        ref = venv.task.info_of(batched, i)
        assert list(fast[i]) == list(ref)
        for k, v in ref.items():
            assert type(fast[i][k]) is type(v), k
            np.testing.assert_array_equal(fast[i][k], v)
