"""Offscreen previews: images are checked for facts (not blank, motion, highlight colors, framing),
videos and sheets by decoding them back (frame count, size), writes for atomicity.

Rendering tests need a working offscreen OpenGL (EGL, OSMesa or X); the session fixture probes it
in a subprocess and skips them with the reason when it does not work.
"""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh
from PIL import Image

from wiggly import render
from wiggly.errors import WigglyInputError
from wiggly.render import (
    Highlight,
    Preview,
    plot_diagnostics,
    render_contact_sheet,
    render_frame,
    render_video,
    video_frame_times,
)
from wiggly.render.setup import checked_highlights

SIZE = (192, 108)


@pytest.fixture(scope="session")
def offscreen() -> str:
    try:
        return render.check_offscreen()
    except render.RenderingError as e:
        pytest.skip(f"offscreen OpenGL rendering is not available on this machine: {e}")


def test_a_module_in_the_working_folder_does_not_break_the_probe(offscreen, tmp_path,
                                                                  monkeypatch):
    """A user's ``random.py`` (a module name VTK's imports use) in the folder wiggly runs
    from: the probe's ``python -c`` child would import it first and fail, and the error
    blamed OpenGL. Children run with ``-P`` (no working folder on their import path)."""
    (tmp_path / "random.py").write_text("raise ImportError('the user random.py was imported')\n")
    monkeypatch.chdir(tmp_path)
    assert render.setup.check_offscreen.__wrapped__() == offscreen


@pytest.fixture(scope="module")
def ball():
    """An icosphere (r = 0.5, 1280 faces) that travels 1.5 m along x and squashes, 21 frames."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    times = np.linspace(0.0, 1.0, 21)
    squash = 1 + 0.2 * np.sin(2 * np.pi * times)
    P = np.array([V * [1 / np.sqrt(s), s, 1 / np.sqrt(s)] + [1.5 * t, 0.5 * s, 0]
                  for t, s in zip(times, squash, strict=True)])
    return times, P, F


def highlight_pixels(img: np.ndarray) -> int:
    """Pixels of the default (orange) highlight hue: red well above green, green above blue."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return int(np.sum((r > 120) & (r - g > 50) & (g - b > 10) & (r - b > 90)))


# ----------------------------------------------------------------------------------------------
# single frames


