"""Stage 5a, ``torchpvs.kernel``: the kernel seam and the eager kernel's own functions.

What is tested, and against what:

- the registry (``KERNELS``): every registered name is accepted by ``SolverOptions(kernel=)``
  and holds a ``Kernel`` of callables; the compiled kernel keeps the eager functions it does
  not replace (the module's documented contract);
- ``newton_step``: Newton's quadratic convergence, from perturbations of a separately
  converged solve (``tol=1e-14``): the error after one step is ``C e0^2`` with the same ``C``
  over two decades of ``e0`` (so the error ratio ``e1 / e0`` falls 10x when ``e0`` does), at
  stable equilibria (the Cholesky path) and at unstable equilibria of the section III-B robot
  (the indefinite Hessian's LU path); a converged solution is a fixed point of the step;
  rows of a batch are independent (a failing row does not touch the others);
- ``EAGER`` against ``COMPILED``: the same equilibria (tips within 1e-12 m) on configurations
  of the Fig. 3 robot, a seeded random three-tube robot and a warm start;
- ``default_guess``: finite in float64 and float32 on a batch with padded compact sections,
  and, where the torsionless bending is the exact equilibrium (tubes whose precurvatures lie
  in one plane, aligned: no torsion arises, eq. 31), equal to a converged solve.
"""

from __future__ import annotations

import math

import pytest
import torch

import torchpvs as tp
from torchpvs import compiled
from torchpvs.kernel import COMPILED, EAGER, KERNELS, Kernel, default_guess, newton_step
from torchpvs.newton import Problem
from torchpvs.plan import plan_for
from torchpvs.sections import n_coordinates
from torchpvs.testing import random_scene, two_tubes

DT = torch.float64
CPU = torch.device("cpu")
pytestmark = pytest.mark.usefixtures("one_thread_module")


def problem_at(eq: tp.Equilibrium, scene: tp.Scene) -> Problem:
    """The kernel's Problem of a solve's own discretization and actuation (the same
    construction as torchpvs.order_control.solve_order)."""
    ctx, info = eq.context, eq.context.implicit
    plan = plan_for(scene, eq.q.dtype, CPU)
    lay, maps = plan.layout(plan.tubes, ctx.insertion, ctx.rotation, ctx.tip_force,
                            ctx.tip_moment, info.loaded, ctx.discretization, eq.q.shape[-1])
    return Problem(lay, ctx.tables, maps, info.with_load, info.has_moment)


