"""Folds of a motion (Animation.folds) and the warning for warped motions that fold.

The reference is independent of the warp's gradient operator: the signed volumes of the
played-back tets, and per-tet rotations from their edge matrices."""

from __future__ import annotations

import warnings
from dataclasses import replace

import meshio
import numpy as np
import pytest

import wiggly
from wiggly.keyframes import Keyframe
from wiggly.linalg import det3
from wiggly.primitives import box_mesh
from wiggly.solve import warn_folded
from wiggly.solve.animation import FOLD_TIMES


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    folder = tmp_path_factory.mktemp("folds")
    V, T = box_mesh((12, 3, 3), (1.2, 0.3, 0.3))
    meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    return wiggly.prepare(str(folder / "bar.vtu"), n_modes=12, gravity=(0.0, 0.0, 0.0),
                          cache_dir=False)


def _push(body, dx):
    """Rest at t = 0; at t = 1 the left end at rest and the right end moved by dx along the
    bar (dx < -1.2 pushes it through the left end)."""
    X = body.rest_positions()
    left, right = np.flatnonzero(X[:, 0] < 0.15), np.flatnonzero(X[:, 0] > 1.05)
    return [Keyframe.rest(body, 0.0, np.arange(len(X)), still=True),
            Keyframe.rest(body, 1.0, left), Keyframe.offset(body, 1.0, right, (dx, 0.0, 0.0))]


def _solve(body, keys, warp):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        anim = wiggly.solve(body, keys, duration=1.5, warp=warp)
    # the warnings name this file's line (not wiggly.solve or its decorator)
    assert all(w.filename == __file__ for w in caught if "inside out" in str(w.message))
    return anim, [str(w.message) for w in caught]


def _inside_out(body, anim, t):
    P = anim.positions([t], on="tets")[0][body.tets.tets]
    return int((np.linalg.det(P[:, 1:] - P[:, :1]) <= 0).sum())


