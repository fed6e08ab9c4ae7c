"""Run by Blender's Python (PyPI ``bpy``): import each file given on the command line into a
fresh scene and print, as JSON, what an animator would see (tests/test_blender.py).

usage: python inspect_imports.py OUT.json FPS FRAME [FRAME ...] -- FILE [FILE ...]
"""

import json
import sys

import bpy

out, fps, rest = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
split = rest.index("--")
frames, files = [int(f) for f in rest[:split]], rest[split + 1:]
report = {}


def _fcurves(action):
    """F-curves of an action: Blender 5 keeps them in layered channel bags."""
    curves = list(getattr(action, "fcurves", None) or [])
    for layer in getattr(action, "layers", []):
        for strip in layer.strips:
            for bag in strip.channelbags:
                curves += list(bag.fcurves)
    return curves


for path in files:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = fps, 1.0
    if path.endswith((".glb", ".gltf")):
        bpy.ops.import_scene.gltf(filepath=path)
    else:
        bpy.ops.wm.usd_import(filepath=path)
    meshes = [o for o in scene.objects if o.type == "MESH"]
    obj = meshes[0]
    entry = {
        "objects": [o.name for o in scene.objects],
        "frame_range": [scene.frame_start, scene.frame_end],
        "fps": scene.render.fps / scene.render.fps_base,
        "modifiers": [m.type for m in obj.modifiers],
    }
    keys = obj.data.shape_keys
    if keys is not None:
        entry["shape_keys"] = [k.name for k in keys.key_blocks]
        entry["basis"] = [list(obj.matrix_world @ v.co) for v in keys.key_blocks[0].data]
        entry["slider_ranges"] = [[k.slider_min, k.slider_max] for k in keys.key_blocks[1:]]
        action = keys.animation_data.action if keys.animation_data else None
        entry["key_frames"] = sorted({p.co[0] for c in _fcurves(action) for p in
                                      c.keyframe_points}) if action else []
    positions = {}
    for f in frames:
        scene.frame_set(f)
        depsgraph = bpy.context.evaluated_depsgraph_get()
        evaluated = obj.evaluated_get(depsgraph)
        data = evaluated.to_mesh()
        positions[f] = [list(evaluated.matrix_world @ v.co) for v in data.vertices]
        evaluated.to_mesh_clear()
    entry["positions"] = positions
    report[path] = entry

with open(out, "w") as file:
    json.dump(report, file)
