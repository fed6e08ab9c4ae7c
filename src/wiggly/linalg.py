"""Sparse symmetric positive definite factorizations with a choice of backend, and small
dense helpers (:func:`det3`).

:func:`factorize_spd` factors a sparse SPD matrix once and returns a solver usable for many
right-hand sides (eigenmode shift-invert; warping's Poisson system).
Backends, in order of preference when ``backend=None``:

``"cholmod"``
    ``sksparse.cholmod`` (scikit-sparse, optional; fastest supernodal Cholesky).
``"cholespy"``
    ``cholespy.CholeskySolverD`` (a dependency, binary wheel; CHOLMOD inside).
``"splu"``
    ``scipy.sparse.linalg.splu`` with ``permc_spec="MMD_AT_PLUS_A"`` and ``SymmetricMode``
    (always available; an LU, slower and fragile on large 3-D FEM matrices).
"""

from __future__ import annotations

import atexit
import importlib.util
import weakref
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from functools import cache, wraps
from typing import ParamSpec, TypeVar

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from wiggly.errors import WigglyInputError

__all__ = [
    "BACKENDS",
    "SPDSolver",
    "available_backends",
    "blas_single_thread",
    "det3",
    "factorize_spd",
    "one_blas_thread",
]

P = ParamSpec("P")
R = TypeVar("R")

BACKENDS = ("cholmod", "cholespy", "splu")
# cholespy solves many right-hand sides in blocks of this many columns: a solve with 37,800
# columns on a 431-vertex mesh takes half the time so (the blocks stay in cache)
CHOLESPY_COLUMNS = 64


