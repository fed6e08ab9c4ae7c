"""Running a scene: outputs checked before the solve, the solve, and every output written
all or nothing."""

from __future__ import annotations

import time as _time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from wiggly import render
from wiggly.drive import following
from wiggly.drive.sequence import carries_times
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.export import stage_animation, surface_animation
from wiggly.export.animation import GLTF, frame_codes, gltf_times, without_seam
from wiggly.export.gltf import frames_bytes, too_big
from wiggly.files import OutputSet, check_writable
from wiggly.keyframes import DEFAULT_STIFFNESS
from wiggly.limits import frame_count
from wiggly.mesh.defects import diagonal
from wiggly.progress import deprecated_progress, say
from wiggly.render import Highlight
from wiggly.render.setup import HIGHLIGHT_WINDOW
from wiggly.scene.body_notes import soft_note, thin_joint
from wiggly.scene.build import build_with_groups
from wiggly.scene.drive import linear_start_of, secondary_of
from wiggly.scene.groups import resolve_groups
from wiggly.scene.schema import loop_cycle_problem, partial_frame_note
from wiggly.scene.spec import (
    GEOMETRY_EXTENSIONS,
    MAX_TARGETS,
    OUTPUT_EXTENSIONS,
    PREVIEW_EXTENSIONS,
    OutputSpec,
    Rigid,
    Scene,
)
from wiggly.scene.validation import input_error, show
from wiggly.solve import FOLDED, SpacetimeProblem, missed_by, missed_keys, solve, warn_folded
from wiggly.solve.surface import warn_straight
from wiggly.warp.kernels import ensure_compiled


def _output_paths(scene: Scene, outputs) -> list[Path]:
    if outputs is None:
        return [scene.resolve(p) for p in scene.output.paths]
    return [Path(o).expanduser() for o in outputs]


def check_outputs(paths: list[Path], overwrite: bool, where: str = "outputs",
                  labels: list[str] | None = None,
                  replace_how: str = "pass --overwrite") -> None:
    """Every output has a known extension, none exists unless ``overwrite``, and each can be
    written: its folder exists or can be created (no path component is a file) and accepts
    new files.  ``labels`` name the outputs in messages (``output.paths[0] = "a.glb"``);
    default: the paths; ``replace_how`` says how to replace an existing one.  Raises one
    :class:`WigglyInputError` listing every problem."""

    problems = []

    def said(label: str, text: str) -> None:  # no "a.mp4: a.mp4 exists"
        problems.append(text if text.startswith(label) else f"{label}: {text}")

    seen = set()
    labels = labels or [str(p) for p in paths]
    for path, label in zip(paths, labels, strict=True):
        ext = path.suffix.lower()
        named = str(path) in label and label != str(path)  # "-o a.glb": a.glb named already
        it, the_file = ("it", "the file") if named else (str(path), str(path))
        if ext not in OUTPUT_EXTENSIONS and path.is_dir():
            said(label, f"{it} is a directory; give a file name in it, e.g. "
                        f"{path / 'shot.glb'}")
            continue
        if ext not in OUTPUT_EXTENSIONS:
            said(label, f"unsupported output extension {path.suffix or '(none)'!r}; use one "
                        f"of {', '.join(OUTPUT_EXTENSIONS)}")
            continue
        if path.resolve() in seen:
            said(label, f"{the_file} is given twice")
        seen.add(path.resolve())
        why = check_writable(path)
        if why is not None:
            said(label, why)
        elif path.is_dir():
            said(label, f"{it} is a directory; give a file name")
        elif not overwrite:
            existing = path if path.exists() else None
            if ext == ".obj" and existing is None:
                first = path.with_name(f"{path.stem}_0000.obj")
                existing = first if first.exists() else None
            if existing is not None:
                said(label, f"{the_file if existing == path else existing} exists; "
                            f"{replace_how} to replace it")
    if problems:
        raise input_error(where, problems)


