"""The "Wiggly" tab of the 3D Viewport's sidebar (N): groups, material, simulation, bake."""

from __future__ import annotations

import bpy

from . import freshness
from .freshness import secondary_shot
from .operators import _running


class WIGGLY_UL_groups(bpy.types.UIList):
    """The vertex groups of the shot, with their role and handle."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_prop, index=0):
        obj = context.active_object
        missing = obj is not None and obj.vertex_groups.get(item.name) is None
        row = layout.row(align=True)
        row.label(text=item.name, icon="ERROR" if missing else "GROUP_VERTEX")
        row.label(text={"HANDLE": item.handle.name if item.handle else "(no handle)",
                        "FIXED": "fixed", "DRIVEN": "driven"}[item.role])


class _WigglyPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Wiggly"

    @classmethod
    def poll(cls, context):
        obj = context.active_object
        return obj is not None and obj.type == "MESH"


class WIGGLY_PT_main(_WigglyPanel, bpy.types.Panel):
    bl_label = "Wiggly"

    @classmethod
    def poll(cls, context):
        return True

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        if obj is None or obj.type != "MESH":
            layout.label(text="Select a mesh object", icon="INFO")
            return
        scene = context.scene
        fps = scene.render.fps / scene.render.fps_base
        layout.label(text=f"Frames {scene.frame_start}-{scene.frame_end} at {fps:g} fps",
                     icon="TIME")
        s = obj.wiggly
        row = layout.row()
        row.template_list("WIGGLY_UL_groups", "", s, "groups", s, "active_group", rows=3)
        col = row.column(align=True)
        col.operator("wiggly.group_add", icon="ADD", text="")
        col.operator("wiggly.group_remove", icon="REMOVE", text="")
        if 0 <= s.active_group < len(s.groups):
            item = s.groups[s.active_group]
            box = layout.box()
            box.prop(item, "role")
            if item.role == "HANDLE":
                row = box.row(align=True)
                row.prop(item, "handle")
                row.operator("wiggly.add_handle", icon="EMPTY_AXIS", text="")
                row.operator("wiggly.set_rest", icon="PINNED", text="")
                box.prop(item, "stiffness")
            elif item.role == "DRIVEN":
                box.prop(s, "drive_physics")
                if s.drive_physics == "KEYS":
                    box.prop(s, "drive_stiffness")
                else:
                    box.prop(s, "drive_intensity")
                    box.prop(s, "drive_free_modes")


class WIGGLY_PT_material(_WigglyPanel, bpy.types.Panel):
    bl_label = "Material"
    bl_parent_id = "WIGGLY_PT_main"

    def draw(self, context):
        s = context.active_object.wiggly
        layout = self.layout
        layout.use_property_split = True
        for name in ("young", "poisson", "density", "alpha", "beta"):
            layout.prop(s, name)


class WIGGLY_PT_simulation(_WigglyPanel, bpy.types.Panel):
    bl_label = "Simulation"
    bl_parent_id = "WIGGLY_PT_main"

    def draw(self, context):
        s = context.active_object.wiggly
        layout = self.layout
        layout.use_property_split = True
        row = layout.row()
        row.enabled = not secondary_shot(s)  # the free parts' own modes move them
        row.prop(s, "modes")
        for name in ("resolution", "warp", "loop"):
            layout.prop(s, name)
        layout.prop(context.scene, "use_gravity", text="Gravity (scene)")


class WIGGLY_PT_bake(_WigglyPanel, bpy.types.Panel):
    bl_label = "Bake"
    bl_parent_id = "WIGGLY_PT_main"

    def draw(self, context):
        s = context.active_object.wiggly
        layout = self.layout
        layout.use_property_split = True
        if freshness.outdated(context.scene, context.active_object):
            layout.label(text="Out of date: the animation or settings changed since the bake",
                         icon="ERROR")
        layout.prop(s, "bake_as")
        if s.bake_as == "MESH_CACHE":
            layout.prop(s, "cache_dir")
        col = layout.column(align=True)
        col.scale_y = 1.4
        col.operator("wiggly.bake", icon="PLAY" if not _running else "TIME",
                     text="Bake" if not _running else "Baking... (Esc cancels)")
        row = layout.row(align=True)
        row.operator("wiggly.remove_bake", icon="TRASH", text="Remove Bake")
        row.operator("wiggly.export_scene", icon="EXPORT", text="Export Scene")


CLASSES = (WIGGLY_UL_groups, WIGGLY_PT_main, WIGGLY_PT_material, WIGGLY_PT_simulation,
           WIGGLY_PT_bake)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
