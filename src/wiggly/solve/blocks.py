"""The per-node derivatives behind the warped solve's Newton matrices, and when to reuse them.

At a constrained node with modal state x = (q, q') and cotangents y (the weighted residuals
pulled to the level's vertices), a Newton matrix block needs, on the model's warp level:
the Jacobian ``J = DW(u) Phi``, for velocity keyframes ``JV = D^2W(u)[Phi, Phi q']``, and the
curvature blocks (:meth:`wiggly.warp.ModalWarp.curvatures`).  They cost a multi-right-hand-
side Poisson solve and a pass over the tets per node, while between iterations (and between
the solves of an editing session) most nodes barely move.

A :class:`NewtonBlocks` store, owned by the solve that creates it and handed on in its
:class:`~wiggly.solve.levels.WarmStart`, keeps each node's derivatives with the state and
cotangents they were computed at.  A node's Jacobians are recomputed when its state moved by
more than ``REUSE_STATE`` (relative to the node's state, or to 5 % of the largest node state
for nodes near rest), its curvature also when its cotangents moved by more than
``REUSE_COTANGENT``.  A matrix built with reused blocks is not the Hessian at the point: the
optimizer then certifies convergence by the measured contraction, or asks for fresh blocks
(:mod:`wiggly.solve.optimizer`).  Reuse changes the path of the solve, never its solution.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wiggly.warp import WarpLevel

__all__ = ["NewtonBlocks", "NodeDerivatives"]

REUSE_STATE = 0.02
REUSE_COTANGENT = 0.25


@dataclass
class NodeDerivatives:
    """A node's derivatives on the model level and where they were computed."""

    x: np.ndarray  # (2 r,) state (q, q')
    J: np.ndarray  # (n_M, 3, r)
    JV: np.ndarray | None  # (n_M, 3, r), velocity nodes
    y: np.ndarray | None  # (n_M, 3) position cotangent (None: no curvature yet)
    yv: np.ndarray | None  # (n_M, 3) velocity cotangent
    qq: np.ndarray | None  # (r, r) curvature blocks
    qv: np.ndarray | None


def _moved(new: np.ndarray | None, old: np.ndarray | None, scale: float, tol: float) -> bool:
    if (new is None) != (old is None):
        return True
    if new is None:
        return False
    return float(np.linalg.norm(new - old)) > tol * scale


class NewtonBlocks:
    """Derivatives per node time on one warp ``level`` (module docstring).  ``reuse=False``
    recomputes every node at every call."""

    def __init__(self, level: WarpLevel, reuse: bool = True) -> None:
        self.level = level
        self.reuse = reuse
        self._nodes: dict[float, NodeDerivatives] = {}
        self.computed = {"jacobians": 0, "curvatures": 0}

    def derivatives(
        self,
        times: list[float],
        Q: np.ndarray,
        Qv: np.ndarray,
        velocity: list[bool],
        Y: np.ndarray,
        Yv: np.ndarray,
        fresh: bool = False,
        curvature: bool = True,
    ) -> tuple[list[NodeDerivatives], bool]:
        """The derivatives at nodes ``times`` with states Q, Qv (f, r) (velocity rows only
        where ``velocity``), cotangents Y, Yv (f, n_M, 3) on the level.  Returns them and
        whether all were computed at exactly these states and cotangents.  ``fresh`` keeps
        only nodes computed at exactly these (recomputes the others).  ``curvature=False``
        computes the Jacobians only (Gauss-Newton matrices; the curvature blocks stay as they
        are, possibly None)."""
        modal = self.level.modal
        f = len(times)
        X = np.concatenate([Q, Qv], axis=1)
        floor = 0.05 * max((float(np.linalg.norm(x)) for x in X), default=0.0)
        jac, curv = [], []
        kept: list[NodeDerivatives | None] = []
        # fresh: only derivatives computed at exactly this state and cotangent are kept
        state, cotangent = (0.0, 0.0) if fresh else (REUSE_STATE, REUSE_COTANGENT)
        for a, t in enumerate(times):
            old = self._nodes.get(t) if self.reuse else None
            yv = Yv[a] if velocity[a] else None
            if old is not None:
                scale = max(float(np.linalg.norm(old.x)), floor)
                if _moved(X[a], old.x, scale, state) or (old.JV is None) == velocity[a]:
                    old = None
            if old is None:
                jac.append(a)
                if curvature:
                    curv.append(a)
            elif curvature and old.qq is None:
                curv.append(a)
            elif curvature:
                ys = max(float(np.linalg.norm(old.y)), float(np.linalg.norm(Y[a])), 1e-300)
                yvs = 0.0 if yv is None else max(float(np.linalg.norm(yv)), 1e-300)
                if _moved(Y[a], old.y, ys, cotangent) or _moved(yv, old.yv, yvs, cotangent):
                    curv.append(a)
            kept.append(old)
        out: list[NodeDerivatives | None] = list(kept)
        if jac:
            J = modal.jacobians(Q[jac])
            vj = [a for a in jac if velocity[a]]
            JV = modal.second_derivatives(Q[vj], Qv[vj]) if vj else None
            for i, a in enumerate(jac):
                jv = JV[vj.index(a)] if velocity[a] else None
                out[a] = NodeDerivatives(X[a].copy(), J[i], jv, None, None, None, None)
            self.computed["jacobians"] += len(jac)
        if curv:
            vc = [velocity[a] for a in curv]
            blocks = modal.curvatures(
                Q[curv], Y[curv],
                Qv[curv] if any(vc) else None,
                Yv[curv] if any(vc) else None,
            )
            for i, a in enumerate(curv):
                node = out[a]
                node.y, node.yv = Y[a].copy(), (Yv[a].copy() if velocity[a] else None)
                node.qq, node.qv = blocks[i]
                if velocity[a] and node.qv is None:
                    node.qv = np.zeros_like(node.qq)
            self.computed["curvatures"] += len(curv)
        for a, t in enumerate(times):
            self._nodes[t] = out[a]
        exact = all(
            np.array_equal(out[a].x, X[a])
            and (
                not curvature
                or (
                    out[a].y is not None
                    and np.array_equal(out[a].y, Y[a])
                    and (not velocity[a] or np.array_equal(out[a].yv, Yv[a]))
                )
            )
            for a in range(f)
        )
        return out, exact
