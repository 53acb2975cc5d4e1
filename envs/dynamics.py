"""Actuator dynamics of a batch of robots: quasi-static tubes, carriages with damping (and mass).

With actuator coordinates ``x = (D, alpha)`` (``(B, 2N)``: [m], [rad]) and the elastic
generalized force ``g(x) = dU*/dx`` from the equilibrium solver (``actuation_forces``,
``actuation_torques``, docs/conventions.md signs), a commanded force/torque ``tau`` moves the
carriages:

* ``"overdamped"`` (default): ``b * xdot = tau - g(x)``;
* ``"second_order"``: ``m * xddot + b * xdot = tau - g(x)``.

Each substep of length ``h`` is linearly implicit in the actuator stiffness ``K = dg/dx``
(symmetrized, negative eigenvalues clipped: ``K+``), which keeps stiff directions stable:

* overdamped: ``(diag(b) + h K+) dx = h (tau - g(x_k))``;
* second order: ``(diag(m) + h diag(b) + h^2 K+) v_{k+1} = diag(m) v_k + h (tau - g(x_k))``,
  ``dx = h v_{k+1}``.

At rest ``tau = g(x)`` holds exactly. The number of substeps per control period is chosen from
the stiffness (``h * lambda_max(diag(b)^-1/2 K+ diag(b)^-1/2) <= stiffness_ratio``) and from a cap
on the motion per substep; every substep is ONE batched solver call warm-started from the last.
Carriages stop inelastically at their stroke limits (:meth:`envs.robots.Robot.project`): the
position is projected and the velocity into the stop zeroed.

Energy: in the overdamped model every substep must lower ``phi(x) = U*(x) - tau . x`` (the
flow is a gradient flow of ``phi``) by Armijo's sufficient-decrease test; the linearly implicit
step passes it wherever ``U*`` is smooth, and a step that overshoots a kink of ``U*`` (O(h)
chatter) is retried halved, using the energy the substep's solve already returned (no extra
solver call when the first step is accepted). The second-order model is not tested this way:
with inertia ``phi`` alone need not fall.

Failures: a substep whose solve does not converge is retried for those robots with the step
halved (up to ``max_retries`` times); if it still fails the robot keeps its last valid state and
is flagged ``solver_failure``. A snap — the equilibrium losing stability, the torsion releasing
(a relative twist ``theta_j(l_1) - theta_1(l_1)`` at the outer tube's tip jumping by more than
``snap_twist`` beyond the change of the base rotations in one substep), or the tip moving more
than ``snap_jump`` beyond what the carriage motion can explain — is flagged ``snapped`` (the
environment decides what to do).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchpvs.jacobians import actuator_stiffness

from .robots import Robot, solve_batch

__all__ = ["CarriageModel", "RobotBatch"]


@dataclass(frozen=True)
class CarriageModel:
    """Carriage (actuator stage) parameters. Damping comes from target speeds: a carriage
    pushed with its full-scale force/torque against no elastic load moves at ``max_speed``.

    Attributes:
        kind: ``"overdamped"`` or ``"second_order"``.
        control_period: [s] time per environment step.
        insertion_speed: [m/s] insertion carriage speed at full-scale force (default 20 mm/s).
        rotation_speed: [rad/s] rotation stage speed at full-scale torque (default 90 deg/s).
        insertion_mass: [kg] moving mass of an insertion carriage (second order only).
        rotation_inertia: [kg·m²] rotation stage inertia (second order only).
        max_substeps: most substeps per control period.
        max_insertion_step, max_rotation_step: [m], [rad] most motion per substep.
        stiffness_ratio: largest ``h * lambda_max`` (normalized by damping) per substep.
        max_retries: step halvings after a failed solve.
        snap_jump: [m] a tip jump this much larger than ``2 (sum |dD| + reach max |dalpha|)``
            in one substep counts as a snap.
        snap_twist: [rad] a relative-twist jump this much larger than the change of the
            relative base rotation in one substep counts as a snap (default 30 deg).
    """

    kind: str = "overdamped"
    control_period: float = 0.1
    insertion_speed: float = 0.02
    rotation_speed: float = math.pi / 2
    insertion_mass: float = 0.5
    rotation_inertia: float = 1e-4
    max_substeps: int = 8
    max_insertion_step: float = 2e-3
    max_rotation_step: float = math.radians(10.0)
    stiffness_ratio: float = 4.0
    max_retries: int = 3
    snap_jump: float = 5e-3
    snap_twist: float = math.radians(30.0)

    def __post_init__(self) -> None:
        if self.kind not in ("overdamped", "second_order"):
            raise ValueError(f"CarriageModel.kind must be 'overdamped' or 'second_order', "
                             f"got {self.kind!r}")
        for name in ("control_period", "insertion_speed", "rotation_speed", "insertion_mass",
                     "rotation_inertia", "max_insertion_step", "max_rotation_step",
                     "stiffness_ratio", "snap_jump", "snap_twist"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
                raise ValueError(f"CarriageModel.{name} must be a positive number, got {v!r}")
        if not isinstance(self.max_substeps, int) or self.max_substeps < 1:
            raise ValueError(f"CarriageModel.max_substeps must be an integer >= 1, "
                             f"got {self.max_substeps!r}")


class RobotBatch:
    """State and stepping of ``B`` robots (numpy state, one batched torch solve per substep).

    State arrays (float64): ``x (B, 2N)``, ``v (B, 2N)``, ``g (B, 2N)`` [N, N·m],
    ``tip (B, 3)`` [m] in the base frame, ``margin (B,)`` (smallest scaled stiffness
    eigenvalue), ``at_lower``/``at_upper (B, N)`` stroke-limit flags.
    """

    def __init__(self, robot: Robot, model: CarriageModel, batch_size: int):
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
                or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        self.robot, self.model, self.B = robot, model, batch_size
        N = robot.n_tubes
        self.N = N
        self.damping = np.concatenate([
            np.asarray(robot.force_scale) / model.insertion_speed,
            np.asarray(robot.torque_scale) / model.rotation_speed])          # (2N,)
        self.mass = np.concatenate([np.full(N, model.insertion_mass),
                                    np.full(N, model.rotation_inertia)])
        self.max_step = np.concatenate([np.full(N, model.max_insertion_step),
                                        np.full(N, model.max_rotation_step)])
        self.x = np.zeros((batch_size, 2 * N))
        self.v = np.zeros((batch_size, 2 * N))
        self.g = np.zeros((batch_size, 2 * N))
        self.K = np.zeros((batch_size, 2 * N, 2 * N))
        self.tip = np.zeros((batch_size, 3))
        self.margin = np.zeros(batch_size)
        self.energy = np.zeros(batch_size)          # U*(x) [J], for the step acceptance
        self._parked = np.zeros(batch_size, dtype=bool)   # rejected at a kink (_advance)
        self._park_x = np.zeros((batch_size, 2 * N))
        self._park_try = np.zeros((batch_size, 2 * N))
        self.twist = np.zeros((batch_size, max(N - 1, 0)))
        self.at_lower = np.zeros((batch_size, N), dtype=bool)
        self.at_upper = np.zeros((batch_size, N), dtype=bool)
        self.q: torch.Tensor | None = None           # warm start, (B, nq)
        self.solves = 0                              # batched solver calls (for benchmarks)

    # ------------------------------------------------------------------------------------------
    def _solve(self, x: np.ndarray, q0: torch.Tensor | None):
        self.solves += 1
        return solve_batch(self.robot, x, initial=q0)

    @staticmethod
    def _unpack(eq):
        g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()
        ok = eq.converged.numpy() & np.isfinite(g).all(-1) & np.isfinite(
            eq.tip_position.numpy()).all(-1)
        return (g, eq.tip_position.numpy(), eq.min_stiffness_eigenvalue.numpy(),
                eq.relative_rotation_at_outer_tip.numpy(), eq.energy.detach().numpy(), ok)

    def set_state(self, idx: np.ndarray, x: np.ndarray, eq=None, rows=None) -> np.ndarray:
        """Place robots ``idx`` at ``x (len(idx), 2N)`` at rest; solve unless ``eq`` (an
        Equilibrium whose ``rows`` are these states) is given. Returns the converged mask."""
        D, lo, hi = self.robot.project(x[:, :self.N])
        x = np.concatenate([D, x[:, self.N:]], -1)
        if eq is None:
            eq, rows = self._solve(x, None), np.arange(len(idx))
        g, tip, margin, twist, energy, ok = self._unpack(eq)
        q = eq.q.detach()
        if self.q is None or self.q.shape[-1] != q.shape[-1]:
            self.q = torch.zeros(self.B, q.shape[-1], dtype=q.dtype)
        self.x[idx], self.v[idx] = x, 0.0
        self.g[idx], self.tip[idx], self.margin[idx] = g[rows], tip[rows], margin[rows]
        self.twist[idx], self.energy[idx] = twist[rows], energy[rows]
        self._parked[idx] = False
        self.at_lower[idx], self.at_upper[idx] = lo, hi
        self.q[torch.as_tensor(idx)] = q[torch.as_tensor(rows)]
        self.K[idx] = self._stiffness_of(eq, rows)
        return ok[rows]

    def _stiffness_of(self, eq, rows) -> np.ndarray:
        K = actuator_stiffness(eq).numpy()[rows]
        K = 0.5 * (K + np.swapaxes(K, -1, -2))
        w, V = np.linalg.eigh(K)
        K = (V * np.clip(w, 0.0, None)[..., None, :]) @ np.swapaxes(V, -1, -2)
        return np.nan_to_num(K, nan=0.0, posinf=0.0, neginf=0.0)

    # ------------------------------------------------------------------------------------------
    def n_substeps(self, tau: np.ndarray) -> np.ndarray:
        """Substeps ``(B,)`` for this control period, per robot, from the stiffness and the
        expected motion (so a robot's trajectory does not depend on its batch mates)."""
        h = self.model.control_period
        s = 1.0 / np.sqrt(self.damping)
        Kn = self.K * s[None, :, None] * s[None, None, :]
        lam = np.linalg.eigvalsh(Kn)[:, -1]
        n_stiff = np.ceil(h * lam / self.model.stiffness_ratio)
        motion = np.abs(h * (tau - self.g) / self.damping) / self.max_step
        n_motion = np.ceil(motion.max(-1))
        return np.clip(np.maximum(n_stiff, n_motion), 1, self.model.max_substeps).astype(int)

    def step_force(self, tau: np.ndarray) -> dict[str, np.ndarray]:
        """Advance every robot one control period under commanded ``tau (B, 2N)`` [N, N·m].

        Returns per-robot flags ``solver_failure``, ``snapped`` (bool ``(B,)``), ``tip_jump``
        [m] (largest per substep) and ``substeps``."""
        tau = np.asarray(tau, dtype=np.float64)
        n = self.n_substeps(tau)
        h = self.model.control_period / n
        accept = self._armijo(tau) if self.model.kind == "overdamped" else None
        return self._run(n, lambda idx, frac: self._implicit_step(tau, h[idx] * frac, idx),
                         stiffness=True, accept=accept)

    def _armijo(self, tau: np.ndarray):
        """Sufficient decrease of the overdamped flow's merit ``phi(x) = U*(x) - tau . x``:
        ``b xdot = tau - g(x) = -grad phi`` is a gradient flow, so every substep must lower
        ``phi``. The linearly implicit step does so wherever ``U*`` is smooth, but overshoots
        at a kink of ``U*`` (a tube end crossing a straight-to-curved transition), where
        ``phi`` could rise by O(h). A substep is accepted when (Armijo, c1 = 1e-4)

            phi(x_new) <= phi(x) + c1 * min(0, grad phi(x) . (x_new - x)) + round-off,

        with ``U*(x_new)`` from the substep's own solve: no extra solver call unless a step
        is rejected; a rejected step is retried with the step halved (``max_retries``), and
        a robot whose halved steps all fail stays where it is (``phi`` cannot rise)."""
        c1 = 1e-4

        def accept(idx, x_new, energy_new):
            x0, g0, t = self.x[idx], self.g[idx], tau[idx]
            phi0 = self.energy[idx] - (t * x0).sum(-1)
            phi1 = energy_new - (t * x_new).sum(-1)
            slope = ((g0 - t) * (x_new - x0)).sum(-1)
            noise = 1e-12 * (np.abs(self.energy[idx]) + np.abs(t * x0).sum(-1)) + 1e-15
            return phi1 <= phi0 + c1 * np.minimum(slope, 0.0) + noise

        return accept

    def step_joint(self, dx: np.ndarray) -> dict[str, np.ndarray]:
        """Position-controlled carriages: move by ``dx (B, 2N)`` [m, rad] (projected onto the
        stroke limits) in one control period. Same flags as :meth:`step_force`."""
        dx = np.asarray(dx, dtype=np.float64)
        x0 = self.x.copy()
        period = self.model.control_period
        return self._run(np.ones(self.B, dtype=int),
                         lambda idx, frac: (x0[idx] + frac * dx[idx], frac * dx[idx] / period),
                         stiffness=False)

    def _run(self, n: np.ndarray, propose, stiffness: bool, accept=None):
        failure = np.zeros(self.B, dtype=bool)
        snapped = np.zeros(self.B, dtype=bool)
        jump = np.zeros(self.B)
        N = self.N
        K_eq = []
        for k in range(int(n.max())):
            active = n > k
            tip0, x0, twist0 = self.tip.copy(), self.x.copy(), self.twist.copy()
            skip = failure | ~active
            committed = self._advance(propose, skip, accept)
            failure |= skip & active
            if committed is not None:
                eq, idx, rows = committed
                last = n[idx] == k + 1  # robots finishing their period in this substep
                if len(idx[last]):
                    K_eq.append((eq, idx[last], rows[last]))
            d = np.linalg.norm(self.tip - tip0, axis=-1)
            dx = self.x - x0
            jump = np.maximum(jump, d)
            explained = 2.0 * (np.abs(dx[:, :N]).sum(-1)
                               + self.robot.reach * np.abs(dx[:, N:]).max(-1))
            d_rel = dx[:, N + 1:] - dx[:, N:N + 1]
            d_twist = np.angle(np.exp(1j * (self.twist - twist0 - d_rel)))
            release = (np.abs(d_twist).max(-1, initial=0.0) > self.model.snap_twist)
            snapped |= active & ((d > self.model.snap_jump + explained) | release
                                 | (self.margin <= 0.0))
        if stiffness:
            for eq, idx, rows in K_eq:
                self.K[idx] = self._stiffness_of(eq, rows)
        return {"solver_failure": failure, "snapped": snapped, "tip_jump": jump,
                "substeps": n}

    def _implicit_step(self, tau, h, idx):
        K, x, v, g = self.K[idx], self.x[idx], self.v[idx], self.g[idx]
        I = np.eye(2 * self.N)
        f = tau[idx] - g
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(idx),))[:, None]
        if self.model.kind == "overdamped":
            A = self.damping * I + h[..., None] * K
            dx = np.linalg.solve(A, (h * f)[..., None])[..., 0]
            v_new = dx / h
        else:
            A = (self.mass + h * self.damping)[..., None] * I + (h * h)[..., None] * K
            v_new = np.linalg.solve(A, (self.mass * v + h * f)[..., None])[..., 0]
            dx = h * v_new
        return x + dx, v_new

    def _advance(self, propose, skip, accept=None):
        """One substep for the robots not in ``skip``: propose, project, solve; robots whose
        solve fails, or whose step ``accept(idx, x_new, energy_new)`` rejects, retry from their
        last valid state with the step halved (up to ``max_retries`` times). Robots whose solve
        still fails keep their state and are flagged (``skip`` is updated in place); robots
        whose step is still rejected keep their state unflagged, at rest (at a kink of
        ``U*``). Such a robot is *parked*: while its state and its first proposal stay exactly
        the same (same ``x``, ``tau``, stiffness), the solves and the verdict would repeat
        bit for bit, so it is left at rest without solving again."""
        todo = np.flatnonzero(~skip)
        committed = None
        frac = 1.0
        failed = np.zeros(0, dtype=bool)
        first = np.full(self.x.shape, np.nan)
        for attempt in range(self.model.max_retries + 1):
            if len(todo) == 0:
                break
            x_try, v = propose(todo, frac)
            D, lo, hi = self.robot.project(x_try[:, :self.N])
            x = np.concatenate([D, x_try[:, self.N:]], -1)
            v = v.copy()
            if attempt == 0 and accept is not None:
                same = (self._parked[todo] & (self._park_x[todo] == self.x[todo]).all(-1)
                        & (self._park_try[todo] == x).all(-1))
                self.v[todo[same]] = 0.0
                todo, x, v, lo, hi = (a[~same] for a in (todo, x, v, lo, hi))
                first[todo] = x
                if len(todo) == 0:
                    break
            # inelastic stops: no velocity into an active limit
            vD = v[:, :self.N]
            vD[lo & (vD < 0)] = 0.0
            vD[hi & (vD > 0)] = 0.0
            eq = self._solve(x, self.q[torch.as_tensor(todo)])
            g, tip, margin, twist, energy, converged = self._unpack(eq)
            ok = converged.copy()
            if accept is not None and ok.any():
                ok[ok] = accept(todo[ok], x[ok], energy[ok])
            good = np.flatnonzero(ok)
            idx = todo[good]
            self.x[idx], self.v[idx], self.g[idx] = x[good], v[good], g[good]
            self.tip[idx], self.margin[idx] = tip[good], margin[good]
            self.twist[idx], self.energy[idx] = twist[good], energy[good]
            self.at_lower[idx], self.at_upper[idx] = lo[good], hi[good]
            self.q[torch.as_tensor(idx)] = eq.q.detach()[torch.as_tensor(good)]
            self._parked[idx] = False
            if attempt == 0:
                committed = (eq, idx, good)
            failed = ~converged[~ok]
            todo = todo[~ok]
            frac /= 2
        skip[todo[failed]] = True
        rejected = todo[~failed]
        if len(rejected):  # at a kink: at rest this substep, parked until something changes
            self.v[rejected] = 0.0
            self._parked[rejected] = True
            self._park_x[rejected] = self.x[rejected]
            self._park_try[rejected] = first[rejected]
        return committed
