"""Stress stiffening of the free parts: the geometric stiffness of their loads' stress.

Linear elasticity has no geometric stiffness: a hanging part's weight does not pull it back
like a pendulum, a standing part's does not soften it, and a spinning part is not stretched
stiff by its centrifugal load (its turning frame's centrifugal force only softens it: past
its lowest frequency that model had no stable motion).  A free part's loads in its turning
frame (:mod:`wiggly.drive.carried`) are, per unit mass, the affine field

    b(X, t) = R^T (g - a_c) - [W]x^2 (X - c)

of gravity g, the frame centre's acceleration a_c and the frame's centrifugal load (R and W
its rotation and angular velocity, c its centre at rest).  The Euler load -[W']x (X - c) is
left out: it bends the part, and a bending stress stiffens it by nothing to first order
(tension and compression cancel across a section), while on coarse tets it gave spurious
softening.  The static displacement under b with the driven group held, its stress
(:func:`wiggly.fem.linear_stress`) and the geometric stiffness of that stress
(:func:`wiggly.fem.geometric_stiffness`) are each linear in b, so twelve static solves per
part (b uniform along each axis, and each (X - c)_j e_i) give ``K_s(b(t)) = sum_k
beta_k(t) K_k`` at any time, and in the free modes ``sum_k beta_k(t) Gamma_k``, Gamma_k =
Psi^T P K_k Psi.  The free modes already hold gravity's stress in the rest pose's
orientation; the solve adds the difference, a coupling of the modes like the turning
frame's own forces, with the loads averaged over a quarter of the lowest period (the stress
is quasi-static: the linearization about the loaded state, Bathe, Finite Element
Procedures, sec. 6.3; dynamic stress of the parts' own vibration is left out).  Loads that
would soften a part below :data:`NEAR_BUCKLING` of linear elasticity's stiffness are not
followed (warned).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from wiggly.body import Body
from wiggly.errors import warn
from wiggly.fem import geometric_stiffness, linear_stress, tet_gradients
from wiggly.linalg import factorize_spd

__all__ = ["NEAR_BUCKLING", "NEGLIGIBLE", "PartLoads", "gravity_stiffnesses", "load_coefficients",
           "load_stiffnesses", "lowest_eigenvalues", "pins_the_body", "stress_change",
           "stress_matters"]

#: A load change that changes the free parts' stiffness by less than this share of the
#: lowest eigenvalue anywhere in the shot is left out.
NEGLIGIBLE = 1e-3


def pins_the_body(V: np.ndarray, held: np.ndarray) -> bool:
    """Whether the held vertices pin the body: three or more, not on a line (a rotation
    about it would stay free, and K on the free dofs singular)."""
    if len(held) < 3:
        return False
    P = V[held] - V[held].mean(axis=0)
    return bool(np.linalg.matrix_rank(P, tol=1e-9 * max(np.abs(P).max(), 1e-300)) >= 2)


def gravity_stiffnesses(body: Body, held: np.ndarray,
                        ) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix] | None:
    """The geometric stiffness of the stress that gravity puts in the body held at the tet
    vertices ``held``, per unit of gravity along the body's x, y and z axes (m/s^2): gravity
    b in the body's axes gives ``K_s(b) = sum_a b_a K_a``.  A hanging part's own weight pulls
    it back to hanging like a pendulum, a standing one's softens it (a review's hanging
    appendage swung 125 ms late, 1.27 Hz against 1.68 Hz, and a pair of standing ears 0.67
    times too little, against a corotational simulation).  None without gravity, or when the
    held vertices do not pin the body."""
    V = body.tets.vertices
    held = np.asarray(held, np.int64)
    if not np.any(body.gravity) or not pins_the_body(V, held):
        return None
    loose = np.ones(len(V), bool)
    loose[held] = False
    return load_stiffnesses(body, held, [np.flatnonzero(loose)], np.zeros((1, 3)),
                            uniform_only=True)[0].global_axes()


@dataclass(frozen=True)
class PartLoads:
    """One free part's load stiffnesses: its dofs and K_k restricted to them (12 or 3
    sparse blocks, :func:`load_stiffnesses`)."""

    dofs: np.ndarray
    blocks: tuple[sp.csr_matrix, ...]
    n_dofs: int

    def couplings(self, psi: np.ndarray) -> np.ndarray:
        """``Gamma_k = Psi^T P K_k Psi`` (k, r, r): symmetric (the part's tets join it to held
        vertices only, where Psi is zero)."""
        rows = psi[self.dofs]
        return np.stack([rows.T @ (K @ rows) for K in self.blocks])

    def global_axes(self) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
        """The uniform loads' K_0, K_1, K_2 as matrices of the whole body (3n, 3n)."""
        pick = sp.csr_matrix((np.ones(len(self.dofs)), (self.dofs, np.arange(len(self.dofs)))),
                             shape=(self.n_dofs, len(self.dofs)))
        out = [(pick @ K @ pick.T).tocsr() for K in self.blocks[:3]]
        return out[0], out[1], out[2]


