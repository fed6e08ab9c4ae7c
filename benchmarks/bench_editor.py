"""``wiggly edit``: the three figures of issue 16, measured in headless Chromium.

Usage: ``python benchmarks/bench_editor.py [--runs 7] [--only release hold prepare onion]``

* **release**: from the release of a dragged gizmo to updated playback on screen.  A structured
  tet box (30 x 10 x 11 cells, 19,800 tets), a scene with 40 modes and 10 keyframes on 10
  groups; select a keyframe, press W, drag the gizmo's Y arrow with real mouse events,
  release.  The browser measures ``performance.now()`` at ``pointerup`` and again in the
  ``requestAnimationFrame`` callback after the new frames were applied and drawn
  (``window.wiggly.latencies``).  Median, min and max over ``--runs`` drags of the total and its
  parts, and once the time until the first warped (Gauss-Newton) frames.
* **hold**: on the same box, drag the gizmo and hold it still without releasing: the time
  from the last pointer move until the warped frames of the held pose are on screen (the
  refinement process solves a drag's pose warped once no newer drag request supersedes it).
* **prepare**: how fast the server answers while it prepares a mesh.  The bundled critter
  tetrahedralized at resolution 46 (about 20k tets, fTetWild) with 40 modes, from an empty
  cache, in the editor's physics process; meanwhile ``GET /api/state`` and ``POST /api/edit``
  (a group's vertices) every 50 ms.  Median, 95th percentile and max of the answer times over
  ``--prepare-runs`` preparations.
* **onion**: frames drawn per second while the box plays with onion skins (3 ghosts on each
  side) in Chromium's software GL (SwiftShader), over 2-second windows, and the drawing
  resolution the page chose (it lowers it while frames take over a 30th of a second); plain
  playback for comparison, and the skins of one selected group (they ghost only the selected
  groups' faces).

The editor answers a release with a linear solve and linear playback first (Theorem 1,
milliseconds), then refines it with the warped solve in the background (Theorem 2, seconds on
this body).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import tempfile
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import meshio
import numpy as np

try:
    from common import table
except ImportError:  # run from elsewhere
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from common import table

from wiggly.editor import serve
from wiggly.primitives import box_mesh

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--no-first-run"]
CELLS = (30, 10, 11)
FRAME = "() => new Promise(r => requestAnimationFrame(() => r()))"
FPS_WINDOW = """() => new Promise(r => { const t0 = performance.now(), n0 = window.wiggly.renders;
  setTimeout(() => r({fps: (window.wiggly.renders - n0) / ((performance.now() - t0) / 1000),
                      scale: window.wiggly.renderScale}), 2000); })"""


def make_project(folder: Path, cells: tuple[int, int, int] = CELLS, warp: bool = True) -> Path:
    """A tet box 1.5 x 0.5 x 0.55 m and a scene with 10 groups and 10 keyframes."""
    size = (1.5, 0.5, 0.55)
    V, T = box_mesh(cells, size)
    meshio.write(folder / "box.vtu", meshio.Mesh(V, [("tetra", T)]))
    lines = ["format = 1", "[mesh]", 'path = "box.vtu"', "[material]", "young = 2e6",
             "[simulation]", "modes = 40",
             f"warp = {'true' if warp else 'false'}", "[time]", "end = 2.0", "fps = 30", ""]
    rng = np.random.default_rng(1)
    for k in range(10):
        x = 0.1 + 1.3 * k / 9
        lines += [f"[groups.g{k}]",
                  f"sphere = {{ center = [{x:.3f}, 0.5, 0.275], radius = 0.09 }}", ""]
    for k in range(10):
        dy = 0.05 * rng.uniform(-1, 1)
        lines += ["[[keyframes]]", f"time = {0.2 * k:.1f}", f'group = "g{k}"',
                  f"position = {{ offset = [0.0, {dy:.4f}, 0.0] }}", ""]
    (folder / "bench.toml").write_text("\n".join(lines))
    return folder / "bench.toml"


def drag_gizmo(page, pixels: float, release: bool = True) -> None:
    h = page.evaluate("window.wiggly.gizmoHandle('Y')")
    for d in range(12, 240, 4):
        x, y = h["x"] + d * h["dx"], h["y"] + d * h["dy"]
        page.mouse.move(x, y)
        if page.evaluate("window.wiggly.gizmoHandle('Y').axis") == "Y":
            break
    else:
        raise RuntimeError("cannot find the gizmo's Y handle")
    page.mouse.down()
    for k in range(1, 7):
        page.mouse.move(x + k * pixels / 6 * h["dx"], y + k * pixels / 6 * h["dy"])
        page.evaluate(FRAME)
    if release:
        page.mouse.up()


@contextmanager
def box_page(p, args, profile: str, ready: str, autosave: bool = True):
    """The benchmark box (:func:`make_project`) served from a temporary folder and open in
    headless Chromium, once the page's ``ready`` condition holds; yields (server, page)."""
    work = Path(tempfile.mkdtemp(prefix="wiggly-bench-editor-"))
    server = serve(make_project(work, tuple(args.cells)), autosave=autosave)
    ctx = None
    try:
        ctx = p.chromium.launch_persistent_context(
            profile, executable_path=args.chromium, headless=True, args=FLAGS,
            viewport={"width": 1280, "height": 800})
        page = ctx.new_page()
        page.goto(server.url)
        page.wait_for_function(f"window.wiggly.ready && {ready}", timeout=600_000)
        yield server, page
    finally:
        if ctx is not None:
            ctx.close()
        server.stop()
        shutil.rmtree(work, ignore_errors=True)


