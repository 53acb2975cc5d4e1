"""Net2WiderNet widening of SB3 SAC/TQC policies (training/widen.py): the wider networks
compute the source's function exactly at zero noise (Chen et al. 2016, the function-preserving
transform), the copies drift apart with noise, and mismatched networks are refused by name."""

from __future__ import annotations

import json

import pytest
import torch

import envs  # noqa: F401  (registers the env ids)
from training import train
from training.widen import widen_state_dict

ZOO_ENV = "torchpvs/CTRReachForce-v0"


def _policies(src_arch, dst_arch, algo="tqc", more_inputs=False):
    """Two policies of the force env's spaces, with random weights, and observations of the
    target's space (``more_inputs``: the target observes the rotation stiffness too)."""
    import gymnasium as gym
    if algo == "tqc":
        from sb3_contrib.tqc.policies import MultiInputPolicy
    else:
        from stable_baselines3.sac.policies import MultiInputPolicy
    env = gym.make(ZOO_ENV, max_episode_steps=5)
    env_dst = gym.make(ZOO_ENV, max_episode_steps=5, observe_stiffness=more_inputs)
    torch.manual_seed(0)
    make = lambda e, arch: MultiInputPolicy(e.observation_space, e.action_space,  # noqa: E731
                                            lambda _: 1e-3, net_arch=arch)
    src, dst = make(env, src_arch), make(env_dst, dst_arch)
    env_dst.observation_space.seed(0)
    obs = {k: torch.stack([torch.as_tensor(sp.sample(), dtype=torch.float32) for _ in range(32)])
           for k, sp in env_dst.observation_space.spaces.items()}
    env.close()
    env_dst.close()
    return src, dst, obs


def _outputs(policy, obs):
    """Deterministic actions, the action distribution's log std and every critic's output."""
    def flat(q):  # SAC: a tuple of (B, 1) per critic; TQC: (B, critics, quantiles)
        return torch.cat([c.flatten(1) for c in q], 1) if isinstance(q, tuple) else q.flatten(1)
    with torch.no_grad():
        mean, log_std, _ = policy.actor.get_action_dist_params(obs)
        act = policy.actor(obs, deterministic=True)
        return mean, log_std, flat(policy.critic(obs, act)), flat(policy.critic_target(obs, act))


