"""A wiggly shot from Blender's own objects, and its scene file (docs/scene-format.md).

The active mesh at its rest pose (its own vertices, before modifiers and shape keys) is the
body; the vertex groups listed in the Wiggly panel are its groups; keyed Empties ("handles")
give rigid partial keyframes; the object's own evaluated animation can drive a group. Blender's
frame f is shot time (f - frame_start) / fps. Everything is written in wiggly's axes (y up,
metres), as Blender's OBJ and glTF exporters write them, so the scene also runs and previews in
``wiggly animate`` / ``wiggly batch`` as is.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .blender_data import fcurves_of

# Blender's z-up world to wiggly's y-up: (x, y, z) -> (x, z, -y)
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
BAKE_NAME = "Wiggly bake"  # the Mesh Cache modifier a bake adds (and a re-bake replaces)
SHAPE_PREFIX = "wiggly."  # the shape keys a bake adds: wiggly.0001, wiggly.0002, ...
BAKE_ACTION = "wiggly_bake"  # an ID property on the shape keys' action a bake made
DRIVE_STIFFNESS = 1e12  # wiggly's default for driven keys
# modifiers that move vertices but keep them (the driver may come from these)
DEFORMING = {
    "ARMATURE", "CAST", "CURVE", "DISPLACE", "HOOK", "LAPLACIANDEFORM", "LATTICE", "MESH_DEFORM",
    "SHRINKWRAP", "SIMPLE_DEFORM", "SMOOTH", "CORRECTIVE_SMOOTH", "LAPLACIANSMOOTH",
    "SURFACE_DEFORM", "WARP", "WAVE", "MESH_CACHE", "NORMAL_EDIT", "WEIGHTED_NORMAL",
    "UV_PROJECT", "UV_WARP", "VERTEX_WEIGHT_EDIT", "VERTEX_WEIGHT_MIX",
    "VERTEX_WEIGHT_PROXIMITY", "DATA_TRANSFER", "MESH_SEQUENCE_CACHE",
}
# modifiers that add geometry made from the mesh's own (the bake goes before them, so the
# parts they add take no part in the physics: a mirrored half tears at its seam)
COPYING = {"MIRROR", "ARRAY"}
# geometry nodes may deform or generate: a driver keeps them and checks the vertex count
DRIVER_STACK = DEFORMING | {"NODES"}


def is_bake_key(name: str) -> bool:
    """Whether a shape key is one a bake added (``wiggly.`` and the frame's four or more
    digits), not the user's own (``wiggly.sag`` is theirs)."""
    return re.fullmatch(re.escape(SHAPE_PREFIX) + r"\d{4,}", name) is not None


class ShotError(Exception):
    """A user mistake: reported in Blender as an error naming the object and group."""


@dataclass
class Shot:
    """Everything wiggly needs, in wiggly's axes; ``to_local`` maps them back to the object."""

    name: str
    rest: np.ndarray  # (V, 3) metres, y up
    triangles: np.ndarray  # (T, 3)
    groups: dict[str, np.ndarray]  # scene group name -> vertex indices
    labels: dict[str, str]  # scene group name -> Blender vertex group name
    keyframes: list[dict]
    fixed: list[str]
    driven: list[str]
    driver: np.ndarray | None  # (F, V, 3) the object's evaluated animation, or None
    frame_start: int
    frame_end: int
    fps: float
    settings: dict
    to_local: np.ndarray  # (4, 4): wiggly coordinates -> the object's local coordinates
    warnings: list[str] = field(default_factory=list)
    #: the (sub)frames of ``driver``'s samples (F,): every frame, and subframes where the
    #: driven group turns fast (:func:`_driver`)
    driver_frames: np.ndarray | None = None

    @property
    def frames(self) -> np.ndarray:
        return np.arange(self.frame_start, self.frame_end + 1)

    def local(self, positions: np.ndarray) -> np.ndarray:
        """Positions in wiggly's axes as the object's local coordinates."""
        return positions @ self.to_local[:3, :3].T + self.to_local[:3, 3]