def pose_key(page, key_id: int = 5) -> None:
    """Select keyframe ``key_id`` and pose it with the move gizmo (W)."""
    page.click(f"#keys li[data-key='{key_id}']")
    page.keyboard.press("w")
    page.wait_for_function("window.wiggly.S.posing !== null")


def _stats(values: list[float]) -> tuple[float, float, float]:
    return (round(statistics.median(values), 1), round(min(values), 1), round(max(values), 1))


def bench_release(p, args, profile: str) -> tuple[list, str]:
    notes = []
    # autosave and undo journal on
    with box_page(p, args, profile, "window.wiggly.S.frames !== null") as (server, page):
        body = server.session.physics.body_future(server.session.scene).result()
        notes.append(f"body: {body.tets.n_tets} tets, {body.surface.n_vertices} surface "
                     f"vertices, {body.r} modes, {len(server.session.scene.keyframes)} keyframes;"
                     f" software GL: {page.evaluate('window.wiggly.softwareGL')}")
        pose_key(page)
        rows = []
        for run in range(args.runs):
            n = page.evaluate("window.wiggly.latencies.length")
            drag_gizmo(page, 30 if run % 2 == 0 else -30)
            first = f"window.wiggly.latencies.slice({n}).find((l) => l.first)"
            page.wait_for_function(f"{first} !== undefined", timeout=60_000)
            rows.append(page.evaluate(first))
            page.wait_for_function("window.wiggly.S.committing === null", timeout=60_000)
        last = ("window.wiggly.latencies.slice(window.wiggly.latencies.findLastIndex("
                "(l) => l.first)).find((l) => l.stage.startsWith('warped'))")
        try:
            page.wait_for_function(f"{last} !== undefined", timeout=180_000)
            notes.append("release -> first warped frames on screen (last drag): "
                         f"{page.evaluate(last)['ms']:.0f} ms")
        except Exception:
            notes.append("release -> first warped frames: not within 180 s")
    for r in rows:
        r["server_ms"] = 1e3 * r["server_seconds"] if r.get("server_seconds") else None
    parts = [("gizmo release -> new frames drawn (target < 300 ms)", "ms"),
             ("  edit POST answered", "posted"), ("  frames event received", "event"),
             ("  frames requested", "requested"), ("  frames fetched", "fetched"),
             ("  frames applied", "applied"),
             ("  server: linear solve + playback frames", "server_ms")]
    out = []
    for label, key in parts:
        vals = [r[key] for r in rows if r.get(key) is not None]
        if vals:
            out.append([label, *_stats(vals)])
    notes.append(f"stage of the first update: {', '.join(sorted({r['stage'] for r in rows}))}")
    return out, "\n".join(notes)


