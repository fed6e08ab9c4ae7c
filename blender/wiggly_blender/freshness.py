"""Whether a bake is out of date: a fingerprint of what it was made from, kept on the object
when it is baked and compared when the panel is drawn.

The fingerprint covers the object's Wiggly settings and groups (role, handle, rest, stiffness;
not the vertex groups' weights), the scene's frame range, frame rate, gravity and unit scale,
the rest mesh's vertices, the object's modifier stack (wiggly's own bake left out), and the
animation of everything that moves the mesh: the object, its parents, the objects its
modifiers use (an armature, a lattice) and their parents, the handles' Empties and the mesh's
shape keys (F-curve keys, NLA strips, static transforms, an armature's bones). Drivers and
constraints are not followed."""

from __future__ import annotations

import hashlib

import numpy as np

from .blender_data import fcurves_of
from .shot import BAKE_ACTION, BAKE_NAME, SHAPE_PREFIX, is_bake_key

#: the object's ID property holding the fingerprint of its bake's inputs
FINGERPRINT = "wiggly_bake_inputs"
#: settings that do not change what a bake is
_NOT_INPUTS = {"rna_type", "groups", "active_group", "cache_dir", "name"}


def _ids(obj) -> list:
    """The data-blocks whose animation or transform moves ``obj``'s mesh, each once."""
    out: list = []

    def add(block) -> None:
        while block is not None and all(block is not b for b in out):
            out.append(block)
            block = getattr(block, "parent", None)

    add(obj)
    for mod in obj.modifiers:
        if mod.name != BAKE_NAME:
            add(getattr(mod, "object", None))
    for item in obj.wiggly.groups:
        add(item.handle)
    keys = obj.data.shape_keys
    if keys is not None and any(not is_bake_key(k.name) for k in keys.key_blocks[1:]):
        out.append(keys)  # the mesh's own shape keys (not only a bake's and its Basis)
    return out


def _numbers(h, values) -> None:
    h.update(np.ascontiguousarray(np.asarray(values, np.float64)).tobytes())


def _animation(h, block) -> None:
    h.update(repr((block.name, type(block).__name__)).encode())
    if hasattr(block, "matrix_basis"):
        _numbers(h, [list(row) for row in block.matrix_basis])
    bones = getattr(getattr(block, "data", None), "bones", None)
    if bones is not None:  # an armature's rest pose
        for bone in bones:
            h.update(bone.name.encode())
            _numbers(h, [list(row) for row in bone.matrix_local])
    for curve in fcurves_of(block):
        if f'"{SHAPE_PREFIX}' in curve.data_path:
            continue  # a shape-key bake's own keys
        h.update(repr((curve.data_path, curve.array_index, curve.mute)).encode())
        points = curve.keyframe_points
        co = np.empty(2 * len(points))
        for attr in ("co", "handle_left", "handle_right"):
            points.foreach_get(attr, co)
            _numbers(h, co)
        h.update(repr([p.interpolation for p in points]).encode())
    data = getattr(block, "animation_data", None)
    if data is not None:
        action = data.action
        ours = action is not None and action.get(BAKE_ACTION)  # a shape-key bake's own
        h.update(repr(None if ours else getattr(action, "name", None)).encode())
        for track in data.nla_tracks:
            h.update(repr((track.name, track.mute, track.is_solo)).encode())
            for strip in track.strips:
                h.update(repr((getattr(strip.action, "name", None), strip.frame_start,
                               strip.frame_end, strip.scale, strip.repeat, strip.blend_type,
                               strip.mute, strip.influence)).encode())


def secondary_shot(settings) -> bool:
    """Whether an object's Wiggly ``settings`` make a secondary-motion shot (a Driven group,
    Drive physics Secondary), whose free parts move in modes of their own: Modes, the
    body's, does not enter it."""
    return (settings.drive_physics == "SECONDARY"
            and any(item.role == "DRIVEN" for item in settings.groups))


def fingerprint(scene, obj) -> str:
    """The fingerprint of what a bake of ``obj`` in ``scene`` is made from (module doc)."""
    h = hashlib.sha256()
    s = obj.wiggly
    unused = {"modes"} if secondary_shot(s) else set()
    for prop in s.bl_rna.properties:
        if prop.identifier not in _NOT_INPUTS | unused:
            h.update(repr((prop.identifier, getattr(s, prop.identifier))).encode())
    for item in s.groups:
        h.update(repr((item.name, item.role, getattr(item.handle, "name", None),
                       item.stiffness)).encode())
        _numbers(h, list(item.rest_matrix))
    h.update(repr((scene.frame_start, scene.frame_end, scene.render.fps,
                   scene.render.fps_base, scene.use_gravity, tuple(scene.gravity),
                   scene.unit_settings.scale_length)).encode())
    mesh = obj.data
    co = np.empty(3 * len(mesh.vertices))
    mesh.vertices.foreach_get("co", co)
    _numbers(h, co)
    h.update(repr((len(mesh.polygons), [(m.name, m.type, m.show_viewport)
                                        for m in obj.modifiers if m.name != BAKE_NAME])).encode())
    for block in _ids(obj):
        _animation(h, block)
    return h.hexdigest()


def outdated(scene, obj) -> bool:
    """Whether ``obj`` has a bake whose inputs changed since it was made."""
    made = obj.get(FINGERPRINT)
    return made is not None and made != fingerprint(scene, obj)
