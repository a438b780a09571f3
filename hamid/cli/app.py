"""The `hamid` command: a thin layer over the Python API.

The only module that knows exit codes: 0 success, 1 a data, model or numerical error
(one message naming the file, column, row or term), 2 a usage error, 3 a fit with warnings
under `fit --strict` (the report is written all the same), 128 + N after signal N
(130 for Ctrl-C). Data go to standard output; messages, warnings and progress to standard
error, with the control characters of any text from data shown escaped. Heavy modules are
imported inside the commands so that `hamid --help` starts fast.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import shlex
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, NoReturn

import click

from hamid import __version__
from hamid.cli import console, option_groups
from hamid.cli.backbone_command import backbone
from hamid.cli.predict_command import predict
from hamid.cli.select_command import select
from hamid.errors import DataError, HamidError, UsageError
from hamid.safe_text import counted

if TYPE_CHECKING:
    from hamid.data import writing

_debug = False
# The data files of the running `fit`, named when it runs out of memory.
_sources: tuple[str, ...] = ()
# The report formats of `fit` and `report` (hamid.report.formats.FORMATS, not imported for --help),
# jsonl for many fits (fit --each, report of several), and the extensions that choose them.
_REPORT_FORMATS = ("table", "json", "csv", "markdown")
_FORMATS = click.Choice([*_REPORT_FORMATS, "jsonl"])
_REPORT_SUFFIXES = {".json": "json", ".csv": "csv", ".md": "markdown", ".txt": "table",
                    ".jsonl": "jsonl"}


class _Terminated(BaseException):
    """SIGTERM, SIGHUP or SIGQUIT, raised where the program is, as Ctrl-C raises
    KeyboardInterrupt, so that the same clean-up runs: temporaries removed, outputs intact."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


class _StreamsChecked:
    """Parsing that may write the help or the version: a failed write is one line, exit 1."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        # `--help` / `--version` write while parsing, before invoke; click would exit 1.
        try:
            return super().parse_args(ctx, args)  # type: ignore[misc]
        except BrokenPipeError:
            _quiet_broken_pipe()
        except OSError as exc:  # a full disk: `hamid --help > /dev/full`
            _stdout_failed(exc.strerror or str(exc))
        except click.exceptions.Exit as exc:
            if exc.exit_code == 0 and sys.stdout is None:  # `>&-`: click wrote nothing
                _stdout_failed("standard output is closed")
            raise


class _HamidCommand(_StreamsChecked, option_groups.GroupedCommand):
    """A subcommand whose help may fail to be written, and lists the options of `hamid.fit`
    under their groups' headings."""


class _HamidGroup(_StreamsChecked, click.Group):
    """Turns library errors into click's exit codes, and bugs into one line."""

    command_class = _HamidCommand

    def invoke(self, ctx: click.Context) -> Any:
        with warnings.catch_warnings():
            if not ctx.params.get("debug"):
                # numpy's floating-point warnings quote numpy's source lines, not the user's
                # data; hamid says in its own words what they mean for the fit.
                warnings.simplefilter("ignore", RuntimeWarning)
            return self._invoke(ctx)

    def _invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except UsageError as exc:
            # Raised inside a subcommand, whose context is gone by now: no usage line.
            raise click.UsageError(console.printable(str(exc))) from exc
        except HamidError as exc:
            if isinstance(exc.__cause__, MemoryError):  # e.g. pyarrow's failed malloc
                raise _out_of_memory(exc.__cause__, ctx.invoked_subcommand) from exc
            raise click.ClickException(console.printable(str(exc))) from exc
        except (click.ClickException, click.exceptions.Exit, click.Abort):
            raise
        except BrokenPipeError:
            _quiet_broken_pipe()
        except KeyboardInterrupt:
            _stop("interrupted", 130)
        except _Terminated as exc:
            _terminated(exc)
        except MemoryError as exc:
            raise _out_of_memory(exc, ctx.invoked_subcommand) from exc
        except Exception as exc:
            if _debug:
                raise
            raise click.ClickException(console.printable(
                f"internal error ({type(exc).__name__}: {exc}); this is a bug in hamid. "
                "Rerun with --debug for the traceback")) from exc


