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

Stiff keyframes make E + E_WC a narrow, curved valley: a quadratic model follows it only for
short steps, and the trust region crawls.  A step along negative curvature or to the region's
boundary, or a poorly predicted Newton step, therefore also tries its second-order correction
(Nocedal & Wright 2006, sec. 18.3; the geodesic acceleration of Transtrum & Sethna 2012):
``dz - B^-1 J^T C m`` with ``m = r(z + dz) - r(z) - J dz`` the residuals' nonlinear part
along the step, which moves the step back onto the valley; the corrected point is taken
when its F is lower.  The correction changes the path, never the stopping rule.

A step is accepted when F drops by more than 1e-4 of the model's prediction (trial points
are evaluated without their gradient, which an accepted point then gets); the radius
shrinks by 4 on a poor prediction and doubles on a good one at the boundary.  Such a good
boundary step of conjugate gradients (along negative curvature, or a Newton step cut short)
is also extended: doubled while F keeps falling, up to ``EXTRAPOLATIONS`` times, the radius
doubling with it.  Those trials cost an evaluation of F each, a fraction of an iteration's
Newton matrices, and save the iterations a doubling radius would take to walk as far.  Newton
matrices built from reused derivatives (:mod:`wiggly.solve.blocks`) are renewed when a step
fails, the matrix is indefinite or it contracts by more than ``contraction``.

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
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np

from wiggly.errors import counted, warn
from wiggly.solve.banded import BandedCholesky, band_matvec

__all__ = ["SolveOptions", "SolveReport", "WarpedSolveWarning", "minimize"]


class WarpedSolveWarning(UserWarning):
    """The warped solve stopped before meeting its stopping rule."""


@dataclass(frozen=True)
class SolveOptions:
    """Options of the warped (nonlinear) solve.

    tolerance : the Newton decrement must fall below ``tolerance * F`` (plus F's rounding
        level).
    distance_tolerance : and the distance bound (the final Newton step's largest vertex
        move, widened by the measured contraction) below this fraction of the body's size;
        not asked when the decrement is below F's rounding level (stop ``"round-off"``: F
        cannot tell closer points apart; ``distance_bound`` then says how far that is).
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
    g: np.ndarray | None  # None at trial points (Objective.evaluate(z, gradient=False))
    magnitude: float


class Objective(Protocol):
    """What :func:`minimize` needs of an objective (see :mod:`wiggly.solve.warped`)."""

    exact: bool
    size: float  # the body's size (m): the scale of distance_tolerance
    timing: dict
    counts: dict

    def evaluate(self, z: np.ndarray, gradient: bool = True) -> Point: ...

    def with_gradient(self, point: Point) -> Point: ...

    def newton_matrices(
        self, point: Point, fresh: bool = False
    ) -> tuple[np.ndarray, np.ndarray, bool]: ...

    def use_exact(self) -> bool: ...

    def step_size(self, dz: np.ndarray) -> float: ...

    def correction_gradient(
        self, point: Point, dz: np.ndarray, trial: Point
    ) -> np.ndarray | None: ...


# Conjugate gradients of the trust-region steps: relative residual and iterations.
CG_TOLERANCE = 1e-6
CG_ITERATIONS = 200
# Relative residual of the Newton step's linear solve.
NEWTON_RESIDUAL = 1e-8
# Accept a step when F drops by at least this share of the model's prediction.
ACCEPT = 1e-4
# Steps along negative curvature or to the trust region's boundary, and Newton steps whose
# reduction ratio is poor (below 0.25), also try their second-order correction, unless the
# predicted decrease is below this share of F's magnitude: there the correction's forward
# difference is rounding noise (a Newton step near the minimiser needs no correction).
CORRECTION_FLOOR = 1e-10
# Good steps to the trust region's boundary (not Newton's) are doubled while F keeps falling,
# at most this many times.
EXTRAPOLATIONS = 3
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


def _second_order_correction(
    objective: Objective, point: Point, dz: np.ndarray, trial: Point, factor
) -> tuple[np.ndarray, Point] | None:
    """The step ``dz`` plus its second-order correction ``-B^-1 J^T C m`` (m: the residuals'
    nonlinear part along dz, :meth:`WarpedObjective.correction_gradient`), and the objective
    there; None when there is nothing to correct."""
    if factor is None:
        return None
    g = objective.correction_gradient(point, dz, trial)
    if g is None or not np.all(np.isfinite(g)) or not np.any(g):
        return None
    step = dz - factor.solve(g, refine=False)
    return step, objective.evaluate(point.z + step, gradient=False)


@dataclass(frozen=True)
class SolveReport:
    """What :func:`minimize` did, and where it stopped.

    ``stop`` is ``"decrement"`` or ``"round-off"`` (the stopping rule held: ``converged``),
    ``"max_iterations"``, ``"no progress"`` (the trust region shrank to nothing) or
    ``"singular"`` (no positive definite matrix to step with).  ``distance_bound`` (m) is
    the stopping rule's ``d`` (None when unknown); ``contraction`` the last measured theta;
    ``exact_newton_from`` the iteration from which an approximate objective used its exact
    Newton matrices; ``corrections`` how many steps took their second-order correction.
    """

    iterations: int
    converged: bool
    stop: str
    objective_start: float
    objective: float
    objective_history: tuple[float, ...]
    newton_decrement: float
    contraction: float | None
    distance_bound: float | None
    exact_newton_from: int | None
    newton_steps: int
    corrections: int
    evaluations: dict[str, int]
    seconds: dict[str, float]

    def as_info(self) -> dict:
        """The report as a plain dict (``Animation.info``, JSON summaries)."""
        info = asdict(self)
        info["objective_history"] = list(self.objective_history)
        return info


@dataclass
class _Model:
    """The quadratic model of F at the current point."""

    gauss_newton: np.ndarray  # band storage; positive definite wherever H is
    newton: np.ndarray  # band storage; may be indefinite
    computed: bool  # from derivatives computed at this point (not reused ones)
    hessian: bool  # ``newton`` is F's exact Hessian here
    factor: BandedCholesky | None  # of ``newton``, when it is positive definite
    step: np.ndarray | None  # Newton's step -B^-1 g (None: B is not positive definite)
    decrement: float  # -1/2 g^T step (inf without a step)


@dataclass
class _State:
    """The iteration's state between its named steps (:func:`minimize`)."""

    point: Point
    theta: float | None  # measured contraction per iteration
    history: list[float]
    iterations: int = 0
    radius: float | None = None  # trust region, in the Gauss-Newton matrix's norm
    last_full: float | None = None  # decrement of the last iteration that took Newton's step
    slow: int = 0  # approximate matrices: iterations in a row that did not earn their keep
    fresh: bool = False  # ask for a matrix from derivatives computed at the point itself
    exact_from: int | None = None
    newton_steps: int = 0
    corrections: int = 0
    t_solve: float = 0.0


