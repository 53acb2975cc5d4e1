"""torchpvs.forces: the closed-form envelope forces against the reverse pass they replace.

Reference: ``envelope_forces_autograd``, the partial derivatives dU/dD, dU/dalpha at fixed ``q``
by reverse-mode autograd through ``build_layout`` and the potential (an independent evaluation:
no hand-derived term). The identity holds at any ``q``, not only at equilibria, so the property
test also checks perturbed coordinates. Physics references for the forces themselves (Table II,
closed forms, the standard model) live in test_paper_forces.py and test_pvs_vs_reference.py."""

import math

import torch
from hypothesis import HealthCheck, given, settings

import torchpvs as tp
from torchpvs.forces import (
    ForceState,
    closed_form_partials,
    envelope_forces_autograd,
    envelope_forces_closed_form,
)
from torchpvs.testing import scene_strategy


def _state(eq, q=None) -> ForceState:
    """The state the force functions read, from a solved Equilibrium."""
    c = eq.context
    info = c.implicit
    return ForceState(q=eq.q if q is None else q, D=c.insertion, alpha=c.rotation,
                      F=c.tip_force, M=c.tip_moment, loaded=info.loaded,
                      disc=c.discretization, tab=c.tables, lay=c.layout,
                      has_moment=info.has_moment, with_load=info.with_load)


def _assert_same(eq, q=None):
    tubes = eq.context.tubes
    ref = envelope_forces_autograd(tubes, _state(eq, q))
    got = envelope_forces_closed_form(tubes, _state(eq, q))
    for r, g, name in zip(ref, got, ("tau_D [N]", "tau_alpha [N m]"), strict=True):
        # relative to the largest value, with a 1e-3 floor for scenes whose forces vanish
        tol = 1e-9 * (float(r.abs().max()) + 1e-3)
        assert (r - g).abs().max() <= tol, (name, r, g)


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene_strategy())
def test_closed_form_matches_reverse_pass(d):
    """Random unloaded scenes (1-3 tubes, straight/curved/mixed, linear precurvature, curved
    material held in the guide, retracted tubes, equal insertions): at the equilibrium and at
    coordinates perturbed off it."""
    d.pop("load", None)
    eq = tp.solve(tp.Scene.from_dict(d), options=tp.SolverOptions(on_failure="ignore", order=2))
    _assert_same(eq)
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(eq.q.shape, generator=g, dtype=eq.q.dtype)
    _assert_same(eq, eq.q + 0.3 * noise * eq.context.layout.qmask)


