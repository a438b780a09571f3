"""Reading the data into Records, whole or in chunks: the sources, the model they settle,
the columns, and the checks that every trajectory's rows are contiguous and in time order.

Both ways of reading share every rule here: a file read in chunks is read as it would be
whole, with the same messages naming the same rows.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from hamid.data import column_roles, input_size, measurement, readers
from hamid.data.records import GAP_STEPS, Channels, Records, check_inputs, locate, runs, split_gaps
from hamid.errors import DataError, UsageError
from hamid.linear import design
from hamid.model.dissipation import shorthand_names
from hamid.model.models import (
    BUILTINS,
    Model,
    builtin_model,
    load_model,
    model_from_info,
    poly_model_over,
)
from hamid.options import FitOptions

__all__ = ["Chunked", "Loaded", "Source", "Survey", "load",
           "open_chunks", "trajectory_label"]

# Times beyond this overflow in the sums of squares the residual summary takes; time
# steps below the smallest underflow in the weak form's integrals (1e-150 gave a division
# by zero, 1e-300 an SVD that did not converge).
_LARGEST_TIME, _SMALLEST_STEP = 1e150, 1e-100
_IN_MEMORY = ("<DataFrame>", "<dict>", "<array>")   # `input_size.in_memory_name`


class Source(Protocol):
    """Data to fit, read whole (`Loaded`) or a pass at a time (`Chunked`): the same members,
    so that the fit (`hamid.api`) takes the same steps and makes the same checks of both."""

    @property
    def model(self) -> Model: ...
    @property
    def labels(self) -> tuple[Any, ...]:
        """Each trajectory's label, in order of their numbers."""
    @property
    def truth(self) -> dict[str, float]:
        """The true parameters a simulated file records for the model, else none."""
    @property
    def notes(self) -> tuple[str, ...]:
        """What the report says of how the data were read, and of the checks of them."""
    @property
    def data_info(self) -> dict[str, Any]:
        """What the report says about the data (docs/output.md, `data`)."""
    def scales(self) -> list[tuple[float | None, float]] | None:
        """Each trajectory's period and time step, None without a time column."""
    def locate(self, row: int) -> tuple[str, int]:
        """The source and 1-based data row of a row read (0-based, all sources)."""
    def durations(self) -> list[float] | None:
        """Each trajectory's length in seconds, None without a time column."""
    def rows(self, purpose: str) -> Iterator[tuple[Records, int]]:
        """The records a chunk at a time, with the row of each chunk's first, in a pass
        for `purpose`; records read whole are one chunk."""
    def whole(self) -> Records:
        """All the records in memory (for the trajectory refinement)."""
    @property
    def channels(self) -> Channels:
        """What was recorded of each coordinate (the rest reconstructed, not fitted)."""
    def whole_bytes(self) -> int | None:
        """The memory `whole` takes anew, None when the records are in memory already."""


@dataclass(frozen=True)
class Loaded:
    """Records read whole, the model, and what the report says about the data (a
    `Source`)."""

    model: Model
    records: Records
    truth: dict[str, float]
    data_info: dict[str, Any]
    notes: tuple[str, ...]
    velocity_gain: float | None  # noise gain of derived velocities, None when measured
    channels: Channels   # what was recorded of each coordinate, and what reconstructed
    row_sources: tuple[tuple[str, int], ...]  # (source, first row) of each input table
    # each trajectory's period and time step (`design.trajectory_scales`), None without a
    # time column: found once, for the velocity check, the derivation and the plan
    trajectory_scales: list[tuple[float | None, float]] | None
    file_rows: Any = None   # the row read of each row of the records, when rows were dropped

    def locate(self, row: int) -> tuple[str, int]:
        """The source and 1-based data row of a row of the records."""
        if self.file_rows is not None:
            row = int(self.file_rows[row])
        return locate(self.row_sources, row)

    def scales(self) -> list[tuple[float | None, float]] | None:
        """Each trajectory's period and time step, None without a time column."""
        return self.trajectory_scales

    def durations(self) -> list[float] | None:
        """Each trajectory's length in seconds, None without a time column."""
        t = self.records.t
        return None if t is None else [float(t[stop - 1] - t[start])
                                       for start, stop in self.records.bounds()]

    @property
    def labels(self) -> tuple[Any, ...]:
        """Each trajectory's label."""
        return self.records.labels

    def rows(self, purpose: str) -> Iterator[tuple[Records, int]]:
        """The records, as one chunk."""
        yield self.records, 0

    def whole(self) -> Records:
        """The records."""
        return self.records

    def whole_bytes(self) -> None:
        """None: the records are in memory."""
        return None



