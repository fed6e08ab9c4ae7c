"""Driver readers (wiggly.drive): every format read back against the mesh sequence that was
written, a skinned glTF against a linear blend computed by hand, and the topology check."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from wiggly.drive import Driver, read_driver
from wiggly.drive.gltf import sample, slerp
from wiggly.errors import WigglyInputError
from wiggly.export import SurfaceAnimation, write_animation

# A cube of 8 vertices and 6 quads (12 triangles), animated: turned about y, moved and
# squashed, frame k at time k / 24.
CUBE = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)]) * 0.2
QUADS = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4],
                  [1, 5, 7, 3]])
TRIS = np.concatenate([QUADS[:, [0, 1, 2]], QUADS[:, [0, 2, 3]]])
FRAMES = 5


def sequence() -> tuple[np.ndarray, np.ndarray]:
    """Times (F,) and positions (F, 8, 3) of the animated cube."""
    times = np.arange(FRAMES) / 24.0
    P = []
    for k in range(FRAMES):
        R = Rotation.from_euler("y", 20.0 * k, degrees=True)
        squash = np.array([1.0 + 0.05 * k, 1.0 - 0.05 * k, 1.0])
        P.append(R.apply(CUBE * squash) + np.array([0.1 * k, 0.02 * k * k, -0.03 * k]))
    return times, np.array(P)


# ----------------------------------------------------------------------------------------------
# mesh sequences: npz, OBJ, USD


def test_npz_driver_reads_back_the_sequence(tmp_path):
    times, P = sequence()
    path = write_animation(tmp_path / "walk.npz", SurfaceAnimation(times, P, TRIS))
    d = read_driver(path)
    np.testing.assert_allclose(d.times, times)
    np.testing.assert_allclose(d.positions, P, atol=1e-7)  # stored as float32
    assert d.n_frames == FRAMES and d.n_vertices == 8 and d.kind == "wiggly npz"
    d.check(8, TRIS, "cube")  # its own triangles: no complaint


def write_obj(path: Path, X: np.ndarray, polygons, time: float | None = None) -> None:
    lines = [f"# time {time!r}"] if time is not None else ["# Blender-style frame"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in X]
    lines += ["f " + " ".join(str(i + 1) for i in p) for p in polygons]
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("style", ["blender", "houdini", "wiggly"])
def test_obj_sequence_driver_reads_back_the_sequence(tmp_path, style):
    """Blender's walk_000001.obj ... (frames numbered from 1, no times: frame N at N / fps),
    a Houdini pattern walk.####.obj, and wiggly's own walk.obj -> walk_0000.obj (times)."""
    times, P = sequence()
    if style == "wiggly":
        write_animation(tmp_path / "walk.obj", SurfaceAnimation(times, P, TRIS))
        d = read_driver(tmp_path / "walk.obj")
        np.testing.assert_allclose(d.times, times)
    else:
        for k in range(FRAMES):
            name = f"walk_{k + 1:06d}.obj" if style == "blender" else f"walk.{k + 1:04d}.obj"
            write_obj(tmp_path / name, P[k], QUADS)
        (tmp_path / "walk_notes.obj").write_text("not a frame\n")  # no number: not in it
        given = "walk_000001.obj" if style == "blender" else "walk.####.obj"
        with pytest.raises(WigglyInputError, match="frame rate"):
            read_driver(tmp_path / given)
        d = read_driver(tmp_path / given, frame_rate=24)
        np.testing.assert_allclose(d.times, (np.arange(FRAMES) + 1) / 24)  # frame N at N/24
        assert len(d.edges) == 12  # a cube's edges: the quads', not the diagonals (18)
    np.testing.assert_allclose(d.positions, P, atol=1e-7)
    d.check(8, TRIS, "cube")


def test_an_obj_sequence_with_missing_or_broken_frames_says_which(tmp_path):
    """Frames 3-4 missing from walk_0001..0005.obj: read, with a warning naming them (the
    driver is interpolated across); a NaN in walk_0005.obj: refused naming that file and the
    vertex (1-based, as in the file), not an index into the frames read."""
    _, P = sequence()
    for k in (1, 2, 5):
        write_obj(tmp_path / f"walk_{k:04d}.obj", P[k - 1], QUADS)
    with pytest.warns(UserWarning, match=r"no files for frames 3-4: the driver is "
                                         r"interpolated across them"):
        d = read_driver(tmp_path / "walk_0001.obj", frame_rate=24)
    np.testing.assert_allclose(d.times, np.array([1, 2, 5]) / 24)
    broken = P[4].copy()
    broken[2, 1] = np.nan
    write_obj(tmp_path / "walk_0005.obj", broken, QUADS)
    with pytest.raises(WigglyInputError, match=r"walk_0005.obj puts vertex 3 at \[.*nan"):
        read_driver(tmp_path / "walk_0001.obj", frame_rate=24)


