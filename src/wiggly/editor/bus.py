"""Plumbing of the editor's threads: the event bus that feeds every open event stream, and
the one-slot mailbox of the fast worker (newest request wins)."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["EventBus", "Mailbox"]


class EventBus:
    """Fan-out of server events (dicts) to every open event stream (one queue each).

    A new subscriber first gets the newest *sticky* event of each type, so that a tab opened
    now sees the current frames and status.  Events of gizmo drags are not sticky: a tab
    opened after an abandoned drag must not show its preview.
    """

    def __init__(self, backlog: int = 256, shown: Callable[[str], str] | None = None):
        self._lock = threading.Lock()
        self._queues: list[queue.Queue] = []
        self.backlog = backlog
        self.last: dict[str, dict] = {}  # newest sticky event of each type
        self.shown = shown  # how an event's "message" is shown (the session's own paths)

    def subscribe(self) -> queue.Queue:
        q: queue.Queue = queue.Queue(self.backlog)
        with self._lock:
            self._queues.append(q)
            for event in self.last.values():
                q.put_nowait(event)
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            if q in self._queues:
                self._queues.remove(q)

    @property
    def n_subscribers(self) -> int:
        with self._lock:
            return len(self._queues)

    def publish(self, kind: str, *, sticky: bool = True, **data: Any) -> None:
        if self.shown is not None and isinstance(data.get("message"), str):
            data["message"] = self.shown(data["message"])
        event = {"type": kind, "time": time.time(), **data}
        with self._lock:
            if sticky:
                self.last[kind] = event
            for q in self._queues:
                try:
                    q.put_nowait(event)
                except queue.Full:  # a stalled client loses its oldest events
                    try:
                        q.get_nowait()
                        q.put_nowait(event)
                    except (queue.Empty, queue.Full):
                        pass


class Mailbox:
    """A one-slot queue where a newer item replaces one not yet taken (newest wins)."""

    def __init__(self):
        self._cv = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self._cv:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self._cv.notify_all()

    def take(self, timeout: float | None = None) -> Any:
        """The newest item (None on timeout or when closed)."""
        with self._cv:
            self._cv.wait_for(lambda: self._item is not None or self._closed, timeout)
            item, self._item = self._item, None
            return item

    def pending(self) -> bool:
        with self._cv:
            return self._item is not None or self._closed

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify_all()
