"""Writing outputs: tables (CSV, TSV, Parquet) and text, atomically or all at once.

How an output is written depends on what it names (`hamid.data.destinations`):

- A regular file, a new name, or a symlink (to a file, or to nothing) is written to a
  temporary file in its folder and renamed onto the name only when complete, so a failure,
  Ctrl-C or a termination signal never leaves a half-written or damaged file, nor a
  temporary one. A symlink is replaced itself, never written through. A file the caller
  may not write is refused, as cp refuses it.
- Anything else is written in place, as a stream, since replacing it would destroy it:
  standard output (``"-"``); ``/dev/stdout``, ``/dev/fd/N`` and ``/proc/self/fd/N``, which
  name a descriptor of this process and are written through it (so ``>>`` keeps appending);
  devices such as ``/dev/null``; FIFOs (which wait for their reader).

`check_destination` finds before long work what can be known then: a missing or unwritable
folder, a read-only file, a name too long, a closed standard output, Parquet bound for a
terminal. `Outputs` holds a command's inputs and outputs: no output may be an input or
another output, checked before the work and again as each file is written.
"""

from __future__ import annotations

import codecs
import contextlib
import errno
import functools
import json
import os
import signal
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

from hamid.data import readers
from hamid.data.destinations import (
    Destination,
    fd_isatty,
    isatty,
    overwrites,
    resolve,
    same_file,
    stdout_open,
)
from hamid.data.readers import STDOUT, Format
from hamid.errors import DataError, UsageError
from hamid.safe_text import printable

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

__all__ = ["Outputs", "all_or_nothing", "check_destination", "create_fresh",
           "remove_temporaries", "table_format", "write_bytes", "write_table", "write_text"]

