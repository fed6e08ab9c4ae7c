"""One editor per scene file: a lock beside it (``.NAME.editor.lock``).

Two editors on one scene would each rewrite its autosave and undo journal, and each would
silently drop the other's edits.  So an editor holds an exclusive lock on the file
``.NAME.editor.lock`` beside the scene while the scene is open, and writes its process id,
host and address into it; a second editor (another ``wiggly edit``, or Open in another
editor's page) is refused with a message naming the first.  The lock is the operating
system's (``flock``), so it is taken atomically and ends with its process, even one killed
with SIGKILL: the file such a process leaves behind locks nothing, and the next editor takes
it over.  A clean stop removes the file.  Where no lock can be taken (a folder that cannot be
written, a system without ``flock``) the scene opens unlocked: edits there are refused anyway
or the check is not available.
"""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

from wiggly.editor.state import EditError

__all__ = ["SceneLock", "held_by", "lock_path"]


def lock_path(scene_path: Path) -> Path:
    """The lock of ``scene_path``: a hidden file beside it."""
    return scene_path.with_name(f".{scene_path.stem}.editor.lock")


def _holder(fd: int) -> dict:
    """What the holder of the lock wrote into it (empty if unreadable)."""
    try:
        data = os.pread(fd, 4096, 0)
        out = json.loads(data.decode("utf-8")) if data else {}
        return out if isinstance(out, dict) else {}
    except (OSError, ValueError):
        return {}


def _describe(holder: dict) -> str:
    """``another wiggly edit (pid 12, http://127.0.0.1:8765/)``, from what it wrote."""
    parts = []
    if isinstance(holder.get("pid"), int):
        host = holder.get("host")
        parts.append(f"pid {holder['pid']}" + (
            f" on {host}" if isinstance(host, str) and host != socket.gethostname() else ""))
    if isinstance(holder.get("url"), str):
        parts.append(holder["url"])
    return "another wiggly edit" + (f" ({', '.join(parts)})" if parts else "")


def held_by(scene_path: Path) -> str | None:
    """Which other editor holds the lock of ``scene_path`` (None: none does)."""
    if fcntl is None:
        return None
    try:
        fd = os.open(lock_path(scene_path), os.O_RDONLY)
    except OSError:
        return None  # no lock file: nobody holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    except OSError:
        return _describe(_holder(fd))
    finally:
        os.close(fd)


class SceneLock:
    """The lock of one scene file, held by this process until :meth:`release`."""

    def __init__(self, scene_path: Path, fd: int):
        self.scene_path = scene_path
        self.path = lock_path(scene_path)
        self._fd: int | None = fd
        self.url: str | None = None
        self._write()

    @classmethod
    def take(cls, scene_path: Path) -> SceneLock | None:
        """Lock ``scene_path``: the lock; None if no lock can be kept there.  Held by
        another editor: :class:`EditError` (409) naming it."""
        if fcntl is None:
            return None
        path = lock_path(scene_path)
        for _ in range(16):  # the holder may remove the file between our open and lock
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
            except OSError:
                try:
                    fd = os.open(path, os.O_RDONLY)
                except OSError:
                    return None  # a folder that cannot be written: nothing to protect
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                who = _describe(_holder(fd))
                os.close(fd)
                raise EditError(f"{scene_path.name} is already open in {who}: edit it there, "
                                "or stop that editor (Ctrl+C in its terminal) and open it "
                                "again", 409) from None
            try:
                st, now = os.fstat(fd), os.stat(path)
                same = (st.st_dev, st.st_ino) == (now.st_dev, now.st_ino)
            except OSError:
                same = False
            if same:
                return cls(scene_path, fd)
            os.close(fd)
        return None

    def serving(self, url: str) -> None:
        """Name the editor's address in the lock (a refused editor tells it)."""
        self.url = url
        self._write()

    def _write(self) -> None:
        if self._fd is None:
            return
        info = {"pid": os.getpid(), "host": socket.gethostname(), "url": self.url}
        data = json.dumps(info).encode()
        try:
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, data, 0)
        except OSError:
            pass  # a read-only lock file: it locks all the same, unnamed

    def release(self) -> None:
        """Remove the lock file and unlock (removed first: nobody locks a file that goes)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None
