"""Training and evaluation pipeline: a short SAC+HER run end to end, config validation, metric
definitions on hand-made episodes, and the model-based baseline on an easy goal."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

import envs
from training import evaluate, train
from training.controllers import OperationalSpaceController, tip_jacobian
from training.evaluate import rollout, summarize

CONFIGS = sorted((train.Path(__file__).resolve().parents[2] / "training" / "configs")
                 .glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_shipped_configs_are_valid(path):
    cfg = train.load_config(path)
    assert cfg["env_id"] in envs.ENV_IDS


def test_bad_config_names_the_key(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump({"env_id": "torchpvs/CTRReachForce-v0", "algo": "dqn"}))
    with pytest.raises(ValueError, match="algo"):
        train.load_config(p)
    p.write_text(yaml.safe_dump({"env_id": "x", "algo": "sac", "oops": 1}))
    with pytest.raises(ValueError, match="oops"):
        train.load_config(p)


def test_train_200_steps_and_evaluate(tmp_path):
    """~200 SAC+HER steps on 2 robots, the run folder's records, then the evaluation script on
    a few goals with the saved model and the baselines."""
    cfg = train.load_config(CONFIGS[[c.stem for c in CONFIGS].index("sac_her_force")])
    cfg = {**cfg, "n_envs": 2, "eval": {"freq": 100, "episodes": 2}, "max_episode_steps": 20,
           "hyperparams": {**cfg["hyperparams"], "learning_starts": 50, "buffer_size": 1000,
                           "batch_size": 32}}
    run = train.train(cfg, steps=200, seed=1, out=tmp_path, name="smoke", progress=False,
                      argv=["--config", "x.yaml"])
    for f in ("config.yaml", "args.json", "command.txt", "model.zip", "model.json",
              "evaluations.npz", "monitor.csv", "train.log"):
        assert (run / f).exists(), f
    meta = json.loads((run / "model.json").read_text())
    assert meta["algo"] == "sac" and meta["steps"] >= 200
    out = tmp_path / "eval"
    code = evaluate.main(["--policy", f"agent={run / 'model.zip'}", "--baselines", "zero",
                          "--episodes", "2", "--batch", "2", "--out", str(out),
                          "--run-dir", str(run)])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"agent", "zero"}
    for m in metrics.values():
        assert 0 <= m["success@1mm"] <= m["success@2mm"] <= m["success@5mm"] <= 1
        assert m["episodes"] == 2
    assert (out / "error_histogram.png").exists() and (out / "learning_curve.png").exists()


class _Scripted:
    """A policy that is not a policy: it teleports nothing, it just replays fixed actions."""

    def __init__(self, actions):
        self.actions, self.t = actions, 0

    def __call__(self, obs):
        a = self.actions[min(self.t, len(self.actions) - 1)]
        self.t += 1
        return a


def test_metrics_on_a_known_rollout():
    """Zero actions on a robot started at rest with tau = 0 ... the final error equals the
    distance the env reports, effort is 0 and nothing saturates (definitions of summarize)."""
    venv = envs.CTRReachVecEnv(2, max_episode_steps=5)
    res = rollout(_Scripted([np.zeros((2, 4), np.float32)]), venv, 2, seed=3, progress=False)
    s = summarize(res)
    assert s["effort_median_N2s"] == 0 and s["saturation_fraction"] == 0
    assert s["episodes"] == 2
    np.testing.assert_allclose(np.median(res["final_error"]) * 1e3, s["median_error_mm"])
    res = rollout(_Scripted([np.ones((2, 4), np.float32)]), venv, 2, seed=3, progress=False)
    assert summarize(res)["saturation_fraction"] == 1.0


def test_tip_jacobian_matches_finite_differences():
    robot = envs.fig3_two_tube()
    x = np.array([[0.05, 0.13, 0.2, -0.7]])
    tip, J = tip_jacobian(robot, x)
    e = 1e-6
    for c in range(4):
        dx = np.zeros_like(x)
        dx[0, c] = e
        tp, _ = tip_jacobian(robot, x + dx)
        tm, _ = tip_jacobian(robot, x - dx)
        np.testing.assert_allclose(J[0, :, c], (tp - tm)[0] / (2 * e), rtol=1e-4, atol=1e-8)


def test_operational_space_controller_reaches_a_near_goal():
    """Goal = the tip of a nearby stable configuration (5 mm of insertion, 10 deg away): the
    model-based controller must bring the tip within 1 mm in 40 steps."""
    venv = envs.CTRReachVecEnv(1, max_episode_steps=40)
    venv.seed(0)
    venv.reset()
    x0 = np.array([[0.06, 0.15, 0.0, 0.5]])
    venv.task.robots.set_state(np.array([0]), x0)
    from envs.robots import solve_batch
    goal = solve_batch(venv.robot, x0 + np.array([[0.0, -0.005, 0.0, 0.17]])).tip_position
    venv.task.goal[0] = goal.numpy()[0]
    ctrl = OperationalSpaceController(venv)
    obs = venv.task.observations()
    for _ in range(40):
        obs, _, _, infos = venv.step(ctrl(obs))
    assert infos[0]["distance"] < 1e-3, infos[0]["distance"]


def _residual_vs_base(residual_action, goal_at_tip: bool = False, steps: int = 5):
    """Final carriage positions of the residual wrapper driven by ``residual_action`` and of
    the bare controller, from the same seeded start (and goal, or goal = the start tip)."""
    from training.residual import ResidualVecEnv

    out = []
    for wrapped in (True, False):
        venv = envs.CTRReachVecEnv(2, max_episode_steps=steps + 1)  # no auto-reset
        venv.seed(3)
        env = ResidualVecEnv(venv, {"scale": 0.3, "gate_radius": 5e-3}) if wrapped else venv
        obs = env.reset()
        if goal_at_tip:
            venv.task.goal[:] = venv.task.robots.tip
        ctrl = OperationalSpaceController(venv)
        for _ in range(steps):
            obs, *_ = env.step(residual_action if wrapped else ctrl(obs))
        out.append(venv.task.robots.x.copy())
    return out


def test_residual_with_zero_action_is_the_base_controller():
    """ResidualVecEnv applies clip(osc + scale * gate * a): with a = 0 the trajectory must be
    the model-based controller's own, step for step (same seeds, same goals)."""
    from training.residual import ResidualVecEnv

    x_res, x_osc = _residual_vs_base(np.zeros((2, 4), np.float32))
    np.testing.assert_allclose(x_res, x_osc, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="residual.scale"):
        ResidualVecEnv(envs.CTRReachVecEnv(1), {"scale": -1})
    with pytest.raises(ValueError, match="residual.gate_radius"):
        ResidualVecEnv(envs.CTRReachVecEnv(1), {"gate_radius": -1e-3})


