"""The ``wiggly`` command line, in-process through ``main([...])`` (and once as a subprocess)."""

from __future__ import annotations

import copy
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tomli_w
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import wiggly
from wiggly.cli import COMMANDS, main
from wiggly.export import SurfaceAnimation, read_animation, write_animation
from wiggly.scene import scene_schema

# A small valid scene: the bundled bar, fixed at x = 0, its tip pulled up and released.
SCENE = {
    "mesh": {"path": "builtin:bar", "resolution": 6},
    "material": {"young": 1e5, "poisson": 0.3, "density": 1000.0},
    "damping": {"alpha": 0.5, "beta": 0.002},
    "simulation": {"modes": 8, "fixed": ["left"]},
    "time": {"end": 1.0, "fps": 10},
    "groups": {
        "left": {"box": {"min": [-0.01, -1.0, -1.0], "max": [0.01, 1.0, 1.0]}},
        "tip": {"sphere": {"center": [1.0, 0.0, 0.0], "radius": 0.06}},
        "some": {"indices": [3, 5, 8]},
    },
    "keyframes": [
        {"time": 0.0, "group": "tip", "position": "rest", "velocity": [0.0, 0.0, 0.0]},
        {"time": 0.5, "group": "tip", "position": {"offset": [0.0, 0.1, 0.0]},
         "name": "pulled"},
    ],
    "output": {"paths": ["out/bar.npz"]},
}


def write_scene(directory: Path, data: dict, name: str = "shot.toml") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    path.write_text(tomli_w.dumps(data))
    return path


