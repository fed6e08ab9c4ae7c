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

Each frame has a reference rotation w0: the mass-weighted best-fit (Kabsch) rotation of the
whole body, its rotation vector taken nearest the previous frame's (the first frame's nearest
zero), so that a body turning past 180 degrees keeps turning.  A tet's rotation vector is
the one of its polar rotation nearest w0 (one branch for all tets of a frame, whatever the
turn).  Tets squeezed below :data:`MIN_DET` or turned by more than :data:`MAX_ANGLE` away
from the frame's rotation (a least-energy extension of a driver may nearly invert tets that
bridge two limbs moving apart) keep their linear gradient F - I: their polar rotation means
nothing.  A body turned as a whole, by any angle, is not such a tet.

The per-tet pass is compiled with numba (polar decomposition by Higham's scaled Newton
iteration, rotation logarithm in closed form) and vectorized numpy
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
from wiggly.linalg import det3, factorize_spd
from wiggly.progress import activity

__all__ = ["MAX_ANGLE", "MIN_DET", "Unwarp", "compile_kernels", "frame_rotations",
           "unwarp_gradients"]

#: Extension penalty relative to the Laplacian's mean diagonal (per unit of E^T E).
_PENALTY = 1e2

#: Tets whose deformation keeps less than this volume ratio keep their linear gradient.
MIN_DET = 0.25
#: Tets turned by more than this angle (radians) from their frame's rotation keep their
#: linear gradient.
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


