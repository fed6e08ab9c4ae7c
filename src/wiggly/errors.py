"""Errors raised for bad user input (shown to users without a traceback)."""
class WigglyInputError(ValueError):
    """A user-supplied file, parameter or keyframe is invalid; the message says what and how to fix it."""  # noqa: E501
