"""Secondary motion: the driver owns the driven group, physics moves the free parts.

A driver (a rig's walk, a motion-capture clip) is a *moving rest state* of the whole body
(Complementary Dynamics, Zhang et al. 2020): the rig field ubar(t) is the driver's
displacement of every surface vertex, extended into the tet mesh (its best-fit affine motion
exactly, plus a harmonic extension of the rest; elastic forces act on Psi q only, so the
extension enters through the mass matrix alone) and unwarped for warped playback
(:mod:`wiggly.drive.unwarp`), cubic in time through the driver's frames.  The motion is

    u(t) = ubar(t) + Psi q(t),

with Psi the lowest modes of the body with the driven group held (fixed-interface modes,
Craig & Bampton 1968): zero on the driven group, which therefore follows the driver, and
M-orthonormal with Psi^T K Psi = diag(lambda) on the free parts.  Elasticity and stiffness
damping act on the complementary displacement Psi q, inertia and mass damping on the whole
motion.  The spacetime energy of Schulz et al. 2014 (eq. (4)), charged on the free parts only,
then decouples per mode as before, with the driver's accelerations as a forcing term:

    E = 1/2 sum_i int (q_i'' + 2 delta_i q_i' + lambda_i q_i + g_i + p_i(t))^2 dt,
    p_i(t) = kappa psi_i^T M (ubar''(t) + alpha ubar'(t)),

where kappa is the ``intensity`` (1: physical; 0: no push from the driver, only gravity's
sag, which turns with the body when warped; 2: twice the swing, at the same timing).
Between two nodes p_i is a quadratic polynomial (ubar is cubic; a cubic where the forces are
turned, below), so it has a polynomial particular solution q_p with L q_p = -(g + p)
(L = d^2 + 2 delta d + lambda); with y = q - q_p the interval's energy is the unforced one of
y, and the minimiser is q_p plus a wiggly spline (Theorem 1 with g = 0), C^1 at every node
and C^2 where no velocity is prescribed.  Nodes fall at the driver's frames and the user's
keyframe times; the unknowns are node values and velocities of every free mode.

Warped playback carries the free parts in the rig's frame (:mod:`wiggly.drive.carried`):
the driver's own pose of the tet mesh plus the fit of the rig's warped gradient times the
free parts' own, less the rig's (W(ubar, Psi q) - W(ubar)), so that the free parts rest on
the rig's pose of them and their bending and sag turn with the body by any angle; the
driver's inertial forces and gravity above act turned into that frame, rotation by rotation
at each vertex (what that adds to g + p is a cubic spline through the driver's frames), and
the frame's own Coriolis, Euler and centrifugal forces and the stress stiffening of the free
parts' loads there (:mod:`wiggly.drive.stress`) act on Psi q, interpolated linearly between
nodes (at least :data:`NODES_PER_PERIOD` per period of those forces and the lowest free
mode).

Without keyframes on the free parts, E = 0 is reached by the forced ODE's solution that
starts at rest relative to the driver (q' = 0, and q = -g / lambda: in equilibrium under
gravity; a looped shot is periodic instead): one banded linear solve, no Newton iterations.
Sparse keyframes on the free parts (eq. (6)) add least-squares terms at their nodes; for warped
playback their targets apply to W(ubar, Psi q) and are met by Gauss-Newton on the few keyed
nodes (Theorem 2: the minimiser is still a wiggly spline in every mode).  Linear playback
(``warped=False``) adds Psi q to the driver's displacement in the rest pose's frame.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike

from wiggly.body import Body, Where
from wiggly.checks import vertex_indices
from wiggly.drive.carried import FrameTerms, HeldWarp, frame_fits, free_parts, turned_forces
from wiggly.drive.driver import Driver, keyed_frames
from wiggly.drive.driver_checks import (
    step_turns,
    warn_cuts,
    warn_seam,
    warn_sparse_turn,
    warn_stop,
    warn_turn,
    warn_unconverged,
    warn_unstable,
)
from wiggly.drive.frame_spline import FrameSpline
from wiggly.drive.held import free_modes, held_modes, held_vertices
from wiggly.drive.stress import (
    gravity_stiffnesses,
    load_stiffnesses,
    lowest_eigenvalues,
    pins_the_body,
    stress_matters,
)
from wiggly.drive.unwarp import Unwarp
from wiggly.errors import WigglyInputError, warn
from wiggly.keyframes import Keyframe
from wiggly.linalg import blas_single_thread, factorize_spd, one_blas_thread
from wiggly.mesh.defects import diagonal
from wiggly.progress import deprecated_progress, note
from wiggly.solve.animation import Animation
from wiggly.solve.nodes import node_index, node_times, refine_nodes
from wiggly.splines import (
    cubic_at,
    cubic_hermite,
    energy_form,
    evaluate,
    particular_cubic,
    wiggly_basis,
)

__all__ = ["DEFAULT_FREE_MODES", "FrameSpline", "HeldWarp", "SecondaryMotion", "free_modes",
           "held_vertices",
           "secondary_frames", "secondary_motion"]

#: Fixed-interface modes of the free parts, unless asked otherwise.
DEFAULT_FREE_MODES = 24
#: Gauss-Newton on warped keyframes of the free parts: iteration budget, and the distance
#: from the fixed point, relative to the largest node coordinate (at least 1), below which
#: the iteration has converged (estimated from the last steps' contraction).
_GN_ITERATIONS, _GN_TOLERANCE = 30, 1e-9
#: Nodes per period of the turning frames' forces, at least, in a warped secondary motion
#: (:meth:`wiggly.drive.carried.FrameTerms.step`): they are interpolated linearly between
#: nodes.
NODES_PER_PERIOD = 16
#: ... but no more nodes than this in all, so that a long shot stays within memory.
MAX_NODES = 4000


@dataclass(eq=False)
class SecondaryMotion(Animation):
    """A solved secondary motion (module doc): u(t) = ubar(t) + Psi q(t), played linear or
    warped (the driver's pose plus the free parts carried in the rig's frame,
    :class:`wiggly.drive.carried.HeldWarp`).  ``values``/``velocities`` are the free modes'
    node data, ``basis`` their wiggly-spline kernels (g = 0) and ``particular`` (m, r, 4)
    each interval's cubic particular solution."""

    rig: FrameSpline = field(default=None, repr=False)
    psi: np.ndarray = field(default=None, repr=False)
    #: lambda of the free modes ``psi`` (their eigenvalues with the driven group held)
    free_eigenvalues: np.ndarray = field(default=None, repr=False)
    particular: np.ndarray = field(default=None, repr=False)
    held_warp: HeldWarp | None = field(default=None, repr=False)
    #: the driver's own displacement extended into the tet mesh (the linear rig; ``rig`` is
    #: its unwarped version for warped motions): what the driven group is held on
    driver_rig: FrameSpline = field(default=None, repr=False)
    #: (shot times, driver frame indices, driven surface vertices, driver): what
    #: :func:`wiggly.drive.following` measures
    driven_frames: tuple | None = field(default=None, repr=False)

    def modal(self, times: ArrayLike, n_derivatives: int = 0, side: str = "right") -> np.ndarray:
        """q(t) of the free modes and its time derivatives: shape (n_derivatives + 1, F, r)."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        tol = 1e-9 * max(1.0, self.duration)
        if np.any(~np.isfinite(t)) or np.any(t < self.start - tol) or np.any(t > self.end + tol):
            raise WigglyInputError(
                f"times must lie in the animation's range [{self.start}, {self.end}] s; got "
                f"[{np.nanmin(t)}, {np.nanmax(t)}]")
        t = np.clip(t, self.start, self.end)
        m, r = len(self.nodes) - 1, self.psi.shape[1]
        k = np.clip(np.searchsorted(self.nodes, t, side=side) - 1, 0, m - 1)
        h = np.diff(self.nodes)[k]
        x = t - self.nodes[k]
        idx = (k[:, None] * r + np.arange(r)).ravel()
        data = np.stack([self.values[k], self.velocities[k], self.values[k + 1],
                         self.velocities[k + 1]], axis=-1)  # (F, r, 4)
        a = self.particular[k]  # (F, r, 4)
        data = (data - cubic_hermite(a, h[:, None])).reshape(-1, 4)
        out = evaluate(self.basis.take(idx), data, 0.0, np.repeat(x / h, r), n_derivatives)
        out = out.reshape(n_derivatives + 1, len(t), r)
        for d in range(min(n_derivatives, 3) + 1):
            out[d] += cubic_at(a, x[:, None], d)
        return out

    def linear_field(self, times: ArrayLike, derivative: int = 0,
                     rig_only: bool = False) -> np.ndarray:
        """ubar(t) + Psi q(t) (or a time derivative; ubar alone with ``rig_only``) on the
        tet mesh: shape (F, n, 3)."""
        U = self._rig_field(times, derivative)
        return U if rig_only else U + self._modal_field(times, derivative)

    def _rig_field(self, times: ArrayLike, derivative: int = 0) -> np.ndarray:
        """ubar(t) (or a time derivative) on the tet mesh, (F, n, 3)."""
        U = self.rig(np.atleast_1d(times), derivative)
        return U.reshape(len(U), -1, 3)

    def _modal_field(self, times: ArrayLike, derivative: int = 0) -> np.ndarray:
        """Psi q(t) (or a time derivative) on the tet mesh, (F, n, 3)."""
        t = np.atleast_1d(times)
        U = self.modal(t, derivative)[derivative] @ self.psi.T
        return U.reshape(len(t), -1, 3)

    @property
    def held_modes(self) -> tuple[np.ndarray, np.ndarray]:
        """(Psi, lambda): the free parts' modes with the driven group held."""
        return self.psi, self.free_eigenvalues

    def _driver(self, times: np.ndarray, derivative: int = 0) -> np.ndarray:
        """The driver's displacement (or velocity) on the tet mesh, (F, n, 3)."""
        D = self.driver_rig(np.atleast_1d(times), derivative)
        return D.reshape(len(D), -1, 3)

    def displacements(self, times: ArrayLike, on: Where = "surface", derivative: int = 0,
                      dtype: type = np.float64) -> np.ndarray:
        """Displacements (or a time derivative), (F, n, 3): ubar + Psi q, or warped
        W(ubar + Psi q) and DW(u) u' (module doc)."""
        if self.warped:  # the warp's compiled passes need the cores (linear playback does not)
            with blas_single_thread():
                return self._displacements(times, on, derivative, dtype)
        return self._displacements(times, on, derivative, dtype)

    def _displacements(self, times: ArrayLike, on: Where, derivative: int,
                       dtype: type) -> np.ndarray:
        times = np.atleast_1d(np.asarray(times, float))
        body = self.body
        if self.warped and derivative > 1:
            raise WigglyInputError(
                "accelerations are available for linear motion (warp=False) only; for the "
                "warped motion sample positions densely and differentiate numerically")
        out = np.empty((len(times), body.n_vertices(on), 3), dtype=dtype)
        E = body.surface_embedding
        for f0 in range(0, len(times), 64):
            tt = times[f0:f0 + 64]
            if not self.warped:
                W = self.linear_field(tt, derivative)
            elif derivative == 0:
                W = self.held_warp.apply(self._rig_field(tt), self._modal_field(tt),
                                         self._driver(tt))
            else:
                W = self.held_warp.jvp(self._rig_field(tt), self._rig_field(tt, 1),
                                       self._modal_field(tt), self._modal_field(tt, 1),
                                       self._driver(tt, 1))
            if on == "surface":
                n = W.shape[1]
                W = (E @ W.transpose(1, 0, 2).reshape(n, -1)).reshape(E.shape[0], -1, 3)
                W = W.transpose(1, 0, 2)
            out[f0:f0 + len(tt)] = W
        return out

    def energy(self) -> float:
        """E of the free parts (module doc): the integrated squared force beyond elasticity,
        damping, gravity and the driver's inertial forcing, in the M^-1 norm."""
        m, r = len(self.nodes) - 1, self.psi.shape[1]
        h = np.diff(self.nodes)
        x = np.stack([self.values[:-1], self.velocities[:-1], self.values[1:],
                      self.velocities[1:]], axis=-1)
        x = (x - cubic_hermite(self.particular, h[:, None])).reshape(-1, 4)
        form = energy_form(self.basis, np.zeros(m * r))
        return float(form(x).sum())


