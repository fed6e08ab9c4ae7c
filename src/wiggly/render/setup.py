"""Rendering setup: constants, the headless (offscreen) backend and its probe, and the
inputs of every renderer checked."""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wiggly.checks import (
    animation_arrays,
    array,
    extension,
    finite_number,
    positive_number,
    unit_color,
    vertex_indices,
)
from wiggly.errors import WigglyInputError

VIDEO_FORMATS = (".mp4", ".gif")

"""Frame rate of a video when ``times`` are not uniformly spaced and no ``fps`` is given."""
GIF_MAX_FPS = 20.0
GIF_MAX_SIDE = 480
"""GIF frames are rendered at ``size`` and downscaled so that the longer side is at most this."""
MP4_CRF = 18
"""x264 constant rate factor (visually lossless for previews); smaller is better and bigger."""
SHEET_GAP = 6
"""Pixels between and around the tiles of a contact sheet."""
SHEET_HEADER = 40
"""Height in pixels of a contact sheet's title band (only when a title is given)."""
HIGHLIGHT_WINDOW = 0.25

CAMERA_PRESETS = {
    "three_quarter": (35.0, 22.0),
    "front": (0.0, 8.0),
    "side": (90.0, 8.0),
    "back": (180.0, 8.0),
    "top": (0.0, 89.0),
}
"""Named views: (azimuth, elevation) in degrees.  Azimuth turns from the front (the direction
``right x up`` where ``right`` is the x axis made orthogonal to ``up``) towards the right."""

BASE_COLOR = (0.64, 0.70, 0.78)
BACKGROUND_TOP = (0.47, 0.51, 0.57)
BACKGROUND_BOTTOM = (0.83, 0.84, 0.86)
GROUND_COLORS = ((0.88, 0.88, 0.89), (0.83, 0.83, 0.84))
TEXT_COLOR = (0.08, 0.09, 0.11)
SHADOW_STRENGTH = 0.45


class RenderingError(RuntimeError):
    """Offscreen OpenGL rendering does not work on this machine; the message says how to fix it."""


@dataclass
class Highlight:
    """A keyframed vertex group, highlighted around its key time (or over a span of time).

    Attributes
    ----------
    vertices : (g,) int
        Surface vertex indices of the group.
    time : float
        Key time in seconds.
    color : (3,) float in [0, 1]
        Highlight color; blended into the vertex colors with weight
        ``smoothstep(1 - |t - time| / window)`` (1 at the key time, 0 beyond ``window``).
    label : str or None
        Shown in the lower left corner while highlighted ("" names it "keyframe N"; None
        shows no label: a colour only).
    targets : (k, 3) float or None
        Target positions, drawn as small spheres while highlighted.
    window : float
        Half-width of the highlight in seconds.
    until : float or None
        The end of a span from ``time``: fully highlighted from ``time`` to ``until``, fading
        over ``window`` on either side (e.g. the frames where a motion folds).
    timed : bool
        Whether the label says the key's time (False: the label alone, for highlights that
        are no keys, such as a mode preview's).
    """

    vertices: np.ndarray
    time: float
    color: tuple[float, float, float] = (1.0, 0.35, 0.1)
    label: str | None = ""
    targets: np.ndarray | None = None
    window: float = HIGHLIGHT_WINDOW
    until: float | None = None
    timed: bool = True

    def weight(self, t: float) -> float:
        """Blend weight of the highlight color at time ``t``: smoothstep, 1 at the key time
        (or between ``time`` and ``until``)."""
        end = self.time if self.until is None else self.until
        gap = max(self.time - t, t - end, 0.0)
        s = min(max(1.0 - gap / self.window, 0.0), 1.0)
        return s * s * (3.0 - 2.0 * s)


# ----------------------------------------------------------------------------------------------
# headless setup


