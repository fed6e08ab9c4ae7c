"""The editor's server side: edits as pure functions, the sandbox, every endpoint with good and
bad requests, concurrent edits, autosave recovery.  A small structured tet mesh (no
tetrahedralizer) keeps every solve in milliseconds."""

from __future__ import annotations

import http.client
import json
import os
import queue
import socket
import threading
import time
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh

from wiggly.editor import EditorServer, Sandbox, Session
from wiggly.editor.bus import EventBus, Mailbox
from wiggly.editor.session import autosave_path
from wiggly.editor.state import EditError, EditorState, apply_edit, rebased, rigid_fit
from wiggly.primitives import box_mesh
from wiggly.scene import load_scene, save_scene

SCENE = """\
format = 1
[mesh]
path = "bar.vtu"
[material]
young = 1e6
[simulation]
modes = 12
fixed = ["left"]
[time]
end = 1.0
fps = 20
[groups.left]
box = { min = [-0.01, -1, -1], max = [0.01, 1, 1] }
[groups.right]
box = { min = [0.99, -1, -1], max = [1.01, 1, 1] }
[[keyframes]]
time = 0.5
group = "right"
position = { offset = [0.0, 0.05, 0.0] }
"""


@pytest.fixture
def project(tmp_path) -> Path:
    """A directory with a tet-mesh bar (1 x 0.1 x 0.1 m) and a scene using it."""
    V, T = box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    meshio.write(tmp_path / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    (tmp_path / "shot.toml").write_text(SCENE)
    return tmp_path


@pytest.fixture
def server(project):
    session = Session(Sandbox([project]))
    session.open(str(project / "shot.toml"))
    srv = EditorServer(session, "127.0.0.1", 0, max_json=64 * 1024, max_upload=256 * 1024)
    srv.start()
    yield srv
    srv.stop()


def call(srv, method, path, body=None, headers=None, raw: bytes | None = None):
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=10)
    h = {"Content-Type": "application/json"}
    h.update(headers or {})
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    conn.request(method, path, body=data, headers=h)
    r = conn.getresponse()
    payload = r.read()
    conn.close()
    if r.getheader("Content-Type", "").startswith("application/json"):
        return r.status, json.loads(payload)
    return r.status, payload


