"""Hindsight experience replay whose samples agree with their goals.

SB3's ``HerReplayBuffer`` relabels ``desired_goal`` (and the reward) of a sampled transition but
leaves ``observation`` as stored. The reaching envs' observation holds two goal-relative
entries, ``(goal - tip) / reach`` and ``tanh((goal - tip) / error_scale)`` (:mod:`envs.task`),
so with the stock buffer a relabelled transition describes one goal in ``desired_goal`` and
another in ``observation``: about 80 % of the sampled transitions of a ``future`` strategy at
``n_sampled_goal=4`` disagree, and no agent learned. A second staleness: the rewards of real
(not relabelled) transitions are the ones computed at the tolerance they were collected at, so
under a tolerance curriculum (:class:`training.callbacks.ToleranceCurriculum`) they contradict
the relabelled ones.

:class:`GoalConsistentHerReplayBuffer` fixes both: every sampled observation (real or virtual,
``obs`` and ``next_obs``) has its goal-relative entries recomputed from its own goals by the
env's ``relabel_observation``, and every sampled reward comes from the env's ``compute_reward``
at the current tolerance. Use it wherever ``HerReplayBuffer`` would go::

    TQC("MultiInputPolicy", venv, replay_buffer_class=GoalConsistentHerReplayBuffer,
        replay_buffer_kwargs=dict(n_sampled_goal=4, goal_selection_strategy="future"))

In an rl-baselines3-zoo hyperparameter file (the zoo evaluates the string)::

    replay_buffer_class: "importlib.import_module('envs.her').GoalConsistentHerReplayBuffer"
"""

from __future__ import annotations

import numpy as np
from stable_baselines3 import HerReplayBuffer

__all__ = ["GoalConsistentHerReplayBuffer", "ZOO_NAME"]

#: The zoo's way to name this buffer in a YAML ``replay_buffer_class`` entry (it ``eval``s it).
ZOO_NAME = "importlib.import_module('envs.her').GoalConsistentHerReplayBuffer"


class GoalConsistentHerReplayBuffer(HerReplayBuffer):
    """A ``HerReplayBuffer`` (same arguments) for envs with a ``relabel_observation``
    method (every torchpvs reaching env face): sampled observations agree with their
    ``desired_goal`` and sampled rewards follow the env's current tolerance."""

    def _normalize_obs(self, obs, env=None):
        # SB3 passes every sampled observation dict (real and virtual, obs and next_obs)
        # through here after setting its goals and before normalizing: the one place where
        # the goal-relative entries can follow the goal for all of them.
        if isinstance(obs, dict) and "desired_goal" in obs and "observation" in obs:
            obs = dict(obs)
            obs["observation"] = self._relabel(obs["observation"], obs["achieved_goal"],
                                               obs["desired_goal"])
        return super()._normalize_obs(obs, env)

    def _relabel(self, observation, achieved_goal, desired_goal) -> np.ndarray:
        if self.env is None:
            raise ValueError("GoalConsistentHerReplayBuffer needs env= (a VecEnv of torchpvs "
                             "reaching envs) to relabel observations")
        try:
            out = self.env.env_method("relabel_observation", observation, achieved_goal,
                                      desired_goal, indices=[0])
        except AttributeError as e:
            raise TypeError(f"GoalConsistentHerReplayBuffer: the env has no "
                            f"relabel_observation(observation, achieved_goal, desired_goal) "
                            f"method ({e}); use it with the torchpvs reaching envs") from None
        return out[0].astype(self.observations["observation"].dtype, copy=False)

    def _get_real_samples(self, batch_indices, env_indices, env=None):
        samples = super()._get_real_samples(batch_indices, env_indices, env)
        next_ag = self.next_observations["achieved_goal"][batch_indices, env_indices]
        goal = self.observations["desired_goal"][batch_indices, env_indices]
        infos = (self.infos[batch_indices, env_indices] if self.copy_info_dict
                 else [{} for _ in range(len(batch_indices))])
        rewards = self.env.env_method("compute_reward", next_ag, goal, infos, indices=[0])[0]
        rewards = self._normalize_reward(np.asarray(rewards, np.float32).reshape(-1, 1), env)
        return samples._replace(rewards=self.to_torch(rewards))
