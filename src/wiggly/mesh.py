"""Stage 1 of the pipeline: the user's model, its tetrahedral mesh and the embedding between them.

A user brings either a closed triangle surface (OBJ, PLY, STL, OFF, glTF) or a
tetrahedral mesh (MSH, VTU, MESH, ...), see ``reference/SYSTEM.md`` section 1.
A surface is checked (closed, consistently oriented, not self-intersecting),
filled with linear tetrahedra by fTetWild (:func:`tetrahedralize`) and its
vertices are embedded in the tetrahedra with barycentric coordinates
(:func:`embed`), so the animation computed on the tet mesh is delivered on the
user's own surface: same vertices, same order, same faces.

Conventions: vertices ``V`` float64 ``(n, 3)`` in metres, tetrahedra ``T`` int64
``(m, 4)`` positively oriented (``det[v1 - v0, v2 - v0, v3 - v0] > 0``),
triangles ``F`` int64 ``(k, 3)``, outward oriented (counter-clockwise seen from
outside).
"""

from __future__ import annotations

import hashlib
import os
import signal
import tempfile
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import meshio
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from wiggly.errors import WigglyInputError
from wiggly.files import atomic_file, default_cache_dir
from wiggly.progress import activity

__all__ = [
    "SURFACE_EXTENSIONS",
    "VOLUME_EXTENSIONS",
    "Embedding",
    "Model",
    "Surface",
    "TetMesh",
    "check_surface",
    "check_tet_mesh",
    "coarse_mesh",
    "embed",
    "load_mesh",
    "load_model",
    "tetrahedralize",
]

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

#: A tet whose volume is at most this times the cube of the bounding-box diagonal is degenerate.
DEGENERATE_VOLUME = 1e-12
#: Surface vertices closer than this times the bounding-box diagonal are welded.
WELD_TOLERANCE = 1e-6
#: fTetWild's envelope (how far the tet mesh boundary may be from the surface), in edge lengths.
ENVELOPE_PER_EDGE = 0.1
#: Default target number of tet edges along the bounding-box diagonal in :func:`tetrahedralize`.
DEFAULT_RESOLUTION = 25

# Faces of a positively oriented tet (v0, v1, v2, v3), each ordered so that its
# normal points out of the tet; face i is opposite vertex i.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_VOLUME_CELLS = {"tetra10", "hexahedron", "hexahedron20", "hexahedron27", "wedge", "pyramid"}
_CELL_DIMENSION = {"vertex": 0, "line": 1, "triangle": 2, "quad": 2, "tetra": 3}


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
        self.vertices = _as_array(self.vertices, np.float64, 3, "TetMesh.vertices")
        self.tets = _as_array(self.tets, np.int64, 4, "TetMesh.tets")
        self.groups = _as_groups(self.groups)

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
        return _tet_volumes(self.vertices, self.tets)

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
        self.vertices = _as_array(self.vertices, np.float64, 3, "Surface.vertices")
        self.faces = _as_array(self.faces, np.int64, 3, "Surface.faces")
        n = len(self.vertices)
        if self.uvs is not None:
            self.uvs = _as_array(self.uvs, np.float64, 2, "Surface.uvs", rows=n)
        if self.normals is not None:
            self.normals = _as_array(self.normals, np.float64, 3, "Surface.normals", rows=n)
        self.groups = _as_groups(self.groups)

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


# --------------------------------------------------------------------------- checks


def check_tet_mesh(mesh: TetMesh, source: str = "tet mesh") -> TetMesh:
    """Validate a tet mesh and orient every tet positively.

    Parameters
    ----------
    mesh : TetMesh
        The mesh to check.
    source : str
        Name used in error messages (usually the file path).

    Returns
    -------
    TetMesh
        The same vertices and groups, with tets whose volume was negative
        re-ordered (vertices 2 and 3 swapped) so that all volumes are positive.

    Raises
    ------
    WigglyInputError
        No tets; NaN or infinite coordinates; an index out of range; a
        degenerate tet (volume at most ``1e-12 * diagonal**3``); a group index
        out of range. Unreferenced vertices are allowed and kept.
    """
    V, T = mesh.vertices, mesh.tets
    n = len(V)
    if len(T) == 0:
        raise WigglyInputError(f"{source}: the mesh has no tetrahedra; at least one is needed.")
    _check_finite(V, source)
    _check_indices(T, n, source, "tet")
    for name, idx in mesh.groups.items():
        _check_indices(idx[:, None], n, source, f"group {name!r} entry")
    vol = _tet_volumes(V, T)
    used = V[np.unique(T)]
    diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    limit = DEGENERATE_VOLUME * diag**3
    bad = np.flatnonzero(np.abs(vol) <= limit)
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {len(bad)} of {len(T)} tetrahedra are degenerate (volume at most "
            f"{limit:.3g} m^3 = 1e-12 * bounding-box diagonal^3); the first is tet {i} with "
            f"vertices {T[i].tolist()} and volume {vol[i]:.3g} m^3. Every tet needs four vertices "
            "that are not coplanar: remove flat tets or re-mesh."
        )
    T = np.where((vol < 0)[:, None], T[:, [0, 1, 3, 2]], T)
    return TetMesh(V, T, dict(mesh.groups))


