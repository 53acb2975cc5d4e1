"""Stage 5a, ``torchpvs.newton``: the kernel's batch helpers against torch.linalg on random
symmetric positive definite (and indefinite) matrices, the gathers against plain indexing, the
chunking against one call, and the kernel registry through a solve. (The kernel's solutions are
checked against references in test_solver.py, test_pvs_vs_reference.py and tests/hard/.)"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs import batch_linalg
from torchpvs.batch_linalg import active_index, chunked, compact, compact_scaled, expand, take
from torchpvs.kernel import EAGER, KERNELS
from torchpvs.mechanics import Maps
from torchpvs.newton import (
    Problem,
    _armijo,
    _damped_step,
    scaled_residual,
    stability_threshold,
    tolerance,
)

DT = torch.float64


def spd(B: int, n: int, seed: int, spread: float = 3.0) -> torch.Tensor:
    """Random SPD matrices with diagonals over ``spread`` decades (like a stiffness in mixed
    units)."""
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(B, n, n, dtype=DT, generator=gen)
    d = 10.0 ** (spread * torch.rand(B, n, dtype=DT, generator=gen))
    M = A @ A.transpose(-1, -2) + n * torch.eye(n, dtype=DT)
    return d.sqrt()[:, :, None] * M * d.sqrt()[:, None, :]


def jacobi(H: torch.Tensor) -> torch.Tensor:
    return H.diagonal(dim1=-2, dim2=-1).abs() ** -0.5


def test_active_index_skips_the_gathers_only_when_everything_is_active():
    """batch_linalg.active_index returns None (compact/take/expand are the identity) exactly when
    every coordinate of every element is active; otherwise the gathers give each element's
    active coordinates first."""
    H = torch.randn(2, 4, 4, dtype=torch.float64)
    v = torch.randn(2, 4, dtype=torch.float64)
    full = torch.ones(2, 4, dtype=torch.float64)
    act = active_index(full)
    assert act is None
    assert compact(H, act) is H and take(v, act) is v and expand(v, act, 4) is v
    mask = full.clone()
    mask[1, 1] = 0.0
    act = active_index(mask)
    assert act is not None and act.shape == (2, 4)
    assert act[1, :3].tolist() == [0, 2, 3]
    assert torch.equal(compact(H, act)[1, :3, :3], H[1][[0, 2, 3]][:, [0, 2, 3]])
    assert torch.equal(expand(take(v, act), act, 4), v)




@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 9), st.sampled_from([0.0, 1e-3, 0.5]))
def test_damped_step_solves_the_levenberg_marquardt_system(seed, n, lam0):
    """On SPD matrices: the step solves (H + lam diag|H_ii|) s = -g (torch.linalg.solve), lam
    is kept, and H comes back bit for bit (its diagonal is shifted in place and restored)."""
    B = 4
    H = spd(B, n, seed)
    g = torch.randn(B, n, dtype=DT, generator=torch.Generator().manual_seed(seed + 1))
    lam = torch.full((B,), lam0, dtype=DT)
    H0 = H.clone()
    step, lam_out = _damped_step(H, g, jacobi(H), lam, torch.eye(n, dtype=DT))
    assert torch.equal(H, H0) and torch.equal(lam_out, lam)
    A = H0 + torch.diag_embed(lam[:, None] * H0.diagonal(dim1=-2, dim2=-1).abs())
    ref = torch.linalg.solve(A, -g)
    assert torch.allclose(step, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))


def test_damped_step_shifts_indefinite_matrices_to_a_descent_step():
    """An indefinite H gets its damping raised past the scaled spectrum's negative end: the
    damped matrix is then positive definite, the step solves it and goes downhill (g.s < 0);
    positive definite rows in the same batch keep their exact Newton step."""
    n = 5
    H = spd(3, n, 7)
    evals, V = torch.linalg.eigh(H[1])
    H[1] = V @ torch.diag(evals * torch.tensor([-1.0, 1, 1, -1, 1], dtype=DT)) @ V.T
    g = torch.randn(3, n, dtype=DT, generator=torch.Generator().manual_seed(8))
    lam = torch.zeros(3, dtype=DT)
    step, lam_out = _damped_step(H.clone(), g, jacobi(H), lam, torch.eye(n, dtype=DT))
    assert float(lam_out[1]) > 0 and lam_out[[0, 2]].tolist() == [0.0, 0.0]
    A = H[1] + lam_out[1] * torch.diag(H[1].diagonal().abs())
    assert float(torch.linalg.eigvalsh(A)[0]) > 0
    assert torch.allclose(step[1], torch.linalg.solve(A, -g[1]), rtol=1e-9, atol=1e-12)
    assert float(g[1] @ step[1]) < 0
    for b in (0, 2):
        assert torch.allclose(step[b], torch.linalg.solve(H[b], -g[b]), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("B", [3, 70])      # below 64: two gathers; from 64: one flat gather
def test_compact_take_expand_are_indexing(B):
    """compact/take/expand on each element's active coordinates equal plain indexing; the
    padding rows of an element with fewer active coordinates are identity rows of H."""
    n = 6
    gen = torch.Generator().manual_seed(B)
    H = spd(B, n, B)
    mask = (torch.rand(B, n, generator=gen) < 0.7).to(DT)
    mask[0] = 1.0                              # one element with every coordinate active
    mask[1] = 0.0
    mask[1, [1, 4]] = 1.0                      # one with two
    inactive = torch.diag_embed(1.0 - mask)
    H = H * mask[:, :, None] * mask[:, None, :] + inactive   # identity on inactive rows
    v = torch.randn(B, n, dtype=DT, generator=gen) * mask
    act = active_index(mask)
    nA = int(mask.sum(-1).max())
    assert act.shape == (B, nA)
    Hc, vc = compact(H, act), take(v, act)
    for b in range(B):
        idx = act[b].tolist()
        k = int(mask[b].sum())
        assert sorted(idx[:k]) == mask[b].nonzero().flatten().tolist()
        assert torch.equal(Hc[b], H[b][idx][:, idx]) and torch.equal(vc[b], v[b][idx])
        if k < nA:      # padding: identity rows and zero entries of v
            assert torch.equal(Hc[b, k:, k:], torch.eye(nA - k, dtype=DT))
    assert torch.equal(expand(vc, act, n), v)
    scale = jacobi(H)
    Hs, sc = compact_scaled(H, scale, act)
    full = scale[:, :, None] * H * scale[:, None, :]
    assert torch.equal(sc, take(scale, act))
    assert torch.allclose(Hs, compact(full, act), rtol=1e-15, atol=0)




def test_scaled_residual_is_the_jacobi_scaled_gradient_times_length():
    """max_i |g_i| / |H_ii| x L, the scale |H_ii|^-1/2; not finite (an overflowed gradient or
    stiffness) counts as an infinite residual, never as a small one."""
    H = spd(3, 4, 1)
    g = torch.randn(3, 4, dtype=DT, generator=torch.Generator().manual_seed(2))
    L = torch.tensor([0.1, 0.2, 0.3], dtype=DT)
    res, scale = scaled_residual(g, H, L)
    d = H.diagonal(dim1=-2, dim2=-1)
    assert torch.allclose(scale, d ** -0.5, rtol=1e-15)
    assert torch.allclose(res, (g.abs() / d).amax(-1) * L, rtol=1e-15)
    g[1, 2] = math.inf
    H[2, 0, 0] = math.nan
    res, _ = scaled_residual(g, H, L)
    assert res[1:].tolist() == [math.inf, math.inf] and math.isfinite(float(res[0]))


def test_thresholds_follow_the_precision():
    """Stability threshold 0.01 sqrt(eps): 1.5e-10 in float64, 3.5e-6 in float32; float32
    tolerances are clamped at 1e-5 (it cannot resolve smaller residuals)."""
    assert stability_threshold(torch.float64) == pytest.approx(1.49e-10, rel=1e-2)
    assert stability_threshold(torch.float32) == pytest.approx(3.45e-6, rel=1e-2)
    assert tolerance(1e-9, torch.float64) == 1e-9
    assert tolerance(1e-9, torch.float32) == 1e-5 and tolerance(1e-3, torch.float32) == 1e-3


def test_armijo_accepts_a_decrease_and_rejects_an_increase_or_nan():
    """A step is accepted on Armijo's sufficient decrease, or where the energy does not rise
    beyond its rounding level (8 eps |f0|: there the comparison is noise); an increase or a
    non-finite energy is rejected."""
    f0 = torch.ones(5, dtype=DT)
    slope = -torch.ones(5, dtype=DT)
    eps = torch.finfo(DT).eps
    f = torch.tensor([0.5, 1.0 - 1e-6, 1.0 + 4 * eps, 1.0 + 1e-9, math.nan], dtype=DT)
    assert _armijo(f, f0, 1.0, slope).tolist() == [True, True, True, False, False]
    # a predicted decrease (-slope t) below the rounding level: the residual, not the energy,
    # decides, and the step is taken
    assert _armijo(f0 + 1e-9, f0, 1.0, -1e-18 * torch.ones(5, dtype=DT)).tolist() == [True] * 5


def test_chunked_equals_one_call(monkeypatch):
    """Over cache-sized chunks (CHUNK_BYTES made small here), a row-wise function gives the
    same result as one call, each chunk seeing its own rows of the per-element maps entries and
    the shared ones whole."""
    B, nq = 100, 4
    q = torch.randn(B, nq, dtype=DT, generator=torch.Generator().manual_seed(0))
    # a per-element field (h) and a shared one (phi); the others are not read here
    maps = Maps._make(None for _ in Maps._fields)._replace(
        h=torch.arange(B, dtype=DT), phi=torch.ones(3, dtype=DT))
    prob = Problem(lay=None, tab=None, maps=maps, with_load=False, has_moment=False)
    calls = []

    def fn(q, prob, scale, *, shift):
        calls.append(q.shape[0])
        assert prob.maps.phi.shape == (3,)
        return q * prob.maps.h[:, None] * scale[:, None] + shift, prob.maps.h

    scale = torch.linspace(1, 2, B, dtype=DT)
    whole = fn(q, prob, scale, shift=1.0)
    calls.clear()
    monkeypatch.setattr(batch_linalg, "CHUNK_BYTES", 16 * nq * nq * 8)    # 16 rows per chunk
    parts = chunked(fn, q, prob, scale, shift=1.0)
    assert calls == [16] * 6 + [4]
    assert all(torch.equal(a, b) for a, b in zip(parts, whole, strict=True))


def test_every_per_element_computation_goes_through_the_kernel(monkeypatch):
    """The kernel seam (torchpvs.kernel): SolverOptions(kernel=name) runs every per-element
    computation of the driver through KERNELS[name] -- the cold guess, the Newton solve, the
    single steps of the order estimate, the tip poses, the new-section step of the one-sided
    forces at a kink, the SPD solve of the rotation predictor, the actuator stiffness's
    Hessian rows, the tip load's rows and the tip partials of the tip Jacobian -- so a kernel
    registered with the eager functions wrapped sees each of them called, and returns the eager
    kernel's results bit for bit. An unknown name is refused."""
    assert isinstance(KERNELS["newton"], tp.kernel.Kernel) and KERNELS["newton"] is EAGER
    calls: dict[str, int] = {}

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] = calls.get(name, 0) + 1
            return fn(*args, **kwargs)
        return wrapper

    spy = type(EAGER)(**{f: counted(f, getattr(EAGER, f)) for f in EAGER._fields})
    monkeypatch.setitem(KERNELS, "spy", spy)
    scene = tp.load_scene("renda2021_fig3")
    Ls = scene.tubes[0].straight_length        # the outer tube's kink at the orifice
    cases = [  # (what the call exercises, keyword arguments of solve)
        ("cold automatic order", dict(rotation=torch.tensor([[0.0, 0.5], [0.0, 2.0]], dtype=DT))),
        ("a kink at the orifice", dict(insertion=torch.tensor([[Ls, Ls + 0.02]], dtype=DT))),
    ]
    for what, kw in cases:
        ref = tp.solve(scene, **kw, options=tp.SolverOptions(kernel="newton"))
        eq = tp.solve(scene, **kw, options=tp.SolverOptions(kernel="spy"))
        for a, b in ((eq.q, ref.q), (eq.tip_position, ref.tip_position),
                     (eq.actuation_forces, ref.actuation_forces),
                     (eq.actuation_forces_insertion, ref.actuation_forces_insertion)):
            assert torch.equal(a.nan_to_num(), b.nan_to_num()), what
    # warm, rotations only: the predictor's solve
    e0 = tp.solve(scene, options=tp.SolverOptions(kernel="spy"))
    tp.solve(scene, rotation=torch.tensor(scene.actuation.rotation, dtype=DT) + 0.02,
             initial=e0, options=tp.SolverOptions(kernel="spy"))
    # the actuator stiffness's Hessian rows and the tip partials (jacobians), the same
    # through the seam
    from torchpvs.jacobians import actuator_stiffness, tip_jacobian
    assert torch.equal(actuator_stiffness(eq), actuator_stiffness(ref))
    assert torch.equal(tip_jacobian(eq), tip_jacobian(ref))
    # under a dead tip force the stiffness asks the kernel for the load's rows (the eager
    # kernel has none: its rows then come from autograd, the same bit for bit)
    F = torch.tensor([[0.1, -0.2, 0.05]], dtype=DT)
    eqF, refF = (tp.solve(scene, tip_force=F, options=tp.SolverOptions(kernel=k))
                 for k in ("spy", "newton"))
    assert torch.equal(actuator_stiffness(eqF), actuator_stiffness(refF))
    assert set(calls) == set(EAGER._fields), calls
    with pytest.raises(ValueError, match="options.kernel"):
        tp.SolverOptions(kernel="no-such-kernel")
