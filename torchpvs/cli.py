"""The ``torchpvs`` command: ``solve``, ``plot``, ``demo`` and ``scenes``.

``torchpvs solve SCENE --json`` prints the object of ``docs/conventions.md`` and exits
0 (converged), 1 (not converged; the output is still printed) or 2 (bad scene or bad arguments,
with a one-line message on stderr). ``SCENE`` is a YAML/JSON file or a built-in scene name;
``--set KEY=VALUE`` overrides a field before validation (``--set actuation.rotation[1]=0.5``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["CONTRACT_KEYS", "EXTENSION_KEYS", "MODELS", "format_table", "main"]

MODELS = ("pvs", "standard")
CONTRACT_KEYS = (
    "model", "converged", "tip_position", "tip_rotation", "relative_rotation_at_outer_tip",
    "actuation_forces", "actuation_torques", "energy", "stable", "min_stiffness_eigenvalue",
    "residual_norm", "iterations", "dofs", "solve_time_s",
)
# Documented extensions (docs/conventions.md allows new output keys): the PVS model reports the
# insertion-side force where U*(D) has a kink, and which forces are one-sided.
EXTENSION_KEYS = ("actuation_forces_insertion", "force_kink", "error_estimate", "accuracy_met")
DEMO_SCENE = "renda2021_fig3"


class CLIError(Exception):
    """A bad scene or bad argument: one line on stderr, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error message (exit status 2, as argparse's own)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _points(text: str) -> int:
    try:
        k = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 2, got {text!r}") from None
    if k < 2:
        raise argparse.ArgumentTypeError(f"must be an integer >= 2, got {text!r}")
    return k


def _build_parser() -> _Parser:
    parser = _Parser(prog="torchpvs", description="Equilibria of concentric tube robots "
                     "(piecewise variable-strain model and the standard reference model).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    def scene_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("scene", metavar="SCENE", help="scene file (.yaml/.yml/.json) or "
                       "built-in name (see `torchpvs scenes`)")
        p.add_argument("--model", choices=MODELS, default="pvs",
                       help="pvs (default) or standard (the reference Cosserat-rod model)")
        p.add_argument("--set", dest="overrides", action="append", default=[],
                       metavar="KEY=VALUE",
                       help="override a scene field, e.g. actuation.rotation[1]=0.5 (repeatable)")

    p = sub.add_parser("solve", help="solve one equilibrium and print it",
                       description="Solve one equilibrium. Exit 0 converged, 1 not converged, "
                       "2 bad scene or arguments.")
    scene_args(p)
    p.add_argument("--json", action="store_true",
                   help="print one JSON object (docs/conventions.md) instead of a table")
    p.add_argument("--backbone", type=_points, metavar="K",
                   help="add K >= 2 backbone points [m] from the orifice to the tip")

    p = sub.add_parser("plot", help="solve and save a 3D plot of the backbone",
                       description="Solve and save a 3D backbone plot (format from the suffix).")
    scene_args(p)
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="image file, e.g. fig.png (missing parent folders are created)")
    p.add_argument("--points", type=_points, default=200, metavar="K",
                   help="backbone points (default 200)")

    p = sub.add_parser("demo", help=f"solve {DEMO_SCENE} with both models, compare, plot",
                       description=f"Solve the built-in scene {DEMO_SCENE} (Renda et al. 2021, "
                       "Fig. 3) with the standard and the PVS model, print both, save a plot.")
    p.add_argument("-o", "--output-dir", default="demo_out", metavar="DIR",
                   help="folder for the figure (default demo_out)")

    sub.add_parser("scenes", help="list the built-in scenes",
                   description="List the built-in scene names, one per line.")

    p = sub.add_parser(
        "calibrate", help="fit a scene to measured tips and write the fitted scene",
        description="Fit tube properties and actuator offsets of SCENE to measured tips "
        "(torchpvs.calibrate, docs/calibration.md). MEASUREMENTS is a CSV file with a header "
        "and one row per measurement: insertion_0..insertion_{N-1} [m], rotation_0.."
        "rotation_{N-1} [rad] (commanded; tube 0 = outermost), tip_x, tip_y, tip_z [m] "
        "(base frame) and optionally weight. Prints the report; writes the fitted scene "
        "as YAML (offsets in its header comment). Exit 0 converged, 1 not converged, 2 bad "
        "input.")
    p.add_argument("scene", metavar="SCENE", help="the nominal scene (file or built-in name)")
    p.add_argument("measurements", metavar="MEASUREMENTS", help="CSV file (see above)")
    p.add_argument("--params", nargs="+", default=["precurvature"], metavar="NAME",
                   help="parameters to fit (default precurvature), e.g. precurvature E[1] G "
                        "insertion_offset")
    p.add_argument("--huber-scale", type=float, default=5e-4, metavar="M",
                   help="[m] Huber scale of the tip error (default 5e-4; 0 = least squares)")
    p.add_argument("-o", "--output", metavar="FILE",
                   help="fitted scene YAML (default <MEASUREMENTS stem>_fitted.yaml)")
    p.add_argument("--json", action="store_true", help="print the fit as one JSON object")
    return parser


