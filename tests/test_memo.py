"""wiggly.memo: a bounded least-recently-used map keyed by values."""

from __future__ import annotations

import numpy as np

from wiggly.memo import Memo, value_key


def test_least_recently_used_leaves_first_and_values_are_computed_once():
    memo = Memo(limit=2)
    calls: list[str] = []

    def compute(name: str):
        return lambda: calls.append(name) or name.upper()

    assert memo.get("a", compute("a")) == "A"
    assert memo.get("b", compute("b")) == "B"
    assert memo.get("a", compute("a")) == "A"  # a hit: "a" is now the most recent
    assert memo.get("c", compute("c")) == "C"  # over the limit: "b" leaves
    assert calls == ["a", "b", "c"]
    assert "a" in memo and "b" not in memo and "c" in memo and len(memo) == 2
    assert (memo.hits, memo.misses) == (1, 3)


def test_drop_forgets_the_keys_it_is_told_are_stale():
    memo = Memo(limit=8)
    for body in ("x", "y"):
        for case in range(3):
            memo.get((body, case), lambda: None)
    memo.drop(lambda key: key[0] == "x")
    assert len(memo) == 3 and all(("y", c) in memo for c in range(3))


def test_value_key_follows_the_array_value_not_its_identity():
    a = np.arange(6.0).reshape(2, 3)
    key = value_key(a)
    assert value_key(a.copy()) == key
    a[0, 0] = 7.0
    assert value_key(a) != key
    assert value_key(a.astype(np.float32)) != value_key(a)
    assert value_key(None) is None


def test_put_stores_as_most_recent_and_peek_does_not_use():
    """For values made elsewhere (a child process's models, futures that may fail): put
    stores and uses, peek only looks; both keep the limit."""
    memo = Memo(limit=2)
    memo.put("a", 1)
    memo.put("b", 2)
    assert memo.peek("a") == 1 and memo.peek("z") is None and memo.peek("z", 0) == 0
    memo.put("c", 3)  # "a" was only peeked at: it is the least recently used
    assert memo.keys() == ["b", "c"]
    memo.put("b", 20)  # replacing a value uses it
    memo.put("d", 4)
    assert memo.keys() == ["b", "d"] and memo.peek("b") == 20
    assert (memo.hits, memo.misses) == (0, 0)  # only get counts
    assert memo.get("b", lambda: 99) == 20 and memo.keys() == ["d", "b"]

