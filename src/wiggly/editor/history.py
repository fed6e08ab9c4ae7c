"""Undo and redo per browser tab, kept on disk so that they survive a restart.

Every logged edit becomes a :class:`Record`: what it changed in the *entities* of the scene.
Entities are the scene's tables (``mesh``, ``material``, ``damping``, ``simulation``, ``time``,
``output``), its groups by name and its keyframes by id, each in the scene file's dict form;
a record holds only the fields that changed (a whole entity only when it was added or
removed), so a step costs what it changed, not the size of a pose.  Undo puts the "before"
fields back into the *current* scene, so a tab undoes its own edits and keeps the others'
(two tabs changing different keyframes, or different fields of one, do not undo each other's
work).  When another tab changed one of those fields since, undoing would silently discard
that change: the undo is refused (HTTP 409, with what changed) and the step dropped.

The histories of all tabs are journaled beside the scene (``.NAME.history.jsonl``, one JSON
line per edit, undo or redo) with the keyframe ids and a hash of the resulting scene.  Each line
is flushed to the disk (``fsync``) before the edit is answered, so the journal is the durable
record of every acknowledged edit; the autosave (written in the background) may lag it.  When
the editor opens the scene again, it finds the newest line whose hash is the autosave's (else
the saved file's, else, for a scene never saved, the journal's first snapshot) and replays the
steps after it, checking each against its hash: the scene comes back as the last acknowledged
edit left it, with its keyframe ids and every tab's history.  A journal that no line of which
matches the scene (changed outside the editor) is dropped with a notice.  The journal is
rewritten compactly (one snapshot line, atomically) when it is opened, once the autosave
agrees with what it recovered (:mod:`wiggly.editor.recovery`).  The snapshot names the digest
of the scene file it was taken against: while the file is unchanged, the snapshot alone
recovers the scene (the autosave lost or unreadable).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from wiggly.editor.state import EditError, EditorState, rebuild_state
from wiggly.errors import WigglyInputError
from wiggly.files import sync_file
from wiggly.scene import Scene, scene_from_dict, scene_to_dict

__all__ = ["Histories", "Record", "edit_label", "history_path", "key_phrase", "scene_hash"]

SECTIONS = ("mesh", "material", "damping", "simulation", "time", "output", "drive")
MAX_RECORDS = 500  # per tab
MAX_TABS = 16
DEFAULT_TAB = "api"  # requests that do not name a tab (scripts, tests)
TAB_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")

Entity = tuple[str, Any]  # ("section", name) | ("group", name) | ("key", id)


def history_path(scene_path: Path) -> Path:
    """Where the undo histories of ``scene_path`` are journaled: a hidden file beside it."""
    return scene_path.with_name(f".{scene_path.stem}.history.jsonl")


def scene_hash(state: EditorState) -> str:
    """A hash of the scene (its dict form) and keyframe ids."""
    text = json.dumps([scene_to_dict(state.scene), list(state.keyframe_ids)], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def entities(state: EditorState) -> dict[Entity, Any]:
    d = scene_to_dict(state.scene)
    out: dict[Entity, Any] = {("section", s): d[s] for s in SECTIONS if s in d}
    out.update({("group", n): g for n, g in d["groups"].items()})
    out.update({("key", i): k for i, k in zip(state.keyframe_ids, d["keyframes"], strict=True)})
    return out


def key_phrase(key: Any) -> str:
    """A keyframe as an animator names it: ``'lift' (right at 0.5 s)`` or ``right at 0.5 s``."""
    if not isinstance(key, dict):
        return "a keyframe"
    where = f"{key.get('group')} at {key.get('time'):g} s" \
        if isinstance(key.get("time"), int | float) else str(key.get("group"))
    return f"{key['name']!r} ({where})" if key.get("name") else where


def _changed_since(entity: Entity, value: Any) -> str:
    """``"<what> was (were) changed since"``, for a step that cannot be undone."""
    kind, name = entity
    if kind == "key":
        return f"the keyframe {key_phrase(value)} was changed since"
    if kind == "group":
        return f"group {name!r} was changed since"
    return f"the {name} settings were changed since"


def edit_label(op: Any, before: EditorState, after: EditorState) -> str:
    """How the undo button names an edit (keyframes by their name or group and time)."""
    kind = op.get("op") if isinstance(op, dict) else None
    label = op.get("label") if isinstance(op, dict) else None
    if isinstance(label, str) and 0 < len(label) <= 80:
        return label
    if kind == "batch":
        return f"{len(op.get('ops') or [])} edits"
    if kind == "set":  # "set material.young", "set damping.alpha, damping.beta"
        section, values = op.get("section"), op.get("values")
        fields = sorted(values)[:3] if isinstance(values, dict) else []
        return "set " + (", ".join(f"{section}.{f}" for f in fields) or str(section))
    if kind in ("update_keyframe", "delete_keyframe"):
        key = _key_of(before, op.get("id"))
        if kind == "delete_keyframe":
            return f"delete keyframe {key_phrase(key)}"
        if set(op) <= {"op", "id", "time"} and isinstance(op.get("time"), int | float):
            return f"move keyframe {key_phrase(key)} to {op['time']:g} s"
        return f"edit keyframe {key_phrase(key)}"
    if kind == "add_keyframe":
        added = [i for i in after.keyframe_ids if i not in set(before.keyframe_ids)]
        return f"add keyframe {key_phrase(_key_of(after, added[-1] if added else None))}"
    return str(kind).replace("_", " ")


def _key_of(state: EditorState, key_id: Any) -> dict | None:
    """The keyframe ``key_id`` of ``state`` in its dict form (None: no such keyframe)."""
    if key_id not in state.keyframe_ids:
        return None
    k = state.scene.keyframes[state.keyframe_ids.index(key_id)]
    return {"name": k.name, "group": k.group, "time": k.time}


@dataclass(frozen=True)
class Record:
    """One undoable step: ``changes`` are (entity kind, name, before, after, partial), None
    for an entity that does not exist on that side.  A ``partial`` change (an entity that
    exists on both sides) holds only the fields that changed, None for a field absent on that
    side: dragging a key's time does not copy its pose."""

    label: str
    changes: tuple[tuple[str, Any, Any, Any, bool], ...]

    @classmethod
    def between(cls, before: EditorState, after: EditorState, label: str) -> Record | None:
        """The step from ``before`` to ``after`` (None if nothing changed)."""
        a, b = entities(before), entities(after)
        changes = tuple(_change(kind, name, a.get((kind, name)), b.get((kind, name)))
                        for kind, name in sorted({*a, *b}, key=repr)
                        if a.get((kind, name)) != b.get((kind, name)))
        return cls(label, changes) if changes else None

    def to_json(self) -> dict:
        return {"label": self.label,
                "changes": [[k, n, b, a, 1] if p else [k, n, b, a]
                            for k, n, b, a, p in self.changes]}

    @classmethod
    def from_json(cls, d: dict) -> Record:
        return cls(str(d["label"]), tuple((str(c[0]), c[1], c[2], c[3], bool(c[4:]))
                                          for c in d["changes"]))

    def applied(self, state: EditorState, undo: bool) -> EditorState:
        """``state`` with this step undone (or redone); :class:`EditError` (409) if what it
        changed (for a partial change: the fields it changed) was changed since."""
        now = entities(state)
        for kind, name, before, after, partial in self.changes:
            expect, has = (after if undo else before), now.get((kind, name))
            if not _matches(has, expect, partial):
                what = "that keyframe was deleted since" if kind == "key" and has is None \
                    and expect is not None else _changed_since(
                        (kind, name), {**(has or {}), **expect} if partial
                        else expect if expect is not None else before)
                raise EditError(f"cannot {'undo' if undo else 'redo'} {self.label!r}: "
                                f"{what} (in another tab or by an edit there); that step is "
                                "dropped", 409)
        for kind, name, before, after, partial in self.changes:
            value = before if undo else after
            if partial:
                value = {**now[(kind, name)], **value}
                value = {f: v for f, v in value.items() if v is not None}
            if value is None:
                now.pop((kind, name), None)
            else:
                now[(kind, name)] = value
        d: dict[str, Any] = {"format": state.scene.format}
        d.update({s: now[("section", s)] for s in SECTIONS if ("section", s) in now})
        d["groups"] = {n: v for (k, n), v in now.items() if k == "group"}
        keys = sorted((n, v) for (k, n), v in now.items() if k == "key")
        d["keyframes"] = [v for _, v in keys]
        ids = tuple(n for n, _ in keys)
        try:
            return rebuild_state(state, d, ids, max([state.next_id, *(i + 1 for i in ids)]))
        except EditError as err:  # e.g. a keyframe whose group another tab deleted since
            raise EditError(f"cannot {'undo' if undo else 'redo'} {self.label!r}: the scene "
                            f"would be invalid ({str(err).splitlines()[0]}); that step is "
                            "dropped", 409) from None


