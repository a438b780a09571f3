"""Which file columns hold a model's coordinates, velocities, time and trajectory.

The naming rules (`x` with `vx`, `x_dot`, `xdot` or `dx`; `x1`, `q1` or `u1` with `v1`;
`theta` with `omega`; `t` or `time`, any case, with a unit; `trajectory`), unit suffixes,
and their resolution against `--columns`. No numpy, pandas or pyarrow: the CLI may use them.

A unit suffix is ``_UNIT``, `` [UNIT]`` or `` (UNIT)`` after the name (``x1_mm``,
``v1_mm_s``, ``Time [s]``, ``t (ms)``); ``/`` in a unit reads as ``_`` (``mm/s``). A column
with a suffix is matched by the name before it, and its values are brought to SI units
(`COLUMN_UNITS`: metres, radians and their rates; `TIME_UNITS` for time).
"""

from __future__ import annotations

import math
import re
from collections.abc import Collection, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from hamid.data import readers
from hamid.errors import DataError, UsageError
from hamid.model.names import acceleration_name

if TYPE_CHECKING:
    from hamid.model.models import Model
    from hamid.options import FitOptions

__all__ = ["ACCELERATION_UNITS", "COLUMN_UNITS", "STANDARD_GRAVITY", "TIME_UNITS",
           "channel_columns", "column_scale", "default_time_column", "left_out_pairs",
           "default_trajectory_column", "find_coordinates", "find_velocity",
           "looks_like_time", "read_units", "resolve_columns", "split_unit", "time_scale",
           "unit_text", "velocity_names"]


VELOCITY_PATTERNS = ("v{}", "{}_dot", "{}dot", "d{}")
# Other pairs by name: x1, q1 or u1 with v1; theta with omega.
_NUMBERED = re.compile(r"^[a-z]+(\d+)$")
_ANGLE_RATES = {"theta": "omega", "phi": "omega"}


TIME_COLUMNS = ("t", "time")
# Seconds per unit of a time column.
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
# SI (metres, radians, and per second) per unit of a coordinate or velocity column.
_LENGTHS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "nm": 1e-9,
            "rad": 1.0, "mrad": 1e-3, "deg": math.pi / 180}
STANDARD_GRAVITY = 9.80665   # m/s^2 per g
# SI per unit of an acceleration column (``a_g``, ``a [m/s^2]``, ``alpha_rad_s2``).
ACCELERATION_UNITS = {"g": STANDARD_GRAVITY,
                      **{f"{unit}_s2": factor for unit, factor in _LENGTHS.items()}}
COLUMN_UNITS = {**_LENGTHS, **{f"{unit}_s": factor for unit, factor in _LENGTHS.items()},
                **ACCELERATION_UNITS}
_BRACKETED = re.compile(r"^(.*?)\s*[\[(]\s*([^\])]*?)\s*[\])]$")


def unit_text(text: str) -> str:
    """A unit as written, in the form of the unit tables (lower case, ``u`` for micro, ``_``
    for ``/``)."""
    text = text.strip().lower().replace("µ", "u").replace("μ", "u").replace("/", "_")
    for square in ("^2", "**2", "²"):
        text = text.replace(square, "2")
    return text.replace(" ", "")


def split_unit(name: str, units: Collection[str]) -> tuple[str, str | None]:
    """Split a column name into its name and a unit suffix of `units`, if it has one.

    Examples
    --------
    >>> split_unit("v1_mm_s", COLUMN_UNITS)
    ('v1', 'mm_s')
    >>> split_unit("Time [ms]", TIME_UNITS)
    ('Time', 'ms')
    >>> split_unit("x_dot", COLUMN_UNITS)
    ('x_dot', None)
    """
    bracketed = _BRACKETED.match(name)
    if bracketed and bracketed.group(1) and unit_text(bracketed.group(2)) in units:
        return bracketed.group(1), unit_text(bracketed.group(2))
    lowered = unit_text(name)
    for unit in sorted(units, key=len, reverse=True):
        if lowered.endswith("_" + unit) and len(name) > len(unit) + 1:
            return name[:-len(unit) - 1], unit
    return name, None


def column_scale(name: str) -> tuple[float, str | None]:
    """The factor that brings a column to SI units by its suffix, and the unit (1, None
    without one)."""
    _, unit = split_unit(name, COLUMN_UNITS)
    return (1.0, None) if unit is None else (COLUMN_UNITS[unit], unit)


