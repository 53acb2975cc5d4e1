"""Non-learned policies evaluated next to the agents: two model-based force controllers
(privileged access to the differentiable solver) — plan-then-servo and operational-space — and
zero and random policies.

Every policy maps batched observations (the ``CTRReachVecEnv`` Dict) to actions ``(B, 2N)`` in
``[-1, 1]``; the model-based ones also read the robots' state through the environment's
``state()`` (:class:`envs.task.RobotState`), the one documented way to read it.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch

import torchpvs
from envs.robots import ENV_SOLVER_OPTIONS, solve_batch
from torchpvs.jacobians import tip_jacobian as tip_jacobian_of

__all__ = ["read_state", "env_robot", "env_config", "controller_model",
           "PlanThenServoController", "PlanThenServoFeedbackController",
           "PlanThenServoAdaptiveController",
           "OperationalSpaceController", "ZeroPolicy", "RandomPolicy", "tip_jacobian",
           "safe_rotation_target", "rotation_crossings", "CONTROLLERS"]


def tip_jacobian(robot, x: np.ndarray, initial=None) -> tuple[np.ndarray, np.ndarray]:
    """Tip positions ``(B, 3)`` [m] and ``d tip / dx`` ``(B, 3, 2N)`` [m/m, m/rad] at actuator
    coordinates ``x (B, 2N)``: one solve and the closed-form Jacobian from its factorization
    (:func:`torchpvs.jacobians.tip_jacobian`)."""
    N = robot.n_tubes
    X = torch.as_tensor(x, dtype=torch.float64)
    eq = torchpvs.solve(robot.scene, insertion=X[:, :N], rotation=X[:, N:],
                        options=ENV_SOLVER_OPTIONS, initial=initial)
    return eq.tip_position.numpy(), tip_jacobian_of(eq)[:, :3].numpy()


#: [s] added to the travel time of a plan that ends near +-180 deg relative rotation.
EDGE_PENALTY_S = 10.0


def read_state(venv):
    """The :class:`envs.task.RobotState` of every robot of ``venv``, batched ``(B, ...)``.

    ``venv.state()`` where the env (or a wrapper around it) has it — the batched envs and the
    SB3 wrappers that forward attributes (``VecMonitor``, ``VecNormalize``); otherwise
    ``venv.env_method("state")`` on each sub-env (an SB3 ``DummyVecEnv``/``SubprocVecEnv`` of
    single ``CTRReachEnv``, as rl_zoo3 builds), stacked along the batch axis.
    """
    from envs.task import RobotState

    if hasattr(venv, "state"):
        return venv.state()
    if not hasattr(venv, "env_method"):
        raise TypeError(f"{type(venv).__name__} has neither state() nor env_method(): the "
                        f"model-based controllers need a torchpvs reaching env")
    parts = venv.env_method("state")
    batched = ("x", "v", "g", "tip", "goal", "margin", "q")
    return RobotState(**{f: np.concatenate([getattr(p, f) for p in parts]) for f in batched},
                      damping=parts[0].damping, action_scale=parts[0].action_scale,
                      control_period=parts[0].control_period)


def env_robot(venv):
    """The :class:`envs.robots.Robot` that ``venv`` drives (``venv.robot``, or that of its
    first sub-env)."""
    robot = getattr(venv, "robot", None)
    return robot if robot is not None else venv.get_attr("robot", indices=[0])[0]


def controller_model(venv, model=None):
    """The :class:`envs.robots.Robot` a model-based controller plans with: ``model`` (a Robot,
    or a Scene given the env robot's strokes and scales), default the env's robot."""
    import dataclasses

    from envs.robots import Robot
    from torchpvs import Scene

    robot = env_robot(venv)
    if model is None:
        return robot
    if isinstance(model, Robot):
        out = model
    elif isinstance(model, Scene):
        out = dataclasses.replace(robot, scene=model)
    else:
        raise TypeError(f"model must be an envs.robots.Robot or a torchpvs.Scene, got "
                        f"{type(model).__name__}")
    if out.n_tubes != robot.n_tubes:
        raise ValueError(f"model has {out.n_tubes} tubes, the env's robot {robot.n_tubes}")
    return out


def env_config(venv):
    """The :class:`envs.task.ReachConfig` of ``venv`` (``venv.config``, or that of its first
    sub-env)."""
    cfg = getattr(venv, "config", None)
    return cfg if cfg is not None else venv.get_attr("config", indices=[0])[0]


def _force_env(venv, who: str) -> bool:
    """Check ``venv`` takes force actions; returns whether they are compensated
    (``tau = g(x) + scale * a`` instead of ``tau = scale * a``)."""
    cfg = env_config(venv)
    if cfg.control != "force":
        raise ValueError(f"{who} commands forces and torques: it needs control='force' "
                         f"(torchpvs/CTRReachForce-v0), got control={cfg.control!r}")
    return bool(getattr(cfg, "compensation", False))


def _action(tau: np.ndarray, st, compensated: bool) -> np.ndarray:
    """The action ``(B, 2N)`` in ``[-1, 1]`` that applies ``tau`` [N, N·m]: ``tau / scale``,
    or ``(tau - g(x)) / scale`` where the env adds the elastic load itself."""
    a = (tau - st.g if compensated else tau) / st.action_scale
    return np.clip(a, -1.0, 1.0).astype(np.float32)


def _warm(q: np.ndarray):
    """The state's solver coordinates as a warm start (``None`` before the first solve)."""
    return torch.as_tensor(q) if q.size else None


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angles [rad] onto ``[-pi, pi)``."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _windows(alpha: np.ndarray) -> np.ndarray:
    """``(B, P)``: for each tube pair ``j < k``, the index of the ``2 pi`` window
    ``((2m-1) pi, (2m+1) pi)`` that holds the relative rotation ``alpha_k - alpha_j``."""
    j, k = np.triu_indices(alpha.shape[-1], 1)
    return np.floor((alpha[..., k] - alpha[..., j] + np.pi) / (2 * np.pi))


def rotation_crossings(alpha: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``(B,)`` how many tube pairs' relative rotations pass an odd multiple of ``pi`` (``+-180
    deg``, where the torsion snaps) on the straight path from ``alpha`` to ``target``
    (``(B, N)`` [rad]): the pairs whose start and end lie in different ``2 pi`` windows."""
    return (_windows(np.asarray(alpha)) != _windows(np.asarray(target))).sum(-1)


def safe_rotation_target(alpha: np.ndarray, alpha_goal: np.ndarray) -> np.ndarray:
    """Base rotations ``(B, N)`` [rad] equal to ``alpha_goal`` modulo ``2 pi`` per tube, chosen
    so that on the straight path from ``alpha (B, N)`` no relative rotation ``alpha_k -
    alpha_j`` of any tube pair passes ``+-180 deg`` (where the torsional snap lives), and the
    common rotation takes the short way round.

    With two tubes this always holds: the relative rotation moves inside the ``2 pi`` window
    that holds its current value. With three or more, keeping every pair in its window may
    be impossible on a straight path; each tube's turn count is then chosen (among the
    window-keeping one for its pair with tube 1 and one more turn either way) for the fewest
    crossing pairs, then the least rotation (:func:`rotation_crossings` counts what is left).

    Equilibria are ``2 pi``-periodic in each base rotation (turning a tube a full turn at its
    base shifts its whole twist by ``2 pi``), so the returned rotations hold the same shape.
    """
    alpha, alpha_goal = np.asarray(alpha, np.float64), np.asarray(alpha_goal, np.float64)
    a1 = alpha[:, :1] + _wrap(alpha_goal[:, :1] - alpha[:, :1])
    rel0 = alpha[:, 1:] - alpha[:, :1]
    # each relative rotation to tube 1 moves from its wrapped value to the goal's wrapped
    # value inside [-pi, pi) (shifted by its current window's multiple of 2 pi): no crossing
    rel = rel0 + (_wrap(alpha_goal[:, 1:] - alpha_goal[:, :1]) - _wrap(rel0))
    best = np.concatenate([a1, a1 + rel], -1)
    if alpha.shape[1] <= 2:
        return best
    cost = _rotation_cost(alpha, best)
    for turns in itertools.product((-1, 0, 1), repeat=alpha.shape[1] - 1):
        if not any(turns):
            continue
        cand = np.concatenate([a1, a1 + rel + 2 * np.pi * np.array(turns)], -1)
        c = _rotation_cost(alpha, cand)
        better = c < cost
        best[better], cost[better] = cand[better], c[better]
    return best


def travel_time(x0: np.ndarray, x1: np.ndarray, g0: np.ndarray, g1: np.ndarray,
                scale: np.ndarray, damping: np.ndarray) -> np.ndarray:
    """``(B,)`` [s]: time the slowest carriage needs from ``x0`` to ``x1`` (``(B, 2N)``) at full
    actuation, with the elastic load taken as the mean of its end values ``g0``, ``g1``
    (``(B, 2N)`` [N, N·m]). A carriage with ``b xdot = tau - g`` moves at
    ``(scale - sign(dx) g) / b`` when saturated: an insertion against the tubes' load is slower
    than the unloaded ``scale / b`` (on the fig3 robot the inner carriage carries ~1.6 N of its
    4.5 N), a retraction with it faster. A carriage whose load outweighs its actuator in the
    direction it must go never arrives (``inf``)."""
    dx = x1 - x0
    g = 0.5 * (g0 + g1)
    push = scale - np.sign(dx) * g
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(dx == 0, 0.0, np.abs(dx) * damping / push)
    t = np.where((dx != 0) & ~(push > 0), np.inf, t)
    return t.max(-1)


def _rotation_cost(alpha: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Crossing pairs first (each outweighs any rotation), then total rotation [rad]."""
    return 1e3 * rotation_crossings(alpha, target) + np.abs(target - alpha).sum(-1)


