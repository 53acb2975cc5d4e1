"""Calibration: fit a robot's model to measured tips, by gradients through the equilibrium.

``calibrate(scene, insertion, rotation, tip, params=...)`` adjusts named tube properties and
actuator offsets so that the PVS equilibria at the commanded actuations land on the measured
tips. It is Levenberg-Marquardt (Marquardt's diagonal scaling) on a robust (Huber) loss, with
the tip Jacobian with respect to the parameters from the implicit-function theorem: every
measurement is one element of ONE batched solve, the parameters are repeated per element, and
three reverse passes of the implicit backward give the ``(M, 3, P)`` Jacobian (no finite
differences). Each iteration's solve is warm-started from the last one's equilibria.

Parameters (the names are fixed; ``name`` means every tube, ``name[j]`` tube ``j``, outermost
first), each in the unit it is reported in:

=====================  =====  ================================================================
name                   unit   meaning
=====================  =====  ================================================================
``precurvature``       1      factor on the tube's nominal precurvature polynomial (its shape
                              is kept; the fitted scene holds the scaled coefficients)
``E``, ``G``           Pa     Young's and shear moduli
``straight_length``    m      proximal straight length
``curved_length``      m      distal precurved length
``insertion_offset``   m      ``D_true = D_commanded + offset`` (carriage zero error)
``rotation_offset``    rad    ``alpha_true = alpha_commanded + offset`` (encoder zero error)
=====================  =====  ================================================================

From tip positions alone some combinations are not identifiable: scaling every ``E`` and ``G``
together leaves an unloaded robot's shape unchanged, and a straight length trades against the
same tube's insertion offset. The result's ``identifiability`` names such combinations (from
the singular values of the column-normalized, weighted Jacobian); fix one parameter of each
(leave it out of ``params``) to make the rest well posed.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from .inputs import check_actuation
from .options import SolverOptions
from .plan import tube_tensors
from .scene import Scene, load_scene
from .sections import TubeTensors
from .solver import solve, solve_tensors

__all__ = ["calibrate", "Calibration", "Identifiability", "CalibrationStep", "PARAMETERS"]

#: Parameter kinds by name -> (unit, default bounds relative to nominal or absolute).
PARAMETERS = ("precurvature", "E", "G", "straight_length", "curved_length",
              "insertion_offset", "rotation_offset")
_UNITS = {"precurvature": "", "E": "Pa", "G": "Pa", "straight_length": "m",
          "curved_length": "m", "insertion_offset": "m", "rotation_offset": "rad"}
_NAME = re.compile(r"^([a-z_A-Z]+)(?:\[(\d+)\])?$")


@dataclass(frozen=True)
class CalibrationStep:
    """One accepted or rejected Levenberg-Marquardt step: ``cost`` (robust loss [m²]),
    ``rms`` [m] of the inlier residuals, ``damping`` (the LM lambda), ``accepted``."""

    cost: float
    rms: float
    damping: float
    accepted: bool


@dataclass(frozen=True)
class Identifiability:
    """What the measurements can and cannot separate, at the fit.

    Attributes:
        singular_values: ``(P,)`` of the weighted Jacobian with unit-norm columns, descending.
        condition: largest over smallest singular value (``inf`` when rank deficient).
        unidentifiable: one tuple of parameter names per direction whose singular value is
            below ``threshold`` times the largest: the parameters that move together there
            (e.g. ``("E[0]", "E[1]", "G[0]", "G[1]")``). Empty when everything is identifiable.
        correlation: ``(P, P)`` correlations from the covariance (NaN where undefined).
        threshold: the relative singular value below which a direction is reported.
    """

    singular_values: np.ndarray
    condition: float
    unidentifiable: tuple[tuple[str, ...], ...]
    correlation: np.ndarray
    threshold: float

    @property
    def identifiable(self) -> bool:
        return not self.unidentifiable


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes:
        scene: the fitted scene (tube properties replaced; the offsets are not part of a
            scene: see ``insertion_offset``/``rotation_offset`` and :meth:`predict`).
        names: ``(P,)`` parameter names (``"E[1]"``, ...).
        value, initial, std: ``(P,)`` fitted and initial values and standard deviations, in
            each parameter's unit (module docstring). ``std`` is from the Gauss-Newton
            covariance ``s² (J^T W J)^-1`` with ``s²`` the weighted residual variance; ``inf``
            for parameters in an unidentifiable direction.
        insertion_offset, rotation_offset: ``(N,)`` [m], [rad] the fitted offsets (0 where not
            fitted).
        residuals: ``(M, 3)`` [m] model tip minus measured tip at the fit.
        inlier: ``(M,)`` measurements within the Huber scale at the fit.
        rms: [m] root-mean-square tip error over the inliers (per measurement, 3-D norm).
        converged, reason: whether the iteration met its tolerance, and why it stopped.
        iterations: LM iterations run; ``history``: one :class:`CalibrationStep` each.
        identifiability: :class:`Identifiability` at the fit.
        solve_failures: measurements whose equilibrium did not converge at the fit.
        wall_s: [s] wall time.
    """

    scene: Scene
    names: tuple[str, ...]
    value: np.ndarray
    initial: np.ndarray
    std: np.ndarray
    insertion_offset: np.ndarray
    rotation_offset: np.ndarray
    residuals: np.ndarray
    inlier: np.ndarray
    rms: float
    converged: bool
    reason: str
    iterations: int
    history: tuple[CalibrationStep, ...]
    identifiability: Identifiability
    solve_failures: int
    wall_s: float

    def __getitem__(self, name: str) -> float:
        """The fitted value of parameter ``name`` (e.g. ``cal["precurvature[1]"]``)."""
        try:
            return float(self.value[self.names.index(name)])
        except ValueError:
            raise KeyError(f"{name!r} was not fitted (fitted: {list(self.names)})") from None

    def predict(self, insertion, rotation, options: SolverOptions | None = None) -> np.ndarray:
        """Tips ``(K, 3)`` [m] of the fitted model at commanded actuations ``(K, N)`` (the
        fitted offsets applied)."""
        D = np.atleast_2d(np.asarray(insertion, np.float64)) + self.insertion_offset
        A = np.atleast_2d(np.asarray(rotation, np.float64)) + self.rotation_offset
        eq = solve(self.scene, insertion=torch.as_tensor(D), rotation=torch.as_tensor(A),
                   options=options or SolverOptions(on_failure="ignore", compute_forces=False))
        return eq.tip_position.detach().numpy()

    def report(self) -> str:
        """A human-readable table of the fit."""
        lines = [f"calibration: {'converged' if self.converged else 'NOT converged'} "
                 f"({self.reason}) after {self.iterations} iterations, {self.wall_s:.1f} s",
                 f"inlier tip rms {self.rms * 1e3:.4f} mm, {int(self.inlier.sum())}/"
                 f"{len(self.inlier)} inliers, {self.solve_failures} solve failures",
                 f"{'parameter':<22}{'initial':>14}{'fitted':>14}{'std':>12}  unit"]
        for n, v0, v, s in zip(self.names, self.initial, self.value, self.std, strict=True):
            unit = _UNITS[_NAME.match(n).group(1)]
            lines.append(f"{n:<22}{v0:>14.6g}{v:>14.6g}{s:>12.3g}  {unit}")
        idf = self.identifiability
        lines.append(f"condition number {idf.condition:.3g}")
        for group in idf.unidentifiable:
            lines.append(f"NOT identifiable from these data (move together): "
                         f"{', '.join(group)}; fix one of them")
        return "\n".join(lines)