def run_main(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ----------------------------------------------------------------------------------------------
# usage, help, version


def test_version(capsys):
    code, out, _ = run_main(capsys, "--version")
    assert code == 0 and out.strip() == f"wiggly {wiggly.__version__}"


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help(capsys, command):
    code, out, _ = run_main(capsys, *([command] if command else []), "--help")
    assert code == 0
    assert "usage: wiggly" in out and "examples:" in out


@pytest.mark.parametrize("argv", [
    [], ["animate"], ["frobnicate"], ["animate", "x.toml", "--bogus"],
    ["animate", "x.toml", "--fps", "-1"], ["modes", "m.obj", "-n", "0"], ["render", "x.npz"]])
def test_usage_errors_exit_2(capsys, argv):
    code, _, err = run_main(capsys, *argv)
    assert code == 2
    assert "usage: wiggly" in err and "Traceback" not in err


@pytest.mark.parametrize(("argv", "said"), [
    (["animate", "x.toml", "--warp"], "wiggly animate: error: unrecognized arguments: --warp "
     "(the solve is warped by default; --linear solves without the warp)"),
    (["animate", "x.toml", "--overwite"], "(did you mean --overwrite?)"),
    (["modes", "m.obj", "--overwite"], "wiggly modes: error: unrecognized arguments"),
])
def test_an_unknown_option_names_the_commands_own(capsys, argv, said):
    """An option the command does not have: the command's usage (not wiggly's, which lists
    no option of it) and the closest option it has, or what the guess means."""
    code, _, err = run_main(capsys, *argv)
    assert code == 2 and said in err, err
    assert f"usage: wiggly {argv[0]} " in err and f"`wiggly {argv[0]} --help`" in err, err


def test_schema_command(capsys):
    code, out, _ = run_main(capsys, "schema")
    assert code == 0 and json.loads(out) == scene_schema()


# ----------------------------------------------------------------------------------------------
# animate


def test_an_obj_sequence_is_named_by_its_frame_files(capsys, tmp_path):
    """``-o out/bar.obj`` writes out/bar_0000.obj, ...: the summary names those, not bar.obj
    (which may be another file: the input mesh)."""
    scene = write_scene(tmp_path, SCENE)
    code, out, err = run_main(capsys, "animate", scene, "--linear", "-o", tmp_path / "o/bar.obj")
    assert code == 0, err
    first = (tmp_path / "o" / "bar_0000.obj").resolve()
    assert f"wrote\n  {first} ... bar_0010.obj (11 frames)" in out, out
    assert not (tmp_path / "o" / "bar.obj").exists()


def test_animate(capsys, tmp_path):
    scene = write_scene(tmp_path, SCENE)
    code, out, err = run_main(capsys, "animate", scene)
    assert code == 0, err
    target = tmp_path / "out" / "bar.npz"
    anim = read_animation(target)
    assert anim.n_frames == 11 and np.isclose(anim.times[-1], 1.0)
    assert f"wrote\n  {target.resolve()}" in out
    assert "Newton iterations" in out and "pulled" in out
    # stage lines on stderr: the surface is checked before it is tetrahedralized (unless the
    # tet mesh comes from the cache) and the tet mesh is reported
    checking = err.index("[wiggly] checking bar.obj (2064 triangles)")
    assert re.search(r"\[wiggly\] \d+ tets, \d+ vertices", err[checking:])
    assert "tetrahedralizing" not in err[:checking]
    rows = [line for line in out.splitlines() if line.strip().startswith(("0 ", "1 "))]
    assert len(rows) == 2
    for row in rows:  # position residuals (rms, max) in mm
        assert [float(x) < 20 for x in re.findall(r"(\S+) mm(?!/)", row)] == [True, True]

    # existing output: refused before any computation, file untouched
    stamp = target.stat().st_mtime_ns
    code, out, err = run_main(capsys, "animate", scene, "--quiet")
    assert code == 1 and "exists; pass --overwrite" in err and "Traceback" not in err
    assert "tetrahedralizing" not in err and target.stat().st_mtime_ns == stamp
    # --overwrite, -o, --linear, --fps, --quiet
    other = tmp_path / "elsewhere" / "b.npz"
    code, out, err = run_main(capsys, "animate", scene, "-o", other, "--linear", "--fps", "20",
                              "--quiet")
    assert code == 0 and err == ""
    assert read_animation(other).n_frames == 21 and "linear" in out
    code, _, err = run_main(capsys, "animate", scene, "--overwrite", "-q")
    assert code == 0 and target.stat().st_mtime_ns != stamp


def test_animate_without_outputs(capsys, tmp_path):
    data = copy.deepcopy(SCENE)
    del data["output"]
    code, out, _ = run_main(capsys, "animate", write_scene(tmp_path, data), "-q")
    assert code == 0 and "wrote      nothing" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shot.toml"]


def test_a_first_run_tells_the_kernels_compile_apart_from_the_solve(capsys, tmp_path,
                                                                    monkeypatch):
    """The warp's kernels compile once after an install (about a minute): the summary's time line
    gives it its own figure instead of folding it into the solve's (stood in for here by a
    0.6 s wait); a slow load from the kernels' cache is called loading, not compiling; an
    already compiled process says nothing of it."""
    import importlib
    import time as _time

    scene_run = importlib.import_module("wiggly.scene.run")
    for compiles, said in ((True, "compiling the warp's kernels \\(once\\)"),
                           (False, "loading the warp's kernels")):
        monkeypatch.setattr(scene_run, "ensure_compiled",
                            lambda c=compiles: _time.sleep(0.6) or c)
        code, out, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE), "-q",
                                  "--overwrite")
        assert code == 0, err
        took = re.search(said + r" (\d+\.\d) s, solve", out)
        assert took and float(took.group(1)) >= 0.6, out  # its own figure (loaded: more)
    monkeypatch.setattr(scene_run, "ensure_compiled", lambda: False)
    code, out, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE), "-q",
                              "--overwrite")
    assert code == 0 and "compiling" not in out and "loading" not in out, out


def test_user_errors_exit_1(capsys, tmp_path):
    code, _, err = run_main(capsys, "animate", tmp_path / "none.toml")
    assert code == 1 and err == f"wiggly: error: {tmp_path / 'none.toml'}: no such scene file\n"
    bad = tmp_path / "bad.toml"
    bad.write_text("[mesh\n")
    code, _, err = run_main(capsys, "animate", bad)
    assert code == 1 and "not valid TOML" in err and "Traceback" not in err
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE), "-o", "x.mov")
    assert code == 1 and "unsupported output extension '.mov'" in err
    code, _, err = run_main(capsys, "modes", tmp_path / "nothing.obj")
    assert code == 1 and "does not exist" in err and "Traceback" not in err
    (tmp_path / "out").mkdir()  # an output folder for a file: named as one
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE), "-o",
                            tmp_path / "out")
    assert code == 1 and "out: it is a directory; give a file name in it, e.g. " in err, err
    (tmp_path / "taken.npz").write_bytes(b"")  # the path once, not "taken.npz: taken.npz"
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE), "-o",
                            tmp_path / "taken.npz")
    assert code == 1 and err.count("taken.npz") == 1, err


