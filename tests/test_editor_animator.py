"""What animators expect of the editor (issue 16), end to end in headless Chromium with real
mouse and keyboard events: the dope sheet, onion skins and motion paths, the gizmo's axis
keys, typed values, snapping and pivots, visible-only selection, views, the preview range
and playback speed, and undo per tab across a restart."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from tests.editor_ui import (
    LOADED,
    bar_project,
    box_select,
    click_time,
    editor_page,
    grab_gizmo,
    grab_ring,
    latest_final,
    move_along,
    next_frame,
    post,
    select_key,
    toast_saying,
    wait_final,
)
from wiggly.editor import serve

pytestmark = pytest.mark.browser

MORE_KEYS = """
[[keyframes]]
time = 0.5
group = "mid"
position = { offset = [0.0, 0.02, 0.0] }

[[keyframes]]
time = 0.2
group = "mid"
position = "rest"
"""


@pytest.fixture
def editor(chromium, tmp_path):
    """The bar with keyframes right@0.5 (id 0), mid@0.5 (id 1), mid@0.2 (id 2), linear, open
    in a page showing its final frames; yields (server, page)."""
    server = serve(bar_project(tmp_path, MORE_KEYS, warp=False))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            yield server, page
            assert not errors, errors
    finally:
        server.stop()


def _keys(server) -> dict[int, tuple]:
    s = server.session.state
    return {i: (k.group, k.time, k.position) for i, k in zip(s.keyframe_ids, s.scene.keyframes,
                                                             strict=True)}


def _shift_click(page, x: float, y: float) -> None:
    page.keyboard.down("Shift")
    page.mouse.click(x, y)
    page.keyboard.up("Shift")


def _undo(page, server, version: int) -> None:
    page.keyboard.press("Control+z")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")


# ----------------------------------------------------------------------------------------------
# dope sheet


def test_dope_sheet_has_one_row_per_group(editor):
    _server, page = editor
    a = page.evaluate("window.wiggly.timePoint(0.5, 'right')")
    b = page.evaluate("window.wiggly.timePoint(0.5, 'mid')")
    c = page.evaluate("window.wiggly.timePoint(0.5, 'left')")
    assert a["x"] == b["x"] and len({a["y"], b["y"], c["y"]}) == 3  # same time, three rows
    for group, key in (("right", 0), ("mid", 1)):  # keys at one time no longer overlap
        click_time(page, 0.5, group)
        page.wait_for_function(f"window.wiggly.S.selectedKey === {key}")
    click_time(page, 0.2, "mid")
    page.wait_for_function("window.wiggly.S.selectedKey === 2 && "
                           "Math.abs(window.wiggly.S.t - 0.2) < 1e-9")
    click_time(page, 0.2, "right")  # an empty spot: no key, the time moves there
    page.wait_for_function("window.wiggly.S.selectedKey === null && window.wiggly.S.keys.size "
                           "=== 0")


def test_dope_sheet_selects_and_moves_several_keys(editor):
    server, page = editor
    click_time(page, 0.5, "right")
    p = page.evaluate("window.wiggly.timePoint(0.2, 'mid')")
    _shift_click(page, p["x"], p["y"])
    page.wait_for_function("window.wiggly.S.keys.size === 2")
    q = page.evaluate("window.wiggly.timePoint(0.5, 'mid')")  # Shift+click adds, and removes
    _shift_click(page, q["x"], q["y"])
    page.wait_for_function("window.wiggly.S.keys.size === 3")
    _shift_click(page, q["x"], q["y"])
    page.wait_for_function("window.wiggly.S.keys.size === 2 && !window.wiggly.S.keys.has(1)")
    assert page.evaluate("[...window.wiggly.S.keys].sort()") == [0, 2]
    # drag one of them 0.2 s later: both move, in one step
    start = page.evaluate("window.wiggly.timePoint(0.5, 'right')")
    end = page.evaluate("window.wiggly.timePoint(0.7, 'right')")
    version = page.evaluate("window.wiggly.S.desc.version")
    page.mouse.move(start["x"], start["y"])
    page.mouse.down()
    page.mouse.move((start["x"] + end["x"]) / 2, start["y"], steps=3)
    page.mouse.move(end["x"], end["y"], steps=3)
    page.mouse.up()
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    keys = _keys(server)
    assert keys[0][1] == pytest.approx(0.7) and keys[2][1] == pytest.approx(0.4)
    assert keys[1][1] == 0.5  # not selected: stays
    assert page.evaluate("window.wiggly.S.desc.undo_label") == "move 2 keyframes"
    _undo(page, server, server.session.version)
    keys = _keys(server)
    assert (keys[0][1], keys[2][1]) == (0.5, 0.2)
    # box-select both keys at 0.5 (two rows), then delete them together
    a = page.evaluate("window.wiggly.timePoint(0.45, 'right')")
    b = page.evaluate("window.wiggly.timePoint(0.55, 'mid')")
    page.mouse.move(a["x"], a["y"] - 6)
    page.mouse.down()
    page.mouse.move(b["x"], b["y"] + 6, steps=4)
    page.mouse.up()
    page.wait_for_function("window.wiggly.S.keys.size === 2 && window.wiggly.S.keys.has(0) && "
                           "window.wiggly.S.keys.has(1)")
    version = server.session.version
    page.keyboard.press("Delete")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    assert list(_keys(server)) == [2]


def test_copy_paste_and_duplicate_keys(editor):
    server, page = editor
    click_time(page, 0.5, "right")
    p = page.evaluate("window.wiggly.timePoint(0.2, 'mid')")
    _shift_click(page, p["x"], p["y"])
    page.wait_for_function("window.wiggly.S.keys.size === 2")
    page.keyboard.press("Control+c")
    click_time(page, 0.6)  # the ruler: time 0.6
    page.wait_for_function("Math.abs(window.wiggly.S.t - 0.6) < 1e-9")
    version = server.session.version
    page.keyboard.press("Control+v")
    # the new pair, and the paste finished (its last step selects the last pasted key)
    page.wait_for_function(f"window.wiggly.S.desc.version > {version} && "
                           "window.wiggly.S.keys.size === 2 && window.wiggly.S.keys.has(3) && "
                           "window.wiggly.S.keys.has(4) && window.wiggly.S.selectedKey === 4")
    keys = _keys(server)
    new = {i: v for i, v in keys.items() if i >= 3}
    # same groups and targets, same spacing (0.3 s), the earliest at the current time
    assert sorted((g, round(t, 9), pos) for g, t, pos in new.values()) == sorted(
        [("mid", 0.6, keys[2][2]), ("right", 0.9, keys[0][2])])
    assert page.evaluate("window.wiggly.S.desc.undo_label") == "paste 2 keyframes"
    # Shift+D duplicates the pasted pair at the current time (not on top: one frame later)
    version = server.session.version
    page.keyboard.press("Shift+D")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    times = sorted(t for i, (g, t, _) in _keys(server).items() if i >= 5)
    assert times == pytest.approx([0.65, 0.95])
    _undo(page, server, server.session.version)
    assert len(_keys(server)) == 5


def test_keying_several_groups_at_once(editor):
    server, page = editor
    click_time(page, 0.8)
    page.wait_for_function("Math.abs(window.wiggly.S.t - 0.8) < 1e-9")
    page.click("#groups li[data-group=right] .name")
    page.keyboard.down("Shift")
    page.click("#groups li[data-group=mid] .name")
    page.keyboard.up("Shift")
    page.wait_for_function("window.wiggly.S.groups.size === 2")
    frames, meta = latest_final(server.url)  # what the page shows when K is pressed
    version = server.session.version
    page.keyboard.press("k")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    added = {g: (t, pos) for i, (g, t, pos) in _keys(server).items() if i >= 3}
    assert set(added) == {"right", "mid"} and all(t == 0.8 for t, _ in added.values())
    # at the current pose: each target is the least-squares rigid fit (Kabsch) of the group's
    # rest vertices to its vertices in the frames at 0.8 s
    from scipy.spatial.transform import Rotation

    rest = server.session.surface.vertices
    k = round((0.8 - meta["start"]) * meta["fps"])
    for g, (_, pos) in added.items():
        idx = server.session.groups()[g]
        c = np.asarray(pos.center)
        target = (rest[idx] - c) @ pos.matrix().T + c + pos.translation
        shown = frames[k][idx].astype(float)
        best, _ = Rotation.align_vectors(shown - shown.mean(0), rest[idx] - rest[idx].mean(0))
        fit = (rest[idx] - rest[idx].mean(0)) @ best.as_matrix().T + shown.mean(0)
        assert np.abs(target - fit).max() < 1e-5
    assert page.evaluate("window.wiggly.S.desc.undo_label") == "key 2 groups"
    _undo(page, server, server.session.version)
    assert len(_keys(server)) == 3


# ----------------------------------------------------------------------------------------------
# onion skins and motion paths


def test_onion_skins_show_earlier_and_later_frames(editor):
    server, page = editor
    page.fill("#onion-step", "2")
    page.press("#onion-step", "Enter")
    click_time(page, 0.5)
    page.wait_for_function("Math.abs(window.wiggly.S.t - 0.5) < 1e-9")
    next_frame(page, 2)
    plain = page.locator("#canvas").screenshot()
    page.keyboard.press("o")
    page.wait_for_function("window.wiggly.onionInfo().length === 6")
    skins = page.evaluate("window.wiggly.onionInfo()")
    frames, meta = latest_final(server.url)
    i = round(0.5 * meta["fps"])
    assert sorted(s["frame"] for s in skins) == [i - 6, i - 4, i - 2, i + 2, i + 4, i + 6]
    for s in skins:  # each ghost is the body at its frame, warm before and cool after
        assert np.allclose(s["vertex0"], frames[s["frame"]][0], atol=1e-6)
        assert s["past"] == (s["frame"] < i)
    near = {s["frame"]: s["opacity"] for s in skins}
    assert near[i - 2] > near[i - 6] > 0
    next_frame(page, 2)
    assert page.locator("#canvas").screenshot() != plain  # they are drawn
    page.keyboard.press("Space")  # they follow playback
    page.wait_for_function("window.wiggly.S.t > 0.6 || window.wiggly.S.t < 0.5")
    page.keyboard.press("Space")
    now = page.evaluate("Math.round(window.wiggly.S.t * 20)")
    assert min(abs(s["frame"] - now) for s in page.evaluate("window.wiggly.onionInfo()")) == 2
    page.keyboard.press("o")
    assert page.evaluate("window.wiggly.onionInfo()") == []


def test_motion_path_follows_the_selected_group(editor):
    server, page = editor
    page.click("#groups li[data-group=right] .name")
    page.keyboard.press("p")
    page.wait_for_function("window.wiggly.pathOf('right') !== null")
    path = np.asarray(page.evaluate("window.wiggly.pathOf('right')")).reshape(-1, 3)
    frames, _ = latest_final(server.url)
    idx = server.session.groups()["right"]
    assert np.allclose(path, frames[:, idx].mean(axis=1), atol=1e-5)
    assert path[:, 1].max() > path[0, 1] + 0.03  # it rises to the keyframe
    page.keyboard.press("p")
    assert page.evaluate("window.wiggly.pathOf('right')") is None


# ----------------------------------------------------------------------------------------------
# gizmo: axis keys, typed values, snapping, pivots


def test_gizmo_axis_keys_and_typed_values(editor):
    server, page = editor
    select_key(page, 0)
    page.keyboard.press("w")
    x, y, h = grab_gizmo(page, "Y")
    move_along(page, x, y, h, 30, steps=4)
    page.keyboard.press("z")      # constrain to Z from where the drag started
    page.wait_for_function("window.wiggly.S.xform.axis === 'Z'")
    page.keyboard.type("0.08")    # an exact value along it
    page.wait_for_function("document.querySelector('#hud').textContent.includes('typed 0.08')")
    version = server.session.version
    page.keyboard.press("Enter")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version} && "
                           "!window.wiggly.S.dragging")
    page.mouse.up()
    pos = _keys(server)[0][2]
    assert np.allclose(pos.translation, [0, 0.05, 0.08], atol=1e-9), pos
    assert np.allclose(pos.rotation, 0, atol=1e-9)
    # rotate: E, grab the X ring, type 90 and Enter: a quarter turn about X
    page.keyboard.press("e")
    grab_ring(page, "X")
    page.keyboard.type("90")
    version = server.session.version
    page.keyboard.press("Enter")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    page.mouse.up()
    pos = _keys(server)[0][2]
    assert np.allclose(pos.rotation, [90, 0, 0], atol=1e-4), pos
    assert np.allclose(pos.translation, [0, 0.05, 0.08], atol=1e-6)
    # velocity: V, grab the arrow's tip along X, type 1.5 (m/s) and Enter
    page.keyboard.press("v")
    page.wait_for_function("window.wiggly.S.posing.mode === 'velocity'")
    grab_gizmo(page, "X")
    page.keyboard.type("1.5")
    version = server.session.version
    page.keyboard.press("Enter")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    page.mouse.up()
    assert np.allclose(server.session.scene.keyframes[0].velocity, [1.5, 0, 0], atol=1e-4)
    # a fast velocity's arrow runs far beyond the group: Frame (F) keeps its tip in view
    edit_key = {"op": "update_keyframe", "id": server.session.state.keyframe_ids[0],
                "velocity": [0.0, 8.0, 0.0]}
    version = server.session.version
    post(server.url, "/api/edit", edit_key)
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    page.keyboard.press("f")
    tip = page.evaluate("window.wiggly.gizmoHandle('Y')")
    box = page.locator("#canvas").bounding_box()
    assert box["x"] <= tip["x"] <= box["x"] + box["width"], (tip, box)
    assert box["y"] <= tip["y"] <= box["y"] + box["height"], (tip, box)


def test_gizmo_snapping(editor):
    server, page = editor
    page.check("#snap")
    page.fill("#snap-move", "0.02")
    page.press("#snap-move", "Enter")
    select_key(page, 0)
    page.keyboard.press("w")
    before = np.array(_keys(server)[0][2].offset)
    x, y, h = grab_gizmo(page, "Y")
    move_along(page, x, y, h, 55, steps=5)
    assert "snapping" in page.locator("#hud").text_content()
    version = server.session.version
    page.mouse.up()
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    moved = np.array(_keys(server)[0][2].translation) - before
    steps = moved[1] / 0.02
    assert abs(moved[1]) >= 0.02 and abs(steps - round(steps)) < 1e-6, moved
    # Ctrl held during the drag inverts snapping
    x, y, h = grab_gizmo(page, "Y")
    page.keyboard.down("Control")
    move_along(page, x, y, h, 37, steps=5)
    assert "snapping" not in page.locator("#hud").text_content()
    version = server.session.version
    page.mouse.up()
    page.keyboard.up("Control")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    after = np.array(_keys(server)[0][2].translation)[1] - before[1]
    assert abs(after / 0.02 - round(after / 0.02)) > 1e-3, after


def test_gizmo_pivot_choices(editor):
    server, page = editor
    # a lopsided group: its centroid is not the centre of its bounds
    post(server.url, "api/edit", {"op": "set_group", "name": "lop",
                                  "indices": [0, 1, 2, 3, 4, 5, 80]})
    _, r = post(server.url, "api/edit", {"op": "add_keyframe", "time": 0.5, "group": "lop"})
    kid = r["id"]
    page.wait_for_function(f"window.wiggly.S.desc.scene.keyframes.some((k) => k.id === {kid})")
    rest = server.session.surface.vertices[server.session.groups()["lop"]]
    center = (rest.min(0) + rest.max(0)) / 2
    assert np.abs(center - rest.mean(0)).max() > 0.05
    select_key(page, kid)
    page.select_option("#pivot", "bounds")
    page.keyboard.press("e")
    grab_ring(page, "Z")
    page.keyboard.type("30")
    version = server.session.version
    page.keyboard.press("Enter")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    page.mouse.up()
    pos = _keys(server)[kid][2]
    assert np.allclose(pos.center, center, atol=1e-6) and np.allclose(pos.rotation, [0, 0, 30],
                                                                     atol=1e-4)
    assert np.allclose(pos.translation, 0, atol=1e-6)  # it turned about the bounds' centre
    # the 3D cursor: Shift+right-click on the body places it; the next turn is about it
    page.select_option("#pivot", "cursor")
    box = page.evaluate("window.wiggly.projectGroup('mid')")
    page.keyboard.press("Escape")
    page.keyboard.down("Shift")
    page.mouse.click((box["x0"] + box["x1"]) / 2, (box["y0"] + box["y1"]) / 2, button="right")
    page.keyboard.up("Shift")
    page.wait_for_function("window.wiggly.S.cursor !== null")
    cursor = np.array(page.evaluate("window.wiggly.S.cursor.toArray()"))
    assert abs(cursor[0] - 0.5) < 0.08  # on the middle of the bar
    select_key(page, kid)
    page.keyboard.press("e")
    grab_ring(page, "Z")
    page.keyboard.type("10")
    version = server.session.version
    page.keyboard.press("Enter")
    page.wait_for_function(f"window.wiggly.S.desc.version > {version}")
    page.mouse.up()
    before, pos = pos, _keys(server)[kid][2]

    def pose(p, x):  # the rigid target's map of rest points
        return (x - p.center) @ p.matrix().T + p.center + p.translation

    th = np.radians(40)
    assert np.allclose(pos.matrix(), [[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0],
                                      [0, 0, 1]], atol=1e-6)
    # the 10 degrees turned about the cursor: the point of the earlier target at the cursor
    # stays there
    at_cursor = np.linalg.solve(before.matrix(), cursor - before.center - before.translation) \
        + before.center
    assert np.allclose(pose(before, at_cursor), cursor, atol=1e-9)
    assert np.allclose(pose(pos, at_cursor), cursor, atol=1e-5)
    assert np.abs(pose(pos, rest) - pose(before, rest)).max() > 0.005  # and the rest moved


# ----------------------------------------------------------------------------------------------
# selection of visible vertices


def _seen_from(eye: np.ndarray, points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """How far in front of each point the surface first meets the ray from ``eye`` (0: the
    point is the first hit), by Moller-Trumbore against every triangle."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    out = np.zeros(len(points))
    for i, p in enumerate(points):
        dist = np.linalg.norm(p - eye)
        d = (p - eye) / dist
        pv = np.cross(d, e2)
        det = (e1 * pv).sum(1)
        ok = np.abs(det) > 1e-12
        inv = 1 / np.where(ok, det, 1)
        tv = eye - a
        u = (tv * pv).sum(1) * inv
        qv = np.cross(tv, e1)
        v = (d * qv).sum(1) * inv
        t = (e2 * qv).sum(1) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        out[i] = max(dist - t[hit].min(), 0.0) if hit.any() else 0.0
    return out


