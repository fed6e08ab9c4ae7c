"""Input checks shared by every stage: one definition, one wording.

Each check names what is wrong and what would be right, in the style of polyscope ("vertex
positions should have shape (n, 3); shape is (n, 2)"), and raises
:class:`wiggly.errors.WigglyInputError`, which every entry point reports as one message.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from wiggly.errors import WigglyInputError, counted

__all__ = [
    "array",
    "finite_vertices",
    "indices_in_range",
    "mesh_arrays",
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
