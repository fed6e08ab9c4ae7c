"""One offscreen plotter for a whole animation: the camera, the lights, the ground, the
contact shadow and the highlighted groups (:class:`Preview`)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np

from wiggly.checks import pixel_size
from wiggly.errors import WigglyInputError
from wiggly.render.setup import (
    BACKGROUND_BOTTOM,
    BACKGROUND_TOP,
    BASE_COLOR,
    CAMERA_PRESETS,
    GROUND_COLORS,
    SHADOW_STRENGTH,
    TEXT_COLOR,
    Highlight,
    check_offscreen,
    checked_highlights,
    configure_headless,
    preview_arrays,
)

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


def _shifted_pose(camera, origin: np.ndarray):
    """An explicit pose (position, focal_point[, view_up]) in the frame centred on
    ``origin`` (:attr:`Preview.origin`); names and angles as they are."""
    if isinstance(camera, str) or camera is None:
        return camera
    try:
        cam = np.array(camera, dtype=np.float64)
    except (TypeError, ValueError):
        return camera
    if cam.shape not in ((2, 3), (3, 3)):
        return camera
    cam[:2] -= origin
    return cam


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
    clock : bool
        Show the time ("t = 0.25 s") in the corner (False: a preview whose time means
        nothing to its viewer, such as a mode preview's).
    """

    def __init__(self, times, positions, faces, *, highlights: Sequence[Highlight] = (),
                 size=(960, 540), up=(0.0, 1.0, 0.0), ground: bool = True, camera=None,
                 title: str | None = None, anti_aliasing: bool = True, clock: bool = True):
        self.times, positions, self.faces = preview_arrays(times, positions, faces)
        self.clock = clock
        # the scene about the centre of the frames' bounding box: VTK draws in float32, and a
        # body 1e4 m from the origin (a map's coordinates) vanished in its rounding
        self.origin = 0.5 * (positions.min(axis=(0, 1)) + positions.max(axis=(0, 1)))
        self.positions = positions - self.origin.astype(positions.dtype)
        camera = _shifted_pose(camera, self.origin)
        n = self.positions.shape[1]
        self.highlights = checked_highlights(highlights, n)
        self.size = pixel_size(size)
        self.frame = _up_frame(up)
        if os.environ.get("WIGGLY_RENDER_PROBE", "1") != "0":
            check_offscreen()
        configure_headless()
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
                    spheres = pv.PolyData(hl.targets - self.origin).glyph(
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
            when = (f"key t = {hl.time:.2f} s" if hl.until is None else
                    f"t = {hl.time:.2f} s" if hl.until == hl.time else
                    f"t = {hl.time:.2f}-{hl.until:.2f} s")
            actor.SetInput("" if hl.label is None else f"{name}  ({when})" if hl.timed
                           else name)
            actor.SetVisibility(False)
            self._key_labels.append(actor)
        self._label_rows = (margin, round(1.3 * font))  # first row, row height

    # --- per frame ------------------------------------------------------------------------
    def positions_at(self, t: float) -> np.ndarray:
        """Vertex positions at time ``t`` relative to :attr:`origin`: linear between frames,
        clamped to the time range."""
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
            shown = wgt > 0 and hl.label is not None
            label.SetVisibility(shown)
            if shown:  # stack the visible labels from the bottom
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
        self._time_label.SetInput(f"t = {t:.2f} s" if self.clock else "")
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
