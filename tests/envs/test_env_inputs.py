"""Regressions in the environments: bad actions and options raise (naming the
field and the rule) instead of being silently fixed; a one-tube robot; Gymnasium's render API;
the energy acceptance of the overdamped carriage step. The home of the environments' input
checks (torchpvs's own are in ``tests/test_inputs.py``), property tests over the classes of bad
action included."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchpvs
from envs import CarriageModel, CTRReachEnv, CTRReachVecEnv, RobotBatch, fig3_two_tube
from envs.robots import Robot, make_robot, solve_batch
from envs.task import ReachBatch, ReachConfig


@pytest.fixture(scope="module")
def force_env():
    env = CTRReachEnv()
    env.reset(seed=0)
    return env


@pytest.fixture(scope="module")
def vec_env():
    venv = CTRReachVecEnv(2)
    venv.seed(0)
    venv.reset()
    return venv


# ---------------------------------------------------------------------------------------------
# Actions: NaN/inf and wrong shapes raise (they used to become 0 / be reshaped)

@settings(max_examples=25, deadline=None)
@given(i=st.integers(0, 3), bad=st.sampled_from([math.nan, math.inf, -math.inf]),
       dtype=st.sampled_from([np.float32, np.float64, np.float16]))
def test_non_finite_actions_raise(force_env, i, bad, dtype):
    x0 = force_env.actuation
    a = np.zeros(4, dtype)
    a[i] = bad
    with pytest.raises(ValueError, match=r"action must be finite; entries \[\(" + str(i)):
        force_env.step(a)
    np.testing.assert_array_equal(force_env.actuation, x0)  # nothing moved


@pytest.fixture(scope="module")
def joint_env():
    env = CTRReachEnv(control="joint")
    env.reset(seed=0)
    return env


@pytest.mark.parametrize("shape", [(2, 2), (1, 4), (4, 1), (3,), (5,), (), (8,), (1, 1, 4)])
@pytest.mark.parametrize("control", ["force", "joint"])
def test_single_env_refuses_actions_of_another_shape(force_env, joint_env, shape, control):
    env = force_env if control == "force" else joint_env
    x0 = env.actuation
    with pytest.raises(ValueError, match=r"action must have shape \(4,\).*got shape"):
        env.step(np.zeros(shape, np.float32))
    np.testing.assert_array_equal(env.actuation, x0)


@pytest.mark.parametrize("shape", [(1, 2, 2), (2, 2, 2), (4, 2), (8,), (2, 4, 1), (1, 4)])
def test_vec_env_refuses_actions_of_another_shape(vec_env, shape):
    with pytest.raises(ValueError, match=r"action must have shape \(2, 4\).*got shape"):
        vec_env.step(np.zeros(shape, np.float32))


def test_vec_env_refuses_non_finite_actions(vec_env):
    a = np.zeros((2, 4))
    a[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"action must be finite; entries \[\(1, 2\)\]"):
        vec_env.step(a)


@pytest.mark.parametrize("action", [np.array(["0", "0", "0", "0"]),
                                    np.array([None] * 4, dtype=object),
                                    np.ones(4, dtype=complex), np.ones(4, dtype=bool)],
                         ids=["str", "object", "complex", "bool"])
def test_non_numeric_actions_raise(force_env, action):
    with pytest.raises(ValueError, match="action must be a real numeric array"):
        force_env.step(action)


# Property tests over the classes of bad action, so that none of them comes back: an action of
# any shape but the action space's, or with any non-finite entry, raises ValueError and leaves
# the robot where it was

PROPS = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])


@PROPS
@given(shape=st.lists(st.integers(0, 4), max_size=3).map(tuple).filter(lambda s: s != (4,)))
def test_actions_of_any_other_shape_raise(force_env, shape):
    x0 = force_env.actuation
    with pytest.raises(ValueError, match=r"action must have shape \(4,\)"):
        force_env.step(np.zeros(shape, np.float32))
    np.testing.assert_array_equal(force_env.actuation, x0)


@PROPS
@given(a=st.lists(st.floats(-2, 2), min_size=4, max_size=4),
       bad=st.lists(st.sampled_from([math.nan, math.inf, -math.inf]), min_size=1, max_size=4),
       where=st.permutations(range(4)))
def test_actions_with_any_non_finite_entry_raise(force_env, a, bad, where):
    x0 = force_env.actuation
    a = np.array(a)
    a[list(where[:len(bad)])] = bad
    with pytest.raises(ValueError, match="action must be finite"):
        force_env.step(a)
    np.testing.assert_array_equal(force_env.actuation, x0)


def test_valid_actions_still_work_and_saturate(force_env):
    """Finite actions outside the box are clipped (actuator saturation, reported)."""
    _, _, _, _, info = force_env.step(np.array([5, -5, 0, 0], np.float64))
    np.testing.assert_allclose(info["tau"][:2], [force_env.robot.force_scale[0],
                                                 -force_env.robot.force_scale[1]])
    assert info["saturated"] == 0.5


# ---------------------------------------------------------------------------------------------
# Options: non-finite or meaningless values raise, naming the field

@pytest.mark.parametrize(("field", "value"), [
    ("snap_penalty", math.nan), ("snap_penalty", -math.inf), ("snap_penalty", 5.0),
    ("snap_penalty", "a"), ("dense_scale", math.inf), ("dense_scale", math.nan),
    ("max_joint_step", (math.nan, 0.1)), ("max_joint_step", (1e-3, math.inf)),
    ("max_joint_step", 1e-3), ("goal_min_distance", math.nan), ("goal_min_distance", -1e-3),
    ("goal_min_distance", math.inf), ("tolerance", math.nan), ("tolerance", True),
])
def test_bad_task_options_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        ReachConfig(**{field: value})


def test_snap_penalty_zero_and_negative_are_fine():
    assert ReachConfig(snap_penalty=0.0).snap_penalty == 0.0
    assert ReachConfig(snap_penalty=-3).snap_penalty == -3


@pytest.mark.parametrize("factory", [CTRReachEnv, lambda **kw: CTRReachVecEnv(2, **kw)],
                         ids=["env", "vec_env"])
def test_goal_min_distance_beyond_the_workspace_raises(factory):
    """Every tip lies within the robot's reach of the orifice: goals are never more than
    2 x reach from the start. 10 m used to return goals 0.056 m away without a word."""
    with pytest.raises(ValueError, match=r"goal_min_distance \(10 m\) cannot be met.*reach"):
        factory(goal_min_distance=10.0)


def test_goal_min_distance_not_met_by_sampling_raises(monkeypatch):
    """Below 2 x reach but beyond what the Fig. 3 robot's tips span (its tubes leave the
    orifice along +z and bend by at most ~70 deg): the redraws fail and reset says so."""
    monkeypatch.setattr(ReachBatch, "GOAL_DRAWS", 3)  # 20 by default; fewer keep it quick
    robot = fig3_two_tube()
    env = CTRReachEnv(goal_min_distance=1.9 * robot.reach)
    with pytest.raises(ValueError, match=r"goal_min_distance .* cannot be met: 4 goals"):
        env.reset(seed=0)


def test_goal_min_distance_that_can_be_met_is_met():
    env = CTRReachEnv(goal_min_distance=0.05)
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        assert np.linalg.norm(obs["desired_goal"] - obs["achieved_goal"]) >= 0.05 - 1e-6


# ---------------------------------------------------------------------------------------------
# Batch size 0 (the solver's message was "expected 1 or 1")

def test_batch_size_zero_is_refused_by_name():
    robot = fig3_two_tube()
    with pytest.raises(ValueError, match=r"batch_size must be an integer >= 1, got 0"):
        RobotBatch(robot, CarriageModel(), 0)
    with pytest.raises(ValueError, match=r"batch_size must be an integer >= 1, got 0"):
        ReachBatch(robot, ReachConfig(), CarriageModel(), 0)
    with pytest.raises(ValueError, match=r"x must have shape \(B, 4\) with a batch size B >= 1.*"
                                         r"got shape \(0, 4\)"):
        solve_batch(robot, np.zeros((0, 4)))
    with pytest.raises(ValueError, match=r"x must have shape \(B, 4\).*got shape \(4,\)"):
        solve_batch(robot, np.zeros(4))
    with pytest.raises(ValueError, match="num_envs"):
        CTRReachVecEnv(0)


# ---------------------------------------------------------------------------------------------
# A one-tube robot (no relative rotation)

@pytest.fixture(scope="module")
def one_tube_scene():
    inner = torchpvs.load_scene("renda2021_fig3").tubes[1]  # kappa 13.8 1/m over 85 mm
    return torchpvs.Scene((inner,), torchpvs.Actuation((0.15,), (0.0,)))


def test_one_tube_robot_is_an_env_robot(one_tube_scene):
    """It used to fail with "force_scale and torque_scale must be > 0": a single tube's base
    rotation is a rigid rotation, dU*/dalpha = 0 (physics.md, "Common rotation": the torques
    sum to zero without a tip load), so it has no measured torque scale. The insertion force
    is the configurational force 1/2 EI kappa^2 whenever the curved part spans the orifice
    (physics.md, "The configurational force"; Bigoni et al. 2015), so the measured scale is
    1.5 x that (the p99 of |tau_D| over the workspace)."""
    robot = make_robot(one_tube_scene)
    tube = one_tube_scene.tubes[0]
    assert robot.force_scale[0] == pytest.approx(1.5 * 0.5 * tube.bending_stiffness * 13.8**2,
                                                 rel=5e-3)
    assert robot.torque_scale[0] > 0
    env = CTRReachEnv(robot=one_tube_scene)
    assert env.action_space.shape == (2,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(env, skip_render_check=True)
    env.reset(seed=0)
    assert env.elastic_forces[1] == pytest.approx(0.0, abs=1e-12)
    a0 = env.actuation[1]
    _, _, _, _, info = env.step(np.array([0.0, 0.6], np.float32))
    # no elastic torque: b alpha_dot = tau, so alpha moves at 0.6 x the rotation speed
    c = env.carriage
    assert env.actuation[1] - a0 == pytest.approx(0.6 * c.rotation_speed * c.control_period,
                                                  rel=1e-6)
    venv = CTRReachVecEnv(3, robot=one_tube_scene, control="joint")
    venv.seed(1)
    venv.reset()
    obs, r, d, infos = venv.step(np.ones((3, 2), np.float32))
    assert np.isfinite(obs["observation"]).all()


def test_a_robot_with_a_zero_scale_names_the_field(one_tube_scene):
    with pytest.raises(ValueError, match=r"Robot\.torque_scale\[0\] must be > 0"):
        Robot(name="x", scene=one_tube_scene, insertion_min=(0.0,), insertion_max=(0.2,),
              force_scale=(1.0,), torque_scale=(0.0,))


# ---------------------------------------------------------------------------------------------
# Gymnasium's render API: "human" draws and returns None

def test_render_modes_follow_the_gymnasium_api():
    """check_env with the render check, every warning an error: it makes the env in each
    declared render mode and checks what render() returns (None for "human"). Both
    registered ids share CTRReachEnv.render, so one is checked."""
    env = gym.make("torchpvs/CTRReachForce-v0", render_mode="human")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gym_check_env(env.unwrapped)
    assert env.unwrapped.render() is None
    env.close()
    rgb = CTRReachEnv(render_mode="rgb_array")
    rgb.reset(seed=0)
    assert rgb.render().ndim == 3
    rgb.close()


# ---------------------------------------------------------------------------------------------
# Energy acceptance (Armijo) of the overdamped carriage step

def _merit_rollout(seed: int, control_period: float, tau_frac, B: int = 4,
                   seconds: float = 1.5):
    """phi = U* - tau . x of B relaxing robots, ``(steps + 1, B)``, from a fresh solve at
    each committed state (independent of the stored energies), and the solver calls."""
    robot = fig3_two_tube()
    rb = RobotBatch(robot, CarriageModel(control_period=control_period), B)
    rb.set_state(np.arange(B), robot.sample_actuation(np.random.default_rng(seed), B))
    tau = np.asarray(tau_frac, dtype=np.float64) * robot.action_scale * np.ones((B, 1))
    solves0 = rb.solves

    def phi():
        e = solve_batch(robot, rb.x, initial=rb.q).energy.numpy()
        return e - (tau * rb.x).sum(-1)

    out = [phi()]
    substeps = 0
    for _ in range(int(round(seconds / control_period))):
        substeps += int(rb.step_force(tau).substeps.max())
        out.append(phi())
    return np.array(out), rb.solves - solves0, substeps


@pytest.mark.parametrize(("seed", "period", "tau"), [
    (4, 0.1, [0, 0, 0, 0]),      # 8.6e-4 J per step of rise before the Armijo acceptance
    (4, 0.05, [0, 0, 0, 0]),
    (1, 0.1, [0.2, -0.1, 0.0, 0.3]),
    (7, 0.1, [-0.3, 0.3, 0.5, -0.5]),
])
@pytest.mark.usefixtures("one_thread")
def test_overdamped_step_never_raises_the_merit(seed, period, tau):
    """b xdot = tau - dU*/dx is the gradient flow of phi = U* - tau . x; with the Armijo
    sufficient-decrease test (L. Armijo, Pacific J. Math. 16(1), 1966; Nocedal & Wright,
    Numerical Optimization, 2nd ed., eq. 3.4) each step lowers phi, kinks of U* included
    (physics.md, "Kinks"), up to the solver's round-off."""
    phi, _, _ = _merit_rollout(seed, period, tau)
    scale = np.abs(phi).max()
    assert np.diff(phi, axis=0).max() <= 1e-10 * scale
    assert (phi[-1] <= phi[0]).all() and (phi[-1] < phi[0] - 1e-6 * scale).any()


