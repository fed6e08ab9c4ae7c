"""fTetWild in a child process, so that its progress can be shown while it runs, and so that
a crash of fTetWild (it segfaults on some surfaces, e.g. long thin rods) ends only the child.

pytetwild holds the interpreter lock for its whole call (1-120 s on the surfaces users
bring), so no thread of the calling process runs meanwhile: a live stage line would freeze
at its first second and look hung.  Where stages are reported (:func:`wiggly.progress.
activity`: a live line on a terminal, or the log), :func:`tetrahedralize_in_child` runs the
same call in a child Python process instead: the parent's line ticks, and fTetWild's own log
(its stdout, line by line) names the stage and the optimization's pass (:class:`Log`), on the
line or in the log every :data:`wiggly.progress.NOTE_EVERY` seconds.  The child works in a
private temporary directory, where fTetWild also writes its debug file.  The answer is the
one the same call gives in-process; fTetWild is randomized either way.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from wiggly.child import python_child
from wiggly.progress import Activity, log

__all__ = ["Log", "MesherCrash", "tetrahedralize_in_child"]


class MesherCrash(RuntimeError):
    """fTetWild's child process was ended by a signal (``signal``: 11 for a segmentation
    fault, 6 for an abort), not by an error Python could report."""

    def __init__(self, message: str, signal: int) -> None:
        super().__init__(message)
        self.signal = signal


class Log:
    """Reads fTetWild's log lines into the stage line's note: which stage runs, and during
    the optimization its pass and its worst tet's energy (conformal AMIPS; a regular tet has
    3).  On a messy surface the passes, about a second each on 14k tets, are where the
    minutes go."""

    def __init__(self, line: Activity, passes: int, stop_energy: float) -> None:
        self.line, self.passes, self.stop_energy = line, passes, stop_energy
        self.energy: float | None = None
        self.k: int | None = None  # the optimization's pass, from 1

    def __call__(self, text: str) -> None:
        if text.startswith("Tetrahedralization performed"):
            self.line.note("inserting the surface")
        elif text.startswith("max_energy = "):
            try:
                self.energy = float(text.split("=")[1])
            except ValueError:
                log.debug("unexpected fTetWild line %r", text)
            self._passes()
        elif text.startswith("////") and " pass " in text:
            k = text.split("pass")[1].strip(" /")
            if k.isdigit():
                self.k = int(k) + 1
                self._passes()
        elif "postprocessing" in text:
            self.k = None
            self.line.note("finishing")

    def _passes(self) -> None:
        """The note during the optimization: its pass and the worst tet's energy now."""
        if self.k is None:
            return
        worst = "" if self.energy is None else f", worst {self.energy:.3g}".replace("e+", "e")
        self.line.note(f"shaping tets {self.k}/{self.passes}{worst} (stop < "
                       f"{self.stop_energy:g})")


def tetrahedralize_in_child(V: np.ndarray, F: np.ndarray, options: dict,
                            on_line: Callable[[str], None]) -> tuple[np.ndarray, np.ndarray]:
    """``pytetwild.tetrahedralize(V, F, **options)`` in a child process, its log lines handed
    to ``on_line`` as they come.  Ctrl+C (or any exception here) ends the child.  A crash of
    fTetWild (a signal) is :class:`MesherCrash`; any other failure a ``RuntimeError``."""
    with tempfile.TemporaryDirectory(prefix="wiggly-ftetwild-") as tmp:
        inp, out = Path(tmp, "surface.npz"), Path(tmp, "tets.npz")
        np.savez(inp, vertices=np.ascontiguousarray(V, np.float64),
                 faces=np.ascontiguousarray(F, np.int32), **{
                     k: np.asarray(v) for k, v in options.items()})
        with python_child(_CHILD, [str(inp), str(out), str(os.getpid())], tmp) as child:
            for text in child.lines():
                on_line(text)
            code = child.wait()
        if code < 0:
            raise MesherCrash(f"fTetWild's process was ended by signal {-code}: "
                              + child.error_tail(), -code)
        if code != 0 or not out.exists():
            raise RuntimeError(f"fTetWild's process ended with code {code}: "
                               + child.error_tail())
        with np.load(out) as data:
            return data["vertices"], data["tets"]


# The child's program: numpy and pytetwild only (importing wiggly would double its start-up).
# C stdio's stdout is made line-buffered before any output (glibc's and macOS's symbols;
# elsewhere the lines come in bursts), so that the parent sees each line as it is written.
_CHILD = """
import ctypes, os, signal, sys
try:
    libc = ctypes.CDLL(None)
    if sys.platform.startswith("linux"):  # killed with the parent, however it ends
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() != int(sys.argv[3]):
            sys.exit(1)
    for symbol in ("stdout", "__stdoutp"):
        try:
            libc.setvbuf(ctypes.c_void_p.in_dll(libc, symbol), None, 1, 0)
            break
        except ValueError:
            pass  # not this C library's name for stdout: try the next
except (OSError, AttributeError):
    pass  # no C library to tune: the lines come in bursts
import numpy as np
import pytetwild
inp, out = sys.argv[1:3]
with np.load(inp) as data:
    V, F = data["vertices"], data["faces"]
    options = {k: data[k].item() for k in data.files if k not in ("vertices", "faces")}
tv, tt = pytetwild.tetrahedralize(V, F, quiet=False, loglevel=6, **options)
sys.stdout.flush()
with open(out + ".part", "wb") as f:
    np.savez(f, vertices=np.asarray(tv), tets=np.asarray(tt))
os.replace(out + ".part", out)
"""
