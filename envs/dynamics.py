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
Contact (two-sided, inelastic): the carriages stop at their stroke ends and against each
other at the nesting stop (``D_j = D_{j-1}``) and the tip-order stop
(``L_j - D_j = L_{j-1} - D_{j-1}``), the set ``G D <= c`` of :meth:`envs.robots.Robot.constraints`.
Each substep's unconstrained solution ``x_u`` is replaced by the feasible point nearest to it in
the step's own metric ``A`` (``diag(b) + h K+``, or ``diag(m) + h diag(b) + h^2 K+``):

    x_new = argmin_{G D <= c} (x - x_u)^T A (x - x_u)   (a small QP, Goldfarb-Idnani),

which is the implicit step with contact forces ``f_c = -G^T lambda / h`` (``/ h^2`` second
order), ``lambda >= 0``, complementary to the gaps. So carriages in contact move together under
their NET force (overdamped: pair velocity = summed force / summed damping; second order: with
the summed masses) and separate as soon as the contact force would have to pull; a stop reached
in a substep absorbs the momentum into it (inelastic). ``step_force`` reports the contact
forces averaged over the control period. Joint control (position-controlled carriages) uses the
same projection in the Euclidean metric: the feasible actuation nearest the command, no carriage
taking precedence.

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
from typing import NamedTuple

import numpy as np

from .plant import Plants, PlantVariation, Solved, solved_from
from .robots import Robot

__all__ = ["CarriageModel", "RobotBatch", "StepFlags"]


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


def project_in_metric(xu: np.ndarray, A: np.ndarray, G: np.ndarray, c: np.ndarray,
                      tol: float = 1e-12, max_iter: int = 100):
    """``argmin_{G x <= c} 0.5 (x - xu)^T A (x - xu)`` for one point ``xu (n,)`` and SPD ``A``,
    by Goldfarb and Idnani's dual active-set method (Math. Programming 27, 1983): start at
    ``xu``, add the most violated constraint, drop constraints whose multiplier would turn
    negative; the active rows stay linearly independent, so degenerate corners (a carriage at
    its stroke end and at its neighbour at once) are handled.

    Returns ``(x, lam, ok)``: the projection, the multipliers ``lam (m,) >= 0`` with
    ``A (x - xu) = -G^T lam`` (KKT) and whether it converged (``False``: infeasible set or
    ``max_iter`` reached; ``x`` is then ``xu``)."""
    Ainv = np.linalg.inv(A)
    x = np.array(xu, dtype=np.float64, copy=True)
    active: list[int] = []
    u = np.zeros(0)
    for _ in range(max_iter):
        slack = c - G @ x
        slack[active] = np.inf
        p = int(np.argmin(slack))
        if slack[p] >= -tol:
            lam = np.zeros(len(c))
            lam[active] = u
            return x, lam, True
        n_p = -G[p]                      # constraint n_p . x >= -c_p, violated
        up = np.append(u, 0.0)
        added = False
        for _ in range(max_iter):
            if active:
                Nw = -G[active].T                                  # (n, q)
                Nstar = np.linalg.solve(Nw.T @ Ainv @ Nw, Nw.T @ Ainv)
                z = (Ainv - Ainv @ Nw @ Nstar) @ n_p              # primal step direction
                r = Nstar @ n_p                                   # dual step direction
            else:
                z, r = Ainv @ n_p, np.zeros(0)
            pos = r > 0
            t1, k = np.inf, -1
            if pos.any():
                ratios = np.where(pos, up[:-1] / np.where(pos, r, 1.0), np.inf)
                k = int(np.argmin(ratios))
                t1 = float(ratios[k])
            zn = float(z @ n_p)
            scale = float(n_p @ Ainv @ n_p)
            t2 = (G[p] @ x - c[p]) / zn if zn > 1e-12 * scale else np.inf
            if not (np.isfinite(t1) or np.isfinite(t2)):
                return np.array(xu, dtype=np.float64, copy=True), np.zeros(len(c)), False
            t = min(t1, t2)
            if np.isfinite(t2):
                x = x + t * z
            up[:-1] -= t * r
            up[-1] += t
            if t2 <= t1:
                active.append(p)
                u = up
                added = True
                break
            del active[k]                 # its multiplier reached zero: the contact opens
            up = np.delete(up, k)
        if not added:
            break
    return np.array(xu, dtype=np.float64, copy=True), np.zeros(len(c)), False


