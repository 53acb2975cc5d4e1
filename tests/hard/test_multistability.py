"""Hard case: rotations near 180 deg with long, highly curved overlaps (docs/physics.md, "Hard
cases":
several equilibria coexist; the solver must converge, report whether the equilibrium is stable,
and give the right gradients up to the fold where the robot snaps).

Independent references: the standard-model shooting solver (torchpvs.reference, its own
stability analysis on a fine torsion grid) and central finite differences of warm-started solves.
Scene: the paper's section III-B robot (Renda et al. 2021, after Rucker et al. IJRR 2010): two
fully curved tubes, rotation imposed at the orifice; beyond the stability threshold.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

import torchpvs as tp
from torchpvs import NearSingularStiffnessWarning, SolverOptions
from torchpvs.reference import solve_standard
from torchpvs.testing import dist, tip

SEC3B = tp.load_scene("renda2021_section3b")
# Fold of the branch reached by rotating alpha2 up from 0 (measured here by bisection on
# warm-started solves, order 4, 16 Magnus steps: the branch exists up to 192.2882212 deg and
# jumps to the mirror branch beyond; the smallest stiffness eigenvalue there is ~1e-7).
ALPHA_FOLD = 192.28822124
FOLD_OPTS = SolverOptions(order=4, n_magnus=16, tol=1e-13, compute_forces=False)



def at(alpha2_deg: float):
    return SEC3B.with_actuation(rotation=[0.0, math.radians(alpha2_deg)])


@pytest.mark.parametrize("alpha2", [170.0, 180.0, 186.0, 190.0])
@pytest.mark.parametrize("method", ["minimize", "root"])
def test_stability_verdict_matches_reference(alpha2, method):
    """Section III-B robot at alpha2 in [170, 190] deg: three equilibria. ``minimize`` must
    return a stable one, ``root`` (plain Newton from the torsionless guess) lands on the unstable
    middle equilibrium. Each PVS answer is matched by the reference (started from the PVS orifice
    torsion, converging on its own equations): tip within 1e-5 m, same stability verdict, and the
    sign of the smallest stiffness eigenvalue agrees (reference: its own grid discretisation)."""
    sc = at(alpha2)
    eq = tp.solve(sc, options=SolverOptions(method=method))
    assert bool(eq.converged[0]), eq.reason
    ref = solve_standard(sc, initial=-eq.actuation_torques[0].numpy(), compute_forces=False)
    assert ref.converged
    assert dist(tip(eq), ref.tip_position) < 1e-5
    assert bool(eq.stable[0]) is ref.stable
    assert (float(eq.min_stiffness_eigenvalue[0]) > 0) == (ref.min_stiffness_eigenvalue > 0)
    if method == "minimize":
        assert ref.stable
    else:
        assert not ref.stable  # measured: the middle (unstable) equilibrium at every alpha2


def _branch_to(alpha2: float):
    """Follow the branch from alpha2 = 150 deg (rotating up, warm starts) to ``alpha2``."""
    prev = None
    for a in list(np.arange(150.0, min(alpha2, 192.0), 3.0)) + [alpha2]:
        prev = tp.solve(at(a), initial=prev, options=FOLD_OPTS)
        assert math.degrees(float(prev.relative_rotation_at_outer_tip[0, 0])) > 50.0, a
    return prev


@pytest.mark.parametrize("distance_deg", [1.0, 1e-2, 1e-4])
def test_gradient_near_fold(distance_deg):
    """d tip / d alpha2 through the implicit backward, approaching the fold (the snap point of
    docs/physics.md's hard case) to 1, 0.01 and 1e-4 deg. Pass: it matches central finite
    differences
    of warm-started solves (step 1/100 of the distance to the fold) within 1e-3 relative, or the
    solver raised NearSingularStiffnessWarning (an explicit flag, not a silent NaN). The gradient
    grows like 1/sqrt(distance): at 1e-4 deg it is ~100x the one at 1 deg."""
    alpha = ALPHA_FOLD - distance_deg
    base = _branch_to(alpha)
    a = torch.tensor([0.0, math.radians(alpha)], dtype=torch.float64, requires_grad=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        eq = tp.solve(SEC3B, rotation=a, initial=base, options=FOLD_OPTS)
        grad = torch.stack([torch.autograd.grad(eq.tip_position[0, k], a, retain_graph=True)[0][1]
                            for k in range(3)]).numpy()
    flagged = any(issubclass(w.category, NearSingularStiffnessWarning) for w in caught)
    h = math.radians(distance_deg) / 100
    tips = [tip(tp.solve(SEC3B, rotation=[0.0, math.radians(alpha) + s * h], initial=base,
                         options=FOLD_OPTS)) for s in (-1, 1)]
    fd = (tips[1] - tips[0]) / (2 * h)
    rel = float(np.linalg.norm(grad - fd) / np.linalg.norm(fd))
    print(f"\n{distance_deg:g} deg before the fold: |dtip/dalpha2| = "
          f"{np.linalg.norm(fd):.3e} m/rad, relative error {rel:.1e}, flagged {flagged}, "
          f"min eigenvalue {float(eq.min_stiffness_eigenvalue[0]):.2e}")
    assert flagged or rel < 1e-3


def test_fold_location():
    """The branch ends at the fold: 0.01 deg before it the stiffness is still positive definite
    and the configuration is on the branch; 0.01 deg after it the warm-started solve leaves the
    branch (the snap: theta_2 jumps from ~+125 deg to the mirror branch, ~-70 deg)."""
    base = _branch_to(ALPHA_FOLD - 1e-2)
    assert bool(base.stable[0])
    after = tp.solve(at(ALPHA_FOLD + 1e-2), initial=base, options=FOLD_OPTS)
    assert bool(after.converged[0]) and bool(after.stable[0])
    assert math.degrees(float(after.relative_rotation_at_outer_tip[0, 0])) < 0.0
    assert dist(tip(after), tip(base)) > 0.05
