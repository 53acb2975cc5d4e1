"""The ``torchpvs`` command line: exit codes, the JSON contract of docs/conventions.md, one-line
errors, tables, plots and the demo.

Error paths never reach a solver. The output format is checked against fake solvers injected
as ``torchpvs.reference`` / ``torchpvs.solver``; the real models are checked when importable.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchpvs.cli import CONTRACT_KEYS, EXTENSION_KEYS, main
from torchpvs.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
EXPECTED_KEYS = {
    "model", "converged", "tip_position", "tip_rotation", "relative_rotation_at_outer_tip",
    "actuation_forces", "actuation_torques", "energy", "stable", "min_stiffness_eigenvalue",
    "residual_norm", "iterations", "dofs", "solve_time_s",
}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def run_captured(*argv: str) -> tuple[int, str, str]:
    """``main`` with stdout/stderr captured without capsys (for module-scoped fixtures)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue(), err.getvalue()


def one_line(err: str) -> str:
    assert err.endswith("\n") and err.count("\n") == 1, f"not one line: {err!r}"
    return err


def strict_json(text: str):
    """Parse exactly one JSON object; NaN/Infinity are not JSON."""
    def reject(name):
        raise ValueError(f"non-standard JSON constant {name}")
    obj = json.loads(text, parse_constant=reject)
    assert isinstance(obj, dict)
    return obj


def test_contract_keys_match_conventions():
    assert set(CONTRACT_KEYS) == EXPECTED_KEYS and len(CONTRACT_KEYS) == len(EXPECTED_KEYS)


# ---------------------------------------------------------------------------------------------
# Bad scenes and bad arguments: exit 2, one line on stderr naming the field, nothing on stdout.
# None of these reaches a solver.

@pytest.fixture
def no_solvers(monkeypatch):
    """Make both models unimportable, so a test passes only if it never needs one."""
    monkeypatch.setitem(sys.modules, "torchpvs.reference", None)
    monkeypatch.setitem(sys.modules, "torchpvs.solver", None)


@pytest.fixture
def bad_nesting_file(tmp_path) -> Path:
    data = load_scene("renda2021_fig3").to_dict()
    data["tubes"][1]["outer_diameter"] = 2.2e-3
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


