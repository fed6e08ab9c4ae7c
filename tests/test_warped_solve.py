"""The warped sparse spacetime solve (Schulz et al. 2014, Theorem 2): objective, Newton matrix,
stopping rule and solutions."""

from __future__ import annotations

import numpy as np
import pytest

from wiggly.keyframes import Keyframe
from wiggly.solve import (
    SolveOptions,
    SpacetimeProblem,
    WarpedObjective,
    WarpedSolveWarning,
    solve,
)
from wiggly.solve.banded import band_matvec, band_to_dense

from .conftest import generic_direction, make_body


@pytest.fixture(scope="module")
def free_bar(tmp_path_factory):
    return make_body(tmp_path_factory, shape=(10, 2, 2), n_modes=16)


@pytest.fixture(scope="module")
def tail(tmp_path_factory):
    """A slender 1 m x 5 cm x 5 cm bar ("tail") fixed at x = 0, stiff enough that its
    gravity sag is small."""
    from wiggly.primitives import box_mesh

    V, _ = box_mesh((20, 2, 2), (1.0, 0.05, 0.05))
    return make_body(
        tmp_path_factory,
        shape=(20, 2, 2),
        size=(1.0, 0.05, 0.05),
        n_modes=16,
        young=1e7,
        fixed=np.flatnonzero(V[:, 0] < 1e-9),
    )


def turn_keys(body, degrees=120.0):
    allv = np.arange(body.n_vertices())
    return [
        Keyframe.rest(body, 0.0, allv, still=True),
        Keyframe.rigid(body, 1.0, allv, rotation=(0, 0, np.radians(degrees))),
    ]


def velocity_keys(body):
    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.9)
    return [
        *turn_keys(body, 60.0),
        Keyframe.offset(body, 0.5, tip, (0, 0.2, 0), velocity=(0.0, 1.5, 0.5)),
    ]


def arc_bend(X, degrees, c=0.025):
    """Pure bending of a bar along x (base at x = 0, centreline z = c) into a circular arc
    toward +z turning the tip by ``degrees``: the natural large swing of a tail."""
    phi_tip = np.radians(degrees)
    rho = 1.0 / phi_tip  # arc length 1 m
    x, y, z = X.T
    d = z - c
    phi = x / rho
    return np.c_[(rho - d) * np.sin(phi), y, c + rho - (rho - d) * np.cos(phi)]


def swing_keys(body, degrees=90.0):
    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.8)
    return [Keyframe(1.0, tip, arc_bend(X[tip], degrees))]


def objective_at(anim, end=None):
    """The fine objective E + E_WC of ``anim``'s problem, and ``anim``'s unknowns z."""
    problem = SpacetimeProblem(anim.body, anim.start, anim.end if end is None else end)
    obj = WarpedObjective(problem, anim.body.fine_level, anim.keyframes, anim.nodes)
    return obj, np.stack([anim.values, anim.velocities], axis=1).ravel()


def edge_and_volume_change(body, P):
    T = body.tets.tets
    X = body.tets.vertices
    e = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    L0 = np.linalg.norm(X[T[:, e[:, 0]]] - X[T[:, e[:, 1]]], axis=-1)
    L1 = np.linalg.norm(P[T[:, e[:, 0]]] - P[T[:, e[:, 1]]], axis=-1)

    def vol(Y):
        d = Y[T[:, 1:]] - Y[T[:, :1]]
        return np.linalg.det(d)

    return np.max(np.abs(L1 / L0 - 1)), np.max(np.abs(vol(P) / vol(X) - 1))


