"""Writing and reading animations by file extension, all or nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError, warn
from wiggly.export.animation import (
    GLTF,
    GLTF_TARGETS,
    SUPPORTED,
    SurfaceAnimation,
    checked_animation,
    frame_codes,
    gltf_times,
    without_seam,
)
from wiggly.export.gltf import read_glb, write_glb
from wiggly.export.npz import read_npz, write_npz
from wiggly.export.obj import read_obj_sequence, stage_obj_sequence
from wiggly.export.usd import read_usd, write_usd
from wiggly.files import OutputSet, shown_name
from wiggly.limits import frame_steps, whole_frames_remedy
from wiggly.progress import deprecated_progress


def surface_animation(anim, fps: float = 30.0, name: str = "wiggly",
                      gltf_targets: str = "frames") -> SurfaceAnimation:
    """The frames of a solved :class:`wiggly.Animation` on its body's surface, sampled at
    ``fps`` over its time range, with the surface's faces, UVs, normals and rest positions
    (and, for ``gltf_targets = "modes"``, the modes and their coordinates): what the
    writers take."""
    if anim.loop:  # its last frame is its first: a cycle of a whole number of frames
        cycle, whole = frame_steps(anim.end - anim.start, fps)
        if not whole:
            raise WigglyInputError(
                f"a looped animation needs a whole number of frames per cycle: "
                f"{anim.end - anim.start:g} s at {fps:g} fps is {cycle:.6g} frames, and its "
                f"seam would jump; {whole_frames_remedy(anim.end - anim.start, fps)}")
    times = anim.frame_times(fps)
    surf = anim.body.surface
    data = SurfaceAnimation(times, anim.positions(times, dtype=np.float32), surf.faces,
                            surf.uvs, surf.normals, name, rest=surf.vertices, loop=anim.loop)
    if gltf_targets == "modes":
        if getattr(anim, "driven_frames", None) is not None:
            raise WigglyInputError(
                'gltf_targets = "modes" cannot hold secondary motion: its frames are the '
                "driver's poses plus the free parts' modes, not the rest pose plus the body's "
                'modes; use "frames"')
        basis = anim.body.surface_basis  # (3p, r): positions = rest + basis q(t)
        data.mode_shapes = basis.T.reshape(anim.body.r, -1, 3)
        data.modal = anim.modal(times)[0]
    return data


@deprecated_progress
def write_animation(
    path, anim, *, overwrite: bool = False,
    frame_start: int | None = None, gltf_targets: str = "frames", fps: float = 30.0,
) -> Path:
    """Write ``anim`` to ``path`` in the format of its extension (:data:`SUPPORTED`).

    Parameters
    ----------
    path : str or Path
        Output file; for ``.obj`` the sequence's base name (``out/frame.obj`` writes
        ``out/frame_0000.obj``, ...).
    anim : SurfaceAnimation or wiggly.Animation
        The frames; their arrays are validated first.  A solved :class:`wiggly.Animation` is
        sampled at ``fps`` on its surface first (:func:`surface_animation`).
    overwrite : bool
        Replace existing output. For OBJ, any file named like a frame of the sequence blocks
        the write without it; with it, the frames are replaced, frames that wiggly wrote for
        a longer sequence are removed, and other files with a frame's name stay (a warning
        names them).
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

    Notes
    -----
    Writing OBJ, USD and glTF frames is reported as :mod:`wiggly.progress` says: a bar on a
    terminal, one line in a log.
    """
    path = Path(path)
    if not isinstance(anim, SurfaceAnimation) and hasattr(anim, "frame_times"):
        anim = surface_animation(anim, fps, path.stem, gltf_targets)
    with OutputSet() as outputs:
        stage_animation(outputs, path, anim, overwrite=overwrite,
                        frame_start=frame_start, gltf_targets=gltf_targets)
    return path


@deprecated_progress
def stage_animation(
    outputs: OutputSet, path, anim: SurfaceAnimation, *, overwrite: bool = False,
    frame_start: int | None = None, gltf_targets: str = "frames",
) -> None:
    """:func:`write_animation` into temporary files of ``outputs``
    (:class:`wiggly.files.OutputSet`), which moves them into place with the other outputs."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED:
        preview = (" (previews: wiggly.render.render_video for .mp4 and .gif, "
                   "wiggly.render.render_contact_sheet for .png)"
                   if ext in (".mp4", ".gif", ".png") else "")
        raise WigglyInputError(
            f"cannot write {path}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(SUPPORTED)}{preview}"
        )
    anim = checked_animation(anim, f"cannot write {path}")
    if gltf_targets not in GLTF_TARGETS:
        raise WigglyInputError(f"cannot write {path}: gltf_targets = {gltf_targets!r}; use one "
                               f"of {', '.join(map(repr, GLTF_TARGETS))}")
    if gltf_targets == "modes" and ext in GLTF and anim.mode_shapes is None:
        raise WigglyInputError(f"cannot write {path} with one morph target per mode: the "
                               "animation has no mode shapes (a warped motion is not a linear "
                               "combination of modes); use gltf_targets='frames'")
    if frame_start is not None:
        frame_codes(anim.times, frame_start, f"cannot write {path}", gltf=ext in GLTF)
    if ext in GLTF and np.any(np.diff(gltf_times(anim.times, frame_start, anim.loop)) <= 0):
        raise WigglyInputError(
            f"cannot write {path}: frame times are too close to be distinct in float32, which "
            "glTF uses; use a larger frame interval (or export .usd / .npz)"
        )
    if path.is_dir():
        raise WigglyInputError(f"cannot write {path}: it is a directory; give a file name")
    if ext == ".obj":
        stage_obj_sequence(outputs, path, without_seam(anim), overwrite=overwrite)
        return
    if path.exists() and not overwrite:
        raise WigglyInputError(f"{path} exists; pass overwrite=True / --overwrite to replace it")
    _warn_far(path, anim)
    tmp = outputs.stage(path)
    if ext in GLTF:
        write_glb(tmp, anim, frame_start=frame_start, targets=gltf_targets,
                  embedded=ext == ".gltf")
    elif ext == ".npz":
        write_npz(tmp, anim)
    else:
        write_usd(tmp, without_seam(anim), frame_start=frame_start)


