"""wiggly.checks: one wording for a mistake, whichever stage finds it."""

from __future__ import annotations

import numpy as np
import pytest

from wiggly import WigglyInputError, render
from wiggly.checks import (
    animation_arrays,
    brief,
    extension,
    finite_number,
    pixel_size,
    positive_number,
    unit_color,
)
from wiggly.export import SurfaceAnimation, write_animation

TIMES = np.array([0.0, 0.5, 1.0])
POSITIONS = np.zeros((3, 4, 3))
FACES = np.array([[0, 1, 2], [0, 2, 3]])

MISTAKES = [
    ({"times": np.array([0.0, 2.0, 1.0])},
     "times should be strictly increasing; times[1] = 2.0 and times[2] = 1.0"),
    ({"positions": np.zeros((2, 4, 3))},
     "positions should have shape (F, n, 3) with F = len(times) = 3; shape is (2, 4, 3)"),
    ({"positions": np.full((3, 4, 3), np.inf)},
     "positions should be finite; frame 0, vertex 0 is [inf, inf, inf]"),
    ({"faces": np.array([[0, 1, 4]])},
     "faces should index the n = 4 vertices (0 <= i < 4); face 0 is [0, 1, 4]"),
    ({"faces": np.array([[0.0, 1.0, 2.0]])}, "faces should be an integer array; dtype is float64"),
]


@pytest.mark.parametrize(("change", "message"), MISTAKES)
def test_export_and_render_say_the_same(tmp_path, monkeypatch, change, message):
    args = {"times": TIMES, "positions": POSITIONS, "faces": FACES, **change}
    with pytest.raises(WigglyInputError) as checked:
        animation_arrays(args["times"], args["positions"], args["faces"])
    assert str(checked.value) == message
    with pytest.raises(WigglyInputError) as exported:
        write_animation(tmp_path / "a.npz", SurfaceAnimation(**args))
    assert str(exported.value).endswith(": " + message)  # prefixed with the file
    monkeypatch.setattr(render.preview, "check_offscreen", lambda: "not needed")
    with pytest.raises(WigglyInputError) as rendered:
        render.render_video(tmp_path / "a.mp4", **args, size=(64, 48))
    assert str(rendered.value) == message
    assert list(tmp_path.iterdir()) == []


def test_valid_arrays_come_back_in_canonical_dtypes():
    t, P, F = animation_arrays([0, 1], np.zeros((2, 3, 3), np.float32), [[0, 1, 2]])
    assert t.dtype == np.float64 and P.dtype == np.float32 and F.dtype == np.int64
    _, P, _ = animation_arrays([0], np.zeros((1, 3, 3), np.int32), [[0, 1, 2]])
    assert P.dtype == np.float64


@pytest.mark.parametrize(("check", "value", "message"), [
    (lambda v: finite_number(v, "keyframe time"), "soon",
     "keyframe time should be a finite number; got 'soon'"),
    (lambda v: finite_number(v, "keyframe time"), True,
     "keyframe time should be a finite number; got True"),
    (lambda v: finite_number(v, "keyframe time"), float("inf"),
     "keyframe time should be a finite number; got inf"),
    (lambda v: positive_number(v, "window", "s"), 0,
     "window should be a number > 0 (s); got 0"),
    (lambda v: pixel_size(v, "tile_size"), (8, 600),
     "tile_size should be (width, height) with each between 16 and 8192 pixels; got (8, 600)"),
    (lambda v: pixel_size(v), "large",
     "size should be (width, height) with each between 16 and 8192 pixels; got 'large'"),
    (lambda v: unit_color(v), (1, 0.5),
     "color should be 3 numbers in [0, 1] (red, green, blue); got (1, 0.5)"),
    (lambda v: extension(v, (".mp4", ".gif")), "shot.avi",
     "shot.avi should end in .mp4 or .gif; its extension is '.avi'"),
    (lambda v: extension(v, (".png",)), "sheet", "sheet should end in .png; it has no extension"),
])
def test_scalar_checks_name_the_field_what_is_right_and_the_value(check, value, message):
    with pytest.raises(WigglyInputError) as err:
        check(value)
    assert str(err.value) == message


def test_scalar_checks_return_the_value_and_fail_as_told():
    assert finite_number(np.float32(0.5), "t") == 0.5 and positive_number(2, "w") == 2.0
    assert pixel_size((640.0, 480), "size") == (640, 480)
    assert unit_color([1, 0, 0.5]) == (1.0, 0.0, 0.5)
    assert extension("a/B.GIF", (".mp4", ".gif")) == ".gif"
    assert brief("x" * 100) == repr("x" * 100)[:57] + "..."

    class Refused(Exception):
        pass

    def refuse(message: str):
        raise Refused(message)

    with pytest.raises(Refused, match="young should be a finite number"):
        finite_number(None, "young", refuse)
