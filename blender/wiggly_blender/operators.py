"""Operators: bake (modal, Esc cancels), export scene, the group list, handles, remove bake.
User mistakes are ShotErrors, reported in Blender's status bar and Info log, never a
traceback."""

from __future__ import annotations

import time
from pathlib import Path

import bpy
import numpy as np
from bpy.props import BoolProperty, StringProperty
from bpy_extras.io_utils import ExportHelper

from . import bake, freshness
from .shot import ShotError, gather, write_shot
from .solve import Solve

_running: dict[str, object] = {}  # the one bake in progress: {"op": operator}


def _mesh_poll(cls, context) -> bool:
    obj = context.active_object
    if obj is None or obj.type != "MESH":
        cls.poll_message_set("Select a mesh object: wiggly animates the active mesh")
        return False
    return True


def _prefs(context):
    addon = context.preferences.addons.get(__package__)
    return addon.preferences if addon is not None else None


def _command(context) -> str:
    prefs = _prefs(context)
    return prefs.command if prefs is not None else "wiggly"


def _vertices(obj) -> np.ndarray:
    """The object's mesh vertices (V, 3), object-local."""
    co = np.empty(3 * len(obj.data.vertices))
    obj.data.vertices.foreach_get("co", co)
    return co.reshape(-1, 3)


def _report_warnings(op, shot) -> None:
    for w in shot.warnings:
        op.report({"WARNING"}, w)


