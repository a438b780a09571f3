"""Fits of a file read in chunks of rows, so that memory does not grow with its length.

Every pass reads the file again, chunk by chunk (Parquet batches, blocks of CSV text):

- ``energy``: the first pass accumulates each trajectory's triangular factor of its
  energy rows (`solve.Factor`), which gives the parameters and levels; the second the
  residual summary and the sums of the standard errors (`uncertainty.ScoreSums`); ``hac``
  takes a third, with the bandwidth found in the second.
- ``weak`` and ``joint``: the first pass finds each trajectory's period and time step,
  the second builds the window rows, carrying each trajectory's unfinished windows into
  the next chunk, and writes them to a temporary file (one record per window: its energy
  row in joint and its weak rows). The fit then passes over that file: one pass gives
  each block's triangular factors, which give the estimates at any balance of the blocks;
  each covariance the balance tries takes two more (``hac``: bandwidth, then meat). A last
  pass over the data file gives the residual summary of the energy rows.
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

from hamid import (
    design,
    estimate,
    io,
    loading,
    naming,
    options,
    plan,
    refine,
    solve,
    summary,
    uncertainty,
)
from hamid.design import Block
from hamid.errors import DataError, FitError, UsageError
from hamid.model import Model, load_model
from hamid.records import Records, runs
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
            label = loading.trajectory_label(values[start])
            keys[start:stop] = self.labels.setdefault(label, len(self.labels))
        return keys

    def label_tuple(self) -> tuple[Any, ...]:
        return tuple(self.labels)


def fit_file(path: str, model: Any, *, columns: Mapping[str, str] | None, time: str | None,
             trajectory: str | None, format: str | None, fix: Mapping[str, float],
             method: str, weak_window: float | None, cov: str, level: float,
             chunk_rows: int, may_refine: bool,
             progress: Callable[[str], None] | None) -> FitResult:
    """`hamid.api.fit` of one file, read in chunks of `chunk_rows` rows (see module);
    `may_refine`: whether ``auto`` may hold the records in memory for its refinement."""
    table = io.TableChunks(path, format=format)
    m, notes = _model(table, model, columns, time, trajectory)
    mapping = naming.resolve_columns(table.columns, m.coordinates, m.velocities,
                                     mapping=columns, source=table.name)
    time_col = loading.optional_column(table.columns, time,
                                       naming.default_time_column(table.columns), "--time",
                                       table.name)
    traj_col = loading.optional_column(table.columns, trajectory,
                                    naming.default_trajectory_column(table.columns),
                                    "--trajectory", table.name)
    reader = _Reader(table, m, mapping, time_col, traj_col, chunk_rows, progress)
    names = list(m.parameters)
    fixed = options.check_fixed(fix, tuple(names))
    free = [k for k, name in enumerate(names) if name not in fixed]
    if not free:
        raise UsageError("every parameter is fixed; nothing is left to fit")
    free_names = [names[k] for k in free]
    fixed_values = np.array([fixed.get(name, 0.0) for name in names])

    scales = _scales(reader, m) if method != "energy" and time_col is not None else None
    kind, kind_reason, window = plan.choose_method(method, m, scales, weak_window)

    def energy_rows(records: Records, first_row: int) -> Block:
        rows = design.energy_block(m, records)
        design.check_finite(rows, lambda r: (table.name, first_row + r + 1), names)
        return design.hold_fixed(rows, free, fixed_values)

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
        reason = plan.refinement_obstacle(cov, False, ()) or _refinement_memory(
            may_refine, n_samples, m)
        if reason is None:
            records = _whole(reader, n_samples)
            refinement, refinement_info = refine.refine_joint(
                m, records, design.Damping((), m.coordinates), free, fixed_values,
                fitted.theta, scales, window, None, "measured", progress)
            del records
            if refinement is not None:
                fitted = _refined(reader, energy_rows, fitted, refinement)
        else:
            refinement_info = {"applied": False, "reason": reason}
        kind_reason += plan.refinement_note(refinement_info)
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
    return summary.fit_result(m, names, fixed, fitted.theta, fitted.covariance, fitted.df,
                       truth=loading.truth_of(table.metadata, m),
                       levels=summary.energy_levels(labels, fitted.h, fitted.h_stderr, sizes),
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


def _refinement_memory(may_refine: bool, n_samples: int, m: Model) -> str | None:
    """Why a chunked auto fit does not hold its records in memory to refine, or None."""
    if not may_refine:
        return plan.CHUNKED_NOT_REFINED
    size = 8 * n_samples * (len(m.variables) + 2)
    if size > options.REFINEMENT_BYTES:
        return (f"it holds the records in memory, {size / 2**30:.1f} GiB here, over the "
                f"limit of {options.REFINEMENT_BYTES / 2**30:g} GiB")
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
        h_stderr=refine.refined_level_errors(means_A, refinement.covariance, residuals),
        stats={**residuals.stats(reader.label_tuple()), "blocks": fitted.block_stats})


def _summarised(reader: _Reader, energy_rows: Any, fitted: _Fit) -> _Fit:
    """The fit with the residual summary of its energy rows, from a pass."""
    residuals = _residual_sums(reader, energy_rows, fitted.theta, fitted.h)
    return dataclasses.replace(
        fitted, stats={**residuals.stats(reader.label_tuple()), "blocks": fitted.block_stats})


def _residual_sums(reader: _Reader, energy_rows: Any, theta: Any,
                   h: Any) -> summary.ResidualSums:
    residuals = summary.ResidualSums(h)
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
        return load_model(model), ()
    if metadata and isinstance(metadata.get("model"), Mapping):
        return loading.model_from_metadata(metadata["model"], table.name), ()
    m = loading.assumed_model(table.columns, table.name, columns, time, trajectory)
    return m, (f"no model given: assumed {m.name} over the coordinates "
               f"{', '.join(m.coordinates)} (pick one with --model)",)


def _scales(reader: _Reader, m: Model) -> list[tuple[float | None, float]]:
    """Each trajectory's period and time step, from the first samples of each that
    `design.trajectory_scales` looks at, which are held until the trajectory ends."""
    scales: list[tuple[float | None, float]] = []
    held: list[Records] = []
    kept = 0   # samples of the current trajectory held
    N = len(m.coordinates)

    def finish() -> None:
        if held:
            t = np.concatenate([r.t for r in held])
            X = np.vstack([r.X[:, :N] for r in held])
            scales.extend(design.trajectory_scales(
                Records(X, t, np.zeros(len(t), np.int64), (0,)), N))
            held.clear()

    for records, _ in reader.rows("periods of the trajectories"):
        for j, start, stop in runs(records.group):
            if held and held[-1].group[0] != j:
                finish()
                kept = 0
            stop = min(stop, start + design.SCALE_SAMPLES - kept)
            if stop > start:
                held.append(_records_slice(records, start, stop))
                kept += stop - start
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
    residuals = summary.ResidualSums(h)

    def score_pass(sums: uncertainty.ScoreSums) -> None:
        for records, row in reader.rows("standard errors"):
            block = energy_rows(records, row)
            r = block.A @ theta - block.b - h[block.group]
            if sums.bandwidth is None:   # the first pass (hac: the one finding the bandwidth)
                residuals.add(block, r)
            for j, start, stop in runs(block.group):
                w = block.weight[start:stop]
                G = w[:, None] * ((block.A[start:stop] - means_A[j]) @ solution.inverse)
                z = np.column_stack([G, w / factor.total_weight[j]])
                sums.add(j, z, r[start:stop], w)
                if stop < len(block.group):   # the trajectory ended inside this chunk
                    sums.close(j)

    sums, automatic = uncertainty.fed_sums(cov, p, J, score_pass)
    c = sums.covariance(df, automatic=automatic)
    stats = residuals.stats(reader.label_tuple())
    stats["blocks"] = {"energy": {"n_rows": int(residuals.n.sum()), "rms": stats["rms"],
                                  "max_abs": stats["max_abs"]}}
    cond = solve.factor_conditioning(factor, names, reader.label_tuple())
    h_stderr = np.sqrt(np.clip(estimate.level_variance(c, means_A), 0, None))
    return _Fit(theta, c.theta, c.description, c.df, h, h_stderr, stats, cond, None, None,
                residuals.n.astype(np.int64))


def _windowed(reader: _Reader, energy_rows: Any, m: Model, kind: str, window: float,
              method: str, weak_window: float | None, free: list[int], fixed_values: Any,
              names: list[str], cov: str) -> _Fit | str:
    """Weak and joint fits: window rows built chunk by chunk into a temporary file, then
    fitted in passes over it (`_fit_windows`); the reason to fall back to the energy rows
    when there are too few windows for `auto`."""
    N = len(m.coordinates)
    layout = ([("energy", 1, True)] if kind == "joint" else []) + [("weak", N, False)]
    store = _WindowRows(layout, len(free), reader.table.name)
    totals: dict[int, np.ndarray] = {}   # sums of A, b and the count of each trajectory
    held: _Held | None = None

    def emit(held: _Held, ended: bool) -> None:
        first, last, held.next = design.window_ranges(
            held.records.t, window, origin=held.origin, skip=held.next, ended=ended)
        if len(first):
            spans = design.windows_at(held.records, first, last,
                                      np.full(len(first), held.j), window)
            weak = design.hold_fixed(design.weak_block(m, held.records, spans), free,
                                   fixed_values)
            store.append([design.window_means(held.rows, spans), weak] if kind == "joint"
                         else [weak])
        # Keep the samples from the first sample of the next window on.
        keep = int(np.searchsorted(held.records.t, held.origin + held.next * window
                                   * design.WINDOW_STEP))
        held.records = _records_slice(held.records, keep, None)
        held.rows = _block_slice(held.rows, keep, None)

    with store:
        for records, row in reader.rows("window rows"):
            rows = energy_rows(records, row)
            for j, start, stop in runs(records.group):
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
                                           np.concatenate([held.records.group, piece.group]),
                                           ())
                    held.rows = _concatenate([held.rows, piece_rows])
                emit(held, ended=False)
        if held is not None:
            emit(held, ended=True)
        J = len(reader.labels)
        needed = len(free) + (J if kind == "joint" else 0) + 1
        if store.n_windows < needed:
            shortage = (f"the records hold {store.n_windows} weak-form windows of "
                        f"{window:.3g} s, fewer than the {needed} that {needed - 1} unknowns "
                        "need")
            if method == "auto" and weak_window is None:
                return f"{shortage}; fitted the energy rows"
            raise FitError(f"cannot determine {', '.join(names)}: {shortage}; use "
                           "--method energy or a shorter --weak-window")
        sizes = np.array([totals[j][-1] for j in range(J)], dtype=np.int64)
        energy_means = np.array([totals[j][:-1] / totals[j][-1] for j in range(J)])
        return _fit_windows(store, kind, names, reader.label_tuple(), cov, sizes,
                            energy_means)


class _WindowRows:
    """The rows of a weak or joint fit in a temporary file, a record per window: the rows
    of each block it has in the window (`layout`: kind, rows per window, has a level),
    each row A, b and weight, then the window's trajectory and time. The fit reads them
    back a chunk of windows at a time, so that memory does not grow with the file."""

    CHUNK_WINDOWS = 1 << 14

    def __init__(self, layout: list[tuple[str, int, bool]], p: int, source: str) -> None:
        self.layout, self.p, self.source = layout, p, source
        self.width = sum(rows for _, rows, _ in layout) * (p + 2) + 2
        self.n_windows = 0
        self.file: Any = None

    @property
    def has_levels(self) -> bool:
        """Whether some block's rows carry their trajectory's energy level (joint)."""
        return any(level for _, _, level in self.layout)

    def __enter__(self) -> _WindowRows:
        import tempfile

        try:
            self.file = tempfile.TemporaryFile()
        except OSError as exc:
            raise self._unwritable(exc) from exc
        return self

    def _unwritable(self, exc: OSError) -> DataError:
        import tempfile

        return DataError(f"{self.source}: cannot keep its window rows in a temporary file in "
                         f"{tempfile.gettempdir()!r}: {io.os_reason(exc)} (the environment "
                         "variable TMPDIR names another folder)")

    def __exit__(self, *_: object) -> None:
        self.file.close()

    def append(self, blocks: list[Block]) -> None:
        """The rows of the same windows, one block per entry of the layout."""
        n = blocks[0].n_rows // self.layout[0][1]
        record = np.empty((n, self.width))
        column = 0
        for block, (_, rows, _) in zip(blocks, self.layout, strict=True):
            width = rows * (self.p + 2)
            record[:, column:column + width] = np.column_stack(
                [block.A, block.b, block.weight]).reshape(n, width)
            column += width
        first = self.layout[0][1]
        record[:, -2], record[:, -1] = blocks[0].group[::first], blocks[0].time[::first]
        try:
            self.file.write(record.data)
        except OSError as exc:
            raise self._unwritable(exc) from exc
        self.n_windows += n

    def chunks(self) -> Iterator[tuple[list[Block], np.ndarray]]:
        """Each chunk's blocks, as the layout lists them, and the trajectory of each window."""
        self.file.seek(0)
        left, p = self.n_windows, self.p
        while left:
            n = min(left, self.CHUNK_WINDOWS)
            record = np.empty((n, self.width))
            self.file.readinto(record.data)
            left -= n
            group, time = record[:, -2].astype(np.int64), record[:, -1]
            blocks, column = [], 0
            for kind, rows, has_level in self.layout:
                values = record[:, column:column + rows * (p + 2)].reshape(n * rows, p + 2)
                column += rows * (p + 2)
                blocks.append(Block(kind, values[:, :p], values[:, p], np.repeat(group, rows),
                                    np.repeat(time, rows), values[:, p + 1], has_level))
            yield blocks, group


