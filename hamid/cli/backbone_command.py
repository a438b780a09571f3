"""`hamid backbone`: the backbone of a saved report's model, with bands, beside the
recording's points (`hamid.backbone`)."""

from __future__ import annotations

import math
import os
from typing import Any

import click

from hamid.cli import console, option_groups
from hamid.errors import UsageError

__all__ = ["backbone"]

# The outputs an extension of -o chooses (a figure by .png, .svg or .pdf).
_FIGURES = (".png", ".svg", ".pdf")


def _numbers(option: str, text: str | None) -> tuple[float, ...] | None:
    """Comma-separated finite numbers, or a one-line usage error naming the option."""
    if text is None:
        return None
    try:
        values = tuple(float(item) for item in text.split(","))
    except ValueError:
        values = ()
    if not values or not all(math.isfinite(v) for v in values):
        shown = text if len(text) <= 40 else text[:40] + "..."
        raise UsageError(f"{option} {shown!r}: expected numbers separated by commas, "
                         "e.g. 0.1,0.5,1")
    return values


@click.command(cls=option_groups.GroupedCommand)
@click.argument("result_file", metavar="RESULT.json")
@click.argument("data", nargs=-1)
@click.option("--amplitudes", metavar="A1,A2,...",
              help="Amplitudes (half the peak-to-peak range of the coordinate) to compute at; "
                   "default: --points of them up to the largest recorded.")
@click.option("--energies", metavar="E1,E2,...",
              help="Levels of the model's energy (as the report's levels) to compute at.")
@click.option("--mode", type=int, default=1, show_default=True, help="The mode (1-based).")
@click.option("--coordinate", metavar="Q", help="The coordinate amplitudes are given for "
                                                "(default: the mode's leading one).")
@click.option("--points", type=click.IntRange(2, 10_000), default=25, show_default=True,
              help="How many default amplitudes.")
@click.option("--format", "fmt", type=click.Choice(["table", "json", "csv"]),
              help="Output: text (table), the hamid.backbone/1 report (json) or the curve's "
                   "rows (csv); default from -o's extension, else table.")
@click.option("-o", "--output", default="-", metavar="OUT",
              help="Write the output here: .json, .csv, .txt, or a figure (.png, .svg, .pdf).")
@option_groups.reading
def backbone(result_file: str, data: tuple[str, ...], amplitudes: str | None,
             energies: str | None, mode: int, coordinate: str | None, points: int,
             fmt: str | None, output: str, **reading: Any) -> None:
    """The backbone of the fitted model of RESULT.json: frequency (Hz) and equivalent damping
    ratio against amplitude, with bands at the fit's level; with DATA (read as the fit read
    its data unless reading options are given), the recording's own points."""
    from hamid import prediction
    from hamid.backbone import backbone_table
    from hamid.data import documents, readers, writing
    from hamid.plot import backbone_figure, figures
    from hamid.result.fit_result import FitResult

    if amplitudes is not None and energies is not None:
        raise UsageError("give --amplitudes or --energies, not both")
    request = backbone_table.Request(amplitudes=_numbers("--amplitudes", amplitudes),
                                     energies=_numbers("--energies", energies), mode=mode,
                                     coordinate=coordinate, points=points)
    outputs = click.get_current_context().with_resource(writing.Outputs([result_file, *data]))
    outputs.claim("-o", output)
    figure = os.path.splitext(output)[1].lower() in _FIGURES
    if figure:
        figures.check_output(output)
    fmt = fmt or ("json" if figure else console.format_of(
        output, ".json, .csv, .txt, or a figure's .png, .svg, .pdf"))
    source = readers.STDIN if readers.is_stdio(result_file) else result_file
    report = FitResult.from_dict(documents.read_json(result_file), source=source).to_dict()
    records = (prediction.read(report, list(data), option_groups.fit_keywords(reading)).records
               if data else None)
    with console.Status("computing the backbone"):
        document = backbone_table.backbone_report(backbone_table.Source.of_report(report),
                                                  request, records=records, names=data)
    for mode in document["modes"]:
        if mode.get("stopped"):
            click.echo(console.printable(f"note: the default levels end short of "
                                         f"{mode['stopped']}"), err=True)
    for note in document["notes"]:
        click.echo(console.printable(f"note: {note}"), err=True)
    if figure:
        figures.write_pages([("backbone", backbone_figure.figure(document))], output)
        return
    writing.write_text(backbone_table.render(document, fmt), output)