def scene_fps(scene) -> float:
    return scene.render.fps / scene.render.fps_base


def _matrix(m) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def scene_name(name: str, taken: set[str]) -> str:
    """A scene group name (letters, digits, ``_``, ``-``) for a Blender vertex group name."""
    base = re.sub(r"[^A-Za-z0-9_-]", "_", name) or "group"
    out, k = base, 2
    while out in taken:
        out, k = f"{base}_{k}", k + 1
    taken.add(out)
    return out


def euler_xyz(R: np.ndarray) -> list[float]:
    """Extrinsic X-then-Y-then-Z Euler angles in degrees of R = Rz Ry Rx (the scene format's)."""
    sy = -R[2, 0]
    if abs(sy) < 1 - 1e-12:
        x, y, z = math.atan2(R[2, 1], R[2, 2]), math.asin(sy), math.atan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: only x - z (or x + z) is determined; take z = 0
        y = math.copysign(math.pi / 2, sy)
        x, z = math.atan2(math.copysign(1, sy) * R[0, 1], R[1, 1]), 0.0
    return [math.degrees(a) for a in (x, y, z)]


def _rigid(m) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (3, 3) and location (3,) of a world matrix, its scale left out."""
    loc, rot, _ = m.decompose()
    return _matrix(rot.to_matrix()), np.array(loc, dtype=np.float64)


#: a group whose members (weight above 0) include more than FAINT_SHARE with weights below
#: FAINT is warned about: a weight-painted falloff keys its faint fringe as fully as its core
FAINT, FAINT_SHARE = 0.1, 0.2


def _members(mesh, indices: set[int]) -> tuple[dict[int, np.ndarray], dict[int, int]]:
    """The vertices (weight above 0) of each vertex group in ``indices``, and how many of
    them have a weight below :data:`FAINT`, in one pass."""
    out: dict[int, list[int]] = {i: [] for i in indices}
    faint = dict.fromkeys(indices, 0)
    for v in mesh.vertices:
        for g in v.groups:
            if g.group in out and g.weight > 0:
                out[g.group].append(v.index)
                faint[g.group] += g.weight < FAINT
    return {i: np.array(idx, np.int64) for i, idx in out.items()}, faint


#: Earth's gravity (m/s^2), for the unit-scale check of the scene's Gravity.
EARTH = 9.81


def gather(context, obj) -> Shot:
    """The shot of mesh object ``obj`` over the scene's frame range; raises ShotError."""
    scene = context.scene
    s = obj.wiggly
    where = f"Object '{obj.name}'"
    if obj.type != "MESH":
        raise ShotError(f"{where} is a {obj.type.lower()}, not a mesh")
    if obj.mode == "EDIT":
        obj.update_from_editmode()  # the edit mesh, not the mesh as it was before Edit Mode
    mesh = obj.data
    V = len(mesh.vertices)
    if V == 0 or len(mesh.polygons) == 0:
        raise ShotError(f"{where} has no faces; wiggly animates a closed surface")
    fs, fe, fps = scene.frame_start, scene.frame_end, scene_fps(scene)
    if fe <= fs:
        raise ShotError(f"the scene's frame range {fs}-{fe} is empty; wiggly needs at least "
                        "two frames")
    if _transform_animated(obj):
        raise ShotError(f"{where}: its own location/rotation/scale is animated; wiggly solves "
                        "in a still placement: animate it with handles or an armature")
    mover = _moving_parent(obj)
    if mover is not None:
        raise ShotError(f"{where}: its parent '{mover}' moves over the frames; wiggly solves "
                        "in a still placement: unparent it (Alt+P > Clear and Keep "
                        "Transformation), or animate it with handles or an armature")
    mesh.calc_loop_triangles()
    tris = np.empty(3 * len(mesh.loop_triangles), np.int64)
    mesh.loop_triangles.foreach_get("vertices", tris)
    tris = tris.reshape(-1, 3)
    loose = V - len(np.unique(tris))
    if loose:
        raise ShotError(f"{where} has {loose} loose vertices (on no face); wiggly needs a "
                        "surface: delete them (Mesh > Clean Up > Delete Loose)")
    frame = scene.frame_current, scene.frame_subframe
    try:
        scene.frame_set(fs)
        world = _matrix(obj.matrix_world)
        unit = scene.unit_settings.scale_length or 1.0
        to_wiggly = np.eye(4)
        to_wiggly[:3, :3] = unit * Y_UP @ world[:3, :3]
        to_wiggly[:3, 3] = unit * Y_UP @ world[:3, 3]
        det = np.linalg.det(to_wiggly[:3, :3])
        if abs(det) < 1e-12:
            raise ShotError(f"{where} has a zero scale")
        if det < 0:  # mirrored by a negative scale: the world's triangles wind the other way
            tris = tris[:, ::-1].copy()
        co = np.empty(3 * V)
        mesh.vertices.foreach_get("co", co)
        rest = co.reshape(-1, 3) @ to_wiggly[:3, :3].T + to_wiggly[:3, 3]
        size = float(np.ptp(rest, axis=0).max())
        moved = _placement_moves(scene, obj, world, size / max(unit, 1e-300), fs, fe)
        if moved is not None:
            raise ShotError(f"{where}: its placement in the world changes from frame {fs} to "
                            f"frame {moved} (a constraint, a driver or a moving parent); "
                            "wiggly solves in a still placement: remove what moves it, or "
                            "animate it with handles or an armature")
        groups, labels, keyframes, fixed, driven, warnings = {}, {}, [], [], [], []
        taken: set[str] = set()
        if not len(s.groups):
            raise ShotError(f"{where} has no vertex groups in the Wiggly panel: add the vertex "
                            "groups to key, fix or drive (+ under Wiggly > Groups)")
        members, faint = _members(mesh, {g.index for g in obj.vertex_groups
                                         if any(item.name == g.name for item in s.groups)})
        for item in s.groups:
            vg = obj.vertex_groups.get(item.name)
            at = f"{where}, group '{item.name}'"
            if vg is None:
                raise ShotError(f"{at}: no such vertex group (renamed or deleted?); the "
                                f"object's vertex groups are: "
                                f"{', '.join(g.name for g in obj.vertex_groups) or 'none'}")
            idx = members[vg.index]
            if not len(idx):
                raise ShotError(f"{at}: the vertex group has no vertices (assign some with a "
                                "weight above 0 in Edit Mode)")
            if faint[vg.index] > FAINT_SHARE * len(idx):
                warnings.append(
                    f"{at}: {faint[vg.index]} of its {len(idx)} vertices have weights below "
                    f"{FAINT:g}, and wiggly takes every vertex of weight above 0 in full "
                    "(weights are not blended): if the faint ones should stay free, remove them "
                    "from the group (Weights > Clean in Weight Paint mode)")
            name = scene_name(item.name, taken)
            groups[name], labels[name] = idx, item.name
            if item.role == "FIXED":
                fixed.append(name)
            elif item.role == "DRIVEN":
                driven.append(name)
                if item.handle is not None:
                    warnings.append(f"{at}: its handle '{item.handle.name}' is not used: a "
                                    "Driven group follows the object's own animation (set "
                                    "the role to Handle to key it with the handle)")
            else:
                keys = _handle_keys(context, item, at, name, rest[idx], unit, size, fs, fe,
                                    fps, warnings)
                keyframes += keys
        if driven and not animated_by_blender(context, obj):
            raise ShotError(f"{where}, driven group "
                            f"{', '.join(repr(labels[d]) for d in driven)}: "
                            + not_evaluated("the object"))
        driver, driver_frames = (_driver(context, obj, driven, groups, labels, to_wiggly, fs,
                                         fe) if driven else (None, None))
        if driver is not None:
            idx = np.unique(np.concatenate([groups[d] for d in driven]))
            if float(np.abs(driver[:, idx] - rest[idx]).max()) <= 1e-6 * size:
                warnings.append(
                    f"{where}, driven group {', '.join(repr(labels[d]) for d in driven)}: "
                    f"the object's animation leaves it at rest over frames {fs}-{fe}, so it "
                    "is held still, as a Fixed group would be: animate the object (an "
                    "Armature modifier, shape keys), or set the role to Fixed")
        for mod in obj.modifiers:
            if mod.type in COPYING and mod.show_viewport:
                warnings.append(
                    f"{where}: modifier '{mod.name}' ({mod.type.lower()}) adds copies of the "
                    "mesh after the bake, which take no part in the physics: the solve sees "
                    "the mesh without them (an open half, for a mirror), so they may tear "
                    "apart at the seams; apply the modifier before baking to animate the "
                    "whole body")
    finally:
        scene.frame_set(frame[0], subframe=frame[1])
    settings = {k: getattr(s, k) for k in ("modes", "resolution", "warp", "loop",
                                            "drive_physics", "drive_free_modes")}
    # Blender keeps float properties in single precision: 0.45 reads 0.44999998807907104
    settings.update({k: _single(getattr(s, k)) for k in ("young", "poisson", "density",
                                                          "alpha", "beta", "drive_stiffness",
                                                          "drive_intensity")})
    # Blender's gravity is in its units per second squared (the Gravity field shows it
    # times the unit scale, in m/s^2): the same scale as the positions
    gravity = (unit * Y_UP @ np.array(scene.gravity, np.float64) if scene.use_gravity
               else np.zeros(3))
    g = float(np.linalg.norm(gravity))
    if scene.use_gravity and unit != 1.0 and not 0.5 * EARTH <= g <= 2.0 * EARTH:
        warnings.append(
            f"the scene's Gravity is {g:.3g} m/s^2 ({np.linalg.norm(scene.gravity):g} at unit "
            f"scale {unit:g}): Blender's Gravity field is in scene units per second squared, "
            f"so Earth's gravity is {EARTH / unit:.4g} here; set it so (or turn Gravity off) "
            "unless this gravity is meant")
    settings["gravity"] = [_single(g) + 0.0 for g in gravity]
    return Shot(obj.name, rest, tris, groups, labels, keyframes, fixed, driven, driver, fs, fe,
                fps, settings, np.linalg.inv(to_wiggly), warnings, driver_frames)