def wait_final(session: Session, timeout: float = 150.0):
    """The final frames of the session's current version (bounded wait: the physics child
    runs at nice +5, and a busy test machine can delay it by a minute)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        fs = session.latest_frames(final=True)
        if fs is not None and fs.version == session.version:
            return fs
        time.sleep(0.02)
    raise AssertionError(f"no final frames for version {session.version} in {timeout} s")


# ----------------------------------------------------------------------------------------------
# edits: pure functions


@pytest.fixture
def state(project) -> EditorState:
    return EditorState.of(load_scene(project / "shot.toml"))


def test_groups_without_a_colour_get_the_palettes_as_in_previews(state):
    """The page coloured every group without its own colour orange; it now gets the colour
    the previews draw it in (the palette, in the groups' order)."""
    from wiggly.editor.state import state_to_json
    from wiggly.scene import PALETTE

    scene = state.scene
    colors = state_to_json(state)["group_colors"]
    assert list(colors) == list(scene.groups) and colors == scene.group_colors()
    for i, (name, g) in enumerate(scene.groups.items()):
        assert colors[name] == (g.color or PALETTE[i % len(PALETTE)])
    bare = [name for name, g in scene.groups.items() if g.color is None]
    assert len({colors[n] for n in bare}) == min(len(bare), len(PALETTE))


def test_the_mesh_scale_and_up_axis_are_set_in_the_editor(state):
    """The units warning names mesh.scale and the axes warning mesh.up_axis: both can be set
    by an edit (they were refused: 'mesh.scale cannot be set here')."""
    s = apply_edit(state, {"op": "set", "section": "mesh",
                           "values": {"scale": 0.01, "up_axis": "z"}})
    assert s.scene.mesh.scale == 0.01 and s.scene.mesh.up == "z"
    with pytest.raises(EditError, match=r'mesh.up_axis = "x" must be "y" or "z"'):
        apply_edit(state, {"op": "set", "section": "mesh", "values": {"up_axis": "x"}})


def test_group_edits(state):
    s = apply_edit(state, {"op": "set_group", "name": "mid", "indices": [5, 3, 3, 4],
                           "color": "#00FF00"})
    g = s.scene.groups["mid"]
    assert g.selector.indices == (3, 4, 5) and g.color == "#00ff00"
    s = apply_edit(s, {"op": "rename_group", "name": "right", "new_name": "tip"})
    assert "right" not in s.scene.groups and s.scene.keyframes[0].group == "tip"
    s = apply_edit(s, {"op": "rename_group", "name": "left", "new_name": "base"})
    assert s.scene.simulation.fixed == ("base",)
    s = apply_edit(s, {"op": "recolor_group", "name": "tip", "color": "#123456"})
    assert s.scene.groups["tip"].color == "#123456"
    s = apply_edit(s, {"op": "set_fixed", "name": "base", "fixed": False})
    assert s.scene.simulation.fixed == ()
    s = apply_edit(s, {"op": "delete_group", "name": "tip"})
    assert "tip" not in s.scene.groups and s.scene.keyframes == [] and s.keyframe_ids == ()


def test_keyframe_edits_keep_ids(state):
    s = apply_edit(state, {"op": "add_keyframe", "time": 0.0, "group": "right"})
    s = apply_edit(s, {"op": "add_keyframe", "time": 1.0, "group": "left",
                       "position": {"rotation": [0, 0, 30], "translation": [0, 0.1, 0]},
                       "velocity": [0, 1, 0], "stiffness": 1e4, "name": "lift"})
    assert s.keyframe_ids == (0, 1, 2)
    assert s.scene.keyframes[1].position.__class__.__name__ == "Rest"
    s = apply_edit(s, {"op": "delete_keyframe", "id": 1})
    assert s.keyframe_ids == (0, 2)
    s = apply_edit(s, {"op": "update_keyframe", "id": 2, "time": 0.25, "velocity": None})
    k = s.scene.keyframes[1]
    assert (k.time, k.velocity, k.stiffness, k.name) == (0.25, None, 1e4, "lift")
    s = apply_edit(s, {"op": "set", "section": "material", "values": {"young": 5e5}})
    assert s.scene.material.young == 5e5
    s = apply_edit(s, {"op": "set", "section": "time", "values": {"duration": 2.0}})
    assert s.scene.time_range() == (0.0, 2.0)


BAD_EDITS = [
    ("not an object", 400), ({"nop": 1}, 400), ({"op": 5}, 400), ({"op": "explode"}, 400),
    ({"op": "set_group", "name": "x"}, 400),
    ({"op": "set_group", "name": "a b", "indices": [1]}, 400),
    ({"op": "set_group", "name": "x", "indices": []}, 400),
    ({"op": "set_group", "name": "x", "indices": [1.5]}, 400),
    ({"op": "set_group", "name": "x", "indices": [True]}, 400),
    ({"op": "set_group", "name": "x", "indices": [10**9]}, 400),
    ({"op": "set_group", "name": "x", "indices": [-1]}, 400),
    ({"op": "set_group", "name": "x", "indices": [1], "color": "red"}, 400),
    ({"op": "set_group", "name": "x", "indices": [1], "on": "volume"}, 400),
    ({"op": "rename_group", "name": "nope", "new_name": "x"}, 404),
    ({"op": "rename_group", "name": "left", "new_name": "right"}, 400),
    ({"op": "delete_group", "name": "nope"}, 404),
    ({"op": "set_fixed", "name": "left", "fixed": "yes"}, 400),
    ({"op": "add_keyframe", "time": "soon", "group": "left"}, 400),
    ({"op": "add_keyframe", "time": float("nan"), "group": "left"}, 400),
    ({"op": "add_keyframe", "time": 0.5, "group": "nope"}, 400),
    ({"op": "add_keyframe", "time": 7.0, "group": "left"}, 400),
    ({"op": "add_keyframe", "time": 0.5, "group": "left", "position": "up"}, 400),
    ({"op": "add_keyframe", "time": 0.5, "group": "left", "velocity": [1, 2]}, 400),
    ({"op": "add_keyframe", "time": 0.5, "group": "left", "stiffness": -1}, 400),
    ({"op": "update_keyframe", "id": 99, "time": 0.1}, 404),
    ({"op": "update_keyframe", "id": "0", "time": 0.1}, 400),
    ({"op": "update_keyframe", "id": 0, "time": None}, 400),
    ({"op": "delete_keyframe", "id": 42}, 404),
    ({"op": "set", "section": "mesh", "values": {"path": "/etc/passwd"}}, 400),
    ({"op": "set", "section": "evil", "values": {}}, 400),
    ({"op": "set", "section": "material", "values": {"young": -1}}, 400),
    ({"op": "set", "section": "material", "values": {"young": "stiff"}}, 400),
    ({"op": "set", "section": "material", "values": [1]}, 400),
    ({"op": "set", "section": "simulation", "values": {"modes": 0}}, 400),
]


@pytest.mark.parametrize(("op", "status"), BAD_EDITS)
def test_bad_edits_are_refused(state, op, status):
    with pytest.raises(EditError) as err:
        apply_edit(state, op, n_vertices=100)
    assert err.value.status == status
    assert str(err.value)


def test_rigid_fit_recovers_a_rigid_motion():
    from scipy.spatial.transform import Rotation

    X = np.random.default_rng(0).normal(size=(30, 3))
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    c = X.mean(axis=0)
    x = (X - c) @ R.T + c + [0.1, 0.2, -0.3]
    fit = rigid_fit(X, x)
    assert np.allclose(fit["rotation"], [10, -20, 35], atol=1e-5)
    assert np.allclose(fit["translation"], [0.1, 0.2, -0.3], atol=1e-8)
    # the rest pose as playback holds it (single precision): a rest key, not a noisy rigid one
    assert rigid_fit(X, X.astype(np.float32).astype(float)) == "rest"
    tiny = rigid_fit(X, X + np.array([1e-3, 0.0, 0.0]))  # a millimetre is a pose, and has no "-0.0"
    assert tiny != "rest" and tiny["translation"][0] == pytest.approx(1e-3)
    assert all(str(v) != "-0.0" for v in tiny["rotation"] + tiny["translation"])


def test_rebased_keeps_files(project, state):
    (project / "sub").mkdir()
    moved = rebased(state.scene, project / "sub" / "copy.toml")
    assert moved.mesh.path == "../bar.vtu"
    assert moved.mesh_file().resolve() == (project / "bar.vtu").resolve()


# ----------------------------------------------------------------------------------------------
# sandbox


def test_sandbox_refuses_escapes(tmp_path):
    root = tmp_path / "root"
    (root / "d").mkdir(parents=True)
    (root / "d" / "a.toml").write_text("")
    (tmp_path / "secret.toml").write_text("")
    os.symlink(tmp_path / "secret.toml", root / "link.toml")
    os.symlink(tmp_path, root / "up")
    sb = Sandbox([root])
    assert sb.resolve("d/a.toml", must_exist=True) == (root / "d" / "a.toml").resolve()
    assert sb.resolve(str(root / "d" / "a.toml")) == (root / "d" / "a.toml").resolve()
    for bad in ["../secret.toml", "d/../../secret.toml", str(tmp_path / "secret.toml"),
                "link.toml", "up/secret.toml", "/etc/passwd", "~/x.toml"]:
        with pytest.raises(EditError) as err:
            sb.resolve(bad)
        assert err.value.status == 403, bad
    for bad in ["", "a\x00b", 5, None, "x" * 5000]:
        with pytest.raises(EditError):
            sb.resolve(bad)
    with pytest.raises(EditError):
        sb.resolve("d/a.toml", suffixes=(".obj",))
    with pytest.raises(EditError) as err:
        sb.resolve("missing.toml", must_exist=True)
    assert err.value.status == 404
    assert "link.toml" not in sb.listing((".toml",))


# ----------------------------------------------------------------------------------------------
# plumbing


def test_the_physics_parent_knows_which_models_its_child_holds(tmp_path):
    """The parent sends a model only to a child without it; both keep the two models used
    last (wiggly.memo), so after models A, B, the modes of A and model C the child still
    holds A, as the parent assumes (a first-in-first-out child had dropped A)."""
    from wiggly.editor.physics import Preparer, model_key

    scenes = {}
    for name, cells in (("a", (4, 1, 1)), ("b", (5, 1, 1)), ("c", (6, 1, 1))):
        folder = tmp_path / name
        folder.mkdir()
        V, T = box_mesh(cells, (1.0, 0.1, 0.1))
        meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
        (folder / "shot.toml").write_text(SCENE.replace("modes = 12", "modes = 8"))
        scenes[name] = load_scene(folder / "shot.toml")
    preparer, models = Preparer(), {}

    def load(name: str) -> None:
        scene = scenes[name]
        m = scene.mesh
        _, models[name] = preparer.call(
            ("model", model_key(scene), str(scene.mesh_file()), m.resolution, m.edge_length,
             m.repair, m.metres_per_unit, m.up), lambda _: None, lambda: False)

    def modes(name: str):
        from wiggly.scene import scene_to_dict

        scene, key = scenes[name], model_key(scenes[name])
        sent = None if preparer.knows(key) else models[name]
        return preparer.call(("modes", key, sent, scene_to_dict(scene), scene.source),
                             lambda _: None, lambda: False)[1]

    try:
        load("a")
        load("b")
        assert modes("a").r == 8
        load("c")
        assert preparer.knows(model_key(scenes["a"])) and not preparer.knows(
            model_key(scenes["b"]))
        assert modes("a").r == 8  # sent no model: the child has it
        assert modes("b").r == 8  # sent again
    finally:
        preparer.close()


def test_what_the_physics_process_warns_of_reaches_the_page(tmp_path):
    """A mesh that fTetWild must repair (an open box) is meshed in the physics process; its
    warning reaches the parent before the model (the page shows it as a notice) instead of
    being printed raw on the editor's terminal."""
    from wiggly.editor.physics import Preparer

    box = trimesh.creation.box()
    keep = ~np.isclose(box.vertices[box.faces][:, :, 1], 0.5).all(axis=1)
    trimesh.Trimesh(box.vertices, box.faces[keep], process=False).export(tmp_path / "box.obj")
    said: list[str] = []
    preparer = Preparer(said.append)
    try:
        kind, model = preparer.call(("model", ("box",), str(tmp_path / "box.obj"), 8, None,
                                     True, 1.0, "y"), lambda _: None, lambda: False)
    finally:
        preparer.close()
    assert kind == "model" and model.tets.n_tets > 0
    assert len(said) == 1 and "the surface has 4 open edges" in said[0], said


def test_mailbox_newest_wins():
    box = Mailbox()
    for i in range(5):
        box.put(i)
    assert box.pending() and box.take(0.1) == 4 and box.dropped == 4
    assert box.take(0.01) is None
    box.close()
    assert box.take() is None


def test_event_bus_replays_last_events_and_bounds_queues():
    bus = EventBus(backlog=3)
    bus.publish("state", version=1)
    q = bus.subscribe()
    assert q.get_nowait()["version"] == 1
    for i in range(10):
        bus.publish("solve", i=i)
    got = [q.get_nowait()["i"] for _ in range(q.qsize())]
    assert got[-1] == 9 and len(got) == 3
    bus.unsubscribe(q)
    assert bus.n_subscribers == 0


# ----------------------------------------------------------------------------------------------
# the HTTP server


def test_endpoints(server, project):
    st, d = call(server, "GET", "/api/state")
    assert st == 200 and d["open"] and set(d["groups"]) == {"left", "right"}
    assert d["scene"]["keyframes"][0]["id"] == 0 and not d["dirty"]
    st, mesh = call(server, "GET", "/api/mesh")
    n, m = np.frombuffer(mesh[:8], "<u4")
    assert st == 200 and len(mesh) == 8 + 12 * n + 12 * m
    st, page = call(server, "GET", "/")
    assert st == 200 and b"importmap" in page
    st, js = call(server, "GET", "/vendor/three.module.js")
    assert st == 200 and len(js) > 100_000
    st, files = call(server, "GET", "/api/files")
    assert "shot.toml" in files["scenes"] and "bar.vtu" in files["meshes"]

    fs = wait_final(server.session)
    st, data = call(server, "GET", f"/api/frames/{fs.id}")
    assert st == 200 and len(data) == fs.positions.nbytes
    assert fs.positions.shape == (21, n, 3)  # 1 s at 20 fps
    right = np.array(d["groups"]["right"])
    k = 10  # t = 0.5 s: the right end is lifted 5 cm
    lift = (fs.positions[k, right] - server.session.surface.vertices[right]).mean(axis=0)
    assert abs(lift[1] - 0.05) < 0.005

    st, r = call(server, "POST", "/api/edit", {"op": "add_keyframe", "time": 1.0,
                                               "group": "right", "position": "current"})
    assert st == 200 and r["changed"] and r["id"] == 1
    pos = server.session.scene.keyframes[1].position
    assert pos.__class__.__name__ == "Rigid"  # the pose of the playback at t = 1
    st, r = call(server, "POST", "/api/preview", {"op": "update_keyframe", "id": 1,
                                                  "position": {"offset": [0, 0.1, 0]}})
    assert st == 200 and r["seq"] > 0
    assert server.session.scene.keyframes[1].position == pos  # a preview changes nothing
    st, r = call(server, "POST", "/api/undo")
    assert r["changed"] and len(server.session.scene.keyframes) == 1
    st, r = call(server, "POST", "/api/redo")
    assert r["changed"] and len(server.session.scene.keyframes) == 2
    st, r = call(server, "POST", "/api/redo")
    assert st == 200 and not r["changed"]
    st, r = call(server, "POST", "/api/save", {"path": "saved.toml"})
    assert st == 200 and r["path"] == "saved.toml"
    assert load_scene(project / "saved.toml") == server.session.scene
    st, r = call(server, "POST", "/api/export", {"paths": ["out/shot.npz"], "overwrite": True})
    assert st == 200
    deadline = time.time() + 30
    while not (project / "out" / "shot.npz").exists() and time.time() < deadline:
        time.sleep(0.05)
    assert np.load(project / "out" / "shot.npz")["positions"].shape[1] == n
    st, r = call(server, "PUT", "/api/upload?name=up.vtu", raw=(project / "bar.vtu").read_bytes(),
                 headers={"X-Wiggly-Upload": "1", "Content-Type": "application/octet-stream"})
    assert st == 200 and r["path"] == "uploads/up.vtu"
    st, r = call(server, "POST", "/api/open", {"path": r["path"]})
    assert st == 200 and server.session.scene.mesh.path == "up.vtu"
    st, d = call(server, "GET", "/api/state")
    assert d["scene"]["groups"] == {} and d["path"] == "uploads/up.toml"


def test_event_stream(server):
    conn = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    conn.sendall(b"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    data = b""
    deadline = time.time() + 10
    while b'"type":"state"' not in data and time.time() < deadline:
        data += conn.recv(65536)
    conn.close()
    assert b"text/event-stream" in data and b'"type":"state"' in data


def test_bad_requests_never_hurt(server, project):
    before = server.session.scene
    version = server.session.version
    for op, _ in BAD_EDITS:
        st, r = call(server, "POST", "/api/edit", op)
        assert st in (400, 404) and "error" in r, op
        st, r = call(server, "POST", "/api/preview", op)
        assert st in (400, 404), op
    checks = [
        ("POST", "/api/edit", None, {}, b"{not json"),
        ("POST", "/api/edit", None, {}, b"\xff\xfe"),
        ("POST", "/api/edit", None, {"Content-Type": "text/plain"}, b'{"op": "set"}'),
        ("POST", "/api/open", {"path": "../outside.toml"}, {}, None),
        ("POST", "/api/open", {"path": "/etc/passwd"}, {}, None),
        ("POST", "/api/open", {"path": 12}, {}, None),
        ("POST", "/api/open", {}, {}, None),
        ("POST", "/api/open", [], {}, None),
        ("POST", "/api/open", {"path": "missing.toml"}, {}, None),
        ("POST", "/api/open", {"path": "builtin:dragon"}, {}, None),
        ("POST", "/api/save", {"path": "../escape.toml"}, {}, None),
        ("POST", "/api/save", {"path": "shot.obj"}, {}, None),
        ("POST", "/api/export", {"paths": ["../../x.glb"]}, {}, None),
        ("POST", "/api/export", {"paths": "x.glb"}, {}, None),
        ("POST", "/api/export", {"paths": ["x.exe"]}, {}, None),
        ("POST", "/api/export", {"paths": ["x.glb"], "overwrite": "yes"}, {}, None),
        ("PUT", "/api/upload?name=../x.obj", None, {"X-Wiggly-Upload": "1"}, b"v 0 0 0"),
        ("PUT", "/api/upload?name=x.exe", None, {"X-Wiggly-Upload": "1"}, b"MZ"),
        ("PUT", "/api/upload?name=x.obj", None, {}, b"v 0 0 0"),
        ("PUT", "/api/upload?name=big.obj", None, {"X-Wiggly-Upload": "1"}, b"v" * 300_000),
        ("POST", "/api/edit", None, {}, b" " * 100_000),
        ("GET", "/api/frames/999999", None, {}, None),
        ("GET", "/api/nothing", None, {}, None),
        ("DELETE", "/api/state", None, {}, None),
        ("GET", "/../../../etc/passwd", None, {}, None),
        ("GET", "/%2e%2e/%2e%2e/etc/passwd", None, {}, None),
        ("GET", "/api/state", None, {"Host": "evil.example:80"}, None),
        ("POST", "/api/undo", {}, {"Origin": "http://evil.example"}, None),
    ]
    for method, path, body, headers, raw in checks:
        st, r = call(server, method, path, body, headers, raw)
        assert 400 <= st < 500 or st == 501, (method, path, st, r)
    # a huge announced body is refused before it is read
    conn = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    conn.sendall(b"POST /api/edit HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json"
                 b"\r\nContent-Length: 10000000000\r\n\r\n{")
    assert b" 413 " in conn.recv(4096)
    conn.close()
    for head in (b"Transfer-Encoding: chunked\r\n", b""):  # no Content-Length
        conn = socket.create_connection(("127.0.0.1", server.port), timeout=10)
        conn.sendall(b"POST /api/edit HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
                     b"application/json\r\n" + head + b"\r\n")
        assert b" 411 " in conn.recv(4096)
        conn.close()
    conn = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    conn.sendall(b"\x16\x03\x01garbage\r\n\r\n")  # not HTTP at all
    conn.recv(4096)
    conn.close()
    assert not (project.parent / "escape.toml").exists()
    assert server.session.scene == before and server.session.version == version
    st, d = call(server, "GET", "/api/state")
    assert st == 200 and d["version"] == version


def test_connection_limit(project):
    session = Session(Sandbox([project]))
    srv = EditorServer(session, "127.0.0.1", 0, max_connections=3).start()
    try:
        idle = [socket.create_connection(("127.0.0.1", srv.port), timeout=5) for _ in range(6)]
        time.sleep(0.2)
        closed = 0
        for s in idle[3:]:  # over the limit: closed by the server at once
            s.settimeout(5)
            closed += s.recv(16) == b""
        assert closed == 3
        for s in idle[:3]:
            s.close()
        deadline = time.time() + 5
        while time.time() < deadline:
            try:
                st, d = call(srv, "GET", "/api/state")
                break
            except (ConnectionError, http.client.HTTPException):
                time.sleep(0.05)
        assert st == 200 and d["open"] is False
    finally:
        srv.stop()


def test_concurrent_edits(server):
    n_threads, per_thread = 6, 8
    errors: list = []

    def work(t: int) -> None:
        try:
            for i in range(per_thread):
                st, r = call(server, "POST", "/api/edit", {
                    "op": "set_group", "name": f"g{t}_{i}", "indices": [t, i + 10]})
                assert st == 200, r
                st, r = call(server, "POST", "/api/edit", {
                    "op": "add_keyframe", "time": round(0.1 * (i % 10), 2), "group": f"g{t}_{i}"})
                assert st == 200, r
                call(server, "GET", "/api/state")
        except Exception as err:  # pragma: no cover - reported below
            errors.append(err)

    threads = [threading.Thread(target=work, args=(t,), daemon=True) for t in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not any(t.is_alive() for t in threads) and not errors, errors
    scene = server.session.scene
    assert len(scene.groups) == 2 + n_threads * per_thread
    assert len(scene.keyframes) == 1 + n_threads * per_thread
    ids = server.session.state.keyframe_ids
    assert len(set(ids)) == len(ids)
    fs = wait_final(server.session, timeout=60)  # the newest state is solved
    assert fs.version == server.session.version


def test_autosave_recovery_after_a_crash(project):
    s1 = Session(Sandbox([project]))
    s1.open("shot.toml")
    s1.edit({"op": "set_group", "name": "mid", "indices": [40, 41, 42]})
    s1.edit({"op": "add_keyframe", "time": 0.2, "group": "mid", "velocity": [0, 1, 0]})
    edited = s1.scene
    s1.close()  # no save: the process dies
    assert load_scene(project / "shot.toml") != edited
    auto = autosave_path(project / "shot.toml")
    assert auto.exists()
    # ... while writing the autosave and the journal: their half-written temporaries stay
    parts = [p.with_name(p.name + ".part") for p in (auto, project / ".shot.history.jsonl")]
    for part in parts:
        part.write_text("")
        os.utime(part, (time.time() - 120, time.time() - 120))

    s2 = Session(Sandbox([project]))
    opened = s2.open("shot.toml")
    assert any("recovered" in n for n in opened["notices"])
    assert s2.scene == edited and s2.dirty
    assert not any(part.exists() for part in parts)  # the restart removed them
    s2.save()
    assert not auto.exists() and load_scene(project / "shot.toml") == edited
    s2.close()

    auto.write_text("this is [not toml")  # a broken autosave is ignored, with a notice
    s3 = Session(Sandbox([project]))
    opened = s3.open("shot.toml")
    assert s3.scene == edited and any("ignored" in n for n in opened["notices"])
    s3.close()


def test_unsaved_new_scene_is_recovered(project):
    s1 = Session(Sandbox([project]))
    s1.open("bar.vtu")  # a new scene: bar.toml (not written until saved)
    s1.edit({"op": "set_group", "name": "end", "indices": [0, 1, 2]})
    edited = s1.scene
    s1.close()
    assert not (project / "bar.toml").exists()
    s2 = Session(Sandbox([project]))
    opened = s2.open("bar.toml")
    assert s2.scene == edited and any("unsaved" in n for n in opened["notices"])
    assert s2.recoverable() == ["bar.toml"]
    s3 = Session(Sandbox([project]))
    s3.open("bar.vtu")  # never overwrites: the next new scene gets another name
    assert s3.scene.source.name == "bar-2.toml"
    s2.close()
    s3.close()


def test_save_round_trip_exact(server, project):
    call(server, "POST", "/api/edit", {"op": "add_keyframe", "time": 0.75, "group": "right",
                                       "position": {"rotation": [12.5, 0, -3], "center":
                                                    [1.0, 0.0, 0.0]}, "stiffness": 1e4})
    call(server, "POST", "/api/save", {})
    text = (project / "shot.toml").read_text()
    scene = load_scene(project / "shot.toml")
    assert scene == server.session.scene
    assert text.startswith(SCENE.splitlines()[0] + "\n[mesh]\n")  # the file's own layout
    save_scene(scene, project / "again.toml")  # a fresh file: wiggly's own layout
    assert load_scene(project / "again.toml") == scene


def test_solve_matches_library(server):
    """The editor's final frames are the library's solve of the same scene."""
    from wiggly.scene import build
    from wiggly.solve import solve

    fs = wait_final(server.session)
    scene = server.session.scene
    body, keys = build(scene)
    anim = solve(body, keys, start=0.0, end=1.0, warp=True)
    ref = anim.positions(anim.frame_times(scene.time.fps), dtype=np.float32)
    assert np.abs(ref - fs.positions).max() < 1e-4


def test_a_looping_scene_loops_in_the_editor(project):
    """A scene with ``[time] loop = true``: the editor's final (warped) frames are the
    library's solve of the scene (scene.solve_scene), and the motion ends where it began."""
    from wiggly.scene import build, solve_scene

    (project / "loop.toml").write_text(SCENE.replace("end = 1.0\n", "end = 1.0\nloop = true\n"))
    session = Session(Sandbox([project]))
    session.open(str(project / "loop.toml"))
    try:
        fs = wait_final(session)
        scene = session.scene
        assert scene.time.loop
        body, keys = build(scene)
        anim = solve_scene(scene, body, keys)
        ref = anim.positions(anim.frame_times(scene.time.fps), dtype=np.float32)
        assert np.abs(ref - fs.positions).max() < 1e-4
        size = float(np.ptp(body.rest_positions(), axis=0).max())
        assert np.abs(fs.positions[0] - fs.positions[-1]).max() < 1e-6 * size
        assert np.abs(fs.positions[len(fs.positions) // 2] - fs.positions[0]).max() > 1e-3 * size
    finally:
        session.close()


def test_cli_edit(project, capsys):
    import argparse

    from wiggly.cli import edit

    parser = argparse.ArgumentParser()
    edit.add_args(parser)
    args = parser.parse_args([str(project / "shot.toml"), "--port", "0", "--no-browser"])
    assert args.host == "127.0.0.1"  # this machine only, unless told otherwise
    assert edit.roots_for(args.path, []) == [project.resolve()]
    assert edit.exposure_warning("127.0.0.1") is None and edit.exposure_warning("::1") is None
    assert "trusted network" in edit.exposure_warning("0.0.0.0")
    srv = edit.start(args)
    try:
        st, d = call(srv, "GET", "/api/state")
        assert st == 200 and d["path"] == "shot.toml"
    finally:
        srv.stop()
    with pytest.raises(Exception, match="no such file"):
        edit.start(parser.parse_args([str(project / "missing.toml"), "--port", "0"]))


# ----------------------------------------------------------------------------------------------
# drag previews, undo per tab


def test_drag_previews_keep_the_final_frames(server):
    """Previews (gizmo drags) neither evict the final frames nor are replayed to new tabs;
    cancelling a drag announces the scene's frames again."""
    session = server.session
    final = wait_final(session)
    for k in range(12):
        seq = session.preview({"op": "update_keyframe", "id": 0,
                               "position": {"offset": [0, 0.01 * k, 0]}})["seq"]
        deadline = time.time() + 10  # let each preview be solved (else newer ones replace it)
        while session.latest_frames().seq < seq:
            assert time.time() < deadline
            time.sleep(0.01)
        assert session.latest_frames().kind == "drag"
    assert session.frames(final.id) is final and session.latest_frames(final=True) is final
    replayed = session.bus.subscribe()
    events = [replayed.get_nowait() for _ in range(replayed.qsize())]
    frames = [e for e in events if e["type"] == "frames"]
    assert frames and frames[-1]["request"] == "final" and frames[-1]["id"] == final.id
    seq = session.cancel_preview()["seq"]
    restored = session.latest_frames()
    assert restored.seq == seq and restored.kind == "final"
    assert np.array_equal(restored.positions, final.positions)


def test_a_page_gone_mid_drag_leaves_no_preview(server):
    """A page reloaded, closed or crashed mid-drag sends no cancel: when its event stream
    ends the server abandons its drag, so the other tabs show the scene's frames again.  A
    cancel from another page leaves the drag alone."""
    session = server.session
    final = wait_final(session)
    stream = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    stream.sendall(b"GET /api/events?page=pageA HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    assert b"text/event-stream" in stream.recv(65536)
    op = {"op": "update_keyframe", "id": 0, "position": {"offset": [0, 0.2, 0]}}
    st, d = call(server, "POST", "/api/preview", op, headers={"X-Wiggly-Page": "pageA"})
    assert st == 200
    deadline = time.time() + 10
    while session.latest_frames().seq < d["seq"]:
        assert time.time() < deadline
        time.sleep(0.01)
    assert session.latest_frames().kind == "drag"
    st, other = call(server, "POST", "/api/preview/cancel", {}, headers={"X-Wiggly-Page": "pageB"})
    assert st == 200 and other["seq"] is None and session.latest_frames().kind == "drag"
    stream.close()  # the page is gone, mid-drag
    deadline = time.time() + 5
    while session.latest_frames().kind == "drag":
        assert time.time() < deadline, "the abandoned drag's preview is still shown"
        time.sleep(0.02)
    assert np.array_equal(session.latest_frames().positions, final.positions)
    st, bad = call(server, "POST", "/api/preview", op, headers={"X-Wiggly-Page": "no/slash"})
    assert st == 400 and "page id" in bad["error"]


def test_the_status_says_warped_refinement_runs(server):
    """Between the linear frames and the warped refinement's first progress (which may load
    the body first) the page is told that the refinement runs, not "solving (linear)"."""
    session = server.session
    wait_final(session)
    events = session.bus.subscribe()
    version = session.edit({"op": "update_keyframe", "id": 0,
                            "position": {"offset": [0, 0.08, 0]}})["version"]
    stages: list[str] = []
    deadline = time.time() + 60
    while "done" not in stages:
        assert time.time() < deadline, stages
        e = events.get(timeout=60)
        if e["type"] == "solve" and e["version"] == version:
            stages.append(e["stage"])
    assert stages[0] == "linear" and stages[1] == "refining", stages
    assert "refining" not in stages[2:] and stages[-1] == "done", stages


def test_a_held_drag_gets_warped_frames(server):
    """A drag preview of a warped scene is refined warped when no newer request comes (the
    gizmo holds still): frames of request "drag", never final, equal to the warped frames of
    the same edit once committed; the committed final frames stay the newest final ones."""
    session = server.session
    final = wait_final(session)
    op = {"op": "update_keyframe", "id": 0, "position": {"offset": [0.0, 0.2, 0.0]}}
    seq = session.preview(op)["seq"]
    deadline = time.time() + 30
    while True:
        held = session.latest_frames()
        if held.seq == seq and held.stage == "warped":
            break
        assert time.time() < deadline, "no warped frames for the held drag"
        time.sleep(0.02)
    assert held.kind == "drag" and not held.final
    assert session.latest_frames(final=True) is final
    assert session.playback.latest(committed=True).seq < seq
    linear = next(fs for fs in map(session.frames, range(held.id - 1, final.id, -1))
                  if fs.seq == seq)  # published before the warped ones, kept (FRAME_SETS_KEPT)
    assert linear.stage == "linear" and linear.kind == "drag"
    assert np.abs(held.positions - linear.positions).max() > 1e-3  # warped, not linear
    session.edit(op)
    committed = wait_final(session)
    assert committed.kind == "final" and committed.stage == "warped"
    assert np.abs(held.positions - committed.positions).max() < 1e-4


def test_undo_belongs_to_the_tab_that_edited(project):
    session = Session(Sandbox([project]))
    try:
        session.open("shot.toml")
        session.edit({"op": "set", "section": "material", "values": {"young": 3e6}}, tab="a")
        session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.7}}, tab="b")
        session.edit({"op": "update_keyframe", "id": 0, "time": 0.25}, tab="a")
        assert session.undo("a")["changed"]  # a's last edit only
        assert session.scene.keyframes[0].time == 0.5 and session.scene.damping.alpha == 0.7
        assert session.undo("a")["changed"]
        assert session.scene.material.young == 1e6 and session.scene.damping.alpha == 0.7
        assert not session.undo("a")["changed"]
        assert session.describe("b")["can_undo"] and not session.describe("b")["can_redo"]
        assert session.describe("a")["redo_label"] == "set material.young"
        # another tab changed what a redo would overwrite: refused, and the step dropped
        session.edit({"op": "set", "section": "material", "values": {"young": 3e6}}, tab="b")
        with pytest.raises(EditError) as err:
            session.redo("a")
        assert err.value.status == 409 and "changed since" in str(err.value)
        assert session.scene.material.young == 3e6
        assert session.redo("a")["changed"]  # the keyframe step, untouched by b
        assert session.scene.keyframes[0].time == 0.25
    finally:
        session.close()


def test_undo_histories_survive_a_restart(project):
    s1 = Session(Sandbox([project]))
    s1.open("shot.toml")
    s1.edit({"op": "add_keyframe", "time": 0.2, "group": "right"}, tab="a")
    s1.edit({"op": "delete_keyframe", "id": 0}, tab="b")
    ids, scene = s1.state.keyframe_ids, s1.scene
    s1.close()  # the process dies
    s2 = Session(Sandbox([project]))
    try:
        s2.open("shot.toml")
        assert s2.scene == scene and s2.state.keyframe_ids == ids == (1,)
        assert s2.undo("b")["changed"]  # the deleted keyframe comes back under its id
        assert s2.state.keyframe_ids == (0, 1) and s2.scene.keyframes[0].time == 0.5
        assert s2.undo("a")["changed"] and s2.state.keyframe_ids == (0,)
        s2.save()
    finally:
        s2.close()
    # the scene file changed behind the editor's back: the journal no longer applies
    text = (project / "shot.toml").read_text()
    assert text.count("young = 1e6") == 1  # the saved file keeps its own layout
    (project / "shot.toml").write_text(text.replace("young = 1e6", "young = 2e6"))
    s3 = Session(Sandbox([project]))
    try:
        opened = s3.open("shot.toml")
        assert any("changed outside the editor" in n for n in opened["notices"]), opened["notices"]
        assert not s3.describe("a")["can_redo"] and not s3.describe("b")["can_redo"]
    finally:
        s3.close()


def test_an_undo_that_would_make_the_scene_invalid_is_refused(project):
    session = Session(Sandbox([project]))
    try:
        session.open("shot.toml")
        session.edit({"op": "set_group", "name": "mid", "indices": [40, 41]}, tab="a")
        session.edit({"op": "add_keyframe", "time": 0.3, "group": "mid"}, tab="b")
        with pytest.raises(EditError) as err:  # the group b's keyframe needs
            session.undo("a")
        assert err.value.status == 409 and "would be invalid" in str(err.value)
        assert "mid" in session.scene.groups and not session.describe("a")["can_undo"]
    finally:
        session.close()


def test_save_never_overwrites_a_change_made_on_disk_unasked(server, project):
    """A scene file changed on disk after it was opened, or another existing file, is
    overwritten only with ``overwrite``; the 409 says which file and why."""
    call(server, "POST", "/api/edit", {"op": "add_keyframe", "time": 0.75, "group": "right",
                                       "position": {"offset": [0.0, 0.1, 0.0]}})
    shot = project / "shot.toml"
    theirs = shot.read_text() + "# changed in another program\n"
    shot.write_text(theirs)
    st, r = call(server, "POST", "/api/save", {})
    assert st == 409 and "shot.toml was changed on disk" in r["error"], r
    assert shot.read_text() == theirs  # untouched
    st, r = call(server, "POST", "/api/save", {"overwrite": True})
    assert st == 200, r
    assert load_scene(shot) == server.session.scene
    call(server, "POST", "/api/edit", {"op": "add_keyframe", "time": 0.5, "group": "right",
                                       "position": {"offset": [0.0, 0.2, 0.0]}})
    st, r = call(server, "POST", "/api/save", {})  # its own last save: no question
    assert st == 200, r
    other = project / "other.toml"
    other.write_text("# someone's notes\n")
    st, r = call(server, "POST", "/api/save", {"path": "other.toml"})
    assert st == 409 and "other.toml already exists" in r["error"], r
    assert other.read_text() == "# someone's notes\n"
    st, r = call(server, "POST", "/api/save", {"path": "other.toml", "overwrite": True})
    assert st == 200 and load_scene(other) == server.session.scene


def test_a_scene_file_changed_on_disk_is_said_once(server, project):
    """A text editor changes the scene file while the editor runs: a notice says so (it went
    unnoticed until Save), once per version on disk; the editor's own saves are not such a
    change."""
    session = server.session
    events = session.bus.subscribe()

    def told() -> list[str]:
        out = []
        while True:
            try:
                event = events.get_nowait()
            except queue.Empty:
                return out
            if event["type"] == "notice" and "was changed on disk" in event["message"]:
                out.append(event["message"])

    session.check_scene_file()
    assert told() == []
    shot = project / "shot.toml"
    shot.write_text(shot.read_text() + "# changed in another program\n")
    session.check_scene_file()
    said = told()
    assert len(said) == 1 and said[0].startswith("shot.toml was changed on disk by another "
                                                 "program: the editor keeps the scene"), said
    session.check_scene_file()  # the same version: said once
    assert told() == []
    st, r = call(server, "POST", "/api/save", {"overwrite": True})
    assert st == 200, r
    session.check_scene_file()  # the editor's own save
    assert told() == []


def test_a_read_only_folder_gets_a_clear_refusal(server, project, monkeypatch):
    """Saving into a folder that cannot be written is a 403 naming the folder and the way
    out, never an internal error; an edit that cannot be journaled says the same.  (The
    file system's refusal is simulated: root writes into folders without write permission.)"""
    import errno

    import wiggly.editor.history as history
    import wiggly.editor.session as session_module

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(project / ".shot.tmp"))

    monkeypatch.setattr(session_module, "save_scene", read_only)
    before = (project / "shot.toml").read_bytes()
    st, r = call(server, "POST", "/api/save", {})
    assert st == 403 and "cannot be written to" in r["error"] and "Save as" in r["error"], r
    assert str(project) in r["error"] and "Read-only file system" in r["error"]
    monkeypatch.setattr(history.os, "open", read_only)
    st, r = call(server, "POST", "/api/edit", {"op": "add_keyframe", "time": 0.25,
                                               "group": "right",
                                               "position": {"offset": [0, 0.1, 0]}})
    assert st == 403 and "cannot be written to" in r["error"], r
    assert "disk space" not in r["error"]
    monkeypatch.undo()
    assert (project / "shot.toml").read_bytes() == before


def test_an_undo_to_known_modes_says_they_are_ready(project):
    """Modes 8 -> 6, then undo: the body of 8 modes is made already, and the physics heading
    is told so again (it said '6 modes ready' before the undo)."""
    session = Session(Sandbox([project]))
    try:
        session.open("shot.toml")
        wait_final(session)
        before = session.scene.simulation.modes
        q = session.bus.subscribe()
        session.edit({"op": "set", "section": "simulation", "values": {"modes": before - 2}})
        wait_final(session)
        session.undo()
        wait_final(session)
        ready = []
        while not q.empty():
            e = q.get_nowait()
            if e["type"] == "physics" and e["stage"] == "ready":
                ready.append(e["modes"])
        assert ready and ready[-1] == before, ready
    finally:
        session.close()


def test_export_asks_before_overwriting_and_names_an_obj_sequence(server, project):
    """An export over existing files is a 409 naming them until ``overwrite``; an OBJ export
    says which frame files it wrote."""
    mine = project / "mine.glb"
    mine.write_bytes(b"not yours")
    st, r = call(server, "POST", "/api/export", {"paths": ["mine.glb"]})
    assert st == 409 and "mine.glb exists" in r["error"], r
    assert mine.read_bytes() == b"not yours"
    q = server.session.bus.subscribe()
    st, r = call(server, "POST", "/api/export", {"paths": ["seq/shot.obj"]})
    assert st == 200, r
    deadline, done = time.time() + 60, None
    while done is None and time.time() < deadline:
        try:
            e = q.get(timeout=1.0)
        except Exception:
            continue
        if e["type"] == "export" and e["stage"] != "running":
            done = e
    assert done is not None and done["stage"] == "done", done
    frames = sorted((project / "seq").glob("shot_*.obj"))
    assert frames and f"{frames[0].name} … {frames[-1].name} ({len(frames)} OBJ frames)" in \
        done["message"], done["message"]
    st, r = call(server, "POST", "/api/export", {"paths": ["seq/shot.obj"]})
    assert st == 409 and "seq/shot.obj exists" in r["error"], r
    st, r = call(server, "POST", "/api/export", {"paths": ["mine.glb"], "overwrite": True})
    assert st == 200


def test_an_export_overtaken_by_an_edit_says_it_has_the_earlier_scene(server, project,
                                                                      monkeypatch):
    """An edit made while an export runs is not in the files: the export's message says so
    (it said only "exported ..."); an export left alone says nothing of the kind.  The export
    writes only once the edit is in (on a loaded machine it could finish first)."""
    import threading

    import wiggly.scene

    q = server.session.bus.subscribe()
    real, gate = wiggly.scene.write_outputs, threading.Event()

    def gated(*args, **kwargs):
        assert gate.wait(60)
        return real(*args, **kwargs)

    monkeypatch.setattr(wiggly.scene, "write_outputs", gated)

    def export_and_wait(edit_meanwhile: bool) -> str:
        gate.clear()
        st, r = call(server, "POST", "/api/export", {"paths": ["takes/shot.npz"],
                                                     "overwrite": True})
        assert st == 200, r
        if edit_meanwhile:
            server.session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.9}})
        gate.set()
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                e = q.get(timeout=1.0)
            except Exception:
                continue
            if e["type"] == "export" and e["stage"] != "running":
                return e["message"]
        raise AssertionError("no export answer")

    said = export_and_wait(False)
    assert "edits made since are not in it" not in said
    assert said.startswith("exported takes/shot.npz"), said  # the path the page gave, not a name
    assert "edits made since are not in it" in export_and_wait(True)