def test_a_driver_frame_that_is_not_finite_is_named_by_its_time():
    times, P = sequence()
    P[4, 6, 0] = np.inf
    with pytest.raises(WigglyInputError, match=r"the frame at t = 0.166667 s \(frame 5 of 5\) "
                                               r"puts vertex 6"):
        Driver(times, P, TRIS, np.zeros((0, 2)), "mine.npz", "test")


def test_usd_points_driver_converts_axes_units_and_transforms(tmp_path):
    """A Z-up stage in centimetres with time-sampled points and an animated parent
    transform: world space, then y up ((x, y, z) -> (x, z, -y)) and metres."""
    from pxr import Gf, Usd, UsdGeom, Vt

    _, P = sequence()
    stage = Usd.Stage.CreateNew(str(tmp_path / "walk.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(24)
    xform = UsdGeom.Xform.Define(stage, "/rig")
    op = xform.AddTranslateOp()
    mesh = UsdGeom.Mesh.Define(stage, "/rig/cube")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(QUADS)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(QUADS.ravel().tolist()))
    shift = np.array([[3.0 * k, -2.0 * k, 1.0] for k in range(FRAMES)])  # cm, per frame
    cm = 100.0 * P  # the sequence in cm, in the stage's z-up axes: (x, -z, y)
    zup = np.stack([cm[..., 0], -cm[..., 2], cm[..., 1]], -1)
    for k in range(FRAMES):
        code = Usd.TimeCode(k + 1)  # Blender writes frames 1, 2, ...
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(zup[k].astype(np.float32)), code)
        op.Set(Gf.Vec3d(*shift[k]), code)
    stage.GetRootLayer().Save()
    d = read_driver(tmp_path / "walk.usda")
    np.testing.assert_allclose(d.times, (np.arange(FRAMES) + 1) / 24)
    world = (zup + shift[:, None, :]) / 100.0  # metres, z up
    expected = np.stack([world[..., 0], world[..., 2], -world[..., 1]], -1)
    np.testing.assert_allclose(d.positions, expected, atol=1e-6)
    np.testing.assert_allclose(d.positions - shift_yup(shift), P, atol=1e-6)
    assert d.kind == "USD points" and len(d.edges) == 12 and d.parts == ("/rig/cube",)
    d.check(8, TRIS, "cube")
    # a prop beside the object: the count differs, and the message names both meshes and
    # drive.object, which keeps one
    prop = UsdGeom.Mesh.Define(stage, "/prop")
    prop.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    prop.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    prop.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.eye(3, dtype=np.float32)))
    stage.GetRootLayer().Save()
    both = read_driver(tmp_path / "walk.usda")
    assert both.parts == ("/rig/cube", "/prop")
    with pytest.raises(WigglyInputError, match=r"holds 2 meshes \(/rig/cube, /prop\): "
                                               r"drive\.object keeps those of one name"):
        both.check(8, TRIS, "cube.obj")
    assert read_driver(tmp_path / "walk.usda", object="rig").parts == ("/rig/cube",)


def test_usd_holds_between_sparse_samples_are_read_as_usd_plays_them(tmp_path):
    """Blender's USD export writes a points sample only where the mesh changes: a turn at
    frames 10-12 of a stage from 1 to 20.  The driver holds the first sample's pose from frame
    1 and the last one's to frame 20, at every frame, as USD plays the stage (a cubic through
    the samples and the stage's ends alone counter-turned a Blender rig by 2.6 degrees during
    its hold); a gap between samples is filled by USD's own (linear) interpolation."""
    from pxr import Usd, UsdGeom, Vt

    _, P = sequence()
    stage = Usd.Stage.CreateNew(str(tmp_path / "hold.usda"))
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(24)
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(20)
    mesh = UsdGeom.Mesh.Define(stage, "/cube")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(QUADS)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(QUADS.ravel().tolist()))
    for code, k in ((10, 0), (11, 1), (12, 2), (16, 4)):
        mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(P[k].astype(np.float32)), code)
    stage.GetRootLayer().Save()
    d = read_driver(tmp_path / "hold.usda")
    np.testing.assert_allclose(d.times, np.arange(1, 21) / 24)
    frames = d.positions
    np.testing.assert_allclose(frames[:10], np.broadcast_to(P[0], (10, *P[0].shape)), atol=1e-6)
    np.testing.assert_allclose(frames[15:], np.broadcast_to(P[4], (5, *P[4].shape)), atol=1e-6)
    np.testing.assert_allclose(frames[13], P[2] + 0.5 * (P[4] - P[2]), atol=1e-6)  # frame 14