def check_surface(surface: Surface, source: str = "surface") -> Surface:
    """Check that a surface bounds a solid that can be filled with tetrahedra.

    Vertices closer than ``1e-6`` times the bounding-box diagonal are welded
    first (by position), so UV seams and STL's unshared vertices are fine, and
    triangles that lose a corner to welding (zero area) are left out. Then the
    surface must be closed (every edge shared by exactly two triangles),
    consistently oriented, enclose a positive volume, and not intersect itself.

    Self-intersections are found with libigl's exact predicates
    (``igl.predicates.find_self_intersections``, MPL-2.0) when the optional
    package ``libigl`` is installed; otherwise with VTK's
    ``vtkCollisionDetectionFilter`` (VTK ships with pyvista, a dependency), which
    ignores pairs of triangles that share a vertex and so cannot see a fold
    between neighbouring triangles.

    Parameters
    ----------
    surface : Surface
        The surface to check.
    source : str
        Name used in error messages (usually the file path).

    Returns
    -------
    Surface
        ``surface`` itself, or, if every triangle faced inwards (negative
        enclosed volume), a copy with all triangles flipped. Nothing else
        changes.

    Raises
    ------
    WigglyInputError
        With the count of open, non-manifold or inconsistently oriented edges
        and an example edge, or the count of intersecting triangle pairs and an
        example pair.
    """
    _, _, flipped = _inspect_surface(surface, source)
    if not flipped:
        return surface
    return Surface(
        surface.vertices,
        surface.faces[:, ::-1],
        surface.uvs,
        surface.normals,
        dict(surface.groups),
    )


