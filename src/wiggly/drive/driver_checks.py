"""Checks of a secondary-motion driver against the shot and the body, said as warnings: a
cut between two frames, a loop the driver does not cycle with, a turn fast against the free
parts' frequencies (warped), frames too far apart for the driver's turn (warped), and a
far turn of a linear shot (:func:`wiggly.drive.secondary_motion` calls them)."""

from __future__ import annotations

import warnings

import numpy as np

from wiggly.body import Body
from wiggly.drive.driver import Driver, keyed_frames
from wiggly.errors import warn
from wiggly.mesh.defects import diagonal

__all__ = ["CUT_SIZE", "CUT_STEPS", "SEAM_KINK", "SEAM_STEPS", "STEP_TURN", "TURN", "best_turn",
           "step_turns", "warn_cuts", "warn_seam", "warn_sparse_turn", "warn_stop", "warn_turn",
           "warn_unconverged", "warn_unstable"]


def best_turn(a: np.ndarray, b: np.ndarray):
    """The rotation (scipy's ``Rotation``) that best takes the points ``a`` (g, 3) onto the
    same points ``b`` about their centroids (Kabsch), or None where either does not span
    (all at one point); scipy's note on a poorly determined fit is not the user's (a group
    along a line: its turn about the line is none)."""
    from scipy.spatial.transform import Rotation

    a, b = a - a.mean(axis=0), b - b.mean(axis=0)
    if len(a) < 3 or not np.any(a) or not np.any(b):
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Rotation.align_vectors(b, a)[0]


def step_turns(P: np.ndarray) -> np.ndarray:
    """The angle (radians) by which the points P (F, g, 3) turn from each frame to the next
    (F - 1,): their best-fit rotation's; 0 where it is undetermined."""
    turns = [best_turn(P[k], P[k + 1]) for k in range(len(P) - 1)]
    return np.array([0.0 if R is None else R.magnitude() for R in turns])


#: A driver that turns its driven group by more than this (degrees) from one frame to the next
#: is said to be too sparse for its turn: its frames are joined by cubics through positions,
#: which cut a turn's arc, and the turning frame's forces come out wrong (a 180-degree turn
#: against a full-space simulation: 3.7 % off at 6 degrees per frame, 10 % at 15, 29 % at 22).
STEP_TURN = 10.0


def warn_sparse_turn(source: str, turns: np.ndarray, times: np.ndarray) -> None:
    """Warn when the driven group turns by more than STEP_TURN degrees between two frames of
    the driver (``turns``: its :func:`step_turns` (F - 1,) at the frames' ``times``)."""
    if not len(turns):
        return
    steps = np.degrees(turns)
    k = int(np.argmax(steps))
    if steps[k] > STEP_TURN:
        warn(
            f"the driver {source} turns its driven group by up to {steps[k]:.0f} degrees from "
            f"one frame to the next (t = {times[k]:g} to {times[k + 1]:g} s): between frames "
            "its motion is a cubic through the positions, which cuts the turn's arc, and the "
            "free parts' swing comes out wrong (by about 10 % at 15 degrees per frame, up to "
            "80 % in a fast whip at 20 and more); export the driver "
            f"with more frames (at most {STEP_TURN:.0f} degrees apart)")


