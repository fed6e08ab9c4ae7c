"""Shared fixtures: small bodies built from structured box meshes (no tetrahedralizer needed)."""

from __future__ import annotations

import meshio
import numpy as np
import pytest

from wiggly.body import Body, Damping, prepare
from wiggly.fem import Material
from wiggly.mesh import load_model
from wiggly.primitives import box_mesh


def make_body(
    tmp_path_factory,
    shape=(10, 2, 2),
    size=(1.0, 0.1, 0.1),
    n_modes=10,
    fixed=None,
    young=1e5,
    damping=None,
    gravity=(0, -9.81, 0),
) -> Body:
    damping = damping or Damping(0.5, 0.002)
    V, T = box_mesh(shape, size)
    path = tmp_path_factory.mktemp("mesh") / "bar.vtu"
    meshio.write(path, meshio.Mesh(V, [("tetra", T)]))
    return prepare(
        load_model(path),
        material=Material(young, 0.3, 1000.0),
        damping=damping,
        n_modes=n_modes,
        fixed_vertices=fixed,
        gravity=gravity,
        cache_dir=False,
    )


@pytest.fixture(scope="session")
def bar(tmp_path_factory) -> Body:
    """A free 1 m x 0.1 m x 0.1 m bar, 10 modes (6 rigid)."""
    return make_body(tmp_path_factory)


@pytest.fixture(scope="session")
def cantilever(tmp_path_factory) -> Body:
    """The same bar fixed at x = 0."""
    V, _ = box_mesh((10, 2, 2), (1.0, 0.1, 0.1))
    return make_body(tmp_path_factory, fixed=np.flatnonzero(V[:, 0] < 1e-9))