def _hex_rgb(color: str) -> tuple[float, float, float]:
    return tuple(int(color[i:i + 2], 16) / 255 for i in (1, 3, 5))


def keyframe_highlights(scene: Scene, body, keyframes, groups: dict[str, np.ndarray]) -> list:
    """:class:`wiggly.render.Highlight` of every position keyframe of ``[[keyframes]]``
    (targets drawn at key times), colored by group; ``keyframes`` may go on with the driven
    keys of ``[drive]``, which are not highlighted."""


    colors = scene.group_colors()
    out = []
    for spec, kf in zip(scene.keyframes, keyframes[:len(scene.keyframes)], strict=True):
        verts = groups[spec.group]
        if scene.groups[spec.group].on == "tets":  # nearest surface vertices
            _, verts = cKDTree(body.surface.vertices).query(body.tets.vertices[verts])
            verts = np.unique(verts)
        targets = None
        if kf.position is not None:  # a few target spheres suffice to show the pose
            pick = np.unique(np.linspace(0, len(kf.position) - 1, MAX_TARGETS).round())
            targets = kf.position[pick.astype(np.int64)]
        out.append(Highlight(np.asarray(verts, np.int64), kf.time, _hex_rgb(colors[spec.group]),
                             spec.label, targets))
    return out


#: The colour of the surface where a warped motion folds, in previews.
FOLD_COLOR = (0.8, 0.0, 0.55)


def fold_highlights(anim, times, checked: list[dict] | None = None) -> list:
    """:class:`wiggly.render.Highlight` of the surface where ``anim`` folds more than
    :data:`wiggly.solve.FOLDED` of its tets (:meth:`~wiggly.Animation.folds` at ``times``,
    the frames a preview shows, or its rows there, ``checked``): one for each span of such
    frames (frames less than two highlight windows apart make one span, since their
    highlights would overlap anyway), over the surface vertices that folded tets carry and
    those nearest to folded tets inside the body, labelled with the most tets folded at a
    frame of the span.  It fades in and out over one checked frame, not a key's window: a
    frame before the first folded one shows no fold."""
    checked = anim.folds(np.asarray(times, dtype=np.float64)) if checked is None else checked
    steps = np.diff([row["time"] for row in checked])
    window = min(HIGHLIGHT_WINDOW, float(steps.min())) if len(steps) else HIGHLIGHT_WINDOW
    rows = [row for row in checked if row["share"] > FOLDED]
    if not rows:
        return []
    body = anim.body
    carrier = body.model.embedding.tet_index
    centres = body.tets.vertices[body.tets.tets].mean(axis=1)
    tree = cKDTree(body.surface.vertices)
    spans: list[list[dict]] = []
    for row in rows:
        if spans and row["time"] - spans[-1][-1]["time"] < 2 * HIGHLIGHT_WINDOW:
            spans[-1].append(row)
        else:
            spans.append([row])
    out = []
    for span in spans:
        tets = np.unique(np.concatenate([row["tets"] for row in span]))
        nearest = tree.query(centres[tets])[1]
        vertices = np.union1d(np.flatnonzero(np.isin(carrier, tets)), nearest)
        worst = max(span, key=lambda row: row["folded"])
        label = (f"folded: {'up to ' if len(span) > 1 else ''}{worst['folded']} tets "
                 f"({100 * worst['share']:.2g} %) turned inside out")
        out.append(Highlight(vertices.astype(np.int64), span[0]["time"], FOLD_COLOR, label,
                             window=window, until=span[-1]["time"]))
    return out


