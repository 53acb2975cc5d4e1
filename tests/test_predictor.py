"""Stage 5 (driver), ``torchpvs.predictor``: where a warm solve starts.

What is tested, and against what:

- ``rotation_predictor`` is the first-order (Euler) step along the branch: its slope
  ``(q_pred - q0) / dalpha`` for a tiny step of each tube's rotation equals the central finite
  difference of separately converged solves (``tol=1e-14``, ``alpha +- 1e-4``) to 1e-6
  (measured: 1e-9), on the Fig. 3 and three-tube robots;
- through ``solve``: a warm start from an Equilibrium after a rotation-only change (the
  predictor applies) converges to the same tips (1e-12 m) as the same start passed as bare
  coordinates (no predictor), in no more Newton iterations per element (fewer in total), and
  the predicted coordinates are far closer to the converged ones than the unpredicted warm
  start (under 5 % of its distance; measured: 0.02-0.4 %), for 1 and 2 deg steps of every
  tube (at 5 deg the three-tube robot's predicted change exceeds the trust bound: the outer
  tube's guide twist ``-dalpha / D_1`` with ``D_1 = 0.1 m``);
- the cases where it must keep the warm start unchanged (its docstring's contract): no
  rotation change, bare coordinates, changed insertions, a tip load, a base at the orifice
  (no guide twist; the same step with the base 1 cm behind it does move), and a predicted
  change beyond ``PREDICTOR_TRUST``; it is linear in the step below that bound, and
  2 pi-periodic in the rotations;
- ``initial_q``: the order and Magnus count it reads back from an Equilibrium are the ones
  that solve reported, the order of bare coordinates is that of their basis size, rows are
  broadcast to the batch and the result carries no gradient; non-finite, integer or
  wrongly-batched starts raise ``ValueError`` naming ``initial``.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchpvs as tp
from torchpvs.plan import tube_tensors
from torchpvs.predictor import PREDICTOR_TRUST, initial_q, rotation_predictor

DT = torch.float64
CPU = torch.device("cpu")
FIG3 = tp.load_scene("renda2021_fig3")
OPTS = tp.SolverOptions(order=2, n_magnus=8, compute_forces=False, tol=1e-14)
pytestmark = pytest.mark.usefixtures("one_thread_module")


def three_tube():
    from envs.robots import rvim_three_tube
    return rvim_three_tube().scene


def start(scene, B=3, offsets=(0.3, 1.5, 2.8), insertion=None):
    """A converged batch: the scene's actuation with the innermost tube turned by offsets."""
    D = torch.tensor([insertion or scene.actuation.insertion] * B, dtype=DT)
    A = torch.tensor([scene.actuation.rotation] * B, dtype=DT)
    A[:, -1] += torch.tensor(offsets[:B], dtype=DT)
    e0 = tp.solve(scene, insertion=D, rotation=A, options=OPTS)
    assert bool(e0.converged.all())
    return e0, D, A, tube_tensors(scene, DT, CPU), torch.zeros(B, 3, dtype=DT)


def predict(e0, scene, tubes, D, A, F=None, M=None, q=None):
    Z = torch.zeros(D.shape[0], 3, dtype=DT)
    q = e0.q.clone() if q is None else q
    return rotation_predictor(e0, q, scene, tubes, D, A, Z if F is None else F,
                              Z if M is None else M, OPTS)


@pytest.mark.parametrize("name", ["fig3", "three_tube"])
def test_predictor_slope_is_the_finite_difference_of_converged_solves(name):
    sc = FIG3 if name == "fig3" else three_tube()
    e0, D, A, tubes, _ = start(sc)
    h, d = 1e-4, 1e-6
    for j in range(sc.n_tubes):
        E = torch.zeros_like(A)
        E[:, j] = 1.0
        qp = tp.solve(sc, insertion=D, rotation=A + h * E, options=OPTS, initial=e0.q).q
        qm = tp.solve(sc, insertion=D, rotation=A - h * E, options=OPTS, initial=e0.q).q
        fd = (qp - qm) / (2 * h)
        slope = (predict(e0, sc, tubes, D, A + d * E) - e0.q) / d
        rel = (slope - fd).norm(dim=-1) / fd.norm(dim=-1)
        assert bool((rel < 1e-6).all()), (j, rel)


@pytest.mark.parametrize("name", ["fig3", "three_tube"])
@pytest.mark.parametrize("deg", [1.0, 2.0])
def test_warm_start_with_the_predictor_is_closer_and_no_slower(name, deg):
    sc = FIG3 if name == "fig3" else three_tube()
    e0, D, A, tubes, _ = start(sc)
    A1 = A.clone()
    A1[:, -1] += math.radians(deg)
    A1[:, 0] -= math.radians(0.5 * deg)              # every tube turns, by different steps
    with_pred = tp.solve(sc, insertion=D, rotation=A1, options=OPTS, initial=e0)
    without = tp.solve(sc, insertion=D, rotation=A1, options=OPTS, initial=e0.q)
    assert bool(with_pred.converged.all()) and bool(without.converged.all())
    assert float((with_pred.tip_position - without.tip_position).abs().max()) <= 1e-12
    assert bool((with_pred.iterations <= without.iterations).all())
    assert int(with_pred.iterations.sum()) < int(without.iterations.sum())
    pred = predict(e0, sc, tubes, D, A1)
    dist_pred = (pred - without.q).norm(dim=-1)
    dist_warm = (e0.q - without.q).norm(dim=-1)
    assert bool((dist_pred < 0.05 * dist_warm).all()), dist_pred / dist_warm


