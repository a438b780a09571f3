"""Fits of a file read in chunks of rows, so that memory does not grow with its length.

Every pass reads the file again, chunk by chunk (Parquet batches, blocks of CSV text):

- ``energy``: the first pass accumulates each trajectory's triangular factor of its
  energy rows (`solve.Factor`), which gives the parameters and levels; the second the
  residual summary and the sums of the standard errors (`uncertainty.ScoreSums`); ``hac``
  takes a third, with the bandwidth found in the second.
- ``weak`` and ``joint``: the first pass finds each trajectory's period and time step,
  the second builds the window rows, carrying each trajectory's unfinished windows into
  the next chunk; the window rows (one per window and coordinate, a small fraction of the
  samples) are then fitted in memory as `hamid.api.fit` does, and a last pass gives the
  residual summary of the energy rows.
- ``auto`` (joint), unless `--chunk-rows` asked for bounded memory: a pass gathers the
  records (times, states, trajectory numbers; 8 bytes a value, a small part of what a fit
  in memory holds) for the trajectory refinement, and the residual pass is taken at the
  refined parameters.

The estimates equal those of the fit in memory up to rounding (tested to 1e-10; 1e-9
after the refinement, whose Gauss-Newton search starts from the linear fit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from hamid import api, design, io, solve, uncertainty
from hamid.design import Block, Records
from hamid.errors import DataError, FitError, UsageError
from hamid.model import Model
from hamid.result import FitResult

__all__ = ["fit_file"]


class _Reader:
    """Chunks of a file as Records, trajectories numbered in order of appearance; checks
    that every trajectory's rows are contiguous and its times increasing."""

    def __init__(self, table: io.TableChunks, model: Model, mapping: Mapping[str, str],
                 time: str | None, trajectory: str | None, chunk_rows: int,
                 progress: Callable[[str], None] | None) -> None:
        self.table, self.model, self.mapping = table, model, mapping
        self.time, self.trajectory, self.chunk_rows = time, trajectory, chunk_rows
        self.progress = progress
        # Without a trajectory column the file is one trajectory, labelled 1.
        self.labels: dict[Any, int] = {} if trajectory else {1: 0}

    def rows(self, purpose: str) -> Iterator[tuple[Records, int]]:
        """Each chunk's records and the file row (0-based) of its first row, in a pass for
        `purpose` (what `progress` is told)."""
        name = self.table.name
        wanted = [self.mapping[v] for v in self.model.variables]
        extra = [c for c in (self.time, self.trajectory) if c is not None]
        row, previous, last_t, closed = 0, None, None, set()
        for chunk in self.table.chunks([*wanted, *extra], self.chunk_rows):
            if self.progress is not None:
                self.progress(f"{name}: {purpose}, from row {row + 1:,}")
            n = len(chunk[wanted[0]])
            X = np.column_stack([io.numeric_values(chunk[c], c, name, first_row=row + 1)
                                 for c in wanted])
            t = (io.numeric_values(chunk[self.time], self.time, name, first_row=row + 1)
                 if self.time else None)
            group = self._keys(chunk, n, row) if self.trajectory else np.zeros(n, np.int64)
            # Contiguous trajectories, increasing times, also across the chunk boundary.
            starts = np.flatnonzero(np.diff(group, prepend=-1 if previous is None
                                            else previous))
            for start in starts:
                if int(group[start]) in closed:
                    raise DataError(f"{name}: column {self.trajectory!r}, row {row + start + 1}"
                                    ": a trajectory resumes after rows of another; sort the "
                                    "file by trajectory then time")
                if previous is not None:
                    closed.add(previous)
                previous = int(group[start])
            if t is not None:
                before = np.concatenate([[np.nan if last_t is None else last_t], t[:-1]])
                same = np.ones(n, dtype=bool)
                same[starts] = False
                bad = np.flatnonzero(same & ~(t > before))
                if bad.size:
                    k = int(bad[0])
                    raise DataError(f"{name}: column {self.time!r}, row {row + k + 1}: time "
                                    f"does not increase ({before[k]:g} then {t[k]:g})")
                last_t = float(t[-1])
            previous = int(group[-1])
            yield Records(X, t, group, ()), row
            row += n

    def _keys(self, chunk: dict[str, Any], n: int, row: int) -> np.ndarray:
        values = chunk[self.trajectory]
        change = np.flatnonzero(values[1:] != values[:-1]) + 1
        keys = np.empty(n, dtype=np.int64)
        for start, stop in zip([0, *change], [*change, n], strict=True):
            if io.is_missing(values[start]):
                raise DataError(f"{self.table.name}: column {self.trajectory!r}, row "
                                f"{row + start + 1}: missing trajectory label")
            label = api.trajectory_label(values[start])
            keys[start:stop] = self.labels.setdefault(label, len(self.labels))
        return keys

    def label_tuple(self) -> tuple[Any, ...]:
        return tuple(self.labels)


