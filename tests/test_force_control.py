"""Force-controlled equilibria (torchpvs.force_control) against independent references:
position solves (round trip x* -> tau(x*) -> x), a bisection on position solves for a commanded
torque, and the range of the elastic torque over a full turn."""

from __future__ import annotations

import math

import pytest
import torch

import torchpvs as tp

NAN = float("nan")
SCENE = tp.load_scene("renda2021_fig3")
OPTS = tp.SolverOptions(order=4, n_magnus=16, tol=1e-12)
# (D1, D2, alpha1, alpha2): outer curve partly in the guide / straight parts crossing the
# orifice; all away from the kinks D_j = Ls_j where tau_D jumps.
X_STAR = torch.tensor([[0.10, 0.18, 0.2, 1.0],
                       [0.08, 0.17, 0.0, 0.6],
                       [0.095, 0.20, -0.3, 2.0]], dtype=torch.float64)


def _position(x):
    return tp.solve(SCENE, insertion=x[:, :2], rotation=x[:, 2:], options=OPTS)


def test_round_trip_insertion_force_and_torque_of_inner_tube():
    """Reference: position solves at x*; the inner tube's (tau_D2, tau_alpha2) commanded from a
    perturbed start (+4 mm, -0.2 rad) must give back x* (positions of tube 1 held)."""
    eq = _position(X_STAR)
    B = X_STAR.shape[0]
    forces = torch.stack([torch.full((B,), NAN, dtype=torch.float64),
                          eq.actuation_forces[:, 1]], -1)
    torques = torch.stack([torch.full((B,), NAN, dtype=torch.float64),
                           eq.actuation_torques[:, 1]], -1)
    x0 = X_STAR + torch.tensor([0.0, 0.004, 0.0, -0.2], dtype=torch.float64)
    res = tp.solve_force_controlled(SCENE, forces=forces, torques=torques, insertion=x0[:, :2],
                                    rotation=x0[:, 2:], options=OPTS, on_failure="raise")
    assert res.converged.all(), res.reason
    assert (res.insertion - X_STAR[:, :2]).abs().max() < 1e-8          # m
    assert (res.rotation - X_STAR[:, 2:]).abs().max() < 1e-8           # rad
    assert (res.equilibrium.tip_position - eq.tip_position).abs().max() < 1e-8
    assert res.residual[:, 1].abs().max() <= 1e-8 and res.residual[:, 3].abs().max() <= 1e-10
    assert (res.residual[:, [0, 2]] == 0).all()
    # stability under force control = shape stable and the free 2x2 stiffness block PD
    K = res.actuator_stiffness[:, [1, 3]][:, :, [1, 3]]
    ell = max(t.length for t in SCENE.tubes)
    S = torch.tensor([ell, 1.0], dtype=torch.float64)
    Ks = S[:, None] * K * S
    lam = torch.linalg.eigvalsh(0.5 * (Ks + Ks.transpose(1, 2)))[:, 0]
    assert torch.allclose(res.stiffness_margin, lam, rtol=1e-9, atol=1e-14)
    assert (res.stable == (res.equilibrium.stable & (lam > 0))).all()


def test_all_torques_commanded_common_rotation_is_least_norm():
    """Every rotation torque-controlled, no load: the common rotation is a zero mode. The
    relative rotation is recovered and the mean rotation keeps its initial value."""
    eq = _position(X_STAR)
    shift = torch.tensor([0.1, -0.2], dtype=torch.float64)
    res = tp.solve_force_controlled(SCENE, torques=eq.actuation_torques, insertion=X_STAR[:, :2],
                                    rotation=X_STAR[:, 2:] + shift, options=OPTS,
                                    on_failure="raise")
    assert res.converged.all(), res.reason
    rel = res.rotation[:, 1] - res.rotation[:, 0]
    assert (rel - (X_STAR[:, 3] - X_STAR[:, 2])).abs().max() < 1e-8
    assert (res.rotation.mean(-1) - (X_STAR[:, 2:] + shift).mean(-1)).abs().max() < 1e-12
    assert (res.zero_modes == 1).all()
    # the shape does not depend on the common rotation: tips agree up to a rotation about z
    r_ref = eq.tip_position[:, :2].norm(dim=-1)
    assert (res.equilibrium.tip_position[:, :2].norm(dim=-1) - r_ref).abs().max() < 1e-8
    # torques that do not sum to zero have no equilibrium: immediate, explained failure
    bad = tp.solve_force_controlled(SCENE, torques=[0.01, 0.02], insertion=X_STAR[0, :2],
                                    rotation=X_STAR[0, 2:], options=OPTS, on_failure="ignore")
    assert not bool(bad.converged[0]) and "sum to zero" in bad.reason[0]