COMMANDS = [("solve",), ("plot", "-o", "unused.png")]


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize("cmd", COMMANDS, ids=["solve", "plot"])
@pytest.mark.parametrize(("scene", "fragments"), [
    ("renda2021_fig99", ["renda2021_fig99", "renda2021_fig3", "renda2021_section3b"]),
    ("missing/dir/scene.yaml", ["scene.yaml", "does not exist"]),
])
def test_unknown_scene(capsys, cmd, scene, fragments):
    code, out, err = run(capsys, cmd[0], scene, *cmd[1:])
    assert code == 2 and out == ""
    one_line(err)
    assert err.startswith(f"torchpvs {cmd[0]}: ")
    for f in fragments:
        assert f in err


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize("cmd", COMMANDS, ids=["solve", "plot"])
def test_bad_scene_file(capsys, cmd, bad_nesting_file):
    code, out, err = run(capsys, cmd[0], str(bad_nesting_file), *cmd[1:])
    assert code == 2 and out == ""
    assert "tubes[1].outer_diameter" in one_line(err)
    assert "tubes[0].inner_diameter" in err


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize(("name", "text", "fragment"), [
    ("broken.yaml", "tubes: [\n  - {E: 1\n", "broken.yaml"),
    ("broken.json", '{"tubes": [}', "broken.json"),
    ("list.yaml", "- 1\n", "scene"),
    ("unknown.yaml", "tubes: []\nactuation: {}\nspeed: 1\n", "speed"),
])
def test_unreadable_scene_file(capsys, tmp_path, name, text, fragment):
    (tmp_path / name).write_text(text)
    code, out, err = run(capsys, "solve", str(tmp_path / name), "--json")
    assert code == 2 and out == ""
    assert fragment in one_line(err)


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize("cmd", COMMANDS, ids=["solve", "plot"])
@pytest.mark.parametrize(("override", "fragment"), [
    ("actuation.insertion[1]=-1", "actuation.insertion[1]"),
    ("actuation.insertion[1]=0.01", "actuation.insertion[1]"),
    ("actuation.rotation[1]=abc", "actuation.rotation[1]"),
    ("actuation.rotation=[0]", "actuation.rotation"),
    ("tubes[1].outer_diameter=3e-3", "tubes[1].outer_diameter"),
    ("tubes[0].E=0", "tubes[0].E"),
    ("tubes[0].E=.nan", "tubes[0].E"),
    ("tubes[4].E=1", "tubes[4].E"),
    ("tubes[0].E=[1", "tubes[0].E"),          # the value is not YAML
    ("tubes[0].young=1", "tubes[0].young"),
    ("load.tip_force=[1, 2]", "load.tip_force"),
    ("foo=1", "foo"),
    ("nokey", "nokey"),
])
def test_bad_set(capsys, cmd, override, fragment):
    code, out, err = run(capsys, cmd[0], "renda2021_fig3", "--set", override, *cmd[1:])
    assert code == 2 and out == ""
    assert fragment in one_line(err)


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize(("argv", "fragment"), [
    (["solve", "renda2021_fig3", "--backbone", "1"], "--backbone"),
    (["solve", "renda2021_fig3", "--backbone", "0"], "--backbone"),
    (["solve", "renda2021_fig3", "--backbone", "-3"], "--backbone"),
    (["solve", "renda2021_fig3", "--backbone", "abc"], "--backbone"),
    (["solve", "renda2021_fig3", "--backbone", "2.5"], "--backbone"),
    (["solve", "renda2021_fig3", "--backbone"], "--backbone"),
    (["solve", "renda2021_fig3", "--model", "exact"], "--model"),
    (["solve", "renda2021_fig3", "--set"], "--set"),
    (["solve", "renda2021_fig3", "--frobnicate"], "--frobnicate"),
    (["solve"], "SCENE"),
    (["plot", "renda2021_fig3"], "-o"),
    (["plot", "renda2021_fig3", "-o", "x.png", "--points", "1"], "--points"),
    (["demo", "--bogus"], "--bogus"),
    (["scenes", "extra"], "extra"),
    (["fly"], "fly"),
    ([], "COMMAND"),
])
def test_bad_arguments(capsys, argv, fragment):
    code, out, err = run(capsys, *argv)
    assert code == 2 and out == ""
    assert fragment in one_line(err)
    assert err.startswith("torchpvs")


@pytest.mark.parametrize(("model", "module"), [("pvs", "torchpvs.solver"),
                                                ("standard", "torchpvs.reference")])
@pytest.mark.parametrize("cmd", COMMANDS, ids=["solve", "plot"])
def test_model_not_available(capsys, monkeypatch, model, module, cmd):
    monkeypatch.setitem(sys.modules, module, None)  # importing it raises ImportError
    code, out, err = run(capsys, cmd[0], "renda2021_fig3", "--model", model, *cmd[1:])
    assert code == 2 and out == ""
    assert err == f"torchpvs {cmd[0]}: --model {model} is not available yet\n"


def test_default_model_is_pvs(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "torchpvs.solver", None)
    code, _, err = run(capsys, "solve", "renda2021_fig3")
    assert code == 2 and "--model pvs is not available yet" in err


def test_help_and_scenes(capsys):
    code, out, err = run(capsys, "--help")
    assert code == 0 and "solve" in out and "demo" in out
    code, out, err = run(capsys, "solve", "--help")
    assert code == 0 and "--backbone" in out and "--set" in out
    code, out, err = run(capsys, "scenes")
    assert code == 0 and err == ""
    assert out.split() == sorted(out.split())
    assert {"renda2021_fig3", "renda2021_section3b"} <= set(out.split())


# ---------------------------------------------------------------------------------------------
# The output format, against fake solvers (fast, independent of the real models)

TIP = [0.040146, 0.011838, 0.080710]


