"""``wiggly batch`` on local worker processes: shots solved on a shared body agree with
solving each scene alone, failures stay isolated, runs resume, folders are whole."""

from __future__ import annotations

import copy
import csv
import fcntl
import json
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import tomli_w
from PIL import Image

from wiggly import WigglyInputError
from wiggly.batch import run
from wiggly.batch.shots import body_scene
from wiggly.batch.worker import BodyJob, ShotJob, prepare_body, run_shot
from wiggly.cli import main
from wiggly.export import read_animation
from wiggly.files import default_cache_dir
from wiggly.scene import load_scene
from wiggly.scene import run as run_scene

# The bundled bar, fixed at x = 0, its tip pulled up at 0.5 s and released.
# Stiff enough (static sag under gravity 3 % of its length) that a shot has one minimum near
# its path: with the default 2e5 Pa the bar would sag by 1.7 m, and on some fTetWild meshes a
# warm-started shot then ended in another local minimum than the same shot solved cold (8.5 cm
# away), which is the nonconvex objective's, not the warm start's doing.
SCENE = {
    "mesh": {"path": "builtin:bar", "resolution": 6},
    "material": {"young": 1e7},
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
    ],
    "output": {"paths": ["out/bar.npz"]},
}
# Two damping values x two random pulls: four shots of one body.
SWEEP = {
    "base": "shot.toml", "samples": 2, "seed": 1,
    "grid": {"damping.alpha": [0.5, 4.0]},
    "random": {"keyframes[pulled].position.offset[1]": {"uniform": [0.05, 0.15]}},
    "output": {"paths": ["bar.npz"]},
}


def write_sweep(directory: Path, sweep: dict = SWEEP, scene: dict = SCENE) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "shot.toml").write_text(tomli_w.dumps(scene))
    path = directory / "sweep.toml"
    path.write_text(tomli_w.dumps(sweep))
    return path


def solved_alone(folder: Path):
    """The shot's saved scene solved by itself (``wiggly animate``'s path, a cold solve)."""
    return run_scene(load_scene(folder / "scene.toml"), outputs=[])


def check_shot_against_alone(out: Path, record: dict) -> np.ndarray:
    """The shot's written motion equals its scene solved alone (to within the warped solve's
    tolerance); returns the motion."""
    folder = out / record["folder"]
    written = read_animation(folder / "bar.npz")
    alone = solved_alone(folder)
    expected = alone.positions(written.times)
    assert np.abs(written.positions - expected).max() < 1e-3  # m, on a 1 m bar
    worst = max(r["position_rms"] for r in alone.constraint_residuals())
    assert record["keyframe_position_rms"] == pytest.approx(worst, rel=0.05, abs=1e-5)
    return written.positions


def test_sweep_on_worker_processes(tmp_path, monkeypatch):
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))  # nothing prepared yet
    out = tmp_path / "out"
    records = run(write_sweep(tmp_path), out, workers=2)
    assert [r["shot"] for r in records] == [f"sweep-{i:04d}" for i in range(4)]
    assert [r["status"] for r in records] == ["done"] * 4, [r["error"] for r in records]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["shots"] == json.loads(json.dumps(records))
    # one body, prepared once, shared by shots that differ in damping and keyframe targets
    assert len(summary["bodies"]) == 1 and summary["bodies"][0]["cached"] is False
    assert summary["bodies"][0]["shots"] == 4 and len({r["body"] for r in records}) == 1
    assert len({r["worker"] for r in records}) <= 2
    for r in records:
        assert sorted(p.name for p in (out / r["folder"]).iterdir()) == \
            ["bar.npz", "result.json", "scene.toml", "thumb.png"]
        assert r["iterations"] >= 1 and r["converged"] and r["solve_seconds"] > 0
    assert not (out / ".staging").exists()
    # each shot is its own scene solved alone; the two dampings give different motions
    motions = {r["parameters"]["damping.alpha"]: check_shot_against_alone(out, r)
               for r in records[:2]}
    assert np.abs(motions[0.5] - motions[4.0]).max() > 10e-3
    # the summary table: a row per shot with the sweep's parameters
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["shot"] for r in rows] == [r["shot"] for r in records]
    for row, r in zip(rows, records, strict=True):
        key = "keyframes[pulled].position.offset[1]"
        assert float(row[key]) == r["parameters"][key]
        assert float(row["damping.alpha"]) == r["parameters"]["damping.alpha"]
        assert row["outputs"] == json.dumps([f"{r['shot']}/bar.npz"])
    # contact sheets: one tile per shot
    with Image.open(out / "contact-sheet.png") as sheet:
        assert sheet.size == (4 * 240 + 5 * 6, 180 + 34 + 2 * 6)
    page = (out / "contact-sheet.html").read_text()
    assert all(f'src="{r["thumbnail"]}"' in page for r in records)
    # a batch without sheets leaves none of an earlier one to contradict its summary
    run(write_sweep(tmp_path), out, contact_sheet=False)
    assert not (out / "contact-sheet.html").exists() and not (out / "contact-sheet.png").exists()