def surface_groups(scene: Scene, groups: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The resolved ``groups`` that index surface vertices (not tet-mesh ones)."""
    return {name: v for name, v in groups.items() if scene.groups[name].on != "tets"}


def problem_of(scene: Scene, body) -> SpacetimeProblem:
    """The scene's spacetime problem on ``body``: its time range, pre-roll and loop (the
    editor keeps it to re-solve after each edit)."""
    start, end = scene.time_range()
    return SpacetimeProblem(body, start, end, scene.simulation.preroll, loop=scene.time.loop)


@deprecated_progress
def solve_scene(scene: Scene, body, keyframes, *, groups: dict[str, np.ndarray] | None = None):
    """The scene's spacetime solve (its time range, warp, pre-roll and loop): the one call
    behind ``wiggly animate`` and the editor's exports.  A ``[drive]`` with ``physics =
    "secondary"`` solves for the free parts' motion on the driver
    (:func:`wiggly.scene.drive.secondary_of`; ``groups`` as resolved on ``body``'s mesh,
    resolved again when not given); with ``physics = "keys"`` the warped solve starts at the
    driver's poses (:func:`wiggly.scene.drive.linear_start_of`)."""
    if scene.secondary_motion:
        if groups is None:
            groups = resolve_groups(scene, body.model)
        return secondary_of(scene, body, groups, keyframes)
    start, end = scene.time_range()
    try:
        return solve(body, keyframes, start=start, end=end, warp=scene.simulation.warp,
                     preroll=scene.simulation.preroll, loop=scene.time.loop,
                     linear_start=linear_start_of(scene, body, keyframes),
                     check_keys=False)  # run() says it of the scene's own keys
    except WigglyInputError as err:  # the keyframes as a whole: said of the scene file
        if str(err).startswith(scene.where()):
            raise
        raise WigglyInputError(f"{scene.where()}: {err}") from None


@deprecated_progress
def run(scene: Scene, *, outputs=None, overwrite: bool | None = None):
    """Animate the scene and write every output; return the :class:`wiggly.Animation`.

    ``outputs`` replaces the scene's ``[output] paths`` (relative to the current directory,
    not the scene's); ``overwrite`` replaces ``[output] overwrite``.  Geometry (.glb .usd*
    .obj .npz) goes through :func:`wiggly.export.write_animation`, previews (.mp4 .gif) through
    :func:`wiggly.render.render_video` with the keyframed groups highlighted, .png through
    :func:`wiggly.render.render_contact_sheet`.  Outputs are checked before anything is
    computed and written atomically.  ``anim.info["keyframe_residuals"]`` has the scene's own
    keyframes' residuals (:meth:`wiggly.Animation.constraint_residuals`), and
    ``anim.info["scene"]`` has the written paths and the
    time spent per stage.  Its stages are reported as :mod:`wiggly.progress` says (on the
    ``wiggly`` logger at INFO, with bars on a terminal).
    """

    overwrite = scene.output.overwrite if overwrite is None else overwrite
    paths = _output_paths(scene, outputs)
    labels = ([f"output.paths[{i}] = {show(p)}" for i, p in enumerate(scene.output.paths)]
              if outputs is None else [f"-o {o}" for o in outputs])
    check_outputs(paths, overwrite, scene.where(), labels,
                  "pass --overwrite (or overwrite = true in [output])")
    _check_gltf_targets(scene, paths)
    timings: dict[str, float] = {}
    t = _time.perf_counter()
    body, keyframes, groups = build_with_groups(scene, body_modes=not scene.secondary_motion)
    timings["prepare"] = _time.perf_counter() - t
    _warn_unit_slips(scene, body)
    _check_glb_size(scene, paths, body.model.surface.n_vertices)
    start, end = scene.time_range()
    if scene.simulation.warp:  # the warp's kernels, compiled once after an install: their
        t = _time.perf_counter()  # own line in the summary, not the solve's seconds
        compiled_now = ensure_compiled()
        if _time.perf_counter() - t > 0.5:  # compiled, or loaded from their cache
            timings["compile" if compiled_now else "load"] = _time.perf_counter() - t
    what = (f"{counted(len(keyframes), 'keyframe')} of the free parts"
            if scene.secondary_motion  # the body's modes are not computed then
            else f"{counted(len(keyframes), 'keyframe')}, {body.r} modes")
    say(f"{'warped' if scene.simulation.warp else 'linear'} spacetime solve: {what}, "
        f"[{start:g}, {end:g}] s")  # for secondary motion, which uses the free parts' own
    t = _time.perf_counter()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        anim = solve_scene(scene, body, keyframes, groups=groups)
    _said_of(scene, said)
    timings["solve"] = _time.perf_counter() - t
    held = anim.held_modes if scene.secondary_motion else None
    joint = thin_joint(scene, body, held)
    if joint is not None:
        warn(f"{scene.where()}: {joint}")
    else:  # the joint, not the material, when there is one
        note = soft_note(scene, body, held)
        if note is not None:
            say(f"note: {note}")
    highlights = check_motion(scene, body, anim, groups, paths)
    written = write_outputs(scene, anim, paths, overwrite=overwrite, highlights=highlights,
                            timings=timings)
    anim.info["scene"] = {"outputs": written, "seconds": timings, "groups": groups}
    return anim


