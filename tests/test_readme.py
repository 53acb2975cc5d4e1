"""The README's install statements match pyproject.toml: every dependency (core and each extra)
is named in its Install section, and the Python version it asks for is ``requires-python``'s
lower bound (so that a dependency added to pyproject.toml cannot go unmentioned)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")      # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]


def project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def section(title: str) -> str:
    """The README's text from the heading ``## title`` to the next ``## `` heading."""
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else None]


def name(requirement: str) -> str:
    """The distribution name of a requirement string (``"torch>=2.2"`` -> ``"torch"``)."""
    return re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0]


def test_requirement_names_are_parsed():
    assert [name(r) for r in ("torch>=2.2", "rl_zoo3>=2.3", "pyyaml", "a[b]>=1")] == \
        ["torch", "rl_zoo3", "pyyaml", "a"]


@pytest.mark.parametrize("group", ["dependencies", "rl", "zoo", "dev"])
def test_every_dependency_is_named_in_the_install_section(group):
    proj = project()
    reqs = proj["dependencies"] if group == "dependencies" else \
        proj["optional-dependencies"][group]
    install = section("Install").lower()
    missing = [name(r) for r in reqs if name(r).lower() not in install]
    assert not missing, f"README's Install section does not name {group}: {missing}"


def test_python_version_matches_requires_python():
    lower = re.fullmatch(r">=\s*(\d+\.\d+)", project()["requires-python"].strip())
    assert lower, project()["requires-python"]
    readme = (ROOT / "README.md").read_text()
    stated = re.findall(r"Python \((\d+\.\d+) or newer", readme)
    assert stated == [lower.group(1)], stated
