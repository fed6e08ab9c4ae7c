"""Where shots run: local worker processes (the default) or a Ray cluster.

Both take the same jobs (:class:`~wiggly.batch.worker.BodyJob`,
:class:`~wiggly.batch.worker.ShotJob`) and share prepared bodies their own way: the pool
through pickles in the cache directory, Ray through its object store.  Neither schedules
anything itself: the pool is :class:`concurrent.futures.ProcessPoolExecutor`, the cluster is
Ray's; the driver only keeps as many tasks in flight as there are cores.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import logging
import multiprocessing
import os
import sys
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from wiggly.batch import worker
from wiggly.errors import WigglyInputError
from wiggly.files import atomic_file, check_writable, default_cache_dir

RAY_EXTRA = 'Ray is not installed; install it with pip install "wiggly[ray]" (or pip install ray)'


class WorkerDied(Exception):
    """The process running a task died (a crash in native code, or killed: out of memory)."""


def cpu_count() -> int:
    """Cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def run_shot_from_file(job: worker.ShotJob, body_file: str) -> dict:
    """A pool task: a shot on the body pickled at ``body_file`` (prepared again, and pickled
    anew, if that pickle cannot be loaded: written by another version of wiggly)."""
    from wiggly.batch.shots import body_scene

    def load():
        try:
            return worker.load_pickled(body_file)()
        except Exception:
            again = worker.BodyJob(job.body_key, body_scene(job.scene), target=body_file)
            info = worker.prepare_body(again)
            if info["status"] != "done":
                raise WigglyInputError(info["error"]) from None
            return worker.load_pickled(body_file)()

    return worker.run_shot(job, load, worker.pickled_identity(body_file))


#: Environment of worker processes: one thread each (the pool has a process per core;
#: threads of BLAS, OpenMP and numba fighting over the cores make solves several times slower).
ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                     "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
                                     "NUMBA_NUM_THREADS")}


def forkserver_context():
    """The ``forkserver`` context, its server started with :data:`ONE_THREAD` in its
    environment (workers are forked from it, so libraries load single-threaded)."""
    from multiprocessing import forkserver

    saved = {k: os.environ.get(k) for k in ONE_THREAD}
    os.environ.update(ONE_THREAD)
    try:
        forkserver.ensure_running()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return multiprocessing.get_context("forkserver")


