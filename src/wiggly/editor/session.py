"""The editor's server-side session: the scene (source of truth), its edit log, and the
background work that turns every edit into playback frames.

Threads
-------
* the HTTP handlers call :meth:`Session.edit`, :meth:`Session.preview`, :meth:`Session.undo`,
  ... which change the state under a lock, autosave it, and post a solve request; they never
  wait for a solve;
* the *physics* thread (one) reads and tetrahedralizes the mesh, assembles the FEM and
  computes the modes (cached on disk by :func:`wiggly.prepare`), publishing its stage;
* the *fast* worker thread answers every request with a linear solve (Theorem 1) and linear
  playback (milliseconds: this is what the browser shows while a gizmo is dragged and right
  after it is released);
* the *warped* refinement then solves committed states with the warped solve (Theorem 2), a
  few Gauss-Newton iterations at a time, warm-started from its previous result, publishing
  frames as it goes.  It runs in a child process (:mod:`wiggly.editor.refine`) so that its
  long calls holding the GIL never delay the server or the fast worker.

Newest request wins: the fast worker has a one-slot :class:`Mailbox` (a request not yet taken
is replaced by a newer one), and the refinement abandons its solve between chunks of
iterations as soon as a newer request exists.  Every request has a sequence number ``seq``;
the browser shows frames of the highest ``seq`` it has seen (and, within one ``seq``, warped
frames over linear ones).  Exports solve the scene exactly as ``wiggly animate`` does.
"""

from __future__ import annotations

import dataclasses
import json
import queue
import threading
import time
import traceback
import warnings
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from wiggly.editor.refine import Refiner, residual_max
from wiggly.editor.sandbox import Sandbox
from wiggly.editor.state import (
    EditError,
    EditLog,
    EditorState,
    apply_edit,
    rebased,
    rigid_fit,
    state_to_json,
)
from wiggly.errors import WigglyInputError
from wiggly.scene import (
    BUILTIN_MODELS,
    OUTPUT_EXTENSIONS,
    MeshSpec,
    Scene,
    TimeSpec,
    builtin_model,
    load_scene,
    resolve_groups,
    save_scene,
)

__all__ = ["EventBus", "Mailbox", "Session", "autosave_path"]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".msh", ".vtu", ".vtk",
                 ".mesh")
SCENE_SUFFIX = ".toml"
FRAME_SETS_KEPT = 6


# ----------------------------------------------------------------------------------------------
# plumbing: events and mailboxes


class EventBus:
    """Fan-out of server events (dicts) to every open event stream (one queue each)."""

    def __init__(self, backlog: int = 256):
        self._lock = threading.Lock()
        self._queues: list[queue.Queue] = []
        self.backlog = backlog
        self.last: dict[str, dict] = {}  # newest event of each type, for new subscribers

    def subscribe(self) -> queue.Queue:
        q: queue.Queue = queue.Queue(self.backlog)
        with self._lock:
            self._queues.append(q)
            for event in self.last.values():
                q.put_nowait(event)
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            if q in self._queues:
                self._queues.remove(q)

    @property
    def n_subscribers(self) -> int:
        with self._lock:
            return len(self._queues)

    def publish(self, kind: str, **data: Any) -> None:
        event = {"type": kind, "time": time.time(), **data}
        with self._lock:
            self.last[kind] = event
            for q in self._queues:
                try:
                    q.put_nowait(event)
                except queue.Full:  # a stalled client loses its oldest events
                    try:
                        q.get_nowait()
                        q.put_nowait(event)
                    except (queue.Empty, queue.Full):
                        pass


class Mailbox:
    """A one-slot queue where a newer item replaces one not yet taken (newest wins)."""

    def __init__(self):
        self._cv = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._cv:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self._cv.notify_all()

    def take(self, timeout: float | None = None) -> Any:
        """The newest item (None on timeout or when closed)."""
        with self._cv:
            self._cv.wait_for(lambda: self._item is not None or self._closed, timeout)
            item, self._item = self._item, None
            return item

    def pending(self) -> bool:
        with self._cv:
            return self._item is not None or self._closed

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()


@dataclass(frozen=True)
class Request:
    """A solve of ``state``: ``kind`` "drag" (linear only) or "final" (linear, then warped)."""

    seq: int
    version: int
    state: EditorState
    kind: str


