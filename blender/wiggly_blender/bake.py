"""Baking wiggly's result back onto the object: a Mesh Cache modifier playing a PC2 point
cache, or a shape key per frame. A bake replaces only wiggly's own previous bake (the modifier
named "Wiggly bake", the shape keys "wiggly.NNNN" and their F-curves); the object's own
modifiers, shape keys and animation stay as they are."""

from __future__ import annotations

import hashlib
import re
import struct
from pathlib import Path

import bpy
import numpy as np

from .blender_data import fcurves_of, new_fcurve, remove_fcurves
from .shot import (
    BAKE_ACTION,
    BAKE_NAME,
    DEFORMING,
    DRIVER_STACK,
    SHAPE_PREFIX,
    Shot,
    ShotError,
    _replace,
    driver_modifiers,
    evaluated_vertices,
    is_bake_key,
    sampled_frames,
    stack_alone,
    unwritable,
)

#: an ID property on the shape keys of a mesh whose Basis a bake added (Remove Bake clears it)
MADE_BASIS = "wiggly_made_basis"
#: the end of every PC2 file name a bake writes
_SUFFIX = "_wiggly.pc2"


def read_result(path: Path, shot: Shot) -> np.ndarray:
    """Positions (F, V, 3) of wiggly's npz result on the shot's frames, object-local."""
    try:
        with np.load(path, allow_pickle=False) as data:
            times, positions = data["times"], data["positions"].astype(np.float64)
    except (OSError, KeyError, ValueError) as e:
        what = "wrote no result" if not path.exists() else f"wrote an unreadable result ({e})"
        raise ShotError(f"the wiggly command finished but {what}: check that the wiggly "
                        "command in Edit > Preferences > Add-ons > wiggly is wiggly's own "
                        "(e.g. .venv/bin/wiggly) and of this add-on's version") from None
    frames = shot.frame_start + np.rint(times * shot.fps).astype(np.int64)
    if shot.settings["loop"] and len(frames) and frames[-1] == shot.frame_end + 1:
        frames, positions = frames[:-1], positions[:-1]  # the seam: the first frame again
    if not np.array_equal(frames, shot.frames) or positions.shape[1] != len(shot.rest):
        raise ShotError(f"wiggly's result {path} has frames {frames[0]}-{frames[-1]} and "
                        f"{positions.shape[1]} vertices; expected frames {shot.frame_start}-"
                        f"{shot.frame_end} and {len(shot.rest)} (a different wiggly version?)")
    return shot.local(positions)


def write_pc2(path: Path, local: np.ndarray, frame_start: int) -> None:
    """A PC2 point cache: header, then float32 x y z of every vertex of every frame."""
    F, V, _ = local.shape
    header = struct.pack("<12siiffi", b"POINTCACHE2\0", 1, V, float(frame_start), 1.0, F)
    _replace(path, lambda f: (f.write(header),
                              f.write(np.ascontiguousarray(local, "<f4").tobytes())))


def remove_bake(obj) -> int:
    """Remove wiggly's bake from ``obj`` (modifier, shape keys and their F-curves); the count
    of things removed."""
    from .freshness import FINGERPRINT

    if FINGERPRINT in obj:
        del obj[FINGERPRINT]
    gone = 0
    for mod in [m for m in obj.modifiers if m.type == "MESH_CACHE" and m.name == BAKE_NAME]:
        obj.modifiers.remove(mod)
        gone += 1
    keys = obj.data.shape_keys
    if keys is not None:
        remove_fcurves(keys, lambda path: not (
            path.startswith('key_blocks["') and path.endswith('"].value')
            and is_bake_key(path[len('key_blocks["'):-len('"].value')])))
        action = keys.animation_data.action if keys.animation_data is not None else None
        if action is not None and action.get(BAKE_ACTION) and not fcurves_of(keys):
            keys.animation_data.action = None  # the bake's own action, now empty: gone
            bpy.data.actions.remove(action)
        for block in [k for k in keys.key_blocks if is_bake_key(k.name)]:
            obj.shape_key_remove(block)
            gone += 1
        # the Basis a bake added to a mesh without shape keys goes with the last of its keys
        if keys.get(MADE_BASIS) and len(keys.key_blocks) == 1:
            obj.shape_key_clear()
    return gone