def load(data: Any, model: str | os.PathLike[str] | Model | None,
         options: FitOptions) -> Loaded:
    """Read the sources whole, settle the model and arrange the rows by trajectory."""
    table = input_size.in_memory_table(data)
    if table is not None:
        tables = [table]
    else:
        paths = [data] if isinstance(data, str | os.PathLike) else list(data)
        if not paths:
            raise UsageError("no data given")
        tables = [(input_size.name_of(p), *readers.read_columns(p, format=options.format,
                                                        text=options.text,
                                                        name=input_size.name_of(p)))
                  for p in paths]
    sources = [name for name, _, _ in tables]
    metadata = tables[0][2]
    if model is None:
        _check_same_model(tables)
    m, notes = _settle_model(model, metadata, [str(c) for c in tables[0][1]], sources[0],
                             options)
    parts, labels, mapping, units = [], [], {}, {}
    channels: Channels | None = None
    while tables:   # each table's columns let go once its records are read
        source, frame, table_metadata = tables.pop(0)
        names = [str(c) for c in frame]
        mapping = column_roles.channel_columns(names, m, options.columns, source=source,
                                               set_aside=options.velocity == "savgol")
        channels = Channels.of(m, mapping).same_as(channels, source, sources[0])
        if not parts and options.velocity != "savgol":   # said of the first file
            notes.extend(channels.notes(source, refined=options.method == "auto"
                                        and options.linear_asked is None))
        time, trajectory = _special_columns(names, mapping, options, source, notes)
        if not parts:   # said of the first file
            notes.extend(column_roles.left_out_pairs(
                names, {*mapping.values(), time, trajectory} - {None}, m.name, source))
        units = column_roles.read_units(names, mapping, time, options, table_metadata,
                                        source)
        notes.extend(units["notes"])
        reader = Reader(m, mapping, time, trajectory, source,
                        typed=source in _IN_MEMORY or readers.is_parquet(source),
                        scales=units["scale"], missing_ok=options.gaps == "split")
        piece = next(reader.read([(frame, 0)]))
        del frame
        notes.extend(reader.notes)
        if labels:
            piece = dataclasses.replace(piece, group=piece.group + len(labels))
        parts.append(piece)
        if len(sources) == 1:
            labels.extend(reader.labels)
        elif reader.trajectory is None:
            labels.append(source)
        else:
            labels.extend(f"{source}:{label}" for label in reader.labels)
    has_time = all(part.t is not None for part in parts)
    records = parts[0] if len(parts) == 1 else Records(
        np.vstack([part.X for part in parts]),
        np.concatenate([part.t for part in parts]) if has_time else None,
        np.concatenate([part.group for part in parts]), (),
        np.vstack([part.U for part in parts]) if m.inputs else None)
    records = dataclasses.replace(records, labels=tuple(labels))
    firsts = np.cumsum([0] + [len(part.group) for part in parts[:-1]])
    del parts
    arrow = sys.modules.get("pyarrow")   # the tables read are gone: their memory goes back
    if arrow is not None:
        arrow.default_memory_pool().release_unused()
    row_sources = tuple((name, int(f)) for name, f in zip(sources, firsts, strict=True))
    if records.U is not None:
        check_inputs(records.U, m.inputs, mapping, sources)
    channels.check_same_times(records.X, sources[0])
    records, file_rows = split_gaps(records, options.gaps, row_sources, notes)
    labels = list(records.labels)
    records = measurement.reconstruct(records, channels)
    # from the coordinates, which a derivation of the velocities leaves as they are
    scales = (None if records.t is None
              else design.trajectory_scales(records, len(m.coordinates)))
    period = None if scales is None else design.median_period(scales)
    if not channels.reconstructed and records.t is not None:
        findings = measurement.velocity_check(records, m.coordinates, m.velocities, mapping,
                                              period)
        aside = options.velocity == "auto" and any(f.disagrees for f in findings)
        notes.extend(f.text + ((measurement.SET_ASIDE if aside else measurement.DERIVE_ADVICE)
                               if f.disagrees else "") for f in findings)
        if aside:
            channels = channels.set_aside({f.velocity for f in findings if f.disagrees},
                                          m.velocities)
    derivation = None
    if channels.derived.any():
        records, derivation = measurement.derive_velocities(records, channels.derived,
                                                             options.window, options.order,
                                                             period)
        notes.append(f"velocities derived from the positions (Savitzky-Golay, window "
                     f"{derivation[0]} samples, order {options.order}); their noise is "
                     "correlated with the positions'")
    data_info = _data_info(sources, len(records.group), len(labels), mapping, options, units)
    if channels.derived.all():   # asked for, no velocity columns, or columns set aside
        data_info["velocity_source"] = "savgol"
    if derivation:
        data_info.update(velocity_window=derivation[0], velocity_order=options.order)
    if options.velocity != "savgol" and channels != Channels.complete(m.coordinates):
        data_info["channels"] = channels.report()
    if (options.damping or m.dissipation or m.forcing) and records.t is None:
        what = "damping" if options.damping or m.dissipation else "a [forcing]"
        raise UsageError(f"{what} needs a time column (its work is an integral over time); "
                         "name it with --time COL")
    data_info.update({"inputs": {name: mapping[name] for name in m.inputs}} if m.inputs else {})
    return Loaded(model=m, records=records, truth=_truth(metadata, m), data_info=data_info,
                  notes=tuple(notes), velocity_gain=derivation[1] if derivation else None,
                  channels=channels,
                  row_sources=row_sources, trajectory_scales=scales, file_rows=file_rows)