def check_motion(scene: Scene, body, anim, groups: dict[str, np.ndarray],
                 paths: list[Path]) -> list:
    """The checks of a solved motion that ``wiggly animate`` and ``wiggly batch`` both make,
    as warnings: keys missed, a warped surface folded, driven vertices that do not follow
    their driver (``anim.info["drive"]``, :func:`wiggly.drive.following`) or free parts flung
    away.  Returns the previews' highlights (the keyed groups, and folds in magenta when
    ``paths`` hold a preview)."""
    _warn_missed(scene, anim)
    warn_straight(anim, anim.frame_times(scene.time.fps), scene.where())
    highlights = keyframe_highlights(scene, body, anim.keyframes, groups)
    if scene.simulation.warp:
        folding = warn_folded(anim, f"{scene.where()}: the warped motion", api=False,
                              groups=surface_groups(scene, groups), remedy=fold_remedy(scene))
        previews = [p.name for p in paths if p.suffix.lower() in PREVIEW_EXTENSIONS]
        if folding is not None and previews:
            highlights += fold_highlights(anim, anim.frame_times(scene.time.fps))
            say(f"the previews ({', '.join(previews)}) colour the folded surface magenta")
    if scene.drive is not None:
        anim.info["drive"] = following(anim)
        say(f"the driven vertices follow the driver within {1e3 * anim.info['drive']['max']:.3g}"
             f" mm (rms {1e3 * anim.info['drive']['rms']:.3g} mm)")
        _warn_unfollowed(scene, anim.info["drive"], body)
        _warn_strayed(scene, anim.info["drive"], body)
    return highlights


#: A velocity key that would carry its group this many body sizes over the shot, or a
#: gravity above IMPLAUSIBLE_GRAVITY (m/s^2, about 10 g: a cm/s^2 slip gives 981), is named as
#: a likely unit slip before the solve.
IMPLAUSIBLE = 100.0
IMPLAUSIBLE_GRAVITY = 100.0


def unit_slips(scene: Scene, size: float) -> list[str]:
    """The scene's velocity keys that would carry their group more than ``IMPLAUSIBLE`` body
    sizes over the shot, and a gravity above ``IMPLAUSIBLE_GRAVITY``: likely unit slips (mm/s
    given as m/s), which no body follows and a stiffer key does not help."""
    start, end = scene.time_range()
    speeds = [(j, float(np.linalg.norm(kf.velocity))) for j, kf in enumerate(scene.keyframes)
              if kf.velocity is not None]
    slips = [f"keyframes[{j}].velocity is {v:.3g} m/s, which would carry the group "
             f"{v * (end - start) / size:.3g} times the body's size over the shot"
             for j, v in speeds if v * (end - start) > IMPLAUSIBLE * size]
    g = float(np.linalg.norm(scene.simulation.gravity))
    if g > IMPLAUSIBLE_GRAVITY:
        slips.append(f"simulation.gravity is {g:.3g} m/s^2, {g / 9.81:.3g} times Earth's "
                     "9.81 (981 would be Earth's in cm/s^2)")
    return slips


