"""Residual agents (training/residual.py): the plan in the observation (``plan_obs``), the
terminal observation it is bootstrapped from, the zero-initialized action head (an untrained
residual agent IS its base controller), and the refusal of HER with ``plan_obs``.
The older residual checks (zero action = base, the gate, reloading) are in
test_training_smoke.py."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest
import torch

import envs
from training import evaluate, train
from training.controllers import PlanThenServoController, PlanThenServoFeedbackController
from training.residual import (
    PLAN_OBS_PERIODS,
    ResidualVecEnv,
    actuation_from_observation,
    zero_residual_head,
)

TABLE = 256   # a small seeding table keeps the plans fast
SPEC = {"base": "pts", "plan_obs": True, "table_size": TABLE}
ENV = "torchpvs/CTRReachForce-v0"


pytestmark = pytest.mark.usefixtures("one_thread")


class _Pair(NamedTuple):
    """A residual-wrapped batch and a bare batch of the same robots, reset alike, with the
    bare batch's base controller: what a zero-residual comparison steps side by side."""

    wrapped: ResidualVecEnv
    obs: dict
    bare_env: envs.CTRReachVecEnv
    bare_obs: dict
    bare: PlanThenServoController
    n_plain: int          # entries of the bare observation (the plan features follow)


def _pair(spec, controller, seed: int, **env_kwargs) -> _Pair:
    """Two 2-robot batches built with ``env_kwargs``, one wrapped with ``spec``, both seeded
    ``seed`` and reset, and ``controller`` on the bare one."""
    wrapped = ResidualVecEnv(envs.CTRReachVecEnv(2, **env_kwargs), spec)
    bare_env = envs.CTRReachVecEnv(2, **env_kwargs)
    for e in (wrapped, bare_env):
        e.seed(seed)
    obs = wrapped.reset()
    bare_obs = bare_env.reset()
    bare = controller(bare_env, table_size=TABLE)
    n_plain = bare_env.observation_space["observation"].shape[0]
    return _Pair(wrapped, obs, bare_env, bare_obs, bare, n_plain)


def _features(target, st):
    """The plan features written out from their definition (module docstring)."""
    ref = PLAN_OBS_PERIODS * st.control_period * st.action_scale / st.damping
    return np.tanh((target - st.x) / ref)


def test_plan_obs_appends_the_plan_and_a_zero_residual_is_plan_then_servo():
    """With plan_obs the observation gains tanh((x* - x) / (10 h v_max)) for the plan x* the
    base made at reset, the observation space says so, and a zero residual drives the robots
    exactly as the bare controller does (same seeds, same goals)."""
    wrapped, obs, bare_env, bare_obs, bare, n_plain = _pair(
        SPEC, PlanThenServoController, 5, max_episode_steps=20)
    assert wrapped.observation_space["observation"].shape == (n_plain + 4,)
    assert wrapped.observation_space.contains({k: v[0] for k, v in obs.items()})
    np.testing.assert_array_equal(obs["observation"][:, :n_plain], bare_obs["observation"])
    a_bare = bare(bare_obs)                                     # plans for the same goals
    np.testing.assert_allclose(obs["observation"][:, n_plain:],
                               _features(bare.target, bare_env.state()), atol=1e-6)
    assert np.abs(obs["observation"][:, n_plain:]).max() > 1e-3   # the plan is not the start
    for _ in range(5):
        obs, *_ = wrapped.step(np.zeros((2, 4), np.float32))
        bare_obs, *_ = bare_env.step(a_bare)
        a_bare = bare(bare_obs)
    np.testing.assert_allclose(wrapped.venv.task.robots.x, bare_env.task.robots.x, atol=1e-12)


