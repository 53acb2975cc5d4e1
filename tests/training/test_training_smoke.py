"""Training and evaluation pipeline: the rl-zoo hyperparameter files, short runs end to end
(training.train and rl_zoo3), metric definitions on hand-made episodes, the model-based
baselines and the residual wrapper."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

import envs
from training import evaluate, train
from training.controllers import OperationalSpaceController, tip_jacobian
from training.evaluate import rollout, summarize

HYPERPARAMS = sorted(train.HYPERPARAMS_DIR.glob("*.yml"))
ZOO_ENV = "torchpvs/CTRReachForce-v0"


def _tiny(hp: dict, **kw) -> dict:
    """An entry cut down to a smoke run: 2 robots, short episodes, a small buffer."""
    hp = {**hp, "n_envs": 2, "env_kwargs": {**hp.get("env_kwargs", {}),
                                            "max_episode_steps": 20}}
    return {**hp, "learning_starts": 50, "buffer_size": 1000, "batch_size": 32, **kw}


def test_every_hyperparameter_file_is_zoo_shaped_and_names_registered_envs():
    """One file per algorithm (sac, tqc, td3, ppo), keyed by registered env ids only, every
    entry accepted by training.train's checks (zoo keys or keywords of the class), and the
    YAML anchors resolved (the joint entry repeats the force entry's shared defaults)."""
    assert {p.stem for p in HYPERPARAMS} == set(train.ALGOS)
    for path in HYPERPARAMS:
        data = yaml.safe_load(path.read_text())
        assert set(data) <= set(envs.ENV_IDS), (path, set(data) - set(envs.ENV_IDS))
        for env_id in data:
            hp = train.load_hyperparams(path.stem, env_id, path)
            assert float(hp["n_timesteps"]) > 0 and hp["n_envs"] >= 1
            if path.stem != "ppo":
                assert 0.98 <= hp["gamma"] <= 0.99, (path, hp["gamma"])
                # HER whose observations follow the relabelled goals (envs/her.py), named
                # the way the zoo evaluates it
                from envs.her import ZOO_NAME, GoalConsistentHerReplayBuffer
                assert hp["replay_buffer_class"] == ZOO_NAME, path
                assert train._eval_str(ZOO_NAME, "x") is GoalConsistentHerReplayBuffer
        # the joint entry repeats the force entry; only env options that exist for force
        # actions alone (compensation) may differ
        force = {k: v for k, v in data[ZOO_ENV].items() if k != "env_kwargs"}
        joint = {k: v for k, v in data["torchpvs/CTRReachJoint-v0"].items() if k != "env_kwargs"}
        assert joint == force
        jk = dict(data["torchpvs/CTRReachJoint-v0"].get("env_kwargs") or {})
        fk = dict(data[ZOO_ENV].get("env_kwargs") or {})
        fk.pop("compensation", None)
        assert jk == fk, path


def test_bad_entries_name_the_key(tmp_path):
    p = tmp_path / "sac.yml"
    p.write_text(yaml.safe_dump({ZOO_ENV: {"n_timesteps": 10, "oops": 1}}))
    with pytest.raises(ValueError, match="oops"):
        train.load_hyperparams("sac", ZOO_ENV, p)
    with pytest.raises(ValueError, match="no entry"):
        train.load_hyperparams("sac", "torchpvs/CTRReachJoint-v0", p)
    with pytest.raises(ValueError, match="env must be one of"):
        train.load_hyperparams("sac", "Pendulum-v1", p)
    with pytest.raises(ValueError, match="key:value"):
        train.parse_pairs(["n_envs=4"], "--hyperparams")
    assert train.parse_pairs(["n_envs:4", "robot:rvim_three_tube", "lr:1e-3"], "x") == {
        "n_envs": 4, "robot": "rvim_three_tube", "lr": 1e-3}


def test_curriculum_schedule_and_env_tolerance():
    from training.callbacks import ToleranceCurriculum

    cb = ToleranceCurriculum(start=0.01, end=0.001, fraction=0.5)
    cb.total = 1000
    assert cb.tolerance(0) == pytest.approx(0.01)
    assert cb.tolerance(250) == pytest.approx(math.sqrt(0.01 * 0.001))
    assert cb.tolerance(500) == pytest.approx(0.001) == cb.tolerance(900)
    with pytest.raises(ValueError, match="fraction"):
        ToleranceCurriculum(0.01, 0.001, fraction=0)


def test_failed_goal_replay_sends_robots_back_to_missed_goals():
    """Every episode of an untrained agent misses (3 steps, 1 mm): with ``fraction=1`` each
    finished robot queues a goal from the pool of missed ones, which its episode after the next
    takes (envs' ``set_next_goal``)."""
    from sb3_contrib import TQC

    from training.callbacks import FailedGoalReplay

    venv = envs.CTRReachVecEnv(2, max_episode_steps=3)
    model = TQC("MultiInputPolicy", venv, learning_starts=10_000, buffer_size=100, seed=0,
                policy_kwargs={"net_arch": [8]})
    cb = FailedGoalReplay(fraction=1.0, capacity=50)
    model.learn(18, callback=cb)               # 9 batched steps: 3 episodes per robot
    assert cb.finished == 6 and cb.replayed == 6 and len(cb.pool) == 6
    assert all(start is None for _, start in cb.pool)
    pool = np.array([g for g, _ in cb.pool])
    # the episodes now running were queued at the end of the first ones: goals from the pool
    for g in venv.state().goal:
        assert np.abs(pool - g).max(-1).min() < 1e-6
    # the pool held the missed episodes' goals, not the goals of the episodes that followed
    assert len({tuple(np.round(g, 9)) for g in pool}) >= 4
    with pytest.raises(ValueError, match="fraction"):
        FailedGoalReplay(fraction=1.5)
    with pytest.raises(ValueError, match="with_start"):
        FailedGoalReplay(with_start="yes")
    with pytest.raises(ValueError, match="capacity"):
        FailedGoalReplay(capacity=0)


def test_failed_episode_replay_sends_robots_back_to_missed_starts_and_goals():
    """``with_start=True``: the pool holds each missed episode's start state with its goal,
    and a replay puts the robot back at that start with that goal."""
    from sb3_contrib import TQC

    from training.callbacks import FailedGoalReplay

    venv = envs.CTRReachVecEnv(2, max_episode_steps=3)
    model = TQC("MultiInputPolicy", venv, learning_starts=10_000, buffer_size=100, seed=0,
                policy_kwargs={"net_arch": [8]})
    venv.seed(4)
    cb = FailedGoalReplay(fraction=1.0, capacity=50, with_start=True)
    model.learn(9, callback=cb)                # the first episode of each robot misses
    first = {(tuple(np.round(x, 9)), tuple(np.round(g, 9))) for g, x in cb.pool}
    assert cb.finished == 2 and len(first) == 2
    model.learn(9, callback=cb, reset_num_timesteps=False)
    s, starts = venv.state(), venv.get_attr("episode_start")
    # the episodes now running replay pool entries: start and goal together
    for i in range(2):
        pair = min(cb.pool, key=lambda e: np.abs(e[1] - starts[i]).max())
        np.testing.assert_allclose(starts[i], pair[1], atol=1e-9)
        np.testing.assert_allclose(s.goal[i], pair[0], atol=1e-6)


def test_train_200_steps_and_evaluate(tmp_path):
    """~200 SAC+HER steps on 2 batched robots from sac.yml, the run folder's records, the
    curriculum applied to the training env, then the evaluation script on a few goals with
    the saved model and a baseline."""
    hp = _tiny(train.load_hyperparams("sac", ZOO_ENV))
    run = train.train("sac", ZOO_ENV, hp, steps=200, seed=1, out=tmp_path, progress=False,
                      eval_freq=100, eval_episodes=2, argv=["--algo", "sac"])
    for f in ("hyperparams.yml", "command.txt", "model.zip", "model.json", "evaluations.npz",
              "monitor.csv", "train.log"):
        assert (run / f).exists(), f
    meta = json.loads((run / "model.json").read_text())
    assert meta["algo"] == "sac" and meta["steps"] >= 200 and "residual" not in meta
    out = tmp_path / "eval"
    code = evaluate.main(["--policy", f"agent={run / 'model.zip'}", "--baselines", "zero",
                          "--episodes", "2", "--batch", "2", "--out", str(out),
                          "--run-dir", str(run), "--per-episode"])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {"agent", "zero"}
    episodes = json.loads((out / "episodes.json").read_text())
    assert episodes["seed"] == 12345
    for name, m in metrics.items():
        assert 0 <= m["success@1mm"] <= m["success@2mm"] <= m["success@5mm"] <= 1
        assert m["episodes"] == 2 and 0 <= m["settled_fraction"] <= 1
        # the per-episode file holds what the summary was computed from
        e = np.array(episodes[name]["final_error"]) * 1e3
        assert len(e) == 2 and math.isclose(float(np.median(e)), m["median_error_mm"])
    assert (out / "error_histogram.png").exists() and (out / "learning_curve.png").exists()
    # learning curves of run folders alone; a folder without evaluations is refused
    curves = tmp_path / "curves"
    assert evaluate.main(["--run-dir", str(run), "--out", str(curves)]) == 0
    assert (curves / "learning_curve.png").exists() and not (curves / "metrics.json").exists()
    with pytest.raises(SystemExit):
        evaluate.main(["--run-dir", str(tmp_path), "--out", str(tmp_path / "none")])
    with pytest.raises(SystemExit):
        evaluate.main(["--out", str(tmp_path / "none")])


def test_fine_tuning_starts_from_the_saved_networks(tmp_path):
    """--init-from: a run on the robust task starts from another run's networks (the same
    weights before its first update), and a model of other spaces is refused by name."""
    import torch
    hp = _tiny(train.load_hyperparams("sac", ZOO_ENV))
    first = train.train("sac", ZOO_ENV, hp, steps=100, seed=1, out=tmp_path / "a",
                        progress=False, eval_freq=0, eval_episodes=0)
    robust = "torchpvs/CTRReachForceRobust-v0"
    hp_r = dict(hp, learning_starts=10**6)   # no update: the weights stay the loaded ones
    run = train.train("sac", robust, hp_r, steps=50, seed=2, out=tmp_path / "b",
                      progress=False, eval_freq=0, eval_episodes=0,
                      init_from=first / "model.zip")
    from stable_baselines3.common.save_util import load_from_zip_file
    a, b = (load_from_zip_file(r / "model.zip", device="cpu")[1]["policy"] for r in (first, run))
    assert all(torch.equal(a[k], b[k]) for k in a)
    # and its entropy coefficient (a tensor variable, not in the state dicts): restarting it
    # at 1.0 undid a learned policy
    ea, eb = (load_from_zip_file(r / "model.zip", device="cpu")[2]["log_ent_coef"]
              for r in (first, run))
    assert float(ea) != 0.0 and torch.equal(ea, eb)
    assert json.loads((run / "model.json").read_text())["init_from"] == str(
        first / "model.zip")
    with pytest.raises(ValueError, match="--init-from"):
        three = dict(hp, env_kwargs={"robot": "rvim_three_tube", "max_episode_steps": 20})
        train.train("sac", "torchpvs/CTRReachForce-v0", three, steps=10, seed=0,
                    out=tmp_path / "c", progress=False, eval_freq=0, eval_episodes=0,
                    init_from=first / "model.zip")


def test_training_cli_overrides_reach_the_run(tmp_path):
    """--env-kwargs merges into env_kwargs, --hyperparams overrides keys, --residual adds the
    wrapper: all recorded in the run's hyperparams.yml and model.json."""
    code = train.main(["--algo", "td3", "-n", "40", "--out", str(tmp_path), "--eval-freq", "0",
                       "--env-kwargs", "max_episode_steps:10",
                       "--hyperparams", "n_envs:2", "learning_starts:20", "buffer_size:500",
                       "batch_size:16", "callback:None",
                       "--residual", "base:osc", "scale:0.2"])
    assert code == 0
    (run,) = tmp_path.iterdir()
    hp = yaml.safe_load((run / "hyperparams.yml").read_text())[ZOO_ENV]
    assert hp["env_kwargs"] == {"robot": "fig3_two_tube", "reward": "sparse",
                                "snap_penalty": -60.0, "max_episode_steps": 10}
    assert hp["n_envs"] == 2 and hp["noise_type"] == "normal"
    meta = json.loads((run / "model.json").read_text())
    assert meta["algo"] == "td3" and meta["residual"] == {"base": "osc", "scale": 0.2}


def test_every_evaluation_has_its_checkpoint(tmp_path):
    """A checkpoint is saved at every evaluation, so the checkpoint chosen by selection success
    (not only EvalCallback's best mean return) exists afterwards."""
    code = train.main(["--algo", "td3", "-n", "60", "--out", str(tmp_path), "--eval-freq", "20",
                       "--eval-episodes", "2", "--env-kwargs", "max_episode_steps:10",
                       "--hyperparams", "n_envs:2", "learning_starts:20", "buffer_size:500",
                       "batch_size:16", "callback:None", "--no-progress"])
    assert code == 0
    (run,) = tmp_path.iterdir()
    evaluated = np.load(run / "evaluations.npz")["timesteps"].tolist()
    assert evaluated == [20, 40, 60]
    saved = sorted(int(f.stem.split("_")[1]) for f in (run / "checkpoints").glob("model_*.zip"))
    assert saved == evaluated


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


def test_the_miss_breakdown_sorts_hand_built_episodes():
    """Six episodes, one of each kind, counted by hand: a success, a snap, one that hit and
    left, a near and a far miss that never hit, and a success whose goal was out of time's
    reach (counted as reachable-late only if it missed)."""
    from training.evaluate import miss_breakdown
    res = {"final_error": np.array([0.5, 8.0, 1.5, 3.0, 40.0, 0.9]) * 1e-3,
           "snap": np.array([0, 1, 0, 0, 0, 0]),
           "first_hit": np.array([10, -1, 20, -1, -1, 30]),
           "travel_steps": np.array([30.0, 50.0, 40.0, 60.0, 150.0, 120.0]),
           "episode_steps": 100}
    m = miss_breakdown(res)
    assert m == {"miss_snapped": 1 / 6, "miss_left_after_hit": 1 / 6, "miss_within_5mm": 1 / 6,
                 "miss_beyond_5mm": 1 / 6, "miss_not_reachable_in_time": 1 / 6}
    # the four kinds partition the misses
    miss = float((res["final_error"] > 1e-3).mean())
    assert math.isclose(sum(v for k, v in m.items() if k != "miss_not_reachable_in_time"), miss)


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
    """A residual run on plan-then-servo trains, writes ``residual`` into model.json, and
    evaluation applies the base controller again (a reloaded residual agent is never the bare
    network): policy = clip(pts + scale * gate * network)."""
    hp = _tiny(train.load_hyperparams("sac", ZOO_ENV), learning_starts=30, buffer_size=500,
               batch_size=16, callback=None)
    hp["env_kwargs"]["max_episode_steps"] = 10
    hp["vec_env_wrapper"] = [{"training.residual.ResidualVecEnv":
                              {"base": "pts", "scale": 0.3, "table_size": 256}}]
    run = train.train("sac", ZOO_ENV, hp, steps=60, seed=2, out=tmp_path, progress=False,
                      eval_freq=0)
    meta = json.loads((run / "model.json").read_text())
    assert meta["residual"] == {"base": "pts", "scale": 0.3, "table_size": 256}
    venv = envs.CTRReachVecEnv(2, max_episode_steps=10)
    venv.seed(0)
    obs = venv.reset()
    policy = evaluate.load_policy(str(run / "model.zip"), venv)
    from stable_baselines3 import SAC

    from training.controllers import PlanThenServoController
    bare = SAC.load(run / "model.zip", env=venv, device="cpu").predict(obs, deterministic=True)[0]
    base = PlanThenServoController(venv, table_size=256)(obs)
    st = venv.state()
    gate = np.minimum(1.0, np.linalg.norm(st.goal - st.tip, axis=-1, keepdims=True) / 5e-3)
    np.testing.assert_allclose(policy(obs), np.clip(base + 0.3 * gate * bare, -1, 1),
                               atol=1e-6)


def _zoo_train(tmp_path, extra: list[str], n: int):
    """``python -m rl_zoo3.train`` on tqc.yml (sb3-contrib's TQC, HER, the curriculum
    callback), cut down to ``n`` steps on 2 robots; returns the zoo run folder."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "rl_zoo3.train", "--algo", "tqc", "--env", ZOO_ENV,
           "--gym-packages", "envs", "--conf-file", "training/hyperparams/tqc.yml",
           "-n", str(n), "--seed", "3", "-f", str(tmp_path / "logs"), "--eval-freq", "-1",
           "--env-kwargs", "max_episode_steps:10",
           "--hyperparams", "n_envs:2", "learning_starts:40", "buffer_size:500",
           "batch_size:16", "gradient_steps:1", "policy_kwargs:dict(net_arch=[32, 32])", *extra]
    root = train.HYPERPARAMS_DIR.parents[1]
    done = subprocess.run(cmd, cwd=root, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    (run,) = (tmp_path / "logs" / "tqc").iterdir()
    assert (run / "torchpvs-CTRReachForce-v0.zip").exists()
    return run


def test_rl_zoo3_trains_from_our_hyperparameters_and_evaluate_loads_the_run(tmp_path):
    """The documented zoo command trains from tqc.yml (a few steps), and training.evaluate
    loads the zoo run folder (algorithm and env from its args.yml/config.yml)."""
    run = _zoo_train(tmp_path, [], n=100)
    _, meta = evaluate.policy_meta(run)
    assert meta["algo"] == "tqc" and meta["env_id"] == ZOO_ENV and meta["residual"] is None
    out = tmp_path / "eval"
    assert evaluate.main(["--policy", f"zoo={run}", "--episodes", "2", "--batch", "2",
                          "--out", str(out)]) == 0
    assert json.loads((out / "metrics.json").read_text())["zoo"]["episodes"] == 2


def test_rl_zoo3_residual_on_plan_then_servo(tmp_path):
    """The zoo with a residual on plan-then-servo as its vec_env_wrapper (the base plans
    through env_method('state') on the zoo's DummyVecEnv); evaluation rebuilds the base."""
    run = _zoo_train(tmp_path, ["vec_env_wrapper:[{'training.residual.ResidualVecEnv': "
                                "{'base': 'pts', 'table_size': 256}}]"], n=150)
    _, meta = evaluate.policy_meta(run)
    assert meta["residual"] == {"base": "pts", "table_size": 256}
    out = tmp_path / "eval"
    assert evaluate.main(["--policy", f"zoo={run}", "--episodes", "2", "--batch", "2",
                          "--out", str(out)]) == 0


def test_two_zoo_sweep_workers_started_at_once_share_one_new_optuna_study(tmp_path):
    """The documented sweep: two rl_zoo3 -optimize runs with the same --storage URL and
    --study-name (as workers on two machines would) add their trials to ONE study.
    Started AT ONCE on a new SQLite file, the zoo's own create_study raced
    (optuna#4621: IntegrityError on alembic_version, or "table studies already exists");
    each worker's documented command now creates the study first (training.study)."""
    import subprocess
    import sys
    import threading

    import optuna

    storage = f"sqlite:///{tmp_path / 'sweep.db'}"
    cwd = train.HYPERPARAMS_DIR.parents[1]
    results: dict[int, list] = {}

    def worker(seed: int) -> None:
        create = [sys.executable, "-m", "training.study", "--storage", storage,
                  "--study-name", "smoke"]
        zoo = [sys.executable, "-m", "rl_zoo3.train", "--algo", "sac", "--env", ZOO_ENV,
               "--gym-packages", "envs", "--conf-file", "training/hyperparams/sac.yml",
               "-optimize", "--n-trials", "1", "--sampler", "random", "--pruner", "none",
               "--storage", storage, "--study-name", "smoke", "-n", "100",
               "--n-evaluations", "1", "--eval-episodes", "2", "--no-optim-plots",
               "--env-kwargs", "max_episode_steps:10", "--hyperparams", "n_envs:2",
               "-f", str(tmp_path / f"logs{seed}"), "--seed", str(seed)]
        results[seed] = [subprocess.run(c, cwd=cwd, capture_output=True, text=True,
                                        timeout=600) for c in (create, zoo)]

    threads = [threading.Thread(target=worker, args=(seed,)) for seed in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for seed in (1, 2):
        for done in results[seed]:
            assert done.returncode == 0, (seed, done.args[2], done.stderr[-3000:])
    study = optuna.load_study(study_name="smoke", storage=storage)
    assert [t.state.name for t in study.trials] == ["COMPLETE", "COMPLETE"]
    assert study.direction == optuna.study.StudyDirection.MAXIMIZE


def test_demo_runs_with_the_controllers(tmp_path, capsys):
    """The README's main job: the demo runs on 2 goals with the shipped policy, plan-then-servo
    and the OSC, prints their success rates and writes the figure."""
    from training import demo

    assert demo.main(["--goals", "2", "-o", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "plan-then-servo: success@1mm" in out
    assert "operational-space controller: success@1mm" in out
    # the shipped policy (training/policies/) loads on the current env and runs beside them
    assert "cannot load" not in out and "TQC residual on PTS: success@1mm" in out
    assert (tmp_path / "reach.png").stat().st_size > 10_000


def test_her_learning_starts_below_one_episode_per_env_is_refused_by_name(tmp_path):
    """SB3's HER samples only from finished episodes and fails mid-run otherwise: the check
    names the key and the bound (n_envs x max_episode_steps) before any training."""
    with pytest.raises(ValueError, match=r"learning_starts=20 .* 4 x 10 = 40"):
        train.main(["--algo", "sac", "-n", "40", "--out", str(tmp_path), "--eval-freq", "0",
                    "--env-kwargs", "max_episode_steps:10", "--no-progress",
                    "--hyperparams", "n_envs:4", "learning_starts:20", "buffer_size:500"])


def test_runs_started_together_get_distinct_folders(tmp_path, monkeypatch):
    """Two runs of the same algorithm, env and seed in the same second (the clock frozen):
    distinct folders, the second with a suffix."""
    monkeypatch.setattr(train.time, "strftime", lambda fmt: "20260101-000000")
    hp = _tiny(train.load_hyperparams("sac", ZOO_ENV), callback=None)
    hp["env_kwargs"]["max_episode_steps"] = 5
    a = train.train("sac", ZOO_ENV, hp, steps=4, seed=0, out=tmp_path, progress=False,
                    eval_freq=0)
    b = train.train("sac", ZOO_ENV, hp, steps=4, seed=0, out=tmp_path, progress=False,
                    eval_freq=0)
    assert a.exists() and b.exists() and b.name == a.name + "-2"


def test_markdown_table_of_saved_metrics(tmp_path, capsys):
    """``--table`` prints one row per policy of saved metrics files, in order, values rounded
    as stated (a settle time that never happened prints as a dash)."""
    m = {"success@1mm": 0.5, "success@2mm": 0.6, "success@5mm": 0.75, "median_error_mm": 0.25,
         "p95_error_mm": 40.0, "steps_to_settle_median": None, "settled_fraction": 0.5,
         "effort_median_N2s": 12.5, "saturation_fraction": 0.125, "snap_rate": 0.0625,
         "episodes": 8}
    path = tmp_path / "metrics.json"
    path.write_text(json.dumps({"a": m, "b": {**m, "steps_to_settle_median": 36.0}}))
    assert evaluate.main(["--table", str(path)]) == 0
    rows = capsys.readouterr().out.strip().splitlines()
    assert len(rows) == 4
    assert rows[2] == ("| a | 0.500 / 0.600 / 0.750 | 0.25 / 40 | —; 0.50 | 12.5 | 0.125 | "
                       "0.062 | 8 |")
    assert rows[3].startswith("| b |") and "| 36; 0.50 |" in rows[3]
