"""The warped refinement (Theorem 2) in a separate, lower-priority process.

The Gauss-Newton iterations of the warped solve spend most of their time in calls that hold
Python's global interpreter lock (sparse products, small dense kernels); run in a thread they
would delay the server's answers and the fast linear solves by seconds while a gizmo is
dragged.  So they run in a child process (:func:`child_main`, at ``nice`` +10),
that keeps its own bodies: the parent sends the tet mesh once per model (fTetWild is
randomized, so the child must not tetrahedralize again) and the modes come from the disk cache
that the parent filled.

Protocol: messages of :mod:`wiggly.editor.channel` on the child's stdin and stdout.  The
parent sends ``("model", key, model)``,
``("solve", seq, version, scene_dict, source, model_key, kind)`` (kind "final" or "drag", as
in :class:`wiggly.editor.playback.Request`) and ``("newest", seq)``; the child answers
``("progress", seq, version, info)``, ``("frames", seq, version, final, start, fps,
positions, info)`` (``info["request"]`` is the kind), ``("error", seq, version, message)``
and ``("abandoned", seq, version, info)``.  After every iteration the child reads what has
arrived and stops as soon as a newer request exists (newest request wins).
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading
import time
import traceback
import warnings
from typing import Any

import numpy as np

from wiggly import limits
from wiggly.editor import channel
from wiggly.memo import Memo
from wiggly.solve import SolveOptions

PUSH_SECONDS = 1.5
MODELS_KEPT = 2  # tet meshes the child keeps
# time ranges (start, end, preroll, loop) of the current body whose problems and last warped
# solutions the child keeps: a solution's warm start holds per-node Jacobians (tens of MB on
# a 20k-tet body), so a session that tries many shot lengths must not keep them all
RANGES_KEPT = 3
PLAYBACK_BYTES = 256 * 2**20  # playback frames of one solve (float32) kept in memory


def playback_fps(fps: float, start: float, end: float, n_vertices: int) -> float:
    """The frame rate of the editor's playback: the scene's, unless its frames of
    ``n_vertices`` would take more than :data:`PLAYBACK_BYTES` (a long shot of a fine
    surface); then the highest rate that fits (the page plays any rate)."""
    frames = limits.frame_count(end - start, fps) if end > start else 1
    if frames * n_vertices * 12 <= PLAYBACK_BYTES or end <= start:
        return float(fps)
    most = max(PLAYBACK_BYTES // (12 * max(n_vertices, 1)), 2)
    return float((most - 1) / (end - start))


class _Inbox:
    """The child's view of its stdin (a file descriptor): messages in order, and the newest
    request's seq."""

    def __init__(self, fd: int):
        self.fd = fd
        self.pending: list = []
        self.newest = 0

    def _take(self, msg) -> None:
        if msg is None:
            self.pending.append(None)
            return
        if msg[0] in ("solve", "newest"):
            self.newest = max(self.newest, msg[1])
        if msg[0] != "newest":
            self.pending.append(msg)

    def poll(self) -> None:
        """Read every message that has arrived, without blocking."""
        while channel.ready(self.fd):
            msg = channel.receive(self.fd)
            self._take(msg)
            if msg is None:
                return

    def get(self):
        while not self.pending:
            self._take(channel.receive(self.fd))
        return self.pending.pop(0)


def child_main() -> None:  # pragma: no cover - runs in the subprocess (tested end to end)
    """The child's loop (started by :class:`Refiner`)."""
    from wiggly.editor.physics import child_niceness

    inp, out = channel.child_ends()
    try:
        os.nice(child_niceness(10))
    except OSError:
        pass
    from wiggly.errors import WigglyInputError
    from wiggly.scene import (
        body_of,
        keyframes_of,
        modes_key,
        problem_of,
        resolve_groups,
        scene_from_dict,
    )
    from wiggly.scene.run import surface_groups

    inbox = _Inbox(inp)
    models = Memo(MODELS_KEPT)  # as sent, oldest out: the parent's Refiner keeps the same
    bodies: dict[tuple, Any] = {}
    problems = Memo(RANGES_KEPT)  # per time range: its SpacetimeProblem
    previous = Memo(RANGES_KEPT)  # per time range: the last warped solution (warm start)
    while True:
        msg = inbox.get()
        if msg is None:
            return
        if msg[0] == "model":
            models.put(msg[1], msg[2])
            continue
        _, seq, version, data, source, model_key, kind = msg
        inbox.poll()
        if inbox.newest > seq:
            continue
        try:
            scene = scene_from_dict(data)
            scene.source = source
            model = models.peek(model_key)
            if model is None:
                raise RuntimeError("the warped solver process does not hold the model")
            s = scene.simulation
            groups = resolve_groups(scene, model)
            bkey = (model_key, *modes_key(scene), scene.damping, s.gravity)
            body = bodies.get(bkey)
            if body is None:
                body = body_of(scene, model, groups, body_modes=not scene.secondary_motion)
                bodies.clear()
                problems.clear()
                previous.clear()
                bodies[bkey] = body
            keys = keyframes_of(scene, body, groups)
            if scene.secondary_motion:
                _secondary(seq, version, scene, body, groups, keys, out,
                           surface_groups(scene, groups))
                continue
            pkey = (*scene.time_range(), s.preroll, scene.time.loop)
            problem = problems.peek(pkey)
            if problem is None:  # a new time range (the oldest kept one leaves)
                problem = problem_of(scene, body)
            problems.put(pkey, problem)
            _refine(seq, version, scene, problem, keys, previous, pkey, out, inbox, kind,
                    surface_groups(scene, groups))
        except WigglyInputError as err:
            channel.send(out, ("error", seq, version, str(err)))
        except BrokenPipeError:  # the editor is gone (stopped or killed): nobody to tell
            return
        except Exception as err:
            traceback.print_exc()
            channel.send(out, ("error", seq, version,
                               f"internal error: {type(err).__name__}: {err}"))