def time_scale(name: str, unit: str | None = None) -> tuple[float, str]:
    """Seconds per unit of a time column: `unit` (--time-unit) if given, else the name's
    suffix, else seconds."""
    if unit is None:
        unit = split_unit(name, TIME_UNITS)[1] or "s"
    return TIME_UNITS[unit], unit


def looks_like_time(name: str) -> bool:
    """Whether a column is named as time (``t``, ``time``, ``timestamp``, any case or
    unit), whether or not its unit is known."""
    base = re.split(r"[\s_\[(]", name.strip(), maxsplit=1)[0].lower()
    return base in ("t", "time", "timestamp", "times")


TRAJECTORY_COLUMN = "trajectory"


def _index(columns: Collection[str]) -> dict[str, str]:
    """Name -> column: each column by its own name, and by its name without a unit suffix
    when no column has that name and no other column has that base."""
    index = {column: column for column in columns}
    bases: dict[str, list[str]] = {}
    for column in columns:
        base, unit = split_unit(column, COLUMN_UNITS)
        if unit is not None:
            bases.setdefault(base, []).append(column)
    for base, owners in bases.items():
        if base not in index and len(owners) == 1:
            index[base] = owners[0]
    return index


def velocity_names(coordinate: str) -> list[str]:
    """The names a coordinate's velocity may have, in the order they are looked for.

    Examples
    --------
    >>> velocity_names("x1")
    ['vx1', 'x1_dot', 'x1dot', 'dx1', 'v1']
    >>> velocity_names("theta")
    ['vtheta', 'theta_dot', 'thetadot', 'dtheta', 'omega']
    """
    names = [pattern.format(coordinate) for pattern in VELOCITY_PATTERNS]
    numbered = _NUMBERED.match(coordinate)
    if numbered and not coordinate.startswith("v"):
        names.append(f"v{numbered.group(1)}")
    lowered = coordinate.lower()
    for angle, rate in _ANGLE_RATES.items():
        if lowered.startswith(angle) and (lowered == angle or lowered[len(angle):].isdigit()):
            names.append(rate + coordinate[len(angle):])
    return [name for name in dict.fromkeys(names) if name != coordinate]


def find_velocity(coordinate: str, columns: Collection[str]) -> str | None:
    """Return the column holding a coordinate's velocity, by `velocity_names`.

    Parameters
    ----------
    coordinate : str
        Name of the coordinate's column.
    columns : collection of str
        Column names to look in (a dict from `_index` is used as it is).

    Returns
    -------
    velocity : str or None
        The first of `velocity_names` present (by name, or by name before a unit suffix),
        else None.

    Examples
    --------
    >>> find_velocity("x", ["t", "x", "x_dot", "dx"])
    'x_dot'
    >>> find_velocity("x1_mm", ["x1_mm", "v1_mm_s"])
    'v1_mm_s'
    """
    if not coordinate:
        return None
    index = columns if isinstance(columns, dict) else _index(columns)
    base = split_unit(coordinate, COLUMN_UNITS)[0]
    for name in (coordinate, base):
        for candidate in velocity_names(name):
            if candidate in index and index[candidate] != coordinate:
                return index[candidate]
    return None


def find_coordinates(columns: Sequence[str], *, exclude: Collection[str]) -> list[tuple[str, str]]:
    """Return the coordinate columns of a table and their velocity columns.

    A coordinate is a column, not excluded, that has a velocity column by
    `velocity_names` and is not itself the velocity of another such column.

    Parameters
    ----------
    columns : sequence of str
        Column names in file order.
    exclude : collection of str
        Columns that are never coordinates or velocities (time, trajectory).

    Returns
    -------
    pairs : list of (str, str)
        (coordinate column, velocity column), in file order.

    Examples
    --------
    >>> find_coordinates(["t", "x", "y", "vx", "vy"], exclude={"t"})
    [('x', 'vx'), ('y', 'vy')]
    >>> find_coordinates(["x", "dx", "ddx"], exclude=())
    [('x', 'dx')]
    >>> find_coordinates(["time_ms", "x1_mm", "x2_mm", "v1", "v2"], exclude={"time_ms"})
    [('x1_mm', 'v1'), ('x2_mm', 'v2')]
    """
    candidates = [column for column in columns if column and column not in exclude]
    present = _index(candidates)   # once: a table may have tens of thousands of columns
    velocity_of = {column: find_velocity(column, present) for column in candidates}
    # Velocities of velocities (dx of x, then ddx of dx) are accelerations, not coordinates.
    velocities = {velocity for velocity in velocity_of.values() if velocity is not None}
    pairs: list[tuple[str, str]] = []
    used: set[str] = set()
    for column in candidates:
        velocity = velocity_of[column]
        if velocity is None or column in velocities or velocity in used:
            continue
        pairs.append((column, velocity))
        used.add(velocity)
    return pairs


