"""Issue 23: the critter bake in Blender against ``wiggly animate`` in the same run.

The bundled critter (3029 vertices) is built in Blender (PyPI ``bpy``, headless, from
``.venv-blender``) with the demo's groups as vertex groups (feet, back, tail tip, trunk) and
an Empty handle per group keyed like the demo's keys (crouch, take-off, landing 0.33 m
forward, tail wag; Moving Hold keys where the demo's feet are still). The shot is frames 1-61
at 24 fps (2.5 s), warped, at the demo's resolution, modes and material.

In one Blender process, alternately: the Bake operator (gathering the shot, exporting it,
``wiggly animate`` in its own process, reading the result and writing the Mesh Cache), and
``wiggly animate`` alone on the scene the add-on exported (what a user would run in a
terminal, the same command line). Blender's overhead is its own work in the Bake (gathering
the shot, writing the files, reading the result and writing the PC2: the Bake's time minus
its wiggly process's) against ``wiggly animate`` alone (issue floor: < 20 %); the ratio of the
two end-to-end medians is printed too, but on shared cores it is as noisy as the solve. A
first CLI run warms the tet-mesh cache and the numba kernels.

Run: ``.venv/bin/python benchmarks/bench_blender.py [--repeats N]`` (needs ``make blender``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from common import table
from wiggly.mesh.loading import load_mesh

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "blender" / "wiggly_addon.py"
FPS = 24


def z_up(v) -> np.ndarray:
    """wiggly's y-up metres as Blender's z-up coordinates."""
    v = np.asarray(v, float)
    return np.stack([v[..., 0], -v[..., 2], v[..., 1]], axis=-1)


def critter_spec() -> dict:
    """The critter's surface in Blender's axes, the demo's groups and handle keys."""
    surface = load_mesh("builtin:critter")
    X = surface.vertices  # y up, as the demo's selectors
    in_box = lambda lo, hi: np.flatnonzero(((X >= lo) & (X <= hi)).all(axis=1))  # noqa: E731
    in_sphere = lambda c, r: np.flatnonzero(np.linalg.norm(X - c, axis=1) <= r)  # noqa: E731
    groups = {
        "feet": in_box([-1.0, -0.01, -1.0], [1.0, 0.03, 1.0]),
        "back": in_sphere([0.0, 0.6, 0.0], 0.12),
        "tail_tip": in_sphere([-0.46, 0.70, 0.0], 0.06),
        "trunk": in_box([-0.27, -0.01, -0.2], [0.6, 0.9, 0.2]),
    }

    def key(t, offset=(0.0, 0.0, 0.0), still=False):
        return [1 + t * FPS, z_up(offset).tolist(), still]

    forward = (0.33, 0.0, 0.0)
    handles = {
        "feet": [key(0.0, still=True), key(0.45), key(0.7, still=True),
                 key(1.3, forward, True), key(2.5, forward, True)],
        "back": [key(0.45, (0.0, -0.1, 0.0))],
        "trunk": [key(0.75, (0.015, 0.041, 0.0)), key(1.25, (0.315, 0.041, 0.0))],
        "tail_tip": [key(1.75, (0.33, 0.0, 0.15)), key(2.05, (0.33, 0.0, -0.12))],
    }
    return {"vertices": z_up(X).tolist(), "faces": surface.faces.tolist(),
            "groups": {k: v.tolist() for k, v in groups.items()}, "handles": handles,
            "modes": 40, "resolution": 12, "young": 1.5e5, "alpha": 0.0, "beta": 0.004}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    python = os.environ.get("WIGGLY_BLENDER_PYTHON") or str(ROOT / ".venv-blender/bin/python")
    wiggly = shutil.which("wiggly", path=str(Path(sys.executable).parent)) or "wiggly"
    with tempfile.TemporaryDirectory(prefix="bench-blender-") as tmp:
        work = Path(tmp)
        (work / "critter.json").write_text(json.dumps(critter_spec()))
        options = {"critter": str(work / "critter.json"), "frames": [1, 61], "fps": FPS,
                   "repeat": args.repeats, "cli": True}
        (work / "options.json").write_text(json.dumps(options))
        done = subprocess.run([python, str(SCRIPT), "critter", str(work / "out.json"), wiggly,
                               str(work), str(work / "options.json")],
                              capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"Blender run failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
        seen = json.loads((work / "out.json").read_text())
    bake, cli = seen["bake_seconds"], seen["cli_seconds"]
    inner = [p[2] for p in seen["phases"]]
    own = [b - w for b, w in zip(bake, inner, strict=True)]
    rows = [[i + 1, b, *p[:2], w, p[3], o, c] for i, (b, p, w, o, c) in enumerate(
        zip(bake, seen["phases"], inner, own, cli, strict=True))]
    print(table(f"Critter bake, frames {seen['frames'][0]}-{seen['frames'][1]} at {FPS} fps "
                f"(2.5 s, warped, {seen['vertices']} vertices), Blender {seen['blender']}, "
                f"{os.cpu_count()} cores (shared)",
                ["run", "Bake operator (s)", "gather (s)", "write files (s)",
                 "wiggly in the Bake (s)", "read + PC2 (s)", "Blender's own work (s)",
                 "wiggly animate alone (s)"], rows))
    b, c, o = statistics.median(bake), statistics.median(cli), statistics.median(own)
    print(f"medians: Bake {b:.2f} s, wiggly animate alone {c:.2f} s (ratio - 1: "
          f"{100 * (b / c - 1):+.1f} %, noisy on shared cores); Blender's own work (the Bake "
          f"minus its wiggly process) {o:.2f} s = {100 * o / c:.1f} % of wiggly animate "
          "(issue floor: overhead < 20 %)")

if __name__ == "__main__":
    main()
