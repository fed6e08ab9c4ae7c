"""Run by Blender's Python (PyPI ``bpy``): a bar and a cap at its tip, two objects skinned to two
bones, their armature scaled by 2 and moved, animated over frames 1..25 of a 24 fps scene
(Blender's defaults), exported as glTF the way the docs tell a user to, with the meshes as
Blender evaluates them at each frame (tests/test_blender.py).

usage: python make_rig.py OUT.glb OUT.json FRAME [FRAME ...]
"""

import importlib
import json
import math
import sys

import bpy
from rigs import two_bone_rig  # beside this script

bmesh = importlib.import_module("bmesh")  # importable once bpy is

glb, out, frames = sys.argv[1], sys.argv[2], [int(f) for f in sys.argv[3:]]
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps, scene.frame_start, scene.frame_end = 24, 1, 25

mesh = bpy.data.meshes.new("Bar")
bm = bmesh.new()
bmesh.ops.create_cube(bm, size=1.0)
bmesh.ops.scale(bm, vec=(1.0, 0.1, 0.1), verts=bm.verts)
bmesh.ops.translate(bm, vec=(0.5, 0.0, 0.0), verts=bm.verts)  # x from 0 to 1
edges = [e for e in bm.edges if abs(e.verts[0].co.x - e.verts[1].co.x) > 0.5]
bmesh.ops.subdivide_edges(bm, edges=edges, cuts=9, use_grid_fill=True)
bmesh.ops.triangulate(bm, faces=bm.faces)
bm.to_mesh(mesh)
bm.free()
bar = bpy.data.objects.new("Bar", mesh)
scene.collection.objects.link(bar)
cap_mesh = bpy.data.meshes.new("Cap")  # a second object under the rig (glTF node order)
bm = bmesh.new()
bmesh.ops.create_cube(bm, size=0.12)
bmesh.ops.translate(bm, vec=(1.0, 0.0, 0.0), verts=bm.verts)
bmesh.ops.triangulate(bm, faces=bm.faces)
bm.to_mesh(cap_mesh)
bm.free()
cap = bpy.data.objects.new("Cap", cap_mesh)
scene.collection.objects.link(cap)

rig = two_bone_rig()
rig.scale, rig.location = (2.0, 2.0, 2.0), (0.3, -0.2, 0.5)
for obj in (bar, cap):
    obj.parent = rig
    obj.modifiers.new("Armature", "ARMATURE").object = rig
    groups = {name: obj.vertex_groups.new(name=name) for name in ("root", "tip")}
    for v in obj.data.vertices:
        groups["root" if v.co.x < 0.5 else "tip"].add([v.index], 1.0, "REPLACE")

bones = rig.pose.bones
for b in bones:
    b.rotation_mode = "XYZ"
for f in range(1, 26, 4):
    s = (f - 1) / 24
    bones["root"].location = (0.0, 0.4 * s, 0.0)  # along the bone's y: world x
    bones["root"].rotation_euler = (0.0, 0.0, math.radians(40) * math.sin(2 * math.pi * s))
    bones["tip"].rotation_euler = (math.radians(30) * math.sin(4 * math.pi * s), 0.0, 0.0)
    for b in bones:
        b.keyframe_insert("location", frame=f)
        b.keyframe_insert("rotation_euler", frame=f)
scene.frame_set(1)

bpy.ops.object.select_all(action="DESELECT")
bar.select_set(True)
cap.select_set(True)
rig.select_set(True)
bpy.ops.export_scene.gltf(filepath=glb, export_format="GLB", use_selection=True,
                          export_animations=True)


def world(f: int) -> list:
    scene.frame_set(f)
    points = []
    for obj in (bar, cap):
        evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        data = evaluated.to_mesh()
        points += [list(evaluated.matrix_world @ v.co) for v in data.vertices]
        evaluated.to_mesh_clear()
    return points


rig.data.pose_position = "REST"
report = {"rest": world(1)}
rig.data.pose_position = "POSE"
report["frames"] = {f: world(f) for f in frames}
with open(out, "w") as fh:
    json.dump(report, fh)