def _warn_unit_slips(scene: Scene, body) -> None:
    """Before the solve (which grinds on such targets): one warning naming the likely unit
    slips of :func:`unit_slips`."""
    slips = unit_slips(scene, diagonal(body.rest_positions()))
    if slips:
        listed = "; ".join(slips[:3]) + (f"; and {len(slips) - 3} more" if len(slips) > 3 else "")
        warn(f"{scene.where()}: {listed}: check the units (m/s, m/s^2); the solve "
             "will take long and miss such targets")


def _said_of(scene: Scene, said: list) -> None:
    """The solve's warnings again (each once, in its category), said of the scene file as the
    scene's other warnings are (a held key, an unconverged solve: the library names the key
    or the solve, not the file)."""
    where = scene.where()
    for message, category in dict.fromkeys((str(w.message), w.category) for w in said):
        warn(message if message.startswith(f"{where}: ") else f"{where}: {message}",
             category)


def _warn_missed(scene: Scene, anim) -> None:
    """Warn what :func:`missed_note` says of ``anim``, if anything."""
    note = missed_note(scene, anim)
    if note is not None:
        warn(note)


def missed_note(scene: Scene, anim) -> str | None:
    """The warning naming the scene's own keyframes (not a driver's) whose targets the motion
    misses by more than ``MISSED`` of the body's size (or by most of their offset from rest,
    :func:`wiggly.solve.missed_keys`), with the likely causes: a shot long
    enough that gravity outweighs the keys' stiffness (a key's weight falls as the cube of
    the duration, gravity's work grows with it), a soft stiffness, or targets nothing can
    reach (contradictory keys, fixed vertices, heavy damping); None when none is missed.
    The residual rows are kept in ``anim.info["keyframe_residuals"]`` (the summary prints
    them)."""
    own = replace(anim, keyframes=anim.keyframes[:len(scene.keyframes)])
    if not own.keyframes:
        return None
    rows, missed, size = missed_keys(own)
    anim.info["keyframe_residuals"] = rows
    if not missed:
        return None
    start, end = scene.time_range()
    listed = "; ".join(f"keyframes[{m.index}] (group {scene.keyframes[m.index].group!r}, t = "
                       f"{scene.keyframes[m.index].time:g} s) by {m.how}" for m in missed[:4])
    more = f"; and {len(missed) - 4} more" if len(missed) > 4 else ""
    explicit = any(scene.keyframes[m.index].c_A is not None for m in missed)
    used = max(own.keyframes[m.index].stiffness for m in missed)
    now = "the default is 1e6" if used == DEFAULT_STIFFNESS else f"now {used:.3g}"
    why = (f"raise their stiffness ({now}; e.g. {1e3 * used:.3g})"
           + (", or their c_A, which replaces it where given" if explicit else "")
           + (" (a stiff material resists keys: the default weighs a key against the body's "
              "mass, not its Young's modulus)" if any("offset" in m.how for m in missed) else ""))
    turned = any(isinstance(scene.keyframes[m.index].position, Rigid)
                 and any(scene.keyframes[m.index].position.rotation) for m in missed)
    if not scene.simulation.warp and turned:
        why = ("a linear solve (simulation.warp = false) cannot meet turned targets, it "
               "stretches them: turn warping on; or " + why)
    # targets no body could follow: a unit slip, not a weight (raising it does not help)
    if unit_slips(scene, size):
        why = ("check the units of the velocities or gravity named before the solve, since no "
               "body follows such targets; otherwise " + why)
    g = float(np.linalg.norm(scene.simulation.gravity))
    if g > 0 and end - start > 2.0:
        why += (f"; over a {end - start:g} s shot gravity can outweigh the keys (a key's weight "
                "falls as the cube of the duration): if so, key the body more often, or "
                "shorten it")
    return (f"{scene.where()}: {counted(len(missed), 'keyframe')} {missed_by(missed)} "
            f"({listed}{more}): {why}; also check that the targets can be reached (fixed "
            "vertices, contradictory keys, heavy damping)")


