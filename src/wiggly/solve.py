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
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from wiggly.body import Body, Where
from wiggly.errors import WigglyInputError
from wiggly.keyframes import Keyframe
from wiggly.linalg import blas_single_thread, factorize_spd
from wiggly.progress import iterations
from wiggly.splines import WigglyBasis, energy_form, equilibrium, evaluate, wiggly_basis
from wiggly.warp import CoarseWarp


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
    warped: bool = False
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
    def modal(self, times: ArrayLike, n_derivatives: int = 0, side: str = "right") -> np.ndarray:
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
        data = np.stack(
            [self.values[k], self.velocities[k], self.values[k + 1], self.velocities[k + 1]],
            axis=-1,
        ).reshape(-1, 4)
        g = np.tile(self.body.modal_gravity, len(t))
        out = evaluate(self.basis.take(idx), data, g, np.repeat(tau, r), n_derivatives)
        return out.reshape(n_derivatives + 1, len(t), r)

    # --- vertex trajectories -------------------------------------------------------------
    def displacements(
        self, times: ArrayLike, on: Where = "surface", derivative: int = 0, dtype: type = np.float64
    ) -> np.ndarray:
        """Displacements (or their ``derivative``-th time derivative): shape (F, n, 3).

        Linear: u(t) = Phi q(t).  Warped: W(u(t)) and DW(u(t)) u'(t) (SYSTEM.md §6), computed
        on the tet mesh in batches of frames (one multi-RHS Poisson solve per batch) and
        carried to the surface by the barycentric embedding.
        """
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
            if on == "surface":
                E = body.surface_embedding
                W = (E @ W.transpose(1, 0, 2).reshape(n, -1)).reshape(E.shape[0], -1, 3)
                W = W.transpose(1, 0, 2)
            out[sl] = W
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
    return np.stack([values[:-1], velocities[:-1], values[1:], velocities[1:]], axis=-1).reshape(
        -1, 4
    )


_PLAYBACK_BATCH = 64


