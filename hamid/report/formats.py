"""Render a fit result as a table, JSON, markdown, CSV, a summary block or HTML.

Presentation only: every number shown is already in the result dict (schema "hamid.fit/1",
docs/output.md); the only arithmetic here is the relative error against a known truth.
No file access and no checking: the caller reads and writes, and a loaded report is
checked by `FitResult.from_dict` before it gets here.
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from decimal import Decimal
from typing import Any, Literal

from hamid.errors import UsageError
from hamid.options import percent
from hamid.result.validation import SCHEMA
from hamid.result.wording import correlation_text, drift_words, method_name
from hamid.safe_text import counted, printable

__all__ = ["FORMATS", "SCHEMA", "printable", "render", "render_grid"]

ReportFormat = Literal["table", "json", "markdown", "csv", "summary", "html"]

_NULL = "—"
_MINUS = "−"
_WEIGHT_SHOWN = 0.05
_CSV_HEADER = (
    "name",
    "role",
    "estimate",
    "stderr",
    "ci_low",
    "ci_high",
    "truth",
    "relative_error",
    "fixed",
)


# --- formatting of single values ----------------------------------------------------------


def _num(value: float | None, spec: str = ".6g") -> str:
    """Helper: a number in the given format, null as an em dash."""
    return _NULL if value is None else format(value, spec)


def _percent(value: float | None) -> str:
    """Helper: a fraction as a signed percentage with 3 significant digits."""
    return _NULL if value is None else f"{100 * value:+.3g}%"


def _count(value: float) -> str:
    """Helper: a count without a spurious decimal point."""
    return str(int(value)) if float(value).is_integer() else str(value)


def _relative_error(parameter: Mapping[str, Any]) -> float | None:
    """Helper: (estimate - truth) / truth, or None when the truth is unknown or zero."""
    truth = parameter["truth"]
    if truth is None or truth == 0:
        return None
    return (parameter["estimate"] - truth) / truth


def _direction(weights: Mapping[str, float]) -> str:
    """Helper: a weighted sum of parameter names, largest weights first."""
    shown = sorted(
        ((w, name) for name, w in weights.items() if abs(w) >= _WEIGHT_SHOWN),
        key=lambda item: -abs(item[0]),
    )
    if not shown:
        return _NULL
    terms = []
    for i, (w, name) in enumerate(shown):
        sign = _MINUS if w < 0 else ("" if i == 0 else "+")
        term = f"{abs(w):.2f}·{name}"
        terms.append(f"{sign}{term}" if i == 0 else f"{sign} {term}")
    return " ".join(terms)


def _sources(sources: Sequence[object], shown: int = 3) -> str:
    """Helper: the input files, shortened when there are many."""
    names = ["standard input" if s == "-" else str(s) for s in sources]
    if len(names) > shown:
        return ", ".join(names[:shown]) + f" and {len(names) - shown} more"
    return ", ".join(names)


# --- the report as plain text blocks, shared by the table and markdown renderers -------------


@dataclass(frozen=True, slots=True)
class _Table:
    """Rows of cells under a header; each group after the first starts a new section."""

    header: tuple[str, ...]
    groups: tuple[tuple[str, tuple[tuple[str, ...], ...]], ...]
    grid: bool = False  # key-value pairs: shown without header where the format allows


@dataclass(frozen=True, slots=True)
class _Section:
    """A heading (may be empty), then lines of text, then tables."""

    heading: str
    lines: tuple[str, ...] = ()
    tables: tuple[_Table, ...] = ()
    style: str = ""


@dataclass(frozen=True, slots=True)
class _View:
    """Everything a report shows, as text."""

    title: str
    intro: tuple[str, ...]
    sections: tuple[_Section, ...]


def _parameter_row(parameter: Mapping[str, Any], with_truth: bool) -> tuple[str, ...]:
    """Helper: the cells of one parameter."""
    if parameter["fixed"]:
        name = f"{parameter['name']} (fixed)"
        spread = ("", "", "")
    else:
        name = parameter["name"]
        spread = tuple(_num(parameter[k]) for k in ("stderr", "ci_low", "ci_high"))
    row = (name, _num(parameter["estimate"]), *spread)
    if with_truth:
        row += (_num(parameter["truth"]), _percent(_relative_error(parameter)))
    return row


def _parameters_section(result: Mapping[str, Any]) -> _Section:
    """Helper: the parameters table, energy parameters first, then damping."""
    parameters = result["parameters"]
    with_truth = any(p["truth"] is not None for p in parameters)
    level = percent(result["method"]["level"])
    header = ("name", "estimate", "std. error", f"{level} CI low", f"{level} CI high")
    if with_truth:
        header += ("truth", "rel. error")
    groups = []
    for label, keep in (("", lambda r: r != "damping"), ("damping", lambda r: r == "damping")):
        rows = tuple(_parameter_row(p, with_truth) for p in parameters if keep(p["role"]))
        if rows:
            groups.append((label, rows))
    return _Section("Parameters", lines=_per_unit_mass(result),
                    tables=(_Table(header, tuple(groups)),))


def _per_unit_mass(result: Mapping[str, Any]) -> tuple[str, ...]:
    """Helper: a line saying the parameters are per unit mass, when they are (reports of
    earlier versions do not say)."""
    if not (result["method"].get("scale") or {}).get("per_unit_mass"):
        return ()
    return ("parameters per unit mass (or moment of inertia): the energy's kinetic part has "
            "no parameter",)


def _energy_levels_section(result: Mapping[str, Any]) -> _Section:
    """Helper: one row per trajectory's fitted energy level."""
    rows = tuple(
        (
            str(level["trajectory"]),
            _num(level["h"]),
            _num(level["stderr"]),
            _count(level["n_samples"]),
        )
        for level in result["energy_levels"]
    )
    header = ("trajectory", "h", "std. error", "samples")
    return _Section("Energy levels", tables=(_Table(header, (("", rows),)),))


