"""glTF 2.0 binary: the rest mesh with one morph target per frame (or two per mode) and a
weights animation."""

from __future__ import annotations

import base64
import io
import struct
import urllib.parse
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from wiggly.errors import WigglyInputError, counted, warn
from wiggly.export.animation import (
    FORMAT_VERSION,
    FrameNormals,
    SurfaceAnimation,
    format_library,
    frame_progress,
    gltf_times,
)
from wiggly.files import shown_name

# ----------------------------------------------------------------------------------------------
# glTF binary

_GL_FLOAT, _GL_UNSIGNED_SHORT, _GL_UNSIGNED_INT = 5126, 5123, 5125
_GL_ARRAY_BUFFER, _GL_ELEMENT_ARRAY_BUFFER = 34962, 34963
_GL_TRIANGLES = 4
_GL_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
_GL_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


class _Chunk:
    """The GLB's binary chunk, laid out before it is written: each buffer view gets its
    4-byte aligned offset now and its bytes from ``write`` later, so that a long animation is
    streamed to the file frame by frame instead of held in memory as one blob."""

    def __init__(self) -> None:
        self.length = 0
        self.parts: list[tuple[int, Callable[[BinaryIO], None]]] = []

    def add(self, nbytes: int, write: Callable[[BinaryIO], None]) -> int:
        """Reserve ``nbytes`` at the next aligned offset (returned) for ``write``."""
        offset = self.length
        self.parts.append((nbytes, write))
        self.length += nbytes + (-nbytes % 4)
        return offset

    def write(self, f: BinaryIO) -> None:
        for nbytes, write in self.parts:
            start = f.tell()
            write(f)
            assert f.tell() - start == nbytes, "a view wrote other than its length"
            f.write(b"\0" * (-nbytes % 4))


def _write_array(data: np.ndarray) -> Callable[[BinaryIO], None]:
    return lambda f: f.write(memoryview(np.ascontiguousarray(data)).cast("B"))


