"""Tests of rotation-strain warping (Schulz et al. 2014, Theorem 2; Huang et al. 2011):
the mathematics of W."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

import wiggly.warp.modal as modal_module
from wiggly.errors import WigglyInputError
from wiggly.primitives import box_mesh
from wiggly.warp import ModalWarp, Warp, compiled, kernels_numpy, rotation_coefficients

RNG_SEED = 20140727


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about the unit vector ``axis`` (Rodrigues, written out)."""
    k = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)


def rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def mesh() -> tuple[np.ndarray, np.ndarray]:
    """A 2 x 1 x 0.8 box, off the origin, 6 x 3 x 3 cubes (648 tets)."""
    return box_mesh((6, 3, 3), size=(2.0, 1.0, 0.8), origin=(0.3, -0.2, 0.1))


@pytest.fixture(scope="module")
def free_warp(mesh) -> Warp:
    return Warp(*mesh)


@pytest.fixture(scope="module")
def clamped_warp(mesh) -> Warp:
    V, T = mesh
    return Warp(V, T, fixed_vertices=np.flatnonzero(V[:, 0] == V[:, 0].min()))


@pytest.fixture(params=["free", "clamped"])
def warp(request, free_warp, clamped_warp) -> Warp:
    return free_warp if request.param == "free" else clamped_warp


def random_displacement(V: np.ndarray, scale: float, seed: int = RNG_SEED) -> np.ndarray:
    """Smooth-ish random field: a random quadratic map plus vertex noise (gradients ~ scale)."""
    rng = np.random.default_rng(seed)
    X = V - V.mean(axis=0)
    quad = np.einsum("nj,nk,ijk->ni", X, X, rng.standard_normal((3, 3, 3)))
    return scale * (X @ rng.standard_normal((3, 3)).T + 0.5 * quad) + 0.02 * scale * (
        rng.standard_normal(V.shape)
    )


# --------------------------------------------------------------------------- #
# Rodrigues coefficients
# --------------------------------------------------------------------------- #
def test_rotation_coefficients_match_closed_forms_and_limits():
    edge = np.sqrt([np.nextafter(0.01, 0.0), 0.01])  # around the series/closed-form switch
    th = np.array([0.0, 1e-9, 1e-4, *edge, 0.7, 2.0, 3.1])
    a, b, c = rotation_coefficients(th**2, derivative=True)
    big = th > 0.05
    np.testing.assert_allclose(a[big], np.sin(th[big]) / th[big], rtol=1e-14)
    np.testing.assert_allclose(b[big], (1 - np.cos(th[big])) / th[big] ** 2, rtol=1e-12)
    np.testing.assert_allclose(c[big], (th[big] - np.sin(th[big])) / th[big] ** 3, rtol=1e-9)
    np.testing.assert_allclose(a[:3], 1.0 - th[:3] ** 2 / 6, rtol=1e-15)
    np.testing.assert_allclose(b[:3], 0.5 - th[:3] ** 2 / 24, rtol=1e-15)
    np.testing.assert_allclose(c[:3], 1 / 6 - th[:3] ** 2 / 120, rtol=1e-15)
    # no jump where the series for c hands over to the closed form
    assert abs(c[3] - c[4]) < 1e-13


# --------------------------------------------------------------------------- #
# The map W
# --------------------------------------------------------------------------- #
def test_zero_maps_to_zero(warp, mesh):
    out = warp.apply(np.zeros_like(mesh[0]))
    assert out.shape == mesh[0].shape
    assert np.max(np.abs(out)) == 0.0


