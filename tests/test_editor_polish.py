"""What an animator tripped over in the editor (issue 25), each driven through the real page in
headless Chromium, with screenshots at 1280x800 and 1920x1080 checked for wrapped labels,
controls outside the window and overlaps: onion skins ghost only the selected groups, the
"recovered" bar goes away after Save, the transport bar fits at 1280 px with labelled onion
fields and error toasts clear of the dope sheet, the driver checkbox only in [drive] scenes,
messages naming keyframes by name, group and time.

``WIGGLY_SCREENSHOTS=DIR`` keeps the screenshots in DIR (default: the test's tmp_path).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from tests.editor_ui import (
    bar_project,
    editor_page,
    post,
    select_key,
    toast_saying,
    wait_final,
)
from tests.test_editor_drive import drive_project
from wiggly.editor import Sandbox, Session, serve
from wiggly.editor.session import autosave_path
from wiggly.editor.state import EditError
from wiggly.scene import load_scene

pytestmark = pytest.mark.browser

SIZES = ((1280, 800), (1920, 1080))
NAMED = """
[[keyframes]]
time = 0.25
group = "mid"
name = "lift"
position = { offset = [0.0, 0.02, 0.0] }
"""

# Every visible control of the header and the transport bar: its box, and the tops of the
# lines its text is laid out on (more than one: a wrapped label).
CONTROLS = """() => {
  const out = [];
  for (const bar of ['bar', 'transport']) {
    for (const el of document.getElementById(bar).children) {
      const r = el.getBoundingClientRect();
      if (!r.width || getComputedStyle(el).display === 'none') continue;
      const tops = new Set();
      const walk = document.createTreeWalker(el, NodeFilter.SHOW_TEXT);
      for (let n = walk.nextNode(); n; n = walk.nextNode()) {
        if (!n.textContent.trim()) continue;
        const range = document.createRange();
        range.selectNodeContents(n);
        for (const q of range.getClientRects()) tops.add(Math.round(q.top));
      }
      out.push({ bar, id: el.id || el.textContent.trim().slice(0, 20) || el.tagName,
                 x0: r.left, x1: r.right, y0: r.top, y1: r.bottom, lines: tops.size,
                 scroll: el.scrollWidth > el.clientWidth + 1 && el.tagName === 'LABEL' });
    }
  }
  return { controls: out, width: innerWidth, height: innerHeight };
}"""


def _box(page, selector: str) -> dict | None:
    return page.evaluate(f"""() => {{ const el = document.querySelector({selector!r});
      if (!el || el.hidden || getComputedStyle(el).display === 'none') return null;
      const r = el.getBoundingClientRect();
      return {{ x0: r.left, x1: r.right, y0: r.top, y1: r.bottom }}; }}""")


def _overlap(a: dict, b: dict) -> bool:
    return a["x0"] < b["x1"] - 0.5 and b["x0"] < a["x1"] - 0.5 and \
        a["y0"] < b["y1"] - 0.5 and b["y0"] < a["y1"] - 0.5


def check_layout(page, name: str, folder: Path) -> None:
    """Screenshot the page, then check that no label of the header or the transport bar wraps,
    every control is inside the window, the transport bar is one row whose controls do not
    overlap, and a toast covers neither the dope sheet nor the transport bar."""
    shots = Path(os.environ.get("WIGGLY_SCREENSHOTS", folder))
    shots.mkdir(parents=True, exist_ok=True)
    size = page.viewport_size
    page.screenshot(path=str(shots / f"{name}-{size['width']}x{size['height']}.png"))
    info = page.evaluate(CONTROLS)
    controls = info["controls"]
    for c in controls:
        assert c["lines"] <= 1 and not c["scroll"], f"{c['id']} wraps: {c}"
        assert 0 <= c["x0"] and c["x1"] <= info["width"] + 0.5, f"{c['id']} is cut off: {c}"
    transport = [c for c in controls if c["bar"] == "transport"]
    middle = [(c["y0"] + c["y1"]) / 2 for c in transport]
    assert max(middle) - min(middle) < 6, f"the transport bar wraps into rows: {transport}"
    for i, a in enumerate(transport):
        for b in transport[i + 1:]:
            assert not _overlap(a, b), f"{a['id']} overlaps {b['id']}"
    toast = _box(page, "#toast")
    if toast is not None:
        for other in ("#dopesheet", "#transport", "#status", "#bar"):
            assert not _overlap(toast, _box(page, other)), f"the toast covers {other}"


@pytest.fixture
def bar(tmp_path):
    server = serve(bar_project(tmp_path, NAMED, warp=False))
    try:
        yield server
    finally:
        server.stop()


def _ghosted(page) -> set[int]:
    info = page.evaluate("window.wiggly.onionInfo()")
    assert info, "no onion skins are drawn"
    vertices = {tuple(s["vertices"]) for s in info}
    assert len(vertices) == 1  # every skin draws the same faces
    return set(vertices.pop())


def _pick_group(page, name: str, add: bool = False) -> None:
    """Click the group in the list (Shift: add it to the selected ones) until it is selected
    (a state refresh may redraw the list under the click)."""
    from playwright.sync_api import TimeoutError as PageTimeout

    done = f"window.wiggly.S.selectedGroup === {name!r} && window.wiggly.S.groups.has({name!r})"
    for _attempt in range(3):
        if page.evaluate(done):
            return
        page.click(f"#groups li[data-group={name}] .name", modifiers=["Shift"] if add else [])
        try:
            page.wait_for_function(done, timeout=10_000)
            return
        except PageTimeout:  # the click missed a redrawn list: again
            continue
    raise AssertionError(f"cannot select group {name!r} in the list")


def test_onion_skins_ghost_only_the_selected_groups(chromium, bar, tmp_path):
    session = bar.session
    faces = session.surface.faces
    groups = {k: set(v.tolist()) for k, v in session.groups().items()}

    def touching(names):  # the vertices of the faces touching the groups, computed here
        mark = np.zeros(session.surface.n_vertices, bool)
        for g in names:
            mark[list(groups[g])] = True
        return set(np.unique(faces[mark[faces].any(axis=1)]).tolist())

    for width, height in SIZES:
        with editor_page(chromium, bar.url, width, height) as (page, errors):
            wait_final(page)
            page.locator("#canvas").click(position={"x": 5, "y": 5})
            page.keyboard.press("o")
            page.wait_for_function("window.wiggly.onionInfo().length > 0")
            page.evaluate("window.wiggly.setTime(0.5)")
            assert _ghosted(page) == set(np.unique(faces).tolist())  # none selected: all
            _pick_group(page, "right")
            ghosted = _ghosted(page)
            assert ghosted == touching(["right"]) and len(ghosted) < 0.4 * len(faces)
            _pick_group(page, "mid", add=True)  # a second group joins the ghosts
            assert _ghosted(page) == touching(["right", "mid"])
            check_layout(page, "onion-selected", tmp_path)
            assert not errors, errors


def test_the_recovered_bar_goes_away_after_save(chromium, tmp_path):
    path = bar_project(tmp_path, warp=False)
    autosave_path(path).write_text(path.read_text().replace("young = 1e6", "young = 2e6"))
    server = serve(path)
    try:
        for width, height in SIZES:
            with editor_page(chromium, server.url, width, height) as (page, errors):
                if width == SIZES[0][0]:
                    page.wait_for_selector("#notices:not([hidden])")
                    assert "recovered unsaved edits" in page.locator("#notices-text").text_content()
                    check_layout(page, "recovered", tmp_path)
                    page.locator("#canvas").click(position={"x": 5, "y": 5})
                    page.keyboard.press("Control+s")
                    page.wait_for_function("!window.wiggly.S.desc.dirty")
                    page.wait_for_selector("#notices", state="hidden")
                    assert "young = 2000000.0" in path.read_text()
                else:  # a page opened after the save is not told either
                    page.wait_for_function("window.wiggly.S.desc && !window.wiggly.S.desc.dirty")
                    assert page.locator("#notices").is_hidden()
                    assert not page.evaluate("window.wiggly.S.desc.notices.length")
                    check_layout(page, "saved", tmp_path)
                assert not errors, errors
    finally:
        server.stop()


def test_the_transport_bar_fits_and_toasts_leave_the_dope_sheet_alone(chromium, tmp_path):
    path, _ = drive_project(tmp_path)  # the most crowded bar: it has the driver checkbox
    server = serve(path)
    try:
        for width, height in SIZES:
            with editor_page(chromium, server.url, width, height) as (page, errors):
                wait_final(page)
                # the onion fields say what they are, in text one can see
                for field, words in (("#onion-count", "ghosts"), ("#onion-step", "every")):
                    label = page.locator(f"label:has({field})")
                    assert label.is_visible() and words in label.inner_text()
                # a real error: free modes must be a positive integer (a driven scene shows
                # the free parts' modes, not the body's, which it does not solve with)
                assert not page.is_visible("[data-set='simulation.modes']")
                modes = "[data-set='drive.free_modes']"
                page.fill(modes, "-3")
                page.press(modes, "Enter")
                page.wait_for_function("!document.querySelector('#toast').hidden && "
                                       "document.querySelector('#toast').className === 'err'")
                check_layout(page, "error-toast", tmp_path)
                ruler = _box(page, "#dopesheet")
                page.mouse.click(ruler["x0"] + 0.75 * (ruler["x1"] - ruler["x0"]),
                                 ruler["y0"] + 6)  # the ruler under where toasts were
                page.wait_for_function("window.wiggly.S.t > 0.6")  # the click reached it
                assert not errors, errors
    finally:
        server.stop()


def test_the_driver_checkbox_shows_only_in_scenes_with_a_driver(chromium, tmp_path):
    driven, _ = drive_project(tmp_path)
    plain = tmp_path / "plain.toml"
    plain.write_text(driven.read_text().split("[drive]")[0])
    for path, shown in ((plain, False), (driven, True)):
        server = serve(path)
        try:
            for width, height in SIZES:
                with editor_page(chromium, server.url, width, height) as (page, errors):
                    wait_final(page)
                    assert page.locator("#driver").is_visible() == shown
                    assert page.locator("#driver-toggle").is_visible() == shown
                    check_layout(page, f"driver-{shown}", tmp_path)
                    assert not errors, errors
        finally:
            server.stop()


def test_messages_name_keyframes_and_read_well(chromium, bar, tmp_path):
    url = bar.url
    with editor_page(chromium, url, *SIZES[0]) as (page, errors):
        wait_final(page)
        # the named key (id 1): moved in its panel; the undo button names it, not its id
        select_key(page, 1)
        page.fill("#key-time", "0.3")
        page.press("#key-time", "Enter")
        page.wait_for_function("window.wiggly.S.desc.can_undo")
        title = page.get_attribute("#btn-undo", "title")
        assert "move keyframe 'lift' (mid at 0.25 s) to 0.3 s" in title, title
        # an unnamed key: its group and time
        select_key(page, 0)
        page.fill("#key-time", "0.6")
        page.press("#key-time", "Enter")
        page.wait_for_function("window.wiggly.S.desc.undo_label.includes('right at 0.5 s')")
        # damping changed here, then in another tab: undo says what changed, grammatically
        alpha = "[data-set='damping.alpha']"
        page.fill(alpha, "0.7")
        page.press(alpha, "Enter")
        page.wait_for_function("window.wiggly.S.desc.scene.damping.alpha === 0.7")
        status, _ = post(url, "/api/edit", {"op": "set", "section": "damping",
                                             "values": {"alpha": 0.9}}, tab="other")
        assert status == 200
        page.wait_for_function("window.wiggly.S.desc.scene.damping.alpha === 0.9")
        page.locator("#canvas").click(position={"x": 5, "y": 5})
        page.keyboard.press("Control+z")
        text = toast_saying(page, "cannot undo")
        assert "the damping settings were changed since" in text, text
        assert "settings was" not in text
        check_layout(page, "messages", tmp_path)
        # a keyframe changed in the other tab: named by its group and time, not its id
        status, _ = post(url, "/api/edit", {"op": "update_keyframe", "id": 0, "time": 0.7},
                         tab="other")
        assert status == 200
        page.wait_for_function("window.wiggly.S.desc.scene.keyframes.find((k) => k.id === 0)"
                               ".time === 0.7")
        page.keyboard.press("Control+z")
        page.wait_for_function("document.querySelector('#toast').textContent.includes("
                               "'keyframe right at')")
        text = page.locator("#toast").text_content()
        assert "the keyframe right at 0.6 s was changed since" in text, text
        assert "keyframe 0" not in text
        assert not errors, errors


def test_labels_of_keyframe_edits(tmp_path):
    """The labels the undo button shows, without a browser."""
    bar_project(tmp_path, NAMED, warp=False)
    session = Session(Sandbox([tmp_path]))
    try:
        session.open("shot.toml")
        session.edit({"op": "add_keyframe", "time": 0.75, "group": "right"})
        assert session.describe("api")["undo_label"] == "add keyframe right at 0.75 s"
        session.edit({"op": "update_keyframe", "id": 1, "stiffness": 1e5})
        assert session.describe("api")["undo_label"] == "edit keyframe 'lift' (mid at 0.25 s)"
        session.edit({"op": "delete_keyframe", "id": 0})
        assert session.describe("api")["undo_label"] == "delete keyframe right at 0.5 s"
        session.edit({"op": "set_group", "name": "tip", "indices": [1, 2]}, tab="b")
        session.edit({"op": "delete_group", "name": "tip"}, tab="c")
        with pytest.raises(EditError) as err:
            session.undo("b")
        assert "group 'tip' was changed since" in str(err.value)
        # a keyframe moved in tab d and deleted in tab e: the undo says it was deleted
        session.edit({"op": "update_keyframe", "id": 1, "time": 0.4}, tab="d")
        session.edit({"op": "delete_keyframe", "id": 1}, tab="e")
        with pytest.raises(EditError) as err:
            session.undo("d")
        text = str(err.value)
        assert "cannot undo \"move keyframe 'lift' (mid at 0.25 s) to 0.4 s\"" in text, text
        assert "that keyframe was deleted since" in text and "None" not in text, text
    finally:
        session.close()


def test_save_asks_before_overwriting_a_change_made_on_disk(chromium, tmp_path):
    """Ctrl+S over a scene file changed in another program asks first (the server's 409 in
    a confirm): declined, the other program's file stays; accepted, the editor's scene is
    saved."""
    path = bar_project(tmp_path, warp=False)
    server = serve(path)
    try:
        with editor_page(chromium, server.url, *SIZES[0]) as (page, errors):
            wait_final(page)
            theirs = (path.read_text().replace("young = 1e6", "young = 3e6")
                      + "# changed in another program\n")
            assert theirs.count("young = 3e6") == 1
            path.write_text(theirs)
            asked = []

            def answer(dialog, accept):
                asked.append(dialog.message)
                dialog.accept() if accept else dialog.dismiss()

            def until(check, what):
                for _ in range(300):
                    if check():
                        return
                    page.wait_for_timeout(100)
                raise AssertionError(f"timed out waiting for {what}")

            page.once("dialog", lambda d: answer(d, False))
            page.locator("#canvas").click(position={"x": 5, "y": 5})
            page.keyboard.press("Control+s")
            until(lambda: asked, "the question")
            assert "was changed on disk" in asked[0]
            page.wait_for_timeout(300)  # a save after the answer would land by now
            assert path.read_text() == theirs
            page.once("dialog", lambda d: answer(d, True))
            page.keyboard.press("Control+s")
            until(lambda: path.read_text() != theirs, "the save")
            assert len(asked) == 2
            # the editor's scene, in the file's own layout (its comments kept)
            assert load_scene(path) == server.session.scene
            assert server.session.scene.material.young == 1e6
            assert not errors, errors
    finally:
        server.stop()


def test_a_long_scene_name_keeps_the_header_one_row(chromium, tmp_path):
    """At 1280 x 800 the header stays one row for a long scene file name: the name is cut
    with an ellipsis, and its tooltip has the whole name."""
    path = bar_project(tmp_path, warp=False, name="a_rather_long_scene_name_v2.toml")
    server = serve(path)
    try:
        with editor_page(chromium, server.url, *SIZES[0]) as (page, errors):
            page.wait_for_function("window.wiggly.S.desc && window.wiggly.S.desc.open")
            rows = page.evaluate("""() => {
                const mid = (e) => {
                  const r = e.getBoundingClientRect(); return r.top + r.height / 2; };
                const kids = [...document.querySelectorAll('#bar > *')]
                  .filter((e) => e.offsetParent);
                return Math.max(...kids.map(mid)) - Math.min(...kids.map(mid)); }""")
            assert rows < 6, f"the header wraps into rows ({rows:.0f} px between centres)"
            title = page.locator("#file-name").get_attribute("title")
            assert "a_rather_long_scene_name_v2.toml" in title
            assert not errors, errors
    finally:
        server.stop()


def test_a_refused_group_name_keeps_the_rename_prompt(chromium, tmp_path):
    """Renaming a group to a name taken already is refused with the server's message; the
    prompt stays open with what was typed (it closed and lost it before), as a refused Save
    as does; a free name then renames it and closes the prompt."""
    server = serve(bar_project(tmp_path, warp=False))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            page.locator("#groups li[data-group='left'] .name").dblclick()
            page.wait_for_selector("#modal:not([hidden])")
            field = page.locator("#modal-body input")
            field.fill("right")
            page.locator("#modal-ok").click()
            toast_saying(page, "exists")
            assert page.locator("#modal").is_visible() and field.input_value() == "right"
            field.fill("base")
            page.locator("#modal-ok").click()
            page.wait_for_selector("#modal", state="hidden")
            page.wait_for_selector("#groups li[data-group='base']")
            groups = server.session.scene.groups
            assert "base" in groups and "left" not in groups
            assert not errors, errors
    finally:
        server.stop()


def test_an_edit_the_stopped_server_cannot_answer_says_so(chromium, tmp_path):
    """The server stops; an edit made in the page then says that the editor server did not
    answer and the change may not be made (it said "Failed to fetch")."""
    server = serve(bar_project(tmp_path, warp=False))
    with editor_page(chromium, server.url) as (page, errors):
        wait_final(page)
        server.stop()
        end = "[data-set='time.end']"
        page.fill(end, "1.5")
        page.press(end, "Enter")
        text = toast_saying(page, "did not answer")
        assert "Failed to fetch" not in text and "may not be made" in text, text
        assert not errors, errors  # the failed request is handled, not an uncaught error
