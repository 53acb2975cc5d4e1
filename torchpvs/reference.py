"""The standard (Kirchhoff-rod) concentric-tube-robot model, solved by shooting: the reference
that the PVS solver is checked against.

This module is deliberately independent of the PVS pipeline (``sections``/``basis``/
``mechanics``/``solver``): it shares only the scene dataclasses. It follows Rucker, Webster,
Chirikjian & Cowan (IJRR 2010) and Dupont, Lock, Itkowitz & Butler (T-RO 2010) in the frames and
signs of ``docs/conventions.md``.

Model
-----
* Backbone arc length ``s`` from the orifice (``s = 0``) to the tip. Tube ``j`` occupies
  ``s in [-D_j, L_j - D_j]`` (material arc length ``sigma = s + D_j``), its exposed length is
  ``l_j = max(0, L_j - D_j)``; tubes present at ``s`` are those with ``l_j > s``. The tip is at
  ``s_tip = max_j l_j``; the *tip tube* is the tube with the largest ``l_j`` (ties: innermost).
* Backbone: twist-free (Bishop) frame ``R(s)``, ``R(0) = I``, ``p(0) = 0``,
  ``R' = R hat([ux, uy, 0])``, ``p' = R e3``. Tube ``j``'s material frame is
  ``R Rz(psi_j)``: its curvature is ``k_j = (Rz(psi_j)^T [ux, uy], psi_j')``.
* Constitutive law ``EI_j``, ``GJ_j``; torsional moment of tube ``j``:
  ``m_j = GJ_j (psi_j' - u*_jz)``. Total moment in the backbone frame ``mb = R^T m`` with
  ``mb_z = sum_present m_j`` and ``mb_xy = sum EI_j Rz(psi_j)(k_j - u*_j)_xy``, i.e. the bending
  closure ``[ux, uy] = (mb_xy + sum EI_j Rz(psi_j) u*_j,xy) / sum EI_j``.
* Balance with a tip force ``F`` and moment ``M`` only: ``n = F``, ``m' = -(R e3) x F``, hence
  ``mb_x' = -uy mb_z + (R^T F)_y``, ``mb_y' = ux mb_z - (R^T F)_x``; per-tube torsion
  ``m_j' = EI_j (k_jx u*_jy - k_jy u*_jx)``, ``psi_j' = u*_jz + m_j / GJ_j``.
* Guide (``s < 0``): straight, rigid, frictionless: tube ``j`` carries a constant torsion, so
  ``psi_j(0) = alpha_j + int_guide u*_jz dsigma + D_j m_j(0) / GJ_j``. A tube entirely inside
  the guide (``l_j = 0``) carries none.
* Boundary conditions: ``m_j(l_j) = 0`` for every tube but the tip tube,
  ``m_tip(s_tip) = e3 . R(s_tip)^T M`` and ``mb_xy(s_tip) = (R(s_tip)^T M)_xy``.

Shooting
--------
Unknowns ``y0``: ``m_j(0)`` for every tube with ``l_j > 0`` (outermost first) and, when the load
is non-zero, ``mb_xy(0)`` (2 components). Residuals: ``m_j(l_j)`` of the non-tip tubes, the tip
tube's torsion condition and, when loaded, the bending condition at the tip: a square system.
Without load ``m(s) = 0`` identically, so the bending is the stiffness-weighted average of the
rotated precurvatures and only the torsion unknowns remain. The ODEs are integrated with
``scipy.integrate.solve_ivp`` (DOP853) section by section, cut at every tube end and every
straight-to-curved transition, and the boundary value problem is solved with
``scipy.optimize.root`` (``hybr``, falling back on ``lm``).

Energy and actuation
--------------------
``U* = sum over the free part of 1/2 EI_j |k_j,xy - u*_j,xy|^2 + 1/2 GJ_j (psi_j' - u*_jz)^2``
(integrated as an extra ODE state) ``+`` the guide: ``1/2 D_j m_j(0)^2 / GJ_j`` and
``int over the guided material of 1/2 EI_j |u*_j,xy|^2`` (precurved material held straight)
``- F . p_tip``. A tip moment is in general not conservative (the rotation vector of the tip is
not a potential), so its work is NOT subtracted from ``U*``: with a tip moment, the actuation
forces and the energy below ignore the moment's virtual work.

``actuation_forces[j] = dU*/dD_j`` by central finite differences of the equilibrium energy
(step ``1e-6 m``, each side re-solved from a warm start); where ``U*(D)`` has a kink (a tube end
or a straight-to-curved transition exactly at the orifice) the central difference is the average
of the insertion and retraction forces. When ``D_j < step`` the one-sided (forward, second order)
difference is used, as ``D_j`` cannot go below 0. ``actuation_torques[j] = dU*/dalpha_j =
-m_j(0)``, the torsion in the guide (0 for a tube entirely in the guide).

Stability
---------
For unloaded scenes the bending can be minimised pointwise, leaving the reduced torsional energy
``int sum_j 1/2 GJ_j (psi_j' - u*_jz)^2 + f(psi) ds`` with
``f = 1/2 sum EI_j |u*_j,xy|^2 - 1/2 |sum EI_j Rz(psi_j) u*_j,xy|^2 / sum EI_j`` plus the guide
springs ``GJ_j / (2 D_j) (psi_j(0) - alpha_j - int_guide u*_jz)^2`` (``psi_j(0) = alpha_j`` when
``D_j = 0``). This is discretised independently of the shooting (piecewise-linear ``psi_j`` on a
fine grid over ``[0, l_j]``, several hundred to ~2000 nodes per tube, finite-difference torsion
terms, analytic second derivatives of ``f`` with trapezoid weights) and its Hessian is evaluated
at the shooting solution. ``min_stiffness_eigenvalue`` is the smallest eigenvalue of
``W^-1/2 H W^-1/2`` with ``W`` the diagonal (lumped) trapezoid weights: it approximates the
smallest eigenvalue of the continuous second-variation operator
``-d/ds (GJ d/ds) + f''(psi)`` (with the guide's Robin conditions), in N per rad^2 (J/m per
rad^2), independent of the grid spacing. ``stable`` = that eigenvalue is positive. For loaded
scenes (and non-converged solves) both are ``None``: the reduction does not apply (the tip
load couples the bending to the position). With no tube beyond the orifice there are no
torsional coordinates: ``stable = True`` and ``min_stiffness_eigenvalue = None``.

Initial guess
-------------
The default guess is zero torsion. For opposed planar precurvatures (e.g. the paper's section
III-B scene, ``alpha_2 = pi``) zero torsion *is* an equilibrium, the symmetric one, which is
unstable there: pass ``initial`` (e.g. ``[0.1, -0.1]`` N m) to reach the stable ones.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.polynomial import polynomial as npoly
from scipy.integrate import solve_ivp
from scipy.linalg import eig_banded
from scipy.optimize import root

from .clock import work_clock
from .scene import Scene, load_scene

__all__ = ["StandardSolution", "solve_standard"]

#: finite-difference step of the actuation forces [m]
FORCE_STEP = 1e-6


# ---------------------------------------------------------------------------------------------
# Problem set-up

def _wrap(a: np.ndarray) -> np.ndarray:
    """Wrap angles to (-pi, pi]."""
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi  # [-pi, pi)
    return np.where(w <= -np.pi, w + 2.0 * np.pi, w)


def _hat(u: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])


class _Problem:
    """Numbers of one scene at one actuation, in arrays (no validation of the actuation order:
    finite-difference neighbours may break the D_j ordering, which the model does not need)."""

    def __init__(self, scene: Scene, D: Sequence[float], alpha: Sequence[float]):
        tubes = scene.tubes
        self.N = N = len(tubes)
        self.EI = np.array([t.bending_stiffness for t in tubes], float)
        self.GJ = np.array([t.torsional_stiffness for t in tubes], float)
        self.L = np.array([t.length for t in tubes], float)
        self.Ls = np.array([t.straight_length for t in tubes], float)
        self.Lc = np.array([t.curved_length for t in tubes], float)
        self.D = np.array(D, float)
        self.alpha = np.array(alpha, float)
        self.coef = [[np.array(ax, float) if len(ax) else np.zeros(1) for ax in t.precurvature]
                     for t in tubes]
        self.F = np.array(scene.load.tip_force, float)
        self.M = np.array(scene.load.tip_moment, float)
        self.loaded = bool(np.any(self.F != 0.0) or np.any(self.M != 0.0))
        self.l = np.maximum(0.0, self.L - self.D)
        self.s_tip = float(self.l.max())
        # tip tube: largest exposed length, ties -> innermost (largest index)
        self.tip = int(max(range(N), key=lambda j: (self.l[j], j)))
        self.active = [j for j in range(N) if self.l[j] > 0.0]
        self.dofs = len(self.active) + (2 if self.loaded and self.active else 0)

        # guide: twist integral and bending energy of precurved material held straight
        self.guide_twist = np.zeros(N)
        self.guide_energy = np.zeros(N)
        for j in range(N):
            T = max(0.0, min(self.D[j], self.L[j]) - self.Ls[j])  # curved material in the guide
            if T > 0.0:
                cx, cy, cz = self.coef[j]
                self.guide_twist[j] = float(npoly.polyval(T, npoly.polyint(cz)))
                sq = npoly.polyadd(npoly.polymul(cx, cx), npoly.polymul(cy, cy))
                self.guide_energy[j] = 0.5 * self.EI[j] * float(npoly.polyval(T, npoly.polyint(sq)))

        # moment scale for the shooting unknowns / residuals [N m]
        umax = 0.0
        for j in range(N):
            if self.Lc[j] > 0.0:
                ts = np.linspace(0.0, self.Lc[j], 9)
                for ax in self.coef[j]:
                    umax = max(umax, float(np.abs(npoly.polyval(ts, ax)).max()))
        ref_len = max(self.s_tip, float(self.L.max()))
        self.m_ref = float(self.EI.max() * max(umax, 1.0 / ref_len)
                           + np.linalg.norm(self.M) + np.linalg.norm(self.F) * ref_len)

        # sections of the free part: cut at every tube end and straight-to-curved transition
        cuts = {0.0, self.s_tip}
        for j in self.active:
            cuts.add(float(self.l[j]))
            st = float(self.Ls[j] - self.D[j])
            if 0.0 < st < self.l[j]:
                cuts.add(st)
        cuts_arr = np.array(sorted(cuts))
        self.sections: list[dict[str, Any]] = []
        for a, b in zip(cuts_arr[:-1], cuts_arr[1:], strict=True):
            if b - a <= 1e-14 * max(1.0, self.s_tip):
                continue
            mid = 0.5 * (a + b)
            P = np.array([j for j in range(N) if self.l[j] > mid], int)
            curved = np.array([mid + self.D[j] > self.Ls[j] for j in P], bool)
            self.sections.append(dict(a=float(a), b=float(b), P=P, curved=curved))

    # -- precurvature -------------------------------------------------------------------------
    def ustar(self, j: int, s: np.ndarray | float, curved: bool) -> np.ndarray:
        """``u*_j`` (3, ...) at backbone arc length ``s`` on the given side of a transition."""
        s = np.asarray(s, float)
        if not curved:
            return np.zeros((3,) + s.shape)
        t = s + self.D[j] - self.Ls[j]
        return np.array([npoly.polyval(t, c) for c in self.coef[j]])

    def psi0(self, m0_full: np.ndarray) -> np.ndarray:
        """``psi_j(0)`` from the guide wind-up (``D_j m_j(0) / GJ_j``; 0 torsion if retracted)."""
        return self.alpha + self.guide_twist + self.D * m0_full / self.GJ

    # -- unknowns ------------------------------------------------------------------------------
    def unpack(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scaled shooting unknowns -> (m_j(0) for all tubes, mb_xy(0)) in N m."""
        m0 = np.zeros(self.N)
        na = len(self.active)
        m0[self.active] = y[:na] * self.m_ref
        mb = y[na:na + 2] * self.m_ref if (self.loaded and na) else np.zeros(2)
        return m0, mb

    def pack(self, m0_full: np.ndarray, mb: np.ndarray) -> np.ndarray:
        parts = [np.asarray(m0_full, float)[self.active] / self.m_ref]
        if self.loaded and self.active:
            parts.append(np.asarray(mb, float) / self.m_ref)
        return np.concatenate(parts) if parts else np.zeros(0)

    # -- ODE -------------------------------------------------------------------------------------
    def _rhs_factory(self, sec: dict[str, Any]):
        N, P, curved = self.N, sec["P"], sec["curved"]
        EI, GJ = self.EI[P], self.GJ[P]
        K = EI.sum()
        loaded, F = self.loaded, self.F
        # precurvature: constant vectors where possible, polynomials otherwise
        const = all((not c) or all(len(ax) == 1 for ax in self.coef[j])
                    for j, c in zip(P, curved, strict=True))
        if const:
            U0 = np.array([[ax[0] for ax in self.coef[j]] if c else [0.0, 0.0, 0.0]
                           for j, c in zip(P, curved, strict=True)]).reshape(len(P), 3)

            def ustar(s: float) -> np.ndarray:
                return U0
        else:
            D, Ls, coef = self.D, self.Ls, self.coef

            def ustar(s: float) -> np.ndarray:
                out = np.zeros((len(P), 3))
                for i, (j, c) in enumerate(zip(P, curved, strict=True)):
                    if c:
                        t = s + D[j] - Ls[j]
                        out[i] = [npoly.polyval(t, ax) for ax in coef[j]]
                return out

        ip, im = 15 + P, 15 + N + P  # psi_j, m_j

        def rhs(s: float, y: np.ndarray) -> np.ndarray:
            dy = np.zeros_like(y)
            R = y[3:12].reshape(3, 3)
            psi, mt = y[ip], y[im]
            us = ustar(s)
            c, sn = np.cos(psi), np.sin(psi)
            rx = c * us[:, 0] - sn * us[:, 1]
            ry = sn * us[:, 0] + c * us[:, 1]
            if loaded:
                mbx, mby = y[12], y[13]
            else:
                mbx = mby = 0.0
            ux = (mbx + EI @ rx) / K
            uy = (mby + EI @ ry) / K
            kx = c * ux + sn * uy
            ky = -sn * ux + c * uy
            dy[0:3] = R[:, 2]
            dR = np.empty((3, 3))
            dR[:, 0] = -uy * R[:, 2]
            dR[:, 1] = ux * R[:, 2]
            dR[:, 2] = uy * R[:, 0] - ux * R[:, 1]
            dy[3:12] = dR.ravel()
            if loaded:
                mbz = mt.sum()
                fb = R.T @ F
                dy[12] = -uy * mbz + fb[1]
                dy[13] = ux * mbz - fb[0]
            dy[ip] = us[:, 2] + mt / GJ
            dy[im] = EI * (kx * us[:, 1] - ky * us[:, 0])
            dy[14] = float(0.5 * EI @ ((kx - us[:, 0]) ** 2 + (ky - us[:, 1]) ** 2)
                           + 0.5 * (mt * mt) @ (1.0 / GJ))
            return dy

        return rhs

    def initial_state(self, m0_full: np.ndarray, mb0: np.ndarray) -> np.ndarray:
        y = np.zeros(15 + 2 * self.N)
        y[3:12] = np.eye(3).ravel()
        y[12:14] = mb0
        y[15:15 + self.N] = self.psi0(m0_full)
        y[15 + self.N:] = m0_full
        return y

    def integrate(self, m0_full: np.ndarray, mb0: np.ndarray, tol: float, dense: bool = False
                  ) -> tuple[np.ndarray, list, bool]:
        """Integrate over all sections; returns (final state, [(a, b, OdeSolution)], ok)."""
        y = self.initial_state(m0_full, mb0)
        pieces = []
        if not hasattr(self, "_rhs"):
            self._rhs = [self._rhs_factory(sec) for sec in self.sections]
        scale = max(self.s_tip, 1e-12)
        for sec, rhs in zip(self.sections, self._rhs, strict=True):
            atol = np.full(y.shape, tol)
            atol[0:3] = tol * scale
            atol[12:14] = tol * self.m_ref
            atol[15 + self.N:] = tol * self.m_ref
            atol[14] = tol * self.m_ref
            sol = solve_ivp(rhs, (sec["a"], sec["b"]), y, method="DOP853", rtol=tol, atol=atol,
                            dense_output=dense)
            if sol.status < 0 or not np.all(np.isfinite(sol.y[:, -1])):
                return y, pieces, False
            y = sol.y[:, -1].copy()
            if dense:
                pieces.append((sec["a"], sec["b"], sol.sol))
            if np.abs(y[15 + self.N:]).max(initial=0.0) > 1e8 * self.m_ref:
                return y, pieces, False
        return y, pieces, True

    def residual(self, yend: np.ndarray) -> np.ndarray:
        """Scaled boundary residuals at the distal ends (see the module docstring)."""
        N = self.N
        mt = yend[15 + N:15 + 2 * N]
        R = yend[3:12].reshape(3, 3)
        Mb = R.T @ self.M
        out = [mt[j] if j != self.tip else mt[j] - Mb[2] for j in self.active]
        if self.loaded and self.active:
            out += [yend[12] - Mb[0], yend[13] - Mb[1]]
        return np.array(out, float) / self.m_ref

    def energy(self, yend: np.ndarray, m0_full: np.ndarray) -> float:
        guide_torsion = 0.5 * self.D * m0_full ** 2 / self.GJ
        return float(yend[14] + guide_torsion.sum() + self.guide_energy.sum()
                     - self.F @ yend[0:3])