def cache_path(obj) -> Path:
    folder = obj.wiggly.cache_dir or "//wiggly/"
    if folder.startswith("//") and not bpy.data.filepath:
        raise ShotError(f"Object '{obj.name}': the cache folder {folder} is relative to the "
                        ".blend file, which is not saved yet: save it, or pick an absolute "
                        "Cache folder")
    directory = Path(bpy.path.abspath(folder))
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        why = e.strerror
    else:
        why = unwritable(directory)
    if why is not None:
        raise ShotError(f"Object '{obj.name}': cannot write into the cache folder "
                        f"{directory}: {why}; pick another Cache folder")
    return directory / cache_name(obj.name, bpy.data.filepath)


def cache_name(name: str, blend: str) -> str:
    """The PC2 file's name for object ``name`` of the .blend file ``blend``: the name with
    characters outside ``[A-Za-z0-9_.-]`` replaced by ``_``, then a digest of the exact name
    and .blend path, so that objects whose names differ only there ("My Obj", "My_Obj"), or
    only in case, or objects of two .blend files sharing a cache folder never share a file."""
    digest = hashlib.sha1(f"{blend}\0{name}".encode()).hexdigest()[:8]
    return f"{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}-{digest}{_SUFFIX}"


#: PC2 files of earlier bakes of an object kept in the cache folder, so that undoing a re-bake
#: (which restores the modifier, not files) plays the earlier bake again
BAKES_KEPT = 4


def bake_file(base: Path, local: np.ndarray) -> Path:
    """The PC2 file of one bake: the object's cache file ``base`` (:func:`cache_path`) with
    a digest of the baked positions, so that a re-bake with other settings writes a new file
    and an undo finds the earlier one where its modifier points."""
    digest = hashlib.sha1(np.ascontiguousarray(local, "<f4").tobytes()).hexdigest()[:8]
    return base.with_name(f"{base.name.removesuffix(_SUFFIX)}-{digest}{_SUFFIX}")


def prune_bakes(base: Path, current: Path) -> None:
    """Delete all but the :data:`BAKES_KEPT` newest bakes (:func:`bake_file`) of the object
    whose cache file is ``base``; never ``current``."""
    stem = base.name.removesuffix(_SUFFIX)
    mine = [p for p in base.parent.glob(f"{stem}-*{_SUFFIX}")
            if re.fullmatch(re.escape(stem) + r"-[0-9a-f]{8}" + re.escape(_SUFFIX), p.name)]
    mine.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    for old in mine[BAKES_KEPT:]:
        if old != current:
            old.unlink(missing_ok=True)


def bake_mesh_cache(obj, shot: Shot, local: np.ndarray) -> Path:
    """Write the PC2 file and play it with a Mesh Cache modifier placed where the solve took
    the mesh: after the driver's modifiers (a driven shot) or the modifiers that only deform,
    before any that make new geometry (so a Subdivision Surface below it still smooths the
    result)."""
    base = cache_path(obj)
    path = bake_file(base, local)
    write_pc2(path, local, shot.frame_start)
    prune_bakes(base, path)
    remove_bake(obj)
    mod = obj.modifiers.new(BAKE_NAME, "MESH_CACHE")
    mod.cache_format = "PC2"
    mod.filepath = bpy.path.relpath(str(path)) if bpy.data.filepath else str(path)
    mod.time_mode, mod.play_mode, mod.deform_mode = "FRAME", "SCENE", "OVERWRITE"
    mod.interpolation = "LINEAR"
    mod.frame_start = float(shot.frame_start)  # cache frame k plays on scene frame start + k
    mod.frame_scale = 1.0
    mod.forward_axis, mod.up_axis = "POS_Y", "POS_Z"  # as written: the object's own axes
    stack = DRIVER_STACK if shot.driver is not None else DEFORMING
    index = next((i for i, m in enumerate(obj.modifiers)
                  if m.type not in stack and m != mod), len(obj.modifiers) - 1)
    if hasattr(obj.modifiers, "move"):
        obj.modifiers.move(len(obj.modifiers) - 1, index)
    else:  # Blender before 4.1
        with bpy.context.temp_override(object=obj, active_object=obj):
            bpy.ops.object.modifier_move_to_index(modifier=mod.name, index=index)
    return path


