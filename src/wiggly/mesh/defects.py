"""Stage 1, before meshing: what is unusual about a user's surface, how many tets it will
make, and the simplified envelope that fTetWild fills (used by :mod:`wiggly.mesh`).

A user's surface is delivered as it is, embedded in the tet mesh (Schulz et al. 2014); it only has
to be *filled* with tets. fTetWild (Hu et al. 2020) fills whatever a triangle soup encloses, by
generalized winding numbers, so open, non-manifold or self-intersecting surfaces can be filled too.
This module:

- welds coincident vertices, orients the triangles consistently, each shell by its nesting
  (winding numbers need it: a cavity's shell faces inwards), and counts what is unusual:
  open, non-manifold and misoriented edges, crossing triangle pairs
  (:func:`inspect_surface`, giving a :class:`SurfaceReport`);
- refuses only what cannot be filled: no triangles of positive area, no enclosed volume, or
  an open sheet (:func:`open_share`);
- estimates the tet count at a given edge length before any memory is spent
  (:func:`estimate_tets`, :func:`max_resolution`);
- simplifies a surface much finer than the tets to an envelope of about
  ``ENVELOPE_FACES_PER_AREA`` triangles per squared edge length (:func:`simplified_envelope`):
  the user's surface is embedded in the tet mesh anyway, and fTetWild's time grows with the
  number of input triangles (a 52k-triangle armadillo: over 300 s as is, 3.6 s simplified).

Arrays in, arrays out: ``V`` float64 (n, 3), ``F`` int64 (k, 3).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components
from scipy.spatial import cKDTree

from wiggly.errors import WigglyInputError, counted
from wiggly.mesh.data import used_only

__all__ = [
    "ENVELOPE_FACES_PER_AREA",
    "TETS_PER_AREA",
    "TETS_PER_VOLUME",
    "CheckedSurface",
    "SurfaceReport",
    "estimate_tets",
    "inspect_surface",
    "max_resolution",
    "orient",
    "self_intersections",
    "simplified_envelope",
]

#: Surface vertices closer than this times the bounding-box diagonal are welded.
WELD_TOLERANCE = 1e-6
#: A volume at most this times the cube of the bounding-box diagonal is zero.
DEGENERATE_VOLUME = 1e-12
#: fTetWild at edge length h makes about TETS_PER_VOLUME V / h^3 + TETS_PER_AREA A / h^2 tets
#: for enclosed volume V and area A.  Fitted on 16 public meshes at 25 and 40 edges per
#: diagonal (measured counts 0.68-1.0 times the estimate; a regular tet of edge h has volume
#: h^3 / 8.5).
TETS_PER_VOLUME = 10.0
TETS_PER_AREA = 6.0
#: Triangles per h^2 of surface area in the simplified envelope (about 0.9 h per triangle side).
ENVELOPE_FACES_PER_AREA = 3.0
#: A surface is simplified only when it has this many times more triangles than the envelope.
SIMPLIFY_ABOVE = 1.25


@dataclass(frozen=True)
class SurfaceReport:
    """What :func:`inspect_surface` found in a surface, in counts.

    Attributes
    ----------
    n_faces : triangles in the file.
    open_edges : edges used by one triangle only (holes, open borders).
    nonmanifold_edges : edges used by more than two triangles.
    misoriented_edges : edges whose two triangles run the same way along them (one of the two
        faces the wrong way).
    crossing_pairs : pairs of triangles that intersect (sharing no vertex, or folding over).
    zero_area_faces : triangles that lost a corner when coincident vertices were welded.
    outward_cavities : shells inside another shell (an odd number of shells deep) that faced
        outwards; they were turned inwards, so that the space inside them is a cavity.
    volume : enclosed volume (m^3), each connected piece oriented by its nesting (a cavity's
        volume is subtracted).
    area : surface area (m^2).
    diagonal : bounding-box diagonal (m).
    examples : one example per kind of defect ("the edge between vertices 3 and 7").
    """

    n_faces: int
    open_edges: int = 0
    nonmanifold_edges: int = 0
    misoriented_edges: int = 0
    crossing_pairs: int = 0
    zero_area_faces: int = 0
    outward_cavities: int = 0
    volume: float = 0.0
    area: float = 0.0
    diagonal: float = 0.0
    examples: dict[str, str] = field(default_factory=dict, compare=False)

    @property
    def clean(self) -> bool:
        """Closed, manifold, consistently oriented and free of self-intersections."""
        return not (self.open_edges or self.nonmanifold_edges or self.misoriented_edges
                    or self.crossing_pairs or self.outward_cavities)

    def defects(self, detailed: bool = False) -> list[str]:
        """One phrase per kind of defect ("6 open edges", ...); ``detailed`` adds what each
        means and an example."""
        kinds = [
            ("open", self.open_edges, counted(self.open_edges, "open edge"),
             "used by only one triangle: the surface has holes"),
            ("nonmanifold", self.nonmanifold_edges,
             counted(self.nonmanifold_edges, "non-manifold edge"),
             "used by more than two triangles"),
            ("misoriented", self.misoriented_edges,
             f"{counted(self.misoriented_edges, 'edge')} between triangles with opposite "
             "orientations", "one of the two triangles faces the wrong way"),
            ("crossing", self.crossing_pairs,
             f"{counted(self.crossing_pairs, 'pair')} of triangles that cross",
             "the surface intersects itself"),
            ("cavity", self.outward_cavities,
             f"{counted(self.outward_cavities, 'inner shell')} facing outwards, made "
             f"{'a cavity' if self.outward_cavities == 1 else 'cavities'} (the space inside "
             f"{'it' if self.outward_cavities == 1 else 'them'} is left empty; remove "
             f"{'it' if self.outward_cavities == 1 else 'them'} for a solid body)",
             "a closed shell inside another bounds a hole in the solid"),
        ]
        out = []
        for key, count, short, meaning in kinds:
            if count:
                example = self.examples.get(key)
                out.append(f"{short} ({meaning}; e.g. {example})" if detailed and example
                           else short)
        return out


@dataclass(eq=False)
class CheckedSurface:
    """A surface ready for fTetWild: ``faces`` index the original ``vertices`` (welded
    duplicates point to one of them), triangles of zero area are left out and every piece
    is consistently oriented outwards as far as its edges allow."""

    vertices: np.ndarray
    faces: np.ndarray
    report: SurfaceReport


def diagonal(V: np.ndarray) -> float:
    """Length of the bounding-box diagonal of ``V``."""
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) if len(V) else 0.0


def surface_area(V: np.ndarray, F: np.ndarray) -> float:
    """The area of the triangles F (m^2)."""
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return 0.5 * float(np.linalg.norm(cross, axis=1).sum())


def enclosed_volume(V: np.ndarray, F: np.ndarray) -> float:
    """The signed volume the triangles F enclose (m^3): positive when they face outwards.
    Summed about the centre of the triangles' bounding box: about the origin, a body far
    from it (1e5 m away) would sum products of its absolute coordinates, and rounding would
    swamp its volume, even its sign."""
    if len(F) == 0:
        return 0.0
    used = V[np.unique(F)]
    X = V - 0.5 * (used.min(axis=0) + used.max(axis=0))
    return float(np.einsum("ij,ij->", X[F[:, 0]], np.cross(X[F[:, 1]], X[F[:, 2]]))) / 6


def weld(V: np.ndarray, tol: float) -> np.ndarray:
    """For each vertex, the smallest index of the vertices within ``tol`` of it (transitively)."""
    n = len(V)
    pairs = cKDTree(V).query_pairs(tol, output_type="ndarray") if tol > 0 else np.empty((0, 2))
    if len(pairs) == 0:
        return np.arange(n)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_labels, labels = connected_components(graph, directed=False)
    representative = np.full(n_labels, n)
    np.minimum.at(representative, labels, np.arange(n))
    return representative[labels]


def inspect_surface(V: np.ndarray, F: np.ndarray, source: str = "surface") -> CheckedSurface:
    """Weld, orient and count the defects of a triangle surface (module docstring).

    ``V`` must be finite and ``F`` in range (checked by :mod:`wiggly.mesh`).  Coincident
    vertices (within ``1e-6`` of the bounding-box diagonal) are welded, so UV seams and STL's
    unshared corners are no defect.

    Raises
    ------
    WigglyInputError
        Every triangle has zero area, or the surface encloses no volume (all triangles in one
        plane): nothing can be filled.
    """
    used = np.unique(F)
    diag = diagonal(V[used])
    rep = weld(V, WELD_TOLERANCE * diag)
    W = rep[F]
    kept = np.flatnonzero((W[:, 0] != W[:, 1]) & (W[:, 1] != W[:, 2]) & (W[:, 2] != W[:, 0]))
    W = W[kept]
    if len(W) == 0:
        raise WigglyInputError(
            f"{source}: all {counted(len(F), 'triangle')} have zero area (each has two corners "
            "at the same point); wiggly needs a surface that encloses a solid.")
    n = len(V)
    half = W[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lo, hi = half.min(axis=1), half.max(axis=1)
    edges, inverse, counts = np.unique(lo * n + hi, return_inverse=True, return_counts=True)
    examples: dict[str, str] = {}

    def example(mask: np.ndarray, key: str) -> int:
        if mask.any():
            a, b = divmod(int(edges[np.flatnonzero(mask)[0]]), n)
            examples[key] = f"the edge between vertices {a} and {b}"
        return int(mask.sum())

    n_open = example(counts == 1, "open")
    n_nonmanifold = example(counts > 2, "nonmanifold")
    W, misoriented, cavities = orient(V, W, half, inverse, counts)
    if cavities:
        examples["cavity"] = f"the shell of vertex {int(W[cavities[0]].min())}"
    if len(misoriented):
        a, b = divmod(int(edges[misoriented[0]]), n)
        examples["misoriented"] = f"the edge between vertices {a} and {b}"
    tri = V[W]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * float(np.linalg.norm(cross, axis=1).sum())
    volume = float(np.einsum("ij,ij->", tri[:, 0] - tri.reshape(-1, 3).mean(axis=0), cross)) / 6
    if abs(volume) <= DEGENERATE_VOLUME * diag**3:
        raise WigglyInputError(
            f"{source}: the surface encloses no volume ({volume:.3g} m^3): its triangles lie in "
            "one plane or fold flat onto each other. wiggly animates solids: give a surface "
            "that bounds one (a sheet needs a thickness).")
    if n_open:
        share = open_share(V, W)
        if share > SHEET_SHARE:
            raise WigglyInputError(
                f"{source}: the surface is an open sheet, not the skin of a solid: its "
                f"{counted(n_open, 'open edge')} bound holes whose area is {100 * share:.0f} % "
                "of the surface's own, so it encloses no volume that could be filled. wiggly "
                "animates solids: give the sheet a thickness (e.g. Blender's Solidify "
                "modifier) or close it, and export it again.")
    pairs = self_intersections(V, W)
    if len(pairs):
        i, j = kept[pairs[0]]
        examples["crossing"] = f"faces {i} and {j}"
    report = SurfaceReport(
        n_faces=len(F), open_edges=n_open, nonmanifold_edges=n_nonmanifold,
        misoriented_edges=len(misoriented), crossing_pairs=len(pairs),
        zero_area_faces=len(F) - len(kept), outward_cavities=len(cavities),
        volume=abs(volume), area=area, diagonal=diag,
        examples=examples)
    return CheckedSurface(V, W, report)


#: An open surface whose holes' area (:func:`open_share`) exceeds this share of its own area
#: is a sheet, refused: a wavy cloth has 0.94, a hemispherical bowl 0.5, an open box 0.2.
SHEET_SHARE = 0.6


def open_share(V: np.ndarray, W: np.ndarray) -> float:
    """The area of the holes of the oriented triangles W over their own area: the holes'
    vector areas (one per connected chain of open edges, half the sum of ``a x b`` over its
    edges a -> b), which no surface spanning a hole is smaller than.  0 for a closed
    surface, small for a solid with holes, near 1 for a sheet."""
    n = len(V)
    half = W[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = half.min(axis=1) * n + half.max(axis=1)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    edges = half[counts[inverse] == 1]
    area = surface_area(V, W)
    if len(edges) == 0 or area <= 0:
        return 0.0
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, chain = connected_components(graph, directed=False)
    chain = np.unique(chain[edges[:, 0]], return_inverse=True)[1]
    P = V[edges]
    centre = np.zeros((chain.max() + 1, 3))
    np.add.at(centre, chain, P.mean(axis=1))
    centre /= np.bincount(chain)[:, None]  # about each chain's centre: no far-origin rounding
    moment = np.cross(P[:, 0] - centre[chain], P[:, 1] - centre[chain])
    vector = np.zeros_like(centre)
    np.add.at(vector, chain, 0.5 * moment)
    return float(np.linalg.norm(vector, axis=1).sum()) / area


def orient(V: np.ndarray, W: np.ndarray, half: np.ndarray, edge_of_half: np.ndarray,
           edge_counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Orient triangles consistently across manifold edges, each connected piece by its
    nesting: outwards, or inwards when it lies inside an odd number of other pieces (the
    inner shell of a hollow ball faces into its cavity), so that the winding number is 1 in
    the solid and 0 in the cavity (and outside).

    Two triangles sharing a manifold edge agree when they run along it in opposite directions.
    A breadth-first walk over the triangles flips every triangle to agree with the one it was
    reached from; then every piece whose signed volume (about its centroid) has the wrong sign
    for its nesting depth (:func:`nesting_depths`) is flipped whole.  A non-orientable piece
    (a Moebius strip) keeps some disagreeing edges.

    Parameters
    ----------
    V, W : vertices and welded triangles (no zero-area ones).
    half : (3k, 2) the directed edges of ``W``, three per triangle.
    edge_of_half, edge_counts : the undirected edge of each half-edge, and each edge's use count.

    Returns
    -------
    oriented : (k, 3) the triangles, some reversed.
    misoriented : indices of the manifold edges whose two triangles disagreed in ``W``.
    cavities : one triangle of each piece at an odd depth that mostly faced outwards in
        ``W`` (by area), now turned inwards.
    """
    k = len(W)
    manifold = np.flatnonzero(edge_counts[edge_of_half] == 2)
    order = manifold[np.argsort(edge_of_half[manifold], kind="stable")]
    h1, h2 = order[0::2], order[1::2]  # the two half-edges of every manifold edge
    same_way = half[h1, 0] == half[h2, 0]
    f1, f2 = h1 // 3, h2 // 3
    misoriented = np.unique(edge_of_half[h1[same_way]])
    # relation +1: the two triangles must be flipped relative to each other, -1: they agree
    # (summed over the edges two triangles share); node k is a root joined to one triangle
    # per connected piece, so that one breadth-first walk reaches every piece
    rows, cols = np.r_[f1, f2], np.r_[f2, f1]
    relation = sp.coo_matrix((np.tile(np.where(same_way, 1.0, -1.0), 2), (rows, cols)),
                             shape=(k, k)).tocsr()
    adjacency = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(k, k)).tocsr()
    n_pieces, piece = connected_components(adjacency, directed=False)
    firsts = np.unique(piece, return_index=True)[1]
    root = sp.coo_matrix((np.ones(n_pieces), (firsts, np.zeros(n_pieces))), shape=(k, 1))
    graph = sp.bmat([[adjacency, root], [root.T, None]], format="csr")
    walk, parent = breadth_first_order(graph, k, directed=False, return_predecessors=True)
    walk = walk[1:]  # the root first
    flip_step = np.zeros(k + 1, dtype=bool)
    inner = walk[parent[walk] < k]
    if len(inner):
        flip_step[inner] = np.asarray(relation[inner, parent[inner]]).ravel() > 0
    flip = np.zeros(k + 1, dtype=bool)
    for f, p, step in zip(walk.tolist(), parent[walk].tolist(), flip_step[walk].tolist(),
                          strict=True):
        flip[f] = flip[p] ^ step
    flip = flip[:k]
    oriented = np.where(flip[:, None], W[:, ::-1], W)
    tri = V[oriented]
    centre = np.zeros((n_pieces, 3))
    np.add.at(centre, piece, tri.mean(axis=1))
    centre /= np.bincount(piece, minlength=n_pieces)[:, None]
    c = centre[piece]
    signed = np.einsum("ij,ij->i", tri[:, 0] - c, np.cross(tri[:, 1] - c, tri[:, 2] - c))
    volume = np.bincount(piece, weights=signed, minlength=n_pieces)
    odd = nesting_depths(V, oriented, piece, n_pieces) % 2 == 1
    turn = np.where(odd, volume > 0, volume < 0)
    oriented = np.where(turn[piece][:, None], oriented[:, ::-1], oriented)
    # the pieces at odd depths that mostly faced outwards in the input (by area)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    reversed_area = np.bincount(piece, weights=area * (flip ^ turn[piece]),
                                minlength=n_pieces)
    total = np.bincount(piece, weights=area, minlength=n_pieces)
    outward = np.flatnonzero(odd & (reversed_area > 0.5 * total))
    firsts = np.unique(piece, return_index=True)[1]
    return oriented, misoriented, [int(firsts[p]) for p in outward]


