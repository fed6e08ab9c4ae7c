"""Mesh data: the simulation tet mesh, the user's surface, the barycentric embedding of one
in the other, and the model holding them.

Conventions: vertices ``V`` float64 ``(n, 3)`` in metres, tetrahedra ``T`` int64 ``(m, 4)``
positively oriented (``det[v1 - v0, v2 - v0, v3 - v0] > 0``), triangles ``F`` int64 ``(k, 3)``,
outward oriented (counter-clockwise seen from outside).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import meshio
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from wiggly import checks
from wiggly.errors import WigglyInputError

#: Surface formats, read with trimesh.
SURFACE_EXTENSIONS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
#: Volume (and surface) formats, read with meshio.
VOLUME_EXTENSIONS = tuple(
    sorted(
        ext
        for ext in meshio.extension_to_filetypes
        if ext not in SURFACE_EXTENSIONS and ext not in (".svg", ".wkt")
    )
)

#: fTetWild's envelope (how far the tet mesh boundary may be from the surface), in edge lengths.
ENVELOPE_PER_EDGE = 0.1
#: Default target number of tet edges along the bounding-box diagonal in :func:`tetrahedralize`.
DEFAULT_RESOLUTION = 25

# Faces of a positively oriented tet (v0, v1, v2, v3), each ordered so that its
# normal points out of the tet; face i is opposite vertex i.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
#: meshio cell types of volume meshes other than linear tets (refused by the loader, by name)
VOLUME_CELLS = {"tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "pyramid"}
#: The dimension of meshio's cell types of linear meshes
CELL_DIMENSION = {"vertex": 0, "line": 1, "triangle": 2, "quad": 2, "tetra": 3}


# --------------------------------------------------------------------------- data


@dataclass(eq=False)
class TetMesh:
    """A linear tetrahedral mesh, the simulation mesh of the FEM stage.

    Parameters
    ----------
    vertices : ndarray, shape (n, 3)
        Vertex positions in metres.
    tets : ndarray, shape (m, 4)
        Vertex indices of each tetrahedron, positively oriented after
        :func:`check_tet_mesh`.
    groups : dict of str to ndarray
        Named vertex sets from the file (physical groups, cell/point sets,
        0/1 point data), as sorted vertex indices.
    """

    vertices: np.ndarray
    tets: np.ndarray
    groups: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = checks.array(self.vertices, "TetMesh.vertices", 3, np.float64)
        self.tets = checks.array(self.tets, "TetMesh.tets", 4, np.int64)
        self.groups = _as_groups(self.groups)

    def __repr__(self) -> str:  # a summary: the arrays are attributes
        return f"TetMesh({self.n_vertices} vertices, {self.n_tets} tets)"

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return len(self.vertices)

    @property
    def n_tets(self) -> int:
        """Number of tetrahedra ``m``."""
        return len(self.tets)

    @property
    def n_components(self) -> int:
        """Number of connected pieces (tets sharing a vertex are connected)."""
        return _count_components(self.tets, self.n_vertices)

    def volumes(self) -> np.ndarray:
        """Signed volume of every tet, ``det[v1 - v0, v2 - v0, v3 - v0] / 6``.

        Returns
        -------
        ndarray, shape (m,)
            Positive for a checked mesh (see :func:`check_tet_mesh`).
        """
        return tet_volumes(self.vertices, self.tets)

    def edge_lengths(self) -> np.ndarray:
        """Length of each tet's six edges, (m, 6) (an edge shared by tets once per tet)."""
        V, T = self.vertices, self.tets
        return np.linalg.norm(V[T[:, [0, 0, 0, 1, 1, 2]]] - V[T[:, [1, 2, 3, 2, 3, 3]]],
                              axis=-1)

    def boundary_faces(self) -> np.ndarray:
        """Triangles used by exactly one tet, oriented outwards.

        Returns
        -------
        ndarray, shape (k, 3)
            Vertex indices; outward if the tets are positively oriented.
        """
        faces = self.tets[:, _TET_FACES].reshape(-1, 3)
        _, inverse, counts = _unique_rows(np.sort(faces, axis=1))
        return faces[counts[inverse] == 1]


