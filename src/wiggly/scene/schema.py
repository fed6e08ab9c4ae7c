"""The scene format's description, reading a scene file and checking it completely
(structure, then the references between keys) before anything is computed."""

from __future__ import annotations

import json
import math
import os
import re
import tomllib
from pathlib import Path

from wiggly.drive import DRIVER_EXTENSIONS
from wiggly.errors import WigglyInputError, warn
from wiggly.export import GLTF_TARGETS
from wiggly.fem import DENSITY_RANGE, YOUNG_RANGE
from wiggly.limits import (
    MAX_DURATION,
    MAX_FPS,
    MAX_FRAMES,
    MAX_MODES,
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    frame_count,
    frame_steps,
    whole_frames_remedy,
)
from wiggly.mesh import (
    BUILTIN_MODELS,
    DEFAULT_RESOLUTION,
    SURFACE_EXTENSIONS,
    UP_AXES,
    VOLUME_EXTENSIONS,
)
from wiggly.scene.drive import check_drive, check_drive_file
from wiggly.scene.spec import (
    CAMERAS,
    DRIVE_PHYSICS,
    FORMAT,
    GROUP_NAME,
    OUTPUT_EXTENSIONS,
    RIGID_MODES,
    Box,
    DampingSpec,
    DriveSpec,
    FromMesh,
    GroupSpec,
    Indices,
    KeyframeSpec,
    MaterialSpec,
    MeshSpec,
    Nearest,
    OutputSpec,
    Rest,
    Rigid,
    Scene,
    SimulationSpec,
    Sphere,
    TimeSpec,
)
from wiggly.scene.validation import (
    Array,
    Bool,
    ByType,
    Const,
    Map,
    Number,
    PositionTable,
    Problems,
    String,
    Table,
    Vector,
    did_you_mean,
    missing_file,
    show,
)

# --- the scene format ---------------------------------------------------------------------------


def _check_box(d: dict, path: str, p: Problems) -> None:
    lo, hi = d["min"], d["max"]
    bad = [a for a, x, y in zip("xyz", lo, hi, strict=True) if x > y]
    if bad:
        raise p.bad(f"{path}.min = {show(list(lo))} exceeds {path}.max = {show(list(hi))} "
                    f"in {', '.join(bad)}; min must be <= max in every coordinate")


def _check_time(d: dict, path: str, p: Problems) -> None:
    start = d.get("start", 0.0)
    if "end" in d and d["end"] <= start:
        raise p.bad(f"{path}.end = {show(d['end'])} must be after {path}.start = {show(start)}")
    if "end" in d and d["end"] - start > MAX_DURATION:
        raise p.bad(f"{path}.end = {show(d['end'])} makes a shot of {d['end'] - start:g} s; "
                    f"shots may last at most {MAX_DURATION:g} s (wiggly.limits.MAX_DURATION)")


_POSITIVE = {"gt": 0.0}
_YOUNG = {"ge": YOUNG_RANGE[0], "le": YOUNG_RANGE[1]}
_SELECTOR_SPECS = {
    "box": Table({"min": Vector(3, unit="m"), "max": Vector(3, unit="m")},
                  required=("min", "max"), check=_check_box,
                  make=lambda d: Box(d["min"], d["max"]),
                  doc="vertices with min <= x <= max in every coordinate"),
    "sphere": Table({"center": Vector(3, unit="m"), "radius": Number(unit="m", **_POSITIVE)},
                     required=("center", "radius"),
                     make=lambda d: Sphere(d["center"], d["radius"]),
                     doc="vertices with |x - center| <= radius"),
    "nearest": Table({"points": Array(Vector(3, unit="m"), min_items=1,
                                        what="an array of [x, y, z] points"),
                       "count": Number(integer=True, ge=1, doc="vertices per point (default 1)")},
                      required=("points",), make=lambda d: Nearest(d["points"],
                                                                   d.get("count", 1)),
                      doc="the count nearest vertices to each point"),
    "indices": Array(Number(integer=True, ge=0), min_items=1, unique=True,
                      what="an array of distinct vertex indices (integers >= 0)",
                      doc="explicit vertex indices (0-based); absolute targets follow this order"),
    "from_mesh": String(doc="name of a vertex group stored in the mesh file"),
}