def test_no_rotation_change_keeps_the_warm_start():
    e0, D, A, tubes, _ = start(FIG3)
    assert torch.equal(predict(e0, FIG3, tubes, D, A), e0.q)


def test_the_predictor_is_periodic_in_the_rotations():
    e0, D, A, tubes, _ = start(FIG3)
    a = predict(e0, FIG3, tubes, D, A + 0.02)
    b = predict(e0, FIG3, tubes, D, A + 0.02 + 2 * math.pi)
    c = predict(e0, FIG3, tubes, D, A + 0.02 - 4 * math.pi)
    assert not torch.equal(a, e0.q)
    scale = float(e0.q.abs().max())
    assert float((a - b).abs().max()) <= 1e-12 * scale
    assert float((a - c).abs().max()) <= 1e-12 * scale


def test_bare_coordinates_changed_insertions_or_a_load_keep_the_warm_start():
    e0, D, A, tubes, Z = start(FIG3)
    A1 = A + 0.02
    q = e0.q.clone()
    assert rotation_predictor(e0.q, q, FIG3, tubes, D, A1, Z, Z, OPTS) is q
    assert torch.equal(predict(e0, FIG3, tubes, D + 1e-3, A1), e0.q)
    F = Z.clone()
    F[:, 0] = 0.01
    assert torch.equal(predict(e0, FIG3, tubes, D, A1, F=F), e0.q)
    M = Z.clone()
    M[:, 1] = 1e-4
    assert torch.equal(predict(e0, FIG3, tubes, D, A1, M=M), e0.q)
    assert rotation_predictor(None, None, FIG3, tubes, D, A1, Z, Z, OPTS) is None


def test_a_base_at_the_orifice_keeps_the_warm_start():
    """With D_1 = 0 the outer tube has no guide twist, so the predictor does not apply; 1 cm
    behind the orifice the same step moves the start."""
    for d1, moves in ((0.0, False), (0.01, True)):
        e0, D, A, tubes, _ = start(FIG3, B=2, insertion=[d1, 0.1])
        moved = not torch.equal(predict(e0, FIG3, tubes, D, A + 0.01), e0.q)
        assert moved == moves, d1


def test_the_predictor_is_linear_in_the_step_up_to_the_trust_bound():
    """The predicted change is linear in ``dalpha``; a step whose change times the robot's
    length reaches PREDICTOR_TRUST keeps the warm start instead."""
    e0, D, A, tubes, _ = start(FIG3, B=1)
    L = max(t.length for t in FIG3.tubes)
    dA = torch.tensor([[0.3, 1.0]], dtype=DT) * 1e-3
    dq = predict(e0, FIG3, tubes, D, A + dA) - e0.q
    size = float(dq.abs().max()) * L                   # the trust measure of this step
    assert 0 < size < PREDICTOR_TRUST
    below = 0.5 * PREDICTOR_TRUST / size
    above = 2.0 * PREDICTOR_TRUST / size
    got = predict(e0, FIG3, tubes, D, A + below * dA) - e0.q
    assert torch.allclose(got, below * dq, rtol=1e-9, atol=1e-12)
    assert torch.equal(predict(e0, FIG3, tubes, D, A + above * dA), e0.q)


def test_initial_q_reads_back_what_solve_reported():
    fine = tp.solve(FIG3, options=tp.SolverOptions(accuracy=1e-9, compute_forces=False))
    q, order, magnus = initial_q(fine, 1, FIG3.n_tubes)
    assert order == fine.order and order >= 3
    assert magnus == fine.context.discretization.n_magnus
    assert torch.equal(q, fine.q)
    # bare coordinates: the order from their size, no Magnus count; a row broadcast to B
    q, order, magnus = initial_q(fine.q[0], 4, FIG3.n_tubes)
    assert q.shape == (4, fine.q.shape[-1]) and order == fine.order and magnus is None
    assert bool((q == fine.q[0]).all())
    assert initial_q(None, 4, 2) == (None, None, None)
    # a size that is no basis size: no order
    assert initial_q(torch.zeros(1, fine.q.shape[-1] + 1, dtype=DT), 1, 2)[1] is None


def test_initial_q_carries_no_gradient():
    q0 = tp.solve(FIG3, options=OPTS).q.clone().requires_grad_(True)
    q, _, _ = initial_q(q0, 2, FIG3.n_tubes)
    assert not q.requires_grad and torch.equal(q[1], q0[0].detach())


@pytest.mark.parametrize("bad, B", [
    (torch.full((1, 50), float("nan"), dtype=DT), 1),
    (torch.full((1, 50), float("inf"), dtype=DT), 1),
    (torch.zeros(1, 50, dtype=torch.long), 1),
    (torch.zeros(2, 50, dtype=DT), 3),
])
def test_initial_q_refuses_bad_starts(bad, B):
    with pytest.raises(ValueError, match="initial"):
        initial_q(bad, B, 2)