def _single(value: float) -> float:
    """A single-precision property as the decimal number the user typed (7 digits)."""
    return float(f"{value:.7g}")


#: Frames of the range at which placements and modifier stacks are checked for motion.
PLACEMENT_SAMPLES = 8


def sampled_frames(fs: int, fe: int) -> list[int]:
    """``PLACEMENT_SAMPLES`` frames spread over fs..fe, both ends included."""
    return [int(f) for f in np.unique(np.linspace(fs, fe, PLACEMENT_SAMPLES).round())]


def _placement_moves(scene, obj, world: np.ndarray, size: float, fs: int, fe: int
                     ) -> int | None:
    """The first of ``PLACEMENT_SAMPLES`` frames spread over the range (ends included) at
    which the object's world matrix differs from ``world`` (its matrix at frame ``fs``) by
    more than 1e-6 of its size, or None: what the animated-transform and parent checks miss
    (constraints, drivers).  The caller restores the current frame."""
    for f in sampled_frames(fs, fe)[1:]:
        scene.frame_set(f)
        m = _matrix(obj.matrix_world)
        if (np.abs(m[:3, :3] - world[:3, :3]).max() * size
                + np.abs(m[:3, 3] - world[:3, 3]).max() > 1e-6 * max(size, 1e-300)):
            return int(f)
    scene.frame_set(fs)
    return None