@pytest.mark.parametrize("rate, fps", [(24, 24), (30, 30), (30, 24)])
def test_usd_skinning_driver_lands_on_its_time_codes(tmp_path, rate, fps):
    """UsdSkel skinning (one joint, turned and moved at time codes 1-5) at the stage's own
    rate: the cube is posed by the joint at code k and lands at time k / rate.  The baked
    points were off between the codes 1 and 5 at 30 codes per second (USD's session layer
    keeps 24 unless told; Blender writes its scene's rate).  Blender 5 writes 24 frames per
    second beside 30 time codes per second: the driver has the time codes' frames only (the
    bake added samples at 2.25, 3.5, ...)."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.CreateNew(str(tmp_path / "rig.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(rate)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(1)  # as Blender writes the scene's frame range
    stage.SetEndTimeCode(FRAMES)
    UsdSkel.Root.Define(stage, "/rig")
    skel = UsdSkel.Skeleton.Define(stage, "/rig/skel")
    identity = Vt.Matrix4dArray([Gf.Matrix4d(1.0)])
    skel.CreateJointsAttr(Vt.TokenArray(["root"]))
    skel.CreateBindTransformsAttr(identity)
    skel.CreateRestTransformsAttr(identity)
    anim = UsdSkel.Animation.Define(stage, "/rig/skel/anim")
    anim.CreateJointsAttr(Vt.TokenArray(["root"]))
    codes = np.arange(1, FRAMES + 1)
    turns = Rotation.from_euler("y", 20.0 * codes[:, None], degrees=True)
    shifts = np.stack([0.1 * codes, 0.02 * codes**2, np.zeros(FRAMES)], -1)
    for k, code in enumerate(codes):
        x, y, z, w = turns[k].as_quat()
        anim.CreateRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(w, x, y, z)]), float(code))
        anim.CreateTranslationsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(*shifts[k])]), float(code))
    anim.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1.0, 1.0, 1.0)]))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    mesh = UsdGeom.Mesh.Define(stage, "/rig/cube")
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(CUBE.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([4] * len(QUADS)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(QUADS.ravel().tolist()))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set(Vt.IntArray([0] * len(CUBE)))
    binding.CreateJointWeightsPrimvar(False, 1).Set(Vt.FloatArray([1.0] * len(CUBE)))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    stage.GetRootLayer().Save()
    d = read_driver(tmp_path / "rig.usda")
    assert d.kind == "USD skinning"
    np.testing.assert_allclose(d.times * rate, codes, atol=1e-9)  # no frame between codes
    for k, code in enumerate(codes):
        t = code / rate
        row = int(np.argmin(np.abs(d.times - t)))
        assert d.times[row] == pytest.approx(t, abs=1e-9)
        np.testing.assert_allclose(d.positions[row], turns[k].apply(CUBE) + shifts[k],
                                   atol=1e-6)


def shift_yup(shift_cm: np.ndarray) -> np.ndarray:
    s = shift_cm / 100.0
    return np.stack([s[:, 0], s[:, 2], -s[:, 1]], -1)[:, None, :]


# ----------------------------------------------------------------------------------------------
# glTF: a minimal writer (JSON + one buffer), independent of the reader


def write_glb(path: Path, doc: dict, arrays: list[tuple[np.ndarray, str, bool]]) -> Path:
    """A .glb of ``doc`` whose accessor i holds arrays[i] = (data, type, normalized)."""
    types = {np.dtype(np.float32): 5126, np.dtype(np.uint8): 5121, np.dtype(np.uint16): 5123,
             np.dtype(np.uint32): 5125}
    blob, views, accessors = bytearray(), [], []
    for data, kind, normalized in arrays:
        raw = np.ascontiguousarray(data).tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(raw)})
        blob += raw + b"\0" * (-len(raw) % 4)
        acc = {"bufferView": len(views) - 1, "componentType": types[data.dtype],
               "count": len(data), "type": kind}
        if normalized:
            acc["normalized"] = True
        accessors.append(acc)
    doc = {"asset": {"version": "2.0"}, **doc, "accessors": accessors, "bufferViews": views,
           "buffers": [{"byteLength": len(blob)}]}
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    out = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + 8 + len(blob))
    out += struct.pack("<II", len(text), 0x4E4F534A) + text
    out += struct.pack("<II", len(blob), 0x004E4942) + bytes(blob)
    path.write_bytes(out)
    return path


@pytest.mark.parametrize("base", ["buffer", "zeros"])
def test_sparse_positions_are_applied_to_the_rest_mesh_and_the_driver(tmp_path, base):
    """A 0.2 m cube whose POSITION accessor has a sparse substitution (glTF 3.6.2.3): the
    four top vertices moved from y = 0.2 to y = 0.5 over the stored cube, or, for an
    accessor without a bufferView, every vertex given by the substitution over zeros.  The
    mesh and the driver are the 0.2 x 0.5 x 0.2 box: its vertices exactly, volume 0.02."""
    top = np.flatnonzero(CUBE[:, 1] > 0)
    moved = CUBE.copy()
    moved[top, 1] = 0.5
    rows = top if base == "buffer" else np.arange(len(CUBE))
    doc = {"scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"name": "bar", "mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}]}
    path = write_glb(tmp_path / "bar.glb", doc, [
        (CUBE.astype(np.float32), "VEC3", False), (TRIS.ravel().astype(np.uint16), "SCALAR",
                                                   False),
        (rows.astype(np.uint32), "SCALAR", False),
        (moved[rows].astype(np.float32), "VEC3", False)])
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + length])
    gltf["accessors"][0]["sparse"] = {
        "count": len(rows), "indices": {"bufferView": 2, "componentType": 5125},
        "values": {"bufferView": 3}}
    gltf["accessors"][0]["max"] = [0.2, 0.5, 0.2]
    if base == "zeros":
        del gltf["accessors"][0]["bufferView"]
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + data[20 + length:]
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    from wiggly.mesh.loading import load_mesh

    surface = load_mesh(path)
    np.testing.assert_allclose(surface.vertices, moved, rtol=0, atol=1e-7)  # float32
    P = surface.vertices[surface.faces]
    volume = np.einsum("ij,ij->i", P[:, 0], np.cross(P[:, 1], P[:, 2])).sum() / 6
    assert abs(volume) == pytest.approx(0.2 * 0.5 * 0.2, rel=1e-6)
    np.testing.assert_allclose(read_driver(path).positions[0], moved, rtol=0, atol=1e-7)


def test_gltf_groups_are_named_by_node_and_primitive_on_every_read(tmp_path):
    """A node "body" whose mesh has two primitives (two cubes) and an unnamed node beside
    it: a group per node (the unnamed one by its mesh's name) and one per primitive of the
    two-primitive mesh, the same names on every read; a file of one mesh node has that
    node's group."""
    cube = CUBE.astype(np.float32)
    tris = TRIS.ravel().astype(np.uint16)
    doc = {"scene": 0, "scenes": [{"nodes": [0, 1]}],
           "nodes": [{"name": "body", "mesh": 0}, {"mesh": 1, "translation": [0, 1.0, 0]}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1},
                                      {"attributes": {"POSITION": 2}, "indices": 1}]},
                      {"name": "lid", "primitives": [{"attributes": {"POSITION": 0},
                                                      "indices": 1}]}]}
    path = write_glb(tmp_path / "two.glb", doc, [(cube, "VEC3", False),
                                                (tris, "SCALAR", False),
                                                (cube + np.float32(0.5), "VEC3", False)])
    from wiggly.mesh.loading import load_mesh

    expected = {"body": range(0, 16), "body/primitive 0": range(0, 8),
                "body/primitive 1": range(8, 16), "lid": range(16, 24)}
    for _ in range(2):
        surface = load_mesh(path)
        assert {k: v.tolist() for k, v in surface.groups.items()} == {
            k: list(v) for k, v in expected.items()}
    np.testing.assert_allclose(surface.vertices[surface.groups["body/primitive 1"]],
                               CUBE + 0.5, atol=1e-7)
    np.testing.assert_allclose(surface.vertices[surface.groups["lid"]],
                               CUBE + np.array([0, 1.0, 0]), atol=1e-7)
    one = write_glb(tmp_path / "one.glb", {"nodes": [{"name": "bar", "mesh": 0}],
                                           "meshes": doc["meshes"][1:]},
                    [(cube, "VEC3", False), (tris, "SCALAR", False)])
    assert {k: v.tolist() for k, v in load_mesh(one).groups.items()} == {"bar": list(range(8))}


