"""Compiled per-tet kernels of the rotation-strain warp (SYSTEM.md §6; Huang et al. 2011).

The warp's per-tet arithmetic (gradient of ``u``, rotation vector and strain, Rodrigues, and
the scatter ``G^T Vol`` back to the vertices) fused into one pass over the tets, compiled with
numba.  :class:`wiggly.warp.kernels.NumbaKernels` wraps them; the vectorized numpy path
(:mod:`wiggly.warp.kernels_numpy`) is an independent implementation of the same formulas,
and the two are tested against each other.

Conventions: ``tets`` (m, 4) int64, ``grads`` (m, 4, 3) the gradients of the four P1 basis
functions of each tet, ``vol`` (m,) volumes.  Displacement fields are (f, n, 3) arrays (f
frames or directions); outputs are accumulated into zeroed (f, n, 3) arrays, in parallel over
the f fields.  A local 3x3 matrix ``M`` is a flat array of 9, ``M[3 i + j] = M_ij``, and the
displacement gradient is ``A_ij = d u_i / d X_j``.

Formulas (the same as :mod:`wiggly.warp.tetmath`):

* ``w = axial((A - A^T) / 2)``, ``S = (A + A^T) / 2``, ``R = exp([w]x) = I + a [w]x + b [w]x^2``
  with ``a = sin(th)/th``, ``b = (1 - cos th)/th^2``; target ``H = (R - I) + S + (R - I) S``;
* tangent ``dH = [J(w) dw]x F + R dS`` with ``F = R (I + S)`` and the left Jacobian
  ``J(w) = I + b [w]x + c [w]x^2``, ``c = (th - sin th)/th^3``;
* its adjoint ``dA = sym(R^T Y) + [J(w)^T g / 2]x`` with ``g = 2 axial(Y F^T)``: the gradient
  ``grad_A (Y : H(A))``, whose derivatives (by central differences) give the curvature terms.
"""

from __future__ import annotations

import math
import os

import numpy as np

try:  # numba is a dependency; the numpy path remains for platforms without its wheels
    if os.environ.get("WIGGLY_NUMBA", "1") == "0":
        raise ImportError("disabled by WIGGLY_NUMBA=0")
    from numba import njit, prange

    AVAILABLE = True
except ImportError:  # pragma: no cover - exercised with WIGGLY_NUMBA=0
    AVAILABLE = False

    def njit(*_args, **_kwargs):
        return lambda fn: fn

    prange = range

jit = njit(cache=True, fastmath={"contract"}, nogil=True, inline="always")
pjit = njit(cache=True, fastmath={"contract"}, nogil=True, parallel=True)

__all__ = [
    "AVAILABLE",
    "chunks",
    "compile_all",
    "curvature_products",
    "field_gradients",
    "jacobians_rhs",
    "jvp_rhs",
    "second_derivatives_rhs",
    "target_rhs",
    "vjp_rhs",
]

# Up to th = pi the Rodrigues coefficients are their Taylor series in t2 = th^2 (no sqrt, sin,
# cos or division): a = sum (-t2)^k/(2k+1)!, b = sum (-t2)^k/(2k+2)!, c = sum (-t2)^k/(2k+3)!.
# The first omitted terms are below pi^28/29! ~ 1e-17 (a), pi^28/30! ~ 3e-19 (b) and
# pi^26/29! ~ 1e-18 (c), and the largest term is 1.7 (a at th = pi): errors ~1e-16 absolute.
_POLY_ANGLE2 = math.pi**2
_A = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(14))
_B = tuple((-1.0) ** k / math.factorial(2 * k + 2) for k in range(14))
_C = tuple((-1.0) ** k / math.factorial(2 * k + 3) for k in range(13))
# Per-tet linearization record: w (3), b, c, R (9), F (9).
_LIN = 23
@jit
def gradient(U, tets, grads, t, A):
    """``A_ij = sum_k U[v_k, i] grad_k_j`` on tet ``t``."""
    for x in range(9):
        A[x] = 0.0
    for k in range(4):
        v = tets[t, k]
        g0, g1, g2 = grads[t, k, 0], grads[t, k, 1], grads[t, k, 2]
        for i in range(3):
            ui = U[v, i]
            A[3 * i] += ui * g0
            A[3 * i + 1] += ui * g1
            A[3 * i + 2] += ui * g2


