"""Secondary motion against physics: the free parts of bodies on drivers, wiggly's linear and
warped solves (``wiggly.drive.secondary_motion``) against a full-space simulation.

The reference is linear FEM on every free tet vertex of the same tet mesh, the driven tet
vertices prescribed, integrated with Newmark's average-acceleration scheme; its own error
is estimated by halving the step (printed).  For a translation bob the driven vertices move
rigidly, so the reference is plain linear elastodynamics with the driven vertices prescribed
(the driver's motion analytic, not its sampled frames).  For drivers that rotate or deform
the body (the sway, the skinned walk) the reference integrates the same continuous model
as wiggly (the driver's extension as wiggly makes it, a moving rest state, Complementary
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
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(__file__))
import wiggly
from common import table
from wiggly.body import Damping, Material, fixed_from_surface
from wiggly.drive import read_driver
from wiggly.drive.driver import Driver
from wiggly.drive.secondary import FrameSpline, secondary_motion
from wiggly.drive.unwarp import Unwarp
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

    def angle(self, t, d=0):
        return np.radians(smooth(np.atleast_1d(t), 12.0, 1.5, self.T, d))

    def positions(self, X, t):
        out = []
        for tk, c in zip(np.atleast_1d(t), self.translation(t), strict=True):
            R = Rotation.from_euler("y", self.angle(tk)[0])
            out.append(R.apply(X - self.pivot) + self.pivot + c)
        return np.array(out)


class Turn(Sway):
    """A turn by 90 degrees about the vertical axis through ``pivot`` in the first 0.8 s
    (C^2: 10 s^3 - 15 s^4 + 6 s^5), then a hold: the free parts swing and must come to rest
    on the turned pose."""

    kind = "turn 90 degrees, hold"
    TURN, SECONDS = np.radians(90.0), 0.8

    def translation(self, t, d=0):
        return np.zeros((len(np.atleast_1d(t)), 3))

    def angle(self, t, d=0):
        s = np.clip(np.atleast_1d(t) / self.SECONDS, 0.0, 1.0)
        inside = np.atleast_1d(t) < self.SECONDS
        curve = [10 * s**3 - 15 * s**4 + 6 * s**5, 30 * s**2 - 60 * s**3 + 30 * s**4,
                 60 * s - 180 * s**2 + 120 * s**3][d]
        return self.TURN * curve / self.SECONDS**d * (inside if d else 1.0)


def corotational_reference(body, driven, bob: Bob, T, dt):
    """Corotational FEM (geometrically nonlinear: each tet's elastic force is R K (R^T x - X)
    with R the rotation of its deformation gradient) in the full space, for a translation bob:
    w = u - c(t), w = 0 on the driven tet vertices, M w'' + D(w) w' + f(w) = -M 1 (c'' +
    alpha c'), D = alpha M + beta K_R; Newmark's average acceleration, linearly implicit
    (K_R and f at the predictor).  Returns the surface's w at the frames (F, p, 3)."""
    from wiggly.fem import lame_parameters, tet_gradients

    n = body.tets.n_vertices
    V, Tt = body.tets.vertices, body.tets.tets
    m = len(Tt)
    lam, mu = lame_parameters(body.material.young, body.material.poisson)
    grads, vol = tet_gradients(V, Tt)  # (m, 4, 3): shape-function gradients
    # element stiffness blocks K_ab (m, 4, 4, 3, 3)
    Ke = vol[:, None, None, None, None] * (
        lam * np.einsum("eai,ebj->eabij", grads, grads)
        + mu * np.einsum("ebi,eaj->eabij", grads, grads)
        + mu * np.einsum("eak,ebk->eab", grads, grads)[..., None, None] * np.eye(3))
    f = free_dofs(body, driven)
    M = body.M.tocsr()
    Mff, Mf = M[f][:, f], M[f]
    alpha, beta = body.damping.alpha, body.damping.beta
    dof = (3 * Tt[:, :, None] + np.arange(3)).reshape(m, 12)
    rows = np.broadcast_to(dof[:, :, None], (m, 12, 12)).ravel()
    cols = np.broadcast_to(dof[:, None, :], (m, 12, 12)).ravel()
    ones = np.tile(np.eye(3), (n, 1))

    def internal(w):
        x = (V + w.reshape(n, 3))[Tt]  # (m, 4, 3)
        F = np.einsum("eai,eaj->eij", x, grads)  # deformation gradients
        U, _, Vt = np.linalg.svd(F)
        d = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= d[:, None]
        R = U @ Vt
        local = np.einsum("eji,eaj->eai", R, x) - V[Tt]  # R^T x - X
        fe = np.einsum("eij,eabjk,ebk->eai", R, Ke, local)
        KR = np.einsum("eij,eabjk,elk->eaibl", R, Ke, R).reshape(m, 12, 12)
        fint = np.zeros(3 * n)
        np.add.at(fint, dof.ravel(), fe.reshape(-1))
        K = sp.csr_matrix((KR.ravel(), (rows, cols)), shape=(3 * n, 3 * n))
        return fint, K

    w = np.zeros(3 * n)
    v, a = np.zeros(int(f.sum())), np.zeros(int(f.sum()))
    steps = round(T / dt)
    frames = np.round(np.arange(round(T * FPS) + 1) / FPS / dt).astype(int)
    keep = dict(zip(frames.tolist(), range(len(frames)), strict=True))
    out = np.zeros((len(frames), 3 * n))
    for k in range(steps):
        t1 = (k + 1) * dt
        xp, vp = w[f] + dt * v + dt * dt / 4 * a, v + dt / 2 * a
        wp = np.zeros(3 * n)
        wp[f] = xp
        fint, K = internal(wp)
        Kff = K[f][:, f]
        C = alpha * Mff + beta * Kff
        rhs = -(Mf @ (ones @ (bob.translation(t1, 2)[0] + alpha * bob.translation(t1, 1)[0])))
        rhs -= C @ vp + fint[f]
        a1 = spla.spsolve((Mff + dt / 2 * C + dt * dt / 4 * Kff).tocsc(), rhs)
        w[f], v, a = xp + dt * dt / 4 * a1, vp + dt / 2 * a1, a1
        if k + 1 in keep:
            out[keep[k + 1]] = w
    E = body.surface_embedding
    return np.stack([E @ u.reshape(n, 3) for u in out])


