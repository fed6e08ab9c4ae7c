"""A trust-region Newton method for E + E_WC (Theorem 2), with an honest stopping rule.

Each iteration evaluates the objective F and its exact gradient g at z and asks the
objective for two band matrices (:mod:`wiggly.solve.warped`): the Gauss-Newton matrix
(the energy's band plus J^T J at each constrained node: positive definite) and the Newton
matrix B (plus the curvature of the residuals, sum c r^T D^2 W, which Gauss-Newton drops;
at a solution with stiff keyframes c r balances the energy's gradient, so this term is as
large as the rest).  The step is

* Newton's, ``dz = -B^-1 g``, where B is positive definite and the step fits in the trust
  region;
* else the Steihaug-Toint conjugate-gradient step on B, preconditioned by the Gauss-Newton
  matrix, whose norm measures the region: it follows negative curvature to the boundary,
  so saddle regions (large turns, velocity keyframes) are left quickly.

A step is accepted when F drops by more than 1e-4 of the model's prediction; the radius
shrinks by 4 on a poor prediction and doubles on a good one at the boundary.  Newton
matrices built from reused derivatives (:mod:`wiggly.solve.blocks`) are renewed when a step
fails or the matrix is indefinite.

Stopping rule.  With the Newton decrement ``dec = -1/2 g^T dz`` (dz = -B^-1 g, B positive
definite) and the distance bound ``d`` (the largest vertex move of dz at any node, m), the
solve has converged when

    dec <= tolerance * F + floor   and   d <= distance_tolerance * size,

``floor = 100 eps *`` (the sum of the magnitudes of F's terms) being F's rounding level (at a
body at rest F itself rounds to ~0; a decrement below it ends the solve as well), and the
last step was a full step (Newton's, or the approximate matrix's) and the iteration
contracts: with theta measured from successive decrements (theta^2 ~ dec_{k+1}/dec_k),
theta <= ``contraction``.  For a contraction, ``|z - z*| <= |dz| / (1 - theta)``, so ``d``
is the largest vertex move of dz divided by ``1 - theta``: the motion's node states are
within ``d`` of the minimiser's.  With an *exact* matrix (B the Hessian of F at z, from
derivatives computed there) theta falls quadratically; with an *approximate* one (from a
coarse mesh, :mod:`wiggly.solve.levels`) the iteration is linear, z_{k+1} - z* = (I - B^-1
H)(z_k - z*), and when theta stays above ``contraction``, the matrix is indefinite, or the
level takes more than ten iterations, the objective improves its matrix by a stage
(Gauss-Newton matrices get the curvature; approximate ones become exact).

``converged`` is true only when this rule holds; otherwise a :class:`WarpedSolveWarning`
gives the decrement reached.  The report's ``distance_bound`` is ``d``; when the decrement
is below F's rounding level (stop ``round-off``), F cannot resolve smaller moves, and ``d``
is widened to the move along the Newton direction whose decrement equals that level.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from wiggly.solve.banded import BandedCholesky, band_matvec

__all__ = ["SolveOptions", "WarpedSolveWarning", "minimize"]


class WarpedSolveWarning(UserWarning):
    """The warped solve stopped before meeting its stopping rule."""


@dataclass(frozen=True)
class SolveOptions:
    """Options of the warped (nonlinear) solve.

    tolerance : the Newton decrement must fall below ``tolerance * F`` (plus F's rounding
        level).
    distance_tolerance : and the distance bound (the final Newton step's largest vertex
        move, widened by the measured contraction) below this fraction of the body's size.
    max_iterations : Newton iterations allowed per level: a budget, not a convergence test
        (a solve that spends it is reported unconverged).  Most scenes need 5-60; paths
        through long regions of negative curvature (a hop or a large turn of a soft, long-
        necked body) crawl with trust-region steps and took up to about 420 in the
        convergence suite.
    contraction : largest measured contraction factor per iteration with which an
        approximate (coarse-mesh) Newton matrix may certify convergence; above it the solve
        improves the matrix (adds the curvature, then takes exact derivatives).
    coarse_tolerance : tolerance of the coarse first level (its solution only starts the
        fine one).
    two_level : solve on the body's coarse mesh first (bodies above ``COARSE_WARP_ABOVE``
        tets whose coarse mesh is coarser, :data:`wiggly.solve.levels.COARSER`); False: the
        fine level only, with exact Newton matrices.
    warn : emit a :class:`WarpedSolveWarning` when the solve stops unconverged.
    callback : called with the number of iterations so far (both levels) after each one; an
        exception it raises ends the solve and propagates (the editor abandons an outdated
        refinement so).
    """

    tolerance: float = 1e-8
    distance_tolerance: float = 1e-3
    max_iterations: int = 1000
    contraction: float = 0.5
    coarse_tolerance: float = 1e-5
    two_level: bool = True
    warn: bool = True
    callback: Callable[[int], None] | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not (self.tolerance > 0 and np.isfinite(self.tolerance)):
            raise ValueError(f"tolerance = {self.tolerance!r} must be a number > 0")
        if int(self.max_iterations) != self.max_iterations or self.max_iterations < 0:
            raise ValueError(f"max_iterations = {self.max_iterations!r} must be an integer >= 0")
        if not 0 < self.contraction < 1:
            raise ValueError(f"contraction = {self.contraction!r} must lie in (0, 1)")


class Point(Protocol):
    z: np.ndarray
    F: float
    g: np.ndarray
    magnitude: float


class Objective(Protocol):
    """What :func:`minimize` needs of an objective (see :mod:`wiggly.solve.warped`)."""

    exact: bool
    size: float  # the body's size (m): the scale of distance_tolerance
    timing: dict
    counts: dict

    def evaluate(self, z: np.ndarray) -> Point: ...

    def newton_matrices(
        self, point: Point, fresh: bool = False
    ) -> tuple[np.ndarray, np.ndarray, bool]: ...

    def use_exact(self) -> bool: ...

    def step_size(self, dz: np.ndarray) -> float: ...


# Conjugate gradients of the trust-region steps: relative residual and iterations.
CG_TOLERANCE = 1e-6
CG_ITERATIONS = 200
# Relative residual of the Newton step's linear solve.
NEWTON_RESIDUAL = 1e-8
# Accept a step when F drops by at least this share of the model's prediction.
ACCEPT = 1e-4
DEBUG = False
# Approximate matrices: improve them by a stage (Objective.use_exact) after this many
# iterations in a row where the matrix is indefinite or contracts by more than
# ``contraction``, or after APPROXIMATE_ITERATIONS iterations in all (the coarse start
# should be close).
SLOW_STEPS = 2
APPROXIMATE_ITERATIONS = 10
# The rounding level of F, relative to the sum of its terms' magnitudes.
ROUNDING = 100 * np.finfo(float).eps


def _norm(ab: np.ndarray, x: np.ndarray) -> float:
    """``sqrt(x^T A x)`` for A in band storage."""
    return float(np.sqrt(max(float(x @ band_matvec(ab, x)), 0.0)))


def steihaug(
    B: np.ndarray, M: np.ndarray, precondition: BandedCholesky, g: np.ndarray, radius: float
) -> np.ndarray:
    """Approximate minimiser of ``g^T p + 1/2 p^T B p`` over ``|p|_M <= radius`` by
    preconditioned conjugate gradients (Steihaug 1983, Toint 1981; Nocedal & Wright,
    Alg. 7.2): stops on the boundary when it leaves the region or meets negative curvature
    of B (which it then follows), or when the residual has fallen by CG_TOLERANCE."""
    p = np.zeros_like(g)
    r = g.copy()
    y = precondition.solve(r, refine=False)
    d = -y
    ry = float(r @ y)
    target = CG_TOLERANCE * np.sqrt(max(ry, 0.0))
    for _ in range(CG_ITERATIONS):
        Bd = band_matvec(B, d)
        dBd = float(d @ Bd)
        if dBd <= 0:
            return p + _to_boundary(M, p, d, radius) * d
        alpha = ry / dBd
        p_next = p + alpha * d
        if _norm(M, p_next) >= radius:
            return p + _to_boundary(M, p, d, radius) * d
        p = p_next
        r = r + alpha * Bd
        y = precondition.solve(r, refine=False)
        ry_next = float(r @ y)
        if np.sqrt(max(ry_next, 0.0)) <= target:
            break
        d = -y + (ry_next / ry) * d
        ry = ry_next
    return p


def _to_boundary(M: np.ndarray, p: np.ndarray, d: np.ndarray, radius: float) -> float:
    """The tau >= 0 with ``|p + tau d|_M = radius`` (p inside the region)."""
    Md = band_matvec(M, d)
    a, b, c = float(d @ Md), float(p @ Md), float(p @ band_matvec(M, p)) - radius**2
    return (-b + np.sqrt(max(b * b - a * c, 0.0))) / a


def _distance(objective: Objective, dz: np.ndarray | None, theta: float | None) -> float:
    """The distance bound (m): the Newton step's largest vertex move divided by ``1 -
    theta``, theta the iteration's measured contraction (inf when unknown or >= 1)."""
    if dz is None or theta is None or theta >= 1.0:
        return np.inf
    return objective.step_size(dz) / (1.0 - theta)


