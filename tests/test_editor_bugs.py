"""The eight bugs of issue 16, each driven through the real page (headless Chromium) or the
server, as a user or another program would meet it."""

from __future__ import annotations

import json
import os
import socket
import threading
import time

import numpy as np
import pytest

from tests.editor_ui import (
    bar_project,
    editor_page,
    get,
    grab_gizmo,
    latest_final,
    move_along,
    next_frame,
    post,
    select_key,
    toast_saying,
    wait_final,
)
from wiggly import limits
from wiggly.editor import EditorServer, Sandbox, Session, serve
from wiggly.editor.session import autosave_path

pytestmark = pytest.mark.browser


def _status(page) -> str:
    return page.locator("#status-text").text_content()


# ----------------------------------------------------------------------------------------------
# 1. the server stops answering while fTetWild runs


def test_1_server_answers_and_shows_progress_while_tetrahedralizing(chromium, tmp_path,
                                                                     monkeypatch):
    """fTetWild runs in a child process: while it works, the server answers and the page shows
    its progress with the elapsed time."""
    import trimesh

    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))  # tetrahedralize afresh
    trimesh.creation.icosphere(subdivisions=3, radius=0.3).export(tmp_path / "ball.obj")
    server = serve(None, roots=[tmp_path])
    events = server.session.bus.subscribe()
    try:
        with editor_page(chromium, server.url, mesh=False) as (page, errors):
            page.wait_for_selector("#modal:not([hidden])")  # nothing open: the Open dialog
            page.fill("#modal-body input[type=text]", "ball.obj")
            page.click("#modal-ok")
            deadline = time.time() + 10  # the page's Open request is on its way to the server
            while json.loads(get(server.url + "api/state")[0])["version"] < 1:
                assert time.time() < deadline, "the Open request did not reach the server"
                time.sleep(0.02)
            running_for, done, during, shown = 0.0, False, 0, []
            deadline = time.time() + 120
            while not done and time.time() < deadline:
                t_sent = running_for
                r = get(server.url + "api/state")[0]
                assert json.loads(r)["version"] >= 1
                while not events.empty():
                    e = events.get_nowait()
                    if e["type"] != "physics":
                        continue
                    if e["stage"] == "mesh" and "tetrahedralizing" in e["message"]:
                        running_for = max(running_for, e["elapsed"])
                    elif e["stage"] != "mesh" or "tets" in e["message"]:
                        done = True  # the tet mesh arrived (or failed)
                if not done and t_sent >= 1.0:
                    during += 1  # sent after 1 s of fTetWild, answered before it ended
                    shown.append(page.locator("#phys-state").text_content())
            assert done, "no tet mesh within 120 s"
            assert server.session.physics.preparer.pid not in (None, os.getpid())
            assert during >= 3, (during, running_for)
            assert any("tetrahedralizing ball.obj" in s and float(s.split("…")[1].split()[0])
                       >= 1.0 for s in shown), shown
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 2. Esc during a gizmo drag


def _start_drag(page, key_id: int = 0):
    select_key(page, key_id)
    page.keyboard.press("w")
    page.wait_for_function("window.wiggly.S.posing && window.wiggly.S.posing.mode === "
                           "'translate'")
    x, y, h = grab_gizmo(page, "Y")
    move_along(page, x, y, h, 60)
    page.wait_for_function("window.wiggly.S.frames.meta.request === 'drag'", timeout=30_000)