class SpacetimeProblem:
    """Assembles and solves the banded SPD system of E + E_C for one body and node set.

    The per-interval energy forms depend only on the node times, so they are reused when
    keyframe targets or weights change (interactive editing).
    """

    def __init__(self, body: Body, start: float, end: float, preroll: float | None = None) -> None:
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
        self._assembled: dict[tuple, tuple] = {}
        # per vertex group (selections, Grams): properties of the body, shared by its problems
        self._group_cache: dict[tuple, tuple] = body._cache.setdefault("group_basis", {})
        self._jacobians: dict[float, tuple] = {}
        self._exact_jacobians: dict[float, tuple] = {}
        self._blocks: dict[float, tuple] = {}  # Gauss-Newton blocks per node (normal_matrix)
        self._coarse_gap: float | None = None  # fine objective gap at the coarse solution
        self._fine_last: _FinePoint | None = None  # the last solve's fine point (warm starts)
        self._coarse_grams: dict[tuple, object] = body._cache.setdefault("coarse_grams", {})
        self._selections: dict[tuple, object] = body._cache.setdefault("selections", {})
        self._projection_cache: dict[tuple, np.ndarray] = {}
        self._preroll_form: tuple | None = None
        self._targets: dict[tuple, list] = {}  # per keyframe: offsets d, S^T d (_target)
        self._generation = 0  # solves so far: _target compares a keyframe's arrays once per solve
        self._stacks: dict[tuple, tuple] = {}  # stacked targets of a batch (_stacked)
        self._batch_terms: dict[tuple, tuple] = {}  # a batch's F and S^T r per W values
        self._fits: dict[tuple, tuple] = {}  # least-squares fits of a batch's targets (_fit)

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
        def compute() -> tuple:
            body = self.body
            r, m = body.r, len(nodes) - 1
            h = np.repeat(np.diff(nodes), r)
            lam = np.tile(body.eigenvalues, m)
            basis = wiggly_basis(lam, np.tile(body.delta, m), h)
            form = energy_form(basis, np.tile(body.modal_gravity, m))
            # global indices of (q_k,i, v_k,i, q_k+1,i, v_k+1,i)
            k = np.repeat(np.arange(m), r)
            i = np.tile(np.arange(r), m)
            idx = np.stack(
                [2 * r * k + i, 2 * r * k + r + i, 2 * r * (k + 1) + i, 2 * r * (k + 1) + r + i],
                axis=1,
            )
            return basis, form, idx

        return _cached(self._energy_cache, tuple(np.round(nodes, 12)), compute, limit=8)

    def _group_basis(self, vertices: np.ndarray, on: str) -> tuple:
        """(S_1, S_1^T, Gram Phi^T A_k^T A_k Phi, rest positions (s, 3)) of a vertex group,
        cached by group.  A_k = S_1 kron I_3 with S_1 the scalar selection (the barycentric
        embedding rows for surface vertices); the Gram is sum_c Phi_c^T (S_1^T S_1) Phi_c
        over the coordinates c, without forming A_k Phi."""

        def compute() -> tuple:
            S, St = self._selection(vertices, on)
            Phi = self.body.modes.vectors.reshape(-1, 3, self.body.r)
            StS = St @ S
            gram = sum(Phi[:, c].T @ (StS @ Phi[:, c]) for c in range(3))
            return S, St, gram, self.body.rest_positions(on)[vertices]

        return _cached(self._group_cache, (on, len(vertices), hash(vertices.tobytes())), compute)

    def _selection(self, vertices: np.ndarray, on: str, coarse: bool = False) -> tuple:
        """A group's scalar selection S_1 (k, n) from tet-mesh vertex values and its transpose
        (both CSR), or S_1 P (k, n_c) from the coarse mesh's (P the lift of
        :class:`wiggly.warp.CoarseWarp`), cached by group."""

        def compute() -> tuple:
            S = self.body.scalar_selection(vertices, on)
            if coarse:
                S = sp.csr_matrix(S @ self.body.coarse_warp.lift)
            return S, sp.csr_matrix(S.T)

        key = (on, len(vertices), hash(vertices.tobytes()), coarse and id(self.body.coarse_warp))
        return _cached(self._selections, key, compute)

    def _coarse_gram(self, vertices: np.ndarray, on: str):
        """(S_1 P)^T (S_1 P): scalar selection S_1 of a group composed with the coarse mesh's
        lift P (:class:`wiggly.warp.CoarseWarp`), cached by group."""

        def compute():
            SP, SPt = self._selection(vertices, on, coarse=True)
            return sp.csr_matrix(SPt @ SP)

        key = (on, len(vertices), hash(vertices.tobytes()), id(self.body.coarse_warp))
        return _cached(self._coarse_grams, key, compute)

    def _target(self, kf: Keyframe, what: str, St=None) -> np.ndarray:
        """A keyframe's position target minus rest ``"d"`` (s, 3), or ``"Stb"`` = S^T b for
        the selection transpose ``St`` (coarse level), kept while the keyframe's targets are
        equal (an edit changes one keyframe; the others are not recomputed).  The contents are
        compared once per solve."""
        target = kf.velocity if what == "Stb" else kf.position  # the one array it depends on
        arrays = (target, kf.vertices)
        key = (what == "Stb", id(target), kf.on, len(kf.vertices))
        kept = self._targets.get(key)
        if kept is not None and kept[2] != self._generation:
            if all(
                (a is None and b is None)
                or (a is not None and b is not None and np.array_equal(a, b))
                for a, b in zip(kept[0], arrays, strict=True)
            ):
                kept[2] = self._generation
            else:
                kept = None
        if kept is None:
            if len(self._targets) > 256:
                self._targets.clear()
            copies = tuple(None if a is None else np.array(a) for a in arrays)
            kept = self._targets[key] = [copies, {}, self._generation]
        values = kept[1]
        name = (what, id(St))
        if name not in values:
            if what == "d":
                rest = self.body.rest_positions(kf.on)[kf.vertices]
                value = kf.position - rest
            else:
                value = St @ kf.velocity
            value.flags.writeable = False
            values[name] = (St, value)
        return values[name][1]

    def _stacked(self, ds: list[np.ndarray], w: np.ndarray) -> np.ndarray:
        """Targets ``ds`` of keyframes sharing a selection, stacked (s, p, 3) and times their
        weights ``w`` (p,); kept while they are the same (read-only) arrays of :meth:`_target`
        and the same weights."""

        def compute() -> tuple:
            D = np.stack(ds, axis=1)
            D *= w[:, None]
            D.flags.writeable = False
            return tuple(ds), D  # the entry holds ds: their ids stay unique while it lives

        key = (*(id(d) for d in ds), w.tobytes())
        return _cached(self._stacks, key, compute)[1]

    def _fit(self, S, St, wD: np.ndarray) -> tuple:
        """The least-squares fit of a batch's weighted targets ``wD`` (s, p, 3) by vertex
        values: the Gram ``C = S^T S``, ``X*`` (n, p, 3) solving ``(C + mu I) X* = S^T wD``
        (mu = 1e-8 mean diag C: C is singular off the selected vertices), ``G* = C X* -
        S^T wD`` (~mu X*) and ``F* = 1/2 |S X* - wD|^2``.  Kept per selection and targets.

        For every x,  1/2 |S x - d|^2 = F* + (x - X*).G* + 1/2 (x - X*)^T C (x - X*),  exactly;
        the first and last terms are >= 0 and the middle one is tiny, so unlike the plain Gram
        form (x^T C x - 2 x^T S^T d + |d|^2) nothing cancels."""

        def gram() -> tuple:
            C = sp.csr_matrix(St @ S)
            mu = 1e-8 * max(float(C.diagonal().mean()), np.finfo(float).tiny)
            return S, C, factorize_spd(C + mu * sp.identity(C.shape[0], format="csr"))

        _, C, solve_C = _cached(self._fits, ("gram", id(S)), gram)

        def fit() -> tuple:
            s, p, _ = wD.shape
            Std = St @ wD.reshape(s, 3 * p)
            X = solve_C(Std)
            G = C @ X - Std
            R = S @ X - wD.reshape(s, 3 * p)
            n = C.shape[0]
            return wD, C, X.reshape(n, p, 3), G.reshape(n, p, 3), 0.5 * float(np.vdot(R, R))

        return _cached(self._fits, ("fit", id(S), id(wD)), fit)[1:]

    def _preroll(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Least energy to reach (q, q') from rest in ``preroll`` seconds, without gravity:
        1/2 (q - q_eq, q')^T Q22 (q - q_eq, q') per mode; returns Q22 and its linear term."""
        if self._preroll_form is not None:
            return self._preroll_form
        body, r = self.body, self.body.r
        basis = wiggly_basis(body.eigenvalues, body.delta, self.preroll)
        Q22 = energy_form(basis, np.zeros(r)).Q[:, 2:, 2:]
        q_eq = equilibrium(body.eigenvalues, body.modal_gravity)
        lin = -Q22[:, :, 0] * q_eq[:, None]  # -Q22 (q_eq, 0)
        const = 0.5 * float(np.sum(Q22[:, 0, 0] * q_eq**2))
        self._preroll_form = (Q22, np.r_[lin[:, 0], lin[:, 1]], const)
        return self._preroll_form

    def _assemble_energy(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Band storage of E (+ pre-roll): 1/2 z^T H z + f^T z + c (read-only, cached by node
        times; the band in Fortran order, which BLAS dsbmv reads in place)."""
        return _cached(
            self._assembled,
            tuple(np.round(nodes, 12)),
            lambda: self._assembled_energy(nodes),
            limit=8,
        )

    def _assembled_energy(self, nodes: np.ndarray) -> tuple:
        _basis, form, idx = self._energy(nodes)
        r = self.body.r
        N = 2 * r * len(nodes)
        bw = 4 * r - 1  # upper bandwidth of the node-major ordering
        ab = np.zeros((bw + 1, N), order="F")
        f = np.zeros(N)
        _add_dense(ab, bw, idx, form.Q)
        np.add.at(f, idx.ravel(), form.l.ravel())
        c = float(form.c0.sum())
        if self.preroll > 0:  # rest before t_0 (see module doc): 2x2 form per mode
            Q22, f0, c_pre = self._preroll()
            i = np.arange(r)
            _add_dense(ab, bw, np.stack([i, r + i], axis=1), Q22)
            f[: 2 * r] += f0
            c += c_pre
        for a in (ab, f):
            a.flags.writeable = False
        return ab, f, c

    def _add_linear_constraints(
        self, ab: np.ndarray, f: np.ndarray, kfs: list[Keyframe], nodes: np.ndarray
    ) -> None:
        """E_C of eq. (4): c_A |A_k Phi q_k - a_k|^2 + c_B |B_k Phi q'_k - b_k|^2 at node k."""
        body, r = self.body, self.body.r
        bw = ab.shape[0] - 1
        for kf in kfs:
            k = _node_index(nodes, kf.time)
            c_A, c_B = kf.weights(body, self.duration)
            _S, St, AtA, rest = self._group_basis(kf.vertices, kf.on)
            if kf.position is not None and c_A > 0:
                blk = 2 * r * k + np.arange(r)
                _add_block(ab, bw, blk, c_A * AtA)
                f[blk] -= c_A * self._projected(St, kf.vertices, kf.on, kf.position, rest)
            if kf.velocity is not None and c_B > 0:
                blk = 2 * r * k + r + np.arange(r)
                _add_block(ab, bw, blk, c_B * AtA)
                f[blk] -= c_B * self._projected(St, kf.vertices, kf.on, kf.velocity, None)

    def _projected(
        self, St, vertices: np.ndarray, on: str, target: np.ndarray, rest: np.ndarray | None
    ) -> np.ndarray:
        """A^T (target - rest) = Phi^T (S_1^T (target - rest)), cached by group and target
        (unchanged keyframes are free)."""
        t = np.ascontiguousarray(target)
        key = (on, len(vertices), hash(vertices.tobytes()), rest is None, hash(t.tobytes()))
        return _cached(
            self._projection_cache,
            key,
            lambda: self.body.modes.vectors.T @ (St @ (t if rest is None else t - rest)).ravel(),
            limit=256,
        )

    def solve(
        self,
        keyframes: list[Keyframe],
        *,
        warped: bool = False,
        initial: Animation | None = None,
        tolerance: float = 1e-8,
        max_iterations: int = 50,
        stall: bool = True,
        progress: bool = False,
    ) -> Animation:
        """Minimise E + E_C (linear, Theorem 1) or E + E_WC (warped, Theorem 2).

        Both have the same unknowns, node values and velocities of every mode.  The warped
        problem is solved by Levenberg-Marquardt (Gauss-Newton with damping), started from
        ``initial`` (a previous solution with the same nodes) or from the linear solution with
        unwarped targets; see :func:`_gauss_newton`.  ``progress`` shows a bar of iterations.
        """
        with blas_single_thread():
            return self._solve(
                keyframes, warped, initial, tolerance, max_iterations, stall, progress
            )

    def _solve(
        self, keyframes, warped, initial, tolerance, max_iterations, stall, progress=False
    ) -> Animation:
        t_start = _time.perf_counter()
        self._generation += 1
        body = self.body
        kfs = [
            kf.checked(body, self.start, self.end, label=_label(kf, j))
            for j, kf in enumerate(keyframes)
        ]
        nodes = self.nodes_for(kfs)
        basis = self._energy(nodes)[0]
        r, n_nodes = body.r, len(nodes)
        ab_E, f_E, c_E = self._assemble_energy(nodes)
        info: dict = {"unknowns": 2 * r * n_nodes, "warped": warped}
        if (
            warped
            and initial is not None
            and initial.nodes.shape == nodes.shape
            and np.allclose(initial.nodes, nodes)
        ):
            z = np.stack([initial.values, initial.velocities], axis=1).ravel()
            info["warm_start"] = True
        else:
            ab, f = ab_E.copy(), f_E.copy()
            start_keys = [_unwarped(kf, body) for kf in kfs] if warped else kfs
            self._add_linear_constraints(ab, f, start_keys, nodes)
            try:
                z = _solve_banded(ab, -f)
            except np.linalg.LinAlgError as err:
                raise WigglyInputError(
                    "the keyframes leave the motion undetermined and preroll is 0; give "
                    "keyframes that fix the start (positions and velocities of the whole "
                    "body) or a preroll > 0"
                ) from err
            info["warm_start"] = False
        info["linear_seconds"] = _time.perf_counter() - t_start
        if warped:
            with iterations("warped solve (Gauss-Newton)", max_iterations, progress) as bar:
                obj = WarpedObjective(self, kfs, nodes, ab_E, f_E, c_E)
                # W, DW v and the pulled-back cotangents of the last fine point: a warm start
                # from it evaluates the edited objective there almost for free
                prior = self._fine_last
                if (
                    info["warm_start"]
                    and prior is not None
                    and prior.layout == obj.layout
                    and np.array_equal(prior.nodes, nodes)
                ):
                    obj._last = prior.last
                continuation = info["warm_start"] and _same_keyframes(initial.keyframes, kfs)
                coarse = None
                if not body.coarse_warp.exact and TWO_LEVEL and not continuation:
                    z, coarse = self._coarse_level(
                        obj, kfs, nodes, z, info, max_iterations, stall, bar
                    )
                z = _gauss_newton(obj, z, tolerance, max_iterations, info, stall, bar)
                if "coarse" in info and not (
                    info["coarse"].get("kept_initial") or info["coarse"].get("corrected")
                ):
                    self._coarse_gap = info["objective_start"] - info["objective"]
                self._fine_last = _FinePoint(
                    obj.layout, nodes.copy(), obj._last, kfs, *obj.last_gradient, coarse
                )
        z = z.reshape(n_nodes, 2, r)
        anim = Animation(
            body, nodes, z[:, 0].copy(), z[:, 1].copy(), kfs, basis, warped=warped, info=info
        )
        info["solve_seconds"] = _time.perf_counter() - t_start
        return anim

    def _coarse_level(
        self, obj: WarpedObjective, kfs, nodes, z, info, max_iterations, stall, bar
    ) -> tuple[np.ndarray, WarpedObjective]:
        """The first level of the warped solve: minimise the objective with the coarse warp
        W~ in place of W from ``z``; its solution is the fine level's start (the unknowns
        are the same).  Returns the start and the coarse objective.

        From a warm start at the last fine point the coarse objective gets the linear
        correction tau^T z, tau = grad F(z0) - grad F~(z0) (full approximation scheme,
        Brandt 1977): its gradient then equals the fine one at z0, so the coarse warp's error
        enters the start only through its change over the edit, not at full size."""
        ab_E, f_E, c_E = obj.ab_E, obj.f_E, obj.c_E
        coarse = WarpedObjective(self, kfs, nodes, ab_E, f_E, c_E, coarse=True)
        info["coarse"] = {}
        prior = self._fine_last
        corrected = (
            FAS and obj._last is not None and np.array_equal(obj._last[0], z) and prior is not None
        )
        if corrected:  # full approximation scheme from the last fine point z0
            old = prior.coarse
            if old is None:
                old = WarpedObjective(self, prior.keyframes, nodes, ab_E, f_E, c_E, coarse=True)
            old.f_E, old.c_E = old.base
            F_c, g_c = old.value_and_gradient(z)
            tau = prior.gradient - g_c  # fine minus coarse gradient at z0, with z0's keys
            if old.layout == coarse.layout:
                coarse._last = old._last  # W~ at z: the same for the edited keyframes
            coarse.f_E = f_E + tau
            coarse.c_E = c_E + (prior.objective - F_c) - float(tau @ z)
            info["coarse"]["corrected"] = True
            # the correction is a first-order model of the coarse warp's error; it fails when
            # the error changes fast over the edit (strong velocity keyframes weigh D^2W,
            # which the coarse mesh renders less well): then the plain coarse solve follows
            F_0 = obj.value(z)  # W at z is kept: no evaluation
            z_c = _gauss_newton(
                coarse, z, COARSE_TOLERANCE, FAS_ITERATIONS, info["coarse"], stall, bar, warn=False
            )
            if info["coarse"]["converged"] and obj.value(z_c) < F_0:
                return z_c, coarse
            coarse.f_E, coarse.c_E = coarse.base
            info["coarse"] = {"correction_failed": True}
        z_c = _gauss_newton(
            coarse, z, COARSE_TOLERANCE, max_iterations, info["coarse"], stall, bar, warn=False
        )
        if not info["warm_start"]:
            return z_c, coarse
        # a warm start may already be closer to the fine solution than the coarse one is
        # (the coarse warp's own error, measured by earlier solves as the fine level's
        # decrease from the coarse solution): keep the better start
        coarse_gain = info["coarse"]["objective_start"] - info["coarse"]["objective"]
        if self._coarse_gap is not None:
            better = coarse_gain > 2 * self._coarse_gap
        else:
            better = obj.value(z_c) < obj.value(z)
        if better:
            return z_c, coarse
        info["coarse"]["kept_initial"] = True
        return z, coarse


def _cached(cache: dict, key, compute, limit: int = 64):
    """``cache[key]``, computed by ``compute()`` on a miss; the cache is emptied when it holds
    more than ``limit`` entries (bounded memory for long editing sessions)."""
    if key not in cache:
        if len(cache) > limit:
            cache.clear()
        cache[key] = compute()
    return cache[key]


def _same_keyframes(a: list[Keyframe], b: list[Keyframe]) -> bool:
    """Whether two keyframe lists pose the same problem (a warm start that continues a solve
    needs no coarse first level)."""

    def same(x, y) -> bool:
        return (x is None and y is None) or (
            x is not None and y is not None and np.array_equal(x, y)
        )

    return len(a) == len(b) and all(
        p.time == q.time
        and p.on == q.on
        and (p.stiffness, p.c_A, p.c_B) == (q.stiffness, q.c_A, q.c_B)
        and same(p.vertices, q.vertices)
        and same(p.position, q.position)
        and same(p.velocity, q.velocity)
        for p, q in zip(a, b, strict=True)
    )


def _unwarped(kf: Keyframe, body: Body) -> Keyframe:
    """A keyframe whose targets a *linear* motion can meet and whose warp is near the original.

    The targets' best-fit rotation R about their centroid (Kabsch) is replaced by its
    linearization with the same rotation vector w = log R (any angle below pi): x = R (X - c)
    + c' + e becomes X + w x (X - c) + (c' - c) + R^T e; velocities are rotated back by R^T.
    Warping maps a linearized rotation to the exact one (SYSTEM.md §6), so the linear solve
    with these targets is the Gauss-Newton start for large-rotation keyframes.
    """
    if kf.position is None or len(kf.vertices) < 3:
        return kf
    X = body.rest_positions(kf.on)[kf.vertices]
    c, c_t = X.mean(axis=0), kf.position.mean(axis=0)
    A, B = X - c, kf.position - c_t
    spread = np.linalg.eigvalsh(A.T @ A)  # squared singular values of A, ascending
    if spread[1] <= 1e-18 * max(spread[2], 1e-300):  # collinear: no unique rotation
        return kf
    U, _, Vt = np.linalg.svd(B.T @ A)  # Kabsch: R = argmax tr(R^T B^T A), det R = 1
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ D @ Vt
    w = Rotation.from_matrix(R).as_rotvec()
    e = B - A @ R.T
    position = X + np.cross(w, A) + (c_t - c) + e @ R
    velocity = None if kf.velocity is None else kf.velocity @ R
    return replace(kf, position=position, velocity=velocity)


def _node_index(nodes: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(nodes - t)))


def _solve_banded(ab: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve H z = rhs for SPD H in upper band storage: equilibrated banded Cholesky with
    iterative refinement (keyframe weights make H ill-conditioned)."""
    return _factor_banded(ab)(rhs)


def _factor_banded(ab: np.ndarray):
    """Factor SPD H (upper band storage) once; returns ``solve(rhs)`` for (N,) or (N, k)
    right-hand sides (equilibrated banded Cholesky, two steps of iterative refinement)."""
    bw = ab.shape[0] - 1
    d = ab[bw]
    s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    abs_ = np.multiply(ab, _band_scale(s, bw), order="F")  # BLAS dsbmv reads it in place
    cb = sla.cholesky_banded(abs_, lower=False, check_finite=False)

    def solve(rhs: np.ndarray) -> np.ndarray:
        if rhs.ndim == 2:
            return np.stack([solve(col) for col in rhs.T], axis=1)
        b = rhs * s
        z = sla.cho_solve_banded((cb, False), b, check_finite=False)
        for _ in range(2):
            r = b - _band_matvec(abs_, bw, z)
            z += sla.cho_solve_banded((cb, False), r, check_finite=False)
        return s * z

    return solve


@dataclass
class _FinePoint:
    """What a warped solve keeps of its last fine point z0 for the next (warm) solve."""

    layout: tuple  # the objective's active and velocity nodes
    nodes: np.ndarray
    last: tuple  # WarpedObjective._last at z0: W values and pulled-back cotangents
    keyframes: list
    objective: float  # F(z0) and its gradient, with these keyframes
    gradient: np.ndarray
    coarse: WarpedObjective | None  # the coarse objective of the same solve


@dataclass
class _WarpedKey:
    """One keyframe's warped least-squares terms at its node (E_WC, SYSTEM.md §6)."""

    node: int
    S: object  # (s, n) sparse scalar selection of the level's vertex values (CSR)
    St: object  # its transpose (CSR)
    C: object  # (n_c, n_c) sparse Gram (S_1 P)^T (S_1 P) of the scalar selection, coarse mesh
    d: np.ndarray | None  # position target minus rest, (s, 3)
    b: np.ndarray | None  # velocity target (s, 3)
    wA: float  # sqrt(c_A)
    wB: float  # sqrt(c_B)
    # coarse level: velocity residual norms from the Gram, |S v - b|^2 = v.Cv - 2 v.S^T b + |b|^2
    gram: bool = False
    Stb: np.ndarray | None = None


class WarpedObjective:
    """F(z) = 1/2 z^T H z + f^T z + c + 1/2 sum_k |r_k(z)|^2, the objective E + E_WC.

    Residuals r_k = sqrt(c_A) (A_k W(Phi q_k) - a_k) and sqrt(c_B) (B_k DW(Phi q_k) Phi q'_k
    - b_k) (SYSTEM.md §6) involve only the node of keyframe k, so their Gauss-Newton blocks
    J^T J land on the diagonal blocks of the banded H.  W and DW are evaluated only at
    constrained nodes, all nodes in one batch.  The gradient is exact (vector-Jacobian
    products of W); the Gauss-Newton blocks use the body's :class:`wiggly.warp.CoarseWarp`.
    With ``coarse=True`` the coarse warp W~ stands in for W everywhere (its Gauss-Newton
    blocks are then exact): the first, cheap level of the warped solve.
    """

    def __init__(
        self,
        problem: SpacetimeProblem,
        kfs: list[Keyframe],
        nodes: np.ndarray,
        ab_E: np.ndarray,
        f_E: np.ndarray,
        c_E: float,
        coarse: bool = False,
    ) -> None:
        body = problem.body
        self.body, self.r = body, body.r
        self.coarse = body.coarse_warp
        if coarse:  # everything on the coarse mesh: W~(Phi q) = P W_c(R Phi q)
            self.warp, basis = self.coarse.warp_c, self.coarse.basis_c
        else:
            self.warp, basis = body.warp, body.modes.vectors
        self.n = self.warp.n_vertices
        self.Phi = basis.reshape(3 * self.n, self.r)
        self.ab_E, self.f_E, self.c_E = ab_E, f_E, c_E
        self.base = (f_E, c_E)  # the linear and constant terms before any FAS correction
        self.problem, self.kfs = problem, kfs
        self.bw = ab_E.shape[0] - 1
        self.keys = []
        for kf in kfs:
            c_A, c_B = kf.weights(body, problem.duration)
            self.keys.append(
                _WarpedKey(
                    _node_index(nodes, kf.time),
                    *problem._selection(kf.vertices, kf.on, coarse),
                    problem._coarse_gram(kf.vertices, kf.on),
                    None if kf.position is None or c_A == 0 else problem._target(kf, "d"),
                    None if kf.velocity is None or c_B == 0 else kf.velocity,
                    np.sqrt(c_A),
                    np.sqrt(c_B),
                )
            )
            if coarse:  # the cancellation in the Gram form costs ~eps |b|^2 / |r|^2: fine here
                key = self.keys[-1]
                key.gram = True
                key.Stb = None if key.b is None else problem._target(kf, "Stb", key.St)
        self.active = sorted({k.node for k in self.keys if k.d is not None or k.b is not None})
        self.slot = {k: a for a, k in enumerate(self.active)}
        # position keyframes sharing a selection are evaluated together (one sparse product)
        batches: dict[int, list[_WarpedKey]] = {}
        for key in self.keys:
            if key.d is not None:
                batches.setdefault(id(key.S), []).append(key)
        self._batches = []
        for keys in batches.values():
            w = np.array([key.wA for key in keys])
            # weighted targets sqrt(c_A) d (s, p, 3)
            self._batches.append((keys, problem._stacked([key.d for key in keys], w), w))
        self.vel = sorted({k.node for k in self.keys if k.b is not None})
        self.timing = {"W": 0.0, "vjp": 0.0, "jacobians": 0.0, "solve": 0.0}
        self.counts = {"W": 0, "vjp": 0, "jacobians": 0}
        # Jacobians depend on the node state only: shared across solves of the same problem
        # (warm starts reuse them), keyed by node time
        self._jac = problem._jacobians
        self._exact_jac = problem._exact_jacobians
        self._blocks = problem._blocks
        self._signature = self._signatures()
        self._node_time = {k: float(np.round(t, 9)) for k, t in enumerate(nodes)}
        self.level = "coarse" if coarse else "fine"
        self._last: tuple | None = None
        self.last_gradient: tuple | None = None  # (F, g) where _gauss_newton stopped
        self._normal: tuple | None = None  # (Jacobians used, band matrix) of the last call

    @property
    def layout(self) -> tuple:
        """The active and velocity nodes, which fix the layout of :attr:`_last`."""
        return tuple(self.active), tuple(self.vel)

    def use_exact_jacobians(self) -> bool:
        """Switch the Gauss-Newton matrix to the fine warp's exact Jacobians (the fallback
        when the coarse mesh's ones converge slowly); False if they are already in use."""
        if self.coarse.exact or self.level == "coarse":
            return False
        body = self.body
        if "exact_jacobians" not in body._cache:
            body._cache["exact_jacobians"] = CoarseWarp.exact(body.warp, body.modes.vectors)
        self.coarse = body._cache["exact_jacobians"]
        for key in self.keys:
            key.C = sp.csr_matrix(key.St @ key.S)
        self._jac = self._exact_jac
        self._signature = self._signatures()
        self._normal = None
        return True

    def _signatures(self) -> dict[int, list]:
        """Per active node, what its Gauss-Newton block depends on besides the Jacobians:
        each keyframe's Gram C and weights."""
        sig: dict[int, list] = {k: [] for k in self.active}
        for key in self.keys:
            if key.d is not None or key.b is not None:
                wA = key.wA if key.d is not None else None
                sig[key.node].append((key.C, wA, key.wB if key.b is not None else None))
        return sig

    def _state(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Z = z.reshape(-1, 2, self.r)
        return Z[:, 0], Z[:, 1]

    def _evaluate(self, z: np.ndarray, gradient: bool):
        """F(z) and, with ``gradient``, its exact gradient.

        W and DW v at the last point are kept, and so are the vector-Jacobian products of its
        last gradient: at the same point with other keyframe targets or weights (a warm start
        of an edited problem), only the cotangents that changed are pulled back (DW^T is
        linear in them)."""
        q, v = self._state(z)
        n, r, Phi = self.n, self.r, self.Phi
        t0 = _time.perf_counter()
        iv = [self.slot[k] for k in self.vel]
        if self._last is not None and np.array_equal(self._last[0], z):
            U, WU, dU, Vel = self._last[1]  # W and DW v at the last point (value, then gradient)
        else:
            U = (q[self.active] @ Phi.T).reshape(len(self.active), n, 3)
            dU = (v[self.vel] @ Phi.T).reshape(len(self.vel), n, 3)
            if self.vel:  # one Poisson solve for both
                WU, Vel = self.warp.apply_and_jvp(U, iv, dU)
            else:
                WU, Vel = self.warp.apply(U) if len(self.active) else U, dU
            self.counts["W"] += len(self.active) + len(self.vel)
            self._last = (z.copy(), (U, WU, dU, Vel), None)
        t1 = _time.perf_counter()
        self.timing["W"] += t1 - t0
        Hz = _band_matvec(self.ab_E, self.bw, z)
        F = 0.5 * z @ Hz + self.f_E @ z + self.c_E
        YA = np.zeros_like(U)
        YB = np.zeros_like(dU)
        for keys, D, w in self._batches:
            F += self._position_terms(keys, D, w, WU, YA if gradient else None)
        for key in self.keys:
            if key.gram:
                if key.b is not None:
                    F += self._gram_velocity_terms(key, Vel, YB if gradient else None)
                continue
            if key.b is not None:
                rB = key.wB * (key.S @ Vel[self.vel.index(key.node)] - key.b)
                F += 0.5 * float(np.vdot(rB, rB))
                if gradient:
                    YB[self.vel.index(key.node)] += key.wB * (key.St @ rB)
        if not gradient:
            return float(F)
        g = Hz + self.f_E
        G = g.reshape(-1, 2, r)
        # one batch of vjps: positions at every node; for velocity keyframes B DW(u) w also
        # the derivative in u, Hess(y.W)(u) w, by a central difference of vjps
        h = (
            1e-6
            * (1.0 + np.abs(U[iv]).max(axis=(1, 2)))
            / np.maximum(np.abs(dU).max(axis=(1, 2)), 1e-300)
        )
        step = h[:, None, None] * dU
        Ub = np.concatenate([U, U[iv], U[iv] + step, U[iv] - step])
        f, nv = len(self.active), len(self.vel)
        index = np.r_[np.arange(f), np.tile(f + np.arange(nv), 3)]
        Y = np.concatenate([YA, YB])
        if self._last[2] is None:  # pull back every cotangent
            frames, dY, out = np.arange(len(Ub)), Y, np.zeros((len(Ub), r))
        else:  # the same point: pull back the change of the cotangents only
            dY = Y - self._last[2][0]
            changed = np.flatnonzero(np.any(dY != 0.0, axis=(1, 2)))
            frames = np.flatnonzero(np.isin(index, changed))
            out = self._last[2][1].copy()
        if len(frames):
            cotangents, sub = np.unique(index[frames], return_inverse=True)
            pulled = self.warp.vjp(Ub[frames], dY[cotangents], sub)
            out[frames] += pulled.reshape(len(frames), 3 * n) @ Phi
            self.counts["vjp"] += len(frames)
        self._last = (self._last[0], self._last[1], (Y, out))
        G[self.active, 0] += out[:f]
        if nv:
            G[self.vel, 1] += out[f : f + nv]
            G[self.vel, 0] += (out[f + nv : f + 2 * nv] - out[f + 2 * nv :]) / (2 * h[:, None])
        self.timing["vjp"] += _time.perf_counter() - t1
        return float(F), g

    def _position_terms(self, keys, wD: np.ndarray, w: np.ndarray, WU: np.ndarray, YA) -> float:
        """1/2 sum |r|^2 of position keyframes sharing one selection S, r = sqrt(c_A) (S W(u)
        - d) = S (sqrt(c_A) W(u)) - sqrt(c_A) d with weights w = sqrt(c_A) (p,) and weighted
        targets wD (s, p, 3), from the Gram about the targets' least-squares fit (see
        :meth:`SpacetimeProblem._fit`: vertex-sized products only, nothing cancels); adds
        sqrt(c_A) S^T r to the cotangents ``YA`` unless it is None."""
        slots = [self.slot[key.node] for key in keys]

        # kept per (W values, targets): an edited objective at the last point (a warm start)
        # recomputes the batches whose targets changed only
        def compute() -> tuple:
            # S^T r always: a value at a new point is followed by its gradient (line search)
            C, Xs, Gs, Fs = self.problem._fit(keys[0].S, keys[0].St, wD)
            p, n = len(keys), WU.shape[1]
            E = WU.transpose(1, 0, 2)[:, slots] * w[:, None]  # sqrt(c_A) W(u) (n, p, 3) ...
            E -= Xs  # ... minus the fit: 1/2 |r|^2 = F* + E.G* + 1/2 E^T C E (see _fit)
            CE = (C @ E.reshape(n, 3 * p)).reshape(n, p, 3)
            F = Fs + float(np.vdot(E, Gs)) + 0.5 * float(np.vdot(E, CE))
            CE += Gs  # S^T r = C E + G*
            CE *= w[:, None]
            return WU, wD, F, CE  # the entry holds WU and wD: their ids stay unique while it lives

        tag = (id(WU), id(wD), tuple(slots), w.tobytes())
        kept = _cached(self.problem._batch_terms, tag, compute, limit=8)
        if YA is not None:
            for j, a in enumerate(slots):
                YA[a] += kept[3][:, j]
        return kept[2]

    def _gram_velocity_terms(self, key: _WarpedKey, Vel, YB) -> float:
        """1/2 c_B |S v - b|^2 of a velocity keyframe from its Gram (coarse level); adds
        c_B (Cv - S^T b) to the cotangents ``YB`` unless it is None."""
        j = self.vel.index(key.node)
        Cv = key.C @ Vel[j]
        F = (
            0.5
            * key.wB**2
            * (np.vdot(Vel[j], Cv) - 2 * np.vdot(Vel[j], key.Stb) + np.vdot(key.b, key.b))
        )
        if YB is not None:
            YB[j] += key.wB**2 * (Cv - key.Stb)
        return float(F)

    def value(self, z: np.ndarray) -> float:
        """F(z)."""
        return self._evaluate(z, False)

    def value_and_gradient(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """F(z) and its exact gradient."""
        return self._evaluate(z, True)

    def normal_matrix(self, z: np.ndarray, reuse: float = 0.0) -> np.ndarray:
        """Band storage of H + sum J^T J (Gauss-Newton), J from :class:`wiggly.warp.CoarseWarp`.

        A node's Jacobian is reused while its state moved by less than ``reuse`` (relative),
        which changes the convergence rate, never the stationary point (the gradient is
        always exact)."""
        q, v = self._state(z)
        r, cj = self.r, self.coarse
        t0 = _time.perf_counter()
        # a node's change is compared with the largest node state, so nodes near rest (u ~ 0,
        # where DW ~ identity) do not count tiny absolute changes as large relative ones
        floor = 0.05 * max((np.linalg.norm(np.r_[q[k], v[k]]) for k in self.active), default=0)
        stale = []
        for k in self.active:
            xk = np.r_[q[k], v[k]]
            cached = self._jac.get(self._node_time[k])
            scale = max(float(np.linalg.norm(xk)), floor)
            limit = min(reuse, 1e-3) if k in self.vel else reuse  # q-v coupling: keep fresh
            if (
                cached is None
                or np.linalg.norm(xk - cached[0]) > limit * scale
                or (k in self.vel and cached[2] is None)
            ):
                stale.append(k)
        if stale:  # all fresh Jacobians in one batch
            Js = cj.jacobians(q[stale])
            sv = [i for i, k in enumerate(stale) if k in self.vel]
            VJs = (
                cj.second_derivatives(q[[stale[i] for i in sv]], v[[stale[i] for i in sv]])
                if sv
                else []
            )
            for i, k in enumerate(stale):
                VJ = VJs[sv.index(i)] if i in sv else None
                self._jac[self._node_time[k]] = (np.r_[q[k], v[k]], Js[i], VJ)
            self.counts["jacobians"] += len(stale)
        used = [self._jac[self._node_time[k]] for k in self.active]
        if self._normal is not None and all(
            a is b for a, b in zip(self._normal[0], used, strict=True)
        ):
            self.timing["jacobians"] += _time.perf_counter() - t0
            return self._normal[1]  # the same Jacobians as last time: the same matrix
        # a node's block depends on its Jacobians and its keyframes' Grams and weights only:
        # kept per problem (the coarse and fine levels of a solve, and later solves, share it)
        blocks, todo = {}, []
        for k, entry in zip(self.active, used, strict=True):
            kept = self._blocks.get(self._node_time[k])
            sig = self._signature[k]
            if (
                kept is not None
                and kept[0] is entry
                and len(kept[1]) == len(sig)
                and all(a[0] is b[0] and a[1:] == b[1:] for a, b in zip(kept[1], sig, strict=True))
            ):
                blocks[k] = kept[2]
            else:
                blocks[k] = np.zeros((2 * r, 2 * r))
                todo.append(k)
        J = {k: self._jac[self._node_time[k]][1] for k in todo}
        # position terms c_A J^T (C kron I_3) J, batched over the keyframes of each group
        groups: dict[int, tuple] = {}
        for key in self.keys:
            if key.d is not None and key.node in J:
                groups.setdefault(id(key.C), (key.C, []))[1].append(key)
        for C, keys in groups.values():
            grams = _grams(C, np.stack([J[key.node] for key in keys]))
            for key, g in zip(keys, grams, strict=True):
                blocks[key.node][:r, :r] += key.wA**2 * g
        for key in self.keys:  # velocity terms: [D^2W, DW] against (q, q')
            if key.b is not None and key.node in J:
                VJ = self._jac[self._node_time[key.node]][2]
                X = np.concatenate([VJ, J[key.node]], axis=2)
                blocks[key.node] += key.wB**2 * _grams(key.C, X[None])[0]
        for k in todo:
            t = self._node_time[k]
            self._blocks[t] = (self._jac[t], self._signature[k], blocks[k])
        ab = np.array(self.ab_E, order="F")  # Fortran order: BLAS dsbmv reads it in place
        if self.active:  # every active node's block at once
            nodes = np.array(self.active)
            idx = 2 * r * nodes[:, None] + np.arange(2 * r)
            _add_dense(ab, self.bw, idx, np.stack([blocks[k] for k in self.active]))
        self._normal = (used, ab)
        self.timing["jacobians"] += _time.perf_counter() - t0
        return ab


def _grams(C, X: np.ndarray) -> np.ndarray:
    """X_p^T (C kron I_3) X_p for p stacked fields X (p, n_c, 3, r), scalar (n_c, n_c) C."""
    p, n_c, _, r = X.shape
    CX = (C @ X.transpose(1, 0, 2, 3).reshape(n_c, -1)).reshape(n_c, p, 3 * r)
    Xf = X.reshape(p, 3 * n_c, r)
    return Xf.transpose(0, 2, 1) @ CX.transpose(1, 0, 2).reshape(p, 3 * n_c, r)


def _gauss_newton(
    obj: WarpedObjective,
    z: np.ndarray,
    tolerance: float,
    max_iterations: int,
    info: dict,
    stall: bool = True,
    bar=None,
    warn: bool = True,
) -> np.ndarray:
    """Minimise E + E_WC (Theorem 2) by Levenberg-Marquardt from ``z``.

    Each iteration solves (H + mu diag H) dz = -g with the Gauss-Newton matrix H (banded)
    and the exact gradient g; the step is accepted when F decreases, and mu follows the
    ratio of actual to predicted decrease (Nielsen's update).  Stopping rule:

    * converged ("decrement") when the Newton decrement m = -1/2 g^T H^-1 g is below
      ``tolerance * F``; then every directional derivative is bounded,
      |g^T d| <= sqrt(2 m d^T H d) (Cauchy-Schwarz in the H-norm);
    * converged ("stalled", unless ``stall=False``) when the relative decrease of F stayed
      below ``STALL_DECREASE`` for three iterations while the model promises less than
      ``STALL_PROMISE`` relative decrease (flat valleys where Gauss-Newton crawls);
    * otherwise, after ``max_iterations``, a :class:`WarpedSolveWarning` reports it.

    The returned iterate is the one where the stopping rule was checked.
    """
    bw = obj.bw
    F, g = obj.value_and_gradient(z)
    F_start, mu, nu, history, converged, it = F, 0.0, 2.0, [F], False, 0
    decrement, reason, slow = np.inf, "", 0
    pairs: list[tuple[np.ndarray, np.ndarray]] = []
    decrements: list[float] = []
    last: tuple | None = None  # the last Gauss-Newton matrix and its factorization
    while it < max_iterations:
        crawling = len(decrements) >= 3 and all(
            b > SLOW_RATIO * a for a, b in zip(decrements[-3:-1], decrements[-2:], strict=True)
        )
        if crawling and obj.use_exact_jacobians():
            info["exact_jacobians_from"] = it
            last = None
        ab = obj.normal_matrix(z, reuse=JACOBIAN_REUSE)
        t0 = _time.perf_counter()
        # the same Jacobians give the same matrix object: its factorization is kept
        solve_H = last[1] if last is not None and last[0] is ab else _factor_banded(ab)
        last = (ab, solve_H)
        dz = solve_H(-g)
        if pairs:
            dz = _secant_step(ab, solve_H, dz, pairs)
        decrement = -0.5 * float(g @ dz)
        decrements.append(decrement)
        if len(history) > 1:
            slow = slow + 1 if history[-2] - history[-1] < STALL_DECREASE * F else 0
        stalled = stall and slow >= 3 and decrement <= STALL_PROMISE * F
        obj.timing["solve"] += _time.perf_counter() - t0
        if decrement <= tolerance * F or stalled:
            converged, reason = True, "stalled" if decrement > tolerance * F else "decrement"
            break
        it += 1
        while True:
            t0 = _time.perf_counter()
            if mu > 0:
                ab_mu = ab.copy()
                ab_mu[bw] *= 1.0 + mu
                try:
                    dz = _factor_banded(ab_mu)(-g)
                except np.linalg.LinAlgError:
                    mu = max(mu * nu, 1e-4)
                    nu *= 2
                    continue
            predicted = -(float(g @ dz) + 0.5 * float(dz @ _band_matvec(ab, bw, dz)))
            obj.timing["solve"] += _time.perf_counter() - t0
            F_new, g_new = obj.value_and_gradient(z + dz)
            rho = (F - F_new) / predicted if predicted > 0 else -1.0
            if rho > 1e-4:
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                if mu < 1e-7:
                    mu = 0.0
                nu = 2.0
                break
            mu = max(mu * nu, 1e-4)
            nu *= 2
            if mu > 1e10:
                break
        if rho <= 1e-4:
            break
        if SECANT and float(dz @ (g_new - g)) > 0:
            pairs = [*pairs, (dz, g_new - g)][-SECANT:]
        z, F, g = z + dz, F_new, g_new
        history.append(F)
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"objective {F:.6g}")
    obj.last_gradient = (F, g)
    info.update(
        iterations=it,
        converged=converged,
        stop=reason,
        objective_start=F_start,
        objective=F,
        objective_history=history,
        newton_decrement=decrement,
        seconds_W=obj.timing["W"],
        seconds_vjp=obj.timing["vjp"],
        seconds_jacobians=obj.timing["jacobians"],
        seconds_solve=obj.timing["solve"],
        evaluations=dict(obj.counts),
    )
    if not converged and warn:
        warnings.warn(
            f"warped solve did not converge in {it} iterations: objective {F:.6g} (start "
            f"{F_start:.6g}), Newton decrement {decrement:.2e} > tolerance * objective = "
            f"{tolerance * F:.2e}; the result is the best iterate",
            WarpedSolveWarning,
            stacklevel=3,
        )
    return z


# Steps kept for the quasi-Newton (BFGS) correction of the Gauss-Newton matrix; 0: none.
SECANT = 1
# Correct the coarse level of a warm start by the full approximation scheme; False: plain.
FAS = True
# Iterations allowed to the corrected coarse level of a warm start before it is dropped.
FAS_ITERATIONS = 10
# Solve with the coarse warp first (bodies with a coarse mesh); False: fine level only.
TWO_LEVEL = True
# The fine level switches from the coarse mesh's Jacobians to exact ones when the Newton
# decrement fell by less than this factor twice in a row (slow, linear convergence: strong
# velocity keyframes); it usually falls by 100 or more per iteration.
SLOW_RATIO = 0.25


def _secant_step(ab: np.ndarray, solve_H, dz: np.ndarray, pairs: list) -> np.ndarray:
    """-B^-1 g for the BFGS updates B of the Gauss-Newton matrix H (banded) by the last steps
    s_i and gradient changes y_i, in compact form (Byrd, Nocedal & Schnabel 1994):

        B = H - [H S, Y] K^-1 [H S, Y]^T,   K = [[S^T H S, L], [L^T, -D]],

    L the strictly lower part of S^T Y and D its diagonal; solved with Woodbury, one banded
    solve per pair (``solve_H``: the factored H).  ``dz = -H^-1 g``.  B s_i = y_i for the
    last pair, and B is SPD when every s_i^T y_i > 0.  The correction captures curvature the
    Gauss-Newton matrix lacks (a coarse mesh's Jacobians, residual curvature), along the
    steps taken.
    """
    S = np.stack([s for s, _ in pairs], axis=1)
    Y = np.stack([y for _, y in pairs], axis=1)
    bw = ab.shape[0] - 1
    HS = np.stack([_band_matvec(ab, bw, s) for s, _ in pairs], axis=1)
    SY = S.T @ Y
    L = np.tril(SY, -1)
    K = np.block([[S.T @ HS, L], [L.T, -np.diag(np.diag(SY))]])
    U = np.concatenate([HS, Y], axis=1)
    HinvU = np.concatenate([S, solve_H(Y)], axis=1)
    # B = H - U K^-1 U^T  =>  B^-1 x = H^-1 x + H^-1 U (K - U^T H^-1 U)^-1 U^T H^-1 x
    return dz + HinvU @ np.linalg.solve(K - U.T @ HinvU, U.T @ dz)


JACOBIAN_REUSE = 0.02
# Tolerance of the coarse first level: its solution is only a start for the fine level.
COARSE_TOLERANCE = 1e-6
STALL_DECREASE = 1e-6
STALL_PROMISE = 1e-2


class WarpedSolveWarning(UserWarning):
    """The nonlinear (warped) solve stopped before meeting its tolerance."""


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
    """y = H x for symmetric H in upper band storage ab[bw + i - j, j] = H[i, j] (BLAS
    dsbmv, whose upper band storage is this one)."""
    return sla.blas.dsbmv(bw, 1.0, ab, x)


def _add_dense(ab: np.ndarray, bw: int, idx: np.ndarray, blocks: np.ndarray) -> None:
    """Scatter symmetric dense blocks (P, b, b) at global indices idx (P, b) into upper band."""
    rows = np.broadcast_to(idx[:, :, None], blocks.shape)
    cols = np.broadcast_to(idx[:, None, :], blocks.shape)
    upper = rows <= cols
    np.add.at(ab, (bw + rows[upper] - cols[upper], cols[upper]), blocks[upper])


def _add_block(ab: np.ndarray, bw: int, idx: np.ndarray, block: np.ndarray) -> None:
    """Add one symmetric block at distinct global indices idx (no repeated entries, so a
    plain fancy-indexed += is exact)."""
    rows, cols = np.triu_indices(len(idx))
    ab[bw + idx[rows] - idx[cols], idx[cols]] += block[rows, cols]


def solve(
    body: Body,
    keyframes: list[Keyframe],
    *,
    duration: float | None = None,
    start: float = 0.0,
    end: float | None = None,
    warp: bool = True,
    preroll: float | None = None,
    progress: bool = False,
) -> Animation:
    """Animate ``body`` through the sparse ``keyframes``.

    ``warp=True`` (default) solves E + E_WC on the rotation-strain-warped motion (Theorem 2)
    and plays back W(u(t)); ``warp=False`` is the linear solve of Theorem 1.  The time range
    is [start, end] (``end = start + duration``; default: the last keyframe time, at least
    start + 1 s).
    """
    if end is None:
        if duration is None:
            last = max((kf.time for kf in keyframes), default=start)
            duration = max(float(last) - start, 1.0)
        end = start + float(duration)
    problem = SpacetimeProblem(body, start, end, preroll)
    anim = problem.solve(keyframes, warped=warp, progress=progress)
    if progress:
        extra = ""
        if warp:
            extra = (
                f", {anim.info['iterations']} Gauss-Newton iterations"
                f"{'' if anim.info['converged'] else ' (not converged)'}"
            )
        print(
            f"[wiggly] {'warped' if warp else 'linear'} solve: {anim.info['unknowns']} "
            f"unknowns in {anim.info['solve_seconds'] * 1e3:.1f} ms{extra}",
            file=sys.stderr,
        )
    return anim
