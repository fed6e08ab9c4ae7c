"""``wiggly demo``: animate the bundled demo scene (the critter jumps)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "animate the bundled demo (the critter crouches, jumps and lands)"
DESCRIPTION = """\
Animate the bundled demo scene (wiggly/data/demo.toml): the critter crouches,
jumps (a ballistic flight under gravity, no keyframes in the air), lands with a
squash and wiggles its tail. Writes critter.glb (glTF animation: open it in
Blender or any glTF viewer), critter.mp4 (preview video) and critter-sheet.png
(contact sheet) into DIR and prints their absolute paths. Takes about 6 seconds
on two cores once its mesh and modes are cached (15 s the first time), plus about
a minute for the kernels' compilation the first time after an install."""
EPILOG = """\
examples:
  wiggly demo
  wiggly demo -o /tmp/demo --overwrite
  wiggly demo --quiet   # only the summary

The scene file is wiggly/data/demo.toml in the installed package: copy it to start
your own shot (replace its [output] paths)."""


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-o", "--output", metavar="DIR", default="wiggly-demo",
                        help="output directory (default: ./wiggly-demo)")
    parser.add_argument("--overwrite", action="store_true", default=None,
                        help="replace existing files")
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars or stage messages")


def demo_scene_path() -> Path:
    from importlib import resources

    return Path(str(resources.files("wiggly") / "data" / "demo.toml"))


def run(args: argparse.Namespace) -> int:
    from wiggly.cli.animate import summary
    from wiggly.errors import WigglyInputError
    from wiggly.scene import load_scene
    from wiggly.scene import run as run_scene

    scene = load_scene(demo_scene_path())
    directory = Path(args.output).expanduser()
    outputs = [directory / Path(p).name for p in scene.output.paths]
    there = [p for p in outputs if p.exists()]
    if there and not args.overwrite:  # said in the demo's terms, before anything is computed
        raise WigglyInputError(
            f"{directory}{'/' if directory.is_dir() else ''} holds a demo's results already "
            f"({', '.join(p.name for p in there)}): pass --overwrite to make them again, or -o "
            "another folder")
    anim = run_scene(scene, outputs=outputs, overwrite=args.overwrite)
    print(summary(scene, anim))
    print(f"\nNext: `source {Path(sys.prefix) / 'bin' / 'activate'}` puts the wiggly command "
          f"({Path(sys.argv[0]).resolve()}) on this shell's PATH; docs/getting-started.md goes "
          "on from there.")
    return 0
