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

from wiggly import checks, mesh_checks
from wiggly.errors import WigglyInputError, counted
from wiggly.files import atomic_file, default_cache_dir
from wiggly.limits import MAX_RESOLUTION, MAX_TETS
from wiggly.mesh_checks import (
    DEGENERATE_VOLUME,
    CheckedSurface,
    SurfaceReport,
    diagonal,
)
from wiggly.progress import activity

__all__ = [
    "SURFACE_EXTENSIONS",
    "VOLUME_EXTENSIONS",
    "Embedding",
    "MeshRepairWarning",
    "Model",
    "Surface",
    "SurfaceDefectError",
    "TetBudgetError",
    "TetMesh",
    "build_model",
    "check_surface",
    "check_tet_mesh",
    "checked_surface",
    "coarse_mesh",
    "embed",
    "inspect_surface",
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
        self.vertices = checks.array(self.vertices, "TetMesh.vertices", 3, np.float64)
        self.tets = checks.array(self.tets, "TetMesh.tets", 4, np.int64)
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
        self.vertices = checks.array(self.vertices, "Surface.vertices", 3, np.float64)
        self.faces = checks.array(self.faces, "Surface.faces", 3, np.int64)
        n = len(self.vertices)
        if self.uvs is not None:
            self.uvs = checks.array(self.uvs, "Surface.uvs", 2, np.float64, rows=n)
        if self.normals is not None:
            self.normals = checks.array(self.normals, "Surface.normals", 3, np.float64, rows=n)
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

    def outside_distance(self, mesh: TetMesh) -> np.ndarray:
        """How far each point lies outside its tet (0 inside), in metres: the largest
        ``-lambda_i * h_i`` over the tet's faces, ``h_i`` the tet's height over face i.

        Returns
        -------
        ndarray, shape (p,)
        """
        T = mesh.tets[self.tet_index]
        V = mesh.vertices
        volume = np.abs(_tet_volumes(V, T))
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
    checks.finite_vertices(V, source)
    checks.indices_in_range(T, n, source, "tet")
    for name, idx in mesh.groups.items():
        checks.indices_in_range(idx[:, None], n, source, f"group {name!r} entry")
    vol = _tet_volumes(V, T)
    used = V[np.unique(T)]
    diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    limit = DEGENERATE_VOLUME * diag**3
    bad = np.flatnonzero(np.abs(vol) <= limit)
    if len(bad):
        i = bad[0]
        raise WigglyInputError(
            f"{source}: {len(bad)} of {counted(len(T), 'tetrahedron', 'tetrahedra')} "
            f"{'is' if len(bad) == 1 else 'are'} degenerate (volume at most "
            f"{limit:.3g} m^3 = 1e-12 * bounding-box diagonal^3); the first is tet {i} with "
            f"vertices {T[i].tolist()} and volume {vol[i]:.3g} m^3. Every tet needs four vertices "
            "that are not coplanar: remove flat tets or re-mesh."
        )
    T = np.where((vol < 0)[:, None], T[:, [0, 1, 3, 2]], T)
    return TetMesh(V, T, dict(mesh.groups))


def inspect_surface(surface: Surface, source: str = "surface") -> SurfaceReport:
    """What is unusual about a surface: open, non-manifold and misoriented edges, crossing
    triangle pairs (see :class:`wiggly.mesh_checks.SurfaceReport`).

    Vertices closer than ``1e-6`` times the bounding-box diagonal are welded first, so UV
    seams and STL's unshared vertices are fine.  Self-intersections are found with libigl's
    exact predicates when the optional package ``libigl`` is installed, else with VTK.

    Raises
    ------
    WigglyInputError
        Only for what no tetrahedralizer can fill: no triangles, NaN or infinite coordinates,
        indices out of range, all triangles of zero area, no enclosed volume.
    """
    return checked_surface(surface, source).report


def check_surface(surface: Surface, source: str = "surface") -> Surface:
    """Check that a surface is closed, manifold, consistently oriented and free of
    self-intersections (the strict check of ``tetrahedralize(repair=False)``).

    Returns
    -------
    Surface
        ``surface`` itself, or, if every triangle faced inwards (negative enclosed volume),
        a copy with all triangles flipped.  Nothing else changes.

    Raises
    ------
    SurfaceDefectError
        Listing every kind of defect with its count and an example (e.g. "4 open edges (used
        by only one triangle: the surface has holes; e.g. the edge between vertices 3 and
        7)"), and what :func:`inspect_surface` refuses.
    """
    checked = checked_surface(surface, source)
    _refuse_defects(checked.report, source)
    V, F = surface.vertices, surface.faces
    volume = float(np.einsum("ij,ij->", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]]))) / 6
    if volume >= 0:
        return surface
    return Surface(V, F[:, ::-1], surface.uvs, surface.normals, dict(surface.groups))


