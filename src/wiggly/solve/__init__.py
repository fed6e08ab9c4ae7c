"""The sparse spacetime solve (Schulz et al. 2014, Theorems 1 and 2).

Modules, in the order data flows:

* :mod:`~wiggly.solve.nodes` -- node times of a shot;
* :mod:`~wiggly.solve.banded` -- band storage, the equilibrated banded Cholesky with
  extended-precision refinement;
* :mod:`~wiggly.solve.problem` -- :class:`SpacetimeProblem`: the energy E over a node set,
  sparse keyframes E_C, the linear solve (Theorem 1);
* :mod:`~wiggly.solve.warped` -- the warped objective E + E_WC: value, exact gradient,
  Newton matrix (Theorem 2);
* :mod:`~wiggly.solve.optimizer` -- a trust-region Newton method with second-order
  corrections and an honest stopping rule (:class:`SolveOptions`, :class:`SolveReport`);
* :mod:`~wiggly.solve.levels` -- the coarse and fine levels, and :class:`WarmStart`;
* :mod:`~wiggly.solve.animation` -- :class:`Animation`, the solved motion and its playback.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from wiggly.body import Body
from wiggly.errors import WigglyInputError, warn
from wiggly.keyframes import Keyframe, held
from wiggly.mesh.defects import diagonal
from wiggly.progress import deprecated_progress, say
from wiggly.solve.animation import Animation
from wiggly.solve.levels import WarmStart
from wiggly.solve.optimizer import SolveOptions, SolveReport, WarpedSolveWarning
from wiggly.solve.problem import SpacetimeProblem, keyframe_list
from wiggly.solve.warped import WarpedObjective, WarpedPoint

__all__ = [
    "FOLDED",
    "MISSED",
    "Animation",
    "Miss",
    "SolveOptions",
    "SolveReport",
    "SpacetimeProblem",
    "WarmStart",
    "WarpedObjective",
    "WarpedPoint",
    "WarpedSolveWarning",
    "fold_note",
    "iteration_count",
    "missed_by",
    "missed_keys",
    "solve",
    "warn_folded",
    "warn_missed",
]


@deprecated_progress
def solve(
    body: Body,
    keyframes: list[Keyframe],
    *,
    duration: float | None = None,
    start: float = 0.0,
    end: float | None = None,
    warp: bool = True,
    preroll: float | None = None,
    loop: bool = False,
    options: SolveOptions | None = None,
    linear_start: list[Keyframe] | None = None,
    check_keys: bool = True,
) -> Animation:
    """Animate ``body`` through the sparse ``keyframes``.

    ``warp=True`` (default) solves E + E_WC on the rotation-strain-warped motion (Theorem 2)
    and plays back W(u(t)); ``warp=False`` is the linear solve of Theorem 1.  The time range
    is [start, end] (``end = start + duration``; default: the last keyframe time, at least
    start + 1 s; give ``duration`` or ``end``, not both).  ``preroll`` (s, default: the shot's
    duration; 0: none): the energy also charges the motion's settling into its initial state
    over this virtual interval before ``start``, which keeps the problem positive definite.
    ``loop=True`` makes the motion periodic: its end is its start (positions and
    velocities), and the wiggly splines wrap around from the last node to the first.
    ``options``: the warped solve's tolerances and budget (:class:`wiggly.SolveOptions`).
    ``linear_start``: keyframes whose linear solution starts the warped solve
    (:meth:`SpacetimeProblem.solve`).  ``check_keys``: warn when the motion misses position
    keys by more than :data:`MISSED` of the body's size or velocity keys by more than
    :data:`MISSED` of their speed (:meth:`Animation.constraint_residuals` has them all), or
    when a warped motion turns more than :data:`FOLDED` of the tets inside out
    (:meth:`Animation.folds`); a scene file's run warns in its own words instead.
    """
    keyframes = keyframe_list(keyframes)
    for name, flag in (("warp", warp), ("loop", loop), ("check_keys", check_keys)):
        if not isinstance(flag, bool | np.bool_):
            raise WigglyInputError(f"{name} should be True or False; got {flag!r}")
    if duration is not None and end is not None:
        raise WigglyInputError(f"give duration ({duration!r} s) or end ({end!r} s), not both")
    if end is None:
        if duration is None:
            last = max((kf.time for kf in keyframes), default=start)
            duration = max(float(last) - start, 1.0)
        end = start + float(duration)
    problem = SpacetimeProblem(body, start, end, preroll, loop=loop)
    anim = problem.solve(keyframes, warped=warp, options=options, linear_start=linear_start)
    extra = ""
    if warp:
        extra = (
            f", {iteration_count(anim.info)}"
            f"{'' if anim.info['converged'] else ' (not converged)'}"
        )
    say(f"{'warped' if warp else 'linear'} solve: {anim.info['unknowns']} "
        f"unknowns in {anim.info['solve_seconds'] * 1e3:.1f} ms{extra}")
    # the warnings name the caller's line: past warn_*, this function and its decorator
    if check_keys:
        warn_missed(anim)
        if warp:
            warn_folded(anim)
    return anim


#: Position keys missed by more than this share of the body's size are warned about; velocity
#: keys missed by more than this share of their RMS speed or of the body's size per the shot's
#: duration, whichever is larger (a still key: the drift that would move the body so far).
MISSED = 0.05
#: Position keys whose targets lie more than :data:`MISSED_FLOOR` of the body's size from rest
#: are also warned about when the motion misses them by more than this share of that offset:
#: a stiff material resists a key of the default stiffness, and a 10 mm key on a stiff 20 cm
#: beam would otherwise be missed whole without a word.
MISSED_OFFSET = 0.5
MISSED_FLOOR = 0.01


class Miss(NamedTuple):
    """A keyframe :func:`missed_keys` names: its index, whether its velocity (not its
    position) was missed, and how far ("0.12 m, 12 %" or "velocity 0.3 m/s, 40 % of its
    speed")."""

    index: int
    velocity: bool
    how: str


def missed_keys(anim: Animation) -> tuple[list[dict], list[Miss], float]:
    """The keyframes' residual rows (:meth:`Animation.constraint_residuals`), the
    :class:`Miss` of each one missed by more than :data:`MISSED` (keys held by fixed
    vertices, warned about when checked, are not listed), and the body's size (its
    bounding-box diagonal, m)."""
    size = diagonal(anim.body.rest_positions())
    duration = float(anim.nodes[-1] - anim.nodes[0])
    rows = anim.constraint_residuals()
    missed = []
    for j, (row, kf) in enumerate(zip(rows, anim.keyframes, strict=True)):
        miss = row.get("position_max")
        offset = _offset(anim.body, kf) if miss is not None else 0.0
        if miss is not None and miss > MISSED * size:
            found = Miss(j, False, f"{miss:.3g} m, {100 * miss / size:.0f} %")
        elif offset > MISSED_FLOOR * size and miss > MISSED_OFFSET * offset:
            found = Miss(j, False, f"{miss:.3g} m, {100 * miss / offset:.0f} % of its "
                                   f"{offset:.3g} m offset from rest")
        else:
            miss = row.get("velocity_rms")
            if miss is None:
                continue
            speed = float(np.sqrt(np.mean(np.sum(np.asarray(kf.velocity) ** 2, axis=-1))))
            scale = max(speed, size / duration)
            if miss <= MISSED * scale:
                continue
            of = ("its speed" if speed >= size / duration else
                  f"{scale:.3g} m/s, the body's size per the shot's duration")
            found = Miss(j, True, f"velocity {miss:.3g} m/s, {100 * miss / scale:.0f} % of {of}")
        if not held(anim.body, kf.vertices, kf.on):  # said when it was checked: nothing moves it
            missed.append(found)
    return rows, missed, size


def _offset(body, kf) -> float:
    """The largest distance (m) of a keyframe's position targets from their rest positions."""
    rest = body.rest_positions(kf.on)[kf.vertices]
    return float(np.sqrt(((np.asarray(kf.position) - rest) ** 2).sum(axis=-1)).max(initial=0.0))


def missed_by(missed: list[Miss]) -> str:
    """"missed by more than 5 % of the body's size" (and "or their velocity by 5 % of its
    speed" when velocity keys are among ``missed``)."""
    text = f"missed by more than {100 * MISSED:g} % of the body's size"
    if any("offset" in m.how for m in missed):
        text += f" or {100 * MISSED_OFFSET:g} % of their offset from rest"
    if any(m.velocity for m in missed):
        text += f" or their velocity by {100 * MISSED:g} % of its speed"
    return text


def warn_missed(anim: Animation) -> None:
    """One warning naming the keyframes whose targets ``anim`` misses by more than
    :data:`MISSED`, with the likely causes (attributed to the user's line:
    :func:`wiggly.errors.warn`)."""
    if not anim.keyframes:
        return
    rows, missed, _ = missed_keys(anim)
    if not missed:
        return
    listed = "; ".join(
        f"keyframes[{m.index}]"
        f"{f' ({anim.keyframes[m.index].name!r})' if anim.keyframes[m.index].name else ''} "
        f"at t = {anim.keyframes[m.index].time:g} s by {m.how}"
        for m in missed[:4]) + (f"; and {len(missed) - 4} more" if len(missed) > 4 else "")
    positions = not all(m.velocity or "offset" in m.how for m in missed)  # far, or turned
    linear = ("" if anim.warped or not positions else "a linear solve cannot meet turned "
              "targets (it stretches them): solve with warp=True; or ")
    stiff = (" (a stiff material resists keys: the default weighs a key against the body's "
             "mass, not its Young's modulus)" if any("offset" in m.how for m in missed) else "")
    warn(
        f"{len(missed)} of {len(rows)} keyframes {missed_by(missed)} ({listed}): {linear}raise "
        f"their stiffness (default 1e6){stiff}, or check that the targets can be reached (fixed "
        "vertices, contradictory keys, velocities in m/s, gravity over a long shot); "
        "anim.constraint_residuals() lists every key")


#: Warped motions that turn more than this share of the tets inside out at a keyframe time
#: are warned about.
FOLDED = 1e-3


def fold_note(
    anim: Animation,
    where: str = "the warped motion",
    api: bool = True,
    groups: dict[str, np.ndarray] | None = None,
    checked: list[dict] | None = None,
    remedy: str = "Keying more of the body near the fold, or a stiffer material, may help",
) -> str | None:
    """What :func:`warn_folded` says of ``anim`` (None when it folds no more than
    :data:`FOLDED` of the tets at any time :meth:`Animation.folds` checks); ``api=False``
    leaves out the pointer to :meth:`Animation.folds` (for the command line and the editor);
    ``groups`` (name: surface vertex indices, a scene's groups) names the group nearest the
    fold; ``checked``: the rows of :meth:`Animation.folds` at other times than its default
    ones (the frames the editor shows), if computed already."""
    if checked is None:
        checked = anim.folds()
    rows = [row for row in checked if row["share"] > FOLDED]
    if not rows:
        return None
    worst = max(rows, key=lambda row: row["folded"])
    rest = anim.body.rest_positions()
    digits = max(0, 3 - int(np.floor(np.log10(max(diagonal(rest), 1e-12)))))
    centre = ", ".join(f"{c:.{digits}f}" for c in worst["centre"])
    gaps = {name: float(np.linalg.norm(rest[v] - worst["centre"], axis=1).min())
            for name, v in (groups or {}).items() if len(v)}
    nearest = ""
    if gaps:
        name = min(gaps, key=gaps.get)
        nearest = f" (the nearest group is {name!r}, {gaps[name]:.{digits}f} m from it)"
    span = (f" (folded at {len(rows)} of the {len(checked)} times checked, t = "
            f"{rows[0]['time']:.3g}-{rows[-1]['time']:.3g} s)" if len(rows) > 1 else "")
    if worst["turns"] > 0.5:
        why = (f"the linear motion spins them by up to {worst['turns']:.2g} turns, and "
               "rotation-strain warping, which turns each tet by its own rotation, cannot fit "
               "neighbours whose rotations differ by more than about half a turn; such spins "
               "come from large motions borne by a few modes: keys that turn a large part of "
               "the body, or a soft or large body held by a small group and collapsing under "
               "its weight")
    else:
        why = (f"the linear motion turns them by at most {worst['turns']:.2g} turns, so they "
               "are squashed or sheared inside out: a soft or large body held by a small group "
               "and collapsing under its weight, a thin part asked for a large, fast "
               "deformation, or targets that pull parts of the body through each other "
               "(linear FEM plus warping treats large strains linearly)")
    return (f"{where} turns {worst['folded']} tets ({100 * worst['share']:.2g} %) inside out "
            f"at t = {worst['time']:.3g} s{span}, around ({centre}) m in the rest pose{nearest}, "
            "so the "
            f"surface may crease there: {why}. {remedy}"
            + ("; anim.folds() lists every time checked" if api else ""))


def warn_folded(
    anim: Animation,
    where: str = "the warped motion",
    api: bool = True,
    groups: dict[str, np.ndarray] | None = None,
    **kw,
) -> str | None:
    """One warning when ``anim`` folds more than :data:`FOLDED` of the tets at a keyframe time
    (:meth:`Animation.folds`), naming when, how many, where (and the nearest of ``groups``)
    and by how many turns the linear motion spins them (attributed as in
    :func:`warn_missed`); returns its text.  ``kw``: :func:`fold_note`'s ``remedy``."""
    note = fold_note(anim, where, api, groups, **kw)
    if note is not None:
        warn(note)
    return note


def iteration_count(info: dict, kind: str = "Newton") -> str:
    """The iterations of a solve's ``info`` as the progress bar counted them: "36 Newton
    iterations (25 on the coarse mesh, 11 on the fine)" with a coarse level, else "11 Newton
    iterations"."""
    fine = int(info.get("iterations", 0))
    coarse = int(info.get("coarse", {}).get("iterations", 0)) if "coarse" in info else 0
    if not coarse:
        return f"{fine} {kind} iteration{'s' if fine != 1 else ''}"
    return (f"{coarse + fine} {kind} iterations ({coarse} on the coarse mesh, {fine} on the "
            "fine)")
