"""Wiggly splines: the per-mode minimisers of the spacetime energy (Schulz et al. 2014, Theorem 1).

For one mode with eigenvalue ``lam`` (lambda >= 0), damping ``delta`` >= 0 and modal gravity ``g``,
the energy of a trajectory q on one interval [0, h] is (Schulz et al. 2014, eq. (4))

    E = 1/2 int_0^h (q'' + 2 delta q' + lam q + g)^2 dt,

and on every interval between nodes its minimiser solves the wiggly-spline ODE

    q'''' + 2 (lam - 2 delta^2) q'' + lam (lam q + g) = 0,                     (Theorem 1)

whose characteristic roots are s = +-delta +- sqrt(delta^2 - lam).  The spline on an interval
is fixed by its Hermite data x = (q(0), q'(0), q(h), q'(h)).  This module provides

* :func:`wiggly_basis`: a numerically stable basis of the ODE's kernel, in every regime,
* :meth:`WigglyBasis.hermite`: the Hermite basis H_j (and derivatives) at any time,
* :func:`energy_form`: the exact energy of the minimiser as a quadratic form in x,
* :func:`particular_cubic`, :func:`cubic_hermite`, :func:`cubic_at`: a particular solution
  of eq. (4)'s ODE under a cubic forcing (secondary motion's), its Hermite data and values.

Numerics.  Everything is computed in dimensionless time tau = t / h, with Lam = lam h^2 and
D = delta h; the roots are +-a, +-b with a = D + sigma, b = D - sigma = Lam / a,
sigma = sqrt(D^2 - Lam) (complex when under-damped).  The kernel is spanned by four *slots*,
each either an exponential e^{r1 s} or a divided difference (e^{r2 s} - e^{r1 s}) / (r2 - r1),
with s = tau - anchor and the anchor (0 or 1) chosen so that every exponential decays over the
interval; divided differences stay exact where roots coalesce (critical damping, delta = 0,
lam = 0).  When all roots are small (``|a| <= 1``) a Taylor series of the fundamental solutions is
used instead.  The regimes are::

    SERIES       |a| <= 1                       cubics-like, entire power series
    OSCILLATORY  |a| > 1, D < 1/2               roots -+D +- i Omega paired across D
    SPLIT_SMALL  |a| > 1, D >= 1/2, b < 1/2     e^{-a tau}, e^{a (tau-1)}, cosh/sinh(b tau)
    SPLIT        otherwise                      kernel(L) anchored at 0, kernel(L*) at 1

so no exponential is ever evaluated with a positive real argument larger than 1/2.  The energy
of the minimiser is obtained without quadrature from boundary terms (Lagrange's identity for
L = d^2 + 2 delta d + lam and its adjoint, since L q lies in the kernel of L*).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import factorial

import numpy as np
from numpy.typing import ArrayLike, NDArray

SERIES, OSCILLATORY, SPLIT_SMALL, SPLIT = 0, 1, 2, 3
REGIME_NAMES = {
    SERIES: "series",
    OSCILLATORY: "oscillatory",
    SPLIT_SMALL: "split-small",
    SPLIT: "split",
}
_N_SERIES = 30  # Taylor terms; |root| <= 1 on the unit interval gives 1/30! ~ 4e-33
_INV_FACT = np.array([1.0 / factorial(n) for n in range(_N_SERIES)])


def _phi1(z: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """(e^z - 1) / z, accurate for all z with Re z <= small, including z -> 0."""
    x, y = z.real, z.imag
    ex = np.exp(x)
    num = (np.expm1(x) * np.cos(y) - 2.0 * np.sin(0.5 * y) ** 2) + 1j * (ex * np.sin(y))
    small = np.abs(z) < 1e-8
    safe = np.where(small, 1.0, z)
    return np.where(small, 1.0 + 0.5 * z, num / safe)


@dataclass(frozen=True)
class WigglyBasis:
    """A stable kernel basis of the wiggly-spline ODE for a batch of (mode, interval) pairs.

    All arrays share the leading batch shape ``(P,)``.  Slots k = 0..3 are, in dimensionless
    time s = tau - anchor[k]: ``e^{r1 s}`` if not ``divided[k]`` else
    ``(e^{r2 s} - e^{r1 s}) / (r2 - r1)``; in the SERIES regime slot k is the fundamental
    solution with f_k^{(j)}(0) = delta_jk, with Taylor coefficients ``series``.
    ``hermite_inverse`` maps Hermite data (q0, q0', q1, q1') in dimensionless time to slot
    coefficients.
    """

    lam: NDArray[np.float64]
    delta: NDArray[np.float64]
    h: NDArray[np.float64]
    regime: NDArray[np.int64]
    r1: NDArray[np.complex128]  # (P, 4)
    r2: NDArray[np.complex128]  # (P, 4)
    anchor: NDArray[np.float64]  # (P, 4)
    divided: NDArray[np.bool_]  # (P, 4)
    series: NDArray[np.float64]  # (P, 4, N + 4) Taylor coefficients c_n = f^{(n)}(0)
    hermite_inverse: NDArray[np.complex128]  # (P, 4, 4)

    @property
    def size(self) -> int:
        return self.lam.shape[0]

    def take(self, index: ArrayLike) -> WigglyBasis:
        """The basis of a sub-batch (fancy indexing along the batch axis)."""
        idx = np.asarray(index)
        return WigglyBasis(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    def kernel(
        self, tau: ArrayLike, n_derivatives: int = 0, *, operator: bool = False
    ) -> NDArray[np.complex128]:
        """Slot functions and their tau-derivatives at ``tau`` (broadcast against the batch).

        Returns shape ``(n_derivatives + 1, P, 4)``.  With ``operator=True`` returns
        L0 f^{(d)} instead, L0 = d^2 + 2D d + Lam, applied exactly: on an exponential slot
        L0 acts as p(r) = (r + a)(r + b), which vanishes on the kernel roots -a, -b, so no
        cancellation occurs for fast oscillations or stiff modes.
        """
        tau = np.broadcast_to(np.asarray(tau, dtype=float), self.lam.shape)
        out = np.empty((n_derivatives + 1, self.size, 4), dtype=complex)
        s = tau[:, None] - self.anchor
        r1, r2 = self.r1, self.r2
        e1 = np.exp(r1 * s)
        dd = np.exp(r2 * s) * s * _phi1((r1 - r2) * s)
        a, b = self.roots
        a, b = a[:, None], b[:, None]
        D = (self.delta * self.h)[:, None]
        for d in range(n_derivatives + 1):
            # P(r) = r^d [p(r)];  divided differences by the Leibniz rule
            pow1, pow2 = r1**d, r2**d
            geo = sum((r1**k * r2 ** (d - 1 - k) for k in range(d)), np.zeros_like(r1))
            if operator:
                p1, p2 = (r1 + a) * (r1 + b), (r2 + a) * (r2 + b)
                pdd = r1 + r2 + 2 * D
                P1, P2, Pdd = pow1 * p1, pow2 * p2, pow2 * pdd + geo * p1
            else:
                P1, P2, Pdd = pow1, pow2, geo
            out[d] = np.where(self.divided, P2 * dd + e1 * Pdd, P1 * e1)
        ser = self.regime == SERIES
        if np.any(ser):
            t = tau[ser]
            powers = t[:, None] ** np.arange(_N_SERIES) * _INV_FACT  # (S, N)
            c = self.series[ser]
            if operator:
                L = (self.lam * self.h**2)[ser][:, None, None]
                c = c[:, :, 2:] + 2 * D[ser][:, :, None] * c[:, :, 1:-1] + L * c[:, :, :-2]
            for d in range(n_derivatives + 1):
                out[d, ser] = np.einsum("skn,sn->sk", c[:, :, d : d + _N_SERIES], powers)
        return out

    @property
    def roots(self) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """Dimensionless characteristic roots (a, b); the kernel's roots are +-a, +-b."""
        return _roots(self.lam * self.h**2, self.delta * self.h)

    def hermite(
        self, tau: ArrayLike, n_derivatives: int = 0, *, operator: bool = False
    ) -> NDArray[np.float64]:
        """Hermite basis H_j^{(d)}(tau), j = 0..3 for data (q0, q0', q1, q1') in tau units.

        Shape ``(n_derivatives + 1, P, 4)``; derivatives are with respect to tau.  With
        ``operator=True``, (L0 H_j)^{(d)} instead (see :meth:`kernel`).
        """
        f = self.kernel(tau, n_derivatives, operator=operator)
        return np.einsum("dpk,pkj->dpj", f, self.hermite_inverse).real


