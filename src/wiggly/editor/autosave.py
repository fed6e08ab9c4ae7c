"""Autosave: every edited scene is written beside its file (``.NAME.autosave.toml``) by a
writer thread, right after the edit but not on its way: the browser's answer and the solve
do not wait for the TOML (about 20 ms on a scene of ten keyframes).  Writes of one file are
coalesced (the newest state wins) and run in order with deletions (an undo back to the saved
scene removes the autosave, which must not come back).  Each write is atomic (a temporary file
flushed to the disk, then renamed): a crash leaves the previous autosave or the new one, never
a torn file.  The autosave may lag the undo journal (:mod:`wiggly.editor.history`), which is
written before an edit is answered; the journal's tail is replayed over it on recovery.

Its first line names the scene file it edits as a digest of that file's bytes when the editor
read or last saved it (:func:`autosave_base`): a file changed since by another program makes
the autosave stale, and recovery then opens the file as it is on disk."""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

from wiggly.errors import WigglyInputError
from wiggly.files import sync_file
from wiggly.scene import Scene, scene_to_toml

_log = logging.getLogger("wiggly.editor")

__all__ = ["Autosaver", "autosave_base", "autosave_path", "write_autosave", "write_durably"]

_BASE = "# wiggly autosave of the scene file with sha256 "


def autosave_path(scene_path: Path) -> Path:
    """Where edits of ``scene_path`` are autosaved: a hidden file beside it."""
    return scene_path.with_name(f".{scene_path.stem}.autosave.toml")


def autosave_base(path: Path) -> str | None:
    """The digest of the scene file an autosave was made from ("none": a scene never saved),
    from its first line; None for an autosave without one (an older wiggly's)."""
    try:
        with open(path, encoding="utf-8") as f:
            first = f.readline().strip()
    except (OSError, UnicodeDecodeError):
        return None
    return first[len(_BASE):] if first.startswith(_BASE) else None


def write_durably(target: Path, text: str) -> None:
    """Replace ``target`` with ``text`` atomically, flushed to the disk before the rename."""
    tmp = target.with_name(target.name + ".part")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)  # a write cut short (a full disk) leaves no part behind
    sync_file(target.parent)


def write_autosave(target: Path, scene: Scene, base: str | None) -> None:
    """Write the autosave ``target`` of ``scene`` (edited from the scene file whose bytes
    have the digest ``base``; None: no file yet), atomically."""
    write_durably(target, f"{_BASE}{base or 'none'}\n" + scene_to_toml(scene))


class Autosaver:
    """Writes (``scene``) or removes (``None``) autosave files on one background thread;
    ``on_error(message)`` is told when a write fails."""

    def __init__(self, on_error: Callable[[str], None]):
        self._on_error = on_error
        self._said: str | None = None  # the last failure said on the terminal
        self._cv = threading.Condition()
        self._pending: dict[Path, tuple[Scene, str | None] | None] = {}
        self._busy = False
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="wiggly-autosave", daemon=True)
        self._thread.start()

    def put(self, target: Path, scene: Scene | None, base: str | None = None) -> None:
        """Autosave ``scene`` to ``target`` (None: remove the autosave), edited from the
        scene file whose bytes have the digest ``base`` (None: no file yet)."""
        with self._cv:
            self._pending[target] = None if scene is None else (scene, base)
            self._cv.notify_all()

    def flush(self) -> None:
        """Wait until every pending write is done."""
        with self._cv:
            self._cv.wait_for(lambda: not self._pending and not self._busy)

    def close(self) -> None:
        """Write what is pending, then stop."""
        self.flush()
        with self._cv:
            self._closed = True
            self._cv.notify_all()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._pending or self._closed)
                if not self._pending:
                    return
                target, item = self._pending.popitem()
                self._busy = True
            try:
                if item is None:
                    target.unlink(missing_ok=True)
                else:
                    write_autosave(target, *item)
            except (OSError, WigglyInputError) as err:
                message = f"autosave failed: {err}"
                if message != self._said:  # the terminal too (no page may be open), once
                    self._said = message
                    _log.warning("%s (the undo journal keeps the answered edits)", message)
                self._on_error(message)
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()
