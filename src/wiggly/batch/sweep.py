"""Sweep files: one base scene and grids or random draws over its parameters
(``docs/sweep-format.md``).

A sweep is checked completely before any shot runs, with the scene format's validation
framework (:mod:`wiggly.scene.validation`): its structure, every parameter path against the
scene format and the base scene, and every grid value and distribution bound against the
scene format's description of that key.  Combinations of values can still make a shot
invalid (a keyframe moved past the end of a shortened shot); such a shot fails alone, with
the scene validator's message.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import zlib
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from wiggly.errors import WigglyInputError
from wiggly.limits import MAX_SHOTS
from wiggly.scene import Scene, scene_from_dict, scene_to_dict
from wiggly.scene.schema import OUTPUT_PATTERN, SCENE_FORMAT
from wiggly.scene.schema import read_toml as read_valid_toml
from wiggly.scene.spec import OUTPUT_EXTENSIONS
from wiggly.scene.validation import (
    Array,
    Bad,
    ByType,
    Map,
    Number,
    PositionTable,
    Problems,
    Spec,
    String,
    Table,
    Vector,
    show,
    unknown_key,
)

#: Sweep format version written in examples and the newest one read.
SWEEP_FORMAT = 1
DISTRIBUTIONS = ("uniform", "log_uniform", "integers", "choice")
#: Files every shot folder holds besides its outputs.
RESERVED_NAMES = ("scene.toml", "result.json", "thumb.png")
#: Keys a sweep may not vary: the batch owns the outputs.
FIXED_ROOTS = ("format", "output")
_STEP = re.compile(r"([A-Za-z0-9_-]+)(?:\[([^\[\]]+)\])?")
_ZERO_DEFAULT = ("offset", "rotation", "translation")  # position vectors that default to 0


class _Any(Spec):
    """Any TOML value (checked later against the key it is meant for)."""

    what = "a value"

    def parse(self, value, path, p):
        return value

    def schema(self):
        return {}


class _ParamMap(Map):
    """``[grid]`` / ``[random]``: parameter paths (quoted TOML keys) to values."""

    def key_path(self, path: str, key: str) -> str:
        return f'{path}."{key}"'

    item_path = key_path  # a parameter path is always a quoted key


PARAM_PATTERN = r"^[A-Za-z0-9_-]+(\[[^\[\]]+\])?(\.[A-Za-z0-9_-]+(\[[^\[\]]+\])?)*$"
_PARAM_WHAT = ('a parameter is a quoted key path into the scene, e.g. "material.young", '
               '"keyframes[2].position.offset" or "keyframes[take-off].velocity[1]"')
_PAIR = Vector(2, "low, high", item=_Any(), what="an array [low, high]")
_DISTRIBUTION = Table(
    {"uniform": _PAIR, "log_uniform": _PAIR, "integers": _PAIR,
     "choice": Array(_Any(), min_items=1, as_list=True, what="an array of values")},
    one_of=DISTRIBUTIONS, one_of_what="distribution",
    what="a table with one of uniform, log_uniform, integers, choice",
    doc="uniform = [low, high] (numbers or vectors, per component), log_uniform = [low, high] "
        "(> 0), integers = [low, high] (inclusive), choice = [value, ...]")
_SWEEP = Table(
    {"format": Number(integer=True, ge=1, le=SWEEP_FORMAT, doc="sweep format version",
                       what=f"{SWEEP_FORMAT} (the newest sweep format this wiggly reads)"),
     "base": String(doc="the base scene file, relative to the sweep file"),
     "name": String(pattern=r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$",
                     what='a name of letters, digits, "_", "-" and "."',
                     doc="prefix of the shot names (default: the sweep file's stem)"),
     "samples": Number(integer=True, ge=1, le=MAX_SHOTS,
                        doc="random draws per grid point (default 1)"),
     "seed": Number(integer=True, ge=0, le=2**63 - 1, what="an integer >= 0",
                     doc="seed of the random draws (default 0)"),
     "grid": _ParamMap(Array(_Any(), min_items=1, as_list=True, what="an array of values"),
                       PARAM_PATTERN, _PARAM_WHAT,
                       doc="every combination of these values (a cartesian product)"),
     "random": _ParamMap(_DISTRIBUTION, PARAM_PATTERN, _PARAM_WHAT,
                         doc="values drawn independently for every shot"),
     "output": Table(
         {"dir": String(doc="where `wiggly batch` writes, relative to the sweep file"),
          "paths": Array(String(pattern=OUTPUT_PATTERN,
                                  what="a file name ending in " + ", ".join(OUTPUT_EXTENSIONS)),
                          unique=True, as_list=True,
                          doc="files written into every shot's folder")},
         doc="where the shots go and what each writes")},
    required=("base",), what="a TOML document")


def sweep_schema() -> dict:
    """The JSON Schema (draft 2020-12) of sweep files, generated from the validator's specs.
    It checks the structure; parameter paths and values are checked against the scene format
    and the base scene by :func:`load_sweep`."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": "wiggly sweep",
            "description": "A wiggly sweep file (TOML): see docs/sweep-format.md.",
            **_SWEEP.schema()}


