"""Every registered task leaves time to reach its goals: the share of goals whose sampled
preimage the actuators can reach within the episode (envs/ceilings.py). Reference: the travel
of each goal recomputed here from the documented per-period steps."""

from __future__ import annotations

import numpy as np
import pytest

import envs
from envs.ceilings import travel_ceiling

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("env_id", sorted(envs.ENV_IDS))
def test_at_least_98_percent_of_goals_are_reachable_in_time(env_id):
    c = travel_ceiling(env_id, goals=200)
    assert c.within >= 0.98, (env_id, c.within, c.median)


def test_joint_actions_needed_longer_episodes():
    """With joint increments (1 mm, 5 deg per step) 100 steps left about a third of the goals
    out of reach; the id's 200 steps are what makes the task fair."""
    short = travel_ceiling("torchpvs/CTRReachJoint-v0", goals=200, max_episode_steps=100)
    assert short.within < 0.8
    assert envs.env_kwargs("torchpvs/CTRReachJoint-v0")["max_episode_steps"] == 200


def test_travel_counts_the_largest_step_per_period():
    venv = envs.CTRReachVecEnv(4, control="joint")
    venv.seed(1)
    venv.reset()
    task = venv.task
    d = task.goal_actuation - task.robots.x
    d[:, 2:] = np.angle(np.exp(1j * d[:, 2:]))
    want = np.max(np.abs(d) / np.array([1e-3, 1e-3, np.radians(5), np.radians(5)]), -1)
    np.testing.assert_allclose(task.travel_steps(), want, rtol=1e-12)
