"""The warp's per-tet formulas on component fields, in numpy.

Schulz et al. 2014, Theorem 2; Huang et al. 2011.

A block of per-tet 3x3 fields is an array ``B`` of shape (3, 3, c, mb): ``B[i, j]`` is entry
(i, j) for c columns (frames or directions) and mb tets; per-tet data shared by all columns
has shape (1, mb) and broadcasts.  With the displacement gradient ``A = grad u``:

* rotation vector ``w = axial((A - A^T)/2)``, strain ``S = (A + A^T)/2``;
* target gradient ``H(A) = exp([w]x)(I + S) - I``, evaluated as ``(R - I) + S + (R - I) S``;
* tangent ``dH = [J(w) dw]x F + R dS``, ``F = R (I + S)``, ``J`` the left Jacobian of the
  rotation map (``d exp([w]x)[dw] = [J(w) dw]x exp([w]x)``);
* cotangent (adjoint of the tangent) ``sym(R^T Y) + [J(w)^T g]x / 2``, ``g = 2 axial(Y F^T)``.

These are the reference implementation of :mod:`wiggly.warp.compiled` (tested against it).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["rotation_coefficients"]

# Below this angle (radians) the coefficient c = (th - sin th) / th^3 of the rotation
# derivative is evaluated by its Taylor series in th^2 (truncation error < 1e-19 there).
_SERIES_ANGLE = 0.1
# Angles are clamped below by this value so that sin(th) / th needs no special case.
_TINY_ANGLE = 1e-300

Field = np.ndarray
Mat = Sequence[Sequence[Field]]


def _cross(u: Sequence[Field], v: Sequence[Field]) -> tuple[Field, Field, Field]:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _rotation_strain(E: Mat) -> tuple[tuple[Field, Field, Field], Mat]:
    """Rotation vector ``w = axial((A - A^T)/2)`` and strain ``S = (A + A^T)/2`` of ``A``."""
    w = (0.5 * (E[2][1] - E[1][2]), 0.5 * (E[0][2] - E[2][0]), 0.5 * (E[1][0] - E[0][1]))
    s01 = 0.5 * (E[0][1] + E[1][0])
    s02 = 0.5 * (E[0][2] + E[2][0])
    s12 = 0.5 * (E[1][2] + E[2][1])
    S = ((E[0][0], s01, s02), (s01, E[1][1], s12), (s02, s12, E[2][2]))
    return w, S


def rotation_coefficients(
    theta2: np.ndarray, *, derivative: bool = False
) -> tuple[np.ndarray, ...]:
    """Rodrigues coefficients from ``theta2 = |w|^2``, accurate at every angle.

    ``a = sin(th)/th`` and ``b = (1 - cos th)/th^2 = (sin(th/2)/th)^2 * 2``, so that
    ``exp([w]x) = I + a [w]x + b [w]x^2``. With ``derivative=True`` also
    ``c = (th - sin th)/th^3`` (Taylor series below ``th = 0.1``), so that the left
    Jacobian of the rotation map is ``J(w) = I + b [w]x + c [w]x^2`` and
    ``d exp([w]x)[dw] = [J(w) dw]x exp([w]x)``.
    """
    th = np.sqrt(theta2)
    np.maximum(th, _TINY_ANGLE, out=th)
    a = np.sin(th)
    a /= th
    b = np.sin(0.5 * th)
    b /= th
    b *= b
    b *= 2.0
    if not derivative:
        return a, b
    x = theta2
    c_series = 1.0 / 6.0 - x / 120.0 * (1.0 - x / 42.0 * (1.0 - x / 72.0 * (1.0 - x / 110.0)))
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.where(x < _SERIES_ANGLE**2, c_series, (1.0 - a) / x)
    return a, b, c


def _rotation_minus_identity(w: Sequence[Field], a: Field, b: Field) -> Mat:
    """``exp([w]x) - I = a [w]x + b (w w^T - |w|^2 I)``, free of cancellation for small ``w``."""
    bw0, bw1, bw2 = b * w[0], b * w[1], b * w[2]
    p01, p02, p12 = bw0 * w[1], bw0 * w[2], bw1 * w[2]
    q0, q1, q2 = a * w[0], a * w[1], a * w[2]
    return (
        (-(bw1 * w[1] + bw2 * w[2]), p01 - q2, p02 + q1),
        (p01 + q2, -(bw0 * w[0] + bw2 * w[2]), p12 - q0),
        (p02 - q1, p12 + q0, -(bw0 * w[0] + bw1 * w[1])),
    )


def target_block(out: np.ndarray, A: np.ndarray) -> None:
    """Target displacement gradient ``exp([w]x)(I + S) - I`` (Schulz et al. 2014, Theorem 2).

    Evaluated as ``(R - I) + S + (R - I) S``, accurate for tiny gradients.
    """
    w, S = _rotation_strain(A)
    a, b = rotation_coefficients(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    Rm = _rotation_minus_identity(w, a, b)
    for i in range(3):
        for j in range(3):
            out[i, j] = (
                Rm[i][j] + S[i][j] + Rm[i][0] * S[0][j] + Rm[i][1] * S[1][j] + Rm[i][2] * S[2][j]
            )


def linearization(A: np.ndarray) -> list[Field]:
    """Per-tet quantities for derivatives at gradient ``A``: ``[w, b, c, R, F]`` (23 fields)."""
    w, S = _rotation_strain(A)
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    a, b, c = rotation_coefficients(t2, derivative=True)
    Rm = _rotation_minus_identity(w, a, b)
    R = [[Rm[i][j] + 1.0 if i == j else Rm[i][j] for j in range(3)] for i in range(3)]
    F = [
        [R[i][j] + R[i][0] * S[0][j] + R[i][1] * S[1][j] + R[i][2] * S[2][j] for j in range(3)]
        for i in range(3)
    ]
    return [
        *w,
        b,
        c,
        *(R[i][j] for i in range(3) for j in range(3)),
        *(F[i][j] for i in range(3) for j in range(3)),
    ]


def _unpack(lin: Sequence[Field]) -> tuple[Sequence[Field], Field, Field, Mat, Mat]:
    return (
        lin[0:3],
        lin[3],
        lin[4],
        [lin[5 + 3 * i : 8 + 3 * i] for i in range(3)],
        [lin[14 + 3 * i : 17 + 3 * i] for i in range(3)],
    )


def tangent_block(out: np.ndarray, lin: Sequence[Field], dA: np.ndarray) -> None:
    """``dH = [J(w) dw]x F + R dS`` with ``dw``, ``dS`` the rotation/strain parts of ``dA``."""
    w, b, c, R, F = _unpack(lin)
    dw, dS = _rotation_strain(dA)
    wxd = _cross(w, dw)
    wwd = _cross(w, wxd)
    v = [dw[k] + b * wxd[k] + c * wwd[k] for k in range(3)]
    for j in range(3):
        vxF = _cross(v, (F[0][j], F[1][j], F[2][j]))
        for i in range(3):
            out[i, j] = vxF[i] + R[i][0] * dS[0][j] + R[i][1] * dS[1][j] + R[i][2] * dS[2][j]


def cotangent_block(out: np.ndarray, lin: Sequence[Field], Yb: np.ndarray) -> None:
    """Adjoint of :func:`_jvp_block`: ``sym(R^T Y) + [J(w)^T g]x / 2``, ``g = 2 axial(Y F^T)``."""
    w, b, c, R, F = _unpack(lin)
    Y = Yb
    g = [
        Y[2][0] * F[1][0]
        + Y[2][1] * F[1][1]
        + Y[2][2] * F[1][2]
        - Y[1][0] * F[2][0]
        - Y[1][1] * F[2][1]
        - Y[1][2] * F[2][2],
        Y[0][0] * F[2][0]
        + Y[0][1] * F[2][1]
        + Y[0][2] * F[2][2]
        - Y[2][0] * F[0][0]
        - Y[2][1] * F[0][1]
        - Y[2][2] * F[0][2],
        Y[1][0] * F[0][0]
        + Y[1][1] * F[0][1]
        + Y[1][2] * F[0][2]
        - Y[0][0] * F[1][0]
        - Y[0][1] * F[1][1]
        - Y[0][2] * F[1][2],
    ]
    wxg = _cross(w, g)
    wwg = _cross(w, wxg)
    half = [0.5 * (g[k] - b * wxg[k] + c * wwg[k]) for k in range(3)]
    P = [
        [R[0][i] * Y[0][j] + R[1][i] * Y[1][j] + R[2][i] * Y[2][j] for j in range(3)]
        for i in range(3)
    ]
    s01 = 0.5 * (P[0][1] + P[1][0])
    s02 = 0.5 * (P[0][2] + P[2][0])
    s12 = 0.5 * (P[1][2] + P[2][1])
    out[:] = (
        (P[0][0], s01 - half[2], s02 + half[1]),
        (s01 + half[2], P[1][1], s12 - half[0]),
        (s02 - half[1], s12 + half[0], P[2][2]),
    )


