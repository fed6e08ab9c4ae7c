"""The rig's motion through a driver's frames: a C^2 cubic spline of many fields at once.

The driver's poses, extended into the tet mesh (:mod:`wiggly.drive.unwarp`), are known at
its frames only; secondary motion (:mod:`wiggly.drive.secondary`) needs them, their velocities
and accelerations at any time, and the Taylor coefficients of the cubic on each interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.interpolate import CubicSpline
from scipy.linalg import solve_banded

__all__ = ["FrameSpline"]

#: Columns per chunk when fitting cubic splines to many fields at once (bounds memory).
_CHUNK = 4096


@dataclass(frozen=True)
class FrameSpline:
    """A C^2 cubic spline through frames ``values`` (F, N) at ``times`` (F,), held in Hermite
    form (values and slopes at the frames); constant before the first and after the last
    frame."""

    times: np.ndarray
    values: np.ndarray
    slopes: np.ndarray

    @classmethod
    def fit(cls, times: np.ndarray, values: np.ndarray, *, loop: bool = False,
            hold_start: bool = False, hold_end: bool = False) -> FrameSpline:
        """The cubic spline through ``values``: periodic for a ``loop``; otherwise zero slope
        at an end where the motion holds its pose beyond the frames (``hold_start``,
        ``hold_end``), not-a-knot elsewhere."""
        times = np.asarray(times, float)
        values = np.ascontiguousarray(values, dtype=float)
        if len(times) < 2:
            return cls(times, values, np.zeros_like(values))
        if loop:
            # the last frame is the first again (secondary_frames); fields computed from it
            # separately may differ from the first's in their last bits, which a periodic
            # spline refuses
            values = values.copy()
            values[-1] = values[0]
            bc = "periodic"
        else:
            bc = ((1, 0.0) if hold_start else "not-a-knot", (1, 0.0) if hold_end else
                  "not-a-knot")
            if len(times) < 4 and "not-a-knot" in bc:
                bc = ((1, 0.0) if hold_start else (2, 0.0), (1, 0.0) if hold_end else (2, 0.0))
        if not loop and len(times) >= 4:  # one banded solve for every column
            return cls(times, values, _spline_slopes(times, values, hold_start, hold_end))
        slopes = np.empty_like(values)
        for c0 in range(0, values.shape[1], _CHUNK):
            c1 = min(values.shape[1], c0 + _CHUNK)
            end_bc = bc if isinstance(bc, str) else tuple(
                b if isinstance(b, str) else (b[0], np.zeros(c1 - c0)) for b in bc)
            slopes[:, c0:c1] = CubicSpline(times, values[:, c0:c1], bc_type=end_bc)(times, 1)
        return cls(times, values, slopes)

    def _segment(self, t: np.ndarray, side: str = "right"):
        T = self.times
        j = np.clip(np.searchsorted(T, t, side=side) - 1, 0, len(T) - 2)
        h = T[j + 1] - T[j]
        s = np.clip((t - T[j]) / h, 0.0, 1.0)
        inside = (t >= T[0]) & (t <= T[-1])
        return j, h, s, inside

    def __call__(self, t: ArrayLike, derivative: int = 0) -> np.ndarray:
        """Values (or the ``derivative``-th time derivative) at times ``t``: shape (T, N)."""
        t = np.atleast_1d(np.asarray(t, float))
        if len(self.times) < 2:
            v = self.values[0] if derivative == 0 else np.zeros(self.values.shape[1])
            return np.tile(v, (len(t), 1))
        j, h, s, inside = self._segment(t)
        if derivative == 0:
            b = [2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2]
        elif derivative == 1:
            b = [(6 * s**2 - 6 * s) / h, 3 * s**2 - 4 * s + 1, (-6 * s**2 + 6 * s) / h,
                 3 * s**2 - 2 * s]
        elif derivative == 2:
            b = [(12 * s - 6) / h**2, (6 * s - 4) / h, (-12 * s + 6) / h**2, (6 * s - 2) / h]
        else:
            raise ValueError("derivative must be 0, 1 or 2")
        if derivative == 0:  # slopes enter as h m in the unit-interval Hermite basis
            b[1] = b[1] * h
            b[3] = b[3] * h
        if derivative > 0:
            b = [np.where(inside, x, 0.0) for x in b]
        out = (b[0][:, None] * self.values[j] + b[1][:, None] * self.slopes[j]
               + b[2][:, None] * self.values[j + 1] + b[3][:, None] * self.slopes[j + 1])
        if derivative == 0:  # held poses outside the frames
            out[t < self.times[0]] = self.values[0]
            out[t > self.times[-1]] = self.values[-1]
        return out

    def taylor(self, t: np.ndarray) -> np.ndarray:
        """Taylor coefficients (T, 4, N) of the cubic right of each time t: value, first
        derivative, second / 2 and third / 6 (zero derivatives outside the frames)."""
        t = np.atleast_1d(np.asarray(t, float))
        N = self.values.shape[1]
        out = np.zeros((len(t), 4, N))
        out[:, 0] = self(t)
        if len(self.times) < 2:
            return out
        j, h, _, _ = self._segment(t, side="right")
        inside = (t >= self.times[0]) & (t < self.times[-1])
        y0, y1 = self.values[j], self.values[j + 1]
        m0, m1 = self.slopes[j], self.slopes[j + 1]
        hh = h[:, None]
        d = (y1 - y0) / hh
        # cubic on the segment in local time x = t - T[j]: y0 + m0 x + c2 x^2 + c3 x^3
        c2 = (3 * d - 2 * m0 - m1) / hh
        c3 = (m0 + m1 - 2 * d) / hh**2
        x = (t - self.times[j])[:, None]
        out[:, 1] = np.where(inside[:, None], m0 + 2 * c2 * x + 3 * c3 * x**2, 0.0)
        out[:, 2] = np.where(inside[:, None], c2 + 3 * c3 * x, 0.0)
        out[:, 3] = np.where(inside[:, None], c3, 0.0)
        return out


def _spline_slopes(x: np.ndarray, y: np.ndarray, clamped_start: bool,
                   clamped_end: bool) -> np.ndarray:
    """Slopes (F, N) at the knots of the C^2 cubic spline through y (F, N), F >= 4: the
    tridiagonal system of spline slopes with a zero slope (clamped) or not-a-knot condition
    at each end, one banded solve for all columns (the system scipy's CubicSpline solves,
    without its piecewise-polynomial coefficients)."""
    n = len(x)
    dx = np.diff(x)
    slope = np.diff(y, axis=0) / dx[:, None]
    A = np.zeros((3, n))
    A[1, 1:-1] = 2 * (dx[:-1] + dx[1:])
    A[0, 2:] = dx[:-1]
    A[-1, :-2] = dx[1:]
    b = np.empty_like(y)
    b[1:-1] = 3 * (dx[1:, None] * slope[:-1] + dx[:-1, None] * slope[1:])
    if clamped_start:
        A[1, 0], A[0, 1], b[0] = 1.0, 0.0, 0.0
    else:  # not-a-knot: the first two intervals are one cubic
        d = x[2] - x[0]
        A[1, 0], A[0, 1] = dx[1], d
        b[0] = ((dx[0] + 2 * d) * dx[1] * slope[0] + dx[0] ** 2 * slope[1]) / d
    if clamped_end:
        A[1, -1], A[-1, -2], b[-1] = 1.0, 0.0, 0.0
    else:
        d = x[-1] - x[-3]
        A[1, -1], A[-1, -2] = dx[-2], d
        b[-1] = (dx[-1] ** 2 * slope[-2] + (2 * d + dx[-1]) * dx[-2] * slope[-1]) / d
    return solve_banded((1, 1), A, b, overwrite_ab=True, overwrite_b=True,
                        check_finite=False)
