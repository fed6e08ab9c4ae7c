"""Checks of meshes before they are used: tet meshes (oriented, non-degenerate) and
surfaces (what fTetWild can fill, and what it has to repair)."""

from __future__ import annotations

import numpy as np

from wiggly import checks
from wiggly.errors import WigglyInputError, counted
from wiggly.mesh import defects as mesh_checks
from wiggly.mesh.data import Surface, TetMesh, check_surface_arrays, tet_volumes
from wiggly.mesh.defects import (
    DEGENERATE_VOLUME,
    CheckedSurface,
    SurfaceReport,
)

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
    vol = tet_volumes(V, T)
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
    triangle pairs (see :class:`wiggly.mesh.defects.SurfaceReport`).

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
    refuse_defects(checked.report, source)
    V, F = surface.vertices, surface.faces
    volume = mesh_checks.enclosed_volume(V, F)
    if volume >= 0:
        return surface
    return Surface(V, F[:, ::-1], surface.uvs, surface.normals, dict(surface.groups))


class SurfaceDefectError(WigglyInputError):
    """A surface refused by the strict check (``repair=False``).  ``defects`` says what is
    wrong (without advice), so that callers can give advice in their own terms."""

    def __init__(self, message: str, source: str, defects: str):
        super().__init__(message)
        self.source, self.defects = source, defects


def refuse_defects(report: SurfaceReport, source: str) -> None:
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
    check_surface_arrays(surface, source)
    return mesh_checks.inspect_surface(surface.vertices, surface.faces, source)