def _inspect_surface(surface: Surface, source: str) -> tuple[np.ndarray, np.ndarray, bool]:
    """Run :func:`check_surface`; return the welded vertices and faces and whether to flip."""
    V, F = surface.vertices, surface.faces
    _check_surface_arrays(surface, source)
    hint = " Fix the model in a modelling tool, or pass repair=True to let fTetWild fill it anyway."
    rep = _weld(V, WELD_TOLERANCE * _diagonal(V[np.unique(F)]))
    W = rep[F]
    # triangles with two corners welded together have no area: leave them out
    kept = np.flatnonzero((W[:, 0] != W[:, 1]) & (W[:, 1] != W[:, 2]) & (W[:, 2] != W[:, 0]))
    W = W[kept]
    if len(W) == 0:
        raise WigglyInputError(f"{source}: all triangles have zero area.")
    n = len(V)
    half = W[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    undirected = np.sort(half, axis=1)
    edges, counts = np.unique(undirected[:, 0] * n + undirected[:, 1], return_counts=True)
    for bad, what, right in [
        (counts == 1, "open edges (used by only one triangle)", "the surface must be closed"),
        (
            counts > 2,
            "non-manifold edges (used by more than two triangles)",
            "each edge must join exactly two triangles",
        ),
    ]:
        if bad.any():
            a, b = divmod(int(edges[np.flatnonzero(bad)[0]]), n)
            raise WigglyInputError(
                f"{source}: {int(bad.sum())} {what}, e.g. the edge between vertices {a} and {b}; "
                f"{right} (watertight).{hint}"
            )
    _, first, directed_counts = np.unique(
        half[:, 0] * n + half[:, 1], return_index=True, return_counts=True
    )
    if (directed_counts > 1).any():
        a, b = half[first[np.flatnonzero(directed_counts > 1)[0]]]
        raise WigglyInputError(
            f"{source}: {int((directed_counts > 1).sum())} edges join two triangles with opposite "
            f"orientations, e.g. the edge between vertices {a} and {b}; all triangles must be "
            f"ordered counter-clockwise seen from outside (recompute normals outside).{hint}"
        )
    volume = float(np.einsum("ij,ij->i", V[W[:, 0]], np.cross(V[W[:, 1]], V[W[:, 2]])).sum()) / 6
    diag = _diagonal(V[np.unique(W)])
    if abs(volume) <= DEGENERATE_VOLUME * diag**3:
        raise WigglyInputError(
            f"{source}: the surface encloses no volume ({volume:.3g} m^3); it must bound a solid."
        )
    pairs = _self_intersections(V, W)
    if len(pairs):
        i, j = kept[pairs[0]]
        raise WigglyInputError(
            f"{source}: the surface intersects itself: {len(pairs)} pairs of triangles cross, "
            f"e.g. faces {i} and {j}; overlapping parts must be merged (boolean union).{hint}"
        )
    return V, W, volume < 0


def _self_intersections(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Pairs of intersecting triangles ``(q, 2)`` of a welded surface, ``i < j``."""
    try:
        import igl.predicates
    except ImportError:
        return _self_intersections_vtk(V, F)
    found, pairs, _ = igl.predicates.find_self_intersections(
        np.ascontiguousarray(V), np.ascontiguousarray(F)
    )
    return (
        np.sort(np.asarray(pairs, dtype=np.int64).reshape(-1, 2), axis=1)
        if found
        else (np.empty((0, 2), dtype=np.int64))
    )


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


# --------------------------------------------------------------------------- loading


BUILTIN_MODELS = ("critter", "plant", "bar")


def resolve_builtin(path: str | Path) -> Path:
    """``builtin:<name>`` names a bundled model (critter, plant, bar); other paths pass."""
    text = str(path)
    if not text.startswith("builtin:"):
        return Path(path)
    name = text.removeprefix("builtin:")
    if name not in BUILTIN_MODELS:
        raise WigglyInputError(f"{text} is not a bundled model; use one of "
                               + ", ".join(f"builtin:{m}" for m in BUILTIN_MODELS))
    return Path(str(resources.files("wiggly") / "data" / f"{name}.obj"))


def load_mesh(path: str | Path) -> TetMesh | Surface:
    """Read a tetrahedral mesh or a triangle surface from a file.

    Surface formats (``.obj .ply .stl .off .glb .gltf``) are read with
    trimesh (``process=False``), which keeps the file's vertices, their order
    and the faces, with these exceptions:

    - STL stores every triangle with its own three corners, so the surface has
      ``3 * n_faces`` vertices in face order (welded by position in
      :func:`check_surface` and :func:`tetrahedralize`).
    - OBJ is read with ``maintain_order=True``: the vertices are the file's
      ``v`` lines (if the file has texture coordinates, ``v`` lines after the
      last one used by a face are dropped), faces in file order, polygons
      split into triangles. Texture coordinates and normals are attached per
      vertex only when every corner of a vertex has the same ``vt`` (``vn``);
      at a UV seam (one ``v`` with several ``vt``) ``uvs`` is ``None`` and a
      warning says so. OBJ groups (``g``, ``o``) and materials are not read.
    - PLY and OFF: exactly the file's vertices and faces.
    - glTF stores one UV per vertex, so its vertices are already split at seams.
      A scene with several meshes is concatenated in node order with each
      node's scene transform applied; every node's vertices form a group named
      after the node.

    Other formats (``.msh .vtu .vtk .mesh .xdmf ...``, see
    :data:`VOLUME_EXTENSIONS`) are read with meshio. A file with ``tetra``
    cells gives a :class:`TetMesh` (checked by :func:`check_tet_mesh`, so
    positively oriented); one with only triangles (or quads, split in two)
    gives a :class:`Surface`. Named vertex sets become ``groups``: meshio point
    sets; cell sets and gmsh physical groups (the vertices of their cells);
    point data arrays holding only 0 and 1 (the vertices marked 1).

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    TetMesh or Surface

    Raises
    ------
    WigglyInputError
        Missing file, unknown extension, unreadable file, no tetrahedra and no
        triangles, other volume cells (hexahedra, quadratic tets), NaN or
        infinite coordinates, indices out of range, degenerate tets.
    """
    path = resolve_builtin(path)
    source = str(path)
    ext = _extension(path)
    if not path.is_file():
        where = "is a directory, not a file" if path.is_dir() else "does not exist"
        raise WigglyInputError(f"{source}: {where}; give the path of a mesh file.")
    if ext in SURFACE_EXTENSIONS:
        surface = _load_trimesh(path, ext)
        _check_surface_arrays(surface, source)
        return surface
    if ext not in VOLUME_EXTENSIONS:
        raise WigglyInputError(
            f"{source}: unknown mesh file extension {ext or '(none)'!r}. Supported surfaces: "
            f"{' '.join(SURFACE_EXTENSIONS)}; tetrahedral meshes: {' '.join(VOLUME_EXTENSIONS)}."
        )
    try:
        raw = meshio.read(path)
    except Exception as exc:  # meshio raises many types for malformed files
        raise WigglyInputError(f"{source}: could not read the file with meshio: {exc}") from exc
    return _from_meshio(raw, source)


def _extension(path: Path) -> str:
    """The longest known extension of ``path`` (``.vol.gz`` before ``.gz``), lower case."""
    name = path.name.lower()
    known = [e for e in (*SURFACE_EXTENSIONS, *VOLUME_EXTENSIONS) if name.endswith(e)]
    return max(known, key=len) if known else path.suffix.lower()


def _from_meshio(raw: meshio.Mesh, source: str) -> TetMesh | Surface:
    """Convert a meshio mesh to a TetMesh (if it has tets) or a Surface."""
    V = np.asarray(raw.points, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] not in (2, 3):
        raise WigglyInputError(f"{source}: points have shape {V.shape}; expected (n, 3).")
    if V.shape[1] == 2:
        raise WigglyInputError(
            f"{source}: the mesh is 2D (points have 2 coordinates); wiggly needs a 3D mesh."
        )
    blocks = [(c.type, np.asarray(c.data, dtype=np.int64)) for c in raw.cells]
    types = sorted({t for t, _ in blocks})
    other = sorted(set(types) & _VOLUME_CELLS)
    if other:
        raise WigglyInputError(
            f"{source}: contains {', '.join(other)} cells, which wiggly cannot simulate; it needs "
            "linear tetrahedra ('tetra'). Re-mesh or export with first-order tetrahedra."
        )

    def cells(kind: str) -> np.ndarray:
        width = 4 if kind == "tetra" else 3
        parts = [d for t, d in blocks if t == kind]
        if kind == "triangle":
            parts += [q[:, [0, 1, 2, 0, 2, 3]].reshape(-1, 3) for t, q in blocks if t == "quad"]
        return np.concatenate(parts) if parts else np.empty((0, width), dtype=np.int64)

    groups = _meshio_groups(raw, blocks, len(V), source)
    T = cells("tetra")
    if len(T):
        return check_tet_mesh(TetMesh(V, T, groups), source)
    F = cells("triangle")
    if len(F) == 0:
        raise WigglyInputError(
            f"{source}: has no tetrahedra and no triangles (cell types: "
            f"{', '.join(types) or 'none'}); give a tetrahedral mesh or a closed triangle surface."
        )
    surface = Surface(V, F, groups=groups)
    _check_surface_arrays(surface, source)
    return surface


def _meshio_groups(
    raw: meshio.Mesh, blocks: list[tuple[str, np.ndarray]], n: int, source: str
) -> dict[str, np.ndarray]:
    """Named vertex sets of a meshio mesh (see :func:`load_mesh`)."""
    groups: dict[str, np.ndarray] = {}
    for name, idx in (raw.point_sets or {}).items():
        groups[name] = np.unique(np.asarray(idx, dtype=np.int64))
    for name, per_block in (raw.cell_sets or {}).items():
        verts = [
            d[np.asarray(s, dtype=np.int64)].ravel()
            for (_, d), s in zip(blocks, per_block, strict=False)
            if s is not None and len(s)
        ]
        if verts:
            groups[name] = np.unique(np.concatenate(verts))
    physical = raw.cell_data.get("gmsh:physical")
    if physical is not None:
        for name, value in (raw.field_data or {}).items():
            value = np.asarray(value).ravel()
            if len(value) < 2:
                continue
            tag, dim = int(value[0]), int(value[1])
            verts = [
                d[np.asarray(p) == tag].ravel()
                for (t, d), p in zip(blocks, physical, strict=False)
                if _CELL_DIMENSION.get(t) == dim
            ]
            if verts and sum(len(v) for v in verts):
                groups[name] = np.unique(np.concatenate(verts))
    for name, data in (raw.point_data or {}).items():
        data = np.asarray(data)
        if name.startswith(("gmsh:", "medit:")) or data.shape != (n,) or name in groups:
            continue
        if np.isin(data, (0, 1)).all() and data.any():
            groups[name] = np.flatnonzero(data)
    for name, idx in groups.items():
        _check_indices(idx[:, None], n, source, f"group {name!r} entry")
    return groups


def _load_trimesh(path: Path, ext: str) -> Surface:
    """Read a surface file with trimesh, keeping the file's vertices (see :func:`load_mesh`)."""
    import trimesh

    source = str(path)
    try:
        if ext == ".obj":
            return _obj_surface(path)
        loaded = trimesh.load(path, process=False)
    except WigglyInputError:
        raise
    except Exception as exc:  # trimesh raises many types for malformed files
        raise WigglyInputError(f"{source}: could not read the file with trimesh: {exc}") from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = _scene_meshes(loaded)
    else:
        meshes = [("", loaded, _file_normals(loaded))]
    meshes = [m for m in meshes if isinstance(m[1], trimesh.Trimesh) and len(m[1].faces)]
    if not meshes:
        raise WigglyInputError(_NO_TRIANGLES.format(source=source))
    return _concatenate(meshes)


_NO_TRIANGLES = (
    "{source}: contains no triangles (only points or lines); give a closed triangle surface."
)


def _scene_meshes(scene) -> list[tuple[str, object, np.ndarray | None]]:
    """``(node name, mesh, file normals)`` of a trimesh scene in node order, transforms applied."""
    out = []
    for node in scene.graph.nodes_geometry:
        transform, geometry = scene.graph[node]
        mesh = scene.geometry.get(geometry)
        if mesh is None or not hasattr(mesh, "faces"):
            continue
        normals = _file_normals(mesh)
        moved = mesh.copy()
        moved.apply_transform(transform)  # also reverses the faces if the transform mirrors
        if normals is not None:
            normals = normals @ np.linalg.inv(transform[:3, :3])  # inverse transpose, row vectors
            normals /= np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-300)
        out.append((str(node), moved, normals))
    return out


def _file_normals(mesh) -> np.ndarray | None:
    """Vertex normals a trimesh mesh was loaded with (not ones trimesh would compute)."""
    cache = getattr(getattr(mesh, "_cache", None), "cache", {})
    normals = cache.get("vertex_normals")
    if normals is None or np.shape(normals) != np.shape(mesh.vertices):
        return None
    return np.asarray(normals, dtype=np.float64)


def _file_uvs(mesh) -> np.ndarray | None:
    """Per-vertex texture coordinates of a trimesh mesh, if any."""
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None or len(uv) != len(mesh.vertices):
        return None
    return np.asarray(uv, dtype=np.float64)[:, :2]


def _concatenate(meshes: list[tuple[str, object, np.ndarray | None]]) -> Surface:
    """One Surface from several trimesh meshes; with several, each node becomes a vertex group."""
    counts = np.array([len(m.vertices) for _, m, _ in meshes])
    offsets = np.concatenate([[0], np.cumsum(counts)])
    V = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for _, m, _ in meshes])
    F = np.concatenate(
        [
            np.asarray(m.faces, dtype=np.int64) + o
            for (_, m, _), o in zip(meshes, offsets[:-1], strict=True)
        ]
    )
    uvs = [_file_uvs(m) for _, m, _ in meshes]
    normals = [n for _, _, n in meshes]
    groups = {}
    if len(meshes) > 1:
        groups = {
            name: np.arange(offsets[i], offsets[i + 1]) for i, (name, _, _) in enumerate(meshes)
        }
    return Surface(
        V,
        F,
        uvs=None if any(u is None for u in uvs) else np.concatenate(uvs),
        normals=None if any(n is None for n in normals) else np.concatenate(normals),
        groups=groups,
    )


