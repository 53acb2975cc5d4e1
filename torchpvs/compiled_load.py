"""Stage 5b (part) — the dead tip force's work and its exact derivatives, compiled.

The compiled kernel (:mod:`torchpvs.compiled`) adds to the elastic energy the potential of a
dead tip force, ``-F . p_tip(q)``. Its gradient and Hessian go through the Magnus pose chain
(:func:`torchpvs.mechanics.tip_pose`: ``p = E_1 E_2 ... E_K o`` with ``E_k = exp(Omega_k)`` one
4th-order Magnus step, ``K`` = kept sections x steps per section), where the eager kernel uses
autograd (:func:`torchpvs.newton._load_hessian`: the batch repeated ``nq`` times and two reverse
passes, most of a loaded solve). Here, per element:

* each step's exponential with its exact first and second derivatives in the step's six twist
  components, by second-order forward (jet) arithmetic on the closed-form ``SE(3)`` exponential;
* the twist's first and second derivatives in ``q``: the Magnus twist is bilinear in the
  bending at the step's two nodes, the bending linear in the section's coefficients plus
  ``Rz(psi_j) u*_j`` of a prescribed (held) tube, with ``psi_j`` linear in ``q``;
* the chain: with ``z_ka = dp/dOmega_ka`` and ``omega_ka`` the spatial angular velocity of step
  ``k`` per twist component ``a``, the mixed second derivative of two different steps
  ``k < l`` is exactly ``omega_ka x z_lb`` (the tip is bilinear in ``E_k`` and ``E_l``), so the
  cross blocks are sums of suffix sums; the same step's block comes from the jets.

Cost: O(K nc^2) per element (``nc`` compact coordinates), no autograd graph. Only a force:
a dead tip moment (non-conservative; the eager kernel's symmetric part) keeps the eager path.
The result is checked against the autograd Hessian in ``tests/test_compiled.py``.
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np

try:
    import numba
    from numba import njit
except ImportError:      # pragma: no cover - numba is a dependency; see torchpvs.compiled
    numba = None

    def njit(*args, **kwargs):
        return lambda f: f


def cache_dir(sources: list[bytes], version: str, base: str) -> str:
    """The directory of the compiled kernels' machine code: ``base/numba-<hash>``, the hash of
    the compiled modules' ``sources`` and numba's ``version``. numba invalidates a cached
    function when its own file changes, not when a function it calls from another file does
    (:mod:`torchpvs.compiled`'s kernels call :func:`load_work`), so a cache keyed by one file
    kept the old load terms after this module changed; a directory per source version cannot."""
    h = hashlib.sha256(version.encode())
    for src in sources:
        h.update(hashlib.sha256(src).digest())
    return os.path.join(base, "numba-" + h.hexdigest()[:16])


def _default_cache_dir() -> str | None:
    """:func:`cache_dir` of this installation: under ``NUMBA_CACHE_DIR`` if set, else the user's
    cache (``$XDG_CACHE_HOME`` or ``~/.cache``) ``/torchpvs``; None (numba's own default, beside
    the sources) where the sources cannot be read."""
    here = Path(__file__).resolve().parent
    try:
        sources = [(here / f).read_bytes()
                   for f in ("compiled.py", "compiled_load.py", "compiled_layout.py")]
    except OSError:      # pragma: no cover - e.g. a zipped installation
        return None
    base = os.environ.get("NUMBA_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
        "torchpvs")
    return cache_dir(sources, numba.__version__, base)


_CACHE_DIR = _default_cache_dir() if numba is not None else None


def cached_jit(**options):
    """``njit(cache=True, **options)`` with the machine code cached in :data:`_CACHE_DIR`
    (numba's ``CACHE_DIR`` is set only while the function is registered, so other libraries'
    caches stay where they were)."""
    def decorate(f):
        if numba is None or _CACHE_DIR is None:
            return njit(cache=True, **options)(f)
        old = numba.config.CACHE_DIR
        numba.config.CACHE_DIR = _CACHE_DIR
        try:
            return njit(cache=True, **options)(f)
        finally:
            numba.config.CACHE_DIR = old
    return decorate


_jit = cached_jit(nogil=True)

# a jet: value, gradient (6), Hessian (6 x 6 row-major, upper triangle used) in the twist
# (wx, wy, wz, vx, vy, vz); its first _NG entries: value and gradient
_NJ = 43
_NG = 7


@_jit
def _series(s, shift, derivatives=True):
    """``f(s) = sum_k (-s)^k / (2k + shift)!`` and (with ``derivatives``, else zeros) its first
    two derivatives in ``s`` (used for ``s < 1``: 12 terms leave < 1e-20)."""
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    fact = 1.0
    for i in range(2, shift + 1):
        fact *= i
    sign = 1.0
    for k in range(12):
        c = sign / fact
        f0 += c * s ** k
        if derivatives and k >= 1:
            f1 += c * k * s ** (k - 1)
        if derivatives and k >= 2:
            f2 += c * k * (k - 1) * s ** (k - 2)
        sign = -sign
        fact *= (2 * k + shift + 1) * (2 * k + shift + 2)
    return f0, f1, f2


@_jit
def exp_value(om, E):
    """``E = exp(om)`` (4 x 4) alone: :func:`exp_jets`' value part by the same operations in
    the same order (bit for bit), without its derivatives; what the line search's energy
    evaluations need (``order = 0``)."""
    w0, w1, w2, v0, v1, v2 = om[0], om[1], om[2], om[3], om[4], om[5]
    s = w0 * w0 + w1 * w1 + w2 * w2
    if s < 1.0:
        A = _series(s, 1, False)[0]
        B = _series(s, 2, False)[0]
        C = _series(s, 3, False)[0]
    else:
        t = math.sqrt(s)
        A = math.sin(t) / t
        B = (1 - math.cos(t)) / s
        C = (1 - A) / s
    E[0, 0] = B * (w0 * w0 - s) + 1.0
    E[1, 1] = B * (w1 * w1 - s) + 1.0
    E[2, 2] = B * (w2 * w2 - s) + 1.0
    E[0, 1] = B * (w0 * w1) - A * w2
    E[1, 0] = B * (w0 * w1) + A * w2
    E[0, 2] = B * (w0 * w2) + A * w1
    E[2, 0] = B * (w0 * w2) - A * w1
    E[1, 2] = B * (w1 * w2) - A * w0
    E[2, 1] = B * (w1 * w2) + A * w0
    wv = w0 * v0 + w1 * v1 + w2 * v2
    E[0, 3] = (v0 + B * (w1 * v2 - w2 * v1)) + C * (w0 * wv - s * v0)
    E[1, 3] = (v1 + B * (w2 * v0 - w0 * v2)) + C * (w1 * wv - s * v1)
    E[2, 3] = (v2 + B * (w0 * v1 - w1 * v0)) + C * (w2 * wv - s * v2)
    E[3, 0] = 0.0
    E[3, 1] = 0.0
    E[3, 2] = 0.0
    E[3, 3] = 1.0


@_jit
def _qv(qc, inv, qm, f):
    """The value of padded coordinate ``f`` (zero where it is not compact)."""
    ci = inv[f]
    return qc[ci] * qm[f] if ci >= 0 else 0.0


@_jit
def mat4(A, B, out):
    """out = A @ B for 4 x 4 arrays (out must not alias A or B)."""
    for i in range(4):
        for j in range(4):
            acc = 0.0
            for k in range(4):
                acc += A[i, k] * B[k, j]
            out[i, j] = acc


@_jit
def _exp_coefficients(s):
    """sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3 as functions of s = t^2, each with its
    first and second derivative in s (lie._coefficients, mechanics' Magnus exponential)."""
    if s < 1.0:
        a0, a1, a2 = _series(s, 1)
        b0, b1, b2 = _series(s, 2)
        c0, c1, c2 = _series(s, 3)
        return a0, a1, a2, b0, b1, b2, c0, c1, c2
    t = math.sqrt(s)
    st = math.sin(t)
    ct = math.cos(t)
    a0 = st / t
    a1 = (ct - a0) / (2 * s)
    a2 = (-0.5 * a0 - 3 * a1) / (2 * s)
    b0 = (1 - ct) / s
    b1 = (0.5 * a0 - b0) / s
    b2 = (0.5 * a1 - 2 * b1) / s
    c0 = (1 - a0) / s
    c1 = (-a1 - c0) / s
    c2 = (-a2 - 2 * c1) / s
    return a0, a1, a2, b0, b1, b2, c0, c1, c2


# Jets with the Hessian's upper triangle only (entries 7 + 6 a + b, a <= b; the lower ones are
# never written, so a zeroed buffer keeps them zero): the exponential below needs 15 general
# products and 9 by a single variable, instead of 36 general full ones.
@_jit
def _jmul_u(x, y, o, nj=_NJ):
    """o = x y (its first ``nj`` entries: 7, value and gradient, or all 43)."""
    x0 = x[0]
    y0 = y[0]
    o[0] = x0 * y0
    for a in range(6):
        o[1 + a] = x0 * y[1 + a] + y0 * x[1 + a]
    if nj <= 7:
        return
    for a in range(6):
        xa = x[1 + a]
        ya = y[1 + a]
        for b in range(a, 6):
            k = 7 + 6 * a + b
            o[k] = x0 * y[k] + y0 * x[k] + xa * y[1 + b] + ya * x[1 + b]


@_jit
def _jmul_var(x, vi, i, o, nj=_NJ):
    """o = x om_i, ``vi`` the value of the variable ``om_i`` (first ``nj`` entries)."""
    x0 = x[0]
    o[0] = x0 * vi
    for a in range(6):
        o[1 + a] = vi * x[1 + a]
    o[1 + i] += x0
    if nj <= 7:
        return
    for a in range(6):
        for b in range(a, 6):
            o[7 + 6 * a + b] = vi * x[7 + 6 * a + b]
    for a in range(i + 1):
        o[7 + 6 * a + i] += x[1 + a]
    for b in range(i, 6):
        o[7 + 6 * i + b] += x[1 + b]


@_jit
def _jfun_u(x, f0, f1, f2, o, nj=_NJ):
    """o = f(x) for a scalar function with f(x0) = f0, f'(x0) = f1, f''(x0) = f2 (first
    ``nj`` entries)."""
    o[0] = f0
    for a in range(6):
        o[1 + a] = f1 * x[1 + a]
    if nj <= 7:
        return
    for a in range(6):
        for b in range(a, 6):
            o[7 + 6 * a + b] = f1 * x[7 + 6 * a + b] + f2 * x[1 + a] * x[1 + b]


@_jit
def _jbilinear(o, x, i, y, j, sign):
    """o += sign om_i om_j (``x``, ``y`` their values; i != j)."""
    o[0] += sign * (x * y)
    o[1 + i] += sign * y
    o[1 + j] += sign * x
    a, b = (i, j) if i < j else (j, i)
    o[7 + 6 * a + b] += sign


@_jit
def exp_jets(om, E, dE, J):
    """``E = exp(om)`` (4 x 4, om = (omega, v)) into E and its derivatives ``dE[a] =
    dE/dom_a`` (6, 4, 4): ``R = I + A W + B W^2``, ``t = v + B (w x v) + C (w (w.v) - |w|^2
    v)`` (W = [w]x), by first-order jets (value and gradient, the first 7 entries); ``J`` (9,
    43) scratch. The value part is :func:`exp_value`'s arithmetic, operation for operation.
    The second derivatives the work's Hessian needs, contracted with the force and the tip,
    are :func:`exp_force_hessian`'s."""
    w0, w1, w2 = om[0], om[1], om[2]
    v0, v1, v2 = om[3], om[4], om[5]
    s, Aj, Bj, Cj, wv, t1, t2, t3, ent = J[0], J[1], J[2], J[3], J[4], J[5], J[6], J[7], J[8]
    s[:] = 0.0
    s[0] = w0 * w0 + w1 * w1 + w2 * w2
    for a in range(3):
        s[1 + a] = 2.0 * om[a]
    a0, a1, a2, b0, b1, b2, c0, c1, c2 = _exp_coefficients(s[0])
    _jfun_u(s, a0, a1, a2, Aj, _NG)
    _jfun_u(s, b0, b1, b2, Bj, _NG)
    _jfun_u(s, c0, c1, c2, Cj, _NG)
    E[:, :] = 0.0
    E[3, 3] = 1.0
    dE[:, 3, :] = 0.0
    # R = I + B (w w^T - s I) + A [w]x; [w]x: (0,1) -wz, (0,2) wy, (1,0) wz, (1,2) -wx,
    # (2,0) -wy, (2,1) wx
    for i in range(3):
        for j in range(3):
            t1[:] = 0.0
            if i == j:
                t1[0] = om[i] * om[i] - s[0]
                t1[1 + i] = 2.0 * om[i]
                for c in range(1, _NG):
                    t1[c] -= s[c]
            else:
                _jbilinear(t1, om[i], i, om[j], j, 1.0)
            _jmul_u(Bj, t1, ent, _NG)
            if i == j:
                ent[0] += 1.0
            else:
                k = 3 - i - j
                sign = 1.0 if (j - i) % 3 == 2 else -1.0
                _jmul_var(Aj, om[k], k, t2, _NG)
                for c in range(_NG):
                    ent[c] += sign * t2[c]
            _jet_out(ent, i, j, E, dE)
    # t = v + B (w x v) + C (w (w.v) - s v)
    wv[:] = 0.0
    _jbilinear(wv, w0, 0, v0, 3, 1.0)
    _jbilinear(wv, w1, 1, v1, 4, 1.0)
    _jbilinear(wv, w2, 2, v2, 5, 1.0)
    wv[0] = w0 * v0 + w1 * v1 + w2 * v2
    for i in range(3):
        j = (i + 1) % 3
        k = (i + 2) % 3
        t1[:] = 0.0                                     # cross_i = w_j v_k - w_k v_j
        _jbilinear(t1, om[j], j, om[3 + k], 3 + k, 1.0)
        _jbilinear(t1, om[k], k, om[3 + j], 3 + j, -1.0)
        t1[0] = om[j] * om[3 + k] - om[k] * om[3 + j]
        _jmul_u(Bj, t1, ent, _NG)
        _jmul_var(wv, om[i], i, t2, _NG)                # inner_i = w_i (w.v) - s v_i
        _jmul_var(s, om[3 + i], 3 + i, t3, _NG)
        for c in range(_NG):
            t2[c] -= t3[c]
        _jmul_u(Cj, t2, t3, _NG)
        ent[0] = (om[3 + i] + ent[0]) + t3[0]
        for c in range(1, _NG):
            ent[c] += t3[c]
        ent[1 + 3 + i] += 1.0
        _jet_out(ent, i, 3, E, dE)


@_jit
def exp_force_hessian(om, F, r, M, J):
    """``M (6, 6)``: the Hessian in ``om`` of ``f(om) = F . (exp(om) [r; 1])[:3]`` (``F``,
    ``r`` 3-vectors: a force and a point in the step's frame), what the work's Hessian takes
    from each Magnus step. With :func:`exp_jets`' ``R = I + A W + B W^2`` and ``t``,

        f = F.r + F.v + A w.(r x F) + B [(F.w)(w.r) - |w|^2 F.r + w.(v x F)]
            + C [(F.w)(w.v) - |w|^2 F.v],

    each bracket a quadratic whose jet is written out, times the jets of ``A, B, C`` (functions
    of ``|w|^2``): three jet products instead of the 12 entries' second-order jets contracted
    afterwards. ``J`` (9, 43) scratch."""
    s, Aj, Bj, Cj, P, t1, f = J[0], J[1], J[2], J[3], J[4], J[5], J[6]
    s[:] = 0.0
    s[0] = om[0] * om[0] + om[1] * om[1] + om[2] * om[2]
    for a in range(3):
        s[1 + a] = 2.0 * om[a]
        s[7 + 7 * a] = 2.0
    a0, a1, a2, b0, b1, b2, c0, c1, c2 = _exp_coefficients(s[0])
    _jfun_u(s, a0, a1, a2, Aj)
    _jfun_u(s, b0, b1, b2, Bj)
    _jfun_u(s, c0, c1, c2, Cj)
    F0, F1, F2 = F[0], F[1], F[2]
    u = F0 * om[0] + F1 * om[1] + F2 * om[2]                     # F.w
    # A: w.(r x F), linear in w
    P[:] = 0.0
    P[1] = r[1] * F2 - r[2] * F1
    P[2] = r[2] * F0 - r[0] * F2
    P[3] = r[0] * F1 - r[1] * F0
    P[0] = om[0] * P[1] + om[1] * P[2] + om[2] * P[3]
    _jmul_u(Aj, P, f)
    # B: (F.w)(w.r) - s F.r + w.(v x F)
    c = om[0] * r[0] + om[1] * r[1] + om[2] * r[2]
    Fr = F0 * r[0] + F1 * r[1] + F2 * r[2]
    x0 = om[4] * F2 - om[5] * F1                                 # v x F
    x1 = om[5] * F0 - om[3] * F2
    x2 = om[3] * F1 - om[4] * F0
    P[:] = 0.0
    P[0] = u * c - s[0] * Fr + (om[0] * x0 + om[1] * x1 + om[2] * x2)
    P[1] = F0 * c + r[0] * u - 2.0 * Fr * om[0] + x0
    P[2] = F1 * c + r[1] * u - 2.0 * Fr * om[1] + x1
    P[3] = F2 * c + r[2] * u - 2.0 * Fr * om[2] + x2
    P[4] = F1 * om[2] - F2 * om[1]                               # F x w
    P[5] = F2 * om[0] - F0 * om[2]
    P[6] = F0 * om[1] - F1 * om[0]
    for a in range(3):
        for b in range(a, 3):
            P[7 + 6 * a + b] = F[a] * r[b] + r[a] * F[b] - (2.0 * Fr if a == b else 0.0)
    # d2/dw_a dv_b of w.(v x F) = eps_abj F_j
    P[7 + 6 * 0 + 4] = F2
    P[7 + 6 * 0 + 5] = -F1
    P[7 + 6 * 1 + 3] = -F2
    P[7 + 6 * 1 + 5] = F0
    P[7 + 6 * 2 + 3] = F1
    P[7 + 6 * 2 + 4] = -F0
    _jmul_u(Bj, P, t1)
    for k in range(7, _NJ):
        f[k] += t1[k]
    # C: (F.w)(w.v) - s F.v
    d = om[0] * om[3] + om[1] * om[4] + om[2] * om[5]
    Fv = F0 * om[3] + F1 * om[4] + F2 * om[5]
    P[:] = 0.0
    P[0] = u * d - s[0] * Fv
    for a in range(3):
        P[1 + a] = F[a] * d + om[3 + a] * u - 2.0 * Fv * om[a]
        P[4 + a] = om[a] * u - s[0] * F[a]
        for b in range(a, 3):
            P[7 + 6 * a + b] = F[a] * om[3 + b] + om[3 + a] * F[b] - (2.0 * Fv if a == b else 0.0)
        for b in range(3):
            P[7 + 6 * a + 3 + b] = (F[a] * om[b] + (u if a == b else 0.0)
                                    - 2.0 * F[b] * om[a])
    _jmul_u(Cj, P, t1)
    for a in range(6):
        for b in range(a, 6):
            k = 7 + 6 * a + b
            M[a, b] = f[k] + t1[k]
            M[b, a] = M[a, b]


@_jit
def _jet_out(x, i, j, E, dE):
    """Entry (i, j) of the exponential and its gradient from its jet ``x``."""
    E[i, j] = x[0]
    for a in range(6):
        dE[a, i, j] = x[1 + a]


@_jit
def _column3(V, dOm, k, c):
    """``sum_a V[k, a, :] dOm[k, a, c]``: a 3-vector per twist component (V (K, 6, 3)) along
    coordinate ``c``."""
    x0 = 0.0
    x1 = 0.0
    x2 = 0.0
    for a in range(6):
        d = dOm[k, a, c]
        x0 += V[k, a, 0] * d
        x1 += V[k, a, 1] * d
        x2 += V[k, a, 2] * d
    return x0, x1, x2


@_jit
def _copy4(src, dst):
    """``dst[:, :] = src`` for 4 x 4 frames, element by element: an array assignment compiles
    numba's shape check and its error message (about 2-3 s of first use per shape)."""
    for i in range(4):
        for j in range(4):
            dst[i, j] = src[i, j]


@_jit
def load_work(qc, inv, qm, psi0b, D, sec, h, presc_inc, us_held, presc_local, F, phi, Qb,
              order, gW, HW):
    """The work ``W = F . p_tip`` [J] of one element's dead tip force (returned); with
    ``order >= 1`` its gradient in the compact coordinates into ``gW (nc,)``, with ``order >= 2``
    its Hessian into ``HW (nc, nc)``. ``qc (nc,)`` compact coordinates, ``inv (nq,)`` the compact
    index of each padded coordinate (-1: not compact, zero), ``qm (nq,)`` the padded mask, and
    the layout's pose constants (:class:`torchpvs.mechanics.PoseConstants` of the element,
    compiled.pose_one's arguments). Zero (and nothing computed) for a zero force."""
    nc = qc.shape[0]
    if order >= 1:
        gW[:] = 0.0
    if order >= 2:
        HW[:, :] = 0.0
    if F[0] == 0.0 and F[1] == 0.0 and F[2] == 0.0:
        return 0.0
    dt = qc.dtype
    N = psi0b.shape[0]
    Sp = sec.shape[0]
    G, n = phi.shape
    m = G // 2
    C = 2 + N
    K = Sp * m
    der = order >= 1
    k3 = 3.0 ** 0.5 / 12.0

    start = np.empty(N, dtype=dt)
    dstart = np.zeros((N, nc), dtype=dt)
    for j in range(N):
        start[j] = psi0b[j] + D[j] * _qv(qc, inv, qm, j)
        if der and inv[j] >= 0:
            dstart[j, inv[j]] = D[j] * qm[j]
    Om = np.empty((K, 6), dtype=dt)
    dOm = np.zeros((K, 6, nc), dtype=dt) if der else np.zeros((1, 6, 1), dtype=dt)
    # per step and node: bending u (2), its gradient, and the held tubes' Rz(psi) u* with
    # the angle's gradient (their second derivatives in q)
    uu = np.empty((K, 2, 2), dtype=dt)
    du = np.zeros((K, 2, 2, nc), dtype=dt) if der else np.zeros((1, 2, 2, 1), dtype=dt)
    held = np.zeros((K, 2, N), dtype=np.bool_)
    Rh = np.zeros((K, 2, N, 2), dtype=dt)
    dpsi = np.zeros((K, 2, N, nc), dtype=dt) if der else np.zeros((1, 2, N, 1), dtype=dt)
    hsv = np.empty(K, dtype=dt)
    cols = np.empty((K, nc) if der else (1, 1), dtype=np.int64)   # each step's columns
    ncols = np.zeros(K, dtype=np.int64)
    k = 0
    for kk in range(Sp):
        off = N + sec[kk] * C * n
        hk = h[kk]
        hs = hk / m
        kq = k3 * hs * hs
        for i in range(m):
            for nd in range(2):
                gg = 2 * i + nd
                ux = 0.0
                uy = 0.0
                for p in range(n):
                    ux += _qv(qc, inv, qm, off + p) * phi[gg, p]
                    uy += _qv(qc, inv, qm, off + n + p) * phi[gg, p]
                    if der:
                        ci = inv[off + p]
                        if ci >= 0:
                            du[k, nd, 0, ci] += qm[off + p] * phi[gg, p]
                        ci = inv[off + n + p]
                        if ci >= 0:
                            du[k, nd, 1, ci] += qm[off + n + p] * phi[gg, p]
                for j in range(N):
                    hx = us_held[kk, gg, j, 0]
                    hy = us_held[kk, gg, j, 1]
                    if hx == 0.0 and hy == 0.0:
                        continue
                    held[k, nd, j] = True
                    loc = 0.0
                    for p in range(n):
                        loc += _qv(qc, inv, qm, off + (2 + j) * n + p) * Qb[gg, p]
                    psi = start[j] + 0.5 * hk * loc + presc_local[kk, gg, j]
                    cs = math.cos(psi)
                    sn = math.sin(psi)
                    rx = cs * hx - sn * hy
                    ry = sn * hx + cs * hy
                    Rh[k, nd, j, 0] = rx
                    Rh[k, nd, j, 1] = ry
                    ux += rx
                    uy += ry
                    if der:
                        for c in range(nc):
                            dpsi[k, nd, j, c] = dstart[j, c]
                        for p in range(n):
                            f = off + (2 + j) * n + p
                            ci = inv[f]
                            if ci >= 0:
                                dpsi[k, nd, j, ci] += 0.5 * hk * Qb[gg, p] * qm[f]
                        for c in range(nc):
                            du[k, nd, 0, c] -= ry * dpsi[k, nd, j, c]
                            du[k, nd, 1, c] += rx * dpsi[k, nd, j, c]
                uu[k, nd, 0] = ux
                uu[k, nd, 1] = uy
            u1x, u1y, u2x, u2y = uu[k, 0, 0], uu[k, 0, 1], uu[k, 1, 0], uu[k, 1, 1]
            Om[k, 0] = 0.5 * hs * (u1x + u2x)
            Om[k, 1] = 0.5 * hs * (u1y + u2y)
            Om[k, 2] = kq * (u1x * u2y - u1y * u2x)
            Om[k, 3] = kq * (u1y - u2y)
            Om[k, 4] = -kq * (u1x - u2x)
            Om[k, 5] = hs
            hsv[k] = hs
            if der:
                # the coordinates this step's twist depends on (its section's strains, and
                # through held tubes' angles the twists before it): every other column of its
                # terms is exactly zero, so the loops below skip them (O(m^2 + m nc) per step
                # in the Hessian, not O(nc^2))
                mc = 0
                for c in range(nc):
                    nz = False
                    for nd in range(2):
                        if du[k, nd, 0, c] != 0.0 or du[k, nd, 1, c] != 0.0:
                            nz = True
                        for j in range(N):
                            if held[k, nd, j] and dpsi[k, nd, j, c] != 0.0:
                                nz = True
                    if nz:
                        cols[k, mc] = c
                        mc += 1
                ncols[k] = mc
                for i2 in range(mc):
                    c = cols[k, i2]
                    d1x, d1y = du[k, 0, 0, c], du[k, 0, 1, c]
                    d2x, d2y = du[k, 1, 0, c], du[k, 1, 1, c]
                    dOm[k, 0, c] = 0.5 * hs * (d1x + d2x)
                    dOm[k, 1, c] = 0.5 * hs * (d1y + d2y)
                    dOm[k, 2, c] = kq * (d1x * u2y + u1x * d2y - d1y * u2x - u1y * d2x)
                    dOm[k, 3, c] = kq * (d1y - d2y)
                    dOm[k, 4, c] = -kq * (d1x - d2x)
            k += 1
        for j in range(N):
            f = off + (2 + j) * n
            start[j] += hk * _qv(qc, inv, qm, f) + presc_inc[kk, j]
            if der and inv[f] >= 0:
                dstart[j, inv[f]] += hk * qm[f]
    # the chain: frames before each step, the exponentials and their jets
    Pprev = np.empty((K, 4, 4), dtype=dt)
    E = np.empty((K, 4, 4), dtype=dt)
    P = np.eye(4, dtype=dt)
    if not der:
        for k in range(K):
            _copy4(P, Pprev[k])
            exp_value(Om[k], E[k])
            mat4(Pprev[k], E[k], P)
        return F[0] * P[0, 3] + F[1] * P[1, 3] + F[2] * P[2, 3]
    dE = np.empty((K, 6, 4, 4), dtype=dt)
    J = np.zeros((9, _NJ), dtype=dt)
    for k in range(K):
        _copy4(P, Pprev[k])
        exp_jets(Om[k], E[k], dE[k], J)
        mat4(Pprev[k], E[k], P)
    W = F[0] * P[0, 3] + F[1] * P[1, 3] + F[2] * P[2, 3]
    p = P[:3, 3].copy()
    gOm = np.empty((K, 6), dtype=dt)
    z = np.empty((K, 6, 3), dtype=dt)         # dp/dOm_ka (base frame)
    w = np.empty((K, 6, 3), dtype=dt)         # spatial angular velocity per Om_ka
    MOm = np.empty((K, 6, 6), dtype=dt)       # d2W/dOm_k dOm_k
    r = np.empty(4, dtype=dt)
    Floc = np.empty(3, dtype=dt)
    y = np.empty(3, dtype=dt)
    om = np.empty(3, dtype=dt)
    Pk = np.empty((4, 4), dtype=dt)
    for k in range(K):
        Rp = Pprev[k, :3, :3]
        mat4(Pprev[k], E[k], Pk)
        for i in range(3):       # the tip in frame k
            acc = 0.0
            for l in range(3):
                acc += Pk[l, i] * (p[l] - Pk[l, 3])
            r[i] = acc
        r[3] = 1.0
        for i in range(3):
            Floc[i] = Rp[0, i] * F[0] + Rp[1, i] * F[1] + Rp[2, i] * F[2]
        for a in range(6):
            for i in range(3):
                acc = 0.0
                for l in range(4):
                    acc += dE[k, a, i, l] * r[l]
                y[i] = acc
            gOm[k, a] = Floc[0] * y[0] + Floc[1] * y[1] + Floc[2] * y[2]
            # omega_local = vee(dR_a R^T)
            om[:] = 0.0
            for l in range(3):
                om[0] += 0.5 * (dE[k, a, 2, l] * E[k, 1, l] - dE[k, a, 1, l] * E[k, 2, l])
                om[1] += 0.5 * (dE[k, a, 0, l] * E[k, 2, l] - dE[k, a, 2, l] * E[k, 0, l])
                om[2] += 0.5 * (dE[k, a, 1, l] * E[k, 0, l] - dE[k, a, 0, l] * E[k, 1, l])
            for i in range(3):
                z[k, a, i] = Rp[i, 0] * y[0] + Rp[i, 1] * y[1] + Rp[i, 2] * y[2]
                w[k, a, i] = Rp[i, 0] * om[0] + Rp[i, 1] * om[1] + Rp[i, 2] * om[2]

        if order >= 2:
            exp_force_hessian(Om[k], Floc, r, MOm[k], J)
        for a in range(6):
            ga = gOm[k, a]
            if ga != 0.0:
                for i2 in range(ncols[k]):
                    c = cols[k, i2]
                    gW[c] += ga * dOm[k, a, c]
    if order < 2:
        return W
    T = np.empty((6, nc), dtype=dt)
    Ysuf = np.zeros((3, nc), dtype=dt)
    Cr = np.zeros((nc, nc), dtype=dt)
    for k in range(K - 1, -1, -1):
        mc = ncols[k]
        # the step's own block: dOm^T MOm dOm
        for a in range(6):
            for i2 in range(mc):
                c = cols[k, i2]
                acc = 0.0
                for b in range(6):
                    acc += MOm[k, a, b] * dOm[k, b, c]
                T[a, c] = acc
        for a in range(6):
            for i1 in range(mc):
                c1 = cols[k, i1]
                d = dOm[k, a, c1]
                if d != 0.0:
                    for i2 in range(mc):
                        c2 = cols[k, i2]
                        HW[c1, c2] += d * T[a, c2]
        # cross blocks with the later steps: A_k^T (sum_{l > k} Z_l x F), then Ysuf += Z_k x F
        for i1 in range(mc):
            c1 = cols[k, i1]
            a0, a1, a2 = _column3(w, dOm, k, c1)
            if a0 != 0.0 or a1 != 0.0 or a2 != 0.0:
                for c2 in range(nc):
                    Cr[c1, c2] += a0 * Ysuf[0, c2] + a1 * Ysuf[1, c2] + a2 * Ysuf[2, c2]
        for i2 in range(mc):
            c = cols[k, i2]
            z0, z1, z2 = _column3(z, dOm, k, c)
            Ysuf[0, c] += z1 * F[2] - z2 * F[1]
            Ysuf[1, c] += z2 * F[0] - z0 * F[2]
            Ysuf[2, c] += z0 * F[1] - z1 * F[0]
        # the twist's own second derivative in q, contracted with dW/dOm
        hs = hsv[k]
        kq = k3 * hs * hs
        g0, g1, g2, g3, g4 = gOm[k, 0], gOm[k, 1], gOm[k, 2], gOm[k, 3], gOm[k, 4]
        u1x, u1y, u2x, u2y = uu[k, 0, 0], uu[k, 0, 1], uu[k, 1, 0], uu[k, 1, 1]
        cx0 = 0.5 * hs * g0 + kq * g2 * u2y - kq * g4
        cx1 = 0.5 * hs * g0 - kq * g2 * u1y + kq * g4
        cy0 = 0.5 * hs * g1 - kq * g2 * u2x + kq * g3
        cy1 = 0.5 * hs * g1 + kq * g2 * u1x - kq * g3
        for nd in range(2):
            cx = cx0 if nd == 0 else cx1
            cy = cy0 if nd == 0 else cy1
            for j in range(N):
                if not held[k, nd, j]:
                    continue
                sj = -(cx * Rh[k, nd, j, 0] + cy * Rh[k, nd, j, 1])
                for i1 in range(mc):
                    c1 = cols[k, i1]
                    d = sj * dpsi[k, nd, j, c1]
                    if d != 0.0:
                        for i2 in range(mc):
                            c2 = cols[k, i2]
                            HW[c1, c2] += d * dpsi[k, nd, j, c2]
        bk = kq * g2
        if bk != 0.0:
            for i1 in range(mc):
                c1 = cols[k, i1]
                a1x, a1y = du[k, 0, 0, c1], du[k, 0, 1, c1]
                a2x, a2y = du[k, 1, 0, c1], du[k, 1, 1, c1]
                for i2 in range(mc):
                    c2 = cols[k, i2]
                    HW[c1, c2] += bk * (a1x * du[k, 1, 1, c2] + a2y * du[k, 0, 0, c2]
                                        - a1y * du[k, 1, 0, c2] - a2x * du[k, 0, 1, c2])
    for c1 in range(nc):
        for c2 in range(nc):
            HW[c1, c2] += Cr[c1, c2] + Cr[c2, c1]
    return W
