"""The warped solve on two levels, and warm starts (Schulz et al. 2014, Theorem 2).

Bodies above ``COARSE_WARP_ABOVE`` tets have a coarse level: the warp of a coarse mesh of
the same solid (:mod:`wiggly.warp.transfer`).  The warped solve then runs

1. on the coarse level: F~ (the objective with W~ in place of W) by Gauss-Newton steps
   from the linear start (positive definite matrices, so full steps far from the solution),
   with the curvature added when they contract slowly (a warm start, near its solution,
   takes Newton steps at once); each iteration costs a few milliseconds, and its
   solution lies within the coarse mesh's error of the fine one;
2. on the fine level from there: the exact fine objective, with Newton matrices from the
   coarse level (approximate: linear convergence, certified by the measured contraction;
   exact fine matrices when it is slow), whose Jacobians carry the coarse mesh's
   interpolation error of the modes (:mod:`wiggly.solve.warped`).  This changes the path,
   never the solution.

Smaller bodies solve on the fine level only, with exact Newton matrices, and so do bodies
whose coarse mesh is not coarser (more than ``COARSER`` of the fine mesh's tets: thin parts
keep fTetWild's coarse mesh at the fine edge length).

Warm starts.  A solve returns a :class:`WarmStart` (``Animation.warm_start``); the caller
passes it back to re-solve the problem with edited keyframes.  It holds the last fine point
z0 (with W and the pulled-back cotangents there, so the edited objective at z0 costs the
changed keyframes only) and the measured contraction.  The coarse level then gets the full
approximation scheme's correction (Brandt 1977): the linear term ``tau^T z``, ``tau = grad F(z0)
- grad F~(z0)``, that makes its gradient equal the fine one at z0, so the coarse mesh's error
reaches the new start only through its change over the edit.  The corrected start is kept
only if the fine objective drops there; otherwise the plain coarse solve follows.  A small
edit skips the coarse level: when the first fine Newton step from z0 moves no vertex by more
than ``NEAR`` of the body's size, the fine level starts at z0 (its coarse-model iteration
then does what the coarse level would, without the transfer).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from wiggly.keyframes import Keyframe
from wiggly.progress import iterations
from wiggly.solve.banded import BandedCholesky
from wiggly.solve.blocks import NewtonBlocks
from wiggly.solve.optimizer import SolveOptions, minimize, warn_unconverged
from wiggly.solve.warped import WarpedObjective, WarpedPoint

if TYPE_CHECKING:
    from wiggly.solve.problem import SpacetimeProblem

__all__ = ["WarmStart", "solve_warped"]

# A warm start whose first fine Newton step moves no vertex by more than this share of the
# body's size goes to the fine level directly: there, one iteration with the coarse-model
# matrix gains as much as the whole coarse level (and its transfer) does.
NEAR = 0.1
# A coarse level with more than this share of the fine mesh's tets is no coarser (fTetWild
# keeps thin legs and tails at about the fine mesh's edge length: the camel's "coarse" mesh
# had 27.6k tets for a 7.9k-tet body), so its iterations cost more than the fine level's
# exact ones and it gains nothing: such bodies solve on the fine level alone.
COARSER = 0.5


@dataclass(frozen=True, eq=False)
class WarmStart:
    """What a warped solve leaves for the next solve of the same problem."""

    nodes: np.ndarray
    z: np.ndarray
    keyframes: tuple[Keyframe, ...]
    point: WarpedPoint  # the fine objective at z
    contraction: float | None  # measured on the fine level (approximate Newton matrices)
    blocks: NewtonBlocks  # the derivatives behind the last Newton matrices

    def fits(self, nodes: np.ndarray, size: int) -> bool:
        """Whether a problem with these node times and ``size`` unknowns can start here."""
        return (
            self.nodes.shape == nodes.shape
            and bool(np.allclose(self.nodes, nodes))
            and self.z.size == size
        )


def same_keyframes(a: tuple[Keyframe, ...] | list[Keyframe], b: list[Keyframe]) -> bool:
    """Whether two validated keyframe lists pose the same problem."""

    def same(x, y) -> bool:
        return (x is None and y is None) or (
            x is not None and y is not None and np.array_equal(x, y)
        )

    return len(a) == len(b) and all(
        p.time == q.time
        and p.on == q.on
        and (p.stiffness, p.c_A, p.c_B) == (q.stiffness, q.c_A, q.c_B)
        and same(p.vertices, q.vertices)
        and same(p.position, q.position)
        and same(p.velocity, q.velocity)
        for p, q in zip(a, b, strict=True)
    )


def solve_warped(
    problem: SpacetimeProblem,
    kfs: list[Keyframe],
    nodes: np.ndarray,
    z0: np.ndarray,
    options: SolveOptions,
    warm: WarmStart | None,
) -> tuple[np.ndarray, dict, WarmStart]:
    """Minimise E + E_WC from z0 (module docstring); returns z, a report, the warm start."""
    body = problem.body
    coarse = body.coarse_level if options.two_level else body.fine_level
    if coarse.warp.n_tets > COARSER * body.fine_level.warp.n_tets:
        coarse = body.fine_level
    two = not coarse.exact
    blocks = warm.blocks if warm is not None and warm.blocks.level is coarse else None
    blocks = blocks or NewtonBlocks(coarse)
    fine = WarpedObjective(
        problem, body.fine_level, kfs, nodes, model=coarse if two else None, blocks=blocks
    )
    report: dict = {}
    with iterations("warped solve (Newton)") as tqdm_bar:
        bar = _Iterations(tqdm_bar, options.callback)
        start = None
        if warm is not None:  # cheap: W at z0 is kept
            start = fine.evaluate(z0, prior=warm.point)
        continuation = warm is not None and same_keyframes(warm.keyframes, kfs)
        if two and not continuation and not (start is not None and _near(fine, start)):
            start, report["coarse"] = _coarse_level(
                problem, coarse, kfs, nodes, fine, z0, start, options, bar, blocks
            )
        elif start is None:
            start = fine.evaluate(z0)
        point, fine_report = minimize(
            fine, start, options, contraction=warm.contraction if warm else None, bar=bar
        )
    report.update(fine_report.as_info())
    if not fine_report.converged and options.warn:
        warn_unconverged(fine_report)
    theta = fine_report.contraction
    if theta is None and warm is not None:
        theta = warm.contraction
    return point.z, report, WarmStart(nodes.copy(), point.z, tuple(kfs), point, theta, fine.blocks)


class _Iterations:
    """The progress bar of both levels, calling ``callback(iterations so far)`` after each
    iteration (:attr:`SolveOptions.callback`)."""

    def __init__(self, bar, callback) -> None:
        self.bar, self.callback, self.count = bar, callback, 0

    def update(self, n: int) -> None:
        self.bar.update(n)
        self.count += n
        if self.callback is not None:
            self.callback(self.count)

    def set_postfix_str(self, text: str) -> None:
        self.bar.set_postfix_str(text)


def _near(fine: WarpedObjective, start: WarpedPoint) -> bool:
    """Whether a warm start is near enough for the fine level alone: the Newton step of the
    fine objective's (coarse-model) matrix at the start exists and moves no vertex by more
    than ``NEAR`` of the body's size."""
    _, B, _ = fine.newton_matrices(start)
    try:
        dz = BandedCholesky(B).solve(-start.g, refine=False)
    except np.linalg.LinAlgError:
        return False
    return fine.step_size(dz) <= NEAR * fine.size


