"""Build the bundled demo surfaces in ``src/wiggly/data/`` with manifold3d.

Each model is a boolean union of smooth primitives (ellipsoids and tapered
capsules revolved from a profile with evenly spaced rings, so that long parts
have vertices along their length and bend smoothly when embedded in a tet
mesh). manifold3d (Apache-2.0) guarantees closed, manifold output; the script
then checks every model with :func:`wiggly.mesh.check_surface` and
tetrahedralizes it.

Units are metres, y is up. Run from the repository root::

    pip install manifold3d   # needed only for this script
    PYTHONPATH=src python scripts/make_demo_models.py
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from manifold3d import CrossSection, Manifold

DATA = Path(__file__).resolve().parents[1] / "src" / "wiggly" / "data"
SEGMENTS = 24  # around every round part


def ellipsoid(center, radii, segments: int = SEGMENTS) -> Manifold:
    """An ellipsoid with the given semi-axes."""
    return Manifold.sphere(1.0, segments).scale(list(radii)).translate(list(center))


def capsule(p0, p1, r0: float, r1: float, spacing: float, segments: int = SEGMENTS) -> Manifold:
    """A tapered capsule from ``p0`` (radius ``r0``) to ``p1`` (radius ``r1``).

    Revolved from a profile: a quarter circle, a straight flank with a ring
    every ``spacing`` metres, and another quarter circle.
    """
    p0, p1 = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    cap = 6
    a = np.linspace(-np.pi / 2, 0, cap + 1)
    bottom = np.stack([r0 * np.cos(a), r0 * np.sin(a)], axis=1)
    rings = max(2, int(np.ceil(length / spacing)))
    t = np.linspace(0, 1, rings + 1)[1:-1]
    flank = np.stack([r0 + (r1 - r0) * t, length * t], axis=1)
    a = np.linspace(0, np.pi / 2, cap + 1)
    top = np.stack([r1 * np.cos(a), length + r1 * np.sin(a)], axis=1)
    profile = np.concatenate([bottom, flank, top])
    profile[:, 0] = np.maximum(profile[:, 0], 0.0)
    # close the polygon along the axis (x = 0), counter-clockwise
    solid = (
        CrossSection([profile[::-1].tolist()])
        if _clockwise(profile)
        else CrossSection([profile.tolist()])
    )
    shape = Manifold.revolve(solid, segments)  # axis along z
    return shape.transform(_frame(axis / length, p0))


def _clockwise(polygon: np.ndarray) -> bool:
    x, y = polygon[:, 0], polygon[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0


def _frame(direction: np.ndarray, origin: np.ndarray) -> list[list[float]]:
    """3x4 affine map taking the z axis to ``direction`` and the origin to ``origin``."""
    z = direction
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z, origin]).tolist()


def union(parts: list[Manifold]) -> Manifold:
    """Boolean union of all parts, with the slivers along the seams collapsed.

    Unions leave very short edges where surfaces cross; ``simplify`` removes
    edges shorter than 0.2 mm without moving the surface by more than that.
    """
    result = parts[0]
    for part in parts[1:]:
        result = result + part
    return result.simplify(2e-4)


def critter() -> Manifold:
    """A soft four-legged animal, about 1 m long (x), standing on y = 0, looking along +x."""
    s = 0.05  # ring spacing
    parts = [
        ellipsoid((0.0, 0.46, 0.0), (0.30, 0.15, 0.14)),  # body
        capsule((0.22, 0.50, 0.0), (0.34, 0.66, 0.0), 0.075, 0.06, s),  # neck
        ellipsoid((0.39, 0.69, 0.0), (0.10, 0.075, 0.075)),  # head
        capsule((0.42, 0.67, 0.0), (0.49, 0.645, 0.0), 0.05, 0.04, s),  # snout
        capsule((0.36, 0.74, 0.04), (0.34, 0.81, 0.065), 0.025, 0.015, s, 12),  # ears
        capsule((0.36, 0.74, -0.04), (0.34, 0.81, -0.065), 0.025, 0.015, s, 12),
        capsule((-0.26, 0.50, 0.0), (-0.38, 0.58, 0.0), 0.045, 0.032, s, 16),  # tail
        capsule((-0.38, 0.58, 0.0), (-0.46, 0.70, 0.0), 0.032, 0.02, s, 16),
    ]
    for x in (0.18, -0.18):
        for z in (0.075, -0.075):
            parts.append(capsule((x, 0.42, z), (x + 0.02, 0.045, z * 1.15), 0.06, 0.045, s))
    shape = union(parts)
    return shape.translate([0.0, -shape.bounding_box()[1], 0.0])


def plant() -> Manifold:
    """A stem with two branches carrying leaves and a leaf on top; flat base at y = 0."""
    s = 0.04
    parts = [
        Manifold.cylinder(0.04, 0.045, 0.04, SEGMENTS).rotate([-90.0, 0.0, 0.0]),  # foot
        capsule((0.0, 0.02, 0.0), (0.0, 0.80, 0.0), 0.028, 0.018, s),  # stem
        capsule((0.0, 0.35, 0.0), (0.20, 0.52, 0.0), 0.018, 0.012, s, 16),  # branches
        capsule((0.0, 0.55, 0.0), (-0.17, 0.70, 0.05), 0.016, 0.011, s, 16),
        _leaf((0.20, 0.52, 0.0), (0.33, 0.60, 0.0)),
        _leaf((-0.17, 0.70, 0.05), (-0.29, 0.79, 0.09)),
        _leaf((0.0, 0.80, 0.0), (0.04, 0.94, 0.0)),
    ]
    shape = union(parts)
    return shape.translate([0.0, -shape.bounding_box()[1], 0.0])


def _leaf(start, end, width: float = 0.06, thickness: float = 0.025) -> Manifold:
    """A flattened ellipsoid leaf from ``start`` to ``end`` (its flat side faces up)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    axis = end - start
    length = float(np.linalg.norm(axis))
    blade = Manifold.sphere(1.0, SEGMENTS).scale([width, thickness, length / 2])
    blade = blade.translate([0.0, 0.0, length / 2])
    return blade.transform(_frame(axis / length, start))


