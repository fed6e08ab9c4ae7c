"""Export of an animated triangle surface: glTF binary, USD, an OBJ sequence or npz.

The last stage of the pipeline (SYSTEM.md §1, step 4: "exports it to animation tools") only
sees plain arrays, a :class:`SurfaceAnimation`: frame times, per-frame vertex positions of the
user's own surface (same vertices, same order, same faces and UVs) and its triangles, plus
optional per-vertex texture coordinates and rest normals.  :func:`write_animation` picks the
format from the file extension (:data:`SUPPORTED`); :func:`read_animation` reads every format
back (tests, and ``wiggly render`` of an exported file).

Formats
-------
``.glb``
    glTF 2.0 binary (pygltflib).  The base mesh is the rest pose (``rest``; frame 0 when it is
    not given): POSITION, NORMAL (the rest normals when given, else the recomputed ones),
    TEXCOORD_0 (when uvs) and uint16/uint32 indices.  Frame k is morph target k (POSITION and
    NORMAL deltas from the base, so the shading follows the deformation), and one animation
    drives the node's ``weights`` with a LINEAR sampler whose keyframe k has weight 1 on target
    k and 0 elsewhere: between frames positions interpolate linearly, and at most two targets
    are active at once.  The mesh's default weights are 0 (a viewer that ignores animations
    shows the rest pose).  Blender imports the base as the ``Basis`` shape key and the targets
    as shape keys (named ``frame_0000``, ...  by ``mesh.extras.targetNames``); three.js plays
    the clip with an ``AnimationMixer``.  **Compact layout** (``gltf_targets="modes"``, linear
    motions): two targets per mode i on the surface, its shape scaled by s_i = max |q_i| and
    negated, with weights max(+-q_i(t) / s_i, 0) in [0, 1] (Blender clamps shape keys to that
    range): the positions are exactly those of the per-frame layout, at and between frames; the
    NORMAL deltas are the normals' derivatives at rest (first order).  Size about ``2 n r 24 + 2
    F r 4`` bytes instead of ``F n 24``.  All data is float32 and 4-byte aligned; the deltas of
    all frames share one bufferView with ``byteStride`` 12; every POSITION accessor (base and
    targets) has its exact min/max.  glTF puts the texture origin at the top-left corner, so V
    is written as ``1 - v`` (and flipped back on reading): :class:`SurfaceAnimation` uvs follow
    the OBJ/USD convention (origin bottom-left).  glTF forbids negative times: if ``times[0] <
    0`` the clip is shifted to start at 0; with ``frame_start`` frame k is at ``(frame_start +
    k) / fps`` s (Blender puts a key at t s on frame ``t * fps`` of its scene, so at the same
    fps keys land on frames ``frame_start``, ``frame_start + 1``, ...); the exact times in
    seconds are kept in the animation's ``extras.wiggly.times`` (and read back from there).
    Size is about ``F * n * 24`` bytes (position and normal deltas per frame): 300 frames of 20k
    vertices take 147 MB.
``.usd``, ``.usda``, ``.usdc``
    A ``UsdGeom.Mesh`` ``/<name>/<name>`` under an Xform ``/<name>`` (the default prim, kind
    component; Blender names the imported object ``<name>``) with time-sampled ``points`` and
    ``extent``; ``subdivisionScheme = "none"``;
    ``primvars:st`` (vertex interpolation) from the uvs; time-sampled vertex ``normals`` only
    when the animation has rest normals (otherwise renderers compute smooth normals).  Stage
    metadata: upAxis Y, metersPerUnit 1, start/end time codes.  Time codes: when the frame
    times are uniform (dt equal to 1e-6 relative), ``timeCodesPerSecond = framesPerSecond =
    1 / dt`` (rounded to an integer when within 1e-6 of one) and frame k has time code
    ``times[0] / dt + k`` (``frame_start + k`` with ``frame_start``); otherwise
    ``timeCodesPerSecond = 1000`` and time code = milliseconds.  Reading gives ``time = time
    code / timeCodesPerSecond`` (shifted by the start time and frame kept in the layer's
    ``customLayerData["wiggly"]``).  Blender's importer sets its scene's frame range from the
    time codes but ignores the frame rate: export at the Blender scene's fps.  ``.usd`` is
    written in the binary crate format (usd-core's default).
``.obj``
    An OBJ sequence: ``out/frame.obj`` writes ``out/frame_0000.obj``, ``out/frame_0001.obj``,
    ... (frame index zero-padded to at least 4 digits, more when F > 10000), each with
    ``v``, ``vt`` (when uvs), ``vn`` and ``f a/a/a`` lines (1-based, the same index for
    position, uv and normal; ``f a//a`` without uvs), an ``o <name>`` line and a
    ``# time <seconds>`` comment (read back as the frame time).  Vertex order and faces are
    the input's.  Positions and uvs are written with ``%.9g`` (float32 values come back bit
    for bit), normals with ``%.6g``.  Each frame's text is made by a single C-level ``%``
    over a preformatted block (the uv and face lines are formatted once): 120 frames of 5k
    vertices take about 2 s (106 MB), 300 frames of 20k vertices about 14 s (1.1 GB), on
    two busy cores.  Overwriting a sequence also deletes the frames of an earlier, longer
    sequence with the same name.
``.npz``
    Compressed numpy archive with ``format_version``, ``times`` (float64), ``positions``
    (float32), ``faces`` (int64), ``name`` and optional ``uvs`` and ``normals`` (float32).

Per-frame normals are recomputed from each frame (area-weighted vertex normals).  When the
animation has rest normals (e.g. smooth normals across a UV seam), frame k's normal is the
rest normal rotated by the smallest rotation taking the recomputed frame-0 normal to the
recomputed frame-k normal, so frame 0 shows the file's normals exactly.

Every write is all or nothing: data goes to temporary files in the output's directory and
is moved into place only when every file is complete (:class:`wiggly.files.OutputSet`;
:func:`stage_animation` adds an animation to a set shared with other outputs), so a failure
never leaves a partial output, a temporary file, or a replaced one.  An existing output is
an error unless ``overwrite=True``.  Missing parent directories are created.
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from tqdm import tqdm

from wiggly.errors import WigglyInputError
from wiggly.files import OutputSet

__all__ = ["GLTF_TARGETS", "SUPPORTED", "SurfaceAnimation", "read_animation", "stage_animation",
           "vertex_normals", "write_animation"]

#: Output formats by file extension.
SUPPORTED = {
    ".glb": "glTF 2.0 binary, one morph target per frame and a weights animation",
    ".usd": "Universal Scene Description (binary crate), time-sampled points",
    ".usda": "Universal Scene Description (text), time-sampled points",
    ".usdc": "Universal Scene Description (binary crate), time-sampled points",
    ".obj": "OBJ sequence: name.obj writes name_0000.obj, name_0001.obj, ...",
    ".npz": "compressed numpy archive (times, positions, faces, uvs, normals)",
}

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
    mode_shapes : (r, n, 3) float array or None
        For a linear motion, ``positions[k] = rest + sum_i modal[k, i] * mode_shapes[i]``
        (the modes on the surface): the compact glTF layout (``gltf_targets="modes"``).
    modal : (F, r) float array or None
        The modal coordinates q(t) of every frame, with ``mode_shapes``.
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

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def n_vertices(self) -> int:
        return self.positions.shape[1]


def write_animation(
    path, anim: SurfaceAnimation, *, overwrite: bool = False, progress: bool = False,
    frame_start: int | None = None, gltf_targets: str = "frames",
) -> Path:
    """Write ``anim`` to ``path`` in the format of its extension (:data:`SUPPORTED`).

    Parameters
    ----------
    path : str or Path
        Output file; for ``.obj`` the sequence's base name (``out/frame.obj`` writes
        ``out/frame_0000.obj``, ...).
    anim : SurfaceAnimation
        The animation; its arrays are validated first.
    overwrite : bool
        Replace existing output (for OBJ: any existing frame of the sequence).
    progress : bool
        Show a tqdm progress bar over frames on stderr (OBJ and USD).
    frame_start : int, optional
        glTF and USD: put frame k on frame ``frame_start + k`` at the frames' rate (glTF time
        ``(frame_start + k) / fps``, USD time code ``frame_start + k``), so that keys land on
        whole frames from ``frame_start`` on (Blender's scenes start at frame 1).  Needs
        uniform frame times; glTF needs ``frame_start >= 0``.  None: the frames' own times
        (module docstring).  The exact times are kept in the file either way.
    gltf_targets : {"frames", "modes"}
        glTF morph targets: one per frame, or one per mode with the modal coordinates as
        weights (exact for a linear motion; needs ``anim.rest``, ``mode_shapes``, ``modal``).

    Returns
    -------
    Path
        ``path`` (for OBJ the base name, as given).

    Raises
    ------
    WigglyInputError
        Unknown extension, existing output without ``overwrite``, or invalid arrays.
    """
    path = Path(path)
    with OutputSet() as outputs:
        stage_animation(outputs, path, anim, overwrite=overwrite, progress=progress,
                        frame_start=frame_start, gltf_targets=gltf_targets)
    return path


def stage_animation(
    outputs: OutputSet, path, anim: SurfaceAnimation, *, overwrite: bool = False,
    progress: bool = False, frame_start: int | None = None, gltf_targets: str = "frames",
) -> None:
    """:func:`write_animation` into temporary files of ``outputs``
    (:class:`wiggly.files.OutputSet`), which moves them into place with the other outputs."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED:
        raise WigglyInputError(
            f"cannot write {path}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(SUPPORTED)}"
        )
    anim = _checked(anim, f"cannot write {path}")
    if gltf_targets not in GLTF_TARGETS:
        raise WigglyInputError(f"cannot write {path}: gltf_targets = {gltf_targets!r}; use one "
                               f"of {', '.join(map(repr, GLTF_TARGETS))}")
    if gltf_targets == "modes" and ext == ".glb" and anim.mode_shapes is None:
        raise WigglyInputError(f"cannot write {path} with one morph target per mode: the "
                               "animation has no mode shapes (a warped motion is not a linear "
                               "combination of modes); use gltf_targets='frames'")
    if frame_start is not None:
        _frame_codes(anim.times, frame_start, f"cannot write {path}", gltf=ext == ".glb")
    if ext == ".glb" and np.any(np.diff(_gltf_times(anim.times, frame_start)) <= 0):
        raise WigglyInputError(
            f"cannot write {path}: frame times are too close to be distinct in float32, which "
            "glTF uses; use a larger frame interval (or export .usd / .npz)"
        )
    if path.is_dir():
        raise WigglyInputError(f"cannot write {path}: it is a directory; give a file name")
    if ext == ".obj":
        _stage_obj_sequence(outputs, path, anim, overwrite=overwrite, progress=progress)
        return
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    tmp = outputs.stage(path)
    if ext == ".glb":
        _write_glb(tmp, anim, progress=progress, frame_start=frame_start, targets=gltf_targets)
    elif ext == ".npz":
        _write_npz(tmp, anim, progress=progress)
    else:
        _write_usd(tmp, anim, progress=progress, frame_start=frame_start)


def read_animation(path) -> SurfaceAnimation:
    """Read an animation written by :func:`write_animation` (any format of :data:`SUPPORTED`).

    For ``.obj`` give the sequence's base name (``out/frame.obj`` reads ``out/frame_0000.obj``,
    ...); a single OBJ file without sequence frames is read as one frame.  glTF node
    transforms are ignored; a glTF file without morph targets is one frame.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED:
        raise WigglyInputError(
            f"cannot read {path}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(SUPPORTED)}"
        )
    if ext == ".obj":
        anim = _read_obj_sequence(path)
    else:
        if not path.is_file():
            raise WigglyInputError(f"cannot read {path}: no such file")
        reader = {".glb": _read_glb, ".npz": _read_npz}.get(ext, _read_usd)
        anim = reader(path)
    return _checked(anim, f"{path}")


# ----------------------------------------------------------------------------------------------
# validation and normals


def _checked(anim: SurfaceAnimation, where: str) -> SurfaceAnimation:
    """Validate the arrays of ``anim`` and return a copy with numpy arrays of canonical dtypes."""

    def fail(msg):
        raise WigglyInputError(f"{where}: {msg}")

    def array(name, value, ndim_shape):
        try:
            a = np.asarray(value)
        except ValueError as e:
            fail(f"{name} should be an array of shape {ndim_shape}; {e}")
        if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
            fail(f"{name} should be a real-valued array of shape {ndim_shape}; dtype is {a.dtype}")
        return a

    times = array("times", anim.times, "(F,)")
    if times.ndim != 1 or len(times) < 1:
        fail(f"times should have shape (F,) with F >= 1; shape is {times.shape}")
    times = times.astype(np.float64)
    if not np.all(np.isfinite(times)):
        fail(f"times should be finite; frame {int(np.flatnonzero(~np.isfinite(times))[0])} is not")
    if np.any(np.diff(times) <= 0):
        k = int(np.flatnonzero(np.diff(times) <= 0)[0])
        fail(f"times should be strictly increasing; times[{k}] = {times[k]} and "
             f"times[{k + 1}] = {times[k + 1]}")
    F = len(times)

    positions = array("positions", anim.positions, "(F, n, 3)")
    if positions.ndim != 3 or positions.shape[2] != 3:
        fail(f"positions should have shape (F, n, 3); shape is {positions.shape}")
    if positions.shape[0] != F:
        fail(f"positions should have shape (F, n, 3) with F = len(times) = {F}; "
             f"shape is {positions.shape}")
    n = positions.shape[1]
    if n < 3:
        fail(f"positions should have shape (F, n, 3) with n >= 3 vertices; shape is "
             f"{positions.shape}")
    if positions.dtype not in (np.float32, np.float64):
        positions = positions.astype(np.float64)
    bad = ~np.isfinite(positions)
    if bad.any():
        k, v, _ = np.argwhere(bad)[0]
        fail(f"positions should be finite; frame {k}, vertex {v} is {positions[k, v].tolist()}")
    limit = float(np.finfo(np.float32).max) / 2
    if np.abs(positions).max() > limit:
        fail(f"positions should fit in float32 (|x| <= {limit:.3g}); the largest is "
             f"{np.abs(positions).max():.3g}")

    faces = array("faces", anim.faces, "(k, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1:
        fail(f"faces should have shape (k, 3) with k >= 1 triangles; shape is {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        fail(f"faces should be an integer array; dtype is {faces.dtype}")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= n:
        t = int(np.flatnonzero((faces < 0).any(1) | (faces >= n).any(1))[0])
        fail(f"faces should index the n = {n} vertices (0 <= i < {n}); face {t} is "
             f"{faces[t].tolist()}")

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
    return SurfaceAnimation(times, positions, faces, uvs, normals, name, rest, shapes, modal)


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


class _FrameNormals:
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


def _require(module: str, package: str, ext: str):
    """Import an optional format library, or say which package to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{ext} files need the package {package}: pip install {package}") from e


def _progress(iterable, total: int, enabled: bool, what: str):
    return tqdm(iterable, total=total, disable=not enabled, file=sys.stderr, unit="frame",
                desc=what)


# ----------------------------------------------------------------------------------------------
# npz


def _write_npz(path: Path, anim: SurfaceAnimation, progress: bool = False) -> None:
    arrays = {
        "format_version": np.array(FORMAT_VERSION),
        "times": anim.times,
        "positions": anim.positions.astype(np.float32),
        "faces": anim.faces,
        "name": np.array(anim.name),
    }
    if anim.uvs is not None:
        arrays["uvs"] = anim.uvs.astype(np.float32)
    if anim.normals is not None:
        arrays["normals"] = anim.normals.astype(np.float32)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def _read_npz(path: Path) -> SurfaceAnimation:
    try:
        with np.load(path, allow_pickle=False) as data:
            d = {key: data[key] for key in data.files}
    except (OSError, ValueError) as e:
        raise WigglyInputError(f"cannot read {path}: not a numpy npz archive ({e})") from e
    missing = [key for key in ("format_version", "times", "positions", "faces") if key not in d]
    if missing:
        raise WigglyInputError(
            f"cannot read {path}: missing arrays {missing}; a wiggly animation npz has "
            "format_version, times, positions, faces (and optional uvs, normals, name)"
        )
    if int(d["format_version"]) > FORMAT_VERSION:
        raise WigglyInputError(
            f"cannot read {path}: format_version {int(d['format_version'])} was written by a "
            f"newer wiggly (this one reads up to {FORMAT_VERSION}); upgrade wiggly"
        )
    return SurfaceAnimation(d["times"], d["positions"], d["faces"], d.get("uvs"),
                            d.get("normals"), str(d.get("name", "wiggly")))


# ----------------------------------------------------------------------------------------------
# glTF binary

_GL_FLOAT, _GL_UNSIGNED_SHORT, _GL_UNSIGNED_INT = 5126, 5123, 5125
_GL_ARRAY_BUFFER, _GL_ELEMENT_ARRAY_BUFFER = 34962, 34963
_GL_TRIANGLES = 4
_GL_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
_GL_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def _gltf_times(times: np.ndarray, frame_start: int | None = None) -> np.ndarray:
    """Sampler input: float32 seconds, shifted to start at 0 if the first time is negative;
    with ``frame_start``, ``(frame_start + k) / fps``."""
    if frame_start is not None:
        fps, codes = _frame_codes(times, frame_start, "glTF", gltf=True)
        return (codes / fps).astype(np.float32)
    return (times - min(times[0], 0.0)).astype(np.float32)


def _frame_codes(times: np.ndarray, frame_start: int | None, where: str,
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


def _write_glb(path: Path, anim: SurfaceAnimation, progress: bool = False,
               frame_start: int | None = None, targets: str = "frames") -> None:
    gl = _require("pygltflib", "pygltflib", ".glb")

    F, n = anim.n_frames, anim.n_vertices
    frame_normals = _FrameNormals(anim)
    P = anim.positions.astype(np.float32)
    rest = anim.positions[0] if anim.rest is None else anim.rest
    base_p = rest.astype(np.float32)
    base_n = (anim.normals if anim.normals is not None else frame_normals(rest))
    base_n = base_n.astype(np.float32)
    if targets == "modes":
        dP, dN, weights, names = _modal_targets(anim, frame_normals, base_n)
    else:
        dP = P - base_p
        dN = np.empty_like(dP)
        for k in _progress(range(F), F, progress, "normals"):
            dN[k] = frame_normals(anim.positions[k]).astype(np.float32) - base_n
        weights = np.eye(F, dtype=np.float32)  # keyframe k: weight 1 on target k
        names = [f"frame_{k:04d}" for k in range(F)]
    n_targets = len(dP)
    t32 = _gltf_times(anim.times, frame_start)
    index_type = _GL_UNSIGNED_SHORT if n <= 65535 else _GL_UNSIGNED_INT

    blob = bytearray()
    views, accessors = [], []

    def add_view(data: np.ndarray, target=None, stride=None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes,
                                   target=target, byteStride=stride))
        blob.extend(data.tobytes())
        blob.extend(b"\0" * (-len(blob) % 4))
        return len(views) - 1

    def add_accessor(view, data, ctype, kind, offset=0, bounds=False) -> int:
        acc = gl.Accessor(bufferView=view, byteOffset=offset, componentType=ctype,
                          count=len(data), type=kind)
        if bounds:
            acc.min = np.atleast_1d(data.min(axis=0)).astype(float).tolist()
            acc.max = np.atleast_1d(data.max(axis=0)).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    indices = anim.faces.ravel().astype(np.uint16 if index_type == _GL_UNSIGNED_SHORT
                                         else np.uint32)
    attributes = gl.Attributes(
        POSITION=add_accessor(add_view(base_p, _GL_ARRAY_BUFFER), base_p, _GL_FLOAT, "VEC3",
                              bounds=True),
        NORMAL=add_accessor(add_view(base_n, _GL_ARRAY_BUFFER), base_n, _GL_FLOAT, "VEC3"),
    )
    if anim.uvs is not None:
        st = np.column_stack([anim.uvs[:, 0], 1.0 - anim.uvs[:, 1]]).astype(np.float32)
        attributes.TEXCOORD_0 = add_accessor(add_view(st, _GL_ARRAY_BUFFER), st, _GL_FLOAT,
                                             "VEC2")
    index_accessor = add_accessor(add_view(indices, _GL_ELEMENT_ARRAY_BUFFER), indices,
                                  index_type, "SCALAR", bounds=True)
    # All position deltas in one strided view, all normal deltas in another.
    view_dp = add_view(dP, _GL_ARRAY_BUFFER, stride=12)
    view_dn = add_view(dN, _GL_ARRAY_BUFFER, stride=12)
    morph = [
        gl.Attributes(
            POSITION=add_accessor(view_dp, dP[k], _GL_FLOAT, "VEC3", offset=k * n * 12,
                                  bounds=True),
            NORMAL=add_accessor(view_dn, dN[k], _GL_FLOAT, "VEC3", offset=k * n * 12),
        )
        for k in range(n_targets)
    ]
    time_accessor = add_accessor(add_view(t32), t32, _GL_FLOAT, "SCALAR", bounds=True)
    flat = weights.astype(np.float32).ravel()
    weight_accessor = add_accessor(add_view(flat), flat, _GL_FLOAT, "SCALAR")
    extras = {"format_version": FORMAT_VERSION, "times": anim.times.tolist(),
              "targets": targets}
    if frame_start is not None:
        extras["frame_start"] = int(frame_start)

    gltf = gl.GLTF2(
        asset=gl.Asset(version="2.0", generator="wiggly"),
        scene=0,
        scenes=[gl.Scene(nodes=[0])],
        nodes=[gl.Node(mesh=0, name=anim.name)],
        meshes=[gl.Mesh(
            name=anim.name,
            primitives=[gl.Primitive(attributes=attributes, indices=index_accessor,
                                     mode=_GL_TRIANGLES, targets=morph)],
            weights=[0.0] * n_targets,
            extras={"targetNames": names},
        )],
        animations=[gl.Animation(
            name=anim.name,
            samplers=[gl.AnimationSampler(input=time_accessor, output=weight_accessor,
                                          interpolation="LINEAR")],
            channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(
                node=0, path="weights"))],
            extras={"wiggly": extras},
        )],
        accessors=accessors,
        bufferViews=views,
        buffers=[gl.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(path))


