"""Driving a solve: [drive] in scene files end to end (a small tet-mesh bar, so no
tetrahedralizer runs), its checks and messages, and the enriched basis."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import meshio
import numpy as np
import pytest
import tomli_w
from scipy.spatial.transform import Rotation

import wiggly
from wiggly.cli import main
from wiggly.drive import driven_keyframes, enrich, following, read_driver
from wiggly.errors import WigglyInputError
from wiggly.export import SurfaceAnimation, read_animation, write_animation
from wiggly.mesh import TetMesh
from wiggly.primitives import box_mesh
from wiggly.scene import load_scene, run, save_scene

SHAPE, SIZE = (8, 2, 2), (0.8, 0.1, 0.1)
PIVOT = np.array([0.15, 0.05, 0.05])


def bar_motion(X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The driver: the whole bar turning about a vertical axis through PIVOT (20 degrees at
    1 Hz) and bobbing (2 cm at 2 Hz), rigidly; (F, n, 3)."""
    out = []
    for tk in t:
        R = Rotation.from_euler("y", 20.0 * np.sin(2 * np.pi * tk), degrees=True)
        out.append(R.apply(X - PIVOT) + PIVOT + [0.0, 0.02 * np.sin(4 * np.pi * tk), 0.0])
    return np.array(out)


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """A folder with bar.vtu, its driver walk.npz (all 81 vertices, 21 frames at 20 fps) and
    a scene driving the left 40 % of the bar; the right end is free."""
    import meshio

    folder = tmp_path_factory.mktemp("drive")
    V, T = box_mesh(SHAPE, SIZE)
    meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    times = np.arange(21) / 20.0
    faces = TetMesh(V, T).boundary_faces()
    write_animation(folder / "walk.npz", SurfaceAnimation(times, bar_motion(V, times), faces))
    data = {
        "mesh": {"path": "bar.vtu"},
        "material": {"young": 5e4, "poisson": 0.3, "density": 1000.0},
        "simulation": {"modes": 12},
        "time": {"end": 1.0, "fps": 20},
        "groups": {"driven": {"box": {"min": [-1, -1, -1], "max": [0.3, 1, 1]}},
                   "tip": {"box": {"min": [0.7, -1, -1], "max": [1, 1, 1]}}},
        "drive": {"path": "walk.npz", "group": "driven"},
        "output": {"paths": ["out/bar.npz"]},
    }
    return folder, data


def write(folder, data, name="shot.toml"):
    path = folder / name
    path.write_text(tomli_w.dumps(data))
    return path


