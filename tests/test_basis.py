"""Stage 3, ``torchpvs.basis``: the normalized Legendre strain basis and Gauss–Legendre quadrature
against hand-written Legendre polynomials, their exact integrals (numpy's ``legint``, an
independent implementation) and the exactness degree of Gauss quadrature."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchpvs.basis import gauss_legendre, legendre_basis

DT = torch.float64


def hand_legendre(x: torch.Tensor) -> list[torch.Tensor]:
    """P_0..P_4 written out (Abramowitz & Stegun 22.16)."""
    return [torch.ones_like(x), x, (3 * x**2 - 1) / 2, (5 * x**3 - 3 * x) / 2,
            (35 * x**4 - 30 * x**2 + 3) / 8]


def test_basis_values_are_normalized_legendre_polynomials():
    x = torch.linspace(-1.0, 1.0, 41, dtype=DT)
    phi, _ = legendre_basis(x, 5)
    assert phi.shape == (41, 5)
    for p, P in enumerate(hand_legendre(x)):
        assert torch.allclose(phi[:, p], math.sqrt(2 * p + 1) * P, rtol=0, atol=1e-14), p
    # at the ends: phi_p(1) = sqrt(2p+1), phi_p(-1) = (-1)^p sqrt(2p+1)
    ends, _ = legendre_basis(torch.tensor([-1.0, 1.0], dtype=DT), 5)
    root = torch.sqrt(2 * torch.arange(5, dtype=DT) + 1)
    assert torch.allclose(ends[1], root, atol=1e-14)
    assert torch.allclose(ends[0], root * (-1.0) ** torch.arange(5, dtype=DT), atol=1e-14)


@pytest.mark.parametrize("n", [1, 3, 6])
def test_basis_is_orthonormal_under_the_half_measure(n):
    """(1/2) int_{-1}^{1} phi_p phi_q dxi = delta_pq, by a quadrature exact for degree 2n."""
    x, w = gauss_legendre(n + 1)
    phi, _ = legendre_basis(x, n)
    gram = 0.5 * (phi * w[:, None]).T @ phi
    assert torch.allclose(gram, torch.eye(n, dtype=DT), rtol=0, atol=1e-13)


def test_integrals_match_numpy_legint():
    """Q_p(xi) = int_{-1}^{xi} phi_p, against numpy's antiderivative of the Legendre series
    (lower bound -1), and Q_p(1) = 2 delta_p0 (orthogonality to P_0)."""
    n = 6
    x = torch.linspace(-1.0, 1.0, 33, dtype=DT)
    _, Q = legendre_basis(x, n)
    assert Q.shape == (33, n)
    for p in range(n):
        c = np.zeros(p + 1)
        c[p] = math.sqrt(2 * p + 1)
        ref = np.polynomial.legendre.legval(x.numpy(), np.polynomial.legendre.legint(c, lbnd=-1))
        assert np.allclose(Q[:, p].numpy(), ref, rtol=0, atol=1e-14), p
    assert torch.allclose(Q[0], torch.zeros(n, dtype=DT), atol=1e-15)          # Q_p(-1) = 0
    assert torch.allclose(Q[-1], torch.tensor([2.0] + [0.0] * (n - 1), dtype=DT), atol=1e-14)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=1, max_size=8), st.integers(1, 7))
def test_derivative_of_the_integral_is_the_basis(xs, n):
    """dQ_p/dxi = phi_p at any point (autograd through the recurrences)."""
    x = torch.tensor(xs, dtype=DT, requires_grad=True)
    phi, Q = legendre_basis(x, n)
    for p in range(n):
        (dQ,) = torch.autograd.grad(Q[:, p].sum(), x, retain_graph=True)
        assert torch.allclose(dQ, phi[:, p].detach(), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_gauss_legendre_is_exact_to_degree_2n_minus_1(n):
    """int_{-1}^{1} x^k dx = 2/(k+1) for even k, 0 for odd k, exact up to k = 2n - 1 and not
    beyond (x^{2n} is the first monomial it misses)."""
    x, w = gauss_legendre(n)
    assert x.shape == w.shape == (n,) and x.dtype == w.dtype == DT
    assert bool((w > 0).all()) and bool((x.diff() > 0).all())
    assert torch.allclose(x, -x.flip(0), atol=1e-15) and torch.allclose(w, w.flip(0))
    for k in range(2 * n):
        exact = 2.0 / (k + 1) if k % 2 == 0 else 0.0
        assert float((w * x**k).sum()) == pytest.approx(exact, rel=1e-13, abs=1e-14), k
    assert abs(float((w * x ** (2 * n)).sum()) - 2.0 / (2 * n + 1)) > 1e-6


def test_gauss_legendre_dtype_cache_and_errors():
    x32, w32 = gauss_legendre(4, dtype=torch.float32)
    assert x32.dtype == w32.dtype == torch.float32
    assert gauss_legendre(4)[0] is gauss_legendre(4)[0]       # cached and shared
    with torch.inference_mode():                              # cached tensors stay ordinary
        assert not gauss_legendre(9)[0].is_inference()
    for bad in (0, -1, 2.0, "3"):
        with pytest.raises(ValueError, match="quadrature points"):
            gauss_legendre(bad)
