"""What the examples share: the command line, one torch thread, and figures saved to ``--out``.

Every example writes its figures to ``--out``, by default ``examples_out/`` in the current
folder (a scratch folder, ignored by git); ``--out docs/figures`` regenerates the figures the
documentation shows. Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no
display needed)::

    from _common import figure, parse_args, save

    args = parse_args(__doc__, extra=lambda ap: ap.add_argument("--iterations", type=int))
    fig = figure((10, 4))
    ...
    save(fig, args.out, "my_example.png")
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

DEFAULT_OUT = Path("examples_out")
"""Where the examples write by default: a scratch folder in the current directory."""

NAN = float("nan")


def parser(doc: str, **kwargs) -> argparse.ArgumentParser:
    """An argument parser described by the first line of ``doc``, with ``--out``."""
    ap = argparse.ArgumentParser(description=doc.strip().splitlines()[0], **kwargs)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help=f"folder for the figures (default: {DEFAULT_OUT}/; "
                         "--out docs/figures regenerates the documentation's figures)")
    return ap


def parse_args(doc: str, argv: Sequence[str] | None = None,
               extra: Callable[[argparse.ArgumentParser], object] | None = None,
               threads: int | None = 1, **kwargs) -> argparse.Namespace:
    """Parse the command line of an example (``--out`` plus what ``extra`` adds to the parser)
    and pin torch to ``threads`` threads (``None``: leave torch's default)."""
    ap = parser(doc, **kwargs)
    if extra is not None:
        extra(ap)
    args = ap.parse_args(argv)
    if threads is not None:
        torch.set_num_threads(threads)
    return args


def figure(figsize: tuple[float, float]) -> Figure:
    """A matplotlib figure on an Agg canvas (no pyplot state, no display)."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def save(fig: Figure, out: Path | str, name: str, dpi: int = 120, tight: bool = True,
         note: str = "") -> Path:
    """Lay out ``fig`` (``tight``), write it to ``out / name`` (folders created) and print
    where it went, followed by ``note``."""
    if tight:
        fig.tight_layout()
    path = Path(out) / name
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    print(f"saved {path}{note}")
    return path
