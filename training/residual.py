"""Residual policy learning on top of the model-based controller.

The agent's action ``a`` in ``[-1, 1]^(2N)`` is added, scaled, to the operational-space force
controller's command (Silver et al. 2018, "Residual Policy Learning"; Johannink et al. 2019):

    tau / tau_max = clip(osc(x, goal) + scale * a, -1, 1)

The robot still receives actuator forces and torques only; the residual learns what the model-based
controller gets wrong (slow settling, snaps through unstable regions, the damped pseudo-inverse
near singular configurations). A pure agent must learn the gravity-like feed-forward ``g(x)`` and
the tip Jacobian from scratch, which the joint-space literature needed millions of steps for.

:class:`ResidualVecEnv` wraps a :class:`envs.CTRReachVecEnv` for training; :func:`residual_policy`
turns a trained model back into a batched policy for evaluation. Both read ``scale`` and the
controller's gains from the config's ``residual:`` entry (recorded in ``model.json``).
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnvWrapper

from .controllers import OperationalSpaceController

__all__ = ["ResidualVecEnv", "residual_policy", "make_base"]


def make_base(venv, spec: dict):
    """The base controller named by ``spec["base"]`` (only ``"osc"``) with its gains."""
    spec = dict(spec)
    base = spec.pop("base", "osc")
    spec.pop("scale", None)
    if base != "osc":
        raise ValueError(f"residual.base must be 'osc', got {base!r}")
    return OperationalSpaceController(venv, **spec)


def _combine(base_action: np.ndarray, residual: np.ndarray, scale: float) -> np.ndarray:
    return np.clip(base_action + scale * np.asarray(residual), -1.0, 1.0).astype(np.float32)


class ResidualVecEnv(VecEnvWrapper):
    """Apply ``clip(base(obs) + scale * action, -1, 1)`` to the wrapped env.

    ``venv`` must be a :class:`envs.CTRReachVecEnv` (the base controller reads its state);
    ``spec`` is the config's ``residual`` mapping: ``scale`` (default 0.3), ``base`` and the base
    controller's keyword arguments (``gain``, ``damping``, ``max_step``).
    """

    def __init__(self, venv, spec: dict | None = None):
        super().__init__(venv)
        spec = dict(spec or {})
        self.scale = float(spec.get("scale", 0.3))
        if not 0.0 < self.scale <= 2.0:
            raise ValueError(f"residual.scale must be in (0, 2], got {self.scale}")
        self.base = make_base(venv, spec)
        self._obs = None

    def reset(self):
        self._obs = self.venv.reset()
        return self._obs

    def step_async(self, actions: np.ndarray) -> None:
        self.venv.step_async(_combine(self.base(self._obs), actions, self.scale))

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        self._obs = obs
        return obs, rewards, dones, infos


def residual_policy(model_predict, venv, spec: dict):
    """A batched policy ``obs -> action`` from a residual agent's ``predict`` on ``venv``."""
    base = make_base(venv, spec)
    scale = float(spec.get("scale", 0.3))

    def policy(obs):
        return _combine(base(obs), model_predict(obs), scale)
    return policy