def _obj_surface(path: Path) -> Surface:
    """An OBJ surface with the file's ``v`` order and unambiguous per-vertex UVs and normals.

    trimesh's ordered read keeps the ``v`` lines but then guesses one UV per
    vertex; a second read that splits vertices at seams gives every face corner
    its true ``vt`` and ``vn``, which are kept per vertex only where they agree.
    """
    ordered = _obj_chunks(path, maintain_order=True)
    if not ordered:
        raise WigglyInputError(_NO_TRIANGLES.format(source=path))
    # with maintain_order every chunk holds a prefix of the file's v lines
    V = np.asarray(max((c["vertices"] for c in ordered), key=len), dtype=np.float64)
    F = np.concatenate([np.asarray(c["faces"], dtype=np.int64) for c in ordered])
    uvs = normals = None
    if any(_chunk_uv(c) is not None or "vertex_normals" in c for c in ordered):
        split = _obj_chunks(path, maintain_order=False)
        corners = np.concatenate([np.asarray(c["vertices"])[c["faces"]] for c in split])
        if corners.shape == (len(F), 3, 3) and np.allclose(corners, V[F], rtol=0, atol=0):
            uv = [_chunk_uv(c) for c in split]
            if all(u is not None for u in uv):
                uvs = _per_vertex(
                    np.concatenate([u[c["faces"]] for u, c in zip(uv, split, strict=True)]),
                    F,
                    len(V),
                )
                if uvs is None:
                    warnings.warn(
                        f"{path}: some vertices have several texture coordinates (UV seams); "
                        "per-vertex UVs cannot represent that, so the surface has no UVs. The "
                        "vertex order is the file's, so the animation still applies to it.",
                        stacklevel=4,
                    )
            if all("vertex_normals" in c for c in split):
                corner_normals = [np.asarray(c["vertex_normals"])[c["faces"]] for c in split]
                normals = _per_vertex(np.concatenate(corner_normals), F, len(V))
    return Surface(V, F, uvs=uvs, normals=normals)