@pytest.mark.parametrize("which", ["turn", "swing", "velocity"])
def test_warped_solution_is_stationary(free_bar, tail, which):
    """At the solution the gradient of E + E_WC vanishes to the solver tolerance: for random
    directions d, the central-difference slope obeys |g.d| <= sqrt(2 tol F d^T H d) (the
    Newton-decrement bound), while at the linear solution it is far larger."""
    body, keys = {
        "turn": (free_bar, turn_keys(free_bar)),
        "swing": (tail, swing_keys(tail)),
        "velocity": (free_bar, velocity_keys(free_bar)),
    }[which]
    tol = 1e-12
    problem = SpacetimeProblem(body, 0.0, 1.5)
    anim = problem.solve(keys, warped=True, options=SolveOptions(tolerance=tol))
    assert anim.info["converged"]
    lin = solve(body, keys, end=1.5, warp=False)
    obj, z = objective_at(anim)
    _, z_lin = objective_at(lin)
    F = obj.evaluate(z).F
    rng = np.random.default_rng(3)

    def value(x):
        return obj.evaluate(x).F

    def slope(x, d, h=1e-5):  # Richardson-extrapolated central difference, O(h^4)
        s1 = (value(x + h * d) - value(x - h * d)) / (2 * h)
        s2 = (value(x + h / 2 * d) - value(x - h / 2 * d)) / h
        return (4 * s2 - s1) / 3

    for _ in range(3):
        d = rng.standard_normal(z.size) * np.abs(z).max()
        h = 1e-4
        curvature = (value(z + h * d) - 2 * F + value(z - h * d)) / h**2
        s, s_lin = slope(z, d), slope(z_lin, d)
        noise = 1e-15 * F / 1e-5  # rounding in the differences
        assert abs(s) <= 2 * np.sqrt(2 * tol * F * curvature) + noise, (s, curvature)
        assert abs(s_lin) > 1e3 * abs(s)


@pytest.mark.parametrize("which", ["positions", "velocities"])
def test_newton_matrix_is_the_hessian(free_bar, which):
    """With the fine level's own derivatives, the Newton matrix is the Hessian of E + E_WC:
    its constrained-node blocks equal central differences of the exact gradient (Richardson
    extrapolated), including the curvature Gauss-Newton omits, which is large here."""
    keys = turn_keys(free_bar, 90.0) if which == "positions" else velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    kfs = problem.checked(keys)
    nodes = problem.nodes_for(kfs)
    z = problem.solve_linear(kfs, nodes)  # far from the warped solution: large residuals
    obj = WarpedObjective(problem, free_bar.fine_level, kfs, nodes)
    gauss_newton, newton = (band_to_dense(m) for m in obj.newton_matrices(obj.evaluate(z))[:2])
    r = free_bar.r

    def hessian_column(i, h):
        e = np.zeros_like(z)
        e[i] = h
        return (obj.evaluate(z + e).g - obj.evaluate(z - e).g) / (2 * h)

    omitted = []
    for k in obj.active:
        idx = 2 * r * k + np.arange(2 * r)
        H = np.stack(
            [(4 * hessian_column(i, 5e-5) - hessian_column(i, 1e-4)) / 3 for i in idx], axis=1
        )[idx]
        scale = np.abs(H).max()
        assert np.abs(newton[np.ix_(idx, idx)] - H).max() < 1e-6 * scale
        omitted.append(np.abs(gauss_newton[np.ix_(idx, idx)] - H).max() / scale)
    assert max(omitted) > 1e-2


def test_warped_meets_a_large_turn_better_than_linear(free_bar):
    lin = solve(free_bar, turn_keys(free_bar), end=1.5, warp=False).constraint_residuals()[-1]
    war = solve(free_bar, turn_keys(free_bar), end=1.5, warp=True).constraint_residuals()[-1]
    assert war["position_rms"] < 0.01 * lin["position_rms"]
    assert war["position_rms"] < 1e-3


@pytest.mark.parametrize("steps, turns", [(3, 1), (4, 1), (6, 1), (5, 2)])
def test_a_turn_keyed_in_steps_keeps_its_direction(free_bar, steps, turns):
    """The whole bar keyed at rest, then turned by 360 * turns / steps degrees more at each
    of ``steps`` keys: consecutive poses are taken the short way (each step is below 180
    degrees), so the bar turns one way through the full 360 * turns, never back, and meets
    every key."""
    X = free_bar.rest_positions()
    allv = np.arange(len(X))
    step = 2 * np.pi * turns / steps
    keys = [Keyframe.rest(free_bar, 0.0, allv, still=True)] + [
        Keyframe.rigid(free_bar, i / steps, allv, rotation=(0, 0, i * step))
        for i in range(1, steps + 1)]
    anim = solve(free_bar, keys, end=1.0, warp=True)
    t = np.linspace(0.0, 1.0, 8 * steps + 1)
    P = anim.positions(t)
    tip, root = X[:, 0] > 0.9, X[:, 0] < 0.1
    axis = P[:, tip].mean(axis=1) - P[:, root].mean(axis=1)
    angle = np.unwrap(np.arctan2(axis[:, 1], axis[:, 0]))
    assert np.all(np.diff(angle) > -0.02), np.degrees(angle).round()
    assert angle[-1] - angle[0] == pytest.approx(2 * np.pi * turns, abs=0.02)
    assert max(r["position_max"] for r in anim.constraint_residuals()) < 0.01


