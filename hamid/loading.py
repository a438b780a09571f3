"""Reading the data into Records: sources, the model they settle, columns, order checks."""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hamid.errors import DataError, UsageError
from hamid.model import (
    BUILTINS,
    Model,
    builtin_model,
    damping_names,
    load_model,
    model_from_expression,
)
from hamid.options import SAVGOL_ORDER
from hamid.records import Records


@dataclass(frozen=True)
class Loaded:
    """Records ready to fit, the model, and what the report says about the data."""

    model: Model
    records: Records
    truth: dict[str, float]
    data_info: dict[str, Any]
    notes: tuple[str, ...]
    velocity_gain: float | None  # noise gain of derived velocities, None when measured
    row_sources: tuple[tuple[str, int], ...]  # (source, first row) of each input table

    def locate(self, row: int) -> tuple[str, int]:
        """The source and 1-based data row of a row of the records."""
        source, first = next((s, f) for s, f in reversed(self.row_sources) if f <= row)
        return source, row - first + 1


def load(data: Any, model: str | os.PathLike[str] | Model | None, *,
               columns: Mapping[str, str] | None, time: str | None,
               trajectory: str | None, format: str | None, velocity: str = "measured",
               window: int | None = None, order: int = SAVGOL_ORDER) -> Loaded:
    """Read the sources, settle the model and arrange the rows by trajectory."""
    from hamid import io, naming

    if _is_data_frame(data):
        tables = [("<DataFrame>", data, data.attrs.get("hamid"))]
    else:
        paths = [data] if isinstance(data, str | os.PathLike) else list(data)
        if not paths:
            raise UsageError("no data given")
        tables = [(os.fspath(p) if os.fspath(p) != "-" else "<stdin>",
                   *io.read_columns(p, format=format)) for p in paths]
    first_name, first_table, metadata = tables[0]
    notes = []
    if isinstance(model, Model):
        m = model
    elif model is not None:
        m = load_model(model)
    elif metadata and isinstance(metadata.get("model"), Mapping):
        m = model_from_metadata(metadata["model"], first_name)
    else:
        m = assumed_model([str(c) for c in first_table], first_name, columns,
                           time, trajectory)
        notes.append(f"no model given: assumed {m.name} over the coordinates "
                     f"{', '.join(m.coordinates)} (pick one with --model)")

    X_parts, t_parts, group_parts, labels, mapping = [], [], [], [], {}
    has_time = True
    for source, frame, _ in tables:
        names = [str(c) for c in frame]
        derived = velocity == "savgol"
        mapping = naming.resolve_columns(names, m.coordinates, () if derived else m.velocities,
                                     mapping=columns, source=source)
        time_col = optional_column(names, time, naming.default_time_column(names), "--time",
                                    source)
        traj_col = optional_column(names, trajectory, naming.default_trajectory_column(names),
                                    "--trajectory", source)
        n_rows = len(frame[names[0]])
        X = np.column_stack([io.numeric_column(frame, mapping[v], source=source)
                             if v in mapping else np.zeros(n_rows) for v in m.variables])
        t = io.numeric_column(frame, time_col, source=source) if time_col else None
        has_time = has_time and t is not None
        if traj_col is None:
            keys = np.zeros(n_rows, dtype=np.int64)
            traj_labels = [source if len(tables) > 1 else 1]
        else:
            keys, traj_labels = trajectory_keys(io.column_values(frame[traj_col]), traj_col,
                                                 source)
            if len(tables) > 1:
                traj_labels = [f"{source}:{label}" for label in traj_labels]
        check_order(keys, t, source, traj_col, time_col)
        X_parts.append(X)
        t_parts.append(t)
        group_parts.append(keys + len(labels))
        labels.extend(traj_labels)
    records = Records(np.vstack(X_parts),
                      np.concatenate(t_parts) if has_time else None,
                      np.concatenate(group_parts), tuple(labels))
    derivation = None
    if velocity == "savgol":
        records, derivation = derive_velocities(records, m, window, order)
    truth = truth_of(metadata, m)
    data_info = {
        "sources": [name for name, _, _ in tables],
        "n_samples": int(len(records.group)),
        "n_trajectories": records.n_trajectories,
        "columns": dict(mapping),
        "velocity_source": velocity,
        **({"velocity_window": derivation[0], "velocity_order": order}
           if derivation else {}),
    }
    if derivation:
        notes.append(f"velocities derived from the positions (Savitzky-Golay, window "
                     f"{derivation[0]} samples, order {order}); their noise is correlated "
                     "with the positions'")
    firsts = np.cumsum([0] + [len(frame) for _, frame, _ in tables[:-1]])
    return Loaded(m, records, truth, data_info, tuple(notes),
                   derivation[1] if derivation else None,
                   tuple((name, int(f)) for (name, _, _), f in zip(tables, firsts, strict=True)))


