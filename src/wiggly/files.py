"""Files: atomic outputs (complete or not at all, never half-written) and the disk cache."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def fix_mode(path: str | os.PathLike[str]) -> None:
    """Give a ``mkstemp`` file (mode 0600) the mode a plain ``open`` would have given it."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextmanager
def atomic_file(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` (same extension); move it to ``path`` when the
    block succeeds (:func:`os.replace`, atomic on one file system), delete it when it raises."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        fix_mode(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def default_cache_dir() -> Path:
    """``$WIGGLY_CACHE_DIR``, else ``$XDG_CACHE_HOME/wiggly``, else ``~/.cache/wiggly``."""
    if os.environ.get("WIGGLY_CACHE_DIR"):
        return Path(os.environ["WIGGLY_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "wiggly"