def test_torque_controlled_inner_rotation_matches_position_solve():
    """Fig. 3 robot (full overlap), alpha_2 torque-controlled from 0. Reference: position solves
    following alpha_2 from 0 on a grid, then bisection on tau_alpha2(alpha_2) = command."""
    cmd = 0.1   # N·m, about alpha_2 = 166 deg on the branch from 0 (max 0.145 near 265 deg)
    grid = torch.linspace(0.0, 3.5, 15, dtype=torch.float64)
    prev, lo, hi = None, None, None
    for a in grid:
        e = tp.solve(SCENE, rotation=torch.stack([torch.zeros(()), a]), options=OPTS,
                     initial=prev)
        t = float(e.actuation_torques[0, 1])
        if t >= cmd:
            hi = (float(a), e)
            break
        lo, prev = (float(a), e), e
    assert lo is not None and hi is not None
    (a0, e0), (a1, _) = lo, hi
    for _ in range(45):
        am = 0.5 * (a0 + a1)
        em = tp.solve(SCENE, rotation=[0.0, am], options=OPTS, initial=e0)
        if float(em.actuation_torques[0, 1]) < cmd:
            a0, e0 = am, em
        else:
            a1 = am
    ref = tp.solve(SCENE, rotation=[0.0, 0.5 * (a0 + a1)], options=OPTS, initial=e0)
    res = tp.solve_force_controlled(SCENE, torques=[NAN, cmd], rotation=[0.0, 0.0],
                                    options=OPTS, on_failure="raise")
    assert res.converged.all()
    assert abs(float(res.rotation[0, 1]) - 0.5 * (a0 + a1)) < 1e-8
    assert (res.equilibrium.tip_position - ref.tip_position).abs().max() < 1e-9
    assert res.insertion.tolist() == [list(SCENE.actuation.insertion)]
    assert bool(res.stable[0]) and float(res.stiffness_margin[0]) > 0   # rising tau: stable


def test_torque_beyond_elastic_range_fails_with_reason():
    """Reference: tau_alpha2 over a full turn of position solves stays below 0.2 N·m; commanding
    1 N·m has no equilibrium."""
    prev, tmax = None, 0.0
    for a in torch.linspace(0.0, 2 * math.pi, 25, dtype=torch.float64):
        prev = tp.solve(SCENE, rotation=torch.stack([torch.zeros(()), a]), options=OPTS,
                        initial=prev)
        tmax = max(tmax, abs(float(prev.actuation_torques[0, 1])))
    assert tmax < 0.2
    res = tp.solve_force_controlled(SCENE, torques=[NAN, 1.0], options=OPTS,
                                    on_failure="ignore")
    assert not bool(res.converged[0])
    assert "torques[1]" in res.reason[0] and "beyond the largest elastic" in res.reason[0]
    assert abs(float(res.torques[0, 1])) <= tmax + 1e-6 and torch.isfinite(res.rotation).all()
    with pytest.raises(tp.SolverError, match="found no equilibrium"):
        tp.solve_force_controlled(SCENE, torques=[NAN, 1.0], options=OPTS, on_failure="raise",
                                  max_iter=20)


F32 = tp.SolverOptions(dtype=torch.float32)


def test_float32_torque_control_converges_at_the_dtype_floor():
    """Regression: in float32, torques=[nan, 0.01] reached 0.00999997 N·m (residual
    3.4e-8 N·m, float32's rounding of tau) but reported converged=False, "beyond the largest
    elastic resistance", against the float64 default torque_tol = 1e-10. The thresholds now
    follow the dtype. Reference: the float64 solve of the same command (its alpha_2)."""
    ref = tp.solve_force_controlled(SCENE, torques=[NAN, 0.01], options=OPTS,
                                    on_failure="raise")
    res = tp.solve_force_controlled(SCENE, torques=[NAN, 0.01], options=F32, on_failure="raise")
    assert bool(res.converged[0]) and res.reason == ("converged",)
    tol = float(res.tolerance[0, 3])
    eps = torch.finfo(torch.float32).eps
    assert 1e-10 < tol < 1e3 * eps * 0.01 + 1e-5          # the floor, not a free pass
    assert abs(float(res.residual[0, 3])) <= tol
    assert abs(float(res.rotation[0, 1]) - float(ref.rotation[0, 1])) < 1e-4      # rad
    # float64 keeps the requested thresholds (its floor is ~1e-15 N·m)
    assert float(ref.tolerance[0, 3]) == 1e-10 and float(ref.tolerance[0, 1]) == 1e-8


def test_a_stall_at_the_rounding_level_is_not_called_unreachable(monkeypatch):
    """The reason must be the true one: with the dtype floors removed, float32 stalls a few
    1e-8 N·m from the command at a regular stiffness, which is rounding, not a command beyond
    the elastic range (that case keeps its reason: test_torque_beyond_elastic_range_...)."""
    monkeypatch.setattr(tp.force_control, "TORQUE_FLOOR", 0.0)
    res = tp.solve_force_controlled(SCENE, torques=[NAN, 0.01], options=F32,
                                    on_failure="ignore")
    assert not bool(res.converged[0])
    assert "rounding level of torch.float32" in res.reason[0]
    assert "beyond the largest elastic" not in res.reason[0]
