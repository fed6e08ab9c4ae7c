"""The add-on's settings: preferences (the wiggly command), per-object shot settings and the
vertex groups wiggly uses, with wiggly's defaults, units and tooltips (docs/scene-format.md)."""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0)


class WigglyPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    command: StringProperty(
        name="wiggly command",
        description="The wiggly command-line program (a path, or a name on PATH). Bakes run "
                    "it in its own process, so Blender stays responsive and Esc can stop it",
        default="wiggly", subtype="FILE_PATH")

    def draw(self, context):
        self.layout.prop(self, "command")
        self.layout.label(text="e.g. /path/to/wiggly/.venv/bin/wiggly (any Python with wiggly)")


def _folder_property(**kwargs):
    """A folder path that may be relative to the .blend ("//"): Blender 4.5+ asks for the
    option, earlier versions do not know it."""
    try:
        return StringProperty(subtype="DIR_PATH", options={"PATH_SUPPORTS_BLEND_RELATIVE"},
                              **kwargs)
    except TypeError:
        return StringProperty(subtype="DIR_PATH", **kwargs)


def _handle_poll(self, obj) -> bool:
    return obj.type == "EMPTY"


def _store_rest(self, context) -> None:
    """A newly assigned handle's current placement is its rest."""
    if self.handle is not None:
        self.rest_matrix = [v for row in self.handle.matrix_world for v in row]


class WigglyGroup(bpy.types.PropertyGroup):
    """One vertex group of the mesh as a wiggly group (``name`` is the vertex group's)."""

    role: EnumProperty(
        name="Role",
        description="How wiggly uses the vertices of this vertex group",
        items=[("HANDLE", "Handle", "Keyed by an Empty: at each of its keyframes the group is "
                "moved rigidly as the Empty moved from its rest placement", "EMPTY_AXIS", 0),
               ("FIXED", "Fixed", "Held at rest for the whole shot", "PINNED", 1),
               ("DRIVEN", "Driven", "Follows the object's own animation (armature, shape "
                "keys, deform modifiers) at every frame (and subframes where it turns fast)",
                "ARMATURE_DATA", 2)],
        default="HANDLE")
    handle: PointerProperty(
        name="Handle", type=bpy.types.Object, poll=_handle_poll, update=_store_rest,
        description="The Empty whose keyframes key this group (its placement when assigned "
                    "is its rest; Moving Hold keys also stop the group)")
    rest_matrix: FloatVectorProperty(
        name="Rest", size=16, default=IDENTITY,
        description="The handle's rest placement (world matrix, row by row)")
    stiffness: FloatProperty(
        name="Stiffness", default=1e6, min=0.0, soft_min=1.0, soft_max=1e9,
        description="How hard the keys pull (dimensionless; 1e6 meets them to a fraction of a "
                    "millimetre on a 1 m body, 1e3 gives a soft, approximate pose)")


class WigglySettings(bpy.types.PropertyGroup):
    """A shot of one mesh object: material, damping, modes, resolution, warp, groups, bake."""

    groups: CollectionProperty(type=WigglyGroup)
    active_group: IntProperty(name="Active group", default=0)
    young: FloatProperty(
        name="Young's modulus (Pa)", default=2e5, min=1e-3, soft_min=1e3, soft_max=1e8,
        description="Stiffness of the material E (pascals); higher is stiffer and wiggles "
                    "faster")
    poisson: FloatProperty(
        name="Poisson ratio", default=0.45, min=0.0, max=0.499, precision=3,
        description="Incompressibility of the material nu (0 <= nu < 0.5; near 0.5 keeps "
                    "the volume)")
    density: FloatProperty(
        name="Density (kg/m³)", default=1000.0, min=1e-6, soft_max=2e4,
        description="Mass per volume (kg/m³; water is 1000)")
    alpha: FloatProperty(
        name="Mass damping (1/s)", default=0.5, min=0.0, soft_max=10.0,
        description="Rayleigh damping alpha (1/s): damps motion as a whole, also rigid motion")
    beta: FloatProperty(
        name="Stiffness damping", default=0.002, min=0.0, soft_max=0.1, precision=4,
        subtype="TIME_ABSOLUTE", unit="TIME_ABSOLUTE",
        description="Rayleigh damping beta (seconds): damps fast wiggles more than slow ones")
    modes: IntProperty(
        name="Modes", default=40, min=1, max=500,
        description="Number of eigenmodes (a free body needs at least its 6 rigid ones); a "
                    "secondary-motion shot moves its free parts in Free modes instead")
    resolution: IntProperty(
        name="Resolution", default=25, min=2, max=200,
        description="Tetrahedral mesh resolution: target tet edges along the bounding box "
                    "diagonal")
    warp: BoolProperty(
        name="Warp", default=True,
        description="Rotation-strain warping: large rotations keep the shape, and a driven "
                    "shot's free parts swing and sag in the turning body's frame (off: "
                    "linear, faster, large rotations distort)")
    loop: BoolProperty(
        name="Loop", default=False,
        description="A seamless cycle: the last frame's positions and velocities equal the "
                    "first's")
    drive_physics: EnumProperty(
        name="Drive physics",
        description="How the Driven group's animation moves the body",
        items=[("SECONDARY", "Secondary motion", "The animation owns the Driven group, which "
                "follows it as closely as the tet mesh can; physics moves the free parts, "
                "pushed by its "
                "accelerations"),
               ("KEYS", "Keys", "The Driven group is keyed to the animation at every frame "
                "(Drive stiffness) and the whole body minimises the spacetime energy")],
        default="SECONDARY")
    drive_intensity: FloatProperty(
        name="Intensity", default=1.0, min=0.0, max=100.0, soft_max=2.0,
        description="Secondary motion: scales the animation's push on the free parts without "
                    "changing their timing (1 physical, 0 no push: gravity alone sags them, 2 "
                    "twice the swing)")
    drive_free_modes: IntProperty(
        name="Free modes", default=24, min=1, max=500,
        description="Secondary motion: modes of the free parts with the Driven group held "
                    "(more: finer wiggles, slower)")
    drive_stiffness: FloatProperty(
        name="Drive stiffness", default=1e12, min=0.0, soft_min=1.0,
        description="Keys physics: how hard the driven group follows the object's own "
                    "animation (dimensionless)")
    bake_as: EnumProperty(
        name="Bake as",
        description="Where the baked motion lands",
        items=[("MESH_CACHE", "Mesh Cache (PC2)", "A point cache file played by a Mesh Cache "
                "modifier (compact; works over an armature)"),
               ("SHAPE_KEYS", "Shape Keys", "A shape key per frame, keyed on its frame "
                "(self-contained in the .blend)")],
        default="MESH_CACHE")
    cache_dir: _folder_property(
        name="Cache folder", default="//wiggly/",
        description="Where the Mesh Cache bake writes its .pc2 file (// is the .blend's folder)")


CLASSES = (WigglyPreferences, WigglyGroup, WigglySettings)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.wiggly = PointerProperty(type=WigglySettings)


def unregister() -> None:
    del bpy.types.Object.wiggly
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
