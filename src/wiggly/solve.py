"""The linear sparse spacetime solve over node values and velocities (SYSTEM.md §4–5).

By Theorem 1 the minimiser of E + E_C is, in every mode, a wiggly spline with nodes at the
keyframe times (and at the start and end of the animation).  The unknowns are the node values
q_i(t_k) and node velocities q_i'(t_k) of every mode i: z = (z_0, ..., z_m) with
z_k = (q_0(t_k) .. q_{r-1}(t_k), q_0'(t_k) .. q_{r-1}'(t_k)).  The energy is a sum of exact
per-interval quadratic forms (:func:`wiggly.splines.energy_form`), banded in time; E_C couples
the modes at a node.  The minimiser solves one banded SPD system H z = -f.

Pre-roll (our regularization).  E vanishes on every free motion, so with sparse keyframes
E + E_C is only semi-definite, and its minimisers may meet the keyframes with large free
vibrations that cost nothing.  We therefore assume the body rests (at static equilibrium
q_eq) until ``preroll`` seconds before t_0 and extend E over that virtual interval, with no
gravity in it: the extra term is exactly the least spacetime energy (same functional, same
wiggly splines) needed to bring each mode from rest to its state (q(t_0), q'(t_0)).  It is
positive definite, so the system always has a unique solution, and it is negligible when the
keyframes fix the start.  ``preroll=None`` (default) uses the animation's duration;
``preroll=0`` disables it (pure E + E_C; undetermined problems then raise an error).
"""

from __future__ import annotations

import sys
import time as _time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike

from wiggly.body import Body, Where
from wiggly.errors import WigglyInputError
from wiggly.keyframes import Keyframe
from wiggly.splines import WigglyBasis, energy_form, equilibrium, evaluate, wiggly_basis