def test_det3_equals_lapack_on_stacks_of_matrices():
    """The folds' determinant (rule of Sarrus) against LAPACK's LU, on stacks of any leading
    shape, including singular and mirrored matrices."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(4, 50, 3, 3))
    A[0, 0, 2] = A[0, 0, 0] + A[0, 0, 1]  # singular
    A[1, 0] = np.diag([1.0, 1.0, -1.0])  # a mirror
    np.testing.assert_allclose(det3(A), np.linalg.det(A), rtol=1e-12, atol=1e-14)
    assert det3(A)[1, 0] == -1.0


@pytest.mark.parametrize("warp", [False, True])
def test_folds_count_the_tets_the_motion_turns_inside_out(bar, warp):
    anim, _ = _solve(bar, _push(bar, -1.8), warp)
    rows = {row["time"]: row for row in anim.folds()}
    assert rows[0.0]["folded"] == 0 and "centre" not in rows[0.0]
    folded = _inside_out(bar, anim, 1.0)
    assert folded > 0.3 * bar.tets.n_tets  # the push turns most of the bar inside out
    assert rows[1.0]["folded"] == folded
    assert rows[1.0]["share"] == pytest.approx(folded / bar.tets.n_tets)
    assert 0.3 < rows[1.0]["centre"][0] < 0.9  # between the ends
    # frames between the keys are checked too (a crease there shows in the playback)
    between = [row for row in rows.values() if row["folded"] and row["time"] not in (0.0, 1.0)]
    assert between
    assert all(row["folded"] == _inside_out(bar, anim, row["time"]) for row in between[:3])
    assert anim.folds([]) == []
    # frames played back already (the editor's): the same rows, without a second playback
    times = anim.frame_times(10.0)
    shown = anim.folds(times, displacements=anim.displacements(times, on="tets"))
    assert [row["folded"] for row in shown] == [row["folded"] for row in anim.folds(times)]
    assert sum(row["folded"] for row in shown) > 0
    with pytest.raises(ValueError, match="tet-mesh displacements at 16 times"):
        anim.folds(times, displacements=anim.displacements(times[:3], on="tets"))
    # a driver keys every frame: at most FOLD_TIMES of the frames and of the key times
    many = replace(anim, keyframes=[replace(anim.keyframes[2], time=float(t))
                                    for t in np.linspace(0.0, 1.5, 400)])
    checked = [row["time"] for row in replace(many, body=bar).folds()]
    assert len(checked) <= 2 * FOLD_TIMES and checked[0] == 0.0 and checked[-1] == 1.5
    without_keys = wiggly.solve(bar, [], duration=1.0, warp=warp)  # a body at rest
    assert [row["folded"] for row in without_keys.folds()] == [0] * 31  # its frames checked
    mild, _ = _solve(bar, _push(bar, -0.6), warp)
    rows = mild.folds()  # the frames at 30 fps and the keys' times
    assert [row["time"] for row in rows] == pytest.approx(np.arange(46) / 30)
    assert [row["folded"] for row in rows] == [0] * 46 == [
        _inside_out(bar, mild, t) for t in (row["time"] for row in rows)]


def test_a_warped_motion_that_folds_is_warned_about(bar):
    _, messages = _solve(bar, _push(bar, -1.8), True)
    folds = [m for m in messages if "inside out" in m]
    assert len(folds) == 1 and "at t = 1 s (folded at" in folds[0], folds
    assert "squashed or sheared inside out" in folds[0]
    _, messages = _solve(bar, _push(bar, -0.6), True)
    assert not [m for m in messages if "inside out" in m]
    _, messages = _solve(bar, _push(bar, -1.8), False)  # linear motions: no such warning
    assert not [m for m in messages if "inside out" in m]


def _rotation_angles(body, U):
    """Per tet, the length of the rotation vector of the linear displacement U (n, 3), from
    the tets' edge matrices (A = dU dX^-1), not the warp's gradient operator."""
    X, T = body.tets.vertices, body.tets.tets
    dX = np.transpose(X[T[:, 1:]] - X[T[:, :1]], (0, 2, 1))
    dU = np.transpose(U[T[:, 1:]] - U[T[:, :1]], (0, 2, 1))
    A = dU @ np.linalg.inv(dX)
    skew = 0.5 * (A - np.transpose(A, (0, 2, 1)))
    return np.sqrt(0.5 * (skew**2).sum(axis=(1, 2)))


def test_a_spun_region_is_reported_in_turns(bar):
    """A linear state that twists the bar by many turns along its length: the warp creases
    it, and ``turns`` is the folded tets' largest rotation."""
    anim, _ = _solve(bar, _push(bar, -0.3), True)
    modes = bar.basis("tets").reshape(-1, 3, bar.r)
    X = bar.tets.vertices
    twist = np.stack([np.zeros(len(X)), -(X[:, 2] - 0.15), X[:, 1] - 0.15], 1) * X[:, :1]
    q = np.linalg.lstsq(modes.reshape(-1, bar.r), twist.ravel(), rcond=None)[0]
    spun = None
    for scale in (4, 8, 16, 32, 64):  # up to 64 rad per metre of twist rate
        values = anim.values.copy()
        values[np.flatnonzero(anim.nodes == 1.0)[0]] = scale * q
        candidate = replace(anim, values=values)
        row = next(r for r in candidate.folds() if r["time"] == 1.0)
        if row["folded"]:
            spun = (candidate, row, scale)
            break
    assert spun is not None, "no twist rate folded the bar"
    candidate, row, scale = spun
    U = (scale * q @ modes.reshape(-1, bar.r).T).reshape(-1, 3)
    angle = _rotation_angles(bar, U)
    assert row["folded"] == _inside_out(bar, candidate, 1.0)
    # the folded tets are among the fastest-turning ones, and turns is their largest rotation
    assert row["turns"] * 2 * np.pi <= angle.max() * (1 + 1e-9)
    assert row["turns"] > 0.5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_folded(candidate)
    assert any("spins them" in str(w.message) for w in caught)


PUSH_SCENE = """\
format = 1
[mesh]
path = "bar.vtu"
[simulation]
modes = 12
gravity = [0, 0, 0]
[time]
end = 1.5
[groups.left]
box = { min = [-0.01, -1, -1], max = [0.15, 1, 1] }
[groups.right]
box = { min = [1.05, -1, -1], max = [1.3, 1, 1] }
[groups.middle]
box = { min = [0.55, -1, -1], max = [0.65, 1, 1] }
on = "tets"
[groups.beside]
box = { min = [0.3, -1, -1], max = [0.9, 1, 1] }
[[keyframes]]
time = 0.0
group = "left"
position = "rest"
[[keyframes]]
time = 1.0
group = "left"
position = "rest"
[[keyframes]]
time = 1.0
group = "right"
position = { offset = [DX, 0.0, 0.0] }
"""


def _push_scene(folder, dx: float = -1.8):
    """The pushed bar as a scene file (``dx`` as in :func:`_push`)."""
    V, T = box_mesh((12, 3, 3), (1.2, 0.3, 0.3))
    meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    (folder / "push.toml").write_text(PUSH_SCENE.replace("DX", repr(dx)))
    return folder / "push.toml"


def test_wiggly_animate_warns_of_folds_in_its_own_words(tmp_path, capsys):
    """The command line names the scene file and leaves out the Python pointer."""
    from wiggly.cli import main

    _push_scene(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["animate", str(tmp_path / "push.toml"), "-o",
                     str(tmp_path / "push.npz")]) == 0
    said = [str(w.message) for w in caught] + [capsys.readouterr().err]
    folds = [m for m in said if "inside out" in m]
    assert folds and "push.toml: the warped motion turns" in folds[0], said
    assert "anim.folds()" not in folds[0]
    # the nearest group is named: a surface group over the folded middle, not the tets group
    assert "in the rest pose (the nearest group is 'beside', " in folds[0], folds[0]