class PlanThenServoController:
    """Plan once per goal with inverse kinematics, then servo the carriages to the plan.

    **Plan.** When a robot's goal changes (a reset, or a goal set by hand),
    :func:`torchpvs.inverse_kinematics` runs for the robots whose goal changed, in one batched
    call, from several initial actuations per goal: the robot's current actuation, and the
    ``neighbours`` stable configurations of a seeded table (``table_size`` uniform samples of
    the robot's feasible set, solved once) whose tips lie nearest the goal once turned to its
    azimuth (a common rotation of every tube turns the tip exactly about z). Of the stable
    solutions within ``ik_tol`` that the carriages can hold (strokes and tip order,
    :meth:`envs.robots.Robot.project`), the one with the least carriage travel time from the
    current actuation (:func:`travel_time`, with the elastic load) is kept. Goals left unsolved
    try the next neighbours, up to ``rounds`` times; a goal still unsolved keeps the closest
    actuation found (``solved`` False).

    Seeding from the table matters: on the 50 fig3 goals of evaluation seed 12345, the current
    actuation alone (the IK's default 8 starts, 60 iterations) solved 80% in 13 s; the nearest
    table entry alone (2 starts, 30 iterations) solved 100% in 3 s. Plans whose relative
    rotations end within ``rotation_margin`` of ``+-180 deg`` rank behind every other (near
    there the elastic torque is steep, and a servo that overshoots slides onto the other
    torsional branch).

    The base rotations of the plan are then shifted by multiples of ``2 pi``
    (:func:`safe_rotation_target`) so that the relative rotations never pass ``+-180 deg`` on
    the way, and one forward solve gives the elastic load ``g(x*)`` that holds the carriages
    at the plan ``x*``.

    **Servo.** Every step commands

        ``tau = g(x*) + Kp (x_ref - x) + b xdot_ref``,   ``Kp = b / time_constant``,

    converted to the env's action (``tau / scale``, or ``(tau - g(x)) / scale`` with the env's
    ``compensation`` option) and clipped to the action range, where ``b (2N,)`` is the
    carriage damping (``b xdot = tau - g``): without the feed-forward ``g(x*)`` a
    force-controlled carriage drifts (force actions integrate), and ``Kp = b / T`` makes an
    unloaded carriage close its error with time constant ``T`` [s]. With ``path_speed`` set,
    ``x_ref`` moves along the straight line from the actuation at planning time to ``x*``,
    every coordinate at most ``path_speed`` of its carriage's full-scale speed, so the
    intermediate relative rotations follow the planned path even when the carriages would
    move at different speeds; with ``path_speed = None`` (default) ``x_ref = x*`` from the
    first step (``path_speed`` 0.7 and 0.9 measured no better on 50 fig3 goals: 0.88, 0.90
    against 0.90 on that set). Feeding forward the current load ``g(x)`` instead of
    ``g(x*)`` measured no better on the 500 evaluation goals (0.952 against 0.948 at 1 mm, one
    snap against none; 0.374 with ``T = 0.05`` s, where the discrete loop rings). All 26
    failures of the 500 are plans that the carriages do not finish within the episode; more
    candidates per goal (``neighbours=6``, twice the planning time) shorten the plans a little:
    0.954 at 1 mm, median settling 32 steps against 35.

    Attributes (per robot, ``(B, ...)``, set at planning): ``target`` the plan ``x*`` [m, rad];
    ``solved`` whether the IK met ``ik_tol`` with a stable, holdable equilibrium; ``plans`` the
    number of plans made.

    Args:
        venv: a batched reaching env (``CTRReachVecEnv``, ``CTRReachVectorEnv``, or an SB3
            vec env of ``CTRReachEnv``; see :func:`read_state`).
        time_constant: [s] ``T`` in ``Kp = b / T``; default the env's control period ``h``,
            which closes an unloaded carriage's error in one step (deadbeat: the force is held
            over the step, so the error shrinks by ``1 - h / T`` per step; ``T < h / 2``
            rings). On 500 fig3 selection goals (seeds 20000+): 0.964 at ``T = h = 0.1 s``,
            0.964 at 0.08 s, 0.958 at 0.15 s (the former default).
        path_speed: fraction in ``(0, 1]`` of each carriage's full-scale speed that the
            reference moves at, or ``None`` to step the reference to ``x*``.
        neighbours: table configurations tried per goal and round (besides the current one).
        rounds: IK rounds for goals left unsolved (each with the next neighbours).
        rotation_margin: [rad] plans whose relative rotations end within this of ``+-180
            deg`` rank behind every other held plan (by ``EDGE_PENALTY_S``).
        table_size: samples of the seeding table (default 2048 per pair of tubes beyond one).
        starts, ik_tol, max_iter: passed to :func:`torchpvs.inverse_kinematics` per initial
            actuation (``starts >= 2`` adds the start turned to the goal's azimuth).
        load_aware: rank plans by :func:`travel_time` with the elastic load (one batched solve
            of the candidates), else at the unloaded full-scale speeds ``scale / b`` (0.964 ->
            0.968 on the 500 selection goals at ``T = h``).
        seed: seed of the table and of the IK's random starts.
        model: the robot the controller believes it drives (an :class:`envs.robots.Robot`,
            or a :class:`torchpvs.Scene` with the env robot's strokes and scales); default the
            env's robot. Plans, the load ``g(x*)`` and Jacobians come from it; a model that
            differs from the plant shows what model error does to a controller.
    """

    def __init__(self, venv, time_constant: float | None = None,
                 path_speed: float | None = None,
                 neighbours: int = 2, rounds: int = 3, table_size: int | None = None,
                 rotation_margin: float = math.radians(20.0), starts: int = 2,
                 ik_tol: float = 1e-4, max_iter: int = 40, load_aware: bool = True,
                 seed: int = 0, model=None):
        if time_constant is not None and not (isinstance(time_constant, (int, float))
                                              and time_constant > 0):
            raise ValueError(f"time_constant must be None or a positive time [s], got "
                             f"{time_constant!r}")
        if path_speed is not None and not (isinstance(path_speed, (int, float))
                                           and 0 < path_speed <= 1):
            raise ValueError(f"path_speed must be None or a fraction in (0, 1] of the carriage "
                             f"speed, got {path_speed!r}")
        for name, v in (("neighbours", neighbours), ("rounds", rounds)):
            if not (isinstance(v, int) and v >= (0 if name == "neighbours" else 1)):
                raise ValueError(f"{name} must be an integer >= "
                                 f"{0 if name == 'neighbours' else 1}, got {v!r}")
        self.venv, self.path_speed = venv, path_speed
        self.time_constant = (float(time_constant) if time_constant is not None
                              else float(read_state(venv).control_period))
        self.robot = controller_model(venv, model)
        self.compensated = _force_env(venv, type(self).__name__)
        self.neighbours, self.rounds, self.seed = neighbours, rounds, seed
        self.load_aware = bool(load_aware)
        self.rotation_margin = float(rotation_margin)
        n_tubes = self.robot.n_tubes
        self.table_size = int(table_size or 2048 * max(1, n_tubes - 1))
        # restarts=0: the planner's own fallbacks (more table neighbours per round) replace
        # failed starts; random restarts would change its plans and the published figures
        self.ik = dict(starts=starts, tol=ik_tol, max_iter=max_iter, restarts=0)
        B, n = venv.num_envs, 2 * n_tubes
        self._goal = np.full((B, 3), np.nan)
        self.target = np.zeros((B, n))
        self.g_target = np.zeros((B, n))
        self.solved = np.zeros(B, dtype=bool)
        self.plans = np.zeros(B, dtype=int)
        self._start = np.zeros((B, n))
        self._s = np.ones(B)         # path parameter of the reference, 0 -> 1
        self._table: tuple[np.ndarray, np.ndarray] | None = None

    # -- planning -----------------------------------------------------------------------------
    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """The seeding table ``(x (M, 2N), tip (M, 3))`` of stable, converged configurations
        sampled uniformly from the robot's feasible set (built on first use, seeded)."""
        if self._table is None:
            robot = self.robot
            x = robot.sample_actuation(np.random.default_rng(self.seed), self.table_size)
            eq = solve_batch(robot, x)
            ok = (eq.converged & eq.stable).numpy()
            self._table = (x[ok], eq.tip_position.numpy()[ok])
        return self._table

    def _seeds(self, goal: np.ndarray, rank: int) -> np.ndarray:
        """``(G, 2N)``: the table entry ranked ``rank`` nearest each goal in (radius, height),
        its rotations turned so its tip has the goal's azimuth (then wrapped)."""
        x, tip = self.table()
        d = np.hypot(np.hypot(goal[:, :1], goal[:, 1:2]) - np.hypot(tip[:, 0], tip[:, 1]),
                     goal[:, 2:3] - tip[:, 2])
        nn = np.argsort(d, axis=1)[:, rank]
        N = self.robot.n_tubes
        turn = np.arctan2(goal[:, 1], goal[:, 0]) - np.arctan2(tip[nn, 1], tip[nn, 0])
        return np.concatenate([x[nn, :N], _wrap(x[nn, N:] + turn[:, None])], -1)

    def plan(self, idx: np.ndarray, st) -> None:
        """Plan robots ``idx`` from ``st`` (an :class:`envs.task.RobotState`): sets
        ``target``, ``g_target`` and ``solved`` for them."""
        robot = self.robot
        N = robot.n_tubes
        idx = np.asarray(idx, dtype=int)
        x0, goal = st.x[idx], st.goal[idx]
        speed = st.action_scale / st.damping                      # full-scale speeds
        best = np.full(len(idx), np.inf)                          # travel time, or 1e6 + error
        target = x0.copy()
        todo = np.arange(len(idx))
        for r in range(self.rounds):
            if not len(todo):
                break
            inits = ([np.concatenate([x0[todo, :N], _wrap(x0[todo, N:])], -1)] if r == 0
                     else [])
            inits += [self._seeds(goal[todo], r * self.neighbours + k)
                      for k in range(self.neighbours)]
            if not inits:
                break
            K = len(inits)
            init = np.concatenate(inits)
            res = torchpvs.inverse_kinematics(
                robot.scene, np.tile(goal[todo], (K, 1)), initial_insertion=init[:, :N],
                initial_rotation=init[:, N:], min_exposed=robot.min_exposed,
                seed=self.seed + r, **self.ik)
            D = res.insertion.numpy()
            Dp, _, _ = robot.project(D)
            held = res.solved.numpy() & np.all(np.abs(Dp - D) <= 1e-9, -1)
            rows = np.tile(todo, K)
            cand = np.concatenate(
                [Dp, safe_rotation_target(x0[rows, N:], res.rotation.numpy())], -1)
            # rank: travel time [s] of the slowest carriage if held, plus a penalty when a
            # relative rotation of a tube pair ends within rotation_margin of +-180 deg (where
            # the torsion snaps, and where the elastic torque is steep enough to pull the servo
            # across) and one per pair that would still cross it (three or more tubes);
            # unheld plans rank far behind, by their error
            j, k = np.triu_indices(N, 1)
            rel = _wrap(cand[:, N + k] - cand[:, N + j])
            edge = (np.abs(rel) > np.pi - self.rotation_margin).any(-1)
            cross = rotation_crossings(x0[rows, N:], cand[:, N:])
            if self.load_aware:
                eq = solve_batch(robot, cand)
                g1 = np.nan_to_num(torch.cat([eq.actuation_forces, eq.actuation_torques],
                                             -1).numpy(), nan=np.inf)
                time = travel_time(x0[rows], cand, st.g[idx][rows], g1, st.action_scale,
                                   st.damping)
            else:
                time = (np.abs(cand - x0[rows]) / speed).max(-1)
            score = np.where(held, time + EDGE_PENALTY_S * (edge + cross),
                             1e6 + res.error.numpy())
            for k in range(K):
                sl = slice(k * len(todo), (k + 1) * len(todo))
                better = score[sl] < best[todo]
                best[todo[better]] = score[sl][better]
                target[todo[better]] = cand[sl][better]
            todo = todo[best[todo] >= 1e6]
        eq = solve_batch(robot, target)
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
        self.target[idx], self.g_target[idx] = target, np.nan_to_num(g)
        self.solved[idx] = best < 1e6
        self.plans[idx] += 1
        self._start[idx] = x0
        self._s[idx] = 0.0 if self.path_speed is not None else 1.0

    @property
    def reference(self) -> np.ndarray:
        """``(B, 2N)`` the actuation each robot is servoing to: its plan ``target``."""
        return self.target

    # -- acting -------------------------------------------------------------------------------
    def replan(self, st) -> None:
        """Plan the robots whose goal in ``st`` (an :class:`envs.task.RobotState`) changed since
        their last plan (a reset, or a goal set by hand)."""
        changed = np.flatnonzero(np.any(st.goal != self._goal, -1))
        if len(changed):
            self.plan(changed, st)
            self._goal[changed] = st.goal[changed]

    def __call__(self, obs) -> np.ndarray:
        st = read_state(self.venv)
        self.replan(st)
        b, h = st.damping, st.control_period
        xdot_ref = np.zeros_like(st.x)
        if self.path_speed is not None:
            # advance the path parameter so that no coordinate's reference outruns its
            # carriage: ds = h / (time the slowest coordinate needs at path_speed)
            speed = st.action_scale / b
            span = (np.abs(self.target - self._start) / (self.path_speed * speed)).max(-1)
            ds = np.minimum(1.0 - self._s, h / np.maximum(span, 1e-12))
            self._s = self._s + ds
            xdot_ref = (self.target - self._start) * (ds / h)[:, None]
        x_ref = self._start + self._s[:, None] * (self.target - self._start)
        tau = self.g_target + (b / self.time_constant) * (x_ref - st.x) + b * xdot_ref
        return _action(tau, st, self.compensated)


