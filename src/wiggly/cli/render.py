"""``wiggly render INPUT -o OUT``: a preview of a scene or of an exported animation."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "render a preview (.mp4, .gif, .png) of a scene or an exported animation"
DESCRIPTION = """\
Render previews: an MP4 or GIF video, or a PNG contact sheet of 8 frames.
INPUT is either a scene file (.toml), which is solved first (keyframed groups are
highlighted at their key times, targets drawn as small spheres), or an animation
(.npz, .glb, .gltf, .usd, .usda, .usdc, or the first file name of an .obj sequence
given as NAME.obj), which is rendered as it is. A glTF or USD file from another
tool is read as a [drive] driver is: skins, morph targets and node transforms
evaluated, in metres with y up. Several outputs are written all or none."""
EPILOG = """\
examples:
  wiggly render examples/turn.toml -o turn.gif
  wiggly render out/jump.npz -o jump.mp4 --camera side
  wiggly render out/jump.glb -o jump-sheet.png --overwrite"""

ANIMATION_EXTENSIONS = (".npz", ".glb", ".gltf", ".usd", ".usda", ".usdc", ".usdz", ".obj")


def _read(source: Path, fps: float | None = None):
    """The animation in ``source``: wiggly's own files as written; a glTF or USD file or an
    OBJ sequence of another tool as a driver is read (:func:`wiggly.drive.read_driver`:
    skins, morph targets and node transforms evaluated; Blender's ``mesh0001.obj`` numbering,
    polygons; frame N at N / ``fps`` (default 24) without wiggly's time comments), which the
    readers of wiggly's layout would refuse or take as one still frame."""
    from wiggly.drive import read_driver
    from wiggly.drive.sequence import sequence_files
    from wiggly.export import SurfaceAnimation, read_animation
    from wiggly.export.formats import written_by_wiggly
    from wiggly.export.obj import existing_frames, written_by_wiggly_obj
    from wiggly.progress import say

    ext = source.suffix.lower()
    if ext == ".obj":
        own = existing_frames(source) or {0: source}
        foreign = sequence_files(source) if not written_by_wiggly_obj(own[min(own)]) else []
        if not foreign:
            return read_animation(source)
        driver = read_driver(source, frame_rate=fps or 24.0)
    elif ext == ".npz" or written_by_wiggly(source):
        return read_animation(source)
    else:
        driver = read_driver(source)
    say(f"{source.name} is not wiggly's: read as a driver ({driver.kind}, "
        f"{len(driver.times)} frames)")
    return SurfaceAnimation(driver.times, driver.positions, driver.faces,
                            name=source.stem)


def size_arg(text: str) -> tuple[int, int]:
    """``--size WxH`` as (width, height) in pixels (argparse's type)."""
    from wiggly.checks import pixel_size

    try:
        w, h = (int(v) for v in text.lower().split("x"))
        return pixel_size((w, h), "--size")
    except (ValueError, TypeError) as err:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a size WIDTHxHEIGHT in pixels, each 16-8192 (e.g. 1280x720)"
        ) from err
    except Exception as err:  # WigglyInputError of pixel_size
        raise argparse.ArgumentTypeError(str(err)) from None


def add_args(parser: argparse.ArgumentParser) -> None:
    from wiggly.scene import CAMERAS

    parser.add_argument("input", metavar="INPUT",
                        help="scene file (.toml) or animation (.npz .glb .usd* .obj)")
    parser.add_argument("-o", "--output", metavar="OUT", action="append", required=True,
                        help="preview to write: .mp4, .gif or .png (repeatable)")
    parser.add_argument("--overwrite", action="store_true", default=None,
                        help="replace existing files")
    parser.add_argument("--fps", type=float, metavar="N",
                        help="video frame rate (default: the scene's, or the animation's)")
    parser.add_argument("--camera", choices=CAMERAS, default=None,
                        help="camera preset (default: the scene's, or three_quarter)")
    parser.add_argument("--size", type=size_arg, metavar="WxH", default=None,
                        help="video size in pixels, e.g. 1280x720; a .png sheet's tiles are "
                             "half of it (default: the scene's, or "
                             "960x540)")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars or stage messages")


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from wiggly.cli.animate import summary
    from wiggly.errors import WigglyInputError, counted
    from wiggly.progress import say
    from wiggly.scene import (
        PREVIEW_EXTENSIONS,
        OutputSpec,
        check_outputs,
        load_scene,
        render_preview,
        with_overrides,
    )
    from wiggly.scene import run as run_scene

    outputs = [Path(o) for o in args.output]
    for out in outputs:
        if out.suffix.lower() not in PREVIEW_EXTENSIONS:
            raise WigglyInputError(f"{out}: render writes .mp4, .gif or .png previews; use "
                                   "`wiggly animate` for geometry (.glb .usd .obj .npz)")
    if args.fps is not None and not args.fps > 0:
        raise WigglyInputError(f"--fps {args.fps:g} must be > 0")
    source = Path(args.input)
    ext = source.suffix.lower()
    if ext == ".toml":
        scene = load_scene(source, output_fps=args.fps)
        scene = with_overrides(scene, fps=args.fps)
        if args.camera is not None:
            scene = replace(scene, output=replace(scene.output, camera=args.camera))
        if args.size is not None:
            scene = replace(scene, output=replace(scene.output, size=args.size))
        anim = run_scene(scene, outputs=outputs, overwrite=args.overwrite)
        print(summary(scene, anim))
        return 0
    if ext not in ANIMATION_EXTENSIONS:
        raise WigglyInputError(f"{source}: not a scene (.toml) or an animation "
                               f"({', '.join(ANIMATION_EXTENSIONS)})")
    from wiggly.export.animation import without_seam
    from wiggly.files import OutputSet

    overwrite = bool(args.overwrite)
    check_outputs(outputs, overwrite)
    anim = _read(source, args.fps)
    shown = without_seam(anim)  # a looping video shows the seam's pose once
    spec = OutputSpec(camera=args.camera or "three_quarter")
    if args.size is not None:
        spec = replace(spec, size=args.size)
    with OutputSet() as staged:  # all or none, also when interrupted
        for out in outputs:
            say(f"rendering {out}")
            render_preview(staged.stage(out), shown.times, shown.positions, shown.faces,
                           output=spec, title=anim.name, overwrite=True, fps=args.fps)
    print(f"{source}: {counted(anim.n_frames, 'frame')}, {anim.n_vertices} vertices, "
          f"[{anim.times[0]:g}, {anim.times[-1]:g}] s")
    print("wrote")
    for out in outputs:
        print(f"  {out.resolve()}")
    return 0