class FakeSolution:
    """Duck-typed solution: ``as_contract``, ``converged``, ``backbone``."""

    def __init__(self, scene, model: str, *, converged: bool = True, torch_backbone=False,
                 chatter: bool = False, energy: float = 0.0495, tip=TIP):
        self.scene, self.model, self.converged = scene, model, converged
        self.torch_backbone, self.chatter, self.energy, self.tip = (torch_backbone, chatter,
                                                                    energy, tip)

    def backbone(self, points: int = 100):
        if self.chatter:
            print("fake solver: computing the backbone")  # must not reach stdout with --json
        t = np.linspace(0.0, 1.0, points)[:, None]
        pts = np.hstack([t**2 * self.tip[0], t**2 * self.tip[1], t * self.tip[2]])
        if self.torch_backbone:
            import torch

            return torch.as_tensor(pts)[None]  # (1, K, 3) tensor
        return pts

    def as_contract(self, backbone_points: int | None = None) -> dict:
        n = self.scene.n_tubes
        out = {
            "model": self.model, "converged": self.converged, "tip_position": list(self.tip),
            "tip_rotation": [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]],  # 90 deg on x
            "relative_rotation_at_outer_tip": [math.radians(15.0)] * (n - 1),
            "actuation_forces": [2.5968, -0.446][:n], "actuation_torques": [-0.0495, 0.0495][:n],
            "energy": self.energy, "stable": True, "min_stiffness_eigenvalue": 1.4e-4,
            "residual_norm": 4e-16, "iterations": 2, "dofs": 34, "solve_time_s": 0.01,
        }
        if backbone_points is not None:
            out["backbone"] = self.backbone(backbone_points).tolist() if not \
                self.torch_backbone else self.backbone(backbone_points)[0].tolist()
        return out


@pytest.fixture
def fakes(monkeypatch):
    """Install fake ``torchpvs.reference.solve_standard`` and ``torchpvs.solver.solve``; returns
    a dict of options (``converged``, ``torch_backbone``, ...) and the scenes they were given."""
    state: dict = {"options": {}, "scenes": []}

    def make(model):
        def solver(scene):
            state["scenes"].append(scene)
            opts = dict(state["options"])
            if opts.pop("warn", False):
                import warnings

                warnings.warn("fake: 1 of 1 element(s) did not converge\n(details)",
                              RuntimeWarning, stacklevel=2)
            if opts.get("chatter"):
                print("fake solver: iteration 1")
            if model == "pvs" and "pvs_tip" in opts:
                opts["tip"] = opts.pop("pvs_tip")
            opts.pop("pvs_tip", None)
            return FakeSolution(scene, model, **opts)
        return solver

    ref = types.ModuleType("torchpvs.reference")
    ref.solve_standard = make("standard")
    pvs = types.ModuleType("torchpvs.solver")
    pvs.solve = make("pvs")
    monkeypatch.setitem(sys.modules, "torchpvs.reference", ref)
    monkeypatch.setitem(sys.modules, "torchpvs.solver", pvs)
    return state


@pytest.mark.parametrize("model", ["pvs", "standard"])
def test_json_contract(capsys, fakes, model):
    code, out, err = run(capsys, "solve", "renda2021_fig3", "--model", model, "--json")
    assert code == 0 and err == ""
    assert out.endswith("\n") and out.count("\n") == 1
    obj = strict_json(out)
    assert set(obj) == EXPECTED_KEYS
    assert obj["model"] == model and obj["converged"] is True


@pytest.mark.parametrize("k", [2, 7])
def test_json_backbone(capsys, fakes, k):
    code, out, _ = run(capsys, "solve", "renda2021_fig3", "--json", "--backbone", str(k))
    obj = strict_json(out)
    assert code == 0 and set(obj) == EXPECTED_KEYS | {"backbone"}
    assert len(obj["backbone"]) == k and all(len(p) == 3 for p in obj["backbone"])


