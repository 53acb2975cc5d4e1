"""Stage 7, ``torchpvs.equilibrium``: what an :class:`~torchpvs.Equilibrium` holds on small solves:
every documented field's shape, dtype and invariants, the energy against the closed form of
fully overlapping planar tubes (paper eq. 31), the stability verdicts at the section III-B
robot's three equilibria (paper Fig. 2), failures, the backbone and the JSON contract."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import two_tubes

import torchpvs as tp
from torchpvs.newton import stability_threshold
from torchpvs.sections import n_coordinates

DT = torch.float64


@pytest.fixture(scope="module")
def fig3():
    """Three default (automatic-order) equilibria of the Fig. 3 robot."""
    scene = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.5], [0.0, 1.0], [0.0, 2.0]], dtype=DT)
    return scene, tp.solve(scene, rotation=rot)


def test_fields_shapes_and_invariants(fig3):
    scene, eq = fig3
    B, N = 3, scene.n_tubes
    assert len(eq) == eq.batch_size == B
    assert eq.q.shape == (B, n_coordinates(N, eq.order + 1)) and eq.q.dtype == DT
    shapes = {"tip_position": (B, 3), "tip_rotation": (B, 3, 3),
              "relative_rotation_at_outer_tip": (B, N - 1), "energy": (B,),
              "actuation_forces": (B, N), "actuation_torques": (B, N),
              "actuation_forces_insertion": (B, N), "force_kink": (B, N), "converged": (B,),
              "residual_norm": (B,), "iterations": (B,), "stable": (B,), "dofs": (B,),
              "error_estimate": (B,), "accuracy_met": (B,), "min_stiffness_eigenvalue": (B,)}
    for name, shape in shapes.items():
        assert getattr(eq, name).shape == shape, name
    for name in ("force_kink", "converged", "stable", "accuracy_met"):
        assert getattr(eq, name).dtype == torch.bool, name
    assert not eq.iterations.dtype.is_floating_point and not eq.dofs.dtype.is_floating_point
    assert bool(eq.converged.all()) and eq.reason == ("converged",) * B
    assert bool((eq.residual_norm < tp.SolverOptions().tol).all())
    R = eq.tip_rotation
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=DT).expand(B, 3, 3),
                          atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(B, dtype=DT), atol=1e-12)
    rel = eq.relative_rotation_at_outer_tip
    assert bool(((rel > -math.pi) & (rel <= math.pi)).all())
    # inactive coordinates are zero: at most dofs nonzero entries, dofs <= the layout's size
    assert bool(((eq.q != 0).sum(-1) <= eq.dofs).all())
    assert bool((eq.dofs <= eq.q.shape[-1]).all())
    # automatic order: an a posteriori estimate within the requested accuracy
    assert bool(torch.isfinite(eq.error_estimate).all())
    assert torch.equal(eq.accuracy_met, eq.error_estimate <= tp.SolverOptions().accuracy)
    assert isinstance(eq.solve_time_s, float) and eq.solve_time_s > 0


@pytest.mark.parametrize("alpha2", [0.0, math.pi])
def test_energy_of_fully_overlapping_planar_tubes_eq31(alpha2):
    """Paper eq. (31): aligned (or opposed) planar tubes of equal length share the curvature
    k = (EI1 k1 + EI2 k2) / (EI1 + EI2) without torsion, so the stored energy is
    (L / 2) [EI1 (k - k1)^2 + EI2 (k - k2)^2]; the rotation torques vanish by symmetry."""
    L = 0.05
    sc = two_tubes(L=L, alpha2=alpha2)
    eq = tp.solve(sc, options=tp.SolverOptions(order=2))
    EI1, EI2 = (t.bending_stiffness for t in sc.tubes)
    k1, k2 = 9.9, 13.8 * math.cos(alpha2)
    k = (EI1 * k1 + EI2 * k2) / (EI1 + EI2)
    expected = 0.5 * L * (EI1 * (k - k1) ** 2 + EI2 * (k - k2) ** 2)
    assert float(eq.energy[0]) == pytest.approx(expected, rel=1e-10)
    assert float(eq.actuation_torques.abs().max()) < 1e-12
    assert bool(eq.stable[0])


def test_stability_verdicts_at_the_three_equilibria_of_section3b():
    """Paper Fig. 2: with the inner tube turned 180 deg the section III-B robot has an unstable
    symmetric equilibrium (relative rotation pi at the outer tube's end, tip in the xz plane),
    which ``method="root"`` converges to from the torsionless start, and two stable mirror
    ones, one of which ``minimize`` returns. ``stable`` is ``min_stiffness_eigenvalue`` above
    ``stability_threshold``, and an unstable one is reported converged but not stable."""
    scene = tp.load_scene("renda2021_section3b")
    rot = [0.0, math.pi]
    sym = tp.solve(scene, rotation=rot, options=tp.SolverOptions(method="root", order=3))
    mirror = tp.solve(scene, rotation=rot, options=tp.SolverOptions(order=3))
    tau = stability_threshold(DT)
    assert bool(sym.converged[0]) and not bool(sym.stable[0])
    assert float(sym.min_stiffness_eigenvalue[0]) < 0
    assert abs(float(sym.relative_rotation_at_outer_tip[0, 0])) == pytest.approx(math.pi,
                                                                                 abs=1e-9)
    assert abs(float(sym.tip_position[0, 1])) < 1e-12
    assert sym.as_contract()["stable"] is False
    assert bool(mirror.converged[0]) and bool(mirror.stable[0])
    assert float(mirror.min_stiffness_eigenvalue[0]) > tau
    assert abs(float(mirror.relative_rotation_at_outer_tip[0, 0])) < math.pi - 0.5
    assert abs(float(mirror.tip_position[0, 1])) > 0.05          # off the symmetry plane
    # the stable equilibrium stores less energy than the symmetric saddle
    assert float(mirror.energy[0]) < float(sym.energy[0])


def test_a_failed_solve_says_why_and_is_not_stable():
    """A solve cut off after one iteration: converged False, stable False (no equilibrium to
    judge), a reason naming the residual and iterations, and null stability in the contract."""
    scene = tp.load_scene("renda2021_section3b")
    eq = tp.solve(scene, rotation=[0.0, 3.0],
                  options=tp.SolverOptions(max_iter=1, order=3, on_failure="ignore"))
    assert not bool(eq.converged[0]) and not bool(eq.stable[0])
    assert "residual" in eq.reason[0] and "iterations" in eq.reason[0]
    assert eq.as_contract()["converged"] is False and eq.as_contract()["stable"] is None


def test_fixed_order_has_no_error_estimate():
    eq = tp.solve(tp.load_scene("renda2021_fig3"), options=tp.SolverOptions(order=2))
    assert eq.order == 2 and math.isnan(float(eq.error_estimate[0]))
    assert not bool(eq.accuracy_met[0])
    assert eq.as_contract()["error_estimate"] is None


def test_backbone_runs_from_the_orifice_to_the_tip(fig3):
    """Uniform arc-length samples from the orifice (the origin) to the tip; consecutive samples
    are at most the arc-length step apart (a chord is shorter than its arc), and the polyline's
    length approaches the exposed length of the tube forming the tip."""
    scene, eq = fig3
    pts = eq.backbone(201)
    assert pts.shape == (3, 201, 3)
    assert torch.allclose(pts[:, 0], torch.zeros(3, 3, dtype=DT), atol=1e-15)
    assert torch.allclose(pts[:, -1], eq.tip_position, rtol=0, atol=1e-12)
    s_tip = max(t.length - d for t, d in zip(scene.tubes, scene.actuation.insertion,
                                             strict=True))
    chords = (pts[:, 1:] - pts[:, :-1]).norm(dim=-1)
    assert float(chords.max()) <= s_tip / 200 * (1 + 1e-9)
    assert torch.allclose(chords.sum(-1), torch.full((3,), s_tip, dtype=DT), rtol=1e-4)
    for bad in (1, 0, 2.5):
        with pytest.raises(ValueError, match="points"):
            eq.backbone(bad)


def test_json_contract_mirrors_the_fields(fig3):
    _, eq = fig3
    b = 1
    c = eq.as_contract(b, backbone_points=5)
    assert json.loads(json.dumps(c)) == c
    assert c["model"] == "pvs" and c["converged"] is True and c["stable"] is True
    assert c["tip_position"] == eq.tip_position[b].tolist()
    assert c["tip_rotation"] == eq.tip_rotation[b].tolist()
    assert c["actuation_forces"] == eq.actuation_forces[b].tolist()
    assert c["actuation_torques"] == eq.actuation_torques[b].tolist()
    assert c["force_kink"] == eq.force_kink[b].tolist()
    assert c["energy"] == float(eq.energy[b]) and c["dofs"] == int(eq.dofs[b])
    assert c["iterations"] == int(eq.iterations[b])
    assert c["min_stiffness_eigenvalue"] == float(eq.min_stiffness_eigenvalue[b])
    assert len(c["backbone"]) == 5 and c["backbone"][-1] == pytest.approx(c["tip_position"])
    assert "backbone" not in eq.as_contract(b)
