"""``[drive]`` in scenes: its checks (references between keys, the driver file, the driver
against the mesh before tetrahedralizing), the driver read once per state of its file, and
the driven keyframes (:func:`wiggly.drive.driven_keyframes`)."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np

from wiggly.drive import (
    DRIVE_STIFFNESS,
    UNIT_FREE,
    UNIT_FREE_NOTE,
    Driver,
    driven_keyframes,
    driver_poses,
    enrich,
    keyed_frames,
    read_driver,
)
from wiggly.drive.driver_checks import best_turn
from wiggly.drive.secondary import secondary_frames, secondary_motion
from wiggly.drive.sequence import sequence_files
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.keyframes import Keyframe
from wiggly.memo import Memo
from wiggly.mesh.defects import diagonal
from wiggly.progress import activity, say
from wiggly.scene.spec import Scene
from wiggly.scene.validation import Problems, did_you_mean, missing_file, show

__all__ = ["check_drive", "check_drive_file", "check_driver_against", "driven_body",
           "driven_keyframes_of", "driven_vertices", "linear_start_of", "scene_driver",
           "secondary_of"]

_GLTF, _USD = (".glb", ".gltf"), (".usd", ".usda", ".usdc", ".usdz")


def check_drive(scene: Scene, p: Problems) -> None:
    """References of ``[drive]``: its groups exist and are on the surface, the shot has a
    time range, and the options fit the driver's format."""
    drive = scene.drive
    if drive is None:
        return
    names = list(scene.groups)
    listing = ", ".join(names) if names else "none are defined ([groups.<name>])"
    many = not isinstance(drive.group, str)
    for j, g in enumerate(drive.groups):
        key = f"drive.group[{j}]" if many else "drive.group"
        if g not in scene.groups:
            p.add(f"{key} = {show(g)} is not a group{did_you_mean(g, names)}; groups are: "
                  f"{listing}")
        elif scene.groups[g].on != "surface":
            p.add(f"{key} = {show(g)} selects tet-mesh vertices (on = \"tets\"); a driver "
                  "animates the surface: use a group of surface vertices")
    if scene.time.end is None and scene.time.duration is None:
        p.add("time.end (or time.duration) is missing: a driven shot needs its time range"
              + _span_hint(scene))
    ext = Path(drive.path).suffix.lower()
    for key, formats, what in (("animation", _GLTF, "glTF"), ("object", _GLTF + _USD,
                                                               "glTF and USD"),
                               ("frame_rate", (".obj",), "OBJ sequence"),
                               ("up_axis", UNIT_FREE, "OBJ-sequence and npz")):
        if getattr(drive, key) is not None and ext not in formats:
            why = f" ({UNIT_FREE_NOTE})" if formats is UNIT_FREE else ""
            p.add(f"drive.{key} = {show(getattr(drive, key))} applies to {what} drivers only; "
                  f"drive.path = {show(drive.path)} is not one{why}")


def _span_hint(scene: Scene) -> str:
    """``; the driver ... runs from a to b s (e.g. end = b)``, when it can be read."""
    try:
        first, last = scene_driver(scene).span
    except (WigglyInputError, OSError):
        return ""
    end = last + scene.drive.offset
    return (f"; the driver {scene.drive.path} runs from {first:g} to {last:g} s (e.g. add "
            f"end = {end:g} to [time])")


def check_drive_file(scene: Scene, p: Problems) -> None:
    """The driver file exists (an OBJ sequence: some numbered file matches)."""
    drive = scene.drive
    if drive is None:
        return
    path = scene.resolve(drive.path)
    if path.suffix.lower() == ".obj":
        try:
            found = sequence_files(path)
        except WigglyInputError as err:
            p.add(f"drive.path = {show(drive.path)}: {err}")
            return
        if not found:
            p.add(f"drive.path = {show(drive.path)}: no OBJ sequence there (no numbered file "
                  f"such as {path.stem.rstrip('#_')}_0001.obj in {path.parent})")
    elif not path.is_file():
        p.add(missing_file("drive.path", drive.path, path))


# ----------------------------------------------------------------------------------------------
# the driver, read once per state of its file(s)

_DRIVERS = Memo(2)  # by (path, file stamps, options); read outside the lock, stored under it
_LOCK = threading.Lock()


def _stamp(path: Path) -> tuple:
    files = [f for _, f in sequence_files(path)] if path.suffix.lower() == ".obj" else [path]
    out = []
    for f in files:
        try:
            st = f.stat()
        except OSError:
            return ()
        out.append((str(f), st.st_mtime_ns, st.st_size))
    return tuple(out)


