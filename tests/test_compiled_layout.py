"""The compiled layout and maps (torchpvs.compiled_layout, numba) against the eager builders.

Reference: :func:`torchpvs.sections.build_layout` and :func:`torchpvs.mechanics.build_maps`
(eager torch), which the rest of the suite checks against closed forms, the paper's tables and
the independent standard model. The compiled builder evaluates the same formulas element by
element: every field of the layout and the maps must agree, elementwise ones bit for bit and
node sums (the energy blocks, the guide's stored energy) to rounding, on the paper's robots,
three nested tubes, seeded random robots, insertions on the section cuts (a tube end at the
orifice, a curved part that starts exactly there, a fully retracted tube), loaded and unloaded
rows and several orders. A solve through the compiled kernel that builds its layouts this way
must then give the eager kernel's equilibria.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs import SolverOptions, compiled, compiled_layout
from torchpvs.kernel import COMPILED, EAGER
from torchpvs.mechanics import build_layout_and_maps
from torchpvs.plan import tube_tensors
from torchpvs.sections import n_coordinates
from torchpvs.testing import (
    assert_same_equilibria,
    feasible_actuations,
    fig3,
    nested_scene,
    random_scene,
)

DT = torch.float64
pytestmark = pytest.mark.skipif(not compiled.available(), reason="numba is not installed")

# Node sums are taken in another order than torch's reductions: agreement to rounding,
# relative to the field's largest entry.
SUM_FIELDS = {"H_sections", "guide_const"}
SUM_RTOL = 1e-13


def _leaves(x, prefix=""):
    """``(name, tensor)`` of a (nested) NamedTuple's tensor fields."""
    for name, v in zip(x._fields, x, strict=True):
        if hasattr(v, "_fields"):
            yield from _leaves(v, f"{prefix}{name}.")
        elif torch.is_tensor(v):
            yield prefix + name, v


def assert_same_layout(scene, D, A, F, order: int = 2, load_coordinates: bool = False):
    """Every field of the compiled ``(lay, maps)`` equals the eager one."""
    tubes = tube_tensors(scene, DT, torch.device("cpu"))
    B, N = D.shape
    M = torch.zeros(B, 3, dtype=DT)
    loaded = (F.abs().sum(-1) > 0) | load_coordinates
    disc = SolverOptions().discretization(order)
    nq = n_coordinates(N, disc.n_basis)
    eager = build_layout_and_maps(tubes, D, A, F, M, loaded, disc, nq)
    comp = compiled_layout.layout_and_maps(tubes, D, A, F, M, loaded, disc, nq)
    assert comp is not None
    names = 0
    for (n_e, a), (n_c, b) in zip(_leaves(eager[0]), _leaves(comp[0]), strict=True):
        assert n_e == n_c
        names += 1
        _assert_field(n_e, a, b)
    for (n_e, a), (n_c, b) in zip(_leaves(eager[1]), _leaves(comp[1]), strict=True):
        assert n_e == n_c
        names += 1
        _assert_field(n_e, a, b)
    assert names > 40           # the comparison walked the whole structures


def _assert_field(name: str, a: torch.Tensor, b: torch.Tensor) -> None:
    assert a.shape == b.shape, (name, a.shape, b.shape)
    assert a.dtype == b.dtype, (name, a.dtype, b.dtype)
    if name.split(".")[-1] in SUM_FIELDS:
        scale = float(a.abs().max()) if a.numel() else 0.0
        assert torch.allclose(a, b, rtol=0, atol=SUM_RTOL * max(scale, 1e-300)), name
    else:
        assert torch.equal(a, b), (name, (a - b).abs().max())


def _batch(scene, rng: np.random.Generator, B: int):
    """Random insertions (each in ``[0, L]``) and rotations, every other row under a tip
    force."""
    L = np.array([t.length for t in scene.tubes])
    N = len(L)
    D = torch.tensor(rng.uniform(0, 1, (B, N)) * L, dtype=DT)
    A = torch.tensor(rng.uniform(-np.pi, np.pi, (B, N)), dtype=DT)
    F = torch.zeros(B, 3, dtype=DT)
    F[::2] = torch.tensor(rng.normal(0, 0.2, (len(F[::2]), 3)), dtype=DT)
    return D, A, F


