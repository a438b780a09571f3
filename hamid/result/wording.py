"""How parts of a report are said to a reader, the same in the fit's warnings, its
renderings and the comparison of several fits: the method that made the numbers, an energy
drift in words."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["correlation_text", "drift_words", "method_name"]


def method_name(method: Mapping[str, Any]) -> str:
    """The method as a reader is told it: the rows' kind (`method.kind`), and "+ trajectory
    refinement" when the refinement made the numbers reported, so that no report credits
    the linear fit with them (the JSON's `kind` stays the rows', which scripts read)."""
    refined = (method.get("refinement") or {}).get("applied")
    return method["kind"] + (" + trajectory refinement" if refined else "")


def drift_words(change: float, *, driven: bool = False) -> str:
    """A trajectory's energy drift (`relative_change`) in words: which way the straight line
    through its energy goes over the record, and by how much of the reference the change is
    divided by: the level h (the mean energy), or a driven fit's spread of the energy.

    The line through a decay to rest falls by more than the mean energy it decays through,
    so a change past 100% is said as a multiple, not as a percentage of something lost.
    """
    reference = "the spread of its energy" if driven else "its level h"
    size = abs(change)
    amount = f"{size:.3g} times" if size > 1 else f"{100 * size:.3g}% of"
    return f"{'falls' if change < 0 else 'rises'} by {amount} {reference}"


def correlation_text(r: float) -> str:
    """A correlation with its sign and the digits that tell it from ±1: -0.998, 0.99994."""
    digits = 3
    while digits < 8 and round(abs(r), digits) == 1 and abs(r) != 1:
        digits += 1
    return f"{r:+.{digits}f}"