@dataclass(eq=False)
class Surface:
    """The user's triangle surface, exactly as in the file.

    Parameters
    ----------
    vertices : ndarray, shape (n, 3)
        Vertex positions in the file's order.
    faces : ndarray, shape (k, 3)
        Triangles (polygons of the file are split into triangles by trimesh).
    uvs : ndarray, shape (n, 2), optional
        Per-vertex texture coordinates, when the file has them and they are
        unambiguous (see :func:`load_mesh` for UV seams).
    normals : ndarray, shape (n, 3), optional
        Per-vertex normals, when the file has them and they are unambiguous.
    groups : dict of str to ndarray
        Named vertex sets (glTF node names, meshio sets), as vertex indices.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    groups: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = checks.array(self.vertices, "Surface.vertices", 3, np.float64)
        self.faces = checks.array(self.faces, "Surface.faces", 3, np.int64)
        n = len(self.vertices)
        if self.uvs is not None:
            self.uvs = checks.array(self.uvs, "Surface.uvs", 2, np.float64, rows=n)
        if self.normals is not None:
            self.normals = checks.array(self.normals, "Surface.normals", 3, np.float64, rows=n)
        self.groups = _as_groups(self.groups)

    def __repr__(self) -> str:
        groups = f", groups {', '.join(self.groups)}" if self.groups else ""
        return f"Surface({self.n_vertices} vertices, {self.n_faces} triangles{groups})"

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        """Number of triangles ``k``."""
        return len(self.faces)


@dataclass(eq=False)
class Embedding:
    """Barycentric coordinates of points in a tet mesh.

    Point ``i`` is ``sum_j barycentric[i, j] * V[vertex_indices[i, j]]`` with
    ``vertex_indices[i] = T[tet_index[i]]``. Coordinates may be slightly
    negative for points outside the mesh: the tet's affine map is then
    extrapolated linearly, so any affine motion of the mesh is reproduced
    exactly at every point.

    Parameters
    ----------
    tet_index : ndarray, shape (p,)
        The tet carrying each point.
    barycentric : ndarray, shape (p, 4)
        Barycentric coordinates in that tet; each row sums to 1.
    vertex_indices : ndarray, shape (p, 4)
        The tet's vertex indices, ``T[tet_index]``.
    """

    tet_index: np.ndarray
    barycentric: np.ndarray
    vertex_indices: np.ndarray

    @property
    def n_points(self) -> int:
        """Number of embedded points ``p``."""
        return len(self.tet_index)

    def matrix(self, n_vertices: int) -> sp.csr_matrix:
        """Interpolation matrix ``B`` with ``points = B @ V``.

        Parameters
        ----------
        n_vertices : int
            Number of tet mesh vertices ``n``.

        Returns
        -------
        scipy.sparse.csr_matrix, shape (p, n)
            Four entries per row, the barycentric coordinates.
        """
        p = self.n_points
        indptr = np.arange(0, 4 * p + 1, 4)
        return sp.csr_matrix(
            (self.barycentric.ravel(), self.vertex_indices.ravel(), indptr), shape=(p, n_vertices)
        )

    def dof_matrix(self, n_vertices: int) -> sp.csr_matrix:
        """Interpolation matrix for interleaved xyz degrees of freedom.

        Parameters
        ----------
        n_vertices : int
            Number of tet mesh vertices ``n``.

        Returns
        -------
        scipy.sparse.csr_matrix, shape (3p, 3n)
            ``kron(B, I3)``: maps ``u`` with dof ``3 * j + c`` (vertex ``j``,
            coordinate ``c``) to point dofs ``3 * i + c``.
        """
        return sp.kron(self.matrix(n_vertices), sp.eye(3), format="csr")

    def outside_distance(self, mesh: TetMesh) -> np.ndarray:
        """How far each point lies outside its tet (0 inside), in metres: the largest
        ``-lambda_i * h_i`` over the tet's faces, ``h_i`` the tet's height over face i.

        Returns
        -------
        ndarray, shape (p,)
        """
        T = mesh.tets[self.tet_index]
        V = mesh.vertices
        volume = np.abs(tet_volumes(V, T))
        faces = V[T[:, _TET_FACES]]  # (p, 4, 3, 3): face i opposite vertex i
        area = 0.5 * np.linalg.norm(np.cross(faces[:, :, 1] - faces[:, :, 0],
                                             faces[:, :, 2] - faces[:, :, 0]), axis=-1)
        height = 3 * volume[:, None] / np.maximum(area, 1e-300)
        return np.maximum(-self.barycentric * height, 0.0).max(axis=1)


@dataclass(eq=False)
class Model:
    """A loaded model: the user's surface, the simulation tet mesh and the embedding.

    Parameters
    ----------
    surface : Surface or None
        What the animation is delivered on. For a surface file it is the
        user's surface as loaded; for a tet mesh file it has all the tet mesh
        vertices (same indices) and the tet mesh's boundary faces.
    tets : TetMesh
        The simulation mesh.
    embedding : Embedding or None
        Surface vertices in ``tets`` (``surface.vertices == embedding.matrix(n) @ tets.vertices``).
    source : str
        Where the model came from (a path).
    """

    surface: Surface | None
    tets: TetMesh
    embedding: Embedding | None
    source: str

    def __repr__(self) -> str:
        surface = "" if self.surface is None else f", {self.surface.n_vertices} surface vertices"
        return f"Model({self.source}: {self.tets.n_tets} tets{surface})"



# --------------------------------------------------------------------------- helpers


def _as_groups(groups: dict) -> dict[str, np.ndarray]:
    """Groups as a dict of str to flat int64 index arrays."""
    return {str(k): np.asarray(v, dtype=np.int64).ravel() for k, v in groups.items()}


def check_surface_arrays(surface: Surface, source: str) -> None:
    """Raise for an empty surface, non-finite coordinates or out-of-range face indices."""
    if surface.n_faces == 0:
        raise WigglyInputError(f"{source}: the surface has no triangles.")
    checks.finite_vertices(surface.vertices, source)
    checks.indices_in_range(surface.faces, surface.n_vertices, source, "face")


def tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed tet volumes ``det[v1 - v0, v2 - v0, v3 - v0] / 6``."""
    e = V[T[:, 1:]] - V[T[:, :1]]
    return np.einsum("ij,ij->i", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0)`` with inverse and counts, fast for small non-negative ints."""
    top = int(rows.max()) + 1 if rows.size else 1
    if top ** rows.shape[1] < 2**62:
        keys = np.zeros(len(rows), dtype=np.int64)
        for column in rows.T:
            keys = keys * top + column
        _, first, inverse, counts = np.unique(
            keys, return_index=True, return_inverse=True, return_counts=True
        )
        return rows[first], inverse, counts
    return np.unique(rows, axis=0, return_inverse=True, return_counts=True)


def used_only(V: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices that ``cells`` (faces or tets, vertex indices) use, and the cells
    renumbered to them (in the vertices' order)."""
    used = np.unique(cells)
    compact = np.zeros(len(V), dtype=np.int64)
    compact[used] = np.arange(len(used))
    return V[used], compact[cells]


