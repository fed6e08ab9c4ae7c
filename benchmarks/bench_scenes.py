"""Issue 22: how fast the warped solve is on scenes as users write them, and how its cost
per Newton iteration scales with the fine mesh.

**Suite.**  At least 30 scenes on 9 meshes of about 3k-40k tets, every mesh made afresh on
each run (fTetWild is run without the on-disk cache, procedural bodies are drawn from the
seed, and modes and coarse meshes are computed anew):

* public meshes (:mod:`public_meshes`): CGAL's camel, diplodocus (a long neck and tail),
  elephant, armadillo and cow, npm's Stanford bunny;
* the bundled critter;
* procedural soft long bodies made of capsules: a dinosaur with a long neck and tail, and a
  random creature (:func:`bench_convergence.random_creature`), at half the default stiffness.

Each mesh gets four of twelve scene kinds in turn, so each kind runs on three meshes:
planted feet with the top turned (up to 180 degrees), velocity keyframes at the start, mid-shot
and at the end, hops with turns of 0, 90 and 180 degrees, fixed feet, and every damping
regime.  Each row gives the iterations (coarse + fine), the solve time, whether the
stopping rule held and the final Newton decrement against its tolerance, and at the
keyframe times how far the solution's linear states turn single tets (the warp wraps
rotations past pi) and the share of tets its warped motion turns inside out
(:meth:`wiggly.Animation.folds`); the summary gives the median and maximum time and the
issue's floors.

**Scaling.**  One scene (a bar bent by 90 degrees at one end with a velocity key mid-shot)
on the same box surface embedded in tet meshes of about 5k, 20k and 80k tets (``--large``
adds 200k: its modes take minutes), with the time per Newton iteration of each level.

Run: ``.venv/bin/python benchmarks/bench_scenes.py [--seed N] [--quick] [--only suite|scaling]
[--large]``.  ``--quick`` runs one scene per mesh and the scaling table up to 20k tets.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, os.path.dirname(__file__))
from bench_convergence import DAMPING, _capsule, random_creature
from common import box_model, table
from public_meshes import public_meshes
from wiggly.body import Body, fixed_from_surface, prepare
from wiggly.errors import WigglyInputError
from wiggly.fem import Material
from wiggly.keyframes import Keyframe
from wiggly.mesh import Model, load_model
from wiggly.solve import Animation, SolveOptions, SpacetimeProblem
from wiggly.solve.animation import rotation_angles

MODES = 30
SOFT = Material(young=1e5)


@dataclass(frozen=True)
class Kind:
    name: str
    damping: str = "default"
    fixed: bool = False


KINDS = [
    Kind("turn 120"),
    Kind("velocity mid-shot, then a 90 degree turn"),
    Kind("velocity at the start"),
    Kind("velocity at the end"),
    Kind("hop"),
    Kind("hop with a 90 degree turn"),
    Kind("hop with a 180 degree turn"),
    Kind("fixed feet, top turned 90", fixed=True),
    Kind("turn 180, undamped", "undamped"),
    Kind("turn 90, heavy damping", "heavy"),
    Kind("turn 150, overdamped", "overdamped"),
    Kind("head turned 86 (about the long axis)"),
]


def keyframes(body: Body, kind: Kind) -> tuple[list[Keyframe], float]:
    """The keyframes and end time of a scene kind, as a user sets them: feet are the lowest
    8 % of the surface, the top its highest quarter."""
    X = body.rest_positions()
    lo, hi = X.min(axis=0), X.max(axis=0)
    height = hi[1] - lo[1]
    feet = np.flatnonzero(X[:, 1] < lo[1] + 0.08 * height)
    top = np.flatnonzero(X[:, 1] > hi[1] - 0.25 * height)
    allv = np.arange(len(X))
    centre = X[top].mean(axis=0)
    long_axis = int(np.argmax([hi[0] - lo[0], 0.0, hi[2] - lo[2]]))
    up = 0.3 * height

    def planted(degrees: float, at: float = 1.0, axis: int = 1) -> list[Keyframe]:
        rotation = np.zeros(3)
        rotation[axis] = np.radians(degrees)
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, at, feet),
            Keyframe.rigid(body, at, top, rotation=rotation, center=centre),
        ]

    def hop(degrees: float) -> list[Keyframe]:
        return [
            Keyframe.rest(body, 0.0, allv, still=True),
            Keyframe.offset(body, 0.5, feet, (0.0, up, 0.0), velocity=(0.0, 2 * up, 0.0)),
            Keyframe.rigid(body, 1.2, feet, rotation=(0, np.radians(degrees), 0)),
        ]

    name = kind.name
    if name == "turn 120":
        return planted(120.0), 2.0
    if name == "velocity mid-shot, then a 90 degree turn":
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.offset(body, 0.5, top, (0.0, 0.1 * height, 0.0),
                            velocity=(0.5 * height, 0.0, 0.0)),
            *planted(90.0, 1.2)[1:],
        ], 2.0
    if name == "velocity at the start":
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.rest(body, 0.0, top, velocity=(0.0, 0.0, 1.5 * height)),
            Keyframe.rest(body, 1.0, feet),
        ], 1.5
    if name == "velocity at the end":
        return [
            Keyframe.rest(body, 0.0, feet, still=True),
            Keyframe.offset(body, 1.5, top, (0.0, 0.0, 0.2 * height),
                            velocity=(0.0, 0.0, height)),
        ], 1.5
    if name.startswith("hop"):
        degrees = {"hop": 0.0, "hop with a 90 degree turn": 90.0}.get(name, 180.0)
        return hop(degrees), 1.6
    if name == "fixed feet, top turned 90":
        return [Keyframe.rigid(body, 1.0, top, rotation=(0, np.radians(90.0), 0),
                               center=centre)], 2.0
    if name.startswith("turn "):
        return planted(float(name.split()[1].rstrip(","))), 2.0
    if name.startswith("head turned 86"):
        return planted(86.0, axis=long_axis), 2.0
    raise ValueError(name)


def dinosaur(rng: np.random.Generator, path: Path) -> Path:
    """A sauropod of capsules: a body on four legs, a long neck rising to a head and a long
    tapering tail (about 3 m long; their union is what fTetWild meshes)."""
    L, H, y = rng.uniform(0.9, 1.1), rng.uniform(0.35, 0.45), 0.8
    parts = [_capsule([-L / 2, y, 0], [L / 2, y, 0], H / 2, 16)]
    for sx in (-1, 1):
        for sz in (-1, 1):
            x, z = sx * L * 0.35, sz * H * 0.3
            parts.append(_capsule([x, y, z], [x, 0.1, z], 0.09, 10))
    neck = [L * 0.4, y, 0.0]
    for _ in range(3):  # three segments, curving up
        nxt = [neck[0] + rng.uniform(0.25, 0.35), neck[1] + rng.uniform(0.2, 0.35), 0.0]
        parts.append(_capsule(neck, nxt, 0.07, 10))
        neck = nxt
    head = trimesh.creation.icosphere(2, 0.1)
    head.apply_translation(neck)
    parts.append(head)
    tail, radius = [-L * 0.45, y, 0.0], 0.08
    for _ in range(4):  # drooping, tapering
        nxt = [tail[0] - rng.uniform(0.25, 0.35), tail[1] - rng.uniform(0.0, 0.1), 0.0]
        parts.append(_capsule(tail, nxt, radius, 10))
        tail, radius = nxt, radius * 0.75
    trimesh.util.concatenate(parts).export(path)
    return path


@dataclass
class Mesh:
    name: str
    make: Callable[[], Model]
    material: Material | None = None


def meshes(seed: int, folder: Path) -> list[Mesh]:
    """The suite's meshes, each made afresh when ``make`` is called."""
    rng = np.random.default_rng(seed)
    dino = dinosaur(rng, folder / "dinosaur.obj")
    creature = random_creature(rng, folder / "creature.obj")

    def surface(path: Path | str, resolution: int | None) -> Callable[[], Model]:
        return lambda: load_model(str(path), resolution=resolution, cache_dir=False)

    out = [
        Mesh("critter", surface("builtin:critter", 40)),
        Mesh("dinosaur (procedural, soft)", surface(dino, 64), SOFT),
        Mesh("creature (procedural, soft)", surface(creature, 36), SOFT),
    ]
    found, skipped = public_meshes()
    for err in skipped:
        print(f"(public meshes skipped: {err})")
    wanted = {"camel": 32, "diplodocus": 48, "elephant": 40, "armadillo": 36, "bunny": None,
              "cow": 48}
    for m in found:
        if m.name in wanted:
            out.append(Mesh(f"{m.name} ({m.source})", surface(m.path, wanted[m.name])))
    return out