def truth_of(metadata: Mapping[str, Any] | None, m: Model) -> dict[str, float]:
    """The true parameters a simulated file records for this model, else none."""
    if not (metadata and isinstance(metadata.get("model"), Mapping)
            and metadata["model"].get("energy") == m.energy):
        return {}
    # A simulated record had no damping but what its [damping] table lists.
    undamped = dict.fromkeys(damping_names(m.coordinates), 0.0) \
        if isinstance(metadata.get("damping"), Mapping) else {}
    values = {**undamped, **(metadata.get("parameters") or {}),
              **(metadata.get("damping") or {})}
    return {k: float(v) for k, v in values.items() if isinstance(v, int | float)}


def derive_velocities(records: Records, model: Model, window: int | None,
                       order: int) -> tuple[Records, tuple[int, float]]:
    """Records whose velocities come from Savitzky-Golay differentiation of the positions."""
    import dataclasses

    from hamid import design, measurement

    if records.t is None:
        raise UsageError("--velocity savgol needs a time column")
    N = len(model.coordinates)
    if window is None:
        period = design.dominant_period(records, N)
        dt = float(np.median(np.diff(records.t)))
        window = measurement.default_savgol_window(None if period is None else period / dt,
                                                   order)
    V, gain = measurement.savgol_velocities(records.X[:, :N], records.t, records.bounds(),
                                            window=window, order=order)
    X = records.X.copy()
    X[:, N:] = V
    return dataclasses.replace(records, X=X), (window, gain)


def noise_levels(noise: str | Mapping[str, float] | None, model: Model, records: Records,
                  loaded: Loaded) -> tuple[Any, dict[str, float] | None]:
    """Noise std per model variable, from the user or estimated; None without --noise."""
    import math

    from hamid import measurement

    if noise is None or noise == "none":
        return None, None
    N = len(model.coordinates)
    columns = loaded.data_info["columns"]
    if noise == "auto":
        sigma = measurement.estimate_noise(records.X, records.bounds())
    elif isinstance(noise, Mapping):
        by_column = {column: name for name, column in columns.items()}
        sigma = np.zeros(len(model.variables))
        for key, value in noise.items():
            name = key if key in model.variables else by_column.get(key)
            if name is None:
                raise UsageError(f"--noise: {key!r} is not a column of the model "
                                 f"({', '.join(model.variables)})")
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise UsageError(f"--noise: {key}={value!r} is not a non-negative number")
            sigma[model.variables.index(name)] = float(value)
    else:
        raise UsageError(f"--noise must be none, auto or COL=SIGMA,..., found {noise!r}")
    if loaded.velocity_gain is not None:
        sigma[N:] = sigma[:N] * loaded.velocity_gain
    if not np.any(sigma > 0):
        raise UsageError("--noise: every column has zero noise; leave --noise out instead")
    return sigma, {name: float(s) for name, s in zip(model.variables, sigma, strict=True)}


def model_from_metadata(info: Mapping[str, Any], source: str) -> Model:
    """The model a simulated file records (built-in by name, else from its energy)."""
    name = info.get("name")
    if isinstance(name, str) and (name in BUILTINS or name.startswith("poly:")):
        candidate = builtin_model(name)
        if candidate.energy == info.get("energy"):
            return candidate
    try:
        return model_from_expression(str(name or "custom"), info["energy"],
                                     info["coordinates"], info["velocities"],
                                     info.get("parameters"), where=f"{source}: metadata model")
    except (KeyError, TypeError) as exc:
        raise DataError(f"{source}: the hamid metadata has no usable model ({exc}); "
                        "give one with --model") from exc