@pytest.mark.usefixtures("one_thread")
def test_the_energy_test_adds_no_solves_where_the_first_step_is_accepted():
    """A smooth stretch (no kink crossed): exactly one batched solve per substep."""
    phi, solves, substeps = _merit_rollout(2, 0.1, [0.05, 0.05, 0.0, 0.0], B=2, seconds=0.5)
    assert np.diff(phi, axis=0).max() <= 0.0
    assert solves == substeps


# ---------------------------------------------------------------------------------------------
# Regression: the ids fix the control, unknown robots list the env robots, step before
# reset says "call reset() first", reset options: a validated user goal, unknown keys refused

FORCE_ID, JOINT_ID = "torchpvs/CTRReachForce-v0", "torchpvs/CTRReachJoint-v0"


@pytest.mark.parametrize("make", ["make", "vector_entry_point", "sync"])
def test_a_control_that_contradicts_the_id_is_refused(make):
    def build(env_id, **kw):
        if make == "make":
            return gym.make(env_id, **kw)
        return gym.make_vec(env_id, num_envs=2, vectorization_mode=make, **kw)

    with pytest.raises(ValueError, match="control='joint' contradicts.*CTRReachForce-v0.*"
                                         "CTRReachJoint-v0"):
        build(FORCE_ID, control="joint")
    with pytest.raises(ValueError, match="control='force' contradicts.*CTRReachJoint-v0"):
        build(JOINT_ID, control="force")
    with pytest.raises(ValueError, match="control must be one of"):
        build(FORCE_ID, control="torque")
    # naming the id's own control is fine
    env = build(FORCE_ID, control="force")
    config = env.unwrapped.config if make == "make" else env.get_attr("config")[0] \
        if make == "sync" else env.config
    assert config.control == "force"


