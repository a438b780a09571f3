"""The fit's options: the choices the user types, their checks, and option values.

No numpy, pandas or pyarrow at import: the CLI takes its choice lists from here.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from hamid.errors import UsageError


def parse_mapping(text: str, *, option: str) -> dict[str, str]:
    """Parse ``NAME=COLUMN,...`` as given to an option such as ``--columns``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> value, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=VALUE`` or a name is given twice.

    Examples
    --------
    >>> parse_mapping("x=pos1, vx=vel1", option="--columns")
    {'x': 'pos1', 'vx': 'vel1'}
    """
    return _parse_items(text, option, "NAME=COLUMN", lambda key, value, item: value)


def parse_float_mapping(text: str, *, option: str) -> dict[str, float]:
    """Parse ``NAME=NUMBER,...`` as given to options such as ``--noise`` and ``--fix``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> finite number, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=NUMBER``, a number is not finite, or a name is given twice.

    Examples
    --------
    >>> parse_float_mapping("x=0.01,vx=2e-2", option="--noise")
    {'x': 0.01, 'vx': 0.02}
    """

    def to_float(key: str, value: str, item: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise UsageError(f"{option}: {item!r}: {value!r} is not a number") from None
        if not math.isfinite(number):
            raise UsageError(f"{option}: {item!r}: {value!r} is not a finite number")
        return number

    return _parse_items(text, option, "NAME=NUMBER", to_float)


def _parse_items(
    text: str, option: str, form: str, convert: Callable[[str, str, str], Any]
) -> dict[str, Any]:
    """Helper function splitting ``NAME=VALUE,...`` and checking each item."""
    result: dict[str, Any] = {}
    if not text.strip():
        raise UsageError(f"{option}: empty value; expected {form},...")
    for raw in text.split(","):
        item = raw.strip()
        key, equals, value = (part.strip() for part in item.partition("="))
        if not equals or not key or not value:
            raise UsageError(f"{option}: {item!r} is not of the form {form}")
        if key in result:
            raise UsageError(f"{option}: {key!r} is given twice")
        result[key] = convert(key, value, item)
    return result
