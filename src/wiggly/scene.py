"""Scene files: one shot (body, material, sparse keyframes, outputs) as TOML.

The format is specified in ``docs/scene-format.md``.  This module reads it (:func:`load_scene`),
checks it completely before anything is computed, writes it back (:func:`save_scene`, exact
round trip) and runs it (:func:`build`, :func:`run`):

    scene file -> Scene -> mesh, groups -> Body + Keyframes -> solve -> export / render

One table of specs (``_SCENE``) drives both the validator and the JSON Schema
(:func:`scene_schema`, shipped as ``wiggly/data/scene.schema.json``), so the two agree on every
structural rule.  Checks that need more than one key (a keyframe's group exists, its time lies
in the shot) follow; checks that need the mesh (a group selects vertices, absolute targets have
one row per vertex) run right after the mesh is read and before it is tetrahedralized.
"""

from __future__ import annotations

import difflib
import json
import math
import os
import re
import sys
import time as _time
import tomllib
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from wiggly.errors import WigglyInputError, counted
from wiggly.files import atomic_file
from wiggly.limits import MAX_DURATION, MAX_FPS, MAX_FRAMES, MAX_MODES, MAX_RESOLUTION
from wiggly.mesh import BUILTIN_MODELS, DEFAULT_RESOLUTION, resolve_builtin

__all__ = [
    "FORMAT",
    "Absolute",
    "Box",
    "DampingSpec",
    "FromMesh",
    "GroupSpec",
    "Indices",
    "KeyframeSpec",
    "MaterialSpec",
    "MeshSpec",
    "Nearest",
    "Offset",
    "OutputSpec",
    "Rest",
    "Rigid",
    "Scene",
    "SimulationSpec",
    "Sphere",
    "TimeSpec",
    "build",
    "load_scene",
    "resolve_groups",
    "run",
    "save_scene",
    "scene_schema",
]

#: Scene format version written by :func:`save_scene` and the newest one read.
FORMAT = 1
GEOMETRY_EXTENSIONS = (".glb", ".usd", ".usda", ".usdc", ".obj", ".npz")
PREVIEW_EXTENSIONS = (".mp4", ".gif", ".png")
OUTPUT_EXTENSIONS = GEOMETRY_EXTENSIONS + PREVIEW_EXTENSIONS
CAMERAS = ("three_quarter", "front", "side", "back", "top")
GLTF_TARGETS = ("frames", "modes")
#: Highlight colors of keyframed groups without a ``color`` (matplotlib's tab10).
PALETTE = ("#ff7f0e", "#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
           "#17becf", "#bcbd22", "#7f7f7f")
GROUP_NAME = r"^[A-Za-z0-9_-]+$"
#: Rigid modes of a free body (3 translations, 3 rotations, SYSTEM.md §3).
RIGID_MODES = 6
#: Target positions drawn per keyframe in previews (a subset of large groups).
MAX_TARGETS = 60

Vec3 = tuple[float, float, float]


# ----------------------------------------------------------------------------------------------
# the scene as dataclasses (field names are the TOML keys)


def _floats(v, n: int | None = None) -> tuple:
    """A tuple of floats (vectors are tuples so that scenes compare with ==)."""
    out = tuple(float(x) for x in v)
    if n is not None and len(out) != n:
        raise WigglyInputError(f"expected {n} numbers, got {len(out)}: {list(v)!r}")
    return out


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)


@dataclass(frozen=True)
class MeshSpec:
    """``[mesh]``: the model file and how to tetrahedralize it."""

    path: str
    resolution: int | None = None
    edge_length: float | None = None
    repair: bool | None = None  # None: true (accept imperfect surfaces, with a warning)


@dataclass(frozen=True)
class MaterialSpec:
    """``[material]``: Young's modulus (Pa), Poisson ratio, density (kg/m^3)."""

    young: float = 2e5
    poisson: float = 0.45
    density: float = 1000.0


@dataclass(frozen=True)
class DampingSpec:
    """``[damping]``: Rayleigh damping D = alpha M + beta K."""

    alpha: float = 0.5
    beta: float = 0.002


@dataclass(frozen=True)
class SimulationSpec:
    """``[simulation]``: gravity, number of modes, warping, fixed groups, pre-roll."""

    gravity: Vec3 = (0.0, -9.81, 0.0)
    modes: int = 40
    warp: bool = True
    lumped_mass: bool = False
    fixed: tuple[str, ...] = ()
    preroll: float | None = None

    def __post_init__(self) -> None:
        _set(self, "gravity", _floats(self.gravity, 3))
        _set(self, "fixed", tuple(self.fixed))


@dataclass(frozen=True)
class TimeSpec:
    """``[time]``: the shot's range (``end`` or ``duration``) and the output frame rate."""

    start: float = 0.0
    end: float | None = None
    duration: float | None = None
    fps: float = 30.0


@dataclass(frozen=True)
class Box:
    """Vertices with ``min <= x <= max`` (component-wise, inclusive)."""

    min: Vec3
    max: Vec3

    def __post_init__(self) -> None:
        _set(self, "min", _floats(self.min, 3))
        _set(self, "max", _floats(self.max, 3))


@dataclass(frozen=True)
class Sphere:
    """Vertices with ``|x - center| <= radius``."""

    center: Vec3
    radius: float

    def __post_init__(self) -> None:
        _set(self, "center", _floats(self.center, 3))


@dataclass(frozen=True)
class Nearest:
    """The ``count`` vertices nearest to each of ``points`` (their union)."""

    points: tuple[Vec3, ...]
    count: int = 1

    def __post_init__(self) -> None:
        _set(self, "points", tuple(_floats(p, 3) for p in self.points))


@dataclass(frozen=True)
class Indices:
    """Explicit vertex indices, in this order (absolute targets follow it)."""

    indices: tuple[int, ...]

    def __post_init__(self) -> None:
        _set(self, "indices", tuple(int(i) for i in self.indices))


@dataclass(frozen=True)
class FromMesh:
    """A named vertex group stored in the mesh file."""

    name: str


Selector = Box | Sphere | Nearest | Indices | FromMesh
_SELECTOR_KEYS = {Box: "box", Sphere: "sphere", Nearest: "nearest", Indices: "indices",
                  FromMesh: "from_mesh"}


@dataclass(frozen=True)
class GroupSpec:
    """``[groups.<name>]``: one selector; ``on`` = "surface" (default) or "tets"."""

    selector: Selector
    on: str = "surface"
    color: str | None = None


@dataclass(frozen=True)
class Rest:
    """``position = "rest"``."""


@dataclass(frozen=True)
class Offset:
    """``position = { offset = [dx, dy, dz] }``: rest + offset."""

    offset: Vec3

    def __post_init__(self) -> None:
        _set(self, "offset", _floats(self.offset, 3))


@dataclass(frozen=True)
class Absolute:
    """``position = { absolute = [[x, y, z], ...] }``: one row per group vertex."""

    positions: tuple[Vec3, ...]

    def __post_init__(self) -> None:
        _set(self, "positions", tuple(_floats(p, 3) for p in self.positions))


