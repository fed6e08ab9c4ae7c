"""The warped objective E + E_WC: value, gradient, Newton matrix.

Schulz et al. 2014, eq. (8) and Theorem 2.

    F(z) = 1/2 z^T H z + f^T z + c + 1/2 sum_k |r_k(z)|^2,
    r_k = sqrt(c_A) (S_k W(Phi q_k) - d_k)   or   sqrt(c_B) (S_k DW(Phi q_k)[Phi q'_k] - b_k),

with S_k the scalar selection of keyframe k's vertices (barycentric rows for surface
vertices) and q_k, q'_k the modal state at its node.  On a coarse level (:mod:`wiggly.warp`)
W is replaced by W~ = P W_c(R .), i.e. S_k by S_k P and the fine warp by the coarse one.

* W and DW v are evaluated only at constrained nodes, all in one multi-right-hand-side
  Poisson solve; the gradient pulls the residuals back with vector-Jacobian products (one
  adjoint solve per distinct cotangent).  For velocity keyframes the q-part of the gradient,
  ``Phi^T D^2W(u)[., Phi q']^T y``, is a central difference of two vjps (error ~1e-11).
* The Newton matrix is the band of H plus, per constrained node, the Gauss-Newton blocks
  J^T (C kron I_3) J (C = S^T S) and the curvature Gauss-Newton omits,
  ``Phi^T grad^2(y . W) Phi`` with the cotangent ``y = sqrt(c) S^T r`` (for velocity keyframes
  also the q-q' and the third-order q-q blocks, :class:`wiggly.warp.ModalWarp`).  At a
  solution with stiff keyframes ``c r`` balances the energy's gradient, so the curvature is
  as large as H: without it Gauss-Newton converges only linearly.  The matrix is taken on
  the objective's own level (exact: Newton's method) or on a coarser one (approximate, with
  the cotangents transferred by ``P^T``).  A coarse model's Jacobians are ``P DW_c(R u) R
  Phi + E`` with ``E = Phi - P R Phi`` the coarse mesh's interpolation error of the modes:
  both warps have DW(0) = I, so these equal the fine Jacobians at rest and differ from them
  by O(|u|) (without E, by the 5-8 % that a coarse mesh misses of the higher modes): on the
  driven benchmark the fine level's first step contracts by 0.08 instead of 0.16.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from wiggly.keyframes import Keyframe
from wiggly.solve.banded import add_blocks, band_matvec
from wiggly.solve.blocks import NewtonBlocks, NodeDerivatives
from wiggly.solve.nodes import node_index
from wiggly.warp import WarpLevel

if TYPE_CHECKING:
    from wiggly.solve.problem import SpacetimeProblem, TargetFit

__all__ = ["WarpedObjective", "WarpedPoint"]

# Relative step of the central difference of vjps that gives D^2W(u)[., v]^T y.
VJP_STEP = 1e-6
# Relative step of the forward difference J dz ~ (r(z + h dz) - r(z)) / h in the second-order
# correction (its error, ~h of the correction, only changes the path).
CORRECTION_STEP = 1e-5


@dataclass(frozen=True)
class _Term:
    """One keyframe's residual on a level: ``w (S x - target)`` at node ``node``."""

    node: int
    w: float
    vertices: np.ndarray
    on: str
    fit: TargetFit  # of the targets (offsets from rest, or velocities) on the level


@dataclass(frozen=True, eq=False)
class WarpedPoint:
    """The objective at z, with what its gradient and Newton matrix were made of."""

    z: np.ndarray
    F: float
    g: np.ndarray | None  # None: a trial point, evaluated without its gradient
    magnitude: float  # sum of the magnitudes of F's terms (its rounding level / eps)
    level: str
    signature: tuple  # (active nodes, velocity nodes)
    U: np.ndarray  # Phi q at the active nodes (f, n_L, 3)
    WU: np.ndarray  # W(U)
    V: np.ndarray  # Phi q' at the velocity nodes (k, n_L, 3)
    Vel: np.ndarray  # DW(U[velocity nodes])[V]
    YA: np.ndarray  # position cotangents per active node (f, n_L, 3)
    YB: np.ndarray  # velocity cotangents per velocity node (k, n_L, 3)
    pulled: np.ndarray | None  # their pull-backs to modal coordinates (f + 3 k, r)


