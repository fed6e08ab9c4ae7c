"""Linear finite elements on P1 tetrahedra: mass, stiffness, damping, gravity.

The matrices of the linear dynamics, Schulz et al. 2014, eq. (1).

The displacement ``u`` from the rest shape is piecewise linear, ``u(x) = sum_a u_a phi_a(x)``,
with dofs interleaved (dof ``3 a + c`` is component ``c`` of vertex ``a``).  The dynamics are (1)

    M u'' + D u' + K u + g = 0,

with M the mass matrix, K the stiffness of isotropic linear elasticity, D = alpha M + beta K
(Rayleigh damping) and g the constant term.  Gravity is the external force ``f = M G`` with
``G`` the gravity acceleration tiled over vertices; moved to the left-hand side it gives
``g = -M G``.  The default gravity is ``(0, -9.81, 0)`` (y up).

All matrices are scipy.sparse CSR, ``3n x 3n``, in SI units (Pa, kg/m^3, m, s).  Assembly is
vectorized over elements (element blocks are summed by a COO -> CSR conversion).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from wiggly.checks import mesh_arrays
from wiggly.errors import WigglyInputError, warn

__all__ = [
    "Material",
    "gravity_term",
    "lame_parameters",
    "mass_matrix",
    "rayleigh_damping",
    "stiffness_matrix",
    "tet_gradients",
]

DEFAULT_GRAVITY = (0.0, -9.81, 0.0)


def _as_real(name: str, value: object, allowed: str) -> float:
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise WigglyInputError(f"{name} should be {allowed}; got {value!r}") from None


#: Material ranges wiggly accepts: far beyond real solids (gels of 1e2 Pa to diamond's
#: 1.2e12 Pa; aerogels of 1 kg/m^3 to osmium's 2.3e4), short of where the modes' arithmetic
#: overflows (a Young's modulus of 1e-300 Pa never finished; 1e300 overflowed K).
YOUNG_RANGE = (1e-3, 1e13)
DENSITY_RANGE = (1e-3, 1e6)


#: Below these a material is softer than any gel (about 1e2 Pa) or lighter than any foam
#: (about 10 kg/m^3): a value in MPa or g/cm^3 read as SI, said once.
PLAUSIBLE_YOUNG = 10.0
PLAUSIBLE_DENSITY = 5.0


def _warn_units(young: float, density: float) -> None:
    """Warn of a Young's modulus or density that reads as another unit than wiggly's SI."""
    if young < PLAUSIBLE_YOUNG:
        warn(
            f"young = {young:g} Pa is softer than any solid (gels are about 1e2 to 1e4 Pa, "
            f"rubber about 1e6): wiggly takes pascals; {young:g} MPa would be "
            f"{young * 1e6:g}")
    if density < PLAUSIBLE_DENSITY:
        warn(
            f"density = {density:g} kg/m^3 is lighter than any foam (water is 1000): wiggly "
            f"takes kg/m^3; {density:g} g/cm^3 would be {density * 1e3:g}")


def _check_young(young: float) -> float:
    allowed = f"finite and in [{YOUNG_RANGE[0]:g}, {YOUNG_RANGE[1]:g}] Pa"
    value = _as_real("young (Young's modulus)", young, allowed)
    if not (math.isfinite(value) and YOUNG_RANGE[0] <= value <= YOUNG_RANGE[1]):
        raise WigglyInputError(f"young (Young's modulus) should be {allowed}; got {young!r}")
    return value


def _check_poisson(poisson: float) -> float:
    allowed = "in [0, 0.5)"
    value = _as_real("poisson (Poisson's ratio)", poisson, allowed)
    if not (math.isfinite(value) and 0.0 <= value < 0.5):
        raise WigglyInputError(f"poisson (Poisson's ratio) should be {allowed}; got {poisson!r}")
    return value


def _check_density(density: float) -> float:
    allowed = f"finite and in [{DENSITY_RANGE[0]:g}, {DENSITY_RANGE[1]:g}] kg/m^3"
    value = _as_real("density", density, allowed)
    if not (math.isfinite(value) and DENSITY_RANGE[0] <= value <= DENSITY_RANGE[1]):
        raise WigglyInputError(f"density should be {allowed}; got {density!r}")
    return value


@dataclass(frozen=True)
class Material:
    """Isotropic linear elastic material (Schulz et al. 2014, eq. (1)).

    Parameters
    ----------
    young : float
        Young's modulus E in Pa, > 0.  Default 2e5 (soft rubber / jelly).
    poisson : float
        Poisson's ratio nu in [0, 0.5).  0.5 (incompressible) is excluded: lambda is infinite.
    density : float
        Mass density rho in kg/m^3, > 0.
    """

    young: float = 2e5
    poisson: float = 0.45
    density: float = 1000.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "young", _check_young(self.young))
        object.__setattr__(self, "poisson", _check_poisson(self.poisson))
        object.__setattr__(self, "density", _check_density(self.density))
        _warn_units(self.young, self.density)

    @property
    def lame(self) -> tuple[float, float]:
        """Lamé parameters ``(lambda, mu)`` in Pa, see :func:`lame_parameters`."""
        return lame_parameters(self.young, self.poisson)


def lame_parameters(young: float, poisson: float) -> tuple[float, float]:
    """Lamé parameters from Young's modulus and Poisson's ratio.

    ``lambda = E nu / ((1 + nu)(1 - 2 nu))``, ``mu = E / (2 (1 + nu))``.
    """
    E = _check_young(young)
    nu = _check_poisson(poisson)
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), E / (2.0 * (1.0 + nu))


def _check_mesh(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return mesh_arrays(V, T, "tet mesh")


def tet_gradients(V: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the P1 shape functions and volumes of all tets.

    With ``Dm = [x1 - x0, x2 - x0, x3 - x0]`` (columns), the barycentric coordinates are
    ``(l1, l2, l3) = Dm^{-1} (x - x0)`` and ``l0 = 1 - l1 - l2 - l3``, so ``grad l_a`` for
    a = 1..3 are the rows of ``Dm^{-1}`` and ``grad l0 = -(grad l1 + grad l2 + grad l3)``.

    Parameters
    ----------
    V : (n, 3) float
        Rest positions.
    T : (m, 4) int
        Tets, positively oriented (``det Dm > 0``).

    Returns
    -------
    grads : (m, 4, 3) float64
        ``grads[e, a]`` is the (constant) gradient of the shape function of vertex ``T[e, a]``.
    volumes : (m,) float64
        ``det(Dm) / 6 > 0``.

    Raises
    ------
    WigglyInputError
        If a tet has non-positive volume (inverted or degenerate).
    """
    V, T = _check_mesh(V, T)
    X = V[T]  # (m, 4, 3)
    Dm = np.swapaxes(X[:, 1:, :] - X[:, :1, :], 1, 2)  # (m, 3, 3), columns x_a - x0
    det = np.linalg.det(Dm)
    # relative test: degenerate tets have det ~ 0 compared to their edge lengths cubed
    edge3 = np.max(np.abs(Dm), axis=(1, 2)) ** 3
    bad = ~(det > 1e-14 * edge3)
    if np.any(bad):
        first = int(np.flatnonzero(bad)[0])
        raise WigglyInputError(
            f"{int(bad.sum())} of {T.shape[0]} tets have non-positive volume (inverted or "
            f"degenerate); first is tet {first} (vertices {T[first].tolist()}, "
            f"volume {det[first] / 6:.3g}); tets should be positively oriented"
        )
    inv = np.linalg.inv(Dm)  # rows are grad l1, grad l2, grad l3
    grads = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)
    return grads, det / 6.0


