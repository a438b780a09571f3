"""Writing outputs: tables (CSV, TSV, Parquet) and text, atomically or all at once.

How an output is written depends on what it names:

- A regular file (or a symlink to one, which is followed so that the link survives) is
  written to a temporary file in its folder and renamed over it only when complete, so a
  failure, Ctrl-C or a termination signal never leaves a half-written or damaged file, nor a
  temporary one. A file the caller may not write is refused, as cp refuses it.
- Anything else is written in place, as a stream, since replacing it would destroy it:
  standard output (``"-"``); ``/dev/stdout``, ``/dev/fd/N`` and ``/proc/self/fd/N``, which
  name a descriptor of this process and are written through it (so ``>>`` keeps appending);
  devices such as ``/dev/null``; FIFOs (which wait for their reader).

`check_destination` finds before long work what can be known then: a missing or unwritable
folder, a read-only file, a name too long, a closed standard output, Parquet bound for a
terminal. `overwrites` tells the caller that an output would replace one of its inputs.
"""

from __future__ import annotations

import codecs
import contextlib
import errno
import functools
import json
import os
import re
import signal
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal

from hamid import io
from hamid.errors import DataError, UsageError
from hamid.io import STDOUT, Format

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

__all__ = ["all_or_nothing", "check_destination", "is_terminal", "overwrites",
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
    io.check_unique([str(column) for column in table.columns], name)
    arrow = _to_arrow(table, name)
    _WRITERS[fmt](arrow, metadata_json, dest, name)


def table_format(dest: str | os.PathLike[str], format: str | None = None) -> Format:
    """The format a table written to `dest` will have; a UsageError if it cannot be told.

    CSV for standard output and for any other stream without a known extension
    (``/dev/stdout``, ``/dev/null``, a FIFO). Callers check this before long work, so that a
    bad output name fails at once.
    """
    if format is not None:
        return io.check_format(format)
    if io.is_stdio(dest):
        return "csv"
    fmt = io.format_from_suffix(dest)
    if fmt is None:
        if _is_stream(dest):
            return "csv"
        raise _unknown_extension(dest)
    return fmt


def _is_stream(dest: str | os.PathLike[str]) -> bool:
    """Helper function: whether an output is written in place (a descriptor, a device)."""
    try:
        return _resolve(dest).kind != "file"
    except DataError:
        return False


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
        merged[io.METADATA_KEY] = metadata_json.encode()
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
    _write_output(dest, lambda stream: stream.write(data), binary=False)


def write_bytes(data: bytes, dest: str | os.PathLike[str]) -> None:
    """Write bytes (a rendered figure) atomically; never to a terminal."""
    _write_output(dest, lambda stream: stream.write(data), binary=True)


# ---------------------------------------------------------------------------------------------
# What an output name leads to


@dataclass(frozen=True, slots=True)
class _Destination:
    """Where an output goes: a regular file to replace, an open descriptor, or a special file.

    `path` is the regular file itself (symlinks resolved) for "file", the name to open for
    "special"; `fd` is the descriptor for "descriptor" (1 is standard output); `folder` is
    the folder as messages name it.
    """

    name: str
    kind: Literal["file", "descriptor", "special"]
    path: Path = Path()
    fd: int = -1
    folder: str = ""


# /dev/stdout, /dev/fd/N and /proc/<this process>/fd/N, once the folder's links are resolved.
_DESCRIPTOR_NAME = re.compile(
    r"/dev/(?:(?P<std>stdin|stdout|stderr)|fd/(?P<dev>\d+))"
    r"|/proc/(?P<pid>self|\d+)(?:/task/\d+)?/fd/(?P<proc>\d+)")
_STANDARD = {"stdin": 0, "stdout": 1, "stderr": 2}
_MAX_LINKS = 40  # as the kernel's ELOOP limit


def _resolve(dest: str | os.PathLike[str]) -> _Destination:
    """Helper function telling what an output name leads to, following symlinks."""
    if io.is_stdio(dest):
        return _Destination(STDOUT, "descriptor", fd=1)
    name = os.fsdecode(dest)
    fd = _descriptor_of(name)
    if fd is not None:
        return _Destination(name, "descriptor", fd=fd)
    try:
        mode = os.stat(name).st_mode
    except FileNotFoundError:
        mode = None   # a new file (or a dangling symlink, whose target is created)
    except NotADirectoryError as exc:  # plain/out.csv, where plain is a file
        raise DataError(f"{name}: cannot write in folder {str(Path(name).parent)!r}: "
                        f"{io.os_reason(exc)}") from exc
    except OSError as exc:  # a name too long, a symlink loop, a folder one may not enter
        raise DataError(f"{name}: cannot write: {io.os_reason(exc)}") from exc
    if mode is not None and stat.S_ISDIR(mode):
        raise DataError(f"{name}: is a folder, not a file")
    if mode is not None and not stat.S_ISREG(mode):
        return _Destination(name, "special", path=Path(name))
    real = Path(os.path.realpath(name))
    folder = str(real.parent) if os.path.islink(name) else str(Path(name).parent)
    return _Destination(name, "file", path=real, folder=folder)


def _descriptor_of(name: str) -> int | None:
    """Helper function: the descriptor of this process that `name` leads to, if it does."""
    path = os.path.abspath(name)
    for _ in range(_MAX_LINKS):
        folder, base = os.path.split(path)
        path = os.path.join(os.path.realpath(folder), base)
        match = _DESCRIPTOR_NAME.fullmatch(path)
        if match is not None and match["pid"] in (None, "self", str(os.getpid())):
            return _STANDARD[match["std"]] if match["std"] else int(match["dev"] or match["proc"])
        try:
            target = os.readlink(path)
        except OSError:  # not a symlink, or not there
            return None
        path = os.path.normpath(os.path.join(os.path.dirname(path), target))
    return None


def is_terminal(dest: str | os.PathLike[str]) -> bool:
    """Whether an output goes to a terminal: standard output or /dev/stdout on a terminal."""
    try:
        target = _resolve(dest)
    except DataError:
        return False
    if target.kind != "descriptor":
        return False
    if target.fd == 1:
        return _stdout_open() and _isatty(sys.stdout)
    return _fd_isatty(target.fd)


def _stdout_open() -> bool:
    """Helper function: whether there is a standard output to write to (not `>&-`)."""
    return sys.stdout is not None and not getattr(sys.stdout, "closed", False)


def _isatty(stream: Any) -> bool:
    """Helper function: whether a stream is a terminal; a stream that cannot tell is not."""
    try:
        return bool(stream.isatty())
    except (AttributeError, OSError, ValueError):
        return False


def _fd_isatty(fd: int) -> bool:
    """Helper function: whether a descriptor is a terminal; a closed one is not."""
    try:
        return os.isatty(fd)
    except OSError:
        return False


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
    target = _resolve(dest)
    if target.kind == "file":
        _check_writable(target)
        fd, temporary = _create_temporary(target)
        os.close(fd)
        _remove(temporary)
    elif target.kind == "descriptor":
        _check_descriptor(target, binary)
    elif not _writable(target.path):
        raise DataError(f"{target.name}: cannot write: permission denied")


def _check_writable(target: _Destination) -> None:
    """Helper function refusing to replace an existing file the caller may not write."""
    if target.path.exists() and not _writable(target.path):
        raise DataError(f"{target.name}: cannot write: the file is read-only (permission "
                        "denied); it is left as it is")


def _writable(path: Path) -> bool:
    """Helper function: whether the caller may write a file (its effective ids, as open's)."""
    effective = os.access in os.supports_effective_ids
    return os.access(path, os.W_OK, effective_ids=effective)


def _check_descriptor(target: _Destination, binary: bool) -> None:
    """Helper function checking an open descriptor (standard output) before long work."""
    if target.fd == 1:
        if not _stdout_open():
            raise DataError(f"{target.name}: cannot write: standard output is closed")
        terminal = _isatty(sys.stdout)
    else:
        try:
            os.fstat(target.fd)
        except OSError as exc:
            raise DataError(f"{target.name}: cannot write: descriptor {target.fd} is "
                            "closed") from exc
        terminal = _fd_isatty(target.fd)
    if binary and terminal:
        raise _binary_to_terminal(target.name)


def _binary_to_terminal(name: str) -> UsageError:
    """Helper function building the refusal to send Parquet to a terminal."""
    return UsageError(f"{name}: refusing to write Parquet, a binary format, to a terminal; "
                      "write it to a file or redirect the output")


def overwrites(output: str | os.PathLike[str], source: str | os.PathLike[str]) -> bool:
    """Whether writing `output` would replace the file `source` (an input, another output).

    Both exist: the same regular file, by device and inode, which sees through ``..``,
    symlinks and hard links. Neither exists: the same name once resolved. A device or pipe
    is never replaced, so it never counts; ``"-"`` as `source` is standard input's file
    (``< data.csv``), as `output` it is standard output, which replaces nothing.
    """
    if io.is_stdio(output):
        return False
    written, read = _identity(output), _identity(source)
    if written is None and read is None and not io.is_stdio(source):
        return os.path.realpath(output) == os.path.realpath(source)
    return written is not None and written == read and written != "special"


def _identity(name: str | os.PathLike[str]) -> tuple[int, int] | str | None:
    """Helper function: (device, inode) of a regular file, "special", or None if absent."""
    try:
        status = os.fstat(0) if io.is_stdio(name) else os.stat(name)
    except (OSError, ValueError):
        return None
    return (status.st_dev, status.st_ino) if stat.S_ISREG(status.st_mode) else "special"


# ---------------------------------------------------------------------------------------------
# Writing


def _write_output(dest: str | os.PathLike[str], write: Write, *, binary: bool,
                  escape_on_terminal: bool = False) -> None:
    """Helper function writing a regular file atomically, anything else in place."""
    target = _resolve(dest)
    if target.kind == "file":
        _write_atomic(target, write)
        return
    send = functools.partial(_write_stream, target, write, binary=binary,
                             escape_on_terminal=escape_on_terminal)
    if _held is not None:
        _held.streams.append(send)
    else:
        send()


def _write_stream(target: _Destination, write: Write, *, binary: bool,
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
        raise DataError(f"{target.name}: cannot write: {io.os_reason(exc)}") from exc


def _write_stdout(name: str, write: Write, *, binary: bool, escape_on_terminal: bool) -> None:
    """Helper function writing bytes to standard output, after any text already there."""
    import io as pyio

    if not _stdout_open():
        raise DataError(f"{name}: cannot write: standard output is closed")
    stdout = sys.stdout
    terminal = _isatty(stdout)
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
        raise DataError(f"{name}: cannot write: {io.os_reason(exc)}") from exc


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
    from hamid.report import printable

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
                raise DataError(f"{name}: cannot write: {io.os_reason(exc)}") from exc
            raise
        _sync_folder(path.parent)


def _write_atomic(target: _Destination, write: Write) -> None:
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
        raise DataError(f"{target.name}: cannot write: {io.os_reason(exc)}") from exc
    except BaseException:
        # KeyboardInterrupt and signals included: the destination is left as it was.
        _remove(temporary)
        raise
    _sync_folder(path.parent)


# Temporary files that exist now; a termination signal's last act removes what is left.
_live: set[str] = set()
_TEMPORARY_SUFFIX = ".tmp"
_SHORT_NAME = 24  # bytes a temporary's name may always take, however short the destination's
_HELD_SIGNALS = {getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT")
                 if hasattr(signal, name)}


def _create_temporary(target: _Destination) -> tuple[int, str]:
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
                            f"{io.os_reason(exc)}") from exc
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
    permissions the file it replaces had, or the usual ones for a new file.
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


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
