"""The editor's playback: every state the session asks for becomes frames the browser plays.

* the *fast* worker thread answers every request with a linear solve (Theorem 1) and linear
  playback (milliseconds: this is what the browser shows while a gizmo is dragged and right
  after it is released);
* the *warped* refinement then solves the same states with the warped solve (Theorem 2), a
  few Gauss-Newton iterations at a time, warm-started from its previous result, publishing
  frames as it goes.  It runs in a child process (:mod:`wiggly.editor.refine`) so that its
  long calls holding the GIL never delay the server or the fast worker.

Newest request wins: the fast worker has a one-slot :class:`~wiggly.editor.bus.Mailbox` (a
request not yet taken is replaced by a newer one), and the refinement abandons its solve
between chunks of iterations as soon as a newer request exists.  Every request has a sequence
number ``seq``; the browser shows frames of the highest ``seq`` it has seen (and, within one
``seq``, warped frames over linear ones).  Sequence numbers restart with the process, so every
frame set also carries the process's ``instance`` id (a restarted server is a new instance).

Gizmo drags ask for "drag" requests: their frames and status events are not replayed to tabs
opened later, and the newest final frames are never evicted by them.  While the gizmo moves,
each drag request supersedes the last, so the refinement abandons their warped solves after
an iteration; when the gizmo holds still, the warped solve of the held pose completes and its
frames (``final`` False, request "drag") replace the linear preview before the release.
"""

from __future__ import annotations

import threading
import time
import traceback
import warnings
from collections import OrderedDict
from concurrent.futures import CancelledError
from dataclasses import dataclass, field, replace

import numpy as np

from wiggly.editor.bus import EventBus, Mailbox
from wiggly.editor.physics import Physics, Superseded, model_key, modes_key
from wiggly.editor.refine import PLAYBACK_BYTES, Refiner, playback_fps, residual_max
from wiggly.editor.state import EditorState
from wiggly.errors import WigglyInputError
from wiggly.memo import Memo
from wiggly.progress import reporting
from wiggly.scene import resolve_groups

__all__ = ["FrameSet", "Playback", "Request"]

FRAME_SETS_KEPT = 6
PROBLEMS_KEPT = 3


@dataclass(frozen=True)
class Request:
    """A solve of ``state`` (linear, then warped if the scene warps): ``kind`` "drag" (a
    gizmo's preview, never logged) or "final"."""

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
    kind: str = "final"  # the request's kind: "drag" frames are previews
    info: dict = field(default_factory=dict)

    def meta(self) -> dict:
        F, n, _ = self.positions.shape
        return {"id": self.id, "seq": self.seq, "version": self.version, "stage": self.stage,
                "final": self.final, "start": self.start, "fps": self.fps, "n_frames": F,
                "n_vertices": n, "request": self.kind, **self.info}


#: A body whose centroid sinks along gravity by more than this many times its size is
#: told why (:func:`fall_notice`).
FALL_SIZES = 2.0


def fall_notice(positions: np.ndarray, times: np.ndarray, gravity, size: float) -> str | None:
    """Why the body leaves the view, when its centroid sinks along gravity by more than
    ``FALL_SIZES`` times its size over the frames (F, n, 3); None otherwise."""
    g = np.asarray(gravity, dtype=np.float64)
    norm = float(np.linalg.norm(g))
    if norm == 0.0 or size <= 0.0 or len(positions) < 2:
        return None
    down = positions.mean(axis=1, dtype=np.float64) @ (g / norm)
    k = int(np.argmax(down - down[0]))
    drop = float(down[k] - down[0])
    if drop <= FALL_SIZES * size:
        return None
    return (f"the body falls {drop:.2g} m by t = {float(times[k]):.3g} s ({drop / size:.0f} "
            "times its size): gravity pulls it and nothing holds it; fix a group (the "
            "fixed box of its row in Groups), key it where it should be, or set gravity to 0")


def done_message(info: dict) -> str:
    """The status of a finished warped solve."""
    return (f"converged in {info['iterations']} iterations" if info["converged"]
            else f"stopped after {info['iterations']} iterations (not converged)")