def _modal_targets(anim: SurfaceAnimation, frame_normals: _FrameNormals, base_n: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Morph targets of the compact layout (module docstring).

    Mode i, scaled by s_i = max_k |q_i(t_k)|, becomes a target ``+`` with weights
    max(q_i / s_i, 0) and a target ``-`` (the shape negated) with weights max(-q_i / s_i, 0):
    weights stay in [0, 1], the range of Blender's shape-key sliders (it clamps to them), and
    their difference interpolates linearly between frames, so positions are exact at and
    between frames.  A half whose weights are all 0 (and modes that stay at 0) is left out.
    NORMAL deltas are the normals' derivatives along the target at rest (central
    differences): first order.
    """
    scale = np.abs(anim.modal).max(axis=0)
    shapes, weights, names = [], [], []
    for i in np.flatnonzero(scale > 0):
        w = anim.modal[:, i] / scale[i]
        for sign, label in ((1.0, "+"), (-1.0, "-")):
            if (sign * w > 0).any():
                shapes.append(sign * scale[i] * anim.mode_shapes[i])
                weights.append(np.maximum(sign * w, 0.0))
                names.append(f"mode_{i:03d}{label}")
    dP = np.asarray(shapes, dtype=np.float32).reshape(-1, anim.n_vertices, 3)
    dN = np.empty_like(dP)
    eps = 1e-3
    for j, shape in enumerate(shapes):
        plus = frame_normals(anim.rest + eps * shape)
        minus = frame_normals(anim.rest - eps * shape)
        dN[j] = ((plus - minus) / (2 * eps)).astype(np.float32)
    return dP, dN, np.asarray(weights).reshape(len(shapes), -1).T, names


def _gl_accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    """The data of accessor ``index`` as a (count, width) array (strides, sparse, zeros)."""
    acc = gltf.accessors[index]
    dtype = np.dtype(_GL_DTYPES[acc.componentType])
    width = _GL_WIDTH[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, width), dtype)
    else:
        view = gltf.bufferViews[acc.bufferView]
        stride = view.byteStride or dtype.itemsize * width
        offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
        out = np.ndarray((acc.count, width), dtype, buffer=blob, offset=offset,
                         strides=(stride, dtype.itemsize)).copy()
    if acc.sparse is not None:
        s = acc.sparse
        iview, vview = gltf.bufferViews[s.indices.bufferView], gltf.bufferViews[s.values.bufferView]
        idx = np.frombuffer(blob, _GL_DTYPES[s.indices.componentType], s.count,
                            (iview.byteOffset or 0) + (s.indices.byteOffset or 0))
        out[idx] = np.frombuffer(blob, dtype, s.count * width,
                                 (vview.byteOffset or 0) + (s.values.byteOffset or 0)
                                 ).reshape(-1, width)
    if acc.normalized:
        out = out.astype(np.float64) / np.iinfo(dtype).max
    return out


def _read_glb(path: Path) -> SurfaceAnimation:
    gl = _require("pygltflib", "pygltflib", ".glb")

    try:
        gltf = gl.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises assorted errors on malformed files
        raise WigglyInputError(f"cannot read {path}: not a valid glTF binary ({e})") from e
    blob = gltf.binary_blob()
    if not gltf.meshes or not gltf.meshes[0].primitives:
        raise WigglyInputError(f"cannot read {path}: the glTF file has no mesh")
    mesh_index = 0
    prim = gltf.meshes[mesh_index].primitives[0]
    if prim.mode not in (None, _GL_TRIANGLES) or prim.attributes.POSITION is None:
        raise WigglyInputError(f"cannot read {path}: the first primitive is not a triangle "
                               "mesh with POSITION")
    base = _gl_accessor(gltf, blob, prim.attributes.POSITION).astype(np.float32)
    n = len(base)
    faces = (_gl_accessor(gltf, blob, prim.indices).reshape(-1, 3) if prim.indices is not None
             else np.arange(n).reshape(-1, 3)).astype(np.int64)
    uvs = normals = None
    if prim.attributes.TEXCOORD_0 is not None:
        st = _gl_accessor(gltf, blob, prim.attributes.TEXCOORD_0).astype(np.float64)
        uvs = np.column_stack([st[:, 0], 1.0 - st[:, 1]])
    if prim.attributes.NORMAL is not None:
        normals = _gl_accessor(gltf, blob, prim.attributes.NORMAL).astype(np.float64)
    targets = prim.targets or []
    deltas = np.stack([_gl_accessor(gltf, blob, t["POSITION"] if isinstance(t, dict)
                                    else t.POSITION) for t in targets]) if targets else None
    nodes = [i for i, node in enumerate(gltf.nodes) if node.mesh == mesh_index]
    sampler = extras = None
    for animation in gltf.animations:
        for channel in animation.channels:
            if channel.target.path == "weights" and channel.target.node in nodes:
                sampler = animation.samplers[channel.sampler]
                extras = (animation.extras or {}).get("wiggly")
    if deltas is None:
        return SurfaceAnimation(np.zeros(1), base[None], faces, uvs, normals,
                                gltf.meshes[0].name or path.stem)
    if sampler is None:
        raise WigglyInputError(f"cannot read {path}: the mesh has morph targets but no "
                               "animation of its weights")
    times = _gl_accessor(gltf, blob, sampler.input).ravel().astype(np.float64)
    W = _gl_accessor(gltf, blob, sampler.output).astype(np.float64)
    if sampler.interpolation == "CUBICSPLINE":  # (in-tangent, value, out-tangent) per key
        W = W.reshape(len(times), 3, -1)[:, 1]
    W = W.reshape(len(times), len(targets))
    if extras and len(extras.get("times", ())) == len(times):
        times = np.asarray(extras["times"], np.float64)
    one_hot = np.all((W == 0) | (W == 1)) and np.all(W.sum(axis=1) <= 1)
    if one_hot:  # the layout written here: gather instead of a dense product
        k = np.where(W.any(axis=1), W.argmax(axis=1), -1)
        positions = base + np.where((k >= 0)[:, None, None], deltas[np.maximum(k, 0)], 0)
    else:
        positions = base + np.einsum("ft,tnc->fnc", W.astype(np.float32), deltas)
    return SurfaceAnimation(times, positions.astype(np.float32), faces, uvs, normals,
                            gltf.meshes[0].name or path.stem)


# ----------------------------------------------------------------------------------------------
# USD


def _usd_time_codes(times: np.ndarray) -> tuple[float, np.ndarray]:
    """(timeCodesPerSecond, time code per frame); see the module docstring."""
    dt = np.diff(times)
    if len(dt) and np.all(np.abs(dt - dt.mean()) <= 1e-6 * dt.mean()):
        fps = 1.0 / dt.mean()
        if abs(fps - round(fps)) <= 1e-6 * fps:
            fps = float(round(fps))
        return fps, times[0] * fps + np.arange(len(times))
    return 1000.0, times * 1000.0


def _write_usd(path: Path, anim: SurfaceAnimation, progress: bool = False,
               frame_start: int | None = None) -> None:
    _require("pxr", "usd-core", "USD")
    from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, Vt

    fps, codes = _frame_codes(anim.times, frame_start, f"cannot write {path}")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(float(codes[0]))
    stage.SetEndTimeCode(float(codes[-1]))
    root_name = Tf.MakeValidIdentifier(anim.name)
    root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(root_name))
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    if root_name != anim.name:
        root.GetPrim().SetDisplayName(anim.name)
    # Blender names the imported object after the Mesh prim (merging the Xform into it)
    mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild(root_name))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(anim.faces), 3,
                                                                  np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(anim.faces.ravel().astype(np.int32)))
    if anim.uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(anim.uvs.astype(np.float32)))
    points, extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    normals = None
    if anim.normals is not None:
        normals = mesh.CreateNormalsAttr()
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        frame_normals = _FrameNormals(anim)
    for k in _progress(range(anim.n_frames), anim.n_frames, progress, "USD"):
        t = Usd.TimeCode(float(codes[k]))
        p = anim.positions[k].astype(np.float32)
        points.Set(Vt.Vec3fArray.FromNumpy(p), t)
        lo, hi = p.min(axis=0).tolist(), p.max(axis=0).tolist()
        extent.Set(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]), t)
        if normals is not None:
            nk = frame_normals(anim.positions[k]).astype(np.float32)
            normals.Set(Vt.Vec3fArray.FromNumpy(nk), t)
    stage.GetRootLayer().customLayerData = {"wiggly": {
        "format_version": FORMAT_VERSION, "start_time": float(anim.times[0]),
        "frame_start": int(codes[0]), "frames_per_second": float(fps)}}
    if not stage.GetRootLayer().Export(str(path)):
        raise OSError(f"USD could not write {path}")


def _forget_usd_layer(path: Path) -> None:
    """Reload ``path`` if USD's layer registry still holds an older version of it."""
    from pxr import Sdf

    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)