def _obj_chunks(path: Path, maintain_order: bool) -> list[dict]:
    """trimesh's OBJ reader output: one dict per material chunk, in file order."""
    from trimesh.exchange.obj import load_obj

    with open(path, "rb") as file:
        kwargs = load_obj(
            file, maintain_order=maintain_order, group_material=False, skip_materials=True
        )
    # trimesh builds the chunks from the end of the file backwards
    return list(kwargs.get("geometry", {}).values())[::-1]


def _chunk_uv(chunk: dict) -> np.ndarray | None:
    """Per-vertex texture coordinates of one OBJ chunk, if any."""
    uv = getattr(chunk.get("visual"), "uv", None)
    if uv is None or len(uv) != len(chunk["vertices"]):
        return None
    return np.asarray(uv, dtype=np.float64)[:, :2]


def _per_vertex(corner_values: np.ndarray, F: np.ndarray, n: int) -> np.ndarray | None:
    """Scatter per-corner values ``(k, 3, d)`` to vertices, or None if a vertex's corners differ."""
    d = corner_values.shape[-1]
    flat = corner_values.reshape(-1, d)
    idx = F.ravel()
    low = np.full((n, d), np.inf)
    high = np.full((n, d), -np.inf)
    np.minimum.at(low, idx, flat)
    np.maximum.at(high, idx, flat)
    if (high - low > 1e-12 * (1 + np.abs(flat).max())).any():
        return None
    values = np.zeros((n, d))
    values[idx] = flat
    return values