def assumed_model(names: list[str], source: str, columns: Mapping[str, str] | None,
                   time: str | None, trajectory: str | None) -> Model:
    """poly:N:3 over every column that has a velocity column (SPEC section 3, fit)."""
    from hamid import naming
    from hamid.model import poly_model_over

    exclude = {c for c in (time or naming.default_time_column(names),
                           trajectory or naming.default_trajectory_column(names)) if c}
    pairs = naming.find_coordinates(names, exclude=exclude)
    if not pairs:
        raise DataError(f"{source}: no model given and no coordinate with a velocity column "
                        f"found (columns: {', '.join(names)}); give --model, or name "
                        "velocities vx, x_dot, xdot or dx")
    if columns:
        raise UsageError("--columns needs --model (the assumed model takes the file's names)")
    return poly_model_over([q for q, _ in pairs], [v for _, v in pairs])


def optional_column(names: list[str], asked: str | None, default: str | None, option: str,
                     source: str) -> str | None:
    if asked is None:
        return default
    if asked not in names:
        raise DataError(f"{source}: no column {asked!r} for {option} "
                        f"(columns: {', '.join(names)})")
    return asked


def trajectory_keys(values: np.ndarray, column: str, source: str) -> tuple[Any, list[Any]]:
    """Index 0..J-1 of each row's trajectory, in order of first appearance, and the labels."""
    from hamid.io import is_missing

    if values.dtype.kind in "iu":
        missing = np.zeros(len(values), bool)
    elif values.dtype.kind == "f":
        missing = np.isnan(values)
    else:
        missing = np.fromiter((is_missing(v) for v in values), bool, len(values))
    if missing.any():
        row = int(np.flatnonzero(missing)[0]) + 1
        raise DataError(f"{source}: column {column!r}, row {row}: missing trajectory label")
    if values.dtype.kind in "iuf":
        uniques, first, codes = np.unique(values, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        codes, uniques = rank[codes.ravel()], uniques[order]
    else:   # text or mixed objects, which need not sort
        index: dict[Any, int] = {}
        codes = np.fromiter((index.setdefault(v, len(index)) for v in values), np.int64,
                            len(values))
        uniques = list(index)
    return codes.astype(np.int64), [trajectory_label(u) for u in uniques]


def trajectory_label(value: Any) -> Any:
    """A trajectory column's value as the label reported: a Python scalar, whole numbers
    as int (a column with missing cells is read as floats)."""
    value = value.item() if hasattr(value, "item") else value
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _is_data_frame(data: Any) -> bool:
    """Whether `data` is a pandas DataFrame, without importing pandas when it cannot be."""
    pandas = sys.modules.get("pandas")
    return pandas is not None and isinstance(data, pandas.DataFrame)


def check_order(keys: Any, t: Any, source: str, traj_col: str | None,
                 time_col: str | None) -> None:
    """Each trajectory's rows must be contiguous and, with a time column, increasing."""
    changes = np.flatnonzero(np.diff(keys)) + 1
    if len(np.unique(keys[np.concatenate([[0], changes])])) != len(changes) + 1:
        seen, row = set(), 0
        for start in np.concatenate([[0], changes]):
            if keys[start] in seen:
                row = int(start) + 1
                break
            seen.add(keys[start])
        raise DataError(f"{source}: column {traj_col!r}, row {row}: a trajectory resumes "
                        "after rows of another; sort the file by trajectory then time")
    if t is not None:
        step = np.diff(t)
        same = np.diff(keys) == 0
        bad = np.flatnonzero(same & ~(step > 0))
        if bad.size:
            row = int(bad[0]) + 2
            raise DataError(f"{source}: column {time_col!r}, row {row}: time does not increase "
                            f"({t[row - 2]:g} then {t[row - 1]:g})")
