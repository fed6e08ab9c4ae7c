"""Render ``docs/walk_secondary.png``: the walk driver above, wiggly's motion below.

Solves ``examples/walk_secondary.toml`` (about half a minute on two cores) and renders two
contact sheets at the same times, seen from its side: the driver
(``examples/critter_walk.glb``, whose tail and ears are skinned rigidly and which holds its
last pose after 2 s) and the solved motion, with the driven group in blue and the free tail
and ears in orange.  The body is the driver's; the tail swings against the trot while the
critter walks (the times are the swing's extremes), and on after it stops.  Run from the
repository root::

    .venv/bin/python scripts/walk_secondary_sheet.py [out.png]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from wiggly.drive import read_driver
from wiggly.progress import reporting
from wiggly.render import Highlight, render_contact_sheet
from wiggly.scene import load_scene, run

ROOT = Path(__file__).resolve().parents[1]
TIMES = (0.45, 0.68, 0.93, 1.18, 2.1, 2.28)
TILE = (300, 250)


def main(out: Path = ROOT / "docs" / "walk_secondary.png") -> Path:
    scene = load_scene(ROOT / "examples" / "walk_secondary.toml")
    with reporting():  # bars on a terminal
        anim = run(scene, outputs=[])
    driver = read_driver(ROOT / "examples" / "critter_walk.glb")
    times = anim.frame_times(scene.time.fps)
    solved = anim.positions(times)
    k = np.minimum(np.searchsorted(driver.times, times - 1e-9), driver.n_frames - 1)
    driven_pose = driver.positions[k]  # frames are on the same 30 fps grid; last pose after
    faces = anim.body.surface.faces
    groups = anim.info["scene"]["groups"]
    free = np.concatenate([groups["tail"], groups["ears"]])
    always = 1e3  # s: a highlight window longer than the shot colours every frame
    colours = [Highlight(groups["body"], 0.0, (0.12, 0.47, 0.71), label=None, window=always),
               Highlight(free, 0.0, (1.0, 0.5, 0.05), label=None, window=always)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, positions in (("driver", driven_pose), ("wiggly", solved)):
            path = render_contact_sheet(Path(tmp) / f"{name}.png", times, positions, faces,
                                        at=TIMES, columns=len(TIMES), tile_size=TILE,
                                        camera="front", highlights=colours)
            rows.append(Image.open(path).convert("RGB"))
    label = 28
    sheet = Image.new("RGB", (rows[0].width, 2 * (rows[0].height + label)), (250, 250, 250))
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=18)
    captions = ("driver: critter_walk.glb, skinned (tail and ears rigid), stops at 2 s",
                "wiggly: the body (blue) follows the driver; the tail and the ears (orange) "
                "move by physics during the walk")
    for j, (row, caption) in enumerate(zip(rows, captions, strict=True)):
        y = j * (row.height + label)
        draw.text((10, y + label / 2), caption, anchor="lm", fill=(20, 22, 28), font=font)
        sheet.paste(row, (0, y + label))
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB)")
    return out


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:2]))