def _roots(lam_h2: NDArray, d_h: NDArray) -> tuple[NDArray, NDArray]:
    """Dimensionless roots a = D + sigma and b = Lam / a (b = D - sigma without cancellation)."""
    sigma = np.sqrt((d_h**2 - lam_h2).astype(complex))
    a = d_h + sigma
    safe = np.where(a == 0, 1.0, a)
    b = np.where(a == 0, 0.0, lam_h2 / safe)
    b = np.where(d_h**2 < lam_h2, np.conj(a), b)  # under-damped: b = conj(a) exactly
    return a, b


def wiggly_basis(lam: ArrayLike, delta: ArrayLike, h: ArrayLike) -> WigglyBasis:
    """Build the stable kernel basis for eigenvalues ``lam``, damping ``delta`` and lengths ``h``.

    Parameters broadcast to a common 1-D batch.  ``lam >= 0``, ``delta >= 0``, ``h > 0``.
    """
    lam, delta, h = np.broadcast_arrays(
        *(np.atleast_1d(np.asarray(v, float)) for v in (lam, delta, h))
    )
    lam, delta, h = lam.ravel().copy(), delta.ravel().copy(), h.ravel().copy()
    if np.any(~np.isfinite(lam) | (lam < 0)) or np.any(~np.isfinite(delta) | (delta < 0)):
        raise ValueError("wiggly_basis needs finite lam >= 0 and delta >= 0")
    if np.any(~np.isfinite(h) | (h <= 0)):
        raise ValueError("wiggly_basis needs interval lengths h > 0")
    P = lam.size
    L = lam * h**2
    D = delta * h
    a, b = _roots(L, D)
    rho = np.abs(a)

    regime = np.full(P, SPLIT, dtype=np.int64)
    regime[(rho > 1) & (D >= 0.5) & (np.abs(b.imag) == 0) & (b.real < 0.5)] = SPLIT_SMALL
    regime[(rho > 1) & (D < 0.5)] = OSCILLATORY
    regime[rho <= 1] = SERIES

    r1 = np.zeros((P, 4), complex)
    r2 = np.zeros((P, 4), complex)
    anchor = np.zeros((P, 4))
    divided = np.zeros((P, 4), bool)

    def put(mask: NDArray, slot: int, s1, s2, anc: float, div: bool) -> None:
        r1[mask, slot] = s1[mask] if np.ndim(s1) else s1
        r2[mask, slot] = s2[mask] if np.ndim(s2) else s2
        anchor[mask, slot] = anc
        divided[mask, slot] = div

    m = regime == SPLIT  # kernel(L) = {-a, -b} anchored at 0, kernel(L*) = {a, b} at 1
    put(m, 0, -a, -a, 0.0, False)
    put(m, 1, -a, -b, 0.0, True)
    put(m, 2, a, a, 1.0, False)
    put(m, 3, a, b, 1.0, True)
    m = regime == SPLIT_SMALL  # a large and real, b small: e^{-a t}, e^{a (t-1)}, e^{+-b t}
    put(m, 0, -a, -a, 0.0, False)
    put(m, 1, a, a, 1.0, False)
    put(m, 2, -b, -b, 0.0, False)
    put(m, 3, -b, b, 0.0, True)
    m = regime == OSCILLATORY  # a = D + i Omega, b = conj(a): pair -b with a, -a with b
    put(m, 0, -b, -b, 0.0, False)
    put(m, 1, -b, a, 0.0, True)
    put(m, 2, -a, -a, 0.0, False)
    put(m, 3, -a, b, 0.0, True)

    # Taylor coefficients of the fundamental solutions: c_{n+4} = A2 c_{n+2} - A0 c_n
    series = np.zeros((P, 4, _N_SERIES + 4))
    ser = regime == SERIES
    if np.any(ser):
        A2 = (4 * D[ser] ** 2 - 2 * L[ser])[:, None]
        A0 = (L[ser] ** 2)[:, None]
        c = np.zeros((int(ser.sum()), 4, _N_SERIES + 4))
        c[:, range(4), range(4)] = 1.0
        for n in range(_N_SERIES):
            c[:, :, n + 4] = A2 * c[:, :, n + 2] - A0 * c[:, :, n]
        series[ser] = c

    basis = WigglyBasis(
        lam, delta, h, regime, r1, r2, anchor, divided, series, np.zeros((P, 4, 4), complex)
    )
    # Hermite matrix rows: f(0), f'(0), f(1), f'(1); equilibrated before inversion.
    f0 = basis.kernel(0.0, 1)
    f1 = basis.kernel(1.0, 1)
    B = np.stack([f0[0], f0[1], f1[0], f1[1]], axis=1)  # (P, 4 rows, 4 slots)
    col = np.max(np.abs(B), axis=1, keepdims=True)
    col = np.where(col == 0, 1.0, col)
    Bs = B / col
    row = np.max(np.abs(Bs), axis=2, keepdims=True)
    Bs = Bs / row
    inv = np.linalg.inv(
        Bs
    )  # Bs = diag(1/row) B diag(1/col)  =>  B^-1 = diag(1/col) inv diag(1/row)
    hermite_inverse = inv / col.transpose(0, 2, 1) / row.transpose(0, 2, 1)
    return WigglyBasis(lam, delta, h, regime, r1, r2, anchor, divided, series, hermite_inverse)


