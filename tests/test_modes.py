"""Eigenmodes (Schulz et al. 2014, eq. (5)) and the sparse SPD factorizations behind them."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import wiggly.modes as modes_module
from wiggly.errors import WigglyInputError
from wiggly.fem import mass_matrix, stiffness_matrix
from wiggly.linalg import available_backends, factorize_spd
from wiggly.modes import Modes, compute_modes, rigid_motions
from wiggly.primitives import box_mesh

SIZE = (1.0, 0.6, 0.35)  # unequal sides: few symmetric degeneracies


@pytest.fixture(scope="module")
def small_body():
    """A box split into 180 tets (72 vertices, 216 dofs)."""
    V, T = box_mesh((5, 3, 2), SIZE)
    K = stiffness_matrix(V, T, 1e5, 0.45)
    M = mass_matrix(V, T, 1000.0)
    return V, T, K, M


def reduced_dense_eigh(K, M, fixed_vertices, n):
    """Reference: all eigenpairs of the reduced dense problem, vectors scattered to 3n."""
    free = np.ones(3 * n, dtype=bool)
    free[(3 * np.asarray(fixed_vertices, dtype=int)[:, None] + np.arange(3)).ravel()] = False
    Kd = K.toarray()[np.ix_(free, free)]
    Md = M.toarray()[np.ix_(free, free)]
    lam, X = la.eigh(Kd, Md)
    full = np.zeros((3 * n, X.shape[1]))
    full[free] = X
    return lam, full


def clusters(lam, rel=1e-6):
    """Index ranges of eigenvalue clusters (relative gap > rel separates them)."""
    scale = max(abs(lam).max(), 1.0)
    starts = [0, *[i + 1 for i in range(len(lam) - 1) if lam[i + 1] - lam[i] > rel * scale]]
    return [range(s, e) for s, e in zip(starts, [*starts[1:], len(lam)], strict=True)]


def assert_same_subspaces(Phi, Ref, lam_ref, M, r):
    """Eigenspaces agree cluster by cluster: Ref_c^T M Phi_c is orthogonal (cosines all 1)."""
    for c in clusters(lam_ref[:r]):
        if c.stop == r and r < len(lam_ref) and lam_ref[r] - lam_ref[r - 1] < 1e-6 * lam_ref[r]:
            continue  # the cluster is cut by r: its span is not determined by the first r
        idx = list(c)
        cosines = la.svdvals(Ref[:, idx].T @ (M @ Phi[:, idx]))
        np.testing.assert_allclose(cosines, 1.0, atol=1e-7)


def assert_orthonormal(modes, K, M):
    P = modes.vectors
    np.testing.assert_allclose(P.T @ (M @ P), np.eye(modes.r), atol=1e-10)
    lam_max = max(modes.eigenvalues.max(), 1.0)
    np.testing.assert_allclose(P.T @ (K @ P), np.diag(modes.eigenvalues), atol=1e-9 * lam_max)


def rigid_residual(Phi, V):
    """Relative distance of each column of Phi from span(rigid motions of V)."""
    R = rigid_motions(V)
    coeff, *_ = np.linalg.lstsq(R, Phi, rcond=None)
    return np.linalg.norm(Phi - R @ coeff, axis=0) / np.linalg.norm(Phi, axis=0)


# --- rigid motions --------------------------------------------------------------------------


def test_rigid_motions_are_translations_and_rotations_about_centroid():
    V = np.random.default_rng(0).standard_normal((7, 3))
    R = rigid_motions(V)
    assert R.shape == (21, 6)
    np.testing.assert_array_equal(R[:, :3], np.tile(np.eye(3), (7, 1)))
    c = V.mean(axis=0)
    for k in range(3):
        np.testing.assert_allclose(R[:, 3 + k].reshape(7, 3), np.cross(np.eye(3)[k], V - c))
    # rotations about the centroid carry no net displacement
    np.testing.assert_allclose(R[:, 3:].reshape(7, 3, 3).sum(axis=0), 0.0, atol=1e-12)


# --- against a dense solve ------------------------------------------------------------------


@pytest.mark.parametrize("method", ["sparse", "dense"])
def test_free_body_modes_match_dense_eigh(small_body, method):
    V, _, K, M = small_body
    r = 30
    modes = compute_modes(K, M, r, vertices=V, cache_dir=False, method=method)
    lam_ref, X_ref = reduced_dense_eigh(K, M, [], len(V))
    assert isinstance(modes, Modes)
    assert modes.n_rigid == 6 and modes.vectors.shape == (3 * len(V), r)
    assert np.all(modes.eigenvalues[:6] == 0.0)
    assert np.all(np.abs(lam_ref[:6]) < 1e-9 * lam_ref[6])  # the reference sees 6 zero modes
    rel = np.abs(modes.eigenvalues[6:] - lam_ref[6:r]) / lam_ref[6:r]
    assert rel.max() < 1e-8
    assert np.all(np.diff(modes.eigenvalues) >= 0)
    assert_orthonormal(modes, K, M)
    assert_same_subspaces(modes.vectors, X_ref, np.r_[np.zeros(6), lam_ref[6:]], M, r)
    assert rigid_residual(modes.vectors[:, :6], V).max() < 1e-12
    assert rigid_residual(modes.vectors[:, 6:], V).min() > 0.1
    # free body: the first three modes are pure translations (M-normalized)
    T3 = modes.vectors[:, :3].reshape(len(V), 3, 3)
    np.testing.assert_allclose(T3 - T3[:1], 0.0, atol=1e-12)
    total_mass = M.sum() / 3
    np.testing.assert_allclose(np.abs(T3[0]), np.eye(3) / math.sqrt(total_mass), atol=1e-12)


FIXED_CASES = {
    # name: (selector of fixed vertices, n_rigid)
    "face": (lambda V: np.flatnonzero(V[:, 0] == 0.0), 0),
    "one vertex": (lambda V: np.array([0]), 3),
    "collinear": (lambda V: np.flatnonzero((V[:, 1] == 0.0) & (V[:, 2] == 0.0)), 1),
    "two vertices": (lambda V: np.array([0, len(V) - 1]), 1),
    "three vertices": (lambda V: np.array([0, 5, len(V) - 1]), 0),
}


@pytest.mark.parametrize("case", list(FIXED_CASES))
@pytest.mark.parametrize("method", ["sparse", "dense"])
def test_fixed_vertices(small_body, case, method):
    V, _, K, M = small_body
    select, n_rigid = FIXED_CASES[case]
    fixed = select(V)
    r = 16
    modes = compute_modes(K, M, r, vertices=V, fixed_vertices=fixed, cache_dir=False, method=method)
    assert modes.n_rigid == n_rigid
    np.testing.assert_array_equal(modes.fixed_vertices, np.sort(fixed))
    assert np.all(modes.eigenvalues[:n_rigid] == 0.0)
    fixed_dofs = (3 * fixed[:, None] + np.arange(3)).ravel()
    assert np.all(modes.vectors[fixed_dofs] == 0.0)
    lam_ref, X_ref = reduced_dense_eigh(K, M, fixed, len(V))
    assert np.all(np.abs(lam_ref[:n_rigid]) < 1e-9 * lam_ref[n_rigid])
    assert lam_ref[n_rigid] > 1.0  # and no other zero modes
    rel = np.abs(modes.eigenvalues[n_rigid:] - lam_ref[n_rigid:r]) / lam_ref[n_rigid:r]
    assert rel.max() < 1e-8
    assert_orthonormal(modes, K, M)
    lam_all = np.r_[np.zeros(n_rigid), lam_ref[n_rigid:]]
    assert_same_subspaces(modes.vectors, X_ref, lam_all, M, r)
    if n_rigid:
        assert rigid_residual(modes.vectors[:, :n_rigid], V).max() < 1e-12
        assert np.linalg.norm(K @ modes.vectors[:, :n_rigid]) < 1e-9 * abs(K).max()


def test_results_are_deterministic(small_body):
    V, _, K, M = small_body
    a = compute_modes(K, M, 12, vertices=V, cache_dir=False, method="sparse")
    b = compute_modes(K, M, 12, vertices=V, cache_dir=False, method="sparse")
    np.testing.assert_array_equal(a.eigenvalues, b.eigenvalues)
    np.testing.assert_array_equal(a.vectors, b.vectors)


def test_frequencies_hz():
    modes = Modes(
        eigenvalues=np.array([0.0, (2 * np.pi) ** 2, (6 * np.pi) ** 2]),
        vectors=np.zeros((3, 3)),
        n_rigid=1,
    )
    np.testing.assert_allclose(modes.frequencies_hz(), [0.0, 1.0, 3.0])
    assert modes.r == 3


# --- Euler-Bernoulli cantilever -------------------------------------------------------------


def test_cantilever_first_bending_frequency_converges_to_euler_bernoulli():
    """Lowest mode of a clamped slender bar -> (1.8751)^4 E I / (rho A L^4).

    nu = 0 removes the Poisson coupling; L / a = 20 keeps the shear (Timoshenko) correction of
    the first mode well below 1%.  P1 tets converge in eigenvalue like O(h^2) (twice the
    energy-norm rate, h the element size), but lock in bending: the constant is large (error
    ~240% with one cell across the section).  Observed errors 60%, 15%, 3.5% for 2, 4, 8
    cells across, i.e. rate ~2.0; we assert it within 0.3 of 2 and 5% at the finest level.
    """
    L, a, E, rho = 1.0, 0.05, 1e6, 1000.0
    I, A = a**4 / 12, a**2
    lam_eb = 1.87510406871196**4 * E * I / (rho * A * L**4)
    errors, hs = [], []
    for cells in (2, 4, 8):
        V, T = box_mesh((20 * cells, cells, cells), (L, a, a))
        K = stiffness_matrix(V, T, E, 0.0)
        M = mass_matrix(V, T, rho)
        clamped = np.flatnonzero(V[:, 0] == 0.0)
        modes = compute_modes(K, M, 2, vertices=V, fixed_vertices=clamped, cache_dir=False)
        assert modes.n_rigid == 0
        errors.append(abs(modes.eigenvalues[0] / lam_eb - 1.0))
        hs.append(a / cells)
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.05
    rate = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert 1.7 < rate < 2.3, (errors, rate)


# --- cache ----------------------------------------------------------------------------------


def test_cache_roundtrip_corruption_and_key(small_body, tmp_path, monkeypatch):
    V, T, K, M = small_body
    first = compute_modes(K, M, 10, vertices=V, cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    assert not list(tmp_path.glob("*.tmp"))  # written atomically, no leftovers

    def fail(*args, **kwargs):
        raise AssertionError("recomputed instead of loading the cache")

    with monkeypatch.context() as mp:
        mp.setattr(modes_module, "_compute_modes", fail)
        second = compute_modes(K, M, 10, vertices=V, cache_dir=tmp_path)
    np.testing.assert_array_equal(first.eigenvalues, second.eigenvalues)
    np.testing.assert_array_equal(first.vectors, second.vectors)
    assert second.n_rigid == first.n_rigid

    files[0].write_bytes(b"not an npz file")  # corrupt: ignored and recomputed
    third = compute_modes(K, M, 10, vertices=V, cache_dir=tmp_path)
    np.testing.assert_allclose(third.eigenvalues, first.eigenvalues, rtol=1e-12)
    with monkeypatch.context() as mp:
        mp.setattr(modes_module, "_compute_modes", fail)
        compute_modes(K, M, 10, vertices=V, cache_dir=tmp_path)  # rewritten, loads again

    K2 = stiffness_matrix(V, T, 2e5, 0.45)  # other material, r, or fixed set: other keys
    compute_modes(K2, M, 10, vertices=V, cache_dir=tmp_path)
    compute_modes(K, M, 11, vertices=V, cache_dir=tmp_path)
    compute_modes(K, M, 10, vertices=V, fixed_vertices=[0], cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 4


def test_cache_dir_from_environment_and_disabled(small_body, tmp_path, monkeypatch):
    V, _, K, M = small_body
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "env"))
    compute_modes(K, M, 7, vertices=V)
    assert len(list((tmp_path / "env").glob("*.npz"))) == 1
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "off"))
    compute_modes(K, M, 7, vertices=V, cache_dir=False)
    assert not (tmp_path / "off").exists()


# --- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"r": 0}, r"r \(number of modes\).*got 0"),
        ({"r": 217}, r"\[1, 216\].*got 217"),
        ({"r": 501}, r"at most 500 \(wiggly\.limits\.MAX_MODES, as in scene files\); got 501"),
        ({"r": 4}, r"r = 4 is smaller than the number of rigid modes.*\(6\)"),
        ({"r": 2.5}, "should be an integer; got 2.5"),
        ({"r": 8, "fixed_vertices": [72]}, r"vertex index 72 does not exist.*0\.\.71"),
        ({"r": 8, "method": "magic"}, "method"),
    ],
)
def test_bad_arguments(small_body, kwargs, pattern):
    V, _, K, M = small_body
    with pytest.raises(WigglyInputError, match=pattern):
        compute_modes(K, M, vertices=V, cache_dir=False, **kwargs)


def test_mismatched_matrices(small_body):
    V, _, K, M = small_body
    with pytest.raises(WigglyInputError, match=r"K should have shape \(213, 213\)"):
        compute_modes(K, M, 8, vertices=V[:-1], cache_dir=False)
    with pytest.raises(WigglyInputError, match="same mesh"):
        compute_modes(
            K, M, 8, vertices=V[np.random.default_rng(0).permutation(len(V))], cache_dir=False
        )
    with pytest.raises(WigglyInputError, match="symmetric"):
        compute_modes(K + sp.triu(K, 1), M, 8, vertices=V, cache_dir=False)


def two_boxes(offset):
    """Two 2x2x2-cell unit boxes, the second shifted by `offset`; coincident vertices merged."""
    V1, T1 = box_mesh((2, 2, 2))
    V2, T2 = box_mesh((2, 2, 2), origin=offset)
    V = np.vstack([V1, V2])
    T = np.vstack([T1, T2 + len(V1)])
    unique, inverse = np.unique(np.round(V, 9), axis=0, return_inverse=True)
    return unique, inverse.ravel()[T]


@pytest.mark.parametrize(
    ("offset", "what"),
    [
        ((3.0, 0.0, 0.0), "separate"),
        ((1.0, 1.0, 1.0), "touching at a vertex"),
        ((1.0, 1.0, 0.0), "hinged at an edge"),
    ],
)
@pytest.mark.parametrize("method", ["sparse", "dense"])
def test_disconnected_body_is_rejected(offset, what, method):
    V, T = two_boxes(offset)
    K = stiffness_matrix(V, T, 1e5, 0.3)
    M = mass_matrix(V, T, 1000.0)
    with pytest.raises(WigglyInputError, match=r"disconnected parts.*mesh it as one "
                       r"connected body"):
        compute_modes(K, M, 14, vertices=V, cache_dir=False, method=method)


def test_unused_vertex_is_rejected(small_body):
    V, T, _, _ = small_body
    V2 = np.vstack([V, [5.0, 5.0, 5.0]])
    K = stiffness_matrix(V2, T, 1e5, 0.3)
    M = mass_matrix(V2, T, 1000.0)
    with pytest.raises(WigglyInputError, match="not used by any tet"):
        compute_modes(K, M, 8, vertices=V2, cache_dir=False)
    # fixing it is fine: a vertex outside the mesh holds nothing, the body stays free
    modes = compute_modes(K, M, 8, vertices=V2, fixed_vertices=[len(V)], cache_dir=False)
    free = compute_modes(K[:-3, :-3], M[:-3, :-3], 8, vertices=V, cache_dir=False)
    assert modes.n_rigid == 6
    np.testing.assert_allclose(modes.eigenvalues, free.eigenvalues, rtol=1e-10, atol=1e-9)
    clamped = compute_modes(K, M, 8, vertices=V2, fixed_vertices=[0, len(V)], cache_dir=False)
    assert clamped.n_rigid == 3


def test_progress_reports_on_the_logger(small_body, caplog):
    V, _, K, M = small_body
    with caplog.at_level(logging.INFO, logger="wiggly"):
        compute_modes(K, M, 10, vertices=V, cache_dir=False, method="sparse")
    err = caplog.text
    assert "factoriz" in err and "eigsh done" in err and "solves" in err


# --- sparse SPD factorizations --------------------------------------------------------------


@pytest.mark.parametrize("backend", available_backends())
def test_factorize_spd_backends_agree(small_body, backend):
    _, _, K, M = small_body
    A = (K + 1e3 * M).tocsr()
    rng = np.random.default_rng(1)
    B = rng.standard_normal((A.shape[0], 3))
    reference = spla.spsolve(A.tocsc(), B)
    solver = factorize_spd(A, backend=backend)
    assert solver.backend == backend
    x = solver(B[:, 0])
    assert x.shape == (A.shape[0],)
    np.testing.assert_allclose(x, reference[:, 0], rtol=1e-9, atol=1e-12 * abs(reference).max())
    X = solver(B)
    np.testing.assert_allclose(X, reference, rtol=1e-9, atol=1e-12 * abs(reference).max())
    X_other = factorize_spd(A, backend=available_backends()[-1])(B)
    np.testing.assert_allclose(X, X_other, rtol=1e-9, atol=1e-12 * abs(reference).max())
    out = np.full((A.shape[0] + 2, 3), np.nan)  # solve into rows of a larger array
    assert solver(B, out=out[1:-1]) is not None
    np.testing.assert_array_equal(out[1:-1], X)
    assert np.isnan(out[[0, -1]]).all()
    many = rng.standard_normal((A.shape[0], 300))  # cholespy: solved in column blocks
    np.testing.assert_allclose(
        solver(many), spla.spsolve(A.tocsc(), many), rtol=1e-9, atol=1e-12 * abs(many).max()
    )


@pytest.mark.skipif("cholespy" not in available_backends(), reason="cholespy not installed")
def test_a_factor_alive_at_exit_is_not_reported_as_a_leak(tmp_path):
    """A cholespy factor still held at the interpreter's exit (by a daemon thread, as the
    editor's are) is released first: nanobind printed "leaked instance" warnings on the
    terminal of an editor stopped with Ctrl+C."""
    import subprocess
    import sys

    script = tmp_path / "held.py"
    script.write_text(
        "import threading, time\n"
        "import scipy.sparse as sp\n"
        "from wiggly.linalg import factorize_spd\n"
        "f = factorize_spd(sp.diags([2.0] * 50).tocsr(), backend='cholespy')\n"
        "threading.Thread(target=lambda x=f: time.sleep(60), daemon=True).start()\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert "leaked" not in done.stderr, done.stderr


def test_factorize_spd_errors():
    with pytest.raises(WigglyInputError, match="backend"):
        factorize_spd(sp.eye(3), backend="magic")
    with pytest.raises(WigglyInputError, match="square"):
        factorize_spd(sp.random(3, 4))
    solver = factorize_spd(sp.eye(3).tocsr())
    with pytest.raises(WigglyInputError, match=r"shape \(3,\)"):
        solver(np.ones(4))
    with pytest.raises(WigglyInputError, match="C-contiguous"):
        solver(np.ones((3, 2)), out=np.ones((2, 3)).T)
    if "cholespy" in available_backends():
        with pytest.raises(np.linalg.LinAlgError, match="positive definite"):
            factorize_spd(sp.diags([1.0, -1.0, 1.0]).tocsr(), backend="cholespy")