def test_fall_notice_is_physics():
    """The notice measures the centroid's sink along gravity against the body's size: a free
    fall 1/2 g t^2 over 2 s (19.6 m for a 1 m body) is told, with its figures; a drop of
    one size, a rise, and no gravity are not."""
    from wiggly.editor.playback import fall_notice

    times = np.linspace(0.0, 2.0, 41)
    body = np.random.default_rng(3).random((50, 3))
    size = float(np.linalg.norm(np.ptp(body, axis=0)))
    fall = body[None] - (0.5 * 9.81 * times**2)[:, None, None] * np.array([0.0, 1.0, 0.0])
    notice = fall_notice(fall, times, (0.0, -9.81, 0.0), size)
    assert notice is not None and "falls 20 m by t = 2 s" in notice, notice
    assert fall_notice(fall, times, (0.0, 0.0, 0.0), size) is None
    assert fall_notice(fall[::-1], times, (0.0, -9.81, 0.0), size) is None  # rising
    sink = body[None] - np.linspace(0.0, size, 41)[:, None, None] * np.array([0.0, 1.0, 0.0])
    assert fall_notice(sink, times, (0.0, -9.81, 0.0), size) is None


def notices_over_two_solves(project, name: str, text: str, about: str) -> list[dict]:
    """Scene ``text`` saved as ``name``, opened, then edited once (two final solves): the
    page's notices whose message contains ``about``."""
    (project / name).write_text(text)
    session = Session(Sandbox([project]))
    q = session.bus.subscribe()
    try:
        session.open(name)
        wait_final(session)
        session.edit({"op": "set", "section": "damping", "values": {"alpha": 0.6}})
        wait_final(session)
    finally:
        session.close()
    events = [q.get_nowait() for _ in range(q.qsize())]
    return [e for e in events if e["type"] == "notice" and about in e["message"]]


