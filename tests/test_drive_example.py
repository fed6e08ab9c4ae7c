"""examples/walk_secondary.toml and walk_cycle.toml as shipped: their driver is what
scripts/make_walk_driver.py makes, a valid, periodic skinned glTF of the critter's own
surface; the driven vertices follow it to within 1 mm; the free tail and ears swing when the
walk stops and settle; the cycle loops without a seam while the tail and ears move."""

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
    assert report["issues"]["numErrors"] == 0, report["issues"]
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


def test_free_parts_swing_when_the_walk_stops_and_settle(walk):
    """The tail and the ears, never keyed, leave the pose the driver gives them once the
    driver stops (at 2 s), by centimetres, and come back to rest by the end of the shot."""
    _, anim = walk
    groups = anim.info["scene"]["groups"]
    driver = read_driver(DRIVER)
    t = np.arange(2.0, 3.5 + 1e-9, 1 / 30)
    P = anim.positions(t)
    rest = driver.positions[-1]  # the driver ends at the rest pose
    for name in ("tail", "ears"):
        v = groups[name]
        off = np.linalg.norm(P[:, v] - rest[v], axis=2).max(axis=1)
        assert off.max() > 0.03, (name, off.max())
        late = t > 3.2
        assert off[late].max() < 0.15 * off.max(), (name, off[late].max(), off.max())


def test_the_walk_cycle_loops_without_a_seam():
    """walk_cycle.toml (one cycle, loop = true, warped): the driven vertices follow within
    1 mm at every driver frame; positions and velocities at the end equal those at the start
    (to 1e-9 relative), and the free tail and ears move along with the walk."""
    scene = load_scene(CYCLE)
    anim = run(scene, outputs=[])
    assert anim.loop and anim.info["converged"]
    report = anim.info["drive"]
    assert report["frames"] == 31 and report["max"] < 1e-3, report
    P, V = anim.positions([0.0, 1.0]), anim.velocities_at([0.0, 1.0])
    assert np.abs(P[1] - P[0]).max() <= 1e-9 * np.abs(P).max()
    assert np.abs(V[1] - V[0]).max() <= 1e-9 * np.abs(V).max()
    groups = anim.info["scene"]["groups"]
    Q = anim.positions(np.arange(31) / 30)
    for name in ("tail", "ears"):
        v = groups[name]
        assert np.linalg.norm(Q[:, v] - Q[0, v], axis=2).max() > 0.01, name