def fit_file(path: str, model: Any, *, columns: Mapping[str, str] | None, time: str | None,
             trajectory: str | None, format: str | None, fix: Mapping[str, float],
             method: str, weak_window: float | None, cov: str, level: float,
             chunk_rows: int, refine: bool,
             progress: Callable[[str], None] | None) -> FitResult:
    """`hamid.api.fit` of one file, read in chunks of `chunk_rows` rows (see module);
    `refine`: whether ``auto`` may hold the records in memory for its refinement."""
    table = io.TableChunks(path, format=format)
    m, notes = _model(table, model, columns, time, trajectory)
    mapping = io.resolve_columns(table.columns, m.coordinates, m.velocities, mapping=columns,
                                 source=table.name)
    time_col = api._optional_column(table.columns, time, io.default_time_column(table.columns),
                                    "--time", table.name)
    traj_col = api._optional_column(table.columns, trajectory,
                                    io.default_trajectory_column(table.columns),
                                    "--trajectory", table.name)
    reader = _Reader(table, m, mapping, time_col, traj_col, chunk_rows, progress)
    names = list(m.parameters)
    fixed = api._check_fixed(fix, tuple(names))
    free = [k for k, name in enumerate(names) if name not in fixed]
    if not free:
        raise UsageError("every parameter is fixed; nothing is left to fit")
    free_names = [names[k] for k in free]
    fixed_values = np.array([fixed.get(name, 0.0) for name in names])

    scales = _scales(reader, m) if method != "energy" and time_col is not None else None
    kind, kind_reason, window = api._choose_method(method, m, scales, weak_window)

    def energy_rows(records: Records, first_row: int) -> Block:
        rows = design.energy_block(m, records)
        api._check_finite(rows, lambda r: (table.name, first_row + r + 1), names)
        return api._hold_fixed(rows, free, fixed_values)

    if kind == "energy":
        fitted = _energy(reader, energy_rows, free_names, cov)
    else:
        fitted = _windowed(reader, energy_rows, m, kind, window, method, weak_window, free,
                           fixed_values, free_names, cov)
        if isinstance(fitted, str):   # too few windows: auto falls back to the energy rows
            kind, kind_reason, window = "energy", fitted, None
            fitted = _energy(reader, energy_rows, free_names, cov)
    refinement_info = None
    if method == "auto" and kind == "joint":
        n_samples = int(fitted.sizes.sum())
        reason = api._refinement_obstacle(cov, False, ()) or _refinement_memory(
            refine, n_samples, m)
        if reason is None:
            records = _whole(reader, n_samples)
            refinement, refinement_info = api._refine(
                m, records, design.Damping((), m.coordinates), free, fixed_values,
                fitted.theta, scales, window, None, "measured", progress)
            del records
            if refinement is not None:
                fitted = _refined(reader, energy_rows, fitted, refinement)
        else:
            refinement_info = {"applied": False, "reason": reason}
        kind_reason += api._refinement_note(refinement_info)
    if fitted.stats is None:
        fitted = _summarised(reader, energy_rows, fitted)
    labels = reader.label_tuple()
    method_info = {
        "kind": kind, "kind_reason": kind_reason, "weak_window": window, "damping": [],
        "weighting": "none", "noise": None, "weighting_rounds": 0, "bias_correction": False,
        "covariance": cov, "covariance_description": fitted.description, "level": level,
        "fixed": dict(fixed), "block_variance": fitted.block_variance,
        "refinement": refinement_info,
    }
    sizes = [int(size) for size in fitted.sizes]
    data_info = {"sources": [table.name], "n_samples": sum(sizes),
                 "n_trajectories": len(labels), "columns": dict(mapping),
                 "velocity_source": "measured"}
    return api._result(m, names, fixed, fitted.theta, fitted.covariance, fitted.df,
                       truth=api._truth(table.metadata, m),
                       levels=api._levels(labels, fitted.h, fitted.h_stderr, sizes),
                       stats=fitted.stats, cond=fitted.cond,
                       block_conditions=fitted.block_conditions, notes=notes,
                       data_info=data_info, method_info=method_info, dissipation=None,
                       samples=None)


