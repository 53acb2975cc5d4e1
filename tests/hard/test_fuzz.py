"""Fuzz test (hypothesis) over valid random scenes: 1-3 nested tubes with any valid geometry,
precurvatures up to 40 1/m (x and y, constant or linear), stiffness ratios up to ~1:100 and more,
insertions anywhere from fully exposed to fully retracted (including D_j = 0 and equal bases),
any rotation, tip forces up to 2 N (docs/physics.md, "Hard cases"; scene rules:
docs/conventions.md).

Pass criteria, for every example:

* never NaN: tip, energy, coordinates and stiffness eigenvalue are finite, converged or not;
* never ``converged=True`` with a large residual: the reported scaled residual is below
  ``tol`` AND an independent check holds — the energy, evaluated by the quadrature-based
  ``mechanics.potential`` (not the analytic gradient the Newton iteration uses), is stationary:
  along random directions the Newton step of its central-difference slope and curvature moves
  the strains by less than 1e-6 rad (strain x robot length, the residual's own units);
* a non-converged element says why (``reason``).

Invalid scenes (one field broken in a valid scene) raise ``SceneError`` naming that field.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs import SceneError, SolverOptions
from torchpvs.mechanics import potential
from torchpvs.scene import Scene
from torchpvs.testing import scene_strategy

MM = 1e-3
OPTS = SolverOptions(compute_forces=False, on_failure="ignore")
FUZZ = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])



def stationarity(eq, n_dirs: int = 3, seed: int = 0) -> float:
    """Largest Newton step (strain x length, rad) along random Jacobi-scaled directions, from
    central differences (step 1e-3 in scaled units) of the quadrature energy."""
    from torchpvs.implicit import full_hessian

    ctx = eq.context
    q = eq.q.detach()
    info = ctx.implicit
    H, mask = full_hessian(info), info.qmask
    lay, tab = ctx.layout, ctx.tables
    if int(mask.sum()) == 0:
        return 0.0
    scale = H.diagonal(dim1=-2, dim2=-1).abs().clamp(min=1e-300) ** -0.5 * mask
    L = float((lay.ell.amax(-1) + ctx.insertion.amax(-1)).clamp(min=1e-6)[0])
    R0 = eq.tip_rotation.detach()
    gen = torch.Generator().manual_seed(seed)
    worst = 0.0
    for _ in range(n_dirs):
        v = torch.randn(q.shape, generator=gen, dtype=q.dtype) * scale
        v = v / v.abs().max()
        eps = 1e-3

        def E(t, v=v):
            return float(potential(q + t * v, lay, tab, R0, info.with_load)[0])
        e0, ep, em = E(0.0), E(eps), E(-eps)
        slope, curv = (ep - em) / (2 * eps), (ep - 2 * e0 + em) / eps**2
        noise = 1e3 * torch.finfo(q.dtype).eps * abs(e0) / eps
        if curv <= 0 or abs(slope) <= noise:
            continue
        worst = max(worst, abs(slope) / curv * L)
    return worst


@FUZZ
@given(scene_strategy())
def test_valid_scenes_never_nan_never_false_convergence(data):
    sc = Scene.from_dict(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        eq = tp.solve(sc, options=OPTS)
    for name in ("tip_position", "energy", "q", "tip_rotation"):
        assert torch.isfinite(getattr(eq, name)).all(), (name, data)
    # The smallest stiffness eigenvalue exists exactly when there are coordinates (a robot
    # entirely in the guide has none: NaN, null in JSON, as the reference reports).
    has_dofs = eq.dofs > 0
    assert torch.equal(torch.isfinite(eq.min_stiffness_eigenvalue), has_dofs), data
    # ... and agrees with the verdict (which keeps a margin of 0.01 sqrt(eps) above zero).
    ev = eq.min_stiffness_eigenvalue
    assert not bool((eq.stable & has_dofs & ~(ev > 0)).any()), (float(ev[0]), data)
    assert not bool((~eq.stable & (ev > 1e-8)).any()), (float(ev[0]), data)
    if bool(eq.converged[0]):
        assert float(eq.residual_norm[0]) < OPTS.tol
        step = stationarity(eq)
        assert step < 1e-6, (step, data)
    else:
        assert eq.reason[0] != "converged" and "residual" in eq.reason[0]


# (corruption, field named in the error)
def _corrupt(data: dict, kind: str, i: int) -> str:
    t = data["tubes"][i]
    n = len(data["tubes"])
    w = f"tubes[{i}]"
    if kind == "E":
        t["E"] = -t["E"]
        return f"{w}.E"
    if kind == "G":
        t["G"] = 0.0
        return f"{w}.G"
    if kind == "nan E":
        t["E"] = float("nan")
        return f"{w}.E"
    if kind == "inner_diameter":
        t["inner_diameter"] = -0.1 * MM
        return f"{w}.inner_diameter"
    if kind == "outer_diameter":
        t["outer_diameter"] = t["inner_diameter"] * 0.5
        return f"{w}.outer_diameter"
    if kind == "straight_length":
        t["straight_length"] = -1 * MM
        return f"{w}.straight_length"
    if kind == "curved_length":
        t["curved_length"] = -1 * MM
        return f"{w}.curved_length"
    if kind == "precurvature":
        t["precurvature"] = {"y": [float("inf")]}
        return f"{w}.precurvature"
    if kind == "nesting":
        assume(i > 0)
        t["outer_diameter"] = data["tubes"][i - 1]["inner_diameter"] + 0.1 * MM
        return f"{w}.outer_diameter"
    if kind == "insertion":
        data["actuation"]["insertion"][i] = -1 * MM
        return "actuation.insertion"
    if kind == "order":
        assume(n > 1)
        data["actuation"]["insertion"][0] = data["actuation"]["insertion"][-1] + 1 * MM
        return "actuation.insertion"
    if kind == "rotation":
        data["actuation"]["rotation"] = data["actuation"]["rotation"] + [0.0]
        return "actuation.rotation"
    if kind == "load":
        data["load"] = {"tip_force": [1.0, 0.0]}
        return "load.tip_force"
    raise AssertionError(kind)


KINDS = ["E", "G", "nan E", "inner_diameter", "outer_diameter", "straight_length",
         "curved_length", "precurvature", "nesting", "insertion", "order", "rotation", "load"]


@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(scene_strategy(), st.sampled_from(KINDS), st.integers(0, 2))
def test_invalid_scenes_name_the_field(data, kind, i):
    """docs/conventions.md: a scene that breaks a rule gets an error naming the tube, the field and
    the rule, never a traceback from inside the solver and never a silent fix."""
    i = min(i, len(data["tubes"]) - 1)
    if kind == "outer_diameter":
        assume(data["tubes"][i]["inner_diameter"] > 0)
    field = _corrupt(data, kind, i)
    with pytest.raises(SceneError) as err:
        Scene.from_dict(data)
    assert field in str(err.value), (field, str(err.value))


@FUZZ
@given(scene_strategy(), st.sampled_from(["insertion", "order", "shape", "nan"]))
def test_invalid_solve_overrides_name_the_argument(data, kind):
    """Overrides passed to solve() are checked too (solver.py): a ValueError naming the
    argument, before any work."""
    sc = Scene.from_dict(data)
    n = sc.n_tubes
    D = list(sc.actuation.insertion)
    if kind == "insertion":
        D[0] = -1e-3
    elif kind == "order":
        assume(n > 1)
        D[0] = D[-1] + 1e-3
    elif kind == "shape":
        D = D + [0.1]
    else:
        D[0] = float("nan")
    with pytest.raises(ValueError, match="insertion"):
        tp.solve(sc, insertion=D, options=OPTS)