def _stop(what: str, status: int) -> NoReturn:
    """Ctrl-C or a signal: remove what was being written, say so in one line, exit."""
    from hamid.data import writing

    writing.remove_temporaries()
    each_output = sys.modules.get("hamid.batch.each_output")   # fit --each keeps its finished fits
    kept = each_output.kept() if each_output is not None else None
    click.echo(f"{what}; {kept or 'no output was written'}", err=True)
    sys.exit(status)


def _terminated(exc: _Terminated) -> NoReturn:
    import signal

    _stop(f"terminated by {signal.Signals(exc.signum).name}", 128 + exc.signum)


# What the innermost hamid module of a traceback was doing, for a MemoryError.
_ACTIVITIES = {"data.readers": "reading the data", "data.loading": "reading the data",
               "linear.chunked": "reading the data in chunks",
               "data.writing": "writing the output", "report.formats": "rendering the report",
               "simulation": "simulating", "result.validation": "checking the report",
               "result.fit_result": "checking the report"}
_MEMORY_HINTS = {
    "fit": "read the data in bounded memory with --chunk-rows ROWS (without --residuals), "
           "or fit fewer samples",
    "simulate": "make the run smaller (a shorter t_end, a larger dt, fewer initial states)",
}


def _out_of_memory(exc: BaseException, command: str | None) -> click.ClickException:
    """The one line for a MemoryError: what was being done, on how much data, what to try."""
    activity = {"fit": "fitting", "simulate": "simulating"}.get(command or "", "working")
    traceback = exc.__traceback__
    while traceback is not None:
        module = traceback.tb_frame.f_globals.get("__name__", "")
        if module.startswith("hamid."):
            activity = _ACTIVITIES.get(module.removeprefix("hamid."), activity)
        traceback = traceback.tb_next
    size = sum(os.path.getsize(s) for s in _sources if os.path.isfile(s))
    if command == "fit" and _sources:
        shown = ", ".join(_sources[:3]) + (f" and {len(_sources) - 3} more"
                                           if len(_sources) > 3 else "")
        activity += f" {shown}" + (f" ({size / 1e6:,.0f} MB)" if size >= 1e6 else "")
    hint = _MEMORY_HINTS.get(command or "", "try a smaller input")
    return click.ClickException(console.printable(f"out of memory while {activity}; {hint}"))


def _quiet_broken_pipe() -> NoReturn:
    """The reader of our output went away (e.g. `| head`): stop quietly, as cat does."""
    _silence_stdout()
    sys.exit(0)


def _stdout_failed(reason: str) -> NoReturn:
    """Writing standard output failed outside a command (the help, the version)."""
    _silence_stdout()
    click.echo(f"Error: <stdout>: cannot write: {reason}", err=True)
    sys.exit(1)


