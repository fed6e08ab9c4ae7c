"""Wiggly-spline basis (Schulz et al. 2014, Theorem 1):
ODE residual, Hermite data, exact energy, extremes."""

from __future__ import annotations

import mpmath
import numpy as np
import pytest

from wiggly.splines import (
    OSCILLATORY,
    SERIES,
    SPLIT,
    SPLIT_SMALL,
    energy_form,
    equilibrium,
    evaluate,
    wiggly_basis,
)

# (lam [s^-2], delta [s^-1], h [s], expected regime): every regime and the degenerate cases
CASES = [
    (0.0, 0.0, 1.0, SERIES),  # rigid, undamped: cubics
    (0.0, 0.3, 1.0, SERIES),  # rigid, lightly damped
    (0.0, 3.0, 1.0, SPLIT_SMALL),  # rigid, damped: 1, t, exp(+-2 delta t)
    (0.0, 5e5, 60.0, SPLIT_SMALL),  # rigid, extreme damping over a long interval
    (0.5, 0.1, 1.0, SERIES),  # slow elastic mode
    (100.0, 0.0, 1.0, OSCILLATORY),  # undamped
    (100.0, 0.2, 1.0, OSCILLATORY),  # lightly under-damped
    (100.0, 2.0, 1.0, SPLIT),  # under-damped
    (100.0, 10.0, 1.0, SPLIT),  # critically damped
    (100.0, 10.0 - 1e-7, 1.0, SPLIT),  # near-critical (under)
    (100.0, 10.0 + 1e-7, 1.0, SPLIT),  # near-critical (over)
    (100.0, 30.0, 1.0, SPLIT),  # over-damped
    (0.01, 5.0, 1.0, SPLIT_SMALL),  # strongly over-damped slow mode
    (1e4, 1e-9, 1.0, OSCILLATORY),  # almost undamped, fast
    (1e8, 0.0, 60.0, OSCILLATORY),  # the extremes the issue names
    (1e8, 1e-3, 60.0, OSCILLATORY),
    (1e8, 10.0, 60.0, SPLIT),
    (1e8, 5e3, 1.0, SPLIT),
    (1e8, 1e4, 1.0, SPLIT),  # critical at lambda = 1e8
    (1e8, 5e5, 60.0, SPLIT),  # beta-damped stiff mode: delta h = 3e7
]


def gravity_for(lam: float) -> float:
    return -9.81 if lam == 0 else 3.0


def derivatives(lam, delta, h, g, data, tau, order=4):
    """q and its first ``order`` time derivatives (exact, from the kernel slots)."""
    B = wiggly_basis(np.full(len(tau), lam), delta, h)
    qp = equilibrium(lam, g)
    xh = data * np.array([1, h, 1, h]) - np.array([qp, 0, qp, 0])
    f = B.kernel(tau, order)
    H = np.einsum("dpk,pkj->dpj", f, B.hermite_inverse).real
    q = np.einsum("dpj,j->dp", H, xh) / h ** np.arange(order + 1)[:, None]
    q[0] += qp
    return q


@pytest.mark.parametrize("lam,delta,h,regime", CASES)
def test_regime_is_the_documented_one(lam, delta, h, regime):
    assert wiggly_basis(lam, delta, h).regime[0] == regime


@pytest.mark.parametrize("lam,delta,h,regime", CASES)
def test_ode_residual_and_hermite_data(lam, delta, h, regime):
    rng = np.random.default_rng(0)
    data = rng.standard_normal(4)
    g = gravity_for(lam)
    tau = np.r_[0.0, rng.uniform(0, 1, 30), 1.0]
    q = derivatives(lam, delta, h, g, data, tau)
    assert np.all(np.isfinite(q))
    # q'''' + 2 (lam - 2 delta^2) q'' + lam (lam q + g) = 0, relative to the size of its terms
    terms = np.array(
        [q[4], 2 * (lam - 2 * delta**2) * q[2], lam * lam * (q[0] - equilibrium(lam, g))]
    )
    scale = np.max(np.abs(terms)) + 1e-300
    assert np.max(np.abs(terms.sum(axis=0))) <= 1e-9 * scale
    # Hermite interpolation: values and velocities at both ends
    assert np.allclose([q[0, 0], q[1, 0], q[0, -1], q[1, -1]], data, rtol=1e-10, atol=1e-10)


