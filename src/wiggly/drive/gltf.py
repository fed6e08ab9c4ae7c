"""glTF 2.0 drivers: morph-target and skinned animations evaluated per frame, as the glTF 2.0
specification defines them (sections 3.7 "Concepts: Geometry" and 3.11 "Animations").

* **Scene.**  The meshes of the default scene (else of every root node), depth first in
  node order, each primitive of triangles in order: the vertices trimesh reads (and the
  user's surface has) when the same file is the mesh.  ``object`` keeps the meshes of the
  nodes (or meshes) of that name.
* **Node transforms.**  A node's local transform is its ``matrix`` (column-major), or
  T * R * S of its ``translation``, ``rotation`` (unit quaternion x, y, z, w) and ``scale``;
  its global transform is its parents' times its own.  glTF is y up and in metres, as wiggly.
* **Animation.**  A channel's sampler maps key times (its ``input``) to values (its
  ``output``): STEP holds the value of the last key, LINEAR interpolates linearly (rotations
  by spherical linear interpolation along the shorter arc), CUBICSPLINE is the cubic Hermite
  spline of (in-tangent, value, out-tangent) triples with tangents scaled by the key interval
  (rotations normalized after).  Before the first key the first value holds, after the last
  the last.  The driver's frames are the key times of every channel of the animation (of
  every animation, when several play together), with frames filled in at about
  ``SAMPLE_RATE`` per second where keys lie further apart, so that the motion between sparse
  keys is the interpolation's.
* **Morph targets** (3.7.2.2): POSITION + sum_i w_i delta_i, with w the node's animated
  ``weights`` (else the node's, else the mesh's default weights, else 0).
* **Skins** (3.7.3): joint matrix j = global(joint j) * inverseBindMatrix j (identity when
  none are given); a vertex moves to sum_k w_k joint matrix(j_k) * p over JOINTS_n /
  WEIGHTS_n (weights normalized to sum 1; a vertex with no weight stays in place).
  Morphing comes first.  The skinned mesh node's own transform is ignored, as the
  specification requires.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from wiggly.drive.driver import Driver, filled_times, polygon_edges
from wiggly.drive.gltf_file import GltfFile
from wiggly.errors import warn

__all__ = ["RestPose", "read_gltf", "rest_pose", "sample", "slerp", "trs_matrix"]

_TRIANGLES = 4


# ----------------------------------------------------------------------------------------------
# transforms and animation sampling


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) stored x, y, z, w."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def trs_matrix(t: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """T * R * S as (..., 4, 4) from translations (..., 3), quaternions (..., 4) and
    scales (..., 3)."""
    M = np.zeros((*np.broadcast_shapes(t.shape[:-1], r.shape[:-1], s.shape[:-1]), 4, 4))
    M[..., :3, :3] = _quat_matrix(r) * s[..., None, :]
    M[..., :3, 3] = t
    M[..., 3, 3] = 1.0
    return M


def slerp(a: np.ndarray, b: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (..., 4) along the shorter arc."""
    d = np.sum(a * b, axis=-1, keepdims=True)
    b = np.where(d < 0, -b, b)
    d = np.abs(d)
    s = s[..., None]
    theta = np.arccos(np.clip(d, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin < 1e-6  # nearly equal: linear interpolation, normalized
    safe = np.where(near, 1.0, sin)
    wa = np.where(near, 1 - s, np.sin((1 - s) * theta) / safe)
    wb = np.where(near, s, np.sin(s * theta) / safe)
    q = wa * a + wb * b
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def sample(keys: np.ndarray, values: np.ndarray, interpolation: str, t: np.ndarray,
           rotation: bool = False) -> np.ndarray:
    """Values (F, w) of an animation sampler at times ``t`` (F,) (module docstring).

    ``keys`` (K,) are the sampler's input times; ``values`` its output, (K, w) or, for
    CUBICSPLINE, (K, 3, w) as (in-tangent, value, out-tangent)."""
    K = len(keys)
    cubic = interpolation == "CUBICSPLINE"
    v = values[:, 1] if cubic else values
    if K == 1:
        out = np.repeat(v[:1], len(t), axis=0)
    else:
        k = np.clip(np.searchsorted(keys, t, side="right") - 1, 0, K - 2)
        t0, t1 = keys[k], keys[k + 1]
        h = t1 - t0
        s = np.clip((t - t0) / np.where(h > 0, h, 1.0), 0.0, 1.0)
        if interpolation == "STEP":
            out = np.where((s >= 1.0)[:, None], v[k + 1], v[k])
        elif cubic:
            s2, s3 = s * s, s * s * s
            hv = h[:, None]
            out = ((2 * s3 - 3 * s2 + 1)[:, None] * v[k]
                   + (s3 - 2 * s2 + s)[:, None] * hv * values[k, 2]
                   + (-2 * s3 + 3 * s2)[:, None] * v[k + 1]
                   + (s3 - s2)[:, None] * hv * values[k + 1, 0])
        elif rotation:
            out = slerp(v[k], v[k + 1], s)
        else:
            out = (1 - s)[:, None] * v[k] + s[:, None] * v[k + 1]
    if rotation:
        out = out / np.linalg.norm(out, axis=-1, keepdims=True)
    return out


@dataclass
class _Channel:
    node: int
    path: str
    keys: np.ndarray
    values: np.ndarray
    interpolation: str


AnimationChoice = str | int | Sequence[str | int] | None


def _channels(f: GltfFile, animation: AnimationChoice) -> list[_Channel]:
    """The channels of ``animation`` (a name or index, default the first), or of several
    played together (a list: their channels merged; two that animate the same property of
    the same node are refused)."""
    animations = f.list("animations")
    if not animations:
        return []
    names = [a.get("name") or f"#{i}" for i, a in enumerate(animations)]
    listing = ", ".join(f"#{i} {n!r}" for i, n in enumerate(names))
    if isinstance(animation, list | tuple):
        merged: list[_Channel] = []
        owner: dict[tuple[int, str], str] = {}
        for one in animation:
            index = _animation_index(f, one, names, listing)
            for c in _animation_channels(f, animations[index], names[index]):
                other = owner.setdefault((c.node, c.path), names[index])
                if other != names[index]:
                    node = f.list("nodes")[c.node].get("name") if 0 <= c.node < len(
                        f.list("nodes")) else None
                    what = f"node {c.node}" + (f" ({node!r})" if node else "")
                    raise f.fail(f"animations {other!r} and {names[index]!r} both animate the "
                                 f"{c.path} of {what}; play one of them")
                merged.append(c)
        return merged
    if animation is None:
        index = 0
        if len(animations) > 1:
            warn(
                f"{f.path}: it has {len(animations)} animations, and the driver plays only the "
                f"first; the others are left out: {listing}. Name one with drive.animation, "
                "or several to play together (drive.animation = [\"walk\", \"breathe\"]; "
                "a rig's action and a shape-key action)")
    else:
        index = _animation_index(f, animation, names, listing)
    return _animation_channels(f, animations[index], names[index])


def _animation_index(f: GltfFile, animation: str | int, names: list[str], listing: str) -> int:
    """The index of an animation given by index or name; refused, listing them, if none."""
    if isinstance(animation, int) and not isinstance(animation, bool):
        if not 0 <= animation < len(names):
            raise f.fail(f"it has no animation #{animation}; its animations are: {listing}")
        return animation
    if animation in names:
        return names.index(animation)
    raise f.fail(f"it has no animation named {animation!r}; its animations are: {listing}")


def _animation_channels(f: GltfFile, anim: dict, name: str) -> list[_Channel]:
    """The geometry channels (node TRS and morph weights) of one animation, checked."""
    samplers = anim.get("samplers") or []
    out = []
    for c in anim.get("channels") or []:
        target = c.get("target") or {}
        path = target.get("path")
        if target.get("node") is None or path not in ("translation", "rotation", "scale",
                                                      "weights"):
            continue  # e.g. KHR_animation_pointer targets: not geometry
        if not 0 <= c.get("sampler", -1) < len(samplers):
            raise f.fail(f"animation {name!r}: a channel refers to sampler {c.get('sampler')}, "
                         "which does not exist")
        smp = samplers[c["sampler"]]
        keys = f.accessor(smp.get("input")).ravel().astype(np.float64)
        if len(keys) == 0 or not np.all(np.isfinite(keys)) or np.any(np.diff(keys) < 0):
            raise f.fail(f"animation {name!r}: sampler {c['sampler']} has key times that are "
                         "not increasing")
        interp = smp.get("interpolation", "LINEAR")
        if interp not in ("LINEAR", "STEP", "CUBICSPLINE"):
            raise f.fail(f"animation {name!r}: unknown interpolation {interp!r}")
        values = f.accessor(smp.get("output")).astype(np.float64)
        per_key = 3 if interp == "CUBICSPLINE" else 1
        width = {"translation": 3, "rotation": 4, "scale": 3}.get(path)
        if width is None:  # weights: one per morph target and key
            width = values.size // (len(keys) * per_key)
        if width == 0 or values.size != len(keys) * per_key * width:
            raise f.fail(f"animation {name!r}: sampler {c['sampler']} has {values.size} output "
                         f"values for {len(keys)} keys of {path}")
        values = values.reshape(len(keys), per_key, width)
        out.append(_Channel(target["node"], path, keys,
                            values if per_key == 3 else values[:, 0], interp))
    return out


#: Key times further apart than 1.5 / SAMPLE_RATE s get frames in between, about this many a
#: second: a driver keyed sparsely (LINEAR keys every half second) moves as its interpolation
#: says between keys, which the spline through the keys alone would not follow (a swing keyed
#: every 0.5 s strayed 0.3 m from it).  Drivers baked per frame (24 fps and up) keep their frames.
SAMPLE_RATE = 30.0


def _frame_times(channels: list[_Channel]) -> np.ndarray:
    """The union of the channels' key times (merged within 1e-6 s), with evenly spaced frames
    filled into gaps longer than ``1.5 / SAMPLE_RATE``; [0] with no channel."""
    if not channels:
        return np.zeros(1)
    t = np.unique(np.concatenate([c.keys for c in channels]))
    return filled_times(t[np.r_[True, np.diff(t) > 1e-6]], SAMPLE_RATE)


def _local_transforms(f: GltfFile, channels: list[_Channel], times: np.ndarray
                      ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Local transforms (N, F, 4, 4) of every node at every frame, and the animated morph
    weights (F, k) by node."""
    nodes = f.list("nodes")
    N, F = len(nodes), len(times)
    by_node: dict[int, dict[str, _Channel]] = {}
    for c in channels:
        if not 0 <= c.node < N:
            raise f.fail(f"an animation channel targets node {c.node}, which does not exist")
        by_node.setdefault(c.node, {})[c.path] = c
    local = np.empty((N, F, 4, 4))
    weights = {}
    for i, node in enumerate(nodes):
        anim = by_node.get(i, {})
        if node.get("matrix") is not None:
            if any(p in anim for p in ("translation", "rotation", "scale")):
                raise f.fail(f"node {i} has a matrix and is animated; glTF forbids that")
            local[i] = np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
        else:
            trs = {"translation": node.get("translation", [0.0, 0.0, 0.0]),
                   "rotation": node.get("rotation", [0.0, 0.0, 0.0, 1.0]),
                   "scale": node.get("scale", [1.0, 1.0, 1.0])}
            parts = {}
            for path, default in trs.items():
                c = anim.get(path)
                parts[path] = (np.broadcast_to(np.asarray(default, np.float64), (F, len(default)))
                               if c is None else sample(c.keys, c.values, c.interpolation, times,
                                                        rotation=path == "rotation"))
            if not np.all(np.linalg.norm(parts["rotation"], axis=-1) > 0):
                raise f.fail(f"node {i} has a zero rotation quaternion")
            local[i] = trs_matrix(parts["translation"], parts["rotation"], parts["scale"])
        if "weights" in anim:
            c = anim["weights"]
            weights[i] = sample(c.keys, c.values, c.interpolation, times)
    return local, weights


def _scene_nodes(f: GltfFile) -> tuple[list[int], dict[int, int | None]]:
    """The nodes of the default scene (else of every root) depth first, with their parents."""
    nodes = f.list("nodes")
    scenes = f.list("scenes")
    if scenes:
        scene = f.item("scenes", f.doc.get("scene", 0), "the default scene")
        roots = list(scene.get("nodes") or [])
    else:
        children = {c for n in nodes for c in n.get("children") or []}
        roots = [i for i in range(len(nodes)) if i not in children]
    order: list[int] = []
    parent: dict[int, int | None] = {}
    stack = [(r, None) for r in reversed(roots)]
    while stack:
        i, p = stack.pop()
        f.item("nodes", i, "the node hierarchy")
        if i in parent:
            raise f.fail(f"node {i} appears twice in the node hierarchy")
        parent[i] = p
        order.append(i)
        stack += [(c, i) for c in reversed(nodes[i].get("children") or [])]
    return order, parent


def _morphed(f: GltfFile, prim: dict, base: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Positions (F, n, 3) of a primitive with its morph targets weighted by (F, k)."""
    deltas = [np.zeros_like(base) if t.get("POSITION") is None else f.accessor(t["POSITION"])
              for t in prim["targets"]]
    D = np.stack(deltas)  # (k, n, 3)
    if weights.shape[1] != len(D) or D.shape[1] != len(base):
        raise f.fail(f"a mesh has {len(D)} morph targets of {D.shape[1]} vertices, {len(base)} "
                     f"vertices and {weights.shape[1]} morph weights")
    return base + np.einsum("fk,knc->fnc", weights, D)


def _joint_matrices(f: GltfFile, skin_index, world: dict[int, np.ndarray]) -> np.ndarray:
    """Joint matrices (F, J, 4, 4): global joint transform times inverse bind matrix."""
    skin = f.item("skins", skin_index, "a mesh node")
    joints = list(skin.get("joints") or [])
    if not joints:
        raise f.fail(f"skin {skin_index} has no joints")
    if not all(j in world for j in joints):
        raise f.fail(f"skin {skin_index} has joints outside the scene's node hierarchy")
    if skin.get("inverseBindMatrices") is None:
        ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
    else:
        ibm = f.accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
        if len(ibm) != len(joints):
            raise f.fail(f"skin {skin_index} has {len(joints)} joints but {len(ibm)} inverse "
                         "bind matrices")
    return np.einsum("jfab,jbc->fjac", np.stack([world[j] for j in joints]), ibm)


def _skinned(f: GltfFile, prim: dict, positions: np.ndarray, joint_mats: np.ndarray,
             linear: list | None = None) -> np.ndarray:
    """Linear blend skinning (3.7.3) of (F, n, 3) positions by the primitive's JOINTS_s /
    WEIGHTS_s and the joint matrices (F, J, 4, 4); ``linear`` gets each frame's blended
    linear parts (n, 3, 3)."""
    attrs = prim["attributes"]
    J, W = [], []
    for s in range(8):
        if attrs.get(f"JOINTS_{s}") is None or attrs.get(f"WEIGHTS_{s}") is None:
            break
        J.append(f.accessor(attrs[f"JOINTS_{s}"]).astype(np.int64))
        W.append(f.accessor(attrs[f"WEIGHTS_{s}"]).astype(np.float64))
    if not J:
        raise f.fail("a skinned mesh primitive has no JOINTS_0 / WEIGHTS_0")
    Jn, Wn = np.concatenate(J, axis=1), np.concatenate(W, axis=1)
    n_joints, n = joint_mats.shape[1], positions.shape[1]
    if Jn.shape[0] != n or Wn.shape != Jn.shape:
        raise f.fail(f"a skinned primitive has {n} vertices but {Jn.shape[0]} joint and "
                     f"{Wn.shape[0]} weight entries")
    used = Wn > 0
    if used.any() and (Jn[used].min() < 0 or Jn[used].max() >= n_joints):
        raise f.fail(f"skin joint indices reach {Jn[used].max()} but the skin has {n_joints} "
                     "joints")
    Jn = np.where(used, Jn, 0)
    total = Wn.sum(axis=1)
    free = total <= 0
    Wn = Wn / np.where(free, 1.0, total)[:, None]
    out = np.empty(positions.shape)
    for k in range(len(positions)):
        B = np.einsum("ni,niab->nab", Wn, joint_mats[k][:, :3, :][Jn])  # (n, 3, 4) blended
        p = positions[k]
        out[k] = np.einsum("nab,nb->na", B[:, :, :3], p) + B[:, :, 3]
        out[k, free] = p[free]
        if linear is not None and k == 0:
            L = B[:, :, :3].copy()
            L[free] = np.eye(3)
            linear.append(L)
    return out


def read_gltf(path: Path, *, animation: AnimationChoice = None,
              object: str | None = None) -> Driver:
    """The driver of a ``.glb`` / ``.gltf`` file: every frame of ``animation`` (a name or
    index, or several played together; default the first) evaluated on the meshes of the
    scene (module docstring)."""
    f = GltfFile(Path(path))
    channels = _channels(f, animation)
    times = _frame_times(channels)
    parts = _pose(f, channels, times, object)
    kinds = {k for part in parts for k in part.kinds}
    kind = "glTF " + " and ".join(sorted(kinds)) if kinds else "glTF node animation"
    nodes = f.list("nodes")
    names = dict.fromkeys(nodes[part.node].get("name") or f"node {part.node}" for part in parts)
    return Driver(times, np.concatenate([part.positions for part in parts], axis=1),
                  np.concatenate([part.faces for part in parts]),
                  np.concatenate([polygon_edges(part.faces) for part in parts]), str(path),
                  kind, tuple(names))


@dataclass
class RestPose:
    """The scene's meshes as a viewer shows them with no animation (module docstring), in
    the vertex order of :func:`read_gltf`: ``positions`` (n, 3), ``faces`` (k, 3), the file's
    ``normals`` turned as the pose turns them and ``uvs`` (v up, as trimesh reads them; None
    unless every primitive has them), ``groups`` (each mesh node's vertices, and each
    primitive's of a mesh with several, see :func:`_node_groups`) and ``bind`` (each
    skinned primitive's vertices as stored, their bind pose, with the slice of
    ``positions`` they become)."""

    positions: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    uvs: np.ndarray | None
    groups: dict[str, np.ndarray]
    bind: list[tuple[slice, np.ndarray]]


def rest_pose(path: Path) -> RestPose:
    """The meshes of a ``.glb`` / ``.gltf`` file with no animation applied: node transforms
    at their static values, default morph weights, sparse accessors applied, and skins
    blended by their joints' static transforms (the skinned node's own transform ignored,
    as the specification requires)."""
    f = GltfFile(Path(path))
    parts = _pose(f, [], np.zeros(1), None)
    normals, uvs = [], []
    for part in parts:
        attrs = part.primitive["attributes"]
        if attrs.get("NORMAL") is not None:  # row vectors: the inverse transpose
            n = np.einsum("ni,nij->nj", f.accessor(attrs["NORMAL"]).astype(np.float64),
                          np.linalg.inv(part.linear))
            normals.append(n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-300))
        if attrs.get("TEXCOORD_0") is not None:
            uv = f.accessor(attrs["TEXCOORD_0"]).astype(np.float64)[:, :2].copy()
            uv[:, 1] = 1.0 - uv[:, 1]
            uvs.append(uv)
    return RestPose(
        np.concatenate([part.positions[0] for part in parts]),
        np.concatenate([part.faces for part in parts]),
        np.concatenate(normals) if len(normals) == len(parts) else None,
        np.concatenate(uvs) if len(uvs) == len(parts) else None,
        _node_groups(f, parts),
        [(part.vertices, part.bind) for part in parts if part.bind is not None])


def _node_groups(f: GltfFile, parts: list[_Part]) -> dict[str, np.ndarray]:
    """Vertex groups of the mesh nodes, the same on every read: each node's vertices named
    as the node (else its mesh, else ``node <i>``; a repeated name gets ``.1``, ``.2``),
    and for a mesh of several triangle primitives each one's as ``<node>/primitive <k>``,
    ``k`` its index in the mesh's ``primitives``."""
    names: dict[int, str] = {}
    for part in parts:
        if part.node not in names:
            node = f.list("nodes")[part.node]
            base = (node.get("name") or f.item("meshes", node["mesh"]).get("name")
                    or f"node {part.node}")
            name, k = base, 1
            while name in names.values():
                name, k = f"{base}.{k}", k + 1
            names[part.node] = name
    groups: dict[str, list[np.ndarray]] = {}
    for part in parts:
        groups.setdefault(names[part.node], []).append(
            np.arange(part.vertices.start, part.vertices.stop))
    for part in parts:
        if len(groups[names[part.node]]) > 1:
            prims = f.item("meshes", f.list("nodes")[part.node]["mesh"])["primitives"]
            k = next(k for k, p in enumerate(prims) if p is part.primitive)
            groups[f"{names[part.node]}/primitive {k}"] = [
                np.arange(part.vertices.start, part.vertices.stop)]
    return {k: np.concatenate(v) for k, v in groups.items()}


@dataclass
class _Part:
    """One triangle primitive of a mesh node, posed: ``positions`` (F, n, 3), ``faces``
    offset to the concatenation (reversed where a node transform mirrors), ``vertices`` its
    slice of the concatenation, the deformations met (``kinds``), and of the first frame the
    per-vertex linear parts applied (``linear``, (n, 3, 3)) and, when skinned, the positions
    before skinning (``bind``)."""

    node: int
    primitive: dict
    positions: np.ndarray
    faces: np.ndarray
    vertices: slice
    kinds: set
    linear: np.ndarray
    bind: np.ndarray | None


def _pose(f: GltfFile, channels: list[_Channel], times: np.ndarray, object: str | None
          ) -> list[_Part]:
    """Every triangle primitive of the scene's mesh nodes, posed at ``times``."""
    nodes = f.list("nodes")
    order, parent = _scene_nodes(f)
    local, weights = _local_transforms(f, channels, times)
    world: dict[int, np.ndarray] = {}
    for i in order:  # parents come first
        world[i] = local[i] if parent[i] is None else world[parent[i]] @ local[i]
    with_mesh = [i for i in order if nodes[i].get("mesh") is not None]
    if object is not None:
        def names(i: int) -> tuple:
            return nodes[i].get("name"), f.item("meshes", nodes[i]["mesh"]).get("name")

        kept = [i for i in with_mesh if object in names(i)]
        if not kept:
            have = sorted({x for i in with_mesh for x in names(i) if x})
            raise f.fail(f"it has no mesh node or mesh named {object!r}; its meshes are: "
                         + (", ".join(repr(x) for x in have) or "unnamed"))
        with_mesh = kept
    parts: list[_Part] = []
    offset = 0
    for i in with_mesh:
        node = nodes[i]
        mesh = f.item("meshes", node["mesh"], f"node {i}")
        for prim in mesh.get("primitives") or []:
            attrs = prim.get("attributes") or {}
            if prim.get("mode", _TRIANGLES) != _TRIANGLES or attrs.get("POSITION") is None:
                continue
            base = f.accessor(attrs["POSITION"])
            n = len(base)
            tri = (f.accessor(prim["indices"]).astype(np.int64).reshape(-1, 3)
                   if prim.get("indices") is not None else np.arange(n - n % 3).reshape(-1, 3))
            if tri.size and (tri.min() < 0 or tri.max() >= n):
                raise f.fail(f"mesh {node['mesh']} has indices beyond its {n} vertices")
            P = np.broadcast_to(base, (len(times), n, 3))
            kinds, bind = set(), None
            k = len(prim.get("targets") or [])
            if k:
                kinds.add("morph targets")
                w = weights.get(i)
                if w is None:
                    default = node.get("weights") or mesh.get("weights") or [0.0] * k
                    w = np.broadcast_to(np.asarray(default, np.float64), (len(times), len(default)))
                P = _morphed(f, prim, base, w)
            if node.get("skin") is not None:
                kinds.add("skin")
                blended: list[np.ndarray] = []
                bind = np.array(P[0])
                P = _skinned(f, prim, P, _joint_matrices(f, node["skin"], world), blended)
                linear = blended[0]
            else:
                M = world[i]  # (F, 4, 4)
                P = np.einsum("fab,fnb->fna", M[:, :3, :3], P) + M[:, None, :3, 3]
                linear = np.broadcast_to(M[0, :3, :3], (n, 3, 3))
                if np.linalg.det(M[0, :3, :3]) < 0:  # a mirror: keep the faces outward
                    tri = tri[:, ::-1]
            parts.append(_Part(i, prim, P, tri + offset, slice(offset, offset + n), kinds,
                               linear, bind))
            offset += n
    if not parts or offset == 0:
        raise f.fail("its scene has no mesh of triangles")
    return parts
