"""Unwarping: linear displacement fields whose rotation-strain warp is a given deformation.

Rotation-strain warping (Huang et al. 2011; Schulz et al. 2014, Sec. 5) maps a linear
displacement u, per tet, from its gradient [w]x + S - I (a rotation vector w and a symmetric
strain) to the deformation exp([w]x) S, and fits positions to these gradients (a Poisson
problem).  Its inverse for a deformation x = X + d, used to carry a driver's poses into the
linear coordinates of the spacetime problem, is therefore, per tet:

1. the deformation gradient F = I + grad d and its polar decomposition F = R S;
2. the linear gradient A = [log R]x + S - I, whose warp is R S = F again;
3. the volume-weighted least-squares fit of these gradients (the warp's own Poisson
   problem), with a tiny mass-weighted pull towards d that fixes the translation.

Tets squeezed below :data:`MIN_DET` or turned by more than :data:`MAX_ANGLE` (a least-energy
extension of a driver may nearly invert tets that bridge two limbs moving apart) keep their
linear gradient F - I: their polar rotation means nothing.

The per-tet pass is compiled with numba (polar decomposition by Higham's scaled Newton
iteration, rotation logarithm in closed form; about 0.1 us per tet) and vectorized numpy
(SVD) where numba is not available.
"""

from __future__ import annotations

import os
from functools import cached_property
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from wiggly.fem import tet_gradients
from wiggly.linalg import factorize_spd

__all__ = ["MAX_ANGLE", "MIN_DET", "Unwarp", "unwarp_gradients"]

#: Extension penalty relative to the Laplacian's mean diagonal (per unit of E^T E).
_PENALTY = 1e2

#: Tets whose deformation keeps less than this volume ratio keep their linear gradient.
MIN_DET = 0.25
#: Tets turned by more than this angle (radians) keep their linear gradient.
MAX_ANGLE = 2.0
#: Frames per batch (per-tet pass and one multi-RHS Poisson solve).
_BATCH = 32

try:
    if os.environ.get("WIGGLY_NUMBA", "1") == "0":
        raise ImportError("disabled by WIGGLY_NUMBA=0")
    from numba import njit, prange

    _HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised with WIGGLY_NUMBA=0
    _HAVE_NUMBA = False


def _unwarp_numpy(Fd: np.ndarray) -> np.ndarray:
    """Linear gradients A (..., 3, 3) of deformation gradients Fd (module doc), by SVD."""
    eye = np.eye(3)
    W, s, Vt = np.linalg.svd(Fd)
    flip = np.linalg.det(W @ Vt) < 0
    W[flip, :, 2] *= -1
    s[flip, 2] *= -1
    R = W @ Vt
    Sym = np.einsum("...ki,...k,...kj->...ij", Vt, s, Vt)
    w = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*R.shape[:-2], 3)
    A = Sym - eye
    A[..., 0, 1] -= w[..., 2]
    A[..., 0, 2] += w[..., 1]
    A[..., 1, 0] += w[..., 2]
    A[..., 1, 2] -= w[..., 0]
    A[..., 2, 0] -= w[..., 1]
    A[..., 2, 1] += w[..., 0]
    bad = (np.linalg.det(Fd) < MIN_DET) | (np.linalg.norm(w, axis=-1) > MAX_ANGLE)
    A[bad] = Fd[bad] - eye
    return A


if _HAVE_NUMBA:

    @njit(cache=True, nogil=True, parallel=True, fastmath={"contract"})
    def _unwarp_compiled(Fd, min_det, max_angle, out):  # pragma: no cover - compiled
        N = Fd.shape[0]
        for e in prange(N):
            F = Fd[e]
            det = (F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
                   - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
                   + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]))
            A = out[e]
            if not det >= min_det:
                for i in range(3):
                    for j in range(3):
                        A[i, j] = F[i, j] - (1.0 if i == j else 0.0)
                continue
            # Higham's Newton iteration for the polar factor, with determinant scaling
            R = F.copy()
            for _ in range(40):
                c00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
                c01 = R[1, 2] * R[2, 0] - R[1, 0] * R[2, 2]
                c02 = R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]
                c10 = R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2]
                c11 = R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0]
                c12 = R[0, 1] * R[2, 0] - R[0, 0] * R[2, 1]
                c20 = R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1]
                c21 = R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2]
                c22 = R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0]
                d = R[0, 0] * c00 + R[0, 1] * c01 + R[0, 2] * c02
                g = abs(d) ** (-1.0 / 3.0)
                # R^-T = cofactor matrix / det
                change = 0.0
                for i in range(3):
                    for j in range(3):
                        if i == 0:
                            cij = c00 if j == 0 else (c01 if j == 1 else c02)
                        elif i == 1:
                            cij = c10 if j == 0 else (c11 if j == 1 else c12)
                        else:
                            cij = c20 if j == 0 else (c21 if j == 1 else c22)
                        new = 0.5 * (g * R[i, j] + cij / (g * d))
                        change = max(change, abs(new - R[i, j]))
                        R[i, j] = new
                if change < 1e-15:
                    break
            # S = sym(R^T F)
            S = np.empty((3, 3))
            for i in range(3):
                for j in range(3):
                    S[i, j] = R[0, i] * F[0, j] + R[1, i] * F[1, j] + R[2, i] * F[2, j]
            for i in range(3):
                for j in range(i + 1, 3):
                    s = 0.5 * (S[i, j] + S[j, i])
                    S[i, j] = s
                    S[j, i] = s
            # w = log R
            cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
            cos = min(1.0, max(-1.0, cos))
            theta = np.arccos(cos)
            if theta > max_angle:
                for i in range(3):
                    for j in range(3):
                        A[i, j] = F[i, j] - (1.0 if i == j else 0.0)
                continue
            if theta < 1e-4:
                f = 0.5 + theta * theta / 12.0
            else:
                f = 0.5 * theta / np.sin(theta)
            w0 = f * (R[2, 1] - R[1, 2])
            w1 = f * (R[0, 2] - R[2, 0])
            w2 = f * (R[1, 0] - R[0, 1])
            for i in range(3):
                for j in range(3):
                    A[i, j] = S[i, j] - (1.0 if i == j else 0.0)
            A[0, 1] -= w2
            A[0, 2] += w1
            A[1, 0] += w2
            A[1, 2] -= w0
            A[2, 0] -= w1
            A[2, 1] += w0


