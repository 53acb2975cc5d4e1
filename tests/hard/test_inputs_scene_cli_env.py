"""Hard suite (scene, CLI, environments): property tests over the
classes of bad input, so that none of them comes back.

* any numeric field of a scene given a value of a refused class (an integer beyond the float
  range, half precision, a string, a bool, NaN/inf), through a mapping, a YAML or JSON file or
  ``--set``, is a ``SceneError`` (CLI: exit 2, one line) naming that field;
* an optional section (``load``, ``precurvature``) given a non-mapping value is refused, not
  read as absent;
* an environment action of any shape but the action space's, or with any non-finite entry,
  raises ``ValueError`` and leaves the robot where it was.
"""

from __future__ import annotations

import contextlib
import io
import json
import math

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchpvs.cli import main
from torchpvs.scene import Scene, SceneError, load_scene

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


@pytest.fixture(scope="module")
def env():
    from envs import CTRReachEnv
    e = CTRReachEnv()
    e.reset(seed=0)
    return e


@PROPS
@given(shape=st.lists(st.integers(0, 4), max_size=3).map(tuple).filter(lambda s: s != (4,)))
def test_actions_of_any_other_shape_raise(env, shape):
    x0 = env.actuation
    with pytest.raises(ValueError, match=r"action must have shape \(4,\)"):
        env.step(np.zeros(shape, np.float32))
    np.testing.assert_array_equal(env.actuation, x0)


@PROPS
@given(a=st.lists(st.floats(-2, 2), min_size=4, max_size=4),
       bad=st.lists(st.sampled_from([math.nan, math.inf, -math.inf]), min_size=1, max_size=4),
       where=st.permutations(range(4)))
def test_actions_with_any_non_finite_entry_raise(env, a, bad, where):
    x0 = env.actuation
    a = np.array(a)
    a[list(where[:len(bad)])] = bad
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(a)
    np.testing.assert_array_equal(env.actuation, x0)
