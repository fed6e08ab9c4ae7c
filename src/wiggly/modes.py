"""Reduction to eigenmodes: the lowest r modes of K phi = lambda M phi.

The modal basis of Schulz et al. 2014, eq. (5).

The modal basis ``Phi = [phi_1 .. phi_r]`` is M-orthonormal and K-diagonal,

    Phi^T M Phi = I,    Phi^T K Phi = diag(lambda),

and a displacement is ``u = Phi q``.  Rigid motions (lambda = 0) must be in the basis, or the
object cannot fly, jump or turn.  They are not found by thresholding eigenvalues: the rigid
motions compatible with the fixed vertices are computed analytically (the null space of
:func:`rigid_motions` restricted to the fixed dofs: 6 for a free body, 3 with one fixed vertex,
1 with collinear fixed vertices, 0 otherwise), M-orthonormalized and put first with
``lambda = 0.0`` exactly.  The elastic modes come from a shift-invert Lanczos solve
(``eigsh``) with a small negative shift sigma, so that ``K - sigma M`` is SPD even though K is
singular, and a sparse Cholesky factorization of it (:func:`wiggly.linalg.factorize_spd`);
they are then M-orthogonalized against the rigid subspace and polished by a Rayleigh-Ritz
step.  Small problems use a dense ``scipy.linalg.eigh`` instead.

Fixed vertices remove their dofs (rows and columns of K and M); the returned vectors have the
full size 3n and are exactly zero on fixed dofs.  Results are cached on disk, keyed by a hash
of K, M, the vertices, r and the fixed set.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from wiggly.checks import vertex_set
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.files import atomic_file, default_cache_dir
from wiggly.limits import MAX_MODES
from wiggly.linalg import blas_single_thread, factorize_spd
from wiggly.progress import deprecated_progress, iterations, say, shown

log = logging.getLogger(__name__)

__all__ = ["Modes", "compute_modes", "default_cache_dir", "rigid_motions"]

CACHE_FORMAT = "wiggly.modes/2"  # 2: with the eigenvalue of the first mode left out
#: Eigenvalues within this relative distance are one group of equal frequencies (a symmetric
#: body's pairs agree to about 1e-12; distinct modes of real meshes differ by far more).
EQUAL = 1e-6
DENSE_MAX_DOFS = 3000
"""Problems with at most this many free dofs are solved densely by ``method="auto"``."""
SHIFT_FRACTION = 1e-8
"""sigma = -SHIFT_FRACTION * median(diag K / diag M) over free dofs (K - sigma M is SPD)."""
CHILD_DOFS = 30_000
"""From this many free dofs on, the sparse eigensolve runs in a child process
(:mod:`wiggly.modes_child`: its factorization takes seconds to minutes and holds the
interpreter lock; below, the child's start-up of about a second would dominate)."""
ZERO_FLOOR = 1e-12
"""An elastic eigenvalue below ZERO_FLOOR * median(diag K / diag M) counts as zero."""
ZERO_RELATIVE = 1e-8
"""... or below ZERO_RELATIVE times the largest eigenvalue found."""


@dataclass
class Modes:
    """Eigenmodes of K phi = lambda M phi (Schulz et al. 2014, eq. (5)).

    Attributes
    ----------
    eigenvalues : (r,) float64
        lambda_i = omega_i^2 in s^-2, ascending; the first ``n_rigid`` are exactly 0.0.
    vectors : (3n, r) float64
        Phi, M-orthonormal (Phi^T M Phi = I) and K-diagonal (Phi^T K Phi = diag(lambda)),
        zero on the dofs of fixed vertices; rigid modes first.
    n_rigid : int
        Number of rigid modes (6 free, 3 one fixed vertex, 1 collinear fixed vertices, else 0).
    fixed_vertices : (k,) int64
        Sorted indices of the fixed vertices (empty for a free body).
    """

    eigenvalues: np.ndarray
    vectors: np.ndarray
    n_rigid: int
    fixed_vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    #: lambda of the lowest mode left out (None: not known), to tell whether the basis ends
    #: inside a group of equal frequencies (:meth:`split_group`)
    next_eigenvalue: float | None = None

    def split_group(self) -> int:
        """How many of the last kept elastic modes share their eigenvalue (to a relative
        :data:`EQUAL`) with the lowest mode left out: then the basis holds part of a group of
        equal frequencies, an arbitrary one (the eigensolver's pick), and a symmetric body
        answers symmetric keys unequally; 0 when it ends between groups (or is unknown)."""
        lam = self.eigenvalues[self.n_rigid:]
        nxt = self.next_eigenvalue
        if nxt is None or not len(lam) or not nxt > 0:
            return 0
        return int(np.sum(np.abs(lam - nxt) <= EQUAL * nxt))

    def __repr__(self) -> str:  # a summary: the arrays are attributes
        f = self.frequencies_hz()[self.n_rigid:]
        band = f", elastic {f[0]:.3g} to {f[-1]:.3g} Hz" if len(f) else ""
        return f"Modes({self.r}, {self.n_rigid} rigid{band})"

    @property
    def r(self) -> int:
        """Number of modes."""
        return int(self.eigenvalues.shape[0])

    def frequencies_hz(self) -> np.ndarray:
        """Natural frequencies ``sqrt(lambda) / (2 pi)`` in Hz (0 for rigid modes)."""
        return np.sqrt(np.maximum(self.eigenvalues, 0.0)) / (2.0 * np.pi)


def rigid_motions(V: np.ndarray) -> np.ndarray:
    """Rigid motions of the vertices, linearized (Schulz et al. 2014, eq. (5)).

    Parameters
    ----------
    V : (n, 3) float
        Rest positions.

    Returns
    -------
    (3n, 6) float64
        Columns 0-2: unit translations along x, y, z.  Columns 3-5: linearized rotations
        ``e_k x (x - c)`` about the axes through the centroid c of the vertices.
        Interleaved dofs (row ``3 i + c``).
    """
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] == 0:
        raise WigglyInputError(f"vertices should have shape (n, 3), n >= 1; shape is {V.shape}")
    n = V.shape[0]
    X = V - V.mean(axis=0)
    R = np.zeros((n, 3, 6))
    R[:, [0, 1, 2], [0, 1, 2]] = 1.0
    zero = np.zeros(n)
    R[:, :, 3] = np.column_stack([zero, -X[:, 2], X[:, 1]])  # e_x x X
    R[:, :, 4] = np.column_stack([X[:, 2], zero, -X[:, 0]])  # e_y x X
    R[:, :, 5] = np.column_stack([-X[:, 1], X[:, 0], zero])  # e_z x X
    return R.reshape(3 * n, 6)


