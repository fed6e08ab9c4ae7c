"""fTetWild's progress: its stage line keeps ticking and names the optimization's pass.

pytetwild holds the interpreter lock for its whole call, so on a terminal fTetWild runs in
a child process (``wiggly.mesh.tetwild_child``) and the parent draws the line meanwhile.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh

import wiggly.progress as progress
from tests.processes import assert_ended, children_of
from wiggly.mesh import Surface, tetrahedralize
from wiggly.mesh.tetwild_child import Log, tetrahedralize_in_child
from wiggly.progress import Activity


def sphere() -> tuple[np.ndarray, np.ndarray]:
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    return np.asarray(s.vertices), np.asarray(s.faces)


def tet_volume(V: np.ndarray, T: np.ndarray) -> float:
    e = V[T[:, 1:]] - V[T[:, :1]]
    return float(np.abs(np.linalg.det(e)).sum() / 6)


def test_the_log_names_the_stage_and_the_pass():
    line = Activity()
    notes = []
    line.note = notes.append
    log = Log(line, 80, 10.0)
    for text in ["Loading mesh...", "Tetrahedralization performed.", "max_energy = 292870",
                 "//////////////// pass 0 ////////////////", "max_energy = 21.6238",
                 "//////////////// pass 11 ////////////////", "max_energy = oops",
                 "//////////////// postprocessing ////////////////"]:
        log(text)
    assert notes == ["inserting the surface", "shaping tets 1/80, worst 2.93e05 (stop < 10)",
                     "shaping tets 1/80, worst 21.6 (stop < 10)",  # the worst tet now
                     "shaping tets 12/80, worst 21.6 (stop < 10)",
                     "shaping tets 12/80, worst 21.6 (stop < 10)", "finishing"]


def test_the_child_gives_the_tets_and_its_log():
    V, F = sphere()
    lines = []
    tv, tt = tetrahedralize_in_child(V, F, {"edge_length_abs": 0.08, "epsilon": 1e-3}, lines.append)
    tt = np.asarray(tt).reshape(-1, 4)
    assert len(tt) > 500
    # the solid it fills is the ball (the icosphere's volume, within fTetWild's envelope)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5).volume
    assert abs(tet_volume(np.asarray(tv), tt) - ball) < 0.01 * ball
    assert any(line.startswith("//////////////// pass 0") for line in lines)
    assert any(line.startswith("max_energy = ") for line in lines)


def test_a_failing_child_is_an_error_not_a_hang():
    V, F = sphere()
    with pytest.raises(RuntimeError, match="fTetWild's process ended with code"):
        tetrahedralize_in_child(V, F, {"no_such_option": 1.0}, lambda _: None)


PARENT = """
import sys, os, numpy as np, trimesh
from wiggly.mesh.tetwild_child import tetrahedralize_in_child
s = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
def line(text):
    if not os.path.exists(sys.argv[1]):
        with open(sys.argv[1], "w") as f:
            f.write(str(os.getpid()))
tetrahedralize_in_child(np.asarray(s.vertices), np.asarray(s.faces),
                        {"edge_length_abs": 0.01, "epsilon": 1e-3}, line)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGKILL])
def test_the_child_ends_with_its_parent(tmp_path, signum):
    """A parent ended by SIGTERM (kill PID) or SIGKILL leaves no fTetWild process running;
    SIGTERM also removes the temporary folder."""
    started = tmp_path / "started"
    private = tmp_path / "tmp"  # its own temporary folder: other tests' fTetWild runs beside
    private.mkdir()
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(started)],
                              env={**os.environ, "TMPDIR": str(private)})
    try:
        deadline = time.monotonic() + 60
        while not started.exists() and time.monotonic() < deadline and parent.poll() is None:
            time.sleep(0.05)
        assert started.exists(), "fTetWild's child never wrote a line"
        children = children_of(parent.pid)
        assert children
        parent.send_signal(signum)
        parent.wait(timeout=30)
        assert_ended(children)
        if signum == signal.SIGTERM:
            assert not list(private.glob("wiggly-ftetwild-*"))
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def test_the_stage_line_ticks_while_ftetwild_runs(monkeypatch):
    """On a terminal the line is redrawn every quarter second through the whole call and
    shows the pass; in-process (the lock held) it was drawn only before and after."""
    draws: list[tuple[float, str]] = []

    def draw(self):
        draws.append((time.perf_counter(), self.text))

    monkeypatch.setattr(progress, "on_terminal", lambda: True)
    monkeypatch.setattr(Activity, "draw", draw)
    V, F = sphere()
    t0 = time.perf_counter()
    with progress.reporting(True):
        mesh = tetrahedralize(Surface(V, F), resolution=30, cache_dir=False)
    t1 = time.perf_counter()
    assert mesh.n_tets > 1000
    stamps = np.array([t0] + [t for t, _ in draws if t0 <= t <= t1] + [t1])
    # never long without a redraw (in-process, the whole fTetWild call went without one)
    assert t1 - t0 > 1.0 and np.diff(stamps).max() < max(1.0, 0.5 * (t1 - t0))
    assert any(text.startswith("shaping tets ") for _, text in draws)


