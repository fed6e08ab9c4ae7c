"""Ctrl+C on ``wiggly edit`` says where unsaved edits are kept, and that an export under way
is finished first."""

from __future__ import annotations

import json
import os
import urllib.request

import pytest

from tests.editor_ui import bar_project
from tests.test_editor_lock import _ctrl_c, _start
from wiggly.cli.edit import stop_messages
from wiggly.editor import Sandbox, Session


@pytest.mark.skipif(os.name != "posix", reason="sends SIGINT")
def test_ctrl_c_with_unsaved_edits_says_they_are_kept_and_how_to_get_them(tmp_path):
    scene = bar_project(tmp_path, warp=False, name="my shot.toml")
    proc, url = _start(scene)
    try:
        request = urllib.request.Request(
            url + "api/edit", method="POST", headers={"Content-Type": "application/json"},
            data=json.dumps({"op": "set", "section": "damping",
                             "values": {"alpha": 0.7}}).encode())
        with urllib.request.urlopen(request, timeout=60) as answer:
            assert answer.status == 200
    finally:
        said = _ctrl_c(proc)
    assert "the unsaved edits of my shot.toml are kept beside it (.my shot.autosave.toml, " \
        in said, said
    assert "`wiggly edit 'my shot.toml'` opens it with them" in said
    session = Session(Sandbox([tmp_path]))
    try:  # and so it does
        assert any("recovered" in n for n in session.open(scene.name)["notices"])
        assert session.scene.damping.alpha == 0.7
    finally:
        session.close()


def test_ctrl_c_during_an_export_says_it_is_finished_first(tmp_path):
    session = Session(Sandbox([tmp_path]))
    try:
        session.open(bar_project(tmp_path, warp=False).name)
        assert stop_messages(session) == ["wiggly edit: stopped"]  # nothing unsaved
        session.exporting = ["take.mp4"]  # as while an export is written
        assert stop_messages(session)[0] == \
            "wiggly edit: finishing the export of take.mp4 before stopping..."
    finally:
        session.close()