# ---------------------------------------------------------------------------------------------
# Solution

@dataclass(frozen=True, eq=False)
class StandardSolution:
    """Equilibrium of the standard model (numpy arrays; see the module docstring for the model).

    Attributes:
        converged: the boundary residual is below the tolerance.
        tip_position: (3,) [m], base frame.
        tip_rotation: (3, 3) ``R(s_tip) Rz(psi_tip(s_tip))``: the material frame of the tip tube.
        relative_rotation_at_outer_tip: (N-1,) [rad] ``psi_j(min(l_j, l_1)) - psi_1(l_1)``,
            ``j = 2..N``, wrapped to (-pi, pi] (the paper's ``theta_2(L_1)``).
        actuation_forces: (N,) [N] ``dU*/dD_j`` (finite differences), ``None`` when not
            computed (``compute_forces=False``) or undefined (not converged).
        actuation_torques: (N,) [N m] ``dU*/dalpha_j = -m_j(0)``.
        energy: ``U*`` [J] (elastic energy minus ``F . p_tip``).
        stable, min_stiffness_eigenvalue: see the module docstring; ``None`` when loaded, not
            converged or not computed.
        residual_norm: Euclidean norm of the boundary residuals divided by the moment scale
            ``m_ref`` (dimensionless).
        iterations: residual evaluations of the root finder (``nfev``).
        dofs: number of shooting unknowns.
        solve_time_s: wall time of the equilibrium solve alone (no forces, no stability).
        y0: (dofs,) shooting unknowns in N m (``m_j(0)`` of the exposed tubes, then ``mb_xy(0)``
            when loaded); usable as ``initial``.
        scene: the scene solved.
        reason: ``"converged"`` or why not (residual, evaluations, time limit).
    """

    converged: bool
    tip_position: np.ndarray
    tip_rotation: np.ndarray
    relative_rotation_at_outer_tip: np.ndarray
    actuation_forces: np.ndarray | None
    actuation_torques: np.ndarray
    energy: float
    stable: bool | None
    min_stiffness_eigenvalue: float | None
    residual_norm: float
    iterations: int
    dofs: int
    solve_time_s: float
    y0: np.ndarray
    scene: Scene
    _m0_full: np.ndarray = field(repr=False)
    _mb0: np.ndarray = field(repr=False)
    _pieces: list = field(repr=False, default_factory=list)
    _psi_end: np.ndarray = field(repr=False, default=None)
    reason: str = "converged"

    # ------------------------------------------------------------------------------------------
    def state_at(self, s: np.ndarray) -> np.ndarray:
        """ODE states (rows: p(3), R(9), mb_xy(2), U, psi(N), m(N)) at arc lengths ``s``."""
        s = np.atleast_1d(np.asarray(s, float))
        n = 15 + 2 * len(self.scene.tubes)
        out = np.zeros((n, s.size))
        if not self._pieces:
            out[3:12] = np.eye(3).ravel()[:, None]
            return out
        for k, (a, b, sol) in enumerate(self._pieces):
            last = k == len(self._pieces) - 1
            mask = (s >= a) & ((s < b) | (last & (s <= b + 1e-15)))
            if k == 0:
                mask |= s < a
            if last:
                mask |= s > b
            if mask.any():
                out[:, mask] = sol(np.clip(s[mask], a, b))
        return out

    def backbone(self, points: int) -> np.ndarray:
        """``(points, 3)`` positions at ``points`` uniformly spaced ``s`` in ``[0, s_tip]``."""
        if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 1:
            raise ValueError(f"points must be a positive integer, got {points!r}")
        s_tip = self._pieces[-1][1] if self._pieces else 0.0
        s = np.linspace(0.0, s_tip, int(points))
        return self.state_at(s)[0:3].T.copy()

    def as_contract(self, backbone_points: int | None = None) -> dict[str, Any]:
        """The JSON-ready dict of docs/conventions.md (plain Python values, no NaN)."""

        def flist(a: Any) -> list:
            return [_fin(v) for v in np.asarray(a, float).ravel()]

        out: dict[str, Any] = {
            "model": "standard",
            "converged": bool(self.converged),
            "tip_position": flist(self.tip_position),
            "tip_rotation": [flist(r) for r in np.asarray(self.tip_rotation)],
            "relative_rotation_at_outer_tip": flist(self.relative_rotation_at_outer_tip),
            "actuation_forces": (None if self.actuation_forces is None
                                 else flist(self.actuation_forces)),
            "actuation_torques": flist(self.actuation_torques),
            "energy": _fin(self.energy),
            "stable": None if self.stable is None else bool(self.stable),
            "min_stiffness_eigenvalue": (None if self.min_stiffness_eigenvalue is None
                                         else _fin(self.min_stiffness_eigenvalue)),
            "residual_norm": _fin(self.residual_norm),
            "iterations": int(self.iterations),
            "dofs": int(self.dofs),
            "solve_time_s": float(self.solve_time_s),
        }
        if backbone_points is not None:
            out["backbone"] = [flist(p) for p in self.backbone(backbone_points)]
        return out


