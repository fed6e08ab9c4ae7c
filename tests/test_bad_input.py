"""What a new user gets wrong, through ``wiggly animate``: every mistake exits with code 1 and
one line naming the file, the key and the value, without a traceback, without touching any
file of the user, and, where the input alone decides, before any expensive work (fTetWild,
the eigenmodes, the solve are replaced by tripwires)."""

from __future__ import annotations

import copy
import hashlib
import importlib
import os
from pathlib import Path

import meshio
import numpy as np
import pytest
import tomli_w
import trimesh

import wiggly.body
import wiggly.export
from wiggly.cli import main
from wiggly.primitives import box_mesh

BASE = {
    "mesh": {"path": "ball.obj"},
    "time": {"end": 1.0, "fps": 10},
    "groups": {"bottom": {"box": {"min": [-1.0, -1.0, -1.0], "max": [1.0, -0.4, 1.0]}},
               "top": {"box": {"min": [-1.0, 0.4, -1.0], "max": [1.0, 1.0, 1.0]}}},
    "keyframes": [{"time": 0.0, "group": "bottom", "position": "rest"},
                  {"time": 1.0, "group": "top", "position": {"rotation": [0.0, 45.0, 0.0]}}],
    "output": {"paths": ["out/shot.glb"]},
}


#: Groups that select vertices of any small mesh.
EVERYWHERE = {"bottom": {"box": {"min": [-9.0, -9.0, -9.0], "max": [9.0, 9.0, 9.0]}},
              "top": {"sphere": {"center": [0.0, 0.0, 0.0], "radius": 9.0}}}