def test_not_converged_still_prints(capsys, fakes):
    fakes["options"] = {"converged": False, "warn": True}
    code, out, err = run(capsys, "solve", "renda2021_fig3", "--json")
    assert code == 1
    assert strict_json(out)["converged"] is False
    assert "did not converge" in one_line(err)  # the solver's warning, on one line
    code, out, _ = run(capsys, "solve", "renda2021_fig3")
    assert code == 1 and "converged" in out and " no" in out


def test_non_finite_values_become_null(capsys, fakes):
    fakes["options"] = {"energy": float("nan")}
    code, out, _ = run(capsys, "solve", "renda2021_fig3", "--json")
    assert code == 0 and strict_json(out)["energy"] is None


def test_solver_chatter_stays_off_stdout(capsys, fakes):
    fakes["options"] = {"chatter": True}
    code, out, err = run(capsys, "solve", "renda2021_fig3", "--json", "--backbone", "3")
    assert code == 0 and len(strict_json(out)["backbone"]) == 3
    assert "iteration 1" in err


def test_set_reaches_the_solver(capsys, fakes):
    code, _, _ = run(capsys, "solve", "renda2021_fig3", "--model", "standard", "--json",
                     "--set", "actuation.rotation[1]=0.5", "--set", "tubes[0].E=6e10")
    assert code == 0
    (scene,) = fakes["scenes"]
    assert scene.actuation.rotation == (0.0, 0.5) and scene.tubes[0].E == 6e10


def test_scene_file_reaches_the_solver(capsys, fakes, tmp_path):
    path = tmp_path / "s.json"
    path.write_text(json.dumps(load_scene("renda2021_section3b").to_dict()))
    code, out, _ = run(capsys, "solve", str(path), "--json")
    assert code == 0 and set(strict_json(out)) == EXPECTED_KEYS
    assert fakes["scenes"][0] == load_scene("renda2021_section3b")


def test_table(capsys, fakes):
    code, out, err = run(capsys, "solve", "renda2021_fig3", "--model", "standard")
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert "renda2021_fig3" in lines[0] and "standard" in lines[1]

    def row(label):
        (line,) = [ln for ln in lines if ln.strip().startswith(label)]
        return line

    assert row("converged").split()[-1] == "yes"
    assert "[mm]" in row("tip position x") and float(row("tip position x").split()[-1]) == \
        pytest.approx(40.146)
    assert float(row("tip position z").split()[-1]) == pytest.approx(80.710)
    assert "[deg]" in row("tip rotation angle")
    assert float(row("tip rotation angle").split()[-1]) == pytest.approx(90.0)
    assert float(row("rotation inner vs outer").split()[-1]) == pytest.approx(15.0)
    assert "[N]" in row("actuation force D1 (outer)")
    assert float(row("actuation force D2 (inner)").split()[-1]) == pytest.approx(-0.446)
    assert "[mN·m]" in row("actuation torque alpha1")
    assert float(row("actuation torque alpha2").split()[-1]) == pytest.approx(49.5)
    assert "[mJ]" in row("energy") and float(row("energy").split()[-1]) == pytest.approx(49.5)
    for label in ("stable", "min stiffness eigenvalue", "residual norm", "iterations", "dofs",
                  "solve time"):
        row(label)
    # aligned: every value ends in the same column
    ends = {len(line) for line in lines[2:]}
    assert len(ends) == 1, ends


@pytest.mark.parametrize("torch_backbone", [False, True], ids=["numpy", "torch(1,K,3)"])
def test_plot_writes_png(capsys, fakes, tmp_path, torch_backbone):
    fakes["options"] = {"torch_backbone": torch_backbone}
    target = tmp_path / "sub" / "fig.png"
    code, out, err = run(capsys, "plot", "renda2021_fig3", "-o", str(target), "--points", "50")
    assert code == 0 and err == ""
    assert str(target) in out
    data = target.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 10_000