class _Progress:
    """Status lines on the ``wiggly.modes`` logger, and a counter of shift-invert solves (a
    bar on a terminal)."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.t0 = time.perf_counter()
        self.bar = None

    def say(self, message: str) -> None:
        if self.enabled:
            log.info(f"modes, {time.perf_counter() - self.t0:.2f} s: {message}")

    def start_counter(self, desc: str) -> None:
        if self.enabled:
            self.bar = iterations(desc, unit="solve")

    def tick(self, n: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def stop_counter(self) -> int:
        count = 0
        if self.bar is not None:
            count = int(self.bar.n)
            self.bar.close()
            self.bar = None
        return count


def _as_csr(A: sp.spmatrix | np.ndarray, name: str, size: int) -> sp.csr_matrix:
    if not sp.issparse(A):
        A = np.asarray(A)
        if A.ndim != 2:
            raise WigglyInputError(
                f"{name} should be a ({size}, {size}) matrix; shape is {A.shape}"
            )
    if A.shape != (size, size):
        raise WigglyInputError(
            f"{name} should have shape ({size}, {size}) = 3 x number of vertices; "
            f"shape is {A.shape}"
        )
    A = sp.csr_matrix(A, dtype=np.float64, copy=True)
    A.sum_duplicates()
    A.sort_indices()
    if not np.all(np.isfinite(A.data)):
        raise WigglyInputError(f"{name} has non-finite entries")
    asym = abs(A - A.T).max() if A.nnz else 0.0
    if asym > 1e-10 * max(abs(A).max(), np.finfo(float).tiny):
        raise WigglyInputError(f"{name} should be symmetric; max |{name} - {name}^T| = {asym:.3g}")
    return A


def _hash_update_csr(h: hashlib._Hash, A: sp.csr_matrix) -> None:
    h.update(repr(A.shape).encode())
    h.update(np.ascontiguousarray(A.indptr, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(A.indices, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(A.data, dtype=np.float64).tobytes())


def _cache_key(K: sp.csr_matrix, M: sp.csr_matrix, r: int, fixed: np.ndarray, V: np.ndarray) -> str:
    h = hashlib.sha256(CACHE_FORMAT.encode())
    h.update(f"|r={r}|".encode())
    h.update(np.ascontiguousarray(fixed, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(V, dtype=np.float64).tobytes())
    _hash_update_csr(h, K)
    _hash_update_csr(h, M)
    return h.hexdigest()


def _load_cache(path: Path, key: str, r: int, n: int) -> Modes | None:
    """The cached modes at ``path`` if it exists, matches ``key`` and is sane, else None."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key:
                return None
            modes = Modes(
                eigenvalues=np.array(data["eigenvalues"], dtype=np.float64),
                vectors=np.array(data["vectors"], dtype=np.float64),
                n_rigid=int(data["n_rigid"]),
                fixed_vertices=np.array(data["fixed_vertices"], dtype=np.int64),
                next_eigenvalue=(float(data["next_eigenvalue"])
                                 if np.isfinite(data["next_eigenvalue"]) else None),
            )
    except Exception:  # corrupt or foreign file: recompute
        return None
    ok = (
        modes.eigenvalues.shape == (r,)
        and modes.vectors.shape == (3 * n, r)
        and 0 <= modes.n_rigid <= min(6, r)
        and np.all(np.isfinite(modes.eigenvalues))
        and np.all(np.isfinite(modes.vectors))
    )
    return modes if ok else None


