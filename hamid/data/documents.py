"""Reading documents: TOML system and model files, and saved fit results (JSON)."""

from __future__ import annotations

import os
from typing import Any

from hamid.data.readers import json_kind, not_utf8, read_bytes
from hamid.errors import DataError, ModelError
from hamid.read_limits import json_value, toml_document

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
    data, name = read_bytes(path)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise not_utf8(data, name, "not valid TOML: ", ModelError) from exc
    return toml_document(text, name)


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
    document = json_value(text, name)
    if not isinstance(document, dict):
        raise DataError(f"{name}: expected a JSON object, found {json_kind(document)}")
    return document