def _residuals_section(result: Mapping[str, Any]) -> _Section:
    """Helper: residual statistics, then the energy drift of each trajectory."""
    residuals = result["residuals"]
    stats = (
        ("rms", _num(residuals["rms"], ".4g")),
        ("max |r|", _num(residuals["max_abs"], ".4g")),
        ("relative rms", _num(residuals["relative_rms"], ".4g")),
        ("R²", _num(residuals["r_squared"], ".6g")),
        ("lag-1 autocorrelation", _num(residuals["lag1_autocorrelation"], ".3g")),
    )
    tables = [_Table(("statistic", "value"), (("", stats),), grid=True)]
    driven = bool(result["data"].get("inputs"))
    drift = tuple((str(d["trajectory"]), _NULL if d["relative_change"] is None else
                   drift_words(d["relative_change"], driven=driven))
                  for d in residuals["drift"])
    if drift:
        tables.append(_Table(("trajectory", "energy over the record (a straight line through it)"),
                             (("", drift),)))
    return _Section("Residuals", tables=tuple(tables))


def _dissipation_section(result: Mapping[str, Any]) -> _Section | None:
    """Helper: energy lost per trajectory, then each mode's natural frequency (Hz) and
    damping ratio at small amplitude, from the model linearized about its equilibrium
    (reports of earlier versions: their damping ratio at the recording's dominant
    period, said so)."""
    dissipation = result.get("dissipation")
    if not dissipation:
        return None
    rows = tuple((str(d["trajectory"]), _percent(d["energy_lost_fraction"]))
                 for d in dissipation["trajectories"])
    tables = [_Table(("trajectory", "energy lost"), (("", rows),))]
    lines: tuple[str, ...] = ()
    limit = dissipation.get("small_amplitude")
    if limit:
        about = ", ".join(f"{q} = {_num(x, '.6g')}" for q, x in limit["equilibrium"].items())
        lines = (f"at small amplitude: the model linearized about {about} (against "
                 "amplitude: hamid backbone)",)
        tables.append(_Table(("mode", "natural frequency (Hz)", "damping ratio ζ"), (("", tuple(
            (str(m["mode"]), _num(m["frequency_hz"], ".6g"), _num(m["damping_ratio"], ".4g"))
            for m in limit["modes"])),)))
    elif dissipation.get("equivalent_damping_ratio") is not None:
        tables.append(_Table(("quantity", "value"), (("", (
            ("equivalent damping ratio ζ", _num(dissipation["equivalent_damping_ratio"],
                                                ".4g")),
            ("at the dominant period", f"{_num(dissipation['period'], '.4g')} s"),
        )),), True))
    return _Section("Dissipation", lines=lines, tables=tuple(tables))