@pytest.mark.parametrize("algo", ["tqc", "sac"])
def test_widening_keeps_the_function_exactly_without_noise(algo):
    src, dst, obs = _policies([16, 12], [40, 12 + 7], algo)
    # a target that differs from its critic (as after Polyak averaging): its own mapping must
    # match the critic's so the pair stays consistent
    with torch.no_grad():
        for p in src.critic_target.parameters():
            p.add_(0.05 * torch.randn_like(p))
    wide = widen_state_dict(src.state_dict(), dst.state_dict(), noise=0.0,
                            generator=torch.Generator().manual_seed(1))
    dst.load_state_dict(wide)
    assert dst.actor.latent_pi[0].weight.shape == (40, src.actor.latent_pi[0].weight.shape[1])
    for a, b in zip(_outputs(src, obs), _outputs(dst, obs), strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dst_arch", [[16, 12], [40, 19]])
def test_an_appended_observation_entry_starts_at_zero_weight(dst_arch):
    """A target observing one more entry (appended last, ``observe_stiffness``) computes the
    source's actions and Q values on the observation without it, whatever the new entry
    reads: its weights are zero in the actor and between features and action in the critics
    (a column appended after the action would read the action as the new feature)."""
    src, dst, obs = _policies([16, 12], dst_arch, more_inputs=True)
    n = src.actor.latent_pi[0].weight.shape[1]
    assert dst.actor.latent_pi[0].weight.shape[1] == n + 1
    dst.load_state_dict(widen_state_dict(src.state_dict(), dst.state_dict(), noise=0.0))
    short = {**obs, "observation": obs["observation"][:, :-1]}
    for value in (0.0, -1.0, 5.0):
        obs["observation"][:, -1] = value
        for a, b in zip(_outputs(src, short), _outputs(dst, obs), strict=True):
            torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    # the new column sits at the actor's old input count in every first layer
    sd = dst.state_dict()
    for k in ("actor.latent_pi.0.weight", "critic.qf0.0.weight", "critic_target.qf1.0.weight"):
        assert torch.count_nonzero(sd[k][:, n]) == 0, k
        assert torch.count_nonzero(sd[k][:, n - 1]) > 0, k
    with pytest.raises(ValueError, match="fewer inputs"):
        widen_state_dict(dst.state_dict(), src.state_dict())


def test_a_target_critic_keeps_its_critics_unit_mapping():
    """Polyak averaging mixes critic and target unit by unit: a target equal to its critic
    stays equal after widening, noise included (independent copies would pair different units
    and differently perturbed copies)."""
    src, dst, _ = _policies([16, 16], [48, 40])
    src.critic_target.load_state_dict(src.critic.state_dict())
    for noise in (0.0, 0.01):       # the copies' noise is the critic's too
        wide = widen_state_dict(src.state_dict(), dst.state_dict(), noise=noise,
                                generator=torch.Generator().manual_seed(3))
        for k, v in wide.items():
            if k.startswith("critic."):
                assert torch.equal(v, wide["critic_target." + k[len("critic."):]]), (noise, k)


def test_noise_separates_the_copies_but_stays_close_to_the_function():
    src, dst, obs = _policies([16, 16], [32, 32])
    wide = widen_state_dict(src.state_dict(), dst.state_dict(), noise=0.01,
                            generator=torch.Generator().manual_seed(1))
    W = wide["actor.latent_pi.0.weight"]
    # every copy differs from the unit it was copied from
    d = torch.cdist(W[16:], W[:16]).min(1).values
    assert (d > 0).all()
    dst.load_state_dict(wide)
    (m0, *_), (m1, *_) = _outputs(src, obs), _outputs(dst, obs)
    rel = float((m1 - m0).norm() / m0.norm())
    assert 0 < rel < 0.05


def test_mismatched_networks_are_refused_by_name():
    src, dst, _ = _policies([16, 16], [8, 32])
    with pytest.raises(ValueError, match=r"actor\.latent_pi\.0.*narrower"):
        widen_state_dict(src.state_dict(), dst.state_dict())
    src, dst, _ = _policies([16, 16], [32, 32, 32])
    with pytest.raises(ValueError, match="different layers"):
        widen_state_dict(src.state_dict(), dst.state_dict())
    src, dst, _ = _policies([16], [32])
    with pytest.raises(ValueError, match="noise"):
        widen_state_dict(src.state_dict(), dst.state_dict(), noise=-1.0)


def _small_sac_run(tmp_path):
    """``(hyperparams, run folder)`` of a 100-step SAC run of [16, 16] networks (with updates,
    so its optimizers hold Adam moments) to start widened runs from."""
    hp = train.load_hyperparams("sac", ZOO_ENV)
    hp = {**hp, "n_envs": 2, "learning_starts": 50, "buffer_size": 1000, "batch_size": 32,
          "env_kwargs": {**hp.get("env_kwargs", {}), "max_episode_steps": 20},
          "policy_kwargs": "dict(net_arch=[16, 16])"}
    return hp, train.train("sac", ZOO_ENV, hp, steps=100, seed=1, out=tmp_path / "a",
                           progress=False, eval_freq=0, eval_episodes=0)


def test_a_run_started_widened_keeps_the_source_agent_and_its_entropy(tmp_path):
    """train(..., widen=True): the run's wider actor acts as the saved one did (before any
    update) and carries its entropy coefficient; --widen without --init-from is refused."""
    from stable_baselines3.common.save_util import load_from_zip_file
    hp, first = _small_sac_run(tmp_path)
    wide_hp = {**hp, "policy_kwargs": "dict(net_arch=[32, 24])", "learning_starts": 10**6}
    run = train.train("sac", ZOO_ENV, wide_hp, steps=20, seed=2, out=tmp_path / "b",
                      progress=False, eval_freq=0, eval_episodes=0,
                      init_from=first / "model.zip", widen=True)
    (_, pa, ta), (_, pb, tb) = (load_from_zip_file(r / "model.zip", device="cpu")
                                for r in (first, run))
    assert pb["policy"]["actor.latent_pi.0.weight"].shape[0] == 32
    src, dst, obs = _policies([16, 16], [32, 24], "sac")
    src.load_state_dict(pa["policy"])
    dst.load_state_dict(pb["policy"])
    (m0, *_), (m1, *_) = _outputs(src, obs), _outputs(dst, obs)
    assert float((m1 - m0).norm() / m0.norm()) < 0.05
    ea, eb = ta["log_ent_coef"].detach(), tb["log_ent_coef"].detach()
    assert float(ea) != 0.0 and torch.equal(ea, eb)
    assert json.loads((run / "model.json").read_text())["widened"] is True
    with pytest.raises(SystemExit):
        train.main(["--algo", "sac", "--env", ZOO_ENV, "--widen"])


def test_a_run_with_an_appended_entry_keeps_the_agent_and_its_adam_moments(tmp_path):
    """train(..., widen=True) on an env observing one more entry: the run starts from the
    saved agent's function and keeps its optimizers' Adam moments (zero for the new weights),
    so its first updates are a plain fine-tune's."""
    from stable_baselines3.common.save_util import load_from_zip_file
    hp, first = _small_sac_run(tmp_path)
    more = {**hp, "learning_starts": 10**6,
            "env_kwargs": {**hp["env_kwargs"], "observe_stiffness": True}}
    run = train.train("sac", ZOO_ENV, more, steps=20, seed=2, out=tmp_path / "b",
                      progress=False, eval_freq=0, eval_episodes=0,
                      init_from=first / "model.zip", widen=True)
    (_, pa, _), (_, pb, _) = (load_from_zip_file(r / "model.zip", device="cpu")
                              for r in (first, run))
    n = pa["policy"]["actor.latent_pi.0.weight"].shape[1]
    for name, first_layer in (("actor.optimizer", "actor.latent_pi.0.weight"),
                              ("critic.optimizer", "critic.qf0.0.weight")):
        a, b = pa[name]["state"], pb[name]["state"]
        assert a and set(a) == set(b)
        for i in a:
            for key in ("exp_avg", "exp_avg_sq"):
                ma, mb = a[i][key], b[i][key]
                if ma.shape == mb.shape:
                    assert torch.equal(ma, mb), (name, i, key)
                else:   # the first layer: one zero column at the old feature count
                    assert mb.shape == (ma.shape[0], ma.shape[1] + 1)
                    assert torch.equal(mb[:, n], torch.zeros(ma.shape[0]))
                    assert torch.equal(torch.cat([mb[:, :n], mb[:, n + 1:]], 1), ma)
        assert pb["policy"][first_layer].shape[1] == pa["policy"][first_layer].shape[1] + 1
    src, dst, obs = _policies([16, 16], [16, 16], "sac", more_inputs=True)
    src.load_state_dict(pa["policy"])
    dst.load_state_dict(pb["policy"])
    short = {**obs, "observation": obs["observation"][:, :-1]}
    torch.testing.assert_close(_outputs(dst, obs)[0], _outputs(src, short)[0])