@dataclass
class FrameSet:
    """Playback frames of one solve: float32 positions (F, n, 3) of the surface."""

    id: int
    seq: int
    version: int
    stage: str  # "linear" | "warped"
    final: bool
    start: float
    fps: float
    positions: np.ndarray
    info: dict = field(default_factory=dict)

    def meta(self) -> dict:
        F, n, _ = self.positions.shape
        return {"id": self.id, "seq": self.seq, "version": self.version, "stage": self.stage,
                "final": self.final, "start": self.start, "fps": self.fps, "n_frames": F,
                "n_vertices": n, **self.info}


# ----------------------------------------------------------------------------------------------
# physics: model, body and modes, computed once per setting


def _model_key(scene: Scene) -> tuple:
    f = scene.mesh_file()
    try:
        mtime = f.stat().st_mtime_ns
    except OSError:
        mtime = 0
    m = scene.mesh
    return (str(f), mtime, m.resolution, m.edge_length, m.repair)


def _modes_key(scene: Scene) -> tuple:
    s = scene.simulation
    fixed = tuple((g, scene.groups[g]) for g in s.fixed)
    return (_model_key(scene), scene.material, s.modes, s.lumped_mass, fixed)


def with_dynamics(body, damping, gravity):
    """``body`` with the scene's damping and gravity (:meth:`wiggly.body.Body.with_dynamics`:
    nothing is recomputed)."""
    from wiggly.body import Damping

    return body.with_dynamics(damping=Damping(damping.alpha, damping.beta), gravity=gravity)


class Physics:
    """Models and bodies by setting, computed on one background thread with stage events."""

    def __init__(self, bus: EventBus):
        self.bus = bus
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="wiggly-physics")
        self._lock = threading.RLock()
        self._models: OrderedDict[tuple, Future] = OrderedDict()
        self._bodies: OrderedDict[tuple, Future] = OrderedDict()
        self._variants: OrderedDict[tuple, Any] = OrderedDict()

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    def _status(self, stage: str, message: str, fraction: float, t0: float, **kw) -> None:
        self.bus.publish("physics", stage=stage, message=message, fraction=fraction,
                         elapsed=time.perf_counter() - t0, **kw)

    def model_future(self, scene: Scene) -> Future:
        key = _model_key(scene)
        with self._lock:
            fut = self._models.get(key)
            if fut is None or (fut.done() and fut.exception() is not None):
                fut = self._pool.submit(self._load_model, scene)
                self._models[key] = fut
                while len(self._models) > 2:
                    self._models.popitem(last=False)
            return fut

    def _load_model(self, scene: Scene):
        from wiggly.mesh import load_model

        t0 = time.perf_counter()
        f = scene.mesh_file()
        self._status("mesh", f"reading and tetrahedralizing {f.name}", 0.1, t0)
        try:
            model = load_model(f, resolution=scene.mesh.resolution,
                               edge_length=scene.mesh.edge_length, repair=scene.mesh.repair)
        except Exception as err:
            self._status("error", f"cannot load {f.name}: {err}", 0.0, t0)
            raise
        self._status("mesh", f"{model.tets.n_tets} tets, {model.tets.n_vertices} vertices", 0.3,
                     t0)
        return model

    def body_future(self, scene: Scene) -> Future:
        key = _modes_key(scene)
        with self._lock:
            fut = self._bodies.get(key)
            if fut is None or (fut.done() and fut.exception() is not None):
                model_fut = self.model_future(scene)
                fut = self._pool.submit(self._prepare, scene, model_fut)
                self._bodies[key] = fut
                while len(self._bodies) > 3:
                    self._bodies.popitem(last=False)
            return fut

    def _prepare(self, scene: Scene, model_fut: Future):
        from wiggly.body import fixed_from_surface, prepare
        from wiggly.fem import Material

        t0 = time.perf_counter()
        model = model_fut.result()
        s, m = scene.simulation, scene.material
        try:
            groups = resolve_groups(scene, model)
            fixed = [groups[g] if scene.groups[g].on == "tets"
                     else fixed_from_surface(model, groups[g]) for g in s.fixed]
            fixed_vertices = np.unique(np.concatenate(fixed)) if fixed else None
            self._status("modes", f"computing {s.modes} modes of {model.tets.n_tets} tets "
                         f"(E = {m.young:g} Pa)", 0.4, t0)
            body = prepare(model, material=Material(m.young, m.poisson, m.density),
                           gravity=s.gravity, fixed_vertices=fixed_vertices, n_modes=s.modes,
                           lumped=s.lumped_mass)
            self._status("warp", "factoring the rotation-strain warp", 0.85, t0)
            _ = body.surface_basis
            _ = body.warp
        except Exception as err:
            self._status("error", f"cannot compute the modes: {err}", 0.0, t0)
            raise
        self._status("ready", f"{body.r} modes ready ({model.tets.n_tets} tets)", 1.0, t0,
                     modes=body.r, tets=model.tets.n_tets,
                     frequencies=[round(float(x), 4) for x in body.modes.frequencies_hz()[:12]])
        return body

    def body(self, scene: Scene, abandon: Callable[[], bool]):
        """The body of ``scene`` (None when ``abandon()`` turns true while waiting)."""
        fut = self.body_future(scene)
        while True:
            try:
                base = fut.result(timeout=0.05)
                break
            except TimeoutError:
                if abandon():
                    return None
        key = (id(base), scene.damping, scene.simulation.gravity)
        with self._lock:
            body = self._variants.get(key)
            if body is None:
                body = with_dynamics(base, scene.damping, scene.simulation.gravity)
                self._variants[key] = body
                while len(self._variants) > 4:
                    self._variants.popitem(last=False)
            return body