@pytest.mark.parametrize("order", [1, 2, 3, 5])
@pytest.mark.parametrize("name", ["renda2021_fig3", "renda2021_section3b"])
def test_paper_robots_random_batches(name, order):
    scene = tp.load_scene(name)
    assert_same_layout(scene, *_batch(scene, np.random.default_rng(order), 48), order=order)


def test_three_nested_tubes_and_forced_load_coordinates():
    scene = nested_scene(3, seed=2)
    D, A, F = _batch(scene, np.random.default_rng(7), 32)
    assert_same_layout(scene, D, A, F)
    assert_same_layout(scene, D, A, F, load_coordinates=True)


def test_insertions_on_the_section_cuts():
    """Ties the sort and the masks must break as the eager builder does: a tube's end or the
    start of its curved part exactly at the orifice, equal exposed lengths, a retracted tube,
    a fully inserted one."""
    scene = fig3()
    L = [t.length for t in scene.tubes]
    Ls = [t.straight_length for t in scene.tubes]
    rows = [[L[0], L[1]], [0.0, L[1]], [0.0, 0.0], [Ls[0], Ls[1]], [L[0] - 0.01, L[1] - 0.01],
            [Ls[0], L[1] - (L[0] - Ls[0])], [L[0] * 0.5, L[1] - L[0] * 0.5], [1e-13, 1e-13]]
    D = torch.tensor(rows, dtype=DT).clamp(min=0.0)
    D = torch.minimum(D, torch.tensor(L, dtype=DT))
    A = torch.zeros_like(D)
    F = torch.zeros(len(rows), 3, dtype=DT)
    assert_same_layout(scene, D, A, F)
    F[:, 1] = 0.1
    assert_same_layout(scene, D, A, F)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), B=st.integers(1, 9), order=st.integers(1, 4))
def test_random_robots(seed, B, order):
    scene = random_scene(seed)
    assert_same_layout(scene, *_batch(scene, np.random.default_rng(seed), B), order=order)


def test_falls_back_where_it_does_not_apply():
    """None (the caller builds eagerly) for float32, a graph to keep, or a foreign ``nq``."""
    scene = fig3()
    disc = SolverOptions().discretization(2)
    nq = n_coordinates(2, disc.n_basis)
    F = torch.zeros(1, 3)
    loaded = torch.zeros(1, dtype=torch.bool)
    for dtype in (torch.float32, DT):
        tubes = tube_tensors(scene, dtype, torch.device("cpu"))
        D = torch.tensor([[0.09, 0.2]], dtype=dtype)
        A = torch.zeros(1, 2, dtype=dtype)
        args = (tubes, D, A, F.to(dtype), F.to(dtype), loaded, disc)
        if dtype == torch.float32:
            assert compiled_layout.layout_and_maps(*args, nq) is None
            continue
        assert compiled_layout.layout_and_maps(*args, nq + 1) is None
        assert compiled_layout.layout_and_maps(*args, nq) is not None
        D.requires_grad_(True)
        assert compiled_layout.layout_and_maps(*args, nq) is None
        with torch.no_grad():
            assert compiled_layout.layout_and_maps(*args, nq) is not None


def test_solves_at_new_insertions_match_the_eager_kernel():
    """The compiled kernel builds its layouts compiled: cold solves at many insertions (each a
    new layout) and a tip-loaded batch give the eager kernel's equilibria."""
    assert COMPILED.layout is not EAGER.layout
    scene = fig3()
    rng = np.random.default_rng(3)
    D, A = (torch.tensor(x, dtype=DT) for x in feasible_actuations(rng, 24, scene))
    F = torch.zeros(24, 3, dtype=DT)
    F[::2] = torch.tensor(rng.normal(0, 0.1, (12, 3)), dtype=DT)
    out = [tp.solve(scene, insertion=D, rotation=A, tip_force=F,
                    options=SolverOptions(kernel=k)) for k in ("newton", "compiled")]
    assert bool(out[0].converged.all())
    assert_same_equilibria(*out)
    warm = [tp.solve(scene, insertion=D * 0.98, rotation=A, tip_force=F, initial=o,
                     options=SolverOptions(kernel=k))
            for o, k in zip(out, ("newton", "compiled"), strict=True)]
    assert_same_equilibria(*warm)