def test_box_and_lasso_select_visible_vertices_only(editor):
    """Box and lasso select the vertices a ray from the eye meets first, not those behind
    the surface (checked by casting rays against the body the page shows); X-ray (Alt+Z)
    selects through."""
    server, page = editor
    faces = server.session.surface.faces
    every = np.arange(server.session.surface.n_vertices)

    def selected():
        return np.flatnonzero(np.array(page.evaluate("Array.from(window.wiggly.S.selection)")))

    def visibility():
        """Vertices seen clearly (the first hit of their ray, on a surface not seen edge-on,
        where pixels cannot tell), and those clearly hidden (1 cm behind the surface)."""
        points = np.reshape(page.evaluate("window.wiggly.shownPositions()"), (-1, 3))
        eye = np.array(page.evaluate("window.wiggly.camera()")["position"])
        behind = _seen_from(eye, points, faces)
        normals = np.zeros_like(points)
        n = np.cross(points[faces[:, 1]] - points[faces[:, 0]],
                     points[faces[:, 2]] - points[faces[:, 0]])
        for k in range(3):
            np.add.at(normals, faces[:, k], n)
        to_eye = eye - points
        size = np.linalg.norm(normals, axis=1) * np.linalg.norm(to_eye, axis=1)
        facing = np.abs((normals * to_eye).sum(1)) / np.where(size > 0, size, np.inf)
        return np.flatnonzero((behind < 1e-4) & (facing > 0.3)), np.flatnonzero(behind > 0.01)

    for view in (None, "Numpad7"):  # the first three-quarter view, then the top
        if view:
            page.keyboard.press(view)
        seen, hidden = visibility()
        assert len(hidden) >= 20 and len(seen) >= 20
        box_select(page, every, xray=False)
        chosen = selected()
        assert not set(chosen) & set(hidden), (view, sorted(set(chosen) & set(hidden)))
        assert len(set(seen) - set(chosen)) <= 0.1 * len(seen), (view, sorted(set(seen) -
                                                                               set(chosen)))
        box_select(page, every, xray=True)
        assert len(selected()) == len(every)
    # the lasso too, around the whole bar (seen from the top), visible vertices only
    page.keyboard.press("Alt+z")
    assert not page.evaluate("window.wiggly.S.view.xray")
    seen, hidden = visibility()
    b = page.evaluate("(idx) => window.wiggly.screenBox(idx)", every.tolist())
    page.keyboard.press("l")
    pts = [(b["x0"] - 8, b["y0"] - 8), (b["x1"] + 8, b["y0"] - 8), (b["x1"] + 8, b["y1"] + 8),
           (b["x0"] - 8, b["y1"] + 8)]
    page.mouse.move(*pts[0])
    page.mouse.down()
    for p in [*pts[1:], pts[0]]:
        page.mouse.move(*p, steps=3)
    page.mouse.up()
    chosen = selected()
    assert not set(chosen) & set(hidden)
    assert len(set(seen) - set(chosen)) <= 0.1 * len(seen)