class Reader:
    """Rows of one table, whole or chunk by chunk, as Records: trajectories numbered in
    order of first appearance; every trajectory's rows contiguous and its times
    increasing, also across chunks. Errors name the table's 1-based data row."""

    def __init__(self, model: Model, mapping: Mapping[str, str], time: str | None,
                 trajectory: str | None, source: str, typed: bool,
                 scales: Mapping[str, float] | None = None, missing_ok: bool = False,
                 chunked: bool = False) -> None:
        self.model, self.mapping, self.source = model, mapping, source
        # X as read: the model's variables (zeros where not recorded), the accelerations after
        self.read_variables = (*model.variables,
                               *(a for a in model.acceleration_names if a in mapping))
        # Missing cells read as NaN (for `records.split_gaps`), else they are errors.
        self.missing_ok = missing_ok
        # Read in chunks: time gaps are refused (`_refuse_gaps`), with each trajectory's
        # median step.
        self.chunked, self._steps = chunked, {}
        # Column -> factor to SI units (seconds for time), applied as values are read.
        self.scales = dict(scales or {})
        self.time, self.trajectory = time, trajectory
        # Without a trajectory column the table is one trajectory, labelled 1.
        self._ids: dict[Any, int] = {} if trajectory else {1: 0}
        # A table that stores its columns' types (Parquet, a DataFrame) and keeps numbers
        # as text is read all the same, and the report says so.
        self.typed, self.text_columns = typed, set()

    @property
    def notes(self) -> tuple[str, ...]:
        """What the report says of how the table was read."""
        return tuple(f"{self.source}: column {column!r} stores its numbers as text; read "
                     "them as numbers" for column in sorted(self.text_columns))

    def _numbers(self, chunk: Mapping[str, Any], column: str, row: int) -> np.ndarray:
        values = readers.column_values(chunk[column])
        if self.typed and values.dtype.kind not in "iuf":
            self.text_columns.add(column)
        missing = None
        if self.missing_ok:
            missing = (np.isnan(values.astype(np.float64)) if values.dtype.kind in "iuf" else
                       np.fromiter((readers.is_missing(v) or (isinstance(v, str) and not v.strip())
                                    for v in values), bool, len(values)))
            if missing.any():
                values = values.copy()
                values[missing] = 0
        try:
            numbers = readers.numeric_values(values, column, self.source, first_row=row + 1)
        except DataError as exc:
            if self.chunked and str(exc).endswith("missing value"):
                raise DataError(f"{exc}; a file read in chunks is not cut at dropouts: read "
                                "it whole (Python: in_memory=True; the command line: "
                                "--residuals FILE)") from None
            raise
        if missing is not None and missing.any():
            numbers[missing] = np.nan
        factor = self.scales.get(column, 1.0)
        return numbers if factor == 1.0 else numbers * factor

    @property
    def columns(self) -> list[str]:
        """The table's columns that are read."""
        wanted = list(self.mapping.values())   # the model's names' columns
        return list(dict.fromkeys([*wanted, *(c for c in (self.time, self.trajectory) if c)]))

    @property
    def labels(self) -> tuple[Any, ...]:
        """The trajectory labels seen so far, in order of their numbers."""
        return tuple(self._ids)

    def read(self, chunks: Iterable[tuple[Mapping[str, Any], int]]) -> Iterator[Records]:
        """The records of each chunk (column name -> values, and its first row counted
        from 0), checked in order; one pass over the table."""
        previous, last_t, closed = None, None, set()
        for chunk, row in chunks:
            n = len(chunk[self.columns[0]])
            X = np.column_stack([self._numbers(chunk, self.mapping[v], row)
                                 if v in self.mapping else np.zeros(n)
                                 for v in self.read_variables])
            U = (np.column_stack([self._numbers(chunk, self.mapping[u], row)
                                  for u in self.model.inputs]) if self.model.inputs else None)
            t = self._numbers(chunk, self.time, row) if self.time else None
            if t is not None and np.any(np.abs(t) > _LARGEST_TIME):
                k = int(np.argmax(np.abs(t) > _LARGEST_TIME))
                raise DataError(f"{self.source}: column {self.time!r}, row {row + k + 1}: time "
                                f"{t[k]:g} is too large to compute with (at most "
                                f"{_LARGEST_TIME:g}); is it the time column?")
            group = (self._keys(readers.column_values(chunk[self.trajectory]), row)
                     if self.trajectory else np.zeros(n, np.int64))
            starts = np.flatnonzero(np.diff(group, prepend=-1 if previous is None
                                            else previous))
            for start in starts:
                if int(group[start]) in closed:
                    raise DataError(f"{self.source}: column {self.trajectory!r}, row "
                                    f"{row + start + 1}: a trajectory resumes after rows of "
                                    "another; sort the file by trajectory then time")
                if previous is not None:
                    closed.add(previous)
                previous = int(group[start])
            if t is not None:
                before = np.concatenate([[np.nan if last_t is None else last_t], t[:-1]])
                same = np.ones(n, dtype=bool)
                same[starts] = False
                # a missing time is cut at by `records.split_gaps`
                bad = np.flatnonzero(same & ~(t > before) & ~np.isnan(t) & ~np.isnan(before))
                if bad.size:
                    k = int(bad[0])
                    raise DataError(f"{self.source}: column {self.time!r}, row {row + k + 1}: "
                                    f"time does not increase ({before[k]:g} then {t[k]:g})")
                tiny = np.flatnonzero(same & (t - before < _SMALLEST_STEP))
                if tiny.size:
                    k = int(tiny[0])
                    raise DataError(f"{self.source}: column {self.time!r}, row {row + k + 1}: "
                                    f"time step {t[k] - before[k]:g} is too small to compute "
                                    f"with (at least {_SMALLEST_STEP:g}); is it the time "
                                    "column?")
                if self.chunked:
                    self._refuse_gaps(t - before, same, group, row)
                last_t = float(t[-1])
            yield Records(X, t, group, (), U)

    def _refuse_gaps(self, steps: np.ndarray, same: np.ndarray, group: np.ndarray,
                     row: int) -> None:
        """A file read in chunks is not cut at time gaps (`records.split_gaps` cuts records in
        memory): a step over `GAP_STEPS` times its trajectory's median step in the first
        chunk that holds three of its rows is an error, not a different fit."""
        reference = np.empty(len(group))
        for j, start, stop in runs(group):
            if j not in self._steps and stop - start >= 3:
                self._steps[j] = float(np.median(steps[start + 1:stop]))
            reference[start:stop] = self._steps.get(j, np.inf)
        gap = np.flatnonzero(same & (steps > GAP_STEPS * reference))
        if gap.size:
            k = int(gap[0])
            raise DataError(f"{self.source}: row {row + k + 1}: a time gap of {steps[k]:g} s "
                            f"(over {GAP_STEPS:g} times the median step); a file read in "
                            "chunks is not cut at gaps: read it whole (Python: "
                            "in_memory=True; the command line: --residuals FILE), or cut it "
                            "with a trajectory column")

    def _keys(self, values: np.ndarray, row: int) -> np.ndarray:
        """The trajectory number of each row of a chunk of the trajectory column."""
        if values.dtype.kind in "iu":
            missing = np.zeros(len(values), bool)
        elif values.dtype.kind == "f":
            missing = np.isnan(values)
        else:
            missing = np.fromiter((readers.is_missing(v) for v in values), bool, len(values))
        if missing.any():
            raise DataError(f"{self.source}: column {self.trajectory!r}, row "
                            f"{row + int(np.flatnonzero(missing)[0]) + 1}: missing "
                            "trajectory label")
        change = np.flatnonzero(values[1:] != values[:-1]) + 1
        keys = np.empty(len(values), dtype=np.int64)
        for start, stop in zip([0, *change], [*change, len(values)], strict=True):
            keys[start:stop] = self._ids.setdefault(trajectory_label(values[start]),
                                                    len(self._ids))
        return keys