def _conditioning_section(result: Mapping[str, Any]) -> _Section:
    """Helper: condition number, its verdict, the worst-determined combination and the
    strongest correlation among the estimates (absent from older reports)."""
    conditioning = result["conditioning"]
    rows = (
        ("condition number", _num(conditioning["condition_number"], ".4g")),
        ("status", conditioning["status"]),
        ("weakest direction", _direction(conditioning["weakest_direction"])),
    )
    strongest = conditioning.get("strongest_correlation")
    if strongest:
        rows += (("strongest correlation", f"{' and '.join(strongest['parameters'])} "
                  f"{correlation_text(strongest['correlation']).replace('-', _MINUS)}"),)
    return _Section("Conditioning", tables=(_Table(("quantity", "value"), (("", rows),), True),))


_LENGTHENING_STOPPED = {
    "longest": "the longest integrated at once",
    "misfit": "longer ones missed the recording beyond the noise",
    "failed": "longer ones could not be fitted",
    "unstable": "the motion too unstable over longer ones for their errors to hold"}


def _refinement_checks(refinement: Mapping[str, Any]) -> list[tuple[str, str]]:
    """Helper: the refinement's noise levels when raised from its residuals and its held-out
    check against the linear fit (reports of older versions have neither)."""
    rows = []
    noise = refinement.get("noise") or {}
    raised = [f"{name} {_num(entry['sigma'], '.3g')}" for name, entry in noise.items()
              if entry["source"] == "residuals"]
    if raised:
        rows.append(("refinement noise σ", f"{', '.join(raised)} from its residuals "
                     f"(misfit {_num(refinement.get('noise_chi2_per_dof'), '.3g')} × the noise "
                     "estimated from differences)"))
    acceptance = refinement.get("acceptance") or {}
    if acceptance.get("rule") == "held-out":
        rows.append(("held-out check", f"misfit {_num(acceptance['held_out_refined'], '.4g')}"
                     f" against {_num(acceptance['held_out_linear'], '.4g')} of the linear "
                     f"fit over {counted(acceptance['folds'], 'fold', 'folds')}, t = "
                     f"{_num(acceptance['t'], '.3g')} (refused above "
                     f"{_num(acceptance['t_limit'], '.3g')})"))
    return rows


def _refinement_rows(refinement: Mapping[str, Any] | None) -> list[tuple[str, str]]:
    """Helper: the fit the refined numbers come from (its segments, the whole record when
    lengthened to it), then the first fit's segments when they were lengthened; or why the
    refinement was not kept."""
    if not refinement:
        return []
    if not refinement["applied"]:
        return [("refinement", f"none: {refinement['reason']}")]

    def fit(last: Mapping[str, Any], span: str) -> str:
        return (f"{span}, misfit {_num(last['chi2_per_dof'])} × noise variance, "
                f"{counted(last['iterations'], 'iteration', 'iterations')}")

    first = fit(refinement, f"{counted(refinement['segments'], 'segment', 'segments')} of "
                            f"{_num(refinement['segment_seconds'])} s")
    lengthening = refinement.get("lengthening")
    if not (lengthening and lengthening["rounds"]):
        return [("refinement", f"trajectory fit over {first}")]
    segments, seconds = lengthening["segments"], _num(lengthening["segment_seconds"])
    if lengthening["stopped"] != "whole":
        span = (f"{counted(segments, 'segment', 'segments')} of up to {seconds} s "
                f"({_LENGTHENING_STOPPED[lengthening['stopped']]})")
    elif segments == 1:
        span = f"the whole record, {seconds} s"
    else:
        span = f"each whole trajectory ({segments}, up to {seconds} s)"
    return [("refinement", f"trajectory fit over {fit(lengthening, span)}"),
            ("lengthened from", first)]


