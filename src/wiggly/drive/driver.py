"""A driver animation of the user's surface, its topology check against the surface, and the
partial keyframes that key a vertex group to it at every driver frame."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from wiggly.body import Body
from wiggly.checks import vertex_indices
from wiggly.errors import WigglyInputError, counted
from wiggly.keyframes import Keyframe

__all__ = ["DRIVE_STIFFNESS", "Driver", "driven_keyframes", "filled_times", "following",
           "polygon_edges"]

#: Driver times closer than this (seconds) are one frame.
TIME_TOLERANCE = 1e-9


def _slack(bound: float) -> float:
    """How far past a range bound a driver time still counts as on it: TIME_TOLERANCE plus
    four single-precision steps at the bound (glTF stores key times as float32, so the
    frame shown at 0.8 s is stored as 0.800000012 s)."""
    return TIME_TOLERANCE + 4.0 * float(np.finfo(np.float32).eps) * abs(bound)
#: Default dimensionless stiffness of driven keys (see :class:`wiggly.Keyframe`): high, so
#: that the driven group meets the driver although following a skinned limb exactly takes
#: large forces (the driver's shapes are stiff, :mod:`wiggly.drive.basis`).
DRIVE_STIFFNESS = 1e12


@dataclass(frozen=True, eq=False)
class Driver:
    """An animation of the user's surface: what every driver reader returns.

    Attributes
    ----------
    times : (F,) float
        Frame times in seconds (the driver's clock), strictly increasing.
    positions : (F, n, 3) float
        Vertex positions per frame in metres, y up (wiggly's axes).
    faces : (k, 3) int
        Triangles (polygons split into fans), e.g. to draw the driver.
    edges : (e, 2) int
        The file's polygon edges (i < j, unique): what must match the surface's triangles
        (a triangulation of the same polygons has these edges and more).
    source : str
        The file, as messages name it.
    kind : str
        What was read ("glTF skin", "glTF morph targets", "USD points", ...).
    parts : tuple of str
        The meshes read, in order (USD prim paths, glTF node names), when the file names
        them: a file of several meshes is told how to keep one (``drive.object``).
    """

    times: np.ndarray
    positions: np.ndarray
    faces: np.ndarray
    edges: np.ndarray
    source: str
    kind: str
    parts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        times = np.asarray(self.times, np.float64)
        positions = np.asarray(self.positions, np.float64)
        where = f"{self.source}"
        if times.ndim != 1 or len(times) == 0 or positions.shape != (len(times),
                                                                      *positions.shape[1:]):
            raise WigglyInputError(f"{where}: a driver needs frame times (F,) and positions "
                                   f"(F, n, 3); got {times.shape} and {positions.shape}")
        if positions.ndim != 3 or positions.shape[2] != 3:
            raise WigglyInputError(f"{where}: positions have shape {positions.shape}; expected "
                                   "(F, n, 3)")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
            raise WigglyInputError(f"{where}: frame times must be finite and increasing")
        bad = np.argwhere(~np.isfinite(positions))
        if bad.size:
            k, v, _ = bad[0]
            raise WigglyInputError(f"{where}: the frame at t = {times[k]:g} s (frame {k + 1} of "
                                   f"{len(times)}) puts vertex {v} at "
                                   f"{positions[k, v].tolist()}; positions must be finite")
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "faces", np.asarray(self.faces, np.int64).reshape(-1, 3))
        object.__setattr__(self, "edges", np.asarray(self.edges, np.int64).reshape(-1, 2))

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def n_vertices(self) -> int:
        return self.positions.shape[1]

    @property
    def span(self) -> tuple[float, float]:
        """(first, last) frame time in seconds."""
        return float(self.times[0]), float(self.times[-1])

    def mismatch(self, vertices: int, faces: np.ndarray, surface: str) -> str | None:
        """Why this driver cannot drive the surface ``surface`` of ``vertices`` vertices and
        triangles ``faces``, or None: the vertex counts must be equal and every polygon edge
        of the driver must be an edge of a surface triangle (same vertices, same order)."""
        n = self.n_vertices
        if n != vertices:
            hint = ""
            glb = (".glb", ".gltf")
            if self.kind.startswith("glTF") != surface.lower().endswith(glb):
                hint = ("; glTF exporters split vertices at UV seams and sharp edges, and USD "
                        "and OBJ do not, so the same object has more vertices in glTF: give "
                        "the mesh and the driver in the same format (the glTF file as both)")
            if len(self.parts) > 1:
                listed = ", ".join(self.parts[:4]) + (", ..." if len(self.parts) > 4 else "")
                hint += (f"; the driver holds {len(self.parts)} meshes ({listed}): "
                         "drive.object keeps those of one name (object= in Python)")
            return (f"the driver {self.source} animates {counted(n, 'vertex')} but the surface "
                    f"{surface} has {counted(vertices, 'vertex')}; a driver must animate the "
                    f"same surface, with the same vertices in the same order (export both from "
                    f"the same object){hint}")
        if len(self.edges) == 0:
            return None
        known = _edge_codes(polygon_edges(faces), n)
        missing = ~np.isin(_edge_codes(self.edges, n), known)
        if missing.any():
            a, b = self.edges[np.flatnonzero(missing)[0]]
            hint = ""
            if not surface.lower().endswith((".glb", ".gltf")):
                hint = ("; for a rig of several objects, exporters list the objects in their "
                        "own orders (Blender's OBJ and USD differ), so export the rig as one "
                        "glTF file and give it as both the mesh and the driver")
            return (f"the driver {self.source} has the {counted(n, 'vertex')} of the surface "
                    f"{surface} but not its triangles: {int(missing.sum())} of its "
                    f"{len(self.edges)} edges join vertices that no triangle of the surface "
                    f"joins (e.g. {a}-{b}), so its vertices are in another order; export both "
                    f"from the same object with the same settings{hint}")
        return None

    def check(self, vertices: int, faces: np.ndarray, surface: str) -> None:
        """Raise :class:`WigglyInputError` if this driver cannot drive the surface
        (:meth:`mismatch`)."""
        why = self.mismatch(vertices, faces, surface)
        if why is not None:
            raise WigglyInputError(why)


def polygon_edges(polygons: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Unique undirected edges (i < j) of polygons: an (k, m) array of m-gons or a list of
    index arrays."""
    if isinstance(polygons, np.ndarray):
        P = polygons.reshape(len(polygons), -1)
        e = np.stack([P, np.roll(P, -1, axis=1)], axis=-1).reshape(-1, 2)
    else:
        e = np.concatenate([np.stack([p, np.roll(p, -1)], axis=1) for p in polygons]) \
            if len(polygons) else np.zeros((0, 2), np.int64)
    e = np.sort(e.astype(np.int64), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    return np.unique(e, axis=0)


def fan_triangles(counts: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, list]:
    """Triangles (fans) and the polygons (index arrays) of a face-vertex-counts layout."""
    counts = np.asarray(counts, np.int64)
    indices = np.asarray(indices, np.int64)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    polys = [indices[s:s + c] for s, c in zip(starts, counts, strict=True)]
    tris = [np.column_stack([np.full(c - 2, indices[s]), indices[s + 1:s + c - 1],
                             indices[s + 2:s + c]])
            for s, c in zip(starts, counts, strict=True) if c >= 3]
    faces = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    return faces, polys


def filled_times(times: np.ndarray, rate: float) -> np.ndarray:
    """Sorted sample ``times`` with evenly spaced times filled into every gap longer than
    1.5 / ``rate``, about ``rate`` a unit of time: where a reader samples its file's own
    interpolation between sparse keys or samples (glTF keys, USD time samples), which a
    spline through the samples alone would not follow."""
    filled = [times[:1]]
    for a, b in itertools.pairwise(times):
        n = max(1, round((b - a) * rate)) if b - a > 1.5 / rate else 1
        filled.append(np.linspace(a, b, n + 1)[1:])
    return np.concatenate(filled)


def _edge_codes(edges: np.ndarray, n: int) -> np.ndarray:
    return edges[:, 0] * n + edges[:, 1]


def keyed_frames(
    driver: Driver,
    *,
    offset: float = 0.0,
    driver_range: tuple[float, float] | None = None,
    start: float | None = None,
    end: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The driver frames that :func:`driven_keyframes` keys, and their shot times: frames
    with driver time in ``driver_range`` (inclusive) and shot time ``t + offset`` in
    ``[start, end]`` (when given), each bound with the slack of single-precision key times
    (:func:`_slack`; times just outside ``[start, end]`` are clamped into it).
    Raises :class:`WigglyInputError` when no frame falls in."""
    if not np.isfinite(offset):
        raise WigglyInputError(f"offset = {offset!r} s must be a finite number")
    keep = np.ones(driver.n_frames, bool)
    if driver_range is not None:
        lo, hi = (float(x) for x in driver_range)
        keep &= (driver.times >= lo - _slack(lo)) & (driver.times <= hi + _slack(hi))
    t = driver.times + float(offset)
    if start is not None:
        keep &= t >= start - _slack(start)
    if end is not None:
        keep &= t <= end + _slack(end)
    if not keep.any():
        first, last = driver.span
        window = "" if driver_range is None else f", range {list(driver_range)} s"
        shot = "" if start is None and end is None else f" in the shot's [{start}, {end}] s"
        fix = ""
        if start is not None and end is not None:  # the offsets that bring frames in
            fix = (f": an offset from {start - last:g} to {end - first:g} s puts some of them "
                   "in it (shot time = driver time + offset)")
        raise WigglyInputError(
            f"no frame of the driver {driver.source} (frames from {first:g} to {last:g} s"
            f"{window}, offset {offset:g} s) falls{shot}{fix}")
    frames = np.flatnonzero(keep)
    times = t[frames]
    if start is not None and end is not None:
        times = np.clip(times, start, end)
    return frames, times


def driven_keyframes(
    body: Body,
    driver: Driver,
    vertices: ArrayLike,
    *,
    stiffness: float = DRIVE_STIFFNESS,
    offset: float = 0.0,
    driver_range: tuple[float, float] | None = None,
    start: float | None = None,
    end: float | None = None,
    name: str = "drive",
) -> list[Keyframe]:
    """Partial keyframes that key ``vertices`` (of the user's surface) to the driver at every
    driver frame: position constraints of eq. (4), dense in time (the driver's frames are
    the nodes of the wiggly splines, Theorem 1); the other vertices stay free.

    Driver time ``t`` is shot time ``t + offset``.  Only frames with driver time in
    ``driver_range`` (inclusive) and shot time in ``[start, end]`` (when given) are keyed.
    Every key has the dimensionless ``stiffness`` of :class:`wiggly.Keyframe` (default
    :data:`DRIVE_STIFFNESS`; use :func:`wiggly.drive.enrich` for a basis that can follow) and
    ``spec = {"kind": "drive", "frame": k, "source": driver.source}``.  Add your own sparse
    keyframes to the list and solve (:func:`wiggly.solve`).  For a looping shot, key one
    period: a last frame equal to the first adds nothing.
    """
    if not isinstance(driver, Driver):
        raise WigglyInputError(f"driver should be a wiggly.drive.Driver (read_driver(path)); "
                               f"got {type(driver).__name__}")
    surface = body.surface
    driver.check(surface.n_vertices, surface.faces, body.model.source or "of the body")
    v = vertex_indices(vertices, surface.n_vertices, "surface", "driven group")
    frames, times = keyed_frames(driver, offset=offset, driver_range=driver_range, start=start,
                                 end=end)
    out = []
    for k, time in zip(frames.tolist(), times.tolist(), strict=True):
        out.append(Keyframe(time, v, position=driver.positions[k, v], stiffness=stiffness,
                            name=f"{name} frame {k}",
                            spec={"kind": "drive", "frame": int(k), "source": driver.source}))
    return out


def following(anim) -> dict | None:
    """How closely the driven vertices of a solved animation follow their targets at the
    driven keys (``spec["kind"] == "drive"``): ``{"frames", "vertices", "max", "rms",
    "worst_time"}`` (distances in metres), or None without driven keys.  One batched
    playback at all the key times.  A secondary motion also reports how far its free
    vertices swing from the driver's own pose of them: ``"free_max"`` and
    ``"free_worst_time"``."""
    driven = getattr(anim, "driven_frames", None)
    if driven is not None:  # a secondary motion: the driver owns the driven group
        times, frames, vertices, driver = driven
        positions = anim.positions(times)
        gaps = np.linalg.norm(positions - driver.positions[frames], axis=2)
        d = gaps[:, vertices]
        free = np.delete(gaps, vertices, axis=1)
        out = {"frames": len(times), "vertices": len(vertices), "max": float(d.max()),
               "rms": float(np.sqrt(np.mean(d**2))),
               "worst_time": float(times[int(d.max(axis=1).argmax())])}
        if free.size:
            out["free_max"] = float(free.max())
            out["free_worst_time"] = float(times[int(free.max(axis=1).argmax())])
        return out
    keys = [k for k in anim.keyframes if k.spec.get("kind") == "drive" and
            k.position is not None]
    if not keys:
        return None
    times = np.array([k.time for k in keys])
    positions = anim.positions(times, keys[0].on)
    d = np.stack([np.linalg.norm(positions[j][k.vertices] - k.position, axis=1).max()
                  for j, k in enumerate(keys)])
    sq = np.concatenate([np.sum((positions[j][k.vertices] - k.position) ** 2, axis=1)
                         for j, k in enumerate(keys)])
    return {"frames": len(keys), "vertices": len(keys[0].vertices), "max": float(d.max()),
            "rms": float(np.sqrt(sq.mean())), "worst_time": float(times[int(d.argmax())])}