class PlanThenServoFeedbackController(PlanThenServoController):
    """Plan-then-servo that corrects its plan from the measured tip: the bar for agents on a
    robot that differs from its model.

    The plan ``x*`` is made on the controller's model as in :class:`PlanThenServoController`
    and becomes the setpoint ``s``. Two loops then close on what the robot does:

    * **inner (actuator space)**: ``tau = g_model(s) + Kp (s - x + z)``, ``Kp = b / T``, with an
      integral term ``z += ki (s - x)`` that removes the steady error a wrong model load
      ``g_model`` leaves; it integrates only near the setpoint and while no action saturates
      (no wind-up), and is capped at ``integral_cap`` of the action scale.
    * **outer (task space)**: once every carriage is within ``settle`` of ``s``,
      ``s <- Proj[s + gain J_model(s)^+ sat(goal - tip_measured)]`` with the model's tip
      Jacobian (implicit-function theorem) and its undamped pseudo-inverse in metres and
      radians (a damping relative to the Jacobian's scale suppresses the rotation columns,
      ~100x smaller than the insertion ones), the error saturated at ``error_cap``, the step
      capped at ``max_step`` and the coordinates at a stroke or nesting contact left out
      (a step into a contact cannot be followed and moves the tip elsewhere); ``Proj`` keeps
      strokes and tip order, and relative rotations within ``edge`` of 0 (off the +-180 deg
      torsional snap).

    Args (beside :class:`PlanThenServoController`'s): ``gain`` fraction of the tip error
    corrected per update; ``settle`` ``(m, rad)``; ``max_step`` ``(m, rad)``; ``error_cap``
    [m]; ``integral_gain`` ``ki`` per step; ``integral_cap`` fraction of the action scale;
    ``edge`` [rad].
    """

    def __init__(self, venv, gain: float = 0.6, settle: tuple[float, float] = (1.5e-3, 0.06),
                 max_step: tuple[float, float] = (1e-3, 0.05), error_cap: float = 3e-3,
                 integral_gain: float = 0.3, integral_cap: float = 0.4,
                 edge: float = math.radians(168.0), **kwargs):
        super().__init__(venv, **kwargs)
        for name, v in (("gain", gain), ("error_cap", error_cap),
                        ("integral_cap", integral_cap), ("edge", edge)):
            if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if not (isinstance(integral_gain, (int, float)) and 0 <= integral_gain < 1):
            raise ValueError(f"integral_gain must be in [0, 1), got {integral_gain!r}")
        N = self.robot.n_tubes
        self.gain, self.error_cap, self.edge = float(gain), float(error_cap), float(edge)
        self.ki, self.integral_cap = float(integral_gain), float(integral_cap)
        self.settle = np.repeat(np.asarray(settle, np.float64), N)
        self.max_step = np.repeat(np.asarray(max_step, np.float64), N)
        B = venv.num_envs
        self.setpoint = np.zeros((B, 2 * N))
        self.g_set = np.zeros((B, 2 * N))
        self.z = np.zeros((B, 2 * N))
        self.updates = np.zeros(B, dtype=int)

    @property
    def reference(self) -> np.ndarray:
        """``(B, 2N)`` the setpoint ``s`` each robot is servoing to: the plan as corrected by
        the outer loop so far."""
        return self.setpoint

    def plan(self, idx, st) -> None:
        super().plan(idx, st)
        self.setpoint[idx], self.g_set[idx] = self.target[idx], self.g_target[idx]
        self.z[idx] = 0.0

    def _correct(self, rows: np.ndarray, st) -> None:
        """The outer loop for robots ``rows``: move their setpoints along the model's
        pseudo-inverse of the measured tip error."""
        robot, N = self.robot, self.robot.n_tubes
        s = self.setpoint[rows]
        err = st.goal[rows] - st.tip[rows]
        norm = np.linalg.norm(err, axis=-1, keepdims=True)
        err = err * np.minimum(1.0, self.error_cap / np.maximum(norm, 1e-15))
        _, J = self._model_jacobian(s, rows)
        _, lower, upper = robot.project(s[:, :N], tol=1e-9)
        ds = np.zeros_like(s)
        for r in range(len(rows)):
            J_r = J[r]
            # pushing a contact: leave the coordinate out (its column would be followed only
            # by the contact force, not by the carriage)
            push = J_r[:, :N].T @ err[r]
            free = np.ones(2 * N, dtype=bool)
            free[:N] &= ~((lower[r] & (push < 0)) | (upper[r] & (push > 0)))
            ds[r, free] = self.gain * np.linalg.pinv(J_r[:, free], rcond=1e-9) @ err[r]
        ds *= np.minimum(1.0, 1.0 / np.max(np.abs(ds) / self.max_step, -1,
                                           initial=1e-15))[:, None]
        new = s + ds
        new[:, :N], _, _ = robot.project(new[:, :N])
        j, k = np.triu_indices(N, 1)
        rel = new[:, N + k] - new[:, N + j]
        off = (np.abs(_wrap(rel)) > self.edge) | (_windows(new[:, N:]) != _windows(s[:, N:]))
        keep = off.any(-1)
        new[keep, N:] = s[keep, N:]                   # no rotation step toward the snap
        g, ok = self._model_load(new, rows)
        rows, new, g = rows[ok], new[ok], g[ok]
        self.setpoint[rows], self.g_set[rows] = new, g
        self.updates[rows] += 1

    # the controller's model, per robot (the adaptive controller's differ after calibration)
    def _model_jacobian(self, x: np.ndarray, rows: np.ndarray):
        """Model tips ``(k, 3)`` and tip Jacobians ``(k, 3, 2N)`` of robots ``rows`` at ``x``."""
        return tip_jacobian(self.robot, x)

    def _model_load(self, x: np.ndarray, rows: np.ndarray):
        """Model loads ``g (k, 2N)`` of robots ``rows`` at ``x`` and whether each is a
        converged, stable equilibrium."""
        eq = solve_batch(self.robot, x)
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
        return np.nan_to_num(g), eq.converged.numpy() & eq.stable.numpy()

    def __call__(self, obs) -> np.ndarray:
        st = read_state(self.venv)
        self.replan(st)
        b = st.damping
        e = self.setpoint - st.x
        near = np.all(np.abs(e) <= self.settle, -1)
        if near.any():
            self._correct(np.flatnonzero(near), st)
            e = self.setpoint - st.x
        kp = b / self.time_constant
        cap = self.integral_cap * st.action_scale / kp
        tau = self.g_set + kp * (e + self.z)
        a = _action(tau, st, self.compensated)
        # integrate only near the setpoint and unsaturated (anti-windup)
        grow = near & (np.abs(a) < 0.999).all(-1)
        self.z[grow] = np.clip(self.z[grow] + self.ki * e[grow], -cap, cap)
        return a


