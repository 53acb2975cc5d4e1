"""The env solvers (envs/plant.py ``SOLVERS``): the compiled warm solve the environments step
on against ``torchpvs.solve``, which they used before it and still use wherever it does not
apply.

Reference: ``torchpvs.solve`` at the environments' fixed discretization (the ``"torch"``
solver, every equilibrium through the full driver and ``torchpvs.jacobians``). The compiled
path runs the same Newton iteration (identical iterations and verdicts: tips and coordinates
equal to 1e-12), the same closed-form forces (1e-9 N) and the same Schur-complement stiffness
(to the rounding of its rows, 1e-9 of its largest entry), so an episode is the same physics.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import envs
from envs.plant import Plants, PlantVariation
from envs.robots import ROBOTS
from torchpvs import compiled

pytestmark = [pytest.mark.usefixtures("one_thread"),
              pytest.mark.skipif(not compiled.available(), reason="numba not importable")]


def _states(robot, rng, k):
    """``k`` feasible actuations and nearby ones (1 mm, 2 deg), and the Fig. 3 outer tube's
    straight-to-curved kink at the orifice as one more row pair."""
    N = robot.n_tubes
    x0 = np.asarray(robot.sample_actuation(rng, k), dtype=np.float64)
    x1 = x0 + np.concatenate([rng.normal(0, 1e-3, (k, N)), rng.normal(0, 0.035, (k, N))], -1)
    x1[:, :N] = robot.project(x1[:, :N])[0]
    if N == 2:   # at the kink D_1 = Ls_1 (one-sided forces and stiffness)
        kink = x0[:1].copy()
        kink[0, 0] = robot.scene.tubes[0].straight_length
        kink[0, :N] = robot.project(kink[:, :N])[0]
        x0, x1 = np.concatenate([x0, kink]), np.concatenate([x1, kink])
    return x0, x1


@pytest.mark.parametrize("name", sorted(ROBOTS))
def test_compiled_warm_solves_equal_the_torch_solver(name):
    robot = ROBOTS[name]()
    torch_p = Plants(robot, PlantVariation(), 8, solver="torch")
    fast = Plants(robot, PlantVariation(), 8, solver="compiled")
    assert torch_p.tracker is None and fast.tracker is not None
    x0, x1 = _states(robot, np.random.default_rng(11), 8)
    rows = np.arange(len(x0))
    q0 = torch_p.solve(x0, rows).q.numpy()
    a = torch_p.warm(x1, rows, q0, stiffness=True)
    b = fast.warm(x1, rows, q0, stiffness=True)
    assert a.ok.all()
    np.testing.assert_array_equal(b.ok, a.ok)
    np.testing.assert_allclose(b.tip, a.tip, atol=1e-12, rtol=0)
    np.testing.assert_allclose(b.q, a.q, atol=1e-12, rtol=0)
    np.testing.assert_allclose(b.g, a.g, atol=1e-9, rtol=0)
    np.testing.assert_allclose(b.energy, a.energy, rtol=1e-12, atol=0)
    np.testing.assert_allclose(b.twist, a.twist, atol=1e-12, rtol=0)
    np.testing.assert_allclose(b.margin, a.margin, atol=1e-12, rtol=0)
    Ka, Kb = a.stiffness(rows), b.stiffness(rows)
    Ka = 0.5 * (Ka + np.swapaxes(Ka, -1, -2))
    # each entry against its largest value over the batch (a row with every curved part in
    # the guide has K ~ 1e-16: round-off only)
    scale = np.abs(Ka).max(0, keepdims=True) + 1e-12
    smooth = np.arange(8)
    np.testing.assert_allclose(Kb[smooth] / scale, Ka[smooth] / scale, atol=1e-9, rtol=0)
    # at a kink both take the retraction side KINK_DELTA (1e-7 m) away, each entry O(delta)
    # off (torchpvs.jacobians; the tracker's own test: 1e-4)
    np.testing.assert_allclose(Kb / scale, Ka / scale, atol=1e-4, rtol=0)
    # a subset of rows, warm from the same coordinates: the same rows of the same results
    sub = np.array([2, 0])
    c = fast.warm(x1[sub], sub, q0[sub], stiffness=True)
    np.testing.assert_array_equal(c.q, b.q[sub])
    np.testing.assert_array_equal(c.g, b.g[sub])


def test_force_episodes_agree_between_solvers():
    """The same seeded force-env steps on both solvers: the same observations (float32
    round-off) and rewards over the first steps, and the compiled one was used."""
    out = {}
    for solver in ("torch", "auto"):
        venv = envs.CTRReachVecEnv(8, control="force", compensation=True,
                                   observe_stiffness=True, solver=solver)
        assert (venv.task.plants.tracker is None) == (solver == "torch")
        venv.seed(3)
        obs = [venv.reset()["observation"]]
        rng = np.random.default_rng(0)
        rewards = []
        for _ in range(5):
            o, r, _, _ = venv.step(rng.uniform(-1, 1, (8, 4)).astype(np.float32))
            obs.append(o["observation"])
            rewards.append(r)
        out[solver] = np.array(obs), np.array(rewards)
    np.testing.assert_allclose(out["auto"][0], out["torch"][0], atol=1e-5, rtol=0)
    np.testing.assert_allclose(out["auto"][1], out["torch"][1], atol=1e-5, rtol=0)


def test_joint_env_steps_on_the_compiled_solver_too():
    a = envs.CTRReachVecEnv(4, control="joint")
    b = envs.CTRReachVecEnv(4, control="joint", solver="torch")
    for v in (a, b):
        v.seed(1)
        v.reset()
    act = np.full((4, 4), 0.5, dtype=np.float32)
    oa, ra, _, _ = a.step(act)
    ob, rb, _, _ = b.step(act)
    assert a.task.plants.tracker is not None
    np.testing.assert_allclose(oa["observation"], ob["observation"], atol=1e-6, rtol=0)
    np.testing.assert_array_equal(ra, rb)


def test_solver_choice_is_checked_and_applies_where_it_can():
    robot = ROBOTS["fig3_two_tube"]()
    with pytest.raises(ValueError, match="solver must be one of"):
        envs.CTRReachVecEnv(2, solver="fast")
    with pytest.raises(ValueError, match="solver must be one of"):
        Plants(robot, PlantVariation(), 2, solver="numba")
    # a plant off the nominal robot (per-robot tubes, tip loads): torchpvs.solve only
    with pytest.raises(ValueError, match="solver='compiled' needs the nominal robot"):
        Plants(robot, PlantVariation(scale=0.1), 2, solver="compiled")
    robust = envs.CTRReachVecEnv(2, plant_scale=0.1, tip_force=0.5)
    assert robust.task.plants.tracker is None
    with pytest.raises(ValueError, match="stiffness was not computed"):
        p = Plants(robot, PlantVariation(), 1, solver="compiled")
        x = np.asarray(robot.sample_actuation(np.random.default_rng(0), 1), dtype=np.float64)
        q0 = p.solve(x, np.arange(1)).q.numpy()
        p.warm(x, np.arange(1), q0).stiffness(np.arange(1))
    assert torch.get_num_threads() == 1
