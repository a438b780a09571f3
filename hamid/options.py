"""The fit's options: the choices the user types, their checks, and option values.

No numpy, pandas or pyarrow at import: the CLI takes its choice lists from here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from hamid.errors import UsageError


def parse_mapping(text: str, *, option: str) -> dict[str, str]:
    """Parse ``NAME=COLUMN,...`` as given to an option such as ``--columns``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> value, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=VALUE`` or a name is given twice.

    Examples
    --------
    >>> parse_mapping("x=pos1, vx=vel1", option="--columns")
    {'x': 'pos1', 'vx': 'vel1'}
    """
    return _parse_items(text, option, "NAME=COLUMN", lambda key, value, item: value)


def parse_float_mapping(text: str, *, option: str) -> dict[str, float]:
    """Parse ``NAME=NUMBER,...`` as given to options such as ``--noise`` and ``--fix``.

    Parameters
    ----------
    text : str
        The option's value.
    option : str
        The option's name, for messages.

    Returns
    -------
    mapping : dict
        Name -> finite number, in the order given.

    Raises
    ------
    UsageError
        An item is not ``NAME=NUMBER``, a number is not finite, or a name is given twice.

    Examples
    --------
    >>> parse_float_mapping("x=0.01,vx=2e-2", option="--noise")
    {'x': 0.01, 'vx': 0.02}
    """

    def to_float(key: str, value: str, item: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise UsageError(f"{option}: {item!r}: {value!r} is not a number") from None
        if not math.isfinite(number):
            raise UsageError(f"{option}: {item!r}: {value!r} is not a finite number")
        return number

    return _parse_items(text, option, "NAME=NUMBER", to_float)


def _parse_items(
    text: str, option: str, form: str, convert: Callable[[str, str, str], Any]
) -> dict[str, Any]:
    """Helper function splitting ``NAME=VALUE,...`` and checking each item."""
    result: dict[str, Any] = {}
    if not text.strip():
        raise UsageError(f"{option}: empty value; expected {form},...")
    for raw in text.split(","):
        item = raw.strip()
        key, equals, value = (part.strip() for part in item.partition("="))
        if not equals or not key or not value:
            raise UsageError(f"{option}: {item!r} is not of the form {form}")
        if key in result:
            raise UsageError(f"{option}: {key!r} is given twice")
        result[key] = convert(key, value, item)
    return result


COVARIANCE_KINDS = ("classical", "hc", "hac", "bootstrap")


VELOCITY_SOURCES = ("measured", "savgol")


SAVGOL_ORDER = 5


METHODS = ("auto", "joint", "weak", "energy")


# Files larger than this are read in chunks when the options allow it: the chunked fit is
# the fit in memory, faster and in a third of the memory.
STREAM_BYTES = 64 << 20


CHUNK_ROWS = 1 << 18


# The trajectory refinement of a chunked fit holds the records (times, states, trajectory
# numbers) in memory, 8 bytes a value; larger records are left unrefined.
REFINEMENT_BYTES = 1 << 30


def reads_in_chunks(data: Any) -> bool:
    """Whether a fit that can read `data` in chunks should, by its size."""
    return os.path.getsize(data) > STREAM_BYTES


def needs_memory(data: Any, velocity: str, noise: Any, damping: str | Sequence[str],
                  cov: str) -> str:
    """Why the fit needs all the data in memory, or "" when it can read them in chunks."""
    if not isinstance(data, str | os.PathLike) or os.fspath(data) == "-" \
            or not os.path.isfile(data):
        return "chunks need one file (not standard input, a list or a DataFrame)"
    if velocity != "measured":
        return "derived velocities (--velocity savgol) need the data in memory"
    if noise not in (None, "none"):
        return "noise weighting (--noise) needs the data in memory"
    if parse_damping(damping):
        return "damping (--damping) needs the data in memory"
    if cov == "bootstrap":
        return "--cov bootstrap needs the data in memory"
    return ""


def check_choice(value: str, choices: tuple[str, ...], option: str) -> None:
    if value not in choices:
        raise UsageError(f"{option} must be one of {', '.join(choices)}, found {value!r}")


def parse_damping(damping: str | Sequence[str]) -> tuple[str, ...]:
    """Damping kinds from "none", "viscous,coulomb" or a list; unknown kinds are errors."""
    from hamid.model import DAMPING_KINDS

    items = damping.split(",") if isinstance(damping, str) else list(damping)
    kinds = [item.strip() for item in items if item.strip()]
    if not kinds:
        raise UsageError("--damping: empty value; expected none or any of "
                         f"{', '.join(DAMPING_KINDS)} (comma separated)")
    if kinds == ["none"]:
        return ()
    for kind in kinds:
        if kind not in DAMPING_KINDS:
            raise UsageError(f"--damping: unknown kind {kind!r} (choose none or any of "
                             f"{', '.join(DAMPING_KINDS)}, comma separated)")
    if len(set(kinds)) != len(kinds):
        raise UsageError(f"--damping: a kind is given twice in {','.join(kinds)!r}")
    return tuple(kinds)


def check_fixed(fix: Mapping[str, float], parameters: tuple[str, ...]) -> dict[str, float]:
    import math

    for name, value in fix.items():
        if name not in parameters:
            raise UsageError(f"--fix: {name!r} is not a parameter of the model "
                             f"({', '.join(parameters)})")
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise UsageError(f"--fix: {name}={value!r} is not a finite number")
    return {name: float(value) for name, value in fix.items()}
