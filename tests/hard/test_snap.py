"""The snap of the section III-B robot (docs/physics.md, hard cases): the fold that
``torchpvs.continuation`` locates while rotating the inner tube must lie within 1 deg of the
fold of the independent standard model (shooting, torchpvs.reference), located there by its own
warm-started sweep and bisection on "the branch still exists and is stable"."""

import math

import pytest

import torchpvs as tp
from torchpvs.reference import solve_standard


def _reference_fold(scene, lo_deg: float, hi_deg: float, tol_deg: float = 0.02):
    """Follow the standard model from 0 deg (unique equilibrium) to ``lo_deg``, then bisect on
    the existence of a stable equilibrium continuous with the branch (warm start from the last
    good one, relative rotation theta_2 moving by less than 15 deg)."""
    ref = None
    for a in range(0, int(lo_deg) + 1, 5):
        ref = solve_standard(scene.with_actuation(rotation=[0.0, math.radians(a)]),
                             initial=ref, compute_forces=False)
        assert ref.converged and ref.stable
    lo, hi = float(int(lo_deg) // 5 * 5), hi_deg
    while hi - lo > tol_deg:
        mid = 0.5 * (lo + hi)
        r = solve_standard(scene.with_actuation(rotation=[0.0, math.radians(mid)]),
                           initial=ref, compute_forces=False)
        d_theta = abs(float(r.relative_rotation_at_outer_tip[0]
                            - ref.relative_rotation_at_outer_tip[0]))
        if r.converged and r.stable and math.degrees(d_theta) < 15.0:
            lo, ref = mid, r
        else:
            hi = mid
    return 0.5 * (lo + hi), ref


@pytest.fixture(scope="module")
def scene3b():
    return tp.load_scene("renda2021_section3b")


@pytest.fixture(scope="module")
def reference_fold(scene3b):
    return _reference_fold(scene3b, 185.0, 200.0)


def test_fold_location_within_one_degree_of_reference(scene3b, reference_fold):
    res = tp.continuation(scene3b, {"rotation": [[0.0, 0.0], [0.0, 2 * math.pi]]},
                          options=tp.SolverOptions(order=4, n_magnus=16, compute_forces=False),
                          max_step=5 / 360)
    assert len(res.folds) == 1
    fold = res.folds[0]
    a_pvs = math.degrees(float(fold.rotation[1]))
    a_ref, ref_lo = reference_fold
    assert abs(a_pvs - a_ref) < 1.0, (a_pvs, a_ref)
    # the reference stiffness really goes to zero there (a fold, not a failed solve)
    assert 0 < ref_lo.min_stiffness_eigenvalue < 0.1
    # the snap lands on the mirror branch: the tip jumps across the y = 0 plane
    assert fold.tip_before[1] * fold.tip_after[1] < 0
    assert fold.tip_jump > 0.1


@pytest.mark.slow
def test_backward_sweep_folds_at_the_mirror_angle(scene3b, reference_fold):
    res = tp.continuation(scene3b, {"rotation": [[0.0, 0.0], [0.0, 2 * math.pi]]},
                          options=tp.SolverOptions(order=3, n_magnus=16, compute_forces=False),
                          max_step=5 / 360, s_span=(1.0, 0.0))
    assert len(res.folds) == 1
    a_fwd, _ = reference_fold
    assert abs(math.degrees(float(res.folds[0].rotation[1])) - (360.0 - a_fwd)) < 1.0