@dataclasses.dataclass(frozen=True)
class _Fit:
    """A fit of the chunks (linear, or refined by the trajectory fit) and what the report
    needs of it.

    `stats` is None until a pass over the energy residuals has summarised them (weak and
    joint fits, after the refinement, if any); `block_stats` is then their block summary
    and `energy_means` the means of each trajectory's energy rows [A, b].
    """

    theta: np.ndarray
    covariance: np.ndarray
    description: str
    df: int
    h: np.ndarray
    h_stderr: np.ndarray
    stats: dict[str, Any] | None
    cond: Any
    block_conditions: Any
    block_variance: Any
    sizes: np.ndarray
    block_stats: dict[str, Any] | None = None
    energy_means: np.ndarray | None = None


def _refinement_memory(refine: bool, n_samples: int, m: Model) -> str | None:
    """Why a chunked auto fit does not hold its records in memory to refine, or None."""
    if not refine:
        return api.CHUNKED_NOT_REFINED
    size = 8 * n_samples * (len(m.variables) + 2)
    if size > api.REFINEMENT_BYTES:
        return (f"it holds the records in memory, {size / 2**30:.1f} GiB here, over the "
                f"limit of {api.REFINEMENT_BYTES / 2**30:g} GiB")
    return None


def _whole(reader: _Reader, n_samples: int) -> Records:
    """All the records of the file, for the trajectory refinement."""
    X = np.empty((n_samples, len(reader.model.variables)))
    t = np.empty(n_samples)
    group = np.empty(n_samples, dtype=np.int64)
    for records, row in reader.rows("records for the trajectory fit"):
        rows = slice(row, row + len(records.group))
        X[rows], t[rows], group[rows] = records.X, records.t, records.group
    return Records(X, t, group, reader.label_tuple())


def _refined(reader: _Reader, energy_rows: Any, fitted: _Fit, refinement: Any) -> _Fit:
    """The fit at the refined parameters: each level the mean energy there, and the
    residual summary of a pass at them."""
    assert fitted.energy_means is not None
    means_A, means_b = fitted.energy_means[:, :-1], fitted.energy_means[:, -1]
    h = means_A @ refinement.theta - means_b
    residuals = _residual_sums(reader, energy_rows, refinement.theta, h)
    return dataclasses.replace(
        fitted, theta=refinement.theta, covariance=refinement.covariance,
        description=refinement.description, df=refinement.dof, h=h,
        h_stderr=api._refined_level_errors(means_A, refinement.covariance, residuals),
        stats={**residuals.stats(reader.label_tuple()), "blocks": fitted.block_stats})


def _summarised(reader: _Reader, energy_rows: Any, fitted: _Fit) -> _Fit:
    """The fit with the residual summary of its energy rows, from a pass."""
    residuals = _residual_sums(reader, energy_rows, fitted.theta, fitted.h)
    return dataclasses.replace(
        fitted, stats={**residuals.stats(reader.label_tuple()), "blocks": fitted.block_stats})


def _residual_sums(reader: _Reader, energy_rows: Any, theta: Any,
                   h: Any) -> api._ResidualSums:
    residuals = api._ResidualSums(h)
    for records, row in reader.rows("residual summary"):
        block = energy_rows(records, row)
        residuals.add(block, block.A @ theta - block.b - h[block.group])
    return residuals


def _model(table: io.TableChunks, model: Any, columns: Mapping[str, str] | None,
           time: str | None, trajectory: str | None) -> tuple[Model, tuple[str, ...]]:
    """The model as `hamid.api.fit` settles it, from the file's names and metadata."""
    metadata = table.metadata
    if isinstance(model, Model):
        return model, ()
    if model is not None:
        return api.load_model(model), ()
    if metadata and isinstance(metadata.get("model"), Mapping):
        return api._model_from_metadata(metadata["model"], table.name), ()
    m = api._assumed_model(table.columns, table.name, columns, time, trajectory)
    return m, (f"no model given: assumed {m.name} over the coordinates "
               f"{', '.join(m.coordinates)} (pick one with --model)",)


