"""Opening a scene file with the edits its autosave and undo journal hold beyond it.

The journal's tail is replayed over the autosave (which may lag it: an edit is answered once
its journal line is on the disk, and the autosave follows in the background).  The recovered
state is then written back before the journal is compacted: the autosave is made the
recovered scene (or removed, when that is the file's), and only then is the journal rewritten
as one snapshot of it.  So a later open, after a clean stop or another crash, finds the same
scene and undo history, however many times it happens.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from wiggly.editor.autosave import autosave_base, autosave_path, write_autosave, write_durably
from wiggly.editor.changes import describe_changes
from wiggly.editor.history import Histories, history_path
from wiggly.editor.scene_files import file_digest, load_checked
from wiggly.editor.state import EditError, EditorState
from wiggly.files import remove_stale
from wiggly.scene import Scene, scene_to_toml

__all__ = ["recover", "set_aside_unsaved"]


def recover(path: str, real: Path, histories: Histories, notices: list[str],
            ) -> tuple[EditorState, Scene | None]:
    """The scene file ``real`` (as the user named it: ``path``) with the edits its autosave
    and journal (``histories``) hold beyond it, and the file's scene (None: never saved).
    What was recovered, set aside or ignored is appended to ``notices``."""
    file_scene = load_checked(real) if real.is_file() else None
    disk = file_digest(real)
    auto = autosave_path(real)
    for written in (auto, history_path(real)):  # a write a crash cut short (a minute old:
        remove_stale(written.with_name(written.name + ".part"), 60.0)  # not another's)
    auto_scene: Scene | None = None
    base_of_auto = autosave_base(auto) if auto.is_file() else None
    # changed in another program (a deleted file has nothing to protect: the edits come back)
    changed = base_of_auto is not None and disk is not None and base_of_auto != disk
    if changed and _saved_edits(real, auto, file_scene, histories):
        auto.unlink(missing_ok=True)  # a save cut short: the file holds the edits
        changed = False
    if changed:
        _set_aside(real, histories, notices)
    elif not auto.is_file() and disk is not None:  # the journal alone may hold the edits
        stranded = histories.unsaved(file_scene, real, disk, replayable=False)
        if stranded is not None:  # ... and the file was changed in another program since
            _set_aside(real, histories, notices, stranded)
    elif auto.is_file():
        try:
            auto_scene = load_checked(auto)
            auto_scene.source = real
        except EditError as err:
            notices.append(f"ignored the unreadable autosave of {real.name} "
                           f"({str(err).splitlines()[0]})")
    histories.disk = disk
    base = auto_scene if auto_scene is not None else file_scene
    state, notice = histories.load(base, real, disk=disk, compact=False, name=real.name,
                                   autosaved=auto_scene is not None)
    if notice:
        notices.append(notice)
    if state is None:
        raise EditError(f"{path}: no such file", 404)
    if histories.path is not None and histories.path.is_file():
        _write_back(auto, state, file_scene, auto_scene, disk, histories)
    if state.scene != file_scene:
        notices.append(_recovered(real, file_scene, state.scene))
    if histories.path is None and Histories(history_path(real)).unsaved(
            state.scene, real, disk) is not None:  # autosave off: the journal is not read
        notices.append(f"the undo journal beside {real.name} ({history_path(real).name}) "
                       "holds edits that are not shown: this editor runs without autosave "
                       f"(--no-autosave); `wiggly edit {real.name}` without it recovers them")
    return state, file_scene


def _recovered(real: Path, file_scene: Scene | None, scene: Scene) -> str:
    """The notice of a recovery: what the unsaved edits changed, and where the file stands."""
    if file_scene is None:
        return (f"recovered the unsaved scene {real.name}, with all its edits: it is not on "
                "disk (never saved, or deleted since); Save writes it")
    changes = describe_changes(file_scene, scene)
    return (f"recovered unsaved edits to {real.name}: {'; '.join(changes)}. {real.name} on "
            "disk is as it was last saved until you save")


def _write_back(auto: Path, state: EditorState, file_scene: Scene | None, auto_scene: Scene | None,
                disk: str | None, histories: Histories) -> None:
    """Make the autosave ``auto`` the recovered ``state`` (removed: it is the file's), then compact
    the journal to it.  If the autosave cannot be written, the journal stays as it is: it
    still gives ``state`` over the old autosave."""
    try:
        if state.scene == file_scene:
            auto.unlink(missing_ok=True)
        elif state.scene != auto_scene:
            write_autosave(auto, state.scene, disk)
    except OSError:
        return
    histories.compact(state)


def _saved_edits(real: Path, auto: Path, file_scene: Scene | None,
                 histories: Histories) -> bool:
    """Whether the scene file is the autosave ``auto`` with the journal's steps replayed over
    it: the editor saved them and stopped before it dropped its autosave (a crash within the
    save), so the file on disk is the editor's own, not another program's change."""
    if file_scene is None:
        return False
    try:
        scene = load_checked(auto)
    except EditError:
        return False
    scene.source = real
    state = histories.peek(scene, real)
    return (state.scene if state is not None else scene) == file_scene


def set_aside_unsaved(real: Path, notices: list[str]) -> None:
    """Before another scene is saved as ``real``: the edits of ``real``'s own that were never
    saved (its autosave, or its journal beyond the file; an earlier session's) are kept as
    the scene ``NAME.unsaved-<date>-<time>.toml`` with their undo history, not overwritten,
    and a notice says so."""
    if not (autosave_path(real).is_file() or history_path(real).is_file()):
        return  # nothing of an earlier session's: the usual Save as
    histories = Histories(history_path(real))
    try:
        file_scene = load_checked(real) if real.is_file() else None
    except EditError:  # not a scene the editor reads: its journal cannot be its edits
        file_scene = None
    state = None
    if not autosave_path(real).is_file():
        state = histories.unsaved(file_scene, real, file_digest(real))
        if state is None:
            return
    _set_aside(real, histories, notices, state,
               why=f"{real.name} had edits of its own that were never saved (an earlier "
                   "session's), and another scene is saved as it now")


def _set_aside(real: Path, histories: Histories, notices: list[str],
               state: EditorState | None = None, why: str | None = None) -> None:
    """The scene file ``real`` was changed in another program after edits that were not
    saved (its autosave was made from another version of it, or only its journal holds
    them: ``state``): they must not overwrite that change unasked.  They are kept as the
    scene ``NAME.unsaved-<date>-<time>.toml``, the journal's tail replayed over the autosave
    (every answered edit), with the journal as its undo history; the file then opens as it
    is on disk, and a notice says so (``why`` in place of its first words)."""
    auto = autosave_path(real)
    kept = real.with_name(f"{real.stem}.unsaved-{time.strftime('%Y%m%d-%H%M%S')}.toml")
    try:
        if state is None:
            scene = load_checked(auto)
            scene.source = kept
            state = histories.peek(scene, kept)  # None: the journal is not of these edits
        else:
            scene = state.scene
        write_durably(kept, scene_to_toml(state.scene if state is not None else scene))
        auto.unlink(missing_ok=True)
        where = f"; they are kept as the scene {kept.name} (Open shows it)"
    except (EditError, OSError):  # unreadable: kept as it is
        state = None
        try:
            os.replace(auto, kept)
            where = f"; they are kept as the scene {kept.name} (Open shows it)"
        except OSError:
            where = ""
    if state is not None and histories.path is not None:  # its undo history goes with it
        try:
            os.replace(histories.path, history_path(kept))
            where = where.replace("(Open shows it)", "(Open shows it, with their undo steps)")
        except OSError:
            pass
    if why is not None:
        notices.append(f"{why}{where or ': they could not be kept as a scene'}")
        return
    notices.append(f"{real.name} was changed outside the editor after edits that were not "
                   f"saved: it opens as it is on disk, without them{where}")
