"""What ``wiggly batch`` tells the person at the console: mesh warnings as ``wiggly animate``
shows them, mistakes in a mesh named with the scene file and its key, a Ray address that is
never a sweep file, and a folder left with no lock file after a clean run."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import tomli_w
import trimesh

from wiggly.batch import run
from wiggly.batch.driver import LOCK
from wiggly.cli import build_parser, main

# A free body made of two overlapping unit cubes (its surface has triangles that cross), its
# far corner pulled at 0.5 s: a linear shot, so the test needs no compiled kernels.
CUBES = {
    "mesh": {"path": "cubes.off", "resolution": 5},
    "simulation": {"modes": 10, "warp": False},
    "time": {"end": 1.0, "fps": 10},
    "groups": {
        "base": {"box": {"min": [-0.1, -0.1, -0.1], "max": [1.1, 0.1, 1.1]}},
        "corner": {"sphere": {"center": [1.5, 1.5, 1.5], "radius": 0.3}},
    },
    "keyframes": [
        {"time": 0.0, "group": "base", "position": "rest", "velocity": [0.0, 0.0, 0.0]},
        {"time": 0.5, "group": "corner", "position": {"offset": [0.0, 0.1, 0.0]}},
        {"time": 1.0, "group": "base", "position": "rest"},
    ],
    "output": {"paths": ["cubes.npz"]},
}


def two_overlapping_cubes() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    V = np.asarray(box.vertices) + 0.5
    F = np.asarray(box.faces)
    return np.vstack([V, V + 0.5]), np.vstack([F, F + len(V)])


def write_scene(folder: Path, data: dict = CUBES, name: str = "cubes.toml") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(tomli_w.dumps(data))
    return path


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    """An empty cache of tet meshes, modes and prepared bodies, so the body is prepared."""
    directory = tmp_path / "cache"
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(directory))
    return directory


def test_a_mesh_warning_reaches_the_console(tmp_path, cache, capsys):
    V, F = two_overlapping_cubes()
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "cubes.off")
    scene = write_scene(tmp_path)
    code = main(["batch", str(scene), "-o", str(tmp_path / "out"), "-j", "1", "--no-sheet"])
    out, err = capsys.readouterr()
    assert code == 0, out + err
    assert "Traceback" not in out + err
    warning = [line for line in err.splitlines() if "pairs of triangles that cross" in line]
    assert len(warning) == 1, err  # once, as `wiggly animate` says it
    assert warning[0].startswith("wiggly: warning: ") and "cubes.off" in warning[0]
    # and so does the second run, which finds the body prepared in the cache
    code = main(["batch", str(scene), "-o", str(tmp_path / "again"), "-j", "1", "--no-sheet"])
    out, err = capsys.readouterr()
    assert code == 0 and err.count("pairs of triangles that cross") == 1, err


def test_a_corrupt_mesh_names_the_scene_file_and_its_key(tmp_path, cache, capsys):
    (tmp_path / "cubes.off").write_text("OFF\n8 12 0\n0 0 0\nnot a number\n")
    scene = write_scene(tmp_path)
    code = main(["batch", str(scene), "-o", str(tmp_path / "out"), "-j", "1", "--no-sheet"])
    out, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in out + err
    failed = [line for line in out.splitlines() if line.strip().startswith("cubes:")]
    assert failed, out
    assert "cubes.toml" in failed[0] and 'mesh.path = "cubes.off"' in failed[0], failed[0]


def test_the_lock_file_is_removed_after_a_clean_run(tmp_path, cache):
    V, F = two_overlapping_cubes()
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "cubes.off")
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="pairs of triangles that cross"):
        records = run(write_scene(tmp_path), out, workers=1, contact_sheet=False)
    assert [r["status"] for r in records] == ["done"]
    assert not (out / LOCK).exists()
    assert sorted(p.name for p in out.iterdir()) == [".wiggly-batch", "cubes", "summary.csv",
                                                      "summary.json"]


@pytest.mark.parametrize(("argv", "ray", "address"), [
    (["--ray", "sweep.toml"], True, None),
    (["sweep.toml", "--ray"], True, None),
    (["--ray", "--ray-address", "10.0.0.2:6379", "sweep.toml"], True, "10.0.0.2:6379"),
    (["--ray-address", "auto", "sweep.toml"], False, "auto"),
    (["sweep.toml"], False, None),
])
def test_ray_takes_no_value_and_the_address_has_its_own_option(argv, ray, address):
    args = build_parser().parse_args(["batch", *argv])
    assert args.inputs == ["sweep.toml"]
    assert args.ray is ray and args.ray_address == address


def test_stage_lines_in_a_log_and_no_progress_bar(tmp_path, cache, capsys, caplog):
    """Off a terminal a batch writes one line per shot and the counts, never a bar's
    carriage-return updates."""
    V, F = two_overlapping_cubes()
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "cubes.off")
    scene = write_scene(tmp_path)
    with caplog.at_level(logging.INFO, logger="wiggly"):
        code = main(["batch", str(scene), "-o", str(tmp_path / "out"), "-j", "1", "--no-sheet"])
    _, err = capsys.readouterr()
    assert code == 0
    assert "\r" not in err
    assert "[wiggly] cubes done (1 of 1)" in err
    assert "[wiggly] batch: 1 of 1 shot, done 1, failed 0, running 0" in err


def test_an_unreachable_ray_cluster_is_said_in_wiggly_terms(monkeypatch):
    """Ray's own message speaks of its --address flag and RAY_ADDRESS: the error adds how to
    start or name a cluster in wiggly's options."""
    ray = pytest.importorskip("ray")
    from wiggly.batch.backends import RayCluster
    from wiggly.errors import WigglyInputError

    def refuse(**_):
        raise ConnectionError("Could not find any running Ray instance. Please specify the one "
                              "to connect to by setting `--address` flag")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", refuse)
    with pytest.raises(WigglyInputError, match=r"--ray-address auto: cannot start or reach a "
                                               r"Ray cluster \(Could not find.*\); start one on "
                                               r"this machine with `ray start --head`"):
        RayCluster("auto", render_checked=True)


