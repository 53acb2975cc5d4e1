"""Stage 1 — the scene: tubes, actuation and loads as frozen, validated dataclasses.

The format, frames and signs are fixed by ``docs/conventions.md``:

* SI units everywhere (m, Pa, N, N·m, rad).
* Base frame at the insertion orifice, z along the insertion axis, out of the orifice.
* Tubes are listed outermost first. Tube ``j``'s material point ``sigma`` (arc length from its
  base) sits at the orifice when ``sigma = D_j``; before it the tube lies in a straight, rigid,
  frictionless guide.
* Precurvature ``u*(t)`` in the tube's material frame, a polynomial in ``t`` [m], the arc length
  measured from the start of the curved part: ``u*_y(t) = y[0] + y[1] t + ...``.

Every rule raises :class:`SceneError` naming the field and the rule; nothing is fixed up.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

__all__ = [
    "Actuation",
    "Load",
    "Scene",
    "SceneError",
    "Tube",
    "builtin_scenes",
    "check_tube_numbers",
    "load_scene",
]


class SceneError(ValueError):
    """A scene, actuation or load breaks a rule. The message names the field and the rule."""


_HALF_DTYPES = ("float16", "bfloat16", "half")


def _finite(value: Any, where: str) -> float:
    """``value`` as a finite Python float, or a :class:`SceneError` naming ``where``.

    Numbers are Python ``int``/``float`` (not ``bool``) and numpy/torch real scalars of at
    least single precision. Refused, each with its rule: strings (no parsing), bools,
    half-precision scalars (``float16``/``bfloat16`` keep about 3 significant digits, so a
    modulus or a diameter would silently lose accuracy), complex values, integers beyond the
    float range (a 400-digit ``E`` is a typo, not a modulus) and NaN/inf.
    """
    dtype = getattr(value, "dtype", None)
    if dtype is not None and not isinstance(value, (int, float)):
        name = str(dtype).removeprefix("torch.")
        if name in _HALF_DTYPES:
            raise SceneError(f"{where} must be a number of at least single precision, got a "
                             f"{name} value (half precision keeps ~3 digits; pass a Python "
                             "float or float32/float64)")
        shape = tuple(getattr(value, "shape", ()))
        if shape != () or not hasattr(value, "item"):
            raise SceneError(f"{where} must be a number, got {type(value).__name__} of shape "
                             f"{shape}")
        if "complex" in name or not any(k in name for k in ("float", "int")) or "bool" in name:
            raise SceneError(f"{where} must be a real number, got a {name} value {value!r}")
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(f"{where} must be a number, got {_short_repr(value)}")
    try:
        value = float(value)
    except OverflowError:
        digits = (int(int(value).bit_length() * math.log10(2)) + 1
                  if isinstance(value, numbers.Integral) else None)
        size = f"an integer of about {digits} digits" if digits else _short_repr(value)
        raise SceneError(f"{where} must be a finite number within the float range "
                         f"(|x| < 1.8e308), got {size}") from None
    if not math.isfinite(value):
        raise SceneError(f"{where} must be finite, got {value!r}")
    return value


def _short_repr(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _vector(values: Any, n: int | None, where: str, per: str = "one per tube") -> tuple[float, ...]:
    """A list (or 1-D numpy array / torch tensor) of numbers, each checked by :func:`_finite`."""
    if getattr(values, "ndim", None) == 1 and hasattr(values, "tolist") \
            and not isinstance(values, Sequence):
        values = list(values)  # elements keep their dtype: _finite refuses half precision
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
        raise SceneError(f"{where} must be a list of numbers, got {_short_repr(values)}")
    if n is not None and len(values) != n:
        raise SceneError(f"{where} must have {n} entries ({per}), got {len(values)}")
    return tuple(_finite(v, f"{where}[{i}]") for i, v in enumerate(values))


def _check_keys(data: Mapping[str, Any], allowed: Sequence[str], where: str) -> None:
    if not isinstance(data, Mapping):
        raise SceneError(f"{where or 'scene'} must be a mapping, got {type(data).__name__}")
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        prefix = f"{where}." if where else ""
        raise SceneError(f"unknown key {prefix}{unknown[0]!s}; allowed keys: {', '.join(allowed)}")


@dataclass(frozen=True)
class Tube:
    """One nitinol-like tube (a Kirchhoff rod), outermost tubes first in a :class:`Scene`.

    Attributes:
        E, G: Young's and shear moduli [Pa], > 0.
        inner_diameter, outer_diameter: [m], ``0 <= inner < outer`` (0 = solid rod).
        straight_length: proximal straight part [m], >= 0.
        curved_length: distal precurved part [m], >= 0 (total length > 0).
        precurvature: ``(x, y, z)`` polynomial coefficients [1/m, 1/m², ...] in the arc length
            ``t`` measured from the start of the curved part, in the tube's material frame.
        name: label for plots and messages.
    """

    E: float
    G: float
    inner_diameter: float
    outer_diameter: float
    straight_length: float
    curved_length: float
    precurvature: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]] = ((), (), ())
    name: str = ""

    @property
    def length(self) -> float:
        """Total length ``L = straight_length + curved_length`` [m]."""
        return self.straight_length + self.curved_length

    @property
    def second_moment(self) -> float:
        """Area second moment ``I = pi (OD^4 - ID^4) / 64`` [m^4]."""
        return math.pi * (self.outer_diameter**4 - self.inner_diameter**4) / 64.0

    @property
    def bending_stiffness(self) -> float:
        """``EI`` [N·m²]."""
        return self.E * self.second_moment

    @property
    def torsional_stiffness(self) -> float:
        """``GJ`` [N·m²] with the polar moment ``J = 2 I``."""
        return self.G * 2.0 * self.second_moment

    def precurvature_at(self, t: float) -> tuple[float, float, float]:
        """``u*(t)`` [1/m] at arc length ``t`` [m] from the start of the curved part."""
        return tuple(sum(c * t**k for k, c in enumerate(axis)) for axis in self.precurvature)

    @property
    def is_precurved(self) -> bool:
        return self.curved_length > 0 and any(c != 0.0 for axis in self.precurvature
                                              for c in axis)


@dataclass(frozen=True)
class Actuation:
    """Actuator coordinates: insertions ``D_j`` [m] (base-to-orifice distance, larger = more
    retracted) and base rotations ``alpha_j`` [rad], one entry per tube."""

    insertion: tuple[float, ...]
    rotation: tuple[float, ...]


@dataclass(frozen=True)
class Load:
    """External tip load, base frame, applied at the robot's distal tip."""

    tip_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_moment: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def is_zero(self) -> bool:
        return not any(self.tip_force) and not any(self.tip_moment)


