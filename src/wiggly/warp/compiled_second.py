"""Compiled second derivatives of the warp's per-tet map (Schulz et al. 2014, Theorem 2), for the
warped solve's Newton matrices: the analytic Hessian of ``A -> Z : H(A)`` (curvature of the keyframe
residuals) and the analytic second derivative ``D^2H(A)[., B]`` (velocity keyframes), their passes
over the tets, and the third-order velocity term by a central difference of the Hessian.  The
conventions and first-order formulas are those of :mod:`wiggly.warp.compiled`; the numpy kernels
(:mod:`wiggly.warp.kernels_numpy`) take the same quantities by central differences of the analytic
first derivatives, an independent check.
"""

from __future__ import annotations

import math

import numpy as np

from wiggly.warp.compiled import (
    LIN,
    POLY_ANGLE2,
    SERIES_B,
    SERIES_C,
    gradient,
    jit,
    linearize,
    pjit,
    prange,
    scatter,
    series,
)

__all__ = [
    "curvature_products",
    "hessian",
    "second_derivatives_rhs",
    "second_tangent",
    "split_fields",
]

_BT = tuple(k * SERIES_B[k] for k in range(1, 14))
_CT = tuple(k * SERIES_C[k] for k in range(1, 13))
# unit gradient E_k (flat k = 3 i + j): its rotation vector is SIGN[k] e_COMPONENT[k]
_COMPONENT = (-1, 2, 1, 2, -1, 0, 1, 0, -1)
_SIGN = (0.0, -0.5, 0.5, 0.5, 0.0, -0.5, -0.5, 0.5, 0.0)


@jit
def rotation_bc_derivatives(t2):
    """``db/dt`` and ``dc/dt`` with ``t = th^2``: Taylor series up to th = pi, beyond it
    ``(th sin th - 2 + 2 cos th) / (2 th^4)`` and ``(th (1 - cos th) - 3 th + 3 sin th) /
    (2 th^5)``."""
    if t2 <= POLY_ANGLE2:
        return series(_BT, t2), series(_CT, t2)
    th = math.sqrt(t2)
    s, co = math.sin(th), math.cos(th)
    return (th * s - 2.0 + 2.0 * co) / (2.0 * t2 * t2), (
        th * (1.0 - co) - 3.0 * th + 3.0 * s
    ) / (2.0 * t2 * t2 * th)



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


