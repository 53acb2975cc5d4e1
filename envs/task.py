"""The reaching task on a batch of robots: goals, observations, rewards, episode logic.

:class:`ReachBatch` is shared by the single-robot Gymnasium environment
(:class:`envs.reach_env.CTRReachEnv`, ``B = 1``) and the natively batched SB3 ``VecEnv``
(:class:`envs.vec_env.CTRReachVecEnv`): both are thin faces over the same arrays, so they cannot
drift apart.

Observation (``observation`` entry, float32, every entry clipped to ``[-OBS_BOUND, OBS_BOUND]``),
in this order for ``N`` tubes:

====================  =====  ==================================================================
entry                 size   meaning
====================  =====  ==================================================================
sin alpha, cos alpha  2N     rotation of each tube's base
D (normalized)        N      insertion mapped from ``[insertion_min, insertion_max]`` to [-1, 1]
g / scale             2N     elastic actuator forces/torques ``dU*/dx`` over the action scale
previous action       2N     the last action (zeros after reset)
xdot (normalized)     2N     carriage velocities / target speeds (``second_order`` only)
tip / reach           3      tip position [m] over the robot's reach (base frame)
(goal - tip) / reach  3      the error vector over the whole workspace
tanh(error / scale)   3      the error near the goal: ``tanh((goal - tip) / error_scale)``
                             (default 10 mm: 1 mm reads 0.0997, 0.1 mm 0.01; far goals
                             saturate at +-1, the entry above still gives their direction)
stability margin      1      ``tanh(lambda_min / margin_scale)``
at limit              2N     lower and upper stroke-limit flags of each insertion carriage
rotation stiffness    1      ``observe_stiffness`` only: ``tanh(k_rel / stiffness_scale)``, the
                             smallest eigenvalue ``k_rel`` of the actuator stiffness's rotation
                             block on relative rotations (:func:`relative_rotation_stiffness`);
                             negative where the torque-controlled robot is unstable, which
                             preceded every snap of the force agent (benchmarks/snap_causes.py)
====================  =====  ==================================================================

Goals (float32, ``(4,)``): ``achieved_goal = (tip [m], snap flag)``, ``desired_goal = (goal [m],
0)``. The snap flag is 1 in the observation that follows a penalized snap (``snap_terminated``),
``UNSTABLE_FLAG`` (0.5) after a statically unstable step when ``stiffness_penalty`` is on
(:class:`ReachConfig`; the penalty is recomputed from it like the snap's), and 0 otherwise;
:func:`compute_reward` adds ``snap_penalty`` where the ACHIEVED flag is 1 and measures the
distance on the first three entries only (a relabelled desired goal may carry a 1: it is
ignored). The flag rides in ``achieved_goal`` because SB3's ``HerReplayBuffer`` keeps
the goals of every stored transition but, by default (``copy_info_dict=False``), not its
``info``: with the flag in ``info`` a snap step relabelled with the goal it reached read reward
0 and done, a rewarded escape. Measured sampling cost of the alternatives
(``benchmarks/her_snap.py``) in docs/environments.md. The tolerance is not in the observation:
HER recomputes rewards with the current tolerance (set_tolerance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from gymnasium import spaces
from gymnasium.error import ResetNeeded
from gymnasium.utils import seeding

from .dynamics import CarriageModel, RobotBatch
from .plant import SOLVERS, Plants, PlantVariation
from .robots import Robot

__all__ = ["ReachConfig", "ReachBatch", "RobotState", "RewardTerms", "OBS_BOUND",
           "compute_reward", "reward_terms", "her_reward", "relative_rotation_stiffness",
           "stiffness_scale", "UNSTABLE_FLAG", "STIFFNESS_HAZARD"]

OBS_BOUND = 10.0
#: ``achieved_goal[3]`` of a step that ends statically unstable (``stiffness_penalty``); a
#: penalized snap reads 1, any other step 0
UNSTABLE_FLAG = 0.5
#: the default ``ReachConfig.stiffness_hazard``: a step is statically unstable where
#: ``k_rel < STIFFNESS_HAZARD * stiffness_scale``: below the round-off of the rigid common
#: rotation (a quarter of random force-control states read ``k_rel = 0`` to 1e-12) and the
#: shallow negative values of states far from any fold
STIFFNESS_HAZARD = -0.01


def relative_rotation_stiffness(K: np.ndarray) -> np.ndarray:
    """``(B,)`` [N·m/rad] the smallest eigenvalue of the rotation block ``dtau_alpha/dalpha``
    of the actuator stiffness ``K (B, 2N, 2N)`` (insertions first, then rotations; symmetrized
    here) restricted to relative rotations, the directions orthogonal to turning every tube
    together. That common rotation is rigid without a tip load (its eigenvalue is 0 up to
    round-off and would mask the others); ``k_rel < 0`` is a relative rotation in which the
    robot is unstable under constant torques, the instability that precedes a snap. For
    ``N = 2`` it is ``v^T K_aa v`` with ``v = (1, -1)/sqrt(2)``; a one-tube robot has no
    relative rotation and gets zeros. Non-finite ``K`` rows give NaN."""
    K = np.asarray(K, dtype=np.float64)
    if K.ndim != 3 or K.shape[-1] != K.shape[-2] or K.shape[-1] % 2:
        raise ValueError(f"K must be (B, 2N, 2N), got shape {K.shape}")
    N = K.shape[-1] // 2
    if N == 1:
        return np.zeros(K.shape[0])
    R = K[:, N:, N:]
    R = 0.5 * (R + np.swapaxes(R, -1, -2))
    # an orthonormal basis of the complement of (1, ..., 1): the last N - 1 columns of a QR
    # of [1 | I] (the first column spans the common rotation)
    Q = np.linalg.qr(np.concatenate([np.ones((N, 1)), np.eye(N)], -1))[0][:, 1:N]
    out = np.full(K.shape[0], np.nan)
    ok = np.isfinite(R).all((-1, -2))
    if ok.any():
        out[ok] = np.linalg.eigvalsh(Q.T @ R[ok] @ Q)[:, 0]
    return out


def stiffness_scale(robot: Robot) -> float:
    """[N·m/rad] the normalization of the rotation-stiffness observation entry: a quarter of
    the robot's mean torque scale per radian (0.0365 for the Fig. 3 robot, where the median
    ``k_rel`` over random force-control states is 0.033 and its maximum 0.072)."""
    return 0.25 * float(np.mean(robot.torque_scale))


@dataclass(frozen=True)
class ReachConfig:
    """Task options (all have defaults; see the environment docs).

    Attributes:
        control: ``"force"`` (actions are actuator forces/torques) or ``"joint"`` (actions are
            joint increments, the literature's convention).
        reward: ``"sparse"`` (``-1`` until within tolerance, ``0`` inside), ``"dense"``
            (``-d / dense_scale``, ``+1`` inside the tolerance) or ``"shaped"`` (the sparse
            reward minus ``shaping_weight * min(d / dense_scale, 1)``: a bounded pull towards
            the goal's centre that only distinguishes distances below ``dense_scale``, so
            that far from the goal it is the sparse reward scaled by ``1 + shaping_weight``).
        tolerance: [m] success radius (default 1 mm); change at run time with
            ``set_tolerance`` (curricula).
        dense_scale: [m] distance normalization of the dense and shaped rewards.
        shaping_weight: weight of the shaped reward's distance term (finite, >= 0; default
            0.5). With it the value of never reaching is ``-(1 + shaping_weight) / (1 -
            gamma)``: ``snap_penalty`` must lie below that for a snap not to pay.
        max_joint_step: ``(insertion [m], rotation [rad])`` per step at action ``+-1`` (joint
            control; default 1 mm and 5 deg).
        snap_mode: ``"terminate"`` (default: end the episode with ``snap_penalty`` added) or
            ``"continue"`` (flag it in ``info`` and go on).
        snap_penalty: reward added at a terminating snap (default ``-60``: below
            ``-1 / (1 - gamma)``, the value of never reaching the goal under the sparse reward,
            for every gamma up to 0.983, so that ending an episode by a snap never pays;
            the former ``-20`` matched gamma 0.95 and made snaps a rewarded escape at 0.98).
        goal_min_distance: [m] goals are at least this far from the start tip (finite, >= 0;
            one that cannot be met raises, see :class:`ReachBatch`).
        compensation: force control only. ``False`` (default): raw force actions,
            ``tau = scale * a``: the carriages integrate any mismatch with the elastic load
            ``g(x)`` (a policy must reproduce ``g`` to about 1 % to hold still). ``True``: the
            action is an offset on the elastic load, ``tau = g(x) + scale * a`` with ``g`` at
            the start of the step (held over it, like a controller sampling at the control
            rate): ``a = 0`` holds the robot still. ``scale`` is the robot's
            ``action_scale``, ``info["tau"]`` the applied total.
        kink_compensation: with ``compensation``, hold against the far side's force where an
            insertion carriage is parked at a kink of ``U*`` and the action pushes across it
            (:meth:`envs.dynamics.RobotBatch.compensation`), so that any push crosses the
            corner; ``False`` (default, what the shipped agents and the published results
            used): the near side's ``g(x)``, under which a push smaller than the force jump
            (1.6 N at the Fig. 3 outer tube's transition, ~93.5 mm) stays parked there.
        error_scale: [m] length of the squashed error entry of the observation (> 0,
            default 10 mm).
        plant_scale, tip_force, tip_noise: how each episode's plant differs from the
            nominal robot (:class:`envs.plant.PlantVariation`; all 0 by default: the plant
            is the robot): each tube's precurvature, ``E`` and ``G`` scaled by
            ``U(1 - plant_scale, 1 + plant_scale)``, an unknown constant tip force of
            ``U(0, tip_force)`` [N] in a uniformly random direction, Gaussian noise of
            ``tip_noise`` [m] per axis on the measured tip (observation, ``achieved_goal``
            and the reward; ``is_success`` and ``info["distance"]`` use the true tip).
        observe_stiffness: force control only. Append ``tanh(k_rel / stiffness_scale)`` to
            the observation (last entry; :func:`relative_rotation_stiffness`,
            :func:`stiffness_scale`): the actuator stiffness that the force step computes
            anyway, whose negative relative-rotation direction preceded every snap of the
            force agent. ``False`` (default): the observation the shipped agents read.
        stiffness_penalty: force control only. A reward (finite, <= 0; default 0: off) added
            at every step that ends statically unstable under torque control, its relative
            rotation stiffness ``k_rel`` below ``stiffness_hazard * stiffness_scale``
            (:func:`relative_rotation_stiffness`), the state that preceded every snap of the
            force agent: a dense signal where the snap penalty is rare. Such a step's
            ``achieved_goal[3]`` reads ``UNSTABLE_FLAG`` (0.5; 1 is a penalized snap), so
            that :func:`compute_reward` recomputes the penalty for relabelled goals.
        stiffness_hazard: the threshold of ``stiffness_penalty`` in units of
            ``stiffness_scale`` (finite, < 0; default ``STIFFNESS_HAZARD = -0.01``, just
            below zero). Lower values penalize only deep instability: about 11 % of the
            shipped agent's successful episodes END with ``k_rel < -0.01 stiffness_scale``
            (the goal lies where the robot must be held by feedback), while its snaps were
            mostly preceded by ``k_rel < -10 stiffness_scale`` (``docs/training.md``).
        solver: how the robots' equilibria are computed along an episode
            (:data:`envs.plant.SOLVERS`): ``"auto"`` (default) steps on the compiled
            control-loop solver (:meth:`torchpvs.Tracker.solve_from`) where it applies (the
            nominal robot: no plant variation), else on ``torchpvs.solve``; ``"torch"``
            always on ``torchpvs.solve``; ``"compiled"`` like ``"auto"`` but an error where
            the compiled path does not apply. Both compute the same equilibria (the same
            Newton iterations; tips and coordinates equal, forces and stiffness to rounding:
            ``tests/envs/test_solvers.py``); the compiled one is faster.
    """

    control: str = "force"
    reward: str = "sparse"
    tolerance: float = 1e-3
    dense_scale: float = 0.01
    shaping_weight: float = 0.5
    max_joint_step: tuple[float, float] = (1e-3, math.radians(5.0))
    snap_mode: str = "terminate"
    snap_penalty: float = -60.0
    goal_min_distance: float = 2e-3
    compensation: bool = False
    kink_compensation: bool = False
    error_scale: float = 0.01
    plant_scale: float = 0.0
    tip_force: float = 0.0
    tip_noise: float = 0.0
    observe_stiffness: bool = False
    stiffness_penalty: float = 0.0
    stiffness_hazard: float = STIFFNESS_HAZARD
    solver: str = "auto"

    @property
    def plant(self) -> PlantVariation:
        return PlantVariation(self.plant_scale, self.tip_force, self.tip_noise)

    def __post_init__(self) -> None:
        self.plant  # noqa: B018 - validates the three plant fields by name
        if self.control not in ("force", "joint"):
            raise ValueError(f"control must be 'force' or 'joint', got {self.control!r}")
        if self.reward not in ("sparse", "dense", "shaped"):
            raise ValueError(f"reward must be 'sparse', 'dense' or 'shaped', got "
                             f"{self.reward!r}")
        if not (_real(self.shaping_weight) and self.shaping_weight >= 0):
            raise ValueError(f"shaping_weight must be a finite number >= 0, got "
                             f"{self.shaping_weight!r}")
        if self.snap_mode not in ("terminate", "continue"):
            raise ValueError(f"snap_mode must be 'terminate' or 'continue', got "
                             f"{self.snap_mode!r}")
        if not (_real(self.tolerance) and self.tolerance > 0):
            raise ValueError(f"tolerance must be a positive length [m], got {self.tolerance!r}")
        if not (_real(self.dense_scale) and self.dense_scale > 0):
            raise ValueError(f"dense_scale must be a finite length > 0 [m], got "
                             f"{self.dense_scale!r}")
        steps = self.max_joint_step
        if isinstance(steps, (str, bytes)) or not hasattr(steps, "__len__") or len(steps) != 2 \
                or not all(_real(v) and v > 0 for v in steps):
            raise ValueError(f"max_joint_step must be two finite numbers > 0 (m, rad), got "
                             f"{steps!r}")
        if not (_real(self.snap_penalty) and self.snap_penalty <= 0):
            raise ValueError(f"snap_penalty must be a finite number <= 0 (a reward added at a "
                             f"snap; > 0 would reward snapping), got {self.snap_penalty!r}")
        if not isinstance(self.compensation, (bool, np.bool_)):
            raise ValueError(f"compensation must be True or False, got {self.compensation!r}")
        if not isinstance(self.kink_compensation, (bool, np.bool_)):
            raise ValueError(f"kink_compensation must be True or False, got "
                             f"{self.kink_compensation!r}")
        if self.kink_compensation and not self.compensation:
            raise ValueError("kink_compensation=True needs compensation=True (it changes which "
                             "elastic load the compensation holds against)")
        if self.compensation and self.control != "force":
            raise ValueError(f"compensation=True needs control='force' (joint control already "
                             f"holds the elastic load), got control={self.control!r}")
        if not isinstance(self.observe_stiffness, (bool, np.bool_)):
            raise ValueError(f"observe_stiffness must be True or False, got "
                             f"{self.observe_stiffness!r}")
        if self.observe_stiffness and self.control != "force":
            raise ValueError(f"observe_stiffness=True needs control='force' (joint steps do not "
                             f"compute the actuator stiffness), got control={self.control!r}")
        if not (_real(self.stiffness_penalty) and self.stiffness_penalty <= 0):
            raise ValueError(f"stiffness_penalty must be a finite number <= 0 (a reward added "
                             f"at a statically unstable step), got {self.stiffness_penalty!r}")
        if self.stiffness_penalty != 0 and self.control != "force":
            raise ValueError(f"stiffness_penalty needs control='force' (joint steps do not "
                             f"compute the actuator stiffness), got control={self.control!r}")
        if not (_real(self.stiffness_hazard) and self.stiffness_hazard < 0):
            raise ValueError(f"stiffness_hazard must be a finite number < 0 (a threshold on "
                             f"k_rel / stiffness_scale; >= 0 would flag stable states), got "
                             f"{self.stiffness_hazard!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if not (_real(self.error_scale) and self.error_scale > 0):
            raise ValueError(f"error_scale must be a finite length > 0 [m], got "
                             f"{self.error_scale!r}")
        if not (_real(self.goal_min_distance) and self.goal_min_distance >= 0):
            raise ValueError(f"goal_min_distance must be a finite length >= 0 [m], got "
                             f"{self.goal_min_distance!r}")


@dataclass(frozen=True)
class RobotState:
    """What a controller may read of ``B`` robots: the one documented way to read state
    (:meth:`ReachBatch.state`, ``CTRReachEnv.state()``, ``CTRReachVectorEnv.state()``,
    ``CTRReachVecEnv.state()``). Every array is a float64 copy, batched over robots (``B = 1``
    for the single env); nothing here aliases the environment's internal arrays.

    Attributes:
        x: ``(B, 2N)`` actuator coordinates: insertions ``D`` [m] then base rotations
            ``alpha`` [rad], tubes outermost first (docs/conventions.md).
        v: ``(B, 2N)`` carriage velocities [m/s, rad/s] (the last substep's; zero at rest and
            in joint control between steps).
        g: ``(B, 2N)`` elastic actuation forces/torques ``dU*/dx`` [N, N·m]: the
            force/torque that holds the carriages still at ``x`` (``tau = g`` means rest).
        tip: ``(B, 3)`` [m] tip position in the base frame.
        goal: ``(B, 3)`` [m] goal position in the base frame.
        margin: ``(B,)`` stability margin (smallest eigenvalue of the scaled stiffness;
            ``<= 0`` means unstable).
        q: ``(B, nq)`` the solver coordinates of the last equilibrium; pass as ``initial=``
            to ``torchpvs.solve`` to warm-start a solve near the current state.
        damping: ``(2N,)`` [N·s/m, N·m·s/rad] carriage damping ``b`` (``b xdot = tau - g``).
        action_scale: ``(2N,)`` [N, N·m] force/torque at action ``+-1`` (``tau = a * scale``
            for raw force actions).
        control_period: [s] time per environment step.
        true_tip: ``(B, 3)`` [m] the true tip (``tip`` is the measured one; they differ with
            ``tip_noise``): for analysis, not for controllers.
        plant_factors: ``(B, 3, N)`` the plant's factors on each tube's precurvature, ``E``
            and ``G`` against the nominal robot (``env.robot``, what controllers know); ones
            without ``plant_scale``. For analysis.
        plant_tip_force: ``(B, 3)`` [N] the plant's unknown tip force. For analysis.
        stiffness: ``(B, 2N, 2N)`` the actuator stiffness ``dtau/dx`` [N/m, N, N·m/rad]
            (symmetrized, not clipped; the carriage dynamics use its positive part) of the
            plant's equilibrium at the last force-control step or reset (joint-control steps
            do not update it). A negative eigenvalue is a direction in which the robot is
            unstable under constant actuator forces and torques: it precedes a snap.
    """

    x: np.ndarray
    v: np.ndarray
    g: np.ndarray
    tip: np.ndarray
    goal: np.ndarray
    margin: np.ndarray
    q: np.ndarray
    damping: np.ndarray
    action_scale: np.ndarray
    control_period: float
    true_tip: np.ndarray | None = None
    plant_factors: np.ndarray | None = None
    plant_tip_force: np.ndarray | None = None
    stiffness: np.ndarray | None = None


ENV_ID_OF_CONTROL = {"force": "torchpvs/CTRReachForce-v0", "joint": "torchpvs/CTRReachJoint-v0"}


def registered_kwargs(control: str, kwargs: dict) -> dict:
    """The keyword arguments of an env made through the registered id of ``control``: a
    ``control=`` that names another control is refused (``gym.make(force id,
    control="joint")`` used to build a joint env under the force id)."""
    given = kwargs.get("control", control)
    if given != control:
        other = ENV_ID_OF_CONTROL.get(given) if isinstance(given, str) else None
        hint = (f"make {other!r} for {given} control" if other else
                f"control must be one of {sorted(ENV_ID_OF_CONTROL)}")
        raise ValueError(f"control={given!r} contradicts the env id "
                         f"{ENV_ID_OF_CONTROL[control]!r}, which is {control} control: {hint}, "
                         f"or leave control out")
    return {**kwargs, "control": control}


def _seed_int(v) -> bool:
    """An integer seed >= 0 (not a bool)."""
    return isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) and v >= 0


def _real(v) -> bool:
    """A finite real number (not a bool, not a string)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
        v, (bool, np.bool_)) and math.isfinite(v)


