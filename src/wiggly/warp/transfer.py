"""Warp levels: the warp of the body's own mesh, or of a coarser mesh of the same solid.

A coarse level stands in for the fine warp where a cheaper, close approximation is enough
(the warped solve's first level and its Newton matrices; Schulz et al. 2014, Theorem 2):

    W~(u) = P W_c(R u),        DW~(u) Phi = P DW_c(R u) R Phi,

with ``P`` (n, n_c) the barycentric interpolation of coarse vertex values at the fine vertices
(exact for affine fields, so rigid motions pass through) and ``R`` the projection of a fine
field onto the coarse mesh.  ``R`` is the mass-weighted least-squares fit with a small pull
toward the coarse field interpolated at the coarse vertices,

    R u = argmin_x |P x - u|^2_M + eps |x - I_c u|^2_{M_c},

(``I_c`` the barycentric interpolation of the fine field at the coarse vertices, ``M_c`` the
coarse lumped masses): its normal matrix ``P^T M P + eps M_c`` is positive definite by
construction, also when a coarse vertex carries no fine vertex (a plain projection is then
singular), and ``R`` reproduces affine fields exactly, since ``P I_c`` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from wiggly.fem import tet_gradients
from wiggly.linalg import factorize_spd
from wiggly.warp.map import Warp
from wiggly.warp.modal import ModalWarp

__all__ = ["CoarseTransfer", "IdentityTransfer", "WarpLevel"]

# Weight of the pull toward the interpolated field in R, relative to the masses.
PULL = 1e-3


def _columns(A, U: np.ndarray, rows: int) -> np.ndarray:
    """A (a linear map on (k, c) columns) applied to each of f fields U (f, k, 3)."""
    f, k = U.shape[:2]
    out = A(np.ascontiguousarray(U.transpose(1, 0, 2)).reshape(k, 3 * f))
    return np.ascontiguousarray(np.asarray(out).reshape(rows, f, 3).transpose(1, 0, 2))


class IdentityTransfer:
    """The fine mesh itself: ``R = P = I``."""

    exact = True

    def __init__(self, n: int) -> None:
        self.n_fine = self.n_coarse = n
        self.lift = sp.identity(n, format="csr")

    def restrict(self, U: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(U, dtype=np.float64)

    def restrict_adjoint(self, Z: np.ndarray) -> np.ndarray:
        return Z

    def lift_fields(self, X: np.ndarray) -> np.ndarray:
        return X

    def lift_adjoint(self, Y: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(Y, dtype=np.float64)


class CoarseTransfer:
    """Transfer between a fine mesh and a coarse mesh of the same solid (module docstring).

    Parameters
    ----------
    lift : (n, n_c) sparse ``P``, coarse vertex values to the fine vertices.
    interpolation : (n_c, n) sparse ``I_c``, fine vertex values at the coarse vertices.
    masses : (n,) fine lumped vertex masses ``M``.
    coarse_masses : (n_c,) positive coarse lumped masses ``M_c``.
    """

    exact = False

    def __init__(
        self,
        lift: sp.spmatrix,
        interpolation: sp.spmatrix,
        masses: np.ndarray,
        coarse_masses: np.ndarray,
    ) -> None:
        self.lift = sp.csr_matrix(lift)
        self.n_fine, self.n_coarse = self.lift.shape
        self._masses = np.asarray(masses, dtype=np.float64)
        pull = PULL * sp.diags(np.asarray(coarse_masses, dtype=np.float64))
        PtM = self.lift.T @ sp.diags(self._masses)
        # right-hand side operator P^T M + eps M_c I_c, and the SPD normal matrix
        self._rhs = sp.csr_matrix(PtM + pull @ sp.csr_matrix(interpolation))
        self._project = factorize_spd(sp.csr_matrix(PtM @ self.lift + pull))

    def restrict(self, U: np.ndarray) -> np.ndarray:
        """``R U`` for fine fields (f, n, 3): coarse fields (f, n_c, 3)."""
        U = np.asarray(U, dtype=np.float64)
        return _columns(lambda X: self._project(self._rhs @ X), U, self.n_coarse)

    def restrict_adjoint(self, Z: np.ndarray) -> np.ndarray:
        """``R^T Z`` for coarse fields (f, n_c, 3): fine fields (f, n, 3)."""
        return _columns(lambda X: self._rhs.T @ self._project(X), Z, self.n_fine)

    def lift_fields(self, X: np.ndarray) -> np.ndarray:
        """``P X`` for coarse fields (f, n_c, 3)."""
        return _columns(lambda Y: self.lift @ Y, X, self.n_fine)

    def lift_adjoint(self, Y: np.ndarray) -> np.ndarray:
        """``P^T Y`` for fine fields (f, n, 3)."""
        return _columns(lambda X: self.lift.T @ X, np.asarray(Y, dtype=np.float64), self.n_coarse)


@dataclass(frozen=True, eq=False)
class WarpLevel:
    """The warp at one resolution, seen from the fine mesh: ``W~(u) = P W_L(R u)``.

    ``modal`` is the level's warp bound to the restricted modes ``R Phi``; ``transfer`` maps
    fields between the fine mesh and the level's; ``basis_error`` is what the level misses of
    the modes, ``Phi - P R Phi`` (n, 3, r): the fine minus the level's Jacobian at rest, where
    both warps have DW = I.  For the fine level itself the transfer is the identity, ``W~ =
    W`` and ``basis_error`` is None.
    """

    modal: ModalWarp
    transfer: IdentityTransfer | CoarseTransfer
    basis_error: np.ndarray | None = None

    @property
    def exact(self) -> bool:
        """Whether this level is the fine warp itself."""
        return self.transfer.exact

    @property
    def warp(self) -> Warp:
        return self.modal.warp

    def apply(self, U: np.ndarray) -> np.ndarray:
        """``W~(u)`` for fine fields U (f, n, 3)."""
        t = self.transfer
        return t.lift_fields(self.warp.apply(t.restrict(U)))

    def jvp(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """``DW~(u)[du] = P DW_L(R u)[R du]`` for U, dU (f, n, 3)."""
        t = self.transfer
        return t.lift_fields(self.warp.jvp(t.restrict(U), t.restrict(dU)))

    def vjp(self, U: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """``DW~(u)^T y = R^T DW_L(R u)^T P^T y`` for U, Y (f, n, 3)."""
        t = self.transfer
        return t.restrict_adjoint(self.warp.vjp(t.restrict(U), t.lift_adjoint(Y)))


def coarse_level(
    fine: Warp,
    coarse_vertices: np.ndarray,
    coarse_tets: np.ndarray,
    lift: sp.spmatrix,
    interpolation: sp.spmatrix,
    basis: np.ndarray,
) -> WarpLevel:
    """The level of a coarse mesh of the fine warp's solid, bound to the restricted modes.

    ``lift`` is ``P`` (fine vertices in coarse tets), ``interpolation`` is ``I_c`` (coarse
    vertices in fine tets).  Coarse vertices are held at rest where most of the fine
    vertices near them are; the coarse warp's gauge masses are ``P^T M``, so interpolated
    fields keep the fine mass-weighted mean.
    """
    P = sp.csr_matrix(lift)
    Ic = sp.csr_matrix(interpolation)
    m = fine.masses
    n_c = P.shape[1]
    density = m.sum() / max(fine.volumes.sum(), np.finfo(float).tiny)
    T_c = np.asarray(coarse_tets, dtype=np.int64)
    _, vol_c = tet_gradients(coarse_vertices, T_c)
    own = density * np.bincount(T_c.ravel(), weights=np.repeat(vol_c / 4.0, 4), minlength=n_c)
    transfer = CoarseTransfer(P, Ic, m, np.maximum(own, 1e-12 * own.max()))
    weight = abs(Ic)
    share = (weight @ fine.fixed.astype(float)) / np.maximum(
        weight @ np.ones(fine.n_vertices), 1e-300
    )
    warp_c = Warp(
        coarse_vertices,
        coarse_tets,
        masses=P.T @ m,  # signed where fine vertices are extrapolated: the mean stays exact
        fixed_vertices=np.flatnonzero(share > 0.5) if fine.fixed.any() else None,
    )
    n, r = fine.n_vertices, np.shape(basis)[-1]
    Phi = np.asarray(basis, dtype=np.float64).reshape(n, 3, r).transpose(2, 0, 1)
    restricted = transfer.restrict(Phi)  # R Phi: (r, n_c, 3)
    error = np.ascontiguousarray((Phi - transfer.lift_fields(restricted)).transpose(1, 2, 0))
    error.flags.writeable = False
    return WarpLevel(ModalWarp(warp_c, restricted.transpose(1, 2, 0)), transfer, error)


def fine_level(fine: Warp, basis: np.ndarray) -> WarpLevel:
    """The fine warp itself as a level (identity transfer)."""
    return WarpLevel(ModalWarp(fine, basis), IdentityTransfer(fine.n_vertices))