class Survey:
    """What a pass over a file read in chunks learns of its trajectories, for the checks
    that a fit in memory makes of its records: each trajectory's samples and time span, its
    first `design.SCALE_SAMPLES` samples for its period and time step, and the velocity
    check's sums (`measurement.VelocitySums`)."""

    def __init__(self, n_coordinates: int, has_time: bool) -> None:
        self.N = n_coordinates
        self.sizes: list[int] = []
        self.spans: list[list[float]] = []   # each trajectory's first and last time
        self.scales: list[tuple[float | None, float]] | None = [] if has_time else None
        self.velocity = measurement.VelocitySums(n_coordinates) if has_time else None
        self._held: list[Records] = []   # the first samples of the open trajectory
        self._kept = 0

    def add(self, records: Records) -> None:
        """A chunk's records."""
        if self.velocity is not None:
            self.velocity.add(records, ended=False)
        for j, start, stop in runs(records.group):
            if j == len(self.sizes):   # a trajectory begins
                self._scale()
                self.sizes.append(0)
                self.spans.append([np.nan, np.nan] if records.t is None
                                  else [float(records.t[start]), np.nan])
            self.sizes[j] += stop - start
            if records.t is not None:
                self.spans[j][1] = float(records.t[stop - 1])
                stop = min(stop, start + design.SCALE_SAMPLES - self._kept)
                if stop > start:
                    self._held.append(records.slice(start, stop))
                    self._kept += stop - start

    def end(self) -> None:
        """The end of the pass."""
        self._scale()
        if self.velocity is not None:
            self.velocity.end()

    def _scale(self) -> None:
        """The period and step of the trajectory whose first samples are held."""
        if self._held and self.scales is not None:
            t = np.concatenate([r.t for r in self._held])
            X = np.vstack([r.X[:, :self.N] for r in self._held])
            self.scales.extend(design.trajectory_scales(
                Records(X, t, np.zeros(len(t), np.int64), (0,)), self.N))
        self._held, self._kept = [], 0

    def durations(self) -> list[float] | None:
        """Each trajectory's length in seconds, None without a time column."""
        return None if self.scales is None else [last - first for first, last in self.spans]


