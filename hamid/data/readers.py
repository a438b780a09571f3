"""Reading files: data tables (whole or in chunks), their metadata, system files and reports.

Compressed text is decompressed here (`hamid.data.compressed`), the layout of text found by
`hamid.data.text_layout`, and MATLAB, HDF5, TDMS and UFF files read by `hamid.data.lab_formats`.

Every problem with a file becomes a `DataError` (or a `ModelError` for a system file) that
names the file, column and row at fault. Writing is `hamid.data.writing`.

pandas and pyarrow are imported inside the functions that need them.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat
import sys
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal

from hamid import read_limits
from hamid.data import compressed, lab_formats, text_layout
from hamid.errors import DataError, ModelError, UsageError
from hamid.safe_text import counted

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt
    import pandas as pd
    import pyarrow as pa

__all__ = ["as_numpy", "column_values", "file_digest", "is_missing", "is_parquet",
           "numeric_column", "not_utf8", "numeric_values", "opened", "read_bytes", "read_columns",
           "read_table"]

Format = Literal["csv", "tsv", "parquet"]


STDIN = "<stdin>"
STDOUT = "<stdout>"

_FORMATS: tuple[Format, ...] = ("csv", "tsv", "parquet")
_SUFFIX_FORMATS: dict[str, Format] = {
    ".csv": "csv",
    ".tsv": "tsv",
    ".tab": "tsv",
    ".parquet": "parquet",
    ".pq": "parquet",
}
_PARQUET_MAGIC = b"PAR1"
METADATA_KEY = b"hamid"
# pyarrow's block_size is an int32; a larger file falls back to reading text columns.
_MAX_BLOCK = 2**31 - 1
# Tables read whole use pyarrow's threads only past this size, where they gain: one still
# running at exit aborts the process (apache/arrow#34314), not to be risked for small files.
THREADED_BYTES = 16 << 20
_MAX_LISTED_COLUMNS = 20
_MAX_CELL_CHARS = 40


# ---------------------------------------------------------------------------------------------
# Reading data tables


def read_table(
    source: str | os.PathLike[str], *, format: str | None = None,
    text: text_layout.TextOptions | None = None,
) -> tuple[pd.DataFrame, dict[str, Any] | None]:
    """Read a CSV, TSV or Parquet table and its hamid metadata.

    Parameters
    ----------
    source : str or path-like
        File to read; ``"-"`` reads standard input.
    format : {"csv", "tsv", "parquet"}, optional
        Overrides the format implied by the extension. Without it, an unknown extension
        (and standard input) is recognised from the content, compressed text too.
    text : hamid.data.text_layout.TextOptions, optional
        Delimiter, decimal mark, preamble lines and units row of text; detected without.

    Returns
    -------
    table : pandas.DataFrame
        Columns in file order, with the file's names. Columns are not checked here;
        `numeric_column` checks each one that is used.
    metadata : dict or None
        The ``# hamid: {...}`` comment line of a CSV/TSV file, or the ``hamid`` key of a
        Parquet file's metadata; None when there is none.

    Raises
    ------
    DataError
        The file is missing, empty, has no data rows, is not valid CSV/TSV/Parquet, is not
        UTF-8 text, or has duplicated column names. The message starts with the file name.

    Examples
    --------
    >>> table, metadata = read_table("run3.csv")  # doctest: +SKIP
    >>> x = numeric_column(table, "x", source="run3.csv")  # doctest: +SKIP
    """
    if _is_lab_file(source, format):
        import pandas as pd

        columns, metadata = lab_formats.read(source)
        return pd.DataFrame(columns), metadata
    table, metadata, name = _read_arrow(source, format, text)
    return _to_pandas(table, name), metadata


def read_columns(
    source: str | os.PathLike[str], *, format: str | None = None,
    text: text_layout.TextOptions | None = None, name: str | None = None,
) -> tuple[dict[str, npt.NDArray[Any]], dict[str, Any] | None]:
    """`read_table` as numpy arrays by column name, in file order, without pandas (whose
    import costs a third of a second) unless a Parquet file stores a pandas index; `name`
    replaces the path in messages. MATLAB, HDF5, TDMS and UFF files: `hamid.data.lab_formats`."""
    if _is_lab_file(source, format):
        return lab_formats.read(source)
    table, metadata, name = _read_arrow(source, format, text, name)
    if _stores_pandas_index(table):
        frame = _to_pandas(table, name)
        return {column: frame[column].to_numpy() for column in frame.columns}, metadata
    names, arrays = table.column_names, table.columns[::-1]
    del table   # each column's chunks go once copied: not all of them twice at once
    return {name: as_numpy(arrays.pop()) for name in names}, metadata


def _read_arrow(source: str | os.PathLike[str], format: str | None,
                text: text_layout.TextOptions | None, name: str | None = None,
                ) -> tuple[pa.Table, dict[str, Any] | None, str]:
    """Helper reading a table file: its Arrow table, hamid metadata and name for messages."""
    fmt = check_format(format) if format is not None else input_format(source)
    data, read_name = read_bytes(source)
    name = name or read_name
    if not data or data.isspace():
        raise DataError(f"{name}: file is empty")
    data = compressed.decompressed(data, name)
    if not data or data.isspace():
        raise DataError(f"{name}: file is empty once decompressed")
    if fmt is None:
        fmt = "parquet" if data.startswith(_PARQUET_MAGIC) else None
    if fmt == "parquet":
        _check_parquet_magic(data, name)
        return (*_read_parquet(data, name), name)
    return (*_read_text(data, name, fmt, text), name)


def _is_lab_file(source: str | os.PathLike[str], format: str | None) -> bool:
    """Helper telling whether a source is read by `hamid.data.lab_formats` (by its extension)."""
    return format is None and not is_stdio(source) and lab_formats.format_of(source) is not None


json_kind = text_layout.json_kind


def is_parquet(source: str | os.PathLike[str]) -> bool:
    """Whether a file (not standard input) begins as Parquet does."""
    if is_stdio(source) or not os.path.isfile(source):
        return False
    with open(source, "rb") as stream:
        return stream.read(len(_PARQUET_MAGIC)) == _PARQUET_MAGIC


def _check_parquet_magic(data: bytes, name: str) -> None:
    """A Parquet file begins with its magic bytes; pyarrow only looks at the footer's, and
    read a file damaged at its start (or not Parquet at all, but for its last bytes)."""
    if not data.startswith(_PARQUET_MAGIC):
        raise DataError(f"{name}: is not a valid Parquet file (it does not begin with "
                        f"Parquet's magic bytes {_PARQUET_MAGIC.decode()!r}; if it is text, "
                        "give --format-in csv)")


def _read_parquet(data: bytes, name: str) -> tuple[pa.Table, dict[str, Any] | None]:
    """Helper function reading a Parquet file held in memory."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        parquet = pq.ParquetFile(pa.BufferReader(data))
        names = parquet.schema_arrow.names
        check_unique(names, name)
        table = parquet.read(use_threads=len(data) > THREADED_BYTES)
        # Parquet readers do not check that text is UTF-8; a damaged page would only fail
        # later, in pandas.
        table.validate(full=True)
        raw = (table.schema.metadata or {}).get(METADATA_KEY)
    except MemoryError:   # pyarrow's ArrowMemoryError is also an ArrowException
        raise
    except (pa.ArrowException, OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{name}: is not a valid Parquet file ({first_line(exc)})") from exc
    metadata = None
    if raw is not None:
        metadata = text_layout.parse_metadata(raw, name)
    if table.num_columns == 0:
        raise DataError(f"{name}: has no columns")
    if table.num_rows == 0:
        raise DataError(f"{name}: has columns but no data rows")
    return table, metadata


def _stores_pandas_index(table: pa.Table) -> bool:
    """Helper telling whether a table written by pandas stores its index as columns (or
    has pandas metadata too damaged to tell): only pandas restores such an index."""
    raw = (table.schema.metadata or {}).get(b"pandas")
    if raw is None:
        return False
    try:
        return any(not isinstance(index, dict) for index in json.loads(raw)["index_columns"])
    except (ValueError, TypeError, KeyError):
        return True


def as_numpy(column: pa.Array | pa.ChunkedArray) -> npt.NDArray[Any]:
    """An Arrow column as a numpy array: numbers without missing cells are a view of
    Arrow's memory (its to_numpy imports pandas), numbers with missing cells floats with
    NaN, anything else (text) objects."""
    import numpy as np
    import pyarrow as pa

    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    kind = ("f" if pa.types.is_floating(column.type) else
            "i" if pa.types.is_signed_integer(column.type) else
            "u" if pa.types.is_unsigned_integer(column.type) else None)
    if kind is None:
        return column.to_numpy(zero_copy_only=False)
    if column.null_count:
        return column.cast(pa.float64()).to_numpy(zero_copy_only=False)
    size = column.type.bit_width // 8
    return np.frombuffer(column.buffers()[1], dtype=f"{kind}{size}", count=len(column),
                         offset=column.offset * size)


def _to_pandas(table: pa.Table, name: str) -> pd.DataFrame:
    """Helper function converting an Arrow table read from a file to pandas."""
    import pyarrow as pa

    try:
        frame = table.to_pandas()
    except (pa.ArrowException, ValueError, TypeError, KeyError):
        # A damaged pandas entry in the Parquet metadata: the columns themselves are usable.
        try:
            frame = table.to_pandas(ignore_metadata=True)
        except (pa.ArrowException, ValueError, TypeError) as exc:
            raise DataError(f"{name}: cannot convert the table ({first_line(exc)})") from exc
    if not _is_default_index(frame):
        # pandas' to_parquet stores the index; a named index is data (e.g. the time column).
        unnamed = all(level is None for level in frame.index.names)
        frame = frame.reset_index(drop=unnamed)
    frame.columns = [str(column) for column in frame.columns]
    check_unique(list(frame.columns), name)
    return frame


def _is_default_index(frame: pd.DataFrame) -> bool:
    """Helper function telling whether a DataFrame's index is 0, 1, ... without a name."""
    import pandas as pd

    index = frame.index
    return (
        isinstance(index, pd.RangeIndex)
        and index.name is None
        and index.start == 0
        and index.step == 1
    )


def _read_text(
    data: bytes, name: str, fmt: Format | None, text: text_layout.TextOptions | None
) -> tuple[pa.Table, dict[str, Any] | None]:
    """Helper function reading CSV or TSV text; ``fmt=None`` sniffs the delimiter."""
    import pyarrow as pa

    if fmt is not None and data.startswith(_PARQUET_MAGIC):
        raise DataError(f"{name}: is a Parquet file, not {fmt.upper()} text")
    layout = text_layout.layout(data, name, fmt, text)
    try:
        table = _parse_csv(data, layout, name)
        names = table.column_names
    except UnicodeDecodeError as exc:
        raise not_utf8(data, name) from exc
    if any(pa.types.is_binary(field.type) for field in table.schema):
        # pyarrow reads cells that are not UTF-8 as bytes instead of failing.
        raise not_utf8(data, name)
    stripped = [column.strip() for column in names]
    check_unique(stripped, name)
    if table.num_rows == 0:
        raise DataError(f"{name}: has a header but no data rows")
    if layout.decimal == ",":   # a column left as text (a bad cell) is checked with points
        table = pa.table([text_layout.points(c) for c in table.columns], names=stripped)
    return table.rename_columns(stripped), layout.metadata


def _parse_csv(data: bytes, layout: text_layout.Layout, name: str) -> pa.Table:
    """Helper function parsing delimited text with pyarrow, typed if possible; a row of
    another number of fields than the header is named, with `--skip-rows N` when the text
    seems to start with N lines of preamble."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    body = pa.py_buffer(data)[layout.start:]
    # Only an empty cell is missing: 'n/a' in a number column must be reported, not hidden.
    convert = pacsv.ConvertOptions(null_values=[""], decimal_point=layout.decimal)
    parse = pacsv.ParseOptions(delimiter=layout.delimiter)
    read = pacsv.ReadOptions(skip_rows_after_names=layout.skip, use_threads=body.size >
                             THREADED_BYTES)
    try:
        return pacsv.read_csv(pa.BufferReader(body), read_options=read, parse_options=parse,
                              convert_options=convert)
    except MemoryError:   # pyarrow's ArrowMemoryError is also an ArrowException
        raise
    except pa.ArrowException:
        # pyarrow infers a column's type from the first block (1 MB) and fails when a later
        # block has a cell that does not fit. Read again as one block, so that such a column
        # becomes text and numeric_column can name the row; single-threaded, so a malformed
        # row is reported with its number.
        pass
    # pyarrow decodes a malformed row's text for the handler below, and a row that is not
    # UTF-8 would make that fail inside pyarrow; such a file is reported as not UTF-8.
    str(memoryview(body), "utf-8")
    bad_rows: list[Any] = []

    def on_invalid_row(row: Any) -> str:
        bad_rows.append(row)
        return "error"

    parse = pacsv.ParseOptions(delimiter=layout.delimiter, invalid_row_handler=on_invalid_row)
    block_size = min(body.size + 1, _MAX_BLOCK)
    read = pacsv.ReadOptions(use_threads=False, block_size=block_size,
                             skip_rows_after_names=layout.skip)
    try:
        return pacsv.read_csv(
            pa.BufferReader(body),
            read_options=read,
            parse_options=parse,
            convert_options=convert,
        )
    except pa.ArrowException as exc:
        if bad_rows:
            row = bad_rows[0]
            raise DataError(
                f"{name}: row {row.number - 1 - layout.skip} has "
                f"{counted(row.actual_columns, 'field', 'fields')} where the header has "
                f"{row.expected_columns}: {_cell(row.text)}"
                + text_layout.preamble_hint(data, layout)) from exc
        if body.size + 1 <= _MAX_BLOCK:
            raise DataError(f"{name}: not valid delimited text ({first_line(exc)})") from exc
    # Larger than one block can be: every column as text, numeric_column converts.
    convert = pacsv.ConvertOptions(null_values=[""], default_column_type=pa.string())
    read = pacsv.ReadOptions(skip_rows_after_names=layout.skip)
    try:
        return pacsv.read_csv(pa.BufferReader(body), read_options=read, parse_options=parse,
                              convert_options=convert)
    except pa.ArrowException as exc:
        raise DataError(f"{name}: not valid delimited text ({first_line(exc)})") from exc


def not_utf8(data: bytes, name: str, what: str = "",
              error: type[DataError | ModelError] = DataError) -> DataError | ModelError:
    """Helper function building the error for text that is not UTF-8; `what` prefixes the
    line (e.g. "not valid TOML: ")."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        byte = data[exc.start]
        return error(f"{name}: {what}line {line} is not UTF-8 text (byte 0x{byte:02x}); "
                     "save the file as UTF-8")
    return error(f"{name}: {what}is not UTF-8 text; save the file as UTF-8")


def check_unique(names: Sequence[str], name: str) -> None:
    """Helper function rejecting duplicated column names."""
    seen: set[str] = set()
    duplicated: list[str] = []
    for column in names:
        if column in seen and column not in duplicated:
            duplicated.append(column)
        seen.add(column)
    if duplicated:
        listed = ", ".join(repr(column) for column in duplicated)
        noun = "name" if len(duplicated) == 1 else "names"
        raise DataError(f"{name}: duplicated column {noun} {listed}")


class TableChunks:
    """A CSV, TSV or Parquet file read in chunks of rows, for data larger than memory.

    Opening reads the column names and the hamid metadata only; `chunks` reads the named
    columns chunk by chunk (Parquet batches, blocks of delimited text), each time from the
    start of the file, so a fit can take several passes in bounded memory.
    """

    def __init__(self, source: str | os.PathLike[str], *, format: str | None = None,
                 text: text_layout.TextOptions | None = None, name: str | None = None) -> None:
        self.path = source
        self.name = name or os.fsdecode(source)
        if _is_lab_file(source, format):   # read whole, given in chunks
            self.format, self.compression = "lab", None
            self._whole, self.metadata = lab_formats.read(source)
            self.columns = list(self._whole)
            return
        fmt = check_format(format) if format is not None else input_format(source)
        with opened(source, self.name) as stream:
            head = stream.read(compressed.HEAD_BYTES)
        if not head:
            raise DataError(f"{self.name}: file is empty")
        # Compressed text is decompressed as it is read, one block at a time.
        self.compression = compressed.codec_of(head)
        if self.compression is not None:
            with self._open() as stream:
                head = stream.read(len(_PARQUET_MAGIC))
            if head == _PARQUET_MAGIC or fmt == "parquet":
                raise DataError(f"{self.name}: a compressed Parquet file cannot be read in "
                                "chunks; decompress it first")
        head = head[:len(_PARQUET_MAGIC)]
        self.format = fmt or ("parquet" if head == _PARQUET_MAGIC else "csv")
        if self.format == "parquet":
            _check_parquet_magic(head, self.name)
            self._open_parquet()
        else:
            self._open_text(fmt, text)

    @contextlib.contextmanager
    def _open(self) -> Iterator[IO[bytes]]:
        """Helper opening the file, decompressing it as it is read when it is compressed."""
        with opened(self.path, self.name) as stream:
            if self.compression is None:
                yield stream
            else:
                with compressed.opened(stream, self.compression, self.name) as reader:
                    yield reader

    def _open_parquet(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        try:
            schema = pq.ParquetFile(self.path).schema_arrow
        except (pa.ArrowException, OSError) as exc:
            raise DataError(f"{self.name}: is not a valid Parquet file "
                            f"({first_line(exc)})") from exc
        self.columns = [str(name) for name in schema.names]
        check_unique(self.columns, self.name)
        raw = (schema.metadata or {}).get(METADATA_KEY)
        self.metadata = text_layout.parse_metadata(raw, self.name) if raw is not None else None

    def _open_text(self, fmt: Format | None, options: text_layout.TextOptions | None) -> None:
        with self._open() as stream:
            head = text_layout.head(stream, self.name, options.skip_rows if options else 0)
        self.layout = text_layout.layout(head, self.name, fmt, options)
        self.offset, self.metadata = self.layout.start, self.layout.metadata
        self.delimiter = self.layout.delimiter
        try:
            header = head[self.offset:].split(b"\n", 1)[0].rstrip(b"\r").decode("utf-8")
        except UnicodeDecodeError as exc:
            raise not_utf8(head, self.name) from exc
        raw = [cell.strip('"') for cell in header.split(self.delimiter)]
        self.columns = [cell.strip() for cell in raw]
        self._raw = dict(zip(self.columns, raw, strict=True))
        check_unique(self.columns, self.name)

    def chunks(self, columns: Sequence[str], rows: int) -> Iterator[dict[str, Any]]:
        """The named columns, about `rows` rows at a time, as numpy arrays."""
        names = list(dict.fromkeys(columns))
        if self.format == "lab":
            yield from lab_formats.chunks(self._whole, names, rows)
            return
        try:
            with _arrow_reading(self.name):
                for batch in self._batches(names, rows):
                    yield {name: as_numpy(self._points(batch.column(name)))
                           for name in batch.schema.names}
        except DataError:
            if self.format != "parquet":
                self._name_the_bad_cell(names, rows)
            raise

    def _name_the_bad_cell(self, columns: list[str], rows: int) -> None:
        """Raise the error that names the file row of a cell that is not a number.

        Text columns take their types from the first block, so a bad cell further on stops
        pyarrow with only the column's position; reading them again as text finds the row.
        """
        first_row = 1
        with _arrow_reading(self.name):
            for batch in self._batches(columns, rows, as_text=True):
                for name in batch.schema.names:
                    numeric_values(as_numpy(self._points(batch.column(name))), name,
                                   self.name, first_row=first_row)
                first_row += batch.num_rows

    def _points(self, column: Any) -> Any:
        """Helper giving text cells of a decimal-comma file with points."""
        decimal = self.layout.decimal if self.format not in ("parquet", "lab") else "."
        return text_layout.points(column) if decimal == "," else column

    def _batches(self, columns: list[str], rows: int, as_text: bool = False) -> Iterator[Any]:
        import pyarrow as pa
        import pyarrow.csv as pacsv
        import pyarrow.parquet as pq

        rows = min(rows, _MAX_BLOCK // 64)   # pyarrow's batch and block sizes are int32

        if self.format == "parquet":
            # one row group at a time: a reader over all of them buffers ever more of the
            # file (130 MB for twelve groups of 2^18 rows, against 30 MB for two)
            parquet = pq.ParquetFile(self.path)
            for group in range(parquet.num_row_groups):
                yield from parquet.iter_batches(batch_size=rows, columns=columns,
                                                row_groups=[group])
            return
        with compressed.arrow_stream(self.path, self.compression, self.name) as stream:
            stream.read(self.offset)   # comment lines and the byte-order mark
            block = max(rows * 64, 1 << 12)
            reader = pacsv.open_csv(
                stream,
                read_options=pacsv.ReadOptions(block_size=block,
                                               skip_rows_after_names=self.layout.skip),
                parse_options=pacsv.ParseOptions(delimiter=self.delimiter),
                convert_options=pacsv.ConvertOptions(
                    null_values=[""], decimal_point=self.layout.decimal,
                    include_columns=[self._raw[c] for c in columns],
                    column_types={self._raw[c]: pa.string() for c in columns} if as_text
                    else None))
            with contextlib.closing(reader), _rows_within(self.name, block):
                # closed, its read-ahead ends before the file closes
                for batch in reader:
                    yield batch.rename_columns([c.strip() for c in batch.schema.names])


@contextlib.contextmanager
def opened(source: str | os.PathLike[str], name: str) -> Iterator[IO[bytes]]:
    """A file opened for reading, with file errors as DataError naming it."""
    try:
        stream = open(source, "rb")  # noqa: SIM115 (closed below)
    except OSError as exc:
        raise _file_error(exc, source, name) from exc
    with stream:
        yield stream


@contextlib.contextmanager
def _rows_within(name: str, block: int) -> Iterator[None]:
    """Helper naming the error of pyarrow's chunked reader at a row longer than a block."""
    import pyarrow as pa

    try:
        yield
    except pa.ArrowInvalid as exc:
        if "straddl" not in str(exc):
            raise
        raise DataError(f"{name}: a row is longer than {block:,} bytes, the text read at a "
                        "time; is it delimited text?") from exc


@contextlib.contextmanager
def _arrow_reading(name: str) -> Iterator[None]:
    """Helper turning pyarrow's errors while reading chunks into a DataError."""
    import pyarrow as pa

    try:
        yield
    except UnicodeDecodeError as exc:
        raise DataError(f"{name}: is not UTF-8 text") from exc
    except MemoryError:   # pyarrow's ArrowMemoryError is also an ArrowException
        raise
    except (pa.ArrowException, OSError) as exc:
        raise DataError(f"{name}: cannot read ({first_line(exc)})") from exc


# ---------------------------------------------------------------------------------------------
# Checking a column


def numeric_column(table: pd.DataFrame | Mapping[str, Any], column: str, *,
                   source: str) -> npt.NDArray[np.float64]:
    """Return one column of a table as finite floating-point numbers.

    Parameters
    ----------
    table : pandas.DataFrame or mapping of column name to array
        Table as read by `read_table` or `read_columns`.
    column : str
        Name of the column.
    source : str
        File name used in messages.

    Returns
    -------
    values : ndarray, shape (n,)
        The column as float64.

    Raises
    ------
    DataError
        The column is missing, or a cell is not a number, is empty or NaN, or is infinite.
        The first bad row is named; rows count data rows from 1, the header not counted
        (the row's position in `table` plus one).

    Examples
    --------
    >>> import pandas as pd
    >>> numeric_column(pd.DataFrame({"x": [1, 2]}), "x", source="run.csv")
    array([1., 2.])
    """
    if column not in table:
        listed = list_columns(list(table))
        raise DataError(f"{source}: no column {column!r} (columns: {listed})")
    return numeric_values(column_values(table[column]), column, source)


def column_values(values: Any) -> npt.NDArray[Any]:
    """A column (numpy array or pandas Series) as a numpy array: numbers as floats with
    NaN for missing cells, anything else as objects."""
    import numpy as np

    if not hasattr(values, "to_numpy"):
        return np.asarray(values)
    if getattr(values.dtype, "kind", "O") in "iuf":
        return values.to_numpy(dtype=np.float64, na_value=np.nan)
    return values.to_numpy(dtype=object)


def numeric_values(values: npt.NDArray[Any], column: str, source: str, *,
                   first_row: int = 1) -> npt.NDArray[np.float64]:
    """Cells of one column (numbers, or text and other objects) as finite floats; errors
    name the row, counting the first of `values` as `first_row`."""
    import numpy as np

    if values.dtype.kind in "iuf":
        values = values.astype(np.float64, copy=False)
    else:
        values = _parse_cells(values, column, source, first_row)
    bad = ~np.isfinite(values)
    if bad.any():
        row = int(np.argmax(bad))
        problem = "missing value" if np.isnan(values[row]) else "infinite value"
        raise DataError(f"{source}: column {column!r}, row {row + first_row}: {problem}")
    return values


def _parse_cells(
    cells: npt.NDArray[np.object_], column: str, source: str, first_row: int = 1
) -> npt.NDArray[np.float64]:
    """Helper function converting cells of a text or mixed column to numbers."""
    import numpy as np

    values = np.empty(len(cells), dtype=np.float64)
    for row, cell in enumerate(cells):
        if isinstance(cell, str):
            text = cell.strip()
            if not text:
                values[row] = np.nan
                continue
            try:
                values[row] = float(text)
                continue
            except ValueError:
                pass
        elif isinstance(cell, (int, float, np.integer, np.floating)) and not isinstance(
            cell, (bool, np.bool_)
        ):
            values[row] = float(cell)
            continue
        elif is_missing(cell):
            values[row] = np.nan
            continue
        else:
            text = str(cell)
        if not np.isfinite(values[:row]).all():
            values[row:] = np.nan  # the caller reports the earlier missing or infinite value
            return values
        raise DataError(
            f"{source}: column {column!r}, row {row + first_row}: {_cell(text)} is not a number"
        )
    return values


def is_missing(cell: object) -> bool:
    """Whether a cell is missing: None, NaN, or one of pandas' markers when pandas is in use
    (a cell of a DataFrame)."""
    if cell is None or (isinstance(cell, float) and math.isnan(cell)):
        return True
    pandas = sys.modules.get("pandas")
    if pandas is None:
        return False
    try:
        return bool(pandas.isna(cell))
    except (TypeError, ValueError):
        return False


def list_columns(columns: Sequence[Any]) -> str:
    """Helper function listing column names in a message."""
    names = [str(column) for column in columns]
    if len(names) > _MAX_LISTED_COLUMNS:
        names = [*names[:_MAX_LISTED_COLUMNS], "..."]
    return ", ".join(names)


def _cell(text: str) -> str:
    """Helper function quoting a cell, shortened, in a message."""
    if len(text) > _MAX_CELL_CHARS:
        text = text[: _MAX_CELL_CHARS - 3] + "..."
    return repr(text)


# ---------------------------------------------------------------------------------------------
# Files and formats


def read_bytes(source: str | os.PathLike[str]) -> tuple[bytes, str]:
    """Helper function reading a whole file, or standard input for ``"-"``; a stream
    (standard input, a device, a FIFO) at most `hamid.read_limits.READ_BYTES`."""
    if is_stdio(source):
        if sys.stdin is None:   # a process started without one (pythonw, a closed fd 0)
            raise DataError(f"{STDIN}: cannot read: standard input is closed")
        try:
            return read_limits.read_at_most(sys.stdin.buffer, STDIN, "standard input"), STDIN
        except OSError as exc:
            raise DataError(f"{STDIN}: cannot read: {os_reason(exc)}") from exc
    name = os.fsdecode(source)
    with opened(source, name) as stream:
        try:
            if stat.S_ISREG(os.fstat(stream.fileno()).st_mode):
                return stream.read(), name
            return read_limits.read_at_most(stream, name, "a device or pipe"), name
        except OSError as exc:
            raise _file_error(exc, source, name) from exc


def file_digest(source: str | os.PathLike[str]) -> tuple[int, str]:
    """A file's size in bytes and SHA-256 (hex), read in one streaming pass of 1 MiB blocks
    (memory does not grow with the file; a file read in chunks is not held whole)."""
    import hashlib

    name = os.fsdecode(source)
    digest, size = hashlib.sha256(), 0
    block = bytearray(1 << 20)
    view = memoryview(block)
    with opened(source, name) as stream:
        try:
            while n := stream.readinto(view):
                digest.update(view[:n])
                size += n
        except OSError as exc:
            raise _file_error(exc, source, name) from exc
    return size, digest.hexdigest()


def _file_error(exc: OSError, source: str | os.PathLike[str], name: str) -> DataError:
    """Helper naming what went wrong opening or reading a file."""
    if isinstance(exc, FileNotFoundError):
        return DataError(f"{name}: no such file")
    if isinstance(exc, IsADirectoryError) or os.path.isdir(source):
        return DataError(f"{name}: is a folder, not a file")
    return DataError(f"{name}: cannot read: {os_reason(exc)}")


def is_stdio(path: str | os.PathLike[str]) -> bool:
    """Helper function telling whether a file name means standard input or output."""
    return isinstance(path, str) and path == "-"


def check_format(format: str) -> Format:
    """Helper function validating a format name given by the caller."""
    fmt = format.lower()
    if fmt not in _FORMATS:
        raise UsageError(f"unknown data format {format!r} (choose csv, tsv or parquet)")
    return fmt  # type: ignore[return-value]


def format_from_suffix(path: str | os.PathLike[str]) -> Format | None:
    """Helper function giving the format implied by a file's extension, if any."""
    if is_stdio(path):
        return None
    return _SUFFIX_FORMATS.get(Path(os.fsdecode(path)).suffix.lower())


def input_format(path: str | os.PathLike[str]) -> Format | None:
    """The format implied by the extension of a file to read (``run.csv.gz`` is CSV)."""
    return None if is_stdio(path) else _SUFFIX_FORMATS.get(compressed.suffix(path))


def os_reason(exc: OSError) -> str:
    """Helper function giving the system's reason for an OSError."""
    return exc.strerror or str(exc)


def first_line(exc: BaseException) -> str:
    """Helper function giving the first line of an exception's message."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__