class RewardTerms(NamedTuple):
    """The parts of a reward (:func:`reward_terms`), each ``(...,)`` float64; the reward is
    ``(distance + snap).astype(float32)``. The step ``info`` reports them as
    ``reward_distance``, ``reward_snap`` and ``reward_stiffness``.

    Attributes:
        distance: the goal term: ``"sparse"`` ``-1`` outside the tolerance, ``0`` inside;
            ``"dense"`` ``-d / dense_scale``, plus ``1`` inside; ``"shaped"`` the sparse term
            minus ``shaping_weight * min(d / dense_scale, 1)`` (``d`` [m] the distance of the
            goals' positions).
        snap: ``snap_penalty`` where the snap flag is set (the achieved goal's 4th entry is
            1, or ``snapped``), else ``0``.
        stiffness: ``stiffness_penalty`` where the step ended statically unstable and did not
            snap (the achieved goal's 4th entry is ``UNSTABLE_FLAG``, or ``unstable``), else
            ``0``.
    """

    distance: np.ndarray
    snap: np.ndarray
    stiffness: np.ndarray


def reward_terms(achieved_goal, desired_goal, tolerance: float, kind: str,
                 dense_scale: float, snapped=None, snap_penalty: float = 0.0,
                 shaping_weight: float = 0.5, unstable=None,
                 stiffness_penalty: float = 0.0) -> tuple[np.ndarray, RewardTerms]:
    """:func:`compute_reward` and its parts: ``(reward (...,) float32, RewardTerms)``."""
    ag = np.asarray(achieved_goal, np.float64)
    dg = np.asarray(desired_goal, np.float64)
    d = np.linalg.norm(ag[..., :3] - dg[..., :3], axis=-1)
    inside = d <= tolerance
    if kind == "dense":
        r = -d / dense_scale + inside
    else:
        r = -(~inside).astype(np.float64)
        if kind == "shaped":
            r = r - shaping_weight * np.minimum(d / dense_scale, 1.0)
    level = ag[..., 3] if ag.shape[-1] == 4 else np.zeros(d.shape)
    flag = level > 0.75
    if snapped is not None:
        flag = flag | np.asarray(snapped, dtype=bool)
    hazard = np.abs(level - UNSTABLE_FLAG) < 0.25
    if unstable is not None:
        hazard = hazard | np.asarray(unstable, dtype=bool)
    snap = snap_penalty * flag
    stiff = stiffness_penalty * (hazard & ~flag)
    return (r + snap + stiff).astype(np.float32), RewardTerms(distance=r, snap=snap,
                                                              stiffness=stiff)


