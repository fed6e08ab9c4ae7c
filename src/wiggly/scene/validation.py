"""The validation framework of scene files: one description per key drives both the
checks (with messages naming the file, key and value) and the JSON Schema."""

from __future__ import annotations

import difflib
import json
import math
import re
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

from wiggly.errors import WigglyInputError
from wiggly.scene.spec import Absolute, Offset, Rigid

# ----------------------------------------------------------------------------------------------
# specs: one description drives the validator and the JSON Schema


class Bad(Exception):
    """Raised inside the validator: one problem, already recorded."""


class Problems:
    """Collects the problems of one file; messages are prefixed with the file name."""

    def __init__(self, where: str):
        self.where = where
        self.items: list[str] = []

    def add(self, message: str) -> None:
        self.items.append(message)

    def bad(self, message: str) -> Bad:
        self.add(message)
        return Bad(message)

    def raise_if_any(self) -> None:
        if self.items:
            raise input_error(self.where, self.items)

    def parse(self, spec: Any, data: Any) -> Any:
        """``spec`` applied to a whole file's ``data``, its problems collected here; raises
        them when parsing could not go on."""
        try:
            return spec.parse(data, "", self)
        except Bad:
            self.raise_if_any()
            raise


def input_error(where: str, messages: list[str]) -> WigglyInputError:
    err = WigglyInputError("\n".join(f"{where}: {m}" for m in messages))
    err.problems = list(messages)
    return err


def did_you_mean(name: str, names) -> str:
    """`` (did you mean 'x'?)`` for the closest of ``names`` to a misspelt ``name``, or ""."""
    close = difflib.get_close_matches(name, list(names), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def missing_file(field: str, text: str, found: Path) -> str:
    """What to say of a path ``text`` given at ``field`` that resolved to ``found``, which is
    not a file; a Windows path (backslashes) is told to use "/", which works everywhere."""
    why = "is a directory" if found.is_dir() else "no such file"
    hint = ""
    if "\\" in text:
        hint = '; scene files separate folders with "/" on every system'
        if Path(str(found).replace("\\", "/")).exists():
            hint += f" ({show(text.replace(chr(92), '/'))} exists)"
    return f"{field} = {show(text)}: {why} ({found}){hint}"


def show(value: Any, limit: int = 60) -> str:
    """A value as it would be written in TOML (shortened)."""
    if isinstance(value, bool):
        s = "true" if value else "false"
    elif isinstance(value, str):
        s = json.dumps(value, ensure_ascii=False)
    elif isinstance(value, float):
        s = "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") \
            if math.isinf(value) else repr(value)
    elif isinstance(value, list | tuple):
        s = "[" + ", ".join(show(v, limit) for v in value) + "]"
    elif isinstance(value, dict):
        s = ("{ " + ", ".join(f"{k} = {show(v, limit)}" for k, v in value.items()) + " }"
             if value else "{}")
    else:
        s = str(value)
    if len(s) <= limit:
        return s
    if isinstance(value, str):  # keep the end too: a long path's file name
        head = limit // 3
        return s[:head] + " ... " + s[len(s) - (limit - head - 5):]
    return s[: limit - 4] + " ..."


def _num(x: float) -> str:
    if float(x).is_integer() and abs(x) < 1e7:
        return repr(int(x))
    return f"{float(x):.12g}" if abs(x) >= 1e7 else repr(float(x))


class Spec(ABC):
    what = "a value"

    @abstractmethod
    def parse(self, value: Any, path: str, p: Problems) -> Any:
        """Validate ``value`` at key ``path``; record problems in ``p``."""

    @abstractmethod
    def schema(self) -> dict:
        """The JSON Schema of this spec."""

    def fail(self, value, path: str, p: Problems) -> Bad:
        return p.bad(f"{path} = {show(value)} must be {self.what}")


class Number(Spec):
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


class Bool(Spec):
    what = "true or false"

    def __init__(self, doc: str = ""):
        self.doc = doc

    def parse(self, value, path, p):
        if not isinstance(value, bool):
            raise self.fail(value, path, p)
        return value

    def schema(self):
        return _described({"type": "boolean"}, self.doc)


class String(Spec):
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


class Vector(Spec):
    """A fixed-length array of finite numbers -> tuple of floats (or of ints)."""

    def __init__(self, n: int = 3, names: str = "x, y, z", unit: str = "", doc: str = "",
                 item: Number | None = None, what: str | None = None):
        self.n, self.doc = n, doc
        self.item = item or Number()
        self.what = what or (f"an array of {n} numbers [{names}]" + (f" ({unit})" if unit else ""))

    def parse(self, value, path, p):
        if not (isinstance(value, list) and len(value) == self.n):
            raise self.fail(value, path, p)
        try:
            return tuple(self.item.parse(x, path, Problems("")) for x in value)
        except Bad:
            raise self.fail(value, path, p) from None

    def schema(self):
        return _described({"type": "array", "items": self.item.schema(), "minItems": self.n,
                           "maxItems": self.n}, self.doc)


