"""SO(3)/SE(3) helpers on plain tensors (stage 3→4: strains to poses).

Twists are ordered ``(omega, v)`` — angular first, as in the paper (``xi = (k, u)``).
Poses are ``(..., 4, 4)`` homogeneous matrices; every function broadcasts over leading dims.
Small-angle branches use Taylor series selected by ``torch.where`` with a clamped denominator,
so neither branch can put NaN into values or gradients.
"""

from __future__ import annotations

import torch

__all__ = ["hat", "exp_se3", "exp_so3", "magnus4_step", "rot_z", "se3_bracket"]


def hat(w: torch.Tensor) -> torch.Tensor:
    """``(..., 3) -> (..., 3, 3)`` skew matrix with ``hat(a) @ b = a x b``."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack([
        torch.stack([zero, -w[..., 2], w[..., 1]], -1),
        torch.stack([w[..., 2], zero, -w[..., 0]], -1),
        torch.stack([-w[..., 1], w[..., 0], zero], -1),
    ], -2)


def _coefficients(theta2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``a = sin t / t``, ``b = (1 - cos t) / t^2``, ``c = (t - sin t) / t^3`` as functions of
    ``t^2``, NaN-free for ``t -> 0`` and without cancellation: ``b = 2 (sin(t/2) / t)^2``
    (half-angle form of ``1 - cos t``), and ``c`` by its Taylor series to ``t^8`` (truncation
    below 1e-15 relative) for ``t^2 < 0.1``, where ``t - sin t`` loses digits. With the direct
    forms, twists of about 1e-3 rad had errors of 1e-13 (against scipy.linalg.expm)."""
    small = theta2 < (1e-6 if theta2.dtype == torch.float64 else 1e-3)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = torch.sqrt(t2)
    a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, torch.sin(t) / t)
    half = torch.where(small, 0.5 - theta2 / 48 + theta2**2 / 3840, torch.sin(0.5 * t) / t)
    b = 2 * half * half
    series = theta2 < 0.1
    tc = torch.where(series, torch.ones_like(theta2), t)
    c = torch.where(series,
                    1.0 / 6 - theta2 / 120 + theta2**2 / 5040 - theta2**3 / 362880
                    + theta2**4 / 39916800,
                    (tc - torch.sin(tc)) / (tc * tc * tc))
    return a, b, c


