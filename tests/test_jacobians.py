"""Control Jacobians against central finite differences of full solves (actuator stiffness,
tip Jacobian, force-control Jacobian, tip compliance). All perturbations of one check are solved
as one batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchpvs as tp

SCENE = tp.load_scene("renda2021_fig3")
# no wall-clock bound: a loaded test machine must not cut a finite-difference solve short
OPTS = tp.SolverOptions(order=4, tol=1e-12, time_limit=None)
X0 = torch.tensor([0.09, 0.2085, 0.1, 1.2], dtype=torch.float64)   # away from the D1 kink


def _solve(x, F, M, initial=None):
    x = torch.atleast_2d(x)
    return tp.solve(SCENE, insertion=x[:, :2], rotation=x[:, 2:], tip_force=F, tip_moment=M,
                    options=OPTS, initial=initial)


def _central(values: torch.Tensor, h: float) -> torch.Tensor:
    """``values (2k, m)`` ordered +e_0, -e_0, +e_1, ... -> ``(m, k)`` central differences."""
    return ((values[0::2] - values[1::2]) / (2 * h)).T


@pytest.mark.parametrize("load", ["none", "force", "force_and_moment"])
def test_jacobians_match_finite_differences(load):
    """Central differences of solves (forces, tips) in x and in the load. "force": a dead tip
    force alone, the closed-form Schur complement with the work's second derivatives through
    the tip pose; "force_and_moment": the implicit-backward path."""
    F = torch.tensor([0.02, 0.0, -0.01] if load != "none" else [0.0] * 3, dtype=torch.float64)
    M = torch.tensor([0.0, 1e-3, 0.0] if load == "force_and_moment" else [0.0] * 3,
                     dtype=torch.float64)
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
    elif load == "force":
        assert torch.allclose(K, K.T, rtol=1e-9, atol=1e-12)   # a dead force is conservative
    else:
        assert not torch.allclose(K, K.T, atol=1e-6)  # a dead moment is non-conservative


@pytest.mark.parametrize("x", [
    # the scene's own state: the outer tube's straight-to-curved transition at the orifice
    [0.0935, 0.2085, 0.0, 1.3962634015954636],
    # the inner tube's transition at the orifice, with the outer one away from its own
    [0.09, 0.2185, 0.3, 1.0],
    # the outer tube's base at the orifice (it cannot insert further)
    [0.0, 0.2085, 0.1, 1.2],
    # the scene's state under a dead tip force and moment (the implicit-backward path)
    [0.0935, 0.2085, 0.0, 1.3962634015954636, "loaded"],
])
def test_jacobians_at_a_kink_are_the_retraction_sides(x):
    """Where an insertion sits at a kink of U*(D_j), the derivatives in D_j are one-sided: the
    control Jacobians report the retraction side (increasing D_j), the side of
    ``actuation_forces``. Reference: second-order one-sided finite differences on that side
    (solves at D_j + h and D_j + 2h); the layout's own derivative at the tie matched neither
    side (4e-2 and 5.7e-1 off a column of ~0.57 at the scene's state)."""
    from torchpvs.jacobians import actuator_stiffness, tip_jacobian

    loaded = x[-1] == "loaded"
    x = torch.tensor(x[:4], dtype=torch.float64)
    F = torch.tensor([0.02, 0.0, -0.01] if loaded else [0.0] * 3, dtype=torch.float64)
    M = torch.tensor([0.0, 1e-3, 0.0] if loaded else [0.0] * 3, dtype=torch.float64)
    opts = tp.SolverOptions(accuracy=1e-9, time_limit=None)
    eq = tp.solve(SCENE, insertion=x[:2], rotation=x[2:], tip_force=F, tip_moment=M,
                  options=opts)
    j = int(eq.force_kink[0].nonzero()[0, 0])
    assert bool(eq.force_kink[0, j])
    h = 1e-6
    Dn = x[:2].repeat(2, 1)
    Dn[0, j] += h
    Dn[1, j] += 2 * h
    ex = tp.solve(SCENE, insertion=Dn, rotation=x[2:].expand(2, 2), tip_force=F, tip_moment=M,
                  options=opts)
    tip_fd = (-3 * eq.tip_position[0] + 4 * ex.tip_position[0] - ex.tip_position[1]) / (2 * h)
    # the force at the kink is itself a one-sided estimate (O(1e-7 m) away): the stiffness
    # column from the two solves on the smooth side (first order, O(h))
    tau = torch.cat([ex.actuation_forces, ex.actuation_torques], -1)
    K_fd = (tau[1] - tau[0]) / h
    step = eq.jacobians(compliance=False)
    col = step.tip_jacobian[0, :3, j]
    assert (col - tip_fd).abs().max() <= 1e-4 * tip_fd.abs().max()
    K = step.actuator_stiffness[0, :, j]
    assert (K - K_fd).abs().max() <= 1e-3 * K_fd.abs().max()
    # the functions alone take the same side
    np.testing.assert_allclose(tip_jacobian(eq)[0, :3, j].numpy(), col.numpy(), rtol=1e-10)
    np.testing.assert_allclose(actuator_stiffness(eq)[0, :, j].numpy(), K.numpy(), rtol=1e-10,
                               atol=1e-12 * float(K.abs().max()))
    # and the other side is really different here (the test would see the tie rule's mix);
    # a base at the orifice has no insertion side
    if float(x[j]) < h:
        return
    other = x[:2].clone()
    other[j] -= h
    ins = tp.solve(SCENE, insertion=other, rotation=x[2:], tip_force=F, tip_moment=M,
                   options=opts)
    ins_fd = (eq.tip_position[0] - ins.tip_position[0]) / h
    assert (ins_fd - tip_fd).abs().max() >= 0.1 * tip_fd.abs().max()


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


def _autograd_jacobians(scene, x, F, M, dtype=torch.float64):
    """Reference: ``(K, J_tip_position)`` by reverse passes through the solver's implicit
    backward (autograd of the forces and tip position w.r.t. the actuation inputs), one row at
    a time — the path the closed forms replaced."""
    N = scene.n_tubes
    X = x.to(dtype).clone().requires_grad_(True)
    eq = tp.solve(scene, insertion=X[:, :N], rotation=X[:, N:], tip_force=F, tip_moment=M,
                  options=tp.SolverOptions(dtype=dtype))
    tau = torch.cat([eq.actuation_forces, eq.actuation_torques], -1)
    out = torch.cat([tau, eq.tip_position], -1)
    rows = [torch.autograd.grad(out[:, i].sum(), X, retain_graph=True)[0]
            for i in range(out.shape[-1])]
    G = torch.stack(rows, 1)
    return G[:, :2 * N], G[:, 2 * N:]


@pytest.mark.parametrize("case", ["unloaded", "force", "force_and_moment", "base_at_orifice",
                                  "three_tubes"])
def test_closed_form_control_step_equals_the_implicit_backward(case):
    """``tip_jacobian`` (``P_x - P_q H^-1 U_qx``) and ``actuator_stiffness`` from the solve's own
    factorization equal autograd through the implicit backward, row by row, on a batch."""
    from envs.robots import rvim_three_tube
    from torchpvs.jacobians import actuator_stiffness, tip_jacobian

    scene = rvim_three_tube().scene if case == "three_tubes" else SCENE
    N = scene.n_tubes
    # (the Fig. 3 scene's own insertion sits on a kink: one-sided forces; X0 is away from it)
    base = (torch.tensor([*scene.actuation.insertion, *scene.actuation.rotation],
                         dtype=torch.float64) if case == "three_tubes" else X0)
    x = base.repeat(3, 1)
    x[:, N:] += torch.tensor([0.0, 0.4, -0.9])[:, None] * torch.arange(1, N + 1)
    if case == "base_at_orifice":
        x[0, 0] = 0.0
    F = torch.tensor([0.05, -0.02, 0.0] if "force" in case else [0.0] * 3, dtype=torch.float64)
    M = torch.tensor([0.0, 2e-3, 1e-3] if "moment" in case else [0.0] * 3, dtype=torch.float64)
    K_ref, J_ref = _autograd_jacobians(scene, x, F, M)
    eq = tp.solve(scene, insertion=x[:, :N], rotation=x[:, N:], tip_force=F, tip_moment=M)
    J = tip_jacobian(eq)
    K = actuator_stiffness(eq)
    assert J.shape == (3, 6, 2 * N) and K.shape == (3, 2 * N, 2 * N)
    # A base at the orifice is a kink of U* in D_1: that row comes from the retraction side,
    # 1e-7 m away (test_jacobians_at_a_kink_are_the_retraction_sides): its D_1 column is not
    # the implicit backward's (torch's rule for the tie), its other entries are to O(1e-7 m).
    rows = slice(1, None) if case == "base_at_orifice" else slice(None)
    np.testing.assert_allclose(J[rows, :3].numpy(), J_ref[rows].numpy(), rtol=1e-8,
                               atol=1e-10 * float(J_ref.abs().max()))
    if case == "base_at_orifice":
        np.testing.assert_allclose(J[0, :3, 1:].numpy(), J_ref[0, :, 1:].numpy(), rtol=0,
                                   atol=1e-4 * float(J_ref.abs().max()))
    # The Schur path symmetrizes (a conservative load).
    if case != "force_and_moment":
        np.testing.assert_allclose(K[rows].numpy(), K_ref[rows].numpy(), rtol=1e-7,
                                   atol=1e-9 * float(K_ref.abs().max()))
    step = eq.jacobians(compliance=False)
    assert step.tip_compliance is None
    # the control step takes K and the tip partials from one reverse pass (the functions alone
    # from one each): the same numbers up to the order of the sums
    np.testing.assert_allclose(step.tip_jacobian.numpy(), J.numpy(), rtol=0, atol=0)
    np.testing.assert_allclose(step.actuator_stiffness.numpy(), K.numpy(), rtol=1e-12,
                               atol=1e-14 * float(K.abs().max()))


def test_tip_jacobian_rotation_rows_match_finite_differences():
    """The rotation rows of the tip Jacobian: the spatial angular velocity of the tip frame,
    ``vee(dR R^T)`` by central differences of full solves."""
    from torchpvs.jacobians import tip_jacobian

    eq = _solve(X0, None, None)
    J = tip_jacobian(eq)[0, 3:]
    h = 1e-6
    steps = torch.zeros(8, 4, dtype=torch.float64)
    for i in range(4):
        steps[2 * i, i], steps[2 * i + 1, i] = h, -h
    ex = _solve(X0 + steps, None, None)
    R = eq.tip_rotation[0]
    dR = (ex.tip_rotation[0::2] - ex.tip_rotation[1::2]) / (2 * h)          # (4, 3, 3)
    W = dR @ R.T
    omega = torch.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], 0)            # (3, 4)
    assert (J - omega).abs().max() <= 1e-6 * omega.abs().max()


def test_tip_jacobian_in_float32_agrees_with_float64():
    from torchpvs.jacobians import tip_jacobian

    x = X0[None]
    J64 = tip_jacobian(tp.solve(SCENE, insertion=x[:, :2], rotation=x[:, 2:]))
    J32 = tip_jacobian(tp.solve(SCENE, insertion=x[:, :2].float(), rotation=x[:, 2:].float(),
                                options=tp.SolverOptions(dtype=torch.float32)))
    assert J32.dtype == torch.float32 and bool(torch.isfinite(J32).all())
    assert (J32.double() - J64).abs().max() <= 1e-3 * J64.abs().max()
