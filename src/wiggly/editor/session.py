"""The editor's server-side session: the scene (source of truth), the tabs' undo histories,
and the background work that turns every edit into playback frames.

Threads and processes
---------------------
* the HTTP handlers call :meth:`Session.edit`, :meth:`Session.preview`, :meth:`Session.undo`,
  ... which change the state under a lock, autosave it, journal the undo histories and post a
  solve request; they never wait for a solve;
* the physics (tetrahedralization, FEM, modes; :mod:`wiggly.editor.physics`) runs in a child
  process, driven by one thread that publishes its stage;
* the playback (:mod:`wiggly.editor.playback`) solves every request: linear at once on the
  fast worker thread, then warped in the refinement process (:mod:`wiggly.editor.refine`).

Every process has an ``instance`` id: the browser resets what it knows about sequence numbers
and the mesh when it meets a new one (a restarted server).  Exports solve the scene exactly as
``wiggly animate`` does.
"""

from __future__ import annotations

import secrets
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from wiggly import limits
from wiggly.editor.autosave import Autosaver, autosave_path
from wiggly.editor.bus import EventBus
from wiggly.editor.exporting import Exports
from wiggly.editor.history import (
    DEFAULT_TAB,
    Histories,
    Record,
    edit_label,
    history_path,
    unwritable,
    write_status,
)
from wiggly.editor.physics import Physics
from wiggly.editor.playback import FrameSet, Playback
from wiggly.editor.presence import TAB_GRACE, Presence
from wiggly.editor.recovery import recover, set_aside_unsaved
from wiggly.editor.sandbox import Sandbox
from wiggly.editor.scene_files import (
    MESH_SUFFIXES,
    SCENE_SUFFIX,
    display_groups,
    driver_ghost,
    driver_stamp,
    file_digest,
    free_name,
    never_saved,
    new_scene,
    surface_of,
)
from wiggly.editor.scene_lock import SceneLock
from wiggly.editor.state import (
    EditError,
    EditorState,
    apply_edit,
    check_limits,
    rebased,
    rigid_fit,
    state_to_json,
)
from wiggly.errors import WigglyInputError
from wiggly.mesh import DEFAULT_RESOLUTION, VOLUME_EXTENSIONS
from wiggly.scene import (
    BUILTIN_MODELS,
    Scene,
    builtin_model,
    save_scene,
)

__all__ = ["Session", "autosave_path"]

