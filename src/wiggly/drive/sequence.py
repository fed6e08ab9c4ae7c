"""Mesh sequences as drivers: numbered OBJ files, and wiggly's own ``.npz`` animations.

An OBJ sequence is named by

* a pattern with a run of ``#`` for the frame number: ``walk_####.obj`` (Houdini's
  ``$F4``), matching ``walk_0001.obj``, ``walk_0002.obj``, ... (any number of digits);
* one numbered file, ``walk_000001.obj`` (Blender's OBJ exporter with "Animation"): every file
  of the folder with the same text around the number;
* wiggly's base name ``walk.obj`` when ``walk_0000.obj``, ... exist (``wiggly.export``).

Frames are ordered by number.  A frame's time is its ``# time`` comment (wiggly writes
them) when every file has one, else frame number / ``frame_rate`` (Blender's frame N at N /
fps, as in its USD files).  The vertices are the ``v`` lines in file order; the faces
(``f`` lines, polygons of any size) give the edges checked against the surface.
"""

from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np

from wiggly.drive.driver import Driver, fan_triangles, polygon_edges
from wiggly.errors import WigglyInputError, warn
from wiggly.progress import frames

__all__ = ["read_npz", "read_obj_sequence", "sequence_files"]

_V = re.compile(rb"^v[ \t]+([^\n]*)", re.M)
_F = re.compile(rb"^f[ \t]+([^\n]*)", re.M)
_TIME = re.compile(rb"^# time[ \t]+(\S+)", re.M)


def sequence_files(path: Path) -> list[tuple[int, Path]]:
    """(frame number, file) of the OBJ sequence ``path`` (module docstring), by number;
    empty if none matches."""
    path = Path(path)
    folder, name = path.parent, path.name
    if "#" in name:
        head, _, tail = name.partition("#")
        tail = tail.lstrip("#")
    else:
        m = re.fullmatch(r"(.*?)(\d+)(\.[^.]+)", name)
        if m and path.is_file():
            head, tail = m.group(1), m.group(3)
        else:
            head, tail = f"{path.stem}_", path.suffix
    pattern = re.compile(re.escape(head) + r"(\d+)" + re.escape(tail), re.IGNORECASE)
    if not folder.is_dir():
        return []
    found = []
    for entry in folder.iterdir():
        m = pattern.fullmatch(entry.name)
        if m and entry.is_file():
            found.append((int(m.group(1)), entry))
    found.sort()
    for (a, fa), (b, fb) in itertools.pairwise(found):
        if a == b:
            raise WigglyInputError(f"the OBJ sequence {path} has frame {a} twice: {fa.name} and "
                                   f"{fb.name}")
    return found


def _floats(file: Path, rows: list[bytes]) -> np.ndarray:
    try:
        values = np.array(b" ".join(rows).split(), np.float64)
        if len(values) != 3 * len(rows):  # optional w (v x y z w) or vertex colors
            values = np.array([row.split()[:3] for row in rows], np.float64)
        return values.reshape(-1, 3)
    except ValueError as e:
        raise WigglyInputError(f"cannot read {file}: malformed v line ({e})") from None


def _polygons(file: Path, data: bytes, n: int) -> list[np.ndarray]:
    polys = []
    for row in _F.findall(data):
        try:
            idx = np.array([int(c.split(b"/")[0]) for c in row.split()], np.int64)
        except ValueError as e:
            raise WigglyInputError(f"cannot read {file}: malformed f line ({e})") from None
        idx = np.where(idx < 0, n + idx, idx - 1)  # 1-based, negative: relative to the end
        if len(idx) < 3 or idx.min() < 0 or idx.max() >= n:
            raise WigglyInputError(f"cannot read {file}: a face has indices outside 1..{n}")
        polys.append(idx)
    return polys


def carries_times(path: Path) -> bool:
    """Whether the OBJ sequence at ``path`` gives its frames' times (wiggly's ``# time``
    comments, read from its first file), so that no frame rate times it."""
    files = sequence_files(Path(path))
    try:
        return bool(files) and _TIME.search(files[0][1].read_bytes()) is not None
    except OSError:
        return False


def read_obj_sequence(path: Path, *, frame_rate: float | None = None) -> Driver:
    """The driver of an OBJ sequence (module docstring), with a bar over the files when
    stages are shown (:mod:`wiggly.progress`)."""
    path = Path(path)
    files = sequence_files(path)
    if not files:
        raise WigglyInputError(
            f"cannot read the OBJ sequence {path}: no numbered files (e.g. "
            f"{path.stem.rstrip('#_')}_0001.obj) in {path.parent}")
    positions, stamps = [], []
    polys: list[np.ndarray] = []
    bar = frames(files, len(files), f"reading {path.name}", unit="file")
    for k, (_, file) in enumerate(bar):
        data = file.read_bytes()
        P = _floats(file, _V.findall(data))
        bad = np.argwhere(~np.isfinite(P))
        if bad.size:
            raise WigglyInputError(
                f"cannot read the OBJ sequence {path}: {file.name} puts vertex {bad[0, 0] + 1} "
                f"at {P[bad[0, 0]].tolist()}; positions must be finite")
        if k == 0:
            polys = _polygons(file, data, len(P))
        elif len(P) != len(positions[0]):
            raise WigglyInputError(
                f"cannot read the OBJ sequence {path}: {file.name} has {len(P)} vertices but "
                f"{files[0][1].name} has {len(positions[0])}; a driver keeps its vertices")
        positions.append(P)
        stamp = _TIME.search(data)
        stamps.append(float(stamp.group(1)) if stamp else None)
    if all(s is not None for s in stamps):
        times = np.array(stamps)
    elif frame_rate is None:
        raise WigglyInputError(
            f"the OBJ sequence {path} gives frame numbers but no times: give its frame rate "
            "(drive.frame_rate in a scene, frame_rate= in Python)")
    else:
        numbers = np.array([number for number, _ in files], np.int64)
        times = numbers / float(frame_rate)
        gaps = [(a + 1, b - 1) for a, b in itertools.pairwise(numbers) if b - a > 1]
        if gaps:
            listed = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in gaps[:4])
            one = len(gaps) == 1 and gaps[0][0] == gaps[0][1]
            warn(
                f"the OBJ sequence {path} has no files for {'frame' if one else 'frames'} "
                f"{listed}{' and more' if len(gaps) > 4 else ''}: the driver is interpolated "
                f"across {'it' if one else 'them'} (as a smooth curve, which a jerk or a cut "
                "there would not be)")
    counts = np.array([len(p) for p in polys], np.int64)
    faces, _ = fan_triangles(counts, np.concatenate(polys) if polys else np.zeros(0, np.int64))
    return Driver(times, np.stack(positions), faces, polygon_edges(polys), str(path),
                  "OBJ sequence")


def read_npz(path: Path) -> Driver:
    """The driver of a wiggly ``.npz`` animation (:mod:`wiggly.export`)."""
    from wiggly.export import read_animation

    anim = read_animation(path)
    return Driver(anim.times, anim.positions, anim.faces, polygon_edges(anim.faces), str(path),
                  "wiggly npz")