@pytest.mark.parametrize("degrees", [10.0, 90.0, 170.0])
def test_linearized_rotation_becomes_exact_rotation_about_mass_centre(mesh, degrees):
    """u = w x (X - c)  ->  X + W(u) = R (X - c_m) + c_m + u_bar (mass-weighted means)."""
    V, T = mesh
    rng = np.random.default_rng(int(degrees))
    masses = rng.uniform(0.5, 2.0, len(V))  # the statement holds for any masses
    W = Warp(V, T, masses=masses)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    w = np.deg2rad(degrees) * axis
    c = rng.standard_normal(3)
    u = np.cross(w, V - c)
    c_m = masses @ V / masses.sum()
    u_bar = masses @ u / masses.sum()
    expected = (V - c_m) @ rotation_matrix(axis, np.deg2rad(degrees)).T + c_m + u_bar
    assert rel(W.apply(u), expected - V) < 1e-8
    # the linear displacement itself is far from the rotation
    assert rel(u, expected - V) > 0.05


def test_homogeneous_gradient_is_warped_exactly(free_warp, mesh):
    """Constant gradient A (compatible): W(u) = (expm(skew A)(I + sym A) - I)(X - c_m) + u_bar."""
    V = mesh[0]
    A = 0.6 * np.random.default_rng(11).standard_normal((3, 3))
    u = (V - np.array([1.0, 2.0, -0.5])) @ A.T
    K, S = (A - A.T) / 2, (A + A.T) / 2
    target = expm(K) @ (np.eye(3) + S) - np.eye(3)  # independent of the Rodrigues code
    m = free_warp.masses
    c_m, u_bar = m @ V / m.sum(), m @ u / m.sum()
    assert rel(free_warp.apply(u), (V - c_m) @ target.T + u_bar) < 1e-10


def test_rotation_about_a_fixed_vertex_is_exact(mesh):
    V, T = mesh
    k = 17
    W = Warp(V, T, fixed_vertices=[k])
    axis = np.array([1.0, -2.0, 0.5])
    angle = np.deg2rad(120.0)
    u = np.cross(angle * axis / np.linalg.norm(axis), V - V[k])
    expected = (V - V[k]) @ rotation_matrix(axis, angle).T + V[k]
    assert rel(W.apply(u), expected - V) < 1e-8


def test_translations_pass_through_unchanged(free_warp, mesh):
    V = mesh[0]
    d = np.array([0.3, -1.7, 2.5])
    t = np.broadcast_to(d, V.shape)
    np.testing.assert_allclose(free_warp.apply(t), t, rtol=0, atol=1e-12 * np.linalg.norm(d))
    # and W commutes with translations: W(u + d) = W(u) + d
    u = random_displacement(V, 0.4)
    np.testing.assert_allclose(free_warp.apply(u + d), free_warp.apply(u) + d, atol=1e-12)


def test_mass_weighted_mean_is_preserved(free_warp, mesh):
    u = random_displacement(mesh[0], 0.5)
    m = free_warp.masses
    np.testing.assert_allclose(m @ free_warp.apply(u), m @ u, rtol=1e-12)
    np.testing.assert_allclose(m.sum(), free_warp.volumes.sum(), rtol=1e-14)


def test_first_order_exact(warp, mesh):
    """||W(eps u) - eps u|| = O(eps^2): halving eps divides the defect by ~4."""
    u = random_displacement(mesh[0], 1.0)
    u[warp.fixed] = 0.0  # an admissible displacement
    defect = [np.linalg.norm(warp.apply(eps * u) - eps * u) for eps in (1e-2, 5e-3, 2.5e-3)]
    assert defect[0] > 1e-6 * np.linalg.norm(u)  # the map is not the identity
    ratios = np.array(defect[:-1]) / np.array(defect[1:])
    assert np.all(np.abs(ratios - 4.0) < 0.2), ratios


def test_fixed_vertices_stay_at_zero(clamped_warp, mesh):
    V = mesh[0]
    u = random_displacement(V, 0.5) + 1.0  # nonzero on the fixed vertices too
    out = clamped_warp.apply(u)
    fixed = clamped_warp.fixed
    assert fixed.sum() == 16
    assert np.max(np.abs(out[fixed])) == 0.0
    assert np.linalg.norm(out[~fixed]) > 1.0


