"""Files: atomic outputs (complete or not at all, never half-written) and the disk cache."""

from __future__ import annotations

import os
import re
import signal
import stat
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: Temporary outputs are named ``.STEM.wiggly-PID.XXXXXXXX.EXT`` (PID: the writing process);
#: those of a process that no longer runs and older than this (s) are removed by the next
#: output written to the same folder (a killed export's leftovers).
LEFTOVER_AGE = 3600.0
_TEMPORARY = re.compile(r"\.(?P<stem>.+)\.wiggly-(?P<pid>\d+)\.(?P<old>old-)?[a-z0-9_]{8}"
                        r"(?P<suffix>\.[^.]*)?")


def _temporary(path: Path, old: bool = False) -> Path:
    """A new empty temporary file next to ``path`` (see :data:`LEFTOVER_AGE`)."""
    kind = "old-" if old else ""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.wiggly-{os.getpid()}."
                               f"{kind}", suffix="" if old else path.suffix)
    os.close(fd)
    return Path(tmp)


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, OverflowError):
        return True  # someone else's process, or cannot tell: keep its files
    return True


def remove_leftovers(folder: str | os.PathLike[str], age: float = LEFTOVER_AGE) -> list[Path]:
    """Remove the temporary outputs in ``folder`` that a killed process left (its process no
    longer runs and the file is older than ``age`` seconds); the removed paths.  A user's
    earlier output moved aside during a commit (``old-``) is kept: it may be the only copy."""
    removed = []
    now = time.time()
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = _TEMPORARY.fullmatch(entry.name)
        if m is None or m["old"] or _running(int(m["pid"])):
            continue
        try:
            if entry.is_file(follow_symlinks=False) and \
                    now - entry.stat(follow_symlinks=False).st_mtime > age:
                os.unlink(entry.path)
                removed.append(Path(entry.path))
        except OSError:
            continue
    return removed


def remove_stale(path: str | os.PathLike[str], age: float) -> bool:
    """Remove ``path`` if it is a file last written more than ``age`` seconds ago (a write
    cut short by a crash); whether it was removed."""
    try:
        if time.time() - os.stat(path).st_mtime > age:
            os.unlink(path)
            return True
    except OSError:  # gone already, or not ours to remove: left as it is
        return False
    return False


def fix_mode(path: str | os.PathLike[str], like: str | os.PathLike[str] | None = None) -> None:
    """Give a ``mkstemp`` file (mode 0600) the mode of the file ``like`` it replaces, or
    where there is none the mode a plain ``open`` would have given it."""
    mode = None
    if like is not None:
        try:
            mode = stat.S_IMODE(os.stat(like).st_mode)
        except OSError:  # no file to replace (or not ours to read): a new one
            mode = None
    if mode is None:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    os.chmod(path, mode)


@contextmanager
def atomic_file(path: str | os.PathLike[str], replace: bool = True,
                durable: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same extension); move it to ``path`` when the
    block succeeds (:func:`os.replace`, atomic on one file system), delete it when it raises.

    ``replace=False`` publishes only if ``path`` does not exist yet (a hard link, atomic:
    of processes racing to write the same cache entry, the first wins) and raises
    :class:`FileExistsError` otherwise.  ``durable``: the file's bytes are flushed to the disk
    before the rename and the folder's entry after it (a user's scene file: an operating
    system crash or a power cut then leaves the old file or the new one, never an empty
    one)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary(path)
    try:
        yield tmp
        fix_mode(tmp, path if replace else None)  # a replaced file keeps its permissions
        if durable:
            sync_file(tmp)
        if replace:
            os.replace(tmp, path)
            if durable:
                sync_file(path.parent)
        else:
            try:
                os.link(tmp, path)
            except FileExistsError:
                raise
            except OSError:  # no hard links here: fall back to a check, then a rename
                if path.exists():
                    raise FileExistsError(str(path)) from None
                os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def sync_file(path: str | os.PathLike[str]) -> None:
    """Flush a file's bytes, or a folder's entries, to the disk (``fsync``); where a file
    system cannot (some network or virtual ones), nothing more is done."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def shown_name(path: str | os.PathLike[str]) -> str:
    """The file name to show users for ``path``: the name a temporary file of
    :func:`atomic_file` stands for (``.shot.wiggly-42.k3x9_a2b.png`` is ``shot.png``), else
    its own."""
    name = Path(path).name
    m = _TEMPORARY.fullmatch(name)
    return m["stem"] + (m["suffix"] or "") if m else name


def default_cache_dir() -> Path:
    """``$WIGGLY_CACHE_DIR``, else ``$XDG_CACHE_HOME/wiggly``, else ``~/.cache/wiggly``."""
    if os.environ.get("WIGGLY_CACHE_DIR"):
        return Path(os.environ["WIGGLY_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "wiggly"


def check_writable(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be written, or None.  The nearest existing ancestor must be a
    directory (not a file) in which a file can be created: tested by creating and removing a
    temporary file there, since permissions alone do not tell (root, read-only mounts,
    immutable folders)."""
    path = Path(path)
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"{parent} is a file, so {path} cannot be created inside it"
    try:
        fd, probe = tempfile.mkstemp(dir=parent, prefix=".wiggly-probe-")
    except OSError as err:
        return f"cannot create files in {parent} ({err.strerror or err})"
    os.close(fd)
    os.unlink(probe)
    return None