def _moving_parent(obj) -> str | None:
    """The name of the first parent of ``obj`` (up its chain) whose location, rotation or
    scale is animated, or whose bone parent's armature is animated; None if none is."""
    child = obj
    while child.parent is not None:
        parent = child.parent
        if _transform_animated(parent) or (
            child.parent_type == "BONE" and parent.animation_data is not None
            and parent.animation_data.action is not None
        ):
            return parent.name
        child = parent
    return None


def _transform_animated(obj) -> bool:
    paths = ("location", "rotation_euler", "rotation_quaternion", "rotation_axis_angle",
             "scale", "delta_")
    return any(c.data_path.startswith(paths) for c in fcurves_of(obj))


def animated_by_blender(context, obj) -> bool:
    """Whether the view layer animates ``obj``: not when it is disabled in viewports, or
    only in collections that are disabled in viewports or excluded (unticked), themselves or
    above; its animation and constraints then do not run and frame changes leave it where it
    was (even when another object's property points at it).  Hidden with H, or with the
    collection's eye, it is still animated."""
    if obj.hide_viewport:
        return False
    live: set[str] = set()

    def walk(layer, alive: bool) -> None:
        alive = alive and not layer.exclude and not layer.collection.hide_viewport
        if alive:
            live.add(layer.collection.name)
        for child in layer.children:
            walk(child, alive)

    walk(context.view_layer.layer_collection, True)
    return any(c.name in live for c in obj.users_collection)


