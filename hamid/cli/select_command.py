"""`hamid select`: which terms of a library the energy of the data has
(`hamid.selection.select_terms`)."""

from __future__ import annotations

import os
from typing import Any

import click

from hamid.cli import console, option_groups
from hamid.errors import UsageError
from hamid.options import SELECTION_CRITERIA

__all__ = ["select"]


@click.command(cls=option_groups.GroupedCommand)
@click.argument("data", nargs=-1, required=True)
@click.option("--library", metavar="poly:N:D|MODEL.toml",
              help="Candidate terms: monomials of degree 2..D, or each parameter's term of "
                   "a model file (default poly:N:4 over the data's coordinates).")
@click.option("--keep", metavar="TERM,...", help="Terms always in (u1**2, or a parameter).")
@click.option("--criterion", default="bic", show_default=True,
              type=click.Choice(SELECTION_CRITERIA), help="How candidate models are scored.")
@click.option("--stability", default=0, type=click.IntRange(min=0), metavar="N",
              help="Inclusion probabilities from N moving-block bootstrap replicates.")
@click.option("--seed", type=click.IntRange(min=0),
              help="Seed of the --stability replicates (default 0).")
@click.option("--damping", default="none", show_default=True,
              metavar="none|viscous|coulomb|quadratic[,...]",
              help="Dissipative forces, always in the model.")
@click.option("--write-model", metavar="FILE.toml", help="Write the chosen model here.")
@click.option("--format", "fmt", type=click.Choice(["table", "json"]),
              help="Report format (default: json for -o *.json, else table).")
@click.option("-o", "--output", default="-", metavar="FILE", help="Write the report here.")
@option_groups.reading
@option_groups.velocities
def select(data: tuple[str, ...], library: str | None, keep: str | None, criterion: str,
           stability: int, seed: int | None, damping: str, write_model: str | None,
           fmt: str | None, output: str, **options: Any) -> None:
    """Choose the terms of the energy of DATA from a library, and refit the chosen model."""
    from hamid.data import destinations, writing
    from hamid.selection import select_render
    from hamid.selection.select_terms import select as run_select

    if seed is not None and not stability:
        raise click.UsageError("--seed applies only to --stability")
    outputs = click.get_current_context().with_resource(writing.Outputs(
        [*data, *([library] if library is not None and os.path.isfile(library) else [])]))
    outputs.claim("-o", output)
    if write_model is not None:
        if not write_model.endswith(".toml"):
            raise UsageError(f"--write-model {write_model!r}: give a FILE.toml (hamid fit "
                             "--model reads model files by that extension)")
        outputs.claim("--write-model", write_model)
    with console.Status("selecting") as status:
        chosen = run_select(list(data), library, keep=(keep or "").split(",") if keep else (),
                            criterion=criterion, stability=stability, seed=seed or 0,
                            damping=damping, progress=status,
                            **option_groups.fit_keywords(options))
    document = chosen.to_dict()
    fmt = fmt or ("json" if output.lower().endswith(".json") else "table")
    text = select_render.render(document, fmt, color=destinations.is_terminal(output)
                                and "NO_COLOR" not in os.environ)
    with writing.all_or_nothing():
        if write_model is not None:
            writing.write_text(chosen.model_file(), write_model)
        writing.write_text(text, output)
    if not (fmt == "table" and output == "-"):
        for warning in [*document["warnings"], *document["fit"]["warnings"]]:
            click.echo(console.printable(f"warning: {warning}"), err=True)