def _silence_stdout() -> None:
    """Point descriptor 1 at /dev/null, so that the flush at exit neither fails nor warns."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
    finally:
        os.close(devnull)


@click.group(cls=_HamidGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="hamid")
@click.option("--debug", is_flag=True, help="Show the traceback of an internal error.")
def cli(debug: bool) -> None:
    """Identify nonlinear vibrating systems by fitting their energy."""
    global _debug
    _debug = debug


cli.add_command(select)
cli.add_command(predict)
cli.add_command(backbone)


@cli.command()
@click.option("--config", "config", required=True, metavar="SYSTEM.toml",
              help="System file: model, true parameters, initial states, settings.")
@click.option("-o", "--output", default="-", show_default=True, metavar="OUT",
              help="Output file (.csv, .tsv, .parquet); '-' for standard output.")
@click.option("--format", "fmt", type=click.Choice(["csv", "tsv", "parquet"]),
              help="Output format (default: from the file name, csv for '-').")
@click.option("--seed", type=click.IntRange(min=0), help="Seed of the measurement noise.")
@click.option("--no-meta", is_flag=True, help="Write no provenance metadata line.")
@click.option("--max-samples", type=click.IntRange(min=1),
              help="Allow runs larger than the safety cap (default 20,000,000 samples).")
@click.option("--realizations", type=click.IntRange(min=1), metavar="N",
              help="Write N copies with their own noise (seeds S, S+1, ...), as OUT with "
                   "-1, -2, ... before its extension.")
def simulate(config: str, output: str, fmt: str | None, seed: int | None, no_meta: bool,
             max_samples: int | None, realizations: int | None) -> None:
    """Integrate a system from its initial states and write the sampled record."""
    from hamid import simulation
    from hamid.data import writing
    from hamid.simulation import simulate_realizations

    table_format = writing.table_format(output, fmt)
    files = [output] if realizations is None else simulation.numbered(output, realizations)
    outputs = _outputs([config])
    for name in files:
        outputs.claim("-o" if realizations is None else "-o's realization file", name,
                     binary=table_format == "parquet")
    _check_room(config, output, table_format, max_samples, len(files))
    stderr = console.stderr_console()
    with console.Progress(stderr, "simulating") as progress:
        frames = simulate_realizations(config, len(files), seed=seed,
                                       max_samples=max_samples, progress=progress)
        first = next(frames)   # the integration; the other realizations only add noise
    with writing.all_or_nothing():
        for name, frame in zip(files, itertools.chain([first], frames), strict=True):
            meta = frame.attrs["hamid"]
            writing.write_table(frame, name, format=fmt, metadata=None if no_meta else meta)
    drift = max(t["energy_drift"] for t in meta["trajectories"])
    for warning in meta.get("warnings", []):
        click.echo(console.printable(f"warning: {warning}"), err=True)
    stderr.print(f"simulated {counted(len(meta['trajectories']), 'trajectory', 'trajectories')}, "
                 f"{counted(len(frame), 'sample', 'samples')} "
                 f"(t = 0..{frame['t'].iloc[-1]:g}, dt = {meta['dt']:g}); "
                 f"largest relative energy drift {drift:.2g}"
                 + ("" if not meta["damping"] else " (energy plus dissipated work)")
                 + ("" if realizations is None else
                    f"; {realizations} realizations, {files[0]} to {files[-1]}"))


# Bytes a value takes in a written table: CSV text of a double's shortest form and a
# separator, or Parquet's uncompressed double.
_VALUE_BYTES = {"csv": 20, "tsv": 20, "parquet": 8}


def _check_room(config: str, output: str, table_format: str, max_samples: int | None,
                copies: int) -> None:
    """Refuse a simulation whose output would not fit on the disk it goes to, before the
    run (150 coordinates of 20 million samples, 48 GB, started writing before)."""
    import shutil

    from hamid import simulation
    from hamid.data import documents

    if output == "-" or not os.path.isdir(os.path.dirname(os.path.abspath(output))):
        return
    system = simulation.parse_system(documents.read_toml(config), where=config,
                                     folder=os.path.dirname(os.path.abspath(config)))
    if max_samples is not None:
        system = dataclasses.replace(system, max_samples=max_samples)
    values = simulation.output_values(system) * copies
    needed = values * _VALUE_BYTES[table_format]
    free = shutil.disk_usage(os.path.dirname(os.path.abspath(output))).free
    if needed > free:
        raise DataError(f"{output}: the run would write about {needed / 2**30:,.1f} GiB "
                        f"({values:,.0f} values), more than the {free / 2**30:,.1f} GiB "
                        "free on its disk; simulate less, or write elsewhere")


def _to_stdout(output: str) -> bool:
    """Whether an output goes to this process's standard output: '-', or a name that leads
    to the same open file (/dev/stdout, /dev/fd/1, a symlink to either)."""
    from hamid.data import readers

    if readers.is_stdio(output):
        return True
    try:
        named, ours, null = os.stat(output), os.fstat(1), os.stat(os.devnull)
    except (OSError, ValueError):
        return False
    # /dev/null as standard output: what goes there cannot interleave
    return (named.st_dev, named.st_ino) == (ours.st_dev, ours.st_ino) != (null.st_dev,
                                                                           null.st_ino)


@cli.command()
@click.argument("data", nargs=-1, required=True)
@click.option("--model", metavar="NAME|MODEL.toml", help="Built-in model or model file.")
@option_groups.reading
@click.option("--strict", is_flag=True,
              help="Exit with status 3 when the fit has any warning (the report is written).")
@option_groups.velocities
@option_groups.method
@option_groups.covariance
@click.option("--format", "fmt", type=_FORMATS,
              help="Report format (default: from -o's extension: .json, .csv, .md, .txt; "
                   "table for standard output and special files).")
@click.option("-o", "--output", default="-", metavar="FILE", help="Write the report here.")
@click.option("--residuals", metavar="FILE",
              help="Write per-sample residuals (CSV/Parquet); reads the data into memory.")
@click.option("--plot", "figure", metavar="FIG",
              help="Also draw the fit (hamid plot): FIG.png or .svg, a file per panel, or "
                   ".pdf, a page per panel.")
@click.option("--each", is_flag=True,
              help="Fit each file by itself (DATA: files, folders, glob patterns, URLs); "
                   "one jsonl line, or CSV or table rows, per file.")
@option_groups.run
@click.option("--scheduler", metavar="tcp://HOST:PORT",
              help="With --each: fit on this Dask cluster (default $DASK_SCHEDULER_ADDRESS).")
@click.option("--ship-data", is_flag=True,
              help="With --scheduler: send the files' bytes rather than their names.")
def fit(data: tuple[str, ...], model: str | None, strict: bool, fmt: str | None,
        output: str, residuals: str | None, figure: str | None, each: bool,
        scheduler: str | None, ship_data: bool, **options: Any) -> None:
    """Fit the energy of the recorded motion in DATA (CSV, TSV, Parquet; '-' for stdin)."""
    from hamid.api import fit as run_fit
    from hamid.data import writing

    if options["seed"] is not None and options["cov"] != "bootstrap":
        raise click.UsageError("--seed applies only to --cov bootstrap")
    if residuals is not None and options["chunk_rows"] is not None:
        raise click.UsageError("--residuals needs the data in memory; leave out --chunk-rows")
    for name in data:
        if name.lower().endswith(".toml"):
            raise UsageError(f"{name!r} is a model file, not data: give it as --model {name}")
    global _sources
    _sources = data
    fit_options = option_groups.fit_keywords(options)
    if each or scheduler or ship_data:
        if figure is not None:
            raise UsageError("--plot draws one fit: it does not combine with --each")
        _fit_each(data, model, fit_options, each=each, scheduler=scheduler,
                  ship_data=ship_data, fmt=fmt, output=output, strict=strict,
                  residuals=residuals, jobs=options["jobs"], level=options["level"])
        return
    outputs = _outputs([*data, *([model] if model is not None and os.path.isfile(model)
                                 else [])])
    outputs.claim("-o", output)
    if residuals is not None:
        residuals_format = writing.table_format(residuals)
        outputs.claim("--residuals", residuals, binary=residuals_format == "parquet")
        if _to_stdout(residuals) and _to_stdout(output):
            raise UsageError("--residuals and the report would both go to standard output, "
                             "where they would interleave; write one of them to a file "
                             "(-o FILE or --residuals FILE)")
    if figure is not None:
        _claim_figure(outputs, "--plot", figure)
    fmt = fmt or _report_format(output)
    if fmt == "jsonl":
        raise UsageError("--format jsonl writes one line per file: it needs --each")
    with console.Status("fitting") as status:
        result = run_fit(list(data), model, **fit_options, in_memory=residuals is not None,
                         progress=status)
    result = result.with_command(shlex.join(["hamid", *sys.argv[1:]]))

    notes: list[str] = []

    def write_files() -> None:
        if residuals is not None:
            import pandas as pd

            writing.write_table(pd.DataFrame(result.samples), residuals)
        if figure is not None:
            from hamid.plot import figures

            notes.extend(figures.save(result.to_dict(), result.recording, figure))

    _emit(result.to_dict(), fmt, output, also=write_files)
    _say(notes)
    if strict and result.warnings:
        click.echo(f"error: --strict: the fit has "
                   f"{counted(len(result.warnings), 'warning', 'warnings')}", err=True)
        raise click.exceptions.Exit(3)


def _fit_each(data: tuple[str, ...], model: str | None, fit_options: dict[str, Any], *,
              each: bool, scheduler: str | None, ship_data: bool, fmt: str | None,
              output: str, strict: bool, residuals: str | None, jobs: int | None,
              level: float) -> None:
    """`fit --each`: a fit per file, written in their order as they end (hamid.batch);
    `fit_options` are `hamid.fit`'s keywords, `jobs` the files fitted at once."""
    from hamid.batch import each_output, many_files
    from hamid.data import destinations
    from hamid.executor import Workers

    if not each:
        raise UsageError("--scheduler and --ship-data apply only to --each")
    if residuals is not None:
        raise UsageError("--residuals writes the samples of one fit; leave it out with --each")
    sources = many_files.expand_sources(data)
    outputs = _outputs([*sources, *([model] if model and os.path.isfile(model) else [])])
    outputs.claim("-o", output)
    output = "-" if _to_stdout(output) else output   # /dev/stdout: one stream, not two
    partial = each_output.partial_name(output)
    if partial is not None:
        outputs.claim("-o's partial file", partial)
    out = each_output.EachOutput(fmt or _report_format(output), output, level,
                              shlex.join(["hamid", *sys.argv[1:]]),
                              destinations.is_terminal(output))
    outcomes = many_files.iter_fits(sources, model, fit_options,
                               Workers.choose(jobs, scheduler, len(sources)), ship_data=ship_data)
    stderr = console.stderr_console()
    with console.Progress(stderr, "fitting", total=len(sources)) as bar:
        def progress(done: int, outcome: object) -> None:
            if bar is not None:
                bar(done)
            if isinstance(outcome, HamidError) and not (out.format == "table" and output == "-"):
                stderr.print(console.printable(f"error: {outcome}"), markup=False)

        tally = each_output.write_each(sources, outcomes, out, progress=progress)
    stderr.print(tally.line(), markup=False)
    if tally.failed or (strict and tally.warned):
        raise click.exceptions.Exit(1 if tally.failed else 3)


