"""Run by Blender's Python (PyPI ``bpy``): the wiggly add-on on scenes built here, as an
animator would set them up; prints what Blender then shows as JSON (tests/test_blender_addon.py,
benchmarks/bench_blender.py).

usage: python wiggly_addon.py CASE OUT.json WIGGLY_COMMAND WORKDIR [OPTIONS.json]
"""

from __future__ import annotations

import io
import json
import math
import re
import shutil
import subprocess
import sys
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import bpy
import numpy as np
from rigs import two_bone_rig  # beside this script

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "blender"))
import wiggly_blender  # noqa: E402
from wiggly_blender import bake, freshness, shot  # noqa: E402

case, out, command, workdir = sys.argv[1:5]
options = json.loads(Path(sys.argv[5]).read_text()) if len(sys.argv) > 5 else {}
workdir = Path(workdir)
#: a folder that exists and takes no file, whoever runs the tests (root included)
UNWRITABLE = "/sys/kernel"
report: dict = {}


def fresh(fps: int = 24, fps_base: float = 1.0, frames=(1, 25)) -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    if not hasattr(bpy.types.Object, "wiggly"):
        wiggly_blender.register()
    if "wiggly_blender" not in bpy.context.preferences.addons:
        bpy.context.preferences.addons.new().module = "wiggly_blender"
    prefs = bpy.context.preferences.addons["wiggly_blender"].preferences
    prefs.command = command
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = fps, fps_base
    scene.frame_start, scene.frame_end = frames
    return scene


def box_mesh(name: str, size=(1.0, 0.2, 0.2), cuts: int = 5, at=(0.3, -0.2, 0.5)):
    """A subdivided box from x = 0 to size[0] (placed at ``at``), the active object."""
    import bmesh  # importable once bpy is

    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=cuts, use_grid_fill=True)
    for v in bm.verts:
        v.co.x = (v.co.x + 0.5) * size[0]
        v.co.y *= size[1]
        v.co.z *= size[2]
    bm.to_mesh(mesh)
    bm.free()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = at
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    obj.select_set(True)
    return obj


def vertex_group(obj, name: str, test) -> list[int]:
    idx = [v.index for v in obj.data.vertices if test(v.co)]
    obj.vertex_groups.new(name=name).add(idx, 1.0, "REPLACE")
    return idx


def use_group(obj, name: str, role: str = "HANDLE") -> None:
    obj.vertex_groups.active_index = obj.vertex_groups[name].index
    assert bpy.ops.wiggly.group_add() == {"FINISHED"}
    obj.wiggly.groups[-1].role = role


def key_handle(handle, frame: float, location=None, rotation=None, still=False) -> None:
    if location is not None:
        handle.location = location
    if rotation is not None:
        handle.rotation_euler = [math.radians(a) for a in rotation]
    handle.keyframe_insert("location", frame=frame)
    handle.keyframe_insert("rotation_euler", frame=frame)
    if still:
        for curve in bake.fcurves_of(handle):
            for p in curve.keyframe_points:
                if abs(p.co[0] - frame) < 1e-9:
                    p.type = "MOVING_HOLD"


def evaluated(obj, frames) -> list:
    """World positions of the evaluated object at each frame."""
    scene, out = bpy.context.scene, []
    for f in frames:
        scene.frame_set(f)
        ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        m = ev.to_mesh()
        co = np.empty(3 * len(m.vertices))
        m.vertices.foreach_get("co", co)
        ev.to_mesh_clear()
        world = np.array([list(r) for r in ev.matrix_world])
        out.append((co.reshape(-1, 3) @ world[:3, :3].T + world[:3, 3]).tolist())
    return out


def run(op, **kwargs) -> dict:
    """An operator's result and what it printed (Blender prints its reports headless)."""
    text = io.StringIO()
    with redirect_stdout(text), redirect_stderr(text):
        try:
            result = sorted(op(**kwargs))
        except RuntimeError as e:  # bpy raises reports of ERROR level as RuntimeError
            result = ["RuntimeError", str(e)]
    return {"result": result, "printed": text.getvalue()}


def handles_scene(bake_as: str) -> object:
    """A bar: its left end keyed by a handle (still at rest, lifted and turned, back at rest),
    a fixed middle ring, the rest free; the user's own shape key and modifier on it."""
    obj = box_mesh("Bar")
    vertex_group(obj, "left end.001", lambda c: c.x < 0.05)
    vertex_group(obj, "middle", lambda c: 0.45 < c.x < 0.55)
    vertex_group(obj, "unused", lambda c: c.x > 0.95)
    obj.shape_key_add(name="Basis")
    own = obj.shape_key_add(name="own")
    own.data[0].co.z += 0.001
    own.value = 0.0  # a shape key at work would add to a shape-key bake (a warning says so)
    obj.modifiers.new("own smooth", "SMOOTH").factor = 0.0  # the user's own, kept
    use_group(obj, "left end.001")
    use_group(obj, "middle", "FIXED")
    s = obj.wiggly
    s.active_group = 0
    assert bpy.ops.wiggly.add_handle() == {"FINISHED"}
    handle = s.groups[0].handle
    fs = bpy.context.scene.frame_start
    key_handle(handle, fs, still=True)
    rest = list(handle.location)
    key_handle(handle, fs + 8, [rest[0] - 0.05, rest[1] + 0.02, rest[2] + 0.15], (10, -20, 30))
    key_handle(handle, fs + 16.5, rest, (0, 0, 0), still=True)  # a subframe key
    key_handle(handle, fs + 400, rest)  # outside the range: left out with a warning
    s.modes, s.resolution, s.young = 16, 10, 5e4
    s.bake_as = bake_as
    s.cache_dir = str(workdir / "cache")
    return obj


