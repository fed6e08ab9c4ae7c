"""The coarse warp W~ = P W_c(R u) and the two-level warped solve (SYSTEM.md §6).

W~ stands in for W in the Gauss-Newton matrix and in a first solve; these tests check the
mathematics it must keep (rigid motions exactly, derivatives consistent with the map) and
that the two-level solve reaches the stationary point of the *fine* problem.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.linalg import expm

import wiggly.body as body_module
from wiggly.keyframes import Keyframe
from wiggly.mesh import coarse_mesh, embed
from wiggly.solve import SpacetimeProblem, WarpedObjective
from wiggly.warp import CoarseWarp

from .conftest import make_body

solve_module = sys.modules["wiggly.solve"]  # the package's `solve` is the function


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    """A free 1 m x 0.25 m x 0.25 m bar of 24 x 6 x 6 cubes (5184 tets), 16 modes, with a
    coarse warp of about 400 tets (fTetWild)."""
    body = make_body(tmp_path_factory, shape=(24, 6, 6), size=(1.0, 0.25, 0.25), n_modes=16)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(body_module, "COARSE_WARP_ABOVE", 1000)
        mp.setattr(body_module, "COARSE_TETS", 400)
        assert not body.coarse_warp.exact
    return body


def skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def test_coarse_mesh_is_coarser_and_covers_the_solid(slab):
    fine = slab.tets
    coarse = coarse_mesh(fine, 400)
    assert coarse.n_tets < fine.n_tets / 4
    assert embed(fine.vertices, coarse).barycentric.min() > -0.5
    assert abs(coarse.volumes().sum() / fine.volumes().sum() - 1) < 0.05


def test_coarse_warp_turns_linearized_rotations_into_exact_rotations(slab):
    """R and P reproduce affine fields and the coarse masses P^T m keep the mass centre, so
    W~ of a linearized rotation is the exact rotation about the fine mass centre, like W."""
    cw = slab.coarse_warp
    X = slab.tets.vertices
    m = slab.vertex_masses("tets")
    c_m = m @ X / m.sum()
    for degrees in (10.0, 90.0, 170.0):
        w = np.radians(degrees) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        u = (X - c_m) @ skew(w).T + np.array([0.1, -0.2, 0.05])
        exact = (X - c_m) @ expm(skew(w)).T + c_m + np.array([0.1, -0.2, 0.05]) - X
        got = cw.apply(u[None])[0]
        assert np.abs(got - exact).max() < 1e-9 * np.abs(exact).max()
        np.testing.assert_allclose(got, slab.warp.apply(u), atol=1e-9 * np.abs(exact).max())


def test_coarse_warp_derivatives_are_consistent(slab):
    """vjp is the adjoint of jvp, jvp is the derivative of W~ (central differences), and the
    Jacobians lifted by P are the jvp along every mode."""
    cw = slab.coarse_warp
    Phi = slab.modes.vectors
    n, r = slab.tets.n_vertices, slab.r
    rng = np.random.default_rng(7)
    q = rng.standard_normal(r) * 0.3
    u = (Phi @ q).reshape(1, n, 3)
    du = (Phi @ rng.standard_normal(r)).reshape(1, n, 3)
    y = rng.standard_normal((1, n, 3))
    jvp = cw.jvp(u, du)
    assert abs(np.vdot(cw.vjp(u, y), du) - np.vdot(y, jvp)) < 1e-11 * np.linalg.norm(
        y
    ) * np.linalg.norm(jvp)
    h = 1e-6
    fd = (cw.apply(u + h * du) - cw.apply(u - h * du)) / (2 * h)
    assert np.linalg.norm(fd - jvp) < 1e-7 * np.linalg.norm(jvp)
    J = cw.jacobians(q[None])[0]  # (n_c, 3, r) on the coarse mesh
    lifted = (cw.lift @ J.reshape(cw.n_coarse, 3 * r)).reshape(n, 3, r)
    for i in (0, 7, r - 1):
        along = cw.jvp(u, Phi[:, i].reshape(1, n, 3))[0]
        assert np.linalg.norm(lifted[:, :, i] - along) < 1e-10 * np.linalg.norm(along)


def test_exact_coarse_warp_is_the_warp(slab):
    cw = CoarseWarp.exact(slab.warp, slab.modes.vectors)
    n = slab.tets.n_vertices
    u = (slab.modes.vectors @ np.linspace(-0.3, 0.3, slab.r)).reshape(1, n, 3)
    np.testing.assert_allclose(cw.apply(u)[0], slab.warp.apply(u[0]), atol=1e-14)
    np.testing.assert_array_equal(cw.restrict(u), u)


def turn_and_swing(body, velocity=None):
    X = body.rest_positions()
    allv = np.arange(len(X))
    tip = np.flatnonzero(X[:, 0] > 0.8)
    return [
        Keyframe.rest(body, 0.0, allv, still=velocity is not None),
        Keyframe.rigid(body, 0.6, allv, rotation=(0, np.radians(100.0), 0)),
        Keyframe.offset(body, 1.0, tip, (0.0, 0.3, 0.0), velocity=velocity),
    ]


def assert_stationary(problem, anim, tol):
    """Central-difference slopes of the fine E + E_WC obey the Newton-decrement bound
    |g.d| <= sqrt(2 tol F d^T H d), and match the gradient the solver uses."""
    ab, f, c = problem._assemble_energy(anim.nodes)
    obj = WarpedObjective(problem, anim.keyframes, anim.nodes, ab, f, c)
    z = np.stack([anim.values, anim.velocities], axis=1).ravel()
    F, g = obj.value_and_gradient(z)
    rng = np.random.default_rng(5)
    for _ in range(2):
        d = rng.standard_normal(z.size) * np.abs(z).max()
        h = 1e-5
        slope = (obj.value(z + h * d) - obj.value(z - h * d)) / (2 * h)
        curvature = (obj.value(z + 1e-4 * d) - 2 * F + obj.value(z - 1e-4 * d)) / 1e-8
        noise = 1e-15 * F / h
        assert abs(slope) <= 2 * np.sqrt(2 * tol * F * curvature) + noise
        assert abs(g @ d - slope) <= 1e-4 * np.sqrt(F * curvature) + noise


@pytest.mark.parametrize("slow_ratio", [np.inf, 0.0], ids=["coarse-jacobians", "exact-fallback"])
def test_two_level_solve_reaches_the_fine_stationary_point(slab, slow_ratio, monkeypatch):
    """The coarse first level and the coarse Gauss-Newton matrix change the path, never the
    solution: the result is stationary for the fine E + E_WC and equals the solution of the
    solve with exact Jacobians (one level).  Both paths are forced, since which one a solve
    takes depends on the (randomized) coarse mesh: coarse Jacobians throughout
    (SLOW_RATIO = inf never switches), and the switch to exact Jacobians (SLOW_RATIO = 0
    switches as soon as three decrements are known)."""
    keys = turn_and_swing(slab)
    tol = 1e-11
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    with monkeypatch.context() as mp:
        mp.setattr(solve_module, "SLOW_RATIO", slow_ratio)
        two_level = problem.solve(keys, warped=True, tolerance=tol, max_iterations=100, stall=False)
    assert two_level.info["converged"] and two_level.info["coarse"]["iterations"] >= 1
    assert ("exact_jacobians_from" in two_level.info) == (slow_ratio == 0.0)
    saved = slab.__dict__["coarse_warp"]
    slab.__dict__["coarse_warp"] = CoarseWarp.exact(slab.warp, slab.modes.vectors)
    try:
        one_level = SpacetimeProblem(slab, 0.0, 1.2).solve(
            keys, warped=True, tolerance=tol, max_iterations=100, stall=False
        )
    finally:
        slab.__dict__["coarse_warp"] = saved
    assert "coarse" not in one_level.info
    z2 = np.stack([two_level.values, two_level.velocities], axis=1).ravel()
    z1 = np.stack([one_level.values, one_level.velocities], axis=1).ravel()
    assert np.abs(z2 - z1).max() < 1e-5 * np.abs(z1).max()
    assert_stationary(problem, two_level, tol)


def test_two_level_solve_with_velocity_keyframes_is_stationary(slab):
    """Velocity keyframes weigh the second derivative D^2W, which the coarse mesh renders
    less well: the solve switches to exact Jacobians when it converges slowly, and ends at a
    stationary point of the fine problem."""
    keys = turn_and_swing(slab, velocity=(0.0, 1.5, 0.0))
    tol = 1e-10
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    anim = problem.solve(keys, warped=True, tolerance=tol, max_iterations=100, stall=False)
    assert anim.info["converged"]
    assert_stationary(problem, anim, tol)


def edited(keys, degrees=8.0):
    """``keys`` with the 0.6 s pose turned further about y (one keyframe changed)."""
    out = list(keys)
    out[1] = Keyframe(
        keys[1].time,
        keys[1].vertices,
        (keys[1].position - keys[1].position.mean(axis=0))
        @ expm(skew(np.radians(degrees) * np.array([0.0, 1.0, 0.0]))).T
        + keys[1].position.mean(axis=0),
    )
    return out


def test_edited_objective_at_the_last_point_pulls_back_only_changed_cotangents(slab):
    """A warm start evaluates the edited objective at the last fine point from the kept W
    values and vector-Jacobian products (DW^T is linear in the cotangent): the result is the
    same as a fresh evaluation, and only the edited keyframe's node is pulled back."""
    keys = turn_and_swing(slab, velocity=(0.0, 1.5, 0.0))
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    anim = problem.solve(keys, warped=True, tolerance=1e-9, max_iterations=100)
    z = np.stack([anim.values, anim.velocities], axis=1).ravel()
    ab, f, c = problem._assemble_energy(anim.nodes)
    new = [kf.checked(slab, 0.0, 1.2) for kf in edited(keys)]
    kept = WarpedObjective(problem, new, anim.nodes, ab, f, c)
    kept._last = problem._fine_last.last
    assert np.array_equal(kept._last[0], z)  # the solve kept its last point
    F_kept, g_kept = kept.value_and_gradient(z)
    assert kept.counts == {"W": 0, "vjp": 1, "jacobians": 0}  # one node, one cotangent
    fresh = WarpedObjective(problem, new, anim.nodes, ab, f, c)
    F, g = fresh.value_and_gradient(z)
    assert abs(F_kept - F) <= 1e-12 * F
    assert np.abs(g_kept - g).max() <= 1e-9 * np.abs(g).max()
    assert np.abs(g).max() > 1e3 * np.abs(anim.info["objective"]) * 1e-9  # the edit matters


