"""The one base class of the errors a user can cause (a bad file, key, option or frame).

The command line turns a :class:`ThermalEdgeError` into one line and exit status 2; any other
exception is a bug and shows its traceback. A leaf: every part of the package may import it.
"""
from __future__ import annotations

__all__ = ["ThermalEdgeError", "UsageError"]


class ThermalEdgeError(Exception):
    """An error caused by the user's input; its message names the file, key or option and the
    cause in one line."""


class UsageError(ThermalEdgeError):
    """A command-line option that is missing, malformed or out of range, or options that do not
    go together; the message names the option."""
