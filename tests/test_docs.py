"""The documentation is self-contained: every relative link and image path in every markdown file
of the repository resolves (anchors into markdown files included), every page under ``docs/`` is
reachable from ``docs/index.md``, and nothing refers to notes outside the repository.

Files considered: those git tracks plus untracked files git does not ignore (``git ls-files
--cached --others --exclude-standard``), so build outputs (``*.egg-info``, ``runs/``,
``demo_out/``) and the virtual environment are left out; without git, a walk of the tree that
skips hidden folders, ``.venv``, ``build``, ``*.egg-info`` and ``__pycache__``.
"""

from __future__ import annotations

import re
import subprocess
import unicodedata
from functools import cache
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {".venv", "venv", "build", "dist", "__pycache__", "node_modules", "runs", "demo_out"}
# Built in two pieces so that this file does not contain the string it looks for.
OUTSIDE_NOTES = "shared" + "/notes"


def _hidden_or_skipped(rel: Path) -> bool:
    return any(part.startswith(".") or part in SKIP_DIRS or part.endswith(".egg-info")
               for part in rel.parts[:-1]) or rel.name.startswith(".")


@cache
def repo_files() -> tuple[Path, ...]:
    """Repository files (relative paths), hidden folders excluded."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
        rels = [Path(p) for p in out.decode("utf-8", "surrogateescape").split("\0") if p]
    except (OSError, subprocess.SubprocessError):
        rels = [p.relative_to(ROOT) for p in ROOT.rglob("*")]
    return tuple(sorted(r for r in rels
                        if not _hidden_or_skipped(r) and (ROOT / r).is_file()))


def markdown_files() -> list[Path]:
    return [r for r in repo_files() if r.suffix.lower() in (".md", ".markdown")]


# ---------------------------------------------------------------------------------------------
# Markdown parsing (enough of CommonMark/GitHub for links, images and heading anchors)

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
_CODE_SPAN = re.compile(r"(`+)(.+?)\1", re.S)
# [text](target "title") and ![alt](target): the target may be <...> or a bare destination
# with balanced parentheses one level deep.
_INLINE = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*(<[^>]*>|(?:[^()\s]|\([^()\s]*\))*)"
                     r"(?:\s+(?:\"[^\"]*\"|'[^']*'|\([^)]*\)))?\s*\)")
_REFDEF = re.compile(r"^ {0,3}\[[^\]]+\]:\s*(<[^>]*>|\S+)", re.M)
_HTML = re.compile(r"<(?:img|a|source)\b[^>]*?\b(?:src|href|srcset)\s*=\s*[\"']([^\"']+)[\"']",
                   re.I)
_HTML_ID = re.compile(r"<[a-z][^>]*?\b(?:id|name)\s*=\s*[\"']([^\"']+)[\"']", re.I)
_HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
_SETEXT = re.compile(r"^ {0,3}(=+|-+)\s*$")


def _prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks (fenced lines become empty)."""
    lines, fence = [], None
    for line in text.splitlines():
        m = _FENCE.match(line)
        if fence is None and m:
            fence = m.group(1)
            lines.append("")
        elif fence is not None:
            if m and m.group(1)[0] == fence[0] and len(m.group(1)) >= len(fence) \
                    and not line.strip()[len(m.group(1)):].strip():
                fence = None
            lines.append("")
        elif line.startswith("    ") and (not lines or not lines[-1].strip()):
            lines.append("")  # indented code block after a blank line
        else:
            lines.append(line)
    return lines


def links(text: str) -> list[tuple[int, str]]:
    """``(line number, target)`` of every link, image and HTML src/href outside code."""
    found = []
    lines = _prose_lines(text)
    for m in _REFDEF.finditer("\n".join(lines)):
        found.append(("\n".join(lines)[:m.start()].count("\n") + 1, m.group(1)))
    for i, line in enumerate(lines, 1):
        line = _CODE_SPAN.sub(lambda m: " " * len(m.group(0)), line)
        for m in _INLINE.finditer(line):
            found.append((i, m.group(1)))
        for m in _HTML.finditer(line):
            found.append((i, m.group(1).split()[0]))
    return [(i, t.strip("<>")) for i, t in found]


