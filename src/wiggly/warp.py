"""Rotation-strain warping of linear displacements (SYSTEM.md §6; Huang et al. 2011).

Linear FEM displacements distort under large rotations (limbs grow). The warp map
``W`` repairs this, one tetrahedron at a time: the displacement gradient
``A = grad u`` is split into a rotation vector ``w = axial((A - A^T) / 2)`` and a
strain ``S = (A + A^T) / 2``; the *target* deformation gradient is

    F_t = exp([w]x) (I + S),

and the warped displacement is the volume-weighted least-squares (Poisson) fit

    W(u) = argmin_x  sum_t vol_t || grad(x)_t - (F_t - I) ||_F^2   (+ gauge),

whose normal matrix is the scalar cotangent Laplacian ``L = G^T Vol G`` (one block
per coordinate). ``L`` does not depend on ``u``: it is factored once per body.

Gauge (the Laplacian only determines ``W(u)`` up to a constant per connected
component of the mesh):

* a component containing fixed vertices gets Dirichlet conditions: ``W(u) = 0``
  on its fixed vertices (their rows and columns are eliminated from ``L``);
* a free-floating component is solved with one vertex pinned to zero (its row and
  column eliminated, which is exact because the right-hand side is orthogonal to
  constants), then shifted by a constant so that its mass-weighted mean
  displacement equals that of ``u``:  ``sum_i m_i W(u)_i = sum_i m_i u_i``.

Consequences, exactly (up to round-off):

* ``W(0) = 0``; for a free body, ``W(u + d) = W(u) + d`` for translations ``d``;
* ``W(u) = u + O(|u|^2)`` (for ``u`` vanishing on the fixed vertices);
* a linearized rotation ``u(X) = w x (X - c)`` of a free body is warped to the
  exact rotation by the angle ``|w|`` about the axis ``w`` through the mass centre
  ``c_m = sum_i m_i X_i / sum_i m_i``, followed by the translation ``u_bar``
  (the mass-weighted mean of ``u``, equal to ``w x (c_m - c)``)::

      X + W(u)(X) = R (X - c_m) + c_m + u_bar,   R = exp([w]x);

  more generally, any ``u`` of a free body with a constant gradient ``A`` maps
  to ``W(u)(X) = (exp([w]x)(I + S) - I)(X - c_m) + u_bar``;

* with fixed vertices the Dirichlet gauge replaces the mean: a linearized rotation
  ``u = w x (X - c)`` about a fixed vertex ``c`` (more fixed vertices on the axis
  are fine) becomes exactly ``X + W(u) = R (X - c) + c``.

Implementation: ``G`` is a sparse (3m, n) matrix acting on all frames at once as
an (n, 3f) array; the per-tet map works on one array per matrix entry in
cache-sized blocks (vectorized Rodrigues, no 3x3 matmul calls); the Laplacian of
the free vertices is factored once (:func:`wiggly.linalg.factorize_spd`) and a
batch of f frames is one solve with 3f right-hand sides. Derivatives use the
left Jacobian ``J(w)`` of the rotation map: ``d exp([w]x)[dw] = [J(w) dw]x
exp([w]x)``, stable at small angles.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy.sparse as sp
from scipy.linalg import blas
from scipy.sparse.csgraph import connected_components

from wiggly import warp_kernels
from wiggly.errors import WigglyInputError
from wiggly.linalg import available_backends, factorize_spd

__all__ = [
    "CoarseWarp",
    "Warp",
    "rotation_coefficients",
    "tet_gradient_operator",
    "tet_gradients",
]

# Below this angle (radians) the coefficient c = (th - sin th) / th^3 of the rotation
# derivative is evaluated by its Taylor series in th^2 (truncation error < 1e-19 there).
_SERIES_ANGLE = 0.1
# Angles are clamped below by this value so that sin(th) / th needs no special case.
_TINY_ANGLE = 1e-300
# Frames (columns) per chunk: bounds the memory of the per-tet gradient arrays.
_CHUNK_COLUMNS = 16
# Elements per component array in a block of the per-tet arithmetic (stays in cache).
_BLOCK_ELEMENTS = 8192


# --------------------------------------------------------------------------- #
# Geometry: the P1 gradient operator
# --------------------------------------------------------------------------- #
def tet_gradients(vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the four P1 basis functions of every tet, (m, 4, 3), and volumes (m,).

    With ``Dm = [X1 - X0, X2 - X0, X3 - X0]`` the gradients of ``phi_1..phi_3`` are the
    rows of ``inv(Dm)`` and ``grad phi_0 = -(grad phi_1 + grad phi_2 + grad phi_3)``.
    """
    X = vertices[tets]  # (m, 4, 3)
    Dm = (X[:, 1:] - X[:, :1]).transpose(0, 2, 1)  # columns are edge vectors
    vol = np.linalg.det(Dm) / 6.0
    if np.any(~(vol > 0.0)):
        bad = np.flatnonzero(~(vol > 0.0))
        raise WigglyInputError(
            f"tets should be positively oriented with positive volume; {bad.size} tets are "
            f"degenerate or inverted (first: tet {bad[0]}, volume {vol[bad[0]]:.3g})"
        )
    Dinv = np.linalg.inv(Dm)
    grads = np.empty((tets.shape[0], 4, 3))
    grads[:, 1:] = Dinv
    grads[:, 0] = -Dinv.sum(axis=1)
    return grads, vol