_TUBE_KEYS = ("name", "E", "G", "inner_diameter", "outer_diameter", "straight_length",
              "curved_length", "precurvature")
_SCENE_KEYS = ("tubes", "actuation", "load")
_ACT_KEYS = ("insertion", "rotation")
_LOAD_KEYS = ("tip_force", "tip_moment")


@dataclass(frozen=True)
class Scene:
    """A concentric tube robot: tubes (outermost first), actuation and tip load.

    Construct it from a mapping with :meth:`from_dict`, from a file or built-in name with
    :func:`load_scene`, or directly; ``__post_init__`` validates every rule of docs/conventions.md.
    """

    tubes: tuple[Tube, ...]
    actuation: Actuation
    load: Load = field(default_factory=Load)

    def __post_init__(self) -> None:
        _validate(self)

    # -- convenience -------------------------------------------------------------------------
    @property
    def n_tubes(self) -> int:
        return len(self.tubes)

    def with_actuation(self, insertion: Sequence[float] | None = None,
                       rotation: Sequence[float] | None = None) -> Scene:
        """A copy with new insertions and/or rotations (validated: numbers only, no strings,
        no half precision; numpy arrays and torch tensors of one dimension are accepted)."""
        n = self.n_tubes
        act = Actuation(
            _vector(insertion, n, "actuation.insertion") if insertion is not None
            else self.actuation.insertion,
            _vector(rotation, n, "actuation.rotation") if rotation is not None
            else self.actuation.rotation,
        )
        return dataclasses.replace(self, actuation=act)

    def with_load(self, tip_force: Sequence[float] | None = None,
                  tip_moment: Sequence[float] | None = None) -> Scene:
        """A copy with a new tip force and/or moment (validated)."""
        load = Load(
            _vector(tip_force, 3, "load.tip_force", "x, y, z") if tip_force is not None
            else self.load.tip_force,
            _vector(tip_moment, 3, "load.tip_moment", "x, y, z") if tip_moment is not None
            else self.load.tip_moment,
        )
        return dataclasses.replace(self, load=load)

    def exposed_lengths(self) -> tuple[float, ...]:
        """Length of each tube beyond the orifice, ``max(0, L_j - D_j)`` [m]."""
        pairs = zip(self.tubes, self.actuation.insertion, strict=True)
        return tuple(max(0.0, t.length - d) for t, d in pairs)

    # -- (de)serialisation -------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Scene:
        """Build and validate a scene from the mapping of docs/conventions.md.

        The optional sections ``load`` and ``tubes[i].precurvature`` mean "none" (zero load,
        a straight tube) only when absent or ``null`` (an empty ``load:`` in YAML) or an empty
        mapping ``{}``. Any other non-mapping value, ``0`` included, is a :class:`SceneError`:
        ``precurvature: 0`` might mean a straight tube or a forgotten list, and ``load: 0``
        a zero load or a missing vector, so neither is guessed.
        """
        _check_keys(data, _SCENE_KEYS, "")
        if "tubes" not in data:
            raise SceneError("tubes is required: a list of at least one tube, outermost first")
        tubes_raw = data["tubes"]
        if isinstance(tubes_raw, (str, bytes)) or not isinstance(tubes_raw, Sequence) \
                or len(tubes_raw) == 0:
            raise SceneError("tubes must be a non-empty list of tubes, outermost first")
        tubes = tuple(_tube_from_dict(t, i) for i, t in enumerate(tubes_raw))
        n = len(tubes)
        if "actuation" not in data:
            raise SceneError("actuation is required: insertion and rotation, one entry per tube")
        act_raw = data["actuation"]
        _check_keys(act_raw, _ACT_KEYS, "actuation")
        for key in _ACT_KEYS:
            if key not in act_raw:
                raise SceneError(f"actuation.{key} is required (one entry per tube)")
        actuation = Actuation(
            _vector(act_raw["insertion"], n, "actuation.insertion"),
            _vector(act_raw["rotation"], n, "actuation.rotation"),
        )
        load_raw = _optional_mapping(data, "load", "load",
                                     "tip_force and/or tip_moment, 3 entries each")
        _check_keys(load_raw, _LOAD_KEYS, "load")
        load = Load(
            _vector(load_raw.get("tip_force", (0.0, 0.0, 0.0)), 3, "load.tip_force", "x, y, z"),
            _vector(load_raw.get("tip_moment", (0.0, 0.0, 0.0)), 3, "load.tip_moment", "x, y, z"),
        )
        return cls(tubes, actuation, load)

    def to_dict(self) -> dict[str, Any]:
        """The mapping of docs/conventions.md (round-trips through :meth:`from_dict`)."""
        tubes = []
        for t in self.tubes:
            tubes.append({
                "name": t.name, "E": t.E, "G": t.G, "inner_diameter": t.inner_diameter,
                "outer_diameter": t.outer_diameter, "straight_length": t.straight_length,
                "curved_length": t.curved_length,
                "precurvature": {ax: list(c) for ax, c in zip("xyz", t.precurvature, strict=True)},
            })
        return {
            "tubes": tubes,
            "actuation": {"insertion": list(self.actuation.insertion),
                          "rotation": list(self.actuation.rotation)},
            "load": {"tip_force": list(self.load.tip_force),
                     "tip_moment": list(self.load.tip_moment)},
        }