def test_2_escape_during_a_drag_leaves_nothing_behind(chromium, tmp_path):
    """Select a keyframe, W, drag the Y arrow 60 px and hold, Esc, release: the scene, the tab,
    its status and a newly opened tab all show the scene as it was."""
    server = serve(bar_project(tmp_path))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            before, version = server.session.scene, server.session.version
            _start_drag(page)
            assert page.evaluate("window.wiggly.S.dragging")
            page.keyboard.press("Escape")
            page.mouse.up()
            assert server.session.scene == before and server.session.version == version
            page.wait_for_function("!window.wiggly.S.dragging && window.wiggly.S.committing "
                                   "=== null")
            meta = wait_final(page)
            page.wait_for_function("!document.querySelector('#status-text').textContent"
                                   ".startsWith('solving')")
            assert "warped" in _status(page), _status(page)
            frames, server_meta = latest_final(server.url)
            shown = np.asarray(page.evaluate("Array.from(window.wiggly.S.frames.data)"))
            assert meta["id"] == server_meta["id"]
            assert np.array_equal(shown.reshape(frames.shape), frames)
            # the gizmo is back on the keyframe's target, and no undo step was made
            assert np.allclose(page.evaluate("window.wiggly.rigidOfPose().translation"),
                               [0, 0.05, 0], atol=1e-6)
            assert not page.evaluate("window.wiggly.S.desc.can_undo")
            with editor_page(chromium, server.url) as (other, other_errors):
                assert wait_final(other)["id"] == server_meta["id"]
                assert not other_errors, other_errors
            assert not errors, errors
    finally:
        server.stop()


def test_2_keyframe_deleted_by_another_tab_during_a_drag(chromium, tmp_path):
    """Another tab deletes the dragged keyframe: the drag ends, this tab says why, and it
    shows the final frames of the scene without it."""
    server = serve(bar_project(tmp_path))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            _start_drag(page)
            st, r = post(server.url, "api/edit", {"op": "delete_keyframe", "id": 0}, tab="other")
            assert st == 200 and r["changed"]
            page.wait_for_function("!window.wiggly.S.dragging && "
                                   "window.wiggly.S.desc.scene.keyframes.length === 0")
            toast_saying(page, "the keyframe being posed was deleted in another tab: the "
                               "move was not applied")  # not dropped without a word
            page.mouse.up()
            wait_final(page)
            # the linear frames come first, then the warped refinement: wait for the last
            page.wait_for_function("!document.querySelector('#status-text').textContent"
                                   ".startsWith('solving')")
            wait_final(page)
            assert "warped" in _status(page), _status(page)
            # the drag cancelled by the deletion re-announces the final frames under a newer
            # id, which the page may still be fetching
            newest = latest_final(server.url)[1]["id"]
            page.wait_for_function(f"window.wiggly.S.frames.meta.id >= {newest}")
            meta = page.evaluate("window.wiggly.S.frames.meta")
            assert meta["final"] and meta["version"] == server.session.version
            assert meta["id"] == latest_final(server.url)[1]["id"]
            assert server.session.scene.keyframes == []
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 3. a restarted server


def test_3_an_open_tab_follows_a_restarted_server(chromium, tmp_path):
    """The server is stopped and started again on the same port: the open tab takes the new
    process's frames (its sequence numbers start again)."""
    path = bar_project(tmp_path)
    server = serve(path)
    port = server.port
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            for _ in range(5):  # the old process's sequence numbers grow past the new one's
                post(server.url, "api/edit", {"op": "set", "section": "damping",
                                              "values": {"alpha": 0.5 + 0.1 * _}})
            wait_final(page)
            old = page.evaluate("window.wiggly.S.instance")
            server.stop()
            server = serve(path, port=port)
            assert server.session.instance != old
            st, _ = post(server.url, "api/edit", {"op": "set", "section": "material",
                                                  "values": {"young": 3e6}})
            assert st == 200
            # the page meets the new process by its frames or its state, whichever comes
            # first; until its state arrives, the old state and the old final frames still
            # agree with each other, so wait for the new state before the final frames
            page.wait_for_function(
                f"window.wiggly.S.desc && window.wiggly.S.desc.instance === "
                f"'{server.session.instance}'", timeout=30_000)
            meta = wait_final(page)
            assert meta["instance"] == server.session.instance
            assert meta["id"] == latest_final(server.url)[1]["id"]
            assert page.evaluate("window.wiggly.S.desc.scene.material.young") == 3e6
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 4. 500s instead of 4xx