@jit
def scatter(H, scale, tets, grads, t, out):
    """``out[v_k, i] += scale sum_j H_ij grad_k_j`` (the adjoint of :func:`gradient`)."""
    for k in range(4):
        v = tets[t, k]
        g0, g1, g2 = grads[t, k, 0], grads[t, k, 1], grads[t, k, 2]
        for i in range(3):
            out[v, i] += scale * (H[3 * i] * g0 + H[3 * i + 1] * g1 + H[3 * i + 2] * g2)


@jit
def _series(coefficients, t2):
    """``sum_k coefficients[k] t2^k`` (Horner)."""
    acc = coefficients[len(coefficients) - 1]
    for k in range(len(coefficients) - 2, -1, -1):
        acc = acc * t2 + coefficients[k]
    return acc


@jit
def rotation_ab(t2):
    """``a = sin(th)/th`` and ``b = (1 - cos th)/th^2`` from ``t2 = th^2``: Taylor series up
    to th = pi, beyond it one sin and one cos of ``th/2`` (``a = 2 sin(th/2) cos(th/2)/th``,
    ``b = 2 (sin(th/2)/th)^2``)."""
    if t2 <= _POLY_ANGLE2:
        return _series(_A, t2), _series(_B, t2)
    th = math.sqrt(t2)
    s = math.sin(0.5 * th) / th
    return 2.0 * s * math.cos(0.5 * th), 2.0 * s * s


@jit
def rotation_c(t2, a):
    """``c = (th - sin th)/th^3``: Taylor series up to th = pi, beyond it ``(1 - a)/t2``."""
    if t2 <= _POLY_ANGLE2:
        return _series(_C, t2)
    return (1.0 - a) / t2


# t-derivatives of b and c (t = th^2), for second derivatives of the rotation map
_BT = tuple(k * _B[k] for k in range(1, 14))
_CT = tuple(k * _C[k] for k in range(1, 13))
# unit gradient E_k (flat k = 3 i + j): its rotation vector is SIGN[k] e_COMPONENT[k]
_COMPONENT = (-1, 2, 1, 2, -1, 0, 1, 0, -1)
_SIGN = (0.0, -0.5, 0.5, 0.5, 0.0, -0.5, -0.5, 0.5, 0.0)


@jit
def rotation_bc_derivatives(t2):
    """``db/dt`` and ``dc/dt`` with ``t = th^2``: Taylor series up to th = pi, beyond it
    ``(th sin th - 2 + 2 cos th) / (2 th^4)`` and ``(th (1 - cos th) - 3 th + 3 sin th) /
    (2 th^5)``."""
    if t2 <= _POLY_ANGLE2:
        return _series(_BT, t2), _series(_CT, t2)
    th = math.sqrt(t2)
    s, co = math.sin(th), math.cos(th)
    return (th * s - 2.0 + 2.0 * co) / (2.0 * t2 * t2), (
        th * (1.0 - co) - 3.0 * th + 3.0 * s
    ) / (2.0 * t2 * t2 * th)


@jit
def rotation_minus_identity(w0, w1, w2, a, b, Rm):
    """``exp([w]x) - I = a [w]x + b (w w^T - |w|^2 I)``."""
    Rm[0] = -b * (w1 * w1 + w2 * w2)
    Rm[1] = b * w0 * w1 - a * w2
    Rm[2] = b * w0 * w2 + a * w1
    Rm[3] = b * w0 * w1 + a * w2
    Rm[4] = -b * (w0 * w0 + w2 * w2)
    Rm[5] = b * w1 * w2 - a * w0
    Rm[6] = b * w0 * w2 - a * w1
    Rm[7] = b * w1 * w2 + a * w0
    Rm[8] = -b * (w0 * w0 + w1 * w1)


@jit
def strain(A, S):
    for i in range(3):
        for j in range(3):
            S[3 * i + j] = 0.5 * (A[3 * i + j] + A[3 * j + i])


@jit
def target(A, S, Rm, H):
    """``H = exp([w]x)(I + S) - I`` evaluated as ``(R - I) + S + (R - I) S``."""
    w0 = 0.5 * (A[7] - A[5])
    w1 = 0.5 * (A[2] - A[6])
    w2 = 0.5 * (A[3] - A[1])
    a, b = rotation_ab(w0 * w0 + w1 * w1 + w2 * w2)
    rotation_minus_identity(w0, w1, w2, a, b, Rm)
    strain(A, S)
    for i in range(3):
        for j in range(3):
            H[3 * i + j] = (
                Rm[3 * i + j]
                + S[3 * i + j]
                + Rm[3 * i] * S[j]
                + Rm[3 * i + 1] * S[3 + j]
                + Rm[3 * i + 2] * S[6 + j]
            )