def test_off_a_terminal_the_log_gets_the_passes_now_and_then(monkeypatch, caplog):
    """Piped (a log, the Blender add-on's status), fTetWild's stage goes to the log every
    NOTE_EVERY seconds while it runs, not only once before it starts."""
    monkeypatch.setattr(progress, "on_terminal", lambda: False)
    monkeypatch.setattr(progress, "NOTE_EVERY", 0.2)
    V, F = sphere()
    with progress.reporting(True), caplog.at_level("INFO", logger="wiggly"):
        tetrahedralize(Surface(V, F), resolution=30, cache_dir=False)
    lines = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("tetrahedralizing surface (fTetWild:") and "tets)" in m[-6:]
               for m in lines), lines
    passes = [m for m in lines if ": shaping tets " in m]
    assert passes and all(m.startswith("tetrahedralizing surface") and m.endswith(" s)")
                          for m in passes), lines


@pytest.mark.parametrize("width", [100, 80, 72, 60, 50, 44])
def test_the_line_fits_the_terminal_and_cuts_the_note_after_a_word(width):
    """The stage line fits the terminal: the description shortens first, then the note ends
    after a whole word with "...", never inside one."""
    desc = "[wiggly] tetrahedralizing a_long_model_name.glb (fTetWild, resolution 49)"
    note = "shaping tets 38/80, worst 18.9 (stop < 10)"
    line = progress.fit_line(desc, "01:12", note, width - 1)
    assert len(line) <= width - 1, line
    shown = line.split(": 01:12", 1)[1].removeprefix(", ")
    if shown.endswith("..."):
        kept = shown[:-3]
        assert note.startswith(kept) and note[len(kept)] in " ,", (kept, note)
    else:
        assert shown == note
    assert line.startswith(desc[:progress.MIN_DESC - 3])


def test_off_a_terminal_long_loops_log_their_count_now_and_then(monkeypatch, caplog):
    """Piped, a solver's iteration counter and a loop over frames log how far they are every
    NOTE_EVERY seconds while they run (a long warped solve in a log does not look hung),
    then one closing line."""
    monkeypatch.setattr(progress, "on_terminal", lambda: False)
    monkeypatch.setattr(progress, "NOTE_EVERY", 0.05)
    with progress.reporting(True), caplog.at_level("INFO", logger="wiggly"):
        with progress.iterations("warped solve (Newton)") as bar:
            for k in range(4):
                time.sleep(0.06)
                bar.update(1)
                bar.set_postfix_str(f"objective {k}")
        for _ in progress.frames(range(3), 3, "rendering"):
            time.sleep(0.06)
    lines = [r.getMessage() for r in caplog.records]
    during = [m for m in lines if m.startswith("warped solve (Newton): ") and "so far" in m]
    assert len(during) >= 3 and during[0].startswith("warped solve (Newton): 1 it so far"), lines
    assert any(m.startswith("warped solve (Newton): 4 it, objective 3 (") for m in lines), lines
    assert any(m.startswith("rendering: 1 frame so far") for m in lines), lines
    assert lines[-1].startswith("rendering: 3 frames ("), lines


def test_a_silent_stage_in_a_log_still_says_it_runs(monkeypatch, caplog):
    """Off a terminal a stage whose call gives no note (fTetWild was silent for two minutes
    while filling a fine plate) is said to run every NOTE_EVERY seconds, with its time."""
    import time

    monkeypatch.setattr(progress, "on_terminal", lambda: False)
    monkeypatch.setattr(progress, "NOTE_EVERY", 0.2)
    with progress.reporting(True), caplog.at_level("INFO", logger="wiggly"):
        with progress.activity("tetrahedralizing plate.obj"):
            time.sleep(0.75)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "tetrahedralizing plate.obj"
    beats = [m for m in lines[1:] if m.startswith("tetrahedralizing plate.obj: still running (")]
    assert 2 <= len(beats) <= 4 and len(beats) == len(lines) - 1, lines


def test_a_library_call_notes_its_step_on_the_activity_around_it(monkeypatch, caplog):
    """progress.note speaks on the innermost activity a caller opened (a secondary motion's
    Gauss-Newton iterations ran silent for 10 s inside "secondary motion on ..."), and says
    nothing outside one or once it has ended."""
    import time

    monkeypatch.setattr(progress, "on_terminal", lambda: False)
    monkeypatch.setattr(progress, "NOTE_EVERY", 0.1)
    with progress.reporting(True), caplog.at_level("INFO", logger="wiggly"):
        progress.note("before")
        with progress.activity("secondary motion on walk.glb"):
            time.sleep(0.15)
            progress.note("warped keys: Gauss-Newton iteration 3")
            time.sleep(0.3)
        progress.note("after")
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "secondary motion on walk.glb", lines
    assert any(m.startswith("secondary motion on walk.glb: warped keys: Gauss-Newton "
                            "iteration 3 (") for m in lines), lines
    assert not any("before" in m or "after" in m for m in lines), lines


