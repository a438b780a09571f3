"""Several fits side by side: `hamid report A.json B.json ...` or `hamid report results.jsonl`.

Saved reports (``hamid fit -o A.json``) and the lines of ``hamid fit --each --format
jsonl`` are read and checked as `hamid report` checks one report; each becomes a column
named by its source: the line's ``source``, else the JSON file's name. A line that
records a failed fit stays a column, with its error below the table.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hamid.data import documents, readers
from hamid.errors import DataError, HamidError, UsageError
from hamid.report import formats
from hamid.result.fit_result import FitResult
from hamid.result.wording import method_name
from hamid.safe_text import counted

__all__ = ["COMPARISON_FORMATS", "ROW_COLUMNS", "Compared", "load", "parameter_rows", "record",
           "render"]

COMPARISON_FORMATS = ("table", "markdown", "csv", "jsonl")
# The rows of `--format csv` over many fits: one per parameter of each, or one per error.
ROW_COLUMNS = ("source", "parameter", "estimate", "stderr", "ci_low", "ci_high", "status",
               "warnings", "error")
_NULL = "—"


@dataclass(frozen=True, slots=True)
class Compared:
    """One column: its source and the fit, or the error that stopped it."""

    source: str
    outcome: FitResult | HamidError


def load(paths: Sequence[str | os.PathLike[str]]) -> list[Compared]:
    """The fits of saved reports (JSON) and of result lines (``.jsonl``), in order.

    Raises
    ------
    DataError
        A file cannot be read, or a report or line is not a hamid fit result (the message
        names the file and line).
    """
    compared = []
    for path in paths:
        name = readers.STDIN if readers.is_stdio(path) else os.fsdecode(path)
        if name.lower().endswith(".jsonl"):
            compared += [_line(document, where) for where, document in
                         documents.read_jsonl(path)]
        else:
            compared.append(Compared(name, FitResult.from_dict(documents.read_json(path),
                                                                source=name)))
    return compared


def _line(document: dict, where: str) -> Compared:
    """Helper: one line of `fit --each` results: a report with its source, or an error."""
    source = document.get("source")
    if not isinstance(source, str):
        raise DataError(f"{where}: not a line of hamid fit --each results (no 'source')")
    if document.get("status") == "error":
        if not isinstance(document.get("error"), str):
            raise DataError(f"{where}: an error line without its message ('error')")
        return Compared(source, HamidError(document["error"]))
    return Compared(source, FitResult.from_dict(document, source=where))


def render(compared: Sequence[Compared], format: str, *, color: bool = False,
           width: int | None = None) -> str:
    """The fits as one table with a column per source (table, markdown), or as the rows
    (csv) or lines (jsonl) of `hamid fit --each`.

    Given a `width` (a terminal's), a table whose columns would not fit takes a row per
    source instead: each parameter's estimate ± its error, the method and the number of
    warnings; no line is wider than `width`.
    """
    records = [record(c.source, c.outcome) for c in compared]
    if format == "jsonl":
        import json

        return "".join(json.dumps(r, allow_nan=False, ensure_ascii=True) + "\n"
                       for r in records)
    if format == "csv":
        import csv
        import io as text_io

        buffer = text_io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(ROW_COLUMNS)
        writer.writerows([row[key] for key in ROW_COLUMNS]
                         for r in records for row in parameter_rows(r))
        return buffer.getvalue()
    if format not in ("table", "markdown"):
        raise UsageError(f"--format {format} shows one fit; several are shown side by side "
                         f"as {', '.join(COMPARISON_FORMATS)}")
    fits = [c.outcome for c in compared if isinstance(c.outcome, FitResult)]
    models = sorted({fit.model["name"] for fit in fits})
    title = (f"hamid report — {counted(len(compared), 'fit', 'fits')}" +
             (f" of {', '.join(models)}" if models else ""))
    names = list(dict.fromkeys(p.name for fit in fits for p in fit.parameters))
    parameters = [(name, [_cell(c.outcome, name) for c in compared]) for name in names]
    summary = [("samples", [_summary(c.outcome, lambda f: f"{f.data['n_samples']:,}")
                            for c in compared]),
               ("method", [_summary(c.outcome, lambda f: method_name(f.method))
                           for c in compared]),
               ("warnings", [_summary(c.outcome, lambda f: str(len(f.warnings)))
                             for c in compared])]
    errors = [f"error: {c.outcome}" for c in compared if isinstance(c.outcome, HamidError)]
    header = ("parameter", *(c.source for c in compared))
    groups = [("", [(name, *cells) for name, cells in parameters]),
              ("fit", [(name, *cells) for name, cells in summary])]
    if width is not None and formats.grid_width(header, groups) > width:
        # a row per source: the parameters and warnings; the method in the title when the
        # fits share it, else a column
        methods = {method_name(fit.method) for fit in fits}
        columns = [*parameters, *(row for row in summary if row[0] == "warnings"
                                  or row[0] == "method" and len(methods) > 1)]
        title += f", method {methods.pop()}" if len(methods) == 1 else ""
        header = ("source", *(name for name, _ in columns))
        groups = [("", [(c.source, *(cells[i] for _, cells in columns))
                        for i, c in enumerate(compared)])]
    return formats.render_grid(title, header, groups, errors, format,  # type: ignore[arg-type]
                               color=color, width=width)


def _cell(outcome: FitResult | HamidError, name: str) -> str:
    """Helper: a parameter's estimate ± its standard error in one fit, or a dash."""
    if isinstance(outcome, HamidError):
        return "error"
    found = [p for p in outcome.parameters if p.name == name]
    if not found:
        return _NULL
    p = found[0]
    if p.fixed:
        return f"{p.estimate:.6g} (fixed)"
    return f"{p.estimate:.6g} ± {_NULL if p.stderr is None else format(p.stderr, '.2g')}"


def _summary(outcome: FitResult | HamidError, show: Callable[[FitResult], str]) -> str:
    """Helper: a fit's figure, or "error"."""
    return "error" if isinstance(outcome, HamidError) else show(outcome)


def record(source: str, outcome: FitResult | HamidError) -> dict[str, Any]:
    """One line of `fit --each --format jsonl`: the report with its `source` and `status`
    ("ok"), or the source, ``"status": "error"`` and the error's message."""
    if isinstance(outcome, HamidError):
        return {"source": source, "status": "error", "error": str(outcome)}
    report = outcome.to_dict()
    return {"schema": report.pop("schema"), "source": source, "status": "ok", **report}


def parameter_rows(line: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The rows (`ROW_COLUMNS`) of one `record`: one per parameter, or one for an error."""
    if line["status"] == "error":
        return [{**dict.fromkeys(ROW_COLUMNS), "source": line["source"], "status": "error",
                 "error": line["error"]}]
    return [{"source": line["source"], "parameter": p["name"], "estimate": p["estimate"],
             "stderr": p["stderr"], "ci_low": p["ci_low"], "ci_high": p["ci_high"],
             "status": line["status"], "warnings": len(line["warnings"]), "error": None}
            for p in line["parameters"]]