#: Points of a piece (its triangles' centroids) tested to tell whether it lies inside another.
NESTING_SAMPLES = 32


def nesting_depths(V: np.ndarray, F: np.ndarray, piece: np.ndarray,
                   n_pieces: int) -> np.ndarray:
    """How many other pieces each piece of the triangles F lies inside: piece p lies inside
    piece q when p's bounding box lies strictly inside q's and the winding number of q
    (:func:`winding_numbers`, by absolute value) exceeds 1/2 at up to ``NESTING_SAMPLES`` of
    p's triangle centroids, all of them (a piece that only overlaps q is not inside it)."""
    depth = np.zeros(n_pieces, dtype=np.int64)
    if n_pieces < 2:
        return depth
    tri = V[F]
    lo = np.full((n_pieces, 3), np.inf)
    hi = np.full((n_pieces, 3), -np.inf)
    np.minimum.at(lo, piece, tri.min(axis=1))
    np.maximum.at(hi, piece, tri.max(axis=1))
    order = np.argsort(piece, kind="stable")
    starts = np.searchsorted(piece[order], np.arange(n_pieces + 1))
    centroid = tri.mean(axis=1)
    for q in range(n_pieces):
        inner = np.flatnonzero(np.all(lo > lo[q], axis=1) & np.all(hi < hi[q], axis=1))
        if len(inner) == 0:
            continue
        samples = [order[starts[p]:starts[p + 1]] for p in inner]
        samples = [f[np.linspace(0, len(f) - 1, min(len(f), NESTING_SAMPLES)).astype(int)]
                   for f in samples]
        w = np.abs(winding_numbers(centroid[np.concatenate(samples)], V,
                                   F[order[starts[q]:starts[q + 1]]]))
        bounds = np.cumsum([0] + [len(f) for f in samples])
        for p, a, b in zip(inner, bounds[:-1], bounds[1:], strict=True):
            depth[p] += bool(np.all(w[a:b] > 0.5))
    return depth