def _matches(has: Any, expect: Any, partial: bool) -> bool:
    """Whether an entity now ``has`` what a step expects (``partial``: in the fields it
    changed)."""
    if not partial:
        return has == expect
    return isinstance(has, dict) and all(has.get(f) == v for f, v in expect.items())


def _change(kind: str, name: Any, before: Any, after: Any) -> tuple[str, Any, Any, Any, bool]:
    """A change of one entity: whole (created, removed, not a table), else only the fields
    that differ (None: absent on that side)."""
    if not (isinstance(before, dict) and isinstance(after, dict)):
        return kind, name, before, after, False
    diff = [f for f in {*before, *after} if before.get(f) != after.get(f)]
    return (kind, name, {f: before.get(f) for f in diff}, {f: after.get(f) for f in diff},
            True)


@dataclass
class _Tab:
    undo: list[Record] = field(default_factory=list)
    redo: list[Record] = field(default_factory=list)
    full: bool = False  # told that its oldest steps are forgotten (once a session)


def _use(tabs: OrderedDict[str, _Tab], tab: str) -> _Tab:
    """``tab``'s stacks, now the most recently used (the least recently used beyond
    :data:`MAX_TABS` are forgotten).

    Not a :class:`wiggly.memo.Memo`: the stacks are the tabs' own state, which nothing can
    compute again, and forgetting a tab is part of the journal's meaning: a snapshot lists
    the tabs in this order and :func:`_replay` applies the same rule line by line, so that
    a restarted editor has the tabs it had."""
    t = tabs.pop(tab, None) or _Tab()
    tabs[tab] = t
    while len(tabs) > MAX_TABS:
        tabs.popitem(last=False)
    return t


