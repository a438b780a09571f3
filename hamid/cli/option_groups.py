"""The command line's options of `hamid.fit`, declared once per group of
`options.OPTION_GROUPS`, each group a decorator: `fit` (and so `fit --each`) takes them all,
`select` the reading and velocity options, `plot` the reading options, so that each command
reads the files the others read.

Every option takes the name of `hamid.fit`'s keyword (``--format-in`` is ``format``);
`fit_keywords` turns what the command line gave into those keywords; `GroupedCommand`'s
help lists each group under its heading. The run group's `in_memory` and `progress` have no
option: the commands set them (`fit --residuals` reads the data into memory; the status line
is the progress)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import click
from click.core import ParameterSource

from hamid import options
from hamid.options import (
    COVARIANCE_KINDS,
    GAP_POLICIES,
    METHODS,
    SAVGOL_ORDER,
    TIME_UNITS,
    VELOCITY_SOURCES,
)

__all__ = ["API_ONLY", "GroupedCommand", "covariance", "fit_keywords", "method", "reading",
           "run", "velocities"]

class _SpecOption(click.Option):
    """An option of `options.OPTION_GROUPS`: `format_options` lists it under its group."""


def _option(*declarations: str, **attributes: Any) -> Callable[[Any], Any]:
    return click.option(*declarations, cls=_SpecOption, **attributes)


# Keywords of `hamid.fit` that no option sets: the commands set them.
API_ONLY = ("in_memory", "progress")
# Spellings of a tab on the command line, where a literal tab is awkward to type.
_DELIMITER_NAMES = {"tab": "\t", "\\t": "\t"}

_GROUPS: dict[str, tuple[Callable[[Any], Any], ...]] = {
    "reading": (
        _option("--columns", metavar="NAME=COL,...",
                     help="Map model names to file columns."),
        _option("--time", metavar="COL",
                     help="Time column (default t or time in any case, with a unit: time_ms, "
                          "Time [s])."),
        _option("--time-unit", type=click.Choice(TIME_UNITS),
                     help="Unit of the time column (default: its name's suffix, else s)."),
        _option("--trajectory", metavar="COL",
                     help="Trajectory column (default trajectory)."),
        _option("--scale", metavar="COL=FACTOR,...",
                     help="Multiply file columns by these factors to bring them to SI units "
                          "(default: from unit suffixes such as x1_mm, v1_mm_s)."),
        _option("--gaps", default="split", show_default=True,
                     type=click.Choice(GAP_POLICIES),
                     help="At a missing value or a time gap, cut the trajectory in two, or "
                          "refuse."),
        _option("--format-in", "format", type=click.Choice(["csv", "tsv", "parquet"]),
                     help="Input format, when the file name does not tell it."),
        _option("--delimiter", metavar="CHAR",
                     help="Delimiter of text input ('tab' or \\t for a tab; default: tab for "
                          ".tsv, else ';' when the header has more ';' than ',', else ',')."),
        _option("--decimal", type=click.Choice([".", ","]),
                     help="Decimal mark of text input (default: ',' when the delimiter is not "
                          "',' and the numbers are written so, else '.')."),
        _option("--skip-rows", default=0, show_default=True, type=click.IntRange(min=0),
                     metavar="N",
                     help="Lines of preamble to skip before the header of text input."),
        _option("--units-row/--no-units-row", default=None,
                     help="Whether the row under the header of text input holds units "
                          "(default: when it has no number and the next row has)."),
    ),
    "velocities": (
        _option("--velocity", default="auto", show_default=True,
                     type=click.Choice(VELOCITY_SOURCES),
                     help="Velocities from the file (measured), derived from the positions "
                          "(Savitzky-Golay), or from the file unless they disagree with the "
                          "positions' rate of change (auto)."),
        _option("--window", type=click.IntRange(min=3), metavar="SAMPLES",
                     help="Savitzky-Golay window (odd; default about a tenth of the period)."),
        _option("--order", default=SAVGOL_ORDER, show_default=True,
                     type=click.IntRange(min=1), help="Savitzky-Golay polynomial order."),
    ),
    "method": (
        _option("--method", default="auto", show_default=True, type=click.Choice(METHODS),
                     help="Energy rows, weak-form equations of motion, or both (auto: joint "
                          "when the data allow it, refined by fitting the integrated "
                          "trajectories)."),
        _option("--weak-window", type=float, metavar="SECONDS",
                     help="Length of the weak-form windows (default: half the dominant "
                          "period)."),
        _option("--damping", default="none", show_default=True,
                     metavar="none|viscous|coulomb|quadratic[,...]",
                     help="Dissipative forces to fit, one coefficient per coordinate and "
                          "kind."),
        _option("--fix", metavar="NAME=VALUE,...", help="Hold parameters at known values."),
        _option("--noise", metavar="none|auto|COL=SIGMA,...",
                     help="Measurement noise std per column; rows are weighted by the "
                          "variance it puts into them. auto estimates it from the data."),
        _option("--bias-correct", is_flag=True,
                     help="Remove the bias that the noise puts into least squares (needs "
                          "--noise)."),
    ),
    "covariance": (
        _option("--cov", default="hac", show_default=True,
                     type=click.Choice(COVARIANCE_KINDS),
                     help="How standard errors are computed."),
        _option("--level", default=0.95, show_default=True,
                     type=click.FloatRange(0, 1, min_open=True, max_open=True),
                     help="Confidence level of the bounds."),
        _option("--bootstrap", default=200, show_default=True,
                     type=click.IntRange(min=10), help="Replicates for --cov bootstrap."),
        _option("--seed", type=click.IntRange(min=0), help="Seed for --cov bootstrap."),
    ),
    "run": (
        _option("--jobs", type=click.IntRange(min=1), metavar="N",
                     help="Local processes, default one per core: with --each, the files "
                          "fitted at once; else, those that auto's trajectory refinement of a "
                          "long record runs in (the same results)."),
        _option("--chunk-rows", type=click.IntRange(min=1), metavar="ROWS",
                     help="Read the file in chunks of ROWS rows, in bounded memory; auto then "
                          "skips its trajectory refinement (default for files over 64 MB once "
                          "decoded: chunks of 262144 rows, and auto refines holding only the "
                          "records)."),
    ),
}

# NAME=VALUE options parsed into the dicts `hamid.fit` takes, and a delimiter's names.
_PARSERS: dict[str, Callable[[str], Any]] = {
    "columns": lambda text: options.parse_mapping(text, option="--columns"),
    "scale": lambda text: options.parse_float_mapping(text, option="--scale"),
    "fix": lambda text: options.parse_float_mapping(text, option="--fix"),
    "noise": lambda text: text if text in ("none", "auto")
    else options.parse_float_mapping(text, option="--noise"),
    "delimiter": lambda text: _DELIMITER_NAMES.get(text, text),
}

Command = TypeVar("Command", bound=Callable[..., Any])


def _group(name: str) -> Callable[[Command], Command]:
    """The decorator adding the options of one group of `options.OPTION_GROUPS`."""

    def add(command: Command) -> Command:
        for option in reversed(_GROUPS[name]):
            command = option(command)
        return command

    add.__name__ = add.__qualname__ = name
    add.__doc__ = (f"Add the {name} options to a command; it takes them as keyword arguments "
                   "named as `hamid.fit`'s (collect them with ``**options``).")
    return add


reading = _group("reading")
velocities = _group("velocities")
method = _group("method")
covariance = _group("covariance")
run = _group("run")


def fit_keywords(given: Mapping[str, Any]) -> dict[str, Any]:
    """The options of `given` (a command's keyword arguments named as `hamid.fit`'s) that
    the command line gave, not left at their defaults, as `hamid.fit`'s keywords:
    ``NAME=VALUE`` lists parsed, delimiter names resolved. Left out, an option takes
    `hamid.fit`'s default, which its option shows (tests/test_option_spec.py)."""
    context = click.get_current_context()
    return {name: _PARSERS.get(name, _identity)(value) for name, value in given.items()
            if context.get_parameter_source(name) is not ParameterSource.DEFAULT}


def _identity(value: Any) -> Any:
    return value


# The help's heading of each group.
_HEADINGS = {"reading": "Reading options", "velocities": "Velocity options",
             "method": "Method options", "covariance": "Covariance options",
             "run": "Run options"}


class GroupedCommand(click.Command):
    """A command whose help lists the options of `hamid.fit` under their groups' headings:
    its own under "Options", then each group's it takes, in the order of
    `options.OPTION_GROUPS`."""

    def format_options(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        group_of = {name: group for group, names in options.OPTION_GROUPS.items()
                    for name in names}
        sections: dict[str, list[tuple[str, str]]] = {"Options": []}
        sections.update((heading, []) for heading in _HEADINGS.values())
        for param in self.get_params(ctx):
            record = param.get_help_record(ctx)
            if record is None or isinstance(param, click.Argument):
                continue
            heading = (_HEADINGS[group_of[param.name]] if isinstance(param, _SpecOption)
                       and param.name is not None else "Options")
            sections[heading].append(record)
        for heading, records in sections.items():
            if records:
                with formatter.section(heading):
                    formatter.write_dl(records)
