"""Band storage and the accurate banded Cholesky of the spacetime solve (Theorem 1)."""

from __future__ import annotations

from fractions import Fraction

import mpmath
import numpy as np
import pytest

from wiggly.body import Damping, prepare
from wiggly.fem import Material
from wiggly.keyframes import Keyframe
from wiggly.mesh import Model, Surface, TetMesh
from wiggly.primitives import box_mesh
from wiggly.solve import SpacetimeProblem
from wiggly.solve.banded import (
    BandedCholesky,
    add_block,
    add_blocks,
    band_matvec,
    band_to_dense,
    extended_residual,
)


def banded(H: np.ndarray, bw: int) -> np.ndarray:
    N = len(H)
    ab = np.zeros((bw + 1, N), order="F")
    for i in range(N):
        for j in range(i, min(N, i + bw + 1)):
            ab[bw + i - j, j] = H[i, j]
    return ab


def test_band_helpers_match_dense_algebra():
    rng = np.random.default_rng(0)
    N, bw = 40, 6
    H = rng.standard_normal((N, N))
    H = H + H.T + 4 * N * np.eye(N)
    H[np.abs(np.subtract.outer(np.arange(N), np.arange(N))) > bw] = 0.0
    ab = banded(H, bw)
    np.testing.assert_array_equal(band_to_dense(ab), H)
    x = rng.standard_normal(N)
    np.testing.assert_allclose(band_matvec(ab, x), H @ x, rtol=1e-13)
    block = rng.standard_normal((4, 4))
    block = block + block.T
    idx = np.array([3, 4, 5, 6])
    add_block(ab, idx, block)
    H[np.ix_(idx, idx)] += block
    np.testing.assert_array_equal(band_to_dense(ab), H)
    blocks = rng.standard_normal((3, 3, 3))
    blocks = blocks + blocks.transpose(0, 2, 1)
    idx = np.array([[0, 1, 2], [8, 9, 10], [9, 10, 11]])  # overlapping blocks add up
    add_blocks(ab, idx, blocks)
    for i, b in zip(idx, blocks, strict=True):
        H[np.ix_(i, i)] += b
    np.testing.assert_allclose(band_to_dense(ab), H, rtol=1e-15)
    # disjoint blocks: of consecutive indices (added by diagonals), and in another order
    # (the direct assignment through index masks)
    for idx in (np.array([[20, 21, 22], [30, 31, 32]]), np.array([[24, 23, 25], [13, 15, 14]])):
        add_blocks(ab, idx, blocks[:2])
        for i, b in zip(idx, blocks[:2], strict=True):
            H[np.ix_(i, i)] += b
        np.testing.assert_allclose(band_to_dense(ab), H, rtol=1e-15)
    np.testing.assert_allclose(BandedCholesky(ab).solve(x), np.linalg.solve(H, x), rtol=1e-10)


def test_extended_residual_is_exact_to_twice_the_precision():
    """rhs - H z where the terms cancel to 1e-12 of their size: plain double arithmetic
    keeps ~4 digits, the extended residual all 16 (checked in exact rational arithmetic)."""
    rng = np.random.default_rng(1)
    N, bw = 30, 5
    H = rng.standard_normal((N, N))
    H = H + H.T
    H[np.abs(np.subtract.outer(np.arange(N), np.arange(N))) > bw] = 0.0
    ab = banded(H, bw)
    z = rng.standard_normal(N)
    rhs = H @ z + 1e-12 * rng.standard_normal(N)  # rhs - H z is tiny against H z
    exact = np.array([
        float(Fraction(rhs[i]) - sum(Fraction(H[i, j]) * Fraction(z[j]) for j in range(N)))
        for i in range(N)
    ])
    got = extended_residual(ab, z, rhs)
    assert np.abs(got - exact).max() <= 1e-15 * np.abs(exact).max()
    plain = rhs - H @ z
    assert np.abs(plain - exact).max() > 1e-6 * np.abs(exact).max()  # what refinement avoids


@pytest.fixture(scope="module")
def stiff_bar():
    V, T = box_mesh((12, 3, 3), (1.2, 0.3, 0.3))
    tets = TetMesh(V, T)
    model = Model(Surface(V, tets.boundary_faces()), tets, None, source="bar")
    return prepare(
        model, material=Material(1e6, 0.45, 1000.0), damping=Damping(0.1, 0.001),
        n_modes=12, cache_dir=False,
    )


@pytest.mark.parametrize("stiffness", [1e10, 1e12])
def test_linear_solve_with_stiff_keyframes_matches_an_extended_precision_solve(
    stiff_bar, stiffness
):
    """Keyframes on single vertices with weights up to 1e12 make the system of Theorem 1
    ill-conditioned (cond ~1e11-1e13); its solution equals a 50-digit solve of the same
    (double) system to 1e-7 relative, while the factorization alone loses up to ~1e-4."""
    body = stiff_bar
    X = body.rest_positions()
    rng = np.random.default_rng(0)
    problem = SpacetimeProblem(body, 0.0, 3.0)
    keys = [Keyframe.rest(body, 0.0, np.arange(len(X)), still=True, stiffness=stiffness)]
    for t in (0.5, 1.1, 1.7, 2.4, 3.0):
        keys.append(Keyframe.offset(
            body, t, rng.choice(len(X), 1), 0.05 * rng.standard_normal(3),
            velocity=0.2 * rng.standard_normal(3), stiffness=stiffness,
        ))
    kfs = problem.checked(keys)
    nodes = problem.nodes_for(kfs)
    ab, f = problem.linear_system(kfs, nodes)
    z = problem.solve_linear(kfs, nodes)
    mpmath.mp.dps = 50
    H = band_to_dense(ab)
    reference = mpmath.lu_solve(mpmath.matrix(H.tolist()), mpmath.matrix((-f).tolist()))
    reference = np.array([float(x) for x in reference])
    scale = np.abs(reference).max()
    assert np.abs(z - reference).max() <= 1e-7 * scale
    unrefined = BandedCholesky(ab).solve(-f, refine=False)
    assert np.abs(unrefined - reference).max() > 1e-7 * scale  # the test is demanding