def test_an_unknown_robot_lists_the_env_robots():
    with pytest.raises(torchpvs.SceneError, match=r"unknown robot 'bogus'.*fig3_two_tube.*"
                                                  r"rvim_three_tube.*renda2021_fig3"):
        CTRReachEnv(robot="bogus")
    with pytest.raises(torchpvs.SceneError, match="rvim_three_tube"):
        gym.make_vec(FORCE_ID, num_envs=2, vectorization_mode="vector_entry_point",
                     robot="bogus")
    # a scene file that does not exist keeps the scene loader's message
    with pytest.raises(torchpvs.SceneError, match="does not exist"):
        make_robot("no_such_scene.yaml")


def test_step_before_reset_says_call_reset_first():
    from gymnasium.error import ResetNeeded

    from envs import CTRReachVectorEnv
    faces = [(CTRReachEnv(), np.zeros(4, np.float32)),
             (CTRReachVectorEnv(2), np.zeros((2, 4), np.float32)),
             (CTRReachVecEnv(2), np.zeros((2, 4), np.float32)),
             (gym.make(FORCE_ID), np.zeros(4, np.float32))]
    for env, action in faces:
        with pytest.raises(ResetNeeded, match="reset"):
            env.step(action)
    # a vector env whose reset_mask left a robot without an episode
    v = CTRReachVectorEnv(2)
    v.reset(seed=0, options={"reset_mask": np.array([True, False])})
    with pytest.raises(ResetNeeded, match="call reset"):
        v.task.step(np.zeros((2, 4)))


