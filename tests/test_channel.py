"""The framing of the editor's child processes (wiggly.editor.channel): messages round-trip
whole, however large; a stream that ends, between messages or inside one, reads as None."""

from __future__ import annotations

import os
import pickle
import threading

import numpy as np
import pytest

from wiggly.editor import channel


@pytest.fixture
def pipe():
    r, w = os.pipe()
    ends = {"r": r, "w": w}
    yield ends
    for fd in ends.values():
        try:
            os.close(fd)
        except OSError:
            pass


def close(ends: dict, which: str) -> None:
    os.close(ends.pop(which))


def test_messages_round_trip_in_order(pipe):
    messages = [("status", "mesh", "tetrahedralizing", 0.1), ("model", {"key": (1, 2.5)}),
                ("error", "bad\nnews", True), ()]
    for m in messages:
        channel.send(pipe["w"], m)
    assert channel.ready(pipe["r"])
    assert [channel.receive(pipe["r"]) for _ in messages] == messages
    assert not channel.ready(pipe["r"], timeout=0.01)  # nothing left, the stream still open


def test_a_message_larger_than_the_pipe_arrives_whole(pipe):
    """A pipe holds 64 KiB: a tet mesh or playback frames go in several writes and reads."""
    frames = np.random.default_rng(0).standard_normal((40, 2000, 3)).astype(np.float32)
    writer = threading.Thread(target=channel.send, args=(pipe["w"], ("frames", 7, frames)))
    writer.start()
    kind, seq, got = channel.receive(pipe["r"])
    writer.join()
    assert (kind, seq) == ("frames", 7) and np.array_equal(got, frames)


def test_the_end_of_the_stream_reads_as_none(pipe):
    channel.send(pipe["w"], ("model", 1))
    close(pipe, "w")
    assert channel.ready(pipe["r"])
    assert channel.receive(pipe["r"]) == ("model", 1)
    assert channel.ready(pipe["r"])  # the end is readable at once
    assert channel.receive(pipe["r"]) is None
    assert channel.receive(pipe["r"]) is None


@pytest.mark.parametrize("cut", [3, channel.HEADER, channel.HEADER + 5])
def test_a_torn_message_reads_as_the_end(pipe, cut):
    """A writer killed inside a message (in its length, or in its pickle): None, no error."""
    data = pickle.dumps(("modes", list(range(100))))
    whole = len(data).to_bytes(channel.HEADER, "little") + data
    os.write(pipe["w"], whole[:cut])
    close(pipe, "w")
    assert channel.receive(pipe["r"]) is None


def test_a_message_that_does_not_unpickle_raises_and_the_stream_stays_in_step(pipe):
    garbage = b"not a pickle"
    os.write(pipe["w"], len(garbage).to_bytes(channel.HEADER, "little") + garbage)
    channel.send(pipe["w"], ("next", 2))
    with pytest.raises(pickle.UnpicklingError):
        channel.receive(pipe["r"])
    assert channel.receive(pipe["r"]) == ("next", 2)


def test_sending_to_a_closed_pipe_raises_broken_pipe(pipe):
    close(pipe, "r")
    with pytest.raises(BrokenPipeError):
        channel.send(pipe["w"], ("solve", 1))
