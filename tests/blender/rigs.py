"""Rigs that the tests' Blender scripts build (run by Blender's Python, PyPI ``bpy``)."""

import bpy


def two_bone_rig() -> bpy.types.Object:
    """An armature object "Rig" in the scene: bone "root" along x from 0 to 0.5 and its child
    "tip" from 0.5 to 1, made in Edit Mode; Object Mode again on return."""
    armature = bpy.data.armatures.new("Rig")
    rig = bpy.data.objects.new("Rig", armature)
    bpy.context.scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    root = armature.edit_bones.new("root")
    root.head, root.tail = (0.0, 0.0, 0.0), (0.5, 0.0, 0.0)
    tip = armature.edit_bones.new("tip")
    tip.head, tip.tail, tip.parent = (0.5, 0.0, 0.0), (1.0, 0.0, 0.0), root
    bpy.ops.object.mode_set(mode="OBJECT")
    return rig