def _method_section(result: Mapping[str, Any]) -> _Section:
    """Helper: how the fit was made."""
    method = result["method"]
    refinement = method.get("refinement")
    covariance = method["covariance"]
    if refinement and refinement["applied"]:
        covariance = ("sandwich over the segments of the trajectory fit"
                      if refinement.get("covariance") == "sandwich"
                      else "Gauss-Newton of the trajectory fit")
    rows = [
        ("covariance", f"{covariance}, {percent(method['level'])} intervals"),
        ("weighting", method["weighting"]),
    ]
    if method["noise"]:
        noise = ", ".join(f"{col} {_num(sigma)}" for col, sigma in method["noise"].items())
        rows.append(("noise σ", noise))
        if method.get("weighting_rounds"):
            rows.append(("weighting rounds", str(method["weighting_rounds"])))
    rows.append(("bias correction", "yes" if method["bias_correction"] else "no"))
    if method["weak_window"] is not None:
        rows.append(("weak window", f"{_num(method['weak_window'])} s"))
    rows += _refinement_rows(refinement)
    rows += _refinement_checks(refinement or {})
    own = (result["model"].get("dissipation") or {}).get("function")
    rows.append(("damping", ", ".join([*([f"R = {own}"] if own else []), *method["damping"]])
                 or "none"))
    fixed = ", ".join(f"{name} = {_num(value)}" for name, value in method["fixed"].items())
    rows.append(("fixed", fixed or "none"))
    rows += _scale_rows(method.get("scale"), result["data"])
    rows.append(("hamid version", result["hamid_version"]))
    return _Section("Method", tables=(_Table(("setting", "value"), (("", tuple(rows)),), True),))


def _scale_rows(scale: Mapping[str, Any] | None, data: Mapping[str, Any]
                ) -> list[tuple[str, str]]:
    """Helper: where the energy's scale comes from, and a driven fit's inputs."""
    rows = []
    if scale:
        rows.append(("scale", {
            "input": f"from the recorded input (work {scale['by']}): physical units",
            "fixed": f"from the fixed {scale['by']}",
            "energy": "from the energy's parameter-free part (parameters per unit of it)",
        }[scale["source"]]))
    forcing = data.get("forcing")
    if forcing:
        columns = ", ".join(f"{name} (column {column})"
                            for name, column in (data.get("inputs") or {}).items())
        fraction = forcing["input_work_fraction"]
        rows.append(("inputs", f"{columns}; work {forcing['work']}"
                     + ("" if fraction is None else
                        f", {_num(100 * fraction, '.3g')}% of the energy budget")))
    return rows


