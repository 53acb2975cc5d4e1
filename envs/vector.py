"""Gymnasium-native batched environment: ``B`` reaching robots stepped with ONE batched solver
call per substep, as a ``gymnasium.vector.VectorEnv``.

``gym.make_vec("torchpvs/CTRReachForce-v0", num_envs=B, vectorization_mode="vector_entry_point")``
returns it (both registered ids declare it as their ``vector_entry_point``). It shares the task
core (:class:`envs.task.ReachBatch`) with the single env and with the Stable-Baselines3 adapter
(:class:`envs.vec_env.CTRReachVecEnv`), and needs only Gymnasium.

Gymnasium's vector contract, exactly as ``SyncVectorEnv`` of the single env with
``autoreset_mode=SAME_STEP`` (``tests/envs/test_vector.py`` compares them key by key):

* Autoreset: ``AutoresetMode.SAME_STEP`` (declared in ``metadata``): a robot whose episode ends
  is reset within the step and the returned observation is the reset one.
* Infos: a dict of arrays, one per key, each with a boolean mask ``"_key"`` (built with
  ``VectorEnv._add_info``, robot by robot, as ``SyncVectorEnv`` does). A robot that did not
  finish contributes its step ``info``; a robot that finished contributes its RESET info
  (``is_success``, ``distance``, ``snapped``, ``solver_failure`` of the new episode's start)
  at the top level, and its last step's info under ``infos["final_info"]`` (itself a dict of
  arrays with ``_key`` masks, ``infos["_final_info"]`` marking the finished robots) and its last
  observation in ``infos["final_obs"]`` (an object array of observation dicts, masked by
  ``infos["_final_obs"]``). ``reset`` returns the reset infos in the same format.
* Seeding: ``reset(seed=s)`` seeds robot ``i`` with ``s + i`` (a list gives one seed per robot,
  ``None`` keeps the generators), so robot ``i`` runs the episodes of
  ``gym.make(id).reset(seed=s + i)`` and of ``SyncVectorEnv``'s sub-env ``i`` (up to solver
  round-off: batched and single solves stop at different iterations).
* ``reset(options=...)``: ``"reset_mask"`` (a ``(num_envs,)`` bool array: reset only those
  robots, checked as ``SyncVectorEnv`` checks it), ``"goal"`` (``(3,)`` for every robot reset or
  ``(num_envs, 3)``, see :meth:`envs.task.ReachBatch.check_goal`), ``"tolerance"``; any other key
  raises ``ValueError``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from torchpvs import Scene

from .dynamics import CarriageModel
from .robots import Robot, make_robot
from .task import ReachBatch, ReachConfig, RobotState, her_reward, registered_kwargs

__all__ = ["CTRReachVectorEnv", "build_batch", "make_force_vector_env", "make_joint_vector_env"]


def build_batch(num_envs: int, robot: str | Robot | Scene, control: str,
                carriage: CarriageModel | dict | None, max_episode_steps: int,
                task: dict) -> tuple[Robot, CarriageModel, ReachConfig, ReachBatch]:
    """The shared core of the batched environments (this one and the SB3 adapter), with the
    checks of their arguments: ``(robot, carriage model, task config, ReachBatch)``."""
    if not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
    if not isinstance(max_episode_steps, int) or max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be an integer >= 1, got "
                         f"{max_episode_steps!r}")
    robot = make_robot(robot)
    if isinstance(carriage, dict):
        carriage = CarriageModel(**carriage)
    carriage = carriage or CarriageModel()
    config = ReachConfig(control=control, **task)
    return robot, carriage, config, ReachBatch(robot, config, carriage, num_envs)


class CTRReachVectorEnv(gym.vector.VectorEnv):
    """``num_envs`` reaching robots in one process (arguments as :class:`envs.CTRReachEnv`;
    ``max_episode_steps`` is the time limit, default 100).

    Spaces, reward and ``info`` keys per robot are :class:`envs.CTRReachEnv`'s (its action,
    observation and reward tables, with units), batched: ``single_action_space`` is
    ``Box(-1, 1, (2N,), float32)`` and ``action_space`` ``(num_envs, 2N)``; the observation
    dict's entries gain a leading ``num_envs`` axis. Actions must have shape
    ``(num_envs, 2N)`` and be finite (``ValueError`` otherwise). Autoreset, infos, seeding and
    reset options: the module docstring.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"],
                "render_fps": 10}

    def __init__(self, num_envs: int = 16, robot: str | Robot | Scene = "fig3_two_tube",
                 control: str = "force", carriage: CarriageModel | dict | None = None,
                 max_episode_steps: int = 100, render_mode: str | None = None, **task: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.robot, self.carriage, self.config, self.task = build_batch(
            num_envs, robot, control, carriage, max_episode_steps, task)
        self.num_envs = num_envs
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self.single_observation_space = self.task.observation_space
        self.single_action_space = self.task.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.elapsed = np.zeros(num_envs, dtype=int)
        self._renderer = None

    def reset(self, *, seed: int | list | None = None, options: dict | None = None):
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"options must be a dict or None, got {type(options).__name__}")
        mask = None
        if options is not None and "reset_mask" in options:
            mask = options["reset_mask"]
            if not isinstance(mask, np.ndarray):
                raise TypeError(f"`options['reset_mask']` must be a numpy array, got "
                                f"{type(mask)}")
            if mask.shape != (self.num_envs,):
                raise ValueError(f"`options['reset_mask']` must have shape "
                                 f"`({self.num_envs},)`, got {mask.shape}")
            if mask.dtype != np.bool_:
                raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got "
                                f"{mask.dtype}")
            if not mask.any():
                raise ValueError(f"`options['reset_mask']` must contain a boolean array with at "
                                 f"least one True value, got reset_mask={mask}")
        idx = np.arange(self.num_envs) if mask is None else np.flatnonzero(mask)
        opts = None if options is None else dict(options)
        if opts and opts.get("goal") is not None and np.shape(opts["goal"]) == (
                self.num_envs, 3):
            opts["goal"] = np.asarray(opts["goal"])[idx]   # one goal per robot: those reset
        tol, goal = self.task.reset_options(opts, len(idx), extra=("reset_mask",))
        self.task.seed(seed, idx)                  # checks the seeds first
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            super().reset(seed=int(seed))
        if tol is not None:
            self.task.set_tolerance(tol)
        self.task.reset(idx, goal=goal)
        self.elapsed[idx] = 0
        infos: dict[str, Any] = {}
        for i in idx:
            infos = self._add_info(infos, self.task.reset_info(i), int(i))
        return self._obs(), infos

    def step(self, actions):
        if not self.task.ready.all():
            raise gym.error.ResetNeeded("CTRReachVectorEnv.step() before reset(): call "
                                        "reset() first")
        actions = self.task.check_action(actions, (self.num_envs, *self.single_action_space.shape))
        reward, terminated, truncated, infos = self.task.step_checked(actions)
        self.elapsed += 1
        truncated = truncated | (self.elapsed >= self.max_episode_steps)
        obs = self._obs()
        done = terminated | truncated
        final_obs = obs
        if done.any():
            idx = np.flatnonzero(done)
            self.task.reset(idx)
            self.elapsed[idx] = 0
            obs = self._obs()
        # SyncVectorEnv's infos, robot by robot (same keys, masks, dtypes and order)
        info: dict[str, Any] = {}
        for i in range(self.num_envs):
            if done[i]:
                info = self._add_info(info, {
                    "final_obs": {k: v[i].copy() for k, v in final_obs.items()},
                    "final_info": self.task.info_of(infos, i)}, i)
                info = self._add_info(info, self.task.reset_info(i), i)
            else:
                info = self._add_info(info, self.task.info_of(infos, i), i)
        return (obs, np.asarray(reward, dtype=np.float64), np.asarray(terminated, dtype=bool),
                np.asarray(truncated, dtype=bool), info)

    def _obs(self) -> dict[str, np.ndarray]:
        return {k: v.copy() for k, v in self.task.observations().items()}

    def state(self) -> RobotState:
        """The robots' state (:class:`~envs.task.RobotState`, copies, ``(num_envs, ...)``);
        after an autoreset it is the new episode's start, like the returned observation."""
        return self.task.state()

    def compute_reward(self, achieved_goal, desired_goal, info):
        """HER-style reward of the task (vectorized over leading dims; as the single env)."""
        return her_reward(self.task, achieved_goal, desired_goal, info)

    def relabel_observation(self, observation, achieved_goal, desired_goal) -> np.ndarray:
        """The observation with its goal-relative entries recomputed for ``desired_goal``
        (vectorized; see :meth:`envs.task.ReachBatch.relabel_observation`)."""
        return self.task.relabel_observation(observation, achieved_goal, desired_goal)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        from .render import ReachRenderer
        if self._renderer is None:
            self._renderer = ReachRenderer(self.robot)
        return tuple(self._renderer.draw(self.task, i) for i in range(self.num_envs))

    def close_extras(self, **kwargs) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


# -- the registered ids' vector entry points: the id fixes the control ---------------------
def make_force_vector_env(**kwargs: Any) -> CTRReachVectorEnv:
    """``gym.make_vec("torchpvs/CTRReachForce-v0", vectorization_mode="vector_entry_point")``
    (a ``control=`` naming another control raises ``ValueError``)."""
    return CTRReachVectorEnv(**registered_kwargs("force", kwargs))


def make_joint_vector_env(**kwargs: Any) -> CTRReachVectorEnv:
    """``gym.make_vec("torchpvs/CTRReachJoint-v0", vectorization_mode="vector_entry_point")``."""
    return CTRReachVectorEnv(**registered_kwargs("joint", kwargs))