def not_evaluated(what: str) -> str:
    return (f"{what} is disabled in viewports, or in a collection that is disabled or "
            "excluded (unticked), so Blender does not animate it: enable it (to keep it out "
            "of sight, hide it with H instead)")


#: F-curves of a handle that key it (its location and rotation; scale plays no role)
PLACEMENT_PATHS = ("location", "rotation_", "delta_location", "delta_rotation_")


def _handle_keys(context, item, at: str, name: str, X: np.ndarray, unit: float, size: float,
                 fs: int, fe: int, fps: float, warnings: list[str]) -> list[dict]:
    """Rigid keyframes of one group from its handle's keyframes (Moving Hold keys: still)."""
    scene = context.scene
    handle = item.handle
    if handle is None:
        raise ShotError(f"{at}: the role Handle needs an Empty: Add Handle, or pick one")
    if not handle.users_collection:  # deleted (X): an orphan the group still points at
        raise ShotError(f"{at}: its handle '{handle.name}' is in no scene (deleted?): Add "
                        "Handle, or pick one")
    if not animated_by_blender(context, handle):
        raise ShotError(f"{at}: " + not_evaluated(f"its handle '{handle.name}'"))
    frames: dict[float, bool] = {}
    curves = list(fcurves_of(handle))
    placing = [c for c in curves if c.data_path.startswith(PLACEMENT_PATHS)]
    scaled = any(c.data_path in ("scale", "delta_scale") for c in curves)
    if scaled:
        warnings.append(f"{at}: the scale keys of handle '{handle.name}' were left out (only "
                        "its location and rotation key the group)")
    for curve in placing:
        for point in curve.keyframe_points:
            f = float(point.co[0])
            frames[f] = frames.get(f, False) or point.type == "MOVING_HOLD"
    inside = {f: still for f, still in frames.items() if fs - 1e-6 <= f <= fe + 1e-6}
    if len(inside) < len(frames):
        warnings.append(f"{at}: {len(frames) - len(inside)} keyframes of handle "
                        f"'{handle.name}' lie outside frames {fs}-{fe} and were left out")
    if not inside:
        outside = (f" (its {len(frames)} keyframes, at frames "
                   f"{', '.join(f'{f:g}' for f in sorted(frames)[:5])}"
                   f"{', ...' if len(frames) > 5 else ''}, lie outside the range)"
                   if frames else "")
        only_scale = " (its scale keys do not count: scale plays no role)" if (
            scaled and not frames) else ""
        raise ShotError(f"{at}: its handle '{handle.name}' has no keyframes in frames "
                        f"{fs}-{fe}{outside}{only_scale}; key its location/rotation (I over "
                        "the viewport), or set the group's role to Fixed")
    R0, l0 = _rigid(_rest_matrix(item))
    center = X.mean(axis=0)
    keys = []
    for f in sorted(inside):
        scene.frame_set(math.floor(f), subframe=f - math.floor(f))
        R1, l1 = _rigid(handle.matrix_world)
        A = R1 @ R0.T  # Blender's world: x -> A x + b
        b = l1 - A @ l0
        Aw = Y_UP @ A @ Y_UP.T  # wiggly's (X = unit Y_UP x): X -> Aw X + unit Y_UP b
        bw = unit * Y_UP @ b
        key = {"time": (f - fs) / fps, "group": name}
        moved = Aw @ center + bw - center
        if np.abs(Aw - np.eye(3)).max() < 1e-9 and np.abs(moved).max() < 1e-9 * max(size, 1e-9):
            key["position"] = "rest"
        else:
            key["position"] = {"rotation": euler_xyz(Aw), "translation": list(moved),
                               "center": list(center)}
        if inside[f]:
            key["velocity"] = [0.0, 0.0, 0.0]
        key["stiffness"] = _single(item.stiffness)
        key["name"] = f"{item.name} @ frame {f:g}" + (" (still)" if inside[f] else "")
        keys.append(key)
    return keys