def _assemble_blocks(T: np.ndarray, n: int, blocks: np.ndarray) -> sp.csr_matrix:
    """Sum element blocks into a (3n, 3n) CSR matrix.

    ``blocks[3 c + d, e, a, b]`` is added to entry ``(3 T[e, a] + c, 3 T[e, b] + d)``.
    Duplicates are summed at the vertex level (16 keys per tet instead of 144), then the
    3x3 blocks become a BSR matrix, converted to CSR.
    """
    m = T.shape[0]
    key = (T[:, :, None] * n + T[:, None, :]).ravel()
    keys, inverse = np.unique(key, return_inverse=True)
    data = np.empty((keys.size, 9))
    for k in range(9):
        data[:, k] = np.bincount(inverse, weights=blocks[k].reshape(m * 16), minlength=keys.size)
    rows, cols = np.divmod(keys, n)
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    A = sp.bsr_matrix((data.reshape(-1, 3, 3), cols, indptr), shape=(3 * n, 3 * n)).tocsr()
    A.has_sorted_indices = True
    return A


def mass_matrix(
    V: np.ndarray, T: np.ndarray, density: float, lumped: bool = False
) -> sp.csr_matrix:
    """Mass matrix M of P1 tets (Schulz et al. 2014, eq. (1)).

    Consistent: per tet and per component, ``M_ab = rho vol / 20 (1 + delta_ab)``
    (exact integral of ``rho phi_a phi_b``).  Lumped: the diagonal of its row sums,
    ``rho vol / 4`` per tet vertex; both have the same row sums and total mass.

    Parameters
    ----------
    V, T : rest positions (n, 3) and tets (m, 4), see :func:`tet_gradients`.
    density : float
        rho in kg/m^3, > 0.
    lumped : bool
        Return the diagonal lumped mass instead of the consistent one.

    Returns
    -------
    M : (3n, 3n) scipy.sparse.csr_matrix, symmetric positive definite on used vertices.
    """
    rho = _check_density(density)
    V, T = _check_mesh(V, T)
    _, vol = tet_gradients(V, T)
    n = V.shape[0]
    if lumped:
        lump = np.zeros(n)
        np.add.at(lump, T.ravel(), np.repeat(rho * vol / 4.0, 4))
        return sp.diags(np.repeat(lump, 3)).tocsr()
    scalar = (np.ones((4, 4)) + np.eye(4)) / 20.0  # (1 + delta_ab) / 20
    Me = (rho * vol)[:, None, None] * scalar  # (m, 4, 4), same for every component
    blocks = np.zeros((9, *Me.shape))
    blocks[[0, 4, 8]] = Me
    return _assemble_blocks(T, n, blocks)