def test_fold_highlights_cover_the_folding_frames_and_the_surface_there(bar):
    """Highlights over the frames that fold more than FOLDED of the tets (counted here from
    the played-back tets' signed volumes; frames less than two highlight windows apart make
    one span), over the surface the folded tets carry."""
    from wiggly.render.setup import HIGHLIGHT_WINDOW
    from wiggly.scene.run import FOLD_COLOR, fold_highlights
    from wiggly.solve import FOLDED

    anim, _ = _solve(bar, _push(bar, -1.8), warp=True)
    times = anim.frame_times(30.0)
    P = anim.positions(times, on="tets")[:, bar.tets.tets]
    inside_out = np.linalg.det(P[:, :, 1:] - P[:, :, :1]) <= 0  # (frames, tets)
    folding = inside_out.mean(axis=1) > FOLDED
    assert folding.any() and not folding.all()
    highlights = fold_highlights(anim, times)
    assert highlights and all(h.color == FOLD_COLOR for h in highlights)
    covered = np.zeros(len(times), bool)
    for h in highlights:
        span = (times >= h.time) & (times <= h.until)
        first, last = np.flatnonzero(span)[[0, -1]]
        assert folding[first] and folding[last]  # a span starts and ends at folding frames
        folded_at = times[folding & span]  # and has no gap of two windows without one
        assert np.diff(folded_at, prepend=h.time).max() < 2 * HIGHLIGHT_WINDOW
        covered |= span
        folded = np.flatnonzero(inside_out[span & folding].any(axis=0))
        carried = np.isin(bar.model.embedding.tet_index, folded)
        assert set(np.flatnonzero(carried)) <= set(h.vertices)  # its surface is shown ...
        # ... and every vertex shown lies within a tet's size of a tet folded in the span
        centres = bar.tets.vertices[bar.tets.tets[folded]].mean(axis=1)
        gap = np.linalg.norm(bar.surface.vertices[h.vertices][:, None] - centres[None], axis=2)
        assert gap.min(axis=1).max() < 0.2
        assert h.label.startswith("folded: ")
        if first > 0:  # the frame before a span shows no fold (a review saw one early)
            assert h.weight(float(times[first - 1])) == 0.0
    assert covered[folding].all()  # no folding frame is left out
    mild, _ = _solve(bar, _push(bar, -0.3), warp=True)
    assert fold_highlights(mild, times) == []


def test_a_preview_shows_where_the_motion_folds(tmp_path):
    """`wiggly render` of a folding scene colours the fold in its contact sheet; the same
    scene pushed mildly shows no such colour."""
    from PIL import Image

    from wiggly import render
    from wiggly.cli import main

    try:
        render.check_offscreen()
    except render.RenderingError as err:
        pytest.skip(f"offscreen OpenGL rendering is not available: {err}")

    def fold_pixels(dx):
        folder = tmp_path / f"dx{dx}"
        folder.mkdir()
        scene = _push_scene(folder, dx)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert main(["render", str(scene), "-o", str(folder / "sheet.png"), "-q"]) == 0
        img = np.asarray(Image.open(folder / "sheet.png").convert("RGB")).astype(int)
        # the body's part of each of the 8 tiles (480 x 270 below a 40-pixel title, 6-pixel
        # gaps): the labels below it name the fold in its colour too
        body = np.zeros(img.shape[:2], bool)
        for row in range(2):
            for col in range(4):
                y, x = 40 + 6 + row * (270 + 6), 6 + col * (480 + 6)
                body[y + 30 : y + 200, x : x + 480] = True
        r, g, b = (img[..., k][body] for k in range(3))
        return int(np.sum((r - g > 50) & (b - g > 30)))  # FOLD_COLOR's hue, shaded

    assert fold_pixels(-1.8) > 200
    assert fold_pixels(-0.3) == 0


def test_a_shot_longer_than_an_outputs_frames_is_checked_for_folds(tmp_path_factory):
    """A warped solve of a 700 s shot (shots may last an hour) raised from its own fold
    check, "more than 20000 frames: lower fps", though no fps was given: the check samples
    at most FOLD_TIMES frames, and it never makes the rest."""
    from tests.conftest import make_body

    body = make_body(tmp_path_factory, shape=(8, 2, 2), n_modes=10, gravity=(0, 0, 0))
    tip = np.flatnonzero(body.rest_positions()[:, 0] > 0.9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a key of a long shot is missed: said, not tested
        anim = wiggly.solve(body, [Keyframe.offset(body, 350.0, tip, (0.0, 0.1, 0.0))],
                            duration=700.0, warp=True)
    checked = anim.folds()
    assert FOLD_TIMES <= len(checked) <= FOLD_TIMES + 1  # frames, and the key's time
    assert checked[0]["time"] == 0.0 and checked[-1]["time"] == pytest.approx(700.0)
