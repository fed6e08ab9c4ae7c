"""What runs in a worker process: preparing a body, and running a shot on a prepared body.

A worker keeps the bodies it has used (with their factorizations) and the spacetime problems
it has solved, so a worker prepares nothing twice and a shot can start from the previous
solution of the same problem (a warm start).  They are keyed by value: the body's content key
(:attr:`Shot.body_key`) *and* the identity of the prepared body it was loaded from (a pickle
file as it is now, a Ray object), since fTetWild is not reproducible and two preparations of
one key (in two cache directories, say) are two different tet meshes; then damping, gravity
and time range for a problem.  Every exception of a task is caught and returned as a failure: one
bad shot never stops the others.
"""

from __future__ import annotations

import errno
import os
import pickle
import shutil
import socket
import tempfile
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from wiggly.errors import WigglyInputError, warn
from wiggly.files import atomic_file
from wiggly.memo import Memo

#: Bodies and problems a worker keeps (least recently used leave first).
KEEP_BODIES = 2
KEEP_PROBLEMS = 4
THUMBNAIL = "thumb.png"
THUMBNAIL_SIZE = (240, 180)

_BODIES = Memo(KEEP_BODIES)
_PROBLEMS = Memo(KEEP_PROBLEMS)


@dataclass(frozen=True)
class BodyJob:
    """Prepare the body of ``scene`` (a :func:`~wiggly.batch.shots.body_scene`).

    ``target``: write the pickled body there (the cache directory; local workers) or, when
    None, return it (Ray puts it in the object store).  ``mesh``: the mesh file's bytes for
    a worker that may not see the file (Ray), else None."""

    key: str
    scene: Any
    target: str | None = None
    mesh: bytes | None = None


@dataclass(frozen=True)
class ShotJob:
    """Run one shot and write its files into ``staging``.

    ``marker`` and ``token``: a worker that finds ``token`` in the file ``marker`` sees the
    batch's folder and writes into ``staging``; any other returns the files' bytes
    (``record["files"]``) for the driver to write."""

    name: str
    scene: Any
    body_key: str
    outputs: tuple[str, ...]
    staging: str
    marker: str
    token: str
    thumbnail: bool = True
    thumbnail_time: float | None = None
    warm_start: bool = True


#: How often (s) a local worker checks that the batch's process still runs.
DRIVER_CHECK = 1.0


def init_process(render_checked: bool = False, cache_dir: str | None = None,
                 driver: int | None = None) -> None:
    """Set up a worker process: one thread for BLAS, OpenMP and numba (there is a process per
    core), also for libraries loaded before (Ray's workers); skip the offscreen-rendering
    probe when the driver has run it; use the caller's cache directory ``cache_dir`` (local
    workers: they are forked from a server process started earlier, whose environment may be
    older than the caller's; the bodies they pickle there must use that directory's tets);
    exit when the process ``driver`` (local workers: the batch's) has ended, so that a batch
    killed outright (SIGKILL, an out-of-memory kill) leaves no worker behind, still solving
    and holding its memory (the pool's fork server lives as long as its workers do)."""
    if cache_dir is not None:
        os.environ["WIGGLY_CACHE_DIR"] = cache_dir
    if driver is not None:
        _exit_with(driver)
    # load the BLAS and OpenMP libraries of a solve now, to limit them all
    import scipy.linalg
    import scipy.sparse.linalg
    from threadpoolctl import threadpool_limits

    import wiggly.solve

    del scipy, wiggly

    threadpool_limits(1)
    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):  # pragma: no cover - numba missing or threads fixed
        pass
    if render_checked:
        os.environ["WIGGLY_RENDER_PROBE"] = "0"


def _exit_with(pid: int) -> None:
    """Exit this process once process ``pid`` has ended, checking every
    :data:`DRIVER_CHECK` seconds on a daemon thread."""
    import threading

    def watch() -> None:
        while _runs(pid):
            time.sleep(DRIVER_CHECK)
        os._exit(1)

    threading.Thread(target=watch, name="wiggly-driver-watch", daemon=True).start()


