"""Shared fixtures: small bodies built from structured box meshes (no tetrahedralizer needed),
and headless Chromium for the editor's browser tests (one browser per test process)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import meshio
import numpy as np
import pytest

# the editor's children yield the processor to their server (nice +5, +10): against this
# suite's parallel workers, at full priority, that starved them past the tests' waits
os.environ.setdefault("WIGGLY_EDITOR_NICE", "0")

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


CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                  "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--no-first-run"]


@pytest.fixture(scope="session")
def chromium():
    """Debian's headless Chromium through Playwright (a fresh profile; no browser download)."""
    if not os.path.exists(CHROMIUM):
        pytest.skip(f"{CHROMIUM} is missing (apt-get install chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright is missing (pip install playwright)")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS)
        try:
            yield browser
        finally:
            browser.close()


@pytest.fixture(scope="session")
def blender_python() -> str:
    """The Python of Blender as a module (PyPI bpy, `make blender`); the test skips, with
    the reason, without it."""
    python = os.environ.get("WIGGLY_BLENDER_PYTHON") or str(
        Path(__file__).resolve().parents[1] / ".venv-blender" / "bin" / "python")
    try:
        done = subprocess.run([python, "-c", "import bpy; print(bpy.app.version_string)"],
                              capture_output=True, text=True, timeout=120)
    except OSError:
        done = None
    if done is None or done.returncode != 0:
        pytest.skip(f"no Blender as a Python module at {python}: `make blender` installs PyPI "
                    "bpy (Python 3.11) into .venv-blender (or set WIGGLY_BLENDER_PYTHON)")
    return python


def generic_direction(rng: np.random.Generator, g: np.ndarray) -> np.ndarray:
    """A random direction along which the slope g . d is not small against |g| |d| (a random
    direction alone is nearly orthogonal to g now and then: in 300 dimensions
    |cos| < 1e-3 about once in 70 draws, and the slope check then compares rounding)."""
    d = rng.standard_normal(g.size)
    return d + np.sign(g @ d or 1.0) * 0.2 * np.linalg.norm(d) * g / np.linalg.norm(g)