# ----------------------------------------------------------------------------------------------
# views


def test_front_side_top_views_and_frame_selected(editor):
    _server, page = editor

    def direction():
        c = page.evaluate("window.wiggly.camera()")
        d = np.subtract(c["position"], c["target"])
        return d / np.linalg.norm(d)

    for key, want in (("Numpad1", [0, 0, 1]), ("Numpad3", [1, 0, 0]), ("Numpad7", [0, 1, 0]),
                      ("Control+Numpad1", [0, 0, -1]), ("3", [1, 0, 0])):
        page.keyboard.press(key)
        assert np.allclose(direction(), want, atol=1e-3), (key, direction())
    page.click("#groups li[data-group=right] .name")
    page.click("#btn-sel-clear")
    page.keyboard.press("f")
    next_frame(page)
    box = page.evaluate("window.wiggly.projectGroup('right')")
    canvas = page.locator("#canvas").bounding_box()
    cx, cy = canvas["x"] + canvas["width"] / 2, canvas["y"] + canvas["height"] / 2
    assert abs((box["x0"] + box["x1"]) / 2 - cx) < 0.05 * canvas["width"]
    assert abs((box["y0"] + box["y1"]) / 2 - cy) < 0.05 * canvas["height"]
    assert max(box["x1"] - box["x0"], box["y1"] - box["y0"]) > 0.3 * min(canvas["width"],
                                                                          canvas["height"])
    assert np.allclose(direction(), [1, 0, 0], atol=1e-3)  # framing keeps the direction


