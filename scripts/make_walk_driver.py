"""Build ``examples/critter_walk.glb``: the bundled critter skinned to six bones and walking.

The driver of ``examples/walk_secondary.toml``: a glTF 2.0 binary with the critter's own
surface (``builtin:critter``: the same vertices in the same order, and its triangles), a
skin and one animation, ``walk``: two cycles of an in-place trot, 1 s each, keyed at 30 fps
(61 keys, LINEAR; the pose and velocity at 2 s equal those at 0 s, so the cycle can loop).

Bones (glTF nodes; bind pose: no rotation, so every inverse bind matrix is a translation)

* ``body`` at the trunk's centre (the skeleton's root): bobs down twice a cycle when the
  legs are spread, sways (roll), yaws and pitches a little;
* ``head`` at the base of the neck, child of ``body``: nods twice a cycle;
* ``leg_fl``, ``leg_fr``, ``leg_bl``, ``leg_br`` where the legs leave the belly, children
  of ``body``: swing fore and aft by 22 degrees, diagonal pairs together (a trot).

Skin weights vary smoothly over the surface (:func:`skin_weights`): a leg bends from where
it leaves the belly to the foot (and blends with its neighbour where they touch), the neck
from its base to the head, as elastic limbs do.  The tail and the ears are skinned rigidly
to the body and the head: in the driver they follow without lag; ``walk_secondary.toml``
leaves them free.

Run from the repository root (a few seconds)::

    .venv/bin/python scripts/make_walk_driver.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib as gl
from scipy.spatial.transform import Rotation

from wiggly.mesh import load_mesh, resolve_builtin

OUT = Path(__file__).resolve().parents[1] / "examples" / "critter_walk.glb"
PERIOD = 1.0  # s per cycle
CYCLES = 2
FPS = 30
LEG_SWING = 22.0  # degrees, fore and aft
BOB = 0.04  # m, body down when the legs are spread
ROLL, YAW, PITCH, NOD = 6.0, 8.0, 4.0, 10.0  # degrees
HIP_Y = 0.34  # the legs' joints: where the legs leave the belly (they bend from there down)

#: name -> (parent, joint position in the bind pose (m))
BONES = {
    "body": (None, (0.0, 0.46, 0.0)),
    "head": ("body", (0.22, 0.50, 0.0)),
    "leg_fl": ("body", (0.18, HIP_Y, 0.075)),
    "leg_fr": ("body", (0.18, HIP_Y, -0.075)),
    "leg_bl": ("body", (-0.18, HIP_Y, 0.075)),
    "leg_br": ("body", (-0.18, HIP_Y, -0.075)),
}


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _along(X: np.ndarray, a, b) -> tuple[np.ndarray, np.ndarray]:
    """Position s in [0, 1] of the points X along the segment a -> b, and their distance
    from it."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    axis = b - a
    s = np.clip((X - a) @ axis / (axis @ axis), 0.0, 1.0)
    return s, np.linalg.norm(X - (a + s[:, None] * axis), axis=1)


def bending(s: np.ndarray) -> np.ndarray:
    """Weight of a limb's bone at s along the limb: s (3 - s) / 2, so that the skinned
    displacement, about w(s) s, grows as a cantilever's deflection s^2 (3 - s) / 2: the
    limb bends smoothly from its root (where the displacement's slope is 0) to its end."""
    return s * (3.0 - s) / 2.0