def _fit_windows(store: _WindowRows, kind: str, names: list[str],
                 labels: tuple[Any, ...], cov: str, sizes: np.ndarray,
                 energy_means: np.ndarray) -> _Fit:
    """The fit of the stored window rows as `hamid.api.fit` makes it of the same rows in
    memory: the blocks' triangular factors from one pass give the estimates for any
    balance of the blocks, and each covariance takes one pass (two for ``hac``)."""
    p, J = len(names), len(labels)
    factors = [solve.Factor(p, J) for _ in store.layout]
    squares = np.zeros(len(store.layout))   # sum w b^2 of each block
    for blocks, _ in store.chunks():
        for k, (factor, block) in enumerate(zip(factors, blocks, strict=True)):
            factor.add(block)
            squares[k] += block.weight @ block.b**2

    def solved(scales: list[float]) -> tuple[solve.Factor, solve.Solution]:
        joined = solve.Factor.joined([f.scaled(c) for f, c in zip(factors, scales,
                                                                  strict=True)])
        return joined, solve.solve_factor(joined.centred(), np.sqrt(joined.raw_squares),
                                          joined.n_rows, names,
                                          n_levels=J if store.has_levels else 0)

    fits: dict[float, _WindowFit] = {}   # the hac fit at each ratio the balance tried
    if len(factors) == 1:
        ratio, scales, block_variance = None, [1.0], None
    else:
        variance = {}   # each block's mean w r^2 in a fit of its own (estimate.balance_blocks)
        for (block_kind, _, level), factor, square in zip(store.layout, factors, squares,
                                                           strict=True):
            R = factor.centred()
            try:
                solve.solve_factor(R, np.sqrt(factor.raw_squares), factor.n_rows, names,
                                   n_levels=J if level else 0)
                residual = R[p, p] ** 2 if R.shape[0] > p else 0.0
            except FitError:
                residual = square
            variance[block_kind] = max(float(residual) / factor.n_rows, estimate.TINY)
        kinds = [block_kind for block_kind, _, _ in store.layout]

        def ratio_scales(ratio: float) -> list[float]:
            return [ratio / variance[kinds[0]], *(1 / variance[k] for k in kinds[1:])]

        def spread(ratio: float) -> float:
            fits[ratio] = _window_fit(store, *solved(ratio_scales(ratio)), ratio_scales(ratio),
                                      "hac", names, J)
            return estimate.log_spread(fits[ratio].covariance.theta)

        ratio = estimate.balanced_ratio(spread)
        scales, block_variance = ratio_scales(ratio), estimate.balanced_variance(variance,
                                                                             kinds[0], ratio)
    joined, solution = solved(scales)
    fit = fits.get(ratio) if cov == "hac" else None
    if fit is None:
        fit = _window_fit(store, joined, solution, scales, cov, names, J)
    c = fit.covariance
    means_A = joined.level_means[0]
    h, h_stderr = estimate.fitted_levels(kind, solution.theta, fit.h,
                                         estimate.level_variance(c, means_A),
                                         lambda: (energy_means[:, :-1], energy_means[:, -1]))
    block_stats = {block_kind: {"n_rows": int(n), "rms": float(np.sqrt(square / n)),
                                "max_abs": float(largest)}
                   for (block_kind, _, _), (n, square, largest) in zip(
                       store.layout, fit.residuals, strict=True)}
    cond = solve.factor_conditioning(joined, names, labels)
    each = ({block_kind: solve.factor_conditioning(factor, names, labels).condition_number
             for (block_kind, _, _), factor in zip(store.layout, factors, strict=True)}
            if len(factors) > 1 else None)
    return _Fit(solution.theta, c.theta, c.description, c.df, h, h_stderr, None, cond, each,
                block_variance, sizes, block_stats=block_stats, energy_means=energy_means)


