"""Action ensembles (training/ensemble.py): ``mean`` is the average of the members' own
deterministic actions (each taken from SB3's ``predict``, not from the ensemble's code),
``qsel`` returns, per robot, the member action that the members' critics (called directly)
rate highest in sum, ``switch`` the far member's action exactly for the robots whose tip is
farther from the goal than the distance (from the env's own state), one member alone is that
member, and bad members and settings are refused by name."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import envs
from training.ensemble import ensemble_policy

ENV = "torchpvs/CTRReachForce-v0"


@pytest.fixture(scope="module")
def members(tmp_path_factory):
    """Three untrained SAC agents (different seeds: different actors and critics) saved with
    the sibling .json training.evaluate reads, and one PPO agent."""
    import gymnasium as gym
    from stable_baselines3 import PPO, SAC
    tmp = tmp_path_factory.mktemp("ensemble")
    env = gym.make(ENV, max_episode_steps=5)
    paths = []
    for i in range(3):
        m = SAC("MultiInputPolicy", env, seed=i, learning_starts=10, buffer_size=100,
                policy_kwargs={"net_arch": [16]}, device="cpu")
        paths.append(tmp / f"sac{i}.zip")
        m.save(paths[-1])
        paths[-1].with_suffix(".json").write_text(json.dumps({"algo": "sac", "env_id": ENV}))
    ppo = tmp / "ppo.zip"
    PPO("MultiInputPolicy", env, n_steps=8, batch_size=8, device="cpu").save(ppo)
    ppo.with_suffix(".json").write_text(json.dumps({"algo": "ppo", "env_id": ENV}))
    env.close()
    return paths, ppo


def _obs(n=6, seed=0):
    venv = envs.CTRReachVecEnv(n)
    venv.seed(seed)
    return venv, venv.reset()


def _predict(path, venv, obs):
    from stable_baselines3 import SAC
    return SAC.load(path, env=venv, device="cpu").predict(obs, deterministic=True)[0]


def test_mean_is_the_average_of_the_members_predictions(members):
    paths, _ = members
    venv, obs = _obs()
    want = np.mean([_predict(p, venv, obs) for p in paths[:2]], 0)
    got = ensemble_policy([str(p) for p in paths[:2]], venv, "mean")(obs)
    assert got.shape == (venv.num_envs,) + venv.action_space.shape
    np.testing.assert_allclose(got, want, atol=1e-6)
    # one member alone is that member, in either mode
    for mode in ("mean", "qsel"):
        np.testing.assert_allclose(ensemble_policy([str(paths[0])], venv, mode)(obs),
                                   _predict(paths[0], venv, obs), atol=1e-6)


def test_qsel_takes_the_action_the_critics_rate_highest(members):
    from stable_baselines3 import SAC
    paths, _ = members
    venv, obs = _obs(8, seed=3)
    models = [SAC.load(p, env=venv, device="cpu") for p in paths]
    cands = [m.predict(obs, deterministic=True)[0] for m in models]
    o, _ = models[0].policy.obs_to_tensor(obs)
    with torch.no_grad():
        score = np.array([sum(torch.cat(m.critic(o, torch.as_tensor(a)), 1).mean(1).numpy()
                              for m in models) for a in cands])          # (K, B)
    want = np.stack(cands)[score.argmax(0), np.arange(venv.num_envs)]
    got = ensemble_policy([str(p) for p in paths], venv, "qsel")(obs)
    np.testing.assert_allclose(got, want, atol=1e-6)
    # the members disagree here, so the selection is not trivially one member's everywhere
    assert len(set(score.argmax(0).tolist())) > 1 or not np.allclose(cands[0], cands[1])


def test_switch_takes_the_far_members_action_beyond_the_distance(members):
    paths, _ = members
    venv, obs = _obs(16, seed=7)
    near, far = (_predict(p, venv, obs) for p in paths[:2])
    st = venv.state()
    d = np.linalg.norm(st.tip - st.goal, axis=-1)          # the env's own tip and goal [m]
    cut = float(np.median(d))                               # about half the robots each side
    got = ensemble_policy([str(p) for p in paths[:2]], venv, "switch", cut)(obs)
    beyond = d > cut
    assert 0 < beyond.sum() < len(d)
    np.testing.assert_allclose(got[beyond], far[beyond], atol=1e-6)
    np.testing.assert_allclose(got[~beyond], near[~beyond], atol=1e-6)


def test_bad_members_and_modes_are_refused_by_name(members, tmp_path):
    paths, ppo = members
    venv, _ = _obs(2)
    with pytest.raises(ValueError, match="mode"):
        ensemble_policy([str(paths[0])], venv, "median")
    with pytest.raises(ValueError, match="ppo.zip.*TQC or SAC"):
        ensemble_policy([str(paths[0]), str(ppo)], venv)
    with pytest.raises(ValueError, match="at least one"):
        ensemble_policy([], venv)
    two = [str(p) for p in paths[:2]]
    with pytest.raises(ValueError, match="exactly two"):
        ensemble_policy([str(p) for p in paths], venv, "switch", 0.01)
    for bad in (None, 0.0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="switch_distance"):
            ensemble_policy(two, venv, "switch", bad)
    with pytest.raises(ValueError, match="switch_distance applies"):
        ensemble_policy(two, venv, "mean", 0.01)
    other = envs.CTRReachVecEnv(2, observe_stiffness=True)
    with pytest.raises(ValueError, match="sac0.zip.*observation or action space"):
        ensemble_policy([str(paths[0])], other)