@dataclass
class _Step:
    """The outcome of one trust-region step: a new point, a retry from the same point with
    fresh derivatives, or no step at all (``stop``)."""

    point: Point | None = None
    newton: bool = False
    refresh: bool = False  # the model came from reused derivatives and predicted poorly
    stop: str | None = None


def _quadratic_model(objective: Objective, state: _State) -> _Model:
    """Step 1, the model: the objective's matrices at the point, Newton's step where the
    Newton matrix is positive definite, and the contraction measured against the last full
    step's decrement."""
    B_gn, B, computed = objective.newton_matrices(state.point, state.fresh)
    state.fresh = False
    t0 = time.perf_counter()
    chol = _factor(B)
    g = state.point.g
    step = _newton_step(chol, B, g) if chol is not None else None
    decrement = -0.5 * float(g @ step) if step is not None else np.inf
    if not decrement >= 0:  # not a descent direction: B is not positive definite
        chol, decrement, step = None, np.inf, None
    state.t_solve += time.perf_counter() - t0
    if chol is not None and state.last_full is not None and state.last_full > 0:
        state.theta = float(np.sqrt(decrement / state.last_full))
    return _Model(B_gn, B, computed, objective.exact and computed, chol, step, decrement)


def _small(model: _Model, point: Point, tolerance: float) -> bool:
    """Whether the Newton decrement is below ``tolerance * F`` plus F's rounding level."""
    return model.decrement <= tolerance * max(point.F, 0.0) + ROUNDING * point.magnitude


def _slow(state: _State, options: SolveOptions) -> bool:
    """Whether the measured contraction exceeds ``options.contraction``."""
    return (state.theta or 0.0) > options.contraction


def _certificate(
    objective: Objective,
    model: _Model,
    state: _State,
    tolerance: float,
    options: SolveOptions,
    certify: bool,
) -> str | None:
    """Step 2, certification: ``"decrement"`` or ``"round-off"`` when the stopping rule holds
    at the point (module docstring), else None.  Without ``certify`` the decrement alone
    decides."""
    floor = ROUNDING * state.point.magnitude
    if not _small(model, state.point, tolerance):
        return None
    # the last step was a full step and the iteration contracted by theta; an exact model
    # must also have its derivatives computed at this point
    trusted = (
        state.theta is not None
        and state.theta <= options.contraction
        and (model.hessian or not objective.exact)
    )
    distance = _distance(objective, model.step, state.theta)
    close = distance <= options.distance_tolerance * objective.size
    if (trusted and close) or not certify or model.decrement <= floor:
        return "decrement" if model.decrement > floor else "round-off"
    return None


