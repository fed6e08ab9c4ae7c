"""Offscreen previews of an animated surface: videos, contact sheets, single frames, plots.

Input is plain arrays, as produced by the solver: frame ``times`` (F,), surface vertex
``positions`` (F, n, 3) and triangle ``faces`` (m, 3).  One :class:`Preview` holds one
offscreen pyvista plotter for the whole animation; every frame only updates the mesh in place
(points, per-vertex normals and colors, the contact shadow, the labels) and re-renders, so a
frame costs one draw and one read-back.  :func:`render_video` writes MP4 (H.264, yuv420p,
through the ffmpeg binary shipped in the ``imageio-ffmpeg`` wheel) or GIF (Pillow, one global
palette, loops forever), :func:`render_contact_sheet` a PNG grid of frames,
:func:`render_frame` one image as an array, and :func:`plot_diagnostics` a matplotlib (Agg)
figure of the modal amplitudes and the keyframe residuals.

Scene
-----
The object is drawn with smooth (Phong) shading of area-weighted vertex normals recomputed every
frame, under soft directional key, fill and rim lights placed relative to the view, plus a faint
bounce from below, with FXAA anti-aliasing (default for stills, optional for videos).  A light
grey checkered ground (checker size 1, 2 or 5 x 10^k m, about half the object's size), fading
into the background, lies at the lowest value of the ``up``-coordinate over all frames; a
soft blob shadow under the object (an elliptical Gaussian fitted to the object's footprint,
darker and sharper when the object is close to the ground) shows contact.  The camera is fixed
for the whole animation and frames the bounding box of all frames, so motion is visible; the
default is a 3/4 perspective view with ``up`` up.  A :class:`Highlight` (a keyframed vertex
group) is blended into the vertex colors over ``window`` seconds (0.25 s) around its key time,
fully at the key time, where its target positions also appear as small spheres.  The time is
printed in the upper left corner, the labels of highlighted groups in the lower left.

Headless rendering
------------------
The VTK wheels (9.4 and later) choose the OpenGL window at run time: an X window when a display
is available, otherwise EGL (GPU or Mesa's llvmpipe software rasterizer, no X server needed),
otherwise OSMesa.  On Linux without ``DISPLAY``/``WAYLAND_DISPLAY`` this module sets
``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` (unless already set) so VTK goes to EGL
directly instead of first failing to reach an X server.  When no backend works VTK does not
raise but crashes the process (segmentation fault), so before the first plotter of a process
:func:`check_offscreen` renders one pixel in a *subprocess* and raises :class:`RenderingError`
with the fix if that fails.  Fixes, in order of preference:

* install the Mesa EGL libraries (Debian 12: ``apt-get install libegl1 libgl1-mesa-dri``;
  they pull ``libegl-mesa0``, ``libglvnd0``, ``libgbm1``, ``libglapi-mesa`` and ``libllvm15``;
  the EGL path opens no X11 or libGL library);
* or OSMesa: ``apt-get install libosmesa6`` and
  ``VTK_DEFAULT_OPENGL_WINDOW=vtkOSOpenGLRenderWindow``;
* or a virtual X server: ``apt-get install xvfb libgl1 libglx-mesa0 libxcursor1`` and
  ``pyvista.start_xvfb()`` (or run under ``xvfb-run``).

``PYVISTA_OFF_SCREEN=true`` is not needed (plotters here are always created off-screen).  Set
``WIGGLY_RENDER_PROBE=0`` to skip the subprocess probe (saves about a second per process).

Speed: with software rendering (Mesa llvmpipe on 2 shared cores) a 10k-face object at 960x540
renders at about 20-24 frames/s, or 9-13 with FXAA (which is why videos default to no FXAA);
the per-frame numpy work (normals, colors, shadow) is under 3 ms.  Creating a :class:`Preview`
takes about 0.3 s (plus a second for the first VTK import and the probe).  A GPU through EGL
is much faster.
"""

from __future__ import annotations

import functools
import math
import os
import re
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from wiggly.errors import WigglyInputError
from wiggly.files import atomic_file

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "Highlight",
    "Preview",
    "RenderingError",
    "check_offscreen",
    "plot_diagnostics",
    "render_contact_sheet",
    "render_frame",
    "render_video",
    "video_frame_times",
]

VIDEO_FORMATS = (".mp4", ".gif")
DEFAULT_FPS = 30.0
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
    """A keyframed vertex group, highlighted around its key time.

    Attributes
    ----------
    vertices : (g,) int
        Surface vertex indices of the group.
    time : float
        Key time in seconds.
    color : (3,) float in [0, 1]
        Highlight color; blended into the vertex colors with weight
        ``smoothstep(1 - |t - time| / window)`` (1 at the key time, 0 beyond ``window``).
    label : str
        Shown in the lower left corner while highlighted.
    targets : (k, 3) float or None
        Target positions, drawn as small spheres while highlighted.
    window : float
        Half-width of the highlight in seconds.
    """

    vertices: np.ndarray
    time: float
    color: tuple[float, float, float] = (1.0, 0.35, 0.1)
    label: str = ""
    targets: np.ndarray | None = None
    window: float = HIGHLIGHT_WINDOW

    def weight(self, t: float) -> float:
        """Blend weight of the highlight color at time ``t``: smoothstep, 1 at the key time."""
        s = min(max(1.0 - abs(t - self.time) / self.window, 0.0), 1.0)
        return s * s * (3.0 - 2.0 * s)


# ----------------------------------------------------------------------------------------------
# headless setup


def _configure_headless() -> None:
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
    _configure_headless()
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True,
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
        raise RenderingError(
            f"offscreen OpenGL rendering does not work here (probe {status}; VTK says: "
            f"{' / '.join(log) or 'nothing'}). {_FIXES}")
    return out.stdout.strip()


