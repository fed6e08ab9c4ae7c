"""A batch's summary (``summary.csv``, ``summary.json``) and contact sheets
(``contact-sheet.html`` with every shot, ``contact-sheet.png`` with up to
:data:`MAX_SHEET_TILES`), all written atomically."""

from __future__ import annotations

import csv
import html
import io
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from wiggly.errors import counted
from wiggly.files import atomic_file
from wiggly.progress import say

SUMMARY_FORMAT = 1
#: The contact sheets' files in a batch's folder.
SHEETS = ("contact-sheet.html", "contact-sheet.png")
#: Shots shown in the PNG contact sheet (the HTML one shows all).
MAX_SHEET_TILES = 400
SHEET_COLUMNS = 6
CAPTION = 34  # pixels of text under each tile
#: CSV columns after the parameters, in this order (keyframe residuals in m and m/s).
METRICS = ("solve_seconds", "iterations", "converged", "distance_bound", "warm_start",
           "keyframe_position_rms", "keyframe_position_max", "keyframe_velocity_rms",
           "drive_max", "drive_rms", "setup_seconds", "output_seconds", "thumbnail_seconds",
           "shot_seconds", "cpu_seconds", "commit_seconds", "output_bytes")
PATHS = ("folder", "outputs", "thumbnail")
TRAILING = ("body", "worker", "resumed", "origin", "key")


