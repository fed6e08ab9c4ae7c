"""Structured tetrahedral meshes of simple shapes, for tests, benchmarks and examples.

:func:`box_mesh` fills an axis-aligned box with a regular grid of cubes and splits every cube
into the 6 tetrahedra of the Kuhn (Freudenthal) triangulation: one tet per permutation of the
axes, along the monotone path of cube edges from corner (0,0,0) to corner (1,1,1).  All cubes
use the same split, so the mesh is conforming (faces match across cubes), and every tet is
positively oriented (det[v1-v0, v2-v0, v3-v0] > 0).  Pure numpy.
"""

from __future__ import annotations

from itertools import permutations

import numpy as np

from wiggly.errors import WigglyInputError

__all__ = ["box_mesh"]


def _kuhn_corners() -> np.ndarray:
    """The 6 Kuhn tets of the unit cube as (6, 4) corner codes ``dx + 2 dy + 4 dz``."""
    tets = []
    for perm in permutations(range(3)):
        corner = np.zeros(3, dtype=np.int64)
        path = [corner.copy()]
        for axis in perm:
            corner[axis] = 1
            path.append(corner.copy())
        codes = [int(c[0] + 2 * c[1] + 4 * c[2]) for c in path]
        # det[e_p0, e_p0 + e_p1, e_p0 + e_p1 + e_p2] = sign of the permutation
        if np.linalg.det(np.eye(3)[list(perm)]) < 0:
            codes[1], codes[2] = codes[2], codes[1]
        tets.append(codes)
    return np.array(tets, dtype=np.int64)


def box_mesh(
    shape: tuple[int, int, int] = (4, 4, 4),
    size: tuple[float, float, float] = (1.0, 1.0, 1.0),
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh of the box ``origin + [0, lx] x [0, ly] x [0, lz]``.

    Parameters
    ----------
    shape : (nx, ny, nz)
        Number of cubes (cells) along each axis, each >= 1.
    size : (lx, ly, lz)
        Edge lengths of the box, each > 0 (metres).
    origin : (x0, y0, z0)
        Position of the minimum corner.

    Returns
    -------
    V : (n, 3) float64
        Grid vertices, ``n = (nx+1)(ny+1)(nz+1)``, x index fastest:
        vertex ``i + (nx+1) (j + (ny+1) k)`` is at ``origin + (i lx/nx, j ly/ny, k lz/nz)``.
    T : (m, 4) int64
        ``m = 6 nx ny nz`` positively oriented tets (Kuhn split of every cell).
    """
    shape_arr = np.asarray(shape)
    if shape_arr.shape != (3,) or not np.issubdtype(shape_arr.dtype, np.integer):
        raise WigglyInputError(f"shape should be 3 integers (nx, ny, nz); got {shape!r}")
    if np.any(shape_arr < 1):
        raise WigglyInputError(f"shape should have every entry >= 1; got {tuple(shape_arr)}")
    size_arr = np.asarray(size, dtype=np.float64)
    if size_arr.shape != (3,) or not np.all(np.isfinite(size_arr)) or np.any(size_arr <= 0):
        raise WigglyInputError(f"size should be 3 finite lengths > 0 (lx, ly, lz); got {size!r}")
    origin_arr = np.asarray(origin, dtype=np.float64)
    if origin_arr.shape != (3,) or not np.all(np.isfinite(origin_arr)):
        raise WigglyInputError(f"origin should be 3 finite numbers; got {origin!r}")

    nx, ny, nz = (int(s) for s in shape_arr)
    axes = [np.linspace(0.0, float(size_arr[a]), int(shape_arr[a]) + 1) for a in range(3)]
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    V = np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]) + origin_arr

    sx, sy = 1, nx + 1
    sz = (nx + 1) * (ny + 1)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = (i * sx + j * sy + k * sz).ravel()  # min corner of every cell
    code = np.arange(8)
    offset = (code & 1) * sx + ((code >> 1) & 1) * sy + ((code >> 2) & 1) * sz  # (8,)
    T = base[:, None, None] + offset[_kuhn_corners()][None, :, :]  # (cells, 6, 4)
    return V, T.reshape(-1, 4).astype(np.int64)
