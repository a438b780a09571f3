"""Checking a loaded report against the JSON Schema of "hamid.fit/1" (hamid/schema/fit-1.json).

The schema file is the contract (docs/output.md explains it key by key); this module runs
it with the `jsonschema` library, imported only when a report is checked, and turns the
first violation into one line that names the key, the value found and what was expected.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Iterator
from typing import Any

from hamid.errors import DataError

__all__ = ["MAX_DEPTH", "SCHEMA", "SCHEMA_FILE", "check_result", "load_schema"]

SCHEMA = "hamid.fit/1"                # the format a report names in its key "schema"
SCHEMA_FILE = "schema/fit-1.json"   # inside the package
# A report is about five levels deep; a value nested far deeper (in a key this version does
# not know) would make the code that copies and renders it recurse past Python's limit.
MAX_DEPTH = 64
_FLOAT_MAX = 1.7976931348623157e308
_TYPE_WORDS = {
    "string": "a string",
    "number": "a number",
    "integer": "a whole number",
    "boolean": "true or false",
    "array": "a list",
    "object": "an object",
    "null": "null",
}


def load_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a "hamid.fit/1" report, as shipped in the package."""
    from importlib import resources

    return json.loads(resources.files("hamid").joinpath(SCHEMA_FILE).read_text("utf-8"))


def check_result(data: object, *, source: str | None = None) -> None:
    """Check that a loaded JSON value is a "hamid.fit/1" report.

    Parameters
    ----------
    data : object
        The decoded JSON value.
    source : str, optional
        The file it came from, named first in the message.

    Raises
    ------
    DataError
        One line: the source, then the first violation, naming its key, e.g.
        ``r.json: not a hamid fit result (key 'method.level' is 5, expected a number
        strictly between 0 and 1)``.
    """
    report, matrix = _without_matrix(data)
    problem = (_depth_problem(report) or _schema_problem(report) or _matrix_problem(matrix)
               or _covariance_problem(data))
    if problem:
        prefix = f"{source}: " if source else ""
        raise DataError(f"{prefix}not a hamid fit result ({problem})")


def _without_matrix(data: object) -> tuple[object, object]:
    """Helper: the report with its covariance matrix left empty, and the matrix. The
    schema's validator took minutes over the 9 million entries of 3,002 parameters;
    `_matrix_problem` checks them in one loop."""
    covariance = data.get("covariance") if isinstance(data, dict) else None
    if not isinstance(covariance, dict) or not isinstance(covariance.get("matrix"), list):
        return data, []
    return {**data, "covariance": {**covariance, "matrix": []}}, covariance["matrix"]


def _matrix_problem(matrix: Any) -> str | None:
    """Helper: the first row of the covariance matrix that is not a list, or entry that is
    not a finite number or null, in words; None when there is none."""
    for i, row in enumerate(matrix):
        if not isinstance(row, list):
            return f"'covariance.matrix[{i}]' is {_describe(row)}, expected a list"
        if all(x is None or type(x) is float and -_FLOAT_MAX <= x <= _FLOAT_MAX
               or type(x) is int for x in row):
            continue
        j, value = next((j, x) for j, x in enumerate(row) if not (
            x is None or type(x) is int
            or type(x) is float and -_FLOAT_MAX <= x <= _FLOAT_MAX))
        return (f"'covariance.matrix[{i}][{j}]' is {_describe(value)}, expected a number "
                "or null")
    return None


def _schema_problem(data: object) -> str | None:
    """Helper: the first violation of the schema, in words, or None."""
    errors = list(_validator().iter_errors(data))
    if not errors:
        return None
    # The schema key first (a file of another kind says so), then the shallowest problem:
    # a missing section matters more than what is wrong inside another one.
    first = min(enumerate(errors), key=lambda item: (
        list(item[1].path) != ["schema"], len(_where(item[1])), item[0]))[1]
    return _words(first)


@functools.cache
def _validator() -> Any:
    """Helper: the schema's validator, with NaN and infinity not counted as numbers."""
    import jsonschema

    def is_number(checker: Any, value: object) -> bool:
        # Python's json reads NaN and Infinity, which JSON does not have.
        return (isinstance(value, int | float) and not isinstance(value, bool)
                and (isinstance(value, int) or math.isfinite(value)))

    base = jsonschema.Draft202012Validator
    checker = base.TYPE_CHECKER.redefine("number", is_number)
    validator = jsonschema.validators.extend(base, type_checker=checker)
    schema = load_schema()
    # Resolving a $ref for each of thousands of trajectories' entries took half the time.
    return validator(_inlined(schema, schema["$defs"]))


def _inlined(node: Any, defs: dict[str, Any]) -> Any:
    """Helper: a schema with each "$ref" to its $defs replaced by the definition, merged
    with the keywords beside it (which win); the schema has no recursive definition."""
    if isinstance(node, list):
        return [_inlined(item, defs) for item in node]
    if not isinstance(node, dict):
        return node
    inlined = {key: _inlined(value, defs) for key, value in node.items()
               if key not in ("$ref", "$defs")}
    if "$ref" in node:
        inlined = {**_inlined(defs[node["$ref"].removeprefix("#/$defs/")], defs), **inlined}
    return inlined