#: Driven vertices further than this share of the body's size from the driver are warned about.
UNFOLLOWED = 0.01


#: Free parts of a secondary motion further than this share of the body's size from the
#: driver's own pose of them are warned about.
STRAYED = 1.0


def _warn_strayed(scene: Scene, report: dict | None, body) -> None:
    """One warning when a secondary motion's free parts swing further than ``STRAYED`` of the
    body's size from where the driver poses them: a driver faster or harder than the body can
    follow (linear FEM turns large rotations into growth; warped, they fold)."""
    if not report or "free_max" not in report:
        return
    size = diagonal(body.rest_positions())
    if report["free_max"] <= STRAYED * size:
        return
    linear = ("" if scene.simulation.warp else
              "turn warping on (simulation.warp = true: a linear motion grows where it turns), "
              "or ")
    warn(
        f"{scene.where()}: the free parts swing up to {report['free_max']:.3g} m from the "
        f"driver's pose of them (at t = {report['free_worst_time']:g} s), "
        f"{report['free_max'] / size:.2g} times the body's size: the driver moves faster or "
        f"harder than this body can follow; {linear}stiffen the material, add damping, or "
        "lower drive.intensity")


def _warn_unfollowed(scene: Scene, report: dict | None, body) -> None:
    """One warning when the driven group strays from its driver by more than ``UNFOLLOWED``
    of the body's size, with the likely causes of each physics."""
    if not report:
        return
    size = diagonal(body.rest_positions())
    if report["max"] <= UNFOLLOWED * size:
        return
    drive = scene.drive
    group = drive.group if isinstance(drive.group, str) else ", ".join(drive.group)
    if (drive.physics or "secondary") == "secondary":
        why = ("the driven group is held on the driver's displacement carried into the tet "
               "mesh, which follows the surface only as finely as the tets do (parts thinner "
               "than the tets, or separate parts that the tet mesh joins): raise "
               "mesh.resolution; and check that mesh.path is the driver's mesh at its rest "
               "pose (for glTF, the same file; for USD, an OBJ of the same object at rest, "
               "with the same modifiers), not another scale or pose of it")
    else:
        why = ('physics = "keys" meets the driver only as closely as the modes can: keep '
               "drive.enrich on, raise simulation.modes or drive.stiffness, or use "
               'physics = "secondary"')
    warn(
        f"{scene.where()}: the driven vertices ({group}) stray up to "
        f"{1e3 * report['max']:.3g} mm from the driver (at t = {report['worst_time']:g} s), "
        f"{100 * report['max'] / size:.1f} % of the body's size: {why}")


def fold_remedy(scene: Scene) -> str:
    """What may unfold a scene's warped motion: its own keys, or for secondary motion the
    driver's push (the editor's notice says the same as ``wiggly animate``)."""
    if scene.secondary_motion:
        return ("A stiffer material, heavier damping, a larger driven group or a lower "
                "drive.intensity may help")
    return "Keying more of the body near the fold, or a stiffer material, may help"


def _check_glb_size(scene: Scene, paths: list[Path], n_vertices: int) -> None:
    """A .glb of a morph target per frame beyond GLB's 4 GiB, refused before the solve (it
    failed after it, in the writer)."""
    if scene.output.gltf_targets == "modes":
        return
    start, end = scene.time_range()
    frames = frame_count(end - start, scene.time.fps)
    for path in paths:
        if path.suffix.lower() in GLTF:
            too_big(path, frames_bytes(n_vertices, frames))