@jit
def linearize(A, S, lin):
    """``lin = [w, b, c, R, F]`` at gradient ``A``."""
    w0 = 0.5 * (A[7] - A[5])
    w1 = 0.5 * (A[2] - A[6])
    w2 = 0.5 * (A[3] - A[1])
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    a, b = rotation_ab(t2)
    c = rotation_c(t2, a)
    lin[0], lin[1], lin[2], lin[3], lin[4] = w0, w1, w2, b, c
    R = lin[5:14]
    F = lin[14:23]
    rotation_minus_identity(w0, w1, w2, a, b, R)
    R[0] += 1.0
    R[4] += 1.0
    R[8] += 1.0
    strain(A, S)
    for i in range(3):
        for j in range(3):
            F[3 * i + j] = (
                R[3 * i + j] + R[3 * i] * S[j] + R[3 * i + 1] * S[3 + j] + R[3 * i + 2] * S[6 + j]
            )


@jit
def tangent(lin, dA, dS, dH):
    """``dH = [J(w) dw]x F + R dS``."""
    w0, w1, w2, b, c = lin[0], lin[1], lin[2], lin[3], lin[4]
    R = lin[5:14]
    F = lin[14:23]
    d0 = 0.5 * (dA[7] - dA[5])
    d1 = 0.5 * (dA[2] - dA[6])
    d2 = 0.5 * (dA[3] - dA[1])
    strain(dA, dS)
    x0 = w1 * d2 - w2 * d1  # w x dw
    x1 = w2 * d0 - w0 * d2
    x2 = w0 * d1 - w1 * d0
    y0 = w1 * x2 - w2 * x1  # w x (w x dw)
    y1 = w2 * x0 - w0 * x2
    y2 = w0 * x1 - w1 * x0
    v0 = d0 + b * x0 + c * y0
    v1 = d1 + b * x1 + c * y1
    v2 = d2 + b * x2 + c * y2
    for j in range(3):
        f0, f1, f2 = F[j], F[3 + j], F[6 + j]
        dH[j] = v1 * f2 - v2 * f1
        dH[3 + j] = v2 * f0 - v0 * f2
        dH[6 + j] = v0 * f1 - v1 * f0
        for i in range(3):
            dH[3 * i + j] += R[3 * i] * dS[j] + R[3 * i + 1] * dS[3 + j] + R[3 * i + 2] * dS[6 + j]


@jit
def cotangent(lin, Y, dA):
    """Adjoint of :func:`tangent`: ``dA = sym(R^T Y) + [J(w)^T g / 2]x``."""
    w0, w1, w2, b, c = lin[0], lin[1], lin[2], lin[3], lin[4]
    R = lin[5:14]
    F = lin[14:23]
    # g = axial-difference of Y F^T: g_0 = (Y F^T)_21 - (Y F^T)_12, cyclic
    P = dA  # scratch: (Y F^T) first
    for i in range(3):
        for j in range(3):
            P[3 * i + j] = (
                Y[3 * i] * F[3 * j] + Y[3 * i + 1] * F[3 * j + 1] + (Y[3 * i + 2] * F[3 * j + 2])
            )
    g0 = P[7] - P[5]
    g1 = P[2] - P[6]
    g2 = P[3] - P[1]
    x0 = w1 * g2 - w2 * g1
    x1 = w2 * g0 - w0 * g2
    x2 = w0 * g1 - w1 * g0
    y0 = w1 * x2 - w2 * x1
    y1 = w2 * x0 - w0 * x2
    y2 = w0 * x1 - w1 * x0
    h0 = 0.5 * (g0 - b * x0 + c * y0)
    h1 = 0.5 * (g1 - b * x1 + c * y1)
    h2 = 0.5 * (g2 - b * x2 + c * y2)
    for i in range(3):  # P = R^T Y
        for j in range(3):
            P[3 * i + j] = R[i] * Y[j] + R[3 + i] * Y[3 + j] + R[6 + i] * Y[6 + j]
    s01 = 0.5 * (P[1] + P[3])
    s02 = 0.5 * (P[2] + P[6])
    s12 = 0.5 * (P[5] + P[7])
    dA[1], dA[2] = s01 - h2, s02 + h1
    dA[3], dA[5] = s01 + h2, s12 - h0
    dA[6], dA[7] = s02 - h1, s12 + h0
    # diagonal entries P[0], P[4], P[8] stay


