"""The free parts carried in the rig's frame: warped playback and forces of a secondary motion.

A warped secondary motion plays the free parts' modal displacement Psi q in the frame that
the rig turns each tet to: per tet the deformation gradient is the rig's warped gradient
times the free parts' own, ``F(ubar) F(Psi q)`` (:meth:`wiggly.warp.Warp.carried`), so that
a tail's bending and sag turn with the body by any angle.  Adding the two rotation vectors
instead (the warp of ``ubar + Psi q``) scales the free parts' rotations across a turn by a
by sin(a) / a: a tail's sag vanished at a half turn and pointed up at three quarters.

The free parts' dynamics then hold in that frame: the driver's inertial forces and gravity
act on Psi q turned into it, ``Psi^T M R_v(t)^T (kappa (ubar'' + alpha ubar') - gravity)``
with R_v(t) the rig's rotation at each vertex (:func:`turned_forces`), and the turning
frame's own forces on Psi q act too: Coriolis ``2 W x q'``, Euler ``W' x q``, centrifugal
``W x (W x q)`` and the mass damping of the frame's motion ``alpha W x q``, with W the frame's
angular velocity, fitted over each free part (:func:`free_parts`, :func:`frame_rates`), in
the frame's axes.  Gravity's stress in the free parts (their geometric stiffness, in the
modes' lambda for the rest pose's orientation) turns with each part's frame too
(:func:`gravity_stiffnesses`, :func:`turned_stress`).  These couple the modes;
:func:`frame_forces` and :func:`turned_stress` give them as modal matrices, and the solve
interpolates them linearly between nodes (:mod:`wiggly.drive.secondary`).  This is
linear elasticity in a floating frame (exact for a rigid rig and small strains in it); a spin
faster than the free parts' lowest frequency overcomes their stiffness
(:func:`wiggly.drive.driver_checks.warn_spin`).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from wiggly.body import Body
from wiggly.fem import geometric_stiffness, linear_stress
from wiggly.linalg import factorize_spd
from wiggly.warp import Warp

__all__ = ["HeldWarp", "frame_couplings", "frame_forces", "frame_rates", "free_parts",
           "gravity_stiffnesses", "stress_couplings", "turned_forces", "turned_stiffest",
           "turned_stress"]


def gravity_stiffnesses(body: Body, held: np.ndarray,
                        ) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix] | None:
    """The geometric stiffness of the stress that gravity puts in the body held at the tet
    vertices ``held``, per unit of gravity along the body's x, y and z axes (m/s^2): gravity
    b in the body's axes gives ``K_s(b) = sum_a b_a K_a`` (the static solution, its stress
    and :func:`wiggly.fem.geometric_stiffness` of it are each linear in b).  A hanging part's
    own weight pulls it back to hanging like a pendulum, a standing one's softens it; linear
    elasticity alone has neither (a review's hanging appendage swung 125 ms late, 1.27 Hz
    against 1.68 Hz, and a pair of standing ears 0.67 times too little, against a
    corotational simulation).  None without gravity, or when the held vertices lie on a
    line (a frame's rotation about it stays free)."""
    V, T = body.tets.vertices, body.tets.tets
    held = np.asarray(held, np.int64)
    if not np.any(body.gravity) or len(held) < 3:
        return None
    P = V[held] - V[held].mean(axis=0)
    if np.linalg.matrix_rank(P, tol=1e-9 * max(np.abs(P).max(), 1e-300)) < 2:
        return None
    used = np.asarray(body.M.diagonal()).reshape(-1, 3).min(axis=1) > 0
    free = np.setdiff1d(np.flatnonzero(used), held)
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    solve = factorize_spd(body.K[dofs][:, dofs].tocsr())
    young = body.material.young if body.young is None else body.young
    out = []
    for axis in np.eye(3):  # K u = M b, the static sag under a unit gravity b
        u = np.zeros(3 * len(V))
        u[dofs] = solve((body.M @ np.tile(axis, len(V)))[dofs])
        out.append(geometric_stiffness(V, T, linear_stress(V, T, u, young,
                                                           body.material.poisson)))
    return out[0], out[1], out[2]


#: A turn that changes the free parts' stiffness by less than this share of the lowest
#: eigenvalue is left out.
NEGLIGIBLE = 1e-3


def stress_couplings(psi: np.ndarray, part: np.ndarray, axes: tuple) -> np.ndarray:
    """``Gamma_a = Psi^T P K_a Psi`` (3, r, r): the modal stiffness of gravity's stress per
    unit gravity along axis a (``axes``, :func:`gravity_stiffnesses`) on one free part's
    tet vertices ``part`` (P its rows; its tets join it to held vertices only, where Psi is
    zero, so Gamma_a is symmetric)."""
    dofs = (3 * np.asarray(part)[:, None] + np.arange(3)).ravel()
    return np.stack([psi[dofs].T @ (K_a[dofs] @ psi) for K_a in axes])


def _stress_change(stress: list[np.ndarray], turns: list[np.ndarray],
                   gravity: np.ndarray) -> np.ndarray:
    """``sum_parts sum_a (R(t)^T gravity - gravity)_a Gamma_a`` (T, r, r)."""
    gravity = np.array(gravity, float)
    out = 0.0
    for Gamma, turn in zip(stress, turns, strict=True):
        b = Rotation.from_rotvec(turn).inv().apply(gravity) - gravity  # (T, 3), body axes
        out = out + np.einsum("ta,aij->tij", b, Gamma)
    return np.asarray(out)


def _lowest(lam: np.ndarray, change: np.ndarray) -> np.ndarray:
    """The lowest eigenvalue (T,) of ``diag(lambda) + change`` per time."""
    sym = 0.5 * (change + change.transpose(0, 2, 1))
    return np.linalg.eigvalsh(np.diag(lam)[None] + sym)[:, 0]


def turned_stiffest(stress: list[np.ndarray], turns: list[np.ndarray], gravity: np.ndarray,
                    lam: np.ndarray) -> float | None:
    """The largest that the free parts' lowest eigenvalue becomes as gravity's stress turns
    with them (:func:`turned_stress`; ``turns`` their frames' rotation vectors at the
    driver's frames), or None where the turn changes their stiffness by less than
    :data:`NEGLIGIBLE` of it."""
    change = _stress_change(stress, turns, gravity)
    floor = max(float(lam[0]), 1e-300)
    if np.linalg.norm(change, 2, axis=(1, 2)).max(initial=0.0) <= NEGLIGIBLE * floor:
        return None
    return max(floor, float(_lowest(lam, change).max()))


def turned_stress(stress: list[np.ndarray], turns: list[np.ndarray], gravity: np.ndarray,
                  lam: np.ndarray) -> np.ndarray:
    """The modal stiffness (T, r, r) that gravity's stress adds to the free parts as their
    frames turn, beyond that of the rest pose's orientation (in the modes' ``lam``): ``sum_a
    (R(t)^T gravity - gravity)_a Gamma_a`` summed over the parts, Gamma from
    :func:`stress_couplings` and R(t) the part's frame's rotation (``turns``, (T, 3) rotation
    vectors each): a part the driver turns upside down stands on its root and is softened
    where hanging stretched and stiffened it.  Where that would buckle a part (diag(lambda)
    plus it not positive definite at some time: a soft hanging part stood on its root),
    nothing, and a warning says so."""
    change = _stress_change(stress, turns, gravity)
    if _lowest(lam, change).min() > 0:
        return change
    warnings.warn(
        "the driver turns a free part so that it would buckle under its own weight (a soft "
        "hanging part stood on its root): its stiffening by gravity stays that of the rest "
        "pose's orientation; a stiffer material for it (or driving more of it) brings back "
        "the turned one", stacklevel=4)
    return np.zeros_like(change)


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


def free_parts(tets: np.ndarray, free: np.ndarray) -> list[np.ndarray]:
    """The free parts (a tail, each ear): the connected components of the ``free`` tet
    vertices ((n,) bool), two free vertices connected when they share a tet; vertex indices
    per part."""
    T = np.asarray(tets)
    a, b = T[:, [0, 0, 0, 1, 1, 2]].ravel(), T[:, [1, 2, 3, 2, 3, 3]].ravel()
    both = free[a] & free[b]
    n = len(free)
    graph = sp.csr_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return [np.flatnonzero(free & (label == k)) for k in np.unique(label[free])]


def turned_forces(warp: Warp, tets: np.ndarray, Ubar: np.ndarray, C: np.ndarray,
                  accelerations: np.ndarray, gravity: np.ndarray) -> np.ndarray:
    """What turning the free parts' forces into the rig's frame adds to their modal forcing
    (module doc), per frame: ``C (R_v^T - I)(accelerations - gravity)`` (F, r), with C = Psi^T
    M (r, 3n), ``accelerations`` (F, 3n) the rig's ``kappa (ubar'' + alpha ubar')``,
    ``gravity`` (3,) in m/s^2, and R_v the rotation the unwarped rig Ubar (3n, F) turns each
    vertex by: ``exp([w_v]x)``, w_v the volume-weighted mean over the tets around the vertex
    of the axial part of the gradient of ubar (the rotation vectors the warp exponentiates,
    on one branch: :mod:`wiggly.drive.unwarp`).  On the vertices where C is not zero (the
    free ones and, through the mass matrix, the held ones beside them) and their tets, a few
    frames at a time."""
    T = np.asarray(tets)
    n = warp.n_vertices
    free = np.abs(C).reshape(C.shape[0], n, 3).max(axis=(0, 2)) > 0
    near = np.flatnonzero(free[T].any(axis=1))
    G = warp.gradient[(3 * near[:, None] + np.arange(3)).ravel()]
    idx = np.flatnonzero(free)
    where = np.full(n, -1)
    where[idx] = np.arange(len(idx))
    corners = where[T[near]]
    inside = corners >= 0
    weights = sp.csr_matrix((np.repeat(warp.volumes[near], 4)[inside.ravel()],
                             (corners[inside], np.nonzero(inside)[0])),
                            shape=(len(idx), len(near)))
    weights = sp.diags(1.0 / np.asarray(weights.sum(axis=1)).ravel()) @ weights
    Cf = C[:, (3 * idx[:, None] + np.arange(3)).ravel()]
    F = Ubar.shape[1]
    out = np.empty((F, C.shape[0]))
    for f0 in range(0, F, _FRAMES):
        f1 = min(F, f0 + _FRAMES)
        k = f1 - f0
        U = np.ascontiguousarray(Ubar[:, f0:f1].reshape(n, 3, k)).reshape(n, 3 * k)
        grad = np.asarray(G @ U).reshape(len(near), 3, 3, k)  # [t, d/dX_j, u_i, frame]
        w = 0.5 * np.stack([grad[:, 1, 2] - grad[:, 2, 1], grad[:, 2, 0] - grad[:, 0, 2],
                            grad[:, 0, 1] - grad[:, 1, 0]], axis=1)  # (t, 3, k)
        w = (weights @ w.reshape(len(near), -1)).reshape(len(idx), 3, k).transpose(2, 0, 1)
        phi = accelerations[f0:f1].reshape(k, n, 3)[:, idx] - gravity
        out[f0:f1] = (_turned_back(w, phi) - phi).reshape(k, -1) @ Cf.T
    return out


#: Frames per pass of :func:`turned_forces`.
_FRAMES = 16


def _turned_back(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``exp([w]x)^T v`` (Rodrigues, about -w) for rotation vectors and vectors (..., 3)."""
    angle = np.linalg.norm(w, axis=-1, keepdims=True)
    axis = w / np.where(angle > 0, angle, 1.0)
    cos, sin = np.cos(angle), np.sin(angle)
    return (v * cos - np.cross(axis, v) * sin
            + axis * np.sum(axis * v, axis=-1, keepdims=True) * (1.0 - cos))


def frame_rates(X: np.ndarray, mass: np.ndarray, D: np.ndarray, V: np.ndarray,
                A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The angular velocity, angular acceleration and rotation vector (T, 3 each) of the
    frame that carries points X (p, 3) of masses ``mass`` (p,), the first two in that
    frame's own axes, from their displacements D, velocities V and accelerations A (T, p, 3)
    on the rig: the rigid fits ``omega = I^-1 sum m
    r x (v - v_c)`` and ``omega' = I^-1 (sum m r x (a - a_c) - omega x I omega)`` (r = x - x_c
    about the mass centre, I the inertia tensor at x = X + D; exact for a rigid motion),
    turned into the frame, which is the points' best-fit rotation."""
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
    return turn.inv().apply(omega), turn.inv().apply(domega), turn.as_rotvec()


def frame_couplings(C: np.ndarray, psi: np.ndarray,
                    vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``S_a = Psi^T M P [e_a]x Psi`` (3, r, r) and ``T_ab = Psi^T M P e_a e_b^T Psi`` (3, 3,
    r, r), P the restriction to one free part's ``vertices``: the turning frame's forces on
    that part of Psi q (C = Psi^T M)."""
    r = psi.shape[1]
    dofs = (3 * np.asarray(vertices)[:, None] + np.arange(3)).ravel()
    Cp = C[:, dofs]
    P = psi[dofs].reshape(-1, 3, r)
    S = np.empty((3, r, r))
    T = np.empty((3, 3, r, r))
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1.0
        S[a] = Cp @ np.cross(e[None, :, None], P, axisa=1, axisb=1, axisc=1).reshape(-1, r)
        for b in range(3):
            F = np.zeros_like(P)
            F[:, a] = P[:, b]
            T[a, b] = Cp @ F.reshape(-1, r)
    return S, T


def frame_forces(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                 alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """Per time the modal matrices (T, r, r) of the turning frames' forces on the free parts,
    ``G q' + N q`` (module doc), summed over the parts ``(S, T, W, W')`` (their couplings from
    :func:`frame_couplings` and their frame's angular velocity and acceleration (T, 3) in its
    own axes from :func:`frame_rates`): Coriolis ``G = 2 Psi^T M [W]x Psi``, and Euler,
    centrifugal and mass damping of the frame's motion ``N = Psi^T M ([W']x + [W]x^2 + alpha
    [W]x) Psi``, with ``[W]x^2 = W W^T - |W|^2 I``."""
    G = N = 0.0
    for S, T, omega, domega in parts:
        cross = np.einsum("ta,aij->tij", omega, S)
        square = np.einsum("ta,tb->tab", omega, omega) - np.einsum(
            "ta,ta->t", omega, omega)[:, None, None] * np.eye(3)
        G = G + 2.0 * cross
        N = N + (np.einsum("ta,aij->tij", domega, S) + alpha * cross
                 + np.einsum("tab,abij->tij", square, T))
    return G, N
