"""Messages between the editor and its child processes (:mod:`wiggly.editor.physics`,
:mod:`wiggly.editor.refine`): one framing for both.

A message is a pickled Python object preceded by its length (8 bytes, little endian), on a
pipe: the child's stdin (parent to child) and its stdout (child to parent).  Both ends read
and write the pipes' raw file descriptors, never Python's buffered streams, so that
:func:`ready` (``select``) sees every message that has arrived: a buffered stream may hold a
message that ``select`` does not report.

* :func:`send` writes a whole message, or raises :class:`BrokenPipeError` (or another
  :class:`OSError`) when the other end is gone;
* :func:`receive` returns the next message, or None at the end of the stream: the other end
  closed it, between messages or in the middle of one (a torn message: the writer died or
  was killed while writing).  A complete message that does not unpickle raises
  :class:`pickle.UnpicklingError`; the stream stays in step.
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import sys
from typing import Any

__all__ = ["HEADER", "child_ends", "ready", "receive", "send"]

#: Bytes of a message's length, before the message.
HEADER = 8
_CHUNK = 1 << 24  # bytes per read: a large message (a tet mesh, playback frames) in pieces


def send(fd: int, obj: Any) -> None:
    """Write ``obj`` as one message on the file descriptor ``fd`` (all of it: a pipe may take
    a large message in several writes)."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    for part in (len(data).to_bytes(HEADER, "little"), data):
        view = memoryview(part)
        while view:
            view = view[os.write(fd, view):]


def _read_exact(fd: int, n: int) -> bytes | None:
    """``n`` bytes from ``fd``, or None if the stream ends first."""
    chunks, got = [], 0
    while got < n:
        chunk = os.read(fd, min(n - got, _CHUNK))
        if not chunk:
            return None
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)


def receive(fd: int) -> Any:
    """The next message on the file descriptor ``fd`` (blocking), or None at the end of the
    stream, also when it ends in the middle of a message."""
    head = _read_exact(fd, HEADER)
    if head is None:
        return None
    data = _read_exact(fd, int.from_bytes(head, "little"))
    return None if data is None else pickle.loads(data)


def ready(fd: int, timeout: float = 0.0) -> bool:
    """Whether a message (or the end of the stream) can be read from ``fd`` within
    ``timeout`` seconds."""
    return bool(select.select([fd], [], [], timeout)[0])


def child_ends() -> tuple[int, int]:  # pragma: no cover - runs in the child processes
    """In a child process: the file descriptors it reads and writes messages on.

    The protocol owns the child's stdout, so the pipe moves to a descriptor of its own and
    whatever else writes to stdout (``print``, and native code such as fTetWild, which
    writes to descriptor 1) goes to stderr.  Ctrl+C is the parent's: it closes the child's
    stdin, which ends the child's loop.
    """
    out = os.dup(sys.stdout.fileno())
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    sys.stdout = sys.stderr
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return sys.stdin.fileno(), out