def test_reset_takes_a_user_goal_on_every_face():
    from envs import CTRReachVectorEnv
    goal = np.array([0.01, -0.02, 0.12])
    e = CTRReachEnv()
    obs, info = e.reset(seed=1, options={"goal": goal})
    np.testing.assert_allclose(obs["desired_goal"], [*goal, 0.0], atol=1e-7)
    np.testing.assert_allclose(e.state().goal[0], goal)
    assert info["distance"] == pytest.approx(np.linalg.norm(e.state().tip[0] - goal))
    assert np.isnan(e.task.travel_steps()).all()        # no sampled preimage
    # the next reset without the option samples again; the start is still the seed's
    o2, _ = e.reset(seed=1)
    assert not np.allclose(o2["desired_goal"][:3], goal)
    np.testing.assert_array_equal(o2["achieved_goal"], obs["achieved_goal"])
    # the vector env: one goal for all, or one per robot
    v = CTRReachVectorEnv(2)
    ov, _ = v.reset(seed=1, options={"goal": goal})
    np.testing.assert_allclose(ov["desired_goal"][:, :3], [goal, goal], atol=1e-7)
    np.testing.assert_allclose(ov["achieved_goal"][0], obs["achieved_goal"], atol=1e-6)
    per = np.array([goal, -goal])
    ov, _ = v.reset(options={"goal": per})
    np.testing.assert_allclose(ov["desired_goal"][:, :3], per, atol=1e-7)
    # the SB3 adapter: per-robot options through set_options
    s = CTRReachVecEnv(2)
    s.seed(1)
    s.set_options([{"goal": goal}, {}])
    os_ = s.reset()
    np.testing.assert_allclose(os_["desired_goal"][0, :3], goal, atol=1e-7)
    assert not np.allclose(os_["desired_goal"][1, :3], goal)
    assert s.reset_infos[0]["distance"] == pytest.approx(
        np.linalg.norm(s.state().tip[0] - goal))


