"""A solved motion: wiggly splines in every mode (Theorem 1), and its playback.

The unknowns of the spacetime solve are the node values q_i(t_k) and node velocities
q_i'(t_k) of every mode; on each interval between nodes each mode is the wiggly spline with
that Hermite data (:mod:`wiggly.splines`).  Linear playback is u(t) = Phi q(t); warped
playback is W(u(t)) (and DW(u(t)) u'(t) for velocities) (Schulz et al. 2014, Theorem 2).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from wiggly import checks, limits
from wiggly.body import Body, Where
from wiggly.errors import WigglyInputError, counted
from wiggly.keyframes import Keyframe
from wiggly.linalg import one_blas_thread
from wiggly.splines import WigglyBasis, energy_form, evaluate

if TYPE_CHECKING:
    from wiggly.solve.levels import WarmStart

__all__ = ["DEFAULT_FPS", "FOLD_TIMES", "Animation", "rotation_angles"]

# Frames per second of sampled motions unless asked otherwise.
DEFAULT_FPS = 30.0
# Animation.folds checks at most this many frames, and as many keyframe times, by default.
FOLD_TIMES = 150


@dataclass(eq=False)
class Animation:
    """A solved motion: wiggly splines in every mode, with nodes at the keyframe times.

    Attributes
    ----------
    body : Body
    nodes : (m+1,) node times t_0 < ... < t_m in seconds.
    values, velocities : numpy.ndarray
        q_i(t_k) and q_i'(t_k) of every mode at every node, shape (m+1, r).
    keyframes : the (validated) keyframes that produced it.
    info : how it was solved (unknowns, timings; for warped motions the iterations,
        ``converged``, the final Newton decrement and ``distance_bound``, see
        :func:`wiggly.solve.optimizer.minimize`).
    """

    body: Body
    nodes: np.ndarray
    values: np.ndarray
    velocities: np.ndarray
    keyframes: list[Keyframe]
    basis: WigglyBasis = field(repr=False)
    warped: bool = False
    info: dict = field(default_factory=dict)
    #: what a later warped solve of an edited problem can start from (None for linear
    #: motions): pass it as ``warm_start=`` to :meth:`SpacetimeProblem.solve`
    warm_start: WarmStart | None = field(default=None, repr=False)
    #: a periodic motion: its end is its start (positions and velocities), and it plays as
    #: a cycle with no seam
    loop: bool = False

    def __repr__(self) -> str:  # a summary: the splines and keyframes are attributes
        how = "warped" if self.warped else "linear"
        if self.warped and "iterations" in self.info:
            done = "converged" if self.info.get("converged") else "not converged"
            how += f", {done} in {self.info['iterations']} iterations"
        loop = ", looped" if self.loop else ""
        return (f"Animation({how}, [{self.nodes[0]:g}, {self.nodes[-1]:g}] s, "
                f"{counted(len(self.keyframes), 'keyframe')}, {self.body.r} modes{loop})")

    @property
    def start(self) -> float:
        return float(self.nodes[0])

    @property
    def end(self) -> float:
        return float(self.nodes[-1])

    @property
    def duration(self) -> float:
        return self.end - self.start

    def frame_times(self, fps: float = DEFAULT_FPS) -> np.ndarray:
        """Frame times start, start + 1/fps, ... up to and including the end (if on the grid);
        ``fps`` in (0, :data:`wiggly.limits.MAX_FPS`], at most :data:`wiggly.limits.MAX_FRAMES`
        frames."""
        fps = checks.positive_number(fps, "fps", "frames per second")
        if fps > limits.MAX_FPS:
            raise WigglyInputError(f"fps = {fps:g} is more than {limits.MAX_FPS:g} frames per "
                                   "second (wiggly.limits.MAX_FPS)")
        n = limits.frame_count(self.duration, fps)
        if n > limits.MAX_FRAMES:
            raise WigglyInputError(
                f"{self.duration:g} s at {fps:g} fps is {n} frames, more than "
                f"{limits.MAX_FRAMES} (wiggly.limits.MAX_FRAMES): lower fps")
        # an end within a hair of the grid (0.96666666 s at 30 fps) ends on the end itself,
        # not 7e-9 s past it
        return np.minimum(self.start + np.arange(n) / fps, self.end)

    # --- modal trajectories ------------------------------------------------------------
    def modal(self, times: ArrayLike, n_derivatives: int = 0, side: str = "right") -> np.ndarray:
        """q(t) and its time derivatives for all modes: shape (n_derivatives + 1, F, r),
        up to the 4th (the order of the wiggly splines' equation, Theorem 1).

        At a node the spline of the interval to the ``side`` of it is used (the one-sided
        limits differ in derivatives of order 2 or 3, Theorem 1).
        """
        if side not in ("left", "right"):
            raise WigglyInputError(f"side should be 'left' or 'right'; got {side!r}")
        _order(n_derivatives, "n_derivatives", 4)
        t = np.atleast_1d(np.asarray(times, dtype=float))
        tol = 1e-9 * max(1.0, self.duration)
        if t.ndim != 1 or t.size == 0:
            raise WigglyInputError(f"times should be a non-empty list of times (s); got shape "
                                   f"{np.shape(times)}")
        bad = int(np.sum(~np.isfinite(t)))
        if bad:
            raise WigglyInputError(f"times must lie in the animation's range [{self.start}, "
                                   f"{self.end}] s; got {bad} that are not finite numbers")
        if np.any(t < self.start - tol) or np.any(t > self.end + tol):
            raise WigglyInputError(
                f"times must lie in the animation's range [{self.start}, {self.end}] s; got "
                f"[{t.min()}, {t.max()}]"
            )
        t = np.clip(t, self.start, self.end)
        m, r = len(self.nodes) - 1, self.body.r
        k = np.clip(np.searchsorted(self.nodes, t, side=side) - 1, 0, m - 1)
        h = np.diff(self.nodes)[k]
        tau = (t - self.nodes[k]) / h
        idx = (k[:, None] * r + np.arange(r)).ravel()  # (F*r,)
        data = np.stack(
            [self.values[k], self.velocities[k], self.values[k + 1], self.velocities[k + 1]],
            axis=-1,
        ).reshape(-1, 4)
        g = np.tile(self.body.modal_gravity, len(t))
        out = evaluate(self.basis.take(idx), data, g, np.repeat(tau, r), n_derivatives)
        return out.reshape(n_derivatives + 1, len(t), r)

    def linear_field(self, times: ArrayLike, derivative: int = 0) -> np.ndarray:
        """The linear motion ``Phi q(t)`` (or a time derivative) on the tet mesh, (F, n, 3):
        what the warp turns into the played-back motion (Schulz et al. 2014, Theorem 2)."""
        q = self.modal(times, derivative)[derivative]
        return (q @ self.body.basis("tets").T).reshape(len(q), -1, 3)

    # --- vertex trajectories -------------------------------------------------------------
    def displacements(
        self, times: ArrayLike, on: Where = "surface", derivative: int = 0, dtype: type = np.float64
    ) -> np.ndarray:
        """Displacements (or their ``derivative``-th time derivative): shape (F, n, 3).

        Linear: u(t) = Phi q(t).  Warped: W(u(t)) and DW(u(t)) u'(t) (Schulz et al. 2014,
        Theorem 2), computed on the tet mesh in batches of frames (one multi-RHS Poisson solve per
        batch) and carried to the surface by the barycentric embedding.
        """
        checks.where(on)
        _order(derivative, "derivative", 3)
        if not np.issubdtype(np.dtype(dtype), np.floating):
            raise WigglyInputError(f"dtype should be a floating type (np.float64 or np.float32); "
                                   f"got {np.dtype(dtype).name}, which would truncate metres")
        if not self.warped:
            q = self.modal(times, derivative)[derivative]
            B = self.body.basis(on)
            out = q.astype(dtype, copy=False) @ B.T.astype(dtype, copy=False)
            return out.reshape(len(q), -1, 3)
        if derivative > 1:
            raise WigglyInputError(
                "accelerations are available for linear motion (warp=False) only; for the "
                "warped motion sample positions densely and differentiate numerically"
            )
        return self._warped(times, on, derivative, dtype)

    @one_blas_thread  # the warp's compiled passes need the cores (linear playback does not)
    def _warped(self, times: ArrayLike, on: Where, derivative: int, dtype: type) -> np.ndarray:
        """W(u(t)) or DW(u(t)) u'(t) on ``on``, in batches of frames."""
        q = self.modal(times, derivative)
        body = self.body
        n = body.tets.n_vertices
        Phi = body.modes.vectors
        F = q.shape[1]
        out = np.empty((F, body.n_vertices(on), 3), dtype=dtype)
        for f0 in range(0, F, _PLAYBACK_BATCH):
            sl = slice(f0, min(F, f0 + _PLAYBACK_BATCH))
            U = (q[0, sl] @ Phi.T).reshape(-1, n, 3)
            if derivative == 0:
                W = body.warp.apply(U)
            else:
                dU = (q[1, sl] @ Phi.T).reshape(-1, n, 3)
                W = np.stack([body.warp.jvp(u, du) for u, du in zip(U, dU, strict=True)])
            out[sl] = body.to_surface(W) if on == "surface" else W
        return out

    def positions(
        self, times: ArrayLike, on: Where = "surface", dtype: type = np.float64
    ) -> np.ndarray:
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
        """E of eq. (4): the integrated squared extra force (M^-1 norm), summed over modes."""
        x = _interval_data(self.values, self.velocities)
        form = energy_form(self.basis, np.tile(self.body.modal_gravity, len(self.nodes) - 1))
        return float(form(x).sum())

    def folds(
        self, times: ArrayLike | None = None, displacements: np.ndarray | None = None
    ) -> list[dict]:
        """Where the motion folds the body: per time, the tets that the played-back motion
        turns inside out (det of the deformation gradient <= 0).

        Default times: the frames at :data:`DEFAULT_FPS` and the keyframes' times (at most
        :data:`FOLD_TIMES` of each, evenly chosen: a driver keys every frame).  Each dict
        has ``time``, ``folded`` (tets), ``share`` (of all tets), and where there are any,
        ``tets`` (their indices), ``centre`` (their rest-pose mass centre, m) and ``turns``:
        the largest rotation the linear motion gives them (the length of the rotation vector
        that the warp exponentiates, in turns).  Rotation-strain warping turns each tet by its own
        rotation, so a linear motion that spins a small region by several turns against its
        surroundings is warped into a crease there.

        ``displacements``: this motion's tet-mesh displacements at ``times``
        (``displacements(times, on="tets")``), when the caller has played them back already
        (the editor shows the same frames).
        """
        if times is None:  # frames at DEFAULT_FPS, at most FOLD_TIMES of them (a long shot
            # has more frames than any output may: they are not all made)
            keys = np.unique([kf.time for kf in self.keyframes])
            count = limits.frame_count(self.duration, DEFAULT_FPS)
            picks = np.unique(np.linspace(0, count - 1, min(count, FOLD_TIMES)).round())
            times = np.unique(np.concatenate([self.start + picks / DEFAULT_FPS, _evenly(keys)]))
        times = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if times.size == 0:  # no times asked
            return []
        body = self.body
        if displacements is not None and displacements.shape != (
            len(times), body.tets.n_vertices, 3
        ):
            raise WigglyInputError(
                f"displacements of shape {displacements.shape} are not this motion's tet-mesh "
                f"displacements at {len(times)} times: give displacements(times, on='tets'), "
                f"shape ({len(times)}, {body.tets.n_vertices}, 3)")
        warp = body.fine_level.warp
        T, X = body.tets.tets, body.tets.vertices
        out = []
        for a in range(0, len(times), _PLAYBACK_BATCH):
            part = times[a : a + _PLAYBACK_BATCH]
            moved = (self.displacements(part, on="tets") if displacements is None
                     else displacements[a : a + _PLAYBACK_BATCH])
            for t, folded in zip(part, warp.inverted(moved), strict=True):
                row = {"time": float(t), "folded": int(folded.sum()),
                       "share": float(folded.mean())}
                if folded.any():
                    row["tets"] = np.flatnonzero(folded)
                    u = self.linear_field([t])[0]
                    v = warp.volumes[folded]
                    row["centre"] = (X[T[folded]].mean(axis=1) * v[:, None]).sum(0) / v.sum()
                    row["turns"] = float(rotation_angles(warp.gradient, u)[folded].max()
                                         / (2 * np.pi))
                out.append(row)
        return out

    def constraint_residuals(self) -> list[dict]:
        """Per keyframe: RMS and max distance (m) to the position targets, RMS velocity error.

        The motion is sampled at the keyframes' times in batches of frames (one warp solve
        per batch, not per keyframe: a driver keys a group at every frame)."""
        kfs = self.keyframes
        out: list[dict] = [
            {"time": kf.time, "name": kf.name, "n_vertices": len(kf.vertices)} for kf in kfs
        ]
        for kind, sample in (("position", self.positions), ("velocity", self.velocities_at)):
            for on in sorted({kf.on for kf in kfs}):
                which = [j for j, kf in enumerate(kfs)
                         if getattr(kf, kind) is not None and kf.on == on]
                for a in range(0, len(which), _PLAYBACK_BATCH):
                    part = which[a : a + _PLAYBACK_BATCH]
                    X = sample([kfs[j].time for j in part], on)
                    for x, j in zip(X, part, strict=True):
                        kf = kfs[j]
                        d = np.linalg.norm(x[kf.vertices] - getattr(kf, kind), axis=1)
                        rms = float(np.sqrt(np.mean(d**2)))
                        if kind == "position":
                            out[j].update(position_rms=rms, position_max=float(d.max()))
                        else:
                            out[j].update(velocity_rms=rms)
        return out