class WIGGLY_OT_bake(bpy.types.Operator):
    """Solve the shot with wiggly (in its own process) and bake it onto the object as a Mesh
    Cache or shape keys; Esc cancels"""

    bl_idname = "wiggly.bake"
    bl_label = "Bake Wiggly"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if _running:
            cls.poll_message_set("A wiggly bake is running (Esc cancels it)")
            return False
        if not _mesh_poll(cls, context):
            return False
        if not len(context.active_object.wiggly.groups):
            cls.poll_message_set("Add a vertex group to the Wiggly group list first")
            return False
        return True

    def _prepare(self, context) -> bool:
        self.obj = context.active_object
        self.bake_as = self.obj.wiggly.bake_as  # as checked now: a change waits for the next
        self.warned = 0
        self.times = {}
        t = time.perf_counter()
        try:
            self.shot = gather(context, self.obj)
            self.rest = _vertices(self.obj)  # the mesh as solved (gather left Edit Mode's)
            self.inputs = freshness.fingerprint(context.scene, self.obj)
            self.times["gather"] = time.perf_counter() - t
            if self.bake_as == "MESH_CACHE":
                bake.cache_path(self.obj)  # a cache folder that cannot be, before the solve
            else:
                bake.refuse_driven(self.obj, self.shot)  # bakes that cannot be: now, not
                bake.check_shape_keys(self.obj)  # after the solve
                self._check_stack(context)
            t = time.perf_counter()
            self.solve = Solve(self.shot, _command(context))
        except ShotError as e:
            self.report({"ERROR"}, str(e))
            return False
        self.times["write"] = time.perf_counter() - t
        _report_warnings(self, self.shot)
        self.warned += len(self.shot.warnings)
        self.solve.start()
        return True

    def _target(self):
        """The object being baked (an undo during the solve replaces its Python wrapper:
        found by name), or None when it was deleted."""
        found = bpy.data.objects.get(self.shot.name)
        if found is not None:
            return found
        try:
            self.obj.name  # noqa: B018 - still there, renamed
        except ReferenceError:
            return None
        return self.obj

    def _check_unchanged(self, obj) -> None:
        """ShotError when the mesh was edited during the solve: the bake would not fit it."""
        if obj.mode == "EDIT":
            obj.update_from_editmode()
        co = _vertices(obj)
        if co.shape == self.rest.shape and np.array_equal(co, self.rest):
            return
        raise ShotError(f"Object '{obj.name}': its mesh was edited while wiggly solved "
                        f"({len(co)} vertices now, {len(self.rest)} when the bake started, or "
                        "moved ones), so the result does not fit it; nothing was baked: bake "
                        "again")

    def _check_stack(self, context) -> None:
        """A shape-key bake under modifiers that move the vertices would be moved again."""
        frame = context.scene.frame_current, context.scene.frame_subframe
        try:
            moving = bake.moving_modifiers(context, self.obj)
        finally:
            context.scene.frame_set(frame[0], subframe=frame[1])
        if moving:
            raise ShotError(
                f"Object '{self.obj.name}': its modifiers {', '.join(map(repr, moving))} move "
                "the vertices, and shape keys sit under the modifiers, so they would move the "
                "bake again: bake as Mesh Cache (it takes the place of their deformation), or "
                "turn them off")

    def _finish(self, context, code: int) -> set[str]:
        self.times["wiggly"] = time.perf_counter() - self.solve.started
        obj = self._target()
        try:
            if obj is None:
                raise ShotError(f"Object '{self.shot.name}' was deleted while wiggly solved: "
                                "nothing was baked")
            self.obj = obj
            if code != 0:
                raise ShotError(f"wiggly could not solve the shot of '{self.obj.name}': "
                                f"{self.solve.failure()}")
            self._check_unchanged(self.obj)
            t = time.perf_counter()
            local = bake.read_result(self.solve.result, self.shot)
            if self.bake_as == "SHAPE_KEYS":
                others = bake.shape_keys_at_work(self.obj)
                if others:
                    self.warned += 1
                    self.report({"WARNING"}, f"Object '{self.obj.name}': its own shape keys "
                                f"{', '.join(others)} add to the baked ones (mute them, or "
                                "bake as Mesh Cache)")
                bake.bake_shape_keys(self.obj, self.shot, local)
                where = "shape keys"
            else:
                where = str(bake.bake_mesh_cache(self.obj, self.shot, local))
            self.obj[freshness.FINGERPRINT] = self.inputs  # what this bake was made from
            self.times["bake"] = time.perf_counter() - t
        except ShotError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except OSError as e:  # a cache file that could not be written after all
            self.report({"ERROR"}, f"Object '{self.shot.name}': cannot write "
                        f"{e.filename or 'the bake'}: {e.strerror}")
            return {"CANCELLED"}
        finally:
            said = self.solve.warnings()
            self.solve.cleanup()
        for w in said:  # the bake is done; what wiggly warned of is the user's to see
            self.report({"WARNING"}, f"Object '{self.obj.name}': {w}")
        self.warned += len(said)
        context.scene.frame_set(context.scene.frame_current)
        sizes = ", ".join(f"{k} {v:.2f} s" for k, v in self.times.items())
        warned = f"; {self.warned} warning(s) above" if self.warned else ""
        self.report({"INFO"}, f"Baked {len(self.shot.frames)} frames ({self.shot.frame_start}-"
                    f"{self.shot.frame_end} at {self.shot.fps:g} fps) of '{self.obj.name}' "
                    f"into {where} ({sizes}){warned}")
        return {"FINISHED"}

    def execute(self, context):
        """Blocking (scripts, tests, F3 without a window's event loop)."""
        if not self._prepare(context):
            return {"CANCELLED"}
        return self._finish(context, self.solve.wait())

    def invoke(self, context, event):
        if not self._prepare(context):
            return {"CANCELLED"}
        _running["op"] = self
        wm = context.window_manager
        self.timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        self._status(context, "starting")
        return {"RUNNING_MODAL"}

    def _status(self, context, text: str) -> None:
        elapsed = time.perf_counter() - self.solve.started
        if context.workspace is not None:
            context.workspace.status_text_set(
                f"wiggly: {self.shot.name}: {text} ({elapsed:.0f} s) | Esc: cancel")

    def _end(self, context) -> None:
        context.window_manager.event_timer_remove(self.timer)
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        _running.clear()

    def _stop(self, context, level: str, message: str) -> set[str]:
        """Stop wiggly and the modal run, bake nothing, and say ``message``."""
        self.solve.cancel()
        self.solve.cleanup()
        self._end(context)
        self.report({level}, message)
        return {"CANCELLED"}

    def modal(self, context, event):
        if event.type == "ESC":
            return self._stop(context, "WARNING", f"wiggly bake of '{self.shot.name}' "
                              "cancelled; nothing changed")
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        if self._target() is None:  # deleted during the solve: stop wiggly, bake nothing
            return self._stop(context, "ERROR", f"Object '{self.shot.name}' was deleted while "
                              "wiggly solved: the bake is cancelled, nothing was baked")
        code = self.solve.poll()
        if code is None:
            self._status(context, self.solve.status())
            return {"PASS_THROUGH"}
        self._end(context)
        return self._finish(context, code)

    def cancel(self, context):
        """Blender ends the operator (e.g. the file is closed): stop wiggly too."""
        self.solve.cancel()
        self.solve.cleanup()
        self._end(context)


