"""Helpers of the editor's browser tests: a page per test on a fresh browser context, real mouse
and keyboard gestures, and waits on explicit page state (never on sleeps).

Projects are structured tet bars (no tetrahedralizer), so every solve takes milliseconds.
"""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import meshio
import numpy as np

from wiggly.primitives import box_mesh

BAR_SCENE = """\
format = 1
[mesh]
path = "bar.vtu"
[material]
young = 1e6
[simulation]
modes = 12
fixed = ["left"]
warp = {warp}
[time]
end = 1.0
fps = 20
[groups.left]
box = {{ min = [-0.01, -1, -1], max = [0.01, 1, 1] }}
[groups.mid]
box = {{ min = [0.49, -1, -1], max = [0.51, 1, 1] }}
[groups.right]
box = {{ min = [0.99, -1, -1], max = [1.01, 1, 1] }}
[[keyframes]]
time = 0.5
group = "right"
position = {{ offset = [0.0, 0.05, 0.0] }}
{extra}"""

# How long (ms) to wait for the editor's first frames: its physics child runs at nice +5, and
# the suite's other worker keeps both cores busy (fTetWild, Blender, batch workers), where
# meshing and modes of the bar took up to about a minute; a wait, not a speed requirement.
LOADED = 150_000


def bar_project(folder: Path, extra: str = "", name: str = "shot.toml",
                warp: bool = True) -> Path:
    """A 1 m x 0.1 m x 0.1 m tet bar (8 x 2 x 2 cells, 81 vertices) and a scene on it: left end
    fixed, right end lifted 5 cm at 0.5 s; ``extra`` is appended to the scene; ``warp=False``:
    linear solves only (no refinement process: quicker)."""
    V, T = box_mesh((8, 2, 2), (1.0, 0.1, 0.1))
    meshio.write(folder / "bar.vtu", meshio.Mesh(V, [("tetra", T)]))
    (folder / name).write_text(BAR_SCENE.format(extra=extra, warp=str(warp).lower()))
    return folder / name


@contextmanager
def editor_page(chromium, url: str, width: int = 1280, height: int = 800, mesh: bool = True):
    """A page of the editor at ``url`` in a fresh browser context (own storage), once it has
    the mesh (``mesh=False``: once it is ready, nothing open); yields (page, errors) where
    errors collects uncaught exceptions of the page."""
    context = chromium.new_context(viewport={"width": width, "height": height})
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(f"{e}: {e.stack}"))
    try:
        # the load event: the page's modules can take more than the default 30 s while the
        # rest of the suite loads both cores
        page.goto(url, timeout=90_000)
        page.wait_for_function("window.wiggly && window.wiggly.ready" +
                               (" && window.wiggly.S.n > 0" if mesh else ""), timeout=LOADED)
        yield page, errors
    except Exception:
        print("status:", page.locator("#status-text").text_content(),
              "| toast:", page.locator("#toast").text_content(), "| errors:", errors)
        raise
    finally:
        context.close()


def wait_final(page, timeout: float = LOADED) -> dict:
    """Wait until the page shows final frames of the current scene version; their meta."""
    page.wait_for_function(
        """() => { const S = window.wiggly.S, m = S.frames && S.frames.meta;
                   return m && S.desc && m.final && m.version === S.desc.version &&
                   m.request === 'final' && m.instance === S.desc.instance; }""",
        timeout=timeout)
    return page.evaluate("window.wiggly.S.frames.meta")


def toast_saying(page, text: str) -> str:
    """Wait until the toast shows with ``text`` in it (a notice that came first is passed
    over); its whole text."""
    page.wait_for_function(
        "(t) => { const e = document.querySelector('#toast'); "
        "return !e.hidden && e.textContent.includes(t); }", arg=text)
    return page.locator("#toast").text_content()


def next_frame(page, n: int = 1) -> None:
    """Let the page draw ``n`` animation frames (pacing real mouse moves)."""
    for _ in range(n):
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")


def get(url: str) -> tuple[bytes, dict]:
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.read(), dict(r.headers)


def latest_final(url: str) -> tuple[np.ndarray, dict]:
    """The server's newest final frames (F, n, 3) and their meta."""
    data, headers = get(url + "api/frames/latest?final=1")
    meta = json.loads(headers["X-Wiggly-Frames"])
    return np.frombuffer(data, "<f4").reshape(meta["n_frames"], meta["n_vertices"], 3), meta