# ----------------------------------------------------------------------------------------------
# parameters: key paths into the scene


@dataclass(frozen=True)
class Param:
    """A parameter of a sweep: its path as written, the steps into the scene's dict (keys and
    list indices), the scene format's spec of its value, the keys it replaces, and the value
    a missing vector starts from (for a component)."""

    path: str
    steps: tuple[str | int, ...]
    spec: Spec
    drop: tuple[str, ...] = ()  # keys of the table ``steps[:drop_at]`` that this replaces
    drop_at: int = 0
    fill: tuple | None = None

    @property
    def numeric(self) -> bool:
        return isinstance(self.spec, Number | Vector)

    @property
    def integer(self) -> bool:
        return isinstance(self.spec, Number) and self.spec.integer


def _child(spec: Spec, key: str) -> Spec | None:
    if isinstance(spec, Table):
        return spec.keys.get(key)
    if isinstance(spec, Map):
        return spec.item
    if isinstance(spec, ByType):  # a keyframe's position: "rest" or a table
        table = next((s for s in spec.options.values() if isinstance(s, PositionTable)), None)
        return None if table is None else table.all_keys.get(key)
    return None


def _keys_of(spec: Spec) -> list[str]:
    if isinstance(spec, Table):
        return list(spec.keys)
    if isinstance(spec, ByType):
        table = next((s for s in spec.options.values() if isinstance(s, PositionTable)), None)
        return list(table.all_keys) if table else []
    return []


def _position_kind(value) -> str | None:
    if not isinstance(value, dict):
        return None
    kinds = [k for k in ("offset", "absolute") if k in value]
    return kinds[0] if kinds else "rigid"


