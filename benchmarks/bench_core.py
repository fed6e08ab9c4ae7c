"""Issue 2 benchmarks: prepare, re-solve, evaluation, and the frame-based baseline.

Run: ``.venv/bin/python benchmarks/bench_core.py [--quick]``.  Prints Markdown tables
(median of repeated runs; ratios against the baseline measured in the same run).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from common import box_body, box_model, median_time, table
from wiggly.body import prepare
from wiggly.fem import Material
from wiggly.framebased import solve_framebased
from wiggly.keyframes import Keyframe
from wiggly.linalg import available_backends
from wiggly.solve import SpacetimeProblem

_RNG = np.random.default_rng(0)


def bench_prepare(sizes: list[int], repeats: int) -> str:
    rows = []
    for n in sizes:
        model = box_model(n)
        t = median_time(
            lambda m=model: prepare(
                m, material=Material(2e5, 0.45, 1000.0), n_modes=40, cache_dir=False
            ),
            repeats=repeats,
            warmup=0,
        )
        target = 5.0 if n <= 25000 else 30.0
        rows.append(
            [
                model.tets.n_tets,
                model.tets.n_vertices * 3,
                40,
                t,
                target,
                "yes" if t < target else "NO",
            ]
        )
    return table(
        f"Prepare a body: assemble + 40 modes (backends: {available_backends()})",
        ["tets", "dofs", "modes", "median s", "target s", "met"],
        rows,
    )


def keyframes_10(body, T=2.0):
    """Ten keyframe times (on the 30 fps grid): rest start, then end groups moved around."""
    X = body.rest_positions()
    L = X[:, 0].max()
    left = np.flatnonzero(X[:, 0] < 0.1 * L)
    right = np.flatnonzero(X[:, 0] > 0.9 * L)
    mid = np.flatnonzero(np.abs(X[:, 0] - 0.5 * L) < 0.05 * L)
    keys = [Keyframe.rest(body, 0.0, np.arange(len(X)), still=True)]
    for j, t in enumerate(np.arange(1, 10) * 0.2):
        group = (left, right, mid)[j % 3]
        keys.append(
            Keyframe.offset(
                body, round(t, 6), group, (0.0, 0.15 * np.sin(3 * t), 0.08 * np.cos(2 * t))
            )
        )
    return keys


def bench_resolve(body, repeats: int) -> str:
    keys = keyframes_10(body)
    problem = SpacetimeProblem(body, 0.0, 2.0)
    problem.solve(keys)  # energy forms cached for these node times
    k = 5

    def one_change():
        keys[k] = Keyframe.offset(
            body, keys[k].time, keys[k].vertices, (0.0, _RNG.uniform(0, 0.2), 0.0)
        )
        return problem.solve(keys)

    t = median_time(one_change, repeats=repeats)
    t_cold = median_time(lambda: SpacetimeProblem(body, 0.0, 2.0).solve(keys), repeats=repeats)
    n_unknowns = one_change().info["unknowns"]
    return table(
        "Linear re-solve after changing one keyframe (40 modes, 10 keyframe times)",
        ["case", "unknowns", "median ms", "target ms"],
        [
            ["one keyframe changed", n_unknowns, 1e3 * t, 20],
            ["from scratch (new node times)", n_unknowns, 1e3 * t_cold, "-"],
        ],
    )


def bench_evaluate(body, repeats: int) -> str:
    anim = SpacetimeProblem(body, 0.0, 2.0).solve(keyframes_10(body))
    times = np.linspace(0.0, 2.0, 300)
    rows = []
    for dtype in (np.float64, np.float32):
        t = median_time(lambda d=dtype: anim.positions(times, "surface", dtype=d), repeats=repeats)
        rows.append([body.surface.n_vertices, 300, np.dtype(dtype).name, 1e3 * t, 200])
    t_modal = median_time(lambda: anim.modal(times), repeats=repeats)
    rows.append([body.surface.n_vertices, 300, "modal q(t) only", 1e3 * t_modal, "-"])
    return table(
        "Evaluate 300 frames on the embedded surface (linear)",
        ["surface vertices", "frames", "output", "median ms", "target ms"],
        rows,
    )


def bench_baseline(body, repeats: int) -> str:
    """Wiggly (exact in time) vs frame-based spacetime at 30 and 240 fps, same functional."""
    keys = keyframes_10(body)
    T = 2.0
    t_eval = np.arange(0, 61) / 30.0
    # reference: Richardson extrapolation of the first-order frame-based method
    t0 = time.perf_counter()
    _, q_a = solve_framebased(body, keys, 1920, 0.0, T)
    _, q_b = solve_framebased(body, keys, 3840, 0.0, T)
    q_ref = 2 * q_b[::128] - q_a[::64]  # at the 30 fps frames
    t_ref = time.perf_counter() - t0
    B = body.surface_basis

    def surface_error(q):
        d = (q - q_ref) @ B.T
        return float(np.max(np.abs(d)))

    scale = float(np.max(np.abs(q_ref @ B.T)))
    problem = SpacetimeProblem(body, 0.0, T, preroll=0.0)
    t_w = median_time(
        lambda: SpacetimeProblem(body, 0.0, T, preroll=0.0).solve(keys), repeats=repeats
    )
    anim = problem.solve(keys)
    err_w = surface_error(anim.modal(t_eval)[0])
    rows = [["wiggly splines (exact in time)", 1e3 * t_w, 1.0, err_w, err_w / scale]]
    for fps in (30, 240):
        t_f = median_time(
            lambda f=fps: solve_framebased(body, keys, f, 0.0, T), repeats=max(1, repeats // 2)
        )
        _, q = solve_framebased(body, keys, fps, 0.0, T)
        err = surface_error(q[:: fps // 30])
        rows.append([f"frame-based, {fps} fps", 1e3 * t_f, t_f / t_w, err, err / scale])
    return table(
        f"Wiggly vs frame-based spacetime (same functional, 40 modes, 10 keyframe times, "
        f"T = {T} s); error = max surface displacement error vs a Richardson-extrapolated "
        f"1920/3840 fps reference ({t_ref:.1f} s to compute); displacement scale "
        f"{scale:.3f} m",
        ["method", "median ms", "time / wiggly", "max error m", "relative error"],
        rows,
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="small sizes, few repeats")
    args = ap.parse_args(argv)
    repeats = 3 if args.quick else 7
    print(f"# wiggly core benchmarks ({os.cpu_count()} cores)\n")
    sizes = [21600] if args.quick else [21600, 103680]
    print(bench_prepare(sizes, repeats=1 if args.quick else 3))
    body = box_body(21600, surface_vertices=20000)
    print(
        f"body: {body.tets.n_tets} tets, {body.tets.n_vertices} vertices, surface "
        f"{body.surface.n_vertices} vertices, {body.r} modes\n"
    )
    print(bench_resolve(body, repeats=repeats * 3))
    print(bench_evaluate(body, repeats=repeats))
    print(bench_baseline(body, repeats=repeats))


if __name__ == "__main__":
    main()
