"""Reading within bounds (issue 33): documents whose parsers recurse (JSON, TOML), and
streams whose size is not known before they are read (devices, FIFOs, standard input,
decompressed text). Past a bound, the input is refused in one line naming it, instead of
exhausting the stack or the memory.
"""

from __future__ import annotations

import json
import sys
from typing import IO, Any

from hamid.errors import DataError, ModelError

__all__ = ["LINE_BYTES", "READ_BYTES", "json_value", "read_at_most", "toml_document"]

# The most bytes read whole from a stream, or decompressed whole: past it the input is
# refused (a file on disk is read in chunks instead).
READ_BYTES = 256 << 20
# The longest line of text before the data rows (comments, the header): a header of
# millions of columns, or text without line breaks, is not a table.
LINE_BYTES = 1 << 20


def json_value(text: str, where: str) -> Any:
    """The value of a JSON text, or a DataError naming `where` (a file, or a file and what
    in it: ``run.csv: line 1: the hamid metadata``).

    json's parser recurses once per nesting level, and int() refuses integers of more than
    `sys.get_int_max_str_digits` digits; both are reported, not raised as they come.
    """
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"{where}: not valid JSON (line {exc.lineno}, column {exc.colno}): "
                        f"{exc.msg}") from exc
    except RecursionError:
        raise DataError(f"{where}: not readable JSON: nested too deeply") from None
    except ValueError as exc:
        raise DataError(f"{where}: not readable JSON: a number has more than "
                        f"{sys.get_int_max_str_digits()} digits") from exc


def toml_document(text: str, name: str) -> dict[str, Any]:
    """The document of a TOML text, or a ModelError naming the file `name`; tomllib
    recurses once per nesting level of arrays and inline tables."""
    import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"{name}: not valid TOML: {exc}") from exc
    except RecursionError:
        raise ModelError(f"{name}: not readable TOML: arrays or inline tables nested too "
                         "deeply") from None


def read_at_most(stream: IO[bytes], name: str, what: str) -> bytes:
    """All of a stream of unknown length, refused past `READ_BYTES` (`what` it is, for the
    message: "standard input", "not a regular file")."""
    data = stream.read(READ_BYTES + 1)
    if len(data) > READ_BYTES:
        raise DataError(f"{name}: more than {READ_BYTES >> 20} MiB from {what}, the most "
                        "read whole; save it to a file (large files are read in chunks)")
    return data
