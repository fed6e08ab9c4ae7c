"""Symmetric banded matrices: the algebra of the spacetime solve (Theorem 1).

The unknowns are ordered node-major, z = (z_0, ..., z_m) with z_k = (q_k, q'_k) (2 r values),
so the spacetime energy couples neighbouring nodes only and every matrix of the solve is
banded with upper bandwidth ``bw = 4 r - 1``.  Matrices are kept in LAPACK's upper band
storage, ``ab[bw + i - j, j] = H[i, j]`` for ``i <= j`` (Fortran order, which BLAS ``dsbmv``
reads in place).

:class:`BandedCholesky` factors an SPD band matrix after symmetric equilibration and solves
with iterative refinement whose residuals are computed in twice the working precision
(compensated, Dekker's exact products): stiff keyframes (weights up to ~1e10 times the
energy) make the system ill-conditioned, and refinement with double-precision residuals
cannot recover the digits the factorization loses.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import scipy.linalg as sla

try:
    from wiggly.warp.compiled import AVAILABLE as _NUMBA

    if _NUMBA:
        from numba import njit
except ImportError:  # pragma: no cover
    _NUMBA = False

__all__ = [
    "BandedCholesky",
    "add_block",
    "add_blocks",
    "band_matvec",
    "band_to_dense",
    "dense_to_band",
    "extended_residual",
]

# Iterative refinement stops when a correction is below this relative size, or after
# REFINE_STEPS steps, or when a correction no longer shrinks.
REFINE_TOLERANCE = 4 * np.finfo(float).eps
REFINE_STEPS = 12


def band_matvec(ab: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``H x`` for symmetric H in upper band storage (BLAS ``dsbmv``)."""
    return sla.blas.dsbmv(ab.shape[0] - 1, 1.0, ab, x)


def add_blocks(ab: np.ndarray, idx: np.ndarray, blocks: np.ndarray) -> None:
    """Add symmetric dense blocks (P, b, b) at global indices ``idx`` (P, b) to ``ab``
    (indices may repeat across blocks)."""
    bw = ab.shape[0] - 1
    b = idx.shape[1]
    disjoint = len(np.unique(idx)) == idx.size  # each entry is hit once
    if disjoint and np.array_equal(idx - idx[:, :1], np.broadcast_to(np.arange(b), idx.shape)):
        # blocks of consecutive indices (a node's unknowns): entry (i, j), i <= j, of a block
        # starting at c sits at band row bw - (j - i), column c + j; disjoint blocks hit
        # distinct entries, so one indexed add does all of them
        i, j = _upper(b)
        ab[bw - (j - i), idx[:, :1] + j] += blocks[:, i, j]
        return
    rows = np.broadcast_to(idx[:, :, None], blocks.shape)
    cols = np.broadcast_to(idx[:, None, :], blocks.shape)
    upper = rows <= cols
    where = (bw + rows[upper] - cols[upper], cols[upper])
    if disjoint:
        ab[where] += blocks[upper]
    else:
        np.add.at(ab, where, blocks[upper])


