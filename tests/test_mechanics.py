"""Stage 4: the closed-form gradient and Hessian against autograd of the energy functional, and
the backbone's closed-form Magnus exponent against the general step (the SE(3) exponential and
the Magnus step themselves: tests/test_lie.py)."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs.lie import exp_se3, magnus4_step
from torchpvs.mechanics import (
    build_maps,
    compact_q,
    elastic_energy,
    elastic_energy_maps,
    elastic_grad_hess,
    expand_hessian,
    expand_q,
    magnus_twists,
    node_constants,
    node_fields,
    pose_constants,
    section_grad_block,
    sum_dim,
    tip_pose,
)
from torchpvs.options import SolverOptions
from torchpvs.plan import tube_tensors
from torchpvs.sections import build_layout, n_coordinates


@pytest.mark.parametrize("order", [0, 2, 4])
@pytest.mark.parametrize("scene_name", ["renda2021_fig3", "renda2021_section3b"])
def test_analytic_derivatives_match_autograd(order, scene_name):
    torch.manual_seed(order)
    dt = torch.float64
    sc = tp.load_scene(scene_name)
    tubes = tube_tensors(sc, dt, torch.device("cpu"))
    B = 3
    D = torch.tensor([sc.actuation.insertion], dtype=dt) * torch.tensor([[1.0], [0.8], [0.5]],
                                                                         dtype=dt)
    D[:, 1] = torch.maximum(D[:, 1], D[:, 0])
    A = torch.rand(B, 2, dtype=dt) * 6
    zeros = torch.zeros(B, 3, dtype=dt)
    disc = SolverOptions().discretization(order)
    lay = build_layout(tubes, D, A, zeros, zeros, torch.zeros(B, dtype=torch.bool), disc)
    tab = disc.tables(dt, torch.device("cpu"))
    nq = n_coordinates(2, disc.n_basis)
    maps = build_maps(lay, tab, nq)
    m = lay.qmask
    q = torch.randn(B, nq, dtype=dt) * 5 * m
    # The maps work on the compact coordinates (every active one kept): compare there, and
    # check that the left-out ones are inactive.
    g, H = elastic_grad_hess(compact_q(q, maps.cidx), maps)
    g, H = expand_q(g, maps.cidx, nq), expand_hessian(H, maps.cidx, nq)
    kept = expand_q(torch.ones_like(maps.qmask), maps.cidx, nq)
    assert bool((kept >= m).all())

    def f(qq, lay_b):
        return elastic_energy(qq, lay_b, tab)

    gA = torch.func.vmap(torch.func.grad(f))(q, lay)
    HA = torch.func.vmap(torch.func.hessian(f))(q, lay)
    mm = m[:, :, None] * m[:, None, :]
    assert torch.allclose(elastic_energy_maps(compact_q(q, maps.cidx), maps), f(q, lay),
                          rtol=1e-13, atol=1e-15)
    assert ((g - gA) * m).abs().max() <= 1e-12 * gA.abs().max()
    assert ((H - HA) * mm).abs().max() <= 1e-12 * HA.abs().max()



def test_section_block_is_the_hessian_block_without_angle_basis_terms():
    """section_grad_block: the gradient is elastic_grad_hess's, and the block of compact
    section k equals the full Hessian's block on that section's coordinates except on the
    pairs of its mean torsions (c_kj0, c_kj'0), which the angles of the sections after it
    couple (b^T V, O(h_k^2)); for the last section (nothing after it) the blocks are equal."""
    dt = torch.float64
    sc = tp.load_scene("renda2021_fig3")
    tubes = tube_tensors(sc, dt, torch.device("cpu"))
    torch.manual_seed(3)
    B, N = 4, 2
    D = torch.tensor([sc.actuation.insertion], dtype=dt).expand(B, N).clone()
    D[:, 0] -= 0.004
    A = torch.rand(B, N, dtype=dt) * 6
    zeros = torch.zeros(B, 3, dtype=dt)
    disc = SolverOptions().discretization(2)
    lay = build_layout(tubes, D, A, zeros, zeros, torch.zeros(B, dtype=torch.bool), disc)
    tab = disc.tables(dt, torch.device("cpu"))
    maps = build_maps(lay, tab, n_coordinates(N, disc.n_basis))
    qc = torch.randn(B, maps.cidx.shape[-1], dtype=dt) * 5 * maps.qmask
    g, H = elastic_grad_hess(qc, maps)
    S = maps.h.shape[1]
    n, C = disc.n_basis, 2 + N
    for k in range(S):
        gk, blk = section_grad_block(qc, maps, torch.full((B,), k))
        assert torch.equal(gk, g)
        i = N + k * C * n + torch.arange(C * n)
        full = H[:, i][:, :, i]
        mean_torsion = torch.zeros(C * n, dtype=torch.bool)
        mean_torsion[2 * n::n] = True
        pairs = mean_torsion[:, None] & mean_torsion[None, :]
        scale = full.abs().max()
        assert ((blk - full)[:, ~pairs]).abs().max() <= 1e-13 * scale
        if k == S - 1:
            assert (blk - full).abs().max() <= 1e-13 * scale
        else:
            assert (blk - full)[:, pairs].abs().max() > 0   # the left-out terms exist


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-300.0, 300.0), min_size=4, max_size=4), st.floats(1e-4, 0.05))
def test_closed_form_magnus_exponent_matches_the_general_step(u, h):
    """The backbone's Magnus exponent in closed form (twists ((ux, uy, 0), e3)) equals the
    general 4th-order step with the se(3) bracket (torchpvs.lie.magnus4_step)."""
    dt = torch.float64
    uu = torch.tensor(u, dtype=dt).reshape(2, 2)
    xi = [torch.tensor([a, b, 0.0, 0.0, 0.0, 1.0], dtype=dt) for a, b in uu]
    ref = magnus4_step(xi[0], xi[1], torch.tensor(h, dtype=dt))
    got = exp_se3(magnus_twists(uu[None], torch.tensor(h, dtype=dt))[0])
    assert torch.allclose(got, ref, rtol=1e-13, atol=1e-14)


def test_cached_node_constants_leave_fields_and_tip_unchanged():
    """node_fields with the layout's precomputed constants (what the solver caches per
    insertion state) equals node_fields computing them, and tip_pose with the constants stored
    by build_maps equals tip_pose without them."""
    scene = tp.load_scene("renda2021_fig3")
    opts = SolverOptions()
    disc = opts.discretization(2)
    dt = torch.float64
    tubes = tube_tensors(scene, dt, torch.device("cpu"))
    D = torch.tensor([[0.0935, 0.2085], [0.05, 0.15]], dtype=dt)
    A = torch.tensor([[0.0, 1.3], [0.2, -2.0]], dtype=dt)
    Z = torch.zeros(2, 3, dtype=dt)
    lay = build_layout(tubes, D, A, Z, Z, torch.zeros(2, dtype=torch.bool), disc)
    tab = disc.tables(dt, torch.device("cpu"))
    nq = n_coordinates(2, disc.n_basis)
    q = 3.0 * torch.randn(2, nq, dtype=dt, generator=torch.Generator().manual_seed(0))
    f0 = node_fields(q, lay, tab.xm, tab.phi_m, tab.Q_m)
    f1 = node_fields(q, lay, tab.xm, tab.phi_m, tab.Q_m, node_constants(lay, tab.xm))
    for k, a, b in zip(f0._fields, f0, f1, strict=True):
        assert torch.equal(a, b), k
    maps = build_maps(lay, tab, nq)
    for a, b in zip(tip_pose(q, lay, tab), tip_pose(q, lay, tab, pose_constants(maps)),
                    strict=True):
        assert torch.allclose(a, b, rtol=0, atol=1e-15)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), three=st.booleans(), loaded=st.booleans())
def test_tip_pose_on_nonempty_sections_equals_the_full_pose(seed, three, loaded):
    """tip_pose from the cached constants walks the nonempty sections only
    (pose_node_constants); an empty section is an identity step, so the result must equal the
    pose over every section slot exactly (up to rounding), for batches whose elements have
    different empty slots: random insertions (tubes retracted into the guide, tips and
    transitions anywhere), random coordinates, two and three tubes, with and without load
    coordinates (which make single-tube sections active)."""
    from envs.robots import rvim_three_tube

    scene = rvim_three_tube().scene if three else tp.load_scene("renda2021_fig3")
    N = scene.n_tubes
    dt = torch.float64
    gen = torch.Generator().manual_seed(seed)
    disc = SolverOptions().discretization(2)
    tubes = tube_tensors(scene, dt, torch.device("cpu"))
    B = 6
    # increasing insertions (the nesting order), some at 0 (all inside the guide)
    D = torch.sort(torch.rand(B, N, generator=gen, dtype=dt) * tubes.length.min(), -1).values
    D = D * (torch.rand(B, 1, generator=gen, dtype=dt) > 0.2)
    A = (torch.rand(B, N, generator=gen, dtype=dt) - 0.5) * 6.0
    F = torch.zeros(B, 3, dtype=dt)
    lay = build_layout(tubes, D, A, F, F, torch.full((B,), loaded), disc)
    tab = disc.tables(dt, torch.device("cpu"))
    nq = n_coordinates(N, disc.n_basis)
    q = 3.0 * torch.randn(B, nq, generator=gen, dtype=dt)
    maps = build_maps(lay, tab, nq)
    assert maps.pose.sec.shape[-1] <= lay.h.shape[-1]
    for a, b in zip(tip_pose(q, lay, tab), tip_pose(q, lay, tab, pose_constants(maps)),
                    strict=True):
        assert torch.allclose(a, b, rtol=0, atol=1e-14), (a - b).abs().max()
    # several coordinate sets per element in one call (a leading dim beyond the layout's)
    q2 = q + 0.1 * torch.randn(B, nq, generator=gen, dtype=dt)
    stacked = tip_pose(torch.stack([q, q2]), lay, tab, pose_constants(maps))
    for k, qk in enumerate((q, q2)):
        for a, b in zip(stacked, tip_pose(qk, lay, tab, pose_constants(maps)), strict=True):
            assert torch.allclose(a[k], b, rtol=0, atol=1e-14)


@pytest.mark.parametrize("size", [1, 2, 3, 4, 5, 7])
@pytest.mark.parametrize("dim", [0, 1, -1, -2])
def test_sum_dim_equals_sum(size, dim):
    """mechanics.sum_dim (explicit adds over short dimensions) is torch.sum."""
    shape = [3, 4, 5]
    shape[dim] = size
    x = torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(size))
    assert torch.allclose(sum_dim(x, dim), x.sum(dim), rtol=1e-15, atol=1e-15)
