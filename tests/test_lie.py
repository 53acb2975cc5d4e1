"""Stage 3→4, ``torchpvs.lie``: the SO(3)/SE(3) helpers against independent references:
scipy's rotations (``scipy.spatial.transform.Rotation``: Rodrigues' formula and the rotation
log), ``scipy.linalg.expm``/``logm`` of the 4x4 twist matrix, the matrix commutator for the
se(3) bracket, and a closed-form helix for the 4th-order Magnus step."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from torchpvs.lie import (
    SMALL_BATCH_TWISTS,
    exp_se3,
    exp_so3,
    hat,
    magnus4_step,
    rot_z,
    se3_bracket,
)

DT = torch.float64
vec3 = st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3)
vec6 = st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6)


def twist_matrix(xi: np.ndarray) -> np.ndarray:
    """The 4x4 matrix of a twist (omega, v), written out."""
    w, v = xi[:3], xi[3:]
    X = np.zeros((4, 4))
    X[:3, :3] = [[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]]
    X[:3, 3] = v
    return X


@settings(max_examples=50, deadline=None)
@given(vec3, vec3)
def test_hat_is_the_cross_product_matrix(a, b):
    A = hat(torch.tensor(a, dtype=DT))
    assert torch.equal(A, -A.T)
    assert torch.allclose(A @ torch.tensor(b, dtype=DT),
                          torch.tensor(np.cross(a, b), dtype=DT), rtol=0, atol=1e-14)


@settings(max_examples=60, deadline=None)
@given(vec3, st.sampled_from([1.0, 1e-2, 1e-4, 1e-8, 0.0]))
def test_exp_so3_is_rodrigues(w, scale):
    """exp_so3 equals scipy's rotation from the rotation vector (down to zero rotation, the
    series branch), is a rotation (R^T R = I, det 1), and maps its axis to itself."""
    w = np.asarray(w) * scale
    R = exp_so3(torch.tensor(w, dtype=DT))
    ref = Rotation.from_rotvec(w).as_matrix()
    assert np.allclose(R.numpy(), ref, rtol=0, atol=1e-14)
    assert torch.allclose(R.T @ R, torch.eye(3, dtype=DT), atol=1e-14)
    assert float(torch.linalg.det(R)) == pytest.approx(1.0, abs=1e-14)
    assert torch.allclose(R @ torch.tensor(w, dtype=DT), torch.tensor(w, dtype=DT), atol=1e-14)


@settings(max_examples=60, deadline=None)
@given(vec3.filter(lambda w: 1e-6 < float(np.linalg.norm(w)) < math.pi - 1e-3))
def test_exp_so3_log_round_trip(w):
    """log(exp(w)) = w for rotation angles in (0, pi), the log from scipy."""
    R = exp_so3(torch.tensor(w, dtype=DT)).numpy()
    assert np.allclose(Rotation.from_matrix(R).as_rotvec(), w, rtol=0, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(vec6.filter(lambda x: 1e-3 < float(np.linalg.norm(x[:3])) < math.pi - 0.1))
def test_exp_se3_log_round_trip(xi):
    """logm(exp_se3(xi)) is the twist matrix of xi (principal log, rotation angle below pi),
    and the rotation block of exp_se3 is exp_so3 of the angular part."""
    xi = np.asarray(xi)
    g = exp_se3(torch.tensor(xi, dtype=DT))
    assert np.allclose(scipy.linalg.logm(g.numpy()).real, twist_matrix(xi), rtol=0, atol=1e-10)
    assert torch.allclose(g[:3, :3], exp_so3(torch.tensor(xi[:3], dtype=DT)), atol=1e-14)
    assert torch.equal(g[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=DT))


def test_exp_se3_closed_forms():
    """Pure translation: (I, v). A screw about z (omega = (0, 0, t), v = (0, 0, c)):
    rotation by t about z with translation c along it. A pure rotation: no translation."""
    v = torch.tensor([0.1, -0.2, 0.3], dtype=DT)
    g = exp_se3(torch.cat([torch.zeros(3, dtype=DT), v]))
    assert torch.equal(g[:3, :3], torch.eye(3, dtype=DT)) and torch.allclose(g[:3, 3], v)
    t, c = 0.7, 0.25
    g = exp_se3(torch.tensor([0.0, 0.0, t, 0.0, 0.0, c], dtype=DT))
    assert torch.allclose(g[:3, :3], rot_z(torch.tensor(t, dtype=DT)), atol=1e-15)
    assert torch.allclose(g[:3, 3], torch.tensor([0.0, 0.0, c], dtype=DT), atol=1e-15)
    g = exp_se3(torch.tensor([0.3, -0.4, 1.2, 0.0, 0.0, 0.0], dtype=DT))
    assert torch.allclose(g[:3, 3], torch.zeros(3, dtype=DT), atol=1e-16)


def test_exp_se3_broadcasts_over_leading_dims():
    xi = torch.randn(2, 3, 6, dtype=DT, generator=torch.Generator().manual_seed(0))
    g = exp_se3(xi)
    assert g.shape == (2, 3, 4, 4)
    for i in range(2):
        for j in range(3):
            assert torch.allclose(g[i, j], exp_se3(xi[i, j]), rtol=0, atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6),
       st.sampled_from([1.0, 1e-3, 1e-9, 0.0]))
def test_exp_se3_matches_the_matrix_exponential(xi, scale):
    """The closed-form SE(3) exponential, in both of its forms, equals scipy.linalg.expm of the
    twist matrix (an independent algorithm: Pade with scaling and squaring), down to zero
    rotation (the series branches). torch.linalg.matrix_exp is not the reference: at
    xi = (0, 0, 1/32, 0, 0, 0) its sine entry is off by 2.4e-11."""
    dt = torch.float64
    x = torch.tensor(xi, dtype=dt)
    x[:3] *= scale
    X = torch.zeros(4, 4, dtype=dt)
    w, v = x[:3], x[3:]
    X[:3, :3] = torch.tensor([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]],
                             dtype=dt)
    X[:3, 3] = v
    ref = torch.from_numpy(scipy.linalg.expm(X.numpy()))
    # one twist: the 3x3 matrix form; a batch beyond SMALL_BATCH_TWISTS: the entry-wise form
    assert torch.allclose(exp_se3(x), ref, rtol=1e-12, atol=1e-13)
    assert torch.allclose(exp_se3(x.expand(SMALL_BATCH_TWISTS + 1, 6))[-1], ref, rtol=1e-12,
                          atol=1e-13)


@pytest.mark.parametrize("form", ["matrix", "entry-wise"])
def test_exp_se3_gradient_is_finite_at_zero_rotation(form):
    """gradcheck of both forms at zero rotation, in the series range of c (|w|^2 < 0.1) and
    beyond it."""
    def f(x):
        return exp_se3(x) if form == "matrix" else exp_se3(x.expand(SMALL_BATCH_TWISTS + 1, 6))[-1]

    for w in ([0.0, 0.0, 0.0], [0.1, -0.15, 0.05], [0.3, -0.2, 0.1]):
        x = torch.tensor(w + [0.1, -0.2, 1.0], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(f, (x,))




def test_magnus_step_exact_for_constant_strain_and_4th_order_for_helix():
    """Constant strain: one Magnus step equals the exponential. Variable strain (a rod whose
    curvature grows linearly, u_y = c s): error falls ~h^4 per unit length (global order 4)."""
    dt = torch.float64
    xi = torch.tensor([0.0, 12.0, 0.0, 0.0, 0.0, 1.0], dtype=dt)
    g = magnus4_step(xi, xi, torch.tensor(0.1, dtype=dt))
    assert torch.allclose(g, exp_se3(0.1 * xi), atol=1e-15)

    def integrate(steps):
        L, c = 0.2, 200.0
        h = L / steps
        pose = torch.eye(4, dtype=dt)
        for i in range(steps):
            s0 = i * h
            pts = [s0 + h * (0.5 - 3**0.5 / 6), s0 + h * (0.5 + 3**0.5 / 6)]
            x1, x2 = (torch.tensor([0.0, c * s, 0.0, 0.0, 0.0, 1.0], dtype=dt) for s in pts)
            pose = pose @ magnus4_step(x1, x2, torch.tensor(h, dtype=dt))
        return pose[:3, 3]

    # Planar: the tangent angle is c s^2 / 2, so x(L), z(L) are Fresnel-type integrals.
    s = torch.linspace(0, 0.2, 200001, dtype=dt)
    ang = 200.0 * s**2 / 2
    ref = torch.stack([torch.trapezoid(torch.sin(ang), s), torch.zeros((), dtype=dt),
                       torch.trapezoid(torch.cos(ang), s)])
    e1 = (integrate(8) - ref).norm()
    e2 = (integrate(16) - ref).norm()
    assert e2 < e1 / 12  # 4th order: ratio ~16
    assert math.isfinite(float(e2))




@settings(max_examples=50, deadline=None)
@given(vec6, vec6)
def test_se3_bracket_is_the_matrix_commutator(x, y):
    """[x, y] = ad_x y is the twist of X Y - Y X (X, Y the 4x4 twist matrices); antisymmetric."""
    x, y = np.asarray(x), np.asarray(y)
    b = se3_bracket(torch.tensor(x, dtype=DT), torch.tensor(y, dtype=DT))
    X, Y = twist_matrix(x), twist_matrix(y)
    assert np.allclose(twist_matrix(b.numpy()), X @ Y - Y @ X, rtol=0, atol=1e-12)
    assert torch.allclose(b, -se3_bracket(torch.tensor(y, dtype=DT), torch.tensor(x, dtype=DT)),
                          rtol=0, atol=1e-14)


@settings(max_examples=40, deadline=None)
@given(st.floats(-10.0, 10.0))
def test_rot_z_matches_scipy(angle):
    R = rot_z(torch.tensor(angle, dtype=DT))
    assert np.allclose(R.numpy(), Rotation.from_euler("z", angle).as_matrix(), atol=1e-15)
    assert rot_z(torch.zeros(4, 2, dtype=DT)).shape == (4, 2, 3, 3)
