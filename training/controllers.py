"""Non-learned policies evaluated next to the agents: a model-based operational-space force
controller (privileged access to the differentiable solver), zero and random policies.

Every policy maps batched observations (the ``CTRReachVecEnv`` Dict) to actions ``(B, 2N)`` in
``[-1, 1]``; model-based ones also read the environment's state (actuation, forces).
"""

from __future__ import annotations

import numpy as np
import torch

import torchpvs
from envs.robots import ENV_SOLVER_OPTIONS

__all__ = ["OperationalSpaceController", "ZeroPolicy", "RandomPolicy", "tip_jacobian"]


def tip_jacobian(robot, x: np.ndarray, initial=None) -> tuple[np.ndarray, np.ndarray]:
    """Tip positions ``(B, 3)`` [m] and ``d tip / dx`` ``(B, 3, 2N)`` [m/m, m/rad] at actuator
    coordinates ``x (B, 2N)``, through the solver's implicit backward (3 reverse passes)."""
    N = robot.n_tubes
    X = torch.as_tensor(x, dtype=torch.float64).clone().requires_grad_(True)
    eq = torchpvs.solve(robot.scene, insertion=X[:, :N], rotation=X[:, N:],
                        options=ENV_SOLVER_OPTIONS, initial=initial)
    rows = [torch.autograd.grad(eq.tip_position[:, i].sum(), X, retain_graph=i < 2)[0]
            for i in range(3)]
    return eq.tip_position.detach().numpy(), torch.stack(rows, 1).numpy()


class OperationalSpaceController:
    """``tau = g(x) + B J^+ (k / h) (goal - tip)``, clipped to the action range.

    ``J^+ = B^-1 J^T (J B^-1 J^T + lambda I)^-1`` is the damped pseudo-inverse weighted by the
    carriage mobilities ``B^-1`` (the least-effort velocity that moves the tip along the error);
    ``k`` is the fraction of the error corrected per control period ``h`` and ``lambda``
    [m²/(N·s)]·scale damps it near singular configurations.
    """

    def __init__(self, venv, gain: float = 0.7, damping: float = 1e-3,
                 max_step: float = 5e-3):
        self.venv, self.gain, self.damping, self.max_step = venv, gain, damping, max_step

    def __call__(self, obs) -> np.ndarray:
        task = self.venv.task
        rb, robot = task.robots, task.robot
        h = task.carriage.control_period
        tip, J = tip_jacobian(robot, rb.x, initial=rb.q)
        err = task.goal - tip
        norm = np.linalg.norm(err, axis=-1, keepdims=True)
        err = err * np.minimum(1.0, self.max_step / np.maximum(norm, 1e-12))  # limit the stride
        Minv = 1.0 / rb.damping                                           # (2N,)
        JM = J * Minv[None, None, :]                                      # J B^-1
        A = JM @ np.swapaxes(J, 1, 2)                                     # (B, 3, 3)
        lam = self.damping * np.trace(A, axis1=1, axis2=2)[:, None, None] / 3 + 1e-18
        y = np.linalg.solve(A + lam * np.eye(3), (self.gain / h * err)[..., None])[..., 0]
        xdot = Minv * np.einsum("bij,bi->bj", J, y)                       # B^-1 J^T y
        tau = rb.g + rb.damping * xdot
        return np.clip(tau / robot.action_scale, -1.0, 1.0).astype(np.float32)


class ZeroPolicy:
    """Action 0: no actuator force (the robot relaxes under its elastic forces)."""

    def __init__(self, venv):
        self.shape = (venv.num_envs, venv.action_space.shape[0])

    def __call__(self, obs) -> np.ndarray:
        return np.zeros(self.shape, np.float32)


class RandomPolicy:
    """Uniform random actions (seeded)."""

    def __init__(self, venv, seed: int = 0):
        self.shape = (venv.num_envs, venv.action_space.shape[0])
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs) -> np.ndarray:
        return self.rng.uniform(-1, 1, self.shape).astype(np.float32)