def stiffness_matrix(
    V: np.ndarray, T: np.ndarray, young: float | np.ndarray, poisson: float
) -> sp.csr_matrix:
    """Stiffness matrix K of isotropic linear elasticity on P1 tets (Schulz et al. 2014, eq. (1)).

    The elastic energy ``int mu eps:eps + lambda/2 tr(eps)^2 = 1/2 u^T K u`` with
    ``eps = sym(grad u)`` gives, per tet and vertex pair (a, b), the 3x3 block

        K_ab = vol (lambda g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I),

    with ``g_a`` the shape-function gradients, which equals the block of ``vol B^T C B``.

    Parameters
    ----------
    V, T : rest positions (n, 3) and tets (m, 4), see :func:`tet_gradients`.
    young : float or (m,) array
        Young's modulus E in Pa, > 0: one for the body, or one per tet (a softer tail on a
        stiffer body).
    poisson : float
        Poisson's ratio nu in [0, 0.5).

    Returns
    -------
    K : (3n, 3n) scipy.sparse.csr_matrix, symmetric positive semi-definite; its null space
        contains the rigid motions (6 for a connected body).
    """
    V, T = _check_mesh(V, T)
    if np.ndim(young) == 0:
        lam, mu = lame_parameters(float(young), poisson)
    else:
        E = np.asarray(young, dtype=np.float64)
        if E.shape != (len(T),):
            raise WigglyInputError(f"young should be a number or one per tet ({len(T)},); "
                                   f"shape is {E.shape}")
        ok = np.isfinite(E) & (E >= YOUNG_RANGE[0]) & (E <= YOUNG_RANGE[1])
        if not np.all(ok):
            raise WigglyInputError(f"young (Young's modulus) should be finite and in "
                                   f"[{YOUNG_RANGE[0]:g}, {YOUNG_RANGE[1]:g}] Pa in every "
                                   f"tet; got {E[~ok][0]!r}")
        lam1, mu1 = lame_parameters(1.0, poisson)
        lam, mu = (lam1 * E)[:, None, None], (mu1 * E)[:, None, None]
    grads, vol = tet_gradients(V, T)
    g = np.ascontiguousarray(np.moveaxis(grads * np.sqrt(vol)[:, None, None], 2, 0))  # (3,m,4)
    dots = mu * np.einsum("cea,ceb->eab", g, g)  # mu vol (g_a . g_b)
    blocks = np.empty((9, *dots.shape))
    for c in range(3):
        for d in range(3):
            # component (c, d) of lambda g_a g_b^T + mu g_b g_a^T, times vol
            blocks[3 * c + d] = lam * g[c][:, :, None] * g[d][:, None, :]
            blocks[3 * c + d] += mu * g[d][:, :, None] * g[c][:, None, :]
        blocks[4 * c] += dots
    return _assemble_blocks(T, V.shape[0], blocks)