def write_glb(path: Path, anim: SurfaceAnimation, *,
              frame_start: int | None = None, targets: str = "frames",
              embedded: bool = False) -> None:
    """The animation as glTF 2.0 at ``path``: binary (.glb), or with ``embedded`` a .gltf
    file, its JSON with the same data in a base64 data URI (a third larger)."""
    gl = format_library("pygltflib", "pygltflib", ".gltf" if embedded else ".glb")

    F, n = anim.n_frames, anim.n_vertices
    frame_normals = FrameNormals(anim)
    rest = anim.positions[0] if anim.rest is None else anim.rest
    base_p = rest.astype(np.float32)
    base_n = (anim.normals if anim.normals is not None else frame_normals(rest))
    base_n = base_n.astype(np.float32)
    chunk = _Chunk()
    if targets == "modes":
        dP, dN, weights, names = _modal_targets(anim, frame_normals, base_n)
        n_targets = len(dP)
        bounds = [(d.min(axis=0), d.max(axis=0)) for d in dP]
        write_dp, write_dn = _write_array(dP), _write_array(dN)
    else:
        def delta(k: int) -> np.ndarray:  # frame k's position target, float32 as written
            return anim.positions[k].astype(np.float32) - base_p

        bounds = [(d.min(axis=0), d.max(axis=0)) for d in map(delta, range(F))]

        def write_dp(f: BinaryIO) -> None:
            for k in range(F):
                f.write(memoryview(delta(k)).cast("B"))

        def write_dn(f: BinaryIO) -> None:  # the normals: the slow part, counted
            for k in frame_progress(range(F), F, path):
                dn = frame_normals(anim.positions[k]).astype(np.float32) - base_n
                f.write(memoryview(np.ascontiguousarray(dn)).cast("B"))

        n_targets = F
        weights = None  # keyframe k: weight 1 on target k, 0 on the others (sparse below)
        names = [f"frame_{k:04d}" for k in range(F)]
    t32 = gltf_times(anim.times, frame_start, anim.loop)
    index_type = _GL_UNSIGNED_SHORT if n <= 65535 else _GL_UNSIGNED_INT

    views, accessors = [], []

    def add_view(nbytes: int, write, target=None, stride=None) -> int:
        views.append(gl.BufferView(buffer=0, byteOffset=chunk.add(nbytes, write),
                                   byteLength=nbytes, target=target, byteStride=stride))
        return len(views) - 1

    def add_data(data: np.ndarray, target=None) -> int:
        return add_view(data.nbytes, _write_array(data), target)

    def add_accessor(view, count, ctype, kind, offset=0, bounds=None) -> int:
        acc = gl.Accessor(bufferView=view, byteOffset=offset, componentType=ctype,
                          count=count, type=kind)
        if bounds is not None:
            acc.min = np.atleast_1d(bounds[0]).astype(float).tolist()
            acc.max = np.atleast_1d(bounds[1]).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    def extent(data: np.ndarray) -> tuple:
        return data.min(axis=0), data.max(axis=0)

    indices = anim.faces.ravel().astype(np.uint16 if index_type == _GL_UNSIGNED_SHORT
                                         else np.uint32)
    attributes = gl.Attributes(
        POSITION=add_accessor(add_data(base_p, _GL_ARRAY_BUFFER), n, _GL_FLOAT, "VEC3",
                              bounds=extent(base_p)),
        NORMAL=add_accessor(add_data(base_n, _GL_ARRAY_BUFFER), n, _GL_FLOAT, "VEC3"),
    )
    if anim.uvs is not None:
        st = np.column_stack([anim.uvs[:, 0], 1.0 - anim.uvs[:, 1]]).astype(np.float32)
        attributes.TEXCOORD_0 = add_accessor(add_data(st, _GL_ARRAY_BUFFER), n, _GL_FLOAT,
                                             "VEC2")
    index_accessor = add_accessor(add_data(indices, _GL_ELEMENT_ARRAY_BUFFER), len(indices),
                                  index_type, "SCALAR", bounds=extent(indices))
    # All position deltas in one strided view, all normal deltas in another.
    view_dp = add_view(n_targets * n * 12, write_dp, _GL_ARRAY_BUFFER, stride=12)
    view_dn = add_view(n_targets * n * 12, write_dn, _GL_ARRAY_BUFFER, stride=12)
    morph = [
        gl.Attributes(
            POSITION=add_accessor(view_dp, n, _GL_FLOAT, "VEC3", offset=k * n * 12,
                                  bounds=bounds[k]),
            NORMAL=add_accessor(view_dn, n, _GL_FLOAT, "VEC3", offset=k * n * 12),
        )
        for k in range(n_targets)
    ]
    time_accessor = add_accessor(add_data(t32), len(t32), _GL_FLOAT, "SCALAR",
                                 bounds=extent(t32))
    if weights is None:  # the identity of F x F weights, sparse: F entries, not F^2 (an
        # 18001-frame shot had 1.3 GB of zeros); indices k F + k rise, as glTF asks
        diagonal = np.arange(F, dtype=np.uint32) * np.uint32(F + 1)
        accessors.append(gl.Accessor(componentType=_GL_FLOAT, count=F * F, type="SCALAR",
                                     byteOffset=None,  # no bufferView: zeros but the sparse
                                     sparse=gl.Sparse(
            count=F,
            indices=gl.AccessorSparseIndices(bufferView=add_data(diagonal),
                                             componentType=_GL_UNSIGNED_INT),
            values=gl.AccessorSparseValues(bufferView=add_data(np.ones(F, np.float32))))))
        weight_accessor = len(accessors) - 1
    else:
        flat = weights.astype(np.float32).ravel()
        weight_accessor = add_accessor(add_data(flat), len(flat), _GL_FLOAT, "SCALAR")
    extras = {"format_version": FORMAT_VERSION, "times": anim.times.tolist(),
              "targets": targets, "loop": bool(anim.loop)}
    dt = np.diff(anim.times)
    if len(dt) and np.all(np.abs(dt - dt.mean()) <= 1e-6 * dt.mean()):  # glTF has only
        extras["frames_per_second"] = _rate(dt.mean())  # seconds: set a scene's rate
    if frame_start is not None:
        extras["frame_start"] = int(frame_start)

    gltf = gl.GLTF2(
        asset=gl.Asset(version="2.0", generator="wiggly"),
        scene=0,
        scenes=[gl.Scene(nodes=[0])],
        nodes=[gl.Node(mesh=0, name=anim.name)],
        meshes=[gl.Mesh(
            name=anim.name,
            primitives=[gl.Primitive(attributes=attributes, indices=index_accessor,
                                     mode=_GL_TRIANGLES, targets=morph)],
            weights=[0.0] * n_targets,
            extras={"targetNames": names},
        )],
        animations=[gl.Animation(
            name=anim.name,
            samplers=[gl.AnimationSampler(input=time_accessor, output=weight_accessor,
                                          interpolation="LINEAR")],
            channels=[gl.AnimationChannel(sampler=0, target=gl.AnimationChannelTarget(
                node=0, path="weights"))],
            extras={"wiggly": extras},
        )],
        accessors=accessors,
        bufferViews=views,
        buffers=[gl.Buffer(byteLength=chunk.length)],
    )
    if embedded:  # the buffer as a data URI (glTF 2.0, sec. 3.6.1.2)
        data = io.BytesIO()
        chunk.write(data)
        gltf.buffers[0].uri = ("data:application/octet-stream;base64,"
                               + base64.b64encode(data.getbuffer()).decode("ascii"))
        with open(path, "w", encoding="utf-8") as f:
            f.write(gltf.gltf_to_json(separators=(",", ":"), indent=None))
        return
    text = gltf.gltf_to_json(separators=(",", ":"), indent=None).encode("utf-8")
    text += b" " * (-len(text) % 4)  # the binary chunk's data starts 4-byte aligned
    too_big(path, 12 + 8 + len(text) + 8 + chunk.length)
    with open(path, "wb") as f:  # GLB: header, JSON chunk, BIN chunk (glTF 2.0, sec. 4.4)
        f.write(struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(text) + 8 + chunk.length))
        f.write(struct.pack("<I4s", len(text), b"JSON") + text)
        f.write(struct.pack("<I4s", chunk.length, b"BIN\0"))
        chunk.write(f)
        assert f.tell() == 12 + 8 + len(text) + 8 + chunk.length