def _save_cache(path: Path, key: str, modes: Modes) -> None:
    """Write atomically (temporary file in the same directory, then os.replace)."""
    try:
        with atomic_file(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                key=np.array(key),
                eigenvalues=modes.eigenvalues,
                vectors=modes.vectors,
                n_rigid=np.array(modes.n_rigid),
                fixed_vertices=modes.fixed_vertices,
                next_eigenvalue=np.array(np.nan if modes.next_eigenvalue is None
                                         else modes.next_eigenvalue),
            )
    except OSError as err:
        warn(f"could not write the modes cache {path}: {err}")


def _rigid_basis(V: np.ndarray, fixed: np.ndarray, free_dofs: np.ndarray, Mf: sp.csr_matrix):
    """M-orthonormal basis (free dofs) of the rigid motions vanishing on the fixed dofs.

    The rigid motions R c with R = rigid_motions(V) that vanish on the fixed dofs are the null
    space of R[fixed dofs]; rotations are scaled by the body's radius so that the singular
    values are comparable.  Translations come first when the body is free (Gram-Schmidt in the
    M inner product keeps them pure translations).
    """
    R = rigid_motions(V)
    radius = np.sqrt(np.mean(np.sum((V - V.mean(axis=0)) ** 2, axis=1)))
    R[:, 3:] /= max(radius, np.finfo(float).tiny)
    if fixed.size:
        A = R[(3 * fixed[:, None] + np.arange(3)).ravel()]
        if A.shape[0] > 6:  # same singular values and right vectors as its 6x6 QR factor
            A = la.qr(A, mode="r")[0][:6]
        _, s, Vt = la.svd(A, full_matrices=True)
        rank = int(np.sum(s > 1e-9 * s[0]))
        R = R @ Vt[rank:].T
    Rf = R[free_dofs]
    if Rf.shape[1] == 0:
        return Rf
    G = Rf.T @ (Mf @ Rf)
    L = la.cholesky(G, lower=True)
    return la.solve_triangular(L, Rf.T, lower=True).T  # Rf L^{-T}


