"""Plants that differ from the nominal robot (envs/plant.py, the robust reaching task).

References: the physics of a perturbed robot is the equilibrium of its own scene, solved alone
with ``torchpvs.solve`` (scaled tubes and the tip force); the noise is what the docstring
says (zero mean, the given standard deviation per axis)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs
import torchpvs
from envs.plant import PlantVariation
from torchpvs.testing import scaled_tubes

ROBUST = "torchpvs/CTRReachForceRobust-v0"


pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_robust_id_fixes_its_task():
    env = gym.make(ROBUST)
    cfg = env.unwrapped.config
    assert env.spec.max_episode_steps == 150
    assert (cfg.control, cfg.compensation, cfg.plant_scale, cfg.tip_force, cfg.tip_noise) == (
        "force", True, 0.1, 0.5, 1e-4)
    assert envs.env_kwargs(ROBUST)["max_episode_steps"] == 150
    vec = gym.make_vec(ROBUST, num_envs=2, vectorization_mode="vector_entry_point")
    assert vec.unwrapped.max_episode_steps == 150 and vec.unwrapped.config == cfg


def test_each_robot_moves_as_its_own_plant():
    """At rest after a reset, every robot's tip, carriage loads and stiffness margin are those
    of its own scaled scene under its own tip force, solved alone."""
    venv = envs.CTRReachVecEnv(3, plant_scale=0.1, tip_force=0.5, tip_noise=0.0)
    venv.seed(4)
    venv.reset()
    st = venv.state()
    assert not np.allclose(st.plant_factors[0], st.plant_factors[1])
    assert (np.abs(st.plant_factors - 1) <= 0.1).all()
    assert (np.linalg.norm(st.plant_tip_force, axis=-1) <= 0.5).all()
    N = venv.robot.n_tubes
    for i in range(3):
        own = scaled_tubes(venv.robot.scene, *st.plant_factors[i])
        eq = torchpvs.solve(own, insertion=st.x[i, :N], rotation=st.x[i, N:],
                            tip_force=st.plant_tip_force[i],
                            options=torchpvs.SolverOptions(order=2, n_magnus=8))
        np.testing.assert_allclose(st.true_tip[i], eq.tip_position[0].numpy(), atol=1e-12)
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1)[0].numpy()
        np.testing.assert_allclose(st.g[i], g, rtol=1e-9, atol=1e-12)
    # and it is not the nominal robot
    nominal = torchpvs.solve(venv.robot.scene, insertion=st.x[:, :N], rotation=st.x[:, N:],
                             options=torchpvs.SolverOptions(order=2, n_magnus=8))
    assert np.linalg.norm(nominal.tip_position.numpy() - st.true_tip, axis=-1).max() > 1e-3


def test_measured_tip_noise_and_success_on_the_true_tip():
    venv = envs.CTRReachVecEnv(8, tip_noise=1e-4)
    venv.seed(0)
    obs = venv.reset()
    errs = []
    for _ in range(6):
        obs, reward, _, infos = venv.step(np.zeros((8, 4), np.float32))
        st = venv.state()
        errs.append(st.tip - st.true_tip)
        np.testing.assert_array_equal(obs["achieved_goal"][:, :3], st.tip.astype(np.float32))
        true_d = np.linalg.norm(st.true_tip - st.goal, axis=-1)
        np.testing.assert_allclose([i["distance"] for i in infos], true_d, rtol=1e-12)
        # the reward is compute_reward of what the agent sees (HER recomputes exactly that)
        np.testing.assert_array_equal(
            reward, venv.env_method("compute_reward", obs["achieved_goal"],
                                    obs["desired_goal"], {}, indices=[0])[0])
    e = np.concatenate(errs)
    assert abs(e.mean()) < 3e-5 and 0.7e-4 < e.std() < 1.3e-4


def test_seeded_plants_repeat_and_nominal_default_is_unchanged():
    a, b = (envs.CTRReachVecEnv(2, plant_scale=0.1, tip_force=0.5) for _ in range(2))
    for v in (a, b):
        v.seed(11)
        v.reset()
    np.testing.assert_array_equal(a.state().plant_factors, b.state().plant_factors)
    np.testing.assert_array_equal(a.state().true_tip, b.state().true_tip)
    plain = envs.CTRReachVecEnv(2)
    plain.seed(11)
    plain.reset()
    st = plain.state()
    assert (st.plant_factors == 1).all() and (st.plant_tip_force == 0).all()
    np.testing.assert_array_equal(st.tip, st.true_tip)


def test_robust_env_passes_check_env():
    from stable_baselines3.common.env_checker import check_env
    check_env(gym.make(ROBUST).unwrapped, skip_render_check=True)


@pytest.mark.parametrize("kw, match", [
    (dict(plant_scale=1.0), "plant scale must be below 1"),
    (dict(plant_scale=-0.1), "plant scale must be a finite number >= 0"),
    (dict(tip_force=float("nan")), "plant tip_force must be"),
    (dict(tip_noise="1e-4"), "plant tip_noise must be"),
])
def test_bad_plant_options_name_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        envs.CTRReachEnv(**kw)
    if "plant_scale" in kw and kw["plant_scale"] == 1.0:
        with pytest.raises(ValueError, match=match):
            PlantVariation(scale=1.0)
