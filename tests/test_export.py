"""Animation export (export.py): round trips through every format, each checked by an independent
reader (pygltflib, pxr, meshio, numpy), the Khronos glTF validator, USD's validators, atomic
writes, overwrite protection and input validation."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
from pathlib import Path

import meshio
import numpy as np
import pytest
import trimesh

from wiggly import export
from wiggly.errors import WigglyInputError
from wiggly.export import (
    SUPPORTED,
    SurfaceAnimation,
    formats,
    read_animation,
    vertex_normals,
    write_animation,
)
from wiggly.export import obj as obj_format
from wiggly.export.animation import FrameNormals, checked_animation
from wiggly.export.obj import frame_names
from wiggly.progress import reporting

GLTF_VALIDATOR = "gltf-validator@2.0.0-dev.3.10"
EXTENSIONS = sorted(SUPPORTED)
EPS32 = float(np.finfo(np.float32).eps)


def rotation(axis, angle) -> np.ndarray:
    """Rodrigues' rotation matrix."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def sphere_animation(F=12, subdivisions=3, uvs=True, normals=False, times=None, rigid=False,
                     dtype=np.float64, name="ball") -> SurfaceAnimation:
    """A unit icosphere that tumbles, rises and (unless rigid) squashes, at 24 fps."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    V, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    t = np.arange(F) / 24.0 if times is None else np.asarray(times, float)
    frames = []
    for tk in t:
        S = np.diag([1.0, 1.0, 1.0]) if rigid else np.diag([1 + 0.3 * np.sin(5 * tk), 1.0, 1.0])
        frames.append(V @ S.T @ rotation([1, 2, 0.5], 2.0 * tk).T + [0.1 * tk, 0.5 * tk, 0])
    uv = np.column_stack([np.arctan2(V[:, 2], V[:, 0]) / (2 * np.pi) + 0.5,
                          np.arcsin(np.clip(V[:, 1], -1, 1)) / np.pi + 0.5]) if uvs else None
    rest_normals = None
    if normals:  # deliberately not the mesh's normals: a fixed tilt, so transport is visible
        rest_normals = V + 0.3 * np.array([0.0, 1.0, 0.0])
        rest_normals /= np.linalg.norm(rest_normals, axis=1, keepdims=True)
    return SurfaceAnimation(t, np.asarray(frames, dtype), faces, uv, rest_normals, name)


def grid_animation(nx, ny, F=2) -> SurfaceAnimation:
    """A flat nx x ny grid of vertices waving in z (for more than 65535 vertices)."""
    x, y = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="ij")
    V = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    i = np.arange(nx - 1)[:, None] * ny + np.arange(ny - 1)[None, :]
    i = i.ravel()
    faces = np.concatenate([np.column_stack([i, i + ny, i + ny + 1]),
                            np.column_stack([i, i + ny + 1, i + 1])])
    P = np.stack([V + [0, 0, 0.1 * k] * np.sin(np.pi * V[:, :1]) for k in range(F)])
    return SurfaceAnimation(np.arange(F) / 30.0, P, faces, V[:, :2].copy(), None, "grid")


def position_tolerance(anim) -> float:
    """A few float32 ulps of the largest coordinate."""
    return 4 * EPS32 * float(np.abs(anim.positions).max())


def out_name(ext: str) -> str:
    return "frame.obj" if ext == ".obj" else f"anim{ext}"


def listing(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


# ----------------------------------------------------------------------------------------------
# round trips through read_animation


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize("extras", [True, False], ids=["uvs+normals", "bare"])
def test_round_trip(tmp_path, ext, extras):
    anim = sphere_animation(uvs=extras, normals=extras, dtype=np.float32 if extras else np.float64)
    path = write_animation(tmp_path / out_name(ext), anim)
    back = read_animation(path)
    assert back.times == pytest.approx(anim.times, abs=1e-9)
    assert back.positions.shape == anim.positions.shape
    np.testing.assert_allclose(back.positions, anim.positions, rtol=0,
                               atol=position_tolerance(anim))
    np.testing.assert_array_equal(back.faces, anim.faces)
    if extras:
        np.testing.assert_allclose(back.uvs, anim.uvs, atol=1e-7)
        np.testing.assert_allclose(back.normals, anim.normals, atol=1e-6)  # rest normals
    else:
        assert back.uvs is None
    assert back.name == "ball"


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_non_uniform_times_and_odd_name(tmp_path, ext):
    times = np.array([-0.25, 0.0, 0.01, 0.3, 1.7])
    anim = sphere_animation(F=5, times=times, name="my ball #2")
    back = read_animation(write_animation(tmp_path / out_name(ext), anim))
    np.testing.assert_allclose(back.times, times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.positions, anim.positions, atol=position_tolerance(anim))
    assert back.name == "my ball #2"


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_single_frame(tmp_path, ext):
    anim = sphere_animation(F=1, subdivisions=1)
    back = read_animation(write_animation(tmp_path / out_name(ext), anim))
    assert back.positions.shape == anim.positions.shape
    np.testing.assert_allclose(back.positions, anim.positions, atol=position_tolerance(anim))
    np.testing.assert_array_equal(back.faces, anim.faces)


# ----------------------------------------------------------------------------------------------
# glTF: Khronos validator and raw accessors


@pytest.fixture(scope="session")
def gltf_validator():
    """A function validating .glb files with the Khronos glTF validator (npm, cached)."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node and npm are needed for the Khronos glTF validator (npm gltf-validator)")
    cache = Path(os.environ.get("WIGGLY_TEST_CACHE", Path.home() / ".cache" / "wiggly-test"))
    prefix = cache / "gltf-validator"
    package = prefix / "node_modules" / "gltf-validator"
    version = GLTF_VALIDATOR.rsplit("@", 1)[1]
    try:
        installed = json.loads((package / "package.json").read_text())["version"]
    except (OSError, ValueError, KeyError):
        installed = None
    if installed != version:
        prefix.mkdir(parents=True, exist_ok=True)
        subprocess.run([npm, "install", "--prefix", str(prefix), "--no-audit", "--no-fund",
                        GLTF_VALIDATOR], check=True, capture_output=True, timeout=600)
    script = (
        "const fs = require('fs'); const v = require(process.argv[1]);"
        "Promise.all(process.argv.slice(2).map((f) => v.validateBytes("
        "new Uint8Array(fs.readFileSync(f)), {maxIssues: 0, writeTimestamp: false})))"
        ".then((r) => console.log(JSON.stringify(r)),"
        " (e) => { console.error(String(e)); process.exit(2); });"
    )

    def validate(paths) -> list[dict]:
        done = subprocess.run([node, "-e", script, str(package), *map(str, paths)],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    return validate


def test_gltf_holds_the_glb_embedded_and_passes_the_validator(tmp_path, gltf_validator):
    """.gltf is the .glb's JSON with the same data as a base64 data URI: read back, both give
    the same frames bit for bit, and the Khronos validator finds no error in it."""
    anim = sphere_animation(normals=True)
    glb = write_animation(tmp_path / "shot.glb", anim)
    text = write_animation(tmp_path / "shot.gltf", anim)
    doc = json.loads(text.read_text(encoding="utf-8"))
    assert doc["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    a, b = read_animation(glb), read_animation(text)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.times, b.times)
    np.testing.assert_array_equal(a.faces, b.faces)
    report = gltf_validator([text])[0]
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1
    assert 1.2 < text.stat().st_size / glb.stat().st_size < 1.4


def test_glb_passes_khronos_validator(tmp_path, gltf_validator):
    import pygltflib

    cases = {
        "uvs+normals": sphere_animation(normals=True),
        "bare": sphere_animation(uvs=False),
        "one frame": sphere_animation(F=1),
        "negative start": sphere_animation(F=4, times=[-1.0, -0.5, 0.25, 2.0]),
        "uint32 indices": grid_animation(260, 256),  # 66560 vertices > 65535
    }
    paths = [write_animation(tmp_path / f"case{i}.glb", anim)
             for i, anim in enumerate(cases.values())]
    reports = gltf_validator(paths)
    for (label, anim), report in zip(cases.items(), reports, strict=True):
        issues = report["issues"]
        errors = [m for m in issues["messages"] if m["severity"] == 0]
        assert issues["numErrors"] == 0, (label, errors)
        others = {m["code"] for m in issues["messages"]}
        print(f"{label}: {issues['numWarnings']} warnings, {issues['numInfos']} infos {others}")
        assert report["info"]["hasMorphTargets"] and report["info"]["animationCount"] == 1
        assert report["info"]["totalVertexCount"] == anim.n_vertices
        assert report["info"]["totalTriangleCount"] == len(anim.faces)
    # the validator is not vacuous: a wrong POSITION max is an error
    broken = tmp_path / "broken.glb"
    gltf = pygltflib.GLTF2().load(str(paths[0]))
    gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION].max = [9.0, 9.0, 9.0]
    gltf.save_binary(str(broken))
    assert gltf_validator([broken])[0]["issues"]["numErrors"] > 0


def raw_accessor(gltf, index) -> np.ndarray:
    """Accessor data straight from the buffer, with pygltflib's objects only."""
    acc = gltf.accessors[index]
    dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[acc.type]
    itemsize = np.dtype(dtype).itemsize
    if acc.bufferView is None:  # glTF: zeros, then the sparse entries (sec. 3.6.2.3)
        out = np.zeros((acc.count, width), dtype)
    else:
        view = gltf.bufferViews[acc.bufferView]
        stride = view.byteStride or itemsize * width
        assert stride % 4 == 0 and (view.byteOffset + acc.byteOffset) % 4 == 0
        out = np.ndarray((acc.count, width), dtype, buffer=gltf.binary_blob(),
                         offset=view.byteOffset + acc.byteOffset, strides=(stride, itemsize))
    if acc.sparse is not None:
        out = out.copy()
        sp_ = acc.sparse
        iview = gltf.bufferViews[sp_.indices.bufferView]
        vview = gltf.bufferViews[sp_.values.bufferView]
        idx = np.frombuffer(gltf.binary_blob(), {5125: np.uint32, 5123: np.uint16}[
            sp_.indices.componentType], sp_.count, iview.byteOffset)
        assert np.all(np.diff(idx.astype(np.int64)) > 0)  # strictly rising, as glTF asks
        out[idx] = np.frombuffer(gltf.binary_blob(), dtype, sp_.count * width,
                                 vview.byteOffset).reshape(-1, width)
    return out


def test_glb_morph_targets_reproduce_frames(tmp_path):
    import pygltflib

    anim = sphere_animation(F=10, normals=True)
    gltf = pygltflib.GLTF2().load(str(write_animation(tmp_path / "a.glb", anim)))
    prim = gltf.meshes[0].primitives[0]
    base = raw_accessor(gltf, prim.attributes.POSITION)
    P32 = anim.positions.astype(np.float32)
    np.testing.assert_array_equal(base, P32[0])
    acc = gltf.accessors[prim.attributes.POSITION]
    assert acc.min == base.min(axis=0).tolist() and acc.max == base.max(axis=0).tolist()
    assert len(prim.targets) == anim.n_frames
    for k, target in enumerate(prim.targets):
        delta = raw_accessor(gltf, target["POSITION"])
        # one float32 rounding of the delta and one of the sum
        np.testing.assert_allclose(base + delta, P32[k], rtol=0, atol=position_tolerance(anim))
        t_acc = gltf.accessors[target["POSITION"]]
        assert t_acc.min == delta.min(axis=0).tolist() and t_acc.max == delta.max(axis=0).tolist()
    # the weights animation: keyframe k is target k alone, at the frame times
    (animation,) = gltf.animations
    (channel,) = animation.channels
    assert channel.target.path == "weights" and channel.target.node == 0
    sampler = animation.samplers[channel.sampler]
    np.testing.assert_allclose(raw_accessor(gltf, sampler.input).ravel(),
                               anim.times.astype(np.float32))
    W = raw_accessor(gltf, sampler.output).reshape(anim.n_frames, anim.n_frames)
    np.testing.assert_array_equal(W, np.eye(anim.n_frames))
    # stored as its F ones (sparse), not F^2 floats: 18001 frames made 1.3 GB of zeros
    out = gltf.accessors[sampler.output]
    assert out.bufferView is None and out.sparse.count == anim.n_frames
    assert animation.extras["wiggly"]["times"] == anim.times.tolist()
    assert gltf.meshes[0].extras["targetNames"][3] == "frame_0003"
    # glTF's V axis points down: TEXCOORD_0 = (u, 1 - v)
    st = raw_accessor(gltf, prim.attributes.TEXCOORD_0)
    np.testing.assert_allclose(st, np.column_stack([anim.uvs[:, 0], 1 - anim.uvs[:, 1]]),
                               atol=1e-7)
    # base NORMAL = the file's rest normals; each frame's normal is a unit vector
    base_n = raw_accessor(gltf, prim.attributes.NORMAL)
    np.testing.assert_allclose(base_n, anim.normals, atol=1e-7)
    for target in prim.targets:
        n_k = base_n + raw_accessor(gltf, target["NORMAL"])
        np.testing.assert_allclose(np.linalg.norm(n_k, axis=1), 1, atol=1e-6)


def test_glb_normals_follow_a_rigid_motion(tmp_path):
    """Without rest normals, frame k's normals are the recomputed ones: on a rigidly moving
    sphere they point away from its centre (to within the mesh's faceting)."""
    import pygltflib

    anim = sphere_animation(F=6, subdivisions=4, uvs=False, rigid=True)
    gltf = pygltflib.GLTF2().load(str(write_animation(tmp_path / "a.glb", anim)))
    prim = gltf.meshes[0].primitives[0]
    base_n = raw_accessor(gltf, prim.attributes.NORMAL)
    for k, target in enumerate(prim.targets):
        n_k = base_n + raw_accessor(gltf, target["NORMAL"])
        P = anim.positions[k]
        radial = P - P.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert np.einsum("ij,ij->i", n_k, radial).min() > 0.999


@pytest.mark.parametrize("ext", [".usda", ".usdc"])
def test_usd_normals_follow_a_rigid_motion_without_rest_normals(tmp_path, ext):
    """A surface without normals of its own gets each frame's recomputed normals in USD, as
    in glTF (a review saw USD without normals shade unlike the glTF of the same shot)."""
    from pxr import Usd, UsdGeom

    anim = sphere_animation(F=6, subdivisions=4, uvs=False, rigid=True)
    stage = Usd.Stage.Open(str(write_animation(tmp_path / f"a{ext}", anim)))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    codes = mesh.GetPointsAttr().GetTimeSamples()
    assert len(codes) == anim.n_frames
    for k, code in enumerate(codes):
        n_k = np.asarray(mesh.GetNormalsAttr().Get(code), np.float64)
        P = anim.positions[k]
        radial = P - P.mean(axis=0)
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        assert np.einsum("ij,ij->i", n_k, radial).min() > 0.999


def test_gltf_says_its_frame_rate(tmp_path):
    """glTF keeps seconds only: a uniform animation's rate is in extras.wiggly (25 fps shots
    landed between frames in a scene at 24 fps, with nothing in the file to say 25)."""
    import pygltflib

    for times, rate in ((np.arange(6) / 25.0, 25.0), (np.array([0.0, 0.1, 0.35]), None)):
        anim = sphere_animation(F=len(times), times=times)
        gltf = pygltflib.GLTF2().load(str(write_animation(tmp_path / "a.glb", anim,
                                                          overwrite=True)))
        assert gltf.animations[0].extras["wiggly"].get("frames_per_second") == rate


def test_rest_normals_are_transported_by_the_smallest_rotation():
    """Frame normals keep the angle between the rest normal and the recomputed normal, are
    the rest normals at frame 0, and become the recomputed normals when they coincide."""
    anim = checked_animation(sphere_animation(F=5, normals=True), "test")
    frame_normals = FrameNormals(anim)
    c0 = vertex_normals(anim.positions[0], anim.faces)
    np.testing.assert_allclose(frame_normals(anim.positions[0]), anim.normals, atol=1e-12)
    for P in anim.positions[1:]:
        ck, nk = vertex_normals(P, anim.faces), frame_normals(P)
        np.testing.assert_allclose(np.linalg.norm(nk, axis=1), 1, atol=1e-12)
        np.testing.assert_allclose(np.einsum("ij,ij->i", nk, ck),
                                   np.einsum("ij,ij->i", anim.normals, c0), atol=1e-9)
    same = checked_animation(SurfaceAnimation(anim.times, anim.positions, anim.faces,
                                            normals=c0), "test")
    for P in anim.positions:
        np.testing.assert_allclose(FrameNormals(same)(P),
                                   vertex_normals(P, anim.faces), atol=1e-9)


def test_vertex_normals_of_a_tetrahedron():
    """Area weighting by hand: vertex 0 of the corner tetrahedron touches three right
    triangles of area 1/2 with normals -x, -y, -z."""
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    T = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    N = vertex_normals(V, T)
    np.testing.assert_allclose(N[0], -np.ones(3) / np.sqrt(3))
    # vertex 1: -y and -z (area 1/2 each) plus the slanted face (area sqrt(3)/2, normal
    # (1, 1, 1)/sqrt(3)): (0, -1/2, 0) + (0, 0, -1/2) + (1/2, 1/2, 1/2) = (1/2, 0, 0)
    np.testing.assert_allclose(N[1], [1, 0, 0], atol=1e-15)


# ----------------------------------------------------------------------------------------------
# USD


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usd"])
def test_usd_stage_read_with_pxr(tmp_path, ext):
    from pxr import Usd, UsdGeom

    anim = sphere_animation(F=8, normals=True)
    path = write_animation(tmp_path / f"a{ext}", anim)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetFramesPerSecond() == 24.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 7.0)
    assert stage.GetDefaultPrim().GetPath() == "/ball"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/ball/ball"))
    assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
    counts = mesh.GetFaceVertexCountsAttr().Get()
    indices = mesh.GetFaceVertexIndicesAttr().Get()
    np.testing.assert_array_equal(np.asarray(indices).reshape(-1, 3), anim.faces)
    points = mesh.GetPointsAttr()
    codes = points.GetTimeSamples()
    np.testing.assert_allclose(np.asarray(codes) / 24.0, anim.times, atol=1e-12)
    for code, P in zip(codes, anim.positions, strict=True):
        p = np.asarray(points.Get(code))
        np.testing.assert_allclose(p, P, atol=position_tolerance(anim))
        assert UsdGeom.Mesh.ValidateTopology(indices, counts, len(p))[0]
        lo, hi = np.asarray(mesh.GetExtentAttr().Get(code))
        np.testing.assert_array_equal(lo, p.min(axis=0))
        np.testing.assert_array_equal(hi, p.max(axis=0))
        n = np.asarray(mesh.GetNormalsAttr().Get(code))
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-6)
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_allclose(np.asarray(st.Get()), anim.uvs, atol=1e-7)


