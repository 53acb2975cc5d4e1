"""Stage 1 — the scene: every validation rule of scene.py and docs/conventions.md,
built-in scenes against the paper, YAML/JSON loading, round trips and ``--set`` overrides."""

from __future__ import annotations

import copy
import dataclasses
import json
import math

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from torchpvs.scene import (
    Actuation,
    Load,
    Scene,
    SceneError,
    Tube,
    apply_overrides,
    builtin_scenes,
    load_scene,
)

MM = 1e-3

# A valid two-tube scene (Table I of Renda et al. 2021, Fig. 3 geometry), as a mapping.
BASE = {
    "tubes": [
        {"name": "outer", "E": 58.0e9, "G": 21.5e9, "inner_diameter": 2.01e-3,
         "outer_diameter": 2.39e-3, "straight_length": 93.5e-3, "curved_length": 92.3e-3,
         "precurvature": {"x": [0.0], "y": [9.9], "z": [0.0]}},
        {"name": "inner", "E": 58.0e9, "G": 21.5e9, "inner_diameter": 0.0,
         "outer_diameter": 1.6e-3, "straight_length": 218.5e-3, "curved_length": 85.0e-3,
         "precurvature": {"y": [13.8, 0.5]}},
    ],
    "actuation": {"insertion": [93.5e-3, 208.5e-3], "rotation": [0.0, math.pi]},
    "load": {"tip_force": [0.0, 0.1, 0.0], "tip_moment": [0.0, 0.0, 0.01]},
}


def base() -> dict:
    return copy.deepcopy(BASE)


def _set(data: dict, path: tuple, value) -> dict:
    node = data
    for p in path[:-1]:
        node = node[p]
    node[path[-1]] = value
    return data


def _del(data: dict, path: tuple) -> dict:
    node = data
    for p in path[:-1]:
        node = node[p]
    del node[path[-1]]
    return data


def _raises(data, *fields: str) -> str:
    """Scene.from_dict(data) raises a SceneError (a ValueError) naming every one of fields."""
    with pytest.raises(SceneError) as info:
        Scene.from_dict(data)
    assert isinstance(info.value, ValueError)
    msg = str(info.value)
    for f in fields:
        assert f in msg, f"{f!r} not named in {msg!r}"
    assert "\n" not in msg
    return msg


def test_base_is_valid():
    s = Scene.from_dict(base())
    assert s.n_tubes == 2
    assert [t.name for t in s.tubes] == ["outer", "inner"]
    assert s.tubes[1].precurvature == ((), (13.8, 0.5), ())
    assert s.load == Load((0.0, 0.1, 0.0), (0.0, 0.0, 0.01))


# ---------------------------------------------------------------------------------------------
# Value rules, one per field, on each tube

TUBE_VALUE_RULES = [
    # (tube index, field, bad value, field named in the message)
    (0, "E", 0.0, "tubes[0].E"),
    (0, "E", -58e9, "tubes[0].E"),
    (1, "E", 0.0, "tubes[1].E"),
    (0, "G", 0.0, "tubes[0].G"),
    (1, "G", -1.0, "tubes[1].G"),
    (0, "inner_diameter", -1e-4, "tubes[0].inner_diameter"),
    (1, "inner_diameter", -1e-9, "tubes[1].inner_diameter"),
    (0, "outer_diameter", 2.01e-3, "tubes[0].outer_diameter"),   # == inner: not a tube
    (0, "outer_diameter", 1.0e-3, "tubes[0].outer_diameter"),    # < inner
    (1, "inner_diameter", 1.6e-3, "tubes[1].outer_diameter"),    # inner == outer
    (1, "outer_diameter", 0.0, "tubes[1].outer_diameter"),       # solid rod of zero size
    (0, "straight_length", -1e-3, "tubes[0].straight_length"),
    (1, "straight_length", -1e-3, "tubes[1].straight_length"),
    (0, "curved_length", -1e-3, "tubes[0].curved_length"),
    (1, "curved_length", -1e-12, "tubes[1].curved_length"),
]


@pytest.mark.parametrize(("i", "key", "value", "field"), TUBE_VALUE_RULES)
def test_tube_value_rules(i, key, value, field):
    _raises(_set(base(), ("tubes", i, key), value), field)


@pytest.mark.parametrize("i", [0, 1])
def test_total_length_must_be_positive(i):
    d = base()
    d["tubes"][i]["straight_length"] = 0.0
    d["tubes"][i]["curved_length"] = 0.0
    _raises(d, f"tubes[{i}]", "straight_length + curved_length")


@pytest.mark.parametrize(("straight", "curved"), [(0.0, 0.1), (0.1, 0.0)])
def test_one_zero_length_part_is_fine(straight, curved):
    d = base()
    d["tubes"][1]["straight_length"] = straight
    d["tubes"][1]["curved_length"] = curved
    assert Scene.from_dict(d).tubes[1].length == pytest.approx(0.1)


