"""What the commands share on the terminal: messages shown safely, and progress on standard
error (only when it is a terminal)."""

from __future__ import annotations

import os
import sys
from typing import Any

from hamid import safe_text

__all__ = ["Progress", "Status", "printable", "printable_lines", "stderr_console",
           "terminal_width"]


def printable(text: str) -> str:
    """A message with the control characters of any text from data shown escaped."""
    return safe_text.printable(text)


def printable_lines(text: str) -> str:
    """Text of several lines, with the control characters of each line escaped."""
    return safe_text.printable(text, keep="\n")


def terminal_width() -> int:
    """The width of standard output as rich sees it: the COLUMNS variable when set, the
    terminal's when it is one, else 80."""
    from rich.console import Console

    return Console().width


def stderr_console() -> Any:
    from rich.console import Console

    return Console(stderr=True, highlight=False, soft_wrap=True)


class Progress:
    """A progress bar on standard error, shown only when it is a terminal; of a fraction, or
    of items done out of `total`."""

    def __init__(self, console: Any, label: str, total: int | None = None):
        self.console, self.label, self.total, self.bar = console, label, total, None

    def __enter__(self) -> Any:
        if not self.console.is_terminal:
            return None
        from rich.progress import MofNCompleteColumn, Progress

        columns = Progress.get_default_columns()
        self.bar = Progress(*columns, *([MofNCompleteColumn()] if self.total else []),
                            console=self.console, transient=True)
        self.bar.start()
        task = self.bar.add_task(self.label, total=self.total or 1.0)
        return lambda fraction: self.bar.update(task, completed=fraction)

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()


class Status:
    """A status line on standard error that a long command updates, shown only when it is
    a terminal (checked before rich is imported, which a pipe then never pays for)."""

    def __init__(self, label: str):
        self.label, self.line = label, None

    def __enter__(self) -> Any:
        if sys.stderr is None or not sys.stderr.isatty():
            return None
        from rich.markup import escape

        self.line = stderr_console().status(self.label)
        self.line.start()
        # the text names files, whose names may hold control characters or rich markup
        return lambda text: self.line.update(escape(f"{self.label}: {printable(text)}"))

    def __exit__(self, *exc: object) -> None:
        if self.line is not None:
            self.line.stop()


# An output's extension -> the format it is written in (the commands that write reports)
REPORT_SUFFIXES = {".json": "json", ".csv": "csv", ".txt": "table"}


def format_of(output: str, told: str = ".json, .csv or .txt") -> str:
    """The format -o's extension tells (`REPORT_SUFFIXES`); table for standard output.
    `told` lists the extensions the command takes, for the error."""
    from hamid.errors import UsageError

    suffix = os.path.splitext(output)[1].lower()
    if output == "-" or suffix in REPORT_SUFFIXES:
        return REPORT_SUFFIXES.get(suffix, "table")
    shown = f"unknown extension {suffix!r}" if suffix else "no extension"
    raise UsageError(f"-o {output!r}: {shown}; the output's format is told by {told}, or "
                     "give --format")