def test_usd_non_uniform_times_use_milliseconds(tmp_path):
    from pxr import Usd

    times = [0.0, 0.1, 0.15, 1.0]
    path = write_animation(tmp_path / "a.usda", sphere_animation(F=4, times=times))
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 1000.0
    points = stage.GetPrimAtPath("/ball/ball").GetAttribute("points")
    np.testing.assert_allclose(points.GetTimeSamples(), [0, 100, 150, 1000])


def usd_validation_errors(stage) -> list[str]:
    """What usdchecker reports: every validator of USD's validation registry."""
    from pxr import UsdValidation

    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(stage)
            if e.GetType() in (UsdValidation.ValidationErrorType.Error,
                               UsdValidation.ValidationErrorType.Warn)]


@pytest.mark.parametrize("ext", [".usda", ".usdc"])
def test_usd_passes_usdchecker(tmp_path, ext):
    from pxr import Usd

    path = write_animation(tmp_path / f"a{ext}", sphere_animation(F=4, normals=True))
    assert usd_validation_errors(Usd.Stage.Open(str(path))) == []
    # not vacuous: a stage without metadata fails
    bare = Usd.Stage.CreateInMemory()
    bare.DefinePrim("/x", "Xform")
    assert len(usd_validation_errors(bare)) >= 3
    # the usdchecker executable, where installed (usd-core's wheel does not ship it)
    checker = shutil.which("usdchecker")
    if checker is not None:
        done = subprocess.run([checker, str(path)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stdout + done.stderr


# ----------------------------------------------------------------------------------------------
# OBJ sequence and npz, read independently


def test_obj_sequence_read_with_meshio(tmp_path):
    anim = sphere_animation(F=5, normals=True)
    write_animation(tmp_path / "frame.obj", anim)
    assert listing(tmp_path) == [f"frame_{k:04d}.obj" for k in range(5)]
    for k in range(5):
        mesh = meshio.read(tmp_path / f"frame_{k:04d}.obj")
        np.testing.assert_allclose(mesh.points, anim.positions[k], atol=position_tolerance(anim))
        np.testing.assert_array_equal(mesh.get_cells_type("triangle"), anim.faces)
        np.testing.assert_allclose(mesh.point_data["obj:vt"], anim.uvs, atol=1e-8)
        np.testing.assert_allclose(np.linalg.norm(mesh.point_data["obj:vn"], axis=1), 1,
                                   atol=1e-5)
    text = (tmp_path / "frame_0002.obj").read_text()
    assert f"# time {float(anim.times[2])!r}" in text and "\no ball\n" in text


def test_one_frame_of_an_obj_sequence_read_alone_says_so(tmp_path, recwarn):
    """``out/frame_0002.obj`` is read as the one frame it is, with a word that
    ``out/frame.obj`` plays the whole sequence; a single OBJ of that name pattern, silently."""
    write_animation(tmp_path / "frame.obj", sphere_animation(F=5))
    with pytest.warns(UserWarning, match=r"frame_0002.obj is one frame of the OBJ sequence "
                      r"frame.obj \(5 frames in .*\): read as one frame; give .*frame.obj"):
        assert read_animation(tmp_path / "frame_0002.obj").n_frames == 1
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "part_0001.obj").write_bytes((tmp_path / "frame_0002.obj").read_bytes())
    recwarn.clear()
    assert read_animation(alone / "part_0001.obj").n_frames == 1
    assert not [w for w in recwarn if "one frame of" in str(w.message)]


def test_obj_float32_positions_are_exact(tmp_path):
    """9 significant digits reproduce float32 values bit for bit."""
    anim = sphere_animation(F=2, dtype=np.float32)
    back = read_animation(write_animation(tmp_path / "f.obj", anim))
    np.testing.assert_array_equal(back.positions.astype(np.float32), anim.positions)


def test_obj_frame_numbers_widen_past_9999(tmp_path):
    names = frame_names(tmp_path / "f.obj", 10001)
    assert names[0].name == "f_00000.obj" and names[-1].name == "f_10000.obj"


def test_npz_layout(tmp_path):
    anim = sphere_animation(F=3, normals=True)
    with np.load(write_animation(tmp_path / "a.npz", anim)) as data:
        assert set(data.files) == {"format_version", "times", "positions", "faces", "uvs",
                                   "normals", "name", "loop"}
        assert int(data["format_version"]) == export.FORMAT_VERSION
        assert data["positions"].dtype == np.float32
        np.testing.assert_array_equal(data["positions"], anim.positions.astype(np.float32))
        np.testing.assert_array_equal(data["faces"], anim.faces)
        np.testing.assert_array_equal(data["times"], anim.times)


def test_npz_from_the_future_is_refused(tmp_path):
    anim = sphere_animation(F=2)
    np.savez(tmp_path / "a.npz", format_version=99, times=anim.times, positions=anim.positions,
             faces=anim.faces)
    with pytest.raises(WigglyInputError, match="newer wiggly"):
        read_animation(tmp_path / "a.npz")


# ----------------------------------------------------------------------------------------------
# atomic writes and overwrite protection


def fail_after(original, partial: bool):
    """A writer that writes (part of) its output, then fails."""

    def writer(path, anim, **options):
        if partial:
            Path(path).write_bytes(b"half a file")
        else:
            original(path, anim, **options)
        raise OSError("disk full")

    return writer


@pytest.mark.parametrize("ext", [".glb", ".usda", ".usdc", ".npz"])
@pytest.mark.parametrize("partial", [True, False], ids=["partial", "complete"])
def test_failed_write_leaves_nothing(tmp_path, monkeypatch, ext, partial):
    name = {".glb": "write_glb", ".npz": "write_npz"}.get(ext, "write_usd")
    monkeypatch.setattr(formats, name, fail_after(getattr(formats, name), partial))
    with pytest.raises(OSError, match="disk full"):
        write_animation(tmp_path / f"a{ext}", sphere_animation(F=3))
    assert listing(tmp_path) == []


@pytest.mark.parametrize("ext", [".glb", ".usda", ".npz"])
def test_failed_overwrite_keeps_the_old_file(tmp_path, monkeypatch, ext):
    path = write_animation(tmp_path / f"a{ext}", sphere_animation(F=2))
    before = path.read_bytes()
    name = {".glb": "write_glb", ".npz": "write_npz"}.get(ext, "write_usd")
    monkeypatch.setattr(formats, name, fail_after(getattr(formats, name), partial=True))
    with pytest.raises(OSError):
        write_animation(path, sphere_animation(F=3), overwrite=True)
    assert path.read_bytes() == before and listing(tmp_path) == [path.name]


def test_failed_obj_sequence_leaves_nothing(tmp_path, monkeypatch):
    written = []

    def write_frame(path, data):
        if len(written) == 3:
            raise OSError("disk full")
        written.append(path)
        path.write_bytes(data)

    monkeypatch.setattr(obj_format, "_write_frame_file", write_frame)
    with pytest.raises(OSError, match="disk full"):
        write_animation(tmp_path / "frame.obj", sphere_animation(F=6))
    assert len(written) == 3 and listing(tmp_path) == []


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_existing_output_is_kept_unless_overwrite(tmp_path, ext):
    path = write_animation(tmp_path / out_name(ext), sphere_animation(F=2))
    files = listing(tmp_path)
    contents = {name: (tmp_path / name).read_bytes() for name in files}
    with pytest.raises(WigglyInputError, match=r"exists; pass overwrite=True / --overwrite"):
        write_animation(path, sphere_animation(F=3))
    assert {name: (tmp_path / name).read_bytes() for name in listing(tmp_path)} == contents
    write_animation(path, sphere_animation(F=3), overwrite=True)
    assert read_animation(path).n_frames == 3


def test_obj_any_existing_frame_blocks_and_overwrite_removes_stale_frames(tmp_path):
    """Any file named like a frame blocks a write without overwrite; with it, the frames
    that wiggly wrote for a longer sequence go, and a file that only has a frame's name (the
    user's own) stays, with a warning that a reader would take it for a frame."""
    (tmp_path / "frame_0007.obj").write_text("# someone else's frame\n")
    with pytest.raises(WigglyInputError, match=r"frame_0007\.obj exists"):
        write_animation(tmp_path / "frame.obj", sphere_animation(F=3))
    with pytest.warns(UserWarning, match=r"left 1 file\(s\) that wiggly did not write.*"
                                         r"frame_0007\.obj"):
        write_animation(tmp_path / "frame.obj", sphere_animation(F=3), overwrite=True)
    assert listing(tmp_path) == ["frame_0000.obj", "frame_0001.obj", "frame_0002.obj",
                                 "frame_0007.obj"]
    assert (tmp_path / "frame_0007.obj").read_text() == "# someone else's frame\n"
    (tmp_path / "frame_0007.obj").unlink()
    (tmp_path / "other.obj").write_text("")  # not part of the sequence: untouched
    write_animation(tmp_path / "frame.obj", sphere_animation(F=2), overwrite=True)
    assert listing(tmp_path) == ["frame_0000.obj", "frame_0001.obj", "other.obj"]
    assert read_animation(tmp_path / "frame.obj").n_frames == 2


def test_usd_overwrite_in_the_same_process_reads_the_new_file(tmp_path):
    """USD's layer registry must not serve the previous file's contents."""
    from pxr import Usd

    path = tmp_path / "a.usdc"
    write_animation(path, sphere_animation(F=2))
    stage = Usd.Stage.Open(str(path))  # keeps the old layer alive
    write_animation(path, sphere_animation(F=5), overwrite=True)
    assert read_animation(path).n_frames == 5
    del stage


def test_missing_directories_are_created(tmp_path):
    path = write_animation(tmp_path / "new" / "dir" / "a.npz", sphere_animation(F=2))
    assert path.is_file()


def test_files_get_the_usual_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        path = write_animation(tmp_path / "a.glb", sphere_animation(F=2))
    finally:
        os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o644


# ----------------------------------------------------------------------------------------------
# input validation


def bad(**changes) -> SurfaceAnimation:
    anim = sphere_animation(F=3, subdivisions=1)
    for key, value in changes.items():
        setattr(anim, key, value)
    return anim


F3, N = 3, 42  # frames and vertices of bad()


@pytest.mark.parametrize(("anim", "message"), [
    (bad(positions=np.zeros((F3, N, 2))),
     r"positions should have shape \(F, n, 3\); shape is \(3, 42, 2\)"),
    (bad(positions=np.zeros((N, 3))),
     r"positions should have shape \(F, n, 3\); shape is \(42, 3\)"),
    (bad(positions=np.zeros((2, N, 3))), r"F = len\(times\) = 3; shape is \(2, 42, 3\)"),
    (bad(positions=np.zeros((F3, 2, 3)), faces=np.array([[0, 1, 1]])), r"n >= 3 vertices"),
    (bad(positions=np.full((F3, N, 3), np.nan)), r"positions should be finite; frame 0, vertex 0"),
    (bad(times=np.array([0.0, 0.2, 0.1])), r"strictly increasing; times\[1\] = 0.2"),
    (bad(times=np.array([])), r"times should have shape \(F,\) with F >= 1"),
    (bad(faces=np.array([[0, 1, 42]])), r"faces should index the n = 42 vertices.*\[0, 1, 42\]"),
    (bad(faces=np.array([[0, 1, -1]])), r"face 0 is \[0, 1, -1\]"),
    (bad(faces=np.zeros((4, 4), int)), r"faces should have shape \(k, 3\).*shape is \(4, 4\)"),
    (bad(faces=np.zeros((4, 3))), r"faces should be an integer array; dtype is float64"),
    (bad(uvs=np.zeros((N, 3))), r"uvs should have shape \(n, 2\) = \(42, 2\); shape is \(42, 3\)"),
    (bad(normals=np.zeros((N, 3))), r"normals should be finite nonzero vectors; vertex 0"),
    (bad(positions=[[1, 2], [3]]), r"positions should be an array of shape \(F, n, 3\)"),
    (bad(positions=np.full((F3, N, 3), "x")), r"positions should be a real-valued array"),
    (bad(times=np.arange(3) * 1j), r"times should be a real-valued array.*complex128"),
])
def test_bad_input_is_refused_with_a_precise_message(tmp_path, anim, message):
    with pytest.raises(WigglyInputError, match=message) as info:
        write_animation(tmp_path / "a.glb", anim)
    assert str(tmp_path / "a.glb") in str(info.value)
    assert listing(tmp_path) == []


def test_glb_refuses_times_that_collide_in_float32(tmp_path):
    anim = sphere_animation(F=2, times=[1e6, 1e6 + 1e-3])
    with pytest.raises(WigglyInputError, match="too close to be distinct in float32"):
        write_animation(tmp_path / "a.glb", anim)
    assert read_animation(write_animation(tmp_path / "a.npz", anim)).times[1] == 1e6 + 1e-3


def test_unknown_extension_lists_the_supported_ones(tmp_path):
    with pytest.raises(WigglyInputError, match=r"unknown extension '\.fbx'.*\.glb.*\.npz"):
        write_animation(tmp_path / "a.fbx", sphere_animation(F=2))
    with pytest.raises(WigglyInputError, match="unknown extension"):
        read_animation(tmp_path / "a.abc")


def test_reading_missing_files_says_so(tmp_path):
    with pytest.raises(WigglyInputError, match="no such file"):
        read_animation(tmp_path / "a.glb")
    with pytest.raises(WigglyInputError, match=r"no OBJ sequence frame_0000\.obj"):
        read_animation(tmp_path / "frame.obj")
    (tmp_path / "frame_0000.obj").write_bytes(b"")
    (tmp_path / "frame_0002.obj").write_bytes(b"")
    with pytest.raises(WigglyInputError, match=r"frame\(s\) \[1\] missing"):
        read_animation(tmp_path / "frame.obj")


@pytest.mark.parametrize("ext", [".obj", ".usda", ".glb"])
def test_progress_bar_on_a_terminal_one_line_in_a_log(tmp_path, capsys, caplog, monkeypatch,
                                                      ext):
    monkeypatch.setattr("wiggly.progress.on_terminal", lambda: True)
    with reporting():
        write_animation(tmp_path / f"a{ext}", sphere_animation(F=4))
    err = capsys.readouterr().err
    assert "4/4" in err
    monkeypatch.setattr("wiggly.progress.on_terminal", lambda: False)
    with caplog.at_level(logging.INFO, logger="wiggly"):
        write_animation(tmp_path / f"a{ext}", sphere_animation(F=4), overwrite=True)
    assert capsys.readouterr().err == ""  # no bar in a log: one line on the logger
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == [f"a{ext}: 4 frames"]
    monkeypatch.setattr("wiggly.progress.on_terminal", lambda: True)
    write_animation(tmp_path / f"a{ext}", sphere_animation(F=4), overwrite=True)
    assert capsys.readouterr().err == ""  # a quiet library: the logger is not at INFO
    with pytest.warns(DeprecationWarning, match=r"write_animation\(progress=...\)"):
        write_animation(tmp_path / f"a{ext}", sphere_animation(F=4), overwrite=True,
                        progress=True)  # the retired flag still draws its bar
    assert "4/4" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# rest pose as the glTF base, frame_start, compact (modal) glTF


def modal_animation(F: int = 90, r: int = 8) -> SurfaceAnimation:
    """A linear motion of an icosphere: rest + sum_i q_i(t) shape_i, with signed weights."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    V, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    rng = np.random.default_rng(2)
    shapes = np.stack([np.sin((i + 1) * V @ rng.standard_normal(3))[:, None]
                       * rng.standard_normal(3) * 0.1 for i in range(r)])
    t = np.arange(F) / 30.0
    q = np.stack([np.sin((i + 1) * 2.0 * t + i) * (1 + i) for i in range(r)], axis=1)
    q[:, 3] = np.abs(q[:, 3])  # one mode that never goes negative
    q[:, 5] = 0.0  # and one that stays at rest
    P = V + np.einsum("fr,rnc->fnc", q, shapes)
    return SurfaceAnimation(t, P, faces, name="blob", rest=V, mode_shapes=shapes, modal=q)


def test_glb_base_is_the_rest_pose(tmp_path):
    import pygltflib

    anim = modal_animation(F=5)
    path = write_animation(tmp_path / "a.glb", anim)
    gltf = pygltflib.GLTF2().load(str(path))
    base = raw_accessor(gltf, gltf.meshes[0].primitives[0].attributes.POSITION)
    np.testing.assert_array_equal(base, anim.rest.astype(np.float32))
    back = read_animation(path)
    assert np.abs(back.positions - anim.positions).max() < position_tolerance(anim)


@pytest.mark.parametrize("ext", [".glb", ".usda"])
def test_frame_start_puts_frame_k_on_frame_start_plus_k(tmp_path, ext):
    anim = sphere_animation(F=6, times=0.2 + np.arange(6) / 24)  # starts at 0.2 s = frame 4.8
    path = write_animation(tmp_path / f"a{ext}", anim, frame_start=1)
    if ext == ".glb":
        import pygltflib

        gltf = pygltflib.GLTF2().load(str(path))
        sampler = gltf.animations[0].samplers[0]
        keys = raw_accessor(gltf, sampler.input).ravel()
        np.testing.assert_allclose(keys * 24, np.arange(1, 7), rtol=1e-6)
    else:
        from pxr import Usd

        stage = Usd.Stage.Open(str(path))
        assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 6.0)
        assert stage.GetTimeCodesPerSecond() == 24.0
    back = read_animation(path)  # the shot's own times come back
    np.testing.assert_allclose(back.times, anim.times, rtol=0, atol=1e-9)
    with pytest.raises(WigglyInputError, match="negative glTF times"):
        write_animation(tmp_path / "b.glb", anim, frame_start=-3)


def test_compact_glb_is_exact_small_and_valid(tmp_path, gltf_validator):
    """One pair of targets per mode: the same positions as the per-frame form at every frame
    and between frames, a fraction of its size, and no validator errors."""
    anim = modal_animation()
    frames = write_animation(tmp_path / "frames.glb", anim)
    modes = write_animation(tmp_path / "modes.glb", anim, gltf_targets="modes")
    a, b = read_animation(frames), read_animation(modes)
    tol = position_tolerance(anim)
    assert np.abs(b.positions - anim.positions).max() < tol
    np.testing.assert_array_equal(b.times, a.times)
    # between frames both layouts interpolate linearly: the weights' difference is linear too
    import pygltflib

    gltf = pygltflib.GLTF2().load(str(modes))
    names = gltf.meshes[0].extras["targetNames"]
    assert len(names) == 2 * 8 - 1 - 2  # mode 3 needs no "-" half, mode 5 nothing at all
    weights = raw_accessor(gltf, gltf.animations[0].samplers[0].output).reshape(90, -1)
    assert weights.min() >= 0 and weights.max() <= 1  # Blender's shape-key slider range
    sizes = frames.stat().st_size, modes.stat().st_size
    assert sizes[1] < sizes[0] / 4, sizes
    reports = gltf_validator([frames, modes])
    for report in reports:
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"][:3]
    print(f"per-frame {sizes[0]} B, modes {sizes[1]} B; validator warnings "
          f"{[r['issues']['numWarnings'] for r in reports]}")


def test_compact_glb_refuses_a_motion_that_is_not_modal(tmp_path):
    anim = modal_animation(F=4)
    with pytest.raises(WigglyInputError, match="has no mode shapes"):
        write_animation(tmp_path / "a.glb", SurfaceAnimation(anim.times, anim.positions,
                                                             anim.faces), gltf_targets="modes")
    anim.positions = anim.positions + 0.01  # not rest + modal . shapes
    with pytest.raises(WigglyInputError, match="linear motions only"):
        write_animation(tmp_path / "b.glb", anim, gltf_targets="modes")


def test_progress_names_the_users_file_not_the_temporary_one(tmp_path):
    """Outputs are written to a hidden temporary file first; progress bars show the user's
    name for it."""
    from wiggly.files import atomic_file, shown_name

    for name in ("walk_cycle.png", "a.b.usdc", "shot"):
        with atomic_file(tmp_path / name) as tmp:
            assert tmp.name != name and shown_name(tmp) == name
    assert shown_name(tmp_path / ".hidden.glb") == ".hidden.glb"  # a user's own hidden file


def test_a_killed_exports_leftovers_are_removed_by_the_next_export(tmp_path):
    """A process killed mid-export leaves its hidden temporary outputs; the next output
    written to that folder removes those of processes that no longer run, once they are an
    hour old. A running process's temporaries, a user's own hidden files and an earlier
    output moved aside during a commit (maybe the only copy) stay."""
    import sys
    import time

    from wiggly.files import OutputSet

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    names = {f".shot.wiggly-{dead}.k3x9_a2b.glb": False,  # removed
             f".shot.wiggly-{dead}.young_ab.glb": True,  # too recent: it may still be written
             f".shot.wiggly-{dead}.old-ab12cd34": True,  # a user's output moved aside
             f".shot.wiggly-{os.getpid()}.live_abc.glb": True,  # a running process's
             ".shot.k3x9_a2b.glb": True, ".my_notes.txt": True}  # the user's
    for name in names:
        (tmp_path / name).write_bytes(b"partial")
        if "young" not in name:
            os.utime(tmp_path / name, (time.time() - 7200, time.time() - 7200))
    with OutputSet() as outputs:
        outputs.stage(tmp_path / "shot.glb").write_bytes(b"glb")
    kept = {p.name for p in tmp_path.iterdir()}
    assert kept == {n for n, stays in names.items() if stays} | {"shot.glb"}


def test_a_folder_made_for_the_outputs_is_said(tmp_path, caplog, monkeypatch):
    """Outputs in folders that do not exist yet are written (the folders are made, and
    removed again when the outputs are not), and the outermost new folder is said: a typo
    in an output path scattered files in a new folder without a word."""
    from wiggly import progress
    from wiggly.files import OutputSet

    monkeypatch.chdir(tmp_path)
    with progress.reporting(True), caplog.at_level("INFO", logger="wiggly"):
        with OutputSet() as outputs:
            outputs.stage(tmp_path / "nope" / "sub" / "shot.glb").write_bytes(b"glb")
            outputs.stage(tmp_path / "nope" / "other.npz").write_bytes(b"npz")
    assert (tmp_path / "nope" / "sub" / "shot.glb").read_bytes() == b"glb"
    assert caplog.messages == ["created the folder nope for the outputs"], caplog.messages
    with pytest.raises(RuntimeError), OutputSet() as outputs:
        outputs.stage(tmp_path / "gone" / "shot.glb").write_bytes(b"glb")
        raise RuntimeError("a failed export")
    assert not (tmp_path / "gone").exists() and len(caplog.messages) == 1


def test_a_solved_animation_is_written_from_python(tmp_path):
    """write_animation takes a solved wiggly.Animation as it is (it failed with an
    AttributeError before): sampled at ``fps`` on the body's surface, and read back the same
    as the motion's own positions."""
    import wiggly
    from wiggly.keyframes import Keyframe

    body = wiggly.prepare("builtin:bar", n_modes=8, resolution=6)
    X = body.rest_positions()
    keys = [Keyframe.rest(body, 0.0, np.arange(len(X)), still=True),
            Keyframe.offset(body, 1.0, np.flatnonzero(X[:, 0] > 0.9), (0.0, 0.1, 0.0))]
    anim = wiggly.solve(body, keys, duration=1.0, warp=False)
    for name in ("bar.glb", "bar.npz"):
        write_animation(tmp_path / name, anim, fps=20)
        back = read_animation(tmp_path / name)
        assert back.n_frames == 21 and back.n_vertices == len(X)
        np.testing.assert_allclose(back.positions[-1], anim.positions([1.0])[0], atol=1e-5)


def _foreign_glb(path, parts, times, weights, meshes=1):
    """A glTF binary as other tools write it: one mesh of several triangle primitives, each
    with its own morph targets, and one animation of the mesh's weights (LINEAR).  ``parts``:
    (positions (n, 3), faces (k, 3), target deltas (t, n, 3)) per primitive."""
    import pygltflib as gl

    blob, views, accessors = bytearray(), [], []

    def add(array, target=None, minmax=False):
        array = np.ascontiguousarray(array)
        while len(blob) % 4:
            blob.append(0)
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=array.nbytes,
                                   target=target))
        blob.extend(array.tobytes())
        kind = {1: gl.SCALAR, 3: gl.VEC3}[1 if array.ndim == 1 else array.shape[1]]
        component = gl.UNSIGNED_INT if array.dtype == np.uint32 else gl.FLOAT
        accessors.append(gl.Accessor(
            bufferView=len(views) - 1, componentType=component, count=len(array), type=kind,
            min=np.atleast_1d(array.min(axis=0)).tolist() if minmax else None,
            max=np.atleast_1d(array.max(axis=0)).tolist() if minmax else None))
        return len(accessors) - 1

    primitives = []
    for positions, faces, deltas in parts:
        position = add(positions.astype(np.float32), gl.ARRAY_BUFFER, minmax=True)
        indices = add(faces.astype(np.uint32).ravel(), gl.ELEMENT_ARRAY_BUFFER)
        targets = [gl.Attributes(POSITION=add(d.astype(np.float32), gl.ARRAY_BUFFER,
                                              minmax=True)) for d in deltas]
        primitives.append(gl.Primitive(attributes=gl.Attributes(POSITION=position),
                                       indices=indices, targets=targets))
    t = add(np.asarray(times, np.float32), minmax=True)
    w = add(np.asarray(weights, np.float32).ravel())
    mesh_list = [gl.Mesh(name="foreign", primitives=primitives,
                         weights=[0.0] * len(parts[0][2]))]
    mesh_list += [gl.Mesh(name=f"extra{j}", primitives=primitives[:1]) for j in range(1, meshes)]
    gltf = gl.GLTF2(
        scene=0, scenes=[gl.Scene(nodes=list(range(meshes)))],
        nodes=[gl.Node(mesh=j) for j in range(meshes)], meshes=mesh_list,
        animations=[gl.Animation(
            samplers=[gl.AnimationSampler(input=t, output=w, interpolation="LINEAR")],
            channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(
                node=0, path="weights"))])],
        accessors=accessors, bufferViews=views, buffers=[gl.Buffer(byteLength=len(blob))])
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(path))