def test_batched_apply_equals_per_frame(warp, mesh, monkeypatch):
    V, T = mesh
    U = np.stack([random_displacement(V, s, seed=i) for i, s in enumerate([0.1, 0.5, 1.0, 2.0, 0])])
    single = np.stack([warp.apply(u) for u in U])
    batched = warp.apply(U)
    assert batched.shape == U.shape
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-13 * np.abs(single).max())
    # the numpy path in chunks of two frames: exercise its chunking
    monkeypatch.setattr(kernels_numpy, "_CHUNK_ENTRIES", 2 * len(T))
    numpy_warp = Warp(V, T, fixed_vertices=warp.fixed, kernels="numpy")
    got = numpy_warp.apply(U)
    np.testing.assert_allclose(got, single, rtol=0, atol=1e-13 * np.abs(single).max())


@pytest.fixture(scope="module")
def jittered() -> tuple[np.ndarray, np.ndarray]:
    """The box with interior vertices moved randomly: tets of unequal volumes and shapes."""
    V, T = box_mesh((6, 3, 3), size=(2.0, 1.0, 0.8), origin=(0.3, -0.2, 0.1))
    inner = np.all((V > V.min(axis=0) + 1e-9) & (V < V.max(axis=0) - 1e-9), axis=1)
    V = V.copy()
    V[inner] += np.random.default_rng(RNG_SEED).uniform(-0.08, 0.08, (inner.sum(), 3))
    return V, T


def test_poisson_matrix_is_the_volume_weighted_p1_laplacian(jittered):
    """L_ab = sum_t vol_t grad phi_a . grad phi_b, assembled here tet by tet from edge
    vectors (an independent computation), on a mesh with unequal tets."""
    V, T = jittered
    warp = Warp(V, T)
    L = np.zeros((len(V), len(V)))
    for tet in T:
        X = V[tet]
        D = (X[1:] - X[0]).T
        vol = np.linalg.det(D) / 6.0
        g = np.linalg.inv(D)  # rows: gradients of phi_1..phi_3 (phi_i(X_j) = delta_ij)
        g = np.vstack([-g.sum(axis=0), g])
        L[np.ix_(tet, tet)] += vol * g @ g.T
    vols = np.array([np.linalg.det((V[t][1:] - V[t][0]).T) for t in T])
    assert np.ptp(vols) > 0.5 * vols.mean()  # unequal tets: a wrong volume weighting shows
    np.testing.assert_allclose(warp.laplacian.toarray(), L, atol=1e-13 * np.abs(L).max())