def _gn_distance(steps: list[float]) -> float:
    """The Gauss-Newton iterate's distance from its fixed point, estimated from its steps
    s_k as a linear contraction's, s_k rho / (1 - rho), rho the larger of the last two step
    ratios; inf while no contraction shows (fewer than three steps, or rho >= 1), 0 after a
    step of 0.  The velocity keys' rig term is linearized at the last iterate, so the
    iteration contracts linearly (0.28 per step on a review's antenna)."""
    if steps and steps[-1] == 0.0:
        return 0.0
    if len(steps) < 3:
        return np.inf
    rho = max(steps[-1] / steps[-2], steps[-2] / steps[-3])
    return steps[-1] * rho / (1.0 - rho) if rho < 1.0 else np.inf


def _runaway(source: str, coupling: tuple | None, lam: np.ndarray,
             seam: bool = False) -> WigglyInputError:
    """The error of a secondary motion whose spline system is not positive definite: its
    free parts' motion grows without bound (the turning frame's centrifugal force beyond
    their stiffness), and its numbers lose all precision.  ``seam``: the shot loops on a
    driver that does not cycle with it (warned), whose jump at the seam makes the turn."""
    rate = 0.0
    if coupling is not None:  # |G| = 2 |W| (Psi^T M Psi = I)
        rate = 0.5 * float(max(np.linalg.norm(G, 2) for G in coupling[0])) / (2 * np.pi)
    if seam:
        return WigglyInputError(
            f"the secondary motion on the driver {source} has no bounded solution: the loop "
            "joins the driver's last pose to its first across the seam (warned above), and "
            "that jump turns the free parts faster than their stiffness holds them; end the "
            "shot on the driver's cycle (time.end), keep one cycle of it (drive.range), or "
            "turn time.loop off")
    return WigglyInputError(
        f"the secondary motion on the driver {source} has no bounded solution: the driver "
        f"turns the free parts at up to {rate:.2g} turns per second, past their lowest "
        f"frequency ({np.sqrt(lam.min()) / (2 * np.pi):.2g} Hz), where the centrifugal force "
        "of the turning frame overcomes their stiffness in linear elasticity; stiffen the "
        "free parts (a group's young), slow the turn, or use simulation.warp = false")


