"""Crash consistency of the editor (issue 25): an edit the server has answered survives any
crash, with every tab's undo history.

The main test runs ``wiggly edit`` as a child process and kills it with SIGKILL at random
moments of a burst of edits, undos and redos sent as fast as it answers (so the kill falls
anywhere: in a request, between the journal's line and the background autosave, in the
autosave's write), many times over; every other kill comes the moment an answer arrives,
while the autosave of that edit is still being written (the race of the issue).  After each
kill the editor is started again on the scene: it must show the state of the last answered
request (or of the one in flight, which may have been made durable before its answer was
lost), and undo and redo must walk the whole history
back to the scene as it was opened and forward again.  The expected states are computed
independently in this process by applying the same edits to the scene file's state
(:func:`wiggly.editor.state.apply_edit`).  ``WIGGLY_CRASH_ROUNDS`` sets the number of kill
points (default 16), ``WIGGLY_CRASH_SEED`` the random requests and kill times.  Whether a kill
falls in the race of the issue depends on timing; the replay it needs is also tested
deterministically below, from the files such a kill leaves.

The other tests reproduce the crash's files directly: an autosave that lags the journal, none
at all, a journal line torn by a crash mid-write, a scene never saved.
"""

from __future__ import annotations

import http.client
import json
import os
import random
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.editor_ui import bar_project
from wiggly.editor import Sandbox, Session
from wiggly.editor.history import DEFAULT_TAB, history_path
from wiggly.editor.session import autosave_path
from wiggly.editor.state import EditError, EditorState, apply_edit, state_to_json
from wiggly.scene import load_scene

ROUNDS = int(os.environ.get("WIGGLY_CRASH_ROUNDS", "16"))
MAX_BURST = 40  # requests answered in a round (the walk after it checks every step)
TAB = "crash"
KEYS = """
[[keyframes]]
time = 0.25
group = "mid"
position = { offset = [0.0, 0.01, 0.0] }
"""


# ----------------------------------------------------------------------------------------------
# the model: what the editor's state must be after the answered requests


class Model:
    """The states a tab's history walks through (``states[p]`` is the current one), computed
    with :func:`apply_edit` on the scene file's state, as the server does it live."""

    def __init__(self, state: EditorState):
        self.states = [state]
        self.p = 0
        self.next_id = state.next_id  # never reused, even after an undo

    @property
    def state(self) -> EditorState:
        s = self.states[self.p]
        return EditorState(s.scene, s.keyframe_ids, self.next_id)

    def after(self, request: tuple[str, dict | None]) -> Model:
        """The model after the request (a copy)."""
        m = Model.__new__(Model)
        m.states, m.p, m.next_id = list(self.states), self.p, self.next_id
        kind, op = request
        if kind == "edit":
            new = apply_edit(m.state, op)
            if state_to_json(new) == state_to_json(m.state):
                return m  # nothing changed: the server records no step
            m.states = [*m.states[:m.p + 1], new]
            m.p += 1
            m.next_id = new.next_id
        elif kind == "undo":
            m.p = max(m.p - 1, 0)
        else:
            m.p = min(m.p + 1, len(m.states) - 1)
        return m

    def view(self, k: int | None = None) -> dict:
        """The scene as ``/api/state`` shows it (keyframes with their ids)."""
        s = self.states[self.p if k is None else k]
        return state_to_json(EditorState(s.scene, s.keyframe_ids, self.next_id))


def next_request(rng: random.Random, model: Model) -> tuple[str, dict | None]:
    """A random edit, undo or redo on the bar."""
    ids = list(model.state.keyframe_ids)
    r = rng.random()
    if r < 0.12 and model.p > 0:
        return "undo", None
    if r < 0.18 and model.p < len(model.states) - 1:
        return "redo", None
    if r < 0.40:
        return "edit", {"op": "set", "section": "damping",
                        "values": {"alpha": round(rng.uniform(0.0, 2.0), 4)}}
    if r < 0.50:
        return "edit", {"op": "set", "section": "material",
                        "values": {"young": round(rng.uniform(5e5, 5e6), 1)}}
    if r < 0.70 or not ids:
        return "edit", {"op": "add_keyframe", "time": round(rng.uniform(0.0, 1.0), 3),
                        "group": rng.choice(["mid", "right"]),
                        "position": {"offset": [0.0, round(rng.uniform(-0.05, 0.05), 4), 0.0]}}
    if r < 0.88:
        return "edit", {"op": "update_keyframe", "id": rng.choice(ids),
                        "time": round(rng.uniform(0.0, 1.0), 3)}
    return "edit", {"op": "delete_keyframe", "id": rng.choice(ids)}


