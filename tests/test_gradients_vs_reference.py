"""Implicit-function gradients of the PVS tip against central finite differences of the
independent standard-model reference ("gradients match central finite
differences of the reference solver on random scenes, 1e-4 relative").

The PVS side is one high-accuracy solve differentiated by the custom backward
(``torchpvs/implicit.py``: adjoint with the stiffness at the solution); the reference side never
touches torch: it re-solves the Kirchhoff shooting problem (tol 1e-12, warm-started on the same
branch) at ``x +- h`` for every insertion, rotation and the outer tube's Young's modulus.
Scenes: the seeded random 2-/3-tube robots of ``test_pvs_vs_reference.py``, skipping those with a
kink within 1 mm of the orifice (U* is not differentiable there: docs/physics.md, "Kinks"), those at
a nesting limit, and those where the reference cannot be put on PVS's stable branch.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_pvs_vs_reference import matched_reference, near_kink, random_scene

import torchpvs
from torchpvs import SolverOptions
from torchpvs.reference import solve_standard

ACCURATE = SolverOptions(order=6, n_magnus=32, compute_forces=False)


def _smooth(scene) -> bool:
    """No kink within 1 mm of the orifice and no two bases together (``D_j = D_j-1`` is the
    nesting limit of docs/conventions.md: only one-sided derivatives exist there)."""
    return not near_kink(scene) and bool(np.diff(scene.actuation.insertion).min() > 1e-3)


SEEDS = [s for s in range(16) if _smooth(random_scene(s))][:6]
REL_TOL = 1e-4


def _reference_tip(scene, warm) -> np.ndarray:
    r = solve_standard(scene, tol=1e-12, initial=warm, compute_forces=False,
                       compute_stability=False)
    assert r.converged, r
    return np.asarray(r.tip_position)


def _central(scene, warm, perturb, h: float) -> np.ndarray:
    return (_reference_tip(perturb(scene, h), warm)
            - _reference_tip(perturb(scene, -h), warm)) / (2 * h)


def _with_actuation_step(kind: str, j: int):
    def perturb(scene, h):
        D = list(scene.actuation.insertion)
        A = list(scene.actuation.rotation)
        (D if kind == "insertion" else A)[j] += h
        return scene.with_actuation(insertion=D, rotation=A)
    return perturb


def _with_modulus_step(scene, h):
    tubes = list(scene.tubes)
    tubes[0] = dataclasses.replace(tubes[0], E=tubes[0].E * (1 + h))
    return dataclasses.replace(scene, tubes=tuple(tubes))


pytestmark = pytest.mark.usefixtures("one_thread_module")


def test_enough_smooth_scenes():
    assert len(SEEDS) >= 5, SEEDS


@pytest.mark.parametrize("seed", SEEDS)
def test_tip_gradients_match_reference_finite_differences(seed):
    scene = random_scene(seed)
    N = scene.n_tubes
    robot = torchpvs.CTR(scene, ACCURATE).learnable("E")
    D = torch.tensor(scene.actuation.insertion, dtype=torch.float64, requires_grad=True)
    A = torch.tensor(scene.actuation.rotation, dtype=torch.float64, requires_grad=True)
    eq = robot(D, A)
    assert bool(eq.converged.all())
    ref, how = matched_reference(scene, torchpvs.solve(scene), seed)
    if how == "no match":
        pytest.skip("the reference has no stable equilibrium on PVS's branch here")
    np.testing.assert_allclose(eq.tip_position[0].detach().numpy(), ref.tip_position, atol=1e-8)

    jac = {"insertion": [], "rotation": [], "E": []}
    for i in range(3):
        gD, gA, gE = torch.autograd.grad(eq.tip_position[0, i], (D, A, robot.E),
                                         retain_graph=i < 2)
        jac["insertion"].append(gD.numpy())
        jac["rotation"].append(gA.numpy())
        jac["E"].append(gE[:1].numpy() * scene.tubes[0].E)  # d tip / d ln E1
    jac = {k: np.stack(v) for k, v in jac.items()}                # (3, n)

    fd = {"insertion": np.stack([_central(scene, ref, _with_actuation_step("insertion", j), 1e-5)
                                 for j in range(N)], 1),
          "rotation": np.stack([_central(scene, ref, _with_actuation_step("rotation", j), 1e-5)
                                for j in range(N)], 1),
          "E": _central(scene, ref, _with_modulus_step, 1e-5)[:, None]}
    for k in jac:
        scale = np.abs(fd[k]).max()
        if scale < 1e-9:          # e.g. d tip / d E1 of a robot with no bending in tube 1
            np.testing.assert_allclose(jac[k], fd[k], atol=1e-8, err_msg=k)
            continue
        err = np.abs(jac[k] - fd[k]).max() / scale
        print(f"seed {seed} ({N} tubes) d tip / d {k}: relative error {err:.2e}")
        assert err < REL_TOL, (k, err, jac[k], fd[k])