def test_a_body_that_nothing_holds_gets_a_notice_once(project):
    """A free bar keyed at rest at t = 0 only, under gravity, falls off the view: the editor
    says why once for the scene file, not again after the next edit."""
    notices = notices_over_two_solves(
        project, "free.toml",
        SCENE.replace('fixed = ["left"]\n', "").replace("end = 1.0", "end = 2.0")
        .replace('position = { offset = [0.0, 0.05, 0.0] }', 'position = "rest"')
        .replace("time = 0.5", "time = 0.0"), "falls")
    assert len(notices) == 1 and "nothing holds it" in notices[0]["message"], notices


def test_the_solves_warnings_reach_the_page_once(project):
    """A key whose vertices are all fixed cannot be met: ``wiggly animate`` warns on the
    terminal, and the editor now says it in the page, once for the scene file (it only
    reached the editor's terminal before)."""
    notices = notices_over_two_solves(
        project, "held.toml", SCENE.replace('fixed = ["left"]', 'fixed = ["left", "right"]'),
        "held by the fixed vertices")
    assert len(notices) == 1 and notices[0]["level"] == "warning", notices
    assert "cannot be met" in notices[0]["message"]


def test_a_material_too_soft_for_the_body_gets_a_notice_once(project):
    """A held bar so soft that gravity alone bends it by more than a fifth of its size curls
    in a way linear elasticity models poorly: the page says so, as `wiggly animate` notes it,
    once for the scene file (it was said only on the command line before)."""
    notices = notices_over_two_solves(
        project, "soft.toml", SCENE.replace("young = 1e6", "young = 1e3"), "sag")
    assert len(notices) == 1 and "Raise material.young (1000 Pa;" in notices[0]["message"]