def _coarse_level(problem, coarse, kfs, nodes, fine, z0, start, options, bar, blocks):
    """The coarse first level from z0 (``start``: the fine objective at a warm start's z0,
    or None); returns the fine point where the fine level starts and the coarse level's
    report."""
    plain = WarpedObjective(problem, coarse, kfs, nodes, blocks=blocks, curvature=False)
    at_z0 = plain.evaluate(z0)
    if start is not None:  # full approximation scheme from the last fine point
        tau = start.g - at_z0.g
        correction = (tau, start.F - at_z0.F - float(tau @ z0))
        corrected = WarpedObjective(  # near its solution: Newton's matrices at once
            problem, coarse, kfs, nodes, correction=correction, blocks=blocks
        )
        point, result = minimize(
            corrected, corrected.evaluate(z0, prior=at_z0), options,
            tolerance=options.coarse_tolerance, certify=False, bar=bar,
        )
        candidate = fine.evaluate(point.z)
        if result.converged and candidate.F < start.F:
            return candidate, {**result.as_info(), "corrected": True}
    point, result = minimize(
        plain, at_z0, options, tolerance=options.coarse_tolerance, certify=False, bar=bar
    )
    report = result.as_info()
    candidate = fine.evaluate(point.z)
    if start is not None and candidate.F >= start.F:
        report["kept_start"] = True
        return start, report
    return candidate, report
