"""Writing scenes back: a dict of every key that has a value, and TOML text (an exact round
trip with :func:`wiggly.scene.load_scene`)."""

from __future__ import annotations

import os
import tomllib
from dataclasses import fields
from pathlib import Path
from typing import Any

import tomli_w

from wiggly.errors import WigglyInputError
from wiggly.files import atomic_file
from wiggly.scene.schema import scene_from_dict
from wiggly.scene.spec import (
    FORMAT,
    SELECTOR_KEYS,
    Absolute,
    Box,
    GroupSpec,
    Indices,
    KeyframeSpec,
    Nearest,
    Offset,
    Rest,
    Rigid,
    Scene,
    Sphere,
)

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
    if scene.drive is not None:
        drive = _fields(scene.drive)
        if not isinstance(drive["group"], str):
            drive["group"] = list(drive["group"])
        if "range" in drive:
            drive["range"] = list(drive["range"])
        if isinstance(drive.get("animation"), tuple):
            drive["animation"] = list(drive["animation"])
        d["drive"] = drive
    return d


def _fields(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in fields(obj) if getattr(obj, f.name) is not None}


def _group_to_dict(g: GroupSpec) -> dict:
    sel = g.selector
    key = SELECTOR_KEYS[type(sel)]
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
    if g.young is not None:
        d["young"] = g.young
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
    """``header`` and ``key = value`` lines; long inline tables become sub-tables, and long
    arrays are wrapped: numbers packed into lines of 100 characters, other items one per
    line."""
    lines, subtables = [header] if header else [], []
    for k, v in table.items():
        text = f"{k} = {_toml_value(v)}"
        if len(text) <= 100:
            lines.append(text)
        elif isinstance(v, dict):
            subtables.append((k, v))
        elif isinstance(v, list):
            lines.append(f"{k} = [")
            if all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
                row = ""  # numbers (a group's indices): packed into lines of 100 characters
                for x in v:
                    item = f"{_toml_value(x)},"
                    if row and len(row) + len(item) + 1 > 100:
                        lines.append(row)
                        row = ""
                    row = f"{row} {item}" if row else f"    {item}"
                lines.append(row)
            else:
                lines += [f"    {_toml_value(x)}," for x in v]
            lines.append("]")
        else:
            lines.append(text)
    for k, v in subtables:
        name = header.strip("[]")
        lines += ["", *_toml_lines(v, f"[{name}.{k}]")]
    return lines


def scene_to_toml(scene: Scene) -> str:
    """The scene as fresh TOML text (:func:`merged_toml` keeps an existing file's comments)."""
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
    if "drive" in d:
        lines += ["", *_toml_lines(d["drive"], "[drive]")]
    lines += ["", *_toml_lines(d["output"], "[output]")]
    return "\n".join(lines) + "\n"


def merged_toml(scene: Scene, original: str) -> str | None:
    """The TOML text ``original`` (a scene file) updated to ``scene`` with tomlkit, keeping its
    comments, layout and formatting wherever a key keeps its value: changed values are
    replaced, keys the scene dropped are removed, and keys it adds are appended to their table
    (not the defaults the original left out).  None when ``original`` is no scene or the
    update does not load back as exactly ``scene`` (the caller then writes it afresh)."""
    import tomlkit

    try:
        doc = tomlkit.parse(original)
        before = scene_to_dict(scene_from_dict(tomllib.loads(original), where="original"))
    except (tomlkit.exceptions.TOMLKitError, tomllib.TOMLDecodeError, WigglyInputError):
        return None
    try:
        _merge(doc, scene_to_dict(scene), before)
        text = tomlkit.dumps(doc)
        again = scene_from_dict(tomllib.loads(text), where="merged")
    except (tomlkit.exceptions.TOMLKitError, tomllib.TOMLDecodeError, WigglyInputError,
            TypeError, ValueError):
        return None
    return text if again == scene else None


def _fresh(value: Any, nested: bool) -> Any:
    """A value for tomlkit written as :func:`scene_to_toml` would: tables inside a section or
    a keyframe inline, keyframes as an array of tables (a plain dict would become a
    ``[keyframes.position]`` sub-table)."""
    import tomlkit

    if isinstance(value, dict):
        if not nested:
            return value  # a section: a table of its own
        out = tomlkit.inline_table()
        out.update({k: _fresh(v, True) for k, v in value.items()})
        return out
    if isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        out = tomlkit.aot()
        for item in value:
            t = tomlkit.table()
            t.update({k: _fresh(v, True) for k, v in item.items()})
            out.append(t)
        return out
    return value


def _merge(table, new: dict, before: dict, nested: bool = False) -> None:
    """Update the tomlkit ``table`` in place to ``new`` (a :func:`scene_to_dict` level), with
    ``before`` the same level of the scene the table held (``nested``: below a section)."""
    import tomlkit

    for key in [k for k in table if k not in new]:
        del table[key]
    for key, value in new.items():
        if key in table:
            old = table[key]
            mine = old.unwrap() if hasattr(old, "unwrap") else old
            if mine == value:
                continue  # unchanged: its formatting and comments stay
            if isinstance(value, dict) and isinstance(old, tomlkit.items.InlineTable) \
                    and set(old) != set(value):  # another kind (an offset made a turn):
                table[key] = _fresh(value, True)  # written afresh, not patched key by key
                continue
            if isinstance(value, dict) and hasattr(old, "items"):
                _merge(old, value, before.get(key, {}) if isinstance(before, dict) else {},
                       True)
                continue
            if (isinstance(value, list) and value and all(isinstance(v, dict) for v in value)
                    and isinstance(old, list) and len(old) == len(value)
                    and all(hasattr(o, "items") for o in old)):
                was = before.get(key) if isinstance(before, dict) else None
                for j, (o, v) in enumerate(zip(old, value, strict=True)):
                    _merge(o, v, was[j] if isinstance(was, list) and j < len(was) else {}, True)
                continue
            table[key] = _fresh(value, nested)
        elif not (isinstance(before, dict) and before.get(key) == value):
            table[key] = _fresh(value, nested)  # new, not a default the original left out


def save_scene(scene: Scene, path: str | os.PathLike[str], overwrite: bool = False) -> Path:
    """Check ``scene`` and write it as TOML, atomically; ``load_scene`` gives it back exactly.

    Paths are written as they are in the scene (relative paths are relative to the directory
    of the file written).  An existing file is an error unless ``overwrite``; overwriting a
    scene file keeps its comments and layout where keys keep their values
    (:func:`merged_toml`).
    """
    path = Path(path)
    text = scene_to_toml(scene)
    if overwrite and path.is_file():
        try:
            original = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            original = None
        text = (merged_toml(scene, original) if original is not None else None) or text
    again = scene_from_dict(tomllib.loads(text), where=str(path))  # validates, too
    if again != scene:  # pragma: no cover - a bug in the writer
        raise AssertionError(f"scene does not survive the TOML round trip: {scene} != {again}")
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    if path.is_dir():
        raise WigglyInputError(f"{path} is a directory")
    with atomic_file(path, durable=True) as tmp:  # on the disk before the editor drops
        tmp.write_text(text, encoding="utf-8")  # its autosave and journal
    return path
