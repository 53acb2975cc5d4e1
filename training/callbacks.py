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

from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["ToleranceCurriculum", "WallClockLimit"]


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