def test_the_terminal_observation_carries_the_plan_at_the_final_actuation():
    """The wrapped env resets a robot in the step that ends its episode, so the terminal
    observation's plan entries are rebuilt from the actuation that observation describes: they
    must equal those of an env run one step longer (no reset) at that step."""
    wrapped = ResidualVecEnv(envs.CTRReachVecEnv(2, max_episode_steps=3), SPEC)
    longer = envs.CTRReachVecEnv(2, max_episode_steps=4)
    for e in (wrapped, longer):
        e.seed(8)
    wrapped.reset()
    bare_obs = longer.reset()
    bare = PlanThenServoController(longer, table_size=TABLE)
    for _ in range(3):
        _, _, dones, infos = wrapped.step(np.zeros((2, 4), np.float32))
        bare_obs, *_ = longer.step(bare(bare_obs))
    assert dones.all()
    term = np.stack([i["terminal_observation"]["observation"] for i in infos])
    n_plain = longer.observation_space["observation"].shape[0]
    np.testing.assert_array_equal(term[:, :n_plain], bare_obs["observation"])
    np.testing.assert_allclose(term[:, n_plain:], _features(bare.target, longer.state()),
                               atol=1e-5)


def test_actuation_is_recovered_from_the_observation_on_the_nearest_turn():
    """sin/cos of the rotation and the normalized insertion give x back; a rotation beyond pi
    comes back on the turn nearest the hint (float32 observation: ~1e-7 relative)."""
    venv = envs.CTRReachVecEnv(1)
    venv.seed(0)
    venv.reset()
    x = np.array([[0.05, 0.12, 4.0, -7.5]])
    venv.task.robots.set_state(np.array([0]), x)
    ob = venv.task.observations()["observation"][0]
    got = actuation_from_observation(ob, venv.robot, x[0, 2:] + np.array([0.4, -0.4]))
    np.testing.assert_allclose(got, x[0], atol=2e-6)


@pytest.mark.parametrize("algo", ["sac", "tqc", "td3"])
def test_a_zeroed_head_acts_zero_so_the_untrained_agent_is_its_base(algo):
    """zero_residual_head makes the deterministic action exactly 0 on any observation."""
    venv = ResidualVecEnv(envs.CTRReachVecEnv(2, max_episode_steps=10), SPEC)
    hp = {k: v for k, v in train.load_hyperparams(algo, ENV).items()
          if k not in ("replay_buffer_class", "replay_buffer_kwargs")}
    hp.update(buffer_size=200, policy_kwargs="dict(net_arch=[16, 16])")
    model = train.make_model(algo, hp, venv, seed=0, log_dir=None)
    obs = venv.reset()
    assert np.abs(model.predict(obs, deterministic=True)[0]).max() > 0   # random head
    zero_residual_head(model)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], 0.0)
    if hasattr(model, "actor_target"):
        obs_t = model.policy.obs_to_tensor(obs)[0]
        with torch.no_grad():
            assert float(model.actor_target(obs_t).abs().max()) == 0.0


def test_a_zero_residual_on_pts_feedback_is_pts_feedback_and_sees_its_setpoint():
    """Base ``pts_feedback`` on a plant off its model (the robust task's ingredients): a zero
    residual drives the robots exactly as the bare feedback controller does, and the plan
    features follow its corrected setpoint (its ``reference``), not the first plan."""
    kw = dict(max_episode_steps=40, plant_scale=0.1, tip_force=0.3, tip_noise=1e-4)
    spec = {"base": "pts_feedback", "plan_obs": True, "table_size": TABLE}
    wrapped, obs, bare_env, bare_obs, bare, n_plain = _pair(
        spec, PlanThenServoFeedbackController, 11, **kw)
    corrected = False
    for _ in range(35):
        a_bare = bare(bare_obs)      # the base acts first: the agent sees the setpoint it uses
        np.testing.assert_allclose(obs["observation"][:, n_plain:],
                                   _features(bare.reference, bare_env.state()), atol=1e-6)
        corrected |= bool(np.any(bare.reference != bare.target))
        obs, *_ = wrapped.step(np.zeros((2, 4), np.float32))
        bare_obs, *_ = bare_env.step(a_bare)
    np.testing.assert_allclose(wrapped.venv.task.robots.x, bare_env.task.robots.x, atol=1e-12)
    assert corrected     # the outer loop moved a setpoint: the features followed it