def _optional_mapping(data: Mapping[str, Any], key: str, where: str, keys: str) -> Any:
    """An optional section: absent or ``null`` means empty (no load, no precurvature); any
    other value must be a mapping. ``0``, ``[]``, ``""`` or ``false`` are refused rather than
    read as absent: a ``0`` could as well be meant as a zero coefficient, so it is not guessed."""
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise SceneError(f"{where} must be a mapping ({keys}) or absent/null, got "
                         f"{_short_repr(value)}; omit it (or write {{}}) for none")
    return value


def _tube_from_dict(raw: Any, i: int) -> Tube:
    where = f"tubes[{i}]"
    _check_keys(raw, _TUBE_KEYS, where)
    for key in ("E", "G", "inner_diameter", "outer_diameter", "straight_length", "curved_length"):
        if key not in raw:
            raise SceneError(f"{where}.{key} is required")
    pc_raw = _optional_mapping(raw, "precurvature", f"{where}.precurvature",
                               "x, y and/or z, each a list of coefficients")
    _check_keys(pc_raw, ("x", "y", "z"), f"{where}.precurvature")
    precurvature = tuple(_vector(pc_raw.get(ax, ()), None, f"{where}.precurvature.{ax}")
                         for ax in "xyz")
    name = raw.get("name", f"tube{i + 1}")
    if not isinstance(name, str):
        raise SceneError(f"{where}.name must be a string, got {name!r}")
    return Tube(
        E=_finite(raw["E"], f"{where}.E"),
        G=_finite(raw["G"], f"{where}.G"),
        inner_diameter=_finite(raw["inner_diameter"], f"{where}.inner_diameter"),
        outer_diameter=_finite(raw["outer_diameter"], f"{where}.outer_diameter"),
        straight_length=_finite(raw["straight_length"], f"{where}.straight_length"),
        curved_length=_finite(raw["curved_length"], f"{where}.curved_length"),
        precurvature=precurvature,  # type: ignore[arg-type]
        name=name,
    )