def _rest_matrix(item):
    from mathutils import Matrix

    r = list(item.rest_matrix)
    return Matrix([r[0:4], r[4:8], r[8:12], r[12:16]])


def driver_modifiers(obj) -> tuple[list, list]:
    """(modifiers the driver is evaluated with, modifiers turned off for it): the driver is
    the mesh deformed by the stack up to the first modifier that makes new geometry
    (geometry nodes are kept: the driver checks that they keep the vertices); wiggly's own
    bake is left out. A deforming modifier after a generating one is a ShotError."""
    keep, off, generating = [], [], None
    for mod in obj.modifiers:
        if mod.type == "MESH_CACHE" and mod.name == BAKE_NAME:
            off.append(mod)
        elif generating is not None:
            if mod.type in DEFORMING and mod.show_viewport and mod.type not in (
                    "NORMAL_EDIT", "WEIGHTED_NORMAL", "UV_PROJECT", "UV_WARP"):
                remedy = (f"apply '{generating.name}' (its copies would copy the deformation "
                          "of the modelled part if it were moved below, legs walking in "
                          "step)" if generating.type in COPYING else
                          f"move '{generating.name}' below it, or apply it")
                raise ShotError(
                    f"Object '{obj.name}': modifier '{mod.name}' ({mod.type.lower()}) comes "
                    f"after '{generating.name}' ({generating.type.lower()}), which changes "
                    f"the vertices; the driver must animate the mesh's own vertices: {remedy}")
            off.append(mod)
        elif mod.type in DRIVER_STACK:
            keep.append(mod)
        else:
            generating = mod
            off.append(mod)
    return keep, off


@contextmanager
def stack_alone(obj, off: list, muted: list) -> Iterator[None]:
    """``obj`` evaluated with the modifiers ``off`` turned off and the shape keys ``muted``
    muted, as they were again afterwards."""
    shown, was = [m.show_viewport for m in off], [k.mute for k in muted]
    try:
        for m in off:
            m.show_viewport = False
        for k in muted:
            k.mute = True
        yield
    finally:
        for m, w in zip(off, shown, strict=True):
            m.show_viewport = w
        for k, w in zip(muted, was, strict=True):
            k.mute = w


def evaluated_vertices(context, obj) -> np.ndarray:
    """The object's evaluated mesh at the current frame: its vertices (n, 3), object-local
    (n may differ from the mesh's own where modifiers make geometry)."""
    evaluated = obj.evaluated_get(context.evaluated_depsgraph_get())
    m = evaluated.to_mesh()
    try:
        co = np.empty(3 * len(m.vertices))
        m.vertices.foreach_get("co", co)
    finally:
        evaluated.to_mesh_clear()
    return co.reshape(-1, 3)


#: The driver is sampled at subframes where its driven group turns by more than this many
#: degrees from one frame to the next: wiggly joins the samples by cubics through positions,
#: which cut a turn's arc (a 180-degree turn in 0.5 s at 24 fps, 22 degrees per frame, swung
#: a tail 13 mm off the same turn sampled at 120 fps; at 4 subframes per frame, 0.4 mm).
SUBFRAME_TURN = 5.0