def _scene_path(filepath: str) -> Path:
    """The scene file to write for the operator's ``filepath``: Blender-relative ``//``
    paths resolved against the .blend file, ``.toml`` added when missing."""
    if not filepath.strip() or filepath.endswith(("/", "\\")):
        raise ShotError("no scene file given: pick a file name for the scene (.toml) in the "
                        "file browser (File > Export > wiggly scene)")
    if filepath.startswith("//") and not bpy.data.filepath:
        raise ShotError(f"the path {filepath} is relative to the .blend file, which is not "
                        "saved yet: save it, or pick an absolute path")
    path = Path(bpy.path.abspath(filepath))
    return path if path.suffix.lower() == ".toml" else path.with_name(path.name + ".toml")


class WIGGLY_OT_export_scene(bpy.types.Operator, ExportHelper):
    """Write the shot as a wiggly scene file (TOML) with its rest mesh (OBJ) and driver (npz),
    to run in `wiggly animate` or `wiggly batch`"""

    bl_idname = "wiggly.export_scene"
    bl_label = "Export Wiggly Scene"
    bl_options = {"REGISTER"}

    filename_ext = ".toml"
    filter_glob: StringProperty(default="*.toml", options={"HIDDEN"})
    overwrite: BoolProperty(
        name="Overwrite", default=False,
        description="Replace existing files (the scene, <name>_rest.obj, <name>_drive.npz)")

    @classmethod
    def poll(cls, context):
        return _mesh_poll(cls, context)

    def execute(self, context):
        obj = context.active_object
        try:
            path = _scene_path(self.filepath)
            shot = gather(context, obj)
            files = write_shot(shot, path, overwrite=self.overwrite)
        except ShotError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        except OSError as e:
            self.report({"ERROR"}, f"cannot write {e.filename or path}: {e.strerror}")
            return {"CANCELLED"}
        _report_warnings(self, shot)
        self.report({"INFO"}, f"Wrote {files['scene']} (run it with: wiggly animate "
                    f"{files['scene'].name})")
        return {"FINISHED"}


class WIGGLY_OT_remove_bake(bpy.types.Operator):
    """Remove wiggly's bake (the Wiggly bake modifier and the wiggly.NNNN shape keys) from the
    active object; its own modifiers, shape keys and animation stay"""

    bl_idname = "wiggly.remove_bake"
    bl_label = "Remove Wiggly Bake"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _mesh_poll(cls, context)

    def execute(self, context):
        gone = bake.remove_bake(context.active_object)
        self.report({"INFO"}, f"Removed {gone} bake items" if gone else "No wiggly bake")
        return {"FINISHED"}


class WIGGLY_OT_group_add(bpy.types.Operator):
    """Use the object's active vertex group in the shot"""

    bl_idname = "wiggly.group_add"
    bl_label = "Add Wiggly Group"
    bl_options = {"REGISTER", "UNDO"}

    name: StringProperty(name="Vertex group", description="The vertex group to add (default: "
                         "the object's active vertex group)")

    @classmethod
    def poll(cls, context):
        if not _mesh_poll(cls, context):
            return False
        if not context.active_object.vertex_groups:
            cls.poll_message_set("The object has no vertex groups: make one in Object Data "
                                 "Properties > Vertex Groups")
            return False
        return True

    def execute(self, context):
        obj = context.active_object
        name = self.name or obj.vertex_groups.active.name
        if obj.vertex_groups.get(name) is None:
            self.report({"ERROR"}, f"Object '{obj.name}' has no vertex group '{name}'")
            return {"CANCELLED"}
        s = obj.wiggly
        if any(g.name == name for g in s.groups):
            self.report({"WARNING"}, f"Object '{obj.name}': group '{name}' is already in the "
                        "list")
            return {"CANCELLED"}
        item = s.groups.add()
        item.name = name
        s.active_group = len(s.groups) - 1
        return {"FINISHED"}


