"""A representative subset of the warped-solve convergence suite (benchmarks/
bench_convergence.py): scenes as users write them, on a bar and on a freshly meshed blob,
each of which must meet the stopping rule, with a distance bound that holds."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from wiggly.body import Damping, prepare
from wiggly.keyframes import Keyframe
from wiggly.mesh import Model, Surface, embed, tetrahedralize
from wiggly.solve import SolveOptions, SpacetimeProblem, WarpedObjective

from .conftest import make_body


@pytest.fixture(scope="module")
def blob():
    """A bumpy closed surface meshed by fTetWild now (a fresh mesh every run)."""
    rng = np.random.default_rng()
    sphere = trimesh.creation.icosphere(3)
    n = sphere.vertices
    r = 1.0 + sum(
        rng.uniform(0.1, 0.3) * np.exp(4.0 * (n @ d / np.linalg.norm(d) - 1))
        for d in rng.standard_normal((4, 3))
    )
    surface = Surface(n * r[:, None] * [0.3, 0.5, 0.25], sphere.faces)
    tets = tetrahedralize(surface, resolution=10, cache_dir=False)
    model = Model(surface, tets, embed(surface.vertices, tets), source="blob")
    return prepare(model, n_modes=16, cache_dir=False)


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return make_body(tmp_path_factory, shape=(10, 2, 2), size=(1.0, 0.1, 0.1), n_modes=16)


def upright(body):
    """Feet (the lowest 10 %) and top (the highest 25 %) of a body standing along its
    longest axis."""
    X = body.rest_positions()
    axis = int(np.argmax(np.ptp(X, axis=0)))
    h = X[:, axis]
    feet = np.flatnonzero(h < h.min() + 0.1 * np.ptp(h))
    top = np.flatnonzero(h > h.max() - 0.25 * np.ptp(h))
    turn_axis = np.eye(3)[axis]
    return feet, top, turn_axis


def scene(body, kind):
    feet, top, axis = upright(body)
    allv = np.arange(body.n_vertices())
    size = float(np.linalg.norm(np.ptp(body.rest_positions(), axis=0)))
    centre = body.rest_positions()[top].mean(axis=0)
    if kind == "turn 150":
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, 1.0, feet),
            Keyframe.rigid(body, 1.0, top, rotation=np.radians(150.0) * axis, center=centre),
        ]
    if kind == "velocity, no turn":
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, 0.7, feet),
            Keyframe.offset(body, 0.7, top, (0, 0, 0), velocity=1.5 * size * np.roll(axis, 1)),
        ]
    if kind == "hop and turn":
        return [
            Keyframe.rest(body, 0.0, allv, still=True),
            Keyframe.offset(body, 0.5, feet, 0.3 * size * axis, velocity=0.6 * size * axis),
            Keyframe.rigid(body, 1.2, feet, rotation=np.pi * axis),
        ]
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["turn 150", "velocity, no turn", "hop and turn"])
@pytest.mark.parametrize("which", ["bar", "blob"])
@pytest.mark.parametrize("damping", ["default", "undamped", "overdamped"])
def test_scene_converges_and_its_distance_bound_holds(request, which, kind, damping):
    """The stopping rule holds (decrement <= 1e-8 F, distance bound <= 1e-3 of the size),
    and the bound holds: a solve to 1e-14 lands within it."""
    base = request.getfixturevalue(which)
    alpha, beta = {"default": (0.5, 0.002), "undamped": (0.0, 0.0),
                   "overdamped": (20.0, 0.2)}[damping]
    body = prepare(base.model, material=base.material, damping=Damping(alpha, beta),
                   n_modes=base.r, cache_dir=False)
    keys = scene(body, kind)
    problem = SpacetimeProblem(body, 0.0, 1.6)
    anim = problem.solve(keys, warped=True)
    info = anim.info
    size = float(np.linalg.norm(np.ptp(body.rest_positions("tets"), axis=0)))
    assert info["converged"], info["stop"]
    assert info["distance_bound"] <= 1e-3 * size
    tight = problem.solve(keys, warped=True, warm_start=anim.warm_start,
                          options=SolveOptions(tolerance=1e-14, distance_tolerance=1e-9))
    dq = tight.values - anim.values
    moved = np.linalg.norm((body.modes.vectors @ dq.T).reshape(-1, 3, len(dq)), axis=1)
    assert moved.max() <= info["distance_bound"] + tight.info["distance_bound"]
    # and the gradient there is what the decrement allows: a stationary point
    obj = WarpedObjective(problem, body.fine_level, anim.keyframes, anim.nodes)
    point = obj.evaluate(np.stack([anim.values, anim.velocities], axis=1).ravel())
    assert np.isclose(point.F, info["objective"], rtol=1e-12)
