"""Errors reported to the user as one clear message.

The command line turns a `HamidError` into exit status 1 and prints its message; anything
else that escapes is a bug.
"""

from __future__ import annotations

__all__ = ["HamidError", "DataError", "ModelError", "FitError", "UsageError"]


class HamidError(Exception):
    """An error reported to the user in one line."""


class DataError(HamidError):
    """A data file cannot be used: names the file, column and row at fault."""


class ModelError(HamidError):
    """A model or system file is wrong: names the term, key or parameter at fault."""


class FitError(HamidError):
    """The data cannot determine the parameters: names the parameters involved."""


class UsageError(HamidError):
    """Options that contradict each other or a value of the wrong form (exit status 2)."""
