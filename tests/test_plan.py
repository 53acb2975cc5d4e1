"""The robot plan (torchpvs/plan.py): what a solve reuses from one call to the next."""

from __future__ import annotations

import torch

import torchpvs as tp
from torchpvs.plan import plan_for
from torchpvs.sections import n_coordinates


def test_plan_cache_keeps_constants_per_reused_layout_only():
    """Plan.cached computes once per reused layout (warm calls at the same insertions) and
    afresh for a layout the plan did not return (another insertion state); a cached value is
    the computed one."""
    scene = tp.load_scene("renda2021_fig3")
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    disc = tp.SolverOptions().discretization(2)
    D = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    Z = torch.zeros(1, 3, dtype=torch.float64)
    off = torch.zeros(1, dtype=torch.bool)
    nq = n_coordinates(2, disc.n_basis)
    calls = []

    def compute():
        calls.append(1)
        return torch.tensor(float(len(calls)))

    with torch.no_grad():
        lay1, _ = plan.layout(plan.tubes, D, torch.zeros(1, 2, dtype=torch.float64), Z, Z, off,
                              disc, nq)
        assert float(plan.cached(disc, lay1, "x", compute)) == 1.0
        lay2, _ = plan.layout(plan.tubes, D, torch.ones(1, 2, dtype=torch.float64), Z, Z, off,
                              disc, nq)                    # rotation only: the layout is reused
        assert float(plan.cached(disc, lay2, "x", compute)) == 1.0 and len(calls) == 1
        lay3, _ = plan.layout(plan.tubes, D * 0.9, torch.ones(1, 2, dtype=torch.float64), Z, Z,
                              off, disc, nq)               # new insertions: a new layout
        assert float(plan.cached(disc, lay3, "x", compute)) == 2.0
        assert float(plan.cached(disc, lay1, "x", compute)) == 3.0   # no longer the plan's


def test_warm_solves_with_cached_pose_constants_match_a_fresh_plan():
    """The step-count check's constants cached on the plan give the same equilibrium, error
    estimate and tip as a solve on a fresh (private) plan."""
    from torchpvs.plan import Plan
    from torchpvs.solver import solve_tensors

    scene = tp.load_scene("renda2021_fig3")
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    eq = tp.solve(scene, rotation=rot)
    for k in range(3):
        eq = tp.solve(scene, rotation=rot + 0.05 * (k + 1), initial=eq)
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    D = torch.tensor([scene.actuation.insertion], dtype=torch.float64)
    Z = torch.zeros(1, 3, dtype=torch.float64)
    fresh = solve_tensors(scene, plan.tubes, D, (rot + 0.15)[None], Z, Z, tp.SolverOptions(),
                          None, Plan(plan.tubes))
    assert torch.allclose(eq.tip_position, fresh.tip_position, rtol=0, atol=1e-9)
    assert torch.allclose(eq.error_estimate, fresh.error_estimate, rtol=1e-3, atol=1e-12)


def test_tube_rows_equal_in_value_reuse_the_layout_and_others_do_not(monkeypatch):
    """The one-sided kink forces re-solve rows of the plan's tubes (``tube_rows``: a new
    object each call) at the same insertions on every warm solve: the layout is reused while
    the tube values are equal, rebuilt when they differ. At the Fig. 3 actuation the outer
    tube's straight-to-curved transition sits at the orifice (a kink), so a warm solve at a
    new rotation rebuilds no layout, and its forces equal a fresh plan's."""
    import torchpvs.compiled_layout as compiled_layout
    import torchpvs.mechanics as mechanics
    import torchpvs.plan as plan_mod
    import torchpvs.solver as solver_mod
    from torchpvs.sections import tube_rows

    # the driver's rounds (the fused path, torchpvs.fused, takes the kink sides in compiled
    # code and keeps no layout of them)
    monkeypatch.setattr(solver_mod, "fused_solve", lambda *a, **k: None)

    scene = tp.load_scene("renda2021_fig3")
    built = []
    # every layout builder: the eager one (also the default of Plan.layout) and the compiled
    # kernel's
    for mod, name in ((mechanics, "build_layout"), (compiled_layout, "layout_and_maps")):
        real = getattr(mod, name)
        monkeypatch.setattr(mod, name, lambda *a, _r=real, **k: built.append(1) or _r(*a, **k))
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    disc = tp.SolverOptions().discretization(2)
    D = torch.tensor([scene.actuation.insertion] * 2, dtype=torch.float64)
    A = torch.zeros(2, 2, dtype=torch.float64)
    Z = torch.zeros(2, 3, dtype=torch.float64)
    off = torch.zeros(2, dtype=torch.bool)
    nq = n_coordinates(2, disc.n_basis)
    rows = torch.tensor([0, 0])
    with torch.no_grad():
        plan.layout(tube_rows(plan.tubes, rows), D, A, Z, Z, off, disc, nq)
        plan.layout(tube_rows(plan.tubes, rows), D, A + 1, Z, Z, off, disc, nq)
        assert len(built) == 1                                   # equal values: reused
        other = plan.tubes.map(lambda t: t * 1.01).map(lambda t: t.expand(2, *t.shape[1:]))
        plan.layout(other, D, A, Z, Z, off, disc, nq)
        assert len(built) == 2                                   # other values: rebuilt

    built.clear()
    eq0 = tp.solve(scene)
    assert built                                                 # the spies see the kernel's
    assert bool(eq0.force_kink.any())
    built.clear()
    eq1 = tp.solve(scene, rotation=[0.0, 1.5], initial=eq0)
    assert not built                                             # main and sides reused
    monkeypatch.setattr(plan_mod, "_PLANS", type(plan_mod._PLANS)())  # a fresh plan
    ref = tp.solve(scene, rotation=[0.0, 1.5], initial=eq0)
    assert torch.equal(eq1.actuation_forces, ref.actuation_forces)
    assert torch.equal(eq1.actuation_forces_insertion, ref.actuation_forces_insertion)


