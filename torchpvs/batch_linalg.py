"""Batch linear algebra of the kernels: one system per batch element, on its active coordinates.

A batch mixes elements whose sections differ (a tube in the guide, a section of zero length),
so each element's Hessian has its own inactive coordinates (identity rows). These helpers
gather every element's active coordinates first (:func:`active_index`), so factorizations and
dense passes skip the padding, scatter the result back (:func:`expand`), and run a large batch
in cache-sized chunks (:func:`chunked`). They know nothing of the mechanics: a compiled or GPU
kernel can use them or not.
"""

from __future__ import annotations

import torch

__all__ = ["CHUNK_BYTES", "GPU_CHUNK_BYTES", "active_index", "chunk_rows", "chunked", "compact",
           "compact_scaled", "expand", "spd_solve", "take"]

CHUNK_BYTES = 4 << 20    # Hessian bytes per chunk of a large batch (cache-sized working set)
# On a GPU a chunk is one launch per pass: chunks there only bound the working memory.
GPU_CHUNK_BYTES = 1 << 30


def chunk_rows(n: int, t: torch.Tensor) -> int:
    """Rows per chunk of a batch of ``n x n`` matrices of ``t``'s dtype on ``t``'s device:
    ``CHUNK_BYTES`` on the CPU (the per-element passes are memory-bound: a cache-sized working
    set), ``GPU_CHUNK_BYTES`` elsewhere (the whole batch in one launch up to that size)."""
    budget = CHUNK_BYTES if t.device.type == "cpu" else GPU_CHUNK_BYTES
    return max(16, budget // (n * n * t.element_size()))


def active_index(qmask: torch.Tensor) -> torch.Tensor | None:
    """``(B, nA)`` indices of each element's active coordinates first (``nA`` = the most active
    coordinates in the batch), padded with distinct inactive ones. Gathering a Hessian with
    :func:`compact` then gives ``nA x nA`` systems (the padding rows are identity rows, as the
    Hessian is identity on inactive coordinates), so the factorizations and every dense pass
    skip the padded coordinates (about half of them for the Fig. 3 robot). ``None`` when every
    coordinate is active (the usual case on the compact coordinates of a batch that shares its
    sections): :func:`compact`, :func:`take` and :func:`expand` are then the identity, and no
    gather is made."""
    if qmask.shape[0] and bool(qmask.all()):
        return None
    n_active = int(qmask.sum(-1).amax()) if qmask.shape[0] else 0
    order = torch.argsort((qmask == 0).to(torch.int8), dim=-1, stable=True)
    return order[:, :max(n_active, 1)]


def compact(H: torch.Tensor, act: torch.Tensor | None) -> torch.Tensor:
    """``H[b][act[b]][:, act[b]]``: ``(B, nq, nq) -> (B, nA, nA)``."""
    if act is None:
        return H
    B, nA = act.shape
    nq = H.shape[-1]
    if B < 64:      # (two gathers: fewer operations, which bound small batches)
        rows = torch.gather(H, 1, act[:, :, None].expand(B, nA, nq))
        return torch.gather(rows, 2, act[:, None, :].expand(B, nA, nA))
    # One gather on flat indices: half the memory traffic of gathering rows, then columns.
    flat = (act[:, :, None] * nq + act[:, None, :]).reshape(B, nA * nA)
    return H.reshape(B, nq * nq).gather(1, flat).view(B, nA, nA)


def take(v: torch.Tensor, act: torch.Tensor | None) -> torch.Tensor:
    """``v[b][act[b]]``: ``(B, nq) -> (B, nA)``."""
    return v if act is None else torch.gather(v, 1, act)


def compact_scaled(H: torch.Tensor, scale: torch.Tensor, act: torch.Tensor | None):
    """The Jacobi-scaled Hessian ``S H S`` (``S = diag(scale)``, ``scale (B, nq)``) on each
    element's active coordinates: ``(B, nA, nA)``, and the gathered scale ``(B, nA)``."""
    sc = take(scale, act)
    return sc[:, :, None] * compact(H, act) * sc[:, None, :], sc


def expand(v: torch.Tensor, act: torch.Tensor | None, nq: int) -> torch.Tensor:
    """Inverse of the compaction for vectors: ``(B, nA) -> (B, nq)``, zero elsewhere."""
    if act is None:
        return v
    return torch.zeros(v.shape[0], nq, dtype=v.dtype, device=v.device).scatter_(1, act, v)


def chunked(fn, q: torch.Tensor, prob, *batched: torch.Tensor, **kwargs) -> tuple:
    """``fn(q, prob, *batched, **kwargs)`` (a tuple of ``(B, ...)`` tensors) over cache-sized
    chunks of the batch (``CHUNK_BYTES`` of ``nq x nq`` Hessians each), concatenated. Elements
    are independent, and the dense per-element passes are memory-bound at large B. ``prob``
    is a :class:`torchpvs.newton.Problem` (its ``subset`` gives a chunk's rows)."""
    B, nq = q.shape
    chunk = chunk_rows(nq, q)
    if B <= 1.5 * chunk:
        return tuple(fn(q, prob, *batched, **kwargs))
    parts = []
    for start in range(0, B, chunk):
        rows = slice(start, min(B, start + chunk))     # views: the maps are not copied
        parts.append(fn(q[rows], prob.subset(rows), *(t[rows] for t in batched), **kwargs))
    return tuple(torch.cat(field) for field in zip(*parts, strict=True))


def spd_solve(H: torch.Tensor, rhs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``H^-1 rhs`` for symmetric positive definite ``H (B, n, n)`` and ``rhs (B, n)`` by
    Cholesky, in cache-sized row chunks (one factorization of a large batch at once is
    slower). Returns ``(x (B, n), ok (B,))``; ``ok`` is False where ``H`` is not positive
    definite (``x`` is then not meaningful)."""
    B, n = rhs.shape
    chunk = chunk_rows(n, H)
    x = torch.empty_like(rhs)
    fail = torch.empty(B, dtype=torch.int32, device=rhs.device)
    for s in range(0, B, chunk):
        L, fail[s:s + chunk] = torch.linalg.cholesky_ex(H[s:s + chunk])
        x[s:s + chunk] = torch.cholesky_solve(rhs[s:s + chunk, :, None], L)[..., 0]
    return x, fail == 0
