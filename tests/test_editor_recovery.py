"""Recovery is idempotent: the scene and undo history an open recovers after a crash come
back the same after any number of later restarts, clean or killed.

A kill is reproduced by the files it leaves: the editor is closed (its background writes
done), then the autosave is put back as it was before the last edits, as when the editor is
killed after their journal lines are on the disk but before their autosave lands.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tests.editor_ui import bar_project
from wiggly import files
from wiggly.editor import Sandbox, Session, presence
from wiggly.editor.session import autosave_path
from wiggly.scene import load_scene, save_scene

KEYS = """
[[keyframes]]
name = "plant"
time = 0.25
group = "mid"
position = { offset = [0.0, 0.01, 0.0] }
"""

YOUNG = {"op": "set", "section": "material", "values": {"young": 8e5}}


def _open(folder: Path, name: str) -> tuple[Session, list[str]]:
    session = Session(Sandbox([folder]))
    return session, session.open(name)["notices"]


def _killed(session: Session, autosave: Path, lagging: bytes | None) -> None:
    """Stop ``session`` as a kill before its last autosave would: the autosave is left as
    ``lagging`` (None: none was written)."""
    session.close()
    if lagging is None:
        autosave.unlink(missing_ok=True)
    else:
        autosave.write_bytes(lagging)


def _view(session: Session) -> tuple:
    return session.scene, session.state.keyframe_ids, session.histories.describe("a")


def _killed_after_two_edits(folder: Path, second: dict, first: dict | None = None
                            ) -> tuple[Path, Path, tuple]:
    """A scene with edit ``first`` (default: damping alpha 0.3) autosaved and edit ``second``
    only journaled, killed before its autosave: (the scene's path, its autosave, the view it
    had)."""
    path = bar_project(folder, KEYS, warp=False)
    auto = autosave_path(path)
    s, _ = _open(folder, path.name)
    s.edit(first or {"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    s.autosaver.flush()
    lagging = auto.read_bytes()
    s.edit(second, tab="a")
    expected = _view(s)
    _killed(s, auto, lagging)
    return path, auto, expected


def test_a_recovered_edit_survives_every_later_restart(tmp_path):
    """Edit A, then B (delete the key "plant"), killed before B's autosave: the restart
    recovers B; a clean stop and more restarts keep B and its undo step, and no notice
    says the file was changed elsewhere."""
    path, auto, expected = _killed_after_two_edits(
        tmp_path, {"op": "delete_keyframe", "id": 1}, first=YOUNG)

    for restart in range(4):  # the recovery, then clean stops and kills with nothing new
        s, notices = _open(tmp_path, path.name)
        try:
            assert _view(s) == expected, f"restart {restart}"
            assert expected[2]["undo_label"] == "delete keyframe 'plant' (mid at 0.25 s)"
            assert not any("outside the editor" in n for n in notices), notices
            assert any("recovered unsaved edits" in n for n in notices), notices
        finally:
            if restart % 2:
                _killed(s, auto, auto.read_bytes() if auto.exists() else None)
            else:
                s.close()
    s, _ = _open(tmp_path, path.name)
    try:  # the whole history is there: undo walks back to the file
        assert s.undo("a")["changed"] and s.undo("a")["changed"]
        assert s.scene == load_scene(path) and not s.dirty
    finally:
        s.close()


def test_an_edit_after_a_recovery_survives_the_next_kill(tmp_path):
    """A crash, a restart that recovers edit B, one more edit C, then a kill before C's
    autosave: the next restart has B and C."""
    path, auto, _ = _killed_after_two_edits(tmp_path, {"op": "delete_keyframe", "id": 1})

    s, _ = _open(tmp_path, path.name)
    assert "plant" not in [k.name for k in s.scene.keyframes]
    lagging = auto.read_bytes()  # as the recovery left it
    s.edit({"op": "set", "section": "damping", "values": {"alpha": 0.9}}, tab="a")
    expected = _view(s)
    _killed(s, auto, lagging)

    s, notices = _open(tmp_path, path.name)
    try:
        assert _view(s) == expected
        assert len(s.scene.keyframes) == 1 and s.scene.damping.alpha == 0.9
        assert not any("outside the editor" in n for n in notices), notices
    finally:
        s.close()


def test_an_undo_back_to_the_file_recovered_after_a_kill_stays_clean(tmp_path):
    """An edit, its undo (back to the saved file), killed before the autosave was removed:
    the restart and every later one open the file clean, with the step to redo."""
    path = bar_project(tmp_path, KEYS, warp=False)
    auto = autosave_path(path)
    s, _ = _open(tmp_path, path.name)
    s.edit({"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    s.autosaver.flush()
    lagging = auto.read_bytes()
    s.undo("a")
    _killed(s, auto, lagging)
    for restart in range(3):
        s, notices = _open(tmp_path, path.name)
        try:
            assert s.scene == load_scene(path) and not s.dirty, f"restart {restart}"
            assert s.describe("a")["redo_label"] == "set damping.alpha"
            assert not any("outside the editor" in n for n in notices), notices
        finally:
            s.close()


def test_the_journal_alone_recovers_when_the_autosave_is_lost(tmp_path):
    """After a recovery, the autosave is lost (removed, or unreadable): the journal alone
    brings the edits back, since the scene file is unchanged since it was written."""
    path = bar_project(tmp_path, KEYS, warp=False)
    auto = autosave_path(path)
    s, _ = _open(tmp_path, path.name)
    s.edit({"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    s.edit({"op": "delete_keyframe", "id": 1}, tab="a")
    expected = _view(s)
    s.close()
    s, _ = _open(tmp_path, path.name)  # a restart: the journal is rewritten as a snapshot
    s.close()
    for lost in ("removed", "unreadable"):
        if lost == "removed":
            auto.unlink()
        else:
            auto.write_text("[material\n")
        s, notices = _open(tmp_path, path.name)
        try:
            assert _view(s) == expected, lost
            assert not any("outside the editor" in n for n in notices), notices
        finally:
            s.close()


def test_save_as_leaves_the_original_clean_and_moves_the_history(tmp_path):
    """Edits, Save as take2.toml, stop: the original reopens as it is on disk, clean and
    without the edits or their undo steps; take2.toml reopens with them."""
    path = bar_project(tmp_path, KEYS, warp=False)
    original = path.read_bytes()
    s, _ = _open(tmp_path, path.name)
    s.edit({"op": "set", "section": "material", "values": {"young": 9e5}}, tab="a")
    s.edit({"op": "update_keyframe", "id": 1, "time": 0.75}, tab="a")
    s.save("take2.toml")
    s.close()
    assert path.read_bytes() == original
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".shot")) == []
    s, notices = _open(tmp_path, path.name)
    try:
        assert s.scene == load_scene(path) and not s.dirty and not notices
        assert not s.histories.describe("a")["can_undo"]
    finally:
        s.close()
    s, notices = _open(tmp_path, "take2.toml")
    try:
        assert s.scene.material.young == 9e5 and not s.dirty and not notices
        assert s.histories.describe("a")["undo_label"] == \
            "move keyframe 'plant' (mid at 0.25 s) to 0.75 s"
    finally:
        s.close()


def test_edits_set_aside_after_an_outside_change_include_the_last_answered_one(tmp_path):
    """Edit A is autosaved, edit B only journaled (killed before its autosave), then the
    scene file is changed in another program: the file opens as it is on disk, one notice
    says so, and the scene the unsaved edits are kept as has A and B, with their undo."""
    path, _, _ = _killed_after_two_edits(tmp_path, YOUNG)
    path.write_text(path.read_text().replace("end = 1.0", "end = 1.5"))
    s, notices = _open(tmp_path, path.name)
    try:
        assert s.scene == load_scene(path) and s.scene.time.end == 1.5 and not s.dirty
        kept = [p for p in tmp_path.iterdir() if p.name.startswith("shot.unsaved-")]
        assert len(kept) == 1
        assert len(notices) == 1 and "changed outside the editor" in notices[0], notices
        assert kept[0].name in notices[0]
        unsaved = load_scene(kept[0])
        assert (unsaved.damping.alpha, unsaved.material.young) == (0.3, 8e5)
        assert not s.histories.describe("a")["can_undo"]
    finally:
        s.close()
    s, notices = _open(tmp_path, kept[0].name)
    try:
        assert s.histories.describe("a")["undo_label"] == "set material.young"
        assert s.undo("a")["changed"] and s.scene.material.young != 8e5
    finally:
        s.close()


def test_a_deleted_scene_with_unsaved_edits_reopens_with_them(tmp_path):
    """The scene file is deleted while the editor has unsaved edits, then a kill: opening
    the scene's name brings the edits back as an unsaved scene, with one notice."""
    path, _, expected = _killed_after_two_edits(tmp_path, YOUNG)
    path.unlink()
    for restart in range(2):
        s, notices = _open(tmp_path, path.name)
        try:
            assert _view(s) == expected and s.dirty, f"restart {restart}"
            assert len(notices) == 1 and "recovered the unsaved scene" in notices[0], notices
            assert not any(p.name.startswith("shot.unsaved-") for p in tmp_path.iterdir())
        finally:
            s.close()


