"""Universal Scene Description: time-sampled points of a Mesh prim named after the model."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError
from wiggly.export.animation import (
    FORMAT_VERSION,
    FrameNormals,
    SurfaceAnimation,
    format_library,
    frame_codes,
    frame_progress,
)

# ----------------------------------------------------------------------------------------------
# USD


def write_usd(path: Path, anim: SurfaceAnimation, *,
              frame_start: int | None = None) -> None:
    format_library("pxr", "usd-core", "USD")
    from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, Vt

    fps, codes = frame_codes(anim.times, frame_start, f"cannot write {path}")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(float(codes[0]))
    stage.SetEndTimeCode(float(codes[-1]))
    root_name = Tf.MakeValidIdentifier(anim.name)
    root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(root_name))
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    if root_name != anim.name:
        root.GetPrim().SetDisplayName(anim.name)
    # Blender names the imported object after the Mesh prim (merging the Xform into it)
    mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild(root_name))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(anim.faces), 3,
                                                                  np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(anim.faces.ravel().astype(np.int32)))
    if anim.uvs is not None:
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(anim.uvs.astype(np.float32)))
    points, extent = mesh.CreatePointsAttr(), mesh.CreateExtentAttr()
    # per-vertex normals of every frame, as the glTF and OBJ outputs carry (the input's turned
    # with the surface, else computed): the same shot shades alike in each format
    normals = mesh.CreateNormalsAttr()
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    frame_normals = FrameNormals(anim)
    for k in frame_progress(range(anim.n_frames), anim.n_frames, path):
        t = Usd.TimeCode(float(codes[k]))
        p = anim.positions[k].astype(np.float32)
        points.Set(Vt.Vec3fArray.FromNumpy(p), t)
        lo, hi = p.min(axis=0).tolist(), p.max(axis=0).tolist()
        extent.Set(Vt.Vec3fArray([Gf.Vec3f(*lo), Gf.Vec3f(*hi)]), t)
        nk = frame_normals(anim.positions[k]).astype(np.float32)
        normals.Set(Vt.Vec3fArray.FromNumpy(nk), t)
    stage.GetRootLayer().customLayerData = {"wiggly": {
        "format_version": FORMAT_VERSION, "start_time": float(anim.times[0]),
        "frame_start": int(codes[0]), "frames_per_second": float(fps),
        "loop": bool(anim.loop)}}
    if not stage.GetRootLayer().Export(str(path)):
        raise OSError(f"USD could not write {path}")


def _forget_usd_layer(path: Path) -> None:
    """Reload ``path`` if USD's layer registry still holds an older version of it."""
    from pxr import Sdf

    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)


def read_usd(path: Path) -> SurfaceAnimation:
    format_library("pxr", "usd-core", "USD")
    from pxr import Usd, UsdGeom

    _forget_usd_layer(path)
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise WigglyInputError(f"cannot read {path}: USD could not open it")
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if not meshes:
        raise WigglyInputError(f"cannot read {path}: no UsdGeom.Mesh in the stage")
    mesh = UsdGeom.Mesh(meshes[0])
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    if counts.size == 0 or np.any(counts != 3):
        raise WigglyInputError(f"cannot read {path}: mesh {mesh.GetPath()} is not a triangle "
                               "mesh (faceVertexCounts should all be 3)")
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), np.int64).reshape(-1, 3)
    points = mesh.GetPointsAttr()
    codes = points.GetTimeSamples() or [Usd.TimeCode.Default()]
    positions = np.stack([np.asarray(points.Get(c), np.float32) for c in codes])
    tcps = stage.GetTimeCodesPerSecond()
    times = (np.asarray(codes, np.float64) / tcps if points.GetTimeSamples() else np.zeros(1))
    ours = stage.GetRootLayer().customLayerData.get("wiggly", {})
    if points.GetTimeSamples() and "start_time" in ours and "frame_start" in ours:
        times = ours["start_time"] + (np.asarray(codes, np.float64) - ours["frame_start"]) / tcps
    uvs = normals = None
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    if st and st.HasValue():
        if st.GetInterpolation() not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
            raise WigglyInputError(f"cannot read {path}: primvars:st has interpolation "
                                   f"{st.GetInterpolation()}; only per-vertex uvs are read")
        uvs = np.asarray(st.ComputeFlattened(), np.float64)
    attr = mesh.GetNormalsAttr()
    if attr.HasValue():
        normals = np.asarray(attr.Get(codes[0]), np.float64)
    root = stage.GetDefaultPrim() or meshes[0]
    name = root.GetDisplayName() or root.GetName()
    return SurfaceAnimation(times, positions, faces, uvs, normals, name,
                            loop=bool(ours.get("loop", False)))