@dataclass(eq=False)
class Animation:
    """A solved motion: wiggly splines in every mode, with nodes at the keyframe times.

    Attributes
    ----------
    body : Body
    nodes : (m+1,) node times t_0 < ... < t_m in seconds.
    values, velocities : (m+1, r) q_i(t_k) and q_i'(t_k) of every mode at every node.
    keyframes : the (validated) keyframes that produced it.
    """

    body: Body
    nodes: np.ndarray
    values: np.ndarray
    velocities: np.ndarray
    keyframes: list[Keyframe]
    basis: WigglyBasis = field(repr=False)
    info: dict = field(default_factory=dict)

    @property
    def start(self) -> float:
        return float(self.nodes[0])

    @property
    def end(self) -> float:
        return float(self.nodes[-1])

    @property
    def duration(self) -> float:
        return self.end - self.start

    def frame_times(self, fps: float = 30.0) -> np.ndarray:
        """Frame times start, start + 1/fps, ... up to and including the end (if on the grid)."""
        n = int(np.floor(self.duration * fps + 1e-9)) + 1
        return self.start + np.arange(n) / fps

    # --- modal trajectories ------------------------------------------------------------
    def modal(self, times: ArrayLike, n_derivatives: int = 0,
              side: str = "right") -> np.ndarray:
        """q(t) and its time derivatives for all modes: shape (n_derivatives + 1, F, r).

        At a node the spline of the interval to the ``side`` of it is used (the one-sided
        limits differ in derivatives of order 2 or 3, Theorem 1).
        """
        t = np.atleast_1d(np.asarray(times, dtype=float))
        tol = 1e-9 * max(1.0, self.duration)
        if np.any(~np.isfinite(t)) or np.any(t < self.start - tol) or np.any(t > self.end + tol):
            raise WigglyInputError(
                f"times must lie in the animation's range [{self.start}, {self.end}] s; got "
                f"[{np.nanmin(t)}, {np.nanmax(t)}]"
            )
        t = np.clip(t, self.start, self.end)
        m, r = len(self.nodes) - 1, self.body.r
        k = np.clip(np.searchsorted(self.nodes, t, side=side) - 1, 0, m - 1)
        h = np.diff(self.nodes)[k]
        tau = (t - self.nodes[k]) / h
        idx = (k[:, None] * r + np.arange(r)).ravel()  # (F*r,)
        data = np.stack([self.values[k], self.velocities[k], self.values[k + 1],
                         self.velocities[k + 1]], axis=-1).reshape(-1, 4)
        g = np.tile(self.body.modal_gravity, len(t))
        out = evaluate(self.basis.take(idx), data, g, np.repeat(tau, r), n_derivatives)
        return out.reshape(n_derivatives + 1, len(t), r)

    # --- vertex trajectories -------------------------------------------------------------
    def displacements(self, times: ArrayLike, on: Where = "surface", derivative: int = 0,
                      dtype: type = np.float64) -> np.ndarray:
        """u(t) = Phi q(t) (or its ``derivative``-th time derivative): shape (F, n, 3)."""
        q = self.modal(times, derivative)[derivative]
        B = self.body.basis(on)
        out = q.astype(dtype, copy=False) @ B.T.astype(dtype, copy=False)
        return out.reshape(len(q), -1, 3)

    def positions(self, times: ArrayLike, on: Where = "surface",
                  dtype: type = np.float64) -> np.ndarray:
        """Vertex positions rest + u(t) for all ``times``: shape (F, n, 3)."""
        u = self.displacements(times, on, 0, dtype)
        u += self.body.rest_positions(on).astype(dtype, copy=False)
        return u

    def velocities_at(self, times: ArrayLike, on: Where = "surface") -> np.ndarray:
        """Vertex velocities u'(t): shape (F, n, 3)."""
        return self.displacements(times, on, 1)

    def accelerations_at(self, times: ArrayLike, on: Where = "surface") -> np.ndarray:
        """Vertex accelerations u''(t): shape (F, n, 3)."""
        return self.displacements(times, on, 2)

    # --- diagnostics ---------------------------------------------------------------------
    def energy(self) -> float:
        """E of eq. (3): the integrated squared extra force (M^-1 norm), summed over modes."""
        x = _interval_data(self.values, self.velocities)
        form = energy_form(self.basis, np.tile(self.body.modal_gravity, len(self.nodes) - 1))
        return float(form(x).sum())

    def constraint_residuals(self) -> list[dict]:
        """Per keyframe: RMS and max distance (m) to the position targets, RMS velocity error."""
        out = []
        for kf in self.keyframes:
            row: dict = {"time": kf.time, "name": kf.name, "n_vertices": len(kf.vertices)}
            if kf.position is not None:
                x = self.positions([kf.time], kf.on)[0][kf.vertices]
                d = np.linalg.norm(x - kf.position, axis=1)
                row.update(position_rms=float(np.sqrt(np.mean(d**2))), position_max=float(d.max()))
            if kf.velocity is not None:
                v = self.velocities_at([kf.time], kf.on)[0][kf.vertices]
                d = np.linalg.norm(v - kf.velocity, axis=1)
                row.update(velocity_rms=float(np.sqrt(np.mean(d**2))))
            out.append(row)
        return out