def jsonable(value: Any) -> Any:
    """``value`` with numpy scalars, tuples and paths made JSON types; NaN and inf as None."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple | dict):
        return json.dumps(jsonable(value))
    return str(value)


def write_summary(out: Path, records: list[dict], meta: dict) -> None:
    """``summary.json`` (the records, the bodies and totals) and ``summary.csv`` (a row per
    shot: name, status, error, every parameter, the solve's numbers, paths)."""
    done = [r for r in records if r["status"] == "done"]
    ran = [r for r in done if not r.get("resumed")]
    wall = meta.get("wall_seconds", 0.0)
    totals = {"shots": len(records), "done": len(done),
              "failed": sum(r["status"] == "failed" for r in records),
              "not_run": sum(r["status"] == "not run" for r in records),
              "resumed": len(done) - len(ran), "ran": len(ran), "wall_seconds": wall,
              "shots_per_hour": 3600 * len(ran) / wall if ran and wall > 0 else None}
    doc = {"format": SUMMARY_FORMAT, "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
           **meta, "totals": totals, "shots": records}
    with atomic_file(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(jsonable(doc), indent=1) + "\n", encoding="utf-8")
    params = list(dict.fromkeys(k for r in records for k in r.get("parameters", {})))
    header = ["shot", "status", "error", "warnings", "seed", "sample", *params, *METRICS,
              *PATHS, *TRAILING]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for r in records:
        p = r.get("parameters", {})
        w.writerow([_cell(r.get("shot")), _cell(r.get("status")),
                    _cell((r.get("error") or "").replace("\n", " | ") or None),
                    _cell(len(r.get("warnings") or ())),  # their text: summary.json
                    _cell(r.get("seed")), _cell(r.get("sample")),
                    *(_cell(p.get(k)) for k in params),
                    *(_cell(r.get(k)) for k in (*METRICS, *PATHS, *TRAILING))])
    with atomic_file(out / "summary.csv") as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")


def _varied(records: list[dict]) -> list[str]:
    """Parameters that differ between shots (the ones worth a caption)."""
    values: dict[str, set] = {}
    for r in records:
        for k, v in r.get("parameters", {}).items():
            values.setdefault(k, set()).add(json.dumps(jsonable(v)))
    return [k for k, v in values.items() if len(v) > 1]


def _short(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    return str(value)


def write_contact_sheets(out: Path, records: list[dict]) -> None:
    """``contact-sheet.html`` (every shot: thumbnail, varied parameters, solve, links) and
    ``contact-sheet.png`` (the first :data:`MAX_SHEET_TILES` thumbnails, captioned)."""
    varied = _varied(records)
    _write_html(out, records, varied)
    _write_png(out, records[:MAX_SHEET_TILES], varied)
    if len(records) > MAX_SHEET_TILES:
        say(f"contact-sheet.png shows the first {MAX_SHEET_TILES} of {len(records)} shots; "
            "contact-sheet.html shows all")


_STYLE = """
body { font: 13px system-ui, sans-serif; margin: 16px; background: #fafafa; color: #222 }
h1 { font-size: 18px } .grid { display: flex; flex-wrap: wrap; gap: 10px }
figure { margin: 0; width: 240px; background: #fff; border: 1px solid #ddd; padding: 4px }
figure.failed { border-color: #d62728; background: #fff4f4 }
figure img, figure .none { width: 240px; height: 180px; display: block; background: #eee }
figcaption { font-size: 12px; line-height: 1.35; word-break: break-word }
.name { font-weight: 600 } .error { color: #b00; white-space: pre-wrap } a { color: #1f77b4 }
.warn summary { color: #a65f00; cursor: pointer } .warn ul { margin: 2px 0; padding-left: 16px }
"""


def _write_html(out: Path, records: list[dict], varied: list[str]) -> None:
    esc = html.escape
    tiles = []
    for r in records:
        p = r.get("parameters", {})
        lines = [f'<div class="name">{esc(r["shot"])}</div>']
        lines += [f"{esc(k)} = {esc(_short(p[k]))}" for k in varied if k in p]
        if r["status"] == "done":
            solve = (f"solve {r.get('solve_seconds', 0):.2f} s, {r.get('iterations', 0)} it"
                     + ("" if r.get("converged", True) else ", <b>not converged</b>"))
            rms = r.get("keyframe_position_rms")
            lines.append(solve + (f", keys &le; {1e3 * rms:.3g} mm" if rms is not None else ""))
            links = [f'<a href="{esc(o)}">{esc(label)}</a>'
                     for o, label in _output_links(r.get("outputs", []))]
            links.append(f'<a href="{esc(r["folder"])}/scene.toml">scene</a>')
            lines.append(" ".join(links))
            if r.get("warnings"):
                said = "".join(f"<li>{esc(w)}</li>" for w in r["warnings"])
                lines.append(f'<details class="warn"><summary>'
                             f'{esc(counted(len(r["warnings"]), "warning"))}</summary>'
                             f"<ul>{said}</ul></details>")
            img = (f'<img src="{esc(r["thumbnail"])}" alt="{esc(r["shot"])}" loading="lazy">'
                   if r.get("thumbnail") else '<div class="none"></div>')
        else:
            lines.append(f'<div class="error">{esc(r["status"])}: {esc(r.get("error") or "")}'
                         "</div>")
            img = '<div class="none"></div>'
        cls = ' class="failed"' if r["status"] != "done" else ""
        tiles.append(f"<figure{cls}>{img}<figcaption>{'<br>'.join(lines)}</figcaption></figure>")
    done = sum(r["status"] == "done" for r in records)
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>wiggly batch</title>"
            f"<style>{_STYLE}</style></head><body><h1>wiggly batch: {done} of {len(records)} "
            f"shots done</h1><p>Summary: <a href='summary.csv'>summary.csv</a>, "
            f"<a href='summary.json'>summary.json</a></p><div class='grid'>{''.join(tiles)}"
            "</div></body></html>\n")
    with atomic_file(out / "contact-sheet.html") as tmp:
        tmp.write_text(page, encoding="utf-8")


def _output_links(outputs: list[str]) -> list[tuple[str, str]]:
    """(href, label) per output of a shot; an OBJ sequence's frame files are one link to its
    first frame, labelled "a.obj, 300 frames"."""
    from wiggly.export.obj import sequence_of

    links: list[tuple[str, str]] = []
    frames: dict[str, list[int]] = {}  # a sequence's name: [its link's index, frame count]
    for o in outputs:
        name = sequence_of(Path(o).name)
        if name is None:
            links.append((o, Path(o).name))
            continue
        if name not in frames:
            frames[name] = [len(links), 0]
            links.append((o, name))
        frames[name][1] += 1
    for name, (j, count) in frames.items():
        links[j] = (links[j][0], f"{name}, {counted(count, 'frame')}")
    return links


def _write_png(out: Path, records: list[dict], varied: list[str]) -> None:
    from PIL import Image, ImageDraw, ImageFont

    from wiggly.batch.worker import THUMBNAIL_SIZE

    if not records:  # an earlier batch's sheet would contradict this summary
        (out / SHEETS[1]).unlink(missing_ok=True)
        return
    tw, th = THUMBNAIL_SIZE
    gap = 6
    cols = min(SHEET_COLUMNS, len(records))
    rows = -(-len(records) // cols)
    font = ImageFont.load_default(size=11)
    captions = [_caption_lines(r.get("parameters", {}), varied, font, tw - 4) for r in records]
    caption = CAPTION + LINE * (max(map(len, captions), default=1) - 1)
    sheet = Image.new("RGB", (cols * tw + (cols + 1) * gap,
                              rows * (th + caption) + (rows + 1) * gap), (250, 250, 250))
    draw = ImageDraw.Draw(sheet)
    for k, r in enumerate(records):
        row, col = divmod(k, cols)
        x, y = gap + col * (tw + gap), gap + row * (th + caption + gap)
        thumb = out / r["thumbnail"] if r.get("thumbnail") else None
        if r["status"] == "done" and thumb is not None and thumb.is_file():
            with Image.open(thumb) as im:
                sheet.paste(im.convert("RGB").resize((tw, th)), (x, y))
        else:
            fill = (255, 228, 228) if r["status"] != "done" else (235, 235, 235)
            draw.rectangle((x, y, x + tw - 1, y + th - 1), fill=fill)
            if r["status"] != "done":
                draw.text((x + 8, y + 8), r["status"], fill=(180, 0, 0), font=font)
        draw.text((x + 2, y + th + 3), r["shot"], fill=(30, 30, 30), font=font)
        if r["status"] == "done" and r.get("warnings"):
            said = counted(len(r["warnings"]), "warning")
            draw.text((x + tw - 2 - font.getlength(said), y + th + 3), said,
                      fill=(166, 95, 0), font=font)
        for j, line in enumerate(captions[k]):
            draw.text((x + 2, y + th + 17 + LINE * j), line, fill=(90, 90, 90), font=font)
    with atomic_file(out / "contact-sheet.png") as tmp:
        sheet.save(tmp, format="PNG", optimize=True)


#: Caption lines of varied parameters under a PNG tile, at most.
CAPTION_LINES = 4
LINE = 14  # pixels per caption line


def _caption_lines(p: dict, varied: list[str], font, width: float) -> list[str]:
    """The varied parameters of a shot as ``name=value`` items, wrapped to ``width`` pixels,
    at most :data:`CAPTION_LINES` lines (the last ends with "..." when more did not fit)."""
    items = [f"{k.rsplit('.', 1)[-1]}={_short(p[k])}" for k in varied if k in p]
    lines: list[str] = []
    for item in items:
        while font.getlength(item) > width and len(item) > 1:  # one item wider than a tile
            item = item[:-2] + "\u2026"
        if lines and font.getlength(f"{lines[-1]}, {item}") <= width:
            lines[-1] = f"{lines[-1]}, {item}"
        else:
            lines.append(item)
    if len(lines) > CAPTION_LINES:
        lines = [*lines[:CAPTION_LINES - 1], lines[CAPTION_LINES - 1] + ", ..."]
    return lines or [""]