_ORDER_BY_HELP = ("Several fits: place each along the x axis by KEY, a dotted key of its "
                  "report holding a number or an ISO 8601 time (data.time_unit, "
                  "provenance.utc, ...), or mtime, the modification time of the data file "
                  "it read (default: the order of the files and lines).")


def _one_report_has_no_order(order_by: str | None) -> None:
    """--order-by places several fits: with one report, a usage error."""
    if order_by is not None:
        raise UsageError("--order-by places several fits (RESULTS.jsonl, or several "
                         "RESULT.json); one report has nothing to order")


@cli.command()
@click.argument("result_files", metavar="RESULT.json|RESULTS.jsonl...", nargs=-1,
                required=True)
@click.option("--format", "fmt", type=_FORMATS,
              help="Output format (default: from -o's extension: .json, .csv, .md, .txt, "
                   ".jsonl; table for standard output and special files).")
@click.option("-o", "--output", default="-", metavar="OUT", help="Write the report here.")
@click.option("--plot", "figure", metavar="FIG",
              help="Also draw the figure hamid plot draws of the same reports: FIG.png, "
                   ".svg or .pdf.")
@click.option("--order-by", metavar="KEY", help=f"With --plot: {_ORDER_BY_HELP}")
def report(result_files: tuple[str, ...], fmt: str | None, output: str, figure: str | None,
           order_by: str | None) -> None:
    """Render a saved fit result (JSON) as a table, JSON, CSV or markdown; several results
    (or the lines of fit --each) side by side, a column per source, or a row per source
    when the table would be wider than the terminal (COLUMNS, else 80 off a terminal).
    With --plot, the report and its figure are written together, or neither."""
    from hamid.data import destinations, documents, readers, writing
    from hamid.result.fit_result import FitResult

    outputs = _outputs(result_files)
    outputs.claim("-o", output)
    fmt = fmt or _report_format(output)
    several = (len(result_files) > 1 or fmt == "jsonl"
               or result_files[0].lower().endswith(".jsonl"))
    if order_by is not None and figure is None:
        raise UsageError("--order-by places the fits along the x axis of --plot's figure; "
                         "give --plot FIG")
    if not several:
        _one_report_has_no_order(order_by)
    if figure is not None:
        _claim_figure(outputs, "--plot", figure, "parameters" if several else None)
    if several:
        from hamid.report import comparison

        to_terminal = destinations.is_terminal(output)
        compared = comparison.load(result_files)
        text = comparison.render(compared, fmt,
                                 color=to_terminal and "NO_COLOR" not in os.environ,
                                 width=console.terminal_width() if fmt == "table" else None)
        notes: list[str] = []
        with writing.all_or_nothing():   # the figure first: a stream cannot be taken back
            if figure is not None:
                from hamid.plot import drift

                notes = drift.save(compared, figure, order_by)
            writing.write_text(console.printable_lines(text) if fmt == "csv" and to_terminal
                               else text, output)
        _say(notes)
        return
    source = readers.STDIN if readers.is_stdio(result_files[0]) else result_files[0]
    checked = FitResult.from_dict(documents.read_json(result_files[0]), source=source).to_dict()
    notes = []

    def draw() -> None:
        from hamid.plot import figures

        notes.extend(figures.save(checked, None, figure))

    _emit(checked, fmt, output, also=None if figure is None else draw)
    _say(notes)