def _raw(port: int, request: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
        conn.sendall(request)
        data = b""
        while chunk := conn.recv(65536):  # the server closes the connection after an error
            data += chunk
        return data


def test_4_nul_paths_and_deep_json_are_client_errors(tmp_path):
    session = Session(Sandbox([tmp_path]))
    server = EditorServer(session).start()
    try:
        for path in (b"/a\x00b.js", b"/vendor/\x00", b"/\x00"):
            head = _raw(server.port, b"GET " + path + b" HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 404"), head[:80]
        for depth in (40, 100_000):  # beyond our limit; beyond the parser's recursion
            body = b"[" * depth + b"]" * depth
            head = _raw(server.port, b"POST /api/edit HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                        b"Content-Type: application/json\r\nContent-Length: "
                        + str(len(body)).encode() + b"\r\n\r\n" + body)
            assert head.startswith(b"HTTP/1.1 400"), head[:80]
            assert b"nested deeper than" in head
        st, r = post(server.url, "api/edit", {"op": "set", "section": "time",
                                              "values": {"end": [[[[[[[[1]]]]]]]]}})
        assert st in (400, 409) and r["error"]  # shallow enough: refused by the checks
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 5. absurd values


@pytest.mark.parametrize(("section", "values", "says"), [
    ("time", {"end": 1e6}, f"at most {limits.MAX_DURATION:g} s"),
    ("time", {"fps": 1e5}, f"{limits.MAX_FPS:g}"),
    ("time", {"end": 3000.0, "fps": 60}, f"more than {limits.MAX_FRAMES}"),
    ("simulation", {"modes": 10**6}, f"in [1, {limits.MAX_MODES}]"),
    ("mesh", {"resolution": 10**5}, f"in [{limits.MIN_RESOLUTION}, {limits.MAX_RESOLUTION}]"),
    ("mesh", {"edge_length": 1e-6}, f"at most {limits.MAX_RESOLUTION}"),
])
def test_5_absurd_settings_are_refused(tmp_path, section, values, says):
    server = serve(bar_project(tmp_path))
    try:
        before = server.session.scene
        st, r = post(server.url, "api/edit", {"op": "set", "section": section,
                                              "values": values})
        assert st == 400 and says in r["error"], r
        assert server.session.scene == before
    finally:
        server.stop()


def test_5_huge_names_and_too_many_keyframes_are_refused(tmp_path):
    server = serve(bar_project(tmp_path))
    try:
        st, r = post(server.url, "api/edit", {"op": "update_keyframe", "id": 0,
                                              "name": "x" * (7 * 2**20 // 8)})
        assert st == 400 and f"at most {limits.MAX_NAME_LENGTH}" in r["error"], r["error"][:200]
        st, r = post(server.url, "api/edit", {"op": "set_group", "indices": [1],
                                              "name": "g" * (limits.MAX_NAME_LENGTH + 1)})
        assert st == 400
        ops = [{"op": "add_keyframe", "time": 0.5, "group": "mid"}] * limits.MAX_KEYFRAMES
        st, r = post(server.url, "api/edit", {"op": "batch", "ops": ops})
        assert st == 400 and f"at most {limits.MAX_KEYFRAMES}" in r["error"]
        auto = autosave_path(tmp_path / "shot.toml")
        assert not auto.exists() or auto.stat().st_size < 10_000
        assert len(server.session.scene.keyframes) == 1
    finally:
        server.stop()


def test_5_a_refused_value_is_explained_in_the_page(chromium, tmp_path):
    server = serve(bar_project(tmp_path))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            end = "[data-set='time.end']"
            page.fill(end, "1e6")
            page.press(end, "Enter")
            # the toast that answers the edit (the soft bar's sag notice may come first)
            message = toast_saying(page, "at most")
            assert f"at most {limits.MAX_DURATION:g} s" in message, message
            assert "shots may last at most" in _status(page)
            page.wait_for_function(f"document.querySelector(\"{end}\").value === '1'")
            assert server.session.scene.time.end == 1.0
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 6. a scene at rest says "not converged"


def test_6_a_scene_at_rest_says_converged(chromium, tmp_path):
    """The bar hangs at rest from its fixed end, no keyframes: its objective is zero (up to
    rounding), and the warped solve must report convergence, not stop after its iteration
    limit."""
    path = bar_project(tmp_path)
    path.write_text(path.read_text().split("[[keyframes]]")[0])
    server = serve(path)
    try:
        with editor_page(chromium, server.url) as (page, _errors):
            meta = wait_final(page, timeout=120_000)
            assert meta["stage"] == "warped"
            page.wait_for_function("document.querySelector('#status-text').textContent"
                                   ".startsWith('warped:')")
            assert "converged in" in _status(page), _status(page)
            assert meta["converged"]
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 7. recovery is silent in the page


def test_7_recovered_edits_are_shown_in_the_page(chromium, tmp_path):
    path = bar_project(tmp_path)
    auto = autosave_path(path)
    auto.write_text(path.read_text().replace("young = 1e6", "young = 2e6"))
    server = serve(path)
    try:
        with editor_page(chromium, server.url) as (page, errors):
            page.wait_for_selector("#notices:not([hidden])")
            text = page.locator("#notices-text").text_content()
            assert "recovered unsaved edits to shot.toml: set material.young = 2e+06" in text, text
            assert page.evaluate("window.wiggly.S.desc.dirty")
            assert page.evaluate("window.wiggly.S.desc.scene.material.young") == 2e6
            page.click("#btn-notices")
            assert page.locator("#notices").is_hidden()
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# 8. the latency figure misses updates


def test_8_release_latency_counts_frames_that_come_before_the_answer(chromium, tmp_path):
    """The edit's answer is held back until the page has fetched the edit's frames: the release
    is still measured, from those frames."""
    server = serve(bar_project(tmp_path))
    session = server.session
    edit, frames = session.edit, session.frames
    fetched: dict[int, threading.Event] = {}

    def frames_seen(frame_id):
        fs = frames(frame_id)
        fetched.setdefault(fs.version, threading.Event()).set()
        return fs

    def edit_answered_late(op, tab="api"):
        r = edit(op, tab)
        if r.get("changed"):
            fetched.setdefault(r["version"], threading.Event()).wait(30)
        return r

    session.frames, session.edit = frames_seen, edit_answered_late
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            select_key(page, 0)
            page.keyboard.press("w")
            x, y, h = grab_gizmo(page, "Y")
            version = session.version
            move_along(page, x, y, h, 40)
            page.mouse.up()
            page.wait_for_function("window.wiggly.latencies.some((l) => l.first)",
                                   timeout=30_000)
            first = page.evaluate("window.wiggly.latencies.find((l) => l.first)")
            version += 1  # the drag's edit
            assert first["version"] == version == session.version
            # the page asked for the frames before the edit's answer came back (the server held
            # the answer until then), and the release was measured all the same
            assert first["requested"] <= first["applied"] <= first["ms"]
            assert first["posted"] is None or first["posted"] > first["requested"]
            next_frame(page, 2)
            assert fetched[version].is_set()
            assert not errors, errors
    finally:
        server.stop()


# ----------------------------------------------------------------------------------------------
# a value typed in a field without Enter was lost on reload


def test_a_value_typed_without_enter_is_kept_on_reload(chromium, tmp_path):
    """Damping typed in its field, then the page reloaded without Enter or leaving the field:
    the value is an edit of the scene (autosaved, undoable), not lost."""
    path = bar_project(tmp_path, warp=False)
    server = serve(path)
    try:
        with editor_page(chromium, server.url) as (page, errors):
            alpha = "[data-set='damping.alpha']"
            page.click(alpha)
            page.fill(alpha, "0.7")
            page.reload()
            page.wait_for_function("window.wiggly && window.wiggly.ready && "
                                   "window.wiggly.S.desc.scene.damping.alpha === 0.7")
            assert page.evaluate("window.wiggly.S.desc.undo_label") == "set damping.alpha"
            assert page.input_value(alpha) == "0.7"
            server.session.autosaver.flush()
            assert "alpha = 0.7" in autosave_path(path).read_text()
            assert not errors, errors
    finally:
        server.stop()


def test_a_job_cut_short_does_not_read_a_descriptor_reused_elsewhere():
    """Closing the editor kills the physics child while a job waits for its reply on
    another thread.  The child's pipe closes, and the process may reuse its descriptor
    number at once (a new `wiggly edit` started by a test, a user's subprocess): the job must
    not read from it.  A closed session's job read a new process's whole stderr that way."""
    import subprocess
    import sys

    from wiggly.editor.physics import Preparer

    class Silent(Preparer):  # a child that takes the job and never answers
        def start(self) -> None:
            with self._lock:
                if self._closed or self._proc is not None:
                    return
                self._proc = subprocess.Popen(
                    [sys.executable, "-c", "import time; time.sleep(60)"],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)

    preparer = Silent()
    number = preparer._proc.stdout.fileno()
    waiting, reused = threading.Event(), threading.Event()
    ended: list = []

    def status(_) -> None:  # busy telling the page while the session closes
        waiting.set()
        reused.wait(10)

    def job() -> None:
        try:
            preparer.call(("prepare",), status, lambda: False)
        except Exception as err:  # the child is gone: its error, whichever it is
            ended.append(err)

    worker = threading.Thread(target=job, daemon=True)
    worker.start()
    assert waiting.wait(10)  # the job waits for the child's reply
    preparer.close()  # kills the child and closes its pipe
    r, w = os.pipe()  # the same number, now another pipe's, with data in it
    if w == number:
        w, first = os.dup(w), w
        os.close(first)
    if r != number:
        os.dup2(r, number)
        os.close(r)
    os.write(w, b"0123456789abcdef" * 4)
    reused.set()
    worker.join(10)
    assert not worker.is_alive() and ended
    os.set_blocking(number, False)
    try:
        assert os.read(number, 1024) == b"0123456789abcdef" * 4  # nobody else read it
    finally:
        os.close(number)
        os.close(w)


@pytest.mark.parametrize("warp", [False, True])
def test_a_surface_that_stays_straight_is_a_notice_as_in_the_cli(tmp_path, warp):
    """A box of 12 triangles fixed at one end bends under gravity while its long surface
    edges stay straight: wiggly animate warns of it, and the editor now says it too, for
    linear and warped scenes (a review's worm, silent in the editor)."""
    import trimesh

    from tests.test_editor_drive import _notices

    trimesh.creation.box(extents=(1.0, 0.1, 0.1)).apply_translation((0.5, 0.0, 0.0)).export(
        tmp_path / "slab.obj")
    said, seen = _notices(tmp_path / "shot.toml", f"""
[mesh]
path = "slab.obj"
resolution = 8
[material]
young = 2e5
[simulation]
modes = 6
warp = {str(warp).lower()}
fixed = ["left"]
[groups.left]
box = {{ min = [-0.01, -1.0, -1.0], max = [0.01, 1.0, 1.0] }}
[time]
end = 0.5
fps = 10
""", "which stay straight")
    assert said is not None, seen
    assert "subdivide the surface where it bends" in said["message"]


def test_a_mesh_warning_stays_in_the_notices_bar(tmp_path):
    """A mesh in millimetres read as metres is warned about while it is tetrahedralized: a
    toast of 3.5 s during a long wait was easy to miss (a review did), so the warning is
    also kept in the notices a page shows, also a page opened later."""
    import trimesh

    from tests.test_editor_drive import _session_final

    trimesh.creation.box(extents=(300.0, 40.0, 40.0)).export(tmp_path / "part.obj")
    session = Session(Sandbox([tmp_path]))
    try:
        session.open("part.obj")
        _session_final(session)
        notes = session.describe()["notices"]
        assert any("the mesh is 30" in n and "scale it by 0.001" in n for n in notes), notes
    finally:
        session.close()
