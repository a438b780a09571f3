"""Compressed input: gzip, bzip2 and Zstandard, told by their magic bytes and read with
pyarrow's codecs (issue 18). `hamid.data.readers` reads a compressed table whole through
`decompressed`, or block by block through `opened`.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from hamid import read_limits
from hamid.errors import DataError

__all__ = ["SUFFIXES", "arrow_stream", "codec_of", "decompressed", "opened", "suffix"]

# Whatever the file's name (standard input too).
_MAGIC = {"gzip": re.compile(rb"\x1f\x8b"),
          "bz2": re.compile(rb"BZh[1-9](1AY&SY|\x17rE8P\x90)"),
          "zstd": re.compile(rb"\x28\xb5\x2f\xfd")}
# Extensions that a file's format is read under (run.csv.gz is CSV).
SUFFIXES = (".gz", ".bz2", ".zst")
# Enough of a file's start to tell its codec.
HEAD_BYTES = 10


def suffix(path: str | os.PathLike[str]) -> str:
    """A file's extension in lower case, under a compression one (``.csv`` for
    ``run.CSV.gz``)."""
    name = Path(os.fsdecode(path))
    if name.suffix.lower() in SUFFIXES:
        name = name.with_suffix("")
    return name.suffix.lower()


def codec_of(head: bytes) -> str | None:
    """The codec ("gzip", "bz2", "zstd") whose magic bytes begin `head`, or None."""
    for codec, magic in _MAGIC.items():
        if magic.match(head):
            return codec
    return None


def decompressed(data: bytes, name: str) -> bytes:
    """`data` decompressed when it is gzip, bzip2 or Zstandard; other data as they are.
    Decompressed whole, the text is refused past `hamid.read_limits.READ_BYTES` (a small file
    can hold gigabytes of text)."""
    codec = codec_of(data)
    if codec is None:
        return data
    import pyarrow as pa

    most = read_limits.READ_BYTES
    with _damage(name, codec):
        text = pa.CompressedInputStream(pa.BufferReader(data), codec).read(most + 1)
    if len(text) > most:
        raise DataError(f"{name}: decompresses to more than {most >> 20} MiB, the most "
                        "decompressed whole; decompress it to a file first")
    return bytes(text)


@contextlib.contextmanager
def opened(stream: IO[bytes], codec: str, name: str) -> Iterator[IO[bytes]]:
    """A binary file object decompressing `stream` as it is read (lines, blocks); a damaged
    stream is a DataError naming the file, also when found by the reads inside."""
    import io

    import pyarrow as pa

    with _damage(name, codec), io.BufferedReader(pa.CompressedInputStream(
            pa.PythonFile(stream, mode="r"), codec)) as reader:
        yield reader


@contextlib.contextmanager
def arrow_stream(path: str | os.PathLike[str], codec: str | None,
                 name: str) -> Iterator[Any]:
    """A file as an Arrow stream, decompressed as it is read when `codec` is given.

    For pyarrow's streaming readers: they read ahead in threads of their own, where a
    Python file object would be called back, and a call still under way when the
    interpreter exits aborts it (issue 33).
    """
    import pyarrow as pa

    with pa.OSFile(os.fspath(path)) as raw:
        if codec is None:
            yield raw
            return
        with _damage(name, codec), pa.CompressedInputStream(raw, codec) as stream:
            yield stream


@contextlib.contextmanager
def _damage(name: str, codec: str) -> Iterator[None]:
    """Helper turning a codec's error into a DataError naming the file."""
    import pyarrow as pa

    try:
        yield
    except MemoryError:   # pyarrow's ArrowMemoryError is also an ArrowException
        raise
    except (pa.ArrowException, OSError) as exc:
        lines = str(exc).strip().splitlines()
        reason = lines[0] if lines else type(exc).__name__
        raise DataError(f"{name}: is not valid {codec} data ({reason})") from exc