def _velocity_names_of(coordinate: str, velocity: str, column: str | None) -> list[str]:
    """The names a velocity's column may have: its own, then `velocity_names` of its
    coordinate's name and of that coordinate's column (with and without its unit)."""
    looked_for = [velocity]
    for base in (coordinate, *([] if column is None else
                               [column, split_unit(column, COLUMN_UNITS)[0]])):
        looked_for += velocity_names(base)
    return list(dict.fromkeys(looked_for))


def _acceleration_names_of(coordinate: str, velocity: str, acceleration: str,
                           column: str | None) -> list[str]:
    """The names an acceleration's column may have: its own, then the names that follow
    each name its velocity may have (`acceleration_name`: vx -> ax, x_dot -> x_ddot), then
    ``acc_`` before the coordinate's name."""
    rates = _velocity_names_of(coordinate, velocity, column)
    bases = [coordinate, *([] if column is None else [split_unit(column, COLUMN_UNITS)[0]])]
    names = [acceleration, *map(acceleration_name, rates), *(f"acc_{b}" for b in bases)]
    return [name for name in dict.fromkeys(names) if name not in (coordinate, velocity)]


def _check_acceleration_unit(name: str, column: str | None, looked_for: Sequence[str],
                             columns: Sequence[str], source: str) -> None:
    """An acceleration's column in a unit not of `ACCELERATION_UNITS` (``a [ft/s2]``,
    ``a_ft_s2``, ``a_mm``) is an error, not a column read as SI or passed over."""
    if column is not None:
        unit = split_unit(column, COLUMN_UNITS)[1]
        if unit is None or unit in ACCELERATION_UNITS:
            return
        candidates = [(column, unit)]
    else:
        candidates = []
        for other in columns:
            bracketed = _BRACKETED.match(other)
            if bracketed and bracketed.group(1) in looked_for:
                candidates.append((other, unit_text(bracketed.group(2))))
            elif unit_text(other).endswith("s2"):
                candidates += [(other, unit_text(other)[len(n) + 1:]) for n in looked_for
                               if other.startswith(n + "_")]
    if candidates:
        other, unit = candidates[0]
        raise DataError(f"{source}: column {other!r}: unit {unit!r} is not an acceleration's "
                        f"that hamid converts ({', '.join(ACCELERATION_UNITS)}); give "
                        f"--scale {other}=FACTOR to SI and rename it {name}")