@dataclass(frozen=True)
class EnergyForm:
    """Per-interval energy of the minimiser, E(x) = 1/2 x^T Q x + l^T x + c0.

    x = (q(t0), q'(t0), q(t1), q'(t1)) in physical units; shapes Q (P,4,4), l (P,4), c0 (P,).
    """

    Q: NDArray[np.float64]
    l: NDArray[np.float64]
    c0: NDArray[np.float64]

    def __call__(self, x: ArrayLike) -> NDArray[np.float64]:
        x = np.asarray(x, float)
        return (
            0.5 * np.einsum("pi,pij,pj->p", x, self.Q, x)
            + np.einsum("pi,pi->p", self.l, x)
            + self.c0
        )


def equilibrium(lam: ArrayLike, g: ArrayLike) -> NDArray[np.float64]:
    """Static solution q_p = -g / lam of the wiggly ODE; 0 for rigid modes (lam = 0)."""
    lam, g = np.broadcast_arrays(np.asarray(lam, float), np.asarray(g, float))
    safe = np.where(lam > 0, lam, 1.0)
    return np.where(lam > 0, -g / safe, 0.0)


#: Below this lam h^2, a mode's energy shifts by the response to its gravity from rest
#: (:func:`_rest_response`), not by the static solution -g / lam, whose size (3e9 at lam =
#: 1e-8, g = 30) cancelled the energy's terms into nonsense (a negative energy).
SLOW_MODE = 0.1


