"""Hard cases of docs/physics.md: very unequal stiffnesses (1:100), high precurvature (> 30 1/m, up
to
40 1/m), tubes fully retracted into the guide.

Independent references: closed forms (paper eq. 31 for aligned torsionless tubes: the overlap
bends with ``k = (EI1 k1 + EI2 k2) / (EI1 + EI2)``, a single tube follows its precurvature, so the
backbone is a chain of circular arcs), the standard-model reference solver (torchpvs.reference)
on the same branch, and the same robot without the retracted tube.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import E, G

import torchpvs as tp
from torchpvs.reference import solve_standard
from torchpvs.scene import Actuation, Scene
from torchpvs.testing import MM, dist, matched_reference, nested_scene, tip, two_tubes

TIP_TOL = 1e-5   # the default SolverOptions.accuracy [m]



def arcs_tip(pieces) -> np.ndarray:
    """Tip of a planar chain of arcs ``[(curvature about y [1/m], length [m]), ...]`` leaving
    the orifice along +z (a positive curvature bends toward +x, docs/conventions.md)."""
    x = z = th = 0.0
    for k, ell in pieces:
        if abs(k) < 1e-12:
            x, z = x + ell * math.sin(th), z + ell * math.cos(th)
        else:
            x += (math.cos(th) - math.cos(th + k * ell)) / k
            z += (math.sin(th + k * ell) - math.sin(th)) / k
        th += k * ell
    return np.array([x, 0.0, z])


# (name, scene kwargs): outer 100x stiffer by geometry; inner 100x stiffer (thin, soft outer)
RATIO = {
    "outer 100x stiffer": dict(od1=3.0 * MM, id1=2.0 * MM, od2=0.9 * MM),
    "inner 100x stiffer": dict(E1=1.45e9, od1=2.0 * MM, id1=1.85 * MM, od2=1.8 * MM),
}


@pytest.mark.parametrize("name", list(RATIO))
def test_stiffness_ratio_1_to_100_closed_form(name):
    """Aligned tubes (alpha = 0), bases at the orifice: torsionless, so the overlap is an arc of
    the eq. (31) curvature and the inner tube alone an arc of its own precurvature."""
    sc = two_tubes(10.0, 30.0, **RATIO[name])
    EI1, EI2 = (t.bending_stiffness for t in sc.tubes)
    ratio = max(EI1, EI2) / min(EI1, EI2)
    assert 90 < ratio < 110, ratio
    eq = tp.solve(sc)
    k_overlap = (EI1 * 10.0 + EI2 * 30.0) / (EI1 + EI2)
    expect = arcs_tip([(k_overlap, 0.1), (30.0, 0.05)])
    assert bool(eq.converged[0]) and bool(eq.stable[0])
    assert dist(tip(eq), expect) < 1e-9


@pytest.mark.parametrize("alpha2", [90.0, 150.0, 180.0])
@pytest.mark.parametrize("name", list(RATIO))
def test_stiffness_ratio_1_to_100_vs_reference(name, alpha2):
    """1:100 bending stiffness, guide in front (D = 50/100 mm, straight parts 50/100 mm), relative
    rotation 90..180 deg: PVS (default options) vs the reference on the same branch."""
    sc = two_tubes(10.0, 30.0, Ls1=0.05, Ls2=0.1, D=(0.05, 0.1),
                   alpha=(0.0, math.radians(alpha2)), **RATIO[name])
    eq = tp.solve(sc)
    ref = matched_reference(sc, eq, compute_forces=False)
    assert bool(eq.converged[0]) and ref is not None
    assert dist(tip(eq), ref.tip_position) < TIP_TOL
    assert bool(eq.stable[0]) is ref.stable is True
    tau_p, tau_r = eq.actuation_torques[0].numpy(), ref.actuation_torques
    assert np.abs(tau_p - tau_r).max() <= 1e-3 * np.abs(tau_r).max() + 1e-9


@pytest.mark.parametrize("kappa", [30.0, 40.0])
def test_high_precurvature_single_tube_circle(kappa):
    """One tube, 50 mm straight + 80 mm at kappa (3.2 rad of arc at 40 1/m: beyond a half
    turn), 30 mm of the straight part in the guide: a straight piece then a circle."""
    from torchpvs.scene import Tube
    sc = Scene((Tube(E=E, G=G, inner_diameter=0.0, outer_diameter=1.0 * MM,
                     straight_length=0.05, curved_length=0.08,
                     precurvature=((), (kappa,), ())),),
               Actuation((0.03,), (0.0,)))
    eq = tp.solve(sc)
    assert bool(eq.converged[0])
    assert dist(tip(eq), arcs_tip([(0.0, 0.02), (kappa, 0.08)])) < 1e-9


@pytest.mark.parametrize("alpha2", [0.0, 90.0, 135.0, 180.0])
def test_high_precurvature_two_tubes(alpha2):
    """Two tubes at 40 1/m each (Table I cross-sections), 60 mm and 90 mm curved, behind a guide:
    closed form at alpha2 = 0 (eq. 31), the reference on the same branch otherwise; the stability
    verdicts agree."""
    sc = two_tubes(40.0, 40.0, Lc1=0.06, Lc2=0.09, Ls1=0.05, Ls2=0.1, D=(0.05, 0.1),
                   alpha=(0.0, math.radians(alpha2)))
    eq = tp.solve(sc)
    assert bool(eq.converged[0]) and bool(eq.stable[0])
    if alpha2 == 0.0:
        assert dist(tip(eq), arcs_tip([(40.0, 0.06), (40.0, 0.03)])) < 1e-9
    ref = matched_reference(sc, eq, compute_forces=False)
    assert ref is not None and ref.stable is True
    assert dist(tip(eq), ref.tip_position) < TIP_TOL


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_high_precurvature_three_tubes(seed):
    """Three nested tubes with precurvatures drawn in 5..40 1/m (torchpvs.testing.nested_scene)."""
    sc = nested_scene(3, seed, kappa_max=40.0)
    assert max(t.precurvature[1][0] for t in sc.tubes) > 30.0 or seed != 0
    eq = tp.solve(sc)
    assert bool(eq.converged[0]), eq.reason
    ref = matched_reference(sc, eq, seed=seed, compute_forces=False)
    assert ref is not None, tip(eq)
    assert dist(tip(eq), ref.tip_position) < TIP_TOL
    assert bool(eq.stable[0]) is ref.stable


@pytest.mark.parametrize("extra", [0.0, 10 * MM])
def test_inner_tube_fully_retracted(extra):
    """A 3-tube robot whose innermost tube lies entirely in the guide (D3 = L3 + extra): the
    equilibrium is the 2-tube robot's (exactly), the retracted tube adds no coordinates, holds no
    torque, and feels no force when inside by more than its own end (D3 > L3: U* does not
    depend on D3); the reference agrees."""
    from torchpvs.testing import random_scene
    sc3 = random_scene(1)                   # a 3-tube robot
    L3 = sc3.tubes[2].length
    D = list(sc3.actuation.insertion[:2]) + [L3 + extra]
    sc3 = sc3.with_actuation(insertion=D)
    sc2 = Scene(sc3.tubes[:2], Actuation(tuple(D[:2]), sc3.actuation.rotation[:2]))
    e3, e2 = tp.solve(sc3), tp.solve(sc2)
    r = solve_standard(sc3)
    assert bool(e3.converged[0]) and bool(e3.stable[0]) and r.converged
    assert dist(tip(e3), tip(e2)) < 1e-12
    assert int(e3.dofs[0]) == int(e2.dofs[0])
    assert dist(tip(e3), r.tip_position) < TIP_TOL
    assert float(e3.actuation_torques[0, 2]) == 0.0
    np.testing.assert_allclose(e3.actuation_forces[0, :2].numpy(), e2.actuation_forces[0].numpy(),
                               atol=1e-9)
    if extra > 0:
        assert float(e3.actuation_forces[0, 2]) == 0.0
        assert abs(r.actuation_forces[2]) < 1e-6
    else:   # the tube's end at the orifice: a kink; retraction side 0 (docs/conventions.md)
        assert bool(e3.force_kink[0, 2]) and float(e3.actuation_forces[0, 2]) == 0.0


def test_all_tubes_retracted():
    """Every tube inside the guide: nothing beyond the orifice. Tip at the origin, no
    coordinates, converged and stable; the energy is the precurved material held straight,
    sum 1/2 EI kappa^2 Lc (docs/physics.md), as in the reference."""
    from torchpvs.testing import fig3
    sc = fig3(D1=0.2, D2=0.31)
    eq = tp.solve(sc)
    r = solve_standard(sc)
    assert bool(eq.converged[0]) and bool(eq.stable[0])
    assert int(eq.dofs[0]) == 0
    assert np.abs(tip(eq)).max() == 0.0
    expect = sum(0.5 * t.bending_stiffness * t.precurvature[1][0] ** 2 * t.curved_length
                 for t in sc.tubes)
    assert float(eq.energy[0]) == pytest.approx(expect, rel=1e-12)
    assert r.energy == pytest.approx(expect, rel=1e-9)
    assert np.abs(eq.actuation_forces[0].numpy()).max() == 0.0