def exp_so3(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ``(..., 3) -> (..., 3, 3)``."""
    a, b, _ = _coefficients((w * w).sum(-1))
    W = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(W.shape)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


#: Twists up to which :func:`exp_se3` uses the 3x3 matrix form (fewer, larger operations: faster
#: for the few dozen twists of a single solve, slower for large batches).
SMALL_BATCH_TWISTS = 512


def exp_se3(xi: torch.Tensor) -> torch.Tensor:
    """Exponential of a twist ``(..., 6) = (omega, v) -> (..., 4, 4)``.

    ``R = I + a W + b W^2`` and ``p = (I + b W + c W^2) v`` (``W = hat(omega)``, coefficients of
    ``t = |omega|`` without cancellation, see :func:`_coefficients`). Up to
    ``SMALL_BATCH_TWISTS`` twists in 3x3 matrix form (about 35 operations: 83 instead of 127 us
    for the 32 twists of a single Fig. 3 pose); beyond, entry by entry with
    ``W^2 = w w^T - t^2 I``, so that every operation runs on ``(...)``-shaped arrays, not on
    ``(..., 3, 3)`` ones (about 6x less memory traffic for the large batches of Magnus steps).
    Both forms agree to rounding (tests/test_mechanics.py checks both against
    ``scipy.linalg.expm``)."""
    if xi.numel() <= 6 * SMALL_BATCH_TWISTS:
        return _exp_se3_matrix(xi)
    return _exp_se3_entrywise(xi)


# Constants of the matrix form: G with ``w @ G = vec(hat(w))``, and the Taylor coefficients of
# ``(sin t / t, sin(t/2) / t, (t - sin t) / t^3)`` in ``t^2`` (rows: powers 0..5). Made per call
# (4 small tensors): tensors cached across calls would escape torch.func transforms when first
# made inside one (the load Hessian runs the tip pose under vmap(jacfwd(grad))).
_HAT = [[0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 1, 0, 0, 0, -1, 0, 0],
        [0, -1, 0, 1, 0, 0, 0, 0, 0]]
_SERIES = [[1.0, 0.5, 1 / 6], [-1 / 6, -1 / 48, -1 / 120], [1 / 120, 1 / 3840, 1 / 5040],
           [-1 / 5040, -1 / 645120, -1 / 362880], [1 / 362880, 1 / 185794560, 1 / 39916800],
           [-1 / 39916800, -1 / 81749606400, -1 / 6227020800]]


def _exp_se3_matrix(xi: torch.Tensor) -> torch.Tensor:
    G = torch.tensor(_HAT, dtype=xi.dtype, device=xi.device)
    series = torch.tensor(_SERIES, dtype=xi.dtype, device=xi.device)
    eye = torch.eye(3, dtype=xi.dtype, device=xi.device)
    w, v = xi[..., :3], xi[..., 3:]
    W = (w @ G).unflatten(-1, (3, 3))
    WW = W @ W
    theta2 = -0.5 * WW.diagonal(dim1=-2, dim2=-1).sum(-1)        # trace(W^2) = -2 t^2
    # The three coefficients at once: series below their thresholds, direct forms above (the
    # direct forms evaluated at t = 1 there, so that neither branch puts NaN into gradients).
    small = 1e-6 if theta2.dtype == torch.float64 else 1e-3
    powers = torch.cumprod(theta2[..., None].expand(theta2.shape + (5,)), -1)
    taylor = series[0] + powers @ series[1:]
    t = torch.sqrt(torch.where(theta2 < small, 1.0, theta2))
    tc = torch.where(theta2 < 0.1, 1.0, t)
    direct = torch.stack([torch.sin(t) / t, torch.sin(0.5 * t) / t,
                          (tc - torch.sin(tc)) / (tc * tc * tc)], -1)
    use_series = theta2[..., None] < theta2.new_tensor([small, small, 0.1])
    a, half, c = torch.where(use_series, taylor, direct)[..., None, None].unbind(-3)
    b = 2 * half * half
    R = eye + a * W + b * WW
    p = (eye + b * W + c * WW) @ v[..., None]
    top = torch.cat([R, p], -1)
    bottom = torch.nn.functional.pad(torch.ones_like(top[..., :1, 3:]), (3, 0))
    return torch.cat([top, bottom], -2)


def _exp_se3_entrywise(xi: torch.Tensor) -> torch.Tensor:
    wx, wy, wz, vx, vy, vz = xi.unbind(-1)
    t2 = wx * wx + wy * wy + wz * wz
    a, b, c = _coefficients(t2)
    d = 1 - b * t2
    bwx, bwy = b * wx, b * wy
    bxy, bxz, byz = bwx * wy, bwx * wz, bwy * wz
    awx, awy, awz = a * wx, a * wy, a * wz
    cwv = c * (wx * vx + wy * vy + wz * vz)
    e = 1 - c * t2
    px = e * vx + b * (wy * vz - wz * vy) + cwv * wx
    py = e * vy + b * (wz * vx - wx * vz) + cwv * wy
    pz = e * vz + b * (wx * vy - wy * vx) + cwv * wz
    zero, one = torch.zeros_like(t2), torch.ones_like(t2)
    return torch.stack([d + bwx * wx, bxy - awz, bxz + awy, px,
                        bxy + awz, d + bwy * wy, byz - awx, py,
                        bxz - awy, byz + awx, d + b * wz * wz, pz,
                        zero, zero, zero, one], -1).unflatten(-1, (4, 4))


def se3_bracket(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Lie bracket ``[x, y] = ad_x y`` of twists ``(omega, v)``."""
    wx, vx, wy, vy = x[..., :3], x[..., 3:], y[..., :3], y[..., 3:]
    return torch.cat([torch.cross(wx, wy, dim=-1),
                      torch.cross(wx, vy, dim=-1) - torch.cross(wy, vx, dim=-1)], -1)


def magnus4_step(xi1: torch.Tensor, xi2: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """4th-order Magnus (Zanna) step for ``g' = g hat(xi)``: ``g(s+h) = g(s) exp(Omega)`` with
    ``Omega = h/2 (xi1 + xi2) + sqrt(3)/12 h^2 [xi1, xi2]``, ``xi1, xi2`` the strains at the two
    Gauss points ``s + h (1/2 -+ sqrt(3)/6)``. ``h`` broadcasts as ``(...,)``."""
    h = h[..., None]
    omega = 0.5 * h * (xi1 + xi2) + (3.0**0.5 / 12.0) * h * h * se3_bracket(xi1, xi2)
    return exp_se3(omega)


def rot_z(angle: torch.Tensor) -> torch.Tensor:
    """Rotation about z: ``(...,) -> (..., 3, 3)``."""
    c, s = torch.cos(angle), torch.sin(angle)
    zero, one = torch.zeros_like(angle), torch.ones_like(angle)
    return torch.stack([torch.stack([c, -s, zero], -1),
                        torch.stack([s, c, zero], -1),
                        torch.stack([zero, zero, one], -1)], -2)