@dataclass(eq=False)
class Chunked:
    """One file read in chunks of rows, a pass at a time (`hamid.linear.chunked`; a
    `Source`). The first whole pass surveys the trajectories (`Survey`)."""

    model: Model
    read_notes: tuple[str, ...]
    truth: dict[str, float]
    table: readers.TableChunks
    reader: Reader
    chunk_rows: int
    progress: Callable[[str], None] | None
    units: dict[str, Any]
    options: FitOptions
    survey: Survey | None = None   # set by the first pass read to its end

    @property
    def labels(self) -> tuple[Any, ...]:
        return self.reader.labels

    def rows(self, purpose: str) -> Iterator[tuple[Records, int]]:
        """Each chunk's records and the file row (0-based) of its first row, in a pass for
        `purpose` (what `progress` is told)."""

        def chunks() -> Iterator[tuple[Mapping[str, Any], int]]:
            row = 0
            with contextlib.closing(self.table.chunks(self.reader.columns,
                                                      self.chunk_rows)) as table_chunks:
                for chunk in table_chunks:
                    if self.progress is not None:
                        self.progress(f"{self.table.name}: {purpose}, from row {row + 1:,}")
                    yield chunk, row
                    row += len(chunk[self.reader.columns[0]])

        row = 0
        survey = None if self.survey else Survey(len(self.model.coordinates),
                                                 self.reader.time is not None)
        # closed when an error stops the pass, not when the interpreter exits: the file's
        # reader and the thread reading ahead for it end here
        with contextlib.closing(chunks()) as pieces:
            for records in self.reader.read(pieces):
                if survey is not None:
                    survey.add(records)
                yield records, row
                row += len(records.group)
        if survey is not None:
            survey.end()
            self.survey = survey

    def locate(self, row: int) -> tuple[str, int]:
        """The file and its 1-based data row of a row read (0-based)."""
        return self.table.name, row + 1

    def surveyed(self) -> Survey:
        """The survey of the trajectories, made in a pass of its own if none was read to its
        end yet."""
        if self.survey is None:
            for _ in self.rows("periods of the trajectories"):
                pass
        assert self.survey is not None
        return self.survey

    def scales(self) -> list[tuple[float | None, float]] | None:
        """Each trajectory's period and time step, from the first samples of each that
        `design.trajectory_scales` looks at (`Survey`)."""
        return self.surveyed().scales

    def durations(self) -> list[float] | None:
        """Each trajectory's length in seconds, None without a time column."""
        return self.surveyed().durations()

    @property
    def notes(self) -> tuple[str, ...]:
        """What the report says of how the file was read, and the velocity check's
        warnings."""
        survey, m = self.surveyed(), self.model
        checked = [] if survey.velocity is None else survey.velocity.warnings(
            m.coordinates, m.velocities, self.reader.mapping,
            design.median_period(survey.scales) if survey.scales else None)
        return (*self.read_notes, *self.reader.notes, *checked)

    @property
    def data_info(self) -> dict[str, Any]:
        """What the report says about the data."""
        return _data_info([self.table.name], sum(self.surveyed().sizes), len(self.labels),
                          self.reader.mapping, self.options, self.units)

    @property
    def channels(self) -> Channels:
        """Every position and velocity: a file read in chunks needs them all."""
        return Channels.complete(self.model.coordinates)

    def whole(self) -> Records:
        """All the records of the file, for the trajectory refinement."""
        n_samples = sum(self.surveyed().sizes)
        X = np.empty((n_samples, len(self.model.variables)))
        t = np.empty(n_samples)
        group = np.empty(n_samples, dtype=np.int64)
        for records, row in self.rows("records for the trajectory fit"):
            rows = slice(row, row + len(records.group))
            X[rows], t[rows], group[rows] = records.X, records.t, records.group
        return Records(X, t, group, self.labels)

    def whole_bytes(self) -> int:
        """The bytes of the records in memory, with their times and trajectories."""
        return 8 * sum(self.surveyed().sizes) * (len(self.model.variables) + 2)


