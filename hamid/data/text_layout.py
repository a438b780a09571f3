"""The layout of delimited text before its data rows (issue 18): comment lines and the hamid
metadata line, the header line, the delimiter (``,``, tab or ``;``), the decimal mark
(``.`` or ``,``) and a units row under the header.

Given or detected: `TextOptions` gives any of them; otherwise

- the delimiter is tab for TSV (``.tsv``, ``.tab``); otherwise ``;`` when the header line
  has more ``;`` than ``,``, else ``,`` -- or tab, when the format is not known (standard
  input, another extension) and the header line has one;
- the decimal mark is ``,`` when the delimiter is not ``,`` and a cell of the first data
  rows is a number written with a decimal comma (``0,25``, ``-1,5e-3``);
- a units row is the row under the header when none of its cells is a number and the row
  after it has numbers. Its cells are recorded by column as ``{"units": {column: unit}}``
  in the table's metadata (empty cells left out), and the row is not data.
"""

from __future__ import annotations

import dataclasses
import re
from typing import IO, Any

from hamid import read_limits
from hamid.errors import DataError, UsageError
from hamid.read_limits import json_value
from hamid.safe_text import counted

__all__ = ["Layout", "TextOptions", "head", "json_kind", "layout", "parse_metadata", "points",
           "preamble_hint", "preamble_lines"]

UTF8_BOM = b"\xef\xbb\xbf"
_METADATA_LINE = re.compile(rb"#\s*hamid:(.*)")
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)",
                     re.IGNORECASE)
_COMMA_NUMBER = re.compile(r"[+-]?\d*,\d+([eE][+-]?\d+)?")
# Data rows looked at to detect the decimal mark and the units row.
_SNIFF_ROWS = 8
# Lines looked at to guess the length of a preamble before the header.
_PREAMBLE_LINES = 200


@dataclasses.dataclass(frozen=True)
class TextOptions:
    """How to read delimited text; None detects (see the module's documentation).

    delimiter : one character between cells (``","``, ``";"``, ``"\\t"``, ...).
    decimal : ``"."`` or ``","``.
    skip_rows : lines skipped at the start of the file, before comments and the header
        (a data logger's preamble).
    units_row : whether the row under the header holds units.
    """

    delimiter: str | None = None
    decimal: str | None = None
    skip_rows: int = 0
    units_row: bool | None = None

    def __post_init__(self) -> None:
        if self.delimiter is not None and (len(self.delimiter) != 1
                                           or self.delimiter in "\r\n\"."):
            raise UsageError(f"--delimiter: {self.delimiter!r} is not one character that "
                             "can separate cells")
        if self.decimal not in (None, ".", ","):
            raise UsageError(f"--decimal: {self.decimal!r} is not '.' or ','")
        if self.decimal is not None and self.decimal == self.delimiter:
            raise UsageError("--decimal: the decimal mark cannot be the delimiter")
        if self.skip_rows < 0:
            raise UsageError("--skip-rows: must be 0 or more")


@dataclasses.dataclass(frozen=True)
class Layout:
    """Where the header line starts, and how the rows under it are read."""

    start: int
    metadata: dict[str, Any] | None
    delimiter: str
    decimal: str = "."
    skip: int = 0   # rows under the header that are not data (the units row)


def layout(head: bytes, name: str, fmt: str | None,
           options: TextOptions | None = None) -> Layout:
    """The layout of delimited text from its start (at least through its header line; a few
    data rows more let the decimal mark and a units row be detected). `fmt` ("csv", "tsv")
    fixes the delimiter unless `options` give one."""
    options = options or TextOptions()
    start = len(UTF8_BOM) if head.startswith(UTF8_BOM) else 0
    for _ in range(options.skip_rows):
        end = head.find(b"\n", start)
        start = len(head) if end < 0 else end + 1
        if start >= len(head):   # not a loop of billions of rows over nothing
            lines = head.count(b"\n") + (not head.endswith(b"\n"))
            raise DataError(f"{name}: --skip-rows {options.skip_rows:,} reaches the end of "
                            f"the text ({lines:,} lines)")
    start, metadata = _skip_comments(head, start, name)
    if start >= len(head):
        raise DataError(f"{name}: has comment lines but no header line")
    lines = _lines(head, start)
    if not lines:   # only blank lines (str.strip counts separators such as \x1c as blank)
        raise DataError(f"{name}: has no header line, only blank lines")
    delimiter = options.delimiter or ("\t" if fmt == "tsv"
                                      else _sniff_delimiter(lines[0], tabs=fmt is None))
    rows = [_cells(line, delimiter) for line in lines[1:]]
    decimal = options.decimal or ("," if delimiter != "," and any(
        _COMMA_NUMBER.fullmatch(cell) for row in rows for cell in row) else ".")
    units_row = options.units_row
    if units_row is None:
        units_row = len(rows) >= 2 and any(rows[0]) \
            and not any(_is_number(c, decimal) for c in rows[0]) \
            and any(_is_number(c, decimal) for c in rows[1])
    if units_row:
        if not rows:
            raise DataError(f"{name}: has no units row under the header")
        header = _cells(lines[0], delimiter)
        units = {column: unit for column, unit in zip(header, rows[0], strict=False)
                 if unit}
        metadata = {**(metadata or {}), "units": units}
    return Layout(start, metadata, delimiter, decimal, int(units_row))


