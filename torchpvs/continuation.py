"""Continuation along an actuation path: ``torchpvs.continuation(scene, path) -> Continuation``.

Follows the equilibrium of one robot while its actuation ``(D(s), alpha(s))`` moves along a path
parameter ``s`` in ``[0, 1]``, with warm starts and an adaptive step, and reports the folds (snap
points) where the followed branch of equilibria ends.

A fold is detected two ways:

* **branch jump** — the warm-started solve lands far from the previous equilibrium (tip moves by
  more than ``max_tip_jump``) and halving the step down to ``min_step`` does not remove the jump:
  with ``method="minimize"`` (the default) this is what happens past a fold, where no minimum is
  left nearby and the solver descends to another stable branch;
* **stability loss** — the stability margin (smallest eigenvalue of the reduced stiffness,
  ``Equilibrium.min_stiffness_eigenvalue``) changes sign along the followed branch (seen with
  ``method="root"``, which follows unstable branches too).

Either way the fold is then located by bisection on ``s`` to within ``fold_tol``. A branch jump
whose final bracket shows no jump (the tip moves at most ``max_tip_jump`` from the last point of
the branch) was a steep stretch before a fold, where the tip speed grows like
``1 / sqrt(s_fold - s)``, not a fold: the continuation goes on from there. Otherwise the snap is
reported: the robot is re-solved with ``method="minimize"`` just past the fold, from the last
equilibrium of the lost branch, and the tip jump to the stable branch it lands on is recorded.
The continuation then goes on from that branch.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import torch

from .clock import work_clock
from .equilibrium import Equilibrium
from .options import SolverOptions, check_time_limit, within_deadline
from .scene import Scene, load_scene
from .solver import solve

__all__ = ["ActuationPath", "Continuation", "FoldEvent", "continuation"]


# ---------------------------------------------------------------------------------------------
# Paths

class ActuationPath:
    """An actuation path ``s in [0, 1] -> (insertion (N,), rotation (N,))`` [m], [rad].

    Build it from callables or waypoints per coordinate group:

    * ``insertion`` / ``rotation``: ``None`` (keep the scene's actuation), a ``(N,)`` constant,
      a ``(K, N)`` array of waypoints (``K >= 2``, at ``s = linspace(0, 1, K)``, linearly
      interpolated), or a callable ``s -> (N,)``.

    Example: rotate the inner tube of a two-tube robot by a full turn::

        ActuationPath(rotation=[[0.0, 0.0], [0.0, 2 * math.pi]])
    """

    def __init__(self, insertion: Any = None, rotation: Any = None):
        self._parts = {"insertion": insertion, "rotation": rotation}

    @staticmethod
    def _eval(part: Any, s: float, default: torch.Tensor, name: str) -> torch.Tensor:
        if part is None:
            return default
        if callable(part):
            v = torch.as_tensor(part(s), dtype=default.dtype).reshape(-1)
        else:
            w = torch.as_tensor(part, dtype=default.dtype)
            if w.ndim == 1:
                v = w
            elif w.ndim == 2:
                K = w.shape[0]
                if K < 2:
                    raise ValueError(f"path.{name}: waypoints need K >= 2 rows, got {K}")
                x = min(max(s, 0.0), 1.0) * (K - 1)
                i = min(int(math.floor(x)), K - 2)
                v = w[i] + (x - i) * (w[i + 1] - w[i])
            else:
                raise ValueError(f"path.{name} must be (N,), (K, N) or a callable, "
                                 f"got shape {tuple(w.shape)}")
        if v.shape != default.shape:
            raise ValueError(f"path.{name} must give {default.shape[0]} values (one per tube), "
                             f"got {v.shape[0]}")
        if not bool(torch.isfinite(v).all()):
            raise ValueError(f"path.{name} is not finite at s = {s:.6g}")
        return v

    def __call__(self, s: float, scene: Scene) -> tuple[torch.Tensor, torch.Tensor]:
        d0 = torch.tensor(scene.actuation.insertion, dtype=torch.float64)
        a0 = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
        return (self._eval(self._parts["insertion"], s, d0, "insertion"),
                self._eval(self._parts["rotation"], s, a0, "rotation"))


def _as_path(path: Any) -> ActuationPath:
    if isinstance(path, ActuationPath):
        return path
    if isinstance(path, Mapping):
        extra = set(path) - {"insertion", "rotation"}
        if extra:
            raise ValueError(f"path has unknown keys {sorted(extra)}; allowed: insertion, rotation")
        return ActuationPath(**path)
    if callable(path):
        class _Fn(ActuationPath):
            def __call__(self, s, scene):
                D, A = path(s)
                d0 = torch.tensor(scene.actuation.insertion, dtype=torch.float64)
                return (self._eval(D, s, d0, "insertion") if D is not None else d0,
                        self._eval(A, s, d0, "rotation") if A is not None else
                        torch.tensor(scene.actuation.rotation, dtype=torch.float64))
        return _Fn()
    raise TypeError("path must be an ActuationPath, a mapping {insertion, rotation} of "
                    "waypoints/callables, or a callable s -> (insertion, rotation)")


# ---------------------------------------------------------------------------------------------
# Results

@dataclass(frozen=True)
class FoldEvent:
    """A fold (snap point) found along the path.

    Attributes:
        s: path parameter of the fold (midpoint of the final bracket).
        bracket: ``(s_lo, s_hi)``: the branch still exists at ``s_lo`` and is lost at ``s_hi``
            (``s_hi - s_lo <= fold_tol``).
        insertion, rotation: ``(N,)`` actuation at ``s`` [m], [rad].
        kind: ``"branch_jump"`` (the warm-started solve left the branch) or
            ``"stability_loss"`` (the margin changed sign on the followed branch).
        tip_before: ``(3,)`` [m] tip on the lost branch at ``s_lo``.
        tip_after: ``(3,)`` [m] tip after the snap (``method="minimize"`` at ``s_hi``).
        tip_jump: ``|tip_after - tip_before|`` [m].
        margin_before: stability margin at ``s_lo`` (the dimensionless smallest stiffness
            eigenvalue, ``Equilibrium.min_stiffness_eigenvalue``: > 0 on a stable branch, small near
            the fold); ``margin_after``: at the landing point.
        index: index into the result's arrays of the point after the snap.
    """

    s: float
    bracket: tuple[float, float]
    insertion: torch.Tensor
    rotation: torch.Tensor
    kind: str
    tip_before: torch.Tensor
    tip_after: torch.Tensor
    tip_jump: float
    margin_before: float
    margin_after: float
    index: int


@dataclass(frozen=True, eq=False)
class Continuation:
    """The equilibria accepted along a path (``K`` points, ``N`` tubes, float64 CPU tensors).

    Attributes:
        s: ``(K,)`` path parameter, non-decreasing.
        insertion, rotation: ``(K, N)`` actuation [m], [rad].
        tip_position: ``(K, 3)`` [m], base frame; ``tip_rotation``: ``(K, 3, 3)``.
        relative_rotation_at_outer_tip: ``(K, N-1)`` [rad].
        energy: ``(K,)`` [J].
        stability_margin: ``(K,)`` smallest eigenvalue of the scaled (dimensionless) stiffness
            (``Equilibrium.min_stiffness_eigenvalue``); ``stable``: ``(K,)`` bool.
        actuation_forces: ``(K, N)`` [N]; ``actuation_torques``: ``(K, N)`` [N·m] (NaN when
            ``options.compute_forces`` is False).
        converged: ``(K,)`` bool.
        branch: ``(K,)`` int, incremented after every snap (points of one branch share it).
        folds: the :class:`FoldEvent` list, in path order.
        n_solves: number of equilibrium solves spent.
        complete: whether the path was followed to its end; ``reason`` says why not (the
            time limit, or a root-finding continuation stuck on an unstable branch).
    """

    s: torch.Tensor
    insertion: torch.Tensor
    rotation: torch.Tensor
    tip_position: torch.Tensor
    tip_rotation: torch.Tensor
    relative_rotation_at_outer_tip: torch.Tensor
    energy: torch.Tensor
    stability_margin: torch.Tensor
    stable: torch.Tensor
    actuation_forces: torch.Tensor
    actuation_torques: torch.Tensor
    converged: torch.Tensor
    branch: torch.Tensor
    folds: tuple[FoldEvent, ...]
    n_solves: int
    complete: bool = True
    reason: str = "complete"

    def __len__(self) -> int:
        return self.s.shape[0]


# ---------------------------------------------------------------------------------------------

def continuation(scene: Scene | str, path: Any, *, options: SolverOptions | None = None,
                 initial: Equilibrium | torch.Tensor | None = None, max_step: float = 0.02,
                 min_step: float = 1e-3, max_tip_jump: float | None = None,
                 fold_tol: float = 1e-4, s_span: tuple[float, float] = (0.0, 1.0),
                 progress: bool = False, time_limit: float | None = 300.0) -> Continuation:
    """Follow the equilibrium of ``scene`` along ``path`` and report folds (snap points).

    Args:
        scene: a :class:`~torchpvs.Scene` or built-in name / file (its load is kept fixed).
        path: an :class:`ActuationPath`, a mapping ``{"insertion": ..., "rotation": ...}``
            (each a ``(K, N)`` waypoint array, a ``(N,)`` constant or a callable ``s -> (N,)``),
            or a callable ``s -> (insertion, rotation)`` (either may be ``None``).
        options: :class:`SolverOptions` of every solve (``method`` decides which branches can
            be followed: ``"minimize"`` stable ones only).
        initial: warm start of the first solve (an :class:`Equilibrium` or coordinates).
        max_step, min_step: largest / smallest step in ``s``. The step grows (x1.5) after easy
            steps and is halved when a solve fails or the tip jumps more than ``max_tip_jump``;
            a jump that survives halving down to ``min_step`` is a fold.
        max_tip_jump: tip displacement [m] per step above which the step is refined; default
            2% of the longest tube.
        fold_tol: bisection tolerance on ``s`` for the fold location.
        s_span: ``(s_start, s_end)``, a sub-range of ``[0, 1]``; ``s_end < s_start`` follows
            the path backwards (for hysteresis sweeps).
        progress: show a tqdm progress bar (only if tqdm is installed).
        time_limit: [s] wall-clock bound on the whole path (default 300 s; ``None``: none),
            checked before every step, every solve bounded by what is left; a path cut short
            returns what it followed with ``complete=False`` and the ``reason``.

    Returns:
        :class:`Continuation`.
    """
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    pth = _as_path(path)
    opts = options or SolverOptions()
    s0, s1 = (float(v) for v in s_span)
    if not (0.0 <= s0 <= 1.0 and 0.0 <= s1 <= 1.0) or s0 == s1:
        raise ValueError(f"s_span must be two distinct values in [0, 1], got {s_span!r}")
    if not (0 < min_step <= max_step):
        raise ValueError(f"need 0 < min_step <= max_step, got min_step={min_step!r}, "
                         f"max_step={max_step!r}")
    if not (0 < fold_tol):
        raise ValueError(f"fold_tol must be > 0, got {fold_tol!r}")
    direction = 1.0 if s1 > s0 else -1.0
    if max_tip_jump is None:
        max_tip_jump = 0.02 * max(t.length for t in scene.tubes)
    if not (max_tip_jump > 0):
        raise ValueError(f"max_tip_jump must be > 0 [m], got {max_tip_jump!r}")
    quiet = replace(opts, on_failure="ignore")
    n_solves = 0

    t_start = work_clock()
    check_time_limit(time_limit)
    deadline = None if time_limit is None else t_start + time_limit

    def at(s: float, init, o: SolverOptions) -> Equilibrium:
        nonlocal n_solves
        D, A = pth(s, scene)
        n_solves += 1
        return solve(scene, insertion=D, rotation=A, options=within_deadline(o, deadline),
                     initial=init)

    bar = None
    if progress:
        try:
            from tqdm import tqdm
            bar = tqdm(total=abs(s1 - s0), unit="s", desc="continuation")
        except ImportError:
            bar = None

    rows: list[dict[str, Any]] = []
    folds: list[FoldEvent] = []
    branch = 0

    def record(s: float, eq: Equilibrium) -> None:
        D, A = pth(s, scene)
        N = scene.n_tubes
        nan = torch.full((N,), float("nan"), dtype=torch.float64)
        f = eq.actuation_forces
        t = eq.actuation_torques
        rows.append({
            "s": s, "D": D, "A": A,
            "tip": eq.tip_position[0].detach().double().cpu(),
            "R": eq.tip_rotation[0].detach().double().cpu(),
            "rel": eq.relative_rotation_at_outer_tip[0].detach().double().cpu(),
            "energy": float(eq.energy[0]),
            "margin": float(eq.min_stiffness_eigenvalue[0]),
            "stable": bool(eq.stable[0]),
            "forces": f[0].detach().double().cpu() if f is not None else nan,
            "torques": t[0].detach().double().cpu() if t is not None else nan,
            "converged": bool(eq.converged[0]),
            "branch": branch,
        })

    cur = at(s0, initial, opts)
    if not bool(cur.converged[0]):
        raise RuntimeError(f"continuation: the first solve (s = {s0:g}) did not converge: "
                           f"{cur.reason[0]}")
    record(s0, cur)
    s = s0
    h = max_step
    complete, why = True, "complete"
    while direction * (s1 - s) > 1e-14:
        if deadline is not None and work_clock() > deadline:
            complete, why = False, (f"time limit time_limit={time_limit:g} s reached at s = "
                                    f"{s:.6g} of {s1:g} after {n_solves} solves")
            break
        h = max(min(h, max_step), min_step)
        s_new = s + direction * min(h, abs(s1 - s))
        trial = at(s_new, cur, opts)
        ok = bool(trial.converged[0])
        jump = float((trial.tip_position[0] - cur.tip_position[0]).norm()) if ok else math.inf
        lost_stability = ok and bool(cur.stable[0]) and not bool(trial.stable[0])
        if ok and jump <= max_tip_jump and not lost_stability:
            if bar is not None:
                bar.update(abs(s_new - s))
            s, cur = s_new, trial
            record(s, cur)
            if jump < 0.25 * max_tip_jump:
                h *= 1.5
            continue
        if h > min_step * (1 + 1e-9) and abs(s_new - s) > min_step * (1 + 1e-9):
            h *= 0.5
            continue
        if not ok:
            raise RuntimeError(f"continuation: no converged equilibrium at s = {s_new:.6g} even "
                               f"with the minimum step ({min_step:g}): {trial.reason[0]}")
        # A fold between s and s_new: bisect.
        kind = "stability_loss" if (lost_stability and jump <= max_tip_jump) else "branch_jump"
        lo, hi, eq_lo = s, s_new, cur
        while abs(hi - lo) > fold_tol:
            mid = 0.5 * (lo + hi)
            e = at(mid, eq_lo, quiet)
            good = bool(e.converged[0]) and float(
                (e.tip_position[0] - eq_lo.tip_position[0]).norm()) <= max_tip_jump
            if kind == "stability_loss":
                good = good and bool(e.stable[0])
            if good:
                lo, eq_lo = mid, e
                record(lo, eq_lo)            # the approach to the fold, step by step
            else:
                hi = mid
        after = at(hi, eq_lo, replace(opts, method="minimize"))
        if not bool(after.converged[0]):
            raise RuntimeError(f"continuation: the snap at s = {hi:.6g} found no converged "
                               f"equilibrium: {after.reason[0]}")
        if kind == "branch_jump" and bool(after.stable[0]) and float(
                (after.tip_position[0] - eq_lo.tip_position[0]).norm()) <= max_tip_jump:
            # The bracket closed without a jump: the same test from the last point of the
            # branch passes, so s_hi was judged from a point farther back and the branch goes
            # on. Close to a fold the tip speed grows like 1 / sqrt(s_fold - s), so a stretch
            # can exceed max_tip_jump per step without ending: no snap here (order 2 on the
            # section III-B robot reported such stretches 0.2 deg before its fold as folds
            # with 0.3 mm and 1.0 mm "jumps").
            if bar is not None:
                bar.update(abs(hi - s))
            s, cur = hi, after
            record(s, cur)
            h = min_step
            continue
        branch += 1
        record(hi, after)
        D_f, A_f = pth(0.5 * (lo + hi), scene)
        tb, ta = eq_lo.tip_position[0].detach().double().cpu(), \
            after.tip_position[0].detach().double().cpu()
        folds.append(FoldEvent(
            s=0.5 * (lo + hi), bracket=(lo, hi), insertion=D_f, rotation=A_f, kind=kind,
            tip_before=tb, tip_after=ta, tip_jump=float((ta - tb).norm()),
            margin_before=float(eq_lo.min_stiffness_eigenvalue[0]),
            margin_after=float(after.min_stiffness_eigenvalue[0]), index=len(rows) - 1))
        if bar is not None:
            bar.update(abs(hi - s))
        s, cur = hi, after
        if opts.method == "root" and not bool(cur.stable[0]):
            # root cannot leave an unstable branch by itself; nothing stable to follow
            complete, why = False, f"stopped at s = {s:.6g} on an unstable branch (method root)"
            break
        h = max_step
    if bar is not None:
        bar.close()

    def stack(key):
        return torch.stack([r[key] for r in rows])

    def vec(key, dtype=torch.float64):
        return torch.tensor([r[key] for r in rows], dtype=dtype)

    return Continuation(
        s=vec("s"), insertion=stack("D"), rotation=stack("A"), tip_position=stack("tip"),
        tip_rotation=stack("R"), relative_rotation_at_outer_tip=stack("rel"),
        energy=vec("energy"), stability_margin=vec("margin"), stable=vec("stable", torch.bool),
        actuation_forces=stack("forces"), actuation_torques=stack("torques"),
        converged=vec("converged", torch.bool), branch=vec("branch", torch.long),
        folds=tuple(folds), n_solves=n_solves, complete=complete, reason=why)
