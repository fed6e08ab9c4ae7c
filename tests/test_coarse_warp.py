"""The coarse warp level W~ = P W_c(R u) and the two-level warped solve (Schulz et al. 2014,
Theorem 2).

W~ stands in for W in the first level of the solve and in the fine level's Newton matrices;
these tests check the mathematics it must keep (rigid motions exactly, derivatives
consistent with the map, a transfer that exists for every coarse mesh) and that the
two-level solve reaches a stationary point of the *fine* problem.
"""

from __future__ import annotations

import importlib
import itertools

import numpy as np
import pytest
import trimesh
from scipy.linalg import expm

import wiggly.body as body_module
from wiggly.keyframes import Keyframe
from wiggly.mesh import Surface, TetMesh, coarse_mesh, embed, tetrahedralize
from wiggly.primitives import box_mesh
from wiggly.solve import SolveOptions, SpacetimeProblem, WarpedObjective
from wiggly.solve.banded import band_matvec
from wiggly.warp import Warp, coarse_level

from .conftest import generic_direction, make_body


@pytest.fixture(scope="module")
def slab(tmp_path_factory):
    """A free 1 m x 0.25 m x 0.25 m bar of 24 x 6 x 6 cubes (5184 tets), 16 modes, with a
    coarse level of about 400 tets (fTetWild)."""
    body = make_body(tmp_path_factory, shape=(24, 6, 6), size=(1.0, 0.25, 0.25), n_modes=16)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(body_module, "COARSE_WARP_ABOVE", 1000)
        mp.setattr(body_module, "COARSE_TETS", 400)
        assert not body.coarse_level.exact
    return body


def skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


def level_of(fine: TetMesh, coarse: TetMesh, warp: Warp, basis: np.ndarray):
    return coarse_level(
        warp, coarse.vertices, coarse.tets,
        lift=embed(fine.vertices, coarse).matrix(coarse.n_vertices),
        interpolation=embed(coarse.vertices, fine).matrix(fine.n_vertices),
        basis=basis,
    )


def assert_keeps_rigid_motions(level, X, m):
    """R and P reproduce affine fields, and W~ of a linearized rotation is the exact
    rotation about the fine mass centre (like W)."""
    c_m = m @ X / m.sum()
    rng = np.random.default_rng(2)
    A, b = rng.standard_normal((3, 3)), rng.standard_normal(3)
    affine = X @ A.T + b
    restricted = level.transfer.restrict(affine[None])[0]
    coarse_X = level.warp.gradient.shape[1]
    assert restricted.shape == (coarse_X, 3)
    lifted = level.transfer.lift_fields(restricted[None])[0]
    assert np.abs(lifted - affine).max() < 1e-9 * np.abs(affine).max()
    for degrees in (10.0, 90.0, 170.0):
        w = np.radians(degrees) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        u = (X - c_m) @ skew(w).T + np.array([0.1, -0.2, 0.05])
        exact = (X - c_m) @ expm(skew(w)).T + c_m + np.array([0.1, -0.2, 0.05]) - X
        assert np.abs(level.apply(u[None])[0] - exact).max() < 1e-9 * np.abs(exact).max()


def test_coarse_mesh_is_coarser_and_covers_the_solid(slab):
    fine = slab.tets
    coarse = coarse_mesh(fine, 400, cache_dir=False)
    assert coarse.n_tets < fine.n_tets / 4
    assert embed(fine.vertices, coarse).barycentric.min() > -0.5
    assert abs(coarse.volumes().sum() / fine.volumes().sum() - 1) < 0.05


def test_coarse_level_keeps_rigid_motions(slab):
    level = slab.coarse_level
    assert_keeps_rigid_motions(level, slab.tets.vertices, slab.vertex_masses("tets"))
    u = (slab.modes.vectors @ np.linspace(-0.2, 0.2, slab.r)).reshape(1, -1, 3)
    np.testing.assert_allclose(slab.fine_level.apply(u), slab.warp.apply(u), atol=1e-14)