#: A GLB file's header and chunks give their lengths as 32-bit numbers (glTF 2.0, sec. 4.4).
GLB_LIMIT = 2**32 - 1


def frames_bytes(n_vertices: int, n_frames: int) -> int:
    """About the size of a .glb of ``n_frames`` frames as morph targets (float32 position and
    normal deltas per vertex and frame; the rest pose, faces and JSON not counted)."""
    return 24 * n_vertices * n_frames


def too_big(path, nbytes: int) -> None:
    """Refuse a .glb of ``nbytes`` beyond :data:`GLB_LIMIT`, saying what fits instead."""
    if nbytes > GLB_LIMIT:
        raise WigglyInputError(
            f"{shown_name(path)}: the .glb would be {nbytes / 2**30:.1f} GiB, more than the 4 "
            "GiB a GLB file can hold (its sizes are 32-bit numbers); write .usdc (no such "
            "limit) or .npz, fewer frames (a lower fps), or for a linear shot gltf_targets = "
            "\"modes\" (a morph target per mode, not per frame)")


def _modal_targets(anim: SurfaceAnimation, frame_normals: FrameNormals, base_n: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Morph targets of the compact layout (module docstring).

    Mode i, scaled by s_i = max_k |q_i(t_k)|, becomes a target ``+`` with weights
    max(q_i / s_i, 0) and a target ``-`` (the shape negated) with weights max(-q_i / s_i, 0):
    weights stay in [0, 1], the range of Blender's shape-key sliders (it clamps to them), and
    their difference interpolates linearly between frames, so positions are exact at and
    between frames.  A half whose weights are all 0 (and modes that stay at 0) is left out.
    NORMAL deltas are the normals' derivatives along the target at rest (central
    differences): first order.
    """
    scale = np.abs(anim.modal).max(axis=0)
    shapes, weights, names = [], [], []
    for i in np.flatnonzero(scale > 0):
        w = anim.modal[:, i] / scale[i]
        for sign, label in ((1.0, "+"), (-1.0, "-")):
            if (sign * w > 0).any():
                shapes.append(sign * scale[i] * anim.mode_shapes[i])
                weights.append(np.maximum(sign * w, 0.0))
                names.append(f"mode_{i:03d}{label}")
    dP = np.asarray(shapes, dtype=np.float32).reshape(-1, anim.n_vertices, 3)
    dN = np.empty_like(dP)
    eps = 1e-3
    for j, shape in enumerate(shapes):
        plus = frame_normals(anim.rest + eps * shape)
        minus = frame_normals(anim.rest - eps * shape)
        dN[j] = ((plus - minus) / (2 * eps)).astype(np.float32)
    return dP, dN, np.asarray(weights).reshape(len(shapes), -1).T, names


def _gl_accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    """The data of accessor ``index`` as a (count, width) array (strides, sparse, zeros)."""
    acc = gltf.accessors[index]
    dtype = np.dtype(_GL_DTYPES[acc.componentType])
    width = _GL_WIDTH[acc.type]
    if acc.bufferView is None:
        out = np.zeros((acc.count, width), dtype)
    else:
        view = gltf.bufferViews[acc.bufferView]
        stride = view.byteStride or dtype.itemsize * width
        offset = (view.byteOffset or 0) + (acc.byteOffset or 0)
        out = np.ndarray((acc.count, width), dtype, buffer=blob, offset=offset,
                         strides=(stride, dtype.itemsize)).copy()
    if acc.sparse is not None:
        s = acc.sparse
        iview, vview = gltf.bufferViews[s.indices.bufferView], gltf.bufferViews[s.values.bufferView]
        idx = np.frombuffer(blob, _GL_DTYPES[s.indices.componentType], s.count,
                            (iview.byteOffset or 0) + (s.indices.byteOffset or 0))
        out[idx] = np.frombuffer(blob, dtype, s.count * width,
                                 (vview.byteOffset or 0) + (s.values.byteOffset or 0)
                                 ).reshape(-1, width)
    if acc.normalized:
        out = out.astype(np.float64) / np.iinfo(dtype).max
    return out


def _read_primitive(gltf, blob: bytes, prim, path: Path, j: int) -> tuple:
    """One triangle primitive: its positions, faces, uvs and normals (None when absent) and
    its morph targets' position deltas (a list)."""
    if prim.mode not in (None, _GL_TRIANGLES) or prim.attributes.POSITION is None:
        raise WigglyInputError(f"cannot read {path}: primitive {j} of its mesh is not a "
                               "triangle mesh with POSITION")
    base = _gl_accessor(gltf, blob, prim.attributes.POSITION).astype(np.float32)
    faces = (_gl_accessor(gltf, blob, prim.indices).reshape(-1, 3) if prim.indices is not None
             else np.arange(len(base)).reshape(-1, 3)).astype(np.int64)
    uvs = normals = None
    if prim.attributes.TEXCOORD_0 is not None:
        st = _gl_accessor(gltf, blob, prim.attributes.TEXCOORD_0).astype(np.float64)
        uvs = np.column_stack([st[:, 0], 1.0 - st[:, 1]])
    if prim.attributes.NORMAL is not None:
        normals = _gl_accessor(gltf, blob, prim.attributes.NORMAL).astype(np.float64)
    deltas = [_gl_accessor(gltf, blob, t["POSITION"] if isinstance(t, dict) else t.POSITION)
              for t in prim.targets or []]
    return base, faces, uvs, normals, deltas