def resolve_columns(
    columns: Sequence[str],
    coordinates: Sequence[str],
    velocities: Sequence[str],
    *,
    mapping: Mapping[str, str] | None = None,
    source: str,
    inputs: Sequence[str] = (),
    accelerations: Sequence[str] = (),
    partial: bool = False,
) -> dict[str, str]:
    """Find the file column of each coordinate, velocity, acceleration and input of a model.

    With `partial`, a coordinate may have any non-empty subset of position, velocity and
    acceleration columns (`accelerations`, the model's names of them, are looked for only
    then): the channels not recorded are reconstructed from those that are. Without it,
    every position and velocity needs its column.

    Each name is looked for in `mapping`, then as the same name (or the same name before a
    unit suffix); a velocity not found so is looked for by `velocity_names`, applied to its
    coordinate's name and to its coordinate's file column, and an acceleration by the names
    that follow those (`acceleration_name`) and ``acc_`` before the coordinate's name.

    Parameters
    ----------
    columns : sequence of str
        Column names of the file.
    coordinates, velocities : sequence of str
        The model's names; ``velocities[i]`` is the velocity of ``coordinates[i]``.
    mapping : mapping of str to str, optional
        Model name -> file column, as given by ``--columns``.
    source : str
        File name used in messages.
    inputs : sequence of str
        The model's recorded inputs (`Model.forcing`), found like coordinates.
    accelerations : sequence of str
        The model's names of the accelerations (`Model.acceleration_names`), with `partial`.

    Returns
    -------
    columns : dict
        Model name -> file column of the names found: coordinates, velocities,
        accelerations, inputs.

    Raises
    ------
    UsageError
        A key of `mapping` is not a name of the model.
    DataError
        A name has no column (with `partial`: a coordinate has none at all), a mapped column
        is missing, two names share a column, or an acceleration's unit is unknown.

    Examples
    --------
    >>> resolve_columns(["t", "pos", "vel"], ["x"], ["v"], mapping={"x": "pos", "v": "vel"},
    ...                 source="run.csv")
    {'x': 'pos', 'v': 'vel'}
    >>> resolve_columns(["t", "a_g"], ["x"], ["v"], accelerations=["a"], partial=True,
    ...                 source="run.csv")
    {'a': 'a_g'}
    """
    mapping = dict(mapping or {})
    accelerations = tuple(accelerations) if partial else ()
    names = [*coordinates, *velocities, *accelerations, *inputs]
    for key in mapping:
        if key not in names:
            kinds = ["coordinate", "velocity", *(["acceleration"] * bool(accelerations)),
                     *(["input"] * bool(inputs))]
            raise UsageError(f"--columns: {key!r} is not a {', '.join(kinds[:-1])} or "
                             f"{kinds[-1]} of the model ({', '.join(names)})")
    present = set(columns)
    index = _index(columns)
    for key, column in mapping.items():
        if column not in present:
            raise DataError(
                f"{source}: no column {column!r} (given for {key!r} by --columns; "
                f"columns: {readers.list_columns(columns)})"
            )
    resolved: dict[str, str] = {}
    # coordinates and inputs: by --columns, else their name (before a unit suffix)
    named = [(name, "coordinate", "") for name in coordinates] + [
        (name, "input", " of the model's [forcing]") for name in inputs]
    for name, kind, owner_text in named:
        column = mapping.get(name, index.get(name, name))
        if column in present:
            resolved[name] = column
        elif not (partial and kind == "coordinate"):
            hint = f"; map it with --columns {name}=COL" if kind == "input" else ""
            raise DataError(
                f"{source}: no column for {kind} {name!r}{owner_text} "
                f"(columns: {readers.list_columns(columns)}){hint}"
            )
    for k, (coordinate, velocity) in enumerate(zip(coordinates, velocities, strict=True)):
        position = resolved.get(coordinate)
        looked_for = _velocity_names_of(coordinate, velocity, position)
        found = mapping.get(velocity, next(
            (index[candidate] for candidate in looked_for if candidate in index), None))
        if found is not None:
            resolved[velocity] = found
        elif not partial:
            raise DataError(
                f"{source}: no column for velocity {velocity!r} of coordinate {coordinate!r} "
                f"(looked for {', '.join(looked_for)}); map it with --columns "
                f"{velocity}=COL, or derive velocities with --velocity savgol"
            )
        if not accelerations:
            continue
        acceleration = accelerations[k]
        rates = _acceleration_names_of(coordinate, velocity, acceleration, position)
        found = mapping.get(acceleration, next(
            (index[candidate] for candidate in rates if candidate in index), None))
        _check_acceleration_unit(acceleration, found, rates, columns, source)
        if found is not None:
            resolved[acceleration] = found
        elif position is None and velocity not in resolved:
            raise DataError(
                f"{source}: no column for coordinate {coordinate!r}: no position, velocity or "
                f"acceleration (looked for {coordinate}, {', '.join(looked_for)}, "
                f"{', '.join(rates)}; columns: {readers.list_columns(columns)}); map one with "
                f"--columns {coordinate}=COL"
            )
    owner: dict[str, str] = {}
    for model_name, column in resolved.items():
        if column in owner:
            raise DataError(
                f"{source}: column {column!r} is used for both {owner[column]!r} and "
                f"{model_name!r}"
            )
        owner[column] = model_name
    return resolved