# ---------------------------------------------------------------------------------------------
# Solving

def _load(source: str, overrides: Sequence[str]) -> Any:
    import yaml

    from .scene import load_scene

    for item in overrides:  # name the --set whose value is not YAML (load_scene would not)
        _, _, raw = item.partition("=")
        try:
            yaml.safe_load(raw)
        except (yaml.YAMLError, ValueError) as exc:  # ValueError: int() digit limit
            raise CLIError(f"--set {_short(item)}: cannot parse the value {_short(raw)} "
                           f"(YAML: {_one_line(exc)[:200]})") from None
    try:
        return load_scene(source, list(overrides))
    except (ValueError, OSError, yaml.YAMLError) as exc:  # SceneError is a ValueError
        raise CLIError(_one_line(exc)) from None


def _short(text: str, limit: int = 60) -> str:
    """``repr(text)``, cut to ``limit`` characters (a 5000-digit value is not echoed whole)."""
    r = repr(text)
    return r if len(r) <= limit else f"{r[:limit]}... ({len(text)} characters)"


def _solve(scene: Any, model: str, prog: str) -> Any:
    """Solve with ``model``; solver chatter and warnings go to stderr, one line each."""
    if model == "standard":
        try:
            from torchpvs.reference import solve_standard as solver
        except ImportError:
            raise CLIError("--model standard is not available yet") from None
    else:
        try:
            from torchpvs.solver import solve as solver
        except ImportError:
            raise CLIError("--model pvs is not available yet") from None
    with warnings.catch_warnings(record=True) as caught, \
            contextlib.redirect_stdout(sys.stderr):
        # Every warning of a solve is shown, one line each, even when the same warning was
        # shown by an earlier solve in this process ("always": the default "once per
        # location" would hide the second batch's non-convergence). Not shown: deprecation
        # warnings that torch raises about its own internals, which a CLI user cannot act on.
        # torch's first forward-mode AD call (torch.func.jvp, used for the loaded
        # equilibria) imports torch._decomp.decompositions_for_jvp, which calls the
        # deprecated torch.jit.script once per decomposition (18 lines per loaded solve).
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch(\.|$)")
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning,
                                module=r"torch(\.|$)")
        try:
            sol = solver(scene)
        except ValueError as exc:  # the solver rejects the scene (SceneError included)
            raise CLIError(_one_line(exc)) from None
    for w in caught:
        print(f"{prog}: warning: {_one_line(w.message)}", file=sys.stderr)
    return sol


def _contract(sol: Any, backbone_points: int | None = None) -> dict[str, Any]:
    with contextlib.redirect_stdout(sys.stderr):
        return _jsonable(sol.as_contract(backbone_points=backbone_points))