def _scales(reader: _Reader, m: Model) -> list[tuple[float | None, float]]:
    """Each trajectory's period and time step: its coordinates are held until it ends
    (memory grows with the longest trajectory, not with the file)."""
    scales: list[tuple[float | None, float]] = []
    held: list[Records] = []
    N = len(m.coordinates)

    def finish() -> None:
        if held:
            t = np.concatenate([r.t for r in held])
            X = np.vstack([r.X[:, :N] for r in held])
            scales.extend(design.trajectory_scales(
                Records(X, t, np.zeros(len(t), np.int64), (0,)), N))
            held.clear()

    for records, _ in reader.rows("periods of the trajectories"):
        for j, start, stop in design.runs(records.group):
            if held and held[-1].group[0] != j:
                finish()
            held.append(_records_slice(records, start, stop))
    finish()
    return scales


def _energy(reader: _Reader, energy_rows: Any, names: list[str], cov: str) -> _Fit:
    """The energy method in three passes: factor, residuals and bandwidth, meat."""
    p = len(names)
    factor = solve.Factor(p, 0)
    for records, row in reader.rows("energy rows"):
        factor.add(energy_rows(records, row))
    J = len(reader.labels)
    factor.grow(J)
    solution = solve.solve_factor(factor.centred(), np.sqrt(factor.raw_squares),
                                  factor.n_rows, names, n_levels=J)
    theta = solution.theta
    means_A, means_b = factor.level_means
    h = means_A @ theta - means_b
    df = factor.n_rows - p - J
    residuals = api._ResidualSums(h)

    def score_pass(sums: uncertainty.ScoreSums, summarise: bool) -> uncertainty.ScoreSums:
        for records, row in reader.rows("standard errors"):
            block = energy_rows(records, row)
            r = block.A @ theta - block.b - h[block.group]
            if summarise:
                residuals.add(block, r)
            for j, start, stop in design.runs(block.group):
                w = block.weight[start:stop]
                G = w[:, None] * ((block.A[start:stop] - means_A[j]) @ solution.inverse)
                z = np.column_stack([G, w / factor.total_weight[j]])
                sums.add(j, z, r[start:stop], w)
                if stop < len(block.group):   # the trajectory ended inside this chunk
                    sums.close(j)
        return sums

    sums = score_pass(uncertainty.ScoreSums(cov, p, J), summarise=True)
    automatic = sums.needs_bandwidth
    if automatic:
        sums = score_pass(uncertainty.ScoreSums(cov, p, J, sums.andrews_bandwidth()),
                          summarise=False)
    c = sums.covariance(df, automatic=automatic)
    stats = residuals.stats(reader.label_tuple())
    stats["blocks"] = {"energy": {"n_rows": int(residuals.n.sum()), "rms": stats["rms"],
                                  "max_abs": stats["max_abs"]}}
    cond = solve.factor_conditioning(factor, names, reader.label_tuple())
    h_stderr = np.sqrt(np.clip(api._level_variance(c, means_A), 0, None))
    return _Fit(theta, c.theta, c.description, c.df, h, h_stderr, stats, cond, None, None,
                residuals.n.astype(np.int64))


