"""The warp's per-tet passes behind one interface, chosen once per mesh.

:func:`kernels_for` returns :class:`NumbaKernels` (fused compiled loops,
:mod:`wiggly.warp.compiled`) when numba is importable and ``WIGGLY_NUMBA`` is not ``0``, and
:class:`wiggly.warp.kernels_numpy.NumpyKernels` (vectorized numpy) otherwise.  Both have the
same methods with the same meaning; a :class:`wiggly.warp.Warp` never asks which one it has.

Methods (fields are (f, n, 3) float64 arrays; ``GB`` (r, m, 9) the per-tet gradients of r
fields from :meth:`field_gradients`):

``target(U)``
    right-hand sides ``G^T Vol H(G U[s])`` of the warp's Poisson fit, (f, n, 3);
``tangent(U, dU)``
    ``G^T Vol dH(G U[s]; G dU[s])``, (f, n, 3);
``carried_target(Ur, Uf, relative)`` / ``carried_tangent(Ur, dUr, Uf, dUf, relative)``
    ``G^T Vol ((I + H(G Ur[s]))(I + H(G Uf[s])) - I)`` (the warped gradients of ``Uf``
    carried by those of ``Ur``; ``relative``: less ``H(G Ur[s])``) and its tangent along
    ``dUr``, ``dUf``, (f, n, 3);
``cotangent(U, Z, index, out)``
    ``out[s] += G^T dA_s`` with ``dA_s`` the cotangent of ``Vol G Z[:, index[s]]``;
``jacobians(U, GB)`` / ``second_derivatives(U, V, GB, step)``
    ``G^T Vol dH(G U[s]; GB[d])`` and ``G^T Vol D^2H(G U[s])[GB[d], G V[s]]``, (f, r, n, 3);
``inverted(U)``
    per field and tet, whether ``det(I + G U[s]) <= 0`` (the tet turned inside out), (f, m);
``curvature_fields(GB)``
    the fields in the form :meth:`curvature` takes them (computed once per modal basis);
``curvature(u, z, zv, v, fields, step, step3)``
    the modal curvature matrices (r, r) of one point (see :meth:`NumbaKernels.curvature`).
"""

from __future__ import annotations

import numpy as np

from wiggly.errors import WigglyInputError
from wiggly.progress import activity
from wiggly.warp import compiled, compiled_second
from wiggly.warp.kernels_numpy import NumpyKernels

__all__ = ["NumbaKernels", "NumpyKernels", "cache_is_cold", "compile_all", "ensure_compiled",
           "kernels_for"]

#: What a first warped solve after an install waits for, said before it starts.
COMPILING = ("compiling the warp kernels, once after an install: about a minute on two "
             "cores (longer on a busy machine)")
_ready = False


