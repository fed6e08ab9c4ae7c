"""Issue 3 benchmarks: warped (nonlinear) solve and warped playback.

Run: ``.venv/bin/python benchmarks/bench_warped.py [--quick]``.  Median of repeated runs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(__file__))
from common import box_body, median_time, table
from wiggly.keyframes import Keyframe
from wiggly.solve import SpacetimeProblem

_RNG = np.random.default_rng(0)


def swing_keys(body):
    """Ten keyframe times, as an animator would set them: rest at t = 0, then the whole body
    turning (up to 120 degrees about y) and travelling, and one end swinging +-30 degrees
    about its attachment on top of the body's motion (consistent, reachable targets)."""
    X = body.rest_positions()
    L = X[:, 0].max()
    end = np.flatnonzero(X[:, 0] > 0.8 * L)
    hinge = np.array([0.8 * L, X[:, 1].mean(), X[:, 2].mean()])
    centre = X.mean(axis=0)
    keys = [Keyframe.rest(body, 0.0, np.arange(len(X)), still=True)]
    for j, t in enumerate(np.arange(1, 10) * 0.2):
        t = round(float(t), 6)
        body_rot = Rotation.from_euler("y", 120.0 * t / 1.8, degrees=True)
        shift = np.array([0.3 * t, 0.0, 0.0])
        if j % 2 == 0:  # whole body pose
            x = body_rot.apply(X - centre) + centre + shift
            keys.append(Keyframe(t, np.arange(len(X)), x))
        else:  # end swing about the hinge, carried by the body's motion
            swing = Rotation.from_euler("z", 30.0 * np.sin(4 * t), degrees=True)
            local = swing.apply(X[end] - hinge) + hinge
            keys.append(Keyframe(t, end, body_rot.apply(local - centre) + centre + shift))
    return keys


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    repeats = 3 if args.quick else 7
    warnings.simplefilter("ignore")
    print(f"# wiggly warped benchmarks ({os.cpu_count()} cores)\n")
    # the 20k-tet body: 34 x 10 x 10 cubes of 6 tets = 20,400 tets
    body = box_body(20400, surface_vertices=20000, cells=(34, 10, 10))
    t0 = time.perf_counter()
    _ = body.warp  # factor the warp's Poisson system once per body
    t_warp = time.perf_counter() - t0
    print(
        f"body: {body.tets.n_tets} tets, {body.tets.n_vertices} vertices, surface "
        f"{body.surface.n_vertices} vertices, {body.r} modes; warp factorization "
        f"{1e3 * t_warp:.0f} ms (once per body)\n"
    )
    keys = swing_keys(body)

    t0 = time.perf_counter()
    coarse = body.coarse_level  # the coarse mesh (fTetWild, cached on disk) and its warp
    t_coarse = time.perf_counter() - t0
    print(
        f"coarse level: {coarse.warp.n_tets} tets, {coarse.warp.n_vertices} "
        f"vertices; {1e3 * t_coarse:.0f} ms (once per body)\n"
    )

    def cold():
        return SpacetimeProblem(body, 0.0, 2.0).solve(keys, warped=True)

    # the first solve also loads the compiled kernels from numba's cache and builds the
    # per-group selections and Grams (cached on the body)
    t0 = time.perf_counter()
    cold()
    t_first = time.perf_counter() - t0
    runs = []

    def cold_recorded():
        anim = cold()
        runs.append(anim.info)
        return anim

    t_cold = median_time(cold_recorded, repeats=repeats)
    anim = cold()
    info = anim.info
    problem = SpacetimeProblem(body, 0.0, 2.0)
    prev = problem.solve(keys, warped=True)
    k = 4
    warm_runs = []

    def change_one():
        nonlocal prev
        kf = keys[k]
        jitter = Rotation.from_euler("z", _RNG.uniform(-10, 10), degrees=True)
        c = kf.position.mean(axis=0)
        keys[k] = Keyframe(kf.time, kf.vertices, jitter.apply(kf.position - c) + c)
        prev = problem.solve(keys, warped=True, warm_start=prev.warm_start)
        warm_runs.append(prev.info)
        return prev

    t_warm = median_time(change_one, repeats=repeats)
    t_lin = median_time(lambda: SpacetimeProblem(body, 0.0, 2.0).solve(keys), repeats=repeats)
    lin = SpacetimeProblem(body, 0.0, 2.0).solve(keys)
    res_w = max(r["position_rms"] for r in anim.constraint_residuals())
    res_l = max(r["position_rms"] for r in lin.constraint_residuals())

    def its(i):
        return f"{i['coarse']['iterations']} + {i['iterations']}" if "coarse" in i else str(
            i["iterations"]
        )

    print(
        table(
            "Warped solve (20k tets, 40 modes, 10 keyframe times: turns up to 120 deg, "
            "+-30 deg swings)",
            ["case", "median ms", "target ms", "ratio to target", "iterations (coarse + fine)",
             "max key RMS m"],
            [
                ["linear solve (for reference)", 1e3 * t_lin, "-", "-", 0, res_l],
                ["warped, from scratch", 1e3 * t_cold, 500, t_cold / 0.5, its(info), res_w],
                ["warped, from scratch, first solve of the process (loads the compiled kernels, "
                 "builds the per-group matrices)", 1e3 * t_first,
                 "-", "-", "-", "-"],
                ["warped, after changing one keyframe (warm start)", 1e3 * t_warm, 200,
                 t_warm / 0.2, its(prev.info), "-"],
            ],
        )
    )

    def split(infos):
        def med(get):
            return 1e3 * statistics.median(get(i) for i in infos)

        rows = [["linear start (unwarped targets)", med(lambda i: i["linear_seconds"]), "-"]]
        for level, get in (("coarse", lambda i: i["coarse"]), ("fine", lambda i: i)):
            if level == "coarse" and "coarse" not in infos[0]:
                continue
            ev = get(infos[-1])["evaluations"]
            rows += [
                [f"{level}: W and DW v ({ev['W']} node evaluations)",
                 med(lambda i, g=get: g(i)["seconds"]["W"]), ev["W"]],
                [f"{level}: vector-Jacobian products, residuals ({ev['vjp']} nodes)",
                 med(lambda i, g=get: g(i)["seconds"]["vjp"]), ev["vjp"]],
                [f"{level}: Newton matrices (coarse mesh; {ev['newton']} node blocks)",
                 med(lambda i, g=get: g(i)["seconds"]["newton"]), ev["newton"]],
                [f"{level}: banded solves, trust-region steps",
                 med(lambda i, g=get: g(i)["seconds"]["solve"]), "-"],
            ]
        rows.append(["total", med(lambda i: i["solve_seconds"]), "-"])
        return rows

    print(table("Cost split of a cold warped solve (medians)", ["part", "ms", "count"],
                split(runs)))
    print(table("Cost split of a warm re-solve (medians)", ["part", "ms", "count"],
                split(warm_runs)))
    frames = np.linspace(0.0, 2.0, 300)
    t_tets = median_time(lambda: anim.positions(frames, "tets", dtype=np.float32), repeats=3)
    t_surf = median_time(lambda: anim.positions(frames, "surface", dtype=np.float32), repeats=3)
    print(
        table(
            "Warped playback, 300 frames",
            ["mesh", "vertices", "median s", "frames/s", "target frames/s"],
            [
                ["tet mesh", body.tets.n_vertices, t_tets, 300 / t_tets, 200],
                ["embedded surface", body.surface.n_vertices, t_surf, 300 / t_surf, 200],
            ],
        )
    )


if __name__ == "__main__":
    main()
