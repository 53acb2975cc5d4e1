"""torchpvs.batch_linalg.spd_solve: the chunked Cholesky solve of the kernels' SPD systems.
Reference: torch.linalg.solve on the same systems (and the definition of positive definite for
the ``ok`` flag). The gathers (``active_index``, ``compact``, ``take``, ``expand``) and
``chunked`` are tested with the Newton step they serve, in test_newton.py."""

from __future__ import annotations

import pytest
import torch

from torchpvs import batch_linalg
from torchpvs.batch_linalg import spd_solve


def spd_batch(B: int, n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(B, n, n, generator=g, dtype=torch.float64)
    H = A @ A.transpose(-1, -2) + n * torch.eye(n, dtype=torch.float64)
    return H, torch.randn(B, n, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("chunk_rows", [None, 16])
def test_spd_solve_equals_a_dense_solve(monkeypatch, chunk_rows):
    B, n = 50, 6
    if chunk_rows is not None:      # chunks of 16 rows: 50 = 16 + 16 + 16 + 2
        monkeypatch.setattr(batch_linalg, "CHUNK_BYTES", chunk_rows * n * n * 8)
    H, rhs = spd_batch(B, n)
    x, ok = spd_solve(H, rhs)
    assert x.shape == (B, n) and ok.shape == (B,) and bool(ok.all())
    ref = torch.linalg.solve(H, rhs[..., None])[..., 0]
    torch.testing.assert_close(x, ref, rtol=1e-12, atol=1e-14)


def test_spd_solve_flags_the_elements_that_are_not_positive_definite(monkeypatch):
    B, n = 40, 4
    monkeypatch.setattr(batch_linalg, "CHUNK_BYTES", 16 * n * n * 8)
    H, rhs = spd_batch(B, n, seed=1)
    bad = [0, 17, 39]                        # one in each chunk, the last in a partial one
    H[bad] = -H[bad]                         # negative definite
    H[5, 0, 0] = 0.0
    H[5, 0, 1:] = H[5, 1:, 0] = 0.0          # positive semidefinite, singular
    x, ok = spd_solve(H, rhs)
    expected = torch.ones(B, dtype=torch.bool)
    expected[bad + [5]] = False
    assert torch.equal(ok, expected)
    good = expected.nonzero().flatten()
    ref = torch.linalg.solve(H[good], rhs[good][..., None])[..., 0]
    torch.testing.assert_close(x[good], ref, rtol=1e-12, atol=1e-14)


def test_chunks_are_cache_sized_on_the_cpu_and_whole_batches_elsewhere():
    """The chunk rule (batch_linalg.chunk_rows): CHUNK_BYTES of n x n matrices on the CPU,
    GPU_CHUNK_BYTES on any other device (a meta tensor stands in for a GPU's here; on an H200
    the CPU's chunks made batches of 16k-131k elements 5.7-19x slower, docs/performance.md)."""
    n = 26
    cpu = torch.zeros(1, dtype=torch.float64)
    other = torch.zeros(1, dtype=torch.float32, device="meta")
    assert batch_linalg.chunk_rows(n, cpu) == batch_linalg.CHUNK_BYTES // (n * n * 8)
    assert batch_linalg.chunk_rows(n, other) == batch_linalg.GPU_CHUNK_BYTES // (n * n * 4)
    assert batch_linalg.chunk_rows(1000, cpu) == 16        # never fewer than 16 rows
