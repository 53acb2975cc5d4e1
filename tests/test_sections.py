"""Stage 2, ``torchpvs.sections``: where the free backbone is cut and what each section holds,
against a two-tube scene worked out by hand (every cut, mask and count below is computed in the
comments from the tube lengths and insertions), and the coordinate count ``n_coordinates``."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchpvs.basis import gauss_legendre
from torchpvs.sections import Discretization, TubeTensors, build_layout, n_coordinates

DT = torch.float64
EI = (0.021, 0.012)          # [N m^2] (values only scale the guide energy below)
GJ = (0.016, 0.009)
K1, K2, UZ1 = 10.0, 15.0, 2.0   # precurvatures [1/m]: outer (0, K1, UZ1), inner (0, K2, 0)


def tubes(lengths=(0.10, 0.20), straight=(0.05, 0.10)) -> TubeTensors:
    """Outer tube: 50 mm straight + 50 mm curved; inner: 100 mm straight + 100 mm curved."""
    coef = torch.tensor([[[[0.0], [K1], [UZ1]], [[0.0], [K2], [0.0]]]], dtype=DT)  # (1, 2, 3, 1)
    return TubeTensors(EI=torch.tensor([EI], dtype=DT), GJ=torch.tensor([GJ], dtype=DT),
                       length=torch.tensor([lengths], dtype=DT),
                       straight=torch.tensor([straight], dtype=DT), coef=coef)


def layout(D, loaded=False, n_basis=3, alpha=(0.0, 0.0)):
    B = len(D)
    return build_layout(tubes(), torch.tensor(D, dtype=DT),
                        torch.tensor([alpha] * B, dtype=DT), torch.zeros(B, 3, dtype=DT),
                        torch.zeros(B, 3, dtype=DT), torch.tensor([loaded] * B),
                        Discretization(n_basis=n_basis, n_quad=n_basis + 2, n_magnus=4))


def test_n_coordinates_counts_guide_twists_and_section_strains():
    """N guide twists + 2N sections x (2 bending + N torsion) x n coefficients."""
    assert n_coordinates(2, 3) == 2 + 4 * 4 * 3 == 50
    assert n_coordinates(3, 2) == 3 + 6 * 5 * 2 == 63
    assert n_coordinates(1, 1) == 1 + 2 * 3 * 1


def test_hand_worked_layout_all_sections_nonempty():
    """D = (20, 30) mm. Exposed lengths ell = L - D = (80, 170) mm; transitions tau = Ls - D =
    (30, 70) mm, both on their tubes. Sorted cuts (30, 70, 80, 170) mm give sections
    [0, 30], [30, 70], [70, 80], [80, 170] mm (h = 30, 40, 10, 90 mm; midpoints 15, 50, 75,
    125 mm). The outer tube is present in the first three, the inner in all; the outer is
    curved beyond 30 mm (sections 2, 3), the inner beyond 70 mm (sections 3, 4). Sections 1-3
    hold two tubes and get coordinates; section 4 holds the inner tube alone, unloaded: its
    strain is its precurvature (prescribed, no coordinates)."""
    n = 3
    lay = layout([[0.02, 0.03]], n_basis=n)
    mm = 1e-3
    assert torch.allclose(lay.ell[0], torch.tensor([80, 170], dtype=DT) * mm)
    assert torch.allclose(lay.tau[0], torch.tensor([30, 70], dtype=DT) * mm)
    assert torch.allclose(lay.start[0], torch.tensor([0, 30, 70, 80], dtype=DT) * mm)
    assert torch.allclose(lay.h[0], torch.tensor([30, 40, 10, 90], dtype=DT) * mm)
    assert lay.present[0].tolist() == [[1, 1], [1, 1], [1, 1], [0, 1]]
    assert lay.curved[0].tolist() == [[0, 0], [1, 0], [1, 1], [0, 1]]
    assert lay.active[0].tolist() == [1, 1, 1, 0]
    assert lay.presc[0].tolist() == [0, 0, 0, 1]
    # Coordinates: both guide twists (D > 0, tube reaches the free space) and, in each of the
    # three active sections, 2 bending + 2 torsion strains with n coefficients each.
    assert lay.qmask.shape == (1, n_coordinates(2, n))
    assert int(lay.qmask.sum()) == 2 + 3 * 4 * n
    assert lay.qmask[0, :2].tolist() == [1, 1]
    assert not bool(lay.qmask[0, 2 + 3 * 4 * n:].any())          # the prescribed section
    # The inner tube forms the tip at s = 170 mm; sections ending by the outer tube's end
    # (80 mm): the first three.
    assert lay.tip_tube[0].tolist() == [0, 1]
    assert float(lay.s_tip[0]) == pytest.approx(0.17)
    assert lay.before_l1[0].tolist() == [1, 1, 1, 0]
    # Energy quadrature weights: (h/2) w_q on active sections, so they sum to h there.
    assert torch.allclose(lay.W[0].sum(-1), torch.tensor([30, 40, 10, 0], dtype=DT) * mm)
    # Nothing curved is inside the guide (D_j < Ls_j): no stored guide energy, psi0 = alpha.
    assert float(lay.guide_const[0]) == 0.0
    assert torch.equal(lay.psi0, lay.alpha)


def test_hand_worked_layout_empty_section_and_curved_part_in_the_guide():
    """D = (70, 30) mm. ell = (30, 170) mm; tau = (-20, 70) mm: the outer tube's transition is
    inside the guide (clipped to 0). Cuts (0, 30, 70, 170) mm: an empty first section, then
    [0, 30], [30, 70], [70, 170] mm. Only [0, 30] holds both tubes (active); the other two hold
    the inner tube alone (prescribed). 20 mm of the outer tube's curved part is in the guide:
    it stores (1/2) EI_1 K1^2 x 20 mm, and its z precurvature turns its base by UZ1 x 20 mm."""
    n = 2
    alpha = (0.3, -0.4)
    lay = layout([[0.07, 0.03]], n_basis=n, alpha=alpha)
    mm = 1e-3
    assert torch.allclose(lay.start[0], torch.tensor([0, 0, 30, 70], dtype=DT) * mm)
    assert torch.allclose(lay.h[0], torch.tensor([0, 30, 40, 100], dtype=DT) * mm)
    assert lay.present[0].tolist() == [[0, 0], [1, 1], [0, 1], [0, 1]]
    assert lay.curved[0].tolist() == [[0, 0], [1, 0], [0, 0], [0, 1]]
    assert lay.active[0].tolist() == [0, 1, 0, 0]
    assert lay.presc[0].tolist() == [0, 0, 1, 1]
    assert int(lay.qmask.sum()) == 2 + 4 * n
    assert lay.before_l1[0].tolist() == [1, 1, 0, 0]
    assert float(lay.guide_const[0]) == pytest.approx(0.5 * EI[0] * K1**2 * 0.02, rel=1e-13)
    assert torch.allclose(lay.psi0[0], torch.tensor([alpha[0] + UZ1 * 0.02, alpha[1]],
                                                    dtype=DT), rtol=0, atol=1e-15)


def test_a_tip_load_gives_the_single_tube_section_coordinates():
    """Loaded, the last section of the first scene (inner tube alone) is no longer prescribed:
    it gets 2 bending + 1 torsion strains (only the inner tube is present)."""
    n = 3
    lay = layout([[0.02, 0.03]], loaded=True, n_basis=n)
    assert lay.active[0].tolist() == [1, 1, 1, 1]
    assert lay.presc[0].tolist() == [0, 0, 0, 0]
    assert int(lay.qmask.sum()) == 2 + 3 * 4 * n + 3 * n


def test_no_guide_twist_without_a_guided_part():
    """D_j = 0: tube j starts at the orifice, so there is no guide twist coordinate for it."""
    lay = layout([[0.0, 0.03]])
    assert lay.qmask[0, :2].tolist() == [0, 1]


def test_batch_elements_keep_their_own_layouts():
    """A batch of the two hand-worked insertions gives each element its own layout, equal to
    the layout built for it alone."""
    both = layout([[0.02, 0.03], [0.07, 0.03]])
    for b, D in enumerate(([0.02, 0.03], [0.07, 0.03])):
        alone = layout([D])
        for name, value in zip(type(both)._fields, both, strict=True):
            assert torch.equal(value[b], getattr(alone, name)[0]), name


@settings(max_examples=40, deadline=None)
@given(st.floats(0.0, 0.099), st.floats(0.0, 0.199))
def test_sections_tile_the_free_backbone(D1, D2):
    """For any insertions: 2N sections that start at 0, have nonnegative lengths, tile
    [0, s_tip] end to end, and whose active coordinates never exceed n_coordinates."""
    lay = layout([[D1, D2]])
    assert lay.h.shape == (1, 4) and bool((lay.h >= 0).all())
    assert float(lay.start[0, 0]) == 0.0
    assert torch.allclose(lay.start[0, 1:], (lay.start + lay.h)[0, :-1])
    assert float((lay.start + lay.h)[0, -1]) == pytest.approx(float(lay.s_tip[0]), abs=1e-15)
    assert float(lay.s_tip[0]) == pytest.approx(max(0.1 - D1, 0.2 - D2), abs=1e-15)
    assert int(lay.qmask.sum()) <= n_coordinates(2, 3)
    assert torch.equal(lay.present * (1 - lay.active[..., None]) * (1 - lay.presc[..., None]),
                       torch.zeros_like(lay.present))  # a tube's section: active or prescribed
    assert not math.isnan(float(lay.guide_const[0]))


def test_discretization_tables():
    """The quadrature tables: Gauss nodes and weights of n_quad points, and two Gauss points
    per Magnus sub-step (m equal pieces of [-1, 1])."""
    disc = Discretization(n_basis=3, n_quad=5, n_magnus=4)
    tab = disc.tables(DT, torch.device("cpu"))
    x, w = gauss_legendre(5)
    assert torch.equal(tab.xq, x) and torch.equal(tab.wq, w)
    assert tab.phi_q.shape == tab.Q_q.shape == (5, 3)
    off = 0.25 / math.sqrt(3)
    centers = torch.tensor([-0.75, -0.25, 0.25, 0.75], dtype=DT)
    assert torch.allclose(tab.xm, torch.stack([centers - off, centers + off], -1).reshape(-1))
    assert disc.tables(DT, torch.device("cpu")).xq is tab.xq        # cached