def test_a_foreign_glb_of_several_primitives_is_read_whole(tmp_path):
    """``wiggly render`` of another tool's glTF read only its mesh's first primitive (2154 of
    2952 vertices of a horse): every primitive is read, with its own morph targets."""
    rng = np.random.default_rng(3)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    parts = [(rng.normal(size=(4, 3)), tri, rng.normal(size=(2, 4, 3))),
             (rng.normal(size=(5, 3)), np.array([[0, 1, 2], [2, 3, 4]]),
              rng.normal(size=(2, 5, 3)))]
    times, weights = [0.0, 0.5, 1.0], [[0.0, 0.0], [0.3, 0.7], [1.0, 0.0]]
    _foreign_glb(tmp_path / "foreign.glb", parts, times, weights)
    anim = read_animation(tmp_path / "foreign.glb")
    base = np.concatenate([p[0] for p in parts])
    deltas = np.concatenate([p[2] for p in parts], axis=1)
    expected = base + np.einsum("ft,tnc->fnc", np.asarray(weights), deltas)
    assert anim.positions.shape == (3, 9, 3)
    np.testing.assert_allclose(anim.positions, expected, atol=1e-5)
    np.testing.assert_array_equal(anim.faces, np.concatenate([tri, np.array([[4, 5, 6],
                                                                            [6, 7, 8]])]))
    np.testing.assert_allclose(anim.times, times)
    # a second mesh in the file is named as left out, not dropped silently
    _foreign_glb(tmp_path / "two.glb", parts, times, weights, meshes=2)
    with pytest.warns(UserWarning, match="only its first mesh .* left out: 1 other mesh"):
        assert read_animation(tmp_path / "two.glb").positions.shape == (3, 9, 3)