def test_plan_obs_with_her_is_refused_by_name():
    hp = train.load_hyperparams("tqc", ENV)          # the HER entry
    hp["vec_env_wrapper"] = [{"training.residual.ResidualVecEnv": dict(SPEC)}]
    venv = train.make_venv(ENV, hp, n_envs=2)
    with pytest.raises(ValueError, match="plan_obs or penalty with HerReplayBuffer"):
        train.make_model("tqc", hp, venv, seed=0, log_dir=None)
    with pytest.raises(ValueError, match="plan_obs needs a base with a plan"):
        ResidualVecEnv(envs.CTRReachVecEnv(1), {"base": "osc", "plan_obs": True})
    with pytest.raises(ValueError, match="plan_obs must be true or false"):
        ResidualVecEnv(envs.CTRReachVecEnv(1), {"base": "pts", "plan_obs": "yes"})
    hp["vec_env_wrapper"] = [{"training.residual.ResidualVecEnv": {"base": "pts",
                                                                   "penalty": 0.5}}]
    with pytest.raises(ValueError, match="plan_obs or penalty with HerReplayBuffer"):
        train.make_model("tqc", hp, train.make_venv(ENV, hp, n_envs=2), seed=0, log_dir=None)
    with pytest.raises(ValueError, match="residual.penalty must be a finite number >= 0"):
        ResidualVecEnv(envs.CTRReachVecEnv(1), {"base": "pts", "penalty": -1.0})


def test_the_penalty_charges_the_residual_not_the_base():
    """penalty p: the training reward loses p * mean(a^2) of the agent's action a, and only
    that (same seeds and actions with p = 0: same robots, rewards differing by exactly it)."""
    a = np.array([[0.5, -1.0, 0.0, 0.2], [0.0, 0.0, 0.0, 0.0]], np.float32)
    out = {}
    for p in (0.0, 0.7):
        env = ResidualVecEnv(envs.CTRReachVecEnv(2, max_episode_steps=20),
                             {"base": "pts", "table_size": TABLE, "penalty": p})
        env.seed(4)
        env.reset()
        _, r, _, _ = env.step(a)
        out[p] = (r, env.venv.task.robots.x.copy())
    np.testing.assert_array_equal(out[0.0][1], out[0.7][1])
    np.testing.assert_allclose(out[0.0][0] - out[0.7][0],
                               0.7 * np.array([(0.25 + 1 + 0.04) / 4, 0.0]), atol=1e-7)


def test_a_plan_obs_run_reloads_with_its_plan_features(tmp_path):
    """A short plan_obs run (plain replay buffer) trains and records plan_obs; evaluation feeds
    the network the observation with the plan appended and adds the gated residual to the
    base: policy = clip(pts + scale * gate * network(obs + plan))."""
    hp = {k: v for k, v in train.load_hyperparams("sac", ENV).items()
          if k not in ("replay_buffer_class", "replay_buffer_kwargs", "callback")}
    hp.update(n_envs=2, learning_starts=30, buffer_size=500, batch_size=16,
              policy_kwargs="dict(net_arch=[16, 16])",
              env_kwargs={**hp["env_kwargs"], "max_episode_steps": 10},
              vec_env_wrapper=[{"training.residual.ResidualVecEnv": dict(SPEC)}])
    run = train.train("sac", ENV, hp, steps=60, seed=2, out=tmp_path, progress=False,
                      eval_freq=0)
    venv = envs.CTRReachVecEnv(2, max_episode_steps=10)
    venv.seed(0)
    obs = venv.reset()
    policy = evaluate.load_policy(str(run / "model.zip"), venv)
    from stable_baselines3 import SAC

    base = PlanThenServoController(venv, table_size=TABLE)
    a_base = base(obs)
    seen = {**obs, "observation": np.concatenate(
        [obs["observation"], _features(base.target, venv.state()).astype(np.float32)], -1)}
    net = SAC.load(run / "model.zip", device="cpu").predict(seen, deterministic=True)[0]
    assert np.abs(net).max() > 0            # 60 steps moved the zeroed head
    st = venv.state()
    gate = np.minimum(1.0, np.linalg.norm(st.goal - st.tip, axis=-1, keepdims=True) / 5e-3)
    np.testing.assert_allclose(policy(obs), np.clip(a_base + 0.3 * gate * net, -1, 1),
                               atol=1e-6)
