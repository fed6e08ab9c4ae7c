"""Public meshes with a default scene: does every one animate, and how long does it take?

Each mesh (see ``public_meshes.py``; fetched from registries into a cache) gets the default
scene of issue 15: the bottom 15 % of its height (y) held at rest at 0, 1 and 2 s, the top
15 % turned 45° about y at t = 1 s; 2 s at 30 fps, 40 modes, warped solve, written as .glb.
One run per mesh on an empty tet cache (fTetWild dominates); the table gives what
was unusual about the surface (wiggly's one warning), the tet count, the time to the first
frame and the result.  ``--only NAME`` runs one mesh.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))

import numpy as np

from common import table
from public_meshes import public_meshes
from wiggly.errors import WigglyInputError
from wiggly.mesh import inspect_surface, load_mesh
from wiggly.scene import run, scene_from_dict


def default_scene(mesh: Path, out: Path) -> dict:
    """Bottom at rest throughout, top turned 45° about y at t = 1 s (the issue's scene)."""
    X = load_mesh(mesh).vertices
    lo, hi = X.min(axis=0), X.max(axis=0)
    h = hi[1] - lo[1]
    pad = (hi - lo).max()
    box = {"min": [float(lo[0] - pad), 0.0, float(lo[2] - pad)],
           "max": [float(hi[0] + pad), 0.0, float(hi[2] + pad)]}
    bottom = {"box": {**box, "min": [box["min"][0], float(lo[1] - pad), box["min"][2]],
                      "max": [box["max"][0], float(lo[1] + 0.15 * h), box["max"][2]]}}
    top = {"box": {**box, "min": [box["min"][0], float(hi[1] - 0.15 * h), box["min"][2]],
                   "max": [box["max"][0], float(hi[1] + pad), box["max"][2]]}}
    return {
        "mesh": {"path": str(mesh)},
        "time": {"end": 2.0, "fps": 30},
        "groups": {"bottom": bottom, "top": top},
        "keyframes": [
            {"time": 0.0, "group": "bottom", "position": "rest", "velocity": [0.0, 0.0, 0.0]},
            {"time": 0.0, "group": "top", "position": "rest"},
            {"time": 1.0, "group": "bottom", "position": "rest"},
            {"time": 1.0, "group": "top", "position": {"rotation": [0.0, 45.0, 0.0]}},
            {"time": 2.0, "group": "bottom", "position": "rest"},
        ],
        "output": {"paths": [str(out)]},
    }


def animate(mesh: Path, work: Path) -> dict:
    row: dict = {}
    surface = load_mesh(mesh)
    row["vertices"], row["faces"] = surface.n_vertices, surface.n_faces
    report = inspect_surface(surface, mesh.name)
    row["unusual"] = ", ".join(report.defects()) or "-"
    out = work / f"{mesh.stem}.glb"
    scene = scene_from_dict(default_scene(mesh, out), where=f"{mesh.stem}.toml")
    t = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            anim = run(scene)
        row["seconds"] = time.perf_counter() - t
        row["tets"] = anim.body.tets.n_tets
        worst = max(r.get("position_max", 0.0) for r in anim.constraint_residuals())
        far = [str(w.message) for w in caught if "outside the filled solid" in str(w.message)]
        conv = "converged" if anim.info.get("converged", True) else "NOT converged"
        row["result"] = (f"ok, {anim.info.get('iterations', 0)} Newton it. ({conv}), keys "
                         f"met to {worst / report.diagonal:.1e} of size (worst vertex)"
                         + ("; thin parts outside the tets" if far else ""))
        row["ok"] = out.is_file()
    except WigglyInputError as err:
        row["seconds"] = time.perf_counter() - t
        row["result"] = "refused: " + str(err).splitlines()[0].split(": ", 1)[-1][:120]
        row["ok"] = False
    except Exception as err:  # a crash is a finding of the benchmark, not its end
        row["seconds"] = time.perf_counter() - t
        row["result"] = f"crash: {type(err).__name__}: {str(err)[:100]}"
        row["ok"] = False
    return row


def main(argv: list[str]) -> list[dict]:
    only = argv[argv.index("--only") + 1] if "--only" in argv else None
    meshes, skipped = public_meshes()
    for reason in skipped:
        print(f"skipped: {reason}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["WIGGLY_CACHE_DIR"] = str(Path(tmp) / "cache")  # an empty tet cache
        for m in meshes:
            if only and m.name != only:
                continue
            r = animate(m.path, Path(tmp))
            rows.append({"name": m.name, "source": m.source, **r})
            print(f"{m.name}: {r}", flush=True)
    print(table(
        "Public meshes, default scene (bottom at rest, top turned 45°), warped, 40 modes",
        ["mesh", "source", "vertices", "unusual", "tets", "time (s)", "result"],
        [[r["name"], r["source"], r["vertices"], r["unusual"], r.get("tets", "-"),
          round(r["seconds"], 1), r["result"]] for r in rows]))
    print(f"{sum(r['ok'] for r in rows)} of {len(rows)} animated")
    return rows


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main(sys.argv[1:])