def test_gltf_morph_targets_under_a_moving_parent(tmp_path):
    """Base + w1 D1 + w2 D2 with LINEAR weights (not one-hot), the mesh node under a parent
    whose translation is animated: both evaluated at every key time and between the keys."""
    D1 = np.zeros_like(CUBE)
    D1[:, 1] = CUBE[:, 0]  # shear
    D2 = 0.1 * CUBE  # grow
    keys = np.array([0.0, 0.5, 1.0], np.float32)
    W = np.array([[0.0, 0.0], [1.0, 0.5], [0.2, 1.0]], np.float32)
    T = np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0.2, 0]], np.float32)
    doc = {"scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"children": [1], "translation": [0, 0, 0]},
                     {"mesh": 0, "scale": [2.0, 2.0, 2.0]}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1,
                                       "targets": [{"POSITION": 2}, {"POSITION": 3}]}]}],
           "animations": [{"name": "wobble",
                           "samplers": [{"input": 4, "output": 5}, {"input": 4, "output": 6}],
                           "channels": [{"sampler": 0, "target": {"node": 1, "path": "weights"}},
                                        {"sampler": 1,
                                         "target": {"node": 0, "path": "translation"}}]}]}
    path = write_glb(tmp_path / "wobble.glb", doc, [
        (CUBE.astype(np.float32), "VEC3", False), (TRIS.astype(np.uint16).ravel(), "SCALAR", False),
        (D1.astype(np.float32), "VEC3", False), (D2.astype(np.float32), "VEC3", False),
        (keys, "SCALAR", False), (W.ravel(), "SCALAR", False), (T, "VEC3", False)])
    d = read_driver(path, animation="wobble")
    assert d.kind == "glTF morph targets"
    # keys half a second apart: frames at the keys and at 30 per second between them, each
    # the LINEAR interpolation of the keys (a spline through the keys alone strays from it)
    assert np.all(np.isin(keys, d.times.astype(np.float32)))
    np.testing.assert_allclose(np.diff(d.times), 1 / 30, rtol=1e-6)
    for k, t in enumerate(d.times):
        w = [np.interp(t, keys, W[:, j]) for j in range(2)]
        shift = [np.interp(t, keys, T[:, j]) for j in range(3)]
        expected = 2.0 * (CUBE + w[0] * D1 + w[1] * D2) + shift
        np.testing.assert_allclose(d.positions[k], expected, atol=1e-6)
    with pytest.raises(WigglyInputError, match=r"no animation named 'walk'.*'wobble'"):
        read_driver(path, animation="walk")


