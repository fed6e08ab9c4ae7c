"""Python child processes for calls that hold the interpreter lock for seconds to minutes
(fTetWild's meshing, the modes' sparse factorization): no thread of the calling process runs
meanwhile, so a live progress line would freeze and Ctrl+C or ``kill PID`` would wait.  In a
child the parent stays free: it reads the child's output line by line, and ends the child
however the parent's own call ends (Ctrl+C, SIGTERM, an exception).

The child is ``python -P -c CODE ARGS``: ``-P`` leaves the working folder off its import path,
so that a user's ``random.py`` there cannot shadow a library module.
"""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from wiggly.files import terminate_as_exit

__all__ = ["PythonChild", "can_run_child", "python_child"]

#: Seconds the main thread waits at a time for a child's line or exit, so that a signal
#: that landed on another thread is acted on within it.
_STEP = 0.1


def can_run_child() -> bool:
    """Whether ``sys.executable`` is a Python that can start a child (not, e.g., a Blender
    binary that embeds the interpreter)."""
    name = Path(sys.executable or "").name.lower()
    return name.startswith("python") or name.startswith("pypy")


class PythonChild:
    """A running child (:func:`python_child`): its output lines, its exit code, and the end
    of its standard error once it has ended."""

    def __init__(self, process: subprocess.Popen, errors: list[bytes]) -> None:
        self.process, self._errors = process, errors

    def lines(self) -> Iterator[str]:
        """The child's standard output, line by line as it writes them (without newlines).
        A thread reads the pipe and this waits for its lines in short steps: a signal to
        this process may land on any of its threads (the reader, a progress line, a BLAS
        worker), and the main thread blocked in the pipe's read would not see Ctrl+C until
        the child's next line (18 s once, mid-factorization)."""
        lines: queue.Queue[bytes | None] = queue.Queue()

        def pump() -> None:
            try:
                for raw in self.process.stdout:
                    lines.put(raw)
            finally:
                lines.put(None)

        threading.Thread(target=pump, name="wiggly-child-lines", daemon=True).start()
        while True:
            try:
                raw = lines.get(timeout=_STEP)
            except queue.Empty:
                continue
            if raw is None:
                return
            yield raw.decode("utf-8", "replace").rstrip("\n")

    def wait(self) -> int:
        """The child's exit code, waited for in short steps (as :meth:`lines`)."""
        while True:
            try:
                return self.process.wait(timeout=_STEP)
            except subprocess.TimeoutExpired:
                continue

    def error_tail(self, n: int = 5) -> str:
        """The last ``n`` lines of the child's standard error, joined by " / " (after the
        :func:`python_child` block)."""
        text = b"".join(self._errors).decode("utf-8", "replace").strip()
        return " / ".join(text.splitlines()[-n:])


@contextmanager
def python_child(code: str, args: list[str], cwd: str | os.PathLike[str]
                 ) -> Iterator[PythonChild]:
    """Run ``python -P -c code *args`` in ``cwd``, its standard error drained meanwhile; on
    leaving the block (normally, by an exception, Ctrl+C, or SIGTERM, which raises
    ``SystemExit`` here: :func:`wiggly.files.terminate_as_exit`) a child still running is
    killed."""
    process = subprocess.Popen(
        [sys.executable, "-P", "-c", code, *args], cwd=cwd, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    errors: list[bytes] = []
    drain = threading.Thread(target=lambda: errors.append(process.stderr.read()), daemon=True)
    drain.start()
    with terminate_as_exit():
        try:
            yield PythonChild(process, errors)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
            process.stdout.close()
            drain.join()
            process.stderr.close()
