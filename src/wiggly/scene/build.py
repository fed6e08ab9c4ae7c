"""From a scene to a body and keyframes: the one path every entry point takes (the CLI,
the editor session and its refinement process)."""

from __future__ import annotations

import time as _time
from typing import Any

import numpy as np

from wiggly import mesh as meshing
from wiggly.body import Damping, fixed_from_surface, prepare, tets_of
from wiggly.errors import WigglyInputError, counted
from wiggly.fem import Material
from wiggly.keyframes import Keyframe
from wiggly.limits import MAX_TETS
from wiggly.mesh import DEFAULT_RESOLUTION, TetBudgetError, check_tet_budget, edge_length_for
from wiggly.progress import activity, deprecated_progress, say
from wiggly.scene.drive import check_driver_against, driven_body, driven_keyframes_of
from wiggly.scene.groups import resolve_group_arrays, resolve_groups
from wiggly.scene.spec import RIGID_MODES, Absolute, Offset, Rest, Scene
from wiggly.scene.validation import Problems, input_error, show

# ----------------------------------------------------------------------------------------------
# building and running


def _load_model(scene: Scene):
    """Read the mesh; check the groups, the surface and the size of its tet mesh before any
    computation; then tetrahedralize and embed."""

    f = scene.mesh_file()
    where = scene.where()
    try:
        loaded = meshing.load_mesh(f, scene.mesh.metres_per_unit, scene.mesh.up)
    except WigglyInputError as err:  # a file that is there but cannot be read
        raise WigglyInputError(f"{where}: mesh.path = {show(scene.mesh.path)}: {err}") from None
    checked = None
    if isinstance(loaded, meshing.Surface):  # check what we can before tetrahedralizing
        p = Problems(where)
        resolve_group_arrays(scene, loaded.vertices, loaded.groups, None, None, p)
        check_driver_against(scene, loaded.n_vertices, loaded.faces, f.name, p, loaded.vertices)
        p.raise_if_any()
        with activity(f"checking {f.name} ({counted(loaded.n_faces, 'triangle')})"):
            try:  # a surface that is read but cannot be a body (flat, no area)
                checked = meshing.checked_surface(loaded, str(f))
            except WigglyInputError as err:
                raise WigglyInputError(
                    f"{where}: mesh.path = {show(scene.mesh.path)}: {err}") from None
        check_surface_for_scene(scene, checked.report, f.name)
    t = _time.perf_counter()
    try:
        model = meshing.build_model(loaded, str(f), resolution=scene.mesh.resolution,
                                    edge_length=scene.mesh.edge_length,
                                    repair=scene.mesh.repair, checked=checked)
    except WigglyInputError as err:  # e.g. fTetWild found no solid at this edge length
        raise WigglyInputError(f"{where}: mesh.path = {show(scene.mesh.path)}: {err}") from None
    say(f"{counted(model.tets.n_tets, 'tet')}, {counted(model.tets.n_vertices, 'vertex')} "
         f"({_time.perf_counter() - t:.1f} s)")
    if checked is None:  # a tet mesh: its surface is known now
        p = Problems(where)
        check_driver_against(scene, model.surface.n_vertices, model.surface.faces, f.name, p,
                             model.surface.vertices)
        p.raise_if_any()
    return model


def check_surface_for_scene(scene: Scene, report, name: str) -> None:
    """``mesh.repair = false`` against a surface with defects, and the tet count that
    ``mesh.resolution`` / ``mesh.edge_length`` would make, in the scene's terms."""

    where, m = scene.where(), scene.mesh
    if m.repair is False and not report.clean:
        raise input_error(where, [
            f"mesh.repair = false refuses {name}: {'; '.join(report.defects(detailed=True))}. "
            "Remove repair = false (or set it to true) to let fTetWild fill the solid its "
            "triangles enclose, or fix the model in a modelling tool"])
    if m.edge_length is not None:
        key, value = "mesh.edge_length", show(m.edge_length)
    else:
        key = "mesh.resolution"
        value = show(m.resolution) if m.resolution is not None else \
            f"{DEFAULT_RESOLUTION} (the default)"
    h = edge_length_for(report.diagonal, m.edge_length, m.resolution, where)
    try:
        check_tet_budget(report, h, where, key)
    except TetBudgetError as err:
        raise input_error(where, [
            f"{key} = {value} would make about {err.estimate:.2g} tetrahedra of {name}, more "
            f"than wiggly's limit of {MAX_TETS} (wiggly.limits.MAX_TETS); use resolution <= "
            f"{err.max_resolution} (or edge_length >= {err.min_edge_length:.3g} m)"]) from None