class WarpedObjective:
    """E + E_WC of ``keyframes`` over ``nodes`` on warp ``level`` (module docstring).

    ``model`` is the level whose derivatives build the Newton matrix (default: ``level``
    itself, i.e. the exact Hessian); ``correction`` = (tau, c) adds ``tau^T z + c`` (the full
    approximation scheme's correction of a coarse level, :mod:`wiggly.solve.levels`);
    ``blocks`` is the :class:`~wiggly.solve.blocks.NewtonBlocks` store of the model's level
    to draw derivatives from (shared by the levels of a solve and kept by its warm start).
    ``curvature=False`` starts with Gauss-Newton matrices (the Newton matrix without the
    curvature blocks: positive definite, so every step is a full one; an approximate model
    that :meth:`use_exact` completes when it converges slowly).
    """

    def __init__(
        self,
        problem: SpacetimeProblem,
        level: WarpLevel,
        keyframes: list[Keyframe],
        nodes: np.ndarray,
        *,
        model: WarpLevel | None = None,
        correction: tuple[np.ndarray, float] | None = None,
        blocks: NewtonBlocks | None = None,
        curvature: bool = True,
    ) -> None:
        body = problem.body
        self.problem, self.level, self.model = problem, level, model or level
        self.curvature = curvature
        if blocks is not None and blocks.level is not self.model:
            raise ValueError("the Newton blocks belong to another warp level")
        self.blocks = blocks if blocks is not None else NewtonBlocks(self.model)
        self.name = "fine" if level.exact else "coarse"
        self.r = body.r
        self.nodes = nodes
        self.layout = problem.layout(nodes)
        energy = problem.energy(nodes)
        self.ab_E, self.f_E, self.c_E = energy.ab, energy.f, energy.c
        if correction is not None:
            self.f_E = self.f_E + correction[0]
            self.c_E = self.c_E + correction[1]
        wanted: list[tuple[int, int, float, Keyframe, np.ndarray]] = []  # kind 0: position
        for kf in keyframes:
            c_A, c_B = kf.weights(body, problem.duration)
            k = self.layout.canonical(node_index(nodes, kf.time))
            if kf.position is not None and c_A > 0:
                wanted.append((0, k, float(np.sqrt(c_A)), kf, problem.offsets(kf)))
            if kf.velocity is not None and c_B > 0:
                wanted.append((1, k, float(np.sqrt(c_B)), kf, kf.velocity))
        fits = problem.fits(level, [(kf.vertices, kf.on, d) for _, _, _, kf, d in wanted])
        self.positions: list[_Term] = []
        self.velocities: list[_Term] = []
        for (kind, k, w, kf, _), fit in zip(wanted, fits, strict=True):
            (self.velocities if kind else self.positions).append(
                _Term(k, w, kf.vertices, kf.on, fit)
            )
        terms = self.positions + self.velocities
        self.active = sorted({t.node for t in terms})
        self.vel = sorted({t.node for t in self.velocities})
        self.slot = {k: a for a, k in enumerate(self.active)}
        self.vslot = {k: a for a, k in enumerate(self.vel)}
        self.signature = (tuple(self.active), tuple(self.vel))
        self.timing = {"W": 0.0, "vjp": 0.0, "newton": 0.0}
        self.counts = {"W": 0, "vjp": 0, "newton": 0}
        self._grams = self._node_grams(self.model)
        # per active node: the Gauss-Newton block J^T C J and the derivatives it was built
        # from (owned here: C is this objective's; the blocks store hands back the same
        # NodeDerivatives object for as long as it keeps that node's Jacobians)
        self._gn_blocks: dict[int, tuple[NodeDerivatives, np.ndarray]] = {}

    @property
    def exact(self) -> bool:
        """Whether the Newton matrix is this objective's exact Hessian."""
        return self.model is self.level and self.curvature

    def use_exact(self) -> bool:
        """Improve the Newton matrix by one stage from now on: add the curvature to
        Gauss-Newton matrices; then build them from this level's own derivatives.  False if
        they already are the exact Hessian."""
        if self.exact:
            return False
        if not self.curvature:
            self.curvature = True
            return True
        if self.model is not self.level:
            self.model = self.level
            self.blocks = NewtonBlocks(self.model)
            self._grams = self._node_grams(self.model)
            self._gn_blocks = {}
        return True

    def _node_grams(self, model: WarpLevel) -> dict[int, tuple]:
        """Per active node, ``sum c_A C_k`` and ``sum c_B C_k`` over its position and
        velocity keyframes, C_k the Gram of keyframe k's selection on ``model``'s level, and
        for a coarse model the same sums of the terms of its interpolation error
        (:meth:`wiggly.body.Body.model_error`)."""
        grams: dict[int, list] = {k: [None, None, None, None] for k in self.active}
        coarse = model is not self.level
        for j, terms in enumerate((self.positions, self.velocities)):
            for t in terms:
                C = t.w**2 * self.problem.selection(model, t.vertices, t.on).C
                old = grams[t.node][j]
                grams[t.node][j] = C if old is None else old + C
                if coarse:
                    K2, K3 = self.problem.body.model_error(model, t.vertices, t.on)
                    old = grams[t.node][2 + j]
                    new = (t.w**2 * K2, t.w**2 * K3)
                    grams[t.node][2 + j] = (
                        new if old is None else (old[0] + new[0], old[1] + new[1])
                    )
        return {k: tuple(v) for k, v in grams.items()}

    # -------------------------------------------------------------- evaluation
    def _states(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.layout.states(z)

    def evaluate(
        self, z: np.ndarray, prior: WarpedPoint | None = None, gradient: bool = True
    ) -> WarpedPoint:
        """F and its gradient at z.  With a ``prior`` point at the same z, level and node
        nodes (an earlier solve's last point: a warm start), its W values are reused and only
        the cotangents that changed are pulled back (the vjp is linear in them).
        ``gradient=False`` leaves the gradient (its vjps, two thirds of the cost) to
        :meth:`with_gradient`: a trial point of the trust region needs F only."""
        z = np.asarray(z, dtype=np.float64)
        t0 = time.perf_counter()
        reuse = (
            prior is not None
            and prior.level == self.name
            and prior.signature == self.signature
            and np.array_equal(prior.z, z)
        )
        if reuse:
            U, WU, V, Vel = prior.U, prior.WU, prior.V, prior.Vel
        else:
            U, WU, V, Vel = self._warped(z)
        t1 = time.perf_counter()
        self.timing["W"] += t1 - t0
        Hz = band_matvec(self.ab_E, z)
        quad, lin = 0.5 * float(z @ Hz), float(self.f_E @ z)
        YA, YB = np.zeros_like(U), np.zeros_like(V)
        F_res = 0.0
        for t in self.positions:
            value, cotangent = t.fit.value_and_cotangent(WU[self.slot[t.node]])
            F_res += t.w**2 * value
            YA[self.slot[t.node]] += t.w**2 * cotangent
        for t in self.velocities:
            value, cotangent = t.fit.value_and_cotangent(Vel[self.vslot[t.node]])
            F_res += t.w**2 * value
            YB[self.vslot[t.node]] += t.w**2 * cotangent
        F = quad + lin + self.c_E + F_res
        magnitude = abs(quad) + abs(lin) + abs(self.c_E) + F_res
        point = WarpedPoint(
            z.copy(), float(F), None, magnitude, self.name, self.signature,
            U, WU, V, Vel, YA, YB, None,
        )
        return self.with_gradient(point, prior if reuse else None) if gradient else point

    def with_gradient(self, point: WarpedPoint, prior: WarpedPoint | None = None) -> WarpedPoint:
        """``point`` with its gradient (the same point if it has one); ``prior``: an earlier
        point at the same z whose pull-backs are updated by the change of the cotangents."""
        if point.g is not None:
            return point
        t0 = time.perf_counter()
        g = band_matvec(self.ab_E, point.z) + self.f_E
        pulled = self._pull_back(point.U, point.V, point.YA, point.YB, prior)
        self._add_pulled(g, pulled, point.U, point.V)
        self.timing["vjp"] += time.perf_counter() - t0
        return replace(point, g=g, pulled=pulled)

    def _warped(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``u = Phi q`` at the active nodes, ``W(u)``, ``v = Phi q'`` at the velocity nodes
        and ``DW(u)[v]`` there, on this objective's level."""
        q, v = self._states(z)
        modal, warp = self.level.modal, self.level.warp
        empty = np.zeros((0, modal.n_vertices, 3))
        U = modal.displacements(q[self.active]) if self.active else empty
        V = modal.displacements(v[self.vel]) if self.vel else empty
        if self.vel:
            WU, Vel = warp.apply_and_jvp(U, [self.slot[k] for k in self.vel], V)
        else:
            WU, Vel = (warp.apply(U) if self.active else U), V
        self.counts["W"] += len(self.active) + len(self.vel)
        return U, WU, V, Vel

    def _add_pulled(self, g: np.ndarray, pulled: np.ndarray, U: np.ndarray, V: np.ndarray) -> None:
        """Add the modal pull-backs of :meth:`_pull_back` to the node gradient g."""
        f, nv = len(self.active), len(self.vel)
        self.layout.add_to(g, self.active, pulled[:f], None)
        if nv:
            iv = [self.slot[k] for k in self.vel]
            h = self._vjp_steps(U[iv], V)
            dq = pulled[f + nv : f + 2 * nv] - pulled[f + 2 * nv :]
            self.layout.add_to(g, self.vel, dq / (2 * h[:, None]), pulled[f : f + nv])

    def correction_gradient(
        self, point: WarpedPoint, dz: np.ndarray, trial: WarpedPoint
    ) -> np.ndarray | None:
        """The right-hand side of the second-order correction of a step ``dz`` from
        ``point`` to ``trial`` (Nocedal & Wright 2006, sec. 18.3; Transtrum & Sethna 2012's
        geodesic acceleration): ``J^T C m``, the residuals' nonlinear part along the step,

            m = r(z + dz) - r(z) - J dz,

        (J dz from a forward difference of W along dz) weighted by the keyframes' Grams and
        pulled back at ``point``.  The correction ``-B^-1 J^T C m`` moves the step back onto
        the curved valley of stiff keyframes, which a quadratic model cannot follow.  None
        without constrained nodes."""
        if not self.active:
            return None
        t0 = time.perf_counter()
        _, WU_h, _, Vel_h = self._warped(point.z + CORRECTION_STEP * dz)
        mU = trial.WU - point.WU - (WU_h - point.WU) / CORRECTION_STEP
        mV = trial.Vel - point.Vel - (Vel_h - point.Vel) / CORRECTION_STEP
        YA, YB = np.zeros_like(point.U), np.zeros_like(point.V)
        for t in self.positions:
            YA[self.slot[t.node]] += t.w**2 * (t.fit.C @ mU[self.slot[t.node]])
        for t in self.velocities:
            YB[self.vslot[t.node]] += t.w**2 * (t.fit.C @ mV[self.vslot[t.node]])
        g = np.zeros_like(point.z)
        self._add_pulled(g, self._pull_back(point.U, point.V, YA, YB, None), point.U, point.V)
        self.timing["vjp"] += time.perf_counter() - t0
        return g

    @staticmethod
    def _vjp_steps(U: np.ndarray, V: np.ndarray) -> np.ndarray:
        return (
            VJP_STEP
            * (1.0 + np.abs(U).max(axis=(1, 2), initial=0.0))
            / np.maximum(np.abs(V).max(axis=(1, 2), initial=0.0), 1e-300)
        )

    def _pull_back(self, U, V, YA, YB, prior: WarpedPoint | None) -> np.ndarray:
        """Modal pull-backs (f + 3 k, r): ``Phi^T DW(u_a)^T y_a`` at every active node, and at
        velocity nodes ``Phi^T DW(u)^T y_v`` and ``Phi^T DW(u +- h v)^T y_v``."""
        f, nv = len(U), len(V)
        iv = [self.slot[k] for k in self.vel]
        if nv:
            step = self._vjp_steps(U[iv], V)[:, None, None] * V
            frames = np.concatenate([U, U[iv], U[iv] + step, U[iv] - step])
        else:
            frames = U
        index = np.r_[np.arange(f), np.tile(f + np.arange(nv), 3)].astype(np.int64)
        Y = np.concatenate([YA, YB])
        if prior is None:
            todo, dY, out = np.arange(len(frames)), Y, np.zeros((len(frames), self.r))
        else:  # the same point: pull back the change of the cotangents only
            dY = Y - np.concatenate([prior.YA, prior.YB])
            changed = np.flatnonzero(np.any(dY != 0.0, axis=(1, 2)))
            todo = np.flatnonzero(np.isin(index, changed))
            out = prior.pulled.copy()
        if len(todo):
            cotangents, sub = np.unique(index[todo], return_inverse=True)
            back = self.level.warp.vjp(frames[todo], dY[cotangents], sub)
            out[todo] += back.reshape(len(todo), -1) @ self.level.modal.matrix
            self.counts["vjp"] += len(todo)
        return out

    # ------------------------------------------------------------ Newton matrix
    def newton_matrices(
        self, point: WarpedPoint, fresh: bool = False
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """Band storage of the Gauss-Newton matrix (H plus each active node's J^T (C kron I)
        J) and of the Newton matrix (plus the curvature blocks), from the derivatives of
        :attr:`model` (module docstring), and whether every node's derivatives were computed
        at this point (``fresh`` forces that; with an exact model the Newton matrix is then
        the Hessian).  The first is positive definite wherever H is; the second may be
        indefinite far from a minimiser."""
        t0 = time.perf_counter()
        model, r = self.model, self.r
        q, v = self._states(point.z)
        gn = np.array(self.ab_E, order="F")
        if not self.active:
            return gn, gn.copy(order="F"), True
        f = len(self.active)
        Qa = q[self.active]
        same = model is self.level
        YA = point.YA if same else model.transfer.lift_adjoint(point.YA)
        Qv = np.zeros_like(Qa)
        Yv = np.zeros_like(YA)
        velocity = [k in self.vslot for k in self.active]
        if self.vel:
            iv = [self.slot[k] for k in self.vel]
            Qv[iv] = v[self.vel]
            Yv[iv] = point.YB if same else model.transfer.lift_adjoint(point.YB)
        times = [float(self.nodes[k]) for k in self.active]
        derivs, all_fresh = self.blocks.derivatives(
            times, Qa, Qv, velocity, YA, Yv, fresh, curvature=self.curvature
        )
        blocks = np.zeros((f, 2 * r, 2 * r))
        curv = np.zeros((f, 2 * r, 2 * r))
        for a, k in enumerate(self.active):
            d = derivs[a]
            kept = self._gn_blocks.get(k)
            if kept is not None and kept[0] is d:  # the same Jacobians: the same block
                blocks[a] = kept[1]
            else:
                C_pos, C_vel, E_pos, E_vel = self._grams[k]
                if C_pos is not None:
                    blocks[a, :r, :r] += _gram(C_pos, d.J)
                    if E_pos is not None:
                        JK = d.J.reshape(-1, r).T @ E_pos[0].reshape(-1, r)
                        blocks[a, :r, :r] += JK + JK.T + E_pos[1]
                if C_vel is not None:
                    X = np.concatenate([d.JV, d.J], axis=2)  # [D^2W[., v], DW]
                    blocks[a] += _gram(C_vel, X)
                    if E_vel is not None:
                        XK = X.reshape(-1, 2 * r).T @ E_vel[0].reshape(-1, r)  # (2r, r)
                        blocks[a, :, r:] += XK
                        blocks[a, r:, :] += XK.T
                        blocks[a, r:, r:] += E_vel[1]
                self._gn_blocks[k] = (d, blocks[a].copy())
            if not self.curvature:
                continue
            curv[a, :r, :r] = d.qq
            if d.qv is not None:
                curv[a, :r, r:] = d.qv
                curv[a, r:, :r] = d.qv.T
        idx = 2 * r * self.layout.block[self.active][:, None] + np.arange(2 * r)
        add_blocks(gn, idx, 0.5 * (blocks + blocks.transpose(0, 2, 1)))
        full = np.array(gn, order="F")
        if self.curvature:
            add_blocks(full, idx, 0.5 * (curv + curv.transpose(0, 2, 1)))
        self.counts["newton"] += f
        self.timing["newton"] += time.perf_counter() - t0
        return gn, full, all_fresh

    @property
    def size(self) -> float:
        """The body's size (m): the diagonal of its rest bounding box."""
        X = self.problem.body.rest_positions("tets")
        return float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))

    def step_size(self, dz: np.ndarray) -> float:
        """The largest vertex displacement (m, tet mesh) of a change ``dz`` of the node
        values, over all nodes."""
        dq, _ = self._states(dz)
        Phi = self.problem.body.modes.vectors
        D = (Phi @ dq.T).reshape(-1, 3, len(dq))
        return float(np.sqrt((D**2).sum(axis=1)).max(initial=0.0))


def _gram(C: sp.spmatrix, X: np.ndarray) -> np.ndarray:
    """``X^T (C kron I_3) X`` for fields X (n, 3, k) and a scalar Gram C (n, n)."""
    n, _, k = X.shape
    CX = (C @ X.reshape(n, 3 * k)).reshape(n, 3, k)
    return X.reshape(3 * n, k).T @ CX.reshape(3 * n, k)