def test_a_queued_goal_takes_the_next_autoreset_once_and_keeps_the_seeds_start():
    """``set_next_goal`` (curricula that pick goals while training): the SB3 adapter resets
    finished robots inside ``step``, where no reset options reach them."""
    goal = np.array([0.01, -0.02, 0.12])
    envs_ = [CTRReachVecEnv(2, max_episode_steps=2) for _ in range(2)]
    for v in envs_:
        v.seed(3)
        v.reset()
    queued, plain = envs_
    queued.env_method("set_next_goal", goal, indices=[1])
    zero = np.zeros((2, 4), np.float32)
    for _ in range(2):                          # the time limit: both robots autoreset
        oq, _, dq, _ = queued.step(zero)
        op, _, dp, _ = plain.step(zero)
    assert dq.all() and dp.all()
    np.testing.assert_allclose(oq["desired_goal"][1, :3], goal, atol=1e-7)
    assert not np.allclose(op["desired_goal"][1, :3], goal)
    # robot 0 had nothing queued; robot 1's start is the one its seed gives without the goal
    np.testing.assert_array_equal(oq["desired_goal"][0], op["desired_goal"][0])
    np.testing.assert_array_equal(queued.state().x, plain.state().x)
    for _ in range(2):                          # used once: the next episode samples again
        oq, _, _, _ = queued.step(zero)
        op, _, _, _ = plain.step(zero)
    np.testing.assert_array_equal(oq["desired_goal"], op["desired_goal"])
    # the single env: its next reset without a goal option takes it; None clears it
    e = CTRReachEnv()
    e.set_next_goal(goal)
    obs, _ = e.reset(seed=1)
    np.testing.assert_allclose(obs["desired_goal"][:3], goal, atol=1e-7)
    e.set_next_goal(goal)
    e.set_next_goal(None)
    assert not np.allclose(e.reset(seed=1)[0]["desired_goal"][:3], goal)
    with pytest.raises(ValueError, match=r"next goal must lie within 2 x reach"):
        e.set_next_goal([0.0, 0.0, 1.0])