def test_obj_sequence_listed_by_its_frame_files(tmp_path, monkeypatch, caplog):
    """A shot's OBJ sequence is named by the files it wrote, in the records and the contact
    sheet's links (``bar.obj`` itself does not exist); the log's counts add up."""
    import wiggly.progress

    sweep = {"base": "shot.toml", "grid": {"damping.alpha": [0.5]},
             "output": {"paths": ["bar.obj"]}}
    out = tmp_path / "out"
    monkeypatch.setattr(wiggly.progress, "NOTE_EVERY", 0.0)  # log every count
    with caplog.at_level("INFO", logger="wiggly"):
        (record,) = run(write_sweep(tmp_path, sweep), out, workers=1)
    counts = [m for m in caplog.messages if m.startswith("batch: 1 of 1 shot so far")]
    assert counts and counts[0].startswith("batch: 1 of 1 shot so far, done 1, failed 0, "
                                           "running 0"), \
        caplog.messages
    assert record["status"] == "done", record["error"]
    frames = [f"sweep-0000/bar_{k:04d}.obj" for k in range(11)]  # 1 s at 10 fps
    assert record["outputs"] == frames and all((out / f).is_file() for f in frames)
    page = (out / "contact-sheet.html").read_text()
    assert '<a href="sweep-0000/bar_0000.obj">bar.obj, 11 frames</a>' in page


def test_shared_body_warm_starts_damping_and_gravity(tmp_path):
    """One worker, one body, four problems (damping x gravity), two random pulls each: the
    second shot of each problem starts from the first's solution, and every shot equals its
    scene solved alone from scratch."""
    sweep = {**SWEEP, "grid": {"damping.alpha": [0.5, 4.0], "simulation.gravity[1]": [-9.81,
                                                                                      -2.0]}}
    out = tmp_path / "out"
    records = run(write_sweep(tmp_path, sweep), out, workers=1, contact_sheet=False)
    assert [r["status"] for r in records] == ["done"] * 8, [r["error"] for r in records]
    assert [r["warm_start"] for r in records] == [False] * 4 + [True] * 4
    motions = {(r["parameters"]["damping.alpha"], r["parameters"]["simulation.gravity"][1],
                r["sample"]): check_shot_against_alone(out, r) for r in records}
    assert np.abs(motions[0.5, -9.81, 0] - motions[0.5, -2.0, 0]).max() > 10e-3


def test_resume_and_changed_shots(tmp_path):
    out = tmp_path / "out"
    sweep = write_sweep(tmp_path)
    first = run(sweep, out, workers=2, contact_sheet=False)
    stamps = {r["shot"]: (out / r["shot"] / "result.json").stat().st_mtime_ns for r in first}
    again = run(sweep, out, contact_sheet=False)  # nothing to do: no worker starts
    assert all(r["resumed"] for r in again)
    driver = ("resumed", "commit_seconds")  # the driver's own, not in the shot's folder
    assert [{k: v for k, v in r.items() if k not in driver} for r in again] == \
        [{k: v for k, v in r.items() if k not in driver} for r in first]
    assert json.loads((out / "summary.json").read_text())["backend"].startswith("none")
    # more samples: the four shots done are kept, two new ones run
    more = write_sweep(tmp_path, {**SWEEP, "samples": 3})
    records = run(more, out, workers=1, contact_sheet=False)
    assert [r["resumed"] for r in records] == [True] * 4 + [False] * 2
    assert all((out / s / "result.json").stat().st_mtime_ns == t for s, t in stamps.items())
    # a changed parameter: refused without overwrite, nothing touched; replaced with it
    changed = write_sweep(tmp_path, {**SWEEP, "grid": {"damping.alpha": [0.5, 2.0]}})
    with pytest.raises(WigglyInputError, match=r"holds 2 shot folders of other shots "
                                               r"\(sweep-0001, sweep-0003\).*--overwrite"):
        run(changed, out, contact_sheet=False)
    assert all((out / s / "result.json").stat().st_mtime_ns == t for s, t in stamps.items())
    records = run(changed, out, workers=2, contact_sheet=False, overwrite=True)
    assert [r["resumed"] for r in records] == [True, False, True, False]
    assert [r["parameters"]["damping.alpha"] for r in records] == [0.5, 2.0] * 2


