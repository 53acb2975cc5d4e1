"""Stage 3 — strain bases and quadrature on a section's normalized coordinate ``xi in [-1, 1]``.

The basis is the *normalized* Legendre family ``phi_p = sqrt(2p+1) P_p`` so that
``(1/2) int phi_p phi_q dxi = delta_pq``: a coefficient is an RMS strain over the section, which
keeps the stiffness matrix well scaled whatever the order. ``Q_p(xi) = int_{-1}^{xi} phi_p`` gives
angles from torsion strains exactly (an integrated polynomial).
"""

from __future__ import annotations

import functools

import numpy as np
import torch

__all__ = ["gauss_legendre", "legendre_basis"]


def gauss_legendre(n: int, *, dtype: torch.dtype = torch.float64,
                   device: torch.device | str | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` Gauss–Legendre nodes and weights on ``[-1, 1]`` (exact to degree ``2n - 1``).

    The tensors are cached per ``(n, dtype, device)`` and shared: do not modify them in place."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"quadrature points must be an integer >= 1, got {n!r}")
    return _gauss_legendre(n, dtype, torch.device(device) if device is not None else None)


@functools.lru_cache(maxsize=64)
def _gauss_legendre(n: int, dtype: torch.dtype, device: torch.device | None):
    # numpy's leggauss costs ~0.3 ms (an eigenvalue problem): once per size, not once per
    # layout.
    x, w = np.polynomial.legendre.leggauss(n)
    with torch.inference_mode(False):    # cached: ordinary tensors (autograd may save them)
        return (torch.as_tensor(x, dtype=dtype, device=device),
                torch.as_tensor(w, dtype=dtype, device=device))


def legendre_basis(xi: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalized Legendre values and their integrals at ``xi``.

    Returns:
        phi: ``(..., n)`` with ``phi_p(xi) = sqrt(2p+1) P_p(xi)``.
        Q: ``(..., n)`` with ``Q_p(xi) = int_{-1}^{xi} phi_p`` (``Q_0 = xi + 1``,
        ``Q_p = sqrt(2p+1) (P_{p+1} - P_{p-1}) / (2p+1)``), so ``Q_p(1) = 2 delta_p0``.
    """
    P = [torch.ones_like(xi), xi]
    for k in range(1, n + 1):
        P.append(((2 * k + 1) * xi * P[k] - k * P[k - 1]) / (k + 1))
    phi = torch.stack([((2 * p + 1) ** 0.5) * P[p] for p in range(n)], -1)
    Q = [xi + 1.0]
    for p in range(1, n):
        Q.append((P[p + 1] - P[p - 1]) / ((2 * p + 1) ** 0.5))
    return phi, torch.stack(Q, -1)