def _energy_system(Q: np.ndarray, lam: np.ndarray, delta: np.ndarray, h: np.ndarray,
                   c: np.ndarray, blocks: int, coupling: tuple | None):
    """H (sparse), b and ``forcing``: E(z) = 1/2 z^T H z - b^T z + const over the node values
    and velocities z (module doc), and ``forcing(z)``, each interval's forcing coefficients
    (m, r, 4).  Q (m, r, 4, 4) are the intervals' energy forms, c (m, r, 4) their forcing.
    With ``coupling`` (G, N), the turning frame's matrices at the nodes (m + 1, r, r), interval
    k's forcing adds ``G q' + N q`` interpolated linearly between its nodes: linear in z, so E
    stays quadratic (and banded), its minimum without keys still the forced ODE's solution."""
    m, r = c.shape[:2]
    k0 = np.arange(m)
    k1 = (k0 + 1) % blocks
    xp = cubic_hermite(particular_cubic(lam, delta, c), h[:, None])  # (m, r, 4)
    if coupling is None:
        i = np.arange(r)
        idx = np.stack([2 * k0[:, None] * r + i, (2 * k0[:, None] + 1) * r + i,
                        2 * k1[:, None] * r + i, (2 * k1[:, None] + 1) * r + i], axis=-1)
        rows = np.broadcast_to(idx[..., :, None], Q.shape).ravel()
        cols = np.broadcast_to(idx[..., None, :], Q.shape).ravel()
        b = np.zeros(2 * r * blocks)
        np.add.at(b, idx.ravel(), np.einsum("mrij,mrj->mri", Q, xp).ravel())
        return (sp.csr_matrix((Q.ravel(), (rows, cols)), shape=(len(b), len(b))), b,
                lambda z: c)
    G, Nq = coupling
    # D: forcing coefficients 0 and 1 of interval k from its [q_k, q'_k, q_k+1, q'_k+1]
    D = np.zeros((m, r, 2, 4 * r))
    D[:, :, 0, :r], D[:, :, 0, r:2 * r] = Nq[:-1], G[:-1]
    hh = h[:, None, None]
    D[:, :, 1] = np.concatenate([-Nq[:-1], -G[:-1], Nq[1:], G[1:]], axis=2) / hh
    # P: the Hermite data of the particular solution per unit coefficient 0 and 1
    P = np.stack([cubic_hermite(particular_cubic(lam, delta, np.broadcast_to(unit, (m, r, 4))),
                              h[:, None]) for unit in np.eye(4)[:2]], axis=-1)  # (m, r, 4, 2)
    A = -np.einsum("kiaj,kijx->kiax", P, D)  # (m, r, 4, 4r): Hermite data minus particular
    i, a = np.arange(r)[:, None], np.arange(4)[None, :]
    A[:, i, a, a * r + i] += 1.0
    QA = np.einsum("kiab,kibx->kiax", Q, A).reshape(m, 4 * r, 4 * r)
    A = A.reshape(m, 4 * r, 4 * r)
    Hk = A.transpose(0, 2, 1) @ QA
    bk = np.einsum("kyx,ky->kx", QA, xp.reshape(m, 4 * r))
    glob = np.concatenate([2 * k0[:, None] * r + np.arange(2 * r),
                           2 * k1[:, None] * r + np.arange(2 * r)], axis=1)  # (m, 4r)
    n = 2 * r * blocks
    b = np.zeros(n)
    np.add.at(b, glob.ravel(), bk.ravel())
    H = sp.csr_matrix((Hk.ravel(), (np.broadcast_to(glob[:, :, None], Hk.shape).ravel(),
                                    np.broadcast_to(glob[:, None, :], Hk.shape).ravel())),
                      shape=(n, n))

    def forcing(z: np.ndarray) -> np.ndarray:
        out = c.copy()
        out[:, :, :2] += np.einsum("kijx,kx->kij", D, z[glob])
        return out

    return H, b, forcing


