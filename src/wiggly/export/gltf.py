"""glTF 2.0 binary: the rest mesh with one morph target per frame (or two per mode) and a
weights animation."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError, counted
from wiggly.export.animation import (
    FORMAT_VERSION,
    FrameNormals,
    SurfaceAnimation,
    format_library,
    frame_progress,
    gltf_times,
)

# ----------------------------------------------------------------------------------------------
# glTF binary

_GL_FLOAT, _GL_UNSIGNED_SHORT, _GL_UNSIGNED_INT = 5126, 5123, 5125
_GL_ARRAY_BUFFER, _GL_ELEMENT_ARRAY_BUFFER = 34962, 34963
_GL_TRIANGLES = 4
_GL_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
_GL_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def write_glb(path: Path, anim: SurfaceAnimation, *,
              frame_start: int | None = None, targets: str = "frames") -> None:
    gl = format_library("pygltflib", "pygltflib", ".glb")

    F, n = anim.n_frames, anim.n_vertices
    frame_normals = FrameNormals(anim)
    P = anim.positions.astype(np.float32)
    rest = anim.positions[0] if anim.rest is None else anim.rest
    base_p = rest.astype(np.float32)
    base_n = (anim.normals if anim.normals is not None else frame_normals(rest))
    base_n = base_n.astype(np.float32)
    if targets == "modes":
        dP, dN, weights, names = _modal_targets(anim, frame_normals, base_n)
    else:
        dP = P - base_p
        dN = np.empty_like(dP)
        for k in frame_progress(range(F), F, path):
            dN[k] = frame_normals(anim.positions[k]).astype(np.float32) - base_n
        weights = np.eye(F, dtype=np.float32)  # keyframe k: weight 1 on target k
        names = [f"frame_{k:04d}" for k in range(F)]
    n_targets = len(dP)
    t32 = gltf_times(anim.times, frame_start, anim.loop)
    index_type = _GL_UNSIGNED_SHORT if n <= 65535 else _GL_UNSIGNED_INT

    blob = bytearray()
    views, accessors = [], []

    def add_view(data: np.ndarray, target=None, stride=None) -> int:
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=data.nbytes,
                                   target=target, byteStride=stride))
        blob.extend(data.tobytes())
        blob.extend(b"\0" * (-len(blob) % 4))
        return len(views) - 1

    def add_accessor(view, data, ctype, kind, offset=0, bounds=False) -> int:
        acc = gl.Accessor(bufferView=view, byteOffset=offset, componentType=ctype,
                          count=len(data), type=kind)
        if bounds:
            acc.min = np.atleast_1d(data.min(axis=0)).astype(float).tolist()
            acc.max = np.atleast_1d(data.max(axis=0)).astype(float).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    indices = anim.faces.ravel().astype(np.uint16 if index_type == _GL_UNSIGNED_SHORT
                                         else np.uint32)
    attributes = gl.Attributes(
        POSITION=add_accessor(add_view(base_p, _GL_ARRAY_BUFFER), base_p, _GL_FLOAT, "VEC3",
                              bounds=True),
        NORMAL=add_accessor(add_view(base_n, _GL_ARRAY_BUFFER), base_n, _GL_FLOAT, "VEC3"),
    )
    if anim.uvs is not None:
        st = np.column_stack([anim.uvs[:, 0], 1.0 - anim.uvs[:, 1]]).astype(np.float32)
        attributes.TEXCOORD_0 = add_accessor(add_view(st, _GL_ARRAY_BUFFER), st, _GL_FLOAT,
                                             "VEC2")
    index_accessor = add_accessor(add_view(indices, _GL_ELEMENT_ARRAY_BUFFER), indices,
                                  index_type, "SCALAR", bounds=True)
    # All position deltas in one strided view, all normal deltas in another.
    view_dp = add_view(dP, _GL_ARRAY_BUFFER, stride=12)
    view_dn = add_view(dN, _GL_ARRAY_BUFFER, stride=12)
    morph = [
        gl.Attributes(
            POSITION=add_accessor(view_dp, dP[k], _GL_FLOAT, "VEC3", offset=k * n * 12,
                                  bounds=True),
            NORMAL=add_accessor(view_dn, dN[k], _GL_FLOAT, "VEC3", offset=k * n * 12),
        )
        for k in range(n_targets)
    ]
    time_accessor = add_accessor(add_view(t32), t32, _GL_FLOAT, "SCALAR", bounds=True)
    flat = weights.astype(np.float32).ravel()
    weight_accessor = add_accessor(add_view(flat), flat, _GL_FLOAT, "SCALAR")
    extras = {"format_version": FORMAT_VERSION, "times": anim.times.tolist(),
              "targets": targets, "loop": bool(anim.loop)}
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
        buffers=[gl.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(bytes(blob))
    gltf.save_binary(str(path))


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


def read_glb(path: Path) -> SurfaceAnimation:
    gl = format_library("pygltflib", "pygltflib", ".glb")

    try:
        gltf = gl.GLTF2().load(str(path))
    except Exception as e:  # pygltflib raises assorted errors on malformed files
        raise WigglyInputError(f"cannot read {path}: not a valid glTF binary ({e})") from e
    blob = gltf.binary_blob()
    if not gltf.meshes or not gltf.meshes[0].primitives:
        raise WigglyInputError(f"cannot read {path}: the glTF file has no mesh")
    mesh_index = 0
    if len(gltf.meshes) > 1:
        warnings.warn(f"{path}: only its first mesh ({gltf.meshes[0].name or 'unnamed'}) is "
                      f"read; left out: {counted(len(gltf.meshes) - 1, 'other mesh')}",
                      stacklevel=3)
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