# ----------------------------------------------------------------------------------------------
# preview range and playback speed


def test_preview_range_and_playback_speed(editor):
    _server, page = editor
    a = page.evaluate("window.wiggly.timePoint(0.25)")
    b = page.evaluate("window.wiggly.timePoint(0.75)")
    page.keyboard.down("Control")
    page.mouse.move(a["x"], a["y"])
    page.mouse.down()
    page.mouse.move(b["x"], b["y"], steps=4)
    page.mouse.up()
    page.keyboard.up("Control")
    assert page.evaluate("window.wiggly.S.view.range") == pytest.approx([0.25, 0.75])
    assert page.input_value("#range-from") == "0.25"
    page.select_option("#speed", "0.5")
    page.keyboard.press("Space")
    seen = []
    while len(seen) < 2 or not any(t1 < t0 for t0, t1 in itertools.pairwise(seen)):
        page.wait_for_function("window.wiggly.lastStep !== undefined")
        step = page.evaluate("window.wiggly.lastStep")
        seen.append(step["t"])
        assert step["advance"] == pytest.approx(0.5 * min(step["wall"], 0.1))
        assert 0.25 - 1e-9 <= step["t"] <= 0.75 + 1e-9
        next_frame(page)
        assert len(seen) < 2000, "playback never looped in the preview range"
    page.keyboard.press("Space")
    page.keyboard.press("Alt+p")
    assert page.evaluate("window.wiggly.S.view.range") is None