def _windowed(reader: _Reader, energy_rows: Any, m: Model, kind: str, window: float,
              method: str, weak_window: float | None, free: list[int], fixed_values: Any,
              names: list[str], cov: str) -> _Fit | str:
    """Weak and joint fits: window rows built chunk by chunk, then fitted in memory; the
    reason to fall back to the energy rows when there are too few windows for `auto`."""
    means, weak = [], []
    totals: dict[int, np.ndarray] = {}   # sums of A, b and the count of each trajectory
    held: _Held | None = None

    def emit(held: _Held, ended: bool) -> None:
        first, last, held.next = design.window_ranges(
            held.records.t, window, origin=held.origin, skip=held.next, ended=ended)
        if len(first):
            spans = design.windows_at(held.records, first, last,
                                      np.full(len(first), held.j), window)
            if kind == "joint":
                means.append(design.window_means(held.rows, spans))
            weak.append(api._hold_fixed(design.weak_block(m, held.records, spans), free,
                                        fixed_values))
        # Keep the samples from the first sample of the next window on.
        keep = int(np.searchsorted(held.records.t, held.origin + held.next * window
                                   * design.WINDOW_STEP))
        held.records = _records_slice(held.records, keep, None)
        held.rows = _block_slice(held.rows, keep, None)

    for records, row in reader.rows("window rows"):
        rows = energy_rows(records, row)
        for j, start, stop in design.runs(records.group):
            piece, piece_rows = (_records_slice(records, start, stop),
                                 _block_slice(rows, start, stop))
            total = totals.setdefault(j, np.zeros(rows.A.shape[1] + 2))
            total += np.r_[piece_rows.A.sum(axis=0), piece_rows.b.sum(), stop - start]
            if held is not None and held.j != j:
                emit(held, ended=True)
                held = None
            if held is None:
                held = _Held(j, float(piece.t[0]), 0, piece, piece_rows)
            else:
                held.records = Records(np.vstack([held.records.X, piece.X]),
                                       np.concatenate([held.records.t, piece.t]),
                                       np.concatenate([held.records.group, piece.group]), ())
                held.rows = _concatenate([held.rows, piece_rows])
            emit(held, ended=False)
    if held is not None:
        emit(held, ended=True)
    J = len(reader.labels)
    n_windows = sum(b.n_rows for b in weak) // len(m.coordinates)
    needed = len(free) + (J if kind == "joint" else 0) + 1
    if n_windows < needed:
        shortage = (f"the records hold {n_windows} weak-form windows of {window:.3g} s, "
                    f"fewer than the {needed} that {needed - 1} unknowns need")
        if method == "auto" and weak_window is None:
            return f"{shortage}; fitted the energy rows"
        raise FitError(f"cannot determine {', '.join(names)}: {shortage}; use "
                           "--method energy or a shorter --weak-window")
    blocks = ([_concatenate(means)] if kind == "joint" else []) + [_concatenate(weak)]
    units, unit_group = api._resampling_units(blocks, kind)
    blocks, block_variance = api._balance_blocks(blocks, names, J, units, unit_group)
    estimate = api._least_squares(blocks, names, J)
    theta = estimate.theta
    c = api._covariance(cov, estimate, units, unit_group)
    energy_means = np.array([totals[j][:-1] / totals[j][-1] for j in range(J)])
    h, h_stderr = api._fitted_levels(
        kind, estimate, api._level_variance(c, estimate.centred.level_means_A),
        lambda: (energy_means[:, :-1], energy_means[:, -1]))
    block_stats, cond, block_conditions = api._block_report(
        blocks, estimate.residual, names, reader.label_tuple())
    return _Fit(theta, c.theta, c.description, c.df, h, h_stderr, None, cond,
                block_conditions, block_variance,
                np.array([totals[j][-1] for j in range(J)], dtype=np.int64),
                block_stats=block_stats, energy_means=energy_means)


@dataclasses.dataclass
class _Held:
    """The open trajectory of a chunked weak/joint pass: its samples (and energy rows)
    from the first sample of its next window on, still to be cut into windows."""

    j: int
    origin: float    # the trajectory's first time, from which windows are counted
    next: int        # number of its next window
    records: Records
    rows: Block


def _records_slice(records: Records, start: int, stop: int | None) -> Records:
    return Records(records.X[start:stop], None if records.t is None else records.t[start:stop],
                   records.group[start:stop], ())


def _block_slice(block: Block, start: int, stop: int | None) -> Block:
    return dataclasses.replace(block, A=block.A[start:stop], b=block.b[start:stop],
                               group=block.group[start:stop], time=block.time[start:stop],
                               weight=block.weight[start:stop])


def _concatenate(blocks: list[Block]) -> Block:
    first = blocks[0]
    return dataclasses.replace(
        first, A=np.vstack([b.A for b in blocks]), b=np.concatenate([b.b for b in blocks]),
        group=np.concatenate([b.group for b in blocks]),
        time=np.concatenate([b.time for b in blocks]),
        weight=np.concatenate([b.weight for b in blocks]))