def test_warping_keeps_every_tet_in_a_large_turn_while_linear_distorts(free_bar):
    """A rigid 120 degree turn: no strain at all, so every edge and tet volume is kept."""
    body, keys = free_bar, turn_keys(free_bar)
    t = np.linspace(0, 1.5, 16)
    lin = solve(body, keys, end=1.5, warp=False).positions(t, "tets")
    war = solve(body, keys, end=1.5, warp=True).positions(t, "tets")
    lin_edge, lin_vol = np.max([edge_and_volume_change(body, P) for P in lin], axis=0)
    war_edge, war_vol = np.max([edge_and_volume_change(body, P) for P in war], axis=0)
    assert lin_edge > 0.2 and lin_vol > 0.2  # the linear motion distorts visibly
    assert war_edge < 0.01 and war_vol < 0.01


def test_swung_tail_keeps_its_length_and_volume_while_linear_grows(tail):
    """A tail bent by 90 degrees has real bending strain (+-kappa h/2 ~ 4 %) but must not
    grow: total volume and centreline length stay within 2 %; the linear one grows."""
    body, keys = tail, swing_keys(tail)
    X, T = body.tets.vertices, body.tets.tets
    centre = np.flatnonzero((np.abs(X[:, 1] - 0.025) < 1e-9) & (np.abs(X[:, 2] - 0.025) < 1e-9))
    centre = centre[np.argsort(X[centre, 0])]

    def growth(P):
        d = P[T[:, 1:]] - P[T[:, :1]]
        vol = np.linalg.det(d).sum() / np.linalg.det(X[T[:, 1:]] - X[T[:, :1]]).sum()
        length = np.linalg.norm(np.diff(P[centre], axis=0), axis=1).sum()
        return abs(vol - 1), abs(length - 1.0)

    t = np.linspace(0, 1.5, 16)
    war = solve(body, keys, end=1.5, warp=True)
    lin = solve(body, keys, end=1.5, warp=False)
    war_growth = np.max([growth(P) for P in war.positions(t, "tets")], axis=0)
    lin_growth = np.max([growth(P) for P in lin.positions(t, "tets")], axis=0)
    assert np.all(war_growth < 0.02), war_growth
    assert lin_growth[0] > 0.2 and lin_growth[1] > 0.1, lin_growth
    assert (
        war.constraint_residuals()[0]["position_rms"]
        < 0.1 * lin.constraint_residuals()[0]["position_rms"]
    )


def test_warped_velocity_is_the_time_derivative_of_warped_positions(free_bar):
    anim = solve(free_bar, turn_keys(free_bar, 90.0), end=1.5, warp=True)
    t, h = 0.63, 1e-5
    P = anim.positions([t - h, t + h])
    V = anim.velocities_at([t])[0]
    fd = (P[1] - P[0]) / (2 * h)
    assert np.max(np.abs(fd - V)) < 1e-6 * np.max(np.abs(V))


def test_non_convergence_is_reported_honestly(free_bar):
    """A solve stopped early says so: converged is False, a warning gives the decrement."""
    keys = velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    with pytest.warns(WarpedSolveWarning, match="did not converge in 1 iteration "):
        anim = problem.solve(keys, warped=True, options=SolveOptions(max_iterations=1))
    assert anim.info["converged"] is False and anim.info["iterations"] == 1
    assert anim.info["newton_decrement"] > 1e-8 * anim.info["objective"]


