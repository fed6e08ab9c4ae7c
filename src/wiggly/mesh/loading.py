"""Reading models: surfaces (PLY, STL, OFF, glTF: trimesh; OBJ: :mod:`wiggly.mesh.obj`) and
tet meshes (MSH, VTU, MESH, ...: meshio), with their vertex groups; the bundled models."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import meshio
import numpy as np

from wiggly import checks
from wiggly.errors import WigglyInputError, warn
from wiggly.mesh.data import (
    CELL_DIMENSION,
    SURFACE_EXTENSIONS,
    VOLUME_CELLS,
    VOLUME_EXTENSIONS,
    Surface,
    TetMesh,
    check_surface_arrays,
)
from wiggly.mesh.defects import diagonal
from wiggly.mesh.obj import read_obj
from wiggly.mesh.validate import check_tet_mesh
from wiggly.progress import activity

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


#: Up axes a mesh file may have; wiggly's is y (glTF's, Blender's exports, USD's default).
UP_AXES = ("y", "z")


def load_mesh(path: str | Path, scale: float = 1.0, up: str = "y") -> TetMesh | Surface:
    """Read a tetrahedral mesh or a triangle surface from a file.

    Surface formats (``.obj .ply .stl .off``) are read with trimesh
    (``process=False``), which keeps the file's vertices, their order and the
    faces, with these exceptions:

    - STL stores every triangle with its own three corners, so the surface has
      ``3 * n_faces`` vertices in face order (welded by position in
      :func:`check_surface` and :func:`tetrahedralize`).
    - OBJ is read by :func:`wiggly.mesh.obj.read_obj`: the vertices are all the
      file's ``v`` lines, in order (also those no face uses), faces in file
      order, polygons split into triangles, negative indices counted back.
      Texture coordinates and normals are attached per vertex only when every
      corner of a vertex has the same ``vt`` (``vn``); at a UV seam (one ``v``
      with several ``vt``) ``uvs`` is ``None`` and a warning says so. OBJ
      groups (``g``, ``o``) and materials are not read.
    - PLY and OFF: exactly the file's vertices and faces.
    - glTF (``.glb .gltf``) is read by wiggly's glTF evaluator
      (:func:`wiggly.drive.gltf.rest_pose`, the one that reads drivers): the
      scene's triangle primitives concatenated depth first in node order, each
      with its node's scene transform, sparse accessors applied, default morph
      weights, skinned meshes posed by their joints' static transforms with
      their own node transform ignored, as the glTF specification says. glTF
      stores one UV per vertex, so its vertices are already split at seams.
      Every mesh node's vertices form a group named after the node, and each
      primitive of a mesh of several one named ``<node>/primitive <k>``.

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
    scale : float
        Metres per unit of the file: its coordinates are multiplied by it (0.01 for a file
        in centimetres, 0.001 for millimetres; wiggly's units are SI).
    up : {"y", "z"}
        The file's up axis: a Z-up file (CAD, 3ds Max, many STL files) is turned to wiggly's
        y up, ``(x, y, z) -> (x, z, -y)`` (a rotation: the surface keeps its orientation).

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
    scale = checks.positive_number(scale, "scale", "metres per unit of the file")
    if up not in UP_AXES:
        raise WigglyInputError(f"up = {up!r} is not an up axis; use one of {', '.join(UP_AXES)}")
    loaded = _load_mesh(resolve_builtin(path))
    if scale != 1.0:
        loaded.vertices = loaded.vertices * scale  # uniform: normals and orientation stay
    if up == "z":
        loaded.vertices = z_up_to_y_up(loaded.vertices)
        if isinstance(loaded, Surface) and loaded.normals is not None:
            loaded.normals = z_up_to_y_up(loaded.normals)
    return loaded


def z_up_to_y_up(X: np.ndarray) -> np.ndarray:
    """Z-up coordinates in wiggly's y-up axes: ``(x, y, z) -> (x, z, -y)``, a rotation by
    -90 degrees about x (the conversion of USD's and glTF's readers)."""
    return np.stack([X[..., 0], X[..., 2], -X[..., 1]], axis=-1)


def _load_mesh(path: Path) -> TetMesh | Surface:
    source = str(path)
    ext = _extension(path)
    if not path.is_file():
        where = "is a directory, not a file" if path.is_dir() else "does not exist"
        raise WigglyInputError(f"{source}: {where}; give the path of a mesh file.")
    size = path.stat().st_size
    with activity(f"reading {source} ({size / 1e6:.0f} MB)", enabled=size > LARGE_FILE):
        return _read(path, ext, source)


#: Mesh files larger than this (bytes) get a line while they are read.
LARGE_FILE = 20_000_000


def _read(path: Path, ext: str, source: str) -> TetMesh | Surface:
    if ext in SURFACE_EXTENSIONS:
        surface = _load_trimesh(path, ext)
        check_surface_arrays(surface, source)
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
    other = sorted(set(types) & VOLUME_CELLS)
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
    check_surface_arrays(surface, source)
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
                if CELL_DIMENSION.get(t) == dim
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
        _check_content(path, ext)
        if ext == ".stl":
            _check_stl_length(path)
        if ext == ".off":
            _check_off_counts(path)
        if ext in (".glb", ".gltf"):
            _check_glb_magic(path, ext)
            return _gltf_surface(path)
        if ext == ".obj":
            return read_obj(path)
        loaded = trimesh.load(path, process=False)
    except WigglyInputError:
        raise
    except Exception as exc:  # trimesh raises many types for malformed files
        raise WigglyInputError(_unreadable(path, ext, exc)) from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = _scene_meshes(loaded)
    else:
        meshes = [("", loaded, _file_normals(loaded))]
    meshes = [m for m in meshes if isinstance(m[1], trimesh.Trimesh) and len(m[1].faces)]
    if not meshes:
        raise WigglyInputError(_NO_TRIANGLES.format(source=source))
    surface = _concatenate(meshes)
    if ext == ".stl":
        _say_unwelded(path, surface.vertices)
    return surface


def _say_unwelded(path: Path, vertices: np.ndarray) -> None:
    """Say what an STL's three vertices per triangle cost: the outputs carry every one (a
    review's 9.9k-triangle duck gave a 35.7 MB .glb for 1.6 s, about six times a welded
    mesh's), and groups count them."""
    from wiggly.progress import say

    distinct = len(np.unique(vertices, axis=0))
    if distinct < 0.75 * len(vertices):
        say(f"{path.name}: an STL stores three vertices per triangle ({len(vertices)} here, "
            f"at {distinct} places), and wiggly keeps them, so groups count them and the "
            f"outputs are about {len(vertices) / distinct:.0f} times a welded mesh's size; "
            "export OBJ or PLY for shared vertices")


def _gltf_surface(path: Path) -> Surface:
    """A glTF surface as a viewer shows it with no animation, read by the glTF evaluator
    that reads drivers (:func:`wiggly.drive.gltf.rest_pose`), so vertices come in the
    driver's order.  trimesh is not used: it ignores sparse accessors (a bar whose sparse
    substitution moves its top from 1 m to 2 m is read 1 m long) and skins (the glTF
    specification, 3.7.3, ignores a skinned node's own transform; trimesh applies it, so a
    Blender rig scaled by 2 gives a rest mesh scaled by 4)."""
    from wiggly.drive.gltf import rest_pose  # the glTF evaluator; no solver import

    pose = rest_pose(path)
    _warn_posed(path, pose.bind, pose.positions)
    return Surface(pose.positions, pose.faces, uvs=pose.uvs, normals=pose.normals,
                   groups=pose.groups)


def _warn_posed(path: Path, bind: list[tuple[slice, np.ndarray]], posed: np.ndarray) -> None:
    """Warn when a skin's static pose deforms its mesh (no one affine map takes a skinned
    primitive's bind positions to its posed ones): the file's skeleton was not saved at its
    bind pose, so the rest mesh is bent as the pose bends it."""
    size = diagonal(posed)
    off = 0.0
    for where, stored in bind:
        A = np.c_[stored, np.ones(len(stored))]
        fit, *_ = np.linalg.lstsq(A, posed[where], rcond=None)
        off = max(off, float(np.linalg.norm(A @ fit - posed[where], axis=1).max()))
    if off > 1e-3 * size:
        warn(
            f"{path}: its skeleton is not at its bind pose (the pose moves vertices up to "
            f"{off:.3g} m, {100 * off / size:.2g} % of the mesh's size, beyond one rigid or "
            "affine motion), so the rest mesh is the posed mesh a viewer shows, bent as the "
            "pose bends it. For the undeformed mesh, export at the rest pose (Blender's glTF "
            "export: Data > Armature > Use Rest Position).")


#: The surface formats' names in messages, by extension.
FORMAT_NAMES = {".obj": "OBJ", ".ply": "PLY", ".stl": "STL", ".off": "OFF",
                ".glb": "binary glTF", ".gltf": "glTF"}
_ARTICLES = {".obj": "an", ".stl": "an", ".off": "an"}


def _is_text(data: bytes) -> bool:
    """Whether ``data`` looks like ASCII text (printable characters and whitespace)."""
    return not data.translate(None, bytes(range(32, 127)) + b"\t\r\n\f\v")


def _binary_stl(head: bytes, size: int) -> bool:
    """Whether a file of ``size`` bytes starting with ``head`` is a binary STL: its size is
    exactly what its header's triangle count says (whatever the header's text)."""
    return len(head) >= 84 and size == 84 + 50 * int.from_bytes(head[80:84], "little")


_OBJ_WORDS = {b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p", b"o", b"g", b"s", b"mtllib",
              b"usemtl"}


def _obj_like(head: bytes) -> bool:
    """Whether ``head`` reads as the start of a Wavefront OBJ file: text whose lines (but
    comments, and the last, maybe cut) all start with OBJ's words, ``v`` among them."""
    if b"\0" in head:
        return False
    words = [line.split(b"#", 1)[0].split()[:1] for line in head.splitlines()[:-1]]
    words = [w[0] for w in words if w]
    return b"v" in words and all(w in _OBJ_WORDS for w in words)


def _sniff(head: bytes, size: int) -> str | None:
    """The surface format a file's first bytes show (an extension), or None if unsure."""
    first = head.split(None, 1)[0] if head.strip() else b""
    if first == b"ply":
        return ".ply"
    if head.startswith(b"glTF"):
        return ".glb"
    if first in (b"OFF", b"COFF", b"NOFF", b"CNOFF", b"STOFF", b"4OFF"):
        return ".off"
    if _binary_stl(head, size):
        return ".stl"
    if first.lower() == b"solid" and b"facet" in head.lower() and _is_text(head):
        return ".stl"
    if head.lstrip().startswith(b"{") and b'"asset"' in head:
        return ".gltf"
    if _obj_like(head):
        return ".obj"
    return None


def _check_content(path: Path, ext: str) -> None:
    """Refuse an empty file, and a file whose first bytes show another format than its
    extension's (a binary STL named .obj), naming the format it is."""
    size = path.stat().st_size
    if size == 0:
        raise WigglyInputError(f"{path}: the file is empty (0 bytes); export or copy it "
                               "again.")
    with open(path, "rb") as file:
        head = file.read(1024)
    found = _sniff(head, size)
    if found is None or found == ext or {found, ext} == {".glb", ".gltf"}:
        return
    raise WigglyInputError(
        f"{path}: is {_ARTICLES.get(found, 'a')} {FORMAT_NAMES[found]} file, not "
        f"{FORMAT_NAMES[ext]} as its extension "
        f"says; rename it to end in {found} (or export it again as {FORMAT_NAMES[ext]}).")


def _check_off_counts(path: Path) -> None:
    """Refuse an OFF file with fewer vertex or face lines than its header announces (cut
    short while copied or downloaded): trimesh reads the faces it finds."""
    with open(path, "rb") as file:
        rows = [r.split(b"#", 1)[0].split() for r in file.read().splitlines()]
    rows = [r for r in rows if r]
    if not rows or not rows[0][0].endswith(b"OFF"):
        return  # not OFF's text form: trimesh says what it is
    header = rows[0][1:] if len(rows[0]) > 1 else (rows[1] if len(rows) > 1 else [])
    start = 1 if len(rows[0]) > 1 else 2
    try:
        n_vertices, n_faces = int(header[0]), int(header[1])
    except (IndexError, ValueError):
        return
    vertices = max(0, min(len(rows) - start, n_vertices))
    faces = max(0, len(rows) - start - n_vertices)
    if vertices < n_vertices or faces < n_faces:
        raise WigglyInputError(
            f"{path}: the file is cut short: its OFF header announces {n_vertices} vertices "
            f"and {n_faces} faces, but it holds {vertices} and {faces}; copy or export it again")


def _check_stl_length(path: Path) -> None:
    """Refuse an STL cut short (while copied or downloaded): a binary one shorter than its
    header says (also one whose header starts with "solid", as SolidWorks writes), an ASCII
    one without its closing ``endsolid``.  trimesh would read the triangles it finds, or
    none."""
    size = path.stat().st_size
    with open(path, "rb") as file:
        head = file.read(1024)
        file.seek(max(size - 256, 0))
        tail = file.read()
    ascii_stl = head.lstrip().lower().startswith(b"solid") and _is_text(head) \
        and not _binary_stl(head, size)
    if ascii_stl:
        if b"endsolid" not in tail.lower():
            raise WigglyInputError(
                f"{path}: the file is cut short: an ASCII STL ends with an 'endsolid' line, "
                f"and this one stops after {size} bytes without it; copy or export it again")
        return
    if len(head) < 84:
        raise WigglyInputError(f"{path}: is not an STL file: it has {size} bytes, fewer "
                               "than a binary STL's 84-byte header")
    n = int.from_bytes(head[80:84], "little")
    if size < 84 + 50 * n:
        raise WigglyInputError(
            f"{path}: the file is cut short: its binary STL header announces {n} triangles "
            f"({84 + 50 * n} bytes) but it has {size} bytes; copy or export it again")


def _check_glb_magic(path: Path, ext: str) -> None:
    """Refuse a .glb that does not start with glTF's magic (a text file, another format)."""
    if ext != ".glb":
        return
    with open(path, "rb") as file:
        magic = file.read(4)
    if magic != b"glTF":
        raise WigglyInputError(f"{path}: is not a binary glTF file (it does not start with "
                               "'glTF'); check its extension, or export it again as .glb")


def _unreadable(path: Path, ext: str, exc: Exception) -> str:
    """What to tell of a surface file trimesh could not read: the reader's own words."""
    kind = ext.lstrip(".").upper()
    return (f"{path}: could not be read as {kind} ({type(exc).__name__}: {exc}); check that "
            f"the file is complete and is {kind}, as its extension says")


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
