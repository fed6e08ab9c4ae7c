"""Timing of rotation-strain warping (Schulz et al. 2014, Theorem 2) on structured boxes.

Usage: ``PYTHONPATH=src python benchmarks/bench_warp.py [cells_per_axis ...]``
(default 8 15: about 3k and 20k tets). Prints the median of 5 runs (wall clock)
of: Warp construction, the factorization of its Laplacian alone, batched apply
per frame (100 frames in one call; also in process CPU time, which is steadier on
a shared machine; and with the vectorized numpy path instead of the compiled kernels, with
the ratio), a single-frame apply, and the Jacobian against r = 40 basis fields.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from wiggly.linalg import factorize_spd
from wiggly.primitives import box_mesh
from wiggly.warp import Warp, tet_gradient_operator

RUNS = 5
FRAMES = 100
MODES = 40


def median_seconds(
    fn: Callable[[], object], runs: int = RUNS, clock: Callable[[], float] = time.perf_counter
) -> float:
    times = []
    for _ in range(runs):
        start = clock()
        fn()
        times.append(clock() - start)
    return float(np.median(times))


def bench(cells: int) -> dict[str, float]:
    V, T = box_mesh((cells, cells, cells))
    rng = np.random.default_rng(0)
    G, vol = tet_gradient_operator(V, T)
    laplacian = sp.csr_matrix(G.T @ sp.diags(np.repeat(vol, 3)) @ G)[1:, 1:]
    warp = Warp(V, T)
    U = 0.2 * rng.standard_normal((FRAMES, *V.shape))
    basis = rng.standard_normal((len(V), 3, MODES))
    warp.apply(U[:2])  # warm up
    batched = median_seconds(lambda: warp.apply(U)) / FRAMES
    compiled = warp.compiled
    warp.compiled = False  # the vectorized numpy path, for the ratio
    numpy_batched = median_seconds(lambda: warp.apply(U), runs=3) / FRAMES
    warp.compiled = compiled
    return {
        "verts": len(V),
        "tets": len(T),
        "build ms": 1e3 * median_seconds(lambda: Warp(V, T)),
        "factor ms": 1e3 * median_seconds(lambda: factorize_spd(laplacian)),
        "apply ms/frame": 1e3 * batched,
        "frames/s": 1.0 / batched,
        "numpy ms/frame": 1e3 * numpy_batched,
        "numpy/compiled": numpy_batched / batched,
        "apply cpu ms/fr": 1e3
        * median_seconds(lambda: warp.apply(U), clock=time.process_time)
        / FRAMES,
        "apply 1 frame ms": 1e3 * median_seconds(lambda: warp.apply(U[0])),
        f"jacobian r={MODES} ms": 1e3 * median_seconds(lambda: warp.jacobian(U[0], basis)),
    }


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    sizes = [int(a) for a in args] or [8, 15]
    rows = [bench(c) for c in sizes]
    keys = list(rows[0])
    print(" | ".join(f"{k:>14}" for k in keys))
    for row in rows:
        print(" | ".join(f"{row[k]:>14.0f}" if row[k] >= 100 else f"{row[k]:>14.2f}" for k in keys))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
