"""OBJ sequences: one file per frame."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError, warn
from wiggly.export.animation import (
    OBJ_DEFAULT_FPS,
    POSITION_FORMAT,
    FrameNormals,
    SurfaceAnimation,
    frame_progress,
)
from wiggly.files import OutputSet

# ----------------------------------------------------------------------------------------------
# OBJ sequence


def frame_names(path: Path, F: int) -> list[Path]:
    width = max(4, len(str(F - 1)))
    return [path.with_name(f"{path.stem}_{k:0{width}d}{path.suffix}") for k in range(F)]


def sequence_of(name: str) -> str | None:
    """The name of the OBJ sequence whose frame file is named ``name`` (``a_0007.obj`` ->
    ``a.obj``, as :func:`frame_names` names them), None for another name."""
    m = re.fullmatch(r"(.+)_\d+(\.obj)", name, re.IGNORECASE)
    return None if m is None else m.group(1) + m.group(2)


def existing_frames(path: Path) -> dict[int, Path]:
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


def stage_obj_sequence(outputs: OutputSet, path: Path, anim: SurfaceAnimation, *,
                        overwrite: bool) -> None:
    F = anim.n_frames
    names = frame_names(path, F)
    existing = existing_frames(path)
    if existing and not overwrite:
        first = existing[min(existing)]
        raise WigglyInputError(
            f"{first} exists; pass overwrite=True / --overwrite to replace the "
            f"{len(existing)} existing frame(s) of the OBJ sequence {path.name} in {path.parent}"
        )
    frame_normals = FrameNormals(anim)
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

    for k in frame_progress(range(F), F, path):
        data = b"".join([
            header.format(k=k, t=float(anim.times[k])).encode(),
            _format_obj_block("v", anim.positions[k], POSITION_FORMAT),
            uv_block,
            _format_obj_block("vn", frame_normals(anim.positions[k]), "%.6g"),
            face_block,
        ])
        _write_frame_file(outputs.stage(names[k]), data)
    foreign = []
    for stale in existing.values():  # frames of an earlier, longer sequence
        if stale in names:
            continue
        if written_by_wiggly_obj(stale):
            outputs.remove_on_commit(stale)
        else:
            foreign.append(stale.name)
    if foreign:
        warn(
            f"{path.parent}: left {len(foreign)} file(s) that wiggly did not write although "
            f"their names continue the OBJ sequence {path.name} ({', '.join(sorted(foreign)[:3])}"
            f"{', ...' if len(foreign) > 3 else ''}); a program reading the sequence would take "
            "them for frames")


def written_by_wiggly_obj(path: Path) -> bool:
    """Whether an OBJ file starts with the header wiggly writes on every frame."""
    try:
        with open(path, "rb") as f:
            return f.read(15) == b"# wiggly frame "
    except OSError:
        return False


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


def read_obj_sequence(path: Path) -> SurfaceAnimation:
    frames = existing_frames(path)
    if frames:
        missing = sorted(set(range(max(frames) + 1)) - set(frames))
        if missing:
            raise WigglyInputError(
                f"cannot read the OBJ sequence {path}: frame(s) {missing[:5]} missing among "
                f"{path.stem}_NNNN{path.suffix} in {path.parent}")
        files = [frames[k] for k in range(len(frames))]
    elif path.is_file():
        files = [path]
        m = re.fullmatch(r"(.+)_(\d+)", path.stem)
        sequence = path.with_name(m.group(1) + path.suffix) if m else None
        count = len(existing_frames(sequence)) if sequence is not None else 0
        if count > 1:
            warn(f"{path.name} is one frame of the OBJ sequence {sequence.name} "
                 f"({count} frames in {path.parent}): read as one frame; give "
                 f"{sequence} for the whole sequence")
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