def test_drive_scene_end_to_end(shot, capsys):
    """The driven group follows the driver to well under a millimetre at every driver frame;
    the free end, keyed nowhere, does not simply follow the driver's rigid motion; the
    output is the solved motion."""
    folder, data = shot
    path = write(folder, data)
    assert main(["animate", str(path), "--overwrite", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "drive      walk.npz:" in out and "moved by the driver over 21 frames" in out
    # the free parts move in their own modes, which the summary reports (not the body's)
    assert re.search(r"modes      \d+ of the free parts with the driven group held", out), out
    scene = load_scene(path)
    anim = run(scene, outputs=[])
    report = following(anim)
    assert report["frames"] == 21 and report["max"] < 1e-4, report
    assert anim.info["drive"] == report
    X = anim.body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.7)
    times = np.arange(21) / 20.0
    lag = np.linalg.norm(anim.positions(times)[:, tip] - bar_motion(X, times)[:, tip], axis=2)
    print(f"following {report['max']:.3g} m, free tip off the rigid driver by {lag.max():.3g} m")
    assert lag.max() > 20 * report["max"]  # free: it moves on its own
    written = read_animation(folder / "out" / "bar.npz")
    np.testing.assert_allclose(written.positions, anim.positions(written.times), atol=1e-6)


def test_per_mode_gltf_targets_of_secondary_motion_are_refused_first(shot, capsys):
    """gltf_targets = "modes" cannot hold a secondary motion (the driver's poses plus the free
    modes): refused before anything is computed, in the scene's terms (it crashed after the
    solve with a mismatch of internal array shapes); from Python too."""
    import copy

    folder, data = shot
    data = copy.deepcopy(data)
    data["simulation"]["warp"] = False
    data["output"] = {"paths": ["out/modes.glb"], "gltf_targets": "modes"}
    path = write(folder, data, "modes.toml")
    assert main(["animate", str(path), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert 'output.gltf_targets = "modes" cannot hold secondary motion' in err, err
    assert "tetrahedraliz" not in err and not (folder / "out" / "modes.glb").exists()
    data["output"] = {"paths": []}
    anim = run(load_scene(write(folder, data, "modes.toml")), outputs=[])
    from wiggly.export import write_animation as write_file

    with pytest.raises(WigglyInputError, match='"modes" cannot hold secondary motion'):
        write_file(folder / "out" / "py.glb", anim, gltf_targets="modes")


def test_driven_keyframes_api_and_range(shot):
    """driven_keyframes keys only frames in the driver range and the shot, shifted by the
    offset; enrich keeps the old modes and adds M-orthonormal, K-diagonal vectors."""
    folder, _ = shot
    body = wiggly.prepare(str(folder / "bar.vtu"), n_modes=10, cache_dir=False)
    driver = read_driver(folder / "walk.npz")
    left = body.rest_positions()[:, 0] <= 0.3
    keys = driven_keyframes(body, driver, left, offset=0.5, driver_range=(0.2, 0.6), start=0.0,
                            end=1.0)
    np.testing.assert_allclose([k.time for k in keys], np.arange(4, 11) / 20 + 0.5, atol=1e-12)
    assert all(k.spec["kind"] == "drive" for k in keys)
    rich = enrich(body, driver, left)
    assert rich.r > body.r
    Phi, M, K = rich.modes.vectors, rich.M, rich.K
    np.testing.assert_allclose(Phi[:, :body.r], body.modes.vectors)
    np.testing.assert_allclose(Phi.T @ (M @ Phi), np.eye(rich.r), atol=1e-8)
    KK = Phi.T @ (K @ Phi)
    np.testing.assert_allclose(KK, np.diag(rich.eigenvalues), atol=1e-6 * np.abs(KK).max())


def test_range_bounds_take_frames_stored_in_single_precision():
    """glTF stores key times as float32: the frame shown at 0.8 s (frame 24 at 30 fps) is
    0.800000012 s.  A range or shot bound at 0.8 s keeps it; a frame one step (1/30 s)
    outside stays out."""
    from wiggly.drive.driver import Driver, keyed_frames

    times = (np.arange(46) / 30.0).astype(np.float32).astype(np.float64)
    assert times[24] > 0.8
    driver = Driver(times, np.zeros((46, 3, 3)), np.array([[0, 1, 2]]),
                    np.array([[0, 1], [0, 2], [1, 2]]), "float32.glb", "glTF skin")
    frames, shot = keyed_frames(driver, offset=0.5, driver_range=(0.2, 0.8))
    assert frames[0] == 6 and frames[-1] == 24
    frames, shot = keyed_frames(driver, start=0.0, end=0.8)
    assert frames[-1] == 24 and shot[-1] == 0.8  # clamped into the shot
    frames, _ = keyed_frames(driver, driver_range=(0.2, 0.8 - 1 / 30))
    assert frames[-1] == 23


def test_drive_round_trips_through_toml(shot, tmp_path):
    folder, data = shot
    data = {**data, "drive": {"path": str(folder / "walk.npz"), "group": ["driven", "tip"],
                              "offset": -0.25, "range": [0.25, 1.0], "stiffness": 1e9,
                              "enrich": False}}
    data["mesh"] = {"path": str(folder / "bar.vtu")}
    scene = load_scene(write(tmp_path, data))
    assert scene.drive.groups == ("driven", "tip") and scene.drive.range == (0.25, 1.0)
    again = load_scene(save_scene(scene, tmp_path / "again.toml"))
    assert again == scene


@pytest.mark.parametrize("change, message", [
    ({"group": "drivn"}, 'drive.group = "drivn" is not a group (did you mean \'driven\'?)'),
    ({"offest": 1.0}, "unknown key 'offest' in [drive]; did you mean 'offset'?"),
    ({"range": [1.0, 0.5]}, "drive.range = [1.0, 0.5] must be [first, last] with first <= last"),
    ({"path": "walk.fbx"}, 'drive.path = "walk.fbx" must be a driver file ending in .glb'),
    ({"path": "run.npz"}, 'drive.path = "run.npz": no such file'),
    ({"animation": "walk"}, 'drive.animation = "walk" applies to glTF drivers only'),
    ({"frame_rate": 0}, "drive.frame_rate = 0 must be a number in (0, "),
])
def test_drive_mistakes_name_file_key_and_value(shot, capsys, change, message):
    folder, data = shot
    data = {**data, "drive": {**data["drive"], **change}}
    path = write(folder, data, "bad.toml")
    assert main(["animate", str(path), "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert "bad.toml: " in err and message in err, err
    assert "Traceback" not in err


def test_drive_needs_a_time_range_and_says_the_drivers(shot, capsys):
    folder, data = shot
    data = {**data, "time": {"fps": 20}}
    path = write(folder, data, "norange.toml")
    assert main(["animate", str(path)]) == 1
    err = capsys.readouterr().err
    assert ("time.end (or time.duration) is missing: a driven shot needs its time range; the "
            "driver walk.npz runs from 0 to 1 s (e.g. add end = 1 to [time])") in err


def test_group_on_tets_is_refused(shot, capsys):
    folder, data = shot
    data = {**data, "groups": {**data["groups"], "inner": {"indices": [0, 1], "on": "tets"}},
            "drive": {"path": "walk.npz", "group": ["driven", "inner"]}}
    assert main(["animate", str(write(folder, data, "tets.toml"))]) == 1
    assert 'drive.group[1] = "inner" selects tet-mesh vertices' in capsys.readouterr().err


def test_topology_mismatch_stops_before_anything_is_computed(shot, capsys):
    """A driver of another surface: one message naming the driver, both vertex counts and the
    mesh; no output is written."""
    folder, data = shot
    V, T = box_mesh((4, 2, 2), SIZE)
    write_animation(folder / "small.npz", SurfaceAnimation(
        np.arange(3) / 20.0, np.repeat(V[None], 3, axis=0), TetMesh(V, T).boundary_faces()))
    data = {**data, "drive": {"path": "small.npz", "group": "driven"},
            "output": {"paths": ["out/never.npz"]}}
    assert main(["animate", str(write(folder, data, "other.toml"))]) == 1
    err = capsys.readouterr().err
    assert "drive.path = \"small.npz\"" in err and "animates 45 vertices" in err
    assert "the surface bar.vtu has 81 vertices" in err
    assert not (folder / "out" / "never.npz").exists()


@pytest.mark.parametrize("time, drive, message", [
    ({"start": 2.0, "end": 3.0}, {},
     "walk.npz (frames from 0 to 1 s, offset 0 s) falls in the shot's [2.0, 3.0] s: an offset "
     "from 1 to 3 s puts some of them in it"),
    ({"start": 1.0, "end": 2.0}, {},
     "has 1 frame in the shot [1, 2] s: secondary motion needs an animated driver"),
    ({"start": 0.0, "end": 1.0}, {"range": [0.5, 0.51]},
     "has 1 frame in the shot [0, 1] s: secondary motion needs an animated driver (two frames "
     "or more); drive.range = [0.5, 0.51] s keeps too little of it"),
    ({"start": 0.0, "end": 1.0, "loop": True}, {"offset": 0.2},
     "a looped shot needs a driver frame at its start (0 s)"),
    ({"start": 1.0, "end": 2.0}, {"physics": "keys"}, None),  # keys: one frame is enough
], ids=["outside", "one frame", "range", "loop start", "keys"])
def test_a_driver_outside_the_shot_stops_before_meshing(tmp_path, capsys, monkeypatch, time,
                                                        drive, message):
    """A surface driven by frames at 0-1 s, in shots that miss them: one message naming the
    driver, its frames and the shot, before the surface is tetrahedralized."""
    import importlib

    import trimesh

    build = importlib.import_module("wiggly.scene.build")
    V, T = box_mesh(SHAPE, SIZE)
    faces = TetMesh(V, T).boundary_faces()
    used, faces = np.unique(faces, return_inverse=True)
    faces = faces.reshape(-1, 3)
    trimesh.Trimesh(V[used], faces, process=False).export(tmp_path / "bar.ply")
    times = np.arange(21) / 20.0
    write_animation(tmp_path / "walk.npz",
                    SurfaceAnimation(times, bar_motion(V[used], times), faces))
    data = {"mesh": {"path": "bar.ply"}, "time": {**time, "fps": 20},
            "groups": {"driven": {"box": {"min": [-1, -1, -1], "max": [0.3, 1, 1]}}},
            "drive": {"path": "walk.npz", "group": "driven", **drive},
            "output": {"paths": ["out/never.npz"]}}

    def meshed(*args, **kwargs):
        raise AssertionError("the surface was meshed before the driver was checked")

    monkeypatch.setattr(build.meshing, "build_model", meshed)
    if message is None:  # the checks pass: meshing is next
        assert main(["animate", str(write(tmp_path, data, "late.toml"))]) != 0
        assert "the surface was meshed" in capsys.readouterr().err
        return
    assert main(["animate", str(write(tmp_path, data, "late.toml"))]) == 1
    err = capsys.readouterr().err
    assert 'late.toml: drive.path = "walk.npz": ' in err and message in err, err
    assert "Traceback" not in err and not (tmp_path / "out" / "never.npz").exists()


def test_a_driver_the_modes_cannot_follow_is_warned_about(shot, recwarn):
    """physics = "keys" without enrichment on a driver that folds the driven part: 12 modes
    miss it by centimetres, and the run says so once, with the remedies; the secondary
    physics holds the group on the same driver, within a millimetre, and says nothing."""
    folder, data = shot
    V, T = box_mesh(SHAPE, SIZE)
    times = np.arange(21) / 20.0
    fold = np.array([V + np.c_[0 * V[:, 0], 0.5 * np.sin(np.pi * t) * (V[:, 0] / 0.3) ** 2,
                               0 * V[:, 0]] for t in times])
    write_animation(folder / "fold.npz",
                    SurfaceAnimation(times, fold, TetMesh(V, T).boundary_faces()))
    keys = {**data, "drive": {"path": "fold.npz", "group": "driven", "physics": "keys",
                              "enrich": False}}
    anim = run(load_scene(write(folder, keys, "fold_keys.toml")), outputs=[])
    size = np.linalg.norm(np.ptp(V, axis=0))
    assert anim.info["drive"]["max"] > 0.01 * size
    said = [str(w.message) for w in recwarn if "stray" in str(w.message)]
    assert len(said) == 1 and "drive.enrich" in said[0] and "fold_keys.toml" in said[0], said
    recwarn.clear()
    held = {**data, "drive": {"path": "fold.npz", "group": "driven"}}
    anim = run(load_scene(write(folder, held, "fold_held.toml")), outputs=[])
    assert anim.info["drive"]["max"] < 1e-2 * size
    assert not [w for w in recwarn if "stray" in str(w.message)]


def test_driven_keys_start_at_the_drivers_poses(tmp_path):
    """A free bar whose left end is keyed (``physics = "keys"``) to a driver that swings the
    whole bar by 140 degrees about that end.  The warp turns a free body about its mass
    centre, so the default start (the keys unwarped by their best-fit rotation, which turns
    about the keyed end) misses the keys by a large share of the bar; the driver's whole
    poses, unwarped, start the solve on them.  Both starts are measured against the driver
    before any iteration, and the solve from the poses converges onto the keys."""
    import importlib

    import meshio

    from wiggly.scene import problem_of
    from wiggly.scene.build import build_with_groups
    from wiggly.scene.drive import linear_start_of
    from wiggly.solve import SolveOptions

    V, T = box_mesh(SHAPE, SIZE)
    meshio.write(tmp_path / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    times = np.arange(21) / 20.0
    end = np.array([0.0, 0.05, 0.05])
    swing = np.array([Rotation.from_euler("z", 140.0 * t, degrees=True).apply(V - end) + end
                      for t in times])
    write_animation(tmp_path / "swing.npz",
                    SurfaceAnimation(times, swing, TetMesh(V, T).boundary_faces()))
    data = {"mesh": {"path": "bar.vtu"},
            "material": {"young": 5e4, "poisson": 0.3, "density": 1000.0},
            "simulation": {"modes": 12, "gravity": [0.0, 0.0, 0.0]},
            "time": {"end": 1.0, "fps": 20},
            "groups": {"driven": {"box": {"min": [-1, -1, -1], "max": [0.15, 1, 1]}}},
            "drive": {"path": "swing.npz", "group": "driven", "physics": "keys"}}
    scene = load_scene(write(tmp_path, data, "swing.toml"))
    body, keys, _ = build_with_groups(scene)
    problem = problem_of(scene, body)
    size = float(np.linalg.norm(np.ptp(V, axis=0)))
    unsolved = SolveOptions(max_iterations=0, warn=False)
    default = following(problem.solve(keys, warped=True, options=unsolved))
    poses = linear_start_of(scene, body, keys)
    assert len(poses) == 21 and all(len(k.vertices) == body.tets.n_vertices for k in poses)
    started = following(problem.solve(keys, warped=True, options=unsolved, linear_start=poses))
    assert default["max"] > 0.1 * size, default
    assert started["max"] < 0.01 * size, started
    anim = run(scene, outputs=[])
    assert anim.info["converged"] and following(anim)["max"] < 1e-3 * size
    # a linear shot, or secondary physics, keeps the solve's own start
    linear = importlib.import_module("wiggly.scene.spec")
    assert linear_start_of(linear.Scene(**{**vars(scene), "simulation": type(
        scene.simulation)(**{**vars(scene.simulation), "warp": False})}), body, keys) is None


def test_the_output_frame_rate_does_not_retime_an_obj_sequence_driver(shot):
    """An OBJ sequence without frame_rate is timed by [time] fps; --fps (the outputs' rate)
    used to retime it too, so a 24 fps Blender sequence played 25 % faster under --fps 30.
    The override now keeps the driver's timing; drivers that carry their times do not need
    it (frame_rate applies to OBJ sequences only)."""
    from wiggly.scene import with_overrides

    folder, data = shot
    write_animation(folder / "seq" / "walk.obj", read_animation(folder / "walk.npz"))
    obj = load_scene(write(folder, {**data, "drive": {"path": "seq/walk.obj", "group": "driven"},
                                    "time": {"end": 1.0, "fps": 24}}, "objseq.toml"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # wiggly's OBJ frames carry their times: nothing to say
        faster = with_overrides(obj, fps=30)
    assert faster.time.fps == 30 and faster.drive.frame_rate == 24
    npz = with_overrides(load_scene(write(folder, data, "npz.toml")), fps=30)
    assert npz.drive.frame_rate is None
    # another tool's frames (numbers only): said, with the remedy
    for frame in (folder / "seq").glob("walk_*.obj"):
        frame.write_bytes(re.sub(rb"(?m)^# time.*\n", b"", frame.read_bytes()))
    with pytest.warns(UserWarning, match=r"is an OBJ sequence timed by the scene's 24 fps .* "
                                         r"not by --fps 30.*set drive\.frame_rate = 30"):
        with_overrides(load_scene(folder / "objseq.toml"), fps=30)


def test_a_driven_body_too_soft_for_its_size_is_noted(shot):
    """A secondary-motion shot holds the body by its driven group as fixed vertices hold it:
    a material that gravity alone bends by more than a fifth of the size gets the same note,
    naming the driven group; the sag is the free parts' static equilibrium (checked against
    the full FEM static solve with the held tet vertices fixed)."""
    import scipy.sparse.linalg as spla

    from wiggly.drive.secondary import held_vertices
    from wiggly.scene.body_notes import soft_note, static_sag
    from wiggly.scene.drive import driven_vertices

    folder, data = shot
    soft = {**data, "material": {"young": 2e3, "poisson": 0.3, "density": 1000.0}}
    scene = load_scene(write(folder, soft, "soft_drive.toml"))
    anim = run(scene, outputs=[])  # the free parts' modes the solve used
    body = anim.body
    note = soft_note(scene, body, anim.held_modes)
    assert note is not None and "where its driven group holds it" in note, note
    held = held_vertices(body, driven_vertices(scene, anim.info["scene"]["groups"]))
    sag = static_sag(body, anim.held_modes)
    free = np.setdiff1d(np.arange(3 * body.tets.n_vertices),
                        (3 * held[:, None] + np.arange(3)).ravel())
    u = spla.spsolve(body.K[free][:, free].tocsc(), -body.gravity_vector[free])
    assert sag == pytest.approx(float(np.linalg.norm(u.reshape(-1, 3), axis=1).max()),
                                rel=0.15)
    stiff = load_scene(write(folder, {**data, "material": {"young": 1e8, "poisson": 0.3,
                                                           "density": 1000.0}},
                             "stiff_drive.toml"))
    anim = run(stiff, outputs=[])
    assert soft_note(stiff, anim.body, anim.held_modes) is None


def test_a_driver_at_another_scale_is_refused_before_the_solve(shot, capsys):
    """A driver of the same surface in centimetres (100 times the mesh) used to run and write
    garbage, said only after the solve as a stray of thousands of percent; it is refused
    before meshing, naming both sizes."""
    folder, data = shot
    walk = read_animation(folder / "walk.npz")
    write_animation(folder / "walk_cm.npz",
                    SurfaceAnimation(walk.times, 100 * walk.positions, walk.faces),
                    overwrite=True)
    scene = write(folder, {**data, "drive": {"path": "walk_cm.npz", "group": "driven"}},
                  "cm.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "cm.npz")]) == 1
    err = capsys.readouterr().err
    assert 'drive.path = "walk_cm.npz": its first pose is 100 times the size of bar.vtu' in err
    assert "the driver is likely in other units: set drive.scale = 0.01" in err  # not the mesh
    assert not (folder / "cm.npz").exists()
    # drive.scale reads it in metres: the same motion as the driver in metres
    base = write(folder, {**data, "drive": {"path": "walk.npz", "group": "driven"}},
                 "m.toml")
    assert main(["animate", str(base), "-q", "-o", str(folder / "m.npz")]) == 0
    scene = write(folder, {**data, "drive": {"path": "walk_cm.npz", "group": "driven",
                                             "scale": 0.01}}, "cm_scaled.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "cm_scaled.npz")]) == 0
    capsys.readouterr()
    # (npz stores float32: the files agree to their rounding, 1.2e-7 m at 1 m)
    np.testing.assert_allclose(read_animation(folder / "cm_scaled.npz").positions,
                               read_animation(folder / "m.npz").positions, atol=1e-6)
    # a scale given to a driver in metres: the remedy is to leave it out
    scene = write(folder, {**data, "drive": {"path": "walk.npz", "group": "driven",
                                             "scale": 0.01}}, "m_scaled.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "x.npz")]) == 1
    err = capsys.readouterr().err
    assert "drive.scale = 0.01 makes the driver 100 times smaller than its files: leave it " \
        "out" in err, err
    # the mesh in centimetres instead (the driver in metres): mesh.scale is the remedy
    mesh = meshio.read(folder / "bar.vtu")
    meshio.write(folder / "bar_cm.vtu", meshio.Mesh(100 * mesh.points, mesh.cells))
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_cm.vtu"},
                           "drive": {"path": "walk.npz", "group": "driven"}}, "cm_mesh.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "cm.npz")]) == 1
    err = capsys.readouterr().err
    assert "0.01 times the size of bar_cm.vtu" in err and "set mesh.scale = 0.01" in err, err
    # mesh.scale given, the driver's files (no units) read in metres: either the driver is in
    # the mesh file's units (drive.scale as well: a review's plant in centimetres was told
    # only to leave mesh.scale out), or the mesh file is in metres (leave it out)
    scene = write(folder, {**data, "mesh": {**data["mesh"], "scale": 0.01},
                           "drive": {"path": "walk.npz", "group": "driven"}}, "scaled.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "s.npz")]) == 1
    err = capsys.readouterr().err
    assert "mesh.scale = 0.01 makes the mesh 100 times smaller than its file, and the " \
        "driver is read in metres: set drive.scale = 0.01 as well if it is in the " \
        "mesh file's units, or leave mesh.scale out if the mesh file is in metres" in err, err
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_cm.vtu",
                                            "scale": 0.01},
                           "drive": {"path": "walk_cm.npz", "group": "driven",
                                     "scale": 0.01}}, "both_cm.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "both.npz")]) == 0


def test_a_mesh_in_other_axes_than_its_driver_is_warned_about(shot, capsys):
    """A Z-up mesh file driven by a Y-up driver: the driver's first pose is the mesh on its
    side (gravity then pulled the free parts sideways, in silence); the warning names
    mesh.up_axis, which then reads the mesh upright, and nothing more is said."""
    folder, data = shot
    mesh = meshio.read(folder / "bar.vtu")
    X = mesh.points
    meshio.write(folder / "bar_z.vtu", meshio.Mesh(np.stack([X[:, 0], -X[:, 2], X[:, 1]], 1),
                                                  mesh.cells))
    drive = {"path": "walk.npz", "group": "driven"}
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_z.vtu"},
                           "drive": drive}, "zup.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z.npz")]) == 0
    err = capsys.readouterr().err
    assert 'its first pose is bar_z.vtu turned by 90 degrees from its up axis' in err, err
    assert 'the mesh file looks Z-up: set mesh.up_axis = "z"' in err
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_z.vtu",
                                            "up_axis": "z"}, "drive": drive}, "zup2.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z2.npz")]) == 0
    assert "up axis" not in capsys.readouterr().err
    # both Z-up: up_axis turns the mesh only, and the driver read as it is stays on its side
    walk = read_animation(folder / "walk.npz")
    P = walk.positions
    write_animation(folder / "walk_z.npz", SurfaceAnimation(
        walk.times, np.stack([P[..., 0], -P[..., 2], P[..., 1]], -1), walk.faces))
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_z.vtu",
                                            "up_axis": "z"},
                           "drive": {"path": "walk_z.npz", "group": "driven"}}, "zup3.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z3.npz")]) == 0
    err = capsys.readouterr().err
    assert 'mesh.up_axis turns the mesh only, and the driver looks Z-up: set drive.up_axis = ' \
        '"z" as well' in err, err
    # drive.up_axis turns the driver upright: the motion of the Y-up files, and no warning
    scene = write(folder, {**data, "mesh": {**data["mesh"], "path": "bar_z.vtu",
                                            "up_axis": "z"},
                           "drive": {"path": "walk_z.npz", "group": "driven",
                                     "up_axis": "z"}}, "zup4.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z4.npz")]) == 0
    assert "up axis" not in capsys.readouterr().err
    np.testing.assert_allclose(read_animation(folder / "z4.npz").positions,
                               read_animation(folder / "z2.npz").positions, atol=1e-9)
    # a Y-up mesh with a Z-up driver: the driver's drive.up_axis is named, not the mesh's
    scene = write(folder, {**data, "drive": {"path": "walk_z.npz", "group": "driven"}},
                  "zup5.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z5.npz")]) == 0
    err = capsys.readouterr().err
    assert 'the driver looks Z-up: set drive.up_axis = "z"' in err, err
    # drive.up_axis = "z" given to a Y-up driver: that setting is named, not the mesh's (a
    # review was told to set mesh.up_axis, which would have turned the mesh too)
    scene = write(folder, {**data, "drive": {"path": "walk.npz", "group": "driven",
                                             "up_axis": "z"}}, "zup6.toml")
    assert main(["animate", str(scene), "-q", "-o", str(folder / "z6.npz")]) == 0
    err = capsys.readouterr().err
    assert 'drive.up_axis = "z" turns the driver: leave it out if the driver file is y up' \
        in err, err
    assert "mesh.up_axis" not in err, err