@dataclasses.dataclass(frozen=True)
class _WindowFit:
    """A covariance of the stored window rows' fit, its levels, and the number of rows,
    sum of squared residuals and largest residual of each block."""

    covariance: uncertainty.Covariance
    h: np.ndarray
    residuals: list[tuple[int, float, float]]


def _window_fit(store: _WindowRows, joined: solve.Factor, solution: solve.Solution,
                scales: list[float], cov: str, names: list[str], J: int) -> _WindowFit:
    """The covariance of kind `cov` of the fit `solution` of the stored rows weighted by
    `scales` (`hamid.estimate.covariance`: ``hac`` on the series of each window's summed
    scores)."""
    p = len(names)
    theta, inverse = solution.theta, solution.inverse
    means_A, means_b = joined.level_means
    h = means_A @ theta - means_b
    fitted = p + (J if store.has_levels else 0)
    by_window = cov == "hac"

    residuals: list[tuple[int, float, float]] = []   # rows, squares, largest of each block

    def scored(sums: uncertainty.ScoreSums) -> None:
        residuals[:] = [(0, 0.0, 0.0)] * len(store.layout)
        for blocks, group in store.chunks():
            window_scores = np.zeros((len(group), p + 1))
            for k, (block, scale) in enumerate(zip(blocks, scales, strict=True)):
                w = scale * block.weight
                r = block.A @ theta - block.b
                if block.has_level:
                    r -= h[block.group]
                    G = w[:, None] * ((block.A - means_A[block.group]) @ inverse)
                    lam = w / joined.total_weight[block.group]
                else:
                    G, lam = w[:, None] * (block.A @ inverse), np.zeros(len(w))
                z = np.column_stack([G, lam])
                n, square, largest = residuals[k]
                residuals[k] = (n + len(r), square + float(r @ r),
                                max(largest, float(np.max(np.abs(r)))))
                if by_window:
                    window_scores += (z * r[:, None]).reshape(len(group), -1, p + 1).sum(axis=1)
                else:
                    for j, start, stop in runs(block.group):
                        sums.add(j, z[start:stop], r[start:stop], w[start:stop])
            if by_window:
                for j, start, stop in runs(group):
                    sums.add(j, window_scores[start:stop], np.ones(stop - start),
                             np.ones(stop - start))
                    if stop < len(group):   # the trajectory ended inside this chunk
                        sums.close(j)

    sums, automatic = uncertainty.fed_sums(cov, p, J, scored)
    n_rows = sum(n for n, _, _ in residuals)
    df = store.n_windows - fitted if by_window else n_rows - fitted
    c = sums.covariance(df, automatic=automatic)
    if by_window:
        c = dataclasses.replace(c, description=c.description + uncertainty.UNITS_NOTE.format(
            n=store.n_windows))
    return _WindowFit(c, h, residuals)


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