def solid_pieces(mesh: TetMesh) -> tuple[np.ndarray, np.ndarray]:
    """The pieces of a tet mesh that hold together as solids: tets sharing a *face* are one
    piece (tets touching only at an edge or a vertex hinge there, a motion that costs no
    elastic energy).  Returns each tet's piece label (m,) and each piece's volume."""
    m = mesh.n_tets
    faces = np.sort(mesh.tets[:, _TET_FACES].reshape(-1, 3), axis=1)
    _, inverse, counts = _unique_rows(faces)
    order = np.argsort(inverse, kind="stable")
    shared = order[counts[inverse[order]] == 2]  # faces of two tets, side by side
    pairs = shared.reshape(-1, 2) // 4
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    _, labels = connected_components(graph, directed=False)
    return labels, np.bincount(labels, weights=np.abs(mesh.volumes()))


def without_small_pieces(mesh: TetMesh, fraction: float) -> tuple[TetMesh, int, float]:
    """``mesh`` without its solid pieces (:func:`solid_pieces`) of less than ``fraction`` of
    its volume (unused vertices removed); also how many pieces went and their share of the
    volume.  A mesh of one piece is returned as it is."""
    labels, volume = solid_pieces(mesh)
    small = volume < fraction * volume.sum()
    if len(volume) == 1 or not small.any() or small.all():
        return mesh, 0, 0.0
    V, T = used_only(mesh.vertices, mesh.tets[~small[labels]])
    return TetMesh(V, T), int(small.sum()), float(volume[small].sum() / volume.sum())