def _runs(pid: int) -> bool:
    """Whether process ``pid`` runs (not ended, nor a zombie not yet reaped, where /proc
    tells)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # pragma: no cover - another user's process of that number
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):  # no /proc (macOS): the signal found it
        return True


def _failure(err: BaseException) -> dict:
    from wiggly.render import RenderingError

    if isinstance(err, WigglyInputError | RenderingError):
        return {"status": "failed", "error": str(err), "traceback": None}
    if isinstance(err, OSError):  # the machine's, not wiggly's: a full disk, a lost mount
        full = " (the disk is full)" if err.errno == errno.ENOSPC else ""
        return {"status": "failed", "error": f"a file could not be read or written{full}: "
                f"{err}", "traceback": None}
    return {"status": "failed", "error": f"internal error (a bug): {type(err).__name__}: {err}",
            "traceback": traceback.format_exc()}


# ----------------------------------------------------------------------------------------------
# bodies


def _build(job: BodyJob) -> tuple[Any, dict]:
    """Build the body of ``job`` (tet mesh and modes come from the disk cache when there)."""
    from wiggly.scene import build

    scene, tmp = job.scene, None
    mesh_file = None if scene.mesh.path.startswith("builtin:") else scene.mesh_file()
    if job.mesh is not None and mesh_file is not None and not _same_file(mesh_file, job.mesh):
        tmp = tempfile.mkdtemp(prefix="wiggly-mesh-")
        (Path(tmp) / mesh_file.name).write_bytes(job.mesh)
        scene = replace(scene, mesh=replace(scene.mesh, path=mesh_file.name),
                        source=Path(tmp) / "scene.toml")
    t = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            body, _ = build(scene)
    except WigglyInputError as err:
        if tmp is not None:  # name the user's file, not the copy
            raise WigglyInputError(str(err).replace(str(Path(tmp) / "scene.toml"),
                                                    job.scene.where())
                                   .replace(tmp, str(mesh_file.parent))) from None
        raise
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    info = {"status": "done", "prepare_seconds": time.perf_counter() - t,
            "tets": int(body.tets.n_tets), "vertices": int(body.surface.n_vertices),
            "modes": int(body.r), "warnings": sorted({str(w.message) for w in caught}),
            "worker": _worker()}
    return body, info


def _same_file(path: Path, content: bytes) -> bool:
    try:
        return path.stat().st_size == len(content) and path.read_bytes() == content
    except OSError:
        return False


def prepare_body(job: BodyJob) -> dict:
    """Build the body and pickle it to ``job.target`` (atomically); return what it took."""
    try:
        body, info = _build(job)
        with atomic_file(job.target) as tmp, open(tmp, "wb") as f:
            pickle.dump(body, f, protocol=pickle.HIGHEST_PROTOCOL)
        return info
    except Exception as err:  # reported with the shots of this body
        return _failure(err)


def prepare_body_object(job: BodyJob) -> tuple[dict, Any]:
    """Build the body and return it with what it took (Ray stores it in its object store)."""
    try:
        body, info = _build(job)
        return info, body
    except Exception as err:
        return _failure(err), None


def pickled_identity(path: str) -> str:
    """A value naming the body pickled at ``path`` as it is now: the file's absolute path,
    inode, size and modification time (a body pickled anew there is another body)."""
    try:
        st = os.stat(path)
    except OSError:
        return f"{os.path.abspath(path)}:missing"
    return f"{os.path.abspath(path)}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}"


def load_pickled(path: str) -> Callable[[], Any]:
    """A loader of a body pickled by :func:`prepare_body`."""

    def load():
        with open(path, "rb") as f:
            return pickle.load(f)

    return load


def _body(key: tuple[str, str], load: Callable[[], Any], warped: bool) -> tuple[Any, float]:
    """The worker's body for ``key`` (content key, prepared body's identity) with its
    factorizations, and the seconds spent on it."""
    t = time.perf_counter()
    body = _BODIES.get(key, load)
    _PROBLEMS.drop(lambda k: k[0] not in _BODIES)  # the problems of a body let go
    # the warp's factorizations (Schulz et al. 2014, Theorem 2), shared by every shot of this body
    if warped:
        _ = body.fine_level, body.coarse_level
    return body, time.perf_counter() - t


# ----------------------------------------------------------------------------------------------
# shots


def run_shot(job: ShotJob, load: Callable[[], Any], identity: str) -> dict:
    """Solve one shot on the body that ``load`` returns (once per worker and ``identity``:
    the prepared body's name, :func:`pickled_identity` or a Ray object id) and write its
    files; return its record (a failure's message instead when anything goes wrong)."""
    t0, cpu0 = time.perf_counter(), time.process_time()
    record: dict[str, Any] = {"worker": _worker()}
    direct = _sees(job.marker, job.token)
    folder = Path(job.staging) if direct else Path(tempfile.mkdtemp(prefix="wiggly-shot-"))
    try:
        record.update(_solve_and_write(job, load, identity, folder))
        record["status"] = "done"
        if not direct:
            record["files"] = {p.name: p.read_bytes() for p in folder.iterdir()}
    except Exception as err:
        record.update(_failure(err))
        if direct:
            shutil.rmtree(folder, ignore_errors=True)
    finally:
        if not direct:
            shutil.rmtree(folder, ignore_errors=True)
    record["shot_seconds"] = time.perf_counter() - t0
    record["cpu_seconds"] = time.process_time() - cpu0  # this process's, whatever the load
    return record


def _sees(marker: str, token: str) -> bool:
    try:
        return Path(marker).read_text(encoding="utf-8").strip() == token
    except OSError:
        return False


def _solve_and_write(job: ShotJob, load, identity: str, folder: Path) -> dict:
    from wiggly.body import Damping
    from wiggly.scene import keyframes_of, problem_of, resolve_groups, write_outputs
    from wiggly.scene.drive import secondary_of
    from wiggly.scene.run import check_motion

    scene = job.scene
    warped = scene.simulation.warp
    bkey = (job.body_key, identity)
    base, setup = _body(bkey, load, warped)
    damping = Damping(scene.damping.alpha, scene.damping.beta)
    start, end = scene.time_range()
    pkey = (bkey, scene.damping.alpha, scene.damping.beta, scene.simulation.gravity,
            start, end, scene.simulation.preroll, scene.time.loop)
    # damping and gravity change only the per-mode coefficients (Schulz et al. 2014, eq. (4));
    # an entry is [the problem, its last warm start]
    entry = _PROBLEMS.get(pkey, lambda: [problem_of(scene, base.with_dynamics(
        damping=damping, gravity=scene.simulation.gravity)), None])
    problem = entry[0]
    body = problem.body
    groups = resolve_groups(scene, body.model)
    keyframes = keyframes_of(scene, body, groups)
    secondary = scene.secondary_motion
    paths = [folder / name for name in job.outputs]
    t = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if secondary:  # the driver owns its groups, physics the rest (one linear solve)
            anim = secondary_of(scene, body, groups, keyframes)
        else:
            anim = problem.solve(keyframes, warped=warped,
                                 warm_start=entry[1] if job.warm_start else None)
        solve_seconds = time.perf_counter() - t
        highlights = check_motion(scene, body, anim, groups, paths)  # as wiggly animate does
    if warped and not secondary:
        entry[1] = anim.warm_start
    info = anim.info
    rows = anim.constraint_residuals()
    record: dict[str, Any] = {
        "setup_seconds": setup, "solve_seconds": solve_seconds,
        "iterations": int(info.get("iterations", 0)),
        "converged": bool(info.get("converged", True)),
        "distance_bound": info.get("distance_bound"),
        "warm_start": bool(info.get("warm_start", False)),
        "keyframe_position_rms": _worst(rows, "position_rms"),
        "keyframe_position_max": _worst(rows, "position_max"),
        "keyframe_velocity_rms": _worst(rows, "velocity_rms"),
        "keyframes": rows,
    }
    if scene.drive is not None:  # how closely the driven groups followed the driver
        record["drive"] = anim.info["drive"]
        if record["drive"]:
            record["drive_max"] = record["drive"]["max"]
            record["drive_rms"] = record["drive"]["rms"]
    with warnings.catch_warnings(record=True) as written:
        warnings.simplefilter("always")
        t = time.perf_counter()
        folder.mkdir(parents=True, exist_ok=True)
        write_outputs(scene, anim, paths, overwrite=True, highlights=highlights)
        record["output_seconds"] = time.perf_counter() - t
        t = time.perf_counter()
        if job.thumbnail:
            record["thumbnail_time"] = _thumbnail(folder / THUMBNAIL, scene, anim,
                                                  job.thumbnail_time)
        record["thumbnail_seconds"] = time.perf_counter() - t
    record["warnings"] = list(dict.fromkeys(str(w.message) for w in [*caught, *written]))
    return record


def _worst(rows: list[dict], key: str) -> float | None:
    values = [r[key] for r in rows if key in r]
    return max(values) if values else None


def _thumbnail(path: Path, scene, anim, at: float | None) -> float:
    """A still of the shot (:data:`THUMBNAIL_SIZE`): at ``at`` seconds, else the frame
    farthest from the rest pose (its mean translation removed), where shots differ most."""
    from PIL import Image

    from wiggly.render import render_frame

    times = anim.frame_times(scene.time.fps)
    X = anim.positions(times, dtype=np.float32)
    if at is None:
        rest = anim.body.surface.vertices
        d = X - rest - (X.mean(axis=1, keepdims=True) - rest.mean(axis=0))
        at = float(times[int(np.argmax(np.sqrt((d ** 2).sum(axis=2).mean(axis=1))))])
    elif not times[0] - 1e-9 <= at <= times[-1] + 1e-9:
        shown = float(times[0] if at < times[0] else times[-1])
        warn(f"the thumbnail time {at:g} s (--thumbnail-time) lies outside the shot's "
             f"frames [{times[0]:g}, {times[-1]:g}] s: its thumbnail shows the frame at "
             f"{shown:g} s")
    at = min(max(at, float(times[0])), float(times[-1]))
    camera = scene.output.camera if isinstance(scene.output.camera, str) else \
        tuple(scene.output.camera)
    image = render_frame(times, X, anim.body.surface.faces, at=at, size=THUMBNAIL_SIZE,
                         camera=camera)
    with atomic_file(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG", optimize=True)
    return at


def _worker() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"
