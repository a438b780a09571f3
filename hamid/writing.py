"""Writing outputs: tables (CSV, TSV, Parquet) and text, atomically or all at once.

Every output goes to a temporary file in the destination's folder and is renamed over the
destination only when complete, so a failure or Ctrl-C never leaves a half-written file.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from hamid import io
from hamid.errors import DataError, UsageError
from hamid.io import STDOUT, Format

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

__all__ = ["all_or_nothing", "check_destination", "table_format", "write_table", "write_text"]


def write_table(
    table: pd.DataFrame,
    dest: str | os.PathLike[str],
    *,
    format: str | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> None:
    """Write a table as CSV, TSV or Parquet, atomically.

    Parameters
    ----------
    table : pandas.DataFrame
        Table to write; its index is not written.
    dest : str or path-like
        Destination file; ``"-"`` writes to standard output.
    format : {"csv", "tsv", "parquet"}, optional
        Overrides the format implied by the extension (CSV for standard output).
    metadata : dict, optional
        Stored as the first line ``# hamid: {json}`` of CSV/TSV, or as the ``hamid`` key of
        the Parquet metadata.

    Raises
    ------
    UsageError
        The format cannot be told from the destination's extension.
    DataError
        The destination cannot be written.

    Examples
    --------
    >>> write_table(table, "run.parquet", metadata={"seed": 0})  # doctest: +SKIP
    """
    name = _output_name(dest)
    fmt = table_format(dest, format)
    metadata_json = _dump_metadata(metadata) if metadata is not None else None
    io.check_unique([str(column) for column in table.columns], name)
    arrow = _to_arrow(table, name)
    _WRITERS[fmt](arrow, metadata_json, dest, name)


def table_format(dest: str | os.PathLike[str], format: str | None = None) -> Format:
    """The format a table written to `dest` will have; a UsageError if it cannot be told.

    Callers check this before long work, so that a bad output name fails at once.
    """
    if format is not None:
        return io.check_format(format)
    if io.is_stdio(dest):
        return "csv"
    fmt = io.format_from_suffix(dest)
    if fmt is None:
        raise _unknown_extension(dest)
    return fmt


def _to_arrow(table: pd.DataFrame, name: str) -> pa.Table:
    """Helper function converting a DataFrame to Arrow before any file is opened."""
    import pyarrow as pa

    try:
        return pa.Table.from_pandas(table, preserve_index=False)
    except (pa.ArrowException, ValueError, TypeError) as exc:
        raise DataError(f"{name}: cannot write the table ({io.first_line(exc)})") from exc


def _write_delimited(
    table: pa.Table,
    metadata_json: str | None,
    dest: str | os.PathLike[str],
    name: str,
    delimiter: str,
) -> None:
    """Helper function writing CSV or TSV, with the metadata as a first comment line."""
    import pyarrow.csv as pacsv

    # pyarrow quotes every header name unless told not to; a plain header is friendlier to
    # awk and spreadsheets, and pyarrow refuses "none" for names that need quotes.
    structural = (delimiter, '"', "\n", "\r")
    plain = all(not any(c in column for c in structural) for column in table.column_names)
    plain = plain and not (table.column_names and table.column_names[0].startswith("#"))
    options = pacsv.WriteOptions(delimiter=delimiter, quoting_header="none" if plain else "needed")

    def write(stream: IO[bytes]) -> None:
        if metadata_json is not None:
            stream.write(f"# hamid: {metadata_json}\n".encode())
        # Floats are written in their shortest round-trip form (1.0 as "1"), integers as
        # integers.
        with _arrow_errors(name):
            pacsv.write_csv(table, stream, write_options=options)

    _write_output(dest, name, write, binary=False)


def _write_csv(table: pa.Table, metadata_json: str | None, dest: Any, name: str) -> None:
    """Helper function writing CSV."""
    _write_delimited(table, metadata_json, dest, name, ",")


def _write_tsv(table: pa.Table, metadata_json: str | None, dest: Any, name: str) -> None:
    """Helper function writing TSV."""
    _write_delimited(table, metadata_json, dest, name, "\t")


def _write_parquet(table: pa.Table, metadata_json: str | None, dest: Any, name: str) -> None:
    """Helper function writing Parquet, with the metadata beside pandas' own."""
    import pyarrow.parquet as pq

    if metadata_json is not None:
        merged = dict(table.schema.metadata or {})
        merged[io.METADATA_KEY] = metadata_json.encode()
        table = table.replace_schema_metadata(merged)

    def write(stream: IO[bytes]) -> None:
        with _arrow_errors(name):
            pq.write_table(table, stream)

    _write_output(dest, name, write, binary=True)


@contextlib.contextmanager
def _arrow_errors(name: str) -> Iterator[None]:
    """Helper function turning pyarrow's errors while writing into a DataError."""
    import pyarrow as pa

    try:
        yield
    except pa.ArrowException as exc:
        raise DataError(f"{name}: cannot write ({io.first_line(exc)})") from exc


_WRITERS: dict[Format, Callable[[Any, str | None, Any, str], None]] = {
    "csv": _write_csv,
    "tsv": _write_tsv,
    "parquet": _write_parquet,
}


def write_text(text: str, dest: str | os.PathLike[str]) -> None:
    """Write text as UTF-8, atomically.

    Parameters
    ----------
    text : str
        Text to write, as is.
    dest : str or path-like
        Destination file; ``"-"`` writes to standard output.

    Examples
    --------
    >>> write_text(json.dumps(result.to_dict()), "result.json")  # doctest: +SKIP
    """
    data = text.encode("utf-8")
    _write_output(dest, _output_name(dest), lambda stream: stream.write(data), binary=False)


