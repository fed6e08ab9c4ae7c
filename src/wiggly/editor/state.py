"""The editor's state and its edits, as small pure functions on :class:`wiggly.scene.Scene`.

The server holds one :class:`EditorState` (a scene plus stable keyframe ids) and the undo
histories of the tabs (:mod:`wiggly.editor.history`).  Every edit the browser sends is a JSON
object ``{"op": <name>, ...}``; :func:`apply_edit` checks it and returns a *new* state, going
through the scene's own dict form (:func:`wiggly.scene.scene_to_dict` /
:func:`scene_from_dict`), so an edit can never produce a scene that the CLI would not read
back.  An invalid edit raises
:class:`EditError` (an HTTP 400 for the server) and leaves the state untouched.

Operations (fields in brackets are optional):

==================  ==========================================================================
``set_group``       ``name, indices [, color, on]``: create or replace a group of vertices
``rename_group``    ``name, new_name``: also renames it in keyframes and fixed groups
``recolor_group``   ``name, color`` ("#rrggbb")
``set_group_young`` ``name, young``: the group's own Young's modulus (Pa; ``null``: none)
``delete_group``    ``name``: also deletes its keyframes and its fixed entry
``set_fixed``       ``name, fixed`` (bool): hold the group's vertices at rest or not
``add_keyframe``    ``time, group [, position, velocity, stiffness, c_A, c_B, name]``
``update_keyframe`` ``id`` and any of the fields above (``velocity: null`` removes it)
``delete_keyframe`` ``id``
``set``             ``section`` (material, damping, simulation, time, mesh, output, drive) and
                    ``values``: a table of that section's keys (``null`` removes a key)
``batch``           ``ops``: a list of the edits above, applied in order as one step (one
                    undo): pasting keyframes, keying several groups at once
==================  ==========================================================================

Sizes are bounded as for scene files (:mod:`wiggly.limits`): a shot of at most
``MAX_DURATION`` seconds and ``MAX_FRAMES`` frames, at most ``MAX_MODES`` modes, a tet
resolution of at most ``MAX_RESOLUTION`` edges along the diagonal (an edge length as short),
``MAX_KEYFRAMES`` keyframes and names of at most ``MAX_NAME_LENGTH`` characters.

Positions are those of the scene format: ``"rest"``, ``{"offset": [...]}``,
``{"absolute": [[...], ...]}`` or ``{"rotation": [...], "translation": [...],
"center": [...]}`` (Euler angles in degrees, X then Y then Z about fixed axes).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from wiggly import limits
from wiggly.checks import brief, finite_number
from wiggly.errors import WigglyInputError
from wiggly.scene import PALETTE, Scene, scene_from_dict, scene_to_dict

__all__ = ["EditError", "EditorState", "apply_edit", "check_limits", "rebased", "rebuild_state",
           "rigid_fit", "state_to_json"]

#: Sections that ``set`` may change, and their keys.
SETTABLE = {
    "material": ("young", "poisson", "density"),
    "damping": ("alpha", "beta"),
    "simulation": ("gravity", "modes", "warp", "lumped_mass", "preroll"),
    "time": ("start", "end", "duration", "fps", "loop"),
    "mesh": ("resolution", "edge_length", "repair", "scale", "up_axis"),
    "output": ("paths", "overwrite", "size", "camera"),
    "drive": ("intensity", "free_modes", "physics"),
}
KEYFRAME_FIELDS = ("time", "group", "position", "velocity", "stiffness", "c_A", "c_B", "name")


class EditError(WigglyInputError):
    """An edit that cannot be applied; ``status`` is the HTTP status the server answers."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class EditorState:
    """One state of the edited scene: the scene and a stable id per keyframe (same order)."""

    scene: Scene
    keyframe_ids: tuple[int, ...] = ()
    next_id: int = 0

    @classmethod
    def of(cls, scene: Scene) -> EditorState:
        n = len(scene.keyframes)
        return cls(scene, tuple(range(n)), n)


# ----------------------------------------------------------------------------------------------
# checks of JSON payloads


def _refuse(message: str) -> NoReturn:
    """Raise the message of a :mod:`wiggly.checks` check as an edit refused (400)."""
    raise EditError(message)