def load_stiffnesses(body: Body, held: np.ndarray, parts: list[np.ndarray],
                     centres: np.ndarray, uniform_only: bool = False) -> list[PartLoads]:
    """Per free part (tet vertices ``parts[p]``, frame centre ``centres[p]`` at rest) the
    geometric stiffness K_k of the static stress under the unit loads per unit mass phi_k
    on it, the ``held`` vertices held: ``e_a`` (k = a < 3) and ``(X - c)_j e_i`` (k = 3 + 3 i
    + j); only the first three with ``uniform_only``.  Parts must not share a tet (the
    free vertices' connected components, :func:`wiggly.drive.carried.free_parts`)."""
    V, T = body.tets.vertices, body.tets.tets
    n = len(V)
    young = body.material.young if body.young is None else np.asarray(body.young)
    used = np.asarray(body.M.diagonal()).reshape(-1, 3).min(axis=1) > 0  # in some tet
    out = []
    for part, c in zip(parts, centres, strict=True):
        part = np.asarray(part, np.int64)
        part = part[used[part]]
        dofs = (3 * part[:, None] + np.arange(3)).ravel()
        count = 3 if uniform_only else 12
        if not len(part):
            out.append(PartLoads(dofs, (sp.csr_matrix((0, 0)),) * count, 3 * n))
            continue
        solve = factorize_spd(body.K[dofs][:, dofs].tocsr())
        mass = body.M[dofs]
        inside = np.zeros(n, bool)
        inside[part] = True
        near = inside[T].any(axis=1)
        Tp = T[near]
        Yp = young if np.ndim(young) == 0 else young[near]
        gradients = tet_gradients(V, Tp)  # once for the part's twelve loads
        offsets = V - c
        fields = [np.broadcast_to(e, (n, 3)) for e in np.eye(3)]
        if not uniform_only:
            fields += [offsets[:, [j]] * e for e in np.eye(3) for j in range(3)]
        blocks = []
        for phi in fields:
            u = np.zeros(3 * n)
            u[dofs] = solve(mass @ np.ascontiguousarray(phi).ravel())
            sigma = linear_stress(V, Tp, u, Yp, body.material.poisson, gradients)
            blocks.append(geometric_stiffness(V, Tp, sigma, gradients)[dofs][:, dofs].tocsr())
        out.append(PartLoads(dofs, tuple(blocks), 3 * n))
    return out


def _skew(w: np.ndarray) -> np.ndarray:
    """[w]x (T, 3, 3) of vectors w (T, 3)."""
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    return out - np.swapaxes(out, -1, -2)


def load_coefficients(gravity: np.ndarray, turn: np.ndarray, acceleration: np.ndarray,
                      omega: np.ndarray, domega: np.ndarray) -> np.ndarray:
    """beta (T, 12) of a part's load b = R^T g - a_c - ([W']x + [W]x^2)(X - c) in the loads
    of :func:`load_stiffnesses` from its frame's rotation vectors ``turn``, its centre's
    ``acceleration`` and its angular velocity and acceleration (T, 3 each; the last three in
    the frame's axes, :func:`wiggly.drive.carried.frame_rates`)."""
    g = Rotation.from_rotvec(turn).inv().apply(np.array(gravity, float))
    W = _skew(omega)
    B = -(W @ W)
    return np.concatenate([np.atleast_2d(g) - acceleration, B.reshape(len(B), 9)], axis=1)


def stress_change(gammas: list[np.ndarray], betas: list[np.ndarray],
                  base: np.ndarray) -> np.ndarray:
    """``sum_parts sum_k (beta_k(t) - base_k) Gamma_k`` (T, r, r): the modal stiffness the
    loads' stress adds beyond that in the modes (``base``, (12,): gravity's in the rest
    pose's orientation, or none)."""
    out = 0.0
    for gamma, beta in zip(gammas, betas, strict=True):
        out = out + np.einsum("tk,kij->tij", beta - base, gamma)
    return np.asarray(out)


def lowest_eigenvalues(lam: np.ndarray, change: np.ndarray) -> np.ndarray:
    """The lowest eigenvalue (T,) of ``diag(lambda)`` plus the symmetric part of ``change``
    (T, r, r) per time."""
    sym = 0.5 * (change + change.transpose(0, 2, 1))
    return np.linalg.eigvalsh(np.diag(lam)[None] + sym)[:, 0]


#: Loads that soften a free part's stiffness below this share of linear elasticity's
#: bring it near buckling: its linear sag grows more than 1 / (1 - P / P_cr) = 2 times,
#: where a real part's own geometric nonlinearity decides (it bends over).
NEAR_BUCKLING = 0.5


def stress_matters(change: np.ndarray, lam: np.ndarray, plain: np.ndarray,
                   times: np.ndarray) -> float | None:
    """The largest lowest eigenvalue of the free parts' modal stiffness with the loads'
    ``change`` at ``times`` (the driver's frames) where that change matters: by more than
    :data:`NEGLIGIBLE` of their lowest eigenvalue somewhere, and nowhere softening them below
    :data:`NEAR_BUCKLING` of linear elasticity's stiffness ``plain`` (r, r; warned); else
    None."""
    floor = max(float(lam[0]), 1e-300)
    if np.linalg.norm(change, 2, axis=(1, 2)).max(initial=0.0) <= NEGLIGIBLE * floor:
        return None
    w, Y = np.linalg.eigh(0.5 * (plain + plain.T))
    scale = Y / np.sqrt(np.maximum(w, 1e-300 * floor))  # plain^-1/2
    sym = np.diag(lam)[None] + 0.5 * (change + change.transpose(0, 2, 1))
    relative = np.linalg.eigvalsh(scale.T @ sym @ scale)[:, 0]
    k = int(np.argmin(relative))
    if relative[k] < NEAR_BUCKLING:
        warn(
            "the driver's loads on a free part (gravity turned with it, the driver's "
            f"accelerations) soften it to {max(relative[k], 0.0):.0%} of its stiffness at "
            f"t = {times[k]:.3g} s, near buckling (a soft hanging part stood on its root, or "
            "a soft part whipped sideways), where its sag would grow past what linear "
            "elasticity holds: its stiffening by its loads stays that of gravity in the rest "
            "pose; a stiffer material for it (or driving more of it) brings it back")
        return None
    return float(lowest_eigenvalues(lam, change).max())