def perturbation(eq: tp.Equilibrium, prob: Problem, seed: int = 0) -> torch.Tensor:
    """A seeded random direction on the active coordinates, of the size of each solution."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.randn(eq.q.shape, generator=gen, dtype=DT) * prob.lay.qmask
    return d / d.norm(dim=-1, keepdim=True) * eq.q.norm(dim=-1, keepdim=True)


def tight(**kw) -> tp.SolverOptions:
    return tp.SolverOptions(order=3, n_magnus=16, tol=1e-14, compute_forces=False,
                            kernel="newton", **kw)


def test_registry_holds_kernels_of_callables_accepted_by_the_options():
    assert {"newton", "compiled"} <= set(KERNELS)
    assert KERNELS["newton"] is EAGER and KERNELS["compiled"] is COMPILED
    for name, kern in KERNELS.items():
        assert isinstance(kern, Kernel), name
        assert all(callable(getattr(kern, f)) for f in Kernel._fields), name
        assert tp.SolverOptions(kernel=name).kernel == name
    # The compiled kernel replaces the layout and maps, the Newton solve, step, new-section
    # step, pose, force partials, the stiffness's actuator rows, the tip partials and the tip
    # load's rows (which the eager kernel leaves to autograd), and reuses the rest.
    replaced = ("layout", "solve", "step", "section_step", "pose", "partials",
                "actuation_rows", "tip_partials", "load_rows")
    for f in Kernel._fields:
        same = getattr(COMPILED, f) is getattr(EAGER, f)
        assert same == (f not in replaced), f


def test_newton_step_converges_quadratically_at_stable_equilibria():
    """e1 = |q1 - q*| against e0 = |q0 - q*| for q0 = q* + eps d: e1 / e0^2 stays within 25 %
    of its value over eps = 1e-1 .. 1e-3 (measured: constant to 12 %), and e1 / e0 shrinks
    with e0 (superlinear), on four Fig. 3 configurations."""
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, a] for a in (0.3, 1.4, 2.5, 3.6)], dtype=DT)
    eq = tp.solve(sc, rotation=rot, options=tight())
    assert bool(eq.converged.all()) and bool(eq.stable.all())
    prob = problem_at(eq, sc)
    d = perturbation(eq, prob)
    consts, ratios = [], []
    for eps in (1e-1, 1e-2, 1e-3):
        q0 = eq.q + eps * d
        q1, ok = newton_step(q0, prob)
        assert bool(ok.all())
        e0, e1 = (q0 - eq.q).norm(dim=-1), (q1 - eq.q).norm(dim=-1)
        consts.append(e1 / e0 ** 2)
        ratios.append(e1 / e0)
    c = torch.stack(consts)
    assert bool((c.amax(0) < 1.25 * c.amin(0)).all()), c
    assert bool((ratios[0] < 0.05).all()), ratios[0]        # a contraction from the start
    for a, b in zip(ratios, ratios[1:], strict=False):
        assert bool((b < 0.15 * a).all()), (a, b)           # 10x smaller e0: ~10x smaller ratio


def test_newton_step_converges_quadratically_at_unstable_equilibria():
    """Unstable equilibria of the section III-B robot (reached with method="root"; the
    smallest stiffness eigenvalue is negative, so the Cholesky fails and the step takes the
    LU path): the same quadratic law."""
    sc = tp.load_scene("renda2021_section3b")
    a2 = torch.linspace(math.radians(150.0), math.radians(190.0), 8, dtype=DT)
    rot = torch.stack([torch.zeros_like(a2), a2], -1)
    eq = tp.solve(sc, rotation=rot, options=tight(method="root", on_failure="ignore"))
    pick = (eq.converged & ~eq.stable & (eq.min_stiffness_eigenvalue < 0)).nonzero().flatten()
    assert pick.numel() >= 2, eq.min_stiffness_eigenvalue
    eq = tp.solve(sc, rotation=rot[pick], initial=eq.q[pick],
                  options=tight(method="root"))
    assert bool(eq.converged.all()) and not bool(eq.stable.any())
    prob = problem_at(eq, sc)
    d = perturbation(eq, prob, seed=1)
    consts = []
    for eps in (1e-2, 1e-3, 1e-4):
        q0 = eq.q + eps * d
        q1, ok = newton_step(q0, prob)
        assert bool(ok.all())
        e0, e1 = (q0 - eq.q).norm(dim=-1), (q1 - eq.q).norm(dim=-1)
        assert bool((e1 < 0.1 * e0).all()), (eps, e1 / e0)
        consts.append(e1 / e0 ** 2)
    c = torch.stack(consts)
    assert bool((c.amax(0) < 1.5 * c.amin(0)).all()), c


def test_a_converged_solution_is_a_fixed_point_of_the_newton_step():
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.7], [0.0, 4.0]], dtype=DT)
    eq = tp.solve(sc, rotation=rot, options=tight())
    q1, ok = newton_step(eq.q, problem_at(eq, sc))
    assert bool(ok.all())
    assert float((q1 - eq.q).abs().max()) <= 1e-10 * float(eq.q.abs().max())


def test_newton_step_rows_are_independent_and_a_failed_row_is_returned_unchanged():
    """A row of non-finite coordinates fails (ok False) and comes back as it went in; the
    other rows get exactly the step they get in a batch of their own."""
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.5], [0.0, 2.0], [0.0, 3.0]], dtype=DT)
    eq = tp.solve(sc, rotation=rot, options=tight())
    prob = problem_at(eq, sc)
    q0 = eq.q + 0.05 * perturbation(eq, prob, seed=2)
    alone, ok_alone = newton_step(q0.clone(), prob)
    bad = q0.clone()
    bad[1] = float("inf")
    q1, ok = newton_step(bad, prob)
    assert ok.tolist() == [True, False, True] and bool(ok_alone.all())
    assert torch.equal(q1[1], bad[1])
    assert torch.allclose(q1[[0, 2]], alone[[0, 2]], rtol=0, atol=1e-14)


@pytest.mark.skipif(not compiled.available(), reason="numba is not installed")
@pytest.mark.parametrize("case", ["fig3_cold", "random3_cold", "fig3_warm"])
def test_eager_and_compiled_kernels_reach_the_same_equilibria(case):
    if case.startswith("fig3"):
        sc = tp.load_scene("renda2021_fig3")
        rot = torch.tensor([[0.0, a] for a in (0.1, 1.2, 2.3, 3.4, 4.5)], dtype=DT)
    else:
        sc = random_scene(3)
        gen = torch.Generator().manual_seed(3)
        rot = (torch.rand(4, sc.n_tubes, generator=gen, dtype=DT) - 0.5) * 2 * math.pi
    out = {}
    for k in ("newton", "compiled"):
        opts = tp.SolverOptions(kernel=k, compute_forces=False)
        if case.endswith("warm"):
            e0 = tp.solve(sc, rotation=rot, options=opts)
            out[k] = tp.solve(sc, rotation=rot + math.radians(2.0), options=opts, initial=e0)
        else:
            out[k] = tp.solve(sc, rotation=rot, options=opts)
    e, c = out["newton"], out["compiled"]
    assert bool(e.converged.all()) and torch.equal(e.converged, c.converged)
    assert e.order == c.order
    assert float((e.tip_position - c.tip_position).abs().max()) <= 1e-12


def guess_inputs(scene, rot, D, dtype, order=2):
    B, N = rot.shape
    Z = torch.zeros(B, 3, dtype=dtype)
    disc = tp.SolverOptions().discretization(order)
    nq = n_coordinates(N, disc.n_basis)
    plan = plan_for(scene, dtype, CPU)
    lay, maps = plan.layout(plan.tubes, D.to(dtype), rot.to(dtype), Z, Z,
                            torch.zeros(B, dtype=torch.bool), disc, nq)
    return lay, maps, disc.tables(dtype, CPU), disc, N


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_default_guess_is_finite_with_padded_compact_sections(dtype):
    """A batch whose elements have different numbers of sections (insertions from fully
    inserted to the inner tube's precurved part alone exposed) pads the compact sections of
    the shorter ones; the guess is finite there and zero on every inactive coordinate."""
    sc = tp.load_scene("renda2021_fig3")
    D = torch.tensor([[0.0, 0.0], [0.0935, 0.2085], [0.15, 0.25], [0.18, 0.29]], dtype=DT)
    rot = torch.tensor([[0.0, 0.3], [1.0, 2.0], [-1.0, 3.0], [0.5, -2.5]], dtype=DT)
    lay, maps, tab, disc, N = guess_inputs(sc, rot, D, dtype)
    assert int((lay.qmask.sum(-1)).unique().numel()) > 1       # the batch is mixed
    q = default_guess(lay, maps, tab, disc, N)
    assert q.dtype == dtype and bool(torch.isfinite(q).all())
    assert bool((q[lay.qmask == 0] == 0).all())
    assert bool((q.abs().sum(-1) > 0).all())                   # precurved tubes bend


@pytest.mark.parametrize("alpha", [0.0, 1.1])
def test_default_guess_is_the_equilibrium_when_no_torsion_arises(alpha):
    """Two tubes with precurvatures in one plane, turned together by ``alpha``: the bending
    planes agree, no torsion arises, and the stiffness-weighted precurvature is the exact
    equilibrium (eq. 31). Reference: the converged solve at the same discretization."""
    sc = two_tubes(9.9, 13.8, Lc1=0.1, Lc2=0.15, D=(0.0, 0.02), alpha=(alpha, alpha))
    rot = torch.tensor([[alpha, alpha]], dtype=DT)
    D = torch.tensor([[0.0, 0.02]], dtype=DT)
    eq = tp.solve(sc, insertion=D, rotation=rot, options=tp.SolverOptions(
        order=2, n_magnus=8, tol=1e-14, compute_forces=False, kernel="newton"))
    lay, maps, tab, disc, N = guess_inputs(sc, rot, D, DT)
    q = default_guess(lay, maps, tab, disc, N)
    assert q.shape == eq.q.shape
    assert float((q - eq.q).abs().max()) <= 1e-9 * float(eq.q.abs().max())
