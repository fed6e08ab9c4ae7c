"""The scene as dataclasses: one shot, its field names the TOML keys of
``docs/scene-format.md``."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from wiggly.body import DEFAULT_MODES, Damping
from wiggly.errors import WigglyInputError
from wiggly.export import SUPPORTED
from wiggly.fem import DEFAULT_GRAVITY, Material
from wiggly.mesh import resolve_builtin
from wiggly.render import VIDEO_FORMATS
from wiggly.solve.animation import DEFAULT_FPS

#: Scene format version written by :func:`save_scene` and the newest one read.
FORMAT = 1
GEOMETRY_EXTENSIONS = tuple(SUPPORTED)  # wiggly.export writes these
PREVIEW_EXTENSIONS = (*VIDEO_FORMATS, ".png")  # videos and contact sheets
OUTPUT_EXTENSIONS = GEOMETRY_EXTENSIONS + PREVIEW_EXTENSIONS
CAMERAS = ("three_quarter", "front", "side", "back", "top")
#: How a ``[drive]`` moves the body (:class:`DriveSpec`).
DRIVE_PHYSICS = ("secondary", "keys")
#: Highlight colors of keyframed groups without a ``color`` (matplotlib's tab10).
PALETTE = ("#ff7f0e", "#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
           "#17becf", "#bcbd22", "#7f7f7f")
GROUP_NAME = r"^[A-Za-z0-9_-]+$"
#: Rigid modes of a free body (3 translations, 3 rotations, Schulz et al. 2014, eq. (5)).
RIGID_MODES = 6
#: Target positions drawn per keyframe in previews (a subset of large groups).
MAX_TARGETS = 60

Vec3 = tuple[float, float, float]


# ----------------------------------------------------------------------------------------------
# the scene as dataclasses (field names are the TOML keys)


def _floats(v, n: int | None = None) -> tuple:
    """A tuple of floats (vectors are tuples so that scenes compare with ==)."""
    out = tuple(float(x) for x in v)
    if n is not None and len(out) != n:
        raise WigglyInputError(f"expected {n} numbers, got {len(out)}: {list(v)!r}")
    return out


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)


class _FileUnits:
    """The ``scale`` and ``up_axis`` of a file's coordinates (the mesh's, a driver's)."""

    scale: float | None
    up_axis: str | None

    @property
    def metres_per_unit(self) -> float:
        """What the file's coordinates are multiplied by (``scale``, default 1)."""
        return 1.0 if self.scale is None else self.scale

    @property
    def up(self) -> str:
        """The file's up axis (``up_axis``, default "y")."""
        return self.up_axis or "y"


@dataclass(frozen=True)
class MeshSpec(_FileUnits):
    """``[mesh]``: the model file and how to tetrahedralize it."""

    path: str
    resolution: int | None = None
    edge_length: float | None = None
    repair: bool | None = None  # None: true (accept imperfect surfaces, with a warning)
    scale: float | None = None  # metres per unit of the file; None: 1
    up_axis: str | None = None  # the file's up axis, "y" or "z"; None: "y"


@dataclass(frozen=True)
class MaterialSpec:
    """``[material]``: Young's modulus (Pa), Poisson ratio, density (kg/m^3)."""

    young: float = Material.young
    poisson: float = Material.poisson
    density: float = Material.density


@dataclass(frozen=True)
class DampingSpec:
    """``[damping]``: Rayleigh damping D = alpha M + beta K."""

    alpha: float = Damping.alpha
    beta: float = Damping.beta


@dataclass(frozen=True)
class SimulationSpec:
    """``[simulation]``: gravity, number of modes, warping, fixed groups, pre-roll."""

    gravity: Vec3 = DEFAULT_GRAVITY
    modes: int = DEFAULT_MODES
    warp: bool = True
    lumped_mass: bool = False
    fixed: tuple[str, ...] = ()
    preroll: float | None = None

    def __post_init__(self) -> None:
        _set(self, "gravity", _floats(self.gravity, 3))
        _set(self, "fixed", tuple(self.fixed))


@dataclass(frozen=True)
class TimeSpec:
    """``[time]``: the shot's range (``end`` or ``duration``) and the output frame rate."""

    start: float = 0.0
    end: float | None = None
    duration: float | None = None
    fps: float = DEFAULT_FPS
    loop: bool = False


@dataclass(frozen=True)
class Box:
    """Vertices with ``min <= x <= max`` (component-wise, inclusive)."""

    min: Vec3
    max: Vec3

    def __post_init__(self) -> None:
        _set(self, "min", _floats(self.min, 3))
        _set(self, "max", _floats(self.max, 3))


@dataclass(frozen=True)
class Sphere:
    """Vertices with ``|x - center| <= radius``."""

    center: Vec3
    radius: float

    def __post_init__(self) -> None:
        _set(self, "center", _floats(self.center, 3))


