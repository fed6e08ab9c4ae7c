"""Issue 11: the warped solve converges on every scene a user writes.

A suite of scenes as a new user writes them (docs/scene-format.md: the default material,
gravity on, 30 modes), on bundled, public and freshly generated random meshes, small ones
(one level, exact Newton matrices) and bodies above 6,000 tets whose coarse meshes are
generated afresh (two levels):

* planted, still feet, then the top turned by 30 to 180 degrees;
* velocity keyframes mid-shot and at the end;
* a hop (the whole body up with an upward velocity, then landed);
* a body with fixed feet and its top turned;
* every damping regime (undamped, the default, heavy, overdamped).

Each row reports iterations (coarse + fine), time, whether the stopping rule held
(``converged``), the final Newton decrement against its tolerance, and the distance bound
the solver reports (largest vertex move of the final Newton step, relative to the body's
size).  A body's one-time warp set-up (the Laplacian's factor, and above 6,000 tets the
coarse mesh and its level), which its first warped solve would pay, is timed apart and
summarized at the end, as in ``bench_scenes.py``.

Run: ``.venv/bin/python benchmarks/bench_convergence.py [--quick] [--seed N]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, os.path.dirname(__file__))
from common import table
from public_meshes import public_meshes
from wiggly.body import Damping, fixed_from_surface, prepare
from wiggly.errors import WigglyInputError
from wiggly.keyframes import Keyframe
from wiggly.mesh import load_model
from wiggly.solve import SolveOptions, SpacetimeProblem

DAMPING = {
    "undamped": Damping(0.0, 0.0),
    "default": Damping(0.5, 0.002),
    "heavy": Damping(4.0, 0.02),
    "overdamped": Damping(20.0, 0.2),
}


@dataclass
class Scene:
    name: str
    keys: list
    end: float
    damping: str = "default"
    fixed: bool = False


def random_blob(rng: np.random.Generator, path: Path) -> Path:
    """A closed star-shaped blob: an icosphere with random smooth bumps (about 1 m)."""
    mesh = trimesh.creation.icosphere(4)
    n = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    r = np.ones(len(n))
    for _ in range(6):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        r += rng.uniform(0.1, 0.4) * np.exp(rng.uniform(2, 6) * (n @ d - 1))
    V = n * r[:, None] * np.array([0.5, rng.uniform(0.4, 0.8), 0.4])
    trimesh.Trimesh(V, mesh.faces).export(path)
    return path


def _capsule(p0, p1, radius: float, count: int = 12) -> trimesh.Trimesh:
    """A capsule whose axis runs from p0 to p1."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    mesh = trimesh.creation.capsule(height=float(np.linalg.norm(d)), radius=radius,
                                    count=(count, count))
    mesh.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], d / np.linalg.norm(d)))
    mesh.apply_translation(0.5 * (p0 + p1))
    return mesh


def random_creature(rng: np.random.Generator, path: Path) -> Path:
    """A body, four legs, a neck with a head and a tail, as overlapping capsules (their
    union is what fTetWild meshes: the surface intersects itself, as modelled ones do).
    Every limb starts inside the body, so the union is one piece."""
    L, H = rng.uniform(0.6, 1.0), rng.uniform(0.25, 0.4)
    y = 0.55
    parts = [_capsule([-L / 2, y, 0], [L / 2, y, 0], H / 2, 16)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            x, z = sx * L * 0.35, sz * H * 0.3
            parts.append(_capsule([x, y, z], [x, 0.08, z], rng.uniform(0.04, 0.07), 10))
    tip = np.array([L * 0.5 + rng.uniform(0.1, 0.25), y + H / 2 + rng.uniform(0.15, 0.35), 0])
    parts.append(_capsule([L * 0.35, y, 0], tip, 0.06, 10))
    head = trimesh.creation.icosphere(2, rng.uniform(0.1, 0.15))
    head.apply_translation(tip)
    parts.append(head)
    angle = rng.uniform(0.2, 1.0)
    length = rng.uniform(0.3, 0.6)
    parts.append(_capsule([-L * 0.4, y, 0],
                          [-L * 0.4 - length * np.cos(angle), y + length * np.sin(angle), 0],
                          0.03, 8))
    trimesh.util.concatenate(parts).export(path)
    return path


def scenes_for(body, quick: bool) -> list[Scene]:
    X = body.rest_positions()
    lo, hi = X.min(axis=0), X.max(axis=0)
    height = hi[1] - lo[1]
    feet = np.flatnonzero(X[:, 1] < lo[1] + 0.08 * height)
    top = np.flatnonzero(X[:, 1] > hi[1] - 0.25 * height)
    allv = np.arange(len(X))
    centre = X[top].mean(axis=0)

    def turn(degrees: float, at: float = 1.0) -> list:
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, at, feet),
            Keyframe.rigid(body, at, top, rotation=(0, np.radians(degrees), 0), center=centre),
        ]

    up = 0.3 * height
    out = [
        Scene("turn 30", turn(30.0), 2.0),
        Scene("turn 90", turn(90.0), 2.0),
        Scene("turn 150", turn(150.0), 2.0),
        Scene("turn 180", turn(180.0), 2.0),
        Scene("velocity mid-shot, no turn", [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, 0.7, feet),
            Keyframe.offset(body, 0.7, top, (0.0, 0.0, 0.0), velocity=(0.0, 1.5 * height, 0.0)),
        ], 1.5),
        Scene("velocity mid-shot, then a 90 degree turn", [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.offset(body, 0.5, top, (0.0, 0.1 * height, 0.0),
                            velocity=(0.5 * height, 0.0, 0.0)),
            *turn(90.0, 1.2)[1:],
        ], 2.0),
        Scene("velocity at the end", [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.offset(body, 1.5, top, (0.0, 0.0, 0.2 * height),
                            velocity=(0.0, 0.0, height)),
        ], 1.5),
        Scene("hop", [
            Keyframe.rest(body, 0.0, allv, still=True),
            Keyframe.offset(body, 0.5, feet, (0.0, up, 0.0), velocity=(0.0, 2 * up, 0.0)),
            Keyframe.rest(body, 1.2, feet, still=True),
        ], 1.6),
        Scene("hop with a 180 degree turn", [
            Keyframe.rest(body, 0.0, allv, still=True),
            Keyframe.offset(body, 0.5, feet, (0.0, up, 0.0), velocity=(0.0, 2 * up, 0.0)),
            Keyframe.rigid(body, 1.2, feet, rotation=(0, np.pi, 0)),
        ], 1.6),
        Scene("fixed feet, top turned 90", [
            Keyframe.rigid(body, 1.0, top, rotation=(0, np.radians(90.0), 0), center=centre),
        ], 2.0, fixed=True),
    ]
    for regime in ("undamped", "heavy", "overdamped"):
        out.append(Scene(f"turn 120, {regime}", turn(120.0), 2.0, damping=regime))
    return out[::3] if quick else out