@pjit
def second_derivatives_rhs(U, V, GB, tets, grads, vol, out):
    """``out[s, d] += G^T Vol D^2H(G U[s])[GB[d], G V[s]]``: derivative of the tangent map
    in the linearization point, for velocity keyframes ``B DW(u) u'`` (Schulz et al. 2014, Thm. 2).

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
        lin = np.empty(LIN)
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


# An orthonormal basis of 3x3 matrices (flat): three skew ones (the rotation vector's
# directions, (E_21 - E_12)/sqrt2, ...) then six symmetric ones.  Row a has entries
# _SPLIT_COEF[a] at flat indices _SPLIT_INDEX[a].  Z : H(A) is linear in the symmetric part S
# of A (H = R(w)(I + S) - I), so every Hessian of it (and their derivatives) has a zero
# symmetric-symmetric block in this basis.
_H = 1.0 / math.sqrt(2.0)
_SPLIT_INDEX = ((7, 5), (2, 6), (3, 1), (0, 0), (4, 4), (8, 8), (1, 3), (2, 6), (5, 7))
_SPLIT_COEF = ((_H, -_H), (_H, -_H), (_H, -_H), (1.0, 0.0), (1.0, 0.0), (1.0, 0.0),
               (_H, _H), (_H, _H), (_H, _H))


def _split_matrix() -> np.ndarray:
    """The change to the skew/symmetric basis as a (9, 9) matrix acting on flat rows."""
    T = np.zeros((9, 9))
    for a, (idx, coef) in enumerate(zip(_SPLIT_INDEX, _SPLIT_COEF, strict=True)):
        T[idx[0], a] += coef[0]
        T[idx[1], a] += coef[1]
    return T


_SPLIT_MATRIX = _split_matrix()


def split_fields(GB: np.ndarray) -> np.ndarray:
    """Field gradients (r, m, 9) in the skew/symmetric basis (rotation parts first): one
    product of the (r m, 9) rows with :data:`_SPLIT_MATRIX` (85 ms as nine strided column
    operations, 13 ms so, for 40 fields on 20k tets)."""
    GB = np.ascontiguousarray(GB, dtype=np.float64)
    return (GB.reshape(-1, 9) @ _SPLIT_MATRIX).reshape(GB.shape)


@jit
def _split_rows(H, Hs):
    """``Hs`` (3 x 9) = the rotation rows of ``B H B^T`` (B the basis above, H flat 9x9)."""
    for a in range(3):
        ia, ca = _SPLIT_INDEX[a], _SPLIT_COEF[a]
        for b in range(9):
            ib, cb = _SPLIT_INDEX[b], _SPLIT_COEF[b]
            acc = 0.0
            for x in range(2):
                for y in range(2):
                    acc += ca[x] * cb[y] * H[9 * ia[x] + ib[y]]
            Hs[9 * a + b] = acc


@jit
def _apply_to_fields(H, Hs, F, t, C):
    """``C[d, t] = Y_d`` (3) with ``Y_d = Hww w_d / 2 + Hws s_d`` for every field d, where
    ``F[d, t] = (w_d, s_d)`` is the field's gradient in the split basis and Hww, Hws the
    rotation rows of H there: then ``GB^T H GB = W^T Y + Y^T W`` per tet (the symmetric-
    symmetric block is zero), a third of the work of applying the full 9x9 matrix."""
    _split_rows(H, Hs)
    r = F.shape[0]
    for d in range(r):
        g = F[d, t]
        c = C[d, t]
        for x in range(3):
            acc = 0.5 * (Hs[9 * x] * g[0] + Hs[9 * x + 1] * g[1] + Hs[9 * x + 2] * g[2])
            for e in range(3, 9):
                acc += Hs[9 * x + e] * g[e]
            c[x] = acc


@pjit
def curvature_products(u, z, zv, v, F, step3, tets, grads, vol, Cqq, Cqv, velocity):
    """Per tet the Hessians of ``y . W`` in the gradient, applied to r field gradients.

    ``u`` (n, 3) the point, ``z`` and ``zv`` (n, 3) the Poisson adjoints of the cotangents
    ``y`` and ``y_v`` (so that ``y . W(u) = sum_t vol_t (G z)_t : H(A_t) + linear``), ``v``
    (n, 3) a velocity, ``F`` (r, m, 9) the fields' gradients in the split basis
    (:func:`split_fields`).  Writes (r, m, 3) arrays (:func:`_apply_to_fields`) of

        Hqq_t = vol_t (Hess(Z_t) + D Hess(Zv_t)[(G v)_t])
        Hqv_t = vol_t Hess(Zv_t)          (only with ``velocity``)

    with ``Z_t = (G z)_t`` and ``Hess(Y)`` the analytic 9x9 Hessian of ``A -> Y : H(A)`` at
    ``A_t = (G u)_t`` (:func:`hessian`); its derivative along ``(G v)_t`` is a central
    difference with step ``step3`` (error ~ step3^2).  ``W^T C + C^T W`` (W the rotation
    columns of F) then gives the modal curvature matrices
    (:meth:`wiggly.warp.kernels.NumbaKernels.curvature`).
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
        lin = np.empty(LIN)
        J = np.empty(9)
        N = np.empty(9)
        P = np.empty(36)
        Hs = np.empty(27)
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
                _apply_to_fields(H2, Hs, F, t, Cqv)
            _apply_to_fields(H1, Hs, F, t, Cqq)