# ----------------------------------------------------------------------------------------------
# the editor as a child process


# The editor's process is forked from one that has imported it (a fork server), so that a
# restart costs a fraction of a second and the test can afford many kill points; the child
# runs ``wiggly edit`` exactly as the command line does (``wiggly.cli.main``).
FORK_SERVER = r"""
import os, sys
from wiggly.cli import main
import wiggly.cli.edit, wiggly.editor.server  # the editor's modules, imported once
out = {}
while True:
    line = sys.stdin.readline()
    if not line:
        break
    command, arg = line.split(None, 1)
    arg = arg.strip()
    if command == "reap":  # wait until a killed editor is gone
        os.waitpid(int(arg), 0)
        out.pop(int(arg)).close()
        print("reaped", flush=True)
        continue
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(read)
        os.dup2(write, 1)
        os.close(write)
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
        os._exit(main(["edit", arg, "--port", "0", "--no-browser"]))
    os.close(write)
    out[pid] = os.fdopen(read)
    print(pid, out[pid].readline().strip(), flush=True)
"""


class ForkServer:
    """Starts editors on request (``start``) and waits for killed ones (``reap``)."""

    def __init__(self, log):
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, "-c", FORK_SERVER], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=log, env=env)
        self.live: set[int] = set()

    def ask(self, line: str) -> str:
        self.proc.stdin.write(line.encode() + b"\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], 120)
        assert ready, f"the fork server did not answer {line!r}"
        return self.proc.stdout.readline().decode().strip()

    def close(self) -> None:
        """Kill the editors still running (a failed test), then stop."""
        for pid in self.live:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self.proc.stdout.close()


class Editor:
    """``wiggly edit SCENE`` (forked by ``forks``), and a keep-alive connection to it."""

    def __init__(self, scene: Path, forks: ForkServer):
        self.forks = forks
        pid, _, url = forks.ask(f"start {scene}").partition(" ")
        self.pid = int(pid)
        forks.live.add(self.pid)
        if "http://" not in url:
            self.stop()
            raise AssertionError(f"the editor did not start: {url!r}")
        self.port = int(url.split("http://")[1].split("/")[0].rsplit(":", 1)[1])
        self.conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)

    def call(self, method: str, path: str, body: dict | None = None) -> tuple[int, dict]:
        data = json.dumps(body or {}).encode() if method == "POST" else None
        headers = {"X-Wiggly-Tab": TAB, "Content-Type": "application/json"}
        self.conn.request(method, path, data, headers)
        r = self.conn.getresponse()
        return r.status, json.loads(r.read() or b"{}")

    def request(self, request: tuple[str, dict | None]) -> dict:
        kind, op = request
        status, out = self.call("POST", f"/api/{kind}", op)
        assert status == 200, (request, out)
        return out

    def state(self) -> dict:
        status, out = self.call("GET", "/api/state")
        assert status == 200, out
        return out

    def kill(self) -> None:
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def stop(self) -> None:
        """Kill the editor and wait until it is gone."""
        self.kill()
        assert self.forks.ask(f"reap {self.pid}") == "reaped"
        self.forks.live.discard(self.pid)
        self.conn.close()


def burst(editor: Editor, model: Model, rng: random.Random, delay: float | None = None,
          answers: int | None = None) -> tuple[Model, Model | None, int]:
    """Send random requests until the editor is killed: ``delay`` seconds in, or the moment
    the answer to the ``answers``-th request arrives (its autosave is still being written).
    The model after the last answered request, after the one in flight (None: none was),
    and the number answered."""
    timer = threading.Timer(delay, editor.kill) if delay is not None else None
    if timer is not None:
        timer.start()
    answered, pending = 0, None
    try:
        while answered < MAX_BURST:
            request = next_request(rng, model)
            pending = model.after(request)
            try:
                editor.request(request)
            except (OSError, http.client.HTTPException):
                break
            model, pending, answered = pending, None, answered + 1
            if answered == answers:
                editor.kill()
                break
    finally:
        if timer is not None:
            timer.cancel()
        editor.stop()
    return model, pending, answered