def test_a_glb_past_4_gib_is_refused_before_the_solve(capsys, tmp_path, monkeypatch):
    """GLB's sizes are 32-bit: a .glb of a morph target per frame past 4 GiB (an hour-long
    shot of a scan) is refused before anything is solved, saying what fits (it failed
    after the solve with an internal error); here the limit is lowered to 1 kB."""
    from wiggly.export import gltf

    monkeypatch.setattr(gltf, "GLB_LIMIT", 1000)
    scene = write_scene(tmp_path, {**SCENE, "output": {"paths": ["out/bar.glb"]}})
    code, _, err = run_main(capsys, "animate", scene)
    assert code == 1 and "more than the 4 GiB a GLB file can hold" in err, err
    assert "write .usdc" in err and "solve" not in err and "Traceback" not in err
    assert not (tmp_path / "out" / "bar.glb").exists()


def test_internal_error_prints_traceback(capsys, tmp_path, monkeypatch):
    import wiggly.scene

    def broken(*args, **kwargs):
        raise ZeroDivisionError("boom")

    monkeypatch.setattr(wiggly.scene, "run", broken)
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE))
    assert code == 1
    assert "Traceback" in err and "ZeroDivisionError: boom" in err and "please report" in err


def test_subprocess(tmp_path):
    """``python -m wiggly`` as a real process: exit codes and a clean error message."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    ok = subprocess.run([sys.executable, "-m", "wiggly", "--version"], capture_output=True,
                        text=True, env=env, timeout=120)
    assert ok.returncode == 0 and ok.stdout.strip() == f"wiggly {wiggly.__version__}"
    data = copy.deepcopy(SCENE)
    data["material"]["yuong"] = 1.0
    write_scene(tmp_path, data)
    bad = subprocess.run([sys.executable, "-m", "wiggly", "animate", "shot.toml"],
                         capture_output=True, text=True, env=env, timeout=120, cwd=tmp_path)
    assert bad.returncode == 1
    assert bad.stderr == ("wiggly: error: shot.toml: unknown key 'yuong' in [material]; did you "
                          "mean 'young'?\n")
    usage = subprocess.run([sys.executable, "-m", "wiggly", "animate"], capture_output=True,
                           text=True, env=env, timeout=120)
    assert usage.returncode == 2


# ----------------------------------------------------------------------------------------------
# modes and render


def test_modes_table(capsys):
    code, out, _ = run_main(capsys, "modes", "builtin:bar", "-n", "9", "--resolution", "6",
                            "--young", "2e6", "-q")
    assert code == 0
    assert "free, 6 rigid modes" in out and "E = 2e+06 Pa" in out
    rows = [line.split() for line in out.splitlines() if line.split()[:1] and
            line.split()[0].isdigit()]
    assert [int(r[0]) for r in rows] == list(range(1, 10))
    assert all(r[2] == "rigid" for r in rows[:6])
    for r in rows[6:]:
        lam, hz, period = map(float, r[1:4])
        assert math.isclose(hz, math.sqrt(lam) / (2 * math.pi), rel_tol=1e-3)
        assert math.isclose(period, 1 / hz, rel_tol=2e-3)
    freqs = [float(r[2]) for r in rows[6:]]
    assert freqs == sorted(freqs) and freqs[0] > 0


def test_modes_of_a_scene_with_preview(capsys, tmp_path):
    scene = write_scene(tmp_path, SCENE)
    out_png = tmp_path / "modes.png"
    code, out, _ = run_main(capsys, "modes", scene, "-n", "5", "-o", out_png, "-q")
    assert code == 0 and "0 rigid modes" in out and "fixed at" in out
    from PIL import Image

    with Image.open(out_png) as im:
        assert im.size[0] > 400 and im.size[1] > 100
    video = tmp_path / "modes.mp4"
    code, _, err = run_main(capsys, "modes", scene, "-n", "5", "-o", video, "--size",
                            "320x180", "-q")
    assert code == 0, err
    import imageio.v3 as iio

    assert iio.improps(video).shape[1:3] == (180, 320)


def small_animation() -> SurfaceAnimation:
    """An icosphere bouncing once: 12 frames."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    times = np.arange(12) / 12.0
    lift = 0.3 * np.sin(np.pi * times)[:, None, None] * np.array([0.0, 1.0, 0.0])
    positions = sphere.vertices[None] + lift + np.array([0.0, 0.2, 0.0])
    return SurfaceAnimation(times, positions, sphere.faces, name="ball")


