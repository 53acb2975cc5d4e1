"""What a non-editable install (``pip install .``) ships: every package under torchpvs/, envs/
and training/, and the data files the code opens at run time (the shipped policies the demo
loads, the hyperparameter files, the built-in scenes) matched by ``[tool.setuptools.
package-data]`` in pyproject.toml. (Checked by hand: ``pip install -c constraints.txt
".[rl,zoo]"`` into a fresh venv runs ``python -m training.demo`` from outside the repository.)"""

from __future__ import annotations

import fnmatch
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")      # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]
DATA = {"training": ["policies", "hyperparams"], "torchpvs": ["scenes"]}


def config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_is_found():
    include = config()["packages"]["find"]["include"]
    for pkg in ("torchpvs", "envs", "training"):
        assert (ROOT / pkg / "__init__.py").is_file(), pkg
        assert any(fnmatch.fnmatch(pkg, pat) for pat in include), pkg


@pytest.mark.parametrize("package", sorted(DATA))
def test_run_time_data_files_are_package_data(package):
    patterns = config()["package-data"][package]
    files = [p for folder in DATA[package] for p in (ROOT / package / folder).iterdir()
             if p.is_file() and not p.name.startswith(".")]
    assert files, package
    missing = [str(p.relative_to(ROOT)) for p in files
               if not any(fnmatch.fnmatch(str(p.relative_to(ROOT / package)), pat)
                          for pat in patterns)]
    assert not missing, f"not package data (a non-editable install lacks them): {missing}"


def test_the_demo_finds_its_policies_beside_its_module():
    """training.demo loads the shipped policies from its own package folder, not from the
    current directory, so the demo runs from anywhere once installed."""
    from training import demo

    assert Path(demo.POLICIES) == ROOT / "training" / "policies"
    assert (Path(demo.POLICIES) / "tqc_force.zip").is_file()
