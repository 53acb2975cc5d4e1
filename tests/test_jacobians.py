"""Control Jacobians against central finite differences of full solves (actuator stiffness,
tip Jacobian, force-control Jacobian, tip compliance). All perturbations of one check are solved
as one batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchpvs as tp

SCENE = tp.load_scene("renda2021_fig3")
OPTS = tp.SolverOptions(order=4, tol=1e-12)
X0 = torch.tensor([0.09, 0.2085, 0.1, 1.2], dtype=torch.float64)   # away from the D1 kink


def _solve(x, F, M, initial=None):
    x = torch.atleast_2d(x)
    return tp.solve(SCENE, insertion=x[:, :2], rotation=x[:, 2:], tip_force=F, tip_moment=M,
                    options=OPTS, initial=initial)


def _central(values: torch.Tensor, h: float) -> torch.Tensor:
    """``values (2k, m)`` ordered +e_0, -e_0, +e_1, ... -> ``(m, k)`` central differences."""
    return ((values[0::2] - values[1::2]) / (2 * h)).T


@pytest.mark.parametrize("load", ["none", "force_and_moment"])
def test_jacobians_match_finite_differences(load):
    F = torch.tensor([0.02, 0.0, -0.01] if load != "none" else [0.0] * 3, dtype=torch.float64)
    M = torch.tensor([0.0, 1e-3, 0.0] if load != "none" else [0.0] * 3, dtype=torch.float64)
    eq = _solve(X0, F, M)
    J = eq.jacobians()
    h = 1e-6
    steps = torch.zeros(8, 4, dtype=torch.float64)
    for i in range(4):
        steps[2 * i, i], steps[2 * i + 1, i] = h, -h
    ex = _solve(X0 + steps, F, M)
    tau = torch.cat([ex.actuation_forces, ex.actuation_torques], -1)
    K_fd, P_fd = _central(tau, h), _central(ex.tip_position, h)
    K = J.actuator_stiffness[0]
    assert (K - K_fd).abs().max() <= 1e-6 * K_fd.abs().max()
    assert (J.tip_jacobian[0, :3] - P_fd).abs().max() <= 1e-6 * P_fd.abs().max()
    dw = torch.zeros(12, 6, dtype=torch.float64)
    for i in range(6):
        dw[2 * i, i], dw[2 * i + 1, i] = 1e-5, -1e-5
    ew = _solve(X0.expand(12, 4), F + dw[:, :3], M + dw[:, 3:])
    C_fd = _central(ew.tip_position, 1e-5)
    assert (J.tip_compliance[0, :3] - C_fd).abs().max() <= 1e-6 * C_fd.abs().max()
    if load == "none":
        # Rotating all tubes together costs nothing; at X0 only straight material crosses the
        # orifice (D1 < Ls1), so translating both tubes together costs nothing either.
        for null in ([0.0, 0.0, 1.0, 1.0], [1.0, 1.0, 0.0, 0.0]):
            v = torch.tensor(null, dtype=torch.float64)
            assert (K @ v).abs().max() <= 1e-9 * K.abs().max()
        assert int(J.force_rank[0]) <= 2
        assert torch.allclose(K, K.T)
    else:
        assert not torch.allclose(K, K.T, atol=1e-6)  # a dead moment is non-conservative


def test_force_jacobian_predicts_tip_motion_under_force_control():
    """A small actuator-force change dtau = K dx (dx in the range of K, i.e. orthogonal to the
    free modes) moves the tip by J_tau dtau, to first order."""
    eq = _solve(X0, None, None)
    J = eq.jacobians()
    K = J.actuator_stiffness[0]
    dx = K[:, 0] / K[:, 0].norm() * 1e-5
    dtau = K @ dx
    moved = _solve(X0 + dx, None, None)
    pred = J.force_jacobian[0, :3] @ dtau
    actual = moved.tip_position[0] - eq.tip_position[0]
    assert (pred - actual).norm() <= 2e-2 * actual.norm()


def test_actuator_stiffness_fast_path_matches_control_jacobians():
    """``actuator_stiffness`` (no re-solve for load coordinates) equals the Schur complement
    from ``control_jacobians`` and central differences of the actuation forces."""
    from torchpvs.jacobians import actuator_stiffness

    sc = tp.load_scene("renda2021_fig3")
    D = torch.tensor([[0.06, 0.15], [0.02, 0.2]], dtype=torch.float64)
    A = torch.tensor([[0.0, 1.0], [0.3, -2.0]], dtype=torch.float64)
    eq = tp.solve(sc, insertion=D, rotation=A)
    K = actuator_stiffness(eq)
    np.testing.assert_allclose(K.numpy(), eq.jacobians().actuator_stiffness.numpy(),
                               rtol=1e-7, atol=1e-9)
    e = 1e-6
    x = torch.cat([D, A], -1)
    for c in range(4):
        dx = torch.zeros_like(x)
        dx[:, c] = e
        gp = tp.solve(sc, insertion=(x + dx)[:, :2], rotation=(x + dx)[:, 2:], initial=eq)
        gm = tp.solve(sc, insertion=(x - dx)[:, :2], rotation=(x - dx)[:, 2:], initial=eq)
        fd = (torch.cat([gp.actuation_forces, gp.actuation_torques], -1)
              - torch.cat([gm.actuation_forces, gm.actuation_torques], -1)) / (2 * e)
        np.testing.assert_allclose(K[:, :, c].numpy(), fd.numpy(), rtol=1e-4,
                                   atol=1e-6 * float(K.abs().max()))


def test_actuator_stiffness_of_selected_rows_equals_the_full_batch_rows():
    """``actuator_stiffness(eq, rows)``: the same values as the full batch's rows, whether the
    adjoint factorization is already cached (after a full call) or not (rows factored alone)."""
    from torchpvs.jacobians import actuator_stiffness

    sc = tp.load_scene("renda2021_fig3")
    A = torch.zeros(6, 2, dtype=torch.float64)
    A[:, 1] = torch.linspace(0.0, 4.0, 6)
    rows = torch.tensor([4, 0, 3])
    fresh = actuator_stiffness(tp.solve(sc, rotation=A), rows)
    eq = tp.solve(sc, rotation=A)
    K = actuator_stiffness(eq)
    np.testing.assert_allclose(fresh.numpy(), K[rows].numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(actuator_stiffness(eq, rows).numpy(), K[rows].numpy(),
                               rtol=1e-12, atol=1e-12)
    assert actuator_stiffness(eq, torch.tensor([], dtype=torch.long)).shape == (0, 4, 4)


def test_actuator_stiffness_with_a_base_at_the_orifice_uses_the_general_rows():
    """With D_1 = 0 (no guide twist coordinate for tube 1) the rotation rows cannot be read off
    the Hessian: the general double-backward path gives the same stiffness as
    control_jacobians; with every D_j > 0 both paths are exercised on one batch row each."""
    from torchpvs.jacobians import actuator_stiffness

    sc = tp.load_scene("renda2021_fig3")
    for D in ([[0.0, 0.15]], [[0.05, 0.15]]):
        eq = tp.solve(sc, insertion=torch.tensor(D, dtype=torch.float64),
                      rotation=torch.tensor([[0.2, 1.1]], dtype=torch.float64))
        np.testing.assert_allclose(actuator_stiffness(eq).numpy(),
                                   eq.jacobians().actuator_stiffness.numpy(),
                                   rtol=1e-7, atol=1e-9)


def test_actuator_stiffness_of_a_batch_of_different_robots():
    """A batch whose elements have their own tube properties (solve_tensors with (B, N) tube
    tensors, as the environments' perturbed plants) gives each element the stiffness of its
    own robot solved alone, also for a subset of rows."""
    from torchpvs.jacobians import actuator_stiffness
    from torchpvs.plan import tube_tensors
    from torchpvs.sections import TubeTensors
    from torchpvs.solver import solve_tensors
    from torchpvs.testing import scaled_tubes

    scene = tp.load_scene("renda2021_fig3")
    f = torch.tensor([[[1.05, 0.95], [0.9, 1.1], [1.0, 1.08]],
                      [[0.93, 1.02], [1.1, 0.97], [0.95, 1.0]]], dtype=torch.float64)
    D = torch.tensor([[0.05, 0.12], [0.03, 0.15]], dtype=torch.float64)
    A = torch.tensor([[0.3, 1.2], [-0.5, 0.4]], dtype=torch.float64)
    F = torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.0, 0.0]], dtype=torch.float64)
    b = tube_tensors(scene, torch.float64, torch.device("cpu"))
    tubes = TubeTensors(EI=b.EI * f[:, 1], GJ=b.GJ * f[:, 2], length=b.length.expand(2, -1),
                        straight=b.straight.expand(2, -1), coef=b.coef * f[:, 0, :, None, None])
    opts = tp.SolverOptions(order=2, n_magnus=8)
    eq = solve_tensors(scene, tubes, D, A, F, torch.zeros_like(F), opts, None, None)
    K = actuator_stiffness(eq)
    np.testing.assert_allclose(actuator_stiffness(eq, [1])[0].numpy(), K[1].numpy(), atol=1e-12)
    for i in range(2):
        own = scaled_tubes(scene, *f[i].numpy())
        e = tp.solve(own, insertion=D[i], rotation=A[i], tip_force=F[i], options=opts)
        np.testing.assert_allclose(e.tip_position[0].numpy(), eq.tip_position[i].numpy(),
                                   atol=1e-15)
        np.testing.assert_allclose(actuator_stiffness(e)[0].numpy(), K[i].numpy(),
                                   rtol=1e-10, atol=1e-12 * float(K[i].abs().max()))