@pytest.mark.parametrize("od", [2.02e-3, 2.39e-3, 3.0e-3])
def test_nesting(od):
    msg = _raises(_set(base(), ("tubes", 1, "outer_diameter"), od),
                  "tubes[1].outer_diameter", "tubes[0].inner_diameter")
    assert "exceed" in msg


def test_nesting_allows_an_exact_fit_and_three_tubes():
    d = base()
    d["tubes"][1]["outer_diameter"] = 2.01e-3  # equal: allowed ("must not exceed")
    assert Scene.from_dict(d).tubes[1].outer_diameter == 2.01e-3
    d = base()
    d["tubes"][1]["inner_diameter"] = 1.0e-3
    d["tubes"].append({"E": 1e9, "G": 1e9, "inner_diameter": 0.0, "outer_diameter": 1.1e-3,
                       "straight_length": 0.3, "curved_length": 0.05})
    d["actuation"] = {"insertion": [0.1, 0.2, 0.2], "rotation": [0, 0, 0]}
    _raises(d, "tubes[2].outer_diameter", "tubes[1].inner_diameter")
    d["tubes"][2]["outer_diameter"] = 0.9e-3
    s = Scene.from_dict(d)
    assert s.n_tubes == 3 and s.tubes[2].name == "tube3"


@pytest.mark.parametrize(("insertion", "field"), [
    ([-1e-3, 0.2], "actuation.insertion[0]"),
    ([0.0, -1e-3], "actuation.insertion[1]"),
    ([0.1, 0.05], "actuation.insertion[1]"),   # D_2 < D_1: base of the inner tube ahead
    ([0.1, 0.0999999], "actuation.insertion[1]"),
])
def test_insertion_rules(insertion, field):
    _raises(_set(base(), ("actuation", "insertion"), insertion), field)


@pytest.mark.parametrize("insertion", [[0.0, 0.0], [0.1, 0.1], [0.0, 5.0], [0.5, 0.6]])
def test_valid_insertions(insertion):
    # equal bases, a tube entirely inside the guide, tips in any order: all allowed
    assert Scene.from_dict(_set(base(), ("actuation", "insertion"), insertion))


@pytest.mark.parametrize(("path", "value", "field"), [
    (("actuation", "insertion"), [0.1], "actuation.insertion"),
    (("actuation", "insertion"), [0.1, 0.2, 0.3], "actuation.insertion"),
    (("actuation", "insertion"), [], "actuation.insertion"),
    (("actuation", "rotation"), [0.0], "actuation.rotation"),
    (("actuation", "rotation"), [0.0, 1.0, 2.0], "actuation.rotation"),
    (("load", "tip_force"), [0.0, 0.0], "load.tip_force"),
    (("load", "tip_force"), [0.0, 0.0, 0.0, 0.0], "load.tip_force"),
    (("load", "tip_moment"), [], "load.tip_moment"),
    (("load", "tip_moment"), [1.0, 2.0, 3.0, 4.0], "load.tip_moment"),
])
def test_wrong_list_lengths(path, value, field):
    msg = _raises(_set(base(), path, value), field)
    assert "entries" in msg


@pytest.mark.parametrize(("path", "value", "field"), [
    (("actuation", "insertion"), 0.1, "actuation.insertion"),
    (("actuation", "rotation"), "0 0", "actuation.rotation"),
    (("load", "tip_force"), 1.0, "load.tip_force"),
    (("tubes", 0, "precurvature", "y"), 9.9, "tubes[0].precurvature.y"),
    (("tubes", 1, "precurvature", "x"), "abc", "tubes[1].precurvature.x"),
])
def test_lists_must_be_lists(path, value, field):
    _raises(_set(base(), path, value), field)


# ---------------------------------------------------------------------------------------------
# Every numeric field: NaN, +-inf, strings, bools, None

NUMERIC_FIELDS = [
    (("tubes", 0, "E"), "tubes[0].E"),
    (("tubes", 1, "G"), "tubes[1].G"),
    (("tubes", 0, "inner_diameter"), "tubes[0].inner_diameter"),
    (("tubes", 1, "outer_diameter"), "tubes[1].outer_diameter"),
    (("tubes", 0, "straight_length"), "tubes[0].straight_length"),
    (("tubes", 1, "curved_length"), "tubes[1].curved_length"),
    (("tubes", 0, "precurvature", "y", 0), "tubes[0].precurvature.y[0]"),
    (("tubes", 1, "precurvature", "y", 1), "tubes[1].precurvature.y[1]"),
    (("tubes", 0, "precurvature", "x", 0), "tubes[0].precurvature.x[0]"),
    (("actuation", "insertion", 1), "actuation.insertion[1]"),
    (("actuation", "rotation", 0), "actuation.rotation[0]"),
    (("load", "tip_force", 2), "load.tip_force[2]"),
    (("load", "tip_moment", 1), "load.tip_moment[1]"),
]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
@pytest.mark.parametrize(("path", "field"), NUMERIC_FIELDS, ids=[f for _, f in NUMERIC_FIELDS])
def test_non_finite(path, field, bad):
    msg = _raises(_set(base(), path, bad), field)
    assert "finite" in msg


