"""``wiggly modes MESH``: eigenfrequencies of a model, optionally a preview of the mode shapes."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from wiggly.cli.render import size_arg
from wiggly.errors import counted
from wiggly.limits import MAX_MODES, MIN_RESOLUTION
from wiggly.mesh import DEFAULT_RESOLUTION
from wiggly.progress import say

HELP = "list a model's eigenmodes (frequencies) and preview their shapes"
DESCRIPTION = """\
Tetrahedralize a model, assemble the linear FEM and compute its lowest eigenmodes
K phi = lambda M phi. Prints one row per mode: eigenvalue lambda (1/s^2),
frequency sqrt(lambda)/(2 pi) (Hz) and period. A free body has 6 rigid modes
(lambda = 0). MESH is a mesh file, builtin:critter|plant|bar, or a scene file
(.toml), whose mesh, material and fixed groups are used.

With -o the elastic modes are previewed, each oscillating for one second in a
video (.mp4/.gif) or at its peak in a contact sheet (.png). The shapes are
rotation-strain warped, so large amplitudes look as they would in an animation."""
EPILOG = """\
examples:
  wiggly modes builtin:plant -n 12
  wiggly modes model.obj --resolution 15 --young 5e4 -o modes.mp4
  wiggly modes examples/plant_swing.toml -o plant-modes.png"""

PREVIEW_SECONDS = 1.0
PREVIEW_FPS = 24
MAX_VIDEO_MODES = 8
MAX_SHEET_MODES = 12
AMPLITUDE = 0.2
"""Largest displacement of a previewed mode, as a fraction of the bounding-box diagonal."""


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", metavar="MESH",
                        help="mesh file, builtin:critter|plant|bar, or a scene file (.toml)")
    parser.add_argument("-n", "--modes", type=_int_at_least(1, MAX_MODES), default=None,
                        metavar="N",
                        help="number of modes, rigid ones included (default 20, or the "
                             "scene's)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--resolution", type=_int_at_least(MIN_RESOLUTION), metavar="R",
                      help="tet edges along the bounding-box diagonal (default "
                           f"{DEFAULT_RESOLUTION}, or the scene's)")
    size.add_argument("--edge-length", type=_number(0), metavar="L",
                      help="target tet edge length in metres")
    parser.add_argument("--young", type=_number(0), metavar="E",
                        help="Young's modulus in Pa (default 2e5)")
    parser.add_argument("--poisson", type=_number(0, 0.5, lower_inclusive=True), metavar="NU",
                        help="Poisson ratio in [0, 0.5) (default 0.45)")
    parser.add_argument("--density", type=_number(0), metavar="RHO",
                        help="density in kg/m^3 (default 1000)")
    parser.add_argument("-o", "--output", metavar="PREVIEW",
                        help="preview of the elastic mode shapes: .mp4, .gif or .png")
    parser.add_argument("--size", type=size_arg, metavar="WxH", default=None,
                        help="video size in pixels, e.g. 1280x720; a .png sheet's tiles are "
                             "half of it (default 960x540)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing preview")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars or stage messages")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from wiggly.errors import WigglyInputError
    from wiggly.scene import (
        PREVIEW_EXTENSIONS,
        MaterialSpec,
        MeshSpec,
        Scene,
        SimulationSpec,
        build,
        check_outputs,
        load_scene,
    )
    from wiggly.scene.spec import RIGID_MODES

    if args.output is not None:
        out = Path(args.output)
        if out.suffix.lower() not in PREVIEW_EXTENSIONS:
            raise WigglyInputError(f"{out}: a mode preview is a .mp4, .gif or .png file")
        check_outputs([out], args.overwrite)
    if args.mesh.lower().endswith(".toml"):
        scene = load_scene(args.mesh)
        scene = replace(scene, keyframes=[])
    else:
        if not args.mesh.startswith("builtin:") and not Path(args.mesh).is_file():
            raise WigglyInputError(
                f"{args.mesh}: {'is a folder' if Path(args.mesh).is_dir() else 'does not exist'}"
                "; give the path of a mesh file.")
        scene = Scene(MeshSpec(args.mesh), simulation=SimulationSpec(modes=20),
                      label=args.mesh)
    mesh = scene.mesh
    if args.resolution is not None or args.edge_length is not None:
        mesh = replace(mesh, resolution=args.resolution, edge_length=args.edge_length)
    m = scene.material
    material = MaterialSpec(args.young or m.young,
                            m.poisson if args.poisson is None else args.poisson,
                            args.density or m.density)
    if args.modes is not None and args.modes <= RIGID_MODES and not scene.simulation.fixed:
        raise WigglyInputError(
            f"-n/--modes {args.modes}: a free body has {RIGID_MODES} rigid modes, which the "
            f"basis must contain; use at least {RIGID_MODES + 1} to see elastic ones")
    sim = replace(scene.simulation, modes=args.modes or scene.simulation.modes)
    scene = replace(scene, mesh=mesh, material=material, simulation=sim)
    try:
        body, _ = build(scene)
    except WigglyInputError as err:
        if scene.source is not None:  # a scene file's keys are the user's own words
            raise
        raise WigglyInputError(_in_options(str(err))) from None
    print(table(scene, body))
    if args.output is not None:
        path = preview(Path(args.output), body, overwrite=args.overwrite,
                       size=args.size or (960, 540))
        print(f"wrote {path.resolve()}")
    return 0


#: Scene keys as this command's options name them (its messages come from the scene checks).
OPTIONS = {"mesh.resolution": "--resolution", "mesh.edge_length": "--edge-length",
           "simulation.modes": "-n/--modes", "material.young": "--young",
           "material.poisson": "--poisson", "material.density": "--density",
           "edge_length": "--edge-length", "resolution": "--resolution"}


def _in_options(message: str) -> str:
    """A scene check's message in this command's terms (``mesh.resolution = 200`` is
    ``--resolution 200``)."""
    import re

    names = "|".join(re.escape(k) for k in sorted(OPTIONS, key=len, reverse=True))
    message = re.sub(rf"(?<![\w.-])({names}) = ", lambda m: f"{OPTIONS[m[1]]} ", message)
    message = re.sub(rf"(?<![\w.-])({names}) (<=|>=)", lambda m: f"{OPTIONS[m[1]]} {m[2]}",
                     message)
    return re.sub(rf"(?<![\w.-])({names})\b", lambda m: OPTIONS[m[1]], message)


def table(scene, body) -> str:
    """The modes as a text table (one row per mode)."""
    lam = body.eigenvalues
    n_rigid = body.modes.n_rigid
    m = scene.material
    kind = ("free" if n_rigid == 6 else
            f"fixed at {len(body.fixed_vertices)} tet vertices")
    lines = [f"{scene.mesh_file().name}: {body.tets.n_tets} tets, {body.tets.n_vertices} "
             f"vertices, {body.mass:.4g} kg, {kind}, {n_rigid} rigid modes",
             f"material: E = {m.young:g} Pa, nu = {m.poisson:g}, rho = {m.density:g} kg/m^3",
             f"{'mode':>5}  {'lambda (1/s^2)':>15}  {'freq (Hz)':>10}  {'period (s)':>10}"]
    for i, value in enumerate(lam):
        if i < n_rigid:
            lines.append(f"{i + 1:>5}  {0.0:>15.6g}  {'rigid':>10}  {'-':>10}")
        else:
            f = math.sqrt(max(value, 0.0)) / (2 * math.pi)
            lines.append(f"{i + 1:>5}  {value:>15.6g}  {f:>10.4g}  "
                         f"{(1 / f if f > 0 else math.inf):>10.4g}")
    return "\n".join(lines)


def drawn_surface(body) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(rest vertices, triangles, tet vertices drawn) of what a mode preview draws: the
    user's surface (None), or the tet mesh's boundary when the surface has fewer than half
    its vertices (an 8-vertex box cannot show a bar's bending, which its tets carry)."""
    faces = body.tets.boundary_faces()
    used, faces = np.unique(faces, return_inverse=True)
    if body.surface.n_vertices >= 0.5 * len(used):
        return body.surface.vertices, body.surface.faces, None
    return body.tets.vertices[used], faces.reshape(-1, 3), used