# --------------------------------------------------------------------------- crashes


def test_a_signal_in_the_child_is_a_crash(monkeypatch):
    """fTetWild's segfault ends only the child, and is told apart from other failures."""
    from wiggly.mesh import tetwild_child

    monkeypatch.setattr(tetwild_child, "_CHILD",
                        "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)")
    V, F = sphere()
    with pytest.raises(tetwild_child.MesherCrash, match="signal 11") as crash:
        tetrahedralize_in_child(V, F, {"edge_length_abs": 0.08}, lambda _: None)
    assert crash.value.signal == 11


def test_a_crash_is_retried_with_the_tightest_envelope_then_refused(monkeypatch, caplog):
    """A crash is retried once with the smallest envelope (with a note in the log); a second
    crash is a refusal that names the file, the crash and what to try."""
    from wiggly.errors import WigglyInputError
    from wiggly.mesh import filling, tetwild_child

    real = tetwild_child.tetrahedralize_in_child
    envelopes = []

    def crashing_once(V, F, options, on_line):
        envelopes.append(options["epsilon"])
        if len(envelopes) == 1:
            raise tetwild_child.MesherCrash("ended by signal 11", 11)
        return real(V, F, options, on_line)

    monkeypatch.setattr(tetwild_child, "tetrahedralize_in_child", crashing_once)
    V, F = sphere()
    with caplog.at_level("INFO", logger="wiggly"):
        mesh = tetrahedralize(Surface(V, F), resolution=12, source="ball.obj", cache_dir=False)
    assert envelopes[0] > filling.MIN_ENVELOPE and envelopes[1] == filling.MIN_ENVELOPE
    assert any("fTetWild crashed (signal 11)" in r.getMessage() for r in caplog.records)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5).volume
    assert abs(mesh.volumes().sum() - ball) < 0.03 * ball

    def crashing(V, F, options, on_line):
        raise tetwild_child.MesherCrash("ended by signal 11", 11)

    monkeypatch.setattr(tetwild_child, "tetrahedralize_in_child", crashing)
    with pytest.raises(WigglyInputError, match=r"^ball\.obj: the tetrahedralizer \(fTetWild\) "
                       r"crashed .* try another resolution or edge_length .* bring the tet "
                       r"mesh \(\.msh, \.vtu\)\.$"):
        tetrahedralize(Surface(V, F), resolution=12, source="ball.obj", cache_dir=False)


def test_a_fill_that_lost_the_body_is_retried_with_the_tightest_envelope(monkeypatch, caplog):
    """fTetWild giving no tets (a thin rod it did not crash on) is retried like a crash."""
    from wiggly.mesh import filling, tetwild_child

    real = tetwild_child.tetrahedralize_in_child
    envelopes = []

    def empty_once(V, F, options, on_line):
        envelopes.append(options["epsilon"])
        if len(envelopes) == 1:
            return np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int32)
        return real(V, F, options, on_line)

    monkeypatch.setattr(tetwild_child, "tetrahedralize_in_child", empty_once)
    V, F = sphere()
    with caplog.at_level("INFO", logger="wiggly"):
        mesh = tetrahedralize(Surface(V, F), resolution=12, cache_dir=False)
    assert envelopes == [pytest.approx(0.1 / 12), filling.MIN_ENVELOPE]
    assert any("fTetWild filled 0 % of the surface's volume" in r.getMessage()
               for r in caplog.records)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5).volume
    assert abs(mesh.volumes().sum() - ball) < 0.03 * ball


ROD = """
import sys, numpy as np, trimesh
from wiggly.mesh import Surface, tetrahedralize
rod = trimesh.creation.cylinder(float(sys.argv[1]), 2.0, sections=12)
mesh = tetrahedralize(Surface(np.asarray(rod.vertices), np.asarray(rod.faces)),
                      resolution=int(sys.argv[2]), cache_dir=False)
print(mesh.volumes().sum() / rod.volume)
"""


@pytest.mark.parametrize("radius", [0.0025, 0.01])
def test_a_long_thin_rod_is_meshed_not_a_crash(radius):
    """fTetWild segfaulted on a 2 m rod of 5 mm and 20 mm diameter at resolution 12 (with no
    progress line it ran in-process and took its host down), or gave 0-2 tets for the 20 mm
    one: now the crash ends a child and the retry with the tightest envelope meshes the rod
    (67-98 % of its volume: thinner than the tets, it loses some)."""
    done = subprocess.run([sys.executable, "-c", ROD, str(radius), "12"], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert 0.5 < float(done.stdout.split()[-1]) < 1.05
