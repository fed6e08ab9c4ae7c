"""Compiled per-tet kernels of the rotation-strain warp.

Schulz et al. 2014, Theorem 2; Huang et al. 2011.

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
    "carried_jvp_rhs",
    "carried_target_rhs",
    "chunks",
    "field_gradients",
    "inverted",
    "jacobians_rhs",
    "jvp_rhs",
    "target_rhs",
    "vjp_rhs",
]

# Up to th = pi the Rodrigues coefficients are their Taylor series in t2 = th^2 (no sqrt, sin,
# cos or division): a = sum (-t2)^k/(2k+1)!, b = sum (-t2)^k/(2k+2)!, c = sum (-t2)^k/(2k+3)!.
# The first omitted terms are below pi^28/29! ~ 1e-17 (a), pi^28/30! ~ 3e-19 (b) and
# pi^26/29! ~ 1e-18 (c), and the largest term is 1.7 (a at th = pi): errors ~1e-16 absolute.
POLY_ANGLE2 = math.pi**2
SERIES_A = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(14))
SERIES_B = tuple((-1.0) ** k / math.factorial(2 * k + 2) for k in range(14))
SERIES_C = tuple((-1.0) ** k / math.factorial(2 * k + 3) for k in range(13))
# Per-tet linearization record: w (3), b, c, R (9), F (9).
LIN = 23
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
def series(coefficients, t2):
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
    if t2 <= POLY_ANGLE2:
        return series(SERIES_A, t2), series(SERIES_B, t2)
    th = math.sqrt(t2)
    s = math.sin(0.5 * th) / th
    return 2.0 * s * math.cos(0.5 * th), 2.0 * s * s


@jit
def rotation_c(t2, a):
    """``c = (th - sin th)/th^3``: Taylor series up to th = pi, beyond it ``(1 - a)/t2``."""
    if t2 <= POLY_ANGLE2:
        return series(SERIES_C, t2)
    return (1.0 - a) / t2


# t-derivatives of b and c (t = th^2), for second derivatives of the rotation map
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
        lin = np.empty(LIN)
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
        lin = np.empty(LIN)
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



@jit
def compose(Hr, Hf, H):
    """``H = (I + Hr)(I + Hf) - I = Hr + Hf + Hr Hf``."""
    for i in range(3):
        for j in range(3):
            H[3 * i + j] = (Hr[3 * i + j] + Hf[3 * i + j] + Hr[3 * i] * Hf[j]
                            + Hr[3 * i + 1] * Hf[3 + j] + Hr[3 * i + 2] * Hf[6 + j])


@pjit
def carried_target_rhs(Ur, Uf, tets, grads, vol, out, chunks, relative):
    """``out[s] += G^T Vol ((I + H(G Ur[s]))(I + H(G Uf[s])) - I)``: the warped gradients of
    the fields ``Uf`` carried by the warped gradients of the fields ``Ur``; ``relative``: less
    ``Ur``'s own, ``G^T Vol (I + H(G Ur[s])) H(G Uf[s])``."""
    f, m = Uf.shape[0], tets.shape[0]
    for c in prange(chunks):
        s0, s1 = _frames(c, chunks, f)
        A = np.empty(9)
        S = np.empty(9)
        Rm = np.empty(9)
        Hr = np.empty(9)
        Hf = np.empty(9)
        H = np.empty(9)
        for b0 in range(0, m, _TET_BLOCK):
            b1 = min(m, b0 + _TET_BLOCK)
            for s in range(s0, s1):
                ur, uf, o = Ur[s], Uf[s], out[s]
                for t in range(b0, b1):
                    gradient(ur, tets, grads, t, A)
                    target(A, S, Rm, Hr)
                    gradient(uf, tets, grads, t, A)
                    target(A, S, Rm, Hf)
                    compose(Hr, Hf, H)
                    if relative:
                        for x in range(9):
                            H[x] -= Hr[x]
                    scatter(H, vol[t], tets, grads, t, o)


@pjit
def carried_jvp_rhs(Ur, dUr, Uf, dUf, tets, grads, vol, out, chunks, relative):
    """``out[s] += G^T Vol (dHr (I + Hf) + (I + Hr) dHf)`` (``relative``: less ``dHr``): the
    tangent of :func:`carried_target_rhs` along ``dUr[s]`` and ``dUf[s]``."""
    f, m = Uf.shape[0], tets.shape[0]
    for c in prange(chunks):
        s0, s1 = _frames(c, chunks, f)
        A = np.empty(9)
        dA = np.empty(9)
        S = np.empty(9)
        dHr = np.empty(9)
        dHf = np.empty(9)
        dH = np.empty(9)
        lr = np.empty(LIN)
        lf = np.empty(LIN)
        for b0 in range(0, m, _TET_BLOCK):
            b1 = min(m, b0 + _TET_BLOCK)
            for s in range(s0, s1):
                o = out[s]
                for t in range(b0, b1):
                    gradient(Ur[s], tets, grads, t, A)
                    linearize(A, S, lr)
                    gradient(dUr[s], tets, grads, t, dA)
                    tangent(lr, dA, S, dHr)
                    gradient(Uf[s], tets, grads, t, A)
                    linearize(A, S, lf)
                    gradient(dUf[s], tets, grads, t, dA)
                    tangent(lf, dA, S, dHf)
                    for i in range(3):  # F = I + H is lin[14:23]
                        for j in range(3):
                            dH[3 * i + j] = (
                                dHr[3 * i] * lf[14 + j] + dHr[3 * i + 1] * lf[17 + j]
                                + dHr[3 * i + 2] * lf[20 + j] + lr[14 + 3 * i] * dHf[j]
                                + lr[15 + 3 * i] * dHf[3 + j] + lr[16 + 3 * i] * dHf[6 + j])
                    if relative:
                        for x in range(9):
                            dH[x] -= dHr[x]
                    scatter(dH, vol[t], tets, grads, t, o)


@pjit
def inverted(U, tets, grads, out):
    """``out[s, t] = det(I + A) <= 0``, ``A`` the gradient of the displacements ``U[s]`` on
    tet ``t``: the tets that the fields U (f, n, 3) turn inside out; ``out`` (f, m) bool."""
    f, m = U.shape[0], tets.shape[0]
    for b in prange((m + _TET_BLOCK - 1) // _TET_BLOCK):
        A = np.empty(9)
        for t in range(b * _TET_BLOCK, min(m, (b + 1) * _TET_BLOCK)):
            for s in range(f):
                gradient(U[s], tets, grads, t, A)
                a, e, i = 1.0 + A[0], 1.0 + A[4], 1.0 + A[8]
                det = (a * (e * i - A[5] * A[7]) - A[1] * (A[3] * i - A[5] * A[6])
                       + A[2] * (A[3] * A[7] - e * A[6]))
                out[s, t] = det <= 0.0


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
    lins = np.empty((f, m, LIN))
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


def chunks(f: int) -> int:
    """Frame chunks for ``f`` frames: one per thread (numba's current thread count)."""
    from numba import get_num_threads

    return max(1, min(f, get_num_threads()))