def _check_gltf_targets(scene: Scene, paths: list[Path]) -> None:
    """What a glTF output asks of ``[output]``, checked before anything is computed: morph
    targets per mode need a linear shot, and glTF times cannot be negative."""
    if not any(p.suffix.lower() in GLTF for p in paths):
        return
    problems = []
    if scene.output.gltf_targets == "modes" and scene.simulation.warp:
        problems.append(
            'output.gltf_targets = "modes" needs a linear shot: a warped motion is no linear '
            "combination of modes; set simulation.warp = false (or pass --linear), or use "
            '"frames"')
    elif scene.output.gltf_targets == "modes" and scene.secondary_motion:
        problems.append(
            'output.gltf_targets = "modes" cannot hold secondary motion: its frames are the '
            "driver's poses plus the free parts' modes, not the rest pose plus the body's "
            'modes; use "frames"')
    start = scene.output.frame_start
    if start is not None and start < 0:
        problems.append(
            f"output.frame_start (or --frame-start) = {start} would give negative glTF times, "
            "which glTF forbids: use frame_start >= 0 with a .glb output (USD takes negative "
            "frames)")
    if problems:
        raise input_error(scene.where(), problems)


def _warn_between_frames(scene: Scene, times: np.ndarray, paths: list[Path]) -> None:
    """Warn when the shot's own time puts glTF/USD frames between the timeline's frames: a
    shot starting at -0.25 s at 30 fps has USD time codes -7.5, -6.5, ... (each format's
    own rule: :func:`~wiggly.export.animation.gltf_times`, ``frame_codes``)."""
    fps = scene.time.fps
    if scene.output.frame_start is not None:
        return
    first = {**dict.fromkeys(GLTF, float(gltf_times(times, None, scene.time.loop)[0]) * fps),
             **dict.fromkeys((".usd", ".usda", ".usdc"), float(frame_codes(times, None, "")[1][0]))}
    late = [p.name for p in paths if p.suffix.lower() in first
            and abs(first[p.suffix.lower()] - round(first[p.suffix.lower()])) > 1e-6]
    if late:
        start = float(times[0])
        warn(
            f"{scene.where()}: the shot starts at {start:g} s, frame {start * fps:g} at {fps:g} "
            f"fps, so the frames of {', '.join(late)} land between the timeline's frames (an "
            "application showing whole frames blends or skips them); set output.frame_start "
            "(or --frame-start; Blender: 1) to put frame k on frame_start + k")


@deprecated_progress
def write_outputs(scene: Scene, anim, paths: list[Path], *, overwrite: bool,
                  highlights=(), timings: dict | None = None) -> list[Path]:
    """Sample ``anim`` at the scene's fps and write ``paths`` (geometry first), all or
    nothing: every output goes to a temporary file first and all are moved into place once
    all are written (:class:`wiggly.files.OutputSet`); on a failure none is replaced."""

    timings = {} if timings is None else timings
    if not paths:
        return []
    _check_gltf_targets(scene, paths)
    _warn_between_frames(scene, anim.frame_times(scene.time.fps), paths)
    t = _time.perf_counter()
    targets = scene.output.gltf_targets or "frames"
    modes = targets == "modes" and any(p.suffix.lower() in GLTF for p in paths)
    say(f"sampling {counted(len(anim.frame_times(scene.time.fps)), 'frame')} at "
        f"{scene.time.fps:g} fps")
    data = surface_animation(anim, scene.time.fps, scene.mesh_file().stem,
                             "modes" if modes else "frames")
    timings["sample"] = _time.perf_counter() - t
    written = []
    with OutputSet() as outputs:
        for path in sorted(paths, key=lambda q: q.suffix.lower() in PREVIEW_EXTENSIONS):
            t = _time.perf_counter()
            ext = path.suffix.lower()
            say(f"writing {path}")
            if ext in GEOMETRY_EXTENSIONS:
                stage_animation(outputs, path, data, overwrite=overwrite,
                                frame_start=scene.output.frame_start, gltf_targets=targets)
            else:
                if path.exists() and not overwrite:
                    raise WigglyInputError(f"{path} exists; pass --overwrite (or overwrite = "
                                           "true in [output]) to replace it")
                shown = without_seam(data)  # a looping video shows the seam's pose once
                render_preview(outputs.stage(path), shown.times, shown.positions, shown.faces,
                               highlights=highlights, output=scene.output, title=scene.name,
                               overwrite=True, up=preview_up(scene.simulation.gravity))
            timings[f"write {path.name}"] = _time.perf_counter() - t
            written.append(path)
    return written