def _rest_response(lam: np.ndarray, delta: np.ndarray, h: np.ndarray, tau: ArrayLike = 1.0,
                   n_derivatives: int = 1) -> np.ndarray:
    """psi and its time derivatives at t = tau h, where psi'' + 2 delta psi' + lam psi = 1
    from rest (psi and its derivative 0 at t = 0): the exponential of the forced system's
    matrix in tau = t / h (scaling and squaring: accurate for small lam h^2 and any damping),
    then the equation for the higher derivatives; shape (n_derivatives + 1, ...)."""
    from scipy.linalg import expm

    tau = np.broadcast_to(np.asarray(tau, float), lam.shape)
    A = np.zeros((*lam.shape, 3, 3))  # state (psi, h dpsi/dt, h^2): its d/dtau
    A[..., 0, 1] = 1.0
    A[..., 1, 0] = -lam * h * h
    A[..., 1, 1] = -2 * delta * h
    A[..., 1, 2] = 1.0
    E = expm((A * tau[..., None, None]).reshape(-1, 3, 3)).reshape(A.shape)
    out = [E[..., 0, 2] * h * h, E[..., 1, 2] * h]
    for d in range(2, n_derivatives + 1):  # psi'' = 1 - 2 delta psi' - lam psi, and on
        out.append((1.0 if d == 2 else 0.0) - 2 * delta * out[d - 1] - lam * out[d - 2])
    return np.stack(out[:n_derivatives + 1])