#: float32 positions (glTF, USD, npz) rounded coarser than this share of the body's size are
#: warned about.
FLOAT32_STEP = 1e-4


def _warn_far(path: Path, anim: SurfaceAnimation) -> None:
    """Warn when the body lies so far from the origin, for its size, that the float32
    positions of glTF, USD and npz round it visibly (a 1 m body 1e5 m away: 8 mm steps)."""
    X = anim.positions
    far = float(np.abs(X).max(initial=0.0))
    size = float(np.linalg.norm(np.ptp(X[0], axis=0))) if X.shape[1] else 0.0
    step = far * np.finfo(np.float32).eps
    if size > 0 and step > FLOAT32_STEP * size:
        warn(
            f"{shown_name(path)}: the body lies {far:.3g} m from the origin, and the file's "
            f"float32 positions round it to steps of about {1e3 * step:.2g} mm ({step / size:.1e} "
            "of its size): move it near the origin for wiggly, and place it in your scene "
            "afterwards")


def read_animation(path) -> SurfaceAnimation:
    """Read an animation written by :func:`write_animation` (any format of :data:`SUPPORTED`).

    For ``.obj`` give the sequence's base name (``out/frame.obj`` reads ``out/frame_0000.obj``,
    ...); a single OBJ file without sequence frames is read as one frame.  A glTF file's
    first mesh is read with all its primitives (another tool's file may hold more meshes:
    they are left out, with a warning); node transforms are ignored, and a glTF file without
    morph targets is one frame.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in SUPPORTED:
        raise WigglyInputError(
            f"cannot read {path}: unknown extension {path.suffix!r}; "
            f"supported: {', '.join(SUPPORTED)}"
        )
    if ext == ".obj":
        anim = read_obj_sequence(path)
    else:
        if not path.is_file():
            raise WigglyInputError(f"cannot read {path}: no such file")
        reader = {".glb": read_glb, ".gltf": read_glb, ".npz": read_npz}.get(ext, read_usd)
        anim = reader(path)
    return checked_animation(anim, f"{path}")


def written_by_wiggly(path) -> bool:
    """Whether the glTF or USD file at ``path`` was written by :func:`write_animation` (its
    asset's generator, or its layer's ``wiggly`` data): its layout is then wiggly's own (a
    morph target per frame, time-sampled points), which :func:`read_animation` reads.  False
    for other files and for files that cannot be read."""
    import json
    import struct

    path = Path(path)
    ext = path.suffix.lower()
    try:
        if ext == ".glb":
            with open(path, "rb") as f:
                head = f.read(20)
                if len(head) < 20 or head[:4] != b"glTF":
                    return False
                length = struct.unpack("<I", head[12:16])[0]
                doc = json.loads(f.read(length))
        elif ext == ".gltf":
            doc = json.loads(path.read_text(encoding="utf-8"))
        elif ext in (".usd", ".usda", ".usdc"):
            from pxr import Sdf

            layer = Sdf.Layer.FindOrOpen(str(path))
            return layer is not None and "wiggly" in dict(layer.customLayerData)
        else:
            return False
    except (OSError, ValueError, UnicodeDecodeError, ImportError):
        return False
    generator = doc.get("asset", {}).get("generator", "") if isinstance(doc, dict) else ""
    return generator == "wiggly"  # write_glb's (bundled examples made by scripts differ)