@pytest.mark.parametrize("bad", ["1.0", "abc", True, False, None, [1.0], {"v": 1.0}],
                         ids=["numeric-str", "str", "true", "false", "none", "list", "dict"])
@pytest.mark.parametrize(("path", "field"), NUMERIC_FIELDS, ids=[f for _, f in NUMERIC_FIELDS])
def test_non_numbers(path, field, bad):
    msg = _raises(_set(base(), path, bad), field)
    assert "number" in msg


@pytest.mark.parametrize("value", [1, 0, 2**40])
def test_integers_are_numbers(value):
    d = _set(base(), ("actuation", "rotation", 1), value)
    assert Scene.from_dict(d).actuation.rotation[1] == float(value)


@pytest.mark.parametrize("name", [3, None, ["a"], True])
def test_tube_name_must_be_a_string(name):
    _raises(_set(base(), ("tubes", 1, "name"), name), "tubes[1].name")


# ---------------------------------------------------------------------------------------------
# Keys: unknown at every level, missing required ones, optional ones defaulted

@pytest.mark.parametrize(("path", "key", "field"), [
    ((), "tube", "tube"),
    ((), "loads", "loads"),
    (("tubes", 0), "youngs_modulus", "tubes[0].youngs_modulus"),
    (("tubes", 1), "length", "tubes[1].length"),
    (("tubes", 0, "precurvature"), "w", "tubes[0].precurvature.w"),
    (("tubes", 1, "precurvature"), "Y", "tubes[1].precurvature.Y"),
    (("actuation",), "translation", "actuation.translation"),
    (("load",), "tip_torque", "load.tip_torque"),
])
def test_unknown_keys(path, key, field):
    d = base()
    node = d
    for p in path:
        node = node[p]
    node[key] = 1.0
    msg = _raises(d, field)
    assert "unknown key" in msg and "allowed keys" in msg


@pytest.mark.parametrize(("path", "field"), [
    (("tubes",), "tubes"),
    (("actuation",), "actuation"),
    (("actuation", "insertion"), "actuation.insertion"),
    (("actuation", "rotation"), "actuation.rotation"),
    *[(("tubes", i, k), f"tubes[{i}].{k}") for i in (0, 1)
      for k in ("E", "G", "inner_diameter", "outer_diameter", "straight_length",
                "curved_length")],
])
def test_missing_required_keys(path, field):
    msg = _raises(_del(base(), path), field)
    assert "required" in msg


def test_optional_keys_default():
    d = base()
    del d["load"]
    for t in d["tubes"]:
        del t["name"], t["precurvature"]
    s = Scene.from_dict(d)
    assert [t.name for t in s.tubes] == ["tube1", "tube2"]
    assert all(t.precurvature == ((), (), ()) and not t.is_precurved for t in s.tubes)
    assert s.load == Load() and s.load.is_zero
    d = base()
    d["load"] = {"tip_force": [1.0, 0.0, 0.0]}
    assert Scene.from_dict(d).load.tip_moment == (0.0, 0.0, 0.0)
    d["load"] = None
    assert Scene.from_dict(d).load.is_zero


@pytest.mark.parametrize(("tubes", "fragment"), [
    ([], "tubes"),
    ("outer", "tubes"),
    (None, "tubes"),
    ([["E", 1]], "tubes[0]"),
])
def test_tubes_must_be_a_non_empty_list_of_mappings(tubes, fragment):
    _raises(_set(base(), ("tubes",), tubes), fragment)


@pytest.mark.parametrize("data", [[], "tubes: []", None, 3])
def test_scene_must_be_a_mapping(data):
    with pytest.raises(SceneError, match="scene"):
        Scene.from_dict(data)


@pytest.mark.parametrize(("key", "value"), [("actuation", [0.1, 0.2]), ("load", [0, 0, 0])])
def test_sections_must_be_mappings(key, value):
    _raises(_set(base(), (key,), value), key)


# ---------------------------------------------------------------------------------------------
# The dataclasses validate too (direct construction, replace, with_actuation, with_load)