@dataclass(frozen=True)
class Rigid:
    """Rest vertices rotated (Euler XYZ, degrees) about ``center`` (default: centroid), then
    translated."""

    rotation: Vec3 = (0.0, 0.0, 0.0)
    translation: Vec3 = (0.0, 0.0, 0.0)
    center: Vec3 | None = None

    def __post_init__(self) -> None:
        _set(self, "rotation", _floats(self.rotation, 3))
        _set(self, "translation", _floats(self.translation, 3))
        if self.center is not None:
            _set(self, "center", _floats(self.center, 3))

    def matrix(self) -> np.ndarray:
        """The rotation matrix: X, then Y, then Z about the fixed axes (degrees)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_euler("xyz", self.rotation, degrees=True).as_matrix()


Position = Rest | Offset | Absolute | Rigid


@dataclass(frozen=True)
class KeyframeSpec:
    """One ``[[keyframes]]`` entry."""

    time: float
    group: str
    position: Position | None = None
    velocity: Vec3 | None = None
    stiffness: float | None = None
    c_A: float | None = None
    c_B: float | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.velocity is not None:
            _set(self, "velocity", _floats(self.velocity, 3))

    @property
    def label(self) -> str:
        return self.name or self.group


@dataclass(frozen=True)
class OutputSpec:
    """``[output]``: files to write (by extension), overwrite, preview size and camera, and
    how glTF/USD files carry time (``frame_start``, ``gltf_targets``; None: the defaults)."""

    paths: tuple[str, ...] = ()
    overwrite: bool = False
    size: tuple[int, int] = (960, 540)
    camera: str | tuple[float, float] = "three_quarter"
    frame_start: int | None = None
    gltf_targets: str | None = None

    def __post_init__(self) -> None:
        _set(self, "paths", tuple(self.paths))
        _set(self, "size", tuple(int(s) for s in self.size))
        if not isinstance(self.camera, str):
            _set(self, "camera", _floats(self.camera, 2))


@dataclass
class Scene:
    """A whole scene file.  ``source`` (the file it was read from; relative paths resolve
    against its directory) does not take part in comparisons."""

    mesh: MeshSpec
    material: MaterialSpec = field(default_factory=MaterialSpec)
    damping: DampingSpec = field(default_factory=DampingSpec)
    simulation: SimulationSpec = field(default_factory=SimulationSpec)
    time: TimeSpec = field(default_factory=TimeSpec)
    groups: dict[str, GroupSpec] = field(default_factory=dict)
    keyframes: list[KeyframeSpec] = field(default_factory=list)
    output: OutputSpec = field(default_factory=OutputSpec)
    format: int = FORMAT
    source: Path | None = field(default=None, compare=False)

    @property
    def base_dir(self) -> Path:
        """Directory that relative paths are relative to (the scene file's, else the cwd)."""
        return self.source.parent if self.source is not None else Path.cwd()

    @property
    def name(self) -> str:
        """The scene file's stem (else the mesh's)."""
        if self.source is not None:
            return self.source.stem
        return Path(self.mesh.path.removeprefix("builtin:")).stem

    def where(self) -> str:
        """How messages name this scene: its file (relative to the cwd if inside), or "scene"."""
        if self.source is None:
            return "scene"
        try:
            return str(self.source.relative_to(Path.cwd()))
        except ValueError:
            return str(self.source)

    def mesh_file(self) -> Path:
        """The mesh file (``builtin:<name>`` resolved to the bundled model)."""
        p = self.mesh.path
        if p.startswith("builtin:"):
            return builtin_model(p.removeprefix("builtin:"))
        return self.resolve(p)

    def resolve(self, path: str | os.PathLike[str]) -> Path:
        """``path`` relative to the scene file's directory (``~`` expanded)."""
        p = Path(path).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    def time_range(self) -> tuple[float, float]:
        """(start, end) in seconds: ``end``, ``start + duration``, or the last keyframe time
        (at least ``start + 1``)."""
        t = self.time
        if t.end is not None:
            return t.start, t.end
        if t.duration is not None:
            return t.start, t.start + t.duration
        last = max((k.time for k in self.keyframes), default=t.start)
        return t.start, max(last, t.start + 1.0)


def builtin_model(name: str) -> Path:
    """Path of a bundled model (``critter``, ``plant``, ``bar``)."""
    return resolve_builtin(f"builtin:{name}")


# ----------------------------------------------------------------------------------------------
# specs: one description drives the validator and the JSON Schema


class _Bad(Exception):
    """Raised inside the validator: one problem, already recorded."""


class _Problems:
    """Collects the problems of one file; messages are prefixed with the file name."""

    def __init__(self, where: str):
        self.where = where
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def bad(self, message: str) -> _Bad:
        self.add(message)
        return _Bad(message)

    def raise_if_any(self) -> None:
        if self.items:
            raise _error(self.where, self.items)


def _error(where: str, messages: list[str]) -> WigglyInputError:
    err = WigglyInputError("\n".join(f"{where}: {m}" for m in messages))
    err.problems = list(messages)
    return err


def _show(value: Any, limit: int = 60) -> str:
    """A value as it would be written in TOML (shortened)."""
    if isinstance(value, bool):
        s = "true" if value else "false"
    elif isinstance(value, str):
        s = json.dumps(value, ensure_ascii=False)
    elif isinstance(value, float):
        s = "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") \
            if math.isinf(value) else repr(value)
    elif isinstance(value, list | tuple):
        s = "[" + ", ".join(_show(v, limit) for v in value) + "]"
    elif isinstance(value, dict):
        s = ("{ " + ", ".join(f"{k} = {_show(v, limit)}" for k, v in value.items()) + " }"
             if value else "{}")
    else:
        s = str(value)
    return s if len(s) <= limit else s[: limit - 4] + " ..."


def _num(x: float) -> str:
    return repr(int(x)) if float(x).is_integer() and abs(x) < 1e15 else repr(float(x))


class _Spec(ABC):
    what = "a value"

    @abstractmethod
    def parse(self, value: Any, path: str, p: _Problems) -> Any:
        """Validate ``value`` at key ``path``; record problems in ``p``."""

    @abstractmethod
    def schema(self) -> dict:
        """The JSON Schema of this spec."""

    def fail(self, value, path: str, p: _Problems) -> _Bad:
        return p.bad(f"{path} = {_show(value)} must be {self.what}")


class _Number(_Spec):
    def __init__(self, *, integer: bool = False, ge: float | None = None, gt: float | None = None,
                 le: float | None = None, lt: float | None = None, unit: str = "",
                 doc: str = "", what: str | None = None):
        self.integer, self.ge, self.gt, self.le, self.lt = integer, ge, gt, le, lt
        self.unit, self.doc = unit, doc
        noun = "an integer" if integer else "a number"
        lo = (f"[{_num(ge)}" if ge is not None else f"({_num(gt)}" if gt is not None else None)
        hi = (f"{_num(le)}]" if le is not None else f"{_num(lt)})" if lt is not None else None)
        if lo and hi:
            rng = f" in {lo}, {hi}"
        elif lo:
            rng = f" {'>=' if ge is not None else '>'} {lo[1:]}"
        elif hi:
            rng = f" {'<=' if le is not None else '<'} {hi[:-1]}"
        else:
            rng = ""
        self.what = what or noun + rng + (f" ({unit})" if unit else "")

    def parse(self, value, path, p):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        if ok and isinstance(value, float):
            ok = math.isfinite(value) and (not self.integer or value.is_integer())
        if ok:
            v = int(value) if self.integer else float(value)
            ok = ((self.ge is None or v >= self.ge) and (self.gt is None or v > self.gt)
                  and (self.le is None or v <= self.le) and (self.lt is None or v < self.lt))
        if not ok:
            raise self.fail(value, path, p)
        return v

    def schema(self):
        s: dict = {"type": "integer" if self.integer else "number"}
        for key, v in (("minimum", self.ge), ("exclusiveMinimum", self.gt),
                       ("maximum", self.le), ("exclusiveMaximum", self.lt)):
            if v is not None:
                s[key] = v
        return _described(s, self.doc)


class _Bool(_Spec):
    what = "true or false"

    def __init__(self, doc: str = ""):
        self.doc = doc

    def parse(self, value, path, p):
        if not isinstance(value, bool):
            raise self.fail(value, path, p)
        return value

    def schema(self):
        return _described({"type": "boolean"}, self.doc)


class _String(_Spec):
    def __init__(self, *, enum: tuple[str, ...] | None = None, pattern: str | None = None,
                 min_length: int = 1, what: str = "a non-empty string", doc: str = ""):
        self.enum, self.pattern, self.min_length, self.doc = enum, pattern, min_length, doc
        self.what = (" or ".join(json.dumps(e) for e in enum) if enum else what)

    def parse(self, value, path, p):
        ok = isinstance(value, str) and (
            value in self.enum if self.enum else
            bool(re.search(self.pattern, value)) if self.pattern else
            len(value) >= self.min_length)
        if not ok:
            raise self.fail(value, path, p)
        return value

    def schema(self):
        s: dict = {"type": "string"}
        if self.enum:
            s["enum"] = list(self.enum)
        elif self.pattern:
            s["pattern"] = self.pattern
        elif self.min_length:
            s["minLength"] = self.min_length
        return _described(s, self.doc)


