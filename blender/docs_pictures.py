"""The pictures of docs/blender.md, made by Blender headless (PyPI ``bpy`` in .venv-blender).

Blender renders the bar of the tests (a handle keys its left end; the middle is fixed) with
Workbench after a real bake, frame by frame; the timeline and the panel come from the same
Blender session: the handle's keyframes and the baked positions per frame, and the Wiggly
panel as the add-on's draw() code lays it out (the Python module bpy has no window, so its
interface cannot be screenshot; the panel is redrawn here from that layout, in Blender's
dark theme colours).

usage: .venv/bin/python blender/docs_pictures.py [OUT_DIR]   (default: docs/)
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "blender" / "wiggly_addon.py"
FRAMES = [1, 4, 7, 9, 12, 15, 18, 25]
BG, PANEL, HEADER, FIELD, TEXT, DIM, ACCENT = ((48, 48, 48), (61, 61, 61), (48, 48, 48),
                                               (84, 84, 84), (230, 230, 230), (150, 150, 150),
                                               (71, 114, 179))


def _font(size: int):
    for name in ("DejaVuSans.ttf", "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"):
        try:
            return ImageFont.truetype(name, size)
        except OSError:
            continue
    return ImageFont.load_default()


def strip(seen: dict, out: Path) -> None:
    """The rendered frames in a 4 x 2 grid, each labelled with its frame and key."""
    keys = dict(next(iter(seen["keys"].values())))
    tiles = [Image.open(path).convert("RGB") for _, path in seen["renders"]]
    w, h = tiles[0].size
    grid = Image.new("RGB", (4 * w, 2 * h), BG)
    draw, font = ImageDraw.Draw(grid), _font(22)
    for i, ((frame, _), tile) in enumerate(zip(seen["renders"], tiles, strict=True)):
        x, y = (i % 4) * w, (i // 4) * h
        grid.paste(tile, (x, y))
        label = f"frame {frame}"
        if frame == 18:  # the subframe key at 17.5
            label += "  (key at 17.5, still)"
        elif frame in keys:
            label += "  (key, Moving Hold: still)" if keys[frame] == "MOVING_HOLD" else "  (key)"
        draw.text((x + 12, y + 10), label, fill=(235, 235, 235), font=font)
    grid.save(out, optimize=True)


def timeline(seen: dict, out: Path) -> None:
    """The handle's keys on Blender's frames above the baked heights of both ends."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = np.arange(1, 26)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 5.0), sharex=True,
                                      gridspec_kw={"height_ratios": [1.3, 2.4]})
    for ax in (top, bottom):
        ax.set_facecolor((0.16, 0.16, 0.16))
        ax.axvspan(0.5, 25.5, color=(0.22, 0.22, 0.22), zorder=0)
    rows = list(seen["keys"].items())
    for row, (_, keys) in enumerate(rows, start=1):
        for still in (False, True):
            at = [f for f, k in keys if f <= 25 and (k == "MOVING_HOLD") == still]
            top.scatter(at, [row] * len(at), marker="D", s=70, zorder=3,
                        color=(0.55, 0.55, 0.55) if still else (0.9, 0.9, 0.9),
                        edgecolor="white",
                        label=("Moving Hold (still)" if still else "keyframe") if row == 1
                        else None)
    top.scatter(frames, [0] * len(frames), marker="|", s=120, color=(0.95, 0.6, 0.2),
                label="Wiggly bake (PC2 sample)")
    top.set_yticks(range(len(rows) + 1), ["Wiggly bake", *(n for n, _ in rows)])
    top.set_ylim(-0.7, len(rows) + 0.9)
    top.legend(loc="upper right", fontsize=8, ncol=3, facecolor=(0.3, 0.3, 0.3),
               labelcolor="white", framealpha=0.9)
    keys = [(f, k) for f, k in seen["keys"][rows[0][0]] if f <= 25]
    bottom.plot(frames, 100 * np.array(seen["left_z"]), "o-", ms=3,
                color=(0.35, 0.55, 1.0), label="left end (keyed by the handle)")
    bottom.plot(frames, 100 * np.array(seen["right_z"]), "o-", ms=3,
                color=(0.95, 0.6, 0.2), label="right end (free: wiggly)")
    for f, _ in keys:
        bottom.axvline(f, color=(0.5, 0.5, 0.5), lw=0.8, ls=":")
    bottom.set_ylabel("height above rest (cm)")
    bottom.set_xlabel("Blender frame (24 fps)")
    bottom.set_xticks(range(1, 26, 2))
    bottom.set_xlim(0.3, 25.7)
    bottom.legend(loc="lower left", fontsize=8, facecolor=(0.3, 0.3, 0.3), labelcolor="white")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


GLYPH = {"ADD": "+", "REMOVE": "-", "EMPTY_AXIS": "E", "PINNED": "R", "TRASH": "", "PLAY": "",
         "EXPORT": ""}