def test_coarse_level_derivatives_are_consistent(slab):
    """vjp is the adjoint of jvp, jvp is the derivative of W~ (central differences), and the
    coarse Jacobians lifted by P are the jvp along every mode."""
    level = slab.coarse_level
    Phi = slab.modes.vectors
    n, r = slab.tets.n_vertices, slab.r
    rng = np.random.default_rng(7)
    q = rng.standard_normal(r) * 0.3
    u = (Phi @ q).reshape(1, n, 3)
    du = (Phi @ rng.standard_normal(r)).reshape(1, n, 3)
    y = rng.standard_normal((1, n, 3))
    jvp = level.jvp(u, du)
    assert abs(np.vdot(level.vjp(u, y), du) - np.vdot(y, jvp)) < 1e-11 * np.linalg.norm(
        y
    ) * np.linalg.norm(jvp)
    h = 1e-6
    fd = (level.apply(u + h * du) - level.apply(u - h * du)) / (2 * h)
    assert np.linalg.norm(fd - jvp) < 1e-7 * np.linalg.norm(jvp)
    J = level.modal.jacobians(q[None])[0]  # (n_c, 3, r) on the coarse mesh
    lifted = level.transfer.lift_fields(J.transpose(2, 0, 1)).transpose(1, 2, 0)
    for i in (0, 7, r - 1):
        along = level.jvp(u, Phi[:, i].reshape(1, n, 3))[0]
        assert np.linalg.norm(lifted[:, :, i] - along) < 1e-10 * np.linalg.norm(along)


def test_transfer_exists_when_coarse_vertices_carry_no_fine_vertex():
    """A coarse mesh reaching beyond the fine solid: some coarse vertices have no fine vertex
    in their tets, so the plain projection (P^T M P)^-1 P^T M is singular.  The transfer's
    pull toward the interpolated field makes it positive definite, and it still reproduces
    affine fields and rigid motions exactly."""
    V, T = box_mesh((10, 2, 2), (1.0, 0.1, 0.1))
    fine = TetMesh(V, T)
    Vc, Tc = box_mesh((3, 1, 1), (1.5, 0.3, 0.3), origin=(-0.1, -0.1, -0.1))
    coarse = TetMesh(Vc, Tc)
    lift = embed(V, coarse).matrix(coarse.n_vertices)
    assert (np.asarray(abs(lift).sum(axis=0)).ravel() == 0).any()  # the singular case
    warp = Warp(V, T)
    basis = np.random.default_rng(0).standard_normal((len(V), 3, 6))
    level = level_of(fine, coarse, warp, basis)
    assert np.all(np.isfinite(level.modal.basis))
    assert_keeps_rigid_motions(level, V, warp.masses)


def fine_bodies():
    """Fine tet meshes of different shapes: a bar, a sphere, a torus (fTetWild)."""
    V, T = box_mesh((24, 6, 6), (1.0, 0.25, 0.25))
    yield TetMesh(V, T)
    for mesh in (trimesh.creation.icosphere(3, 0.5), trimesh.creation.torus(0.5, 0.18)):
        yield tetrahedralize(Surface(mesh.vertices, mesh.faces), resolution=12, cache_dir=False)