def _need(op: dict, key: str) -> Any:
    if key not in op:
        raise EditError(f"edit {op.get('op')!r} needs the field {key!r}")
    return op[key]


def _string(v: Any, what: str) -> str:
    if not isinstance(v, str):
        raise EditError(f"{what} must be a string; got {brief(v)}")
    return v


def _number(v: Any, what: str) -> float:
    return finite_number(v, what, _refuse)


def _group_name(v: Any) -> str:
    name = _string(v, "group name")
    n = limits.MAX_NAME_LENGTH
    if not re.fullmatch(rf"[A-Za-z0-9_-]{{1,{n}}}", name):
        raise EditError(f"group name {brief(name)} is invalid: use 1 to {n} letters, digits, "
                        "'_' or '-'")
    return name


def _color(v: Any) -> str:
    c = _string(v, "color")
    if not re.fullmatch(r"#[0-9a-fA-F]{6}", c):
        raise EditError(f"color {brief(c)} is invalid: use \"#rrggbb\"")
    return c.lower()


def _indices(v: Any, n_vertices: int | None) -> list[int]:
    if not isinstance(v, list) or not v:
        raise EditError(f"indices must be a non-empty list of vertex indices; got {brief(v)}")
    if not all(isinstance(i, int) and not isinstance(i, bool) for i in v):
        raise EditError("indices must be integers")
    idx = sorted(set(v))
    if idx[0] < 0 or (n_vertices is not None and idx[-1] >= n_vertices):
        bad = idx[0] if idx[0] < 0 else idx[-1]
        raise EditError(f"vertex index {bad} is out of range"
                        + (f": the surface has {n_vertices} vertices" if n_vertices else ""))
    return idx


# ----------------------------------------------------------------------------------------------
# edits


def check_limits(scene: Scene, diagonal: float | None = None) -> None:
    """Refuse sizes beyond those of :mod:`wiggly.limits` (the scene files' bounds) with a
    message naming the value; ``diagonal`` (of the mesh, m) bounds the tet edge length."""
    problems = []
    start, end = scene.time_range()
    t = scene.time
    if end - start > limits.MAX_DURATION:
        problems.append(f"the shot from {start:g} s to {end:g} s lasts {end - start:g} s; the "
                        f"longest shot is {limits.MAX_DURATION:g} s")
    elif t.fps > limits.MAX_FPS:
        problems.append(f"time.fps = {t.fps:g}: at most {limits.MAX_FPS:g} frames per second")
    elif limits.frame_count(end - start, t.fps) > limits.MAX_FRAMES:
        problems.append(f"{end - start:g} s at {t.fps:g} fps is "
                        f"{limits.frame_count(end - start, t.fps)} frames; at most "
                        f"{limits.MAX_FRAMES} (shorten the shot or lower the fps)")
    if scene.simulation.modes > limits.MAX_MODES:
        problems.append(f"simulation.modes = {scene.simulation.modes}: at most "
                        f"{limits.MAX_MODES} modes")
    res = scene.mesh.resolution
    if res is not None and res > limits.MAX_RESOLUTION:
        problems.append(f"mesh.resolution = {res}: at most {limits.MAX_RESOLUTION} tet edges "
                        "along the diagonal")
    edge = scene.mesh.edge_length
    if edge is not None and diagonal is not None and diagonal / edge < limits.MIN_RESOLUTION:
        problems.append(f"mesh.edge_length = {edge:g} m is longer than 1/"
                        f"{limits.MIN_RESOLUTION} of the mesh's {diagonal:.3g} m diagonal, "
                        "coarser than fTetWild can mesh (edge_length <= "
                        f"{diagonal / limits.MIN_RESOLUTION:.3g} m)")
    if edge is not None and diagonal is not None and diagonal / edge > limits.MAX_RESOLUTION:
        problems.append(f"mesh.edge_length = {edge:g} m is {diagonal / edge:.0f} edges along "
                        f"the mesh's {diagonal:.3g} m diagonal; at most "
                        f"{limits.MAX_RESOLUTION} (edge_length >= "
                        f"{diagonal / limits.MAX_RESOLUTION:.3g} m)")
    if len(scene.keyframes) > limits.MAX_KEYFRAMES:
        problems.append(f"{len(scene.keyframes)} keyframes: at most {limits.MAX_KEYFRAMES}")
    names = [("keyframe name", k.name) for k in scene.keyframes] + \
        [("group name", g) for g in scene.groups]
    for what, name in names:
        if len(name) > limits.MAX_NAME_LENGTH:
            problems.append(f"a {what} of {len(name)} characters ({brief(name, 40)}): at most "
                            f"{limits.MAX_NAME_LENGTH}")
            break
    if problems:
        raise EditError("; ".join(problems))