def test_the_callback_sees_every_iteration_and_can_end_the_solve(free_bar):
    """``SolveOptions.callback`` is called with the iteration count after each iteration; an
    exception it raises ends the solve and reaches the caller (the editor's refinement
    abandons an outdated request so); without one, the same solve runs to convergence."""
    keys = velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    seen = []
    anim = problem.solve(keys, warped=True, options=SolveOptions(callback=seen.append))
    assert anim.info["converged"] and seen == list(range(1, len(seen) + 1))
    assert len(seen) >= anim.info["iterations"] >= 2

    class Stop(Exception):
        pass

    def stop_at_two(count):
        if count == 2:
            raise Stop

    with pytest.raises(Stop):
        problem.solve(keys, warped=True, options=SolveOptions(callback=stop_at_two))


def test_convergence_means_the_stopping_rule_holds_and_bounds_the_distance(free_bar):
    """``converged`` is reported only when the Newton decrement meets the tolerance, and the
    reported distance bound (largest vertex move of the final Newton step, m) bounds the
    distance to the minimiser, computed here by a solve to round-off."""
    keys = velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    loose = problem.solve(keys, warped=True, options=SolveOptions(tolerance=1e-6))
    exact = problem.solve(keys, warped=True, options=SolveOptions(tolerance=1e-15))
    info = loose.info
    assert info["converged"] and info["newton_decrement"] <= 1e-6 * info["objective"] + 1e-9
    _, z = objective_at(loose)
    _, z_star = objective_at(exact)
    dq = (z - z_star).reshape(-1, 2, free_bar.r)[:, 0]
    moved = np.linalg.norm((free_bar.modes.vectors @ dq.T).reshape(-1, 3, len(dq)), axis=1)
    assert moved.max() <= info["distance_bound"]


def test_a_body_at_rest_converges(free_bar):
    """Keyframes at rest without gravity: the objective is zero up to rounding, and the
    stopping rule (decrement <= tol F + F's rounding level) says converged."""
    from wiggly.body import prepare

    body = prepare(
        free_bar.model, material=free_bar.material, damping=free_bar.damping,
        gravity=(0.0, 0.0, 0.0), n_modes=free_bar.r, cache_dir=False,
    )
    allv = np.arange(body.n_vertices())
    keys = [Keyframe.rest(body, t, allv, still=True) for t in (0.0, 0.5, 1.0)]
    anim = SpacetimeProblem(body, 0.0, 1.0).solve(keys, warped=True)
    assert anim.info["converged"]
    assert abs(anim.info["objective"]) < 1e-10


def test_warm_start_after_an_edit_reaches_the_cold_solution(free_bar):
    keys = velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    tight = SolveOptions(tolerance=1e-13)
    first = problem.solve(keys, warped=True, options=tight)
    keys[1] = Keyframe.rigid(free_bar, 1.0, keys[1].vertices, rotation=(0, 0, np.radians(65)))
    second = problem.solve(keys, warped=True, warm_start=first.warm_start, options=tight)
    cold = SpacetimeProblem(free_bar, 0.0, 1.5).solve(keys, warped=True, options=tight)
    assert second.info["warm_start"] and second.info["converged"]
    assert second.info["iterations"] < cold.info["iterations"]
    # both are within their distance bounds (m, largest vertex move at a node) of the minimiser
    dq = second.values - cold.values
    moved = np.linalg.norm((free_bar.modes.vectors @ dq.T).reshape(-1, 3, len(dq)), axis=1)
    assert moved.max() <= second.info["distance_bound"] + cold.info["distance_bound"]


def test_keyframe_changed_in_place_between_solves_is_seen(free_bar):
    """A keyframe's target array edited in place (same object) poses a new problem: the next
    solve of the same problem equals a fresh problem's solve, not the kept targets'."""
    keys = turn_keys(free_bar, degrees=60.0)
    problem = SpacetimeProblem(free_bar, 0.0, 1.2)
    options = SolveOptions(tolerance=1e-12)
    before = problem.solve(keys, warped=True, options=options)
    keys[1].position[:] += np.array([0.0, 0.2, 0.0])  # in place: same array, same Keyframe
    again = problem.solve(keys, warped=True, options=options)
    fresh = SpacetimeProblem(free_bar, 0.0, 1.2).solve(keys, warped=True, options=options)
    assert np.abs(again.values - before.values).max() > 1e-2 * np.abs(before.values).max()
    np.testing.assert_allclose(again.values, fresh.values, atol=1e-9 * np.abs(fresh.values).max())


