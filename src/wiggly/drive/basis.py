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

from wiggly.body import Body
from wiggly.checks import vertex_indices
from wiggly.drive.driver import Driver, keyed_frames
from wiggly.drive.held import free_modes, held_vertices
from wiggly.drive.unwarp import Unwarp
from wiggly.keyframes import Keyframe
from wiggly.linalg import factorize_spd
from wiggly.modes import Modes
from wiggly.progress import deprecated_progress, iterations

__all__ = ["driver_poses", "enrich", "least_energy_fields"]

#: Extension penalty c relative to K's mean diagonal (per unit of E^T E): larger values fit
#: the driver no closer (the surface has more vertices than the tets) but let poorly held
#: tet vertices run wild.
_PENALTY = 1e2
#: At most this many driver frames are unwarped: those that span the others best (a walk
#: repeats itself; 300 frames of a 20k-tet body would take half a minute).
_FRAMES = 32


def least_energy_fields(body: Body, vertices: np.ndarray, D: np.ndarray) -> np.ndarray:
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


def _unwarp(body: Body, U: np.ndarray) -> np.ndarray:
    """Linear fields (3n, F) whose rotation-strain warp is approximately U (module doc;
    :class:`wiggly.drive.unwarp.Unwarp`)."""
    mass = np.asarray(body.M.sum(axis=1)).ravel()[::3]  # lumped: the diagonal
    bar = iterations("unwarping driver frames", unit="frame")
    out = Unwarp(body.tets.vertices, body.tets.tets, mass)(U, bar)
    bar.close()
    return out


#: At most this many driver frames give poses for a warped solve's start
#: (:func:`driver_poses`), evenly spread over the keyed ones.
START_FRAMES = 64


def driver_poses(body: Body, driver: Driver, *, offset: float = 0.0,
                 driver_range: tuple[float, float] | None = None, start: float | None = None,
                 end: float | None = None, warped: bool = True) -> list[Keyframe]:
    """The driver's whole poses at the frames :func:`~wiggly.drive.driven_keyframes` keys
    (at most :data:`START_FRAMES` of them, evenly spread), as keyframes of every tet vertex
    whose targets are the poses' least-energy tet fields (module doc, step 1), unwarped for
    ``warped`` solves (step 2) so that their warp is the pose.

    They start a warped solve of driven keys (``linear_start`` of
    :meth:`wiggly.SpacetimeProblem.solve`): keys on a part alone, unwarped by their best-fit
    rotation, start it far from them when the rest of the body is free (the warp turns a free
    body about its mass centre, not about the keyed part), and a solve of a body hanging from
    driven ears then crawled through hundreds of iterations."""
    surface = body.surface
    driver.check(surface.n_vertices, surface.faces, body.model.source or "of the body")
    frames, times = keyed_frames(driver, offset=offset, driver_range=driver_range,
                                 start=start, end=end)
    if len(frames) > START_FRAMES:
        pick = np.unique(np.linspace(0, len(frames) - 1, START_FRAMES).round().astype(int))
        frames, times = frames[pick], times[pick]
    U = least_energy_fields(body, np.arange(surface.n_vertices),
                            driver.positions[frames] - surface.vertices)
    if warped:
        U = _unwarp(body, U)
    X = body.rest_positions("tets")
    every = np.arange(len(X))
    return [Keyframe(float(t), every, X + U[:, j].reshape(-1, 3), on="tets",
                     name=f"driver pose {k}")
            for j, (k, t) in enumerate(zip(frames.tolist(), times.tolist(), strict=True))]


def _free_modes(body: Body, vertices: np.ndarray, count: int) -> np.ndarray:
    """The lowest ``count`` modes of the free parts with the driven ones held: eigenvectors of
    (K, M) with the tet vertices that carry ``vertices`` fixed (3n, k), zero there; none if
    nothing is free."""
    free_dofs = 3 * (body.tets.n_vertices - len(held_vertices(body, vertices)))
    if min(count, free_dofs - 1) <= 0:
        return np.zeros((3 * body.tets.n_vertices, 0))
    return free_modes(body, vertices, count)[0]


@deprecated_progress
def enrich(body: Body, driver: Driver, vertices: ArrayLike, *, warped: bool = True,
           tolerance: float = 1e-5, max_shapes: int = 32, free_modes: int = 0) -> Body:
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
    U = least_energy_fields(body, v, D)
    Phi, M, K = body.modes.vectors, body.M, body.K
    if U.shape[1] > _FRAMES:  # frames repeat themselves: keep those that span the others
        U = U[:, np.sort(_spanning(U - Phi @ (Phi.T @ (M @ U)), M, _FRAMES))]  # in time order
    if warped:
        U = _unwarp(body, U)
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
                modes=new, lumped=body.lumped, cache_dir=body.cache_dir, young=body.young)


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