class Histories:
    """Undo/redo stacks of every tab, and their journal (``path``; None: not kept)."""

    def __init__(self, path: Path | None = None):
        self.path = path
        self.tabs: OrderedDict[str, _Tab] = OrderedDict()
        self.write_error: str | None = None
        self.disk: str | None = None  # digest of the scene file as read or saved (a snapshot's)
        self._base: EditorState | None = None  # the snapshot a new journal starts with
        # taker -> (the tab it took a history from, the stacks' tops and sizes then)
        self._taken: dict[str, tuple[str, tuple]] = {}

    @staticmethod
    def tab_id(value: str | None) -> str:
        if value is None or value == "":
            return DEFAULT_TAB
        if not TAB_ID.fullmatch(value):
            raise EditError("the X-Wiggly-Tab header must be 1 to 64 letters, digits, '_' or '-'")
        return value

    def _tab(self, tab: str) -> _Tab:
        return _use(self.tabs, tab)

    def attend(self, tab: str, gone: Callable[[str], bool]) -> None:
        """A request of ``tab``: a browser tab without a history of its own takes over the
        newest history of a tab that is ``gone`` (no page of it open: closed, its browser
        crashed, or not back since the editor restarted), so that the edits it made can
        still be undone.  The take-over is journaled; if it cannot be, the history stays
        where it was."""
        own = self.tabs.get(tab)
        if tab == DEFAULT_TAB or (own is not None and (own.undo or own.redo)):
            return
        # back after another tab took its history (a reload slower than the grace period):
        # it takes it back while that tab has not used it
        taker = next((t for t, (source, mark) in self._taken.items()
                      if source == tab and self._mark(t) == mark), None)
        left = [taker] if taker is not None else self._left_by(gone, but=tab)
        if not left:
            return
        try:
            self._begin()
            self._journal({"op": "adopt", "tab": tab, "from": left[-1]}, None)
        except EditError:
            return
        _adopt(self.tabs, tab, left[-1])
        self._taken.pop(left[-1], None)
        if taker is None:
            self._taken[tab] = (left[-1], self._mark(tab))

    def _mark(self, tab: str) -> tuple:
        """What tells whether ``tab``'s stacks changed: their sizes and top records."""
        t = self.tabs.get(tab) or _Tab()
        return (len(t.undo), len(t.redo), t.undo[-1] if t.undo else None,
                t.redo[-1] if t.redo else None)

    def orphaned(self, gone: Callable[[str], bool]) -> bool:
        """Whether a tab that is ``gone`` left a history that another tab could take over."""
        return bool(self._left_by(gone))

    def _left_by(self, gone: Callable[[str], bool], but: str = DEFAULT_TAB) -> list[str]:
        """The tabs that are ``gone`` and left a history (not ``but``, nor the API's)."""
        return [t for t, h in self.tabs.items()
                if t not in (but, DEFAULT_TAB) and (h.undo or h.redo) and gone(t)]

    def describe(self, tab: str) -> dict:
        t = self.tabs.get(tab) or _Tab()
        return {"can_undo": bool(t.undo), "can_redo": bool(t.redo),
                "undo_label": t.undo[-1].label if t.undo else None,
                "redo_label": t.redo[-1].label if t.redo else None}

    # --- steps ----------------------------------------------------------------------------
    def record(self, tab: str, record: Record, state: EditorState) -> str | None:
        """Journal the step ``record`` of ``tab`` that gave ``state`` (on the disk before
        this returns), then push it on the tab's undo stack; :class:`EditError` (507) and
        nothing recorded if the journal cannot be written.  A notice the first time (this
        session) the tab's oldest step is forgotten, :data:`MAX_RECORDS` being reached."""
        self._begin()
        self._journal({"op": "edit", "tab": tab, "rec": record.to_json()}, state)
        t = self._tab(tab)
        t.undo.append(record)
        full = len(t.undo) > MAX_RECORDS
        del t.undo[:-MAX_RECORDS]
        t.redo.clear()
        if full and not t.full:
            t.full = True
            return (f"undo keeps the last {MAX_RECORDS} steps of each tab: from now on, each "
                    "edit forgets this tab's oldest step")
        return None

    def step(self, tab: str, state: EditorState, undo: bool) -> EditorState | None:
        """``state`` with the tab's last step undone (redone), journaled; None if there is
        none.  :class:`EditError`: another tab changed what it would change (409, the step is
        dropped) or the journal cannot be written (507, nothing changes)."""
        self._begin()
        t = self._tab(tab)
        source, target = (t.undo, t.redo) if undo else (t.redo, t.undo)
        if not source:
            return None
        try:
            new = source[-1].applied(state, undo)
        except EditError:
            source.pop()
            try:
                self._journal({"op": "drop", "tab": tab, "undo": undo}, None)
            except EditError:
                pass  # the step is gone from this session; a restart may offer it again
            raise
        self._journal({"op": "undo" if undo else "redo", "tab": tab}, new)
        target.append(source.pop())
        return new

    # --- the journal ----------------------------------------------------------------------
    @staticmethod
    def _line(line: dict, state: EditorState | None) -> str:
        if state is not None:
            line.update(ids=list(state.keyframe_ids), next=state.next_id, hash=scene_hash(state))
        return json.dumps(line, separators=(",", ":")) + "\n"

    def _begin(self) -> None:
        """Start a new journal with the snapshot of the scene as it was opened (before the
        first step is journaled: a scene never saved is recovered from it)."""
        if self._base is not None:
            self.compact(self._base, strict=True)

    def _journal(self, line: dict, state: EditorState | None) -> None:
        """Append ``line`` and flush it to the disk (before the edit is answered);
        :class:`EditError` (507) if it cannot be written."""
        if self.path is None:
            return
        data = self._line(line, state).encode()
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
            try:
                end = os.lseek(fd, 0, os.SEEK_END)
                try:
                    if os.write(fd, data) != len(data):  # a full disk: a short write
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    os.fsync(fd)
                except OSError:  # a refused edit leaves no line (nor part of one) behind
                    try:
                        os.ftruncate(fd, end)
                    except OSError:
                        pass
                    raise
            finally:
                os.close(fd)
            self.write_error = None
        except OSError as err:
            raise self._unwritable(err) from None

    def _unwritable(self, err: OSError) -> EditError:
        return EditError("not done: " + unwritable(
            err, f"the undo journal {self.path.name} cannot be written, so the change would "
            "not survive a crash", self.path.parent), write_status(err))

    def load(self, scene: Scene | None, source: Path | None = None, *,
             disk: str | None = None, compact: bool = True, name: str = "the scene",
             autosaved: bool = False) -> tuple[EditorState | None, str | None]:
        """Recover from the journal for ``scene`` (just opened: the autosave, else the saved
        file; None: neither exists): the state after the last journaled step, with its
        keyframe ids and every tab's history, and a notice if the journal was dropped.  The
        newest line whose hash is ``scene``'s is where the steps after it are replayed from;
        else (or for ``scene=None``) the journal's snapshot, made ``source``'s, if it was
        taken of the scene file as it is on disk now (``disk``: its digest) or there is no
        ``scene``.  The journal is then rewritten compactly (unless not ``compact``: the
        caller makes the autosave agree first, then calls :meth:`compact`).  None for the
        state: no scene and no journal to recover it.  The notice names the scene as
        ``name``; ``autosaved``: ``scene`` is its autosave (its unsaved edits, which stand)."""
        fresh = EditorState.of(scene) if scene is not None else None
        if self.path is None or not self.path.is_file():
            self._base = fresh
            return fresh, None
        try:
            lines = _read_lines(self.path)
            state, tabs = _replay(lines, scene, source, disk or "none")
        except (OSError, ValueError, KeyError, TypeError, IndexError, EditError,
                WigglyInputError) as err:
            self._discard(fresh)
            why = str(err).splitlines()[0] if str(err) else type(err).__name__
            return fresh, f"ignored the unreadable undo history of {name} ({why}): undo " \
                "starts afresh"
        if state is None:
            if fresh is None or not any("hash" in line for line in lines):
                self._discard(fresh)
                return fresh, None
            if autosaved:  # the unsaved scene stands; only its steps are lost
                self._discard(fresh, keep=True)
                return fresh, (f"the undo history kept for {name} does not match its "
                               "unsaved edits: they are recovered, but undo starts afresh")
            if source is not None and self.unsaved(scene, source, disk) is None:
                # nothing beyond the file's last save here: only the steps to it are old
                self._discard(fresh)
                return fresh, (f"{name} was changed outside the editor since it was last "
                               "saved here: it opens as it is on disk; undo starts afresh")
            kept = self._discard(fresh, keep=True)  # edits not saved (not set aside as a scene)
            where = f"; they are kept in {kept.name}" if kept is not None else ""
            return fresh, (f"{name} was changed outside the editor after edits that were not "
                           f"saved: it opens as it is on disk, without them{where}; undo "
                           "starts afresh")
        self.tabs = tabs
        if compact:
            self.compact(state)
        return state, None

    def peek(self, scene: Scene, source: Path | None) -> EditorState | None:
        """The scene after the journal's steps replayed over ``scene`` (made ``source``'s),
        changing nothing; None: no journal, or none of its lines is ``scene``."""
        if self.path is None or not self.path.is_file():
            return None
        try:
            state, _ = _replay(_read_lines(self.path), scene, None)
        except (OSError, ValueError, KeyError, TypeError, IndexError, EditError,
                WigglyInputError):
            return None
        if state is not None:
            state.scene.source = source
        return state

    def unsaved(self, scene: Scene | None, source: Path, disk: str | None, *,
                replayable: bool = True) -> EditorState | None:
        """The scene the journal's steps lead to when it is not the scene file ``scene``
        (its digest ``disk``; None: no file): replayed over the file where they can be,
        else from the journal's snapshot (made ``source``'s).  None: the journal holds no
        edits beyond the file, nor beyond the snapshot's own save; with ``replayable``
        false, also when its steps replay over the file (the file is unchanged since, and
        an ordinary recovery brings them back)."""
        if self.path is None or not self.path.is_file():
            return None
        try:
            lines = _read_lines(self.path)
            state = None
            if scene is not None:
                state, _ = _replay(lines, scene, source, disk or "none")
                if state is not None and not replayable:
                    return None
            if state is None:
                state, _ = _replay(lines, None, source)
                if state is not None and lines[0].get("file", "none") != "none" \
                        and scene_hash(state) == lines[0]["hash"]:
                    return None  # the snapshot's own save, as it was: nothing unsaved
        except (OSError, ValueError, KeyError, TypeError, IndexError, EditError,
                WigglyInputError):
            return None
        if state is None or (scene is not None and state.scene == scene):
            return None
        return state

    def compact(self, state: EditorState, strict: bool = False) -> None:
        """Rewrite the journal as one snapshot line (with the scene), atomically.  A failure
        is kept in :attr:`write_error` (``strict``: raised as :class:`EditError`, 507)."""
        if self.path is None:
            self._base = None
            return
        line = {"op": "snapshot", "file": self.disk or "none",
                "scene": scene_to_dict(state.scene), "tabs": {
            tab: {"undo": [r.to_json() for r in t.undo], "redo": [r.to_json() for r in t.redo]}
            for tab, t in self.tabs.items()}}
        tmp = self.path.with_name(self.path.name + ".part")
        try:
            try:
                with open(tmp, "w", encoding="utf-8") as f:
                    f.write(self._line(line, state))
                    f.flush()
                    os.fsync(f.fileno())
                tmp.replace(self.path)
            finally:
                tmp.unlink(missing_ok=True)  # a write cut short leaves no part behind
            sync_file(self.path.parent)
            self._base = None
        except OSError as err:
            if strict:
                raise self._unwritable(err) from None
            self.write_error = f"cannot keep the undo history in {self.path.name}: {err}"

    def _discard(self, base: EditorState | None, keep: bool = False) -> Path | None:
        """Start afresh from ``base``; the journal is deleted, or with ``keep`` renamed
        beside it with the time (what it held may be someone's work): that path, or None."""
        self._base = base
        if self.path is None:
            return None
        if keep:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            old = self.path.with_name(f"{self.path.stem}-{stamp}{self.path.suffix}")
            try:
                os.replace(self.path, old)
            except OSError:  # best effort: then it goes, as a journal that does not match
                self.path.unlink(missing_ok=True)
                return None
            return old
        self.path.unlink(missing_ok=True)
        return None