def _interval_data(values: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """Hermite data (q_k, q_k', q_k+1, q_k+1') per (interval, mode): shape (m*r, 4)."""
    return np.stack([values[:-1], velocities[:-1], values[1:], velocities[1:]],
                    axis=-1).reshape(-1, 4)


class SpacetimeProblem:
    """Assembles and solves the banded SPD system of E + E_C for one body and node set.

    The per-interval energy forms depend only on the node times, so they are reused when
    keyframe targets or weights change (interactive editing).
    """

    def __init__(self, body: Body, start: float, end: float,
                 preroll: float | None = None) -> None:
        if not (np.isfinite(start) and np.isfinite(end)) or end <= start:
            raise WigglyInputError(
                f"the animation's time range [{start}, {end}] s is empty: end must be after start"
            )
        preroll = end - start if preroll is None else float(preroll)
        if not np.isfinite(preroll) or preroll < 0:
            raise WigglyInputError(f"preroll = {preroll!r} s must be a number >= 0")
        self.body = body
        self.start, self.end = float(start), float(end)
        self.preroll = preroll
        self._energy_cache: dict[tuple, tuple] = {}

    @property
    def duration(self) -> float:
        return self.end - self.start

    def nodes_for(self, keyframes: list[Keyframe]) -> np.ndarray:
        """Node times: start, end and every keyframe time (merged within 1e-9 T)."""
        t = np.sort(np.r_[self.start, self.end, [kf.time for kf in keyframes]])
        keep = np.r_[True, np.diff(t) > 1e-9 * self.duration]
        t = t[keep]
        t[-1] = self.end
        return t

    def _energy(self, nodes: np.ndarray) -> tuple:
        key = tuple(np.round(nodes, 12))
        if key not in self._energy_cache:
            body = self.body
            r, m = body.r, len(nodes) - 1
            h = np.repeat(np.diff(nodes), r)
            lam = np.tile(body.eigenvalues, m)
            basis = wiggly_basis(lam, np.tile(body.delta, m), h)
            form = energy_form(basis, np.tile(body.modal_gravity, m))
            # global indices of (q_k,i, v_k,i, q_k+1,i, v_k+1,i)
            k = np.repeat(np.arange(m), r)
            i = np.tile(np.arange(r), m)
            idx = np.stack([2 * r * k + i, 2 * r * k + r + i, 2 * r * (k + 1) + i,
                            2 * r * (k + 1) + r + i], axis=1)
            if len(self._energy_cache) > 8:
                self._energy_cache.clear()
            self._energy_cache[key] = (basis, form, idx)
        return self._energy_cache[key]

    def _preroll(self) -> tuple[np.ndarray, np.ndarray]:
        """Least energy to reach (q, q') from rest in ``preroll`` seconds, without gravity:
        1/2 (q - q_eq, q')^T Q22 (q - q_eq, q') per mode; returns Q22 and its linear term."""
        body, r = self.body, self.body.r
        basis = wiggly_basis(body.eigenvalues, body.delta, self.preroll)
        Q22 = energy_form(basis, np.zeros(r)).Q[:, 2:, 2:]
        q_eq = equilibrium(body.eigenvalues, body.modal_gravity)
        lin = -Q22[:, :, 0] * q_eq[:, None]  # -Q22 (q_eq, 0)
        return Q22, np.r_[lin[:, 0], lin[:, 1]]

    def solve(self, keyframes: list[Keyframe]) -> Animation:
        """Minimise E + E_C over node values and velocities; return the :class:`Animation`."""
        t_start = _time.perf_counter()
        body = self.body
        kfs = [kf.checked(body, self.start, self.end, label=_label(kf, j))
               for j, kf in enumerate(keyframes)]
        nodes = self.nodes_for(kfs)
        basis, form, idx = self._energy(nodes)
        r, n_nodes = body.r, len(nodes)
        N = 2 * r * n_nodes
        bw = 4 * r - 1  # upper bandwidth of the node-major ordering
        ab = np.zeros((bw + 1, N))
        f = np.zeros(N)
        _add_dense(ab, bw, idx, form.Q)
        np.add.at(f, idx.ravel(), form.l.ravel())
        T = self.duration
        if self.preroll > 0:  # rest before t_0 (see module doc): 2x2 form per mode
            Q22, f0 = self._preroll()
            i = np.arange(r)
            _add_dense(ab, bw, np.stack([i, r + i], axis=1), Q22)
            f[:2 * r] += f0
        # sparse least-squares keyframes, eq. (4), at their nodes
        for kf in kfs:
            k = int(np.argmin(np.abs(nodes - kf.time)))
            c_A, c_B = kf.weights(body, T)
            A = body.basis_rows(kf.vertices, kf.on)  # (3s, r) = A_k Phi
            AtA = A.T @ A
            rest = body.rest_positions(kf.on)[kf.vertices].ravel()
            if kf.position is not None and c_A > 0:
                blk = 2 * r * k + np.arange(r)
                _add_block(ab, bw, blk, c_A * AtA)
                f[blk] -= c_A * (A.T @ (kf.position.ravel() - rest))
            if kf.velocity is not None and c_B > 0:
                blk = 2 * r * k + r + np.arange(r)
                _add_block(ab, bw, blk, c_B * AtA)
                f[blk] -= c_B * (A.T @ kf.velocity.ravel())
        # equilibrate (node values and velocities have different units), then banded Cholesky
        d = ab[bw].copy()
        s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
        abs_ = ab * _band_scale(s, bw)
        try:
            cb = sla.cholesky_banded(abs_, lower=False, check_finite=False)
        except np.linalg.LinAlgError as err:
            raise WigglyInputError(
                "the keyframes leave the motion undetermined and preroll is 0; give keyframes "
                "that fix the start (positions and velocities of the whole body) or a preroll > 0"
            ) from err
        z = sla.cho_solve_banded((cb, False), -f * s, check_finite=False)
        for _ in range(2):  # iterative refinement: keyframe weights make H ill-conditioned
            z += sla.cho_solve_banded((cb, False), -f * s - _band_matvec(abs_, bw, z),
                                      check_finite=False)
        z = s * z
        z = z.reshape(n_nodes, 2, r)
        anim = Animation(body, nodes, z[:, 0].copy(), z[:, 1].copy(), kfs, basis)
        anim.info["solve_seconds"] = _time.perf_counter() - t_start
        anim.info["unknowns"] = N
        return anim



def _label(kf: Keyframe, j: int) -> str:
    return f"keyframe #{j}" + (f" ('{kf.name}')" if kf.name else "") + f" at t={kf.time}"


def _band_scale(s: np.ndarray, bw: int) -> np.ndarray:
    """Entries s_i s_j of the upper band storage ab[bw + i - j, j]."""
    N = len(s)
    out = np.zeros((bw + 1, N))
    for d in range(bw + 1):  # diagonal offset j - i = d, stored in row bw - d
        out[bw - d, d:] = s[: N - d] * s[d:]
    return out


def _band_matvec(ab: np.ndarray, bw: int, x: np.ndarray) -> np.ndarray:
    """y = H x for symmetric H in upper band storage ab[bw + i - j, j] = H[i, j]."""
    N = len(x)
    y = ab[bw] * x
    for d in range(1, bw + 1):
        row = ab[bw - d, d:]  # H[i, i + d] for i = 0 .. N-d-1
        y[: N - d] += row * x[d:]
        y[d:] += row * x[: N - d]
    return y


def _add_dense(ab: np.ndarray, bw: int, idx: np.ndarray, blocks: np.ndarray) -> None:
    """Scatter symmetric dense blocks (P, b, b) at global indices idx (P, b) into upper band."""
    rows = np.broadcast_to(idx[:, :, None], blocks.shape)
    cols = np.broadcast_to(idx[:, None, :], blocks.shape)
    upper = rows <= cols
    np.add.at(ab, (bw + rows[upper] - cols[upper], cols[upper]), blocks[upper])


def _add_block(ab: np.ndarray, bw: int, idx: np.ndarray, block: np.ndarray) -> None:
    _add_dense(ab, bw, idx[None], block[None])


def solve(body: Body, keyframes: list[Keyframe], *, duration: float | None = None,
          start: float = 0.0, end: float | None = None,
          preroll: float | None = None, progress: bool = False) -> Animation:
    """Animate ``body`` through the sparse ``keyframes`` (linear solve, Theorem 1).

    The time range is [start, end] (``end = start + duration``; default: the last keyframe
    time, at least start + 1 s).
    """
    if end is None:
        if duration is None:
            last = max((kf.time for kf in keyframes), default=start)
            duration = max(float(last) - start, 1.0)
        end = start + float(duration)
    problem = SpacetimeProblem(body, start, end, preroll)
    anim = problem.solve(keyframes)
    if progress:
        print(f"[wiggly] linear solve: {anim.info['unknowns']} unknowns in "
              f"{anim.info['solve_seconds'] * 1e3:.1f} ms", file=sys.stderr)
    return anim