def _secondary(seq, version, scene, body, groups, keys, out,
               shown_groups=None) -> None:  # pragma: no cover - runs in the subprocess
    """The warped secondary motion of a ``[drive]`` scene (one linear solve, Gauss-Newton
    only for keys on the free parts), as ``wiggly animate`` runs it, with the notices of its
    checks (folds, keys missed) as a keyed scene's final motion has them."""
    from wiggly.scene.drive import secondary_of

    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:  # the page's notices, as `wiggly
        warnings.simplefilter("always")  # animate` warns (the linear preview's are not said)
        anim = secondary_of(scene, body, groups, keys)
    start, end = scene.time_range()
    fps = playback_fps(scene.time.fps, start, end, body.surface.n_vertices)
    times = anim.frame_times(fps)
    notes = _notes(scene, anim, times, anim.folds(times), shown_groups)  # before residual_max
    info = {"iterations": int(anim.info.get("iterations", 0)),
            "converged": bool(anim.info.get("converged", True)),
            "objective": float(anim.energy()),
            "seconds": time.perf_counter() - t0, "residual_max": residual_max(anim), **notes,
            "said": list(dict.fromkeys([*(str(w.message) for w in caught), *notes["said"]]))}
    positions = anim.positions(times, dtype=np.float32)
    channel.send(out, ("frames", seq, version, True, float(times[0]), fps, positions, info))


def _notes(scene, anim, times, checked, groups) -> dict:  # pragma: no cover - subprocess
    """A final motion's notices, as ``wiggly animate`` warns: its folds (``checked``:
    ``anim.folds(times)``, None: not checked) with the spans the page tints, and the keys it
    misses (the residual rows are kept in ``anim.info`` for :func:`residual_max`)."""
    from wiggly.scene.run import fold_highlights, fold_remedy, missed_note
    from wiggly.solve import fold_note
    from wiggly.solve.surface import straight_note

    straight = straight_note(anim, times, scene.where())  # long edges that stay straight
    out = {"folds": None if checked is None
           else fold_note(anim, api=False, groups=groups, checked=checked,
                          remedy=fold_remedy(scene)),
           "missed": missed_note(scene, anim), "source": scene.source,
           "said": [straight] if straight else []}
    if out["folds"] is not None:  # and where: the page tints them as previews do
        out["fold_spans"] = [{"from": h.time, "until": h.until, "vertices": h.vertices.tolist()}
                             for h in fold_highlights(anim, times, checked)]
    return out


class _Abandoned(Exception):
    """A newer request arrived: this refinement's result would be outdated."""