def test_render_animation_file(capsys, tmp_path):
    npz = write_animation(tmp_path / "ball.npz", small_animation())
    sheet, gif = tmp_path / "previews" / "ball.png", tmp_path / "ball.gif"
    code, out, err = run_main(capsys, "render", npz, "-o", sheet, "-o", gif, "--camera", "side",
                              "-q")
    assert code == 0, err
    assert "ball.npz: 12 frames" in out and str(sheet.resolve()) in out
    from PIL import Image

    with Image.open(sheet) as im:
        assert im.format == "PNG" and im.size[0] > im.size[1]
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.n_frames >= 10
    code, _, err = run_main(capsys, "render", npz, "-o", sheet)
    assert code == 1 and "exists" in err
    code, _, err = run_main(capsys, "render", npz, "-o", tmp_path / "x.glb")
    assert code == 1 and "render writes .mp4, .gif or .png" in err


def test_render_reads_other_tools_files_as_drivers_and_takes_a_size(capsys, tmp_path,
                                                                   monkeypatch):
    """A skinned glTF of another tool renders its whole walk (it rendered one still frame),
    wiggly's own files are read as written; --size sets the picture's size; a failed second
    output leaves no first one."""
    import imageio.v3 as iio

    import wiggly.scene
    from wiggly.export.formats import written_by_wiggly

    walk = Path(__file__).resolve().parents[1] / "examples" / "critter_walk.glb"
    video = tmp_path / "walk.mp4"
    code, out, err = run_main(capsys, "render", walk, "-o", video, "--size", "320x180")
    assert code == 0, err
    assert "critter_walk.glb: 61 frames" in out and "read as a driver (glTF skin" in err, err
    assert iio.improps(video).shape[1:3] == (180, 320)
    ours = write_animation(tmp_path / "ball.glb", small_animation())
    assert written_by_wiggly(ours) and not written_by_wiggly(walk)
    code, _, err = run_main(capsys, "render", walk, "-o", tmp_path / "a.png", "--size", "3x3")
    assert code == 2 and "--size" in err
    real, calls = wiggly.scene.render_preview, []

    def failing(path, *args, **kwargs):  # the second preview fails
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return real(path, *args, **kwargs)

    monkeypatch.setattr(wiggly.scene, "render_preview", failing)
    code, _, err = run_main(capsys, "render", ours, "-o", tmp_path / "one.png", "-o",
                            tmp_path / "two.png")
    assert code == 1 and "disk full" in err, err
    assert len(calls) == 2  # the first was written, then taken back
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.glb", "walk.mp4"]