def rebuild_state(state: EditorState, d: dict, ids: tuple[int, ...] | None = None,
                  next_id: int | None = None) -> EditorState:
    """A new state from the scene's dict form, validated like a scene file and bounded as
    one (:func:`check_limits`)."""
    try:
        scene = scene_from_dict(d, where="edit")
    except WigglyInputError as err:
        raise EditError(str(err)) from None
    check_limits(scene)
    scene.source = state.scene.source
    return EditorState(scene, state.keyframe_ids if ids is None else ids,
                       state.next_id if next_id is None else next_id)



def _keyframe_dict(op: dict, base: dict | None = None) -> dict:
    """Keyframe fields of an edit merged into ``base`` (``None`` values remove a field)."""
    d = dict(base or {})
    for key in KEYFRAME_FIELDS:
        if key not in op:
            continue
        v = op[key]
        if v is None:
            if key in ("time", "group"):
                raise EditError(f"keyframe {key} cannot be removed")
            d.pop(key, None)
        elif key == "time":
            d[key] = _number(v, "keyframe time")
        elif key == "group":
            d[key] = _group_name(v)
        else:
            d[key] = v
    return d


@dataclass
class _Draft:
    """An edit in progress: the scene's dict form and its keyframe ids (same order).  Edits
    change a draft; the scene is rebuilt and checked once, after all of them (a batch)."""

    d: dict
    ids: list[int]
    next_id: int

    def key_index(self, kid: Any) -> int:
        if isinstance(kid, bool) or not isinstance(kid, int):
            raise EditError(f"keyframe id must be an integer; got {brief(kid)}")
        try:
            return self.ids.index(kid)
        except ValueError:
            raise EditError("that keyframe was deleted meanwhile (in another tab or by an "
                            f"undo), so this edit of it is not made (keyframe id {kid}; ids "
                            f"are {brief(self.ids)})", 404) from None

    def group(self, name: str) -> dict:
        if name not in self.d["groups"]:
            raise EditError(f"there is no group {name!r}", 404)
        return self.d["groups"][name]


def apply_edit(state: EditorState, op: Any, n_vertices: int | None = None,
               diagonal: float | None = None) -> EditorState:
    """The state after the edit ``op`` (a JSON object, see the module doc).

    ``n_vertices`` (of the surface) bounds group indices, ``diagonal`` (of its bounding box)
    the tet edge length.  Raises :class:`EditError`.
    """
    draft = _Draft(scene_to_dict(state.scene), list(state.keyframe_ids), state.next_id)
    if isinstance(op, dict) and op.get("op") == "batch":
        ops = _need(op, "ops")
        if not isinstance(ops, list) or not ops or len(ops) > limits.MAX_KEYFRAMES:
            raise EditError(f"batch: ops must be a list of 1 to {limits.MAX_KEYFRAMES} edits")
        for i, sub in enumerate(ops):
            try:
                if isinstance(sub, dict) and sub.get("op") == "batch":
                    raise EditError("edits in a batch cannot be batches")
                _apply(draft, sub, n_vertices)
            except EditError as err:
                raise EditError(f"batch edit {i + 1} of {len(ops)}: {err}", err.status) from None
    else:
        _apply(draft, op, n_vertices)
    new = rebuild_state(state, draft.d, tuple(draft.ids), draft.next_id)
    if diagonal is not None:
        check_limits(new.scene, diagonal)
    return new