def channel_columns(names: Sequence[str], model: Model, mapping: Mapping[str, str] | None, *,
                    source: str, set_aside: bool) -> dict[str, str]:
    """Model name -> column of each channel a table records (`resolve_columns`, `partial`),
    the measured velocities `set_aside` (--velocity savgol)."""
    found = resolve_columns(names, model.coordinates, model.velocities, mapping=mapping,
                            source=source, inputs=model.inputs,
                            accelerations=model.acceleration_names, partial=True)
    if not set_aside:
        return found
    found = {name: column for name, column in found.items() if name not in model.velocities}
    for coordinate, acceleration in zip(model.coordinates, model.acceleration_names,
                                        strict=True):
        if coordinate not in found and acceleration not in found:
            raise DataError(f"{source}: --velocity savgol derives the velocities from the "
                            f"positions, and coordinate {coordinate!r} has no position "
                            "column; leave the option out to fit its velocities")
    return found


def default_time_column(columns: Sequence[str]) -> str | None:
    """Return the time column, if the table has one: ``t``, else ``time``, else the first
    column named so in any case with a unit of `TIME_UNITS` (``Time``, ``time_ms``,
    ``t (ms)``, ``Time [s]``).

    Examples
    --------
    >>> default_time_column(["time_ms", "x1_mm", "v1"])
    'time_ms'
    """
    exact = next((name for name in TIME_COLUMNS if name in columns), None)
    if exact is not None:
        return exact
    return next((name for name in columns
                 if split_unit(name, TIME_UNITS)[0].strip().lower() in TIME_COLUMNS), None)


def default_trajectory_column(columns: Sequence[str]) -> str | None:
    """Return the trajectory column, ``trajectory``, if the table has one."""
    return TRAJECTORY_COLUMN if TRAJECTORY_COLUMN in columns else None


def read_units(names: list[str], mapping: Mapping[str, str], time: str | None,
           options: FitOptions, metadata: Mapping[str, Any] | None,
           source: str) -> dict[str, Any]:
    """The time column, its unit, and the factor bringing each column read to SI units
    (seconds for time): --scale, else the column's unit suffix, else the unit the table's
    metadata records (``{"units": {column: unit}}``), else 1."""
    recorded = metadata.get("units") if isinstance(metadata, Mapping) else None
    recorded = recorded if isinstance(recorded, Mapping) else {}
    given = dict(options.scale or {})
    read = [*mapping.values(), *([time] if time else [])]
    for column in given:
        if column not in read:
            raise UsageError(f"--scale: {column!r} is not a column read from {source} "
                             f"(read: {', '.join(read)})")
    scale: dict[str, float] = {}
    unknown = []
    for column in mapping.values():
        factor, unit = column_scale(column)
        if unit is None and isinstance(recorded.get(column), str):
            factor = COLUMN_UNITS.get(unit_text(recorded[column]), 1.0)
            if unit_text(recorded[column]) not in COLUMN_UNITS \
                    and column not in given:
                unknown.append(f"{column!r} ({recorded[column]!r})")
        scale[column] = given.get(column, factor)
    time_unit = None
    if time is not None:
        unit = options.time_unit
        if unit is None and split_unit(time, TIME_UNITS)[1] is None \
                and isinstance(recorded.get(time), str) \
                and unit_text(recorded[time]) in TIME_UNITS:
            unit = unit_text(recorded[time])
        scale[time], time_unit = time_scale(time, unit)
        if time in given:
            scale[time], time_unit = given[time], f"{given[time]:g} s"
    elif options.time_unit is not None:
        raise UsageError(f"--time-unit {options.time_unit}: {source} has no time column; "
                         "name it with --time COL")
    notes = [f"{source}: the units of {', '.join(unknown)} are not among those converted "
             f"({', '.join(COLUMN_UNITS)}): read as SI; give --scale COL=FACTOR"
             ] if unknown else []
    return {"time": time, "time_unit": time_unit, "scale": scale, "notes": notes}


def left_out_pairs(columns: Sequence[str], used: Collection[str], model: str,
                   source: str) -> list[str]:
    """A note naming the columns that look like a coordinate and its velocity (`find_coordinates`)
    but that the model does not read (`used`: the columns read): a model of fewer coordinates
    than the recording, fitted without a word about the rest."""
    pairs = [f"{q} with {v}" for q, v in find_coordinates(columns, exclude=used)]
    if not pairs:
        return []
    return [f"{source}: {', '.join(pairs)} look{'s' if len(pairs) == 1 else ''} like a "
            f"coordinate and its velocity that the model {model!r} does not have: not fitted"]