# --------------------------------------------------------------------------- meshing


_CWD_LOCK = threading.Lock()
_TET_CACHE_VERSION = b"wiggly-tets-1"


def _tet_cache(V: np.ndarray, F: np.ndarray, edge_length: float, envelope: float,
               cache_dir: str | os.PathLike[str] | bool | None) -> Path | None:
    """Cache file of a tetrahedralization: fTetWild is randomized, so caching makes re-runs
    reproducible (and lets the modes cache hit).  Keyed by surface and options."""
    if cache_dir is False:
        return None
    h = hashlib.sha256(_TET_CACHE_VERSION)
    for a in (np.ascontiguousarray(V, np.float64), np.ascontiguousarray(F, np.int64),
              np.array([edge_length, envelope])):
        h.update(a.tobytes())
    root = Path(cache_dir) if cache_dir not in (None, True) else default_cache_dir()
    return root / "tets" / f"{h.hexdigest()[:32]}.npz"


@contextmanager
def _scratch_cwd() -> Iterator[None]:
    """Run in a private temporary working directory: fTetWild writes a debug file
    (``__tracked_surface.stl``) into the current directory, which must not litter the
    user's folder.  The working directory is process-wide, hence the lock."""
    main = threading.current_thread() is threading.main_thread()
    handler = signal.getsignal(signal.SIGINT) if main else None
    with _CWD_LOCK, tempfile.TemporaryDirectory(prefix="wiggly-ftetwild-") as tmp:
        old = os.getcwd()
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)
            if main and handler is not None:  # native code may replace Python's Ctrl+C handler
                signal.signal(signal.SIGINT, handler)


