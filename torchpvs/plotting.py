"""3D backbone plots of a concentric tube robot (matplotlib, headless-safe).

Frames follow ``docs/conventions.md``: the base frame sits at the insertion orifice with
``z`` along the insertion axis, out of the orifice. Data are given in metres and drawn in mm.

matplotlib is imported lazily inside the functions, so importing this module is cheap and never
selects a GUI backend; :func:`save_backbone_plot` does not touch ``pyplot`` at all.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .scene import Scene

__all__ = ["backbone_owners", "overlay_backbone", "plot_backbone", "save_backbone_plot"]

_MM = 1e3            # m -> mm
_MAX_LINEWIDTH = 5.0  # pt, for the thickest tube; widths are proportional to outer diameter
_GUIDE_FRACTION = 0.3  # the drawn guide is at most this fraction of the plot extent


def as_points(points_xyz: Any) -> np.ndarray:
    """``(K, 3)`` float64 numpy array [m] from a numpy array or torch tensor of shape ``(K, 3)``
    or ``(1, K, 3)``."""
    if hasattr(points_xyz, "detach"):  # torch tensor
        points_xyz = points_xyz.detach().cpu().numpy()
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.ndim == 3 and pts.shape[0] == 1:
        pts = pts[0]
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < 1:
        raise ValueError(f"points_xyz must have shape (K, 3) or (1, K, 3), got {pts.shape}")
    return pts


def backbone_owners(scene: Scene, n_points: int) -> np.ndarray:
    """Index of the outermost tube present at each of ``n_points`` arc lengths ``s`` uniformly
    spaced from the orifice (``s = 0``) to the tip (``s_tip = max_j l_j``), ``(K,)`` int.

    Tube ``j`` is present for ``s < l_j`` (``l_j`` = :meth:`Scene.exposed_lengths`); the
    outermost present tube is the smallest such ``j``. At the tip itself the owner is the
    outermost tube ending there.
    """
    lengths = np.asarray(scene.exposed_lengths(), dtype=np.float64)
    s_tip = float(lengths.max())
    s = np.linspace(0.0, s_tip, n_points)
    present = s[:, None] < lengths[None, :]                       # (K, N)
    tip_owner = int(np.flatnonzero(lengths == s_tip)[0])
    return np.where(present.any(-1), present.argmax(-1), tip_owner)


def _runs(owners: np.ndarray) -> list[tuple[int, int, int]]:
    """Contiguous runs ``(owner, first, last)`` (inclusive point indices) of a backbone whose
    segment ``k -> k+1`` is coloured by the owner of its start point ``k``."""
    K = len(owners)
    if K == 1:
        return [(int(owners[0]), 0, 0)]
    seg = owners[:-1]
    runs = []
    start = 0
    for k in range(1, K - 1):
        if seg[k] != seg[start]:
            runs.append((int(seg[start]), start, k))
            start = k
    runs.append((int(seg[start]), start, K - 1))
    return runs


def equalize_axes(ax: Any) -> None:
    """Limits and box aspect from everything drawn (lines and points), in data units, so that
    one mm is as long along x, y and z."""
    chunks = [np.column_stack(line.get_data_3d()) for line in ax.lines]
    for coll in ax.collections:
        offsets = getattr(coll, "_offsets3d", None)
        if offsets is not None:
            chunks.append(np.column_stack([np.asarray(c, dtype=float) for c in offsets]))
    data = np.concatenate([c for c in chunks if c.size], axis=0) if chunks else np.zeros((1, 3))
    data = data[np.isfinite(data).all(-1)]
    if data.size == 0:
        data = np.zeros((1, 3))
    lo, hi = data.min(0), data.max(0)
    span = float((hi - lo).max()) or 1.0
    pad = 0.05 * span
    floor = 0.2 * span  # keep flat directions visible
    center = 0.5 * (lo + hi)
    half = np.maximum(0.5 * (hi - lo), 0.5 * floor) + pad
    ax.set_xlim(center[0] - half[0], center[0] + half[0])
    ax.set_ylim(center[1] - half[1], center[1] + half[1])
    ax.set_zlim(center[2] - half[2], center[2] + half[2])
    ax.set_box_aspect(tuple(2 * half))
    from matplotlib.ticker import MaxNLocator

    for axis, h in zip((ax.xaxis, ax.yaxis, ax.zaxis), half, strict=True):
        nbins = max(2, int(round(6 * h / half.max())))  # fewer ticks on short axes
        axis.set_major_locator(MaxNLocator(nbins=nbins, steps=[1, 2, 2.5, 5, 10]))


def plot_backbone(scene: Scene, points_xyz: Any, *, ax: Any = None, title: str | None = None,
                  show_guide: bool = True) -> tuple[Any, Any]:
    """Draw the backbone in 3D, in the base frame, in mm.

    Args:
        scene: the robot (tube names, diameters, exposed lengths, insertions).
        points_xyz: ``(K, 3)`` [m] backbone points uniformly spaced in arc length from the
            orifice (``s = 0``) to the tip ``s_tip = max(scene.exposed_lengths())``; a numpy
            array or torch tensor, ``(1, K, 3)`` accepted.
        ax: a matplotlib 3D axes to draw into; ``None`` = a new ``pyplot`` figure.
        title: axes title; ``None`` = the tube names.
        show_guide: draw the insertion guide as a grey segment along ``-z`` (length = the largest
            insertion ``D_j``, clipped to 30 % of the plot extent).

    Each part of the backbone is coloured by the outermost tube present there (``C0`` for tube 0,
    ``C1`` for tube 1, ...), with a line width proportional to that tube's outer diameter.

    Returns:
        ``(figure, axes)``.
    """
    pts = as_points(points_xyz) * _MM
    if ax is None:
        import matplotlib.pyplot as plt

        fig = plt.figure(figsize=(7.0, 6.0))
        ax = fig.add_subplot(projection="3d")
    else:
        fig = ax.figure
    od_max = max(t.outer_diameter for t in scene.tubes)
    owners = backbone_owners(scene, len(pts))
    drawn: set[int] = set()
    for j, first, last in _runs(owners):
        tube = scene.tubes[j]
        label = (tube.name or f"tube{j + 1}") if j not in drawn else None
        drawn.add(j)
        seg = pts[first:last + 1]
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color=f"C{j}",
                linewidth=_MAX_LINEWIDTH * tube.outer_diameter / od_max, label=label,
                solid_capstyle="round")
    extent = float(np.ptp(pts, axis=0).max()) if len(pts) > 1 else 0.0
    extent = max(extent, max(scene.exposed_lengths()) * _MM)
    if show_guide:
        d_max = max(scene.actuation.insertion) * _MM
        if d_max > 0:
            shown = min(d_max, _GUIDE_FRACTION * extent) if extent > 0 else d_max
            label = "guide" if shown >= d_max else f"guide ({d_max:.1f} mm, clipped)"
            ax.plot([0.0, 0.0], [0.0, 0.0], [0.0, -shown], color="0.6",
                    linewidth=_MAX_LINEWIDTH + 2.0, alpha=0.6, label=label,
                    solid_capstyle="butt")
    # base frame triad at the orifice
    size = 0.12 * (extent or 1.0)
    for axis, color, name in ((0, "tab:red", "x"), (1, "tab:green", "y"), (2, "tab:blue", "z")):
        end = np.zeros(3)
        end[axis] = size
        ax.plot([0.0, end[0]], [0.0, end[1]], [0.0, end[2]], color=color, linewidth=0.8)
        ax.text(*(end * 1.1), name, color=color, fontsize=8)
    tip = pts[-1]
    ax.scatter([tip[0]], [tip[1]], [tip[2]], color="k", marker="o", s=25, depthshade=False,
               label=f"tip ({tip[0]:.1f}, {tip[1]:.1f}, {tip[2]:.1f}) mm")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_zlabel("z [mm]")
    ax.set_title(title if title is not None
                 else ", ".join(t.name or f"tube{j + 1}" for j, t in enumerate(scene.tubes)))
    equalize_axes(ax)
    ax.legend(loc="upper left", fontsize=8)
    return fig, ax


def overlay_backbone(ax: Any, points_xyz: Any, *, label: str, color: str = "k",
                     linestyle: str = "--", linewidth: float = 1.2) -> Any:
    """Add a second backbone (``(K, 3)`` [m]) to axes from :func:`plot_backbone`, by default as
    a dashed black line, and refresh the limits, aspect and legend. Returns the line."""
    pts = as_points(points_xyz) * _MM
    (line,) = ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], color=color, linestyle=linestyle,
                      linewidth=linewidth, label=label)
    equalize_axes(ax)
    ax.legend(loc="upper left", fontsize=8)
    return line


def save_backbone_plot(scene: Scene, points_xyz: Any, path: str | Path, *,
                       overlays: Sequence[tuple[str, Any]] = (), dpi: int = 120,
                       **kw: Any) -> Path:
    """Draw :func:`plot_backbone` (keywords ``title``, ``show_guide``) on a figure that is not
    managed by ``pyplot`` (Agg canvas, works headless), add ``overlays`` (``(label, points)``
    pairs, dashed black), save it to ``path`` (format from the suffix; parent folders are
    created) and return the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    fig = Figure(figsize=(7.0, 6.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    plot_backbone(scene, points_xyz, ax=ax, **kw)
    for label, pts in overlays:
        overlay_backbone(ax, pts, label=label)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight")
    return path