class _Vector(_Spec):
    """A fixed-length array of finite numbers -> tuple of floats (or of ints)."""

    def __init__(self, n: int = 3, names: str = "x, y, z", unit: str = "", doc: str = "",
                 item: _Number | None = None, what: str | None = None):
        self.n, self.doc = n, doc
        self.item = item or _Number()
        self.what = what or (f"an array of {n} numbers [{names}]" + (f" ({unit})" if unit else ""))

    def parse(self, value, path, p):
        if not (isinstance(value, list) and len(value) == self.n):
            raise self.fail(value, path, p)
        try:
            return tuple(self.item.parse(x, path, _Problems("")) for x in value)
        except _Bad:
            raise self.fail(value, path, p) from None

    def schema(self):
        return _described({"type": "array", "items": self.item.schema(), "minItems": self.n,
                           "maxItems": self.n}, self.doc)


class _Array(_Spec):
    """An array of items -> tuple (or list) of parsed items."""

    def __init__(self, item: _Spec, *, min_items: int = 0, unique: bool = False,
                 what: str | None = None, doc: str = "", as_list: bool = False):
        self.item, self.min_items, self.unique, self.doc = item, min_items, unique, doc
        self.as_list = as_list
        self.what = what or f"an array of {item.what}"

    def parse(self, value, path, p):
        if not isinstance(value, list):
            raise self.fail(value, path, p)
        if len(value) < self.min_items:
            raise p.bad(f"{path} = {_show(value)} must have at least {self.min_items} "
                        f"item{'s' if self.min_items > 1 else ''}")
        out, failed = [], False
        for i, v in enumerate(value):
            try:
                out.append(self.item.parse(v, f"{path}[{i}]", p))
            except _Bad:
                failed = True
        if failed:
            raise _Bad(path)
        if self.unique:
            seen: dict = {}
            for i, v in enumerate(out):
                if v in seen:
                    raise p.bad(f"{path}[{i}] = {_show(value[i])} repeats {path}[{seen[v]}]; "
                                "items must be distinct")
                seen[v] = i
        return out if self.as_list else tuple(out)

    def schema(self):
        s: dict = {"type": "array", "items": self.item.schema()}
        if self.min_items:
            s["minItems"] = self.min_items
        if self.unique:
            s["uniqueItems"] = True
        return _described(s, self.doc)


class _Table(_Spec):
    """A table with known keys.

    ``one_of``: exactly one of these keys; ``any_of``: at least one; ``exclusive``: pairs
    that may not appear together; ``make`` builds the result from the parsed keys.
    """

    def __init__(self, keys: dict[str, _Spec], *, required: tuple[str, ...] = (),
                 make: Callable[[dict], Any] = dict, one_of: tuple[str, ...] = (),
                 any_of: tuple[str, ...] = (), exclusive: tuple[tuple[str, str], ...] = (),
                 check: Callable[[dict, str, _Problems], None] | None = None,
                 what: str = "a table", doc: str = "", one_of_what: str = "selector"):
        self.keys, self.required, self.make = keys, required, make
        self.one_of_what = one_of_what
        self.one_of, self.any_of, self.exclusive, self.check = one_of, any_of, exclusive, check
        self.what, self.doc = what, doc

    def parse(self, value, path, p):
        if not isinstance(value, dict):
            raise self.fail(value, path, p)
        out, failed = {}, False
        for k, v in value.items():
            if k not in self.keys:
                p.add(_unknown_key(k, path, self.keys))
                failed = True
                continue
            try:
                out[k] = self.keys[k].parse(v, _join(path, k), p)
            except _Bad:
                failed = True
        for k in self.required:
            if k not in value:
                p.add(f"{_join(path, k)} is missing; it is required: {self.keys[k].what}")
                failed = True
        if self.one_of:
            given = [k for k in self.one_of if k in value]
            if len(given) != 1:
                has = f"{len(given)} {self.one_of_what}s ({', '.join(given)})" if given \
                    else f"no {self.one_of_what}"
                p.add(f"{path} has {has}; give exactly one of {', '.join(self.one_of)}")
                failed = True
        if self.any_of and not any(k in value for k in self.any_of):
            p.add(f"{path} has neither {' nor '.join(self.any_of)}; give at least one")
            failed = True
        for a, b in self.exclusive:
            if a in value and b in value:
                p.add(f"{path} has both {a} and {b}; give only one")
                failed = True
        if failed:
            raise _Bad(path)
        if self.check is not None:
            self.check(out, path, p)
        return self.make(out)

    def schema(self):
        s: dict = {"type": "object",
                   "properties": {k: spec.schema() for k, spec in self.keys.items()},
                   "additionalProperties": False}
        if self.required:
            s["required"] = list(self.required)
        all_of = []
        if self.one_of:
            all_of.append({"oneOf": [{"required": [k]} for k in self.one_of]})
        if self.any_of:
            all_of.append({"anyOf": [{"required": [k]} for k in self.any_of]})
        for a, b in self.exclusive:
            all_of.append({"not": {"required": [a, b]}})
        if len(all_of) == 1:
            s.update(all_of[0])
        elif all_of:
            s["allOf"] = all_of
        return _described(s, self.doc)


class _Map(_Spec):
    """A table of named items (``[groups.<name>]``)."""

    def __init__(self, item: _Spec, key_pattern: str, key_what: str, doc: str = ""):
        self.item, self.key_pattern, self.key_what, self.doc = item, key_pattern, key_what, doc
        self.what = "a table of named items"

    def parse(self, value, path, p):
        if not isinstance(value, dict):
            raise self.fail(value, path, p)
        out, failed = {}, False
        for k, v in value.items():
            if not re.search(self.key_pattern, k):
                p.add(f"{path}.{json.dumps(k)}: {self.key_what}")
                failed = True
                continue
            try:
                out[k] = self.item.parse(v, f"{path}.{k}", p)
            except _Bad:
                failed = True
        if failed:
            raise _Bad(path)
        return out

    def schema(self):
        return _described({"type": "object", "propertyNames": {"pattern": self.key_pattern},
                           "additionalProperties": self.item.schema()}, self.doc)


class _ByType(_Spec):
    """One of several specs, chosen by the value's TOML type (string, array or table)."""

    def __init__(self, options: dict[type, _Spec], what: str, doc: str = ""):
        self.options, self.what, self.doc = options, what, doc

    def parse(self, value, path, p):
        for kind, spec in self.options.items():
            if isinstance(value, kind) and not isinstance(value, bool):
                n = len(p.items)
                try:
                    return spec.parse(value, path, p)
                except _Bad:
                    if not isinstance(spec, _String):
                        raise
                    del p.items[n:]  # say what every alternative allows
                    raise self.fail(value, path, p) from None
        raise self.fail(value, path, p)

    def schema(self):
        return _described({"oneOf": [s.schema() for s in self.options.values()]}, self.doc)


class _Const(_String):
    def __init__(self, value: str, result: Any, what: str, doc: str = ""):
        super().__init__(enum=(value,), doc=doc)
        self.result, self.what = result, what

    def parse(self, value, path, p):
        super().parse(value, path, p)
        return self.result