def configure_headless() -> None:
    """Point VTK at EGL on a Linux machine without a display (see the module docstring)."""
    if (sys.platform.startswith("linux") and not os.environ.get("DISPLAY")
            and not os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


_PROBE = """
from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
from vtkmodules.vtkRenderingCore import vtkRenderer, vtkRenderWindow
import vtkmodules.vtkRenderingOpenGL2  # registers the OpenGL render windows
window = vtkRenderWindow()
window.SetOffScreenRendering(1)
window.SetSize(8, 8)
renderer = vtkRenderer()
renderer.SetBackground(1.0, 0.5, 0.0)
window.AddRenderer(renderer)
window.Render()
pixel = vtkUnsignedCharArray()
window.GetPixelData(0, 0, 0, 0, 0, pixel, 0)
gl = [s for s in window.ReportCapabilities().splitlines() if "renderer string" in s]
print(window.GetClassName(), tuple(int(c) for c in pixel.GetTuple3(0)), *gl[:1])
"""

_FIXES = (
    "Fix: install Mesa's EGL libraries (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri), "
    "or OSMesa (apt-get install libosmesa6, then set "
    "VTK_DEFAULT_OPENGL_WINDOW=vtkOSOpenGLRenderWindow), or run under a virtual X server "
    "(apt-get install xvfb libgl1 libglx-mesa0 libxcursor1; xvfb-run or pyvista.start_xvfb())."
)


@functools.cache
def check_offscreen(timeout: float = 60.0) -> str:
    """Render one pixel offscreen in a subprocess; return a description of the OpenGL backend.

    A subprocess, because VTK crashes the process (segmentation fault) when no OpenGL backend
    works.  Cached: runs once per process.

    Raises
    ------
    RenderingError
        Rendering fails or gives a wrong pixel; the message lists the fixes.
    """
    configure_headless()
    try:
        out = subprocess.run([sys.executable, "-P", "-c", _PROBE], capture_output=True, text=True,
                             timeout=timeout, env=os.environ.copy())
    except subprocess.TimeoutExpired as e:
        raise RenderingError(
            f"offscreen OpenGL probe did not finish in {timeout} s. {_FIXES}") from e
    if out.returncode != 0 or "(255, 128, 0)" not in out.stdout:
        # VTK log lines: "<color codes>date (time) [thread] file:line  WARN| message<reset>"
        log = [re.sub(r"\x1b\[[0-9;]*m", "", line).split("| ", 1)[-1].strip()
               for line in out.stderr.splitlines() if line.strip()][-3:]
        status = (f"crashed with signal {-out.returncode}" if out.returncode < 0 else
                  f"exit code {out.returncode}, output {out.stdout.strip()!r}")
        # VTK's Python modules themselves missing or broken (not a system OpenGL library)
        broken = re.search(r"No module named 'vtk|cannot import name .* from 'vtk", out.stderr)
        fixes = ("Fix: reinstall VTK in this Python environment (pip install "
                 "--force-reinstall vtk)." if broken else _FIXES)
        raise RenderingError(
            f"offscreen OpenGL rendering does not work here (probe {status}; VTK says: "
            f"{' / '.join(log) or 'nothing'}). {fixes}")
    return out.stdout.strip()


# ----------------------------------------------------------------------------------------------
# input checks


def preview_arrays(times, positions, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`wiggly.checks.animation_arrays`, also taking one frame as (n, 3) positions."""
    times = np.atleast_1d(np.asarray(times))
    positions = np.asarray(positions)
    if positions.ndim == 2:
        positions = positions[None]
    return animation_arrays(times, positions, faces)


def checked_highlights(highlights: Sequence[Highlight], n: int) -> list[Highlight]:
    """``highlights`` on a surface of ``n`` vertices, checked (:mod:`wiggly.checks`) and with
    plain types: int64 vertex indices, float time and window, a color tuple."""
    out = []
    for i, h in enumerate(highlights):
        if not isinstance(h, Highlight):
            raise WigglyInputError(
                f"highlights[{i}] should be a Highlight; it is {type(h).__name__}")
        where = f"highlights[{i}]" + (f" ({h.label!r})" if h.label else "")
        v = vertex_indices(h.vertices, n, "surface", where)
        color = unit_color(h.color, f"{where}: color")
        time = finite_number(h.time, f"{where}: time")
        window = positive_number(h.window, f"{where}: window", "s")
        until = None
        if h.until is not None:
            until = finite_number(h.until, f"{where}: until")
            if until < time:
                raise WigglyInputError(f"{where}: until = {until:g} s comes before time = "
                                       f"{time:g} s")
        targets = None
        if h.targets is not None:
            targets = array(h.targets, f"{where}: targets", 3)
            bad = np.flatnonzero(~np.isfinite(targets).all(axis=1))
            if len(bad):
                raise WigglyInputError(f"{where}: targets should be finite; target {bad[0]} is "
                                       f"{targets[bad[0]].tolist()}")
        out.append(Highlight(v, time, color, h.label, targets, window, until, bool(h.timed)))
    return out


def output_path(path, suffixes: Sequence[str], overwrite: bool) -> Path:
    """``path`` as a Path, if it ends in one of ``suffixes`` and is not an existing file
    (unless ``overwrite``) or a directory."""
    path = Path(path)
    extension(path, suffixes)
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    if path.is_dir():
        raise WigglyInputError(f"{path} is a directory")
    return path