class Clock:
    """Timestamps of the solve's iterations (:attr:`SolveOptions.callback`)."""

    def __init__(self) -> None:
        self.stamps: list[float] = []

    def __call__(self, count: int) -> None:
        self.stamps.append(time.perf_counter())


def timed_solve(
    body: Body, keys: list[Keyframe], end: float
) -> tuple[dict, float, list, Animation]:
    """A cold warped solve: its report, seconds, the iteration timestamps from its start,
    and the motion."""
    clock = Clock()
    options = SolveOptions(callback=clock)
    t0 = time.perf_counter()
    anim = SpacetimeProblem(body, 0.0, end).solve(keys, warped=True, options=options)
    seconds = time.perf_counter() - t0
    return anim.info, seconds, [s - t0 for s in clock.stamps], anim


def wound(body: Body, anim: Animation, keys: list[Keyframe]) -> tuple[float, float]:
    """How far the solution's linear states turn single tets, at the keyframe times: the
    largest share of tets (%) whose rotation vector (the skew part of the displacement
    gradient, which the warp exponentiates) is longer than pi, and the longest one (rad).
    Past pi the warp's rotation wraps around: W is periodic there, and its objective has
    nearby minima and narrow, curved valleys."""
    q = anim.modal(sorted({k.time for k in keys}))[0]  # the linear states u = Phi q
    share, longest = 0.0, 0.0
    for u in (q @ body.basis("tets").T).reshape(len(q), -1, 3):
        angle = rotation_angles(body.fine_level.warp.gradient, u)
        share, longest = max(share, 100 * float(np.mean(angle > np.pi))), max(
            longest, float(angle.max()))
    return share, longest


