"""The exported animation (:class:`SurfaceAnimation`), its checks, and per-frame normals."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from wiggly.checks import animation_arrays, real_array
from wiggly.errors import WigglyInputError
from wiggly.files import shown_name
from wiggly.progress import frames

#: Output formats by file extension.
SUPPORTED = {
    ".glb": "glTF 2.0 binary, one morph target per frame and a weights animation",
    ".gltf": "glTF 2.0 as JSON, the .glb's data embedded (base64, a third larger)",
    ".usd": "Universal Scene Description (binary crate), time-sampled points",
    ".usda": "Universal Scene Description (text), time-sampled points",
    ".usdc": "Universal Scene Description (binary crate), time-sampled points",
    ".obj": "OBJ sequence: name.obj writes name_0000.obj, name_0001.obj, ...",
    ".npz": "compressed numpy archive (times, positions, faces, uvs, normals)",
}

#: The glTF formats (binary, and JSON with its data embedded).
GLTF = (".glb", ".gltf")
#: glTF morph target layouts: one target per frame, or one per mode (linear motions).
GLTF_TARGETS = ("frames", "modes")
#: Version of the npz layout and of the glTF extras written here.
FORMAT_VERSION = 1
#: OBJ number format of positions: 9 significant digits reproduce float32 values exactly.
POSITION_FORMAT = "%.9g"
#: Frame rate assumed for an OBJ sequence without ``# time`` comments.
OBJ_DEFAULT_FPS = 30.0
#: Normal of a vertex that belongs to no triangle of positive area (and has no rest normal).
FALLBACK_NORMAL = (0.0, 1.0, 0.0)


@dataclass
class SurfaceAnimation:
    """An animated triangle surface: what every export format stores.

    Attributes
    ----------
    times : (F,) float array
        Frame times in seconds, strictly increasing.
    positions : (F, n, 3) float array
        Vertex positions per frame (float32 or float64), in metres.
    faces : (k, 3) int array
        Triangles, counter-clockwise seen from outside, indices into the n vertices.
    uvs : (n, 2) float array or None
        Per-vertex texture coordinates, origin at the bottom-left (OBJ/USD convention).
    normals : (n, 3) float array or None
        Rest normals from the user's file; per-frame normals are recomputed.
    name : str
        Object name (glTF mesh/node name, USD prim names, OBJ ``o`` line).
    rest : (n, 3) float array or None
        The rest positions: the glTF base mesh (Blender's ``Basis`` shape key), with every
        frame a morph target relative to it.  None: frame 0 is the base.
    mode_shapes : float array or None
        Shape (r, n, 3).  For a linear motion,
        ``positions[k] = rest + sum_i modal[k, i] * mode_shapes[i]`` (the modes on the
        surface): the compact glTF layout (``gltf_targets="modes"``).
    modal : float array or None
        Shape (F, r): the modal coordinates q(t) of every frame, with ``mode_shapes``.
    loop : bool
        A cycle whose last frame is its first: glTF keeps that frame (a time-based player
        then wraps between identical poses), USD and OBJ sequences leave it out (a frame-based
        player steps from the last frame to the first).
    """

    times: np.ndarray
    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    name: str = "wiggly"
    rest: np.ndarray | None = None
    mode_shapes: np.ndarray | None = None
    modal: np.ndarray | None = None
    loop: bool = False

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def n_vertices(self) -> int:
        return self.positions.shape[1]



# ----------------------------------------------------------------------------------------------
# validation and normals


def checked_animation(anim: SurfaceAnimation, where: str) -> SurfaceAnimation:
    """Validate the arrays of ``anim`` and return a copy with numpy arrays of canonical dtypes."""

    def fail(msg):
        raise WigglyInputError(f"{where}: {msg}")

    def array(name, value, shape):
        return real_array(value, name, shape, fail)

    times, positions, faces = animation_arrays(anim.times, anim.positions, anim.faces,
                                               min_vertices=3, fail=fail)
    F, n = positions.shape[:2]
    limit = float(np.finfo(np.float32).max) / 2
    if np.abs(positions).max() > limit:
        fail(f"positions should fit in float32 (|x| <= {limit:.3g}); the largest is "
             f"{np.abs(positions).max():.3g}")

    uvs = normals = None
    if anim.uvs is not None:
        uvs = array("uvs", anim.uvs, "(n, 2)").astype(np.float64)
        if uvs.shape != (n, 2):
            fail(f"uvs should have shape (n, 2) = ({n}, 2); shape is {uvs.shape}")
        if not np.all(np.isfinite(uvs)):
            fail(f"uvs should be finite; vertex {int(np.argwhere(~np.isfinite(uvs))[0, 0])} "
                 "is not")
    if anim.normals is not None:
        normals = array("normals", anim.normals, "(n, 3)").astype(np.float64)
        if normals.shape != (n, 3):
            fail(f"normals should have shape (n, 3) = ({n}, 3); shape is {normals.shape}")
        length = np.linalg.norm(normals, axis=1)
        if not np.all(np.isfinite(length) & (length > 0)):
            v = int(np.flatnonzero(~(np.isfinite(length) & (length > 0)))[0])
            fail(f"normals should be finite nonzero vectors; vertex {v} has "
                 f"{normals[v].tolist()}")
        normals = normals / length[:, None]
    name = anim.name if isinstance(anim.name, str) and anim.name.strip() else "wiggly"
    name = re.sub(r"[\x00-\x1f]+", " ", name).strip()  # one line in OBJ's "o" statement
    rest = shapes = modal = None
    if anim.rest is not None:
        rest = array("rest", anim.rest, "(n, 3)").astype(np.float64)
        if rest.shape != (n, 3) or not np.all(np.isfinite(rest)):
            fail(f"rest should be finite with shape (n, 3) = ({n}, 3); shape is {rest.shape}")
    if (anim.mode_shapes is None) != (anim.modal is None):
        fail("give mode_shapes and modal together (or neither)")
    if anim.mode_shapes is not None:
        if rest is None:
            fail("mode_shapes need the rest positions (rest)")
        shapes = array("mode_shapes", anim.mode_shapes, "(r, n, 3)").astype(np.float64)
        modal = array("modal", anim.modal, "(F, r)").astype(np.float64)
        r = len(shapes)
        if shapes.ndim != 3 or shapes.shape[1:] != (n, 3) or modal.shape != (F, r):
            fail(f"mode_shapes should have shape (r, n, 3) and modal (F, r) with n = {n}, "
                 f"F = {F}; shapes are {shapes.shape} and {modal.shape}")
        if not (np.all(np.isfinite(shapes)) and np.all(np.isfinite(modal))):
            fail("mode_shapes and modal should be finite")
        # they must be the positions: checked on the first, middle and last frames
        for k in sorted({0, F // 2, F - 1}):
            err = np.abs(rest + np.tensordot(modal[k], shapes, axes=1) - positions[k]).max()
            scale = max(float(np.abs(positions[k]).max()), 1e-300)
            if err > 1e-5 * scale:
                fail(f"positions[{k}] differ from rest + modal[{k}] . mode_shapes by {err:.3g}; "
                     "the compact layout is for linear motions only")
    return SurfaceAnimation(times, positions, faces, uvs, normals, name, rest, shapes, modal,
                            bool(anim.loop))


def without_seam(anim: SurfaceAnimation) -> SurfaceAnimation:
    """A looped animation without its last frame (which repeats the first): for frame-based
    formats, whose players step from the last frame to the first."""
    if not anim.loop or anim.n_frames < 3:
        return anim
    modal = None if anim.modal is None else anim.modal[:-1]
    return SurfaceAnimation(anim.times[:-1], anim.positions[:-1], anim.faces, anim.uvs,
                            anim.normals, anim.name, anim.rest, anim.mode_shapes, modal, True)


def _incidence(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """The (n, k) vertex-triangle incidence matrix."""
    k = len(faces)
    return sp.csr_matrix(
        (np.ones(3 * k), (faces.T.ravel(), np.tile(np.arange(k), 3))), shape=(n, k)
    )


def vertex_normals(points: np.ndarray, faces: np.ndarray, incidence=None) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) of one frame.

    n_i = normalize(sum over triangles t containing i of (p1 - p0) x (p2 - p0)), the cross
    product being twice the area times the unit normal.  Vertices without a triangle of
    positive area get zero.
    """
    p = np.asarray(points, np.float64)
    A = _incidence(faces, len(p)) if incidence is None else incidence
    c = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    N = A @ c
    length = np.linalg.norm(N, axis=1, keepdims=True)
    return np.divide(N, length, out=np.zeros_like(N), where=length > 0)


class FrameNormals:
    """Per-frame unit normals: recomputed, or the rest normals carried along (module doc)."""

    def __init__(self, anim: SurfaceAnimation):
        self.faces = anim.faces
        self.incidence = _incidence(anim.faces, anim.n_vertices)
        base = anim.positions[0] if anim.rest is None else anim.rest
        self.rest_computed = vertex_normals(base, anim.faces, self.incidence)
        self.rest = anim.normals

    def __call__(self, points: np.ndarray) -> np.ndarray:
        b = vertex_normals(points, self.faces, self.incidence)
        has_b = np.linalg.norm(b, axis=1) > 0
        if self.rest is None:
            return np.where(has_b[:, None], b, np.asarray(FALLBACK_NORMAL))
        # Rodrigues for the smallest rotation taking a to b, applied to v:
        # R v = (a.b) v + w x v + w (w.v) / (1 + a.b),  w = a x b.
        a, v = self.rest_computed, self.rest
        c = np.einsum("ij,ij->i", a, b)
        w = np.cross(a, b)
        ok = (c > -1 + 1e-6) & has_b & (np.linalg.norm(a, axis=1) > 0)
        denom = np.where(ok, 1 + c, 1.0)
        Rv = c[:, None] * v + np.cross(w, v) + w * (np.einsum("ij,ij->i", w, v) / denom)[:, None]
        out = np.where(ok[:, None], Rv, np.where(has_b[:, None], b, v))
        return out / np.linalg.norm(out, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# atomic output


def format_library(module: str, package: str, ext: str):
    """Import an optional format library, or say which package to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{ext} files need the package {package}: pip install {package}") from e


def frame_progress(iterable, total: int, what: str | os.PathLike[str]):
    """``iterable`` with the frames written counted as :mod:`wiggly.progress` says, named
    after the user's file ``what`` (not its hidden temporary file)."""
    return frames(iterable, total, shown_name(what))


# time codes of the formats


def gltf_times(times: np.ndarray, frame_start: int | None = None,
               loop: bool = False) -> np.ndarray:
    """Sampler input: float32 seconds, shifted to start at 0 if the first time is negative,
    or for a ``loop`` (time-based players such as three.js cycle over [0, the last key], and
    a cycle starting at 0.5 s held its first pose for 0.5 s of each); with ``frame_start``,
    ``(frame_start + k) / fps``."""
    if frame_start is not None:
        fps, codes = frame_codes(times, frame_start, "glTF", gltf=True)
        return (codes / fps).astype(np.float32)
    return (times - (times[0] if loop else min(times[0], 0.0))).astype(np.float32)


def frame_codes(times: np.ndarray, frame_start: int | None, where: str,
                 gltf: bool = False) -> tuple[float, np.ndarray]:
    """(frames per second, frame number of every frame): ``frame_start + k`` when given
    (uniform times only), else the USD time codes of the module docstring."""
    fps, codes = _usd_time_codes(times)
    if frame_start is None:
        return fps, codes
    if len(times) > 1 and fps == 1000.0 and not np.allclose(np.diff(times), 1e-3):
        raise WigglyInputError(f"{where}: frame_start needs uniformly spaced frame times")
    if isinstance(frame_start, bool) or int(frame_start) != frame_start:
        raise WigglyInputError(f"{where}: frame_start must be an integer, got {frame_start!r}")
    if gltf and frame_start < 0:
        raise WigglyInputError(f"{where}: frame_start = {frame_start} would give negative glTF "
                               "times, which glTF forbids; use frame_start >= 0")
    if len(times) == 1:
        fps = 1.0
    return fps, int(frame_start) + np.arange(len(times), dtype=np.float64)


def _usd_time_codes(times: np.ndarray) -> tuple[float, np.ndarray]:
    """(timeCodesPerSecond, time code per frame); see the module docstring."""
    dt = np.diff(times)
    if len(dt) and np.all(np.abs(dt - dt.mean()) <= 1e-6 * dt.mean()):
        fps = 1.0 / dt.mean()
        if abs(fps - round(fps)) <= 1e-6 * fps:
            fps = float(round(fps))
        return fps, times[0] * fps + np.arange(len(times))
    return 1000.0, times * 1000.0