def slug(heading: str) -> str:
    """GitHub's heading anchor: link text kept, markup and punctuation dropped, lower case,
    spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)       # links: keep the text
    text = re.sub(r"<[^>]+>", "", text)                                 # inline HTML
    text = unicodedata.normalize("NFC", text).lower()
    text = "".join(c for c in text
                   if c in "-_ " or unicodedata.category(c)[0] in "LNM")
    return text.replace(" ", "-")


@cache
def anchors(rel: Path) -> frozenset[str]:
    """The anchors a markdown file defines: heading slugs (with GitHub's -1, -2 suffixes for
    repeats) and explicit HTML ids/names."""
    text = (ROOT / rel).read_text(encoding="utf-8")
    lines = _prose_lines(text)
    seen: dict[str, int] = {}
    out = set(m.group(1) for m in _HTML_ID.finditer("\n".join(lines)))
    for i, line in enumerate(lines):
        m = _HEADING.match(line)
        title = m.group(2) if m else None
        if title is None and i > 0 and lines[i - 1].strip() and _SETEXT.match(line) \
                and not _HEADING.match(lines[i - 1]) and not lines[i - 1].lstrip().startswith("|"):
            title = lines[i - 1].strip()
        if title is None:
            continue
        s = slug(title)
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return frozenset(out)


_SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")


def _check(rel: Path, line: int, target: str) -> str | None:
    """None if ``target`` (found in ``rel`` at ``line``) resolves, else why not."""
    where = f"{rel}:{line}: {target!r}"
    if not target or _SCHEME.match(target) or target.startswith("//"):
        return None  # external (http:, https:, mailto:, ...): not checked offline
    path, _, anchor = target.partition("#")
    path = unquote(path.split("?", 1)[0])
    if path.startswith("/"):
        return f"{where}: absolute path; use a path relative to the file"
    dest = (ROOT / rel).parent / path if path else ROOT / rel
    try:
        inside = dest.resolve().relative_to(ROOT)
    except ValueError:
        return f"{where}: points outside the repository"
    if not dest.exists():
        return f"{where}: {inside} does not exist"
    if anchor and dest.is_file() and dest.suffix.lower() in (".md", ".markdown"):
        if unquote(anchor).lower() not in anchors(inside):
            return f"{where}: no heading or id #{anchor} in {inside}"
    return None


def test_markdown_files_found():
    names = {str(p) for p in markdown_files()}
    assert {"README.md", "docs/index.md", "docs/conventions.md", "docs/physics.md"} <= names


@pytest.mark.parametrize("rel", markdown_files(), ids=str)
def test_relative_links_and_images_resolve(rel):
    """Every relative link and image path of a markdown file names an existing file or folder
    inside the repository; an anchor into a markdown file names one of its headings."""
    text = (ROOT / rel).read_text(encoding="utf-8")
    problems = [p for line, target in links(text) if (p := _check(rel, line, target))]
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_every_docs_page_is_linked_from_the_index():
    """docs/index.md is the first page: every other page under docs/ is reachable from it."""
    index = Path("docs/index.md")
    linked = set()
    for _, target in links((ROOT / index).read_text(encoding="utf-8")):
        path = unquote(target.partition("#")[0])
        if path and not _SCHEME.match(path):
            try:
                linked.add(((ROOT / index).parent / path).resolve().relative_to(ROOT))
            except ValueError:
                pass
    pages = {p for p in markdown_files() if p.parts[0] == "docs" and p != index}
    assert not pages - linked, f"not linked from docs/index.md: {sorted(map(str, pages - linked))}"


def test_no_reference_to_notes_outside_the_repository():
    """Users who install or clone torchpvs have only the repository: no file may point to the
    development notes that live beside it (their content is in docs/conventions.md and
    docs/physics.md)."""
    needle = OUTSIDE_NOTES.encode()
    hits = []
    for rel in repo_files():
        data = (ROOT / rel).read_bytes()
        if needle in data:
            for i, line in enumerate(data.splitlines(), 1):
                if needle in line:
                    hits.append(f"{rel}:{i}: {line.decode('utf-8', 'replace').strip()[:100]}")
    assert not hits, f"{len(hits)} references to {OUTSIDE_NOTES}:\n" + "\n".join(hits)


# ---------------------------------------------------------------------------------------------
# The checker itself

def test_link_parser_and_slugs():
    text = "\n".join([
        "# Title: with `code`, (parens) and Euler–Bernoulli",
        "## Title: with `code`, (parens) and Euler–Bernoulli",
        "[a](docs/x.md#y) ![img](figures/p.png \"t\") [b](<with space.md>) [c](f(1).md)",
        "`[not](a link)` and [ext](https://example.org)",
        "```",
        "[also not](inside/a/fence.md)",
        "```",
        "[ref]: ../up.md",
        '<img src="pic.png" width="3">',
    ])
    assert [t for _, t in links(text)] == [
        "../up.md", "docs/x.md#y", "figures/p.png", "with space.md", "f(1).md",
        "https://example.org", "pic.png"]
    assert slug("Title: with `code`, (parens) and Euler–Bernoulli") == \
        "title-with-code-parens-and-eulerbernoulli"
    assert slug("The hard cases (tests/hard)") == "the-hard-cases-testshard"
    assert slug("`torchpvs solve SCENE --json`") == "torchpvs-solve-scene---json"
    assert slug("Actuation forces and torques: signs") == "actuation-forces-and-torques-signs"


def test_api_reference_builds_offline(tmp_path):
    """``make api``: the API reference is built from the docstrings (pdoc, no network), without
    warnings (a warning is an unresolvable name in ``__all__`` or a broken import)."""
    import subprocess
    import sys

    pytest.importorskip("pdoc")
    run = subprocess.run([sys.executable, "-m", "pdoc", "--docformat", "google", "-o",
                          str(tmp_path), "torchpvs", "envs"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "Warn" not in run.stderr, run.stderr
    # The public surface (each package's __all__) is what the reference documents.
    api = (tmp_path / "torchpvs.html").read_text()
    for name in ("solve", "SolverOptions", "Equilibrium", "accuracy_met", "CTR", "Plan",
                 "continuation", "solve_force_controlled"):
        assert name in api, name
    assert "CTRReachVectorEnv" in (tmp_path / "envs.html").read_text()