def iteration_counts(info: dict) -> tuple[int, int]:
    return (info["coarse"]["iterations"] if "coarse" in info else 0), info["iterations"]


def suite(args, folder: Path) -> None:
    options = SolveOptions()
    rows, times, its_all = [], [], []
    converged = total = 0
    for i, mesh in enumerate(meshes(args.seed, folder)):
        try:
            model = mesh.make()
        except WigglyInputError as err:
            print(f"  {mesh.name}: refused: {err}", file=sys.stderr, flush=True)
            rows.append([mesh.name, "-", "-", "(refused)", "-", "NO", "-", "-", "-", "-", "-",
                         "-", "-"])
            total += 1
            continue
        kinds = [KINDS[(4 * i + j) % len(KINDS)] for j in range(1 if args.quick else 4)]
        prepared: dict = {}
        for kind in kinds:
            key = (kind.damping, kind.fixed)
            if key not in prepared:
                fixed = None
                if kind.fixed:
                    X = model.surface.vertices
                    feet = np.flatnonzero(X[:, 1] < X[:, 1].min() + 0.08 * np.ptp(X[:, 1]))
                    fixed = fixed_from_surface(model, feet)
                prepared[key] = prepare(model, n_modes=MODES, material=mesh.material,
                                        damping=DAMPING[kind.damping], fixed_vertices=fixed,
                                        cache_dir=False)
                # the warps, their factorizations and the coarse mesh are made with the body
                _ = prepared[key].coarse_level, prepared[key].fine_level
            body = prepared[key]
            keys, end = keyframes(body, kind)
            info, seconds, _, anim = timed_solve(body, keys, end)
            share, longest = wound(body, anim, keys)
            folded = max(100 * row["share"] for row in anim.folds())
            coarse, fine = iteration_counts(info)
            ratio = info["newton_decrement"] / (options.tolerance * max(info["objective"], 1e-300))
            total += 1
            converged += bool(info["converged"])
            times.append(seconds)
            its_all.append(coarse + fine)
            rows.append([mesh.name, body.tets.n_tets, body.coarse_level.warp.n_tets,
                         kind.name, f"{coarse} + {fine}",
                         "yes" if info["converged"] else "NO", seconds, ratio,
                         info["seconds"].get("newton", 0.0), info["seconds"].get("W", 0.0)
                         + info["seconds"].get("vjp", 0.0), share, longest, folded])
            print(f"  {mesh.name} ({body.tets.n_tets} tets) / {kind.name}: {coarse} + {fine} "
                  f"iterations, {seconds:.2f} s, converged {info['converged']}",
                  file=sys.stderr, flush=True)
    print(table(
        "Warped solves of scenes as users write them (cold, 30 modes)",
        ["mesh", "tets", "coarse tets", "scene", "iterations (coarse + fine)", "converged", "s",
         "decrement / (tol F)", "fine Newton matrices s", "fine W + vjp s",
         "tets turned past pi, % (worst key time)", "longest tet rotation, rad",
         "tets inside out in the warped motion, % (worst time checked)"],
        rows,
    ))
    med, worst = statistics.median(times), max(times)
    print(f"converged: {converged} of {total} scenes; time per scene: median {med:.2f} s, "
          f"max {worst:.2f} s; iterations: median {statistics.median(its_all):.0f}, "
          f"max {max(its_all)}")
    print(f"floors: median < 0.5 s {'met' if med < 0.5 else 'NOT met'}; max < 3 s "
          f"{'met' if worst < 3 else 'NOT met'}; <= 30 iterations "
          f"{'met' if max(its_all) <= 30 else 'NOT met'}; 100 % converged "
          f"{'met' if converged == total else 'NOT met'}\n")


