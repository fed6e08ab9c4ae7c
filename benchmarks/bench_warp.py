"""Timing of rotation-strain warping (Schulz et al. 2014, Theorem 2) on structured boxes.

Usage: ``PYTHONPATH=src python benchmarks/bench_warp.py [cells_per_axis ...]``
(default 8 15: about 3k and 20k tets). Prints the median of 5 runs (wall clock)
of: Warp construction, the factorization of its Laplacian alone, batched apply
per frame (100 frames in one call; also in process CPU time, which is steadier on
a shared machine; and with the vectorized numpy path instead of the compiled kernels, with
the ratio), a single-frame apply, the adjoint (vjp) per frame of a batch, and 40
directional derivatives (jvp) at one frame: a Jacobian against 40 basis fields.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from wiggly.linalg import factorize_spd
from wiggly.primitives import box_mesh
from wiggly.warp import Warp

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
    warp = Warp(V, T)
    numpy_warp = Warp(V, T, kernels="numpy")  # the vectorized numpy path, for the ratio
    laplacian = sp.csr_matrix(warp.laplacian)[1:, 1:]  # the gauge's one eliminated vertex
    U = 0.2 * rng.standard_normal((FRAMES, *V.shape))
    Y = rng.standard_normal((FRAMES, *V.shape))
    dU = rng.standard_normal((MODES, *V.shape))  # MODES directions at one frame
    at = np.repeat(U[:1], MODES, axis=0)
    warp.apply(U[:2])  # warm up
    batched = median_seconds(lambda: warp.apply(U)) / FRAMES
    numpy_batched = median_seconds(lambda: numpy_warp.apply(U), runs=3) / FRAMES
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
        "vjp ms/frame": 1e3 * median_seconds(lambda: warp.vjp(U, Y)) / FRAMES,
        f"jvp x{MODES} ms": 1e3 * median_seconds(lambda: warp.jvp(at, dU)),
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