def test_a_rerun_redoes_broken_shots_and_never_deletes_a_users_files(tmp_path):
    """A shot done before whose output was deleted or rewritten runs again; a folder where a
    shot goes that wiggly did not write, or a shot folder holding a user's file, is refused
    even with overwrite, and nothing of it is touched."""
    out = tmp_path / "out"
    sweep = write_sweep(tmp_path, {**SWEEP, "samples": 1})
    run(sweep, out, workers=1, contact_sheet=False)
    (out / "sweep-0000" / "bar.npz").unlink()
    (out / "sweep-0001" / "bar.npz").write_bytes(b"not what wiggly wrote")
    records = run(sweep, out, workers=1, contact_sheet=False)
    assert [r["resumed"] for r in records] == [False, False]
    assert read_animation(out / "sweep-0001" / "bar.npz").n_frames == 11
    # a stranger's folder where a new shot goes
    (out / "sweep-0002").mkdir()
    (out / "sweep-0002" / "keep.txt").write_text("mine")
    grown = write_sweep(tmp_path, {**SWEEP, "samples": 2})
    for overwrite in (False, True):
        with pytest.raises(WigglyInputError, match=r"1 folder where shots go that wiggly did "
                                                   r"not write \(sweep-0002: no result.json\)"):
            run(grown, out, contact_sheet=False, overwrite=overwrite)
    assert (out / "sweep-0002" / "keep.txt").read_text() == "mine"
    (out / "sweep-0002" / "keep.txt").unlink()
    (out / "sweep-0002").rmdir()
    # a note in a shot folder that a changed sweep would replace
    (out / "sweep-0001" / "notes.txt").write_text("take 2 looks best")
    changed = write_sweep(tmp_path, {**SWEEP, "samples": 1, "grid": {"damping.alpha": [0.5, 2]}})
    with pytest.raises(WigglyInputError, match=r"hold files wiggly did not write "
                                               r"\(sweep-0001 \(notes.txt\)\)"):
        run(changed, out, contact_sheet=False, overwrite=True)
    assert (out / "sweep-0001" / "notes.txt").read_text() == "take 2 looks best"


def test_failures_are_isolated(tmp_path, capsys):
    shots = tmp_path / "shots"
    shots.mkdir()
    scenes = {
        "good": SCENE,
        "typo": {**SCENE, "material": {"yuong": 1.0}},  # invalid: found before any work
        "nogroup": {**SCENE, "groups": {**SCENE["groups"], "tip": {
            "sphere": {"center": [5.0, 0.0, 0.0], "radius": 0.01}}}},  # fails in its worker
        "toomany": {**SCENE, "simulation": {"modes": 500, "fixed": ["left"]}},  # its body fails
        "badout": {**SCENE, "output": {"paths": ["bar.glb"], "gltf_targets": "modes"}},
    }
    for name, data in scenes.items():
        (shots / f"{name}.toml").write_text(tomli_w.dumps(data))
    (shots / "broken.toml").write_text("[mesh\n")
    out = tmp_path / "out"
    files = sorted(shots.glob("*.toml"))
    code = main(["batch", *map(str, files), "-o", str(out), "-j", "2", "--no-sheet"])
    stdout, stderr = capsys.readouterr()
    assert code == 1
    assert "6 shots: 1 done, 5 failed" in stdout
    errors = {
        "broken": "broken.toml: not valid TOML",
        "typo": "typo.toml: unknown key 'yuong' in [material]; did you mean 'young'?",
        "nogroup": "nogroup.toml: groups.tip (sphere) selects no vertex of the surface",
        "toomany": "its body could not be prepared: ",
        "badout": 'output.gltf_targets = "modes" needs a linear shot',
    }
    rows = {r["shot"]: r for r in csv.DictReader((out / "summary.csv").open())}
    assert rows["good"]["status"] == "done"
    for name, message in errors.items():
        assert rows[name]["status"] == "failed" and message in rows[name]["error"], rows[name]
        assert f"  {name}: " in stdout and not (out / name).exists()
    assert "simulation.modes = 500 is more than the" in rows["toomany"]["error"]
    assert "Traceback" not in stdout + stderr
    # the progress bar counted them
    assert "[wiggly] batch" in stderr and "failed 5" in stderr and "running" in stderr
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == \
        ["good", "summary.csv", "summary.json"]
    assert read_animation(out / "good" / "bar.npz").n_frames == 11