def test_twenty_fresh_coarse_meshes_give_working_levels():
    """fTetWild's coarse meshes differ from run to run; 21 fresh ones (7 per shape) all give a
    transfer (none singular), keep rigid motions exactly, and have finite restricted modes."""
    count = 0
    for fine in fine_bodies():
        warp = Warp(fine.vertices, fine.tets)
        basis = np.random.default_rng(1).standard_normal((fine.n_vertices, 3, 6))
        for _ in range(7):
            coarse = coarse_mesh(fine, max(200, fine.n_tets // 8), cache_dir=False)
            assert coarse is not None
            level = level_of(fine, coarse, warp, basis)
            assert np.all(np.isfinite(level.modal.basis))
            assert_keeps_rigid_motions(level, fine.vertices, warp.masses)
            count += 1
    assert count >= 20


def turn_and_swing(body, velocity=None):
    X = body.rest_positions()
    allv = np.arange(len(X))
    tip = np.flatnonzero(X[:, 0] > 0.8)
    return [
        Keyframe.rest(body, 0.0, allv, still=velocity is not None),
        Keyframe.rigid(body, 0.6, allv, rotation=(0, np.radians(100.0), 0)),
        Keyframe.offset(body, 1.0, tip, (0.0, 0.3, 0.0), velocity=velocity),
    ]


def assert_stationary(anim, tol):
    """Central-difference slopes of the fine E + E_WC obey the Newton-decrement bound
    |g.d| <= sqrt(2 tol F d^T H d), and match the gradient."""
    problem = SpacetimeProblem(anim.body, anim.start, anim.end)
    obj = WarpedObjective(problem, anim.body.fine_level, anim.keyframes, anim.nodes)
    z = np.stack([anim.values, anim.velocities], axis=1).ravel()
    point = obj.evaluate(z)
    F, g = point.F, point.g
    rng = np.random.default_rng(5)
    for _ in range(2):
        d = rng.standard_normal(z.size) * np.abs(z).max()
        h = 1e-5
        slope = (obj.evaluate(z + h * d).F - obj.evaluate(z - h * d).F) / (2 * h)
        curvature = (obj.evaluate(z + 1e-4 * d).F - 2 * F + obj.evaluate(z - 1e-4 * d).F) / 1e-8
        noise = 1e-15 * F / h
        assert abs(slope) <= 2 * np.sqrt(2 * tol * F * curvature) + noise
        assert abs(g @ d - slope) <= 1e-4 * np.sqrt(F * curvature) + noise


@pytest.mark.parametrize("velocity", [None, (0.0, 1.5, 0.0)], ids=["positions", "velocity"])
def test_two_level_solve_reaches_the_fine_stationary_point(slab, velocity):
    """The coarse first level and the coarse Newton matrices change the path, never the
    solution: the result is stationary for the fine E + E_WC and equals the solution of the
    one-level solve with exact Newton matrices."""
    keys = turn_and_swing(slab, velocity)
    tol = 1e-11
    two = SpacetimeProblem(slab, 0.0, 1.2).solve(
        keys, warped=True, options=SolveOptions(tolerance=tol)
    )
    one = SpacetimeProblem(slab, 0.0, 1.2).solve(
        keys, warped=True, options=SolveOptions(tolerance=tol, two_level=False)
    )
    assert two.info["converged"] and two.info["coarse"]["iterations"] >= 1
    assert one.info["converged"] and "coarse" not in one.info
    z2 = np.stack([two.values, two.velocities], axis=1).ravel()
    z1 = np.stack([one.values, one.velocities], axis=1).ravel()
    assert np.abs(z2 - z1).max() < 1e-5 * np.abs(z1).max()
    assert_stationary(two, tol)



def test_a_coarse_mesh_that_is_no_coarser_is_not_used(slab, monkeypatch):
    """fTetWild keeps thin parts at the fine edge length, so a body's "coarse" mesh can have
    more tets than the body (the camel's: 27.6k for 7.9k).  A coarse level with more than
    ``COARSER`` of the fine tets is then skipped: the solve runs on the fine level alone,
    with exact Newton matrices, and reaches the same stationary point."""
    levels = importlib.import_module("wiggly.solve.levels")
    keys = turn_and_swing(slab)
    share = slab.coarse_level.warp.n_tets / slab.fine_level.warp.n_tets
    assert 0 < share < levels.COARSER  # the slab's coarse mesh is coarser: two levels
    used = SpacetimeProblem(slab, 0.0, 1.2).solve(keys, warped=True)
    assert "coarse" in used.info
    monkeypatch.setattr(levels, "COARSER", 0.5 * share)  # now it counts as no coarser
    skipped = SpacetimeProblem(slab, 0.0, 1.2).solve(
        keys, warped=True, options=SolveOptions(tolerance=1e-11)
    )
    assert skipped.info["converged"] and "coarse" not in skipped.info
    assert skipped.info["exact_newton_from"] is None  # exact from the start: never switched
    assert_stationary(skipped, 1e-11)

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


def test_warm_start_after_an_edit_is_corrected_and_reaches_the_cold_solution(slab):
    """After one keyframe changes, the coarse level starts from the last fine point with the
    full-approximation-scheme correction (its gradient equals the fine one there): it needs
    fewer coarse iterations than a cold solve, and both end at the same fine stationary
    point."""
    keys = turn_and_swing(slab)
    options = SolveOptions(tolerance=1e-10)
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    prev = problem.solve(keys, warped=True, options=options)
    new = edited(keys)
    warm = problem.solve(new, warped=True, warm_start=prev.warm_start, options=options)
    cold = SpacetimeProblem(slab, 0.0, 1.2).solve(new, warped=True, options=options)
    assert warm.info["warm_start"] and warm.info["coarse"].get("corrected")
    assert warm.info["converged"] and cold.info["converged"]
    assert warm.info["coarse"]["iterations"] < cold.info["coarse"]["iterations"]
    assert_stationary(warm, 1e-10)
    zw = np.stack([warm.values, warm.velocities], axis=1).ravel()
    zc = np.stack([cold.values, cold.velocities], axis=1).ravel()
    assert np.abs(zw - zc).max() < 1e-4 * np.abs(zc).max()


def test_coarse_objective_is_the_coarse_warp_least_squares(slab):
    """The coarse level's objective equals its definition
    E + 1/2 sum c_A |S P W_c(R Phi q) - d|^2 + 1/2 sum c_B |S P DW_c(R Phi q)[R Phi q'] - b|^2
    evaluated directly, and its gradient matches central differences."""
    keys = turn_and_swing(slab, velocity=(0.0, 1.5, 0.0))
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    anim = problem.solve(keys, warped=True, options=SolveOptions(tolerance=1e-6))
    level = slab.coarse_level
    obj = WarpedObjective(problem, level, anim.keyframes, anim.nodes)
    rng = np.random.default_rng(3)
    z = np.stack([anim.values, anim.velocities], axis=1).ravel()
    z = z + 0.05 * np.abs(z).max() * rng.standard_normal(z.size)
    r = slab.r
    Z = z.reshape(-1, 2, r)
    energy = problem.energy(anim.nodes)
    direct = 0.5 * z @ band_matvec(energy.ab, z) + energy.f @ z + energy.c
    X = slab.rest_positions()
    for kf in anim.keyframes:
        k = int(np.argmin(np.abs(anim.nodes - kf.time)))
        c_A, c_B = kf.weights(slab, 1.2)
        S = slab.scalar_selection(kf.vertices, "surface")
        q, v = Z[k, 0], Z[k, 1]
        u = level.modal.displacements(q[None])
        moved = S @ level.transfer.lift_fields(level.warp.apply(u))[0]
        res = X[kf.vertices] + moved - kf.position
        direct += 0.5 * c_A * np.vdot(res, res)
        if kf.velocity is not None:
            du = level.modal.displacements(v[None])
            res = S @ level.transfer.lift_fields(level.warp.jvp(u, du))[0] - kf.velocity
            direct += 0.5 * c_B * np.vdot(res, res)
    point = obj.evaluate(z)
    assert abs(point.F - direct) <= 1e-10 * abs(direct)
    for _ in range(3):
        d = generic_direction(rng, point.g)
        h = 1e-6 * np.abs(z).max() / np.abs(d).max()
        slope = (obj.evaluate(z + h * d).F - obj.evaluate(z - h * d).F) / (2 * h)
        assert abs(point.g @ d - slope) <= 1e-7 * abs(slope)


def test_coarse_model_gauss_newton_matrix_is_exact_at_rest_and_first_order_near_it(slab):
    """The fine level's model Jacobians ``P DW_c(R u) R Phi + (Phi - P R Phi)`` equal the
    fine ``DW(u) Phi`` at rest (DW(0) = I on both meshes), so the model's Gauss-Newton matrix
    is the fine one there, and its error grows linearly with the motion (halving the states
    halves it).  Without the interpolation-error term the matrices differ at rest by the
    coarse mesh's error of the modes (1.2 % of the largest entry here)."""
    keys = turn_and_swing(slab, velocity=(0.0, 1.5, 0.0))
    problem = SpacetimeProblem(slab, 0.0, 1.2)
    anim = problem.solve(keys, warped=True)
    z_star = np.stack([anim.values, anim.velocities], axis=1).ravel()

    def gauss_newton(model, z):
        obj = WarpedObjective(problem, slab.fine_level, anim.keyframes, anim.nodes, model=model)
        return obj.newton_matrices(obj.evaluate(z), fresh=True)[0]

    scale = np.abs(gauss_newton(slab.fine_level, 0 * z_star)).max()
    rest = 0.0 * z_star
    at_rest = gauss_newton(slab.coarse_level, rest) - gauss_newton(slab.fine_level, rest)
    assert np.abs(at_rest).max() <= 1e-10 * scale
    errors = []
    for s in (0.04, 0.02, 0.01):
        z = s * z_star
        errors.append(
            np.abs(gauss_newton(slab.coarse_level, z) - gauss_newton(slab.fine_level, z)).max()
        )
    assert errors[0] > 1e-8 * scale  # the states move: the model is not exact there
    for a, b in itertools.pairwise(errors):
        assert 1.7 <= a / b <= 2.3, errors