def test_gltf_skin_matches_a_hand_computed_blend(tmp_path):
    """Linear blend skinning of a two-joint chain: root joint rotating about z (LINEAR: slerp
    of coaxial rotations interpolates the angle linearly) and translating along a CUBICSPLINE,
    child joint rotating about x (STEP), inverse bind matrices, normalized UNSIGNED_BYTE
    weights, and a transform on the mesh node that the specification says to ignore.  The
    expected positions are products of explicit 4x4 matrices."""
    X = np.array([[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 2.0, 0.5], [1.5, 1.5, 0.0]],
                 np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]], np.uint16)
    joints = np.array([[0, 1, 0, 0]] * 4, np.uint8)
    wb = np.array([[255, 0, 0, 0], [0, 255, 0, 0], [64, 191, 0, 0], [128, 127, 0, 0]],
                  np.uint8)  # normalized: w = byte / 255
    ibm = np.stack([np.linalg.inv(trans(1, 0, 0)), np.linalg.inv(trans(1, 1, 0))])
    root_keys = np.array([0.0, 0.5, 1.0], np.float32)
    root_angles = np.radians([0.0, 40.0, 100.0])
    root_rot = Rotation.from_euler("z", root_angles[:, None]).as_quat().astype(np.float32)
    child_keys = np.array([0.0, 0.4, 1.0], np.float32)
    child_angles = np.radians([0.0, 30.0, -20.0])
    child_rot = Rotation.from_euler("x", child_angles[:, None]).as_quat().astype(np.float32)
    # CUBICSPLINE translation of the root: (in-tangent, value, out-tangent) per key
    values = np.array([[1, 0, 0], [1, 0.2, 0], [1.5, 0.5, 0]], np.float64)
    tangents_in = np.array([[0, 0, 0], [0.4, 0.0, 0], [0, 1, 0]], np.float64)
    tangents_out = np.array([[0, 1.0, 0], [0.2, 0.6, 0], [0, 0, 0]], np.float64)
    cubic = np.stack([tangents_in, values, tangents_out], 1).astype(np.float32)
    doc = {"scene": 0, "scenes": [{"nodes": [0, 1]}],
           "nodes": [{"mesh": 0, "skin": 0, "translation": [10.0, 0, 0]},  # ignored
                     {"name": "root", "translation": [1.0, 0, 0], "children": [2]},
                     {"name": "child", "translation": [0, 1.0, 0]}],
           "skins": [{"joints": [1, 2], "inverseBindMatrices": 4}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 2,
                                                      "WEIGHTS_0": 3}, "indices": 1}]}],
           "animations": [{"samplers": [
               {"input": 5, "output": 6, "interpolation": "LINEAR"},
               {"input": 7, "output": 8, "interpolation": "STEP"},
               {"input": 5, "output": 9, "interpolation": "CUBICSPLINE"}],
               "channels": [{"sampler": 0, "target": {"node": 1, "path": "rotation"}},
                            {"sampler": 1, "target": {"node": 2, "path": "rotation"}},
                            {"sampler": 2, "target": {"node": 1, "path": "translation"}}]}]}
    path = write_glb(tmp_path / "chain.glb", doc, [
        (X, "VEC3", False), (faces.ravel(), "SCALAR", False), (joints, "VEC4", False),
        (wb, "VEC4", True), (ibm.transpose(0, 2, 1).reshape(-1, 16).astype(np.float32), "MAT4",
                             False),
        (root_keys, "SCALAR", False), (root_rot, "VEC4", False), (child_keys, "SCALAR", False),
        (child_rot, "VEC4", False), (cubic.reshape(-1, 3), "VEC3", False)])
    d = read_driver(path)
    assert d.kind == "glTF skin"
    # every key time, and frames in between (keys 0.1-0.5 s apart), each checked below
    assert np.all(np.isin(np.float32([0.0, 0.4, 0.5, 1.0]), d.times.astype(np.float32)))
    assert np.diff(d.times).max() <= 1.5 / 30 and len(d.times) > 4
    w = wb / 255.0
    for t, x in zip(d.times, d.positions, strict=True):
        # root: angle linear in t between keys; translation: the cubic Hermite segment
        k = 0 if t < 0.5 else 1
        s = (t - root_keys[k]) / 0.5
        alpha = root_angles[k] + s * (root_angles[k + 1] - root_angles[k])
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        p = (h00 * values[k] + h10 * 0.5 * tangents_out[k] + h01 * values[k + 1]
             + h11 * 0.5 * tangents_in[k + 1])
        beta = child_angles[np.searchsorted(child_keys, t + 1e-6) - 1]  # STEP: last key <= t
        G_root = trans(*p) @ rot("z", alpha)
        G_child = G_root @ trans(0, 1, 0) @ rot("x", beta)
        J = [G_root @ ibm[0], G_child @ ibm[1]]
        Xh = np.c_[X, np.ones(4)]
        expected = np.array([(w[i, 0] * J[0] + w[i, 1] * J[1]) @ Xh[i] for i in range(4)])
        np.testing.assert_allclose(x, expected[:, :3], atol=2e-6, err_msg=f"t = {t}")