@jit
def _jacobian_matrix(w0, w1, w2, b, c, J):
    """The left Jacobian ``J(w) = I + b [w]x + c [w]x^2`` (flat 3x3)."""
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    J[0] = 1.0 + c * (w0 * w0 - t2)
    J[1] = -b * w2 + c * w0 * w1
    J[2] = b * w1 + c * w0 * w2
    J[3] = b * w2 + c * w1 * w0
    J[4] = 1.0 + c * (w1 * w1 - t2)
    J[5] = -b * w0 + c * w1 * w2
    J[6] = -b * w1 + c * w2 * w0
    J[7] = b * w0 + c * w2 * w1
    J[8] = 1.0 + c * (w2 * w2 - t2)


@jit
def hessian(lin, Z, H, J, N, P):
    """``H`` (flat 9x9, symmetric) = the Hessian of ``A -> Z : H(A)`` at the linearization
    ``lin`` (analytic; scratch ``J`` (9), ``N`` (9), ``P`` (27)).

    With ``phi = Z : (R (I + S))``, ``alpha_a = J(w) dw_a``, ``gamma(N) = (N12 - N21, N20 -
    N02, N01 - N10)`` (so that ``Z : ([x]x M) = x . gamma(M Z^T)``):

        d2phi[a, b] = dw_a^T (M + J^T K J) dw_b + alpha_a . L(dS_b) + alpha_b . L(dS_a),

    ``K = F Z^T - tr(F Z^T) I``, ``L(dS) = gamma(R dS Z^T)``, and ``M`` the bilinear form of
    ``(DJ(w)[dw_b] dw_a) . gamma(F Z^T)`` (the second derivative of the rotation map).
    """
    w0, w1, w2, b, c = lin[0], lin[1], lin[2], lin[3], lin[4]
    R = lin[5:14]
    F = lin[14:23]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    bt, ct = rotation_bc_derivatives(t2)
    for i in range(3):  # N = F Z^T
        for j in range(3):
            N[3 * i + j] = (
                F[3 * i] * Z[3 * j] + F[3 * i + 1] * Z[3 * j + 1] + F[3 * i + 2] * Z[3 * j + 2]
            )
    g0, g1, g2 = N[5] - N[7], N[6] - N[2], N[1] - N[3]
    tr = N[0] + N[4] + N[8]
    N[0] -= tr
    N[4] -= tr
    N[8] -= tr  # N is now K
    _jacobian_matrix(w0, w1, w2, b, c, J)
    # Q = J^T K J (into P[0:9]), via P[9:18] = K J
    for i in range(3):
        for j in range(3):
            P[9 + 3 * i + j] = N[3 * i] * J[j] + N[3 * i + 1] * J[3 + j] + N[3 * i + 2] * J[6 + j]
    for i in range(3):
        for j in range(3):
            P[3 * i + j] = J[i] * P[9 + j] + J[3 + i] * P[12 + j] + J[6 + i] * P[15 + j]
    # + M: 2 bt (g x w) w^T + b [g]x + 2 ct ([w]x^2 g) w^T + c ((w.g) I - g w^T) + c [g x w]x
    wg = w0 * g0 + w1 * g1 + w2 * g2
    u0, u1, u2 = g1 * w2 - g2 * w1, g2 * w0 - g0 * w2, g0 * w1 - g1 * w0  # g x w
    v0, v1, v2 = w0 * wg - t2 * g0, w1 * wg - t2 * g1, w2 * wg - t2 * g2  # [w]x^2 g
    p0 = 2.0 * bt * u0 + 2.0 * ct * v0 - c * g0
    p1 = 2.0 * bt * u1 + 2.0 * ct * v1 - c * g1
    p2 = 2.0 * bt * u2 + 2.0 * ct * v2 - c * g2
    P[0] += p0 * w0 + c * wg
    P[1] += p0 * w1 - b * g2 - c * u2
    P[2] += p0 * w2 + b * g1 + c * u1
    P[3] += p1 * w0 + b * g2 + c * u2
    P[4] += p1 * w1 + c * wg
    P[5] += p1 * w2 - b * g0 - c * u0
    P[6] += p2 * w0 - b * g1 - c * u1
    P[7] += p2 * w1 + b * g0 + c * u0
    P[8] += p2 * w2 + c * wg
    # vectors P_l = J^T L(dS_l), L(dS_l) = (R_i x Z_j + R_j x Z_i) / 2 for l = 3 i + j
    for l in range(9):
        i, j = l // 3, l % 3
        x0 = 0.5 * (
            R[3 + i] * Z[6 + j] - R[6 + i] * Z[3 + j] + R[3 + j] * Z[6 + i] - R[6 + j] * Z[3 + i]
        )
        x1 = 0.5 * (R[6 + i] * Z[j] - R[i] * Z[6 + j] + R[6 + j] * Z[i] - R[j] * Z[6 + i])
        x2 = 0.5 * (R[i] * Z[3 + j] - R[3 + i] * Z[j] + R[j] * Z[3 + i] - R[3 + j] * Z[i])
        P[9 + 3 * l] = J[0] * x0 + J[3] * x1 + J[6] * x2
        P[10 + 3 * l] = J[1] * x0 + J[4] * x1 + J[7] * x2
        P[11 + 3 * l] = J[2] * x0 + J[5] * x1 + J[8] * x2
    for k in range(9):
        ck, sk = _COMPONENT[k], _SIGN[k]
        for l in range(k, 9):
            cl, sl = _COMPONENT[l], _SIGN[l]
            h = 0.0
            if ck >= 0:
                h += sk * P[9 + 3 * l + ck]
                if cl >= 0:
                    h += 0.5 * sk * sl * (P[3 * ck + cl] + P[3 * cl + ck])
            if cl >= 0:
                h += sl * P[9 + 3 * k + cl]
            H[9 * k + l] = h
            H[9 * l + k] = h


