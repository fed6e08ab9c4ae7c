"""The modes' shift-invert eigensolve in a child process, so that it can be stopped and its
progress shown while it runs.

The sparse Cholesky factorization of ``K - sigma M`` holds the interpreter lock for its whole
call (cholespy's: 100 s on 85k dofs, minutes beyond), so neither a signal handler nor a
progress thread of the calling process runs meanwhile: Ctrl+C and ``kill PID`` would wait for
it, and a live stage line would freeze.  From :data:`wiggly.modes.CHILD_DOFS` free dofs on,
:func:`eigsh_in_child` runs the same solve (:func:`wiggly.modes.shift_invert`) in a child
Python process instead: the parent's line ticks while the child factorizes, the shift-invert
solves are counted as the child reports them, and Ctrl+C or SIGTERM end the child at once.
The answer is the one the same call gives in-process.
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from wiggly.child import python_child
from wiggly.progress import activity

__all__ = ["child_main", "eigsh_in_child"]

#: The child reports its shift-invert solves in steps of this many.
SOLVES_EVERY = 5


def eigsh_in_child(Kf: sp.csr_matrix, Mf: sp.csr_matrix, k: int, sigma: float,
                   backend: str | None, factored: Callable[[str], None],
                   solved: Callable[[], None]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`wiggly.modes.shift_invert` with the same arguments, in a child process: a live
    line while the child factorizes, then ``factored(backend name)`` and ``solved()`` for
    each solve as the child reports them.  A failed factorization raises
    ``np.linalg.LinAlgError`` as in-process; Ctrl+C, SIGTERM or any exception here ends the
    child."""
    nf = Kf.shape[0]
    with tempfile.TemporaryDirectory(prefix="wiggly-modes-") as tmp:
        inp, out = Path(tmp, "problem.npz"), Path(tmp, "modes.npz")
        np.savez(inp, K_data=Kf.data, K_indices=Kf.indices, K_indptr=Kf.indptr,
                 M_data=Mf.data, M_indices=Mf.indices, M_indptr=Mf.indptr,
                 n=nf, k=k, sigma=sigma, backend=backend or "")
        failure = None
        with python_child("from wiggly.modes_child import child_main; child_main()",
                          [str(inp), str(out), str(os.getpid())], tmp) as child:
            lines = (text.strip() for text in child.lines())
            text = ""
            with activity(f"factorizing K - sigma M for the modes ({nf} dofs; minutes from "
                          "about 100k)"):
                for text in lines:
                    if text.startswith(("factorized ", "error ")):
                        break
            if text.startswith("error "):
                failure = text[len("error "):]
            elif text.startswith("factorized "):
                factored(text.split()[1])
                solves = 0
                for text in lines:
                    if text.startswith("solves "):
                        done = int(text.split()[1])
                        for _ in range(done - solves):
                            solved()
                        solves = done
            code = child.wait()
        if failure is not None:
            raise np.linalg.LinAlgError(failure)
        if code != 0 or not out.exists():
            raise RuntimeError(f"the modes' eigensolve process ended with code {code}: "
                               + child.error_tail())
        with np.load(out) as data:
            return data["lam"], data["X"]


def child_main() -> None:  # pragma: no cover - runs in the child (tested end to end)
    """The child: ``python -c "..." problem.npz modes.npz PARENT_PID``."""
    import signal

    inp, out, parent = sys.argv[1], sys.argv[2], int(sys.argv[3])
    if sys.platform.startswith("linux"):  # killed with the parent, however it ends
        try:
            import ctypes

            ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass  # no C library to ask: the parent's kill on exit remains
        if os.getppid() != parent:
            sys.exit(1)
    from wiggly.modes import shift_invert

    with np.load(inp) as d:
        n = int(d["n"])
        Kf = sp.csr_matrix((d["K_data"], d["K_indices"], d["K_indptr"]), shape=(n, n))
        Mf = sp.csr_matrix((d["M_data"], d["M_indices"], d["M_indptr"]), shape=(n, n))
        k, sigma, backend = int(d["k"]), float(d["sigma"]), str(d["backend"]) or None
    count = 0

    def solved() -> None:
        nonlocal count
        count += 1
        if count % SOLVES_EVERY == 0:
            print(f"solves {count}", flush=True)

    try:
        lam, X = shift_invert(Kf, Mf, k, sigma, backend,
                              lambda name: print(f"factorized {name}", flush=True), solved)
    except np.linalg.LinAlgError as err:
        print(f"error {err}", flush=True)
        sys.exit(3)
    print(f"solves {count}", flush=True)
    with open(out + ".part", "wb") as f:
        np.savez(f, lam=lam, X=X)
    os.replace(out + ".part", out)