class WIGGLY_OT_group_remove(bpy.types.Operator):
    """Leave the selected group out of the shot (the vertex group itself stays)"""

    bl_idname = "wiggly.group_remove"
    bl_label = "Remove Wiggly Group"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not _mesh_poll(cls, context):
            return False
        s = context.active_object.wiggly
        if not 0 <= s.active_group < len(s.groups):
            cls.poll_message_set("Select a group in the list")
            return False
        return True

    def execute(self, context):
        s = context.active_object.wiggly
        s.groups.remove(s.active_group)
        s.active_group = max(0, min(s.active_group, len(s.groups) - 1))
        return {"FINISHED"}


def _active_item(context):
    obj = context.active_object
    if obj is None or obj.type != "MESH":
        return None
    s = obj.wiggly
    return s.groups[s.active_group] if 0 <= s.active_group < len(s.groups) else None


class WIGGLY_OT_add_handle(bpy.types.Operator):
    """Make an Empty at the group's centre as its handle, keyed at rest on the first frame:
    key its location and rotation where the group should be (Moving Hold keys: still)"""

    bl_idname = "wiggly.add_handle"
    bl_label = "Add Handle"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        if not _mesh_poll(cls, context):
            return False
        item = _active_item(context)
        if item is None or item.role != "HANDLE":
            cls.poll_message_set("Select a group whose role is Handle")
            return False
        return True

    def execute(self, context):
        obj, item = context.active_object, _active_item(context)
        vg = obj.vertex_groups.get(item.name)
        if vg is None:
            self.report({"ERROR"}, f"Object '{obj.name}' has no vertex group '{item.name}'")
            return {"CANCELLED"}
        old = item.handle
        if old is not None and context.scene.objects.get(old.name) is old:
            # a second Empty would leave the first (maybe keyed) unused in the scene
            if obj.mode != "EDIT":
                for o in context.selected_objects:
                    o.select_set(False)
                old.select_set(True)
            self.report({"INFO"}, f"Group '{item.name}' has its handle '{old.name}' already "
                        "(selected); to make a new one, clear the group's Handle field first")
            return {"CANCELLED"}
        if obj.mode == "EDIT":
            obj.update_from_editmode()  # the group where it is now, not before Edit Mode
        co = [obj.matrix_world @ v.co for v in obj.data.vertices
              if any(g.group == vg.index and g.weight > 0 for g in v.groups)]
        if not co:
            self.report({"ERROR"}, f"Object '{obj.name}', group '{item.name}': the vertex "
                        "group has no vertices")
            return {"CANCELLED"}
        handle = bpy.data.objects.new(f"{item.name} handle", None)
        handle.empty_display_type = "ARROWS"
        handle.empty_display_size = 0.25 * max(obj.dimensions) or 0.1
        handle.location = np.mean(np.array([list(c) for c in co]), axis=0)
        (obj.users_collection[0] if obj.users_collection else
         context.scene.collection).objects.link(handle)
        context.view_layer.update()
        item.handle = handle  # stores its placement as the rest
        frame = context.scene.frame_start
        handle.keyframe_insert("location", frame=frame)
        handle.keyframe_insert("rotation_euler", frame=frame)
        return {"FINISHED"}


class WIGGLY_OT_set_rest(bpy.types.Operator):
    """Take the handle's current placement as its rest: where the group is undeformed"""

    bl_idname = "wiggly.set_rest"
    bl_label = "Set Handle Rest"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        item = _active_item(context)
        if item is None or item.handle is None:
            cls.poll_message_set("Select a group with a handle")
            return False
        return True

    def execute(self, context):
        item = _active_item(context)
        item.rest_matrix = [v for row in item.handle.matrix_world for v in row]
        return {"FINISHED"}


CLASSES = (WIGGLY_OT_bake, WIGGLY_OT_export_scene, WIGGLY_OT_remove_bake, WIGGLY_OT_group_add,
           WIGGLY_OT_group_remove, WIGGLY_OT_add_handle, WIGGLY_OT_set_rest)


def menu_export(self, context):
    self.layout.operator(WIGGLY_OT_export_scene.bl_idname, text="wiggly scene (.toml)")


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)


def unregister() -> None:
    bpy.types.TOPBAR_MT_file_export.remove(menu_export)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