def _adopt(tabs: OrderedDict[str, _Tab], tab: str, gone: str) -> None:
    """``tab`` takes over the history of the tab ``gone`` (:meth:`Histories.attend`)."""
    if gone in tabs:
        tabs[tab] = tabs.pop(gone)
        tabs.move_to_end(tab)


def _read_lines(path: Path) -> list[dict]:
    """The journal's lines; a last line cut short by a crash (no newline: its edit was never
    answered) is left out."""
    text = path.read_text(encoding="utf-8")
    parts = text.split("\n")
    if parts[-1]:
        parts.pop()  # torn by a crash mid-write
    return [json.loads(p) for p in parts if p]


def _replay(lines: list[dict], scene: Scene | None, source: Path | None, disk: str = "none",
            ) -> tuple[EditorState | None, OrderedDict[str, _Tab]]:
    """Every tab's stacks after ``lines``, and the scene after them: replayed from the newest
    line whose state ``scene`` is, else from the snapshot if it was taken of the scene file
    whose digest is ``disk`` (the file unchanged since); None: neither."""
    start, state = -1, None
    if scene is not None:
        hashes: dict[tuple, str] = {}
        for i in range(len(lines) - 1, -1, -1):
            line = lines[i]
            if "hash" not in line or len(line["ids"]) != len(scene.keyframes):
                continue
            ids = tuple(int(k) for k in line["ids"])
            if ids not in hashes:
                hashes[ids] = scene_hash(EditorState(scene, ids, 0))
            if hashes[ids] == line["hash"]:
                start, state = i, EditorState(scene, ids, int(line["next"]))
                break
    if state is None and lines and lines[0]["op"] == "snapshot" and "scene" in lines[0] and (
            scene is None or lines[0].get("file") == disk):
        snap = scene_from_dict(lines[0]["scene"], where="the undo history's snapshot")
        snap.source = source
        start, state = 0, EditorState(snap, tuple(int(k) for k in lines[0]["ids"]),
                                      int(lines[0]["next"]))
        if scene_hash(state) != lines[0]["hash"]:
            raise ValueError("its snapshot does not match its hash")
    tabs: OrderedDict[str, _Tab] = OrderedDict()
    for i, line in enumerate(lines):
        op = line["op"]
        rec: Record | None = None
        if op == "snapshot":
            tabs = OrderedDict(
                (tab, _Tab([Record.from_json(r) for r in v["undo"]],
                           [Record.from_json(r) for r in v["redo"]]))
                for tab, v in line["tabs"].items())
        elif op == "edit":
            t = _use(tabs, line["tab"])
            rec = Record.from_json(line["rec"])
            t.undo.append(rec)
            del t.undo[:-MAX_RECORDS]
            t.redo.clear()
        elif op == "adopt":
            _adopt(tabs, line["tab"], line["from"])
        elif op in ("undo", "redo", "drop"):
            t = _use(tabs, line["tab"])
            src, dst = (t.undo, t.redo) if op == "undo" or (
                op == "drop" and line["undo"]) else (t.redo, t.undo)
            if src:
                rec = src.pop()
                if op != "drop":
                    dst.append(rec)
        if state is None or i <= start:
            continue
        if "hash" not in line:  # a step dropped: the scene is unchanged
            continue
        if rec is None or op == "drop":
            raise ValueError(f"line {i + 1} ({op}) cannot be replayed")
        try:
            new = rec.applied(state, undo=op == "undo")
        except EditError as err:
            raise ValueError(f"line {i + 1} ({op} {rec.label!r}) cannot be replayed: "
                             f"{str(err).splitlines()[0]}") from None
        new = EditorState(new.scene, tuple(int(k) for k in line["ids"]), int(line["next"]))
        if scene_hash(new) != line["hash"]:
            raise ValueError(f"replaying line {i + 1} ({op} {rec.label!r}) does not give "
                             "the scene it journaled")
        state = new
    return state, tabs


#: errors of a file system or folder that refuses writes
READ_ONLY = (errno.EROFS, errno.EACCES, errno.EPERM)


def unwritable(err: OSError, what: str, folder: Path) -> str:
    """A message for a file that cannot be written: the cause, and the way out that fits."""
    cause = err.strerror or str(err)
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{what} ({cause}): free some disk space, or Save as a scene elsewhere"
    if err.errno in READ_ONLY:
        return (f"{what} ({cause}): the folder {folder} cannot be written to; Save as a "
                "scene in a folder you can write (inside the editor's --root)")
    return f"{what} ({cause}); Save as a scene elsewhere"


def write_status(err: OSError) -> int:
    """The HTTP status of a write that failed: 403 for a folder that cannot be written, 507
    (insufficient storage) otherwise."""
    return 403 if err.errno in READ_ONLY else 507