def _rayleigh_ritz(
    X: np.ndarray, Kf: sp.csr_matrix, Mf: sp.csr_matrix, Rig: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ritz pairs of (K, M) on span(X) minus the rigid subspace, ascending.

    X is projected onto the M-orthogonal complement of span(Rig) (twice, for accuracy);
    directions that vanish under the projection (X's rigid part) are dropped.
    """
    for _ in range(2):
        X = X - Rig @ (Rig.T @ (Mf @ X))
    B = X.T @ (Mf @ X)
    d, U = la.eigh((B + B.T) / 2)
    keep = d > 1e-8 * d.max() if d.size and d.max() > 0 else np.zeros(d.size, dtype=bool)
    Y = X @ (U[:, keep] / np.sqrt(d[keep]))
    for _ in range(2):
        Y = Y - Rig @ (Rig.T @ (Mf @ Y))
    A = Y.T @ (Kf @ Y)
    B = Y.T @ (Mf @ Y)
    lam, W = la.eigh((A + A.T) / 2, (B + B.T) / 2)
    return lam, Y @ W


def _candidates_dense(
    Kf: sp.csr_matrix, Mf: sp.csr_matrix, k: int
) -> tuple[np.ndarray, np.ndarray]:
    nf = Kf.shape[0]
    lam, X = la.eigh(Kf.toarray(), Mf.toarray(), subset_by_index=[0, min(k, nf) - 1])
    return lam, X


def shift_invert(
    Kf: sp.csr_matrix,
    Mf: sp.csr_matrix,
    k: int,
    sigma: float,
    backend: str | None,
    factored: Callable[[str], None],
    solved: Callable[[], None],
) -> tuple[np.ndarray, np.ndarray]:
    """The k eigenpairs of ``Kf x = lam Mf x`` nearest ``sigma``: Lanczos (``eigsh``) on
    ``(Kf - sigma Mf)^-1 Mf`` with a sparse Cholesky factor; ``factored(backend name)`` is
    called once the factor exists, ``solved()`` after each of its solves."""
    nf = Kf.shape[0]
    solver = factorize_spd((Kf - sigma * Mf).tocsr(), backend=backend)
    factored(solver.backend)

    def matvec(x: np.ndarray) -> np.ndarray:
        solved()
        return solver(np.ravel(x))

    OPinv = spla.LinearOperator((nf, nf), matvec=matvec, dtype=np.float64)
    v0 = np.random.default_rng(0).standard_normal(nf)
    return spla.eigsh(Kf, k=k, M=Mf, sigma=sigma, which="LM", OPinv=OPinv, v0=v0)


def _candidates_sparse(
    Kf: sp.csr_matrix,
    Mf: sp.csr_matrix,
    k: int,
    sigma: float,
    backend: str | None,
    progress: _Progress,
) -> tuple[np.ndarray, np.ndarray]:
    nf = Kf.shape[0]
    solve, where = shift_invert, ""
    if nf >= CHILD_DOFS:
        from wiggly.child import can_run_child
        from wiggly.modes_child import eigsh_in_child

        if can_run_child():  # stoppable, with a live line while it factorizes
            solve, where = eigsh_in_child, " in a child process"
    progress.say(f"factorizing K - sigma M ({nf} dofs, sigma = {sigma:.3g}){where}")

    def factored(name: str) -> None:
        progress.say(f"factorized with {name}; eigsh for {k} eigenpairs")
        progress.start_counter("eigsh shift-invert solves")

    try:
        lam, X = solve(Kf, Mf, k, sigma, backend, factored, progress.tick)
    finally:
        count = progress.stop_counter()
    progress.say(f"eigsh done ({count} solves)" if count else "eigsh done")
    return lam, X


def _normalize_signs(Phi: np.ndarray) -> np.ndarray:
    """Flip columns so that each one's largest-magnitude entry is positive (reproducible)."""
    if Phi.size == 0:
        return Phi
    idx = np.argmax(np.abs(Phi), axis=0)
    signs = np.sign(Phi[idx, np.arange(Phi.shape[1])])
    signs[signs == 0] = 1.0
    return Phi * signs


@deprecated_progress
def compute_modes(
    K: sp.spmatrix,
    M: sp.spmatrix,
    r: int,
    *,
    vertices: np.ndarray,
    fixed_vertices: np.ndarray | list[int] | None = None,
    cache_dir: str | os.PathLike[str] | Literal[False] | None = None,
    method: Literal["auto", "sparse", "dense"] = "auto",
    backend: str | None = None,
    called: str = "r",
) -> Modes:
    """Lowest r eigenmodes of K phi = lambda M phi, rigid modes first (Schulz et al. 2014, eq. (5)).

    Parameters
    ----------
    K, M : (3n, 3n) sparse, symmetric
        Stiffness (PSD) and mass (PD) from :mod:`wiggly.fem`.
    r : int
        Number of modes, rigid ones included; ``n_rigid <= r <= number of free dofs`` and
        ``r <= MAX_MODES`` (:mod:`wiggly.limits`, as for scene files).
    vertices : (n, 3) float
        Rest positions (the rigid motions depend on them).
    fixed_vertices : indices or (n,) bool mask, optional
        Vertices held at rest; their dofs are removed.
    cache_dir : path, None or False
        Directory of the ``.npz`` cache; None uses :func:`default_cache_dir`; False disables.
    method : {"auto", "sparse", "dense"}
        "sparse": shift-invert ``eigsh``; "dense": ``scipy.linalg.eigh`` on dense matrices;
        "auto": dense up to :data:`DENSE_MAX_DOFS` free dofs (or when r >= free dofs - 1).
    backend : str, optional
        Sparse Cholesky backend, see :func:`wiggly.linalg.factorize_spd`.
    called : str
        How messages name ``r`` (``"n_modes"`` for :func:`wiggly.prepare`).

    Returns
    -------
    Modes

    Raises
    ------
    WigglyInputError
        Bad r, shapes or fixed set; unused vertices; K not annihilating rigid motions of
        ``vertices``; a body with disconnected parts (more zero modes than rigid motions).
    """
    V = np.asarray(vertices, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or V.shape[0] == 0:
        raise WigglyInputError(f"vertices should have shape (n, 3), n >= 1; shape is {V.shape}")
    if not np.all(np.isfinite(V)):
        raise WigglyInputError("vertices should be finite")
    n = V.shape[0]
    K = _as_csr(K, "K", 3 * n)
    M = _as_csr(M, "M", 3 * n)
    fixed = vertex_set(fixed_vertices, n, "fixed_vertices")
    if isinstance(r, bool) or not isinstance(r, int | np.integer):
        raise WigglyInputError(f"{called} (number of modes) should be an integer; got {r!r}")
    r = int(r)
    free_mask = np.ones(3 * n, dtype=bool)
    free_mask[(3 * fixed[:, None] + np.arange(3)).ravel()] = False
    free_dofs = np.flatnonzero(free_mask)
    nf = free_dofs.size
    if r > MAX_MODES:
        raise WigglyInputError(
            f"{called} (number of modes) should be at most {MAX_MODES} (wiggly.limits.MAX_MODES, "
            f"as in scene files); got {r}"
        )
    if nf == 0:
        raise WigglyInputError(
            "every vertex is fixed: no degrees of freedom are left to move (fix fewer vertices)")
    if r < 1 or r > nf:
        raise WigglyInputError(
            f"{called} (number of modes) should be in [1, {nf}] (the number of free dofs); got "
            f"{r}"
        )
    if method not in ("auto", "sparse", "dense"):
        raise WigglyInputError(f"method should be 'auto', 'sparse' or 'dense'; got {method!r}")

    path = None
    if cache_dir is not False:
        key = _cache_key(K, M, r, fixed, V)
        directory = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        path = directory / f"modes-{key[:40]}.npz"
        cached = _load_cache(path, key, r, n)
        if cached is not None:
            say(f"loaded {r} modes from {path}", logger=log)
            return cached

    with blas_single_thread():
        modes = _compute_modes(K, M, r, V, fixed, free_dofs, method, backend,
                               _Progress(shown()), called)
    if path is not None:
        _save_cache(path, key, modes)
    return modes


def _compute_modes(
    K: sp.csr_matrix,
    M: sp.csr_matrix,
    r: int,
    V: np.ndarray,
    fixed: np.ndarray,
    free_dofs: np.ndarray,
    method: str,
    backend: str | None,
    progress: _Progress,
    called: str = "r",
) -> Modes:
    n = V.shape[0]
    nf = free_dofs.size
    Kf = K[free_dofs][:, free_dofs].tocsr()
    Mf = M[free_dofs][:, free_dofs].tocsr()
    dK, dM = Kf.diagonal(), Mf.diagonal()
    if np.any(dM <= 0):
        unused = np.unique(free_dofs[dM <= 0] // 3)
        raise WigglyInputError(
            f"{counted(unused.size, 'free vertex')} {'has' if unused.size == 1 else 'have'} "
            "no mass (not used by any tet), "
            f"e.g. vertex {unused[0]}; remove them or fix them"
        )
    # fixed vertices outside the mesh (no mass) hold nothing: leave them out of the analysis
    used = M.diagonal().reshape(n, 3).min(axis=1) > 0
    all_fixed, fixed = fixed, fixed[used[fixed]]
    _check_connected(K, fixed, used)
    scale = float(np.median(dK / dM))  # ~ the highest eigenvalues of the mesh
    if not scale > 0:
        raise WigglyInputError("K has a non-positive diagonal; is it a stiffness matrix?")

    Rig = _rigid_basis(V, fixed, free_dofs, Mf)
    n_rigid = Rig.shape[1]
    if n_rigid:
        residual = np.linalg.norm(Kf @ Rig, axis=0) / (
            np.abs(dK).max() * np.linalg.norm(Rig, axis=0)
        )
        if np.any(residual > 1e-8):
            raise WigglyInputError(
                "K does not vanish on the rigid motions of `vertices` (relative residual "
                f"{residual.max():.3g}); are K and vertices from the same mesh?"
            )
    if r < n_rigid:
        raise WigglyInputError(
            f"{called} = {r} is smaller than the number of rigid modes of this body "
            f"({n_rigid}); the basis must contain all rigid modes, or the body could not move "
            f"freely: use {called} >= {n_rigid} ({called} = {n_rigid} moves it rigidly only; "
            "each mode more bends it)"
        )
    progress.say(f"{n_rigid} rigid modes; {r - n_rigid} elastic modes to compute ({nf} dofs)")

    k_el = r - n_rigid
    next_eigenvalue = None
    lam_el = np.zeros(0)
    Phi_el = np.zeros((nf, 0))
    if k_el:
        dense = method == "dense" or (method == "auto" and (nf <= DENSE_MAX_DOFS or r >= nf - 1))
        if method == "sparse" and r >= nf - 1:
            raise WigglyInputError(
                f"method='sparse' needs r < free dofs - 1 = {nf - 1}; got r = {r}; use 'dense'"
            )
        k = min(r + 1, nf - (0 if dense else 2))  # one more: the first left out
        while True:
            if dense:
                progress.say(f"dense eigh ({nf} dofs)")
                _, X = _candidates_dense(Kf, Mf, k)
            else:
                _, X = _candidates_sparse(Kf, Mf, k, -SHIFT_FRACTION * scale, backend, progress)
            lam, Phi = _rayleigh_ritz(X, Kf, Mf, Rig)
            if lam.size >= k_el or k >= nf - (0 if dense else 2):
                break
            k = min(k + n_rigid + 4, nf - (0 if dense else 2))  # rare: not enough survived
        if lam.size < k_el:
            raise RuntimeError(f"found only {lam.size} of {k_el} elastic modes")
        zero_tol = max(ZERO_RELATIVE * lam.max(), ZERO_FLOOR * scale)
        n_zero = int(np.sum(lam < zero_tol))
        if n_zero:
            raise WigglyInputError(
                f"the body has {n_zero} more zero-energy {'mode' if n_zero == 1 else 'modes'} "
                f"than its {n_rigid} rigid "
                "motions: it has disconnected parts (or parts joined only at a vertex or an "
                "edge, or parts free to move despite the fixed vertices); mesh it as one "
                "connected body (join the parts in a modelling tool, or mesh it at a higher "
                "resolution so that thin joints get tets of their own), or fix vertices on "
                "each loose part"
            )
        lam_el, Phi_el = lam[:k_el], Phi[:, :k_el]
        next_eigenvalue = float(lam[k_el]) if lam.size > k_el else None

    vectors = np.zeros((3 * n, r))
    vectors[free_dofs] = _normalize_signs(np.hstack([Rig, Phi_el]))
    eigenvalues = np.concatenate([np.zeros(n_rigid), lam_el])
    progress.say("done")
    return Modes(
        eigenvalues=eigenvalues, vectors=vectors, n_rigid=n_rigid, fixed_vertices=all_fixed,
        next_eigenvalue=next_eigenvalue,
    )


def _check_connected(K: sp.csr_matrix, fixed: np.ndarray, used: np.ndarray) -> None:
    """Reject a body made of separate pieces one of which has no fixed vertex.

    Only ``used`` vertices (those with mass) count.  Pieces joined only through K's sparsity
    (a shared vertex or edge) pass this test; their extra zero modes are caught after the
    eigensolve.
    """
    n = used.size
    coo = K.tocoo()
    graph = sp.csr_matrix((np.ones(coo.nnz), (coo.row // 3, coo.col // 3)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    parts, labels = np.unique(labels[used], return_inverse=True)
    if parts.size == 1:
        return
    held = np.zeros(parts.size, dtype=bool)
    held[labels[np.searchsorted(np.flatnonzero(used), fixed)]] = True
    if not np.all(held):
        sizes = np.bincount(labels, minlength=parts.size)
        raise WigglyInputError(
            f"the body has {parts.size} disconnected parts (tet-mesh vertex counts "
            f"{sorted(sizes.tolist(), reverse=True)[:8]}), and not every part has fixed "
            "vertices; its loose parts would float away (keyframes alone do not hold a "
            "part): mesh it as one connected body, or fix a group on each part"
        )
