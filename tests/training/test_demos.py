"""Demonstrations (training/demos.py) and behaviour cloning from them
(training.callbacks.DemoCloning)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from training import demos, train
from training.callbacks import DemoCloning
from training.evaluate import TOLERANCES

ZOO_ENV = "torchpvs/CTRReachForce-v0"


def test_demonstrations_replay_to_the_recorded_observations_and_reach_the_goal():
    """Each kept episode's recorded actions, replayed open loop from the same seed in a fresh
    env of one robot, give back the recorded observations step by step (so every action is
    paired with the observation it answered) and end within 1 mm of the goal."""
    venv = envs.CTRReachVecEnv(2)
    data = demos.collect("pts", venv, episodes=2, seed=12345)
    kept = np.unique(data["episode"])
    assert int(data["kept"]) == len(kept) >= 1 and int(data["episodes"]) == 2
    assert len(data["action"]) == venv.max_episode_steps * len(kept)
    for k in kept:
        rows = np.flatnonzero(data["episode"] == k)
        one = envs.CTRReachVecEnv(1)
        one.seed(12345 + int(k))
        obs = one.reset()
        for r in rows:
            for key in demos.KEYS:
                np.testing.assert_allclose(obs[key][0], data[key][r], rtol=0, atol=1e-6)
            obs, _, _, infos = one.step(data["action"][r][None])
        assert infos[0]["distance"] <= TOLERANCES[0]
    with pytest.raises(ValueError, match="controller must be one of"):
        demos.collect("nobody", venv, episodes=1, seed=0)


def _model_and_demos(tmp_path, action: float = 0.5):
    """A tiny TQC model and a demonstration file of its env's observations, every action
    ``action``."""
    from stable_baselines3.common.logger import configure

    hp = train.load_hyperparams("tqc", ZOO_ENV)
    hp = {**hp, "n_envs": 2, "learning_starts": 10**6, "buffer_size": 1000,
          "env_kwargs": {**hp["env_kwargs"], "max_episode_steps": 20}}
    venv = train.make_venv(ZOO_ENV, hp)
    model = train.make_model("tqc", hp, venv, seed=0, log_dir=None)
    model.set_logger(configure(None, []))
    obs = venv.reset()
    n = 64
    data = {k: np.repeat(obs[k], n // 2, axis=0) for k in demos.KEYS}
    data["action"] = np.full((n, venv.action_space.shape[0]), action, dtype=np.float32)
    path = tmp_path / "demos.npz"
    np.savez(path, **data)
    return model, path, data


def _cloning_error(model, data) -> float:
    with torch.no_grad():
        obs = {k: torch.as_tensor(data[k]) for k in demos.KEYS}
        a = model.actor(obs, deterministic=True).numpy()
    return float(((a - data["action"]) ** 2).sum(-1).mean())


def _run(cb, model, updates: int) -> None:
    cb.init_callback(model)
    cb.on_training_start({}, {})
    model._n_updates += updates   # as if the algorithm had taken these gradient steps
    cb.on_rollout_end()


def test_cloning_moves_the_policy_to_the_demonstrated_actions(tmp_path):
    model, path, data = _model_and_demos(tmp_path)
    before = _cloning_error(model, data)
    cb = DemoCloning(str(path), learning_rate=1e-2, batch_size=32, q_filter=False)
    _run(cb, model, updates=40)
    assert cb.steps == 40
    assert _cloning_error(model, data) < 0.1 * before


def test_the_q_filter_refuses_actions_the_critic_does_not_prefer(tmp_path):
    """A critic that rates every action alike passes no pair (Q(s, a) > Q(s, pi(s)) is
    strict): the actor's weights do not move. One that rates the demonstrated action highest
    passes every pair."""
    model, path, data = _model_and_demos(tmp_path)
    demo = torch.as_tensor(data["action"][0])

    class Critic(torch.nn.Module):
        def __init__(self, prefer_demo: bool):
            super().__init__()
            self.prefer_demo = prefer_demo

        def forward(self, obs, action):
            q = -((action - demo) ** 2).sum(-1) if self.prefer_demo else 0.0 * action[:, 0]
            return q[:, None, None].expand(-1, 2, 5)

    weights = [p.detach().clone() for p in model.actor.parameters()]
    model.critic = Critic(prefer_demo=False)
    cb = DemoCloning(str(path), learning_rate=1e-2, batch_size=32)
    _run(cb, model, updates=5)
    assert all(torch.equal(a, b) for a, b in zip(weights, model.actor.parameters(),
                                                  strict=True))
    model.critic = Critic(prefer_demo=True)
    before = _cloning_error(model, data)
    cb = DemoCloning(str(path), learning_rate=1e-2, batch_size=32)
    _run(cb, model, updates=20)
    assert _cloning_error(model, data) < 0.5 * before


def test_demonstrations_of_another_env_are_refused_by_field(tmp_path):
    model, path, data = _model_and_demos(tmp_path)
    bad = dict(data, observation=data["observation"][:, :-1])
    np.savez(path, **bad)
    cb = DemoCloning(str(path))
    cb.init_callback(model)
    with pytest.raises(ValueError, match="'observation' has shape"):
        cb.on_training_start({}, {})
    with pytest.raises(ValueError, match="learning_rate"):
        DemoCloning(str(path), learning_rate=0)


def test_cloning_runs_from_a_hyperparameter_entry(tmp_path):
    """The callback as users name it (``callback:`` list of an entry, dotted path), on SAC
    (its critics answer a tuple of values): the run logs its cloning steps."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    hp = train.load_hyperparams("sac", ZOO_ENV)
    hp = {**hp, "n_envs": 2, "env_kwargs": {**hp.get("env_kwargs", {}), "max_episode_steps": 20},
          "learning_starts": 50, "buffer_size": 1000, "batch_size": 32}
    venv = train.make_venv(ZOO_ENV, hp)
    obs = venv.reset()
    path = tmp_path / "demos.npz"
    np.savez(path, **{k: np.repeat(obs[k], 8, axis=0) for k in demos.KEYS},
             action=np.zeros((16, venv.action_space.shape[0]), dtype=np.float32))
    hp["callback"] = [{"training.callbacks.DemoCloning": {"path": str(path),
                                                          "batch_size": 8}}]
    run = train.train("sac", ZOO_ENV, hp, steps=120, seed=3, out=tmp_path / "run",
                      progress=False, eval_freq=0, eval_episodes=0)
    events = EventAccumulator(str(next((run / "tb").rglob("events.out.tfevents.*")).parent))
    events.Reload()
    accepted = [e.value for e in events.Scalars("demo/accepted")]
    assert accepted and all(0.0 <= a <= 1.0 for a in accepted)


def test_min_distance_keeps_only_the_pairs_far_from_their_goal(tmp_path):
    model, path, data = _model_and_demos(tmp_path)
    d = np.linalg.norm(data["achieved_goal"][:, :3] - data["desired_goal"][:, :3], axis=-1)
    cut = float(np.median(d))
    cb = DemoCloning(str(path), min_distance=cut)
    cb.init_callback(model)
    cb.on_training_start({}, {})
    assert cb.n == int((d > cut).sum()) and 0 < cb.n < len(d)
    kept = cb.obs["desired_goal"][:, :3].numpy() - cb.obs["achieved_goal"][:, :3].numpy()
    assert (np.linalg.norm(kept, axis=-1) > cut).all()
    cb = DemoCloning(str(path), min_distance=float(d.max()) + 1.0)
    cb.init_callback(model)
    with pytest.raises(ValueError, match="min_distance"):
        cb.on_training_start({}, {})


@pytest.mark.parametrize("bad", [-0.001, True, "1mm"])
def test_min_distance_must_be_a_distance(tmp_path, bad):
    with pytest.raises(ValueError, match="min_distance"):
        DemoCloning(str(tmp_path / "demos.npz"), min_distance=bad)