@pytest.mark.skipif(not compiled.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("fixed", [False, True])
def test_compiled_kernels_equal_the_vectorized_numpy_path(jittered, fixed):
    """Two independent implementations of the per-tet formulas (fused numba loops and
    vectorized numpy component arrays) agree on W, DW, DW^T, the Jacobians, the second
    derivatives and the curvature matrices, at small and large gradients (rotation angles up
    to ~3 rad, near the series switch of c)."""
    V, T = jittered
    fixed_vertices = np.flatnonzero(V[:, 0] == V[:, 0].min()) if fixed else None
    U = np.stack([random_displacement(V, s, seed=i) for i, s in enumerate([1e-3, 0.3, 1.5, 3.0])])
    dU = np.stack([random_displacement(V, 1.0, seed=10 + i) for i in range(4)])
    basis = np.stack([random_displacement(V, 1.0, seed=20 + i) for i in range(5)], axis=2)
    rng = np.random.default_rng(3)
    Q, Qv = rng.standard_normal((3, 5)), rng.standard_normal((3, 5))
    Qv[1] = 0.0  # a point without a velocity
    Y, Yv = rng.standard_normal((3, len(V), 3)), rng.standard_normal((3, len(V), 3))
    Yv[1] = 0.0

    def evaluate(kernels):
        warp = Warp(V, T, fixed_vertices=fixed_vertices, kernels=kernels)
        modal = ModalWarp(warp, basis)
        curvatures = modal.curvatures(Q, Y, Qv, Yv)
        return [
            warp.apply(U),
            warp.jvp(U, dU),
            warp.vjp(U, dU),
            modal.jacobians(Q),
            modal.second_derivatives(Q, Qv),
            np.stack([qq for qq, _ in modal.curvatures(Q, Y)]),
            np.stack([qv for _, qv in curvatures if qv is not None]),
            np.stack([qq for qq, _ in curvatures]),
        ]

    compiled_, numpy_ = evaluate("numba"), evaluate("numpy")
    assert compiled_[6].shape[0] == 2  # the point without velocity has no q-q' block
    for a, b in zip(compiled_[:4], numpy_[:4], strict=True):
        assert rel(a, b) < 1e-13
    # second derivatives and Hessians: numba analytic, numpy central differences of the
    # analytic first derivative (error ~ step^2 ~ 1e-10)
    for a, b in zip(compiled_[4:7], numpy_[4:7], strict=True):
        assert rel(a, b) < 1e-8
    # with the third-order velocity term: numpy nests central differences (step ~3e-4 at
    # these gradients: truncation ~1e-7)
    assert rel(compiled_[7], numpy_[7]) < 1e-6


@pytest.mark.parametrize("kernels", ["numba", "numpy"])
def test_inverted_tets_are_those_of_negative_signed_volume(jittered, kernels):
    """Warp.inverted against the signed volumes of the displaced tets (their edge matrices,
    not the warp's gradients), on fields that turn some tets inside out and leave others."""
    if kernels == "numba" and not compiled.AVAILABLE:
        pytest.skip("numba not installed")
    V, T = jittered
    warp = Warp(V, T, kernels=kernels)
    U = np.stack([random_displacement(V, s, seed=30 + i) for i, s in enumerate([0.0, 0.3, 1.0])])
    U[0, :, 0] = -2.0 * V[:, 0]  # a mirror: every tet inside out
    P = (V + U)[:, T]  # (f, m, 4, 3)
    signed = np.linalg.det(np.swapaxes(P[:, :, 1:] - P[:, :, :1], -1, -2))
    expected = signed <= 0.0
    got = warp.inverted(U)
    assert got.shape == (3, len(T)) and got.dtype == bool
    assert got[0].all() and not expected[1].any() and 0 < expected[2].sum() < len(T)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(warp.inverted(U[2]), expected[2:])


def test_components_get_their_own_gauge():
    """Two disjoint boxes: one clamped (Dirichlet), one free (mean gauge), plus a loose vertex."""
    V1, T1 = box_mesh((2, 2, 2))
    V2, T2 = box_mesh((2, 2, 2), origin=(3.0, 0.0, 0.0))
    V = np.vstack([V1, V2, [[10.0, 10.0, 10.0]]])
    T = np.vstack([T1, T2 + len(V1)])
    W = Warp(V, T, fixed_vertices=[0])
    u = random_displacement(V, 0.5)
    out = W.apply(u)
    second = slice(len(V1), len(V1) + len(V2))
    m = W.masses[second]
    np.testing.assert_allclose(m @ out[second], m @ u[second], rtol=1e-12)
    assert np.all(out[0] == 0.0)
    np.testing.assert_array_equal(out[-1], u[-1])  # massless isolated vertex: plain mean
    # each component is warped independently of the other
    W2 = Warp(V2, T2)
    np.testing.assert_allclose(out[second], W2.apply(u[second]), atol=1e-12)


def test_derivatives_with_several_components_are_consistent():
    """The same mesh (a clamped box, a free box, a loose vertex: a gauge per component): vjp
    is the adjoint of jvp for single fields, batches and indexed cotangents, jvp the central
    difference of W, and the Jacobians the jvp along each field."""
    V1, T1 = box_mesh((2, 2, 2))
    V2, T2 = box_mesh((2, 2, 2), origin=(3.0, 0.0, 0.0))
    V = np.vstack([V1, V2, [[10.0, 10.0, 10.0]]])
    W = Warp(V, np.vstack([T1, T2 + len(V1)]), fixed_vertices=[0])
    U = np.stack([random_displacement(V, 0.5, seed=s) for s in range(3)])
    dU = np.stack([random_displacement(V, 1.0, seed=10 + s) for s in range(3)])
    Y = np.stack([random_displacement(V, 1.0, seed=20 + s) for s in range(2)])
    jvp = W.jvp(U, dU)
    assert rel(jvp[1], central_difference(W, U[1], dU[1])) < 1e-6
    index = np.array([1, 0, 1])
    vjp = W.vjp(U, Y, index)
    for s in range(3):
        assert abs(np.vdot(vjp[s], dU[s]) - np.vdot(Y[index[s]], jvp[s])) < 1e-12 * np.linalg.norm(
            Y[index[s]]
        ) * np.linalg.norm(jvp[s])
        np.testing.assert_allclose(W.vjp(U[s], Y[index[s]]), vjp[s], atol=1e-13)
    np.testing.assert_allclose(W.vjp(U, Y[index]), vjp, atol=1e-13)
    basis = dU.transpose(1, 2, 0)  # three fields (n, 3, 3)
    modal = ModalWarp(W, basis)
    Q = np.linalg.lstsq(basis.reshape(-1, 3), U.reshape(3, -1).T, rcond=None)[0].T
    J = modal.jacobians(Q)
    for s in range(3):
        u = modal.displacements(Q[s : s + 1])[0]
        for k in range(3):
            assert rel(J[s, :, :, k], W.jvp(u, basis[:, :, k])) < 1e-12
    with pytest.raises(WigglyInputError, match="index"):
        W.vjp(U, Y, np.array([0, 1, 2]))


def test_warping_a_bent_cantilever_keeps_lengths_and_volumes():
    """A linearized 90-degree bend of a thin beam: linear FEM grows it, the warp does not."""
    length, h = 5.0, 0.2
    V, T = box_mesh((25, 2, 2), size=(length, h, h), origin=(0.0, -h / 2, -h / 2))
    W = Warp(V, T, fixed_vertices=np.flatnonzero(V[:, 0] == 0.0))
    k = (np.pi / 2) / length  # curvature: the tip cross-section turns by 90 degrees
    x, y = V[:, 0], V[:, 1]
    u = np.column_stack([-k * x * y, 0.5 * k * x**2, np.zeros_like(x)])  # Euler-Bernoulli

    edges = np.vstack([T[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])

    def edge_change(P):
        rest = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
        return np.abs(np.linalg.norm(P[edges[:, 0]] - P[edges[:, 1]], axis=1) / rest - 1)

    def volume_change(P):
        def vol(Q):
            e = Q[T[:, 1:]] - Q[T[:, :1]]
            return np.linalg.det(e) / 6

        return np.abs(vol(P) / vol(V) - 1)

    linear, warped = V + u, V + W.apply(u)
    assert edge_change(linear).max() > 0.5 and volume_change(linear).max() > 1.0
    # the bending strain itself is |k y| <= k h / 2 ~ 3 %
    assert edge_change(warped).max() < 0.05
    assert volume_change(warped).max() < 0.05
    # and the centre line follows the circular arc of radius 1 / k
    tip = np.flatnonzero((x == length) & (y == 0.0) & (V[:, 2] == 0.0))
    arc_tip = np.array([np.sin(k * length), 1 - np.cos(k * length), 0.0]) / k
    assert np.linalg.norm(warped[tip[0]] - arc_tip) < 0.02 * length


# --------------------------------------------------------------------------- #
# Derivatives
# --------------------------------------------------------------------------- #
def central_difference(W: Warp, u: np.ndarray, du: np.ndarray, h: float = 1e-6) -> np.ndarray:
    return (W.apply(u + h * du) - W.apply(u - h * du)) / (2 * h)


def test_jvp_matches_finite_differences(warp, mesh):
    V = mesh[0]
    u = random_displacement(V, 0.8)  # rotations of up to ~1 rad per tet
    du = random_displacement(V, 1.0, seed=1)
    jvp = warp.jvp(u, du)
    assert rel(jvp, central_difference(warp, u, du)) < 1e-6
    assert rel(jvp, du) > 0.05  # the derivative away from 0 is not the identity


def test_jvp_at_zero_is_identity(warp, mesh):
    V = mesh[0]
    du = random_displacement(V, 1.0, seed=3)
    du[warp.fixed] = 0.0
    assert rel(warp.jvp(np.zeros_like(V), du), du) < 1e-10


def test_jacobian_matches_jvp_and_finite_differences(warp, mesh):
    V = mesh[0]
    n = len(V)
    u = random_displacement(V, 0.8, seed=5)
    basis = np.stack([random_displacement(V, 1.0, seed=10 + k) for k in range(7)], axis=-1)
    basis[:, :, 0] = u  # u = Phi q with q = e_0
    q = np.eye(7)[:1]
    J = ModalWarp(warp, basis).jacobians(q)[0]
    assert J.shape == basis.shape
    for k in (0, 6):
        assert rel(J[:, :, k], central_difference(warp, u, basis[:, :, k])) < 1e-6
        assert rel(J[:, :, k], warp.jvp(u, basis[:, :, k])) < 1e-12
    flat = ModalWarp(warp, basis.reshape(3 * n, 7)).jacobians(q)[0]
    np.testing.assert_allclose(flat, J, rtol=0, atol=1e-12 * np.abs(J).max())


def test_vjp_is_the_adjoint_of_jvp(warp, mesh):
    V = mesh[0]
    u = random_displacement(V, 0.8, seed=7)
    du = random_displacement(V, 1.0, seed=8)
    y = np.random.default_rng(9).standard_normal(V.shape)
    lhs = np.sum(warp.vjp(u, y) * du)
    rhs = np.sum(y * warp.jvp(u, du))
    assert abs(lhs - rhs) < 1e-11 * np.linalg.norm(y) * np.linalg.norm(warp.jvp(u, du))


def test_apply_and_jvp_in_one_solve_equal_them_apart(warp, mesh):
    """The fused evaluation (one Poisson solve for W and DW[du]) gives what apply and jvp
    give, for selected frames, to rounding."""
    V = mesh[0]
    U = np.stack([random_displacement(V, s, seed=30 + i) for i, s in enumerate([0.3, 1.2, 0.7])])
    dU = np.stack([random_displacement(V, 1.0, seed=40 + i) for i in range(2)])
    W, D = warp.apply_and_jvp(U, [2, 0], dU)
    scale = np.abs(warp.apply(U)).max()
    np.testing.assert_allclose(W, warp.apply(U), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(D, warp.jvp(U[[2, 0]], dU), rtol=0, atol=1e-12 * np.abs(D).max())
    assert rel(D[0], central_difference(warp, U[2], dU[0])) < 1e-6


def test_batched_derivatives_equal_per_frame(warp, mesh):
    V = mesh[0]
    U = np.stack([random_displacement(V, s, seed=i) for i, s in enumerate([0.2, 0.9, 1.5])])
    dU = np.stack([random_displacement(V, 1.0, seed=20 + i) for i in range(3)])
    np.testing.assert_allclose(
        warp.jvp(U, dU), np.stack([warp.jvp(u, d) for u, d in zip(U, dU, strict=True)]), atol=1e-12
    )
    np.testing.assert_allclose(
        warp.vjp(U, dU), np.stack([warp.vjp(u, d) for u, d in zip(U, dU, strict=True)]), atol=1e-12
    )


def test_jvp_near_half_turn(free_warp, mesh):
    """Large per-tet rotations (~170 degrees) keep the analytic derivative accurate."""
    V = mesh[0]
    w = np.deg2rad(170.0) * np.array([0.0, 0.6, 0.8])
    u = np.cross(w, V - V.mean(axis=0)) + random_displacement(V, 0.05)
    du = random_displacement(V, 1.0, seed=4)
    assert rel(free_warp.jvp(u, du), central_difference(free_warp, u, du, h=1e-7)) < 1e-6


# --------------------------------------------------------------------------- #
# Input validation
# --------------------------------------------------------------------------- #
def test_inputs_are_validated(free_warp, mesh):
    V, T = mesh
    with pytest.raises(WigglyInputError, match="positively oriented"):
        Warp(V, T[:, [1, 0, 2, 3]])
    with pytest.raises(WigglyInputError, match="shape"):
        Warp(V[:, :2], T)
    with pytest.raises(WigglyInputError, match="fixed_vertices"):
        Warp(V, T, fixed_vertices=[len(V)])
    with pytest.raises(WigglyInputError, match="masses"):
        Warp(V, T, masses=np.ones(3))
    with pytest.raises(WigglyInputError, match="masses"):
        Warp(V, T, masses=np.full(len(V), np.nan))
    with pytest.raises(WigglyInputError, match="U should have shape"):
        free_warp.apply(np.zeros((len(V), 2)))
    with pytest.raises(WigglyInputError, match="basis"):
        ModalWarp(free_warp, np.zeros((len(V), 2, 4)))
    with pytest.raises(WigglyInputError, match="kernels"):
        Warp(V, T, kernels="fortran")
    with pytest.raises(WigglyInputError, match="dU"):
        free_warp.jvp(np.zeros_like(V), np.zeros((2, len(V), 3)))


@pytest.mark.skipif(not compiled.AVAILABLE, reason="numba not installed")
def test_compiled_rotation_coefficients_match_high_precision():
    """The kernels' a, b, c (Taylor series up to th = pi, closed forms beyond) against 50-digit
    values, at every angle and on both sides of the switch at th = pi."""
    import mpmath

    mpmath.mp.dps = 50
    pi2 = float(mpmath.pi**2)
    t2s = [0.0, 1e-12, 1e-4, 0.01, 0.5, 1.0, 4.0, np.nextafter(pi2, 0), pi2]
    t2s += [np.nextafter(pi2, 20), 12.0, 30.0, 39.0]
    for t2 in t2s:
        a, b = compiled.rotation_ab(t2)
        c = compiled.rotation_c(t2, a)
        th = mpmath.sqrt(mpmath.mpf(t2))
        if t2 == 0.0:
            exact = (1, mpmath.mpf(1) / 2, mpmath.mpf(1) / 6)
        else:
            exact = (
                mpmath.sin(th) / th,
                (1 - mpmath.cos(th)) / th**2,
                (th - mpmath.sin(th)) / th**3,
            )
        for got, want in zip((a, b, c), exact, strict=True):
            # a few ulps of the largest series term (1.7 for a at th = pi): absolute error
            assert abs(got - float(want)) <= 4e-16


def test_jacobians_of_many_frames_are_made_chunk_by_chunk(warp, mesh, monkeypatch):
    """Frames are solved a few at a time (``CHUNK_BYTES``): with chunks of one or two frames
    the Jacobians and second derivatives are the per-frame tangents."""
    V = mesh[0]
    basis = np.stack([random_displacement(V, 1.0, seed=30 + k) for k in range(4)], axis=-1)
    modal = ModalWarp(warp, basis)
    rng = np.random.default_rng(8)
    Q, Qv = 0.3 * rng.standard_normal((5, 4)), rng.standard_normal((5, 4))
    whole_J, whole_JV = modal.jacobians(Q), modal.second_derivatives(Q, Qv)
    for per_frame in (1, 2):
        monkeypatch.setattr(modal_module, "CHUNK_BYTES", per_frame * 24 * len(V) * 4)
        J, JV = modal.jacobians(Q), modal.second_derivatives(Q, Qv)
        np.testing.assert_allclose(J, whole_J, rtol=0, atol=1e-13 * np.abs(J).max())
        np.testing.assert_allclose(JV, whole_JV, rtol=0, atol=1e-13 * np.abs(JV).max())
    for s in range(5):
        u = modal.displacements(Q[s : s + 1])[0]
        for k in range(4):
            assert rel(J[s, :, :, k], warp.jvp(u, basis[:, :, k])) < 1e-12


# --------------------------------------------------------------------------- #
# The carried warp (secondary motion's free parts in the rig's frame)
# --------------------------------------------------------------------------- #
def test_carried_warp_composes_a_rigid_turn_and_reduces_to_the_warp(warp, mesh):
    """``carried(Ubar, U)`` fits ``F(Ubar) F(U) - I``: with either field zero it is the warp
    of the other; under a linearized turn by 2.5 rad about y it is the turn of the warped U
    (exactly, up to the free body's translation gauge), where the warp of ``Ubar + U``
    scales U's rotations across the axis by sin(a) / a."""
    V, _ = mesh
    ubar = random_displacement(V, 0.3, seed=5)
    u = random_displacement(V, 0.05, seed=6)
    np.testing.assert_allclose(warp.carried(ubar, 0 * u), warp.apply(ubar), atol=1e-14)
    np.testing.assert_allclose(warp.carried(0 * ubar, u), warp.apply(u), atol=1e-14)
    w = np.array([0.0, 2.5, 0.0])
    turn = np.cross(w, V - V.mean(axis=0))
    R = expm(np.cross(np.eye(3), w))
    x = warp.carried(turn, u)
    expected = (V + warp.apply(u)) @ R.T - V
    if warp.gauge.floating:  # the translation is the gauge's: compare shapes
        x, expected = x - x.mean(axis=0), expected - expected.mean(axis=0)
        assert rel(x, expected) < 1e-12
        added = warp.apply(turn + u)
        assert rel(added - added.mean(axis=0), expected) > 0.01


@pytest.mark.parametrize("kernels", ["numba", "numpy"])
def test_carried_warp_jvp_matches_central_differences(mesh, kernels):
    """The analytic tangent of the carried warp along both fields, for large fields (tets
    turned by radians), against central differences; the compiled and numpy passes agree."""
    V, T = mesh
    w = Warp(V, T, fixed_vertices=np.flatnonzero(V[:, 0] == V[:, 0].min()), kernels=kernels)
    ubar, u = random_displacement(V, 1.2, seed=7), random_displacement(V, 0.4, seed=8)
    dubar, du = random_displacement(V, 1.0, seed=9), random_displacement(V, 1.0, seed=10)
    h = 1e-6
    fd = (w.carried(ubar + h * dubar, u + h * du) - w.carried(ubar - h * dubar, u - h * du)) / (
        2 * h)
    assert rel(w.carried_jvp(ubar, dubar, u, du), fd) < 1e-7
    other = Warp(V, T, fixed_vertices=np.flatnonzero(V[:, 0] == V[:, 0].min()),
                 kernels="numpy" if kernels == "numba" else "numba")
    assert rel(w.carried(ubar, u), other.carried(ubar, u)) < 1e-13
    assert rel(w.carried_jvp(ubar, dubar, u, du), other.carried_jvp(ubar, dubar, u, du)) < 1e-12
    # relative: U's part alone, carried(Ubar, U) - apply(Ubar), and its tangent
    part = w.carried(ubar, u, relative=True)
    assert rel(part, w.carried(ubar, u) - w.apply(ubar)) < 1e-12
    assert rel(part, other.carried(ubar, u, relative=True)) < 1e-13
    fd = (w.carried(ubar + h * dubar, u + h * du, relative=True)
          - w.carried(ubar - h * dubar, u - h * du, relative=True)) / (2 * h)
    assert rel(w.carried_jvp(ubar, dubar, u, du, relative=True), fd) < 1e-7
