"""The driver of a batch: checks, resumes, prepares each distinct body once, runs the shots on
a backend, commits each shot's folder whole and writes the summary and the contact sheet."""

from __future__ import annotations

import fcntl
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
import uuid
from collections import deque
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from tqdm import tqdm

from wiggly.batch import summary as summary_files
from wiggly.batch.backends import LocalPool, RayCluster, WorkerDied, cpu_count
from wiggly.batch.shots import (
    TOP_LEVEL,
    Digests,
    Shot,
    body_scene,
    collect,
    keyed,
    saved_scene,
)
from wiggly.batch.sweep import Sweep
from wiggly.batch.worker import THUMBNAIL, ShotJob
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.files import atomic_file, check_writable
from wiggly.progress import (
    Counter,
    activity,
    bar,
    deprecated_progress,
    log,
    on_terminal,
    say,
    shown,
)
from wiggly.scene import Scene, scene_to_toml

MARKER = ".wiggly-batch"
LOCK = ".wiggly-batch.lock"
STAGING = ".staging"
RESULT = "result.json"
DEFAULT_DIR = "wiggly-batch"
#: Seconds between refreshes of the progress bar while nothing finishes.
TICK = 0.5


@deprecated_progress
def run(inputs, out_dir: str | os.PathLike[str] | None = None, *, workers: int | None = None,
        ray: bool | str | None = None, write: Sequence[str] | None = None,
        overwrite: bool = False, contact_sheet: bool = True,
        thumbnail_time: float | None = None, warm_start: bool = True) -> list[dict]:
    """Run many shots; return the summary as records (one dict per shot, in input order).

    ``inputs``: scene files, sweep files (``docs/sweep-format.md``), :class:`~wiggly.scene.Scene`
    or :class:`~wiggly.batch.Sweep` objects, or one of them.  Shots go into folders of
    ``out_dir`` (default: a single sweep's ``[output] dir``, else ``./wiggly-batch``), with
    ``summary.csv``, ``summary.json``, ``contact-sheet.html`` and ``contact-sheet.png``.

    ``workers``: local worker processes (default: one per core); ``ray``: True for a Ray
    cluster (a new local one, or ``RAY_ADDRESS``'s, or the one this process is connected to),
    or its address.  ``write``: file names each shot writes (default: the scene's or sweep's
    outputs).  Shots already done with the same content are skipped; a folder holding a
    different shot is replaced only with ``overwrite``.  ``contact_sheet``: render a thumbnail
    per shot (at ``thumbnail_time`` s, default: the frame farthest from rest).
    ``warm_start``: start each solve from the previous solution of the same problem in the
    worker (faster; agrees with a cold solve within the solver's distance bound).
    The shots done and failed are counted as :mod:`wiggly.progress` says: a bar on a
    terminal, a line per shot in a log.

    Paths in the records are relative to ``out_dir``.  Failed shots have ``status`` "failed"
    and an ``error``; they never stop the others.  Raises :class:`WigglyInputError` before
    any work for an invalid sweep, a changed shot's folder without ``overwrite``, or an
    unusable ``out_dir``.
    """
    t_start = time.perf_counter()
    if _imported_by_a_worker():
        raise WigglyInputError(
            "wiggly.batch.run was called while a worker process imported the script that "
            "started the batch: put the call under `if __name__ == \"__main__\":`")
    if isinstance(inputs, str | os.PathLike | Scene | Sweep):
        inputs = [inputs]
    inputs = list(inputs)
    if not inputs:
        raise WigglyInputError("no inputs: give scene files or a sweep file")
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise WigglyInputError(f"workers = {workers!r} must be an integer >= 1")
    if thumbnail_time is not None and not (isinstance(thumbnail_time, int | float)
                                           and math.isfinite(thumbnail_time)):
        raise WigglyInputError(f"thumbnail_time = {thumbnail_time!r} must be a number of "
                               "seconds")
    if workers is not None and ray not in (None, False):
        raise WigglyInputError("workers counts local processes; a Ray cluster uses its CPUs: "
                               "give workers or ray, not both")
    shots, sweeps = collect(inputs, write)
    out = Path(out_dir).expanduser() if out_dir is not None else default_out_dir(inputs, sweeps)
    with activity(f"hashing {len(shots)} shots", len(shots) > 5000):
        keyed(shots, Digests())
    request = {"contact_sheet": contact_sheet, "thumbnail_time": thumbnail_time}
    with _batch_folder(out) as token:
        _resume_names(out, shots)
        records, todo, replace = _scan(out, shots, overwrite, request)
        render_checked = False
        if contact_sheet and todo:
            from wiggly.render import RenderingError, check_offscreen

            try:
                check_offscreen()  # before any work
            except RenderingError as err:
                raise WigglyInputError(f"thumbnails for the contact sheets: {err} Or run "
                                       "without them: --no-sheet (contact_sheet=False)") from None
            render_checked = True
        backend = None
        if todo and any(s.scene.simulation.warp for s in todo):
            # compiled (or loaded) here, once, with its line; workers then load, never compile
            from wiggly.warp.kernels import ensure_compiled

            ensure_compiled()
        if todo:
            # a Ray worker may run on a machine without offscreen rendering: it checks itself
            backend = (RayCluster(None if ray is True else str(ray), False)
                       if ray not in (None, False) else
                       LocalPool(min(workers or cpu_count(), len(todo)), render_checked))
        driver = _Driver(out, token, backend, records, replace, request, warm_start)
        main = threading.current_thread() is threading.main_thread()
        previous = signal.getsignal(signal.SIGINT) if main else None
        try:
            driver.run(shots, todo)
        finally:
            try:
                ordered = _finish(out, inputs, shots, records, backend, driver, contact_sheet,
                                  t_start)
            finally:
                if main and driver.interrupted:  # Ctrl+C works again once the summary is out
                    signal.signal(signal.SIGINT, previous if previous is not None
                                  else signal.default_int_handler)
    return ordered