def geometric_stiffness(V: np.ndarray, T: np.ndarray, stress: np.ndarray,
                        gradients: tuple[np.ndarray, np.ndarray] | None = None,
                        ) -> sp.csr_matrix:
    """Geometric (stress) stiffness of P1 tets under a per-tet Cauchy stress ``stress``
    (m, 3, 3): the second variation of ``int sigma : E(u)`` with the Green strain's
    quadratic part ``1/2 grad u^T grad u``, per tet and vertex pair the 3x3 block

        K_sigma_ab = vol (g_a^T sigma g_b) I

    (Bathe, Finite Element Procedures, sec. 6.3): tension stiffens (a hanging rope swings
    back like a pendulum), compression softens (a column's self-weight buckling).
    ``gradients``: :func:`tet_gradients` of (V, T), where the caller has them."""
    V, T = _check_mesh(V, T)
    grads, vol = tet_gradients(V, T) if gradients is None else gradients
    S = np.asarray(stress, dtype=np.float64)
    if S.shape != (len(T), 3, 3):
        raise WigglyInputError(f"stress should have shape ({len(T)}, 3, 3); shape is {S.shape}")
    scalar = vol[:, None, None] * np.einsum("mai,mij,mbj->mab", grads, S, grads)
    blocks = np.zeros((9, *scalar.shape))
    blocks[[0, 4, 8]] = scalar
    return _assemble_blocks(T, V.shape[0], blocks)


def linear_stress(V: np.ndarray, T: np.ndarray, u: np.ndarray, young: float | np.ndarray,
                  poisson: float, gradients: tuple[np.ndarray, np.ndarray] | None = None,
                  ) -> np.ndarray:
    """Per-tet Cauchy stress ``lambda tr(eps) I + 2 mu eps`` of the displacement ``u`` (n, 3)
    or (3n,), ``eps = sym(grad u)`` (Schulz et al. 2014, eq. (1)): (m, 3, 3).
    ``gradients``: :func:`tet_gradients` of (V, T), where the caller has them."""
    V, T = _check_mesh(V, T)
    grads, _ = tet_gradients(V, T) if gradients is None else gradients
    U = np.asarray(u, dtype=np.float64).reshape(-1, 3)
    A = np.einsum("mki,mkj->mij", U[T], grads)  # A_ij = d u_i / d X_j
    eps = 0.5 * (A + A.transpose(0, 2, 1))
    lam, mu = lame_parameters(1.0, poisson)
    E = np.broadcast_to(np.asarray(young, dtype=np.float64), (len(T),))[:, None, None]
    trace = np.trace(eps, axis1=1, axis2=2)[:, None, None]
    return E * (lam * trace * np.eye(3) + 2.0 * mu * eps)


def gravity_term(
    M: sp.spmatrix, gravity: tuple[float, float, float] = DEFAULT_GRAVITY
) -> np.ndarray:
    """Constant term g of dynamics (1) for uniform gravity (Schulz et al. 2014, eq. (1)).

    Gravity acts as the external force ``f = M G`` with ``G = tile(gravity, n)``; in (1),
    ``M u'' + D u' + K u + g = 0``, it sits on the left-hand side, so ``g = -M G``.

    Parameters
    ----------
    M : (3n, 3n) sparse
        Mass matrix.
    gravity : (3,) float
        Gravity acceleration in m/s^2; default ``(0, -9.81, 0)``, i.e. y is up.

    Returns
    -------
    g : (3n,) float64
    """
    G = np.asarray(gravity, dtype=np.float64)
    if G.shape != (3,) or not np.all(np.isfinite(G)):
        raise WigglyInputError(f"gravity should be 3 finite numbers (m/s^2); got {gravity!r}")
    if M.ndim != 2 or M.shape[0] != M.shape[1] or M.shape[0] % 3:
        raise WigglyInputError(f"M should be a square (3n, 3n) matrix; shape is {M.shape}")
    return -(M @ np.tile(G, M.shape[0] // 3))


def rayleigh_damping(M: sp.spmatrix, K: sp.spmatrix, alpha: float, beta: float) -> sp.csr_matrix:
    """Rayleigh damping ``D = alpha M + beta K`` (Schulz et al. 2014, eq. (1)).

    Parameters
    ----------
    M, K : (3n, 3n) sparse
        Mass and stiffness matrices.
    alpha : float
        Mass-proportional damping in 1/s, >= 0.
    beta : float
        Stiffness-proportional damping in s, >= 0.
    """
    for name, value in (("alpha", alpha), ("beta", beta)):
        number = _as_real(f"{name} (Rayleigh damping)", value, "finite and >= 0")
        if not (math.isfinite(number) and number >= 0.0):
            raise WigglyInputError(
                f"{name} (Rayleigh damping) should be finite and >= 0; got {value!r}"
            )
    if M.shape != K.shape:
        raise WigglyInputError(f"M and K should have the same shape; got {M.shape} and {K.shape}")
    return (float(alpha) * sp.csr_matrix(M) + float(beta) * sp.csr_matrix(K)).tocsr()
