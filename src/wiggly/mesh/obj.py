"""Reading Wavefront OBJ surfaces: every ``v`` line is a vertex, in the file's order.

trimesh's OBJ reader, which wiggly used before, keeps the ``v`` order only in its
``maintain_order`` mode, and that mode refuses negative (relative) indices with texture
coordinates, drops the ``v`` lines after the last one a face uses, and loses every UV when
one ``v`` line is unused.  OBJ's geometry is a few line kinds, so wiggly reads them itself:
``v`` (x y z, any colour or weight after them ignored), ``vt``, ``vn`` and ``f`` (``v``,
``v/vt``, ``v//vn`` or ``v/vt/vn`` corners, 1-based, or negative counting back from the last
line of that kind before the face; a polygon split into a fan of triangles from its first
corner).  Everything else (materials, groups, smoothing, lines, points) is skipped.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError, counted, warn
from wiggly.mesh.data import Surface

__all__ = ["read_obj"]

_NO_TRIANGLES = (
    "{source}: contains no triangles (only points or lines); give a closed triangle surface."
)


def read_obj(path: Path) -> Surface:
    """The OBJ file's surface: its ``v`` lines as vertices (those no face uses too), faces in
    file order, and per-vertex UVs and normals where every corner of a vertex has the same
    ``vt`` (``vn``) and every face has them; at a UV seam (one ``v`` with several ``vt``)
    there are no UVs and a warning says so.  Unused vertices get UV (0, 0) and normal 0.

    Raises
    ------
    WigglyInputError
        A number that is not one, a face corner naming a line the file does not have, or no
        faces at all.
    """
    counts = {b"v": 0, b"vt": 0, b"vn": 0}
    values: dict[bytes, list[list[bytes]]] = {b"v": [], b"vt": [], b"vn": []}
    corners: list[list[int]] = []  # per triangle corner: v, vt, vn (0-based; -1: none)
    with open(path, "rb") as file:
        data = file.read().replace(b"\\\r\n", b" ").replace(b"\\\n", b" ")
    lines = data.splitlines()
    plain = _plain(lines)
    if plain is not None:
        return Surface(*plain)
    last = len(lines)
    for line_no, raw in enumerate(lines, 1):
        words = raw.split(b"#", 1)[0].split()
        if not words:
            continue
        kind = words[0]
        if kind in values:
            values[kind].append(words[1:4 if kind != b"vt" else 3])
            counts[kind] += 1
        elif kind == b"f":
            if len(words) < 4:
                raise WigglyInputError(
                    f"{path}: line {line_no}: a face of {len(words) - 1} corners (a face "
                    f"needs 3 or more){' at the end of the file' if line_no == last else ''}"
                    ": the file is damaged or cut short; export or copy it again")
            poly = [_corner(word, counts, line_no, path) for word in words[1:]]
            for i in range(1, len(poly) - 1):
                corners.extend((poly[0], poly[i], poly[i + 1]))
    if not corners and not counts[b"v"]:
        what = "binary data" if b"\0" in data[:65536] else "no vertex (v) or face (f) lines"
        raise WigglyInputError(f"{path}: is not a Wavefront OBJ file ({what}); check its "
                               "extension, or export it again as OBJ")
    if not corners:
        raise WigglyInputError(_NO_TRIANGLES.format(source=path))
    V = _numbers(values[b"v"], 3, b"v", path)
    C = np.asarray(corners, dtype=np.int64).reshape(-1, 3, 3)
    F = C[:, :, 0]
    uvs = normals = None
    if (C[:, :, 1] >= 0).all():
        uv = _numbers(values[b"vt"], 2, b"vt", path)
        uvs = _per_vertex(uv[C[:, :, 1]], F, len(V))
        if uvs is None:
            warn(
                f"{path}: some vertices have several texture coordinates (UV seams); "
                "per-vertex UVs cannot represent that, so the surface has no UVs. The "
                "vertex order is the file's, so the animation still applies to it.")
    if (C[:, :, 2] >= 0).all():
        normals = _per_vertex(_numbers(values[b"vn"], 3, b"vn", path)[C[:, :, 2]], F, len(V))
    return Surface(V, F, uvs=uvs, normals=normals)


# lines a plain file may hold besides v and f: nothing the reader keeps
_SKIPPED = (b"#", b"o ", b"g ", b"s ", b"usemtl", b"mtllib")


def _plain(lines: list[bytes]) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices and triangles of a file of ``v x y z`` lines, then ``f a b c`` lines
    (1-based, no ``/``), comments and names (a scanner's or a converter's output, often
    millions of lines), parsed by numpy at once: the general reader takes 6 s per million
    lines.  None for any other file, which the general reader then reads, with its checks
    and messages."""
    v = [line[2:] for line in lines if line[:2] == b"v "]
    f = [line[2:] for line in lines if line[:2] == b"f "]
    if not v or not f or len(v) + len(f) + sum(
            1 for line in lines if not line.strip() or line.startswith(_SKIPPED)) != len(lines):
        return None
    last_v = len(lines) - 1 - next(i for i, line in enumerate(reversed(lines))
                                   if line[:2] == b"v ")
    first_f = next(i for i, line in enumerate(lines) if line[:2] == b"f ")
    faces = b" ".join(f)
    if last_v > first_f or b"/" in faces or b"#" in faces or b"-" in faces:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a token that is not a number: not plain
        try:
            V = np.fromstring(b" ".join(v), sep=" ")
            F = np.fromstring(faces, dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
    if V.size != 3 * len(v) or F.size != 3 * len(f) or not np.isfinite(V).all() \
            or F.min() < 1 or F.max() > len(v):
        return None
    return V.reshape(-1, 3), F.reshape(-1, 3) - 1


def _corner(word: bytes, counts: dict[bytes, int], line_no: int, path: Path) -> list[int]:
    """One face corner ``v[/vt[/vn]]`` as 0-based indices (-1 where absent), checked."""
    out = [-1, -1, -1]
    for slot, (part, kind) in enumerate(zip(word.split(b"/")[:3], (b"v", b"vt", b"vn"),
                                            strict=False)):
        if not part and slot:
            continue
        try:
            i = int(part)
        except ValueError:
            raise WigglyInputError(
                f"{path}: line {line_no}: face corner {word.decode(errors='replace')!r} is not "
                "a vertex number") from None
        n = counts[kind]
        if i == 0 or i > n or i < -n:
            what = {b"v": "vertex", b"vt": "texture coordinate", b"vn": "normal"}[kind]
            raise WigglyInputError(
                f"{path}: line {line_no}: a face names {what} {i}, but the file has "
                f"{counted(n, what)} ('{kind.decode()}' lines) before it; the file is damaged "
                "or cut short")
        out[slot] = i - 1 if i > 0 else n + i
    return out


def _numbers(rows: list[list[bytes]], width: int, kind: bytes, path: Path) -> np.ndarray:
    """The ``kind`` lines' first ``width`` numbers (a ``vt`` line's missing v is 0, OBJ's
    default; a ``v`` or ``vn`` line needs all three)."""
    out = np.zeros((len(rows), width))
    least = 1 if kind == b"vt" else width
    for k, row in enumerate(rows):
        try:
            if len(row) < least:
                raise ValueError
            out[k, :len(row)] = [float(x) for x in row[:width]]
        except ValueError:
            raise WigglyInputError(
                f"{path}: '{kind.decode()}' line {k + 1} holds "
                f"{b' '.join(row).decode(errors='replace')!r}, not {least} numbers; the file "
                "is damaged, cut short or not OBJ") from None
    return out


def _per_vertex(corner_values: np.ndarray, F: np.ndarray, n: int) -> np.ndarray | None:
    """Scatter per-corner values ``(k, 3, d)`` to ``n`` vertices (0 where no corner is), or
    None if a vertex's corners differ."""
    d = corner_values.shape[-1]
    flat = corner_values.reshape(-1, d)
    idx = F.ravel()
    low = np.full((n, d), np.inf)
    high = np.full((n, d), -np.inf)
    np.minimum.at(low, idx, flat)
    np.maximum.at(high, idx, flat)
    if (high - low > 1e-12 * (1 + np.abs(flat).max())).any():
        return None
    values = np.zeros((n, d))
    values[idx] = flat
    return values