def unwarp_gradients(Fd: np.ndarray) -> np.ndarray:
    """Linear gradients A = [log R]x + S - I of deformation gradients Fd = R S, (..., 3, 3);
    F - I where the tet is nearly inverted (det F < :data:`MIN_DET`) or turned by more than
    :data:`MAX_ANGLE` (module doc)."""
    Fd = np.asarray(Fd, dtype=np.float64)
    if not _HAVE_NUMBA:
        return _unwarp_numpy(Fd)
    flat = np.ascontiguousarray(Fd.reshape(-1, 3, 3))
    out = np.empty_like(flat)
    _unwarp_compiled(flat, MIN_DET, MAX_ANGLE, out)
    return out.reshape(Fd.shape)


class Unwarp:
    """The unwarping of one tet mesh (module doc): its gradient operator G (3m, n), tet
    volumes and Laplacian G^T Vol G, made once; the Poisson matrix is factorized on first
    use.  :meth:`extend` carries surface displacements into the tet mesh."""

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, mass: np.ndarray) -> None:
        grads, vol = tet_gradients(vertices, tets)
        m, n = len(tets), len(vertices)
        rows = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]).repeat(4, axis=1)
        cols = np.broadcast_to(tets[:, :, None], (m, 4, 3))
        self.G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())),
                               shape=(3 * m, n))
        self.vol3 = np.repeat(vol, 3)
        self.laplacian = (self.G.T @ sp.diags(self.vol3) @ self.G).tocsr()
        self.mass = np.asarray(mass, dtype=np.float64)
        self.mu = 1e-9 * float(self.laplacian.diagonal().mean()) / max(
            float(self.mass.mean()), 1e-300)
        self.n, self.m = n, m

    @cached_property
    def solve(self):
        """The factorized Poisson matrix G^T Vol G + mu M_lumped of the unwarping."""
        return factorize_spd(sp.csr_matrix(self.laplacian + sp.diags(self.mu * self.mass)))

    def extend(self, embedding: sp.spmatrix, positions: np.ndarray, frames: np.ndarray,
               rest: np.ndarray) -> np.ndarray:
        """Tet-mesh fields (3n, F) meeting the surface displacements positions[frames] - rest
        (positions (K, p, 3)), carried by the barycentric ``embedding`` (p, n), harmonic per
        component: the minimiser of x^T L x + c |embedding x - d|^2 (L = G^T Vol G).  Affine
        motions (translations, linearized rotations, uniform strains) are reproduced
        exactly."""
        E = sp.csr_matrix(embedding)
        EtE = (E.T @ E).tocsr()
        L = self.laplacian
        c = _PENALTY * float(L.diagonal().mean()) / max(float(EtE.diagonal().mean()), 1e-300)
        solve = factorize_spd(sp.csr_matrix(L + c * EtE))
        Et = sp.csr_matrix(E.T)
        base = Et @ rest  # (n, 3)
        rhs = np.empty((self.n, len(frames), 3))
        for j, k in enumerate(frames):  # frame by frame: no copy of all the frames at once
            rhs[:, j] = Et @ positions[k] - base
        X = solve(c * rhs.reshape(self.n, -1)).reshape(self.n, len(frames), 3)
        return np.ascontiguousarray(X.transpose(0, 2, 1)).reshape(3 * self.n, len(frames))

    def __call__(self, U: np.ndarray, progress: Any = None) -> np.ndarray:
        """Linear fields (3n, F) whose warp is approximately the displacements U (3n, F)."""
        n, m, F = self.n, self.m, U.shape[1]
        out = np.empty_like(U)
        for f0 in range(0, F, _BATCH):
            f1 = min(F, f0 + _BATCH)
            Uk = U[:, f0:f1].reshape(n, 3, -1)  # (n, 3 components, frames)
            grad = (self.G @ Uk.reshape(n, -1)).reshape(m, 3, 3, -1)  # [tet, d/dX_j, u_i, f]
            Fd = np.eye(3) + np.moveaxis(grad, -1, 0).transpose(0, 1, 3, 2)  # (f, m, i, j)
            A = unwarp_gradients(Fd)
            # per component i: G^T Vol G x_i = G^T Vol a_i, a_i[3 e + j] = A[e, i, j]
            a = A.transpose(1, 3, 2, 0).reshape(3 * m, -1)  # columns i * f + frame, as Uk
            rhs = self.G.T @ (self.vol3[:, None] * a)
            rhs += self.mu * self.mass[:, None] * Uk.reshape(n, -1)
            out[:, f0:f1] = self.solve(rhs).reshape(3 * n, -1)
            if progress is not None:
                progress.update(f1 - f0)
        return out