def _covariance_problem(data: Any) -> str | None:
    """Helper: what JSON Schema cannot say of `covariance`: a square matrix with a row per
    name (None when it is, or absent)."""
    covariance = data.get("covariance")
    if covariance is None:
        return None
    n = len(covariance["names"])
    matrix = covariance["matrix"]
    for i, row in enumerate(matrix):
        if len(row) != n:
            return (f"key 'covariance.matrix[{i}]' has {len(row)} entries, expected {n} "
                    "(one per name)")
    if len(matrix) != n:
        return f"key 'covariance.matrix' has {len(matrix)} rows, expected {n} (one per name)"
    return None


def _where(error: Any) -> list[str | int]:
    """Helper: the key path an error is about (for a missing key, that key's)."""
    path = list(error.absolute_path)
    missing = _missing(error)
    return path + [missing] if missing is not None else path


def _missing(error: Any) -> str | None:
    """Helper: the key whose absence an error reports, or None."""
    if error.validator == "required":
        return next(k for k in error.validator_value if k not in error.instance)
    if error.validator == "dependentRequired":
        return next(k for key, needed in error.validator_value.items()
                    if key in error.instance for k in needed if k not in error.instance)
    return None


def _words(error: Any) -> str:
    """Helper: one violation as a short sentence."""
    where = _where(error)
    if _missing(error) is not None:
        return f"missing key '{_path(where)}'"
    found = _describe(error.instance)
    expected = _expected(error)
    if not where:
        return f"top level is {found}, expected {expected}"
    noun = "key " if isinstance(where[-1], str) else ""
    return f"{noun}'{_path(where)}' is {found}, expected {expected}"


def _expected(error: Any) -> str:
    """Helper: what the schema asks for where an error was found."""
    keyword, value, schema = error.validator, error.validator_value, error.schema
    if keyword == "type":
        kinds = [value] if isinstance(value, str) else value
        return " or ".join(_TYPE_WORDS.get(k, k) for k in kinds)
    if keyword == "const":
        return _describe(value)
    if keyword == "enum":
        return "one of " + ", ".join(_describe(v) for v in value)
    if keyword in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        return _range(schema, value)
    return error.message


def _range(schema: dict[str, Any], broken: float) -> str:
    """Helper: a number's allowed range, as the schema gives it; `broken` is the bound the
    value is beyond."""
    noun = "a whole number" if schema.get("type") == "integer" else "a number"
    if abs(broken) == _FLOAT_MAX:
        return f"{noun} within the range of a double (±{_FLOAT_MAX:.2g})"

    def bound(key: str) -> Any:   # the range of a double goes without saying
        value = schema.get(key)
        return None if value is None or abs(value) == _FLOAT_MAX else value

    low, high = bound("minimum"), bound("maximum")
    low_open, high_open = bound("exclusiveMinimum"), bound("exclusiveMaximum")
    if low_open is not None and high_open is not None:
        return f"{noun} strictly between {low_open:g} and {high_open:g}"
    if low is not None and high is not None:
        return f"{noun} from {low} to {high}"
    if low_open is not None:
        return f"{noun} > {low_open:g}"
    if high_open is not None:
        return f"{noun} < {high_open:g}"
    return f"{noun} ≥ {low}" if low is not None else f"{noun} ≤ {high}"


def _path(where: list[str | int]) -> str:
    """Helper: a key path as text: method.refinement, parameters[2].name, noise["a b"]."""
    text = ""
    for step in where:
        if isinstance(step, int):
            text += f"[{step}]"
        elif step.isidentifier():
            text += f".{step}" if text else step
        else:
            text += f"[{json.dumps(step)}]"   # escapes quotes and control characters
    return text


def _describe(value: object) -> str:
    """Helper: a short description of a JSON value for an error message."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value if len(value) <= 40 else value[:37] + "...")
    if isinstance(value, int) and abs(value) > 10**15:
        # Written out in full, such a number could fill the screen.
        digits = int(value.bit_length() * math.log10(2)) + 1
        return f"an integer of about {digits} digits"
    if isinstance(value, int | float):
        return repr(value)
    return "a list" if isinstance(value, list) else "an object"


def _depth_problem(data: object) -> str | None:
    """Helper: a value nested deeper than MAX_DEPTH, named by its first keys, or a number
    that JSON cannot hold (NaN, infinity: Python's json reads them) anywhere, also under
    keys the schema leaves open; None when there is neither.

    Walked with a stack of our own, so that the check itself never recurses.
    """
    stack: list[tuple[object, list[str | int], int]] = [(data, [], 0)]
    while stack:
        value, where, depth = stack.pop()
        if depth > MAX_DEPTH:
            shown = _path(where[:3]) + ("..." if len(where) > 3 else "")
            return f"key '{shown}' is nested more than {MAX_DEPTH} levels deep"
        if isinstance(value, float) and not math.isfinite(value):
            return f"key '{_path(where)}' is {value!r}, expected a number"
        stack.extend((child, [*where, step], depth + 1) for step, child in _children(value))
    return None


def _children(value: object) -> Iterator[tuple[str | int, object]]:
    """Helper: the members of a JSON object or list, with their keys or positions."""
    if isinstance(value, dict):
        yield from value.items()
    elif isinstance(value, list):
        yield from enumerate(value)