def _driver(context, obj, driven: list[str], groups: dict, labels: dict,
            to_wiggly: np.ndarray, fs: int, fe: int) -> tuple[np.ndarray, np.ndarray]:
    """The object's evaluated animation in wiggly's axes, (F, V, 3), and the (sub)frames it
    was sampled at (F,): every frame fs..fe, and between two frames where the driven groups
    turn by more than SUBFRAME_TURN degrees, subframes at most that far apart."""
    idx = np.unique(np.concatenate([groups[d] for d in driven]))
    frames = np.arange(fs, fe + 1, dtype=np.float64)
    out = _sampled(context, obj, driven, labels, to_wiggly, frames)
    steps = [_turn_degrees(out[i][idx], out[i + 1][idx]) for i in range(len(out) - 1)]
    extra = [f + j / k for f, turn in zip(frames[:-1], steps, strict=True)
             if (k := math.ceil(turn / SUBFRAME_TURN)) > 1 for j in range(1, k)]
    if not extra:
        return out, frames
    between = _sampled(context, obj, driven, labels, to_wiggly, np.array(extra))
    order = np.argsort(np.r_[frames, extra], kind="stable")
    return np.concatenate([out, between])[order], np.r_[frames, extra][order]


def _sampled(context, obj, driven: list[str], labels: dict, to_wiggly: np.ndarray,
             frames: np.ndarray) -> np.ndarray:
    """The object's evaluated animation at (sub)frames ``frames``, in wiggly's axes."""
    scene = context.scene
    _, off = driver_modifiers(obj)
    keys = obj.data.shape_keys
    ours = [k for k in keys.key_blocks if is_bake_key(k.name)] if keys else []
    V = len(obj.data.vertices)
    out = np.empty((len(frames), V, 3))
    with stack_alone(obj, off, ours):
        for i, f in enumerate(frames):
            scene.frame_set(math.floor(f), subframe=f - math.floor(f))
            co = evaluated_vertices(context, obj)
            if len(co) != V:
                names = ", ".join(f"'{g}'" for g in (labels[d] for d in driven))
                raise ShotError(
                    f"Object '{obj.name}', driven group {names}: its animation has {len(co)} "
                    f"vertices at frame {f:g} but the mesh has {V}; a driver must move the "
                    "mesh's own vertices (a modifier or geometry nodes change their count)")
            out[i] = co @ to_wiggly[:3, :3].T + to_wiggly[:3, 3]
    return out


def _turn_degrees(a: np.ndarray, b: np.ndarray) -> float:
    """The angle (degrees) of the best-fit rotation taking points ``a`` (g, 3) onto ``b``
    about their centroids (Kabsch); 0 for fewer than three points."""
    if len(a) < 3:
        return 0.0
    H = (a - a.mean(axis=0)).T @ (b - b.mean(axis=0))
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


# ----------------------------------------------------------------------------------------------
# the scene file


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_value(x)}" for k, x in v.items()) + " }"
    return "[" + ", ".join(_value(x) for x in v) + "]"


def _table(name: str, values: dict) -> str:
    return f"[{name}]\n" + "".join(f"{k} = {_value(v)}\n" for k, v in values.items())