def case_handles() -> None:
    fps, base, frames = options.get("fps", 24), options.get("fps_base", 1.0), options["frames"]
    scene = fresh(fps, base, tuple(frames))
    obj = handles_scene(options.get("bake_as", "MESH_CACHE"))
    obj.wiggly.loop = options.get("loop", False)
    handle = obj.wiggly.groups[0].handle
    before = [(c.data_path, c.array_index, [tuple(p.co) for p in c.keyframe_points])
              for c in bake.fcurves_of(handle)]
    export = workdir / "shot.toml"
    report["export"] = run(bpy.ops.wiggly.export_scene, filepath=str(export))
    report["export_again"] = run(bpy.ops.wiggly.export_scene, filepath=str(export))
    report["files"] = sorted(p.name for p in workdir.iterdir())
    report["bake"] = run(bpy.ops.wiggly.bake)
    report["bake_again"] = run(bpy.ops.wiggly.bake)  # replaces only wiggly's own bake
    after = [(c.data_path, c.array_index, [tuple(p.co) for p in c.keyframe_points])
             for c in bake.fcurves_of(handle)]
    report["handle_keys_kept"] = before == after
    report["modifiers"] = [(m.name, m.type) for m in obj.modifiers]
    keys = obj.data.shape_keys
    report["shape_keys"] = [k.name for k in keys.key_blocks]
    report["shape_key_curves"] = sorted({c.data_path for c in bake.fcurves_of(keys)})
    report["frame_range"] = [scene.frame_start, scene.frame_end]
    report["fps"] = scene.render.fps / scene.render.fps_base
    report["positions"] = evaluated(obj, range(scene.frame_start, scene.frame_end + 1))
    cache = [m for m in obj.modifiers if m.name == shot.BAKE_NAME]
    if cache:
        cache[0].show_viewport = False  # without the bake: the object as it was
    else:
        for k in keys.key_blocks:
            k.mute = k.name.startswith(shot.SHAPE_PREFIX)
    report["unbaked"] = evaluated(obj, [scene.frame_start + 8])
    report["rest_world"] = evaluated(obj, [scene.frame_start])[0]
    report["remove"] = run(bpy.ops.wiggly.remove_bake)
    report["after_remove"] = {"modifiers": [m.name for m in obj.modifiers],
                              "shape_keys": [k.name for k in obj.data.shape_keys.key_blocks]}


