"""Natively batched Stable-Baselines3 ``VecEnv``: ``B`` robots stepped with ONE batched solver
call per substep (instead of ``B`` sequential single-robot solves in a ``DummyVecEnv``).

Semantics follow SB3's ``VecEnv`` contract: ``step`` returns ``(obs, rewards, dones, infos)``,
a finished robot is reset in the same step, its ``info`` holds ``terminal_observation`` and
``TimeLimit.truncated`` (``reset_infos`` the reset's info); seeds given through ``seed()`` and
options through ``set_options()`` are used at the next ``reset()``. Seeding is SB3's own
(``VecEnv.seed``): ``seed(s)`` gives robot ``i`` the seed ``s + i``, so the batch reproduces a
``DummyVecEnv`` of single environments seeded ``s`` (robot ``i`` = ``gym.make(id)`` reset with
seed ``s + i``, then its autoresets), the same rule as the Gymnasium vector env, up to solver
round-off. Options: ``"goal"`` (``(3,)`` [m], that robot's goal for the next episode),
``"tolerance"``; any other key raises ``ValueError``. Options reach an explicit ``reset()``
only (SB3's rule); ``env_method("set_next_goal", goal, indices=[i])`` queues a goal for robot
``i``'s next episode, an autoreset included.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.error import ResetNeeded
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from torchpvs import Scene

from .dynamics import CarriageModel
from .robots import Robot
from .task import RobotState, her_reward
from .vector import build_batch

__all__ = ["CTRReachVecEnv"]


class CTRReachVecEnv(VecEnv):
    """``num_envs`` reaching robots in one process (see :class:`envs.reach_env.CTRReachEnv` for
    the arguments; ``max_episode_steps`` is the time limit, default 100).

    Spaces, reward and ``info`` keys per robot are :class:`envs.reach_env.CTRReachEnv`'s (its
    action, observation and reward tables, with units): ``action_space`` is the single robot's
    ``Box(-1, 1, (2N,), float32)`` (SB3's convention), ``step`` takes ``(num_envs, 2N)`` finite
    actions (``ValueError`` otherwise) and returns observations with a leading ``num_envs``
    axis and a list of ``info`` dicts. Autoreset, seeding and options: the module docstring.
    """

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
        parsed = [self.task.reset_options(opt or None, 1) for opt in self._options]
        self.task.seed(list(self._seeds))
        for tol, _ in parsed:
            if tol is not None:
                self.task.set_tolerance(tol)
        self._reset_seeds()
        self._reset_options()
        user = np.array([g is not None for _, g in parsed], dtype=bool)
        self.task.reset(np.flatnonzero(~user))
        if user.any():
            self.task.reset(np.flatnonzero(user),
                            goal=np.concatenate([g for _, g in parsed if g is not None]))
        self.elapsed[:] = 0
        self.reset_infos = [self.task.reset_info(i) for i in range(self.num_envs)]
        return self.task.observations()

    def step_async(self, actions: np.ndarray) -> None:
        if not self.task.ready.all():
            raise ResetNeeded("CTRReachVecEnv.step() before reset(): call reset() first")
        self._actions = self.task.check_action(actions, (self.num_envs, *self.action_space.shape))

    def step_wait(self):
        reward, terminated, truncated, infos = self.task.step_checked(self._actions)
        self.elapsed += 1
        time_limit = self.elapsed >= self.max_episode_steps
        truncated = truncated | time_limit
        dones = terminated | truncated
        obs = self.task.observations()
        info_list = self.task.info_list(infos, self.num_envs)
        for i, info in enumerate(info_list):
            info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
            if dones[i]:
                info["terminal_observation"] = {k: v[i].copy() for k, v in obs.items()}
        done_idx = np.flatnonzero(dones)
        if len(done_idx):
            self.task.reset(done_idx)
            self.elapsed[done_idx] = 0
            obs = self.task.observations()
            for i in done_idx:
                self.reset_infos[i] = self.task.reset_info(i)
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

    def set_next_goal(self, goal) -> None:
        """This robot's goal [m] for its next episode (:meth:`envs.task.ReachBatch.set_next_goal`;
        ``env_method("set_next_goal", goal, indices=[i])``)."""
        self._venv.task.set_next_goal([self._i], goal)

    def set_next_start(self, x) -> None:
        """This robot's start state for its next episode
        (:meth:`envs.task.ReachBatch.set_next_start`)."""
        self._venv.task.set_next_start([self._i], x)

    @property
    def episode_start(self) -> np.ndarray:
        """This robot's state ``x (2N,)`` at the start of its current episode."""
        return self._venv.task.episode_start[self._i].copy()

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
