"""The nodes of a shot: the times where the wiggly splines join (Theorem 1).

Nodes are the shot's start and end and every keyframe time; keyframe times closer than
1e-9 of the duration share a node.
"""

from __future__ import annotations

import numpy as np

__all__ = ["node_index", "node_times"]


def node_times(start: float, end: float, times: list[float]) -> np.ndarray:
    """Sorted node times: ``start``, ``end`` and ``times`` (merged within 1e-9 T)."""
    duration = end - start
    t = np.sort(np.r_[start, end, times])
    keep = np.r_[True, np.diff(t) > 1e-9 * duration]
    t = t[keep]
    t[-1] = end
    return t


def node_index(nodes: np.ndarray, t: float) -> int:
    """The node of time ``t``."""
    return int(np.argmin(np.abs(nodes - t)))
