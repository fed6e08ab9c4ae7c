"""What a driver holds, and the free parts' modes with it held.

The driver holds the tet vertices that carry the driven surface vertices and the solid under
the driven group's own triangles (:func:`held_vertices`); the free parts move in the lowest
modes of the body with those held, fixed-interface modes (:func:`free_modes`), with gravity's
geometric stiffness where it does not buckle a part (:mod:`wiggly.drive.stress`).
"""

from __future__ import annotations

import numpy as np

from wiggly.body import Body, fixed_from_surface, tets_of
from wiggly.drive.stress import gravity_stiffnesses
from wiggly.errors import WigglyInputError, warn
from wiggly.modes import compute_modes
from wiggly.progress import reporting

__all__ = ["free_modes", "held_modes", "held_vertices"]


def held_vertices(body: Body, driven: np.ndarray) -> np.ndarray:
    """The tet vertices a driver holds: those that carry the driven surface vertices (the
    corners of their tets), those inside the solid under the driven group's own triangles
    (no tet of theirs outside it, :func:`wiggly.body.tets_of` with ``whole``), and the
    body's fixed vertices."""
    T = body.tets.tets
    outside = np.ones(len(T), bool)
    outside[tets_of(body.model, driven, whole=True)] = False
    inside = np.ones(body.tets.n_vertices, bool)
    inside[T[outside].ravel()] = False
    return np.union1d(np.union1d(fixed_from_surface(body.model, driven),
                                 np.flatnonzero(inside)), body.fixed_vertices)


def free_modes(body: Body, driven: np.ndarray, count: int, stressed: bool = False,
               ) -> tuple[np.ndarray, np.ndarray]:
    """The lowest ``count`` modes of the body with :func:`held_vertices` held: (Psi (3n, r),
    lambda (r,)), Psi^T M Psi = I, Psi^T K Psi = diag(lambda), Psi zero on the held
    vertices.  ``stressed``: of K plus gravity's geometric stiffness K_s in the rest pose's
    orientation (:func:`wiggly.drive.stress.gravity_stiffnesses`), the small vibrations
    about the sagged pose, by Rayleigh-Ritz in twice as many modes of K; where K + K_s is
    not positive definite there (gravity's stress would buckle a free part: a soft part
    standing up, or sagging further than linear elasticity holds), K alone, and a warning
    says so."""
    held = held_vertices(body, driven)
    axes = gravity_stiffnesses(body, held) if stressed else None
    psi, lam, _ = held_modes(body, held, count, axes)
    return psi, lam


def held_modes(body: Body, held: np.ndarray, count: int, axes: tuple | None,
               ) -> tuple[np.ndarray, np.ndarray, bool]:
    """:func:`free_modes` for the held tet vertices and gravity's stiffness per axis (or
    None), and whether that stiffness is in them (False where it would buckle a part)."""
    free_dofs = 3 * (body.tets.n_vertices - len(held))
    if free_dofs <= 0:
        raise WigglyInputError("the driven groups hold every vertex of the body: nothing is "
                               "left free to move on its own; drive fewer vertices")
    count = min(int(count), free_dofs - 1)
    wanted = count if axes is None else min(2 * count, free_dofs - 1)
    with reporting(False):  # a step of the caller's stage, not a stage of its own
        modes = compute_modes(body.K, body.M, wanted, vertices=body.tets.vertices,
                              fixed_vertices=held, cache_dir=body.cache_dir)
    psi, lam = np.asarray(modes.vectors), np.asarray(modes.eigenvalues, float)
    stressed = False
    if axes is not None:  # Ritz: Psi^T (K + K_s) Psi = diag(lambda) + Psi^T K_s Psi
        stress = sum(float(b) * K_a for b, K_a in zip(body.gravity, axes, strict=True))
        ritz = np.diag(lam) + psi.T @ (stress @ psi)
        mu, Y = np.linalg.eigh(0.5 * (ritz + ritz.T))
        if mu[0] > 0:
            psi, lam, stressed = psi @ Y[:, :count], mu[:count], True
        else:  # K scales with E, K_s does not: s K + K_s is singular at s = the largest
            ratio = -(ritz + ritz.T - 2 * np.diag(lam)) / (2 * np.sqrt(np.outer(lam, lam)))
            times = float(np.linalg.eigvalsh(ratio)[-1])  # eigenvalue of -K_s against K
            where = np.linalg.norm((psi @ Y[:, 0]).reshape(-1, 3), axis=1).argmax()
            warn(
                "a free part would buckle under its own weight (a soft part standing up, or "
                "sagging further than linear elasticity holds), around "
                f"({', '.join(f'{c:.3g}' for c in body.tets.vertices[where])}) m: its "
                "stiffening and softening by gravity are left out, and it moves as linear "
                f"elasticity alone makes it; a material {times:.2g} times as stiff there "
                "holds it (twice that keeps it well away), or drive more of it")
    return psi[:, :count], np.maximum(lam[:count], 0.0), stressed