def test_direct_construction_validates():
    s = Scene.from_dict(base())
    with pytest.raises(SceneError, match=r"tubes\[0\]\.E"):
        Scene((dataclasses.replace(s.tubes[0], E=-1.0), s.tubes[1]), s.actuation)
    with pytest.raises(SceneError, match=r"tubes\[1\]\.G"):
        Scene((s.tubes[0], dataclasses.replace(s.tubes[1], G=math.nan)), s.actuation)
    with pytest.raises(SceneError, match=r"tubes\[0\]\.precurvature\.y\[0\]"):
        Scene((dataclasses.replace(s.tubes[0], precurvature=((), (math.inf,), ())),
               s.tubes[1]), s.actuation)
    with pytest.raises(SceneError, match="tubes"):
        Scene(list(s.tubes), s.actuation)  # type: ignore[arg-type]
    with pytest.raises(SceneError, match="tubes"):
        Scene((), Actuation((), ()))
    with pytest.raises(SceneError, match=r"actuation\.rotation"):
        Scene(s.tubes, Actuation((0.1, 0.2), (0.0,)))
    with pytest.raises(SceneError, match=r"load\.tip_force"):
        Scene(s.tubes, s.actuation, Load((0.0, 0.0), (0.0, 0.0, 0.0)))  # type: ignore[arg-type]
    with pytest.raises(SceneError, match="actuation"):
        Scene(s.tubes, (0.1, 0.2))  # type: ignore[arg-type]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.tubes[0].E = 1.0  # type: ignore[misc]


def test_with_actuation_and_with_load_validate():
    s = Scene.from_dict(base())
    t = s.with_actuation(rotation=[0.0, 1.0])
    assert t.actuation.rotation == (0.0, 1.0) and t.actuation.insertion == s.actuation.insertion
    with pytest.raises(SceneError, match=r"actuation\.insertion\[1\]"):
        s.with_actuation(insertion=[0.2, 0.1])
    with pytest.raises(SceneError, match=r"actuation\.insertion\[0\]"):
        s.with_actuation(insertion=[-0.1, 0.1])
    with pytest.raises(SceneError, match=r"actuation\.rotation\[1\]"):
        s.with_actuation(rotation=[0.0, math.nan])
    assert s.with_load(tip_force=[1, 2, 3]).load.tip_force == (1.0, 2.0, 3.0)
    with pytest.raises(SceneError, match=r"load\.tip_moment\[2\]"):
        s.with_load(tip_moment=[0.0, 0.0, math.inf])


def test_derived_quantities():
    s = Scene.from_dict(base())
    outer = s.tubes[0]
    assert outer.length == pytest.approx(185.8 * MM)
    assert outer.second_moment == pytest.approx(math.pi * (2.39e-3**4 - 2.01e-3**4) / 64)
    assert outer.bending_stiffness == pytest.approx(58e9 * outer.second_moment)
    assert outer.torsional_stiffness == pytest.approx(21.5e9 * 2 * outer.second_moment)
    assert s.tubes[1].precurvature_at(0.1) == pytest.approx((0.0, 13.8 + 0.05, 0.0))
    assert s.exposed_lengths() == pytest.approx((92.3 * MM, 95.0 * MM))
    assert s.with_actuation(insertion=[0.5, 0.5]).exposed_lengths() == (0.0, 0.0)


# ---------------------------------------------------------------------------------------------
# Built-in scenes against the paper (Renda et al., RA-L 2021, Table I, Fig. 3, section III-B)

def test_builtin_scene_names():
    names = builtin_scenes()
    assert {"renda2021_fig3", "renda2021_section3b"} <= set(names)
    assert names == sorted(names)


@pytest.mark.parametrize("name", ["renda2021_fig3", "renda2021_section3b"])
def test_builtin_table1(name):
    s = load_scene(name)
    assert s.n_tubes == 2
    outer, inner = s.tubes
    for t in s.tubes:
        assert t.E == pytest.approx(58e9) and t.G == pytest.approx(21.5e9)
    assert (outer.inner_diameter, outer.outer_diameter) == pytest.approx((2.01 * MM, 2.39 * MM))
    assert (inner.inner_diameter, inner.outer_diameter) == pytest.approx((0.0, 1.6 * MM))
    assert outer.precurvature_at(0.0) == pytest.approx((0.0, 9.9, 0.0))   # 0.0099 1/mm
    assert inner.precurvature_at(0.0) == pytest.approx((0.0, 13.8, 0.0))  # 0.0138 1/mm
    assert s.load.is_zero
    assert Scene.from_dict(s.to_dict()) == s


def test_builtin_fig3():
    s = load_scene("renda2021_fig3")
    outer, inner = s.tubes
    assert (outer.straight_length, inner.straight_length) == pytest.approx((93.5 * MM,
                                                                           218.5 * MM))
    assert (outer.curved_length, inner.curved_length) == pytest.approx((92.3 * MM, 85.0 * MM))
    assert s.actuation.insertion == pytest.approx((93.5 * MM, 208.5 * MM))
    alpha1, alpha2 = s.actuation.rotation
    assert alpha1 == 0.0
    deg = math.degrees(alpha2)  # one step of the paper's 0..280 deg sweep in 20 deg steps
    assert 0.0 <= deg <= 280.0 and deg / 20.0 == pytest.approx(round(deg / 20.0))