def _finish(out: Path, inputs, shots: list[Shot], records: dict, backend, driver,
            contact_sheet: bool, t_start: float) -> list[dict]:
    """After the shots (or an interruption): close the workers (cancelling what runs when
    interrupted), write the summary and the contact sheets; the records in shot order."""
    if backend is not None:
        backend.close(cancel=driver.interrupted)
    meta = {"backend": backend.describe() if backend else "none (nothing to run)",
            "wall_seconds": time.perf_counter() - t_start, "bodies": driver.bodies,
            "inputs": [str(i) if not isinstance(i, Scene | Sweep) else i.where()
                       for i in inputs]}
    ordered = [records[s.name] for s in shots if s.name in records]
    summary_files.write_summary(out, ordered, meta)
    if contact_sheet:
        with activity("writing the contact sheets", len(ordered) > 100):
            summary_files.write_contact_sheets(out, ordered)
    else:  # an earlier batch's sheets would contradict this summary
        for name in summary_files.SHEETS:
            (out / name).unlink(missing_ok=True)
    return ordered


def default_out_dir(inputs: list, sweeps: list[Sweep]) -> Path:
    """A single sweep's ``[output] dir``, else ``./wiggly-batch``."""
    if len(inputs) == 1 and len(sweeps) == 1 and sweeps[0].out_dir is not None:
        return sweeps[0].out_dir
    return Path(DEFAULT_DIR)


# ----------------------------------------------------------------------------------------------
# the output folder


def _imported_by_a_worker() -> bool:
    """Whether this call comes from a script that a worker process is importing (Python's
    forkserver and spawn run the calling script as ``__mp_main__``)."""
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_globals.get("__name__") == "__mp_main__":
            return True
        frame = frame.f_back
    return False