def test_render_reads_another_tools_obj_sequence(capsys, tmp_path):
    """Blender's OBJ sequence (mesh0001.obj, ...: quads, no time comments) renders all its
    frames at --fps (it was refused: "faces should be triangles"); wiggly's own sequence
    is read as written."""
    box = trimesh.creation.box()
    V, quads = np.asarray(box.vertices), [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1],
                                          [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    for k in range(1, 7):
        lines = ["# Blender 5.0.1", "mtllib mesh.mtl", "o Cube"]
        lines += [f"v {x:.6f} {y + 0.1 * k:.6f} {z:.6f}" for x, y, z in V]
        lines += ["s 0", *("f " + " ".join(f"{i + 1}//1" for i in q) for q in quads)]
        (tmp_path / f"mesh{k:04d}.obj").write_text("\n".join(lines) + "\n")
    code, out, err = run_main(capsys, "render", tmp_path / "mesh0001.obj", "-o",
                              tmp_path / "seq.gif", "--fps", "12", "--size", "160x90")
    assert code == 0, err
    assert "read as a driver" in err and "6 frames" in out, (out, err)
    ours = write_animation(tmp_path / "own" / "ball.obj", small_animation())
    code, out, err = run_main(capsys, "render", ours, "-o", tmp_path / "own.png")
    assert code == 0 and "read as a driver" not in err, err


def test_render_scene(capsys, tmp_path):
    scene = write_scene(tmp_path, SCENE)
    sheet = tmp_path / "sheet.png"
    code, out, err = run_main(capsys, "render", scene, "-o", sheet, "-q")
    assert code == 0, err
    assert "pulled" in out
    assert sheet.is_file() and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_demo(capsys, tmp_path):
    """The demo writes its three files and finishes well under a minute."""
    start = time.perf_counter()
    code, out, err = run_main(capsys, "demo", "-o", tmp_path / "demo", "-q")
    seconds = time.perf_counter() - start
    assert code == 0, err
    names = ["critter.glb", "critter.mp4", "critter-sheet.png"]
    for name in names:
        path = (tmp_path / "demo" / name).resolve()
        assert path.is_file() and path.stat().st_size > 10_000
        assert f"  {path}\n" in out
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == sorted(names)
    assert seconds < 60
    assert "Next: `source " in out and "bin/activate` puts the wiggly command" in out
    code, _, err = run_main(capsys, "demo", "-o", tmp_path / "demo", "-q")
    assert code == 1 and "holds a demo's results already (critter.glb, critter.mp4, " in err
    assert "pass --overwrite to make them again, or -o another folder" in err
    assert "demo.toml" not in err  # the package's own scene file is not the user's business


# ----------------------------------------------------------------------------------------------
# malformed scenes: always exit code 1, a message, no traceback, nothing written

NUMBER_FIELDS = ["material.young", "material.density", "material.poisson", "damping.alpha",
                 "damping.beta", "simulation.modes", "time.end", "time.fps", "mesh.resolution",
                 "groups.tip.sphere.radius", "keyframes.1.time"]
POSITIVE_FIELDS = ["material.young", "material.density", "simulation.modes", "time.fps",
                   "mesh.resolution", "groups.tip.sphere.radius"]
STRING_FIELDS = ["mesh.path", "keyframes.0.group", "keyframes.1.name"]
VECTOR_FIELDS = ["keyframes.1.position.offset", "keyframes.0.velocity",
                 "groups.tip.sphere.center", "groups.left.box.min"]
TABLES = ["", "mesh", "material", "damping", "simulation", "time", "groups.tip",
          "groups.tip.sphere", "keyframes.0", "keyframes.1.position", "output"]
REQUIRED = ["mesh", "mesh.path", "keyframes.0.time", "keyframes.1.group",
            "groups.left.box.max", "groups.tip.sphere.radius"]
KNOWN_KEYS = {"mesh", "path", "material", "young", "poisson", "density", "damping", "alpha",
              "beta", "simulation", "time", "groups", "tip", "sphere", "keyframes", "output",
              "format", "resolution", "edge_length", "repair", "gravity", "modes", "warp",
              "lumped_mass", "fixed", "preroll", "start", "end", "duration", "fps", "box",
              "nearest", "indices", "from_mesh", "on", "color", "center", "radius", "group",
              "position", "velocity", "stiffness", "c_A", "c_B", "name", "offset", "absolute",
              "rotation", "translation", "paths", "overwrite", "size", "camera"}


def _node(data, path: str):
    parts = [int(p) if p.isdigit() else p for p in path.split(".") if p]
    for p in parts[:-1]:
        data = data[p]
    return data, parts[-1] if parts else None


@st.composite
def malformed(draw) -> dict:
    """SCENE with one change that makes it invalid (by construction)."""
    data = copy.deepcopy(SCENE)
    kind = draw(st.sampled_from(["type", "missing", "nan", "negative", "unknown", "time",
                                 "index", "vector"]))
    if kind == "type":
        path = draw(st.sampled_from(NUMBER_FIELDS + STRING_FIELDS))
        node, key = _node(data, path)
        wrong = st.sampled_from(["soft", True, [1.0], {"a": 1}]) if path in NUMBER_FIELDS \
            else st.sampled_from([3, 2.5, False, ["x"], {"a": "b"}])
        node[key] = draw(wrong)
    elif kind == "missing":
        node, key = _node(data, draw(st.sampled_from(REQUIRED)))
        del node[key]
    elif kind == "nan":
        path = draw(st.sampled_from(NUMBER_FIELDS + VECTOR_FIELDS))
        node, key = _node(data, path)
        bad = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
        if path in VECTOR_FIELDS:
            node[key] = [0.0, bad, 0.0]
        else:
            node[key] = bad
    elif kind == "negative":
        node, key = _node(data, draw(st.sampled_from(POSITIVE_FIELDS)))
        node[key] = -draw(st.integers(0, 10**6)) * 1.0
        if key in ("modes", "resolution"):
            node[key] = int(node[key])
    elif kind == "unknown":
        table = draw(st.sampled_from(TABLES))
        name = draw(st.from_regex(r"[a-z_]{1,10}", fullmatch=True).filter(
            lambda s: s not in KNOWN_KEYS))
        node = _node(data, table + ".x")[0] if table else data
        node[name] = draw(st.sampled_from([1, "x", [1.0, 2.0]]))
    elif kind == "time":
        t = draw(st.floats(1.0001, 1e6) | st.floats(-1e6, -0.0001))
        data["keyframes"][draw(st.integers(0, 1))]["time"] = t
    elif kind == "index":
        data["groups"]["some"]["indices"] = [3, draw(st.integers(10**6, 10**9))]
    else:  # vectors of the wrong length
        node, key = _node(data, draw(st.sampled_from(VECTOR_FIELDS)))
        node[key] = draw(st.lists(st.floats(-1, 1), max_size=6).filter(lambda v: len(v) != 3))
    return data


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=malformed())
def test_malformed_scenes_exit_1(data, tmp_path_factory, capsys):
    directory = tmp_path_factory.mktemp("malformed")
    scene = write_scene(directory, data)
    code, out, err = run_main(capsys, "animate", scene, "-o", directory / "out" / "a.glb")
    assert code == 1, (data, out, err)
    assert err.startswith("wiggly: error: ") and "Traceback" not in err
    assert out == ""
    assert sorted(p.name for p in directory.iterdir()) == ["shot.toml"]  # nothing written


