"""A warp bound to a modal basis: the derivatives of W in modal coordinates.

Schulz et al. 2014, Theorem 2.

The warped solve (Theorem 2) needs, at a constrained node with modal state ``q`` (and
``q'``), ``u = Phi q``:

* the Jacobian ``DW(u) Phi`` (Gauss-Newton blocks of position keyframes);
* the second derivative ``D^2W(u)[Phi, Phi q']`` (velocity keyframes ``B DW(u) Phi q'``);
* the curvature ``Phi^T grad^2(y . W)(u) Phi`` of a cotangent y (the residual weighted by
  its keyframe), and for velocity keyframes also ``Phi^T grad^3(y_v . W)(u)[., ., Phi q'] Phi``
  and ``Phi^T grad^2(y_v . W)(u) Phi``: the terms Gauss-Newton drops, which make the
  Newton Hessian exact.

Since the Poisson fit and the gauge are linear, only the per-tet map ``H(A)`` is
differentiated twice: ``y . W(u) = sum_t vol_t Z_t : H(A_t) + linear(u)`` with ``Z = G L^-1 y``
(the Poisson adjoint of y), so the curvature is a sum over tets of ``(G Phi)_t^T Hess_t
(G Phi)_t`` with the 9x9 Hessians ``Hess_t`` of ``A -> Z_t : H(A)``.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import pairwise

import numpy as np

from wiggly.errors import WigglyInputError
from wiggly.warp.map import Warp

__all__ = ["ModalWarp"]

# Central-difference steps (relative to the largest displacement gradient, at least 1): the
# numpy kernels' second derivatives from the analytic first derivative (error ~ step^2 ~
# 4e-11, round-off ~ eps / step ~ 2e-11), and the third derivative from the analytic
# Hessian (compiled kernels; ~1e-10 each way).
HESSIAN_STEP = 6e-6
THIRD_STEP = 1e-5
# Jacobians of many frames are made a few frames at a time: each chunk's right-hand sides
# (r fields x n vertices x 3 per frame) stay near this many bytes, so the per-tet pass, the
# transposes and the solve work in cache instead of streaming arrays of 100+ MB.
CHUNK_BYTES = 16 << 20


class ModalWarp:
    """The warp ``W`` of a mesh bound to r displacement fields ``Phi`` (n, 3, r) (modes).

    The per-tet gradients of the fields are computed once here; every derivative below is
    taken against them.  ``basis`` may also be given as (3 n, r) (vertex-major rows).
    """

    def __init__(self, warp: Warp, basis: np.ndarray) -> None:
        n = warp.n_vertices
        B = np.asarray(basis, dtype=np.float64)
        if B.ndim == 2 and B.shape[0] == 3 * n:
            B = B.reshape(n, 3, B.shape[1])
        if B.ndim != 3 or B.shape[:2] != (n, 3):
            raise WigglyInputError(
                f"basis should have shape ({n}, 3, r) or ({3 * n}, r); shape is {B.shape}"
            )
        self.warp = warp
        self.basis = np.array(B)
        self.basis.flags.writeable = False
        self.r = B.shape[2]
        self.matrix = self.basis.reshape(3 * n, self.r)  # (3 n, r) view
        frames = np.ascontiguousarray(self.basis.transpose(2, 0, 1))
        self._gradients = warp.kernels.field_gradients(frames)  # (r, m, 9)
        self._curvature_fields = warp.kernels.curvature_fields(self._gradients)

    @property
    def n_vertices(self) -> int:
        return self.warp.n_vertices

    def displacements(self, Q: np.ndarray) -> np.ndarray:
        """``Phi q_s`` for modal states Q (f, r): (f, n, 3)."""
        Q = np.atleast_2d(np.asarray(Q, dtype=np.float64))
        if Q.shape[1] != self.r:
            raise WigglyInputError(f"modal states should have shape (f, {self.r}); got {Q.shape}")
        return (Q @ self.matrix.T).reshape(len(Q), self.n_vertices, 3)

    def _step(self, U: np.ndarray, relative: float) -> float:
        n = self.n_vertices
        A = self.warp.gradient @ np.ascontiguousarray(U.transpose(1, 0, 2)).reshape(n, -1)
        return relative * max(1.0, float(np.abs(A).max(initial=0.0)))

    def _by_chunks(self, f: int, solve_chunk: Callable[[int, int], np.ndarray]) -> np.ndarray:
        """(f, n, 3, r) fields made by ``solve_chunk(a, b)`` for frames a:b, in chunks of
        equal frame counts and at most about CHUNK_BYTES of right-hand sides."""
        out = np.empty((f, self.n_vertices, 3, self.r))
        chunks = -(-f * 24 * self.n_vertices * self.r // CHUNK_BYTES)  # ceil
        cuts = np.linspace(0, f, max(1, min(f, chunks)) + 1).round().astype(int)
        for a, b in pairwise(cuts):
            out[a:b] = solve_chunk(a, b)
        return out

    def jacobians(self, Q: np.ndarray) -> np.ndarray:
        """``DW(Phi q_s) Phi`` at f states Q (f, r): (f, n, 3, r), a multi-RHS solve per
        chunk of frames."""
        U = self.displacements(Q)
        return self._by_chunks(
            len(U),
            lambda a, b: self.warp.solve_fields(
                self.warp.kernels.jacobians(U[a:b], self._gradients), self.basis
            ),
        )

    def second_derivatives(self, Q: np.ndarray, Qv: np.ndarray) -> np.ndarray:
        """``D^2W(Phi q_s)[Phi, Phi q'_s]`` at f states: (f, n, 3, r) (analytic in the compiled
        kernels, central differences of the analytic tangent in numpy: error ~1e-10).  The
        gauge's mean term of ``DW(u)[v]`` is the mean of v, independent of u: it does not
        enter."""
        U, V = self.displacements(Q), self.displacements(Qv)
        step = self._step(U, HESSIAN_STEP)
        return self._by_chunks(
            len(U),
            lambda a, b: self.warp.solve_fields(
                self.warp.kernels.second_derivatives(U[a:b], V[a:b], self._gradients, step),
                None,
            ),
        )

    def curvatures(
        self,
        Q: np.ndarray,
        Y: np.ndarray,
        Qv: np.ndarray | None = None,
        Yv: np.ndarray | None = None,
    ) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """Modal curvature matrices at f states Q (f, r) with cotangents Y (f, n, 3):

            qq_s = Phi^T [grad^2(y_s . W) + grad^3(yv_s . W)[Phi q'_s]] Phi
            qv_s = Phi^T grad^2(yv_s . W) Phi            (None without a velocity)

        (all derivatives at ``u_s = Phi q_s``).  ``Qv`` (f, r) and ``Yv`` (f, n, 3) give the
        velocities and velocity cotangents; a row of zeros in ``Qv`` marks a point without
        one.  Returns one (qq, qv) pair per point.
        """
        U = self.displacements(Q)
        Y = np.ascontiguousarray(Y, dtype=np.float64)
        if Y.shape != U.shape:
            raise WigglyInputError(f"Y should have shape {U.shape}; shape is {Y.shape}")
        Z, _ = self.warp.poisson_adjoint(Y)  # (n, f, 3)
        velocity = Qv is not None
        if velocity:
            V = self.displacements(Qv)
            Zv, _ = self.warp.poisson_adjoint(np.ascontiguousarray(Yv, dtype=np.float64))
        step = self._step(U, HESSIAN_STEP)
        step3 = self._step(U, THIRD_STEP)
        out = []
        for s in range(len(U)):
            moving = velocity and bool(np.any(Qv[s] != 0.0) or np.any(Yv[s] != 0.0))
            out.append(
                self.warp.kernels.curvature(
                    U[s], np.ascontiguousarray(Z[:, s]),
                    np.ascontiguousarray(Zv[:, s]) if moving else None,
                    V[s] if moving else None,
                    self._curvature_fields, step, step3,
                )
            )
        return out
