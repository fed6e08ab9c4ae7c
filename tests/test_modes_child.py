"""The modes' eigensolve in a child process (``wiggly.modes_child``): the same modes as
in-process, a failed factorization reported as in-process, a live line while the child
factorizes, and Ctrl+C or ``kill PID`` end the run at once (cholespy's factorization holds
the interpreter lock: in-process, they waited for it, minutes on large bodies)."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import scipy.sparse as sp

import wiggly.modes as modes
import wiggly.progress as progress
from tests.processes import assert_ended, children_of
from wiggly.fem import mass_matrix, stiffness_matrix
from wiggly.linalg import BACKENDS
from wiggly.modes_child import eigsh_in_child
from wiggly.primitives import box_mesh
from wiggly.progress import Activity


@pytest.fixture(scope="module")
def bar():
    V, T = box_mesh((12, 7, 5), (1.2, 0.7, 0.45))  # unequal sides: no repeated eigenvalues
    return V, stiffness_matrix(V, T, 1e6, 0.45), mass_matrix(V, T, 1000.0)


def test_the_child_finds_the_modes_of_the_process(bar, monkeypatch):
    V, K, M = bar
    monkeypatch.setattr(modes, "DENSE_MAX_DOFS", 0)
    here = modes.compute_modes(K, M, 16, vertices=V, cache_dir=False)
    monkeypatch.setattr(modes, "CHILD_DOFS", 0)
    started = []
    real = subprocess.Popen
    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: started.append(a) or real(*a, **k))
    child = modes.compute_modes(K, M, 16, vertices=V, cache_dir=False)
    assert started and "wiggly.modes_child" in " ".join(started[0][0])
    np.testing.assert_allclose(child.eigenvalues, here.eigenvalues, rtol=1e-12, atol=0)
    np.testing.assert_allclose(child.vectors, here.vectors, rtol=0, atol=1e-10)


class _Report:
    """The callbacks of :func:`wiggly.modes.shift_invert`: the backend named, solves counted."""

    def __init__(self):
        self.backends, self.ticks = [], 0

    def factored(self, name):
        self.backends.append(name)

    def solved(self):
        self.ticks += 1


def test_a_failed_factorization_is_a_linalg_error_as_in_process():
    n = 50
    K, M = -sp.identity(n, format="csr"), sp.identity(n, format="csr")
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        report = _Report()
        eigsh_in_child(K, M, 4, 0.1, "cholespy", report.factored, report.solved)


def test_a_live_line_while_the_child_factorizes_then_its_solves_counted(bar, monkeypatch):
    """On a terminal the factorization gets a live stage line (the parent keeps the lock:
    it ticks), then the child's shift-invert solves are counted."""
    _, K, M = bar
    draws: list[str] = []
    monkeypatch.setattr(progress, "on_terminal", lambda: True)
    monkeypatch.setattr(Activity, "draw", lambda self: draws.append(self.desc))
    report = _Report()
    with progress.reporting(True):
        lam, X = eigsh_in_child(sp.csr_matrix(K), sp.csr_matrix(M), 12, -1.0, None,
                                report.factored, report.solved)
    assert lam.shape == (12,) and X.shape == (K.shape[0], 12)
    assert any("factorizing K - sigma M" in text for text in draws) and report.ticks > 12
    assert len(report.backends) == 1 and report.backends[0] in BACKENDS


PARENT = """
import signal, sys, logging
# a user's terminal: Ctrl+C is Python's KeyboardInterrupt, whatever the test runner's worker
# passed on (an ignored SIGINT is inherited across exec)
signal.signal(signal.SIGINT, signal.default_int_handler)
import numpy as np
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
import wiggly.modes as modes
from wiggly.primitives import box_mesh
from wiggly.fem import stiffness_matrix, mass_matrix
V, T = box_mesh((22, 22, 22), (1.0, 0.9, 0.8))  # 36.5k dofs: a factorization of seconds
K, M = stiffness_matrix(V, T, 1e6, 0.45), mass_matrix(V, T, 1000.0)
print("assembled", flush=True)
modes.compute_modes(K, M, 20, vertices=V, cache_dir=False)
print("finished", flush=True)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_and_kill_end_the_factorization_at_once(signum):
    """The run ends within seconds of the signal, mid-factorization, and leaves no child."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    try:
        for line in parent.stdout:
            if "in a child process" in line:
                break
        else:
            pytest.fail("the factorization did not start in a child: " + parent.stderr.read())
        time.sleep(1.0)  # well inside the factorization (about 10 s on 2 cores)
        children = children_of(parent.pid)
        assert children
        sent = time.monotonic()
        parent.send_signal(signum)
        parent.wait(timeout=30)
        assert time.monotonic() - sent < 3.0
        assert parent.returncode != 0
        assert_ended(children)
        assert "finished" not in parent.stdout.read()
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


WAITER = """
import signal, sys, threading, time
signal.signal(signal.SIGINT, signal.default_int_handler)
from wiggly.child import python_child
other = threading.Thread(target=time.sleep, args=(60,), daemon=True)
other.start()

def interrupt():  # Ctrl+C, caught by a thread that is not the main one
    time.sleep(1.0)
    signal.pthread_kill(other.ident, signal.SIGINT)

threading.Thread(target=interrupt, daemon=True).start()
t0 = time.monotonic()
try:
    with python_child("import time; time.sleep(30)", [], ".") as child:
        for line in child.lines():
            pass
        child.wait()
except KeyboardInterrupt:
    print(f"interrupted after {time.monotonic() - t0:.1f} s", flush=True)
"""


@pytest.mark.skipif(not hasattr(signal, "pthread_kill"), reason="POSIX threads")
def test_ctrl_c_caught_by_another_thread_still_ends_the_wait_for_a_child():
    """A signal to a process lands on any of its threads; one caught by a thread other than
    the main one, while the main thread waits for a child's output, ends the wait within
    a second (it waited for the child's next line: 18 s once, mid-factorization)."""
    done = subprocess.run([sys.executable, "-c", WAITER], capture_output=True, text=True,
                          timeout=60)
    said = re.search(r"interrupted after ([\d.]+) s", done.stdout)
    assert said, done.stdout + done.stderr
    assert float(said.group(1)) < 2.5