def _data_line(data: Mapping[str, Any]) -> str:
    """Helper: one line on the samples, their files and where velocities came from."""
    text = (
        f"data: {counted(data['n_samples'], 'sample', 'samples')} in "
        f"{counted(data['n_trajectories'], 'trajectory', 'trajectories')}"
    )
    if data["sources"]:
        text += f" from {_sources(data['sources'])}"
    channels = data.get("channels")
    if channels:   # what each coordinate recorded, and what was reconstructed from it
        text += "; recorded " + ", ".join(
            f"{name}: {' + '.join(kinds['recorded'])}"
            + (f" ({' + '.join(kinds['reconstructed'])} reconstructed"
               + ("; its velocity column set aside" if kinds.get("set_aside") else "") + ")"
               if kinds["reconstructed"] else "") for name, kinds in channels.items())
    elif data["velocity_source"] == "savgol":
        text += "; velocities derived from positions (Savitzky-Golay)"
    else:
        text += f"; velocities {data['velocity_source']}"
    renamed = [f"{name}={col}" for name, col in data["columns"].items() if name != col]
    if renamed:
        text += f"; columns {', '.join(renamed)}"
    time, unit = data.get("time"), data.get("time_unit")
    if time and (time.lower() not in ("t", "time") or unit not in (None, "s")):
        # the usual t in seconds goes without saying
        text += f"; time {time}" + (f" ({unit})" if unit else "")
    # the time column's factor is the unit just shown
    factors = [f"{col} × {_num(factor)}" for col, factor in (data.get("scale") or {}).items()
               if not (col == time and unit)]
    if factors:
        text += f"; scaled {', '.join(factors)}"
    return text


def _skipped_lines(result: Mapping[str, Any]) -> tuple[str, ...]:
    """Helper: a line for each check the fit skipped (`checks_skipped`), and why."""
    return tuple(f"skipped: {skip['check']}: {skip['reason']}"
                 for skip in result.get("checks_skipped", ()))


def _view(result: Mapping[str, Any]) -> _View:
    """Helper: the report's content, in order, as text."""
    method = result["method"]
    title = f"hamid fit — {result['model']['name']}, method {method_name(method)}"
    if method["kind_reason"]:
        title += f" ({method['kind_reason']})"
    warnings = (*(f"warning: {w}" for w in result["warnings"]),
                *_skipped_lines(result))
    sections = tuple(section for section in (
        _parameters_section(result),
        _energy_levels_section(result),
        _dissipation_section(result),
        _residuals_section(result),
        _conditioning_section(result),
        _method_section(result),
    ) if section is not None)
    if warnings:
        sections += (_Section("", lines=warnings, style="yellow"),)
    return _printable_view(_View(title, (_data_line(result["data"]),), sections))


def _printable_view(view: _View) -> _View:
    """Helper: the view with the control characters of every text escaped.

    Names, labels, file names and warnings come from data files and saved reports; a
    terminal showing the table, or the markdown file, must not obey what they hold.
    """

    def table(spec: _Table) -> _Table:
        groups = tuple((printable(label), tuple(tuple(map(printable, row)) for row in rows))
                       for label, rows in spec.groups)
        return replace(spec, header=tuple(map(printable, spec.header)), groups=groups)

    def section(part: _Section) -> _Section:
        return replace(part, heading=printable(part.heading),
                       lines=tuple(map(printable, part.lines)),
                       tables=tuple(map(table, part.tables)))

    return _View(printable(view.title), tuple(map(printable, view.intro)),
                 tuple(map(section, view.sections)))


# --- renderers ---------------------------------------------------------------------------