def det3(A: np.ndarray) -> np.ndarray:
    """Determinants of a stack of 3x3 matrices ``A (..., 3, 3)`` by the rule of Sarrus:
    equal to ``np.linalg.det`` to rounding and about five times faster on a tet mesh's
    deformation gradients (no batched LU factorization)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def available_backends() -> list[str]:
    """Names of the backends importable here, in order of preference."""
    modules = {"cholmod": "sksparse", "cholespy": "cholespy", "splu": "scipy"}
    found = []
    for name in BACKENDS:
        try:
            spec = importlib.util.find_spec(modules[name])
        except (ImportError, ValueError):
            spec = None
        if spec is not None:
            found.append(name)
    return found


@dataclass(frozen=True)
class SPDSolver:
    """A factored SPD matrix A: ``solver(b)`` returns ``A^{-1} b`` for b of shape (n,) or (n, k);
    ``solver(b, out=x)`` writes it into ``x`` (b's shape, float64, C-contiguous rows) instead.

    Attributes
    ----------
    backend : str
        Name of the factorization backend (one of :data:`BACKENDS`).
    n : int
        Size of A.
    """

    backend: str
    n: int
    _solve: Callable[[np.ndarray, np.ndarray | None], np.ndarray]

    def __call__(self, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        b = np.asarray(b, dtype=np.float64)
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise WigglyInputError(
                f"right-hand side should have shape ({self.n},) or ({self.n}, k); "
                f"shape is {b.shape}"
            )
        if out is not None and (
            out.shape != b.shape or out.dtype != np.float64 or not out.flags.c_contiguous
        ):
            raise WigglyInputError(
                f"out should be a C-contiguous float64 array of shape {b.shape}; got "
                f"{out.dtype} {out.shape}"
            )
        if b.ndim == 2 and b.shape[1] == 0:
            return np.zeros_like(b) if out is None else out
        return self._solve(b, out)


def _into(solve: Callable[[np.ndarray], np.ndarray]) -> Callable[..., np.ndarray]:
    """``solve(b)`` with an optional output array (copied into)."""

    def solve_into(b: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        x = solve(b)
        if out is None:
            return x
        out[...] = x
        return out

    return solve_into


def _factor_cholmod(A: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
    from sksparse import cholmod

    not_pd = getattr(cholmod, "CholmodNotPositiveDefiniteError", cholmod.CholmodError)
    try:
        factor = cholmod.cholesky(A.tocsc())
    except not_pd as err:
        raise np.linalg.LinAlgError(f"matrix is not positive definite ({err})") from err
    return _into(lambda b: np.asarray(factor(b)))


class _Held:
    """A cholespy factor, released at the interpreter's exit (:func:`_release`) before its
    module is torn down: nanobind otherwise reports every factor still alive then as a
    leak, on the user's terminal (an editor stopped with Ctrl+C held two)."""

    __slots__ = ("__weakref__", "solver")

    def __init__(self, solver):
        self.solver = solver


_HELD: weakref.WeakSet[_Held] = weakref.WeakSet()


@atexit.register
def _release() -> None:
    for held in list(_HELD):
        held.solver = None


def _factor_cholespy(A: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
    import cholespy

    try:
        held = _Held(cholespy.CholeskySolverD(
            A.shape[0],
            A.indptr.astype(np.int32),
            A.indices.astype(np.int32),
            A.data.astype(np.float64),
            cholespy.MatrixType.CSR,
        ))
    except ValueError as err:  # "Matrix is not positive definite!"
        raise np.linalg.LinAlgError(f"matrix is not positive definite ({err})") from err
    _HELD.add(held)

    def solve(b: np.ndarray, out: np.ndarray | None) -> np.ndarray:
        solver = held.solver
        rhs = np.ascontiguousarray(b)  # (n,) or (n, k), C order, float64
        x = np.empty_like(rhs) if out is None else out
        if rhs.ndim == 1 or rhs.shape[1] <= 2 * CHOLESPY_COLUMNS:
            solver.solve(rhs, x)
            return x
        # many columns: in blocks, whose right-hand sides stay in cache with the factor
        for a in range(0, rhs.shape[1], CHOLESPY_COLUMNS):
            piece = np.ascontiguousarray(rhs[:, a : a + CHOLESPY_COLUMNS])
            solved = np.empty_like(piece)
            solver.solve(piece, solved)
            x[:, a : a + CHOLESPY_COLUMNS] = solved
        return x

    return solve


def _factor_splu(A: sp.csr_matrix) -> Callable[[np.ndarray], np.ndarray]:
    try:
        lu = spla.splu(A.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    except RuntimeError as err:  # "Factor is exactly singular"
        raise np.linalg.LinAlgError(f"matrix is singular ({err})") from err
    return _into(lu.solve)


_FACTORS = {"cholmod": _factor_cholmod, "cholespy": _factor_cholespy, "splu": _factor_splu}


def factorize_spd(A: sp.spmatrix, backend: str | None = None) -> SPDSolver:
    """Factor a sparse symmetric positive definite matrix once, for repeated solves.

    Parameters
    ----------
    A : (n, n) sparse, symmetric positive definite
        Only its values are used as given; symmetry is not checked (cholmod and cholespy read
        one triangle).
    backend : {"cholmod", "cholespy", "splu"} or None
        None picks the first available in that order.

    Returns
    -------
    SPDSolver
        Callable ``solver(b) -> A^{-1} b``; ``solver.backend`` names the backend used.

    Raises
    ------
    WigglyInputError
        Unknown or unavailable backend, or A not square.
    numpy.linalg.LinAlgError
        The Cholesky backends detected that A is not positive definite.
    """
    if A.ndim != 2 or A.shape[0] != A.shape[1] or A.shape[0] == 0:
        raise WigglyInputError(f"A should be a non-empty square matrix; shape is {A.shape}")
    available = available_backends()
    if backend is None:
        backend = available[0]
    elif backend not in BACKENDS:
        raise WigglyInputError(f"backend should be one of {BACKENDS} or None; got {backend!r}")
    elif backend not in available:
        raise WigglyInputError(f"backend {backend!r} is not installed here; available: {available}")
    A = sp.csr_matrix(A, dtype=np.float64)
    A.sum_duplicates()
    return SPDSolver(backend=backend, n=A.shape[0], _solve=_FACTORS[backend](A))


def blas_single_thread() -> AbstractContextManager[object]:
    """Limit BLAS to one thread, if threadpoolctl is installed.

    The eigensolve is dominated by level-2 BLAS and skinny products with tall (3n, r) blocks:
    memory bound.  Multithreaded OpenBLAS busy-waits badly on such products when the cores are
    shared (measured 5-10x slower on a loaded 2-core machine), so one thread is both safer
    and, on an idle machine, hardly slower.  The loaded libraries are inspected once per
    process (:func:`_blas_controller`; about 2 ms each time with numba loaded), so that the
    editor's many short solves do not pay for it.
    """
    controller = _blas_controller()
    if controller is None:
        return nullcontext()
    return controller.limit(limits=1, user_api="blas")


def one_blas_thread(function: Callable[P, R]) -> Callable[P, R]:
    """Run ``function`` under :func:`blas_single_thread`: for passes that alternate BLAS
    products with the warp's compiled loops.  Idle OpenBLAS workers spin for a while after
    each product and take the cores from the compiled loop's threads: 300 frames of warped
    playback on the benchmark box took 0.42 s with BLAS on 2 threads, 0.26 s on one."""

    @wraps(function)
    def limited(*args: P.args, **kwargs: P.kwargs) -> R:
        with blas_single_thread():
            return function(*args, **kwargs)

    return limited


@cache
def _blas_controller() -> object | None:
    """threadpoolctl's view of this process's thread pools (None without threadpoolctl).
    BLAS libraries are loaded with numpy and scipy, before the first solve asks."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return None
    return ThreadpoolController()
