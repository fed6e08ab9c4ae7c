"""A [drive] scene in the editor (issue 13): the driver's pose as a ghost that follows the
time cursor, the driven group in its colour with a tick per driven frame, D to hide the ghost;
the server's driver endpoint and its errors."""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request

import meshio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.editor_ui import editor_page, first_event, wait_final
from wiggly.editor import serve
from wiggly.export import SurfaceAnimation, write_animation
from wiggly.mesh import TetMesh
from wiggly.primitives import box_mesh

pytestmark = pytest.mark.browser

FPS = 20
SCENE = """\
format = 1
[mesh]
path = "bar.vtu"
[material]
young = 5e4
[simulation]
modes = 12
warp = false
[time]
end = 1.0
fps = 20
[groups.driven]
box = { min = [-1, -1, -1], max = [0.3, 1, 1] }
color = "#d62728"
[groups.tip]
box = { min = [0.7, -1, -1], max = [1, 1, 1] }
[drive]
path = "walk.npz"
group = "driven"
"""


def driver_motion(V: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The whole bar turning about a vertical axis (25 degrees at 1 Hz), rigidly: (F, n, 3)."""
    pivot = np.array([0.15, 0.05, 0.05])
    return np.array([Rotation.from_euler("y", 25.0 * np.sin(2 * np.pi * tk), degrees=True)
                     .apply(V - pivot) + pivot for tk in t])


def drive_project(folder, driver_vertices: slice = slice(None)):
    """An 0.8 m tet bar whose left part is driven by a rigid turn (walk.npz, 21 frames);
    returns (scene path, driver positions)."""
    V, T = box_mesh((8, 2, 2), (0.8, 0.1, 0.1))
    meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    times = np.arange(21) / FPS
    faces = TetMesh(V, T).boundary_faces()
    keep = np.arange(len(V))[driver_vertices]
    P = driver_motion(V, times)[:, keep]
    if len(keep) < len(V):  # another surface: a driver of the first vertices only
        faces = faces[np.all(np.isin(faces, keep), axis=1)]
    write_animation(folder / "walk.npz", SurfaceAnimation(times, P, faces))
    (folder / "shot.toml").write_text(SCENE)
    return folder / "shot.toml", P


def get_driver(url: str):
    try:
        with urllib.request.urlopen(url + "api/driver", timeout=30) as r:
            return r.status, r.read(), json.loads(r.headers["X-Wiggly-Driver"])
    except urllib.error.HTTPError as err:
        return err.code, None, json.loads(err.read())


def test_the_driver_is_a_ghost_that_follows_the_time_cursor(chromium, tmp_path):
    """The ghost shows the driver's pose at the current frame; the driven vertices of the
    solved motion lie on it (the solve follows the driver), the free tip does not; D hides
    and shows it; the driven group's row has a tick per driven frame."""
    path, P = drive_project(tmp_path)
    server = serve(path)
    try:
        status, data, meta = get_driver(server.url)
        assert status == 200 and meta["n_frames"] == 21 and meta["groups"] == ["driven"]
        assert np.allclose(meta["times"], np.arange(21) / FPS)
        assert np.array_equal(np.frombuffer(data, "<f4").reshape(P.shape), P.astype("<f4"))
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            page.wait_for_function("window.wiggly.driverInfo().loaded")
            page.locator("#canvas").click(position={"x": 5, "y": 5})  # focus, no selection
            for _ in range(5):
                page.keyboard.press("ArrowRight")  # 0.25 s: driver frame 5
            page.wait_for_function("Math.abs(window.wiggly.S.t - 0.25) < 1e-9")
            info = page.evaluate("window.wiggly.driverInfo()")
            assert info["visible"] and info["groups"] == ["driven"]
            ghost = np.asarray(info["positions"]).reshape(-1, 3)
            assert np.array_equal(ghost, P[5].astype(np.float32))
            shown = np.asarray(page.evaluate("window.wiggly.shownPositions()")).reshape(-1, 3)
            driven = np.asarray(server.session.groups()["driven"])
            tip = np.asarray(server.session.groups()["tip"])
            assert np.abs(shown[driven] - ghost[driven]).max() < 1e-3  # m: it follows
            assert np.abs(shown[tip] - ghost[tip]).max() > 5e-3  # the free end lags
            # halfway between frames 5 and 6 the ghost is the linear blend of the two
            page.evaluate("window.wiggly.setTime(0.275)")
            info = page.evaluate("window.wiggly.driverInfo()")
            half = (P[5].astype(np.float32) + P[6].astype(np.float32)) / 2
            assert np.abs(np.asarray(info["positions"]).reshape(-1, 3) - half).max() < 1e-6
            page.keyboard.press("d")
            assert not page.evaluate("window.wiggly.driverInfo().visible")
            assert not page.locator("#driver").is_checked()
            page.keyboard.press("d")
            assert page.evaluate("window.wiggly.driverInfo().visible")
            # the driven group is drawn in its colour (#d62728), far more than the tip is
            color = np.asarray(page.evaluate("window.wiggly.shownColors()")).reshape(-1, 3)
            red = np.array([0xd6, 0x27, 0x28]) / 255
            to_red = np.linalg.norm(color - red, axis=1)
            assert to_red[driven].max() < 0.5 * to_red[tip].min(), (color[driven[0]],
                                                                   color[tip[0]])
            assert page.evaluate("window.wiggly.drivenTicks()") == {"driven": 21}
            assert not errors, errors
    finally:
        server.stop()


def test_driver_errors_reach_the_page(chromium, tmp_path):
    """A scene without [drive] has no ghost (404); a driver of another surface is refused
    with both vertex counts, in the page's status line."""
    path, _ = drive_project(tmp_path, driver_vertices=slice(0, 40))
    server = serve(path)
    try:
        status, _, body = get_driver(server.url)
        assert status == 400
        assert "40" in body["error"] and "81" in body["error"], body
        with editor_page(chromium, server.url) as (page, errors):
            # the ghost's request and the physics (which checks the driver before
            # tetrahedralizing) both refuse it; whichever speaks last, both counts show
            page.wait_for_function("(() => { const t = document.querySelector("
                                   "'#status-text').textContent; return t.includes('40') && "
                                   "t.includes('81'); })()")
            assert not page.evaluate("window.wiggly.driverInfo().loaded")
            assert not errors, errors
    finally:
        server.stop()
    (tmp_path / "plain.toml").write_text(SCENE.split("[drive]")[0])
    server = serve(tmp_path / "plain.toml")
    try:
        status, _, body = get_driver(server.url)
        assert status == 404 and "no [drive]" in body["error"]
    finally:
        server.stop()


def _session_final(session):
    """The final frames of the session's current version (a minute at the most)."""
    from tests.test_editor_server import wait_final as final_frames

    return final_frames(session, timeout=60.0)


@pytest.mark.parametrize("warp", [False, True])
def test_secondary_motion_in_the_editor_and_its_controls(tmp_path, warp):
    """A [drive] scene plays the library's secondary motion (linear and warped: the editor's
    final frames equal wiggly.scene's solve); the swing (drive.intensity) and a group's own
    Young's modulus are edits that change the motion, and undo walks them back with the
    [drive] table intact."""
    from wiggly.editor.session import Sandbox, Session
    from wiggly.scene import solve_scene
    from wiggly.scene.build import build_with_groups

    path, _ = drive_project(tmp_path)
    if warp:
        path.write_text(SCENE.replace("warp = false", "warp = true"))
    session = Session(Sandbox([tmp_path]))
    session.open(str(path))
    try:
        first = _session_final(session).positions.copy()

        def library():
            body, keys, groups = build_with_groups(session.scene)
            anim = solve_scene(session.scene, body, keys, groups=groups)
            assert anim.info["secondary"]
            return anim.positions(anim.frame_times(FPS), dtype=np.float32)

        assert np.abs(library() - first).max() < 1e-5
        # its body keeps the rigid modes only, as `wiggly animate`'s: the motion uses the
        # free parts' own modes, and the scene's 12 would cost seconds on a large mesh
        assert session.physics.body(session.scene, abandon=lambda: False).r < 12
        session.edit({"op": "set", "section": "drive", "values": {"intensity": 2.0}})
        assert session.scene.drive.intensity == 2.0
        doubled = _session_final(session).positions.copy()
        assert np.abs(library() - doubled).max() < 1e-5
        assert np.abs(doubled - first).max() > 1e-4  # the free end swings more
        session.edit({"op": "set_group_young", "name": "tip", "young": 1e4})
        assert session.scene.groups["tip"].young == 1e4
        soft = _session_final(session).positions.copy()
        assert np.abs(library() - soft).max() < 1e-5 and np.abs(soft - doubled).max() > 1e-4
        session.undo()
        session.undo()
        assert session.scene.drive is not None and session.scene.drive.intensity == 1.0
        assert session.scene.groups["tip"].young is None
        assert np.abs(_session_final(session).positions - first).max() < 1e-5
    finally:
        session.close()


def test_drive_settings_need_a_drive(tmp_path):
    from wiggly.editor.state import EditError, EditorState, apply_edit
    from wiggly.scene import load_scene

    path, _ = drive_project(tmp_path)
    path.write_text(SCENE.split("[drive]")[0])
    state = EditorState.of(load_scene(path))
    with pytest.raises(EditError, match="no \\[drive\\]"):
        apply_edit(state, {"op": "set", "section": "drive", "values": {"intensity": 2.0}})
    with pytest.raises(EditError):
        apply_edit(state, {"op": "set_group_young", "name": "tip", "young": -5})


def test_the_page_tints_where_the_warped_motion_folds(chromium, tmp_path):
    """The bar's free end pushed through its fixed one: the final warped frames carry the
    spans and surface vertices where tets turn inside out, and the page tints those vertices
    magenta over their span (as previews do), and nothing away from it."""
    from tests.editor_ui import bar_project

    path = bar_project(tmp_path)
    path.write_text(path.read_text().replace("[0.0, 0.05, 0.0]", "[-1.8, 0.0, 0.0]"))
    server = serve(path)
    base, fold = np.array([0.70, 0.74, 0.80]), np.array([0.8, 0.0, 0.55])
    try:
        with editor_page(chromium, server.url) as (page, errors):
            spans = wait_final(page).get("fold_spans")
            assert spans, "no fold spans in the final frames"
            span = max(spans, key=lambda s: len(s["vertices"]))
            inside = np.asarray(span["vertices"])
            page.evaluate(f"window.wiggly.setTime({(span['from'] + span['until']) / 2})")
            color = np.asarray(page.evaluate("window.wiggly.shownColors()")).reshape(-1, 3)
            tinted = base + 0.9 * (fold - base)
            assert np.abs(color[inside] - tinted).max() < 1e-3
            others = np.setdiff1d(np.arange(len(color)), np.concatenate(
                [s["vertices"] for s in spans]))
            assert (np.linalg.norm(color[others] - tinted, axis=1) > 0.2).all()
            # away from every span (by more than the 0.25 s fade) nothing is magenta
            far = [t for t in np.linspace(0.0, 1.0, 41)
                   if all(t < s["from"] - 0.26 or t > s["until"] + 0.26 for s in spans)]
            assert far, spans
            page.evaluate(f"window.wiggly.setTime({far[0]})")
            color = np.asarray(page.evaluate("window.wiggly.shownColors()")).reshape(-1, 3)
            assert (np.linalg.norm(color - tinted, axis=1) > 0.2).all()
            assert not errors, errors
    finally:
        server.stop()


def test_a_driven_scenes_missed_key_is_a_notice(tmp_path):
    """The warped secondary motion's checks reach the page as a keyed scene's do: a key on
    the free tip that the motion cannot meet (a 0.3 m lift held by a weak key) is a notice
    naming it, as wiggly animate warns (the editor said nothing, only residual_max)."""
    path, _ = drive_project(tmp_path)
    said, _ = _notices(path, SCENE.replace("warp = false", "warp = true") + (
        '[[keyframes]]\ntime = 0.5\ngroup = "tip"\nposition = { offset = [0.0, 0.3, 0.0] }\n'
        "stiffness = 1e-3\n"), "missed by more than")
    assert said is not None and "keyframes[0] (group 'tip', t = 0.5 s)" in said["message"]


def _notices(path, text: str, words: str):
    """The scene ``text`` written to ``path`` and opened in a session, to its final frames:
    the first notice that says ``words`` (None: none within 30 s) and every notice said
    until then and queued after it."""
    from wiggly.editor.session import Sandbox, Session

    path.write_text(text)
    session = Session(Sandbox([path.parent]))
    events = session.bus.subscribe()
    session.open(str(path))
    seen: list[str] = []

    def wanted(e) -> bool:
        if e["type"] == "notice":
            seen.append(e["message"])
        return e["type"] == "notice" and words in e["message"]

    try:
        _session_final(session)
        said = first_event(events, wanted, 30.0)
        seen += [e["message"] for e in [events.get_nowait() for _ in range(events.qsize())]
                 if e["type"] == "notice"]
        return said, seen
    finally:
        session.close()


def test_a_driver_at_another_scale_is_refused_in_the_editor_as_by_the_cli(tmp_path):
    """The editor solved (and exported) a driven scene whose driver is 100 times the mesh,
    which wiggly animate refuses: it now says the CLI's error instead of frames."""
    from wiggly.editor.session import Sandbox, Session
    from wiggly.export import read_animation

    path, _ = drive_project(tmp_path)
    walk = read_animation(tmp_path / "walk.npz")
    write_animation(tmp_path / "walk.npz", SurfaceAnimation(walk.times, 100 * walk.positions,
                                                            walk.faces), overwrite=True)
    session = Session(Sandbox([tmp_path]))
    events = session.bus.subscribe()
    session.open(str(path))
    try:
        said = first_event(events, lambda e: e["type"] == "solve" and e.get("stage") == "error",
                           120.0)
        assert said is not None
        assert "its first pose is 100 times the size of bar.vtu" in said["message"]
        assert session.latest_frames(final=True) is None
    finally:
        session.close()


def test_a_driver_changed_on_disk_is_read_again(tmp_path, monkeypatch):
    """Another tool re-exports the driver while the editor runs: the motion is solved again
    with it, a notice says so, and the page's description changes its driver stamp (the
    ghost fetches it again). It used to stay stale until some edit, the ghost until a
    reload."""
    import wiggly.editor.session as session_module
    from wiggly.editor.session import Sandbox, Session
    from wiggly.export import read_animation

    monkeypatch.setattr(session_module, "DRIVER_WATCH", 0.2)
    path, _ = drive_project(tmp_path)
    session = Session(Sandbox([tmp_path]))
    events = session.bus.subscribe()
    session.open(str(path))
    try:
        first = _session_final(session).positions.copy()
        stamp = session.describe()["driver_stamp"]
        walk = read_animation(tmp_path / "walk.npz")
        lifted = walk.positions + np.array([0.0, 0.2, 0.0], np.float32)
        write_animation(tmp_path / "walk.npz", SurfaceAnimation(walk.times, lifted, walk.faces),
                        overwrite=True)
        said = first_event(events, lambda e: e["type"] == "notice" and
                           "walk.npz changed on disk" in e["message"], 60.0)
        assert said is not None
        assert session.describe()["driver_stamp"] != stamp
        for _ in range(60):
            now = _session_final(session).positions
            if np.abs(now - first).max() > 0.1:
                break
            time.sleep(0.5)
        assert np.abs(now - first).max() > 0.1  # the body follows the lifted driver
    finally:
        session.close()


def test_after_the_drivers_last_frame_the_ghost_holds_it(chromium, tmp_path):
    """A 1.5 s shot of a 1 s driver: the motion holds the driver's last pose after its last
    frame, and so does the ghost (it vanished there, leaving nothing to compare with)."""
    from tests.editor_ui import post

    path, P = drive_project(tmp_path)
    server = serve(path)
    try:
        st, _ = post(server.url, "api/edit", {"op": "set", "section": "time",
                                              "values": {"end": 1.5}})
        assert st == 200
        with editor_page(chromium, server.url) as (page, errors):
            wait_final(page)
            page.wait_for_function("window.wiggly.driverInfo().loaded && "
                                   "window.wiggly.S.desc.scene.time.end === 1.5")
            page.evaluate("window.wiggly.setTime(1.3)")
            info = page.evaluate("window.wiggly.driverInfo()")
            assert info["visible"]
            ghost = np.asarray(info["positions"]).reshape(-1, 3)
            assert np.array_equal(ghost, P[-1].astype(np.float32))
            assert not errors, errors
    finally:
        server.stop()


def test_a_warped_drive_scene_shows_the_warped_solves_warnings(tmp_path):
    """A warped [drive] scene whose driver turns the bar by 90 degrees in five frames (18
    per frame): the page says what `wiggly animate` warns of the warped motion (its frames
    too far apart for the turn), not the linear preview's warning for `warp = false` scenes
    (it showed that one, and never the warped solve's)."""
    path, _ = drive_project(tmp_path)
    V, T = box_mesh((8, 2, 2), (0.8, 0.1, 0.1))
    times = np.arange(21) / FPS
    pivot = np.array([0.15, 0.05, 0.05])
    P = np.array([Rotation.from_euler("y", 90.0 * min(k / 5, 1.0), degrees=True)
                  .apply(V - pivot) + pivot for k in range(len(times))])
    write_animation(tmp_path / "walk.npz",
                    SurfaceAnimation(times, P, TetMesh(V, T).boundary_faces()), overwrite=True)
    said, later = _notices(path, SCENE.replace("warp = false", "warp = true"),
                           "from one frame to the next")
    assert said is not None and "by up to 18 degrees" in said["message"]
    assert not [m for m in later if "a linear secondary motion" in m], later