class Playback:
    """Frames of the states the session asks for (see the module doc)."""

    def __init__(self, bus: EventBus, physics: Physics, instance: str):
        self.bus, self.physics, self.instance = bus, physics, instance
        self._lock = threading.Lock()
        self._seq = 0
        self._told_falling: set = set()  # scene files whose fall a notice explained
        # the scene file whose final warped frames folded tets (a notice said so)
        self._folding: object = None
        self._told: set = set()  # (scene file, warning) pairs the page was told of
        # the published frame sets by id (a counter), oldest first; not a cache (a page that
        # asks for a forgotten id gets a 404) and the newest final ones are never evicted
        self._frames: OrderedDict[int, FrameSet] = OrderedDict()
        self._frame_id = 0
        self.fast_box = Mailbox()
        self._stop = threading.Event()
        self._refiner: Refiner | None = None  # started by the first warped scene
        self._thread = threading.Thread(target=self._worker, args=(self.fast_box,),
                                        name="wiggly-fast", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self.fast_box.close()
        if self._refiner is not None:
            self._refiner.close()

    @property
    def refiner(self) -> Refiner:
        if self._refiner is None:
            self._refiner = Refiner(self._on_refined)
        return self._refiner

    def _supersede(self, seq: int) -> None:
        if self._refiner is not None:  # a running warped refinement stops
            self._refiner.supersede(seq)

    def _next_seq(self) -> int:
        with self._lock:
            self._seq += 1
            return self._seq

    def request(self, state: EditorState, version: int, kind: str) -> int:
        """Solve ``state`` (newest wins); its ``seq``."""
        seq = self._next_seq()
        self.physics.want(state.scene)
        self._supersede(seq)
        self.fast_box.put(Request(seq, version, state, kind))
        return seq

    def restore(self, state: EditorState, version: int) -> int:
        """A drag was abandoned: show ``state`` again.  Its final frames are announced again
        under a new ``seq`` if they exist; otherwise (the drag interrupted its refinement)
        it is solved again."""
        with self._lock:
            best = self._best(lambda fs: fs.version == version and fs.kind == "final")
        if best is None or not best.final:
            return self.request(state, version, "final")
        seq = self._next_seq()
        self.physics.want(state.scene)
        self._supersede(seq)
        self._publish(replace(best, seq=seq, info=dict(best.info)))
        info = best.info
        message = done_message(info) if best.stage == "warped" else "linear solve"
        self.bus.publish("solve", seq=seq, version=version, stage="done", message=message,
                         **info)
        return seq

    # --- frames ---------------------------------------------------------------------------
    def frames(self, frame_id: int) -> FrameSet | None:
        with self._lock:
            return self._frames.get(frame_id)

    def _best(self, keep) -> FrameSet | None:
        best = None
        for fs in self._frames.values():
            if keep(fs) and (best is None or (fs.seq, fs.stage == "warped", fs.final) >=
                             (best.seq, best.stage == "warped", best.final)):
                best = fs
        return best

    def latest(self, final: bool = False, committed: bool = False) -> FrameSet | None:
        """The frames of the newest request (``final``: the newest final ones; ``committed``:
        the newest of a logged state, not of a drag)."""
        with self._lock:
            return self._best(lambda fs: (fs.final or not final) and
                              (fs.kind == "final" or not committed))

    def _publish(self, fs: FrameSet) -> None:
        with self._lock:
            self._frame_id += 1
            fs.id = self._frame_id
            self._frames[fs.id] = fs
            newest_final = self._best(lambda f: f.final)
            pinned = {fs.id, newest_final.id if newest_final is not None else fs.id}
            for old in list(self._frames):
                if len(self._frames) <= FRAME_SETS_KEPT:
                    break
                if old not in pinned:  # the newest final frames stay (a new tab's)
                    del self._frames[old]
        self.bus.publish("frames", sticky=fs.kind != "drag", instance=self.instance,
                         **fs.meta())

    # --- workers --------------------------------------------------------------------------
    def _on_refined(self, kind: str, seq: int, version: int, payload: list) -> None:
        """Answers of the warped refinement process (on its relay thread)."""
        if kind == "frames":
            final, start, fps, positions, info = payload
            request = info.pop("request", "final")
            drag = request == "drag"  # a held drag's warped preview: never the final frames
            folds, source = info.pop("folds", None), info.pop("source", None)
            missed, said_by_solve = info.pop("missed", None), info.pop("said", [])
            if final and not drag:
                for message in said_by_solve:  # a warped secondary motion's own warnings
                    self._notice_once(source, message)
                # said when a file's motion starts to fold, not again while its edits keep it
                if folds is not None and self._folding != source:
                    self.bus.publish("notice", sticky=False, level="warning", message=folds)
                self._folding = source if folds is not None else None
                self._notice_once(source, missed)  # keys the final motion misses
            self._publish(FrameSet(0, seq, version, "warped", final and not drag, start, fps,
                                   positions, request, info))
            said = {k: v for k, v in info.items() if k != "fold_spans"}  # the frames' own
            if final:
                self.bus.publish("solve", sticky=not drag, seq=seq, version=version,
                                 stage="done", message=done_message(said), **said)
            else:
                self.bus.publish("solve", sticky=not drag, seq=seq, version=version,
                                 stage="warped",
                                 message=f"warped solve: {info['iterations']} iterations", **said)
        elif kind == "progress":
            info = payload[0]
            drag = info.pop("request", "final") == "drag"
            self.bus.publish("solve", sticky=not drag, seq=seq, version=version, stage="warped",
                             message=f"warped solve: {info['iterations']} iterations", **info)
        elif kind == "abandoned":
            self.bus.publish("solve", sticky=False, seq=seq, version=version, stage="abandoned",
                             message="superseded by a newer edit", **payload[0])
        elif kind == "error":
            self.bus.publish("solve", seq=seq, version=version, stage="error",
                             message=payload[0])
        elif kind == "died" and not self._stop.is_set():
            self.bus.publish("notice", level="error", message=payload[0]["message"] +
                             "; restarting it")
            self._refiner = Refiner(self._on_refined)

    def _worker(self, box: Mailbox) -> None:
        with reporting(False):  # the page shows the solves; the server's terminal stays quiet
            self._serve(box)

    def _serve(self, box: Mailbox) -> None:
        problems = Memo(PROBLEMS_KEPT)  # by body and time range: their splines are reused
        while not self._stop.is_set():
            req = box.take(timeout=0.5)
            if req is None:
                continue
            try:
                self._solve(req, box, problems)
            except (CancelledError, Superseded):  # closing, or a newer edit needs other physics
                continue
            except WigglyInputError as err:
                self.bus.publish("solve", seq=req.seq, version=req.version, stage="error",
                                 message=str(err))
            except Exception as err:  # a bug: report it, keep the worker alive
                if self._stop.is_set():  # closing: the physics' pool is shut down under it
                    return
                traceback.print_exc()
                self.bus.publish("solve", seq=req.seq, version=req.version, stage="error",
                                 message=f"internal error: {type(err).__name__}: {err}")

    def _solve(self, req: Request, box: Mailbox, problems) -> None:
        """Linear solve and linear playback (fast); then hand final requests of warped scenes
        to the refinement process."""
        scene = req.state.scene
        body = self.physics.body(scene, abandon=lambda: box.pending() or self._stop.is_set())
        if body is None:
            return
        # what the solve warns of (a key on fixed vertices, ...) is the user's to see in the
        # page, as `wiggly animate` prints it: a notice, once per scene file and warning
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            self._solve_linear(req, box, problems, body, scene)
        # a warped secondary motion's preview is its linear solve, whose warnings are the
        # linear model's (a turn keeps the rest axes): the warped refinement says its own
        refined = scene.secondary_motion and scene.simulation.warp
        if req.kind == "final" and not refined:
            for w in said:
                self._tell_once(scene, str(w.message))

    def _tell_once(self, scene, message: str | None) -> None:
        """A notice of ``message`` in the page, once per scene file (the linear solve's)."""
        self._notice_once(scene.source, message)

    def _notice_once(self, source, message: str | None) -> None:
        """A notice of ``message`` in the page, once per scene file ``source``."""
        if message is not None and (source, message) not in self._told:
            self._told.add((source, message))
            self.bus.publish("notice", sticky=False, level="warning", message=message)

    def _solve_linear(self, req: Request, box: Mailbox, problems, body, scene) -> None:
        """:meth:`_solve` once the body is ready."""
        from wiggly.scene import keyframes_of, problem_of, scene_to_dict
        from wiggly.scene.body_notes import soft_note, thin_joint
        from wiggly.scene.drive import check_driver_against, secondary_of
        from wiggly.scene.validation import Problems
        from wiggly.solve.surface import warn_straight

        if scene.drive is not None:  # the driver's scale and axes, as `wiggly animate` checks
            p = Problems(scene.where())
            check_driver_against(scene, body.surface.n_vertices, body.surface.faces,
                                 scene.mesh_file().name, p, body.surface.vertices)
            p.raise_if_any()
        groups = resolve_groups(scene, body.model)
        keys = keyframes_of(scene, body, groups)
        start, end = scene.time_range()
        pkey = (modes_key(scene), scene.damping, scene.simulation.gravity, start, end,
                scene.simulation.preroll, scene.time.loop)
        drag = req.kind == "drag"
        t0 = time.perf_counter()
        self.bus.publish("solve", sticky=not drag, seq=req.seq, version=req.version,
                         stage="linear", message="linear solve")
        if scene.secondary_motion:
            # the driver owns its groups, physics the rest (wiggly.drive.secondary)
            linear = replace(scene, simulation=replace(scene.simulation, warp=False))
            anim = secondary_of(linear, body, groups, keys)
        else:
            anim = problems.get(pkey, lambda: problem_of(scene, body)).solve(keys, warped=False)
        if drag and box.pending():
            return  # a newer request waits: skip this stale preview's playback frames
        fps = playback_fps(scene.time.fps, start, end, body.surface.n_vertices)
        if fps < scene.time.fps and not drag:
            self._tell_once(scene, (
                f"playback shows {fps:.3g} of the shot's {scene.time.fps:g} frames per second: "
                f"all of them, of {body.surface.n_vertices} surface vertices, would take more "
                f"than {PLAYBACK_BYTES // 2**20} MB; exports keep {scene.time.fps:g} fps"))
        times = anim.frame_times(fps)
        positions = anim.positions(times, dtype=np.float32)
        warp = scene.simulation.warp
        final = not warp and not drag
        info = {"seconds": time.perf_counter() - t0,
                "residual_max": residual_max(anim) if final else None}
        self._publish(FrameSet(0, req.seq, req.version, "linear", final, float(times[0]), fps,
                               positions, req.kind, info))
        if req.kind == "final" and not warp:  # as `wiggly animate` checks (warped: refine)
            warn_straight(anim, times, scene.where())
        if req.kind == "final":
            held = anim.held_modes if scene.secondary_motion else None
            self._tell_once(scene, thin_joint(scene, body, held) or soft_note(scene, body, held))
        if req.kind == "final" and scene.source not in self._told_falling:
            rest = body.rest_positions()
            notice = fall_notice(positions, times, scene.simulation.gravity,
                                 float(np.linalg.norm(np.ptp(rest, axis=0))))
            if notice is not None:  # once per scene file: a drop may be what the user wants
                self._told_falling.add(scene.source)
                self.bus.publish("notice", sticky=False, level="warning", message=notice)
        if final:
            self.bus.publish("solve", seq=req.seq, version=req.version, stage="done",
                             message="linear solve", **info)
        elif warp and not (drag and scene.secondary_motion):
            # a drag's warped solve completes only while the gizmo holds still (newest wins)
            model = self.physics.model_future(scene).result()
            # the linear frames are shown; until the refinement's first progress (it may
            # load the body first) the page says what runs
            self.bus.publish("solve", sticky=not drag, seq=req.seq, version=req.version,
                             stage="refining", message="linear frames shown; refining warped",
                             **info)
            self.refiner.solve(req.seq, req.version, scene_to_dict(scene), scene.source,
                               model_key(scene), model, req.kind)
