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
