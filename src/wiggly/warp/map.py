"""The rotation-strain warp map W and its derivatives.

Schulz et al. 2014, Theorem 2; Huang et al. 2011.

Per tetrahedron the displacement gradient ``A = grad u`` splits into a rotation vector
``w = axial((A - A^T)/2)`` and a strain ``S = (A + A^T)/2``; the target deformation gradient
is ``exp([w]x)(I + S)``, and the warped displacement is the volume-weighted least-squares
(Poisson) fit of the target gradients,

    W(u) = argmin_x  sum_t vol_t || grad(x)_t - (exp([w_t]x)(I + S_t) - I) ||_F^2  (+ gauge),

whose normal matrix, the scalar P1 Laplacian ``L = G^T Vol G``, does not depend on ``u``: it
is factored once per mesh.  The gauge (:class:`wiggly.warp.gauge.Gauge`) fixes the constant
per component.  Exactly (up to round-off): ``W(0) = 0``; ``W(u + d) = W(u) + d`` for
translations of a free body; ``W(u) = u + O(|u|^2)``; a linearized rotation ``w x (X - c)`` of
a free body becomes the exact rotation by ``|w|`` about the mass centre followed by the mean
translation, and about a fixed vertex ``c`` it becomes ``R (X - c) + c``.

Batches of f frames are one Poisson solve with 3 f right-hand sides; the per-tet passes run
in the kernels chosen once per mesh (:func:`wiggly.warp.kernels.kernels_for`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from wiggly.checks import vertex_set
from wiggly.errors import WigglyInputError
from wiggly.fem import tet_gradients
from wiggly.linalg import available_backends, factorize_spd
from wiggly.warp.gauge import Gauge
from wiggly.warp.kernels import kernels_for

__all__ = ["Warp"]


class Warp:
    """Rotation-strain warp map ``W`` of a tet mesh, and its derivatives (Schulz et al., Thm. 2).

    Parameters
    ----------
    vertices : (n, 3) rest positions.
    tets : (m, 4) positively oriented tetrahedra.
    masses : (n,) vertex weights of the mass-weighted-mean gauge (default: a quarter of the
        incident tets' volumes).  They may be signed (a coarse level's ``P^T m`` is, where
        fine vertices lie outside the coarse mesh); a component whose weights do not sum to
        a positive total uses the plain mean.
    fixed_vertices : indices or an (n,) bool mask of vertices where ``W(u) = 0``.
    kernels : "numba" or "numpy" per-tet passes (default: numba when available).

    Displacements are (n, 3) arrays or batches (f, n, 3).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        tets: np.ndarray,
        *,
        masses: np.ndarray | None = None,
        fixed_vertices: np.ndarray | None = None,
        kernels: str | None = None,
    ) -> None:
        V = np.asarray(vertices, dtype=np.float64)
        grads, vol = tet_gradients(V, tets)  # validates shapes, indices, orientation
        n = V.shape[0]
        T = np.asarray(tets).astype(np.int64)
        self.n_vertices, self.n_tets = n, T.shape[0]
        self.volumes = vol
        self.kernels = kernels_for(T, grads, vol, n, kernels)
        G = self._gradient_operator(T, grads, n)
        #: the scalar P1 gradient operator (3 m, n): row 3 t + j is d/dX_j on tet t
        self.gradient = G
        self.laplacian = sp.csr_matrix(G.T @ sp.diags(np.repeat(vol, 3)) @ G)
        if masses is None:
            m = np.bincount(T.ravel(), weights=np.repeat(vol / 4.0, 4), minlength=n)
        else:
            m = np.asarray(masses, dtype=np.float64)
            if m.shape != (n,):
                raise WigglyInputError(f"masses should have shape ({n},); shape is {m.shape}")
            if not np.all(np.isfinite(m)):
                raise WigglyInputError("masses should be finite")
        self.masses = m
        self.fixed = np.zeros(n, dtype=bool)
        self.fixed[vertex_set(fixed_vertices, n, "fixed_vertices")] = True
        self.gauge = Gauge(self.laplacian, m, self.fixed)
        free = self.gauge.free
        # many right-hand sides per solve (3 per frame): cholespy's multi-RHS solve is ~3x
        # faster than CHOLMOD on Debian's reference BLAS, and on a par with it on OpenBLAS
        self._solve = (
            factorize_spd(
                self.laplacian[free][:, free],
                backend="cholespy" if "cholespy" in available_backends() else None,
            )
            if free.size
            else None
        )

    @staticmethod
    def _gradient_operator(T: np.ndarray, grads: np.ndarray, n: int) -> sp.csr_matrix:
        """Scalar P1 gradient operator G (3 m, n): row 3 t + j is d/dX_j on tet t."""
        m = len(T)
        rows = np.broadcast_to((3 * np.arange(m)[:, None] + np.arange(3))[:, :, None], (m, 3, 4))
        cols = np.broadcast_to(T[:, None, :], (m, 3, 4))
        G = sp.csr_matrix(
            (grads.transpose(0, 2, 1).ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n)
        )
        G.sum_duplicates()
        return G

    # ------------------------------------------------------------ Poisson + gauge
    def _frames(self, U: np.ndarray, name: str) -> tuple[np.ndarray, bool]:
        """(n, 3) -> (1, n, 3) and (f, n, 3) as contiguous float64 frames; flag: batched."""
        U = np.asarray(U, dtype=np.float64)
        n = self.n_vertices
        if U.shape == (n, 3):
            return np.ascontiguousarray(U[None]), False
        if U.ndim == 3 and U.shape[1:] == (n, 3):
            return np.ascontiguousarray(U), True
        raise WigglyInputError(
            f"{name} should have shape ({n}, 3) or (f, {n}, 3); shape is {U.shape}"
        )

    def solve_free(self, B: np.ndarray) -> np.ndarray:
        """``L^-1 B`` on the free vertices and 0 on the eliminated ones, for B (n, c)."""
        n, c = B.shape
        X = np.empty((n, c))
        rows = self.gauge.rows
        if self._solve is None:
            X[:] = 0.0
        elif isinstance(rows, slice):  # free vertices first: solve into X's rows
            k = rows.stop
            self._solve(np.ascontiguousarray(B[:k]), out=X[:k])
            X[k:] = 0.0
        else:
            X[:] = 0.0
            X[rows] = self._solve(B[rows])
        return X

    def _poisson(self, rhs: np.ndarray, means_of: Sequence[np.ndarray]) -> np.ndarray:
        """Gauged fit of right-hand sides (f, n, 3); the gauge takes the mass-weighted means
        of the frames ``means_of`` (parts of f frames in all).  Result (f, n, 3) (a view of
        the solve's (n, f, 3) columns)."""
        f, n = rhs.shape[:2]
        X = self.solve_free(np.ascontiguousarray(rhs.transpose(1, 0, 2)).reshape(n, 3 * f))
        if self.gauge.floating:
            self.gauge.shift(X, self.gauge.frame_means(means_of))
        return X.reshape(n, f, 3).transpose(1, 0, 2)

    def poisson_adjoint(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Adjoint of the gauged fit for cotangents Y (f, n, 3): the cotangent of the
        right-hand sides as (n, f, 3) columns ``Z``, and ``spread^T Y`` (n_float, f, 3), the
        cotangent of the gauge's means (None when no component floats)."""
        f, n = Y.shape[:2]
        Yc = np.array(Y.transpose(1, 0, 2), order="C").reshape(n, 3 * f)
        s = self.gauge.unshift(Yc).reshape(-1, f, 3) if self.gauge.floating else None
        return self.solve_free(Yc).reshape(n, f, 3), s

    def solve_fields(self, rhs: np.ndarray, fields: np.ndarray | None) -> np.ndarray:
        """Gauged fit of (f, r, n, 3) right-hand sides: result (f, n, 3, r).  The gauge takes
        the means of the r ``fields`` (n, 3, r) at every point (Jacobians' directions); None:
        zero means."""
        f, r, n, _ = rhs.shape
        X = self.solve_free(rhs.transpose(2, 3, 0, 1).reshape(n, 3 * f * r))
        if self.gauge.floating:
            means = np.zeros((self.gauge.mean.shape[0], 3, 1, r))
            if fields is not None:
                means[:, :, 0] = (self.gauge.mean @ fields.reshape(n, 3 * r)).reshape(-1, 3, r)
            self.gauge.shift(
                X, np.broadcast_to(means, (len(means), 3, f, r)).reshape(-1, 3 * f * r)
            )
        return np.ascontiguousarray(X.reshape(n, 3, f, r).transpose(2, 0, 1, 3))

    # ---------------------------------------------------------------- the map
    def apply(self, U: np.ndarray) -> np.ndarray:
        """Warped displacements ``W(u)`` for U of shape (n, 3) or (f, n, 3)."""
        Uf, batched = self._frames(U, "U")
        out = self._poisson(self.kernels.target(Uf), [Uf])
        return out if batched else out[0]

    __call__ = apply

    def inverted(self, U: np.ndarray) -> np.ndarray:
        """Per frame and tet, whether the displacements U (f, n, 3) turn the tet inside out
        (``det(I + grad u) <= 0``): (f, m) bool."""
        Uf, _ = self._frames(U, "U")
        return self.kernels.inverted(Uf)

    def jvp(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """Directional derivative ``DW(u)[du]`` (analytic), for (n, 3) or (f, n, 3)."""
        Uf, batched = self._frames(U, "U")
        dUf, dbatched = self._frames(dU, "dU")
        if dUf.shape != Uf.shape or dbatched != batched:
            raise WigglyInputError(
                f"dU should have the shape of U {np.shape(U)}; shape is {np.shape(dU)}"
            )
        out = self._poisson(self.kernels.tangent(Uf, dUf), [dUf])
        return out if batched else out[0]

    def carried(self, Ubar: np.ndarray, U: np.ndarray, *, relative: bool = False) -> np.ndarray:
        """The warp of displacements U carried by the warp of ``Ubar``: the Poisson fit of the
        per-tet gradients ``F(Ubar) F(U) - I``, ``F(u) = exp([w]x)(I + S)`` as in :meth:`apply`.

        So U acts in the frame that ``Ubar`` turns each tet to: its rotations compose with
        Ubar's instead of adding to them (:meth:`apply` of ``Ubar + U`` adds the rotation
        vectors, which scales U's rotations across a turn by a of Ubar by sin(a) / a).
        ``carried(Ubar, 0) = apply(Ubar)`` and ``carried(0, U) = apply(U)``.  ``relative``:
        ``carried(Ubar, U) - apply(Ubar)``, U's part alone (one fit of ``F(Ubar) H(U)``).
        Shapes as :meth:`apply`; the gauge takes the means of ``Ubar + U`` (``U``)."""
        Ur, batched = self._frames(Ubar, "Ubar")
        Uf, fbatched = self._frames(U, "U")
        if Uf.shape != Ur.shape or fbatched != batched:
            raise WigglyInputError(
                f"U should have the shape of Ubar {np.shape(Ubar)}; shape is {np.shape(U)}")
        out = self._poisson(self.kernels.carried_target(Ur, Uf, relative),
                            [Uf if relative else Ur + Uf])
        return out if batched else out[0]

    def carried_jvp(self, Ubar: np.ndarray, dUbar: np.ndarray, U: np.ndarray,
                    dU: np.ndarray, *, relative: bool = False) -> np.ndarray:
        """Directional derivative of :meth:`carried` along ``dUbar`` and ``dU`` (analytic)."""
        fields = [self._frames(x, name) for x, name in
                  ((Ubar, "Ubar"), (dUbar, "dUbar"), (U, "U"), (dU, "dU"))]
        if len({(f.shape, b) for f, b in fields}) != 1:
            raise WigglyInputError(
                "Ubar, dUbar, U and dU should have one shape, (n, 3) or (f, n, 3); shapes are "
                f"{[np.shape(x) for x in (Ubar, dUbar, U, dU)]}")
        (Ur, batched), (dUr, _), (Uf, _), (dUf, _) = fields
        out = self._poisson(self.kernels.carried_tangent(Ur, dUr, Uf, dUf, relative),
                            [dUf if relative else dUr + dUf])
        return out if batched else out[0]

    def apply_and_jvp(
        self, U: np.ndarray, index: Sequence[int] | np.ndarray, dU: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``W(U)`` for frames U (f, n, 3) and ``DW(U[index])[dU]`` for dU (k, n, 3), with one
        Poisson solve for both (velocity keyframes evaluate them together)."""
        Uf, _ = self._frames(U, "U")
        index = np.asarray(index, dtype=np.int64)
        dUf = np.ascontiguousarray(np.asarray(dU, dtype=np.float64).reshape(-1, *Uf.shape[1:]))
        if dUf.shape[0] != index.size:
            raise WigglyInputError(
                f"dU should have shape ({index.size}, {self.n_vertices}, 3); shape is "
                f"{np.shape(dU)}"
            )
        f = len(Uf)
        rhs = np.concatenate(
            [self.kernels.target(Uf), self.kernels.tangent(np.ascontiguousarray(Uf[index]), dUf)]
        )
        out = self._poisson(rhs, [Uf, dUf])
        return out[:f], out[f:]

    def vjp(self, U: np.ndarray, Y: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """Adjoint derivative ``DW(u)^T y``: ``<vjp(u, y), du> = <y, jvp(u, du)>``.

        With ``index`` (batches only), frame s uses the cotangent ``Y[index[s]]``: the Poisson
        solve runs once per distinct cotangent.
        """
        Uf, batched = self._frames(U, "U")
        Yf, ybatched = self._frames(Y, "Y")
        indexed = index is not None
        if index is None:
            if Yf.shape != Uf.shape or ybatched != batched:
                raise WigglyInputError(
                    f"Y should have the shape of U {np.shape(U)}; shape is {np.shape(Y)}"
                )
            index = np.arange(len(Uf))
        index = np.asarray(index, dtype=np.int64)
        if (
            (indexed and not batched)
            or index.shape != (len(Uf),)
            or (index.size and not 0 <= index.min() <= index.max() < len(Yf))
        ):
            raise WigglyInputError(
                f"index should hold {len(Uf)} frame indices of Y in [0, {len(Yf)}) for a batch "
                f"U; got shape {index.shape}, range [{index.min(initial=0)}, "
                f"{index.max(initial=0)}]"
            )
        Z, s = self.poisson_adjoint(Yf)
        out = np.zeros_like(Uf) if s is None else self.gauge.means_adjoint(s, index)
        self.kernels.cotangent(Uf, Z, index, out)
        return out if batched else out[0]
