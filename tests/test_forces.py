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
from torchpvs.forces import envelope_forces_autograd, envelope_forces_closed_form
from torchpvs.testing import scene_strategy


def _state(eq, q=None) -> dict:
    """The solution dict the force functions read, from a solved Equilibrium."""
    c = eq._ctx
    info = c["implicit_info"]
    return {"q": eq.q if q is None else q, "D": c["D"], "alpha": c["alpha"], "F": c["F"],
            "M": c["M"], "loaded": info["loaded"], "disc": c["disc"], "tab": c["tab"],
            "lay": c["lay"], "has_moment": info["has_moment"], "with_load": info["with_load"]}


def _assert_same(eq, q=None):
    tubes = eq._ctx["tubes"]
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
    _assert_same(eq, eq.q + 0.3 * noise * eq._ctx["lay"].qmask)


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


def test_loaded_solves_keep_the_reverse_pass():
    """With a tip load the work moves with D through the Magnus chain: the solver then uses the
    reverse pass, and its forces equal it exactly."""
    scene = tp.load_scene("renda2021_fig3")
    eq = tp.solve(scene, rotation=torch.tensor([0.0, 1.0], dtype=torch.float64),
                  tip_force=torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64),
                  insertion=torch.tensor([0.05, 0.06], dtype=torch.float64))
    ref, _ = envelope_forces_autograd(eq._ctx["tubes"], _state(eq))
    assert torch.equal(eq.actuation_forces, ref)