def test_driver_units_and_axes_apply_to_files_without_their_own(shot, tmp_path):
    """drive.up_axis is for OBJ sequences and npz: a glTF or USD driver carries its own axes,
    and the key is refused there, saying so. drive.scale multiplies a glTF's or USD's metres
    too (Blender writes its units as metres: a review's centimetre scene could not be
    brought to size)."""
    folder, data = shot
    scene = write(folder, {**data, "drive": {"path": "walk.glb", "group": "driven",
                                             "scale": 0.01, "up_axis": "z"}}, "glb.toml")
    with pytest.raises(WigglyInputError) as err:
        load_scene(scene)
    text = str(err.value)
    assert 'drive.up_axis = "z" applies to OBJ-sequence and npz drivers only; drive.path = ' \
        '"walk.glb" is not one (a glTF driver is in metres, y up, by its specification' in text
    assert "drive.scale" not in text
    with pytest.raises(WigglyInputError, match=r"up applies to OBJ sequences and \.npz"):
        read_driver(tmp_path / "walk.glb", up="z")
    walk = Path(__file__).resolve().parents[1] / "examples" / "critter_walk.glb"
    np.testing.assert_allclose(read_driver(walk, scale=0.01).positions,
                               0.01 * read_driver(walk).positions, rtol=1e-12)
    with pytest.raises(WigglyInputError, match="up = 'x' is not an up axis"):
        read_driver(folder / "walk.npz", up="x")
    with pytest.raises(WigglyInputError, match="scale should be a number > 0"):
        read_driver(folder / "walk.npz", scale=-1)
    # the conversion itself: (x, y, z) -> (x, z, -y) after the scale, as for meshes
    plain = read_driver(folder / "walk.npz")
    turned = read_driver(folder / "walk.npz", scale=0.5, up="z")
    P = 0.5 * plain.positions
    np.testing.assert_array_equal(turned.positions,
                                  np.stack([P[..., 0], P[..., 2], -P[..., 1]], -1))
    np.testing.assert_array_equal(turned.times, plain.times)


