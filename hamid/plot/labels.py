"""Words and numbers in the figures: names from a report shown safely, the recordings
behind the fitted trajectories, and axes labelled with their unit and plain tick labels
(`hamid.plot.figures`)."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["label_axis", "number", "plain", "power_text", "recordings", "source_name", "ticks"]

LONGEST_NAME = 40           # characters of a name from the report shown in a figure


def plain(name: Any) -> str:
    """A name from the report as plain text in a figure: cut to `LONGEST_NAME`
    characters, its dollar signs escaped (mathtext parsed an edited report's "$x^$", and
    3,000 nested braces overflowed its parser's recursion)."""
    text = str(name)
    if len(text) > LONGEST_NAME:
        text = text[:LONGEST_NAME - 1] + "…"
    return text.replace("$", r"\$")


# A piece of a record cut at dropouts or time gaps (`hamid.data.records.split_gaps`).
_PIECE = re.compile(r"^(.*)/(\d+)$")


def recordings(labels: Sequence[str]) -> list[tuple[str, list[int]]]:
    """The recordings behind the fitted trajectories, in order: the pieces of one record cut
    at dropouts or gaps (labelled NAME/1, NAME/2, ...) together under NAME, each other
    trajectory alone; a file's path shown by its name."""
    prefixes = [m.group(1) if (m := _PIECE.match(label)) else None for label in labels]
    shared = {p for p in prefixes if p is not None and prefixes.count(p) > 1}
    grouped: dict[str, list[int]] = {}
    for j, (label, prefix) in enumerate(zip(labels, prefixes, strict=True)):
        grouped.setdefault(prefix if prefix in shared else label, []).append(j)
    return [(plain(os.path.basename(name) or name) if not name.isdigit()
             else f"trajectory {name}", pieces) for name, pieces in grouped.items()]


def source_name(source: str) -> str:
    """A source in a title: a file's name, or what an in-memory table was."""
    if source in ("<DataFrame>", "<dict>", "<array>"):
        return "data in memory"
    return plain(os.path.basename(source.strip("<>")))


def ticks(n: int) -> Any:
    """A locator of at most n ticks at round numbers."""
    from matplotlib.ticker import MaxNLocator

    return MaxNLocator(n, steps=[1, 2, 2.5, 5, 10])


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def power_text(power: int) -> str:
    return f"10{str(power).translate(_SUPERSCRIPT)}"


def label_axis(ax: Axes, which: str, name: str, unit: str | None = None) -> None:
    """Label an axis with its name and unit, its ticks plain numbers: a power of ten far
    from 1 goes into the label ("E [10⁻⁵ m²/s²]"), never as matplotlib's offset or
    multiplier text over the axes, which ran into legends and titles."""
    from matplotlib.ticker import FuncFormatter, ScalarFormatter

    axis = ax.xaxis if which == "x" else ax.yaxis
    low, high = axis.get_view_interval()
    largest = max(abs(low), abs(high))
    power = int(np.floor(np.log10(largest))) if 0 < largest < math.inf else 0
    if -1 <= power <= 3:
        axis.set_major_formatter(ScalarFormatter(useOffset=False))
    else:
        axis.set_major_formatter(FuncFormatter(lambda x, _: number(x / 10.0**power)))
        unit = power_text(power) + (f" {unit}" if unit else "")
    label = f"{name} [{unit}]".replace("\n [", "\n[") if unit else name
    (ax.set_xlabel if which == "x" else ax.set_ylabel)(label)


def number(x: float, digits: int = 6) -> str:
    """A tick label: `digits` significant digits at most, matplotlib's minus sign."""
    return f"{x:.{digits}g}".replace("-", "−")