def rotation_angles(gradient, U: np.ndarray) -> np.ndarray:
    """Per tet, the length (rad) of the rotation vector of the linear displacement U (n, 3):
    the axial vector of the skew part of its gradient, which the warp exponentiates.
    ``gradient``: the warp's scalar P1 gradient operator (3 m, n)."""
    A = (gradient @ U).reshape(-1, 3, 3)
    skew = 0.5 * (A - A.transpose(0, 2, 1))
    return np.sqrt(0.5 * (skew**2).sum(axis=(1, 2)))


def _evenly(times: np.ndarray) -> np.ndarray:
    """At most :data:`FOLD_TIMES` of the sorted ``times``, evenly chosen (the ends kept)."""
    if len(times) <= FOLD_TIMES:
        return times
    return times[np.linspace(0, len(times) - 1, FOLD_TIMES).round().astype(int)]


def _interval_data(values: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """Hermite data (q_k, q_k', q_k+1, q_k+1') per (interval, mode): shape (m*r, 4)."""
    return np.stack([values[:-1], velocities[:-1], values[1:], velocities[1:]], axis=-1).reshape(
        -1, 4
    )


_PLAYBACK_BATCH = 64


def _order(k, name: str, highest: int) -> None:
    """Refuse a derivative order that is not an integer in [0, highest]."""
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 0 <= k <= highest:
        raise WigglyInputError(f"{name} should be an integer in [0, {highest}]; got {k!r}")
