"""What a scene's unsaved edits changed, said in the scene's terms ("moved keyframe 'plant'
to 1.2 s", "set damping.alpha = 0.3"), for the notices of a recovery or a reload."""

from __future__ import annotations

from typing import Any

from wiggly.editor.history import SECTIONS, key_phrase
from wiggly.scene import Scene, scene_to_dict

__all__ = ["describe_changes"]

SHOWN = 5  # the changes named; the rest are counted


def describe_changes(before: Scene, after: Scene) -> list[str]:
    """What changed from ``before`` to ``after``, one phrase per change (the first
    :data:`SHOWN`, then how many more)."""
    a, b = scene_to_dict(before), scene_to_dict(after)
    out: list[str] = []
    for section in SECTIONS:
        old, new = a.get(section) or {}, b.get(section) or {}
        for f in sorted(f for f in {*old, *new} if old.get(f) != new.get(f)):
            out.append(f"set {section}.{f}{_value(new.get(f))}")
    for name in sorted({*a["groups"], *b["groups"]}):
        old, new = a["groups"].get(name), b["groups"].get(name)
        if old != new:
            verb = "added" if old is None else "deleted" if new is None else "changed"
            out.append(f"{verb} group {name!r}")
    out += _keyframes(a["keyframes"], b["keyframes"])
    if len(out) > SHOWN:
        out[SHOWN:] = [f"{len(out) - SHOWN} more"]
    return out


def _value(v: Any) -> str:
    if isinstance(v, bool) or not isinstance(v, int | float | str):
        return ""
    return f" = {v:g}" if isinstance(v, int | float) else f" = {v!r}"


def _keyframes(old: list[dict], new: list[dict]) -> list[str]:
    """Keyframes deleted, added or changed: the same keyframe is found by its name, else
    by its group (in order)."""
    old, new = list(old), list(new)
    for k in list(old):  # unchanged
        if k in new:
            old.remove(k)
            new.remove(k)
    pairs = []
    for same in (lambda k, n: k.get("name") and k.get("name") == n.get("name"),
                 lambda k, n: not k.get("name") and not n.get("name")
                 and k.get("group") == n.get("group")):
        for k in list(old):
            match = next((n for n in new if same(k, n)), None)
            if match is not None:
                pairs.append((k, match))
                old.remove(k)
                new.remove(match)
    out = []
    for k, n in pairs:
        fields = sorted(f for f in {*k, *n} if k.get(f) != n.get(f))
        if fields == ["time"]:
            out.append(f"moved keyframe {key_phrase(k)} to {n['time']:g} s")
        else:
            out.append(f"changed the {', '.join(fields)} of keyframe {key_phrase(k)}")
    out += [f"deleted keyframe {key_phrase(k)}" for k in old]
    out += [f"added keyframe {key_phrase(n)}" for n in new]
    return out