def trans(x, y, z) -> np.ndarray:
    M = np.eye(4)
    M[:3, 3] = (x, y, z)
    return M


def rot(axis: str, angle: float) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler(axis, angle).as_matrix()
    return M


def test_sampler_interpolations_hold_the_ends_and_slerp_the_short_way():
    keys = np.array([1.0, 2.0])
    v = np.array([[0.0], [10.0]])
    t = np.array([0.0, 1.0, 1.25, 2.0, 3.0])
    np.testing.assert_allclose(sample(keys, v, "LINEAR", t)[:, 0], [0, 0, 2.5, 10, 10])
    np.testing.assert_allclose(sample(keys, v, "STEP", t)[:, 0], [0, 0, 0, 10, 10])
    a = Rotation.from_euler("z", 170, degrees=True).as_quat()
    b = -Rotation.from_euler("z", -170, degrees=True).as_quat()  # 20 degrees away, sign flipped
    mid = Rotation.from_quat(slerp(a, b, np.array(0.5)))
    assert abs(abs(mid.as_euler("xyz", degrees=True)[2]) - 180.0) < 1e-9


# ----------------------------------------------------------------------------------------------
# topology


def test_topology_mismatch_names_both_counts_and_the_file():
    times, P = sequence()
    d = Driver(times, np.concatenate([P, P[:, :1]], axis=1), TRIS, np.zeros((0, 2)),
               "walk.usdc", "USD points")
    with pytest.raises(WigglyInputError) as err:
        d.check(8, TRIS, "cube.obj")
    message = str(err.value)
    assert "walk.usdc" in message and "9 vertices" in message and "cube.obj" in message
    assert "8 vertices" in message and "split vertices at UV seams" not in message
    # a USD driver of the object whose glTF is the mesh: the counts differ by the glTF's
    # split vertices, which the message explains (it only said "the same object")
    with pytest.raises(WigglyInputError, match="glTF exporters split vertices at UV seams"):
        d.check(8, TRIS, "cube.glb")


def test_same_count_in_another_order_is_refused():
    from wiggly.drive.driver import polygon_edges

    times, P = sequence()
    perm = np.array([0, 7, 2, 5, 4, 3, 6, 1])  # the vertices shuffled: the edges no longer fit
    inverse = np.argsort(perm)
    d = Driver(times, P[:, perm], inverse[TRIS], polygon_edges(inverse[QUADS]), "walk.glb",
               "glTF skin")
    assert d.mismatch(8, TRIS, "cube.obj") is not None
    assert "another order" in d.mismatch(8, TRIS, "cube.obj")
    # a mesh from another file: the hint names the one-glTF way for rigs of several objects
    assert "one glTF file" in d.mismatch(8, TRIS, "cube.obj")
    assert "one glTF file" not in d.mismatch(8, TRIS, "walk.glb")
    d.check(8, inverse[TRIS], "shuffled.obj")  # the same shuffle on both sides is fine


def test_unreadable_drivers_say_what_is_wrong(tmp_path):
    (tmp_path / "broken.glb").write_bytes(b"glTF\x02\x00\x00\x00")
    with pytest.raises(WigglyInputError, match=r"broken\.glb"):
        read_driver(tmp_path / "broken.glb")
    with pytest.raises(WigglyInputError, match="no such file"):
        read_driver(tmp_path / "missing.usdc")
    with pytest.raises(WigglyInputError, match=r"unknown extension '\.fbx'"):
        read_driver(tmp_path / "walk.fbx")
    with pytest.raises(WigglyInputError, match="no numbered files"):
        read_driver(tmp_path / "walk_####.obj", frame_rate=24)