def test_a_queued_start_takes_the_next_autoreset_once_and_keeps_the_seeds_later_episodes():
    """``set_next_start`` (replaying a failed episode's start with its goal): the robot starts
    at rest at the queued state, its equilibrium the one a fresh solve there gives; the
    episode after it is the one the seed gives without the queue."""
    envs_ = [CTRReachVecEnv(2, max_episode_steps=2) for _ in range(2)]
    for v in envs_:
        v.seed(5)
        v.reset()
    queued, plain = envs_
    start = queued.get_attr("episode_start", indices=[0])[0]   # robot 0's first start
    np.testing.assert_array_equal(start, queued.state().x[0])
    queued.env_method("set_next_start", start, indices=[1])
    zero = np.zeros((2, 4), np.float32)
    for _ in range(2):
        queued.step(zero)
        plain.step(zero)
    sq, sp = queued.state(), plain.state()
    np.testing.assert_allclose(sq.x[1], start, atol=1e-12)
    np.testing.assert_array_equal(sq.v[1], 0.0)
    np.testing.assert_array_equal(queued.get_attr("episode_start", indices=[1])[0], sq.x[1])
    # the tip is the plant's equilibrium at that state (a separate solve of the same robot)
    eq = queued.task.plants.solve(start[None], np.array([1]))
    np.testing.assert_allclose(sq.tip[1], eq.tip_position.numpy()[0], atol=1e-9)
    # the goal is the one the seed gives; robot 0 untouched
    np.testing.assert_array_equal(sq.goal, sp.goal)
    np.testing.assert_array_equal(sq.x[0], sp.x[0])
    for _ in range(2):                          # used once
        queued.step(zero)
        plain.step(zero)
    np.testing.assert_array_equal(queued.state().x, plain.state().x)
    e = CTRReachEnv()
    e.set_next_start(start)
    e.reset(seed=1)
    np.testing.assert_allclose(e.state().x[0], start, atol=1e-12)
    e.set_next_start(start)
    e.set_next_start(None)
    e.reset(seed=1)
    assert not np.allclose(e.state().x[0], start)
    with pytest.raises(ValueError, match=r"next start must have shape \(4,\)"):
        e.set_next_start([0.1, 0.2])
    with pytest.raises(ValueError, match="finite"):
        e.set_next_start([0.1, 0.2, np.nan, 0.0])


@pytest.mark.parametrize("goal,match", [
    ([0.01, 0.02], r"shape \(3,\)"),
    ([0.0, 0.0, np.nan], "finite"),
    ([0.0, 0.0, 1.0], r"within 2 x reach"),
    ("here", "real 3-vector"),
])
def test_a_bad_user_goal_names_the_rule(goal, match):
    from envs import CTRReachVectorEnv
    e = CTRReachEnv()
    with pytest.raises(ValueError, match=match):
        e.reset(seed=0, options={"goal": goal})
    with pytest.raises(ValueError, match=match):
        CTRReachVectorEnv(2).reset(seed=0, options={"goal": goal})
    s = CTRReachVecEnv(2)
    s.set_options({"goal": goal})
    with pytest.raises(ValueError, match=match):
        s.reset()


def test_unknown_reset_options_are_refused_by_name():
    from envs import CTRReachVectorEnv
    e = CTRReachEnv()
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['gaol'\].*'goal', "
                                         r"'tolerance'"):
        e.reset(options={"gaol": [0.0, 0.0, 0.1]})
    with pytest.raises(ValueError, match=r"\['speed'\].*reset_mask"):
        CTRReachVectorEnv(2).reset(options={"speed": 1})
    s = CTRReachVecEnv(2)
    s.set_options({"speed": 1})
    with pytest.raises(ValueError, match=r"\['speed'\]"):
        s.reset()
    with pytest.raises(ValueError, match="tolerance must be a positive length"):
        e.reset(options={"tolerance": "1mm"})
    # the tolerance option still works
    e.reset(seed=0, options={"tolerance": 2e-3})
    assert e.task.tolerance == 2e-3