# ----------------------------------------------------------------------------------------------
# undo per tab, across a restart


def test_undo_is_per_tab_and_survives_a_restart(chromium, tmp_path):
    path = bar_project(tmp_path, MORE_KEYS, warp=False)
    server = serve(path)
    port = server.port
    young = "[data-set='material.young']"
    alpha = "[data-set='damping.alpha']"
    try:
        with editor_page(chromium, server.url) as (a, a_errors), \
                editor_page(chromium, server.url) as (b, b_errors):
            for page, field, value, key in ((a, young, "3e6", "material.young"),
                                            (b, alpha, "0.7", "damping.alpha")):
                page.fill(field, value)
                page.press(field, "Enter")
                page.wait_for_function(f"window.wiggly.S.desc.scene.{key} === {value} && "
                                       "window.wiggly.S.desc.can_undo")
            a.wait_for_function("window.wiggly.S.desc.scene.damping.alpha === 0.7")
            assert "material" in a.evaluate("window.wiggly.S.desc.undo_label")
            version = server.session.version
            a.keyboard.press("Control+z")  # undoes tab A's edit only
            a.wait_for_function(f"window.wiggly.S.desc.version > {version}")
            scene = server.session.scene
            assert scene.material.young == 1e6 and scene.damping.alpha == 0.7
            assert a.evaluate("window.wiggly.S.desc.can_redo")
            b.wait_for_function(f"window.wiggly.S.desc.version === {server.session.version}")
            assert b.evaluate("window.wiggly.S.desc.can_undo && !window.wiggly.S.desc.can_redo")
            # the server restarts; tab A reloads, tab B stays open: both keep their histories
            server.stop()
            server = serve(path, port=port)
            a.reload()
            a.wait_for_function("window.wiggly && window.wiggly.ready && "
                                "window.wiggly.S.desc && window.wiggly.S.desc.can_redo",
                                timeout=30_000)
            version = server.session.version
            a.keyboard.press("Control+Shift+z")
            a.wait_for_function(f"window.wiggly.S.desc.version > {version}")
            assert server.session.scene.material.young == 3e6
            b.wait_for_function(f"window.wiggly.S.instance === '{server.session.instance}' && "
                                "window.wiggly.S.desc.can_undo", timeout=30_000)
            version = server.session.version
            b.keyboard.press("Control+z")
            # the version also moves when a re-solve lands: wait for the undo itself
            b.wait_for_function(f"window.wiggly.S.desc.version > {version} && "
                                "window.wiggly.S.desc.scene.damping.alpha === 0.5")
            assert server.session.scene.damping.alpha == 0.5
            assert server.session.scene.material.young == 3e6
            # an undo that would discard another tab's later change is refused, and says so
            for page, value in ((a, "0.3"), (b, "0.35")):
                page.click("#keys li[data-key='2']")
                page.fill("#key-time", value)
                page.press("#key-time", "Enter")
                page.wait_for_function("window.wiggly.S.desc.scene.keyframes.find((k) => "
                                       f"k.id === 2).time === {value}")
            a.keyboard.press("Control+z")
            assert "changed since" in toast_saying(a, "cannot undo")
            assert server.session.scene.keyframes[2].time == 0.35
            assert not a_errors and not b_errors, (a_errors, b_errors)
    finally:
        server.stop()


