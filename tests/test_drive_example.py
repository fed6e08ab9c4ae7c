"""examples/walk_secondary.toml and walk_cycle.toml as shipped: their driver is what
scripts/make_walk_driver.py makes, a valid, periodic skinned glTF of the critter's own
surface; the driven vertices follow it to within 1 mm; the free tail and ears swing during
the walk and meet their keys; the cycle loops without a seam while the tail swings."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from tests.test_export import gltf_validator  # noqa: F401  (a fixture)
from wiggly.drive import read_driver
from wiggly.mesh import load_mesh, resolve_builtin
from wiggly.scene import load_scene, run

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "examples" / "walk_secondary.toml"
CYCLE = ROOT / "examples" / "walk_cycle.toml"
DRIVER = ROOT / "examples" / "critter_walk.glb"


def test_driver_is_what_the_script_makes(tmp_path):
    spec = importlib.util.spec_from_file_location("make_walk_driver",
                                                  ROOT / "scripts" / "make_walk_driver.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.build(tmp_path / "walk.glb").read_bytes() == DRIVER.read_bytes()


def test_driver_is_a_valid_periodic_walk_of_the_critter(gltf_validator):  # noqa: F811
    report = gltf_validator([DRIVER])[0]
    # no warnings either (joint slots of zero weight named other joints: 7123 of them)
    assert report["issues"]["numErrors"] == report["issues"]["numWarnings"] == 0, \
        report["issues"]
    d = read_driver(DRIVER, animation="walk")
    critter = load_mesh(resolve_builtin("builtin:critter"))
    d.check(critter.n_vertices, critter.faces, "critter.obj")
    assert d.kind == "glTF skin" and d.n_frames == 61 and d.span == (0.0, 2.0)
    P, h = d.positions, d.times[1] - d.times[0]
    np.testing.assert_allclose(P[0], critter.vertices, atol=1e-6)  # starts at rest
    for a, b in ((0, 30), (0, 60)):  # one cycle is 1 s: positions and velocities repeat
        np.testing.assert_allclose(P[b], P[a], atol=1e-6)
        np.testing.assert_allclose((P[b + 1 if b < 60 else 1] - P[b]) / h,
                                   (P[a + 1] - P[a]) / h, atol=1e-4)
    assert np.linalg.norm(P - P[0], axis=2).max() > 0.15  # the feet travel


@pytest.fixture(scope="module")
def walk():
    scene = load_scene(SCENE)
    return scene, run(scene, outputs=[])


def test_driven_vertices_follow_within_a_millimetre(walk):
    _, anim = walk
    report = anim.info["drive"]
    assert report["frames"] == 61
    assert report["max"] < 1e-3, report


def offsets(anim, driver, part, times):
    """Distance (F, s) of a free part's vertices from where the driver puts them."""
    v = anim.info["scene"]["groups"][part]
    k = np.clip(np.searchsorted(driver.times, times - 1e-9), 0, driver.n_frames - 1)
    return np.linalg.norm(anim.positions(times)[:, v] - driver.positions[k][:, v], axis=2)


def test_free_parts_swing_during_the_walk_and_meet_their_keys(walk):
    """While the critter trots (0.25-2 s) the tail and the ears move on their own, relative to
    where the driver carries them (the tail by centimetres: the full-space reference of
    benchmarks/bench_secondary.py gives the same motion); the sparse keys on the free parts
    bring them back in place, still (ears at 3 s, tail at 3.5 s)."""
    _, anim = walk
    driver = read_driver(DRIVER)
    t = driver.times[driver.times > 0.25]
    tail, ears = offsets(anim, driver, "tail", t), offsets(anim, driver, "ears", t)
    assert np.sqrt(np.mean(tail**2)) > 0.01 and tail.max() > 0.05
    assert np.sqrt(np.mean(ears**2)) > 3e-4
    rows = {row["name"]: row for row in anim.constraint_residuals()[:2]}
    assert rows["ears back"]["position_max"] < 1e-3 and rows["tail back"]["position_max"] < 1e-3
    assert rows["ears back"]["velocity_rms"] < 1e-3 and rows["tail back"]["velocity_rms"] < 1e-3
    assert anim.info["converged"]


def test_the_walk_cycle_loops_without_a_seam():
    """walk_cycle.toml (one cycle, loop = true, warped): the driven vertices follow within
    1 mm at every driver frame; positions and velocities at the end equal those at the start
    (to 1e-9 relative), and the free tail and ears move along with the walk."""
    scene = load_scene(CYCLE)
    anim = run(scene, outputs=[])
    assert anim.loop and anim.info["secondary"]
    report = anim.info["drive"]
    assert report["frames"] == 31 and report["max"] < 1e-3, report
    P, V = anim.positions([0.0, 1.0]), anim.velocities_at([0.0, 1.0])
    assert np.abs(P[1] - P[0]).max() <= 1e-9 * np.abs(P).max()
    assert np.abs(V[1] - V[0]).max() <= 1e-9 * np.abs(V).max()
    driver = read_driver(DRIVER)
    t = np.arange(30) / 30
    assert np.sqrt(np.mean(offsets(anim, driver, "tail", t) ** 2)) > 0.01  # swings with it