def _buffer(gltf, path: Path) -> bytes:
    """A .gltf file's buffer 0: a base64 data URI, or a file beside it."""
    if not gltf.buffers or not gltf.buffers[0].uri:
        return b""
    uri = gltf.buffers[0].uri
    if uri.startswith("data:"):
        return base64.b64decode(uri.split(",", 1)[1])
    source = path.parent / urllib.parse.unquote(uri)
    if not source.is_file():
        raise WigglyInputError(f"cannot read {path}: its buffer {uri} is not beside it")
    return source.read_bytes()


def read_glb(path: Path) -> SurfaceAnimation:
    gl = format_library("pygltflib", "pygltflib", ".glb")

    try:
        gltf = gl.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises assorted errors on malformed files
        raise WigglyInputError(f"cannot read {path}: not a valid glTF binary ({e})") from e
    blob = gltf.binary_blob() if path.suffix.lower() == ".glb" else _buffer(gltf, path)
    if not gltf.meshes or not gltf.meshes[0].primitives:
        raise WigglyInputError(f"cannot read {path}: the glTF file has no mesh")
    mesh_index = 0
    if len(gltf.meshes) > 1:
        warn(f"{path}: only its first mesh ({gltf.meshes[0].name or 'unnamed'}) is "
             f"read; left out: {counted(len(gltf.meshes) - 1, 'other mesh')}")
    parts = [_read_primitive(gltf, blob, prim, path, j)
             for j, prim in enumerate(gltf.meshes[mesh_index].primitives)]
    offsets = np.cumsum([0] + [len(part[0]) for part in parts])
    base = np.concatenate([part[0] for part in parts])
    faces = np.concatenate([part[1] + o for part, o in zip(parts, offsets[:-1], strict=True)])
    uvs = (np.concatenate([part[2] for part in parts])
           if all(part[2] is not None for part in parts) else None)
    normals = (np.concatenate([part[3] for part in parts])
               if all(part[3] is not None for part in parts) else None)
    counts = {len(part[4]) for part in parts}
    if len(counts) > 1:
        raise WigglyInputError(f"cannot read {path}: its mesh's primitives have different "
                               f"numbers of morph targets ({sorted(counts)}); glTF asks the same "
                               "number of every primitive")
    targets = parts[0][4]
    deltas = (np.concatenate([np.stack(part[4]) for part in parts], axis=1)
              if targets else None)
    nodes = [i for i, node in enumerate(gltf.nodes) if node.mesh == mesh_index]
    sampler = extras = None
    for animation in gltf.animations:
        for channel in animation.channels:
            if channel.target.path == "weights" and channel.target.node in nodes:
                sampler = animation.samplers[channel.sampler]
                extras = (animation.extras or {}).get("wiggly")
    if deltas is None:
        return SurfaceAnimation(np.zeros(1), base[None], faces, uvs, normals,
                                gltf.meshes[0].name or path.stem)
    if sampler is None:
        raise WigglyInputError(f"cannot read {path}: the mesh has morph targets but no "
                               "animation of its weights")
    times = _gl_accessor(gltf, blob, sampler.input).ravel().astype(np.float64)
    W = _gl_accessor(gltf, blob, sampler.output).astype(np.float64)
    if sampler.interpolation == "CUBICSPLINE":  # (in-tangent, value, out-tangent) per key
        W = W.reshape(len(times), 3, -1)[:, 1]
    W = W.reshape(len(times), len(targets))
    if extras and len(extras.get("times", ())) == len(times):
        times = np.asarray(extras["times"], np.float64)
    one_hot = np.all((W == 0) | (W == 1)) and np.all(W.sum(axis=1) <= 1)
    if one_hot:  # the layout written here: gather instead of a dense product
        k = np.where(W.any(axis=1), W.argmax(axis=1), -1)
        positions = base + np.where((k >= 0)[:, None, None], deltas[np.maximum(k, 0)], 0)
    else:
        positions = base + np.einsum("ft,tnc->fnc", W.astype(np.float32), deltas)
    return SurfaceAnimation(times, positions.astype(np.float32), faces, uvs, normals,
                            gltf.meshes[0].name or path.stem,
                            loop=bool((extras or {}).get("loop", False)))


def _rate(dt: float) -> float:
    """The frame rate of frames ``dt`` seconds apart, a whole number when it is one."""
    fps = 1.0 / dt
    return float(round(fps)) if abs(fps - round(fps)) <= 1e-6 * fps else fps
