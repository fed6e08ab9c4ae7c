"""The classic frame-based spacetime method, as an independent reference and baseline.

Witkin & Kass (1988) style: the same functional E + E_C (Schulz et al. 2014, eqs. (4) and (6)) in
the same modal coordinates, but with q_i sampled on a uniform time grid t_j = t_0 + j dt and the
energy discretized by central differences,

    E ~ 1/2 sum_i sum_{j interior} dt (D2 q_i + 2 delta_i D1 q_i + lambda_i q_i + g_i)_j^2,

keyframes applied at their grid points (times must lie on the grid) and velocities by
central (one-sided at the ends: second order) differences.  Solved directly as one sparse
least-squares problem.  Used by the tests (convergence toward the wiggly solution as dt -> 0)
and by the benchmarks (what the wiggly solver replaces).  No pre-roll: give keyframes that
determine the start.  With ``loop=True`` the grid is periodic (frame n is frame 0, the
differences wrap around): the reference of looped shots.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from wiggly.body import Body
from wiggly.errors import WigglyInputError
from wiggly.keyframes import Keyframe


def solve_framebased(
    body: Body, keyframes: list[Keyframe], fps: float, start: float, end: float,
    loop: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame-based minimiser of E + E_C; returns (times (N+1,), q (N+1, r)) (for a loop the
    last frame repeats the first)."""
    n = round((end - start) * fps)
    if n < 2 or abs(n / fps - (end - start)) > 1e-9 * max(1.0, end - start):
        raise WigglyInputError(
            f"duration {end - start} s is not a whole number of frames at {fps} fps"
        )
    dt = 1.0 / fps
    times = start + np.arange(n + 1) * dt
    r = body.r
    lam, delta, g = body.eigenvalues, body.delta, body.modal_gravity
    frames = n if loop else n + 1  # unknown q_i(t_j) at index j * r + i
    N = frames * r

    def at(f: int) -> int:  # the unknown frame of grid frame f
        return f % n if loop else f

    # energy rows: sqrt(dt) * (residual at interior frame j, mode i); every frame of a loop
    inner = np.arange(n) if loop else np.arange(1, n)
    j = np.repeat(inner, r)
    i = np.tile(np.arange(r), len(inner))
    c_m = 1 / dt**2 - delta[i] / dt
    c_0 = -2 / dt**2 + lam[i]
    c_p = 1 / dt**2 + delta[i] / dt
    rows = np.repeat(np.arange(len(j)), 3)
    jm, jp = (j - 1) % frames, (j + 1) % frames
    cols = np.stack([jm * r + i, j * r + i, jp * r + i], axis=1).ravel()
    vals = np.sqrt(dt) * np.stack([c_m, c_0, c_p], axis=1).ravel()
    blocks = [sp.csr_matrix((vals, (rows, cols)), shape=(len(j), N))]
    rhs = [-np.sqrt(dt) * g[i]]

    J_E = sp.vstack(blocks).tocsr()
    H = (J_E.T @ J_E).tolil()
    b = J_E.T @ np.concatenate(rhs)
    T = end - start
    for kf in keyframes:  # normal equations per keyframe, through the r x r Gram A^T A
        kf = kf.checked(body, start, end)
        k = round((kf.time - start) * fps)
        if abs(times[k] - kf.time) > 1e-9 * max(1.0, abs(kf.time)):
            raise WigglyInputError(f"keyframe time {kf.time} is not on the {fps} fps grid")
        c_A, c_B = kf.weights(body, T)
        A = body.basis_rows(kf.vertices, kf.on)
        AtA = A.T @ A
        rest = body.rest_positions(kf.on)[kf.vertices].ravel()
        if kf.position is not None and c_A > 0:
            sl = slice(at(k) * r, (at(k) + 1) * r)
            H[sl, sl] = H[sl, sl] + c_A * AtA
            b[sl] += c_A * (A.T @ (kf.position.ravel() - rest))
        if kf.velocity is not None and c_B > 0:
            if loop:
                stencil = {at(k - 1): -0.5 / dt, at(k + 1): 0.5 / dt}
            elif 0 < k < n:
                stencil = {k - 1: -0.5 / dt, k + 1: 0.5 / dt}
            elif k == 0:
                stencil = {0: -1.5 / dt, 1: 2.0 / dt, 2: -0.5 / dt}
            else:
                stencil = {n: 1.5 / dt, n - 1: -2.0 / dt, n - 2: 0.5 / dt}
            AtB = A.T @ kf.velocity.ravel()
            for f1, w1 in stencil.items():
                s1 = slice(f1 * r, (f1 + 1) * r)
                b[s1] += c_B * w1 * AtB
                for f2, w2 in stencil.items():
                    s2 = slice(f2 * r, (f2 + 1) * r)
                    H[s1, s2] = H[s1, s2] + c_B * w1 * w2 * AtA
    q = spla.spsolve(H.tocsc(), b).reshape(frames, r)
    return times, np.vstack([q, q[:1]]) if loop else q