def _quadrature_energy(lam, delta, h, g, data):
    """1/2 int (q'' + 2 delta q' + lam q + g)^2 dt by composite Gauss-Legendre, panels
    resolving every oscillation and geometrically graded boundary layers."""
    omega = np.sqrt(lam)
    n = int(max(200, 4 * omega * h / np.pi))
    edges = np.linspace(0, h, n + 1)
    if delta * h > 10:
        layer = np.minimum(h / 4, 60 / delta) * np.geomspace(1e-12, 1, 120)
        edges = np.unique(np.r_[edges, layer, h - layer])
    x, w = np.polynomial.legendre.leggauss(16)
    t = (edges[:-1, None] + (x + 1) / 2 * np.diff(edges)[:, None]).ravel()
    wt = (w * np.diff(edges)[:, None] / 2).ravel()
    B = wiggly_basis(np.full(t.size, lam), delta, h)
    q = evaluate(B, np.broadcast_to(data, (t.size, 4)), g, t / h, 2)
    return 0.5 * np.sum(wt * (q[2] + 2 * delta * q[1] + lam * q[0] + g) ** 2)


@pytest.mark.parametrize("lam,delta,h,regime", [c for c in CASES if np.sqrt(c[0]) * c[2] < 1e5])
def test_energy_form_matches_quadrature(lam, delta, h, regime):
    rng = np.random.default_rng(1)
    data = rng.standard_normal(4)
    g = gravity_for(lam)
    form = energy_form(wiggly_basis(lam, delta, h), g)
    exact = form(data[None])[0]
    quad = _quadrature_energy(lam, delta, h, g, data)
    assert exact > 0
    assert abs(exact - quad) <= 1e-9 * quad


def test_energy_undamped_stiff_long_interval_against_mpmath():
    """lam = 1e8 s^-2 over 60 s (6e5 rad): independent closed form in 40-digit arithmetic."""
    lam, h, g = 1e8, 60.0, 3.0
    data = np.array([0.3, -2.0, 1.1, 0.7])
    mpmath.mp.dps = 40
    w = mpmath.sqrt(mpmath.mpf(lam))
    H = mpmath.mpf(h)
    qp = -mpmath.mpf(g) / lam
    fs = [
        lambda t: mpmath.cos(w * t),
        lambda t: mpmath.sin(w * t),
        lambda t: t * mpmath.cos(w * t),
        lambda t: t * mpmath.sin(w * t),
    ]
    dfs = [
        lambda t: -w * mpmath.sin(w * t),
        lambda t: w * mpmath.cos(w * t),
        lambda t: mpmath.cos(w * t) - t * w * mpmath.sin(w * t),
        lambda t: mpmath.sin(w * t) + t * w * mpmath.cos(w * t),
    ]
    A = mpmath.matrix(
        [[f(0) for f in fs], [f(0) for f in dfs], [f(H) for f in fs], [f(H) for f in dfs]]
    )
    rhs = mpmath.matrix([mpmath.mpf(data[0]) - qp, data[1], mpmath.mpf(data[2]) - qp, data[3]])
    c = mpmath.lu_solve(A, rhs)
    # L(t cos) = -2 w sin, L(t sin) = 2 w cos  =>  r = 2 w (c4 cos - c3 sin)
    a, b = 2 * w * c[3], -2 * w * c[2]
    s2 = mpmath.sin(2 * w * H)
    int_cc = H / 2 + s2 / (4 * w)
    int_ss = H / 2 - s2 / (4 * w)
    int_cs = mpmath.sin(w * H) ** 2 / (2 * w)
    exact = float((a * a * int_cc + b * b * int_ss + 2 * a * b * int_cs) / 2)
    ours = energy_form(wiggly_basis(lam, 0.0, h), g)(data[None])[0]
    assert abs(ours - exact) <= 1e-9 * exact


@pytest.mark.parametrize("lam", [0.0, 1e-6, 1.0, 1e4, 1e8])
@pytest.mark.parametrize("delta", [0.0, 1e-3, 1.0, 1e3, 5e5])
@pytest.mark.parametrize("h", [1e-3, 1.0, 60.0])
def test_extremes_stay_finite_and_interpolate(lam, delta, h):
    data = np.array([1.0, -1.0, 0.5, 2.0])
    B = wiggly_basis(lam, delta, h)
    form = energy_form(B, 0.0)
    assert np.all(np.isfinite(B.hermite_inverse)) and np.all(np.isfinite(form.Q))
    assert form(data[None])[0] >= -1e-12 * np.abs(form.Q).max()
    tau = np.linspace(0, 1, 101)
    q = evaluate(B.take(np.zeros(101, int)), np.broadcast_to(data, (101, 4)), 0.0, tau, 2)
    assert np.all(np.isfinite(q))
    assert np.allclose(q[:2, [0, -1]].T.ravel(), data, rtol=1e-8, atol=1e-8)