def post(url: str, path: str, body: dict, tab: str | None = None) -> tuple[int, dict]:
    headers = {"Content-Type": "application/json"}
    if tab:
        headers["X-Wiggly-Tab"] = tab
    req = urllib.request.Request(url + path.lstrip("/"), json.dumps(body).encode(), headers)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read() or b"{}")
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read() or b"{}")


def box_select(page, indices, xray: bool = True) -> None:
    """Box-select the given vertices with the Box tool (a real mouse drag); ``xray``: through
    the body (Alt+Z), else only the visible ones."""
    box = page.evaluate("(idx) => window.wiggly.screenBox(idx)", [int(i) for i in indices])
    if page.evaluate("window.wiggly.S.view.xray") != xray:
        page.keyboard.press("Alt+z")
    page.keyboard.press("x")
    pad = 6
    page.mouse.move(box["x0"] - pad, box["y0"] - pad)
    page.mouse.down()
    page.mouse.move((box["x0"] + box["x1"]) / 2, (box["y0"] + box["y1"]) / 2, steps=3)
    page.mouse.move(box["x1"] + pad, box["y1"] + pad, steps=3)
    page.mouse.up()
    page.keyboard.press("q")


def grab_gizmo(page, axis: str) -> tuple[float, float, dict]:
    """Press the mouse on the gizmo's ``axis`` handle (found by hovering along it); returns the
    point and the handle's screen direction."""
    for _attempt in range(3):  # the gizmo picks against matrices updated when it renders
        next_frame(page, 2)
        h = page.evaluate(f"window.wiggly.gizmoHandle('{axis}')")
        for d in range(12, 200, 4):
            x, y = h["x"] + d * h["dx"], h["y"] + d * h["dy"]
            page.mouse.move(x, y)
            if page.evaluate(f"window.wiggly.gizmoHandle('{axis}').axis") == axis:
                page.mouse.down()
                page.wait_for_function("window.wiggly.S.dragging")
                return x, y, h
        page.mouse.move(5, 5)
    raise AssertionError(f"cannot find the gizmo's {axis} handle")


def move_along(page, x: float, y: float, h: dict, pixels: float, steps: int = 10) -> None:
    """Move the pressed mouse ``pixels`` along the direction ``h`` from (x, y), one step per
    drawn frame."""
    for k in range(1, steps + 1):
        page.mouse.move(x + k * pixels / steps * h["dx"], y + k * pixels / steps * h["dy"])
        next_frame(page)


def drag_gizmo(page, axis: str, pixels: float, steps: int = 10) -> None:
    """Drag the gizmo's ``axis`` arrow ``pixels`` along its screen direction and release."""
    x, y, h = grab_gizmo(page, axis)
    move_along(page, x, y, h, pixels, steps)
    page.mouse.up()


def select_key(page, key_id: int) -> None:
    page.click(f"#keys li[data-key='{key_id}']")
    page.wait_for_function(f"window.wiggly.S.selectedKey === {key_id}")


def grab_ring(page, axis: str) -> dict:
    """Press the mouse on the rotate gizmo's ring about ``axis`` (found by hovering along
    it); returns the point."""
    for _attempt in range(3):
        next_frame(page, 2)
        ring = page.evaluate(f"window.wiggly.gizmoRing('{axis}')")
        for p in ring["points"]:
            page.mouse.move(p["x"], p["y"])
            if page.evaluate(f"window.wiggly.gizmoHandle('{axis}').axis") == axis:
                page.mouse.down()
                page.wait_for_function("window.wiggly.S.dragging")
                return p
        page.mouse.move(5, 5)
    raise AssertionError(f"cannot find the gizmo's {axis} ring")


def click_time(page, t: float, group: str | None = None, **kw) -> None:
    """Click the dope sheet at time ``t``: on the ruler, or on ``group``'s row."""
    p = page.evaluate("([t, g]) => window.wiggly.timePoint(t, g ?? undefined)", [t, group])
    page.mouse.click(p["x"], p["y"], **kw)


def first_event(events, wanted, seconds: float = 60.0) -> dict | None:
    """The first event of a bus subscription ``events`` for which ``wanted(event)`` holds,
    within ``seconds`` (None if none came)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            e = events.get(timeout=min(1.0, max(deadline - time.monotonic(), 0.01)))
        except Exception:
            continue
        if wanted(e):
            return e
    return None


def notices(events, quiet: float = 2.0) -> list[str]:
    """The notices' messages of a bus subscription until it stays quiet for ``quiet`` s."""
    said = []
    while True:
        try:
            e = events.get(timeout=quiet)
        except Exception:
            return said
        if e["type"] == "notice":
            said.append(e["message"])