def walk(editor: Editor, model: Model) -> None:
    """Undo back to the scene as opened, then redo to the newest state, checking each."""
    for k in range(model.p - 1, -1, -1):
        assert editor.request(("undo", None))["changed"]
        assert editor.state()["scene"] == model.view(k), f"undo to step {k}"
    assert not editor.request(("undo", None))["changed"]
    assert not editor.state()["can_undo"]
    for k in range(1, len(model.states)):
        assert editor.request(("redo", None))["changed"]
        assert editor.state()["scene"] == model.view(k), f"redo to step {k}"
    assert not editor.state()["can_redo"]
    # the ids go on where they were: a new keyframe gets the id the live editor would give it
    out = editor.request(("edit", {"op": "add_keyframe", "time": 0.5, "group": "mid"}))
    assert out["id"] == model.next_id


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork and SIGKILL (POSIX)")
def test_no_answered_edit_is_lost_when_the_editor_is_killed(tmp_path):
    with open(tmp_path / "editor.log", "wb") as log:
        forks = ForkServer(log)
        try:
            t0 = time.perf_counter()
            rng = random.Random(int(os.environ.get("WIGGLY_CRASH_SEED", "25")))
            replayed, landed, answered = crash_rounds(tmp_path, forks, rng)
        finally:
            forks.close()
    print(f"\n{ROUNDS} kill points, {answered} answered requests in "
          f"{time.perf_counter() - t0:.1f} s; unsaved edits were recovered "
          f"after {replayed} kills; the request in flight had landed after {landed}")


def crash_rounds(folder: Path, forks: ForkServer, rng: random.Random) -> tuple[int, int, int]:
    """:data:`ROUNDS` kills and restarts, each on a fresh scene; how often unsaved
    edits were recovered, how often the request in flight had landed, and the requests answered."""
    scenes = [bar_project(folder, KEYS, name=f"shot{r}.toml", warp=False)
              for r in range(ROUNDS + 1)]
    editor = Editor(scenes[0], forks)
    replayed = in_flight_landed = answered_total = 0
    for r in range(ROUNDS):
        model = Model(EditorState.of(load_scene(scenes[r])))
        if r > 0:
            assert editor.request(("open", {"path": scenes[r].name}))
        assert editor.state()["scene"] == model.view()
        if r % 2:
            model, pending, answered = burst(editor, model, rng, answers=rng.randint(1, 12))
        else:
            model, pending, answered = burst(editor, model, rng, delay=rng.uniform(0.01, 0.5))
        answered_total += answered

        editor = Editor(scenes[r], forks)  # the restart
        shown = editor.state()
        assert not any("does not match" in n or "ignored" in n for n in shown["notices"]), \
            shown["notices"]
        if pending is not None and shown["scene"] == pending.view() != model.view():
            model, in_flight_landed = pending, in_flight_landed + 1
        assert shown["scene"] == model.view(), f"round {r}: after {answered} answers"
        assert shown["can_undo"] == (model.p > 0)
        assert shown["can_redo"] == (model.p < len(model.states) - 1)
        replayed += any(n.startswith("recovered") for n in shown["notices"])
        walk(editor, model)
    editor.stop()
    return replayed, in_flight_landed, answered_total


# ----------------------------------------------------------------------------------------------
# the crash's files, made directly


def _edits(session: Session) -> EditorState:
    """Five edits in tab "a" and an undo; the state they leave."""
    ops = [{"op": "set", "section": "damping", "values": {"alpha": 0.5}},
           {"op": "set", "section": "damping", "values": {"alpha": 0.7}},
           {"op": "add_keyframe", "time": 0.75, "group": "right"},
           {"op": "delete_keyframe", "id": 0},
           {"op": "set", "section": "damping", "values": {"alpha": 0.9}}]
    for op in ops:
        session.edit(op, tab="a")
    session.undo("a")
    session.autosaver.flush()
    return session.state