@pytest.fixture(scope="module")
def embedded_bar():
    """A free 1 m x 0.1 m x 0.1 m bar of 10 x 2 x 2 cubes with a finer box surface embedded
    in it (1.5k vertices): the surface's targets are not fitted exactly by vertex values."""
    import trimesh

    from wiggly.body import Damping, prepare
    from wiggly.fem import Material
    from wiggly.mesh import Model, Surface, TetMesh, embed
    from wiggly.primitives import box_mesh

    size = np.array([1.0, 0.1, 0.1])
    V, T = box_mesh((10, 2, 2), tuple(size))
    tets = TetMesh(V, T)
    box = trimesh.creation.box(extents=size)
    v, f = trimesh.remesh.subdivide_to_size(box.vertices + size / 2, box.faces, 0.02)
    surface = Surface(v * (1 - 1e-9) + size * 0.5e-9, f)
    model = Model(surface, tets, embed(surface.vertices, tets), source="embedded bar")
    body = prepare(
        model, material=Material(1e5, 0.3, 1000.0), damping=Damping(0.5, 0.002), n_modes=16,
        cache_dir=False,
    )
    assert body.surface.n_vertices > 2 * body.tets.n_vertices
    return body


def test_fine_objective_is_the_warped_least_squares(embedded_bar):
    """The objective equals its definition E + 1/2 sum c_A |S W(Phi q) - d|^2 + 1/2 sum c_B
    |S DW[Phi q'] - b|^2 evaluated directly on the embedded surface, at and far from the
    solution, and its gradient matches central differences."""
    body = embedded_bar
    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.7)
    ripple = 0.01 * np.sin(40.0 * X[tip])  # finer than the tets: no vertex values fit it
    keys = [
        *turn_keys(body, degrees=80.0),
        Keyframe(0.5, tip, X[tip] + [0.0, 0.3, 0.1] + ripple, velocity=(0.5, 0.0, 0.0)),
        Keyframe(0.8, tip, X[tip] + [0.1, -0.2, 0.0] - ripple),
    ]
    problem = SpacetimeProblem(body, 0.0, 1.2)
    anim = problem.solve(keys, warped=True)
    obj, z0 = objective_at(anim)
    energy = problem.energy(anim.nodes)
    rng = np.random.default_rng(4)
    r, n = body.r, body.n_vertices("tets")
    Phi = body.modes.vectors
    E = body.surface_embedding
    for scale in (0.0, 0.02, 1.0):  # at the solution, near it, and far from it
        z = z0 + scale * np.abs(z0).max() * rng.standard_normal(z0.size)
        Z = z.reshape(-1, 2, r)
        direct = 0.5 * z @ band_matvec(energy.ab, z) + energy.f @ z + energy.c
        for kf in anim.keyframes:
            k = int(np.argmin(np.abs(anim.nodes - kf.time)))
            c_A, c_B = kf.weights(body, 1.2)
            u = (Phi @ Z[k, 0]).reshape(n, 3)
            res = X[kf.vertices] + (E @ body.warp.apply(u))[kf.vertices] - kf.position
            direct += 0.5 * c_A * np.vdot(res, res)
            if kf.velocity is not None:
                du = (Phi @ Z[k, 1]).reshape(n, 3)
                res = (E @ body.warp.jvp(u, du))[kf.vertices] - kf.velocity
                direct += 0.5 * c_B * np.vdot(res, res)
        point = obj.evaluate(z)
        assert abs(point.F - direct) <= 1e-12 * abs(direct), (scale, point.F, direct)
    g = point.g
    d = generic_direction(rng, g)
    h = 1e-6 * np.abs(z).max() / np.abs(d).max()
    slope = (obj.evaluate(z + h * d).F - obj.evaluate(z - h * d).F) / (2 * h)
    assert abs(g @ d - slope) <= 1e-7 * abs(slope)


