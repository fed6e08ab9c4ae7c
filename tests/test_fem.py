"""Linear FEM on P1 tets (Schulz et al. 2014, eq. (1)):
hand-derived single-element values and identities."""

from __future__ import annotations

import itertools
import math
import re
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from wiggly.errors import WigglyInputError
from wiggly.fem import (
    Material,
    gravity_term,
    lame_parameters,
    mass_matrix,
    rayleigh_damping,
    stiffness_matrix,
    tet_gradients,
)
from wiggly.primitives import box_mesh

REF_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
REF_T = np.array([[0, 1, 2, 3]])


def jittered_box(shape=(3, 3, 2), size=(1.0, 0.8, 0.5), seed=0):
    """A box mesh with every vertex moved randomly by up to 5% of a cell (all tets stay valid)."""
    V, T = box_mesh(shape, size)
    h = np.array(size) / np.array(shape)
    V = V + np.random.default_rng(seed).uniform(-0.05, 0.05, V.shape) * h
    return V, T


def tet_volumes(V, T):
    """Volumes by the scalar triple product (independent of tet_gradients)."""
    a, b, c, d = (V[T[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


# --- Material -------------------------------------------------------------------------------


def test_material_defaults_and_lame():
    mat = Material()
    assert (mat.young, mat.poisson, mat.density) == (2e5, 0.45, 1000.0)
    # scene files take their defaults from the library: one definition
    from wiggly.scene import MaterialSpec

    spec = MaterialSpec()
    assert (spec.young, spec.poisson, spec.density) == (mat.young, mat.poisson, mat.density)
    lam, mu = Material(young=2e3, poisson=0.25).lame
    # nu = 1/4: lambda = mu = E / 2.5
    assert lam == pytest.approx(800.0) and mu == pytest.approx(800.0)
    with pytest.raises(AttributeError):
        mat.young = 1.0  # frozen


@pytest.mark.parametrize(("kw", "said"), [
    ({"young": 0.05}, "young = 0.05 Pa is softer than any solid"),  # 0.05 MPa meant
    ({"density": 1.1}, "density = 1.1 kg/m^3 is lighter than any foam"),  # g/cm^3 meant
])
def test_a_material_in_other_units_is_warned_about(kw, said):
    """A modulus in MPa or a density in g/cm^3 read as SI: accepted (within the ranges the
    arithmetic takes), and said, with the value in the other unit."""
    with pytest.warns(UserWarning, match=re.escape(said)):
        Material(**kw)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Material(young=1e2, density=10.0)  # a soft gel, a light foam: no warning


@pytest.mark.parametrize(
    ("kwargs", "field", "shown"),
    [
        ({"young": -1.0}, "young", "-1.0"),
        ({"young": 0.0}, "young", "0.0"),
        ({"young": math.inf}, "young", "inf"),
        ({"poisson": 0.5}, "poisson", "0.5"),
        ({"poisson": -0.1}, "poisson", "-0.1"),
        ({"poisson": math.nan}, "poisson", "nan"),
        ({"density": 0.0}, "density", "0.0"),
        ({"density": -5.0}, "density", "-5.0"),
        ({"density": "heavy"}, "density", "'heavy'"),
        ({"young": None}, "young", "None"),
    ],
)
def test_material_rejects_bad_values(kwargs, field, shown):
    with pytest.raises(WigglyInputError, match=field) as info:
        Material(**kwargs)
    assert shown in str(info.value)
    assert isinstance(info.value, ValueError)


def test_matrix_builders_validate_material():
    with pytest.raises(WigglyInputError, match="poisson"):
        stiffness_matrix(REF_V, REF_T, 1e5, 0.5)
    with pytest.raises(WigglyInputError, match="young"):
        stiffness_matrix(REF_V, REF_T, -1.0, 0.3)
    with pytest.raises(WigglyInputError, match="density"):
        mass_matrix(REF_V, REF_T, 0.0)
    with pytest.raises(WigglyInputError, match="alpha"):
        rayleigh_damping(sp.eye(3), sp.eye(3), -0.1, 0.0)


# --- geometry -------------------------------------------------------------------------------


def test_inverted_tet_is_reported_with_count_and_index():
    V, T = box_mesh((2, 2, 2))
    T = T.copy()
    T[[5, 9]] = T[[5, 9]][:, [1, 0, 2, 3]]  # flip two tets
    with pytest.raises(WigglyInputError, match=r"2 of 48 tets.*first is tet 5"):
        tet_gradients(V, T)
    with pytest.raises(WigglyInputError, match="non-positive volume"):
        stiffness_matrix(V, T, 1e5, 0.3)


def test_degenerate_tet_is_rejected():
    V = REF_V.copy()
    V[3] = [0.3, 0.3, 0.0]  # coplanar with the others
    with pytest.raises(WigglyInputError, match="tet 0"):
        tet_gradients(V, REF_T)


def test_bad_mesh_arrays():
    with pytest.raises(WigglyInputError, match=r"shape \(n, 3\)"):
        tet_gradients(REF_V[:, :2], REF_T)
    with pytest.raises(WigglyInputError, match=r"indices outside 0\.\.3"):
        tet_gradients(REF_V, np.array([[0, 1, 2, 4]]))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=12, max_size=12))
def test_gradients_reproduce_linear_functions(coords):
    X = np.array(coords).reshape(4, 3)
    vol = tet_volumes(X, REF_T)[0]
    if abs(vol) < 1e-3:
        return  # nearly flat: not a meaningful element
    T = REF_T if vol > 0 else REF_T[:, [1, 0, 2, 3]]
    grads, volumes = tet_gradients(X, T)
    assert volumes[0] == pytest.approx(abs(vol), rel=1e-10)
    # partition of unity and linear precision: sum_a g_a = 0, sum_a x_a g_a^T = I
    np.testing.assert_allclose(grads[0].sum(axis=0), 0.0, atol=1e-9)
    np.testing.assert_allclose(X[T[0]].T @ grads[0], np.eye(3), atol=1e-8)


# --- mass -----------------------------------------------------------------------------------


def test_reference_tet_consistent_mass():
    rho = 2700.0
    M = mass_matrix(REF_V, REF_T, rho).toarray()
    vol = 1.0 / 6.0
    hand = np.array([[2, 1, 1, 1], [1, 2, 1, 1], [1, 1, 2, 1], [1, 1, 1, 2]], dtype=float)
    scalar = rho * vol / 20.0 * hand
    expected = np.zeros((12, 12))
    for a, b, c in itertools.product(range(4), range(4), range(3)):
        expected[3 * a + c, 3 * b + c] = scalar[a, b]
    np.testing.assert_allclose(M, expected, rtol=1e-14, atol=0)


def test_total_mass_and_lumping():
    rho = 1234.0
    V, T = box_mesh((4, 3, 2), (2.0, 0.9, 0.5))
    M = mass_matrix(V, T, rho)
    assert sp.isspmatrix_csr(M) and M.shape == (3 * len(V),) * 2
    np.testing.assert_allclose(M.sum() / 3.0, rho * 2.0 * 0.9 * 0.5, rtol=1e-12)
    np.testing.assert_allclose(abs(M - M.T).max(), 0.0, atol=1e-12 * abs(M).max())
    assert np.linalg.eigvalsh(M.toarray()).min() > 0

    Vj, Tj = jittered_box()
    Mc = mass_matrix(Vj, Tj, rho)
    Ml = mass_matrix(Vj, Tj, rho, lumped=True)
    np.testing.assert_allclose(Mc.sum() / 3.0, rho * tet_volumes(Vj, Tj).sum(), rtol=1e-12)
    np.testing.assert_allclose(Ml.diagonal(), np.asarray(Mc.sum(axis=1)).ravel(), rtol=1e-12)
    assert (Ml - sp.diags(Ml.diagonal())).count_nonzero() == 0


# --- stiffness ------------------------------------------------------------------------------

# Strain-displacement matrix of the reference tet, written by hand.  Shape functions
# phi0 = 1 - x - y - z, phi1 = x, phi2 = y, phi3 = z, so grad phi = (-1,-1,-1), (1,0,0),
# (0,1,0), (0,0,1).  Voigt order (xx, yy, zz, yz, xz, xy) with engineering shears.
# fmt: off
B_REF = np.array([
    # u0x u0y u0z  u1x u1y u1z  u2x u2y u2z  u3x u3y u3z
    [-1,  0,  0,   1,  0,  0,   0,  0,  0,   0,  0,  0],  # eps_xx = du_x/dx
    [ 0, -1,  0,   0,  0,  0,   0,  1,  0,   0,  0,  0],  # eps_yy
    [ 0,  0, -1,   0,  0,  0,   0,  0,  0,   0,  0,  1],  # eps_zz
    [ 0, -1, -1,   0,  0,  0,   0,  0,  1,   0,  1,  0],  # du_y/dz + du_z/dy
    [-1,  0, -1,   0,  0,  1,   0,  0,  0,   1,  0,  0],  # du_x/dz + du_z/dx
    [-1, -1,  0,   0,  1,  0,   1,  0,  0,   0,  0,  0],  # du_x/dy + du_y/dx
], dtype=float)
# fmt: on


def test_reference_tet_stiffness_against_hand_derived_B():
    E, nu = 3.0e5, 0.3
    lam = E * nu / ((1 + nu) * (1 - 2 * nu))
    mu = E / (2 * (1 + nu))
    C = np.zeros((6, 6))
    C[:3, :3] = lam
    C += np.diag([2 * mu] * 3 + [mu] * 3)
    expected = (1.0 / 6.0) * B_REF.T @ C @ B_REF
    K = stiffness_matrix(REF_V, REF_T, E, nu).toarray()
    np.testing.assert_allclose(K, expected, rtol=1e-13, atol=1e-13 * abs(expected).max())
    # a few entries by hand: K[u1x, u1x] = vol (lam + 2 mu), K[u1x, u2y] = vol lam,
    # K[u1x, u2x] = 0 (grad phi1 . grad phi2 = 0), K[u1y, u2x] = vol mu
    assert K[3, 3] == pytest.approx((lam + 2 * mu) / 6)
    assert K[3, 7] == pytest.approx(lam / 6)
    assert K[3, 6] == pytest.approx(0.0, abs=1e-9)
    assert K[4, 6] == pytest.approx(mu / 6)

    assert np.array_equal(K, K.T) or abs(K - K.T).max() < 1e-12 * abs(K).max()
    w = np.linalg.eigvalsh(K)
    assert w.min() > -1e-10 * w.max()
    assert int(np.sum(w < 1e-10 * w.max())) == 6  # exactly the 6 rigid motions


def linearized_rigid(V):
    """Translations and infinitesimal rotations (e_k x x) written independently of wiggly."""
    cols = []
    for k in range(3):
        t = np.zeros_like(V)
        t[:, k] = 1.0
        cols.append(t.ravel())
    for k in range(3):
        cols.append(np.cross(np.eye(3)[k], V).ravel())  # about the origin
    return np.column_stack(cols)


@pytest.mark.parametrize("seed", [0, 1])
def test_rigid_motions_in_null_space_of_K(seed):
    V, T = jittered_box(seed=seed)
    rng = np.random.default_rng(seed)
    K = stiffness_matrix(V, T, rng.uniform(1e4, 1e7), rng.uniform(0.0, 0.49))
    norm_K = abs(K).sum(axis=1).max()  # ||K||_inf >= ||K||_2 (K symmetric)
    R = linearized_rigid(V)
    residual = np.linalg.norm(K @ R, axis=0) / (norm_K * np.linalg.norm(R, axis=0))
    assert residual.max() < 1e-12
    # and a non-rigid motion (a shear) is not in the null space
    shear = np.column_stack([V[:, 1], np.zeros(len(V)), np.zeros(len(V))]).ravel()
    assert np.linalg.norm(K @ shear) / (norm_K * np.linalg.norm(shear)) > 1e-4


def test_patch_test_constant_strain():
    """Affine displacement: K u vanishes at interior vertices and 1/2 u^T K u is exact."""
    V, T = jittered_box(shape=(4, 4, 3), seed=3)
    E, nu = 2.0e5, 0.35
    lam, mu = lame_parameters(E, nu)
    F = np.array([[0.01, 0.002, -0.003], [0.004, -0.02, 0.001], [0.0, 0.005, 0.015]])
    u = (V @ F.T + np.array([0.1, -0.2, 0.3])).ravel()
    K = stiffness_matrix(V, T, E, nu)
    f = (K @ u).reshape(-1, 3)
    Vb, _ = box_mesh((4, 4, 3), (1.0, 0.8, 0.5))
    interior = np.all((Vb > 1e-9) & (Vb < np.array([1.0, 0.8, 0.5]) - 1e-9), axis=1)
    assert interior.sum() == 3 * 3 * 2
    assert np.abs(f[interior]).max() < 1e-10 * np.abs(f).max()
    eps = (F + F.T) / 2
    energy_density = mu * np.sum(eps * eps) + lam / 2 * np.trace(eps) ** 2
    volume = tet_volumes(V, T).sum()
    assert 0.5 * u @ (K @ u) == pytest.approx(energy_density * volume, rel=1e-12)


# --- gravity, damping -----------------------------------------------------------------------


def test_gravity_term_sign_and_total_force():
    V, T = jittered_box()
    rho = 800.0
    M = mass_matrix(V, T, rho)
    mass = rho * tet_volumes(V, T).sum()
    g = gravity_term(M)
    assert g.shape == (3 * len(V),)
    # (1): M u'' + D u' + K u + g = 0, so the external force is -g = M G, pointing down (y up)
    np.testing.assert_allclose(-g.reshape(-1, 3).sum(axis=0), [0.0, -9.81 * mass, 0.0], rtol=1e-12)
    # at rest, a free body accelerates with gravity: u'' = -M^-1 g = G at every vertex
    accel = sp.linalg.spsolve(M.tocsc(), -g).reshape(-1, 3)
    np.testing.assert_allclose(accel, np.tile([0.0, -9.81, 0.0], (len(V), 1)), atol=1e-10)
    g2 = gravity_term(M, gravity=(0.0, 0.0, -1.0))
    np.testing.assert_allclose(g2.reshape(-1, 3).sum(axis=0), [0.0, 0.0, mass], rtol=1e-12)
    with pytest.raises(WigglyInputError, match="gravity"):
        gravity_term(M, gravity=(0.0, 1.0))


def test_rayleigh_damping_combination():
    V, T = jittered_box()
    M = mass_matrix(V, T, 1000.0)
    K = stiffness_matrix(V, T, 1e5, 0.4)
    D = rayleigh_damping(M, K, 0.5, 0.01)
    x = np.random.default_rng(0).standard_normal(M.shape[0])
    np.testing.assert_allclose(D @ x, 0.5 * (M @ x) + 0.01 * (K @ x), rtol=1e-12)
    assert sp.isspmatrix_csr(D)


# --- box mesh (primitives) ------------------------------------------------------------------


def test_box_mesh_is_conforming_and_positively_oriented():
    shape, size = (3, 2, 4), (1.5, 1.0, 2.0)
    V, T = box_mesh(shape, size, origin=(1.0, -1.0, 0.5))
    nx, ny, nz = shape
    assert V.shape == ((nx + 1) * (ny + 1) * (nz + 1), 3) and T.shape == (6 * nx * ny * nz, 4)
    assert T.dtype == np.int64 and V.dtype == np.float64
    vol = tet_volumes(V, T)
    np.testing.assert_allclose(vol, np.prod(size) / (6 * nx * ny * nz), rtol=1e-12)
    np.testing.assert_allclose(V.min(axis=0), [1.0, -1.0, 0.5])
    np.testing.assert_allclose(V.max(axis=0), [2.5, 0.0, 2.5])
    # conforming: every face is shared by two tets, except 2 triangles per boundary square
    faces = np.sort(T[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert set(counts.tolist()) == {1, 2}
    assert int(np.sum(counts == 1)) == 4 * (nx * ny + ny * nz + nx * nz)


def test_box_mesh_rejects_bad_shape():
    with pytest.raises(WigglyInputError, match="shape"):
        box_mesh((0, 1, 1))
    with pytest.raises(WigglyInputError, match="size"):
        box_mesh((1, 1, 1), (1.0, -1.0, 1.0))


def test_assembly_matches_naive_loop():
    """The vectorized assembly equals a plain element-by-element sum (small mesh)."""
    V, T = jittered_box(shape=(2, 2, 1), seed=5)
    E, nu, rho = 1e5, 0.3, 900.0
    lam, mu = lame_parameters(E, nu)
    n = len(V)
    K_ref = np.zeros((3 * n, 3 * n))
    M_ref = np.zeros((3 * n, 3 * n))
    C = np.zeros((6, 6))
    C[:3, :3] = lam
    C += np.diag([2 * mu] * 3 + [mu] * 3)
    for tet in T:
        X = V[tet]
        Dm = (X[1:] - X[0]).T
        vol = np.linalg.det(Dm) / 6
        G = np.vstack([-np.linalg.inv(Dm).sum(axis=0), np.linalg.inv(Dm)])  # rows grad phi_a
        B = np.zeros((6, 12))
        for a in range(4):
            gx, gy, gz = G[a]
            B[:, 3 * a : 3 * a + 3] = [
                [gx, 0, 0],
                [0, gy, 0],
                [0, 0, gz],
                [0, gz, gy],
                [gz, 0, gx],
                [gy, gx, 0],
            ]
        dofs = (3 * tet[:, None] + np.arange(3)).ravel()
        K_ref[np.ix_(dofs, dofs)] += vol * B.T @ C @ B
        Me = rho * vol / 20 * (np.ones((4, 4)) + np.eye(4))
        M_ref[np.ix_(dofs, dofs)] += np.kron(Me, np.eye(3))
    np.testing.assert_allclose(
        stiffness_matrix(V, T, E, nu).toarray(), K_ref, atol=1e-9 * abs(K_ref).max()
    )
    np.testing.assert_allclose(
        mass_matrix(V, T, rho).toarray(), M_ref, atol=1e-13 * abs(M_ref).max()
    )


def _edge_gradients(V, T, U):
    """Per tet the displacement gradient F_kj = d u_k / d X_j from edge vectors, and the
    volume: independent of wiggly.fem's shape-function gradients."""
    Dm = np.stack([V[T[:, i]] - V[T[:, 0]] for i in (1, 2, 3)], axis=2)  # columns: edges
    Ds = np.stack([U[T[:, i]] - U[T[:, 0]] for i in (1, 2, 3)], axis=2)
    return Ds @ np.linalg.inv(Dm), np.abs(np.linalg.det(Dm)) / 6.0


def test_linear_stress_of_an_affine_displacement_is_hookes_law():
    """u = A X on a box: every tet carries sigma = lambda tr(eps) I + 2 mu eps with eps =
    sym(A) and the Lame parameters of (young, poisson) (Schulz et al. 2014, eq. (1));
    per-tet Young's moduli scale it tet by tet."""
    from wiggly.fem import linear_stress

    V, T = box_mesh((3, 2, 2), (1.0, 0.6, 0.4))
    A = np.random.default_rng(3).normal(size=(3, 3))
    young, nu = 2e5, 0.3
    lam = young * nu / ((1 + nu) * (1 - 2 * nu))
    mu = young / (2 * (1 + nu))
    eps = 0.5 * (A + A.T)
    expected = lam * np.trace(eps) * np.eye(3) + 2 * mu * eps
    got = linear_stress(V, T, V @ A.T, young, nu)
    np.testing.assert_allclose(got, np.broadcast_to(expected, got.shape), rtol=1e-10,
                               atol=1e-9 * np.abs(expected).max())
    per_tet = np.linspace(1.0, 2.0, len(T)) * young
    scaled = linear_stress(V, T, V @ A.T, per_tet, nu)
    np.testing.assert_allclose(scaled, got * (per_tet / young)[:, None, None], rtol=1e-10,
                               atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("seed", [0, 1])
def test_geometric_stiffness_is_the_second_variation_of_the_stress_work(seed):
    """u^T K_sigma u = sum over tets vol sigma_ij F_ki F_kj (F = grad u from edge vectors;
    the second variation of int sigma : 1/2 grad u^T grad u), for random per-tet stresses and
    displacements; symmetric; translations cost nothing."""
    from wiggly.fem import geometric_stiffness

    rng = np.random.default_rng(seed)
    V, T = box_mesh((3, 3, 2), (1.0, 0.8, 0.5))
    V = V + 0.02 * rng.normal(size=V.shape)  # not a lattice
    S = rng.normal(size=(len(T), 3, 3))
    S = S + S.transpose(0, 2, 1)
    Ks = geometric_stiffness(V, T, S)
    for _ in range(3):
        U = rng.normal(size=V.shape)
        F, vol = _edge_gradients(V, T, U)
        expected = np.einsum("m,mij,mki,mkj->", vol, S, F, F)
        assert U.ravel() @ (Ks @ U.ravel()) == pytest.approx(expected, rel=1e-10)
    assert abs(Ks - Ks.T).max() <= 1e-12 * abs(Ks).max()
    shift = np.tile(rng.normal(size=3), len(V))
    assert np.abs(Ks @ shift).max() <= 1e-10 * abs(Ks).max() * np.abs(shift).max()
