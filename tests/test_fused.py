"""The fused path (torchpvs/fused.py) against the driver's rounds it stands in for.

Reference: the same ``torchpvs.solve`` call with the fused path switched off (the rounds of
torchpvs/solver.py: predictor, Newton, the order and Magnus checks, the forces with their kink
sides, each stage a separate compiled call): the same equilibria (flags, iterations, verdicts,
orders), tips within 1e-12 m, forces within 1e-9 N, error estimates within 1e-12 m. Where the
fused path declines (a higher order or more Magnus steps needed, a tip load, a gradient), the
result is the rounds' own.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

import torchpvs as tp
import torchpvs.fused as fused_mod
import torchpvs.solver as solver_mod
from torchpvs import compiled
from torchpvs.plan import Plan, plan_for
from torchpvs.testing import (
    assert_same_equilibria,
    feasible_actuations,
    fig3,
    nested_scene,
    random_scene,
    spy_results,
)

pytestmark = pytest.mark.skipif(not compiled.available(), reason="numba not importable")


def _both(monkeypatch, scene, **kw):
    """``(fused, rounds, taken)``: the call with the fused path, the same call without it, and
    whether the fused path returned the first (not declined)."""
    real = fused_mod.fused_solve
    taken = spy_results(monkeypatch, solver_mod, "fused_solve", real)
    a = tp.solve(scene, **kw)
    monkeypatch.setattr(solver_mod, "fused_solve", lambda *a, **k: None)
    b = tp.solve(scene, **kw)
    monkeypatch.setattr(solver_mod, "fused_solve", real)
    return a, b, taken[0]


def _assert_same(a, b):
    if a.actuation_forces is None:          # compute_forces=False: none on either side
        assert b.actuation_forces is None and b.actuation_torques is None
        a = replace(a, actuation_forces=a.q[:, :1] * 0, actuation_torques=a.q[:, :1] * 0)
        b = replace(b, actuation_forces=b.q[:, :1] * 0, actuation_torques=b.q[:, :1] * 0)
    assert_same_equilibria(a, b, tip_tol=1e-12, force_tol=1e-9)
    assert a.order == b.order
    assert a.context.discretization == b.context.discretization
    assert torch.equal(a.dofs, b.dofs)
    assert torch.equal(a.force_kink, b.force_kink)
    assert torch.equal(a.accuracy_met, b.accuracy_met)
    assert a.reason == b.reason
    assert torch.allclose(a.error_estimate, b.error_estimate, rtol=0, atol=1e-12,
                          equal_nan=True)
    assert torch.equal(a.energy, b.energy) or torch.allclose(a.energy, b.energy, rtol=1e-12)
    assert torch.allclose(a.relative_rotation_at_outer_tip, b.relative_rotation_at_outer_tip,
                          rtol=0, atol=1e-12)
    ins_a, ins_b = a.actuation_forces_insertion, b.actuation_forces_insertion
    if ins_a is not None:
        assert torch.equal(torch.isnan(ins_a), torch.isnan(ins_b))
        ok = ~torch.isnan(ins_a)
        assert float((ins_a - ins_b)[ok].abs().max()) <= 1e-9
    assert float((a.q - b.q).abs().max()) <= 1e-9


def test_fig3_kink_warm_and_cold_equal_the_rounds(monkeypatch):
    """The Fig. 3 robot at its scene actuation (the outer tube's curved part starts at the
    orifice: one-sided insertion forces), cold and warm 1 deg steps over the rotation range
    (the rotation predictor), batched: the fused path is taken and equals the rounds."""
    sc = tp.load_scene("renda2021_fig3")
    a, b, taken = _both(monkeypatch, sc)
    assert taken and bool(a.force_kink.any())
    _assert_same(a, b)
    rot = torch.tensor([[0.0, math.radians(d)] for d in (0, 40, 80, 120, 160)],
                       dtype=torch.float64)
    cold = tp.solve(sc, rotation=rot)
    a, b, taken = _both(monkeypatch, sc, rotation=rot + math.radians(1), initial=cold)
    assert taken
    _assert_same(a, b)
    assert int(a.iterations.max()) <= 2                   # warm: the predictor worked


@pytest.mark.parametrize("seed", range(8))
def test_random_scenes_equal_the_rounds(monkeypatch, seed):
    """Seeded random 2- and 3-tube robots (testing.random_scene), 6 feasible actuations each,
    cold and then warm from a small rotation and insertion change: wherever the fused path
    is taken it equals the rounds; where it declines the result is the rounds' (same call)."""
    sc = random_scene(seed)
    rng = np.random.default_rng(seed)
    D, A = feasible_actuations(rng, 6, sc)
    D, A = torch.from_numpy(D), torch.from_numpy(A)
    a, b, _ = _both(monkeypatch, sc, insertion=D, rotation=A)
    _assert_same(a, b)
    # a rotation-only step (predictor) and an insertion step (no predictor), warm
    for dD, dA in ((0.0, 0.02), (1e-4, 0.0)):
        a, b, taken = _both(monkeypatch, sc, insertion=D + dD, rotation=A + dA, initial=b)
        _assert_same(a, b)
        assert taken         # warm at the order found: one round suffices on these scenes