_TUBE_NUMBERS = ("E", "G", "inner_diameter", "outer_diameter", "straight_length",
                 "curved_length")


def check_tube_numbers(i: int, E: float, G: float, inner_diameter: float, outer_diameter: float,
                       straight_length: float, curved_length: float, *,
                       outer_inner_diameter: float | None = None,
                       precurvature: Sequence[float] = ()) -> None:
    """The rules of docs/conventions.md on the numbers of tube ``i`` (Python floats, SI units:
    ``E``, ``G`` [Pa], diameters and lengths [m]; ``outer_inner_diameter`` [m] the inner
    diameter of tube ``i - 1``, the next outer one, ``None`` for the outermost;
    ``precurvature`` its coefficients [1/m, 1/m², ...] in any order). Raises a
    :class:`SceneError` naming the tube, the field and the rule.

    The one validator of tube properties: :class:`Scene` applies it to its tubes (after
    converting their numbers), :class:`torchpvs.CTR` to its tensors at every forward (which
    users may edit in place)."""
    w = f"tubes[{i}]"
    for key, value in zip(_TUBE_NUMBERS, (E, G, inner_diameter, outer_diameter,
                                          straight_length, curved_length), strict=True):
        if not math.isfinite(value):
            raise SceneError(f"{w}.{key} must be finite, got {value!r}")
    if not all(math.isfinite(c) for c in precurvature):
        raise SceneError(f"{w}.precurvature must be finite, got {list(precurvature)!r}")
    if E <= 0:
        raise SceneError(f"{w}.E ({E:g} Pa) must be > 0")
    if G <= 0:
        raise SceneError(f"{w}.G ({G:g} Pa) must be > 0")
    if inner_diameter < 0:
        raise SceneError(f"{w}.inner_diameter ({inner_diameter:g} m) must be >= 0")
    if outer_diameter <= inner_diameter:
        raise SceneError(f"{w}.outer_diameter ({outer_diameter:g} m) must exceed "
                         f"inner_diameter ({w}.inner_diameter = {inner_diameter:g} m)")
    if straight_length < 0:
        raise SceneError(f"{w}.straight_length ({straight_length:g} m) must be >= 0")
    if curved_length < 0:
        raise SceneError(f"{w}.curved_length ({curved_length:g} m) must be >= 0")
    if straight_length + curved_length <= 0:
        raise SceneError(f"{w}: straight_length + curved_length must be > 0")
    if outer_inner_diameter is not None and outer_diameter > outer_inner_diameter:
        raise SceneError(
            f"{w}.outer_diameter ({outer_diameter:g} m) must not exceed "
            f"tubes[{i - 1}].inner_diameter ({outer_inner_diameter:g} m): each tube fits "
            f"inside the next outer tube")


