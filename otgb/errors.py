"""The error raised for bad input a user gave: a config value, a measured-data file, a shape.

The ``otgb`` command prints an :class:`InputError` as one line (``otgb: error: <message>``)
and exits with status 2, instead of a traceback: its message already names what was wrong,
where, and what was expected. Anything else (a bug, a diverging solve) keeps its traceback.
It subclasses ValueError, so code that catches ValueError keeps working.
"""


class InputError(ValueError):
    """Bad user input; the message names what, where, and what was expected."""


class OutputNotWritten(OSError):
    """A checkpoint, log or report could not be written (a full disk, no permission); the message says which."""


def first_line(error: BaseException) -> str:
    """``Type: first line of the message`` (the type alone for an empty message): an error in one line."""
    lines = str(error).strip().splitlines()
    return f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__