def _lines(node: dict, indent: int = 0) -> list[tuple]:
    """The recorded layout as drawable lines: (kind, indent, payload)."""
    out = []
    for item in node["items"]:
        if "kind" not in item:
            kind = next(k for k in ("label", "prop", "operator", "list") if k in item)
            out.append((kind if kind != "operator" else "buttons", indent,
                        [item] if kind == "operator" else item))
            continue
        children = item["items"]
        icons = [c for c in children if isinstance(c, dict) and c.get("operator") == ""]
        lists = [c for c in children if "list" in c]
        if item["kind"] == "row" and lists:
            column = next(c for c in children if c.get("kind") == "column")
            out.append(("list", indent, {**lists[0], "buttons": column["items"]}))
        elif item["kind"] == "row" and icons and any("prop" in c for c in children):
            prop = next(c for c in children if "prop" in c)
            out.append(("prop", indent, {**prop, "buttons": icons}))
        elif item["kind"] == "row" and all("operator" in c for c in children):
            out.append(("buttons", indent, children))
        else:
            out += _lines(item, indent + (8 if item["kind"] == "box" else 0))
    return out


def panel(seen: dict, out: Path) -> None:
    """The Wiggly panel as its draw() code laid it out, in Blender's dark theme."""
    width, row_h, pad = 430, 30, 10
    font, bold = _font(15), _font(16)
    sections = [(p["title"], _lines(p["layout"])) for p in seen["panel"]]
    height = pad + sum(row_h + 6 + sum(row_h * (max(len(n["list"]), n["rows"]) if kind ==
                                                "list" else 1) for kind, _, n in ls)
                       for _, ls in sections)
    image = Image.new("RGB", (width, height + pad), BG)
    d = ImageDraw.Draw(image)

    def button(x0, y, x1, b, accent=False):
        d.rounded_rectangle([x0 + 1, y + 3, x1 - 2, y + row_h - 5], 4,
                            fill=ACCENT if accent else FIELD)
        text = b["operator"] or GLYPH.get(b["icon"], "")
        tw = d.textlength(text, font=font)
        d.text(((x0 + x1 - tw) / 2, y + 6), text, fill=TEXT if b["enabled"] else DIM, font=font)

    y = pad
    for title, ls in sections:
        d.rectangle([6, y, width - 6, y + row_h - 4], fill=HEADER)
        d.text((16, y + 5), ("v  " if title == "Wiggly" else "   v  ") + title, fill=TEXT,
               font=bold)
        y += row_h
        for kind, indent, node in ls:
            x0, right = 16 + indent, width - 16
            if kind == "label":
                d.text((x0, y + 6), node["label"], fill=DIM, font=font)
                y += row_h
            elif kind == "prop":
                name, value = node["prop"], node["value"]
                icons = node.get("buttons", [])
                field_right = right - 30 * len(icons)
                for i, b in enumerate(icons):
                    button(field_right + 30 * i, y, field_right + 30 * (i + 1), b)
                if node["type"] == "BOOLEAN":
                    d.rectangle([width // 2 - 40, y + 7, width // 2 - 26, y + 21],
                                fill=ACCENT if value else FIELD)
                    d.text((width // 2 - 18, y + 5), name, fill=TEXT, font=font)
                else:
                    fx = width // 2 - 40 if node["split"] else x0 + 110
                    nx = fx - 10 - d.textlength(name, font=font) if node["split"] else x0
                    d.text((nx, y + 6), name, fill=TEXT, font=font)
                    d.rounded_rectangle([fx, y + 3, field_right - 2, y + row_h - 5], 4,
                                        fill=FIELD)
                    d.text((fx + 8, y + 6), str(value), fill=TEXT, font=font)
                y += row_h
            elif kind == "buttons":
                span = (right - x0) / len(node)
                for i, b in enumerate(node):
                    button(x0 + i * span, y, x0 + (i + 1) * span, b, b["operator"] == "Bake")
                y += row_h
            elif kind == "list":
                rows = max(len(node["list"]), node["rows"])
                lr = right - 34
                d.rectangle([x0, y + 2, lr, y + rows * row_h - 2], fill=(40, 40, 40))
                for i, b in enumerate(node["buttons"]):
                    button(lr + 4, y + i * row_h, right, b)
                for i, r in enumerate(node["list"]):
                    ry = y + i * row_h
                    if r["active"]:
                        d.rectangle([x0, ry + 2, lr, ry + row_h - 2], fill=ACCENT)
                    cells = [c for c in r["cells"]["items"][0]["items"] if "label" in c]
                    d.text((x0 + 8, ry + 6), cells[0]["label"], fill=TEXT, font=font)
                    d.text((x0 + 170, ry + 6), cells[1]["label"], fill=TEXT if r["active"]
                           else DIM, font=font)
                y += rows * row_h
        y += 6
    image.save(out, optimize=True)


def main() -> None:
    out_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs"
    python = os.environ.get("WIGGLY_BLENDER_PYTHON") or str(ROOT / ".venv-blender/bin/python")
    wiggly = shutil.which("wiggly", path=str(Path(sys.executable).parent)) or "wiggly"
    with tempfile.TemporaryDirectory(prefix="blender-pictures-") as tmp:
        work = Path(tmp)
        (work / "options.json").write_text(json.dumps({"frames": FRAMES, "size": [400, 250]}))
        done = subprocess.run([python, str(SCRIPT), "pictures", str(work / "out.json"), wiggly,
                               str(work), str(work / "options.json")], capture_output=True,
                              text=True)
        if done.returncode != 0:
            sys.exit(f"Blender run failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
        seen = json.loads((work / "out.json").read_text())
        strip(seen, out_dir / "blender_bake.png")
    timeline(seen, out_dir / "blender_timeline.png")
    panel(seen, out_dir / "blender_panel.png")
    print(f"wrote {out_dir}/blender_bake.png, blender_timeline.png, blender_panel.png")


if __name__ == "__main__":
    main()