def bar() -> Manifold:
    """A 1 x 0.1 x 0.1 m bar along x from x = 0 to x = 1, centred on the x axis."""
    box = Manifold.cube([1.0, 0.1, 0.1], True).translate([0.5, 0.0, 0.0])
    return box.refine_to_length(0.025)


def write_obj(shape: Manifold, path: Path, comment: str) -> tuple[np.ndarray, np.ndarray]:
    """Write the shape's triangles as an OBJ with 5 decimals (10 micrometres)."""
    mesh = shape.to_mesh()
    V = np.asarray(mesh.vert_properties)[:, :3].astype(np.float64)
    F = np.asarray(mesh.tri_verts).astype(np.int64)
    lines = [f"# {comment}", "# generated by scripts/make_demo_models.py (manifold3d)"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in V]
    lines += [f"f {a} {b} {c}" for a, b, c in F + 1]
    path.write_text("\n".join(lines) + "\n")
    return V, F


def main() -> None:
    from wiggly.mesh import check_surface, load_mesh, tetrahedralize

    DATA.mkdir(parents=True, exist_ok=True)
    models = {
        "critter": (critter(), "soft four-legged critter, ~1 m long along x, y up, feet on y = 0"),
        "plant": (plant(), "plant: stem, two branches, three leaves, y up, flat base on y = 0"),
        "bar": (bar(), "bar 1 x 0.1 x 0.1 m along x from x = 0 to 1, centred on the x axis"),
    }
    for name, (shape, comment) in models.items():
        path = DATA / f"{name}.obj"
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
