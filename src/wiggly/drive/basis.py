"""A modal basis that can follow a driver: the body's eigenmodes enriched with the driver's
shapes by Rayleigh-Ritz (Schulz et al. 2014, eq. (5) and Theorem 1).

Why.  Dense keys ask the driven group to take the driver's shape at every frame.  The lowest
r eigenmodes span a skinned limb's bending only approximately (a trotting leg of the
critter: several percent of its displacement with 40 to 160 modes), so without more shapes
the driven vertices cannot follow closer than that, whatever the keys' stiffness.

What :func:`enrich` does:

1. **Extension.**  The driver's displacement d_k at frame k, given on the driven surface
   vertices, becomes the tet-mesh field of least elastic energy that meets it:
   u_k = argmin 1/2 u^T K u + c/2 |E u - d_k|^2 (E the barycentric embedding rows, c >> K).
2. **Unwarping** (for warped solves).  Per tet, I + grad u_k = R S (polar decomposition) is
   replaced by the linear gradient [log R]x + S - I, whose rotation-strain warp is R S again
   (Schulz et al. 2014, Theorem 2); the unwarped field is the volume-weighted least-squares fit
   of these gradients (the warp's own Poisson problem), so that W(unwarped field) ~ u_k.
   (Nearly inverted tets keep their linear gradient.)
   Only the (at most 32) frames whose fields span the others best are unwarped
   (column-pivoted QR).
3. **Reduction.**  The fields' parts M-orthogonal to the modes are compressed by POD
   (eigenvectors of their M-Gram) to the directions whose RMS displacement over the frames
   exceeds ``tolerance`` metres (at most ``max_shapes``).
4. **The free parts' own modes.**  The lowest modes of the body with the tet vertices that
   carry the driven vertices held (the fixed-interface modes of component mode synthesis,
   Craig & Bampton 1968): zero on the driven group, they give the free parts (tail, ears)
   motion of their own.  Without them the keys, which see every eigenmode of the whole body,
   fix the free parts' motion too while the driver plays: they follow it nearly rigidly, and
   lag and swing only once the keys stop.  Experimental (``free_modes=0`` by default): on
   the walk example they make the free parts lag during the walk, but the warped solve takes
   minutes instead of seconds and the tail swings up again near the shot's end.
5. **Rayleigh-Ritz.**  Those directions, M-orthonormalized, are rotated to diagonalize K.
   Because the eigenmodes are exact (Phi^T K Q = Lambda Phi^T M Q = 0), the new basis is the
   old modes, unchanged, followed by the Ritz vectors: M-orthonormal and K-diagonal, so the
   spacetime energy still decouples per vector (Schulz et al. 2014, eq. (4)) and Theorem 1 holds
   as it is.
   The motion is the least-force motion in a larger subspace.

The Ritz values of driver shapes are large (stiff shapes: following a skinned limb exactly
takes force), so driven keys need a high stiffness to be met
(:data:`wiggly.drive.driver.DRIVE_STIFFNESS`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from wiggly.body import Body, fixed_from_surface
from wiggly.checks import vertex_indices
from wiggly.drive.driver import Driver
from wiggly.fem import tet_gradients
from wiggly.linalg import factorize_spd
from wiggly.modes import Modes, compute_modes
from wiggly.progress import iterations

__all__ = ["enrich"]

#: Extension penalty c relative to K's mean diagonal (per unit of E^T E): larger values fit
#: the driver no closer (the surface has more vertices than the tets) but let poorly held
#: tet vertices run wild.
_PENALTY = 1e2
#: Frames per batch of the unwarping (per-tet polar decompositions).
_BATCH = 16
#: At most this many driver frames are unwarped: those that span the others best (a walk
#: repeats itself; 300 frames of a 20k-tet body would take half a minute).
_FRAMES = 32
#: Tets squeezed below this volume ratio, or turned by more than this angle (radians), keep
#: their linear gradient when unwarping: the elastic extension may nearly invert tets that
#: bridge two limbs moving apart, and their polar rotation is meaningless.
_MIN_DET, _MAX_ANGLE = 0.25, 2.0


def _extend(body: Body, vertices: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Tet-mesh fields (3n, F) of least elastic energy meeting the surface displacements
    D (F, s, 3) of ``vertices``; zero on fixed vertices."""
    n = body.tets.n_vertices
    E = sp.kron(body.surface_embedding[vertices], sp.identity(3), format="csr")
    EtE = (E.T @ E).tocsr()
    c = _PENALTY * float(body.K.diagonal().mean()) / max(float(EtE.diagonal().mean()), 1e-300)
    A = body.K + c * EtE
    fixed = np.zeros(3 * n, bool)
    fixed[(3 * body.fixed_vertices[:, None] + np.arange(3)).ravel()] = True
    if fixed.any():
        A = A + sp.diags(np.where(fixed, c, 0.0))
    U = factorize_spd(sp.csr_matrix(A))(np.asarray(c * (E.T @ D.reshape(len(D), -1).T)))
    U[fixed] = 0.0
    return U