def winding_numbers(P: np.ndarray, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """The generalized winding number of the triangles F at each point P (Jacobson et al.
    2013): their solid angles (van Oosterom and Strackee 1983) over 4 pi; 1 inside a closed
    outward surface, 0 outside, in between near the holes of an open one."""
    out = np.empty(len(P))
    A0, B0, C0 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    chunk = max(1, 200_000 // max(len(F), 1))
    for s in range(0, len(P), chunk):
        p = P[s:s + chunk, None, :]
        A, B, C = A0 - p, B0 - p, C0 - p
        a, b, c = (np.linalg.norm(X, axis=2) for X in (A, B, C))
        det = np.einsum("pki,pki->pk", A, np.cross(B, C))
        den = (a * b * c + np.einsum("pki,pki->pk", A, B) * c
               + np.einsum("pki,pki->pk", B, C) * a + np.einsum("pki,pki->pk", C, A) * b)
        out[s:s + chunk] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


def self_intersections(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Pairs of intersecting triangles ``(q, 2)`` of a welded surface, ``i < j``.

    With libigl's exact predicates (``igl.predicates.find_self_intersections``, MPL-2.0, a
    dependency: 1 s for 800k triangles); where libigl cannot be imported, with VTK's
    ``vtkCollisionDetectionFilter`` (VTK ships with pyvista), which reports every pair of
    touching neighbours before they are dropped (530 s for those 800k triangles) and so cannot
    see a fold between neighbouring triangles either.
    """
    try:
        import igl.predicates
    except ImportError:
        return _self_intersections_vtk(V, F)
    found, pairs, _ = igl.predicates.find_self_intersections(
        np.ascontiguousarray(V), np.ascontiguousarray(F)
    )
    return (np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1) if found
            else np.empty((0, 2), dtype=np.int64))


def _self_intersections_vtk(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Self-intersections with VTK's collision filter, ignoring triangles that share a vertex."""
    import pyvista as pv
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonMath import vtkMatrix4x4
    from vtkmodules.vtkFiltersModeling import vtkCollisionDetectionFilter

    poly = pv.PolyData.from_regular_faces(V, F)
    collide = vtkCollisionDetectionFilter()
    identity = vtkMatrix4x4()
    for port in (0, 1):
        collide.SetInputData(port, poly)
        collide.SetMatrix(port, identity)
    collide.SetCollisionModeToAllContacts()
    collide.SetBoxTolerance(0.0)
    collide.SetCellTolerance(0.0)
    collide.GenerateScalarsOff()
    collide.Update()
    contacts = [collide.GetOutput(port).GetFieldData().GetArray("ContactCells") for port in (0, 1)]
    if contacts[0] is None or contacts[1] is None:
        return np.empty((0, 2), dtype=np.int64)
    pairs = np.stack([vtk_to_numpy(c) for c in contacts], axis=1).astype(np.int64)
    pairs = pairs[pairs[:, 0] < pairs[:, 1]]
    shares_vertex = (F[pairs[:, 0], :, None] == F[pairs[:, 1], None, :]).any(axis=(1, 2))
    pairs = pairs[~shares_vertex]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def estimate_tets(volume: float, area: float, edge_length: float) -> float:
    """About how many tets fTetWild makes at ``edge_length`` (see :data:`TETS_PER_VOLUME`)."""
    return TETS_PER_VOLUME * volume / edge_length**3 + TETS_PER_AREA * area / edge_length**2


def max_resolution(volume: float, area: float, diag: float, max_tets: float) -> int:
    """The largest resolution (edges per diagonal) whose :func:`estimate_tets` is within
    ``max_tets``."""
    a, b = TETS_PER_VOLUME * volume / diag**3, TETS_PER_AREA * area / diag**2
    r = max_tets ** (1 / 3) / max(a, 1e-300) ** (1 / 3)
    for _ in range(60):  # Newton on a r^3 + b r^2 = max_tets, from above (convex, increasing)
        r -= (a * r**3 + b * r**2 - max_tets) / (3 * a * r**2 + 2 * b * r)
    return int(np.floor(r + 1e-9))


def simplified_envelope(V: np.ndarray, F: np.ndarray, edge_length: float,
                        area: float) -> tuple[np.ndarray, np.ndarray] | None:
    """A simplification of the surface to about ``ENVELOPE_FACES_PER_AREA * area /
    edge_length^2`` triangles (quadric decimation, VTK), or None when the surface is not
    ``SIMPLIFY_ABOVE`` times finer than that (or decimation fails).  Deterministic."""
    target = max(int(ENVELOPE_FACES_PER_AREA * area / edge_length**2), 100)
    if len(F) <= SIMPLIFY_ABOVE * target:
        return None
    import pyvista as pv

    poly = pv.PolyData.from_regular_faces(*used_only(V, F))
    simple = poly.decimate(1.0 - target / len(F))
    if simple.n_cells < 4 or not simple.is_all_triangles:
        return None
    return np.asarray(simple.points, dtype=np.float64), simple.regular_faces.astype(np.int64)