def test_builtin_section3b():
    s = load_scene("renda2021_section3b")
    outer, inner = s.tubes
    assert (outer.length, inner.length) == pytest.approx((140 * MM, 200 * MM))
    assert outer.straight_length == 0.0 and inner.straight_length == 0.0  # fully curved
    assert s.actuation.insertion == (0.0, 0.0)                           # bases at the orifice
    assert s.actuation.rotation == pytest.approx((0.0, math.pi))
    assert s.exposed_lengths() == pytest.approx((140 * MM, 200 * MM))


def test_unknown_scene_name_lists_builtins():
    with pytest.raises(SceneError) as info:
        load_scene("renda2021_fig99")
    msg = str(info.value)
    assert "renda2021_fig99" in msg
    for name in builtin_scenes():
        assert name in msg


# ---------------------------------------------------------------------------------------------
# Files: YAML and JSON give the same scene

YAML_TEXT = """\
# the same scene as BASE, written by hand with YAML-1.1-unfriendly floats (58.0e9, 1e-3)
tubes:
  - name: outer
    E: 58.0e9
    G: 21.5e9
    inner_diameter: 2.01e-3
    outer_diameter: 2.39e-3
    straight_length: 93.5e-3
    curved_length: 92.3e-3
    precurvature: {x: [0.0], y: [9.9], z: [0.0]}
  - name: inner
    E: 58e9
    G: 21.5E+9
    inner_diameter: 0
    outer_diameter: 1.6e-3
    straight_length: 218.5e-3
    curved_length: 85.0e-3
    precurvature:
      y: [13.8, 0.5]
actuation:
  insertion: [93.5e-3, 208.5e-3]
  rotation: [0, 3.141592653589793]
load:
  tip_force: [0.0, 0.1, 0.0]
  tip_moment: [0.0, 0.0, 1e-2]
"""


def test_yaml_and_json_files_give_the_same_scene(tmp_path):
    expected = Scene.from_dict(base())
    (tmp_path / "hand.yaml").write_text(YAML_TEXT)
    (tmp_path / "dump.yml").write_text(yaml.safe_dump(base()))
    (tmp_path / "dump.json").write_text(json.dumps(base(), indent=2))
    (tmp_path / "noext").write_text(yaml.safe_dump(base()))
    for name in ("hand.yaml", "dump.yml", "dump.json", "noext"):
        assert load_scene(tmp_path / name) == expected, name
        assert load_scene(str(tmp_path / name)) == expected, name


@pytest.mark.parametrize(("name", "text", "fragment"), [
    ("broken.yaml", "tubes: [\n", "broken.yaml"),
    ("broken.json", '{"tubes": [}', "broken.json"),
    ("list.yaml", "- 1\n- 2\n", "scene"),
    ("empty.yaml", "", "scene"),
    ("nested.yaml", YAML_TEXT.replace("outer_diameter: 1.6e-3", "outer_diameter: 2.2e-3"),
     "tubes[1].outer_diameter"),
])
def test_bad_files(tmp_path, name, text, fragment):
    (tmp_path / name).write_text(text)
    with pytest.raises(SceneError) as info:
        load_scene(tmp_path / name)
    assert fragment in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nope.yaml")


# ---------------------------------------------------------------------------------------------
# Round trip and pass-through

@pytest.mark.parametrize("source", ["base", "renda2021_fig3", "renda2021_section3b"])
def test_to_dict_from_dict_round_trip(source):
    s = Scene.from_dict(base()) if source == "base" else load_scene(source)
    d = s.to_dict()
    assert Scene.from_dict(d) == s
    assert Scene.from_dict(json.loads(json.dumps(d))) == s
    assert Scene.from_dict(yaml.safe_load(yaml.safe_dump(d))) == s
    assert load_scene(s) is s
    assert load_scene(d) == s


# ---------------------------------------------------------------------------------------------
# --set overrides

@pytest.mark.parametrize(("override", "check"), [
    ("actuation.rotation[1]=0.5", lambda s: s.actuation.rotation[1] == 0.5),
    ("actuation.rotation=[0.1, 0.2]", lambda s: s.actuation.rotation == (0.1, 0.2)),
    ("actuation.insertion[1]=0.25", lambda s: s.actuation.insertion[1] == 0.25),
    ("tubes[0].E=6e10", lambda s: s.tubes[0].E == 6e10),
    ("tubes[1].precurvature.y=[1.0, 2.0]", lambda s: s.tubes[1].precurvature[1] == (1.0, 2.0)),
    ("tubes[1].precurvature.x[0]=0.5", None),  # x is not set: there is no x[0] to set
    ("load.tip_force=[0, 0.1, 0]", lambda s: s.load.tip_force == (0.0, 0.1, 0.0)),
    ("load.tip_moment=[0, 0, 1e-3]", lambda s: s.load.tip_moment == (0.0, 0.0, 1e-3)),
    ("tubes[1].name=rod", lambda s: s.tubes[1].name == "rod"),
])
def test_overrides(override, check):
    if check is None:
        with pytest.raises(SceneError, match=r"tubes\[1\]\.precurvature\.x"):
            load_scene("renda2021_fig3", [override])
        return
    s = load_scene("renda2021_fig3", [override])
    assert check(s)
    assert load_scene(load_scene("renda2021_fig3"), [override]) == s   # Scene source
    assert load_scene(load_scene("renda2021_fig3").to_dict(), [override]) == s  # mapping


