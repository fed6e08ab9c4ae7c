"""The prepared body: immutable, and with other dynamics without recomputation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from wiggly.body import Damping, prepare
from wiggly.keyframes import Keyframe
from wiggly.solve import solve

from .conftest import make_body


@pytest.fixture(scope="module")
def body(tmp_path_factory):
    return make_body(tmp_path_factory, shape=(8, 2, 2), n_modes=12)


def test_body_is_immutable(body):
    with pytest.raises(dataclasses.FrozenInstanceError):
        body.damping = Damping(1.0, 0.0)


def test_with_dynamics_shares_what_does_not_depend_on_them_and_solves_as_prepared(body):
    """Other damping and gravity: the warp, levels, embedding and groups are the same objects
    (nothing recomputed), delta and the modal gravity follow, and a solve equals that of a
    body prepared with those dynamics from scratch."""
    warp, level = body.warp, body.fine_level
    group = body.group(level, np.arange(5), "surface")
    damping, gravity = Damping(2.0, 0.01), (0.0, -3.0, 1.0)
    other = body.with_dynamics(damping=damping, gravity=gravity)
    assert other.warp is warp and other.fine_level is level
    assert other.group(level, np.arange(5), "surface") is group
    assert other.damping == damping and np.array_equal(other.gravity, gravity)
    np.testing.assert_allclose(other.delta, 0.5 * (2.0 + 0.01 * body.eigenvalues))
    fresh = prepare(body.model, material=body.material, damping=damping, gravity=gravity,
                    n_modes=body.r, cache_dir=False)
    np.testing.assert_allclose(other.modal_gravity, fresh.modal_gravity, rtol=1e-10,
                               atol=1e-12 * np.abs(fresh.modal_gravity).max())
    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.7)
    keys = [Keyframe.rest(other, 0.0, np.arange(len(X)), still=True),
            Keyframe.offset(other, 0.8, tip, (0.0, 0.2, 0.0))]
    a = solve(other, keys, end=1.2, warp=False)
    b = solve(fresh, keys, end=1.2, warp=False)
    np.testing.assert_allclose(a.positions([0.5, 1.0]), b.positions([0.5, 1.0]), atol=1e-9)
    assert body.with_dynamics(damping=body.damping) is body


def test_a_body_copied_with_other_modes_keeps_no_old_group_matrices(body):
    """dataclasses.replace(body, modes=...) shared the body's per-group modal matrices,
    computed with the old modes: a solve then used them with the new ones (0.15 m off on a
    1 m cube).  A copy with other modes (here the same modes, sign-flipped) solves as a
    body prepared with them would."""
    from wiggly.modes import Modes

    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.7)

    def keys(b):
        return [Keyframe.rest(b, 0.0, np.arange(len(X)), still=True),
                Keyframe.offset(b, 0.8, tip, (0.0, 0.2, 0.0))]

    before = solve(body, keys(body), end=1.2, warp=False)  # fills the body's group memo
    flip = np.where(np.arange(body.r) % 2, -1.0, 1.0)  # the same space, other coordinates
    m = body.modes
    other = dataclasses.replace(body, modes=Modes(m.eigenvalues.copy(), m.vectors * flip,
                                                  m.n_rigid, m.fixed_vertices))
    after = solve(other, keys(other), end=1.2, warp=False)
    np.testing.assert_allclose(after.positions([0.5, 1.0]), before.positions([0.5, 1.0]),
                               atol=1e-9)


def test_prepare_leaves_the_callers_model_alone(body):
    model = dataclasses.replace(body.model, embedding=None)
    prepared = prepare(model, n_modes=8, cache_dir=False)
    assert model.embedding is None and prepared.model.embedding is not None


def test_objects_print_as_short_summaries(body):
    """At a prompt, a body, its model, modes, a keyframe and an animation print one line
    each that says what they are (counts, time range, how solved), not their arrays."""
    X = body.rest_positions()
    key = Keyframe.rest(body, 0.0, np.arange(len(X)), still=True, name="start")
    anim = solve(body, [key, Keyframe.offset(body, 1.0, [0, 1, 2], (0.0, 0.05, 0.0))],
                 duration=1.0)
    said = {"body": repr(body), "model": repr(body.model), "surface": repr(body.surface),
            "tets": repr(body.tets), "modes": repr(body.modes), "key": repr(key),
            "anim": repr(anim)}
    for text in said.values():
        assert "\n" not in text and len(text) < 200 and "array(" not in text, text
    assert f"{body.tets.n_tets} tets" in said["body"] and f"{body.r}, " in said["modes"]
    assert f"{len(X)} surface vertices, position and velocity" in said["key"]
    assert "'start'" in said["key"] and "[0, 1] s, 2 keyframes" in said["anim"]
    assert ("converged in" in said["anim"]) == anim.warped


def test_a_mode_count_inside_a_group_of_equal_frequencies_is_warned_about(tmp_path):
    """A 1 m cube (symmetric under a quarter turn about y): 10 modes end inside a pair of
    equal frequencies, so the top pulled 5 cm along x moved 4.95 cm and along z 4.52 cm (the
    eigensolver kept one of the pair); the count is warned about, and the count it names
    answers both pulls alike."""
    import re
    import warnings

    import meshio

    from wiggly.primitives import box_mesh

    V, T = box_mesh((4, 4, 4), (1.0, 1.0, 1.0))
    meshio.write(tmp_path / "cube.vtu", meshio.Mesh(V, [("tetra", T)]))
    bottom, top = np.flatnonzero(V[:, 1] < 0.01), np.flatnonzero(V[:, 1] > 0.99)

    def pulls(n):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            b = prepare(str(tmp_path / "cube.vtu"), n_modes=n, cache_dir=False,
                        gravity=(0, 0, 0))
        moved = []
        for d in ((0.05, 0.0, 0.0), (0.0, 0.0, 0.05)):
            a = solve(b, [Keyframe.rest(b, 1.0, bottom), Keyframe.offset(b, 1.0, top, d)],
                      duration=1.0, warp=False, check_keys=False)
            moved.append(np.linalg.norm((a.positions([1.0])[0] - V)[top].mean(axis=0)))
        return [str(w.message) for w in said if "equal frequency" in str(w.message)], moved

    said, moved = pulls(10)
    assert len(said) == 1 and said[0].startswith("n_modes = 10 (simulation.modes in a scene) "
                                                 "ends inside a group"), said
    assert abs(moved[0] - moved[1]) > 1e-3  # the split pair: unequal answers
    fewer = int(re.search(r"use (\d+) modes", said[0]).group(1))
    said, moved = pulls(fewer)
    assert not said and moved[0] == pytest.approx(moved[1], rel=1e-6)