def _laplacian(body: Body) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """The scalar P1 gradient operator G (3m, n), tet volumes (m,) and G^T Vol G."""
    V, T = body.tets.vertices, body.tets.tets
    grads, vol = tet_gradients(V, T)
    m, n = len(T), len(V)
    rows = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]).repeat(4, axis=1)
    cols = np.broadcast_to(T[:, :, None], (m, 4, 3))
    G = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n))
    L = (G.T @ sp.diags(np.repeat(vol, 3)) @ G).tocsr()
    return G, vol, L


def _unwarp(body: Body, U: np.ndarray, progress: bool) -> np.ndarray:
    """Linear fields (3n, F) whose rotation-strain warp is approximately U (module doc)."""
    n, F = body.tets.n_vertices, U.shape[1]
    G, vol, L = _laplacian(body)
    m = len(vol)
    mass = np.asarray(body.M.diagonal()[::3]) if body.lumped else \
        np.asarray(body.M.sum(axis=1)).ravel()[::3]
    mu = 1e-9 * float(L.diagonal().mean()) / max(float(mass.mean()), 1e-300)
    solve = factorize_spd(sp.csr_matrix(L + sp.diags(mu * mass)))
    out = np.empty_like(U)
    eye = np.eye(3)
    bar = iterations("unwarping driver frames", progress, unit="frame")
    for f0 in range(0, F, _BATCH):
        f1 = min(F, f0 + _BATCH)
        Uk = U[:, f0:f1].reshape(n, 3, -1)  # (n, 3 components, frames)
        grad = (G @ Uk.reshape(n, -1)).reshape(m, 3, 3, -1)  # [tet, d/dx_j, u_i, frame]
        Fd = eye + np.moveaxis(grad, -1, 0).transpose(0, 1, 3, 2)  # (f, m, 3, 3): dx_i/dX_j
        W, s, Vt = np.linalg.svd(Fd)
        flip = np.linalg.det(W @ Vt) < 0  # keep R a rotation (inverted tets: reflect)
        W[flip, :, 2] *= -1
        s[flip, 2] *= -1
        R = W @ Vt
        Sym = np.einsum("...ki,...k,...kj->...ij", Vt, s, Vt)
        w = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(*R.shape[:2], 3)
        A = Sym - eye  # the linear gradient [w]x + S - I
        A[..., 0, 1] -= w[..., 2]
        A[..., 0, 2] += w[..., 1]
        A[..., 1, 0] += w[..., 2]
        A[..., 1, 2] -= w[..., 0]
        A[..., 2, 0] -= w[..., 1]
        A[..., 2, 1] += w[..., 0]
        bad = (np.linalg.det(Fd) < _MIN_DET) | (np.linalg.norm(w, axis=-1) > _MAX_ANGLE)
        A[bad] = Fd[bad] - eye  # nearly inverted tets: their rotation means nothing
        # per component i: G^T Vol G x_i = G^T Vol a_i, a_i[3 e + j] = A[e, i, j]
        a = A.transpose(1, 3, 2, 0).reshape(3 * m, -1)  # columns: i * f + frame, as Uk
        rhs = G.T @ (np.repeat(vol, 3)[:, None] * a)
        rhs += mu * mass[:, None] * Uk.reshape(n, -1)
        out[:, f0:f1] = solve(rhs).reshape(3 * n, -1)
        bar.update(f1 - f0)
    bar.close()
    return out