@contextmanager
def _batch_folder(out: Path):
    """Create or reuse ``out`` (a batch's folder, or a new or empty one), hold its lock, and
    yield the token workers look for to know they see it."""
    if out.exists() and not out.is_dir():
        raise WigglyInputError(f"{out} is a file; give a folder for the batch's outputs (-o)")
    if out.is_dir() and not (out / MARKER).exists() and any(out.iterdir()):
        raise WigglyInputError(f"{out} is not empty and holds no batch ({MARKER} is missing); "
                               "give a new or empty folder (-o), so that no file of yours is "
                               "replaced")
    why = check_writable(out / MARKER)
    if why is not None:
        raise WigglyInputError(f"cannot write the batch into {out}: {why}")
    out.mkdir(parents=True, exist_ok=True)
    with open(out / LOCK, "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            if not _still_there(out / LOCK, lock):  # its holder finished and removed it
                raise OSError
        except OSError:
            raise WigglyInputError(f"another wiggly batch is writing into {out}; wait for it "
                                   "or give another folder (-o)") from None
        try:
            shutil.rmtree(out / STAGING, ignore_errors=True)  # left by an interrupted batch
            token = uuid.uuid4().hex
            with atomic_file(out / MARKER) as tmp:
                tmp.write_text(token + "\n", encoding="utf-8")
            yield token
        finally:
            shutil.rmtree(out / STAGING, ignore_errors=True)
            (out / LOCK).unlink(missing_ok=True)  # while still holding it


def _still_there(path: Path, lock) -> bool:
    """Whether ``path`` is still the file ``lock`` holds (a batch removes its lock file when
    it ends; a lock taken on the removed file would lock nothing)."""
    try:
        return os.stat(path).st_ino == os.fstat(lock.fileno()).st_ino
    except OSError:
        return False


def _resume_names(out: Path, shots: list[Shot]) -> None:
    """Shots done before in ``out`` keep their folders' names, whatever other scene files
    are given now: a shot whose content key a finished folder holds takes that folder's name
    (the first such shot), and a shot whose name that takes is renamed as
    :func:`wiggly.batch.shots.collect` renames twins (``-2``, ``-3``, ...)."""
    found: dict[str, str] = {}  # content key -> the finished folder holding it
    if out.is_dir():
        for folder in sorted(out.iterdir()):
            old = read_result(folder) if folder.is_dir() else None
            if old is not None and old.get("status") == "done" and old.get("key"):
                found.setdefault(old["key"], folder.name)
    claimed: dict[str, int] = {}  # folder name -> the shot (its index) that takes it back
    for i, s in enumerate(shots):
        name = found.get(s.key) if s.scene is not None else None
        if name is not None and name not in claimed:
            claimed[name] = i
    if all(shots[i].name == name for name, i in claimed.items()):
        return
    for name, i in claimed.items():
        shots[i].name = name
    taken = set(TOP_LEVEL) | set(claimed)
    back = set(claimed.values())
    for i, s in enumerate(shots):
        if i in back:
            continue
        base, k = s.name, 2
        while s.name in taken:
            s.name, k = f"{base}-{k}", k + 1
        taken.add(s.name)


def _scan(out: Path, shots: list[Shot], overwrite: bool, request: dict):
    """Records of the shots done before (skipped), the shots to run, and the names whose
    folders may be replaced.  A shot done before runs again when its files are missing or
    changed; a folder holding another shot is an error unless ``overwrite``; a folder that
    holds no shot, or files wiggly did not write, is never replaced."""
    records: dict[str, dict] = {}
    todo: list[Shot] = []
    replace: set[str] = set()
    changed, strangers, foreign, others, pictured = [], [], [], [], []
    for s in shots:
        folder = out / s.name
        if s.scene is None:
            records[s.name] = _failed(s, s.error or "invalid scene")
            continue
        if not folder.exists():
            todo.append(s)
            continue
        old = read_result(folder)
        if old is None:
            strangers.append(s.name)
            continue
        if old.get("key") == s.key and old.get("status") == "done":
            broken = _broken(folder, old)
            wants = request["contact_sheet"] and (
                not (folder / THUMBNAIL).is_file() or
                old.get("thumbnail_request") != request["thumbnail_time"])
            if broken is None and not wants:
                records[s.name] = {**old, "resumed": True}
                continue
            if broken is not None:
                say(f"{s.name}: {broken}; it runs again")
            else:
                pictured.append(s.name)
        elif not overwrite:
            changed.append(s.name)
            continue
        else:
            others.append(s.name)
        extra = sorted(set(os.listdir(folder)) - _written(old))
        if extra:
            foreign.append(f"{s.name} ({_listed(extra, 3)})")
            continue
        replace.add(s.name)  # another shot, or this one again (broken, or a thumbnail asked)
        todo.append(s)
    if pictured:  # a solve makes the thumbnail: said, since its files are written again
        say(f"{counted(len(pictured), 'shot')} done before ({_listed(pictured)}) run again "
            "for the thumbnail the contact sheet asks (missing, or at another time), and their "
            "files are written again; --no-sheet keeps them as they are")
    problems = []
    if strangers:
        problems.append(f"{out} holds {counted(len(strangers), 'folder')} where shots go that "
                        f"wiggly did not write ({_listed(strangers)}: no {RESULT}); move them "
                        "away or give another folder (-o): --overwrite replaces only shot "
                        "folders")
    if foreign:
        problems.append(f"shot folders of {out} hold files wiggly did not write "
                        f"({_listed(foreign)}), which replacing them would delete: move "
                        "those files away first")
    if changed:
        problems.append(
            f"{out} holds {counted(len(changed), 'shot folder')} of other shots "
            f"({_listed(changed)}): their scene, mesh or outputs changed since they were "
            "written. Pass --overwrite (overwrite=True) to replace them, or give another "
            "folder (-o)")
    if problems:
        raise WigglyInputError("; ".join(problems))
    if others:
        say(f"replacing {counted(len(others), 'shot folder')} of other shots (--overwrite): "
            f"{_listed(others)}")
    return records, todo, replace


def _listed(names: list[str], most: int = 5) -> str:
    """The first ``most`` names, and how many more there are."""
    return ", ".join(names[:most]) + (f" and {len(names) - most} more"
                                      if len(names) > most else "")


def _written(record: dict) -> set[str]:
    """The names of the files wiggly wrote into a shot's folder (:meth:`_Driver._commit`)."""
    names = {Path(o).name for o in record.get("outputs") or ()} | {"scene.toml", RESULT}
    return names | ({THUMBNAIL} if record.get("thumbnail") else set())


def _broken(folder: Path, record: dict) -> str | None:
    """Why the files of a shot done before are no longer what it wrote (one missing, or
    their sizes changed), or None."""
    total = 0
    for name in sorted(_written(record) - {RESULT}):
        try:
            total += (folder / name).stat().st_size
        except OSError:
            return f"{name} is missing"
    if record.get("output_bytes") not in (None, total):
        return "its files changed since they were written"
    return None


def read_result(folder: Path) -> dict | None:
    try:
        data = json.loads((folder / RESULT).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _base_record(s: Shot) -> dict:
    return {"shot": s.name, "status": "", "error": None, "origin": s.origin, "seed": s.seed,
            "sample": s.sample, "parameters": s.parameters(), "key": s.key or None,
            "body": s.body_key[:12] or None, "resumed": False, "warnings": list(s.warnings)}


def _failed(s: Shot, error: str) -> dict:
    return {**_base_record(s), "status": "failed", "error": error}


# ----------------------------------------------------------------------------------------------
# the loop


class _Driver:
    """Keeps every core busy: bodies first (each distinct one once), then the shots whose
    body is ready; commits finished shots; shows progress."""

    def __init__(self, out: Path, token: str, backend, records: dict, replace: set,
                 request: dict, warm_start: bool) -> None:
        self.out, self.token, self.backend = out, token, backend
        self.records, self.replace, self.request = records, replace, request
        self.warm_start = warm_start
        self.shown = shown()  # the bar, or the lines, of the whole batch (wiggly.progress)
        self.bodies: list[dict] = []
        self.interrupted = False
        self.in_flight: dict[Any, tuple[str, Any]] = {}
        self.suspects: set[str] = set()  # in flight when a worker died: rerun one at a time
        self.warned: set[str] = set()
        self.body_warnings: dict[str, list[str]] = {}  # by body key: for its shots' records

    def run(self, shots: list[Shot], todo: list[Shot]) -> None:
        done = sum(r["status"] == "done" for r in self.records.values())
        failed = len(self.records) - done
        self.total = len(shots)
        self.live = self.shown and on_terminal()
        if self.live:
            self.bar = bar(total=len(shots), initial=done + failed, desc="[wiggly] batch",
                           unit="shot", dynamic_ncols=True)
        else:  # in a log: a line per shot, and the counts at the end
            self.bar = Counter("batch", "shot", self.shown, total=len(shots))
            self.bar.n = done + failed
        self.counts = {"done": done, "failed": failed}
        for r in self.records.values():
            if r["status"] == "failed":
                self._say_failed(r)
        try:
            self._loop(todo)
        except (KeyboardInterrupt, SystemExit):  # Ctrl+C, or SIGTERM (a farm, `timeout`)
            self.interrupted = True
            if threading.current_thread() is threading.main_thread():
                # an impatient second Ctrl+C would cut the summary of the shots not run
                # short (the workers' cleanup takes a second or two): batch.run restores it
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            for s in todo:
                self.records.setdefault(s.name, {**_base_record(s), "status": "not run",
                                                 "error": "interrupted"})
            raise
        finally:
            self.bar.close()

    def _loop(self, todo: list[Shot]) -> None:
        if not todo:
            return
        b = self.backend
        order = {k: i for i, k in enumerate(dict.fromkeys(s.body_key for s in todo))}
        todo = sorted(todo, key=lambda s: (order[s.body_key], s.scene.damping.alpha,
                                           s.scene.damping.beta, s.scene.simulation.gravity,
                                           s.scene.time_range()))
        waiting: dict[str, deque[Shot]] = {}
        for s in todo:
            waiting.setdefault(s.body_key, deque()).append(s)
        self.sources: dict[str, Any] = {}
        to_prepare: deque = deque()
        for key, group in waiting.items():
            source = b.cached_body(key)
            if source is not None:
                self.sources[key] = source
                self.body_warnings[key] = b.kept_warnings(key)
                for w in self.body_warnings[key]:  # said again, as `wiggly animate` does
                    self._warn(f"{body_scene(group[0].scene).where()}: {w}")
                self.bodies.append({"body": key[:12], "shots": len(group), "cached": True,
                                    "prepare_seconds": 0.0})
            else:
                scene = body_scene(group[0].scene)
                mesh = None if scene.mesh.path.startswith("builtin:") else scene.mesh_file()
                to_prepare.append(b.body_job(key, scene, mesh))
        ready: deque[Shot] = deque()
        for key in list(waiting):
            if key in self.sources:
                ready += waiting.pop(key)
        while to_prepare or ready or waiting or self.in_flight:
            if self.suspects:  # after a worker died: the tasks it may have killed, alone
                if not self.in_flight:
                    found = [(q, x) for q in (to_prepare, ready) for x in q
                             if _name(x) in self.suspects][:1]
                    if not found:
                        self.suspects.clear()
                        continue
                    queue, item = found[0]
                    queue.remove(item)
                    self._submit(item)
            else:
                while len(self.in_flight) < b.slots and to_prepare:
                    self._submit(to_prepare.popleft())
                while len(self.in_flight) < b.slots and ready:
                    self._submit(ready.popleft())
            self._status(len(to_prepare) + sum(k == "body" for k, _ in self.in_flight.values()))
            if not self.in_flight:
                for key in list(waiting):  # bodies that failed to prepare
                    for s in waiting.pop(key):
                        self._record(s, _failed(s, "its body was not prepared"))
                break
            for handle in b.wait(self.in_flight, TICK):
                if handle not in self.in_flight:  # lost with a broken pool
                    continue
                kind, item = self.in_flight.pop(handle)
                try:
                    result = b.outcome(handle)
                except WorkerDied as err:
                    self._died(kind, item, handle, str(err), to_prepare, ready, waiting)
                    continue
                self.suspects.discard(_name(item))
                if kind == "body":
                    self._body_done(item, handle, result, waiting, ready)
                else:
                    self._shot_done(item, result)

    def _submit(self, item) -> None:
        if isinstance(item, Shot):
            staging = self.out / STAGING / item.name
            job = ShotJob(item.name, item.scene, item.body_key, item.outputs, str(staging),
                          str(self.out / MARKER), self.token, self.request["contact_sheet"],
                          self.request["thumbnail_time"], self.warm_start)
            self.in_flight[self.backend.shot(job, self.sources[item.body_key])] = ("shot", item)
        else:
            self.in_flight[self.backend.prepare(item)] = ("body", item)

    def _died(self, kind, item, handle, message, to_prepare, ready, waiting) -> None:
        """A worker died.  A broken local pool loses every task in flight: with several, each
        is run again alone; the one that dies alone fails (Ray retries a task by itself)."""
        if self.backend.kind == "local":
            lost = [(kind, item), *self.in_flight.values()]
            self.in_flight.clear()
            self.backend.restart()
            if len(lost) > 1:
                for k, i in reversed(lost):
                    self.suspects.add(_name(i))
                    (to_prepare if k == "body" else ready).appendleft(i)
                return
        self.suspects.discard(_name(item))
        why = (f"the worker process died while running it ({message}); it may have run out "
               "of memory or crashed in native code")
        if kind == "body":
            self._body_done(item, handle, {"status": "failed", "error": why}, waiting, ready)
        else:
            self._record(item, _failed(item, why))

    def _body_done(self, job, handle, result, waiting, ready) -> None:
        info, source = self.backend.prepared(job, handle, result)
        shots = waiting.pop(job.key, deque())
        self.bodies.append({"body": job.key[:12], "shots": len(shots), "cached": False,
                            **{k: v for k, v in info.items() if k != "traceback"}})
        self.backend.keep_warnings(job.key, info.get("warnings", []))
        self.body_warnings[job.key] = list(info.get("warnings", []))
        for w in info.get("warnings", ()):
            self._warn(f"{job.scene.where()}: {w}")
        if info.get("status") != "done":
            for s in shots:
                self._record(s, _failed(s, f"its body could not be prepared: {info['error']}"))
            return
        self.sources[job.key] = source
        ready += shots

    def _shot_done(self, shot: Shot, result: dict) -> None:
        record = {**_base_record(shot), **{k: v for k, v in result.items() if k != "files"}}
        own = list(result.get("warnings") or ())  # the solve's and the writers' (said below)
        record["warnings"] = list(dict.fromkeys(
            [*shot.warnings, *self.body_warnings.get(shot.body_key, ()), *own]))
        staging = self.out / STAGING / shot.name
        if result.get("status") != "done":
            shutil.rmtree(staging, ignore_errors=True)
            self._record(shot, record, own)
            return
        try:
            t = time.perf_counter()
            self._commit(shot, staging, record, result.get("files"))
            record["commit_seconds"] = time.perf_counter() - t  # the summary's, not result.json's
        except OSError as err:
            shutil.rmtree(staging, ignore_errors=True)
            record.update(status="failed", error=f"could not write its folder: {err}")
        self._record(shot, record, own)

    def _commit(self, shot: Shot, staging: Path, record: dict, files: dict | None) -> None:
        """Move the shot's complete folder into place (one rename: never half-written)."""
        staging.mkdir(parents=True, exist_ok=True)
        for name, data in (files or {}).items():  # from a worker that cannot see the folder
            (staging / name).write_bytes(data)
        (staging / "scene.toml").write_text(scene_to_toml(saved_scene(shot)), encoding="utf-8")
        record["folder"] = shot.name
        record["outputs"] = [f"{shot.name}/{o}" for o in _output_files(staging, shot.outputs)]
        record["thumbnail"] = f"{shot.name}/{THUMBNAIL}" if (staging / THUMBNAIL).is_file() \
            else None
        record["thumbnail_request"] = self.request["thumbnail_time"]
        record["output_bytes"] = sum(p.stat().st_size for p in staging.iterdir())
        (staging / RESULT).write_text(json.dumps(summary_files.jsonable(record), indent=1),
                                      encoding="utf-8")
        final = self.out / shot.name
        aside = None
        if final.exists() and shot.name in self.replace:
            aside = self.out / STAGING / f"{shot.name}.replaced"
            os.replace(final, aside)
        try:
            os.replace(staging, final)
        except OSError:
            if aside is not None:
                os.replace(aside, final)
            raise
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)

    def _record(self, shot: Shot, record: dict, said: Sequence[str] = ()) -> None:
        """Count ``record`` in and show it; ``said``: its warnings not said before (those of
        its scene and body are said when read and prepared)."""
        self.records[shot.name] = record
        self.counts["done" if record["status"] == "done" else "failed"] += 1
        if record["status"] != "done":
            self._say_failed(record)
        self._status(0)  # before the count: a log line shows both (Counter.update)
        if not self.live and record["status"] == "done":
            say(f"{record['shot']} done ({self.bar.n + 1} of {self.total})")
        self.bar.update(1)
        for w in said:
            self._warn(f"{record['shot']}: {w}")

    def _warn(self, message: str) -> None:
        """A warning of a body or a shot, shown as ``wiggly animate`` shows it (once per
        message), besides the summary's record."""
        if message in self.warned:
            return
        self.warned.add(message)
        with tqdm.external_write_mode(file=sys.stderr):  # above a live bar
            warn(message)

    def _say_failed(self, record: dict) -> None:
        if self.shown:
            first = (record.get("error") or "").splitlines() or [""]
            if self.live:
                self.bar.write(f"[wiggly] {record['shot']} failed: {first[0]}", file=sys.stderr)
            else:
                log.info(f"{record['shot']} failed: {first[0]}")

    def _status(self, preparing: int) -> None:
        running = sum(k == "shot" for k, _ in self.in_flight.values())
        text = (f"done {self.counts['done']}, failed {self.counts['failed']}, "
                f"running {running}")
        if preparing:
            text += f", preparing {counted(preparing, 'body', 'bodies')}"
        self.bar.set_postfix_str(text, refresh=True)


def _output_files(folder: Path, outputs) -> list[str]:
    """The files a shot's ``outputs`` wrote into ``folder``: an OBJ sequence ``a.obj`` by its
    frame files ``a_0000.obj``, ... (no file ``a.obj`` exists)."""
    from wiggly.export.obj import existing_frames

    names = []
    for o in outputs:
        frames = existing_frames(folder / o) if o.lower().endswith(".obj") else {}
        names += [frames[k].name for k in sorted(frames)] or [o]
    return names


def _name(item) -> str:
    return item.name if isinstance(item, Shot) else f"body {item.key}"