class Session(Exports):
    """One edited scene with its histories, workers and frames.  See the module doc."""

    def __init__(self, sandbox: Sandbox, *, autosave: bool = True, bus: EventBus | None = None):
        self.sandbox = sandbox
        self.autosave = autosave
        self.bus = bus or EventBus(shown=sandbox.shown)
        self.instance = secrets.token_hex(6)  # this process (the browser's frame order)
        self.physics = Physics(self.bus, on_warning=self._prepared_note)
        self.playback = Playback(self.bus, self.physics, self.instance)
        self._lock = threading.RLock()
        self.version = 0
        self._state: EditorState | None = None
        self._saved: Scene | None = None  # as last saved or loaded (None: never saved)
        self._disk: str | None = None  # digest of the scene file as last read or written
        self._disk_seen: tuple | None = None  # its (path, mtime, size) when last checked
        self._disk_told: str | None = None  # the digest on disk the browsers were told of
        self.histories = Histories()
        self.surface = None  # the user's surface (rest), for the browser
        self._surface_key: tuple | None = None  # the mesh settings it was read with
        self.diagonal: float | None = None  # of the surface's bounding box
        self._opened = 0  # how many scenes were opened (the browser reloads the mesh)
        self.notices: list[str] = []
        self._groups_cache: tuple[Any, dict] | None = None
        self._dragging: str | None = None  # the page load whose drag preview is shown
        self.presence = Presence()  # the tabs with a page open
        self._export_pool = ThreadPoolExecutor(1, thread_name_prefix="wiggly-export")
        self._stop = threading.Event()
        self._told: str | None = None  # the journal's write error the browsers were told
        self.autosaver = Autosaver(
            lambda message: self.bus.publish("notice", level="warning", message=message))
        self._driver_stamp: tuple | None = None  # the [drive] file(s) as last seen
        self._scene_lock: SceneLock | None = None  # no other editor opens the scene meanwhile
        self.url: str | None = None  # where this editor is served (named in its lock)
        threading.Thread(target=self._watch_driver, name="wiggly-driver-watch",
                         daemon=True).start()

    def _watch_driver(self) -> None:
        """Every :data:`DRIVER_WATCH` seconds: when the scene's driver file (or an OBJ
        sequence's files) changed on disk, solve again and tell the browsers (whose ghost
        then fetches it again), with a notice: another tool re-exported the animation.  And
        when the scene file itself changed on disk (:meth:`check_scene_file`)."""
        while not self._stop.wait(DRIVER_WATCH):
            self.check_scene_file()
            with self._lock:
                scene = self._state.scene if self._state is not None else None
                stamp = driver_stamp(scene) if scene is not None else None
                before, self._driver_stamp = self._driver_stamp, stamp
                changed = stamp is not None and before is not None and stamp != before \
                    and stamp[0] == before[0]
                if changed:
                    self._changed(autosave=False)
            if changed:
                self.bus.publish("notice", sticky=False, level="info",
                                 message=f"{Path(stamp[0]).name} changed on disk: the driver "
                                         "is read again and the motion solved anew")

    def check_scene_file(self) -> None:
        """Tell the browsers, once per version, when the scene file on disk is no longer the
        one the editor read or saved (a text editor or another tool wrote it): the editor
        keeps its own scene, Open shows the disk's version, and Save asks before
        overwriting it."""
        with self._lock:
            scene = self._state.scene if self._state is not None else None
            path = scene.source if scene is not None else None
            if path is None or self._disk is None:
                return
            try:
                st = Path(path).stat()
                seen = (str(path), st.st_mtime_ns, st.st_size)
            except OSError:
                return  # gone: saving writes it again
            if seen == self._disk_seen:
                return
            self._disk_seen = seen
            digest = file_digest(Path(path))
            if digest is None or digest in (self._disk, self._disk_told):
                return
            self._disk_told = digest
            name = self.sandbox.relative(Path(path))
        self.bus.publish("notice", sticky=True, level="warning",
                         message=f"{name} was changed on disk by another program: the editor "
                                 f"keeps the scene as edited here; Open {name} to see the "
                                 "disk's version, or Save to replace it (Save asks first)")

    # --- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        self._stop.set()
        self.autosaver.close()
        with self._lock:
            if self._scene_lock is not None:
                self._scene_lock.release()
                self._scene_lock = None
        self.playback.close()
        self.physics.close()
        self._export_pool.shutdown(wait=False, cancel_futures=True)

    @property
    def state(self) -> EditorState:
        if self._state is None:
            raise EditError("no scene is open", 409)
        return self._state

    @property
    def scene(self) -> Scene:
        return self.state.scene

    @property
    def dirty(self) -> bool:
        """Whether the scene differs from the last saved (or loaded) one."""
        return self._saved is None or self._saved != self.state.scene

    # --- opening and saving ---------------------------------------------------------------
    def serving(self, url: str) -> None:
        """The editor is served at ``url``: its scene's lock names it."""
        with self._lock:
            self.url = url
            if self._scene_lock is not None:
                self._scene_lock.serving(url)

    def _claim(self, scene_path: Path, taken: list[SceneLock]) -> None:
        """Lock ``scene_path`` for this editor (unless it holds it already), adding the lock
        to ``taken``; :class:`EditError` (409) if another editor has it open."""
        held = self._scene_lock
        if held is not None and held.scene_path == scene_path:
            return
        lock = SceneLock.take(scene_path)
        if lock is not None:
            taken.append(lock)
            if self.url is not None:
                lock.serving(self.url)

    def _keep_lock(self, scene_path: Path | None, taken: list[SceneLock]) -> None:
        """The scene is now ``scene_path``: keep its lock, release the one held before."""
        old = self._scene_lock
        if taken:
            self._scene_lock = taken.pop()
        elif old is not None and old.scene_path != scene_path:
            self._scene_lock = None
        if old is not None and old is not self._scene_lock:
            old.release()

    def open(self, path: str) -> dict:
        """Open a scene file (.toml) or a mesh (new scene) inside the sandbox.  A scene whose
        autosave or undo journal holds edits the file lacks (the editor stopped or crashed
        before a save) is recovered from them, and says so; the undo histories come back.
        A scene another editor has open is refused (409, naming it)."""
        taken: list[SceneLock] = []
        try:
            return self._open(path, taken)
        finally:
            for lock in taken:  # not kept: the open failed
                lock.release()

    def _open(self, path: str, taken: list[SceneLock]) -> dict:
        notices: list[str] = []
        file_scene: Scene | None = None
        if path.startswith("builtin:"):
            name = path.removeprefix("builtin:")
            if name not in BUILTIN_MODELS:
                raise EditError(f"{path}: not a bundled model; use one of "
                                + ", ".join(f"builtin:{m}" for m in BUILTIN_MODELS))
            scene = new_scene(builtin_model(name), builtin=name)
            scene.source = free_name(self.sandbox.home, name)
            self._claim(scene.source, taken)
            histories = self._histories(scene.source)
            state, _ = histories.load(scene)
        else:
            real = self.sandbox.resolve(path, suffixes=(SCENE_SUFFIX, *MESH_SUFFIXES))
            if real.suffix.lower() == SCENE_SUFFIX:
                self._claim(real, taken)
                state, file_scene, histories = self._recover(path, real, notices)
            elif real.is_file():
                scene = new_scene(real)
                self._claim(scene.source, taken)
                histories = self._histories(scene.source)
                state, _ = histories.load(scene)
                # a scene of this mesh already (saved, or with edits never saved: a crash,
                # another editor at work on it): a new name, and the page says where it is
                unsaved = real.with_name(f"{real.stem}{SCENE_SUFFIX}")
                edited = autosave_path(unsaved).exists() or (  # a save drops the autosave
                    not unsaved.exists() and history_path(unsaved).exists())
                if scene.source != unsaved and (unsaved.exists() or edited):
                    what = ("with unsaved edits, " if edited else "") + unsaved.name + (
                        "" if unsaved.exists() else " (never saved)")
                    notices.append(
                        f"{real.name} already has a scene {what}; this is a new one, "
                        f"{scene.source.name}: to go on with that scene, Open {unsaved.name} "
                        f"(wiggly edit {unsaved.name})")
            else:
                raise EditError(f"{path}: no such file", 404)
            assert state is not None
            if not state.scene.mesh.path.startswith("builtin:") and \
                    not self.sandbox.contains(state.scene.mesh_file()):
                raise EditError(f"{path}: its mesh {state.scene.mesh.path} is outside the "
                                "directories this editor may use "
                                f"({', '.join(map(str, self.sandbox.roots))}); start wiggly "
                                "edit with --root and the mesh's folder to allow it", 403)
        assert state is not None
        scene = state.scene
        surface = surface_of(scene)
        diagonal = float(np.linalg.norm(np.ptp(surface.vertices, axis=0)))
        check_limits(scene, diagonal)
        with self._lock:
            self._keep_lock(scene.source, taken)
            self._state = state
            self.histories = histories
            self._saved = file_scene
            # the scene file as read: a save checks that nobody changed it since
            self._disk = histories.disk = file_digest(scene.source)
            self.surface, self.diagonal = surface, diagonal
            self._surface_key = (scene.mesh.path, scene.mesh.metres_per_unit, scene.mesh.up)
            self._opened += 1
            self.presence.restart()
            self._offer_history()
            self._groups_cache = None
            self.notices = notices
            self.version += 1
            self._changed(autosave=False)
        return {"path": self.sandbox.relative(scene.source), "notices": notices}

    def _histories(self, source: Path | None) -> Histories:
        """The undo histories of a scene saved as ``source``, journaled beside it (not when
        autosave is off or the folder is outside the sandbox)."""
        keep = self.autosave and source is not None and self.sandbox.contains(source.parent)
        return Histories(history_path(source) if keep else None)

    def _recover(self, path: str, real: Path, notices: list[str],
                 ) -> tuple[EditorState, Scene | None, Histories]:
        """The scene file ``real`` with its unsaved edits (:func:`recover`), the file's scene
        (None: never saved) and the histories."""
        self.autosaver.flush()  # a write still pending for this scene must not land later
        histories = self._histories(real)
        state, file_scene = recover(path, real, histories, notices)
        return state, file_scene, histories

    def save(self, path: str | None = None, overwrite: bool = False) -> dict:
        """Save the scene to its file, or to ``path`` (inside the sandbox).  A file that is
        not the scene's own, or its own file changed on disk since it was opened or last
        saved, is overwritten only with ``overwrite`` (409 otherwise, saying which); a file
        another editor has open, never (409, naming it)."""
        taken: list[SceneLock] = []
        try:
            return self._save(path, overwrite, taken)
        finally:
            for lock in taken:  # not kept: the save failed
                lock.release()

    def _save(self, path: str | None, overwrite: bool, taken: list[SceneLock]) -> dict:
        with self._lock:
            state = self.state
            scene = state.scene
            if path is None:
                if scene.source is None:
                    raise EditError("give a path to save to")
                target = self.sandbox.resolve(str(scene.source), suffixes=(SCENE_SUFFIX,))
            else:
                target = self.sandbox.resolve(path, suffixes=(SCENE_SUFFIX,))
            out = rebased(scene, target) if target != scene.source else scene
            if not out.mesh.path.startswith("builtin:") and \
                    not self.sandbox.contains(out.mesh_file()):
                raise EditError(f"{out.mesh.path}: the mesh is outside the sandbox", 403)
            if target != scene.source:
                self._claim(target, taken)
            on_disk = file_digest(target)
            if on_disk is not None and not overwrite:
                name = self.sandbox.relative(target)
                if target != scene.source:
                    raise EditError(f"{name} already exists: overwrite it, or save under "
                                    "another name", 409)
                if on_disk != self._disk:
                    raise EditError(f"{name} was changed on disk after the editor opened or "
                                    "last saved it: overwrite that change with the scene as "
                                    "edited here, or Save as another file (opening "
                                    f"{name} again shows the disk's version)", 409)
            said: list[str] = []
            if target != scene.source:  # the target's own unsaved edits are kept, not lost
                set_aside_unsaved(target, said)
            try:
                save_scene(out, target, overwrite=True)
            except WigglyInputError as err:
                raise EditError(str(err)) from None
            except OSError as err:
                raise EditError(unwritable(err, f"cannot save {self.sandbox.relative(target)}",
                                           target.parent), write_status(err)) from None
            self._disk = self.histories.disk = file_digest(target)
            self._keep_lock(target, taken)
            old_source = scene.source
            out.source = target
            if out is not scene or old_source != target:
                state = EditorState(out, state.keyframe_ids, state.next_id)
                self._state = state
            if self.histories.path is not None:  # one snapshot: the save, with its undo steps
                old_journal, self.histories.path = self.histories.path, history_path(target)
                self.histories.compact(state)
                if old_journal != self.histories.path:  # the old file reopens clean
                    old_journal.unlink(missing_ok=True)
            self._saved = out
            # what was recovered is saved now: the page stops saying so
            self.notices = [n for n in self.notices if not n.startswith("recovered")]
            for src in {old_source, target}:
                if src is not None:
                    self.autosaver.put(autosave_path(Path(src)), None)
            self.autosaver.flush()
            self.bus.publish("state", version=self.version, dirty=False)
            for message in said:
                self.bus.publish("notice", level="warning", message=message)
            return {"path": self.sandbox.relative(target), "notices": said}

    # --- edits ----------------------------------------------------------------------------
    def edit(self, op: Any, tab: str = DEFAULT_TAB) -> dict:
        """Apply an edit (see :mod:`wiggly.editor.state`), record it in ``tab``'s history and
        start a solve.  New keyframes' ids are returned (``ids``; ``id``: the last one)."""
        with self._lock:
            self.histories.attend(tab, self.presence.gone)
            old = self.state
            op = self._expand(op)
            new = apply_edit(old, op, self._n_vertices(), self.diagonal)
            self._check_tets(old.scene, new.scene)
            record = Record.between(old, new, edit_label(op, old, new))
            if record is None:
                return {"version": self.version, "changed": False}
            self._check_groups(old.scene, new.scene)
            # the solve starts while the journal line is flushed to the disk; the edit is
            # made (and told) only once it is there
            self.playback.request(new, self.version + 1, "final")
            try:
                full = self.histories.record(tab, record, new)
            except EditError:
                self.playback.restore(old, self.version)
                raise
            self._state = new
            self.version += 1
            self._changed(solve=False)
            out: dict[str, Any] = {"version": self.version, "changed": True}
            if full:
                out["notice"] = full
            added = [i for i in new.keyframe_ids if i not in set(old.keyframe_ids)]
            if added:
                out["ids"], out["id"] = added, added[-1]
            return out

    def _sync_surface(self, scene: Scene) -> None:
        """The surface shown, read again when the scene reads its file otherwise (another
        ``mesh.scale`` or ``up_axis``, by an edit or its undo); the page then fetches it."""
        key = (scene.mesh.path, scene.mesh.metres_per_unit, scene.mesh.up)
        if self.surface is None or key == self._surface_key:
            return
        self.surface = surface_of(scene)
        self.diagonal = float(np.linalg.norm(np.ptp(self.surface.vertices, axis=0)))
        self._surface_key = key
        self._opened += 1  # the page's mesh key: it loads the mesh again
        self._groups_cache = None

    def _check_tets(self, old: Scene, new: Scene) -> None:
        """Refuse mesh settings whose tet mesh would pass wiggly's tet limit, before the edit
        is made (it was made, and the model then failed to load with nothing in the page to
        undo it but Undo), as ``wiggly animate`` refuses them
        (:func:`wiggly.scene.build.check_surface_for_scene`), on the surface shown scaled as
        ``new`` asks."""
        from wiggly.mesh.defects import SurfaceReport, enclosed_volume, surface_area
        from wiggly.scene.build import check_surface_for_scene

        a, b = old.mesh, new.mesh
        if self.surface is None or (a.resolution, a.edge_length, a.metres_per_unit) == \
                (b.resolution, b.edge_length, b.metres_per_unit) or \
                new.mesh_file().suffix.lower() in VOLUME_EXTENSIONS:  # tets as they are
            return
        s = b.metres_per_unit / a.metres_per_unit
        V, F = self.surface.vertices, self.surface.faces
        report = SurfaceReport(len(F), volume=abs(enclosed_volume(V, F)) * s**3,
                               area=surface_area(V, F) * s**2,
                               diagonal=(self.diagonal or 0.0) * s)
        try:
            check_surface_for_scene(new, report, new.mesh_file().name)
        except WigglyInputError as err:
            raise EditError(str(err)) from None

    def _check_groups(self, old: Scene, new: Scene) -> None:
        """Refuse an edit after which the groups no longer resolve on the mesh while they did
        before (e.g. a group given another vertex count than an ``absolute`` key of it has
        rows): the scene file would not read back in ``wiggly animate``."""
        if (old.groups, old.keyframes) == (new.groups, new.keyframes):
            return
        model = self._model_if_ready(new)
        try:
            out = display_groups(new, self.surface, model)
        except WigglyInputError as err:
            try:
                display_groups(old, self.surface, model)
            except WigglyInputError:
                return  # already unresolved: the edit may be the user's way out
            raise EditError(str(err).splitlines()[0]) from None
        self._groups_cache = ((dict(new.groups), new.mesh), out)  # groups() of the edit

    def preview(self, op: Any, page: str | None = None) -> dict:
        """Solve the state an edit would give, without logging it (linear: gizmo drags).
        ``page`` names the page load that drags (see :meth:`page_closed`)."""
        with self._lock:
            if self.presence.ended(page):  # sent before its page closed, arrived after it:
                return {"seq": None}  # no tab would ever see that drag end
            state = apply_edit(self.state, self._expand(op), self._n_vertices(), self.diagonal)
            self._dragging = page
            return {"seq": self.playback.request(state, self.version, "drag")}

    def cancel_preview(self, page: str | None = None) -> dict:
        """A gizmo drag was abandoned (Esc): every tab shows the scene's frames again.  A
        ``page`` that is not the one dragging last cancels nothing (``seq`` None): another
        page's drag goes on."""
        with self._lock:
            if page is not None and self._dragging not in (None, page):
                return {"seq": None, "version": self.version}
            self._dragging = None
            return {"seq": self.playback.restore(self.state, self.version),
                    "version": self.version}

    def page_opened(self, tab: str) -> None:
        """A page of ``tab`` opened its event stream: the tab is live (its undo history
        stays its own, :mod:`wiggly.editor.presence`)."""
        self.presence.opened(tab)

    def page_closed(self, page: str | None, tab: str | None = None) -> None:
        """The event stream of a page load ended (reloaded, closed or crashed): a drag it
        left mid-way is abandoned, so the other tabs stop showing its preview; ``tab`` has
        one page fewer."""
        with self._lock:
            if page is not None:
                self.presence.page_ended(page)
                if self._dragging == page:
                    self.cancel_preview(page)
        if tab is not None and self.presence.closed(tab):
            self._offer_history()

    def _offer_history(self) -> None:
        """Once tabs may be gone: the pages ask again, and one without an undo history of
        its own takes over theirs (:meth:`wiggly.editor.history.Histories.attend`)."""
        def offer() -> None:
            with self._lock:
                if self._state is not None and self.histories.orphaned(self.presence.gone):
                    self.bus.publish("state", version=self.version, dirty=self.dirty)
        timer = threading.Timer(TAB_GRACE + 0.25, offer)
        timer.daemon = True
        timer.start()

    def undo(self, tab: str = DEFAULT_TAB) -> dict:
        return self._step(tab, undo=True)

    def redo(self, tab: str = DEFAULT_TAB) -> dict:
        return self._step(tab, undo=False)

    def _step(self, tab: str, undo: bool) -> dict:
        with self._lock:
            self.histories.attend(tab, self.presence.gone)
            try:
                new = self.histories.step(tab, self.state, undo)
            except EditError:
                self.bus.publish("state", version=self.version, dirty=self.dirty)
                raise
            if new is None:
                return {"version": self.version, "changed": False}
            self._state = new
            self.version += 1
            self._changed()
            return {"version": self.version, "changed": True}

    def _n_vertices(self) -> int | None:
        return self.surface.n_vertices if self.surface is not None else None

    def _expand(self, op: Any) -> Any:
        """``position: "current"`` becomes the rigid pose nearest to the group's position in
        the newest playback frames of the scene at that time (so adding a keyframe does not
        jump); in a batch, for every edit."""
        if isinstance(op, dict) and op.get("op") == "batch" and isinstance(op.get("ops"), list):
            return {**op, "ops": [self._expand(o) for o in op["ops"]]}
        if not (isinstance(op, dict) and op.get("position") == "current"):
            return op
        op = dict(op)
        op["position"] = "rest"
        name, t = op.get("group"), op.get("time")
        fs = self.playback.latest(committed=True)
        groups = self.groups()
        if fs is None or name not in groups or isinstance(t, bool) or \
                not isinstance(t, int | float) or self.scene.groups[name].on != "surface" or \
                fs.positions.shape[1] != self.surface.n_vertices:
            return op
        k = int(np.clip(round((float(t) - fs.start) * fs.fps), 0, len(fs.positions) - 1))
        idx = groups[name]
        op["position"] = rigid_fit(self.surface.vertices[idx], fs.positions[k][idx])
        return op

    def _changed(self, autosave: bool = True, solve: bool = True) -> None:
        """After a state change: solve (unless already asked), tell the browsers, autosave
        (in the background).  A drag under way is over: its next preview starts another."""
        state = self.state
        self._dragging = None
        self._sync_surface(state.scene)
        self.bus.publish("state", version=self.version, dirty=self.dirty)
        if solve:
            self.playback.request(state, self.version, "final")
        if autosave and self.autosave and state.scene.source is not None:
            target = autosave_path(Path(state.scene.source))
            if self.sandbox.contains(target.parent):
                # back to the saved scene (undo): an older autosave must not come back
                self.autosaver.put(target, state.scene if self.dirty else None, self._disk)
        if self.histories.write_error and self.histories.write_error != self._told:
            self.bus.publish("notice", level="warning", message=self.histories.write_error)
        self._told = self.histories.write_error

    # --- queries --------------------------------------------------------------------------
    def groups(self) -> dict[str, np.ndarray]:
        """Surface vertex indices of every group of the current scene (tet-mesh groups through
        their nearest surface vertices, once the tet mesh is known)."""
        scene = self.scene
        cached = self._groups_cache
        if cached is not None and cached[0] == (scene.groups, scene.mesh):
            return cached[1]
        out = display_groups(scene, self.surface, self._model_if_ready(scene))
        self._groups_cache = ((dict(scene.groups), scene.mesh), out)
        return out

    def _model_if_ready(self, scene: Scene):
        fut = self.physics.model_future(scene)
        if fut.done() and fut.exception() is None:
            return fut.result()
        return None

    def describe(self, tab: str = DEFAULT_TAB) -> dict:
        """Everything the browser needs to draw the editor (but the mesh and frames)."""
        with self._lock:
            base = {"version": self.version, "instance": self.instance,
                    "roots": [str(r) for r in self.sandbox.roots],
                    "limits": {k: getattr(limits, k) for k in dir(limits)
                               if k.startswith("MAX_")}}
            if self._state is None:
                return {"open": False, **base}
            state = self.state
            self.histories.attend(tab, self.presence.gone)
            try:
                groups = {k: v.tolist() for k, v in self.groups().items()}
                group_error = None
            except WigglyInputError as err:
                groups, group_error = {}, str(err)
            return {
                "open": True,
                **base,
                "scene": state_to_json(state),
                "groups": groups,
                "group_error": group_error,
                "path": self.sandbox.relative(state.scene.source) if state.scene.source else None,
                "dirty": self.dirty,
                **self.histories.describe(tab),
                "notices": self.notices,
                "opened": self._opened,
                "n_vertices": self.surface.n_vertices if self.surface is not None else 0,
                "mesh_key": f"{self.instance}:{self._opened}:{state.scene.mesh.path}",
                "driver_stamp": repr(driver_stamp(state.scene)),
                "default_resolution": DEFAULT_RESOLUTION,
            }

    def _prepared_note(self, message: str) -> None:
        """A warning of the mesh's preparation (its units, a repair): a toast, and kept in
        the notices bar, which a page opened or reloaded later shows too."""
        with self._lock:
            if message not in self.notices:
                self.notices = [*self.notices, message]
            dirty = self._state is not None and self.dirty
        self.bus.publish("notice", sticky=False, level="warning", message=message)
        self.bus.publish("state", version=self.version, dirty=dirty)

    def recoverable(self) -> list[str]:
        """Scenes never saved whose autosave or undo journal exists (edited before a crash)."""
        return never_saved(self.sandbox)

    @property
    def changed_on_disk(self) -> bool:
        """Whether another program changed the scene file since it was read or saved."""
        path = self._state.scene.source if self._state is not None else None
        return path is not None and file_digest(path) not in (None, self._disk)

    def mesh_bytes(self) -> bytes:
        """The rest surface: uint32 n, uint32 m, float32 vertices (n, 3), uint32 faces (m, 3)."""
        s = self.surface
        if s is None:
            raise EditError("no scene is open", 409)
        head = np.array([s.n_vertices, s.n_faces], "<u4").tobytes()
        return head + s.vertices.astype("<f4").tobytes() + s.faces.astype("<u4").tobytes()

    def driver_frames(self) -> tuple[bytes, dict]:
        """The scene's driver as the editor's ghost (:func:`driver_ghost`)."""
        with self._lock:
            scene, surface = self.scene, self.surface
        return driver_ghost(scene, surface)

    def frames(self, frame_id: int) -> FrameSet:
        fs = self.playback.frames(frame_id)
        if fs is None:
            raise EditError(f"no frames with id {frame_id} (newer frames replaced them)", 404)
        return fs

    def latest_frames(self, final: bool = False) -> FrameSet | None:
        """The frames of the newest request (``final``: the newest final ones)."""
        return self.playback.latest(final=final)


#: How often (s) the editor looks at the scene's driver file(s) for changes.
DRIVER_WATCH = 1.0
