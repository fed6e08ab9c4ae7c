"""Errors raised for bad user input (shown to users without a traceback), and message helpers."""


class WigglyInputError(ValueError):
    """A user-supplied file, parameter or keyframe is invalid; the message says what and how to fix it."""  # noqa: E501


_IRREGULAR = {"vertex": "vertices", "vertices": "vertices", "index": "indices"}


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and the noun in the right number: "1 vertex", "2 vertices", "0 open edges"."""
    if n == 1:
        return f"1 {noun}"
    if plural is None:
        head, _, last = noun.rpartition(" ")
        plural = (head + " " if head else "") + _IRREGULAR.get(last, last + "s")
    return f"{n} {plural}"
