"""Reading documents: TOML system and model files, and saved fit results (JSON)."""

from __future__ import annotations

import json
import os
import sys
from typing import Any

from hamid.data.readers import json_kind, not_utf8, read_bytes
from hamid.errors import DataError, ModelError

__all__ = ["read_json", "read_jsonl", "read_toml"]


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a TOML file such as a system file.

    Parameters
    ----------
    path : str or path-like
        File to read; ``"-"`` reads standard input.

    Returns
    -------
    document : dict

    Raises
    ------
    ModelError
        The file is not valid TOML.
    DataError
        The file cannot be read.
    """
    import tomllib

    data, name = read_bytes(path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise not_utf8(data, name, "not valid TOML: ", ModelError) from exc
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"{name}: not valid TOML: {exc}") from exc


def read_json(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a JSON object such as a saved fit result.

    Parameters
    ----------
    path : str or path-like
        File to read; ``"-"`` reads standard input.

    Returns
    -------
    document : dict

    Raises
    ------
    DataError
        The file cannot be read, is not JSON, or does not hold a JSON object.
    """
    data, name = read_bytes(path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise not_utf8(data, name, "not valid JSON: ") from exc
    return _json_object(text, name)


def read_jsonl(path: str | os.PathLike[str]) -> list[tuple[str, dict[str, Any]]]:
    """Read JSON lines (one object per line, blank lines skipped), such as the results of
    `hamid fit --each --format jsonl`.

    Returns
    -------
    lines : list of (where, document)
        Each object with the file and line it came from (``results.jsonl, line 3``), for
        messages.

    Raises
    ------
    DataError
        The file cannot be read, or a line is not JSON or not a JSON object.
    """
    data, name = read_bytes(path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise not_utf8(data, name, "not valid JSON lines: ") from exc
    return [(f"{name}, line {n}", _json_object(line, f"{name}, line {n}"))
            # "\n" only: str.splitlines would also split at U+2028 inside a string
            for n, line in enumerate(text.split("\n"), 1) if line.strip()]


def _json_object(text: str, name: str) -> dict[str, Any]:
    """Helper: the JSON object of a text, or an error naming `name`."""
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(
            f"{name}: not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}"
        ) from exc
    except RecursionError:
        # json's parser recurses once per nesting level: 100,000 brackets exhaust the stack.
        raise DataError(f"{name}: not readable JSON: nested too deeply") from None
    except ValueError as exc:
        # An integer of more digits than int() converts (sys.get_int_max_str_digits()).
        raise DataError(f"{name}: not readable JSON: a number has more than "
                        f"{sys.get_int_max_str_digits()} digits") from exc
    if not isinstance(document, dict):
        raise DataError(f"{name}: expected a JSON object, found {json_kind(document)}")
    return document
