"""Errors raised for bad user input (shown to users without a traceback), and message helpers."""

import os
import sys
import warnings


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


_PACKAGE = os.path.dirname(os.path.abspath(__file__)) + os.sep


def warn(message: str, category: type[Warning] = UserWarning) -> None:
    """:func:`warnings.warn` attributed to the first caller outside wiggly (the user's
    line, not wiggly's own: a wrapper or a helper in between would move it otherwise)."""
    frame, level = sys._getframe(1), 2
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