class SurfaceDefectError(WigglyInputError):
    """A surface refused by the strict check (``repair=False``).  ``defects`` says what is
    wrong (without advice), so that callers can give advice in their own terms."""

    def __init__(self, message: str, source: str, defects: str):
        super().__init__(message)
        self.source, self.defects = source, defects


def _refuse_defects(report: SurfaceReport, source: str) -> None:
    if report.clean:
        return
    defects = "; ".join(report.defects(detailed=True))
    raise SurfaceDefectError(
        f"{source}: the surface is not a clean closed surface: {defects}. Fix the model in a "
        "modelling tool, or tetrahedralize with repair=True (the default) to let fTetWild fill "
        "the solid its triangles enclose.", source, defects)


def checked_surface(surface: Surface, source: str = "surface") -> CheckedSurface:
    """The surface welded, oriented and inspected for meshing (:func:`inspect_surface`),
    to pass to :func:`build_model` after looking at its report."""
    _check_surface_arrays(surface, source)
    return mesh_checks.inspect_surface(surface.vertices, surface.faces, source)


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
        checks.indices_in_range(idx[:, None], n, source, f"group {name!r} entry")
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
_TET_CACHE_VERSION = b"wiggly-tets-2"


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


class MeshRepairWarning(UserWarning):
    """A surface was accepted although it is open, non-manifold, misoriented or
    self-intersecting (fTetWild filled what it encloses), or parts of it lie outside the
    tet mesh.  One warning per model says what was unusual and what was done."""


class TetBudgetError(WigglyInputError):
    """The requested tet size would make more than ``wiggly.limits.MAX_TETS`` tets.

    ``estimate`` is the estimated count, ``max_resolution`` the largest resolution within the
    limit and ``min_edge_length`` the smallest edge length (m) within it, so that callers can
    say what to change in their own terms."""

    def __init__(self, message: str, estimate: float, max_resolution: int,
                 min_edge_length: float):
        super().__init__(message)
        self.estimate, self.max_resolution = estimate, max_resolution
        self.min_edge_length = min_edge_length


#: A surface vertex farther than this many tet edge lengths outside the tet mesh is reported.
FAR_OUTSIDE = 1.0