def _slow(basis: WigglyBasis, g: np.ndarray) -> np.ndarray:
    """The modes whose particular solution is the response to g from rest (lam h^2 below
    :data:`SLOW_MODE`), not the static -g / lam."""
    return (basis.lam > 0) & (basis.lam * basis.h**2 < SLOW_MODE) & (g != 0)


def _particular_data(basis: WigglyBasis, g: np.ndarray, slow: np.ndarray) -> np.ndarray:
    """The physical Hermite data (P, 4) of each mode's particular solution q_p on its
    interval: (qp, 0, qp, 0) of the static -g / lam, or for ``slow`` modes (0, 0, -g psi(h),
    -g dpsi/dt(h)) of the response from rest (:func:`_rest_response`)."""
    qp = np.where(slow, 0.0, equilibrium(basis.lam, g))
    p = np.stack([qp, np.zeros_like(qp), qp, np.zeros_like(qp)], axis=1)
    if slow.any():
        end = -g[slow] * _rest_response(basis.lam[slow], basis.delta[slow], basis.h[slow])
        p[slow, 2:] = end.T
    return p


def energy_form(basis: WigglyBasis, g: ArrayLike) -> EnergyForm:
    """Exact energy 1/2 int (q'' + 2 delta q' + lam q + g)^2 dt of the Hermite interpolant.

    With w = q - q_p and r = L w (+ g if lam = 0) in the kernel of the adjoint
    L* = d^2 - 2 delta d + lam, Lagrange's identity gives, in tau units,
    int_0^1 r^2 = [r w' - r' w + 2D r w]_0^1 + c int_0^1 r, c = lam q_p + g,
    so the 4 x 4 Gram matrix G needs only H'', H''' at the ends (no quadrature).  q_p is the
    static solution -g / lam, or for slow modes (lam h^2 below :data:`SLOW_MODE`) the
    response to g from rest, -g psi(t), which stays bounded as lam -> 0: any exact
    particular solution leaves w in the interval's basis (Theorem 1's equation is
    L*(L q + g) = 0).
    """
    g = np.broadcast_to(np.asarray(g, float), basis.lam.shape)
    h = basis.h
    D = basis.delta * h
    # R = L0 H = H'' + 2D H' + Lam H and its derivative R' at both ends, applied exactly
    R0, R0p = basis.hermite(0.0, 1, operator=True)
    R1, R1p = basis.hermite(1.0, 1, operator=True)
    G = np.stack([R0p - 2 * D[:, None] * R0, -R0, -R1p + 2 * D[:, None] * R1, R1], axis=2)
    G = 0.5 * (G + G.transpose(0, 2, 1))
    # energy (tau units): (x-p)^T G (x-p) + 2 c ell^T (x-p) + c^2, ell = (-2D, -1, 2D, 1)
    g_hat = g * h**2
    c = np.where(basis.lam > 0, 0.0, g_hat)
    ell = np.stack([-2 * D, -np.ones_like(D), 2 * D, np.ones_like(D)], axis=1)
    # physical data x = S^-1 x_hat with S = diag(1, h, 1, h); p: q_p's data
    S = np.stack([np.ones_like(h), h, np.ones_like(h), h], axis=1)
    scale = 1.0 / h**3  # int_0^h (Lq)^2 dt = h^-3 int_0^1 (L_hat q)^2 dtau
    Gp = G * S[:, :, None] * S[:, None, :] * scale[:, None, None]
    ellp = ell * S * scale[:, None]
    p = _particular_data(basis, g, _slow(basis, g))
    # 1/2 [(x-p)^T Gp (x-p) + 2 c ellp^T (x-p) + c^2 / h^3]
    Gp_p = np.einsum("pij,pj->pi", Gp, p)
    Q = Gp
    lin = -Gp_p + c[:, None] * ellp
    c0 = (
        0.5 * np.einsum("pi,pi->p", p, Gp_p)
        - c * np.einsum("pi,pi->p", ellp, p)
        + 0.5 * c**2 * scale
    )
    return EnergyForm(Q, lin, c0)