class _PositionTable(_Spec):
    """``{ offset = ... }`` | ``{ absolute = ... }`` | ``{ rotation, translation, center }``."""

    what = ('"rest" or a table with offset, absolute, or rotation/translation '
            "(and optional center)")

    def __init__(self):
        self.vec = _Vector(3, unit="m")
        self.kinds = {
            "offset": {"offset": _Vector(3, "dx, dy, dz", "m",
                                         doc="displacement from rest (m) of every vertex")},
            "absolute": {"absolute": _Array(_Vector(3, unit="m"), min_items=1,
                                            what="an array of [x, y, z] rows, one per vertex",
                                            doc="target positions (m), one row per group vertex "
                                                "in group order")},
            "rigid": {"rotation": _Vector(3, "rx, ry, rz", "degrees",
                                          doc="Euler angles in degrees, applied X then Y then Z "
                                              "(fixed axes)"),
                      "translation": _Vector(3, "tx, ty, tz", "m", doc="translation (m)"),
                      "center": _Vector(3, "cx, cy, cz", "m",
                                        doc="center of rotation (m); default: group centroid")},
        }
        self.all_keys = {k: s for kinds in self.kinds.values() for k, s in kinds.items()}

    def parse(self, value, path, p):
        out, failed = {}, False
        for k, v in value.items():
            if k not in self.all_keys:
                p.add(_unknown_key(k, path, self.all_keys))
                failed = True
                continue
            try:
                out[k] = self.all_keys[k].parse(v, _join(path, k), p)
            except _Bad:
                failed = True
        if failed:
            raise _Bad(path)
        kinds = [kind for kind, keys in self.kinds.items() if any(k in value for k in keys)]
        if len(kinds) != 1:
            raise p.bad(f"{path} = {_show(value)} must be {self.what}"
                        + (f"; it mixes {' and '.join(kinds)} targets" if kinds else ""))
        if kinds == ["rigid"] and not ({"rotation", "translation"} & value.keys()):
            raise p.bad(f"{path} has a center but neither rotation nor translation; give at "
                        "least one of them")
        if "offset" in out:
            return Offset(out["offset"])
        if "absolute" in out:
            return Absolute(out["absolute"])
        return Rigid(**out)

    def schema(self):
        branches = []
        for kind, keys in self.kinds.items():
            b: dict = {"type": "object", "properties": {k: s.schema() for k, s in keys.items()},
                       "additionalProperties": False}
            if kind == "rigid":
                b["anyOf"] = [{"required": ["rotation"]}, {"required": ["translation"]}]
            else:
                b["required"] = [kind]
            branches.append(b)
        return {"oneOf": branches}


def _described(schema: dict, doc: str) -> dict:
    if doc:
        schema["description"] = doc
    return schema


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _unknown_key(key: str, path: str, allowed) -> str:
    where = f"in [{path}]" if path and "[" not in path else f"in {path}" if path else \
        "at the top level"
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"allowed keys: {', '.join(allowed)}"
    return f"unknown key {key!r} {where}; {hint}"


# --- the scene format ---------------------------------------------------------------------------


def _check_box(d: dict, path: str, p: _Problems) -> None:
    lo, hi = d["min"], d["max"]
    bad = [a for a, x, y in zip("xyz", lo, hi, strict=True) if x > y]
    if bad:
        raise p.bad(f"{path}.min = {_show(list(lo))} exceeds {path}.max = {_show(list(hi))} "
                    f"in {', '.join(bad)}; min must be <= max in every coordinate")


def _check_time(d: dict, path: str, p: _Problems) -> None:
    start = d.get("start", 0.0)
    if "end" in d and d["end"] <= start:
        raise p.bad(f"{path}.end = {_show(d['end'])} must be after {path}.start = {_show(start)}")
    if "end" in d and d["end"] - start > MAX_DURATION:
        raise p.bad(f"{path}.end = {_show(d['end'])} makes a shot of {d['end'] - start:g} s; "
                    f"shots may last at most {MAX_DURATION:g} s (wiggly.limits.MAX_DURATION)")


_POSITIVE = {"gt": 0.0}
_SELECTOR_SPECS = {
    "box": _Table({"min": _Vector(3, unit="m"), "max": _Vector(3, unit="m")},
                  required=("min", "max"), check=_check_box,
                  make=lambda d: Box(d["min"], d["max"]),
                  doc="vertices with min <= x <= max in every coordinate"),
    "sphere": _Table({"center": _Vector(3, unit="m"), "radius": _Number(unit="m", **_POSITIVE)},
                     required=("center", "radius"),
                     make=lambda d: Sphere(d["center"], d["radius"]),
                     doc="vertices with |x - center| <= radius"),
    "nearest": _Table({"points": _Array(_Vector(3, unit="m"), min_items=1,
                                        what="an array of [x, y, z] points"),
                       "count": _Number(integer=True, ge=1, doc="vertices per point (default 1)")},
                      required=("points",), make=lambda d: Nearest(d["points"],
                                                                   d.get("count", 1)),
                      doc="the count nearest vertices to each point"),
    "indices": _Array(_Number(integer=True, ge=0), min_items=1, unique=True,
                      what="an array of distinct vertex indices (integers >= 0)",
                      doc="explicit vertex indices (0-based); absolute targets follow this order"),
    "from_mesh": _String(doc="name of a vertex group stored in the mesh file"),
}


def _make_group(d: dict) -> GroupSpec:
    kind = next(k for k in _SELECTOR_SPECS if k in d)
    sel = d[kind]
    selector = Indices(sel) if kind == "indices" else FromMesh(sel) if kind == "from_mesh" \
        else sel
    return GroupSpec(selector, d.get("on", "surface"), d.get("color"))


_GROUP = _Table(
    {**_SELECTOR_SPECS,
     "on": _String(enum=("surface", "tets"),
                   doc='"surface" (default): vertices of the user\'s surface; "tets": '
                       "vertices of the tet mesh"),
     "color": _String(pattern=r"^#[0-9a-fA-F]{6}$", what='a color "#rrggbb"',
                      doc="color in previews and the editor")},
    one_of=tuple(_SELECTOR_SPECS), make=_make_group,
    doc="a named vertex group: exactly one selector")

_KEYFRAME = _Table(
    {"time": _Number(unit="s", doc="key time (s), within the shot's time range"),
     "group": _String(doc="name of a group"),
     "position": _ByType({str: _Const("rest", Rest(), _PositionTable.what),
                          dict: _PositionTable()},
                         what='"rest" or a table with offset, absolute, or '
                              "rotation/translation (and optional center)",
                         doc="position target"),
     "velocity": _Vector(3, "vx, vy, vz", "m/s", doc="target velocity (m/s) of every vertex"),
     "stiffness": _Number(ge=0.0, doc="dimensionless weight (default 1e6)"),
     "c_A": _Number(ge=0.0, doc="explicit position weight of eq. (4)"),
     "c_B": _Number(ge=0.0, doc="explicit velocity weight of eq. (4)"),
     "name": _String(min_length=0, what="a string", doc="label")},
    required=("time", "group"), any_of=("position", "velocity"),
    make=lambda d: KeyframeSpec(**d), what="a table ([[keyframes]])",
    doc="constraints on one group at one time")

_OUTPUT_PATTERN = r"\.(" + "|".join(
    "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c for c in e[1:])
    for e in OUTPUT_EXTENSIONS) + r")$"