Write = Callable[[IO[bytes]], object]


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
        The format cannot be told from the destination's extension, or Parquet would go to
        a terminal.
    DataError
        The destination cannot be written.

    Examples
    --------
    >>> write_table(table, "run.parquet", metadata={"seed": 0})  # doctest: +SKIP
    """
    name = _output_name(dest)
    fmt = table_format(dest, format)
    metadata_json = _dump_metadata(metadata) if metadata is not None else None
    readers.check_unique([str(column) for column in table.columns], name)
    arrow = _to_arrow(table, name)
    _WRITERS[fmt](arrow, metadata_json, dest, name)


def table_format(dest: str | os.PathLike[str], format: str | None = None) -> Format:
    """The format a table written to `dest` will have; a UsageError if it cannot be told.

    CSV for standard output and for any other stream without a known extension
    (``/dev/stdout``, ``/dev/null``, a FIFO). Callers check this before long work, so that a
    bad output name fails at once.
    """
    if format is not None:
        return readers.check_format(format)
    if readers.is_stdio(dest):
        return "csv"
    fmt = readers.format_from_suffix(dest)
    if fmt is None:
        if _is_stream(dest):
            return "csv"
        raise _unknown_extension(dest)
    return fmt


def _is_stream(dest: str | os.PathLike[str]) -> bool:
    """Helper function: whether an output is written in place (a descriptor, a device)."""
    try:
        return resolve(dest).kind != "file"
    except DataError:
        return False


def _to_arrow(table: pd.DataFrame, name: str) -> pa.Table:
    """Helper function converting a DataFrame to Arrow before any file is opened."""
    import pyarrow as pa

    try:
        return pa.Table.from_pandas(table, preserve_index=False)
    except (pa.ArrowException, ValueError, TypeError) as exc:
        raise DataError(f"{name}: cannot write the table ({readers.first_line(exc)})") from exc


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

    _write_output(dest, write, binary=False, escape_on_terminal=True)


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
        merged[readers.METADATA_KEY] = metadata_json.encode()
        table = table.replace_schema_metadata(merged)

    def write(stream: IO[bytes]) -> None:
        with _arrow_errors(name):
            pq.write_table(table, stream)

    _write_output(dest, write, binary=True)


@contextlib.contextmanager
def _arrow_errors(name: str) -> Iterator[None]:
    """Helper function turning pyarrow's errors while writing into a DataError.

    An OSError of the stream (a full disk) passes through pyarrow as itself, and is
    reported by the code that opened the stream.
    """
    import pyarrow as pa

    try:
        yield
    except pa.ArrowException as exc:
        if isinstance(exc, MemoryError):
            raise
        raise DataError(f"{name}: cannot write ({readers.first_line(exc)})") from exc


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
    _write_output(dest, lambda stream: stream.write(data), binary=False)


def write_bytes(data: bytes, dest: str | os.PathLike[str]) -> None:
    """Write bytes (a rendered figure) atomically; never to a terminal."""
    _write_output(dest, lambda stream: stream.write(data), binary=True)


# ---------------------------------------------------------------------------------------------
# Before the work


def check_destination(dest: str | os.PathLike[str], *, binary: bool = False) -> None:
    """Fail at once, before long work, if an output cannot be written.

    Parameters
    ----------
    dest : str or path-like
        Destination file; ``"-"`` is standard output.
    binary : bool, optional
        The output is binary (Parquet), which must not go to a terminal.

    Raises
    ------
    DataError
        The destination is a folder; its folder does not exist or takes no new file (a
        temporary file is created there and removed, as the write will); the file exists and
        the caller may not write it; its name is too long; standard output is closed.
    UsageError
        Binary output would go to a terminal.
    """
    target = resolve(dest)
    if target.kind == "file":
        _check_writable(target)
        fd, temporary = _create_temporary(target)
        os.close(fd)
        _remove(temporary)
    elif target.kind == "descriptor":
        _check_descriptor(target, binary)
    elif not _writable(target.path):
        raise DataError(f"{target.name}: cannot write: permission denied")


def _check_writable(target: Destination) -> None:
    """Helper function refusing to replace an existing file the caller may not write (a
    symlink is replaced itself, whatever it leads to)."""
    if _own_mode(target.path) is not None and not _writable(target.path):
        raise DataError(f"{target.name}: cannot write: the file is read-only (permission "
                        "denied); it is left as it is")


def _writable(path: Path) -> bool:
    """Helper function: whether the caller may write a file (its effective ids, as open's)."""
    effective = os.access in os.supports_effective_ids
    return os.access(path, os.W_OK, effective_ids=effective)


def _check_descriptor(target: Destination, binary: bool) -> None:
    """Helper function checking an open descriptor (standard output) before long work."""
    if target.fd == 1:
        if not stdout_open():
            raise DataError(f"{target.name}: cannot write: standard output is closed")
        terminal = isatty(sys.stdout)
    else:
        try:
            os.fstat(target.fd)
        except OSError as exc:
            raise DataError(f"{target.name}: cannot write: descriptor {target.fd} is "
                            "closed") from exc
        terminal = fd_isatty(target.fd)
    if binary and terminal:
        raise _binary_to_terminal(target.name)


def _binary_to_terminal(name: str) -> UsageError:
    """Helper function building the refusal to send Parquet to a terminal."""
    return UsageError(f"{name}: refusing to write Parquet, a binary format, to a terminal; "
                      "write it to a file or redirect the output")


class Outputs:
    """The outputs of one command, checked against its inputs and against each other.

    No output may be an input (the same file, through ``..``, symlinks or hard links) nor
    another output of the same command (the same name, or the same file). `claim` checks
    an output before any work, with `check_destination`; the command claims every name it
    may write, those it derives included (a figure's panel files, ``OUT.partial``,
    numbered realizations). Inside ``with outputs:``, every file this module writes is
    checked again as it is written, against the inputs and the files written before it:
    the one place no writer goes around.

    Examples
    --------
    >>> with Outputs(["data.csv"]) as outputs:  # doctest: +SKIP
    ...     outputs.claim("-o", "report.json")
    ...     write_text(report, "report.json")
    """

    def __init__(self, inputs: Sequence[str | os.PathLike[str]]):
        self.inputs = tuple(map(os.fsdecode, inputs))
        self.claimed: list[tuple[str, str]] = []   # (what names it, name)
        self.written: list[tuple[str, str]] = []
        self._outer: Outputs | None = None

    def claim(self, label: str, output: str | os.PathLike[str], *,
              binary: bool = False) -> None:
        """Check an output before any work; `label` names it in messages ("-o",
        "--plot's panel file"). A UsageError if it is an input or another output, a
        DataError (or a UsageError) from `check_destination` if it cannot be written."""
        name = os.fsdecode(output)
        _refuse_overlap(label, name, self.inputs, self.claimed)
        check_destination(name, binary=binary)
        self.claimed.append((label, name))

    def _write(self, name: str) -> None:
        """Helper method checking a file about to be written, and noting it."""
        label = next((label for label, claimed in self.claimed
                      if same_file(claimed, name)), "output")
        _refuse_overlap(label, name, self.inputs, self.written)
        self.written.append((label, name))

    def __enter__(self) -> Outputs:
        global _outputs
        self._outer, _outputs = _outputs, self
        return self

    def __exit__(self, *exc: object) -> None:
        global _outputs
        _outputs = self._outer


_outputs: Outputs | None = None


def _refuse_overlap(label: str, name: str, inputs: Sequence[str],
                    outputs: Sequence[tuple[str, str]]) -> None:
    """Helper function: a UsageError if `name` is one of the inputs or of the outputs."""
    for source in inputs:
        if overwrites(name, source):
            shown = "standard input" if source == "-" else f"the input file {source!r}"
            raise UsageError(f"{label} {name!r} is {shown}; writing it would destroy the "
                             "input: choose another output")
    for other_label, other in outputs:
        if not same_file(name, other):
            continue
        if other_label == label:
            raise UsageError(f"{label} names one file twice: {other!r} and {name!r}")
        alias = "" if os.path.normpath(name) == os.path.normpath(other) else f" (as {name!r})"
        raise UsageError(f"{other_label} and {label} name the same file {other!r}{alias}")


# ---------------------------------------------------------------------------------------------
# Writing


def _write_output(dest: str | os.PathLike[str], write: Write, *, binary: bool,
                  escape_on_terminal: bool = False) -> None:
    """Helper function writing a regular file atomically, anything else in place."""
    target = resolve(dest)
    if target.kind == "file":
        if _outputs is not None:
            _outputs._write(target.name)
        _write_atomic(target, write)
        return
    send = functools.partial(_write_stream, target, write, binary=binary,
                             escape_on_terminal=escape_on_terminal)
    if _held is not None:
        _held.streams.append(send)
    else:
        send()


def _write_stream(target: Destination, write: Write, *, binary: bool,
                  escape_on_terminal: bool) -> None:
    """Helper function writing to a descriptor or a special file, in place."""
    if target.kind == "descriptor" and target.fd == 1:
        _write_stdout(target.name, write, binary=binary, escape_on_terminal=escape_on_terminal)
        return
    try:
        if target.kind == "descriptor":
            stream = os.fdopen(os.dup(target.fd), "wb")
        else:
            stream = open(target.path, "wb")  # noqa: SIM115 (a FIFO waits here for its reader)
        with stream:
            terminal = stream.isatty()
            if binary and terminal:
                raise _binary_to_terminal(target.name)
            _send(stream, write, escape=escape_on_terminal and terminal)
    except BrokenPipeError:
        raise
    except OSError as exc:
        raise DataError(f"{target.name}: cannot write: {readers.os_reason(exc)}") from exc


def _write_stdout(name: str, write: Write, *, binary: bool, escape_on_terminal: bool) -> None:
    """Helper function writing bytes to standard output, after any text already there."""
    import io as pyio

    if not stdout_open():
        raise DataError(f"{name}: cannot write: standard output is closed")
    stdout = sys.stdout
    terminal = isatty(stdout)
    if binary and terminal:
        raise _binary_to_terminal(name)
    try:
        stdout.flush()
        buffer = getattr(stdout, "buffer", None)
        if buffer is not None:
            _send(buffer, write, escape=escape_on_terminal and terminal)
            return
        # A text-only stream, as some embedding applications install: text goes through as
        # text.
        if binary:
            raise DataError(f"{name}: cannot write Parquet to a text-only output stream")
        collected = pyio.BytesIO()
        write(collected)
        text = collected.getvalue().decode("utf-8")
        stdout.write(_terminal_text(text) if escape_on_terminal and terminal else text)
        stdout.flush()
    except BrokenPipeError:
        raise
    except OSError as exc:  # a full disk (`> /dev/full`), a file-size limit
        raise DataError(f"{name}: cannot write: {readers.os_reason(exc)}") from exc


def _send(stream: IO[bytes], write: Write, *, escape: bool) -> None:
    """Helper function running a writer on a stream, through the terminal filter if asked."""
    complete = _Complete(stream)
    if escape:
        escaping = _TerminalSafe(complete)
        write(escaping)  # type: ignore[arg-type]
        escaping.finish()
    else:
        write(complete)  # type: ignore[arg-type]
    stream.flush()


class _Complete:
    """A binary stream whose write writes every byte, or raises.

    A buffered stream's write may write part of a large block and return the count without
    an error (a full disk, a file-size limit): the error comes only with the next write.
    pyarrow does not look at the count, so the end of the output would be lost in silence.
    """

    closed = False

    def __init__(self, stream: IO[bytes]):
        self.stream = stream

    def writable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        total = len(view)
        while view:
            written = self.stream.write(view)
            if not written:
                raise OSError(errno.EIO, "the output takes no more data")
            view = view[written:]
        return total

    def flush(self) -> None:
        self.stream.flush()


def _terminal_text(text: str) -> str:
    """Helper function: data text with the control characters a terminal obeys escaped."""
    return printable(text, keep="\n\t")


class _TerminalSafe:
    """A binary stream to a terminal that shows control characters escaped.

    Data (CSV cells, column names) may hold ESC sequences; on a terminal they are shown as
    ``\\x1b`` rather than obeyed. Newlines and tabs, which lay out the table, pass.
    """

    def __init__(self, stream: IO[bytes]):
        self.stream = stream
        self.decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
        self.closed = False

    def writable(self) -> bool:
        return True

    def write(self, data: bytes) -> int:
        text = self.decoder.decode(bytes(data))
        self.stream.write(_terminal_text(text).encode("utf-8"))
        return len(data)

    def flush(self) -> None:
        self.stream.flush()

    def finish(self) -> None:
        self.stream.write(_terminal_text(self.decoder.decode(b"", final=True)).encode("utf-8"))


# ---------------------------------------------------------------------------------------------
# Regular files: a temporary file, then a rename


@dataclass
class _Held:
    """What `all_or_nothing` holds back: renames of temporaries, and writes to streams."""

    renames: list[tuple[str, Path, str]] = field(default_factory=list)
    streams: list[Callable[[], None]] = field(default_factory=list)


_held: _Held | None = None


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Files written inside appear together at the end, or none of them does.

    Each regular file is written to its temporary as usual; the renames onto the
    destinations wait until the block ends without an error. On any error (Ctrl-C and
    signals included) the temporaries are removed and every destination is left as it was.
    Outputs written in place (standard output, devices, FIFOs) cannot be taken back: they are
    written at the end, after every file has been written and before the renames, so that a
    failure to write a file sends nothing to them.

    Examples
    --------
    >>> with all_or_nothing():  # doctest: +SKIP
    ...     write_table(residuals, "residuals.csv")
    ...     write_text(report, "report.json")
    """
    global _held
    outer, held = _held, _Held()
    _held = held
    try:
        yield
        for send in held.streams:
            send()
    except BaseException:
        for temporary, _, _ in held.renames:
            _remove(temporary)
        raise
    finally:
        _held = outer
    for k, (temporary, path, name) in enumerate(held.renames):
        try:
            _replace(temporary, path)
        except BaseException as exc:
            for later, _, _ in held.renames[k:]:
                _remove(later)
            if isinstance(exc, OSError):
                raise DataError(f"{name}: cannot write: {readers.os_reason(exc)}") from exc
            raise
        _sync_folder(path.parent)


def _write_atomic(target: Destination, write: Write) -> None:
    """Helper function writing through a temporary file in the destination's folder."""
    _check_writable(target)
    path = target.path
    fd, temporary = _create_temporary(target)
    try:
        with os.fdopen(fd, "wb") as stream:
            write(_Complete(stream))  # type: ignore[arg-type]
            stream.flush()
            os.fsync(stream.fileno())
        os.chmod(temporary, _new_file_mode(path))
        if _held is not None:
            _held.renames.append((temporary, path, target.name))
            return
        _replace(temporary, path)
    except OSError as exc:  # a full disk, a file-size limit, a name too long
        _remove(temporary)
        raise DataError(f"{target.name}: cannot write: {readers.os_reason(exc)}") from exc
    except BaseException:
        # KeyboardInterrupt and signals included: the destination is left as it was.
        _remove(temporary)
        raise
    _sync_folder(path.parent)


def create_fresh(dest: str | os.PathLike[str]) -> IO[bytes]:
    """A new, empty file at `dest`, open for writing as records come, whatever was there.

    The file is created under a private name in the destination's folder and renamed to
    `dest` at once, before anything is written: a symlink there is replaced, not written
    through, and a hard link loses only this name. What is written stays if the command is
    cut short (`fit --each`'s ``OUT.partial``), unlike the temporaries of the atomic
    writers. Inside `Outputs`, `dest` is checked as every written file is.
    """
    target = resolve(dest)
    if target.kind != "file":
        raise DataError(f"{target.name}: cannot write: not a regular file")
    if _outputs is not None:
        _outputs._write(target.name)
    fd, temporary = _create_temporary(target)
    try:
        os.fchmod(fd, _new_file_mode(target.path))
        _replace(temporary, target.path)
    except BaseException as exc:
        os.close(fd)
        _remove(temporary)
        if isinstance(exc, OSError):
            raise DataError(f"{target.name}: cannot write: {readers.os_reason(exc)}") from exc
        raise
    return os.fdopen(fd, "wb")


# Temporary files that exist now; a termination signal's last act removes what is left.
_live: set[str] = set()
_TEMPORARY_SUFFIX = ".tmp"
_SHORT_NAME = 24  # bytes a temporary's name may always take, however short the destination's
_HELD_SIGNALS = {getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT")
                 if hasattr(signal, name)}


def _create_temporary(target: Destination) -> tuple[int, str]:
    """Helper function creating the temporary file beside the destination, with errors named.

    The temporary's name is no longer than the destination's (or than _SHORT_NAME bytes):
    ``.`` + the start of the name + ``.`` + 8 random characters + ``.tmp``.
    """
    folder = target.path.parent
    with _signals_held():
        try:
            fd, temporary = tempfile.mkstemp(dir=folder, prefix=_temporary_prefix(target.path),
                                             suffix=_TEMPORARY_SUFFIX)
        except FileNotFoundError as exc:
            if folder.is_dir():   # /proc, /sys: the folder exists, but takes no new file
                raise DataError(f"{target.name}: cannot write: folder {target.folder!r} does "
                                "not accept new files") from exc
            raise DataError(f"{target.name}: cannot write: folder {target.folder!r} does not "
                            "exist") from exc
        except OSError as exc:
            raise DataError(f"{target.name}: cannot write in folder {target.folder!r}: "
                            f"{readers.os_reason(exc)}") from exc
        _live.add(temporary)
    return fd, temporary


def _temporary_prefix(path: Path) -> str:
    """Helper function: ``.`` + as much of the name as keeps the temporary's name short."""
    try:
        limit = os.pathconf(path.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    own = len(os.fsencode(path.name))
    room = min(limit, max(own, _SHORT_NAME)) - len(".." + _TEMPORARY_SUFFIX) - 8
    start = path.name
    while start and len(os.fsencode(start)) > room:
        start = start[:-1]
    return f".{start}."


def _replace(temporary: str, path: Path) -> None:
    """Helper function renaming a complete temporary file over its destination."""
    with _signals_held():
        os.replace(temporary, path)
        _live.discard(temporary)


def _remove(temporary: str) -> None:
    """Helper function removing a temporary file that may already be gone."""
    with _signals_held(), contextlib.suppress(OSError):
        os.unlink(temporary)
    _live.discard(temporary)


def remove_temporaries() -> None:
    """Remove the temporary files still there; the command line's last act on a signal."""
    for temporary in list(_live):
        _remove(temporary)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Helper: Ctrl-C and termination signals wait while a temporary is created, renamed or
    removed, so that their handlers never run between the system call and `_live`'s update.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _new_file_mode(path: Path) -> int:
    """Helper function giving the permissions the written file should have.

    mkstemp creates files readable by their owner only; an output file should have the
    permissions the file it replaces had, or the usual ones for a new file (which replaces
    a symlink, not what it leads to).
    """
    mode = _own_mode(path)
    if mode is not None:
        return mode
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def _own_mode(path: Path) -> int | None:
    """Helper function: the permissions of the regular file that is `path` itself (not
    through a symlink), or None."""
    try:
        status = os.lstat(path)
    except OSError:
        return None
    return stat.S_IMODE(status.st_mode) if stat.S_ISREG(status.st_mode) else None


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
    return STDOUT if readers.is_stdio(dest) else os.fsdecode(dest)


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
