"""The gauge of the warp's Poisson fit (Schulz et al. 2014, Theorem 2).

The volume-weighted Laplacian ``L = G^T Vol G`` determines ``W(u)`` only up to a constant per
connected component of the mesh.  The gauge fixes it:

* a component with fixed vertices gets Dirichlet conditions: ``W(u) = 0`` there (their rows
  and columns are eliminated from ``L``);
* a free-floating component is solved with one vertex pinned to zero (eliminated; exact,
  since the right-hand side is orthogonal to constants), then shifted by a constant so that
  its mass-weighted mean displacement equals that of ``u``.

Consequences: ``W(0) = 0``, translations pass through a free body exactly, and a linearized
rotation becomes the exact rotation about the mass centre (see :class:`wiggly.warp.Warp`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.linalg import blas
from scipy.sparse.csgraph import connected_components

__all__ = ["Gauge"]


class Gauge:
    """Eliminated vertices and floating components of a mesh's Laplacian.

    Parameters
    ----------
    laplacian : (n, n) sparse, the mesh's connectivity (only its pattern is used)
    masses : (n,) vertex masses for the mass-weighted means (massless components use the
        plain mean)
    fixed : (n,) bool, vertices held at zero
    """

    def __init__(self, laplacian: sp.spmatrix, masses: np.ndarray, fixed: np.ndarray) -> None:
        n = len(masses)
        n_comp, label = connected_components(laplacian, directed=False)
        floating = np.ones(n_comp, dtype=bool)
        floating[label[fixed]] = False
        last = np.full(n_comp, -1)
        np.maximum.at(last, label, np.arange(n))
        eliminated = fixed.copy()
        eliminated[last[floating]] = True  # one pinned vertex per floating component
        #: vertices of the reduced system, and their rows (a slice when they come first)
        self.free = np.flatnonzero(~eliminated)
        k = self.free.size
        self.rows: slice | np.ndarray = (
            slice(0, k) if k == 0 or self.free[-1] == k - 1 else self.free
        )
        n_float = int(floating.sum())
        comp_id = np.full(n_comp, -1)
        comp_id[floating] = np.arange(n_float)
        vid = comp_id[label]
        members = np.flatnonzero(vid >= 0)
        fid = vid[members]
        weight = masses[members]
        total = np.bincount(fid, weights=weight, minlength=n_float)
        massless = total <= 0.0
        weight = np.where(massless[fid], 1.0, weight)
        total = np.where(massless, np.bincount(fid, minlength=n_float), total)
        self.floating = n_float > 0
        self.mean = sp.csr_matrix((weight / total[fid], (fid, members)), shape=(n_float, n))
        self._weights = self.mean.toarray()[0] if n_float == 1 else None
        # one floating component holding every vertex: spreading is broadcasting
        self._spread = (
            None
            if n_float == 1 and members.size == n
            else sp.csr_matrix((np.ones(members.size), (members, fid)), shape=(n, n_float))
        )

    def shift(self, X: np.ndarray, means_in: np.ndarray) -> None:
        """Shift each floating component of X (n, c), in place, to the mass-weighted means
        ``means_in`` (n_float, c)."""
        delta = means_in - self.mean @ X
        if self._spread is None:
            X += delta
        else:
            X += self._spread @ delta

    def unshift(self, Y: np.ndarray) -> np.ndarray:
        """Adjoint of :meth:`shift` on Y (n, c), in place (``Y -= mean^T spread^T Y``);
        returns ``spread^T Y``, the cotangent of ``means_in``."""
        if self._spread is None and Y.flags.c_contiguous:  # rank-1 update in place
            s = Y.sum(axis=0, keepdims=True)
            blas.dger(-1.0, s[0], self._weights, a=Y.T, overwrite_a=True)
            return s
        s = (Y.sum(axis=0, keepdims=True) if self._spread is None else self._spread.T @ Y)
        Y -= self.mean.T @ s
        return s

    def frame_means(self, parts: Sequence[np.ndarray]) -> np.ndarray:
        """Mass-weighted means of the frames of ``parts`` (each (f_i, n, 3)) as (n_float, 3 f)
        columns."""
        if self._spread is None:
            return np.concatenate([self._weights @ p for p in parts]).reshape(1, -1)
        frames = [self.mean @ x for p in parts for x in p]
        return np.stack(frames, axis=1).reshape(self.mean.shape[0], -1)

    def means_adjoint(self, s: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Cotangents of the input frames (len(index), n, 3): ``mean^T s[:, index[j]]``."""
        if self._spread is None:
            return self._weights[None, :, None] * s[0, index][:, None, :]
        return np.stack([self.mean.T @ s[:, c] for c in index])