def test_edited_objective_at_the_last_point_pulls_back_only_changed_cotangents(free_bar):
    """A warm start evaluates the edited objective at the last point from its W values and
    pull-backs (DW^T is linear in the cotangent): the same value and gradient as a fresh
    evaluation, with one node pulled back."""
    keys = velocity_keys(free_bar)
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    anim = problem.solve(keys, warped=True)
    kfs = problem.checked(keys)
    kfs[1] = Keyframe.rigid(free_bar, 1.0, kfs[1].vertices, rotation=(0, 0, np.radians(70)))
    kept = WarpedObjective(problem, free_bar.fine_level, kfs, anim.nodes)
    z = anim.warm_start.z
    point = kept.evaluate(z, prior=anim.warm_start.point)
    assert kept.counts["W"] == 0 and kept.counts["vjp"] == 1
    fresh = WarpedObjective(problem, free_bar.fine_level, kfs, anim.nodes).evaluate(z)
    assert abs(point.F - fresh.F) <= 1e-12 * fresh.F
    assert np.abs(point.g - fresh.g).max() <= 1e-9 * np.abs(fresh.g).max()
    assert np.abs(fresh.g).max() > 1e-3 * np.abs(anim.warm_start.point.g).max() + 1e-6


def test_unwarped_targets_linearize_each_keyframes_rotation(free_bar):
    """``unwarped`` replaces a keyframe's best-fit rotation R (about its targets' centroid) by
    its rotation vector: rigidly turned and moved targets x = R (X - c) + c' + e become
    X + w x (X - c) + (c' - c) + R^T e, with velocities turned back by R^T; keyframes of one
    group are fitted together and agree with fitting each alone; groups of fewer than 3 or
    collinear vertices keep their targets."""
    from scipy.spatial.transform import Rotation

    from wiggly.solve.problem import unwarped

    X = free_bar.rest_positions()
    group = np.flatnonzero(X[:, 0] > 0.5)
    rng = np.random.default_rng(4)
    A = X[group] - X[group].mean(axis=0)
    keys, expected = [], []
    for k in range(4):
        w = rng.uniform(-1.5, 1.5, 3)  # up to about 150 degrees
        R = Rotation.from_rotvec(w).as_matrix()
        e = 0.01 * rng.standard_normal(A.shape)
        move = rng.standard_normal(3)
        velocity = rng.standard_normal(A.shape)
        position = A @ R.T + X[group].mean(axis=0) + move + e
        keys.append(Keyframe(0.2 * (k + 1), group, position, velocity))
        # the targets' own best-fit rotation is R only for e = 0: use the exact Kabsch R
        B = position - position.mean(axis=0)
        U, _, Vt = np.linalg.svd(B.T @ A)
        R_fit = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        w_fit = Rotation.from_matrix(R_fit).as_rotvec()
        residual = B - A @ R_fit.T
        expected.append((
            X[group] + np.cross(w_fit, A) + (position.mean(axis=0) - X[group].mean(axis=0))
            + residual @ R_fit,
            velocity @ R_fit,
        ))
    line = np.flatnonzero((np.abs(X[:, 1] - X[0, 1]) < 1e-9) & (np.abs(X[:, 2] - X[0, 2]) < 1e-9))
    assert len(line) >= 3
    keys.append(Keyframe(0.9, line, X[line] + 0.1, None))
    keys.append(Keyframe(1.0, group[:2], X[group[:2]] + 0.1, None))
    keys = [kf.checked(free_bar, 0.0, 1.0) for kf in keys]
    out = unwarped(keys, free_bar)
    for kf, (position, velocity) in zip(out, expected, strict=False):
        np.testing.assert_allclose(kf.position, position, atol=1e-12)
        np.testing.assert_allclose(kf.velocity, velocity, atol=1e-12)
    for a, kf in enumerate(keys):
        alone = unwarped([kf], free_bar)[0]
        np.testing.assert_allclose(alone.position, out[a].position, atol=1e-12)
    assert out[4] is keys[4] and out[5] is keys[5]