# ----------------------------------------------------------------------------------------------
# the session


def autosave_path(scene_path: Path) -> Path:
    """Where edits of ``scene_path`` are autosaved: a hidden file beside it."""
    return scene_path.with_name(f".{scene_path.stem}.autosave.toml")


def new_scene(mesh_file: Path, builtin: str | None = None) -> Scene:
    """A fresh scene for a mesh: no groups or keyframes, a 2 s shot, saved beside the mesh
    (or in the current directory for a bundled model)."""
    if builtin is not None:
        scene = Scene(MeshSpec(f"builtin:{builtin}"), time=TimeSpec(end=2.0))
        scene.source = _free_name(Path.cwd(), builtin)
        return scene
    scene = Scene(MeshSpec(mesh_file.name), time=TimeSpec(end=2.0))
    scene.source = _free_name(mesh_file.parent, mesh_file.stem)
    return scene


class Session:
    """One edited scene with its log, workers and frames.  See the module doc."""

    def __init__(self, sandbox: Sandbox, *, autosave: bool = True, bus: EventBus | None = None):
        self.sandbox = sandbox
        self.autosave = autosave
        self.bus = bus or EventBus()
        self.physics = Physics(self.bus)
        self._lock = threading.RLock()
        self._seq = 0
        self.version = 0
        self.log: EditLog | None = None
        self.surface = None  # the user's surface (rest), for the browser
        self._opened = 0  # how many scenes were opened (the browser reloads the mesh)
        self.notices: list[str] = []
        self._frames: OrderedDict[int, FrameSet] = OrderedDict()
        self._frame_id = 0
        self._groups_cache: tuple[Any, dict] | None = None
        self.fast_box = Mailbox()
        self._export_pool = ThreadPoolExecutor(1, thread_name_prefix="wiggly-export")
        self._stop = threading.Event()
        self.refiner = Refiner(self._on_refined)
        self._thread = threading.Thread(target=self._worker, args=(self.fast_box,),
                                        name="wiggly-fast", daemon=True)
        self._thread.start()

    # --- lifecycle ------------------------------------------------------------------------
    def close(self) -> None:
        self._stop.set()
        self.fast_box.close()
        self.refiner.close()
        self.physics.close()
        self._export_pool.shutdown(wait=False, cancel_futures=True)

    @property
    def state(self) -> EditorState:
        if self.log is None:
            raise EditError("no scene is open", 409)
        return self.log.current

    @property
    def scene(self) -> Scene:
        return self.state.scene

    # --- opening and saving ---------------------------------------------------------------
    def open(self, path: str) -> dict:
        """Open a scene file (.toml) or a mesh (new scene) inside the sandbox; a scene with an
        autosave that differs from it is recovered from the autosave (and says so)."""
        notices = []
        if path.startswith("builtin:"):
            name = path.removeprefix("builtin:")
            if name not in BUILTIN_MODELS:
                raise EditError(f"{path}: not a bundled model; use one of "
                                + ", ".join(f"builtin:{m}" for m in BUILTIN_MODELS))
            scene = new_scene(builtin_model(name), builtin=name)
            scene.source = _free_name(self.sandbox.home, name)
        else:
            real = self.sandbox.resolve(path, suffixes=(SCENE_SUFFIX, *MESH_SUFFIXES))
            unsaved = real.suffix.lower() == SCENE_SUFFIX and not real.exists() and \
                autosave_path(real).is_file()
            if unsaved:  # a scene that was never saved, edited before a crash
                scene = _load(autosave_path(real))
                scene.source = real
                notices.append(f"recovered the unsaved scene from {autosave_path(real).name}")
            elif not real.is_file():
                raise EditError(f"{path}: no such file", 404)
            elif real.suffix.lower() == SCENE_SUFFIX:
                scene = _load(real)
                auto = autosave_path(real)
                if auto.is_file():
                    try:
                        recovered = _load(auto)
                        recovered.source = real
                        if recovered != scene:
                            scene = recovered
                            notices.append(f"recovered unsaved edits from {auto.name} (the "
                                           f"saved file is unchanged until you save)")
                    except WigglyInputError as err:
                        notices.append(f"ignored an unreadable autosave {auto.name}: "
                                       f"{str(err).splitlines()[0]}")
            else:
                scene = new_scene(real)
            if not scene.mesh.path.startswith("builtin:") and \
                    not self.sandbox.contains(scene.mesh_file()):
                raise EditError(f"{path}: its mesh {scene.mesh.path} is outside the directories "
                                "this editor may use", 403)
        surface = _surface_of(scene)
        with self._lock:
            state = EditorState.of(scene)
            self.log = EditLog([state])
            if not notices and scene.source is not None and scene.source.is_file():
                self.log.saved = state
            self.surface = surface
            self._opened += 1
            self._groups_cache = None
            self.notices = notices
            self.version += 1
            self._changed(autosave=False)
        self.physics.body_future(scene)  # start tetrahedralizing and the modes right away
        return {"path": self.sandbox.relative(scene.source), "notices": notices}

    def save(self, path: str | None = None) -> dict:
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
            try:
                save_scene(out, target, overwrite=True)
            except WigglyInputError as err:
                raise EditError(str(err)) from None
            old_source = scene.source
            out.source = target
            if out is not scene or old_source != target:
                new_state = EditorState(out, state.keyframe_ids, state.next_id)
                self.log.states[self.log.index] = new_state
                state = new_state
            self.log.saved = state
            for src in {old_source, target}:
                if src is not None:
                    autosave_path(Path(src)).unlink(missing_ok=True)
            self.bus.publish("state", version=self.version, dirty=False)
            return {"path": self.sandbox.relative(target)}

    # --- edits ----------------------------------------------------------------------------
    def edit(self, op: Any) -> dict:
        """Apply an edit (see :mod:`wiggly.editor.state`), log it and start a solve."""
        with self._lock:
            op = self._expand(op)
            new = apply_edit(self.state, op, self.surface.n_vertices if self.surface else None)
            if new.scene == self.state.scene and new.keyframe_ids == self.state.keyframe_ids:
                return {"version": self.version, "changed": False}
            self.log.push(new)
            self.version += 1
            self._changed()
            out = {"version": self.version, "changed": True}
            if isinstance(op, dict) and op.get("op") == "add_keyframe":
                out["id"] = new.keyframe_ids[-1]
            return out

    def preview(self, op: Any) -> dict:
        """Solve the state an edit would give, without logging it (linear: gizmo drags)."""
        with self._lock:
            state = apply_edit(self.state, self._expand(op),
                               self.surface.n_vertices if self.surface else None)
            seq = self._request(state, "drag")
            return {"seq": seq}

    def undo(self) -> dict:
        return self._move(self.log.undo if self.log else None)

    def redo(self) -> dict:
        return self._move(self.log.redo if self.log else None)

    def _move(self, step) -> dict:
        with self._lock:
            if step is None:
                raise EditError("no scene is open", 409)
            moved = step()
            if moved:
                self.version += 1
                self._changed()
            return {"version": self.version, "changed": moved}

    def _expand(self, op: Any) -> Any:
        """``position: "current"`` becomes the rigid pose nearest to the group's position in
        the newest playback frames at that time (so adding a keyframe does not jump)."""
        if not (isinstance(op, dict) and op.get("position") == "current"):
            return op
        op = dict(op)
        op["position"] = "rest"
        name, t = op.get("group"), op.get("time")
        fs = self.latest_frames()
        groups = self.groups()
        if fs is None or name not in groups or isinstance(t, bool) or \
                not isinstance(t, int | float) or self.scene.groups[name].on != "surface" or \
                fs.positions.shape[1] != self.surface.n_vertices:
            return op
        k = int(np.clip(round((float(t) - fs.start) * fs.fps), 0, len(fs.positions) - 1))
        idx = groups[name]
        op["position"] = rigid_fit(self.surface.vertices[idx], fs.positions[k][idx])
        return op

    def _changed(self, autosave: bool = True) -> None:
        """After a state change: autosave, tell the browsers, solve."""
        state = self.state
        if autosave and self.autosave and state.scene.source is not None and self.log.dirty:
            try:
                target = autosave_path(Path(state.scene.source))
                if self.sandbox.contains(target.parent):
                    save_scene(state.scene, target, overwrite=True)
            except (OSError, WigglyInputError) as err:
                self.bus.publish("notice", level="warning", message=f"autosave failed: {err}")
        self.bus.publish("state", version=self.version, dirty=self.log.dirty)
        self._request(state, "final")

    def _request(self, state: EditorState, kind: str) -> int:
        self._seq += 1
        req = Request(self._seq, self.version, state, kind)
        self.refiner.supersede(req.seq)  # a running warped refinement stops
        self.fast_box.put(req)
        return self._seq

    # --- queries --------------------------------------------------------------------------
    def groups(self) -> dict[str, np.ndarray]:
        """Surface vertex indices of every group of the current scene (tet-mesh groups through
        their nearest surface vertices, once the tet mesh is known)."""
        scene = self.scene
        cached = self._groups_cache
        if cached is not None and cached[0] == (scene.groups, scene.mesh):
            return cached[1]
        out = _display_groups(scene, self.surface, self._model_if_ready(scene))
        self._groups_cache = ((dict(scene.groups), scene.mesh), out)
        return out

    def _model_if_ready(self, scene: Scene):
        fut = self.physics.model_future(scene)
        if fut.done() and fut.exception() is None:
            return fut.result()
        return None

    def describe(self) -> dict:
        """Everything the browser needs to draw the editor (but the mesh and frames)."""
        with self._lock:
            if self.log is None:
                return {"open": False, "version": self.version,
                        "roots": [str(r) for r in self.sandbox.roots]}
            state = self.state
            try:
                groups = {k: v.tolist() for k, v in self.groups().items()}
                group_error = None
            except WigglyInputError as err:
                groups, group_error = {}, str(err)
            return {
                "open": True,
                "version": self.version,
                "scene": state_to_json(state),
                "groups": groups,
                "group_error": group_error,
                "path": self.sandbox.relative(state.scene.source) if state.scene.source else None,
                "dirty": self.log.dirty,
                "can_undo": self.log.can_undo,
                "can_redo": self.log.can_redo,
                "notices": self.notices,
                "roots": [str(r) for r in self.sandbox.roots],
                "n_vertices": self.surface.n_vertices if self.surface is not None else 0,
                "mesh_key": f"{self._opened}:{state.scene.mesh.path}",
            }

    def recoverable(self) -> list[str]:
        """Scenes never saved whose autosave exists (edited before a crash)."""
        out = []
        for root in self.sandbox.roots:
            for auto in sorted(root.glob(".*.autosave.toml")):
                scene = auto.with_name(auto.name[1:].removesuffix(".autosave.toml") + ".toml")
                if not scene.exists() and self.sandbox.contains(auto):
                    out.append(self.sandbox.relative(scene))
        return out

    def mesh_bytes(self) -> bytes:
        """The rest surface: uint32 n, uint32 m, float32 vertices (n, 3), uint32 faces (m, 3)."""
        s = self.surface
        if s is None:
            raise EditError("no scene is open", 409)
        head = np.array([s.n_vertices, s.n_faces], "<u4").tobytes()
        return head + s.vertices.astype("<f4").tobytes() + s.faces.astype("<u4").tobytes()

    def frames(self, frame_id: int) -> FrameSet:
        with self._lock:
            fs = self._frames.get(frame_id)
        if fs is None:
            raise EditError(f"no frames with id {frame_id} (newer frames replaced them)", 404)
        return fs

    def latest_frames(self, final: bool = False) -> FrameSet | None:
        """The frames of the newest request (``final``: the newest final ones)."""
        with self._lock:
            best = None
            for fs in self._frames.values():
                if final and not fs.final:
                    continue
                if best is None or (fs.seq, fs.stage == "warped", fs.final) >= \
                        (best.seq, best.stage == "warped", best.final):
                    best = fs
            return best

    # --- workers --------------------------------------------------------------------------
    def _publish_frames(self, seq: int, version: int, stage: str, final: bool, start: float,
                        fps: float, positions: np.ndarray, info: dict) -> None:
        with self._lock:
            self._frame_id += 1
            fs = FrameSet(self._frame_id, seq, version, stage, final, start, fps, positions, info)
            self._frames[fs.id] = fs
            while len(self._frames) > FRAME_SETS_KEPT:
                self._frames.popitem(last=False)
        self.bus.publish("frames", **fs.meta())

    def _on_refined(self, kind: str, seq: int, version: int, payload: list) -> None:
        """Answers of the warped refinement process (on its relay thread)."""
        if kind == "frames":
            final, start, fps, positions, info = payload
            self._publish_frames(seq, version, "warped", final, start, fps, positions, info)
            if final:
                msg = (f"converged in {info['iterations']} iterations" if info["converged"]
                       else f"stopped after {info['iterations']} iterations (not converged)")
                self.bus.publish("solve", seq=seq, version=version, stage="done", message=msg,
                                 **info)
            else:
                self.bus.publish("solve", seq=seq, version=version, stage="warped",
                                 message=f"warped solve: {info['iterations']} iterations", **info)
        elif kind == "progress":
            info = payload[0]
            self.bus.publish("solve", seq=seq, version=version, stage="warped",
                             message=f"warped solve: {info['iterations']} iterations", **info)
        elif kind == "abandoned":
            self.bus.publish("solve", seq=seq, version=version, stage="abandoned",
                             message="superseded by a newer edit", **payload[0])
        elif kind == "error":
            self.bus.publish("solve", seq=seq, version=version, stage="error",
                             message=payload[0])
        elif kind == "died" and not self._stop.is_set():
            self.bus.publish("notice", level="error", message=payload[0]["message"] +
                             "; restarting it")
            self.refiner = Refiner(self._on_refined)

    def _worker(self, box: Mailbox) -> None:
        problems: OrderedDict[tuple, Any] = OrderedDict()
        while not self._stop.is_set():
            req = box.take(timeout=0.5)
            if req is None:
                continue
            try:
                self._solve(req, box, problems)
            except CancelledError:  # the session is closing
                return
            except WigglyInputError as err:
                self.bus.publish("solve", seq=req.seq, version=req.version, stage="error",
                                 message=str(err))
            except Exception as err:  # a bug: report it, keep the worker alive
                traceback.print_exc()
                self.bus.publish("solve", seq=req.seq, version=req.version, stage="error",
                                 message=f"internal error: {type(err).__name__}: {err}")

    def _solve(self, req: Request, box: Mailbox, problems) -> None:
        """Linear solve and linear playback (fast); then hand final requests of warped scenes
        to the refinement process."""
        from wiggly.scene import keyframes_of, scene_to_dict
        from wiggly.solve import SpacetimeProblem

        scene = req.state.scene
        body = self.physics.body(scene, abandon=lambda: box.pending() or self._stop.is_set())
        if body is None:
            return
        groups = resolve_groups(scene, body.model)
        keys = keyframes_of(scene, body, groups)
        start, end = scene.time_range()
        pkey = (id(body), start, end, scene.simulation.preroll)
        problem = problems.get(pkey)
        if problem is None:
            problem = problems[pkey] = SpacetimeProblem(body, start, end, scene.simulation.preroll)
            while len(problems) > 3:
                problems.popitem(last=False)
        t0 = time.perf_counter()
        self.bus.publish("solve", seq=req.seq, version=req.version, stage="linear",
                         message="linear solve")
        anim = problem.solve(keys, warped=False)
        if req.kind == "drag" and box.pending():
            return  # a newer request waits: skip this stale preview's playback frames
        times = anim.frame_times(scene.time.fps)
        positions = anim.positions(times, dtype=np.float32)
        warp = scene.simulation.warp
        final = not warp and req.kind == "final"
        info = {"seconds": time.perf_counter() - t0, "request": req.kind,
                "residual_max": residual_max(anim) if final else None}
        self._publish_frames(req.seq, req.version, "linear", final, float(times[0]),
                             float(scene.time.fps), positions, info)
        if final:
            self.bus.publish("solve", seq=req.seq, version=req.version, stage="done",
                             message="linear solve", **info)
        elif warp and req.kind == "final":
            model = self.physics.model_future(scene).result()
            self.refiner.solve(req.seq, req.version, scene_to_dict(scene), scene.source,
                               _model_key(scene), model)

    # --- export ---------------------------------------------------------------------------
    def export(self, paths: Any, overwrite: Any = False) -> dict:
        if not isinstance(paths, list) or not paths or len(paths) > 8:
            raise EditError("paths must be a list of 1 to 8 output files")
        if not isinstance(overwrite, bool):
            raise EditError("overwrite must be true or false")
        real = [self.sandbox.resolve(p, suffixes=OUTPUT_EXTENSIONS) for p in paths]
        from wiggly.scene import check_outputs

        try:
            check_outputs(real, overwrite)
        except WigglyInputError as err:
            raise EditError(str(err)) from None
        with self._lock:
            state, version = self.state, self.version
        self._export_pool.submit(self._export, state, version, real, overwrite)
        return {"paths": [self.sandbox.relative(p) for p in real]}

    def _export(self, state: EditorState, version: int, paths: list[Path], overwrite: bool):
        """Solve the scene as ``wiggly animate`` does (same body) and write ``paths``."""
        scene = state.scene
        names = [p.name for p in paths]
        self.bus.publish("export", stage="running", message=f"exporting {', '.join(names)}")
        try:
            from wiggly.scene import keyframe_highlights, keyframes_of, write_outputs
            from wiggly.solve import solve

            body = self.physics.body(scene, abandon=self._stop.is_set)
            if body is None:
                return
            groups = resolve_groups(scene, body.model)
            keys = keyframes_of(scene, body, groups)
            start, end = scene.time_range()
            with warnings.catch_warnings():  # the library's solve, as `wiggly animate` runs it
                warnings.simplefilter("ignore")
                anim = solve(body, keys, start=start, end=end, warp=scene.simulation.warp,
                             preroll=scene.simulation.preroll)
            write_outputs(scene, anim, paths, overwrite=overwrite,
                          highlights=keyframe_highlights(scene, body, anim.keyframes, groups))
            self.bus.publish("export", stage="done", message=f"exported {', '.join(names)}",
                             paths=[self.sandbox.relative(p) for p in paths])
        except Exception as err:
            if not isinstance(err, WigglyInputError):
                traceback.print_exc()
            self.bus.publish("export", stage="error", message=f"export failed: {err}")