def evaluate(
    basis: WigglyBasis, data: ArrayLike, g: ArrayLike, tau: ArrayLike, n_derivatives: int = 0
) -> NDArray[np.float64]:
    """Spline values and time derivatives at ``tau`` for physical Hermite ``data`` (P, 4).

    Returns shape ``(n_derivatives + 1, P)``: q, dq/dt, d2q/dt2, ... (physical time units).
    """
    data = np.asarray(data, float)
    h = basis.h
    g = np.broadcast_to(np.asarray(g, float), h.shape)
    slow = _slow(basis, g)
    p = _particular_data(basis, g, slow)  # q = q_p + the Hermite interpolant of data - p
    xhat = (data - p) * np.stack([np.ones_like(h), h, np.ones_like(h), h], axis=1)
    H = basis.hermite(tau, n_derivatives)
    out = np.einsum("dpj,pj->dp", H, xhat)
    out[0] += p[:, 0]  # the static q_p (0 for slow modes, added below)
    out /= h[None, :] ** np.arange(n_derivatives + 1)[:, None]
    if slow.any():
        at = np.broadcast_to(np.asarray(tau, float), h.shape)[slow]
        out[:, slow] -= g[slow] * _rest_response(basis.lam[slow], basis.delta[slow],
                                                 h[slow], at, n_derivatives)
    return out


def particular_cubic(lam: np.ndarray, delta: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Coefficients a (..., 4) of the cubic q_p = a0 + a1 x + a2 x^2 + a3 x^3 with
    q_p'' + 2 delta q_p' + lambda q_p = -(c0 + c1 x + c2 x^2 + c3 x^3) (lambda > 0): a
    particular solution of eq. (4)'s ODE under a cubic forcing (secondary motion's)."""
    a3 = -c[..., 3] / lam
    a2 = (-c[..., 2] - 6 * delta * a3) / lam
    a1 = (-c[..., 1] - 4 * delta * a2 - 6 * a3) / lam
    a0 = (-c[..., 0] - 2 * delta * a1 - 2 * a2) / lam
    return np.stack([a0, a1, a2, a3], axis=-1)


def cubic_at(a: np.ndarray, x: np.ndarray, derivative: int) -> np.ndarray:
    """The ``derivative``-th derivative of cubics a (..., 4) at x."""
    if derivative == 0:
        return a[..., 0] + x * (a[..., 1] + x * (a[..., 2] + x * a[..., 3]))
    if derivative == 1:
        return a[..., 1] + x * (2 * a[..., 2] + 3 * x * a[..., 3])
    if derivative == 2:
        return 2 * a[..., 2] + 6 * x * a[..., 3]
    return 6 * a[..., 3] + 0 * x


def cubic_hermite(a: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Hermite data (q(0), q'(0), q(h), q'(h)) of cubics a (..., 4) on intervals h."""
    return np.stack([a[..., 0], a[..., 1], cubic_at(a, h, 0), cubic_at(a, h, 1)], axis=-1)