def _make_group(d: dict) -> GroupSpec:
    kind = next(k for k in _SELECTOR_SPECS if k in d)
    sel = d[kind]
    selector = Indices(sel) if kind == "indices" else FromMesh(sel) if kind == "from_mesh" \
        else sel
    return GroupSpec(selector, d.get("on", "surface"), d.get("color"), d.get("young"))


_GROUP = Table(
    {**_SELECTOR_SPECS,
     "on": String(enum=("surface", "tets"),
                   doc='"surface" (default): vertices of the user\'s surface; "tets": '
                       "vertices of the tet mesh"),
     "color": String(pattern=r"^#[0-9a-fA-F]{6}$", what='a color "#rrggbb"',
                      doc="color in previews and the editor"),
     "young": Number(unit="Pa", **_YOUNG,
                      doc="Young's modulus (Pa) of the group's tets (surface groups: the "
                          "tets nearest the surface they carry, inside included; on = \"tets\": "
                          "those whose corners are all in it) in place of [material] young: "
                          "a softer tail on a stiffer body; later groups win where groups "
                          "overlap")},
    one_of=tuple(_SELECTOR_SPECS), make=_make_group,
    doc="a named vertex group: exactly one selector")

_KEYFRAME = Table(
    {"time": Number(unit="s", doc="key time (s), within the shot's time range"),
     "group": String(doc="name of a group"),
     "position": ByType({str: Const("rest", Rest(), PositionTable.what),
                          dict: PositionTable()},
                         what='"rest" or a table with offset, absolute, or '
                              "rotation/translation (and optional center)",
                         doc="position target"),
     "velocity": Vector(3, "vx, vy, vz", "m/s", doc="target velocity (m/s) of every vertex"),
     "stiffness": Number(ge=0.0, doc="dimensionless weight (default 1e6)"),
     "c_A": Number(ge=0.0, doc="explicit position weight of eq. (6)"),
     "c_B": Number(ge=0.0, doc="explicit velocity weight of eq. (6)"),
     "name": String(min_length=0, what="a string", doc="label")},
    required=("time", "group"), any_of=("position", "velocity"),
    make=lambda d: KeyframeSpec(**d), what="a table ([[keyframes]])",
    doc="constraints on one group at one time")

def _check_drive_range(d: dict, path: str, p: Problems) -> None:
    if "range" in d and d["range"][0] > d["range"][1]:
        raise p.bad(f"{path}.range = {show(list(d['range']))} must be [first, last] with "
                    "first <= last (seconds of the driver's clock)")


def _extensions_pattern(extensions) -> str:
    return r"\.(" + "|".join("".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c
                                      for c in e[1:]) for e in extensions) + r")$"