def _apply(draft: _Draft, op: Any, n_vertices: int | None) -> None:
    if not isinstance(op, dict):
        raise EditError(f"an edit must be a JSON object with an 'op' field; got {brief(op)}")
    kind = op.get("op")
    handler = _EDITS.get(kind) if isinstance(kind, str) else None
    if handler is None:
        raise EditError(f"unknown edit op {brief(kind)}; known: {', '.join(_EDITS)}, batch")
    handler(draft, op, n_vertices)
    if len(draft.ids) > limits.MAX_KEYFRAMES:
        raise EditError(f"{len(draft.ids)} keyframes: at most {limits.MAX_KEYFRAMES}")


def _set_group(draft, op, n):
    name = _group_name(_need(op, "name"))
    d = draft.d
    old = d["groups"].get(name, {})
    g: dict[str, Any] = {"indices": _indices(_need(op, "indices"), n)}
    on = op.get("on", old.get("on", "surface"))
    if on not in ("surface", "tets"):
        raise EditError(f"group 'on' must be \"surface\" or \"tets\"; got {brief(on)}")
    if on != "surface":
        g["on"] = on
    color = op.get("color") or old.get("color") or PALETTE[len(d["groups"]) % len(PALETTE)]
    g["color"] = _color(color)
    d["groups"][name] = g


def _rename_group(draft, op, n):
    name, new = _group_name(_need(op, "name")), _group_name(_need(op, "new_name"))
    d = draft.d
    draft.group(name)
    if new != name and new in d["groups"]:
        raise EditError(f"a group named {new!r} exists already")
    d["groups"] = {(new if k == name else k): v for k, v in d["groups"].items()}
    for k in d["keyframes"]:
        if k["group"] == name:
            k["group"] = new
    d["simulation"]["fixed"] = [new if g == name else g for g in d["simulation"]["fixed"]]


def _recolor_group(draft, op, n):
    draft.group(_group_name(_need(op, "name")))["color"] = _color(_need(op, "color"))


def _set_group_young(draft, op, n):
    """A group's own Young's modulus (Pa), or none (``young`` null: the material's)."""
    group = draft.group(_group_name(_need(op, "name")))
    young = _need(op, "young")
    if young is None:
        group.pop("young", None)
    else:
        group["young"] = _number(young, "young (Pa)")


def _delete_group(draft, op, n):
    name = _group_name(_need(op, "name"))
    d = draft.d
    draft.group(name)
    del d["groups"][name]
    keep = [i for i, k in enumerate(d["keyframes"]) if k["group"] != name]
    d["keyframes"] = [d["keyframes"][i] for i in keep]
    draft.ids = [draft.ids[i] for i in keep]
    d["simulation"]["fixed"] = [g for g in d["simulation"]["fixed"] if g != name]


def _set_fixed(draft, op, n):
    name = _group_name(_need(op, "name"))
    fixed = _need(op, "fixed")
    if not isinstance(fixed, bool):
        raise EditError(f"fixed must be true or false; got {brief(fixed)}")
    draft.group(name)
    names = [g for g in draft.d["simulation"]["fixed"] if g != name]
    draft.d["simulation"]["fixed"] = [*names, name] if fixed else names


def _add_keyframe(draft, op, n):
    _need(op, "time"), _need(op, "group")
    k = _keyframe_dict(op)
    if "position" not in k and "velocity" not in k:
        k["position"] = "rest"
    draft.d["keyframes"].append(k)
    draft.ids.append(draft.next_id)
    draft.next_id += 1


def _update_keyframe(draft, op, n):
    i = draft.key_index(_need(op, "id"))
    draft.d["keyframes"][i] = _keyframe_dict(op, draft.d["keyframes"][i])


def _delete_keyframe(draft, op, n):
    i = draft.key_index(_need(op, "id"))
    del draft.d["keyframes"][i]
    del draft.ids[i]