def scene_driver(scene: Scene) -> Driver:
    """The scene's driver (:func:`wiggly.drive.read_driver`), kept for the two most recent
    (file, modification time, size, options) values so that re-solves do not read it
    again."""
    drive = scene.drive
    if drive is None:
        raise WigglyInputError(f"{scene.where()}: the scene has no [drive]")
    path = scene.resolve(drive.path)
    rate = drive.frame_rate if drive.frame_rate is not None else scene.time.fps
    key = (str(path), _stamp(path), drive.animation, drive.object, rate, drive.metres_per_unit,
           drive.up)
    with _LOCK:
        kept = _DRIVERS.peek(key)
        if kept is not None:
            _DRIVERS.put(key, kept)  # the most recently used
            return kept
    try:
        with activity(f"reading the driver {path.name}"):
            driver = read_driver(path, animation=drive.animation, object=drive.object,
                                 frame_rate=rate, scale=drive.metres_per_unit, up=drive.up)
    except WigglyInputError as err:
        # a clip the file lacks is drive.animation's mistake, not the file's
        key_at_fault = (f"drive.animation = {show(drive.animation)}"
                        if drive.animation is not None and "has no animation" in str(err)
                        else f"drive.path = {show(drive.path)}")
        raise WigglyInputError(f"{scene.where()}: {key_at_fault}: {err}") from None
    with _LOCK:
        _DRIVERS.put(key, driver)
    return driver


#: A driver whose first pose is more than this many times larger (or smaller) than the mesh
#: is in other units or at another scale.
SCALE_MISMATCH = 5.0


#: A driver whose first pose turns the mesh's up axis by more than this (degrees) is likely
#: in other axes (a Z-up file against a Y-up one).
UP_TURN = 60.0


def _warn_up_axes(scene: Scene, rest: np.ndarray, posed: np.ndarray, mesh: str) -> None:
    """Warn when the driver's first pose is the rest mesh turned onto its side: the best
    rotation from the rest vertices to the driver's (the same vertices) takes one's up axis
    far from the other's, as a Z-up mesh against a Y-up driver does (its gravity then pulls
    sideways)."""
    R = best_turn(rest, posed)
    if R is None:
        return
    y = np.array([0.0, 1.0, 0.0])
    turn = float(np.degrees(np.arccos(np.clip(R.apply(y) @ y, -1.0, 1.0))))
    if turn <= UP_TURN:
        return
    mesh_z_up = float(R.apply([0.0, 0.0, 1.0]) @ y) > 0.7  # the mesh's z is the driver's up
    driver_z_up = float(R.apply(y)[2]) > 0.7  # the mesh's up is the driver's z
    unit_free = Path(scene.drive.path).suffix.lower() in UNIT_FREE
    if scene.drive.up == "z" and scene.mesh.up == "y":  # the setting given is the likely slip
        remedy = ('drive.up_axis = "z" turns the driver: leave it out if the driver file is '
                  "y up")
    elif mesh_z_up and scene.mesh.up == "y":
        remedy = 'the mesh file looks Z-up: set mesh.up_axis = "z"'
    elif scene.mesh.up == "z" and unit_free and scene.drive.up == "y":
        remedy = ('mesh.up_axis turns the mesh only, and the driver looks Z-up: set '
                  'drive.up_axis = "z" as well')
    elif driver_z_up and unit_free and scene.drive.up == "y":
        remedy = 'the driver looks Z-up: set drive.up_axis = "z"'
    elif scene.mesh.up == "z" and not unit_free:
        remedy = ("mesh.up_axis turns the mesh only, and the driver looks Z-up although its "
                  "reader turns it to y up by its format's rules: export it from the same "
                  "object as the mesh")
    elif scene.drive.up == "z":
        remedy = ('drive.up_axis = "z" turns the driver: leave it out if the driver file is '
                  "y up")
    else:
        remedy = ("export the mesh and the driver with the same up axis (y, or mesh.up_axis = "
                  '"z" for a Z-up mesh)')
    warn(
        f"{scene.where()}: drive.path = {show(scene.drive.path)}: its first pose is {mesh} "
        f"turned by {turn:.0f} degrees from its up axis: the two are likely in other axes "
        f"(gravity would pull the free parts sideways); {remedy}, unless the driver starts "
        "with the body on its side")