def scene_toml(shot: Shot, mesh_file: str, driver_file: str | None,
               outputs: list[str]) -> str:
    """The scene file of ``shot`` (docs/scene-format.md), its files named relative to it."""
    s = shot.settings
    parts = [
        f"# wiggly scene of Blender object {json.dumps(shot.name)}, frames {shot.frame_start}-"
        f"{shot.frame_end} at {shot.fps:g} fps (frame f is time (f - {shot.frame_start}) / "
        "fps); y up, metres\nformat = 1\n",
        _table("mesh", {"path": mesh_file, "resolution": s["resolution"]}),
        _table("material", {"young": s["young"], "poisson": s["poisson"],
                            "density": s["density"]}),
        _table("damping", {"alpha": s["alpha"], "beta": s["beta"]}),
        _table("simulation", {"gravity": s["gravity"], "modes": s["modes"], "warp": s["warp"],
                              "fixed": shot.fixed}),
        # a loop's cycle is the range and the step from its last frame back to its first:
        # Blender plays frame_end, then frame_start, so the cycle's end is one frame later
        _table("time", {"start": 0.0, "end": (shot.frame_end - shot.frame_start
                                              + (1 if s["loop"] else 0)) / shot.fps,
                        "fps": shot.fps, "loop": s["loop"]}),
    ]
    for name, idx in shot.groups.items():
        parts.append(f"# Blender vertex group {json.dumps(shot.labels[name])}\n"
                     + _table(f"groups.{name}", {"indices": idx.tolist()}))
    for key in shot.keyframes:
        parts.append("[[keyframes]]\n" + "".join(f"{k} = {_value(v)}\n" for k, v in key.items()))
    if shot.driver is not None:
        drive = {"path": driver_file, "group": shot.driven,
                 "physics": s["drive_physics"].lower()}
        if drive["physics"] == "keys":
            drive["stiffness"] = s["drive_stiffness"]
        else:
            drive["intensity"] = s["drive_intensity"]
            drive["free_modes"] = s["drive_free_modes"]
        parts.append(_table("drive", drive))
    parts.append(_table("output", {"paths": outputs, "frame_start": shot.frame_start}))
    return "\n".join(parts)


def _replace(path: Path, write) -> None:
    """Write ``path`` atomically: ``write(file)`` into a temporary file, then rename."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def shot_files(toml: Path) -> dict[str, Path]:
    """The files "Export scene" writes for scene file ``toml``."""
    stem = toml.stem
    return {"scene": toml, "mesh": toml.with_name(f"{stem}_rest.obj"),
            "driver": toml.with_name(f"{stem}_drive.npz"),
            "output": toml.with_name(f"{stem}_wiggly.glb")}


def unwritable(folder: Path) -> str | None:
    """Why no file can be written into the existing ``folder`` (its OS error), or None."""
    try:
        tempfile.TemporaryFile(dir=folder).close()
    except OSError as e:
        return e.strerror or str(e)
    return None


def write_shot(shot: Shot, toml: Path, overwrite: bool = False) -> dict[str, Path]:
    """Write the scene file ``toml``, its rest mesh (OBJ) and driver (wiggly npz) beside it;
    an existing file is an error unless ``overwrite``."""
    files = shot_files(toml)
    mine = [files["scene"], files["mesh"]] + ([files["driver"]] if shot.driver is not None
                                              else [])
    if not toml.parent.is_dir():
        raise ShotError(f"the folder {toml.parent} does not exist")
    why = unwritable(toml.parent)  # before the first file: a refusal leaves nothing behind
    if why is not None:
        raise ShotError(f"cannot write into the folder {toml.parent}: {why}")
    existing = [str(p) for p in mine if p.exists()]
    if existing and not overwrite:
        raise ShotError(f"{', '.join(existing)} already exist; tick Overwrite to replace them")

    def obj(f):
        f.write(f"# rest mesh of Blender object {shot.name} (y up, metres)\n".encode())
        np.savetxt(f, shot.rest, fmt="v %.17g %.17g %.17g")
        np.savetxt(f, shot.triangles + 1, fmt="f %d %d %d")

    _replace(files["mesh"], obj)
    if shot.driver is not None:
        times = (shot.driver_frames - shot.frame_start) / shot.fps
        _replace(files["driver"], lambda f: np.savez(
            f, format_version=np.array(1), times=times, positions=shot.driver,
            faces=shot.triangles, name=np.array(shot.name), loop=np.array(False)))
    text = scene_toml(shot, files["mesh"].name,
                      files["driver"].name if shot.driver is not None else None,
                      [files["output"].name])
    _replace(files["scene"], lambda f: f.write(text.encode()))
    return files