def resolve_param(path: str, base: dict, label: str) -> Param:
    """The :class:`Param` of ``path`` in the base scene's dict ``base``; raises
    :class:`WigglyInputError` (``label: ...``) when the scene format has no such key or the
    base scene lacks what it refers to."""
    steps: list[str | int] = []
    spec: Spec = SCENE_FORMAT
    node: Any = base
    drop: tuple[str, ...] = ()
    drop_at = 0
    fill = None
    where = ""
    parts = _split(path)
    for n, part in enumerate(parts):
        m = _STEP.fullmatch(part)
        if m is None:
            raise WigglyInputError(f"{label}: {_PARAM_WHAT}")
        key, bracket = m.group(1), m.group(2)
        last_key = n == len(parts) - 1 and bracket is None
        if n == 0 and key in FIXED_ROOTS:
            raise WigglyInputError(f"{label}: [{key}] cannot be varied by a sweep (the batch "
                                   "writes each shot's outputs into its folder); vary the "
                                   "material, damping, simulation, time, groups or keyframes")
        child = _child(spec, key)
        if child is None:
            allowed = _keys_of(spec)
            if where == "keyframes" and isinstance(spec, Array):
                raise WigglyInputError(f"{label}: keyframes is an array; pick a keyframe by "
                                       "index or name: keyframes[2] or keyframes[take-off]")
            if not allowed:
                raise WigglyInputError(f"{label}: {where or 'the scene'} takes no key "
                                       f"{key!r}; vary it whole")
            raise WigglyInputError(f"{label}: {unknown_key(key, where, allowed)}")
        if isinstance(spec, Map) and (not isinstance(node, dict) or key not in node):
            names = ", ".join(node) if isinstance(node, dict) and node else "none"
            if not last_key:
                raise WigglyInputError(f"{label}: the base scene has no {where} {key!r}; "
                                       f"its {where} are: {names}")
        replaced = _replaced(spec, key, node, label, where, last_key)
        if replaced:
            drop, drop_at = replaced, len(steps)
        where = f"{where}.{key}" if where else key
        if isinstance(node, str) and isinstance(spec, ByType):
            node = {}  # "rest" is an offset of 0, a rigid target with no rotation
        node = node.get(key) if isinstance(node, dict) else None
        steps.append(key)
        spec = child
        if bracket is not None:
            node, index, spec, fill = _index(spec, node, bracket, label, where, key, parts, n)
            steps.append(index)
            where = f"{where}[{bracket}]"
    return Param(path, tuple(steps), spec, drop, drop_at, fill)


def _split(path: str) -> list[str]:
    """Split at dots outside brackets (keyframe names may contain dots)."""
    parts, depth, cur = [], 0, ""
    for c in path:
        depth += c == "["
        depth -= c == "]"
        if c == "." and depth == 0:
            parts.append(cur)
            cur = ""
        else:
            cur += c
    return [*parts, cur]


def _replaced(spec: Spec, key: str, node, label: str, where: str, last: bool) -> tuple:
    """Keys of the same table that setting ``key`` replaces (``end`` replaces ``duration``, a
    group's ``sphere`` its ``box``); an error when a path below ``key`` would mix them."""
    if isinstance(spec, ByType):
        kind = "offset" if key == "offset" else "absolute" if key == "absolute" else "rigid"
        have = _position_kind(node)
        if have is not None and have != kind:
            raise WigglyInputError(
                f"{label}: {where} is {'an' if have[0] in 'ao' else 'a'} {have} target in the "
                f"base scene; a sweep may vary its {have} keys, or replace the whole position "
                f'(e.g. "{where}" = [...])')
        return ()
    if not isinstance(spec, Table) or not isinstance(node, dict):
        return ()
    out = [b for a, b in spec.exclusive if a == key] + [a for a, b in spec.exclusive if b == key]
    if key in spec.one_of:
        others = [k for k in spec.one_of if k != key and k in node]
        if others and not last:
            raise WigglyInputError(f"{label}: {where} has a {others[0]} selector in the base "
                                   f"scene, not {key}; vary {where}.{others[0]}, or replace "
                                   f'the selector whole ("{where}.{key}" = [...])')
        out += others
    return tuple(out)