# ----------------------------------------------------------------------------------------------
# input checks


def _check_animation(times, positions, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    positions = np.asarray(positions)
    if positions.dtype not in (np.float32, np.float64):  # float32 stays: half the memory
        positions = positions.astype(np.float64)
    if positions.ndim == 2:
        positions = positions[None]
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[1] == 0:
        raise WigglyInputError(
            f"positions should have shape (F, n, 3) (or (n, 3) for one frame); shape is "
            f"{positions.shape}")
    if times.ndim != 1 or len(times) != positions.shape[0]:
        raise WigglyInputError(
            f"times should have shape (F,) with F = {positions.shape[0]} frames of positions; "
            f"shape is {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise WigglyInputError("times should be finite and strictly increasing")
    if not np.all(np.isfinite(positions)):
        bad = np.flatnonzero(~np.isfinite(positions).all(axis=(1, 2)))
        raise WigglyInputError(f"positions contain NaN or inf (frames {bad[:5].tolist()})")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise WigglyInputError(
            f"faces should have shape (m, 3) (triangles); shape is {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise WigglyInputError(f"faces should be integer vertex indices; dtype is {faces.dtype}")
    n = positions.shape[1]
    if faces.min() < 0 or faces.max() >= n:
        raise WigglyInputError(
            f"faces index vertices {faces.min()}..{faces.max()}, but positions have {n} vertices")
    return times, positions, faces.astype(np.int64)


def _check_highlights(highlights: Sequence[Highlight], n: int) -> list[Highlight]:
    out = []
    for i, h in enumerate(highlights):
        if not isinstance(h, Highlight):
            raise WigglyInputError(
                f"highlights[{i}] should be a Highlight; it is {type(h).__name__}")
        v = np.asarray(h.vertices)
        if v.ndim != 1 or len(v) == 0 or not np.issubdtype(v.dtype, np.integer):
            raise WigglyInputError(
                f"highlight {i} ({h.label!r}): vertices should be a non-empty 1-d integer array; "
                f"got shape {v.shape}, dtype {v.dtype}")
        if v.min() < 0 or v.max() >= n:
            raise WigglyInputError(
                f"highlight {i} ({h.label!r}): vertex indices {v.min()}..{v.max()} out of range "
                f"for {n} surface vertices")
        color = np.asarray(h.color, dtype=np.float64)
        if color.shape != (3,) or not np.all((color >= 0) & (color <= 1)):
            raise WigglyInputError(
                f"highlight {i} ({h.label!r}): color should be 3 floats in [0, 1]; got {h.color}")
        if not math.isfinite(h.time):
            raise WigglyInputError(f"highlight {i} ({h.label!r}): time should be finite")
        if not h.window > 0:
            raise WigglyInputError(f"highlight {i} ({h.label!r}): window should be > 0 s")
        targets = None
        if h.targets is not None:
            targets = np.asarray(h.targets, dtype=np.float64)
            if targets.ndim != 2 or targets.shape[1] != 3 or not np.all(np.isfinite(targets)):
                raise WigglyInputError(
                    f"highlight {i} ({h.label!r}): targets should be finite with shape (k, 3); "
                    f"shape is {targets.shape}")
        out.append(Highlight(v.astype(np.int64), float(h.time), tuple(color.tolist()), h.label,
                             targets, float(h.window)))
    return out


def _check_size(size, what: str = "size") -> tuple[int, int]:
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError) as e:
        raise WigglyInputError(f"{what} should be (width, height) in pixels; got {size!r}") from e
    if w < 16 or h < 16 or w > 8192 or h > 8192:
        raise WigglyInputError(f"{what} should be between 16 and 8192 pixels per side; got {size}")
    return w, h


def _check_output(path, suffixes: Sequence[str], overwrite: bool) -> Path:
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise WigglyInputError(
            f"{path}: unsupported extension {path.suffix!r}; use one of {', '.join(suffixes)}")
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    if path.is_dir():
        raise WigglyInputError(f"{path} is a directory")
    return path


# ----------------------------------------------------------------------------------------------
# geometry helpers


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _up_frame(up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (right, up, front) with ``front = right x up`` (the viewer's side)."""
    u = np.asarray(up, dtype=np.float64)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) == 0:
        raise WigglyInputError(f"up should be a non-zero 3-vector; got {up!r}")
    u = _unit(u)
    for axis in (np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0])):
        r = axis - (axis @ u) * u
        if np.linalg.norm(r) > 0.3:
            r = _unit(r)
            return r, u, np.cross(r, u)
    raise AssertionError("unreachable")  # pragma: no cover


def _vertex_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (sum of the incident faces' cross products)."""
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    fn = np.cross(b - a, c - a)
    n = len(x)
    idx = faces.ravel()
    out = np.empty((n, 3))
    for k in range(3):
        out[:, k] = np.bincount(idx, weights=np.repeat(fn[:, k], 3), minlength=n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.divide(out, norm, out=np.zeros_like(out), where=norm > 0)


def _grid(pv, k: int, place, frame, level: float):
    """A k x k quad grid in the ground plane: unit square point (a, b) -> ``place((a, b))``.

    Points are row-major in b (the front direction), cell (i, j) is ``j * k + i``.
    """
    right, up, front = frame
    a = np.linspace(0.0, 1.0, k + 1)
    uv = place(np.stack(np.meshgrid(a, a), axis=-1).reshape(-1, 2))
    points = uv[:, :1] * right + uv[:, 1:] * front + level * up
    i, j = np.meshgrid(np.arange(k), np.arange(k))
    p0 = (j * (k + 1) + i).ravel()
    quads = np.column_stack([np.full(k * k, 4), p0, p0 + 1, p0 + k + 2, p0 + k + 1])
    return pv.PolyData(points, quads.ravel())


def _nice(x: float) -> float:
    """The number 1, 2 or 5 times a power of ten closest below ``x`` (grid spacings)."""
    e = math.floor(math.log10(x))
    m = x / 10**e
    return (5 if m >= 5 else 2 if m >= 2 else 1) * 10.0**e


def _camera_pose(camera, lo, hi, frame, aspect: float, view_angle: float):
    """(position, focal_point, view_up) for a preset name, (azimuth, elevation) or explicit pose."""
    right, up, front = frame
    if camera is None:
        camera = "three_quarter"
    if isinstance(camera, str):
        if camera not in CAMERA_PRESETS:
            raise WigglyInputError(
                f"unknown camera {camera!r}; use one of {', '.join(CAMERA_PRESETS)}, "
                f"(azimuth, elevation) in degrees, or (position, focal_point[, view_up])")
        camera = CAMERA_PRESETS[camera]
    try:
        cam = np.asarray(camera, dtype=np.float64)
    except (TypeError, ValueError):
        cam = np.array([])
    center = 0.5 * (lo + hi)
    if cam.shape == (2,):
        az, el = np.radians(cam)
        d = np.cos(el) * (np.cos(az) * front + np.sin(az) * right) + np.sin(el) * up
        view_up = up - (up @ d) * d
        view_up = _unit(view_up) if np.linalg.norm(view_up) > 1e-3 else -front
        cam_right = np.cross(-d, view_up)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) - center
        cx, cy, cz = corners @ cam_right, corners @ view_up, corners @ d
        tv = math.tan(math.radians(view_angle) / 2) * 0.92
        th = tv * aspect
        dist = max(np.max(cz + np.abs(cx) / th), np.max(cz + np.abs(cy) / tv))
        dist = max(dist, 1.05 * np.max(cz), 1e-3)  # outside the box, even a degenerate one
        return center + dist * d, center, view_up
    if cam.shape in ((2, 3), (3, 3)) and np.all(np.isfinite(cam)):
        position, focal = cam[0], cam[1]
        view_up = cam[2] if len(cam) == 3 else up
        if np.linalg.norm(position - focal) == 0:
            raise WigglyInputError("camera position and focal point coincide")
        return position, focal, view_up
    raise WigglyInputError(
        f"camera should be one of {', '.join(CAMERA_PRESETS)}, (azimuth, elevation) in degrees, "
        f"or (position, focal_point[, view_up]); got {camera!r}")


# ----------------------------------------------------------------------------------------------
# the scene


class Preview:
    """One offscreen scene of an animated surface, re-rendered at any time.

    The plotter, camera, lights and ground are built once; :meth:`render` moves the mesh to
    the positions at time ``t`` (linear interpolation between frames), updates normals, colors,
    shadow and labels, and returns the image.  Use as a context manager or call :meth:`close`.

    Parameters
    ----------
    times : (F,) float
        Frame times in seconds, strictly increasing.
    positions : (F, n, 3) float
        Surface vertex positions per frame (``(n, 3)`` for a single frame).
    faces : (m, 3) int
        Triangles.
    highlights : sequence of Highlight
        Keyframed vertex groups to highlight around their key times.
    size : (width, height)
        Image size in pixels.
    up : (3,) float
        World up direction (ground normal and the camera's up).
    ground : bool
        Draw the checkered ground plane and the contact shadow.
    camera : str, (azimuth, elevation) or (position, focal_point[, view_up]), optional
        A name in :data:`CAMERA_PRESETS` (default ``"three_quarter"``), angles in degrees (the
        view is fitted to the bounding box of all frames), or an explicit pose.
    title : str, optional
        Printed at the top of every frame.
    anti_aliasing : bool
        FXAA, a screen-space pass: smooth silhouettes, but about half the frame rate with
        software rendering (llvmpipe).
    """

    def __init__(self, times, positions, faces, *, highlights: Sequence[Highlight] = (),
                 size=(960, 540), up=(0.0, 1.0, 0.0), ground: bool = True, camera=None,
                 title: str | None = None, anti_aliasing: bool = True):
        self.times, self.positions, self.faces = _check_animation(times, positions, faces)
        n = self.positions.shape[1]
        self.highlights = _check_highlights(highlights, n)
        self.size = _check_size(size)
        self.frame = _up_frame(up)
        if os.environ.get("WIGGLY_RENDER_PROBE", "1") != "0":
            check_offscreen()
        _configure_headless()
        import pyvista as pv  # deferred: importing VTK takes a second

        upv = self.frame[1]
        lo = self.positions.min(axis=(0, 1))
        hi = self.positions.max(axis=(0, 1))
        first = self.positions[0]
        self.scale = float(np.linalg.norm(first.max(axis=0) - first.min(axis=0))) or 1.0
        w, h = self.size

        position, focal, view_up = _camera_pose(camera, lo, hi, self.frame, w / h, 30.0)

        theme = pv.themes.DocumentTheme()
        theme.multi_samples = 0  # MSAA costs 3x with software rendering; FXAA instead
        self.plotter = pl = pv.Plotter(off_screen=True, window_size=(w, h), lighting="none",
                                       theme=theme)
        try:
            pl.set_background(BACKGROUND_BOTTOM, top=BACKGROUND_TOP)
            self._mesh = pv.PolyData(
                first.copy(), np.column_stack([np.full(len(self.faces), 3), self.faces]).ravel())
            self._normals = np.zeros((n, 3))
            self._mesh.point_data["Normals"] = self._normals
            self._mesh.point_data.active_normals_name = "Normals"
            self._normals = self._mesh.point_data["Normals"]  # the VTK-backed buffer
            base = np.asarray(BASE_COLOR)
            self._base_rgb = np.broadcast_to(base, (n, 3))
            self._mesh.point_data["rgb"] = np.zeros((n, 3), dtype=np.uint8)
            self._rgb = self._mesh.point_data["rgb"]
            actor = pl.add_mesh(self._mesh, scalars="rgb", rgb=True, ambient=0.22, diffuse=0.78,
                                specular=0.18, specular_power=24.0, show_scalar_bar=False,
                                reset_camera=False)
            actor.GetProperty().SetInterpolationToPhong()  # our per-frame normals, per pixel
            self._targets = []
            for hl in self.highlights:
                actor = None
                if hl.targets is not None:
                    radius = 0.012 * self.scale
                    spheres = pv.PolyData(hl.targets).glyph(
                        geom=pv.Sphere(radius=radius, theta_resolution=16, phi_resolution=12),
                        scale=False, orient=False)
                    color = 0.75 * np.asarray(hl.color)
                    actor = pl.add_mesh(spheres, color=color, ambient=0.3, specular=0.4,
                                        reset_camera=False)
                    actor.SetVisibility(False)
                self._targets.append(actor)

            pl.camera.view_angle = 30.0
            pl.camera_position = [tuple(position), tuple(focal), tuple(view_up)]
            self._ground_level = float(np.min(self.positions @ upv)) - 1e-3 * self.scale
            self._ground = self._shadow = None
            if ground:
                self._build_ground(pv, lo, hi)
            pl.renderer.ResetCameraClippingRange()
            self._add_lights(pv, np.asarray(position), np.asarray(focal), np.asarray(view_up))
            self._add_labels(title)
            if anti_aliasing:
                pl.renderer.SetUseFXAA(True)
        except BaseException:
            pl.close()
            raise

    # --- construction ---------------------------------------------------------------------
    def _build_ground(self, pv, lo, hi) -> None:
        """Checkered ground fading out with distance, and the blob shadow above it."""
        right, upv, front = self.frame
        center = np.array([0.5 * (lo + hi) @ right, 0.5 * (lo + hi) @ front])
        radius = max(1.5 * np.linalg.norm(hi - lo), 4.0 * self.scale)
        checker = max(_nice(self.scale / 2.0), _nice(radius / 25))  # <= 100 squares per side
        squares = 2 * math.ceil(radius / checker)
        sub = max(1, min(4, 220 // squares))  # cells per square side, for a smooth fade
        m = squares * sub
        corner = np.floor(center / checker) * checker - squares // 2 * checker
        self._ground = _grid(pv, m, lambda uv: corner + uv * (squares * checker), self.frame,
                             self._ground_level)
        cells = (np.arange(m) + 0.5) / sub  # cell centres in checker units
        cu, cv = np.meshgrid(cells, cells)
        parity = ((np.floor(cu) + np.floor(cv)) % 2).ravel().astype(int)
        uv = corner + checker * np.column_stack([cu.ravel(), cv.ravel()])
        s = np.clip((np.linalg.norm(uv - center, axis=1) / radius - 0.3) / 0.7, 0, 1)
        fade = (s * s * (3 - 2 * s))[:, None]
        # Fade (opaque: translucency costs a third of the frame rate in software) into the
        # background seen behind each cell: the vertical gradient at the cell's screen height.
        y = self._screen_height(uv[:, :1] * right + uv[:, 1:] * front + self._ground_level * upv)
        behind = (1 - y) * np.asarray(BACKGROUND_BOTTOM) + y * np.asarray(BACKGROUND_TOP)
        rgb = (1 - fade) * np.asarray(GROUND_COLORS)[parity] + fade * behind
        self._ground.cell_data["rgb"] = np.round(255 * rgb).astype(np.uint8)
        self.plotter.add_mesh(self._ground, scalars="rgb", rgb=True, lighting=False,
                              show_scalar_bar=False, reset_camera=False)

        # blob shadow: a grid of 32 x 32 quads with per-vertex alpha, moved every frame
        self._shadow = _grid(pv, 32, lambda uv: uv, self.frame, 0.0)
        a = np.linspace(-1.0, 1.0, 33)
        self._shadow_grid = np.stack(np.meshgrid(a, a), axis=-1).reshape(-1, 2)
        self._shadow.point_data["rgba"] = np.zeros((33 * 33, 4), dtype=np.uint8)
        self._shadow_rgba = self._shadow.point_data["rgba"]
        self.plotter.add_mesh(self._shadow, scalars="rgba", rgba=True, lighting=False,
                              show_scalar_bar=False, reset_camera=False)

    def _screen_height(self, points: np.ndarray) -> np.ndarray:
        """Height of ``points`` on the image as (k, 1): 0 at the bottom, 1 at the top (clamped)."""
        w, h = self.size
        M = self.plotter.camera.GetCompositeProjectionTransformMatrix(w / h, -1, 1)
        M = np.array([[M.GetElement(i, j) for j in range(4)] for i in range(4)])
        clip = np.column_stack([points, np.ones(len(points))]) @ M.T
        y = clip[:, 1] / np.maximum(clip[:, 3], 1e-12)
        return np.clip(0.5 * (y + 1), 0, 1)[:, None]

    def _add_lights(self, pv, position, focal, view_up) -> None:
        """Key (warm, upper right), fill (cool, left), rim (behind) and a faint bounce light."""
        d = _unit(position - focal)
        vr = _unit(np.cross(view_up, d))  # camera right
        vu = np.cross(d, vr)
        lights = [  # (direction towards the light in camera coordinates, color, intensity)
            ((0.8, 1.0, 0.9), (1.0, 0.97, 0.92), 0.80),
            ((-1.0, 0.2, 0.7), (0.88, 0.92, 1.0), 0.35),
            ((-0.3, 0.8, -1.0), (1.0, 1.0, 1.0), 0.45),
            ((0.0, -1.0, 0.3), (0.95, 0.93, 0.9), 0.15),  # bounce from the ground
        ]
        for (a, b, c), color, intensity in lights:
            direction = _unit(a * vr + b * vu + c * d)
            self.plotter.add_light(pv.Light(
                position=tuple(focal + direction), focal_point=tuple(focal), color=color,
                intensity=intensity, light_type="scene light"))

    def _add_labels(self, title: str | None) -> None:
        from vtkmodules.vtkRenderingCore import vtkTextActor

        w, h = self.size
        font = max(12, round(h / 30))
        margin = max(6, round(h / 45))

        def text(position, justify="left", valign="top", bold=False, color=TEXT_COLOR, size=font):
            actor = vtkTextActor()
            prop = actor.GetTextProperty()
            prop.SetFontSize(size)
            prop.SetColor(*color)
            prop.SetFontFamilyToArial()
            prop.SetBold(bold)
            getattr(prop, f"SetJustificationTo{justify.capitalize()}")()
            getattr(prop, f"SetVerticalJustificationTo{valign.capitalize()}")()
            actor.SetDisplayPosition(*position)
            self.plotter.renderer.AddViewProp(actor)
            return actor

        self._time_label = text((margin, h - margin), bold=True)
        if title:
            text((w - margin, h - margin), justify="right").SetInput(title)
        self._key_labels = []
        for k, hl in enumerate(self.highlights):
            actor = text((margin, margin), valign="bottom",
                         color=tuple(0.8 * np.asarray(hl.color)), bold=True)
            name = hl.label or f"keyframe {k + 1}"
            actor.SetInput(f"{name}  (key t = {hl.time:.2f} s)")
            actor.SetVisibility(False)
            self._key_labels.append(actor)
        self._label_rows = (margin, round(1.3 * font))  # first row, row height

    # --- per frame ------------------------------------------------------------------------
    def positions_at(self, t: float) -> np.ndarray:
        """Vertex positions at time ``t``: linear between frames, clamped to the time range."""
        times, X = self.times, self.positions
        if len(times) == 1 or t <= times[0]:
            return X[0]
        if t >= times[-1]:
            return X[-1]
        k = int(np.searchsorted(times, t, side="right")) - 1
        a = (t - times[k]) / (times[k + 1] - times[k])
        return X[k] if a == 0 else (1 - a) * X[k] + a * X[k + 1]

    def render(self, t: float) -> np.ndarray:
        """The image at time ``t`` (s): (height, width, 3) uint8."""
        t = float(t)
        x = self.positions_at(t)
        self._mesh.points[:] = x
        self._mesh.GetPoints().Modified()
        self._normals[:] = _vertex_normals(x, self.faces)
        self._normals.VTKObject.Modified()

        colors = np.array(self._base_rgb)
        row = 0
        for hl, spheres, label in zip(self.highlights, self._targets, self._key_labels,
                                      strict=True):
            wgt = hl.weight(t)
            if wgt > 0:
                colors[hl.vertices] = (1 - wgt) * colors[hl.vertices] + wgt * np.asarray(hl.color)
            label.SetVisibility(wgt > 0)
            if wgt > 0:  # stack the visible labels from the bottom
                first, height = self._label_rows
                label.SetDisplayPosition(first, first + row * height)
                row += 1
            label.GetTextProperty().SetOpacity(min(1.0, 0.4 + 2 * wgt))
            if spheres is not None:
                spheres.SetVisibility(wgt > 0)
                spheres.GetProperty().SetOpacity(min(1.0, 1.5 * wgt))
        self._rgb[:] = np.round(255 * colors).astype(np.uint8)
        self._rgb.VTKObject.Modified()

        if self._ground is not None:
            self._update_shadow(x)
        self._time_label.SetInput(f"t = {t:.2f} s")
        return self._grab()

    def _update_shadow(self, x: np.ndarray) -> None:
        """Move the blob shadow: a Gaussian fitted to the object's footprint on the ground.

        The footprint's covariance (of the vertices projected on the ground) is widened by a
        blur growing with the height of the lowest point, and the darkness falls off with it.
        """
        right, upv, front = self.frame
        p2 = np.column_stack([x @ right, x @ front])
        height = max(float(np.min(x @ upv)) - self._ground_level, 0.0)
        center = p2.mean(axis=0)
        blur = 0.05 * self.scale + 0.4 * height
        cov = 1.5 * np.cov(p2.T) + blur**2 * np.eye(2)
        half = 3.0 * math.sqrt(np.linalg.eigvalsh(cov)[-1])
        uv = center + half * self._shadow_grid
        self._shadow.points[:] = (uv[:, :1] * right + uv[:, 1:] * front
                                  + (self._ground_level + 1e-3 * self.scale) * upv)
        self._shadow.GetPoints().Modified()
        d = uv - center
        m2 = np.einsum("ij,jk,ik->i", d, np.linalg.inv(cov), d)
        strength = SHADOW_STRENGTH * math.exp(-height / (0.6 * self.scale))
        self._shadow_rgba[:, 3] = np.round(255 * strength * np.exp(-0.5 * m2))
        self._shadow_rgba.VTKObject.Modified()

    def _grab(self) -> np.ndarray:
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkCommonCore import vtkUnsignedCharArray

        window = self.plotter.render_window
        window.Render()
        w, h = self.size
        buf = vtkUnsignedCharArray()
        window.GetPixelData(0, 0, w - 1, h - 1, 0, buf, 0)
        return vtk_to_numpy(buf).reshape(h, w, 3)[::-1].copy()

    def close(self) -> None:
        """Release the plotter and its OpenGL context."""
        self.plotter.close()

    def __enter__(self) -> Preview:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ----------------------------------------------------------------------------------------------
# public entry points


def render_frame(times_or_time, positions, faces, *, at: float | None = None,
                 highlights: Sequence[Highlight] = (), size=(960, 540), up=(0.0, 1.0, 0.0),
                 ground: bool = True, camera=None, title: str | None = None,
                 anti_aliasing: bool = True) -> np.ndarray:
    """Render one image of the animation: (height, width, 3) uint8.

    Either a single pose, ``render_frame(time, positions (n, 3), faces)``, or a frame of an
    animation, ``render_frame(times (F,), positions (F, n, 3), faces, at=t)`` (default: the
    first frame).  The camera frames all frames, as in a video of the animation, so images at
    different times are comparable.  Other parameters as in :class:`Preview`.  Builds a new
    plotter per call (about 0.3 s); to render many frames use :class:`Preview` directly.
    """
    times = np.atleast_1d(np.asarray(times_or_time, dtype=np.float64))
    with Preview(times, positions, faces, highlights=highlights, size=size, up=up, ground=ground,
                 camera=camera, title=title, anti_aliasing=anti_aliasing) as preview:
        return preview.render(preview.times[0] if at is None else at)


def video_frame_times(times, fps: float | None = None,
                      max_fps: float | None = None) -> tuple[np.ndarray, float]:
    """Frame times of a video of an animation sampled at ``times``, and its frame rate.

    Without ``fps``, uniformly spaced ``times`` (spacing equal within 1e-6 relative) are used
    as they are, at ``fps = 1 / dt``.  Otherwise (or when that exceeds ``max_fps``) the video
    samples ``t0 + k / fps`` for ``k = 0 .. floor((t_end - t0) fps)``, with ``fps`` the given
    rate (default :data:`DEFAULT_FPS`) capped at ``max_fps``.
    """
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if times.ndim != 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise WigglyInputError("times should be a 1-d array, finite and strictly increasing")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise WigglyInputError(f"fps should be a positive number; got {fps}")
    if fps is None and len(times) > 1:
        dt = np.diff(times)
        native = 1.0 / dt.mean()
        if np.ptp(dt) <= 1e-6 * dt.mean() and (max_fps is None or native <= max_fps * (1 + 1e-9)):
            return times.copy(), float(native)
    if len(times) == 1:
        return times.copy(), float(fps or DEFAULT_FPS)
    rate = float(fps or DEFAULT_FPS)
    if max_fps is not None:
        rate = min(rate, max_fps)
    count = math.floor((times[-1] - times[0]) * rate + 1e-9) + 1
    return times[0] + np.arange(count) / rate, rate


def _scene_progress(frames, enabled: bool, what: str):
    return tqdm(frames, total=len(frames), disable=not enabled, file=sys.stderr, unit="frame",
                desc=what)


def render_video(path, times, positions, faces, *, highlights: Sequence[Highlight] = (),
                 fps: float | None = None, size=(960, 540), up=(0.0, 1.0, 0.0),
                 ground: bool = True, camera=None, title: str | None = None,
                 anti_aliasing: bool = False, progress: bool = False,
                 overwrite: bool = False) -> Path:
    """Render the animation to an ``.mp4`` or ``.gif`` video; return the path.

    ``anti_aliasing`` (FXAA) is off by default here: with software rendering it halves the
    frame rate (about 10 instead of 20 frames/s for 10k faces at 960x540 on 2 cores).

    Frame times follow :func:`video_frame_times`.  MP4: H.264, yuv420p, constant quality (CRF
    :data:`MP4_CRF`), ``+faststart``; an odd width or height is reduced by one pixel (yuv420p
    needs even sizes).  GIF: frame delays are whole centiseconds, so the rate is
    ``100 / round(100 / fps)`` with fps capped at :data:`GIF_MAX_FPS`; frames are rendered at
    ``size`` and downscaled (Lanczos, which anti-aliases too: no FXAA then) to at most
    :data:`GIF_MAX_SIDE` pixels per side; one 256-color palette for all frames; loops forever.
    Written atomically (temporary file in the same directory, then :func:`os.replace`); an
    existing ``path`` is kept unless ``overwrite``.  Scene parameters as in :class:`Preview`;
    ``progress`` shows a progress bar on stderr.
    """
    path = _check_output(path, VIDEO_FORMATS, overwrite)
    w, h = _check_size(size)
    gif = path.suffix.lower() == ".gif"
    if gif:
        anti_aliasing = anti_aliasing and GIF_MAX_SIDE / max(w, h) > 0.67
    else:
        w, h = w - w % 2, h - h % 2
    with Preview(times, positions, faces, highlights=highlights, size=(w, h), up=up,
                 ground=ground, camera=camera, title=title,
                 anti_aliasing=anti_aliasing) as preview:
        if gif:
            requested = fps if fps is not None else video_frame_times(preview.times)[1]
            delay_cs = max(round(100 / GIF_MAX_FPS), round(100 / requested))
            frame_times, _ = video_frame_times(preview.times, 100 / delay_cs)
        else:
            frame_times, rate = video_frame_times(preview.times, fps)
        frames = _scene_progress(frame_times, progress, path.name)
        with atomic_file(path) as tmp:
            if gif:
                _write_gif(tmp, preview, frame_times, frames, delay_cs)
            else:
                _write_mp4(tmp, preview, frames, rate)
    return path


def _write_mp4(tmp: Path, preview: Preview, frames, fps: float) -> None:
    import imageio_ffmpeg

    w, h = preview.size
    writer = imageio_ffmpeg.write_frames(
        str(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
        quality=None, macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-crf", str(MP4_CRF), "-preset", "veryfast", "-movflags", "+faststart"])
    writer.send(None)  # start ffmpeg
    try:
        for t in frames:
            writer.send(preview.render(t))
    finally:
        writer.close()


def _write_gif(tmp: Path, preview: Preview, frame_times: np.ndarray, frames, delay_cs: int) -> None:
    from PIL import Image

    w, h = preview.size
    scale = min(1.0, GIF_MAX_SIDE / max(w, h))
    out_size = (max(1, round(w * scale)), max(1, round(h * scale)))

    def image(t: float) -> Image.Image:
        im = Image.fromarray(preview.render(t))
        return im if out_size == (w, h) else im.resize(out_size, Image.Resampling.LANCZOS)

    # one palette for all frames, from a few samples including the highlighted key times
    t0, t1 = frame_times[0], frame_times[-1]
    samples = list(np.linspace(t0, t1, 5)) + [hl.time for hl in preview.highlights
                                             if t0 <= hl.time <= t1]
    palette = _gif_palette([image(t) for t in samples])

    def quantized() -> Iterator[Image.Image]:
        for t in frames:
            yield image(t).quantize(palette=palette, dither=Image.Dither.NONE)

    it = quantized()
    first = next(it)
    # Pillow stores each frame cropped to where it differs from the previous one
    first.save(tmp, format="GIF", save_all=True, append_images=it, duration=10 * delay_cs, loop=0)


def _gif_palette(images) -> Image.Image:
    """A 256-color palette image: median cut of the *distinct* colors of ``images``.

    Median cut of all pixels spends the palette on the large smooth background and leaves
    the object (and the few highlight-colored pixels) banded or grey; cutting the set of
    distinct colors gives every region colors in proportion to its tonal range instead.
    """
    from PIL import Image

    distinct = np.unique(np.concatenate([np.asarray(im).reshape(-1, 3) for im in images]), axis=0)
    return Image.fromarray(distinct[None]).quantize(256, method=Image.Quantize.MEDIANCUT)


def render_contact_sheet(path, times, positions, faces, *, n_frames: int = 8, columns: int = 4,
                         at: Sequence[float] | None = None,
                         highlights: Sequence[Highlight] = (), tile_size=(480, 270),
                         up=(0.0, 1.0, 0.0), ground: bool = True, camera=None,
                         title: str | None = None, anti_aliasing: bool = True,
                         progress: bool = False, overwrite: bool = False) -> Path:
    """A PNG grid of frames (each with its time label), row by row; return the path.

    The frames are at ``n_frames`` evenly spaced times from the first to the last (or at the
    times ``at``, e.g. the key times).  With ``N`` frames, ``c = min(columns, N)`` columns and
    ``rows = ceil(N / c)``, the image is ``c * tile_w + (c + 1) * SHEET_GAP`` pixels wide and
    ``rows * tile_h + (rows + 1) * SHEET_GAP`` (plus :data:`SHEET_HEADER` with a ``title``)
    high.  Written atomically; an existing ``path`` is kept unless ``overwrite``.
    """
    path = _check_output(path, (".png",), overwrite)
    tw, th = _check_size(tile_size, "tile_size")
    times, positions, faces = _check_animation(times, positions, faces)
    if at is None:
        if not (isinstance(n_frames, int | np.integer) and n_frames >= 1):
            raise WigglyInputError(f"n_frames should be an integer >= 1; got {n_frames!r}")
        sheet_times = np.linspace(times[0], times[-1], n_frames)
    else:
        sheet_times = np.atleast_1d(np.asarray(at, dtype=np.float64))
        if sheet_times.ndim != 1 or len(sheet_times) == 0 or not np.all(np.isfinite(sheet_times)):
            raise WigglyInputError(f"at should be a non-empty list of finite times; got {at!r}")
    if not (isinstance(columns, int | np.integer) and columns >= 1):
        raise WigglyInputError(f"columns should be an integer >= 1; got {columns!r}")
    count = len(sheet_times)
    cols = min(columns, count)
    rows = -(-count // cols)
    gap = SHEET_GAP
    header = SHEET_HEADER if title else 0
    sheet = np.full((header + rows * th + (rows + 1) * gap, cols * tw + (cols + 1) * gap, 3), 250,
                    dtype=np.uint8)
    with Preview(times, positions, faces, highlights=highlights, size=(tw, th), up=up,
                 ground=ground, camera=camera, anti_aliasing=anti_aliasing) as preview:
        for k, t in enumerate(_scene_progress(sheet_times, progress, path.name)):
            r, c = divmod(k, cols)
            y, x = header + gap + r * (th + gap), gap + c * (tw + gap)
            sheet[y:y + th, x:x + tw] = preview.render(t)
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(sheet)
    if title:
        font = ImageFont.load_default(size=round(0.55 * header))
        ImageDraw.Draw(image).text((gap + 4, header / 2 + gap / 2), title, anchor="lm",
                                   fill=tuple(round(255 * c) for c in TEXT_COLOR), font=font)
    with atomic_file(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)
    return path


def plot_diagnostics(path, times, modal, residuals: Sequence[dict], eigenvalues, *,
                     n_rigid: int | None = None, title: str | None = None, max_labeled: int = 8,
                     size=(10.0, 7.5), dpi: int = 110, overwrite: bool = False) -> Path:
    """A PNG of the solve: modal amplitudes over time and keyframe residuals; return the path.

    Three panels over a shared time axis: the rigid modes' amplitudes ``q_i(t)`` (eigenvalue 0,
    the first ``n_rigid``; default: the count of eigenvalues <= 1e-12 max |lambda|), the
    elastic modes' amplitudes labeled with their frequency ``sqrt(lambda) / (2 pi)`` (the lowest
    ``max_labeled`` in color, the others thin grey), and per keyframe (``residuals``: dicts with
    ``time``, ``name`` and optional ``position_rms`` (m), ``position_max`` (m), ``velocity_rms``
    (m/s), as from ``Animation.constraint_residuals()``) bars of the RMS position error (mm) and,
    on a second axis, the RMS velocity error (mm/s) at the key times; the maximum position
    error is a dot.  Key times are dashed lines in every panel.  Written atomically.
    """
    path = _check_output(path, (".png",), overwrite)
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    modal = np.asarray(modal, dtype=np.float64)
    lam = np.atleast_1d(np.asarray(eigenvalues, dtype=np.float64))
    if modal.ndim != 2 or modal.shape[0] != len(times):
        raise WigglyInputError(
            f"modal should have shape (F, r) with F = {len(times)} times; shape is {modal.shape}")
    if lam.shape != (modal.shape[1],):
        raise WigglyInputError(
            f"eigenvalues should have shape ({modal.shape[1]},) (one per mode); shape is "
            f"{lam.shape}")
    if n_rigid is None:
        n_rigid = int(np.sum(np.abs(lam) <= 1e-12 * max(np.max(np.abs(lam)), 1.0)))
    if not 0 <= n_rigid <= len(lam):
        raise WigglyInputError(f"n_rigid should be in 0..{len(lam)}; got {n_rigid}")
    for k, row in enumerate(residuals):
        if not isinstance(row, dict) or "time" not in row:
            raise WigglyInputError(
                f"residuals[{k}] should be a dict with a 'time' key; got {row!r}")

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True, height_ratios=(1, 1.4, 1))
    ax_rigid, ax_elastic, ax_res = axes
    key_times = [float(row["time"]) for row in residuals]
    for ax in axes:
        for t in key_times:
            ax.axvline(t, color="0.35", lw=0.9, ls=(0, (4, 3)), zorder=1.5)
        ax.grid(True, color="0.92", zorder=0)
        ax.axhline(0, color="0.6", lw=0.6)

    # a free body's rigid modes are the translations, then rotations (M-orthonormalized)
    rigid_names = ["tx", "ty", "tz", "rot 1", "rot 2", "rot 3"] if n_rigid == 6 else None
    for i in range(n_rigid):
        name = rigid_names[i] if rigid_names else f"rigid {i + 1}"
        ax_rigid.plot(times, modal[:, i], lw=1.5, label=name)
    ax_rigid.set_ylabel("rigid modes\nq (kg$^{1/2}$ m)")
    if n_rigid:
        ax_rigid.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small",
                        frameon=False)
    else:
        ax_rigid.text(0.5, 0.5, "no rigid modes (the body is fixed)", transform=ax_rigid.transAxes,
                      ha="center", va="center", color="0.4")

    freq = np.sqrt(np.maximum(lam, 0)) / (2 * np.pi)
    cmap = __import__("matplotlib").colormaps["viridis"]
    n_el = len(lam) - n_rigid
    for j, i in enumerate(range(n_rigid, len(lam))):
        if j < max_labeled:
            ax_elastic.plot(times, modal[:, i], lw=1.4, color=cmap(j / max(1, min(n_el,
                            max_labeled) - 1) * 0.9), label=f"mode {i + 1}: {freq[i]:.3g} Hz")
        else:
            ax_elastic.plot(times, modal[:, i], lw=0.7, color="0.7",
                            label=f"modes {max_labeled + n_rigid + 1}..{len(lam)}"
                            if j == max_labeled else None)
    ax_elastic.set_ylabel("elastic modes\nq (kg$^{1/2}$ m)")
    if n_el:
        ax_elastic.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small",
                          frameon=False)

    span = float(times[-1] - times[0]) if len(times) > 1 else 1.0
    width = 0.012 * span
    pos = [(row["time"], 1e3 * row["position_rms"], 1e3 * row.get("position_max", np.nan))
           for row in residuals if row.get("position_rms") is not None]
    vel = [(row["time"], 1e3 * row["velocity_rms"]) for row in residuals
           if row.get("velocity_rms") is not None]
    if pos:
        t, rms, mx = map(np.asarray, zip(*pos, strict=True))
        ax_res.bar(t - width / 2, rms, width, color="#d95f02", label="position RMS")
        ax_res.plot(t - width / 2, mx, "o", ms=4, color="#7f2704", label="position max")
    ax_res.set_ylabel("position error (mm)")
    ax_res.set_ylim(bottom=0)
    ax_vel = ax_res.twinx()
    if vel:
        t, rms = map(np.asarray, zip(*vel, strict=True))
        ax_vel.bar(t + width / 2, rms, width, color="#1b9e77", hatch="//", edgecolor="white",
                   label="velocity RMS")
    ax_vel.set_ylabel("velocity error (mm/s)")
    ax_vel.set_ylim(bottom=0)
    handles = ax_res.get_legend_handles_labels()
    handles2 = ax_vel.get_legend_handles_labels()
    if handles[0] or handles2[0]:
        ax_res.legend(handles[0] + handles2[0], handles[1] + handles2[1], loc="upper left",
                      fontsize="small", frameon=False, ncols=3)
    else:
        ax_res.text(0.5, 0.5, "no keyframes", transform=ax_res.transAxes, ha="center",
                    va="center", color="0.4")
    for ax in (ax_res, ax_vel):  # headroom for the legend
        top = ax.get_ylim()[1]
        ax.set_ylim(0, 1.35 * top)
    ax_res.set_xlabel("time (s)")
    if len(times) > 1:
        ax_res.set_xlim(times[0], times[-1])
    if residuals:  # keyframe names on top, over their dashed lines through all panels
        names = ax_rigid.secondary_xaxis("top")
        names.set_xticks(key_times, [str(row.get("name", "")) for row in residuals],
                         fontsize="small", color="0.25")
        names.tick_params(length=3)
    if title:
        fig.suptitle(title)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
