"""Embedding the user's surface in the tet mesh, and loading a model from a file."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from wiggly.checks import mesh_arrays
from wiggly.errors import counted, warn
from wiggly.mesh.data import Embedding, Model, Surface, TetMesh, embed, without_small_pieces
from wiggly.mesh.defects import (
    CheckedSurface,
    diagonal,
    enclosed_volume,
)
from wiggly.mesh.filling import (
    FAR_OUTSIDE,
    LARGE_SURFACE,
    MeshRepairWarning,
    repair_note,
    tetrahedralize_with_report,
    volume_lost,
)
from wiggly.mesh.loading import load_mesh
from wiggly.progress import activity, deprecated_progress

#: Solid pieces of a filled surface's tet mesh with less than this share of its volume are left
#: out (:func:`wiggly.mesh.data.without_small_pieces`); larger loose parts are refused by the
#: eigenmode stage unless held by fixed vertices.
SMALL_PIECE = 0.02


@deprecated_progress
def load_model(
    path: str | Path,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    cache_dir: str | os.PathLike[str] | bool | None = None,
    scale: float = 1.0,
    up: str = "y",
) -> Model:
    """Load a model, tetrahedralize it if it is a surface and embed the surface.

    :func:`load_mesh`, then :func:`build_model`.

    Parameters
    ----------
    path : str or Path
        Surface or tet mesh file (see :func:`load_mesh`).
    edge_length, resolution, repair
        Passed to :func:`tetrahedralize` for a surface; ignored for a tet mesh.
    scale : float
        Metres per unit of the file (:func:`load_mesh`): 0.01 for centimetres.
    up : {"y", "z"}
        The file's up axis (:func:`load_mesh`).

    Returns
    -------
    Model
    """
    return build_model(load_mesh(path, scale, up), str(path), edge_length=edge_length,
                       resolution=resolution, repair=repair, cache_dir=cache_dir)


@deprecated_progress
def build_model(
    loaded: TetMesh | Surface,
    source: str,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    cache_dir: str | os.PathLike[str] | bool | None = None,
    checked: CheckedSurface | None = None,
) -> Model:
    """The model of a loaded surface or tet mesh (:func:`load_mesh`).

    For a surface: :func:`tetrahedralize` (with the given options; ``checked`` is the
    surface's :func:`wiggly.mesh.defects.inspect_surface` if already done) and :func:`embed` of
    the surface vertices.  One :class:`MeshRepairWarning` says what was unusual: the
    surface's defects, small solid pieces of the tet mesh left out (less than
    ``SMALL_PIECE`` of its volume, joined to the rest by an edge, a vertex or nothing: they
    would hinge there), surface vertices farther than ``FAR_OUTSIDE`` tet edge lengths
    outside the tets, and tets lacking more than ``LOST_VOLUME`` of the surface's enclosed
    volume (both: parts thinner than the tets).  For a tet mesh: the surface has all the
    tet mesh vertices (same indices, so groups and keyframes address the same vertices;
    interior vertices are simply not used by any face) and the mesh's boundary faces; the
    embedding puts every vertex at a corner of one of its tets (barycentrics ``(1, 0, 0, 0)``
    up to order), so ``embedding.matrix(n)`` is the identity (vertices used by no tet, if
    any, are placed by :func:`embed`).
    """
    _warn_units(loaded.vertices, source)
    if isinstance(loaded, Surface):
        loaded = _outward(loaded, source)
        tets, report, info = tetrahedralize_with_report(
            loaded, edge_length=edge_length, resolution=resolution, repair=repair,
            source=source, cache_dir=cache_dir, checked=checked)
        # slivers and bits that hold to the body by an edge or a vertex only would hinge
        # there (a motion of zero elastic energy): the surface around them follows the
        # nearest tets of the body instead
        tets, dropped, share = without_small_pieces(tets, SMALL_PIECE)
        with activity(f"placing {counted(loaded.n_vertices, 'surface vertex')} in the "
                      f"{counted(tets.n_tets, 'tet')}",
                      enabled=loaded.n_faces > LARGE_SURFACE):
            embedding = embed(loaded.vertices, tets)
        outside = embedding.outside_distance(tets)[np.unique(loaded.faces)] / info["edge_length"]
        far = outside > FAR_OUTSIDE
        filled = float(tets.volumes().sum())
        if not report.clean or far.any() or dropped or volume_lost(report, filled):
            warn(repair_note(source, report, int(far.sum()), float(outside.max()),
                                      dropped, share, filled, info["edge_length"]),
                 MeshRepairWarning)
        return Model(loaded, tets, embedding, source)
    mesh_arrays(loaded.vertices, loaded.tets, source)  # indices in range, tets present
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


def _outward(surface: Surface, source: str) -> Surface:
    """The surface with its triangles facing outwards: when they enclose a negative volume
    (every triangle turned inwards, as some exporters write), all are flipped, with a
    warning, so that the outputs are not shown inside out by viewers that cull back faces.
    File normals then go (they belonged to the inward triangles, or contradicted them)."""
    V, F = surface.vertices, surface.faces
    volume = enclosed_volume(V, F)
    if not volume < 0:
        return surface
    warn(
        f"{source}: the surface's triangles face inwards (they enclose a volume of "
        f"{volume:.3g} m^3); wiggly flipped them all, so that its outputs face outwards",
        MeshRepairWarning)
    return replace(surface, faces=np.ascontiguousarray(F[:, ::-1]), normals=None)


#: Bodies whose bounding-box diagonal lies outside this range (m) are likely in other units
#: (props modelled in centimetres or millimetres are tens of "metres" across: a 50 cm block
#: read as 50 m, a 42 mm gear as 42 m; a body larger than 20 m is rare and is told how to
#: keep it).
PLAUSIBLE_SIZE = (1e-3, 20.0)


def _warn_units(vertices: np.ndarray, source: str) -> None:
    """Warn when a mesh's size suggests millimetres or kilometres read as metres (wiggly's
    units are SI: a 1.2 m capsule exported in millimetres becomes a 1.2 km body of 3e10 kg
    whose modes are a few mHz)."""
    size = diagonal(vertices)
    low, high = PLAUSIBLE_SIZE
    if low <= size <= high or size == 0.0 or not np.isfinite(size):
        return  # (non-finite coordinates are refused with their own message)
    hint = ("millimetres or centimetres, scale it by 0.001 or 0.01" if size > high
            else "kilometres, scale it by 1000")
    warn(
        f"{source}: the mesh is {size:.3g} m across; wiggly reads its coordinates as metres "
        f"(SI units throughout). If the file is in {hint} (a scene file's mesh.scale, the "
        "scale= of wiggly.prepare and load_model; or in Blender, the object's applied scale "
        "or the exporter's Scale); if the body is that large, nothing needs doing")