_DRIVE = Table(
    {"path": String(pattern=_extensions_pattern(DRIVER_EXTENSIONS),
                     what="a driver file ending in " + ", ".join(DRIVER_EXTENSIONS),
                     doc="driver animation of the surface, relative to the scene file: glTF "
                         "(skinned or morph targets), USD (time-sampled points or UsdSkel), "
                         "an OBJ sequence (walk_####.obj, walk_000001.obj) or a wiggly .npz"),
     "group": ByType({str: String(what="a group name"),
                       list: Array(String(what="a group name"), min_items=1, unique=True)},
                      what="a group name or an array of group names",
                      doc="the driven group (or groups: their union), which follows the "
                          "driver (held on it, or keyed at every frame with physics = keys)"),
     "offset": Number(unit="s", doc="driver time t plays at shot time t + offset (default 0)"),
     "range": Vector(2, "first, last", "s",
                      doc="only driver frames with first <= t <= last (driver seconds) are "
                          "keyed (default: all)"),
     "physics": String(enum=DRIVE_PHYSICS,
                        doc='"secondary" (default): the driver is a moving rest state, the '
                            "driven group follows it as closely as the tet mesh can and physics "
                            "moves the free parts "
                            'during the animation; "keys": the driven group is keyed at every '
                            "driver frame and the whole body minimises the spacetime energy"),
     "free_modes": Number(integer=True, ge=1, le=MAX_MODES,
                           doc="secondary: modes of the free parts with the driven group held "
                               "(default 24)"),
     "intensity": Number(ge=0.0, le=100.0,
                          doc="secondary: scales the driver's inertial forces on the free "
                              "parts without changing their timing (1 physical, 0 no push: "
                              "gravity alone sags them; default 1)"),
     "stiffness": Number(ge=0.0, doc='physics = "keys": dimensionless weight of every driven '
                                       "key (default 1e12: the driven group meets the driver)"),
     "enrich": Bool(doc='physics = "keys": add the driver\'s shapes to the modal basis '
                         "(Rayleigh-Ritz), so that the driven group can follow it closely "
                         "(default true)"),
     "animation": ByType({str: String(), int: Number(integer=True, ge=0),
                          list: Array(ByType({str: String(), int: Number(integer=True, ge=0)},
                                             what="an animation name or index (integer >= 0)"),
                                      min_items=1, unique=True)},
                          what="an animation name or index (integer >= 0), or an array of them",
                          doc="glTF: the animation to play, by name or index, or several played "
                              "together (a rig's action and a shape-key action; default: the "
                              "first)"),
     "object": String(doc="glTF: the mesh node (or mesh) to read; USD: the prim at or below "
                           "which meshes are read, by path or name (default: every mesh)"),
     "frame_rate": Number(gt=0.0, le=MAX_FPS, unit="frames/s",
                           doc="OBJ sequences without wiggly's # time comments: frame N is at "
                               "N / frame_rate s (default: time.fps)"),
     "scale": Number(gt=0.0, le=1e6,
                     doc="metres per unit of the driver files (0.01 for centimetres; "
                         "default 1), as mesh.scale is for the mesh; for glTF and USD, which "
                         "carry their own units, a factor on their metres (a Blender scene in "
                         "centimetres writes them 100 times too large)"),
     "up_axis": String(enum=UP_AXES,
                       doc='OBJ sequences and npz: the driver files\' up axis, "y" (default) '
                           'or "z" (turned to y up when read), as mesh.up_axis is for the '
                           "mesh; glTF and USD drivers carry their own axes")},
    required=("path", "group"), check=_check_drive_range, make=lambda d: DriveSpec(**d),
    doc="secondary motion on an existing animation: a driver animation of the surface moves "
        "the driven group; the rest moves freely, driven by physics")

OUTPUT_PATTERN = r"\.(" + "|".join(
    "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else c for c in e[1:])
    for e in OUTPUT_EXTENSIONS) + r")$"

