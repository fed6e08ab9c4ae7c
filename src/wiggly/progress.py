"""Progress feedback on stderr for anything that takes more than a second."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext

from tqdm import tqdm


@contextmanager
def _ticking(desc: str) -> Iterator[None]:
    bar = tqdm(total=None, desc=f"[wiggly] {desc}", file=sys.stderr,
               bar_format="{desc}: {elapsed} elapsed",
               leave=True)
    stop = threading.Event()

    def tick() -> None:
        while not stop.wait(0.25):
            bar.refresh()

    thread = threading.Thread(target=tick, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()
        bar.close()


def activity(desc: str, enabled: bool = True):
    """A live elapsed-time line while a blocking call (e.g. fTetWild) runs."""
    return _ticking(desc) if enabled else nullcontext()


def iterations(desc: str, enabled: bool = True) -> tqdm:
    """A counter of solver iterations (``bar.update(1)``, ``bar.set_postfix_str(...)``),
    with no total: the iteration budget is no estimate of the iterations a solve takes."""
    return tqdm(total=None, desc=desc, file=sys.stderr, disable=not enabled, leave=False,
                unit="it")
