"""How well a linear basis of the warp's nonlinear part represents it on solved scenes.

A reduced warp ``W_r(Phi q) = Phi q + U c(q)`` (cubature, An, Kim & James 2008; reduced
rotation-strain coordinates, Li et al. 2014) would make a Newton iteration's cost
independent of the mesh: U (n, 3, d) a basis of the nonlinear part ``y(q) = W(Phi q) - Phi
q`` and c the Galerkin projection of the warp's Poisson fit onto it,

    c(q) = (U^T L U)^-1 U^T G^T Vol N(G Phi q),   N(A) = H(A) - A,

exact when y(q) lies in span U.  Cubature would then approximate the sum over tets.  This
measures the step before cubature: how far W_r, with the sum taken over every tet, lies from
W at the nodes of a solved warped motion (states the basis was not trained on), for bases of
d fields from

* **random states**: proper orthogonal decomposition (SVD) of y at S random modal states,
  half of them dense (modal amplitudes ~ 1/sqrt(eigenvalue)) and half of them one to three
  modes, each scaled to a largest tet rotation of 0.05-3 radians;
* **the scene's own states**: the linear solution's node states, scaled by 0.3-1.5 and
  perturbed, with those states themselves.

Errors are the largest vertex error of y, relative to the largest |y| at the same node (max
over the nodes), and in % of the body's diagonal.  The best projection onto span U (no
Galerkin) is printed as a lower bound.

Run: ``.venv/bin/python benchmarks/bench_reduced_basis.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from bench_scenes import KINDS, MODES, SOFT, dinosaur, keyframes
from common import table
from wiggly.body import Body, prepare
from wiggly.mesh import load_model
from wiggly.solve import SpacetimeProblem

SCENES = [
    ("critter", "turn 120"),
    ("critter", "velocity at the end"),
    ("dinosaur (procedural, soft)", "hop with a 90 degree turn"),
]


def nonlinear_part(body: Body, Q: np.ndarray) -> np.ndarray:
    """``W(Phi q) - Phi q`` at states Q (f, r): (f, n, 3)."""
    n = body.warp.n_vertices
    U = (Q @ body.modes.vectors.T).reshape(len(Q), n, 3)
    return body.warp.apply(U) - U


def random_states(body: Body, count: int, rng: np.random.Generator) -> np.ndarray:
    """Random modal states (module docstring), each scaled to a largest tet rotation."""
    n, r = body.warp.n_vertices, body.r
    grads = (body.warp.gradient @ body.modes.vectors.reshape(n, 3 * r)).reshape(-1, 3, 3, r)
    lam = body.eigenvalues
    floor = lam[lam > 1e-6].min() if np.any(lam > 1e-6) else 1.0
    sigma = 1.0 / np.sqrt(np.maximum(lam, floor))
    out = []
    for s in range(count):
        if s % 2:
            xi = np.zeros(r)
            pick = rng.choice(r, int(rng.integers(1, 4)), replace=False)
            xi[pick] = rng.standard_normal(len(pick))
        else:
            xi = rng.standard_normal(r) * sigma
        A = grads @ xi
        w = 0.5 * np.stack([A[:, 2, 1] - A[:, 1, 2], A[:, 0, 2] - A[:, 2, 0],
                            A[:, 1, 0] - A[:, 0, 1]], axis=1)
        scale = max(float(np.linalg.norm(w, axis=1).max()), 0.3 * float(np.abs(A).max()), 1e-12)
        out.append(xi * rng.uniform(0.05, 3.0) / scale)
    return np.array(out)


def scene_states(linear: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """The linear solution's node states, scaled and perturbed, and those states."""
    base = linear[rng.integers(0, len(linear), count)] * rng.uniform(0.3, 1.5, (count, 1))
    noise = 0.3 * rng.standard_normal((count, linear.shape[1])) * np.abs(linear).max(axis=0)
    return np.vstack([base + noise, linear])


def errors(body: Body, training: np.ndarray, test: np.ndarray, d: int) -> tuple[float, ...]:
    """Galerkin and best-projection errors of a d-field basis of y at the training states."""
    n = body.warp.n_vertices
    L = body.warp.laplacian
    Y = nonlinear_part(body, training).reshape(len(training), -1).T
    basis = np.linalg.svd(Y, full_matrices=False)[0][:, :d]
    Ub = basis.reshape(n, 3, d)
    M = basis.T @ np.stack([L @ Ub[:, c] for c in range(3)], axis=1).reshape(-1, d)
    U = (test @ body.modes.vectors.T).reshape(len(test), n, 3)
    exact = body.warp.apply(U) - U
    LU = np.stack([(L @ U[:, :, c].T).T for c in range(3)], axis=2)
    g = (body.warp.kernels.target(U) - LU).reshape(len(test), -1) @ basis
    galerkin = (np.linalg.solve(M, g.T).T @ basis.T).reshape(exact.shape)
    flat = exact.reshape(len(test), -1).T
    best = (basis @ (basis.T @ flat)).T.reshape(exact.shape)
    scale = np.linalg.norm(exact, axis=2).max(axis=1)
    X = body.rest_positions("tets")
    size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))

    def worst(approx: np.ndarray) -> tuple[float, float]:
        e = np.linalg.norm(approx - exact, axis=2).max(axis=1)
        return 100 * float((e / np.maximum(scale, 1e-300)).max()), 100 * float(e.max()) / size

    return (*worst(galerkin), worst(best)[0])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="the first scene only")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"# wiggly: a linear basis of the warp's nonlinear part ({os.cpu_count()} cores)\n")
    rng = np.random.default_rng(0)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        sources = {"critter": ("builtin:critter", 40, None),
                   "dinosaur (procedural, soft)": (dinosaur(rng, Path(tmp) / "d.obj"), 64, SOFT)}
        for mesh, kind_name in SCENES[:1] if args.quick else SCENES:
            path, resolution, material = sources[mesh]
            kind = next(k for k in KINDS if k.name == kind_name)
            model = load_model(str(path), resolution=resolution, cache_dir=False)
            body = prepare(model, n_modes=MODES, material=material, cache_dir=False)
            keys, end = keyframes(body, kind)
            problem = SpacetimeProblem(body, 0.0, end)
            solved = problem.solve(keys, warped=True).values
            linear = problem.solve(keys, warped=False).values
            label = f"{mesh}, {kind_name} ({body.tets.n_tets} tets)"
            for source, training in (
                ("random, 400 states", random_states(body, 400, rng)),
                ("the scene's, 120 + nodes", scene_states(linear, 120, rng)),
            ):
                for d in (20, 40, 80, 160):
                    if d <= len(training):
                        rel, absolute, best = errors(body, training, solved, d)
                        rows.append([label, source, d, f"{rel:.1f}", f"{absolute:.2f}",
                                     f"{best:.1f}"])
                print(f"(done: {label}, {source})", flush=True)
    print(table("Nonlinear part of W at the solved nodes: largest error of W_r",
                ["scene", "training states", "fields d", "% of largest |y|",
                 "% of the body's diagonal", "best projection, % of largest |y|"], rows))


if __name__ == "__main__":
    main()