def _read_usd(path: Path) -> SurfaceAnimation:
    _require("pxr", "usd-core", "USD")
    from pxr import Usd, UsdGeom

    _forget_usd_layer(path)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise WigglyInputError(f"cannot read {path}: USD could not open it")
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if not meshes:
        raise WigglyInputError(f"cannot read {path}: no UsdGeom.Mesh in the stage")
    mesh = UsdGeom.Mesh(meshes[0])
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    if counts.size == 0 or np.any(counts != 3):
        raise WigglyInputError(f"cannot read {path}: mesh {mesh.GetPath()} is not a triangle "
                               "mesh (faceVertexCounts should all be 3)")
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), np.int64).reshape(-1, 3)
    points = mesh.GetPointsAttr()
    codes = points.GetTimeSamples() or [Usd.TimeCode.Default()]
    positions = np.stack([np.asarray(points.Get(c), np.float32) for c in codes])
    tcps = stage.GetTimeCodesPerSecond()
    times = (np.asarray(codes, np.float64) / tcps if points.GetTimeSamples() else np.zeros(1))
    ours = stage.GetRootLayer().customLayerData.get("wiggly", {})
    if points.GetTimeSamples() and "start_time" in ours and "frame_start" in ours:
        times = ours["start_time"] + (np.asarray(codes, np.float64) - ours["frame_start"]) / tcps
    uvs = normals = None
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    if st and st.HasValue():
        if st.GetInterpolation() not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
            raise WigglyInputError(f"cannot read {path}: primvars:st has interpolation "
                                   f"{st.GetInterpolation()}; only per-vertex uvs are read")
        uvs = np.asarray(st.ComputeFlattened(), np.float64)
    attr = mesh.GetNormalsAttr()
    if attr.HasValue():
        normals = np.asarray(attr.Get(codes[0]), np.float64)
    root = stage.GetDefaultPrim() or meshes[0]
    name = root.GetDisplayName() or root.GetName()
    return SurfaceAnimation(times, positions, faces, uvs, normals, name)