def _write_output(
    dest: str | os.PathLike[str],
    name: str,
    write: Callable[[IO[bytes]], object],
    *,
    binary: bool,
) -> None:
    """Helper function sending bytes to standard output or atomically to a file."""
    if io.is_stdio(dest):
        _write_stdout(write, binary=binary)
    else:
        _write_atomic(Path(os.fspath(dest)), name, write)


def _write_stdout(write: Callable[[IO[bytes]], object], *, binary: bool) -> None:
    """Helper function writing bytes to standard output, after any text already there."""
    import io

    sys.stdout.flush()
    buffer = getattr(sys.stdout, "buffer", None)
    if buffer is not None:
        write(buffer)
        buffer.flush()
        return
    # A text-only stream, as some embedding applications install: text goes through as text.
    if binary:
        raise DataError(f"{STDOUT}: cannot write Parquet to a text-only output stream")
    collected = io.BytesIO()
    write(collected)
    sys.stdout.write(collected.getvalue().decode("utf-8"))
    sys.stdout.flush()


def check_destination(dest: str | os.PathLike[str]) -> None:
    """Fail at once, before long work, if an output file cannot be created.

    Parameters
    ----------
    dest : str or path-like
        Destination file; ``"-"`` (standard output) always passes.

    Raises
    ------
    DataError
        The destination is a folder, or its folder does not exist.
    """
    if io.is_stdio(dest):
        return
    path, name = Path(os.fspath(dest)), os.fsdecode(dest)
    if path.is_dir():
        raise DataError(f"{name}: is a folder, not a file")
    if not path.parent.is_dir():
        raise DataError(f"{name}: cannot write: folder {str(path.parent)!r} does not exist")


# Renames held back by `all_or_nothing`: (temporary, destination, name).
_held: list[tuple[str, Path, str]] | None = None


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Files written inside appear together at the end, or none of them does.

    Each file is written to its temporary as usual; the renames onto the destinations wait
    until the block ends without an error. On any error (Ctrl-C included) the temporaries
    are removed and every destination is left as it was. Standard output is not held back.

    Examples
    --------
    >>> with all_or_nothing():  # doctest: +SKIP
    ...     write_table(residuals, "residuals.csv")
    ...     write_text(report, "report.json")
    """
    global _held
    outer, held = _held, []
    _held = held
    try:
        yield
    except BaseException:
        for temporary, _, _ in held:
            _remove_quietly(temporary)
        raise
    finally:
        _held = outer
    for k, (temporary, path, name) in enumerate(held):
        try:
            os.replace(temporary, path)
        except BaseException as exc:
            for later, _, _ in held[k:]:
                _remove_quietly(later)
            if isinstance(exc, OSError):
                raise DataError(f"{name}: cannot write: {io.os_reason(exc)}") from exc
            raise
        _sync_folder(path.parent)


def _write_atomic(path: Path, name: str, write: Callable[[IO[bytes]], object]) -> None:
    """Helper function writing through a temporary file in the destination's folder."""
    if path.is_dir():
        raise DataError(f"{name}: is a folder, not a file")
    folder = path.parent
    try:
        fd, temporary = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    except FileNotFoundError as exc:
        raise DataError(f"{name}: cannot write: folder {str(folder)!r} does not exist") from exc
    except OSError as exc:
        raise DataError(f"{name}: cannot write in folder {str(folder)!r}: "
                        f"{io.os_reason(exc)}") from exc
    try:
        with os.fdopen(fd, "wb") as stream:
            write(stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.chmod(temporary, _new_file_mode(path))
        if _held is not None:
            _held.append((temporary, path, name))
            return
        os.replace(temporary, path)
    except OSError as exc:
        _remove_quietly(temporary)
        raise DataError(f"{name}: cannot write: {io.os_reason(exc)}") from exc
    except BaseException:
        # KeyboardInterrupt included: the destination is left as it was.
        _remove_quietly(temporary)
        raise
    _sync_folder(folder)


def _new_file_mode(path: Path) -> int:
    """Helper function giving the permissions the written file should have.

    mkstemp creates files readable by their owner only; an output file should have the
    permissions the file it replaces had, or the usual ones for a new file.
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def _remove_quietly(path: str) -> None:
    """Helper function removing a temporary file that may already be gone."""
    with contextlib.suppress(OSError):
        os.unlink(path)


def _sync_folder(folder: Path) -> None:
    """Helper function making a rename durable; not every system can open a folder."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _dump_metadata(metadata: Mapping[str, Any]) -> str:
    """Helper function encoding metadata as one line of strict JSON."""
    return json.dumps(metadata, separators=(",", ":"), allow_nan=False, default=_json_default)


def _json_default(value: Any) -> Any:
    """Helper function encoding numpy scalars and arrays, which json does not know."""
    if hasattr(value, "tolist"):
        return value.tolist()
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


def _output_name(dest: str | os.PathLike[str]) -> str:
    """Helper function naming a destination in messages."""
    return STDOUT if io.is_stdio(dest) else os.fsdecode(dest)


def _unknown_extension(dest: str | os.PathLike[str]) -> UsageError:
    """Helper function building the error for an output whose format is not known."""
    name = os.fsdecode(dest)
    suffix = Path(name).suffix
    if not suffix:
        return UsageError(
            f"{name}: cannot tell the format without an extension (.csv, .tsv or .parquet); "
            "give the format"
        )
    return UsageError(
        f"{name}: unknown extension {suffix!r} (use .csv, .tsv, .tab, .parquet or .pq, "
        "or give the format)"
    )