def test_folder_is_checked_first(tmp_path, capsys):
    sweep = write_sweep(tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    code = main(["batch", str(sweep), "-o", str(mine), "-q"])
    assert code == 1 and "is not empty and holds no batch" in capsys.readouterr().err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    out = tmp_path / "out"
    out.mkdir()
    (out / ".wiggly-batch").write_text("x\n")
    with open(out / ".wiggly-batch.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        with pytest.raises(WigglyInputError, match="another wiggly batch is writing into"):
            run(sweep, out)
    code = main(["batch", str(sweep), str(tmp_path / "missing.toml"), "-o", str(out),
                 "--dry-run"])
    assert code == 1 and "missing.toml: no such file" in capsys.readouterr().out
    nowhere = tmp_path / "nowhere"
    code = main(["batch", str(tmp_path / "missing.toml"), "-o", str(nowhere)])
    assert code == 2 and "no such file" in capsys.readouterr().err
    assert not nowhere.exists()  # a lone typo makes no output folder


def test_dry_run_and_schema(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))
    sweep, folder = write_sweep(tmp_path), tmp_path / "batch"
    code = main(["batch", str(sweep), "-o", str(folder), "--dry-run"])
    out = capsys.readouterr().out
    assert code == 0 and out.count("sweep-000") == 4
    assert out.endswith(f"4 shots into {folder}\n"), out
    assert "damping.alpha = 4.0" in out
    # what a run would find in the batch's folder: a shot done, another one, a stranger
    other = {**SWEEP, "samples": 1, "grid": {"damping.alpha": [0.5, 2.0]}}
    run(write_sweep(tmp_path / "earlier", other), folder, contact_sheet=False)
    (folder / "sweep-0003").mkdir()
    assert main(["batch", str(sweep), "-o", str(folder), "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("[done in an earlier run]") and not lines[2].endswith("]"), lines
    assert lines[1].endswith("[its folder holds another shot: replaced only with "
                             "--overwrite]"), lines
    assert lines[3].endswith("holds no shot (no result.json): refused]"), lines
    assert lines[4].endswith("4 shots into " + str(folder) + ", 1 done in an earlier run")
    assert main(["batch", "--schema"]) == 0
    assert json.loads(capsys.readouterr().out)["title"] == "wiggly sweep"
    assert main(["batch"]) == 2
    assert main(["batch", "x.toml", "-j", "0"]) == 2
    bad = write_sweep(tmp_path, {**SWEEP, "grid": {"damping.alfa": [1.0]}})
    assert main(["batch", str(bad), "-q"]) == 1
    err = capsys.readouterr().err
    assert "sweep.toml: grid.\"damping.alfa\": unknown key 'alfa' in [damping]; did you mean " \
           "'alpha'?" in err


def test_shot_files_come_back_when_the_worker_cannot_see_the_folder(tmp_path):
    """A Ray worker on another machine returns the files' bytes; nothing stays behind."""
    scene = load_scene(write_sweep(tmp_path).parent / "shot.toml")
    body = BodyJob("k", body_scene(scene), target=str(tmp_path / "body.pickle"))
    assert prepare_body(body)["status"] == "done"
    staging = tmp_path / "staging"
    job = ShotJob("s", scene, "k", ("bar.npz",), str(staging), str(tmp_path / "no-marker"),
                  "token", thumbnail=False)
    from wiggly.batch.worker import load_pickled, pickled_identity

    record = run_shot(job, load_pickled(body.target), pickled_identity(body.target))
    assert record["status"] == "done" and set(record["files"]) == {"bar.npz"}
    assert not staging.exists()
    path = tmp_path / "bar.npz"
    path.write_bytes(record["files"]["bar.npz"])
    assert read_animation(path).n_frames == 11


def test_a_worker_tells_two_preparations_of_one_body_apart(tmp_path):
    """Two bodies prepared under one content key (fTetWild is not reproducible: two cache
    directories hold two tet meshes) are two bodies to a worker: each shot runs on the body it
    was given, never on one the worker kept from before."""
    from wiggly.batch.worker import load_pickled, pickled_identity

    scene = load_scene(write_sweep(tmp_path).parent / "shot.toml")
    stiff = copy.deepcopy(SCENE)
    stiff["material"] = {"young": 8e5}
    (tmp_path / "stiff.toml").write_text(tomli_w.dumps(stiff))
    motions = []
    for name, source in (("soft", scene), ("stiff", load_scene(tmp_path / "stiff.toml"))):
        body = BodyJob("one key", body_scene(source), target=str(tmp_path / f"{name}.pickle"))
        assert prepare_body(body)["status"] == "done"
        job = ShotJob(name, scene, "one key", ("bar.npz",), str(tmp_path / name),
                      str(tmp_path / "no-marker"), "token", thumbnail=False)
        record = run_shot(job, load_pickled(body.target), pickled_identity(body.target))
        assert record["status"] == "done", record["error"]
        (tmp_path / f"{name}.npz").write_bytes(record["files"]["bar.npz"])
        motions.append(read_animation(tmp_path / f"{name}.npz").positions)
    assert np.abs(motions[0] - motions[1]).max() > 0.01  # the stiff bar bends less


def test_workers_use_the_callers_cache_directory(tmp_path, monkeypatch):
    """Local workers are forked from a server process started once (its environment is that
    of its start): a batch run with another $WIGGLY_CACHE_DIR still prepares its body (tet mesh
    and modes) in that directory."""
    for name in ("first", "second"):
        cache = tmp_path / f"{name}-cache"
        monkeypatch.setenv("WIGGLY_CACHE_DIR", str(cache))
        sweep = write_sweep(tmp_path / name, {**SWEEP, "samples": 1,
                                              "grid": {"damping.alpha": [1.0]}})
        records = run(sweep, tmp_path / name / "out", workers=1, contact_sheet=False)
        assert [r["status"] for r in records] == ["done"], records
        assert len(list((cache / "tets").glob("*.npz"))) == 1, name
        assert len(list((cache / "batch" / "bodies").glob("*.pickle"))) == 1, name


class InProcessPool:
    """A stand-in for the local pool that runs its tasks in this process when waited for;
    ``hook(names in flight)`` plays a worker's death or a Ctrl-C."""

    kind = "local"
    slots = 2
    hook = staticmethod(lambda names: None)
    seen: ClassVar[list] = []

    def __init__(self, workers, render_checked):
        self.tasks, self.broken = {}, False
        self.bodies = default_cache_dir() / "test-bodies"

    def describe(self):
        return "in-process test pool"

    def cached_body(self, key):
        return None

    def keep_warnings(self, key, messages):
        pass

    def kept_warnings(self, key):
        return []

    def body_job(self, key, scene, mesh_file):
        return BodyJob(key, scene, target=str(self.bodies / f"{key}.pickle"))

    def prepare(self, job):
        self.tasks[h := object()] = job
        return h

    def prepared(self, job, handle, result):
        return result, job.target

    def shot(self, job, source):
        self.tasks[h := object()] = (job, source)
        return h

    def wait(self, handles, timeout):
        self.seen.append(len(handles))
        names = [getattr(self.tasks[h], "key", None) or self.tasks[h][0].name for h in handles]
        self.broken = bool(self.hook(names))
        return list(handles)

    def outcome(self, handle):
        from wiggly.batch.backends import WorkerDied
        from wiggly.batch.worker import load_pickled, pickled_identity

        task = self.tasks.pop(handle)
        if self.broken:
            raise WorkerDied("killed")
        if isinstance(task, BodyJob):
            return prepare_body(task)
        job, source = task
        return run_shot(job, load_pickled(source), pickled_identity(source))

    def restart(self):
        self.seen.append("restart")

    def close(self, cancel=False):
        pass


def test_a_dying_worker_fails_its_shot_only(tmp_path, monkeypatch):
    """A worker that dies (a crash, out of memory) breaks the local pool: the shots in flight
    run again one at a time, so only the one that dies again fails."""
    import wiggly.batch.driver as driver

    seen = []  # "sweep-0001" takes the whole pool down whenever it runs
    monkeypatch.setattr(InProcessPool, "seen", seen)
    monkeypatch.setattr(InProcessPool, "hook", staticmethod(lambda n: "sweep-0001" in n))
    monkeypatch.setattr(driver, "LocalPool", InProcessPool)
    records = run(write_sweep(tmp_path), tmp_path / "out", contact_sheet=False)
    assert [r["status"] for r in records] == ["done", "failed", "done", "done"]
    assert "the worker process died while running it (killed)" in records[1]["error"]
    assert seen.count("restart") == 2, seen
    first = seen.index("restart")  # after a crash with two in flight: each alone
    assert seen[first - 1] == 2 and seen[first + 1:first + 4] == [1, "restart", 1], seen


@pytest.mark.parametrize("stop", [KeyboardInterrupt, SystemExit(143)], ids=["ctrl-c", "sigterm"])
def test_an_interrupted_batch_leaves_whole_folders(tmp_path, monkeypatch, stop):
    """Ctrl-C, or SIGTERM (a farm's scheduler, ``timeout``: an exit with 143): the shots done
    keep their folders, the summary says which did not run, nothing is half-written; the
    next run does the rest. (SIGTERM's summary left out the shots not run.)"""
    import wiggly.batch.driver as driver

    waits = []

    def interrupt(names):
        waits.append(names)
        if len(waits) == 3:  # the body, two shots, then Ctrl-C
            raise stop

    monkeypatch.setattr(InProcessPool, "hook", staticmethod(interrupt))
    monkeypatch.setattr(driver, "LocalPool", InProcessPool)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt if stop is KeyboardInterrupt else SystemExit):
        run(write_sweep(tmp_path), out, contact_sheet=False)
    records = json.loads((out / "summary.json").read_text())["shots"]
    assert [r["status"] for r in records] == ["done", "not run", "done", "not run"]
    assert sorted(p.name for p in out.iterdir()) == \
        [".wiggly-batch", "summary.csv", "summary.json", "sweep-0000", "sweep-0002"]
    monkeypatch.setattr(InProcessPool, "hook", staticmethod(lambda names: None))
    records = run(write_sweep(tmp_path), out, contact_sheet=False)
    assert [r["resumed"] for r in records] == [True, False, True, False]


def test_a_second_ctrl_c_does_not_cut_the_summary_short(tmp_path, monkeypatch):
    """Ctrl+C twice (the second while the workers are closed): the summary still lists every
    shot, the ones not run marked, and Ctrl+C works again afterwards (the second one cut the
    cleanup short, and no summary was written)."""
    import os
    import signal

    import wiggly.batch.driver as driver

    waits = []

    def interrupt(names):
        waits.append(names)
        if len(waits) == 3:
            raise KeyboardInterrupt

    def close_again(self, cancel=False):  # the second Ctrl+C, while the workers close
        os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(InProcessPool, "hook", staticmethod(interrupt))
    monkeypatch.setattr(InProcessPool, "close", close_again)
    monkeypatch.setattr(driver, "LocalPool", InProcessPool)
    out = tmp_path / "out"
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        run(write_sweep(tmp_path), out, contact_sheet=False)
    records = json.loads((out / "summary.json").read_text())["shots"]
    assert [r["status"] for r in records] == ["done", "not run", "done", "not run"]
    assert signal.getsignal(signal.SIGINT) is before


def test_scene_files_of_the_same_name(tmp_path):
    from wiggly.batch.shots import collect

    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "shot.toml").write_text(tomli_w.dumps(copy.deepcopy(SCENE)))
    shots, _ = collect([tmp_path / "a" / "shot.toml", tmp_path / "b" / "shot.toml"])
    assert [s.name for s in shots] == ["shot", "b-shot"]  # a file added later renames none
    assert shots[0].outputs == ("bar.npz",)
    with pytest.warns(UserWarning, match=r"shot\.toml is given more than once; it runs once"):
        shots, _ = collect([tmp_path / "a" / "shot.toml", tmp_path / "a" / "shot.toml"])
    assert [s.name for s in shots] == ["shot"]
    scene = load_scene(tmp_path / "a" / "shot.toml")  # Scene objects, and --write
    shots, _ = collect([scene, scene], write=["x.glb", "x.gif"])
    assert [s.name for s in shots] == ["shot", "a-shot"]
    assert all(s.scene == scene and s.outputs == ("x.glb", "x.gif") for s in shots)
    with pytest.raises(WigglyInputError, match=r"--write: 'out/x\.glb' has folders"):
        collect([scene], write=["out/x.glb"])


