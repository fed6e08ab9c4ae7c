"""The undo journal stays proportional to what the edits changed: a step stores the fields it
changed, not whole keyframes, and reopening the scene rewrites the journal as one snapshot of
the live undo history."""

from __future__ import annotations

import numpy as np

from tests.editor_ui import bar_project
from wiggly.editor import Sandbox, Session
from wiggly.editor.session import history_path

BODY = """
[groups.body]
box = { min = [0.1, -1, -1], max = [0.9, 1, 1] }
[[keyframes]]
name = "plant"
time = 0.25
group = "body"
position = { offset = [0.0, 0.01, 0.0] }
"""


def _posed(tmp_path):
    """A session on a bar whose key "plant" (id 1) holds an absolute pose; the pose's size
    in the journal's form (bytes)."""
    path = bar_project(tmp_path, BODY, warp=False)
    s = Session(Sandbox([tmp_path]))
    s.open(path.name)
    n = len(s.groups()["body"])
    pose = np.random.default_rng(1).uniform(-0.5, 0.5, (n, 3)).tolist()
    s.edit({"op": "update_keyframe", "id": 1, "position": {"absolute": pose}}, tab="a")
    return s, path, len(str(pose))


def test_dragging_a_posed_key_journals_only_its_time(tmp_path):
    """Forty time drags of a key with an absolute pose add far less than one copy of the
    pose each; after a restart the journal is about the pose and the steps, and undo walks
    the drags back, then the pose."""
    s, path, pose_bytes = _posed(tmp_path)
    journal = history_path(path)
    try:
        assert pose_bytes > 4000
        start = journal.stat().st_size
        for i in range(40):
            s.edit({"op": "update_keyframe", "id": 1, "time": round(0.3 + 0.01 * i, 2)},
                   tab="a")
        per_drag = (journal.stat().st_size - start) / 40
        assert per_drag < 600, per_drag
    finally:
        s.close()
    s = Session(Sandbox([tmp_path]))
    try:
        s.open(path.name)
        assert s.scene.keyframes[1].time == 0.69
        assert journal.stat().st_size < 3 * pose_bytes + 40 * 300, journal.stat().st_size
        for _ in range(40):
            assert s.undo("a")["changed"]
        assert s.scene.keyframes[1].time == 0.25
        assert s.undo("a")["changed"] and s.scene.keyframes[1].position.offset == (0, 0.01, 0)
    finally:
        s.close()


def test_two_tabs_changing_different_fields_of_a_key_keep_each_others_work(tmp_path):
    """Tab a drags the key's time, tab b then sets its stiffness: a's undo puts the time
    back and keeps b's stiffness."""
    s, _, _ = _posed(tmp_path)
    try:
        s.edit({"op": "update_keyframe", "id": 1, "time": 0.4}, tab="a")
        s.edit({"op": "update_keyframe", "id": 1, "stiffness": 0.5}, tab="b")
        assert s.undo("a")["changed"]
        key = s.scene.keyframes[1]
        assert (key.time, key.stiffness) == (0.25, 0.5)
    finally:
        s.close()


def test_undo_says_once_when_its_depth_is_reached(tmp_path):
    """The 501st edit of a tab says that undo keeps the last 500 steps; later edits do not
    say it again, and undo then walks back 500 steps."""
    path = bar_project(tmp_path, warp=False)
    s = Session(Sandbox([tmp_path]))
    try:
        s.open(path.name)
        said = [s.edit({"op": "set", "section": "damping",
                        "values": {"alpha": 0.001 * (i + 1)}}, tab="a").get("notice")
                for i in range(502)]
        assert said[:500] == [None] * 500 and said[501] is None
        assert said[500] and "last 500 steps" in said[500], said[500]
        steps = 0
        while s.undo("a")["changed"]:
            steps += 1
        assert steps == 500 and s.scene.damping.alpha == 0.002
    finally:
        s.close()