def test_a_body_in_loose_pieces_is_refused_naming_the_scene_and_mesh(capsys, tmp_path):
    """Two cubes a metre apart, both keyed but none fixed: a one-line error naming the scene
    file and its mesh.path, never a traceback."""
    parts = [trimesh.creation.box(extents=(0.2, 0.2, 0.2)) for _ in range(2)]
    parts[1].apply_translation((1.0, 0.0, 0.0))
    trimesh.util.concatenate(parts).export(tmp_path / "two.obj")
    (tmp_path / "two.toml").write_text(
        'format = 1\n[mesh]\npath = "two.obj"\nresolution = 8\n[simulation]\nmodes = 16\n'
        '[time]\nend = 1.0\n[groups.a]\nbox = { min = [-1, -1, -1], max = [0.5, 1, 1] }\n'
        '[groups.b]\nbox = { min = [0.5, -1, -1], max = [2, 1, 1] }\n'
        '[[keyframes]]\ntime = 0.5\ngroup = "a"\nposition = "rest"\n'
        '[[keyframes]]\ntime = 0.5\ngroup = "b"\nposition = { offset = [0, 0.1, 0] }\n')
    assert main(["animate", str(tmp_path / "two.toml"), "-o", str(tmp_path / "two.npz")]) == 1
    err = capsys.readouterr().err
    assert 'two.toml: mesh.path = "two.obj": the body has 2 disconnected parts' in err, err
    assert "fix a group on each part" in err and "Traceback" not in err
    assert not (tmp_path / "two.npz").exists()


def test_keys_that_gravity_outweighs_are_warned_about(capsys, tmp_path):
    """A 60 s shot under gravity with the default stiffness misses its keys by metres: one
    warning lists them with the cause and the cure; with stiffness 1e9 the same keys are met
    to millimetres and nothing is said."""
    keys = ('[[keyframes]]\ntime = 0.0\ngroup = "left"\nposition = "rest"\n'
            'velocity = [0, 0, 0]\n{s}'
            '[[keyframes]]\ntime = 30.0\ngroup = "right"\n'
            'position = {{ offset = [0.0, 0.1, 0.0] }}\n{s}'
            '[[keyframes]]\ntime = 60.0\ngroup = "left"\nposition = "rest"\n{s}')
    head = ('format = 1\n[mesh]\npath = "builtin:bar"\n[simulation]\nmodes = 12\n'
            'warp = false\n[time]\nend = 60.0\nfps = 2\n'
            '[groups.left]\nbox = { min = [-1, -1, -1], max = [0.1, 1, 1] }\n'
            '[groups.right]\nbox = { min = [0.9, -1, -1], max = [2, 1, 1] }\n')
    for stiffness, warned in (("", True), ("stiffness = 1e9\n", False)):
        (tmp_path / "long.toml").write_text(head + keys.format(s=stiffness))
        assert main(["animate", str(tmp_path / "long.toml"), "-o",
                     str(tmp_path / "long.npz"), "--overwrite"]) == 0
        captured = capsys.readouterr()
        said = "keyframes missed by more than 5 % of the body's size" in captured.err
        assert said == warned, captured.err
        if warned:
            assert "keyframes[0] (group 'left', t = 0 s)" in captured.err
            assert "gravity can outweigh the keys" in captured.err