_SCENE = _Table(
    {"format": _Number(integer=True, ge=1, le=FORMAT, doc="scene format version",
                       what=f"{FORMAT} (the newest format this version of wiggly reads)"),
     "mesh": _Table(
         {"path": _String(doc='mesh file, relative to the scene file, or "builtin:critter", '
                              '"builtin:plant", "builtin:bar"'),
          "resolution": _Number(integer=True, ge=1, le=MAX_RESOLUTION,
                                doc="tet edges along the bounding-box diagonal (default "
                                    f"{DEFAULT_RESOLUTION})"),
          "edge_length": _Number(unit="m", **_POSITIVE, doc="target tet edge length (m)"),
          "repair": _Bool(doc="accept open, non-manifold or self-intersecting surfaces and "
                              "let fTetWild fill them (default true; false refuses them)")},
         required=("path",), exclusive=(("resolution", "edge_length"),),
         make=lambda d: MeshSpec(**d), doc="the model"),
     "material": _Table(
         {"young": _Number(unit="Pa", **_POSITIVE, doc="Young's modulus E (Pa)"),
          "poisson": _Number(ge=0.0, lt=0.5, doc="Poisson ratio"),
          "density": _Number(unit="kg/m^3", **_POSITIVE, doc="density (kg/m^3)")},
         make=lambda d: MaterialSpec(**d)),
     "damping": _Table(
         {"alpha": _Number(ge=0.0, unit="1/s", doc="mass-proportional damping (1/s)"),
          "beta": _Number(ge=0.0, unit="s", doc="stiffness-proportional damping (s)")},
         make=lambda d: DampingSpec(**d), doc="Rayleigh damping D = alpha M + beta K"),
     "simulation": _Table(
         {"gravity": _Vector(3, "gx, gy, gz", "m/s^2", doc="gravity (m/s^2)"),
          "modes": _Number(integer=True, ge=1, le=MAX_MODES,
                           doc="number of eigenmodes (rigid ones included)"),
          "warp": _Bool(doc="rotation-strain warping (false: linear)"),
          "lumped_mass": _Bool(doc="lumped instead of consistent mass matrix"),
          "fixed": _Array(_String(what="a group name"), unique=True,
                          what="an array of group names", doc="groups held at rest"),
          "preroll": _Number(ge=0.0, unit="s",
                             doc="seconds of rest before the start (default: the duration)")},
         make=lambda d: SimulationSpec(**d)),
     "time": _Table(
         {"start": _Number(unit="s"),
          "end": _Number(unit="s"),
          "duration": _Number(unit="s", gt=0.0, le=MAX_DURATION),
          "fps": _Number(gt=0.0, le=MAX_FPS, doc="frames per second of the outputs")},
         exclusive=(("end", "duration"),), check=_check_time, make=lambda d: TimeSpec(**d),
         doc="time range (default: start 0, end at the last keyframe, at least 1 s)"),
     "groups": _Map(_GROUP, GROUP_NAME,
                    "group names may contain only letters, digits, '_' and '-'",
                    doc="named vertex groups"),
     "keyframes": _Array(_KEYFRAME, as_list=True, what="an array of tables ([[keyframes]])"),
     "output": _Table(
         {"paths": _Array(_String(pattern=_OUTPUT_PATTERN,
                                  what="a file name ending in "
                                       + ", ".join(OUTPUT_EXTENSIONS)),
                          unique=True, doc="output files, by extension"),
          "overwrite": _Bool(doc="replace existing outputs"),
          "size": _Vector(2, item=_Number(integer=True, ge=16, le=8192),
                          what="[width, height] in pixels (integers from 16 to 8192)",
                          doc="video size in pixels (default [960, 540])"),
          "camera": _ByType({str: _String(enum=CAMERAS),
                             list: _Vector(2, "azimuth, elevation", "degrees")},
                            what=" or ".join(json.dumps(c) for c in CAMERAS)
                            + " or [azimuth, elevation] in degrees",
                            doc="preview camera"),
          "frame_start": _Number(integer=True, ge=-1_000_000, le=1_000_000,
                                 doc="glTF/USD frame of the first output frame: frame k lands "
                                     "on frame_start + k at the output fps (default: the "
                                     "shot's own time, t * fps)"),
          "gltf_targets": _String(enum=GLTF_TARGETS,
                                  doc='glTF morph targets: "frames" (one per frame, default) '
                                      'or "modes" (one per mode, weights q(t); linear shots '
                                      "only: exact and compact)")},
         make=lambda d: OutputSpec(**d)),
     },
    required=("mesh",), make=lambda d: Scene(**d), what="a TOML document")

def scene_schema() -> dict:
    """The JSON Schema (draft 2020-12) of scene files, generated from the validator's specs.

    It checks the structure (keys, types, ranges); references between keys (a keyframe's
    group exists, its time lies in the shot) and checks against the mesh are the validator's.
    """
    s = _SCENE.schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "wiggly scene",
            "description": "A wiggly scene file (TOML), format 1: see docs/scene-format.md.",
            **s}


# ----------------------------------------------------------------------------------------------
# reading and checking


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Read and check a scene file; every problem raises one :class:`WigglyInputError` that
    lists all problems found (file, key path, value, what is allowed)."""
    path = Path(path)
    if not path.is_file():
        raise WigglyInputError(f"{path}: no such scene file" if not path.exists()
                               else f"{path}: is not a file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise WigglyInputError(f"{path}: not a text file (UTF-8): {err}") from None
    except tomllib.TOMLDecodeError as err:
        raise WigglyInputError(f"{path}: not valid TOML: {err}") from None
    return scene_from_dict(data, where=str(path), source=path.resolve())


def scene_from_dict(data: dict, where: str = "scene", source: Path | None = None) -> Scene:
    """Check a parsed scene (the TOML as dicts and lists) and build the :class:`Scene`;
    ``source`` is the file it came from (relative paths resolve against its directory and the
    mesh file must exist)."""
    p = _Problems(where)
    try:
        scene = _SCENE.parse(data, "", p)
    except _Bad:
        p.raise_if_any()
        raise
    scene.source = source
    _cross_check(scene, p)
    if source is not None:
        _check_files(scene, p)
    p.raise_if_any()
    return scene


def _suggest(name: str, names) -> str:
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _cross_check(scene: Scene, p: _Problems) -> None:
    """Checks between keys: group names, key times in the shot's time range."""
    names = list(scene.groups)
    listing = ", ".join(names) if names else "none are defined ([groups.<name>])"
    for j, kf in enumerate(scene.keyframes):
        if kf.group not in scene.groups:
            p.add(f"keyframes[{j}].group = {_show(kf.group)} is not a group"
                  f"{_suggest(kf.group, names)}; groups are: {listing}")
    for j, g in enumerate(scene.simulation.fixed):
        if g not in scene.groups:
            p.add(f"simulation.fixed[{j}] = {_show(g)} is not a group{_suggest(g, names)}; "
                  f"groups are: {listing}")
    t0, t1 = scene.time_range()
    for j, kf in enumerate(scene.keyframes):
        if not t0 - 1e-9 <= kf.time <= t1 + 1e-9:
            p.add(f"keyframes[{j}].time = {_show(kf.time)} is outside the shot's time range "
                  f"[{t0}, {t1}] s")
    if scene.mesh.path.startswith("builtin:") and \
            scene.mesh.path.removeprefix("builtin:") not in BUILTIN_MODELS:
        p.add(f"mesh.path = {_show(scene.mesh.path)} is not a bundled model; use one of "
              + ", ".join(f'"builtin:{m}"' for m in BUILTIN_MODELS))
    if t1 - t0 > MAX_DURATION and scene.time.end is None and scene.time.duration is None:
        p.add(f"the shot runs from {t0:g} s to the last keyframe at {t1:g} s, longer than "
              f"{MAX_DURATION:g} s (wiggly.limits.MAX_DURATION); check the keyframe times")
    frames = math.floor((t1 - t0) * scene.time.fps + 1e-9) + 1
    if frames > MAX_FRAMES and t1 - t0 <= MAX_DURATION:
        p.add(f"time.fps = {_show(scene.time.fps)} makes {frames} frames of a {t1 - t0:g} s "
              f"shot, more than {MAX_FRAMES} (wiggly.limits.MAX_FRAMES); use fps <= "
              f"{math.floor((MAX_FRAMES - 1) / (t1 - t0)):g}")
    if not scene.simulation.fixed and scene.simulation.modes < RIGID_MODES:
        p.add(f"simulation.modes = {scene.simulation.modes} is fewer than the {RIGID_MODES} "
              "rigid modes of a free body (simulation.fixed holds no group), which the basis "
              f"must contain; use at least {RIGID_MODES + 1} ({RIGID_MODES} rigid and the "
              "elastic ones; the default is 40), or hold a group fixed")


def _check_files(scene: Scene, p: _Problems) -> None:
    if scene.mesh.path.startswith("builtin:"):
        return
    f = scene.mesh_file()
    if not f.is_file():
        p.add(f"mesh.path = {_show(scene.mesh.path)}: "
              f"{'is a directory' if f.is_dir() else 'no such file'} ({f})")


# ----------------------------------------------------------------------------------------------
# writing


def scene_to_dict(scene: Scene) -> dict:
    """The scene as TOML-ready dicts and lists (``None`` values left out)."""
    d: dict[str, Any] = {"format": scene.format}
    d["mesh"] = _fields(scene.mesh)
    d["material"] = _fields(scene.material)
    d["damping"] = _fields(scene.damping)
    sim = _fields(scene.simulation)
    sim["gravity"], sim["fixed"] = list(sim["gravity"]), list(sim["fixed"])
    d["simulation"] = sim
    d["time"] = _fields(scene.time)
    d["groups"] = {name: _group_to_dict(g) for name, g in scene.groups.items()}
    d["keyframes"] = [_keyframe_to_dict(k) for k in scene.keyframes]
    out = _fields(scene.output)
    out["paths"], out["size"] = list(out["paths"]), list(out["size"])
    if not isinstance(out["camera"], str):
        out["camera"] = list(out["camera"])
    d["output"] = out
    return d


def _fields(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in fields(obj) if getattr(obj, f.name) is not None}