# ----------------------------------------------------------------------------------------------
# OBJ sequence


def _obj_frame_names(path: Path, F: int) -> list[Path]:
    width = max(4, len(str(F - 1)))
    return [path.with_name(f"{path.stem}_{k:0{width}d}{path.suffix}") for k in range(F)]


def _obj_existing_frames(path: Path) -> dict[int, Path]:
    """Files of the sequence ``path`` already on disk, by frame index."""
    if not path.parent.is_dir():
        return {}
    pattern = re.compile(rf"{re.escape(path.stem)}_(\d+){re.escape(path.suffix)}")
    found = {}
    for entry in path.parent.iterdir():
        m = pattern.fullmatch(entry.name)
        if m and entry.is_file():
            found[int(m.group(1))] = entry
    return found


def _format_obj_block(prefix: str, X: np.ndarray, fmt: str) -> bytes:
    """Lines ``prefix x0 x1 ...`` for the rows of X: one C-level ``%`` over the whole block.

    (Faster than ``np.savetxt``, which formats row by row, and than building the digits with
    numpy, which needs many passes over the array.)
    """
    row = prefix + f" {fmt}" * X.shape[1] + "\n"
    return ((row * len(X)) % tuple(X.ravel().tolist())).encode()


def _write_frame_file(path: Path, data: bytes) -> None:
    path.write_bytes(data)


