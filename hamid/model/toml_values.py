"""Checks for values read from TOML tables: unknown keys and numbers, with clear errors."""

from __future__ import annotations

import difflib
import math
from collections.abc import Collection, Mapping
from typing import Any

from hamid.errors import ModelError

__all__ = ["check_keys", "number", "table"]


def check_keys(table: Mapping[str, Any], allowed: Collection[str], *, where: str) -> None:
    """Reject keys not in `allowed`, suggesting the closest valid key."""
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), list(allowed), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else (
                f"; valid keys: {', '.join(allowed)}" if allowed else "")
            raise ModelError(f"{where}: unknown key {key!r}{hint}")


def table(value: Any, *, where: str) -> Mapping[str, Any]:
    """A TOML table (dict), or an error naming where a table was expected."""
    if not isinstance(value, Mapping):
        raise ModelError(f"{where}: expected a table, found {type(value).__name__}")
    return value


def number(value: Any, *, where: str, positive: bool = False,
           non_negative: bool = False) -> float:
    """A finite number from TOML (int or float), checked for sign."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelError(f"{where}: expected a number, found {value!r}")
    try:
        value = float(value)
    except OverflowError:   # TOML integers have no bound; a double ends near 1.8e308
        raise ModelError(f"{where}: expected a finite number, found an integer of "
                         f"{len(str(abs(value)))} digits") from None
    if not math.isfinite(value):
        raise ModelError(f"{where}: expected a finite number, found {value!r}")
    if positive and value <= 0:
        raise ModelError(f"{where}: must be positive, found {value!r}")
    if non_negative and value < 0:
        raise ModelError(f"{where}: must not be negative, found {value!r}")
    return value
