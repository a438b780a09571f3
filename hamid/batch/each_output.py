"""The output of `hamid fit --each`: one record per file, written as each fit ends.

Standard output, a device or a FIFO gets each record as it comes. A file ``-o OUT`` gets
them appended to ``OUT.partial``, which is renamed to OUT when every file is done: a
reader never takes an unfinished batch for a finished one, and Ctrl-C or a crash leaves
the finished fits in the ``.partial`` file (`kept` says where, for the message).

Formats: ``jsonl`` (one `comparison.record` per line), ``csv`` (`comparison.ROW_COLUMNS`, one row
per file and parameter) and ``table`` (the same rows, aligned for reading).
"""

from __future__ import annotations

import csv
import io
import json
import os
import stat
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import IO, Any

from hamid.batch import many_files
from hamid.data import writing
from hamid.errors import DataError, HamidError, UsageError
from hamid.options import percent
from hamid.report import comparison
from hamid.safe_text import printable

__all__ = ["EACH_FORMATS", "EachOutput", "Tally", "kept", "partial_name", "write_each"]

EACH_FORMATS = ("jsonl", "csv", "table")
PARTIAL_SUFFIX = ".partial"
_NUMBER_WIDTH = 12
_NAME_WIDTH = 10
_SOURCE_WIDTH = 48  # longer names push their row to the right rather than widen every row
_NULL = "—"


@dataclass(frozen=True, slots=True)
class EachOutput:
    """What `write_each` writes: the format, where (``"-"``: standard output), the
    confidence level the table's header names and the command line each report records."""

    format: str
    output: str = "-"
    level: float = 0.95
    command: str | None = None
    to_terminal: bool = False   # text is then shown with control characters escaped

    def __post_init__(self) -> None:
        if self.format not in EACH_FORMATS:
            raise UsageError(f"--each writes one record per file: --format "
                             f"{'|'.join(EACH_FORMATS)}, not {self.format}")


@dataclass(slots=True)
class Tally:
    """How many files failed, were fitted, and were fitted with warnings."""

    failed: int = 0
    fitted: int = 0
    warned: int = 0

    def line(self) -> str:
        """The summary the command line prints last."""
        total = self.failed + self.fitted
        return (f"{total} file{'' if total == 1 else 's'}: {self.failed} failed, "
                f"{self.fitted} fitted, {self.warned} warned")


def write_each(sources: Sequence[str], outcomes: Iterable[many_files.Outcome], out: EachOutput, *,
               progress: Callable[[int, many_files.Outcome], None] | None = None) -> Tally:
    """Write each outcome as it comes, in the order of `sources`; return the tally.

    `progress` is called after each record is written, with the number done and the
    outcome. The output is created with the first record: an error before any fit ends
    (a bad option, no scheduler) leaves nothing behind.
    """
    global _sink
    tally = Tally()
    lines = _LINES[out.format](sources, out)
    iterator = iter(outcomes)
    _sink = _Sink(out.output)
    try:
        for done, (source, outcome) in enumerate(zip(sources, iterator, strict=False), 1):
            if out.command is not None and not isinstance(outcome, HamidError):
                outcome = outcome.with_command(out.command)
            text = lines(comparison.record(source, outcome))
            _sink.write(printable(text, keep="\n") if out.to_terminal else text)
            _sink.records += 1
            if isinstance(outcome, HamidError):
                tally.failed += 1
            else:
                tally.fitted += 1
                tally.warned += bool(outcome.warnings)
            if progress is not None:
                progress(done, outcome)
        _sink.finish()
    finally:
        close = getattr(iterator, "close", None)
        if close is not None:   # stops the workers of a run cut short
            close()
    _sink = None
    return tally


def kept() -> str | None:
    """What an interrupted `write_each` leaves, in words, or None when it wrote nothing."""
    if _sink is None or not _sink.records:
        return None
    n = _sink.records
    fits = "the finished fit" if n == 1 else f"the {n} finished fits"
    if _sink.partial is not None:
        return f"{fits} {'is' if n == 1 else 'are'} in {_sink.partial}"
    return f"{fits} {'was' if n == 1 else 'were'} written"


Lines = Callable[[dict[str, Any]], str]


def _jsonl(sources: Sequence[str], out: EachOutput) -> Lines:
    """Helper: one JSON object per line."""

    def lines(line: dict[str, Any]) -> str:
        # ASCII: control characters in names and messages reach no terminal
        return json.dumps(line, allow_nan=False, ensure_ascii=True) + "\n"

    return lines