SCENE_FORMAT = Table(
    {"format": Number(integer=True, ge=1, le=FORMAT, doc="scene format version",
                       what=f"{FORMAT} (the newest format this version of wiggly reads)"),
     "mesh": Table(
         {"path": String(doc='mesh file, relative to the scene file, or "builtin:critter", '
                              '"builtin:plant", "builtin:bar"'),
          "resolution": Number(integer=True, ge=MIN_RESOLUTION, le=MAX_RESOLUTION,
                                doc="tet edges along the bounding-box diagonal (default "
                                    f"{DEFAULT_RESOLUTION})"),
          "edge_length": Number(unit="m", **_POSITIVE, doc="target tet edge length (m)"),
          "repair": Bool(doc="accept open, non-manifold or self-intersecting surfaces and "
                              "let fTetWild fill them (default true; false refuses them)"),
          "scale": Number(gt=0.0, le=1e6,
                          doc="metres per unit of the mesh file: its coordinates are "
                              "multiplied by it when read (0.01 for centimetres, 0.001 for "
                              "millimetres; default 1); everything else in the scene is in "
                              "metres, on the scaled mesh"),
          "up_axis": String(enum=UP_AXES,
                            doc='the mesh file\'s up axis: "y" (default: glTF, Blender\'s '
                                'exports) or "z" (CAD, 3ds Max, many STL files: turned to y '
                                "up when read); the rest of the scene is y up")},
         required=("path",), exclusive=(("resolution", "edge_length"),),
         make=lambda d: MeshSpec(**d), doc="the model"),
     "material": Table(
         {"young": Number(unit="Pa", **_YOUNG, doc="Young's modulus E (Pa)"),
          "poisson": Number(ge=0.0, lt=0.5, doc="Poisson ratio"),
          "density": Number(unit="kg/m^3", ge=DENSITY_RANGE[0], le=DENSITY_RANGE[1],
                            doc="density (kg/m^3)")},
         make=lambda d: MaterialSpec(**d)),
     "damping": Table(
         {"alpha": Number(ge=0.0, unit="1/s", doc="mass-proportional damping (1/s)"),
          "beta": Number(ge=0.0, unit="s", doc="stiffness-proportional damping (s)")},
         make=lambda d: DampingSpec(**d), doc="Rayleigh damping D = alpha M + beta K"),
     "simulation": Table(
         {"gravity": Vector(3, "gx, gy, gz", "m/s^2", doc="gravity (m/s^2)"),
          "modes": Number(integer=True, ge=1, le=MAX_MODES,
                           doc="number of eigenmodes (rigid ones included)"),
          "warp": Bool(doc="rotation-strain warping (false: linear)"),
          "lumped_mass": Bool(doc="lumped instead of consistent mass matrix"),
          "fixed": Array(String(what="a group name"), unique=True,
                          what="an array of group names", doc="groups held at rest"),
          "preroll": Number(ge=0.0, unit="s",
                             doc="seconds of rest before the start (default: the duration)")},
         make=lambda d: SimulationSpec(**d)),
     "time": Table(
         {"start": Number(unit="s"),
          "end": Number(unit="s"),
          "duration": Number(unit="s", gt=0.0, le=MAX_DURATION),
          "fps": Number(gt=0.0, le=MAX_FPS, doc="frames per second of the outputs"),
          "loop": Bool(doc="a periodic shot: the end is the start (positions and velocities), "
                            "and it plays as a cycle with no seam")},
         exclusive=(("end", "duration"),), check=_check_time, make=lambda d: TimeSpec(**d),
         doc="time range (default: start 0, end at the last keyframe, at least 1 s)"),
     "groups": Map(_GROUP, GROUP_NAME,
                    "group names may contain only letters, digits, '_' and '-'",
                    doc="named vertex groups"),
     "keyframes": Array(_KEYFRAME, as_list=True, what="an array of tables ([[keyframes]])"),
     "output": Table(
         {"paths": Array(String(pattern=OUTPUT_PATTERN,
                                  what="a file name ending in "
                                       + ", ".join(OUTPUT_EXTENSIONS)),
                          unique=True, doc="output files, by extension"),
          "overwrite": Bool(doc="replace existing outputs"),
          "size": Vector(2, item=Number(integer=True, ge=16, le=8192),
                          what="[width, height] in pixels (integers from 16 to 8192)",
                          doc="video size in pixels (default [960, 540])"),
          "camera": ByType({str: String(enum=CAMERAS),
                             list: Vector(2, "azimuth, elevation", "degrees")},
                            what=" or ".join(json.dumps(c) for c in CAMERAS)
                            + " or [azimuth, elevation] in degrees",
                            doc="preview camera"),
          "frame_start": Number(integer=True, ge=-1_000_000, le=1_000_000,
                                 doc="glTF/USD frame of the first output frame: frame k lands "
                                     "on frame_start + k at the output fps (default: the "
                                     "shot's own time: USD time code t * fps; glTF moves a "
                                     "negative start, and a loop's start, to 0 s)"),
          "gltf_targets": String(enum=GLTF_TARGETS,
                                  doc='glTF morph targets: "frames" (one per frame, default) '
                                      'or "modes" (one per mode, weights q(t); linear shots '
                                      "only: exact and compact)")},
         make=lambda d: OutputSpec(**d)),
     "drive": _DRIVE,
     },
    required=("mesh",), make=lambda d: Scene(**d), what="a TOML document")

def scene_schema() -> dict:
    """The JSON Schema (draft 2020-12) of scene files, generated from the validator's specs.

    It checks the structure (keys, types, ranges); references between keys (a keyframe's
    group exists, its time lies in the shot) and checks against the mesh are the validator's.
    """
    s = SCENE_FORMAT.schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": "wiggly scene",
            "description": "A wiggly scene file (TOML), format 1: see docs/scene-format.md.",
            **s}


# ----------------------------------------------------------------------------------------------
# reading and checking


