"""Issue 13 benchmark: driving a solve with a 10 s driver at 30 fps (300 frames) on the
20.4k-tet box of ``bench_warped.py`` (40 modes, a 20k-vertex surface).

The driver turns the box's left third (x < 0.4 m of 1.2 m) about the vertical by 20 degrees
at 1 Hz and bobs it by 3 cm at 2 Hz, bending the rest of the box with it; the left third is
keyed at every frame (300 partial keyframes, dense in time), the rest is free.  Reported:
reading nothing (the driver is made in memory), the enrichment of the basis with the
driver's shapes (``wiggly.drive.enrich``), the keyframes, and the linear and warped solves
(issue floors: linear < 1 s, warped < 10 s on 2 cores) with the warped solve's cost split
from ``anim.info``, for the plain 40 modes and the enriched basis.

Run: ``.venv/bin/python benchmarks/bench_drive.py [--quick]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(__file__))
from common import box_body, median_time, table
from wiggly.drive import Driver, driven_keyframes, enrich, following
from wiggly.drive.driver import polygon_edges
from wiggly.drive.secondary import secondary_motion
from wiggly.solve import SpacetimeProblem

FRAMES, FPS = 300, 30.0


def walk_driver(body) -> Driver:
    """300 frames: the left third turning and bobbing, the rest bending along (module doc)."""
    X = body.rest_positions()
    t = np.arange(FRAMES) / FPS
    pivot = np.array([0.2, 0.2, 0.2])
    w = np.clip((0.8 - X[:, 0]) / 0.4, 0.0, 1.0)[:, None]  # 1 on the left third, 0 past 0.8 m
    P = np.empty((FRAMES, len(X), 3))
    for k, tk in enumerate(t):
        R = Rotation.from_euler("y", 20.0 * np.sin(2 * np.pi * tk), degrees=True)
        moved = R.apply(X - pivot) + pivot + [0.0, 0.03 * np.sin(4 * np.pi * tk), 0.0]
        P[k] = w * moved + (1 - w) * X
    faces = body.surface.faces
    return Driver(t, P, faces, polygon_edges(faces), "bench (in memory)", "benchmark")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--secondary-only", action="store_true",
                    help="only the secondary-motion solve (physics = \"secondary\")")
    args = ap.parse_args(argv)
    repeats = 1 if args.quick else 3
    warnings.simplefilter("ignore")
    print(f"# wiggly drive benchmark ({os.cpu_count()} cores)\n")
    body = box_body(20400, surface_vertices=20000, cells=(34, 10, 10))
    _ = body.warp, body.coarse_level  # factored and built once per body, as in bench_warped
    driver = walk_driver(body)
    X = body.rest_positions()
    driven = np.flatnonzero(X[:, 0] < 0.4)
    end = float(driver.times[-1])
    print(f"body: {body.tets.n_tets} tets, surface {body.surface.n_vertices} vertices, "
          f"{body.r} modes; driver: {driver.n_frames} frames over {end:.2f} s; driven: "
          f"{len(driven)} surface vertices\n")

    if args.secondary_only:
        secondary(body, driver, driven, end, repeats)
        return
    t0 = time.perf_counter()
    rich = enrich(body, driver, driven)
    t_enrich = time.perf_counter() - t0
    _ = rich.warp, rich.coarse_level
    rows, splits = [], []
    for name, b in (("40 eigenmodes", body), (f"enriched ({rich.r} vectors)", rich)):
        t0 = time.perf_counter()
        keys = driven_keyframes(b, driver, driven, start=0.0, end=end)
        t_keys = time.perf_counter() - t0
        lin = median_time(lambda b=b, keys=keys: SpacetimeProblem(b, 0.0, end).solve(keys),
                          repeats=repeats)
        anim_l = SpacetimeProblem(b, 0.0, end).solve(keys)
        t0 = time.perf_counter()
        anim_w = SpacetimeProblem(b, 0.0, end).solve(keys, warped=True)
        t_warp = time.perf_counter() - t0
        f_l, f_w = following(anim_l), following(anim_w)
        info = anim_w.info
        rows.append([name, 1e3 * t_keys, lin, 1.0, t_warp, 10.0,
                     info.get("iterations"), 1e3 * f_l["max"], 1e3 * f_w["max"]])
        parts = [["linear start (unwarped targets)", info.get("linear_seconds", 0.0)]]
        for level, sub in (("coarse", info.get("coarse")), ("fine", info)):
            if sub:
                parts += [[f"{level}: {k}", v] for k, v in sub["seconds"].items()]
        parts.append(["total", info["solve_seconds"]])
        splits.append((name, parts))
    print(table("Driven solve, 300 keyframe times (10 s at 30 fps), 20.4k tets",
                ["basis", "keyframes ms", "linear s", "floor s", "warped s", "floor s",
                 "Newton iterations", "linear: driven max error mm",
                 "warped: driven max error mm"], rows))
    print(f"enrich (driver shapes, unwarped, Rayleigh-Ritz): {t_enrich:.2f} s, "
          f"{rich.r - body.r} shapes added\n")
    for name, parts in splits:
        print(table(f"Cost split of the warped solve ({name}), seconds", ["part", "s"], parts))
    secondary(body, driver, driven, end, repeats)


def secondary(body, driver, driven, end, repeats) -> None:
    """physics = "secondary" (the default since the keys model above): the driver as a
    moving rest state, the free parts' fixed-interface modes forced by its accelerations;
    one linear solve (issue floors: linear < 1 s, warped < 3 s on 2 cores).  The first run
    also computes the free modes (cached on disk by K, M and the held vertices) and compiles
    the unwarp kernel; the medians are of the runs after it."""
    rows = []
    for warped in (False, True):
        t0 = time.perf_counter()
        anim = secondary_motion(body, driver, driven, start=0.0, end=end, warped=warped)
        first = time.perf_counter() - t0
        med = median_time(lambda w=warped: secondary_motion(body, driver, driven, start=0.0,
                                                            end=end, warped=w),
                          repeats=repeats, warmup=0)
        rows.append(["warped" if warped else "linear", first, med, 3.0 if warped else 1.0,
                     anim.info["seconds"]["rig"], anim.info["free_modes"],
                     1e3 * following(anim)["max"]])
    print(table("Secondary motion, 300 driver frames (10 s at 30 fps), 20.4k tets",
                ["solve", "first s", "median s", "floor s", "rig (extension, unwarp) s",
                 "free modes", "driven max error mm"], rows))


if __name__ == "__main__":
    main()