def compute_reward(achieved_goal, desired_goal, tolerance: float, kind: str,
                   dense_scale: float, snapped=None, snap_penalty: float = 0.0,
                   shaping_weight: float = 0.5, unstable=None,
                   stiffness_penalty: float = 0.0) -> np.ndarray:
    """Vectorized reward over the last axis -> ``(...,)`` float32.

    Goals are ``(..., 3)`` positions [m] or the environments' ``(..., 4)`` goals whose 4th
    entry is the snap flag: the distance uses the positions, the snap penalty is added where
    the achieved flag is 1 or ``snapped`` (e.g. from ``info``) is true, the stiffness penalty
    where it is ``UNSTABLE_FLAG`` or ``unstable`` is true (and no snap). Its parts:
    :func:`reward_terms`."""
    return reward_terms(achieved_goal, desired_goal, tolerance, kind, dense_scale, snapped,
                        snap_penalty, shaping_weight, unstable, stiffness_penalty)[0]


def info_field(info, key: str, shape) -> np.ndarray | None:
    """``info[key]`` from a dict, or from a list/array of dicts (HER with
    ``copy_info_dict=True``), else ``None``."""
    if info is None:
        return None
    if isinstance(info, dict):
        return np.asarray(info[key]) if key in info else None
    items = list(np.asarray(info, dtype=object).reshape(-1))
    if not items or not all(isinstance(i, dict) and key in i for i in items):
        return None
    return np.array([bool(i[key]) for i in items]).reshape(shape)