def _stage_obj_sequence(outputs: OutputSet, path: Path, anim: SurfaceAnimation, *,
                        overwrite: bool, progress: bool) -> None:
    F = anim.n_frames
    names = _obj_frame_names(path, F)
    existing = _obj_existing_frames(path)
    if existing and not overwrite:
        first = existing[min(existing)]
        raise WigglyInputError(
            f"{first} exists; pass overwrite=True / --overwrite to replace the "
            f"{len(existing)} existing frame(s) of the OBJ sequence {path.name} in {path.parent}"
        )
    frame_normals = _FrameNormals(anim)
    f = anim.faces + 1
    if anim.uvs is not None:
        uv_block = _format_obj_block("vt", anim.uvs, "%.9g")
        face_row = "f %d/%d/%d %d/%d/%d %d/%d/%d\n"
        face_values = np.repeat(f, 3, axis=1)
    else:
        uv_block = b""
        face_row = "f %d//%d %d//%d %d//%d\n"
        face_values = np.repeat(f, 2, axis=1)
    face_block = ((face_row * len(f)) % tuple(face_values.ravel().tolist())).encode()
    header = f"# wiggly frame {{k}} of {F}\n# time {{t!r}}\no {anim.name}\n"

    for k in _progress(range(F), F, progress, "OBJ"):
        data = b"".join([
            header.format(k=k, t=float(anim.times[k])).encode(),
            _format_obj_block("v", anim.positions[k], POSITION_FORMAT),
            uv_block,
            _format_obj_block("vn", frame_normals(anim.positions[k]), "%.6g"),
            face_block,
        ])
        _write_frame_file(outputs.stage(names[k]), data)
    for stale in existing.values():  # frames of an earlier, longer sequence
        if stale not in names:
            outputs.remove_on_commit(stale)