class OutputSet:
    """Several output files written all or nothing.

    :meth:`stage` gives a temporary path next to each output (same extension); once every
    output is written, :meth:`commit` moves them all into place.  An existing file is first
    moved aside and restored if a later move fails, so on any failure no output is replaced
    and no temporary file is left; directories created for the outputs are removed again if
    they stay empty.  Use as a context manager: commit on success, roll back on an exception.
    """

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path]] = []
        self._remove: list[Path] = []
        self._created: list[Path] = []
        self._swept: set[Path] = set()

    def stage(self, path: str | os.PathLike[str]) -> Path:
        """A new temporary file next to ``path`` that :meth:`commit` moves to ``path``."""
        path = Path(path)
        missing = []
        parent = path.parent
        while not parent.exists():
            missing.append(parent)
            parent = parent.parent
        path.parent.mkdir(parents=True, exist_ok=True)
        self._created += missing
        if path.parent not in self._swept:  # a killed export's leftovers, once per folder
            self._swept.add(path.parent)
            remove_leftovers(path.parent)
        tmp = _temporary(path)
        self._staged.append((tmp, path))
        return tmp

    def remove_on_commit(self, path: str | os.PathLike[str]) -> None:
        """Delete ``path`` when the outputs are committed (stale frames of a sequence)."""
        self._remove.append(Path(path))

    def commit(self) -> None:
        """Move every staged file into place, all or none."""
        moved: list[tuple[Path, Path | None]] = []  # (output, its old file moved aside)
        try:
            for tmp, path in self._staged:
                fix_mode(tmp, path)  # a replaced file keeps its permissions
                aside = None
                if path.exists() or path.is_symlink():
                    aside = _temporary(path, old=True)
                    os.replace(path, aside)
                moved.append((path, aside))
                os.replace(tmp, path)
        except BaseException:
            for path, aside in reversed(moved):
                if aside is not None:
                    os.replace(aside, path)
                else:
                    path.unlink(missing_ok=True)
            self.abort()
            raise
        for _, aside in moved:
            if aside is not None:
                aside.unlink(missing_ok=True)
        for path in self._remove:
            path.unlink(missing_ok=True)
        self._staged.clear()
        from wiggly.progress import say

        for folder in self._created:  # the outermost one of each new chain of folders
            if folder.parent not in self._created:
                say(f"created the folder {os.path.relpath(folder)} for the outputs")
        self._created.clear()

    def abort(self) -> None:
        """Delete every staged file and the directories created for them (when empty)."""
        for tmp, _ in self._staged:
            tmp.unlink(missing_ok=True)
        self._staged.clear()
        for directory in self._created:  # deepest first
            try:
                directory.rmdir()
            except OSError:
                pass

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.commit()
        else:
            self.abort()


@contextmanager
def terminate_as_exit() -> Iterator[None]:
    """In the main thread, a SIGTERM (``kill PID``, ``timeout``, a process manager) raises
    SystemExit(143) instead of ending the process at once, so that temporary outputs are
    removed and child processes (fTetWild's) killed as on Ctrl+C.  A handler the program set
    itself is left alone."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        yield
        return

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
