"""What an output name leads to, and whether two names lead to one file.

An output name leads to one of three things:

- a regular file, a name with nothing behind it, or a symlink to either: the name is
  replaced by a new file (`hamid.data.writing` renames a complete temporary file onto it). A
  symlink there is replaced itself, never written through, so that no link can send an
  output onto a file the command was not told to write;
- a descriptor of this process (``"-"``, ``/dev/stdout``, ``/dev/fd/N``,
  ``/proc/self/fd/N``, or a symlink to one), written through it;
- a special file (a device, a FIFO, or a symlink to one), written in place.

`overwrites` and `same_file` tell whether an output would meet an input or another
output of the same command.
"""

from __future__ import annotations

import os
import re
import stat
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from hamid.data import readers
from hamid.data.readers import STDOUT
from hamid.errors import DataError

__all__ = ["Destination", "fd_isatty", "is_terminal", "isatty", "overwrites", "resolve",
           "same_file", "stdout_open"]


@dataclass(frozen=True, slots=True)
class Destination:
    """Where an output goes: a name to replace by a new file, an open descriptor, or a
    special file.

    `path` is the name to replace for "file" (a symlink there included), the name to open
    for "special"; `fd` is the descriptor for "descriptor" (1 is standard output); `folder`
    is the folder as messages name it.
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


def resolve(dest: str | os.PathLike[str]) -> Destination:
    """What an output name leads to (a folder, or a name no folder can hold, is a DataError)."""
    if readers.is_stdio(dest):
        return Destination(STDOUT, "descriptor", fd=1)
    name = os.fsdecode(dest)
    fd = _descriptor_of(name)
    if fd is not None:
        return Destination(name, "descriptor", fd=fd)
    try:
        mode = os.stat(name).st_mode
    except FileNotFoundError:
        mode = None   # a new file, or a symlink to nothing, which is replaced
    except NotADirectoryError as exc:  # plain/out.csv, where plain is a file
        raise DataError(f"{name}: cannot write in folder {str(Path(name).parent)!r}: "
                        f"{readers.os_reason(exc)}") from exc
    except OSError as exc:  # a name too long, a symlink loop, a folder one may not enter
        raise DataError(f"{name}: cannot write: {readers.os_reason(exc)}") from exc
    if mode is not None and stat.S_ISDIR(mode):
        raise DataError(f"{name}: is a folder, not a file")
    if mode is not None and not stat.S_ISREG(mode):
        return Destination(name, "special", path=Path(name))
    return Destination(name, "file", path=Path(name), folder=str(Path(name).parent))


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
        target = resolve(dest)
    except DataError:
        return False
    if target.kind != "descriptor":
        return False
    if target.fd == 1:
        return stdout_open() and isatty(sys.stdout)
    return fd_isatty(target.fd)


def stdout_open() -> bool:
    """Whether there is a standard output to write to (not `>&-`)."""
    return sys.stdout is not None and not getattr(sys.stdout, "closed", False)


def isatty(stream: Any) -> bool:
    """Whether a stream is a terminal; a stream that cannot tell is not."""
    try:
        return bool(stream.isatty())
    except (AttributeError, OSError, ValueError):
        return False


def fd_isatty(fd: int) -> bool:
    """Whether a descriptor is a terminal; a closed one is not."""
    try:
        return os.isatty(fd)
    except OSError:
        return False


def overwrites(output: str | os.PathLike[str], source: str | os.PathLike[str]) -> bool:
    """Whether `output` names the file `source` (an input, another output).

    Both exist: the same regular file, by device and inode, which sees through ``..``,
    symlinks and hard links (a link to an input is replaced rather than written through,
    but an output name that leads to an input is taken for the mistake it almost surely
    is). Neither exists: the same name once resolved. A device or pipe is never replaced,
    so it never counts; ``"-"`` as `source` is standard input's file (``< data.csv``), as
    `output` it is standard output, which replaces nothing.
    """
    if readers.is_stdio(output):
        return False
    written, read = _identity(output), _identity(source)
    if written is None and read is None and not readers.is_stdio(source):
        return os.path.realpath(output) == os.path.realpath(source)
    return written is not None and written == read and written != "special"


def same_file(output: str | os.PathLike[str], other: str | os.PathLike[str]) -> bool:
    """Whether two outputs of one command would be written to one file: the same name in
    the same folder (through ``..`` or linked folders), or names of one existing file.
    Streams (standard output, devices, FIFOs) are written in place and never count."""
    if any(readers.is_stdio(name) or _identity(name) == "special" for name in (output, other)):
        return False
    return _entry(output) == _entry(other) or overwrites(output, other)


def _entry(name: str | os.PathLike[str]) -> str:
    """Helper function: the folder entry a name replaces (its folder resolved, not itself)."""
    folder, base = os.path.split(os.path.abspath(os.fsdecode(name)))
    return os.path.join(os.path.realpath(folder), base)


def _identity(name: str | os.PathLike[str]) -> tuple[int, int] | str | None:
    """Helper function: (device, inode) of a regular file, "special", or None if absent."""
    try:
        status = os.fstat(0) if readers.is_stdio(name) else os.stat(name)
    except (OSError, ValueError):
        return None
    return (status.st_dev, status.st_ino) if stat.S_ISREG(status.st_mode) else "special"