def check_shape_keys(obj) -> None:
    """Raise ShotError where a shape-key bake would reach beyond ``obj``: a mesh shared with
    other objects (linked duplicates), or an object in Edit Mode (leaving it writes the edit
    mesh over new shape keys)."""
    users = obj.data.users - int(obj.data.use_fake_user)
    if users > 1:
        raise ShotError(f"Object '{obj.name}': its mesh '{obj.data.name}' is shared with "
                        f"{users - 1} other object(s) (linked duplicates), which shape keys "
                        "would move too: bake as Mesh Cache, or make the mesh single-user "
                        "(Object > Relations > Make Single User > Object & Data)")
    if obj.mode == "EDIT":
        raise ShotError(f"Object '{obj.name}' is in Edit Mode: leave it (Tab) to bake shape "
                        "keys, or bake as Mesh Cache")


def refuse_driven(obj, shot: Shot) -> None:
    """A driven shot cannot be baked as shape keys: ShotError."""
    if shot.driver is not None:
        raise ShotError(f"Object '{obj.name}': a driven bake cannot be shape keys (they sit "
                        "under the modifiers, which would move it twice): bake as Mesh Cache")


def bake_shape_keys(obj, shot: Shot, local: np.ndarray) -> int:
    """A shape key ``wiggly.NNNN`` per frame N, its value 1 on frame N and 0 on the frames
    next to it (the first and last hold before and after the range)."""
    refuse_driven(obj, shot)
    check_shape_keys(obj)
    remove_bake(obj)
    if obj.data.shape_keys is None:
        obj.shape_key_add(name="Basis", from_mix=False)
        obj.data.shape_keys[MADE_BASIS] = True
    keys = obj.data.shape_keys
    made = keys.animation_data is None or keys.animation_data.action is None
    fs, fe = shot.frame_start, shot.frame_end
    for i, frame in enumerate(shot.frames):
        name = f"{SHAPE_PREFIX}{frame:04d}"
        block = obj.shape_key_add(name=name, from_mix=False)
        block.data.foreach_set("co", local[i].astype(np.float32).ravel())
        block.slider_min, block.slider_max, block.value = 0.0, 1.0, 0.0
        points = [(f, float(f == frame)) for f in (frame - 1, frame, frame + 1) if fs <= f <= fe]
        curve = new_fcurve(keys, f'key_blocks["{name}"].value', f"{keys.name} wiggly")
        curve.keyframe_points.add(len(points))
        curve.keyframe_points.foreach_set("co", [c for p in points for c in p])
        for p in curve.keyframe_points:
            p.interpolation = "LINEAR"
        curve.update()
    if made and keys.animation_data is not None and keys.animation_data.action is not None:
        keys.animation_data.action[BAKE_ACTION] = True  # the bake's: Remove Bake removes it
    return len(shot.frames)


def shape_keys_at_work(obj) -> list[str]:
    """The object's own shape keys that add to a shape-key bake: animated, or with a value."""
    keys = obj.data.shape_keys
    if keys is None:
        return []
    animated = {c.data_path for c in fcurves_of(keys)
                if any(p.co[1] != 0 for p in c.keyframe_points) or c.driver is not None}
    return [k.name for k in keys.key_blocks[1:] if not is_bake_key(k.name)
            and not k.mute and (k.value != 0 or f'key_blocks["{k.name}"].value' in animated)]


def moving_modifiers(context, obj) -> list[str]:
    """The object's modifiers that move its vertices on top of shape keys, as the Mesh Cache
    bake would override them but a shape-key bake would not: those of its deforming stack
    (:func:`wiggly_blender.shot.driver_modifiers`) when that stack moves a vertex by more
    than 1e-6 of the mesh's size at one of the sampled frames of the range, and
    every deforming modifier after one that makes new geometry.  The caller restores the
    frame."""
    try:
        keep, off = driver_modifiers(obj)
    except ShotError:  # a deforming modifier after a generating one
        return [m.name for m in obj.modifiers if m.type in DEFORMING and m.show_viewport
                and m.name != BAKE_NAME]
    keep = [m for m in keep if m.show_viewport]
    if not keep:
        return []
    rest = np.empty(3 * len(obj.data.vertices))
    obj.data.vertices.foreach_get("co", rest)
    rest = rest.reshape(-1, 3)
    size = max(float(np.ptp(rest, axis=0).max()), 1e-300)
    keys = obj.data.shape_keys
    scene = context.scene
    moved = False
    with stack_alone(obj, off, list(keys.key_blocks) if keys is not None else []):
        for f in sampled_frames(scene.frame_start, scene.frame_end):
            scene.frame_set(f)
            co = evaluated_vertices(context, obj)
            moved = co.shape != rest.shape or float(np.abs(co - rest).max()) > 1e-6 * size
            if moved:
                break
    return [m.name for m in keep] if moved else []
