"""Whether the surface shows the solid's motion.

The outputs are the user's triangles, each vertex carried by the tet that holds it (its
barycentric embedding): along a surface edge that spans several tets the surface stays
straight while the tets bend under it, and whatever lies on the solid halfway along it
parts from it (a review's low-poly plant: a 60 cm stalk modelled as two rings of vertices
was drawn straight while the tets bent it, and a leaf embedded halfway up floated beside
it).  :func:`straight_edges` measures that gap on the played motion: the middle of each long
edge as the surface plays it, the mean of its corners, against the point of the solid it
lies on at rest, as the tets move it.  The two agree exactly under any affine motion (the
embedding reproduces affine maps), so the gap is the bending within the edge's span.
"""

from __future__ import annotations

import numpy as np

from wiggly.errors import warn
from wiggly.mesh.data import embed
from wiggly.mesh.defects import diagonal

__all__ = ["BENT", "LONG_EDGE", "straight_edges", "warn_straight"]

#: Surface edges longer than this many tet edges (the median) are measured ...
LONG_EDGE = 2.0
#: ... and said to part from the solid when their middle lies further than this share of
#: the body's size from it at some frame.
BENT = 0.01
#: At most this many frames are measured, evenly spread.
FRAMES = 100


def straight_edges(anim, times: np.ndarray) -> dict | None:
    """The largest gap between a long surface edge's middle and the solid under it over
    ``times`` (module doc): ``{"gap"`` (m), ``"time"``, ``"edge"`` (its two surface
    vertices), ``"at"`` (its middle at rest), ``"parted"`` (long edges whose gap exceeds
    :data:`BENT` of the body's size), ``"long"`` (the long edges), ``"longest"`` (m),
    ``"tet_edge"`` (m)``}``, or None when no surface edge is long."""
    body = anim.body
    surface, tets = body.surface, body.tets
    faces = surface.faces
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]],
                                              faces[:, [2, 0]]]), axis=1), axis=0)
    V = surface.vertices
    length = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    h = float(np.median(tets.edge_lengths()))
    long = np.flatnonzero(length > LONG_EDGE * h)
    if not len(long):
        return None
    a, b = edges[long].T
    middle = 0.5 * (V[a] + V[b])
    E = body.surface_embedding
    D = (embed(middle, tets).matrix(tets.n_vertices) - 0.5 * (E[a] + E[b])).tocsr()
    times = np.asarray(times, float)
    if len(times) > FRAMES:
        times = times[np.unique(np.linspace(0, len(times) - 1, FRAMES).round().astype(int))]
    P = anim.positions(times, "tets")  # (f, n, 3)
    f, n = P.shape[:2]
    rest = D @ body.rest_positions("tets")  # 0 up to the embedding's round-off
    gap = (D @ P.transpose(1, 0, 2).reshape(n, 3 * f)).reshape(len(long), f, 3) - rest[:, None]
    gap = np.linalg.norm(gap, axis=2)  # (edges, frames)
    e, k = np.unravel_index(int(gap.argmax()), gap.shape)
    return {"gap": float(gap[e, k]), "time": float(times[k]), "edge": (int(a[e]), int(b[e])),
            "at": middle[e], "long": len(long), "longest": float(length[long].max()),
            "parted": int((gap.max(axis=1) > BENT * diagonal(V)).sum()), "tet_edge": h}


def warn_straight(anim, times: np.ndarray, where: str) -> str | None:
    """One warning when long surface edges part from the solid by more than :data:`BENT` of
    the body's size (:func:`straight_edges`), saying where, when and how far; its text."""
    note = straight_note(anim, times, where)
    if note is not None:
        warn(note)
    return note


def straight_note(anim, times: np.ndarray, where: str) -> str | None:
    """The text of :func:`warn_straight`'s warning (None: no edge parts), not warned."""
    worst = straight_edges(anim, times)
    if worst is None or not worst["parted"]:
        return None
    size = diagonal(anim.body.surface.vertices)
    at = ", ".join(f"{c:.3g}" for c in worst["at"])
    note = (f"{where}: the solid bends under {worst['parted']} of the surface's "
            f"{worst['long']} long edges (longer than {LONG_EDGE:g} tets of "
            f"{worst['tet_edge']:.3g} m; the longest {worst['longest']:.3g} m), which stay "
            f"straight: at t = {worst['time']:.3g} s the middle of the edge between surface "
            f"vertices {worst['edge'][0]} and {worst['edge'][1]}, around ({at}) m at rest, "
            f"lies {1e3 * worst['gap']:.3g} mm ({100 * worst['gap'] / size:.2g} % of the "
            "body's size) off the solid it rests on, and what is attached along such an "
            "edge (a leaf on a stalk) parts from it; subdivide the surface where it bends "
            "(Blender: Subdivide or Remesh)")
    return note