def test_a_held_drag_shows_its_warped_frames_before_the_release(chromium, tmp_path):
    """On a warped scene, drag the Y arrow 60 px and hold still: the page shows the held
    pose's warped frames (request "drag", not final) while the mouse is down and nothing is
    logged; the release then logs one edit and shows its final warped frames."""
    server = serve(bar_project(tmp_path))
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            version = server.session.version
            select_key(page, 0)
            page.keyboard.press("w")
            page.wait_for_function("window.wiggly.S.posing && "
                                   "window.wiggly.S.posing.mode === 'translate'")
            x, y, h = grab_gizmo(page, "Y")
            move_along(page, x, y, h, 60)
            page.wait_for_function("window.wiggly.S.frames.meta.request === 'drag' && "
                                   "window.wiggly.S.frames.meta.stage === 'warped'",
                                   timeout=60_000)
            held = page.evaluate("window.wiggly.S.frames.meta")
            assert not held["final"] and held["version"] == version
            assert page.evaluate("window.wiggly.S.dragging")
            assert server.session.version == version
            page.mouse.up()
            meta = wait_final(page)
            assert meta["version"] == server.session.version == version + 1
            page.wait_for_function("window.wiggly.S.frames.meta.stage === 'warped' && "
                                   "window.wiggly.S.frames.meta.final", timeout=60_000)
            assert not errors, errors
    finally:
        server.stop()