def her_reward(task: ReachBatch, achieved_goal, desired_goal, info) -> np.ndarray:
    """``compute_reward`` of every environment face (one function, so they cannot differ):
    the goals' snap flag, or ``info["snap_terminated"]`` where HER passes infos."""
    snapped = info_field(info, "snap_terminated", np.shape(achieved_goal)[:-1])
    c = task.config
    return compute_reward(achieved_goal, desired_goal, task.tolerance, c.reward, c.dense_scale,
                          snapped, c.snap_penalty, c.shaping_weight,
                          stiffness_penalty=c.stiffness_penalty)


class ReachBatch:
    """``B`` reaching tasks on one :class:`~envs.dynamics.RobotBatch`.

    Goals: the tip of a second stable equilibrium sampled like the start, redrawn up to
    ``GOAL_DRAWS`` times while closer than ``config.goal_min_distance`` to the start tip; a
    distance beyond ``2 x robot.reach`` raises at construction, one not met after the redraws
    raises ``ValueError`` at reset (it is never silently relaxed).

    Randomness, one rule for every face: robot ``i`` has its own episode generator
    (``np_randoms[i]``, what ``np_random`` is to a ``gymnasium.Env``); :meth:`seed` with an
    integer ``s`` seeds it as ``gymnasium.utils.seeding.np_random(s + i)``, Gymnasium's
    ``SyncVectorEnv`` and SB3's ``DummyVecEnv`` convention, and each reset of robot ``i``
    samples its start and goal from a generator drawn from ``np_randoms[i]`` exactly as
    :class:`envs.CTRReachEnv` draws one from its ``np_random``. So robot ``i`` of a batch
    seeded with ``s`` runs the episodes of ``gym.make(id).reset(seed=s + i)`` and its later
    resets (up to solver round-off).

    User goals: ``reset(idx, goal=...)`` takes the goals [m] instead of sampling them (checked
    by :meth:`check_goal`); their actuation preimage is unknown, so :meth:`travel_steps` is NaN
    for them. :meth:`set_next_goal` queues such a goal for a robot's next reset, autoresets
    included (a training curriculum's hook: the vector faces reset finished robots themselves).
    Stepping a robot that was never reset raises ``gymnasium.error.ResetNeeded``.
    """

    GOAL_DRAWS = 20

    def __init__(self, robot: Robot, config: ReachConfig, carriage: CarriageModel,
                 batch_size: int):
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
                or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        self.robot, self.config, self.carriage = robot, config, carriage
        self.B, self.N = batch_size, robot.n_tubes
        self.plants = Plants(robot, config.plant, batch_size, solver=config.solver)
        self.robots = RobotBatch(robot, carriage, batch_size, plants=self.plants)
        self.measured_tip = np.zeros((batch_size, 3))   # tip + measurement noise
        self.tolerance = config.tolerance
        self.goal = np.zeros((batch_size, 3))
        self.goal_actuation = np.zeros((batch_size, 2 * robot.n_tubes))  # one preimage of goal
        self.next_goal = np.full((batch_size, 3), np.nan)   # set_next_goal's; NaN: none
        self.next_start = np.full((batch_size, 2 * robot.n_tubes), np.nan)  # set_next_start's
        self.episode_start = np.full((batch_size, 2 * robot.n_tubes), np.nan)  # x at reset
        self.prev_action = np.zeros((batch_size, 2 * self.N))
        self.snap_flag = np.zeros(batch_size)   # 1 after a penalized snap (achieved_goal[3])
        # per robot: the episode generator (an env's np_random) and the one the current
        # episode samples from (drawn from the former at each reset)
        self.np_randoms = [seeding.np_random()[0] for _ in range(batch_size)]
        self.rngs = [np.random.default_rng(g.integers(2**63)) for g in self.np_randoms]
        self.ready = np.zeros(batch_size, dtype=bool)   # reset at least once
        N = self.N
        # where (goal - tip) / reach starts: after the actuation, forces, action, velocity and
        # tip entries (the two goal-relative entries, 6 values, follow; relabel_observation)
        self.goal_entries = 2 * N + N + 2 * N + 2 * N + (
            2 * N if carriage.kind == "second_order" else 0) + 3
        self.obs_size = self.goal_entries + 3 + 3 + 1 + 2 * N + int(config.observe_stiffness)
        self.stiffness_scale = stiffness_scale(robot)
        # goals: the tip within 2 x reach of the orifice, then the snap flag in [0, 1]
        goal_low = np.array([-2 * robot.reach] * 3 + [0.0], np.float32)
        goal_high = np.array([2 * robot.reach] * 3 + [1.0], np.float32)
        self.observation_space = spaces.Dict({
            "observation": spaces.Box(-OBS_BOUND, OBS_BOUND, (self.obs_size,), np.float32),
            "achieved_goal": spaces.Box(goal_low, goal_high, (4,), np.float32),
            "desired_goal": spaces.Box(goal_low, goal_high, (4,), np.float32),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (2 * N,), np.float32)
        self.speeds = np.concatenate([np.full(N, carriage.insertion_speed),
                                      np.full(N, carriage.rotation_speed)])
        # every tip lies within the longest exposed length (robot.reach) of the orifice, so two
        # tips are never more than 2 reach apart
        if config.goal_min_distance > 2.0 * robot.reach:
            raise ValueError(
                f"goal_min_distance ({config.goal_min_distance:g} m) cannot be met: every tip "
                f"lies within the robot's reach ({robot.reach:.4g} m) of the orifice, so no "
                f"goal is more than 2 x reach = {2.0 * robot.reach:.4g} m from the start")

    # -- seeding and sampling -------------------------------------------------------------------
    def seed(self, seed, idx=None) -> None:
        """Seed the episode generators of robots ``idx`` (default: all): an integer ``s`` gives
        robot ``i`` the seed ``s + i`` (``gymnasium.utils.seeding.np_random(s + i)``, as
        ``SyncVectorEnv`` and SB3's ``DummyVecEnv`` seed their sub-environments); a sequence
        gives one seed (an integer >= 0 or ``None``) per robot of the batch; ``None`` (or a
        ``None`` entry) leaves a generator as it is (Gymnasium's ``reset(seed=None)``)."""
        idx = np.arange(self.B) if idx is None else np.asarray(idx, dtype=int)
        if seed is None:
            return
        if _seed_int(seed):
            seeds = [int(seed) + i for i in range(self.B)]
        elif isinstance(seed, (list, tuple, np.ndarray)):
            seeds = list(seed)
            if len(seeds) != self.B:
                raise ValueError(f"seed as a list must have one entry per robot (num_envs = "
                                 f"{self.B}), got length {len(seeds)}")
        else:
            raise ValueError(f"seed must be an integer >= 0, a list of num_envs = {self.B} "
                             f"such seeds (or None entries), or None; got {seed!r}")
        for i, s in enumerate(seeds):
            if not (s is None or _seed_int(s)):
                raise ValueError(f"seed must be an integer >= 0 or None, got {s!r} for robot "
                                 f"{i}")
        for i in idx:
            if seeds[i] is not None:
                self.np_randoms[i] = seeding.np_random(int(seeds[i]))[0]

    def check_goal(self, goal, n: int, name: str = "options['goal']") -> np.ndarray:
        """A user goal (``reset(options={"goal": ...})``) as ``(n, 3)`` float64 [m]: one
        position ``(3,)`` for all ``n`` robots or one per robot ``(n, 3)``, in the base frame
        (origin at the orifice), finite and within ``2 x robot.reach`` of the orifice (the
        goal space; whether the tip can reach it is not checked). Raises ``ValueError``."""
        g = np.asarray(goal)
        if g.dtype == object or not (np.issubdtype(g.dtype, np.floating)
                                     or np.issubdtype(g.dtype, np.integer)):
            raise ValueError(f"{name} must be a real 3-vector [m] (or one per robot, "
                             f"({n}, 3)), got {goal!r}")
        g = g.astype(np.float64)
        if g.shape == (3,):
            g = np.broadcast_to(g, (n, 3)).copy()
        if g.shape != (n, 3):
            raise ValueError(f"{name} must have shape (3,) or ({n}, 3) (a position "
                             f"[m] in the base frame), got shape {np.shape(goal)}")
        if not np.isfinite(g).all():
            raise ValueError(f"{name} must be finite, got {goal!r}")
        limit = 2.0 * self.robot.reach
        far = np.linalg.norm(g, axis=-1) > limit
        if far.any():
            raise ValueError(f"{name} must lie within 2 x reach = {limit:.4g} m of the "
                             f"orifice (the base frame's origin), got {g[far][0].tolist()} at "
                             f"{float(np.linalg.norm(g[far][0])):.4g} m")
        return g

    def sample_stable(self, idx: np.ndarray, per_robot: int = 2, max_rounds: int = 10):
        """For each robot in ``idx``, ``per_robot`` stable, converged equilibria sampled
        uniformly in actuator space with that robot's generator (one batched solve per round;
        rejected samples are redrawn). Returns ``(x (len, per_robot, 2N), tips, eq, rows)`` where
        ``eq``/``rows`` give the Equilibrium rows of the first sample of each robot."""
        k = len(idx)
        xs = np.zeros((k, per_robot, 2 * self.N))
        tips = np.zeros((k, per_robot, 3))
        first_eq, first_rows = [None] * k, [None] * k
        need = [(i, s) for i in range(k) for s in range(per_robot)]
        for _ in range(max_rounds):
            if not need:
                break
            cand = np.stack([self.robot.sample_actuation(self.rngs[idx[i]], 1)[0]
                             for i, _ in need])
            eq = self.plants.solve(cand, idx[[i for i, _ in need]])
            self.robots.solves += 1
            ok = (eq.converged & eq.stable).numpy()
            tip = eq.tip_position.numpy()
            rest = []
            for r, (i, s) in enumerate(need):
                if ok[r]:
                    xs[i, s], tips[i, s] = cand[r], tip[r]
                    if s == 0:
                        first_eq[i], first_rows[i] = eq, r
                else:
                    rest.append((i, s))
            need = rest
        if need:
            raise RuntimeError(f"could not sample stable equilibria for robots "
                               f"{sorted({int(idx[i]) for i, _ in need})} in {max_rounds} rounds")
        return xs, tips, first_eq, first_rows

    RESET_OPTIONS = ("goal", "tolerance")

    def reset_options(self, options, n: int, extra: tuple[str, ...] = ()):
        """Check ``reset(options=...)`` for ``n`` robots before anything changes: returns
        ``(tolerance or None, goal (n, 3) or None)``. Known keys: ``"goal"`` (a position [m],
        see :meth:`check_goal`), ``"tolerance"`` (the success radius [m] from now on, as
        :meth:`set_tolerance`) and the face's ``extra`` keys; any other key raises
        ``ValueError`` naming it (a misspelt option is never silently ignored)."""
        if options is None:
            return None, None
        if not isinstance(options, dict):
            raise ValueError(f"options must be a dict or None, got {type(options).__name__}")
        known = self.RESET_OPTIONS + tuple(extra)
        unknown = [k for k in options if k not in known]
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}: the options are "
                             f"{list(known)}")
        tol = options.get("tolerance")
        if tol is not None:
            _check_tolerance(tol)
        goal = options.get("goal")
        return tol, (None if goal is None else self.check_goal(goal, n))

    def reset(self, idx: np.ndarray, goal=None) -> None:
        """New start state (at rest) and goal for robots ``idx``: each draws its sampling
        generator from its episode generator (``np_randoms``), then samples a stable start and
        (without ``goal``) a goal; ``goal`` (``(3,)`` or ``(len(idx), 3)`` [m], see
        :meth:`check_goal`) replaces the sampled goal (``goal_min_distance`` does not apply;
        the start is the one the same generator gives without it). Without ``goal``, a robot
        with a goal queued by :meth:`set_next_goal` takes that one (and the queue empties)."""
        idx = np.asarray(idx, dtype=int)
        if len(idx) == 0:
            return
        if goal is None:
            queued = np.isfinite(self.next_goal[idx, 0])
            if queued.any():
                goals = self.next_goal[idx[queued]].copy()
                self.next_goal[idx[queued]] = np.nan
                self.reset(idx[~queued])
                self.reset(idx[queued], goal=goals)
                return
        user_goal = None if goal is None else self.check_goal(goal, len(idx))
        starts = self.next_start[idx].copy()
        self.next_start[idx] = np.nan
        for i in idx:
            self.rngs[i] = np.random.default_rng(self.np_randoms[i].integers(2**63))
        self.plants.draw(idx, self.rngs)
        # two samples either way, so that a user goal keeps the start the seed gives
        xs, tips, eqs, rows = self.sample_stable(idx, per_robot=2)
        if user_goal is not None:
            goal, goal_x = user_goal, np.full((len(idx), 2 * self.N), np.nan)
            close = np.zeros(len(idx), dtype=bool)
        else:
            # start = sample 0, goal = tip of sample 1 (resampled while too close to the start)
            goal = tips[:, 1]
            goal_x = xs[:, 1]
            close = np.linalg.norm(goal - tips[:, 0], axis=-1) < self.config.goal_min_distance
        for i in np.flatnonzero(close):
            farthest = float(np.linalg.norm(goal[i] - tips[i, 0]))
            for _ in range(self.GOAL_DRAWS):
                x2, t2, _, _ = self.sample_stable(idx[i:i + 1], per_robot=1)
                dist = float(np.linalg.norm(t2[0, 0] - tips[i, 0]))
                farthest = max(farthest, dist)
                if dist >= self.config.goal_min_distance:
                    goal[i], goal_x[i] = t2[0, 0], x2[0, 0]
                    break
            else:
                raise ValueError(
                    f"goal_min_distance ({self.config.goal_min_distance:g} m) cannot be met: "
                    f"{self.GOAL_DRAWS + 1} goals drawn for robot {int(idx[i])} were all "
                    f"closer to its start tip (farthest {farthest:.4g} m); lower "
                    f"goal_min_distance")
        # start states: one Equilibrium per solve round; set them per source batch
        by_eq: dict[int, tuple] = {}
        for i, (e, r) in enumerate(zip(eqs, rows, strict=True)):
            by_eq.setdefault(id(e), (e, [], []))[1].append(i)
            by_eq[id(e)][2].append(r)
        for e, members, r in by_eq.values():
            self.robots.set_state(idx[members], xs[members, 0], eq=e, rows=np.array(r))
        self._start_at(idx, starts)
        self.episode_start[idx] = self.robots.x[idx]
        self.goal[idx] = goal
        self.goal_actuation[idx] = goal_x
        self.prev_action[idx] = 0.0
        self.snap_flag[idx] = 0.0
        self.ready[idx] = True
        self._measure(idx)

    def set_next_goal(self, idx, goal) -> None:
        """Queue ``goal`` (``(3,)`` or ``(len(idx), 3)`` [m], checked as :meth:`check_goal`)
        for the next reset of robots ``idx``, an autoreset included, as if it had been passed
        to that reset; ``goal=None`` clears the queue. A queued goal is used once. For
        curricula that choose goals while training (``training.callbacks.FailedGoalReplay``):
        the vector envs reset finished robots inside ``step``, where no options reach them."""
        idx = np.asarray(idx, dtype=int).reshape(-1)
        if goal is None:
            self.next_goal[idx] = np.nan
            return
        self.next_goal[idx] = self.check_goal(goal, len(idx), name="next goal")

    def set_next_start(self, idx, x) -> None:
        """Queue a start state ``x`` (``(2N,)`` or ``(len(idx), 2N)``: insertions [m] then
        rotations [rad], at rest) for the next reset of robots ``idx``, an autoreset included;
        ``x=None`` clears the queue. A queued start is used once, in place of the sampled one
        (the generators draw as without it, so later episodes do not change), if the robot's
        plant is a converged, stable equilibrium there; otherwise the sampled start stays.
        Insertions are projected onto the feasible set as in any placement. For curricula
        that replay the episodes an agent failed (``training.callbacks.FailedGoalReplay``
        with ``with_start=True``); the queued goal (:meth:`set_next_goal`) is separate."""
        idx = np.asarray(idx, dtype=int).reshape(-1)
        if x is None:
            self.next_start[idx] = np.nan
            return
        x = np.asarray(x, dtype=np.float64)
        if x.shape == (2 * self.N,):
            x = np.broadcast_to(x, (len(idx), 2 * self.N))
        if x.shape != (len(idx), 2 * self.N):
            raise ValueError(f"next start must have shape ({2 * self.N},) or "
                             f"({len(idx)}, {2 * self.N}) (insertions then rotations), "
                             f"got {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError("next start must be finite (insertions [m], rotations [rad])")
        self.next_start[idx] = x

    def _start_at(self, idx: np.ndarray, starts: np.ndarray) -> None:
        """Place the robots of ``idx`` whose row of ``starts`` is finite (queued by
        :meth:`set_next_start`) there, where their plant is converged and stable."""
        q = np.isfinite(starts[:, 0])
        if not q.any():
            return
        x = starts[q].copy()
        x[:, :self.N] = self.robot.project(x[:, :self.N])[0]
        eq = self.plants.solve(x, idx[q])
        self.robots.solves += 1
        ok = (eq.converged & eq.stable).numpy()
        if ok.any():
            self.robots.set_state(idx[q][ok], x[ok], eq=eq, rows=np.flatnonzero(ok))

    def _measure(self, idx) -> None:
        """The measured tip of robots ``idx``: the true tip plus ``tip_noise`` per axis, from
        each robot's episode generator."""
        idx = np.asarray(idx, dtype=int)
        self.measured_tip[idx] = self.robots.tip[idx]
        sd = self.config.tip_noise
        if sd > 0:
            self.measured_tip[idx] += np.stack([self.rngs[i].normal(0.0, sd, 3) for i in idx])

    def reset_info(self, i: int) -> dict:
        """The ``info`` of a reset of robot ``i`` (every face: the single env's ``reset``,
        the vector faces after a reset or an autoreset)."""
        d = float(np.linalg.norm(self.robots.tip[i] - self.goal[i]))
        return {"is_success": bool(self._goal_distance32()[i] <= self.tolerance), "distance": d,
                "snapped": False, "solver_failure": False}

    @staticmethod
    def info_of(infos: dict[str, np.ndarray], i: int) -> dict:
        """Robot ``i``'s entry of :meth:`step`'s batched ``infos`` as a single env's ``info``:
        Python scalars for per-robot scalars, array copies for per-robot vectors."""
        return {k: (v[i].copy() if v.ndim > 1 else v[i].item()) for k, v in infos.items()}

    @staticmethod
    def info_list(infos: dict[str, np.ndarray], n: int) -> list[dict]:
        """The ``n`` robots' :meth:`info_of`, the scalars converted once per key
        (``tolist``: the same Python scalars as ``item``, without a call per robot and
        key)."""
        cols = {k: v.tolist() if v.ndim == 1 else None for k, v in infos.items()}
        return [{k: (v[i].copy() if cols[k] is None else cols[k][i]) for k, v in infos.items()}
                for i in range(n)]

    def _goal_distance32(self) -> np.ndarray:
        """``(B,)`` distance from the float32 goals of the observation (what
        ``compute_reward`` sees), so that the step reward, ``is_success`` and
        ``compute_reward(achieved_goal, desired_goal)`` agree to the bit."""
        tip = self.robots.tip.astype(np.float32).astype(np.float64)
        goal = self.goal.astype(np.float32).astype(np.float64)
        return np.linalg.norm(tip - goal, axis=-1)

    def travel_steps(self, idx=None) -> np.ndarray:
        """Control periods the actuators need, at their largest step per period
        (:meth:`max_step_per_period`), to move from the current actuation to the sampled
        preimage of the goal (rotations wrapped): a lower
        bound on the time to reach the goal that way (``(B,)``). Optimistic as a measure of
        what is reachable: an insertion against the elastic load is slower, and the wrapped
        rotation may pass +-180 deg (``benchmarks/reach_ceiling.py`` searches the whole
        solution set with loaded speeds). NaN for a user goal (``options["goal"]``: no
        preimage was sampled)."""
        idx = np.arange(self.B) if idx is None else idx
        d = self.goal_actuation[idx] - self.robots.x[idx]
        d[:, self.N:] = np.angle(np.exp(1j * d[:, self.N:]))
        return (np.abs(d) / self.max_step_per_period()).max(-1)

    def max_step_per_period(self) -> np.ndarray:
        """``(2N,)`` the most each actuator coordinate can move in one control period [m,
        rad]: the joint increment at action ``+-1`` under joint control, the carriage's
        full-scale (unloaded) speed times the period under force control."""
        if self.config.control == "joint":
            N = self.N
            return np.concatenate([np.full(N, self.config.max_joint_step[0]),
                                   np.full(N, self.config.max_joint_step[1])])
        return self.speeds * self.carriage.control_period

    # -- stepping -----------------------------------------------------------------------------
    @staticmethod
    def check_action(action, shape: tuple[int, ...]) -> np.ndarray:
        """``action`` as float64 of exactly ``shape``, clipped to the action box ``[-1, 1]``
        (actuator saturation, reported as ``info["saturated"]``). Raises ``ValueError`` for
        another shape (no reshaping: a ``(2, 2)`` action for four actuators is a bug in the
        caller, not a layout to guess), a non-numeric or complex action, and NaN/inf entries
        (a diverged policy must not be driven as if it had asked for zero force)."""
        a = np.asarray(action)
        if a.dtype == object or not (np.issubdtype(a.dtype, np.floating)
                                     or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"action must be a real numeric array of shape {shape}, got dtype "
                             f"{a.dtype}")
        if a.shape != shape:
            raise ValueError(f"action must have shape {shape} (one entry per actuator: "
                             f"insertions then rotations), got shape {a.shape}")
        a = a.astype(np.float64)
        bad = ~np.isfinite(a)
        if bad.any():
            where = [tuple(int(i) for i in ix) for ix in np.argwhere(bad)[:4]]
            raise ValueError(f"action must be finite; entries {where} are {a[bad][0]!r}"
                             + (f" (and {int(bad.sum()) - len(where)} more)"
                                if bad.sum() > len(where) else ""))
        return np.clip(a, -1.0, 1.0)

    def step(self, action: np.ndarray):
        """Apply ``action (B, 2N)`` in ``[-1, 1]`` (see :meth:`check_action`); returns
        ``(reward, terminated, truncated, infos)`` with ``infos`` a dict of ``(B,)`` arrays."""
        self._check_ready()
        return self.step_checked(self.check_action(action, (self.B, 2 * self.N)))

    def _check_ready(self) -> None:
        if not self.ready.all():
            never = np.flatnonzero(~self.ready).tolist()
            raise ResetNeeded(f"step() before reset(): call reset() first (robot(s) {never} of "
                              f"{self.B} have no episode yet)")

    def step_checked(self, a: np.ndarray):
        """:meth:`step` for an action that :meth:`check_action` already returned (float64
        ``(B, 2N)``, clipped): the env faces validate against their own action space's shape
        (so the error names the shape their caller sees) and step through here, so an action
        is validated once."""
        self._check_ready()
        tip0 = self.robots.tip.copy()
        if self.config.control == "force":
            tau = a * self.robot.action_scale
            if self.config.compensation:
                # g at the start of the step, held over it (one-sided at a parked kink)
                tau = tau + (self.robots.compensation(a) if self.config.kink_compensation
                             else self.robots.g)
            flags = self.robots.step_force(tau)
        else:
            N = self.N
            step = np.concatenate([np.full(N, self.config.max_joint_step[0]),
                                   np.full(N, self.config.max_joint_step[1])])
            tau = self.robots.g.copy()  # position control holds the elastic load
            flags = self.robots.step_joint(a * step)
        self.prev_action = a
        snapped = flags.snapped
        failure = flags.solver_failure
        d = np.linalg.norm(self.robots.tip - self.goal, axis=-1)
        snap_term = snapped & (self.config.snap_mode == "terminate")
        unstable = np.zeros(self.B, dtype=bool)
        if self.config.stiffness_penalty != 0:
            k = relative_rotation_stiffness(self.robots.K_unclipped)
            unstable = (k < self.config.stiffness_hazard * self.stiffness_scale) & ~snap_term
        self.snap_flag = np.where(snap_term, 1.0, np.where(unstable, UNSTABLE_FLAG, 0.0))
        self._measure(np.arange(self.B))
        reward, terms = self._get_rew(snap_term, unstable)
        infos = {
            "is_success": self._goal_distance32() <= self.tolerance,
            "distance": d,
            "snapped": snapped,
            "snap_terminated": snap_term,
            "solver_failure": failure,
            "tip_jump": flags.tip_jump,
            "substeps": flags.substeps,
            "tau": tau,
            "effort": (tau ** 2).sum(-1) * self.carriage.control_period,
            "saturated": (np.abs(a) >= 0.999).mean(-1),
            "tip_speed": np.linalg.norm(self.robots.tip - tip0, axis=-1)
            / self.carriage.control_period,
            "at_limit": self.robots.at_lower.any(-1) | self.robots.at_upper.any(-1),
            "contact_force": flags.contact_force,
            "stop_force": flags.stop_force,
            "reward_distance": terms.distance,
            "reward_snap": terms.snap,
            "reward_stiffness": terms.stiffness,
            "unstable": unstable,
        }
        terminated = snap_term & ~failure
        truncated = failure
        return reward, terminated, truncated, infos

    def _get_rew(self, snap_term: np.ndarray,
                 unstable: np.ndarray | None = None) -> tuple[np.ndarray, RewardTerms]:
        """The step reward ``(B,)`` float32 and its :class:`RewardTerms`, from the float32
        goals of the observation (the measured tip): the values ``compute_reward`` gets back
        from a replay buffer (float64 goals differ in the 8th digit), with the penalties where
        ``snap_term`` (a terminating snap this step) and ``unstable``."""
        c = self.config
        return reward_terms(self.measured_tip.astype(np.float32), self.goal.astype(np.float32),
                            self.tolerance, c.reward, c.dense_scale, snap_term, c.snap_penalty,
                            c.shaping_weight, unstable, c.stiffness_penalty)

    # -- observations -------------------------------------------------------------------------
    def observations(self) -> dict[str, np.ndarray]:
        rb, robot = self.robots, self.robot
        N = self.N
        alpha = rb.x[:, N:]
        lo, hi = np.array(robot.insertion_min), np.array(robot.insertion_max)
        Dn = 2.0 * (rb.x[:, :N] - lo) / np.maximum(hi - lo, 1e-12) - 1.0
        parts = [np.sin(alpha), np.cos(alpha), Dn, rb.g / robot.action_scale, self.prev_action]
        if self.carriage.kind == "second_order":
            parts.append(rb.v / self.speeds)
        tip = self.measured_tip
        err = self.goal - tip
        parts += [tip / robot.reach, err / robot.reach,
                  np.tanh(err / self.config.error_scale),
                  np.tanh(rb.margin / robot.margin_scale)[:, None],
                  rb.at_lower.astype(np.float64), rb.at_upper.astype(np.float64)]
        if self.config.observe_stiffness:
            k = relative_rotation_stiffness(rb.K_unclipped)
            parts.append(np.tanh(k / self.stiffness_scale)[:, None])
        obs = np.clip(np.nan_to_num(np.concatenate(parts, -1), nan=0.0), -OBS_BOUND, OBS_BOUND)
        return {"observation": obs.astype(np.float32),
                "achieved_goal": np.concatenate([tip, self.snap_flag[:, None]],
                                                -1).astype(np.float32),
                "desired_goal": np.concatenate([self.goal, np.zeros((self.B, 1))],
                                               -1).astype(np.float32)}

    def relabel_observation(self, observation, achieved_goal, desired_goal) -> np.ndarray:
        """``observation (..., obs_size)`` with its goal-relative entries, ``(goal - tip) /
        reach`` and ``tanh((goal - tip) / error_scale)``, recomputed from the goals' positions
        (``(..., 4)`` or ``(..., 3)`` [m]): what the observation would read had the episode's
        goal been ``desired_goal``. HER relabels ``desired_goal`` only
        (:class:`envs.her.GoalConsistentHerReplayBuffer` calls this so that the rest of the
        observation follows). Returns a new float32 array; the other entries are copied."""
        obs = np.array(observation, dtype=np.float32, copy=True)
        if obs.shape[-1] != self.obs_size:
            raise ValueError(f"observation must have {self.obs_size} entries on its last axis, "
                             f"got shape {obs.shape}")
        ag = np.asarray(achieved_goal, np.float64)[..., :3]
        dg = np.asarray(desired_goal, np.float64)[..., :3]
        if ag.shape != obs.shape[:-1] + (3,) or dg.shape != ag.shape:
            raise ValueError(f"achieved_goal and desired_goal must be (..., 3) or (..., 4) with "
                             f"the observation's leading shape {obs.shape[:-1]}, got "
                             f"{np.shape(achieved_goal)} and {np.shape(desired_goal)}")
        err = dg - ag
        k = self.goal_entries
        obs[..., k:k + 3] = np.clip(err / self.robot.reach, -OBS_BOUND, OBS_BOUND)
        obs[..., k + 3:k + 6] = np.tanh(err / self.config.error_scale)
        return obs

    def state(self) -> RobotState:
        """The robots' state as a :class:`RobotState` of copies (``(B, ...)`` arrays)."""
        rb = self.robots
        q = np.zeros((self.B, 0)) if rb.q is None else rb.q
        return RobotState(x=rb.x.copy(), v=rb.v.copy(), g=rb.g.copy(),
                          tip=self.measured_tip.copy(), goal=self.goal.copy(),
                          margin=rb.margin.copy(), q=np.array(q, dtype=np.float64, copy=True),
                          damping=rb.damping.copy(), action_scale=self.robot.action_scale,
                          control_period=float(self.carriage.control_period),
                          true_tip=rb.tip.copy(), plant_factors=self.plants.factors.copy(),
                          plant_tip_force=self.plants.tip_force.copy(),
                          stiffness=rb.K_unclipped.copy())

    def set_tolerance(self, tolerance: float) -> None:
        _check_tolerance(tolerance)
        self.tolerance = float(tolerance)


def _check_tolerance(tolerance) -> None:
    if not (_real(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive length [m], got {tolerance!r}")