def open_chunks(path: str | os.PathLike[str], model: str | os.PathLike[str] | Model | None,
                options: FitOptions, chunk_rows: int,
                progress: Callable[[str], None] | None) -> Chunked | None:
    """A file to read in chunks of `chunk_rows` rows: its model and columns, settled as
    `load` settles them; None when its channels need it read whole (a coordinate without
    its position or velocity) and `options` did not ask for chunks, which is then an
    error."""
    table = readers.TableChunks(path, format=options.format, text=options.text,
                           name=input_size.name_of(path))
    m, notes = _settle_model(model, table.metadata, table.columns, table.name, options)
    if m.dissipation:
        raise UsageError(f"{table.name}: the model's dissipation function needs the data in "
                         "memory (its work is integrated along each whole trajectory); "
                         "give the model file with --model")
    mapping = _chunked_columns(table.columns, m, options, table.name, notes)
    if mapping is None:
        return None
    time, trajectory = _special_columns(table.columns, mapping, options, table.name, notes)
    units = column_roles.read_units(table.columns, mapping, time, options, table.metadata,
                                     table.name)
    notes.extend(units["notes"])
    reader = Reader(m, mapping, time, trajectory, table.name,
                    typed=table.format == "parquet", scales=units["scale"], chunked=True)
    return Chunked(model=m, read_notes=tuple(notes), truth=_truth(table.metadata, m),
                   table=table, reader=reader, chunk_rows=chunk_rows, progress=progress,
                   units=units, options=options)


def _chunked_columns(names: list[str], model: Model, options: FitOptions,
                     source: str, notes: list[str]) -> dict[str, str] | None:
    """Model name -> column for reading in chunks, which takes each coordinate's position
    and velocity; recorded accelerations are left out, said in `notes`. A record without
    them is read whole, where the missing ones are reconstructed over whole trajectories
    (None), or refused when `--chunk-rows` asked for chunks."""
    found = column_roles.channel_columns(names, model, options.columns, source=source,
                                         set_aside=False)
    channels = Channels.of(model, found)
    if not all(kinds >= {"position", "velocity"} for kinds in channels.recorded):
        if options.chunk_rows is None:
            return None
        raise UsageError(f"{source}: --chunk-rows reads each coordinate's position and "
                         f"velocity, and the file records {channels.text}; leave out "
                         "--chunk-rows to fit it in memory")
    if channels.accelerated:
        notes.append(f"{source}: the accelerations recorded are not read in chunks (leave "
                     "out --chunk-rows to fit them too)")
    return {name: column for name, column in found.items()
            if name not in model.acceleration_names}