def test_overrides_apply_in_order_and_do_not_mutate():
    d = base()
    out = apply_overrides(d, ["actuation.rotation[1]=0.5", "actuation.rotation[1]=0.7"])
    assert out["actuation"]["rotation"][1] == 0.7
    assert d == BASE
    s = load_scene("renda2021_fig3", ["actuation.rotation[1]=0.5", "tubes[0].G=2e10"])
    assert s.actuation.rotation[1] == 0.5 and s.tubes[0].G == 2e10


def test_override_adds_a_missing_load():
    s = load_scene("renda2021_fig3", ["load.tip_force=[0.0, 0.0, -0.1]"])
    assert s.load.tip_force == (0.0, 0.0, -0.1) and s.load.tip_moment == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(("override", "fragment"), [
    ("actuation.rotation[1]", "KEY=VALUE"),
    ("tubes[5].E=1", "tubes[5].E"),
    ("actuation.rotation[7]=1", "actuation.rotation[7]"),
    ("actuation.rotation[0].x=1", "actuation.rotation[0].x"),
    ("1tubes=2", "1tubes"),
    ("tubes[a].E=2", "tubes[a].E"),
    ("foo=1", "foo"),
    ("tubes[0].young=1", "tubes[0].young"),
    ("actuation.speed=1", "actuation.speed"),
    ("actuation.rotation[1]=abc", "actuation.rotation[1]"),
    ("actuation.insertion[1]=-1", "actuation.insertion[1]"),
    ("tubes[1].outer_diameter=3e-3", "tubes[1].outer_diameter"),
    ("tubes[0].E=.nan", "tubes[0].E"),
    ("load.tip_force=[1, 2]", "load.tip_force"),
    ("load.tip_moment[2]=1e-3", "load.tip_moment"),  # renda2021_fig3 has no load to index
])
def test_bad_overrides(override, fragment):
    with pytest.raises(SceneError) as info:
        load_scene("renda2021_fig3", [override])
    assert fragment in str(info.value)


# ---------------------------------------------------------------------------------------------
# Property tests: random valid scenes construct and round-trip; broken rules always raise

finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def valid_scenes(draw) -> dict:
    n = draw(st.integers(2, 3))
    od = draw(st.floats(0.5e-3, 5e-3))
    tubes = []
    for j in range(n):
        last = j == n - 1
        solid = last and draw(st.booleans())
        idia = 0.0 if solid else od * draw(st.floats(0.3, 0.95))
        straight = draw(st.floats(0.0, 0.3))
        curved = draw(st.floats(0.0, 0.3))
        if straight + curved <= 0.0:
            curved = 0.05
        tube = {
            "E": draw(st.floats(1e8, 3e11)), "G": draw(st.floats(1e8, 1.5e11)),
            "inner_diameter": idia, "outer_diameter": od,
            "straight_length": straight, "curved_length": curved,
            "precurvature": {ax: draw(st.lists(st.floats(-50, 50), max_size=3))
                             for ax in draw(st.sets(st.sampled_from("xyz")))},
        }
        if draw(st.booleans()):
            tube["name"] = draw(st.text(max_size=8))
        tubes.append(tube)
        od = idia * draw(st.floats(0.5, 1.0))  # the next tube fits inside
    insertion = sorted(draw(st.lists(st.floats(0.0, 0.5), min_size=n, max_size=n)))
    data = {
        "tubes": tubes,
        "actuation": {"insertion": insertion,
                      "rotation": draw(st.lists(st.floats(-10, 10), min_size=n, max_size=n))},
    }
    if draw(st.booleans()):
        data["load"] = {"tip_force": draw(st.lists(st.floats(-1, 1), min_size=3, max_size=3)),
                        "tip_moment": draw(st.lists(st.floats(-0.1, 0.1), min_size=3,
                                                    max_size=3))}
    return data


@settings(max_examples=60, deadline=None)
@given(valid_scenes())
def test_random_valid_scenes_construct_and_round_trip(data):
    s = Scene.from_dict(data)
    assert s.n_tubes == len(data["tubes"])
    assert all(isinstance(t, Tube) for t in s.tubes)
    assert Scene.from_dict(s.to_dict()) == s
    assert Scene.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    assert all(l >= 0.0 for l in s.exposed_lengths())


