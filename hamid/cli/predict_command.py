"""`hamid predict`: the fitted model of a saved report over a recording, beside it
(`hamid.prediction`)."""

from __future__ import annotations

import os
from typing import Any

import click

from hamid.cli import console, option_groups

__all__ = ["predict"]

# The output formats an extension of -o chooses.


@click.command(cls=option_groups.GroupedCommand)
@click.argument("result_file", metavar="RESULT.json")
@click.argument("data", nargs=-1, required=True)
@click.option("--from-rest", is_flag=True,
              help="Start every trajectory at rest (zero state) instead of the state fitted "
                   "to its first period.")
@click.option("--format", "fmt", type=click.Choice(["table", "json", "csv"]),
              help="Output: the errors per channel (table), the report (json) or the time "
                   "series recorded and predicted (csv); default from -o's extension (.json, "
                   ".csv, .txt), else table.")
@click.option("-o", "--output", default="-", metavar="OUT", help="Write the output here.")
@option_groups.reading
def predict(result_file: str, data: tuple[str, ...], from_rest: bool, fmt: str | None,
            output: str, **reading: Any) -> None:
    """Integrate the fitted model of RESULT.json over each trajectory of DATA, from its
    fitted start state, and give the RMS error and NRMSE of every channel. DATA is read as
    the fit read its data (the report's reading options) unless reading options are given."""
    from hamid import prediction
    from hamid.data import destinations, documents, readers, writing
    from hamid.result.fit_result import FitResult

    outputs = click.get_current_context().with_resource(writing.Outputs([result_file, *data]))
    outputs.claim("-o", output)
    fmt = fmt or console.format_of(output)
    source = readers.STDIN if readers.is_stdio(result_file) else result_file
    report = FitResult.from_dict(documents.read_json(result_file), source=source).to_dict()
    with console.Status("predicting"):
        predicted = prediction.predict(report, list(data), option_groups.fit_keywords(reading),
                                       from_rest=from_rest, source=source)
    to_terminal = destinations.is_terminal(output)
    text = predicted.render(fmt, color=to_terminal and "NO_COLOR" not in os.environ)
    writing.write_text(console.printable_lines(text) if fmt == "csv" and to_terminal else text,
                       output)