def _fin(v: Any) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


# ---------------------------------------------------------------------------------------------
# Solver

def _check_tol(tol: Any) -> float:
    if isinstance(tol, bool) or not isinstance(tol, (int, float, np.floating, np.integer)):
        raise ValueError(f"tol must be a number in (0, 1e-3], got {tol!r}")
    tol = float(tol)
    if not (math.isfinite(tol) and 0.0 < tol <= 1e-3):
        raise ValueError(f"tol must be a number in (0, 1e-3], got {tol!r}")
    return max(tol, 1e-13)


def _initial_guess(prob: _Problem, initial: Any) -> np.ndarray:
    if initial is None:
        return np.zeros(prob.dofs)
    if isinstance(initial, StandardSolution):
        if len(initial._m0_full) != prob.N:
            raise ValueError(f"initial: a solution of a {len(initial._m0_full)}-tube scene "
                             f"cannot warm-start a {prob.N}-tube scene")
        return prob.pack(initial._m0_full, initial._mb0)
    try:
        arr = np.asarray(initial, float).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"initial must be None, a StandardSolution or an array of {prob.dofs} "
                         f"shooting unknowns [N m], got {type(initial).__name__}") from None
    if arr.shape != (prob.dofs,):
        raise ValueError(f"initial must have {prob.dofs} entries (m_j(0) of the {len(prob.active)}"
                         f" exposed tubes" + (", then mb_xy(0)" if prob.loaded else "")
                         + f"), got shape {np.shape(initial)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("initial must be finite")
    return arr / prob.m_ref


def _conv_tol(tol: float) -> float:
    """Scaled residual norm below which a solve counts as converged."""
    return min(max(1e2 * tol, 1e-10), 1e-6)


class _OutOfTime(Exception):
    """The solve's time limit passed (raised between residual evaluations)."""


@dataclass(eq=False)
class _Shot:
    """A shooting solve (:func:`_shoot`) and, from :func:`_equilibrium`, the state it
    integrates to (``dofs`` unknowns, ``N`` tubes).

    Attributes:
        x: ``(dofs,)`` the scaled unknowns (``m_j(0)``, then ``mb_xy(0)`` with a load, over
            ``m_ref``).
        res: ``(dofs,)`` the scaled residual there.
        nfev: residual evaluations made.
        ok: the residual norm is below the convergence threshold (and, with the state, the
            integration succeeded).
        out_of_time: the time limit stopped the solve.
        m0: ``(N,)`` [N·m] the torsional moments at the orifice; ``mb``: ``(2,)`` [N·m] the
            bending moment there (zero without a load).
        yend: the state vector at the tip (position, rotation, angles, moments).
        pieces: the dense solution pieces along the backbone (``dense=True``), or ``[]``.
        energy: [J] the stored energy minus the load's potential.
    """

    x: np.ndarray
    res: np.ndarray
    nfev: int
    ok: bool
    out_of_time: bool
    m0: np.ndarray | None = None
    mb: np.ndarray | None = None
    yend: np.ndarray | None = None
    pieces: list | None = None
    energy: float | None = None


def _shoot(prob: _Problem, x0: np.ndarray, tol: float,
           deadline: float | None = None) -> _Shot:
    """Solve the boundary value problem from scaled unknowns ``x0`` (stopping at the first
    residual evaluation after ``deadline``, a :func:`~torchpvs.clock.work_clock` value)."""
    conv_tol = _conv_tol(tol)
    xtol = min(tol, 1e-10)
    nfev = 0
    big = 1e6
    out_of_time = False

    def fun(x: np.ndarray) -> np.ndarray:
        nonlocal nfev
        if deadline is not None and nfev > 0 and work_clock() > deadline:
            raise _OutOfTime
        nfev += 1
        m0, mb = prob.unpack(x)
        yend, _, ok = prob.integrate(m0, mb, tol)
        r = prob.residual(yend) if ok else np.full(prob.dofs, big)
        if not np.all(np.isfinite(r)):
            r = np.full(prob.dofs, big)
        return r

    if prob.dofs == 0:
        return _Shot(x=np.zeros(0), res=np.zeros(0), nfev=0, ok=True, out_of_time=False)
    best_x, best_r = x0, fun(x0)
    if np.linalg.norm(best_r) > conv_tol:
        for method, opts in (("hybr", {"xtol": xtol, "eps": tol, "maxfev": 200 * (prob.dofs + 1)}),
                             ("lm", {"xtol": xtol, "ftol": xtol * 1e-2, "eps": tol,
                                     "maxiter": 200 * (prob.dofs + 1)})):
            try:
                sol = root(fun, best_x, method=method, options=opts)
                x = np.asarray(sol.x, float)
                r = fun(x)
            except _OutOfTime:
                out_of_time = True
                break
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                continue
            if np.all(np.isfinite(x)) and np.linalg.norm(r) < np.linalg.norm(best_r):
                best_x, best_r = x, r
            if np.linalg.norm(best_r) <= conv_tol:
                break
    return _Shot(x=best_x, res=best_r, nfev=nfev, ok=bool(np.linalg.norm(best_r) <= conv_tol),
                 out_of_time=out_of_time)


def _equilibrium(prob: _Problem, x0: np.ndarray, tol: float, dense: bool,
                 deadline: float | None = None) -> _Shot:
    out = _shoot(prob, x0, tol, deadline)
    m0, mb = prob.unpack(out.x)
    yend, pieces, ok = prob.integrate(m0, mb, tol, dense=dense)
    if dense and not pieces:  # nothing exposed: a constant "solution" at s = 0
        y_init = yend.copy()
        pieces = [(0.0, 0.0, lambda s, y=y_init: np.repeat(y[:, None], np.size(s), axis=1))]
    out.m0, out.mb, out.yend, out.pieces = m0, mb, yend, pieces
    out.energy = prob.energy(yend, m0)
    if not ok:
        out.ok = False
    return out


def _actuation_forces(scene: Scene, prob: _Problem, x_full: tuple[np.ndarray, np.ndarray],
                      tol: float, base_energy: float) -> np.ndarray:
    h = FORCE_STEP
    forces = np.zeros(prob.N)

    def energy_at(D: np.ndarray) -> float:
        p = _Problem(scene, D, prob.alpha)
        res = _equilibrium(p, p.pack(*x_full), tol, dense=False)
        return res.energy

    for j in range(prob.N):
        Dp = prob.D.copy()
        Dp[j] += h
        if prob.D[j] >= h:
            Dm = prob.D.copy()
            Dm[j] -= h
            forces[j] = (energy_at(Dp) - energy_at(Dm)) / (2.0 * h)
        else:  # D_j cannot go below 0: forward second-order difference
            Dpp = prob.D.copy()
            Dpp[j] += 2.0 * h
            forces[j] = (-3.0 * base_energy + 4.0 * energy_at(Dp) - energy_at(Dpp)) / (2.0 * h)
    return forces


def _stability(prob: _Problem, sol_state, nodes_target: int = 1500) -> float:
    """Smallest eigenvalue of the mass-normalised Hessian of the reduced torsional energy on a
    fine grid (see the module docstring)."""
    N = prob.N
    cuts = sorted({sec["a"] for sec in prob.sections} | {sec["b"] for sec in prob.sections})
    s_tip = prob.s_tip
    # spacing: nodes_target over the robot, at least 400 nodes on the shortest exposed tube,
    # never finer than s_tip / 20000
    h_grid = max(min(s_tip / nodes_target, min(prob.l[j] for j in prob.active) / 400.0),
                 s_tip / 20000.0)
    grid = [np.array([cuts[0]])]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        n = max(4, int(math.ceil((b - a) / h_grid)))
        grid.append(np.linspace(a, b, n + 1)[1:])
    s = np.concatenate(grid)
    n_nodes = s.size
    states = sol_state(s)
    psi = states[15:15 + N]  # (N, n_nodes)

    # unknown numbering: node-major, tubes present at the node (s_i <= l_j), fixed psi_j(0)
    # dropped when D_j = 0
    idx = -np.ones((N, n_nodes), int)
    k = 0
    for i in range(n_nodes):
        for j in prob.active:
            if s[i] <= prob.l[j] * (1 + 1e-12) + 1e-15 and not (i == 0 and prob.D[j] == 0.0):
                idx[j, i] = k
                k += 1
    n = k
    if n == 0:
        return float("inf")
    H: dict[tuple[int, int], float] = {}
    W = np.zeros(n)

    def add(a: int, b: int, v: float) -> None:
        if a < 0 or b < 0:
            return
        key = (a, b) if a >= b else (b, a)
        H[key] = H.get(key, 0.0) + v

    for j in prob.active:  # guide springs
        if prob.D[j] > 0.0:
            add(idx[j, 0], idx[j, 0], prob.GJ[j] / prob.D[j])

    for i in range(n_nodes - 1):
        h = s[i + 1] - s[i]
        mid = 0.5 * (s[i] + s[i + 1])
        P = [j for j in prob.active if prob.l[j] > mid]
        if not P:
            continue
        K = prob.EI[P].sum()
        for j in P:  # torsion, finite differences
            g = prob.GJ[j] / h
            a, b = idx[j, i], idx[j, i + 1]
            add(a, a, g)
            add(b, b, g)
            add(b, a, -g)
            if a >= 0:
                W[a] += 0.5 * h
            if b >= 0:
                W[b] += 0.5 * h
        for node in (i, i + 1):  # reduced bending potential, trapezoid rule
            w = {}
            for j in P:
                curved = mid + prob.D[j] > prob.Ls[j]
                us = prob.ustar(j, s[node], curved)
                c, sn = math.cos(psi[j, node]), math.sin(psi[j, node])
                w[j] = prob.EI[j] * np.array([c * us[0] - sn * us[1], sn * us[0] + c * us[1]])
            v = sum(w.values())
            for j in P:
                for q in P:
                    val = -(w[j] @ w[q]) / K
                    if j == q:
                        val += (v @ w[j]) / K
                    if q <= j:  # each unordered pair once (add() symmetrises by storage)
                        add(idx[j, node], idx[q, node], 0.5 * h * val)
    # banded storage (lower), mass normalisation
    bw = max(a - b for (a, b) in H) if H else 0
    ab = np.zeros((bw + 1, n))
    winv = 1.0 / np.sqrt(np.where(W > 0, W, 1.0))
    for (a, b), v in H.items():
        ab[a - b, b] += v * winv[a] * winv[b]
    ev = eig_banded(ab, lower=True, eigvals_only=True, select="i", select_range=(0, 0))
    return float(ev[0])


def solve_standard(scene: Scene | Any, *, tol: float = 1e-10, initial: Any = None,
                   compute_forces: bool = True, compute_stability: bool = True,
                   time_limit: float | None = 120.0) -> StandardSolution:
    """Equilibrium of the standard (Kirchhoff) CTR model by shooting.

    Args:
        scene: a :class:`~torchpvs.scene.Scene` (or anything :func:`load_scene` accepts).
        tol: relative/absolute tolerance of the ODE integration (``rtol``; ``atol`` scaled to
            lengths and moments) and of the root finder; the solve counts as converged when the
            scaled residual norm is below ``min(max(100 tol, 1e-10), 1e-6)``. In (0, 1e-3];
            values below 1e-13 are used as 1e-13 (the integrator's floor).
        initial: ``None`` (zero torsion), a :class:`StandardSolution` (warm start, any scene
            with the same number of tubes) or an array of ``dofs`` shooting unknowns [N m].
        compute_forces: compute ``actuation_forces`` by finite differences (2 N extra solves);
            otherwise ``actuation_forces`` is ``None``.
        compute_stability: compute ``stable``/``min_stiffness_eigenvalue`` (unloaded scenes).
        time_limit: [s] bound on the equilibrium solve (checked between residual evaluations;
            ``None``: no bound). Past it the solve stops with ``converged=False`` and says so in
            ``reason`` (stiff scenes, e.g. G = 1e3 Pa, can take many minutes).

    Never raises on a failed solve: returns ``converged=False`` with the residual and a
    ``reason``.
    """
    scene = load_scene(scene) if not isinstance(scene, Scene) else scene
    tol = _check_tol(tol)
    prob = _Problem(scene, scene.actuation.insertion, scene.actuation.rotation)
    x0 = _initial_guess(prob, initial)

    if time_limit is not None and not (time_limit > 0):
        raise ValueError(f"time_limit must be a positive number of seconds or None, "
                         f"got {time_limit!r}")
    t0 = time.perf_counter()
    res = _equilibrium(prob, x0, tol, dense=True,
                       deadline=None if time_limit is None else work_clock() + time_limit)
    solve_time = time.perf_counter() - t0

    N = prob.N
    yend, m0 = res.yend, res.m0
    R = yend[3:12].reshape(3, 3)
    psi_end = yend[15:15 + N]  # psi_j frozen beyond l_j: psi_j(l_j)
    c, sn = math.cos(psi_end[prob.tip]), math.sin(psi_end[prob.tip])
    Rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
    tip_rot = R @ Rz

    pieces = res.pieces

    def state_fn(s: np.ndarray) -> np.ndarray:
        tmp = StandardSolution.__new__(StandardSolution)
        object.__setattr__(tmp, "_pieces", pieces)
        object.__setattr__(tmp, "scene", scene)
        return StandardSolution.state_at(tmp, s)

    # relative rotation at the outer tube's end: psi_j(min(l_j, l_1)) - psi_1(l_1)
    if N > 1:
        st = state_fn(np.array([prob.l[0]]))[15:15 + N, 0]
        rel = np.array([(st[j] if prob.l[j] >= prob.l[0] else psi_end[j]) - st[0]
                        for j in range(1, N)])
        rel = _wrap(rel)
    else:
        rel = np.zeros(0)

    converged = bool(res.ok)
    if converged:
        reason = "converged"
    else:
        reason = (f"scaled residual {float(np.linalg.norm(res.res)):.3g} > "
                  f"{_conv_tol(tol):.3g} after {int(res.nfev)} evaluations")
        if res.out_of_time:
            reason += f"; time limit {time_limit:g} s reached"
    forces = None
    if compute_forces and converged:
        forces = _actuation_forces(scene, prob, (m0, res.mb), tol, res.energy)
    stable = ev = None
    if compute_stability and converged and not prob.loaded and prob.active:
        ev = _stability(prob, state_fn)
        stable = bool(ev > 0.0)
    elif compute_stability and converged and not prob.loaded:
        ev, stable = None, True  # nothing exposed: no torsional coordinates, trivially stable

    y0 = res.x * prob.m_ref
    return StandardSolution(
        converged=converged,
        tip_position=yend[0:3].copy(),
        tip_rotation=tip_rot,
        relative_rotation_at_outer_tip=rel,
        actuation_forces=forces,
        actuation_torques=-m0.copy(),
        energy=float(res.energy),
        stable=stable,
        min_stiffness_eigenvalue=ev,
        residual_norm=float(np.linalg.norm(res.res)),
        iterations=int(res.nfev),
        dofs=int(prob.dofs),
        solve_time_s=float(solve_time),
        y0=y0,
        scene=scene,
        _m0_full=m0.copy(),
        _mb0=np.asarray(res.mb, float).copy(),
        _pieces=pieces,
        _psi_end=psi_end.copy(),
        reason=reason,
    )