@cli.command()
@click.argument("result_file", metavar="RESULT.json|RESULTS.jsonl")
@click.argument("data", nargs=-1)
@click.option("-o", "--output", required=True, metavar="FIG",
              help="Figure file: .png or .svg, a file per panel (FIG-1-energy.png, ...), or "
                   ".pdf, a page per panel.")
@click.option("--panels", metavar="LIST",
              help="Panels by number or name: 1 energy, 2 residuals, 3 phase, 4 motion, "
                   "5 parameters, 6 correlation, 7 backbone (default: all of 1-6 that "
                   "apply; 7 only when asked for).")
@click.option("--order-by", metavar="KEY", help=_ORDER_BY_HELP)
@option_groups.reading
def plot(result_file: str, data: tuple[str, ...], output: str, panels: str | None,
         order_by: str | None, **reading: Any) -> None:
    """Draw a saved fit result (JSON); panels 1-4 need the DATA it was fitted to, read as
    the fit read them (the report's reading options) unless reading options are given.

    Several fits (RESULTS.jsonl of fit --each, or several RESULT.json): each parameter
    against the order of the fits (or --order-by) with its confidence interval."""
    from hamid.data import documents, readers, writing
    from hamid.plot import drift, figures, fitted
    from hamid.report import comparison
    from hamid.result.fit_result import FitResult

    reports = [result_file, *data]
    if result_file.lower().endswith(".jsonl") or (
            data and all(name.lower().endswith(".json") for name in data)):
        if panels is not None or option_groups.fit_keywords(reading):
            raise UsageError("several fits are drawn as one figure of their parameters: "
                             "--panels and reading options apply to one report and its data")
        _claim_figure(_outputs(reports), "-o", output, "parameters")
        compared = comparison.load(reports)
        with writing.all_or_nothing():
            notes = drift.save(compared, output, order_by)
        _say(notes)
        return
    _one_report_has_no_order(order_by)
    _claim_figure(_outputs(reports), "-o", output, panels)
    source = readers.STDIN if readers.is_stdio(result_file) else result_file
    report = FitResult.from_dict(documents.read_json(result_file), source=source).to_dict()
    recording = (fitted.read_recording(report, data, option_groups.fit_keywords(reading))
                 if data else None)
    with writing.all_or_nothing(), console.Status("drawing"):
        notes = figures.save(report, recording, output, panels)
    _say(notes)


