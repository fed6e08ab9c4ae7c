"""The editor's physics: models (tet meshes) and bodies (M, K, modes) by setting.

Tetrahedralization (fTetWild) and the eigensolver run for seconds in native calls that hold
Python's global interpreter lock, so they run in a child process (:func:`child_main`): in a thread
they would stop the server from answering, and the page from showing their progress, until
they end.  The parent keeps one job thread (:class:`Physics`) that sends a job to the child and
waits on its pipe, publishing the child's stage and the elapsed time twice a second.  A job
nobody wants any more (the user changed the resolution again) is abandoned by killing the
child, which is started again for the next job.

Protocol (messages of :mod:`wiggly.editor.channel` on the child's stdin and stdout): the
parent sends ``("model", key, path, resolution, edge_length, repair, scale, up)`` and ``("modes",
model_key, model or None, scene_dict, source)``; the child answers ``("status", stage, message,
fraction)`` while it works, then ``("model", model)``, ``("modes", body)`` (the scene's body
from :func:`wiggly.scene.body_of`, without its damping and gravity) or ``("error", message,
is_input_error)``, after a ``("warning", message)`` for each warning the job raised (the page
shows them as notices).  The child keeps the :data:`MODELS_KEPT` models it used last (a
:class:`~wiggly.memo.Memo`, touched when a job succeeds), and the parent mirrors that memo
with the same rule, so it sends a model only to a child that does not have it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace

import numpy as np

from wiggly.editor import channel
from wiggly.editor.bus import EventBus
from wiggly.errors import WigglyInputError
from wiggly.memo import Memo
from wiggly.scene import Scene, resolve_groups, scene_to_dict
from wiggly.scene import modes_key as scene_modes_key

__all__ = ["Physics", "Preparer", "Superseded", "child_main", "model_key", "modes_key",
           "with_dynamics"]

HEARTBEAT = 0.5  # s between progress events while the child works
MODELS_KEPT = 2  # tet meshes the child keeps (and the parent's model futures)
BODIES_KEPT = 3  # bodies (M, K, modes) by setting
VARIANTS_KEPT = 4  # bodies with their damping and gravity
# The child yields the processor to the server (and the page) when both want it: a busy machine
# must not delay the server's answers (it costs the preparation little: the server is idle).
CHILD_NICENESS = 5
_NICE = "import os\ntry:\n    os.nice({})\nexcept OSError:\n    pass\n"


def child_niceness(niceness: int) -> int:
    """The niceness an editor child process takes: ``niceness``, or 0 where the environment
    sets ``WIGGLY_EDITOR_NICE=0`` (the test suite: its parallel workers, at full priority,
    starved a child at +10 past a 150 s wait for its frames; a user's editor yields)."""
    return 0 if os.environ.get("WIGGLY_EDITOR_NICE") == "0" else niceness


class Superseded(Exception):
    """The job was abandoned: a newer edit wants another model or body."""


def model_key(scene: Scene) -> tuple:
    """What the tet mesh depends on: the file (path and modification time) and its options."""
    f = scene.mesh_file()
    try:
        mtime = f.stat().st_mtime_ns
    except OSError:
        mtime = 0
    m = scene.mesh
    return (str(f), mtime, m.resolution, m.edge_length, m.repair, m.metres_per_unit, m.up)


def modes_status(scene: Scene, model) -> str:
    """What the body's preparation says while it works: a secondary motion's body has only
    its rigid modes (its free parts' modes come with each solve)."""
    n = model.tets.n_tets
    if scene.secondary_motion:
        return f"preparing the body's {n} tets for secondary motion"
    return f"computing {scene.simulation.modes} modes of {n} tets (E = {scene.material.young:g} Pa)"


def modes_key(scene: Scene) -> tuple:
    """What M, K and the modes depend on: the model and :func:`wiggly.scene.modes_key`."""
    return (model_key(scene), *scene_modes_key(scene))


def with_dynamics(body, damping, gravity):
    """``body`` with the scene's damping and gravity (:meth:`wiggly.Body.with_dynamics`:
    same M, K, modes and warp; nothing is recomputed)."""
    from wiggly.body import Damping

    return body.with_dynamics(damping=Damping(damping.alpha, damping.beta),
                              gravity=np.asarray(gravity, float))


# ----------------------------------------------------------------------------------------------
# the child process


def child_main() -> None:  # pragma: no cover - runs in the subprocess (tested end to end)
    """The child's loop (started by :class:`Preparer`)."""
    inp, out = channel.child_ends()
    models = Memo(MODELS_KEPT)  # touched on success only: the parent's mirror does the same

    def status(stage: str, message: str, fraction: float) -> None:
        channel.send(out, ("status", stage, message, fraction))

    while True:
        msg = channel.receive(inp)
        if msg is None:
            return
        # what the job warns of (a repaired mesh, ...) is the user's: told to the parent
        # before the answer, and shown in the page, not printed raw on the editor's terminal
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            reply, keep = _child_job(msg, models, status)
        for message in dict.fromkeys(str(w.message) for w in said):
            channel.send(out, ("warning", message))
        channel.send(out, reply)
        if keep is not None:
            models.put(*keep)


def _child_job(msg: tuple, models: Memo, status) -> tuple[tuple, tuple | None]:  # pragma: no cover
    """One job of :func:`child_main`: its answer (or error), and the model to keep."""
    from wiggly.mesh import load_model
    from wiggly.scene import body_of, scene_from_dict

    try:
        if msg[0] == "model":
            _, key, path, resolution, edge_length, repair, scale, up = msg
            name = os.path.basename(path)
            status("mesh", f"reading and tetrahedralizing {name}", 0.1)
            model = load_model(path, resolution=resolution, edge_length=edge_length,
                               repair=repair, scale=scale, up=up)
            return ("model", model), (key, model)
        _, key, model, data, source = msg
        if model is None:
            model = models.peek(key)
        if model is None:
            raise RuntimeError("the physics process does not hold the model")
        scene = scene_from_dict(data)
        scene.source = source
        status("modes", modes_status(scene, model), 0.4)
        body = body_of(scene, model, resolve_groups(scene, model), dynamics=False,
                       body_modes=not scene.secondary_motion)
        return ("modes", body), (key, model)
    except WigglyInputError as err:
        return ("error", str(err), True), None
    except Exception as err:
        traceback.print_exc()
        return ("error", f"{type(err).__name__}: {err}", False), None


class Preparer:
    """The parent side of the child process: one job at a time (from the job thread)."""

    def __init__(self, on_warning: Callable[[str], None] | None = None):
        self.on_warning = on_warning  # what the child's jobs warn of
        self._proc: subprocess.Popen | None = None
        self._known = Memo(MODELS_KEPT)  # the model keys the running child holds (its mirror)
        self._lock = threading.Lock()
        self._closed = False
        self.start()

    def start(self) -> None:
        """Start the child if it is not running (it imports the libraries right away)."""
        with self._lock:
            if self._closed or (self._proc is not None and self._proc.poll() is None):
                return
            self._proc = subprocess.Popen(
                [sys.executable, "-P", "-c", _NICE.format(child_niceness(CHILD_NICENESS)) +
                 "from wiggly.editor.physics import child_main; child_main()"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, close_fds=True)
            self._known.clear()

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def knows(self, key: tuple) -> bool:
        return key in self._known

    def call(self, msg: tuple, on_status: Callable[[tuple | None], None],
             abandon: Callable[[], bool]) -> tuple:
        """Send a job, relay its status (None: a heartbeat) and return its answer; kill the
        child and raise :class:`Superseded` as soon as ``abandon()`` is true."""
        self.start()
        proc = self._proc
        if proc is None:
            raise Superseded("the editor is closing")
        try:
            out = os.dup(proc.stdin.fileno())  # this call's own (below)
            try:
                channel.send(out, msg)
            finally:
                os.close(out)
        except (BrokenPipeError, OSError, ValueError):
            self.kill()
            raise RuntimeError("the physics process exited") from None
        # a descriptor of this call's own: kill() on another thread closes the child's
        # pipe, and the number it had may be reused at once by a file or pipe opened
        # elsewhere in the process (a later job's child, a user's subprocess), which this
        # loop would then read from (a closed session's job took a new `wiggly edit`'s
        # whole stderr in a test)
        try:
            fd = os.dup(proc.stdout.fileno())
        except (OSError, ValueError):
            raise Superseded("the editor is closing") from None
        try:
            return self._replies(fd, proc, msg, on_status, abandon)
        finally:
            os.close(fd)

    def _replies(self, fd: int, proc: subprocess.Popen, msg: tuple,
                 on_status: Callable[[tuple | None], None], abandon: Callable[[], bool],
                 ) -> tuple:
        """:meth:`call`'s loop over the child's replies on ``fd``."""
        while True:
            if abandon():
                self.kill()
                raise Superseded("superseded by a newer edit")
            if not channel.ready(fd, HEARTBEAT):
                on_status(None)
                continue
            reply = channel.receive(fd)
            if reply is None:
                code = proc.wait()
                self.kill()
                raise RuntimeError(f"the physics process exited ({code})")
            if reply[0] == "status":
                on_status(reply[1:])
                continue
            if reply[0] == "warning":
                if self.on_warning is not None:
                    self.on_warning(reply[1])
                continue
            if reply[0] == "error":
                if reply[2]:
                    raise WigglyInputError(reply[1])
                raise RuntimeError(reply[1])
            if reply[0] in ("model", "modes"):
                self._known.put(msg[1], True)
            return reply

    def kill(self) -> None:
        with self._lock:
            proc, self._proc = self._proc, None
            self._known.clear()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc is not None:
            for stream in (proc.stdin, proc.stdout):
                try:
                    stream.close()
                except OSError:
                    pass

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self.kill()


# ----------------------------------------------------------------------------------------------
# the parent: futures by setting


class Physics:
    """Models and bodies by setting, prepared by the child process one job at a time, with
    stage events.  Jobs for settings that nobody wants any more are abandoned."""

    def __init__(self, bus: EventBus, on_warning: Callable[[str], None] | None = None):
        self.bus = bus
        self.preparer = Preparer(on_warning or (lambda message: bus.publish(
            "notice", sticky=False, level="warning", message=message)))
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="wiggly-physics")
        self._lock = threading.RLock()
        # futures by model_key / modes_key, and bodies with dynamics by (modes_key, damping,
        # gravity): value keys; a failed future is submitted again
        self._models = Memo(MODELS_KEPT)
        self._bodies = Memo(BODIES_KEPT)
        self._variants = Memo(VARIANTS_KEPT)
        self._wanted: tuple = ()
        self._held: dict[tuple, int] = {}
        self._closed = False

    def close(self) -> None:
        self._closed = True
        self._pool.shutdown(wait=False, cancel_futures=True)
        self.preparer.close()

    def want(self, scene: Scene) -> None:
        """The newest edit's scene: jobs for other settings are abandoned (unless held)."""
        with self._lock:
            self._wanted = (model_key(scene), modes_key(scene))

    def _unwanted(self, key: tuple) -> bool:
        with self._lock:
            return self._closed or (key not in self._wanted and not self._held.get(key))

    def _status(self, stage: str, message: str, fraction: float, t0: float, **kw) -> None:
        self.bus.publish("physics", stage=stage, message=message, fraction=fraction,
                         elapsed=time.perf_counter() - t0, **kw)

    def _run(self, msg: tuple, key: tuple, t0: float, first: tuple) -> tuple:
        """A child job, its stages and heartbeats published."""
        last = list(first)

        def on_status(st: tuple | None) -> None:
            if st is not None:
                last[:] = st
            self._status(*last, t0)

        self._status(*last, t0)
        return self.preparer.call(msg, on_status, lambda: self._unwanted(key))

    def model_future(self, scene: Scene) -> Future:
        key = model_key(scene)
        with self._lock:
            fut = self._models.peek(key)
            if not _usable(fut):
                fut = self._pool.submit(self._load_model, scene, key)
            self._models.put(key, fut)
            return fut

    def _load_model(self, scene: Scene, key: tuple):
        t0 = time.perf_counter()
        f = scene.mesh_file()
        if self._unwanted(key):
            raise Superseded("superseded by a newer edit")
        try:
            _, model = self._run(("model", key, str(f), scene.mesh.resolution,
                                  scene.mesh.edge_length, scene.mesh.repair,
                                  scene.mesh.metres_per_unit, scene.mesh.up),
                                 key, t0,
                                 ("mesh", f"reading and tetrahedralizing {f.name}", 0.05))
        except Superseded:
            raise
        except Exception as err:
            self._status("error", f"cannot load {f.name}: {err}", 0.0, t0)
            raise
        self._status("mesh", f"{model.tets.n_tets} tets, {model.tets.n_vertices} vertices", 0.3,
                     t0)
        return model

    def body_future(self, scene: Scene) -> Future:
        key = modes_key(scene)
        with self._lock:
            fut = self._bodies.peek(key)
            if not _usable(fut):
                model_fut = self.model_future(scene)
                fut = self._pool.submit(self._prepare, scene, key, model_fut)
            elif fut.done():  # a body made before (an undo): the page's heading says it again
                self._ready(fut.result(), time.perf_counter(), scene.secondary_motion)
            self._bodies.put(key, fut)
            return fut

    def _prepare(self, scene: Scene, key: tuple, model_fut: Future):
        t0 = time.perf_counter()
        model = model_fut.result()
        if self._unwanted(key):
            raise Superseded("superseded by a newer edit")
        mkey = key[0]
        try:
            resolve_groups(scene, model)  # a group that does not fit the mesh: say so here
            first = ("modes", modes_status(scene, model), 0.4)
            sent = None if self.preparer.knows(mkey) else model
            _, body = self._run(("modes", mkey, sent, scene_to_dict(scene), scene.source), key,
                                t0, first)
            body = replace(body, model=model)  # the model this process holds (equal values)
            _ = body.surface_basis  # playback needs it; the warp is built by exports only
        except Superseded:
            raise
        except Exception as err:
            self._status("error", f"cannot compute the modes: {err}", 0.0, t0)
            raise
        self._ready(body, t0, scene.secondary_motion)
        return body

    def _ready(self, body, t0: float, secondary: bool) -> None:
        n = body.tets.n_tets
        said = (f"body ready for secondary motion ({n} tets)" if secondary
                else f"{body.r} modes ready ({n} tets)")
        self._status("ready", said, 1.0, t0, modes=body.r,
                     tets=n,
                     frequencies=[round(float(x), 4) for x in body.modes.frequencies_hz()[:12]])

    def body(self, scene: Scene, abandon: Callable[[], bool], hold: bool = False):
        """The body of ``scene`` (None when ``abandon()`` turns true while waiting).
        ``hold``: the job must not be abandoned for newer edits (an export waits on it)."""
        key = modes_key(scene)
        if hold:
            with self._lock:
                self._held[key] = self._held.get(key, 0) + 1
        try:
            fut = self.body_future(scene)
            while True:
                try:
                    base = fut.result(timeout=0.05)
                    break
                except TimeoutError:
                    if abandon():
                        return None
        finally:
            if hold:
                with self._lock:
                    self._held[key] -= 1
                    if not self._held[key]:
                        del self._held[key]
        vkey = (key, scene.damping, scene.simulation.gravity)
        with self._lock:
            return self._variants.get(vkey, lambda: with_dynamics(base, scene.damping,
                                                                  scene.simulation.gravity))


def _usable(fut: Future | None) -> bool:
    """A future to keep: running, or done with a result (a failed one is submitted again)."""
    return fut is not None and not (fut.done() and fut.exception() is not None)