# resolves, polled every animation frame, with the ms from its start until the frames shown
# are the warped frames of a drag (the held pose's)
HELD = """() => new Promise((resolve) => { const t0 = performance.now();
  const poll = () => { const m = window.wiggly.S.frames && window.wiggly.S.frames.meta;
    if (m && m.request === 'drag' && m.stage === 'warped') resolve(performance.now() - t0);
    else if (performance.now() - t0 > 60000) resolve(null);
    else requestAnimationFrame(poll); };
  poll(); })"""


def bench_hold(p, args, profile: str) -> tuple[list, str]:
    held, warm = [], []
    final = ("window.wiggly.S.frames && window.wiggly.S.frames.meta.final && "
             "window.wiggly.S.frames.meta.stage === 'warped' && "
             "window.wiggly.S.committing === null")
    with box_page(p, args, profile, final, autosave=False) as (server, page):
        pose_key(page)
        events = server.session.bus.subscribe()
        for run in range(args.runs):
            drag_gizmo(page, 30 if run % 2 == 0 else -30, release=False)
            held.append(page.evaluate(HELD))
            page.mouse.up()
            page.wait_for_function(final, timeout=120_000)
        while not events.empty():  # the child's own time for the held poses' warped solves
            e = events.get_nowait()
            if e["type"] == "frames" and e.get("request") == "drag" and e["stage"] == "warped":
                warm.append(1e3 * e["seconds"])
    done = [h for h in held if h is not None]
    rows = []
    if done:
        rows.append(["last pointer move -> warped frames of the held pose drawn", *_stats(done)])
    if warm:
        rows.append(["  refinement process: the held pose's warped solve (warm start)",
                     *_stats(warm)])
    notes = f"{len(done)} of {len(held)} held drags showed warped frames within 60 s"
    return rows, notes


def bench_prepare(args) -> tuple[list, str]:
    from wiggly.scene import builtin_model

    answers: dict[str, list[float]] = {"GET /api/state": [], "POST /api/edit": []}
    notes = []
    for _ in range(args.prepare_runs):
        work = Path(tempfile.mkdtemp(prefix="wiggly-bench-prepare-"))
        old = os.environ.get("WIGGLY_CACHE_DIR")
        os.environ["WIGGLY_CACHE_DIR"] = str(work / "cache")  # fTetWild and modes afresh
        shutil.copy(builtin_model("critter"), work / "critter.obj")
        (work / "critter.toml").write_text(
            'format = 1\n[mesh]\npath = "critter.obj"\nresolution = 46\n[simulation]\n'
            "modes = 40\n[time]\nend = 2.0\n")
        t0 = time.perf_counter()
        server = serve(work / "critter.toml")
        try:
            events = server.session.bus.subscribe()
            ready, k = None, 0
            while ready is None and time.perf_counter() - t0 < 600:
                for label, req in (
                        ("GET /api/state", urllib.request.Request(server.url + "api/state")),
                        ("POST /api/edit", urllib.request.Request(
                            server.url + "api/edit", json.dumps(
                                {"op": "set_group", "name": "g", "indices": [k % 50]}).encode(),
                            {"Content-Type": "application/json"}))):
                    t = time.perf_counter()
                    with urllib.request.urlopen(req, timeout=60) as r:
                        r.read()
                    answers[label].append(1e3 * (time.perf_counter() - t))
                k += 1
                while not events.empty():
                    e = events.get_nowait()
                    if e["type"] == "physics" and e["stage"] in ("ready", "error"):
                        ready = e
                time.sleep(0.05)
            notes.append(f"prepared {ready and ready['message']} in "
                         f"{time.perf_counter() - t0:.1f} s")
        finally:
            server.stop()
            if old is None:
                os.environ.pop("WIGGLY_CACHE_DIR", None)
            else:
                os.environ["WIGGLY_CACHE_DIR"] = old
            shutil.rmtree(work, ignore_errors=True)
    rows = []
    for label, vals in answers.items():
        vals = sorted(vals)
        rows.append([f"{label} while preparing (target < 100 ms)",
                     round(statistics.median(vals), 1), round(vals[int(0.95 * len(vals))], 1),
                     round(vals[-1], 1), len(vals)])
    return rows, "\n".join(notes)