def _validate(scene: Scene) -> None:
    """Check every rule; store the numbers as Python floats (a lossless conversion of ints and
    numpy/torch scalars of single or double precision; anything else raises)."""
    if not isinstance(scene.tubes, tuple) or len(scene.tubes) == 0:
        raise SceneError("tubes must be a non-empty tuple of Tube, outermost first")
    n = len(scene.tubes)
    tubes: list[Tube] = []
    for i, t in enumerate(scene.tubes):
        w = f"tubes[{i}]"
        if not isinstance(t, Tube):
            raise SceneError(f"{w} must be a Tube, got {type(t).__name__}")
        nums = {key: _finite(getattr(t, key), f"{w}.{key}") for key in _TUBE_NUMBERS}
        pc = t.precurvature
        if isinstance(pc, (str, bytes)) or not isinstance(pc, Sequence) or len(pc) != 3:
            raise SceneError(f"{w}.precurvature must have the axes x, y, z")
        pc = tuple(_vector(c, None, f"{w}.precurvature.{ax}") for ax, c in zip("xyz", pc,
                                                                               strict=True))
        if not isinstance(t.name, str):
            raise SceneError(f"{w}.name must be a string, got {_short_repr(t.name)}")
        t = dataclasses.replace(t, **nums, precurvature=pc)  # type: ignore[arg-type]
        tubes.append(t)
        check_tube_numbers(i, *(nums[key] for key in _TUBE_NUMBERS),
                           outer_inner_diameter=tubes[i - 1].inner_diameter if i else None,
                           precurvature=[c for axis in pc for c in axis])
    object.__setattr__(scene, "tubes", tuple(tubes))
    act = scene.actuation
    if not isinstance(act, Actuation):
        raise SceneError("actuation must be an Actuation")
    act = Actuation(*(_vector(getattr(act, key), n, f"actuation.{key}")
                      for key in ("insertion", "rotation")))
    for j, d in enumerate(act.insertion):
        if d < 0:
            raise SceneError(f"actuation.insertion[{j}] ({d:g} m) must be >= 0 "
                             "(D_j is the distance from the tube's base to the orifice)")
        if j > 0 and d < act.insertion[j - 1]:
            raise SceneError(
                f"actuation.insertion[{j}] ({d:g} m) must be >= actuation.insertion[{j - 1}] "
                f"({act.insertion[j - 1]:g} m): an inner tube's base lies behind the outer one's")
    object.__setattr__(scene, "actuation", act)
    load = scene.load
    if not isinstance(load, Load):
        raise SceneError("load must be a Load")
    load = Load(*(_vector(getattr(load, key), 3, f"load.{key}", "x, y, z")
                  for key in ("tip_force", "tip_moment")))
    object.__setattr__(scene, "load", load)


# ---------------------------------------------------------------------------------------------
# Loading

def builtin_scenes() -> list[str]:
    """Names of the scenes shipped with torchpvs (``torchpvs/scenes/*.yaml``)."""
    root = resources.files("torchpvs") / "scenes"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".yaml"))