def armature_bar():
    """A bar skinned to two bones; the second bends up and back over the frames."""
    obj = box_mesh("Tail", size=(1.0, 0.16, 0.16), cuts=6, at=(0.0, 0.0, 0.0))
    rig = two_bone_rig()
    w = {}
    for v in obj.data.vertices:
        t = min(max((v.co.x - 0.35) / 0.3, 0.0), 1.0)
        w.setdefault(("root", 1 - t), []).append(v.index)
        w.setdefault(("tip", t), []).append(v.index)
    for (bone, weight), idx in w.items():
        group = obj.vertex_groups.get(bone) or obj.vertex_groups.new(name=bone)
        group.add(idx, weight, "REPLACE")
    obj.modifiers.new("Armature", "ARMATURE").object = rig
    pose = rig.pose.bones["tip"]
    pose.rotation_mode = "XYZ"
    fs, fe = bpy.context.scene.frame_start, bpy.context.scene.frame_end
    for f, angle in ((fs, 0.0), ((fs + fe) // 2, 35.0), (fe, -10.0)):
        pose.rotation_euler = (0.0, math.radians(angle), 0.0)
        pose.keyframe_insert("rotation_euler", frame=f)
    vertex_group(obj, "body", lambda c: c.x < 0.7)
    bpy.context.view_layer.objects.active = obj
    return obj, rig


def case_driven() -> None:
    scene = fresh(24, 1.0, tuple(options["frames"]))
    obj, rig = armature_bar()
    use_group(obj, "body", "DRIVEN")
    s = obj.wiggly
    s.modes, s.resolution, s.young = 16, 10, 5e4
    s.cache_dir = str(workdir / "cache")
    report["original"] = evaluated(obj, range(scene.frame_start, scene.frame_end + 1))
    report["export"] = run(bpy.ops.wiggly.export_scene, filepath=str(workdir / "shot.toml"))
    report["bake"] = run(bpy.ops.wiggly.bake)
    report["modifiers"] = [(m.name, m.type) for m in obj.modifiers]
    report["positions"] = evaluated(obj, range(scene.frame_start, scene.frame_end + 1))
    report["body"] = [v.index for v in obj.data.vertices if v.co.x < 0.7]
    report["warnings"] = shot.gather(bpy.context, obj).warnings
    # the bake goes out of date when the animation or a setting changes, not on playback
    fresh_now = [freshness.outdated(scene, obj)]
    scene.frame_set(scene.frame_start + 3)
    fresh_now.append(freshness.outdated(scene, obj))
    tip = rig.pose.bones["tip"]
    tip.rotation_euler = (0.0, math.radians(60.0), 0.0)
    tip.keyframe_insert("rotation_euler", frame=scene.frame_start + 1)
    fresh_now.append(freshness.outdated(scene, obj))
    tip.keyframe_delete("rotation_euler", frame=scene.frame_start + 1)  # the animation as before
    run(bpy.ops.wiggly.remove_bake)  # no bake: nothing out of date
    fresh_now.append(freshness.outdated(scene, obj))
    run(bpy.ops.wiggly.bake)  # baked again: fresh
    fresh_now.append(freshness.outdated(scene, obj))
    s.young *= 2
    fresh_now.append(freshness.outdated(scene, obj))
    s.young /= 2
    fresh_now.append(freshness.outdated(scene, obj))
    s.modes += 4  # the body's modes: not what moves a secondary motion's free parts
    fresh_now.append(freshness.outdated(scene, obj))
    s.modes -= 4
    report["outdated"] = fresh_now
    s.bake_as = "SHAPE_KEYS"
    report["shape_keys"] = run(bpy.ops.wiggly.bake)
    s.drive_intensity, s.drive_free_modes = 0.5, 12
    report["export_half"] = run(bpy.ops.wiggly.export_scene,
                                filepath=str(workdir / "shot_half.toml"))
    s.drive_physics = "KEYS"
    report["export_keys"] = run(bpy.ops.wiggly.export_scene,
                                filepath=str(workdir / "shot_keys.toml"))
    from mathutils import Matrix  # the rig left at rest: the driven group is held still

    rig.animation_data_clear()
    for bone in rig.pose.bones:
        bone.matrix_basis = Matrix()
    empty = bpy.data.objects.new("stray handle", None)  # a handle left on a Driven group
    bpy.context.scene.collection.objects.link(empty)
    s.groups[0].handle = empty
    report["still_rig"] = shot.gather(bpy.context, obj).warnings


def case_turning() -> None:
    """The armature bar's rig turned by 180 degrees about the vertical in half a second (15
    degrees per frame at 24 fps), then held: exported and baked."""
    scene = fresh(24, 1.0, (1, 25))
    obj, rig = armature_bar()
    use_group(obj, "body", "DRIVEN")
    from mathutils import Matrix

    root = rig.pose.bones["root"]
    root.rotation_mode = "QUATERNION"
    rest = root.bone.matrix_local.copy()
    for f, angle in ((1, 0.0), (13, 180.0)):
        root.matrix = Matrix.Rotation(math.radians(angle), 4, "Z") @ rest
        bpy.context.view_layer.update()
        root.keyframe_insert("rotation_quaternion", frame=f)
    s = obj.wiggly
    s.modes, s.resolution, s.young = 16, 10, 5e4
    s.cache_dir = str(workdir / "cache")
    report["export"] = run(bpy.ops.wiggly.export_scene, filepath=str(workdir / "turn.toml"))
    report["bake"] = run(bpy.ops.wiggly.bake)
    report["frames"] = [scene.frame_start, scene.frame_end]


def case_errors() -> None:
    """Each mistake: the operator's result and printed report, and gather()'s message."""
    out = {}

    def attempt(label, op=bpy.ops.wiggly.bake, **kwargs):
        try:
            shot.gather(bpy.context, bpy.context.active_object)
            message = None
        except shot.ShotError as e:
            message = str(e)
        out[label] = {"message": message, **run(op, **kwargs)}

    fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    obj.vertex_groups["left end.001"].name = "renamed"
    attempt("no vertex group")
    obj.vertex_groups["renamed"].name = "left end.001"
    obj.vertex_groups["middle"].remove(list(range(len(obj.data.vertices))))
    attempt("empty vertex group")
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    obj.wiggly.groups[0].handle = None
    attempt("no handle")
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    handle = obj.wiggly.groups[0].handle
    handle.animation_data_clear()
    attempt("unkeyed handle")
    handle.keyframe_insert("scale", frame=5)
    attempt("scale-only keys")
    for collection in list(handle.users_collection):  # X in the viewport: an orphan
        collection.objects.unlink(handle)
    attempt("deleted handle")
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    middle = obj.vertex_groups["middle"]  # a painted falloff: a faint fringe around the ring
    middle.add([v.index for v in obj.data.vertices if 0.3 < v.co.x < 0.45], 0.02, "REPLACE")
    out["faint weights"] = shot.gather(bpy.context, obj).warnings
    probe = object.__new__(wiggly_blender.solve.Solve)  # how wiggly's messages are shown
    probe.folder = workdir / "tmp"
    probe.files = {"mesh": probe.folder / "shot_rest.obj", "scene": probe.folder / "shot.toml",
                   "driver": probe.folder / "shot_drive.npz"}
    probe.result = probe.folder / "result.npz"
    out["plain"] = [probe._plain(text) for text in (
        f"{probe.folder}/shot_rest.obj: the mesh is 52 m across",
        "shot.toml: 1 keyframe missed (keyframes[1] (group 'tip', t = 0.5 s) by 3 mm): raise "
        "material.young, or lower simulation.gravity; mesh.resolution",
        "the driver shot_drive.npz jumps: its driven vertices move 0.3 m",
        "[wiggly] secondary motion on shot_drive.npz (24 modes of the free parts)",
        "result.npz", "a larger driven group or a lower drive.intensity may help",
        "shot.toml: simulation.fixed = ['bottom', 'all'] holds every vertex of "
        "shot_rest.obj's tet mesh",
        "raise mesh.resolution; and check that mesh.path is the driver's mesh at its rest pose "
        "(for glTF, the same file; for USD, an OBJ of it), not another scale or pose of it")]
    from types import SimpleNamespace  # a shot from frame 1001 at 30 fps, y up -> z up

    probe.shot = SimpleNamespace(frame_start=1001, fps=30.0,
                                 labels={"left_end_001": "left end.001", "tip": "tip"},
                                 local=lambda p: np.array([p[0], -p[2], p[1]]))
    out["blender terms"] = [probe._plain(text) for text in (
        "turns by up to 22 degrees from one frame to the next (t = 0.5 to 0.533333 s): export",
        "keyframes[1] (group 'left_end_001', t = 0.5 s) missed by 3 mm",
        "bends almost freely at a joint near (-0.355, 0.548, 0.00182) m; gravity (0, -9.81, 0) "
        "m/s^2",
        "moves 0.3 m between t = 0.5 and 0.533333 s; at 1.95833 s 671 mm from their pose at 0 s")]
    probe.shot = None
    probe.log = probe.folder / "wiggly.log"  # the status bar: the last stage, not a warning
    probe.folder.mkdir(parents=True, exist_ok=True)
    probe.log.write_text("[wiggly] checking shot_rest.obj (12 triangles)\n"
                         "[wiggly] tetrahedralizing shot_rest.obj (fTetWild: 3 s)\r"
                         "[wiggly] tetrahedralizing shot_rest.obj (fTetWild: 9 s)\n"
                         "wiggly: warning: shot.toml: " + "a long paragraph " * 20 + "\n")
    out["status"] = probe.status()
    obj.scale = (-1.0, 1.0, 1.0)  # mirrored: its world triangles wind the other way
    out["mirrored export"] = run(bpy.ops.wiggly.export_scene,
                                 filepath=str(workdir / "mirrored.toml"))
    fresh(24, 1.0, (1, 13))
    obj, _ = armature_bar()
    use_group(obj, "body", "DRIVEN")
    obj.wiggly.cache_dir = str(workdir / "cache")
    sub = obj.modifiers.new("Subdivision", "SUBSURF")
    obj.modifiers.move(len(obj.modifiers) - 1, 0)
    attempt("unsupported modifier")
    obj.modifiers.remove(sub)
    mirror = obj.modifiers.new("Mirror", "MIRROR")
    obj.modifiers.move(len(obj.modifiers) - 1, 0)
    attempt("mirror above the rig")
    obj.modifiers.remove(mirror)
    tree = bpy.data.node_groups.new("more vertices", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    n_in, n_out = tree.nodes.new("NodeGroupInput"), tree.nodes.new("NodeGroupOutput")
    subdivide = tree.nodes.new("GeometryNodeSubdivideMesh")
    tree.links.new(n_in.outputs[0], subdivide.inputs[0])
    tree.links.new(subdivide.outputs[0], n_out.inputs[0])
    nodes = obj.modifiers.new("Refine", "NODES")
    nodes.node_group = tree
    attempt("driver vertex count")
    obj.modifiers.remove(nodes)
    bpy.context.preferences.addons["wiggly_blender"].preferences.command = str(
        workdir / "no-such-wiggly")
    attempt("no wiggly command")
    bpy.context.preferences.addons["wiggly_blender"].preferences.command = str(workdir)
    attempt("a folder as wiggly command")
    (workdir / "notes.txt").write_text("not a program\n")
    bpy.context.preferences.addons["wiggly_blender"].preferences.command = str(
        workdir / "notes.txt")
    attempt("a text file as wiggly command")
    bpy.context.preferences.addons["wiggly_blender"].preferences.command = "//bin/wiggly"
    attempt("a blend-relative wiggly command")
    bpy.context.preferences.addons["wiggly_blender"].preferences.command = command
    obj.wiggly.modes = 500  # more modes than the coarse tet mesh has: wiggly refuses
    obj.wiggly.resolution = 2
    attempt("wiggly refuses")
    obj.wiggly.modes = 16
    obj.wiggly.cache_dir = "//wiggly/"  # the .blend is not saved
    obj.wiggly.resolution = 10
    attempt("unsaved blend")
    obj.wiggly.cache_dir = UNWRITABLE  # a folder that exists and takes no file
    attempt("unwritable cache folder")
    out["unwritable export folder"] = run(bpy.ops.wiggly.export_scene,
                                          filepath=f"{UNWRITABLE}/shot.toml")
    obj.wiggly.cache_dir = str(workdir / "cache")
    prefs = bpy.context.preferences.addons["wiggly_blender"].preferences
    prefs.command = shutil.which("true")  # a command that exits 0 and writes nothing
    attempt("no result")
    prefs.command = command
    obj.location.x += 0.1
    obj.keyframe_insert("location", frame=1)
    attempt("animated transform")
    obj.animation_data_clear()
    rig = bpy.data.objects.new("Mover", None)  # an Empty parent carrying the object along
    bpy.context.scene.collection.objects.link(rig)
    obj.parent = rig
    rig.keyframe_insert("location", frame=1)
    rig.location.x += 1.0
    rig.keyframe_insert("location", frame=13)
    attempt("animated parent")
    obj.parent = None
    follow = obj.constraints.new("COPY_LOCATION")  # a constraint on an animated target
    follow.target, follow.use_offset = rig, True
    attempt("constrained placement")
    obj.constraints.remove(follow)
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("SHAPE_KEYS")
    twin = obj.copy()  # Alt+D: a second object on the same mesh
    bpy.context.scene.collection.objects.link(twin)
    attempt("shared mesh")
    fresh(24, 1.0, (1, 13))
    bpy.ops.mesh.primitive_cube_add()
    attempt("no groups")
    report["errors"] = out


def case_housekeeping() -> None:
    """Cache files of look-alike names; a bake from Edit Mode; the Basis a bake adds."""
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    names = ["My Obj", "My_Obj", "my_obj", "My?Obj"]
    paths = []
    for name in names:
        obj.name = name
        paths.append(str(bake.cache_path(obj)))
    report["cache_paths"] = paths
    import bmesh

    obj.name = "Bar"
    bpy.context.view_layer.objects.active = obj
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=1, use_grid_fill=True)
    bmesh.update_edit_mesh(obj.data)
    report["edit_vertices"] = len(bm.verts)
    report["edit_bake"] = run(bpy.ops.wiggly.bake)
    bpy.ops.object.mode_set(mode="OBJECT")
    report["mesh_vertices"] = len(obj.data.vertices)
    cache = next(m for m in obj.modifiers if m.name == shot.BAKE_NAME)
    with open(bpy.path.abspath(cache.filepath), "rb") as f:
        report["pc2_vertices"] = int.from_bytes(f.read(20)[16:20], "little")
    report["moved"] = float(np.abs(np.array(evaluated(obj, [9])[0])
                                   - np.array(evaluated(obj, [1])[0])).max())
    fresh(24, 1.0, (1, 13))
    obj = handles_scene("SHAPE_KEYS")
    obj.shape_key_clear()  # a mesh with no shape keys of its own
    report["keys_bake"] = run(bpy.ops.wiggly.bake)
    report["keys_baked"] = len(obj.data.shape_keys.key_blocks)
    report["keys_outdated"] = [freshness.outdated(bpy.context.scene, obj)]
    report["keys_rebake"] = run(bpy.ops.wiggly.bake)
    report["keys_outdated"].append(freshness.outdated(bpy.context.scene, obj))
    obj.wiggly.young *= 2  # a real change is still seen
    report["keys_outdated"].append(freshness.outdated(bpy.context.scene, obj))
    report["keys_actions"] = len(bpy.data.actions)  # the handle's and the bake's
    report["keys_remove"] = run(bpy.ops.wiggly.remove_bake)
    report["keys_after"] = obj.data.shape_keys is not None
    report["actions_after"] = len(bpy.data.actions)  # the handle's: none left behind


def case_modal() -> None:
    """The modal Bake as Blender drives it (timer events, then Esc or the end), its methods
    called on a stand-in operator: bpy as a module has no event loop to run a modal operator."""
    from types import MethodType, SimpleNamespace

    from wiggly_blender import operators

    context = bpy.context
    for scenario in ("escape", "finish", "deleted", "edited"):
        fresh(24, 1.0, (1, 25))
        obj = handles_scene("MESH_CACHE")
        if scenario == "escape":
            obj.wiggly.resolution = 40  # a longer solve
        reports = []

        def note(kind, text, out=reports):
            out.append([sorted(kind)[0], text])

        op = SimpleNamespace(report=note)
        for name in ("_prepare", "_finish", "_status", "_end", "modal", "_target",
                     "_check_unchanged", "_stop"):
            setattr(op, name, MethodType(getattr(operators.WIGGLY_OT_bake, name), op))
        assert op._prepare(context)
        operators._running["op"] = op  # what invoke() does besides the event handler
        op.timer = context.window_manager.event_timer_add(0.2, window=context.window)
        seen = {"blocked": not operators.WIGGLY_OT_bake.poll(context), "events": 0}
        while True:
            time.sleep(0.05)
            if scenario == "escape" and op.solve.status().startswith("[wiggly]"):
                seen["status"] = op.solve.status()
                seen["running_before"] = op.solve.poll() is None
                t = time.perf_counter()
                result = op.modal(context, SimpleNamespace(type="ESC"))
                seen["cancel_seconds"] = time.perf_counter() - t
                break
            if seen["events"] == 1 and scenario == "deleted":  # while wiggly solves
                bpy.data.objects.remove(obj)
            if seen["events"] == 1 and scenario == "edited":  # a vertex fewer
                import bmesh

                bm = bmesh.new()
                bm.from_mesh(obj.data)
                bm.verts.ensure_lookup_table()
                bmesh.ops.delete(bm, geom=[bm.verts[0]], context="VERTS")
                bm.to_mesh(obj.data)
                bm.free()
            result = op.modal(context, SimpleNamespace(type="TIMER"))
            seen["events"] += 1
            if result != {"PASS_THROUGH"}:
                break
        alive = scenario != "deleted"
        if op.solve.process.poll() is None:
            op.solve.process.wait(timeout=5)
        seen.update(result=sorted(result), reports=reports, running=bool(operators._running),
                    returncode=op.solve.process.returncode, pid=op.solve.process.pid,
                    folder_left=op.solve.folder.exists(),
                    modifiers=[m.name for m in obj.modifiers] if alive else None,
                    poll_after=operators.WIGGLY_OT_bake.poll(context) if alive else True)
        report[scenario] = seen


def case_critter() -> None:
    """The critter bake of the benchmark: its surface, the demo's groups, keyed handles."""
    spec = json.loads(Path(options["critter"]).read_text())
    scene = fresh(options.get("fps", 24), 1.0, tuple(options["frames"]))
    mesh = bpy.data.meshes.new("critter")
    V = np.array(spec["vertices"])
    mesh.from_pydata(V.tolist(), [], spec["faces"])
    obj = bpy.data.objects.new("critter", mesh)
    scene.collection.objects.link(obj)
    bpy.context.view_layer.objects.active = obj
    for name, idx in spec["groups"].items():
        obj.vertex_groups.new(name=name).add(idx, 1.0, "REPLACE")
    s = obj.wiggly
    s.modes, s.resolution, s.warp = spec["modes"], spec["resolution"], True
    s.young, s.alpha, s.beta = spec["young"], spec["alpha"], spec["beta"]
    s.cache_dir = str(workdir / "cache")
    for name, keys in spec["handles"].items():
        use_group(obj, name)
        s.active_group = len(s.groups) - 1
        bpy.ops.wiggly.add_handle()
        handle = s.groups[-1].handle
        rest = np.array(handle.location)
        for frame, offset, still in keys:
            key_handle(handle, frame, (rest + offset).tolist(), (0, 0, 0), still)
    export = workdir / "critter.toml"
    report["export"] = run(bpy.ops.wiggly.export_scene, filepath=str(export), overwrite=True)
    cli = [command, "animate", str(export), "-o", str(workdir / "cli.npz"), "--overwrite"]
    if options.get("cli"):
        subprocess.run(cli, check=True, capture_output=True)  # warms the caches
    report.update(bake_seconds=[], cli_seconds=[], phases=[])
    for _ in range(options.get("repeat", 1)):
        t = time.perf_counter()
        report["bake"] = run(bpy.ops.wiggly.bake)
        report["bake_seconds"].append(time.perf_counter() - t)
        found = re.search(r"\(gather ([\d.]+) s, write ([\d.]+) s, wiggly ([\d.]+) s, bake "
                          r"([\d.]+) s\)", report["bake"]["printed"])
        report["phases"].append([float(x) for x in found.groups()] if found else [])
        if options.get("cli"):
            t = time.perf_counter()
            subprocess.run(cli, check=True, capture_output=True)
            report["cli_seconds"].append(time.perf_counter() - t)
    report["frames"] = [scene.frame_start, scene.frame_end]
    report["vertices"] = len(obj.data.vertices)
    report["blender"] = bpy.app.version_string
    if options.get("positions"):
        report["positions"] = evaluated(obj, range(scene.frame_start, scene.frame_end + 1))


def _color(obj, rgba_of_vertex) -> None:
    """A point color attribute for Workbench's vertex colour shading."""
    attr = obj.data.color_attributes.new("wiggly", "FLOAT_COLOR", "POINT")
    for v in obj.data.vertices:
        attr.data[v.index].color = rgba_of_vertex(v)
    obj.data.color_attributes.active_color = attr


def _handle_proxy(handle, size: float = 0.12):
    """Arrows of the handle's axes as a mesh (renders do not draw Empties)."""
    verts, faces, colors = [], [], []
    for axis, rgba in enumerate(((0.9, 0.2, 0.2, 1), (0.3, 0.8, 0.2, 1), (0.2, 0.4, 0.95, 1))):
        lo, hi = [-0.008] * 3, [0.008] * 3
        hi[axis] = size
        base = len(verts)
        verts += [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        faces += [[base + i for i in f] for f in ((0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1),
                                                 (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3))]
        colors += [rgba] * 8
    mesh = bpy.data.meshes.new("handle proxy")
    mesh.from_pydata(verts, [], faces)
    proxy = bpy.data.objects.new("handle proxy", mesh)
    bpy.context.scene.collection.objects.link(proxy)
    proxy.parent = handle
    _color(proxy, lambda v: colors[v.index])
    return proxy


def case_pictures() -> None:
    """Workbench renders of the handle bake, the timeline's data, the panel's layout."""
    scene = fresh(24, 1.0, (1, 25))
    obj = handles_scene("MESH_CACHE")
    scene.use_gravity = False  # the swing of the free end, not its sag
    obj.wiggly.groups.remove(1)  # the middle is free too
    obj.wiggly.active_group = 0
    blue, grey = (0.25, 0.45, 0.95, 1), (0.78, 0.78, 0.74, 1)
    groups = {obj.vertex_groups["left end.001"].index: blue}
    _color(obj, lambda v: next((groups[g.group] for g in v.groups if g.group in groups), grey))
    handle = obj.wiggly.groups[0].handle
    vertex_group(obj, "whole", lambda c: True)  # the whole bar: still, at rest, on frame 1
    use_group(obj, "whole")
    obj.wiggly.active_group = 1
    bpy.ops.wiggly.add_handle()
    key_handle(obj.wiggly.groups[1].handle, 1, still=True)
    obj.wiggly.active_group = 0
    _handle_proxy(handle)
    bpy.ops.wm.save_as_mainfile(filepath=str(workdir / "bar.blend"))
    obj.wiggly.cache_dir = "//wiggly/"  # beside the .blend, the default
    report["bake"] = run(bpy.ops.wiggly.bake)
    target = bpy.data.objects.new("target", None)
    target.location = (0.8, -0.2, 0.55)
    scene.collection.objects.link(target)
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.location = (1.9, -2.4, 1.35)
    cam.data.lens = 50
    scene.collection.objects.link(cam)
    cam.constraints.new("TRACK_TO").target = target
    scene.camera = cam
    scene.render.engine = "BLENDER_WORKBENCH"
    shading = scene.display.shading
    shading.light, shading.color_type = "STUDIO", "VERTEX"
    shading.show_shadows, shading.show_cavity = True, True
    scene.render.resolution_x, scene.render.resolution_y = options.get("size", [480, 300])
    scene.render.film_transparent = False
    world = bpy.data.worlds.new("world")
    scene.world = world
    frames = options.get("frames", [1, 5, 9, 13, 17, 21, 25])
    report["renders"] = []
    for f in frames:
        scene.frame_set(f)
        scene.render.filepath = str(workdir / f"frame_{f:03d}.png")
        with redirect_stdout(io.StringIO()):
            bpy.ops.render.render(write_still=True)
        report["renders"].append([f, scene.render.filepath])
    # the timeline: the handle's keys and the baked motion of both ends
    report["keys"] = {}
    for item in obj.wiggly.groups:
        keys = {}
        for curve in bake.fcurves_of(item.handle):
            for p in curve.keyframe_points:
                keys[float(p.co[0])] = p.type
        report["keys"][item.handle.name] = sorted(keys.items())
    positions = np.array(evaluated(obj, range(1, 26)))
    world = np.array([list(r) for r in obj.matrix_world])
    rest = np.array([list(v.co) for v in obj.data.vertices]) @ world[:3, :3].T + world[:3, 3]
    x = np.array([v.co.x for v in obj.data.vertices])
    for end, inside in (("left", x < 0.05), ("right", x > 0.95)):  # heights above rest
        report[f"{end}_z"] = (positions[:, inside, 2] - rest[inside, 2]).mean(axis=1).tolist()
    report["panel"] = panel_layout(obj)


class _Recorder:
    """A stand-in for Blender's UILayout that records what a panel's draw() lays out."""

    def __init__(self, kind="column"):
        self.kind, self.items, self.use_property_split, self.scale_y = kind, [], False, 1.0

    def _child(self, kind):
        child = _Recorder(kind)
        self.items.append(child)
        return child

    def row(self, align=False):
        return self._child("row")

    def column(self, align=False):
        return self._child("column")

    def box(self):
        return self._child("box")

    def label(self, text="", icon="NONE"):
        self.items.append({"label": text})

    def operator(self, idname, text=None, icon="NONE"):
        op = getattr(bpy.types, idname.replace(".", "_OT_", 1).upper(), None)
        name = text if text is not None else getattr(op, "bl_label", idname)
        enabled = True
        if op is not None and hasattr(op, "poll"):
            enabled = bool(op.poll(bpy.context))
        self.items.append({"operator": name or "", "icon": icon, "enabled": enabled})

    def prop(self, data, name, text=None, icon="NONE"):
        rna = data.bl_rna.properties[name]
        value = getattr(data, name)
        if rna.type == "ENUM":
            shown = rna.enum_items[value].name
        elif rna.type == "POINTER":
            shown = value.name if value is not None else ""
        elif rna.type == "BOOLEAN":
            shown = bool(value)
        elif rna.type == "FLOAT":
            shown = bpy.utils.units.to_string(
                "METRIC", rna.unit, value, precision=4) if rna.unit != "NONE" else f"{value:g}"
        else:
            shown = str(value)
        self.items.append({"prop": text if text is not None else rna.name, "value": shown,
                           "type": rna.type, "split": self.use_property_split})

    def template_list(self, listtype, list_id, data, prop, active_data, active_prop, rows=3):
        ul = getattr(bpy.types, listtype)
        rows_out = []
        for i, item in enumerate(getattr(data, prop)):
            row = _Recorder("row")
            ul.draw_item(None, bpy.context, row, data, item, 0, active_data, active_prop, i)
            rows_out.append({"cells": row.dump(), "active": i == getattr(active_data,
                                                                          active_prop)})
        self.items.append({"list": rows_out, "rows": rows})

    def dump(self):
        return {"kind": self.kind, "items": [i.dump() if isinstance(i, _Recorder) else i
                                             for i in self.items]}


def case_sweep() -> None:
    """What animators do that the first cases do not: handles and meshes out of the view
    layer's evaluation, wiggly's own warnings, a key of their own named ``wiggly.``, shape
    keys under a rig, export paths, gravity at a unit scale, a Mirror, Add Handle in Edit
    Mode."""
    import bmesh

    scene = fresh(24, 1.0, (1, 13))
    obj = handles_scene("MESH_CACHE")
    handle = obj.wiggly.groups[0].handle
    controls = bpy.data.collections.new("Controls")
    scene.collection.children.link(controls)
    for c in list(handle.users_collection):
        c.objects.unlink(handle)
    controls.objects.link(handle)
    layer = bpy.context.view_layer.layer_collection.children["Controls"]
    layer.exclude = True
    report["excluded_handle"] = run(bpy.ops.wiggly.bake)
    layer.exclude = False
    handle.hide_viewport = True
    report["disabled_handle"] = run(bpy.ops.wiggly.export_scene,
                                    filepath=str(workdir / "hidden.toml"))
    handle.hide_viewport = False
    handle.hide_set(True)  # hidden with H: still evaluated
    # the user's own key named like wiggly's; the left end also fixed: wiggly warns
    obj.shape_key_add(name="wiggly.sag")
    vertex_group(obj, "left fixed", lambda c: c.x < 0.05)
    use_group(obj, "left fixed", "FIXED")
    bpy.context.view_layer.objects.active = obj
    report["warned_bake"] = run(bpy.ops.wiggly.bake)
    report["shape_keys"] = [k.name for k in obj.data.shape_keys.key_blocks]
    first = bpy.path.abspath(obj.modifiers[shot.BAKE_NAME].filepath)
    obj.wiggly.young *= 4  # a re-bake with other settings: a new file, the first one kept
    report["rebake"] = run(bpy.ops.wiggly.bake)
    second = bpy.path.abspath(obj.modifiers[shot.BAKE_NAME].filepath)
    report["bake_files"] = [first, second, Path(first).exists(), Path(second).exists()]
    obj.modifiers.new("Mirror", "MIRROR")
    report["mirror_export"] = run(bpy.ops.wiggly.export_scene,
                                  filepath=str(workdir / "mirror"), overwrite=True)
    report["files"] = sorted(p.name for p in workdir.iterdir())
    report["no_path"] = run(bpy.ops.wiggly.export_scene, filepath="")
    report["relative_unsaved"] = run(bpy.ops.wiggly.export_scene, filepath="//x.toml")
    scene.unit_settings.scale_length = 0.01
    report["centimetres_export"] = run(bpy.ops.wiggly.export_scene,
                                       filepath=str(workdir / "centimetres.toml"))
    report["centimetres"] = (workdir / "centimetres.toml").read_text()
    scene.gravity = (0.0, 0.0, -981.0)
    report["centimetres_earth"] = run(bpy.ops.wiggly.export_scene,
                                      filepath=str(workdir / "centimetres_earth.toml"))

    fresh(24, 1.0, (1, 13))
    obj, _ = armature_bar()
    use_group(obj, "body", "FIXED")
    obj.wiggly.bake_as = "SHAPE_KEYS"
    report["keys_under_rig"] = run(bpy.ops.wiggly.bake)
    obj.wiggly.groups[0].role = "DRIVEN"
    obj.wiggly.bake_as = "MESH_CACHE"
    obj.hide_viewport = True
    report["disabled_driven"] = run(bpy.ops.wiggly.export_scene,
                                    filepath=str(workdir / "driven.toml"))

    fresh(24, 1.0, (1, 13))
    obj = box_mesh("Bar")
    vertex_group(obj, "tip", lambda c: c.x > 0.95)
    use_group(obj, "tip")
    bpy.ops.object.mode_set(mode="EDIT")
    bm = bmesh.from_edit_mesh(obj.data)
    tip = obj.vertex_groups["tip"].index
    layer = bm.verts.layers.deform.active
    for v in bm.verts:
        if tip in v[layer]:
            v.co.z += 0.5
    bmesh.update_edit_mesh(obj.data)
    obj.wiggly.active_group = 0
    report["edit_handle"] = run(bpy.ops.wiggly.add_handle)
    bpy.ops.object.mode_set(mode="OBJECT")
    idx = [v.index for v in obj.data.vertices if any(g.group == tip for g in v.groups)]
    centre = np.mean([list(obj.matrix_world @ obj.data.vertices[i].co) for i in idx], axis=0)
    report["edit_handle_off"] = float(np.abs(np.array(obj.wiggly.groups[0].handle.location)
                                             - centre).max())
    empties = len(bpy.data.objects)  # Add Handle again: no second Empty
    report["second_handle"] = run(bpy.ops.wiggly.add_handle)
    report["second_handle_new_objects"] = len(bpy.data.objects) - empties
    report["second_handle_selected"] = obj.wiggly.groups[0].handle.select_get()


def panel_layout(obj) -> list:
    """The Wiggly panel and its sub-panels as their draw() lays them out for ``obj``."""
    from types import SimpleNamespace

    from wiggly_blender import panel

    obj.wiggly.active_group = 0
    out = []
    for cls in (panel.WIGGLY_PT_main, panel.WIGGLY_PT_material, panel.WIGGLY_PT_simulation,
                panel.WIGGLY_PT_bake):
        layout = _Recorder()
        cls.draw(SimpleNamespace(layout=layout), bpy.context)
        out.append({"title": cls.bl_label, "layout": layout.dump()})
    return out


{"handles": case_handles, "driven": case_driven, "turning": case_turning,
 "errors": case_errors, "modal": case_modal,
 "critter": case_critter, "pictures": case_pictures, "housekeeping": case_housekeeping,
 "sweep": case_sweep}[case]()
Path(out).write_text(json.dumps(report))