def _free_modes(body: Body, vertices: np.ndarray, count: int) -> np.ndarray:
    """The lowest ``count`` modes of the free parts with the driven ones held: eigenvectors of
    (K, M) with the tet vertices that carry ``vertices`` fixed (3n, k), zero there; none if
    nothing is free."""
    support = fixed_from_surface(body.model, vertices)
    fixed = np.union1d(support, body.fixed_vertices)
    free_dofs = 3 * (body.tets.n_vertices - len(fixed))
    count = min(count, free_dofs - 1)
    if count <= 0:
        return np.zeros((3 * body.tets.n_vertices, 0))
    return compute_modes(body.K, body.M, count, vertices=body.tets.vertices,
                         fixed_vertices=fixed, cache_dir=body.cache_dir).vectors


def enrich(body: Body, driver: Driver, vertices: ArrayLike, *, warped: bool = True,
           tolerance: float = 1e-5, max_shapes: int = 32, free_modes: int = 0,
           progress: bool = False) -> Body:
    """``body`` with its eigenmodes followed by the driver's shapes and the free parts' own
    modes (module docstring): a new :class:`~wiggly.body.Body` whose ``modes`` are the old
    ones plus Ritz vectors of (a) at most ``max_shapes`` POD directions of the driver's
    displacements on ``vertices`` (surface indices), unwarped for ``warped`` solves, kept
    while their RMS displacement exceeds ``tolerance`` metres, and (b) the lowest
    ``free_modes`` modes of the rest of the body with the driven vertices held (default
    none: experimental, see the module docstring)."""
    surface = body.surface
    driver.check(surface.n_vertices, surface.faces, body.model.source or "of the body")
    v = vertex_indices(vertices, surface.n_vertices, "surface", "driven group")
    D = driver.positions[:, v] - surface.vertices[v]
    U = _extend(body, v, D)
    Phi, M, K = body.modes.vectors, body.M, body.K
    if U.shape[1] > _FRAMES:  # frames repeat themselves: keep those that span the others
        U = U[:, _spanning(U - Phi @ (Phi.T @ (M @ U)), M, _FRAMES)]
    if warped:
        U = _unwarp(body, U, progress)
    U -= Phi @ (Phi.T @ (M @ U))
    sigma2, Y = _principal(U, M)
    rms = np.sqrt(np.maximum(sigma2, 0.0) / (len(D) * body.mass))  # m, per direction
    k = int(min(max_shapes, np.sum(rms > tolerance)))
    extra = np.hstack([U @ Y[:, :k], _free_modes(body, v, free_modes)])
    extra -= Phi @ (Phi.T @ (M @ extra))
    sigma2, Y = _principal(extra, M)
    keep = sigma2 > 1e-10 * max(float(sigma2[0]), 1e-300) if len(sigma2) else sigma2 > 0
    if not keep.any():
        return body
    Q = extra @ (Y[:, keep] / np.sqrt(sigma2[keep]))  # M-orthonormal, M-orthogonal to Phi
    Q -= Phi @ (Phi.T @ (M @ Q))  # once more, against round-off
    KQ = Q.T @ (K @ Q)
    lam, Z = np.linalg.eigh(0.5 * (KQ + KQ.T))
    modes = body.modes
    new = Modes(np.concatenate([modes.eigenvalues, lam]), np.hstack([Phi, Q @ Z]),
                modes.n_rigid, modes.fixed_vertices)
    return Body(model=body.model, material=body.material, damping=body.damping,
                gravity=body.gravity, fixed_vertices=body.fixed_vertices, M=M, K=K,
                modes=new, lumped=body.lumped, cache_dir=body.cache_dir)


def _spanning(U: np.ndarray, M: sp.spmatrix, count: int) -> np.ndarray:
    """Indices of ``count`` columns of U that span the others best: column-pivoted QR of U
    with every dof weighted by the square root of M's diagonal (its mass)."""
    w = np.sqrt(np.asarray(M.diagonal()))[:, None]
    _, _, piv = sl.qr(w * U, mode="economic", pivoting=True)
    return np.sort(piv[:count])


def _principal(U: np.ndarray, M: sp.spmatrix) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (descending) and eigenvectors of the M-Gram U^T M U: the POD of the
    columns of U in the M inner product."""
    gram = U.T @ (M @ U)
    sigma2, Y = np.linalg.eigh(0.5 * (gram + gram.T))
    return sigma2[::-1], Y[:, ::-1]