@pytest.mark.parametrize("velocity", [None, (0.0, 1.5, 0.0)])
def test_warm_start_after_an_edit_is_stationary_and_corrected(slab, velocity):
    """After one keyframe changes, the coarse level starts from the last fine point with the
    full-approximation-scheme correction (coarse gradient = fine gradient there), which
    brings the coarse solution closer to the fine one than the plain coarse solve; with a
    strong velocity keyframe the correction fails its check (the fine objective must drop)
    and the plain coarse solve follows.  Either way the result is a stationary point of the
    fine problem, the one a cold solve finds."""
    keys = turn_and_swing(slab, velocity=velocity)
    tol = 1e-10
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    prev = problem.solve(keys, warped=True, tolerance=tol, max_iterations=100, stall=False)
    new = edited(keys)
    warm = problem.solve(
        new, warped=True, initial=prev, tolerance=tol, max_iterations=100, stall=False
    )
    assert warm.info["warm_start"]
    assert ("correction_failed" if velocity else "corrected") in warm.info["coarse"]
    assert warm.info["converged"]
    assert_stationary(problem, warm, tol)
    cold = SpacetimeProblem(slab, 0.0, 1.2).solve(
        new, warped=True, tolerance=tol, max_iterations=100, stall=False
    )
    assert "corrected" not in cold.info["coarse"]
    zw = np.stack([warm.values, warm.velocities], axis=1).ravel()
    zc = np.stack([cold.values, cold.velocities], axis=1).ravel()
    assert np.abs(zw - zc).max() < 1e-4 * np.abs(zc).max()
    if velocity:
        return
    # the fine level's decrease from its start: the coarse warp's error left in the start
    gap_warm = warm.info["objective_start"] - warm.info["objective"]
    gap_cold = cold.info["objective_start"] - cold.info["objective"]
    assert gap_warm < 0.2 * gap_cold