def _index(spec: Spec, node, bracket: str, label: str, where: str, key: str, parts, n):
    """A ``[...]`` step: a keyframe by index or name, or a component of a vector."""
    if isinstance(spec, Array) and key == "keyframes" and n == 0:
        frames = node if isinstance(node, list) else []
        if bracket.isdigit():
            index = int(bracket)
            if index >= len(frames):
                raise WigglyInputError(f"{label}: the base scene has {len(frames)} keyframes "
                                       f"(keyframes[0] .. keyframes[{len(frames) - 1}])")
        else:
            hits = [j for j, k in enumerate(frames) if k.get("name") == bracket]
            if len(hits) != 1:
                names = sorted({k["name"] for k in frames if k.get("name")})
                why = ("is not a keyframe name" if not hits else
                       f"names {len(hits)} keyframes ({', '.join(map(str, hits))}); use an "
                       "index")
                raise WigglyInputError(f"{label}: {bracket!r} {why}; keyframe names are: "
                                       f"{', '.join(names) or 'none'} (or use keyframes[index])")
            index = hits[0]
        return frames[index], index, spec.item, None
    if isinstance(spec, Vector):
        if not (bracket.isdigit() and int(bracket) < spec.n):
            raise WigglyInputError(f"{label}: {where} has {spec.n} components; index them "
                                   f"[0] .. [{spec.n - 1}]")
        fill = None
        if node is None:
            if key not in _ZERO_DEFAULT:
                raise WigglyInputError(f"{label}: {where} is not set in the base scene; vary "
                                       "the whole vector")
            fill = (0.0,) * spec.n
        return None, int(bracket), spec.item, fill
    raise WigglyInputError(f"{label}: {where} takes no index; vary it whole")


def apply_param(d: dict, param: Param, value) -> None:
    """Set ``param`` to ``value`` in a scene's dict (in place)."""
    node: Any = d
    for j, step in enumerate(param.steps):
        if j == param.drop_at:
            for key in param.drop:
                node.pop(key, None)
        if j == len(param.steps) - 1:
            node[step] = value
            return
        child = node[step] if not isinstance(node, dict) or step in node else None
        if isinstance(child, str) or child is None:  # "rest" or a missing table / vector
            fill = isinstance(param.steps[j + 1], int) and param.fill
            child = list(param.fill) if fill else {}
            node[step] = child
        node = child


# ----------------------------------------------------------------------------------------------
# the sweep


@dataclass(frozen=True)
class Distribution:
    """How a random parameter is drawn: ``kind`` in :data:`DISTRIBUTIONS` and its arguments
    (``[low, high]`` or the choices), as TOML values."""

    kind: str
    args: tuple

    def draw(self, rng: np.random.Generator):
        if self.kind == "choice":
            return copy.deepcopy(self.args[int(rng.integers(len(self.args)))])
        lo, hi = (np.asarray(a, dtype=float) for a in self.args)
        if self.kind == "integers":
            return int(rng.integers(int(lo), int(hi) + 1))
        if self.kind == "log_uniform":
            x = np.exp(rng.uniform(np.log(lo), np.log(hi)))
        else:
            x = rng.uniform(lo, hi)
        x = np.asarray(x)
        return x.tolist() if x.ndim else float(x)


@dataclass
class Sweep:
    """A checked sweep file: the base scene, the grid (cartesian product, file order, the
    last key fastest) and the random parameters, drawn ``samples`` times per grid point."""

    source: Path
    base: Scene
    name: str
    seed: int = 0
    samples: int = 1
    grid: dict[str, list] = field(default_factory=dict)
    random: dict[str, Distribution] = field(default_factory=dict)
    params: dict[str, Param] = field(default_factory=dict)
    outputs: tuple[str, ...] | None = None
    out_dir: Path | None = None

    def where(self) -> str:
        try:
            return str(self.source.relative_to(Path.cwd()))
        except ValueError:
            return str(self.source)

    @property
    def n_grid(self) -> int:
        return math.prod(len(v) for v in self.grid.values())

    def __len__(self) -> int:
        return self.n_grid * self.samples

    def values(self, i: int) -> tuple[int, dict[str, Any]]:
        """Shot ``i``'s sample number and parameter values.  Shots run sample by sample
        (``i = sample * n_grid + grid point``), so raising ``samples`` keeps the earlier
        shots; each parameter of a sample draws from its own stream, seeded by (seed, sample,
        parameter path), so adding a parameter leaves the others' draws alone."""
        sample, g = divmod(i, self.n_grid)
        sizes = [len(v) for v in self.grid.values()]
        values: dict[str, Any] = {}
        for (path, options), k in zip(self.grid.items(), _unravel(g, sizes), strict=True):
            values[path] = copy.deepcopy(options[k])
        for path, dist in self.random.items():
            rng = np.random.default_rng([self.seed, sample, zlib.crc32(path.encode())])
            values[path] = dist.draw(rng)
        return sample, values

    @cached_property
    def _base_dict(self) -> dict:
        return scene_to_dict(self.base)

    def scene(self, values: dict[str, Any], label: str, name: str | None = None) -> Scene:
        """The base scene with ``values`` set, checked (raises :class:`WigglyInputError`,
        naming ``label``); ``name`` names it in later messages (:meth:`Scene.where`)."""
        d = copy.deepcopy(self._base_dict)
        for path, value in values.items():
            apply_param(d, self.params[path], value)
        scene = scene_from_dict(d, where=label, source=self.base.source)
        return scene if name is None else replace(scene, label=name)


