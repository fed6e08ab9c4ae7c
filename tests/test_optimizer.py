"""The trust-region Newton method (:func:`wiggly.solve.optimizer.minimize`) on functions
with known minimisers: a quadratic, a nonconvex double well, and approximate matrices whose
convergence is certified by the measured contraction."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from wiggly.solve.banded import BandedCholesky, band_to_dense, dense_to_band
from wiggly.solve.optimizer import SolveOptions, SolveReport, minimize, steihaug


@dataclass(frozen=True)
class Point:
    z: np.ndarray
    F: float
    g: np.ndarray
    magnitude: float


class Toy:
    """An objective with analytic F, gradient and Hessian.  ``approximate(z)`` (if given)
    replaces the Hessian as the Newton matrix until :meth:`use_exact`; the Gauss-Newton
    matrix is ``gauss_newton(z)`` (default: the Hessian where it is positive definite, else
    the identity)."""

    size = 1.0

    def __init__(self, F, grad, hess, *, approximate=None, gauss_newton=None, magnitude=None):
        self.F, self.grad, self.hess = F, grad, hess
        self.approximate, self.gauss_newton = approximate, gauss_newton
        self.magnitude = magnitude or (lambda z: abs(F(z)))
        self.exact = approximate is None
        self.timing: dict = {}
        self.counts = {"evaluate": 0, "newton": 0}

    def evaluate(self, z, gradient=True):
        self.counts["evaluate"] += 1
        z = np.asarray(z, dtype=float)
        g = self.grad(z) if gradient else None
        return Point(z.copy(), float(self.F(z)), g, float(self.magnitude(z)))

    def with_gradient(self, point):
        return point if point.g is not None else Point(
            point.z, point.F, self.grad(point.z), point.magnitude
        )

    def newton_matrices(self, point, fresh=False):
        self.counts["newton"] += 1
        H = self.hess(point.z) if self.exact else self.approximate(point.z)
        if self.gauss_newton is not None:
            G = self.gauss_newton(point.z)
        else:
            G = H if np.linalg.eigvalsh(H).min() > 0 else np.eye(len(H))
        return dense_to_band(G), dense_to_band(H), True

    def use_exact(self):
        if self.exact:
            return False
        self.exact = True
        return True

    def step_size(self, dz):
        return float(np.abs(dz).max(initial=0.0))

    def correction_gradient(self, point, dz, trial):
        return None


def quadratic(A, b):
    return Toy(
        lambda z: 0.5 * z @ A @ z + b @ z,
        lambda z: A @ z + b,
        lambda z: A,
        magnitude=lambda z: abs(0.5 * z @ A @ z) + abs(b @ z),
    )


def spd(n, seed, condition=1e3):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    A = (Q * np.geomspace(1.0, condition, n)) @ Q.T
    return 0.5 * (A + A.T)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_quadratic_is_minimised_by_one_newton_step(seed):
    A = spd(12, seed)
    b = np.random.default_rng(seed + 10).standard_normal(12)
    toy = quadratic(A, b)
    point, report = minimize(toy, toy.evaluate(np.zeros(12)), SolveOptions())
    assert isinstance(report, SolveReport)
    assert report.converged and report.iterations == 1 and report.newton_steps == 1
    exact = np.linalg.solve(A, -b)
    assert np.abs(point.z - exact).max() <= 1e-10 * np.abs(exact).max()
    assert report.objective == pytest.approx(0.5 * b @ exact, rel=1e-12)
    assert report.distance_bound is not None
    assert np.abs(point.z - exact).max() <= report.distance_bound


def test_steihaug_follows_negative_curvature_to_the_boundary():
    """On an indefinite B, the conjugate-gradient step stops on the trust region's boundary
    (in the preconditioner's norm) along a direction of negative curvature, and lowers the
    model more than any step inside the region along the gradient."""
    B = np.diag([2.0, -1.0, 3.0])
    M = np.diag([1.0, 2.0, 1.0])
    g = np.array([0.5, 0.1, -0.3])
    radius = 0.7
    p = steihaug(dense_to_band(B), dense_to_band(M), BandedCholesky(dense_to_band(M)), g, radius)
    assert np.sqrt(p @ M @ p) == pytest.approx(radius, rel=1e-12)
    model = g @ p + 0.5 * p @ B @ p
    for t in np.linspace(0.0, 1.0, 21):  # the steepest-descent segment inside the region
        s = -t * radius * g / np.sqrt(g @ M @ g)
        assert model <= g @ s + 0.5 * s @ B @ s + 1e-12
    # a positive definite B with the minimiser inside: Newton's step itself
    A = np.diag([2.0, 1.0, 3.0])
    p = steihaug(dense_to_band(A), dense_to_band(M), BandedCholesky(dense_to_band(M)), g, 10.0)
    assert np.allclose(p, np.linalg.solve(A, -g), rtol=1e-5, atol=1e-12)


def test_a_nonconvex_double_well_reaches_a_minimiser_from_a_saddle_region():
    """F = (x^2 - 1)^2 + y^2 + x y / 10 from a point where the Hessian is indefinite: the
    solve leaves the saddle region along negative curvature and converges, with the
    stopping rule, to a local minimiser (gradient zero, Hessian positive definite)."""

    def F(z):
        x, y = z
        return (x * x - 1) ** 2 + y * y + 0.1 * x * y

    def grad(z):
        x, y = z
        return np.array([4 * x * (x * x - 1) + 0.1 * y, 2 * y + 0.1 * x])

    def hess(z):
        x, _ = z
        return np.array([[12 * x * x - 4, 0.1], [0.1, 2.0]])

    toy = Toy(F, grad, hess, magnitude=lambda z: (z[0] ** 2 - 1) ** 2 + z[1] ** 2 + 1.0)
    start = np.array([0.05, 0.5])
    assert np.linalg.eigvalsh(hess(start)).min() < 0
    point, report = minimize(toy, toy.evaluate(start), SolveOptions(tolerance=1e-12))
    assert report.converged and report.stop in ("decrement", "round-off")
    assert np.linalg.norm(grad(point.z)) < 1e-6
    assert np.linalg.eigvalsh(hess(point.z)).min() > 0
    assert abs(abs(point.z[0]) - 1.0) < 0.05
    assert report.iterations <= 20


def test_an_approximate_matrix_is_certified_by_its_measured_contraction():
    """A fixed approximate Newton matrix (the Hessian of a quadratic, perturbed) converges
    linearly; the solve certifies by the measured contraction, without exact matrices, and
    its distance bound holds for the true error."""
    A = spd(10, 4, condition=50.0)
    b = np.random.default_rng(5).standard_normal(10)
    E = 0.15 * spd(10, 6, condition=1.0)  # B = A + E: contraction |I - B^-1 A| < 0.5
    toy = quadratic(A, b)
    toy.approximate, toy.exact = (lambda z: A + E), False
    theta = np.abs(np.linalg.eigvals(np.eye(10) - np.linalg.solve(A + E, A))).max()
    assert 0.01 < theta < 0.5
    point, report = minimize(toy, toy.evaluate(np.zeros(10)), SolveOptions(tolerance=1e-14))
    assert report.converged and report.exact_newton_from is None and not toy.exact
    assert report.iterations > 2  # linear, not one Newton step
    assert report.contraction is not None and report.contraction <= 0.5
    exact = np.linalg.solve(A, -b)
    assert np.abs(point.z - exact).max() <= report.distance_bound


def test_a_slowly_contracting_approximate_matrix_is_replaced_by_the_exact_one():
    """An approximate matrix three times the Hessian contracts by 2/3 per iteration, more
    than ``contraction`` allows: the solve asks for the exact matrix and then converges in
    Newton steps."""
    A = spd(8, 7, condition=20.0)
    b = np.random.default_rng(8).standard_normal(8)
    toy = quadratic(A, b)
    toy.approximate, toy.exact = (lambda z: 3.0 * A), False
    point, report = minimize(toy, toy.evaluate(np.zeros(8)), SolveOptions())
    assert report.converged and toy.exact and report.exact_newton_from is not None
    assert np.allclose(point.z, np.linalg.solve(A, -b), rtol=1e-8, atol=1e-12)


def test_the_report_counts_iterations_and_keeps_the_objective_history():
    A, b = spd(5, 9), np.ones(5)
    toy = quadratic(A, b)
    _, report = minimize(toy, toy.evaluate(np.full(5, 3.0)), SolveOptions(max_iterations=0))
    assert not report.converged and report.stop == "max_iterations"
    assert report.iterations == 0 and report.objective_history == (report.objective_start,)
    info = report.as_info()
    assert info["objective_history"] == [report.objective_start] and info["converged"] is False


def test_band_storage_round_trips():
    H = spd(7, 3)
    assert np.array_equal(band_to_dense(dense_to_band(H)), H)


def test_a_slowly_contracting_matrix_of_reused_derivatives_is_renewed():
    """An exact objective whose Newton matrix comes from reused derivatives (here three times
    the Hessian, contracting by 2/3) renews them once the measured contraction exceeds
    ``contraction``, instead of creeping on: a stale matrix can hide negative curvature."""
    A = spd(8, 11, condition=20.0)
    b = np.random.default_rng(12).standard_normal(8)
    toy = quadratic(A, b)
    fresh_calls = []

    def newton_matrices(point, fresh=False):
        fresh_calls.append(fresh)
        return dense_to_band(A), dense_to_band(A if fresh else 3.0 * A), fresh

    toy.newton_matrices = newton_matrices
    point, report = minimize(toy, toy.evaluate(np.zeros(8)), SolveOptions(tolerance=1e-14))
    assert report.converged
    assert np.allclose(point.z, np.linalg.solve(A, -b), rtol=1e-8, atol=1e-12)
    assert any(fresh_calls) and report.iterations <= 6


def test_good_boundary_steps_are_extended(monkeypatch):
    """F = (x^2 - a^2)^2 / (4 a^2) + y^2 is concave in x for |x| < a / sqrt(3): from x near 0
    the trust region would have to double for about log2(a / x_0) iterations to walk there.
    Good boundary steps are doubled while F falls, at the cost of evaluations of F only: the
    same minimiser (x = a) in less than half the iterations."""
    import importlib

    optimizer = importlib.import_module("wiggly.solve.optimizer")

    a = 100.0

    def toy():
        return Toy(lambda z: (z[0] ** 2 - a * a) ** 2 / (4 * a * a) + z[1] ** 2,
                   lambda z: np.array([z[0] * (z[0] ** 2 - a * a) / (a * a), 2 * z[1]]),
                   lambda z: np.diag([(3 * z[0] ** 2 - a * a) / (a * a), 2.0]),
                   magnitude=lambda z: (z[0] ** 2 + a * a) ** 2 / (4 * a * a) + z[1] ** 2)

    start = np.array([0.01, 0.0])
    reports = {}
    for extensions in (optimizer.EXTRAPOLATIONS, 0):
        monkeypatch.setattr(optimizer, "EXTRAPOLATIONS", extensions)
        point, report = minimize(t := toy(), t.evaluate(start), SolveOptions())
        assert report.converged and abs(point.z[0] - a) < 1e-6 * a and abs(point.z[1]) < 1e-6
        reports[extensions] = report
    assert reports[3].iterations <= reports[0].iterations / 2, \
        (reports[3].iterations, reports[0].iterations)
