"""Stage 5c — the control-loop solve: a warm, fixed-discretization equilibrium in one compiled
call per step.

:func:`torchpvs.solve` re-chooses the discretization at every call (the order check, the
Magnus check), computes the actuation forces and builds an :class:`~torchpvs.Equilibrium`
around its tensors; at a batch of one that glue, not arithmetic, is nearly all of its time
(docs/performance.md). A control loop steps the same robot by small actuator moves, where the
discretization chosen once stays valid and the previous solution is the warm start. Then the
whole step is ONE compiled call per batch: the input checks, the layout and energy maps at the
new actuation (:func:`torchpvs.compiled_layout.layout_maps_arrays`), then, per element, the
rotation predictor, the damped Newton solve of :mod:`torchpvs.compiled`, the tip pose and the
stability verdict; on request the actuation forces (with their one-sided values at kinks) and
the control step (tip Jacobian, actuator stiffness) in the same call.

:class:`Tracker` is that loop. It is built from a scene by one default :func:`torchpvs.solve`
(which picks the basis order and Magnus steps for the requested accuracy at the scene's
actuation, or takes them from ``options``) and keeps, per element, the last coordinates and
Hessian. Each :meth:`Tracker.step` computes what ``torchpvs.solve(scene, insertion=...,
rotation=..., initial=previous, options=SolverOptions(order=k, n_magnus=m))`` computes for the
pose, the forces and ``Equilibrium.jacobians()``: the same layout, predictor, Newton iteration,
tip pose and closed forms (``tests/test_tracker.py`` compares them step by step). It does not
re-check the discretization, carry gradients or take a tip load; for those, and whenever a step
does not converge, :func:`torchpvs.solve` is the tool (:meth:`Tracker.equilibrium` runs it at
the tracker's state).

:meth:`Tracker.solve_from` is the same call for any rows from warm starts the caller keeps
(no predictor, the tracker's state untouched; optionally split across threads): the
environments' substeps (``envs/plant.py``) solve there, with the stability margin, the
relative twist, the energy and the actuator stiffness from the same call.

Where it applies: CPU, float64, numba importable, an unloaded scene.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np
import torch

from . import compiled
from .basis import gauss_legendre
from .compiled import (
    cholesky,
    cut_slopes,
    factor_leading,
    guide_curved,
    horner,
    horner_derivative,
    horner_integral,
    lu_solve,
    newton_into,
    partials_one,
    pose_one,
    section_moved,
    section_step_one,
    solve_leading,
    step_one,
)
from .compiled_layout import layout_maps_arrays
from .compiled_load import cached_jit
from .forces import KINK_DELTA, KINK_TOL
from .kernel import VANISHING
from .newton import stability_threshold, tolerance
from .options import SolverOptions
from .order_control import newton_tol
from .predictor import PREDICTOR_TRUST
from .scene import Scene, load_scene
from .sections import n_coordinates

# the precurvature polynomials' components (int64: numba compiles once per literal value)
_X, _Y, _Z = np.int64(0), np.int64(1), np.int64(2)

__all__ = ["Tracker", "TrackState", "layout_and_track", "solve_core"]


@dataclass(frozen=True)
class TrackState:
    """One :meth:`Tracker.step`'s result, numpy arrays over the batch ``B``.

    q: ``(B, nq)`` generalized coordinates (the padded layout of :class:`Equilibrium.q`).
    tip: ``(B, 3)`` [m] tip position, base frame. R: ``(B, 3, 3)`` tip orientation.
    converged: ``(B,)`` bool, Newton's test passed and the pose is finite.
    residual: ``(B,)`` Newton's scaled residual at ``q``. iterations: ``(B,)`` int.
    stable: ``(B,)`` bool, the Hessian at ``q`` is positive definite (a minimum of the energy)
    where the solve converged.
    energy: ``(B,)`` [J] the stored elastic energy; relative_rotation_at_outer_tip: ``(B, N-1)``
    [rad] ``psi_j - psi_1`` at the outer tube's end, wrapped to ``(-pi, pi]``;
    min_stiffness_eigenvalue: ``(B,)`` the stability margin (``None`` unless asked for): all
    three as :class:`~torchpvs.Equilibrium` defines them.
    tip_jacobian: ``(B, 6, 2N)`` ``d(tip)/dx``, rows the tip position [m] and spatial rotation
    [rad], columns ``x = (D_1..D_N [m], alpha_1..alpha_N [rad])``; actuator_stiffness:
    ``(B, 2N, 2N)`` ``dtau/dx`` [N/m, N, N·m] (:mod:`torchpvs.jacobians`' closed forms, the
    same one-sided rule at a kink); both ``None`` unless the step was asked for them, NaN
    rows where it did not converge.
    actuation_forces, actuation_torques, actuation_forces_insertion: ``(B, N)`` [N], [N·m]
    ``dU*/dD`` and ``dU*/dalpha`` as :class:`~torchpvs.Equilibrium` reports them (the
    retraction side at a kink, the insertion side beside it, NaN where a carriage cannot move
    in), force_kink ``(B, N)`` where ``U*(D_j)`` has a kink; ``None`` unless asked for, NaN
    rows where the step did not converge.
    """

    q: np.ndarray
    tip: np.ndarray
    R: np.ndarray
    converged: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    stable: np.ndarray
    energy: np.ndarray | None = None
    relative_rotation_at_outer_tip: np.ndarray | None = None
    min_stiffness_eigenvalue: np.ndarray | None = None
    tip_jacobian: np.ndarray | None = None
    actuator_stiffness: np.ndarray | None = None
    actuation_forces: np.ndarray | None = None
    actuation_torques: np.ndarray | None = None
    actuation_forces_insertion: np.ndarray | None = None
    force_kink: np.ndarray | None = None


@cached_jit(nogil=True)
def _scaled_active(H, qm):
    """The Jacobi-scaled stiffness ``S H S`` (``S = diag(|H_ii|^-1/2)``) on the active
    coordinates of a compact Hessian ``H`` (``qm`` its active mask): ``(m, m)``, the matrix
    Equilibrium.stable and min_stiffness_eigenvalue are decided on."""
    n = H.shape[0]
    act = np.empty(n, dtype=np.int64)
    sc = np.empty(n, dtype=H.dtype)
    tiny = np.finfo(H.dtype).tiny
    m = 0
    for i in range(n):
        if qm[i] > 0 and abs(H[i, i]) > 0:
            act[m] = i
            # S as Equilibrium's (torchpvs.equilibrium._scaled_stiffness): m powers, not m^2
            sc[m] = max(abs(H[i, i]), tiny) ** -0.5
            m += 1
    A = np.empty((m, m), dtype=H.dtype)
    for a in range(m):
        i = act[a]
        for c in range(m):
            A[a, c] = sc[a] * H[i, act[c]] * sc[c]
    return A


def _series_coefficients(shift: int, terms: int) -> list[float]:
    return [(-1) ** k / math.factorial(2 * k + shift) for k in range(terms)]


#: ``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` as power series in ``s = t^2``:
#: ``sum_k (-s)^k / (2k + shift)!``, shifts 1, 2, 3; 12 terms leave < 1e-20 for ``s < 1``
_SE3_SERIES = np.array([_series_coefficients(shift, 12) for shift in (1, 2, 3)])


@cached_jit(nogil=True)
def _se3_series(f, s):
    """Series ``f`` of :data:`_SE3_SERIES` and its derivative at ``s`` (Horner)."""
    K = _SE3_SERIES.shape[1]
    v = _SE3_SERIES[f, K - 1]
    dv = (K - 1) * _SE3_SERIES[f, K - 1]
    for k in range(K - 2, -1, -1):
        v = v * s + _SE3_SERIES[f, k]
    for k in range(K - 2, 0, -1):
        dv = dv * s + k * _SE3_SERIES[f, k]
    return v, dv


@cached_jit(nogil=True)
def _exp_tangents(om, dom, E, Et):
    """Rows 0-2 of ``E = exp(om)`` (4 x 4, ``om = (omega, v)``: ``R = I + A W + B W^2``,
    ``t = v + B (w x v) + C (w (w.v) - |w|^2 v)``, ``W = [w]x``, the exponential of
    :func:`torchpvs.compiled.exp_right_any`) into ``E (3, 4)`` and its tangents along the
    columns of ``dom (6, M)`` into ``Et (M, 3, 4)``, from ``A, B, C`` and their derivatives in
    ``s = |w|^2`` (series below ``s = 1``, closed forms above)."""
    wx, wy, wz, vx, vy, vz = om[0], om[1], om[2], om[3], om[4], om[5]
    s = wx * wx + wy * wy + wz * wz
    if s < 1.0:
        A, A1 = _se3_series(0, s)
        B, B1 = _se3_series(1, s)
        C, C1 = _se3_series(2, s)
    else:
        t = math.sqrt(s)
        st = math.sin(t)
        ct = math.cos(t)
        A = st / t
        A1 = (ct - A) / (2 * s)
        B = (1 - ct) / s
        B1 = (0.5 * A - B) / s
        C = (1 - A) / s
        C1 = (-A1 - C) / s
    wv = wx * vx + wy * vy + wz * vz
    cx = wy * vz - wz * vy
    cy = wz * vx - wx * vz
    cz = wx * vy - wy * vx
    E[0, 0] = 1.0 + B * (wx * wx - s)
    E[1, 1] = 1.0 + B * (wy * wy - s)
    E[2, 2] = 1.0 + B * (wz * wz - s)
    E[0, 1] = B * wx * wy - A * wz
    E[1, 0] = B * wx * wy + A * wz
    E[0, 2] = B * wx * wz + A * wy
    E[2, 0] = B * wx * wz - A * wy
    E[1, 2] = B * wy * wz - A * wx
    E[2, 1] = B * wy * wz + A * wx
    E[0, 3] = vx + B * cx + C * (wx * wv - s * vx)
    E[1, 3] = vy + B * cy + C * (wy * wv - s * vy)
    E[2, 3] = vz + B * cz + C * (wz * wv - s * vz)
    for d in range(Et.shape[0]):
        ax, ay, az = dom[0, d], dom[1, d], dom[2, d]
        bx, by, bz = dom[3, d], dom[4, d], dom[5, d]
        ds = 2.0 * (wx * ax + wy * ay + wz * az)
        dA = A1 * ds
        dB = B1 * ds
        dC = C1 * ds
        Et[d, 0, 0] = dB * (wx * wx - s) + B * (2.0 * wx * ax - ds)
        Et[d, 1, 1] = dB * (wy * wy - s) + B * (2.0 * wy * ay - ds)
        Et[d, 2, 2] = dB * (wz * wz - s) + B * (2.0 * wz * az - ds)
        p = dB * wx * wy + B * (ax * wy + wx * ay)
        r = dA * wz + A * az
        Et[d, 0, 1] = p - r
        Et[d, 1, 0] = p + r
        p = dB * wx * wz + B * (ax * wz + wx * az)
        r = dA * wy + A * ay
        Et[d, 0, 2] = p + r
        Et[d, 2, 0] = p - r
        p = dB * wy * wz + B * (ay * wz + wy * az)
        r = dA * wx + A * ax
        Et[d, 1, 2] = p - r
        Et[d, 2, 1] = p + r
        dwv = ax * vx + wx * bx + ay * vy + wy * by + az * vz + wz * bz
        dcx = ay * vz + wy * bz - az * vy - wz * by
        dcy = az * vx + wz * bx - ax * vz - wx * bz
        dcz = ax * vy + wx * by - ay * vx - wy * bx
        Et[d, 0, 3] = (bx + dB * cx + B * dcx + dC * (wx * wv - s * vx)
                       + C * (ax * wv + wx * dwv - ds * vx - s * bx))
        Et[d, 1, 3] = (by + dB * cy + B * dcy + dC * (wy * wv - s * vy)
                       + C * (ay * wv + wy * dwv - ds * vy - s * by))
        Et[d, 2, 3] = (bz + dB * cz + B * dcz + dC * (wz * wv - s * vz)
                       + C * (az * wv + wz * dwv - ds * vz - s * bz))


@cached_jit(nogil=True)
def tip_forward(q, dq, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved, presc,
                tip_tube, xm, phi, Qb, Ds, As, Px):
    """:func:`torchpvs.compiled.tip_directional` with ``dq (nq, 2N)`` by forward-mode
    (tangent) arithmetic instead of one complex step per actuator: ``Px[:, d] = d(tip twist)/
    dx_d`` with the coordinates moving by ``dq[:, d]`` per unit of actuator ``d`` (the
    insertions, then the rotations), at the insertions ``D + Ds`` and rotations moved by
    ``As`` (the layout's fields along their slopes, as :func:`torchpvs.compiled.
    tip_twist_core`). Every scalar of the pose carries its ``2N`` tangents, the Magnus
    exponentials too (:func:`_exp_tangents`). Rows: the tip position [m] and the spatial rotation
    ``vee(skew(dR R^T))`` [rad]. The same derivatives as the complex step to round-off, at
    about half its work (the complex step repeats the whole pose in complex arithmetic once
    per actuator)."""
    N = D.shape[0]
    M = 2 * N
    S = h.shape[0]
    G, n = phi.shape
    ms = G // 2
    Cn = (2 + N) * n
    dh, dstart = cut_slopes(D, L, Ls, S)
    Dc = np.empty(N)
    for j in range(N):
        Dc[j] = D[j] + Ds[j]
    psi = np.empty(N)
    dpsi = np.zeros((N, M))
    ntau = np.empty(N)
    Z0 = np.empty(N)
    dZ0 = np.zeros((N, M))
    for j in range(N):
        tg, tg_r, dtg = guide_curved(D, L, Ls, Dc, j)
        w = q[j] * qmask[j]
        psi[j] = (psi0[j] + As[j] + horner_integral(coef, j, tg)
                  - horner_integral(coef, j, tg_r) + Dc[j] * w)
        pz = horner(coef, j, _Z, tg)
        for d in range(M):
            dpsi[j, d] = Dc[j] * (dq[j, d] * qmask[j])
        dpsi[j, j] += pz * dtg + w
        dpsi[j, N + j] += 1.0
        ntau[j] = (Dc[j] - D[j]) - tau[j]        # its tangent: 1 along D_j
    g = np.eye(4)
    dg = np.zeros((M, 4, 4))
    gn = np.empty((4, 4))
    dgn = np.empty((M, 4, 4))
    E = np.empty((3, 4))
    Et = np.empty((M, 3, 4))
    om = np.empty(6)
    dom = np.empty((6, M))
    u = np.empty((G, 2))
    du = np.empty((G, 2, M))
    dsk = np.zeros(M)
    dhk = np.zeros(M)
    ds = np.empty(M)
    dt = np.empty(M)
    dps = np.empty(M)
    k3 = 3.0 ** 0.5 / 12.0
    for k in range(S):
        moves = False
        for l in range(N):
            if dh[k, l] != 0.0:
                moves = True
        if h[k] == 0.0 and not moves:      # an identity step that adds no angle
            continue
        off = N + k * Cn
        sk, hk = section_moved(start, h, dstart, dh, k, Dc, D)
        for l in range(N):
            dsk[l] = dstart[k, l]
            dhk[l] = dh[k, l]
        for j in range(N):
            t0 = sk + ntau[j]
            Z0[j] = horner_integral(coef, j, t0)
            pz = horner(coef, j, _Z, t0)
            for d in range(M):
                dZ0[j, d] = pz * dsk[d]
            dZ0[j, j] += pz
        for gg in range(G):
            xi = 0.5 * (xm[gg] + 1.0)
            s_node = sk + xi * hk
            for d in range(M):
                ds[d] = dsk[d] + xi * dhk[d]
            ux = 0.0
            uy = 0.0
            for d in range(M):
                du[gg, 0, d] = 0.0
                du[gg, 1, d] = 0.0
            for p in range(n):
                fx = off + p
                fy = off + n + p
                cx = qmask[fx] * phi[gg, p]
                cy = qmask[fy] * phi[gg, p]
                ux += q[fx] * cx
                uy += q[fy] * cy
                for d in range(M):
                    du[gg, 0, d] += dq[fx, d] * cx
                    du[gg, 1, d] += dq[fy, d] * cy
            for j in range(N):       # a prescribed section's strain: its precurvature
                held = presc[k] * present[k, j]
                if held == 0.0:
                    continue
                t = s_node + ntau[j]
                for d in range(M):
                    dt[d] = ds[d]
                dt[j] += 1.0
                lq = 0.0
                for d in range(M):
                    dps[d] = 0.0
                for p in range(n):
                    f = off + (2 + j) * n + p
                    c = qmask[f] * Qb[gg, p]
                    lq += q[f] * c
                    for d in range(M):
                        dps[d] += dq[f, d] * c      # d(lq) for now
                cp = curved[k, j] * presc[k]
                ps = psi[j] + 0.5 * hk * lq + (horner_integral(coef, j, t) - Z0[j]) * cp
                pz = horner(coef, j, _Z, t)
                for d in range(M):
                    dps[d] = (dpsi[j, d] + 0.5 * (dhk[d] * lq + hk * dps[d])
                              + (pz * dt[d] - dZ0[j, d]) * cp)
                usx = horner(coef, j, _X, t) * curved[k, j]
                usy = horner(coef, j, _Y, t) * curved[k, j]
                dusx = horner_derivative(coef, j, _X, t) * curved[k, j]
                dusy = horner_derivative(coef, j, _Y, t) * curved[k, j]
                cs = math.cos(ps)
                sn = math.sin(ps)
                ux += held * (cs * usx - sn * usy)
                uy += held * (sn * usx + cs * usy)
                ax = held * (-sn * usx - cs * usy)     # d(u)/d(ps)
                ay = held * (cs * usx - sn * usy)
                bx = held * cs                          # d(u)/d(us)
                by = held * sn
                for d in range(M):
                    dsx = dusx * dt[d]
                    dsy = dusy * dt[d]
                    du[gg, 0, d] += ax * dps[d] + bx * dsx - by * dsy
                    du[gg, 1, d] += ay * dps[d] + by * dsx + bx * dsy
            u[gg, 0] = ux
            u[gg, 1] = uy
        hs = hk / ms
        kq = k3 * hs * hs
        for i in range(ms):
            a, b = 2 * i, 2 * i + 1
            u1x, u1y, u2x, u2y = u[a, 0], u[a, 1], u[b, 0], u[b, 1]
            om[0] = 0.5 * hs * (u1x + u2x)
            om[1] = 0.5 * hs * (u1y + u2y)
            om[2] = kq * (u1x * u2y - u1y * u2x)
            om[3] = kq * (u1y - u2y)
            om[4] = -kq * (u1x - u2x)
            om[5] = hs
            for d in range(M):
                dhs = dhk[d] / ms
                dkq = 2.0 * k3 * hs * dhs
                d1x, d1y, d2x, d2y = du[a, 0, d], du[a, 1, d], du[b, 0, d], du[b, 1, d]
                dom[0, d] = 0.5 * (dhs * (u1x + u2x) + hs * (d1x + d2x))
                dom[1, d] = 0.5 * (dhs * (u1y + u2y) + hs * (d1y + d2y))
                dom[2, d] = (dkq * (u1x * u2y - u1y * u2x)
                             + kq * (d1x * u2y + u1x * d2y - d1y * u2x - u1y * d2x))
                dom[3, d] = dkq * (u1y - u2y) + kq * (d1y - d2y)
                dom[4, d] = -(dkq * (u1x - u2x) + kq * (d1x - d2x))
                dom[5, d] = dhs
            _exp_tangents(om, dom, E, Et)
            # g <- g E, dg <- dg E + g dE (the frames' last rows stay (0, 0, 0, 1) and 0)
            for r in range(3):
                for c in range(4):
                    acc = g[r, 0] * E[0, c] + g[r, 1] * E[1, c] + g[r, 2] * E[2, c]
                    if c == 3:
                        acc += g[r, 3]
                    gn[r, c] = acc
            for d in range(M):
                for r in range(3):
                    for c in range(4):
                        acc = (dg[d, r, 0] * E[0, c] + dg[d, r, 1] * E[1, c]
                               + dg[d, r, 2] * E[2, c] + g[r, 0] * Et[d, 0, c]
                               + g[r, 1] * Et[d, 1, c] + g[r, 2] * Et[d, 2, c])
                        if c == 3:
                            acc += dg[d, r, 3]
                        dgn[d, r, c] = acc
            for r in range(3):
                for c in range(4):
                    g[r, c] = gn[r, c]
                    for d in range(M):
                        dg[d, r, c] = dgn[d, r, c]
        for j in range(N):
            f = off + (2 + j) * n
            cp = curved[k, j] * presc[k]
            t1 = sk + ntau[j] + hk
            pz = horner(coef, j, _Z, t1)
            psi[j] += hk * q[f] * qmask[f] + (horner_integral(coef, j, t1) - Z0[j]) * cp
            for d in range(M):
                dt1 = dsk[d] + dhk[d] + (1.0 if d == j else 0.0)
                dpsi[j, d] += (dhk[d] * q[f] * qmask[f] + hk * dq[f, d] * qmask[f]
                               + (pz * dt1 - dZ0[j, d]) * cp)
    angle = 0.0
    for j in range(N):
        angle += psi[j] * tip_tube[j]
    ca = math.cos(angle)
    sa = math.sin(angle)
    # the tip frame R = [g0 ca + g1 sa, -g0 sa + g1 ca, g2] (columns of g's rotation)
    R = np.empty((3, 3))
    for r in range(3):
        R[r, 0] = g[r, 0] * ca + g[r, 1] * sa
        R[r, 1] = -g[r, 0] * sa + g[r, 1] * ca
        R[r, 2] = g[r, 2]
    W = np.empty((3, 3))
    for d in range(M):
        da = 0.0
        for j in range(N):
            da += dpsi[j, d] * tip_tube[j]
        for r in range(3):
            Px[r, d] = dg[d, r, 3]
        for r in range(3):
            dR0 = dg[d, r, 0] * ca + dg[d, r, 1] * sa + R[r, 1] * da
            dR1 = -dg[d, r, 0] * sa + dg[d, r, 1] * ca - R[r, 0] * da
            dR2 = dg[d, r, 2]
            for c in range(3):
                W[r, c] = dR0 * R[c, 0] + dR1 * R[c, 1] + dR2 * R[c, 2]
        Px[3, d] = 0.5 * (W[2, 1] - W[1, 2])
        Px[4, d] = 0.5 * (W[0, 2] - W[2, 0])
        Px[5, d] = 0.5 * (W[1, 0] - W[0, 1])


@cached_jit(nogil=True)
def _horner_second(coef, j, c, t):
    """d^2/dt^2 of :func:`torchpvs.compiled.horner`."""
    P = coef.shape[2]
    if P < 3:
        return 0.0
    out = (P - 1) * (P - 2) * coef[j, c, P - 1]
    for p in range(P - 2, 1, -1):
        out = out * t + p * (p - 1) * coef[j, c, p]
    return out


@cached_jit(nogil=True)
def stiffness_forward(q, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h, present, curved,
                      active, presc, W, xq, wq, phi, Qb, Gq, X):
    """:func:`torchpvs.compiled.stiffness_rows_one` by forward-mode tangents: the unloaded
    energy's Hessian rows at fixed ``q`` along the ``M = Gq.shape[0]`` directions ``D_1..D_N``
    then (``M = 2N``) ``alpha_1..alpha_N``, ``Gq[d] (nq,)`` (``U_qx`` column ``d``, zero on
    inactive coordinates) and ``X[d] (2N,)`` (``U_xx`` column ``d``): the arithmetic of
    :func:`torchpvs.compiled.partials_core` (the gradient and the partials ``tau_D, tau_A``
    at fixed ``q`` on the layout's sections moved along their slopes in ``D``) with every
    scalar that depends on the actuation carrying its ``M`` tangents, in one pass instead of
    one complex-step pass per direction."""
    N = D.shape[0]
    S = h.shape[0]
    Q, n = phi.shape
    Cn = (2 + N) * n
    nq = q.shape[0]
    M = Gq.shape[0]
    dh, dstart = cut_slopes(D, L, Ls, S)
    dg = Gq                                  # the gradient's tangents, written in place
    for d in range(M):
        for m in range(nq):
            dg[d, m] = 0.0
    dtD = np.zeros((N, M))
    dtA = np.zeros((N, M))
    g0 = np.empty(N)
    dg0 = np.zeros((N, M))
    psi_start = np.empty(N)
    dpsi = np.zeros((N, M))
    for j in range(N):
        w = q[j] * qmask[j]
        tg, tg_r, dtg = guide_curved(D, L, Ls, D, j)
        ugx = horner(coef, j, _X, tg)
        ugy = horner(coef, j, _Y, tg)
        g0[j] = w + horner(coef, j, _Z, tg) * dtg
        psi_start[j] = (psi0[j] + horner_integral(coef, j, tg) - horner_integral(coef, j, tg_r)
                        + D[j] * w)
        if j < M:                            # along D_j: tg moves by dtg
            dtD[j, j] = EI[j] * (ugx * horner_derivative(coef, j, _X, tg)
                                 + ugy * horner_derivative(coef, j, _Y, tg)) * dtg * dtg
            dg0[j, j] = horner_derivative(coef, j, _Z, tg) * dtg * dtg
            dpsi[j, j] = horner(coef, j, _Z, tg) * dtg + w
            dg[j, j] = GJ[j] * w
        if N + j < M:
            dpsi[j, N + j] = 1.0
    before = np.zeros((N, N))
    Gps = np.zeros((S + 1, N))
    dGps = np.zeros((S + 1, N, M))
    ntau = np.empty(N)
    for j in range(N):
        ntau[j] = -tau[j]                    # its tangent: 1 along D_j
    a = np.empty((2, n))
    c = np.empty((N, n))
    Rx = np.empty(N)
    Ry = np.empty(N)
    dRx = np.empty((N, M))
    dRy = np.empty((N, M))
    us = np.empty((N, 3))
    dus = np.empty((N, 3))                   # d(us)/dt (times dt per direction)
    dp = np.empty(N)
    cs = np.empty(N)
    sn = np.empty(N)
    dps = np.empty((N, M))
    locq = np.empty(N)
    Gp = np.empty(N)
    dGp = np.empty((N, M))
    Z0 = np.empty(N)
    dZ0 = np.empty((N, M))
    pm = np.empty(N)
    dsk = np.zeros(M)
    dhk = np.zeros(M)
    dsn_ = np.empty(M)
    dtn = np.empty((N, M))
    dux = np.empty(M)
    duy = np.empty(M)
    ddens = np.empty(M)
    dgsum = np.empty(M)
    dGx = np.empty(M)
    dGy = np.empty(M)
    ds_loc = np.zeros(M)
    for k in range(S):
        off = N + k * Cn
        sk, hk = start[k], h[k]
        for d in range(M):
            dsk[d] = dstart[k, d] if d < N else 0.0
            dhk[d] = dh[k, d] if d < N else 0.0
        for p in range(n):
            a[0, p] = q[off + p] * qmask[off + p]
            a[1, p] = q[off + n + p] * qmask[off + n + p]
        for j in range(N):
            for p in range(n):
                c[j, p] = q[off + (2 + j) * n + p] * qmask[off + (2 + j) * n + p]
            pm[j] = curved[k, j] * presc[k]
            t0 = sk + ntau[j]
            Z0[j] = horner_integral(coef, j, t0)
            pz = horner(coef, j, _Z, t0)
            for d in range(M):
                dZ0[j, d] = pz * dsk[d]
            if j < M:
                dZ0[j, j] += pz
            Gp[j] = 0.0
            for d in range(M):
                dGp[j, d] = 0.0
        s_loc = 0.0
        for d in range(M):
            ds_loc[d] = 0.0
        for i in range(Q):
            frac = 0.5 * (xq[i] + 1.0)
            s_node = sk + frac * hk
            for d in range(M):
                dsn_[d] = dsk[d] + frac * dhk[d]
            Wki = W[k, i]
            cW = wq[i] * 0.5 * active[k]     # d(Wki) = cW dhk
            ux = 0.0
            uy = 0.0
            for p in range(n):
                ux += a[0, p] * phi[i, p]
                uy += a[1, p] * phi[i, p]
            for d in range(M):
                dux[d] = 0.0
                duy[d] = 0.0
            for j in range(N):
                t = s_node + ntau[j]
                for d in range(M):
                    dtn[j, d] = dsn_[d]
                if j < M:
                    dtn[j, j] += 1.0
                for cc in range(3):
                    us[j, cc] = horner(coef, j, cc, t) * curved[k, j]
                    dus[j, cc] = horner_derivative(coef, j, cc, t) * curved[k, j]
                lq = 0.0
                d1 = 0.0
                for p in range(n):
                    lq += c[j, p] * Qb[i, p]
                    d1 += c[j, p] * phi[i, p]
                locq[j] = lq
                ps = (psi_start[j] + 0.5 * hk * lq
                      + (horner_integral(coef, j, t) - Z0[j]) * pm[j])
                pz = horner(coef, j, _Z, t)
                cs[j] = math.cos(ps)
                sn[j] = math.sin(ps)
                Rx[j] = cs[j] * us[j, 0] - sn[j] * us[j, 1]
                Ry[j] = sn[j] * us[j, 0] + cs[j] * us[j, 1]
                dp[j] = d1 + pm[j] * us[j, 2]
                for d in range(M):
                    v = dpsi[j, d] + 0.5 * dhk[d] * lq + (pz * dtn[j, d] - dZ0[j, d]) * pm[j]
                    dps[j, d] = v
                    du0 = dus[j, 0] * dtn[j, d]
                    du1 = dus[j, 1] * dtn[j, d]
                    # d(R) = d(rotation by ps) us + rotation d(us)
                    dRx[j, d] = -Ry[j] * v + cs[j] * du0 - sn[j] * du1
                    dRy[j, d] = Rx[j] * v + sn[j] * du0 + cs[j] * du1
            for j in range(N):        # a prescribed section's strain: its precurvature
                held = presc[k] * present[k, j]
                ux += held * Rx[j]
                uy += held * Ry[j]
                if held != 0.0:
                    for d in range(M):
                        dux[d] += held * dRx[j, d]
                        duy[d] += held * dRy[j, d]
            Gx = 0.0
            Gy = 0.0
            for d in range(M):
                ddens[d] = 0.0
                dgsum[d] = 0.0
                dGx[d] = 0.0
                dGy[d] = 0.0
            for j in range(N):
                EIp = EI[j] * present[k, j]
                GJp = GJ[j] * present[k, j]
                ex = ux - Rx[j]
                ey = uy - Ry[j]
                tors = dp[j] - us[j, 2]
                cross = Ry[j] * ux - Rx[j] * uy
                gpsi = Wki * EIp * cross
                Gp[j] += gpsi
                s_loc += gpsi * 0.5 * locq[j]
                t = s_node + ntau[j]
                # (the first derivatives at this node: the same products as dus above)
                dx, dy, dz = dus[j, 0], dus[j, 1], dus[j, 2]
                ddx = _horner_second(coef, j, _X, t) * curved[k, j]
                ddy = _horner_second(coef, j, _Y, t) * curved[k, j]
                ddz = _horner_second(coef, j, _Z, t) * curved[k, j]
                px = cs[j] * dx - sn[j] * dy
                py = sn[j] * dx + cs[j] * dy
                inner = EIp * (ex * px + ey * py) + GJp * tors * dz
                base = off + (2 + j) * n
                for d in range(M):
                    dt_ = dtn[j, d]
                    dW = cW * dhk[d]
                    dex = dux[d] - dRx[j, d]
                    dey = duy[d] - dRy[j, d]
                    dtors = pm[j] * dus[j, 2] * dt_ - dus[j, 2] * dt_
                    ddens[d] += EIp * (ex * dex + ey * dey) + GJp * tors * dtors
                    dcross = dRy[j, d] * ux + Ry[j] * dux[d] - dRx[j, d] * uy - Rx[j] * duy[d]
                    dgp = dW * EIp * cross + Wki * EIp * dcross
                    dGp[j, d] += dgp
                    ds_loc[d] += dgp * 0.5 * locq[j]
                    v = dps[j, d]
                    dpx = -py * v + (cs[j] * ddx - sn[j] * ddy) * dt_
                    dpy = px * v + (sn[j] * ddx + cs[j] * ddy) * dt_
                    dinner = (EIp * (dex * px + ex * dpx + dey * py + ey * dpy)
                              + GJp * (dtors * dz + tors * ddz * dt_))
                    dgs = -(dW * inner + Wki * dinner)
                    dgsum[d] += dgs
                    dtD[j, d] += dgs
                    dGx[d] += EIp * dex
                    dGy[d] += EIp * dey
                    for p in range(n):
                        dg[d, base + p] += (dgp * 0.5 * hk * Qb[i, p]
                                            + gpsi * 0.5 * dhk[d] * Qb[i, p]
                                            + (dW * tors + Wki * dtors) * GJp * phi[i, p]
                                            ) * qmask[base + p]
                Gx += EIp * ex
                Gy += EIp * ey
            for l in range(N):
                sl = dstart[k, l] + frac * dh[k, l]
                for d in range(M):
                    dtD[l, d] += ddens[d] * 0.5 * wq[i] * dh[k, l] * active[k] + dgsum[d] * sl
            for d in range(M):
                dW = cW * dhk[d]
                for p in range(n):
                    dg[d, off + p] += (dW * Gx + Wki * dGx[d]) * phi[i, p] * qmask[off + p]
                    dg[d, off + n + p] += ((dW * Gy + Wki * dGy[d]) * phi[i, p]
                                           * qmask[off + n + p])
        for l in range(N):
            for d in range(M):
                acc = ds_loc[d] * dh[k, l] + g0[l] * dGp[l, d] + dg0[l, d] * Gp[l]
                for j in range(N):
                    acc += dGp[j, d] * before[j, l]
                dtD[l, d] += acc
                dtA[l, d] += dGp[l, d]
        for j in range(N):
            Gps[k, j] = Gp[j]
            for d in range(M):
                dGps[k, j, d] = dGp[j, d]
            for l in range(N):
                before[j, l] += dh[k, l] * c[j, 0]
            t1 = sk + ntau[j] + hk
            pz = horner(coef, j, _Z, t1)
            psi_start[j] += hk * c[j, 0] + (horner_integral(coef, j, t1) - Z0[j]) * pm[j]
            for d in range(M):
                dt1 = dsk[d] + dhk[d] + (1.0 if d == j else 0.0)
                dpsi[j, d] += dhk[d] * c[j, 0] + (pz * dt1 - dZ0[j, d]) * pm[j]
    # the angles of section k carry D_j w_j and h_k' c_k'j0 of every earlier section k'
    for k in range(S - 1, -1, -1):
        off = N + k * Cn
        hk = h[k]
        for j in range(N):
            f = off + (2 + j) * n
            for d in range(M):
                dhkd = dh[k, d] if d < N else 0.0
                dg[d, f] += (dhkd * Gps[S, j] + hk * dGps[S, j, d]) * qmask[f]
                dGps[S, j, d] += dGps[k, j, d]
            Gps[S, j] += Gps[k, j]
    for j in range(N):
        for d in range(M):
            v = dg[d, j] + D[j] * dGps[S, j, d]
            if d == j:
                v += Gps[S, j]
            dg[d, j] = v * qmask[j]
    for d in range(M):
        for j in range(N):
            X[d, j] = dtD[j, d]
            X[d, N + j] = dtA[j, d]


@cached_jit(nogil=True)
def _stable(H, qm, tau):
    """Equilibrium.stable for an element without the kernel's verdict: the Jacobi-scaled
    stiffness on the active coordinates minus ``tau`` is positive definite."""
    A = _scaled_active(H, qm)
    m = A.shape[0]
    for a in range(m):
        A[a, a] -= tau
    return cholesky(A, np.empty((m, m), dtype=H.dtype))


@cached_jit(nogil=True)
def _track(q_prev, H_prev, cidx_prev, qmc_prev, predict, dA, D, GJ, length, trust,
           qmask, psi0, tip_tube, cidx, qmask_c, bvec, h_c, ustar, EIw, EIws, GJw, Hsec,
           guide, gconst, phi, Qb, psec, p_h, p_inc, p_held, p_local, phi_m, Q_m, S, small,
           Lc, consts, minimize, max_iter, tau, q_out, H, tip, R, res, it, conv, verdict, U):
    """Per element: the rotation predictor on the previous compact Hessian (where
    ``predict``), the warm start masked to the new layout, compacted, the damped Newton solve
    (its last energy into ``U``), the padded solution and its tip pose."""
    B, nq = q_prev.shape
    N = D.shape[1]
    nc = cidx.shape[1]
    ncp = cidx_prev.shape[1]
    dt = q_prev.dtype
    g = np.empty((B, nc), dtype=dt)
    qc = np.empty((B, nc), dtype=dt)
    psi_tip = np.empty((B, N), dtype=dt)
    qi = np.empty(nq, dtype=dt)
    rhs = np.empty(ncp, dtype=dt)
    x = np.empty(ncp, dtype=dt)
    for b in range(B):
        for i in range(nq):
            qi[i] = q_prev[b, i]
        if predict[b]:
            # torchpvs.predictor.rotation_predictor: dq = -H^-1 U_q,alpha dalpha
            Lp, ok = factor_leading(H_prev[b], qmc_prev[b], 0)
            if ok:
                for i in range(ncp):
                    rhs[i] = 0.0
                for j in range(N):
                    rhs[j] = GJ[b, j] * dA[b, j]
                solve_leading(H_prev[b], Lp, rhs, x)
                for j in range(N):
                    x[j] -= dA[b, j] / (D[b, j] if D[b, j] > 0 else 1.0)
                big = 0.0
                for i in range(ncp):
                    x[i] *= qmc_prev[b, i]
                    if not math.isfinite(x[i]):
                        ok = False
                    big = max(big, abs(x[i]))
                for j in range(N):
                    ok = ok and qmc_prev[b, j] > 0
                if ok and big * length < trust:
                    for i in range(ncp):
                        qi[cidx_prev[b, i]] += x[i]
        for i in range(nc):
            qc[b, i] = qi[cidx[b, i]] * qmask[b, cidx[b, i]]
        newton_into(b, qc, qmask_c, psi0, bvec, h_c, ustar, EIw, EIws, GJw, Hsec, guide,
                    gconst, phi, Qb, None, Lc, consts, minimize, max_iter, H, g, U, res, it,
                    conv, verdict)
        for i in range(nq):
            q_out[b, i] = 0.0
        for i in range(nc):
            q_out[b, cidx[b, i]] = qc[b, i]
        pose_one(q_out[b], qmask[b], psi0[b], D[b], tip_tube[b], psec[b], p_h[b], p_inc[b],
                 p_held[b], p_local[b], phi_m, Q_m, S, small, tip[b], R[b], psi_tip[b])
        for k in range(3):
            if not math.isfinite(tip[b, k]):
                conv[b] = False
        if verdict[b] < 0 and conv[b]:
            verdict[b] = 1 if _stable(H[b], qmask_c[b], tau) else 0


class _Snapshot(NamedTuple):
    q: np.ndarray
    H: np.ndarray
    cidx: np.ndarray
    qmask_c: np.ndarray
    D: np.ndarray
    A: np.ndarray
    state: TrackState


@cached_jit(nogil=True)
def _control_rows(b, q, H, cidx, qmask_c, qmask, D, L, Ls, EI, GJ, coef, tau, psi0, start, h,
                  present, curved, active, presc, W, tip_tube, xq, wq, phi, Qb, xm, phi_m, Q_m,
                  J, K, want_J):
    """Element ``b``'s control step at ``q`` with the compact Hessian ``H`` (its Schur
    complement: torchpvs.jacobians): the energy's rows ``U_qx, U_xx`` at fixed ``q`` on the
    layout given (a kink's side or the solution's own), ``Z = H^-1 U_qx``, ``K = sym(U_xx -
    U_xq Z)`` ``(2N, 2N)`` and ``J = P_x - P_q Z`` ``(6, 2N)`` as the tip pose's tangent
    along each actuator with ``q`` moving by ``-Z`` (:func:`tip_forward`: ``P_q``, 6 x nq
    through the Magnus chain, is never formed); ``J`` is
    left as it is unless ``want_J`` (the stiffness alone is what time stepping needs)."""
    N = D.shape[1]
    m = 2 * N
    nq = q.shape[1]
    nc = cidx.shape[1]
    dt = q.dtype
    # where every guide twist w_j is a coordinate (every D_j > 0), the rotation rows are read
    # off H (torchpvs.jacobians._rotation_rows_from_hessian: U depends on alpha_j and w_j
    # only through alpha_j + D_j w_j, plus the guide's GJ_j D_j w_j^2 / 2); the insertion
    # rows by forward-mode tangents (stiffness_forward)
    iw = np.full(N, -1, dtype=np.int64)
    for i in range(nc):
        c = cidx[b, i]
        if c < N and qmask_c[b, i] > 0:
            iw[c] = i
    from_H = True
    for j in range(N):
        from_H = from_H and iw[j] >= 0 and qmask[b, j] > 0 and D[b, j] > 0
    n_rows = N if from_H else m
    Gq = np.empty((n_rows, nq), dtype=dt)
    X = np.empty((m, m), dtype=dt)
    stiffness_forward(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau[b],
                      psi0[b], start[b], h[b], present[b], curved[b], active[b], presc[b],
                      W[b], xq, wq, phi, Qb, Gq, X[:n_rows])
    G = np.empty((m, nc), dtype=dt)
    for d in range(n_rows):
        for i in range(nc):
            G[d, i] = Gq[d, cidx[b, i]] * qmask_c[b, i]
    if from_H:
        for j in range(N):
            a = N + j
            gjd = GJ[b, j] * D[b, j]
            for i in range(nc):
                v = H[b, iw[j], i] - (gjd if i == iw[j] else 0.0)
                G[a, i] = v / D[b, j] * qmask_c[b, i]
            for k in range(N):
                X[a, k] = X[k, a]                    # dtau_D_k / dalpha_j = dtau_alpha_j / dD_k
                v = H[b, iw[j], iw[k]] - (gjd if j == k else 0.0)
                X[a, N + k] = v / (D[b, j] * D[b, k])
    Z = np.empty((nc, m), dtype=dt)
    rhs = np.empty(nc, dtype=dt)
    z = np.empty(nc, dtype=dt)
    # (on the leading block: the rest is a batch's padding, compiled.factor_leading)
    Lf, chol = factor_leading(H[b], qmask_c[b], 0)
    for d in range(m):
        for i in range(nc):
            rhs[i] = G[d, i]
        if chol:
            solve_leading(H[b], Lf, rhs, z)
        else:
            # not positive definite (an unstable equilibrium): pivoted elimination
            if not lu_solve(H[b].copy(), rhs, z):
                for i in range(nc):
                    z[i] = np.nan
        for i in range(nc):
            Z[i, d] = z[i] * qmask_c[b, i]
    if want_J:
        dq = np.zeros((nq, m), dtype=dt)       # dq*/dx = -Z on the padded coordinates
        for i in range(nc):
            for c in range(m):
                dq[cidx[b, i], c] = -Z[i, c] * qmask_c[b, i]
        zero = np.zeros(N, dtype=dt)
        tip_forward(q[b], dq, qmask[b], D[b], L[b], Ls[b], coef[b], tau[b], psi0[b],
                    start[b], h[b], present[b], curved[b], presc[b], tip_tube[b], xm,
                    phi_m, Q_m, zero, zero, J[b])
    for a in range(m):
        for c in range(m):
            s = X[c, a]
            for i in range(nc):
                s -= G[a, i] * Z[i, c]
            K[b, a, c] = s
    for a in range(m):
        for c in range(a + 1, m):
            v = 0.5 * (K[b, a, c] + K[b, c, a])
            K[b, a, c] = v
            K[b, c, a] = v


@cached_jit(nogil=True)
def _side_forces(q, qmask, conv, sel, sj, Dn, EI, GJ, L, Ls, coef, A, unloaded, xg, wg, xq, wq,
                 xm, phi, Qb, n, hmax, tiny, vals):
    """The one-sided insertion forces at kinks (torchpvs.forces.equilibrium_forces with the
    driver's SolutionResolver.near): for each side ``r``, element ``sel[r]`` at the insertions
    ``Dn[r]`` (``delta`` to one side), its coordinates ``q`` on the layout there where that has
    the same active coordinates (envelope theorem: no solve), else with a section that appears
    solved for with the rest held (the new-section step) or, where that does not apply, one
    Newton step; ``vals[r]`` is ``dU/dD_j`` there, ``j = sj[r]`` (NaN where the element did not
    converge)."""
    nq = q.shape[1]
    N = Dn.shape[1]
    tD = np.empty(N, dtype=q.dtype)
    tA = np.empty(N, dtype=q.dtype)
    for r in range(sel.shape[0]):
        b = sel[r]
        if not conv[b]:
            vals[r] = np.nan
            continue
        (_ell, tau_, start, h, present, curved, active, presc, qm, psi0, gconst, W, _tt,
         _st, _bl, _sec, _psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide, bvec, qmask_c, h_c,
         _pi, _ph, _pinc, _pheld, _ploc) = layout_maps_arrays(
            EI[b:b + 1], GJ[b:b + 1], L[b:b + 1], Ls[b:b + 1], coef[b:b + 1], Dn[r:r + 1],
            A[b:b + 1], unloaded[:1], 1e-12, xg, wg, xq, wq, xm, phi, n)
        q1 = np.empty((1, nq), dtype=q.dtype)
        moved = False
        for i in range(nq):
            q1[0, i] = q[b, i] * qm[0, i]
            moved = moved or qm[0, i] != qmask[b, i]
        if moved:
            nc = cidx.shape[1]
            qc = np.empty(nc, dtype=q.dtype)
            newc = np.empty(nc, dtype=np.bool_)
            for i in range(nc):
                c = cidx[0, i]
                qc[i] = q1[0, c]
                newc[i] = qm[0, c] > 0 and not qmask[b, c] > 0
            ok = section_step_one(qc, qmask_c[0], psi0[0], bvec[0], h_c[0], ustar[0], EIw[0],
                                  EIws[0], GJw[0], Hsec[0], guide[0], gconst[0], phi, Qb,
                                  newc, hmax)
            if not ok:
                ok = step_one(qc, qmask_c[0], psi0[0], bvec[0], h_c[0], ustar[0], EIw[0],
                              EIws[0], GJw[0], Hsec[0], guide[0], gconst[0], phi, Qb, None,
                              tiny)
            if ok:
                for i in range(nq):
                    q1[0, i] = 0.0
                for i in range(nc):
                    q1[0, cidx[0, i]] = qc[i]
        partials_one(q1[0], qm[0], Dn[r], L[b], Ls[b], EI[b], GJ[b], coef[b], tau_[0],
                     psi0[0], start[0], h[0], present[0], curved[0], active[0], presc[0], W[0],
                     xq, wq, phi, Qb, tD, tA)
        vals[r] = tD[sj[r]]


@cached_jit(nogil=True)
def _outer_twist(q, qmask, psi0, D, h, before_l1, presc_inc, n, twist):
    """``twist (B, N-1)`` [rad]: ``psi_j - psi_1`` at the outer tube's end, wrapped to
    ``(-pi, pi]`` (Equilibrium.relative_rotation_at_outer_tip: the angle at the orifice, the
    guide twist ``D_j w_j``, then each section's increment ``h_k c_k,j,0`` plus a prescribed
    section's twist, for the sections before ``l_1``)."""
    B, N = D.shape
    S = h.shape[1]
    two_pi = 2.0 * math.pi
    psi = np.empty(N, dtype=q.dtype)
    for b in range(B):
        for j in range(N):
            a = psi0[b, j] + D[b, j] * (q[b, j] * qmask[b, j])
            for k in range(S):
                i = N + (k * (2 + N) + 2 + j) * n
                a += (h[b, k] * (q[b, i] * qmask[b, i]) + presc_inc[b, k, j]) * before_l1[b, k]
            psi[j] = a
        for j in range(1, N):
            r = math.pi - (psi[j] - psi[0])
            twist[b, j - 1] = math.pi - (r - two_pi * math.floor(r / two_pi))


@cached_jit(nogil=True)
def _margin(H, qm):
    """Equilibrium.min_stiffness_eigenvalue of one element: the smallest eigenvalue of the
    Jacobi-scaled compact Hessian ``S H S`` on its active coordinates (NaN without any)."""
    A = _scaled_active(H, qm)
    if A.shape[0] == 0:
        return np.nan
    return min_eigenvalue(A)


@cached_jit(nogil=True)
def min_eigenvalue(A):
    """The smallest eigenvalue of a symmetric ``A (m, m)`` (its lower triangle is read and
    overwritten): Householder reduction to tridiagonal form on the lower triangle, then
    Sturm-sequence multisection (three points per round) to round-off. At the environments'
    sizes (m ~ 26) several times faster than LAPACK's ``syevd`` through
    ``np.linalg.eigvalsh`` (29 us), which computes the whole spectrum; the two agree to
    round-off (``tests/test_tracker.py``)."""
    m = A.shape[0]
    v = np.empty(m, dtype=A.dtype)
    p = np.empty(m, dtype=A.dtype)
    for k in range(m - 2):
        # the Householder vector of A[k+1:, k]
        alpha = 0.0
        for i in range(k + 1, m):
            alpha += A[i, k] * A[i, k]
        alpha = math.sqrt(alpha)
        if alpha == 0.0:
            continue
        if A[k + 1, k] > 0:
            alpha = -alpha
        for i in range(k + 1, m):
            v[i] = A[i, k]
        v[k + 1] -= alpha
        vv = 0.0
        for i in range(k + 1, m):
            vv += v[i] * v[i]
        if vv == 0.0:
            continue
        beta = 2.0 / vv
        # p = beta A v on the trailing block, reading its lower triangle row by row
        for i in range(k + 1, m):
            p[i] = 0.0
        for i in range(k + 1, m):
            s = A[i, i] * v[i]
            vi = v[i]
            for j in range(k + 1, i):
                s += A[i, j] * v[j]
                p[j] += A[i, j] * vi
            p[i] += s
        pv = 0.0
        for i in range(k + 1, m):
            p[i] *= beta
            pv += p[i] * v[i]
        c = 0.5 * beta * pv
        for i in range(k + 1, m):
            p[i] -= c * v[i]
        # A <- P A P, P = I - beta v v^T: a rank-2 update of the lower triangle
        for i in range(k + 1, m):
            vi, pi = v[i], p[i]
            for j in range(k + 1, i + 1):
                A[i, j] -= vi * p[j] + pi * v[j]
        A[k + 1, k] = alpha
    # the tridiagonal: d = A[i, i], e_i = A[i, i - 1]. Gershgorin bounds, then the count of
    # eigenvalues below x (the signs of the LDL^T pivots of T - x I) at three points a round
    lo = math.inf
    hi = math.inf
    for i in range(m):
        r = (abs(A[i, i - 1]) if i > 0 else 0.0) + (abs(A[i + 1, i]) if i < m - 1 else 0.0)
        lo = min(lo, A[i, i] - r)
        hi = min(hi, A[i, i])          # the smallest eigenvalue is <= every diagonal entry
    eps = np.finfo(A.dtype).eps
    tiny = np.finfo(A.dtype).tiny
    for _ in range(200):
        w = hi - lo
        if w <= 2.0 * eps * max(abs(lo), abs(hi)) + tiny:
            break
        x1 = lo + 0.25 * w
        x2 = lo + 0.5 * w
        x3 = lo + 0.75 * w
        q1 = A[0, 0] - x1
        q2 = A[0, 0] - x2
        q3 = A[0, 0] - x3
        n1 = 1 if q1 < 0 else 0
        n2 = 1 if q2 < 0 else 0
        n3 = 1 if q3 < 0 else 0
        for i in range(1, m):
            e2 = A[i, i - 1] * A[i, i - 1]
            guard = eps * abs(A[i - 1, i - 1]) + tiny
            q1 = A[i, i] - x1 - e2 / (q1 if q1 != 0.0 else guard)
            q2 = A[i, i] - x2 - e2 / (q2 if q2 != 0.0 else guard)
            q3 = A[i, i] - x3 - e2 / (q3 if q3 != 0.0 else guard)
            n1 += 1 if q1 < 0 else 0
            n2 += 1 if q2 < 0 else 0
            n3 += 1 if q3 < 0 else 0
        if n1 >= 1:
            hi = x1
        elif n2 >= 1:
            lo, hi = x1, x2
        elif n3 >= 1:
            lo, hi = x2, x3
        else:
            lo = x3
        if not (lo < hi):
            break
    return 0.5 * (lo + hi)


@cached_jit(nogil=True)
def _check_and_wrap(D, A, D_prev, A_prev, predict, dA):
    """The step's input checks and angle bookkeeping in one call (about ten numpy calls at a
    microsecond each otherwise): returns 0, or 1 / 2 for a non-finite insertion / rotation, 3
    for a negative insertion, 4 for bases out of nesting order (``D_j < D_{j-1}``;
    torchpvs.inputs.check_actuation). ``A`` is wrapped in place to ``alpha - 2 pi k`` (the
    energy is 2 pi-periodic in every rotation, as in torchpvs.solve), ``dA`` gets the wrapped
    change from ``A_prev`` and ``predict`` whether the insertions are unchanged (the rotation
    predictor's condition)."""
    B, N = D.shape
    two_pi = 2.0 * math.pi
    for b in range(B):
        for j in range(N):
            if not math.isfinite(D[b, j]):
                return 1
            if not math.isfinite(A[b, j]):
                return 2
    for b in range(B):
        same = True
        for j in range(N):
            if D[b, j] < 0.0:
                return 3
            if j > 0 and D[b, j] < D[b, j - 1]:
                return 4
            A[b, j] -= two_pi * np.round(A[b, j] / two_pi)
            d = A[b, j] - A_prev[b, j]
            dA[b, j] = d - two_pi * np.round(d / two_pi)
            same = same and D[b, j] == D_prev[b, j]
        predict[b] = same
    return 0


@cached_jit(nogil=True)
def _kink_mask(L, Ls, curved, D, tol, kink):
    """:func:`torchpvs.forces.kink_mask` in one compiled call (its torch form is about 40
    operations, more than a whole tracker step when the insertions change at every step):
    ``kink (B, N)`` where a tube's base, straight-to-curved transition or end is at the
    orifice, or a cut that moves with ``D_j`` coincides with another tube's cut."""
    B, N = D.shape
    for b in range(B):
        for j in range(N):
            d = D[b, j]
            k = ((d <= tol and L[j] - d > tol)
                 or (abs(Ls[j] - d) <= tol and curved[j] and L[j] > Ls[j])
                 or abs(L[j] - d) <= tol)
            # a moving cut of tube j (its end; its transition beyond the orifice) meeting one
            # of another tube's (forces._coinciding_cuts)
            for c in range(2):
                if k:
                    break
                ell_j = max(L[j] - d, 0.0)
                cut = ell_j if c == 0 else Ls[j] - d
                if c == 0:
                    ok = ell_j > tol
                else:
                    ok = curved[j] and cut > tol and cut < ell_j - tol
                if not ok:
                    continue
                for o in range(N):
                    if o == j or k:
                        continue
                    ell_o = max(L[o] - D[b, o], 0.0)
                    for c2 in range(2):
                        other = ell_o if c2 == 0 else Ls[o] - D[b, o]
                        if c2 == 0:
                            ok2 = ell_o > tol
                        else:
                            ok2 = curved[o] and other > tol and other < ell_o - tol
                        if ok2 and abs(cut - other) <= tol:
                            k = True
            kink[b, j] = k


def kink_sides(kink: np.ndarray, D: np.ndarray) -> tuple:
    """:func:`torchpvs.forces.kink_plan` for the kink mask ``kink (B, N)`` at insertions ``D
    (B, N)`` (compiled: its numpy form is a dozen calls, about 50 us at B = 1): ``(blocked (B,
    N), sel, sj, Dn, n_retract)``, every kink ``(sel, sj)`` retracted by ``KINK_DELTA``, then
    those whose carriage can move in inserted; ``Dn`` the sides' insertions (nesting kept),
    the first ``n_retract`` rows the retraction sides."""
    return _kink_sides(kink, np.ascontiguousarray(D, dtype=np.float64), KINK_DELTA)


@cached_jit(nogil=True)
def _kink_sides(kink, D, delta):
    B, N = D.shape
    blocked = np.empty((B, N), dtype=np.bool_)
    n_r = 0
    n_i = 0
    for b in range(B):
        for j in range(N):
            prev = D[b, j - 1] if j > 0 else 0.0
            blocked[b, j] = D[b, j] - delta < prev
            if kink[b, j]:
                n_r += 1
                if not blocked[b, j]:
                    n_i += 1
    sel = np.empty(n_r + n_i, dtype=np.int64)
    sj = np.empty(n_r + n_i, dtype=np.int64)
    r = 0
    for side in range(2):           # the retraction sides, then the insertion sides
        for b in range(B):
            for j in range(N):
                if kink[b, j] and (side == 0 or not blocked[b, j]):
                    sel[r] = b
                    sj[r] = j
                    r += 1
    Dn = np.empty((n_r + n_i, N), dtype=D.dtype)
    for r in range(n_r + n_i):
        for k in range(N):
            Dn[r, k] = D[sel[r], k]
        Dn[r, sj[r]] += delta * (1.0 if r < n_r else -1.0)
        for k in range(1, N):       # a base moved past the next one's moves it along
            Dn[r, k] = max(Dn[r, k - 1], Dn[r, k])
    return blocked, sel, sj, Dn, n_r


def kink_mask_arrays(L: np.ndarray, Ls: np.ndarray, curved: np.ndarray,
                     D: np.ndarray) -> np.ndarray:
    """:func:`torchpvs.forces.kink_mask` ``(B, N)`` of one robot's tubes (lengths ``L``,
    straight lengths ``Ls`` [m], ``curved`` flags, each ``(N,)``) at insertions ``D (B,
    N)``, in one compiled call."""
    kink = np.empty(D.shape, dtype=np.bool_)
    _kink_mask(L, Ls, curved, D, KINK_TOL, kink)
    return kink


# the fewest rows a thread of Tracker.solve_from takes (below it the thread's start costs
# more than the rows)
_MIN_CHUNK = 16

_INPUT_ERRORS = {
    1: "insertion must be finite",
    2: "rotation must be finite",
    3: "insertion: every D_j must be >= 0 (docs/conventions.md)",
    4: "insertion: D_j must be >= D_{j-1} for every batch element (an inner tube's base lies "
       "behind the outer one's)",
}


@cached_jit(nogil=True)
def _no_rows(b, J, K):
    """Element ``b``'s control step where there is no equilibrium to take it at: NaN."""
    J[b] = np.nan
    K[b] = np.nan


@cached_jit(nogil=True)
def solve_core(EI, GJ, L, Ls, coef, D, A, unloaded, xg, wg, xq, wq, xm, n, q_prev, H_prev,
                cidx_prev, qmc_prev, predict, dA, length, trust, phi, Qb, phi_m, Q_m, small,
                consts, minimize, max_iter, tau, tip, R, res, it, conv, verdict, want_forces,
                tau_D, tau_A, sel, sj, Dn, hmax, side_vals, U, twist):
    """:func:`layout_and_track` up to the stability margin and the control step (the arguments
    of the same names): ``(layout arrays, q, H, Lc)``; :mod:`torchpvs.fused` calls it from
    Python (the layout's 32 arrays come back boxed, about 30 us, where a compiled wrapper would
    compile the whole call tree a second time on first use)."""
    lay = layout_maps_arrays(EI, GJ, L, Ls, coef, D, A, unloaded, 1e-12, xg, wg, xq, wq, xm,
                             phi, n)
    (ell, tau_, start, h, present, curved, active, presc, qmask, psi0, gconst, W,
     tip_tube, _s_tip, before_l1, _sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide,
     bvec, qmask_c, h_c, presc_inc, p_h, p_inc, p_held, p_local) = lay
    B, nq = q_prev.shape
    N = D.shape[1]
    nc = cidx.shape[1]
    Lc = np.empty(B, dtype=D.dtype)
    for b in range(B):
        a = 0.0
        d = 0.0
        for j in range(N):
            a = max(a, ell[b, j])
            d = max(d, D[b, j])
        Lc[b] = max(a + d, 1e-6)
    q = np.empty((B, nq), dtype=D.dtype)
    H = np.empty((B, nc, nc), dtype=D.dtype)
    _track(q_prev, H_prev, cidx_prev, qmc_prev, predict, dA, D, GJ, length, trust, qmask,
           psi0, tip_tube, cidx, qmask_c, bvec, h_c, ustar, EIw, EIws, GJw, Hsec, guide,
           gconst, phi, Qb, psec, p_h, p_inc, p_held, p_local, phi_m, Q_m, h.shape[1], small,
           Lc, consts, minimize, max_iter, tau, q, H, tip, R, res, it, conv, verdict, U)
    _outer_twist(q, qmask, psi0, D, h, before_l1, presc_inc, n, twist)
    if want_forces:
        for b in range(B):
            if conv[b]:
                partials_one(q[b], qmask[b], D[b], L[b], Ls[b], EI[b], GJ[b], coef[b], tau_[b],
                             psi0[b], start[b], h[b], present[b], curved[b], active[b],
                             presc[b], W[b], xq, wq, phi, Qb, tau_D[b], tau_A[b])
            else:
                for j in range(N):
                    tau_D[b, j] = np.nan
                    tau_A[b, j] = np.nan
        _side_forces(q, qmask, conv, sel, sj, Dn, EI, GJ, L, Ls, coef, A, unloaded, xg, wg,
                     xq, wq, xm, phi, Qb, n, hmax, consts[3], side_vals)
    return lay, q, H, Lc


@cached_jit(nogil=True)
def layout_and_track(EI, GJ, L, Ls, coef, D, A, unloaded, xg, wg, xq, wq, xm, n, q_prev,
                      H_prev, cidx_prev, qmc_prev, predict, dA, length, trust, phi, Qb, phi_m,
                      Q_m, small, consts, minimize, max_iter, tau, tip, R, res, it, conv,
                      verdict, jac, D_side, side, J, K, want_forces, tau_D, tau_A, sel, sj, Dn,
                      hmax, side_vals, want_J, U, twist, want_margin, margin):
    """:func:`torchpvs.compiled_layout.layout_maps_arrays` at ``(D, A)`` then :func:`_track`, in
    one call: only what the next step and the caller read is returned to Python, ``(q,
    H, cidx, qmask_c)`` (boxing each of the layout's 32 arrays costs about a microsecond).
    With ``jac``: the control step into ``J``, ``K`` (:func:`_control_rows`), for the rows
    where ``side`` at the insertions ``D_side`` (a kink's one side, torchpvs.jacobians) with
    this ``q`` and ``H`` where the layout there has the same active coordinates, else at the
    side's own equilibrium (one Newton solve from ``q``); ``side`` then reads 2. With
    ``want_forces``: the actuation forces and torques at the solution into ``tau_D, tau_A``
    and the one-sided values at its kinks into ``side_vals`` (:func:`_side_forces`). Always:
    the energy into ``U``, the relative rotations at the outer tube's end into ``twist`` (both
    as :class:`~torchpvs.Equilibrium`); with ``want_margin`` its ``min_stiffness_eigenvalue``
    into ``margin`` (:func:`_margin`). ``want_J`` False: the stiffness without the tip
    Jacobian."""
    lay, q, H, Lc = solve_core(
        EI, GJ, L, Ls, coef, D, A, unloaded, xg, wg, xq, wq, xm, n, q_prev, H_prev, cidx_prev,
        qmc_prev, predict, dA, length, trust, phi, Qb, phi_m, Q_m, small, consts, minimize,
        max_iter, tau, tip, R, res, it, conv, verdict, want_forces, tau_D, tau_A, sel, sj, Dn,
        hmax, side_vals, U, twist)
    (ell, tau_, start, h, present, curved, active, presc, qmask, psi0, gconst, W,
     tip_tube, _s_tip, before_l1, _sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide,
     bvec, qmask_c, h_c, presc_inc, p_h, p_inc, p_held, p_local) = lay
    B = q.shape[0]
    if want_margin:
        for b in range(B):
            margin[b] = _margin(H[b], qmask_c[b])
    if not jac:
        return q, H, cidx, qmask_c
    any_side = False
    for b in range(B):
        any_side = any_side or side[b] > 0
    lay2 = lay
    if any_side:
        lay2 = layout_maps_arrays(EI, GJ, L, Ls, coef, D_side, A, unloaded, 1e-12, xg, wg, xq,
                                  wq, xm, phi, n)
    (_ell, tau2, start2, h2, present2, curved2, active2, presc2, qmask2, psi02, gconst2,
     W2, tip_tube2, _s2, _b2, _sec2, _psec2, cidx2, ustar2, EIw2, EIws2, GJw2, Hsec2,
     guide2, bvec2, qmask_c2, h_c2, _pi2, _ph2, _pinc2, _pheld2, _ploc2) = lay2
    nc2 = cidx2.shape[1]
    q2 = q.copy()
    H2 = np.empty((B, nc2, nc2), dtype=D.dtype)
    g2 = np.empty((B, nc2), dtype=D.dtype)
    U2 = np.empty(B, dtype=D.dtype)
    res2 = np.empty(B, dtype=D.dtype)
    it2 = np.zeros(B, dtype=np.int64)
    conv2 = np.zeros(B, dtype=np.bool_)
    ver2 = np.empty(B, dtype=np.int8)
    qc2 = np.empty((B, nc2), dtype=D.dtype)
    for b in range(B):
        if side[b] > 0 and not conv[b]:
            side[b] = 0
        if not conv[b]:
            _no_rows(b, J, K)
            continue
        if side[b] == 0:
            _control_rows(b, q, H, cidx, qmask_c, qmask, D, L, Ls, EI, GJ, coef, tau_, psi0,
                          start, h, present, curved, active, presc, W, tip_tube, xq, wq, phi,
                          Qb, xm, phi_m, Q_m, J, K, want_J)
            continue
        same = cidx2.shape[1] == cidx.shape[1]
        if same:
            for i in range(q.shape[1]):
                same = same and qmask2[b, i] == qmask[b, i]
        if same:
            _control_rows(b, q, H, cidx, qmask_c, qmask2, D_side, L, Ls, EI, GJ, coef, tau2,
                          psi02, start2, h2, present2, curved2, active2, presc2, W2, tip_tube2,
                          xq, wq, phi, Qb, xm, phi_m, Q_m, J, K, want_J)
            continue
        # a coordinate appears on the side (a base leaving the orifice): its own equilibrium
        side[b] = 2
        for i in range(cidx2.shape[1]):
            qc2[b, i] = q[b, cidx2[b, i]] * qmask2[b, cidx2[b, i]]
        newton_into(b, qc2, qmask_c2, psi02, bvec2, h_c2, ustar2, EIw2, EIws2, GJw2, Hsec2,
                    guide2, gconst2, phi, Qb, None, Lc, consts, minimize, max_iter, H2, g2,
                    U2, res2, it2, conv2, ver2)
        if not conv2[b]:
            _no_rows(b, J, K)
            continue
        for i in range(q.shape[1]):
            q2[b, i] = 0.0
        for i in range(cidx2.shape[1]):
            q2[b, cidx2[b, i]] = qc2[b, i]
        _control_rows(b, q2, H2, cidx2, qmask_c2, qmask2, D_side, L, Ls, EI, GJ, coef, tau2,
                      psi02, start2, h2, present2, curved2, active2, presc2, W2, tip_tube2,
                      xq, wq, phi, Qb, xm, phi_m, Q_m, J, K, want_J)
    return q, H, cidx, qmask_c


@dataclass(frozen=True)
class _Tubes:
    EI: np.ndarray
    GJ: np.ndarray
    length: np.ndarray
    straight: np.ndarray
    coef: np.ndarray


class Tracker:
    """Warm equilibria of one robot (batched) along a control loop, at a fixed discretization.

    Args:
        scene: a :class:`~torchpvs.Scene` or a built-in scene name / file path; unloaded.
        insertion, rotation: ``(N,)`` or ``(B, N)`` [m], [rad]: where the tracker starts
            (default the scene's actuation); the first state is a :func:`torchpvs.solve` there.
        options: :class:`SolverOptions` of that first solve (its accuracy picks the basis
            order and Magnus steps unless ``order`` and ``n_magnus`` are given) and of the
            steps (``tol``, ``accuracy``, ``method``, ``max_iter``). ``dtype`` must be
            float64, ``device`` CPU.
        initial: the first solve's warm start (as :func:`torchpvs.solve`'s): an
            :class:`~torchpvs.Equilibrium` on the branch to follow.

    Raises:
        ValueError: a tip load, a non-float64 or non-CPU option, numba not importable, or a
            first solve that did not converge.

    Attributes: ``order``, ``n_magnus`` (the fixed discretization), ``state`` (the last
    :class:`TrackState`), ``batch``.

    :meth:`snapshot` and :meth:`restore` save and return to a state (e.g. to try several
    actions from one state, as a sampling planner or MPC does); :meth:`solve_from` solves any
    rows from warm starts the caller keeps (the environments' substeps).
    """

    def __init__(self, scene: Scene | str, *, insertion=None, rotation=None,
                 options: SolverOptions | None = None, initial=None):
        from .solver import solve
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        opts = options or SolverOptions()
        if not compiled.available():
            raise ValueError("Tracker needs numba (the compiled kernel): pip install numba")
        if opts.dtype not in (None, torch.float64):
            raise ValueError(f"options.dtype must be torch.float64 for a Tracker, got "
                             f"{opts.dtype}")
        if opts.device is not None and torch.device(opts.device).type != "cpu":
            raise ValueError(f"options.device must be the CPU for a Tracker, got {opts.device}")
        if not scene.load.is_zero:
            raise ValueError("scene.load must be zero for a Tracker (a tip load needs the "
                             "loaded Newton of torchpvs.solve)")
        eq = solve(scene, insertion=insertion, rotation=rotation, initial=initial,
                   options=replace(opts, compute_forces=False))
        if not bool(eq.converged.all()):
            b = int((~eq.converged).nonzero()[0])
            raise ValueError(f"Tracker: the first solve did not converge (element {b}: "
                             f"{eq.reason[b]})")
        self.scene = scene
        self._user_order, self._user_magnus = opts.order, opts.n_magnus
        self.order = int(eq.order)
        self.n_magnus = int(eq.context.discretization.n_magnus)
        self.options = replace(opts, order=self.order, n_magnus=self.n_magnus,
                               compute_forces=False)
        self._disc = self.options.discretization(self.order)
        dt = torch.float64
        tubes = eq.context.tubes
        # (D's bytes, side mask, side insertions) of the last D: a bytes key compares in
        # 0.15 us, np.array_equal in 2 us (the batch and N are fixed, so equal bytes are an
        # equal D)
        self._kink_at = (None, None, None)
        N = scene.n_tubes
        self.N = N
        self._tubes = _Tubes(*(x.detach().numpy().astype(np.float64) for x in
                               (tubes.EI, tubes.GJ, tubes.length, tubes.straight, tubes.coef)))
        self._length = float(tubes.length.max())
        P = tubes.coef.shape[-1]
        tab = self._disc.tables(dt, torch.device("cpu"))
        xg, wg = gauss_legendre(max(2, P + 1), dtype=dt)
        self._layout_tables = tuple(np.ascontiguousarray(a.numpy()) for a in
                                    (xg, wg, tab.xq, tab.wq, tab.xm, tab.phi_q))
        self._phi, self._Qb = tab.phi_q.numpy(), tab.Q_q.numpy()
        self._phi_m, self._Q_m = tab.phi_m.numpy(), tab.Q_m.numpy()
        self._n = self._disc.n_basis
        self.nq = n_coordinates(N, self._n)
        eps = float(torch.finfo(dt).eps)
        self._tau = stability_threshold(dt)
        self._consts = np.array([tolerance(newton_tol(scene, self.options), dt),
                                 0.01 * eps ** 0.5, eps, float(torch.finfo(dt).tiny)])
        # the state: padded q, compact Hessian on the layout's compact coordinates
        info = eq.context.implicit
        self._q = np.ascontiguousarray(eq.q.detach().numpy())
        self._H = np.ascontiguousarray(info.Hc.detach().numpy())
        self._cidx = np.ascontiguousarray(info.cidx.numpy())
        self._qmc = np.ascontiguousarray(info.qmask_c.detach().numpy())
        self._D = np.ascontiguousarray(eq.context.insertion.detach().numpy(), dtype=np.float64)
        self._A = np.ascontiguousarray(eq.context.rotation.detach().numpy(), dtype=np.float64)
        self.batch = B = self._q.shape[0]
        # the tube arrays broadcast to the batch once (the layout call reads (B, ...) arrays)
        tb = self._tubes
        # (writable copies: a readonly view is another type to numba, see fused._tube_arrays)
        self._tube_args = tuple(np.array(np.broadcast_to(a, (B,) + a.shape[-k:]), order="C")
                                for a, k in ((tb.EI, 1), (tb.GJ, 1), (tb.length, 1),
                                             (tb.straight, 1), (tb.coef, 3)))
        self._tube_args_k = {B: (self._tube_args, np.zeros(B, dtype=np.bool_))}
        self._pool: ThreadPoolExecutor | None = None    # solve_from's threads, made on use
        self._pool_size = 0
        # (placeholders of the compiled call's Jacobian arguments when none are asked for)
        self._no_J, self._no_K = np.empty((B, 6, 2 * N)), np.empty((B, 2 * N, 2 * N))
        self._no_sel, self._no_Dn = np.zeros(0, dtype=np.int64), np.zeros((0, N))
        self._no_tau, self._no_vals = np.empty((B, N)), np.empty(0)
        self._force_plan = (None, None)       # (D's bytes, kink plan) of the last D
        self._curved = np.ascontiguousarray(
            (np.abs(tb.coef).sum((-1, -2)) > 0).reshape(-1))
        self._hmax = VANISHING * self._length
        self.state = TrackState(q=self._q.copy(), tip=eq.tip_position.detach().numpy().copy(),
                                R=eq.tip_rotation.detach().numpy().copy(),
                                converged=eq.converged.numpy().copy(),
                                residual=eq.residual_norm.detach().numpy().copy(),
                                iterations=eq.iterations.numpy().copy(),
                                stable=eq.stable.numpy().copy(),
                                energy=eq.energy.detach().numpy().copy(),
                                relative_rotation_at_outer_tip=(
                                    eq.relative_rotation_at_outer_tip.detach().numpy().copy()))

    def equilibrium(self, options: SolverOptions | None = None):
        """:func:`torchpvs.solve` at the tracker's current actuation, warm from its
        coordinates, with ``options`` (default: the tracker's own, automatic order and Magnus
        steps restored, forces computed): the full :class:`~torchpvs.Equilibrium` (actuation
        forces, stability margin, Jacobians, gradients), or the re-solve of a step that did
        not converge. The tracker's state is not changed."""
        from .solver import solve
        opts = options or replace(self.options, order=self._user_order,
                                  n_magnus=self._user_magnus, compute_forces=True)
        return solve(self.scene, insertion=torch.from_numpy(self._D.copy()),
                     rotation=torch.from_numpy(self._A.copy()),
                     initial=torch.from_numpy(self._q.copy()), options=opts)

    def snapshot(self) -> _Snapshot:
        """The tracker's state (warm start, Hessian, actuation, last result), for
        :meth:`restore`. Arrays are not copied: a step replaces them, it never writes into
        them."""
        return _Snapshot(self._q, self._H, self._cidx, self._qmc, self._D, self._A, self.state)

    def restore(self, snap: _Snapshot) -> None:
        """Return to a :meth:`snapshot` of this tracker: the next step starts from it."""
        if not isinstance(snap, _Snapshot) or snap.q.shape != (self.batch, self.nq):
            raise ValueError("restore: snap must be a snapshot() of this tracker")
        self._q, self._H, self._cidx, self._qmc, self._D, self._A, self.state = snap

    def _batched(self, x, name: str) -> np.ndarray:
        """``x`` as a fresh C-contiguous float64 ``(B, N)`` array (the step wraps it in
        place and keeps it as its state); the values are checked by :func:`_check_and_wrap`."""
        if isinstance(x, torch.Tensor):
            x = x.detach().cpu().numpy()
        a = np.array(x, dtype=np.float64, order="C")
        if a.ndim == 1:
            a = a[None]
        if a.shape != (self.batch, self.N):
            raise ValueError(f"{name} must have shape ({self.N},) or ({self.batch}, {self.N}) "
                             f"(the tracker's batch), got {a.shape}")
        return a

    def _kinks(self, D: np.ndarray) -> np.ndarray:
        """``(B, N)`` bool: :func:`torchpvs.forces.kink_mask` at ``D`` (compiled)."""
        tb = self._tubes
        return kink_mask_arrays(tb.length.reshape(-1), tb.straight.reshape(-1), self._curved, D)

    def _kink_side(self, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(side (B,) int8, D_side (B, N))``: the rows whose insertions sit at a kink of
        ``U*(D_j)`` and the insertions of the one side :mod:`torchpvs.jacobians` takes there
        (``KINK_DELTA`` retracted, inserted where the tube's end is at the orifice; nesting
        kept); kept for the next step at the same insertions."""
        last_D, side, D_side = self._kink_at
        key = D.tobytes()
        if last_D == key:
            return side.copy(), D_side
        kink = self._kinks(D)
        L = np.broadcast_to(self._tubes.length, D.shape)
        sign = np.where(np.abs(L - D) <= KINK_DELTA / 2, -1.0, 1.0)
        D_side = np.maximum.accumulate(D + KINK_DELTA * sign * kink, axis=-1)
        side = kink.any(-1).astype(np.int8)
        self._kink_at = (key, side, D_side)
        return side.copy(), D_side

    def _kink_plan(self, D: np.ndarray):
        """The one-sided forces' sides (torchpvs.forces.equilibrium_forces): ``(kink (B, N),
        blocked (B, N), sel, sj, Dn, n_retract)``: every kink ``(sel, sj)`` retracted by
        ``KINK_DELTA``, then those whose carriage can move in inserted; ``Dn`` the sides'
        insertions (nesting kept). Kept for the next step at the same insertions."""
        last_D, plan = self._force_plan
        key = D.tobytes()
        if last_D == key:
            return plan
        kink = self._kinks(D)
        plan = (kink, *kink_sides(kink, D))
        self._force_plan = (key, plan)
        return plan

    def step(self, insertion, rotation, *, jacobians: bool = False, stiffness: bool = False,
             forces: bool = False, margin: bool = False) -> TrackState:
        """The equilibrium at ``insertion`` ``(N,)``/``(B, N)`` [m] and ``rotation`` [rad],
        warm from the last state; becomes :attr:`state`. Elements that did not converge keep
        their result (``converged`` False, ``residual``): the next step starts from it, so a
        caller that needs a converged state re-solves with :meth:`equilibrium`.

        ``jacobians=True``: the control step, the tip Jacobian and the actuator stiffness at
        the new equilibrium from its own Hessian (:class:`TrackState`), in the same compiled
        call; ``stiffness=True`` the actuator stiffness alone. ``forces=True``: the actuation
        forces and torques that hold it (closed form, one-sided at kinks as
        :func:`torchpvs.solve` reports them), in the same call. ``margin=True``: the
        stability margin (``min_stiffness_eigenvalue``)."""
        D = self._batched(insertion, "insertion")
        A = self._batched(rotation, "rotation")
        B = D.shape[0]
        dA = np.empty_like(A)
        predict = np.empty(B, dtype=np.bool_)
        code = _check_and_wrap(D, A, self._D, self._A, predict, dA)
        if code:
            raise ValueError(_INPUT_ERRORS[code])
        state, (q, H, cidx, qmask_c) = self._run(
            D, A, (self._q, self._H, self._cidx, self._qmc), predict, dA, jacobians, stiffness,
            forces, margin)
        self._q, self._H, self._cidx, self._qmc, self._D, self._A = q, H, cidx, qmask_c, D, A
        self.state = state
        return state

    def solve_from(self, initial, insertion, rotation, *, stiffness: bool = False,
                   forces: bool = False, margin: bool = False,
                   threads: int | None = None) -> TrackState:
        """The equilibria of ``k`` elements (any ``k``) at ``insertion``, ``rotation``
        ``(k, N)`` [m], [rad], warm from ``initial`` ``(k, nq)`` (coordinates of nearby
        equilibria, e.g. a :class:`TrackState`'s ``q``), at the tracker's discretization:
        what ``torchpvs.solve(scene, insertion=..., rotation=..., initial=initial,
        options=SolverOptions(order=k, n_magnus=m))`` computes (no rotation predictor: a
        plain warm start). The tracker's own state is neither read nor changed: a batch that
        keeps its own warm starts and retries steps (an environment's substeps) solves here.
        ``stiffness``, ``forces``, ``margin`` as :meth:`step`.

        ``threads`` (default ``torch.get_num_threads()``): the rows are split into that many
        contiguous chunks solved at once (the compiled calls release the GIL), from 16 rows a
        chunk; every row's result is the same as in one call."""
        q0 = np.array(initial.detach().cpu().numpy() if isinstance(initial, torch.Tensor)
                      else initial, dtype=np.float64, order="C")
        D = np.array(insertion, dtype=np.float64, order="C")
        A = np.array(rotation, dtype=np.float64, order="C")
        k = q0.shape[0] if q0.ndim == 2 else -1
        for name, a, n in (("initial", q0, self.nq), ("insertion", D, self.N),
                           ("rotation", A, self.N)):
            if a.ndim != 2 or a.shape != (k, n):
                raise ValueError(f"{name} must have shape (k, {n}) with the same k for "
                                 f"initial, insertion and rotation, got {a.shape}")
        predict = np.zeros(k, dtype=np.bool_)
        dA = np.empty_like(A)
        code = _check_and_wrap(D, A, D, A.copy(), predict, dA)
        if code:
            raise ValueError(_INPUT_ERRORS[code])
        predict[:] = False
        T = torch.get_num_threads() if threads is None else threads
        if isinstance(T, bool) or not isinstance(T, (int, np.integer)) or T < 1:
            raise ValueError(f"threads must be an integer >= 1, got {threads!r}")
        T = int(min(T, k // _MIN_CHUNK)) if k >= 2 * _MIN_CHUNK else 1

        def run(lo: int, hi: int) -> TrackState:
            n = hi - lo
            none = (np.zeros((n, 1, 1)), np.zeros((n, 1), dtype=np.int64), np.zeros((n, 1)))
            return self._run(D[lo:hi], A[lo:hi], (q0[lo:hi],) + none, predict[lo:hi],
                             dA[lo:hi], False, stiffness, forces, margin)[0]

        if T == 1:
            return run(0, k)
        cuts = np.linspace(0, k, T + 1).astype(int)
        if self._pool is None or self._pool_size < T:
            if self._pool is not None:      # a larger pool replaces it: release its threads
                self._pool.shutdown(wait=False)
            self._pool = ThreadPoolExecutor(max_workers=T, thread_name_prefix="tracker")
            self._pool_size = T
        parts = list(self._pool.map(run, cuts[:-1], cuts[1:]))
        return TrackState(**{f.name: (None if getattr(parts[0], f.name) is None else
                                      np.concatenate([getattr(p, f.name) for p in parts]))
                             for f in fields(TrackState)})

    def _tube_args_for(self, k: int) -> tuple:
        """``(tube arrays, unloaded)`` broadcast to ``k`` elements (the layout call reads
        ``(k, ...)`` arrays)."""
        args = self._tube_args_k.get(k)
        if args is None:
            args = (tuple(np.array(np.broadcast_to(a[:1], (k,) + a.shape[1:]), order="C")
                          for a in self._tube_args), np.zeros(k, dtype=np.bool_))
            self._tube_args_k[k] = args
        return args

    def _run(self, D, A, prev, predict, dA, jacobians, stiffness, forces, margin):
        """One compiled call at ``(D, A)`` (checked and wrapped) from ``prev = (q, H, cidx,
        qmask_c)``: the :class:`TrackState` and the next ``prev``."""
        B = D.shape[0]
        xg, wg, xq, wq, xm, _ = self._layout_tables
        tip = np.empty((B, 3))
        R = np.empty((B, 3, 3))
        res = np.empty(B)
        it = np.zeros(B, dtype=np.int64)
        conv = np.zeros(B, dtype=np.bool_)
        verdict = np.empty(B, dtype=np.int8)
        U = np.empty(B)
        twist = np.empty((B, max(self.N - 1, 0)))
        marg = np.empty(B)
        m = 2 * self.N
        rows = jacobians or stiffness
        if rows:
            side, D_side = self._kink_side(D)
            J, K = np.empty((B, 6, m)), np.empty((B, m, m))
        else:
            side, D_side = np.zeros(B, dtype=np.int8), D
            J, K = self._no_J[:1], self._no_K[:1]
        if forces:
            kink, blocked, sel, sj, Dn, n_r = self._kink_plan(D)
            tD, tA, vals = np.empty((B, self.N)), np.empty((B, self.N)), np.empty(len(sel))
        else:
            sel, sj, Dn = self._no_sel, self._no_sel, self._no_Dn
            tD, tA, vals = self._no_tau, self._no_tau, self._no_vals
        tubes, unloaded = self._tube_args_for(B)
        q, H, cidx, qmask_c = layout_and_track(
            *tubes, D, A, unloaded, xg, wg, xq, wq, xm, self._n,
            *prev, predict, dA, self._length, PREDICTOR_TRUST, self._phi, self._Qb,
            self._phi_m, self._Q_m, 1e-6, self._consts, self.options.method == "minimize",
            self.options.max_iter, self._tau, tip, R, res, it, conv, verdict, rows, D_side,
            side, J, K, forces, tD, tA, sel, sj, Dn, self._hmax, vals, jacobians, U, twist,
            margin, marg)
        out = {}
        if forces:
            retract = tD.copy()
            retract[sel[:n_r], sj[:n_r]] = vals[:n_r]
            ins = tD.copy()
            ins[blocked] = np.nan
            ins[sel[n_r:], sj[n_r:]] = vals[n_r:]
            out = {"actuation_forces": retract, "actuation_torques": tA,
                   "actuation_forces_insertion": ins, "force_kink": kink.copy()}
        state = TrackState(q=q, tip=tip, R=R, converged=conv, residual=res, iterations=it,
                           stable=conv & (verdict == 1), energy=U,
                           relative_rotation_at_outer_tip=twist,
                           min_stiffness_eigenvalue=marg if margin else None,
                           tip_jacobian=J if jacobians else None,
                           actuator_stiffness=K if rows else None, **out)
        return state, (q, H, cidx, qmask_c)