@settings(max_examples=40, deadline=None)
@given(valid_scenes(), st.data())
def test_random_broken_nesting_or_ordering_raises(data, draw):
    n = len(data["tubes"])
    j = draw.draw(st.integers(1, n - 1))
    if draw.draw(st.booleans()):
        outer_id = data["tubes"][j - 1]["inner_diameter"]
        data["tubes"][j]["outer_diameter"] = outer_id * draw.draw(st.floats(1.001, 2.0))
        data["tubes"][j]["inner_diameter"] = min(data["tubes"][j]["inner_diameter"],
                                                 0.5 * data["tubes"][j]["outer_diameter"])
        field = f"tubes[{j}].outer_diameter"
    else:
        ins = data["actuation"]["insertion"]
        ins[j] = ins[j - 1] - draw.draw(st.floats(1e-6, 0.1))
        field = f"actuation.insertion[{j}]"
    with pytest.raises(SceneError) as info:
        Scene.from_dict(data)
    assert field in str(info.value)


# ---------------------------------------------------------------------------------------------
# Regression: inputs that used to escape as internal exceptions or were silently
# reinterpreted. Each is an error naming the field (or the file) and the rule.

@settings(max_examples=40, deadline=None)
@given(st.sampled_from(NUMERIC_FIELDS),
       st.integers(min_value=2**1024, max_value=10**700), st.booleans())
def test_integers_beyond_the_float_range_name_the_field(path_field, big, negative):
    """A 400-digit E used to raise OverflowError from float(); now a SceneError names it."""
    path, field = path_field
    msg = _raises(_set(base(), path, -big if negative else big), field)
    assert "float range" in msg and "digits" in msg
    assert str(big)[:80] not in msg  # the value is summarized, not echoed whole


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_huge_integer_in_a_file_or_set_names_the_field(tmp_path, suffix):
    big = int("9" * 400)
    d = _set(base(), ("tubes", 0, "E"), big)
    path = tmp_path / f"big{suffix}"
    path.write_text(json.dumps(d) if suffix == ".json" else yaml.safe_dump(d))
    with pytest.raises(SceneError, match=r"tubes\[0\]\.E .*float range"):
        load_scene(path)
    with pytest.raises(SceneError, match=r"tubes\[1\]\.G .*float range"):
        load_scene("renda2021_fig3", [f"tubes[1].G={big}"])
    # beyond Python's int() digit limit (4300) the parser itself refuses: still a SceneError
    # that names the file / the --set
    path.write_text(json.dumps(d).replace(str(big), "9" * 5000))
    with pytest.raises(SceneError, match=f"big{suffix}"):
        load_scene(path)
    with pytest.raises(SceneError, match=r"tubes\[0\]\.E"):
        load_scene("renda2021_fig3", ["tubes[0].E=" + "9" * 5000])


def _half_values():
    import numpy as np
    import torch
    return [np.float16(2.0), torch.tensor(2.0, dtype=torch.float16),
            torch.tensor(2.0, dtype=torch.bfloat16)]


@pytest.mark.parametrize("value", _half_values(), ids=["np.float16", "torch.half", "bfloat16"])
@pytest.mark.parametrize(("path", "field"), NUMERIC_FIELDS, ids=[f for _, f in NUMERIC_FIELDS])
def test_half_precision_numbers_are_refused(path, field, value):
    msg = _raises(_set(base(), path, value), field)
    assert "precision" in msg


def test_single_and_double_precision_scalars_become_python_floats():
    import numpy as np
    import torch
    d = base()
    d["tubes"][0]["E"] = np.float32(58e9)
    d["tubes"][1]["G"] = torch.tensor(21.5e9, dtype=torch.float64)
    d["actuation"]["rotation"] = np.array([0.0, 1.0])
    d["load"]["tip_force"] = torch.tensor([0.0, 0.1, 0.0], dtype=torch.float64)
    s = Scene.from_dict(d)
    assert type(s.tubes[0].E) is float and s.tubes[0].E == float(np.float32(58e9))
    assert type(s.tubes[1].G) is float and s.tubes[1].G == 21.5e9
    assert all(type(v) is float for v in s.actuation.rotation + s.load.tip_force)
    # direct construction stores floats too (no float32 arithmetic downstream)
    t = Scene((dataclasses.replace(s.tubes[0], E=np.float32(6e10)), s.tubes[1]), s.actuation)
    assert type(t.tubes[0].E) is float
    for bad in (np.array([[0.0, 1.0]]), 1j, torch.tensor([0.0, 1.0])):
        with pytest.raises(SceneError, match=r"actuation\.rotation"):
            Scene.from_dict(_set(base(), ("actuation", "rotation", 1), bad))


