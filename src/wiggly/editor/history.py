"""Undo and redo per browser tab, kept on disk so that they survive a restart.

Every logged edit becomes a :class:`Record`: what it changed, as the *entities* of the scene
before and after it.  Entities are the scene's tables (``mesh``, ``material``, ``damping``,
``simulation``, ``time``, ``output``), its groups by name and its keyframes by id, each in the
scene file's dict form.  Undo puts the "before" entities back into the *current* scene, so a
tab undoes its own edits and keeps the others' (two tabs working on different keyframes do not
undo each other's work).  When another tab changed an entity since, undoing would silently
discard that change: the undo is refused (HTTP 409, with what changed) and the step dropped.

The histories of all tabs are journaled beside the scene (``.NAME.history.jsonl``, one JSON
line per edit, undo or redo) with the keyframe ids and a hash of the resulting scene.  When the
editor opens the scene again and the hash matches (the autosave or the saved file is the state
the journal ends in), the ids and every tab's history come back; otherwise the journal is
dropped with a notice.  The journal is rewritten compactly when it is opened.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from wiggly.editor.state import EditError, EditorState, rebuild_state
from wiggly.scene import scene_to_dict

__all__ = ["Histories", "Record", "history_path", "scene_hash"]

SECTIONS = ("mesh", "material", "damping", "simulation", "time", "output")
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
    out: dict[Entity, Any] = {("section", s): d[s] for s in SECTIONS}
    out.update({("group", n): g for n, g in d["groups"].items()})
    out.update({("key", i): k for i, k in zip(state.keyframe_ids, d["keyframes"], strict=True)})
    return out


def _show(entity: Entity, value: Any) -> str:
    kind, name = entity
    if kind == "key":
        return f"keyframe {name}" + (f" ({value['group']} at {value['time']:g} s)"
                                     if isinstance(value, dict) else "")
    return f"group {name!r}" if kind == "group" else f"the {name} settings"


@dataclass(frozen=True)
class Record:
    """One undoable step: ``changes`` are (entity kind, name, before, after), None for an
    entity that does not exist on that side."""

    label: str
    changes: tuple[tuple[str, Any, Any, Any], ...]

    @classmethod
    def between(cls, before: EditorState, after: EditorState, label: str) -> Record | None:
        """The step from ``before`` to ``after`` (None if nothing changed)."""
        a, b = entities(before), entities(after)
        changes = tuple((kind, name, a.get((kind, name)), b.get((kind, name)))
                        for kind, name in sorted({*a, *b}, key=repr)
                        if a.get((kind, name)) != b.get((kind, name)))
        return cls(label, changes) if changes else None

    def to_json(self) -> dict:
        return {"label": self.label, "changes": [list(c) for c in self.changes]}

    @classmethod
    def from_json(cls, d: dict) -> Record:
        return cls(str(d["label"]), tuple((str(k), n, b, a) for k, n, b, a in d["changes"]))

    def applied(self, state: EditorState, undo: bool) -> EditorState:
        """``state`` with this step undone (or redone); :class:`EditError` (409) if an
        entity it changed was changed since."""
        now = entities(state)
        for kind, name, before, after in self.changes:
            expect = after if undo else before
            if now.get((kind, name)) != expect:
                what = _show((kind, name), expect if expect is not None else before)
                raise EditError(f"cannot {'undo' if undo else 'redo'} {self.label!r}: "
                                f"{what} was changed since (in another tab or by an edit "
                                "there); that step is dropped", 409)
        for kind, name, before, after in self.changes:
            value = before if undo else after
            if value is None:
                now.pop((kind, name), None)
            else:
                now[(kind, name)] = value
        d: dict[str, Any] = {"format": state.scene.format}
        d.update({s: now[("section", s)] for s in SECTIONS})
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


@dataclass
class _Tab:
    undo: list[Record] = field(default_factory=list)
    redo: list[Record] = field(default_factory=list)


class Histories:
    """Undo/redo stacks of every tab, and their journal (``path``; None: not kept)."""

    def __init__(self, path: Path | None = None):
        self.path = path
        self.tabs: OrderedDict[str, _Tab] = OrderedDict()
        self.write_error: str | None = None

    @staticmethod
    def tab_id(value: str | None) -> str:
        if value is None or value == "":
            return DEFAULT_TAB
        if not TAB_ID.fullmatch(value):
            raise EditError("the X-Wiggly-Tab header must be 1 to 64 letters, digits, '_' or '-'")
        return value

    def _tab(self, tab: str) -> _Tab:
        t = self.tabs.pop(tab, None) or _Tab()
        self.tabs[tab] = t  # most recently used last
        while len(self.tabs) > MAX_TABS:
            self.tabs.popitem(last=False)
        return t

    def describe(self, tab: str) -> dict:
        t = self.tabs.get(tab) or _Tab()
        return {"can_undo": bool(t.undo), "can_redo": bool(t.redo),
                "undo_label": t.undo[-1].label if t.undo else None,
                "redo_label": t.redo[-1].label if t.redo else None}

    # --- steps ----------------------------------------------------------------------------
    def record(self, tab: str, record: Record, state: EditorState) -> None:
        t = self._tab(tab)
        t.undo.append(record)
        del t.undo[:-MAX_RECORDS]
        t.redo.clear()
        self._journal({"op": "edit", "tab": tab, "rec": record.to_json()}, state)

    def step(self, tab: str, state: EditorState, undo: bool) -> EditorState | None:
        """``state`` with the tab's last step undone (redone); None if there is none."""
        t = self._tab(tab)
        source, target = (t.undo, t.redo) if undo else (t.redo, t.undo)
        if not source:
            return None
        try:
            new = source[-1].applied(state, undo)
        except EditError:
            source.pop()
            self._journal({"op": "drop", "tab": tab, "undo": undo}, None)
            raise
        target.append(source.pop())
        self._journal({"op": "undo" if undo else "redo", "tab": tab}, new)
        return new

    def changed(self, state: EditorState) -> None:
        """The scene changed without a step (saved under another name, rebased paths)."""
        self._journal({"op": "state"}, state)

    # --- the journal ----------------------------------------------------------------------
    @staticmethod
    def _line(line: dict, state: EditorState | None) -> str:
        if state is not None:
            line.update(ids=list(state.keyframe_ids), next=state.next_id, hash=scene_hash(state))
        return json.dumps(line, separators=(",", ":")) + "\n"

    def _journal(self, line: dict, state: EditorState | None) -> None:
        if self.path is None:
            return
        try:
            with open(self.path, "a", encoding="utf-8") as f:
                f.write(self._line(line, state))
            self.write_error = None
        except OSError as err:
            self.write_error = f"cannot keep the undo history in {self.path.name}: {err}"

    def load(self, state: EditorState) -> tuple[EditorState, str | None]:
        """Read the journal for ``state`` (just opened): the state with its journaled keyframe
        ids and every tab's history if the journal ends in this scene, and a notice if a
        journal was dropped.  The journal is then rewritten compactly."""
        if self.path is None or not self.path.is_file():
            return state, None
        tabs: OrderedDict[str, _Tab] = OrderedDict()
        end: dict | None = None
        try:
            with open(self.path, encoding="utf-8") as f:
                for text in f:
                    line = json.loads(text)
                    op = line["op"]
                    if op == "snapshot":
                        tabs = OrderedDict(
                            (tab, _Tab([Record.from_json(r) for r in v["undo"]],
                                       [Record.from_json(r) for r in v["redo"]]))
                            for tab, v in line["tabs"].items())
                    elif op == "edit":
                        t = tabs.setdefault(line["tab"], _Tab())
                        t.undo.append(Record.from_json(line["rec"]))
                        del t.undo[:-MAX_RECORDS]
                        t.redo.clear()
                    elif op in ("undo", "redo", "drop"):
                        t = tabs.setdefault(line["tab"], _Tab())
                        src, dst = (t.undo, t.redo) if op == "undo" or (
                            op == "drop" and line["undo"]) else (t.redo, t.undo)
                        if src:
                            rec = src.pop()
                            if op != "drop":
                                dst.append(rec)
                    if "hash" in line:
                        end = line
        except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
            self._discard()
            return state, f"ignored an unreadable undo history {self.path.name}: {err}"
        if end is None:
            self._discard()
            return state, None
        ids = tuple(int(i) for i in end["ids"])
        candidate = EditorState(state.scene, ids, int(end["next"])) \
            if len(ids) == len(state.scene.keyframes) else None
        if candidate is None or scene_hash(candidate) != end["hash"]:
            self._discard()
            return state, (f"the undo history {self.path.name} does not match the scene (it "
                           "was changed outside the editor); undo starts afresh")
        self.tabs = OrderedDict(list(tabs.items())[-MAX_TABS:])
        self.compact(candidate)
        return candidate, None

    def compact(self, state: EditorState) -> None:
        """Rewrite the journal as one snapshot line."""
        if self.path is None:
            return
        line = {"op": "snapshot", "tabs": {
            tab: {"undo": [r.to_json() for r in t.undo], "redo": [r.to_json() for r in t.redo]}
            for tab, t in self.tabs.items()}}
        tmp = self.path.with_name(self.path.name + ".part")
        try:
            tmp.write_text(self._line(line, state), encoding="utf-8")
            tmp.replace(self.path)
        except OSError as err:
            self.write_error = f"cannot keep the undo history in {self.path.name}: {err}"

    def _discard(self) -> None:
        if self.path is not None:
            self.path.unlink(missing_ok=True)
