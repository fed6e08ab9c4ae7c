"""Filling a surface with tetrahedra (fTetWild, cached on disk), and coarse meshes of the
same solid."""

from __future__ import annotations

import hashlib
import os
import signal
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from wiggly.child import can_run_child
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.files import atomic_file, default_cache_dir
from wiggly.limits import MAX_RESOLUTION, MAX_TETS, MIN_RESOLUTION
from wiggly.mesh import defects as mesh_checks
from wiggly.mesh import tetwild_child
from wiggly.mesh.data import (
    DEFAULT_RESOLUTION,
    ENVELOPE_PER_EDGE,
    Surface,
    TetMesh,
    check_surface_arrays,
    embed,
    tet_volumes,
    used_only,
)
from wiggly.mesh.defects import (
    DEGENERATE_VOLUME,
    CheckedSurface,
    SurfaceReport,
    diagonal,
)
from wiggly.mesh.validate import check_tet_mesh, checked_surface, refuse_defects
from wiggly.progress import Activity, activity, deprecated_progress, log, reporting

# --------------------------------------------------------------------------- meshing


_CWD_LOCK = threading.Lock()
_TET_CACHE_VERSION = b"wiggly-tets-2"
# fTetWild's mesh optimization: at most this many passes, ending early once the worst tet's
# conformal AMIPS energy is below STOP_ENERGY (its defaults; a regular tet has 3)
OPTIMIZATION_PASSES = 80
STOP_ENERGY = 10.0



def _tet_cache(V: np.ndarray, F: np.ndarray, edge_length: float, envelope: float,
               cache_dir: str | os.PathLike[str] | bool | None) -> Path | None:
    """Cache file of a tetrahedralization: fTetWild is randomized, so caching makes re-runs
    reproducible (and lets the modes cache hit).  Keyed by surface and options."""
    if cache_dir is False:
        return None
    h = hashlib.sha256(_TET_CACHE_VERSION)
    for a in (np.ascontiguousarray(V, np.float64), np.ascontiguousarray(F, np.int64),
              np.array([edge_length, envelope])):
        h.update(a.tobytes())
    root = Path(cache_dir) if cache_dir not in (None, True) else default_cache_dir()
    return root / "tets" / f"{h.hexdigest()[:32]}.npz"


@contextmanager
def _scratch_cwd() -> Iterator[None]:
    """Run in a private temporary working directory: fTetWild writes a debug file
    (``__tracked_surface.stl``) into the current directory, which must not litter the
    user's folder.  The working directory is process-wide, hence the lock."""
    main = threading.current_thread() is threading.main_thread()
    handler = signal.getsignal(signal.SIGINT) if main else None
    with _CWD_LOCK, tempfile.TemporaryDirectory(prefix="wiggly-ftetwild-") as tmp:
        old = os.getcwd()
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)
            if main and handler is not None:  # native code may replace Python's Ctrl+C handler
                signal.signal(signal.SIGINT, handler)


class MeshRepairWarning(UserWarning):
    """A surface was accepted although it is open, non-manifold, misoriented or
    self-intersecting (fTetWild filled what it encloses), or parts of it lie outside the
    tet mesh.  One warning per model says what was unusual and what was done."""


class TetBudgetError(WigglyInputError):
    """The requested tet size would make more than ``wiggly.limits.MAX_TETS`` tets.

    ``estimate`` is the estimated count, ``max_resolution`` the largest resolution within the
    limit and ``min_edge_length`` the smallest edge length (m) within it, so that callers can
    say what to change in their own terms."""

    def __init__(self, message: str, estimate: float, max_resolution: int,
                 min_edge_length: float):
        super().__init__(message)
        self.estimate, self.max_resolution = estimate, max_resolution
        self.min_edge_length = min_edge_length


#: A surface vertex farther than this many tet edge lengths outside the tet mesh is reported.
FAR_OUTSIDE = 1.0

#: Surfaces of more triangles (scans) get a line before each step that takes them seconds.
LARGE_SURFACE = 200_000

