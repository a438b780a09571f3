"""Which file columns hold a model's coordinates, velocities, time and trajectory.

The naming rules (`x` with `vx`, `x_dot`, `xdot` or `dx`; `t` or `time`; `trajectory`) and
their resolution against `--columns`. No numpy, pandas or pyarrow: the CLI may use them.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence

from hamid import io
from hamid.errors import DataError, UsageError

__all__ = ["default_time_column", "default_trajectory_column", "find_coordinates",
           "find_velocity", "resolve_columns"]


VELOCITY_PATTERNS = ("v{}", "{}_dot", "{}dot", "d{}")


TIME_COLUMNS = ("t", "time")


TRAJECTORY_COLUMN = "trajectory"


def find_velocity(coordinate: str, columns: Collection[str]) -> str | None:
    """Return the column holding a coordinate's velocity, by `VELOCITY_PATTERNS`.

    Parameters
    ----------
    coordinate : str
        Name of the coordinate's column.
    columns : collection of str
        Column names to look in (a set is used as it is).

    Returns
    -------
    velocity : str or None
        The first of ``v<x>``, ``<x>_dot``, ``<x>dot``, ``d<x>`` present, else None.

    Examples
    --------
    >>> find_velocity("x", ["t", "x", "x_dot", "dx"])
    'x_dot'
    """
    if not coordinate:
        return None
    present = columns if isinstance(columns, set | frozenset) else set(columns)
    for pattern in VELOCITY_PATTERNS:
        candidate = pattern.format(coordinate)
        if candidate in present:
            return candidate
    return None


def find_coordinates(columns: Sequence[str], *, exclude: Collection[str]) -> list[tuple[str, str]]:
    """Return the coordinate columns of a table and their velocity columns.

    A coordinate is a column, not excluded, that has a velocity column by
    `VELOCITY_PATTERNS` and is not itself the velocity of another such column.

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
    """
    candidates = [column for column in columns if column and column not in exclude]
    present = set(candidates)   # once: a table may have tens of thousands of columns
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


def resolve_columns(
    columns: Sequence[str],
    coordinates: Sequence[str],
    velocities: Sequence[str],
    *,
    mapping: Mapping[str, str] | None = None,
    source: str,
) -> dict[str, str]:
    """Find the file column of each coordinate and velocity of a model.

    Each name is looked for in `mapping`, then as the same name; a velocity not found so is
    looked for by `VELOCITY_PATTERNS`, applied to its coordinate's name and to its
    coordinate's file column.

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

    Returns
    -------
    columns : dict
        Model name -> file column, coordinates first.

    Raises
    ------
    UsageError
        A key of `mapping` is not a name of the model.
    DataError
        A name has no column, a mapped column is missing, or two names share a column.

    Examples
    --------
    >>> resolve_columns(["t", "pos", "vel"], ["x"], ["v"], mapping={"x": "pos", "v": "vel"},
    ...                 source="run.csv")
    {'x': 'pos', 'v': 'vel'}
    """
    mapping = dict(mapping or {})
    names = [*coordinates, *velocities]
    for key in mapping:
        if key not in names:
            raise UsageError(
                f"--columns: {key!r} is not a coordinate or velocity of the model "
                f"({', '.join(names)})"
            )
    present = set(columns)
    for key, column in mapping.items():
        if column not in present:
            raise DataError(
                f"{source}: no column {column!r} (given for {key!r} by --columns; "
                f"columns: {io.list_columns(columns)})"
            )
    resolved: dict[str, str] = {}
    for coordinate in coordinates:
        column = mapping.get(coordinate, coordinate)
        if column not in present:
            raise DataError(
                f"{source}: no column for coordinate {coordinate!r} "
                f"(columns: {io.list_columns(columns)})"
            )
        resolved[coordinate] = column
    # No velocities: they will be derived from the positions.
    for coordinate, velocity in zip(coordinates if velocities else (), velocities, strict=True):
        if velocity in mapping:
            resolved[velocity] = mapping[velocity]
            continue
        looked_for = [velocity]
        for base in (coordinate, resolved[coordinate]):
            looked_for += [pattern.format(base) for pattern in VELOCITY_PATTERNS]
        looked_for = list(dict.fromkeys(looked_for))
        found = next((candidate for candidate in looked_for if candidate in present), None)
        if found is None:
            raise DataError(
                f"{source}: no column for velocity {velocity!r} of coordinate {coordinate!r} "
                f"(looked for {', '.join(looked_for)})"
            )
        resolved[velocity] = found
    owner: dict[str, str] = {}
    for model_name, column in resolved.items():
        if column in owner:
            raise DataError(
                f"{source}: column {column!r} is used for both {owner[column]!r} and "
                f"{model_name!r}"
            )
        owner[column] = model_name
    return resolved


def default_time_column(columns: Sequence[str]) -> str | None:
    """Return the time column, ``t`` or else ``time``, if the table has one."""
    return next((name for name in TIME_COLUMNS if name in columns), None)


def default_trajectory_column(columns: Sequence[str]) -> str | None:
    """Return the trajectory column, ``trajectory``, if the table has one."""
    return TRAJECTORY_COLUMN if TRAJECTORY_COLUMN in columns else None
