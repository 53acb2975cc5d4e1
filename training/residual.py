"""Residual policy learning on top of a model-based controller.

The agent's action ``a`` in ``[-1, 1]^(2N)`` is added, scaled, to a base force controller's
command (Silver et al. 2018, "Residual Policy Learning"; Johannink et al. 2019):

    tau / tau_max = clip(base(x, goal) + scale * gate * a, -1, 1),
    gate = min(1, |goal - tip| / r)

The base is the plan-then-servo controller (``base: pts``, the stronger one on the nominal task:
0.95 at 1 mm on 100 seeded fig3 goals), its tip-feedback variant (``base: pts_feedback``, the
bar on the robust task, where the plant differs from the controller's model) or the
operational-space controller (``base: osc``, 0.70), all in :mod:`training.controllers`.

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
``base``, ``scale``, ``gate_radius``, ``plan_obs`` and the base controller's keyword arguments
(recorded in
``model.json`` by training/train.py; rl_zoo3 records it in the run's ``config.yml`` as the
``vec_env_wrapper`` entry, e.g. ``{training.residual.ResidualVecEnv: {base: pts, scale: 0.3}}``).

**The plan in the observation** (``plan_obs: true``, bases ``pts`` and ``pts_feedback``).
Plan-then-servo acts on a plan ``x*`` it made when the goal appeared, from the actuation it had
then: the base's action is not a function of what the agent observes (tip, goal, actuation),
so the residual's environment is not Markov. With ``plan_obs`` the observation's
``"observation"`` vector gains ``tanh((x* - x) / (10 h v_max))`` (``2N`` entries: the
remaining travel in units of ten control periods at each carriage's full-scale speed), which
restores it. For ``pts_feedback`` ``x*`` is its current setpoint (the plan as its outer loop
has corrected it from the measured tip), so the base acts on each observation before the
agent sees it. The same augmented observation goes to the policy at evaluation
(:func:`residual_policy`). HER must not relabel such transitions (the plan belongs to the
episode's goal, not to a relabelled one): train them with a plain replay buffer (the base
reaches most goals, so the sparse reward is not
sparse); ``training.train`` refuses the combination.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env import VecEnvWrapper

from .controllers import CONTROLLERS, read_state

__all__ = ["ResidualVecEnv", "residual_policy", "make_base", "zero_residual_head",
           "actuation_from_observation", "needs_plain_replay", "BASES"]

#: Base controllers a residual can be learned on.
BASES = ("pts", "pts_feedback", "osc")

#: The bases that servo to a plan (their ``reference``), which ``plan_obs`` can show the agent.
PLAN_BASES = ("pts", "pts_feedback")


def make_base(venv, spec: dict):
    """The base controller named by ``spec["base"]`` (one of :data:`BASES`, default
    ``"osc"`` for the runs recorded before plan-then-servo existed) with the rest of ``spec``
    (less ``scale`` and ``gate_radius``) as its keyword arguments."""
    spec = dict(spec)
    base = spec.pop("base", "osc")
    for key in ("scale", "gate_radius", "plan_obs", "penalty"):
        spec.pop(key, None)
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


class _Spec(NamedTuple):
    scale: float
    gate_radius: float
    plan_obs: bool
    penalty: float


def _spec(spec: dict | None) -> _Spec:
    spec = dict(spec or {})
    scale, radius = float(spec.get("scale", 0.3)), float(spec.get("gate_radius", 5e-3))
    plan_obs, penalty = spec.get("plan_obs", False), float(spec.get("penalty", 0.0))
    if not 0.0 < scale <= 2.0:
        raise ValueError(f"residual.scale must be in (0, 2], got {scale}")
    if not radius >= 0.0:
        raise ValueError(f"residual.gate_radius must be >= 0 [m], got {radius}")
    if not isinstance(plan_obs, bool):
        raise ValueError(f"residual.plan_obs must be true or false, got {plan_obs!r}")
    if plan_obs and spec.get("base", "osc") not in PLAN_BASES:
        raise ValueError(f"residual.plan_obs needs a base with a plan, one of {PLAN_BASES}, "
                         f"got base {spec.get('base', 'osc')!r}")
    if not 0.0 <= penalty < float("inf"):
        raise ValueError(f"residual.penalty must be a finite number >= 0, got {penalty}")
    return _Spec(scale, radius, plan_obs, penalty)


def needs_plain_replay(spec: dict | None) -> bool:
    """Whether a residual with this spec must not be trained with HER: ``plan_obs`` (the plan
    belongs to the episode's goal) and ``penalty`` (a reward term that HER's
    ``compute_reward`` does not know) both are."""
    sp = _spec(spec)
    return sp.plan_obs or sp.penalty > 0


#: Travel (in control periods at full-scale speed) that ``plan_obs`` maps to tanh(1).
PLAN_OBS_PERIODS = 10.0


def plan_observation_space(space: spaces.Dict, n_actuators: int) -> spaces.Dict:
    """``space`` with ``n_actuators`` entries in ``[-1, 1]`` appended to ``"observation"``."""
    box = space["observation"]
    low = np.concatenate([box.low, -np.ones(n_actuators, box.dtype)])
    high = np.concatenate([box.high, np.ones(n_actuators, box.dtype)])
    return spaces.Dict({**space.spaces,
                        "observation": spaces.Box(low, high, dtype=box.dtype)})


def _plan_features(target: np.ndarray, x: np.ndarray, st) -> np.ndarray:
    """``tanh((x* - x) / (PLAN_OBS_PERIODS h v_max))``, ``(..., 2N)``."""
    ref = PLAN_OBS_PERIODS * st.control_period * st.action_scale / st.damping
    return np.tanh((target - x) / ref)


def _append(obs: dict, extra: np.ndarray) -> dict:
    ob = obs["observation"]
    return {**obs, "observation": np.concatenate([ob, extra.astype(ob.dtype)], -1)}


def _with_plan(obs: dict, base, venv) -> dict:
    """``obs`` with the plan features appended to ``"observation"`` (``base`` has planned for
    the current goals)."""
    st = read_state(venv)
    return _append(obs, _plan_features(base.reference, st.x, st))


def actuation_from_observation(ob: np.ndarray, robot, alpha_near: np.ndarray) -> np.ndarray:
    """The actuation ``x (2N,)`` that an observation vector ``ob`` describes (its first ``3N``
    entries: ``sin alpha``, ``cos alpha``, normalized ``D``; see :mod:`envs.task`), with each
    rotation on the turn nearest ``alpha_near (N,)`` [rad] (the observation holds the angle
    modulo ``2 pi``; one control period turns a tube by far less than ``pi``)."""
    N = robot.n_tubes
    ob = np.asarray(ob, np.float64)
    lo, hi = np.array(robot.insertion_min), np.array(robot.insertion_max)
    D = lo + (ob[2 * N:3 * N] + 1.0) * (hi - lo) / 2.0
    alpha = np.arctan2(ob[:N], ob[N:2 * N])
    alpha = alpha_near + (alpha - alpha_near + np.pi) % (2 * np.pi) - np.pi
    return np.concatenate([D, alpha])


class ResidualVecEnv(VecEnvWrapper):
    """Apply ``clip(base(obs) + scale * gate * action, -1, 1)`` to the wrapped env.

    ``venv`` must be a torchpvs reaching env on force actions: a :class:`envs.CTRReachVecEnv`,
    or an SB3 vec env of :class:`envs.CTRReachEnv` (rl_zoo3's ``vec_env_wrapper``); the base
    controller reads its state (:func:`training.controllers.read_state`). The spec is ``spec``
    updated with the keyword arguments (rl_zoo3 passes the wrapper's YAML mapping as keywords):
    ``base`` (one of :data:`BASES`, default ``"osc"``), ``scale`` (default 0.3),
    ``gate_radius`` [m] (default 5e-3; 0 = no gate), ``plan_obs`` (default false: see the
    module's docstring), ``penalty`` (default 0: the training reward loses ``penalty *
    mean(a^2)`` per step, so the residual stays 0 where it does not pay for itself; evaluation
    metrics do not depend on it) and the base controller's keyword arguments
    (``time_constant``, ... for pts; ``gain``, ``damping``, ``max_step`` for osc).
    """

    def __init__(self, venv, spec: dict | None = None, **fields):
        spec = {**dict(spec or {}), **fields}
        sp = _spec(spec)
        space = (plan_observation_space(venv.observation_space, venv.action_space.shape[0])
                 if sp.plan_obs else None)
        super().__init__(venv, observation_space=space)
        self.residual_spec = spec
        self.scale, self.gate_radius, self.plan_obs = sp.scale, sp.gate_radius, sp.plan_obs
        self.penalty = sp.penalty
        self._penalties = None
        self.base = make_base(venv, spec)
        self._obs = None
        self._base_action = None
        self._x = None    # (B, 2N) the actuation the agent last observed

    def _observe(self, obs):
        self._obs, self._base_action = obs, None
        if not self.plan_obs:
            return obs
        # the base acts on this observation now: it plans for new goals (and pts_feedback
        # corrects its setpoint) before the agent sees the plan it will follow
        self._base_action = self.base(obs)
        st = read_state(self.venv)
        self._x = st.x.copy()
        return _append(obs, _plan_features(self.base.reference, st.x, st))

    def _terminal_with_plan(self, term: dict, i: int) -> dict:
        """The terminal observation of robot ``i`` (already reset: its state is gone) with the
        features of the plan it was following, at the actuation the observation describes."""
        robot = self.base.robot
        x = actuation_from_observation(term["observation"], robot, self._x[i, robot.n_tubes:])
        return _append(term, _plan_features(self.base.reference[i], x, read_state(self.venv)))

    def reset(self):
        return self._observe(self.venv.reset())

    def step_async(self, actions: np.ndarray) -> None:
        weight = self.scale * _gate(self.venv, self.gate_radius)
        if self.penalty > 0:
            a = np.clip(np.asarray(actions, np.float64), -1.0, 1.0)
            self._penalties = self.penalty * np.mean(a ** 2, -1)
        base = self.base(self._obs) if self._base_action is None else self._base_action
        self.venv.step_async(_combine(base, actions, weight))

    def step_wait(self):
        obs, rewards, dones, infos = self.venv.step_wait()
        if self.penalty > 0:
            rewards = rewards - self._penalties
        if self.plan_obs:   # the episode's last observation (SB3 keeps it for bootstrapping)
            for i in np.flatnonzero(dones):
                term = infos[i].get("terminal_observation")
                if term is not None:
                    infos[i]["terminal_observation"] = self._terminal_with_plan(term, i)
        return self._observe(obs), rewards, dones, infos


def residual_policy(model_predict, venv, spec: dict):
    """A batched policy ``obs -> action`` from a residual agent's ``predict`` on ``venv``
    (``obs`` as ``venv`` returns it: the plan is appended here when ``spec`` has
    ``plan_obs``)."""
    base = make_base(venv, spec)
    sp = _spec(spec)

    def policy(obs):
        a_base = base(obs)
        seen = _with_plan(obs, base, venv) if sp.plan_obs else obs
        return _combine(a_base, model_predict(seen), sp.scale * _gate(venv, sp.gate_radius))
    return policy


def zero_residual_head(model) -> None:
    """Zero the last layer of ``model``'s action mean (SAC/TQC ``actor.mu``, TD3 ``actor.mu``'s
    last linear layer and its target copy, PPO ``action_net``), so that the untrained residual
    agent's deterministic action is exactly 0: it starts as its base controller, and learning
    moves it away only where the critic finds a gain (a random head starts it below the base,
    and a residual agent has been measured to stay there)."""
    import torch

    policy = model.policy
    actor = getattr(policy, "actor", None)
    head = getattr(actor, "mu", None) if actor is not None else getattr(policy, "action_net",
                                                                        None)
    if isinstance(head, torch.nn.Sequential):
        head = [m for m in head if isinstance(m, torch.nn.Linear)][-1]
    if not isinstance(head, torch.nn.Linear):
        raise TypeError(f"zero_residual_head: no linear action head found on "
                        f"{type(policy).__name__}")
    with torch.no_grad():
        head.weight.zero_()
        head.bias.zero_()
    target = getattr(policy, "actor_target", None)
    if target is not None:
        target.load_state_dict(actor.state_dict())