@dataclass(frozen=True)
class Nearest:
    """The ``count`` vertices nearest to each of ``points`` (their union)."""

    points: tuple[Vec3, ...]
    count: int = 1

    def __post_init__(self) -> None:
        _set(self, "points", tuple(_floats(p, 3) for p in self.points))


@dataclass(frozen=True)
class Indices:
    """Explicit vertex indices, in this order (absolute targets follow it)."""

    indices: tuple[int, ...]

    def __post_init__(self) -> None:
        _set(self, "indices", tuple(int(i) for i in self.indices))


@dataclass(frozen=True)
class FromMesh:
    """A named vertex group stored in the mesh file."""

    name: str


Selector = Box | Sphere | Nearest | Indices | FromMesh
#: The scene file's key of each group selector (``[groups.<name>] box = ...``)
SELECTOR_KEYS = {Box: "box", Sphere: "sphere", Nearest: "nearest", Indices: "indices",
                  FromMesh: "from_mesh"}


@dataclass(frozen=True)
class GroupSpec:
    """``[groups.<name>]``: one selector; ``on`` = "surface" (default) or "tets"; ``young``:
    a Young's modulus (Pa) of the group's tets in place of ``[material] young``."""

    selector: Selector
    on: str = "surface"
    color: str | None = None
    young: float | None = None


@dataclass(frozen=True)
class Rest:
    """``position = "rest"``."""


@dataclass(frozen=True)
class Offset:
    """``position = { offset = [dx, dy, dz] }``: rest + offset."""

    offset: Vec3

    def __post_init__(self) -> None:
        _set(self, "offset", _floats(self.offset, 3))


@dataclass(frozen=True)
class Absolute:
    """``position = { absolute = [[x, y, z], ...] }``: one row per group vertex."""

    positions: tuple[Vec3, ...]

    def __post_init__(self) -> None:
        _set(self, "positions", tuple(_floats(p, 3) for p in self.positions))


@dataclass(frozen=True)
class Rigid:
    """Rest vertices rotated (Euler XYZ, degrees) about ``center`` (default: centroid), then
    translated."""

    rotation: Vec3 = (0.0, 0.0, 0.0)
    translation: Vec3 = (0.0, 0.0, 0.0)
    center: Vec3 | None = None

    def __post_init__(self) -> None:
        _set(self, "rotation", _floats(self.rotation, 3))
        _set(self, "translation", _floats(self.translation, 3))
        if self.center is not None:
            _set(self, "center", _floats(self.center, 3))

    def matrix(self) -> np.ndarray:
        """The rotation matrix: X, then Y, then Z about the fixed axes (degrees)."""

        return Rotation.from_euler("xyz", self.rotation, degrees=True).as_matrix()


Position = Rest | Offset | Absolute | Rigid


@dataclass(frozen=True)
class KeyframeSpec:
    """One ``[[keyframes]]`` entry."""

    time: float
    group: str
    position: Position | None = None
    velocity: Vec3 | None = None
    stiffness: float | None = None
    c_A: float | None = None
    c_B: float | None = None
    name: str = ""

    def __post_init__(self) -> None:
        if self.velocity is not None:
            _set(self, "velocity", _floats(self.velocity, 3))

    @property
    def label(self) -> str:
        return self.name or self.group


@dataclass(frozen=True)
class DriveSpec(_FileUnits):
    """``[drive]``: a driver animation of the surface (``path``) that keys the vertices of
    ``group`` (one group name or several, their union) at every driver frame
    (:mod:`wiggly.drive`).  Driver time t plays at shot time t + ``offset``; only frames with
    driver time in ``range`` (inclusive) are keyed.  ``animation`` picks a glTF animation
    (name or index), ``object`` the glTF mesh node / USD prim to read, ``frame_rate`` times an
    OBJ sequence without time comments (default: ``time.fps``), ``scale`` and ``up_axis``
    bring an OBJ sequence or an npz in other units or axes to metres, y up (``scale`` also
    multiplies a glTF's or USD's own metres).
    ``physics = "secondary"`` (default) makes the driver a moving rest state and moves the
    free parts by physics (:func:`wiggly.drive.secondary_motion`, with ``free_modes`` and
    ``intensity``); ``physics = "keys"`` keys the driven group at every frame instead, with
    ``stiffness``, and ``enrich`` adds the driver's shapes to the modal basis
    (:func:`wiggly.drive.enrich`)."""

    path: str
    group: str | tuple[str, ...]
    offset: float = 0.0
    range: tuple[float, float] | None = None
    stiffness: float | None = None
    enrich: bool = True
    animation: str | int | tuple[str | int, ...] | None = None
    object: str | None = None
    frame_rate: float | None = None
    physics: str = "secondary"
    free_modes: int = 24
    intensity: float = 1.0
    scale: float | None = None  # metres per unit of the file (glTF, USD: on theirs); None: 1
    up_axis: str | None = None  # OBJ sequences and npz: the file's up axis; None: "y"

    def __post_init__(self) -> None:
        if not isinstance(self.group, str):
            _set(self, "group", tuple(self.group))
        if self.range is not None:
            _set(self, "range", _floats(self.range, 2))
        if isinstance(self.animation, list):
            _set(self, "animation", tuple(self.animation))

    @property
    def adds_shapes(self) -> bool:
        """The driver's shapes join the modal basis (``physics = "keys"`` with ``enrich``)."""
        return self.physics == "keys" and self.enrich

    @property
    def groups(self) -> tuple[str, ...]:
        """The driven groups' names."""
        return (self.group,) if isinstance(self.group, str) else self.group


