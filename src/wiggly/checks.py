"""Input checks shared by every stage: one definition, one wording.

Each check names the field, what would be right and the value it got, in the style of
polyscope ("vertex positions should have shape (n, 3); shape is (n, 2)"; "keyframe time
should be a finite number; got 'soon'"), and raises :class:`wiggly.errors.WigglyInputError`,
which every entry point reports as one message.  Checks that take ``fail`` call it with the
message instead (it raises: the editor's :class:`~wiggly.editor.state.EditError`, or a
message prefixed with a file name).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np
from numpy.typing import ArrayLike

from wiggly.errors import WigglyInputError, counted

__all__ = [
    "animation_arrays",
    "array",
    "brief",
    "extension",
    "finite_number",
    "finite_vertices",
    "indices_in_range",
    "mesh_arrays",
    "pixel_size",
    "positive_number",
    "real_array",
    "unit_color",
    "vertex_indices",
    "vertex_set",
]


def array(
    values: ArrayLike, name: str, width: int, dtype: type = np.float64, rows: int | None = None
) -> np.ndarray:
    """``values`` as a C-contiguous (rows, width) array of ``dtype``, or a clear error."""
    a = np.asarray(values)
    if a.ndim != 2 or a.shape[1] != width or (rows is not None and len(a) != rows):
        want = f"({rows if rows is not None else 'n'}, {width})"
        raise WigglyInputError(f"{name} should have shape {want}; shape is {a.shape}")
    if np.issubdtype(dtype, np.integer) and a.size and not np.issubdtype(a.dtype, np.integer):
        if not (np.issubdtype(a.dtype, np.number) and np.array_equal(a, np.round(a))):
            raise WigglyInputError(
                f"{name} should hold integer indices; got {a.dtype} values with fractions"
            )
    elif not np.issubdtype(a.dtype, np.number) and a.size:
        raise WigglyInputError(f"{name} should hold numbers; dtype is {a.dtype}")
    return np.ascontiguousarray(a, dtype=dtype)


def finite_vertices(V: np.ndarray, source: str) -> None:
    """Every coordinate of V (n, 3) is a finite number."""
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {counted(len(bad), 'vertex')} {'has' if len(bad) == 1 else 'have'} "
            f"NaN or infinite coordinates, e.g. vertex {i} at {V[i].tolist()}; all coordinates "
            "must be finite numbers (metres)"
        )


def indices_in_range(cells: np.ndarray, n: int, source: str, what: str) -> None:
    """Every index in ``cells`` (k, c) lies in 0 .. n - 1."""
    bad = np.flatnonzero(((cells < 0) | (cells >= n)).any(axis=1))
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {counted(len(bad), what)} {'uses' if len(bad) == 1 else 'use'} vertex "
            f"indices outside 0..{n - 1}, e.g. {what} {i} with indices {cells[i].tolist()}; the "
            f"mesh has {counted(n, 'vertex')}"
        )


def mesh_arrays(
    V: ArrayLike, T: ArrayLike, source: str = "tet mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and tets (m >= 1, 4) int64 indexing them, or a clear error."""
    V = array(V, f"{source}: vertices", 3)
    T = array(T, f"{source}: tets", 4, np.int64)
    if len(T) == 0:
        raise WigglyInputError(f"{source}: the mesh has no tetrahedra; at least one is needed")
    finite_vertices(V, source)
    indices_in_range(T, len(V), source, "tet")
    return V, T


def vertex_indices(
    vertices: ArrayLike,
    n: int,
    on: str = "surface",
    what: str = "selection",
    allow_empty: bool = False,
) -> np.ndarray:
    """int64 vertex indices (order kept) from an index list or an (n,) boolean mask."""
    v = np.asarray(vertices)
    if v.dtype == bool:
        if v.shape != (n,):
            raise WigglyInputError(f"{what}: vertex mask has {v.size} entries; the {on} has {n}")
        v = np.flatnonzero(v)
    if v.ndim > 1:  # e.g. triangles or pairs: a list of indices was meant, or was it?
        raise WigglyInputError(
            f"{what}: vertex indices should be a flat list; got an array of shape {v.shape} "
            "(flatten it, e.g. np.unique(faces), if every vertex in it is meant)")
    if v.size == 0 and not allow_empty:
        raise WigglyInputError(f"{what}: selects no vertices")
    if v.size and not np.issubdtype(v.dtype, np.integer):
        if not np.issubdtype(v.dtype, np.number) or not np.all(np.isfinite(v)) or np.any(
            v != np.round(v)
        ):
            raise WigglyInputError(f"{what}: vertex indices must be integers; got {v.ravel()[:5]}")
    v = v.astype(np.int64).ravel()
    bad = v[(v < 0) | (v >= n)]
    if bad.size:
        raise WigglyInputError(
            f"{what}: vertex index {int(bad[0])} does not exist: the {on} has {n} vertices "
            f"(valid indices 0..{n - 1})"
        )
    return v


def vertex_set(vertices: ArrayLike | None, n: int, what: str = "fixed vertices") -> np.ndarray:
    """Sorted distinct int64 indices of a vertex set given as indices or an (n,) boolean mask
    (None: empty)."""
    if vertices is None:
        return np.zeros(0, np.int64)
    return np.unique(vertex_indices(vertices, n, "mesh", what, allow_empty=True))