#: A tet mesh that lacks more than this share of the volume its surface encloses is reported:
#: parts thinner than the tets get no tets of their own, so the body is lighter and softer
#: than its surface.  Tets / enclosed volume measured at resolutions 12, 25 and 40: the
#: bundled critter 0.94-0.99, plant 0.77-0.79 at 12 (three runs), 0.84-0.86 at 14, 0.96 at
#: 25, bar 0.98-1.00; trimesh's box, icosphere, cylinder, capsule, cone and torus
#: 0.95-1.00.  Thin rods 2 m long: 40 mm across at resolution 12 0.68-0.70, 5 mm across at
#: resolution 200 0.71.  Only fills of surfaces without crossing triangles are compared
#: (overlapping parts count twice in the enclosed volume).
LOST_VOLUME = 0.25


@deprecated_progress
def tetrahedralize(
    surface: Surface,
    *,
    edge_length: float | None = None,
    resolution: int | None = None,
    repair: bool | None = True,
    source: str = "surface",
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> TetMesh:
    """Fill a surface with linear tetrahedra using fTetWild (pytetwild).

    The surface is inspected first (:func:`inspect_surface`).  By default (``repair=True``)
    an open, non-manifold, misoriented or self-intersecting surface is accepted: its
    triangles are oriented consistently, each closed shell by its nesting (a shell inside
    another faces into its cavity), and fTetWild fills the solid they enclose (it decides
    inside and outside by generalized winding numbers, so it copes with self-intersections,
    overlapping parts and holes); one :class:`MeshRepairWarning` says what was unusual.
    ``repair=False`` refuses such a surface (:class:`SurfaceDefectError`).  What cannot be
    filled is always refused: no triangles, NaN coordinates, no enclosed volume.

    The tet count is estimated before any meshing (``wiggly.mesh.defects.estimate_tets``);
    above ``wiggly.limits.MAX_TETS`` the call fails (:class:`TetBudgetError`).  A surface much
    finer than the tets is first simplified to an envelope of about three triangles per
    squared edge length (``wiggly.mesh.defects.simplified_envelope``): the surface itself is
    embedded in the tets later (:func:`embed`), and fTetWild's time grows with its input.

    fTetWild (Hu et al. 2020) meshes the volume inside an envelope around its input: the
    boundary of the tet mesh stays within ``0.1 * edge_length`` (clamped to 0.1 %-1 % of the
    bounding-box diagonal) of it.  **fTetWild is not reproducible**: it shuffles the input
    triangles with a hardware-seeded random generator (``std::random_device``), which
    pytetwild does not let us seed, and one thread does not help; tet counts vary by a few
    percent between runs.  Results are therefore cached on disk (``cache_dir``; None:
    :func:`wiggly.files.default_cache_dir`, False: off), keyed by the surface and the options,
    so that repeated runs on one machine (or with a copied cache) get the same tet mesh.

    Parameters
    ----------
    surface : Surface
        A triangle surface.
    edge_length : float, optional
        Target tet edge length in metres.
    resolution : int, optional
        Target number of tet edges along the bounding-box diagonal, i.e.
        ``edge_length = diagonal / resolution``, at most ``wiggly.limits.MAX_RESOLUTION``.
        Give at most one of ``edge_length`` and ``resolution``; the default is
        ``resolution = 25``, about 18k tets for a sphere and 5k for the bundled critter
        (slender shapes fill less of their bounding box).  The count grows like
        ``resolution**3``.
    repair : bool
        Accept (True, the default; None means the same) or refuse (False) surfaces that are
        not clean closed surfaces.
    source : str
        Name used in messages (usually the file path).

    Returns
    -------
    TetMesh
        Positively oriented, no unreferenced vertices.

    Notes
    -----
    Measured on the 2-core development machine while other jobs were running: an icosphere
    of radius 1 with 1280 faces gives 17.7k tets at the default resolution in 2-3 s; the
    bundled critter about 5k tets in 6-7 s; public meshes of 1k-100k triangles 2-6 s at the
    default resolution once simplified (the 52k-triangle armadillo did not finish in 300 s
    unsimplified).
    """
    mesh, report, _ = tetrahedralize_with_report(
        surface, edge_length=edge_length, resolution=resolution, repair=repair,
        source=source, cache_dir=cache_dir)
    if not report.clean:
        warn(repair_note(source, report), MeshRepairWarning)
    return mesh


def repair_note(source: str, report: SurfaceReport, far_outside: int = 0,
                farthest: float = 0.0, dropped: int = 0, share: float = 0.0,
                filled: float | None = None, edge_length: float = 0.0) -> str:
    """The one-line warning of an accepted surface: what was unusual and what was done
    (``filled``: the tet mesh's volume, told when it lacks more than ``LOST_VOLUME`` of the
    enclosed ``report.volume``)."""
    parts = []
    if not report.clean:
        parts.append(f"the surface has {_join(report.defects())}; fTetWild filled the solid "
                     "its triangles enclose (by winding numbers), and the animation is "
                     "delivered on your surface as it is")
    if dropped:
        parts.append(f"{counted(dropped, 'small piece')} of the tet mesh ({100 * share:.2g} % "
                     f"of its volume) {'holds' if dropped == 1 else 'hold'} to the body by an "
                     "edge, a vertex or nothing and would swing freely there; "
                     f"{'it was' if dropped == 1 else 'they were'} left out, and the surface "
                     "around them follows the nearest tets")
    if far_outside:
        parts.append(f"{counted(far_outside, 'vertex')} of the surface "
                     f"{'lies' if far_outside == 1 else 'lie'} outside the filled solid, up to "
                     f"{farthest:.2g} tet edge lengths away (parts thinner than the "
                     f"tets), and {'follows' if far_outside == 1 else 'follow'} the nearest "
                     "tets; a higher resolution resolves them")
    if filled is not None and volume_lost(report, filled):
        parts.append(f"the tet mesh holds {filled:.3g} m^3, {100 * filled / report.volume:.0f} "
                     f"% of the {report.volume:.3g} m^3 the surface encloses: parts thinner "
                     f"than the tets (edge length {edge_length:.3g} m) got no tets of their "
                     "own, so the body is that much lighter and softer there; a higher "
                     "resolution (or a shorter edge_length) gives them tets")
    return f"{source}: " + "; ".join(parts) + "."


def volume_lost(report: SurfaceReport, filled: float) -> bool:
    """Whether a fill of ``filled`` m^3 lacks more than ``LOST_VOLUME`` of the surface's
    enclosed volume (not judged with crossing triangles, which make that volume count
    overlaps twice)."""
    return report.crossing_pairs == 0 and filled < (1 - LOST_VOLUME) * report.volume


def _join(items: list[str]) -> str:
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def edge_length_for(diag: float, edge_length: float | None, resolution: int | None,
                    source: str = "tetrahedralize") -> float:
    """The target tet edge length from the options of :func:`tetrahedralize` (checked)."""
    if edge_length is not None and resolution is not None:
        raise WigglyInputError(
            f"{source}: got edge_length={edge_length} and resolution={resolution}; give "
            "only one (resolution means edge_length = bounding-box diagonal / resolution)."
        )
    if edge_length is not None and not (np.isfinite(edge_length) and edge_length > 0):
        raise WigglyInputError(
            f"{source}: edge_length must be a positive length in metres, got {edge_length}."
        )
    if resolution is not None and not (isinstance(resolution, int | np.integer | float)
                                       and int(resolution) == resolution
                                       and MIN_RESOLUTION <= resolution <= MAX_RESOLUTION):
        raise WigglyInputError(
            f"{source}: resolution must be an integer in [{MIN_RESOLUTION}, {MAX_RESOLUTION}] "
            f"(wiggly.limits.MIN_RESOLUTION, MAX_RESOLUTION), got {resolution}."
        )
    if edge_length is not None and diag > 0 and edge_length > diag / MIN_RESOLUTION:
        raise WigglyInputError(
            f"{source}: edge_length = {edge_length:g} m is longer than 1/{MIN_RESOLUTION} of "
            f"the body's {diag:.3g} m diagonal, coarser than fTetWild can mesh (it would run "
            f"for minutes); use edge_length <= {diag / MIN_RESOLUTION:.3g} m.")
    return float(edge_length) if edge_length is not None else \
        diag / int(resolution or DEFAULT_RESOLUTION)


def check_tet_budget(report: SurfaceReport, edge_length: float, source: str,
                     asked: str) -> float:
    """The estimated tet count at ``edge_length``; :class:`TetBudgetError` above MAX_TETS.
    ``asked`` names the option in the message ("resolution=300")."""
    estimate = mesh_checks.estimate_tets(report.volume, report.area, edge_length)
    if estimate > MAX_TETS:
        best = mesh_checks.max_resolution(report.volume, report.area, report.diagonal, MAX_TETS)
        shortest = report.diagonal / max(best, 1)
        raise TetBudgetError(
            f"{source}: {asked} would make about {estimate:.2g} tetrahedra "
            f"({report.volume:.3g} m^3 at edge length {edge_length:.3g} m), more than wiggly's "
            f"limit of {MAX_TETS} (wiggly.limits.MAX_TETS); use resolution <= {best} "
            f"(edge_length >= {shortest:.3g} m).", estimate, best, shortest)
    return estimate


def canonical_faces(F: np.ndarray) -> np.ndarray:
    """The triangles F (k, 3) in an order that does not depend on the input's: each rotated
    to start at its smallest vertex index (its orientation kept), then sorted by rows."""
    F = np.asarray(F)
    first = np.argmin(F, axis=1)
    rolled = F[np.arange(len(F))[:, None], (first[:, None] + np.arange(3)) % 3]
    return rolled[np.lexsort(rolled.T[::-1])]


def tetrahedralize_with_report(
    surface: Surface,
    *,
    edge_length: float | None,
    resolution: int | None,
    repair: bool | None,
    source: str,
    cache_dir: str | os.PathLike[str] | bool | None,
    checked: CheckedSurface | None = None,
    simplify: bool = True,
) -> tuple[TetMesh, SurfaceReport, dict]:
    """:func:`tetrahedralize`, also returning the surface report and what was done
    (``simplify=False``: fTetWild gets the surface as it is)."""
    if checked is None:
        check_surface_arrays(surface, source)
        edge_length_for(1.0, edge_length, resolution, source)  # options first: fail fast
        with activity(f"checking {source} ({counted(surface.n_faces, 'triangle')})"):
            checked = checked_surface(surface, source)
    report = checked.report
    if repair is False:
        refuse_defects(report, source)
    h = edge_length_for(report.diagonal, edge_length, resolution, source)
    asked = f"edge_length={edge_length}" if edge_length is not None else \
        f"resolution={resolution or DEFAULT_RESOLUTION}"
    estimate = check_tet_budget(report, h, source, asked)
    # the same solid in another face order: the same envelope and the same cache entry
    V, F = checked.vertices, canonical_faces(checked.faces)
    centre = far_centre(V[np.unique(F)], report.diagonal)
    V = V - centre  # exact (Sterbenz): both are about the same far coordinate
    # a scan's million triangles take VTK's decimation seconds: a line says what runs
    with activity(f"simplifying {Path(source).name}'s {counted(len(F), 'triangle')} for the "
                  "tetrahedralizer", enabled=simplify and len(F) > LARGE_SURFACE):
        simple = mesh_checks.simplified_envelope(V, F, h, report.area) if simplify else None
    if simple is not None:
        V, F = simple
    V, F = used_only(V, F)
    info = {"edge_length": h, "estimate": estimate, "input_faces": len(F),
            "simplified": simple is not None}
    envelope = float(np.clip(ENVELOPE_PER_EDGE * h / report.diagonal, 1e-3, 1e-2))
    cached = _tet_cache(V, F, h, envelope, cache_dir)
    tv = tt = None
    if cached is not None and cached.exists():
        try:
            with np.load(cached) as data:
                tv, tt = data["vertices"], data["tets"]
        except (OSError, ValueError, KeyError):
            cached.unlink(missing_ok=True)
    if tv is not None:  # a mesh cached before flat tets were dropped
        tv, tt = _without_flat(tv, tt)
    if tv is None:
        what = (f"{counted(len(F), 'triangle')} simplified from {report.n_faces}"
                if simple is not None else counted(len(F), "triangle"))
        options = {"edge_length_abs": float(h), "epsilon": envelope,
                   "stop_energy": STOP_ENERGY, "num_opt_iter": OPTIMIZATION_PASSES}
        name = os.path.basename(source) or source  # as the checking line names it
        with activity(f"tetrahedralizing {name} (fTetWild: {what}, about "
                      f"{_round(estimate)} tets)") as line:
            tv, tt = _without_flat(*_fill_or_retry(V, F, options, line, source, h,
                                                   report.volume))
        if cached is not None and len(tt):
            try:  # first writer wins: every process then meshes this surface the same way
                with atomic_file(cached, replace=False) as tmp, open(tmp, "wb") as f:
                    np.savez(f, vertices=np.asarray(tv), tets=np.asarray(tt))
            except FileExistsError:  # another process filled the same surface meanwhile
                try:
                    with np.load(cached) as data:
                        tv, tt = data["vertices"], data["tets"]
                except (OSError, ValueError, KeyError):
                    pass  # unreadable: keep ours
            except OSError:
                pass  # a read-only cache directory only costs time
    tt = np.asarray(tt, dtype=np.int64).reshape(-1, 4)
    if len(tt) == 0:
        raise WigglyInputError(f"{source}: fTetWild produced no tetrahedra; {_too_thin(report, h)}")
    mesh = TetMesh(*used_only(np.asarray(tv, dtype=np.float64) + centre, tt))
    return check_tet_mesh(mesh, f"{source} (tetrahedralized)"), report, info


def _without_flat(tv: np.ndarray, tt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild's output without its tets of (nearly) no volume, which
    :func:`wiggly.mesh.validate.check_tet_mesh` refuses (at most ``DEGENERATE_VOLUME``
    times the diagonal cubed): its float output leaves a few among tens of thousands on some
    surfaces (39 of 26050 on a creature at resolution 40), and they carry no mass or
    stiffness."""
    V = np.asarray(tv, dtype=np.float64)
    T = np.asarray(tt, dtype=np.int64).reshape(-1, 4)
    if not len(T):
        return V, T
    flat = np.abs(tet_volumes(V, T)) <= DEGENERATE_VOLUME * diagonal(V[np.unique(T)]) ** 3
    if flat.any():
        flats = counted(int(flat.sum()), "flat tetrahedron", "flat tetrahedra")
        log.info(f"fTetWild left {flats} of {len(T)}; dropped")
    return V, T[~flat]


#: A body whose bounding-box centre lies farther from the origin than this many diagonals
#: is meshed about its centre: fTetWild and VTK's decimation (float32 points) round far
#: coordinates.  A 1 m sphere at (3e6, 5e6, 1e6) m lost a piece and half its tets (1160
#: against 2312 at the origin) and missed its key by 57 mm against 9.8 mm.  Bodies nearer
#: the origin keep their coordinates (and their cached tet meshes).
FAR_FROM_ORIGIN = 10.0


def far_centre(V: np.ndarray, diag: float) -> np.ndarray:
    """The bounding-box centre of ``V`` if it lies more than ``FAR_FROM_ORIGIN`` diagonals
    from the origin, else zeros: what to subtract before meshing and add back after."""
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
    return centre if np.linalg.norm(centre) > FAR_FROM_ORIGIN * diag else np.zeros(3)


def _too_thin(report: SurfaceReport, h: float) -> str:
    """Why a fill made no tets and what to do: the body's mean thickness (twice its volume
    over its area, exact for a plate) against the edge length ``h``, and the resolution at
    which the tets fit into it."""
    thick = 2.0 * report.volume / report.area if report.area > 0 else 0.0
    needed = int(np.ceil(report.diagonal / thick)) if thick > 0 else 0
    say = (f"the body is about {thick:.3g} m thick, against tets of edge length {h:.3g} m")
    if 0 < needed <= MAX_RESOLUTION:
        return (f"{say}: a resolution of {needed} or more (edge_length {thick:.3g} m or less) "
                "gives it tets, or thicken it in the model, or bring a tet mesh (.msh, .vtu).")
    return (f"{say}, thinner than the finest resolution ({MAX_RESOLUTION}) reaches: thicken "
            "it in the model (e.g. Blender's Solidify modifier), or tetrahedralize it "
            "yourself and bring the tet mesh (.msh, .vtu).")


#: fTetWild's smallest envelope (relative to the bounding-box diagonal) that wiggly asks for
MIN_ENVELOPE = 1e-3


def _fill(V: np.ndarray, F: np.ndarray, options: dict, line: Activity) -> tuple:
    """fTetWild on (V, F): in a child process wherever one can be started, so that its crash
    ends only the child (:class:`tetwild_child.MesherCrash`) and the line ticks meanwhile (the
    call holds the interpreter lock); in-process only in hosts that cannot start a Python
    child (Blender's binary)."""
    if can_run_child():
        return tetwild_child.tetrahedralize_in_child(
            V, F, options, tetwild_child.Log(line, OPTIMIZATION_PASSES, STOP_ENERGY))
    import pytetwild

    with _scratch_cwd():
        return pytetwild.tetrahedralize(
            np.ascontiguousarray(V), np.ascontiguousarray(F, dtype=np.int32),
            quiet=True, loglevel=6, **options)


#: A fill of less than this share of the surface's enclosed volume is tried again with the
#: smallest envelope.
LOST_SHARE = 0.5


def _fill_or_retry(V: np.ndarray, F: np.ndarray, options: dict, line: Activity,
                   source: str, h: float, volume: float) -> tuple:
    """:func:`_fill`; once more with the smallest envelope if fTetWild crashes or fills less
    than ``LOST_SHARE`` of the surface's enclosed ``volume``, keeping the fuller result; two
    crashes are a refusal that says what to try.  A 2 m rod of 5 mm diameter at resolutions
    12 and 25 always made fTetWild segfault with wiggly's envelope, wider than the rod; one of
    20 mm crashed or gave 0-2 tets; with the smallest envelope both meshed in 2-7 s."""
    tv = tt = None
    filled = 0.0
    try:
        tv, tt = _fill(V, F, options, line)
        filled = _volume(tv, tt)
        if filled >= LOST_SHARE * volume or options["epsilon"] <= MIN_ENVELOPE:
            return tv, tt
        why = f"filled {100 * filled / volume:.2g} % of the surface's volume"
    except tetwild_child.MesherCrash as crash:
        failure = crash
        why = f"crashed (signal {crash.signal})"
    if options["epsilon"] > MIN_ENVELOPE:
        log.info("%s: fTetWild %s with an envelope of %.2g of the diagonal; retrying with "
                 "%.2g", source, why, options["epsilon"], MIN_ENVELOPE)
        try:
            tv2, tt2 = _fill(V, F, {**options, "epsilon": MIN_ENVELOPE}, line)
            return (tv2, tt2) if tv is None or _volume(tv2, tt2) > filled else (tv, tt)
        except tetwild_child.MesherCrash as crash:
            if tv is not None:
                return tv, tt
            failure = crash
    raise WigglyInputError(
        f"{source}: the tetrahedralizer (fTetWild) crashed on this surface (signal "
        f"{failure.signal}), also with its tightest envelope; try another resolution or "
        f"edge_length (now {h:.3g} m; thin parts mesh better with shorter edges), or "
        "tetrahedralize it yourself and bring the tet mesh (.msh, .vtu).")


def _volume(tv: np.ndarray, tt: np.ndarray) -> float:
    """The total volume of fTetWild's tets (m^3)."""
    V, T = np.asarray(tv, dtype=np.float64), np.asarray(tt, dtype=np.int64).reshape(-1, 4)
    return float(np.abs(np.linalg.det(V[T[:, 1:]] - V[T[:, :1]])).sum()) / 6


def _round(x: float) -> str:
    """A count to two significant digits ("4700")."""
    return f"{float(f'{x:.2g}'):.0f}"


def coarse_mesh(
    mesh: TetMesh,
    n_tets: int,
    *,
    cache_dir: str | os.PathLike[str] | bool | None = None,
) -> TetMesh | None:
    """A coarser tet mesh of the same solid, with about ``n_tets`` tets (fTetWild).

    The boundary of ``mesh`` is tetrahedralized with an edge length ``(mesh.n_tets /
    n_tets)^(1/3)`` times the mean edge length of ``mesh``.  If some vertex of ``mesh`` lies
    far outside the result (a thin part lost at that size: its smallest barycentric
    coordinate in the nearest coarse tet is below -0.5), the edge length shrinks by 1.5 and
    fTetWild runs again, twice at most; then None.  Results are cached like
    :func:`tetrahedralize`.
    """
    V, T = mesh.vertices, mesh.tets
    edge = float(np.mean(mesh.edge_lengths())) * (len(T) / n_tets) ** (1 / 3)
    B = mesh.boundary_faces()
    area = 0.5 * float(np.linalg.norm(np.cross(V[B[:, 1]] - V[B[:, 0]],
                                               V[B[:, 2]] - V[B[:, 0]]), axis=1).sum())
    report = SurfaceReport(n_faces=len(B), volume=float(mesh.volumes().sum()), area=area,
                           diagonal=diagonal(V[np.unique(T)]))
    checked = CheckedSurface(V, B, report)  # a tet mesh's boundary: closed, oriented outwards
    for _ in range(3):
        with reporting(False):
            coarse, _, _ = tetrahedralize_with_report(
                Surface(V, B), edge_length=edge, resolution=None, repair=True,
                source="coarse mesh", cache_dir=cache_dir, checked=checked,
                simplify=False)  # its boundary must follow the fine mesh (the warp's lift)
        if embed(V, coarse).barycentric.min() > -0.5:
            return coarse
        edge /= 1.5
    return None