def test_energy_form_is_symmetric_positive_semidefinite():
    lam = np.array([0.0, 0.0, 10.0, 1e3, 1e6])
    delta = np.array([0.0, 2.0, 0.1, 50.0, 1e3])
    Q = energy_form(wiggly_basis(lam, delta, 0.7), 0.0).Q
    assert np.allclose(Q, Q.transpose(0, 2, 1))
    for q in Q:
        w = np.linalg.eigvalsh(q)
        assert w.min() >= -1e-10 * w.max()


def test_free_motion_costs_nothing():
    """Hermite data of a solution of q'' + 2 delta q' + lam q + g = 0 has zero energy."""
    lam, delta, h, g = 40.0, 0.8, 1.3, 2.0
    om = np.sqrt(lam - delta**2)
    qp = -g / lam

    def q(t):
        return qp + np.exp(-delta * t) * (0.4 * np.cos(om * t) - 0.2 * np.sin(om * t))

    def dq(t):
        e = np.exp(-delta * t)
        return e * (
            -delta * (0.4 * np.cos(om * t) - 0.2 * np.sin(om * t))
            + om * (-0.4 * np.sin(om * t) - 0.2 * np.cos(om * t))
        )

    data = np.array([q(0), dq(0), q(h), dq(h)])
    form = energy_form(wiggly_basis(lam, delta, h), g)
    scale = 0.5 * np.abs(data) @ np.abs(form.Q[0]) @ np.abs(data)
    assert abs(form(data[None])[0]) <= 1e-12 * scale


def _slow_mode_reference(lam, delta, h, g, data, taus):
    """q, q'' at ``taus`` and the energy of the spline with Hermite ``data``, in 50 digits:
    q = -g / lam + sum c_k exp(s_k t) over the roots of s^4 + 2 (lam - 2 delta^2) s^2 +
    lam^2 (Theorem 1's equation; the static offset's cancellation is harmless there)."""
    mpmath.mp.dps = 50
    lam, delta, h, g = (mpmath.mpf(x) for x in (lam, delta, h, g))
    a = lam - 2 * delta**2
    roots = [sign * mpmath.sqrt(-a + branch * mpmath.sqrt(a * a - lam * lam))
             for branch in (1, -1) for sign in (1, -1)]
    qp = -g / lam
    A = mpmath.matrix([[mpmath.e ** (s * t) * (s if d else 1) for s in roots]
                       for t in (0, h) for d in (0, 1)])
    rhs = mpmath.matrix([data[0] - qp, data[1], data[2] - qp, data[3]])
    c = mpmath.lu_solve(A, rhs)

    def q(t, d=0):
        return (qp if d == 0 else 0) + sum(c[k] * roots[k] ** d * mpmath.e ** (roots[k] * t)
                                           for k in range(4))

    values = [(float(q(tau * h)), float(q(tau * h, 2))) for tau in taus]
    energy = mpmath.quad(lambda t: (q(t, 2) + 2 * delta * q(t, 1) + lam * q(t) + g) ** 2,
                         [0, h / 2, h]) / 2
    mpmath.mp.dps = 15
    return values, float(energy)


@pytest.mark.parametrize("lam", [1e-3, 1e-6, 1e-8])
def test_a_slow_mode_under_gravity_keeps_its_energy_and_values(lam):
    """A slow elastic mode (lam h^2 small) under a modal gravity of -30: the static offset
    -g / lam (3e9 at lam = 1e-8) cancelled the energy's terms into a relative error of 6e-9
    (lam = 1e-3), 6e-4 (1e-6) and a negative energy (1e-8); the spline now shifts by its
    response to gravity from rest, and matches a 50-digit solution."""
    delta, h, g = 0.25, 1.0, -30.0
    data = np.array([0.03, -0.12, 0.08, 0.05])
    taus = [0.3, 0.7]
    ref, energy = _slow_mode_reference(lam, delta, h, g, data, taus)
    basis = wiggly_basis(lam, delta, h)
    assert abs(energy_form(basis, g)(data[None])[0] - energy) <= 1e-12 * energy
    for tau, (q, q2) in zip(taus, ref, strict=True):
        got = evaluate(basis, data[None], g, tau, 2)[:, 0]
        assert abs(got[0] - q) <= 1e-12 and abs(got[2] - q2) <= 1e-10 * abs(q2), (tau, got)
