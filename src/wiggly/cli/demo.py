"""``wiggly demo``: animate the bundled demo scene (the critter jumps)."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "animate the bundled demo (the critter crouches, jumps and lands)"
DESCRIPTION = """\
Animate the bundled demo scene (wiggly/data/demo.toml): the critter crouches,
jumps (a ballistic flight under gravity, no keyframes in the air), lands with a
squash and wiggles its tail. Writes critter.glb (glTF animation: open it in
Blender or any glTF viewer), critter.mp4 (preview video) and critter-sheet.png
(contact sheet) into DIR and prints their absolute paths. Takes some 20 to 40
seconds on two cores."""
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
    from wiggly.scene import load_scene
    from wiggly.scene import run as run_scene

    scene = load_scene(demo_scene_path())
    directory = Path(args.output).expanduser()
    outputs = [directory / Path(p).name for p in scene.output.paths]
    anim = run_scene(scene, outputs=outputs, overwrite=args.overwrite)
    print(summary(scene, anim))
    return 0