def _improve_matrix(objective: Objective, model: _Model, state: _State, options) -> bool:
    """Step 3, an approximate matrix must keep earning its keep: after ``SLOW_STEPS``
    iterations in a row where it is indefinite or contracts by more than ``contraction``, or
    after ``APPROXIMATE_ITERATIONS`` in all, the objective improves it by a stage.  True when
    it did (the model is then made again at the same point)."""
    if objective.exact:
        return False
    state.slow = state.slow + 1 if model.factor is None or _slow(state, options) else 0
    if state.slow < SLOW_STEPS and state.iterations < APPROXIMATE_ITERATIONS:
        return False
    if not objective.use_exact():
        return False
    state.theta, state.last_full, state.slow = None, None, 0
    if objective.exact and state.exact_from is None:
        state.exact_from = state.iterations
    return True


def _trust_region_step(objective: Objective, model: _Model, state: _State) -> _Step:
    """Step 4, the step and its acceptance: Newton's step where it fits in the trust region,
    else Steihaug-Toint conjugate gradients on B preconditioned by the Gauss-Newton matrix
    (which follows negative curvature); each tried with its second-order correction where
    the valley curves; accepted when F drops by more than ``ACCEPT`` of the model's
    prediction, the region shrinking by 4 on a poor prediction and doubling on a good one
    at its boundary (where a conjugate-gradient step is also extended, :func:`_extended`)."""
    point, B_gn, B = state.point, model.gauss_newton, model.newton
    floor = ROUNDING * point.magnitude
    t0 = time.perf_counter()
    precondition = None  # the Gauss-Newton matrix's factor, made when first needed
    if model.step is None:
        precondition = _factor(B_gn)
        if precondition is None:  # only when H itself is singular (no pre-roll)
            return _Step(stop="singular")
    if state.radius is None:
        dz0 = model.step if model.step is not None else precondition.solve(-point.g)
        state.radius = _norm(B_gn, dz0)
    newton, refresh, rho, new = False, False, -np.inf, None
    while True:
        if model.step is not None and _norm(B_gn, model.step) <= state.radius * (1 + 1e-12):
            dz, newton = model.step, True
        else:
            precondition = precondition or _factor(B_gn) or model.factor
            dz, newton = steihaug(B, B_gn, precondition, point.g, state.radius), False
        size = _norm(B_gn, dz)
        predicted = -(float(point.g @ dz) + 0.5 * float(dz @ band_matvec(B, dz)))
        state.t_solve += time.perf_counter() - t0
        if not predicted > floor:  # no decrease left above F's rounding level
            if model.computed:
                state.radius = 0.0
            else:
                refresh, rho = True, -np.inf
            break
        new = objective.evaluate(point.z + dz, gradient=False)
        t0 = time.perf_counter()
        rho = (point.F - new.F) / predicted
        if (not newton or rho < 0.25) and predicted > CORRECTION_FLOOR * point.magnitude:
            precondition = precondition or _factor(B_gn) or model.factor
            corrected = _second_order_correction(objective, point, dz, new, precondition)
            if corrected is not None and corrected[1].F < new.F:
                dz, new = corrected
                rho = (point.F - new.F) / predicted
                state.corrections += 1
        if rho < 0.25 and not model.computed:  # a poor model from reused derivatives: renew
            refresh = True
            break
        if rho < 0.25:
            state.radius = 0.25 * size
        elif rho > 0.75 and size >= 0.99 * state.radius:
            state.radius = 2.0 * state.radius
            if not newton:
                new = _extended(objective, point, dz, new, state)
        if rho > ACCEPT:
            break
        if state.radius <= 1e-14 * max(_norm(B_gn, point.z), 1e-300):
            state.radius = 0.0
            break
    if state.radius == 0.0:
        return _Step(stop="no progress")
    if refresh and rho <= ACCEPT:  # retry from the same point with fresh derivatives
        return _Step(refresh=True)
    return _Step(point=new, newton=newton, refresh=refresh)