def band_to_dense(ab: np.ndarray) -> np.ndarray:
    """The symmetric matrix H of upper band storage ab[bw + i - j, j] = H[i, j]."""
    bw, N = ab.shape[0] - 1, ab.shape[1]
    H = np.zeros((N, N))
    for i in range(N):
        for j in range(i, min(N, i + bw + 1)):
            H[i, j] = H[j, i] = ab[bw + i - j, j]
    return H


def test_band_helpers_match_dense_algebra():
    rng = np.random.default_rng(0)
    N, bw = 40, 6
    H = rng.standard_normal((N, N))
    H = H + H.T + 4 * N * np.eye(N)
    H[np.abs(np.subtract.outer(np.arange(N), np.arange(N))) > bw] = 0.0
    ab = np.zeros((bw + 1, N))
    for i in range(N):
        for j in range(i, min(N, i + bw + 1)):
            ab[bw + i - j, j] = H[i, j]
    np.testing.assert_array_equal(band_to_dense(ab), H)
    x = rng.standard_normal(N)
    np.testing.assert_allclose(solve_module._band_matvec(ab, bw, x), H @ x, rtol=1e-13)
    block = rng.standard_normal((4, 4))
    block = block + block.T
    idx = np.array([3, 4, 5, 6])
    solve_module._add_block(ab, bw, idx, block)
    H[np.ix_(idx, idx)] += block
    np.testing.assert_array_equal(band_to_dense(ab), H)
    blocks = rng.standard_normal((2, 3, 3))
    blocks = blocks + blocks.transpose(0, 2, 1)
    idx = np.array([[0, 1, 2], [8, 9, 10]])  # a stack of blocks at once
    solve_module._add_dense(ab, bw, idx, blocks)
    for i, b in zip(idx, blocks, strict=True):
        H[np.ix_(i, i)] += b
    np.testing.assert_allclose(band_to_dense(ab), H, rtol=1e-15)
    np.testing.assert_allclose(solve_module._solve_banded(ab, x), np.linalg.solve(H, x), rtol=1e-10)


