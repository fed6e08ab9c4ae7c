"""``wiggly animate SCENE``: solve a scene and write its outputs."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

HELP = "animate a scene file and write its outputs"
DESCRIPTION = """\
Solve the sparse spacetime problem of a scene file (docs/scene-format.md) and write
every output: geometry (.glb .usd .usda .usdc .obj .npz) and previews (.mp4 .gif,
.png contact sheet). The scene is checked completely before anything is computed.
Prints a summary: mesh, modes, solve time, Newton iterations, the residual of
every keyframe, and where the outputs went."""
EPILOG = """\
examples:
  wiggly animate examples/jump.toml
  wiggly animate shot.toml -o out/shot.glb -o out/shot.mp4 --overwrite
  wiggly animate shot.toml --linear --fps 24 --quiet
  wiggly animate shot.toml -o shot.glb -o shot.usdc --fps 24 --frame-start 1   # for Blender
  wiggly animate shot.toml --linear -o shot.glb --gltf-targets modes   # compact, exact glTF

Blender: its glTF importer puts a key at t seconds on frame t * (scene fps), and its USD
importer takes the frame range from the file but ignores its frame rate. Export at the
Blender scene's rate (--fps 24 for a new scene) with --frame-start 1 to land on frames
1, 2, ...; but leave --frame-start out for a shot driven by a Blender export, whose frame N
is already at N / fps. See docs/blender.md."""


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", metavar="SCENE", help="scene file (.toml)")
    parser.add_argument("-o", "--output", metavar="OUT", action="append",
                        help="write OUT instead of the scene's [output] paths (repeatable; "
                             "relative to the current directory)")
    parser.add_argument("--overwrite", action="store_true", default=None,
                        help="replace existing outputs")
    parser.add_argument("--linear", action="store_true",
                        help="linear solve without rotation-strain warping (faster, but large "
                             "rotations distort)")
    parser.add_argument("--fps", type=_positive, metavar="N",
                        help="frame rate of the outputs (overrides [time] fps); match the "
                             "target scene's (Blender's USD importer ignores the file's rate)")
    parser.add_argument("--frame-start", type=int, metavar="N",
                        help="glTF/USD: put the first output frame on frame N (frame k on "
                             "N + k at the output fps); overrides [output] frame_start")
    parser.add_argument("--gltf-targets", choices=("frames", "modes"),
                        help="glTF morph targets: one per frame, or one per mode with q(t) "
                             "as weights (linear shots; exact and compact); overrides "
                             "[output] gltf_targets")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars or stage messages")


def run(args: argparse.Namespace) -> int:
    from wiggly.errors import WigglyInputError
    from wiggly.scene import load_scene, with_overrides
    from wiggly.scene import run as run_scene

    scene = load_scene(args.scene, output_fps=args.fps)
    scene = with_overrides(scene, fps=args.fps, warp=False if args.linear else None,
                           frame_start=args.frame_start, gltf_targets=args.gltf_targets)
    glb = any(str(p).lower().endswith((".glb", ".gltf"))
              for p in (args.output or scene.output.paths))
    if args.gltf_targets == "modes" and scene.simulation.warp and glb:  # the flag's request
        raise WigglyInputError(
            f"--gltf-targets modes needs a linear shot, and {args.scene} is warped: a warped "
            "motion is no linear combination of modes; add --linear, or use --gltf-targets "
            "frames")
    anim = run_scene(scene, outputs=args.output, overwrite=args.overwrite)
    print(summary(scene, anim))
    return 0


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"{text} must be a number > 0")
    return value


def summary(scene, anim) -> str:
    """A short report of a solved scene: mesh, modes, solve, residuals, outputs."""
    from wiggly.solve import iteration_count

    body, info = anim.body, anim.info
    lam = body.eigenvalues[body.modes.n_rigid:]
    hz = (lam ** 0.5) / (2 * 3.141592653589793)
    lines = [
        f"scene      {scene.where()}",
        f"mesh       {scene.mesh_file().name}: {body.tets.n_tets} tets, {body.tets.n_vertices} "
        f"tet vertices, {body.surface.n_vertices} surface vertices, {body.mass:.3g} kg",
        f"modes      {body.r} ({body.modes.n_rigid} rigid)"
        + (f", elastic {hz.min():.3g} to {hz.max():.3g} Hz" if len(hz) else ""),
    ]
    if info.get("free_hz"):  # secondary motion moves the free parts in their own modes
        low, high = info["free_hz"]
        lines[-1] = (f"modes      {info['free_modes']} of the free parts with the driven group "
                     f"held (drive.free_modes), {low:.3g} to {high:.3g} Hz")
    solve = f"{'warped' if anim.warped else 'linear'}, {info['solve_seconds']:.2f} s"
    if info.get("secondary"):
        solve += (f", secondary motion: {info['free_modes']} modes of the free parts on "
                  f"{info['driver_frames']} driver frames")
    if "iterations" in info:
        kind = "Gauss-Newton" if info.get("secondary") else "Newton"
        solve += (f", {iteration_count(info, kind)}"
                  + ("" if info.get("converged") else " (not converged)"))
    lines.append(f"solve      {solve}")
    seconds = info.get("scene", {}).get("seconds", {})
    if seconds:
        write = sum(v for k, v in seconds.items() if k.startswith(("write", "sample")))
        compiled = (f"compiling the warp's kernels (once) {seconds['compile']:.1f} s, "
                    if "compile" in seconds else
                    f"loading the warp's kernels {seconds['load']:.1f} s, "
                    if "load" in seconds else "")
        lines.append(f"time       mesh and modes {seconds.get('prepare', 0):.1f} s, {compiled}"
                     f"solve {seconds.get('solve', 0):.1f} s, outputs {write:.1f} s, total "
                     f"{sum(seconds.values()):.1f} s")
    lines.append(f"shot       [{anim.start:g}, {anim.end:g}] s at {scene.time.fps:g} fps")
    rows = anim.info.get("keyframe_residuals")  # scene.run's, of the scene's own keyframes
    if rows is None:
        sparse = replace(anim, keyframes=anim.keyframes[:len(scene.keyframes)])  # not [drive]'s
        rows = sparse.constraint_residuals()
    if rows:
        lines.append("keyframes  residuals at the key times")
        lines.append(f"  {'#':>3}  {'time':>6}  {'group':<14} {'name':<16} {'pos rms':>10} "
                     f"{'pos max':>10} {'vel rms':>12}")
        for j, (spec, row) in enumerate(zip(scene.keyframes, rows, strict=True)):
            def mm(key, unit="mm", row=row):
                return f"{1e3 * row[key]:.3g} {unit}" if key in row else "-"
            lines.append(f"  {j:>3}  {row['time']:>6.3g}  {spec.group:<14.14} "
                         f"{spec.name:<16.16} {mm('position_rms'):>10} {mm('position_max'):>10} "
                         f"{mm('velocity_rms', 'mm/s'):>12}")
    drive = info.get("drive")
    if drive:
        how = ("moved by the driver over" if scene.secondary_motion else "keyed at")
        lines.append(f"drive      {scene.drive.path}: {drive['vertices']} vertices {how} "
                     f"{drive['frames']} frames, followed within {1e3 * drive['max']:.3g} mm "
                     f"(rms {1e3 * drive['rms']:.3g} mm)")
    outputs = info.get("scene", {}).get("outputs", [])
    if outputs:
        lines.append("wrote")
        lines += [f"  {_written(Path(p).resolve())}" for p in outputs]
    else:
        lines.append("wrote      nothing: list files in [output] paths or pass -o FILE")
    return "\n".join(lines)


def _written(path: Path) -> str:
    """An output as the summary names it: an OBJ sequence by its first and last frame files
    (``out/frame.obj`` writes ``out/frame_0000.obj``, ...), not by its base name, which may
    be another file (the input mesh)."""
    if path.suffix.lower() != ".obj":
        return str(path)
    from wiggly.errors import counted
    from wiggly.export.obj import existing_frames

    found = existing_frames(path)
    if not found:
        return str(path)
    first, last = found[min(found)], found[max(found)]
    return f"{first} ... {last.name} ({counted(len(found), 'frame')})"