def test_console_mistakes_and_an_interruption_are_said_plainly(tmp_path, cache, capsys):
    """A folder given as input, --write none beside file names: usage errors naming what to
    give; an interrupted batch says what is done and that the same command runs the rest
    (from its own summary, never an earlier batch's)."""
    import json
    import os
    import time

    from wiggly.cli.batch import interrupted

    scene = write_scene(tmp_path / "shots")
    assert main(["batch", str(tmp_path / "shots")]) == 2
    err = capsys.readouterr().err
    assert "shots: is a folder; give the scene files in it" in err and "*.toml" in err, err
    assert main(["batch", str(scene), "--write", "a.npz", "--write", "none"]) == 2
    assert "--write none (no outputs, only the summary) cannot go with other names (a.npz)" \
        in capsys.readouterr().err
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").write_text(json.dumps(
        {"totals": {"shots": 12, "done": 2, "not_run": 10}}))
    said = interrupted(out, time.time() - 60)
    assert "2 of 12 shots done, 10 not run" in said and "the same command runs the rest" in said
    os.utime(out / "summary.json", (0, 0))  # an earlier batch's summary: not its counts
    said = interrupted(out, time.time() - 60)
    assert "of 12" not in said and "the same command runs the rest" in said


def test_a_sweeps_output_dir_beside_other_inputs_is_said_to_be_unused(tmp_path, capsys,
                                                                    monkeypatch):
    """A sweep's [output] dir applies when it is the only input; beside a scene file the
    batch goes to ./wiggly-batch, which used to happen without a word."""
    monkeypatch.chdir(tmp_path)
    scene = write_scene(tmp_path)
    (tmp_path / "cubes.off").write_text("OFF\n0 0 0\n")
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(tomli_w.dumps({"base": "cubes.toml", "grid": {"damping.alpha": [0.5, 1.0]},
                                    "output": {"dir": "sweep_out"}}))
    assert main(["batch", str(sweep), str(scene), "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert "sweep.toml: a sweep's [output] dir applies when the sweep is the only input; " \
           "with 2 inputs the batch goes to wiggly-batch" in err, err
    assert main(["batch", str(sweep), "--dry-run"]) == 0
    assert "only input" not in capsys.readouterr().err
