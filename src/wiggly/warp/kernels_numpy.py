"""The warp's per-tet passes in vectorized numpy: the reference path (``WIGGLY_NUMBA=0``).

Every method has the signature and the meaning of its compiled twin in
:class:`wiggly.warp.kernels.NumbaKernels`; the per-tet formulas are those of
:mod:`wiggly.warp.tetmath`.  Gradients of f fields are laid out as component fields
(3, 3, f, m), ``A[i, j] = d u_i / d X_j``; a flat 3x3 index is ``3 i + j``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from wiggly.linalg import det3
from wiggly.warp.tetmath import cotangent_block, linearization, tangent_block, target_block

# Frames per chunk are chosen so that one component field holds at most this many entries.
_CHUNK_ENTRIES = 1 << 17


def _units() -> np.ndarray:
    """The nine unit gradients E_ij as component fields (3, 3, 9, 1), unit 3 i + j."""
    e = np.arange(9)
    units = np.zeros((3, 3, 9, 1))
    units[e // 3, e % 3, e, 0] = 1.0
    return units


def _flat(fields: np.ndarray) -> np.ndarray:
    """Component fields (3, 3, c, m) as flat per-tet matrices (m, 9, c)."""
    return fields.reshape(9, fields.shape[2], fields.shape[3]).transpose(2, 0, 1)


class NumpyKernels:
    """Vectorized per-tet passes of one tet mesh (see the module docstring)."""

    name = "numpy"

    def __init__(self, tets: np.ndarray, grads: np.ndarray, vol: np.ndarray, n: int) -> None:
        m = len(tets)
        self.n, self.m = n, m
        self.vol = vol
        rows = np.broadcast_to((3 * np.arange(m)[:, None] + np.arange(3))[:, :, None], (m, 3, 4))
        cols = np.broadcast_to(tets[:, None, :], (m, 3, 4))
        G = sp.csr_matrix(
            (grads.transpose(0, 2, 1).ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n)
        )
        G.sum_duplicates()
        self._G = G
        self._Gt = sp.csr_matrix(G.T)
        self._GtV = sp.csr_matrix((sp.diags(np.repeat(vol, 3)) @ G).T)

    # ----------------------------------------------------------------- layout
    def _grad(self, U: np.ndarray) -> np.ndarray:
        """Gradients of fields U (f, n, 3) as component fields (3, 3, f, m)."""
        f = U.shape[0]
        X = np.ascontiguousarray(U.transpose(1, 0, 2)).reshape(self.n, 3 * f)
        Y = (self._G @ X).reshape(self.m, 3, f, 3)
        return np.ascontiguousarray(Y.transpose(3, 1, 2, 0))

    def _scatter(self, H: np.ndarray, volume: bool = True) -> np.ndarray:
        """``G^T Vol H`` (or ``G^T H``) of component fields (3, 3, f, m): fields (f, n, 3)."""
        f = H.shape[2]
        Hm = np.ascontiguousarray(H.transpose(3, 1, 2, 0)).reshape(3 * self.m, 3 * f)
        out = ((self._GtV if volume else self._Gt) @ Hm).reshape(self.n, f, 3)
        return np.ascontiguousarray(out.transpose(1, 0, 2))

    def _chunks(self, f: int) -> list[slice]:
        size = max(1, _CHUNK_ENTRIES // max(self.m, 1))
        return [slice(s, min(f, s + size)) for s in range(0, f, size)]

    # --------------------------------------------------------------- passes
    def inverted(self, U: np.ndarray) -> np.ndarray:
        """Per field and tet, whether ``det(I + G U[s]) <= 0``: (f, m) bool."""
        A = np.moveaxis(self._grad(U), (0, 1), (-2, -1))  # (f, m, 3, 3)
        return det3(A + np.eye(3)) <= 0.0

    def target(self, U: np.ndarray) -> np.ndarray:
        """``G^T Vol H(G U[s])`` for every frame: (f, n, 3)."""
        out = np.empty_like(U)
        for sl in self._chunks(len(U)):
            A = self._grad(U[sl])
            H = np.empty_like(A)
            target_block(H, A)
            out[sl] = self._scatter(H)
        return out

    def tangent(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """``G^T Vol dH(G U[s]; G dU[s])`` for every frame: (f, n, 3)."""
        out = np.empty_like(U)
        for sl in self._chunks(len(U)):
            dA = self._grad(dU[sl])
            H = np.empty_like(dA)
            tangent_block(H, linearization(self._grad(U[sl])), dA)
            out[sl] = self._scatter(H)
        return out

    def carried_target(self, Ur: np.ndarray, Uf: np.ndarray, relative: bool) -> np.ndarray:
        """``G^T Vol ((I + Hr)(I + Hf) - I)``, ``Hr = H(G Ur[s])``, ``Hf = H(G Uf[s])``
        (``relative``: less ``Hr``)."""
        out = np.empty_like(Uf)
        for sl in self._chunks(len(Uf)):
            Ar, Af = self._grad(Ur[sl]), self._grad(Uf[sl])
            Hr, Hf = np.empty_like(Ar), np.empty_like(Af)
            target_block(Hr, Ar)
            target_block(Hf, Af)
            H = Hf + np.einsum("ik...,kj...->ij...", Hr, Hf)
            out[sl] = self._scatter(H if relative else H + Hr)
        return out

    def carried_tangent(self, Ur: np.ndarray, dUr: np.ndarray, Uf: np.ndarray,
                        dUf: np.ndarray, relative: bool) -> np.ndarray:
        """``G^T Vol (dHr (I + Hf) + (I + Hr) dHf)`` (``relative``: less ``dHr``): the tangent
        of :meth:`carried_target`."""
        out = np.empty_like(Uf)
        for sl in self._chunks(len(Uf)):
            lr, lf = linearization(self._grad(Ur[sl])), linearization(self._grad(Uf[sl]))
            dAr, dAf = self._grad(dUr[sl]), self._grad(dUf[sl])
            dHr, dHf = np.empty_like(dAr), np.empty_like(dAf)
            tangent_block(dHr, lr, dAr)
            tangent_block(dHf, lf, dAf)
            Fr = np.array(lr[14:23]).reshape(dAr.shape)  # I + H
            Ff = np.array(lf[14:23]).reshape(dAf.shape)
            dH = (np.einsum("ik...,kj...->ij...", dHr, Ff)
                  + np.einsum("ik...,kj...->ij...", Fr, dHf))
            out[sl] = self._scatter(dH - dHr if relative else dH)
        return out

    def cotangent(self, U: np.ndarray, Z: np.ndarray, index: np.ndarray, out: np.ndarray) -> None:
        """``out[s] += G^T dA`` with ``dA`` the cotangent of ``Vol G Z[:, index[s]]`` at
        ``G U[s]`` (``Z`` (n, k, 3): Poisson-adjoint columns)."""
        for sl in self._chunks(len(U)):
            Y = self._grad(np.ascontiguousarray(Z[:, index[sl]].transpose(1, 0, 2)))
            Y *= self.vol
            dA = np.empty_like(Y)
            cotangent_block(dA, linearization(self._grad(U[sl])), Y)
            out[sl] += self._scatter(dA, volume=False)

    def field_gradients(self, B: np.ndarray) -> np.ndarray:
        """Per-tet gradients (r, m, 9) of fields B (r, n, 3)."""
        return np.ascontiguousarray(_flat(self._grad(B)).transpose(2, 0, 1))

    def _apply(self, M: np.ndarray, GB: np.ndarray) -> np.ndarray:
        """``G^T Vol (M_t GB[d, t])`` for per-tet 9x9 matrices M (m, 9, 9): (r, n, 3)."""
        r = GB.shape[0]
        dH = M @ GB.transpose(1, 2, 0)  # (m, 9, r)
        fields = dH.reshape(self.m, 3, 3, r).transpose(1, 2, 3, 0)
        return self._scatter(np.ascontiguousarray(fields))

    def jacobians(self, U: np.ndarray, GB: np.ndarray) -> np.ndarray:
        """``G^T Vol dH(G U[s]; GB[d])``: (f, r, n, 3)."""
        out = np.empty((len(U), GB.shape[0], self.n, 3))
        units = _units()
        for s in range(len(U)):
            res = np.empty((3, 3, 9, self.m))
            tangent_block(res, linearization(self._grad(U[s : s + 1])), units)
            out[s] = self._apply(_flat(res), GB)  # tangent matrix column e = unit e
        return out

    def second_derivatives(
        self, U: np.ndarray, V: np.ndarray, GB: np.ndarray, step: float
    ) -> np.ndarray:
        """``G^T Vol D^2H(G U[s])[GB[d], G V[s]]`` by central differences of the tangent in
        the linearization point (step ``step``): (f, r, n, 3)."""
        out = np.empty((len(U), GB.shape[0], self.n, 3))
        units = _units()
        for s in range(len(U)):
            A, gv = self._grad(U[s : s + 1]), self._grad(V[s : s + 1])
            T2 = np.empty((self.m, 9, 9))
            for e in range(9):
                plus, minus = np.empty_like(A), np.empty_like(A)
                tangent_block(plus, linearization(A + step * units[:, :, e : e + 1]), gv)
                tangent_block(minus, linearization(A - step * units[:, :, e : e + 1]), gv)
                T2[:, :, e] = _flat((plus - minus) / (2 * step))[:, :, 0]
            out[s] = self._apply(T2, GB)
        return out

    def _hessian(self, A: np.ndarray, Y: np.ndarray, step: float) -> np.ndarray:
        """Per-tet Hessians (m, 9, 9) of ``A -> Y : H(A)`` by central differences."""
        units = _units()
        H = np.empty((self.m, 9, 9))
        for e in range(9):
            plus, minus = np.empty_like(Y), np.empty_like(Y)
            cotangent_block(plus, linearization(A + step * units[:, :, e : e + 1]), Y)
            cotangent_block(minus, linearization(A - step * units[:, :, e : e + 1]), Y)
            H[:, :, e] = _flat((plus - minus) / (2 * step))[:, :, 0]
        return 0.5 * (H + H.transpose(0, 2, 1))

    def curvature_fields(self, GB: np.ndarray) -> np.ndarray:
        """The fields as :meth:`curvature` takes them: their gradients GB themselves."""
        return GB

    def curvature(
        self,
        u: np.ndarray,
        z: np.ndarray,
        zv: np.ndarray | None,
        v: np.ndarray | None,
        GB: np.ndarray,
        step: float,
        step3: float,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Modal curvature matrices (r, r): ``qq = sum_t GB_t^T vol_t (Hess(Z_t) +
        D Hess(Zv_t)[(G v)_t]) GB_t`` and ``qv = sum_t GB_t^T vol_t Hess(Zv_t) GB_t`` (None
        without a velocity); see :func:`wiggly.warp.compiled_second.curvature_products`."""
        A = self._grad(u[None])
        Y1 = self._grad(z[None]) * self.vol
        GBm = GB.transpose(1, 2, 0)  # (m, 9, r)
        flat = GBm.reshape(9 * self.m, -1)
        qv = None
        if zv is not None:
            Y2 = self._grad(zv[None]) * self.vol
            H2 = self._hessian(A, Y2, step)
            H1 = self._hessian(A, Y1, step)
            a = self._grad(v[None])
            scale = np.abs(a).max(axis=(0, 1, 2))  # per tet
            a = a / np.where(scale > 0, scale, 1.0)
            units = _units()
            # nested central differences: a step of 10 step3 balances truncation and rounding
            step3 = 10.0 * step3
            T = np.zeros((self.m, 9, 9))
            for e in range(9):
                for sign in (1.0, -1.0):
                    Ae = A + sign * step3 * units[:, :, e : e + 1]
                    p, q = np.empty_like(Y2), np.empty_like(Y2)
                    cotangent_block(p, linearization(Ae + step3 * a), Y2)
                    cotangent_block(q, linearization(Ae - step3 * a), Y2)
                    T[:, :, e] += sign * _flat(p - q)[:, :, 0] / (2 * step3)
            T /= 2 * step3
            H1 += scale[:, None, None] * 0.5 * (T + T.transpose(0, 2, 1))
            qv = flat.T @ (H2 @ GBm).reshape(9 * self.m, -1)
        else:
            H1 = self._hessian(A, Y1, step)
        qq = flat.T @ (H1 @ GBm).reshape(9 * self.m, -1)
        return qq, qv