def test_wiggly_edit_on_a_deleted_scene_with_unsaved_edits_recovers_them(tmp_path):
    from tests.test_editor_lock import _ctrl_c, _start

    path = bar_project(tmp_path, KEYS, warp=False)
    s, _ = _open(tmp_path, path.name)
    s.edit({"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    s.close()
    path.unlink()
    proc, _ = _start(path)  # before, "no such file"
    said = _ctrl_c(proc)
    assert "recovered the unsaved scene shot.toml, with all its edits" in said, said


def test_the_recovery_notice_says_what_came_back_in_the_scenes_terms(tmp_path):
    """A key moved and damping set, killed before the autosave of the move: one notice
    names both changes and where the saved file stands, and no hidden file of the editor."""
    path, _, _ = _killed_after_two_edits(tmp_path,
                                         {"op": "update_keyframe", "id": 1, "time": 0.4})
    s, notices = _open(tmp_path, path.name)
    try:
        assert notices == ["recovered unsaved edits to shot.toml: set damping.alpha = 0.3; "
                           "moved keyframe 'plant' (mid at 0.25 s) to 0.4 s. shot.toml on "
                           "disk is as it was last saved until you save"], notices
    finally:
        s.close()


def test_a_save_cut_short_by_a_kill_is_the_editors_own(tmp_path):
    """Killed inside Save, after the new scene file is in place but before the autosave is
    dropped: the restart opens the file clean, as the editor's own save (no notice of a
    change made elsewhere, no edits set aside), with the undo history of the saved edits."""
    path, auto, expected = _killed_after_two_edits(tmp_path, YOUNG)
    edited = expected[0]
    save_scene(edited, path, overwrite=True)  # what Save had written when it was killed
    assert auto.exists()
    s, notices = _open(tmp_path, path.name)
    try:
        assert s.scene == load_scene(path) == edited and not s.dirty
        assert notices == [], notices
        assert not [p for p in tmp_path.iterdir() if ".unsaved-" in p.name]
        assert not auto.exists()
        assert s.histories.describe("a")["undo_label"] == "set material.young"
    finally:
        s.close()


def _two_tabs_after_an_edit_in_a(tmp_path, monkeypatch, other: str) -> tuple[Session, Path]:
    """A session of the bar with pages of tabs a and ``other`` open, no grace period, and
    one edit made in a."""
    monkeypatch.setattr(presence, "TAB_GRACE", 0.0)
    path = bar_project(tmp_path, KEYS, warp=False)
    s, _ = _open(tmp_path, path.name)
    s.page_opened("a")
    s.page_opened(other)
    s.edit({"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    return s, path


def test_a_new_tab_takes_over_the_history_of_a_tab_that_is_gone(tmp_path, monkeypatch):
    """Edits made in tab a: while a page of a listens, its history is its own; once a is
    gone (closed, its browser crashed, or not back after a restart), a tab without a history
    of its own takes it over, so the edits can still be undone; the take-over is journaled
    and survives a kill."""
    s, path = _two_tabs_after_an_edit_in_a(tmp_path, monkeypatch, "b")
    try:
        assert not s.describe("b")["can_undo"]  # a is live
        s.page_closed("page-a", "a")
        assert s.describe("b")["undo_label"] == "set damping.alpha"
        assert not s.histories.describe("a")["can_undo"]  # (a request of a would take it back)
        s.edit(YOUNG, tab="b")
        assert s.describe("b")["undo_label"] == "set material.young"
    finally:
        _killed(s, autosave_path(path), None)  # the journal alone recovers both steps
    s, _ = _open(tmp_path, path.name)
    try:
        s.page_opened("b")  # b came back: its history stays its own
        assert not s.describe("c")["can_undo"]
        assert s.undo("b")["changed"] and s.undo("b")["changed"]
        assert s.scene == load_scene(path) and not s.dirty
    finally:
        s.close()


def test_a_tab_back_from_a_slow_reload_takes_its_history_back(tmp_path, monkeypatch):
    """A reload slower than the grace period lets another tab take the history over (a
    review's reload, its stream held back 4.5 s, found its undo handed to the other tab);
    the reloaded tab takes it back at its first request while the other has not used it,
    and the give-back is journaled.  Once the other tab has used it, it keeps it."""
    s, path = _two_tabs_after_an_edit_in_a(tmp_path, monkeypatch, "c")
    try:
        s.page_closed("page-a1", "a")  # a reloads, slowly
        assert s.describe("c")["undo_label"] == "set damping.alpha"  # c took it over
        s.page_opened("a")
        assert s.describe("a")["undo_label"] == "set damping.alpha"  # and gave it back
        assert not s.describe("c")["can_undo"]
        s.page_closed("page-a2", "a")  # a reloads slowly again, and c uses it this time
        assert s.undo("c")["changed"] and s.describe("c")["redo_label"] == "set damping.alpha"
        s.page_opened("a")
        assert not s.describe("a")["can_undo"] and not s.describe("a")["can_redo"]
        assert s.describe("c")["can_redo"]
    finally:
        _killed(s, autosave_path(path), None)
    s, _ = _open(tmp_path, path.name)  # the journal replays the hand-overs
    try:
        s.page_opened("c")
        assert s.describe("c")["redo_label"] == "set damping.alpha"
    finally:
        s.close()


def test_a_tab_back_after_a_restart_keeps_its_history(tmp_path):
    """Right after a restart, before the tabs of the journal could come back, a new tab
    takes nothing (a reload or a reconnect takes a second or two)."""
    path, _, _ = _killed_after_two_edits(tmp_path, YOUNG)
    s, _ = _open(tmp_path, path.name)
    try:
        assert not s.describe("new")["can_undo"]
        s.page_opened("a")
        assert s.describe("a")["undo_label"] == "set material.young"
    finally:
        s.close()


def test_a_saved_scene_is_on_the_disk_before_it_replaces_the_file(tmp_path, monkeypatch):
    """save_scene flushes the new file's bytes to the disk before the rename, and the
    folder's entry after it: an operating-system crash leaves the old file or the new one,
    and the editor drops its autosave only after that."""
    path = bar_project(tmp_path, KEYS, warp=False)
    scene = load_scene(path)
    scene = dataclasses.replace(scene, damping=dataclasses.replace(scene.damping, alpha=0.7))
    synced: list[tuple[str, str | None]] = []

    def sync(p):
        p = Path(p)
        synced.append((p.name, p.read_text() if p.is_file() else None))

    monkeypatch.setattr(files, "sync_file", sync)
    save_scene(scene, path, overwrite=True)
    assert len(synced) == 2 and synced[1] == (tmp_path.name, None)
    assert synced[0][0] != path.name and synced[0][1] == path.read_text()


def test_a_preview_from_a_page_that_has_closed_is_ignored(tmp_path):
    """A drag's preview sent before its page closed and arriving after the page's event
    stream ended (an in-flight request) is ignored: no tab would ever see that drag end,
    and the others kept showing it until their next edit."""
    path = bar_project(tmp_path, KEYS, warp=False)
    s, _ = _open(tmp_path, path.name)
    try:
        op = {"op": "set", "section": "damping", "values": {"alpha": 1.3}}
        assert s.preview(op, page="live")["seq"] is not None
        s.page_closed("gone", "a")
        assert s.preview(op, page="gone") == {"seq": None}
        assert s.cancel_preview("live")["seq"] is not None  # the live page's drag was on
    finally:
        s.close()


def test_notices_show_paths_inside_the_root_as_the_editor_does(tmp_path):
    """A warning about a file inside the editor's root (a mesh whose triangles face inwards,
    said by the physics process with the file's absolute path) reaches the page with the
    path as the editor shows it, relative to the root."""
    import queue
    import time

    import trimesh

    root = tmp_path / "shots"
    (root / "meshes").mkdir(parents=True)
    box = trimesh.creation.box(extents=(0.4, 0.1, 0.1))
    trimesh.Trimesh(box.vertices, box.faces[:, ::-1], process=False).export(
        root / "meshes" / "inward.obj")
    session = Session(Sandbox([root]))
    events = session.bus.subscribe()
    try:
        session.open("meshes/inward.obj")
        deadline, said = time.monotonic() + 120, None
        while said is None and time.monotonic() < deadline:
            try:
                e = events.get(timeout=1.0)
            except queue.Empty:
                continue
            if e["type"] == "notice" and "face inwards" in e["message"]:
                said = e["message"]
        assert said is not None and said.startswith("meshes/inward.obj: "), said
        assert str(root) not in said, said
    finally:
        session.close()