def test_secant_step_is_the_bfgs_update_of_the_gauss_newton_matrix():
    """-B^-1 g with B = H - Hs(Hs)^T/s^T H s + y y^T/y^T s (dense): B s = y by construction."""
    rng = np.random.default_rng(1)
    N, bw = 30, 4
    A = rng.standard_normal((N, N))
    H = A @ A.T + N * np.eye(N)
    H[np.abs(np.subtract.outer(np.arange(N), np.arange(N))) > bw] = 0.0
    H += 2 * N * np.eye(N)  # still SPD after banding
    ab = np.zeros((bw + 1, N))
    for i in range(N):
        for j in range(i, min(N, i + bw + 1)):
            ab[bw + i - j, j] = H[i, j]
    g, s = rng.standard_normal(N), rng.standard_normal(N)
    y = H @ s + 0.3 * rng.standard_normal(N)
    assert y @ s > 0
    Hs = H @ s
    B = H - np.outer(Hs, Hs) / (s @ Hs) + np.outer(y, y) / (y @ s)
    np.testing.assert_allclose(B @ s, y, rtol=1e-12)
    dz = solve_module._solve_banded(ab, -g)
    step = solve_module._secant_step(ab, solve_module._factor_banded(ab), dz, [(s, y)])
    np.testing.assert_allclose(step, np.linalg.solve(B, -g), rtol=1e-9)


def test_coarse_objective_is_the_coarse_warp_least_squares(slab):
    """The coarse level's keyframe terms (positions from Grams about the targets' fit, in
    batches; velocities from Grams) equal their definition
    1/2 sum c_A |S P W_c(R Phi q) - d|^2 + 1/2 sum c_B |S P DW_c(R Phi q)[R Phi q'] - b|^2
    evaluated directly, and the gradient matches central differences."""
    keys = turn_and_swing(slab, velocity=(0.0, 1.5, 0.0))
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    anim = problem.solve(keys, warped=True, tolerance=1e-6, max_iterations=100)
    ab, f, c = problem._assemble_energy(anim.nodes)
    kfs = [kf.checked(slab, 0.0, 1.2) for kf in keys]
    obj = WarpedObjective(problem, kfs, anim.nodes, ab, f, c, coarse=True)
    assert obj._batches and all(key.gram for key in obj.keys)
    rng = np.random.default_rng(3)
    z = np.stack([anim.values, anim.velocities], axis=1).ravel()
    z = z + 0.05 * np.abs(z).max() * rng.standard_normal(z.size)
    cw, r = slab.coarse_warp, slab.r
    Z = z.reshape(-1, 2, r)
    direct = 0.5 * z @ solve_module._band_matvec(ab, ab.shape[0] - 1, z) + f @ z + c
    for key in obj.keys:
        q, v = Z[key.node, 0], Z[key.node, 1]
        u = (cw.basis_c.reshape(-1, r) @ q).reshape(1, -1, 3)
        if key.d is not None:
            res = key.S @ cw.warp_c.apply(u)[0] - key.d
            direct += 0.5 * key.wA**2 * np.vdot(res, res)
        if key.b is not None:
            du = (cw.basis_c.reshape(-1, r) @ v).reshape(1, -1, 3)
            res = key.S @ cw.warp_c.jvp(u, du)[0] - key.b
            direct += 0.5 * key.wB**2 * np.vdot(res, res)
    F, g = obj.value_and_gradient(z)
    assert abs(F - direct) <= 1e-10 * abs(direct)
    for _ in range(3):
        d = rng.standard_normal(z.size)
        h = 1e-6 * np.abs(z).max() / np.abs(d).max()
        slope = (obj.value(z + h * d) - obj.value(z - h * d)) / (2 * h)
        assert abs(g @ d) > 1e-3 * np.linalg.norm(g) * np.linalg.norm(d)  # a generic direction
        assert abs(g @ d - slope) <= 1e-7 * abs(slope)  # measured ~1e-9: O(h^2) and roundoff