def bench_onion(p, args, profile: str) -> tuple[list, str]:
    rows = []
    final = ("window.wiggly.S.frames && window.wiggly.S.frames.meta.final && "
             "window.wiggly.S.frames.meta.stage === 'warped'")
    with box_page(p, args, profile, final, autosave=False) as (_, page):
        soft = page.evaluate("window.wiggly.softwareGL")
        page.keyboard.press("Space")
        for label, key in (("plain playback", None),
                           ("with onion skins, 3 + 3 (target >= 30)", "o"),
                           ("with onion skins of one selected group (g5)", "g5")):
            if key == "g5":  # the skins ghost only the selected groups
                page.click("#groups li[data-group=g5] .name")
                page.wait_for_function("window.wiggly.S.selectedGroup === 'g5'")
            elif key:
                page.keyboard.press(key)
            page.evaluate(FPS_WINDOW)  # let the resolution settle
            windows = [page.evaluate(FPS_WINDOW) for _ in range(args.windows)]
            fps = [w["fps"] for w in windows]
            scale = statistics.median(w["scale"] for w in windows)
            rows.append([label, *_stats(fps), round(scale, 2)])
    return rows, f"software GL: {soft}; viewport 1280 x 800"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=7, help="gizmo drags")
    ap.add_argument("--prepare-runs", type=int, default=2, help="mesh preparations")
    ap.add_argument("--windows", type=int, default=5, help="2-second playback windows")
    ap.add_argument("--quick", action="store_true", help="fewer runs (run_all.py --quick)")
    ap.add_argument("--only", nargs="+", choices=("release", "hold", "prepare", "onion"),
                    default=("release", "hold", "prepare", "onion"))
    ap.add_argument("--cells", type=int, nargs=3, default=CELLS)
    ap.add_argument("--chromium", default="/usr/bin/chromium")
    args = ap.parse_args(argv)
    if args.quick:
        args.runs, args.prepare_runs, args.windows = 3, 1, 3
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        print("bench_editor: skipped (pip install playwright)")
        return 0
    if not Path(args.chromium).exists():
        print(f"bench_editor: skipped ({args.chromium} missing: apt-get install chromium)")
        return 0
    profile = tempfile.mkdtemp(prefix="wiggly-bench-chromium-")
    try:
        if "prepare" in args.only:
            rows, notes = bench_prepare(args)
            print(table("Editor: server answers while a 20k-tet mesh is prepared (ms)",
                        ["request", "median", "95th pct", "max", "requests"], rows))
            print(notes + "\n")
        with sync_playwright() as p:
            if "release" in args.only:
                rows, notes = bench_release(p, args, profile)
                print(table(f"Editor: gizmo release to updated playback ({args.runs} drags, "
                            "ms)", ["measure", "median", "min", "max"], rows))
                print(notes + "\n")
            if "hold" in args.only:
                rows, notes = bench_hold(p, args, tempfile.mkdtemp(prefix="wiggly-bench-h-"))
                print(table(f"Editor: a held gizmo drag to warped frames ({args.runs} drags, "
                            "ms)", ["measure", "median", "min", "max"], rows))
                print(notes + "\n")
            if "onion" in args.only:
                rows, notes = bench_onion(p, args, tempfile.mkdtemp(prefix="wiggly-bench-c-"))
                print(table(f"Editor: playback in Chromium, 20k-tet box, frames/s "
                            f"({args.windows} windows of 2 s)",
                            ["playback", "median", "min", "max", "resolution scale"], rows))
                print(notes + "\n")
    finally:
        shutil.rmtree(profile, ignore_errors=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