def test_the_journal_tail_is_replayed_over_a_lagging_autosave(tmp_path):
    path = bar_project(tmp_path, KEYS, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open(path.name)
    s1.edit({"op": "set", "section": "damping", "values": {"alpha": 0.3}}, tab="a")
    s1.autosaver.flush()
    lagging = autosave_path(path).read_bytes()  # the autosave after the first edit only
    end = _edits(s1)
    s1.close()
    for autosave in (lagging, None):  # the autosave lags, or was never written
        if autosave is None:
            autosave_path(path).unlink(missing_ok=True)
        else:
            autosave_path(path).write_bytes(autosave)
        kept = history_path(path).read_bytes()
        s2 = Session(Sandbox([tmp_path]))
        try:
            opened = s2.open(path.name)
            assert s2.scene == end.scene and s2.state.keyframe_ids == end.keyframe_ids
            assert any("recovered unsaved edits to shot.toml: set damping.alpha = 0.7" in n
                       for n in opened["notices"]), opened["notices"]
            assert s2.dirty and s2.describe("a")["redo_label"] == "set damping.alpha"
            assert s2.redo("a")["changed"] and s2.scene.damping.alpha == 0.9
            for _ in range(6):
                assert s2.undo("a")["changed"]
            assert s2.scene == load_scene(path) and not s2.dirty
            assert not s2.undo("a")["changed"]
        finally:
            s2.close()
        history_path(path).write_bytes(kept)


def test_a_torn_last_line_is_not_an_edit(tmp_path):
    path = bar_project(tmp_path, KEYS, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open(path.name)
    end = _edits(s1)
    s1.close()
    with open(history_path(path), "a") as f:  # a crash in the middle of the next line
        f.write('{"op":"edit","tab":"a","rec":{"label":"set damping","chan')
    s2 = Session(Sandbox([tmp_path]))
    try:
        opened = s2.open(path.name)
        assert s2.scene == end.scene and not any("ignored" in n for n in opened["notices"])
        assert s2.describe("a")["can_undo"] and s2.describe("a")["can_redo"]
    finally:
        s2.close()


def test_a_scene_never_saved_comes_back_from_its_journal_alone(tmp_path):
    bar_project(tmp_path, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open("bar.vtu")  # a new scene, bar.toml, never saved
    s1.edit({"op": "set_group", "name": "tip", "indices": [78, 79, 80]}, tab="a")
    s1.edit({"op": "add_keyframe", "time": 0.4, "group": "tip"}, tab="a")
    s1.autosaver.flush()
    end = s1.state
    s1.close()
    autosave_path(tmp_path / "bar.toml").unlink()  # killed before the autosave was written
    s2 = Session(Sandbox([tmp_path]))
    try:
        assert s2.recoverable() == ["bar.toml"]
        opened = s2.open("bar.toml")
        assert s2.scene == end.scene and s2.state.keyframe_ids == end.keyframe_ids
        assert any("unsaved scene" in n for n in opened["notices"]), opened["notices"]
        assert s2.undo("a")["changed"] and s2.undo("a")["changed"]
        assert not s2.scene.groups and not s2.scene.keyframes
    finally:
        s2.close()


def test_a_file_changed_on_disk_after_a_crash_keeps_the_old_journal(tmp_path):
    """Edits journaled but not saved, the editor killed before its autosave, then the scene
    file changed in another program: it opens as it is on disk, the notice says the unsaved
    edits are not applied, and they are kept as a scene of their own, the old journal (not
    deleted) as its undo history, as when the autosave exists."""
    path = bar_project(tmp_path, KEYS, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open(path.name)
    s1.edit({"op": "set", "section": "damping", "values": {"alpha": 0.7}})
    s1.close()
    autosave_path(path).unlink(missing_ok=True)  # killed before the autosave was written
    journal = history_path(path).read_text()
    path.write_text(path.read_text().replace("end = 1.0", "end = 1.5"))
    s2 = Session(Sandbox([tmp_path]))
    try:
        opened = s2.open(path.name)
        assert s2.scene == load_scene(path) and s2.scene.damping.alpha != 0.7
        notice = " ".join(opened["notices"])
        assert "changed outside the editor" in notice and "without them" in notice, notice
        kept = [p for p in tmp_path.iterdir() if p.name.startswith("shot.unsaved-")]
        assert len(kept) == 1 and kept[0].name in notice
        assert load_scene(kept[0]).damping.alpha == 0.7
        assert history_path(kept[0]).read_text() == journal
    finally:
        s2.close()
    s3 = Session(Sandbox([tmp_path]))
    try:  # the edits open with their undo step
        s3.open(kept[0].name)
        assert s3.scene.damping.alpha == 0.7 and s3.histories.describe(DEFAULT_TAB)["can_undo"]
    finally:
        s3.close()


def test_a_file_changed_on_disk_after_an_autosave_is_not_overwritten(tmp_path):
    """Edits autosaved but not saved, the editor stopped, then the scene file changed in
    another program: it opens as it is on disk (not the autosave over it), the unsaved edits
    are kept as a scene of their own, and a Save writes the disk's version, nothing of the
    autosave. Before, the autosave was recovered over the changed file, said "the saved file
    is unchanged", and a Save overwrote the other program's change without asking."""
    path = bar_project(tmp_path, KEYS, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open(path.name)
    s1.edit({"op": "set", "section": "damping", "values": {"alpha": 0.7}})
    s1.autosaver.flush()
    s1.close()
    assert autosave_path(path).is_file()
    changed = path.read_text().replace("end = 1.0", "end = 1.5") + "# another program\n"
    path.write_text(changed)
    s2 = Session(Sandbox([tmp_path]))
    try:
        opened = s2.open(path.name)
        assert s2.scene == load_scene(path) and s2.scene.damping.alpha != 0.7
        notice = " ".join(opened["notices"])
        assert "changed outside the editor after edits that were not saved" in notice, notice
        assert "the saved file is unchanged" not in notice
        kept = [p for p in tmp_path.iterdir() if p.name.startswith(f"{path.stem}.unsaved-")]
        assert len(kept) == 1 and kept[0].name in notice
        assert load_scene(kept[0]).damping.alpha == 0.7  # the edits, as a scene
        assert not autosave_path(path).exists() and not s2.dirty
        other = load_scene(path)
        s2.save()  # writes the other program's scene (in the editor's own layout)
        assert load_scene(path) == other and other.time.end == 1.5
    finally:
        s2.close()
    # the same without a change on disk: the autosave is recovered
    s3 = Session(Sandbox([tmp_path]))
    try:
        s3.open(path.name)
        s3.edit({"op": "set", "section": "damping", "values": {"alpha": 0.9}})
        s3.autosaver.flush()
    finally:
        s3.close()
    s4 = Session(Sandbox([tmp_path]))
    try:
        opened = s4.open(path.name)
        assert s4.scene.damping.alpha == 0.9 and s4.dirty
        assert any("recovered unsaved edits" in n for n in opened["notices"])
    finally:
        s4.close()


def test_a_group_edit_that_an_absolute_key_would_not_fit_is_refused(tmp_path):
    """A group given another vertex count than its ``absolute`` key has rows: refused with
    the scene's message, nothing changed (before, it was taken, the group showed 0 vertices
    and Save wrote a file ``wiggly animate`` refuses)."""
    path = bar_project(tmp_path, KEYS, warp=False)
    session = Session(Sandbox([tmp_path]))
    try:
        session.open(path.name)
        session.edit({"op": "set_group", "name": "g", "indices": [0, 1, 2]})
        rows = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]]
        session.edit({"op": "add_keyframe", "time": 0.5, "group": "g",
                      "position": {"absolute": rows}})
        before, version = session.scene, session.version
        with pytest.raises(EditError) as err:
            session.edit({"op": "set_group", "name": "g", "indices": [0, 1, 2, 3, 4]})
        assert "position.absolute has 3 rows but group 'g' has 5 vertices" in str(err.value)
        assert session.scene == before and session.version == version
        session.edit({"op": "set_group", "name": "g", "indices": [4, 5, 6]})  # 3 still fit
        assert session.scene.groups["g"] != before.groups["g"]
    finally:
        session.close()


def test_editing_the_mesh_again_after_a_crash_points_to_its_unsaved_scene(tmp_path):
    """``wiggly edit bar.vtu``, edits, a crash before any save, then ``wiggly edit bar.vtu``
    again: a new scene (the old one may still be open in another editor), and a notice that
    says where the unsaved edits are; opening that scene brings them back."""
    bar_project(tmp_path, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open("bar.vtu")
    s1.edit({"op": "set_group", "name": "tip", "indices": [78, 79, 80]}, tab="a")
    s1.autosaver.flush()
    end = s1.scene
    s1.close()
    s2 = Session(Sandbox([tmp_path]))
    try:
        opened = s2.open("bar.vtu")
        assert opened["path"] == "bar-2.toml" and not s2.scene.groups
        assert any("already has a scene with unsaved edits, bar.toml" in n and
                   "Open bar.toml" in n for n in opened["notices"]), opened["notices"]
        s2.open("bar.toml")
        assert s2.scene == end
        s2.save()
    finally:
        s2.close()
    s3 = Session(Sandbox([tmp_path]))
    try:  # saved, no edits since: the mesh opened again points to it as well (it did not)
        notices = s3.open("bar.vtu")["notices"]
        assert any("already has a scene bar.toml;" in n and "Open bar.toml" in n
                   for n in notices), notices
    finally:
        s3.close()


def test_a_journal_that_cannot_be_replayed_is_dropped_with_a_notice(tmp_path):
    path = bar_project(tmp_path, KEYS, warp=False)
    s1 = Session(Sandbox([tmp_path]))
    s1.open(path.name)
    _edits(s1)
    s1.close()
    autosave_path(path).unlink(missing_ok=True)
    lines = history_path(path).read_text().splitlines()
    line = json.loads(lines[1])  # the first edit's record (alpha 0.7), tampered with
    line["rec"]["changes"][0][3]["alpha"] = 0.123
    lines[1] = json.dumps(line)
    history_path(path).write_text("\n".join(lines) + "\n")
    s2 = Session(Sandbox([tmp_path]))
    try:
        opened = s2.open(path.name)
        assert s2.scene == load_scene(path) and not s2.describe("a")["can_undo"]
        assert any("unreadable undo history of shot.toml" in n and "line 2" in n
                   for n in opened["notices"]), opened["notices"]
    finally:
        s2.close()


def test_an_edit_that_cannot_be_journaled_is_refused(tmp_path):
    """An edit is answered only once it is on the disk: if the journal cannot be written,
    the edit (or undo) is refused with the reason and the scene stays as it was."""
    path = bar_project(tmp_path, KEYS, warp=False)
    session = Session(Sandbox([tmp_path]))
    try:
        session.open(path.name)
        session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.7}})
        history_path(path).unlink()
        history_path(path).mkdir()  # a journal that cannot be appended to
        version, scene = session.version, session.scene
        for act in (lambda: session.edit({"op": "add_keyframe", "time": 0.9, "group": "mid"}),
                    lambda: session.undo()):
            with pytest.raises(EditError) as err:
                act()
            assert err.value.status == 507 and ".shot.history.jsonl" in str(err.value)
            assert session.version == version and session.scene == scene
            assert session.describe("api")["undo_label"] == "set damping.alpha"
        history_path(path).rmdir()
        assert session.undo()["changed"] and session.scene.damping.alpha == 0.5
    finally:
        session.close()


def test_a_failed_flush_leaves_no_line_behind(tmp_path, monkeypatch):
    """A journal line whose flush fails is taken back: the refused edit does not come back
    after a restart (the disk said nothing about it; a full disk cuts lines short)."""
    import wiggly.editor.history as history

    path = bar_project(tmp_path, KEYS, warp=False)
    session = Session(Sandbox([tmp_path]))
    try:
        session.open(path.name)
        session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.7}})
        before = history_path(path).read_bytes()

        def failing_fsync(fd):
            raise OSError(5, "Input/output error")

        monkeypatch.setattr(history.os, "fsync", failing_fsync)
        with pytest.raises(EditError) as err:
            session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.9}})
        assert err.value.status == 507 and "Input/output error" in str(err.value)
        monkeypatch.undo()
        assert history_path(path).read_bytes() == before
        assert session.scene.damping.alpha == 0.7
    finally:
        session.close()
    s2 = Session(Sandbox([tmp_path]))
    try:
        s2.open(path.name)
        assert s2.scene.damping.alpha == 0.7
        assert s2.describe("api")["undo_label"] == "set damping.alpha"
    finally:
        s2.close()