def _units_remedy(scene: Scene, ratio: float, size: float) -> str:
    """How to bring a driver ``ratio`` times the size of the mesh (``size`` m across) to its
    scale: a power of ten is units; the one of the two whose size is implausible for metres
    is in other units (mesh.scale for the mesh; exporting in metres for the driver).  USD
    drivers are read in metres by their metersPerUnit, which USD takes as 0.01 (centimetres)
    in a stage that does not give it."""
    from wiggly.mesh.model import PLAUSIBLE_SIZE

    power = math.log10(ratio)
    usd = Path(scene.drive.path).suffix.lower() in (".usd", ".usda", ".usdc")
    usd_note = (" (a USD driver is read in metres by its stage's metersPerUnit, and a stage "
                "without one counts as centimetres: author metersPerUnit)" if usd else "")
    if abs(power - round(power)) > 0.05 or round(power) == 0:
        return (f"scale the mesh by mesh.scale, or export the driver at the mesh's scale"
                f"{usd_note}")
    factor = 10.0 ** round(power)
    scale = scene.mesh.metres_per_unit
    unit_free = Path(scene.drive.path).suffix.lower() in UNIT_FREE
    drive_scale = scene.drive.metres_per_unit
    # glTF and USD are read in metres by their own units; Blender writes its units as metres
    blender = "" if unit_free else " (Blender writes its scene's units as the file's metres)"
    if scale != 1.0 and abs(math.log10(factor * scale)) < 0.05:  # the scale made the ratio
        made = (f"mesh.scale = {scale:g} makes the mesh {1 / scale:g} times "
                f"{'smaller' if scale < 1 else 'larger'} than its file")
        if drive_scale == 1.0:  # the driver was likely written in the mesh file's units
            return (f"{made}, and the driver is read in metres{blender}: set drive.scale = "
                    f"{scale:g} as well if it is in the mesh file's units, or leave "
                    "mesh.scale out if the mesh file is in metres")
        return f"{made}: leave it out if the file is in metres, as the driver is"
    if drive_scale != 1.0 and abs(math.log10(factor / drive_scale)) < 0.05:
        return (f"drive.scale = {drive_scale:g} makes the driver {1 / drive_scale:g} times "
                f"{'smaller' if drive_scale < 1 else 'larger'} than its files: leave it out if "
                "they are in metres, as the mesh is")
    if not PLAUSIBLE_SIZE[0] <= size <= PLAUSIBLE_SIZE[1]:
        return (f"the mesh, {size:.3g} m across, is likely in other units: set mesh.scale = "
                f"{factor * scene.mesh.metres_per_unit:g}")
    return (f"the driver is likely in other units{blender}: set drive.scale = "
            f"{drive_scale / factor:g}, or export it in metres{usd_note}")


def check_driver_against(scene: Scene, vertices: int, faces: np.ndarray, mesh: str,
                         p: Problems, rest: np.ndarray | None = None) -> None:
    """The driver animates the surface just read (``vertices`` vertices, triangles
    ``faces``, file ``mesh``; ``rest`` its positions) at the same scale, and some of its
    frames fall in the shot: checked before tetrahedralizing."""
    if scene.drive is None:
        return
    try:
        driver = scene_driver(scene)
    except WigglyInputError as err:
        p.add(str(err).removeprefix(f"{scene.where()}: "))
        return
    why = driver.mismatch(vertices, faces, mesh)
    if why is not None:
        p.add(f"drive.path = {show(scene.drive.path)}: {why}")
    elif rest is not None:
        size, posed = diagonal(rest), diagonal(driver.positions[0])
        ratio = posed / size if size > 0 else 1.0
        if not 1.0 / SCALE_MISMATCH <= ratio <= SCALE_MISMATCH:
            p.add(f"drive.path = {show(scene.drive.path)}: its first pose is {ratio:.3g} times "
                  f"the size of {mesh} ({posed:.3g} m against {size:.3g} m): the driver and the "
                  f"mesh must be in the same units and scale; {_units_remedy(scene, ratio, size)}")
        else:
            _warn_up_axes(scene, rest, driver.positions[0], mesh)
    if scene.time.end is None and scene.time.duration is None:
        return  # check_drive has said so
    start, end = scene.time_range()
    drive = scene.drive
    try:  # the frames in the shot that the solve will need
        if scene.secondary_motion:
            secondary_frames(driver, start=start, end=end, loop=scene.time.loop,
                             offset=drive.offset, driver_range=drive.range)
        else:
            keyed_frames(driver, offset=drive.offset, driver_range=drive.range, start=start,
                         end=end)
    except WigglyInputError as err:
        p.add(f"drive.path = {show(drive.path)}: {err}")