def bodies(quick: bool, seed: int, folder: Path):
    """(name, model path or spec, resolution) of the suite's meshes."""
    rng = np.random.default_rng(seed)
    out = [
        ("critter", "builtin:critter", None),
        ("critter, fine (two levels)", "builtin:critter", 32),
        ("random blob", str(random_blob(rng, folder / "blob.obj")), None),
        ("random creature (two levels)", str(random_creature(rng, folder / "creature.obj")), 30),
    ]
    meshes, skipped = public_meshes()
    for err in skipped:
        print(f"(public meshes skipped: {err})")
    wanted = {"elephant": None, "bunny": None, "camel": 28}
    for m in meshes:
        if m.name in wanted:
            out.append((f"{m.name} ({m.source})", str(m.path), wanted[m.name]))
    return out[:3] if quick else out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seed", type=int, default=int(time.time()) % 100000)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"# wiggly warped-solve convergence suite ({os.cpu_count()} cores, seed "
          f"{args.seed})\n")
    options = SolveOptions()
    rows, times, setups = [], [], []
    converged = total = 0
    with tempfile.TemporaryDirectory() as tmp:
        for name, source, resolution in bodies(args.quick, args.seed, Path(tmp)):
            # fresh coarse meshes: bodies are prepared without the on-disk cache
            cache = False  # fresh modes and, above 6000 tets, a fresh coarse mesh
            try:
                model = load_model(source, resolution=resolution, cache_dir=False)
                first = prepare(model, n_modes=30, cache_dir=cache)
            except WigglyInputError as err:  # counted as a failure of the suite
                total += 1
                rows.append([name, "-", "(refused)", "-", "-", "NO", "-", "-", str(err)[:60]])
                print(f"  {name}: refused: {err}", file=sys.stderr, flush=True)
                continue
            prepared: dict = {}
            for scene in scenes_for(first, args.quick):
                key = (scene.damping, scene.fixed)
                if key not in prepared:
                    fixed = None
                    if scene.fixed:
                        X = model.surface.vertices
                        feet = np.flatnonzero(X[:, 1] < X[:, 1].min() + 0.08 * np.ptp(X[:, 1]))
                        fixed = fixed_from_surface(model, feet)
                    prepared[key] = prepare(model, n_modes=30, damping=DAMPING[scene.damping],
                                            fixed_vertices=fixed, cache_dir=cache)
                    # the body's one-time warp set-up (Laplacian factor, coarse mesh and
                    # level), paid by its first warped solve: timed apart, as the modes are
                    t0 = time.perf_counter()
                    _ = prepared[key].fine_level, prepared[key].coarse_level
                    setups.append(time.perf_counter() - t0)
                body = prepared[key]
                keys = next(kf for kf in scenes_for(body, False) if kf.name == scene.name).keys
                size = float(np.linalg.norm(np.ptp(body.rest_positions(), axis=0)))
                t0 = time.perf_counter()
                anim = SpacetimeProblem(body, 0.0, scene.end).solve(
                    keys, warped=True, options=options
                )
                seconds = time.perf_counter() - t0
                info = anim.info
                its = (f"{info['coarse']['iterations']} + {info['iterations']}"
                       if "coarse" in info else str(info["iterations"]))
                ratio = info["newton_decrement"] / (options.tolerance * max(info["objective"],
                                                                            1e-300))
                bound = info["distance_bound"]
                total += 1
                converged += bool(info["converged"])
                times.append(seconds)
                rows.append([
                    name, body.tets.n_tets, scene.name, scene.damping, its,
                    "yes" if info["converged"] else "NO", seconds, ratio,
                    "-" if bound is None else bound / size,
                ])
                print(f"  {name} / {scene.name}: {its} iterations, {seconds:.2f} s, "
                      f"converged {info['converged']}", file=sys.stderr, flush=True)
    print(table(
        "Warped solves: every scene must meet the stopping rule (decrement <= 1e-8 F)",
        ["mesh", "tets", "scene", "damping", "iterations (coarse + fine)", "converged", "s",
         "decrement / (tol F)", "distance bound / size"],
        rows,
    ))
    print(f"converged: {converged} of {total} scenes; median time per scene "
          f"{statistics.median(times):.2f} s (max {max(times):.2f} s); each body's one-time "
          f"warp set-up (not in the scenes' times): median {statistics.median(setups):.2f} s "
          f"(max {max(setups):.2f} s, {len(setups)} bodies)")


if __name__ == "__main__":
    main()