class LocalPool:
    """Worker processes on this machine, one per core, forked from a server process (no state
    inherited from the caller; one thread each); prepared bodies are pickled under
    ``<cache>/batch/bodies/``."""

    kind = "local"

    def __init__(self, workers: int, render_checked: bool) -> None:
        self.slots = workers
        cache = default_cache_dir()
        self.bodies = cache / "batch" / "bodies"
        why = check_writable(self.bodies / "probe")
        if why is not None:
            raise WigglyInputError(
                f"wiggly batch keeps the bodies it prepares in its cache directory, and "
                f"{self.bodies} cannot be written ({why}); set WIGGLY_CACHE_DIR to a folder "
                "that can")
        self._args = (render_checked, str(cache), os.getpid())  # workers end with the batch
        self._start()

    def _start(self) -> None:
        """A new pool whose workers are known to start: each first imports the calling
        script (Python's forkserver), and a script that starts a batch at import kills it."""
        self._pool = cf.ProcessPoolExecutor(self.slots, mp_context=forkserver_context(),
                                            initializer=worker.init_process,
                                            initargs=self._args)
        try:
            self._pool.submit(os.getpid).result()
        except BrokenProcessPool as err:
            # wait for the dead workers, so that their last words on stderr come before the
            # caller's error and not after it
            self._pool.shutdown(wait=True, cancel_futures=True)
            raise WigglyInputError(_unstartable(err)) from None

    def describe(self) -> str:
        return f"{self.slots} local worker process{'es' if self.slots != 1 else ''}"

    def cached_body(self, key: str) -> Any | None:
        """The source of a body prepared by an earlier batch, or None."""
        path = self.bodies / f"{key}.pickle"
        return str(path) if path.is_file() else None

    def keep_warnings(self, key: str, messages: list[str]) -> None:
        """Keep what preparing the body warned about beside it, to say it again when a later
        batch finds the body prepared."""
        with atomic_file(self.bodies / f"{key}.warnings.json") as tmp:
            tmp.write_text(json.dumps(list(messages)), encoding="utf-8")

    def kept_warnings(self, key: str) -> list[str]:
        try:
            data = json.loads((self.bodies / f"{key}.warnings.json").read_text("utf-8"))
        except (OSError, ValueError):
            return []
        return [str(m) for m in data] if isinstance(data, list) else []

    def prepare(self, job: worker.BodyJob) -> cf.Future:
        return self._pool.submit(worker.prepare_body, job)

    def body_job(self, key: str, scene, mesh_file: Path | None) -> worker.BodyJob:
        return worker.BodyJob(key, scene, target=str(self.bodies / f"{key}.pickle"))

    def prepared(self, job: worker.BodyJob, handle: Any, result: Any) -> tuple[dict, Any]:
        """(what preparing took, the body's source for shots)."""
        return result, job.target

    def shot(self, job: worker.ShotJob, source: Any) -> cf.Future:
        return self._pool.submit(run_shot_from_file, job, source)

    def wait(self, handles, timeout: float) -> list:
        done, _ = cf.wait(list(handles), timeout=timeout, return_when=cf.FIRST_COMPLETED)
        return list(done)

    def outcome(self, handle: cf.Future) -> Any:
        try:
            return handle.result()
        except BrokenProcessPool as err:
            raise WorkerDied(str(err)) from None

    def restart(self) -> None:
        """A new pool after a worker died (the old one refuses work)."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._start()

    def close(self, cancel: bool = False) -> None:
        self._pool.shutdown(wait=not cancel, cancel_futures=cancel)


def _unstartable(err: BaseException) -> str:
    """Why the worker processes could not start, with the likely cause for a script."""
    main = getattr(sys.modules.get("__main__"), "__file__", None)
    message = f"the batch's worker processes could not start ({err})"
    if main and "wiggly" not in Path(main).parts[-3:-1] and Path(main).name != "wiggly":
        message += (f". Each worker first imports the script that started the batch, {main}; "
                    "if it calls wiggly.batch.run at import, put the call under "
                    '`if __name__ == "__main__":`')
    return message


class RayCluster:
    """Tasks on a Ray cluster: a new local one (``address`` None: all cores of this machine,
    unless ``RAY_ADDRESS`` names a cluster), one at ``address`` ("auto", "host:6379",
    "ray://host:10001"), or the one this process is already connected to.  Prepared bodies
    stay in Ray's object store; each worker process fetches a body once."""

    kind = "ray"

    def __init__(self, address: str | None, render_checked: bool) -> None:
        try:
            import ray
        except ImportError:
            raise WigglyInputError(RAY_EXTRA) from None
        self.ray = ray
        self.started = False
        if not ray.is_initialized():
            try:
                ray.init(address=address, include_dashboard=False, log_to_driver=False,
                         logging_level=logging.WARNING)
            except (ConnectionError, ValueError, RuntimeError) as err:
                where = f"--ray-address {address}" if address else "--ray"
                # Ray's own text speaks of its --address flag and RAY_ADDRESS: say ours
                hint = ("; start one on this machine with `ray start --head`, give its address "
                        "(--ray-address host:6379), or use --ray alone for a cluster of this "
                        "machine's cores" if address else "")
                first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                raise WigglyInputError(f"{where}: cannot start or reach a Ray cluster "
                                       f"({first}){hint}") from None
            self.started = True
        self.slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
        options = {"num_cpus": 1, "max_retries": 1}
        self._prepare = ray.remote(num_returns=2, **options)(_prepare_on_ray)
        self._shot = ray.remote(**options)(_shot_on_ray)
        self._render_checked = render_checked
        self._bodies: dict = {}

    def describe(self) -> str:
        return f"a Ray cluster of {self.slots} CPU{'s' if self.slots != 1 else ''}"

    def cached_body(self, key: str) -> Any | None:
        return None

    def keep_warnings(self, key: str, messages: list[str]) -> None:
        """Bodies live in the object store, for one batch: nothing to keep."""

    def kept_warnings(self, key: str) -> list[str]:
        return []

    def body_job(self, key: str, scene, mesh_file: Path | None) -> worker.BodyJob:
        return worker.BodyJob(key, scene, mesh=None if mesh_file is None else
                              mesh_file.read_bytes())

    def prepare(self, job: worker.BodyJob) -> Any:
        info, body = self._prepare.remote(job)
        self._bodies[info] = body
        return info

    def prepared(self, job: worker.BodyJob, handle: Any, result: Any) -> tuple[dict, Any]:
        """(what preparing took, the body's reference in the object store)."""
        return result, self._bodies.pop(handle)

    def shot(self, job: worker.ShotJob, source: Any) -> Any:
        # the reference inside a list, so that Ray does not fetch the body for every task
        return self._shot.remote(job, [source], self._render_checked)

    def wait(self, handles, timeout: float) -> list:
        refs = list(handles)
        ready, rest = self.ray.wait(refs, num_returns=1, timeout=timeout)
        if ready and rest:
            more, _ = self.ray.wait(rest, num_returns=len(rest), timeout=0)
            ready += more
        return ready

    def outcome(self, handle) -> Any:
        try:
            return self.ray.get(handle)
        except self.ray.exceptions.RayError as err:
            raise WorkerDied(f"{type(err).__name__}: {str(err).splitlines()[0]}") from None

    def restart(self) -> None:
        """Ray restarts its workers itself."""

    def close(self, cancel: bool = False) -> None:
        if self.started:
            self.ray.shutdown()


def _prepare_on_ray(job: worker.BodyJob) -> tuple[dict, Any]:
    worker.init_process()
    return worker.prepare_body_object(job)


def _shot_on_ray(job: worker.ShotJob, body: list, render_checked: bool) -> dict:
    import ray

    worker.init_process(render_checked)
    return worker.run_shot(job, lambda: ray.get(body[0]), f"ray:{body[0].hex()}")