class PlanThenServoAdaptiveController(PlanThenServoFeedbackController):
    """:class:`PlanThenServoFeedbackController` that re-calibrates its model from the tips it
    has measured in the episode, then re-plans on the calibrated model.

    The robot is quasi-static (every step's tip is the equilibrium tip of that step's
    actuation), so every step gives a measurement ``(x, tip)``. Once a robot has
    ``calibrate_after`` of them, :func:`torchpvs.calibrate` fits ``params`` (default the
    precurvature of every tube) of the nominal model to them (Huber scale ``huber_scale``);
    the robot's model becomes the fitted one (per-robot factors on the nominal tubes, solved
    together: :func:`envs.plant.solve_robots`), and ``replan_iters`` Gauss-Newton steps on it
    move the setpoint to where the calibrated model puts the tip on the goal (each capped at
    ``replan_step``, projected and kept off the torsional snap as the feedback steps are). The
    feedback loops then run on the calibrated model (its Jacobian and load).

    Attributes (per robot): ``factors (B, 3, N)`` the model's precurvature, ``E``, ``G``
    factors on the nominal tubes; ``calibrated`` whether this episode's calibration ran.
    """

    def __init__(self, venv, params=("precurvature",), calibrate_after: int = 30,
                 huber_scale: float = 3e-4, replan_iters: int = 3,
                 replan_step: tuple[float, float] = (5e-3, 0.2), **kwargs):
        super().__init__(venv, **kwargs)
        if not (isinstance(calibrate_after, int) and calibrate_after >= 3):
            raise ValueError(f"calibrate_after must be an integer >= 3, got "
                             f"{calibrate_after!r}")
        kinds = {p.split("[")[0] for p in ((params,) if isinstance(params, str) else params)}
        if not kinds <= {"precurvature", "E", "G"}:
            raise ValueError(f"params: the adaptive controller fits precurvature, E and G "
                             f"factors, got {params!r}")
        self.params, self.calibrate_after = params, calibrate_after
        self.huber_scale, self.replan_iters = huber_scale, int(replan_iters)
        N = self.robot.n_tubes
        self.replan_step = np.repeat(np.asarray(replan_step, np.float64), N)
        B = venv.num_envs
        self.factors = np.ones((B, 3, N))
        self.calibrated = np.zeros(B, dtype=bool)
        self.history: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(B)]

    def plan(self, idx, st) -> None:
        idx = np.asarray(idx, dtype=int)
        self.factors[idx] = 1.0
        self.calibrated[idx] = False
        for i in idx:
            self.history[i] = []
        super().plan(idx, st)

    def _model_jacobian(self, x, rows):
        from envs.plant import solve_robots
        eq = solve_robots(self.robot, torch.as_tensor(x, dtype=torch.float64),
                          self.factors[rows])
        return eq.tip_position.numpy(), tip_jacobian_of(eq)[:, :3].numpy()

    def _model_load(self, x, rows):
        from envs.plant import solve_robots
        with torch.no_grad():
            eq = solve_robots(self.robot, torch.as_tensor(x, dtype=torch.float64),
                              self.factors[rows])
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
        return np.nan_to_num(g), eq.converged.numpy() & eq.stable.numpy()

    def _recalibrate(self, rows: np.ndarray, st) -> None:
        N = self.robot.n_tubes
        kinds = {"precurvature": 0, "E": 1, "G": 2}
        for i in rows:
            X = np.array([h[0] for h in self.history[i]])
            T = np.array([h[1] for h in self.history[i]])
            cal = torchpvs.calibrate(self.robot.scene, X[:, :N], X[:, N:], T,
                                     params=self.params, huber_scale=self.huber_scale,
                                     max_iter=20)
            if not (cal.converged and cal.identifiability.identifiable):
                continue
            for name, v in zip(cal.names, cal.value, strict=True):
                kind, j = name.split("[")[0], int(name.split("[")[1][:-1])
                nominal = {"precurvature": 1.0, "E": self.robot.scene.tubes[j].E,
                           "G": self.robot.scene.tubes[j].G}[kind]
                self.factors[i, kinds[kind], j] = v / nominal
        self.calibrated[rows] = True
        # re-plan locally on the calibrated models: Gauss-Newton on the setpoint
        s = self.setpoint[rows].copy()
        goal = st.goal[rows]
        j, k = np.triu_indices(N, 1)
        for _ in range(self.replan_iters):
            tip, J = self._model_jacobian(s, rows)
            ds = np.stack([np.linalg.pinv(J[r], rcond=1e-9) @ (goal[r] - tip[r])
                           for r in range(len(rows))])
            ds *= np.minimum(1.0, 1.0 / np.max(np.abs(ds) / self.replan_step, -1,
                                               initial=1e-15))[:, None]
            new = s + ds
            new[:, :N], _, _ = self.robot.project(new[:, :N])
            off = ((np.abs(_wrap(new[:, N + k] - new[:, N + j])) > self.edge)
                   | (_windows(new[:, N:]) != _windows(s[:, N:]))).any(-1)
            new[off, N:] = s[off, N:]
            s = new
        g, ok = self._model_load(s, rows)
        self.setpoint[rows[ok]], self.g_set[rows[ok]] = s[ok], g[ok]

    def __call__(self, obs) -> np.ndarray:
        st = read_state(self.venv)
        self.replan(st)
        for i in range(len(self.history)):
            self.history[i].append((st.x[i].copy(), st.tip[i].copy()))
        due = np.flatnonzero(~self.calibrated & (np.array([len(h) for h in self.history])
                                                 >= self.calibrate_after))
        if len(due):
            self._recalibrate(due, st)
        return super().__call__(obs)