def test_a_warped_motion_that_folds_gets_a_notice_once(project):
    """Keys that push the bar's free end through its fixed one turn tets inside out in the
    warped frames: the page says where and why (``wiggly animate`` warns), once while the
    next edit keeps the fold."""
    notices = notices_over_two_solves(
        project, "folded.toml", SCENE.replace("[0.0, 0.05, 0.0]", "[-1.8, 0.0, 0.0]"),
        "inside out")
    assert len(notices) == 1 and notices[0]["level"] == "warning", notices
    assert "at t = 0.5 s" in notices[0]["message"]
    assert "anim.folds()" not in notices[0]["message"]  # the page has no Python
    assert "(the nearest group is '" in notices[0]["message"]


def test_each_scene_file_that_folds_gets_its_own_notice(project):
    """Two files whose motions fold, opened one after the other: a notice for each (the
    second was taken for the first one's lasting fold)."""
    folded = SCENE.replace("[0.0, 0.05, 0.0]", "[-1.8, 0.0, 0.0]")
    (project / "a.toml").write_text(folded)
    (project / "b.toml").write_text(folded.replace("time = 0.5", "time = 0.6"))
    session = Session(Sandbox([project]))
    q = session.bus.subscribe()
    try:
        for name in ("a.toml", "b.toml"):
            session.open(name)
            wait_final(session)
    finally:
        session.close()
    events = [q.get_nowait() for _ in range(q.qsize())]
    notices = [e["message"] for e in events if e["type"] == "notice" and "inside out" in
               e["message"]]
    assert len(notices) == 2 and "at t = 0.6 s" in notices[1], notices