def _data_info(sources: list[str], n_samples: int, n_trajectories: int,
               mapping: Mapping[str, str], options: FitOptions,
               units: Mapping[str, Any]) -> dict[str, Any]:
    """What the report says about the data (docs/output.md, `data`)."""
    return {"sources": sources, "n_samples": n_samples,
            "n_trajectories": n_trajectories, "columns": dict(mapping),
            "velocity_source": "savgol" if options.velocity == "savgol" else "measured",
            "time": units["time"],
            "time_unit": units["time_unit"],
            "scale": {c: f for c, f in units["scale"].items() if f != 1.0},
            **({"reading": options.reading} if options.reading else {})}


def in_memory_only(model: str | os.PathLike[str] | Model | None) -> str:
    """Why a model given to a fit needs the data in memory (its own dissipation function, a
    forcing: their integrals between the samples are not made in chunks), or ""."""
    if isinstance(model, str | os.PathLike) and os.fspath(model).endswith(".toml"):
        model = load_model(model)
    part = ("" if not isinstance(model, Model) else "dissipation function"
            if model.dissipation is not None else "forcing" if model.forcing else "")
    return f"the model's {part} needs the data in memory" if part else ""


def _settle_model(model: str | os.PathLike[str] | Model | None,
                  metadata: Mapping[str, Any] | None, names: list[str], source: str,
                  options: FitOptions) -> tuple[Model, list[str]]:
    """The model given, else the one the file's metadata records, else poly:N:3 over every
    column that has a velocity column (said in a note)."""
    if isinstance(model, Model):
        return model, []
    if model is not None:
        return load_model(model), []
    if metadata and isinstance(metadata.get("model"), Mapping):
        return _model_from_metadata(metadata["model"], source), []
    exclude = {c for c in (
        options.time or column_roles.default_time_column(names),
        options.trajectory or column_roles.default_trajectory_column(names)) if c}
    pairs = column_roles.find_coordinates(names, exclude=exclude)
    if not pairs:
        raise DataError(f"{source}: no model given and no coordinate with a velocity column "
                        f"found (columns: {', '.join(names)}); give --model "
                        f"{_model_beside(source)}, or name velocities vx, x_dot, xdot, dx "
                        "or v1 for x1 (positions without velocities are fitted given "
                        "--model)")
    if options.columns:
        raise UsageError("--columns needs --model (the assumed model takes the file's names)")
    # The model's names are the columns' without their units (`x [mm]` is `x`), which
    # `naming.resolve_columns` matches back to the columns and scales to SI.
    def name(column: str) -> str:
        return column_roles.split_unit(column, column_roles.COLUMN_UNITS)[0]

    m = poly_model_over([name(q) for q, _ in pairs], [name(v) for _, v in pairs])
    return m, [f"no model given: assumed {m.name} over the coordinates "
               f"{', '.join(m.coordinates)} (pick one with --model {_model_beside(source)})"]


def _check_same_model(tables: list[tuple[str, Any, Any]]) -> None:
    """Files whose metadata record different models are not fitted together by default."""
    def recorded(metadata: Any) -> Any:
        info = metadata.get("model") if isinstance(metadata, Mapping) else None
        return (info.get("name"), info.get("energy")) if isinstance(info, Mapping) else None

    first = recorded(tables[0][2])
    for name, _, metadata in tables[1:]:
        other = recorded(metadata)
        if other != first:
            said = [f"{source}: {'no model' if m is None else repr(m[0])}"
                    for source, m in ((tables[0][0], first), (name, other))]
            raise UsageError(f"the files record different models ({'; '.join(said)}); fit "
                             "them apart, or give the model of all of them with --model")


def _model_beside(source: str) -> str:
    """The model file to suggest for a data file: a .toml beside it whose name begins its
    name (pendulum.toml for pendulum_encoder.csv), else NAME|FILE.toml."""
    folder = os.path.dirname(source) or "."
    try:
        models = sorted(name for name in os.listdir(folder) if name.endswith(".toml"))
    except OSError:
        return "NAME|FILE.toml"
    stem = os.path.basename(source).split(".")[0]
    fitting = [name for name in models if stem.startswith(name[:-len(".toml")])]
    if fitting:
        return os.path.join(os.path.dirname(source), max(fitting, key=len))
    if len(models) == 1:
        return os.path.join(os.path.dirname(source), models[0])
    return "NAME|FILE.toml"


