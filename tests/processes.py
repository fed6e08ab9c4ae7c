"""Child processes of a test's subprocess, read from /proc (Linux)."""

from __future__ import annotations

import time
from pathlib import Path


def children_of(pid: int) -> list[int]:
    """The process ids of ``pid``'s children now."""
    return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def assert_ended(pids: list[int], timeout: float = 10.0) -> None:
    """Every process of ``pids`` ends (or is a zombie) within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while any(Path(f"/proc/{c}").exists() for c in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = [c for c in pids if Path(f"/proc/{c}").exists()
             and Path(f"/proc/{c}/stat").read_text().split()[2] != "Z"]
    assert not alive, f"still running: {alive}"