@pytest.mark.parametrize("opts", [
    dict(order=3),
    dict(n_magnus=8),
    dict(order=2, n_magnus=8),
    dict(compute_forces=False),
    dict(method="root"),
    dict(accuracy=1e-6),
], ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()))
def test_options_equal_the_rounds(monkeypatch, opts):
    """A fixed order (no order check), fixed Magnus steps (no step-count check), both, no
    forces, plain Newton, a tighter accuracy: the same as the rounds, warm and cold."""
    sc = tp.load_scene("renda2021_fig3")
    o = tp.SolverOptions(**opts)
    rot = torch.tensor([[0.2, 0.5], [0.0, 2.0]], dtype=torch.float64)
    a, b, _ = _both(monkeypatch, sc, rotation=rot, options=o)
    _assert_same(a, b)
    a, b, taken = _both(monkeypatch, sc, rotation=rot + 0.01, initial=b, options=o)
    _assert_same(a, b)
    if "accuracy" not in opts:
        assert taken                     # these are within the fused path's scope


def test_declines_where_the_rounds_go_further():
    """The fused path returns None (the driver's rounds then solve) where its one round is not
    final (an accuracy that needs a higher order) or where it does not apply (a tip load, a
    warm start of another order, the eager kernel, the paper's force model, a batch above
    MAX_BATCH); it takes the default case."""
    sc = tp.load_scene("renda2021_fig3")
    tubes = plan_for(sc, torch.float64, torch.device("cpu")).tubes
    plan = Plan(tubes)
    D = torch.tensor([sc.actuation.insertion], dtype=torch.float64)
    A = torch.tensor([sc.actuation.rotation], dtype=torch.float64)
    Z = torch.zeros(1, 3, dtype=torch.float64)

    def run(opts=None, F=Z, initial=None):
        return fused_mod.fused_solve(sc, tubes, D, A, F, Z, opts or tp.SolverOptions(),
                                     initial, plan)

    assert run() is not None
    assert run(tp.SolverOptions(accuracy=1e-10)) is None            # order 2 is not enough
    assert run(F=torch.tensor([[0.0, 0.1, 0.0]], dtype=torch.float64)) is None
    eq3 = tp.solve(sc, options=tp.SolverOptions(order=3))
    assert run(tp.SolverOptions(order=2), initial=eq3) is None     # another basis order
    assert run(initial=eq3) is not None                            # continues at its order
    assert run(tp.SolverOptions(kernel="newton")) is None
    assert run(tp.SolverOptions(force_model="paper")) is None
    big = fused_mod.MAX_BATCH + 1                                   # the rounds are faster
    assert fused_mod.fused_solve(sc, tubes, D.expand(big, 2).clone(), A.expand(big, 2).clone(),
                                 Z.expand(big, 3).clone(), Z.expand(big, 3).clone(),
                                 tp.SolverOptions(), None, plan) is None


def test_fused_result_supports_gradients_jacobians_and_warm_starts(monkeypatch):
    """What an Equilibrium offers after the fused path: its Jacobians (the kink side's layout
    built on demand) equal those after the rounds; it warm-starts the next solve; its stiffness
    eigenvalue and backbone are there; a solve that needs a gradient does not take the path
    and still differentiates."""
    sc = tp.load_scene("renda2021_fig3")
    a, b, taken = _both(monkeypatch, sc, rotation=[0.0, 1.0])
    assert taken
    ja, jb = a.jacobians(compliance=False), b.jacobians(compliance=False)
    for name in ("actuator_stiffness", "tip_jacobian"):
        x, y = getattr(ja, name), getattr(jb, name)
        assert float((x - y).abs().max()) <= 1e-8 * max(1.0, float(y.abs().max())), name
    nxt = tp.solve(sc, rotation=[0.0, 1.01], initial=a)
    assert bool(nxt.converged.all()) and int(nxt.iterations.max()) <= 2
    assert torch.allclose(a.min_stiffness_eigenvalue, b.min_stiffness_eigenvalue, rtol=1e-10)
    assert torch.allclose(a.backbone(20), b.backbone(20), rtol=0, atol=1e-12)
    rot = torch.tensor([[0.0, 1.0]], dtype=torch.float64, requires_grad=True)
    called = []
    real = fused_mod.fused_solve
    monkeypatch.setattr(solver_mod, "fused_solve",
                        lambda *x, **k: called.append(1) or real(*x, **k))
    eq = tp.solve(sc, rotation=rot)
    assert not called
    eq.tip_position.sum().backward()
    assert torch.isfinite(rot.grad).all() and float(rot.grad.abs().max()) > 0


