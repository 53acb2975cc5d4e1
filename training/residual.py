"""Residual policy learning on top of a model-based controller.

The agent's action ``a`` in ``[-1, 1]^(2N)`` is added, scaled, to a base force controller's
command (Silver et al. 2018, "Residual Policy Learning"; Johannink et al. 2019):

    tau / tau_max = clip(base(x, goal) + scale * gate * a, -1, 1),
    gate = min(1, |goal - tip| / r)

The base is the plan-then-servo controller (``base: pts``, the stronger one: 0.95 at 1 mm on
100 seeded fig3 goals) or the operational-space controller (``base: osc``, 0.70), both in
:mod:`training.controllers`.

The gate keeps the goal a fixed point of the closed loop: without it any residual the network
outputs at the goal (SAC's deterministic mean is never exactly 0) becomes a constant force
offset, which the controller's proportional term balances with a steady-state tip error — in a
first run the deterministic success at 1 mm fell from 0.65 to 0.28 as training went on. With it
the residual shapes the approach (large motions, snap avoidance) and the controller owns the
last ``r`` (default 5 mm). The robot still receives actuator forces and torques only; the
residual learns what the model-based controller gets wrong (for the OSC: slow settling, snaps
through unstable regions, the damped pseudo-inverse near singular configurations; for
plan-then-servo: slow carriages under load, goals that need more travel than the episode).
A pure agent must learn the feed-forward ``g(x)`` and the tip Jacobian from scratch, which the
joint-space literature needed millions of steps for.

:class:`ResidualVecEnv` wraps a :class:`envs.CTRReachVecEnv` for training; :func:`residual_policy`
turns a trained model back into a batched policy for evaluation. Both take the same ``spec``:
``base``, ``scale``, ``gate_radius`` and the base controller's keyword arguments (recorded in
``model.json`` by training/train.py; rl_zoo3 records it in the run's ``config.yml`` as the
``vec_env_wrapper`` entry, e.g. ``{training.residual.ResidualVecEnv: {base: pts, scale: 0.3}}``).
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnvWrapper

from .controllers import CONTROLLERS, read_state

__all__ = ["ResidualVecEnv", "residual_policy", "make_base", "BASES"]

#: Base controllers a residual can be learned on.
BASES = ("pts", "osc")


def make_base(venv, spec: dict):
    """The base controller named by ``spec["base"]`` (``"pts"`` or ``"osc"``, default
    ``"osc"`` for the runs recorded before plan-then-servo existed) with the rest of ``spec``
    (less ``scale`` and ``gate_radius``) as its keyword arguments."""
    spec = dict(spec)
    base = spec.pop("base", "osc")
    spec.pop("scale", None)
    spec.pop("gate_radius", None)
    if base not in BASES:
        raise ValueError(f"residual.base must be one of {BASES}, got {base!r}")
    try:
        return CONTROLLERS[base](venv, **spec)
    except TypeError as e:   # an unknown gain name: say which entry it came from
        raise ValueError(f"residual: bad keyword for base {base!r}: {e}") from None


def _gate(venv, radius: float) -> np.ndarray:
    """``(B, 1)`` residual weight ``min(1, |goal - tip| / radius)`` (1 everywhere if radius 0)."""
    if radius <= 0:
        return np.ones((venv.num_envs, 1))
    st = read_state(venv)
    d = np.linalg.norm(st.goal - st.tip, axis=-1, keepdims=True)
    return np.minimum(1.0, d / radius)


def _combine(base_action: np.ndarray, residual: np.ndarray, weight) -> np.ndarray:
    return np.clip(base_action + weight * np.asarray(residual), -1.0, 1.0).astype(np.float32)


def _spec(spec: dict | None) -> tuple[float, float]:
    spec = dict(spec or {})
    scale, radius = float(spec.get("scale", 0.3)), float(spec.get("gate_radius", 5e-3))
    if not 0.0 < scale <= 2.0:
        raise ValueError(f"residual.scale must be in (0, 2], got {scale}")
    if not radius >= 0.0:
        raise ValueError(f"residual.gate_radius must be >= 0 [m], got {radius}")
    return scale, radius


class ResidualVecEnv(VecEnvWrapper):
    """Apply ``clip(base(obs) + scale * gate * action, -1, 1)`` to the wrapped env.

    ``venv`` must be a torchpvs reaching env on force actions: a :class:`envs.CTRReachVecEnv`,
    or an SB3 vec env of :class:`envs.CTRReachEnv` (rl_zoo3's ``vec_env_wrapper``); the base
    controller reads its state (:func:`training.controllers.read_state`). The spec is ``spec``
    updated with the keyword arguments (rl_zoo3 passes the wrapper's YAML mapping as keywords):
    ``base`` (``"pts"`` or ``"osc"``, default ``"osc"``), ``scale`` (default 0.3),
    ``gate_radius`` [m] (default 5e-3; 0 = no gate) and the base controller's keyword arguments
    (``time_constant``, ... for pts; ``gain``, ``damping``, ``max_step`` for osc).
    """

    def __init__(self, venv, spec: dict | None = None, **fields):
        super().__init__(venv)
        spec = {**dict(spec or {}), **fields}
        self.residual_spec = spec
        self.scale, self.gate_radius = _spec(spec)
        self.base = make_base(venv, spec)
        self._obs = None

    def reset(self):
        self._obs = self.venv.reset()
        return self._obs

    def step_async(self, actions: np.ndarray) -> None:
        weight = self.scale * _gate(self.venv, self.gate_radius)
        self.venv.step_async(_combine(self.base(self._obs), actions, weight))

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        self._obs = obs
        return obs, rewards, dones, infos


def residual_policy(model_predict, venv, spec: dict):
    """A batched policy ``obs -> action`` from a residual agent's ``predict`` on ``venv``."""
    base = make_base(venv, spec)
    scale, radius = _spec(spec)

    def policy(obs):
        return _combine(base(obs), model_predict(obs), scale * _gate(venv, radius))
    return policy
