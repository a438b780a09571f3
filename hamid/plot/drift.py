"""Parameters across recordings: `hamid plot results.jsonl` (the lines of `fit --each`) or
`hamid plot A.json B.json ...`, each parameter against the order of the fits, or against a
value each report carries (`--order-by`), with its confidence interval; the drift an
engineer who monitors a structure looks for. Drawn without pyplot, like the panels."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from datetime import datetime
from typing import TYPE_CHECKING, Any

from hamid.errors import DataError, UsageError
from hamid.plot import figures, labels
from hamid.plot.palette import OKABE_ITO
from hamid.report.comparison import Compared
from hamid.result.fit_result import FitResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["MTIME", "drift_figure", "order_values", "save"]

MTIME = "mtime"   # --order-by mtime: the modification time of the data file each fit read


def _key(report: Mapping[str, Any], key: str, source: str) -> Any:
    """The value at a dotted key of a report (``provenance.utc``, ``data.start_time``)."""
    value: Any = report
    for part in key.split("."):
        if not isinstance(value, Mapping) or part not in value:
            raise DataError(f"{source}: --order-by {key}: the report has no {key!r} (give a "
                            "dotted key of its data or provenance, or mtime)")
        value = value[part]
    return value


def _order_value(fit: FitResult, key: str, source: str) -> float | datetime:
    """One fit's place on the x axis: a number, or a time (ISO 8601 text, or a file's
    modification time)."""
    if key == MTIME:
        path = fit.data["sources"][0]
        try:
            return datetime.fromtimestamp(os.stat(path).st_mtime).astimezone()
        except OSError as exc:
            raise DataError(f"{source}: --order-by mtime: the data file {path!r} it read "
                            f"cannot be found here ({exc.strerror})") from None
    value = _key(fit.to_dict(), key, source)
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise DataError(f"{source}: --order-by {key}: {value!r} is neither a number nor a time")
    if isinstance(value, str):
        try:
            return datetime.fromisoformat(value)
        except ValueError:
            raise DataError(f"{source}: --order-by {key}: {value!r} is not an ISO 8601 time "
                            "(such as 2024-05-01T12:00:00Z)") from None
    return float(value)


def order_values(fits: Sequence[Compared], order_by: str | None) -> list[float | datetime]:
    """Each fit's place: its position (1, 2, ...) without `order_by`, else its value."""
    if order_by is None:
        return [float(k) for k in range(1, len(fits) + 1)]
    values = [_order_value(c.outcome, order_by, c.source) for c in fits]  # type: ignore[arg-type]
    if len({type(v) for v in values}) > 1:
        raise DataError(f"--order-by {order_by}: some reports give a number, others a time")
    try:
        sorted(values)   # type: ignore[type-var]
    except TypeError:
        raise DataError(f"--order-by {order_by}: times with and without a time zone cannot "
                        "be ordered together") from None
    return values


def drift_figure(compared: Sequence[Compared],
                 order_by: str | None = None) -> tuple[Figure, list[str]]:
    """The figure: a row per parameter, its estimate and interval per fit; and notes on the
    fits left out (the lines of failed fits)."""
    from matplotlib.figure import Figure

    figures.check_output("drift.png")   # matplotlib there, or the one-line error naming the extra
    fits = [c for c in compared if isinstance(c.outcome, FitResult)]
    notes = [f"left out {c.source}: its fit failed ({c.outcome})" for c in compared
             if not isinstance(c.outcome, FitResult)]
    if not fits:
        raise UsageError("no fit to draw: every line records a failed fit")
    x = order_values(fits, order_by)
    names = list(dict.fromkeys(p.name for c in fits for p in c.outcome.parameters))
    if len(names) > figures.MAX_PARAMETERS["parameters"]:
        raise UsageError(f"at most {figures.MAX_PARAMETERS['parameters']} parameters to show "
                         f"across the fits (they have {len(names):,})")
    fig = Figure(figsize=(10.0, 1.6 + 1.5 * len(names)), layout="constrained", dpi=120)
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)[:, 0]
    level = fits[0].outcome.method["level"]
    for ax, name in zip(axes, names, strict=True):
        for colour, fixed in ((OKABE_ITO[0], False), (OKABE_ITO[3], True)):
            rows = [(xk, p) for xk, c in zip(x, fits, strict=True) for p in c.outcome.parameters
                    if p.name == name and p.fixed == fixed]
            if not rows:
                continue
            low = [p.estimate - (p.ci_low if p.ci_low is not None else p.estimate)
                   for _, p in rows]
            high = [(p.ci_high if p.ci_high is not None else p.estimate) - p.estimate
                    for _, p in rows]
            ax.errorbar([xk for xk, _ in rows], [p.estimate for _, p in rows],
                        yerr=[low, high], fmt="D" if fixed else "o", color=colour,
                        capsize=3, markersize=4, linewidth=1.0,
                        label="fixed" if fixed else "estimate")
        labels.label_axis(ax, "y", labels.plain(name))
    if order_by is None:
        axes[-1].xaxis.set_major_locator(labels.ticks(10))
        axes[-1].set_xlabel("fit, in the order of the files and lines")
    else:
        axes[-1].set_xlabel(f"{labels.plain(order_by)}" + (" (modification time of the "
                                                            "data file)" if order_by == MTIME
                                                            else ""))
        if isinstance(x[0], datetime):
            from matplotlib.dates import AutoDateLocator, ConciseDateFormatter

            locator = AutoDateLocator(maxticks=8)
            axes[-1].xaxis.set_major_locator(locator)
            axes[-1].xaxis.set_major_formatter(ConciseDateFormatter(locator))
    models = sorted({c.outcome.model["name"] for c in fits})
    first, last = labels.plain(fits[0].source), labels.plain(fits[-1].source)
    fig.suptitle(f"Parameters across {len(fits)} fits — {', '.join(models)}",
                 fontsize="large")
    fig.supxlabel(f"bars: {100 * level:g}% confidence intervals; first fit {first}, last "
                  f"{last}", fontsize="small")
    return fig, notes


def save(compared: Sequence[Compared], path: str, order_by: str | None = None) -> list[str]:
    """Draw the parameters across the fits and write the figure (one file, atomically);
    returns the notes on fits left out."""
    figures.check_output(path)
    fig, notes = drift_figure(compared, order_by)
    figures.write_pages([("parameters", fig)], path)
    return notes