def test_a_clip_the_driver_lacks_is_blamed_on_drive_animation(tmp_path):
    """A glTF clip name the file does not have is drive.animation's mistake: the message
    names that key (it named drive.path) and lists the clips there are."""
    import shutil
    from pathlib import Path

    from wiggly.errors import WigglyInputError
    from wiggly.scene.drive import scene_driver

    walk = Path(__file__).resolve().parents[1] / "examples" / "critter_walk.glb"
    shutil.copy(walk, tmp_path / "walk.glb")
    data = {"mesh": {"path": "walk.glb"}, "time": {"end": 1.0},
            "groups": {"body": {"box": {"min": [-9, -9, -9], "max": [9, 9, 9]}}},
            "drive": {"path": "walk.glb", "group": "body", "animation": "walking"}}
    with pytest.raises(WigglyInputError) as err:
        scene_driver(load_scene(write(tmp_path, data, "clip.toml")))
    said = str(err.value)
    assert 'drive.animation = "walking": ' in said and "its animations are: #0 'walk'" in said


def test_a_driver_with_no_animation_says_so():
    """A driver file with a single pose (a glTF without animations) is told as not animated,
    not as "1 frame in the shot"."""
    from wiggly.drive.driver import Driver
    from wiggly.drive.secondary import secondary_frames
    from wiggly.errors import WigglyInputError

    V, T = box_mesh(SHAPE, SIZE)
    still = Driver(np.array([0.0]), V[None], TetMesh(V, T).boundary_faces(), np.zeros((0, 2)),
                   "still.glb", "test")
    with pytest.raises(WigglyInputError, match=r"still\.glb is not animated"):
        secondary_frames(still, start=0.0, end=1.0)
