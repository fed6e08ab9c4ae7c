"""The sparse spacetime problem of one body over one time range.

Schulz et al. 2014, eqs. (4)-(6) and Theorem 1.

By Theorem 1 the minimiser of E + E_C is, in every mode, a wiggly spline with nodes at the
keyframe times (and at the start and end).  The unknowns are the node values q_i(t_k) and
node velocities q_i'(t_k) of every mode, z = (z_0, ..., z_m), z_k = (q_k, q'_k).  The energy
E is a sum of exact per-interval quadratic forms (:func:`wiggly.splines.energy_form`), banded
in time; E_C couples the modes at a node.  The linear minimiser solves one banded SPD system
H z = -f (:class:`wiggly.solve.banded.BandedCholesky`).

Pre-roll (our regularization).  E vanishes on every free motion, so with sparse keyframes
E + E_C is only semi-definite.  We assume the body rests (at static equilibrium) until
``preroll`` seconds before t_0 and add the least spacetime energy (same functional, same
wiggly splines, no gravity) that brings each mode from rest to its state at t_0.  It is
positive definite, so the system has a unique solution, and negligible when the keyframes fix
the start.  ``preroll=None`` uses the shot's duration; ``preroll=0`` disables it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from wiggly import limits
from wiggly.body import Body, GroupSelection
from wiggly.errors import WigglyInputError
from wiggly.keyframes import Keyframe
from wiggly.linalg import blas_single_thread
from wiggly.memo import Memo, value_key
from wiggly.progress import deprecated_progress
from wiggly.solve.animation import Animation
from wiggly.solve.banded import BandedCholesky, add_block, add_blocks
from wiggly.solve.levels import WarmStart, solve_warped
from wiggly.solve.nodes import NodeLayout, merge_tolerance, node_index, node_times
from wiggly.solve.optimizer import SolveOptions
from wiggly.splines import WigglyBasis, energy_form, equilibrium, wiggly_basis
from wiggly.warp import WarpLevel

__all__ = ["Energy", "SpacetimeProblem", "TargetFit"]


@dataclass(frozen=True)
class Energy:
    """E (+ pre-roll) over a node set: 1/2 z^T H z + f^T z + c, H in upper band storage."""

    nodes: np.ndarray
    basis: WigglyBasis
    ab: np.ndarray  # read-only, Fortran order (BLAS dsbmv reads it in place)
    f: np.ndarray
    c: float

    @property
    def bandwidth(self) -> int:
        return self.ab.shape[0] - 1


@dataclass(frozen=True)
class TargetFit:
    """The least-squares fit of a group's targets d (s, 3) by level vertex values, which
    turns the residual ``1/2 |S x - d|^2`` into vertex-sized terms (exactly, for every x):

        1/2 |S x - d|^2 = F* + (x - X*) . G* + 1/2 (x - X*)^T C (x - X*),

    with ``X* = (C + mu I)^-1 S^T d`` (mu = 1e-8 mean diag C: C is singular off the group),
    ``G* = C X* - S^T d`` (~ mu X*) and ``F* = 1/2 |S X* - d|^2``; its gradient is
    ``S^T (S x - d) = C (x - X*) + G*``.  The first and last terms are nonnegative and the
    middle one tiny, so nothing cancels (unlike ``x^T C x - 2 x^T S^T d + |d|^2``), and a
    group of many surface vertices costs products of the level's size only."""

    C: sp.csr_matrix
    X: np.ndarray
    G: np.ndarray
    F: float

    def value_and_cotangent(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """``1/2 |S x - d|^2`` and ``S^T (S x - d)`` for level vertex values x (n_L, 3)."""
        e = x - self.X
        Ce = self.C @ e
        return self.F + float(np.vdot(e, self.G)) + 0.5 * float(np.vdot(e, Ce)), Ce + self.G


#: Node intervals shorter than this share of the duration are named when the linear system
#: cannot be factorized; keyframe weights above HEAVIEST (stiffness units) likewise.
SHORTEST = 1e-4
HEAVIEST = 1e14

#: Why a loop's keyframes that hold nowhere are refused (velocity keys alone included).
UNDETERMINED_LOOP = (
    "the keyframes leave the looped motion undetermined: a loop has no rest before it, and "
    "velocity keys do not say where the body is, so position keyframes must hold its "
    "position (e.g. a group at rest, a driven group, or a fixed group)")


class SpacetimeProblem:
    """E + E_C (Theorem 1) and E + E_WC (Theorem 2) of ``body`` over [start, end].

    The problem owns a :class:`~wiggly.memo.Memo` of what an edit leaves unchanged: the
    energy of a node set, the fits and projections of keyframe targets.  Its keys are values
    (node times, vertex indices, targets), so the same problem serves every edit of a shot.
    What depends on the body and a vertex group only (selections, Grams, modal Grams, the
    coarse model's error terms) the body keeps, for every problem on it.
    """

    def __init__(
        self,
        body: Body,
        start: float,
        end: float,
        preroll: float | None = None,
        loop: bool = False,
    ) -> None:
        if not isinstance(body, Body):
            raise WigglyInputError(f"body should be a wiggly.Body (wiggly.prepare(mesh path)); "
                                   f"got a {type(body).__name__}")
        if not (np.isfinite(start) and np.isfinite(end)) or end <= start:
            raise WigglyInputError(
                f"the animation's time range [{start}, {end}] s is empty: end must be after start"
            )
        if end - start > limits.MAX_DURATION:
            raise WigglyInputError(
                f"the animation's time range [{start:g}, {end:g}] s lasts {end - start:g} s: "
                f"shots may last at most {limits.MAX_DURATION:g} s (wiggly.limits.MAX_DURATION)")
        if loop and preroll not in (None, 0, 0.0):
            raise WigglyInputError(
                f"preroll = {preroll!r} s does not apply to a looped shot: a loop has no "
                "before; leave preroll out (or 0)"
            )
        preroll = (0.0 if loop else end - start) if preroll is None else float(preroll)
        if not np.isfinite(preroll) or preroll < 0:
            raise WigglyInputError(f"preroll = {preroll!r} s must be a number >= 0")
        self.body = body
        self.start, self.end = float(start), float(end)
        self.preroll = preroll
        self.loop = bool(loop)
        self.memo = Memo(limit=512)

    @property
    def duration(self) -> float:
        return self.end - self.start

    # ------------------------------------------------------------------ keyframes
    def checked(self, keyframes: list[Keyframe]) -> list[Keyframe]:
        """Validated, normalized copies of ``keyframes`` (times clamped into the range)."""
        keyframe_list(keyframes)
        out = []
        for j, kf in enumerate(keyframes):
            label = f"keyframe #{j}" + (f" ('{kf.name}')" if kf.name else "") + f" at t={kf.time}"
            out.append(kf.checked(self.body, self.start, self.end, label=label))
        return out

    def nodes_for(self, keyframes: list[Keyframe]) -> np.ndarray:
        """Node times: start, end and every keyframe time (:func:`node_times`)."""
        return node_times(self.start, self.end, [kf.time for kf in keyframes])

    def layout(self, nodes: np.ndarray) -> NodeLayout:
        """Where each node's unknowns sit in z (:class:`NodeLayout`; periodic for a loop)."""
        return NodeLayout(nodes, self.body.r, self.loop)

    # --------------------------------------------------------------------- energy
    def energy(self, nodes: np.ndarray) -> Energy:
        """E (+ pre-roll) over ``nodes``, kept per node set."""
        nodes = np.asarray(nodes, dtype=np.float64)
        return self.memo.get(("energy", value_key(nodes)), lambda: self._energy(nodes))

    def _energy(self, nodes: np.ndarray) -> Energy:
        body = self.body
        r, m = body.r, len(nodes) - 1
        h = np.repeat(np.diff(nodes), r)
        basis = wiggly_basis(np.tile(body.eigenvalues, m), np.tile(body.delta, m), h)
        form = energy_form(basis, np.tile(body.modal_gravity, m))
        # global indices of (q_k,i, v_k,i, q_k+1,i, v_k+1,i); a loop's last node is its first
        layout = self.layout(nodes)
        k, i = np.repeat(np.arange(m), r), np.tile(np.arange(r), m)
        b0, b1 = 2 * r * layout.block[k], 2 * r * layout.block[k + 1]
        idx = np.stack([b0 + i, b0 + r + i, b1 + i, b1 + r + i], axis=1)
        N, bw = layout.size, layout.bandwidth
        ab = np.zeros((bw + 1, N), order="F")
        f = np.zeros(N)
        add_blocks(ab, idx, form.Q)
        np.add.at(f, idx.ravel(), form.l.ravel())
        c = float(form.c0.sum())
        if self.preroll > 0:  # rest before t_0 (module doc): a 2x2 form per mode
            pre = wiggly_basis(body.eigenvalues, body.delta, self.preroll)
            Q22 = energy_form(pre, np.zeros(r)).Q[:, 2:, 2:]
            q_eq = equilibrium(body.eigenvalues, body.modal_gravity)
            add_blocks(ab, np.stack([np.arange(r), r + np.arange(r)], axis=1), Q22)
            f[:r] -= Q22[:, 0, 0] * q_eq
            f[r : 2 * r] -= Q22[:, 1, 0] * q_eq
            c += 0.5 * float(np.sum(Q22[:, 0, 0] * q_eq**2))
        for a in (ab, f):
            a.flags.writeable = False
        return Energy(nodes.copy(), basis, ab, f, c)

    # --------------------------------------------------------------------- groups
    def selection(self, level: WarpLevel, vertices: np.ndarray, on: str) -> GroupSelection:
        """A vertex group's selection and Gram on ``level`` (kept by the body)."""
        return self.body.group(level, vertices, on)

    def fits(
        self, level: WarpLevel, requests: list[tuple[np.ndarray, str, np.ndarray]]
    ) -> list[TargetFit]:
        """The :class:`TargetFit` on ``level`` of each (vertices, on, targets (s, 3)) request,
        kept per level, group and target; the missing ones of a group are fitted together
        (one multi-right-hand-side solve: a driver keys one group at every frame)."""
        name = "fine" if level.exact else "coarse"
        keys = [
            ("fit", name, on, value_key(v), value_key(np.asarray(d, dtype=float)))
            for v, on, d in requests
        ]
        made: dict = {}
        groups: dict[tuple, list[int]] = {}
        for j, key in enumerate(keys):
            if key not in self.memo and key not in made:
                groups.setdefault(key[2:4], []).append(j)
                made[key] = None
        for members in groups.values():
            vertices, on, _ = requests[members[0]]
            sel = self.selection(level, vertices, on)
            s = len(vertices)
            D = np.stack([np.broadcast_to(requests[j][2], (s, 3)) for j in members], axis=1)
            Std = sel.St @ D.reshape(s, -1)  # columns (member, coordinate)
            X = sel.fit_solver(Std)
            R = sel.S @ X - D.reshape(s, -1)
            G = sel.C @ X - Std
            R = R.reshape(s, len(members), 3)
            F = 0.5 * np.einsum("skc,skc->k", R, R)
            n = X.shape[0]
            for a, j in enumerate(members):
                Xa = np.array(X.reshape(n, -1, 3)[:, a])
                Ga = np.array(G.reshape(n, -1, 3)[:, a])
                for arr in (Xa, Ga):
                    arr.flags.writeable = False
                made[keys[j]] = TargetFit(sel.C, Xa, Ga, float(F[a]))
        return [self.memo.get(key, lambda key=key: made[key]) for key in keys]

    def projected(self, vertices: np.ndarray, on: str, target: np.ndarray) -> np.ndarray:
        """``Phi^T A_k^T target`` (r,) for per-vertex vectors ``target`` (s, 3)."""

        def compute() -> np.ndarray:
            St = self.selection(self.body.fine_level, vertices, on).St
            return self.body.modes.vectors.T @ (St @ target).ravel()

        key = ("projected", on, value_key(vertices), value_key(target))
        return self.memo.get(key, compute)

    def offsets(self, kf: Keyframe) -> np.ndarray:
        """A keyframe's position targets minus rest, (s, 3)."""
        return kf.position - self.body.rest_positions(kf.on)[kf.vertices]

    # ----------------------------------------------------------------- linear
    def linear_system(
        self, kfs: list[Keyframe], nodes: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Band storage and linear term of E + E_C (eq. (6)): ``c_A |A_k Phi q_k - a_k|^2 +
        c_B |B_k Phi q'_k - b_k|^2`` added at the keyframes' nodes."""
        energy = self.energy(nodes)
        ab, f = np.array(energy.ab, order="F"), energy.f.copy()
        layout = self.layout(nodes)
        for kf in kfs:
            k = node_index(nodes, kf.time)
            c_A, c_B = kf.weights(self.body, self.duration)
            if kf.position is not None and c_A > 0:
                blk = layout.indices(k)
                add_block(ab, blk, c_A * self.body.modal_gram(kf.vertices, kf.on))
                f[blk] -= c_A * self.projected(kf.vertices, kf.on, self.offsets(kf))
            if kf.velocity is not None and c_B > 0:
                blk = layout.indices(k, velocity=True)
                add_block(ab, blk, c_B * self.body.modal_gram(kf.vertices, kf.on))
                f[blk] -= c_B * self.projected(kf.vertices, kf.on, kf.velocity)
        return ab, f

    def solve_linear(self, kfs: list[Keyframe], nodes: np.ndarray) -> np.ndarray:
        """The minimiser z of E + E_C (Theorem 1)."""
        if self.loop and self.body.modes.n_rigid and not any(
                kf.position is not None and kf.weights(self.body, self.duration)[0] > 0
                for kf in kfs):
            # velocity keys fix no place: the rigid modes' offsets are free (E is singular
            # there, but rounding may still let the factorization through)
            raise WigglyInputError(UNDETERMINED_LOOP)
        ab, f = self.linear_system(kfs, nodes)
        try:
            return BandedCholesky(ab).solve(-f)
        except np.linalg.LinAlgError as err:
            raise WigglyInputError(self._singular(kfs, nodes)) from err

    def _singular(self, kfs: list[Keyframe], nodes: np.ndarray) -> str:
        """Why the linear system of E + E_C could not be factorized, as far as can be told:
        keyframe times a hair apart, weights beyond double precision, or nothing fixing the
        start (a loop, or no pre-roll)."""
        h = np.diff(nodes)
        j = int(np.argmin(h))
        if h[j] < SHORTEST * self.duration:
            a, b = float(nodes[j]), float(nodes[j + 1])
            tol = merge_tolerance(self.start, self.end)
            near = [f"#{i} ('{kf.name}')" if kf.name else f"#{i}"
                    for i, kf in enumerate(kfs) if min(abs(kf.time - a), abs(kf.time - b)) <= tol]
            return (
                f"keyframes {', '.join(near) or '(the shot start or end)'} at t = {a!r} s and "
                f"{b!r} s are {b - a:.3g} s apart: the spline between them is numerically "
                f"singular; give them the same time, or move them at least "
                f"{SHORTEST * self.duration:.3g} s apart")
        T, m = self.duration, self.body.mass
        weights = [max(c_A * T**3, c_B * T) * max(len(kf.vertices), 1) / m  # as stiffness
                   for kf in kfs for c_A, c_B in [kf.weights(self.body, T)]]
        if weights and max(weights) > HEAVIEST:
            i = int(np.argmax(weights))
            kf = kfs[i]
            explicit = ", or its c_A / c_B" if kf.c_A is not None or kf.c_B is not None else ""
            return (
                f"keyframe #{i}{f' ({kf.name!r})' if kf.name else ''} weighs too much for "
                f"double precision (stiffness {kf.stiffness:g}{explicit}): the linear system is "
                "numerically singular; use a stiffness of at most 1e12 (the default is 1e6)")
        if self.loop:
            return UNDETERMINED_LOOP
        if self.preroll == 0:
            return ("the keyframes leave the motion undetermined and preroll is 0; give "
                    "keyframes that fix the start (positions and velocities of the whole body) or "
                    "a preroll > 0")
        return ("the linear system of the keyframes is numerically singular (preroll "
                f"{self.preroll:g} s); check for contradictory or extreme keyframes")

    # ----------------------------------------------------------------- solve
    @deprecated_progress
    def solve(
        self,
        keyframes: list[Keyframe],
        *,
        warped: bool = False,
        warm_start: WarmStart | None = None,
        options: SolveOptions | None = None,
        linear_start: list[Keyframe] | None = None,
    ) -> Animation:
        """Minimise E + E_C (linear, Theorem 1) or E + E_WC (``warped``, Theorem 2).

        Both have the same unknowns.  The warped problem starts from ``warm_start`` (the
        :attr:`Animation.warm_start` of an earlier solve of this problem, also with edited
        keyframes) or from the linear solution of ``linear_start`` (keyframes whose linear
        motion warps near the solution, each at the node nearest its time, e.g. a driver's
        whole poses, :func:`wiggly.drive.driver_poses`; default: ``keyframes`` with unwarped
        targets, :func:`unwarped`), and is minimised by
        :func:`wiggly.solve.levels.solve_warped` with ``options``
        (:class:`wiggly.solve.optimizer.SolveOptions`).  The start changes the path (and
        may change which local minimum is reached), never the objective.
        """
        options = options or SolveOptions()
        t0 = time.perf_counter()
        with blas_single_thread():
            kfs = self.checked(keyframes)
            nodes = self.nodes_for(kfs)
            energy = self.energy(nodes)
            size = self.layout(nodes).size
            info: dict = {"unknowns": size, "warped": warped, "loop": self.loop}
            warm = None
            if warped:
                if warm_start is not None and warm_start.fits(nodes, size):
                    z, warm = warm_start.z.copy(), warm_start
                else:
                    first = (unwarped(kfs, self.body) if linear_start is None else
                             self.checked(linear_start))
                    z = self.solve_linear(first, nodes)
                info["warm_start"] = warm is not None
                info["linear_seconds"] = time.perf_counter() - t0
                z, report, new_warm = solve_warped(self, kfs, nodes, z, options, warm)
                info.update(report)
            else:
                z, new_warm = self.solve_linear(kfs, nodes), None
        values, velocities = self.layout(nodes).states(z)
        info["solve_seconds"] = time.perf_counter() - t0
        return Animation(
            self.body, nodes, values.copy(), velocities.copy(), kfs, energy.basis,
            warped=warped, info=info, warm_start=new_warm, loop=self.loop,
        )


def keyframe_list(keyframes) -> list[Keyframe]:
    """``keyframes`` as a list, refused unless it is a list (or tuple) of :class:`Keyframe`."""
    if isinstance(keyframes, Keyframe) or not isinstance(keyframes, list | tuple):
        hint = " (put it in a list: [key])" if isinstance(keyframes, Keyframe) else ""
        raise WigglyInputError(f"keyframes should be a list of wiggly.Keyframe; got a "
                               f"{type(keyframes).__name__}{hint}")
    for j, kf in enumerate(keyframes):
        if not isinstance(kf, Keyframe):
            raise WigglyInputError(f"keyframes[{j}] is a {type(kf).__name__}, not a "
                                   "wiggly.Keyframe")
    return list(keyframes)


def nearest_turn(w: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """The rotation vector of the same rotation as ``w`` (its angle plus a multiple of 2 pi
    about its axis) nearest to ``previous``: consecutive keyed poses of a group turn the short
    way from one to the next, so a turn keyed in steps keeps its direction past 180 degrees
    (as angles are unwrapped).  A rest pose (w = 0) takes the axis of ``previous``."""
    theta = float(np.linalg.norm(w))
    if theta > 1e-12:
        axis = w / theta
    elif np.linalg.norm(previous) > 1e-12:
        axis = previous / np.linalg.norm(previous)
    else:
        return w
    k = round((float(previous @ axis) - theta) / (2.0 * np.pi))
    return (theta + 2.0 * np.pi * k) * axis


def unwarped(kfs: list[Keyframe], body: Body) -> list[Keyframe]:
    """Keyframes whose targets a *linear* motion can meet and whose warp is near the originals.

    Each keyframe's best-fit rotation R of its targets about their centroid (Kabsch) is
    replaced by its linearization with the same rotation vector w = log R: x = R (X - c) + c'
    + e becomes X + w x (X - c) + (c' - c) + R^T e; velocities are rotated back by R^T.  The
    angle of w is at most pi for a group's first key in time, and each later key takes the
    equivalent nearest the one before it (:func:`nearest_turn`), so a turn keyed in steps
    keeps its direction.  Warping maps a linearized rotation to the exact one (Schulz et al.
    2014, Theorem 2), so the linear solve with these targets starts the warped solve in the
    basin of large-rotation keyframes.  Keyframes of the same vertex group are fitted
    together (a driver keys one group at every frame); groups of fewer than 3 or collinear
    vertices have no unique rotation and keep their targets.
    """
    out = list(kfs)
    groups: dict[tuple, list[int]] = {}
    for j, kf in enumerate(kfs):
        if kf.position is not None and len(kf.vertices) >= 3:
            groups.setdefault((kf.on, value_key(kf.vertices)), []).append(j)
    for members in groups.values():
        first = kfs[members[0]]
        X = body.rest_positions(first.on)[first.vertices]
        A = X - X.mean(axis=0)
        spread = np.linalg.eigvalsh(A.T @ A)  # squared singular values of A, ascending
        if spread[1] <= 1e-18 * max(spread[2], 1e-300):  # collinear: no unique rotation
            continue
        # Kabsch: R = argmax tr(R^T B^T A), B = x - c' (B^T A = x^T A: A sums to zero)
        c_t = np.array([kfs[j].position.mean(axis=0) for j in members])
        U, _, Vt = np.linalg.svd(np.array([kfs[j].position.T @ A for j in members]))
        sign = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= np.where(sign == 0, 1.0, sign)[:, None]  # det R = 1
        R = U @ Vt
        w = Rotation.from_matrix(R).as_rotvec()
        previous = np.zeros(3)  # at rest before the first key: its turn is at most pi
        for a in np.argsort([kfs[j].time for j in members], kind="stable"):
            w[a] = nearest_turn(w[a], previous)
            previous = w[a]
        # X + w x A + (c' - c) + (B - A R^T) R = x R + (c' - c' R) + w x A  (R^T R = I)
        cross = np.zeros((len(members), 3, 3))  # [w]x^T: a @ cross[a] = w x a
        cross[:, [1, 2, 0], [2, 0, 1]] = w
        cross[:, [2, 0, 1], [1, 2, 0]] = -w
        shift = c_t - np.einsum("ki,kij->kj", c_t, R)
        for a, j in enumerate(members):
            kf = kfs[j]
            position = kf.position @ R[a] + A @ cross[a] + shift[a]
            velocity = None if kf.velocity is None else kf.velocity @ R[a]
            out[j] = replace(kf, position=position, velocity=velocity)
    return out
