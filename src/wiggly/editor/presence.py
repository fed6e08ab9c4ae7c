"""Which browser tabs have a page open: an undo history whose tab is gone goes to another.

A tab is live while one of its pages listens to the event stream.  A reload ends the stream
and opens another within a second or two, so a tab counts as *gone* only once no page of it
has listened for :data:`TAB_GRACE` seconds (the tabs of a scene's journal, until they come
back, from the scene's opening).  :meth:`wiggly.editor.history.Histories.attend` gives a
gone tab's history to a tab without one of its own.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict

__all__ = ["TAB_GRACE", "Presence"]

#: Seconds without a page before a tab counts as gone (longer than a reload takes).
TAB_GRACE = 3.0


class Presence:
    """The open event streams of each browser tab, and when each tab's last one ended."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._streams: Counter[str] = Counter()
        self._left: dict[str, float] = {}
        self._since = time.monotonic()
        self._ended: OrderedDict[str, None] = OrderedDict()  # page loads whose stream ended

    def page_ended(self, page: str) -> None:
        """The event stream of the page load ``page`` ended: a page never comes back (a reload
        is a new page), so what it still sends (a drag's last preview) is stale."""
        with self._lock:
            self._ended[page] = None
            while len(self._ended) > 1024:
                self._ended.popitem(last=False)

    def ended(self, page: str | None) -> bool:
        with self._lock:
            return page is not None and page in self._ended

    def opened(self, tab: str) -> None:
        with self._lock:
            self._streams[tab] += 1

    def closed(self, tab: str) -> bool:
        """A stream of ``tab`` ended; True when it was the tab's last."""
        with self._lock:
            self._streams[tab] -= 1
            if self._streams[tab] > 0:
                return False
            del self._streams[tab]
            self._left[tab] = time.monotonic()
            return True

    def restart(self) -> None:
        """A scene was opened: the tabs of its journal are away from now on, until they
        come back."""
        with self._lock:
            self._since = time.monotonic()

    def gone(self, tab: str) -> bool:
        """No page of ``tab`` has listened for :data:`TAB_GRACE` seconds."""
        with self._lock:
            return tab not in self._streams and \
                time.monotonic() - self._left.get(tab, self._since) >= TAB_GRACE