@pytest.mark.parametrize("case", ["fig3_kink", "fig3_off_kink", "random1", "random4"])
def test_compiled_control_blocks_equal_the_torch_closed_forms(case):
    """``Equilibrium.jacobians`` takes its actuator stiffness and tip Jacobian from one compiled
    call (fused.control_blocks through the solve's resolver) where it applies; they equal the
    torch closed forms of torchpvs/jacobians.py (``_one_sided`` with ``_control_blocks_here``,
    one-sided at kinks) on the same equilibrium, to 1e-9 of each block's scale, and finite
    differences of solves confirm the tip Jacobian's rotation columns (smooth there)."""
    from torchpvs import jacobians as jac_mod
    if case.startswith("fig3"):
        sc = tp.load_scene("renda2021_fig3")
        D = torch.tensor([sc.actuation.insertion], dtype=torch.float64)
        if case == "fig3_off_kink":
            D = D + torch.tensor([[2e-3, 2e-3]], dtype=torch.float64)
        A = torch.tensor([[0.0, 0.7], [0.3, -1.2]], dtype=torch.float64)
        D = D.expand(2, 2).clone()
    else:
        sc = random_scene(int(case[-1]))
        D, A = feasible_actuations(np.random.default_rng(5), 3, sc)
        D, A = torch.from_numpy(D), torch.from_numpy(A)
    eq = tp.solve(sc, insertion=D, rotation=A)
    out = fused_mod.control_blocks(eq)
    assert out is not None
    K, J = out
    rows = torch.arange(len(eq))
    K_ref, J_ref = jac_mod._one_sided(eq, rows, jac_mod._control_blocks_here)
    assert bool(eq.force_kink.any()) == (case == "fig3_kink") or not case.startswith("fig3")
    for x, y in ((K, K_ref), (J, J_ref)):
        assert float((x - y).abs().max()) <= 1e-9 * float(y.abs().max())
    cj = eq.jacobians(compliance=False)
    assert torch.equal(cj.actuator_stiffness, K) and torch.equal(cj.tip_jacobian, J)
    # rotation columns by central differences of warm solves of the same discrete model
    N, h = sc.n_tubes, 1e-5
    opts = tp.SolverOptions(order=eq.order, n_magnus=eq.context.discretization.n_magnus,
                            tol=1e-13)
    for j in range(N):
        e = torch.zeros_like(A)
        e[:, j] = h
        tp_ = tp.solve(sc, insertion=D, rotation=A + e, initial=eq, options=opts).tip_position
        tm_ = tp.solve(sc, insertion=D, rotation=A - e, initial=eq, options=opts).tip_position
        fd = (tp_ - tm_) / (2 * h)
        assert float((J[:, :3, N + j] - fd).abs().max()) <= 1e-6 * float(fd.abs().max()) + 1e-12


@pytest.mark.parametrize("scene_fn", [fig3, lambda: nested_scene(3, seed=2)],
                         ids=["fig3", "three_tubes"])
def test_the_compiled_kink_plan_is_the_torch_one(scene_fn):
    """The fused path's (and the tracker's) kink analysis, a compiled mask and compiled sides
    (``fused._kinks``, ``tracker.kink_sides``), against ``forces.kink_plan`` in torch, which
    the rounds use: the same kink mask, blocked carriages, side rows and side insertions, bit
    for bit, at insertions that put every tube's base, straight-to-curved transition and end
    at the orifice, bases blocked by the next one, and ordinary insertions."""
    from torchpvs.forces import KINK_DELTA, KINK_TOL, kink_plan
    scene = scene_fn()
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    tubes = plan.tubes
    L = tubes.length.numpy().reshape(-1)
    Ls = tubes.straight.numpy().reshape(-1)
    rng = np.random.default_rng(4)
    N = scene.n_tubes
    special = np.concatenate([[0.0], L, Ls, L - 1e-8, Ls + 1e-8])
    D = rng.choice(special, size=(200, N))
    D[::3] = rng.uniform(0.0, L.min(), size=D[::3].shape)
    D = np.minimum(np.maximum.accumulate(D, -1), L)            # the nesting rule
    D[5, 1:] = D[5, 0]                                         # blocked bases
    D = np.ascontiguousarray(np.maximum.accumulate(D, -1))
    kink, blocked, sel, sj, Dn, n_r = fused_mod._kinks(tubes, D, plan)
    kp = kink_plan(tubes, torch.from_numpy(D), KINK_DELTA, KINK_TOL)
    assert kink.any() and blocked.any() and n_r > 0
    np.testing.assert_array_equal(kink, kp.kink.numpy())
    np.testing.assert_array_equal(blocked, kp.blocked.numpy())
    np.testing.assert_array_equal(sel, kp.sel.numpy())
    np.testing.assert_array_equal(sj, kp.sj.numpy())
    np.testing.assert_array_equal(Dn, kp.Dn.numpy())
    assert n_r == len(kp.rows_b)