def corotated_reference(body, driven, sway: Sway, T, dt):
    """Linear elasticity in the sway's rotating frame (a floating frame, exact for a rigid
    rig and small strains in it): x = R(t) (X - p + w) + p + c(t), w = 0 on the driven tet
    vertices, M w'' + C w' + K w = -M (R^T c'' + W' x r + W x (W x r) + 2 W x w')
    - alpha M (R^T c' + W x r), r = X - p + w, W the angular velocity (about y); the terms in
    w and w' lag by a Newmark predictor.  Returns the surface's w (F, p, 3) at the frames: the
    motion relative to the driver, in the body's frame."""
    n = body.tets.n_vertices
    f = free_dofs(body, driven)
    M, K = body.M.tocsr(), body.K.tocsr()
    Mff, Kff, Mf = M[f][:, f], K[f][:, f], M[f]
    alpha, beta = body.damping.alpha, body.damping.beta
    C = alpha * Mff + beta * Kff
    A = factorize_spd((Mff + dt / 2 * C + dt * dt / 4 * Kff).tocsr())
    X0 = body.tets.vertices - sway.pivot
    yhat = np.array([0.0, 1.0, 0.0])

    def force(t, w, v):
        th, om, dom = (float(sway.angle(t, d)[0]) for d in range(3))
        R = Rotation.from_euler("y", th).as_matrix()
        r = X0 + w.reshape(n, 3)
        W, dW = om * yhat, dom * yhat
        acc = (sway.translation(t, 2)[0] @ R + np.cross(dW, r) + np.cross(W, np.cross(W, r))
               + 2 * np.cross(W, v.reshape(n, 3)))
        vel = sway.translation(t, 1)[0] @ R + np.cross(W, r)
        return -(Mf @ (acc + alpha * vel).ravel())

    x = np.zeros(int(f.sum()))
    v, a = np.zeros_like(x), np.zeros_like(x)
    full_w, full_v = np.zeros(3 * n), np.zeros(3 * n)
    steps = round(T / dt)
    frames = np.round(np.arange(round(T * FPS) + 1) / FPS / dt).astype(int)
    keep = dict(zip(frames.tolist(), range(len(frames)), strict=True))
    out = np.zeros((len(frames), 3 * n))
    for k in range(steps):
        xp, vp = x + dt * v + dt * dt / 4 * a, v + dt / 2 * a
        full_w[f], full_v[f] = xp, vp
        rhs = force((k + 1) * dt, full_w, full_v) - C @ vp - Kff @ xp
        a1 = A(rhs)
        x, v, a = x + dt * v + dt * dt / 4 * (a + a1), v + dt / 2 * (a + a1), a1
        if k + 1 in keep:
            out[keep[k + 1], f] = x
    E = body.surface_embedding
    return np.stack([E @ u.reshape(n, 3) for u in out])


