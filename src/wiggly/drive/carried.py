"""The free parts carried in the rig's frame: warped playback and forces of a secondary motion.

A warped secondary motion plays the free parts' modal displacement Psi q in the frame that
the rig turns each tet to: per tet the deformation gradient is the rig's warped gradient
times the free parts' own, ``F(ubar) F(Psi q)`` (:meth:`wiggly.warp.Warp.carried`), so that
a tail's bending and sag turn with the body by any angle.  Adding the two rotation vectors
instead (the warp of ``ubar + Psi q``) scales the free parts' rotations across a turn by a
by sin(a) / a: a tail's sag vanished at a half turn and pointed up at three quarters.

The free parts' dynamics then hold in that frame: the driver's inertial forces and gravity
act on Psi q turned into it, ``Psi^T M R_v(t)^T (kappa (ubar'' + alpha ubar') - gravity)``
with R_v(t) the rig's rotation at each vertex (:func:`vertex_rotations`), and the turning
frame's own forces on Psi q act too: Coriolis ``2 W x q'``, Euler ``W' x q``, centrifugal
``W x (W x q)`` and the mass damping of the frame's motion ``alpha W x q``, with W the frame's
angular velocity, fitted over the free parts as a whole (:func:`frame_rates`), in the
frame's axes.  They couple the modes; :func:`frame_forces` gives them as modal matrices, and
the solve interpolates them linearly between nodes (:mod:`wiggly.drive.secondary`).  This is
linear elasticity in a floating frame (exact for a rigid rig and small strains in it); a spin
faster than the free parts' lowest frequency overcomes their stiffness
(:func:`wiggly.drive.driver_checks.warn_spin`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from wiggly.body import Body
from wiggly.warp import Warp

__all__ = ["HeldWarp", "frame_couplings", "frame_forces", "frame_rates", "turned_forces",
           "vertex_rotations"]


class HeldWarp:
    """Warped playback of a secondary motion: the driver's own displacement d of the tet mesh
    (its extension, the rig's pose) plus the free parts' carried warp relative to the rig's,
    x = d + W_S(ubar, Psi q) - W_S(ubar, 0), one Poisson fit of ``F(ubar) H(Psi q)`` per frame
    (module doc; Schulz et al. 2014, Theorem 2) with the tet vertices that carry the driven
    group (``held``) fixed at zero.  So the driven group follows the driver as closely as the
    linear solve does, the free parts rest exactly on the rig's pose of them when q rests at
    0 (the warp of the unwarped rig is only a least-squares fit of it where the rig bends and
    turns tets: 2.6-6.5 mm off on a tail the rig raised during a turn), and the free parts'
    warp cannot shift the driven group through the warp's translation gauge."""

    def __init__(self, body: Body, held: np.ndarray) -> None:
        tets = body.tets
        self.body = body
        self.held = np.zeros(tets.n_vertices, bool)
        self.held[held] = True
        self.warp = Warp(tets.vertices, tets.tets, fixed_vertices=self.held)

    def apply(self, Ubar: np.ndarray, U: np.ndarray, D: np.ndarray) -> np.ndarray:
        """x (f, n, 3) for the unwarped rig Ubar, the free parts' modal displacements U and
        the driver's displacements D of the tet mesh (f, n, 3 each)."""
        return D + self.warp.carried(Ubar, U, relative=True)

    def jvp(self, Ubar: np.ndarray, dUbar: np.ndarray, U: np.ndarray, dU: np.ndarray,
            dD: np.ndarray) -> np.ndarray:
        """The derivative of :meth:`apply` along dUbar, dU and dD (the time derivative with
        the rig's, the free parts' and the driver's velocities)."""
        return dD + self.warp.carried_jvp(Ubar, dUbar, U, dU, relative=True)


def vertex_rotations(warp: Warp, tets: np.ndarray, Ubar: np.ndarray) -> np.ndarray:
    """Per frame and vertex of the warp's tet mesh (``tets`` (m, 4)) the rotation (F, n, 3,
    3) that the unwarped rig Ubar (3n, F) turns it by: each tet's ``exp([w]x)``, ``w`` the
    axial part of the gradient of ubar (the rotation the warp gives the tet), averaged over
    the tets around the vertex by volume and taken to the nearest rotation."""
    n, m = warp.n_vertices, warp.n_tets
    T = np.asarray(tets)
    weights = sp.csr_matrix((np.repeat(warp.volumes / 4.0, 4), (T.ravel(), np.repeat(
        np.arange(m), 4))), shape=(n, m))
    out = np.empty((Ubar.shape[1], n, 3, 3))
    for f in range(Ubar.shape[1]):
        grad = np.asarray(warp.gradient @ Ubar[:, f].reshape(n, 3)).reshape(m, 3, 3)
        # grad[t, j, i] = d ubar_i / d X_j: w = axial((A - A^T) / 2) with A = grad^T
        w = 0.5 * np.stack([grad[:, 1, 2] - grad[:, 2, 1], grad[:, 2, 0] - grad[:, 0, 2],
                            grad[:, 0, 1] - grad[:, 1, 0]], axis=1)
        mean = weights @ Rotation.from_rotvec(w).as_matrix().reshape(m, 9)
        out[f] = Rotation.from_matrix(mean.reshape(n, 3, 3)).as_matrix()
    return out


def turned_forces(C: np.ndarray, R: np.ndarray, accelerations: np.ndarray,
                  gravity: np.ndarray) -> np.ndarray:
    """What turning the free parts' forces into the rig's frame adds to their modal forcing
    (module doc), per frame: ``C (R^T - I)(accelerations - gravity)`` (F, r), with C = Psi^T
    M (r, 3n), R (F, n, 3, 3) from :func:`vertex_rotations`, ``accelerations`` (F, 3n) the
    rig's ``kappa (ubar'' + alpha ubar')`` and ``gravity`` (3,) in m/s^2."""
    F, n = R.shape[:2]
    phi = accelerations.reshape(F, n, 3) - gravity
    turned = np.einsum("fnji,fnj->fni", R, phi) - phi
    return turned.reshape(F, 3 * n) @ C.T


def frame_rates(X: np.ndarray, mass: np.ndarray, D: np.ndarray, V: np.ndarray,
                A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The angular velocity and acceleration (T, 3 each) of the frame that carries points X
    (p, 3) of masses ``mass`` (p,), in that frame's own axes, from their displacements D,
    velocities V and accelerations A (T, p, 3) on the rig: the rigid fits ``omega = I^-1 sum m
    r x (v - v_c)`` and ``omega' = I^-1 (sum m r x (a - a_c) - omega x I omega)`` (r = x - x_c
    about the mass centre, I the inertia tensor at x = X + D; exact for a rigid motion),
    turned into the frame of the points' best-fit rotation."""
    from wiggly.drive.unwarp import frame_rotations

    m = mass / mass.sum()
    turn = Rotation.from_rotvec(frame_rotations(X, D.reshape(len(D), -1).T, mass))
    x = X[None] + D
    r = x - np.einsum("p,tpj->tj", m, x)[:, None]
    inertia = (np.einsum("p,tpk,tpk->t", m, r, r)[:, None, None] * np.eye(3)
               - np.einsum("p,tpi,tpj->tij", m, r, r))
    inertia += 1e-12 * np.trace(inertia, axis1=1, axis2=2)[:, None, None] * np.eye(3)

    def moment(F: np.ndarray) -> np.ndarray:
        F = F - np.einsum("p,tpj->tj", m, F)[:, None]
        return np.einsum("p,tpj->tj", m, np.cross(r, F))

    omega = np.linalg.solve(inertia, moment(V)[..., None])[..., 0]
    spin = np.cross(omega, np.einsum("tij,tj->ti", inertia, omega))
    domega = np.linalg.solve(inertia, (moment(A) - spin)[..., None])[..., 0]
    return turn.inv().apply(omega), turn.inv().apply(domega)


def frame_couplings(C: np.ndarray, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S_a = Psi^T M [e_a]x Psi`` (3, r, r) and ``T_ab = Psi^T M e_a e_b^T Psi`` (3, 3, r,
    r) for the turning frame's forces on Psi q (C = Psi^T M)."""
    n, r = psi.shape[0] // 3, psi.shape[1]
    P = psi.reshape(n, 3, r)
    S = np.empty((3, r, r))
    T = np.empty((3, 3, r, r))
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        S[a] = C @ np.cross(e[None, :, None], P, axisa=1, axisb=1, axisc=1).reshape(3 * n, r)
        for b in range(3):
            F = np.zeros((n, 3, r))
            F[:, a] = P[:, b]
            T[a, b] = C @ F.reshape(3 * n, r)
    return S, T


def frame_forces(S: np.ndarray, T: np.ndarray, omega: np.ndarray, domega: np.ndarray,
                 alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Per time the modal matrices (T, r, r) of the turning frame's forces on the free parts,
    ``G q' + N q`` (module doc): Coriolis ``G = 2 Psi^T M [W]x Psi``, and Euler, centrifugal
    and mass damping of the frame's motion ``N = Psi^T M ([W']x + [W]x^2 + alpha [W]x) Psi``
    (Psi^T M Psi = I), for the frame's angular velocity W and acceleration W' (T, 3) in its
    own axes."""
    cross = np.einsum("ta,aij->tij", omega, S)
    G = 2.0 * cross
    N = (np.einsum("ta,aij->tij", domega, S) + alpha * cross
         + np.einsum("ta,tb,abij->tij", omega, omega, T)
         - np.sum(omega**2, axis=1)[:, None, None] * np.eye(S.shape[1]))
    return G, N