def preview_up(gravity) -> tuple[float, float, float]:
    """A preview's up direction: against gravity, or y where there is none."""
    g = np.asarray(gravity, dtype=np.float64)
    norm = float(np.linalg.norm(g))
    return (0.0, 1.0, 0.0) if norm == 0.0 else tuple(float(x) for x in -g / norm)


@deprecated_progress
def render_preview(path: Path, times, positions, faces, *, highlights=(),
                   output: OutputSpec | None = None, title: str | None = None,
                   overwrite: bool = False, fps: float | None = None,
                   up=(0.0, 1.0, 0.0)) -> Path:
    """An .mp4/.gif video (at ``fps``, default: the frames' rate) or a .png contact sheet of
    an animated surface, seen with ``up`` up (its ground plane across it)."""

    output = output or OutputSpec()
    camera = output.camera if isinstance(output.camera, str) else tuple(output.camera)
    if path.suffix.lower() == ".png":
        tile = (max(16, output.size[0] // 2), max(16, output.size[1] // 2))
        return render.render_contact_sheet(path, times, positions, faces, n_frames=8, columns=4,
                                           highlights=highlights, tile_size=tile, camera=camera,
                                           title=title, overwrite=overwrite, up=up)
    return render.render_video(path, times, positions, faces, highlights=highlights,
                               fps=fps, size=output.size, camera=camera, title=title,
                               overwrite=overwrite, up=up)


def with_overrides(scene: Scene, *, fps: float | None = None, warp: bool | None = None,
                   resolution: int | None = None, modes: int | None = None,
                   frame_start: int | None = None, gltf_targets: str | None = None) -> Scene:
    """A copy of ``scene`` with some settings replaced (command-line options, tests)."""
    s = scene
    if frame_start is not None:
        s = replace(s, output=replace(s.output, frame_start=int(frame_start)))
    if gltf_targets is not None:
        s = replace(s, output=replace(s.output, gltf_targets=gltf_targets))
    if fps is not None:
        if s.drive is not None and s.drive.frame_rate is None and \
                Path(s.drive.path).suffix.lower() == ".obj":
            # an OBJ sequence's frames are timed by the scene's fps unless frame_rate says
            # otherwise: the output's rate must not retime the driver (and its physics)
            if float(fps) != s.time.fps and not carries_times(s.resolve(s.drive.path)):
                warn(
                    f"{s.where()}: drive.path = {show(s.drive.path)} is an OBJ sequence timed "
                    f"by the scene's {s.time.fps:g} fps (its file N at N / {s.time.fps:g} s), "
                    f"not by --fps {float(fps):g}, which sets only the outputs' rate; if the "
                    f"sequence was made at {float(fps):g} fps, set drive.frame_rate = "
                    f"{float(fps):g} (or time.fps) in the scene")
            s = replace(s, drive=replace(s.drive, frame_rate=s.time.fps))
        s = replace(s, time=replace(s.time, fps=float(fps)))
        cycle = loop_cycle_problem(s, f" (from --fps {float(fps):g})")
        if cycle is not None:
            raise WigglyInputError(f"{s.where()}: {cycle}")
        note = partial_frame_note(s, f" (from --fps {float(fps):g})")
        if note is not None:  # as the file's own fps is checked when it is read
            warn(f"{s.where()}: {note}")
    if warp is not None:
        s = replace(s, simulation=replace(s.simulation, warp=warp))
    if modes is not None:
        s = replace(s, simulation=replace(s.simulation, modes=int(modes)))
    if resolution is not None:
        s = replace(s, mesh=replace(s.mesh, resolution=int(resolution), edge_length=None))
    return s
