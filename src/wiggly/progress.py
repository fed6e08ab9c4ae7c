"""Progress for anything that takes more than a second: a live bar on a terminal, one line per
stage in a log.

Library modules print nothing themselves: they report through the ``wiggly`` logger
(:mod:`logging`), whose INFO lines the command line shows (``-v`` adds DEBUG, ``-q`` keeps
warnings and errors only); a program that imports wiggly sees them only if it configures
logging.  No library function takes a ``progress`` flag: stages are reported when
:func:`shown` is true, that is when the ``wiggly`` logger is enabled for INFO, or as a
:func:`reporting` block says (the command line, the editor and a batch's workers use it to
switch reporting on or off whatever the logger's level).  The bars (tqdm) of the functions
below are drawn only when stages are reported *and* stderr is a terminal; otherwise each stage
is one INFO line on the logger, so a log holds no carriage-return updates.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TypeVar

from tqdm import tqdm

from wiggly.errors import counted, warn

__all__ = [
    "Activity", "Counter", "activity", "bar", "deprecated_progress", "frames", "iterations", "log",
    "note", "on_terminal", "reporting", "say", "shown",
]

#: The library's logger; modules log on ``logging.getLogger(__name__)`` beneath it.
log = logging.getLogger("wiggly")

# None: as the logger's level says; True/False: inside ``reporting(True/False)`` (per thread
# and per asyncio task: a thread starts with None)
_reporting: ContextVar[bool | None] = ContextVar("wiggly_reporting", default=None)

# the innermost running activity (per thread and task), which :func:`note` speaks on
_activity: ContextVar[Activity | None] = ContextVar("wiggly_activity", default=None)

F = TypeVar("F", bound=Callable)


def shown() -> bool:
    """Whether stages are reported here and now: as the innermost :func:`reporting` block
    says, else when the ``wiggly`` logger is enabled for INFO."""
    on = _reporting.get()
    return log.isEnabledFor(logging.INFO) if on is None else on


@contextmanager
def reporting(on: bool = True) -> Iterator[None]:
    """Report stages (bars on a terminal, INFO lines otherwise) inside the block, or with
    ``on=False`` report none, whatever the ``wiggly`` logger's level.  It holds for the
    current thread: a thread the block starts reports as the logger's level says.

    A stage line still reaches a log only if the logger is enabled for INFO; ``reporting``
    decides whether it is said, and whether bars are drawn."""
    token = _reporting.set(bool(on))
    try:
        yield
    finally:
        _reporting.reset(token)


def deprecated_progress(function: F) -> F:
    """Accept the retired ``progress=`` keyword of a public function with a
    :class:`DeprecationWarning`: ``progress=True`` (or False) runs the call inside
    ``reporting(True)`` (or False), as the flag once did."""

    @functools.wraps(function)
    def accepting(*args, **kwargs):
        if "progress" not in kwargs:
            return function(*args, **kwargs)
        on = kwargs.pop("progress")
        warn(
            f"{function.__module__}.{function.__qualname__}(progress=...) is deprecated: "
            "stages are reported when the 'wiggly' logger is enabled for INFO, or inside "
            "wiggly.progress.reporting(True)", DeprecationWarning)
        with reporting(bool(on)):
            return function(*args, **kwargs)

    return accepting  # type: ignore[return-value]


def on_terminal() -> bool:
    """Whether stderr is an interactive terminal (where live bars belong)."""
    stream = sys.stderr
    try:
        return stream is not None and stream.isatty()
    except (AttributeError, ValueError):  # replaced or closed stream
        return False


def _stderr_columns() -> int | None:
    """The width of the terminal on stderr (0 for a pseudo-terminal whose size was never set),
    or None when stderr is no terminal."""
    try:
        return os.get_terminal_size(sys.stderr.fileno()).columns
    except (AttributeError, ValueError, OSError):
        return None


def bar(**options) -> tqdm:
    """A tqdm bar on stderr.  A terminal that reports 0 columns (a pseudo-terminal whose size
    was never set, as some container and CI runners give) would get empty lines from tqdm:
    there the bar takes ``$COLUMNS`` x ``$LINES``, or 80 x 24."""
    columns = _stderr_columns()
    if columns == 0:
        size = shutil.get_terminal_size()  # $COLUMNS and $LINES, or 80 x 24
        options.update(ncols=size.columns, nrows=size.lines, dynamic_ncols=False)
    return tqdm(file=sys.stderr, **options)


def say(message: str, enabled: bool = True, logger: logging.Logger = log) -> None:
    """One INFO line of a stage, when stages are :func:`shown` (and ``enabled``: a further
    condition of the caller, e.g. only for a large sweep)."""
    if enabled and shown():
        logger.info(message)


#: Off a terminal, an activity's notes reach the log at most this often (s).
NOTE_EVERY = 10.0


class Activity:
    """The handle :func:`activity` gives: ``live`` when a line is drawn on a terminal,
    ``logged`` when stages go to the log instead, and :meth:`note` to say what the blocking
    call is doing now (e.g. fTetWild's pass): on the live line, or in the log at most every
    :data:`NOTE_EVERY` seconds."""

    def __init__(self, desc: str = "", line: tqdm | None = None, logged: bool = False) -> None:
        self.desc, self.line, self.text, self.logged = desc, line, "", logged
        self.t0 = self.said = time.perf_counter()

    @property
    def live(self) -> bool:
        return self.line is not None

    def note(self, text: str) -> None:
        self.text = text  # the ticker draws it
        now = time.perf_counter()
        if self.logged and text and now - self.said >= NOTE_EVERY:
            self.said = now
            log.info(f"{self.desc}: {text} ({now - self.t0:.0f} s)")

    def draw(self) -> None:
        """Redraw the line: the description, the elapsed time and the note, fitted to the
        terminal's width (:func:`fit_line`)."""
        if self.line is None:
            return
        elapsed = tqdm.format_interval(time.perf_counter() - self.t0)
        width = _stderr_columns() or shutil.get_terminal_size().columns  # as bar() does
        self.line.set_description_str(fit_line(self.desc, elapsed, self.text, width - 1),
                                      refresh=True)


#: A shortened description keeps at least this many characters.
MIN_DESC = 20


def fit_line(desc: str, elapsed: str, note: str, room: int) -> str:
    """``desc: elapsed, note`` (``desc: elapsed elapsed`` without a note) in at most ``room``
    characters where it can be: the description is shortened first (to ``MIN_DESC``
    characters, ending in "..."), then the note is cut after a whole word ("...") or left
    out."""
    tail = f", {note}" if note else " elapsed"
    excess = len(desc) + len(elapsed) + 2 + len(tail) - room
    if excess > 0 and len(desc) > MIN_DESC:
        desc = desc[:max(len(desc) - excess, MIN_DESC) - 3] + "..."
        excess = len(desc) + len(elapsed) + 2 + len(tail) - room
    if excess > 0 and note:
        words = tail[: max(len(tail) - excess - 3, 0) + 1].rsplit(" ", 1)[0].rstrip(" ,:;")
        tail = words + "..." if words else ""
    return f"{desc}: {elapsed}{tail}"


@contextmanager
def _every(seconds: Callable[[], float], action: Callable[[], None]) -> Iterator[None]:
    """Run ``action`` on a daemon thread every ``seconds()`` seconds while the block runs."""
    stop = threading.Event()

    def repeat() -> None:
        while not stop.wait(seconds()):
            action()

    thread = threading.Thread(target=repeat, name="wiggly-progress", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


@contextmanager
def _ticking(desc: str) -> Iterator[Activity]:
    line = bar(total=None, bar_format="{desc}", leave=True)
    handle = Activity(f"[wiggly] {desc}", line)
    handle.draw()
    try:
        with _every(lambda: 0.25, handle.draw):
            yield handle
    finally:
        handle.note("")
        handle.draw()
        line.close()


@contextmanager
def activity(desc: str, enabled: bool = True) -> Iterator[Activity]:
    """While a blocking call (e.g. fTetWild) runs: a live elapsed-time line on a terminal, or
    one INFO line before it starts (when stages are :func:`shown` and ``enabled``)."""
    if not (enabled and shown()):
        yield Activity()
        return
    with _ticking(desc) if on_terminal() else _heartbeat(desc) as handle:
        token = _activity.set(handle)
        try:
            yield handle
        finally:
            _activity.reset(token)


def note(text: str) -> None:
    """Say what the innermost running :func:`activity` is doing now (its live line, or the
    log at most every :data:`NOTE_EVERY` seconds), for a library function that one of its
    callers wraps in an activity; nothing outside one."""
    handle = _activity.get()
    if handle is not None:
        handle.note(text)


@contextmanager
def _heartbeat(desc: str) -> Iterator[Activity]:
    """The logged :class:`Activity`, which also says every :data:`NOTE_EVERY` seconds that
    it still runs when the call gives no note (fTetWild was silent in a log for two minutes
    while it filled a fine plate)."""
    log.info(desc)
    handle = Activity(desc, logged=True)

    def beat() -> None:
        now = time.perf_counter()
        if now - handle.said >= NOTE_EVERY:
            handle.said = now
            log.info(f"{desc}: {handle.text or 'still running'} ({now - handle.t0:.0f} s)")

    with _every(lambda: max(NOTE_EVERY / 4, 0.05), beat):
        yield handle


def _counted(n: int, unit: str) -> str:
    """``n`` and the unit in the right number, tqdm's "it" unchanged."""
    return counted(n, unit, "it" if unit == "it" else None)


class Counter:
    """What :func:`iterations` gives off a terminal: counts like a tqdm bar, logs the count
    and the last status at most every :data:`NOTE_EVERY` seconds while it runs (a long solve
    piped to a log does not look hung), and one line when it closes."""

    def __init__(self, desc: str, unit: str, enabled: bool, total: int | None = None) -> None:
        self.desc, self.unit, self.enabled, self.total = desc, unit, enabled, total
        self.n, self.postfix, self.t0 = 0, "", time.perf_counter()
        self.said = self.t0

    def _count(self) -> str:
        if self.total is None:
            return _counted(self.n, self.unit)
        return f"{self.n} of {_counted(self.total, self.unit)}"

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if self.enabled and now - self.said >= NOTE_EVERY:
            self.said = now
            status = f", {self.postfix}" if self.postfix else ""
            log.info(f"{self.desc}: {self._count()} so far{status} "
                     f"({now - self.t0:.0f} s)")

    def set_postfix_str(self, text: str = "", refresh: bool = True) -> None:
        self.postfix = text

    def write(self, text: str, file=None) -> None:
        log.info(text)

    def close(self) -> None:
        if self.enabled:
            status = f", {self.postfix}" if self.postfix else ""
            log.info(f"{self.desc}: {self._count()}{status} "
                     f"({time.perf_counter() - self.t0:.1f} s)")
            self.enabled = False

    def __enter__(self) -> Counter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def iterations(desc: str, enabled: bool = True, unit: str = "it") -> tqdm | Counter:
    """A counter of solver iterations (``bar.update(1)``, ``bar.set_postfix_str(...)``),
    with no total: the iteration budget is no estimate of the iterations a solve takes.
    It reports when stages are :func:`shown` and ``enabled``."""
    enabled = enabled and shown()
    if enabled and on_terminal():
        return bar(total=None, desc=desc, leave=False, unit=unit)
    return Counter(desc, unit, enabled)


def frames(items: Iterable, total: int | None, desc: str, enabled: bool = True,
           unit: str = "frame") -> Iterable:
    """``items`` with a bar on a terminal, or one INFO line when they are done (when stages
    are :func:`shown` and ``enabled``)."""
    if not (enabled and shown()):
        return items
    if on_terminal():
        return bar(iterable=items, total=total, unit=unit, desc=desc)
    return _logged(items, desc, unit)


def _logged(items: Iterable, desc: str, unit: str) -> Iterator:
    """``items``, logging the count at most every :data:`NOTE_EVERY` seconds and when done."""
    t0, n = time.perf_counter(), 0
    said = t0
    for n, item in enumerate(items, 1):
        yield item
        now = time.perf_counter()
        if now - said >= NOTE_EVERY:
            said = now
            log.info(f"{desc}: {_counted(n, unit)} so far ({now - t0:.0f} s)")
    log.info(f"{desc}: {_counted(n, unit)} ({time.perf_counter() - t0:.1f} s)")