def test_plot_says_which_folder_it_created(capsys, fakes, tmp_path):
    """Regression: `plot -o` into a missing folder created it silently. It is documented
    (--help) and said: the message names the topmost folder created; none when it existed."""
    target = tmp_path / "new" / "deeper" / "fig.png"
    code, out, err = run(capsys, "plot", "renda2021_fig3", "-o", str(target))
    assert code == 0 and err == "" and target.is_file()
    assert f"created folder {tmp_path / 'new'}" in out
    code, out, _ = run(capsys, "plot", "renda2021_fig3", "-o", str(target))
    assert code == 0 and "created folder" not in out
    code, out, _ = run(capsys, "plot", "--help")
    assert code == 0 and "missing parent folders are created" in " ".join(out.split())


def test_plot_not_converged_exit_1(capsys, fakes, tmp_path):
    fakes["options"] = {"converged": False}
    code, out, _ = run(capsys, "plot", "renda2021_section3b", "--model", "standard",
                       "-o", str(tmp_path / "f.png"))
    assert code == 1 and "NOT converged" in out and (tmp_path / "f.png").stat().st_size > 0


def test_demo_with_both_models(capsys, fakes, tmp_path):
    fakes["options"] = {"pvs_tip": [TIP[0] + 3e-4, TIP[1], TIP[2] - 4e-4]}
    code, out, err = run(capsys, "demo", "-o", str(tmp_path / "demo"))
    assert code == 0, err
    header = [ln for ln in out.splitlines() if ln.strip().startswith("standard")]
    assert header and "pvs" in header[0] and "pvs - standard" in header[0]
    (diff,) = [ln for ln in out.splitlines() if ln.startswith("tip difference")]
    assert "0.5000 mm" in diff  # |(0.3, 0, -0.4)| mm
    png = tmp_path / "demo" / "renda2021_fig3.png"
    assert str(png) in out and png.read_bytes().startswith(PNG_MAGIC)
    assert [s.actuation.rotation for s in fakes["scenes"]] == [
        load_scene("renda2021_fig3").actuation.rotation] * 2


@pytest.mark.parametrize("missing", ["torchpvs.reference", "torchpvs.solver"])
def test_demo_with_one_model(capsys, fakes, tmp_path, monkeypatch, missing):
    monkeypatch.setitem(sys.modules, missing, None)
    code, out, _ = run(capsys, "demo", "-o", str(tmp_path))
    assert code == 0 and "not available yet" in out
    assert "tip difference" not in out
    assert (tmp_path / "renda2021_fig3.png").read_bytes().startswith(PNG_MAGIC)


def test_demo_without_models(capsys, no_solvers, tmp_path):
    code, _, err = run(capsys, "demo", "-o", str(tmp_path))
    assert code == 2 and "not available" in one_line(err)