class StepFlags(NamedTuple):
    """What one control period of :meth:`RobotBatch.step_force` / :meth:`RobotBatch.step_joint`
    reports per robot: ``solver_failure``, ``snapped`` bool ``(B,)``; ``tip_jump`` ``(B,)`` [m]
    the largest tip motion in one substep; ``substeps`` ``(B,)`` int; the contact forces
    averaged over the period [N] (signs in :meth:`RobotBatch.contact_forces`): ``stop_force
    (B, N)`` from the stroke ends, ``contact_force (B, N-1)`` between neighbouring carriages."""

    solver_failure: np.ndarray
    snapped: np.ndarray
    tip_jump: np.ndarray
    substeps: np.ndarray
    stop_force: np.ndarray
    contact_force: np.ndarray


class RobotBatch:
    """State and stepping of ``B`` robots: numpy state throughout, one batched solve per
    substep (the compiled warm solve, or ``torchpvs.solve``: :meth:`envs.plant.Plants.warm`;
    actuations in, :class:`envs.plant.Solved` arrays out).

    State arrays (float64): ``x (B, 2N)``, ``v (B, 2N)``, ``g (B, 2N)`` [N, N·m],
    ``tip (B, 3)`` [m] in the base frame, ``margin (B,)`` (smallest scaled stiffness
    eigenvalue), ``at_lower``/``at_upper (B, N)`` stroke-limit flags, ``q (B, nq)`` the
    solver coordinates of the last equilibrium (the warm start of the next solve).

    The batch owns its solves (:class:`envs.plant.Plants`, the nominal robot's when ``plants``
    is ``None``): the robot's plan is looked up once, and the actuations it solves at are ones
    it produced (projected onto the feasible set from validated actions), so they are not
    re-checked per substep; :meth:`set_state` checks the states it is given.
    """

    def __init__(self, robot: Robot, model: CarriageModel, batch_size: int, plants=None):
        if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
                or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        self.robot, self.model, self.B = robot, model, batch_size
        # the robots' plants (envs.plant.Plants): per-robot tubes and tip loads; the nominal
        # robot's without them
        self.plants = plants if plants is not None else Plants(robot, PlantVariation(),
                                                               batch_size)
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
        # the same stiffness before clipping (RobotState.stiffness): its negative directions
        # are the torque-controlled instabilities that precede snaps (benchmarks/snap_causes)
        self.K_unclipped = np.zeros((batch_size, 2 * N, 2 * N))
        self.tip = np.zeros((batch_size, 3))
        self.margin = np.zeros(batch_size)
        self.energy = np.zeros(batch_size)          # U*(x) [J], for the step acceptance
        self._parked = np.zeros(batch_size, dtype=bool)   # rejected at a kink (_advance)
        self._park_x = np.zeros((batch_size, 2 * N))
        self._park_try = np.zeros((batch_size, 2 * N))
        self._park_g = np.full((batch_size, 2 * N), np.nan)   # g at the rejected try
        self.twist = np.zeros((batch_size, max(N - 1, 0)))
        self.at_lower = np.zeros((batch_size, N), dtype=bool)
        self.at_upper = np.zeros((batch_size, N), dtype=bool)
        self.q: np.ndarray | None = None             # warm start, (B, nq)
        self.solves = 0                              # batched solver calls (for benchmarks)
        G, self._c = robot.constraints()             # G D <= c on the insertions
        self._G = np.concatenate([G, np.zeros_like(G)], -1)    # (m, 2N): no rotation limits
        self.contact_fallbacks = 0                   # contact QPs that failed (clipped instead)

    # ------------------------------------------------------------------------------------------
    def _warm(self, x: np.ndarray, idx: np.ndarray, stiffness: bool) -> Solved:
        """Equilibria of robots ``idx`` at feasible, finite ``x`` (their own plants), warm
        from their last ones (:meth:`envs.plant.Plants.warm`)."""
        self.solves += 1
        return self.plants.warm(x, idx, self.q[idx], stiffness=stiffness)

    def set_state(self, idx: np.ndarray, x: np.ndarray, eq=None, rows=None) -> np.ndarray:
        """Place robots ``idx`` at ``x (len(idx), 2N)`` at rest (insertions projected onto the
        feasible set); solve unless ``eq`` (an Equilibrium whose ``rows`` are these states) is
        given. Returns the converged mask. Raises ``ValueError`` for an ``x`` of another shape
        or with non-finite entries."""
        idx = np.asarray(idx, dtype=int)
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (len(idx), 2 * self.N):
            raise ValueError(f"x must have shape ({len(idx)}, {2 * self.N}) (one row of "
                             f"insertions then rotations per robot of idx), got {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError("x must be finite (insertions [m] and rotations [rad])")
        D, lo, hi = self.robot.project(x[:, :self.N])
        x = np.concatenate([D, x[:, self.N:]], -1)
        if eq is None:
            self.solves += 1
            eq, rows = self.plants.solve(x, idx), np.arange(len(idx))
        s = solved_from(eq)
        if self.q is None or self.q.shape[-1] != s.q.shape[-1]:
            self.q = np.zeros((self.B, s.q.shape[-1]), dtype=s.q.dtype)
        self.x[idx], self.v[idx] = x, 0.0
        self.g[idx], self.tip[idx], self.margin[idx] = s.g[rows], s.tip[rows], s.margin[rows]
        self.twist[idx], self.energy[idx] = s.twist[rows], s.energy[rows]
        self._parked[idx] = False
        self.at_lower[idx], self.at_upper[idx] = lo, hi
        self.q[idx] = s.q[rows]
        self.K[idx], self.K_unclipped[idx] = self._stiffness_of(s, rows)
        return s.ok[rows]

    def compensation(self, direction: np.ndarray) -> np.ndarray:
        """The elastic load ``(B, 2N)`` [N, N·m] to hold against when commanding motion in
        ``direction (B, 2N)`` (its signs): ``g(x)``, except for an insertion carriage parked
        at a kink of ``U*`` (its last step rejected there, see :meth:`_advance`) and commanded
        the way that step went, which gets the force its rejected step met beyond the kink.
        At a convex corner of ``U*`` the two one-sided forces differ (1.6 N at the Fig. 3
        outer tube's straight-to-curved transition); compensating with the near side's
        leaves every push below the jump parked at the corner, while a large enough step
        jumps over it (the acceptance compares with the start of the step), so whether a
        compensated carriage passed depended on its step size."""
        g = self.g.copy()
        d_try = self._park_try - self._park_x
        far = ((self._parked & (self._park_x == self.x).all(-1))[:, None]
               & (d_try != 0) & (np.sign(direction) == np.sign(d_try))
               & np.isfinite(self._park_g))
        far[:, self.N:] = False        # U* has kinks in the insertions only
        g[far] = self._park_g[far]
        return g

    @staticmethod
    def _stiffness_of(s: Solved, rows) -> tuple[np.ndarray, np.ndarray]:
        """``(K_clipped, K)`` of the solve ``s``'s ``rows``: ``K`` the symmetrized actuator
        stiffness ``dtau/dx``, ``K_clipped`` its positive part (the implicit step's; non-finite
        entries zero)."""
        K = s.stiffness(np.asarray(rows))
        K = 0.5 * (K + np.swapaxes(K, -1, -2))
        w, V = np.linalg.eigh(K)
        Kc = (V * np.clip(w, 0.0, None)[..., None, :]) @ np.swapaxes(V, -1, -2)
        return np.nan_to_num(Kc, nan=0.0, posinf=0.0, neginf=0.0), K

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

    def step_force(self, tau: np.ndarray) -> StepFlags:
        """Advance every robot one control period under commanded ``tau (B, 2N)`` [N, N·m].

        Returns the per-robot :class:`StepFlags` (failures, snaps, tip jump, substeps and the
        contact forces averaged over the control period)."""
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

    def step_joint(self, dx: np.ndarray) -> StepFlags:
        """Position-controlled carriages: move by ``dx (B, 2N)`` [m, rad] (projected onto the
        stroke limits) in one control period. Same flags as :meth:`step_force`."""
        dx = np.asarray(dx, dtype=np.float64)
        x0 = self.x.copy()
        period = self.model.control_period
        eye = np.broadcast_to(np.eye(2 * self.N), (self.B, 2 * self.N, 2 * self.N))

        def propose(idx, frac):
            # position control: the feasible actuation nearest the command (Euclidean), no
            # contact force reported (the carriages' position loops carry it)
            x, _ = self._contact(x0[idx] + frac * dx[idx], eye[idx])
            return x, (x - x0[idx]) / period, np.zeros((len(idx), len(self._c)))

        return self._run(np.ones(self.B, dtype=int), propose, stiffness=False)

    def _run(self, n: np.ndarray, propose, stiffness: bool, accept=None):
        self._impulse = np.zeros((self.B, len(self._c)))   # contact impulses this period
        failure = np.zeros(self.B, dtype=bool)
        snapped = np.zeros(self.B, dtype=bool)
        jump = np.zeros(self.B)
        N = self.N
        K_eq = []
        for k in range(int(n.max())):
            active = n > k
            tip0, x0, twist0 = self.tip.copy(), self.x.copy(), self.twist.copy()
            skip = failure | ~active
            committed = self._advance(propose, skip, accept, stiffness)
            failure |= skip & active
            if committed is not None:
                s, idx, rows = committed
                last = n[idx] == k + 1  # robots finishing their period in this substep
                if len(idx[last]):
                    K_eq.append((s, idx[last], rows[last]))
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
            for s, idx, rows in K_eq:
                self.K[idx], self.K_unclipped[idx] = self._stiffness_of(s, rows)
        stop, pair = self.contact_forces(self._impulse / self.model.control_period)
        return StepFlags(solver_failure=failure, snapped=snapped, tip_jump=jump, substeps=n,
                         stop_force=stop, contact_force=pair)

    # -- contact --------------------------------------------------------------------------------
    TOL = 1e-12  # [m] feasibility tolerance of the contact solve (positions are ~0.1 m)

    def _contact(self, x_u: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The feasible points nearest to ``x_u (k, 2N)`` in the metrics ``A (k, 2N, 2N)``
        (:func:`project_in_metric`) and the multipliers ``lam (k, m)`` of the rows of
        :meth:`Robot.constraints`. Only robots whose ``x_u`` leaves the feasible set are
        solved; one whose solve fails is clipped outermost-first (counted in
        ``contact_fallbacks``, with no contact force)."""
        x = x_u.copy()
        lam = np.zeros((len(x_u), len(self._c)))
        out = (x_u @ self._G.T - self._c > self.TOL).any(-1)
        for i in np.flatnonzero(out):
            xi, li, ok = project_in_metric(x_u[i], A[i], self._G, self._c, self.TOL)
            if not ok:
                self.contact_fallbacks += 1
                xi = x_u[i].copy()
                xi[:self.N] = self.robot.project(xi[None, :self.N])[0][0]
            x[i], lam[i] = xi, li
        return x, lam

    def contact_forces(self, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Split the multipliers (or forces) of the constraint rows into ``(stop (k, N),
        pair (k, N-1))``: the force of the stroke ends on each insertion carriage along
        ``+D`` (``> 0`` at the lower end, ``< 0`` at the upper end) and the force of carriage
        ``j-1`` on carriage ``j`` along ``+D_j`` (``> 0`` at the nesting stop, the outer
        carriage pushing the inner one back; ``< 0`` at the tip-order stop)."""
        N = self.N
        stop = lam[:, 0:2 * N:2] - lam[:, 1:2 * N:2]
        pair = lam[:, 2 * N::2] - lam[:, 2 * N + 1::2]
        return stop, pair

    def _implicit_step(self, tau, h, idx):
        K, x, v, g = self.K[idx], self.x[idx], self.v[idx], self.g[idx]
        I = np.eye(2 * self.N)
        f = tau[idx] - g
        h = np.broadcast_to(np.asarray(h, dtype=np.float64), (len(idx),))[:, None]
        if self.model.kind == "overdamped":
            A = self.damping * I + h[..., None] * K
            dx = np.linalg.solve(A, (h * f)[..., None])[..., 0]
            per_force = h                  # A dx = h (f + f_c)
        else:
            A = (self.mass + h * self.damping)[..., None] * I + (h * h)[..., None] * K
            v_new = np.linalg.solve(A, (self.mass * v + h * f)[..., None])[..., 0]
            dx = h * v_new
            per_force = h * h              # A dx = h (m v + h (f + f_c))
        # both are quadratic programs in the new position with the metric A: the contact
        # solve adds the contact impulse -G^T lam, i.e. the force -G^T lam / per_force
        x_new, lam = self._contact(x + dx, A)
        return x_new, (x_new - x) / h, lam / per_force * h     # contact impulse [N·s] per row

    def _advance(self, propose, skip, accept=None, stiffness: bool = False):
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
        first_g = np.full(self.x.shape, np.nan)
        for attempt in range(self.model.max_retries + 1):
            if len(todo) == 0:
                break
            x_try, v, impulse = propose(todo, frac)
            # the proposal is feasible (contact solve); this only puts round-off onto the
            # limits and reads which are active
            D, lo, hi = self.robot.project(x_try[:, :self.N], tol=self.TOL)
            x = np.concatenate([D, x_try[:, self.N:]], -1)
            v = v.copy()
            if attempt == 0 and accept is not None:
                same = (self._parked[todo] & (self._park_x[todo] == self.x[todo]).all(-1)
                        & (self._park_try[todo] == x).all(-1))
                self.v[todo[same]] = 0.0
                todo, x, v, lo, hi, impulse = (a[~same] for a in (todo, x, v, lo, hi, impulse))
                first[todo] = x
                if len(todo) == 0:
                    break
            s = self._warm(x, todo, stiffness and attempt == 0)
            converged = s.ok
            ok = converged.copy()
            if attempt == 0:
                first_g[todo[converged]] = s.g[converged]
            if accept is not None and ok.any():
                ok[ok] = accept(todo[ok], x[ok], s.energy[ok])
            good = np.flatnonzero(ok)
            idx = todo[good]
            self.x[idx], self.v[idx], self.g[idx] = x[good], v[good], s.g[good]
            self.tip[idx], self.margin[idx] = s.tip[good], s.margin[good]
            self.twist[idx], self.energy[idx] = s.twist[good], s.energy[good]
            self.at_lower[idx], self.at_upper[idx] = lo[good], hi[good]
            self.q[idx] = s.q[good]
            self._parked[idx] = False
            self._impulse[idx] += impulse[good]
            if attempt == 0:
                committed = (s, idx, good)
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
            self._park_g[rejected] = first_g[rejected]
        return committed