_OBJ_V = re.compile(rb"^v[ \t]+([^\n]*)", re.M)
_OBJ_VT = re.compile(rb"^vt[ \t]+([^\n]*)", re.M)
_OBJ_VN = re.compile(rb"^vn[ \t]+([^\n]*)", re.M)
_OBJ_F = re.compile(rb"^f[ \t]+([^\n]*)", re.M)
_OBJ_TIME = re.compile(rb"^# time[ \t]+(\S+)", re.M)
_OBJ_NAME = re.compile(rb"^o[ \t]+([^\r\n]*)", re.M)


def _obj_floats(rows: list[bytes], width: int) -> np.ndarray:
    """The first ``width`` numbers of each row (a ``v``, ``vt`` or ``vn`` line's rest)."""
    values = np.array(b" ".join(rows).split(), np.float64)
    if len(values) != width * len(rows):  # optional extra values (v x y z w, vt u v w)
        values = np.array([row.split()[:width] for row in rows], np.float64)
    return values.reshape(-1, width)


def _read_obj_faces(file: Path, data: bytes, n: int) -> np.ndarray:
    rows = _OBJ_F.findall(data)
    try:
        corners = np.array(b" ".join(rows).replace(b"//", b"/0/").replace(b"/", b" ").split(),
                           np.int64)
    except ValueError as e:
        raise WigglyInputError(f"cannot read {file}: malformed f line ({e})") from e
    per_corner = len(corners) // (3 * len(rows)) if rows else 0
    if not rows or per_corner * 3 * len(rows) != len(corners) or per_corner not in (1, 2, 3):
        raise WigglyInputError(f"cannot read {file}: faces should be triangles "
                               "'f a b c', 'f a/a/a ...' or 'f a//a ...'")
    corners = corners.reshape(len(rows), 3, per_corner)
    v = corners[..., 0]
    for j in range(1, per_corner):
        used = corners[..., j] != 0
        if np.any(corners[..., j][used] != v[used]):
            raise WigglyInputError(
                f"cannot read {file}: a face uses different position and uv/normal indices; "
                "only per-vertex uvs and normals are supported (f a/a/a)")
    if v.min() < 1 or v.max() > n:
        raise WigglyInputError(f"cannot read {file}: face indices should be in 1..{n}")
    return v - 1