def test_closed_form_matches_on_a_batch_across_the_workspace():
    """Fig. 3 robot, 48 insertions (outer base from the orifice to past its straight part, so
    that its curved part is partly held in the guide) and rotations over the full circle."""
    scene = tp.load_scene("renda2021_fig3")
    g = torch.Generator().manual_seed(1)
    B = 48
    Ls = scene.tubes[0].straight_length
    D1 = torch.rand(B, generator=g, dtype=torch.float64) * (Ls + 0.03)
    D = torch.stack([D1, D1 + torch.rand(B, generator=g, dtype=torch.float64) * 0.05], -1)
    A = (torch.rand(B, 2, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    eq = tp.solve(scene, insertion=D, rotation=A, options=tp.SolverOptions(on_failure="ignore"))
    assert bool((D[:, 0] > Ls).any()) and bool((D[:, 0] < Ls).any())
    _assert_same(eq)


def _assert_tip_force_same(eq, q=None):
    """The tip-force path (elastic closed form minus ``F . P_x``) of both kernels' tip
    partials against the reverse pass through the loaded potential, to 1e-9 relative."""
    from torchpvs.forces import envelope_forces_tip_force
    from torchpvs.kernel import KERNELS
    tubes = eq.context.tubes
    ref = envelope_forces_autograd(tubes, _state(eq, q))
    for kernel in KERNELS.values():
        got = envelope_forces_tip_force(tubes, _state(eq, q), kernel.partials,
                                        kernel.tip_partials)
        for r, g, name in zip(ref, got, ("tau_D [N]", "tau_alpha [N m]"), strict=True):
            tol = 1e-9 * (float(r.abs().max()) + 1e-3)
            assert (r - g).abs().max() <= tol, (name, r, g)


@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
@given(scene_strategy())
def test_tip_force_path_matches_reverse_pass(d):
    """Random scenes under a dead tip force (coordinates on the distal sections): the forces'
    closed form of the elastic energy minus the work along the tip partials equals the reverse
    pass through the loaded potential, at the equilibrium and off it, on both kernels."""
    d["load"] = {"tip_force": [0.2, -0.1, 0.3], "tip_moment": [0.0, 0.0, 0.0]}
    eq = tp.solve(tp.Scene.from_dict(d), options=tp.SolverOptions(on_failure="ignore", order=2))
    assert eq.context.implicit.with_load and not eq.context.implicit.has_moment
    _assert_tip_force_same(eq)
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(eq.q.shape, generator=g, dtype=eq.q.dtype)
    _assert_tip_force_same(eq, eq.q + 0.3 * noise * eq.context.implicit.qmask)


def test_loaded_solves_use_the_tip_force_path_and_a_moment_the_reverse_pass():
    """With a tip force the solver's forces are the tip-force path's (to rounding of the
    reverse pass, 1e-9); with a tip moment (not conservative) the reverse pass itself."""
    scene = tp.load_scene("renda2021_fig3")
    kw = dict(rotation=torch.tensor([0.0, 1.0], dtype=torch.float64),
              insertion=torch.tensor([0.05, 0.06], dtype=torch.float64))
    eq = tp.solve(scene, tip_force=torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64), **kw)
    ref, _ = envelope_forces_autograd(eq.context.tubes, _state(eq))
    torch.testing.assert_close(eq.actuation_forces, ref, rtol=1e-9, atol=1e-12)
    eq = tp.solve(scene, tip_moment=torch.tensor([0.0, 0.01, 0.0], dtype=torch.float64), **kw)
    ref, _ = envelope_forces_autograd(eq.context.tubes, _state(eq))
    assert torch.equal(eq.actuation_forces, ref)


def test_closed_form_second_derivatives_match_double_backward():
    """One reverse pass through closed_form_partials (what actuator_stiffness uses) gives the
    same U_Dq, U_DD, U_Dalpha as a double backward through the potential."""
    from torchpvs.mechanics import potential
    from torchpvs.sections import build_layout

    scene = tp.load_scene("renda2021_fig3")
    g = torch.Generator().manual_seed(2)
    B = 16
    D = torch.sort(torch.rand(B, 2, generator=g, dtype=torch.float64) * 0.08 + 0.01, -1).values
    A = (torch.rand(B, 2, generator=g, dtype=torch.float64) - 0.5) * 4
    eq = tp.solve(scene, insertion=D, rotation=A,
                  options=tp.SolverOptions(order=2, n_magnus=8, on_failure="ignore"))
    st = _state(eq)
    tubes, tab, disc = eq.context.tubes, st.tab, st.disc
    out = []
    for way in ("closed form", "double backward"):
        q, Dg, Ag = (t.detach().clone().requires_grad_(True) for t in (eq.q, st.D, st.alpha))
        lay = build_layout(tubes, Dg, Ag, st.F, st.M, st.loaded, disc)
        if way == "closed form":
            tau = closed_form_partials(
                q, lay, tubes, tab, disc)[0]
        else:
            U = potential(q, lay, tab, None, False)
            tau = torch.autograd.grad(U.sum(), Dg, create_graph=True)[0]
        rows = [torch.autograd.grad(tau[:, j].sum(), (q, Dg, Ag), retain_graph=True)
                for j in range(2)]
        out.append([torch.stack([r[k] for r in rows], 1) for k in range(3)])
    for a, b in zip(*out, strict=True):
        assert (a - b).abs().max() <= 1e-10 * b.abs().max(), (a - b).abs().max()
