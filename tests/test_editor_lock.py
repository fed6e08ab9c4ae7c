"""One editor per scene: a second editor on a scene that one has open is refused, naming the
first (its process and address), and a lock left by a killed editor is taken over."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.editor_ui import bar_project
from wiggly.editor import Sandbox, Session
from wiggly.editor.state import EditError

pytestmark = pytest.mark.skipif(os.name != "posix", reason="the lock is flock's (POSIX)")

START = "import sys; from wiggly.cli import main; sys.exit(main())"


def test_a_second_session_on_a_scene_is_refused_until_the_first_closes(tmp_path):
    path = bar_project(tmp_path, warp=False)
    first = Session(Sandbox([tmp_path]))
    second = Session(Sandbox([tmp_path]))
    try:
        first.open(path.name)
        first.serving("http://127.0.0.1:8123/")
        with pytest.raises(EditError) as err:
            second.open(path.name)
        assert err.value.status == 409
        message = str(err.value)
        assert "shot.toml is already open in another wiggly edit" in message, message
        assert f"pid {os.getpid()}" in message and "http://127.0.0.1:8123/" in message
        assert second._state is None  # nothing opened
        # Save as onto the scene the first has open is refused the same way
        other = bar_project(tmp_path, warp=False, name="other.toml")
        second.open(other.name)
        with pytest.raises(EditError) as err:
            second.save(path.name, overwrite=True)
        assert err.value.status == 409 and "already open in another wiggly edit" in str(err.value)
        # the first opens another scene: the second may now open its old one
        first.open(bar_project(tmp_path, warp=False, name="third.toml").name)
        second.open(path.name)
        assert second.scene.source == path
    finally:
        first.close()
        second.close()


def test_the_same_mesh_in_two_editors_gives_two_scenes(tmp_path):
    bar_project(tmp_path, warp=False)
    first = Session(Sandbox([tmp_path]))
    second = Session(Sandbox([tmp_path]))
    try:
        assert first.open("bar.vtu")["path"] == "bar.toml"
        assert second.open("bar.vtu")["path"] == "bar-2.toml"
    finally:
        first.close()
        second.close()


def _start(scene: Path) -> tuple[subprocess.Popen, str]:
    """``wiggly edit SCENE`` in its own process; the process and the address it serves."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", START, "edit", str(scene), "--no-browser",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=scene.parent)
    line = proc.stdout.readline()
    url = re.search(r"http://127\.0\.0\.1:\d+/", line)
    assert url, line + proc.stderr.read()
    return proc, url.group(0)


def _ctrl_c(proc: subprocess.Popen) -> str:
    """Ctrl+C to a ``wiggly edit`` of :func:`_start`: it stops cleanly; what it said on
    stderr."""
    try:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
        return proc.stderr.read()
    finally:
        proc.stdout.close()
        proc.stderr.close()


def test_a_second_wiggly_edit_is_refused_and_a_killed_ones_lock_is_taken_over(tmp_path):
    folder = tmp_path / "my shots ü 猫"
    folder.mkdir()
    scene = bar_project(folder, warp=False, name="take one é.toml")
    first, url = _start(scene)
    try:
        second = subprocess.run([sys.executable, "-c", START, "edit", str(scene),
                                 "--no-browser", "--port", "0"], capture_output=True,
                                text=True, timeout=120,
                                env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
        assert second.returncode == 1
        assert "Traceback" not in second.stderr
        assert "take one é.toml is already open in another wiggly edit" in second.stderr
        assert f"pid {first.pid}" in second.stderr and url in second.stderr, second.stderr
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
        first.stdout.close()
        first.stderr.close()
    assert any(p.name.endswith(".editor.lock") for p in folder.iterdir())  # left by the kill
    third, _ = _start(scene)  # the stale lock is taken over
    _ctrl_c(third)
    assert not any(p.name.endswith(".editor.lock") for p in folder.iterdir())