def test_a_skinned_rest_mesh_is_posed_by_its_joints_not_its_node(tmp_path):
    """A rig scaled by 2 and moved, as Blender writes it: the skinned mesh node is the rig's
    child, its positions are already in world scale, and each inverse bind matrix undoes its
    joint's bind transform.  The rest mesh is the linear blend of the joints' static
    transforms (glTF 3.7.3: the skinned node's transform is ignored), not the positions times
    the node's transform (which trimesh alone applies: twice the scale, moved twice).  The
    second joint's static rotation differs from its bind pose, so that vertex's rest is a
    true blend; normals follow the blended linear parts."""
    X = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                 np.float32)
    N = np.array([[-1, -1, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint16)
    joints = np.array([[0, 1, 0, 0]] * 4, np.uint8)
    w = np.array([[1, 0, 0, 0], [1, 0, 0, 0], [0.5, 0.5, 0, 0], [0, 1, 0, 0]], np.float32)
    rig = trans(3, 0, 0) @ np.diag([2.0, 2, 2, 1])
    bind_root, bind_child = rig, rig @ trans(0, 0.5, 0)
    static_child = rig @ trans(0, 0.5, 0) @ rot("x", np.radians(30))
    ibm = np.stack([np.linalg.inv(bind_root), np.linalg.inv(bind_child)])
    quat = Rotation.from_euler("x", np.radians(30)).as_quat().tolist()
    doc = {"scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"name": "Rig", "translation": [3.0, 0, 0], "scale": [2.0, 2, 2],
                      "children": [1, 2]},
                     {"name": "Body", "mesh": 0, "skin": 0},
                     {"name": "root", "children": [3]},
                     {"name": "child", "translation": [0, 0.5, 0], "rotation": quat}],
           "skins": [{"joints": [2, 3], "inverseBindMatrices": 5}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1,
                                                      "JOINTS_0": 3, "WEIGHTS_0": 4},
                                       "indices": 2}]}]}
    path = write_glb(tmp_path / "rig.glb", doc, [
        (X, "VEC3", False), (N, "VEC3", False), (faces.ravel(), "SCALAR", False),
        (joints, "VEC4", False), (w, "VEC4", False),
        (ibm.transpose(0, 2, 1).reshape(-1, 16).astype(np.float32), "MAT4", False)])
    from wiggly.mesh.loading import load_mesh

    surface = load_mesh(path)
    J = [bind_root @ ibm[0], static_child @ ibm[1]]
    B = np.array([w[i, 0] * J[0] + w[i, 1] * J[1] for i in range(4)])
    expected = np.einsum("nab,nb->na", B[:, :3, :3], X) + B[:, :3, 3]
    np.testing.assert_allclose(surface.vertices, expected, atol=1e-6)
    np.testing.assert_allclose(surface.vertices[:2], X[:2], atol=1e-6)  # Blender's case
    normals = np.einsum("ni,nij->nj", N, np.linalg.inv(B[:, :3, :3]))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_allclose(surface.normals, normals, atol=1e-6)
    d = read_driver(path)  # no animation: the driver's one frame is the rest
    np.testing.assert_allclose(d.positions[0], surface.vertices, atol=1e-6)


def test_a_glb_with_several_animations_says_which_it_plays(tmp_path):
    """Blender writes a rig's action and a shape-key action as two glTF animations; the driver
    plays the first and names the ones it leaves out, unless one is named."""
    keys = np.array([0.0, 1.0], np.float32)
    T = np.array([[0, 0, 0], [1.0, 0, 0]], np.float32)
    doc = {"scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "hips"}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
           "animations": [
               {"name": name, "samplers": [{"input": 2, "output": 3}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]}
               for name in ("ArmatureAction", "KeyAction")]}
    path = write_glb(tmp_path / "two.glb", doc, [
        (CUBE.astype(np.float32), "VEC3", False), (TRIS.astype(np.uint16).ravel(), "SCALAR", False),
        (keys, "SCALAR", False), (T, "VEC3", False)])
    with pytest.warns(UserWarning, match=r"2 animations.*#0 'ArmatureAction', #1 'KeyAction'"):
        read_driver(path)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_driver(path, animation="KeyAction")
    with pytest.raises(WigglyInputError, match=r"'ArmatureAction' and 'KeyAction' both animate "
                                               r"the translation of node 0 \('hips'\)"):
        read_driver(path, animation=["ArmatureAction", "KeyAction"])