def bar_keys(body: Body) -> tuple[list[Keyframe], float]:
    """The scaling scene: the bar's left end planted, a velocity key on its right end
    mid-shot, then the right end bent by 90 degrees about z."""
    X = body.rest_positions()
    L = X[:, 0].max()
    left = np.flatnonzero(X[:, 0] < 0.1 * L)
    right = np.flatnonzero(X[:, 0] > 0.9 * L)
    return [
        Keyframe.rest(body, 0.0, left, still=True),
        Keyframe.rest(body, 0.0, right, still=True),
        Keyframe.offset(body, 0.5, right, (0.0, 0.1 * L, 0.0), velocity=(0.0, 0.0, 0.5 * L)),
        Keyframe.rest(body, 1.2, left),
        Keyframe.rigid(body, 1.2, right, rotation=(0, 0, np.pi / 2)),
    ], 2.0


def scaling(args) -> None:
    sizes = [5000, 20000] if args.quick else [5000, 20000, 80000]
    if args.large:
        sizes.append(200000)
    rows = []
    for n in sizes:
        t0 = time.perf_counter()
        body = prepare(box_model(n, surface_vertices=20000), n_modes=MODES,
                       damping=DAMPING["default"], cache_dir=False)
        _ = body.coarse_level, body.warp
        setup = time.perf_counter() - t0
        keys, end = bar_keys(body)
        info, seconds, stamps, _ = timed_solve(body, keys, end)
        coarse, fine = iteration_counts(info)
        t_coarse = stamps[coarse - 1] if coarse else 0.0
        per_coarse = t_coarse / coarse if coarse else float("nan")
        per_fine = (seconds - t_coarse) / fine if fine else float("nan")
        rows.append([body.tets.n_tets, f"{coarse} + {fine}",
                     "yes" if info["converged"] else "NO", seconds, per_coarse * 1e3,
                     per_fine * 1e3, setup])
        print(f"  scaling {body.tets.n_tets} tets: {coarse} + {fine} iterations, "
              f"{seconds:.2f} s", file=sys.stderr, flush=True)
    print(table(
        "Scaling: one scene on the same box surface (1.2 x 0.4 x 0.4 m, 30 modes)",
        ["tets", "iterations (coarse + fine)", "converged", "solve s",
         "ms per coarse iteration", "ms per fine iteration (incl. its level's start)",
         "set-up s (modes, coarse mesh; not in the solve)"],
        rows,
    ))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--large", action="store_true", help="add the 200k-tet scaling row")
    ap.add_argument("--only", choices=["suite", "scaling"])
    ap.add_argument("--seed", type=int, default=int(time.time()) % 100000)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"# wiggly warped solve on user scenes ({os.cpu_count()} cores, seed {args.seed})\n")
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "suite"):
            suite(args, Path(tmp))
        if args.only in (None, "scaling"):
            scaling(args)


if __name__ == "__main__":
    main()