def _read_obj_frame(file: Path) -> tuple[bytes, np.ndarray]:
    data = file.read_bytes()
    try:
        return data, _obj_floats(_OBJ_V.findall(data), 3)
    except ValueError as e:
        raise WigglyInputError(f"cannot read {file}: malformed v line ({e})") from e


def _read_obj_sequence(path: Path) -> SurfaceAnimation:
    frames = _obj_existing_frames(path)
    if frames:
        missing = sorted(set(range(max(frames) + 1)) - set(frames))
        if missing:
            raise WigglyInputError(
                f"cannot read the OBJ sequence {path}: frame(s) {missing[:5]} missing among "
                f"{path.stem}_NNNN{path.suffix} in {path.parent}")
        files = [frames[k] for k in range(len(frames))]
    elif path.is_file():
        files = [path]
    else:
        raise WigglyInputError(
            f"cannot read {path}: no file and no OBJ sequence {path.stem}_0000{path.suffix} in "
            f"{path.parent}")
    data, p0 = _read_obj_frame(files[0])
    n = len(p0)
    if n < 3:
        raise WigglyInputError(f"cannot read {files[0]}: it has {n} vertices (v lines)")
    uv_rows = _OBJ_VT.findall(data)
    uvs = _obj_floats(uv_rows, 2) if len(uv_rows) == n else None
    vn_rows = _OBJ_VN.findall(data)
    normals = _obj_floats(vn_rows, 3) if len(vn_rows) == n else None
    faces = _read_obj_faces(files[0], data, n)
    positions = np.empty((len(files), n, 3), np.float64)
    positions[0] = p0
    stamps = [_OBJ_TIME.search(data)]
    for k, file in enumerate(files[1:], start=1):
        data_k, p = _read_obj_frame(file)
        if len(p) != n:
            raise WigglyInputError(f"cannot read the OBJ sequence {path}: {file.name} has "
                                   f"{len(p)} vertices, {files[0].name} has {n}")
        positions[k] = p
        stamps.append(_OBJ_TIME.search(data_k))
    if all(stamps):
        times = np.array([float(s.group(1)) for s in stamps])
    else:
        times = np.arange(len(files)) / OBJ_DEFAULT_FPS
    name_match = _OBJ_NAME.search(data)
    name = name_match.group(1).decode(errors="replace").strip() if name_match else path.stem
    return SurfaceAnimation(times, positions, faces, uvs, normals, name)