def test_python_dash_m_error_path(tmp_path):
    """``python -m torchpvs`` works, exits 2 on a bad scene with one line on stderr."""
    proc = subprocess.run([sys.executable, "-m", "torchpvs", "solve", "no_such_scene", "--json"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"})
    assert proc.returncode == 2 and proc.stdout == ""
    assert "no_such_scene" in one_line(proc.stderr)


# ---------------------------------------------------------------------------------------------
# The real models (skipped while they are not importable)

def _real(module: str, attr: str):
    mod = pytest.importorskip(module)
    if not hasattr(mod, attr):
        pytest.skip(f"{module}.{attr} is not available yet")


@pytest.fixture(scope="module")
def pvs_json():
    _real("torchpvs.solver", "solve")
    return run_captured("solve", "renda2021_fig3", "--json", "--backbone", "9")


def test_pvs_solve_json(pvs_json):
    code, out, err = pvs_json
    assert code == 0, err
    obj = strict_json(out)
    assert set(obj) == EXPECTED_KEYS | set(EXTENSION_KEYS) | {"backbone"}
    assert obj["model"] == "pvs" and obj["converged"] is True
    # Fig. 3: D1 = Ls1, the outer tube's transition sits at the orifice (docs/physics.md, kinks).
    assert obj["force_kink"] == [True, False]
    assert obj["actuation_forces_insertion"][0] < obj["actuation_forces"][0]
    assert len(obj["tip_position"]) == 3 and np.array(obj["tip_rotation"]).shape == (3, 3)
    assert len(obj["relative_rotation_at_outer_tip"]) == 1
    assert len(obj["actuation_forces"]) == 2 and len(obj["actuation_torques"]) == 2
    bb = np.array(obj["backbone"])
    assert bb.shape == (9, 3)
    assert bb[0] == pytest.approx([0.0, 0.0, 0.0], abs=1e-12)
    assert bb[-1] == pytest.approx(obj["tip_position"], abs=1e-9)


def test_pvs_table_and_plot(capsys, tmp_path):
    _real("torchpvs.solver", "solve")
    code, out, _ = run(capsys, "solve", "renda2021_section3b", "--model", "pvs")
    assert code in (0, 1) and "tip position x" in out and "[mm]" in out
    code, out, _ = run(capsys, "plot", "renda2021_fig3", "-o", str(tmp_path / "p.png"),
                       "--points", "60")
    assert code == 0 and (tmp_path / "p.png").read_bytes().startswith(PNG_MAGIC)


def test_standard_solve_json(capsys):
    _real("torchpvs.reference", "solve_standard")
    code, out, err = run(capsys, "solve", "renda2021_fig3", "--model", "standard", "--json",
                         "--backbone", "5")
    assert code == 0, err
    obj = strict_json(out)
    assert set(obj) == EXPECTED_KEYS | {"backbone"}
    assert obj["model"] == "standard" and obj["converged"] is True
    assert len(obj["backbone"]) == 5


def test_standard_python_dash_m(tmp_path):
    _real("torchpvs.reference", "solve_standard")
    proc = subprocess.run([sys.executable, "-m", "torchpvs", "solve", "renda2021_fig3",
                           "--model", "standard", "--json"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    obj = strict_json(proc.stdout)
    assert set(obj) == EXPECTED_KEYS and obj["model"] == "standard"


# ---------------------------------------------------------------------------------------------
# torchpvs.plotting (what `torchpvs plot` draws)

def test_backbone_owners():
    from torchpvs.plotting import backbone_owners

    s = load_scene("renda2021_fig3")  # exposed lengths 92.3 mm (outer), 95.0 mm (inner)
    owners = backbone_owners(s, 951)  # s = 0, 0.1, ..., 95.0 mm
    assert (owners[:923] == 0).all() and (owners[923:] == 1).all()
    s = s.with_actuation(insertion=[93.5e-3, 293.5e-3])  # inner tube ends 10 mm out
    assert (backbone_owners(s, 50) == 0).all()
    s = s.with_actuation(insertion=[0.3, 0.3])  # outer hidden in the guide, inner 3.5 mm out
    assert (backbone_owners(s, 20) == 1).all()


def test_plot_backbone_artists():
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from torchpvs.plotting import plot_backbone

    s = load_scene("renda2021_fig3")
    l_tip = max(s.exposed_lengths())
    z = np.linspace(0.0, l_tip, 200)
    pts = np.column_stack([0.2 * z, 0.0 * z, z])
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    out_fig, out_ax = plot_backbone(s, pts, ax=ax, title="t")
    assert out_fig is fig and out_ax is ax and ax.get_title() == "t"
    lines = {ln.get_label(): ln for ln in ax.lines}
    assert {"outer", "inner"} <= set(lines)
    assert lines["outer"].get_linewidth() / lines["inner"].get_linewidth() == \
        pytest.approx(2.39 / 1.6)
    (guide,) = [k for k in lines if k.startswith("guide")]
    gz = lines[guide].get_data_3d()[2]
    assert gz.min() < 0.0 and -gz.min() <= 0.3 * l_tip * 1e3 + 1e-9  # along -z, clipped
    assert lines["inner"].get_data_3d()[2].max() == pytest.approx(l_tip * 1e3)  # in mm
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "outer" in legend and "inner" in legend and any(t.startswith("tip") for t in legend)
    assert ax.get_xlabel() == "x [mm]" and ax.get_zlabel() == "z [mm]"
    _, ax2 = plot_backbone(s.with_actuation(insertion=[0.0, 0.1]), pts, ax=fig.add_subplot(
        122, projection="3d"), show_guide=False)
    assert not any(ln.get_label().startswith("guide") for ln in ax2.lines)


# ---------------------------------------------------------------------------------------------
# Regression: internal exceptions and noise on the command line

BIG = "9" * 400


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize("cmd", COMMANDS, ids=["solve", "plot"])
@pytest.mark.parametrize(("override", "fragments"), [
    (f"tubes[0].E={BIG}", ["tubes[0].E", "float range", "401 digits"]),
    (f"tubes[1].G=-{BIG}", ["tubes[1].G", "float range"]),
    (f"actuation.rotation[1]={BIG}", ["actuation.rotation[1]", "float range"]),
    ("tubes[0].E=" + "9" * 5000, ["tubes[0].E", "4300 digits"]),  # beyond int()'s limit
    ("load.tip_force[1]=0.1", ["load.tip_force is not in the scene", "--set load.tip_force="]),
    ("tubes[0].precurvature.x[0]=1", ["tubes[0].precurvature.x is not in the scene"]),
])
def test_set_values_that_used_to_crash_or_confuse(capsys, cmd, override, fragments):
    code, out, err = run(capsys, cmd[0], "renda2021_fig3", "--set", override, *cmd[1:])
    assert code == 2 and out == ""
    one_line(err)
    assert len(err) < 600  # a 5000-digit value is not echoed whole
    for f in fragments:
        assert f in err


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_huge_integer_in_a_scene_file_exits_2(capsys, tmp_path, suffix):
    data = load_scene("renda2021_fig3").to_dict()
    data["tubes"][0]["E"] = int(BIG)
    path = tmp_path / f"big{suffix}"
    path.write_text(json.dumps(data) if suffix == ".json" else yaml.safe_dump(data))
    code, out, err = run(capsys, "solve", str(path), "--json")
    assert code == 2 and out == ""
    assert "tubes[0].E" in one_line(err) and "float range" in err


@pytest.mark.usefixtures("no_solvers")
@pytest.mark.parametrize(("scene", "content", "fragments"), [
    ("bin.yaml", bytes(range(256)), ["bin.yaml", "not a UTF-8 text file"]),
    ("bin.json", b"\x00\x01\x02\x03", ["bin.json", "NUL bytes"]),
    ("", None, ["scene name is empty", "renda2021_fig3"]),
    (" ", None, ["scene name is empty"]),
    (".", None, ["'.' is a directory"]),
])
def test_unusable_scene_paths_name_the_file(capsys, tmp_path, monkeypatch, scene, content,
                                            fragments):
    monkeypatch.chdir(tmp_path)
    if content is not None:
        (tmp_path / scene).write_bytes(content)
    code, out, err = run(capsys, "solve", scene, "--json")
    assert code == 2 and out == ""
    one_line(err)
    for f in fragments:
        assert f in err


def test_torch_internal_deprecations_are_not_shown_but_solver_warnings_are(capsys, fakes,
                                                                           monkeypatch):
    """torch's first forward-mode AD call imports torch._decomp.decompositions_for_jvp, whose
    calls of the deprecated torch.jit.script each warn from torch.jit._script: the CLI used to
    re-emit all 18 (simplefilter("always")). torchpvs's own warnings, deprecations included,
    still reach stderr, one line each."""
    import warnings

    fake_solver = sys.modules["torchpvs.solver"]  # the fake installed by ``fakes``
    real = fake_solver.solve

    def noisy(scene):
        for module in ("torch.jit._script", "torch"):
            warnings.warn_explicit("`torch.jit.script` is deprecated.", DeprecationWarning,
                                   "_script.py", 1488, module=module)
        warnings.warn_explicit("torch pending", PendingDeprecationWarning, "x.py", 1,
                               module="torch._decomp")
        warnings.warn_explicit("option X is deprecated", DeprecationWarning, "solver.py", 1,
                               module="torchpvs.solver")
        warnings.warn("1 of 1 element(s) did not converge", RuntimeWarning, stacklevel=1)
        return real(scene)

    monkeypatch.setattr(fake_solver, "solve", noisy)
    for _ in range(2):  # shown again by a second solve in the same process
        code, out, err = run(capsys, "solve", "renda2021_fig3", "--json")
        assert code == 0
        lines = err.splitlines()
        assert lines == ["torchpvs solve: warning: option X is deprecated",
                         "torchpvs solve: warning: 1 of 1 element(s) did not converge"]


def test_loaded_real_solve_prints_nothing_on_stderr(tmp_path):
    """A loaded solve in a fresh interpreter (where torch's jvp decompositions are first
    loaded) exits 0 with nothing on stderr."""
    _real("torchpvs.solver", "solve")
    proc = subprocess.run(
        [sys.executable, "-m", "torchpvs", "solve", "renda2021_fig3", "--json",
         "--set", "load.tip_force=[0, 0.1, 0]"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert strict_json(proc.stdout)["converged"] is True


# -- torchpvs calibrate -----------------------------------------------------------------------

def _calibration_csv(path: Path, rows: int = 12, weight: bool = False) -> None:
    """Noise-free PVS tips of the Fig. 3 robot with precurvatures scaled by 1.06 / 0.95."""
    import torch

    import torchpvs
    from torchpvs.testing import feasible_actuations, scaled_tubes
    rng = np.random.default_rng(0)
    D, A = feasible_actuations(rng, rows)
    truth = scaled_tubes(load_scene("renda2021_fig3"), precurvature=(1.06, 0.95))
    tip = torchpvs.solve(truth, insertion=torch.tensor(D),
                         rotation=torch.tensor(A)).tip_position.numpy()
    head = "insertion_0,insertion_1,rotation_0,rotation_1,tip_x,tip_y,tip_z"
    data = np.concatenate([D, A, tip] + ([np.ones((rows, 1))] if weight else []), -1)
    np.savetxt(path, data, delimiter=",", header=head + (",weight" if weight else ""),
               comments="")


def test_calibrate_writes_the_fitted_scene(tmp_path, capsys):
    csv_path = tmp_path / "tips.csv"
    _calibration_csv(csv_path, weight=True)
    out = tmp_path / "fitted.yaml"
    code = main(["calibrate", "renda2021_fig3", str(csv_path), "--params", "precurvature",
                 "-o", str(out), "--json"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report["converged"] and report["output"] == str(out)
    assert report["parameters"]["precurvature[0]"]["value"] == pytest.approx(1.06, rel=1e-5)
    fitted = load_scene(str(out))
    nominal = load_scene("renda2021_fig3")
    for j, f in enumerate((1.06, 0.95)):
        assert fitted.tubes[j].precurvature[1][0] == pytest.approx(
            f * nominal.tubes[j].precurvature[1][0], rel=1e-5)
    assert out.read_text().startswith("# fitted by `torchpvs calibrate")


@pytest.mark.parametrize("text, fragment", [
    ("insertion_0,rotation_0,tip_x\n1,2,3\n", "missing column(s) ['insertion_1'"),
    ("insertion_0,insertion_1,rotation_0,rotation_1,tip_x,tip_y,tip_z\n"
     "0.05,0.1,0,0,abc,0,0.1\n", "line 2: column tip_x is not a number"),
    ("insertion_0,insertion_1,rotation_0,rotation_1,tip_x,tip_y,tip_z\n", "no measurements"),
])
def test_calibrate_names_the_bad_column(tmp_path, capsys, text, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    assert main(["calibrate", "renda2021_fig3", str(path)]) == 2
    err = capsys.readouterr().err
    assert fragment in err and err.count("\n") == 1


def test_calibrate_refuses_an_unknown_parameter(tmp_path, capsys):
    csv_path = tmp_path / "tips.csv"
    _calibration_csv(csv_path, rows=3)
    assert main(["calibrate", "renda2021_fig3", str(csv_path), "--params", "stiffness"]) == 2
    assert "unknown parameter 'stiffness'" in capsys.readouterr().err