def warn_unstable(source: str, nodes: np.ndarray, lowest: np.ndarray, rates: np.ndarray,
                  lam: np.ndarray) -> None:
    """Warn where the free parts' stiffness in their turning frames is not positive for
    longer than a quarter of their lowest period: their own stiffness and their loads'
    stress stiffening (:mod:`wiggly.drive.stress`) less the frame's centrifugal softening,
    ``lowest`` (nodes,) the lowest eigenvalue of its symmetric part at the ``nodes``.  Their
    linear motion grows there without bound (a part along the spin axis whirls, as a shaft
    past its critical speed), where a real one bends out and its nonlinear stiffness holds
    it; a brief whip is a push, not a spin (a review's 0.05 s whip stayed bounded).
    ``rates``: the frames' turn rates (rad/s) at the nodes."""
    positive = lam[lam > 1e-9 * max(float(lam.max(initial=0.0)), 1e-300)]
    bad = np.asarray(lowest) <= 0
    if not bad.any() or not len(positive):
        return
    edges = np.diff(np.r_[0, bad.astype(int), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    spans = nodes[ends] - nodes[starts]
    k = int(np.argmax(spans))
    if spans[k] < 0.5 * np.pi / float(np.sqrt(positive.min())):
        return
    rate = float(np.max(rates[starts[k]:ends[k] + 1]))
    warn(
        f"the driver {source} turns the free parts at up to {rate / (2 * np.pi):.2g} turns "
        f"per second, where the turning frame's centrifugal force overcomes their stiffness "
        f"(their own and the stretch of their loads) for {spans[k]:.2g} s from "
        f"t = {nodes[starts[k]]:.3g} s: their motion in linear elasticity grows there without "
        "bound (they swing erratically, by up to metres); a stiffer material for the free "
        "parts, or a slower turn, keeps it bounded")


#: A linear secondary motion whose driver turns the driven group further than this (degrees)
#: from its rest pose is warned about: its free parts' swing and sag stay in the rest pose's
#: axes instead of turning with the body.
TURN = 45.0


def warn_turn(source: str, rest: np.ndarray, P: np.ndarray, times: np.ndarray) -> None:
    """Warn when the driver turns the driven group far from its rest pose, in a linear
    secondary motion (``warp = false``): it adds the free parts' modal displacement to the
    driver's in the rest pose's axes, so after a turn their sag and bending point as they
    did at rest, not as the turned body's would (after a half turn about the vertical a
    tail's static sag was 141 % of itself off a full-space static solve in the body's frame;
    the warped motion, which carries them in the rig's frame, 1 %).  ``rest``: the driven
    vertices at rest (g, 3); ``P``: at the driver's frames (F, g, 3)."""
    turns = [best_turn(rest, pose) for pose in P]
    angles = np.array([0.0 if R is None else np.degrees(R.magnitude()) for R in turns])
    if not len(angles):
        return
    k = int(np.argmax(angles))
    if angles[k] <= TURN:
        return
    warn(
        f"the driver {source} turns its driven group by up to {angles[k]:.0f} degrees from "
        f"its rest pose (at t = {times[k]:g} s): a linear secondary motion "
        "(simulation.warp = false) keeps the free parts' swing and sag in the rest pose's "
        "axes instead of turning them with the body; the warped motion (the default) turns "
        "them")


#: A looped shot's driver is said not to cycle with it when its driven vertices at the shot's
#: end lie further than SEAM_STEPS of its largest step between frames from its start pose.
SEAM_STEPS = 1.5


#: ... and when the change of their velocity across the seam is more than SEAM_KINK times its
#: largest change between two steps elsewhere (a driver that cycles makes the seam one more
#: such change: a review's trot looped on its own cycle, 0.27 times; on three quarters of it,
#: with its turn reversed at the seam, 2.25 times).
SEAM_KINK = 1.5


def _seam_kink(P: np.ndarray, times: np.ndarray, step_to_start: bool) -> tuple[float, float]:
    """The largest change of velocity (m/s) of points P (F, g, 3) at ``times`` across a
    loop's seam, and the largest between two steps elsewhere: the frames taken cyclically,
    the last one the first again or (``step_to_start``) one step before it."""
    if step_to_start:  # ..., P[-1], then P[0] one step later
        P, times = np.concatenate([P, P[:1]]), np.r_[times, 2 * times[-1] - times[-2]]
    v = np.diff(P, axis=0) / np.diff(times)[:, None, None]  # per step, the seam between
    dv = np.linalg.norm(np.diff(v, axis=0), axis=2).max(axis=1)  # the last and the first
    seam = float(np.linalg.norm(v[0] - v[-1], axis=1).max())
    return seam, float(dv.max()) if len(dv) else 0.0


def warn_seam(driver: Driver, driven: np.ndarray, *, start: float, end: float,
               offset: float, driver_range: tuple[float, float] | None) -> bool:
    """Warn when a looped shot's driver does not cycle with the shot: the loop makes its
    pose at the end its pose at the start (:func:`wiggly.drive.secondary.secondary_frames`),
    a jump at the seam when the two differ, or a curve over the time after its last frame in
    the shot when it ends early, which stretches its cycle to the shot's.  Whether it
    warned."""
    frames, times = keyed_frames(driver, offset=offset, driver_range=driver_range,
                                 start=start, end=end)
    if len(frames) < 3:
        return False
    P = driver.positions[frames][:, driven]
    step = float(np.linalg.norm(np.diff(P, axis=0), axis=2).max())
    gap = float(np.linalg.norm(P[-1] - P[0], axis=1).max())
    spacing = float(np.median(np.diff(times)))
    remedy = ("end the shot on the driver's cycle (time.end), or keep one cycle of it "
              "(drive.range)")
    if end - times[-1] <= 1.5 * spacing:  # the seam is one step: the last frame at the end,
        if gap > SEAM_STEPS * step:  # or a frame before it (a cycle of frames 1..N)
            warn(
                f"the driver {driver.source} does not cycle with the looped shot: its driven "
                f"vertices at {times[-1]:g} s lie up to {1e3 * gap:.3g} mm from their pose at "
                f"{start:g} s (they move at most {1e3 * step:.3g} mm from one frame to the "
                f"next), and the loop joins the two with a jump at the seam; {remedy}")
            return True
        kink, most = _seam_kink(P, times, end - times[-1] > 0.5 * spacing)
        if kink > SEAM_KINK * most:
            warn(
                f"the driver {driver.source} does not cycle with the looped shot: its driven "
                f"vertices meet their start pose again at {times[-1]:g} s, but their velocity "
                f"changes there by up to {kink:.3g} m/s from the last frame to the first (by at "
                f"most {most:.3g} m/s from one frame to the next elsewhere: a cycle whose "
                f"motion reverses, or that is not the driver's), and the loop joins them with "
                f"a kink, a hitch in every cycle; {remedy}")
            return True
        return False
    warn(
        f"the driver {driver.source} ends {end - times[-1]:.3g} s before the looped "
        f"shot's end ({times[-1]:g} s of [{start:g}, {end:g}] s): the loop joins its last "
        f"frame to its first by a curve over that time, which stretches the driver's "
        f"cycle to the shot's; {remedy}")
    return True


#: A driver step between two frames is called a cut when its driven vertices move further
#: than CUT_STEPS times the steps on either side of it (and the median step), and more than
#: CUT_SIZE of the body's size.
CUT_STEPS, CUT_SIZE = 8.0, 0.05


def warn_cuts(source: str, P: np.ndarray, times: np.ndarray, body: Body) -> None:
    """Warn when the driver jumps between two frames (a cut, a teleport): the C2 spline
    through the frames (:class:`wiggly.drive.secondary.FrameSpline`) swings before and after
    such a jump, and the body then moves before the driver does.  A jump is one step far
    larger than the steps beside it: a fast move over a few frames between holds (a turn in
    half a second) is none.  ``P``: the driven vertices at the frames (F, g, 3)."""
    if len(P) < 3:
        return
    step = np.linalg.norm(np.diff(P, axis=0), axis=2).max(axis=1)
    size, typical = diagonal(body.surface.vertices), float(np.median(step))
    beside = np.maximum(np.r_[0.0, step[:-1]], np.r_[step[1:], 0.0])
    around = np.maximum(beside, typical)
    cuts = np.flatnonzero((step > CUT_STEPS * around) & (step > CUT_SIZE * size))
    if not len(cuts):
        return
    k = int(cuts[np.argmax(step[cuts])])
    than = (f"{step[k] / around[k]:.0f} times the steps beside it" if around[k] > 1e-9 * size
            else "the frames beside it hold still")
    more = f", and at {len(cuts) - 1} more steps" if len(cuts) > 1 else ""
    warn(
        f"the driver {source} jumps: its driven vertices move {step[k]:.3g} m between "
        f"t = {times[k]:g} and {times[k + 1]:g} s ({than}){more}; the smooth curve through "
        "its frames swings before and after such a jump, so the body moves before the driver "
        "does: end the shot at the cut (drive.range, or time.end), or animate the move over "
        "several frames")


#: A driver that ends inside the shot is said to stop its driven group dead when the group's
#: centre moves faster than this many body sizes per second over its last step (a walk's
#: travel: a review's 0.75 m/s on a 1.6 m critter; a trot in place bobs at about 0.2 of its
#: size per second, and the bundled walk stops from there by design).
STOP_SPEED = 0.25


def warn_stop(source: str, P: np.ndarray, times: np.ndarray, end: float, body: Body) -> None:
    """Warn when the driver's frames end inside the shot (its last frame, or drive.range)
    while its driven group still travels: it then stops dead and holds that pose to the
    shot's end, an unbounded deceleration of the frame the free parts ride in.  ``P``: the
    driven vertices at the frames (F, g, 3), at shot ``times``."""
    if len(P) < 2 or times[-1] >= end - 1e-9 * max(1.0, end):
        return
    step = float(np.linalg.norm(P[-1].mean(axis=0) - P[-2].mean(axis=0)))
    speed = step / float(times[-1] - times[-2])
    if speed <= STOP_SPEED * diagonal(body.surface.vertices):
        return
    warn(f"the driver {source} ends at {times[-1]:g} s of the shot's {end:g} s while its "
         f"driven group travels at {speed:.3g} m/s: it stops dead there and holds that pose "
         "to the end, which jolts the free parts; end the shot there (time.end), keep more "
         "of the driver (drive.range), or let it come to rest")


def warn_unconverged(source: str, iterations: int, steps: list[float]) -> None:
    """Say that the Gauss-Newton iteration on the warped keys of the free parts ran out of
    iterations, with its last step and contraction (``steps``: the largest change of a node
    coordinate per iteration)."""
    rate = steps[-1] / steps[-2] if len(steps) > 1 and steps[-2] > 0 else float("nan")
    warn(
        f"secondary motion on {source}: the warped keys of the free parts did not converge in "
        f"{iterations} Gauss-Newton iterations (the last moved a modal coordinate by "
        f"{steps[-1]:.3g}, {rate:.2g} times the step before): the motion is the last "
        "iterate, which meets the keys as their residuals say, not the energy's minimum; "
        "keys that pull the free parts far from the driver's pose of them converge slowly "
        "(a lower key stiffness, or keys nearer that pose, help)")