def _model_from_metadata(info: Mapping[str, Any], source: str) -> Model:
    """The model a simulated file records (built-in by name, else from its energy), with
    its dissipation function."""
    name = info.get("name")
    own = info.get("dissipation")
    if isinstance(name, str) and (name in BUILTINS or name.startswith("poly:")) and not own:
        candidate = builtin_model(name)
        if candidate.energy == info.get("energy"):
            return candidate
    try:
        return model_from_info(info, where=f"{source}: metadata model")
    except (KeyError, TypeError) as exc:
        raise DataError(f"{source}: the hamid metadata has no usable model ({exc}); "
                        "give one with --model") from exc


def _special_columns(names: list[str], mapping: Mapping[str, str], options: FitOptions,
                     source: str, notes: list[str]) -> tuple[str | None, str | None]:
    """The time and trajectory columns: as asked for, else by their usual names. A column
    named as time that is not taken is said in `notes`."""
    found = []
    for asked, default, option in (
            (options.time, column_roles.default_time_column(names), "--time"),
            (options.trajectory, column_roles.default_trajectory_column(names), "--trajectory")):
        if asked is not None and asked not in names:
            raise DataError(f"{source}: no column {asked!r} for {option} "
                            f"(columns: {', '.join(names)})")
        found.append(default if asked is None else asked)
    if found[0] is None:
        unused = [name for name in names if column_roles.looks_like_time(name)
                  and name not in mapping.values() and name != found[1]]
        if unused:
            notes.append(f"{source}: column {unused[0]!r} looks like time but its unit is "
                         f"not one of {', '.join(column_roles.TIME_UNITS)}: it was not used; give "
                         f"--time {unused[0]} --time-unit UNIT")
    return found[0], found[1]


def _truth(metadata: Mapping[str, Any] | None, m: Model) -> dict[str, float]:
    """The true parameters a simulated file records for this model, else none."""
    if not (metadata and isinstance(metadata.get("model"), Mapping)
            and metadata["model"].get("energy") == m.energy):
        return {}
    # A simulated record had no damping but what its [damping] table lists.
    undamped = dict.fromkeys(shorthand_names(m.coordinates), 0.0) \
        if isinstance(metadata.get("damping"), Mapping) else {}
    values = {**undamped, **(metadata.get("parameters") or {}),
              **(metadata.get("damping") or {})}
    return {k: float(v) for k, v in values.items() if isinstance(v, int | float)}


def noise_levels(loaded: Source,
                 noise: str | Mapping[str, float] | None) -> tuple[Any, dict[str, float] | None]:
    """Noise std per model variable, from the user or estimated; None without --noise."""
    if noise is None or noise == "none":
        return None, None
    assert isinstance(loaded, Loaded)   # noise weighting reads the records whole
    model, records = loaded.model, loaded.records
    N = len(model.coordinates)
    if noise == "auto":
        sigma = measurement.estimate_noise(records.X, records.bounds())
    elif isinstance(noise, Mapping):
        by_column = {column: name for name, column in loaded.data_info["columns"].items()}
        sigma = np.zeros(len(model.variables))
        for key, value in noise.items():
            name = key if key in model.variables else by_column.get(key)
            if name is None:
                raise UsageError(f"--noise: {key!r} is not a column of the model "
                                 f"({', '.join(model.variables)})")
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise UsageError(f"--noise: {key}={value!r} is not a non-negative number")
            k = model.variables.index(name)
            spread = float(records.spread[k])
            if value > 2 * spread:   # the column's spread holds its noise and its motion
                raise UsageError(f"--noise: {key}={value:g} is more than twice the spread of "
                                 f"the column itself (standard deviation {spread:.3g}); give "
                                 "the noise in the column's units")
            sigma[k] = float(value)
    else:
        raise UsageError(f"--noise must be none, auto or COL=SIGMA,..., found {noise!r}")
    if loaded.velocity_gain is not None:   # the velocities derived from recorded positions
        sigma[N:] = np.where(loaded.channels.derived, sigma[:N] * loaded.velocity_gain,
                             sigma[N:])
    if not np.any(sigma > 0):
        raise UsageError("--noise: every column has zero noise; leave --noise out instead")
    return sigma, {name: float(s) for name, s in zip(model.variables, sigma, strict=True)}


def trajectory_label(value: Any) -> Any:
    """A trajectory column's value as the label reported: a Python scalar, whole numbers
    as int (a column with missing cells is read as floats)."""
    value = value.item() if hasattr(value, "item") else value
    return int(value) if isinstance(value, float) and value.is_integer() else value
