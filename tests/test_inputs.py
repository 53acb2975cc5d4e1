"""Bad and extreme inputs to torchpvs: clear errors that name the field, and no spurious
verdicts (every input answers with a true verdict). The home of torchpvs's input checks
(``torchpvs.inputs`` and the checks of ``solve``, ``CTR``, scenes and the CLI); the
environments' are in ``tests/envs/test_env_inputs.py``, the scene module's own rules (one per
field, files, ``--set``) in ``test_scene.py``.

* ``torchpvs.solve`` and ``torchpvs.CTR`` (Stage 5). Independent references: the closed form of
  a common base rotation (it turns the whole robot about the guide axis z, so the tip turns by
  the same angle: tip(alpha + c) = Rz(c) tip(alpha)), the 2 pi-periodicity of the base
  rotations, and the scene rules of torchpvs.scene.
* Scenes and the CLI, property tests over the classes of bad input, so that none of them comes
  back: any numeric field of a scene given a value of a refused class (an integer beyond the
  float range, half precision, a string, a bool, NaN/inf), through a mapping, a YAML or JSON
  file or ``--set``, is a ``SceneError`` (CLI: exit 2, one line) naming that field; an optional
  section (``load``, ``precurvature``) given a non-mapping value is refused, not read as
  absent.
"""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest
import torch
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchpvs as tp
from torchpvs.cli import main
from torchpvs.scene import Scene, SceneError, load_scene

SC = tp.load_scene("renda2021_fig3")