def test_other_tabs_are_told_when_a_tab_opens_or_saves_as(server, project):
    """Save as (or Open) in one tab switches the whole editor to that file: the other tabs
    get a notice naming it (their title changed silently before); the tab that did it is
    not told (its notice names it), and a plain Save tells nobody."""
    events = server.session.bus.subscribe()
    st, _ = call(server, "POST", "/api/save", {"path": "copy.toml"},
                 headers={"X-Wiggly-Tab": "a"})
    assert st == 200
    st, _ = call(server, "POST", "/api/save", {}, headers={"X-Wiggly-Tab": "a"})
    st, _ = call(server, "POST", "/api/open", {"path": "shot.toml"},
                 headers={"X-Wiggly-Tab": "b"})
    assert st == 200
    notices = [e for e in (events.get_nowait() for _ in range(events.qsize()))
               if e["type"] == "notice" and "from_tab" in e]  # (not the solves' notices)
    assert [(e["from_tab"], e["message"]) for e in notices] == [
        ("a", "another tab saved the scene as copy.toml: this tab edits that file now"),
        ("b", "another tab opened shot.toml: this tab shows it now")], notices


def test_keys_the_final_warped_motion_misses_get_a_notice(project, monkeypatch):
    """A stiff bar (1e9 Pa) barely follows its 5 cm key: the final warped motion misses it by
    most of its offset, and the page says so as `wiggly animate` warns (the warped
    refinement ran with warnings off, so only a linear solve's misses were said). The linear
    solve's own notices are switched off here: this one comes from the warped frames."""
    from wiggly.editor.playback import Playback

    monkeypatch.setattr(Playback, "_tell_once", lambda self, scene, message: None)
    (project / "stiff.toml").write_text(SCENE.replace("young = 1e6", "young = 1e9"))
    session = Session(Sandbox([project]))
    q = session.bus.subscribe()
    try:
        session.open("stiff.toml")
        wait_final(session)
    finally:
        session.close()
    events = [q.get_nowait() for _ in range(q.qsize())]
    done = [e for e in events if e["type"] == "solve" and e.get("stage") == "done"]
    notices = [e["message"] for e in events
               if e["type"] == "notice" and "missed by more than" in e["message"]]
    assert done and len(notices) == 1, (notices, done)
    assert "stiff.toml: 1 keyframe missed by more than 5 % of the body's size or 50 % of " \
           "their offset from rest" in notices[0], notices
    assert "Young's modulus" in notices[0]