def mode_shapes(body, modes, phase, on_tets: np.ndarray | None = None) -> np.ndarray:
    """Surface positions (len(phase), p, 3) of the warped mode ``modes[k]`` scaled by
    ``phase[k]`` (amplitude: :data:`AMPLITUDE` of the bounding-box diagonal at phase 1);
    ``on_tets``: those tet vertices instead (:func:`drawn_surface`)."""
    V = body.tets.vertices
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    Phi = body.modes.vectors
    n = body.tets.n_vertices
    U = np.empty((len(modes), n, 3))
    for k, (i, s) in enumerate(zip(modes, phase, strict=True)):
        u = Phi[:, i].reshape(n, 3)
        U[k] = s * AMPLITUDE * diag / max(np.abs(u).max(), 1e-300) * u
    W = np.concatenate([body.warp.apply(U[k:k + 64]) for k in range(0, len(U), 64)])
    if on_tets is not None:
        return (W + V)[:, on_tets]
    return body.to_surface(W) + body.surface.vertices


def preview(path: Path, body, *, overwrite: bool = False,
            size: tuple[int, int] = (960, 540)) -> Path:
    """Render the elastic modes: a video (one second each) or a contact sheet (at peak)."""
    from wiggly.errors import WigglyInputError
    from wiggly.render import Highlight, render_contact_sheet, render_video

    lam = body.eigenvalues
    elastic = list(range(body.modes.n_rigid, body.r))
    if not elastic:
        raise WigglyInputError("the model has no elastic modes to preview; ask for more "
                               "modes with -n")
    sheet = path.suffix.lower() == ".png"
    every = elastic
    elastic = elastic[:MAX_SHEET_MODES if sheet else MAX_VIDEO_MODES]
    V = body.tets.vertices
    diag = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))

    rest, faces, on_tets = drawn_surface(body)
    if on_tets is not None:
        say(f"{body.surface.n_vertices} surface vertices cannot show the modes' bending: "
            f"drawing the boundary of the {body.tets.n_tets} tets instead")

    def highlight(i: int, t: float) -> Highlight:
        shape = mode_shapes(body, [i], [1.0], on_tets)[0] - rest
        d = np.linalg.norm(shape, axis=1)
        moving = np.flatnonzero(d >= np.quantile(d, 0.85))
        hz = math.sqrt(max(lam[i], 0.0)) / (2 * math.pi)
        return Highlight(moving, t, (1.0, 0.45, 0.1), f"mode {i + 1}: {hz:.3g} Hz",
                         window=0.5 * PREVIEW_SECONDS, timed=False)

    shown = (f"the first {len(elastic)} of {counted(len(every), 'elastic mode shape')} (a "
             f"{'sheet' if sheet else 'video'} shows at most "
             f"{MAX_SHEET_MODES if sheet else MAX_VIDEO_MODES})" if len(elastic) < len(every)
             else counted(len(elastic), "elastic mode shape"))
    say(f"rendering {shown}, largest displacement {AMPLITUDE * diag:.3g} m, orange where each "
        "mode moves most")
    if sheet:
        times = PREVIEW_SECONDS * (np.arange(len(elastic)) + 0.25)
        positions = mode_shapes(body, elastic, np.ones(len(elastic)), on_tets)
        hls = [highlight(i, t) for i, t in zip(elastic, times, strict=True)]
        tile = (max(16, size[0] // 2), max(16, size[1] // 2))  # as a scene's sheet
        return render_contact_sheet(path, times, positions, faces, at=times, columns=4,
                                    tile_size=tile,
                                    highlights=hls,
                                    title="elastic modes at peak amplitude (orange: moves most)",
                                    clock=False,
                                    overwrite=overwrite)
    per = round(PREVIEW_SECONDS * PREVIEW_FPS)
    tau = np.arange(per) / PREVIEW_FPS
    times = np.concatenate([k * PREVIEW_SECONDS + tau for k in range(len(elastic))] +
                           [[len(elastic) * PREVIEW_SECONDS]])
    modes = np.concatenate([np.full(per, i) for i in elastic] + [[elastic[-1]]])
    phase = np.sin(2 * np.pi * times / PREVIEW_SECONDS)
    positions = mode_shapes(body, modes, phase, on_tets)
    hls = [highlight(i, (k + 0.5) * PREVIEW_SECONDS) for k, i in enumerate(elastic)]
    return render_video(path, times, positions, faces, highlights=hls, fps=PREVIEW_FPS,
                        size=size,
                        title="elastic modes, one per second (orange: moves most)", clock=False,
                        overwrite=overwrite)


def _int_at_least(low: int, high: int | None = None):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(
                f"{text} must be an integer >= {low}"
                + (f" and <= {high}" if high is not None else ""))
        return value
    return parse


def _number(low: float, high: float | None = None, lower_inclusive: bool = False):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        ok = (value >= low if lower_inclusive else value > low) and math.isfinite(value)
        if high is not None:
            ok = ok and value < high
        if not ok:
            rng = (f"in [{low:g}, {high:g})" if high is not None
                   else f"{'>=' if lower_inclusive else '>'} {low:g}")
            raise argparse.ArgumentTypeError(f"{text} must be a number {rng}")
        return value
    return parse