def _say(notes: Sequence[str]) -> None:
    """A figure's notes (panels left out, and why) on stderr, after its files are
    written."""
    for note in notes:
        click.echo(console.printable(note), err=True)


def _claim_figure(outputs: writing.Outputs, option: str, figure: str,
                  panels: str | None = None) -> None:
    """Before any work: a figure's format (its extension), matplotlib, and every file the
    figure may take (`figures.panel_files`)."""
    from hamid.plot import figures

    try:
        figures.check_output(figure)
    except UsageError as exc:
        raise UsageError(f"{option} {exc}") from None
    outputs.claim(option, figure, binary=True)
    for name in figures.panel_files(figure, panels):
        outputs.claim(f"{option}'s panel file", name, binary=True)


def _outputs(inputs: Sequence[str]) -> writing.Outputs:
    """The command's outputs, checked against `inputs` and each other as they are claimed
    and as they are written, until the command ends."""
    from hamid.data import writing

    return click.get_current_context().with_resource(writing.Outputs(inputs))


def _report_format(output: str) -> str:
    """The report format `-o` implies: its extension's, else table for standard output and
    special files (devices, FIFOs, /dev/stdout); a UsageError for any other name."""
    from hamid.data import readers, writing

    suffix = os.path.splitext(output)[1].lower()
    if suffix in _REPORT_SUFFIXES:
        return _REPORT_SUFFIXES[suffix]
    # writing.table_format tells a stream without a table extension (as CSV) and refuses a
    # regular file without one: the same rule, asked of the module that writes.
    try:
        stream = (writing.table_format(output) == "csv"
                  and readers.format_from_suffix(output) is None)
    except (UsageError, DataError):
        stream = False
    if stream:
        return "table"
    known = ", ".join(f"{s} ({f})" for s, f in _REPORT_SUFFIXES.items())
    shown = f"unknown extension {suffix!r}" if suffix else "no extension"
    raise UsageError(f"-o {output!r}: {shown}; the report's format is told by {known}, "
                     "or give --format")