def test_a_shot_done_keeps_its_folder_when_a_twin_is_given_before_it(tmp_path):
    """b/shot.toml runs alone (folder shot); then a/shot.toml and b/shot.toml together: the
    new a/shot takes another name and b/shot resumes from its folder (before, a/shot took
    the name, and the batch stopped saying that the folder's scene had changed)."""
    for d, alpha in (("a", 0.5), ("b", 2.0)):
        (tmp_path / d).mkdir()
        data = copy.deepcopy(SCENE)
        data["damping"] = {"alpha": alpha}
        (tmp_path / d / "shot.toml").write_text(tomli_w.dumps(data))
    out = tmp_path / "out"
    first = run([tmp_path / "b" / "shot.toml"], out, contact_sheet=False)
    assert [r["shot"] for r in first] == ["shot"]
    both = run([tmp_path / "a" / "shot.toml", tmp_path / "b" / "shot.toml"], out,
               contact_sheet=False)
    by_name = {r["shot"]: r for r in both}
    assert set(by_name) == {"shot", "shot-2"}, by_name
    assert by_name["shot"]["resumed"] and not by_name["shot-2"].get("resumed")
    assert load_scene(out / "shot-2" / "scene.toml").damping.alpha == 0.5  # a's, new
    assert load_scene(out / "shot" / "scene.toml").damping.alpha == 2.0  # b's, kept