def test_residual_gate_keeps_the_goal_a_fixed_point():
    """With the tip on the goal the gate is 0: a full-scale residual changes nothing in the
    first step (the controller alone holds tau = g), while away from the goal it does."""
    ones = np.ones((2, 4), np.float32)
    x_res, x_osc = _residual_vs_base(ones, goal_at_tip=True, steps=1)
    np.testing.assert_allclose(x_res, x_osc, rtol=0, atol=1e-12)
    # away from it the residual acts (one sign at least is not clipped away by a saturated
    # controller command)
    moved = [np.abs(np.subtract(*_residual_vs_base(a, steps=1))).max() for a in (ones, -ones)]
    assert max(moved) > 1e-5, moved


def test_residual_run_records_and_reloads_its_base(tmp_path):
    """A residual config trains, writes ``residual`` into model.json, and evaluation applies the
    base controller again (a reloaded residual agent is never the bare network)."""
    cfg = train.load_config(CONFIGS[[c.stem for c in CONFIGS].index("sac_her_force_residual")])
    cfg = {**cfg, "n_envs": 2, "eval": {}, "max_episode_steps": 10,
           "hyperparams": {**cfg["hyperparams"], "learning_starts": 30, "buffer_size": 500,
                           "batch_size": 16}}
    run = train.train(cfg, steps=60, seed=2, out=tmp_path, name="res", progress=False)
    meta = json.loads((run / "model.json").read_text())
    assert meta["residual"]["scale"] == pytest.approx(0.3)
    venv = envs.CTRReachVecEnv(2, max_episode_steps=10)
    venv.seed(0)
    obs = venv.reset()
    policy = evaluate.load_policy(str(run / "model.zip"), venv)
    from stable_baselines3 import SAC
    bare = SAC.load(run / "model.zip", env=venv, device="cpu").predict(obs, deterministic=True)[0]
    osc = OperationalSpaceController(venv, gain=0.7)(obs)
    np.testing.assert_allclose(policy(obs), np.clip(osc + 0.3 * bare, -1, 1), atol=1e-6)


def test_shipped_policy_demo_runs(tmp_path, capsys):
    """The README's main job: the shipped policy loads (as a residual on the controller, per its
    model.json), runs on 2 goals next to the controller, and the rollout strip is written."""
    from training import demo

    meta = json.loads(demo.DEFAULT_POLICY.with_suffix(".json").read_text())
    assert meta["env_id"] == "torchpvs/CTRReachForce-v0" and "residual" in meta
    assert demo.main(["--goals", "2", "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "SAC+HER residual on OSC" in out and "operational-space controller" in out
    assert (tmp_path / "reach.png").stat().st_size > 10_000