@pytest.fixture
def bar_editor(chromium, tmp_path):
    """The bar with its one keyframe, linear, open in a page showing its final frames; yields
    (server, page, scene path) and checks the page raised no errors."""
    path = bar_project(tmp_path, warp=False)
    server = serve(path)
    try:
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            yield server, page, path
            assert not errors, errors
    finally:
        server.stop()


def test_a_keyframe_field_left_empty_is_refused_not_zeroed(bar_editor):
    """An emptied velocity component (or time) is not a number: the page says so and sends
    nothing, where it used to send 0 for the velocity and "cannot be removed" for the time.
    A number typed there is taken."""
    server, page, _ = bar_editor
    select_key(page, 0)
    page.check("#key-vel-on")
    page.wait_for_function("window.wiggly.S.desc.scene.keyframes[0].velocity")
    page.fill("#key-vx", "0.25")
    page.press("#key-vx", "Enter")
    page.wait_for_function("window.wiggly.S.desc.scene.keyframes[0].velocity[0] === 0.25")
    version = server.session.version
    for field, what in (("#key-vx", "velocity"), ("#key-time", "time")):
        page.fill(field, "")
        page.press(field, "Enter")
        toast_saying(page, f"keyframe {what}: empty is not a number")
    assert server.session.version == version
    assert server.session.scene.keyframes[0].velocity[0] == 0.25
    assert page.input_value("#key-vx") != ""  # the scene's value again


def test_escape_in_a_field_cancels_what_was_typed(bar_editor):
    """Escape puts a field back as it was when it got the focus and sends nothing (it used to
    commit the half-typed value, as Enter does); Enter commits."""
    server, page, _ = bar_editor
    field = '[data-set="material.density"]'
    before = page.input_value(field)
    version = server.session.version
    page.click(field)
    page.fill(field, "5")
    page.press(field, "Escape")
    page.wait_for_timeout(500)  # an edit, if one were sent, is answered well within
    assert server.session.version == version
    assert server.session.scene.material.density == float(before)
    assert page.input_value(field) == before
    page.click(field)
    page.fill(field, "900")
    page.press(field, "Enter")
    page.wait_for_function("window.wiggly.S.desc.scene.material.density === 900")
    assert server.session.scene.material.density == 900


def test_undo_with_nothing_to_undo_says_so(bar_editor):
    """Ctrl+Z in a tab with no edits of its own says so in the status line (it did nothing
    visible: each tab undoes its own edits)."""
    _, page, _ = bar_editor
    page.locator("#canvas").click(position={"x": 5, "y": 5})
    page.keyboard.press("Control+z")
    page.wait_for_function(
        "document.getElementById('status-text').textContent.startsWith("
        "'nothing to undo in this tab')")


