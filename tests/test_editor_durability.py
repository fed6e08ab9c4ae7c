"""Nothing the user wrote is lost, and nothing is said to be lost that is not: Save as onto a
scene with unsaved edits of its own, an outside change after a clean save, a start without
autosave, a private file's permissions, and what Ctrl+C says when the file was changed on
disk. (Edits only the journal holds, then an outside change: ``test_editor_crash.py``.)"""

from __future__ import annotations

import os
from pathlib import Path

from tests.editor_ui import bar_project
from wiggly.cli.edit import stop_messages
from wiggly.editor import Sandbox, Session
from wiggly.editor.history import history_path
from wiggly.editor.session import autosave_path
from wiggly.scene import load_scene

ALPHA = {"op": "set", "section": "damping", "values": {"alpha": 0.77}}
END = {"op": "set", "section": "time", "values": {"end": 3.0}}


def _open(folder: Path, name: str, autosave: bool = True) -> tuple[Session, list[str]]:
    session = Session(Sandbox([folder]), autosave=autosave)
    return session, session.open(name)["notices"]


def _kept(folder: Path, stem: str) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.name.startswith(f"{stem}.unsaved-"))


def test_save_as_onto_a_scene_with_unsaved_edits_keeps_them(tmp_path):
    """A scene with unsaved edits (a kill), then another scene is saved as its name: its
    edits are kept as a scene of their own with their undo steps, and the save says so."""
    for journal_only in (False, True):
        folder = tmp_path / ("journal" if journal_only else "autosave")
        folder.mkdir()
        path = bar_project(folder, warp=False)
        other = bar_project(folder, warp=False, name="other.toml")
        s, _ = _open(folder, path.name)
        s.edit(ALPHA, tab="a")
        s.edit(END, tab="a")
        s.close()  # as a kill after the edits were answered
        if journal_only:  # killed before the autosave landed: the journal alone has them
            autosave_path(path).unlink()
        s, _ = _open(folder, other.name)
        try:
            said = s.save(path.name, overwrite=True)["notices"]
        finally:
            s.close()
        kept = _kept(folder, "shot")
        assert len(kept) == 1, journal_only
        assert len(said) == 1 and kept[0].name in said[0] and "never saved" in said[0], said
        unsaved = load_scene(kept[0])
        assert (unsaved.damping.alpha, unsaved.time.end) == (0.77, 3.0), journal_only
        s, notices = _open(folder, kept[0].name)
        try:
            assert s.histories.describe("a")["undo_label"] == "set time.end"
        finally:
            s.close()
        s, notices = _open(folder, path.name)  # the saved scene opens clean, as saved
        try:
            assert not s.dirty and not notices and s.scene.damping.alpha != 0.77
        finally:
            s.close()


def test_an_outside_change_after_a_clean_save_is_no_loss(tmp_path):
    """Edits, Save, stop; another program changes the file: it opens as it is on disk with
    one notice that undo starts afresh, and no word of lost edits or a scene set aside."""
    path = bar_project(tmp_path, warp=False)
    s, _ = _open(tmp_path, path.name)
    s.edit(ALPHA, tab="a")
    s.save()
    s.close()
    path.write_text(path.read_text().replace("end = 1.0", "end = 1.5"))
    s, notices = _open(tmp_path, path.name)
    try:
        assert s.scene == load_scene(path) and not s.dirty
        assert len(notices) == 1 and "since it was last saved here" in notices[0], notices
        assert "not saved" not in notices[0]
        assert not _kept(tmp_path, "shot") and not s.histories.describe("a")["can_undo"]
    finally:
        s.close()


def test_a_start_without_autosave_says_the_journal_holds_edits(tmp_path):
    """Edits only the journal holds, then ``--no-autosave``: the scene opens as saved, and
    a notice says where the edits are and how to get them; the next start recovers them."""
    path = bar_project(tmp_path, warp=False)
    s, _ = _open(tmp_path, path.name)
    s.edit(ALPHA, tab="a")
    s.close()
    autosave_path(path).unlink()
    s, notices = _open(tmp_path, path.name, autosave=False)
    try:
        assert s.scene.damping.alpha != 0.77
        assert any(history_path(path).name in n and "--no-autosave" in n for n in notices), \
            notices
    finally:
        s.close()
    s, notices = _open(tmp_path, path.name)
    try:
        assert s.scene.damping.alpha == 0.77
    finally:
        s.close()


def test_save_keeps_a_private_scene_files_permissions(tmp_path):
    path = bar_project(tmp_path, warp=False)
    path.chmod(0o600)
    s, _ = _open(tmp_path, path.name)
    try:
        s.edit(ALPHA, tab="a")
        s.save()
    finally:
        s.close()
    assert load_scene(path).damping.alpha == 0.77
    assert os.stat(path).st_mode & 0o777 == 0o600


def test_ctrl_c_after_an_outside_change_says_where_the_edits_will_be(tmp_path):
    path = bar_project(tmp_path, warp=False)
    s, _ = _open(tmp_path, path.name)
    try:
        s.edit(ALPHA, tab="a")
        path.write_text(path.read_text() + "\n# changed\n")
        said = stop_messages(s)[-1]
    finally:
        s.close()
    assert "changed on disk by another program" in said, said
    assert "opens the disk's version" in said and "shot.unsaved-" in said


def test_a_failed_autosave_is_said_on_the_terminal_once(tmp_path, caplog):
    """With no page open, nobody would hear of a failed autosave: it is also logged, once
    per cause, not once per edit."""
    import logging

    from wiggly.editor.autosave import Autosaver
    from wiggly.scene import Scene
    from wiggly.scene.spec import MeshSpec

    told: list[str] = []
    saver = Autosaver(told.append)
    target = tmp_path / "gone" / ".shot.autosave.toml"  # its folder does not exist
    with caplog.at_level(logging.WARNING, logger="wiggly"):
        for _ in range(3):
            saver.put(target, Scene(MeshSpec("builtin:bar")), None)
            saver.flush()
    saver.close()
    said = [r.getMessage() for r in caplog.records if "autosave failed" in r.getMessage()]
    assert len(told) == 3 and len(said) == 1, (told, said)


def test_ctrl_c_on_a_new_scene_without_edits_promises_nothing(tmp_path):
    """A mesh opened as a new scene and left as it was: Ctrl+C says it was not saved and had
    no edits, not that unsaved edits are kept in files that do not exist."""
    bar_project(tmp_path, warp=False)
    s = Session(Sandbox([tmp_path]))
    try:
        s.open("bar.vtu")
        said = stop_messages(s)[-1]
    finally:
        s.close()
    assert "was not saved (it had no edits to keep)" in said, said
    assert "kept beside it" not in said