def _check_modes_for_scene(scene: Scene, model, fixed_vertices) -> None:
    """``simulation.modes`` against the tet mesh: at most its free degrees of freedom, at
    least its rigid modes (before the modes are computed)."""
    n = model.tets.n_vertices
    fixed = np.zeros((0,), np.int64) if fixed_vertices is None else fixed_vertices
    free = 3 * (n - len(fixed))
    modes, name = scene.simulation.modes, scene.mesh_file().name
    if free == 0:
        groups = ", ".join(repr(g) for g in scene.simulation.fixed)
        raise input_error(scene.where(), [
            f"simulation.fixed = [{groups}] holds every vertex of {name}'s tet mesh, so "
            "nothing can move: fix fewer vertices (a base, the feet), and key the others"])
    if len(fixed) and scene.drive is None and np.isin(
            fixed_from_surface(model, np.arange(model.surface.n_vertices)), fixed).all():
        groups = ", ".join(repr(g) for g in scene.simulation.fixed)
        raise input_error(scene.where(), [
            f"simulation.fixed = [{groups}] holds every vertex of {name}'s surface (through "
            "the tets that carry them), so the surface cannot move: fix fewer vertices (a "
            "base, the feet), and key the others"])
    if modes > free:
        held = f", {len(fixed)} of them fixed" if len(fixed) else ""
        raise input_error(scene.where(), [
            f"simulation.modes = {modes} is more than the {free} degrees of freedom of {name}'s "
            f"tet mesh ({counted(n, 'vertex')}{held}, 3 each); use at most {free}, or a higher "
            "mesh.resolution"])
    rigid = _rigid_mode_count(model.tets.vertices[fixed])
    if modes < rigid:
        raise input_error(scene.where(), [
            f"simulation.modes = {modes} is fewer than the {rigid} rigid modes that the fixed "
            f"groups leave free (they are {'collinear' if len(fixed) > 1 else 'one point'}), "
            f"which the basis must contain; use at least {rigid} ({rigid} moves it rigidly "
            "only; each mode more bends it)"])


def _rigid_mode_count(points: np.ndarray) -> int:
    """Rigid motions left by holding ``points`` at rest: 6 if none, 3 (rotations) about one
    point, 1 about a line, 0 otherwise (Schulz et al. 2014, eq. (5))."""
    if len(points) == 0:
        return RIGID_MODES
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    size = max(float(np.ptp(points, axis=0).max()), 1e-300)
    rank = int(np.sum(spread > 1e-9 * size))
    return {0: 3, 1: 1}.get(rank, 0)


@deprecated_progress
def build(scene: Scene):
    """Body and keyframes of a scene: ``(wiggly.Body, list[wiggly.Keyframe])``.

    Reads and tetrahedralizes the mesh, resolves the groups, assembles the FEM and computes
    the modes (cached on disk), reporting the stages (:mod:`wiggly.progress`).
    """
    body, keyframes, _ = build_with_groups(scene)
    return body, keyframes


def build_with_groups(scene: Scene, *, body_modes: bool = True):
    """:func:`build`, also returning the resolved vertex groups ``{name: indices}``.  Without
    ``body_modes`` a secondary motion's body gets only its rigid modes (at least one): the
    solve uses the free parts' own modes (:func:`wiggly.drive.secondary_motion`), and the
    body's cost seconds on a new mesh (2.3 s for the walk's 35.7k tets)."""
    model = _load_model(scene)
    groups = resolve_groups(scene, model)
    body = body_of(scene, model, groups, body_modes=body_modes)
    return body, keyframes_of(scene, body, groups), groups


def fixed_vertices_of(scene: Scene, model, groups: dict[str, np.ndarray]) -> np.ndarray | None:
    """The tet-mesh vertices held by the scene's ``simulation.fixed`` groups (surface groups
    through the tets that contain them), or None."""
    fixed = [groups[g] if scene.groups[g].on == "tets" else fixed_from_surface(model, groups[g])
             for g in scene.simulation.fixed]
    return np.unique(np.concatenate(fixed)) if fixed else None