def _rows(body: Body, psi: np.ndarray, vertices: np.ndarray, on: Where) -> np.ndarray:
    """Rows (3s, r) of Psi for the xyz dofs of ``vertices`` (surface: embedded)."""
    n, r = body.tets.n_vertices, psi.shape[1]
    P = psi.reshape(n, 3 * r)
    if on == "surface":
        rows = body.surface_embedding[vertices] @ P
    else:
        rows = P[vertices]
    return np.asarray(rows).reshape(-1, r)


def _field_rows(body: Body, U: np.ndarray, vertices: np.ndarray, on: Where) -> np.ndarray:
    """A tet field U (n, 3) at ``vertices`` (s, 3)."""
    return np.asarray(body.surface_embedding[vertices] @ U) if on == "surface" else U[vertices]


def _forcing(nodes: np.ndarray, rig: FrameSpline, C: np.ndarray, g: np.ndarray,
             alpha: float, intensity: float) -> np.ndarray:
    """Coefficients c (m, r, 4) of the forcing g + p(t) on every interval between ``nodes``,
    in local time: intensity Psi^T M (ubar'' + alpha ubar') of the rig (exact: a quadratic,
    ubar being cubic) plus gravity's g (r,); C = Psi^T M (r, 3n).  The accelerations are the
    driver's in world space, for warped playback too (module doc)."""
    m, r = len(nodes) - 1, C.shape[0]
    out = np.zeros((m, r, 4))
    # the Taylor coefficients are linear in the frames' values and slopes: project first
    projected = FrameSpline(rig.times, rig.values @ C.T, rig.slopes @ C.T)
    s = projected.taylor(nodes[:-1])  # (m, 4, r): Taylor coefficients right of each node
    out[:, :, 0] = intensity * (2 * s[:, 2] + alpha * s[:, 1])
    out[:, :, 1] = intensity * (6 * s[:, 3] + 2 * alpha * s[:, 2])
    out[:, :, 2] = intensity * 3 * alpha * s[:, 3]
    out[:, :, 0] += g
    return out


