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
the frame's axes, and the stress that the loads in that frame put in the free parts
stiffens them (:mod:`wiggly.drive.stress`).  These couple the modes; :func:`frame_forces`
gives the frame's as modal matrices, and the solve interpolates them linearly between nodes
(:mod:`wiggly.drive.secondary`).  This is
linear elasticity in a floating frame, with the stress stiffening of its loads (exact for a
rigid rig and small strains in it).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial.transform import Rotation

from wiggly.body import Body
from wiggly.drive.stress import load_coefficients, stress_change
from wiggly.warp import Warp

__all__ = ["FrameTerms", "HeldWarp", "frame_couplings", "frame_fits", "frame_forces",
           "frame_rates", "free_parts", "moving_mean", "turned_forces"]


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


def frame_fits(parts: list[np.ndarray], everything: np.ndarray,
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(part, the vertices its frame is fitted over) per free part: its own vertices, and
    for the stray ones (fewer than 4 vertices, no frame of their own: interior tet vertices
    that the driven group's tets leave free) all the free vertices, as one part.  Their
    frames are the same fit, so one part for all of them gives the same forces and load
    stiffnesses (they share no tet) at one fit's cost: a critter held by its skinned body
    had 23 strays, and fitting each made 4.6 of its 10 s of solve."""
    fits = [(part, part) for part in parts if len(part) >= 4]
    strays = [part for part in parts if len(part) < 4]
    if strays:
        fits.append((np.concatenate(strays), everything))
    return fits


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
                A: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The angular velocity, angular acceleration, rotation vector and centre's
    acceleration (T, 3 each) of the frame that carries points X (p, 3) of masses ``mass``
    (p,), all but the rotation in that frame's own axes, from their displacements D,
    velocities V and accelerations A (T, p, 3) on the rig: the rigid fits ``omega = I^-1 sum m
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
    centre = np.einsum("p,tpj->tj", m, A)
    back = turn.inv()
    return back.apply(omega), back.apply(domega), turn.as_rotvec(), back.apply(centre)


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


class FrameTerms:
    """The turning frames' terms of the free parts' modal equations at given times: their
    forces ``G q' + N q`` (:func:`frame_forces`) and the change of the loads' stress
    stiffening (:mod:`wiggly.drive.stress`), frame by frame of each free part ``fits``
    ((part, the tet vertices its frame is fitted over) pairs)."""

    def __init__(self, vertices: np.ndarray, mass: np.ndarray,
                 fits: list[tuple[np.ndarray, np.ndarray]], C: np.ndarray, psi: np.ndarray,
                 alpha: float, gravity: np.ndarray, response: float) -> None:
        self.vertices, self.mass, self.fits = vertices, mass, fits
        self.alpha, self.gravity, self.response = alpha, gravity, response
        self.couplings = [frame_couplings(C, psi, part) for part, _ in fits]

    def __call__(self, times: np.ndarray, rig, gammas: list[np.ndarray], base: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray | float, np.ndarray]:
        """G and N (T, r, r), the stress change (T, r, r; 0.0 without ``gammas``, the parts'
        load couplings) beyond ``base`` (:func:`wiggly.drive.stress.stress_change`), and
        the fastest part's turn rate (T,), at ``times`` of the ``rig``
        (:class:`wiggly.drive.frame_spline.FrameSpline` of the tet mesh's displacements).
        The loads' stress follows their mean over ``response`` seconds (the free parts'
        quarter period): it is quasi-static, and a whip's brief pulse of acceleration is a
        push, not a load they settle under."""
        parts, betas = [], []
        at = [rig(times, d).reshape(len(times), -1, 3) for d in range(3)]
        for (_, fit), (S, T) in zip(self.fits, self.couplings, strict=True):
            omega, domega, turn, centre = frame_rates(self.vertices[fit], self.mass[fit],
                                                      *(R[:, fit] for R in at))
            parts.append((S, T, omega, domega))
            betas.append(moving_mean(times, load_coefficients(
                self.gravity, turn, centre, omega, domega), self.response))
        G, N = frame_forces(parts, self.alpha)
        change = stress_change(gammas, betas, base) if gammas else 0.0
        rates = np.max([np.linalg.norm(p[2], axis=1) for p in parts], axis=0)
        return np.asarray(G), np.asarray(N), change, rates

    def resting(self, time: float, rig, gammas: list[np.ndarray], base: np.ndarray,
                ) -> np.ndarray:
        """The stress change (r, r) of gravity alone at ``time``, turned with each part's
        frame: the loads the free parts rest under before a shot whose driver holds its
        first pose (the loads' mean at the start looked ahead into the shot's first
        accelerations: a turn that starts at 2 g left the start's sag 1.3-2.6 % off)."""
        from wiggly.drive.unwarp import frame_rotations

        D = rig(np.array([time])).reshape(-1, 3)  # the frames' turns: no rates needed
        still = np.zeros((1, 3))
        betas = [load_coefficients(self.gravity, frame_rotations(
            self.vertices[fit], D[fit].reshape(-1, 1), self.mass[fit]), still, still, still)
            for _, fit in self.fits]
        return stress_change(gammas, betas, base)[0]

    @staticmethod
    def step(G: np.ndarray, N: np.ndarray, lowest: float, per_period: int) -> float:
        """The longest step between nodes that resolves the frames' forces ``G q' + N q``
        (T, r, r) and the lowest mode (``lowest``, its largest eigenvalue over the shot) by
        ``per_period`` nodes per period of the fastest of their rates, |G| / 2, sqrt |N|
        (the turn rate, for a spin: linear interpolation of N q misses about (h rate)^2 / 8
        of it) and sqrt(lowest)."""
        rate = np.sqrt(max(float(lowest), 0.0))
        if np.size(G):
            rate = max(rate, float(np.sqrt(np.linalg.norm(N, 2, axis=(1, 2)).max())),
                       0.5 * float(np.linalg.norm(G, 2, axis=(1, 2)).max()))
        return 2 * np.pi / rate / per_period if rate > 0 else np.inf


def moving_mean(times: np.ndarray, values: np.ndarray, window: float) -> np.ndarray:
    """The mean of piecewise linear ``values`` (T, ...) at ``times`` over the ``window``
    seconds centred on each time (cut at the ends)."""
    t = np.asarray(times, float)
    if window <= 0 or len(t) < 2:
        return values
    flat = values.reshape(len(t), -1)
    area = np.concatenate([np.zeros((1, flat.shape[1])), np.cumsum(
        0.5 * (flat[1:] + flat[:-1]) * np.diff(t)[:, None], axis=0)])
    a = np.clip(t - 0.5 * window, t[0], t[-1])
    b = np.clip(t + 0.5 * window, t[0], t[-1])
    out = np.stack([np.interp(b, t, col) - np.interp(a, t, col) for col in area.T], axis=1)
    return (out / np.maximum(b - a, 1e-300)[:, None]).reshape(values.shape)