def load_scene(path: str | os.PathLike[str], *, output_fps: float | None = None) -> Scene:
    """Read and check a scene file; every problem raises one :class:`WigglyInputError` that
    lists all problems found (file, key path, value, what is allowed).  ``output_fps``: the
    outputs' frame rate will be this one (``--fps``), so the frame-count checks of the file's
    own rate (a loop's whole frames, an end between frames) are left to
    :func:`wiggly.scene.with_overrides`."""
    path = Path(path)
    if not path.is_file():
        raise WigglyInputError(f"{path}: no such scene file" if not path.exists()
                               else f"{path}: is not a file")
    ext = path.suffix.lower()
    if ext in SURFACE_EXTENSIONS or ext in VOLUME_EXTENSIONS:
        raise WigglyInputError(
            f"{path}: is a mesh, not a scene file (.toml); write a scene that names it as "
            f"mesh.path (docs/scene-format.md), or open it in the editor: wiggly edit {path}")
    return scene_from_dict(read_toml(path), where=str(path), source=path.resolve(),
                           output_fps=output_fps)


def read_toml(path: Path) -> dict:
    """A TOML file's content; an unreadable or invalid one raises :class:`WigglyInputError`
    saying what is wrong where (:func:`toml_message`)."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise WigglyInputError(f"{path}: not a text file (UTF-8): {err}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise WigglyInputError(f"{path}: {toml_message(err, text)}") from None


def toml_message(err: tomllib.TOMLDecodeError, text: str) -> str:
    """tomllib's complaint in a user's words: keys as dotted names (not Python tuples), the
    key given twice named, a hint for a table declared both ways, and JSON recognized."""
    message = re.sub(r"\(((?:'[^']*',? ?)+)\)",
                     lambda m: ".".join(re.findall(r"'([^']*)'", m.group(1))), str(err))
    if text.lstrip().startswith("{"):
        return ("not TOML (this looks like JSON): scene and sweep files are TOML, with "
                f"[tables] and key = value lines (docs/scene-format.md); {message}")
    hint = ""
    declared = re.match(r"Cannot declare (\S+) twice", message)
    line = re.search(r"at line (\d+)", message)
    if declared:
        name = declared.group(1)
        hint = (f"; [{name}] and [[{name}]] cannot both appear: a list of tables is written "
                f"[[{name}]] before each entry" if f"[[{name}]]" in text.replace(" ", "") else
                f"; [{name}] appears twice: give its keys in one table")
    elif message.startswith("Cannot overwrite a value") and line:
        row = text.splitlines()[int(line.group(1)) - 1] if int(line.group(1)) <= len(
            text.splitlines()) else ""
        key = row.split("=", 1)[0].strip()
        if key:
            hint = f"; {key!r} is given twice in its table"
    return f"not valid TOML: {message}{hint}"


def scene_from_dict(data: dict, where: str = "scene", source: Path | None = None, *,
                    output_fps: float | None = None) -> Scene:
    """Check a parsed scene (the TOML as dicts and lists) and build the :class:`Scene`;
    ``source`` is the file it came from (relative paths resolve against its directory and the
    mesh file must exist); ``output_fps`` as in :func:`load_scene`."""
    p = Problems(where)
    scene = p.parse(SCENE_FORMAT, data)
    scene.source = source
    _cross_check(scene, p, output_fps)
    if source is not None:
        _check_files(scene, p)
    p.raise_if_any()
    return scene


def _frame_steps(scene) -> tuple[float, bool]:
    """The shot's length in frame steps, and whether that is a whole number (to rounding)."""
    t0, t1 = scene.time_range()
    return frame_steps(t1 - t0, scene.time.fps)


def loop_cycle_problem(scene, fps_from: str = "") -> str | None:
    """What is wrong with a looped shot's frame rate, or None: a loop needs a whole number
    of frames per cycle (its last frame is its first)."""
    cycle, whole = _frame_steps(scene)
    if not scene.time.loop or whole:
        return None
    t0, t1 = scene.time_range()
    return (f"time.loop = true needs a whole number of frames per cycle: {t1 - t0:g} s at "
            f"{scene.time.fps:g} fps{fps_from} is {cycle:.6g} frames; "
            f"{whole_frames_remedy(t1 - t0, scene.time.fps)}")