def test_target_fits_give_the_least_squares_residual_alone_and_in_batches(free_bar):
    """``TargetFit.value_and_cotangent(x)`` is ``1/2 |S x - d|^2`` and ``S^T (S x - d)`` for
    any level values x; targets of one group are fitted in one batch (also a repeated
    target, and groups interleaved), each as it would be alone."""
    from wiggly.solve import SpacetimeProblem

    X = free_bar.rest_positions()
    groups = [np.flatnonzero(X[:, 0] > 0.6), np.flatnonzero(X[:, 0] < 0.2)]
    rng = np.random.default_rng(6)
    requests = []
    for a in range(5):
        g = groups[a % 2]
        requests.append((g, "surface", rng.standard_normal((len(g), 3))))
    requests.append(requests[0])
    requests.append((groups[1], "surface", np.array([0.0, 0.1, 0.0])))  # broadcast target
    level = free_bar.fine_level
    batch = SpacetimeProblem(free_bar, 0.0, 1.0).fits(level, requests)
    for req, fit in zip(requests, batch, strict=True):
        alone = SpacetimeProblem(free_bar, 0.0, 1.0).fits(level, [req])[0]
        S = free_bar.scalar_selection(req[0], "surface")
        d = np.broadcast_to(req[2], (len(req[0]), 3))
        x = rng.standard_normal((S.shape[1], 3))
        value, cotangent = fit.value_and_cotangent(x)
        r = S @ x - d
        assert abs(value - 0.5 * np.vdot(r, r)) <= 1e-12 * np.vdot(r, r)
        np.testing.assert_allclose(cotangent, S.T @ r, atol=1e-12 * np.abs(S.T @ r).max())
        np.testing.assert_allclose(fit.X, alone.X, atol=1e-13 * np.abs(alone.X).max())
        assert fit.F == pytest.approx(alone.F, rel=1e-12, abs=1e-15)


def test_second_order_correction_is_the_residuals_nonlinear_part_pulled_back(free_bar):
    """The second-order correction's right-hand side is ``J^T C m`` with ``m = r(z + dz) -
    r(z) - J dz`` (Nocedal & Wright, sec. 18.3): checked against the warp map alone (each
    keyframe's selection, W and DW[v], central differences for J), in random directions,
    and it is second order in the step."""
    problem = SpacetimeProblem(free_bar, 0.0, 1.5)
    kfs = problem.checked(velocity_keys(free_bar))
    nodes = problem.nodes_for(kfs)
    z = problem.solve_linear(kfs, nodes)
    obj = WarpedObjective(problem, free_bar.fine_level, kfs, nodes)
    layout, modal, warp = problem.layout(nodes), free_bar.fine_level.modal, free_bar.warp
    rng = np.random.default_rng(7)
    dz = 0.05 * rng.standard_normal(z.size) * np.abs(z).max()

    def residuals(x):
        """Each keyframe's weighted residual field sqrt(c) (S X - target) at its node."""
        q, v = layout.states(x)
        out = []
        for kf in kfs:
            k = layout.canonical(int(np.argmin(np.abs(nodes - kf.time))))
            c_A, c_B = kf.weights(free_bar, problem.duration)
            S = free_bar.scalar_selection(kf.vertices, kf.on)
            u = modal.displacements(q[k])[0]
            if kf.position is not None:
                out.append(np.sqrt(c_A) * (S @ warp.apply(u) - problem.offsets(kf)))
            if kf.velocity is not None:
                w = modal.displacements(v[k])[0]
                out.append(np.sqrt(c_B) * (S @ warp.jvp(u, w) - kf.velocity))
        return out

    def along(x, d, h=1e-5):
        plus, minus = residuals(x + h * d), residuals(x - h * d)
        return [(a - b) / (2 * h) for a, b in zip(plus, minus, strict=True)]

    def correction(step):
        return obj.correction_gradient(obj.evaluate(z), step, obj.evaluate(z + step))

    r0, r1, Jdz = residuals(z), residuals(z + dz), along(z, dz)
    m = [b - a - j for a, b, j in zip(r0, r1, Jdz, strict=True)]
    g = correction(dz)
    for _ in range(3):
        e = rng.standard_normal(z.size)
        expected = sum(float(np.vdot(je, mi)) for je, mi in zip(along(z, e), m, strict=True))
        assert abs(float(e @ g) - expected) <= 1e-3 * abs(expected)
    small = [np.linalg.norm(correction(s * dz)) for s in (0.02, 0.01)]
    assert small[1] / small[0] == pytest.approx(0.25, rel=0.05)