def _csv(sources: Sequence[str], out: EachOutput) -> Lines:
    """Helper: the header, then one row per file and parameter (numbers in full)."""
    started = False

    def lines(line: dict[str, Any]) -> str:
        nonlocal started
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        if not started:
            writer.writerow(comparison.ROW_COLUMNS)
            started = True
        for row in comparison.parameter_rows(line):
            writer.writerow(row[key] for key in comparison.ROW_COLUMNS)
        return buffer.getvalue()

    return lines


def _table(sources: Sequence[str], out: EachOutput) -> Lines:
    """Helper: aligned columns, the source named on its first row; errors in words."""
    width = min(max(map(len, map(printable, sources)), default=6), _SOURCE_WIDTH)
    level = percent(out.level)
    names = ("estimate", "std. error", f"{level} CI low", f"{level} CI high")
    header = (f"{'source':<{width}}  {'parameter':<{_NAME_WIDTH}}"
              + "".join(f"  {name:>{_NUMBER_WIDTH}}" for name in names) + "  warnings\n")
    started = False

    def row(source: str, name: str, values: Iterable[float | None], warnings: str) -> str:
        cells = (_NULL if v is None else format(v, ".6g") for v in values)
        return (f"{source:<{width}}  {name:<{_NAME_WIDTH}}"
                + "".join(f"  {cell:>{_NUMBER_WIDTH}}" for cell in cells)
                + f"  {warnings:>8}".rstrip() + "\n")

    def lines(line: dict[str, Any]) -> str:
        nonlocal started
        text = "" if started else header
        started = True
        source = printable(line["source"])
        if line["status"] == "error":
            return text + f"{source:<{width}}  error: {printable(line['error'])}\n"
        for k, p in enumerate(comparison.parameter_rows(line)):
            text += row(source if k == 0 else "", printable(p["parameter"]),
                        (p[key] for key in ("estimate", "stderr", "ci_low", "ci_high")),
                        str(p["warnings"]) if k == 0 else "")
        return text

    return lines


_LINES: dict[str, Callable[[Sequence[str], EachOutput], Lines]] = {
    "jsonl": _jsonl, "csv": _csv, "table": _table}


class _Sink:
    """Where the records go: standard output or a special file, written in place, else the
    ``.partial`` file beside the output, created fresh with the first record."""

    def __init__(self, output: str):
        self.output, self.records = output, 0
        self.stream: IO[bytes] | None = None
        self.partial = partial_name(output)

    def write(self, text: str) -> None:
        try:
            if self.output == "-":
                _to_stdout(text)
                return
            if self.stream is None:
                self.stream = (writing.create_fresh(self.partial) if self.partial is not None
                               else open(self.output, "wb"))  # noqa: SIM115 (in place)
            self.stream.write(text.encode("utf-8"))
            self.stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            name = "<stdout>" if self.output == "-" else self.partial or self.output
            raise DataError(f"{name}: cannot write: {exc.strerror or exc}") from exc

    def finish(self) -> None:
        """Close the output; a complete ``.partial`` file becomes the output (replacing
        a symlink there, not what it leads to)."""
        if self.stream is None:
            return
        try:
            if self.partial is not None:
                os.fsync(self.stream.fileno())
            self.stream.close()
            if self.partial is not None:
                os.replace(self.partial, self.output)
                self.partial = None
        except OSError as exc:
            raise DataError(f"{self.output}: cannot write: {exc.strerror or exc}") from exc


def partial_name(output: str) -> str | None:
    """The file the records collect in until the batch is done: ``OUT.partial``; None for
    an output written in place (standard output, a device, a FIFO)."""
    return None if _in_place(output) else output + PARTIAL_SUFFIX


def _to_stdout(text: str) -> None:
    """Helper: text to standard output at once, through its bytes where it has them."""
    sys.stdout.flush()
    buffer = getattr(sys.stdout, "buffer", None)
    if buffer is None:   # a text-only stream, as some embedding applications install
        sys.stdout.write(text)
    else:
        buffer.write(text.encode("utf-8"))
        buffer.flush()


def _in_place(output: str) -> bool:
    """Helper: whether an output is written in place (standard output, a device, a FIFO),
    not through a ``.partial`` file renamed over it."""
    if output == "-":
        return True
    try:
        return not stat.S_ISREG(os.stat(output).st_mode)
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise DataError(f"{output}: cannot write: {exc.strerror or exc}") from exc


_sink: _Sink | None = None
