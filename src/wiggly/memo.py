"""Derived values kept by the object that owns them, keyed by the values they derive from.

The spacetime solve recomputes little between edits: the energy of a node set, the
selection matrices and Grams of a vertex group, the least-squares fit of a group's targets.
Each such value lives in a :class:`Memo` owned by one object (a
:class:`~wiggly.solve.problem.SpacetimeProblem`, or a :class:`~wiggly.body.Body` for its
vertex groups), under a key built from *values*: plain numbers and strings, and
:func:`value_key` snapshots of arrays (their bytes, shape and dtype), compared by equality.
An array edited in place therefore gets a new key; nothing is keyed by ``id()`` or a memory
address.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import TypeVar

import numpy as np

__all__ = ["Memo", "value_key"]

T = TypeVar("T")


def value_key(a: np.ndarray | None) -> tuple | None:
    """A hashable snapshot of an array's value: (shape, dtype, bytes); None stays None."""
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    return (a.shape, a.dtype.str, a.tobytes())


class Memo:
    """A bounded map from value keys to derived values (least recently used leaves first).

    ``memo.get(key, compute)`` returns the value for ``key``, calling ``compute()`` on a miss.
    Where the value is made elsewhere (in another process, or as a future that may fail and
    be made again), :meth:`peek` looks without using and :meth:`put` stores and uses.
    A memo does no locking: an owner shared by threads locks around it.
    """

    def __init__(self, limit: int = 128) -> None:
        self.limit = limit
        self._values: OrderedDict[Hashable, object] = OrderedDict()
        self.hits = self.misses = 0

    def get(self, key: Hashable, compute: Callable[[], T]) -> T:
        if key in self._values:
            self._values.move_to_end(key)
            self.hits += 1
            return self._values[key]  # type: ignore[return-value]
        self.misses += 1
        value = compute()
        self.put(key, value)
        return value

    def peek(self, key: Hashable, default: T | None = None) -> object | T | None:
        """The value for ``key`` (``default`` if there is none), leaving it as recently used
        as it was."""
        return self._values.get(key, default)

    def put(self, key: Hashable, value: object) -> None:
        """Store ``value`` for ``key`` as the most recently used (the least recently used
        beyond ``limit`` leave)."""
        self._values[key] = value
        self._values.move_to_end(key)
        while len(self._values) > self.limit:
            self._values.popitem(last=False)

    def keys(self) -> list[Hashable]:
        """The keys, least recently used first."""
        return list(self._values)

    def __contains__(self, key: Hashable) -> bool:
        return key in self._values

    def __len__(self) -> int:
        return len(self._values)

    def clear(self) -> None:
        self._values.clear()

    def drop(self, stale: Callable[[Hashable], bool]) -> None:
        """Forget the values whose keys ``stale(key)`` is true for."""
        for key in [k for k in self._values if stale(k)]:
            del self._values[key]