def test_shots_run_again_for_their_thumbnails_say_so(tmp_path, monkeypatch, caplog):
    """A batch without sheets, then with them: the shots done run again to render their
    thumbnails (their files are written again), and the log says so (it was silent)."""
    import logging

    import wiggly.batch.driver as driver

    monkeypatch.setattr(driver, "LocalPool", InProcessPool)
    out = tmp_path / "out"
    run(write_sweep(tmp_path), out, contact_sheet=False)
    with caplog.at_level(logging.INFO, logger="wiggly"):
        records = run(write_sweep(tmp_path), out)
    assert not any(r.get("resumed") for r in records)
    said = [r.getMessage() for r in caplog.records if "for the thumbnail" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("4 shots done before"), said


def test_an_unreadable_prepared_body_is_prepared_again(tmp_path, monkeypatch):
    """A prepared body that does not load (another wiggly wrote it) costs a preparation,
    not the batch."""
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))
    sweep = write_sweep(tmp_path, {**SWEEP, "samples": 1, "grid": {"damping.alpha": [0.5]}})
    first = run(sweep, tmp_path / "a", workers=1, contact_sheet=False)
    (pickle,) = (tmp_path / "cache" / "batch" / "bodies").glob("*.pickle")
    pickle.write_bytes(b"not a pickle")
    again = run(sweep, tmp_path / "b", workers=1, contact_sheet=False)
    assert again[0]["status"] == "done" and again[0]["body"] == first[0]["body"]
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["bodies"][0]["cached"] is True and pickle.read_bytes() != b"not a pickle"