def test_iteration_counts_say_what_the_progress_bar_counted():
    """The progress bar counts the coarse level's iterations and the fine level's; the
    summary says the same total and splits it, instead of the fine level's alone."""
    from wiggly.solve import iteration_count

    assert iteration_count({"iterations": 11, "coarse": {"iterations": 25}}) == \
        "36 Newton iterations (25 on the coarse mesh, 11 on the fine)"
    assert iteration_count({"iterations": 1}) == "1 Newton iteration"
    assert iteration_count({"iterations": 4}, "Gauss-Newton") == "4 Gauss-Newton iterations"


def test_a_mesh_given_for_a_scene_and_a_missing_mesh_are_said_plainly(tmp_path, capsys):
    """`wiggly animate mesh.obj` says it is a mesh and what to do instead of a TOML parse
    error; `wiggly modes missing.obj` names the missing mesh without a scene it never had."""
    mesh = tmp_path / "capsule.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    assert main(["animate", str(mesh)]) != 0
    err = capsys.readouterr().err
    assert "is a mesh, not a scene file (.toml)" in err and f"wiggly edit {mesh}" in err
    assert "TOML" not in err.replace("(.toml)", "")
    assert main(["modes", str(tmp_path / "missing.obj")]) != 0
    err = capsys.readouterr().err
    assert f"{tmp_path / 'missing.obj'}: does not exist" in err and "scene:" not in err


def test_an_existing_preview_is_refused_with_the_commands_own_remedy(capsys, tmp_path):
    """``wiggly modes -o`` onto an existing file: refused before any work, with the remedy of
    that command (``--overwrite``), not a scene file's ``[output]`` table it has none of."""
    (tmp_path / "modes.png").write_bytes(b"mine")
    code, _, err = run_main(capsys, "modes", "builtin:bar", "-o", tmp_path / "modes.png")
    assert code == 1 and "modes.png exists; pass --overwrite to replace it" in err, err
    assert "[output]" not in err and "tetrahedraliz" not in err
    assert (tmp_path / "modes.png").read_bytes() == b"mine"


def test_gltf_targets_modes_from_the_flag_names_the_flag(capsys, tmp_path):
    """``--gltf-targets modes`` on a warped scene is refused naming the flag and --linear,
    not a scene key ``output.gltf_targets`` the user did not write; with --linear it runs."""
    scene = write_scene(tmp_path, SCENE)
    code, _, err = run_main(capsys, "animate", scene, "-o", tmp_path / "a.glb",
                            "--gltf-targets", "modes")
    assert code == 1 and "--gltf-targets modes needs a linear shot" in err, err
    assert "output.gltf_targets" not in err and "add --linear" in err
    code, _, err = run_main(capsys, "animate", scene, "-o", tmp_path / "a.glb",
                            "--gltf-targets", "modes", "--linear", "-q")
    assert code == 0, err


def test_modes_count_out_of_range_is_told_before_any_work(capsys):
    """``wiggly modes -n``: above the limit a usage error; fewer than a free body's rigid
    modes an error naming -n, both before tetrahedralizing."""
    code, _, err = run_main(capsys, "modes", "builtin:bar", "-n", "600")
    assert code == 2 and "-n/--modes: 600 must be an integer >= 1 and <= 500" in err
    code, _, err = run_main(capsys, "modes", "builtin:bar", "-n", "3")
    assert code == 1 and "-n/--modes 3: a free body has 6 rigid modes" in err
    assert "tetrahedraliz" not in err and "simulation.modes" not in err


def test_modes_speaks_in_its_options_and_refuses_runaway_coarseness(capsys, tmp_path):
    """``wiggly modes`` says its own options (not scene keys, not "scene:"); a tet edge longer
    than half the body (fTetWild ran for over 10 minutes on one of seven diagonals) and
    resolution 1 are refused before any meshing; a folder is called a folder."""
    code, _, err = run_main(capsys, "modes", "builtin:bar", "--resolution", "200")
    assert code == 1 and "builtin:bar: --resolution 200 would make about" in err, err
    assert "use --resolution <= " in err and "mesh." not in err and "scene:" not in err
    code, _, err = run_main(capsys, "modes", "builtin:bar", "--edge-length", "10")
    assert code == 1 and "--edge-length 10 m is longer than 1/2 of the body's" in err, err
    assert "tetrahedraliz" not in err
    code, _, err = run_main(capsys, "modes", "builtin:bar", "--resolution", "1")
    assert code == 2 and "--resolution: 1 must be an integer >= 2" in err
    code, _, err = run_main(capsys, "modes", tmp_path)
    assert code == 1 and f"{tmp_path}: is a folder" in err