def _count_components(T: np.ndarray, n: int) -> int:
    """Number of connected components of the tets (vertex-sharing tets are connected)."""
    if len(T) == 0:
        return 0
    rows = np.repeat(T[:, 0], 3)
    cols = T[:, 1:].ravel()
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[np.unique(T)]))


def embed(points: np.ndarray, mesh: TetMesh) -> Embedding:
    """Barycentric embedding of points in a tet mesh.

    Each point gets the tet that contains it. A point outside the mesh (the
    tet mesh only approximates the user's surface, so some surface vertices
    lie slightly outside) gets the nearby tet whose smallest barycentric
    coordinate is the least negative, and keeps its raw coordinates, so the
    tet's affine map is extrapolated linearly: any affine motion of the mesh
    vertices moves every embedded point exactly affinely.

    Candidates are the tets with the 16 nearest centroids (a k-d tree); for
    points that none of them contains, the 64 nearest. A point inside the mesh
    whose containing tet is not among these (only in badly graded meshes) is
    treated as outside.

    Parameters
    ----------
    points : ndarray, shape (p, 3)
        Points to embed, e.g. the surface vertices.
    mesh : TetMesh
        The tet mesh (positively oriented or not).

    Returns
    -------
    Embedding
    """
    P = checks.array(points, "points", 3, np.float64)
    V, T = mesh.vertices, mesh.tets
    if len(T) == 0:
        raise WigglyInputError("embed: the tet mesh has no tetrahedra.")
    origin = V[T[:, 0]]
    edges = (V[T[:, 1:]] - origin[:, None, :]).transpose(0, 2, 1)  # columns v1-v0, v2-v0, v3-v0
    inverse = np.linalg.inv(edges)
    tree = cKDTree(V[T].mean(axis=1))
    tet_index = np.zeros(len(P), dtype=np.int64)
    bary = np.zeros((len(P), 4))
    todo = np.arange(len(P))
    for k in (16, 64):
        k = min(k, len(T))
        for chunk in np.array_split(todo, max(1, len(todo) // 20000)):
            if len(chunk) == 0:
                continue
            _, cand = tree.query(P[chunk], k=k)
            cand = cand.reshape(len(chunk), k)
            lam = np.einsum("pkij,pkj->pki", inverse[cand], P[chunk, None, :] - origin[cand])
            lam = np.concatenate([1 - lam.sum(axis=2, keepdims=True), lam], axis=2)
            best = lam.min(axis=2).argmax(axis=1)
            rows = np.arange(len(chunk))
            tet_index[chunk] = cand[rows, best]
            bary[chunk] = lam[rows, best]
        todo = todo[bary[todo].min(axis=1) < -1e-12]
        if k == len(T) or len(todo) == 0:
            break
    return Embedding(tet_index, bary, T[tet_index])