def _extended(objective: Objective, point: Point, dz: np.ndarray, new: Point,
              state: _State) -> Point:
    """The point of a good boundary step ``dz`` from ``point`` (reaching ``new``) doubled
    while F keeps falling, at most ``EXTRAPOLATIONS`` times; the radius doubles with each."""
    for _ in range(EXTRAPOLATIONS):
        dz = 2.0 * dz
        trial = objective.evaluate(point.z + dz, gradient=False)
        if not trial.F < new.F:
            break
        new = trial
        state.radius = 2.0 * state.radius
    return new


def minimize(
    objective: Objective,
    point: Point,
    options: SolveOptions,
    *,
    tolerance: float | None = None,
    contraction: float | None = None,
    certify: bool = True,
    bar=None,
) -> tuple[Point, SolveReport]:
    """Minimise ``objective`` from ``point`` (evaluated); see the module docstring.

    Each iteration runs four named steps: the quadratic model at the point
    (:func:`_quadratic_model`), certification by the stopping rule (:func:`_certificate`),
    improvement of an approximate matrix that converges slowly (:func:`_improve_matrix`),
    and the trust-region step with its acceptance (:func:`_trust_region_step`).

    ``contraction`` is a contraction factor known from an earlier solve of the same problem
    (a warm start), which lets an approximate matrix certify a start that already meets the
    tolerance.  ``certify=False`` stops on the decrement alone (a coarse level, whose
    solution only starts the fine one).  Returns the final point and a :class:`SolveReport`.
    """
    tol = options.tolerance if tolerance is None else tolerance
    state = _State(point=point, theta=contraction, history=[point.F])
    converged, stop = False, "max_iterations"
    while True:
        model = _quadratic_model(objective, state)
        verdict = _certificate(objective, model, state, tol, options, certify)
        if verdict is not None:
            converged, stop = True, verdict
            break
        if not model.computed and (
            (certify and _small(model, state.point, tol))
            or model.factor is None
            or _slow(state, options)
        ):
            # reused derivatives: check afresh at this point (and renew them when their
            # matrix is indefinite or contracts slowly: it may hide negative curvature)
            state.fresh = True
            continue
        if _improve_matrix(objective, model, state, options):
            continue  # the model again at the same point, with the better matrix
        if state.iterations >= options.max_iterations:
            break
        state.iterations += 1
        step = _trust_region_step(objective, model, state)
        if step.stop is not None:
            stop = step.stop
            break
        if step.point is None:  # retry from the same point with fresh derivatives
            state.iterations -= 1
            state.fresh = True
            continue
        state.newton_steps += step.newton
        state.last_full = model.decrement if step.newton else None
        state.fresh = step.refresh  # a poor step on reused derivatives: renew them
        state.point = objective.with_gradient(step.point)
        state.history.append(step.point.F)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"objective {step.point.F:.6g}")
    return state.point, _report(objective, model, state, converged, stop)


def _report(
    objective: Objective, model: _Model, state: _State, converged: bool, stop: str
) -> SolveReport:
    """The :class:`SolveReport` of a finished :func:`minimize`."""
    point = state.point
    distance = _distance(objective, model.step, state.theta)
    if stop == "round-off" and model.decrement > 0:
        # below F's rounding level the gradient is rounding noise: widen the bound to the move
        # along the Newton direction whose decrement is the rounding level
        distance *= float(np.sqrt(max(ROUNDING * point.magnitude / model.decrement, 1.0)))
    objective.timing["solve"] = objective.timing.get("solve", 0.0) + state.t_solve
    return SolveReport(
        iterations=state.iterations,
        converged=converged,
        stop=stop,
        objective_start=state.history[0],
        objective=point.F,
        objective_history=tuple(state.history),
        newton_decrement=model.decrement,
        contraction=state.theta,
        distance_bound=None if not np.isfinite(distance) else distance,
        exact_newton_from=state.exact_from,
        newton_steps=state.newton_steps,
        corrections=state.corrections,
        evaluations=dict(objective.counts),
        seconds=dict(objective.timing),
    )


def warn_unconverged(report: SolveReport, level: str = "") -> None:
    """A :class:`WarpedSolveWarning` with the decrement reached."""
    decrement = (f"Newton decrement {report.newton_decrement:.2e}"
                 if np.isfinite(report.newton_decrement) else
                 "no Newton decrement (the last Newton matrix was not positive definite: the "
                 "iterate is not near a minimum)")
    warn(
        f"warped solve{level} did not converge in {counted(report.iterations, 'iteration')} "
        f"({report.stop}): objective {report.objective:.6g} (start "
        f"{report.objective_start:.6g}), {decrement}; the result is the best iterate",
        WarpedSolveWarning,
    )