def _newton_step(chol: BandedCholesky, B: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``-B^-1 g`` with a relative residual below NEWTON_RESIDUAL (an inexact Newton step
    whose error is far below any contraction the stopping rule accepts): from the
    factorization alone when its residual, checked in working precision, is that small,
    else refined in extended precision (stiff keyframes)."""
    dz = chol.solve(-g, refine=False)
    if np.linalg.norm(band_matvec(B, dz) + g) <= NEWTON_RESIDUAL * np.linalg.norm(g):
        return dz
    return chol.solve(-g)


def _factor(ab: np.ndarray) -> BandedCholesky | None:
    try:
        return BandedCholesky(ab)
    except np.linalg.LinAlgError:
        return None


def minimize(
    objective: Objective,
    point: Point,
    options: SolveOptions,
    *,
    tolerance: float | None = None,
    contraction: float | None = None,
    certify: bool = True,
    bar=None,
) -> tuple[Point, dict]:
    """Minimise ``objective`` from ``point`` (evaluated); see the module docstring.

    ``contraction`` is a contraction factor known from an earlier solve of the same problem
    (a warm start), which lets an approximate matrix certify a start that already meets the
    tolerance.  ``certify=False`` stops on the decrement alone (a coarse level, whose
    solution only starts the fine one).  Returns the final point and a report.
    """
    tol = options.tolerance if tolerance is None else tolerance
    F_start = point.F
    history = [point.F]
    radius: float | None = None
    theta = contraction
    last_full: float | None = None  # decrement of the last iteration that took a Newton step
    slow, exact_from, newton_steps = 0, None, 0
    converged, stop, it = False, "max_iterations", 0
    decrement, dz_newton = np.inf, None
    t_solve = 0.0
    fresh = False  # ask for a matrix from derivatives computed at the point itself
    while True:
        B_gn, B, computed = objective.newton_matrices(point, fresh)
        fresh = False
        hessian = objective.exact and computed
        t0 = time.perf_counter()
        chol = _factor(B)
        dz_newton = _newton_step(chol, B, point.g) if chol is not None else None
        decrement = -0.5 * float(point.g @ dz_newton) if dz_newton is not None else np.inf
        if not decrement >= 0:  # not a descent direction: B is not positive definite
            chol, decrement, dz_newton = None, np.inf, None
        t_solve += time.perf_counter() - t0
        if chol is not None and last_full is not None and last_full > 0:
            theta = float(np.sqrt(decrement / last_full))
        floor = ROUNDING * point.magnitude
        distance = _distance(objective, dz_newton, theta)
        small = decrement <= tol * max(point.F, 0.0) + floor
        close = distance <= options.distance_tolerance * objective.size
        if DEBUG:
            print(f"  check exact={objective.exact} computed={computed} "
                  f"dec/F={decrement / max(point.F, 1e-300):.3g} "
                  f"dist/size={distance / objective.size:.3g} theta={theta}")
        # the last step was a full step of this iteration and it contracted by theta; an
        # exact model must also have its derivatives computed at this point
        trusted = (
            theta is not None
            and theta <= options.contraction
            and (hessian or not objective.exact)
        )
        if small and ((trusted and close) or not certify or decrement <= floor):
            converged, stop = True, "decrement" if decrement > floor else "round-off"
            break
        if not computed and ((small and certify) or chol is None):  # reused: check afresh
            fresh = True
            continue
        if not objective.exact:  # an approximate matrix must keep earning its keep
            slow = slow + 1 if chol is None or (theta or 0.0) > options.contraction else 0
            if (slow >= SLOW_STEPS or it >= APPROXIMATE_ITERATIONS) and objective.use_exact():
                theta, last_full, slow = None, None, 0
                exact_from = it if objective.exact and exact_from is None else exact_from
                continue  # recompute the matrix at the same point
        if it >= options.max_iterations:
            break
        it += 1
        # trust region in the Gauss-Newton matrix's norm: Newton's step where B is positive
        # definite and the step fits, else Steihaug-Toint conjugate gradients on B
        # preconditioned by the Gauss-Newton matrix (which follows negative curvature)
        t0 = time.perf_counter()
        precondition = None  # the Gauss-Newton matrix's factor, made when first needed
        if dz_newton is None:
            precondition = _factor(B_gn)
            if precondition is None:  # only when H itself is singular (no pre-roll)
                stop = "singular"
                break
        if radius is None:
            dz0 = dz_newton if dz_newton is not None else precondition.solve(-point.g)
            radius = _norm(B_gn, dz0)
        newton, refresh, rho = False, False, -np.inf
        while True:
            if dz_newton is not None and _norm(B_gn, dz_newton) <= radius * (1 + 1e-12):
                dz, newton = dz_newton, True
            else:
                precondition = precondition or _factor(B_gn) or chol
                dz, newton = steihaug(B, B_gn, precondition, point.g, radius), False
            size = _norm(B_gn, dz)
            predicted = -(float(point.g @ dz) + 0.5 * float(dz @ band_matvec(B, dz)))
            t_solve += time.perf_counter() - t0
            if not predicted > floor:  # no decrease left above F's rounding level
                if computed:
                    radius = 0.0
                else:
                    refresh, rho = True, -np.inf
                break
            new = objective.evaluate(point.z + dz)
            t0 = time.perf_counter()
            rho = (point.F - new.F) / predicted
            if DEBUG:
                print(f"  it={it} radius={radius:.3g} size={size:.3g} rho={rho:.3g} "
                      f"newton={newton} step={objective.step_size(dz):.3g} F={new.F:.6g}")
            if rho < 0.25 and not computed:  # a poor model from reused derivatives: renew
                refresh = True
                break
            if rho < 0.25:
                radius = 0.25 * size
            elif rho > 0.75 and size >= 0.99 * radius:
                radius = 2.0 * radius
            if rho > ACCEPT:
                break
            if radius <= 1e-14 * max(_norm(B_gn, point.z), 1e-300):
                radius = 0.0
                break
        if radius == 0.0:
            stop = "no progress"
            break
        if refresh and rho <= ACCEPT:  # retry from the same point with fresh derivatives
            fresh = True
            it -= 1
            continue
        newton_steps += newton
        last_full = decrement if newton else None
        fresh = refresh  # a poor step on reused derivatives: renew them at the new point
        point = new
        history.append(point.F)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"objective {point.F:.6g}")
    distance = _distance(objective, dz_newton, theta)
    if stop == "round-off" and decrement > 0:
        # below F's rounding level the gradient is rounding noise: widen the bound to the move
        # along the Newton direction whose decrement is the rounding level
        distance *= float(np.sqrt(max(ROUNDING * point.magnitude / decrement, 1.0)))
    objective.timing["solve"] = objective.timing.get("solve", 0.0) + t_solve
    report = {
        "iterations": it,
        "converged": converged,
        "stop": stop,
        "objective_start": F_start,
        "objective": point.F,
        "objective_history": history,
        "newton_decrement": decrement,
        "contraction": theta,
        "distance_bound": None if not np.isfinite(distance) else distance,
        "exact_newton_from": exact_from,
        "newton_steps": newton_steps,
        "evaluations": dict(objective.counts),
        "seconds": dict(objective.timing),
    }
    return point, report


def warn_unconverged(report: dict, level: str = "") -> None:
    """A :class:`WarpedSolveWarning` with the decrement reached."""
    warnings.warn(
        f"warped solve{level} did not converge in {report['iterations']} iterations "
        f"({report['stop']}): objective {report['objective']:.6g} (start "
        f"{report['objective_start']:.6g}), Newton decrement {report['newton_decrement']:.2e}; "
        "the result is the best iterate",
        WarpedSolveWarning,
        stacklevel=4,
    )