def secondary_frames(
    driver: Driver,
    *,
    start: float,
    end: float,
    loop: bool = False,
    offset: float = 0.0,
    driver_range: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The driver frames secondary motion follows, and their shot times
    (:func:`wiggly.drive.keyed_frames`): two or more in the shot; a looped shot needs one at
    its start and ends on its first frame again.  Raises :class:`WigglyInputError` naming
    the driver otherwise (the scene checks call it before meshing)."""
    frames, times = keyed_frames(driver, offset=offset, driver_range=driver_range,
                                 start=start, end=end)
    if len(frames) < 2:
        if driver.n_frames == 1:
            raise WigglyInputError(
                f"the driver {driver.source} is not animated (it has a single pose): secondary "
                "motion needs an animated driver (two frames or more)")
        kept = ("" if driver_range is None else
                f"; drive.range = {[float(x) for x in driver_range]} s keeps too little of it")
        raise WigglyInputError(
            f"the driver {driver.source} has {len(frames)} frame in the shot [{start:g}, "
            f"{end:g}] s: secondary motion needs an animated driver (two frames or more)"
            f"{kept}")
    tol = 1e-9 * (end - start)
    frames = frames.copy()
    if loop:
        if times[0] > start + tol:
            raise WigglyInputError(
                f"a looped shot needs a driver frame at its start ({start:g} s); the first "
                f"frame of {driver.source} in the shot is at {times[0]:g} s: set drive.offset "
                f"= {offset - (times[0] - start):.10g} to start the loop on it (a Blender "
                "export starts at frame 1), or time.start to its time")
        if times[-1] < end - tol:
            times, frames = np.r_[times, end], np.r_[frames, frames[:1]]
        else:
            frames[-1] = frames[0]
    return frames, times


@deprecated_progress
@one_blas_thread
def secondary_motion(
    body: Body,
    driver: Driver,
    driven: ArrayLike,
    keyframes: list[Keyframe] | tuple = (),
    *,
    start: float,
    end: float,
    warped: bool = True,
    loop: bool = False,
    free_mode_count: int = DEFAULT_FREE_MODES,
    intensity: float = 1.0,
    offset: float = 0.0,
    driver_range: tuple[float, float] | None = None,
) -> SecondaryMotion:
    """Secondary motion of the free parts on a driver (module doc).

    ``driven`` are the surface vertices that the driver owns; ``keyframes`` are sparse keys
    of the free parts (targets of vertices the driver owns are the driver's business and do
    not enter).  Driver time ``t`` is shot time ``t + offset``; only driver times in
    ``driver_range`` are used.  Before its first and after its last frame in the shot the
    driver holds its pose.  ``intensity`` scales the driver's inertial forces on the free
    parts without changing their timing.
    """
    t0 = _time.perf_counter()
    if not end > start:
        raise WigglyInputError(f"end = {end} s must be after start = {start} s")
    if not (np.isfinite(intensity) and intensity >= 0):
        raise WigglyInputError(f"intensity = {intensity!r} must be a number >= 0 (1 is "
                               "physical, 0 no push from the driver)")
    surface = body.surface
    driver.check(surface.n_vertices, surface.faces, body.model.source or "of the body")
    v = vertex_indices(driven, surface.n_vertices, "surface", "driven group")
    frames, times = secondary_frames(driver, start=start, end=end, loop=loop, offset=offset,
                                     driver_range=driver_range)
    driven_path = driver.positions[frames][:, v]  # the driven vertices at the frames
    # a loop's last step, back to its first frame, is the seam: warn_seam's, not a cut's
    path, path_times = (driven_path[:-1], times[:-1]) if loop else (driven_path, times)
    seam = loop and warn_seam(driver, v, start=start, end=end, offset=offset,
                              driver_range=driver_range)  # a loop the driver does not cycle
    warn_cuts(driver.source, path, path_times, body)
    if not loop:
        warn_stop(driver.source, driven_path, times, end, body)
    duration = end - start
    tol = 1e-9 * duration
    # the rig: the driver extended into the tet mesh (unwarped for warped playback)
    mass = np.asarray(body.M.sum(axis=1)).ravel()[::3]
    rigging = Unwarp(body.tets.vertices, body.tets.tets, mass)
    note("the driver extended into the tet mesh")
    U = rigging.extend(body.surface_embedding, driver.positions, frames,
                       surface.vertices)  # (3n, F)
    hold_start, hold_end = bool(times[0] > start + tol), bool(times[-1] < end - tol)
    bc = {"loop": loop, "hold_start": hold_start, "hold_end": hold_end}
    linear_rig = FrameSpline.fit(times, U.T, **bc)
    rig = linear_rig
    if warped:
        unwarped = rigging(U)
        # a loop whose driver turns by whole turns per cycle ends unwarped a whole turn (or
        # more) from its start: a periodic fit would unwind that turn in the last interval
        wound = loop and np.abs(unwarped[:, -1] - unwarped[:, 0]).max() > 1e-6 * diagonal(
            body.tets.vertices)
        rig = FrameSpline.fit(times, unwarped.T, **(bc | {"loop": False} if wound else bc))
    rig_seconds = _time.perf_counter() - t0
    # the free parts' modes and their forcing
    t1 = _time.perf_counter()
    held = held_vertices(body, v)
    gravity = np.asarray(body.gravity, float)
    loose = np.ones(body.tets.n_vertices, bool)
    loose[held] = False
    fits, loads = [], None  # warped: the free parts, the vertices their frames fit
    if warped:
        fits = frame_fits(free_parts(body.tets.tets, loose), np.flatnonzero(loose))
        if pins_the_body(body.tets.vertices, held):  # their loads' stress (drive.stress)
            centres = np.array([mass[fit] @ body.tets.vertices[fit] / mass[fit].sum()
                                for _, fit in fits])
            note("the free parts' stiffening by their loads")
            loads = load_stiffnesses(body, held, [part for part, _ in fits], centres)
    if loads is not None and np.any(gravity):
        axes = tuple(sum(blocks) for blocks in zip(*(p.global_axes() for p in loads),
                                                    strict=True))
    else:
        axes = None if loads is not None else gravity_stiffnesses(body, held)
    note("the free parts' modes")
    psi, lam, stressed = held_modes(body, held, free_mode_count, axes)
    modes_seconds = _time.perf_counter() - t1
    steps = step_turns(path)
    if not warped:  # linear: the rest pose's axes, whatever the turn rate
        warn_turn(driver.source, surface.vertices[v], path, path_times)
    warn_sparse_turn(driver.source, steps, path_times)  # the driver's own arc, either way
    held_warp = HeldWarp(body, held) if warped else None
    r = psi.shape[1]
    alpha, beta = body.damping.alpha, body.damping.beta
    delta = 0.5 * (alpha + beta * lam)
    C = np.ascontiguousarray((body.M @ psi).T)  # Psi^T M, (r, 3n)
    own = [k for k in keyframes if k.spec.get("kind") != "drive"]
    nodes = node_times(start, end, list(times) + [k.time for k in own])
    gammas = []  # the loads' modal stiffness per part (drive.stress), when it changes
    base = np.r_[gravity if stressed else np.zeros(3), np.zeros(9)]  # in the modes' lambda
    if warped:
        note("the turning frames' forces")
        terms = FrameTerms(body.tets.vertices, mass, fits, C, psi, alpha, gravity,
                           0.5 * np.pi / np.sqrt(max(float(lam[0]), 1e-300)))
        if loads is not None and (stressed or axes is None):  # (gravity's would buckle)
            gammas = [p.couplings(psi) for p in loads]
        G, Nq, change, _ = terms(times, linear_rig, gammas, base)
        if gammas:  # linear elasticity's stiffness, without gravity's stress in lambda
            plain = np.diag(lam) - sum(np.einsum("k,kij->ij", base, g) for g in gammas)
        lowest = stress_matters(change, lam, plain, times) if gammas else None
        gammas = gammas if lowest is not None else []
        # the frames' forces are interpolated linearly between nodes: resolve their rates
        longest = terms.step(G, Nq, max(float(lam[0]), lowest or 0.0), NODES_PER_PERIOD)
        nodes = refine_nodes(nodes, max(longest, (end - start) / MAX_NODES))
    m = len(nodes) - 1
    h = np.diff(nodes)
    g = psi.T @ body.gravity_vector  # gravity's g_i = psi_i^T g (the sag: -g / lambda)
    c = _forcing(nodes, linear_rig, C, g, alpha, intensity)  # (m, r, 4): g + p(t)
    g0 = g
    if warped:  # the forces turned into the rig's frame (wiggly.drive.carried)
        t1 = _time.perf_counter()
        turned = turned_forces(held_warp.warp, body.tets.tets, rig.values.T, C,
                               intensity * (linear_rig(times, 2) + alpha * linear_rig(times, 1)),
                               gravity)
        c += FrameSpline.fit(times, turned, **bc).taylor(nodes[:-1]).transpose(0, 2, 1)
        g0 = g + turned_forces(held_warp.warp, body.tets.tets, rig.values[:1].T, C,
                               np.zeros((1, C.shape[1])), gravity)[0]
        rig_seconds += _time.perf_counter() - t1
    basis = wiggly_basis(np.tile(lam, m), np.tile(delta, m), np.repeat(h, r))
    Q = energy_form(basis, np.zeros(m * r)).Q.reshape(m, r, 4, 4)
    # unknowns: node k (node m is node 0 in a loop): values at 2 k r + i, velocities at
    # (2 k + 1) r + i
    blocks = m if loop else m + 1
    N = 2 * r * blocks
    coupling = None
    at_start = np.diag(lam)  # the free parts' stiffness at the start (their sag: -g0 by it)
    if warped:  # the turning frames' forces on Psi q, part by part (wiggly.drive.carried)
        G, Nq, change, rates = terms(nodes, linear_rig, gammas, base)
        if gammas:
            Nq = Nq + change  # resting before the shot: gravity's stress alone
            at_start = at_start + terms.resting(start, linear_rig, gammas, base)
        coupling = G, Nq
        warn_unstable(driver.source, nodes, lowest_eigenvalues(lam, Nq), rates, lam)
    H0, b0, forcing = _energy_system(Q, lam, delta, h, c, blocks, coupling)
    fixed = np.zeros(N, bool)
    z = np.zeros(N)
    if not loop:  # at rest relative to the driver, sagging under gravity
        fixed[:2 * r] = True
        z[:r], z[r:2 * r] = np.linalg.solve(at_start, -g0), 0.0
    # the user's keys on the free parts
    keys = []
    for kf in own:
        k = node_index(nodes, kf.time) % blocks
        A = _rows(body, psi, kf.vertices, kf.on)
        if not np.any(A):  # the driver owns every vertex it keys
            warn(f"keyframe {kf.name or ''} at {kf.time:g} s keys only vertices that "
                 "the driver moves; it does not enter the secondary motion (key the "
                 "free parts, or remove it)")
            continue
        c_A, c_B = kf.weights(body, duration)
        keys.append((kf, k, A, c_A, c_B))
    hz = np.sqrt(np.maximum(lam, 0.0)) / (2 * np.pi)
    info: dict = {"secondary": True, "free_modes": r, "driver_frames": len(frames),
                  "free_hz": [float(hz.min()), float(hz.max())] if r else [],
                  "unknowns": int(N - fixed.sum()), "warped": warped, "loop": loop,
                  "intensity": float(intensity),
                  "seconds": {"rig": rig_seconds, "free modes": modes_seconds}}
    t1 = _time.perf_counter()
    iterations, converged, steps = 0, True, []
    n = body.tets.n_vertices
    while True:
        b, added = b0.copy(), []  # the keys' blocks of H: (indices, block) pairs
        for kf, k, A, c_A, c_B in keys:
            t = np.array([kf.time])
            X = body.rest_positions(kf.on)[kf.vertices]
            ubar = rig(t)[0].reshape(n, 3)
            qk = z[2 * k * r:(2 * k + 1) * r]
            if warped:  # linearize the held warp at the current state of the node
                u = (psi @ qk).reshape(n, 3)
                Wu = held_warp.apply(ubar[None], u[None], linear_rig(t).reshape(1, n, 3))[0]
                ubars = np.repeat(ubar[None], r, axis=0)
                dW = held_warp.warp.carried_jvp(ubars, np.zeros_like(ubars),
                                                np.repeat(u[None], r, axis=0),
                                                np.ascontiguousarray(psi.T.reshape(r, n, 3)))
                J = np.stack([_field_rows(body, dW[j], kf.vertices, kf.on).ravel()
                              for j in range(r)], 1)
                base = _field_rows(body, Wu, kf.vertices, kf.on).ravel() - J @ qk
            else:
                J, base = A, _field_rows(body, ubar, kf.vertices, kf.on).ravel()
            blk = np.arange(2 * k * r, (2 * k + 1) * r)
            if kf.position is not None and c_A > 0:
                target = (kf.position - X).ravel() - base
                added.append((blk, c_A * (J.T @ J)))
                b[blk] += c_A * (J.T @ target)
            if kf.velocity is not None and c_B > 0:
                vel = rig(t, 1)[0]
                if warped:
                    du = held_warp.jvp(ubar[None], vel.reshape(1, n, 3), u[None],
                                       np.zeros((1, n, 3)), linear_rig(t, 1).reshape(1, n, 3))[0]
                    vbase = _field_rows(body, du, kf.vertices, kf.on).ravel()
                else:
                    vbase = _field_rows(body, vel.reshape(n, 3), kf.vertices, kf.on).ravel()
                vblk = blk + r
                target = np.broadcast_to(kf.velocity, (len(kf.vertices), 3)).ravel() - vbase
                added.append((vblk, c_B * (J.T @ J)))
                b[vblk] += c_B * (J.T @ target)
        H = H0 + sp.csr_matrix((np.concatenate([B.ravel() for _, B in added]), (
            np.concatenate([np.repeat(i, len(i)) for i, _ in added]),
            np.concatenate([np.tile(i, len(i)) for i, _ in added]))),
            shape=H0.shape) if added else H0
        free = ~fixed
        rhs = b[free] - H[free][:, fixed] @ z[fixed]
        new = z.copy()
        try:
            new[free] = factorize_spd(H[free][:, free])(rhs)
        except np.linalg.LinAlgError as error:  # E is a sum of squares: only a runaway
            raise _runaway(driver.source, coupling, lam, seam) from error
        step = float(np.max(np.abs(new - z))) if keys else 0.0
        z = new
        if not (warped and keys):
            break
        iterations += 1
        steps.append(step)
        note(f"warped keys: Gauss-Newton iteration {iterations}, step {step:.2g}")
        if _gn_distance(steps) <= _GN_TOLERANCE * max(1.0, float(np.max(np.abs(z)))):
            break
        if iterations >= _GN_ITERATIONS:
            converged = False
            warn_unconverged(driver.source, iterations, steps)
            break
    info["seconds"]["spline solve" + (" (Gauss-Newton)" if warped and keys else "")] = \
        _time.perf_counter() - t1
    if warped and keys:
        info.update(iterations=iterations, converged=converged)
    a = particular_cubic(lam, delta, forcing(z))  # (m, r, 4)
    values = z.reshape(blocks, 2, r)[:, 0]
    velocities = z.reshape(blocks, 2, r)[:, 1]
    if loop:
        values, velocities = np.vstack([values, values[:1]]), np.vstack([velocities,
                                                                         velocities[:1]])
    kfs = list(own)
    info["solve_seconds"] = _time.perf_counter() - t0
    return SecondaryMotion(body, nodes, values.copy(), velocities.copy(), kfs, basis,
                           warped=warped, info=info, loop=loop, rig=rig, psi=psi,
                           free_eigenvalues=lam, particular=a, held_warp=held_warp,
                           driver_rig=linear_rig,
                           driven_frames=(times[:len(frames)], frames, v, driver))