def skin_weights(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """JOINTS_0 (n, 4) and WEIGHTS_0 (n, 4), smooth over the surface (module docstring).

    A limb's bone (a leg, the head) weighs :func:`bending` of the position along the limb
    (under the belly to the foot, neck base to the back of the head) times a falloff with
    the distance from the limb's axis (1 inside the limb, 0 at ``reach``), so the belly
    stays on ``body`` and touching legs blend; ``body`` takes the rest.  The four largest
    weights are kept."""
    names = list(BONES)
    W = np.zeros((len(X), len(names)))
    for k, name in enumerate(names):
        root = np.asarray(BONES[name][1])
        if name.startswith("leg"):  # from under the belly to the foot
            end, reach = np.array([root[0] + 0.02, 0.05, 1.15 * root[2]]), 0.12
        elif name == "head":  # from the base of the neck to the back of the head
            end, reach = np.array([0.33, 0.62, 0.0]), 0.3
        else:
            continue
        s, d = _along(X, root, end)
        W[:, k] = bending(s) * smoothstep((reach - d) / 0.06)
    W /= np.maximum(W.sum(axis=1), 1.0)[:, None]
    W[:, names.index("body")] = 1.0 - W.sum(axis=1)
    top = np.argsort(-W, axis=1)[:, :4]
    weights = np.take_along_axis(W, top, axis=1)
    weights /= weights.sum(axis=1, keepdims=True)
    top[weights == 0.0] = 0  # unused slots name joint 0 (the glTF validator warns otherwise)
    return top.astype(np.uint8), weights.astype(np.float32)


def pose(t: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Local (translation, rotation quaternion x y z w) of every bone at times t (F,)."""
    phase = 2 * np.pi * t / PERIOD
    out = {}
    _, p = BONES["body"]
    bob = -BOB * np.sin(phase) ** 2
    euler = np.column_stack([ROLL * np.sin(phase), YAW * np.sin(phase),
                             PITCH * np.sin(2 * phase)])
    out["body"] = (np.column_stack([np.full_like(t, p[0]), p[1] + bob, np.full_like(t, p[2])]),
                   Rotation.from_euler("xyz", euler, degrees=True).as_quat())
    for name, (parent, p) in BONES.items():
        if parent is None:
            continue
        offset = np.asarray(p) - np.asarray(BONES[parent][1])
        if name == "head":
            angle = NOD * np.sin(2 * phase)
        else:
            diagonal = name in ("leg_fl", "leg_br")
            angle = LEG_SWING * np.sin(phase) * (1 if diagonal else -1)
        rot = Rotation.from_euler("z", angle[:, None], degrees=True).as_quat()
        out[name] = (np.broadcast_to(offset, (len(t), 3)).copy(), rot)
    return out


def build(path: Path = OUT) -> Path:
    surface = load_mesh(resolve_builtin("builtin:critter"))
    X = surface.vertices.astype(np.float32)
    faces = surface.faces.astype(np.uint16 if len(X) < 65536 else np.uint32)
    joints, weights = skin_weights(surface.vertices)
    names = list(BONES)
    times = (np.arange(CYCLES * PERIOD * FPS + 1) / FPS).astype(np.float32)
    poses = pose(times.astype(np.float64))
    ibm = np.zeros((len(names), 4, 4), np.float32)
    for k, name in enumerate(names):
        ibm[k] = np.eye(4)
        ibm[k, :3, 3] = -np.asarray(BONES[name][1])

    blob = bytearray()
    views, accessors = [], []

    def add(data: np.ndarray, ctype: int, kind: str, target: int | None = None,
            bounds: bool = False) -> int:
        while len(blob) % 4:
            blob.append(0)
        raw = np.ascontiguousarray(data).tobytes()
        views.append(gl.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(raw),
                                   target=target))
        blob.extend(raw)
        flat = data.reshape(len(data), -1)
        acc = gl.Accessor(bufferView=len(views) - 1, componentType=ctype, count=len(data),
                          type=kind)
        if bounds:
            acc.min, acc.max = flat.min(axis=0).tolist(), flat.max(axis=0).tolist()
        accessors.append(acc)
        return len(accessors) - 1

    position = add(X, gl.FLOAT, gl.VEC3, gl.ARRAY_BUFFER, bounds=True)
    joint_acc = add(joints, gl.UNSIGNED_BYTE, gl.VEC4, gl.ARRAY_BUFFER)
    weight_acc = add(weights, gl.FLOAT, gl.VEC4, gl.ARRAY_BUFFER)
    index_acc = add(faces.ravel(), gl.UNSIGNED_SHORT if faces.dtype == np.uint16
                    else gl.UNSIGNED_INT, gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER)
    # the column-major layout glTF expects: the transpose of each row-major matrix
    ibm_acc = add(ibm.transpose(0, 2, 1).reshape(-1, 16), gl.FLOAT, gl.MAT4)
    time_acc = add(times, gl.FLOAT, gl.SCALAR, bounds=True)

    nodes = [gl.Node(name="critter", mesh=0, skin=0)]
    for name, (parent, p) in BONES.items():
        local = np.asarray(p) - (np.zeros(3) if parent is None else np.asarray(BONES[parent][1]))
        nodes.append(gl.Node(name=name, translation=local.tolist()))
    for k, (parent, _) in enumerate(BONES.values()):
        if parent is not None:
            node = nodes[1 + names.index(parent)]
            node.children = [*(node.children or []), 1 + k]
    samplers, channels = [], []
    for k, name in enumerate(names):
        translation, rotation = poses[name]
        for prop, data in (("translation", translation), ("rotation", rotation)):
            out = add(data.astype(np.float32), gl.FLOAT, gl.VEC3 if prop == "translation"
                      else gl.VEC4)
            samplers.append(gl.AnimationSampler(input=time_acc, output=out,
                                                interpolation="LINEAR"))
            channels.append(gl.AnimationChannel(
                sampler=len(samplers) - 1, target=gl.AnimationChannelTarget(node=1 + k,
                                                                            path=prop)))
    doc = gl.GLTF2(
        asset=gl.Asset(generator="wiggly scripts/make_walk_driver.py", version="2.0"),
        scene=0, scenes=[gl.Scene(nodes=[0, 1])], nodes=nodes,
        meshes=[gl.Mesh(name="critter", primitives=[gl.Primitive(
            attributes=gl.Attributes(POSITION=position, JOINTS_0=joint_acc,
                                     WEIGHTS_0=weight_acc), indices=index_acc)])],
        skins=[gl.Skin(name="critter_rig", joints=list(range(1, 1 + len(names))), skeleton=1,
                       inverseBindMatrices=ibm_acc)],
        animations=[gl.Animation(name="walk", samplers=samplers, channels=channels)],
        accessors=accessors, bufferViews=views, buffers=[gl.Buffer(byteLength=len(blob))])
    doc.set_binary_blob(bytes(blob))
    path.parent.mkdir(parents=True, exist_ok=True)
    doc.save_binary(str(path))
    return path


if __name__ == "__main__":
    out = build()
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