def test_the_export_dialog_offers_the_last_paths_again(bar_editor):
    """Export a second time: the dialog offers the paths exported last, not the defaults."""
    _, page, path = bar_editor
    page.click("#btn-export")
    field = page.locator("#modal-body input")
    assert ".glb" in field.input_value()  # the first time: the defaults
    field.fill("renders/take1.npz")
    page.click("#modal-ok")
    page.wait_for_function("document.getElementById('modal').hidden")
    for _ in range(300):  # the export runs in the background
        if (path.parent / "renders" / "take1.npz").exists():
            break
        page.wait_for_timeout(100)
    assert (path.parent / "renders" / "take1.npz").exists()
    page.click("#btn-export")
    assert page.locator("#modal-body input").input_value() == "renders/take1.npz"
    page.click("#modal-cancel")


def test_the_cycle_checkbox_makes_the_shot_a_loop(bar_editor):
    """The physics panel's cycle box sets time.loop: the shot's end becomes its start (positions and
    velocities), which the solved frames show; unchecked, the bar ends elsewhere."""
    server, page, _ = bar_editor
    frames, _ = latest_final(server.url)
    drift = np.abs(frames[-1] - frames[0]).max()
    assert drift > 1e-3, drift  # not a cycle: the bar swings on after its key
    page.check('[data-set="time.loop"]')
    page.wait_for_function("window.wiggly.S.desc.scene.time.loop === true")
    wait_final(page)
    frames, meta = latest_final(server.url)
    assert server.session.scene.time.loop
    seam = np.abs(frames[-1] - frames[0]).max()
    assert seam < 1e-6, (seam, meta)  # float32 frames of a 1 m bar: about 1e-7
    page.uncheck('[data-set="time.loop"]')
    page.wait_for_function("!window.wiggly.S.desc.scene.time.loop")
    assert not server.session.scene.time.loop
    # a refused toggle (20.6 frames a cycle) leaves the box as the scene is, though focused
    st, _ = post(server.url, "api/edit", {"op": "set", "section": "time", "values": {"end": 1.03}})
    assert st == 200
    page.wait_for_function("window.wiggly.S.desc.scene.time.end === 1.03")
    page.click('[data-set="time.loop"]')
    toast_saying(page, "whole number of frames")
    page.wait_for_function("!document.querySelector('[data-set=\"time.loop\"]').checked")
    assert not server.session.scene.time.loop


def test_a_duplicated_tab_gets_a_history_of_its_own(chromium, tmp_path):
    """A tab duplicated from another (window.open of its page copies sessionStorage, with its
    tab id) takes an id of its own: undo in the original undoes the original's edit, not the
    copy's (they shared one history); a reload keeps its tab's id."""
    path = bar_project(tmp_path, MORE_KEYS, warp=False)
    server = serve(path)
    alpha = "[data-set='damping.alpha']"
    try:
        with editor_page(chromium, server.url) as (a, errors):
            a.fill(alpha, "0.7")
            a.press(alpha, "Enter")
            a.wait_for_function("window.wiggly.S.desc.scene.damping.alpha === 0.7 && "
                                "window.wiggly.S.desc.can_undo")
            tab = a.evaluate("() => import('./core.js').then(m => m.TAB)")
            with a.context.expect_page() as opened:
                a.evaluate("window.open(location.href)")
            d = opened.value
            d.wait_for_function("window.wiggly && window.wiggly.ready && window.wiggly.S.desc",
                                timeout=LOADED)
            assert d.evaluate("() => import('./core.js').then(m => m.TAB)") != tab
            assert not d.evaluate("window.wiggly.S.desc.can_undo")
            beta = "[data-set='damping.beta']"
            d.fill(beta, "0.0071")
            d.press(beta, "Enter")
            d.wait_for_function("window.wiggly.S.desc.scene.damping.beta === 0.0071")
            version = server.session.version
            a.keyboard.press("Control+z")
            a.wait_for_function(f"window.wiggly.S.desc.version > {version}")
            scene = server.session.scene
            assert scene.damping.alpha != 0.7 and scene.damping.beta == 0.0071
            a.reload()
            a.wait_for_function("window.wiggly && window.wiggly.ready && window.wiggly.S.desc")
            assert a.evaluate("() => import('./core.js').then(m => m.TAB)") == tab
            assert a.evaluate("window.wiggly.S.desc.can_redo")
            assert not errors, errors
    finally:
        server.stop()