def _jsonable(value: Any) -> Any:
    """Plain JSON values: non-finite floats become ``null``; numpy/torch values become lists
    and Python scalars."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value


def _backbone(sol: Any, points: int) -> Any:
    from .plotting import as_points

    with contextlib.redirect_stdout(sys.stderr):
        return as_points(sol.backbone(points))


# ---------------------------------------------------------------------------------------------
# Tables

def _rotvec_deg(R: Any) -> list[float] | None:
    """Rotation vector [deg] of a 3x3 rotation matrix (axis times angle)."""
    try:
        import numpy as np
        from scipy.spatial.transform import Rotation

        m = np.asarray(R, dtype=float)
        if m.shape != (3, 3) or not np.isfinite(m).all():
            return None
        return list(np.degrees(Rotation.from_matrix(m).as_rotvec()))
    except (TypeError, ValueError):
        return None


def _rows(c: dict[str, Any], scene: Any) -> list[tuple[str, str, Any, str]]:
    """``(label, unit, value, format)`` rows of one contract, in display units."""
    names = [t.name or f"tube{j + 1}" for j, t in enumerate(scene.tubes)]

    def at(key: str, i: int, scale: float = 1.0) -> float | None:
        vals = c.get(key)
        if not isinstance(vals, list) or i >= len(vals) or vals[i] is None:
            return None
        return float(vals[i]) * scale

    def num(key: str, scale: float = 1.0) -> float | None:
        v = c.get(key)
        return None if v is None else float(v) * scale

    rows: list[tuple[str, str, Any, str]] = [("converged", "", c.get("converged"), "")]
    for i, ax in enumerate("xyz"):
        rows.append((f"tip position {ax}", "mm", at("tip_position", i, 1e3), ".4f"))
    R = c.get("tip_rotation")
    tangent = None
    if isinstance(R, list) and len(R) == 3 and all(isinstance(r, list) and len(r) == 3
                                                   and r[2] is not None for r in R):
        tangent = [float(r[2]) for r in R]
    for i, ax in enumerate("xyz"):
        rows.append((f"tip tangent {ax}", "-", None if tangent is None else tangent[i], ".5f"))
    rv = _rotvec_deg(R) if R is not None else None
    rows.append(("tip rotation angle", "deg",
                 None if rv is None else math.sqrt(sum(v * v for v in rv)), ".3f"))
    for i, ax in enumerate("xyz"):
        rows.append((f"tip rotation vector {ax}", "deg", None if rv is None else rv[i], ".3f"))
    for j in range(1, len(names)):
        rows.append((f"rotation {names[j]} vs {names[0]} at l_1", "deg",
                     at("relative_rotation_at_outer_tip", j - 1, 180.0 / math.pi), ".3f"))
    for j, name in enumerate(names):
        rows.append((f"actuation force D{j + 1} ({name})", "N",
                     at("actuation_forces", j), ".5f"))
    for j, name in enumerate(names):
        rows.append((f"actuation torque alpha{j + 1} ({name})", "mN·m",
                     at("actuation_torques", j, 1e3), ".4f"))
    rows += [
        ("energy", "mJ", num("energy", 1e3), ".5f"),
        ("stable", "", c.get("stable"), ""),
        ("min stiffness eigenvalue", "", num("min_stiffness_eigenvalue"), ".4e"),
        ("residual norm", "", num("residual_norm"), ".3e"),
        ("iterations", "", c.get("iterations"), "d"),
        ("dofs", "", c.get("dofs"), "d"),
        ("solve time", "s", num("solve_time_s"), ".3f"),
    ]
    if "backbone" in c:
        rows.append(("backbone points", "", len(c["backbone"] or []), "d"))
    return rows


def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if spec and isinstance(value, (int, float)):
        return format(value, spec)
    return str(value)


def format_table(contracts: Sequence[dict[str, Any]], scene: Any, *,
                 headers: Sequence[str] | None = None, title: str | None = None) -> str:
    """An aligned, human-readable table of one or more contracts (one column each; with two,
    a third column ``second - first``) in mm, deg, N, mN·m and mJ."""
    headers = list(headers or [str(c.get("model", "")) for c in contracts])
    per = [_rows(c, scene) for c in contracts]
    labels: list[tuple[str, str, str]] = []
    values: dict[str, list[Any]] = {}
    for k, rows in enumerate(per):
        for label, unit, value, spec in rows:
            if label not in values:
                labels.append((label, unit, spec))
                values[label] = [None] * len(contracts)
            values[label][k] = value
    diff = len(contracts) == 2
    if diff:
        headers.append(f"{headers[1]} - {headers[0]}")
    table: list[list[str]] = [["", "", *headers]]
    for label, unit, spec in labels:
        cells = [_fmt(v, spec) for v in values[label]]
        if diff:
            a, b = values[label]
            is_num = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b))
            skip = ("iterations", "dofs", "solve time", "residual norm",
                    "min stiffness eigenvalue")  # model-specific diagnostics
            if is_num and spec and label not in skip:
                d = b - a
                if label.startswith("rotation ") and unit == "deg":
                    d = 180.0 - (180.0 - d) % 360.0  # angles: wrap to (-180, 180]
                cells.append(format(d, "+" + spec))
            else:
                cells.append("")
        table.append([label, f"[{unit}]" if unit else "", *cells])
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
    lines = [title] if title else []
    for row in table:
        left = f"{row[0]:<{widths[0]}}  {row[1]:<{widths[1]}}"
        right = "  ".join(f"{cell:>{w}}" for cell, w in zip(row[2:], widths[2:], strict=True))
        lines.append(f"  {left}  {right}".rstrip())
    return "\n".join(lines)


def _describe(source: str, scene: Any) -> str:
    names = ", ".join(t.name or f"tube{j + 1}" for j, t in enumerate(scene.tubes))
    return f"scene {source}: {scene.n_tubes} tube(s) ({names}, outermost first)"


# ---------------------------------------------------------------------------------------------
# Commands

def _cmd_solve(args: argparse.Namespace) -> int:
    prog = "torchpvs solve"
    scene = _load(args.scene, args.overrides)
    sol = _solve(scene, args.model, prog)
    contract = _contract(sol, args.backbone)
    if args.json:
        print(json.dumps(contract))
    else:
        print(format_table([contract], scene, title=_describe(args.scene, scene)))
    return 0 if contract.get("converged") is True else 1


def _cmd_plot(args: argparse.Namespace) -> int:
    prog = "torchpvs plot"
    from .plotting import save_backbone_plot

    scene = _load(args.scene, args.overrides)
    sol = _solve(scene, args.model, prog)
    contract = _contract(sol)
    points = _backbone(sol, args.points)
    # save_backbone_plot creates missing parent folders (documented in --help); say so, so
    # that a mistyped path does not go unnoticed.
    created = next((p for p in reversed(Path(args.output).absolute().parents)
                    if not p.exists()), None)
    try:
        path = save_backbone_plot(scene, points, args.output,
                                  title=f"{args.scene} ({args.model} model)")
    except (OSError, ValueError) as exc:
        raise CLIError(f"cannot save {args.output!r}: {_one_line(exc)}") from None
    tip = points[-1] * 1e3
    state = "converged" if contract.get("converged") is True else "NOT converged"
    made = f"; created folder {created}" if created is not None else ""
    print(f"saved {path} ({args.model} model, {state}, tip "
          f"[{tip[0]:.3f}, {tip[1]:.3f}, {tip[2]:.3f}] mm{made})")
    return 0 if contract.get("converged") is True else 1


def _cmd_demo(args: argparse.Namespace) -> int:
    prog = "torchpvs demo"
    from .plotting import save_backbone_plot

    scene = _load(DEMO_SCENE, ())
    print(f"torchpvs demo: Renda et al. 2021, Fig. 3: {_describe(DEMO_SCENE, scene)}")
    print(f"  insertion D = {[round(d * 1e3, 3) for d in scene.actuation.insertion]} mm, "
          f"rotation alpha = {[round(math.degrees(a), 3) for a in scene.actuation.rotation]} deg")
    results: dict[str, tuple[dict[str, Any], Any]] = {}
    for model in ("standard", "pvs"):
        try:
            sol = _solve(scene, model, prog)
        except CLIError as exc:
            print(f"  note: {exc}; skipped")
            continue
        results[model] = (_contract(sol), _backbone(sol, 200))
    if not results:
        raise CLIError("--model standard and --model pvs are not available yet")
    models = list(results)
    print()
    print(format_table([results[m][0] for m in models], scene, headers=models))
    print()
    if len(models) == 2:
        a = results["standard"][0].get("tip_position")
        b = results["pvs"][0].get("tip_position")
        if a is not None and b is not None and None not in a + b:
            d = [(y - x) * 1e3 for x, y in zip(a, b, strict=True)]
            print(f"tip difference pvs - standard: |dp| = {math.sqrt(sum(v * v for v in d)):.4f} "
                  f"mm  (dx {d[0]:+.4f}, dy {d[1]:+.4f}, dz {d[2]:+.4f} mm)")
    main_model = "pvs" if "pvs" in results else "standard"
    overlays = [(f"{m} model", results[m][1]) for m in models if m != main_model]
    path = Path(args.output_dir) / f"{DEMO_SCENE}.png"
    try:
        save_backbone_plot(scene, results[main_model][1], path, overlays=overlays,
                           title=f"{DEMO_SCENE}: {main_model} model"
                           + (" (dashed: " + ", ".join(m for m in models if m != main_model)
                              + ")" if overlays else ""))
    except (OSError, ValueError) as exc:
        raise CLIError(f"cannot save {str(path)!r}: {_one_line(exc)}") from None
    print(f"saved backbone plot: {path}")
    return 0 if all(results[m][0].get("converged") is True for m in models) else 1


def _cmd_scenes(args: argparse.Namespace) -> int:
    from .scene import builtin_scenes

    for name in builtin_scenes():
        print(name)
    return 0


def _read_measurements(path: str, n_tubes: int):
    """``(insertion (M, N), rotation (M, N), tip (M, 3), weights (M,) or None)`` from the
    calibration CSV; a missing column or a bad value names the column and the row."""
    import csv

    cols = ([f"insertion_{j}" for j in range(n_tubes)] + [f"rotation_{j}" for j in range(n_tubes)]
            + ["tip_x", "tip_y", "tip_z"])
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            header = [h.strip() for h in (reader.fieldnames or [])]
            missing = [c for c in cols if c not in header]
            if missing:
                raise CLIError(f"{path}: missing column(s) {missing} (header: {header}; the "
                               f"scene has {n_tubes} tubes)")
            rows = []
            for i, raw in enumerate(reader, start=2):
                row = {k.strip(): v for k, v in raw.items() if k is not None}
                try:
                    rows.append([float(row[c]) for c in cols]
                                + ([float(row["weight"])] if "weight" in header else []))
                except (TypeError, ValueError):
                    bad = next(c for c in cols + ["weight"] if c in row
                               and not _is_float(row[c]))
                    raise CLIError(f"{path}, line {i}: column {bad} is not a number: "
                                   f"{_short(str(row[bad]))}") from None
    except OSError as exc:
        raise CLIError(f"cannot read {path!r}: {_one_line(exc)}") from None
    if not rows:
        raise CLIError(f"{path}: no measurements (only a header)")
    import numpy as np
    a = np.array(rows)
    N = n_tubes
    return a[:, :N], a[:, N:2 * N], a[:, 2 * N:2 * N + 3], (a[:, -1] if "weight" in header
                                                            else None)


def _is_float(text) -> bool:
    try:
        float(text)
    except (TypeError, ValueError):
        return False
    return True


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import yaml

    from .calibration import calibrate

    scene = _load(args.scene, [])
    D, A, T, w = _read_measurements(args.measurements, scene.n_tubes)
    try:
        cal = calibrate(scene, D, A, T, params=args.params, weights=w,
                        huber_scale=args.huber_scale or None)
    except ValueError as exc:
        raise CLIError(_one_line(exc)) from None
    out = Path(args.output or Path(args.measurements).with_name(
        Path(args.measurements).stem + "_fitted.yaml"))
    header = (f"# fitted by `torchpvs calibrate {args.scene} {args.measurements}` to "
              f"{len(T)} measurements: inlier tip rms {cal.rms * 1e3:.4f} mm, "
              f"{'converged' if cal.converged else 'NOT converged'} ({cal.reason})\n"
              f"# actuator offsets (not part of a scene; D_true = D_cmd + offset): "
              f"insertion_offset {cal.insertion_offset.tolist()} m, rotation_offset "
              f"{cal.rotation_offset.tolist()} rad\n")
    try:
        out.write_text(header + yaml.safe_dump(cal.scene.to_dict(), sort_keys=False))
    except OSError as exc:
        raise CLIError(f"cannot write {str(out)!r}: {_one_line(exc)}") from None
    if args.json:
        print(json.dumps({
            "converged": bool(cal.converged), "reason": cal.reason,
            "iterations": cal.iterations, "rms_m": cal.rms,
            "parameters": {n: {"value": float(v), "std": float(sd)}
                           for n, v, sd in zip(cal.names, cal.value, cal.std, strict=True)},
            "unidentifiable": [list(g) for g in cal.identifiability.unidentifiable],
            "insertion_offset": cal.insertion_offset.tolist(),
            "rotation_offset": cal.rotation_offset.tolist(), "output": str(out)}))
    else:
        print(cal.report())
        print(f"wrote {out}")
    return 0 if cal.converged else 1


_COMMANDS = {"solve": _cmd_solve, "plot": _cmd_plot, "demo": _cmd_demo, "scenes": _cmd_scenes,
             "calibrate": _cmd_calibrate}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``torchpvs`` command line; returns the exit status (0, 1 or 2)."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return _COMMANDS[args.command](args)
    except CLIError as exc:
        print(f"torchpvs {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