def test_frames_show_the_object_moving(offscreen, ball):
    times, P, F = ball
    with Preview(times, P, F, size=SIZE) as preview:
        a, b = preview.render(0.0), preview.render(1.0)
    assert a.shape == b.shape == (SIZE[1], SIZE[0], 3) and a.dtype == np.uint8
    for img in (a, b):
        assert img.std() > 10  # not blank
        assert len(np.unique(img.reshape(-1, 3), axis=0)) > 200  # shaded, not flat
    diff = np.abs(a.astype(int) - b.astype(int))
    assert diff.mean() > 1.0
    moved = diff.sum(axis=-1) > 40  # object pixels in one frame, background in the other
    moved[: SIZE[1] // 5, : SIZE[0] // 3] = False  # the time label
    assert 0.01 < moved.mean() < 0.5  # the object (and its shadow) moved; the scene did not
    # the ball travels 1.5 m (3 diameters) along x: the changed pixels span both positions
    cols = np.flatnonzero(moved.any(axis=0))
    assert cols.max() - cols.min() > SIZE[0] / 3


def test_camera_frames_all_frames(offscreen, ball):
    """Without ground the background is a vertical gradient (rows uniform); the object never
    touches the image border in any frame, and the camera does not move."""
    times, P, F = ball
    with Preview(times, P, F, size=SIZE, ground=False) as preview:
        images = [preview.render(t) for t in (0.0, 0.25, 1.0)]
    for img in images:
        background = img[:, -1:].astype(int)  # right column: no label there
        obj = np.abs(img.astype(int) - background).sum(axis=-1) > 30
        obj[: SIZE[1] // 5, : SIZE[0] // 3] = False  # the time label
        assert obj.mean() > 0.01
        assert not obj[0].any() and not obj[-1].any() and not obj[:, 0].any()
    top_rows = [img[1, -10:] for img in images]  # background identical: camera fixed
    assert all(np.array_equal(top_rows[0], row) for row in top_rows)


def test_single_pose_and_z_up(offscreen, ball):
    _, P, F = ball
    z_up = P[0][:, [0, 2, 1]]  # the same ball with z up
    img = render_frame(0.0, z_up, F, size=SIZE, up=(0, 0, 1))
    assert img.shape == (SIZE[1], SIZE[0], 3) and img.std() > 10


def test_highlight_colors_group_at_key_time(offscreen, ball):
    times, P, F = ball
    top = np.flatnonzero(P[0][:, 1] > 0.6)
    hl = Highlight(top, time=0.5, label="top")
    with Preview(times, P, F, size=SIZE, highlights=[hl]) as preview:
        at_key = highlight_pixels(preview.render(0.5))
        far = highlight_pixels(preview.render(0.0))
        just_outside = highlight_pixels(preview.render(0.5 + 1.01 * hl.window))
    assert far == 0 and just_outside == 0
    assert at_key > 100


def test_highlight_weight_is_a_smoothstep():
    hl = Highlight(np.array([0]), time=1.0, window=0.25)
    assert hl.weight(1.0) == 1.0
    assert hl.weight(1.25) == hl.weight(0.75) == 0.0 == hl.weight(3.0)
    assert hl.weight(1.125) == pytest.approx(0.5)
    assert hl.weight(1.0 + 0.25 * 0.25) == pytest.approx(hl.weight(1.0 - 0.25 * 0.25))
    s = np.linspace(1.0, 1.3, 31)
    assert np.all(np.diff([hl.weight(t) for t in s]) <= 0)  # fades out monotonically


def test_a_span_highlight_is_full_from_time_until_and_fades_outside():
    hl = Highlight(np.array([0]), time=1.0, window=0.25, until=2.0)
    assert hl.weight(1.0) == hl.weight(1.5) == hl.weight(2.0) == 1.0
    assert hl.weight(0.75) == hl.weight(2.25) == 0.0
    assert hl.weight(2.125) == pytest.approx(0.5) == hl.weight(0.875)
    with pytest.raises(WigglyInputError, match=r"highlights\[0\]: until = 0.5 s comes before "
                       r"time = 1 s"):
        checked_highlights([Highlight(np.array([0]), time=1.0, until=0.5)], 4)


def test_targets_drawn_only_around_key_time(offscreen, ball):
    times, P, F = ball
    above = P[10][:5] + np.array([0, 1.2, 0])  # targets 1.2 m above the ball, in view
    groups = dict(vertices=np.arange(5), time=0.5, color=(0.1, 0.3, 1.0))
    with Preview(times, P, F, size=SIZE, highlights=[Highlight(**groups, targets=above)]) as p:
        with_targets = p.render(0.5), p.render(0.0)
    with Preview(times, P, F, size=SIZE, highlights=[Highlight(**groups)]) as p:
        without = p.render(0.5), p.render(0.0)
    assert np.abs(with_targets[0].astype(int) - without[0]).sum(axis=-1).max() > 100
    assert np.array_equal(with_targets[1], without[1])


def test_targets_sit_where_their_key_puts_the_vertices(offscreen, ball):
    """A key's target spheres are drawn at its targets, in the same place as the body: a key
    met exactly puts them on its vertices (the scene is drawn about the frames' centre, and
    the targets were not moved with it: a demo's feet targets floated at mid-body)."""
    times, P, F = ball
    P = P + np.array([0.3, 2.0, -0.5])  # off the origin, so the drawn scene is shifted
    keyed = np.arange(0, len(P[0]), 7)
    hl = Highlight(keyed, time=times[10], color=(0.1, 0.3, 1.0), targets=P[10][keyed])
    with Preview(times, P, F, size=SIZE, highlights=[hl]) as p:
        p.render(times[10])
        lo, hi = np.reshape(p._targets[0].GetBounds(), (3, 2)).T
        drawn = p.positions_at(times[10])[keyed]
        radius = 0.012 * p.scale
    assert np.allclose(lo, drawn.min(axis=0) - radius, atol=1e-3 * p.scale)
    assert np.allclose(hi, drawn.max(axis=0) + radius, atol=1e-3 * p.scale)


# ----------------------------------------------------------------------------------------------
# videos


def test_video_frame_times():
    t = np.linspace(0.0, 2.0, 49)  # uniform, 24 fps
    same, fps = video_frame_times(t)
    assert np.array_equal(same, t) and fps == pytest.approx(24.0)
    resampled, fps = video_frame_times(t, 10)
    assert fps == 10 and len(resampled) == 21 and resampled[-1] == pytest.approx(2.0)
    capped, fps = video_frame_times(t, max_fps=20)
    assert fps == 20 and len(capped) == 41
    uneven = np.array([0.0, 0.1, 0.35, 1.0])
    frames, fps = video_frame_times(uneven)
    assert fps == render.DEFAULT_FPS and len(frames) == 31
    with pytest.raises(WigglyInputError, match="fps"):
        video_frame_times(t, -1)


def test_mp4_decodes_with_frame_count_and_size(offscreen, ball, tmp_path):
    times, P, F = ball
    with pytest.warns(UserWarning, match=r"ball.mp4: an H.264 video needs an even width and "
                      r"height: the size 193 x 109 is written as 192 x 108"):
        path = render_video(tmp_path / "ball.mp4", times, P, F, size=(193, 109))  # odd: cropped
    frames = iio.imread(path)
    assert frames.shape == (len(times), 108, 192, 3)
    assert frames[0].std() > 10
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 1.0

    path = render_video(tmp_path / "ball10.mp4", times, P, F, size=SIZE, fps=10)
    assert iio.imread(path).shape[0] == 11  # 1 s at 10 fps, both ends


def test_gif_decodes_loops_and_is_downscaled(offscreen, ball, tmp_path):
    times, P, F = ball
    hl = Highlight(np.flatnonzero(P[0][:, 1] > 0.6), time=0.5)
    path = render_video(tmp_path / "ball.gif", times, P, F, size=(640, 360), highlights=[hl])
    frames = iio.imread(path)
    scale = render.GIF_MAX_SIDE / 640
    assert frames.shape[:3] == (len(times), round(360 * scale), round(640 * scale))  # 20 fps
    with Image.open(path) as im:
        assert im.info["loop"] == 0 and im.info["duration"] == 50
    key = int(np.argmin(np.abs(times - 0.5)))
    assert highlight_pixels(frames[key][..., :3]) > 100  # the palette kept the highlight color
    assert highlight_pixels(frames[0][..., :3]) == 0


def test_gif_caps_frame_rate(offscreen, ball, tmp_path):
    _, P, F = ball
    fine = np.linspace(0.0, 1.0, 51)  # 50 fps
    P50 = np.array([P[min(round(20 * t), 20)] for t in fine])
    path = render_video(tmp_path / "fast.gif", fine, P50, F, size=SIZE)
    assert iio.imread(path).shape[0] == 21  # 20 fps, 1 s


# ----------------------------------------------------------------------------------------------
# sheets and plots


@pytest.mark.parametrize("title", [None, "ball"])
def test_contact_sheet_grid_size(offscreen, ball, tmp_path, title):
    times, P, F = ball
    tile = (120, 80)
    path = render_contact_sheet(tmp_path / "sheet.png", times, P, F, n_frames=5, columns=3,
                                tile_size=tile, title=title)
    img = np.asarray(Image.open(path).convert("RGB"))
    gap, header = render.SHEET_GAP, render.SHEET_HEADER if title else 0
    assert img.shape == (header + 2 * tile[1] + 3 * gap, 3 * tile[0] + 4 * gap, 3)
    first = img[header + gap: header + gap + tile[1], gap: gap + tile[0]]
    empty = img[header + 2 * gap + tile[1]:-gap, 3 * gap + 2 * tile[0]:-gap]  # 6th slot
    assert first.std() > 10 and empty.std() == 0
    if title:
        assert img[:header].std() > 1  # the title text


def test_a_one_frame_animation_gets_one_tile(offscreen, ball, tmp_path):
    """A contact sheet of a single frame is one tile, not eight copies of it."""
    times, P, F = ball
    tile = (64, 48)
    path = render_contact_sheet(tmp_path / "one.png", times[:1], P[:1], F, tile_size=tile)
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape == (tile[1] + 2 * render.SHEET_GAP, tile[0] + 2 * render.SHEET_GAP, 3)


def test_diagnostics_plot(tmp_path):
    times = np.linspace(0, 2, 101)
    lam = np.concatenate([np.zeros(6), (2 * np.pi * np.array([1.5, 2.2, 4.0, 7.1])) ** 2])
    modal = np.column_stack([np.sin(k * times) / (k + 1) for k in range(len(lam))])
    residuals = [{"time": 0.5, "name": "lift", "position_rms": 2e-3, "position_max": 4e-3},
                 {"time": 1.5, "name": "land", "position_rms": 5e-4, "velocity_rms": 0.01}]
    path = plot_diagnostics(tmp_path / "diag.png", times, modal, residuals, lam,
                            title="diagnostics", dpi=80, size=(8, 6))
    img = np.asarray(Image.open(path).convert("RGB"))
    assert img.shape == (6 * 80, 8 * 80, 3)
    assert img.std() > 10 and (img < 128).mean() > 0.005  # lines and text drawn


def test_diagnostics_rejects_mismatched_shapes(tmp_path):
    with pytest.raises(WigglyInputError, match=r"eigenvalues should have shape \(3,\)"):
        plot_diagnostics(tmp_path / "d.png", [0, 1], np.zeros((2, 3)), [], np.zeros(4))
    with pytest.raises(WigglyInputError, match=r"modal should have shape \(F, r\) with F = 2"):
        plot_diagnostics(tmp_path / "d.png", [0, 1], np.zeros((3, 3)), [], np.zeros(3))


# ----------------------------------------------------------------------------------------------
# files: overwrite protection and atomic writes


def test_existing_output_is_kept_unless_overwrite(offscreen, ball, tmp_path):
    times, P, F = ball
    path = tmp_path / "sheet.png"
    path.write_bytes(b"precious")
    with pytest.raises(WigglyInputError, match="exists; pass overwrite=True"):
        render_contact_sheet(path, times, P, F, n_frames=1, tile_size=(64, 48))
    assert path.read_bytes() == b"precious"
    render_contact_sheet(path, times, P, F, n_frames=1, tile_size=(64, 48), overwrite=True)
    assert Image.open(path).size == (64 + 2 * render.SHEET_GAP, 48 + 2 * render.SHEET_GAP)


@pytest.mark.parametrize("name", ["ball.mp4", "ball.gif", "sheet.png"])
def test_failed_render_leaves_no_file(offscreen, ball, tmp_path, monkeypatch, name):
    times, P, F = ball
    calls = []
    original = Preview.render

    def failing(self, t):
        calls.append(t)
        if len(calls) > 3:
            raise RuntimeError("boom")
        return original(self, t)

    monkeypatch.setattr(Preview, "render", failing)
    with pytest.raises(RuntimeError, match="boom"):
        if name.endswith(".png"):
            render_contact_sheet(tmp_path / name, times, P, F, tile_size=(64, 48))
        else:
            render_video(tmp_path / name, times, P, F, size=(64, 48))
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------
# input errors (raised before any rendering)


@pytest.mark.parametrize(("change", "message"), [
    (dict(positions=np.zeros((3, 4, 2))), r"positions should have shape \(F, n, 3\)"),
    (dict(times=[0.0, 1.0]), r"positions should have shape \(F, n, 3\) with F = len\(times\) = 2"),
    (dict(times=[0.0, 2.0, 1.0]), "strictly increasing"),
    (dict(faces=np.array([[0, 1, 4]])), r"faces should index the n = 4 vertices .* face 0 is"),
    (dict(faces=np.array([[0.0, 1, 2]])), "integer"),
    (dict(highlights=[Highlight(np.array([7]), 0.5)]),
     r"highlights\[0\]: vertex index 7 does not exist: the surface has 4 vertices"),
    (dict(highlights=[Highlight(np.array([1]), 0.5, color=(2, 0, 0))]),
     r"highlights\[0\]: color should be 3 numbers in \[0, 1\] \(red, green, blue\); "
     r"got \(2, 0, 0\)"),
    (dict(highlights=[Highlight(np.array([1]), float("nan"), label="lift")]),
     r"highlights\[0\] \('lift'\): time should be a finite number; got nan"),
    (dict(highlights=[Highlight(np.array([1]), 0.5, window=0.0)]),
     r"highlights\[0\]: window should be a number > 0 \(s\); got 0\.0"),
    (dict(camera="sideways"), "unknown camera 'sideways'"),
    (dict(camera=(1, 2, 3)), "camera should be one of"),
    (dict(up=(0, 0, 0)), "up should be a non-zero 3-vector"),
    (dict(size=(8, 8)), r"size should be \(width, height\) with each between 16 and 8192 "
                        r"pixels; got \(8, 8\)"),
])
def test_bad_input_is_reported(change, message, monkeypatch):
    monkeypatch.setattr(render.preview, "check_offscreen", lambda: "not needed")
    args = dict(times=[0.0, 0.5, 1.0], positions=np.zeros((3, 4, 3)), faces=np.array([[0, 1, 2]]))
    args.update(change)
    kwargs = {k: v for k, v in args.items() if k not in ("times", "positions", "faces")}
    with pytest.raises(WigglyInputError, match=message):
        render_frame(args["times"], args["positions"], args["faces"], at=0.5, **kwargs)


def test_bad_output_paths(tmp_path, ball):
    times, P, F = ball
    with pytest.raises(WigglyInputError, match=r"x\.avi should end in \.mp4 or \.gif; its "
                                               r"extension is '\.avi'"):
        render_video(tmp_path / "x.avi", times, P, F)
    with pytest.raises(WigglyInputError, match=r"should end in \.png; its extension is '\.jpg'"):
        render_contact_sheet(tmp_path / "x.jpg", times, P, F)


def test_probe_reports_the_backend(offscreen):
    assert "RenderWindow" in offscreen


def test_a_body_far_from_the_origin_renders_as_it_does_at_the_origin():
    """A body 2e4 m from the origin (a map's coordinates) was a blank picture (VTK draws in
    float32): the scene is drawn about the frames' centre, so the picture is the same as at
    the origin, for a preset camera and for an explicit pose moved with the body."""
    sphere = trimesh.creation.icosphere(3, radius=0.5)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    X = np.stack([V, V + np.array([0.0, 0.1, 0.0])]).astype(np.float32)
    t = np.array([0.0, 1.0])
    off = np.array([1e4, 2e4, -3e3])
    far = (X + off).astype(np.float32)
    near = render_frame(t, X, F, at=0.5).astype(int)
    assert np.abs(near - render_frame(t, far, F, at=0.5)).mean() < 0.5
    pose = ((3.0, 2.0, 3.0), (0.0, 0.0, 0.0))
    posed = render_frame(t, X, F, at=0.5, camera=pose).astype(int)
    moved = (tuple(np.add(pose[0], off)), tuple(off))
    assert np.abs(posed - render_frame(t, far, F, at=0.5, camera=moved)).mean() < 0.5
    assert np.abs(posed - near).mean() > 5  # the poses differ: the check can tell pictures apart


def test_a_preview_without_a_clock_draws_no_time():
    """``clock=False`` (mode previews, whose time means nothing): a still body renders the
    same picture at 0 s and 5 s, where the clock's "t = ..." makes the two differ."""
    from wiggly.render.preview import Preview

    sphere = trimesh.creation.icosphere(2, radius=0.5)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    still = np.stack([V, V])
    for clock, same in ((True, False), (False, True)):
        with Preview([0.0, 5.0], still, F, size=(320, 180), clock=clock) as preview:
            a, b = preview.render(0.0), preview.render(5.0)
        assert np.array_equal(a, b) == same, clock



def test_a_scene_with_z_up_gravity_is_previewed_with_z_up(offscreen, tmp_path):
    """A shot whose gravity points along -z is previewed as its own motion turned to y up:
    the preview's up is against gravity, not the y axis."""
    from wiggly.export import read_animation
    from wiggly.scene import load_scene, render_preview
    from wiggly.scene import run as run_scene

    box = trimesh.creation.box(extents=(1.0, 0.1, 0.1))
    box.apply_translation((0.5, 0.0, 0.0))
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.05))
    box.export(tmp_path / "bar.obj")
    (tmp_path / "bar.toml").write_text("""
[mesh]
path = "bar.obj"
resolution = 8
[material]
young = 1e6
[simulation]
gravity = [0.0, 0.0, -9.81]
modes = 6
warp = false
fixed = ["left"]
[groups.left]
box = { min = [-0.01, -1.0, -1.0], max = [0.01, 1.0, 1.0] }
[time]
end = 0.5
fps = 8
[output]
size = [192, 108]
""")
    scene = load_scene(tmp_path / "bar.toml")
    run_scene(scene, outputs=[tmp_path / "bar.png", tmp_path / "bar.npz"])
    anim = read_animation(tmp_path / "bar.npz")
    z_to_y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # z -> y
    render_preview(tmp_path / "turned.png", anim.times, anim.positions @ z_to_y.T, anim.faces,
                   output=scene.output, title=scene.name)
    shown, turned = (np.asarray(Image.open(tmp_path / f"{name}.png"), dtype=np.float64)
                     for name in ("bar", "turned"))
    assert shown.shape == turned.shape
    assert np.abs(shown - turned).mean() < 0.5