@dataclass(frozen=True)
class _Param:
    kind: str
    tube: int

    @property
    def name(self) -> str:
        return f"{self.kind}[{self.tube}]"


def _parse(params, n_tubes: int) -> list[_Param]:
    if isinstance(params, str):
        params = (params,)
    try:
        items = list(params)
    except TypeError:
        raise ValueError(f"params must be a sequence of parameter names, got {params!r}") from None
    out: list[_Param] = []
    for p in items:
        m = _NAME.match(p) if isinstance(p, str) else None
        if m is None or m.group(1) not in PARAMETERS:
            raise ValueError(f"params: unknown parameter {p!r}; names are {PARAMETERS}, for "
                             f"every tube, or one tube as e.g. 'precurvature[1]'")
        kind = m.group(1)
        tubes = range(n_tubes) if m.group(2) is None else [int(m.group(2))]
        for j in tubes:
            if not 0 <= j < n_tubes:
                raise ValueError(f"params: {p!r} names tube {j}, but the scene has {n_tubes} "
                                 f"tubes (0 = outermost)")
            q = _Param(kind, j)
            if q in out:
                raise ValueError(f"params: {q.name} is named twice")
            out.append(q)
    if not out:
        raise ValueError("params: name at least one parameter to fit")
    return out


def _nominal(scene: Scene, p: _Param) -> float:
    t = scene.tubes[p.tube]
    return {"precurvature": 1.0, "E": t.E, "G": t.G, "straight_length": t.straight_length,
            "curved_length": t.curved_length, "insertion_offset": 0.0,
            "rotation_offset": 0.0}[p.kind]


