"""Plot ``docs/tail_lag.png``: the tail tip of examples/walk_secondary.toml against its driver.

Top: the height of the tail's root as the driver carries it (the trot's bob).  Gravity
acts in both, and both start at rest in equilibrium under it.  Bottom: the
tail tip's offset from where the driver puts it, in wiggly's warped and linear solves and in
a full-space simulation of the same model (every free tet vertex a degree of freedom,
Newmark's average acceleration at 1/960 s; ``benchmarks/bench_secondary.py``).  The tail lags
the bob, swings, and settles once the walk stops at 2 s.  Takes about a minute on two
cores.  Run from the repository root::

    .venv/bin/python scripts/tail_lag_plot.py [out.png]
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_secondary import reference  # noqa: E402
from wiggly.drive import read_driver  # noqa: E402
from wiggly.drive.secondary import FrameSpline  # noqa: E402
from wiggly.drive.unwarp import Unwarp  # noqa: E402
from wiggly.progress import reporting  # noqa: E402
from wiggly.scene import load_scene, run  # noqa: E402


def main(out: Path = ROOT / "docs" / "tail_lag.png") -> Path:
    scene = load_scene(ROOT / "examples" / "walk_secondary.toml")
    scene = replace(scene, keyframes=())  # the free parts on their own
    with reporting():  # bars on a terminal
        warped = run(scene, outputs=[])
    linear = run(replace(scene, simulation=replace(scene.simulation, warp=False)), outputs=[])
    driver = read_driver(ROOT / "examples" / "critter_walk.glb")
    body = warped.body
    tail = warped.info["scene"]["groups"]["tail"]
    X = body.surface.vertices
    tip = tail[np.argmin(X[tail, 0])]  # the tail's last vertex (smallest x)
    root = tail[np.argmax(X[tail, 0])]
    end = scene.time_range()[1]
    t = np.arange(0.0, end + 1e-9, 1 / 120)
    # the driver between its frames as wiggly plays it: the cubic spline through them,
    # holding its last pose after 2 s
    pair = FrameSpline.fit(driver.times, driver.positions[:, [tip, root]].reshape(
        driver.n_frames, -1), hold_end=True)
    carried = np.zeros((len(t), len(X), 3))
    carried[:, [tip, root]] = pair(t).reshape(len(t), 2, 3)

    def offset(anim):
        return 1e3 * (anim.positions(t)[:, tip] - carried[:, tip])

    # the full-space reference of the same model (the driver's extension as moving rest state)
    driven = warped.info["scene"]["groups"]["body"]
    mass = np.asarray(body.M.sum(axis=1)).ravel()[::3]
    rig_u = Unwarp(body.tets.vertices, body.tets.tets, mass).extend(
        body.surface_embedding, driver.positions, np.arange(driver.n_frames), X)
    rig = FrameSpline.fit(driver.times, rig_u.T, hold_end=True)

    class Motion:
        kind = "skinned walk"

    ref_frames = reference(body, driven, Motion(), end, 1 / 960, rig, gravity=True)  # 30 fps
    t_ref = np.arange(len(ref_frames)) / 30.0
    ref_tip = 1e3 * ref_frames[:, tip]  # relative to the rig already

    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True,
                                   gridspec_kw={"height_ratios": [1, 2]})
    ax0.plot(t, 1e3 * (carried[:, root, 1] - X[root, 1]), color="#1f77b4")
    ax0.set_ylabel("tail root\nheight (mm)")
    ax0.set_title("the tail tip against the trot that drives it (walk_secondary.toml, no keys)")
    for anim, name, style in ((warped, "wiggly, warped", "-"), (linear, "wiggly, linear", "--")):
        ax1.plot(t, offset(anim)[:, 1], style, label=f"{name}: vertical", color="#ff7f0e")
        ax1.plot(t, offset(anim)[:, 0], style, label=f"{name}: along the body",
                 color="#2ca02c")
    ax1.plot(t_ref, ref_tip[:, 1], "k.", ms=3, label="full-space simulation: vertical")
    ax1.plot(t_ref, ref_tip[:, 0], "kx", ms=3, label="full-space: along the body")
    ax1.axvline(float(driver.times[-1]), color="0.6", lw=0.8)
    ax1.text(float(driver.times[-1]) + 0.03, ax1.get_ylim()[1] * 0.85, "the walk stops",
             color="0.4")
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("tail tip offset from\nthe driver's pose (mm)")
    ax1.legend(fontsize=7, ncol=3, loc="lower left")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(out)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:2]))