class NumbaKernels:
    """Compiled per-tet passes of one tet mesh (:mod:`wiggly.warp.compiled`)."""

    name = "numba"

    def __init__(self, tets: np.ndarray, grads: np.ndarray, vol: np.ndarray, n: int) -> None:
        self.tets = np.ascontiguousarray(tets, dtype=np.int64)
        self.grads = np.ascontiguousarray(grads)
        self.vol = np.ascontiguousarray(vol)
        self.n, self.m = n, len(tets)

    def target(self, U: np.ndarray) -> np.ndarray:
        out = np.zeros_like(U)
        compiled.target_rhs(U, self.tets, self.grads, self.vol, out, compiled.chunks(len(U)))
        return out

    def tangent(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        out = np.zeros_like(U)
        compiled.jvp_rhs(U, dU, self.tets, self.grads, self.vol, out, compiled.chunks(len(U)))
        return out

    def carried_target(self, Ur: np.ndarray, Uf: np.ndarray, relative: bool) -> np.ndarray:
        out = np.zeros_like(Uf)
        compiled.carried_target_rhs(Ur, Uf, self.tets, self.grads, self.vol, out,
                                    compiled.chunks(len(Uf)), relative)
        return out

    def carried_tangent(self, Ur: np.ndarray, dUr: np.ndarray, Uf: np.ndarray,
                        dUf: np.ndarray, relative: bool) -> np.ndarray:
        out = np.zeros_like(Uf)
        compiled.carried_jvp_rhs(Ur, dUr, Uf, dUf, self.tets, self.grads, self.vol, out,
                                 compiled.chunks(len(Uf)), relative)
        return out

    def cotangent(self, U: np.ndarray, Z: np.ndarray, index: np.ndarray, out: np.ndarray) -> None:
        compiled.vjp_rhs(
            U, Z, index, self.tets, self.grads, self.vol, out, compiled.chunks(len(U))
        )

    def field_gradients(self, B: np.ndarray) -> np.ndarray:
        return compiled.field_gradients(np.ascontiguousarray(B), self.tets, self.grads)

    def inverted(self, U: np.ndarray) -> np.ndarray:
        out = np.empty((len(U), self.m), dtype=np.bool_)
        compiled.inverted(np.ascontiguousarray(U), self.tets, self.grads, out)
        return out

    def jacobians(self, U: np.ndarray, GB: np.ndarray) -> np.ndarray:
        out = np.zeros((len(U), GB.shape[0], self.n, 3))
        compiled.jacobians_rhs(U, GB, self.tets, self.grads, self.vol, out)
        return out

    def second_derivatives(
        self, U: np.ndarray, V: np.ndarray, GB: np.ndarray, step: float
    ) -> np.ndarray:
        out = np.zeros((len(U), GB.shape[0], self.n, 3))  # analytic: ``step`` is not used
        compiled_second.second_derivatives_rhs(U, V, GB, self.tets, self.grads, self.vol, out)
        return out

    def curvature_fields(self, GB: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What :meth:`curvature` takes for the fields GB: their gradients in the skew /
        symmetric basis (:func:`wiggly.warp.compiled_second.split_fields`), and the rotation
        part alone as (r, 3 m) rows."""
        F = compiled_second.split_fields(np.ascontiguousarray(GB))
        return F, np.ascontiguousarray(F[:, :, :3]).reshape(len(F), -1)

    def curvature(
        self,
        u: np.ndarray,
        z: np.ndarray,
        zv: np.ndarray | None,
        v: np.ndarray | None,
        fields: tuple[np.ndarray, np.ndarray],
        step: float,
        step3: float,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """``qq = sum_t GB_t^T Hqq_t GB_t`` and ``qv = sum_t GB_t^T Hqv_t GB_t`` (r, r) from
        the per-tet products of :func:`wiggly.warp.compiled_second.curvature_products`
        (analytic Hessians; ``step`` is not used): ``W^T C + C^T W`` with W the fields'
        rotation parts, one BLAS product each."""
        F, W = fields
        r = F.shape[0]
        velocity = zv is not None
        Cqq = np.empty((r, self.m, 3))
        Cqv = np.empty((r, self.m, 3)) if velocity else Cqq[:0]
        zero = np.zeros((self.n, 3))
        compiled_second.curvature_products(
            np.ascontiguousarray(u), np.ascontiguousarray(z),
            np.ascontiguousarray(zv) if velocity else zero,
            np.ascontiguousarray(v) if velocity else zero,
            F, step3, self.tets, self.grads, self.vol, Cqq, Cqv, velocity,
        )
        half = W @ Cqq.reshape(r, -1).T
        qq = half + half.T
        if not velocity:
            return qq, None
        half = W @ Cqv.reshape(r, -1).T
        return qq, half + half.T


def kernels_for(
    tets: np.ndarray, grads: np.ndarray, vol: np.ndarray, n: int, choice: str | None = None
) -> NumbaKernels | NumpyKernels:
    """The per-tet passes of a mesh: ``choice`` "numba" or "numpy"; None: compiled when
    numba is available, else numpy."""
    if choice not in (None, "numba", "numpy"):
        raise WigglyInputError(f"kernels = {choice!r}; use 'numba', 'numpy' or None")
    if choice == "numba" and not compiled.AVAILABLE:
        raise WigglyInputError("kernels = 'numba' but numba is not available")
    if choice == "numba" or (choice is None and compiled.AVAILABLE):
        ensure_compiled()
        return NumbaKernels(tets, grads, vol, n)
    return NumpyKernels(tets, grads, vol, n)


def compile_all() -> None:
    """Compile every kernel (or load it from numba's on-disk cache: ~0.5 s when cached, ~30 s
    the first time after installation) by running it on one tetrahedron."""
    if not compiled.AVAILABLE:
        return
    tets = np.array([[0, 1, 2, 3]], dtype=np.int64)
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    grads = np.zeros((1, 4, 3))
    grads[0, 1:] = np.linalg.inv((V[1:] - V[0]).T)
    grads[0, 0] = -grads[0, 1:].sum(axis=0)
    vol = np.array([1.0 / 6.0])
    U = np.full((2, 4, 3), 0.1)
    out = np.zeros_like(U)
    compiled.target_rhs(U, tets, grads, vol, out, 1)
    compiled.jvp_rhs(U, U, tets, grads, vol, out, 1)
    compiled.vjp_rhs(U, U.transpose(1, 0, 2).copy(), np.arange(2), tets, grads, vol, out, 1)
    compiled.carried_target_rhs(U, U, tets, grads, vol, out, 1, True)
    compiled.carried_jvp_rhs(U, U, U, U, tets, grads, vol, out, 1, True)
    GB = compiled.field_gradients(U, tets, grads)
    compiled.inverted(U, tets, grads, np.empty((2, 1), dtype=np.bool_))
    compiled.jacobians_rhs(U, GB, tets, grads, vol, np.zeros((2, 2, 4, 3)))
    compiled_second.second_derivatives_rhs(U, U, GB, tets, grads, vol, np.zeros((2, 2, 4, 3)))
    C = np.zeros((2, 1, 9))
    compiled_second.curvature_products(
        U[0], U[0], U[1], U[1], GB, 1e-5, tets, grads, vol, C, C.copy(), True
    )


def _entry_points() -> list:
    return [compiled.target_rhs, compiled.jvp_rhs, compiled.vjp_rhs, compiled.field_gradients,
            compiled.carried_target_rhs, compiled.carried_jvp_rhs,
            compiled.inverted, compiled.jacobians_rhs, compiled_second.second_derivatives_rhs,
            compiled_second.curvature_products]


def cache_is_cold() -> bool:
    """Whether numba's on-disk cache lacks a kernel that :func:`compile_all` runs, so that
    running them compiles (20-120 s) instead of loading (about 1 s)."""
    if not compiled.AVAILABLE:
        return False
    for kernel in _entry_points():
        try:  # numba keeps an index of the compiled signatures beside the source
            if not kernel._cache._cache_file._load_index():
                return True
        except Exception:  # another numba's layout: assume the worst, say so
            return True
    return False


def ensure_compiled() -> bool:
    """Compile or load every kernel once per process, announcing a compilation first (on the
    ``wiggly`` logger, and as a live line on a terminal), so a first run never looks hung.
    Batches call it before starting their workers, so that workers load, never compile.
    Whether this call compiled them (False: loaded from the on-disk cache, or ready)."""
    global _ready
    if _ready or not compiled.AVAILABLE:
        return False
    cold = cache_is_cold()
    if cold:
        with activity(COMPILING):
            compile_all()
    else:
        compile_all()
    _ready = True
    return cold