def _unravel(g: int, sizes: list[int]) -> list[int]:
    out = []
    for s in reversed(sizes):
        g, k = divmod(g, s)
        out.append(k)
    return out[::-1]


def _is_sweep_file(path: Path) -> bool:
    try:
        return is_sweep(read_toml(path))
    except WigglyInputError:
        return False


def is_sweep(data: dict) -> bool:
    """A TOML document is a sweep when it names a base scene."""
    return "base" in data


def load_sweep(path: str | os.PathLike[str]) -> Sweep:
    """Read and check a sweep file (and its base scene); every problem raises one
    :class:`WigglyInputError` listing all problems found (file, key, value, what is
    allowed)."""
    path = Path(path)
    return sweep_from_dict(read_toml(path), where=str(path), source=path.resolve())


def read_toml(path: Path) -> dict:
    """A TOML file's content; unreadable files raise :class:`WigglyInputError`."""
    if not path.is_file():
        raise WigglyInputError(f"{path}: no such file" if not path.exists() else
                               f"{path}: is not a file")
    return read_valid_toml(path)


def sweep_from_dict(data: dict, where: str, source: Path) -> Sweep:
    """Check a parsed sweep file (structure, the base scene, parameters, values) and build
    the :class:`Sweep`; ``source`` is the sweep file (relative paths resolve against its
    directory)."""
    from wiggly.scene import load_scene

    p = Problems(where)
    try:
        d = _SWEEP.parse(data, "", p)
    except Bad:  # the file's own problems, said with the base scene's (below)
        d = None
    name = data.get("base") if d is None else d["base"]
    base = None
    if isinstance(name, str):
        base_path = (source.parent / Path(name).expanduser()).resolve()
        try:
            base = load_scene(base_path)
        except WigglyInputError as err:
            if _is_sweep_file(base_path):
                p.add(f"base = {show(name)} is a sweep file; a sweep's base is a scene file "
                      "(give that sweep's own base, and its [grid] and [random] here)")
            else:
                p.add(f"base = {show(name)}: the base scene is not valid:\n{err}"
                      if base_path.is_file() else
                      f"base = {show(name)}: no such scene file ({base_path})")
    p.raise_if_any()
    if d is None or base is None:  # pragma: no cover - their problems were raised above
        raise WigglyInputError(f"{where}: the sweep file could not be read")
    base_dict = scene_to_dict(base)
    params: dict[str, Param] = {}
    grid, random = d.get("grid", {}), d.get("random", {})
    for table, entries in (("grid", grid), ("random", random)):
        for key in entries:
            label = f'{table}."{key}"'
            if key in params:
                p.add(f"{label} is also in [grid]; vary a parameter in one table only")
                continue
            try:
                params[key] = resolve_param(key, base_dict, label)
            except WigglyInputError as err:
                p.add(str(err))
    for key, values in grid.items():
        if key in params:
            for j, v in enumerate(values):
                _check_value(params[key], v, f'grid."{key}"[{j}]', p)
        seen: dict[str, int] = {}
        for j, v in enumerate(values):
            text = json.dumps(v, sort_keys=True)
            if text in seen:
                p.add(f'grid."{key}"[{j}] = {show(v)} repeats grid."{key}"[{seen[text]}]: it '
                      "would make identical shots; give each value once")
                break
            seen[text] = j
    dists = {}
    for key, table in random.items():
        if key in params and key not in grid:
            dists[key] = _check_distribution(params[key], table, f'random."{key}"', p)
    samples = d.get("samples")
    if random and samples is None:
        p.add("samples is missing; a sweep with [random] draws samples shots per grid point: "
              "give samples = N")
    if not random and samples not in (None, 1):
        p.add(f"samples = {samples} would repeat identical shots: without [random] every "
              "sample is the same; remove samples or add a [random] table")
    if not grid and not random:
        p.add("the sweep varies nothing: give the parameters to vary in [grid] (e.g. "
              '"material.young" = [1e5, 3e5]) or [random]; to run the base scene alone, use '
              "wiggly animate")
    samples = samples or 1
    n_grid = math.prod(len(v) for v in grid.values())
    if n_grid * samples > MAX_SHOTS:
        p.add(f"the sweep makes {n_grid * samples} shots ({n_grid} grid points x {samples} "
              f"samples), more than {MAX_SHOTS} (wiggly.limits.MAX_SHOTS); split it")
    out = d.get("output", {})
    outputs = None
    if "paths" in out:
        outputs = tuple(out["paths"])
        for j, name in enumerate(outputs):
            if Path(name).name != name or name in RESERVED_NAMES:
                why = ("must be a file name, without folders: every shot writes into its own "
                       "folder" if Path(name).name != name else
                       f"is a name the batch uses itself ({', '.join(RESERVED_NAMES)})")
                p.add(f"output.paths[{j}] = {show(name)} {why}")
    out_dir = (source.parent / Path(out["dir"]).expanduser()) if "dir" in out else None
    if out_dir is not None and out_dir.exists() and not out_dir.is_dir():
        p.add(f"output.dir = {show(out['dir'])}: {out_dir} is a file; give a folder for the "
              "batch's outputs")
    p.raise_if_any()
    return Sweep(source, base, d.get("name", source.stem), int(d.get("seed", 0)), samples,
                 {k: list(v) for k, v in grid.items()}, dists, params, outputs, out_dir)