def _rz(c: float) -> torch.Tensor:
    return torch.tensor([[math.cos(c), -math.sin(c), 0.0], [math.sin(c), math.cos(c), 0.0],
                         [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_options_of_the_wrong_type_are_named():
    with pytest.raises(TypeError, match="options must be a torchpvs.SolverOptions"):
        tp.solve(SC, options={"accuracy": 1e-6})


def test_solve_names_the_bad_field():
    with pytest.raises(ValueError, match="insertion"):
        tp.solve(SC, insertion=[0.1])
    with pytest.raises(ValueError, match="insertion"):
        tp.solve(SC, insertion=[0.2, 0.1])
    with pytest.raises(ValueError, match="rotation"):
        tp.solve(SC, rotation=[float("nan"), 0.0])
    with pytest.raises(ValueError, match="options.method"):
        tp.SolverOptions(method="bfgs")
    with pytest.raises(ValueError, match="options.accuracy"):
        tp.SolverOptions(accuracy=-1.0)


def test_solve_force_controlled_names_the_bad_field():
    with pytest.raises(ValueError, match="torques must have shape"):
        tp.solve_force_controlled(SC, torques=[0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="forces must be finite or NaN"):
        tp.solve_force_controlled(SC, forces=[math.inf, math.nan])
    with pytest.raises(ValueError, match="insertion"):
        tp.solve_force_controlled(SC, forces=[math.nan, 1.0], insertion=[0.1, 0.05])


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_inputs_are_refused_by_name(dtype):
    with pytest.raises(ValueError, match=r"rotation: dtype .*float16.* not supported"):
        tp.solve(SC, rotation=torch.tensor([0.0, 1.0], dtype=dtype))


@pytest.mark.parametrize("field", ["forces", "torques"])
def test_half_precision_commands_are_refused_by_name(field):
    # Regression: a float16 command set the solve's dtype, and the error named `insertion`.
    with pytest.raises(ValueError, match=rf"{field}: dtype torch.float16 is not supported"):
        tp.solve_force_controlled(SC, **{field: torch.zeros(2, dtype=torch.float16)})


def test_the_first_floating_input_sets_the_dtype():
    # an integer insertion does not decide the dtype; the float32 rotation does
    eq = tp.solve(SC, insertion=torch.tensor([0, 0]), rotation=torch.zeros(2, dtype=torch.float32))
    assert eq.q.dtype == torch.float32
    assert tp.solve(SC, insertion=torch.tensor([0, 0])).q.dtype == torch.float64


def test_non_finite_initial_guess_is_refused_by_name():
    eq = tp.solve(SC)
    with pytest.raises(ValueError, match="initial"):
        tp.solve(SC, initial=torch.full_like(eq.q, float("nan")))


@pytest.mark.parametrize("prop, index, value, field", [
    ("E", 0, -1.0, r"tubes\[0\]\.E"),
    ("G", 1, 0.0, r"tubes\[1\]\.G"),
    ("inner_diameter", 0, 5e-3, r"tubes\[0\]\.outer_diameter .* must exceed inner_diameter"),
    ("outer_diameter", 1, 5e-3, r"tubes\[1\]\.outer_diameter .* next outer tube"),
    ("curved_length", 0, -0.1, r"tubes\[0\]\.curved_length"),
    ("E", 1, float("nan"), "finite"),
])
def test_ctr_enforces_the_scene_rules(prop, index, value, field):
    """torchpvs.CTR holds tube properties as tensors that users may edit: the same rules as
    scenes apply at forward (they used to solve as converged and stable)."""
    robot = tp.CTR(SC)
    with torch.no_grad():
        getattr(robot, prop)[index] = value
    with pytest.raises(ValueError, match=field):
        robot(torch.tensor([0.0, 0.01]), torch.tensor([0.0, 1.0]))


@settings(max_examples=8, deadline=None)
@given(c=st.floats(-1e6, 1e6), phi=st.floats(0.0, 2 * math.pi))
def test_common_rotation_turns_the_tip_about_z(c, phi):
    """Closed form: a common base rotation c turns the robot rigidly about z. Large angles (up
    to 1e6 rad) converge as well as small ones (the residual test used to fail at 1e6 rad:
    cos/sin of 1e6 lose 1e-10 absolute)."""
    base = tp.solve(SC, rotation=[0.0, phi])
    eq = tp.solve(SC, rotation=[c, c + phi], options=tp.SolverOptions(on_failure="raise"))
    expected = base.tip_position[0] @ _rz(c).T
    assert float((eq.tip_position[0] - expected).norm()) < 1e-9


def test_robot_inside_the_guide_reports_no_eigenvalue():
    """No free coordinates: nothing can buckle (stable) and there is no smallest eigenvalue to
    report (NaN in the API, null in JSON; the reference model reports null)."""
    full = [t.length for t in SC.tubes]
    eq = tp.solve(SC, insertion=[max(full), max(full)])
    assert bool(eq.converged[0]) and bool(eq.stable[0]) and int(eq.dofs[0]) == 0
    assert math.isnan(float(eq.min_stiffness_eigenvalue[0]))
    assert eq.as_contract()["min_stiffness_eigenvalue"] is None


def test_overflowing_load_is_not_reported_converged():
    """A tip force of 1e300 N overflows the stiffness; it used to pass the residual test as
    inf/inf after 0 iterations with converged=True."""
    eq = tp.solve(SC, tip_force=[1e300, 0.0, 0.0],
                  options=tp.SolverOptions(on_failure="ignore", max_iter=5, order=2,
                                           n_magnus=8))
    assert not bool(eq.converged[0])
    assert "residual" in eq.reason[0]


def test_max_order_one_is_honoured():
    eq = tp.solve(SC, options=tp.SolverOptions(max_order=1))
    assert eq.order == 1 and bool(eq.converged[0])
    assert math.isfinite(float(eq.error_estimate[0]))


def test_warm_start_continues_at_the_order_it_came_from():
    """A warm start keeps the discretization of its initial equilibrium, so a continuation stays
    on the branch of the model it follows (it used to restart at order 2, which folds earlier
    near the III-B snap)."""
    fine = tp.solve(SC, options=tp.SolverOptions(accuracy=1e-9))
    assert fine.order >= 3
    nxt = tp.solve(SC, rotation=[0.0, 0.05], initial=fine)
    assert nxt.order == fine.order
    cold = tp.solve(SC, rotation=[0.0, 0.05])
    assert cold.order <= nxt.order


def test_unmet_accuracy_is_reported_and_warned():
    """max_order caps the automatic order below what the request needs: the solve says so (a
    warning and Equilibrium.accuracy_met) instead of returning converged with no word."""
    with pytest.warns(tp.AccuracyWarning, match="not reached"):
        eq = tp.solve(SC, options=tp.SolverOptions(max_order=2, accuracy=1e-9))
    assert bool(eq.converged[0]) and not bool(eq.accuracy_met[0])
    assert float(eq.error_estimate[0]) > 1e-9
    ok = tp.solve(SC)
    assert bool(ok.accuracy_met[0])
    fixed = tp.solve(SC, options=tp.SolverOptions(order=2))
    assert not bool(fixed.accuracy_met[0])          # no estimate exists for a fixed order


def _scaled_robot(factor: float, diam: float = 1.0):
    import dataclasses
    tubes = tuple(dataclasses.replace(t, E=t.E * factor, G=t.G * factor,
                                      inner_diameter=t.inner_diameter * diam,
                                      outer_diameter=t.outer_diameter * diam) for t in SC.tubes)
    return dataclasses.replace(SC, tubes=tubes)


@settings(max_examples=6, deadline=None)
@given(factor=st.floats(1e-8, 1e8), diam=st.sampled_from([1e-4, 1e-2, 1.0, 3.0]),
       alpha=st.floats(0.0, 3.0))
def test_stability_verdict_does_not_depend_on_the_robot_scale(factor, diam, alpha):
    """Scaling every modulus by ``factor`` and every diameter by ``diam`` multiplies the
    stiffness by a constant (EI, GJ ~ E d^4): the equilibrium, the verdict and the reported
    (nondimensional) eigenvalue must not change. A robot with diameters x 1e-4 used to be
    reported unstable (eigenvalue -3.4e-15) while the reference said stable."""
    base = tp.solve(SC, rotation=[0.0, alpha])
    eq = tp.solve(_scaled_robot(factor, diam), rotation=[0.0, alpha])
    assert float((eq.tip_position - base.tip_position).norm()) < 1e-9
    assert bool(eq.stable[0]) == bool(base.stable[0])
    ev, ev0 = float(eq.min_stiffness_eigenvalue[0]), float(base.min_stiffness_eigenvalue[0])
    assert abs(ev - ev0) <= 1e-6 * abs(ev0) + 1e-12, (ev, ev0)
    assert bool(eq.stable[0]) == (ev > 0)


def test_large_tip_moment_stops_within_the_work_bound_with_a_reason():
    """A tip moment the model cannot carry (0.5 N m about z on the Fig. 3 robot; 10 N m used to
    run for minutes): the solve ramps the load, stops at max_total_iter and says how far the
    ramp got."""
    opts = tp.SolverOptions(order=2, n_magnus=8, max_iter=15, max_total_iter=40, load_steps=4,
                            on_failure="ignore")
    eq = tp.solve(SC, tip_moment=[0.0, 0.0, 0.5], options=opts)
    assert not bool(eq.converged[0])
    reason = eq.reason[0]
    assert "load ramp (4 steps) reached" in reason and "% of the tip load" in reason, reason
    assert "max_total_iter=40" in reason, reason
    assert int(eq.iterations[0]) <= 15 + 1


def test_load_ramp_carries_a_load_the_single_solve_cannot():
    """With a tight iteration budget (max_iter=4) a 20 N lateral tip force is not reached from
    the initial guess in one Newton solve, but is by 8 warm-started load steps; the result is
    the equilibrium of the full load: the same tip as an independent solve with ample
    iterations (the stable equilibrium reached from the same guess)."""
    F = [20.0, 0.0, 0.0]
    tight = dict(order=2, n_magnus=8, max_iter=4, on_failure="ignore")
    single = tp.solve(SC, tip_force=F, options=tp.SolverOptions(load_steps=1, **tight))
    assert not bool(single.converged[0])
    ramped = tp.solve(SC, tip_force=F, options=tp.SolverOptions(load_steps=8, **tight))
    assert bool(ramped.converged[0])
    ample = tp.solve(SC, tip_force=F, options=tp.SolverOptions(order=2, n_magnus=8))
    assert float((ramped.tip_position - ample.tip_position).norm()) < 1e-9


def test_options_bounds_are_validated():
    with pytest.raises(ValueError, match="options.load_steps"):
        tp.SolverOptions(load_steps=0)
    with pytest.raises(ValueError, match="options.max_total_iter"):
        tp.SolverOptions(max_total_iter=0)


def test_plan_reuse_is_not_fooled_by_reused_buffers():
    """The robot's plan reuses the layout of the last insertions: a caller that mutates its
    insertion buffer after a solve must not change what a later solve at the old insertions
    sees (the plan keeps its own copies)."""
    D = torch.tensor([[0.05, SC.actuation.insertion[1]]], dtype=torch.float64)  # no force kink
    first = tp.solve(SC, insertion=D, rotation=[0.0, 2.0])
    D[0, 1] -= 0.05                    # the caller reuses its buffer
    again = tp.solve(SC, insertion=[0.05, SC.actuation.insertion[1]], rotation=[0.0, 2.0])
    assert float((again.tip_position - first.tip_position).norm()) < 1e-12
    assert torch.allclose(again.actuation_forces, first.actuation_forces, atol=1e-12)
    # (the relative twist at the outer tip reads the insertions held by the layout: it moved by
    # 0.21 rad when the plan kept a reference to the caller's buffer)
    assert torch.allclose(again.relative_rotation_at_outer_tip,
                          first.relative_rotation_at_outer_tip, atol=1e-12)


def test_chunked_batches_equal_the_whole_batch(monkeypatch):
    """Large batches run in cache-sized chunks (batch_linalg.CHUNK_BYTES): elements are
    independent, so
    a chunked solve gives the same equilibria, forces and verdicts as one whole batch."""
    import torchpvs.batch_linalg as batch_linalg

    alpha = torch.linspace(0.0, 4.0, 40, dtype=torch.float64)
    rot = torch.stack([torch.zeros_like(alpha), alpha], -1)
    whole = tp.solve(SC, rotation=rot)
    monkeypatch.setattr(batch_linalg, "CHUNK_BYTES", 1)      # chunks of 16 elements
    parts = tp.solve(SC, rotation=rot)
    assert float((whole.tip_position - parts.tip_position).abs().max()) < 1e-12
    assert float((whole.actuation_forces - parts.actuation_forces).abs().max()) < 1e-9
    assert torch.equal(whole.stable, parts.stable) and torch.equal(whole.converged,
                                                                   parts.converged)


def test_no_stability_verdict_without_an_equilibrium():
    """Regression: a CTR with precurvature 1e6 1/m does not converge (61 iterations,
    residual 0.12) and was reported stable=True. A state that is not an equilibrium gets no
    verdict: stable is False and the contract's "stable" is null (as the standard reference
    does for a failed solve, tests/test_reference.py)."""
    robot = tp.CTR(SC, tp.SolverOptions(on_failure="ignore"))
    with torch.no_grad():
        robot.precurvature[:] = 1e6
    eq = robot(torch.tensor(SC.actuation.insertion), torch.tensor(SC.actuation.rotation))
    assert not bool(eq.converged[0])
    assert not bool(eq.stable[0])
    c = eq.as_contract()
    assert c["converged"] is False and c["stable"] is None
    # a converged solve keeps its verdict in both
    ok = tp.solve(SC)
    assert bool(ok.converged[0]) and bool(ok.stable[0]) and ok.as_contract()["stable"] is True


def test_time_limit_bounds_a_hard_solve_and_says_so():
    """Regression (time bound of a solve): a 10 N·m tip moment on the Fig. 3 robot fails after
    61 iterations (about 10 s on one thread, 100 s with default threads on a loaded machine).
    SolverOptions.time_limit bounds the Newton iterations; the answer is reported unconverged
    with the reason, not NaN, and the call returns soon after the limit (the remaining work is
    one iteration plus the outputs)."""
    from torchpvs.clock import work_clock
    tp.solve(SC, options=tp.SolverOptions(order=2))               # warm: first-call setup
    opts = tp.SolverOptions(on_failure="ignore", time_limit=0.3, compute_forces=False)
    t0 = work_clock()         # (the limit's clock: compiling a kernel on first use not counted)
    eq = tp.solve(SC, tip_moment=[0.0, 10.0, 0.0], options=opts)
    elapsed = work_clock() - t0
    assert not bool(eq.converged[0]) and "time limit time_limit=0.3 s reached" in eq.reason[0]
    assert math.isfinite(float(eq.residual_norm[0])) and bool(torch.isfinite(eq.q).all())
    assert elapsed < 0.3 + 2.0, elapsed
    # an easy solve is untouched by the default bound (30 s)
    assert tp.SolverOptions().time_limit == 30.0 and bool(tp.solve(SC).converged[0])


@pytest.mark.parametrize("value", [0.0, -1.0, math.inf, math.nan, "10", True])
def test_time_limit_must_be_positive_seconds(value):
    with pytest.raises(ValueError, match="options.time_limit must be a positive number"):
        tp.SolverOptions(time_limit=value)


# -- wall-clock bounds of the calls made of many solves -------------------------------------

def test_calls_of_many_solves_honour_their_time_limit():
    """inverse_kinematics, solve_force_controlled and continuation stop at their time_limit
    (checked before every iteration, every inner solve bounded by what is left) and say so;
    with the default limits the same calls finish. The limits bound work: they run on
    :func:`torchpvs.clock.work_clock`, which does not count numba compiling a kernel on its
    first use (tens of seconds with an empty cache), so the elapsed time is taken on it."""
    import math

    import torchpvs
    from torchpvs.clock import work_clock
    scene = torchpvs.load_scene("renda2021_fig3")
    t = work_clock()
    ik = torchpvs.inverse_kinematics(scene, [0.03, 0.02, 0.09], time_limit=0.05)
    assert ik.timed_out and work_clock() - t < 3.0
    assert not torchpvs.inverse_kinematics(scene, [0.03, 0.02, 0.09], max_iter=2).timed_out
    t = work_clock()
    fc = torchpvs.solve_force_controlled(scene, torques=[math.nan, 0.01], time_limit=1e-3,
                                         on_failure="ignore")
    assert work_clock() - t < 3.0
    assert not bool(fc.converged[0]) and "time limit" in fc.reason[0]
    path = torchpvs.ActuationPath(rotation=[[0, 0], [0, 2 * math.pi]])
    t = work_clock()
    # (182 steps of about 1 ms: 0.3 s of work was at times enough to finish the path)
    res = torchpvs.continuation("renda2021_section3b", path, time_limit=0.03)
    assert work_clock() - t < 3.0
    assert not res.complete and "time limit" in res.reason and len(res) >= 1
    for call in (lambda: torchpvs.inverse_kinematics(scene, [0.03, 0.02, 0.09], time_limit=0),
                 lambda: torchpvs.solve_force_controlled(scene, torques=[math.nan, 0.01],
                                                         time_limit=-1.0),
                 lambda: torchpvs.continuation("renda2021_section3b", path,
                                               time_limit=math.inf)):
        with pytest.raises(ValueError, match="time_limit must be a positive number"):
            call()


# ---------------------------------------------------------------------------------------------
# Scenes and the CLI: property tests over the classes of bad input

PROPS = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                 suppress_health_check=[HealthCheck.function_scoped_fixture])

BASE = load_scene("renda2021_fig3").with_load(tip_force=[0.0, 0.1, 0.0]).to_dict()


def _numeric_paths(node, prefix=()):
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _numeric_paths(v, (*prefix, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _numeric_paths(v, (*prefix, i))
    elif isinstance(node, float):
        yield prefix


PATHS = list(_numeric_paths(BASE))


def _name(path) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def _with(path, value):
    data = json.loads(json.dumps(BASE))
    node = data
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return data


big_ints = st.integers(min_value=2**1024, max_value=10**600).flatmap(
    lambda n: st.sampled_from([n, -n]))
text_safe = st.one_of(big_ints, st.sampled_from(["1.0", "abc", True, False, math.nan,
                                                 math.inf, -math.inf]))


def _half():
    import torch
    return st.sampled_from([np.float16(1.0), torch.tensor(1.0, dtype=torch.float16),
                            torch.tensor(1.0, dtype=torch.bfloat16)])


@PROPS
@given(path=st.sampled_from(PATHS), value=st.one_of(text_safe, _half()))
def test_bad_numbers_in_a_mapping_name_the_field(path, value):
    with pytest.raises(SceneError) as info:
        Scene.from_dict(_with(path, value))
    assert _name(path) in str(info.value)


@PROPS
@given(path=st.sampled_from(PATHS), value=text_safe, fmt=st.sampled_from(["yaml", "json"]))
def test_bad_numbers_in_files_and_set_exit_2_naming_the_field(tmp_path_factory, path, value,
                                                             fmt):
    d = tmp_path_factory.mktemp("s")
    data = _with(path, value)
    file = d / f"s.{fmt}"
    if fmt == "json":
        file.write_text(json.dumps(data))  # NaN/Infinity: Python's JSON extension
    else:
        file.write_text(yaml.safe_dump(data))
    yaml_value = {True: "true", False: "false"}.get(value, None) if isinstance(value, bool) \
        else (".nan" if isinstance(value, float) and math.isnan(value)
              else ".inf" if value == math.inf else "-.inf" if value == -math.inf
              else json.dumps(value))
    for argv in (["solve", str(file), "--json"],
                 ["solve", "renda2021_fig3", "--set", "load.tip_force=[0, 0.1, 0]",
                  "--set", f"{_name(path)}={yaml_value}", "--json"]):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
        assert code == 2 and out.getvalue() == "", (argv, err.getvalue())
        assert err.getvalue().count("\n") == 1
        assert _name(path) in err.getvalue(), (argv, err.getvalue())


@PROPS
@given(section=st.sampled_from([("load",), ("tubes", 0, "precurvature"),
                                ("tubes", 1, "precurvature")]),
       value=st.one_of(st.just(0), st.just(0.0), st.just(False), st.just(""), st.just([]),
                       st.lists(st.floats(allow_nan=False), max_size=3),
                       st.floats(allow_nan=False), st.text(max_size=5)))
def test_optional_sections_are_mappings_or_absent(section, value):
    with pytest.raises(SceneError) as info:
        Scene.from_dict(_with(section, value))
    assert f"{_name(section)} must be a mapping" in str(info.value)