class OperationalSpaceController:
    """``tau = g(x) + B J^+ (k / h) (goal - tip)``, clipped to the action range.

    ``J^+ = B^-1 J^T (J B^-1 J^T + lambda I)^-1`` is the damped pseudo-inverse weighted by the
    carriage mobilities ``B^-1`` (the least-effort velocity that moves the tip along the error);
    ``k`` is the fraction of the error corrected per control period ``h`` and ``lambda``
    [m²/(N·s)]·scale damps it near singular configurations.
    """

    def __init__(self, venv, gain: float = 0.7, damping: float = 1e-3,
                 max_step: float = 5e-3):
        self.venv, self.gain, self.damping, self.max_step = venv, gain, damping, max_step
        self.robot = env_robot(venv)
        self.compensated = _force_env(venv, "OperationalSpaceController")

    def __call__(self, obs) -> np.ndarray:
        st, robot = read_state(self.venv), self.robot
        h = st.control_period
        tip, J = tip_jacobian(robot, st.x, initial=_warm(st.q))
        err = st.goal - tip
        norm = np.linalg.norm(err, axis=-1, keepdims=True)
        err = err * np.minimum(1.0, self.max_step / np.maximum(norm, 1e-12))  # limit the stride
        Minv = 1.0 / st.damping                                           # (2N,)
        JM = J * Minv[None, None, :]                                      # J B^-1
        A = JM @ np.swapaxes(J, 1, 2)                                     # (B, 3, 3)
        lam = self.damping * np.trace(A, axis1=1, axis2=2)[:, None, None] / 3 + 1e-18
        y = np.linalg.solve(A + lam * np.eye(3), (self.gain / h * err)[..., None])[..., 0]
        xdot = Minv * np.einsum("bij,bi->bj", J, y)                       # B^-1 J^T y
        tau = st.g + st.damping * xdot
        return _action(tau, st, self.compensated)


class ZeroPolicy:
    """Action 0: no actuator force (the robot relaxes under its elastic forces)."""

    def __init__(self, venv):
        self.shape = (venv.num_envs, venv.action_space.shape[0])

    def __call__(self, obs) -> np.ndarray:
        return np.zeros(self.shape, np.float32)


class RandomPolicy:
    """Uniform random actions (seeded)."""

    def __init__(self, venv, seed: int = 0):
        self.shape = (venv.num_envs, venv.action_space.shape[0])
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs) -> np.ndarray:
        return self.rng.uniform(-1, 1, self.shape).astype(np.float32)


#: Baselines by name (``training.evaluate --baselines``, ``residual: {base: ...}``).
CONTROLLERS = {"pts": PlanThenServoController, "pts_feedback": PlanThenServoFeedbackController,
               "pts_adaptive": PlanThenServoAdaptiveController,
               "osc": OperationalSpaceController,
               "zero": ZeroPolicy, "random": RandomPolicy}