def tet_gradient_operator(
    vertices: np.ndarray, tets: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Scalar P1 gradient operator and tetrahedron volumes.

    Parameters
    ----------
    vertices : (n, 3) float array
        Rest positions ``X``.
    tets : (m, 4) int array
        Positively oriented tetrahedra.

    Returns
    -------
    G : (3 m, n) csr_matrix
        Row ``3 t + j`` gives ``d phi / d X_j`` on tetrahedron ``t`` of a P1
        scalar field ``phi`` (tet-major rows). For a displacement field laid out
        as columns ``U[:, i]`` (component ``i``), ``(G @ U)[3 t + j, i] = d u_i / d X_j``
        on tet ``t``, so ``(G @ U).reshape(m, 3, 3)[t]`` is the transposed gradient.
    vol : (m,) float array
        Volumes (positive for positively oriented tets).

    Notes
    -----
    With ``Dm = [X1 - X0, X2 - X0, X3 - X0]`` the gradients of the barycentric
    basis functions ``phi_1..phi_3`` are the rows of ``inv(Dm)``, and
    ``grad phi_0 = -(grad phi_1 + grad phi_2 + grad phi_3)``.
    """
    grads, vol = tet_gradients(vertices, tets)
    m = tets.shape[0]
    rows = np.broadcast_to((3 * np.arange(m)[:, None] + np.arange(3))[:, :, None], (m, 3, 4))
    cols = np.broadcast_to(tets[:, None, :], (m, 3, 4))
    data = grads.transpose(0, 2, 1)  # (m, 3 j, 4 k)
    G = sp.csr_matrix(
        (data.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, vertices.shape[0])
    )
    G.sum_duplicates()
    return G, vol


# --------------------------------------------------------------------------- #
# Per-tet arithmetic on component fields (one array per matrix entry)
# --------------------------------------------------------------------------- #
# A block of per-tet 3x3 fields is a contiguous array ``B`` of shape (3, 3, c, mb):
# ``B[i, j]`` is entry (i, j) for c columns (frames or directions) and mb tets.
# Per-tet data shared by all columns has shape (1, mb) and broadcasts.
Field = np.ndarray
Mat = Sequence[Sequence[Field]]


def _cross(u: Sequence[Field], v: Sequence[Field]) -> tuple[Field, Field, Field]:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _rotation_strain(E: Mat) -> tuple[tuple[Field, Field, Field], Mat]:
    """Rotation vector ``w = axial((A - A^T)/2)`` and strain ``S = (A + A^T)/2`` of ``A``."""
    w = (0.5 * (E[2][1] - E[1][2]), 0.5 * (E[0][2] - E[2][0]), 0.5 * (E[1][0] - E[0][1]))
    s01 = 0.5 * (E[0][1] + E[1][0])
    s02 = 0.5 * (E[0][2] + E[2][0])
    s12 = 0.5 * (E[1][2] + E[2][1])
    S = ((E[0][0], s01, s02), (s01, E[1][1], s12), (s02, s12, E[2][2]))
    return w, S


def rotation_coefficients(
    theta2: np.ndarray, *, derivative: bool = False
) -> tuple[np.ndarray, ...]:
    """Rodrigues coefficients from ``theta2 = |w|^2``, accurate at every angle.

    ``a = sin(th)/th`` and ``b = (1 - cos th)/th^2 = (sin(th/2)/th)^2 * 2``, so that
    ``exp([w]x) = I + a [w]x + b [w]x^2``. With ``derivative=True`` also
    ``c = (th - sin th)/th^3`` (Taylor series below ``th = 0.1``), so that the left
    Jacobian of the rotation map is ``J(w) = I + b [w]x + c [w]x^2`` and
    ``d exp([w]x)[dw] = [J(w) dw]x exp([w]x)``.
    """
    th = np.sqrt(theta2)
    np.maximum(th, _TINY_ANGLE, out=th)
    a = np.sin(th)
    a /= th
    b = np.sin(0.5 * th)
    b /= th
    b *= b
    b *= 2.0
    if not derivative:
        return a, b
    x = theta2
    c_series = 1.0 / 6.0 - x / 120.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0 * (1.0 - x / 110.0)))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(x < _SERIES_ANGLE**2, c_series, (1.0 - a) / x)
    return a, b, c


def _rotation_minus_identity(w: Sequence[Field], a: Field, b: Field) -> Mat:
    """``exp([w]x) - I = a [w]x + b (w w^T - |w|^2 I)``, free of cancellation for small ``w``."""
    bw0, bw1, bw2 = b * w[0], b * w[1], b * w[2]
    p01, p02, p12 = bw0 * w[1], bw0 * w[2], bw1 * w[2]
    q0, q1, q2 = a * w[0], a * w[1], a * w[2]
    return (
        (-(bw1 * w[1] + bw2 * w[2]), p01 - q2, p02 + q1),
        (p01 + q2, -(bw0 * w[0] + bw2 * w[2]), p12 - q0),
        (p02 - q1, p12 + q0, -(bw0 * w[0] + bw1 * w[1])),
    )


def _target_block(out: np.ndarray, A: np.ndarray) -> None:
    """Target displacement gradient ``exp([w]x)(I + S) - I`` (SYSTEM.md §6).

    Evaluated as ``(R - I) + S + (R - I) S``, accurate for tiny gradients.
    """
    w, S = _rotation_strain(A)
    a, b = rotation_coefficients(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    Rm = _rotation_minus_identity(w, a, b)
    for i in range(3):
        for j in range(3):
            out[i, j] = (
                Rm[i][j] + S[i][j] + Rm[i][0] * S[0][j] + Rm[i][1] * S[1][j] + Rm[i][2] * S[2][j]
            )


def _linearization(A: np.ndarray) -> list[Field]:
    """Per-tet quantities for derivatives at gradient ``A``: ``[w, b, c, R, F]`` (23 fields)."""
    w, S = _rotation_strain(A)
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    a, b, c = rotation_coefficients(t2, derivative=True)
    Rm = _rotation_minus_identity(w, a, b)
    R = [[Rm[i][j] + 1.0 if i == j else Rm[i][j] for j in range(3)] for i in range(3)]
    F = [
        [R[i][j] + R[i][0] * S[0][j] + R[i][1] * S[1][j] + R[i][2] * S[2][j] for j in range(3)]
        for i in range(3)
    ]
    return [
        *w,
        b,
        c,
        *(R[i][j] for i in range(3) for j in range(3)),
        *(F[i][j] for i in range(3) for j in range(3)),
    ]


def _unpack(lin: Sequence[Field]) -> tuple[Sequence[Field], Field, Field, Mat, Mat]:
    return (
        lin[0:3],
        lin[3],
        lin[4],
        [lin[5 + 3 * i : 8 + 3 * i] for i in range(3)],
        [lin[14 + 3 * i : 17 + 3 * i] for i in range(3)],
    )


def _jvp_block(out: np.ndarray, lin: Sequence[Field], dA: np.ndarray) -> None:
    """``dH = [J(w) dw]x F + R dS`` with ``dw``, ``dS`` the rotation/strain parts of ``dA``."""
    w, b, c, R, F = _unpack(lin)
    dw, dS = _rotation_strain(dA)
    wxd = _cross(w, dw)
    wwd = _cross(w, wxd)
    v = [dw[k] + b * wxd[k] + c * wwd[k] for k in range(3)]
    for j in range(3):
        vxF = _cross(v, (F[0][j], F[1][j], F[2][j]))
        for i in range(3):
            out[i, j] = vxF[i] + R[i][0] * dS[0][j] + R[i][1] * dS[1][j] + R[i][2] * dS[2][j]


def _vjp_block(out: np.ndarray, lin: Sequence[Field], Yb: np.ndarray) -> None:
    """Adjoint of :func:`_jvp_block`: ``sym(R^T Y) + [J(w)^T g]x / 2``, ``g = 2 axial(Y F^T)``."""
    w, b, c, R, F = _unpack(lin)
    Y = Yb
    g = [
        Y[2][0] * F[1][0]
        + Y[2][1] * F[1][1]
        + Y[2][2] * F[1][2]
        - Y[1][0] * F[2][0]
        - Y[1][1] * F[2][1]
        - Y[1][2] * F[2][2],
        Y[0][0] * F[2][0]
        + Y[0][1] * F[2][1]
        + Y[0][2] * F[2][2]
        - Y[2][0] * F[0][0]
        - Y[2][1] * F[0][1]
        - Y[2][2] * F[0][2],
        Y[1][0] * F[0][0]
        + Y[1][1] * F[0][1]
        + Y[1][2] * F[0][2]
        - Y[0][0] * F[1][0]
        - Y[0][1] * F[1][1]
        - Y[0][2] * F[1][2],
    ]
    wxg = _cross(w, g)
    wwg = _cross(w, wxg)
    half = [0.5 * (g[k] - b * wxg[k] + c * wwg[k]) for k in range(3)]
    P = [
        [R[0][i] * Y[0][j] + R[1][i] * Y[1][j] + R[2][i] * Y[2][j] for j in range(3)]
        for i in range(3)
    ]
    s01 = 0.5 * (P[0][1] + P[1][0])
    s02 = 0.5 * (P[0][2] + P[2][0])
    s12 = 0.5 * (P[1][2] + P[2][1])
    out[:] = (
        (P[0][0], s01 - half[2], s02 + half[1]),
        (s01 + half[2], P[1][1], s12 - half[0]),
        (s02 - half[1], s12 + half[0], P[2][2]),
    )


def _jvp_fused(out: np.ndarray, A: np.ndarray, dA: np.ndarray) -> None:
    _jvp_block(out, _linearization(A), dA)


def _vjp_fused(out: np.ndarray, A: np.ndarray, Yb: np.ndarray) -> None:
    _vjp_block(out, _linearization(A), Yb)


# --------------------------------------------------------------------------- #
# The warp map
# --------------------------------------------------------------------------- #
class Warp:
    """Rotation-strain warp map ``W`` of a body, and its derivatives (SYSTEM.md §6).

    Built once per body: precomputes the P1 gradient operator, tet volumes, and a
    factorization of the (reduced) scalar cotangent Laplacian ``L = G^T Vol G``.
    See the module docstring for the map, the gauge and its exact consequences.

    Parameters
    ----------
    vertices : (n, 3) float array
        Rest positions.
    tets : (m, 4) int array
        Positively oriented tetrahedra.
    masses : (n,) float array, optional
        Per-vertex lumped masses defining the mass-weighted-mean gauge. Default:
        a quarter of the volume of the incident tets (volume-weighted).
    fixed_vertices : int index array or (n,) bool mask, optional
        Vertices where ``W(u) = 0`` (Dirichlet). Components of the mesh without
        fixed vertices keep the mass-weighted-mean gauge.

    Notes
    -----
    Displacements are ``(n, 3)`` arrays or batches ``(f, n, 3)``; a batch is
    processed with one multi-right-hand-side solve (``3 f`` columns).
    """

    def __init__(
        self,
        vertices: np.ndarray,
        tets: np.ndarray,
        *,
        masses: np.ndarray | None = None,
        fixed_vertices: np.ndarray | None = None,
    ) -> None:
        V = np.asarray(vertices, dtype=np.float64)
        T = np.asarray(tets)
        if V.ndim != 2 or V.shape[1] != 3:
            raise WigglyInputError(f"vertices should have shape (n, 3); shape is {V.shape}")
        if not np.all(np.isfinite(V)):
            raise WigglyInputError("vertices should be finite")
        if T.ndim != 2 or T.shape[1] != 4 or T.shape[0] == 0:
            raise WigglyInputError(f"tets should have shape (m, 4), m >= 1; shape is {T.shape}")
        if not np.issubdtype(T.dtype, np.integer):
            raise WigglyInputError(f"tets should be integer indices; dtype is {T.dtype}")
        n = V.shape[0]
        T = T.astype(np.int64)
        if T.min() < 0 or T.max() >= n:
            raise WigglyInputError(
                f"tet indices should lie in [0, {n}); range is [{T.min()}, {T.max()}]"
            )
        self.n_vertices = n
        self.n_tets = T.shape[0]

        G, vol = tet_gradient_operator(V, T)
        self.volumes = vol
        self._tets = np.ascontiguousarray(T)
        self._grads = tet_gradients(V, T)[0]
        # fused compiled per-tet kernels (numba); False: the vectorized numpy path
        self.compiled = warp_kernels.AVAILABLE
        self._G = G  # (3m, n): per-tet gradients
        self._Gt = sp.csr_matrix(G.T)  # (n, 3m)
        self._VG = sp.csr_matrix(sp.diags(np.repeat(vol, 3)) @ G)  # Vol G (rows 3 t + j)
        self._GtV = sp.csr_matrix(self._VG.T)  # G^T Vol: right-hand sides
        laplacian = sp.csr_matrix(self._GtV @ G)

        if masses is None:
            m = np.bincount(T.ravel(), weights=np.repeat(vol / 4.0, 4), minlength=n)
        else:
            m = np.asarray(masses, dtype=np.float64)
            if m.shape != (n,):
                raise WigglyInputError(f"masses should have shape ({n},); shape is {m.shape}")
            if not np.all(np.isfinite(m)) or np.any(m < 0):
                raise WigglyInputError("masses should be finite and non-negative")
        self.masses = m

        fixed = np.zeros(n, dtype=bool)
        if fixed_vertices is not None:
            fv = np.asarray(fixed_vertices)
            if fv.dtype == bool:
                if fv.shape != (n,):
                    raise WigglyInputError(
                        f"fixed_vertices mask should have shape ({n},); shape is {fv.shape}"
                    )
                fixed = fv.copy()
            elif np.issubdtype(fv.dtype, np.integer) or fv.size == 0:
                fv = fv.astype(np.int64).ravel()
                if fv.size and (fv.min() < 0 or fv.max() >= n):
                    raise WigglyInputError(
                        f"fixed_vertices should be indices in [0, {n}); "
                        f"range is [{fv.min()}, {fv.max()}]"
                    )
                fixed[fv] = True
            else:
                raise WigglyInputError(
                    f"fixed_vertices should be integer indices or a bool mask; dtype is {fv.dtype}"
                )
        self.fixed = fixed

        # Gauge. Connected components (an isolated vertex is one of its own): those
        # with fixed vertices are Dirichlet; the others get their highest-index vertex
        # pinned, then a constant shift restoring the mass-weighted mean of u.
        n_comp, label = connected_components(laplacian, directed=False)
        floating = np.ones(n_comp, dtype=bool)
        floating[label[fixed]] = False
        last = np.full(n_comp, -1)
        np.maximum.at(last, label, np.arange(n))
        eliminated = fixed.copy()
        eliminated[last[floating]] = True
        self._free = np.flatnonzero(~eliminated)
        # free vertices 0..k-1 (one free body: all but the last vertex): slices, not copies
        k = self._free.size
        self._rows = slice(0, k) if k == 0 or self._free[-1] == k - 1 else self._free

        n_float = int(floating.sum())
        comp_id = np.full(n_comp, -1)
        comp_id[floating] = np.arange(n_float)
        vid = comp_id[label]
        fv_idx = np.flatnonzero(vid >= 0)
        fid = vid[fv_idx]
        weight = m[fv_idx]
        total = np.bincount(fid, weights=weight, minlength=n_float)
        massless = total <= 0.0  # a component without mass uses the plain mean
        weight = np.where(massless[fid], 1.0, weight)
        total = np.where(massless, np.bincount(fid, minlength=n_float), total)
        self._has_floating = n_float > 0
        self._mean = sp.csr_matrix((weight / total[fid], (fid, fv_idx)), shape=(n_float, n))
        self._mean_weights = self._mean.toarray()[0] if n_float == 1 else None
        self._spread = (
            None  # one floating component, every vertex: spreading is broadcasting
            if n_float == 1 and fv_idx.size == n
            else sp.csr_matrix((np.ones(fv_idx.size), (fv_idx, fid)), shape=(n, n_float))
        )

        self._gb_key: tuple | None = None
        self._gb = np.zeros(0)
        self._frames_key: tuple | None = None
        self._frames = np.zeros(0)
        self._fg_key: tuple | None = None
        self._fg = np.zeros(0)
        if self._free.size:
            # many right-hand sides per solve (3 per frame): cholespy's multi-RHS solve is ~3x
            # faster than CHOLMOD on Debian's reference BLAS, and on a par with it on OpenBLAS
            self._solve = factorize_spd(
                laplacian[self._free][:, self._free],
                backend="cholespy" if "cholespy" in available_backends() else None,
            )
        else:
            self._solve = None

    # ------------------------------------------------------------------ layout
    def _as_columns(self, U: np.ndarray, name: str) -> tuple[np.ndarray, bool]:
        """(n, 3) -> (n, 3, 1) and (f, n, 3) -> (n, 3, f) view; flag: batched."""
        U = np.asarray(U, dtype=np.float64)
        n = self.n_vertices
        if U.shape == (n, 3):
            return U[:, :, None], False
        if U.ndim == 3 and U.shape[1:] == (n, 3):
            return U.transpose(1, 2, 0), True
        raise WigglyInputError(
            f"{name} should have shape ({n}, 3) or (f, {n}, 3); shape is {U.shape}"
        )

    @staticmethod
    def _from_columns(X: np.ndarray, batched: bool) -> np.ndarray:
        if batched:
            return np.ascontiguousarray(X.transpose(2, 0, 1))
        return X[:, :, 0]

    # --------------------------------------------------------- per-tet pipeline
    def _per_tet(
        self,
        kernel: Callable[..., None],
        inputs: Sequence[tuple[sp.csr_matrix, np.ndarray]],
        last: sp.csr_matrix,
    ) -> np.ndarray:
        """``last @ kernel(first_1 @ X_1, ...)`` column chunk by chunk, tet block by block.

        ``inputs`` are pairs ``(first, X)`` with ``first`` (3m, n) and ``X`` (n, 3, c).
        Gradients ``first @ X`` are laid out (m, 3 j, 3 i, c); the kernel gets
        contiguous (3 i, 3 j, c, mb) blocks and fills its first argument. Python
        loops run over chunks of columns and blocks of tets, never single ones.
        """
        m = self.n_tets
        c = inputs[0][1].shape[2]
        result = np.empty((last.shape[0], 3, c))
        for c0 in range(0, c, _CHUNK_COLUMNS):
            cc = min(c, c0 + _CHUNK_COLUMNS) - c0
            grads = [
                (first @ np.ascontiguousarray(X[:, :, c0 : c0 + cc]).reshape(-1, 3 * cc)).reshape(
                    m, 3, 3, cc
                )
                for first, X in inputs
            ]
            out = np.empty((m, 3, 3, cc))
            mb = max(1, _BLOCK_ELEMENTS // cc)
            for t0 in range(0, m, mb):
                blk = slice(t0, t0 + mb)
                ins = [np.ascontiguousarray(Y[blk].transpose(2, 1, 3, 0)) for Y in grads]
                res = np.empty_like(ins[0])
                kernel(res, *ins)
                out[blk] = res.transpose(3, 1, 0, 2)
            result[:, :, c0 : c0 + cc] = (last @ out.reshape(3 * m, 3 * cc)).reshape(-1, 3, cc)
        return result

    def _linearize(self, X: np.ndarray) -> list[Field]:
        """Per-tet linearization data (23 fields of shape (1, m)) at ``X`` (n, 3, 1)."""
        m = self.n_tets
        Y = (self._G @ np.ascontiguousarray(X).reshape(-1, 3)).reshape(m, 3, 3)
        A = Y.transpose(2, 1, 0)[:, :, None, :]  # (3 i, 3 j, 1, m)
        return _linearization(A)

    # ------------------------------------------------------------ Poisson + gauge
    def _solve_free(self, B: np.ndarray) -> np.ndarray:
        """``L^-1 B`` on the free vertices and 0 on the eliminated ones, for B (n, c)."""
        n, c = B.shape
        X = np.empty((n, c))
        if self._solve is None:
            X[:] = 0.0
        elif isinstance(self._rows, slice):  # free vertices first: solve into X's rows
            k = self._rows.stop
            self._solve(np.ascontiguousarray(B[:k]), out=X[:k])
            X[k:] = 0.0
        else:
            X[:] = 0.0
            X[self._rows] = self._solve(B[self._rows])
        return X

    def _gauge(self, X: np.ndarray, means_in: np.ndarray) -> None:
        """Shift each floating component of X (n, c), in place, to the mass-weighted means
        ``means_in`` (one row per floating component)."""
        delta = means_in - self._mean @ X
        if self._spread is None:  # one floating component, every vertex
            X += delta
        else:
            X += self._spread @ delta

    def _unmean(self, Y: np.ndarray) -> np.ndarray:
        """Adjoint of the gauge's shift on Y (n, c), in place: ``Y -= mean^T spread^T Y``;
        returns ``spread^T Y`` (the cotangent of ``means_in``)."""
        if self._spread is None and Y.flags.c_contiguous:  # one component: rank-1, in place
            s = Y.sum(axis=0, keepdims=True)
            blas.dger(-1.0, s[0], self._mean_weights, a=Y.T, overwrite_a=True)
            return s
        s = self._spread.T @ Y
        Y -= self._mean.T @ s
        return s

    def _frame_means(self, parts: Sequence[np.ndarray]) -> np.ndarray:
        """Mass-weighted means of the frames of ``parts`` (each (f_i, n, 3)) as (n_float, 3 f)
        columns, without transposing the frames."""
        if self._spread is None:  # one component: weights @ frames
            return np.concatenate([self._mean_weights @ p for p in parts]).reshape(1, -1)
        frames = [self._mean @ x for p in parts for x in p]
        return np.stack(frames, axis=1).reshape(self._mean.shape[0], -1)

    def _poisson(self, rhs: np.ndarray, X_in: np.ndarray) -> np.ndarray:
        """Gauged least-squares fit from right-hand sides ``G^T Vol H`` (n, 3, c).

        ``X_in`` (n, 3, c) supplies the mass-weighted means of floating components.
        """
        n = self.n_vertices
        X = self._solve_free(rhs.reshape(n, -1))
        if self._has_floating:
            self._gauge(X, self._mean @ X_in.reshape(n, -1))
        return X.reshape(rhs.shape)

    def _poisson_adjoint(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Adjoint of :meth:`_poisson`: cotangents on ``rhs`` and on ``X_in`` (n, 3, c)."""
        n = self.n_vertices
        Yf = np.array(Y.reshape(n, -1))
        Y_in = np.zeros_like(Yf)
        if self._has_floating:
            Y_in = self._mean.T @ self._unmean(Yf)
        return self._solve_free(Yf).reshape(Y.shape), Y_in.reshape(Y.shape)

    def _frames_of(self, U: np.ndarray, name: str) -> tuple[np.ndarray, bool]:
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

    def _poisson_frames(self, rhs: np.ndarray, X_in: Sequence[np.ndarray]) -> np.ndarray:
        """:meth:`_poisson` for frames: ``rhs`` (f, n, 3) and ``X_in`` the same frames in parts
        (each (f_i, n, 3)); the result (f, n, 3) is a view of the solve's (n, f, 3) columns
        (no copy back to frame order)."""
        f, n = rhs.shape[:2]
        X = self._solve_free(np.ascontiguousarray(rhs.transpose(1, 0, 2)).reshape(n, 3 * f))
        if self._has_floating:
            self._gauge(X, self._frame_means(X_in))
        return X.reshape(n, f, 3).transpose(1, 0, 2)

    def _poisson_adjoint_frames(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Adjoint of :meth:`_poisson_frames` for cotangents Y (f, n, 3): the cotangent of the
        right-hand sides as (n, f, 3) columns, and ``spread^T Y`` (n_float, f, 3), from which
        :meth:`_means_adjoint` makes the cotangent of ``X_in``; None when no component
        floats (it is zero)."""
        f, n = Y.shape[:2]
        Yc = np.array(Y.transpose(1, 0, 2), order="C").reshape(n, 3 * f)  # a copy: changed below
        s = self._unmean(Yc).reshape(-1, f, 3) if self._has_floating else None
        return self._solve_free(Yc).reshape(n, f, 3), s

    def _means_adjoint(self, s: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Cotangents of ``X_in`` (len(index), n, 3): ``mean^T s[:, index[j]]`` per frame j."""
        if self._spread is None:  # one component: mean^T s = w s, w the mass weights
            return self._mean_weights[None, :, None] * s[0, index][:, None, :]
        out = np.empty((len(index), self.n_vertices, 3))
        for j, c in enumerate(index):
            out[j] = self._mean.T @ s[:, c]
        return out

    # ---------------------------------------------------------------- public API
    def apply(self, U: np.ndarray) -> np.ndarray:
        """Warped displacements ``W(u)`` for ``U`` of shape (n, 3) or (f, n, 3).

        Per tet the target gradient ``exp([w]x)(I + S) - I`` (batched Rodrigues),
        then one Poisson solve with ``3 f`` right-hand sides and the gauge
        (SYSTEM.md §6; Huang et al. 2011).
        """
        if self.compiled:
            Uf, batched = self._frames_of(U, "U")
            rhs = np.zeros_like(Uf)
            warp_kernels.target_rhs(
                Uf, self._tets, self._grads, self.volumes, rhs, warp_kernels.chunks(len(Uf))
            )
            out = self._poisson_frames(rhs, [Uf])
            return out if batched else out[0]
        X, batched = self._as_columns(U, "U")
        rhs = self._per_tet(_target_block, [(self._G, X)], self._GtV)
        return self._from_columns(self._poisson(rhs, X), batched)

    __call__ = apply

    def jvp(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """Directional derivative ``DW(u)[du]`` (analytic), frame by frame for batches.

        ``dF_t = [J(w) dw]x F_t + exp([w]x) dS`` with ``J`` the left Jacobian of the
        rotation map, then the same Poisson solve and gauge.
        """
        X, batched = self._as_columns(U, "U")
        dX, dbatched = self._as_columns(dU, "dU")
        if dX.shape != X.shape or dbatched != batched:
            raise WigglyInputError(
                f"dU should have the shape of U {np.shape(U)}; shape is {np.shape(dU)}"
            )
        if self.compiled:
            Uf, _ = self._frames_of(U, "U")
            dUf, _ = self._frames_of(dU, "dU")
            rhs = np.zeros_like(Uf)
            warp_kernels.jvp_rhs(
                Uf, dUf, self._tets, self._grads, self.volumes, rhs, warp_kernels.chunks(len(Uf))
            )
            out = self._poisson_frames(rhs, [dUf])
            return out if batched else out[0]
        rhs = self._per_tet(_jvp_fused, [(self._G, X), (self._G, dX)], self._GtV)
        return self._from_columns(self._poisson(rhs, dX), batched)

    def apply_and_jvp(
        self, U: np.ndarray, index: list[int] | np.ndarray, dU: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``W(U)`` for frames U (f, n, 3) and ``DW(U[index])[dU]`` for dU (k, n, 3), with one
        Poisson solve for both (velocity keyframes evaluate them together)."""
        Uf, _ = self._frames_of(U, "U")
        index = np.asarray(index, dtype=np.int64)
        if not self.compiled or index.size == 0:
            return self.apply(Uf), self.jvp(Uf[index], dU)
        dUf, _ = self._frames_of(dU, "dU")
        f, k = len(Uf), len(dUf)
        if dUf.shape != (index.size, *Uf.shape[1:]):
            raise WigglyInputError(
                f"dU should have shape ({index.size}, {self.n_vertices}, 3); shape is {dUf.shape}"
            )
        rhs = np.zeros((f + k, *Uf.shape[1:]))
        warp_kernels.target_rhs(
            Uf, self._tets, self._grads, self.volumes, rhs[:f], warp_kernels.chunks(f)
        )
        warp_kernels.jvp_rhs(
            np.ascontiguousarray(Uf[index]),
            dUf,
            self._tets,
            self._grads,
            self.volumes,
            rhs[f:],
            warp_kernels.chunks(k),
        )
        out = self._poisson_frames(rhs, [Uf, dUf])
        return out[:f], out[f:]

    def vjp(self, U: np.ndarray, Y: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
        """Adjoint derivative ``DW(u)^T y``: ``<vjp(u, y), du> = <y, jvp(u, du)>``.

        With ``index`` (batches only), frame s uses the cotangent ``Y[index[s]]``: the
        Poisson solve runs once per distinct cotangent.
        """
        Uf, batched = self._frames_of(U, "U")
        Yf, ybatched = self._frames_of(Y, "Y")
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
        if self.compiled:
            Zc, s = self._poisson_adjoint_frames(Yf)
            out = np.zeros_like(Uf) if s is None else self._means_adjoint(s, index)
            warp_kernels.vjp_rhs(
                Uf,
                Zc,
                index,
                self._tets,
                self._grads,
                self.volumes,
                out,
                warp_kernels.chunks(len(Uf)),
            )
            return out if batched else out[0]
        X, _ = self._as_columns(Uf, "U")
        Yc, _ = self._as_columns(Yf[index], "Y")
        Z, Y_in = self._poisson_adjoint(Yc)
        out = self._per_tet(_vjp_fused, [(self._G, X), (self._VG, Z)], self._Gt)
        return self._from_columns(out + Y_in, batched)

    def jacobian(self, u: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """``DW(u) @ basis`` for ``r`` displacement fields, with one multi-RHS solve.

        Parameters
        ----------
        u : (n, 3) array
            Linearization point.
        basis : (n, 3, r) or (3 n, r) array
            Columns are displacement fields (``3 n`` rows ordered vertex-major,
            ``3 * vertex + component``), e.g. the ``r`` eigenmodes for Gauss-Newton.

        Returns
        -------
        array of the shape of ``basis``.
        """
        n = self.n_vertices
        X, batched = self._as_columns(u, "u")
        if batched:
            raise WigglyInputError(f"u should have shape ({n}, 3); shape is {np.shape(u)}")
        dX = self._basis_fields(basis)
        shape = np.shape(basis)
        if self.compiled:
            return self.jacobians(X[:, :, 0][None], dX)[0].reshape(shape)
        r = dX.shape[2]
        M = self._tangent_matrices(X)
        m = self.n_tets
        GB = self._basis_gradients(dX, dX)
        dH = np.matmul(M, GB)  # (m, 9, r)
        rhs = (self._GtV @ dH.reshape(3 * m, 3 * r)).reshape(n, 3, r)
        return self._poisson(rhs, dX).reshape(shape)

    def _basis_frames(self, B: np.ndarray, dX: np.ndarray) -> np.ndarray:
        """The r basis fields as a contiguous (r, n, 3) array, cached for the last basis."""
        key = (B.ctypes.data, B.shape, B.strides)
        if self._frames_key != key:
            self._frames = np.ascontiguousarray(dX.transpose(2, 0, 1))
            self._frames_key = key
        return self._frames

    def _basis_gradients(self, B: np.ndarray, dX: np.ndarray) -> np.ndarray:
        """Per-tet gradients of the r basis fields, (m, 9, r), cached for the last basis
        (the modal basis is fixed per body; treat it as immutable)."""
        key = (B.ctypes.data, B.shape, B.strides)
        if self._gb_key != key:
            n, r = self.n_vertices, dX.shape[2]
            self._gb = (self._G @ np.ascontiguousarray(dX).reshape(n, 3 * r)).reshape(
                self.n_tets, 9, r
            )
            self._gb_key = key
        return self._gb

    def _tangent_matrices(self, X: np.ndarray) -> np.ndarray:
        """Per-tet 9x9 matrices of ``dA -> dH`` at ``X`` (n, 3, 1), acting on (3 j, 3 i) vectors.

        Built by applying the analytic tangent map to the 9 unit gradients, so that a
        Jacobian against r fields costs one batched (m, 9, 9) @ (m, 9, r) product.
        """
        e = np.arange(9)
        units = np.zeros((3, 3, 9, 1))
        units[e % 3, e // 3, e, 0] = 1.0  # unit e = 3 j + i is E_ij
        res = np.empty((3, 3, 9, self.n_tets))
        _jvp_block(res, self._linearize(X), units)
        return np.ascontiguousarray(res.transpose(3, 1, 0, 2)).reshape(self.n_tets, 9, 9)

    def jacobians(self, U: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """``DW(u_s) @ basis`` at f points ``U`` (f, n, 3): shape (f, n, 3, r), one solve.

        ``basis`` is (n, 3, r) or (3 n, r), as in :meth:`jacobian`.
        """
        U = self._points(U)
        dX = self._basis_fields(basis)
        if not self.compiled:
            return np.stack([self.jacobian(u, dX) for u in U])
        f, r = len(U), dX.shape[2]
        out = np.zeros((f, r, self.n_vertices, 3))
        warp_kernels.jacobians_rhs(
            U, self._field_gradients(dX), self._tets, self._grads, self.volumes, out
        )
        return self._solve_fields(out, dX)

    def second_derivatives(self, U: np.ndarray, V: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """``D^2W(u_s)[basis_j, v_s]`` at f points: shape (f, n, 3, r); see
        :meth:`velocity_jacobian` (one point) for the method."""
        U = self._points(U)
        V = self._points(V, "V")
        if V.shape != U.shape:
            raise WigglyInputError(f"V should have the shape of U {U.shape}; shape is {V.shape}")
        dX = self._basis_fields(basis)
        if not self.compiled:
            return np.stack([self.velocity_jacobian(u, v, dX) for u, v in zip(U, V, strict=True)])
        f, r = len(U), dX.shape[2]
        out = np.zeros((f, r, self.n_vertices, 3))
        gradients = self._G @ U.transpose(1, 0, 2).reshape(self.n_vertices, -1)
        step = 6e-6 * max(1.0, float(np.abs(gradients).max(initial=0.0)))
        warp_kernels.second_derivatives_rhs(
            U, V, self._field_gradients(dX), step, self._tets, self._grads, self.volumes, out
        )
        # the gauge's mean term of DW(u)[v] is the mean of v: independent of u
        return self._solve_fields(out, None)

    def _points(self, U: np.ndarray, name: str = "U") -> np.ndarray:
        U = np.ascontiguousarray(U, dtype=np.float64)
        n = self.n_vertices
        if U.ndim != 3 or U.shape[1:] != (n, 3):
            raise WigglyInputError(f"{name} should have shape (f, {n}, 3); shape is {U.shape}")
        return U

    def _basis_fields(self, basis: np.ndarray) -> np.ndarray:
        n = self.n_vertices
        B = np.asarray(basis, dtype=np.float64)
        if B.ndim == 3 and B.shape[:2] == (n, 3):
            return B
        if B.ndim == 2 and B.shape[0] == 3 * n:
            return B.reshape(n, 3, B.shape[1])
        raise WigglyInputError(
            f"basis should have shape ({n}, 3, r) or ({3 * n}, r); shape is {B.shape}"
        )

    def _field_gradients(self, dX: np.ndarray) -> np.ndarray:
        """Per-tet gradients (r, m, 9) of the basis fields, cached for the last basis (the
        modal basis is fixed per body; treat it as immutable)."""
        frames = self._basis_frames(dX, dX)
        if self._fg_key != self._frames_key:
            self._fg = warp_kernels.field_gradients(frames, self._tets, self._grads)
            self._fg_key = self._frames_key
        return self._fg

    def _solve_fields(self, rhs: np.ndarray, fields: np.ndarray | None) -> np.ndarray:
        """Poisson fit and gauge of (f, r, n, 3) right-hand sides: result (f, n, 3, r).

        The gauge takes the means of the r ``fields`` (n, 3, r) at every point (the
        Jacobians' directions); None: zero means."""
        f, r, n, _ = rhs.shape
        X = self._solve_free(rhs.transpose(2, 3, 0, 1).reshape(n, 3 * f * r))
        if self._has_floating:
            means = np.zeros((self._mean.shape[0], 3, 1, r))
            if fields is not None:
                means[:, :, 0] = (self._mean @ fields.reshape(n, 3 * r)).reshape(-1, 3, r)
            self._gauge(X, np.broadcast_to(means, (len(means), 3, f, r)).reshape(-1, 3 * f * r))
        return np.ascontiguousarray(X.reshape(n, 3, f, r).transpose(2, 0, 1, 3))

    def velocity_jacobian(self, u: np.ndarray, v: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """``d/du (DW(u)[v]) @ basis``: the second derivative ``D^2W(u)[basis_j, v]``.

        Needed for velocity keyframes on the warped motion, ``B DW(u) u'`` (SYSTEM.md §6).
        The Poisson fit and the gauge are linear, so only the per-tet map is differentiated
        twice: its 9x9 derivative in the local gradient ``A`` is taken by central differences
        of the analytic tangent map (step ~ eps^(1/3), error ~ 1e-10 relative), then applied
        to the r fields with one multi-RHS solve.  Shapes as in :meth:`jacobian`.
        """
        n, m = self.n_vertices, self.n_tets
        X, batched = self._as_columns(u, "u")
        Vc, vbatched = self._as_columns(v, "v")
        if batched or vbatched:
            raise WigglyInputError(f"u and v should have shape ({n}, 3)")
        B = np.asarray(basis, dtype=np.float64)
        r = B.shape[-1]
        if B.size != 3 * n * r:
            raise WigglyInputError(
                f"basis should have shape ({n}, 3, r) or ({3 * n}, r); shape is {B.shape}"
            )
        dX = B.reshape(n, 3, r)
        A = (self._G @ X.reshape(n, 3)).reshape(m, 3, 3).transpose(2, 1, 0)[:, :, None, :]
        gv = (self._G @ Vc.reshape(n, 3)).reshape(m, 3, 3).transpose(2, 1, 0)[:, :, None, :]
        A = np.ascontiguousarray(A)
        gv = np.ascontiguousarray(gv)
        h = 6e-6 * max(1.0, float(np.abs(A).max()))
        T2 = np.empty((m, 9, 9))
        plus = np.empty_like(A)
        minus = np.empty_like(A)
        for e in range(9):  # unit e = 3 j + i perturbs A_ij
            j, i = divmod(e, 3)
            Ap = A.copy()
            Ap[i, j] += h
            _jvp_block(plus, _linearization(Ap), gv)
            Ap[i, j] -= 2 * h
            _jvp_block(minus, _linearization(Ap), gv)
            d = (plus - minus) / (2 * h)
            T2[:, :, e] = d[:, :, 0, :].transpose(2, 1, 0).reshape(m, 9)
        dH = np.matmul(T2, self._basis_gradients(B, dX))
        rhs = (self._GtV @ dH.reshape(3 * m, 3 * r)).reshape(n, 3, r)
        # the gauge's mean term of DW(u)[v] is the mean of v: independent of u
        return self._poisson(rhs, np.zeros_like(rhs)).reshape(B.shape)


# --------------------------------------------------------------------------- #
# The warp of a coarser mesh of the same body
# --------------------------------------------------------------------------- #
class CoarseWarp:
    """The warp of a coarser tet mesh of the same solid, seen from the fine mesh.

    The displacement is projected onto the coarse mesh, warped there, and interpolated back:

        W~(u) = P W_c(R u),        DW~(u) Phi = P DW_c(R u) R Phi,

    with ``P`` (n, n_c) the barycentric interpolation at the fine vertices (exact for affine
    fields, so rigid motions pass through) and ``R = (P^T M P)^-1 P^T M`` the mass-weighted
    least-squares projection (``M`` the fine lumped masses), the best coarse approximation
    of a fine field.  ``W~`` approximates ``W`` (SYSTEM.md §6) to the coarse mesh's
    resolution, at a fraction of the cost.  The warped solve uses it twice (see
    :func:`wiggly.solve.solve`): its Jacobians (fields on the coarse mesh, lifted by ``P``)
    stand in for ``DW(u_k) Phi`` in the Gauss-Newton matrix, which changes the convergence
    rate of the iteration, never its stationary point; and the problem with ``W~`` in place
    of ``W`` is solved first, as a start close to the solution.

    :meth:`exact` wraps the fine warp itself (``R = P = I``): for small bodies.

    Parameters
    ----------
    warp_c : Warp
        The warp of the coarse mesh (built with masses ``P^T m``, so that interpolated fields
        keep the fine mass-weighted mean).
    lift : (n, n_c) sparse
        ``P``: coarse vertex values to fine vertices.
    masses : (n,) array
        Fine lumped vertex masses ``M``.
    basis : (3 n, r) array
        The modes ``Phi`` (vertex-major rows).
    """

    def __init__(
        self, warp_c: Warp, lift: sp.csr_matrix, masses: np.ndarray, basis: np.ndarray
    ) -> None:
        n, n_c = lift.shape
        r = basis.shape[1]
        self.warp_c = warp_c
        self.lift = sp.csr_matrix(lift)
        self.exact = False
        self.n_vertices, self.n_coarse, self.r = n, n_c, r
        self._masses = np.asarray(masses, dtype=np.float64)
        self._PtM = sp.csr_matrix(self.lift.T @ sp.diags(self._masses))
        self._project = factorize_spd(sp.csc_matrix(self._PtM @ self.lift), backend="splu")
        self.basis_c = self.restrict(basis.reshape(n, 3, r).transpose(2, 0, 1)).transpose(1, 2, 0)

    @classmethod
    def exact(cls, warp: Warp, basis: np.ndarray) -> CoarseWarp:
        """The fine warp itself (``R = P = I``)."""
        self = cls.__new__(cls)
        n, r = warp.n_vertices, basis.shape[1]
        self.warp_c, self.exact, self.r = warp, True, r
        self.n_vertices = self.n_coarse = n
        self.lift = sp.identity(n, format="csr")
        self.basis_c = np.ascontiguousarray(basis.reshape(n, 3, r))
        return self

    # ----------------------------------------------------------------- transfer
    @staticmethod
    def _apply_columns(A, U: np.ndarray, rows: int) -> np.ndarray:
        """``A`` applied to each of f fields (f, k, 3): result (f, rows, 3)."""
        f, k = U.shape[:2]
        out = A(np.ascontiguousarray(U.transpose(1, 0, 2)).reshape(k, 3 * f))
        return np.ascontiguousarray(out.reshape(rows, f, 3).transpose(1, 0, 2))

    def restrict(self, U: np.ndarray) -> np.ndarray:
        """``R U`` for fine fields (f, n, 3): coarse fields (f, n_c, 3)."""
        U = np.asarray(U, dtype=np.float64)
        if self.exact:
            return np.ascontiguousarray(U)
        return self._apply_columns(lambda X: self._project(self._PtM @ X), U, self.n_coarse)

    def _restrict_adjoint(self, Z: np.ndarray) -> np.ndarray:
        """``R^T Z = M P (P^T M P)^-1 Z`` for coarse fields (f, n_c, 3)."""
        return self._apply_columns(
            lambda X: self._masses[:, None] * (self.lift @ self._project(X)), Z, self.n_vertices
        )

    def _lift(self, X: np.ndarray) -> np.ndarray:
        return self._apply_columns(lambda Y: self.lift @ Y, X, self.n_vertices)

    def _lift_adjoint(self, Y: np.ndarray) -> np.ndarray:
        return self._apply_columns(lambda X: self.lift.T @ X, Y, self.n_coarse)

    # --------------------------------------------------------------- the map W~
    def apply(self, U: np.ndarray) -> np.ndarray:
        """``W~(u) = P W_c(R u)`` for U (f, n, 3)."""
        if self.exact:
            return self.warp_c.apply(U)
        return self._lift(self.warp_c.apply(self.restrict(U)))

    def jvp(self, U: np.ndarray, dU: np.ndarray) -> np.ndarray:
        """``DW~(u)[du] = P DW_c(R u)[R du]`` for U, dU (f, n, 3)."""
        if self.exact:
            return self.warp_c.jvp(U, dU)
        return self._lift(self.warp_c.jvp(self.restrict(U), self.restrict(dU)))

    def vjp(self, U: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """``DW~(u)^T y = R^T DW_c(R u)^T P^T y`` for U, Y (f, n, 3)."""
        if self.exact:
            return self.warp_c.vjp(U, Y)
        return self._restrict_adjoint(self.warp_c.vjp(self.restrict(U), self._lift_adjoint(Y)))

    def jacobians(self, q: np.ndarray) -> np.ndarray:
        """``DW_c(R Phi q_s) R Phi`` at f modal states q (f, r): shape (f, n_c, 3, r); the
        Jacobian of ``W~`` at ``u = Phi q`` is ``P`` (:attr:`lift`) applied to it."""
        U = np.asarray(q, dtype=np.float64) @ self.basis_c.reshape(-1, self.r).T
        return self.warp_c.jacobians(U.reshape(len(U), -1, 3), self.basis_c)

    def second_derivatives(self, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``D^2 W_c(R Phi q_s)[R Phi, R Phi v_s]`` (velocity keyframes): (f, n_c, 3, r)."""
        B = self.basis_c.reshape(-1, self.r).T
        U = (np.asarray(q, dtype=np.float64) @ B).reshape(len(q), -1, 3)
        V = (np.asarray(v, dtype=np.float64) @ B).reshape(len(v), -1, 3)
        return self.warp_c.second_derivatives(U, V, self.basis_c)
