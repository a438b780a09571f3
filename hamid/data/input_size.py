"""An input before it is read: the memory its table takes once decoded, which decides
whether a fit reads it in chunks, and standard input kept in a temporary file, so that it
is read (in chunks too) like any file; data given in memory (a DataFrame, a dict of arrays)
read as a table.

A file's size on disk says little about the memory it needs: a Parquet file of
repetitive data decodes to five times its size, and compressed text to many times more.
The decoded size counts 8 bytes a cell: a Parquet file's rows and columns are in its
metadata; text's rows are estimated from the bytes per row of its first lines (after
decompression), its columns from its header line.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
import tempfile
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hamid.data import compressed, lab_formats, readers, text_layout
from hamid.errors import DataError

__all__ = ["Spooled", "decoded_bytes", "in_memory_name", "in_memory_table", "name_of",
           "spooled"]

# The start of a text file whose rows are counted: enough lines for a steady mean.
SAMPLE_BYTES = 1 << 20
CELL_BYTES = 8


def decoded_bytes(path: str | os.PathLike[str], *, format: str | None = None,
                  text: text_layout.TextOptions | None = None) -> int:
    """The bytes a table file takes once decoded, 8 a cell (an estimate for text).

    Parameters
    ----------
    path : str or path-like
        A file (not standard input).
    format : {"csv", "tsv", "parquet"}, optional
        As given to the fit; else told from the extension and the content.
    text : hamid.data.text_layout.TextOptions, optional
        The layout options of text (for its delimiter and preamble).

    Returns
    -------
    size : int
        Rows times columns times 8. Lab files (read whole in any case) and files that
        cannot be made sense of give their size on disk: reading them reports what is
        wrong.
    """
    on_disk = os.path.getsize(path)
    if format is None and lab_formats.format_of(path) is not None:
        return on_disk
    fmt = readers.check_format(format) if format is not None else readers.input_format(path)
    name = name_of(path)
    with readers.opened(path, name) as stream:
        head = stream.read(compressed.HEAD_BYTES)
    codec = compressed.codec_of(head)
    if codec is None and (fmt == "parquet" or fmt is None and head.startswith(b"PAR1")):
        return _parquet_bytes(path, on_disk)
    sample, whole, ratio = _text_sample(path, codec, name)
    try:
        return _text_bytes(sample, whole, on_disk * ratio, fmt, text, name)
    except DataError:
        return on_disk


def _parquet_bytes(path: str | os.PathLike[str], on_disk: int) -> int:
    """Helper: rows times columns times 8, from a Parquet file's metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        metadata = pq.ParquetFile(path).metadata
    except (pa.ArrowException, OSError):
        return on_disk
    return metadata.num_rows * metadata.num_columns * CELL_BYTES


def _text_bytes(sample: bytes, whole: bool, size: float, fmt: str | None,
                options: text_layout.TextOptions | None, name: str) -> int:
    """Helper: the rows of text (its `size` decompressed over the bytes per row of its
    first lines) times the cells of its header line, times 8."""
    if not whole:
        sample = sample[:sample.rfind(b"\n") + 1]
    layout = text_layout.layout(sample, name, fmt, options)
    header, _, rows = sample[layout.start:].partition(b"\n")
    n_rows = rows.count(b"\n") + (whole and not rows.endswith(b"\n") and bool(rows.strip()))
    cells = header.count(layout.delimiter.encode()) + 1
    if whole or not n_rows:
        return max(n_rows, 1) * cells * CELL_BYTES
    text = size - layout.start - len(header) - 1   # of the rows, decompressed
    return int(text / (len(rows) / n_rows) * cells * CELL_BYTES)


def _text_sample(path: str | os.PathLike[str], codec: str | None,
                 name: str) -> tuple[bytes, bool, float]:
    """Helper: the first `SAMPLE_BYTES` of text (decompressed), whether they are all of
    it, and the bytes of text per byte of the file.

    A compressed file is read from in 64 KiB pieces, and its codec reads the file in
    blocks ahead of them; the ratio is the text given between the first block read and the
    last over the file's bytes read between them (three blocks on, within a few percent).
    At most 16 samples of text are decompressed, whatever the file's lines (a bomb of
    zeros).
    """
    with readers.opened(path, name) as raw:
        if codec is None:
            sample = raw.read(SAMPLE_BYTES)
            whole = len(sample) < SAMPLE_BYTES
            return sample if whole else _lines_checked(sample, name), whole, 1.0
        with compressed.opened(raw, codec, name) as stream:
            kept, given, blocks = bytearray(), 0, []
            read = raw.tell()
            while piece := stream.read(1 << 16):
                if raw.tell() != read and read:   # a block was read for this piece
                    blocks.append((given, read))
                read, given = raw.tell(), given + len(piece)
                kept += piece[:SAMPLE_BYTES - len(kept)]
                if len(kept) >= SAMPLE_BYTES and len(blocks) >= 3 \
                        or given >= 16 * SAMPLE_BYTES:
                    if len(blocks) < 2:   # a bomb: all of it in one block
                        blocks = [(0, 0), (given, read)]
                    (given_0, read_0), (given_1, read_1) = blocks[0], blocks[-1]
                    ratio = (given_1 - given_0) / (read_1 - read_0)
                    return _lines_checked(bytes(kept), name), False, ratio
            # all of it read: the ratio is exact
            return bytes(kept), given == len(kept), given / max(raw.tell(), 1)


