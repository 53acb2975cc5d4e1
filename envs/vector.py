"""Gymnasium-native batched environment: ``B`` reaching robots stepped with ONE batched solver
call per substep, as a ``gymnasium.vector.VectorEnv``.

``gym.make_vec("torchpvs/CTRReachForce-v0", num_envs=B, vectorization_mode="vector_entry_point")``
returns it (both registered ids declare it as their ``vector_entry_point``). It shares the task
core (:class:`envs.task.ReachBatch`) with the single env and with the Stable-Baselines3 adapter
(:class:`envs.vec_env.CTRReachVecEnv`), and needs only Gymnasium.

Autoreset: ``AutoresetMode.SAME_STEP`` (declared in ``metadata``): a robot whose episode ends is
reset within the step; the returned observation is the reset one, and ``infos["final_obs"]``
(an object array, masked by ``infos["_final_obs"]``) and ``infos["final_info"]`` hold the last
observation and info of the finished episode. Infos are Gymnasium's vector format: one array per
key with a boolean mask ``"_key"``. Seeding: ``reset(seed=s)`` gives robot ``i`` the ``i``-th
child of ``SeedSequence(s)`` (the batch reproduces ``B`` single environments seeded that way).
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
from .task import ReachBatch, ReachConfig, RobotState, her_reward

__all__ = ["CTRReachVectorEnv", "build_batch"]


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
    ``max_episode_steps`` is the time limit, default 100)."""

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

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self.task.seed(seed)
        if options and "tolerance" in options:
            self.task.set_tolerance(options["tolerance"])
        self.task.reset(np.arange(self.num_envs))
        self.elapsed[:] = 0
        return self._obs(), {}

    def step(self, actions):
        actions = self.task.check_action(actions, (self.num_envs, *self.single_action_space.shape))
        reward, terminated, truncated, infos = self.task.step(actions)
        self.elapsed += 1
        truncated = truncated | (self.elapsed >= self.max_episode_steps)
        obs = self._obs()
        info: dict[str, Any] = {}
        for key, value in infos.items():
            info[key] = value
            info[f"_{key}"] = np.ones(self.num_envs, dtype=bool)
        done = terminated | truncated
        if done.any():
            idx = np.flatnonzero(done)
            final_obs = np.full(self.num_envs, None, dtype=object)
            final_info = np.full(self.num_envs, None, dtype=object)
            for i in idx:
                final_obs[i] = {k: v[i].copy() for k, v in obs.items()}
                final_info[i] = {k: (v[i].copy() if np.ndim(v) > 1 else v[i].item())
                                 for k, v in infos.items()}
            info["final_obs"], info["_final_obs"] = final_obs, done.copy()
            info["final_info"], info["_final_info"] = final_info, done.copy()
            self.task.reset(idx)
            self.elapsed[idx] = 0
            obs = self._obs()
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