def _free_name(folder: Path, stem: str) -> Path:
    """``folder/stem.toml``, or ``stem-2.toml``, ... if taken (never overwrite a scene)."""
    path, k = folder / f"{stem}{SCENE_SUFFIX}", 2
    while path.exists() or autosave_path(path).exists():
        path, k = folder / f"{stem}-{k}{SCENE_SUFFIX}", k + 1
    return path


def _load(path: Path) -> Scene:
    try:
        return load_scene(path)
    except WigglyInputError as err:
        raise EditError(str(err)) from None


def _surface_of(scene: Scene):
    """The user's surface, read without tetrahedralizing (a tet mesh's boundary)."""
    from wiggly.mesh import Surface, TetMesh, load_mesh

    try:
        loaded = load_mesh(scene.mesh_file())
    except WigglyInputError as err:
        raise EditError(str(err)) from None
    if isinstance(loaded, Surface):
        return loaded
    assert isinstance(loaded, TetMesh)
    return Surface(loaded.vertices, loaded.boundary_faces(), groups=dict(loaded.groups))


def _display_groups(scene: Scene, surface, model) -> dict[str, np.ndarray]:
    from types import SimpleNamespace

    tets = model.tets if model is not None else SimpleNamespace(vertices=None, groups=None)
    resolved = resolve_groups(scene, SimpleNamespace(surface=surface, tets=tets))
    out = {}
    for name, idx in resolved.items():
        if scene.groups[name].on == "tets":
            from scipy.spatial import cKDTree

            _, idx = cKDTree(surface.vertices).query(model.tets.vertices[idx])
            idx = np.unique(idx)
        out[name] = np.asarray(idx, np.int64)
    return out


def dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), default=_default).encode()


def _default(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    raise TypeError(f"cannot serialize {type(o).__name__}")