def test_constraint_residuals_sample_each_keyframe_at_its_time(free_bar):
    """Residuals are sampled in batches of frames (more keyframes than a batch here, on both
    meshes, with velocities): each row equals the motion sampled at that keyframe alone."""
    X = free_bar.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.9)
    Xt = free_bar.rest_positions("tets")
    root = np.flatnonzero(Xt[:, 0] < 0.1)
    rng = np.random.default_rng(3)
    keys = [Keyframe.rest(free_bar, 0.0, np.arange(len(X)), still=True)]
    for k, t in enumerate(np.linspace(0.02, 1.5, 70)):
        if k % 3 == 0:
            keys.append(Keyframe.offset(free_bar, t, root, rng.normal(0, 0.01, 3), on="tets"))
        else:
            keys.append(Keyframe.offset(free_bar, t, tip, rng.normal(0, 0.05, 3),
                                        velocity=rng.normal(0, 0.2, 3)))
    anim = solve(free_bar, keys, end=1.5, warp=True, options=SolveOptions(max_iterations=3,
                                                                          warn=False))
    rows = anim.constraint_residuals()
    assert len(rows) == len(anim.keyframes) > 64
    for row, kf in zip(rows, anim.keyframes, strict=True):
        assert row["time"] == kf.time
        x = anim.positions([kf.time], kf.on)[0][kf.vertices]
        d = np.linalg.norm(x - kf.position, axis=1)
        assert row["position_max"] == pytest.approx(d.max(), rel=1e-9, abs=1e-12)
        assert row["position_rms"] == pytest.approx(np.sqrt(np.mean(d**2)), rel=1e-9, abs=1e-12)
        if kf.velocity is not None:
            v = anim.velocities_at([kf.time], kf.on)[0][kf.vertices]
            e = np.linalg.norm(v - kf.velocity, axis=1)
            assert row["velocity_rms"] == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-9,
                                                        abs=1e-12)
        else:
            assert "velocity_rms" not in row


def test_keys_missed_by_a_python_solve_are_warned_about(free_bar, recwarn):
    """wiggly.solve says when its motion misses position keys by more than 5 % of the body's
    size, as `wiggly animate` does for scene files: a linear solve of a 120 degree turn
    stretches the bar off its key (the warning names the key and warp=True); the warped solve
    meets it and says nothing."""
    import warnings

    X = free_bar.rest_positions()
    allv = np.arange(len(X))
    keys = [Keyframe.rest(free_bar, 0.0, allv, still=True),
            Keyframe.rigid(free_bar, 1.0, allv, rotation=(0, 0, np.radians(120)), name="turn")]
    anim = solve(free_bar, keys, end=1.0, warp=False)
    size = float(np.linalg.norm(np.ptp(X, axis=0)))
    worst = max(r["position_max"] for r in anim.constraint_residuals())
    said = [str(w.message) for w in recwarn if "missed by more than" in str(w.message)]
    assert worst > 0.05 * size and len(said) == 1, said
    assert "keyframes[1] ('turn') at t = 1 s by" in said[0] and "warp=True" in said[0]
    recwarn.clear()
    with warnings.catch_warnings(record=True) as quiet:
        warnings.simplefilter("always")
        solve(free_bar, keys, end=1.0, warp=True)
        solve(free_bar, keys, end=1.0, warp=False, check_keys=False)
    assert not [w for w in quiet if "missed by more than" in str(w.message)]


def test_warped_playback_runs_blas_on_one_thread(free_bar, monkeypatch):
    """Idle OpenBLAS workers spin after each product and take the cores from the warp's
    compiled passes (1.6x slower playback on 2 cores): playback limits BLAS to one thread."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    anim = solve(free_bar, turn_keys(free_bar, 90.0), end=1.5, warp=True)
    warp, seen = free_bar.warp, []

    def blas_threads() -> list[int]:
        return [p["num_threads"] for p in threadpoolctl.threadpool_info()
                if p["user_api"] == "blas"]

    apply = warp.apply
    monkeypatch.setattr(warp, "apply", lambda U: (seen.extend(blas_threads()), apply(U))[1])
    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        outside = blas_threads()
        if not outside or max(outside) < 2:
            pytest.skip(f"BLAS does not run on 2 threads here ({outside})")
        anim.positions([0.3, 0.9])
        assert blas_threads() == outside
    assert seen and set(seen) == {1}