def _emit(result: dict[str, Any], fmt: str, output: str, *,
          also: Callable[[], None] | None = None) -> None:
    """Render a result and write it; warnings also go to stderr unless a terminal shows them.

    `also` writes further output files; they and the report file appear together or, if
    anything fails, none of them does.
    """
    from hamid.data import destinations, writing
    from hamid.report.formats import render

    to_terminal = destinations.is_terminal(output)
    color = to_terminal and "NO_COLOR" not in os.environ
    text = render(result, fmt, color=color)
    if fmt == "csv" and to_terminal:
        # CSV is data, written exactly; on a terminal its names are shown escaped
        text = console.printable_lines(text)
    # Written last, after the files: a stream (standard output, a FIFO) cannot be taken back.
    with writing.all_or_nothing():
        if also is not None:
            also()
        writing.write_text(text, output)
    if not (fmt == "table" and output == "-"):
        for warning in result["warnings"]:
            click.echo(console.printable(f"warning: {warning}"), err=True)


@cli.command()
@click.argument("name", required=False)
def models(name: str | None) -> None:
    """List the built-in models, or show one in full (NAME may also be a model file)."""
    from hamid.api import load_model
    from hamid.data import writing
    from hamid.model.models import BUILTINS, POLY_HELP

    writing.check_destination("-")
    if name is None:
        lines = []
        for key, spec in BUILTINS.items():
            lines.append(f"{key:16s} {len(spec['coordinates'])} DOF  "
                         f"parameters: {' '.join(spec['parameters'])}")
            lines.append(f"{'':16s} E = {spec['energy']}")
        lines.append(f"{POLY_HELP:16s} N DOF  kinetic energy plus one parameter c_<exponents> "
                     "per monomial of degree 2..D (e.g. poly:2:3)")
        writing.write_text("\n".join(lines) + "\n", "-")
        return
    m = load_model(name)
    lines = [f"name:        {m.name}",
             *([f"about:       {m.description}"] if m.description else []),
             f"coordinates: {' '.join(m.coordinates)}",
             f"velocities:  {' '.join(m.velocities)}",
             f"parameters:  {' '.join(m.parameters)}",
             f"energy:      E = {m.energy}",
             f"natural:     {'yes (E = T + V)' if m.is_natural else 'no'}"]
    # a model file's name and description are text from a file: shown escaped
    writing.write_text("\n".join(console.printable(line) for line in lines) + "\n", "-")


