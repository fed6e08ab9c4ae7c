"""Scene files: exact TOML round trip, every validation error, the JSON Schema, group selectors."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import shutil
import tomllib
import warnings
from pathlib import Path

import jsonschema
import meshio
import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from wiggly import WigglyInputError
from wiggly.mesh import load_model
from wiggly.primitives import box_mesh
from wiggly.scene import (
    Absolute,
    Box,
    DampingSpec,
    FromMesh,
    GroupSpec,
    Indices,
    KeyframeSpec,
    MaterialSpec,
    MeshSpec,
    Nearest,
    Offset,
    OutputSpec,
    Rest,
    Rigid,
    Scene,
    SimulationSpec,
    Sphere,
    TimeSpec,
    builtin_model,
    keyframes_of,
    load_scene,
    resolve_groups,
    save_scene,
    scene_from_dict,
    scene_schema,
    scene_to_dict,
    scene_to_toml,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))
DEMO = ROOT / "src" / "wiggly" / "data" / "demo.toml"
SCHEMA_FILE = ROOT / "src" / "wiggly" / "data" / "scene.schema.json"

# A valid scene touching every table, selector and kind of position target.
BASE = {
    "format": 1,
    "mesh": {"path": "builtin:bar", "resolution": 6},
    "material": {"young": 1e5, "poisson": 0.3, "density": 1000.0},
    "damping": {"alpha": 0.5, "beta": 0.002},
    "simulation": {"gravity": [0.0, -9.81, 0.0], "modes": 8, "fixed": ["left"]},
    "time": {"start": 0.0, "end": 1.0, "fps": 20},
    "groups": {
        "left": {"box": {"min": [-0.01, -1.0, -1.0], "max": [0.01, 1.0, 1.0]}},
        "tip": {"sphere": {"center": [1.0, 0.0, 0.0], "radius": 0.06}, "color": "#ff0000"},
        "mid": {"nearest": {"points": [[0.5, 0.05, 0.05]], "count": 4}},
        "three": {"indices": [5, 3, 9]},
    },
    "keyframes": [
        {"time": 0.0, "group": "tip", "position": "rest", "velocity": [0.0, 0.0, 0.0]},
        {"time": 0.4, "group": "tip", "position": {"offset": [0.0, 0.1, 0.0]}},
        {"time": 0.6, "group": "three",
         "position": {"absolute": [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]]}},
        {"time": 0.8, "group": "mid",
         "position": {"rotation": [0.0, 0.0, 30.0], "center": [0.5, 0.0, 0.0]},
         "stiffness": 1e3, "name": "twist"},
    ],
    "output": {"paths": ["out/bar.npz"]},
}


def write(tmp_path: Path, data: dict, name: str = "shot.toml") -> Path:
    path = tmp_path / name
    path.write_text(tomli_w.dumps(data))
    return path


def every_kind_scene() -> Scene:
    """Every selector, position kind and optional key, with awkward values."""
    return Scene(
        mesh=MeshSpec("meshes/thing.obj", edge_length=0.0125, repair=True),
        material=MaterialSpec(1.0 / 3.0 * 1e5, 0.0, 1e-3),
        damping=DampingSpec(0.0, 1e-300),
        simulation=SimulationSpec(gravity=(0.0, 0.0, -1.62), modes=1, warp=False,
                                  lumped_mass=True, fixed=("base", "ring"), preroll=0.0),
        time=TimeSpec(start=-0.5, duration=2.25, fps=23.976),
        groups={
            "base": GroupSpec(Box((-1.0, -2.0, -3.0), (1.0, 2.0, 3.0)), color="#00FF7f"),
            "ball": GroupSpec(Sphere((0.1, 0.2, 0.3), 1e-3)),
            "near": GroupSpec(Nearest(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), count=7)),
            "ring": GroupSpec(Indices((9, 0, 4)), on="tets"),
            "saddle": GroupSpec(FromMesh("saddle group é \"q\"")),
            "with-dash_1": GroupSpec(Indices(tuple(range(40)))),
        },
        keyframes=[
            KeyframeSpec(-0.5, "base", Rest()),
            KeyframeSpec(0.0, "ball", Offset((0.1, -0.2, 1e-12)), velocity=(1.0, 2.0, 3.0)),
            KeyframeSpec(0.25, "ring", Absolute(((0.0, 0.0, 0.0), (1.0, 1.0, 1.0),
                                                 (0.1, 0.2, 0.3)))),
            KeyframeSpec(0.5, "near", Rigid((10.0, 20.0, 30.0))),
            KeyframeSpec(0.75, "near", Rigid((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (1.0, 2.0, 3.0))),
            KeyframeSpec(1.0, "saddle", None, velocity=(0.0, -1.0, 0.0), c_A=2.5, c_B=0.0,
                         name="ünïcode 'name' \\ with # and \"quotes\""),
            KeyframeSpec(1.75, "with-dash_1", Absolute(tuple((i * 0.1, 0.0, -i * 1e-3)
                                                             for i in range(40))),
                         stiffness=0.0),
        ],
        output=OutputSpec(paths=("a.glb", "b/c.usda", "frames/f.obj", "x.GIF"), overwrite=True,
                          size=(640, 480), camera=(30.0, -10.5)),
    )


# ----------------------------------------------------------------------------------------------
# round trip


def test_round_trip_every_kind(tmp_path):
    scene = every_kind_scene()
    path = save_scene(scene, tmp_path / "s.toml")
    text = path.read_text()
    assert scene_from_dict(tomllib.loads(text)) == scene
    assert tomllib.loads(text) == _without_none(scene_to_dict(scene))
    # load_scene also checks that the mesh file exists
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "thing.obj").write_text("")
    loaded = load_scene(path)
    assert loaded == scene
    assert loaded.source == path.resolve()
    assert scene_to_toml(loaded) == text


def test_round_trip_a_drive_with_several_animations(tmp_path):
    """drive.animation as an array (several glTF animations played together) reads as a
    tuple, writes back as the same array, and its items are checked one by one."""
    text = ('format = 1\n[mesh]\npath = "m.obj"\n[time]\nend = 1.0\n[groups.g]\n'
            'indices = [0]\n[drive]\npath = "d.glb"\ngroup = "g"\n'
            'animation = ["walk", 2]\n')
    scene = scene_from_dict(tomllib.loads(text))
    assert scene.drive.animation == ("walk", 2)
    assert 'animation = ["walk", 2]' in scene_to_toml(scene)
    assert scene_from_dict(tomllib.loads(scene_to_toml(scene))) == scene
    with pytest.raises(WigglyInputError, match=r"drive\.animation\[1\] = 1\.5 must be an "
                                               r"animation name or index"):
        scene_from_dict(tomllib.loads(text.replace('["walk", 2]', '["walk", 1.5]')))


def _without_none(d):
    if isinstance(d, dict):
        return {k: _without_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list | tuple):
        return [_without_none(v) for v in d]
    return d


@pytest.mark.parametrize("path", [*EXAMPLES, DEMO], ids=lambda p: p.name)
def test_round_trip_examples(path, tmp_path):
    scene = load_scene(path)
    if scene.drive is not None:  # the copy's relative driver path must resolve, too
        (tmp_path / scene.drive.path).write_bytes(scene.resolve(scene.drive.path).read_bytes())
    copy_path = save_scene(scene, tmp_path / path.name)
    assert load_scene(copy_path) == scene


def test_saved_text_is_readable(tmp_path):
    text = scene_to_toml(every_kind_scene())
    assert "[groups.base]\nbox = { min = [-1.0, -2.0, -3.0], max = [1.0, 2.0, 3.0] }" in text
    assert 'position = "rest"' in text
    assert "[keyframes.position]\nabsolute = [\n    [0.0, 0.0, 0.0]," in text  # long: wrapped
    assert "\n[[keyframes]]\ntime = 1.75\n" in text


_finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)
_positive = st.floats(1e-6, 1e9, allow_nan=False)
_vec = st.tuples(_finite, _finite, _finite)
_names = st.from_regex(r"[A-Za-z0-9_-]{1,12}", fullmatch=True)


@st.composite
def scenes(draw) -> Scene:
    names = draw(st.lists(_names, min_size=1, max_size=4, unique=True))
    selectors = st.one_of(
        st.builds(lambda a, b: Box(tuple(map(min, a, b)), tuple(map(max, a, b))), _vec, _vec),
        st.builds(Sphere, _vec, _positive),
        st.builds(Nearest, st.lists(_vec, min_size=1, max_size=3).map(tuple),
                  st.integers(1, 50)),
        st.builds(Indices, st.lists(st.integers(0, 10**6), min_size=1, max_size=8,
                                    unique=True).map(tuple)),
        st.builds(FromMesh, st.text(min_size=1, max_size=10)))
    groups = {n: GroupSpec(draw(selectors), draw(st.sampled_from(["surface", "tets"])),
                           draw(st.none() | st.from_regex(r"#[0-9a-fA-F]{6}", fullmatch=True)))
              for n in names}
    start = draw(st.floats(-10, 10, allow_nan=False))
    duration = draw(st.floats(0.01, 100, allow_nan=False))
    positions = st.one_of(
        st.none(), st.just(Rest()), st.builds(Offset, _vec),
        st.builds(Absolute, st.lists(_vec, min_size=1, max_size=3).map(tuple)),
        st.builds(Rigid, _vec, _vec, st.none() | _vec))
    keys = []
    for _ in range(draw(st.integers(0, 5))):
        pos = draw(positions)
        vel = draw(_vec) if pos is None else draw(st.none() | _vec)
        t = draw(st.floats(start, start + duration, allow_nan=False))
        w = st.none() | st.floats(0, 1e12, allow_nan=False)
        keys.append(KeyframeSpec(t, draw(st.sampled_from(names)), pos, vel, draw(w), draw(w),
                                 draw(w), draw(st.text(max_size=10))))
    fixed = tuple(draw(st.lists(st.sampled_from(names), unique=True)))
    return Scene(
        mesh=MeshSpec("builtin:bar", draw(st.none() | st.integers(2, 200)),
                      repair=draw(st.none() | st.booleans())),
        material=MaterialSpec(draw(st.floats(1e-3, 1e13)), draw(st.floats(0, 0.4999)),
                              draw(st.floats(1e-3, 1e6))),
        damping=DampingSpec(draw(st.floats(0, 100)), draw(st.floats(0, 1))),
        simulation=SimulationSpec(draw(_vec), draw(st.integers(1 if fixed else 6, 500)),
                                  draw(st.booleans()), fixed=fixed),
        time=TimeSpec(start, end=start + duration,
                      fps=draw(st.floats(0.1, min(1000, 19_999 / duration)))),
        groups=groups, keyframes=keys,
        output=OutputSpec(tuple(draw(st.lists(st.sampled_from(
            ["a.glb", "b.usd", "c.npz", "d.mp4", "e.png", "f/g.obj"]), unique=True))),
            frame_start=draw(st.none() | st.integers(-1000, 1000)),
            gltf_targets=draw(st.none() | st.sampled_from(["frames", "modes"]))))


@settings(max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(scene=scenes())
def test_round_trip_random_scenes(scene, tmp_path):
    path = save_scene(scene, tmp_path / "random.toml", overwrite=True)
    assert load_scene(path) == scene


def test_save_refuses_existing_and_is_atomic(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    target = tmp_path / "copy.toml"
    target.write_text("keep me")
    with pytest.raises(WigglyInputError, match=r"copy.toml exists"):
        save_scene(scene, target)
    assert target.read_text() == "keep me"
    save_scene(scene, target, overwrite=True)
    assert load_scene(target) == scene
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy.toml", "shot.toml"]


def test_saving_over_a_scene_file_keeps_its_comments_and_layout(tmp_path):
    """Saving an edited scene over its commented file (what the editor's Save does) keeps the
    comments, the order and the formatting of what did not change, changes what did, adds
    no defaults the file left out, and loads back as exactly the edited scene."""
    from dataclasses import replace

    text = """# my shot: notes the author keeps
format = 1

[mesh]
path = "builtin:critter"   # the bundled one, for now
resolution = 14

[material]
young = 3e5     # soft rubber

[time]
end = 2.0
fps = 24

[groups.feet]
box = { min = [-1, -1, -1], max = [1, 0.06, 1] }   # below the ankles

[[keyframes]]   # planted
time = 0.0
group = "feet"
position = "rest"

[[keyframes]]   # planted again
time = 1.5
group = "feet"
position = "rest"
"""
    path = tmp_path / "shot.toml"
    path.write_text(text)
    scene = load_scene(path)
    edited = replace(scene, material=replace(scene.material, young=5e5),
                     keyframes=[*scene.keyframes[:1], replace(scene.keyframes[1], time=1.25)])
    save_scene(edited, path, overwrite=True)
    saved = path.read_text()
    for kept in ("# my shot: notes the author keeps", "# the bundled one, for now",
                 "# below the ankles", "# planted\n", "# planted again", "fps = 24\n"):
        assert kept in saved, (kept, saved)
    assert "young = 500000.0" in saved and "time = 1.25" in saved and "poisson" not in saved
    assert saved.index("[mesh]") < saved.index("[material]") < saved.index("[time]")
    assert load_scene(path) == edited
    # an edit that removes a group and its key, and adds another: still exact
    fewer = replace(edited, keyframes=edited.keyframes[:1],
                    groups={**edited.groups, "head": GroupSpec(Sphere((0.45, 0.3, 0.0), 0.1))})
    save_scene(fewer, path, overwrite=True)
    assert load_scene(path) == fewer and "# my shot: notes the author keeps" in path.read_text()
    # a key posed (rest -> a turn), then another added: poses stay one inline table per key
    posed = replace(fewer, keyframes=[replace(fewer.keyframes[0], position=Rigid(
        (0.0, 0.0, 5.0), (0.0, 0.1, 0.0), (0.4, 0.3, 0.0)))])
    for scene in (posed, replace(posed, keyframes=[*posed.keyframes, replace(
            posed.keyframes[0], time=1.0, position=Rigid((0.0, 9.0, 0.0), (0.0, 0.0, 0.0),
                                                         None))])):
        save_scene(scene, path, overwrite=True)
        saved = path.read_text()
        assert load_scene(path) == scene
        assert "position = {rotation = [0.0, 0.0, 5.0], translation = [0.0, 0.1, 0.0], " \
            "center = [0.4, 0.3, 0.0]}\n" in saved, saved
        assert "[keyframes.position]" not in saved and "{  " not in saved, saved


def test_save_refuses_invalid_scene(tmp_path):
    scene = load_scene(write(tmp_path, BASE))
    scene.keyframes.append(KeyframeSpec(0.5, "nope", Rest()))
    with pytest.raises(WigglyInputError, match=r'keyframes\[4\].group = "nope" is not a group'):
        save_scene(scene, tmp_path / "bad.toml")
    assert not (tmp_path / "bad.toml").exists()


# ----------------------------------------------------------------------------------------------
# validation: every error path, with the exact key path


def mutate(path: str, value=None, delete: bool = False) -> dict:
    """A copy of BASE with the key at ``path`` (dots and [i]) set to ``value`` or deleted."""
    data = copy.deepcopy(BASE)
    parts = [int(p) if p.isdigit() else p
             for p in path.replace("[", ".").replace("]", "").split(".")]
    node = data
    for p in parts[:-1]:
        node = node[p]
    if delete:
        del node[parts[-1]]
    else:
        node[parts[-1]] = value
    return data


ERRORS = [
    # (key path, new value or DELETE, expected message)
    ("material.yuong", 1.0, "unknown key 'yuong' in [material]; did you mean 'young'?"),
    ("meshh", {}, "unknown key 'meshh' at the top level; did you mean 'mesh'?"),
    ("keyframes[1].position.ofset", [0, 0, 0],
     "unknown key 'ofset' in keyframes[1].position; did you mean 'offset'?"),
    ("groups.tip.zzz", 1, "unknown key 'zzz' in [groups.tip]; allowed keys: box, sphere"),
    ("format", 2, "format = 2 must be 1 (the newest format this version of wiggly reads)"),
    ("mesh", "DELETE", "mesh is missing; it is required"),
    ("mesh.path", "DELETE", "mesh.path is missing; it is required: a non-empty string"),
    ("mesh.path", "", 'mesh.path = "" must be a non-empty string'),
    ("mesh.path", "builtin:crtter", 'mesh.path = "builtin:crtter" is not a bundled model'),
    ("mesh.resolution", 0, "mesh.resolution = 0 must be an integer in [2, 200]"),
    ("mesh.resolution", 2.5, "mesh.resolution = 2.5 must be an integer in [2, 200]"),
    ("mesh.resolution", 100000, "mesh.resolution = 100000 must be an integer in [2, 200]"),
    ("mesh.edge_length", 0.1, "mesh has both resolution and edge_length; give only one"),
    ("mesh.repair", "yes", 'mesh.repair = "yes" must be true or false'),
    ("material.young", -1.0, "material.young = -1.0 must be a number in [0.001, 1e+13] (Pa)"),
    ("material.young", "soft", 'material.young = "soft" must be a number in [0.001, 1e+13] (Pa)'),
    ("material.young", True, "material.young = true must be a number in [0.001, 1e+13] (Pa)"),
    ("material.young", math.nan, "material.young = nan must be a number in [0.001, 1e+13] (Pa)"),
    ("material.young", 1e-300, "material.young = 1e-300 must be a number in [0.001, "),
    ("material.density", 1e300, "material.density = 1e+300 must be a number in [0.001, "),
    ("material.young", math.inf, "material.young = inf must be a number in [0.001, 1e+13] (Pa)"),
    ("material.poisson", 0.5, "material.poisson = 0.5 must be a number in [0, 0.5)"),
    ("material.density", 0, "material.density = 0 must be a number in [0.001, 1000000] (kg/m^3)"),
    ("damping.alpha", -0.1, "damping.alpha = -0.1 must be a number >= 0 (1/s)"),
    ("damping.beta", [1], "damping.beta = [1] must be a number >= 0 (s)"),
    ("simulation.gravity", [0, -9.81], "simulation.gravity = [0, -9.81] must be an array of 3 "
                                       "numbers [gx, gy, gz] (m/s^2)"),
    ("simulation.gravity", [0, math.nan, 0], "simulation.gravity = [0, nan, 0] must be"),
    ("simulation.modes", 0, "simulation.modes = 0 must be an integer in [1, 500]"),
    ("simulation.modes", 100000, "simulation.modes = 100000 must be an integer in [1, 500]"),
    ("output.gltf_targets", "mode", 'output.gltf_targets = "mode" must be "frames" or '
                                    '"modes"'),
    ("output.frame_start", 1.5, "output.frame_start = 1.5 must be an integer in "),
    ("simulation.warp", 1, "simulation.warp = 1 must be true or false"),
    ("simulation.fixed", "left", 'simulation.fixed = "left" must be an array of group names'),
    ("simulation.fixed", ["left", "left"], 'simulation.fixed[1] = "left" repeats '
                                           "simulation.fixed[0]"),
    ("simulation.fixed", ["lft"], 'simulation.fixed[0] = "lft" is not a group (did you mean '
                                  "'left'?); groups are: left, tip, mid, three"),
    ("simulation.preroll", -1, "simulation.preroll = -1 must be a number >= 0 (s)"),
    ("time.end", -1.0, "time.end = -1.0 must be after time.start = 0.0"),
    ("time.duration", 1.0, "time has both end and duration; give only one"),
    ("time.fps", 0, "time.fps = 0 must be a number in (0, 1000]"),
    ("time.fps", 5000, "time.fps = 5000 must be a number in (0, 1000]"),
    ("groups", [], "groups = [] must be a table of named items"),
    ("groups.tip", {"color": "#ff0000"}, "groups.tip has no selector; give exactly one of box, "
                                         "sphere, nearest, indices, from_mesh"),
    ("groups.tip.box", {"min": [0, 0, 0], "max": [1, 1, 1]},
     "groups.tip has 2 selectors (box, sphere); give exactly one"),
    ("groups.left.box.min", [0.5, -1, -1], "groups.left.box.min = [0.5, -1.0, -1.0] exceeds "
                                           "groups.left.box.max = [0.01, 1.0, 1.0] in x"),
    ("groups.left.box.max", "DELETE", "groups.left.box.max is missing; it is required"),
    ("groups.tip.sphere.radius", -0.1, "groups.tip.sphere.radius = -0.1 must be a number > 0 (m)"),
    ("groups.tip.color", "red", 'groups.tip.color = "red" must be a color "#rrggbb"'),
    ("groups.tip.on", "volume", 'groups.tip.on = "volume" must be "surface" or "tets"'),
    ("groups.mid.nearest.count", 0, "groups.mid.nearest.count = 0 must be an integer >= 1"),
    ("groups.mid.nearest.points", [], "groups.mid.nearest.points = [] must have at least 1 item"),
    ("groups.three.indices", [1, -2], "groups.three.indices[1] = -2 must be an integer >= 0"),
    ("groups.three.indices", [1, 1], "groups.three.indices[1] = 1 repeats "
                                     "groups.three.indices[0]"),
    ("groups.three.indices", [], "groups.three.indices = [] must have at least 1 item"),
    ("groups.three.from_mesh", "x", "groups.three has 2 selectors (indices, from_mesh)"),
    ("keyframes", {"time": 0}, "keyframes = { time = 0 } must be an array of tables"),
    ("keyframes[0].time", "DELETE", "keyframes[0].time is missing; it is required: a number (s)"),
    ("keyframes[0].time", 3.5, "keyframes[0].time = 3.5 is outside the shot's time range "
                               "[0.0, 1.0] s (the keyframe of group \"tip\"): move it, or the "
                               "shot's start or end"),
    ("keyframes[0].time", -0.1, "keyframes[0].time = -0.1 is outside the shot's time range"),
    ("keyframes[0].group", "DELETE", "keyframes[0].group is missing; it is required"),
    ("keyframes[0].group", "tpi", 'keyframes[0].group = "tpi" is not a group (did you mean '
                                  "'tip'?); groups are: left, tip, mid, three"),
    ("keyframes[0].position", "Rest", 'keyframes[0].position = "Rest" must be "rest" or a table'),
    ("keyframes[0].position", [0, 1, 0], "keyframes[0].position = [0, 1, 0] must be \"rest\" or"),
    ("keyframes[1].position", {}, "keyframes[1].position = {} must be \"rest\" or a table with "
                                  "offset, absolute, or rotation/translation"),
    ("keyframes[1].position.rotation", [0, 0, 1],
     "keyframes[1].position = { offset = [0.0, 0.1, 0.0], rotation = [0, 0, 1] } must be "
     '"rest" or a table with offset, absolute, or rotation/translation (and optional center); '
     "it mixes offset and rigid targets"),
    ("keyframes[1].position.offset", [0, "up", 0],
     'keyframes[1].position.offset = [0, "up", 0] must be an array of 3 numbers [dx, dy, dz] (m)'),
    ("keyframes[2].position.absolute", [[0, 0, 0], [1, 1]],
     "keyframes[2].position.absolute[1] = [1, 1] must be an array of 3 numbers"),
    ("keyframes[3].position", {"center": [0, 0, 0]},
     "keyframes[3].position has a center but neither rotation nor translation"),
    ("keyframes[3].position.rotation", [0, 0, math.inf],
     "keyframes[3].position.rotation = [0, 0, inf] must be an array of 3 numbers "
     "[rx, ry, rz] (degrees)"),
    ("keyframes[0].velocity", "fast", 'keyframes[0].velocity = "fast" must be an array of 3 '
                                      "numbers [vx, vy, vz] (m/s)"),
    ("keyframes[1].position", "DELETE", "keyframes[1] has neither position nor velocity; give at "
                                        "least one"),
    ("keyframes[3].stiffness", -5, "keyframes[3].stiffness = -5 must be a number >= 0"),
    ("keyframes[3].c_A", math.nan, "keyframes[3].c_A = nan must be a number >= 0"),
    ("keyframes[3].name", 3, "keyframes[3].name = 3 must be a string"),
    ("output.paths", ["a.mov"], 'output.paths[0] = "a.mov" must be a file name ending in .glb, '),
    ("output.paths", ["a.glb", "a.glb"], 'output.paths[1] = "a.glb" repeats output.paths[0]'),
    ("output.overwrite", "no", 'output.overwrite = "no" must be true or false'),
    ("output.size", [10, 10], "output.size = [10, 10] must be [width, height] in pixels"),
    ("output.size", [640], "output.size = [640] must be [width, height] in pixels"),
    ("output.camera", "side2", 'output.camera = "side2" must be "three_quarter" or "front" or '
                               '"side" or "back" or "top" or [azimuth, elevation] in degrees'),
    ("output.camera", [1, 2, 3], "output.camera = [1, 2, 3] must be"),
]


@pytest.mark.parametrize("key, value, message", ERRORS, ids=[e[0] for e in ERRORS])
def test_validation_errors(key, value, message, tmp_path):
    data = mutate(key, delete=True) if value == "DELETE" else mutate(key, value)
    path = write(tmp_path, data)
    with pytest.raises(WigglyInputError) as err:
        load_scene(path)
    lines = str(err.value).splitlines()
    assert any(line.startswith(f"{path}: ") and message in line for line in lines), lines


def test_all_problems_reported_at_once(tmp_path):
    data = mutate("material.young", -1.0)
    data["damping"]["alpha"] = "x"
    data["keyframes"][0]["time"] = "late"
    with pytest.raises(WigglyInputError) as err:
        load_scene(write(tmp_path, data))
    assert len(err.value.problems) == 3
    assert [p.split(" ")[0] for p in err.value.problems] == [
        "material.young", "damping.alpha", "keyframes[0].time"]


@pytest.mark.parametrize("text, says", [
    ("format = 1\n[[keyframes]]\ntime = 0.0\n[keyframes]\ntime = 1.0\n",
     "Cannot declare keyframes twice (at line 4, column 11); [keyframes] and [[keyframes]] "
     "cannot both appear: a list of tables is written [[keyframes]] before each entry"),
    ("format = 1\n[time]\nend = 1.0\n[time]\nfps = 10\n",
     "Cannot declare time twice (at line 4, column 6); [time] appears twice"),
    ("format = 1\n[time]\nend = 1.0\nend = 2.0\n",
     "Cannot overwrite a value (at line 4, column 10); 'end' is given twice in its table"),
    ('{"format": 1, "time": {"end": 1.0}}\n', "not TOML (this looks like JSON)"),
])
def test_toml_mistakes_are_named_in_a_users_words(tmp_path, text, says):
    """tomllib's complaints name keys as dotted names, not Python tuples, say which key is
    given twice, how a list of tables is written, and that JSON is not TOML."""
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    with pytest.raises(WigglyInputError) as caught:
        load_scene(bad)
    assert str(caught.value).startswith(f"{bad}: ") and says in str(caught.value), caught.value
    assert "('" not in str(caught.value)


def test_file_errors(tmp_path):
    with pytest.raises(WigglyInputError, match=r"missing.toml: no such scene file"):
        load_scene(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("a = [\n")
    with pytest.raises(WigglyInputError, match=r"bad.toml: not valid TOML"):
        load_scene(bad)
    data = mutate("mesh.path", "nothere.obj")
    with pytest.raises(WigglyInputError, match=r'mesh.path = "nothere.obj": no such file'):
        load_scene(write(tmp_path, data))


def test_a_windows_path_is_told_to_use_slashes(tmp_path):
    (tmp_path / "meshes").mkdir()
    shutil.copy(builtin_model("bar"), tmp_path / "meshes" / "bar.obj")
    with pytest.raises(WigglyInputError) as err:
        load_scene(write(tmp_path, mutate("mesh.path", "meshes\\bar.obj")))
    assert 'separate folders with "/" on every system ("meshes/bar.obj" exists)' in str(err.value)
    with pytest.raises(WigglyInputError) as err:
        load_scene(write(tmp_path, mutate("mesh.path", "other\\bar.obj")))
    assert str(err.value).endswith('separate folders with "/" on every system'), err.value


def test_defaults_and_time_range(tmp_path):
    scene = load_scene(write(tmp_path, {"mesh": {"path": "builtin:bar"}}))
    assert scene == Scene(MeshSpec("builtin:bar"))
    assert scene.time_range() == (0.0, 1.0)
    assert scene.mesh_file() == builtin_model("bar")
    data = {"mesh": {"path": "builtin:bar"}, "groups": {"a": {"indices": [0]}},
            "keyframes": [{"time": 2.5, "group": "a", "position": "rest"}],
            "time": {"start": 0.5}}
    assert load_scene(write(tmp_path, data)).time_range() == (0.5, 2.5)
    data["time"] = {"start": 0.5, "duration": 3.0}
    assert load_scene(write(tmp_path, data)).time_range() == (0.5, 3.5)


# ----------------------------------------------------------------------------------------------
# JSON Schema


def test_schema_file_is_current():
    shipped = json.loads(SCHEMA_FILE.read_text())
    assert shipped == scene_schema(), (
        "src/wiggly/data/scene.schema.json is stale; regenerate it with "
        "`wiggly schema > src/wiggly/data/scene.schema.json`")
    jsonschema.Draft202012Validator.check_schema(shipped)


@pytest.mark.parametrize("path", [*EXAMPLES, DEMO], ids=lambda p: p.name)
def test_schema_accepts_examples(path):
    jsonschema.Draft202012Validator(scene_schema()).validate(tomllib.loads(path.read_text()))


# Errors the schema cannot express: references between keys, NaN/inf (not JSON), min <= max.
NOT_IN_SCHEMA = ("is not a group", "outside the shot's time range", "must be after", "exceeds",
                 "is not a bundled model", "nan", "inf")


STRUCTURAL = [e for e in ERRORS if not any(s in e[2] for s in NOT_IN_SCHEMA)]


@pytest.mark.parametrize("key, value, message", STRUCTURAL, ids=[e[0] for e in STRUCTURAL])
def test_schema_rejects_malformed(key, value, message):
    data = mutate(key, delete=True) if value == "DELETE" else mutate(key, value)
    errors = list(jsonschema.Draft202012Validator(scene_schema()).iter_errors(data))
    assert errors, f"the schema accepts {key} = {value!r}"


def test_schema_accepts_base():
    jsonschema.Draft202012Validator(scene_schema()).validate(BASE)


# ----------------------------------------------------------------------------------------------
# groups, against the bar model (x in [0, 1], y and z in [-0.05, 0.05])


@pytest.fixture(scope="module")
def bar_model():
    return load_model(builtin_model("bar"), resolution=6)


def scene_with(groups: dict, keyframes=()) -> Scene:
    return Scene(MeshSpec("builtin:bar"), groups=groups, keyframes=list(keyframes))


def test_selectors_on_the_bar(bar_model):
    V = bar_model.surface.vertices
    T = bar_model.tets.vertices
    groups = resolve_groups(scene_with({
        "end": GroupSpec(Box((-1.0, -1.0, -1.0), (1e-9, 1.0, 1.0))),
        "corner": GroupSpec(Sphere((1.0, 0.05, 0.05), 0.0301)),
        "near": GroupSpec(Nearest(((0.5123, 0.0131, 0.05), (0.0, 0.0471, 0.0317)), 3)),
        "three": GroupSpec(Indices((5, 3, 9))),
        "tets_end": GroupSpec(Box((0.99, -1.0, -1.0), (2.0, 1.0, 1.0)), on="tets"),
    }), bar_model)
    # hand-computed: loops over the vertices, plain Python arithmetic
    end = [i for i, (x, _, _) in enumerate(V) if x <= 1e-9]
    assert len(end) == 37  # the x = 0 face (see src/wiggly/data/README.md)
    assert groups["end"].tolist() == end
    corner = [i for i, v in enumerate(V) if math.dist(v, (1.0, 0.05, 0.05)) <= 0.0301]
    assert groups["corner"].tolist() == corner and len(corner) > 0
    near = set()
    for p in ((0.5123, 0.0131, 0.05), (0.0, 0.0471, 0.0317)):
        near |= set(sorted(range(len(V)), key=lambda i, p=p: math.dist(V[i], p))[:3])
    assert groups["near"].tolist() == sorted(near)
    assert groups["three"].tolist() == [5, 3, 9]  # order kept
    assert groups["tets_end"].tolist() == [i for i, (x, _, _) in enumerate(T) if x >= 0.99]


def test_from_mesh_groups(tmp_path):
    V, T = box_mesh((4, 2, 2), (1.0, 0.2, 0.2))
    top = (V[:, 1] > 0.15).astype(float)
    path = tmp_path / "box.vtu"
    meshio.write(path, meshio.Mesh(V, [("tetra", T)], point_data={"top": top}))
    model = load_model(path)
    scene = Scene(MeshSpec(str(path)), groups={
        "top": GroupSpec(FromMesh("top")), "top_tets": GroupSpec(FromMesh("top"), on="tets")})
    groups = resolve_groups(scene, model)
    assert groups["top"].tolist() == np.flatnonzero(top).tolist()
    assert groups["top_tets"].tolist() == np.flatnonzero(top).tolist()
    with pytest.raises(WigglyInputError, match=r'groups.x.from_mesh = "tpo": the surface has no '
                                               r"vertex group of that name \(did you mean 'top'"):
        resolve_groups(Scene(MeshSpec(str(path)), groups={"x": GroupSpec(FromMesh("tpo"))}),
                       model)


@pytest.mark.parametrize("group, keyframe, message", [
    (GroupSpec(Box((5.0, 5.0, 5.0), (6.0, 6.0, 6.0))), None,
     "groups.g (box) selects no vertex of the surface; its bounding box is [0.0, -0.05, -0.05]"),
    (GroupSpec(Sphere((0.5, 0.5, 0.5), 0.01)), None, "groups.g (sphere) selects no vertex"),
    (GroupSpec(Indices((0, 1034))), None,
     "groups.g.indices[1] = 1034 is out of range: the surface has 1034 vertices "
     "(indices 0..1033)"),
    (GroupSpec(Indices((0, 10**6)), on="tets"), None,
     "groups.g.indices[1] = 1000000 is out of range: the tet mesh has"),
    (GroupSpec(Nearest(((0.0, 0.0, 0.0),), 5000)), None,
     "groups.g.nearest.count = 5000 exceeds the number of vertex positions of the surface "
     "(1034)"),
    (GroupSpec(FromMesh("saddle")), None,
     'groups.g.from_mesh = "saddle": the surface has no vertex group of that name; it has no '
     "vertex groups"),
    (GroupSpec(Indices((0, 1, 2))), KeyframeSpec(0.5, "g", Absolute(((0.0, 0.0, 0.0),) * 2)),
     "keyframes[0].position.absolute has 2 rows but group 'g' has 3 vertices"),
])
def test_group_errors(bar_model, group, keyframe, message):
    scene = scene_with({"g": group}, [keyframe] if keyframe else [])
    with pytest.raises(WigglyInputError) as err:
        resolve_groups(scene, bar_model)
    assert str(err.value).startswith("scene: ")
    assert message in str(err.value)


def test_an_empty_box_on_a_z_up_file_read_y_up_says_so():
    """A column 0.2 m wide, 0.1 m deep and 1 m tall along z (a Z-up file read as y up, the
    default): a box around its top as the user sees it (y = 0.9 .. 1.1) selects nothing,
    and the message says that read Z-up it would select vertices; not when the scene names
    its up axis, nor when a Z-up reading selects nothing either."""
    from types import SimpleNamespace

    import trimesh

    column = trimesh.creation.box(extents=(0.2, 0.1, 1.0))
    column.apply_translation((0.0, 0.0, 0.5))
    surface = SimpleNamespace(vertices=np.asarray(column.vertices), groups={})
    for box, up, hinted in (((-1.0, 0.9, -1.0), None, True),
                            ((-1.0, 0.9, -1.0), "y", False),
                            ((-1.0, 2.0, -1.0), None, False)):
        top = GroupSpec(Box(box, (1.0, box[1] + 0.2, 1.0)))
        scene = scene_with({"top": top}, [])
        scene = dataclasses.replace(scene, mesh=dataclasses.replace(scene.mesh, up_axis=up))
        with pytest.raises(WigglyInputError) as err:
            resolve_groups(scene, surface=surface)
        said = 'read as a Z-up file (mesh.up_axis = "z": its z axis up), it would select 4'
        assert (said in str(err.value)) == hinted, str(err.value)


def test_nearest_counts_positions_so_an_stl_corner_is_one(tmp_path):
    """An STL file stores each triangle's corners apart: `nearest` with count 4 took four
    copies of one corner (a "fixed base" of a single point). It counts positions, and takes
    every vertex at them: on the STL and on the same welded mesh, the same points."""
    import trimesh

    from wiggly.mesh import load_model

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.export(tmp_path / "box.stl")
    box.export(tmp_path / "box.obj")
    nearest = GroupSpec(Nearest(((-0.6, -0.6, -0.6),), 4))
    picked = {}
    for name in ("box.stl", "box.obj"):
        model = load_model(tmp_path / name, resolution=4)
        scene = Scene(MeshSpec(str(tmp_path / name)), groups={"base": nearest})
        idx = resolve_groups(scene, model)["base"]
        picked[name] = np.unique(np.round(model.surface.vertices[idx], 9), axis=0)
    assert len(picked["box.obj"]) == 4  # the corner and its three neighbours
    np.testing.assert_array_equal(picked["box.stl"], picked["box.obj"])


# ----------------------------------------------------------------------------------------------
# keyframes built from a scene


def test_keyframe_targets(bar):
    """Targets of every position kind, against hand-computed values (``bar``: conftest)."""
    X = bar.surface.vertices
    sel = np.array([1, 7, 20, 33])
    groups = {"g": sel}
    c = (0.5, 0.0, 0.0)
    scene = scene_with({"g": GroupSpec(Indices(tuple(sel)))}, [
        KeyframeSpec(0.0, "g", Rest(), velocity=(0.0, 0.0, 0.0)),
        KeyframeSpec(0.1, "g", Offset((0.0, 0.2, 0.0)), stiffness=5.0, name="up"),
        KeyframeSpec(0.2, "g", Absolute(tuple(map(tuple, X[sel] * 2)))),
        KeyframeSpec(0.3, "g", Rigid((90.0, 90.0, 0.0), (1.0, 0.0, 0.0), c)),
        KeyframeSpec(0.4, "g", None, velocity=(0.0, 1.0, 0.0), c_A=1.0, c_B=2.0),
    ])
    keys = keyframes_of(scene, bar, groups)
    assert np.allclose(keys[0].position, X[sel]) and np.allclose(keys[0].velocity, 0)
    assert np.allclose(keys[1].position, X[sel] + [0.0, 0.2, 0.0])
    assert keys[1].stiffness == 5.0 and keys[1].name == "up" and keys[0].name == "g"
    assert np.allclose(keys[2].position, 2 * X[sel])
    # 90 degrees about X (y -> z, z -> -y), then 90 degrees about the fixed Y (z -> x, x -> -z)
    Rx = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    Ry = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    expected = (X[sel] - c) @ (Ry @ Rx).T + c + [1.0, 0.0, 0.0]
    assert np.allclose(keys[3].position, expected)
    assert keys[4].position is None and (keys[4].c_A, keys[4].c_B) == (1.0, 2.0)
    assert all(k.on == "surface" for k in keys)


def test_build_fixes_groups_and_checks_before_tetrahedralizing(tmp_path, monkeypatch):
    import pytetwild

    from wiggly.mesh import tetwild_child
    from wiggly.scene import build

    scene = load_scene(write(tmp_path, BASE))
    body, keys = build(scene)
    assert body.modes.n_rigid == 0 and len(body.fixed_vertices) > 0
    assert np.all(body.tets.vertices[body.fixed_vertices, 0] < 0.3)
    assert [k.time for k in keys] == [0.0, 0.4, 0.6, 0.8]

    calls = []
    monkeypatch.setattr(pytetwild, "tetrahedralize", lambda *a, **k: calls.append(1))
    monkeypatch.setattr(tetwild_child, "tetrahedralize_in_child",
                        lambda *a, **k: calls.append(1))
    bad = mutate("groups.three.indices", [5, 3, 99999])
    with pytest.raises(WigglyInputError, match=r"groups.three.indices\[2\] = 99999"):
        build(load_scene(write(tmp_path, bad)))
    assert calls == []  # the surface groups were checked before tetrahedralizing


def test_environment_independent_paths(tmp_path, monkeypatch):
    """Relative paths resolve against the scene file, not the working directory."""
    (tmp_path / "sub").mkdir()
    scene = load_scene(write(tmp_path / "sub", BASE, "s.toml"))
    monkeypatch.chdir(tmp_path)
    assert scene.resolve("out/bar.npz") == tmp_path / "sub" / "out" / "bar.npz"
    assert scene.where() == os.path.join("sub", "s.toml")


def test_a_stiffness_that_explicit_weights_replace_is_warned_about(recwarn):
    """stiffness sets only the weights not given: with c_A beside it on a position key the
    stiffness does nothing there, and the scene says so; alone, nothing is said."""
    base = ('format = 1\n[mesh]\npath = "m.obj"\n[time]\nend = 1.0\n[groups.g]\n'
            'indices = [0]\n[[keyframes]]\ntime = 0.5\ngroup = "g"\nposition = "rest"\n')
    scene_from_dict(tomllib.loads(base + "stiffness = 1e7\n"))
    assert not [w for w in recwarn if "replace" in str(w.message)]
    scene_from_dict(tomllib.loads(base + "stiffness = 1e7\nc_A = 5.0\n"))
    said = [str(w.message) for w in recwarn if "replace" in str(w.message)]
    assert len(said) == 1 and "keyframes[0]: c_A = 5.0 replaces stiffness = 10000000.0" in said[0]


def test_a_material_too_soft_for_the_body_is_noted(tmp_path):
    """Gravity alone bending a held body by more than a fifth of its size is noted, with the
    Young's modulus that sags 5 %. The static sag of the modes is checked against
    the full FEM static solve ``K_ff u_f = -g_f`` (an independent computation): the modes
    hold most of it."""
    import scipy.sparse.linalg as spla

    from wiggly.scene.body_notes import soft_note, static_sag
    from wiggly.scene.build import build_with_groups

    data = {k: v for k, v in BASE.items() if k != "keyframes"}
    data["material"] = {"young": 3e5, "poisson": 0.3, "density": 1000.0}
    scene = load_scene(write(tmp_path, data))
    body, _, _ = build_with_groups(scene)
    sag = static_sag(body)
    free = np.setdiff1d(np.arange(3 * body.tets.n_vertices),
                        (3 * body.fixed_vertices[:, None] + np.arange(3)).ravel())
    u = spla.spsolve(body.K[free][:, free].tocsc(), -body.gravity_vector[free])
    full = float(np.linalg.norm(u.reshape(-1, 3), axis=1).max())
    assert sag == pytest.approx(full, rel=0.1)
    size = float(np.linalg.norm(np.ptp(body.rest_positions(), axis=0)))
    assert sag > 0.2 * size
    said = soft_note(scene, body)
    assert said is not None and "Raise material.young (300000 Pa;" in said
    suggested = float(said.split("Pa;")[1].split("Pa sags")[0])
    assert suggested * 0.05 * size == pytest.approx(3e5 * sag, rel=0.05)  # sag ~ 1 / young
    data["material"]["young"] = suggested
    stiff, _, _ = build_with_groups(load_scene(write(tmp_path, data, "stiff.toml")))
    assert static_sag(stiff) == pytest.approx(0.05 * size, rel=0.1)
    assert soft_note(load_scene(tmp_path / "stiff.toml"), stiff) is None


def test_a_key_turned_by_half_a_turn_or_more_is_warned_about(recwarn):
    """A rigid key's rotation is a placement: 190 degrees is -170 and 360 is no turn, which
    the scene says; under 180 nothing is said."""
    base = ('format = 1\n[mesh]\npath = "m.obj"\n[time]\nend = 1.0\n[groups.g]\n'
            'indices = [0]\n[[keyframes]]\ntime = 0.5\ngroup = "g"\n')
    scene_from_dict(tomllib.loads(base + "position = { rotation = [0.0, 170.0, -90.0] }\n"))
    assert not [w for w in recwarn if "short way" in str(w.message)]
    for turn, wrapped in (("190.0", "-170.0"), ("360.0", "0.0"), ("-540.0", "-180.0")):
        recwarn.clear()
        scene_from_dict(tomllib.loads(base + f"position = {{ rotation = [0.0, {turn}, 0.0] }}\n"))
        said = [str(w.message) for w in recwarn if "short way" in str(w.message)]
        assert len(said) == 1 and f"keyframes[0].position.rotation = [0.0, {turn}, 0.0]" in \
            said[0] and f"(here [0.0, {wrapped}, 0.0])" in said[0], said


def test_a_shot_end_between_frames_is_warned_about(recwarn):
    """An explicit end that is not on the frame grid: the outputs end at the last frame
    before it, which the scene says; on the grid, or an end taken from the keys, nothing."""
    base = 'format = 1\n[mesh]\npath = "m.obj"\n[time]\nstart = 1.0\nfps = 24\n'
    scene_from_dict(tomllib.loads(base + "end = 2.0\n"))
    scene_from_dict(tomllib.loads(
        'format = 1\n[mesh]\npath = "m.obj"\n[time]\nfps = 24\n[groups.g]\nindices = [0]\n'
        '[[keyframes]]\ntime = 1.2311\ngroup = "g"\nposition = "rest"\n'))
    assert not [w for w in recwarn if "whole number of frames" in str(w.message)]
    scene_from_dict(tomllib.loads(base + "end = 2.05\n"))
    said = [str(w.message) for w in recwarn if "whole number of frames" in str(w.message)]
    assert len(said) == 1 and "its last frame is at 2.04167 s" in said[0]
    assert "use end = 2.04167 or 2.08333" in said[0]


def test_an_fps_from_the_command_line_is_checked_for_whole_frames_too(recwarn):
    """``--fps`` (with_overrides) that puts the shot's end between frames says so, as the
    same fps written in the file does, naming the option; a whole number of frames, nothing."""
    from wiggly.scene.run import with_overrides

    scene = scene_from_dict(tomllib.loads(
        'format = 1\n[mesh]\npath = "m.obj"\n[time]\nend = 2.5\nfps = 30\n'))
    with_overrides(scene, fps=24.0)
    assert not [w for w in recwarn if "whole number of frames" in str(w.message)]
    with_overrides(scene, fps=17.0)
    said = [str(w.message) for w in recwarn if "whole number of frames" in str(w.message)]
    assert len(said) == 1 and "at 17 fps (from --fps 17)" in said[0], said
    assert "its last frame is at 2.47059 s" in said[0]


def test_a_mesh_in_centimetres_with_mesh_scale_is_the_same_body(tmp_path, recwarn):
    """``mesh.scale = 0.01`` reads a file in centimetres as metres: the same tet bar written
    in metres and in centimetres gives the same vertices, groups and eigenfrequencies (an
    independent check that the scale is applied before the FEM: frequencies of an elastic
    bar scale as 1 / length), and the centimetre file read without it is warned about with
    the remedy."""
    import warnings

    from wiggly.scene.build import build_with_groups

    V, T = box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    meshio.write(tmp_path / "bar_m.vtu", meshio.Mesh(V, [("tetra", T)]))
    meshio.write(tmp_path / "bar_cm.vtu", meshio.Mesh(100.0 * V, [("tetra", T)]))
    data = {k: v for k, v in BASE.items() if k != "keyframes"}
    metres, _, g1 = build_with_groups(load_scene(write(tmp_path, {
        **data, "mesh": {"path": "bar_m.vtu"}}, "m.toml")))
    scaled, _, g2 = build_with_groups(load_scene(write(tmp_path, {
        **data, "mesh": {"path": "bar_cm.vtu", "scale": 0.01}}, "cm.toml")))
    assert np.allclose(scaled.tets.vertices, metres.tets.vertices, rtol=0, atol=1e-12)
    assert {k: list(v) for k, v in g1.items()} == {k: list(v) for k, v in g2.items()}
    assert np.allclose(scaled.modes.eigenvalues, metres.modes.eigenvalues, rtol=1e-8)
    assert not [w for w in recwarn if "reads its coordinates as metres" in str(w.message)]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        load_model(tmp_path / "bar_cm.vtu")
    said = [str(w.message) for w in seen if "reads its coordinates as metres" in str(w.message)]
    assert len(said) == 1 and "a scene file's mesh.scale" in said[0], said


@pytest.mark.parametrize("value", [0, -0.01, "cm", 1e7])
def test_a_mesh_scale_that_is_no_scale_is_refused(tmp_path, value):
    with pytest.raises(WigglyInputError, match=r"mesh.scale = .* must be a number in \(0, "):
        load_scene(write(tmp_path, mutate("mesh.scale", value)))


def test_a_z_up_mesh_with_mesh_up_axis_is_the_same_body(tmp_path):
    """``mesh.up_axis = "z"`` reads a Z-up file (CAD, 3ds Max, STL) in wiggly's y-up axes:
    the same tet bar written Z-up gives the Y-up file's vertices and eigenvalues; "x" is
    refused by name."""
    from wiggly.scene.build import build_with_groups

    V, T = box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    meshio.write(tmp_path / "bar_y.vtu", meshio.Mesh(V, [("tetra", T)]))
    z_up = np.stack([V[:, 0], -V[:, 2], V[:, 1]], axis=1)  # the same bar, z up
    meshio.write(tmp_path / "bar_z.vtu", meshio.Mesh(z_up, [("tetra", T)]))
    data = {k: v for k, v in BASE.items() if k != "keyframes"}
    upright, _, _ = build_with_groups(load_scene(write(tmp_path, {
        **data, "mesh": {"path": "bar_y.vtu"}}, "y.toml")))
    turned, _, _ = build_with_groups(load_scene(write(tmp_path, {
        **data, "mesh": {"path": "bar_z.vtu", "up_axis": "z"}}, "z.toml")))
    assert np.allclose(turned.tets.vertices, upright.tets.vertices, rtol=0, atol=1e-12)
    assert np.allclose(turned.modes.eigenvalues, upright.modes.eigenvalues, rtol=1e-8)
    with pytest.raises(WigglyInputError, match=r'mesh.up_axis = "x" must be "y" or "z"'):
        load_scene(write(tmp_path, mutate("mesh.up_axis", "x"), "x.toml"))


def _hinged_boxes(folder: Path) -> None:
    """hinged.vtu: two 0.4 m boxes that share only an edge, joined there by one sliver tet;
    free.vtu: the same without the sliver; box.vtu: one of the boxes."""
    V, T = box_mesh((4, 4, 4), (0.4, 0.4, 0.4))
    upper = V + np.array([-0.4, 0.4, 0.0])  # it shares the edge x = 0, y = 0.4
    X = np.vstack([V, upper])
    X, index = np.unique(np.round(X, 9), axis=0, return_inverse=True)
    tets = index.ravel()[np.vstack([T, T + len(V)])]

    def at(p):
        return int(np.argmin(np.linalg.norm(X - p, axis=1)))

    sliver = [at([0, 0.4, 0.1]), at([0, 0.4, 0.2]), at([0.1, 0.4, 0.1]), at([0, 0.5, 0.1])]
    if np.linalg.det(X[sliver[1:]] - X[sliver[0]]) < 0:
        sliver = [sliver[0], sliver[2], sliver[1], sliver[3]]
    meshio.write(folder / "hinged.vtu", meshio.Mesh(X, [("tetra", np.vstack([tets, sliver]))]))
    meshio.write(folder / "free.vtu", meshio.Mesh(X, [("tetra", tets)]))
    meshio.write(folder / "box.vtu", meshio.Mesh(V, [("tetra", T)]))


def test_parts_meeting_at_an_edge_are_said_to_hinge(tmp_path):
    """Two boxes that share only an edge, joined there by one sliver tet (as fTetWild may join
    them): the top box swung tens of metres between keys, said only as a soft-material note;
    the joint is warned about, naming where it is.  Without the sliver the hinge is free, and
    refused (an extra zero-energy mode).  A soft box alone gets no joint warning."""
    from wiggly.scene import run

    _hinged_boxes(tmp_path)
    for name in ("hinged", "free", "box"):
        (tmp_path / f"{name}.toml").write_text(tomli_w.dumps({
            "mesh": {"path": f"{name}.vtu"},
            "simulation": {"modes": 12, "warp": False, "fixed": ["bottom"]},
            "time": {"end": 1.0, "fps": 10},
            "groups": {"bottom": {"box": {"min": [-1, -0.01, -1], "max": [1, 0.05, 1]}}}}))
    with pytest.warns(UserWarning, match=r"the body bends almost freely at a joint near "
                                         r"\(0\.025, 0\.425, 0\.125\) m: 1 of its 769 tets "
                                         r"holds half the elastic energy"):
        run(load_scene(tmp_path / "hinged.toml"), outputs=[])
    with pytest.raises(WigglyInputError, match="parts joined only at a vertex or an edge"):
        run(load_scene(tmp_path / "free.toml"), outputs=[])
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(load_scene(tmp_path / "box.toml"), outputs=[])
    assert not [w for w in said if "joint" in str(w.message)]


def test_a_free_body_whose_parts_meet_at_an_edge_is_said_to_hinge(tmp_path):
    """The same hinged boxes keyed, not held (a review's two cubes sharing an edge folded
    into a V between keys, their softest mode at 0.042 Hz against 9.7 Hz for one cube, with
    no word: the joint check looked only at a held body's sag): the softest mode, far
    softer than the next, holds half its energy in the sliver, and the joint is said.  One
    box keyed the same way is not."""
    from wiggly.scene import run

    _hinged_boxes(tmp_path)
    for name in ("hinged", "box"):
        (tmp_path / f"{name}.toml").write_text(tomli_w.dumps({
            "mesh": {"path": f"{name}.vtu"},
            "simulation": {"modes": 12, "warp": False},
            "time": {"end": 1.0, "fps": 10},
            "groups": {"bottom": {"box": {"min": [-1, -0.01, -1], "max": [1, 0.05, 1]}}},
            "keyframes": [{"time": 0.0, "group": "bottom", "position": "rest"},
                          {"time": 0.5, "group": "bottom",
                           "position": {"offset": [0.05, 0.0, 0.0]}}]}))
    with pytest.warns(UserWarning, match=r"the body bends almost freely at a joint near "
                                         r"\(0\.025, 0\.425, 0\.125\) m: 1 of its 769 tets "
                                         r"holds half the elastic energy of its softest mode"):
        run(load_scene(tmp_path / "hinged.toml"), outputs=[])
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(load_scene(tmp_path / "box.toml"), outputs=[])
    assert not [w for w in said if "joint" in str(w.message)]


def test_a_thin_tail_on_a_held_block_is_no_hinge(tmp_path):
    """A 0.4 m tail of 10 x 10 cm, joined by its whole end face to a held 0.6 m block, sags
    (soft): it holds half its elastic energy near its root, in under 2 % of all the tets but
    far more of those that move, and is said to be soft, not to hinge (a Blender reviewer's
    creature was told to join its parts by a face, which they were)."""
    from wiggly.scene import run

    block, Tb = box_mesh((12, 6, 6), (0.6, 0.3, 0.3))
    tail, Tt = box_mesh((8, 2, 2), (0.4, 0.1, 0.1))
    X = np.vstack([block, tail + np.array([0.6, 0.1, 0.1])])
    X, index = np.unique(np.round(X, 9), axis=0, return_inverse=True)
    tets = index.ravel()[np.vstack([Tb, Tt + len(block)])]
    meshio.write(tmp_path / "tailed.vtu", meshio.Mesh(X, [("tetra", tets)]))
    (tmp_path / "tailed.toml").write_text(tomli_w.dumps({
        "mesh": {"path": "tailed.vtu"}, "material": {"young": 200.0},
        "simulation": {"modes": 12, "warp": False, "fixed": ["block"]},
        "time": {"end": 1.0, "fps": 10},
        "groups": {"block": {"box": {"min": [-1, -1, -1], "max": [0.6001, 1, 1]}}}}))
    scene = load_scene(tmp_path / "tailed.toml")
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run(scene, outputs=[])
    assert not [w for w in said if "joint" in str(w.message)], [str(w.message) for w in said]


def test_a_missed_offset_key_of_a_linear_shot_is_not_blamed_on_turns(tmp_path):
    """A plain offset key missed in a linear shot was told that "a linear solve cannot meet
    turned targets" (a numerics review): that hint is for keys that turn their group."""
    from wiggly.scene import run

    V, T = box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    meshio.write(tmp_path / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    base = {"mesh": {"path": "bar.vtu"}, "simulation": {"modes": 10, "warp": False},
            "time": {"end": 1.0},
            "groups": {"tip": {"box": {"min": [0.9, -1, -1], "max": [2, 1, 1]}}}}
    for name, position, turned in (("offset", {"offset": [0.0, 0.3, 0.0]}, False),
                                   ("turn", {"rotation": [0.0, 0.0, 60.0]}, True)):
        data = {**base, "keyframes": [{"time": 0.5, "group": "tip", "position": position,
                                       "stiffness": 1e-4}]}
        (tmp_path / f"{name}.toml").write_text(tomli_w.dumps(data))
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            run(load_scene(tmp_path / f"{name}.toml"), outputs=[])
        missed = [str(w.message) for w in said if "missed by more than" in str(w.message)]
        assert len(missed) == 1, [str(w.message) for w in said]
        assert ("cannot meet turned targets" in missed[0]) == turned, missed


def test_a_surface_too_coarse_to_show_the_bending_is_warned_about(tmp_path):
    """A soft bar of 12 triangles held at one end sags under its weight: its 1 m edges
    stay straight while the tets bend (a review's low-poly plant stalk was drawn straight
    and a leaf parted from it, with no warning), so the gap at an edge's middle is said;
    the same bar subdivided to the tets' size follows them, silently."""
    import trimesh

    from wiggly.scene import load_scene, run
    from wiggly.solve.surface import straight_edges

    box = trimesh.creation.box(extents=(1.0, 0.1, 0.1))
    box.apply_translation((0.5, 0.0, 0.0))
    trimesh.Trimesh(box.vertices, box.faces).export(tmp_path / "coarse.obj")
    V, F = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.03)
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "fine.obj")
    data = {"mesh": {"path": "coarse.obj", "resolution": 20},
            "material": {"young": 3e4, "density": 1000.0},
            "simulation": {"modes": 12, "warp": False, "fixed": ["root"]},
            "time": {"end": 1.0, "fps": 10},
            "groups": {"root": {"box": {"min": [-1, -1, -1], "max": [0.05, 1, 1]}}}}
    scene = load_scene(write(tmp_path, data, "coarse.toml"))
    with pytest.warns(UserWarning, match=r"coarse\.toml: the solid bends under \d+ of the "
                                         r"surface's \d+ long edges .* off the solid it rests "
                                         r"on"):
        anim = run(scene, outputs=[])
    worst = straight_edges(anim, anim.frame_times(10))
    assert worst["gap"] > 0.01 and worst["longest"] == pytest.approx(np.sqrt(1.01), rel=1e-6)
    data["mesh"]["path"] = "fine.obj"
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        fine = run(load_scene(write(tmp_path, data, "fine.toml")), outputs=[])
    assert not any("long edges" in str(w.message) for w in said), [str(w.message) for w in said]
    sag = np.abs(fine.positions([1.0])[0][:, 1] - V[:, 1]).max()
    assert sag > 10 * 0.01 * np.sqrt(1.02)  # it bends: the check has something to see


def test_two_keys_of_a_group_at_one_time_that_disagree_are_said(tmp_path):
    """Two keys of one group at one time with other targets cannot both be met (a review
    keyed a box's top 5 cm left and 5 cm right at 0.5 s and was told only that the keys
    were missed, and to raise their stiffness): the scene says so when it is read; the same
    key twice, or keys of other groups or times, are not."""
    import copy

    data = copy.deepcopy(BASE)
    data["keyframes"].append({"time": 0.4, "group": "tip",
                              "position": {"offset": [0.0, -0.1, 0.0]}})
    with pytest.warns(UserWarning, match=r"shot\.toml: keyframes\[1\] and keyframes\[4\] both "
                                         r"key group 'tip' at t = 0\.4 s, with another "
                                         r"position: both cannot be met"):
        load_scene(write(tmp_path, data))
    data["keyframes"][4]["position"] = {"offset": [0.0, 0.1, 0.0]}
    data["keyframes"].append({"time": 0.4, "group": "mid", "position": "rest"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scene(write(tmp_path, data, "same.toml"))


def test_a_missed_keys_stiffness_advice_starts_from_the_stiffness_in_use(tmp_path):
    """A key on a stiff clamped bar missed at stiffness 1e9: the advice names 1e9 as the
    stiffness now and suggests more (a review was told "e.g. 1e9" at 1e9); at the default it
    names the default."""
    from wiggly.scene import run as run_scene

    for stiffness, advice in ((None, "the default is 1e6; e.g. 1e+09"),
                              (1e9, "now 1e+09; e.g. 1e+12")):
        key = {"time": 0.5, "group": "tip", "position": {"offset": [0.0, 0.03, 0.0]}}
        if stiffness is not None:
            key["stiffness"] = stiffness
        data = {"mesh": {"path": "builtin:bar", "resolution": 6},
                "material": {"young": 2e11, "density": 7800.0},
                "simulation": {"gravity": [0.0, 0.0, 0.0], "modes": 8, "fixed": ["left"],
                               "warp": False},
                "time": {"end": 1.0, "fps": 10},
                "groups": BASE["groups"], "keyframes": [key]}
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            run_scene(load_scene(write(tmp_path, data)), outputs=[])
        texts = [str(w.message) for w in said if "raise their stiffness" in str(w.message)]
        assert len(texts) == 1 and f"raise their stiffness ({advice})" in texts[0], texts


def test_paths_through_a_parent_folder_are_said_tidily(tmp_path):
    """``mesh.path = "../meshes/x.ply"`` names ``meshes/x.ply`` in messages, not
    ``scenes/../meshes/x.ply``; a path through a symbolic link keeps its ``..``."""
    (tmp_path / "scenes").mkdir()
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "x.ply").write_text("ply\n")
    scene = Scene(MeshSpec("../meshes/x.ply"))
    scene.source = tmp_path / "scenes" / "shot.toml"
    assert scene.mesh_file() == tmp_path / "meshes" / "x.ply"
    assert scene.resolve("../meshes/missing.ply") == tmp_path / "meshes" / "missing.ply"
    (tmp_path / "deep" / "er").mkdir(parents=True)
    (tmp_path / "scenes" / "link").symlink_to(tmp_path / "deep" / "er")
    (tmp_path / "deep" / "y.ply").write_text("ply\n")  # link/.. is deep/, not scenes/
    assert scene.resolve("link/../y.ply") == tmp_path / "scenes" / "link" / ".." / "y.ply"
    assert scene.resolve("link/../y.ply").is_file()


def test_a_long_index_group_is_written_in_a_few_lines():
    """A group of 200 indices (a brush selection) is written packed, not one index per line
    (a review's two groups took 258 lines, hard to read in a diff), and reads back equal."""
    from wiggly.scene.spec import Indices

    scene = Scene(MeshSpec("builtin:bar"),
                  groups={"g": GroupSpec(Indices(tuple(range(0, 600, 3))))})
    text = scene_to_toml(scene)
    start = text.index("indices = [")
    block = text[start:text.index("]", start) + 1].splitlines()
    assert len(block) <= 14 and max(map(len, block)) <= 100, block  # 11 of numbers
    assert tomllib.loads(text)["groups"]["g"]["indices"] == list(range(0, 600, 3))