def _default_bounds(scene: Scene, p: _Param) -> tuple[float, float]:
    v = _nominal(scene, p)
    t = scene.tubes[p.tube]
    if p.kind in ("precurvature", "E", "G"):
        return 0.2 * v, 5.0 * v
    if p.kind in ("straight_length", "curved_length"):
        return max(0.0, v - 0.5 * t.length), v + 0.5 * t.length
    if p.kind == "insertion_offset":
        return -0.02, 0.02
    return -math.pi, math.pi


def _measurements(scene: Scene, insertion, rotation, tip, weights):
    N = scene.n_tubes
    arrays = {}
    for name, value, width in (("insertion", insertion, N), ("rotation", rotation, N),
                               ("tip", tip, 3)):
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a real array of shape (M, {width})") from None
        if a.ndim != 2 or a.shape[1] != width:
            raise ValueError(f"{name} must have shape (M, {width}), got {a.shape}")
        if not np.isfinite(a).all():
            rows = sorted({int(i) for i in np.argwhere(~np.isfinite(a))[:, 0]})
            raise ValueError(f"{name} must be finite (rows {rows[:5]} are not)")
        arrays[name] = a
    M = arrays["tip"].shape[0]
    for name in ("insertion", "rotation"):
        if arrays[name].shape[0] != M:
            raise ValueError(f"{name} has {arrays[name].shape[0]} rows but tip has {M}: one row "
                             f"per measurement")
    if weights is None:
        w = np.ones(M)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (M,) or not np.isfinite(w).all() or (w < 0).any() or not (w > 0).any():
            raise ValueError(f"weights must be ({M},) finite, >= 0 and not all 0, got shape "
                             f"{w.shape}")
    return arrays["insertion"], arrays["rotation"], arrays["tip"], w