def head(stream: IO[bytes], name: str, skip_rows: int = 0) -> bytes:
    """The start of a text read line by line: preamble, comment and blank lines, the
    header line and a few rows (what `layout` needs), each line at most
    `hamid.read_limits.LINE_BYTES` and all of them at most `hamid.read_limits.READ_BYTES`."""
    lines: list[bytes] = []
    more, size, longest = 0, 0, read_limits.LINE_BYTES
    while line := stream.readline(longest + 1):
        if len(line) > longest:
            raise DataError(f"{name}: line {len(lines) + 1:,} is longer than "
                            f"{longest >> 20} MiB; is it delimited text?")
        if size > read_limits.READ_BYTES:
            raise DataError(f"{name}: more than {read_limits.READ_BYTES >> 20} MiB of lines "
                            "before the data rows")
        text = line.removeprefix(UTF8_BOM) if not lines else line
        more += bool(more) or (len(lines) >= skip_rows and text.strip()
                               and not text.startswith(b"#"))
        lines.append(line)
        size += len(line)
        if more > _SNIFF_ROWS + 1:
            break
    return b"".join(lines)


def preamble_lines(text: bytes, delimiter: str) -> int:
    """How many lines a preamble seems to take at the start of `text` (a data logger's lines
    before the header): the first line from which on the header and the rows after it split
    into as many fields, more than one, at `delimiter` or at the delimiter sniffed from that
    line (a preamble's commas can make the whole text's sniffed delimiter wrong), the header
    holding names (no number). A guess for a hint, not a reading: 0 when the first
    line already starts such a table."""
    lines = [line.decode("utf-8", "replace") for line in text.removeprefix(UTF8_BOM).split(
        b"\n", _PREAMBLE_LINES)[:_PREAMBLE_LINES]]
    for first, line in enumerate(lines):
        if not line.strip():
            continue
        rows = [row for row in lines[first + 1:] if row.strip()][:_SNIFF_ROWS]
        if not rows:
            break
        for separator in {delimiter, _sniff_delimiter(line, tabs=True)}:
            fields = line.count(separator) + 1
            if (fields > 1 and all(row.count(separator) + 1 == fields for row in rows)
                    and not any(_is_number(cell, ",") for cell in _cells(line, separator))):
                return first
    return 0


def preamble_hint(data: bytes, layout: Layout) -> str:
    """The hint to a malformed row's error when the text seems to start with a preamble
    (`preamble_lines`), counting the lines skipped before the header already; else ""."""
    preamble = preamble_lines(data[layout.start:], layout.delimiter)
    if not preamble:
        return ""
    preamble += data.count(b"\n", 0, layout.start)   # skipped lines, comments
    return (f"; the file seems to start with {counted(preamble, 'line', 'lines')} before "
            f"its header: give --skip-rows {preamble}")


def points(column: Any) -> Any:
    """An Arrow column of text with its decimal commas as points (other columns as they
    are), for the cells that pyarrow left as text because one of them is not a number."""
    import pyarrow as pa
    import pyarrow.compute as pc

    if pa.types.is_string(column.type) or pa.types.is_large_string(column.type):
        return pc.replace_substring(column, ",", ".")
    return column


def _lines(data: bytes, start: int) -> list[str]:
    """Helper giving the header line and a few lines after it (non-blank), as text."""
    lines: list[str] = []
    while start < len(data) and len(lines) <= _SNIFF_ROWS:
        end = data.find(b"\n", start)
        end = len(data) if end < 0 else end
        line = data[start:end].rstrip(b"\r").decode("utf-8", errors="replace")
        if line.strip():
            lines.append(line)
        start = end + 1
    return lines


def _cells(line: str, delimiter: str) -> list[str]:
    return [cell.strip().strip('"').strip() for cell in line.split(delimiter)]


def _is_number(cell: str, decimal: str) -> bool:
    return bool(_NUMBER.fullmatch(cell.replace(",", ".") if decimal == "," else cell))


def _sniff_delimiter(header: str, tabs: bool) -> str:
    """Helper choosing tab (when `tabs`), semicolon or comma from the header line."""
    if tabs and "\t" in header:
        return "\t"
    return ";" if header.count(";") > header.count(",") else ","


def _skip_comments(data: bytes, start: int, name: str) -> tuple[int, dict[str, Any] | None]:
    """Helper function skipping leading ``#`` and blank lines and reading the metadata line."""
    metadata = None
    line_number = 0
    while start < len(data):
        end = data.find(b"\n", start)
        end = len(data) if end < 0 else end
        line = data[start:end].rstrip(b"\r")
        if line.strip() and not line.startswith(b"#"):
            break
        line_number += 1
        match = _METADATA_LINE.fullmatch(line)
        if match is not None and metadata is None:
            metadata = parse_metadata(match.group(1), name, line_number)
        start = end + 1
    return start, metadata


def parse_metadata(raw: bytes, name: str, line_number: int | None = None) -> dict[str, Any]:
    """Decode the JSON of hamid's metadata (of text, Parquet or a lab file)."""
    where = f"{name}: line {line_number}: " if line_number is not None else f"{name}: "
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataError(f"{where}the hamid metadata is not UTF-8 text") from exc
    metadata = json_value(text, f"{where}the hamid metadata")
    if not isinstance(metadata, dict):
        raise DataError(f"{where}the hamid metadata is not a JSON object "
                        f"(found {json_kind(metadata)})")
    return metadata


def json_kind(value: object) -> str:
    """The JSON type of a decoded value, in words."""
    kinds = {list: "an array", str: "a string", bool: "a boolean", type(None): "null"}
    return kinds.get(type(value), "a number")