def _set(draft, op, n):
    section = _need(op, "section")
    if section not in SETTABLE:
        raise EditError(f"section {brief(section)} cannot be set; use one of "
                        f"{', '.join(SETTABLE)}")
    values = _need(op, "values")
    if not isinstance(values, dict):
        raise EditError(f"values must be a table of {section} keys; got {brief(values)}")
    if section == "drive" and "drive" not in draft.d:
        raise EditError("the scene has no [drive]: there is no driver whose settings to set")
    table = draft.d.setdefault(section, {})
    for key, v in values.items():
        if key not in SETTABLE[section]:
            raise EditError(f"{section}.{key} cannot be set here; keys: "
                            f"{', '.join(SETTABLE[section])}")
        if v is None:
            table.pop(key, None)
        else:
            table[key] = v
    if section == "time" and "end" in values and values["end"] is not None:
        table.pop("duration", None)
    if section == "time" and values.get("duration") is not None:
        table.pop("end", None)
    if section == "mesh" and values.get("resolution") is not None:
        table.pop("edge_length", None)
    if section == "mesh" and values.get("edge_length") is not None:
        table.pop("resolution", None)


_EDITS = {
    "set_group": _set_group,
    "rename_group": _rename_group,
    "recolor_group": _recolor_group,
    "set_group_young": _set_group_young,
    "delete_group": _delete_group,
    "set_fixed": _set_fixed,
    "add_keyframe": _add_keyframe,
    "update_keyframe": _update_keyframe,
    "delete_keyframe": _delete_keyframe,
    "set": _set,
}


# ----------------------------------------------------------------------------------------------
# helpers for the browser


#: A fitted pose this close to rest (radians of rotation; translation relative to the
#: group's extent) is keyed as "rest": playback frames are single precision.
REST_ANGLE, REST_SHIFT = 1e-5, 1e-6


def rigid_fit(rest: np.ndarray, current: np.ndarray) -> dict | str:
    """The rigid position target closest to ``current`` (Kabsch fit of the rest vertices):
    ``{"rotation": Euler XYZ degrees, "translation": [...], "center": rest centroid}``, so
    that a keyframe added at the current pose starts where the group is; ``"rest"`` where
    that pose is rest up to the frames' round-off (``REST_ANGLE``, ``REST_SHIFT``)."""
    from scipy.spatial.transform import Rotation

    rest, current = np.asarray(rest, float), np.asarray(current, float)
    c, c_t = rest.mean(axis=0), current.mean(axis=0)
    if len(rest) >= 3 and np.linalg.matrix_rank(rest - c, tol=1e-9) >= 2:
        rot, _ = Rotation.align_vectors(current - c_t, rest - c)
    else:
        rot = Rotation.identity()
    extent = float(np.ptp(rest, axis=0).max(initial=0.0)) if len(rest) else 0.0
    if rot.magnitude() < REST_ANGLE and \
            np.linalg.norm(c_t - c) <= REST_SHIFT * max(extent, np.finfo(float).tiny):
        return "rest"
    angles = rot.as_euler("xyz", degrees=True)
    return {"rotation": [round(float(a), 6) + 0.0 for a in angles],  # + 0.0: no "-0.0"
            "translation": [round(float(x), 9) + 0.0 for x in c_t - c],
            "center": [round(float(x), 9) + 0.0 for x in c]}


def state_to_json(state: EditorState) -> dict:
    """The scene as the browser sees it: the scene file's tables, keyframes with ids."""
    d = scene_to_dict(state.scene)
    for kid, k in zip(state.keyframe_ids, d["keyframes"], strict=True):
        k["id"] = kid
    d["time_range"] = list(state.scene.time_range())
    d["name"] = state.scene.name
    d["group_colors"] = state.scene.group_colors()  # a group without its own: the palette's
    return d



def rebased(scene: Scene, new_source) -> Scene:
    """``scene`` to be saved as ``new_source``: relative mesh and output paths rewritten so
    that they still name the same files from the new file's directory."""
    new_dir = Path(new_source).parent
    old_dir = scene.base_dir

    def fix(p: str) -> str:
        if p.startswith("builtin:") or Path(p).expanduser().is_absolute():
            return p
        return Path(os.path.relpath(old_dir / p, new_dir)).as_posix()

    out = replace(scene, mesh=replace(scene.mesh, path=fix(scene.mesh.path)),
                  output=replace(scene.output, paths=tuple(fix(p) for p in scene.output.paths)))
    out.source = Path(new_source)
    return out