def test_a_reused_layout_is_the_layout_built_afresh():
    """``Plan.reused_layout`` (the actuator stiffness reads the solve's layout instead of
    building one): after a solve, every field equals ``build_layout`` at the same insertions
    with the new rotations and no load; at other insertions there is none."""
    from torchpvs.sections import build_layout
    sc = tp.load_scene("renda2021_fig3")
    D = torch.tensor([[0.05, 0.15], [0.02, 0.2]], dtype=torch.float64)
    eq = tp.solve(sc, insertion=D, rotation=torch.zeros(2, 2, dtype=torch.float64))
    ctx, info = eq.context, eq.context.implicit
    A = torch.tensor([[0.4, -1.0], [2.0, 0.3]], dtype=torch.float64)
    lay = ctx.plan.reused_layout(ctx.tubes, D, A, info.loaded, info.disc)
    zero = torch.zeros(2, 3, dtype=torch.float64)
    ref = build_layout(ctx.tubes, D, A, zero, zero, info.loaded, info.disc)
    for name, a, b in zip(ref._fields, lay, ref, strict=True):
        assert a.shape == b.shape and torch.allclose(a.to(b.dtype), b, rtol=1e-15, atol=0), name
    assert ctx.plan.reused_layout(ctx.tubes, D + 1e-3, A, info.loaded, info.disc) is None


def test_rows_of_a_kept_layout_are_the_layout_built_afresh(monkeypatch):
    """The one-sided forces re-solve both sides of the Fig. 3 kink in one batch of 2; the
    control Jacobians then ask for the retraction side alone (a batch of 1). ``reused_layout``
    returns that row of the kept layout: every field equals ``build_layout`` there, and the
    control step builds no layout of its own. Rows that no kept layout holds get None."""
    import torchpvs.jacobians as jac_mod
    import torchpvs.solver as solver_mod
    from torchpvs.sections import build_layout

    # the driver's rounds (the fused path keeps no layout of the kink sides)
    monkeypatch.setattr(solver_mod, "fused_solve", lambda *a, **k: None)
    sc = tp.load_scene("renda2021_fig3")
    eq0 = tp.solve(sc)
    eq = tp.solve(sc, rotation=[0.0, 1.0], initial=eq0)
    assert bool(eq.force_kink.any())
    ctx, info = eq.context, eq.context.implicit
    D = ctx.insertion + torch.tensor([[1e-7, 0.0]], dtype=torch.float64)   # the side
    A = torch.tensor([[0.3, -0.7]], dtype=torch.float64)
    lay = ctx.plan.reused_layout(ctx.tubes, D, A, info.loaded, info.disc)
    assert lay is not None
    zero = torch.zeros(1, 3, dtype=torch.float64)
    ref = build_layout(ctx.tubes, D, A, zero, zero, info.loaded, info.disc)
    for name, a, b in zip(ref._fields, lay, ref, strict=True):
        assert a.shape == b.shape and torch.allclose(a.to(b.dtype), b, rtol=1e-15, atol=0), name
    both = torch.cat([D, ctx.insertion + torch.tensor([[3e-7, 0.0]], dtype=torch.float64)])
    assert ctx.plan.reused_layout(ctx.tubes, both, A.expand(2, 2), info.loaded.expand(2),
                                  info.disc) is None
    built = []
    real = jac_mod.build_layout
    monkeypatch.setattr(jac_mod, "build_layout",
                        lambda *a, **k: built.append(1) or real(*a, **k))
    eq.jacobians(compliance=False)
    assert not built