def _refine(seq, version, scene, problem, keys, previous, pkey, out, inbox,
            kind="final", groups=None):  # pragma: no cover - runs in the subprocess
    """One warped solve, as ``wiggly animate`` runs it (the same options: the editor's
    exports and the CLI agree), reading the inbox after every iteration: a newer request
    abandons it, and a progress line goes out every ``PUSH_SECONDS``.  Its answers carry the
    request's ``kind``; a drag's solution, too, starts the next solve of the range."""
    from wiggly.scene.drive import linear_start_of

    t0 = time.perf_counter()
    init = previous.peek(pkey)
    last_push = time.perf_counter()

    def after_iteration(count: int) -> None:
        nonlocal last_push
        inbox.poll()
        if inbox.newest > seq:
            raise _Abandoned(count)
        if time.perf_counter() - last_push > PUSH_SECONDS:
            channel.send(out, ("progress", seq, version,
                               {"iterations": count, "converged": False,
                                "seconds": time.perf_counter() - t0, "request": kind}))
            last_push = time.perf_counter()

    try:
        after_iteration(0)  # a newer request may have arrived already
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            anim = problem.solve(
                keys, warped=True, warm_start=init.warm_start if init is not None else None,
                options=SolveOptions(warn=False, callback=after_iteration),
                linear_start=linear_start_of(scene, problem.body, keys) if init is None
                else None,
            )
    except _Abandoned as stop:
        channel.send(out, ("abandoned", seq, version, {"iterations": stop.args[0]}))
        return
    previous.put(pkey, anim)
    solved = time.perf_counter() - t0
    body = problem.body
    fps = playback_fps(scene.time.fps, problem.start, problem.end, body.surface.n_vertices)
    times = anim.frame_times(fps)
    # one warped playback on the tet mesh: the frames shown, and the folds in them
    moved = anim.displacements(times, on="tets")
    # creases and missed keys of the final motion, explained (before residual_max: it reads
    # the missed-key check's rows)
    notes = (_notes(scene, anim, times, anim.folds(times, displacements=moved), groups)
             if kind == "final" else {"folds": None, "missed": None, "source": scene.source,
                                      "said": []})
    info = {"iterations": int(anim.info.get("iterations", 0)),
            "converged": bool(anim.info.get("converged")),
            "objective": float(anim.info.get("objective", np.nan)),
            "seconds": solved, "residual_max": residual_max(anim),
            "request": kind, **notes}
    positions = (body.to_surface(moved) + body.rest_positions()).astype(np.float32)
    channel.send(out, ("frames", seq, version, True, float(times[0]), fps, positions, info))


def residual_max(anim) -> float | None:
    """Largest distance (m) of a keyframed vertex to its target, over all keyframes (the
    rows a missed-key check kept in ``anim.info``, if it ran)."""
    try:
        rows = anim.info.get("keyframe_residuals") or anim.constraint_residuals()
    except Exception:
        return None
    vals = [r["position_max"] for r in rows if "position_max" in r]
    return float(max(vals)) if vals else None


class Refiner:
    """The parent side: starts the child, relays requests and answers.

    ``on_result(kind, seq, version, payload)`` is called on the relay thread for every answer.
    """

    def __init__(self, on_result):
        self._proc = subprocess.Popen(
            [sys.executable, "-P", "-c",
             "from wiggly.editor.refine import child_main; child_main()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0, close_fds=True)
        self._lock = threading.Lock()
        self._sent_models = Memo(MODELS_KEPT)  # what the child holds: put on send, as there
        self._newest = 0
        self._on_result = on_result
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="wiggly-warped-relay",
                                        daemon=True)
        self._thread.start()

    def _send(self, msg) -> None:
        with self._lock:
            try:
                channel.send(self._proc.stdin.fileno(), msg)
            except (BrokenPipeError, OSError, ValueError):
                pass  # the relay reports a dead child

    def supersede(self, seq: int) -> None:
        """A newer request exists: the child stops refining older ones."""
        if seq > self._newest:
            self._newest = seq
            self._send(("newest", seq))

    def solve(self, seq: int, version: int, scene_dict: dict, source, model_key: tuple,
              model, kind: str = "final") -> None:
        if model_key not in self._sent_models:
            self._send(("model", model_key, model))
            self._sent_models.put(model_key, True)
        self._newest = max(self._newest, seq)
        self._send(("solve", seq, version, scene_dict, source, model_key, kind))

    def _relay(self) -> None:
        while True:
            try:
                msg = channel.receive(self._proc.stdout.fileno())
            except (OSError, ValueError, pickle.UnpicklingError):
                msg = None
            if msg is None:
                if not self._stop.is_set():
                    code = self._proc.wait()
                    self._on_result("died", 0, 0, [{"message": "the warped solver process "
                                                    f"exited ({code})"}])
                return
            kind, seq, version, *rest = msg
            try:
                self._on_result(kind, seq, version, rest)
            except Exception:
                traceback.print_exc()

    def close(self) -> None:
        """Stop the child: it ends when its stdin closes (between chunks of iterations); one
        still busy (or importing its libraries) is terminated after a moment."""
        self._stop.set()
        with self._lock:
            try:
                self._proc.stdin.close()
            except OSError:
                pass
        try:
            self._proc.wait(timeout=0.3)
        except subprocess.TimeoutExpired:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=2)
            except subprocess.TimeoutExpired:
                self._proc.kill()
        self._thread.join(timeout=2)