class Array(Spec):
    """An array of items -> tuple (or list) of parsed items."""

    def __init__(self, item: Spec, *, min_items: int = 0, unique: bool = False,
                 what: str | None = None, doc: str = "", as_list: bool = False):
        self.item, self.min_items, self.unique, self.doc = item, min_items, unique, doc
        self.as_list = as_list
        self.what = what or f"an array of {item.what}"

    def parse(self, value, path, p):
        if not isinstance(value, list):
            raise self.fail(value, path, p)
        if len(value) < self.min_items:
            raise p.bad(f"{path} = {show(value)} must have at least {self.min_items} "
                        f"item{'s' if self.min_items > 1 else ''}")
        out, failed = [], False
        for i, v in enumerate(value):
            try:
                out.append(self.item.parse(v, f"{path}[{i}]", p))
            except Bad:
                failed = True
        if failed:
            raise Bad(path)
        if self.unique:
            seen: dict = {}
            for i, v in enumerate(out):
                if v in seen:
                    raise p.bad(f"{path}[{i}] = {show(value[i])} repeats {path}[{seen[v]}]; "
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


class Table(Spec):
    """A table with known keys.

    ``one_of``: exactly one of these keys; ``any_of``: at least one; ``exclusive``: pairs
    that may not appear together; ``make`` builds the result from the parsed keys.
    """

    def __init__(self, keys: dict[str, Spec], *, required: tuple[str, ...] = (),
                 make: Callable[[dict], Any] = dict, one_of: tuple[str, ...] = (),
                 any_of: tuple[str, ...] = (), exclusive: tuple[tuple[str, str], ...] = (),
                 check: Callable[[dict, str, Problems], None] | None = None,
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
                p.add(unknown_key(k, path, self.keys))
                failed = True
                continue
            try:
                out[k] = self.keys[k].parse(v, _join(path, k), p)
            except Bad:
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
            raise Bad(path)
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


class Map(Spec):
    """A table of named items (``[groups.<name>]``)."""

    def __init__(self, item: Spec, key_pattern: str, key_what: str, doc: str = ""):
        self.item, self.key_pattern, self.key_what, self.doc = item, key_pattern, key_what, doc
        self.what = "a table of named items"

    def parse(self, value, path, p):
        if not isinstance(value, dict):
            raise self.fail(value, path, p)
        out, failed = {}, False
        for k, v in value.items():
            if not re.search(self.key_pattern, k):
                p.add(f"{self.key_path(path, k)}: {self.key_what}")
                failed = True
                continue
            try:
                out[k] = self.item.parse(v, self.item_path(path, k), p)
            except Bad:
                failed = True
        if failed:
            raise Bad(path)
        return out

    def key_path(self, path: str, key: str) -> str:
        """Where a key that is not allowed is reported (quoted: it may hold anything)."""
        return f"{path}.{json.dumps(key)}"

    def item_path(self, path: str, key: str) -> str:
        """Where the problems of an item are reported."""
        return f"{path}.{key}"

    def schema(self):
        return _described({"type": "object", "propertyNames": {"pattern": self.key_pattern},
                           "additionalProperties": self.item.schema()}, self.doc)


class ByType(Spec):
    """One of several specs, chosen by the value's TOML type (string, array or table)."""

    def __init__(self, options: dict[type, Spec], what: str, doc: str = ""):
        self.options, self.what, self.doc = options, what, doc

    def parse(self, value, path, p):
        for kind, spec in self.options.items():
            if isinstance(value, kind) and not isinstance(value, bool):
                n = len(p.items)
                try:
                    return spec.parse(value, path, p)
                except Bad:
                    if not isinstance(spec, String):
                        raise
                    del p.items[n:]  # say what every alternative allows
                    raise self.fail(value, path, p) from None
        raise self.fail(value, path, p)

    def schema(self):
        return _described({"oneOf": [s.schema() for s in self.options.values()]}, self.doc)


class Const(String):
    def __init__(self, value: str, result: Any, what: str, doc: str = ""):
        super().__init__(enum=(value,), doc=doc)
        self.result, self.what = result, what

    def parse(self, value, path, p):
        super().parse(value, path, p)
        return self.result


class PositionTable(Spec):
    """``{ offset = ... }`` | ``{ absolute = ... }`` | ``{ rotation, translation, center }``."""

    what = ('"rest" or a table with offset, absolute, or rotation/translation '
            "(and optional center)")

    def __init__(self):
        self.vec = Vector(3, unit="m")
        self.kinds = {
            "offset": {"offset": Vector(3, "dx, dy, dz", "m",
                                         doc="displacement from rest (m) of every vertex")},
            "absolute": {"absolute": Array(Vector(3, unit="m"), min_items=1,
                                            what="an array of [x, y, z] rows, one per vertex",
                                            doc="target positions (m), one row per group vertex "
                                                "in group order")},
            "rigid": {"rotation": Vector(3, "rx, ry, rz", "degrees",
                                          doc="Euler angles in degrees, applied X then Y then Z "
                                              "(fixed axes)"),
                      "translation": Vector(3, "tx, ty, tz", "m", doc="translation (m)"),
                      "center": Vector(3, "cx, cy, cz", "m",
                                        doc="center of rotation (m); default: group centroid")},
        }
        self.all_keys = {k: s for kinds in self.kinds.values() for k, s in kinds.items()}

    def parse(self, value, path, p):
        out, failed = {}, False
        for k, v in value.items():
            if k not in self.all_keys:
                p.add(unknown_key(k, path, self.all_keys))
                failed = True
                continue
            try:
                out[k] = self.all_keys[k].parse(v, _join(path, k), p)
            except Bad:
                failed = True
        if failed:
            raise Bad(path)
        kinds = [kind for kind, keys in self.kinds.items() if any(k in value for k in keys)]
        if len(kinds) != 1:
            raise p.bad(f"{path} = {show(value)} must be {self.what}"
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


def unknown_key(key: str, path: str, allowed) -> str:
    where = f"in [{path}]" if path and "[" not in path else f"in {path}" if path else \
        "at the top level"
    close = difflib.get_close_matches(key, list(allowed), n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"allowed keys: {', '.join(allowed)}"
    return f"unknown key {key!r} {where}; {hint}"