def test_a_script_without_a_main_guard_is_told_how_to_fix_it(tmp_path):
    """Local workers import the calling script first (forkserver); one that starts a batch at
    import would start it again in every worker, which then dies.  The caller hears that,
    with the fix, instead of "out of memory"; the worker says why it stopped."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    script = tmp_path / "sweep_script.py"
    script.write_text("import wiggly.batch\n"
                      f"wiggly.batch.run([{str(root / 'examples' / 'jump.toml')!r}], "
                      f"{str(tmp_path / 'out')!r}, workers=1)\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path)
    assert done.returncode != 0
    last = done.stderr.strip().splitlines()[-1]
    assert "worker processes could not start" in last and str(script) in last, last
    assert 'if __name__ == "__main__":' in last and "memory" not in last
    assert "called while a worker process imported the script" in done.stderr


def test_a_driven_shot_reports_how_closely_it_followed(tmp_path, monkeypatch):
    """A batch of a [drive] scene: summary.csv gives drive_max and drive_rms, the same
    figures as following() on the same scene run alone."""
    import meshio

    import wiggly.batch.driver as driver
    from wiggly.drive import following
    from wiggly.export import SurfaceAnimation, write_animation
    from wiggly.mesh import TetMesh
    from wiggly.primitives import box_mesh

    V, T = box_mesh((8, 2, 2), (0.8, 0.1, 0.1))
    meshio.write(tmp_path / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    times = np.arange(11) / 10.0
    sway = np.array([V + np.array([0.0, 0.05 * np.sin(2 * np.pi * t), 0.0]) for t in times])
    write_animation(tmp_path / "sway.npz",
                    SurfaceAnimation(times, sway, TetMesh(V, T).boundary_faces()))
    scene = {"mesh": {"path": "bar.vtu"}, "material": {"young": 5e4},
             "simulation": {"modes": 12}, "time": {"end": 1.0, "fps": 10},
             "groups": {"driven": {"box": {"min": [-1, -1, -1], "max": [0.3, 1, 1]}}},
             "drive": {"path": "sway.npz", "group": "driven"}}
    (tmp_path / "shot.toml").write_text(tomli_w.dumps(scene))
    monkeypatch.setattr(driver, "LocalPool", InProcessPool)
    records = run([tmp_path / "shot.toml"], tmp_path / "out", contact_sheet=False)
    assert records[0]["status"] == "done", records[0].get("error")
    with open(tmp_path / "out" / "summary.csv", newline="") as f:
        row = next(csv.DictReader(f))
    alone = following(run_scene(load_scene(tmp_path / "shot.toml"), outputs=[]))
    assert float(row["drive_max"]) == pytest.approx(alone["max"], rel=1e-6, abs=1e-12)
    assert float(row["drive_rms"]) == pytest.approx(alone["rms"], rel=1e-6, abs=1e-12)


def test_contact_sheet_captions_wrap_instead_of_cutting_values():
    """A tile's caption gives every varied value whole, wrapped to the tile's width; a value
    that cuts at 48 characters ("offset[1]=-0.") is not."""
    from PIL import ImageFont

    from wiggly.batch.summary import CAPTION_LINES, _caption_lines
    from wiggly.batch.worker import THUMBNAIL_SIZE

    font = ImageFont.load_default(size=11)
    width = THUMBNAIL_SIZE[0] - 4
    p = {"simulation.gravity": [0.0, -1.62, 0.0], "material.young": 150000.0,
         "keyframes[crouch].position.offset[1]": -0.1234}
    lines = _caption_lines(p, list(p), font, width)
    text = ", ".join(lines)
    assert "offset[1]=-0.1234" in text and "gravity=" in text and "young=" in text
    assert all(font.getlength(line) <= width for line in lines)
    many = {f"k{i}": 1000.0 + i for i in range(60)}
    assert len(_caption_lines(many, list(many), font, width)) == CAPTION_LINES


def _descendants(pid: int) -> set[int]:
    """Live processes below ``pid`` (from /proc)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if fields[0] != "Z":  # zombies are already gone
            parents[int(entry.name)] = int(fields[1])
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        children = {c for c, pp in parents.items() if pp == p}
        todo += sorted(children - found)
        found |= children
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")
def test_workers_end_with_a_batch_killed_outright(tmp_path):
    """SIGKILL of the batch's process (an out-of-memory kill, kill -9) cannot stop its
    workers: they notice their parent is gone and exit within seconds instead of finishing
    their shots, holding their memory."""
    import os
    import signal
    import subprocess
    import sys
    import time

    sweep = write_sweep(tmp_path, {**SWEEP, "grid": {"damping.alpha": [0.5, 1.0, 2.0, 4.0]}})
    script = tmp_path / "batch_script.py"
    script.write_text("import wiggly.batch\n"
                      'if __name__ == "__main__":\n'
                      f"    wiggly.batch.run([{str(sweep)!r}], {str(tmp_path / 'out')!r}, "
                      "workers=2)\n")
    driver = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        workers: set[int] = set()
        while time.monotonic() < deadline and not (tmp_path / "out" / ".staging").is_dir():
            time.sleep(0.1)  # until a shot runs (its staging folder)
        workers = _descendants(driver.pid)
        assert len(workers) >= 3, workers  # the fork server and two workers
    finally:
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(Path(f"/proc/{w}").exists() and
                                              "Z" not in _state(w) for w in workers):
        time.sleep(0.2)
    left = [w for w in workers if Path(f"/proc/{w}").exists() and "Z" not in _state(w)]
    for w in left:  # do not leave them to the next tests
        os.kill(w, signal.SIGKILL)
    assert not left, f"{len(left)} worker processes outlived the batch"


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"