class _Loader(yaml.SafeLoader):
    """SafeLoader that reads ``58.0e9`` and ``1e-3`` as floats (YAML 1.2), not strings."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


def _first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def _yaml_load(text: str) -> Any:
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass


def _parse_text(text: str, source: str) -> Any:
    try:
        if source.endswith(".json"):
            return json.loads(text)
        return _yaml_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        raise SceneError(f"{source}: not valid YAML/JSON: {exc}") from None
    except ValueError as exc:  # e.g. an integer beyond Python's digit limit for int()
        raise SceneError(f"{source}: cannot read a value: {_first_line(exc)}") from None


def apply_overrides(data: dict[str, Any], overrides: Sequence[str]) -> dict[str, Any]:
    """Apply ``KEY=VALUE`` overrides (``actuation.rotation[1]=3.14``, ``tubes[0].E=6e10``,
    ``load.tip_force=[0,0.1,0]``) to a scene mapping. Values are parsed as YAML."""
    import copy

    data = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise SceneError(f"--set {item!r}: expected KEY=VALUE")
        key, raw = item.split("=", 1)
        try:
            value = _yaml_load(raw)
        except (yaml.YAMLError, ValueError) as exc:
            raise SceneError(f"--set {_short_repr(item)}: value is not valid YAML "
                             f"({_first_line(exc)})") from None
        parts: list[str | int] = []
        for token in key.strip().split("."):
            m = re.fullmatch(r"([A-Za-z_][A-Za-z_0-9]*)((\[\d+\])*)", token)
            if not m:
                raise SceneError(f"--set {item!r}: cannot parse key {key!r}")
            parts.append(m.group(1))
            parts.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
        node: Any = data
        for k, p in enumerate(parts[:-1]):
            try:
                if isinstance(p, str) and isinstance(node, dict) and node.get(p) is None:
                    nxt = parts[k + 1]
                    if isinstance(nxt, int):
                        # an absent (or null) list: the documented default is "none" (a zero
                        # load, no coefficients), which has no element [nxt] to set
                        field_name = _field_name(parts[:k + 1])
                        raise SceneError(
                            f"--set {_short_repr(item)}: {field_name} is not in the scene, so "
                            f"its element [{nxt}] cannot be set; set the whole list, e.g. "
                            f"--set {field_name}=[...]")
                    node[p] = {}
                node = node[p]
            except (KeyError, IndexError, TypeError):
                raise SceneError(f"--set {_short_repr(item)}: no such field {key!r}") from None
        last = parts[-1]
        try:
            if isinstance(node, list):
                node[last] = value  # type: ignore[index]
            elif isinstance(node, dict) and isinstance(last, str):
                node[last] = value
            else:
                raise TypeError
        except (IndexError, TypeError):
            size = f" (it has {len(node)} entries)" if isinstance(node, list) else ""
            raise SceneError(f"--set {_short_repr(item)}: no such field {key!r}{size}") \
                from None
    return data


def _field_name(parts: Sequence[str | int]) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
    return out


def _read_file(path: Path, shown: str) -> Any:
    """Parse a scene file; every failure is a SceneError that names the file."""
    try:
        raw = path.read_bytes()
    except IsADirectoryError:
        raise SceneError(f"scene file {shown!r} is a directory, not a YAML/JSON file") from None
    except OSError as exc:
        raise SceneError(f"scene file {shown!r} cannot be read: "
                         f"{exc.strerror or _first_line(exc)}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SceneError(f"scene file {shown!r} is not a UTF-8 text file (byte "
                         f"0x{raw[exc.start]:02x} at offset {exc.start}); a scene is YAML or "
                         "JSON text") from None
    if "\x00" in text:
        raise SceneError(f"scene file {shown!r} contains NUL bytes: it is a binary file, not "
                         "YAML or JSON text")
    data = _parse_text(text, shown)
    if not isinstance(data, Mapping):
        raise SceneError(f"scene file {shown!r}: the scene must be a mapping with tubes, "
                         f"actuation and load, got {type(data).__name__}")
    return data


def load_scene(source: str | Path | Mapping[str, Any] | Scene,
               overrides: Sequence[str] = ()) -> Scene:
    """Load a scene from a YAML/JSON path, a built-in name, a mapping, or pass a Scene through.

    Args:
        source: file path (``.yaml``, ``.yml``, ``.json``), a built-in name (see
            :func:`builtin_scenes`), a mapping in the format of docs/conventions.md, or a Scene.
        overrides: ``KEY=VALUE`` strings applied before validation (see :func:`apply_overrides`).
    """
    if isinstance(source, Scene):
        if not overrides:
            return source
        data: Any = source.to_dict()
    elif isinstance(source, Mapping):
        data = dict(source)
    else:
        if not isinstance(source, (str, Path)):
            raise SceneError(f"scene must be a file path, a built-in name, a mapping or a "
                             f"Scene, got {type(source).__name__}")
        text_source = str(source)
        if not text_source.strip():
            raise SceneError(f"scene name is empty: give a scene file (.yaml, .yml, .json) or "
                             f"a built-in name ({', '.join(builtin_scenes())})")
        path = Path(text_source)
        if path.suffix in (".yaml", ".yml", ".json") or path.exists():
            if not path.exists():
                raise SceneError(f"scene file {text_source!r} does not exist")
            data = _read_file(path, text_source)
        else:
            names = builtin_scenes()
            if text_source not in names:
                raise SceneError(f"unknown scene {text_source!r}: not a file and not a built-in "
                                 f"scene (built-in: {', '.join(names)})")
            res = resources.files("torchpvs") / "scenes" / f"{text_source}.yaml"
            data = _parse_text(res.read_text(), f"{text_source}.yaml")
    if overrides:
        data = apply_overrides(data, overrides)
    return Scene.from_dict(data)