def test_with_actuation_and_with_load_refuse_what_from_dict_refuses():
    """with_actuation used float(v) on anything: '0.1' (a string) and bfloat16 tensors passed."""
    import numpy as np
    import torch
    s = Scene.from_dict(base())
    with pytest.raises(SceneError, match=r"actuation\.insertion\[0\] must be a number"):
        s.with_actuation(insertion=["0.1", "0.2"])
    with pytest.raises(SceneError, match=r"actuation\.rotation\[0\].*precision"):
        s.with_actuation(rotation=torch.zeros(2, dtype=torch.bfloat16))
    with pytest.raises(SceneError, match=r"load\.tip_force\[1\] must be a number"):
        s.with_load(tip_force=[0.0, True, 0.0])
    with pytest.raises(SceneError, match=r"load\.tip_moment must have 3 entries"):
        s.with_load(tip_moment=[0.0, 0.0])
    t = s.with_actuation(rotation=np.array([0.0, 0.5]), insertion=torch.tensor([0.1, 0.21],
                                                                          dtype=torch.float64))
    assert t.actuation.rotation == (0.0, 0.5) and t.actuation.insertion == (0.1, 0.21)


@pytest.mark.parametrize("value", [0, 0.0, False, [], "", [0, 0, 0], "none"],
                         ids=["0", "0.0", "false", "[]", "empty-str", "list", "str"])
@pytest.mark.parametrize(("path", "field"), [
    (("load",), "load"),
    (("tubes", 0, "precurvature"), "tubes[0].precurvature"),
    (("tubes", 1, "precurvature"), "tubes[1].precurvature"),
])
def test_falsy_or_scalar_sections_are_not_read_as_absent(path, field, value):
    """`precurvature: 0` and `load: 0` used to be read as absent (``x or {}``)."""
    msg = _raises(_set(base(), path, value), field)
    assert "must be a mapping" in msg


@pytest.mark.parametrize("value", [None, {}])
def test_null_or_empty_sections_mean_none(value):
    d = _set(_set(base(), ("load",), value), ("tubes", 0, "precurvature"), value)
    s = Scene.from_dict(d)
    assert s.load.is_zero and not s.tubes[0].is_precurved and s.tubes[1].is_precurved


def test_yaml_files_with_zero_sections(tmp_path):
    text = YAML_TEXT.replace("precurvature: {x: [0.0], y: [9.9], z: [0.0]}", "precurvature: 0")
    (tmp_path / "pc0.yaml").write_text(text)
    with pytest.raises(SceneError, match=r"tubes\[0\]\.precurvature must be a mapping"):
        load_scene(tmp_path / "pc0.yaml")
    text = YAML_TEXT.split("load:")[0] + "load: 0\n"
    (tmp_path / "load0.yaml").write_text(text)
    with pytest.raises(SceneError, match="load must be a mapping"):
        load_scene(tmp_path / "load0.yaml")
    (tmp_path / "load_empty.yaml").write_text(YAML_TEXT.split("load:")[0] + "load:\n")
    assert load_scene(tmp_path / "load_empty.yaml").load.is_zero


@pytest.mark.parametrize(("override", "field"), [
    ("load.tip_force[1]=0.1", "load.tip_force"),
    ("load.tip_moment[0]=1e-3", "load.tip_moment"),
    ("tubes[1].precurvature.x[0]=0.5", "tubes[1].precurvature.x"),
    ("tubes[0].precurvature.z[2]=1", "tubes[0].precurvature.z"),
])
def test_set_an_element_of_an_absent_list(override, field):
    """Used to build ``{1: 0.1}`` and report "got {1: 0.1}"; now says what is missing."""
    with pytest.raises(SceneError) as info:
        load_scene("renda2021_fig3", [override])
    msg = str(info.value)
    assert f"{field} is not in the scene" in msg and f"--set {field}=" in msg
    assert "{" not in msg.split(":", 1)[1]


def test_set_an_index_out_of_range_says_the_size():
    with pytest.raises(SceneError, match=r"actuation\.rotation\[5\].*2 entries"):
        load_scene("renda2021_fig3", ["actuation.rotation[5]=1"])


@pytest.mark.parametrize(("content", "fragment"), [
    (bytes(range(256)), "not a UTF-8 text file"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a UTF-8 text file"),
    (b"tubes: []\x00\x00", "NUL bytes"),
    (b"\xff\xfe\x00t\x00u", "not a UTF-8 text file"),
])
@pytest.mark.parametrize("name", ["scene.yaml", "scene.json", "noext"])
def test_binary_scene_files_name_the_file(tmp_path, content, fragment, name):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert str(path) in str(info.value) and fragment in str(info.value)


@pytest.mark.parametrize("source", ["", " ", "\t"])
def test_empty_scene_name(source):
    with pytest.raises(SceneError, match="scene name is empty.*renda2021_fig3"):
        load_scene(source)


def test_directory_as_scene(tmp_path):
    with pytest.raises(SceneError, match=f"{tmp_path.name}.* is a directory"):
        load_scene(tmp_path)
    with pytest.raises(SceneError, match=r"scene must be a file path.*int"):
        load_scene(3)  # type: ignore[arg-type]
