"""The nodes of a shot: the times where the wiggly splines join (Theorem 1).

Nodes are the shot's start and end and every keyframe time; keyframe times closer than
:func:`merge_tolerance` (1e-5 of the duration, or float32 rounding of the times) share
a node: the same frame written by another tool in single precision is one node, not an
interval of nanoseconds whose spline energy (growing as 1/h^3) no factorization survives.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NodeLayout", "merge_tolerance", "node_index", "node_times", "refine_nodes"]


def merge_tolerance(start: float, end: float) -> float:
    """Keyframe times closer than this (s) share a node: 1e-5 of the duration, or four float32
    rounding steps of the shot's latest time, whichever is larger."""
    return max(1e-5 * (end - start), 2.5e-7 * max(abs(start), abs(end)))


def node_times(start: float, end: float, times: list[float]) -> np.ndarray:
    """Sorted node times: ``start``, ``end`` and ``times`` (merged within
    :func:`merge_tolerance`; a time merged with the end becomes the end)."""
    t = np.sort(np.r_[start, end, times])
    keep = np.r_[True, np.diff(t) > merge_tolerance(start, end)]
    t = t[keep]
    t[-1] = end
    return t


def refine_nodes(nodes: np.ndarray, longest: float) -> np.ndarray:
    """``nodes`` with every interval longer than ``longest`` split into equal ones."""
    if not np.isfinite(longest):
        return nodes
    pieces = np.maximum(1, np.ceil(np.diff(nodes) / longest - 1e-9).astype(int))
    if pieces.max() == 1:
        return nodes
    inner = [a + (b - a) * np.arange(k) / k
             for a, b, k in zip(nodes[:-1], nodes[1:], pieces, strict=True)]
    return np.r_[np.concatenate(inner), nodes[-1]]


def node_index(nodes: np.ndarray, t: float) -> int:
    """The node of time ``t``."""
    return int(np.argmin(np.abs(nodes - t)))


class NodeLayout:
    """Where each node's values and velocities sit in the unknowns z (Theorem 1).

    A shot has nodes ``t_0 < ... < t_m``; the unknowns are blocks ``z_j = (q, q')`` of 2 r
    values.  Plain shots: node k is block k, and every matrix of the solve is banded with upper
    bandwidth ``4 r - 1``.  Looped (periodic) shots: node m *is* node 0 (positions and
    velocities at the end equal those at the start, and the wiggly splines wrap around from the
    last node to the first), so there are m blocks; they are ordered 0, 1, m-1, 2, m-2, ...,
    which puts the two nodes of every interval, the wrapping one included, at most two blocks
    apart: the matrices stay banded (upper bandwidth ``6 r - 1``).
    """

    def __init__(self, nodes: np.ndarray, r: int, loop: bool = False) -> None:
        self.nodes = np.asarray(nodes, dtype=np.float64)
        self.r = int(r)
        self.loop = bool(loop)
        m = len(self.nodes) - 1
        if loop:
            order = [0]
            lo, hi = 1, m - 1
            while lo <= hi:
                order.append(lo)
                if hi != lo:
                    order.append(hi)
                lo, hi = lo + 1, hi - 1
            block = np.empty(m + 1, dtype=np.int64)
            block[order] = np.arange(m)
            block[m] = block[0]
        else:
            block = np.arange(m + 1, dtype=np.int64)
        self.block = block
        self.n_blocks = m if loop else m + 1
        gap = int(np.abs(np.diff(block)).max(initial=0))
        self.bandwidth = 2 * self.r * (gap + 1) - 1

    @property
    def size(self) -> int:
        """Number of unknowns."""
        return 2 * self.r * self.n_blocks

    def canonical(self, k: int) -> int:
        """The node that owns node k's unknowns (node 0 for the last node of a loop)."""
        return 0 if self.loop and k == len(self.nodes) - 1 else int(k)

    def indices(self, k: int, velocity: bool = False) -> np.ndarray:
        """Positions in z of node k's r values (or velocities)."""
        return 2 * self.r * int(self.block[k]) + (self.r if velocity else 0) + np.arange(self.r)

    def states(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and velocities (m + 1, r) of every node (for a loop the last row repeats the
        first)."""
        Z = np.asarray(z).reshape(self.n_blocks, 2, self.r)[self.block]
        return Z[:, 0], Z[:, 1]

    def unknowns(self, values: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """z from per-node values and velocities (m + 1, r)."""
        Z = np.empty((self.n_blocks, 2, self.r))
        Z[self.block, 0] = values
        Z[self.block, 1] = velocities
        return Z.ravel()

    def add_to(self, g: np.ndarray, nodes: list[int], q: np.ndarray | None,
               v: np.ndarray | None) -> None:
        """Add per-node gradients q, v (len(nodes), r) of ``nodes`` into z-shaped ``g``."""
        G = g.reshape(self.n_blocks, 2, self.r)
        b = self.block[np.asarray(nodes, dtype=np.int64)]
        if q is not None:
            np.add.at(G[:, 0], b, q)
        if v is not None:
            np.add.at(G[:, 1], b, v)