def _lines_checked(sample: bytes, name: str) -> bytes:
    """Helper: the start of a text that goes on, refused when it holds no line break (no
    table: a header of millions of cells, or none at all)."""
    if b"\n" not in sample:
        raise DataError(f"{name}: its first line is longer than {len(sample):,} bytes; "
                        "it is not a table of delimited text")
    return sample


@dataclass(frozen=True)
class Spooled(os.PathLike):  # type: ignore[type-arg]
    """A temporary file holding what was read from standard input, named as it."""

    path: str
    name: str = readers.STDIN

    def __fspath__(self) -> str:
        return self.path


def name_of(source: Any) -> str:
    """The name of a source in messages and reports: ``<stdin>`` for standard input,
    spooled or not, else its path."""
    if isinstance(source, Spooled):
        return source.name
    return readers.STDIN if readers.is_stdio(source) else os.fsdecode(source)


@contextlib.contextmanager
def spooled(data: Any) -> Iterator[Any]:
    """The data with standard input (``"-"``, alone or in a list) copied to a temporary
    file in blocks of 1 MiB, deleted at the end; other data as they are.

    A fit passes over a file read in chunks several times, which standard input cannot
    be; held in a file, it is read as a file is, in chunks when large.
    """
    items = list(data) if isinstance(data, list | tuple) else [data]
    if not any(isinstance(item, str) and readers.is_stdio(item) for item in items):
        yield data
        return
    if sys.stdin is None:   # a process started without one (pythonw, a closed fd 0)
        raise DataError(f"{readers.STDIN}: cannot read: standard input is closed")
    try:
        folder = tempfile.TemporaryDirectory(prefix="hamid-stdin-")
    except OSError as exc:
        raise _unkept(exc) from exc
    with folder:
        path = os.path.join(folder.name, "stdin")
        _copy_stdin(path)
        spool = Spooled(path)
        items = [spool if isinstance(item, str) and readers.is_stdio(item) else item
                 for item in items]
        yield items if isinstance(data, list | tuple) else items[0]


def _copy_stdin(path: str) -> None:
    """Helper: standard input into the file `path`, 1 MiB at a time."""
    try:
        # closing writes what is still buffered: a full disk can show there too
        with open(path, "wb") as copy:
            while block := _stdin_block():
                copy.write(block)
    except OSError as exc:
        raise _unkept(exc) from exc


def _stdin_block() -> bytes:
    """Helper: the next MiB of standard input, empty at its end."""
    try:
        return sys.stdin.buffer.read(1 << 20)
    except OSError as exc:
        raise DataError(f"{readers.STDIN}: cannot read: {readers.os_reason(exc)}") from exc


def _unkept(exc: OSError) -> DataError:
    """Helper: the error when standard input cannot be kept in a temporary file."""
    folder = tempfile.gettempdir()
    if exc.errno == errno.ENOSPC:
        return DataError(f"{readers.STDIN}: cannot keep it in a temporary file: the temporary "
                         f"folder {folder} is full; set TMPDIR to a folder with room, or "
                         "give a file")
    return DataError(f"{readers.STDIN}: cannot keep it in a temporary file in {folder} "
                     f"({readers.os_reason(exc)}); set TMPDIR to a folder with room, or give "
                     "a file")


def in_memory_name(data: Any) -> str | None:
    """The name of data given in memory, in messages and the report's sources:
    ``<DataFrame>`` (pandas), ``<array>`` (a NumPy structured array) or ``<dict>`` (a
    mapping of column name to array); None for files."""
    pandas = sys.modules.get("pandas")   # no import: a DataFrame needs pandas loaded
    if pandas is not None and isinstance(data, pandas.DataFrame):
        return "<DataFrame>"
    if isinstance(data, np.ndarray) and data.dtype.names:
        return "<array>"
    return "<dict>" if isinstance(data, Mapping) else None


def in_memory_table(data: Any) -> tuple[str, Mapping[str, Any], Any] | None:
    """Data given in memory as a table, read as a file's columns would be: its name
    (`in_memory_name`), its columns and its metadata (a DataFrame's ``attrs["hamid"]``);
    None for files."""
    name = in_memory_name(data)
    if name == "<DataFrame>":
        # the columns of a frame without its attrs: pandas deep-copies them on every column
        # taken, and a simulated record's provenance lists every trajectory (5,000
        # trajectories: a second of copies)
        return name, type(data)(data, copy=False), data.attrs.get("hamid")
    if name == "<array>":
        return name, {field: data[field] for field in data.dtype.names}, None
    if name is None:
        return None
    columns = {str(key): np.asarray(values) for key, values in data.items()}
    for key, values in columns.items():
        if values.ndim != 1:
            raise DataError(f"{name}: column {key!r} has shape {values.shape}; give one "
                            "one-dimensional array per column")
    if len({len(values) for values in columns.values()}) > 1:
        listed = ", ".join(f"{key}: {len(values)}" for key, values in columns.items())
        raise DataError(f"{name}: the columns have different lengths ({listed})")
    return name, columns, None