def test_two_animations_play_together(tmp_path):
    """A node's translation in one animation and the morph weights of its mesh in another
    (as Blender writes a rig's action and a shape-key action): named together, both play,
    at the union of their key times."""
    D = 0.1 * CUBE
    doc = {"scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1,
                                       "targets": [{"POSITION": 2}]}]}],
           "animations": [
               {"name": "walk", "samplers": [{"input": 3, "output": 4}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}]},
               {"name": "breathe", "samplers": [{"input": 5, "output": 6}],
                "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}]}
    path = write_glb(tmp_path / "both.glb", doc, [
        (CUBE.astype(np.float32), "VEC3", False), (TRIS.astype(np.uint16).ravel(), "SCALAR", False),
        (D.astype(np.float32), "VEC3", False),
        (np.array([0.0, 1.0], np.float32), "SCALAR", False),
        (np.array([[0, 0, 0], [1.0, 0, 0]], np.float32), "VEC3", False),
        (np.array([0.0, 0.5, 1.0], np.float32), "SCALAR", False),
        (np.array([0.0, 1.0, 0.0], np.float32), "SCALAR", False)])
    d = read_driver(path, animation=["walk", "breathe"])
    assert np.all(np.isin([0.0, 0.5, 1.0], d.times))
    for t, w, x in ((0.0, 0.0, 0.0), (0.5, 1.0, 0.5), (1.0, 0.0, 1.0)):
        k = int(np.argmin(np.abs(d.times - t)))
        np.testing.assert_allclose(d.positions[k], CUBE + w * D + [x, 0, 0], atol=1e-6)


@pytest.mark.parametrize("angle", [0.0, 30.0])
def test_a_skin_saved_off_its_bind_pose_is_warned_about(tmp_path, angle):
    """A bar skinned to two joints: saved at its bind pose (angle 0, as Blender's default
    export) the rest mesh is the stored bar and nothing is said; with the second joint
    turned 30 degrees from its bind, the rest mesh is the bent bar a viewer shows, and the
    loader says that the skeleton is not at its bind pose."""
    x = np.linspace(0.0, 1.0, 6)
    X = np.array([[a, b, c] for a in x for b in (0.0, 0.1) for c in (0.0, 0.1)], np.float32)
    faces = np.array([[i, i + 1, i + 2] for i in range(len(X) - 2)], np.uint16)
    joints = np.zeros((len(X), 4), np.uint8)
    joints[:, 0] = X[:, 0] > 0.5
    w = np.zeros((len(X), 4), np.float32)
    w[:, 0] = 1.0
    ibm = np.stack([np.eye(4), np.linalg.inv(trans(0.5, 0, 0))])
    quat = Rotation.from_euler("z", np.radians(angle)).as_quat().tolist()
    doc = {"scene": 0, "scenes": [{"nodes": [0, 1]}],
           "nodes": [{"mesh": 0, "skin": 0}, {"name": "root", "children": [2]},
                     {"name": "tip", "translation": [0.5, 0, 0], "rotation": quat}],
           "skins": [{"joints": [1, 2], "inverseBindMatrices": 4}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 2,
                                                      "WEIGHTS_0": 3}, "indices": 1}]}]}
    path = write_glb(tmp_path / "bar.glb", doc, [
        (X, "VEC3", False), (faces.ravel(), "SCALAR", False), (joints, "VEC4", False),
        (w, "VEC4", False), (ibm.transpose(0, 2, 1).reshape(-1, 16).astype(np.float32),
                             "MAT4", False)])
    import warnings

    from wiggly.mesh.loading import load_mesh

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        surface = load_mesh(path)
    said = [str(s.message) for s in seen if "bind pose" in str(s.message)]
    tip = X[:, 0] > 0.5
    expected = X.astype(np.float64)
    R = Rotation.from_euler("z", np.radians(angle)).as_matrix()
    expected[tip] = (X[tip] - [0.5, 0, 0]) @ R.T + [0.5, 0, 0]
    np.testing.assert_allclose(surface.vertices, expected, atol=1e-6)
    if angle == 0.0:
        assert not said, said
    else:
        assert len(said) == 1 and "bar.glb" in said[0] and "Use Rest Position" in said[0]


def test_a_scaled_skin_beside_a_plain_mesh_is_not_called_posed(tmp_path):
    """Centimetre exports (a skin whose joints scale it by 0.01, as converted Mixamo files
    are) next to a mesh without a skin: each skinned primitive is checked on its own, so
    one affine map per skin is not mistaken for a pose."""
    import warnings

    from wiggly.mesh.loading import load_mesh

    X = (100 * CUBE).astype(np.float32)
    joints = np.zeros((len(X), 4), np.uint8)
    w = np.zeros((len(X), 4), np.float32)
    w[:, 0] = 1.0
    doc = {"scene": 0, "scenes": [{"nodes": [0, 1, 2]}],
           "nodes": [{"mesh": 0, "skin": 0}, {"name": "root", "scale": [0.01, 0.01, 0.01]},
                     {"mesh": 1, "translation": [2.0, 0, 0]}],
           "skins": [{"joints": [1]}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "JOINTS_0": 2,
                                                      "WEIGHTS_0": 3}, "indices": 1}]},
                      {"primitives": [{"attributes": {"POSITION": 4}, "indices": 1}]}]}
    path = write_glb(tmp_path / "cm.glb", doc, [
        (X, "VEC3", False), (TRIS.astype(np.uint16).ravel(), "SCALAR", False),
        (joints, "VEC4", False), (w, "VEC4", False), (CUBE.astype(np.float32), "VEC3", False)])
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        surface = load_mesh(path)
    assert not [s for s in seen if "bind pose" in str(s.message)]
    np.testing.assert_allclose(surface.vertices[:len(X)], CUBE, atol=1e-6)
    np.testing.assert_allclose(surface.vertices[len(X):], CUBE + np.array([2.0, 0, 0]), atol=1e-6)