def _group_to_dict(g: GroupSpec) -> dict:
    sel = g.selector
    key = _SELECTOR_KEYS[type(sel)]
    if isinstance(sel, Box):
        value: Any = {"min": list(sel.min), "max": list(sel.max)}
    elif isinstance(sel, Sphere):
        value = {"center": list(sel.center), "radius": sel.radius}
    elif isinstance(sel, Nearest):
        value = {"points": [list(x) for x in sel.points], "count": sel.count}
    elif isinstance(sel, Indices):
        value = list(sel.indices)
    else:
        value = sel.name
    d = {key: value}
    if g.on != "surface":
        d["on"] = g.on
    if g.color is not None:
        d["color"] = g.color
    return d


def _keyframe_to_dict(k: KeyframeSpec) -> dict:
    d: dict[str, Any] = {"time": k.time, "group": k.group}
    pos = k.position
    if isinstance(pos, Rest):
        d["position"] = "rest"
    elif isinstance(pos, Offset):
        d["position"] = {"offset": list(pos.offset)}
    elif isinstance(pos, Absolute):
        d["position"] = {"absolute": [list(x) for x in pos.positions]}
    elif isinstance(pos, Rigid):
        r: dict[str, Any] = {"rotation": list(pos.rotation)}
        if any(pos.translation):
            r["translation"] = list(pos.translation)
        if pos.center is not None:
            r["center"] = list(pos.center)
        d["position"] = r
    for name in ("velocity", "stiffness", "c_A", "c_B"):
        v = getattr(k, name)
        if v is not None:
            d[name] = list(v) if name == "velocity" else v
    if k.name:
        d["name"] = k.name
    return d


def _toml_value(v: Any) -> str:
    import tomli_w

    if isinstance(v, bool | str | int):
        return tomli_w.dumps({"v": v})[4:-1]
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_lines(table: dict, header: str) -> list[str]:
    """``header`` and ``key = value`` lines; long inline tables become sub-tables and long
    arrays are wrapped one item per line."""
    lines, subtables = [header] if header else [], []
    for k, v in table.items():
        text = f"{k} = {_toml_value(v)}"
        if len(text) <= 100:
            lines.append(text)
        elif isinstance(v, dict):
            subtables.append((k, v))
        elif isinstance(v, list):
            lines.append(f"{k} = [")
            lines += [f"    {_toml_value(x)}," for x in v]
            lines.append("]")
        else:
            lines.append(text)
    for k, v in subtables:
        name = header.strip("[]")
        lines += ["", *_toml_lines(v, f"[{name}.{k}]")]
    return lines


def scene_to_toml(scene: Scene) -> str:
    """The scene as TOML text (comments of the original file are not kept)."""
    d = scene_to_dict(scene)
    lines = [f"# wiggly scene (format {FORMAT}); see docs/scene-format.md",
             f"format = {d['format']}"]
    for section in ("mesh", "material", "damping", "simulation", "time"):
        lines += ["", *_toml_lines(d[section], f"[{section}]")]
    for name, g in d["groups"].items():
        lines += ["", *_toml_lines(g, f"[groups.{name}]")]
    for k in d["keyframes"]:
        body = _toml_lines(k, "[keyframes]")
        lines += ["", "[" + body[0] + "]", *body[1:]]
    lines += ["", *_toml_lines(d["output"], "[output]")]
    return "\n".join(lines) + "\n"


