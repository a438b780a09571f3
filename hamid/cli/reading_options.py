"""The reading options: how a data file is read, one list for every command that reads data
(`fit`, `fit --each`, `select`, `plot`), so that each reads the files the others read.

The options take the names of `hamid.fit`'s keywords (`options.READING_OPTIONS`);
`reading_keywords` turns what the command line gave into those keywords.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import click
from click.core import ParameterSource

from hamid import options
from hamid.options import GAP_POLICIES, TIME_UNITS

__all__ = ["reading_keywords", "reading_options"]

_DELIMITER_NAMES = {"tab": "\t", "\\t": "\t"}

_OPTIONS = (
    click.option("--columns", metavar="NAME=COL,...", help="Map model names to file columns."),
    click.option("--time", metavar="COL",
                 help="Time column (default t or time in any case, with a unit: time_ms, "
                      "Time [s])."),
    click.option("--time-unit", type=click.Choice(TIME_UNITS),
                 help="Unit of the time column (default: its name's suffix, else s)."),
    click.option("--scale", metavar="COL=FACTOR,...",
                 help="Multiply file columns by these factors to bring them to SI units "
                      "(default: from unit suffixes such as x1_mm, v1_mm_s)."),
    click.option("--gaps", default="split", show_default=True, type=click.Choice(GAP_POLICIES),
                 help="At a missing value or a time gap, cut the trajectory in two, or "
                      "refuse."),
    click.option("--trajectory", metavar="COL", help="Trajectory column (default trajectory)."),
    click.option("--format-in", "format", type=click.Choice(["csv", "tsv", "parquet"]),
                 help="Input format, when the file name does not tell it."),
    click.option("--delimiter", metavar="CHAR",
                 help="Delimiter of text input ('tab' or \\t for a tab; default: tab for "
                      ".tsv, else ';' when the header has more ';' than ',', else ',')."),
    click.option("--decimal", type=click.Choice([".", ","]),
                 help="Decimal mark of text input (default: ',' when the delimiter is not ',' "
                      "and the numbers are written so, else '.')."),
    click.option("--skip-rows", default=0, show_default=True, type=click.IntRange(min=0),
                 metavar="N", help="Lines of preamble to skip before the header of text input."),
    click.option("--units-row/--no-units-row", default=None,
                 help="Whether the row under the header of text input holds units (default: "
                      "when it has no number and the next row has)."),
)

Command = TypeVar("Command", bound=Callable[..., Any])


def reading_options(command: Command) -> Command:
    """Add the reading options to a command; it takes them as keyword arguments named as
    `hamid.fit`'s (collect them with ``**reading``)."""
    for option in reversed(_OPTIONS):
        command = option(command)
    return command


def reading_keywords(reading: Mapping[str, Any]) -> dict[str, Any]:
    """The reading options given on the command line (not left at their defaults) as
    `hamid.fit`'s keywords: ``NAME=VALUE`` lists parsed, delimiter names resolved."""
    context = click.get_current_context()
    given = {name: value for name, value in reading.items()
             if context.get_parameter_source(name) is not ParameterSource.DEFAULT}
    if "columns" in given:
        given["columns"] = options.parse_mapping(given["columns"], option="--columns")
    if "scale" in given:
        given["scale"] = options.parse_float_mapping(given["scale"], option="--scale")
    if "delimiter" in given:
        given["delimiter"] = _DELIMITER_NAMES.get(given["delimiter"], given["delimiter"])
    return given
