"""Named vertex groups of a scene, resolved against the mesh (box, sphere, nearest points,
indices, groups stored in the mesh file)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from wiggly.errors import counted
from wiggly.mesh.loading import z_up_to_y_up
from wiggly.scene.spec import (
    SELECTOR_KEYS,
    Absolute,
    Box,
    GroupSpec,
    Indices,
    Nearest,
    Scene,
    Sphere,
)
from wiggly.scene.validation import Problems, did_you_mean, show

# ----------------------------------------------------------------------------------------------
# groups (checked against the mesh)


def _placed(sel, X: np.ndarray) -> np.ndarray:
    """The vertices a box or sphere selector selects among positions ``X``."""
    if isinstance(sel, Box):
        return np.flatnonzero(np.all((X >= np.asarray(sel.min)) & (X <= np.asarray(sel.max)),
                                     axis=1))
    return np.flatnonzero(np.linalg.norm(X - np.asarray(sel.center), axis=1) <= sel.radius)


def _select(name: str, group: GroupSpec, X: np.ndarray, mesh_groups: dict[str, np.ndarray],
            what: str, p: Problems, y_up: bool = False) -> np.ndarray | None:
    """Vertex indices of one group among the rest positions ``X``; None (and a problem).
    ``y_up``: the file was read y up by default, so an empty box or sphere that would select
    vertices of a Z-up reading says so."""
    sel = group.selector
    path = f"groups.{name}"
    n = len(X)
    if isinstance(sel, (Box, Sphere)):
        idx = _placed(sel, X)
    elif isinstance(sel, Nearest):
        # positions, not vertices: coincident copies (an STL's corners) count once, all taken
        places, place_of = np.unique(X, axis=0, return_inverse=True)
        if sel.count > len(places):
            p.add(f"{path}.nearest.count = {sel.count} exceeds the number of vertex "
                  f"positions of the {what} ({len(places)})")
            return None
        _, nn = cKDTree(places).query(np.asarray(sel.points), k=sel.count)
        idx = np.flatnonzero(np.isin(place_of.ravel(), np.asarray(nn).ravel()))
    elif isinstance(sel, Indices):
        idx = np.asarray(sel.indices, dtype=np.int64)
        bad = np.flatnonzero(idx >= n)
        if bad.size:
            p.add(f"{path}.indices[{bad[0]}] = {idx[bad[0]]} is out of range: the {what} has "
                  f"{counted(n, 'vertex')} (indices 0..{n - 1})")
            return None
    else:
        if sel.name not in mesh_groups:
            have = (f"its groups are: {', '.join(mesh_groups)}" if mesh_groups else
                    "it has no vertex groups")
            p.add(f"{path}.from_mesh = {show(sel.name)}: the {what} has no vertex group of "
                  f"that name{did_you_mean(sel.name, mesh_groups)}; {have}")
            return None
        idx = np.asarray(mesh_groups[sel.name], dtype=np.int64)
    if idx.size == 0:
        lo, hi = X.min(axis=0), X.max(axis=0)
        turned = (len(_placed(sel, z_up_to_y_up(X))) if y_up and isinstance(sel, (Box, Sphere))
                  else 0)
        hint = (f"; read as a Z-up file (mesh.up_axis = \"z\": its z axis up), it would "
                f"select {counted(turned, 'vertex')}" if turned else "")
        p.add(f"{path} ({SELECTOR_KEYS[type(sel)]}) selects no vertex of the {what}; its "
              f"bounding box is {show(lo.round(4).tolist())} .. {show(hi.round(4).tolist())}"
              + hint)
        return None
    return idx


def resolve_groups(scene: Scene, model=None, *, surface=None) -> dict[str, np.ndarray]:
    """Vertex indices of every group: of the user's surface, or of the tet mesh for
    ``on = "tets"`` (``model`` a :class:`wiggly.Model`).  Without a model (a mesh not yet
    tetrahedralized), ``surface`` alone resolves the surface groups; tet groups are left
    out.  Raises a :class:`WigglyInputError` listing every group that is invalid."""
    if model is not None:
        surface, tet_X, tet_groups = model.surface, model.tets.vertices, model.tets.groups
    elif surface is not None:
        tet_X = tet_groups = None
    else:
        raise TypeError("resolve_groups needs a model or a surface")
    p = Problems(scene.where())
    out = resolve_group_arrays(scene, surface.vertices, surface.groups, tet_X, tet_groups, p)
    p.raise_if_any()
    return out


def resolve_group_arrays(scene: Scene, surface_X, surface_groups, tet_X, tet_groups,
                         p: Problems) -> dict[str, np.ndarray]:
    """The groups of ``scene`` on the given vertex arrays (``tet_X`` None: surface groups
    only), adding every mistake to ``p``."""
    out = {}
    y_up = scene.mesh.up_axis is None  # the default: a Z-up file would lie on its side
    for name, g in scene.groups.items():
        if g.on == "tets":
            if tet_X is None:
                continue
            idx = _select(name, g, tet_X, tet_groups, "tet mesh", p, y_up)
        else:
            idx = _select(name, g, surface_X, surface_groups, "surface", p, y_up)
        if idx is not None:
            out[name] = idx
    for j, kf in enumerate(scene.keyframes):
        if isinstance(kf.position, Absolute) and kf.group in out:
            k, rows = len(out[kf.group]), len(kf.position.positions)
            if rows != k:
                p.add(f"keyframes[{j}].position.absolute has {counted(rows, 'row')} but "
                      f"group {kf.group!r} has {counted(k, 'vertex')}; give one [x, y, z] per "
                      "vertex")
    return out