def _render_json(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: the result as indented JSON, keys in the dict's order.

    ASCII only: every other character is written as a \\u escape, so control characters in
    names and warnings (C1 ones included, which ensure_ascii=False would write raw) reach
    no terminal, and a reader gets the text back exactly.
    """
    return json.dumps(result, indent=2, allow_nan=False, ensure_ascii=True) + "\n"


def _csv_cell(value: object) -> str:
    """Helper: a CSV cell: full-precision repr for numbers, empty for null."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, int | float) else str(value)


def _render_csv(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: one CSV row per parameter.

    CSV is data: names are written exactly as they are (quoted where CSV needs it). The
    command line escapes control characters only when the CSV goes to a terminal.
    """
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(_CSV_HEADER)
    for p in result["parameters"]:
        values = {**p, "relative_error": _relative_error(p)}
        writer.writerow(_csv_cell(values[key]) for key in _CSV_HEADER)
    return buffer.getvalue()


def _markdown_cell(text: str) -> str:
    """Helper: text safe inside a markdown table cell."""
    return text.replace("|", "\\|").replace("\n", " ")


def _markdown_table(table: _Table) -> list[str]:
    """Helper: a GitHub markdown table; later groups start with an italic label row."""
    width = len(table.header)
    lines = [
        "| " + " | ".join(_markdown_cell(h) for h in table.header) + " |",
        "|" + "---|" * width,
    ]
    for label, rows in table.groups:
        if label:
            lines.append("| " + " | ".join([f"*{label}*"] + [""] * (width - 1)) + " |")
        lines.extend("| " + " | ".join(_markdown_cell(c) for c in row) + " |" for row in rows)
    return lines


def _render_markdown(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: the report as GitHub markdown."""
    return _markdown_text(_view(result))


def _markdown_text(view: _View, *, color: bool = False, width: int | None = None) -> str:
    """Helper: a view as GitHub markdown."""
    blocks = [f"**{view.title}**", *view.intro]
    for section in view.sections:
        if section.heading:
            blocks.append(f"## {section.heading}")
        if section.lines:
            blocks.append("\n".join(f"- {line}" for line in section.lines))
        blocks.extend("\n".join(_markdown_table(t)) for t in section.tables)
    return "\n\n".join(blocks) + "\n"


def _rich_table(spec: _Table, width: int) -> Any:
    """Helper: a rich Table of the given text table, header wrapped by hand when narrow."""
    from rich import box
    from rich.table import Table
    from rich.text import Text

    if spec.grid:
        table = Table.grid(padding=(0, 3))
        for _ in spec.header:
            table.add_column(overflow="fold")
    else:
        header = spec.header
        rows = [row for _, group in spec.groups for row in group]
        columns = [[len(name), *(len(row[i]) for row in rows)] for i, name in enumerate(header)]
        # Rich shrinks the widest columns first and would fold numbers before it wraps a
        # header; splitting the headers over two lines keeps whole numbers on one line.
        if sum(max(c) for c in columns) + 2 * (len(header) - 1) > width:
            header = tuple("\n".join(name.rsplit(" ", 1)) for name in header)
        table = Table(
            box=box.SIMPLE_HEAD,
            show_edge=False,
            pad_edge=False,
            collapse_padding=True,
            header_style="bold",
        )
        for i, name in enumerate(header):
            table.add_column(name, justify="left" if i == 0 else "right", overflow="fold")
    for label, group in spec.groups:
        if label:
            table.add_section()
            table.add_row(Text(label, style="italic"))
        for row in group:
            table.add_row(*(Text(cell) for cell in row))
    return table


def _render_table(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: the report as text tables drawn by rich."""
    return _table_text(_view(result), color=color, width=width)


def _table_text(view: _View, *, color: bool, width: int | None) -> str:
    """Helper: a view as text tables drawn by rich."""
    from rich.console import Console
    from rich.text import Text

    buffer = io.StringIO()
    # Text objects throughout and markup/emoji off: names like "k[1]" are not rich markup.
    console = Console(
        file=buffer,
        width=width or 100,
        color_system="standard" if color else None,
        force_terminal=color,
        highlight=False,
        markup=False,
        emoji=False,
    )
    console.print(Text(view.title, style="bold"))
    for line in view.intro:
        console.print(Text(line))
    for section in view.sections:
        console.print()
        if section.heading:
            console.print(Text(section.heading, style="bold underline"))
        for line in section.lines:
            console.print(Text(line, style=section.style))
        for i, spec in enumerate(section.tables):
            if i:
                console.print()
            console.print(_rich_table(spec, console.width))
    # Rich pads lines to the table width; trailing blanks only get in the way of diffs.
    return "\n".join(line.rstrip() for line in buffer.getvalue().splitlines()) + "\n"


def _text_table(spec: _Table, width: int) -> list[str]:
    """Helper: a table as aligned plain text under a rule, later groups after a label."""
    rows = [spec.header, *(row for _, group in spec.groups for row in group)]
    widths = [max(len(row[i]) for row in rows if i < len(row)) for i in range(len(spec.header))]

    def line(row: Sequence[str]) -> str:
        cells = [cell.ljust(w) if i == 0 else cell.rjust(w)
                 for i, (cell, w) in enumerate(zip(row, widths, strict=False))]
        return "  ".join(cells).rstrip()

    lines = [] if spec.grid else [line(spec.header), "-" * width]
    for label, group in spec.groups:
        if label:
            lines.append(label)
        lines.extend(line(row) for row in group)
    return lines


def _render_summary(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: a block in the style of statsmodels' `summary()`: key facts in two columns,
    the parameters and levels under double rules, then numbered notes and warnings."""
    import textwrap

    width = width or 78
    view = _view(result)
    method, residuals = result["method"], result["residuals"]
    refined = bool((method.get("refinement") or {}).get("applied"))
    conditioning = result["conditioning"]
    facts = [
        ("Model:", result["model"]["name"]),
        ("Samples:", _count(result["data"]["n_samples"])),
        ("Method:", method_name(method)),
        ("Trajectories:", _count(result["data"]["n_trajectories"])),
        ("Covariance:", "Gauss-Newton" if refined else method["covariance"]),
        ("Residual rms:", _num(residuals["rms"], ".4g")),
        ("Level:", percent(method["level"])),
        ("R²:", _num(residuals["r_squared"], ".6g")),
        ("Condition:", f"{_num(conditioning['condition_number'], '.4g')} "
                       f"({conditioning['status']})"),
        ("Lag-1 autocorr.:", _num(residuals["lag1_autocorrelation"], ".3g")),
    ]
    half = (width - 2) // 2
    cells = [printable(f"{key}{value.rjust(half - len(key))}") for key, value in facts]
    title = printable(f"hamid fit — {result['model']['name']}")
    lines = [title.center(width).rstrip(), "=" * width]
    lines += ["  ".join(cells[i:i + 2]) for i in range(0, len(cells), 2)]
    # statsmodels' short headers: the bounds as quantiles, [2.5% 97.5%]
    level = Decimal(repr(float(method["level"])))
    short = {"std. error": "std err", "rel. error": "rel err",
             f"{percent(level)} CI low": f"[{percent((1 - level) / 2)}",
             f"{percent(level)} CI high": f"{percent((1 + level) / 2)}]"}
    shown = {"Parameters", "Energy levels", "Dissipation"}
    for section in view.sections:
        for table in section.tables if section.heading in shown else ():
            table = replace(table, header=tuple(short.get(h, h) for h in table.header))
            lines += ["=" * width, *_text_table(table, width)]
    lines.append("=" * width)
    notes = [f"method {method['kind']}: {method['kind_reason']}",
             method.get("covariance_description") or "", *result["warnings"],
             *_skipped_lines(result), *_per_unit_mass(result),
             *(line for section in view.sections if section.heading == "Dissipation"
               for line in section.lines)]
    notes = [printable(note) for note in notes if note]
    lines += ["Notes:", *(textwrap.fill(f"[{i}] {note}", width, subsequent_indent="    ")
                          for i, note in enumerate(notes, 1))]
    return "\n".join(lines) + "\n"


def _html_table(spec: _Table) -> str:
    """Helper: a table as HTML; a later group's label spans a row of its own."""
    from html import escape

    head = "" if spec.grid else \
        "<thead><tr>" + "".join(f"<th>{escape(h)}</th>" for h in spec.header) + "</tr></thead>"
    body = []
    for label, group in spec.groups:
        if label:
            body.append(f'<tr><td colspan="{len(spec.header)}"><i>{escape(label)}</i></td></tr>')
        body += ["<tr>" + "".join(f"<td>{escape(cell)}</td>" for cell in row) + "</tr>"
                 for row in group]
    return f"<table>{head}<tbody>{''.join(body)}</tbody></table>"


def _render_html(result: Mapping[str, Any], *, color: bool, width: int | None) -> str:
    """Helper: the report as HTML tables, for a notebook's rich display."""
    from html import escape

    view = _view(result)
    parts = [f"<p><b>{escape(view.title)}</b></p>", *(f"<p>{escape(line)}</p>"
                                                     for line in view.intro)]
    for section in view.sections:
        if section.heading:
            parts.append(f"<h4>{escape(section.heading)}</h4>")
        if section.lines:
            parts.append("<ul>" + "".join(f"<li>{escape(line)}</li>" for line in section.lines)
                         + "</ul>")
        parts += [_html_table(table) for table in section.tables]
    return '<div class="hamid-fit">' + "\n".join(parts) + "</div>\n"


_RENDERERS: dict[str, Callable[..., str]] = {
    "table": _render_table,
    "json": _render_json,
    "markdown": _render_markdown,
    "csv": _render_csv,
}

FORMATS: tuple[str, ...] = tuple(_RENDERERS)   # those of `hamid fit` and `hamid report`
# Python's own: `FitResult.summary()` and a notebook's display of a result
_PYTHON_RENDERERS: dict[str, Callable[..., str]] = {"summary": _render_summary,
                                                    "html": _render_html}


Grid = Sequence[tuple[str, Sequence[Sequence[str]]]]


def grid_width(header: Sequence[str], groups: Grid) -> int:
    """The width a table of these cells takes when no column folds (`render_grid`)."""
    rows = [row for _, group in groups for row in group]
    return sum(max(len(printable(cell)) for cell in column) + 3
               for column in zip(header, *rows, strict=True))


def render_grid(title: str, header: Sequence[str], groups: Grid, lines: Sequence[str],
                format: Literal["table", "markdown"], *, color: bool = False,
                width: int | None = None) -> str:
    """Render one table under a title, then lines of text (e.g. errors), as the report's
    table or markdown; for tables of several fits (`hamid.report.comparison`).

    `groups` are (label, rows); each group after the first starts a section under its
    label. The table is as wide as its cells (a column per fit does not fold), or at most
    `width` when given: text wrapped and columns folded to fit.
    """
    table = _Table(tuple(header), tuple((label, tuple(map(tuple, rows)))
                                        for label, rows in groups))
    sections = (_Section("", tables=(table,)),
                *([_Section("", lines=tuple(lines), style="yellow")] if lines else []))
    view = _printable_view(_View(title, (), sections))
    text = {"table": _table_text, "markdown": _markdown_text}[format]
    return text(view, color=color, width=width or max(100, grid_width(header, groups)))


def render(
    result: dict,
    format: ReportFormat,
    *,
    color: bool = False,
    width: int | None = None,
) -> str:
    """Render a fit result as text.

    Parameters
    ----------
    result : dict
        A fit result of schema "hamid.fit/1": `FitResult.to_dict()` (a loaded JSON report
        goes through `FitResult.from_dict` first, which checks it).
    format : {"table", "json", "markdown", "csv", "summary", "html"}
        "table" is for a terminal; "json" is the result itself; "markdown" for notes and
        issues; "csv" has one row per parameter; "summary" is plain text in the style of
        statsmodels (`FitResult.summary()`); "html" is a notebook's display of the result.
    color : bool, optional
        Use terminal colors (table only).
    width : int, optional
        Line width of the table (100 when not given) or the summary (78).

    Returns
    -------
    str
        The rendered text, ending with a newline.

    Examples
    --------
    >>> text = render(result, "markdown")  # doctest: +SKIP
    """
    renderer = _RENDERERS.get(format) or _PYTHON_RENDERERS.get(format)
    if renderer is None:
        raise UsageError(f"unknown report format {format!r} (choose from "
                         f"{', '.join([*FORMATS, *_PYTHON_RENDERERS])})")
    return renderer(result, color=color, width=width)
