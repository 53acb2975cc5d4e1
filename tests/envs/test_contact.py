"""Two-sided carriage contact: carriages in contact at the nesting and
tip-order stops move together under the net force and report the contact force."""

from __future__ import annotations

import numpy as np
import pytest

from envs import CarriageModel, CTRReachEnv, RobotBatch, fig3_two_tube, rvim_three_tube
from envs.dynamics import project_in_metric


def _at(robot, kind, x):
    rb = RobotBatch(robot, CarriageModel(kind=kind), 1)
    rb.set_state(np.array([0]), np.array([x], dtype=np.float64))
    return rb


def _reduced_step(rb, f, T, h):
    """Hand computation of one linearly implicit substep with the carriages in contact
    moving as one body: coordinates ``x = x0 + T y`` (``T`` ties the carriages in contact),
    so the summed forces ``T^T f`` act on the summed damping/mass ``T^T A T``. Returns
    ``(dx, contact force vector f_c = A dx / h_f - f)`` for rest initial velocities."""
    A = np.diag(rb.damping) + h * rb.K[0]
    per = h
    if rb.model.kind == "second_order":
        A = np.diag(rb.mass + h * rb.damping) + h * h * rb.K[0]
        per = h * h
    y = np.linalg.solve(T.T @ A @ T, T.T @ (per * f))
    dx = T @ y
    return dx, A @ dx / per - f


@pytest.mark.parametrize("kind", ["overdamped", "second_order"])
@pytest.mark.parametrize("f_outer,f_inner,stop", [
    (0.98, -2.255, "nesting"),    # the reported pair at half force: inner wins, pair inserts
    (-0.98, 2.255, "tip"),        # tips flush, inner pulls back harder: pair retracts
    (1.5, -0.5, "nesting"),       # outer pulls back harder: it pushes the inner back
])
def test_pair_in_contact_moves_under_the_net_force(kind, f_outer, f_inner, stop):
    robot = fig3_two_tube()
    dL = robot.lengths[1] - robot.lengths[0]
    D1 = 0.08
    rb = _at(robot, kind, [D1, D1 + (0.0 if stop == "nesting" else dL), 0.3, -0.2])
    f = np.array([f_outer, f_inner, 0.0, 0.0])
    x0 = rb.x[0].copy()
    flags = rb.step_force(rb.g + f)
    assert flags.substeps[0] == 1           # one substep: the hand computation applies
    T = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    dx, fc = _reduced_step(rb, f, T, rb.model.control_period)
    np.testing.assert_allclose(rb.x[0] - x0, dx, rtol=1e-9, atol=1e-15)
    # summed force over summed damping (K vanishes here; a check of the hand computation)
    if kind == "overdamped":
        b = rb.damping
        assert dx[0] / 0.1 == pytest.approx((f_outer + f_inner) / (b[0] + b[1]), rel=1e-6)
    # Newton's third law: the contact force acts equal and opposite on the two carriages
    assert fc[0] == pytest.approx(-fc[1], rel=1e-9)
    np.testing.assert_allclose(flags.contact_force[0], [fc[1]], rtol=1e-9)
    assert (fc[1] > 0) == (stop == "nesting")   # sign: along +D of the inner carriage
    np.testing.assert_array_equal(flags.stop_force, 0.0)


def test_pair_separates_when_the_contact_would_pull():
    """Inner pulling back, outer pushing in at the nesting stop: they part, each moving as if
    alone (the unconstrained implicit step), with no contact force."""
    robot = fig3_two_tube()
    rb = _at(robot, "overdamped", [0.08, 0.08, 0.3, -0.2])
    f = np.array([-0.5, 1.0, 0.0, 0.0])
    x0 = rb.x[0].copy()
    flags = rb.step_force(rb.g + f)
    dx, fc = _reduced_step(rb, f, np.eye(4), 0.1)
    np.testing.assert_allclose(rb.x[0] - x0, dx, rtol=1e-9, atol=1e-15)
    assert rb.x[0, 1] > rb.x[0, 0]
    np.testing.assert_array_equal(flags.contact_force, 0.0)


