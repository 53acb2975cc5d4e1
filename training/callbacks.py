"""Training callbacks usable from rl-baselines3-zoo's YAML (``callback:`` entries) and from
training/train.py, which reads the same files.

In a hyperparameter file::

    callback:
      - training.callbacks.ToleranceCurriculum:
          start: 0.01
          end: 0.001
          fraction: 0.6
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["DemoCloning", "FailedGoalReplay", "ToleranceCurriculum", "WallClockLimit",
           "critic_mean"]


class ToleranceCurriculum(BaseCallback):
    """Success tolerance [m] decaying exponentially from ``start`` to ``end`` over the first
    ``fraction`` of the run's ``total_timesteps``, then ``end``; applied to the training env
    through ``env_method("set_tolerance")`` (every sub-env of an SB3 vec env; the batched
    ``CTRReachVecEnv`` shares one tolerance). Evaluation envs keep their own (1 mm default),
    so checkpoints are chosen at the final tolerance. Logged as ``curriculum/tolerance_mm``.
    """

    def __init__(self, start: float, end: float, fraction: float = 0.5, verbose: int = 0):
        super().__init__(verbose)
        start, end, fraction = float(start), float(end), float(fraction)
        if not (start > 0 and end > 0 and math.isfinite(start) and math.isfinite(end)):
            raise ValueError(f"ToleranceCurriculum start and end must be positive lengths [m], "
                             f"got start={start!r}, end={end!r}")
        if not 0 < fraction <= 1:
            raise ValueError(f"ToleranceCurriculum fraction must be in (0, 1], got {fraction!r}")
        self.start, self.end, self.fraction = start, end, fraction
        self.total = 1

    def _on_training_start(self) -> None:
        self.total = int(self.locals.get("total_timesteps", 1))

    def tolerance(self, t: int) -> float:
        """The tolerance [m] after ``t`` environment steps."""
        p = min(1.0, t / max(1.0, self.fraction * self.total))
        return math.exp(math.log(self.start) + p * (math.log(self.end) - math.log(self.start)))

    def _on_step(self) -> bool:
        tol = self.tolerance(self.num_timesteps)
        self.training_env.env_method("set_tolerance", tol)
        self.logger.record("curriculum/tolerance_mm", tol * 1e3)
        return True


class WallClockLimit(BaseCallback):
    """Stop training after ``minutes`` of wall time (the model so far is kept and saved)."""

    def __init__(self, minutes: float, verbose: int = 0):
        super().__init__(verbose)
        if not float(minutes) > 0:
            raise ValueError(f"WallClockLimit minutes must be > 0, got {minutes!r}")
        self.minutes = float(minutes)
        self.deadline = math.inf

    def _on_training_start(self) -> None:
        self.deadline = time.perf_counter() + 60.0 * self.minutes

    def _on_step(self) -> bool:
        return time.perf_counter() < self.deadline


class FailedGoalReplay(BaseCallback):
    """Replay the goals of failed episodes: a robot's episode that ends unsuccessful
    (``info["is_success"]`` False at its last step: a miss at the time limit or a snap) adds its
    goal to a pool of the last ``capacity`` such goals, and each robot that finishes an episode
    draws, with probability ``fraction``, a goal from the pool (uniformly) for its episode after
    the next one (the next has started in the same step: vector envs reset finished robots
    themselves). The start state is the one the robot's seed gives, unless ``with_start``:
    then the pool holds each failed episode's start state with its goal, and a replay queues
    both (``set_next_start``), so the agent meets the same situation again (a goal missed from
    a deeply retracted start is an easy goal from most other starts).

    Why: the goals a nearly trained agent misses are rare under the goal distribution (the
    force agent's far misses cluster at the top of the workspace, 7 % of the goals), so uniform
    goals give the policy few episodes where it still fails; this focuses a share of the
    episodes there, as prioritized or "hard goal" curricula do. Evaluation envs are untouched.

    Needs an env with ``set_next_goal`` (:class:`envs.CTRReachVecEnv`, or single
    :class:`envs.CTRReachEnv` in an SB3 vec env) and goals in ``desired_goal[:3]`` [m];
    observations normalized by ``VecNormalize`` are refused (the pool would hold normalized
    goals). Logged: ``replay/pool`` (goals in the pool), ``replay/share`` (the share of finished
    episodes that queued a replayed goal)."""

    def __init__(self, fraction: float = 0.3, capacity: int = 1000, seed: int | None = None,
                 with_start: bool = False, verbose: int = 0):
        super().__init__(verbose)
        fraction = float(fraction)
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"FailedGoalReplay fraction must be in [0, 1], got {fraction!r}")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"FailedGoalReplay capacity must be an integer >= 1, got "
                             f"{capacity!r}")
        if not isinstance(with_start, bool):
            raise ValueError(f"FailedGoalReplay with_start must be a bool, got {with_start!r}")
        self.fraction, self.capacity, self.seed = fraction, capacity, seed
        self.with_start = with_start
        # (goal (3,), start x (2N,) or None)
        self.pool: deque[tuple[np.ndarray, np.ndarray | None]] = deque(maxlen=capacity)
        self.starts: list[np.ndarray] = []
        self.finished = 0
        self.replayed = 0
        self.rng = np.random.default_rng(seed)

    def _on_training_start(self) -> None:
        from stable_baselines3.common.vec_env import VecNormalize, unwrap_vec_wrapper
        norm = unwrap_vec_wrapper(self.training_env, VecNormalize)
        if norm is not None and norm.norm_obs:
            raise ValueError("FailedGoalReplay: the training env normalizes observations "
                             "(VecNormalize norm_obs), so its goals are not positions [m]")
        if self.seed is None and self.model.seed is not None:
            self.rng = np.random.default_rng(self.model.seed + 7919)
        if self.with_start:
            # the episodes under way started here (set at every reset, autoresets included)
            self.starts = [np.array(x) for x in self.training_env.get_attr("episode_start")]

    def _on_step(self) -> bool:
        dones, infos = self.locals["dones"], self.locals["infos"]
        for i in np.flatnonzero(dones):
            i = int(i)
            info = infos[i]
            self.finished += 1
            last = info.get("terminal_observation")
            if not info.get("is_success", False) and last is not None:
                start = self.starts[i] if self.with_start else None
                self.pool.append((np.array(last["desired_goal"][:3], dtype=np.float64), start))
            if self.with_start:   # the episode the autoreset began
                self.starts[i] = np.array(
                    self.training_env.get_attr("episode_start", indices=[i])[0])
            if self.pool and self.rng.random() < self.fraction:
                goal, start = self.pool[int(self.rng.integers(len(self.pool)))]
                self.training_env.env_method("set_next_goal", goal, indices=[i])
                if start is not None:
                    self.training_env.env_method("set_next_start", start, indices=[i])
                self.replayed += 1
        self.logger.record("replay/pool", len(self.pool))
        self.logger.record("replay/share", self.replayed / max(1, self.finished))
        return True


def critic_mean(critic, obs, action):
    """``(B,)`` the mean of a critic's estimates: TQC's ``(B, n_critics, n_quantiles)``
    quantiles or SAC's tuple of ``(B, 1)`` values."""
    import torch
    q = critic(obs, action)
    if isinstance(q, (tuple, list)):
        q = torch.cat(q, dim=1)
    return q.flatten(1).mean(1)


class DemoCloning(BaseCallback):
    """Behaviour cloning from a controller's demonstrations, with a Q filter (Nair et al.,
    "Overcoming exploration in reinforcement learning with demonstrations", ICRA 2018).

    Between rollouts, for each gradient step the algorithm took since the last rollout, the
    actor takes one step on ``L = mean_i 1[Q(s_i, a_i) > Q(s_i, pi(s_i))] ||pi(s_i) - a_i||^2``
    over ``batch_size`` demonstration pairs ``(s_i, a_i)`` (its deterministic action ``pi``;
    ``Q`` the mean of the critics' estimates), with an Adam optimizer of its own at
    ``learning_rate``: the policy copies the demonstrator only where its own critic rates the
    demonstrated action above the policy's, so a demonstrator that is worse somewhere is not
    copied there. The critic learns from the agent's own transitions only. The policy that
    results is model-free when it acts; the demonstrator (a model-based controller) only
    supplies training data.

    ``min_distance`` [m]: only the pairs whose tip is farther than this from their goal are
    cloned (the demonstrator's travel, not its hold at the goal).

    ``path`` is a file of :mod:`training.demos` made with the training env's observation and
    action (``--like`` a policy of that env). Needs an off-policy algorithm with ``actor`` and
    ``critic`` (SAC, TQC) and dict observations. Logged: ``demo/loss``, ``demo/accepted`` (the
    share of pairs the Q filter passes)."""

    def __init__(self, path: str, learning_rate: float = 3e-5, batch_size: int = 256,
                 q_filter: bool = True, min_distance: float = 0.0, seed: int | None = None,
                 verbose: int = 0):
        super().__init__(verbose)
        if isinstance(min_distance, bool) or not (isinstance(min_distance, (int, float))
                                                  and min_distance >= 0):
            raise ValueError(f"DemoCloning min_distance must be a distance >= 0 [m], got "
                             f"{min_distance!r}")
        self.min_distance = float(min_distance)
        if not (isinstance(learning_rate, (int, float)) and learning_rate > 0):
            raise ValueError(f"DemoCloning learning_rate must be > 0, got {learning_rate!r}")
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"DemoCloning batch_size must be an integer >= 1, got "
                             f"{batch_size!r}")
        self.path, self.learning_rate, self.batch_size = str(path), float(learning_rate), batch_size
        self.q_filter, self.seed = bool(q_filter), seed
        self.rng = np.random.default_rng(seed)
        self.steps = 0
        self._seen_updates = 0

    def _on_training_start(self) -> None:
        import torch

        model = self.model
        for name in ("actor", "critic"):
            if getattr(model, name, None) is None:
                raise ValueError(f"DemoCloning needs an algorithm with an {name} (SAC, TQC), "
                                 f"got {type(model).__name__}")
        space = model.observation_space
        with np.load(self.path) as f:
            data = {k: f[k] for k in ("observation", "achieved_goal", "desired_goal",
                                      "action")}
        for key, arr in data.items():
            want = model.action_space.shape if key == "action" else space[key].shape
            if arr.shape[1:] != tuple(want):
                raise ValueError(f"DemoCloning: {self.path} field {key!r} has shape "
                                 f"{arr.shape[1:]} per step, the model's is {tuple(want)} "
                                 f"(make the demonstrations with --like a policy of this env)")
        # pairs whose tip is farther than min_distance from their goal (the travel, not the
        # hold at the goal)
        far = np.linalg.norm(data["achieved_goal"][:, :3] - data["desired_goal"][:, :3],
                             axis=-1) > self.min_distance
        if not far.any():
            raise ValueError(f"DemoCloning: no pair of {self.path} lies farther than "
                             f"min_distance = {self.min_distance} m from its goal")
        data = {k: v[far] for k, v in data.items()}
        self.n = len(data["action"])
        dev = model.device
        self.obs = {k: torch.as_tensor(data[k], dtype=torch.float32, device=dev)
                    for k in ("observation", "achieved_goal", "desired_goal")}
        # the algorithm's actions live in [-1, 1] (scale_action), the env's in its Box
        self.actions = torch.as_tensor(model.policy.scale_action(data["action"]),
                                       dtype=torch.float32, device=dev)
        self.optimizer = torch.optim.Adam(model.actor.parameters(), lr=self.learning_rate)
        if self.seed is None and model.seed is not None:
            self.rng = np.random.default_rng(model.seed + 104729)
        self._seen_updates = model._n_updates

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        import torch

        model = self.model
        todo = model._n_updates - self._seen_updates
        self._seen_updates = model._n_updates
        loss_sum = accepted = 0.0
        for _ in range(todo):
            idx = torch.as_tensor(self.rng.integers(self.n, size=self.batch_size))
            obs = {k: v[idx] for k, v in self.obs.items()}
            a_demo = self.actions[idx]
            a_pi = model.actor(obs, deterministic=True)
            if self.q_filter:
                with torch.no_grad():
                    keep = (critic_mean(model.critic, obs, a_demo)
                            > critic_mean(model.critic, obs, a_pi.detach())).float()
            else:
                keep = torch.ones(self.batch_size, device=a_pi.device)
            loss = (keep * ((a_pi - a_demo) ** 2).sum(-1)).mean()
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            loss_sum += float(loss.detach())
            accepted += float(keep.mean())
        if todo:
            self.steps += todo
            self.logger.record("demo/loss", loss_sum / todo)
            self.logger.record("demo/accepted", accepted / todo)