def tetrahedralize(
    surface: Surface,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    progress: bool = False,
    source: str = "surface",
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> TetMesh:
    """Fill a surface with linear tetrahedra using fTetWild (pytetwild).

    The surface is inspected first (:func:`inspect_surface`).  By default (``repair=True``)
    an open, non-manifold, misoriented or self-intersecting surface is accepted: its
    triangles are oriented consistently and fTetWild fills the solid they enclose (it decides
    inside and outside by generalized winding numbers, so it copes with self-intersections,
    overlapping parts and holes); one :class:`MeshRepairWarning` says what was unusual.
    ``repair=False`` refuses such a surface (:class:`SurfaceDefectError`).  What cannot be
    filled is always refused: no triangles, NaN coordinates, no enclosed volume.

    The tet count is estimated before any meshing (``wiggly.mesh_checks.estimate_tets``);
    above ``wiggly.limits.MAX_TETS`` the call fails (:class:`TetBudgetError`).  A surface much
    finer than the tets is first simplified to an envelope of about three triangles per
    squared edge length (``wiggly.mesh_checks.simplified_envelope``): the surface itself is
    embedded in the tets later (:func:`embed`), and fTetWild's time grows with its input.

    fTetWild (Hu et al. 2020) meshes the volume inside an envelope around its input: the
    boundary of the tet mesh stays within ``0.1 * edge_length`` (clamped to 0.1 %-1 % of the
    bounding-box diagonal) of it.  **fTetWild is not reproducible**: it shuffles the input
    triangles with a hardware-seeded random generator (``std::random_device``), which
    pytetwild does not let us seed, and one thread does not help; tet counts vary by a few
    percent between runs.  Results are therefore cached on disk (``cache_dir``; None:
    :func:`wiggly.files.default_cache_dir`, False: off), keyed by the surface and the options,
    so that repeated runs on one machine (or with a copied cache) get the same tet mesh.

    Parameters
    ----------
    surface : Surface
        A triangle surface.
    edge_length : float, optional
        Target tet edge length in metres.
    resolution : int, optional
        Target number of tet edges along the bounding-box diagonal, i.e.
        ``edge_length = diagonal / resolution``, at most ``wiggly.limits.MAX_RESOLUTION``.
        Give at most one of ``edge_length`` and ``resolution``; the default is
        ``resolution = 25``, about 18k tets for a sphere and 5k for the bundled critter
        (slender shapes fill less of their bounding box).  The count grows like
        ``resolution**3``.
    repair : bool
        Accept (True, the default; None means the same) or refuse (False) surfaces that are
        not clean closed surfaces.
    progress : bool
        Print the stages (checking, tetrahedralizing) with the elapsed time on stderr.
    source : str
        Name used in messages (usually the file path).

    Returns
    -------
    TetMesh
        Positively oriented, no unreferenced vertices.

    Notes
    -----
    Measured on the 2-core development machine while other jobs were running: an icosphere
    of radius 1 with 1280 faces gives 17.7k tets at the default resolution in 2-3 s; the
    bundled critter about 5k tets in 6-7 s; public meshes of 1k-100k triangles 2-6 s at the
    default resolution once simplified (the 52k-triangle armadillo did not finish in 300 s
    unsimplified).
    """
    mesh, report, _ = _tetrahedralize(surface, edge_length=edge_length, resolution=resolution,
                                      repair=repair, progress=progress, source=source,
                                      cache_dir=cache_dir)
    if not report.clean:
        warnings.warn(repair_note(source, report), MeshRepairWarning, stacklevel=2)
    return mesh


def repair_note(source: str, report: SurfaceReport, far_outside: int = 0,
                farthest: float = 0.0) -> str:
    """The one-line warning of an accepted surface: what was unusual and what was done."""
    parts = []
    if not report.clean:
        parts.append(f"the surface has {_join(report.defects())}; fTetWild filled the solid "
                     "its triangles enclose (by winding numbers), and the animation is "
                     "delivered on your surface as it is")
    if far_outside:
        parts.append(f"{counted(far_outside, 'vertex')} of the surface "
                     f"{'lies' if far_outside == 1 else 'lie'} outside the filled solid, up to "
                     f"{farthest:.2g} tet edge lengths away (parts thinner than the "
                     f"tets), and {'follows' if far_outside == 1 else 'follow'} the nearest "
                     "tets; a higher resolution resolves them")
    return f"{source}: " + "; ".join(parts) + "."


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def edge_length_for(diag: float, edge_length: float | None, resolution: int | None,
                    source: str = "tetrahedralize") -> float:
    """The target tet edge length from the options of :func:`tetrahedralize` (checked)."""
    if edge_length is not None and resolution is not None:
        raise WigglyInputError(
            f"{source}: got edge_length={edge_length} and resolution={resolution}; give "
            "only one (resolution means edge_length = bounding-box diagonal / resolution)."
        )
    if edge_length is not None and not (np.isfinite(edge_length) and edge_length > 0):
        raise WigglyInputError(
            f"{source}: edge_length must be a positive length in metres, got {edge_length}."
        )
    if resolution is not None and not (isinstance(resolution, int | np.integer | float)
                                       and int(resolution) == resolution
                                       and 1 <= resolution <= MAX_RESOLUTION):
        raise WigglyInputError(
            f"{source}: resolution must be an integer in [1, {MAX_RESOLUTION}] "
            f"(wiggly.limits.MAX_RESOLUTION), got {resolution}."
        )
    return float(edge_length) if edge_length is not None else \
        diag / int(resolution or DEFAULT_RESOLUTION)


def check_tet_budget(report: SurfaceReport, edge_length: float, source: str,
                     asked: str) -> float:
    """The estimated tet count at ``edge_length``; :class:`TetBudgetError` above MAX_TETS.
    ``asked`` names the option in the message ("resolution=300")."""
    estimate = mesh_checks.estimate_tets(report.volume, report.area, edge_length)
    if estimate > MAX_TETS:
        best = mesh_checks.max_resolution(report.volume, report.area, report.diagonal, MAX_TETS)
        shortest = report.diagonal / max(best, 1)
        raise TetBudgetError(
            f"{source}: {asked} would make about {estimate:.2g} tetrahedra "
            f"({report.volume:.3g} m^3 at edge length {edge_length:.3g} m), more than wiggly's "
            f"limit of {MAX_TETS} (wiggly.limits.MAX_TETS); use resolution <= {best} "
            f"(edge_length >= {shortest:.3g} m).", estimate, best, shortest)
    return estimate


def _tetrahedralize(
    surface: Surface,
    *,
    edge_length: float | None,
    resolution: int | None,
    repair: bool | None,
    progress: bool,
    source: str,
    cache_dir: str | os.PathLike[str] | bool | None,
    checked: CheckedSurface | None = None,
    simplify: bool = True,
) -> tuple[TetMesh, SurfaceReport, dict]:
    """:func:`tetrahedralize`, also returning the surface report and what was done
    (``simplify=False``: fTetWild gets the surface as it is)."""
    if checked is None:
        _check_surface_arrays(surface, source)
        edge_length_for(1.0, edge_length, resolution, source)  # options first: fail fast
        with activity(f"checking {source} ({counted(surface.n_faces, 'triangle')})",
                      progress):
            checked = checked_surface(surface, source)
    report = checked.report
    if repair is False:
        _refuse_defects(report, source)
    h = edge_length_for(report.diagonal, edge_length, resolution, source)
    asked = f"edge_length={edge_length}" if edge_length is not None else \
        f"resolution={resolution or DEFAULT_RESOLUTION}"
    estimate = check_tet_budget(report, h, source, asked)
    V, F = checked.vertices, checked.faces
    simple = mesh_checks.simplified_envelope(V, F, h, report.area) if simplify else None
    if simple is not None:
        V, F = simple
    used = np.unique(F)
    compact = np.zeros(len(V), dtype=np.int64)
    compact[used] = np.arange(len(used))
    V, F = V[used], compact[F]
    info = {"edge_length": h, "estimate": estimate, "input_faces": len(F),
            "simplified": simple is not None}
    import pytetwild

    envelope = float(np.clip(ENVELOPE_PER_EDGE * h / report.diagonal, 1e-3, 1e-2))
    cached = _tet_cache(V, F, h, envelope, cache_dir)
    tv = tt = None
    if cached is not None and cached.exists():
        try:
            with np.load(cached) as data:
                tv, tt = data["vertices"], data["tets"]
        except (OSError, ValueError, KeyError):
            cached.unlink(missing_ok=True)
    if tv is None:
        what = (f"{counted(len(F), 'triangle')} simplified from {report.n_faces}"
                if simple is not None else counted(len(F), "triangle"))
        with activity(f"tetrahedralizing {source} (fTetWild: {what}, about "
                      f"{_round(estimate)} tets)", progress), _scratch_cwd():
            tv, tt = pytetwild.tetrahedralize(
                np.ascontiguousarray(V),
                np.ascontiguousarray(F, dtype=np.int32),
                edge_length_abs=float(h),
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
            f"that is thick compared to the edge length {h:.3g} m."
        )
    used = np.unique(tt)
    compact = np.zeros(len(tv), dtype=np.int64)
    compact[used] = np.arange(len(used))
    mesh = TetMesh(np.asarray(tv, dtype=np.float64)[used], compact[tt])
    return check_tet_mesh(mesh, f"{source} (tetrahedralized)"), report, info


def _round(x: float) -> str:
    """A count to two significant digits ("4700")."""
    return f"{float(f'{x:.2g}'):.0f}"


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
    B = mesh.boundary_faces()
    area = 0.5 * float(np.linalg.norm(np.cross(V[B[:, 1]] - V[B[:, 0]],
                                               V[B[:, 2]] - V[B[:, 0]]), axis=1).sum())
    report = SurfaceReport(n_faces=len(B), volume=float(mesh.volumes().sum()), area=area,
                           diagonal=diagonal(V[np.unique(T)]))
    checked = CheckedSurface(V, B, report)  # a tet mesh's boundary: closed, oriented outwards
    for _ in range(3):
        coarse, _, _ = _tetrahedralize(
            Surface(V, B), edge_length=edge, resolution=None, repair=True, progress=False,
            source="coarse mesh", cache_dir=cache_dir, checked=checked,
            simplify=False)  # its boundary must follow the fine mesh (the warp's lift)
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


def load_model(
    path: str | Path,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    progress: bool = False,
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> Model:
    """Load a model, tetrahedralize it if it is a surface and embed the surface.

    :func:`load_mesh`, then :func:`build_model`.

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
    return build_model(load_mesh(path), str(path), edge_length=edge_length,
                       resolution=resolution, repair=repair, progress=progress,
                       cache_dir=cache_dir)


def build_model(
    loaded: TetMesh | Surface,
    source: str,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    progress: bool = False,
    cache_dir: str | os.PathLike[str] | bool | None = None,
    checked: CheckedSurface | None = None,
) -> Model:
    """The model of a loaded surface or tet mesh (:func:`load_mesh`).

    For a surface: :func:`tetrahedralize` (with the given options; ``checked`` is the
    surface's :func:`wiggly.mesh_checks.inspect_surface` if already done) and :func:`embed` of
    the surface vertices.  One :class:`MeshRepairWarning` says what was unusual: the
    surface's defects, and surface vertices farther than ``FAR_OUTSIDE`` tet edge lengths
    outside the tets (parts thinner than the tets).  For a tet mesh: the surface has all the
    tet mesh vertices (same indices, so groups and keyframes address the same vertices;
    interior vertices are simply not used by any face) and the mesh's boundary faces; the
    embedding puts every vertex at a corner of one of its tets (barycentrics ``(1, 0, 0, 0)``
    up to order), so ``embedding.matrix(n)`` is the identity (vertices used by no tet, if
    any, are placed by :func:`embed`).
    """
    if isinstance(loaded, Surface):
        tets, report, info = _tetrahedralize(
            loaded, edge_length=edge_length, resolution=resolution, repair=repair,
            progress=progress, source=source, cache_dir=cache_dir, checked=checked)
        embedding = embed(loaded.vertices, tets)
        outside = embedding.outside_distance(tets)[np.unique(loaded.faces)] / info["edge_length"]
        far = outside > FAR_OUTSIDE
        if not report.clean or far.any():
            warnings.warn(repair_note(source, report, int(far.sum()), float(outside.max())),
                          MeshRepairWarning, stacklevel=2)
        return Model(loaded, tets, embedding, source)
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


def _as_groups(groups: dict) -> dict[str, np.ndarray]:
    """Groups as a dict of str to flat int64 index arrays."""
    return {str(k): np.asarray(v, dtype=np.int64).ravel() for k, v in groups.items()}


def _check_surface_arrays(surface: Surface, source: str) -> None:
    """Raise for an empty surface, non-finite coordinates or out-of-range face indices."""
    if surface.n_faces == 0:
        raise WigglyInputError(f"{source}: the surface has no triangles.")
    checks.finite_vertices(surface.vertices, source)
    checks.indices_in_range(surface.faces, surface.n_vertices, source, "face")


def _tet_volumes(V: np.ndarray, T: np.ndarray) -> np.ndarray:
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


def _count_components(T: np.ndarray, n: int) -> int:
    """Number of connected components of the tets (vertex-sharing tets are connected)."""
    if len(T) == 0:
        return 0
    rows = np.repeat(T[:, 0], 3)
    cols = T[:, 1:].ravel()
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return len(np.unique(labels[np.unique(T)]))
