"""Sweep files: every validation error names the file, key and value; expansion into shots
(grid order, random draws within bounds and reproducible, parameters applied to the scene)."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import tomli_w

from wiggly import WigglyInputError
from wiggly.batch import load_sweep, sweep_schema
from wiggly.batch.shots import collect
from wiggly.scene import Offset, Rest, Rigid, load_scene

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "sweeps" / "jump_sweep.toml"
SCHEMA_FILE = ROOT / "src" / "wiggly" / "data" / "sweep.schema.json"

# The bundled bar, fixed at x = 0: its tip keyed at rest, pulled up, turned.
SCENE = {
    "mesh": {"path": "builtin:bar", "resolution": 6},
    "simulation": {"modes": 8, "fixed": ["left"]},
    "time": {"end": 1.0, "fps": 10},
    "groups": {
        "left": {"box": {"min": [-0.01, -1.0, -1.0], "max": [0.01, 1.0, 1.0]}},
        "tip": {"sphere": {"center": [1.0, 0.0, 0.0], "radius": 0.06}},
    },
    "keyframes": [
        {"time": 0.0, "group": "tip", "position": "rest", "velocity": [0.0, 0.0, 0.0]},
        {"time": 0.5, "group": "tip", "position": {"offset": [0.0, 0.1, 0.0]},
         "name": "pulled"},
        {"time": 0.8, "group": "tip", "position": {"rotation": [0.0, 0.0, 10.0]},
         "name": "turned"},
        {"time": 0.9, "group": "tip", "position": "rest", "name": "turned"},
    ],
    "output": {"paths": ["out/bar.npz"]},
}
SWEEP = {
    "base": "shot.toml",
    "seed": 3,
    "samples": 2,
    "grid": {"damping.alpha": [0.5, 2.0], "material.young": [1e5, 2e5, 4e5]},
    "random": {"keyframes[pulled].position.offset[1]": {"uniform": [0.05, 0.15]}},
    "output": {"paths": ["bar.npz"]},
}


def write(directory: Path, sweep: dict, scene: dict | None = None) -> Path:
    (directory / "shot.toml").write_text(tomli_w.dumps(scene or SCENE))
    path = directory / "sweep.toml"
    path.write_text(tomli_w.dumps(sweep))
    return path


def with_(**changes) -> dict:
    d = json.loads(json.dumps(SWEEP))
    for key, value in changes.items():
        table, _, name = key.partition("__")
        if name:
            d.setdefault(table, {})[name.replace("_DOT_", ".")] = value
        elif value is None:
            d.pop(table, None)
        else:
            d[table] = value
    return d


# ----------------------------------------------------------------------------------------------
# expansion


def test_grid_and_samples(tmp_path):
    sweep = load_sweep(write(tmp_path, SWEEP))
    assert len(sweep) == 2 * 3 * 2 and sweep.n_grid == 6
    values = [sweep.values(i) for i in range(len(sweep))]
    # grid-point order: the last key fastest; samples one after the other
    assert [v["damping.alpha"] for _, v in values[:6]] == [0.5, 0.5, 0.5, 2.0, 2.0, 2.0]
    assert [v["material.young"] for _, v in values[:6]] == [1e5, 2e5, 4e5] * 2
    assert [s for s, _ in values] == [0] * 6 + [1] * 6
    draws = [v["keyframes[pulled].position.offset[1]"] for _, v in values]
    assert all(0.05 <= d <= 0.15 for d in draws)
    # one draw per sample, shared by its grid points; samples differ
    assert len(set(draws[:6])) == 1 and len(set(draws[6:])) == 1 and draws[0] != draws[6]


def test_parameters_reach_the_scene(tmp_path):
    sweep = load_sweep(write(tmp_path, SWEEP))
    _, values = sweep.values(7)
    scene = sweep.scene(values, "test")
    assert scene.damping.alpha == values["damping.alpha"]
    assert scene.material.young == values["material.young"]
    y = values["keyframes[pulled].position.offset[1]"]
    assert scene.keyframes[1].position == Offset((0.0, y, 0.0))  # only y changes
    assert scene.keyframes[0].position == Rest() and scene.source == (tmp_path / "shot.toml")


def test_draws_are_reproducible_and_independent(tmp_path):
    a = load_sweep(write(tmp_path, SWEEP))
    again = load_sweep(tmp_path / "sweep.toml")
    assert [a.values(i) for i in range(12)] == [again.values(i) for i in range(12)]
    more = with_(samples=5, random={**SWEEP["random"],
                                    "keyframes[0].velocity[0]": {"uniform": [0.0, 1.0]}})
    b = load_sweep(write(tmp_path, more))
    key = "keyframes[pulled].position.offset[1]"
    # more samples and another parameter leave the earlier shots' draws as they were
    assert [b.values(i)[1][key] for i in range(12)] == [a.values(i)[1][key] for i in range(12)]
    c = load_sweep(write(tmp_path, with_(seed=4)))
    assert c.values(0)[1][key] != a.values(0)[1][key]


@pytest.mark.parametrize("dist, check", [
    ({"uniform": [[0.0, 0.0, -0.1], [0.2, 0.0, 0.1]]},
     lambda v: 0 <= v[0] <= 0.2 and v[1] == 0 and -0.1 <= v[2] <= 0.1),
    ({"log_uniform": [[1e-3, 1e-3, 1e-3], [1e-1, 1e-1, 1e-1]]},
     lambda v: all(1e-3 <= x <= 1e-1 for x in v)),
    ({"choice": [[0.0, 0.1, 0.0], [0.0, 0.2, 0.0]]}, lambda v: v in ([0, 0.1, 0], [0, 0.2, 0])),
])
def test_distributions(tmp_path, dist, check):
    sweep = load_sweep(write(tmp_path, with_(grid=None, samples=200,
                                             random={"keyframes[1].position.offset": dist})))
    draws = [sweep.values(i)[1]["keyframes[1].position.offset"] for i in range(len(sweep))]
    assert all(check(v) for v in draws)
    spread = np.ptp(np.asarray(draws, dtype=float), axis=0)
    assert spread.max() > 0  # they vary
    if "log_uniform" in dist:  # uniform in log: the median near the geometric mean
        assert np.median(np.log10([v[0] for v in draws])) == pytest.approx(-2, abs=0.25)


def test_integers_and_choice_of_tables(tmp_path):
    random = {"simulation.modes": {"integers": [8, 10]},
              "keyframes[1].position": {"choice": ["rest", {"offset": [0, 0.2, 0]}]}}
    sweep = load_sweep(write(tmp_path, with_(grid=None, samples=60, random=random)))
    shots, _ = collect([sweep])
    modes = {s.scene.simulation.modes for s in shots}
    kinds = {type(s.scene.keyframes[1].position) for s in shots}
    assert modes == {8, 9, 10} and kinds == {Rest, Offset}


def test_replacing_keys(tmp_path):
    grid = {"time.duration": [2.0],                          # replaces time.end
            "mesh.edge_length": [0.05],                       # replaces mesh.resolution
            "keyframes[0].position.offset": [[0, 0.05, 0]],   # "rest" becomes an offset
            "keyframes[2].position.rotation[2]": [45.0],      # one angle of a rigid target
            "groups.tip.box": [{"min": [0.9, -1, -1], "max": [1.1, 1, 1]}]}  # new selector
    sweep = load_sweep(write(tmp_path, with_(grid=grid, random=None, samples=None)))
    scene = sweep.scene(sweep.values(0)[1], "test")
    assert scene.time_range() == (0.0, 2.0) and scene.time.end is None
    assert scene.mesh.edge_length == 0.05 and scene.mesh.resolution is None
    assert scene.keyframes[0].position == Offset((0.0, 0.05, 0.0))
    assert scene.keyframes[2].position == Rigid(rotation=(0.0, 0.0, 45.0))
    assert scene.groups["tip"].selector.min == (0.9, -1.0, -1.0)


def test_invalid_combination_fails_its_shot_only(tmp_path):
    grid = {"time.end": [1.0, 0.7]}  # a keyframe at 0.9 s lies outside a 0.7 s shot
    sweep = load_sweep(write(tmp_path, with_(grid=grid, random=None, samples=None)))
    shots, _ = collect([sweep])
    assert shots[0].scene is not None and shots[0].error is None
    assert shots[1].scene is None
    assert "keyframes[2].time = 0.8 is outside the shot's time range [0.0, 0.7] s" in \
        shots[1].error and 'time.end = 0.7' in shots[1].error


def test_example_sweep(tmp_path):
    sweep = load_sweep(EXAMPLE)
    shots, _ = collect([sweep])
    assert len(shots) == len(sweep) >= 8
    assert all(s.scene is not None for s in shots), [s.error for s in shots if s.error]
    assert sweep.base == load_scene(ROOT / "examples" / "jump.toml")
    assert sweep.out_dir.resolve() == (ROOT / "examples" / "out" / "jump_sweep").resolve()
    jsonschema.Draft202012Validator(sweep_schema()).validate(tomllib.loads(EXAMPLE.read_text()))


def test_schema_file_is_current():
    assert json.loads(SCHEMA_FILE.read_text()) == sweep_schema(), (
        "src/wiggly/data/sweep.schema.json is stale; regenerate it with "
        "`wiggly batch --schema > src/wiggly/data/sweep.schema.json`")
    jsonschema.Draft202012Validator.check_schema(sweep_schema())


# ----------------------------------------------------------------------------------------------
# validation: one message per problem, naming the file, the key and the value


ERRORS = [
    (with_(grd={}), "unknown key 'grd' at the top level; did you mean 'grid'?"),
    (with_(base=None), "base is missing; it is required"),
    (with_(base="nope.toml"), 'base = "nope.toml": no such scene file'),
    (with_(samples=0), "samples = 0 must be an integer in [1, 100000]"),
    (with_(samples=None), "samples is missing; a sweep with [random] draws samples shots"),
    (with_(random=None), "samples = 2 would repeat identical shots"),
    (with_(seed=-1), "seed = -1 must be an integer >= 0"),
    (with_(format=2), "format = 2 must be 1 (the newest sweep format this wiggly reads)"),
    (with_(grid__material_DOT_yuong=[1.0]),
     "grid.\"material.yuong\": unknown key 'yuong' in [material]; did you mean 'young'?"),
    (with_(grid__material_DOT_poisson=[0.3, 0.6]),
     'grid."material.poisson"[1] = 0.6 must be a number in [0, 0.5)'),
    (with_(grid__material_DOT_young=[]), 'grid."material.young" = [] must have at least 1 item'),
    (with_(grid__material_DOT_young=2e5), 'grid."material.young" = 200000.0 must be an array'),
    (with_(grid__output_DOT_fps=[1]), 'grid."output.fps": [output] cannot be varied'),
    (with_(grid__keyframes_DOT_pulled=[1]), "keyframes is an array; pick a keyframe by index"),
    (with_(grid={"material.young.x": [1]}), "material.young takes no key 'x'; vary it whole"),
    (with_(grid={"keyframes[7].time": [0.1]}), "the base scene has 4 keyframes"),
    (with_(grid={"keyframes[jump].time": [0.1]}), "'jump' is not a keyframe name; keyframe "
                                                  "names are: pulled, turned"),
    (with_(grid={"keyframes[turned].time": [0.1]}), "'turned' names 2 keyframes (2, 3); use an "
                                                    "index"),
    (with_(grid={"keyframes[2].position.offset": [[0, 1, 0]]}),
     'grid."keyframes[2].position.offset": keyframes[2].position is a rigid target in the base '
     "scene"),
    (with_(grid={"keyframes[1].position.offset[3]": [1.0]}),
     "keyframes[1].position.offset has 3 components; index them [0] .. [2]"),
    (with_(grid={"keyframes[1].velocity[0]": [1.0]}),
     "keyframes[1].velocity is not set in the base scene; vary the whole vector"),
    (with_(grid={"keyframes[1].time": ["soon"]}),
     'grid."keyframes[1].time"[0] = "soon" must be a number (s)'),
    (with_(grid={"groups.tip.box.min": [[0, 0, 0]]}),
     "groups.tip has a sphere selector in the base scene, not box"),
    (with_(grid={"groups.head.sphere.radius": [0.1]}), "the base scene has no groups 'head'"),
    (with_(grid={"simulation.gravity[1]": [-9.81]},
           random={"simulation.gravity[1]": {"uniform": [-10, -1]}}),
     'random."simulation.gravity[1]" is also in [grid]'),
    (with_(grid=None, random={"material.young": {"uniform": [2e5, 1e5]}}),
     'random."material.young".uniform = [200000.0, 100000.0]: low exceeds high'),
    (with_(grid=None, random={"material.young": {"uniform": [-1.0, 1e5]}}),
     'random."material.young".uniform[0] = -1.0 must be a number in [0.001, 1e+13] (Pa)'),
    (with_(grid=None, random={"damping.alpha": {"log_uniform": [0.0, 1.0]}}),
     "log_uniform needs low > 0"),
    (with_(random={"simulation.modes": {"uniform": [8, 12]}}),
     "simulation.modes is an integer in [1, 500]; use integers = [low, high]"),
    (with_(grid=None, random={"material.young": {"integers": [1, 5]}}),
     "use uniform or log_uniform"),
    (with_(random={"simulation.warp": {"uniform": [0, 1]}}),
     "simulation.warp is true or false, not a number or vector; draw it with choice"),
    (with_(grid=None, random={"material.young": {"uniform": [1, 2], "choice": [1]}}),
     'random."material.young" has 2 distributions (uniform, choice); give exactly one'),
    (with_(grid=None, random={"material.young": {"normal": [1, 2]}}),
     "unknown key 'normal' in [random.\"material.young\"]; did you mean 'uniform'?"),
    (with_(output={"paths": ["out/a.glb"]}), 'output.paths[0] = "out/a.glb" must be a file '
                                             "name, without folders"),
    (with_(output={"paths": ["thumb.png"]}), "is a name the batch uses itself"),
    (with_(output={"paths": ["a.mov"]}), 'output.paths[0] = "a.mov" must be a file name '
                                         "ending in .glb"),
    (with_(grid={}, random=None, samples=None), "the sweep varies nothing: give the "
                                                "parameters to vary in [grid]"),
    (with_(output={"dir": "shot.toml"}), 'output.dir = "shot.toml": '),
    (with_(grid__material_DOT_young=[1e5, 2e5, 1e5]),
     'grid."material.young"[2] = 100000.0 repeats grid."material.young"[0]: it would make '
     "identical shots"),
    (with_(grid={"material.young": [float(k) for k in range(1, 401)]}, samples=300),
     "the sweep makes 120000 shots (400 grid points x 300 samples), more than 100000"),
]


@pytest.mark.parametrize("data, message", ERRORS, ids=[m[:40] for _, m in ERRORS])
def test_validation_errors(tmp_path, data, message):
    path = write(tmp_path, data)
    with pytest.raises(WigglyInputError) as err:
        load_sweep(path)
    lines = str(err.value).splitlines()
    assert any(line.startswith(f"{path}: ") and message in line for line in lines), lines


def test_all_problems_at_once_and_base_errors(tmp_path):
    data = with_(grid={"material.young": [-1.0], "damping.beta": [-2.0]},
                 random={"time.end": {"uniform": [0.5, "x"]}})
    with pytest.raises(WigglyInputError) as err:
        load_sweep(write(tmp_path, data))
    assert len(str(err.value).splitlines()) == 3
    bad_scene = {**SCENE, "material": {"yuong": 1.0}}
    with pytest.raises(WigglyInputError) as err:  # with the sweep's own problems
        load_sweep(write(tmp_path, with_(seed=-1), bad_scene))
    text = str(err.value)
    assert "sweep.toml: seed = -1 must be an integer >= 0" in text
    assert 'sweep.toml: base = "shot.toml": the base scene is not valid' in text
    assert "shot.toml: unknown key 'yuong' in [material]; did you mean 'young'?" in text
    inner = write(tmp_path, with_())  # a sweep whose base is that sweep file
    (tmp_path / "outer.toml").write_text(tomli_w.dumps(with_(base=inner.name)))
    with pytest.raises(WigglyInputError) as err:
        load_sweep(tmp_path / "outer.toml")
    assert str(err.value).splitlines() == [
        f'{tmp_path / "outer.toml"}: base = "sweep.toml" is a sweep file; a sweep\'s base is a '
        "scene file (give that sweep's own base, and its [grid] and [random] here)"]


def test_documented_sweep(tmp_path):
    """The sweep of docs/sweep-format.md is valid against examples/jump.toml."""
    import re
    import shutil

    text = (ROOT / "docs" / "sweep-format.md").read_text()
    block = re.findall(r"```toml\n(.*?)```", text, re.S)[0]
    (tmp_path / "sweeps").mkdir()
    shutil.copy(ROOT / "examples" / "jump.toml", tmp_path / "jump.toml")
    (tmp_path / "sweeps" / "doc.toml").write_text(block)
    sweep = load_sweep(tmp_path / "sweeps" / "doc.toml")
    assert len(sweep) == 4 * 3 * 2 * 2 and sweep.name == "jump"
    shots, _ = collect([sweep])
    assert all(s.scene is not None for s in shots), [s.error for s in shots if s.error]
    assert all(s.outputs == ("jump.glb", "jump.gif") for s in shots)
    assert {s.scene.simulation.modes for s in shots} <= set(range(20, 41))


def test_replaced_keys_leave_vectors_alone(tmp_path):
    """``time.end`` drops ``time.duration`` from [time]; a vector component drops nothing."""
    scene = {**SCENE, "time": {"duration": 1.0, "fps": 10}}
    grid = {"time.end": [1.0], "simulation.gravity[1]": [-1.62]}
    sweep = load_sweep(write(tmp_path, with_(grid=grid, random=None, samples=None), scene))
    s = sweep.scene(sweep.values(0)[1], "test")
    assert s.time.end == 1.0 and s.time.duration is None
    assert s.simulation.gravity == (0.0, -1.62, 0.0)
