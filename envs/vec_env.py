"""Natively batched Stable-Baselines3 ``VecEnv``: ``B`` robots stepped with ONE batched solver
call per substep (instead of ``B`` sequential single-robot solves in a ``DummyVecEnv``).

Semantics follow SB3's ``VecEnv`` contract: ``step`` returns ``(obs, rewards, dones, infos)``,
a finished robot is reset in the same step, its ``info`` holds ``terminal_observation`` and
``TimeLimit.truncated``; seeds given through ``seed()`` are used at the next ``reset()``.
Robot ``i`` draws from the ``i``-th child of ``SeedSequence(seed)``, so the batch reproduces
``B`` single environments seeded that way (up to solver round-off).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from torchpvs import Scene

from .dynamics import CarriageModel
from .robots import Robot
from .task import RobotState, her_reward
from .vector import build_batch

__all__ = ["CTRReachVecEnv"]


class CTRReachVecEnv(VecEnv):
    """``num_envs`` reaching robots in one process (see :class:`envs.reach_env.CTRReachEnv` for
    the arguments; ``max_episode_steps`` is the time limit, default 100)."""

    def __init__(self, num_envs: int = 16, robot: str | Robot | Scene = "fig3_two_tube",
                 control: str = "force", carriage: CarriageModel | dict | None = None,
                 max_episode_steps: int = 100, render_mode: str | None = None, **task: Any):
        self.robot, self.carriage, self.config, self.task = build_batch(
            num_envs, robot, control, carriage, max_episode_steps, task)
        self.max_episode_steps = max_episode_steps
        self.render_mode = render_mode
        self._renderer = None
        super().__init__(num_envs, self.task.observation_space, self.task.action_space)
        self.elapsed = np.zeros(num_envs, dtype=int)
        self._actions: np.ndarray | None = None

    # -- VecEnv API ---------------------------------------------------------------------------
    def reset(self):
        if self._seeds and self._seeds[0] is not None:
            self.task.seed(self._seeds[0])
        for opt in self._options:
            if opt and "tolerance" in opt:
                self.task.set_tolerance(opt["tolerance"])
        self._reset_seeds()
        self._reset_options()
        self.task.reset(np.arange(self.num_envs))
        self.elapsed[:] = 0
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return self.task.observations()

    def seed(self, seed: int | None = None):
        """Seed robot ``i`` with the ``i``-th child of ``SeedSequence(seed)`` at the next
        reset (SB3 convention: used up by the next ``reset()``)."""
        self._seeds = [seed] * self.num_envs
        return [seed] * self.num_envs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = self.task.check_action(actions, (self.num_envs, *self.action_space.shape))

    def step_wait(self):
        reward, terminated, truncated, infos = self.task.step(self._actions)
        self.elapsed += 1
        time_limit = self.elapsed >= self.max_episode_steps
        truncated = truncated | time_limit
        dones = terminated | truncated
        obs = self.task.observations()
        info_list = []
        for i in range(self.num_envs):
            info = {k: (v[i].copy() if v.ndim > 1 else v[i].item()) for k, v in infos.items()}
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            if dones[i]:
                info["terminal_observation"] = {k: v[i].copy() for k, v in obs.items()}
            info_list.append(info)
        done_idx = np.flatnonzero(dones)
        if len(done_idx):
            self.task.reset(done_idx)
            self.elapsed[done_idx] = 0
            obs = self.task.observations()
        return obs, reward, dones, info_list

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()

    def get_images(self):
        from .render import ReachRenderer
        if self._renderer is None:
            self._renderer = ReachRenderer(self.robot)
        return [self._renderer.draw(self.task, i) for i in range(self.num_envs)]

    # attribute and method access, per robot, through a light proxy --------------------------
    def _proxy(self, i: int) -> _RobotProxy:
        return _RobotProxy(self, i)

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self._proxy(i), attr_name) for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        for i in self._get_indices(indices):
            setattr(self._proxy(i), attr_name, value)

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list[Any]:
        return [getattr(self._proxy(i), method_name)(*args, **kwargs)
                for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    # -- convenience --------------------------------------------------------------------------
    def state(self) -> RobotState:
        """The robots' state (:class:`~envs.task.RobotState`, copies, ``(num_envs, ...)``);
        after an autoreset it is the new episode's start, like the returned observation."""
        return self.task.state()

    def set_tolerance(self, tolerance: float) -> None:
        self.task.set_tolerance(tolerance)


class _RobotProxy:
    """What ``get_attr``/``env_method`` see for robot ``i``: the task's shared settings."""

    def __init__(self, venv: CTRReachVecEnv, i: int):
        object.__setattr__(self, "_venv", venv)
        object.__setattr__(self, "_i", i)

    def compute_reward(self, achieved_goal, desired_goal, info):
        return her_reward(self._venv.task, achieved_goal, desired_goal, info)

    def set_tolerance(self, tolerance: float) -> None:
        self._venv.task.set_tolerance(tolerance)

    def relabel_observation(self, observation, achieved_goal, desired_goal):
        return self._venv.task.relabel_observation(observation, achieved_goal, desired_goal)

    def __getattr__(self, name: str):
        v = self._venv
        if name == "tolerance":
            return v.task.tolerance
        if name in ("render_mode", "robot", "config", "carriage", "max_episode_steps",
                    "observation_space", "action_space", "metadata"):
            return getattr(v, name)
        if name == "spec":
            return None
        raise AttributeError(f"CTRReachVecEnv robots have no attribute {name!r}")

    def __setattr__(self, name: str, value) -> None:
        if name == "tolerance":
            self._venv.task.set_tolerance(value)
        else:
            raise AttributeError(f"cannot set {name!r} on a CTRReachVecEnv robot")
