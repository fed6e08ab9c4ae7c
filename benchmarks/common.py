"""Shared helpers for the benchmarks: timing (median of repeats), tables, test bodies."""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import trimesh

from wiggly.body import Body, Damping, prepare
from wiggly.fem import Material
from wiggly.mesh import Model, Surface, TetMesh, embed
from wiggly.primitives import box_mesh


def median_time(fn: Callable[[], object], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall time in seconds of ``repeats`` calls (after ``warmup`` calls)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def table(title: str, header: list[str], rows: list[list[object]]) -> str:
    """A Markdown table (printed by the benchmarks, pasted into notes)."""

    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.3e}"
        return str(v)

    lines = [
        f"### {title}",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" for _ in header) + "|",
    ]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def box_shape_for(n_tets: int, aspect=(3.0, 1.0, 1.0)) -> tuple[int, int, int]:
    """Grid cells (6 tets each) of a box with the given aspect and about ``n_tets`` tets."""
    a = np.asarray(aspect, float)
    s = (n_tets / 6 / np.prod(a)) ** (1 / 3)
    return tuple(int(max(1, round(s * x))) for x in a)


def box_model(
    n_tets: int, surface_vertices: int | None = None, size=(1.2, 0.4, 0.4), cells=None
) -> Model:
    """A box tet mesh with ~n_tets tets (or exactly 6 prod(cells)) and, optionally, a finer
    embedded box surface with ~surface_vertices vertices (the user's surface is independent
    of the simulation mesh)."""
    if cells is None:
        cells = box_shape_for(n_tets, np.asarray(size) / min(size))
    V, T = box_mesh(tuple(cells), size)
    tets = TetMesh(V, T)
    if surface_vertices is None:
        surf = Surface(V, tets.boundary_faces())
    else:
        mesh = trimesh.creation.box(extents=size)
        mesh.apply_translation(np.asarray(size) / 2)
        v, f = mesh.vertices, mesh.faces
        while len(v) * 4 <= surface_vertices * 1.5:  # each subdivision ~quadruples vertices
            v, f = trimesh.remesh.subdivide(v, f)
        v = v * (1 - 1e-9) + np.asarray(size) * 0.5e-9  # strictly inside the box
        surf = Surface(v, f)
    return Model(surf, tets, embed(surf.vertices, tets), source=f"box{n_tets}")


def box_body(
    n_tets: int, surface_vertices: int | None = None, n_modes: int = 40, cells=None
) -> Body:
    return prepare(
        box_model(n_tets, surface_vertices, cells=cells),
        material=Material(2e5, 0.45, 1000.0),
        damping=Damping(0.5, 0.002),
        n_modes=n_modes,
        cache_dir=bench_cache(),
    )


def bench_cache() -> str:
    path = os.path.join(os.path.dirname(__file__), ".cache")
    os.makedirs(path, exist_ok=True)
    return path