def modes_key(scene: Scene) -> tuple:
    """What a scene's M, K and modes (with a driver's shapes) depend on besides its mesh (a
    value key)."""
    s = scene.simulation
    key = (scene.material, s.modes, s.lumped_mass, tuple((g, scene.groups[g]) for g in s.fixed),
           tuple((g, spec) for g, spec in scene.groups.items() if spec.young is not None),
           scene.secondary_motion)  # a secondary motion's body: rigid modes only
    if scene.drive is not None and scene.drive.adds_shapes:
        key += (scene.drive, tuple((g, scene.groups[g]) for g in scene.drive.groups), s.warp)
    return key


def young_of(scene: Scene, model, groups: dict[str, np.ndarray]) -> np.ndarray | None:
    """Young's modulus per tet with groups of their own (``[groups.<name>] young``; later
    groups win where they overlap), or None when every tet has ``[material] young``."""
    soft = [(g, spec) for g, spec in scene.groups.items() if spec.young is not None]
    if not soft:
        return None
    young = np.full(model.tets.n_tets, float(scene.material.young))
    for g, spec in soft:
        young[tets_of(model, groups[g], spec.on)] = spec.young
    return young


@deprecated_progress
def body_of(scene: Scene, model, groups: dict[str, np.ndarray], *, dynamics: bool = True,
            body_modes: bool = True):
    """The scene's :class:`wiggly.Body` on ``model`` (material, fixed groups, modes, lumped
    mass, and the driver's shapes with ``[drive]``; with ``dynamics`` its damping and
    gravity, else the library's defaults, for :meth:`wiggly.Body.with_dynamics` to set).
    Modes come from the on-disk cache when computed before; without ``body_modes`` a
    secondary motion's body has its rigid modes only (:func:`build_with_groups`)."""
    fixed_vertices = fixed_vertices_of(scene, model, groups)
    _check_modes_for_scene(scene, model, fixed_vertices)
    m, s = scene.material, scene.simulation
    count = s.modes
    if not body_modes and scene.secondary_motion:
        held = model.tets.vertices[[] if fixed_vertices is None else fixed_vertices]
        count = max(1, _rigid_mode_count(held))
    extra = {}
    if dynamics:
        extra = {"damping": Damping(scene.damping.alpha, scene.damping.beta),
                 "gravity": s.gravity}
    try:
        body = prepare(model, material=Material(m.young, m.poisson, m.density),
                       fixed_vertices=fixed_vertices, n_modes=count, lumped=s.lumped_mass,
                       young=young_of(scene, model, groups), **extra)
    except WigglyInputError as err:  # the body the mesh makes (loose parts): say which
        raise WigglyInputError(f"{scene.where()}: mesh.path = {show(scene.mesh.path)}: {err}"
                               ) from None
    return driven_body(scene, body, groups)  # + the driver's shapes ([drive])


@deprecated_progress
def keyframes_of(scene: Scene, body, groups: dict[str, np.ndarray]) -> list:
    """The scene's keyframes as :class:`wiggly.Keyframe` objects for ``body``: its
    ``[[keyframes]]``, then the driven keys of ``[drive]`` (one per driver frame)."""

    out = []
    for kf in scene.keyframes:
        v, on = groups[kf.group], scene.groups[kf.group].on
        kw: dict[str, Any] = {"on": on, "name": kf.label}
        for name in ("stiffness", "c_A", "c_B"):
            if getattr(kf, name) is not None:
                kw[name] = getattr(kf, name)
        vel = None if kf.velocity is None else np.asarray(kf.velocity)
        pos = kf.position
        if pos is None:
            k = Keyframe(kf.time, v, velocity=vel, **kw)
        elif isinstance(pos, Rest):
            k = Keyframe.rest(body, kf.time, v, velocity=vel, **kw)
        elif isinstance(pos, Offset):
            k = Keyframe.offset(body, kf.time, v, pos.offset, velocity=vel, **kw)
        elif isinstance(pos, Absolute):
            k = Keyframe(kf.time, v, position=np.asarray(pos.positions), velocity=vel, **kw)
        else:
            k = Keyframe.rigid(body, kf.time, v, rotation=pos.matrix(),
                               translation=pos.translation, center=pos.center, velocity=vel,
                               **kw)
        out.append(k)
    return out + driven_keyframes_of(scene, body, groups)