def test_a_terminated_run_leaves_no_temporary_outputs(tmp_path):
    """SIGTERM (``timeout``, a scheduler, ``kill``) while outputs are being written ends the
    command as Ctrl+C does: exit code 143, "wiggly: terminated", and the staged files are
    removed, where the default action would leave them (tens of MB) in the user's folder."""
    import signal
    import subprocess
    import sys

    program = f"""
import os, signal, sys
import wiggly.cli as cli
from wiggly.files import OutputSet

def run(args):
    with OutputSet() as outputs:
        outputs.stage({str(tmp_path / "shot.mp4")!r}).write_bytes(b"x" * 1000)
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not end the run")

cli.animate.run = run
sys.exit(cli.main(["animate", "builtin:bar"]))
"""
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 128 + signal.SIGTERM, done.stderr
    assert "wiggly: terminated" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [], list(tmp_path.iterdir())


@pytest.mark.parametrize("ext", [".glb", ".usda", ".npz"])
def test_a_body_far_from_the_origin_is_told_its_float32_rounding(tmp_path, ext, recwarn):
    """float32 positions 1e5 m from the origin step by about 8-16 mm: the test's ball there
    is warned about, with the step; 1 km away (steps of about 0.1 mm, under 1e-4 of its
    size) it is not."""
    anim = sphere_animation(F=3)
    far = SurfaceAnimation(anim.times, anim.positions + 1e5, anim.faces, name="far")
    near = SurfaceAnimation(anim.times, anim.positions + 1e3, anim.faces, name="near")
    write_animation(tmp_path / f"near{ext}", near)
    assert not [w for w in recwarn if "float32" in str(w.message)]
    with pytest.warns(UserWarning, match=rf"far{re.escape(ext)}: the body lies 1e\+05 m from "
                                         r"the origin.* steps of about 1\d mm"):
        write_animation(tmp_path / f"far{ext}", far)


def test_a_glb_past_its_32_bit_sizes_is_refused_and_leaves_no_file(tmp_path, monkeypatch):
    """write_animation refuses a .glb beyond GLB's 32-bit sizes with a WigglyInputError that
    says what fits (a struct.error and an internal error before); the limit lowered here."""
    from wiggly.export import gltf

    monkeypatch.setattr(gltf, "GLB_LIMIT", 10_000)
    with pytest.raises(WigglyInputError, match=r"a.glb: the .glb would be .* GiB, more than "
                       r"the 4 GiB a GLB file can hold .*write .usdc"):
        write_animation(tmp_path / "a.glb", sphere_animation(F=10))
    assert list(tmp_path.iterdir()) == []
