"""How many goals of a registered reaching task can be reached in time at all.

:func:`travel_ceiling` resets seeded episodes of an env id (episode ``k`` seeded ``seed + k``,
the seeds of ``training.evaluate``) and counts the travel from each start to the goal's sampled
preimage in control periods at the actuators' largest step per period
(:meth:`envs.task.ReachBatch.travel_steps`). The share within the id's episode length is an
optimistic ceiling (unloaded speeds, rotations the short way even across +-180 deg) and a
necessary condition only (a goal whose sampled preimage is out of reach may have a nearer one).
``benchmarks/env_ceilings.py`` prints it for every id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Ceiling", "travel_ceiling"]


@dataclass(frozen=True)
class Ceiling:
    """``steps``: the id's episode length; ``within``: share of goals whose sampled preimage
    is within it; ``median``, ``p95``: of the travel [control periods]; ``travel``: per goal."""

    steps: int
    within: float
    median: float
    p95: float
    travel: np.ndarray


def travel_ceiling(env_id: str, goals: int = 500, seed: int = 12345, batch: int = 100,
                   **env_kwargs) -> Ceiling:
    """The :class:`Ceiling` of ``env_id`` on ``goals`` seeded episodes (``env_kwargs`` override
    the id's options, e.g. ``max_episode_steps``)."""
    import envs

    if not (isinstance(goals, int) and goals >= 1):
        raise ValueError(f"goals must be an integer >= 1, got {goals!r}")
    kw = {**envs.env_kwargs(env_id), **env_kwargs}
    travel = []
    for b in range(-(-goals // batch)):
        n = min(batch, goals - b * batch)
        venv = envs.CTRReachVecEnv(n, **kw)
        venv.seed(seed + b * batch)
        venv.reset()
        travel.append(venv.task.travel_steps())
    t = np.concatenate(travel)
    T = int(kw["max_episode_steps"])
    return Ceiling(steps=T, within=float((t <= T).mean()), median=float(np.median(t)),
                   p95=float(np.percentile(t, 95)), travel=t)