def test_three_carriages_in_a_chain_share_the_net_force():
    """All three bases together (D1 = D2 = D3), forces (+1, -0.5, -0.8) N: the net -0.3 N
    inserts all three at -0.3 N over the summed damping; contact forces by hand from each
    carriage's balance, b_j v = f_j + (force from j-1) - (force on j+1)."""
    robot = rvim_three_tube()
    rb = _at(robot, "overdamped", [0.1, 0.1, 0.1, 0.3, -0.2, 0.5])
    f = np.array([1.0, -0.5, -0.8, 0.0, 0.0, 0.0])
    flags = rb.step_force(rb.g + f)
    assert flags.substeps[0] == 1
    b = rb.damping[:3]
    v = f[:3].sum() / b.sum()
    np.testing.assert_allclose(rb.x[0, :3] - 0.1, 0.1 * v, rtol=1e-6)
    c12 = f[0] - b[0] * v            # outer: b1 v = f1 - c12 (it pushes the middle with c12)
    c23 = b[2] * v - f[2]            # inner: b3 v = f3 + c23
    np.testing.assert_allclose(flags.contact_force[0], [c12, c23], rtol=1e-6)
    assert c12 > 0 and c23 > 0


def test_the_issue_scenario_now_advances():
    """Regression: at the nesting stop, outer pulling back at 1.96 N and inner pushing in at
    4.51 N (net of the elastic load) retracted the pair 10 mm in 1 s (the outer carriage won).
    Now the pair inserts at the net 2.55 N over the summed damping: 6.05 mm in 1 s."""
    robot = fig3_two_tube()
    for kind in ("overdamped", "second_order"):
        rb = _at(robot, kind, [0.08, 0.08, 0.3, -0.2])
        for _ in range(10):
            flags = rb.step_force(rb.g + np.array([1.96, -4.51, 0.0, 0.0]))
            assert rb.x[0, 1] == rb.x[0, 0]                 # still in contact
        b = rb.damping
        expected = 1.0 * (1.96 - 4.51) / (b[0] + b[1])     # -6.05 mm
        assert rb.x[0, 0] - 0.08 == pytest.approx(expected, rel=0.02)
        assert flags.contact_force[0, 0] == pytest.approx(4.51 + b[1] * expected, rel=0.02)


def test_stroke_end_reports_the_force_it_holds():
    """Outer carriage pushed in against D1 = 0 with 1 N beyond its elastic load: it stays on
    the stop, which pushes back with the 1 N (stop_force > 0 at a lower end)."""
    robot = fig3_two_tube()
    rb = _at(robot, "overdamped", [0.0, 0.1, 0.3, -0.2])
    for _ in range(3):
        flags = rb.step_force(rb.g + np.array([-1.0, 0.0, 0.0, 0.0]))
    assert rb.x[0, 0] == 0.0 and rb.at_lower[0, 0]
    assert flags.stop_force[0, 0] == pytest.approx(1.0, rel=1e-3)
    np.testing.assert_array_equal(flags.stop_force[0, 1], 0.0)


@pytest.mark.parametrize("make", [fig3_two_tube, rvim_three_tube])
def test_contact_solve_satisfies_the_kkt_conditions(make):
    """project_in_metric on random metrics and points (many at corners): feasible, multipliers
    >= 0, stationarity A (x - xu) = -G^T lam, complementarity — a certificate that x is THE
    minimizer of the convex QP (independent of how it was found)."""
    robot = make()
    N = robot.n_tubes
    G, c = robot.constraints()
    G = np.concatenate([G, np.zeros_like(G)], -1)
    rng = np.random.default_rng(0)
    for i in range(300):
        M = rng.normal(size=(2 * N, 2 * N))
        S = np.diag(np.exp(rng.normal(size=2 * N)))
        A = S @ (M @ M.T + 0.1 * np.eye(2 * N)) @ S
        xu = np.concatenate([rng.uniform(-0.1, 0.4, N), rng.normal(size=N)])
        if i % 2:   # near the corners, where several stops act at once
            xu[:N] = rng.choice([0.0, 0.1, 0.18], N) + 1e-3 * rng.normal(size=N)
        x, lam, ok = project_in_metric(xu, A, G, c)
        scale = np.abs(A).max()
        assert ok
        assert (G @ x - c).max() <= 1e-10
        assert lam.min() >= 0.0
        np.testing.assert_allclose(A @ (x - xu), -G.T @ lam, atol=1e-9 * scale)
        assert np.abs(lam * (G @ x - c)).max() <= 1e-9 * scale


def test_env_info_reports_contact_forces():
    env = CTRReachEnv(robot="rvim_three_tube")
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(6, np.float32))
    assert info["contact_force"].shape == (2,) and info["stop_force"].shape == (3,)
    joint = CTRReachEnv(control="joint")
    joint.reset(seed=0)
    _, _, _, _, info = joint.step(np.zeros(4, np.float32))
    np.testing.assert_array_equal(info["contact_force"], [0.0])