@cache
def _upper(b: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the upper triangle of a b x b block (read-only)."""
    i, j = np.triu_indices(b)
    for a in (i, j):
        a.flags.writeable = False
    return i, j


def add_block(ab: np.ndarray, idx: np.ndarray, block: np.ndarray) -> None:
    """Add one symmetric block at distinct global indices ``idx``."""
    bw = ab.shape[0] - 1
    rows, cols = np.triu_indices(len(idx))
    ab[bw + idx[rows] - idx[cols], idx[cols]] += block[rows, cols]


def band_to_dense(ab: np.ndarray) -> np.ndarray:
    """The dense symmetric matrix of upper band storage ``ab`` (for tests and small N)."""
    bw, N = ab.shape[0] - 1, ab.shape[1]
    H = np.zeros((N, N))
    for d in range(bw + 1):
        i = np.arange(N - d)
        H[i, i + d] = ab[bw - d, d:]
        H[i + d, i] = ab[bw - d, d:]
    return H


def _band_scale(s: np.ndarray, bw: int) -> np.ndarray:
    """Entries ``s_i s_j`` of the upper band storage."""
    N = len(s)
    out = np.zeros((bw + 1, N))
    for d in range(bw + 1):
        out[bw - d, d:] = s[: N - d] * s[d:]
    return out


if _NUMBA:

    @njit(cache=True, nogil=True)
    def _split(a):
        c = 134217729.0 * a  # 2^27 + 1: Dekker's splitting of a double into two halves
        hi = c - (c - a)
        return hi, a - hi

    @njit(cache=True, nogil=True)
    def _residual_dd(ab, z, rhs, out):
        """``out = rhs - H z`` accumulated in double-double (exact products, compensated
        sums), rounded to double."""
        bw = ab.shape[0] - 1
        N = z.shape[0]
        for i in range(N):
            hi = rhs[i]
            lo = 0.0
            for j in range(max(0, i - bw), min(N, i + bw + 1)):
                h = ab[bw + i - j, j] if j >= i else ab[bw + j - i, i]
                p = h * z[j]
                ah, al = _split(h)
                zh, zl = _split(z[j])
                e = al * zl - (((p - ah * zh) - al * zh) - ah * zl)  # h z[j] = p + e exactly
                s = hi - p
                bb = s - hi
                t = (hi - (s - bb)) + (-p - bb)  # hi - p = s + t exactly (two-sum)
                hi = s
                lo += t - e
            out[i] = hi + lo


def extended_residual(ab: np.ndarray, z: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``rhs - H z`` computed in about twice the working precision, rounded to double."""
    z = np.ascontiguousarray(z, dtype=np.float64)
    rhs = np.ascontiguousarray(rhs, dtype=np.float64)
    if _NUMBA:
        out = np.empty_like(z)
        _residual_dd(np.asarray(ab, dtype=np.float64), z, rhs, out)
        return out
    # numpy: extended precision where the platform has it (80-bit x87 on x86-64)
    L = np.longdouble
    bw, N = ab.shape[0] - 1, len(z)
    acc = rhs.astype(L)
    zl = z.astype(L)
    for d in range(bw + 1):
        a = ab[bw - d, d:].astype(L)
        acc[: N - d] -= a * zl[d:]
        if d:
            acc[d:] -= a * zl[: N - d]
    return acc.astype(np.float64)


class BandedCholesky:
    """Factor an SPD band matrix once; :meth:`solve` returns ``H^-1 rhs`` accurately.

    ``H`` is equilibrated (``D H D`` with unit diagonal), factored by LAPACK ``dpbtrf``, and
    each solve is refined with extended-precision residuals (:func:`extended_residual`)
    until the correction is below ``REFINE_TOLERANCE`` relative.  Raises
    ``numpy.linalg.LinAlgError`` when H is not numerically positive definite.
    """

    def __init__(self, ab: np.ndarray) -> None:
        bw = ab.shape[0] - 1
        d = ab[bw]
        if not np.all(np.isfinite(ab)) or np.any(d <= 0):
            raise np.linalg.LinAlgError("the matrix is not positive definite")
        self.ab = ab
        self._s = 1.0 / np.sqrt(d)
        self._scaled = np.multiply(ab, _band_scale(self._s, bw), order="F")
        self._cb = sla.cholesky_banded(self._scaled, lower=False, check_finite=False)

    def _base(self, b: np.ndarray) -> np.ndarray:
        """``H^-1 b`` from the factorization alone (no refinement)."""
        s = self._s
        return s * sla.cho_solve_banded((self._cb, False), s * b, check_finite=False)

    def solve(self, rhs: np.ndarray, refine: bool = True) -> np.ndarray:
        """``H^-1 rhs`` for rhs (N,) or (N, k); refined unless ``refine=False``."""
        rhs = np.asarray(rhs, dtype=np.float64)
        if rhs.ndim == 2:
            return np.stack([self.solve(col, refine) for col in rhs.T], axis=1)
        z = self._base(rhs)
        if not refine:
            return z
        last = np.inf
        for _ in range(REFINE_STEPS):
            dz = self._base(extended_residual(self.ab, z, rhs))
            size = float(np.abs(dz).max(initial=0.0))
            z += dz
            if size <= REFINE_TOLERANCE * float(np.abs(z).max(initial=0.0)) or size >= last:
                break
            last = size
        return z


def dense_to_band(H: np.ndarray, bw: int | None = None) -> np.ndarray:
    """Upper band storage (Fortran order) of the symmetric matrix H with upper bandwidth
    ``bw`` (default: the full matrix); the inverse of :func:`band_to_dense`."""
    N = H.shape[0]
    bw = N - 1 if bw is None else bw
    ab = np.zeros((bw + 1, N), order="F")
    for d in range(bw + 1):
        ab[bw - d, d:] = np.diagonal(H, offset=d)
    return ab