def test_keys_missed_under_an_implausible_gravity_name_the_units(capsys, tmp_path):
    """Gravity given in the wrong units (981, Earth's in cm/s^2) is named as a likely unit
    slip before the solve (which grinds on such targets), and the missed-key warning points
    to it, not only to "raise their stiffness", which would not help."""
    data = copy.deepcopy(SCENE)
    data["simulation"]["gravity"] = [0.0, -981.0, 0.0]
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, data), "--linear",
                            "-o", tmp_path / "b.npz")
    assert code == 0, err
    said = err.index("simulation.gravity is 981 m/s^2, 100 times Earth's 9.81 (981 would be "
                     "Earth's in cm/s^2): check the units")
    assert said < err.index("spacetime solve")
    data["simulation"]["gravity"] = [0.0, -1e5, 0.0]  # mm/s^2: the keys are missed too
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, data, "mm.toml"),
                            "--linear", "-o", tmp_path / "m.npz")
    said = err.index("simulation.gravity is 1e+05 m/s^2")
    assert code == 0 and said < err.index("spacetime solve") < err.index("missed by more than 5 %")
    assert "check the units of the velocities or gravity named before the solve" in err
    data = copy.deepcopy(SCENE)
    data["keyframes"][0]["velocity"] = [1e6, 0.0, 0.0]  # mm/s given as m/s
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, data, "fast.toml"),
                            "--linear", "-o", tmp_path / "f.npz")
    assert code == 0 and err.index("keyframes[0].velocity is 1e+06 m/s, which would carry the "
                                   "group") < err.index("spacetime solve"), err
    code, _, err = run_main(capsys, "animate", write_scene(tmp_path, SCENE, "earth.toml"),
                            "--linear", "-o", tmp_path / "e.npz")
    assert code == 0 and "check the units" not in err


def test_the_solves_warnings_name_the_scene_file(capsys, tmp_path):
    """A key whose vertices the fixed group holds cannot be met: the library names the key,
    `wiggly animate` also the scene file, as it does for the scene's other warnings."""
    scene = ('format = 1\n[mesh]\npath = "builtin:bar"\n[simulation]\nmodes = 8\n'
             'warp = false\nfixed = ["left"]\n[time]\nend = 1.0\nfps = 4\n'
             '[groups.left]\nbox = { min = [-1, -1, -1], max = [0.1, 1, 1] }\n'
             '[[keyframes]]\ntime = 0.5\ngroup = "left"\nposition = { offset = [0, 0.1, 0] }\n')
    (tmp_path / "held.toml").write_text(scene)
    assert main(["animate", str(tmp_path / "held.toml"), "-o", str(tmp_path / "held.npz")]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "held by the fixed" in line]
    assert len(lines) == 1 and lines[0].startswith(f"wiggly: warning: {tmp_path / 'held.toml'}: "
                                                   "keyframe #0 ('left') at t=0.5: all "), lines


def test_mode_previews_of_a_coarse_surface_draw_the_tets(tmp_path):
    """An 8-vertex box cannot show a bar's bending: its mode preview draws the tet mesh's
    boundary, on which the first bending mode moves the bar's middle; a fine surface is
    drawn as it is."""
    import wiggly
    from wiggly.cli.modes import drawn_surface, mode_shapes

    trimesh.creation.box((1.0, 0.05, 0.05)).export(tmp_path / "bar.obj")
    body = wiggly.prepare(str(tmp_path / "bar.obj"), n_modes=8, resolution=20)
    rest, faces, on_tets = drawn_surface(body)
    assert on_tets is not None and len(rest) > 8 and faces.max() == len(rest) - 1
    bent = mode_shapes(body, [6], [1.0], on_tets)[0]
    middle = np.abs(rest[:, 0] - 0.0) < 0.05
    assert np.abs(bent[middle] - rest[middle]).max() > 0.05  # the first bending mode
    critter = wiggly.prepare("builtin:critter", n_modes=8)
    assert drawn_surface(critter)[2] is None
