"""The plant a robot batch really is, when it differs from the nominal robot its controllers know.

A real concentric tube robot is not its datasheet: tube precurvatures and moduli are off by a
few percent, an unknown load may press on the tip, and the tip is measured with noise. With a
:class:`PlantVariation`, each episode draws its own plant for each robot (seeded from that
robot's generator): every tube's precurvature, ``E`` and ``G`` scaled by ``U(1 - scale,
1 + scale)``, a constant tip force of magnitude ``U(0, tip_force)`` [N] in a uniformly random
direction, and Gaussian tip-measurement noise of ``tip_noise`` [m] per axis. The physics
(carriage loads, equilibria, snaps, success) follows the plant; observations and the reward see
the measured tip; controllers are given the nominal robot (``env.robot``).

:class:`Plants` holds the ``B`` robots' draws and solves their equilibria in one batched call
with per-robot tube properties and tip loads (``torchpvs.solver.solve_tensors``). The warm
solves of time stepping (:meth:`Plants.warm`) run on the compiled control-loop solver
(:meth:`torchpvs.Tracker.solve_from`: the same Newton iteration and closed forms as the solve
at the environments' fixed discretization, in one compiled call with the forces, the stability
margin and the actuator stiffness) wherever it applies: the nominal robot (no plant variation),
numba importable, ``solver="auto"`` or ``"compiled"``; elsewhere on ``torchpvs`` 's solve.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from torchpvs import compiled
from torchpvs.jacobians import actuator_stiffness
from torchpvs.plan import tube_tensors
from torchpvs.sections import TubeTensors
from torchpvs.solver import solve_tensors
from torchpvs.tracker import Tracker

from .robots import ENV_SOLVER_OPTIONS, Robot, RobotSolver

__all__ = ["PlantVariation", "Plants", "Solved", "solve_robots", "SOLVERS"]

#: The env solvers (``Plants(solver=...)``): ``"auto"`` the compiled warm solves where they
#: apply, else torch's; ``"compiled"`` the same but an error where they cannot apply;
#: ``"torch"`` always ``torchpvs``' solve (the reference the compiled path is tested against).
SOLVERS = ("auto", "compiled", "torch")


class Solved(NamedTuple):
    """What a substep reads of a batched solve of ``k`` robots, as numpy arrays (float64,
    ``(k, ...)``): the one place where a solver's results become the batch's state."""

    g: np.ndarray          # (k, 2N) [N, N·m] dU*/dx (the retraction side at a kink)
    tip: np.ndarray        # (k, 3) [m]
    margin: np.ndarray     # (k,) Equilibrium.min_stiffness_eigenvalue
    twist: np.ndarray      # (k, N-1) [rad] relative rotations at the outer tube's tip
    energy: np.ndarray     # (k,) [J]
    q: np.ndarray          # (k, nq) solver coordinates (the next warm start)
    ok: np.ndarray         # (k,) converged with finite forces and tip
    #: ``stiffness(rows)``: the actuator stiffness ``dtau/dx`` ``(len(rows), 2N, 2N)`` of
    #: those rows (torchpvs.jacobians.actuator_stiffness, one-sided at kinks)
    stiffness: Callable[[np.ndarray], np.ndarray]


def _usable(converged: np.ndarray, g: np.ndarray, tip: np.ndarray) -> np.ndarray:
    """``(k,)``: converged with finite loads and tip (a substep can take the state)."""
    return converged & np.isfinite(g).all(-1) & np.isfinite(tip).all(-1)


def solved_from(eq) -> Solved:
    """:class:`Solved` of an :class:`~torchpvs.Equilibrium` (its stiffness on request)."""
    g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
    tip = eq.tip_position.numpy()
    ok = _usable(eq.converged.numpy(), g, tip)
    return Solved(g=g, tip=tip, margin=eq.min_stiffness_eigenvalue.numpy(),
                  twist=eq.relative_rotation_at_outer_tip.numpy(),
                  energy=eq.energy.detach().numpy(), q=eq.q.detach().numpy(), ok=ok,
                  stiffness=lambda rows: actuator_stiffness(eq, torch.as_tensor(rows)).numpy())


def _nonneg(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class PlantVariation:
    """How each episode's plant differs from the nominal robot (all 0: the nominal robot).

    Attributes:
        scale: each tube's precurvature, ``E`` and ``G`` are multiplied by independent
            ``U(1 - scale, 1 + scale)`` factors (``0 <= scale < 1``; 0.1 = +-10 %).
        tip_force: [N] an unknown constant tip force of magnitude ``U(0, tip_force)`` in a
            uniformly random direction (0.1 N moves the Fig. 3 tip by up to 0.8 mm).
        tip_noise: [m] standard deviation per axis of the Gaussian noise on the measured tip
            (observation and ``achieved_goal``; success is judged on the true tip).
    """

    scale: float = 0.0
    tip_force: float = 0.0
    tip_noise: float = 0.0

    def __post_init__(self) -> None:
        for name in ("scale", "tip_force", "tip_noise"):
            _nonneg(getattr(self, name), f"plant {name}")
        if self.scale >= 1:
            raise ValueError(f"plant scale must be below 1 (factors U(1 - scale, 1 + scale) "
                             f"must stay positive), got {self.scale!r}")

    @property
    def nominal(self) -> bool:
        """Whether the plant is the nominal robot (nothing drawn, nothing solved apart)."""
        return self.scale == 0 and self.tip_force == 0


class Plants:
    """The plants of ``B`` robots: ``factors (B, 3, N)`` (precurvature, E, G per tube) and
    ``tip_force (B, 3)`` [N] in the base frame."""

    def __init__(self, robot: Robot, variation: PlantVariation, batch_size: int,
                 solver: str = "auto"):
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        self.robot, self.variation = robot, variation
        N = robot.n_tubes
        self.factors = np.ones((batch_size, 3, N))
        self.tip_force = np.zeros((batch_size, 3))
        # the nominal robot's solves and tube tensors, built once (the plan of its scene)
        self._nominal = RobotSolver(robot)
        self._base = self._nominal.plan.tubes
        fits = variation.nominal and robot.scene.load.is_zero and compiled.available()
        if solver == "compiled" and not fits:
            raise ValueError("solver='compiled' needs the nominal robot (no plant variation), "
                             "an unloaded scene and numba; use solver='auto' or 'torch'")
        #: the compiled warm solver (torchpvs.Tracker at the envs' discretization), or None
        self.tracker = (Tracker(robot.scene, options=ENV_SOLVER_OPTIONS)
                        if fits and solver != "torch" else None)
        self.solver = solver

    def draw(self, idx: np.ndarray, rngs) -> None:
        """New plants for robots ``idx``, each from its own generator ``rngs[i]``."""
        v = self.variation
        if v.nominal:
            return
        N = self.robot.n_tubes
        for i in np.asarray(idx, dtype=int):
            rng = rngs[i]
            self.factors[i] = rng.uniform(1 - v.scale, 1 + v.scale, (3, N))
            d = rng.normal(size=3)
            self.tip_force[i] = rng.uniform(0, v.tip_force) * d / np.linalg.norm(d)

    def solve(self, x: np.ndarray, rows: np.ndarray, initial=None):
        """Equilibria of robots ``rows`` at feasible, finite actuations ``x (len(rows), 2N)``
        (one batched solve; the nominal robot's plan when there is no variation; the inputs
        are not re-checked: the robot batch produced them)."""
        if self.variation.nominal:
            return self._nominal(x, initial=initial)
        rows = np.asarray(rows, dtype=int)
        with torch.no_grad():
            return solve_robots(self.robot, torch.as_tensor(np.asarray(x, np.float64)),
                                self.factors[rows], self.tip_force[rows], initial,
                                base=self._base)

    def warm(self, x: np.ndarray, rows: np.ndarray, q0: np.ndarray,
             stiffness: bool = False) -> Solved:
        """:class:`Solved` of robots ``rows`` at feasible, finite ``x (len(rows), 2N)``, warm
        from their coordinates ``q0 (len(rows), nq)``: one compiled call (with the actuator
        stiffness of every row when ``stiffness``) where :attr:`tracker` applies, else
        :meth:`solve`."""
        if self.tracker is None:
            return solved_from(self.solve(x, rows, initial=torch.from_numpy(q0)))
        N = self.robot.n_tubes
        st = self.tracker.solve_from(q0, x[:, :N], x[:, N:], stiffness=stiffness,
                                     forces=True, margin=True)
        g = np.concatenate([st.actuation_forces, st.actuation_torques], -1)
        ok = _usable(st.converged, g, st.tip)
        K = st.actuator_stiffness

        def stiffness_of(r: np.ndarray) -> np.ndarray:
            if K is None:
                raise ValueError("Plants.warm: the stiffness was not computed (stiffness=True)")
            return K[r]

        return Solved(g=g, tip=st.tip, margin=st.min_stiffness_eigenvalue,
                      twist=st.relative_rotation_at_outer_tip, energy=st.energy, q=st.q, ok=ok,
                      stiffness=stiffness_of)


def solve_robots(robot: Robot, x: torch.Tensor, factors: np.ndarray, tip_force=None,
                 initial=None, base: TubeTensors | None = None):
    """Equilibria of ``k`` variants of ``robot`` in one batched solve: row ``i`` at actuation
    ``x[i] (2N,)`` with each tube's precurvature, ``E`` and ``G`` multiplied by
    ``factors[i] (3, N)`` and tip force ``tip_force[i] (3,)`` [N] (default none).
    Differentiable in ``x`` (the implicit backward)."""
    N = robot.n_tubes
    k = x.shape[0]
    f = torch.as_tensor(np.asarray(factors, np.float64))                 # (k, 3, N)
    b = base if base is not None else tube_tensors(robot.scene, torch.float64,
                                                   torch.device("cpu"))
    tubes = TubeTensors(EI=b.EI * f[:, 1], GJ=b.GJ * f[:, 2], length=b.length.expand(k, -1),
                        straight=b.straight.expand(k, -1), coef=b.coef * f[:, 0, :, None, None])
    F = (torch.zeros(k, 3, dtype=torch.float64) if tip_force is None
         else torch.as_tensor(np.asarray(tip_force, np.float64)))
    return solve_tensors(robot.scene, tubes, x[:, :N], x[:, N:], F, torch.zeros_like(F),
                         ENV_SOLVER_OPTIONS, initial, None)