@jit
def _cross3(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@jit
def second_tangent(lin, gb, T, J, Q):
    """``T`` (flat 9x9): column k is ``D^2H(A)[E_k, B]`` (flat 3x3) for the direction
    ``gb`` = B (analytic; scratch ``J`` (9), ``Q`` (36)).

    ``D^2H[a, b] = [beta]x F + [alpha_a]x [alpha_b]x F + [alpha_a]x R dS_b + [alpha_b]x R dS_a``
    with ``alpha = J(w) dw``, ``beta = DJ(w)[dw_b] dw_a`` the second derivative of the rotation
    map, ``F = R (I + S)``."""
    w0, w1, w2, b, c = lin[0], lin[1], lin[2], lin[3], lin[4]
    R = lin[5:14]
    F = lin[14:23]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    bt, ct = rotation_bc_derivatives(t2)
    _jacobian_matrix(w0, w1, w2, b, c, J)
    d0 = 0.5 * (gb[7] - gb[5])  # dw_b
    d1 = 0.5 * (gb[2] - gb[6])
    d2 = 0.5 * (gb[3] - gb[1])
    wd = w0 * d0 + w1 * d1 + w2 * d2
    a0 = J[0] * d0 + J[1] * d1 + J[2] * d2  # alpha_b
    a1 = J[3] * d0 + J[4] * d1 + J[5] * d2
    a2 = J[6] * d0 + J[7] * d1 + J[8] * d2
    for m in range(3):  # Q[0:9] = [alpha_b]x F ; Q[9:18] = R dS_b ; column m
        x0, x1, x2 = _cross3(a0, a1, a2, F[m], F[3 + m], F[6 + m])
        Q[m], Q[3 + m], Q[6 + m] = x0, x1, x2
        for p in range(3):
            acc = 0.0
            for q in range(3):
                acc += R[3 * p + q] * 0.5 * (gb[3 * q + m] + gb[3 * m + q])
            Q[9 + 3 * p + m] = acc
    for k in range(9):
        ck, sk = _COMPONENT[k], _SIGN[k]
        i, j = k // 3, k % 3
        for x in range(9):
            T[9 * x + k] = 0.0
        if ck >= 0:
            x0 = sk if ck == 0 else 0.0  # dw_k = sk e_ck
            x1 = sk if ck == 1 else 0.0
            x2 = sk if ck == 2 else 0.0
            e0 = sk * J[ck]  # alpha_k = J dw_k
            e1 = sk * J[3 + ck]
            e2 = sk * J[6 + ck]
            wx0, wx1, wx2 = _cross3(w0, w1, w2, x0, x1, x2)
            wwx0, wwx1, wwx2 = _cross3(w0, w1, w2, wx0, wx1, wx2)
            dx0, dx1, dx2 = _cross3(d0, d1, d2, x0, x1, x2)
            dwx0, dwx1, dwx2 = _cross3(d0, d1, d2, wx0, wx1, wx2)
            wdx0, wdx1, wdx2 = _cross3(w0, w1, w2, dx0, dx1, dx2)
            g0 = 2.0 * bt * wd * wx0 + b * dx0 + 2.0 * ct * wd * wwx0 + c * (dwx0 + wdx0)
            g1 = 2.0 * bt * wd * wx1 + b * dx1 + 2.0 * ct * wd * wwx1 + c * (dwx1 + wdx1)
            g2 = 2.0 * bt * wd * wx2 + b * dx2 + 2.0 * ct * wd * wwx2 + c * (dwx2 + wdx2)
            for m in range(3):
                # [beta]x F + [alpha_k]x ([alpha_b]x F + R dS_b), column m
                y0, y1, y2 = _cross3(g0, g1, g2, F[m], F[3 + m], F[6 + m])
                z0, z1, z2 = _cross3(
                    e0, e1, e2, Q[m] + Q[9 + m], Q[3 + m] + Q[12 + m], Q[6 + m] + Q[15 + m]
                )
                T[9 * m + k] += y0 + z0
                T[9 * (3 + m) + k] += y1 + z1
                T[9 * (6 + m) + k] += y2 + z2
        # [alpha_b]x R dS_k, dS_k = (E_ij + E_ji) / 2: columns j and i
        for m in range(3):
            r0 = 0.5 * ((R[i] if m == j else 0.0) + (R[j] if m == i else 0.0))
            r1 = 0.5 * ((R[3 + i] if m == j else 0.0) + (R[3 + j] if m == i else 0.0))
            r2 = 0.5 * ((R[6 + i] if m == j else 0.0) + (R[6 + j] if m == i else 0.0))
            y0, y1, y2 = _cross3(a0, a1, a2, r0, r1, r2)
            T[9 * m + k] += y0
            T[9 * (3 + m) + k] += y1
            T[9 * (6 + m) + k] += y2


@jit
def _frames(c, chunks, f):
    """Frames ``[s0, s1)`` of chunk ``c`` of ``chunks``."""
    return c * f // chunks, (c + 1) * f // chunks


# Tets per block: a block's tets, gradients and volumes (~35 kB) stay in cache while every
# frame of a chunk passes over them (streaming the whole mesh once per frame is memory bound).
_TET_BLOCK = 256


@pjit
def target_rhs(U, tets, grads, vol, out, chunks):
    """``out[s] += G^T Vol H(G U[s])``: right-hand sides of the warp's Poisson fit.

    The f frames are split into ``chunks`` (one per thread), each processed tet block by
    tet block; the same blocking in :func:`jvp_rhs` and :func:`vjp_rhs`.
    """
    f, m = U.shape[0], tets.shape[0]
    for c in prange(chunks):
        s0, s1 = _frames(c, chunks, f)
        A = np.empty(9)
        S = np.empty(9)
        Rm = np.empty(9)
        H = np.empty(9)
        for b0 in range(0, m, _TET_BLOCK):
            b1 = min(m, b0 + _TET_BLOCK)
            for s in range(s0, s1):
                u, o = U[s], out[s]
                for t in range(b0, b1):
                    gradient(u, tets, grads, t, A)
                    target(A, S, Rm, H)
                    scatter(H, vol[t], tets, grads, t, o)


@pjit
def jvp_rhs(U, dU, tets, grads, vol, out, chunks):
    """``out[s] += G^T Vol dH(G U[s]; G dU[s])``: the tangent map, per field pair."""
    f, m = U.shape[0], tets.shape[0]
    for c in prange(chunks):
        s0, s1 = _frames(c, chunks, f)
        A = np.empty(9)
        dA = np.empty(9)
        S = np.empty(9)
        dH = np.empty(9)
        lin = np.empty(_LIN)
        for b0 in range(0, m, _TET_BLOCK):
            b1 = min(m, b0 + _TET_BLOCK)
            for s in range(s0, s1):
                u, du, o = U[s], dU[s], out[s]
                for t in range(b0, b1):
                    gradient(u, tets, grads, t, A)
                    linearize(A, S, lin)
                    gradient(du, tets, grads, t, dA)
                    tangent(lin, dA, S, dH)
                    scatter(dH, vol[t], tets, grads, t, o)


@pjit
def vjp_rhs(U, Z, index, tets, grads, vol, out, chunks):
    """``out[s] += G^T dA`` with ``dA`` the cotangent of ``Y = Vol G Z[:, index[s]]``
    (``Z`` (n, k, 3): the Poisson solve's columns, read in place)."""
    f, m = U.shape[0], tets.shape[0]
    for c in prange(chunks):
        s0, s1 = _frames(c, chunks, f)
        A = np.empty(9)
        Y = np.empty(9)
        S = np.empty(9)
        dA = np.empty(9)
        lin = np.empty(_LIN)
        for b0 in range(0, m, _TET_BLOCK):
            b1 = min(m, b0 + _TET_BLOCK)
            for s in range(s0, s1):
                u, z, o = U[s], Z[:, index[s], :], out[s]
                for t in range(b0, b1):
                    gradient(u, tets, grads, t, A)
                    linearize(A, S, lin)
                    gradient(z, tets, grads, t, Y)
                    for x in range(9):
                        Y[x] *= vol[t]
                    cotangent(lin, Y, dA)
                    scatter(dA, 1.0, tets, grads, t, o)




@pjit
def field_gradients(B, tets, grads):
    """Per-tet gradients ``A`` (flat 3x3) of the fields ``B`` (r, n, 3): shape (r, m, 9)."""
    r, m = B.shape[0], tets.shape[0]
    out = np.empty((r, m, 9))
    for d in prange(r):
        for t in range(m):
            gradient(B[d], tets, grads, t, out[d, t])
    return out


@pjit
def jacobians_rhs(U, GB, tets, grads, vol, out):
    """``out[s, d] += G^T Vol dH(G U[s]; GB[d])``: Jacobians against r fields at f points.

    ``U`` (f, n, 3) linearization points, ``GB`` (r, m, 9) gradients of the fields (see
    :func:`field_gradients`), ``out`` (f, r, n, 3).
    """
    f, r, m = U.shape[0], GB.shape[0], tets.shape[0]
    lins = np.empty((f, m, _LIN))
    for s in prange(f):
        A = np.empty(9)
        S = np.empty(9)
        for t in range(m):
            gradient(U[s], tets, grads, t, A)
            linearize(A, S, lins[s, t])
    for item in prange(f * r):
        s = item // r
        d = item - s * r
        dS = np.empty(9)
        dH = np.empty(9)
        o = out[s, d]
        for t in range(m):
            tangent(lins[s, t], GB[d, t], dS, dH)
            scatter(dH, vol[t], tets, grads, t, o)


@pjit
def second_derivatives_rhs(U, V, GB, tets, grads, vol, out):
    """``out[s, d] += G^T Vol D^2H(G U[s])[GB[d], G V[s]]``: derivative of the tangent map
    in the linearization point, for velocity keyframes ``B DW(u) u'`` (SYSTEM.md §6).

    Per tet the 9x9 matrix ``dA -> D^2H(A)[dA, G V[s]]`` (analytic, :func:`second_tangent`)
    is applied to the r field gradients.  Shapes as in :func:`jacobians_rhs`; ``V`` (f, n, 3).
    """
    f, r, m = U.shape[0], GB.shape[0], tets.shape[0]
    T2 = np.empty((f, m, 81))
    for item in prange(f * m):
        s = item // m
        t = item - s * m
        A = np.empty(9)
        gv = np.empty(9)
        S = np.empty(9)
        lin = np.empty(_LIN)
        J = np.empty(9)
        Q = np.empty(36)
        gradient(U[s], tets, grads, t, A)
        gradient(V[s], tets, grads, t, gv)
        linearize(A, S, lin)
        second_tangent(lin, gv, T2[s, t], J, Q)
    for item in prange(f * r):
        s = item // r
        d = item - s * r
        dH = np.empty(9)
        o = out[s, d]
        for t in range(m):
            g = GB[d, t]
            T = T2[s, t]
            for x in range(9):
                acc = 0.0
                for e in range(9):
                    acc += T[9 * x + e] * g[e]
                dH[x] = acc
            scatter(dH, vol[t], tets, grads, t, o)


@jit
def _apply_to_fields(H, GB, t, C):
    """``C[d, t] = H GB[d, t]`` for every field d (H flat 9x9)."""
    r = GB.shape[0]
    for d in range(r):
        g = GB[d, t]
        c = C[d, t]
        for x in range(9):
            acc = 0.0
            for e in range(9):
                acc += H[9 * x + e] * g[e]
            c[x] = acc


@pjit
def curvature_products(u, z, zv, v, GB, step3, tets, grads, vol, Cqq, Cqv, velocity):
    """Per tet the Hessians of ``y . W`` in the gradient, applied to r field gradients.

    ``u`` (n, 3) the point, ``z`` and ``zv`` (n, 3) the Poisson adjoints of the cotangents
    ``y`` and ``y_v`` (so that ``y . W(u) = sum_t vol_t (G z)_t : H(A_t) + linear``), ``v``
    (n, 3) a velocity, ``GB`` (r, m, 9) the fields' gradients.  Writes (r, m, 9) arrays

        Cqq[d, t] = vol_t (Hess(Z_t) + D Hess(Zv_t)[(G v)_t]) GB[d, t]
        Cqv[d, t] = vol_t Hess(Zv_t) GB[d, t]          (only with ``velocity``)

    with ``Z_t = (G z)_t`` and ``Hess(Y)`` the analytic 9x9 Hessian of ``A -> Y : H(A)`` at
    ``A_t = (G u)_t`` (:func:`hessian`); its derivative along ``(G v)_t`` is a central
    difference with step ``step3`` (error ~ step3^2).  ``GB^T C`` then gives the modal
    curvature matrices (:meth:`wiggly.warp.kernels.NumbaKernels.curvature`).
    """
    m = tets.shape[0]
    n_chunks = max(1, min(m, 64))
    for ch in prange(n_chunks):
        t0, t1 = ch * m // n_chunks, (ch + 1) * m // n_chunks
        A = np.empty(9)
        Ah = np.empty(9)
        Y1 = np.empty(9)
        Y2 = np.empty(9)
        a = np.empty(9)
        S = np.empty(9)
        lin = np.empty(_LIN)
        J = np.empty(9)
        N = np.empty(9)
        P = np.empty(36)
        H1 = np.empty(81)
        H2 = np.empty(81)
        Tp = np.empty(81)
        Tm = np.empty(81)
        for t in range(t0, t1):
            gradient(u, tets, grads, t, A)
            linearize(A, S, lin)
            gradient(z, tets, grads, t, Y1)
            for x in range(9):
                Y1[x] *= vol[t]
            hessian(lin, Y1, H1, J, N, P)
            if velocity:
                gradient(zv, tets, grads, t, Y2)
                gradient(v, tets, grads, t, a)
                for x in range(9):
                    Y2[x] *= vol[t]
                hessian(lin, Y2, H2, J, N, P)
                scale = 0.0
                for x in range(9):
                    scale = max(scale, abs(a[x]))
                if scale > 0.0:
                    h = step3 / scale
                    for x in range(9):
                        Ah[x] = A[x] + h * a[x]
                    linearize(Ah, S, lin)
                    hessian(lin, Y2, Tp, J, N, P)
                    for x in range(9):
                        Ah[x] = A[x] - h * a[x]
                    linearize(Ah, S, lin)
                    hessian(lin, Y2, Tm, J, N, P)
                    for x in range(81):
                        H1[x] += (Tp[x] - Tm[x]) / (2.0 * h)
                _apply_to_fields(H2, GB, t, Cqv)
            _apply_to_fields(H1, GB, t, Cqq)


def chunks(f: int) -> int:
    """Frame chunks for ``f`` frames: one per thread (numba's current thread count)."""
    from numba import get_num_threads

    return max(1, min(f, get_num_threads()))


def compile_all() -> None:
    """Compile every kernel (or load it from numba's on-disk cache: ~0.5 s when cached, ~30 s
    the first time after installation) by running it on one tetrahedron."""
    if not AVAILABLE:
        return
    tets = np.array([[0, 1, 2, 3]], dtype=np.int64)
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    grads = np.zeros((1, 4, 3))
    grads[0, 1:] = np.linalg.inv((V[1:] - V[0]).T)
    grads[0, 0] = -grads[0, 1:].sum(axis=0)
    vol = np.array([1.0 / 6.0])
    U = np.full((2, 4, 3), 0.1)
    out = np.zeros_like(U)
    target_rhs(U, tets, grads, vol, out, 1)
    jvp_rhs(U, U, tets, grads, vol, out, 1)
    vjp_rhs(U, U.transpose(1, 0, 2).copy(), np.arange(2), tets, grads, vol, out, 1)
    GB = field_gradients(U, tets, grads)
    jacobians_rhs(U, GB, tets, grads, vol, np.zeros((2, 2, 4, 3)))
    second_derivatives_rhs(U, U, GB, tets, grads, vol, np.zeros((2, 2, 4, 3)))
    C = np.zeros((2, 1, 9))
    curvature_products(U[0], U[0], U[1], U[1], GB, 1e-5, tets, grads, vol, C, C.copy(), True)