def save_scene(scene: Scene, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
    """Check ``scene`` and write it as TOML, atomically; ``load_scene`` gives it back exactly.

    Paths are written as they are in the scene (relative paths are relative to the directory
    of the file written).  An existing file is an error unless ``overwrite``.
    """
    path = Path(path)
    text = scene_to_toml(scene)
    again = scene_from_dict(tomllib.loads(text), where=str(path))  # validates, too
    if again != scene:  # pragma: no cover - a bug in the writer
        raise AssertionError(f"scene does not survive the TOML round trip: {scene} != {again}")
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    if path.is_dir():
        raise WigglyInputError(f"{path} is a directory")
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


# ----------------------------------------------------------------------------------------------
# groups (checked against the mesh)


def _select(name: str, group: GroupSpec, X: np.ndarray, mesh_groups: dict[str, np.ndarray],
            what: str, p: _Problems) -> np.ndarray | None:
    """Vertex indices of one group among the rest positions ``X``; None (and a problem)."""
    sel = group.selector
    path = f"groups.{name}"
    n = len(X)
    if isinstance(sel, Box):
        lo, hi = np.asarray(sel.min), np.asarray(sel.max)
        idx = np.flatnonzero(np.all((X >= lo) & (X <= hi), axis=1))
    elif isinstance(sel, Sphere):
        idx = np.flatnonzero(np.linalg.norm(X - np.asarray(sel.center), axis=1) <= sel.radius)
    elif isinstance(sel, Nearest):
        if sel.count > n:
            p.add(f"{path}.nearest.count = {sel.count} exceeds the number of vertices of the "
                  f"{what} ({n})")
            return None
        from scipy.spatial import cKDTree

        _, nn = cKDTree(X).query(np.asarray(sel.points), k=sel.count)
        idx = np.unique(np.asarray(nn).ravel())
    elif isinstance(sel, Indices):
        idx = np.asarray(sel.indices, dtype=np.int64)
        bad = np.flatnonzero(idx >= n)
        if bad.size:
            p.add(f"{path}.indices[{bad[0]}] = {idx[bad[0]]} is out of range: the {what} has "
                  f"{counted(n, 'vertex')} (indices 0..{n - 1})")
            return None
    else:
        if sel.name not in mesh_groups:
            have = (f"its groups are: {', '.join(mesh_groups)}" if mesh_groups else
                    "it has no vertex groups")
            p.add(f"{path}.from_mesh = {_show(sel.name)}: the {what} has no vertex group of "
                  f"that name{_suggest(sel.name, mesh_groups)}; {have}")
            return None
        idx = np.asarray(mesh_groups[sel.name], dtype=np.int64)
    if idx.size == 0:
        lo, hi = X.min(axis=0), X.max(axis=0)
        p.add(f"{path} ({_SELECTOR_KEYS[type(sel)]}) selects no vertex of the {what}; its "
              f"bounding box is {_show(lo.round(4).tolist())} .. {_show(hi.round(4).tolist())}")
        return None
    return idx


def resolve_groups(scene: Scene, model) -> dict[str, np.ndarray]:
    """Vertex indices of every group: of the user's surface, or of the tet mesh for
    ``on = "tets"`` (``model`` a :class:`wiggly.Model`).  Raises a
    :class:`WigglyInputError` listing every group that is invalid for this mesh."""
    p = _Problems(scene.where())
    out = _resolve(scene, model.surface.vertices, model.surface.groups, model.tets.vertices,
                   model.tets.groups, p)
    p.raise_if_any()
    return out


def _resolve(scene: Scene, surface_X, surface_groups, tet_X, tet_groups,
             p: _Problems) -> dict[str, np.ndarray]:
    out = {}
    for name, g in scene.groups.items():
        if g.on == "tets":
            if tet_X is None:
                continue
            idx = _select(name, g, tet_X, tet_groups, "tet mesh", p)
        else:
            idx = _select(name, g, surface_X, surface_groups, "surface", p)
        if idx is not None:
            out[name] = idx
    for j, kf in enumerate(scene.keyframes):
        if isinstance(kf.position, Absolute) and kf.group in out:
            k, rows = len(out[kf.group]), len(kf.position.positions)
            if rows != k:
                p.add(f"keyframes[{j}].position.absolute has {counted(rows, 'row')} but "
                      f"group {kf.group!r} has {counted(k, 'vertex')}; give one [x, y, z] per "
                      "vertex")
    return out


# ----------------------------------------------------------------------------------------------
# building and running


def _say(message: str, progress: bool) -> None:
    if progress:
        print(f"[wiggly] {message}", file=sys.stderr, flush=True)


def _load_model(scene: Scene, progress: bool):
    """Read the mesh; check the groups, the surface and the size of its tet mesh before any
    computation; then tetrahedralize and embed."""
    from wiggly import mesh as meshing
    from wiggly.progress import activity

    f = scene.mesh_file()
    where = scene.where()
    loaded = meshing.load_mesh(f)
    checked = None
    if isinstance(loaded, meshing.Surface):  # check what we can before tetrahedralizing
        p = _Problems(where)
        _resolve(scene, loaded.vertices, loaded.groups, None, None, p)
        p.raise_if_any()
        with activity(f"checking {f.name} ({counted(loaded.n_faces, 'triangle')})", progress):
            checked = meshing.checked_surface(loaded, str(f))
        _check_surface_for_scene(scene, checked.report, f.name)
    t = _time.perf_counter()
    model = meshing.build_model(loaded, str(f), resolution=scene.mesh.resolution,
                                edge_length=scene.mesh.edge_length, repair=scene.mesh.repair,
                                progress=progress, checked=checked)
    _say(f"{counted(model.tets.n_tets, 'tet')}, {counted(model.tets.n_vertices, 'vertex')} "
         f"({_time.perf_counter() - t:.1f} s)", progress)
    return model


def _check_surface_for_scene(scene: Scene, report, name: str) -> None:
    """``mesh.repair = false`` against a surface with defects, and the tet count that
    ``mesh.resolution`` / ``mesh.edge_length`` would make, in the scene's terms."""
    from wiggly.limits import MAX_TETS
    from wiggly.mesh import TetBudgetError, check_tet_budget, edge_length_for

    where, m = scene.where(), scene.mesh
    if m.repair is False and not report.clean:
        raise _error(where, [
            f"mesh.repair = false refuses {name}: {'; '.join(report.defects(detailed=True))}. "
            "Remove repair = false (or set it to true) to let fTetWild fill the solid its "
            "triangles enclose, or fix the model in a modelling tool"])
    if m.edge_length is not None:
        key, value = "mesh.edge_length", _show(m.edge_length)
    else:
        key = "mesh.resolution"
        value = _show(m.resolution) if m.resolution is not None else \
            f"{DEFAULT_RESOLUTION} (the default)"
    h = edge_length_for(report.diagonal, m.edge_length, m.resolution, where)
    try:
        check_tet_budget(report, h, where, key)
    except TetBudgetError as err:
        raise _error(where, [
            f"{key} = {value} would make about {err.estimate:.2g} tetrahedra of {name}, more "
            f"than wiggly's limit of {MAX_TETS} (wiggly.limits.MAX_TETS); use resolution <= "
            f"{err.max_resolution} (or edge_length >= {err.min_edge_length:.3g} m)"]) from None


def _check_modes_for_scene(scene: Scene, model, fixed_vertices) -> None:
    """``simulation.modes`` against the tet mesh: at most its free degrees of freedom, at
    least its rigid modes (before the modes are computed)."""
    n = model.tets.n_vertices
    fixed = np.zeros((0,), np.int64) if fixed_vertices is None else fixed_vertices
    free = 3 * (n - len(fixed))
    modes, name = scene.simulation.modes, scene.mesh_file().name
    if modes > free:
        held = f", {len(fixed)} of them fixed" if len(fixed) else ""
        raise _error(scene.where(), [
            f"simulation.modes = {modes} is more than the {free} degrees of freedom of {name}'s "
            f"tet mesh ({counted(n, 'vertex')}{held}, 3 each); use at most {free}, or a higher "
            "mesh.resolution"])
    rigid = _rigid_mode_count(model.tets.vertices[fixed])
    if modes < rigid:
        raise _error(scene.where(), [
            f"simulation.modes = {modes} is fewer than the {rigid} rigid modes that the fixed "
            f"groups leave free (they are {'collinear' if len(fixed) > 1 else 'one point'}), "
            f"which the basis must contain; use at least {rigid + 1}"])


def _rigid_mode_count(points: np.ndarray) -> int:
    """Rigid motions left by holding ``points`` at rest: 6 if none, 3 (rotations) about one
    point, 1 about a line, 0 otherwise (SYSTEM.md §3)."""
    if len(points) == 0:
        return RIGID_MODES
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    size = max(float(np.ptp(points, axis=0).max()), 1e-300)
    rank = int(np.sum(spread > 1e-9 * size))
    return {0: 3, 1: 1}.get(rank, 0)


def build(scene: Scene, progress: bool = False):
    """Body and keyframes of a scene: ``(wiggly.Body, list[wiggly.Keyframe])``.

    Reads and tetrahedralizes the mesh, resolves the groups, assembles the FEM and computes
    the modes (cached on disk).  ``progress`` prints stages and progress bars on stderr.
    """
    body, keyframes, _ = _build(scene, progress)
    return body, keyframes


def _build(scene: Scene, progress: bool):
    from wiggly.body import Damping, fixed_from_surface, prepare
    from wiggly.fem import Material

    model = _load_model(scene, progress)
    groups = resolve_groups(scene, model)
    fixed = [groups[g] if scene.groups[g].on == "tets" else fixed_from_surface(model, groups[g])
             for g in scene.simulation.fixed]
    fixed_vertices = np.unique(np.concatenate(fixed)) if fixed else None
    _check_modes_for_scene(scene, model, fixed_vertices)
    m, s = scene.material, scene.simulation
    body = prepare(model, material=Material(m.young, m.poisson, m.density),
                   damping=Damping(scene.damping.alpha, scene.damping.beta), gravity=s.gravity,
                   fixed_vertices=fixed_vertices, n_modes=s.modes, lumped=s.lumped_mass,
                   progress=progress)
    return body, keyframes_of(scene, body, groups), groups


def keyframes_of(scene: Scene, body, groups: dict[str, np.ndarray]) -> list:
    """The scene's keyframes as :class:`wiggly.Keyframe` objects for ``body``."""
    from wiggly.keyframes import Keyframe

    out = []
    for kf in scene.keyframes:
        v, on = groups[kf.group], scene.groups[kf.group].on
        kw: dict[str, Any] = {"on": on, "name": kf.label}
        for name in ("stiffness", "c_A", "c_B"):
            if getattr(kf, name) is not None:
                kw[name] = getattr(kf, name)
        vel = None if kf.velocity is None else np.asarray(kf.velocity)
        pos = kf.position
        if pos is None:
            k = Keyframe(kf.time, v, velocity=vel, **kw)
        elif isinstance(pos, Rest):
            k = Keyframe.rest(body, kf.time, v, velocity=vel, **kw)
        elif isinstance(pos, Offset):
            k = Keyframe.offset(body, kf.time, v, pos.offset, velocity=vel, **kw)
        elif isinstance(pos, Absolute):
            k = Keyframe(kf.time, v, position=np.asarray(pos.positions), velocity=vel, **kw)
        else:
            k = Keyframe.rigid(body, kf.time, v, rotation=pos.matrix(),
                               translation=pos.translation, center=pos.center, velocity=vel,
                               **kw)
        out.append(k)
    return out


def _output_paths(scene: Scene, outputs) -> list[Path]:
    if outputs is None:
        return [scene.resolve(p) for p in scene.output.paths]
    return [Path(o).expanduser() for o in outputs]


def check_outputs(paths: list[Path], overwrite: bool, where: str = "outputs",
                  labels: list[str] | None = None) -> None:
    """Every output has a known extension, none exists unless ``overwrite``, and each can be
    written: its folder exists or can be created (no path component is a file) and accepts
    new files.  ``labels`` name the outputs in messages (``output.paths[0] = "a.glb"``);
    default: the paths.  Raises one :class:`WigglyInputError` listing every problem."""
    from wiggly.files import check_writable

    problems = []
    seen = set()
    labels = labels or [str(p) for p in paths]
    for path, label in zip(paths, labels, strict=True):
        ext = path.suffix.lower()
        if ext not in OUTPUT_EXTENSIONS:
            problems.append(f"{label}: unsupported output extension "
                            f"{path.suffix or '(none)'!r}; use one of "
                            f"{', '.join(OUTPUT_EXTENSIONS)}")
            continue
        if path.resolve() in seen:
            problems.append(f"{label}: {path} is given twice")
        seen.add(path.resolve())
        why = check_writable(path)
        if why is not None:
            problems.append(f"{label}: {why}")
        elif path.is_dir():
            problems.append(f"{label}: {path} is a directory; give a file name")
        elif not overwrite:
            existing = path if path.exists() else None
            if ext == ".obj" and existing is None:
                first = path.with_name(f"{path.stem}_0000.obj")
                existing = first if first.exists() else None
            if existing is not None:
                problems.append(f"{label}: {existing} exists; pass --overwrite (or overwrite = "
                                "true in [output]) to replace it")
    if problems:
        raise _error(where, problems)


def _hex_rgb(color: str) -> tuple[float, float, float]:
    return tuple(int(color[i:i + 2], 16) / 255 for i in (1, 3, 5))


def keyframe_highlights(scene: Scene, body, keyframes, groups: dict[str, np.ndarray]) -> list:
    """:class:`wiggly.render.Highlight` of every position keyframe (targets drawn at key
    times), colored by group."""
    from scipy.spatial import cKDTree

    from wiggly.render import Highlight

    colors = {name: g.color or PALETTE[i % len(PALETTE)]
              for i, (name, g) in enumerate(scene.groups.items())}
    out = []
    for spec, kf in zip(scene.keyframes, keyframes, strict=True):
        verts = groups[spec.group]
        if scene.groups[spec.group].on == "tets":  # nearest surface vertices
            _, verts = cKDTree(body.surface.vertices).query(body.tets.vertices[verts])
            verts = np.unique(verts)
        targets = None
        if kf.position is not None:  # a few target spheres suffice to show the pose
            pick = np.unique(np.linspace(0, len(kf.position) - 1, MAX_TARGETS).round())
            targets = kf.position[pick.astype(np.int64)]
        out.append(Highlight(np.asarray(verts, np.int64), kf.time, _hex_rgb(colors[spec.group]),
                             spec.label, targets))
    return out


def run(scene: Scene, *, outputs=None, overwrite: bool | None = None,
        progress: bool = False):
    """Animate the scene and write every output; return the :class:`wiggly.Animation`.

    ``outputs`` replaces the scene's ``[output] paths`` (relative to the current directory,
    not the scene's); ``overwrite`` replaces ``[output] overwrite``.  Geometry (.glb .usd*
    .obj .npz) goes through :func:`wiggly.export.write_animation`, previews (.mp4 .gif) through
    :func:`wiggly.render.render_video` with the keyframed groups highlighted, .png through
    :func:`wiggly.render.render_contact_sheet`.  Outputs are checked before anything is
    computed and written atomically.  ``anim.info["scene"]`` has the written paths and the
    time spent per stage.
    """
    from wiggly.solve import solve

    overwrite = scene.output.overwrite if overwrite is None else overwrite
    paths = _output_paths(scene, outputs)
    labels = ([f"output.paths[{i}] = {_show(p)}" for i, p in enumerate(scene.output.paths)]
              if outputs is None else [f"-o {o}" for o in outputs])
    check_outputs(paths, overwrite, scene.where(), labels)
    _check_gltf_targets(scene, paths)
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    body, keyframes, groups = _build(scene, progress)
    timings["prepare"] = _time.perf_counter() - t
    start, end = scene.time_range()
    _say(f"{'warped' if scene.simulation.warp else 'linear'} spacetime solve: "
         f"{len(keyframes)} keyframes, {body.r} modes, [{start:g}, {end:g}] s", progress)
    t = _time.perf_counter()
    anim = solve(body, keyframes, start=start, end=end, warp=scene.simulation.warp,
                 preroll=scene.simulation.preroll, progress=progress)
    timings["solve"] = _time.perf_counter() - t
    written = write_outputs(scene, anim, paths, overwrite=overwrite, progress=progress,
                            highlights=keyframe_highlights(scene, body, anim.keyframes, groups),
                            timings=timings)
    anim.info["scene"] = {"outputs": written, "seconds": timings, "groups": groups}
    return anim


def _check_gltf_targets(scene: Scene, paths: list[Path]) -> None:
    if scene.output.gltf_targets == "modes" and scene.simulation.warp and \
            any(p.suffix.lower() == ".glb" for p in paths):
        raise _error(scene.where(), [
            'output.gltf_targets = "modes" needs a linear shot: a warped motion is no linear '
            "combination of modes; set simulation.warp = false (or pass --linear), or use "
            '"frames"'])


def write_outputs(scene: Scene, anim, paths: list[Path], *, overwrite: bool,
                  progress: bool = False, highlights=(), timings: dict | None = None
                  ) -> list[Path]:
    """Sample ``anim`` at the scene's fps and write ``paths`` (geometry first), all or
    nothing: every output goes to a temporary file first and all are moved into place once
    all are written (:class:`wiggly.files.OutputSet`); on a failure none is replaced."""
    from wiggly.export import SurfaceAnimation, stage_animation
    from wiggly.files import OutputSet

    timings = {} if timings is None else timings
    if not paths:
        return []
    _check_gltf_targets(scene, paths)
    t = _time.perf_counter()
    times = anim.frame_times(scene.time.fps)
    _say(f"sampling {counted(len(times), 'frame')} at {scene.time.fps:g} fps", progress)
    positions = anim.positions(times, dtype=np.float32)
    surf = anim.body.surface
    data = SurfaceAnimation(times, positions, surf.faces, surf.uvs, surf.normals,
                            scene.mesh_file().stem, rest=surf.vertices)
    targets = scene.output.gltf_targets or "frames"
    if targets == "modes" and any(p.suffix.lower() == ".glb" for p in paths):
        basis = anim.body.surface_basis  # (3p, r): positions = rest + basis q(t)
        data.mode_shapes = basis.T.reshape(anim.body.r, -1, 3)
        data.modal = anim.modal(times)[0]
    timings["sample"] = _time.perf_counter() - t
    written = []
    with OutputSet() as outputs:
        for path in sorted(paths, key=lambda q: q.suffix.lower() in PREVIEW_EXTENSIONS):
            t = _time.perf_counter()
            ext = path.suffix.lower()
            _say(f"writing {path}", progress)
            if ext in GEOMETRY_EXTENSIONS:
                stage_animation(outputs, path, data, overwrite=overwrite, progress=progress,
                                frame_start=scene.output.frame_start, gltf_targets=targets)
            else:
                if path.exists() and not overwrite:
                    raise WigglyInputError(f"{path} exists; pass --overwrite (or overwrite = "
                                           "true in [output]) to replace it")
                render_preview(outputs.stage(path), times, positions, surf.faces,
                               highlights=highlights, output=scene.output, title=scene.name,
                               overwrite=True, progress=progress)
            timings[f"write {path.name}"] = _time.perf_counter() - t
            written.append(path)
    return written


def render_preview(path: Path, times, positions, faces, *, highlights=(),
                   output: OutputSpec | None = None, title: str | None = None,
                   overwrite: bool = False, progress: bool = False,
                   fps: float | None = None) -> Path:
    """An .mp4/.gif video (at ``fps``, default: the frames' rate) or a .png contact sheet of
    an animated surface."""
    from wiggly import render

    output = output or OutputSpec()
    camera = output.camera if isinstance(output.camera, str) else tuple(output.camera)
    if path.suffix.lower() == ".png":
        tile = (max(16, output.size[0] // 2), max(16, output.size[1] // 2))
        return render.render_contact_sheet(path, times, positions, faces, n_frames=8, columns=4,
                                           highlights=highlights, tile_size=tile, camera=camera,
                                           title=title, progress=progress, overwrite=overwrite)
    return render.render_video(path, times, positions, faces, highlights=highlights,
                               fps=fps, size=output.size, camera=camera, title=title,
                               progress=progress, overwrite=overwrite)


def with_overrides(scene: Scene, *, fps: float | None = None, warp: bool | None = None,
                   resolution: int | None = None, modes: int | None = None,
                   frame_start: int | None = None, gltf_targets: str | None = None) -> Scene:
    """A copy of ``scene`` with some settings replaced (command-line options, tests)."""
    s = scene
    if frame_start is not None:
        s = replace(s, output=replace(s.output, frame_start=int(frame_start)))
    if gltf_targets is not None:
        s = replace(s, output=replace(s.output, gltf_targets=gltf_targets))
    if fps is not None:
        s = replace(s, time=replace(s.time, fps=float(fps)))
    if warp is not None:
        s = replace(s, simulation=replace(s.simulation, warp=warp))
    if modes is not None:
        s = replace(s, simulation=replace(s.simulation, modes=int(modes)))
    if resolution is not None:
        s = replace(s, mesh=replace(s.mesh, resolution=int(resolution), edge_length=None))
    return s