@dataclass(frozen=True)
class OutputSpec:
    """``[output]``: files to write (by extension), overwrite, preview size and camera, and
    how glTF/USD files carry time (``frame_start``, ``gltf_targets``; None: the defaults)."""

    paths: tuple[str, ...] = ()
    overwrite: bool = False
    size: tuple[int, int] = (960, 540)
    camera: str | tuple[float, float] = "three_quarter"
    frame_start: int | None = None
    gltf_targets: str | None = None

    def __post_init__(self) -> None:
        _set(self, "paths", tuple(self.paths))
        _set(self, "size", tuple(int(s) for s in self.size))
        if not isinstance(self.camera, str):
            _set(self, "camera", _floats(self.camera, 2))


@dataclass
class Scene:
    """A whole scene file.  ``source`` (the file it was read from; relative paths resolve
    against its directory) does not take part in comparisons."""

    mesh: MeshSpec
    material: MaterialSpec = field(default_factory=MaterialSpec)
    damping: DampingSpec = field(default_factory=DampingSpec)
    simulation: SimulationSpec = field(default_factory=SimulationSpec)
    time: TimeSpec = field(default_factory=TimeSpec)
    groups: dict[str, GroupSpec] = field(default_factory=dict)
    keyframes: list[KeyframeSpec] = field(default_factory=list)
    output: OutputSpec = field(default_factory=OutputSpec)
    drive: DriveSpec | None = None
    format: int = FORMAT
    source: Path | None = field(default=None, compare=False)
    #: how messages name a scene that is not its file (a sweep's shot); None: its file
    label: str | None = field(default=None, compare=False)

    @property
    def base_dir(self) -> Path:
        """Directory that relative paths are relative to (the scene file's, else the cwd)."""
        return self.source.parent if self.source is not None else Path.cwd()

    @property
    def name(self) -> str:
        """The scene file's stem (else the mesh's)."""
        if self.source is not None:
            return self.source.stem
        return Path(self.mesh.path.removeprefix("builtin:")).stem

    def where(self) -> str:
        """How messages name this scene: its label, its file (relative to the cwd if
        inside), or "scene"."""
        if self.label is not None:
            return self.label
        if self.source is None:
            return "scene"
        try:
            return str(self.source.relative_to(Path.cwd()))
        except ValueError:
            return str(self.source)

    def group_colors(self) -> dict[str, str]:
        """Each group's colour: its own, else the palette's in the groups' order (previews,
        the editor)."""
        return {name: g.color or PALETTE[i % len(PALETTE)]
                for i, (name, g) in enumerate(self.groups.items())}

    @property
    def secondary_motion(self) -> bool:
        """A ``[drive]`` with ``physics = "secondary"``: the driver owns the driven groups
        and physics moves the rest (:func:`wiggly.drive.secondary_motion`)."""
        return self.drive is not None and self.drive.physics == "secondary"

    def mesh_file(self) -> Path:
        """The mesh file (``builtin:<name>`` resolved to the bundled model)."""
        p = self.mesh.path
        if p.startswith("builtin:"):
            return builtin_model(p.removeprefix("builtin:"))
        return self.resolve(p)

    def resolve(self, path: str | os.PathLike[str]) -> Path:
        """``path`` relative to the scene file's directory (``~`` expanded), with ``a/../b``
        written ``b`` where that names the same file (not through a symbolic link)."""
        p = Path(path).expanduser()
        joined = p if p.is_absolute() else self.base_dir / p
        tidy = Path(os.path.normpath(joined))
        if tidy == joined:
            return joined
        try:
            same = os.path.samefile(tidy, joined) if joined.exists() else not tidy.exists()
        except OSError:
            same = False
        return tidy if same else joined

    def time_range(self) -> tuple[float, float]:
        """(start, end) in seconds: ``end``, ``start + duration``, or the last keyframe time
        (at least ``start + 1``)."""
        t = self.time
        if t.end is not None:
            return t.start, t.end
        if t.duration is not None:
            return t.start, t.start + t.duration
        last = max((k.time for k in self.keyframes), default=t.start)
        return t.start, max(last, t.start + 1.0)


def builtin_model(name: str) -> Path:
    """Path of a bundled model (``critter``, ``plant``, ``bar``)."""
    return resolve_builtin(f"builtin:{name}")
