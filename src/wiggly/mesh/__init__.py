"""Stage 1 of the pipeline: the user's model, its tetrahedral mesh and the embedding between them.

A user brings a triangle surface (OBJ, PLY, STL, OFF, glTF) or a tetrahedral mesh (MSH, VTU,
MESH, ...).  A surface is inspected (open edges, crossing triangles, orientation), filled with
linear tetrahedra by fTetWild (:func:`tetrahedralize`; imperfect surfaces are repaired, with
a warning) and its vertices are embedded in the tetrahedra with barycentric coordinates
(:func:`embed`), so the animation computed on the tet mesh is delivered on the user's own
surface: same vertices, same order, same faces.

* :mod:`~wiggly.mesh.data` -- :class:`TetMesh`, :class:`Surface`, :class:`Embedding`,
  :class:`Model`, :func:`embed`;
* :mod:`~wiggly.mesh.defects` -- what is unusual about a surface (open, non-manifold and
  misoriented edges, crossing pairs), its volume, and tet-count estimates;
* :mod:`~wiggly.mesh.validate` -- checks of tet meshes and surfaces;
* :mod:`~wiggly.mesh.loading` -- reading files, and the bundled models;
* :mod:`~wiggly.mesh.filling` -- fTetWild, cached on disk; coarse meshes of the same solid;
* :mod:`~wiggly.mesh.model` -- :func:`load_model`, :func:`build_model`.
"""

from wiggly.mesh.data import (
    DEFAULT_RESOLUTION,
    ENVELOPE_PER_EDGE,
    SURFACE_EXTENSIONS,
    VOLUME_EXTENSIONS,
    Embedding,
    Model,
    Surface,
    TetMesh,
    embed,
)
from wiggly.mesh.filling import (
    MeshRepairWarning,
    TetBudgetError,
    check_tet_budget,
    coarse_mesh,
    edge_length_for,
    repair_note,
    tetrahedralize,
)
from wiggly.mesh.loading import BUILTIN_MODELS, UP_AXES, load_mesh, resolve_builtin
from wiggly.mesh.model import build_model, load_model
from wiggly.mesh.validate import (
    SurfaceDefectError,
    check_surface,
    check_tet_mesh,
    checked_surface,
    inspect_surface,
)

__all__ = [
    "BUILTIN_MODELS",
    "DEFAULT_RESOLUTION",
    "ENVELOPE_PER_EDGE",
    "SURFACE_EXTENSIONS",
    "UP_AXES",
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
    "check_tet_budget",
    "check_tet_mesh",
    "checked_surface",
    "coarse_mesh",
    "edge_length_for",
    "embed",
    "inspect_surface",
    "load_mesh",
    "load_model",
    "repair_note",
    "resolve_builtin",
    "tetrahedralize",
]
