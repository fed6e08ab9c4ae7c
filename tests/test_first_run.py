"""A first run never looks hung: compiling the warp kernels is announced before it starts, a
batch compiles once in its own process before any worker starts, and a log holds one line
per stage instead of a progress bar's updates."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import tomli_w

from tests.test_batch import SCENE  # the bundled bar, its tip pulled up: a warped shot
from wiggly.cli import main
from wiggly.warp import compiled, kernels

needs_numba = pytest.mark.skipif(not compiled.AVAILABLE, reason="numba is not installed")

def write_scene(folder: Path) -> Path:
    path = folder / "shot.toml"
    path.write_text(tomli_w.dumps(SCENE))
    return path


@needs_numba
def test_an_empty_numba_cache_is_cold_and_a_filled_one_is_not(tmp_path):
    kernels.compile_all()  # loads (or compiles) into this process's cache directory
    assert not kernels.cache_is_cold()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty")}
    probe = "from wiggly.warp.kernels import cache_is_cold; print(cache_is_cold())"
    done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"


@needs_numba
def test_compiling_is_announced_before_it_starts(monkeypatch, caplog):
    events: list[str] = []
    monkeypatch.setattr(kernels, "_ready", False)
    monkeypatch.setattr(kernels, "cache_is_cold", lambda: True)
    monkeypatch.setattr(kernels, "compile_all", lambda: events.append("compiled"))
    monkeypatch.setattr("wiggly.progress.on_terminal", lambda: False)
    with caplog.at_level(logging.INFO, logger="wiggly"):
        logging.getLogger("wiggly").addHandler(_Recorder(events))
        try:
            said = [kernels.ensure_compiled(), kernels.ensure_compiled()]  # once per process
        finally:
            logging.getLogger("wiggly").handlers.pop()
    assert events == [kernels.COMPILING, "compiled"]
    assert said == [True, False]  # the summary says "compiling" for the first only
    assert kernels.COMPILING.startswith("compiling the warp kernels, once after an install: "
                                        "about a minute")


@needs_numba
def test_a_warm_cache_compiles_silently(monkeypatch, caplog):
    monkeypatch.setattr(kernels, "_ready", False)
    monkeypatch.setattr(kernels, "cache_is_cold", lambda: False)
    with caplog.at_level(logging.DEBUG, logger="wiggly"):
        loaded = kernels.ensure_compiled()
    assert caplog.records == []
    assert loaded is False  # loaded from the cache: the summary says "loading", not "compiling"


@needs_numba
def test_a_batch_compiles_before_starting_its_workers(tmp_path, monkeypatch, capsys):
    import wiggly.batch.driver as driver

    events: list[str] = []
    monkeypatch.setattr(kernels, "ensure_compiled", lambda: events.append(
        "compiled"))

    class Pool(driver.LocalPool):
        def __init__(self, *args, **kw) -> None:
            events.append("workers")
            super().__init__(*args, **kw)

    monkeypatch.setattr(driver, "LocalPool", Pool)
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path / "cache"))
    code = main(["batch", str(write_scene(tmp_path)), "-o", str(tmp_path / "out"), "-j", "1",
                 "--no-sheet", "-q"])
    assert code == 0, capsys.readouterr()
    assert events == ["compiled", "workers"]


def test_a_log_has_one_line_per_stage(tmp_path, capsys):
    """``wiggly animate`` piped to a file: stage lines, no carriage returns; ``-q``: none."""
    scene = write_scene(tmp_path)
    assert main(["animate", str(scene)]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    newton = [line for line in err.splitlines() if line.startswith("[wiggly] warped solve (")]
    assert len(newton) == 1 and " it" in newton[0], err
    assert main(["animate", str(scene), "--overwrite", "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_verbose_and_quiet_choose_the_level(tmp_path, capsys):
    scene = write_scene(tmp_path)
    logger = logging.getLogger("wiggly")
    seen: list[int] = []

    class Probe(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(logger.getEffectiveLevel())

    probe = Probe()
    logger.addHandler(probe)
    try:
        for flags, level in ([], logging.INFO), (["-v"], logging.DEBUG), (["-q"], logging.WARNING):
            seen.clear()
            assert main(["animate", str(scene), "--overwrite", "--linear", *flags]) == 0
            capsys.readouterr()
            if level < logging.WARNING:
                assert seen and set(seen) == {level}
            else:
                assert seen == []  # nothing below a warning is emitted
    finally:
        logger.removeHandler(probe)
    assert logger.level == logging.NOTSET and not any(
        type(h).__name__ == "_Stderr" for h in logger.handlers)  # the CLI leaves no trace


class _Recorder(logging.Handler):
    def __init__(self, events: list[str]) -> None:
        super().__init__()
        self.events = events

    def emit(self, record: logging.LogRecord) -> None:
        self.events.append(record.getMessage())


@pytest.mark.skipif(sys.platform == "win32", reason="needs a POSIX pseudo-terminal")
def test_bars_show_on_a_terminal_that_reports_zero_columns():
    """A pseudo-terminal whose size was never set reports 0 x 0 (some container and CI
    runners); tqdm then drew empty lines, and a run looked hung.  The bars fall back to 80 x
    24 there."""
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 0, 0, 0, 0))
    code = ("from wiggly.progress import frames, reporting\n"
            "with reporting(True):\n"
            "    for _ in frames(range(3), 3, '[wiggly] writing frames'):\n"
            "        pass\n")
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    try:
        done = subprocess.run([sys.executable, "-c", code], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=slave, env=env, timeout=120)
    finally:
        os.close(slave)
    chunks = []
    while True:
        try:
            chunk = os.read(master, 4096)
        except OSError:  # EIO: the terminal's other end is closed and drained
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(master)
    text = b"".join(chunks).decode(errors="replace")
    assert done.returncode == 0, text
    assert "[wiggly] writing frames" in text and "3/3" in text, repr(text)