def tetrahedralize(
    surface: Surface,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool = False,
    progress: bool = False,
    source: str = "surface",
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> TetMesh:
    """Fill a closed surface with linear tetrahedra using fTetWild (pytetwild).

    Results are cached on disk (``cache_dir``; None: :func:`wiggly.files.default_cache_dir`,
    False: off), keyed by the surface and the options: fTetWild is randomized, so the cache
    makes repeated runs reproducible.

    fTetWild (Hu et al. 2020) meshes the volume inside an envelope around the
    input: the boundary of the tet mesh stays within ``0.1 * edge_length``
    (clamped to 0.1 %-1 % of the bounding-box diagonal) of the surface, so the
    tet mesh approximates the surface and :func:`embed` maps the surface into
    it. The envelope follows the edge length so that thin parts do not force
    tets much smaller than requested. fTetWild is not deterministic: tet counts
    vary by a few percent between runs.

    Parameters
    ----------
    surface : Surface
        A closed triangle surface.
    edge_length : float, optional
        Target tet edge length in metres.
    resolution : int, optional
        Target number of tet edges along the bounding-box diagonal, i.e.
        ``edge_length = diagonal / resolution``. Give at most one of
        ``edge_length`` and ``resolution``; the default is ``resolution = 25``,
        about 18k tets for a sphere and 5k for the bundled critter (slender
        shapes fill less of their bounding box). The count grows roughly like
        ``resolution**3``.
    repair : bool
        Skip :func:`check_surface` and let fTetWild fill whatever the
        triangles enclose (it decides inside and outside by winding numbers, so
        it copes with self-intersections, overlapping parts and small holes),
        for surfaces that fail the check.
    progress : bool
        Print fTetWild's log.
    source : str
        Name used in error messages (usually the file path).

    Returns
    -------
    TetMesh
        Positively oriented, no unreferenced vertices.

    Notes
    -----
    Measured on the 2-core development machine while other jobs were running
    (wall time, CPU time in brackets): an icosphere of radius 1 with 1280
    faces gives 17.7k tets at the default resolution in 2-3 s (1.5-1.8 s),
    6.1k tets at ``resolution=20`` in 1.9 s (0.7 s) and 21k tets at
    ``resolution=28`` in 3.6-4.7 s (1.9 s); the bundled critter (6k faces)
    gives 4.6k-4.9k tets in 6-7 s (4 s). Cost grows with the number of tets
    and with the number of small features of the surface.
    """
    if edge_length is not None and resolution is not None:
        raise WigglyInputError(
            f"tetrahedralize: got edge_length={edge_length} and resolution={resolution}; give "
            "only one (resolution means edge_length = bounding-box diagonal / resolution)."
        )
    if edge_length is not None and not (np.isfinite(edge_length) and edge_length > 0):
        raise WigglyInputError(
            f"tetrahedralize: edge_length must be a positive length in metres, got {edge_length}."
        )
    if resolution is not None and not (int(resolution) == resolution and resolution >= 1):
        raise WigglyInputError(
            f"tetrahedralize: resolution must be a positive integer, got {resolution}."
        )
    if repair:
        _check_surface_arrays(surface, source)
        V, F = surface.vertices, surface.faces
    else:
        V, F, flipped = _inspect_surface(surface, source)
        if flipped:
            F = F[:, ::-1]
    used = np.unique(F)
    compact = np.zeros(len(V), dtype=np.int64)
    compact[used] = np.arange(len(used))
    V, F = V[used], compact[F]
    diag = _diagonal(V)
    if edge_length is None:
        edge_length = diag / (resolution or DEFAULT_RESOLUTION)
    import pytetwild

    envelope = float(np.clip(ENVELOPE_PER_EDGE * edge_length / diag, 1e-3, 1e-2))
    cached = _tet_cache(V, F, edge_length, envelope, cache_dir)
    if cached is not None and cached.exists():
        try:
            with np.load(cached) as data:
                tv, tt = data["vertices"], data["tets"]
        except (OSError, ValueError, KeyError):
            cached.unlink(missing_ok=True)
            tv = tt = None
    else:
        tv = tt = None
    if tv is None:
        with activity(f"tetrahedralizing {source} (fTetWild)", progress), _scratch_cwd():
            tv, tt = pytetwild.tetrahedralize(
                np.ascontiguousarray(V),
                np.ascontiguousarray(F, dtype=np.int32),
                edge_length_abs=float(edge_length),
                epsilon=envelope,
                quiet=True,
                loglevel=6,
            )
        if cached is not None and len(tt):
            try:
                with atomic_file(cached) as tmp, open(tmp, "wb") as f:
                    np.savez(f, vertices=np.asarray(tv), tets=np.asarray(tt))
            except OSError:
                pass  # a read-only cache directory only costs time
    tt = np.asarray(tt, dtype=np.int64).reshape(-1, 4)
    if len(tt) == 0:
        raise WigglyInputError(
            f"{source}: fTetWild produced no tetrahedra; the surface does not enclose a volume "
            f"that is thick compared to the edge length {edge_length:.3g} m."
        )
    used = np.unique(tt)
    compact = np.zeros(len(tv), dtype=np.int64)
    compact[used] = np.arange(len(used))
    mesh = TetMesh(np.asarray(tv, dtype=np.float64)[used], compact[tt])
    return check_tet_mesh(mesh, f"{source} (tetrahedralized)")


def coarse_mesh(
    mesh: TetMesh,
    n_tets: int,
    *,
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> TetMesh | None:
    """A coarser tet mesh of the same solid, with about ``n_tets`` tets (fTetWild).

    The boundary of ``mesh`` is tetrahedralized with an edge length ``(mesh.n_tets /
    n_tets)^(1/3)`` times the mean edge length of ``mesh``.  If some vertex of ``mesh`` lies
    far outside the result (a thin part lost at that size: its smallest barycentric
    coordinate in the nearest coarse tet is below -0.5), the edge length shrinks by 1.5 and
    fTetWild runs again, twice at most; then None.  Results are cached like
    :func:`tetrahedralize`.
    """
    V, T = mesh.vertices, mesh.tets
    edges = V[T[:, [0, 0, 0, 1, 1, 2]]] - V[T[:, [1, 2, 3, 2, 3, 3]]]
    edge = float(np.mean(np.linalg.norm(edges, axis=-1))) * (len(T) / n_tets) ** (1 / 3)
    surface = Surface(V, mesh.boundary_faces())
    for _ in range(3):
        coarse = tetrahedralize(
            surface, edge_length=edge, repair=True, source="coarse mesh", cache_dir=cache_dir
        )
        if embed(V, coarse).barycentric.min() > -0.5:
            return coarse
        edge /= 1.5
    return None


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
    P = _as_array(points, np.float64, 3, "points")
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


def load_model(
    path: str | Path,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool = False,
    progress: bool = False,
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> Model:
    """Load a model, tetrahedralize it if it is a surface and embed the surface.

    For a surface file: :func:`load_mesh`, :func:`tetrahedralize` (with the
    given options) and :func:`embed` of the surface vertices. For a tet mesh
    file: the surface has all the tet mesh vertices (same indices, so groups
    and keyframes address the same vertices; interior vertices are simply not
    used by any face) and the mesh's boundary faces; the embedding puts every
    vertex at a corner of one of its tets (barycentrics ``(1, 0, 0, 0)`` up to
    order), so ``embedding.matrix(n)`` is the identity (vertices used by no
    tet, if any, are placed by :func:`embed`).

    Parameters
    ----------
    path : str or Path
        Surface or tet mesh file (see :func:`load_mesh`).
    edge_length, resolution, repair, progress
        Passed to :func:`tetrahedralize` for a surface; ignored for a tet mesh.

    Returns
    -------
    Model
    """
    loaded = load_mesh(path)
    source = str(path)
    if isinstance(loaded, Surface):
        tets = tetrahedralize(
            loaded,
            edge_length=edge_length,
            resolution=resolution,
            repair=repair,
            progress=progress,
            source=source,
            cache_dir=cache_dir,
        )
        return Model(loaded, tets, embed(loaded.vertices, tets), source)
    tets = loaded
    n, m = tets.n_vertices, tets.n_tets
    tet_of = np.full(n, -1, dtype=np.int64)
    corner = np.zeros(n, dtype=np.int64)
    tet_of[tets.tets.ravel()] = np.repeat(np.arange(m), 4)
    corner[tets.tets.ravel()] = np.tile(np.arange(4), m)
    bary = np.zeros((n, 4))
    bary[np.arange(n), corner] = 1.0
    embedding = Embedding(tet_of, bary, tets.tets[tet_of.clip(0)])
    loose = np.flatnonzero(tet_of < 0)
    if len(loose):
        extra = embed(tets.vertices[loose], tets)
        embedding.tet_index[loose] = extra.tet_index
        embedding.barycentric[loose] = extra.barycentric
        embedding.vertex_indices[loose] = extra.vertex_indices
    surface = Surface(tets.vertices, tets.boundary_faces(), groups=dict(tets.groups))
    return Model(surface, tets, embedding, source)


# --------------------------------------------------------------------------- helpers


def _as_array(
    values: np.ndarray, dtype: type, width: int, name: str, rows: int | None = None
) -> np.ndarray:
    """``values`` as a C-contiguous ``(rows, width)`` array of ``dtype``, or a clear error."""
    array = np.asarray(values)
    if array.ndim != 2 or array.shape[1] != width or (rows is not None and len(array) != rows):
        want = f"({rows if rows is not None else 'n'}, {width})"
        raise WigglyInputError(f"{name} should have shape {want}; shape is {array.shape}.")
    if (
        np.issubdtype(dtype, np.integer)
        and array.size
        and not np.issubdtype(array.dtype, np.integer)
    ):
        if not np.array_equal(array, np.round(array)):
            raise WigglyInputError(
                f"{name} should hold integer indices; got {array.dtype} values with fractions."
            )
    return np.ascontiguousarray(array, dtype=dtype)


def _as_groups(groups: dict) -> dict[str, np.ndarray]:
    """Groups as a dict of str to flat int64 index arrays."""
    return {str(k): np.asarray(v, dtype=np.int64).ravel() for k, v in groups.items()}


def _check_finite(V: np.ndarray, source: str) -> None:
    """Raise if any vertex coordinate is NaN or infinite."""
    bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {len(bad)} vertices have NaN or infinite coordinates, e.g. vertex {i} at "
            f"{V[i].tolist()}; all coordinates must be finite numbers (metres)."
        )


def _check_indices(cells: np.ndarray, n: int, source: str, what: str) -> None:
    """Raise if any index in ``cells`` is outside ``0 .. n - 1``."""
    bad = np.flatnonzero(((cells < 0) | (cells >= n)).any(axis=1))
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {len(bad)} {what}s use vertex indices outside 0..{n - 1}, e.g. {what} {i} "
            f"with indices {cells[i].tolist()}; the mesh has {n} vertices."
        )


def _check_surface_arrays(surface: Surface, source: str) -> None:
    """Raise for an empty surface, non-finite coordinates or out-of-range face indices."""
    if surface.n_faces == 0:
        raise WigglyInputError(f"{source}: the surface has no triangles.")
    _check_finite(surface.vertices, source)
    _check_indices(surface.faces, surface.n_vertices, source, "face")


def _tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed tet volumes ``det[v1 - v0, v2 - v0, v3 - v0] / 6``."""
    e = V[T[:, 1:]] - V[T[:, :1]]
    return np.einsum("ij,ij->i", e[:, 0], np.cross(e[:, 1], e[:, 2])) / 6.0


def _diagonal(V: np.ndarray) -> float:
    """Length of the bounding-box diagonal of ``V``."""
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) if len(V) else 0.0


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


def _weld(V: np.ndarray, tol: float) -> np.ndarray:
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


def _count_components(T: np.ndarray, n: int) -> int:
    """Number of connected components of the tets (vertex-sharing tets are connected)."""
    if len(T) == 0:
        return 0
    rows = np.repeat(T[:, 0], 3)
    cols = T[:, 1:].ravel()
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[np.unique(T)]))