def partial_frame_note(scene, fps_from: str = "") -> str | None:
    """What to say of a shot whose set length is not a whole number of frames (the outputs
    end on the last whole frame), or None; ``fps_from`` names where the fps came from."""
    steps, whole = _frame_steps(scene)
    if scene.time.loop or (scene.time.end is None and scene.time.duration is None) or whole:
        return None
    t0, t1 = scene.time_range()
    fps = scene.time.fps
    last = t0 + (frame_count(t1 - t0, fps) - 1) / fps
    return (f"the shot [{t0:g}, {t1:g}] s is not a whole number of frames at {fps:g} "
            f"fps{fps_from}: its last frame is at {last:.6g} s, and the outputs end there; "
            f"to end on a frame, use end = {last:.6g} or "
            f"{t0 + math.ceil(steps - 1e-9) / fps:.6g}")


def _warn_seam_keys(scene: Scene, where: str, t0: float, t1: float) -> None:
    """In a loop the end is the start: keys of one group there that say different things
    cannot both be met (the missed-keys warning would then advise a higher stiffness)."""
    tol = 1e-9 * max(t1 - t0, 1.0)
    first = [(j, k) for j, k in enumerate(scene.keyframes) if abs(k.time - t0) <= tol]
    last = [(j, k) for j, k in enumerate(scene.keyframes) if abs(k.time - t1) <= tol]
    for i, a in first:
        for j, b in last:
            differ = [what for what, x, y in (("position", a.position, b.position),
                                              ("velocity", a.velocity, b.velocity))
                      if x is not None and y is not None and x != y]
            if a.group == b.group and differ:
                warn(
                    f"{where}: keyframes[{i}] (t = {t0:g} s) and keyframes[{j}] (t = {t1:g} s) "
                    f"key group {a.group!r} with another {' and '.join(differ)}, but in a loop "
                    f"t = {t1:g} s is t = {t0:g} s: both cannot be met; give them the same "
                    "target, or keep one of them")


def _warn_twin_keys(scene: Scene, where: str, span: float) -> None:
    """Keys of one group at one time that say different things cannot both be met: the
    motion lands between them, and the missed-keys warning would advise a higher stiffness,
    which cannot help (a review keyed a box's top 5 cm left and 5 cm right at 0.5 s)."""
    tol = 1e-9 * max(span, 1.0)
    keys = list(enumerate(scene.keyframes))
    for n, (i, a) in enumerate(keys):
        for j, b in keys[n + 1:]:
            differ = [what for what, x, y in (("position", a.position, b.position),
                                              ("velocity", a.velocity, b.velocity))
                      if x is not None and y is not None and x != y]
            if a.group == b.group and abs(a.time - b.time) <= tol and differ:
                warn(
                    f"{where}: keyframes[{i}] and keyframes[{j}] both key group {a.group!r} at "
                    f"t = {a.time:g} s, with another {' and '.join(differ)}: both cannot be "
                    "met, and the motion lands between them; give them the same target, or "
                    "keep one of them")