def _check_value(param: Param, value, label: str, p: Problems) -> bool:
    try:
        param.spec.parse(value, label, p)
    except Bad:
        return False
    return True


def _check_distribution(param: Param, table: dict, label: str, p: Problems):
    kind = next(k for k in DISTRIBUTIONS if k in table)
    args = table[kind]
    at = f"{label}.{kind}"
    if kind == "choice":
        ok = all([_check_value(param, v, f"{at}[{j}]", p) for j, v in enumerate(args)])
        return Distribution(kind, tuple(args)) if ok else None
    if not param.numeric:
        p.add(f"{at}: {param.path} is {param.spec.what}, not a number or vector; draw it "
              "with choice = [...]")
        return None
    if (kind == "integers") != param.integer:
        p.add(f"{at}: {param.path} is {param.spec.what}; use "
              + ("integers = [low, high]" if param.integer else "uniform or log_uniform"))
        return None
    if not all([_check_value(param, v, f"{at}[{j}]", p) for j, v in enumerate(args)]):
        return None
    lo, hi = (np.atleast_1d(np.asarray(a, dtype=float)) for a in args)
    if np.any(lo > hi):
        p.add(f"{at} = {show(list(args))}: low exceeds high"
              + (f" in component {int(np.argmax(lo > hi))}" if lo.size > 1 else ""))
        return None
    if kind == "log_uniform" and np.any(lo <= 0):
        p.add(f"{at} = {show(list(args))}: log_uniform needs low > 0 (use uniform to include "
              "0 or negative values)")
        return None
    return Distribution(kind, tuple(args))
