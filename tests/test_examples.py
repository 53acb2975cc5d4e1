"""Every example runs to completion and writes its figure (a quick smoke run: the numbers they
print are checked by the physics tests they cite; here only that they still run)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = {
    "paper_figures.py": (["--quick"], "fig4_sweeps.png"),
    "snap_through.py": ([], "snap_through.png"),
    "position_vs_torque_control.py": ([], "position_vs_torque.png"),
    "design_optimization.py": ([], "design_optimization.png"),
    "force_controller.py": ([], "force_controller.png"),
    "calibration.py": (["--measurements", "20"], "calibration.png"),
    "control_loop.py": (["--seconds", "0.5"], "control_loop.png"),
}


def test_every_example_is_listed():
    """Every script in examples/ is run below (``_common.py`` is the helper they share)."""
    scripts = [p.name for p in (ROOT / "examples").glob("*.py") if not p.name.startswith("_")]
    assert sorted(scripts) == sorted(EXAMPLES)


def test_examples_write_to_a_scratch_folder_by_default(monkeypatch):
    """Without ``--out`` an example writes to ``examples_out/`` in the current folder, never
    over the committed figures in docs/figures (``--out docs/figures`` regenerates those)."""
    monkeypatch.syspath_prepend(str(ROOT / "examples"))
    import _common

    assert _common.parse_args("doc", [], threads=None).out == Path("examples_out")
    assert _common.parse_args("doc", ["--out", "docs/figures"], threads=None).out == \
        Path("docs/figures")
    for name in EXAMPLES:
        text = (ROOT / "examples" / name).read_text()
        assert 'default="docs/figures"' not in text and "default=Path(\"docs" not in text, name


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_runs(name, tmp_path):
    args, figure = EXAMPLES[name]
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    subprocess.run([sys.executable, str(ROOT / "examples" / name), *args, "--out",
                    str(tmp_path)], check=True, cwd=ROOT, env=env, capture_output=True,
                   timeout=300)
    assert (tmp_path / figure).stat().st_size > 10_000