def test_playback_at_a_lower_frame_rate_is_said(tmp_path, monkeypatch):
    """A long shot of a fine surface plays at a lower rate than the scene's (its frames would
    pass the playback's memory cap): a notice says so, and that exports keep the scene's
    rate (the page played 22 of a 2M-vertex shot's 61 frames without a word)."""
    import wiggly.editor.refine as refine
    from tests.editor_ui import bar_project, notices

    monkeypatch.setattr(refine, "PLAYBACK_BYTES", 81 * 12 * 6)  # six frames of the bar
    path = bar_project(tmp_path, warp=False)
    session = Session(Sandbox([tmp_path]))
    events = session.bus.subscribe()
    session.open(str(path))
    try:
        wait_final(session)
        said = notices(events)
        assert any(m.startswith("playback shows 5 of the shot's 20 frames per second") and
                   "exports keep 20 fps" in m for m in said), said
    finally:
        session.close()


def test_mesh_settings_past_the_tet_limit_are_refused_and_scale_reloads_the_surface(
        tmp_path):
    """A resolution whose tets would pass wiggly's limit is refused before the edit (it was
    made, and the model then failed to load); a mesh.scale edit reads the surface again, so
    the page shows it at its new size (its mesh key changes)."""
    from tests.editor_ui import bar_project

    path = bar_project(tmp_path, warp=False)  # the bar as a surface (a tet mesh keeps its tets)
    box = trimesh.creation.box((1.0, 0.1, 0.1))
    box.apply_translation((0.5, 0.05, 0.05))
    box.subdivide().subdivide().export(tmp_path / "bar.obj")
    path.write_text(path.read_text().replace('"bar.vtu"', '"bar.obj"'))
    session = Session(Sandbox([tmp_path]))
    session.open(str(path))
    try:
        before = session.version
        with pytest.raises(EditError, match=r"mesh.resolution = 200 would make about .* "
                                            r"tetrahedra of bar.obj, more than wiggly's limit "
                                            r"of 400000 .*use resolution <= \d+"):
            session.edit({"op": "set", "section": "mesh", "values": {"resolution": 200}})
        assert session.version == before and session.scene.mesh.resolution is None
        key, size = session.describe()["mesh_key"], session.diagonal
        session.edit({"op": "set", "section": "mesh", "values": {"scale": 0.5}})
        assert session.describe()["mesh_key"] != key
        assert session.diagonal == pytest.approx(0.5 * size)
        session.undo()
        assert session.diagonal == pytest.approx(size)
    finally:
        session.close()
