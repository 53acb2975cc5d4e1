"""Single-robot Gymnasium face of the reaching task (goal-conditioned, Dict observations).

``gymnasium.make("torchpvs/CTRReachForce-v0")`` — actions are actuator forces and torques;
``gymnasium.make("torchpvs/CTRReachJoint-v0")`` — the same robot with joint increments.
See :mod:`envs.task` for the observation layout and :mod:`envs.dynamics` for the physics.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from torchpvs import Scene

from .dynamics import CarriageModel
from .robots import Robot, make_robot
from .task import ReachBatch, ReachConfig, RobotState, her_reward, registered_kwargs

__all__ = ["CTRReachEnv", "make_force_env", "make_joint_env"]


class CTRReachEnv(gym.Env):
    """Reach a goal with the tip of a concentric tube robot.

    Args:
        robot: preset name (``"fig3_two_tube"`` default, ``"rvim_three_tube"``), a
            :class:`~envs.robots.Robot`, a :class:`~torchpvs.Scene` or a scene file path.
        control: ``"force"`` or ``"joint"`` (see :class:`~envs.task.ReachConfig`).
        carriage: a :class:`~envs.dynamics.CarriageModel` or a dict of its fields
            (e.g. ``{"kind": "second_order"}``).
        render_mode: ``None``, ``"rgb_array"`` or ``"human"``.
        **task: any :class:`~envs.task.ReachConfig` field (``reward``, ``tolerance``,
            ``snap_mode``, ...).

    Action space: ``Box(-1, 1, (2N,), float32)``, insertions first, for ``N`` tubes (outermost
    first):

    =========  ===========================  ========================================
    index      force control (default)      joint control
    =========  ===========================  ========================================
    0 .. N-1   insertion force of carriage  insertion increment ``a * 1 mm`` [m]
               ``j``: ``a * force_scale_j``
               [N] (plus ``g(x)`` with
               ``compensation=True``)
    N .. 2N-1  base torque of tube ``j``:   rotation increment ``a * 5 deg`` [rad]
               ``a * torque_scale_j`` [N·m]
    =========  ===========================  ========================================

    Observation space: a ``Dict`` with ``observation`` (the table in :mod:`envs.task`:
    rotations, insertions, elastic loads, the previous action, the tip, the error to the goal,
    the stability margin, stroke flags; float32), ``achieved_goal = (tip [m], snap flag)`` and
    ``desired_goal = (goal [m], 0)``, all in the robot's base frame.

    Reward: ``"sparse"`` (default) ``-1`` per step until the measured tip is within
    ``tolerance`` (1 mm), then ``0``; ``"dense"`` ``-distance / dense_scale``, ``+1`` inside;
    ``"shaped"`` the sparse reward minus ``shaping_weight * min(distance / dense_scale, 1)``;
    plus ``snap_penalty`` (``-60``) at a terminating snap. Episodes end at a snap
    (``snap_mode="terminate"``) or after the registered number of steps (truncation).

    Actions must have the action space's shape ``(2N,)`` and be finite: anything else raises
    ``ValueError`` (nothing is reshaped, NaN is never read as 0); finite entries outside
    ``[-1, 1]`` saturate (``info["saturated"]``).

    ``info`` of every step holds ``is_success``, ``distance`` [m], ``snapped``,
    ``solver_failure``, ``tip_jump`` [m], ``substeps``, ``tau`` (the applied forces/torques
    [N, N·m]), ``effort`` [N²s], ``saturated`` (fraction of saturated action components),
    ``tip_speed`` [m/s], ``at_limit``, and the contact forces averaged over the step [N]:
    ``contact_force (N-1,)`` the force of carriage ``j-1`` on carriage ``j`` along ``+D_j``
    (``> 0`` at the nesting stop ``D_j = D_{j-1}``, ``< 0`` at the tip-order stop, ``0`` apart)
    and ``stop_force (N,)`` the force of the stroke ends on each insertion carriage along
    ``+D`` (``> 0`` at the lower end). Both are zero under joint control. The reward's parts
    (:class:`~envs.task.RewardTerms`): ``reward_distance`` (the goal term above),
    ``reward_snap`` (``snap_penalty`` at a terminating snap, else 0) and ``reward_stiffness``
    (``stiffness_penalty`` at a step that ends statically unstable, ``unstable``, else 0);
    they sum to the reward.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(self, robot: str | Robot | Scene = "fig3_two_tube", control: str = "force",
                 carriage: CarriageModel | dict | None = None, render_mode: str | None = None,
                 **task: Any):
        self.robot = make_robot(robot)
        if isinstance(carriage, dict):
            carriage = CarriageModel(**carriage)
        self.carriage = carriage or CarriageModel()
        self.config = ReachConfig(control=control, **task)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or "
                             f"None, got {render_mode!r}")
        self.render_mode = render_mode
        self.task = ReachBatch(self.robot, self.config, self.carriage, 1)
        self.observation_space = self.task.observation_space
        self.action_space = self.task.action_space
        self._renderer = None
        self._last_info: dict[str, Any] = {}

    # -- Gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Gymnasium's reset. ``options`` (all optional; any other key raises ``ValueError``):
        ``"goal"``, a goal position ``(3,)`` [m] in the base frame for this episode instead of
        a sampled one (finite, within ``2 x robot.reach`` of the orifice; the start is the
        one the seed gives without the option, ``goal_min_distance`` does not apply,
        reachability is not checked);
        ``"tolerance"``, the success radius [m] from now on (as :meth:`set_tolerance`)."""
        tol, goal = self.task.reset_options(options, 1)
        super().reset(seed=seed)
        # the task draws its episode's generator from the env's own np_random
        self.task.np_randoms[0] = self.np_random
        if tol is not None:
            self.set_tolerance(tol)
        self.task.reset(np.array([0]), goal=goal)
        self._last_info = self.task.reset_info(0)
        if self.render_mode == "human":
            self.render()
        return self._obs(), dict(self._last_info)

    def step(self, action):
        if not self.task.ready[0]:
            raise gym.error.ResetNeeded("CTRReachEnv.step() before reset(): call reset() first")
        a = self.task.check_action(action, self.action_space.shape)  # raises on NaN/shape
        reward, terminated, truncated, infos = self.task.step_checked(a[None])
        info = self.task.info_of(infos, 0)
        self._last_info = info
        if self.render_mode == "human":
            self.render()
        return (self._obs(), float(reward[0]), bool(terminated[0]), bool(truncated[0]), info)

    def compute_reward(self, achieved_goal, desired_goal, info) -> np.ndarray | float:
        """Vectorized over leading axes (SB3's HerReplayBuffer relabelling): depends on the
        goals (positions and the achieved snap flag, see :mod:`envs.task`), the current
        tolerance and, where ``info`` carries it, ``snap_terminated``."""
        r = her_reward(self.task, achieved_goal, desired_goal, info)
        return r if r.ndim else float(r)

    def relabel_observation(self, observation, achieved_goal, desired_goal) -> np.ndarray:
        """The observation with its goal-relative entries recomputed for ``desired_goal``
        (vectorized; see :meth:`envs.task.ReachBatch.relabel_observation`)."""
        return self.task.relabel_observation(observation, achieved_goal, desired_goal)

    def state(self) -> RobotState:
        """The robot's state (:class:`~envs.task.RobotState`, copies) with the batch axis
        kept: ``x`` is ``(1, 2N)``, ``tip`` ``(1, 3)``, ``margin`` ``(1,)``, so controllers
        written for the batched envs run unchanged on this one."""
        return self.task.state()

    def set_tolerance(self, tolerance: float) -> None:
        """Success radius [m] from now on (curricula)."""
        self.task.set_tolerance(tolerance)

    def set_next_goal(self, goal) -> None:
        """Goal ``(3,)`` [m] for the next episode when its ``reset`` names none (curricula:
        SB3's ``DummyVecEnv`` autoresets without options); ``None`` clears it. Used once."""
        self.task.set_next_goal([0], goal)

    def set_next_start(self, x) -> None:
        """Start state ``x (2N,)`` (insertions [m] then rotations [rad], at rest) for the
        next episode (:meth:`envs.task.ReachBatch.set_next_start`); ``None`` clears it."""
        self.task.set_next_start([0], x)

    @property
    def episode_start(self) -> np.ndarray:
        """The state ``x (2N,)`` the current episode started at."""
        return self.task.episode_start[0].copy()

    def render(self):
        """Gymnasium's render API: ``"rgb_array"`` returns the frame ``(H, W, 3)`` uint8;
        ``"human"`` draws into a pyplot window (also done by every ``reset``/``step``) and
        returns ``None``; without a render mode it warns and returns ``None``."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode= to make")
            return None
        from .render import ReachRenderer
        if self._renderer is None:
            self._renderer = ReachRenderer(self.robot, human=self.render_mode == "human")
        frame = self._renderer.draw(self.task, 0)
        return None if self.render_mode == "human" else frame

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # -- helpers ----------------------------------------------------------------------------
    def _obs(self) -> dict[str, np.ndarray]:
        return {k: v[0] for k, v in self.task.observations().items()}

    @property
    def actuation(self) -> np.ndarray:
        """Current actuator coordinates ``(2N,)`` ``(D [m], alpha [rad])``."""
        return self.task.robots.x[0].copy()

    @property
    def elastic_forces(self) -> np.ndarray:
        """Current ``g = dU*/dx`` ``(2N,)`` [N, N·m]."""
        return self.task.robots.g[0].copy()


# -- the registered ids' entry points: the id fixes the control ----------------------------
def make_force_env(**kwargs: Any) -> CTRReachEnv:
    """``torchpvs/CTRReachForce-v0``: a :class:`CTRReachEnv` with force control (a
    ``control=`` naming another control raises ``ValueError``)."""
    return CTRReachEnv(**registered_kwargs("force", kwargs))


def make_joint_env(**kwargs: Any) -> CTRReachEnv:
    """``torchpvs/CTRReachJoint-v0``: a :class:`CTRReachEnv` with joint control."""
    return CTRReachEnv(**registered_kwargs("joint", kwargs))


# gym.make reads the entry point's render modes
make_force_env.metadata = make_joint_env.metadata = CTRReachEnv.metadata