def _huber(d: np.ndarray, delta: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-measurement loss and IRLS weight for tip-error norms ``d`` [m]."""
    if delta is None:
        return 0.5 * d ** 2, np.ones_like(d)
    inside = d <= delta
    loss = np.where(inside, 0.5 * d ** 2, delta * (d - 0.5 * delta))
    return loss, np.where(inside, 1.0, delta / np.maximum(d, 1e-300))


class _Model:
    """The batched, differentiable map ``z (P,) -> tips (M, 3)`` and its Jacobian."""

    def __init__(self, scene: Scene, specs: list[_Param], D: np.ndarray, A: np.ndarray,
                 F: np.ndarray | None, options: SolverOptions):
        self.scene, self.specs, self.options = scene, specs, options
        dt = torch.float64
        self.M = D.shape[0]
        self.base = tube_tensors(scene, dt, torch.device("cpu"))
        self.second = torch.tensor([t.second_moment for t in scene.tubes], dtype=dt)
        self.D = torch.as_tensor(D, dtype=dt)
        self.A = torch.as_tensor(A, dtype=dt)
        self.F = (torch.zeros(self.M, 3, dtype=dt) if F is None
                  else torch.as_tensor(F, dtype=dt).expand(self.M, 3).contiguous())
        self.initial = None

    def inputs(self, z: torch.Tensor):
        """Per-measurement tube tensors and actuation for parameters ``z (M, P)``."""
        M, N = self.M, self.scene.n_tubes
        b = self.base
        fac = {k: torch.ones(M, N, dtype=z.dtype) for k in ("precurvature", "E", "G")}
        add = {k: torch.zeros(M, N, dtype=z.dtype) for k in
               ("straight_length", "curved_length", "insertion_offset", "rotation_offset")}
        tubes = self.scene.tubes
        for i, p in enumerate(self.specs):
            if p.kind in fac:
                nominal = _nominal(self.scene, p)
                fac[p.kind] = _set_col(fac[p.kind], p.tube, z[:, i] / nominal)
            elif p.kind in ("straight_length", "curved_length"):
                nominal = getattr(tubes[p.tube], p.kind)
                add[p.kind] = _set_col(add[p.kind], p.tube, z[:, i] - nominal)
            else:
                add[p.kind] = _set_col(add[p.kind], p.tube, z[:, i])
        straight = b.straight + add["straight_length"]
        length = b.length + add["straight_length"] + add["curved_length"]
        t = TubeTensors(EI=b.EI * fac["E"], GJ=b.GJ * fac["G"], length=length,
                        straight=straight, coef=b.coef * fac["precurvature"][..., None, None])
        return t, self.D + add["insertion_offset"], self.A + add["rotation_offset"]

    def feasible(self, z: np.ndarray) -> str | None:
        """Why ``z`` is outside the model's domain (negative or unnested insertions, a
        non-positive length), or None."""
        with torch.no_grad():
            t, D, _ = self.inputs(torch.as_tensor(z, dtype=torch.float64)[None].expand(self.M, -1))
            if (t.length <= 0).any() or (t.straight < 0).any() or (t.straight > t.length).any():
                return "a tube length left its range"
            try:
                check_actuation(D, self.scene)
            except ValueError as e:
                return str(e)
        return None

    def tips(self, z: np.ndarray, jacobian: bool):
        """``(tips (M, 3), J (M, 3, P) or None, converged (M,))`` at ``z (P,)``."""
        P = len(self.specs)
        zr = torch.as_tensor(z, dtype=torch.float64)[None].expand(self.M, P).clone()
        if jacobian:
            zr.requires_grad_(True)
        with torch.set_grad_enabled(jacobian):
            t, D, A = self.inputs(zr)
            eq = solve_tensors(self.scene, t, D, A, self.F, torch.zeros_like(self.F),
                               self.options, self.initial, None)
            tip = eq.tip_position
            J = None
            if jacobian:
                rows = [torch.autograd.grad(tip[:, i].sum(), zr, retain_graph=i < 2)[0]
                        for i in range(3)]
                J = torch.stack(rows, 1).numpy()
        self.initial = eq
        return tip.detach().numpy(), J, eq.converged.numpy()


def _set_col(x: torch.Tensor, j: int, col: torch.Tensor) -> torch.Tensor:
    # out of place, so that autograd sees the column's dependence on z
    mask = torch.zeros(x.shape[1], dtype=torch.bool)
    mask[j] = True
    return torch.where(mask[None, :], col[:, None], x)


def calibrate(scene: Scene | str, insertion, rotation, tip, *,
              params=("precurvature",), weights=None, huber_scale: float | None = 5e-4,
              bounds: dict | None = None, tip_force=None, max_iter: int = 50,
              tol: float = 1e-8, rank_threshold: float = 1e-6,
              options: SolverOptions | None = None, verbose: bool = False) -> Calibration:
    """Fit ``params`` of ``scene`` to measured tips.

    Args:
        scene: the nominal robot (a :class:`~torchpvs.Scene`, built-in name or file).
        insertion, rotation: ``(M, N)`` commanded actuations [m], [rad] of the measurements.
        tip: ``(M, 3)`` [m] measured tip positions, base frame.
        params: parameter names to fit (module docstring): ``"precurvature"`` (every tube)
            or ``"precurvature[1]"`` (one tube), ... The rest keep the scene's values.
        weights: ``(M,)`` per-measurement weights (>= 0), default 1.
        huber_scale: [m] Huber scale of the per-measurement tip error: errors beyond it count
            linearly, so outliers do not drag the fit (``None``: least squares). A few times
            the measurement noise (per axis) is a good choice.
        bounds: ``{name: (low, high)}`` in the parameter's unit, per kind or per tube
            (``"E"`` or ``"E[1]"``); defaults: factors and moduli 0.2-5x nominal, lengths
            +-half the tube's length, insertion offsets +-20 mm, rotation offsets +-pi.
        tip_force: ``(3,)`` or ``(M, 3)`` [N] known tip forces of the measurements.
        max_iter: Levenberg-Marquardt iterations.
        tol: stop when the relative decrease of the loss, or the step relative to the
            parameters' typical magnitudes, is below this (or when every residual is below
            1 % of ``options.accuracy``, the solver's own error).
        rank_threshold: relative singular value below which a direction is unidentifiable.
        options: solver options (default: the solver's defaults, failures not warned).
        verbose: print one line per iteration.

    Returns:
        :class:`Calibration`. Never raises for a fit that does not converge: ``converged``
        and ``reason`` say so.

    Raises:
        ValueError: bad shapes, non-finite data, unknown parameter names or bounds, initial
            values outside the bounds, fewer measurement components (3 M) than parameters.
    """
    t_start = time.perf_counter()
    scene = scene if isinstance(scene, Scene) else load_scene(scene)
    N = scene.n_tubes
    D, A, T, w_user = _measurements(scene, insertion, rotation, tip, weights)
    specs = _parse(params, N)
    P, M = len(specs), T.shape[0]
    if 3 * int((w_user > 0).sum()) < P:
        raise ValueError(f"tip: {int((w_user > 0).sum())} weighted measurements give "
                         f"{3 * int((w_user > 0).sum())} equations for {P} parameters; "
                         f"measure more configurations or fit fewer parameters")
    if huber_scale is not None and not (isinstance(huber_scale, (int, float))
                                        and math.isfinite(huber_scale) and huber_scale > 0):
        raise ValueError(f"huber_scale must be a positive length [m] or None, got "
                         f"{huber_scale!r}")
    if not (isinstance(max_iter, int) and max_iter >= 1):
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    lo, hi = _bounds(scene, specs, bounds)
    z = np.array([_nominal(scene, p) for p in specs])
    z0 = z.copy()
    F = None
    if tip_force is not None:
        F = np.asarray(tip_force, np.float64)
        if F.shape not in ((3,), (M, 3)) or not np.isfinite(F).all():
            raise ValueError(f"tip_force must be finite, (3,) or ({M}, 3) [N], got {F.shape}")
    opts = options or SolverOptions(on_failure="ignore", compute_forces=False)
    model = _Model(scene, specs, D, A, F, opts)
    why = model.feasible(z)
    if why is not None:
        raise ValueError(f"insertion: the nominal model cannot be solved at the measurements: "
                         f"{why}")
    # Marquardt's scaling: z in units of a typical magnitude, so damping is per unit change
    scale = np.array([abs(_nominal(scene, p)) or (1e-3 if p.kind == "insertion_offset"
                                                  else 1e-2) for p in specs])
    tips, J, conv = model.tips(z, jacobian=True)
    cost, rms, w_irls, inl = _cost(tips, T, w_user, huber_scale, conv)
    # below this the residuals are the discretization's, not the data's: nothing to gain
    floor = 0.5 * float(w_user.sum()) * (1e-2 * opts.accuracy) ** 2
    history: list[CalibrationStep] = []
    lam, converged, reason, it = 1e-3, False, f"stopped after max_iter={max_iter} iterations", 0
    for it in range(1, max_iter + 1):
        e = (tips - T)                                                   # (M, 3)
        sw = np.sqrt(w_irls * w_user * conv)[:, None, None]
        Js = (J * sw * scale[None, None, :]).reshape(3 * M, P)
        r = (e[..., None] * sw).reshape(3 * M)
        g = Js.T @ r
        Hm = Js.T @ Js
        step_taken, at_floor = False, False
        for _ in range(12):
            Ad = Hm + lam * np.diag(np.maximum(np.diag(Hm), 1e-12 * np.trace(Hm) / P + 1e-300))
            try:
                dz = -np.linalg.solve(Ad, g) * scale
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            z_new = np.clip(z + dz, lo, hi)
            # the decrease the Gauss-Newton model predicts for this step (scaled units)
            u = (z_new - z) / scale
            predicted = -(g @ u) - 0.5 * u @ Hm @ u
            if model.feasible(z_new) is not None:
                lam *= 10.0
                history.append(CalibrationStep(cost, rms, lam, False))
                continue
            tips_n, J_n, conv_n = model.tips(z_new, jacobian=True)
            cost_n, rms_n, w_n, inl_n = _cost(tips_n, T, w_user, huber_scale, conv_n)
            if conv_n.sum() >= conv.sum() and cost_n <= cost:
                rel = (cost - cost_n) / max(cost, 1e-300)
                small = np.max(np.abs(z_new - z) / scale) < tol
                z, tips, J, conv = z_new, tips_n, J_n, conv_n
                cost, rms, w_irls, inl = cost_n, rms_n, w_n, inl_n
                lam = max(lam / 3.0, 1e-9)
                history.append(CalibrationStep(cost, rms, lam, True))
                step_taken = True
                if verbose:
                    print(f"  it {it:3d}: loss {cost:.4e} m², inlier rms {rms * 1e3:.4f} mm, "
                          f"lambda {lam:.1e}", flush=True)
                if rel < tol or small or cost <= floor:
                    converged = True
                    reason = ("loss decrease below tol" if rel < tol else
                              "step below tol" if small else
                              "tip residuals below 1 % of the solver's accuracy")
                break
            if predicted <= max(tol, 1e-6) * cost:
                # what is left to gain is below the noise of the solves themselves (their
                # accuracy): this is the minimum, to the model's precision
                at_floor = True
                break
            lam *= 10.0
            history.append(CalibrationStep(cost, rms, lam, False))
            model.initial = None   # the rejected solve's equilibria are not a good warm start
        if at_floor:
            converged, reason = True, "predicted decrease below tol (the solver's precision)"
            break
        if converged:
            break
        if not step_taken:
            converged = bool(np.linalg.norm(g) <= 1e-12 * max(1.0, cost))
            reason = ("gradient zero" if converged else
                      "no step reduced the loss (lambda exhausted); the fit is a local minimum "
                      "at the solver's precision or the data are inconsistent")
            break
    idf, std = _uncertainty(J, tips - T, w_irls * w_user * conv, scale, specs, rank_threshold, P)
    fitted = _fitted_scene(scene, specs, z)
    off_D, off_A = np.zeros(N), np.zeros(N)
    for p, v in zip(specs, z, strict=True):
        if p.kind == "insertion_offset":
            off_D[p.tube] = v
        elif p.kind == "rotation_offset":
            off_A[p.tube] = v
    return Calibration(
        scene=fitted, names=tuple(p.name for p in specs), value=z, initial=z0, std=std,
        insertion_offset=off_D, rotation_offset=off_A, residuals=tips - T, inlier=inl,
        rms=rms, converged=converged, reason=reason, iterations=it, history=tuple(history),
        identifiability=idf, solve_failures=int((~conv).sum()),
        wall_s=time.perf_counter() - t_start)


def _bounds(scene: Scene, specs: list[_Param], bounds: dict | None):
    lo = np.array([_default_bounds(scene, p)[0] for p in specs])
    hi = np.array([_default_bounds(scene, p)[1] for p in specs])
    names = [p.name for p in specs]
    for key, value in (bounds or {}).items():
        m = _NAME.match(key) if isinstance(key, str) else None
        if m is None or m.group(1) not in PARAMETERS:
            raise ValueError(f"bounds: unknown parameter {key!r}; names are {PARAMETERS}")
        hit = [i for i, p in enumerate(specs) if p.kind == m.group(1)
               and (m.group(2) is None or p.tube == int(m.group(2)))]
        if not hit:
            raise ValueError(f"bounds: {key!r} is not among the fitted parameters {names}")
        try:
            low, high = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ValueError(f"bounds[{key!r}] must be a pair (low, high), got {value!r}") from None
        if not low < high:
            raise ValueError(f"bounds[{key!r}]: low ({low}) must be below high ({high})")
        lo[hit], hi[hit] = low, high
    z = np.array([_nominal(scene, p) for p in specs])
    out = (z < lo) | (z > hi)
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise ValueError(f"bounds[{names[i]!r}] = ({lo[i]:g}, {hi[i]:g}) excludes the scene's "
                         f"value {z[i]:g}, where the fit starts")
    return lo, hi


def _cost(tips, T, w_user, delta, conv):
    d = np.linalg.norm(tips - T, axis=-1)
    d = np.where(conv, d, 0.0)
    loss, w = _huber(d, delta)
    inl = (d <= delta) & conv if delta is not None else conv.copy()
    rms = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan")
    # a non-converged measurement costs as much as an outlier at 100 Huber scales
    penalty = 0.0 if delta is None else float(((~conv) * w_user).sum()) * 100 * delta ** 2
    return float((w_user * loss).sum()) + penalty, rms, w, inl


def _uncertainty(J, e, w, scale, specs, threshold, P):
    """Identifiability report and standard deviations at the fit."""
    M = e.shape[0]
    sw = np.sqrt(w)[:, None, None]
    Js = (J * sw * scale[None, None, :]).reshape(3 * M, P)
    norms = np.linalg.norm(Js, axis=0)
    Jn = Js / np.where(norms > 0, norms, 1.0)
    _, sv, Vt = np.linalg.svd(Jn, full_matrices=False)
    names = [p.name for p in specs]
    weak = sv < threshold * sv[0] if sv[0] > 0 else np.ones_like(sv, dtype=bool)
    # a weak direction in the scaled parameters (relative changes): who moves together
    moves = [np.abs(Vt[k] / np.where(norms > 0, norms, 1.0)) for k in np.flatnonzero(weak)]
    members = [np.flatnonzero(u > 0.2 * u.max()) for u in moves]
    groups = [tuple(names[i] for i in m) for m in members]
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    dof = max(1, int((w > 0).sum()) * 3 - P)
    s2 = float(((e ** 2).sum(-1) * w).sum() / dof)
    H = Js.T @ Js
    std = np.full(P, np.inf)
    corr = np.full((P, P), np.nan)
    if not weak.any():
        cov = s2 * np.linalg.inv(H)
        std = np.sqrt(np.maximum(np.diag(cov), 0.0)) * scale
        d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        corr = cov / np.outer(d, d)
    else:
        bad = {int(i) for m in members for i in m}
        good = [i for i in range(P) if i not in bad]
        if good:
            cov = s2 * np.linalg.pinv(H[np.ix_(good, good)])
            std[good] = np.sqrt(np.maximum(np.diag(cov), 0.0)) * scale[good]
    return Identifiability(singular_values=sv, condition=cond, unidentifiable=tuple(groups),
                           correlation=corr, threshold=threshold), std


def _fitted_scene(scene: Scene, specs: list[_Param], z: np.ndarray) -> Scene:
    tubes = list(scene.tubes)
    for p, v in zip(specs, z, strict=True):
        t = tubes[p.tube]
        if p.kind == "precurvature":
            t = replace(t, precurvature=tuple(tuple(float(c) * float(v) for c in ax)
                                              for ax in t.precurvature))
        elif p.kind in ("E", "G", "straight_length", "curved_length"):
            t = replace(t, **{p.kind: float(v)})
        tubes[p.tube] = t
    return replace(scene, tubes=tuple(tubes))