def test_a_shot_keeps_what_wiggly_animate_would_warn_about(tmp_path, monkeypatch, recwarn):
    """The checks of a solved motion (keys missed, folds) and the scene's own warnings reach
    each shot's record, its summary row and the contact sheet, named by the sweep's shot, as
    ``wiggly animate`` of the shot's scene says them; a clean shot has none."""
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))
    scene = copy.deepcopy(SCENE)
    scene["time"]["end"] = 1.05  # not a whole number of frames at 10 fps: the scene's warning
    sweep = {"base": "shot.toml", "grid": {"keyframes[pulled].stiffness": [1e6, 1e-3]},
             "output": {"paths": ["bar.npz"]}}
    out = tmp_path / "out"
    records = run(write_sweep(tmp_path, sweep, scene), out, workers=1)
    assert [r["status"] for r in records] == ["done"] * 2, [r["error"] for r in records]
    kept, soft = records
    assert all("not a whole number of frames" in " ".join(r["warnings"]) for r in records)
    missed = [w for w in soft["warnings"] if "missed by more than" in w]
    assert missed and "sweep.toml shot 1: 1 keyframe missed" in missed[0], soft["warnings"]
    assert not [w for w in kept["warnings"] if "missed by more than" in w], kept["warnings"]
    alone = recwarn_messages(recwarn, lambda: solved_alone(out / soft["folder"]))
    assert any("missed by more than" in w for w in alone)  # what wiggly animate says
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [int(r["warnings"]) for r in rows] == [len(r["warnings"]) for r in records]
    page = (out / "contact-sheet.html").read_text()
    assert page.count('<details class="warn">') == 2 and "missed by more than" in page


def recwarn_messages(recwarn, call) -> list[str]:
    recwarn.clear()
    call()
    return [str(w.message) for w in recwarn]


def test_a_cache_or_disk_that_cannot_be_written_is_not_called_a_bug(tmp_path, monkeypatch):
    """An unwritable cache directory is refused before any worker starts, naming the folder
    and WIGGLY_CACHE_DIR; a full disk during a shot is the machine's failure, not a bug."""
    import errno

    from wiggly.batch.worker import _failure

    blocker = tmp_path / "cache"
    blocker.write_text("a file where the cache directory should be")
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(blocker))
    with pytest.raises(WigglyInputError, match=r"cache directory.*cannot be written.*set "
                                               r"WIGGLY_CACHE_DIR to a folder that can"):
        run(write_sweep(tmp_path / "sweep"), tmp_path / "out", workers=1)
    said = _failure(OSError(errno.ENOSPC, "No space left on device"))["error"]
    assert "the disk is full" in said and "bug" not in said, said