def main() -> None:
    """Console-script entry point."""
    _prepare_process()
    try:
        try:
            cli(prog_name="hamid")
        except SystemExit as exc:
            _finish(exc.code)
    except _Terminated as exc:  # a signal outside a command, or while finishing
        _terminated(exc)


def _prepare_process() -> None:
    """Before any work: standard streams that can be used, signals that clean up."""
    import signal

    # `<&-`, `>&-`, `2>&-`: the next file opened would take the closed descriptor, and a
    # message or a native library's output meant for the terminal would land in it.
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            devnull = os.open(os.devnull, os.O_RDWR)
            if devnull != fd:
                os.dup2(devnull, fd)
                os.close(devnull)
    if sys.stdin is None:
        sys.stdin = _ClosedInput()  # type: ignore[assignment]
    if sys.stderr is None:  # messages go nowhere, and the exit status says what happened
        sys.stderr = open(2, "w", closefd=False)  # noqa: SIM115 (/dev/null, kept open)
    # A file-size limit (ulimit -f) makes a write fail with EFBIG, reported, rather than
    # kill the process, leaving its temporary file.
    if hasattr(signal, "SIGXFSZ"):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    for name in ("SIGTERM", "SIGHUP", "SIGQUIT"):
        signum = getattr(signal, name, None)
        # an ignored signal stays ignored (nohup, a background job's SIGQUIT)
        if signum is not None and signal.getsignal(signum) == signal.SIG_DFL:
            signal.signal(signum, _on_signal)


def _on_signal(signum: int, frame: object) -> None:
    """Turn a termination signal into an exception, once: a second must not cut the clean-up
    short."""
    import signal

    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    raise _Terminated(signum)


class _ClosedInput:
    """Standard input when the shell closed it (`<&-`): reading fails as on a closed
    descriptor, and the reader reports it in one line."""

    closed = False

    @property
    def buffer(self) -> _ClosedInput:
        return self

    def read(self, *args: object) -> bytes:
        import errno

        raise OSError(errno.EBADF, "standard input is closed")

    def isatty(self) -> bool:
        return False


def _finish(status: object) -> NoReturn:
    """Flush standard output before exiting: output the buffer still held (a full disk)
    fails here as one line, not as Python's warning at exit."""
    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except OSError as exc:
        _silence_stdout()
        if status in (0, None):
            click.echo(f"Error: <stdout>: cannot write: {exc.strerror or exc}", err=True)
            status = 1
    sys.exit(status)


if __name__ == "__main__":
    main()
