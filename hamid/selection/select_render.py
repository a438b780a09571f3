"""Render a selection report (schema "hamid.select/1", docs/output.md) as a table or JSON.

Presentation only: every number shown is in the report; the refit is rendered by
`hamid.report.formats` as any fit is.
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping, Sequence
from typing import Any

from hamid import safe_text
from hamid.errors import UsageError
from hamid.report import formats

__all__ = ["FORMATS", "render"]

FORMATS = ("table", "json")


def render(document: Mapping[str, Any], format: str, *, color: bool = False,
           width: int | None = None) -> str:
    """A selection report as text.

    Parameters
    ----------
    document : dict
        A report of schema "hamid.select/1" (`Selection.to_dict()`).
    format : {"table", "json"}
        "table" is for a terminal: the chosen terms, the candidate models, the inclusion
        probabilities, then the refit's report; "json" is the report itself.
    color : bool, optional
        Use terminal colors (table only).
    width : int, optional
        Line width of the table; 100 when not given.
    """
    if format == "json":
        return json.dumps(document, indent=2, allow_nan=False, ensure_ascii=True) + "\n"
    if format != "table":
        raise UsageError(f"unknown select format {format!r} (choose from {', '.join(FORMATS)})")
    return _table(document, color, width or 100)


def _number(value: float | None) -> str:
    return "—" if value is None else f"{value:.6g}"


def _terms(terms: Sequence[str]) -> str:
    """Library terms as a list; "(none)" for a model of no library term (the energy's
    parameter-free part alone, with the damping that every candidate has)."""
    return ", ".join(terms) or "(none)"


def _table(doc: Mapping[str, Any], color: bool, width: int) -> str:
    from rich import box
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    buffer = io.StringIO()
    console = Console(file=buffer, width=width, color_system="standard" if color else None,
                      force_terminal=color, highlight=False, markup=False, emoji=False)

    def line(text: str, style: str = "") -> None:
        console.print(Text(safe_text.printable(text), style=style))

    def table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int) -> None:
        shown = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False,
                      collapse_padding=True, header_style="bold")
        for i, name in enumerate(header):
            shown.add_column(name, justify="left" if i < left else "right", overflow="fold")
        for row in rows:
            shown.add_row(*(Text(safe_text.printable(cell)) for cell in row))
        console.print(shown)

    library, rows = doc["library"], doc["rows"]
    line(f"hamid select — library {library['name']} ({len(library['terms'])} terms), "
         f"criterion {doc['criterion']}, {doc['search']} search over "
         f"{rows['subsets_scored']:,} subsets", "bold")
    line(f"rows: {rows['kind']}, {rows['n_rows']} ({rows['effective_rows']:.0f} effective)"
         + (f"; always in: {', '.join(doc['kept'])}" if doc["kept"] else ""))
    console.print()
    line("Chosen terms", "bold underline")
    line(_terms(doc["chosen"]))
    console.print()
    line("Candidate models", "bold underline")
    table(("rank", "terms", doc["criterion"], "Δ", "residual variance"),
          [(f"{i + 1}{' *' if c['chosen'] else ''}", _terms(c["terms"]),
            _number(c["criterion"]), _number(c["delta"]), _number(c["residual_variance"]))
           for i, c in enumerate(doc["candidates"])], 2)
    line(f"* chosen: {doc['rule']}; residual variance relative to the whole library's")
    if doc["inclusion"] is not None:
        console.print()
        stability = doc["stability"]
        line(f"Inclusion probabilities ({stability['replicates']} moving-block bootstrap "
             f"replicates, seed {stability['seed']})", "bold underline")
        table(("term", "probability"),
              [(term, f"{p:.2f}") for term, p in doc["inclusion"].items()], 1)
    for warning in doc["warnings"]:
        line(f"warning: {warning}", "yellow")
    console.print()
    line("Refit of the chosen model", "bold underline")
    line(f"Its intervals are {doc['intervals']}.")
    text = "\n".join(row.rstrip() for row in buffer.getvalue().splitlines()) + "\n"
    return text + formats.render(doc["fit"], "table", color=color, width=width)