def _cross_check(scene: Scene, p: Problems, output_fps: float | None = None) -> None:
    """Checks between keys: group names, key times in the shot's time range; the frame
    counts at ``output_fps`` when given (see :func:`load_scene`)."""
    names = list(scene.groups)
    listing = ", ".join(names) if names else "none are defined ([groups.<name>])"
    for j, kf in enumerate(scene.keyframes):
        if kf.group not in scene.groups:
            p.add(f"keyframes[{j}].group = {show(kf.group)} is not a group"
                  f"{did_you_mean(kf.group, names)}; groups are: {listing}")
    for j, g in enumerate(scene.simulation.fixed):
        if g not in scene.groups:
            p.add(f"simulation.fixed[{j}] = {show(g)} is not a group{did_you_mean(g, names)}; "
                  f"groups are: {listing}")
    t0, t1 = scene.time_range()
    for j, kf in enumerate(scene.keyframes):
        if not t0 - 1e-9 <= kf.time <= t1 + 1e-9:
            who = f"{show(kf.name)} of group {show(kf.group)}" if kf.name else \
                f"of group {show(kf.group)}"
            p.add(f"keyframes[{j}].time = {show(kf.time)} is outside the shot's time range "
                  f"[{t0}, {t1}] s (the keyframe {who}): move it, or the shot's start or end")
    if scene.mesh.path.startswith("builtin:") and \
            scene.mesh.path.removeprefix("builtin:") not in BUILTIN_MODELS:
        p.add(f"mesh.path = {show(scene.mesh.path)} is not a bundled model; use one of "
              + ", ".join(f'"builtin:{m}"' for m in BUILTIN_MODELS))
    if t1 - t0 > MAX_DURATION and scene.time.end is None and scene.time.duration is None:
        p.add(f"the shot runs from {t0:g} s to the last keyframe at {t1:g} s, longer than "
              f"{MAX_DURATION:g} s (wiggly.limits.MAX_DURATION); check the keyframe times")
    fps = scene.time.fps if output_fps is None else float(output_fps)
    frames = frame_count(t1 - t0, fps)
    cycle = loop_cycle_problem(scene) if output_fps is None else None
    if cycle is not None:
        p.add(cycle)
    if frames <= MAX_FRAMES and output_fps is None:
        note = partial_frame_note(scene)
        if note is not None:
            warn(f"{p.where}: {note}")
    if scene.time.loop and not scene.simulation.fixed and scene.drive is None and not any(
            kf.position is not None for kf in scene.keyframes):
        what = ("velocity keys do not say where it is" if scene.keyframes else
                "nothing says where it is")
        p.add("time.loop = true, but no keyframe has a position, no group is fixed and "
              f"nothing drives the body: {what}, so the looped motion is undetermined (a "
              "loop has no rest before it); key a group's position (e.g. position = "
              "\"rest\"), or fix a group")
    if scene.time.loop and scene.simulation.preroll not in (None, 0.0):
        p.add(f"simulation.preroll = {show(scene.simulation.preroll)} does not apply to a "
              "looped shot (time.loop = true): a loop has no before; leave it out")
    if scene.time.loop:
        _warn_seam_keys(scene, p.where, t0, t1)
    _warn_twin_keys(scene, p.where, t1 - t0)
    if frames > MAX_FRAMES and t1 - t0 <= MAX_DURATION:
        which = f"time.fps = {show(scene.time.fps)}" if output_fps is None else f"--fps {fps:g}"
        p.add(f"{which} makes {frames} frames of a {t1 - t0:g} s "
              f"shot, more than {MAX_FRAMES} (wiggly.limits.MAX_FRAMES); use fps <= "
              f"{math.floor((MAX_FRAMES - 1) / (t1 - t0)):g}")
    check_drive(scene, p)
    for j, kf in enumerate(scene.keyframes):
        replaced = [f"{w} = {show(v)}" for w, v, target in
                    (("c_A", kf.c_A, kf.position), ("c_B", kf.c_B, kf.velocity))
                    if v is not None and target is not None]
        if kf.stiffness is not None and replaced:
            warn(f"{p.where}: keyframes[{j}]: {' and '.join(replaced)} replace"
                 f"{'s' if len(replaced) == 1 else ''} stiffness = "
                 f"{show(kf.stiffness)} (stiffness sets only the weights not given "
                 "explicitly); give one of them")
        turn = kf.position.rotation if isinstance(kf.position, Rigid) else ()
        if any(abs(a) >= 180.0 for a in turn):
            wrapped = [(a + 180.0) % 360.0 - 180.0 for a in turn]
            warn(
                f"{p.where}: keyframes[{j}].position.rotation = {show(list(turn))}: a key is a "
                "placement, so a turn of 180 degrees or more is taken the short way (here "
                f"{show([round(a, 6) for a in wrapped])}) and a whole turn is no turn; to spin "
                "further, key the turn in steps under 180 degrees (e.g. a key every 90)")
    if not scene.simulation.fixed and scene.simulation.modes < RIGID_MODES:
        p.add(f"simulation.modes = {scene.simulation.modes} is fewer than the {RIGID_MODES} "
              "rigid modes of a free body (simulation.fixed holds no group), which the basis "
              f"must contain; use at least {RIGID_MODES + 1} ({RIGID_MODES} rigid and the "
              "elastic ones; the default is 40), or hold a group fixed")


def _check_files(scene: Scene, p: Problems) -> None:
    check_drive_file(scene, p)
    if scene.mesh.path.startswith("builtin:"):
        return
    f = scene.mesh_file()
    if not f.is_file():
        p.add(missing_file("mesh.path", scene.mesh.path, f))