@pytest.fixture
def user(tmp_path, monkeypatch):
    """A user's folder with a mesh (an icosphere), a notes file and a scene writer."""
    sphere = trimesh.creation.icosphere(2, radius=0.5)
    sphere.export(tmp_path / "ball.obj")
    (tmp_path / "notes.txt").write_text("my notes\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path.parent / f"{tmp_path.name}-cache"))

    def scene(change=None, name: str = "shot.toml") -> Path:
        data = copy.deepcopy(BASE)
        for key, value in (change or {}).items():
            table, _, leaf = key.rpartition(".")
            node = data
            for part in filter(None, table.split(".")):
                node = node.setdefault(part, {})
            if value is None:
                node.pop(leaf, None)
            else:
                node[leaf] = value
        path = tmp_path / name
        path.write_text(tomli_w.dumps(data))
        return path

    return tmp_path, scene


@pytest.fixture
def tripwires(monkeypatch):
    """Make fTetWild, the eigenmodes and the solve fail loudly if they are reached."""
    import pytetwild

    from wiggly.mesh import tetwild_child

    def wire(what):
        def tripped(*args, **kwargs):
            raise AssertionError(f"expensive work started: {what}")
        return tripped

    monkeypatch.setattr(pytetwild, "tetrahedralize", wire("fTetWild"))
    monkeypatch.setattr(tetwild_child, "tetrahedralize_in_child", wire("fTetWild"))
    monkeypatch.setattr(wiggly.body, "compute_modes", wire("eigenmodes"))
    # the solve where the scene runner calls it
    monkeypatch.setattr(importlib.import_module("wiggly.scene.run"), "solve", wire("solve"))


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` with a hash of its contents."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def refused(capsys, folder: Path, scene: Path, *options) -> str:
    """Run ``wiggly animate``; check code 1, one line, no traceback, no file touched."""
    before = snapshot(folder)
    code = main(["animate", str(scene), "-q", *map(str, options)])
    _, err = capsys.readouterr()
    # a refusal after the solve may follow the missed-keys warning: BASE's linear 45 degree
    # turn misses its key by about 5 % of the ball, the warning's threshold
    lines = [line for line in err.strip().splitlines() if "missed by more than" not in line]
    assert code == 1, err
    assert "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith("wiggly: error: ")
    assert snapshot(folder) == before  # nothing written, replaced or left behind
    return lines[0]


def test_resolution_typo_is_refused_by_the_bound(user, tripwires, capsys):
    folder, scene = user
    line = refused(capsys, folder, scene({"mesh.resolution": 100000}))
    assert "shot.toml: mesh.resolution = 100000 must be an integer in [2, 200]" in line


def test_resolution_too_fine_for_the_tet_budget(user, tripwires, capsys):
    folder, scene = user
    line = refused(capsys, folder, scene({"mesh.resolution": 190}))
    assert "shot.toml: mesh.resolution = 190 would make about" in line
    assert "tetrahedra of ball.obj, more than wiggly's limit of 400000" in line
    assert "use resolution <= " in line
    line = refused(capsys, folder, scene({"mesh.edge_length": 0.001}))
    assert "shot.toml: mesh.edge_length = 0.001 would make about" in line


@pytest.mark.parametrize("modes, expected", [
    (100000, "shot.toml: simulation.modes = 100000 must be an integer in [1, 500]"),
    (3, "shot.toml: simulation.modes = 3 is fewer than the 6 rigid modes of a free body"),
])
def test_mode_counts_name_file_key_and_value(user, tripwires, capsys, modes, expected):
    folder, scene = user
    assert expected in refused(capsys, folder, scene({"simulation.modes": modes}))


def test_more_modes_than_degrees_of_freedom(user, tripwires, capsys):
    folder, scene = user
    V, T = box_mesh((2, 1, 1), (1.0, 0.5, 0.5))  # 12 vertices: 36 degrees of freedom
    meshio.write(folder / "block.vtu", meshio.Mesh(V - [0.5, 0.25, 0.25], [("tetra", T)]))
    line = refused(capsys, folder, scene({"mesh.path": "block.vtu", "simulation.modes": 40,
                                          "groups": EVERYWHERE}))
    assert "shot.toml: simulation.modes = 40 is more than the 36 degrees of freedom of " \
           "block.vtu's tet mesh (12 vertices, 3 each); use at most 36" in line


def test_a_body_fixed_everywhere_is_told_so(user, tripwires, capsys):
    """Every tet vertex fixed: the message names the fixed groups, not "use at most 0
    modes, or a higher mesh.resolution" (neither helps)."""
    folder, scene = user
    V, T = box_mesh((2, 1, 1), (1.0, 0.5, 0.5))
    meshio.write(folder / "block.vtu", meshio.Mesh(V - [0.5, 0.25, 0.25], [("tetra", T)]))
    line = refused(capsys, folder, scene({"mesh.path": "block.vtu", "groups": EVERYWHERE,
                                          "simulation.fixed": ["bottom"]}))
    assert "shot.toml: simulation.fixed = ['bottom'] holds every vertex of block.vtu's tet " \
           "mesh, so nothing can move" in line and "use at most 0" not in line


def test_a_surface_fixed_everywhere_is_told_so(user, capsys):
    """Every vertex of a cube's 8-vertex surface fixed (a Blender user's first try): its
    tets' inner vertices were free, so the solve took 15 s and warned of a 1.27 m sag and
    folds while the surface could not move; it is refused, naming the fixed groups."""
    import trimesh

    folder, scene = user
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(folder / "cube.obj")
    line = refused(capsys, folder, scene({"mesh.path": "cube.obj", "mesh.resolution": 8,
                                          "groups": EVERYWHERE,
                                          "simulation.fixed": ["bottom"]}))
    assert "shot.toml: simulation.fixed = ['bottom'] holds every vertex of cube.obj's surface " \
           "(through the tets that carry them), so the surface cannot move" in line


def test_a_plate_thinner_than_any_tet_says_how_thick_it_is(user, capsys):
    """A 1 mm plate, 1 m across, at resolution 12: fTetWild makes no tets, and the refusal
    said only "not thick compared to the edge length", with no way out; it names the
    plate's thickness (twice its volume over its area) and what to do."""
    import trimesh

    folder, scene = user
    trimesh.creation.box(extents=(1.0, 0.001, 1.0)).export(folder / "plate.obj")
    line = refused(capsys, folder, scene({"mesh.path": "plate.obj", "mesh.resolution": 12,
                                          "groups": EVERYWHERE}))
    assert "fTetWild produced no tetrahedra; the body is about 0.000998 m thick, against " \
           "tets of edge length" in line, line
    assert "thinner than the finest resolution (200) reaches: thicken it in the model" in line


def test_unwritable_folder_is_found_before_the_solve(user, tripwires, capsys):
    folder, scene = user
    if os.geteuid() == 0:  # root may write anywhere a permission allows: use a read-only fs
        target = "/proc/wiggly-test-out/shot.glb"
    else:
        (folder / "locked").mkdir()
        (folder / "locked").chmod(0o500)
        target = "locked/shot.glb"
    line = refused(capsys, folder, scene({"output.paths": [target]}))
    assert f'shot.toml: output.paths[0] = "{target}": cannot create files in ' in line
    assert ".shot." not in line  # no hidden temporary file named


def test_a_file_in_the_output_path_is_found_before_the_solve(user, tripwires, capsys):
    folder, scene = user
    line = refused(capsys, folder, scene({"output.paths": ["notes.txt/out/shot.glb"]}))
    assert 'output.paths[0] = "notes.txt/out/shot.glb": ' in line
    assert "notes.txt is a file, so" in line


def test_failed_output_replaces_no_file(user, capsys, monkeypatch):
    """overwrite = true, and the second output fails to write: the first, existing output
    keeps its old contents (outputs are moved into place only when all are written)."""
    folder, scene = user
    (folder / "out").mkdir()
    (folder / "out" / "shot.glb").write_bytes(b"the user's old export")

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(importlib.import_module("wiggly.export.formats"), "write_npz", disk_full)
    path = scene({"output.paths": ["out/shot.glb", "out/shot.npz"], "output.overwrite": True,
                  "simulation.modes": 8, "simulation.warp": False, "mesh.resolution": 6})
    line = refused(capsys, folder, path)
    assert "No space left on device" in line
    assert (folder / "out" / "shot.glb").read_bytes() == b"the user's old export"


def test_repair_false_speaks_the_scene_file(user, tripwires, capsys):
    folder, scene = user
    box = trimesh.creation.box()
    keep = ~np.isclose(box.vertices[box.faces][:, :, 1], 0.5).all(axis=1)  # open at the top
    trimesh.Trimesh(box.vertices, box.faces[keep], process=False).export(folder / "box.obj")
    line = refused(capsys, folder, scene({"mesh.path": "box.obj", "mesh.repair": False}))
    assert "shot.toml: mesh.repair = false refuses box.obj: 4 open edges" in line
    assert "repair=True" not in line and "Remove repair = false" in line


@pytest.mark.parametrize("content, expected", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n", "encloses no volume"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "contains no triangles"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0.5\nf 1 2 3\nf 2 4 3\n", "is an open sheet"),
    ("v 0 0 0\nv 1 0 nan\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
     "1 vertex has NaN or infinite coordinates"),
])
def test_what_cannot_be_filled(user, tripwires, capsys, content, expected):
    folder, scene = user
    (folder / "bad.obj").write_text(content)
    shot = scene({"mesh.path": "bad.obj", "groups": EVERYWHERE})
    line = refused(capsys, folder, shot)
    assert "bad.obj" in line and expected in line
    # in the scene's terms, as an unreadable file is: the file, its key and value
    assert line.startswith(f"wiggly: error: {shot.name}: mesh.path = \"bad.obj\": "), line


def test_a_long_mesh_path_keeps_its_file_name_in_messages(user, tripwires, capsys):
    folder, scene = user
    deep = folder / ("a_rather_long_folder_name_" * 3) / "and_deeper"
    deep.mkdir(parents=True)
    (deep / "flat_sheet.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\n"
                                         "f 2 4 3\n")
    path = str(deep.relative_to(folder) / "flat_sheet.obj")
    line = refused(capsys, folder, scene({"mesh.path": path, "groups": EVERYWHERE}))
    key = line.split("mesh.path = ", 1)[1].split('": ', 1)[0]
    assert len(key) < len(path) and " ... " in key and key.endswith("flat_sheet.obj"), line


def _stl_binary_solid_header() -> bytes:
    """A binary STL whose 80-byte header starts with "solid", as SolidWorks writes."""
    data = trimesh.creation.icosphere(2).export(file_type="stl")
    return b"solid SolidWorks exported part".ljust(80) + data[80:]


@pytest.mark.parametrize("name, content, expected", [
    ("ball.obj", lambda: trimesh.creation.icosphere(2).export(file_type="stl"),
     "is an STL file, not OBJ as its extension says; rename it to end in .stl"),
    ("ball.stl", lambda: trimesh.creation.icosphere(2).export(file_type="ply"),
     "is a PLY file, not STL as its extension says; rename it to end in .ply"),
    ("ball.stl", lambda: trimesh.creation.icosphere(2).export(file_type="obj").encode(),
     "is an OBJ file, not STL as its extension says; rename it to end in .obj"),
    ("ball.ply", lambda: ("# Blender 4.2\no ball\n" + trimesh.creation.icosphere(2).export(
        file_type="obj")).encode(), "is an OBJ file, not PLY as its extension says"),
    ("ball.stl", lambda: trimesh.creation.icosphere(2).export(file_type="stl_ascii")[:20000]
     .encode(), "the file is cut short: an ASCII STL ends with an 'endsolid' line"),
    ("ball.stl", lambda: _stl_binary_solid_header()[:8042],
     "the file is cut short: its binary STL header announces 320 triangles (16084 bytes) but "
     "it has 8042 bytes"),
    ("ball.obj", lambda: b"", "the file is empty (0 bytes)"),
    ("ball.off", lambda: trimesh.creation.icosphere(2).export(file_type="off")[:-3000].encode(),
     "the file is cut short: its OFF header announces 162 vertices and 320 faces, but it "
     "holds 162 and"),
    ("ball.obj", lambda: trimesh.creation.icosphere(2).export(file_type="obj")
     .rstrip()[:-4].encode(), "a face of 2 corners (a face needs 3 or more) at the end of the "
     "file: the file is damaged or cut short"),
])
def test_a_file_of_another_format_or_cut_short_says_what_it_is(user, tripwires, capsys, name,
                                                               content, expected):
    """The refusal names the real cause (the content's format, a cut, an empty file), not
    "contains no triangles" or a header count read from another format's bytes."""
    folder, scene = user
    (folder / name).write_bytes(content())
    line = refused(capsys, folder, scene({"mesh.path": name, "groups": EVERYWHERE}))
    assert name in line and expected in line, line


def test_a_binary_stl_with_a_solid_header_loads(tmp_path):
    from wiggly.mesh import load_mesh

    (tmp_path / "ball.stl").write_bytes(_stl_binary_solid_header())
    assert load_mesh(tmp_path / "ball.stl").n_faces == 320


@pytest.mark.parametrize("name, damage, expected", [
    ("cut.stl", "truncate", "the file is cut short: its binary STL header announces 320 "
     "triangles (16084 bytes) but it has 5361 bytes"),
    ("notes.glb", "text", "is not a binary glTF file (it does not start with 'glTF')"),
    ("holes.obj", "index", "line 4: a face names vertex 98, but the file has 3 vertices"),
    ("web.glb", "compressed", "its geometry is compressed (EXT_meshopt_compression); export "
     "it without compression"),
])
def test_a_damaged_mesh_file_is_named_for_what_is_wrong(user, tripwires, capsys, name,
                                                         damage, expected):
    """A mesh file cut short, a text file under a mesh's extension, an OBJ face naming a
    vertex the file lacks, a compressed glTF: the message says which, not the reader
    library's words."""
    folder, scene = user
    if damage == "truncate":
        data = trimesh.creation.icosphere(2).export(file_type="stl")
        (folder / name).write_bytes(data[:len(data) // 3])
    elif damage == "text":
        (folder / name).write_text("these are my notes, not a mesh\n")
    elif damage == "index":
        (folder / name).write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 98\n")
    else:  # a valid glb whose geometry needs a decoder (web models are compressed)
        import json
        import struct

        data = trimesh.creation.icosphere(2).export(file_type="glb")
        length = struct.unpack_from("<I", data, 12)[0]
        doc = json.loads(data[20:20 + length])
        doc["extensionsUsed"] = doc["extensionsRequired"] = ["EXT_meshopt_compression"]
        doc["accessors"][0]["bufferView"] = 99  # its data in a view only a decoder makes
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + length:]
        (folder / name).write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    line = refused(capsys, folder, scene({"mesh.path": name, "groups": EVERYWHERE}))
    assert name in line and expected in line, line
    assert "trimesh" not in line and "axis 0" not in line


def test_compact_gltf_needs_a_linear_shot(user, tripwires, capsys):
    folder, scene = user
    line = refused(capsys, folder, scene({"output.gltf_targets": "modes"}))
    assert 'shot.toml: output.gltf_targets = "modes" needs a linear shot' in line


def test_a_negative_gltf_frame_start_is_refused_before_anything_is_computed(
        user, tripwires, capsys):
    folder, scene = user
    line = refused(capsys, folder, scene({"output.frame_start": -5}))
    assert "shot.toml: output.frame_start (or --frame-start) = -5 would give negative glTF " \
           "times" in line and "frame_start >= 0" in line, line


def test_an_imperfect_surface_is_accepted_with_one_warning(user, capsys):
    folder, scene = user
    box = trimesh.creation.box()
    keep = ~np.isclose(box.vertices[box.faces][:, :, 1], 0.5).all(axis=1)
    trimesh.Trimesh(box.vertices, box.faces[keep], process=False).export(folder / "box.obj")
    path = scene({"mesh.path": "box.obj", "mesh.resolution": 8, "simulation.modes": 8,
                  "simulation.warp": False})
    code = main(["animate", str(path), "-q"])
    _, err = capsys.readouterr()
    assert code == 0, err
    warnings = [line for line in err.splitlines() if line.startswith("wiggly: warning:")]
    missed = [w for w in warnings if "missed by more than" in w]  # a 45 degree turn, linear
    assert all("cannot meet turned targets" in w for w in missed), missed
    # its 12 triangles cannot show the bending of the linear turn, also said
    coarse = [w for w in warnings if "long edges" in w]
    warnings = [w for w in warnings if w not in missed + coarse]
    assert len(warnings) == 1 and "box.obj: the surface has 4 open edges;" in warnings[0]
    assert (folder / "out" / "shot.glb").is_file()


@pytest.mark.parametrize("start, frame_start, named, loop", [
    (0.05, None, ["shot.glb", "shot.usda"], False),  # frame 0.5: both land between frames
    (-0.05, None, ["shot.usda"], False),  # glTF shifts a negative start to 0
    (0.05, None, ["shot.usda"], True),  # and a loop's
    (0.05, 1, [], False),  # frame_start puts frame k on 1 + k
    (0.1, None, [], False),  # frame 1
])
def test_a_shot_starting_between_frames_is_warned_about(user, capsys, start, frame_start,
                                                        named, loop):
    _, scene = user
    path = scene({"time.start": start, "time.end": start + 1.0, "time.loop": loop,
                  "keyframes": [
        {"time": start, "group": "bottom", "position": "rest"},
        {"time": start + 1.0, "group": "top", "position": {"offset": [0.0, 0.05, 0.0]}}],
        "output.paths": ["out/shot.glb", "out/shot.usda"], "output.frame_start": frame_start,
        "mesh.resolution": 8, "simulation.modes": 8, "simulation.warp": False})
    code = main(["animate", str(path), "-q"])
    _, err = capsys.readouterr()
    assert code == 0, err
    between = [line for line in err.splitlines() if "between the timeline's frames" in line]
    if not named:
        assert between == []
    else:
        assert len(between) == 1, err
        assert f"frames of {', '.join(named)} land" in between[0], between[0]
        assert f"frame {10 * start:g} at 10 fps" in between[0] and "frame_start" in between[0]