def where(on, name: str = "on") -> str:
    """``on`` if it names a mesh of a body ("surface": the user's surface, "tets": the tet
    mesh); any other value is refused (a typo must not silently mean the tet mesh)."""
    if not (isinstance(on, str) and on in ("surface", "tets")):
        raise WigglyInputError(f"{name} = {brief(on)}: use 'surface' (the user's surface) or "
                               "'tets' (the tet mesh)")
    return on


def _raise(message: str) -> NoReturn:
    raise WigglyInputError(message)


def brief(value, limit: int = 60) -> str:
    """How a message shows a value it got: its ``repr``, cut to ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _real(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int | float | np.integer |
                                                      np.floating)


def finite_number(value, name: str, fail: Callable[[str], NoReturn] = _raise) -> float:
    """``value`` as a float: an integer or a float (not a bool), finite."""
    if not (_real(value) and math.isfinite(value)):
        fail(f"{name} should be a finite number; got {brief(value)}")
    return float(value)


def positive_number(value, name: str, unit: str = "",
                    fail: Callable[[str], NoReturn] = _raise) -> float:
    """``value`` as a float: a finite number > 0 (``unit`` is named in the message)."""
    if not (_real(value) and math.isfinite(value) and value > 0):
        fail(f"{name} should be a number > 0{f' ({unit})' if unit else ''}; got {brief(value)}")
    return float(value)


def pixel_size(size, name: str = "size", low: int = 16, high: int = 8192,
               fail: Callable[[str], NoReturn] = _raise) -> tuple[int, int]:
    """``size`` as (width, height) in whole pixels, each between ``low`` and ``high``."""
    right = f"{name} should be (width, height) with each between {low} and {high} pixels"
    try:
        w, h = (int(s) for s in size)
    except (TypeError, ValueError):
        fail(f"{right}; got {brief(size)}")
    if not (low <= w <= high and low <= h <= high):
        fail(f"{right}; got {brief(size)}")
    return w, h


def unit_color(color, name: str = "color",
               fail: Callable[[str], NoReturn] = _raise) -> tuple[float, float, float]:
    """``color`` as (red, green, blue), each a number in [0, 1]."""
    try:
        c = np.asarray(color, dtype=np.float64)
    except (TypeError, ValueError):
        c = np.zeros(0)
    if c.shape != (3,) or not np.all((c >= 0) & (c <= 1)):
        fail(f"{name} should be 3 numbers in [0, 1] (red, green, blue); got {brief(color)}")
    return tuple(c.tolist())  # type: ignore[return-value]


def extension(path, suffixes: Sequence[str], fail: Callable[[str], NoReturn] = _raise) -> str:
    """The lower-case extension of ``path``, one of ``suffixes``."""
    suffix = Path(path).suffix.lower()
    if suffix not in suffixes:
        it = f"its extension is {Path(path).suffix!r}" if suffix else "it has no extension"
        fail(f"{path} should end in {' or '.join(suffixes)}; {it}")
    return suffix


def real_array(value, name: str, shape: str,
               fail: Callable[[str], NoReturn] = _raise) -> np.ndarray:
    """``value`` as an array of integers or floats (its shape is the caller's to check; the
    ``shape`` it should have is only named in the message)."""
    try:
        a = np.asarray(value)
    except ValueError as e:
        fail(f"{name} should be an array of shape {shape}; {e}")
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        fail(f"{name} should be a real-valued array of shape {shape}; dtype is {a.dtype}")
    return a


def animation_arrays(
    times: ArrayLike, positions: ArrayLike, faces: ArrayLike, *, min_vertices: int = 1,
    fail: Callable[[str], NoReturn] = _raise,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame times (F,) float64, finite and strictly increasing; surface positions
    (F, n >= ``min_vertices``, 3), finite (float32 stays float32, anything else becomes
    float64); triangles (k >= 1, 3) int64 indexing them.  ``fail(message)`` raises (default:
    :class:`WigglyInputError`; a caller prefixes its file)."""

    def real(name: str, value, shape: str) -> np.ndarray:
        return real_array(value, name, shape, fail)

    times = real("times", times, "(F,)")
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

    positions = real("positions", positions, "(F, n, 3)")
    if positions.ndim != 3 or positions.shape[2] != 3:
        fail(f"positions should have shape (F, n, 3); shape is {positions.shape}")
    if positions.shape[0] != F:
        fail(f"positions should have shape (F, n, 3) with F = len(times) = {F}; "
             f"shape is {positions.shape}")
    n = positions.shape[1]
    if n < min_vertices:
        fail(f"positions should have shape (F, n, 3) with n >= {min_vertices} "
             f"{'vertex' if min_vertices == 1 else 'vertices'}; shape is {positions.shape}")
    if positions.dtype not in (np.float32, np.float64):
        positions = positions.astype(np.float64)
    bad = ~np.isfinite(positions)
    if bad.any():
        k, v, _ = np.argwhere(bad)[0]
        fail(f"positions should be finite; frame {k}, vertex {v} is {positions[k, v].tolist()}")

    faces = real("faces", faces, "(k, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1:
        fail(f"faces should have shape (k, 3) with k >= 1 triangles; shape is {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        fail(f"faces should be an integer array; dtype is {faces.dtype}")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= n:
        t = int(np.flatnonzero((faces < 0).any(1) | (faces >= n).any(1))[0])
        fail(f"faces should index the n = {n} vertices (0 <= i < {n}); face {t} is "
             f"{faces[t].tolist()}")
    return times, positions, faces