def _nearest_branch(w: np.ndarray, w0: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of the same rotations as ``w`` (angles in [0, pi]), each
    the one nearest the reference ``w0`` (broadcast): its angle plus a multiple of 2 pi
    about its axis (a turn of 0 takes w0's axis)."""
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    n0 = np.linalg.norm(w0, axis=-1, keepdims=True)
    axis = np.where(theta > 1e-12, w / np.maximum(theta, 1e-300),
                    w0 / np.maximum(n0, 1e-300))
    k = np.round((np.sum(w0 * axis, axis=-1, keepdims=True) - theta) / (2 * np.pi))
    return np.where(n0 > 1e-12, (theta + 2 * np.pi * k) * axis, w)


def _unwarp_numpy(Fd: np.ndarray, w0: np.ndarray | None = None) -> np.ndarray:
    """Linear gradients A (..., 3, 3) of deformation gradients Fd (module doc), by SVD;
    ``w0`` (..., 3) the reference rotation vectors (default zero)."""
    eye = np.eye(3)
    W, s, Vt = np.linalg.svd(Fd)
    flip = np.linalg.det(W @ Vt) < 0
    W[flip, :, 2] *= -1
    s[flip, 2] *= -1
    R = W @ Vt
    Sym = np.einsum("...ki,...k,...kj->...ij", Vt, s, Vt)
    w = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*R.shape[:-2], 3)
    w0 = np.zeros(3) if w0 is None else np.asarray(w0, dtype=np.float64)
    R0 = Rotation.from_rotvec(np.array(np.broadcast_to(w0, w.shape)).reshape(-1, 3)).as_matrix()
    turned = np.arccos(np.clip(0.5 * (np.einsum("...ij,...ij->...", R0.reshape(R.shape), R)
                                      - 1.0), -1.0, 1.0))
    w = _nearest_branch(w, w0)
    A = Sym - eye
    A[..., 0, 1] -= w[..., 2]
    A[..., 0, 2] += w[..., 1]
    A[..., 1, 0] += w[..., 2]
    A[..., 1, 2] -= w[..., 0]
    A[..., 2, 0] -= w[..., 1]
    A[..., 2, 1] += w[..., 0]
    bad = (det3(Fd) < MIN_DET) | (turned > MAX_ANGLE)
    A[bad] = Fd[bad] - eye
    return A


if _HAVE_NUMBA:

    @njit(cache=True, nogil=True, inline="always", fastmath={"contract"})
    def _unwarp_one(f00, f01, f02, f10, f11, f12, f20, f21, f22, min_det, max_angle,
                    w0x, w0y, w0z):  # pragma: no cover - compiled
        """A = [log R]x + S - I of one F = R S (row-major 9-tuple), log R on the branch
        nearest the reference rotation vector w0, or F - I (module doc)."""
        det = (f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20)
               + f02 * (f10 * f21 - f11 * f20))
        linear = not det >= min_det
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = f00, f01, f02, f10, f11, f12, f20, f21, f22
        theta = 0.0
        if not linear:
            # Higham's Newton iteration R <- (g R + R^-T / g) / 2 for the polar factor,
            # with determinant scaling g = |det R|^(-1/3) while far from convergence
            for it in range(40):
                c00 = r11 * r22 - r12 * r21
                c01 = r12 * r20 - r10 * r22
                c02 = r10 * r21 - r11 * r20
                c10 = r02 * r21 - r01 * r22
                c11 = r00 * r22 - r02 * r20
                c12 = r01 * r20 - r00 * r21
                c20 = r01 * r12 - r02 * r11
                c21 = r02 * r10 - r00 * r12
                c22 = r00 * r11 - r01 * r10
                d = r00 * c00 + r01 * c01 + r02 * c02
                g = abs(d) ** (-1.0 / 3.0) if it < 3 else 1.0
                h = 1.0 / (g * d)
                n00 = 0.5 * (g * r00 + c00 * h)
                n01 = 0.5 * (g * r01 + c01 * h)
                n02 = 0.5 * (g * r02 + c02 * h)
                n10 = 0.5 * (g * r10 + c10 * h)
                n11 = 0.5 * (g * r11 + c11 * h)
                n12 = 0.5 * (g * r12 + c12 * h)
                n20 = 0.5 * (g * r20 + c20 * h)
                n21 = 0.5 * (g * r21 + c21 * h)
                n22 = 0.5 * (g * r22 + c22 * h)
                change = max(abs(n00 - r00), abs(n01 - r01), abs(n02 - r02),
                             abs(n10 - r10), abs(n11 - r11), abs(n12 - r12),
                             abs(n20 - r20), abs(n21 - r21), abs(n22 - r22))
                r00, r01, r02, r10, r11, r12, r20, r21, r22 = \
                    n00, n01, n02, n10, n11, n12, n20, n21, n22
                if change < 1e-15:
                    break
            # the reference rotation R0 = exp([w0]x) (Rodrigues), and the turn R0^T R
            t0 = np.sqrt(w0x * w0x + w0y * w0y + w0z * w0z)
            a0 = 1.0 if t0 < 1e-12 else np.sin(t0) / t0
            b0 = 0.5 if t0 < 1e-12 else (1.0 - np.cos(t0)) / (t0 * t0)
            q00 = 1.0 - b0 * (w0y * w0y + w0z * w0z)
            q11 = 1.0 - b0 * (w0x * w0x + w0z * w0z)
            q22 = 1.0 - b0 * (w0x * w0x + w0y * w0y)
            q01, q10 = b0 * w0x * w0y - a0 * w0z, b0 * w0x * w0y + a0 * w0z
            q02, q20 = b0 * w0x * w0z + a0 * w0y, b0 * w0x * w0z - a0 * w0y
            q12, q21 = b0 * w0y * w0z - a0 * w0x, b0 * w0y * w0z + a0 * w0x
            trace = (q00 * r00 + q01 * r01 + q02 * r02 + q10 * r10 + q11 * r11 + q12 * r12
                     + q20 * r20 + q21 * r21 + q22 * r22)
            linear = np.arccos(min(1.0, max(-1.0, 0.5 * (trace - 1.0)))) > max_angle
        if linear:
            return (f00 - 1.0, f01, f02, f10, f11 - 1.0, f12, f20, f21, f22 - 1.0)
        # w = log R: angle theta in [0, pi] and its axis (from the symmetric part near pi,
        # where the skew part vanishes)
        cos = min(1.0, max(-1.0, 0.5 * (r00 + r11 + r22 - 1.0)))
        theta = np.arccos(cos)
        k0, k1, k2 = r21 - r12, r02 - r20, r10 - r01  # 2 sin(theta) axis
        if theta < 1e-4:
            fac = 0.5 + theta * theta / 12.0
            w0, w1, w2 = fac * k0, fac * k1, fac * k2
        elif theta < 3.0:
            fac = 0.5 * theta / np.sin(theta)
            w0, w1, w2 = fac * k0, fac * k1, fac * k2
        else:  # (R + R^T) / 2 - cos I = (1 - cos) a a^T
            one = 1.0 - cos
            d0, d1, d2 = (r00 - cos) / one, (r11 - cos) / one, (r22 - cos) / one
            s01, s02, s12 = 0.5 * (r01 + r10) / one, 0.5 * (r02 + r20) / one, \
                0.5 * (r12 + r21) / one
            if d0 >= d1 and d0 >= d2:
                x0 = np.sqrt(max(d0, 0.0))
                x1, x2 = s01 / x0, s02 / x0
            elif d1 >= d2:
                x1 = np.sqrt(max(d1, 0.0))
                x0, x2 = s01 / x1, s12 / x1
            else:
                x2 = np.sqrt(max(d2, 0.0))
                x0, x1 = s02 / x2, s12 / x2
            norm = np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            sign = -1.0 if x0 * k0 + x1 * k1 + x2 * k2 < 0.0 else 1.0
            w0, w1, w2 = (sign * theta / norm * x0, sign * theta / norm * x1,
                          sign * theta / norm * x2)
        # the branch nearest the reference: theta + 2 pi k about the same axis
        if t0 > 1e-12:
            if theta > 1e-12:
                u0, u1, u2 = w0 / theta, w1 / theta, w2 / theta
            else:
                u0, u1, u2 = w0x / t0, w0y / t0, w0z / t0
            turns = np.floor((w0x * u0 + w0y * u1 + w0z * u2 - theta) / (2.0 * np.pi) + 0.5)
            angle = theta + 2.0 * np.pi * turns
            w0, w1, w2 = angle * u0, angle * u1, angle * u2
        # S = sym(R^T F), and A = S - I + [w]x
        s00 = r00 * f00 + r10 * f10 + r20 * f20
        s11 = r01 * f01 + r11 * f11 + r21 * f21
        s22 = r02 * f02 + r12 * f12 + r22 * f22
        s01 = 0.5 * (r00 * f01 + r10 * f11 + r20 * f21 + r01 * f00 + r11 * f10 + r21 * f20)
        s02 = 0.5 * (r00 * f02 + r10 * f12 + r20 * f22 + r02 * f00 + r12 * f10 + r22 * f20)
        s12 = 0.5 * (r01 * f02 + r11 * f12 + r21 * f22 + r02 * f01 + r12 * f11 + r22 * f21)
        return (s00 - 1.0, s01 - w2, s02 + w1, s01 + w2, s11 - 1.0, s12 - w0,
                s02 - w1, s12 + w0, s22 - 1.0)

    @njit(cache=True, nogil=True, parallel=True, fastmath={"contract"})
    def _unwarp_compiled(Fd, w0, min_det, max_angle, out):  # pragma: no cover - compiled
        """Fd (m, 3, 3) with reference rotation vectors w0 (m, 3)."""
        for e in prange(Fd.shape[0]):
            F = Fd[e]
            A = _unwarp_one(F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2], F[2, 0],
                            F[2, 1], F[2, 2], min_det, max_angle, w0[e, 0], w0[e, 1],
                            w0[e, 2])
            for k in range(9):
                out[e, k // 3, k % 3] = A[k]

    @njit(cache=True, nogil=True, parallel=True, fastmath={"contract"})
    def _unwarp_fields(grad, w0, min_det, max_angle, out):  # pragma: no cover - compiled
        """grad[e, j, i, f] = d u_i / d X_j of frame f, w0[f] its reference rotation
        vector; out[e, j, i, f] = A_ij."""
        for e in prange(grad.shape[0]):
            for f in range(grad.shape[3]):
                A = _unwarp_one(1.0 + grad[e, 0, 0, f], grad[e, 1, 0, f], grad[e, 2, 0, f],
                                grad[e, 0, 1, f], 1.0 + grad[e, 1, 1, f], grad[e, 2, 1, f],
                                grad[e, 0, 2, f], grad[e, 1, 2, f], 1.0 + grad[e, 2, 2, f],
                                min_det, max_angle, w0[f, 0], w0[f, 1], w0[f, 2])
                for k in range(9):
                    out[e, k % 3, k // 3, f] = A[k]


#: Said before a first compilation of the unwarp kernels (numba's cache is cold).
COMPILING = ("compiling the unwarp kernels, once after an install: about 10 s (longer "
             "on a busy machine)")
_ready = False


def compile_kernels() -> None:
    """Compile (or load from numba's on-disk cache) the unwarp kernels once per process,
    announcing a compilation first (when stages are shown: :mod:`wiggly.progress`), so that
    a first warped secondary motion never looks hung."""
    global _ready
    if _ready or not _HAVE_NUMBA:
        return
    cold = False
    for kernel in (_unwarp_compiled, _unwarp_fields):
        try:  # numba keeps an index of the compiled signatures beside the source
            cold = cold or not kernel._cache._cache_file._load_index()
        except Exception:  # another numba's layout: assume the worst, say so
            cold = True
    with activity(COMPILING, cold):
        F = np.eye(3)[None] + 0.01
        _unwarp_compiled(F, np.zeros((1, 3)), MIN_DET, MAX_ANGLE, np.empty_like(F))
        grad = np.zeros((1, 3, 3, 1))
        _unwarp_fields(grad, np.zeros((1, 3)), MIN_DET, MAX_ANGLE, np.empty_like(grad))
    _ready = True


def unwarp_gradients(Fd: np.ndarray, w0: np.ndarray | None = None) -> np.ndarray:
    """Linear gradients A = [log R]x + S - I of deformation gradients Fd = R S, (..., 3, 3),
    log R on the branch nearest the reference rotation vectors ``w0`` (..., 3; default
    zero); F - I where the tet is nearly inverted (det F < :data:`MIN_DET`) or turned by
    more than :data:`MAX_ANGLE` from the reference (module doc)."""
    Fd = np.asarray(Fd, dtype=np.float64)
    ref = np.zeros((*Fd.shape[:-2], 3)) if w0 is None else np.broadcast_to(
        np.asarray(w0, dtype=np.float64), (*Fd.shape[:-2], 3))
    if not _HAVE_NUMBA:
        return _unwarp_numpy(Fd, ref)
    compile_kernels()
    flat = np.ascontiguousarray(Fd.reshape(-1, 3, 3))
    out = np.empty_like(flat)
    _unwarp_compiled(flat, np.ascontiguousarray(ref.reshape(-1, 3)), MIN_DET, MAX_ANGLE, out)
    return out.reshape(Fd.shape)


def _linear_gradients(grad: np.ndarray, w0: np.ndarray | None = None) -> np.ndarray:
    """A[e, j, i, f] (the layout of ``grad[e, j, i, f]`` = d u_i / d X_j of frame f) of the
    deformation gradients I + grad, frame f with the reference rotation vector ``w0[f]``
    (default zero; :func:`unwarp_gradients`)."""
    ref = np.zeros((grad.shape[3], 3)) if w0 is None else np.asarray(w0, dtype=np.float64)
    if _HAVE_NUMBA:
        compile_kernels()
        out = np.empty_like(grad)
        _unwarp_fields(np.ascontiguousarray(grad), np.ascontiguousarray(ref), MIN_DET,
                       MAX_ANGLE, out)
        return out
    Fd = np.eye(3) + np.moveaxis(grad, -1, 0).transpose(0, 1, 3, 2)  # (f, m, i, j)
    return _unwarp_numpy(Fd, ref[:, None, :]).transpose(1, 3, 2, 0)


def frame_rotations(X: np.ndarray, U: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """The reference rotation vectors (F, 3) of displacement fields U (3n, F) of points X
    (n, 3): per frame the mass-weighted best-fit (Kabsch) rotation of X + U about the mass
    centres, its vector taken nearest the previous frame's (the first's nearest zero)."""
    from wiggly.solve.problem import nearest_turn

    m = mass / mass.sum()
    A = X - m @ X
    x = X[None] + U.T.reshape(-1, len(X), 3)  # (F, n, 3)
    B = x - np.einsum("i,fij->fj", m, x)[:, None]
    H = np.einsum("fik,ij->fkj", B, m[:, None] * A)  # sum m (x - x')(X - X')^T
    V, _, Wt = np.linalg.svd(H)
    sign = np.sign(np.linalg.det(V @ Wt))
    V[:, :, 2] *= np.where(sign == 0, 1.0, sign)[:, None]
    w = Rotation.from_matrix(V @ Wt).as_rotvec()
    previous = np.zeros(3)
    for f in range(len(w)):
        w[f] = previous = nearest_turn(w[f], previous)
    return w


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
        self.vertices = np.asarray(vertices, dtype=np.float64)
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
        """Tet-mesh fields (3n, F) meeting the surface displacements d = positions[frames] -
        rest (positions (K, p, 3)), carried by the barycentric ``embedding`` (p, n): per frame
        the least-squares affine motion of the surface, d_a(X) = B X + b, plus the harmonic
        extension of the rest, the minimiser of x^T L x + c |embedding x - (d - d_a)|^2
        (L = G^T Vol G).  Affine motions (translations, rotations by any angle, uniform
        strains) are thus reproduced exactly, also at tet vertices no surface point pins (a
        harmonic extension alone bends them there: its natural boundary condition is no
        flux, which an affine field does not meet; a rigid turn by 90 degrees was off by 7 %
        of the body's size there, and its warp bent the free parts)."""
        E = sp.csr_matrix(embedding)
        EtE = (E.T @ E).tocsr()
        L = self.laplacian
        c = _PENALTY * float(L.diagonal().mean()) / max(float(EtE.diagonal().mean()), 1e-300)
        solve = factorize_spd(sp.csr_matrix(L + c * EtE))
        Et = sp.csr_matrix(E.T)
        centre = rest.mean(axis=0)
        S = np.column_stack([rest - centre, np.ones(len(rest))])  # (p, 4)
        fit = np.linalg.pinv(S)  # (4, p): the affine least-squares fit of a displacement
        T = np.column_stack([self.vertices - centre, np.ones(self.n)])  # (n, 4)
        affine = np.empty((self.n, len(frames), 3))
        rhs = np.empty((self.n, len(frames), 3))
        for j, k in enumerate(frames):  # frame by frame: no copy of all the frames at once
            d = positions[k] - rest
            coef = fit @ d  # (4, 3)
            affine[:, j] = T @ coef
            rhs[:, j] = Et @ (d - S @ coef)
        X = solve(c * rhs.reshape(self.n, -1)).reshape(self.n, len(frames), 3) + affine
        return np.ascontiguousarray(X.transpose(0, 2, 1)).reshape(3 * self.n, len(frames))

    def __call__(self, U: np.ndarray, progress: Any = None) -> np.ndarray:
        """Linear fields (3n, F) whose warp is approximately the displacements U (3n, F)."""
        n, m, F = self.n, self.m, U.shape[1]
        out = np.empty_like(U)
        w0 = frame_rotations(self.vertices, U, self.mass)
        for f0 in range(0, F, _BATCH):
            f1 = min(F, f0 + _BATCH)
            Uk = U[:, f0:f1].reshape(n, 3, -1)  # (n, 3 components, frames)
            grad = (self.G @ Uk.reshape(n, -1)).reshape(m, 3, 3, -1)  # [tet, d/dX_j, u_i, f]
            # per component i: G^T Vol G x_i = G^T Vol a_i, a_i[3 e + j] = A[e, i, j]
            a = _linear_gradients(grad, w0[f0:f1]).reshape(3 * m, -1)  # columns i*f + frame
            rhs = self.G.T @ (self.vol3[:, None] * a)
            rhs += self.mu * self.mass[:, None] * Uk.reshape(n, -1)
            out[:, f0:f1] = self.solve(rhs).reshape(3 * n, -1)
            if progress is not None:
                progress.update(f1 - f0)
        return out
