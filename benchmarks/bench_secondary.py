"""Secondary motion against physics: the free parts of bodies on drivers, wiggly's linear and
warped solves (``wiggly.drive.secondary_motion``) against a full-space simulation.

The reference is linear FEM on every free tet vertex of the same tet mesh, the driven tet
vertices prescribed, integrated with Newmark's average-acceleration scheme; its own error
is estimated by halving the step (printed).  For a translation bob the driven vertices move
rigidly, so the reference is plain linear elastodynamics with the driven vertices prescribed
(the driver's motion analytic, not its sampled frames).  For drivers that rotate or deform
the body (the sway, the skinned walk) the reference integrates the same continuous model
as wiggly (the driver's least-energy extension as a moving rest state, Complementary
Dynamics) in the full space: it checks the reduction to free modes and the spline solve,
not that model; the warped solve is printed against it too, and differs where rotations are
large, which is what the warp is for.

Per scene: the free surface vertices' rms motion relative to the driver (mm) in the
reference and in wiggly, their ratio, and the rms trajectory difference relative to the
reference's motion.  Targets on translation drivers: ratio 0.67-1.5 and difference < 30 %.

Run: ``.venv/bin/python benchmarks/bench_secondary.py [--quick]``.
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
import wiggly
from common import table
from wiggly.body import Damping, Material, fixed_from_surface
from wiggly.drive import read_driver
from wiggly.drive.basis import _extend
from wiggly.drive.driver import Driver
from wiggly.drive.secondary import FrameSpline, secondary_motion
from wiggly.linalg import factorize_spd

FPS, DT = 30.0, 1 / 960


def smooth(t, amp, hz, T, d=0):
    """amp sin(2 pi hz t) sin^2(pi t / T) and its derivatives: starts and ends at rest."""
    w, k = 2 * np.pi * hz, 2 * np.pi / T
    a = [amp * np.sin(w * t), amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t)]
    s = [(1 - np.cos(k * t)) / 2, k / 2 * np.sin(k * t), k * k / 2 * np.cos(k * t)]
    return [a[0] * s[0], a[1] * s[0] + a[0] * s[1],
            a[2] * s[0] + 2 * a[1] * s[1] + a[0] * s[2]][d]


class Bob:
    """Translation: 2 cm sideways at 2 Hz, 3 cm up and down at 2.5 Hz, over T seconds."""

    kind = "translation bob"

    def __init__(self, T):
        self.T = T

    def translation(self, t, d=0):
        t = np.atleast_1d(t)
        return np.stack([smooth(t, 0.02, 2.0, self.T, d), smooth(t, 0.03, 2.5, self.T, d),
                         np.zeros_like(t)], -1)

    def positions(self, X, t):
        return X[None] + self.translation(t)[:, None, :]


class Sway(Bob):
    """Rotation: +-12 degrees about the vertical axis through ``pivot`` at 1.5 Hz, and the
    bob."""

    kind = "sway with rotation"

    def __init__(self, T, pivot):
        super().__init__(T)
        self.pivot = pivot

    def positions(self, X, t):
        out = []
        for tk, c in zip(np.atleast_1d(t), self.translation(t), strict=True):
            R = Rotation.from_euler("y", np.radians(smooth(tk, 12.0, 1.5, self.T)))
            out.append(R.apply(X - self.pivot) + self.pivot + c)
        return np.array(out)


def reference(body, driven, motion, T, dt, rig: FrameSpline | None, gravity: bool = False):
    """Full-space Newmark simulation (module doc); surface displacement relative to the
    driver's own motion of the surface, sampled at the driver frames (F, p, 3).  With
    ``gravity`` the body's gravity acts too, and the free parts start in static equilibrium
    under it (as wiggly's do)."""
    n = body.tets.n_vertices
    held = fixed_from_surface(body.model, driven)
    fixed = np.zeros(3 * n, bool)
    fixed[(3 * held[:, None] + np.arange(3)).ravel()] = True
    f = ~fixed
    M, K = body.M.tocsr(), body.K.tocsr()
    Mff, Kff = M[f][:, f], K[f][:, f]
    alpha, beta = body.damping.alpha, body.damping.beta
    C = alpha * Mff + beta * Kff
    Mf = M[f]
    ones = np.tile(np.eye(3), (n, 1))

    g = body.gravity_vector[f] if gravity else np.zeros(int(f.sum()))

    def force(t):
        if rig is None:  # rigid translation: K and beta K annihilate it
            return -(Mf @ (ones @ (motion.translation(t, 2)[0] + alpha *
                                   motion.translation(t, 1)[0]))) - g
        return -(Mf @ (rig([t], 2)[0] + alpha * rig([t], 1)[0])) - g

    A = factorize_spd((Mff + dt / 2 * C + dt * dt / 4 * Kff).tocsr())
    x = factorize_spd(Kff.tocsr())(-g) if gravity else np.zeros(int(f.sum()))
    v, a = np.zeros_like(x), np.zeros_like(x)
    steps = round(T / dt)
    frames = np.round(np.arange(round(T * FPS) + 1) / FPS / dt).astype(int)
    out = np.zeros((len(frames), 3 * n))
    out[0, f] = x
    keep = dict(zip(frames.tolist(), range(len(frames)), strict=True))
    for k in range(steps):
        rhs = force((k + 1) * dt) - C @ (v + dt / 2 * a) - Kff @ (x + dt * v + dt * dt / 4 * a)
        a1 = A(rhs)
        x, v, a = x + dt * v + dt * dt / 4 * (a + a1), v + dt / 2 * (a + a1), a1
        if k + 1 in keep:
            out[keep[k + 1], f] = x
    E = body.surface_embedding
    return np.stack([E @ u.reshape(n, 3) for u in out])


def scene_rows(name, body, driven, driver, motion, T, rig_reference, quick):
    """Rows: reference, linear and warped (module doc)."""
    X = body.surface.vertices
    free = np.setdiff1d(np.arange(len(X)), driven)
    times = driver.times
    if rig_reference:
        D = driver.positions - X
        U = _extend(body, np.arange(len(X)), D)
        rig = FrameSpline.fit(times, U.T)
    else:
        rig = None
    t0 = time.perf_counter()
    ref = reference(body, driven, motion, T, DT, rig)
    ref_s = time.perf_counter() - t0
    half = ref if quick else reference(body, driven, motion, T, DT / 2, rig)

    def rms(R):
        return float(np.sqrt(np.mean(np.sum(R[:, free] ** 2, -1))))

    base = rms(half)
    step_error = rms(ref - half) / base
    rows = [[name, motion.kind, "reference", f"{1e3 * base:.3g}", "1", "0",
             f"halving {100 * step_error:.2g} % ({ref_s:.0f} s)"]]
    for warped in (False, True):
        t0 = time.perf_counter()
        anim = secondary_motion(body, driver, driven, start=0.0, end=T, warped=warped)
        s = time.perf_counter() - t0
        rel = anim.positions(times) - driver.positions
        follow = np.abs(rel[:, driven]).max()
        rows.append([name, motion.kind, "warped" if warped else "linear",
                     f"{1e3 * rms(rel):.3g}", f"{rms(rel) / base:.3f}",
                     f"{100 * rms(rel - half) / base:.3g} %",
                     f"solve {s:.2f} s, driven within {1e3 * follow:.2g} mm"])
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="no step-halving run")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    print(f"# secondary motion against physics ({os.cpu_count()} cores)\n")
    mat = Material(young=8e4, poisson=0.45, density=1000.0)
    damp = Damping(alpha=0.5, beta=0.004)
    T = 2.0
    times = np.arange(round(T * FPS) + 1) / FPS
    rows = []
    bodies = [
        ("critter: tail, ears", "builtin:critter", 32,
         lambda X: (X[:, 0] > -0.28) & (X[:, 1] < 0.745)),
        ("plant: leaves", "builtin:plant", 32, lambda X: X[:, 1] < np.quantile(X[:, 1], 0.3)),
        ("bar: antenna", "builtin:bar", 32, lambda X: X[:, 0] < np.quantile(X[:, 0], 0.25)),
    ]
    for name, path, res, pick in bodies:
        body = wiggly.prepare(path, n_modes=12, resolution=res, material=mat, damping=damp,
                              gravity=(0.0, 0.0, 0.0))
        X = body.surface.vertices
        driven = np.flatnonzero(pick(X))
        print(f"{name}: {body.tets.n_tets} tets, {len(driven)} of {len(X)} surface vertices "
              "driven", flush=True)
        for motion, rig_ref in ((Bob(T), False),
                                (Sway(T, X[driven].mean(axis=0)), True)):
            drv = Driver(times, motion.positions(X, times), body.surface.faces,
                         np.zeros((0, 2)), name, motion.kind)
            rows += scene_rows(name, body, driven, drv, motion, T, rig_ref, args.quick)
    # the skinned walk
    body = wiggly.prepare("builtin:critter", n_modes=12, resolution=40, material=mat,
                          damping=damp, gravity=(0.0, 0.0, 0.0))
    X = body.surface.vertices
    driven = np.flatnonzero((X[:, 0] > -0.28) & (X[:, 1] < 0.745))
    walk = read_driver(os.path.join(os.path.dirname(__file__), "..", "examples",
                                    "critter_walk.glb"))

    class Walk:
        kind = "skinned walk"

    rows += scene_rows("critter: tail, ears", body, driven, walk, Walk(),
                       float(walk.times[-1]), True, args.quick)
    print(table("free parts' rms motion relative to the driver",
                ["body", "driver", "solve", "rms mm", "ratio", "difference", "notes"], rows))


if __name__ == "__main__":
    main()