def driven_vertices(scene: Scene, groups: dict[str, np.ndarray]) -> np.ndarray:
    """Surface vertices of the driven groups (their union, ascending)."""
    return np.unique(np.concatenate([groups[g] for g in scene.drive.groups]))


def driven_body(scene: Scene, body, groups: dict[str, np.ndarray]):
    """``body`` with the driver's shapes added to its modes (``drive.enrich``, the default),
    else ``body`` itself."""
    drive = scene.drive
    if drive is None or not drive.adds_shapes:
        return body
    driver = scene_driver(scene)
    with activity("adding the driver's shapes to the modes"):
        out = enrich(body, driver, driven_vertices(scene, groups),
                     warped=scene.simulation.warp)
    say(f"{body.r} modes + {counted(out.r - body.r, 'driver shape')}")
    return out


def driven_keyframes_of(scene: Scene, body, groups: dict[str, np.ndarray]) -> list[Keyframe]:
    """The keyframes of ``[drive]`` with ``physics = "keys"`` (none otherwise): the driven
    groups keyed to the driver at every driver frame in the shot."""
    drive = scene.drive
    if drive is None or scene.secondary_motion:
        return []
    driver = scene_driver(scene)
    start, end = scene.time_range()
    try:
        keys = driven_keyframes(
            body, driver, driven_vertices(scene, groups),
            stiffness=DRIVE_STIFFNESS if drive.stiffness is None else drive.stiffness,
            offset=drive.offset, driver_range=drive.range, start=start, end=end,
            name=f"drive {'+'.join(drive.groups)}")
    except WigglyInputError as err:
        raise WigglyInputError(f"{scene.where()}: drive.path = {show(drive.path)}: "
                               f"{err}") from None
    say(f"driving {counted(len(keys[0].vertices), 'vertex')} ({'+'.join(drive.groups)}) at "
        f"{counted(len(keys), 'frame')} of {Path(drive.path).name} ({driver.kind})")
    return keys


def linear_start_of(scene: Scene, body, keyframes: list[Keyframe]) -> list[Keyframe] | None:
    """Where the warped solve of driven keys (``physics = "keys"``) starts: at the driver's
    whole poses (:func:`wiggly.drive.driver_poses`) with the scene's own keys unwarped
    (:func:`wiggly.solve.problem.unwarped`).  None (the solve's default start) otherwise, and
    for a linear shot."""
    from wiggly.solve.problem import unwarped

    drive = scene.drive
    if drive is None or scene.secondary_motion or not scene.simulation.warp:
        return None
    start, end = scene.time_range()
    with activity("the driver's poses, to start the warped solve"):
        poses = driver_poses(body, scene_driver(scene), offset=drive.offset,
                             driver_range=drive.range, start=start, end=end)
    return poses + unwarped([kf for kf in keyframes if kf.spec.get("kind") != "drive"], body)


def secondary_of(scene: Scene, body, groups: dict[str, np.ndarray], keyframes: list[Keyframe]):
    """The scene's secondary motion (``[drive]`` with ``physics = "secondary"``): the driver
    owns the driven groups, physics and ``keyframes`` move the rest
    (:func:`wiggly.drive.secondary_motion`)."""
    drive = scene.drive
    driver = scene_driver(scene)
    start, end = scene.time_range()
    driven = driven_vertices(scene, groups)
    try:
        with activity(f"secondary motion on {Path(drive.path).name} ({drive.free_modes} "
                      f"modes of the free parts)"):
            anim = secondary_motion(
                body, driver, driven, keyframes, start=start, end=end,
                warped=scene.simulation.warp, loop=scene.time.loop,
                free_mode_count=drive.free_modes, intensity=drive.intensity,
                offset=drive.offset, driver_range=drive.range)
    except WigglyInputError as err:
        raise WigglyInputError(f"{scene.where()}: drive.path = {show(drive.path)}: "
                               f"{err}") from None
    say(f"driving {counted(len(driven), 'vertex')} ({'+'.join(drive.groups)}) with "
        f"{counted(anim.info['driver_frames'], 'frame')} of {Path(drive.path).name} "
        f"({driver.kind}); {anim.info['free_modes']} modes of the free parts")
    return anim
