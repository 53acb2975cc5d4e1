"""torchpvs.Tracker: the fused warm step against the solver it shortcuts.

Reference: ``torchpvs.solve`` chained warm along the same actuation path at the tracker's fixed
discretization (``SolverOptions(order=k, n_magnus=m, compute_forces=False)``), which runs the
same layout, rotation predictor, Newton iteration and tip pose through the driver, one stage at
a time. The tracker must reproduce it step for step: tips and coordinates within 1e-12,
identical iterations, convergence and stability verdicts.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs import compiled

pytestmark = [pytest.mark.usefixtures("one_thread_module"),
              pytest.mark.skipif(not compiled.available(), reason="numba not importable")]


def _follow(scene, path, tracker):
    """Step ``tracker`` and a chained warm ``torchpvs.solve`` along ``path`` (a list of
    ``(insertion (B, N), rotation (B, N))``); return the largest tip and q differences and
    assert identical iterations and verdicts at every step."""
    eq = tp.solve(scene, insertion=path[0][0], rotation=path[0][1], options=tracker.options)
    tracker.restore(tracker.snapshot())    # (a no-op restore is allowed)
    worst_tip = worst_q = 0.0
    for D, A in path[1:]:
        eq = tp.solve(scene, insertion=D, rotation=A, initial=eq, options=tracker.options)
        s = tracker.step(D, A)
        np.testing.assert_array_equal(s.converged, eq.converged.numpy())
        np.testing.assert_array_equal(s.iterations, eq.iterations.numpy())
        np.testing.assert_array_equal(s.stable, eq.stable.numpy())
        assert s.tip.shape == (D.shape[0], 3) and s.R.shape == (D.shape[0], 3, 3)
        worst_tip = max(worst_tip, float(np.abs(s.tip - eq.tip_position.numpy()).max()))
        worst_q = max(worst_q, float(np.abs(s.q - eq.q.numpy()).max()))
        np.testing.assert_allclose(s.R, eq.tip_rotation.numpy(), atol=1e-12, rtol=0)
        # (at convergence the residuals are round-off, 1e-16, and differ at that level)
        np.testing.assert_allclose(s.residual, eq.residual_norm.numpy(), rtol=1e-6,
                                   atol=1e-13)
    return worst_tip, worst_q


def test_rotation_path_matches_the_solver_with_its_predictor():
    """Fig. 3 robot, the inner tube turned 0 -> 120 deg in 2 deg steps at fixed insertion:
    every step takes the rotation predictor (same insertions), as the warm solve does."""
    scene = tp.load_scene("renda2021_fig3")
    D = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    path = [(D, torch.tensor([[0.0, math.radians(a)]], dtype=torch.float64))
            for a in range(0, 122, 2)]
    tr = tp.Tracker(scene, insertion=path[0][0], rotation=path[0][1])
    assert (tr.order, tr.n_magnus) == (tr.options.order, tr.options.n_magnus)
    tip, q = _follow(scene, path, tr)
    assert tip < 1e-12 and q < 1e-12


def test_insertion_path_across_the_orifice_matches_the_solver():
    """Fig. 3 robot (the outer tube's curved part starts at the orifice), both tubes moved
    +-6 mm in 0.5 mm steps with a rotation change at each step: the sections appear and
    vanish at the orifice, the layout and its compact coordinates change, no predictor."""
    scene = tp.load_scene("renda2021_fig3")
    D0 = np.array(scene.actuation.insertion)
    path = []
    for k in range(-12, 13):
        D = D0 + np.array([0.5e-3 * k, -0.25e-3 * k])
        A = np.array([0.0, math.radians(40 + 2 * k)])
        path.append((torch.tensor(D[None]), torch.tensor(A[None])))
    tr = tp.Tracker(scene, insertion=path[0][0], rotation=path[0][1])
    tip, q = _follow(scene, path, tr)
    assert tip < 1e-12 and q < 1e-12


def test_three_tube_batch_matches_the_solver():
    """A three-tube robot (torchpvs.testing.nested_scene), a batch of 4 with random rotations
    and insertion moves: batch elements are independent, each as the batched solve gives
    it."""
    from torchpvs.testing import nested_scene
    scene = nested_scene(3, seed=2)
    rng = np.random.default_rng(3)
    D0 = np.array(scene.actuation.insertion)
    A = rng.uniform(-1.0, 1.0, (4, 3))
    D = np.repeat(D0[None], 4, 0)
    path = [(torch.tensor(D), torch.tensor(A))]
    for _ in range(8):
        A = A + rng.uniform(-0.05, 0.05, A.shape)
        if rng.random() < 0.5:   # every tube retracted together by up to 1 mm (stays ordered)
            D = D + rng.uniform(0.0, 1e-3, (4, 1))
        path.append((torch.tensor(D), torch.tensor(A)))
    tr = tp.Tracker(scene, insertion=path[0][0], rotation=path[0][1])
    assert tr.batch == 4
    tip, q = _follow(scene, path, tr)
    assert tip < 1e-12 and q < 1e-12


@settings(max_examples=8, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.floats(-3e-3, 3e-3), st.floats(-3e-3, 3e-3), st.floats(-0.3, 0.3),
       st.floats(-0.3, 0.3))
def test_any_small_move_matches_the_solver(dD1, dD2, dA1, dA2):
    """Any single move of up to 3 mm and 0.3 rad per actuator from the Fig. 3 scene: the
    tracker's step is the warm solve's."""
    scene = tp.load_scene("renda2021_fig3")
    D0 = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    A0 = torch.tensor([scene.actuation.rotation], dtype=torch.float64)
    path = [(D0, A0), (D0 + torch.tensor([[dD1, dD2]], dtype=torch.float64),
                       A0 + torch.tensor([[dA1, dA2]], dtype=torch.float64))]
    tip, q = _follow(scene, path, tp.Tracker(scene))
    assert tip < 1e-12 and q < 1e-12


def test_snapshot_and_restore_replay_a_step_exactly():
    """A step from a restored snapshot repeats the first step bit for bit, whatever steps were
    taken in between (a planner trying several actions from one state)."""
    scene = tp.load_scene("renda2021_fig3")
    tr = tp.Tracker(scene)
    D = np.array(scene.actuation.insertion)
    snap = tr.snapshot()
    first = tr.step(D, [0.0, 0.3])
    tr.step(D + 1e-3, [0.2, -0.4])
    tr.restore(snap)
    again = tr.step(D, [0.0, 0.3])
    for f in dataclasses.fields(first):
        np.testing.assert_array_equal(getattr(first, f.name), getattr(again, f.name))
    with pytest.raises(ValueError, match="snapshot"):
        tr.restore((1, 2))


def test_a_step_too_far_for_its_iterations_reports_it():
    """With one Newton iteration allowed, a 90 deg step cannot converge: the tracker says so
    (converged False, the residual above the tolerance, not stable) rather than returning a
    state as an equilibrium."""
    scene = tp.load_scene("renda2021_fig3")
    # (the first solve, warm from the scene's equilibrium, needs no iteration)
    tr = tp.Tracker(scene, options=tp.SolverOptions(max_iter=1), initial=tp.solve(scene))
    snap = tr.snapshot()
    s = tr.step(scene.actuation.insertion, [0.0, math.radians(90)])
    assert not s.converged[0] and not s.stable[0]
    assert np.isfinite(s.residual[0]) and s.residual[0] > tr.options.tol
    # what holds an equilibrium is not reported for a state that is not one
    tr.restore(snap)
    s = tr.step(scene.actuation.insertion, [0.0, math.radians(90)], jacobians=True,
                forces=True)
    assert not s.converged[0]
    for name in ("tip_jacobian", "actuator_stiffness", "actuation_forces",
                 "actuation_torques"):
        assert np.isnan(getattr(s, name)).all(), name


def test_bad_inputs_name_the_field():
    scene = tp.load_scene("renda2021_fig3")
    tr = tp.Tracker(scene)
    with pytest.raises(ValueError, match=r"insertion must have shape \(2,\) or \(1, 2\)"):
        tr.step([0.1, 0.1, 0.1], [0.0, 0.0])
    with pytest.raises(ValueError, match="rotation must be finite"):
        tr.step(scene.actuation.insertion, [0.0, float("nan")])
    with pytest.raises(ValueError, match=r"insertion: D_j must be >= D_\{j-1\}"):
        tr.step([0.2, 0.1], [0.0, 0.0])
    loaded = tp.Scene(tubes=scene.tubes, actuation=scene.actuation,
                      load=tp.Load(tip_force=(0.0, 0.1, 0.0)))
    with pytest.raises(ValueError, match="scene.load must be zero"):
        tp.Tracker(loaded)
    with pytest.raises(ValueError, match="options.dtype must be torch.float64"):
        tp.Tracker(scene, options=tp.SolverOptions(dtype=torch.float32))


def test_equilibrium_is_the_full_solve_at_the_tracker_state():
    """``Tracker.equilibrium()``: ``torchpvs.solve`` at the current actuation warm from the
    tracker's coordinates; at the tracker's own discretization it lands on the same tip, and
    by default it is the automatic solve with forces (within its accuracy of the tip)."""
    scene = tp.load_scene("renda2021_fig3")
    tr = tp.Tracker(scene)
    s = tr.step(scene.actuation.insertion, [0.1, 0.6])
    same = tr.equilibrium(tr.options)
    np.testing.assert_allclose(same.tip_position.numpy(), s.tip, atol=1e-12, rtol=0)
    full = tr.equilibrium()
    assert full.actuation_forces is not None and bool(full.converged.all())
    assert np.abs(full.tip_position.numpy() - s.tip).max() <= tp.SolverOptions().accuracy
    np.testing.assert_array_equal(tr.state.tip, s.tip)     # the state is unchanged


def _fd_jacobian(tr, D, A, h_D=1e-6, h_A=1e-6):
    """Central differences of the tracker's own tip position in every actuator, each from a
    snapshot of the state at ``(D, A)`` (an independent check of the closed form)."""
    snap = tr.snapshot()
    B, N = D.shape
    J = np.empty((B, 3, 2 * N))
    for c in range(2 * N):
        h = h_D if c < N else h_A
        tips = []
        for sgn in (1.0, -1.0):
            Dp, Ap = D.copy(), A.copy()
            if c < N:
                Dp[:, c] += sgn * h
            else:
                Ap[:, c - N] += sgn * h
            tr.restore(snap)
            tips.append(tr.step(Dp, Ap).tip)
        J[:, :, c] = (tips[0] - tips[1]) / (2 * h)
    tr.restore(snap)
    return J


def test_control_step_matches_the_jacobians_away_from_kinks():
    """``step(..., jacobians=True)`` off every kink (both insertions 1 mm from the Fig. 3
    scene's, where the outer tube's transition sits at the orifice): the tip Jacobian and the
    actuator stiffness are ``Equilibrium.jacobians()``' closed forms at the same equilibrium
    (to rounding), and the tip rows agree with central differences of the tracker's steps."""
    scene = tp.load_scene("renda2021_fig3")
    D = np.array([scene.actuation.insertion]) + 1e-3
    A = np.array([[0.2, 1.1]])
    tr = tp.Tracker(scene, insertion=D, rotation=A)
    s = tr.step(D, A + 0.01, jacobians=True)
    cj = tr.equilibrium(tr.options).jacobians(compliance=False)
    J, K = cj.tip_jacobian.numpy(), cj.actuator_stiffness.numpy()
    np.testing.assert_allclose(s.tip_jacobian, J, atol=1e-12 * np.abs(J).max(), rtol=0)
    np.testing.assert_allclose(s.actuator_stiffness, K, atol=1e-12 * np.abs(K).max(), rtol=0)
    fd = _fd_jacobian(tr, D, A + 0.01)
    np.testing.assert_allclose(s.tip_jacobian[:, :3], fd, atol=1e-6 * np.abs(fd).max(), rtol=0)


def test_control_step_takes_the_retracting_side_at_a_kink():
    """At the Fig. 3 scene's insertions the outer tube's curved part starts at the orifice: a
    kink of the tip and of ``U*`` in ``D_1``. The control step takes the retracting side as
    ``Equilibrium.jacobians()`` does (agreeing to the O(1e-7 m) offset of that side), and its
    ``D_1`` column is the one-sided difference on that side, not the other."""
    scene = tp.load_scene("renda2021_fig3")
    D = np.array([scene.actuation.insertion])
    A = np.array([[0.0, 0.8]])
    tr = tp.Tracker(scene, rotation=A)
    s = tr.step(D, A, jacobians=True)
    cj = tr.equilibrium(tr.options).jacobians(compliance=False)
    J, K = cj.tip_jacobian.numpy(), cj.actuator_stiffness.numpy()
    np.testing.assert_allclose(s.tip_jacobian, J, atol=1e-5 * np.abs(J).max(), rtol=0)
    np.testing.assert_allclose(s.actuator_stiffness, K, atol=1e-4 * np.abs(K).max(), rtol=0)
    snap = tr.snapshot()
    h = 1e-6
    side = {}
    for sgn in (1.0, -1.0):
        tr.restore(snap)
        Dp = D.copy()
        Dp[0, 0] += sgn * h
        side[sgn] = (tr.step(Dp, A).tip - s.tip) / (sgn * h)
    retract, advance = side[1.0][0], side[-1.0][0]
    col = s.tip_jacobian[0, :3, 0]
    assert np.abs(col - retract).max() < 1e-3 * np.abs(retract).max()
    assert np.abs(col - advance).max() > 0.1 * np.abs(retract).max()   # a real kink


def test_control_step_batched_three_tubes_against_differences():
    """Three tubes, a batch of 3 random states: the tip rows against central differences, the
    stiffness symmetric with the common rotation as its null direction (no tip load: turning
    every tube together costs no energy)."""
    from torchpvs.testing import nested_scene
    scene = nested_scene(3, seed=4)
    rng = np.random.default_rng(5)
    # (bases 1 mm apart and off the scene's values: no kink, differences on both sides)
    D = (np.repeat(np.array([scene.actuation.insertion]), 3, 0) + np.array([1e-3, 2e-3, 3e-3])
         + rng.uniform(0, 2e-3, (3, 1)))
    A = rng.uniform(-1.5, 1.5, (3, 3))
    tr = tp.Tracker(scene, insertion=D, rotation=A)
    s = tr.step(D, A, jacobians=True)
    assert s.converged.all()
    fd = _fd_jacobian(tr, D, A)
    np.testing.assert_allclose(s.tip_jacobian[:, :3], fd, atol=2e-6 * np.abs(fd).max(), rtol=0)
    K = s.actuator_stiffness
    np.testing.assert_array_equal(K, np.swapaxes(K, 1, 2))
    common = np.array([0, 0, 0, 1.0, 1.0, 1.0])
    assert np.abs(K @ common).max() < 1e-9 * np.abs(K).max()


@pytest.mark.parametrize("case", ["transition_at_orifice", "base_at_orifice", "no_kink",
                                  "three_tubes"])
def test_forces_match_the_solver_with_their_one_sided_values(case):
    """``step(..., forces=True)``: the actuation forces and torques, their insertion side and
    the kink mask equal ``torchpvs.solve``'s at the tracker's discretization (within 1e-9 N;
    NaN at the same blocked entries). Cases: the Fig. 3 scene, whose outer tube's curved part
    starts at the orifice (a kink: its sides at the same active coordinates); the outer base at
    the orifice (``D_1 = 0``: the retraction side gains the guide twist, one Newton step; the
    insertion side is blocked); 1 mm off every kink; a three-tube batch."""
    from torchpvs.testing import nested_scene
    scene = tp.load_scene("renda2021_fig3")
    D = np.array([scene.actuation.insertion])
    A = np.array([[0.3, 1.2]])
    if case == "base_at_orifice":
        D = D.copy()
        D[0, 0] = 0.0
    elif case == "no_kink":
        D = D + 1e-3
    elif case == "three_tubes":
        scene = nested_scene(3, seed=6)
        D = np.repeat(np.array([scene.actuation.insertion]), 2, 0) + np.array([[0.0], [1e-3]])
        A = np.array([[0.1, -0.4, 0.9], [1.0, 0.2, -0.3]])
    tr = tp.Tracker(scene, insertion=D, rotation=A)
    s = tr.step(D, A + 0.02, forces=True)
    eq = tr.equilibrium(tp.SolverOptions(order=tr.order, n_magnus=tr.n_magnus))
    assert s.converged.all()
    np.testing.assert_array_equal(s.force_kink, eq.force_kink.numpy())
    for name in ("actuation_forces", "actuation_torques", "actuation_forces_insertion"):
        np.testing.assert_allclose(getattr(s, name), getattr(eq, name).numpy(), atol=1e-9,
                                   rtol=0, err_msg=name)
    if case != "no_kink" and case != "three_tubes":
        assert s.force_kink[0, 0]
    if case == "base_at_orifice":
        assert np.isnan(s.actuation_forces_insertion[0, 0])


def test_compiled_kink_mask_is_the_solvers():
    """The tracker's compiled kink mask (``force_kink``) equals ``torchpvs.forces.kink_mask``
    on insertions at every kind of kink (a base, a straight-to-curved transition at the
    orifice, an inner tube's end level with the outer tube's) within and just beyond its
    tolerance, and on random ones."""
    from torchpvs.forces import KINK_TOL, kink_mask
    from torchpvs.testing import nested_scene
    for scene in (tp.load_scene("renda2021_fig3"), nested_scene(3, seed=7)):
        L = np.array([t.length for t in scene.tubes])
        Ls = np.array([t.straight_length for t in scene.tubes])
        D0 = np.array(scene.actuation.insertion)
        N = len(L)
        rows = [D0, np.zeros(N)]
        for j in range(N):
            for target in (Ls[j], 0.0):
                for off in (0.0, 0.5 * KINK_TOL, 2 * KINK_TOL, -3e-4):
                    D = D0.copy()
                    D[j] = max(target + off, 0.0)
                    rows.append(np.maximum.accumulate(D))
        D = D0.copy()       # the inner tube's end level with the outer tube's
        D[1] = D[0] + (L[1] - L[0])
        rows.append(np.maximum.accumulate(D))
        rng = np.random.default_rng(8)
        rows += [np.sort(rng.uniform(0, Ls.min(), N)) for _ in range(10)]
        D = np.array(rows)
        A = np.zeros_like(D)
        tr = tp.Tracker(scene, insertion=D, rotation=A)
        got = tr.step(D, A, forces=True).force_kink
        expected = kink_mask(tp.solve(scene).context.tubes, torch.tensor(D)).numpy()
        np.testing.assert_array_equal(got, expected)
        assert expected.any() and not expected.all()


def test_solve_from_is_the_plain_warm_solve_with_its_outputs():
    """``Tracker.solve_from`` (any number of rows, warm from given coordinates, no predictor)
    against ``torchpvs.solve(initial=q)`` at the same fixed discretization: identical
    iterations and verdicts, tips and coordinates within 1e-12; energy, relative rotation
    and stability margin as the Equilibrium defines them (to round-off); forces equal; the
    actuator stiffness equals ``torchpvs.jacobians.actuator_stiffness``; the tracker's own
    state untouched."""
    from torchpvs.jacobians import actuator_stiffness
    scene = tp.load_scene("renda2021_fig3")
    opts = tp.SolverOptions(order=2, n_magnus=8)
    rng = np.random.default_rng(5)
    k = 7
    D0 = np.array(scene.actuation.insertion) + rng.uniform(-0.01, 0.01, (k, 2))
    D0 = np.maximum.accumulate(np.clip(D0, 0, None), -1)
    A0 = rng.uniform(-math.pi, math.pi, (k, 2))
    eq0 = tp.solve(scene, insertion=torch.from_numpy(D0), rotation=torch.from_numpy(A0),
                   options=opts)
    D1 = D0 + rng.normal(0, 5e-4, (k, 2))
    D1 = np.maximum.accumulate(np.clip(D1, 0, None), -1)
    A1 = A0 + rng.normal(0, 0.03, (k, 2))
    eq = tp.solve(scene, insertion=torch.from_numpy(D1), rotation=torch.from_numpy(A1),
                  initial=eq0.q, options=opts)
    tr = tp.Tracker(scene, options=opts)
    before = tr.snapshot()
    s = tr.solve_from(eq0.q, D1, A1, stiffness=True, forces=True, margin=True)
    assert tr.snapshot() == before
    assert bool(eq.converged.all())
    np.testing.assert_array_equal(s.iterations, eq.iterations.numpy())
    np.testing.assert_array_equal(s.stable, eq.stable.numpy())
    np.testing.assert_allclose(s.tip, eq.tip_position.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(s.q, eq.q.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(s.energy, eq.energy.numpy(), rtol=1e-12, atol=0)
    np.testing.assert_allclose(s.relative_rotation_at_outer_tip,
                               eq.relative_rotation_at_outer_tip.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(s.min_stiffness_eigenvalue,
                               eq.min_stiffness_eigenvalue.numpy(), atol=1e-12, rtol=0)
    np.testing.assert_allclose(s.actuation_forces, eq.actuation_forces.numpy(), atol=1e-9,
                               rtol=0)
    np.testing.assert_allclose(s.actuation_torques, eq.actuation_torques.numpy(), atol=1e-9,
                               rtol=0)
    K = actuator_stiffness(eq).numpy()
    K = 0.5 * (K + np.swapaxes(K, -1, -2))
    np.testing.assert_allclose(s.actuator_stiffness, K, atol=1e-9 * np.abs(K).max(), rtol=0)
    assert s.tip_jacobian is None
    # without the margin or the stiffness: not computed, reported as None
    s2 = tr.solve_from(eq0.q, D1, A1)
    assert s2.min_stiffness_eigenvalue is None and s2.actuator_stiffness is None
    np.testing.assert_array_equal(s2.tip, s.tip)


def test_solve_from_checks_its_inputs():
    tr = tp.Tracker("renda2021_fig3", options=tp.SolverOptions(order=2, n_magnus=8))
    q = tr.state.q
    D = np.array([tr.scene.actuation.insertion])
    A = np.zeros((1, 2))
    with pytest.raises(ValueError, match="initial must have shape"):
        tr.solve_from(q[:, :-1], D, A)
    with pytest.raises(ValueError, match="rotation must have shape"):
        tr.solve_from(q, D, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="insertion must be finite"):
        tr.solve_from(q, D * np.nan, A)
    with pytest.raises(ValueError, match="D_j must be >= D_{j-1}"):
        tr.solve_from(q, D[:, ::-1] + [[0.0, -0.01]], A)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(m=st.integers(1, 40), seed=st.integers(0, 2**31), scale=st.floats(1e-3, 1e3),
       kind=st.sampled_from(["indefinite", "definite", "scaled"]))
def test_min_eigenvalue_is_lapacks(m, seed, scale, kind):
    """The margin's eigenvalue routine (tridiagonal reduction and multisection) against
    LAPACK's full spectrum (``numpy.linalg.eigvalsh``), to round-off of the spectrum's size."""
    from torchpvs.tracker import min_eigenvalue
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(m, m)) * scale
    A = {"indefinite": 0.5 * (M + M.T), "definite": M @ M.T}.get(kind)
    if A is None:   # the margin's own kind: unit diagonal (Jacobi-scaled), near singular
        S = M @ M.T + 1e-9 * np.eye(m)
        d = np.sqrt(np.diag(S))
        A = S / d[:, None] / d[None, :]
    ref = np.linalg.eigvalsh(A)
    got = min_eigenvalue(A.copy())
    assert abs(got - ref[0]) <= 1e-13 * max(1.0, np.abs(ref).max())


def test_solve_from_in_threads_equals_one_call():
    """Rows split into chunks solved in threads (``threads=2``): every row's result is the one
    call's, bit for bit; a bad thread count names the field."""
    scene = tp.load_scene("renda2021_fig3")
    opts = tp.SolverOptions(order=2, n_magnus=8)
    rng = np.random.default_rng(9)
    k = 40
    D = np.maximum.accumulate(np.array(scene.actuation.insertion)
                              + rng.uniform(-0.01, 0.01, (k, 2)), -1).clip(0, None)
    A = rng.uniform(-math.pi, math.pi, (k, 2))
    eq = tp.solve(scene, insertion=torch.from_numpy(D), rotation=torch.from_numpy(A),
                  options=opts)
    tr = tp.Tracker(scene, options=opts)
    D1, A1 = np.maximum.accumulate(D + rng.normal(0, 5e-4, (k, 2)), -1).clip(0, None), A + 0.02
    one = tr.solve_from(eq.q, D1, A1, stiffness=True, forces=True, margin=True, threads=1)
    two = tr.solve_from(eq.q, D1, A1, stiffness=True, forces=True, margin=True, threads=2)
    for f in dataclasses.fields(one):
        a, b = getattr(one, f.name), getattr(two, f.name)
        if a is None:
            assert b is None, f.name
        else:
            np.testing.assert_array_equal(b, a, err_msg=f.name)
    assert one.converged.all()
    with pytest.raises(ValueError, match="threads must be an integer >= 1"):
        tr.solve_from(eq.q, D1, A1, threads=0)



def _tracked_layouts(robot: str, seed: int, retract: float, trials: int = 6):
    """``(tracker, state, layout arrays, tube arrays, D)`` at ``trials`` random rotations with
    every tube retracted together by up to ``retract`` [m]: a converged tracker step, and the
    compiled layout there (``compiled_layout.layout_maps_arrays``), for the tests of the
    control step's pieces."""
    from torchpvs.compiled_layout import layout_maps_arrays
    from torchpvs.testing import nested_scene
    scene = tp.load_scene("renda2021_fig3") if robot == "fig3" else nested_scene(3, seed=2)
    rng = np.random.default_rng(seed)
    tr = tp.Tracker(scene)
    xg, wg, xq, wq, xm, _ = tr._layout_tables
    tubes, unloaded = tr._tube_args_for(1)
    for _ in range(trials):
        D = tr._D + rng.uniform(0.0, retract, (1, 1))
        A = rng.uniform(-2.0, 2.0, (1, tr.N))
        s = tr.step(D, A)
        assert s.converged[0]
        lay = layout_maps_arrays(*tubes, D, A, unloaded, 1e-12, xg, wg, xq, wq, xm, tr._phi,
                                 tr._n)
        yield tr, s, lay, tuple(a[0] for a in tubes), D[0]


@pytest.mark.parametrize("robot", ["fig3", "three_tube"])
def test_forward_mode_tip_tangents_equal_the_complex_step(robot):
    """The control step's ``J = P_x - P_q Z`` by forward-mode tangents
    (``tracker.tip_forward``) against the complex step of the same pose, one pass per actuator
    (``compiled.tip_directional``, an independent derivative of the same arithmetic): random
    coordinate directions, at the layout's own insertions and moved along its slopes, on
    random rotations and insertions (straight sections in the guide, transitions, tube ends),
    to round-off."""
    from torchpvs import tracker as T
    rng = np.random.default_rng(11)
    worst = 0.0
    for tr, s, lay, (_EI, _GJ, L, Ls, coef), D in _tracked_layouts(robot, 11, 0.02):
        N = tr.N
        xm = tr._layout_tables[4]
        tau, psi0, start, h, present, curved, presc, qmask, tip_tube = (
            lay[1][0], lay[9][0], lay[2][0], lay[3][0], lay[4][0], lay[5][0], lay[7][0],
            lay[8][0], lay[12][0])
        dq = rng.normal(size=(s.q.shape[1], 2 * N)) * qmask[:, None]
        for Ds, As in ((np.zeros(N), np.zeros(N)),
                       (rng.normal(size=N) * 1e-4, rng.normal(size=N) * 1e-2)):
            args = (s.q[0], dq, qmask, D, L, Ls, coef, tau, psi0, start, h, present, curved,
                    presc, tip_tube, xm, tr._phi_m, tr._Q_m, Ds, As)
            ref, fwd = np.empty((6, 2 * N)), np.empty((6, 2 * N))
            compiled.tip_directional(*args, ref)
            T.tip_forward(*args, fwd)
            assert np.abs(ref).max() > 0
            worst = max(worst, float(np.abs(fwd - ref).max() / np.abs(ref).max()))
    assert worst < 1e-13


@pytest.mark.parametrize("robot", ["fig3", "three_tube"])
def test_forward_mode_stiffness_rows_equal_the_complex_step(robot):
    """The control step's energy rows ``U_qx, U_xx`` at fixed ``q`` by forward-mode tangents
    (``tracker.stiffness_forward``, what the tracker and the environments use) against one
    complex step of the same partials per actuator (``compiled.stiffness_rows_one``), along
    the insertions alone (the rotation rows read off the Hessian) and along all actuators, on
    random rotations and insertions, to round-off."""
    from torchpvs import tracker as T
    worst, nonzero = 0.0, 0
    for tr, s, lay, (EI, GJ, L, Ls, coef), D in _tracked_layouts(robot, 12, 0.005):
        N = tr.N
        xq, wq = tr._layout_tables[2], tr._layout_tables[3]
        args = (s.q[0], lay[8][0], D, L, Ls, EI, GJ, coef, lay[1][0], lay[9][0], lay[2][0],
                lay[3][0], lay[4][0], lay[5][0], lay[6][0], lay[7][0], lay[11][0], xq, wq,
                tr._phi, tr._Qb)
        for m in (N, 2 * N):
            Gr, Xr = np.empty((m, s.q.shape[1])), np.empty((m, 2 * N))
            Gf, Xf = np.full_like(Gr, np.nan), np.full_like(Xr, np.nan)
            compiled.stiffness_rows_one(*args, Gr, Xr)
            T.stiffness_forward(*args, Gf, Xf)
            size = max(np.abs(Gr).max(), np.abs(Xr).max())
            nonzero += size > 0
            err = max(np.abs(Gf - Gr).max(), np.abs(Xf - Xr).max())
            worst = max(worst, err / max(size, 1e-300))
    assert nonzero >= 8 and worst < 1e-13


def test_the_anatomy_benchmark_times_the_calls_a_step_makes(capsys):
    """benchmarks/tracker_anatomy.py captures the step's compiled call by its name (a rename
    would otherwise break it unnoticed) and prints every row with ordered, positive times."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "tracker_anatomy.py"
    spec = importlib.util.spec_from_file_location("tracker_anatomy", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.main(["--calls", "20"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "kink side 1" in lines[0]          # the Fig. 3 insertions sit at a kink
    rows = {ln[:52].strip(): [float(v) for v in ln[52:].split()] for ln in lines[2:]}
    assert len(rows) == 7 and all(0 < lo <= p10 for lo, p10 in rows.values())
