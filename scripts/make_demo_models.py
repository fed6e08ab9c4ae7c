"""Build the bundled demo surfaces in ``src/wiggly/data/`` with manifold3d.

Each model is a union of smooth primitives (ellipsoids and tapered capsules)
given as signed distance functions and combined with a smooth minimum (a
"soft" union that rounds the joints), meshed by manifold3d's
``Manifold.level_set`` (marching tetrahedra on a body-centred cubic grid with
grid points snapped to the surface). manifold3d (Apache-2.0) guarantees a
closed, manifold result; the snapping keeps triangles well shaped. (Exact
booleans of tessellated primitives were tried first: they leave near-zero
edges and slivers along the seams that self-intersect once rounded to file
precision and make fTetWild several times slower.) The bar is a subdivided box.

The script checks every model with :func:`wiggly.mesh.check_surface` and
tetrahedralizes it. Units are metres, y is up. Run from the repository root::

    pip install manifold3d   # needed only for this script
    PYTHONPATH=src python scripts/make_demo_models.py
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from manifold3d import Manifold

DATA = Path(__file__).resolve().parents[1] / "src" / "wiggly" / "data"

Distance = Callable[[float, float, float], float]  # negative inside


def capsule(a, b, ra: float, rb: float) -> Distance:
    """Tapered capsule from ``a`` (radius ``ra``) to ``b`` (radius ``rb``)."""
    ax, ay, az = a
    dx, dy, dz = b[0] - ax, b[1] - ay, b[2] - az
    length2 = dx * dx + dy * dy + dz * dz

    def distance(x: float, y: float, z: float) -> float:
        px, py, pz = x - ax, y - ay, z - az
        t = min(1.0, max(0.0, (px * dx + py * dy + pz * dz) / length2))
        qx, qy, qz = px - t * dx, py - t * dy, pz - t * dz
        return math.sqrt(qx * qx + qy * qy + qz * qz) - (ra + (rb - ra) * t)

    return distance


def ellipsoid(center, radii, axis=None) -> Distance:
    """Ellipsoid with semi-axes ``radii``; its local z axis along ``axis`` if given."""
    R = np.eye(3) if axis is None else _frame(np.asarray(axis, dtype=float))
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.T.tolist()
    cx, cy, cz = center
    rx, ry, rz = radii
    scale = min(radii)

    def distance(x: float, y: float, z: float) -> float:
        px, py, pz = x - cx, y - cy, z - cz
        u = (r00 * px + r01 * py + r02 * pz) / rx
        v = (r10 * px + r11 * py + r12 * pz) / ry
        w = (r20 * px + r21 * py + r22 * pz) / rz
        return (math.sqrt(u * u + v * v + w * w) - 1.0) * scale

    return distance


def _frame(direction: np.ndarray) -> np.ndarray:
    """Rotation whose columns are x, y, z with z along ``direction`` and x horizontal."""
    z = direction / np.linalg.norm(direction)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
    return np.column_stack([x, np.cross(z, x), z])


def soft_union(parts: list[Distance], k: float) -> Distance:
    """Smooth minimum of the distances (polynomial smin, blending width ``k``)."""

    def distance(x: float, y: float, z: float) -> float:
        d = parts[0](x, y, z)
        for part in parts[1:]:
            e = part(x, y, z)
            h = max(k - abs(d - e), 0.0) / k
            d = min(d, e) - 0.25 * k * h * h
        return d

    return distance


def mesh(distance: Distance, bounds, edge_length: float) -> Manifold:
    """Mesh the zero level set of ``distance`` (negative inside) in ``bounds``."""
    return Manifold.level_set(lambda x, y, z: -distance(x, y, z), bounds, edge_length, 0.0, 1e-4)


def critter() -> Manifold:
    """A soft four-legged animal, about 1 m long (x), standing on y = 0, looking along +x."""
    parts = [
        ellipsoid((0.0, 0.46, 0.0), (0.30, 0.15, 0.14)),  # body
        capsule((0.22, 0.50, 0.0), (0.34, 0.66, 0.0), 0.075, 0.06),  # neck
        ellipsoid((0.39, 0.69, 0.0), (0.10, 0.075, 0.075)),  # head
        capsule((0.42, 0.67, 0.0), (0.50, 0.645, 0.0), 0.05, 0.04),  # snout
        ellipsoid((0.36, 0.77, 0.045), (0.02, 0.045, 0.03), (0.0, 1.0, 0.3)),  # ears
        ellipsoid((0.36, 0.77, -0.045), (0.02, 0.045, 0.03), (0.0, 1.0, -0.3)),
        capsule((-0.25, 0.50, 0.0), (-0.38, 0.58, 0.0), 0.045, 0.032),  # tail
        capsule((-0.38, 0.58, 0.0), (-0.46, 0.70, 0.0), 0.032, 0.022),
    ]
    for x in (0.18, -0.18):  # legs
        for z in (0.075, -0.075):
            parts.append(capsule((x, 0.42, z), (x + 0.02, 0.05, z * 1.15), 0.06, 0.048))
    shape = mesh(soft_union(parts, 0.05), [-0.6, -0.05, -0.3, 0.65, 0.9, 0.3], 0.032)
    return shape.translate([0.0, -shape.bounding_box()[1], 0.0])


def plant() -> Manifold:
    """A stem with two branches carrying leaves and a leaf on top; flat base at y = 0."""
    leaves = [((0.20, 0.52, 0.0), (0.32, 0.60, 0.0)), ((-0.17, 0.70, 0.05), (-0.28, 0.78, 0.09))]
    parts = [
        capsule((0.0, -0.05, 0.0), (0.0, 0.80, 0.0), 0.04, 0.022),  # stem, cut at y = 0 below
        capsule((0.0, 0.33, 0.0), (0.20, 0.52, 0.0), 0.024, 0.018),  # branches
        capsule((0.0, 0.53, 0.0), (-0.17, 0.70, 0.05), 0.022, 0.017),
        ellipsoid((0.0, 0.86, 0.0), (0.06, 0.02, 0.09), (0.25, 1.0, 0.0)),  # top leaf
    ]
    for start, end in leaves:
        direction = np.subtract(end, start)
        center = np.add(start, 0.5 * direction)
        parts.append(ellipsoid(center, (0.06, 0.02, 0.1), direction))
    stem = soft_union(parts, 0.03)

    def distance(x: float, y: float, z: float) -> float:
        return max(stem(x, y, z), -y)  # cut off below the ground

    return mesh(distance, [-0.4, -0.02, -0.2, 0.45, 1.0, 0.25], 0.02)


def bar() -> Manifold:
    """A 1 x 0.1 x 0.1 m bar along x from x = 0 to x = 1, centred on the x axis."""
    box = Manifold.cube([1.0, 0.1, 0.1], True).translate([0.5, 0.0, 0.0])
    return box.refine_to_length(0.025)


def write_obj(shape: Manifold, path: Path, comment: str) -> tuple[np.ndarray, np.ndarray]:
    """Write the shape's triangles as an OBJ with 5 decimals (10 micrometres)."""
    mesh = shape.to_mesh64()
    V = np.asarray(mesh.vert_properties)[:, :3]
    F = np.asarray(mesh.tri_verts, dtype=np.int64)
    lines = [f"# {comment}", "# generated by scripts/make_demo_models.py (manifold3d)"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in V]
    lines += [f"f {a} {b} {c}" for a, b, c in F + 1]
    path.write_text("\n".join(lines) + "\n")
    return V, F


def main() -> None:
    from wiggly.mesh import check_surface, load_mesh, tetrahedralize

    DATA.mkdir(parents=True, exist_ok=True)
    models = {
        "critter": (critter, "soft four-legged critter, ~1 m long along x, y up, feet on y = 0"),
        "plant": (plant, "plant: stem, two branches, three leaves, y up, flat base on y = 0"),
        "bar": (bar, "bar 1 x 0.1 x 0.1 m along x from x = 0 to 1, centred on the x axis"),
    }
    for name, (build, comment) in models.items():
        path = DATA / f"{name}.obj"
        shape = build()
        V, F = write_obj(shape, path, comment)
        surface = check_surface(load_mesh(path), str(path))
        start = time.perf_counter()
        tets = tetrahedralize(surface)
        seconds = time.perf_counter() - start
        size = V.max(axis=0) - V.min(axis=0)
        print(
            f"{path.name}: {len(V)} vertices, {len(F)} faces, {path.stat().st_size / 1e3:.0f} kB, "
            f"size {size.round(3).tolist()} m, volume {shape.volume():.4g} m^3; "
            f"{tets.n_tets} tets ({tets.volumes().sum():.4g} m^3) in {seconds:.1f} s"
        )


if __name__ == "__main__":
    main()
