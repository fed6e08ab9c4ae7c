"""USD drivers: time-sampled mesh ``points`` (what Blender, Maya and Houdini write for a
deformed mesh), or UsdSkel skinning baked to points by USD itself (``UsdSkel.BakeSkinning``,
into the stage's session layer: the file is not touched).

Every ``UsdGeom.Mesh`` of the stage (in traversal order; ``object`` keeps the meshes whose
path or name is ``object`` and the meshes below a prim of that path or name) is evaluated at
every time code where its points or any transform above it has a sample, at the stage's
start and end, and at every whole time code inside longer gaps (:func:`_filled`): points in
world space (``UsdGeom.XformCache``), converted to wiggly's axes and units: a Z-up stage is
turned to Y up as Blender's glTF and OBJ exporters do, (x, y, z) -> (x, z, -y), and coordinates are
scaled by the stage's ``metersPerUnit``.  Time = time code / ``timeCodesPerSecond`` (wiggly's
own USD files keep their exact start time in the layer's ``customLayerData``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wiggly.drive.driver import Driver, fan_triangles, filled_times, polygon_edges
from wiggly.errors import WigglyInputError

__all__ = ["read_usd"]


def _meshes(stage, object: str | None, path: Path) -> list:
    from pxr import Usd, UsdGeom

    meshes = [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdGeom.Mesh)]
    if not meshes:
        raise WigglyInputError(f"cannot read {path}: no UsdGeom.Mesh in the stage")
    if object is None:
        return meshes

    def chosen(prim) -> bool:
        while prim and not prim.IsPseudoRoot():
            if object in (str(prim.GetPath()), prim.GetName()):
                return True
            prim = prim.GetParent()
        return False

    kept = [m for m in meshes if chosen(m)]
    if not kept:
        raise WigglyInputError(
            f"cannot read {path}: no mesh at or below a prim named {object!r}; its meshes are: "
            + ", ".join(str(m.GetPath()) for m in meshes))
    return kept


def _time_codes(meshes) -> list[float]:
    """Time codes of the points of ``meshes`` and of the transforms above them."""
    from pxr import UsdGeom

    codes: set[float] = set()
    for mesh in meshes:
        codes.update(UsdGeom.Mesh(mesh).GetPointsAttr().GetTimeSamples())
        prim = mesh
        while prim and not prim.IsPseudoRoot():
            if prim.IsA(UsdGeom.Xformable):
                codes.update(UsdGeom.Xformable(prim).GetTimeSamples())
            prim = prim.GetParent()
    return sorted(codes)


#: At most this many time codes are read from a stage (gaps are filled up to it).
MAX_CODES = 20000


def _filled(codes: list[float], stage) -> list[float]:
    """The time codes to read: the samples, the stage's start and end time codes (where it
    has them, and samples) and time codes about one apart inside every gap of more than 1.5
    between them (:func:`wiggly.drive.driver.filled_times`), so that holds between sparse
    samples (Blender writes a sample only where the mesh changes) are read as USD plays them
    (held before the first sample and after the last, interpolated by the stage between),
    not joined by a cubic that swings through them."""
    if not codes:
        return []
    ends = {stage.GetStartTimeCode(), stage.GetEndTimeCode()} if \
        stage.HasAuthoredTimeCodeRange() else set()
    known = sorted(set(codes) | ends)
    filled = filled_times(np.asarray(known, np.float64), 1.0)  # one a time code
    return known if len(filled) > MAX_CODES else [float(c) for c in filled]


def _bake_skinning(stage) -> bool:
    """Bake UsdSkel skinning into time-sampled points in the session layer; whether any
    skinned mesh was found."""
    from pxr import Usd, UsdSkel

    roots = [p for p in stage.Traverse() if p.IsA(UsdSkel.Root)]
    if not roots:
        return False
    # the session layer keeps USD's default 24 time codes per second; samples authored
    # there from a stage of another rate (Blender writes its scene's, e.g. 30) land at
    # scaled times, and the baked points then lag the skeleton (by 110 mm on a 30 fps
    # Blender plant): author them at the stage's rate
    session = stage.GetSessionLayer()
    session.timeCodesPerSecond = stage.GetTimeCodesPerSecond()
    # and one baked sample per time code: at the stage's framesPerSecond, where it differs
    # (Blender 5 writes 24 beside a 30 fps scene's 30 time codes per second), the bake adds
    # samples between the codes (2.25, 3.5, ...), frames the scene does not have
    session.framesPerSecond = stage.GetTimeCodesPerSecond()
    stage.SetEditTarget(Usd.EditTarget(session))
    for root in roots:
        if not UsdSkel.BakeSkinning(UsdSkel.Root(root)):
            raise WigglyInputError(f"USD could not evaluate the skinning of {root.GetPath()}")
    return True


def read_usd(path: Path, *, object: str | None = None) -> Driver:
    """The driver of a ``.usd`` / ``.usda`` / ``.usdc`` / ``.usdz`` file (module
    docstring)."""
    from pxr import Sdf, Usd, UsdGeom

    path = Path(path)
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:  # USD keeps opened layers: read the file as it is now
        layer.Reload(force=True)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Exception as e:  # pxr raises Tf errors of its own
        raise WigglyInputError(f"cannot read {path}: USD could not open it ({e})") from None
    if stage is None:
        raise WigglyInputError(f"cannot read {path}: USD could not open it")
    skinned = _bake_skinning(stage)
    meshes = _meshes(stage, object, path)
    codes = _filled(_time_codes(meshes), stage) or [Usd.TimeCode.Default()]
    faces, edges, counts, offset = [], [], [], 0
    for mesh in meshes:
        m = UsdGeom.Mesh(mesh)
        fc = np.asarray(m.GetFaceVertexCountsAttr().Get() or [], np.int64)
        fi = np.asarray(m.GetFaceVertexIndicesAttr().Get() or [], np.int64)
        n = len(m.GetPointsAttr().Get(codes[0]) or [])
        if fc.sum() != len(fi) or (len(fi) and (fi.min() < 0 or fi.max() >= n)):
            raise WigglyInputError(f"cannot read {path}: mesh {mesh.GetPath()} has inconsistent "
                                   "faceVertexCounts / faceVertexIndices")
        tri, polys = fan_triangles(fc, fi)
        faces.append(tri + offset)
        edges.append(polygon_edges(polys) + offset)
        counts.append(n)
        offset += n
    positions = np.empty((len(codes), offset, 3))
    for k, code in enumerate(codes):
        cache = UsdGeom.XformCache(code)
        start = 0
        for mesh, n in zip(meshes, counts, strict=True):
            P = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(code) or [], np.float64)
            if len(P) != n:
                raise WigglyInputError(
                    f"cannot read {path}: mesh {mesh.GetPath()} has {len(P)} points at time code "
                    f"{code} but {n} at the first; a driver keeps its vertices")
            M = np.asarray(cache.GetLocalToWorldTransform(mesh))  # row vectors: p M
            positions[k, start:start + n] = P @ M[:3, :3] + M[3, :3]
            start += n
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        positions = np.stack([positions[..., 0], positions[..., 2], -positions[..., 1]], -1)
    positions *= UsdGeom.GetStageMetersPerUnit(stage)
    if isinstance(codes[0], Usd.TimeCode) or len(codes) < 2:
        samples = "no time samples" if isinstance(codes[0], Usd.TimeCode) else "one time sample"
        raise WigglyInputError(
            f"cannot use {path} as a driver: it has no animation (its mesh points and "
            f"skeleton have {samples}); a driver needs two frames or more. "
            "Export it with animation on (Blender: File > Export > Universal Scene "
            "Description, Animation)")
    else:
        tcps = stage.GetTimeCodesPerSecond()
        times = np.asarray(codes, np.float64) / tcps
        ours = stage.GetRootLayer().customLayerData.get("wiggly", {})
        if "start_time" in ours and "frame_start" in ours:  # written by wiggly.export
            times = ours["start_time"] + (np.asarray(codes, np.float64) - ours["frame_start"]) \
                / tcps
    kind = "USD skinning" if skinned else "USD points"
    return Driver(times, positions, np.concatenate(faces), np.concatenate(edges), str(path),
                  kind, tuple(str(mesh.GetPath()) for mesh in meshes))