def free_dofs(body, driven) -> np.ndarray:
    """Mask (3n,) of the degrees of freedom the references integrate: every dof but those of
    the tet vertices that carry the driven surface vertices."""
    held = fixed_from_surface(body.model, driven)
    free = np.ones(3 * body.tets.n_vertices, bool)
    free[(3 * held[:, None] + np.arange(3)).ravel()] = False
    return free


def reference(body, driven, motion, T, dt, rig: FrameSpline | None, gravity: bool = False):
    """Full-space Newmark simulation (module doc); surface displacement relative to the
    driver's own motion of the surface, sampled at the driver frames (F, p, 3).  With
    ``gravity`` the body's gravity acts too, and the free parts start in static equilibrium
    under it (as wiggly's do)."""
    n = body.tets.n_vertices
    f = free_dofs(body, driven)
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
    if rig_reference:  # the rig as wiggly extends it into the tet mesh
        mass = np.asarray(body.M.sum(axis=1)).ravel()[::3]
        U = Unwarp(body.tets.vertices, body.tets.tets, mass).extend(
            body.surface_embedding, driver.positions, np.arange(len(times)), X)
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
    corot = None
    if isinstance(motion, Bob) and not isinstance(motion, Sway) and not quick:
        t0 = time.perf_counter()
        c1 = corotational_reference(body, driven, motion, T, 2 * DT)
        corot = corotational_reference(body, driven, motion, T, DT)
        rows.append([name, motion.kind, "corotational FEM", f"{1e3 * rms(corot):.3g}",
                     f"{rms(corot) / base:.3f}", f"{100 * rms(corot - half) / base:.3g} %",
                     f"halving {100 * rms(c1 - corot) / rms(corot):.2g} % "
                     f"({time.perf_counter() - t0:.0f} s); vs the reference"])
    if isinstance(motion, Sway):
        t0 = time.perf_counter()
        c1 = corotated_reference(body, driven, motion, T, DT)
        corot = c1 if quick else corotated_reference(body, driven, motion, T, DT / 2)
        rows.append([name, motion.kind, "corotated reference", f"{1e3 * rms(corot):.3g}",
                     f"{rms(corot) / base:.3f}", f"{100 * rms(corot - half) / base:.3g} %",
                     f"halving {100 * rms(c1 - corot) / rms(corot):.2g} % "
                     f"({time.perf_counter() - t0:.0f} s); vs the reference"])
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
        if corot is not None and not isinstance(motion, Sway):
            rows.append([name, motion.kind, f"{rows[-1][2]} vs corotational",
                         f"{1e3 * rms(rel):.3g}", f"{rms(rel) / rms(corot):.3f}",
                         f"{100 * rms(rel - corot) / rms(corot):.3g} %", ""])
        if corot is not None and isinstance(motion, Sway):  # in the body frame: R^T (x - d)
            body_rel = np.stack([Rotation.from_euler("y", motion.angle(tk)[0]).inv().apply(r)
                                 for tk, r in zip(times, rel, strict=True)])
            rest = ""
            if isinstance(motion, Turn):  # where the free parts come to rest after the hold
                end = np.linalg.norm(body_rel[-1][free], axis=1).max()
                ref_end = np.linalg.norm(corot[-1][free], axis=1).max()
                rest = f"at the end {1e3 * end:.3g} mm off the pose (corotated {1e3 * ref_end:.3g})"
            rows.append([name, motion.kind, f"{rows[-1][2]} vs corotated",
                         f"{1e3 * rms(body_rel):.3g}", f"{rms(body_rel) / rms(corot):.3f}",
                         f"{100 * rms(body_rel - corot) / rms(corot):.3g} %", rest])
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
    import tempfile

    import meshio

    from wiggly.primitives import box_mesh

    V, Tt = box_mesh((3, 14, 3), (0.08, 0.5, 0.08))  # a hanging trunk, its top 15 % held
    trunk = os.path.join(tempfile.mkdtemp(), "trunk.vtu")
    meshio.write(trunk, meshio.Mesh(V - [0.04, 0.5, 0.04], [("tetra", Tt)]))
    bodies.append(("trunk: hanging", trunk, None, lambda X: X[:, 1] > -0.075))
    for name, path, res, pick in bodies:
        body = wiggly.prepare(path, n_modes=12, resolution=res, material=mat, damping=damp,
                              gravity=(0.0, 0.0, 0.0))
        X = body.surface.vertices
        driven = np.flatnonzero(pick(X))
        print(f"{name}: {body.tets.n_tets} tets, {len(driven)} of {len(X)} surface vertices "
              "driven", flush=True)
        for motion, rig_ref in ((Bob(T), False),
                                (Sway(T, X[driven].mean(axis=0)), True),
                                (Turn(T, X[driven].mean(axis=0)), True)):
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
