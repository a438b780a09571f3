"""Recorded states, grouped by trajectory: what every step after loading works on; and
the cutting of records read whole at missing values and time gaps."""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from hamid.errors import DataError
from hamid.safe_text import counted

if TYPE_CHECKING:
    from hamid.model.models import Model

__all__ = ["CHANNEL_KINDS", "GAP_STEPS", "SHORTEST_PIECE", "Channels", "Recording", "Records",
           "check_inputs", "locate", "medians_by", "ranges", "runs", "split_gaps"]


@dataclass(frozen=True)
class Records:
    """Recorded states of one or more trajectories, rows grouped by trajectory in time order.

    X : shape (n_samples, 2N), the coordinates then the velocities, in model order.
    t : shape (n_samples,), or None when the data have no time column.
    group : shape (n_samples,), trajectory index 0..J-1, contiguous.
    labels : the trajectory labels shown to the user, one per index.
    U : shape (n_samples, m), the recorded inputs of a driven model (`Model.forcing`), in
        the order of its inputs; None for a free one.
    A : shape (n_samples, N), the recorded accelerations of the coordinates (0 where a
        coordinate has none, `Channels.fitted`), fitted by the trajectory refinement; None
        when none is recorded.
    """

    X: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64] | None
    group: npt.NDArray[np.int64]
    labels: tuple[str | int, ...]
    U: npt.NDArray[np.float64] | None = None
    A: npt.NDArray[np.float64] | None = None

    @property
    def n_trajectories(self) -> int:
        return len(self.labels)

    def slice(self, start: int, stop: int | None) -> Records:
        """Rows start:stop, without labels (a piece of a chunked pass)."""
        return Records(self.X[start:stop], None if self.t is None else self.t[start:stop],
                       self.group[start:stop], (),
                       None if self.U is None else self.U[start:stop],
                       None if self.A is None else self.A[start:stop])

    @cached_property
    def spread(self) -> npt.NDArray[np.float64]:
        """Each column's standard deviation, a column at a time (over X at once, numpy
        takes 3x as long and a copy of X)."""
        return np.array([self.X[:, k].std() for k in range(self.X.shape[1])])

    @cached_property
    def extent(self) -> npt.NDArray[np.float64]:
        """Each column's largest absolute value, a column at a time (no copy of X)."""
        return np.array([max(-self.X[:, k].min(), self.X[:, k].max())
                         for k in range(self.X.shape[1])])

    @property
    def compared(self) -> npt.NDArray[np.float64]:
        """X, then the recorded accelerations when there are any: the channels the
        trajectory refinement compares with the integrated motion."""
        return self.X if self.A is None else np.hstack([self.X, self.A])

    @property
    def compared_spread(self) -> npt.NDArray[np.float64]:
        """Each compared channel's standard deviation (`spread`, then the accelerations')."""
        return self.spread if self.A is None else np.concatenate([self.spread,
                                                                  self.A.std(axis=0)])

    def bounds(self) -> list[tuple[int, int]]:
        """(start, stop) row range of each trajectory."""
        return [(start, stop) for _, start, stop in runs(self.group)]


CHANNEL_KINDS = ("position", "velocity", "acceleration")
_PLURALS = {"position": "positions", "velocity": "velocities",
            "acceleration": "accelerations"}


@dataclass(frozen=True)
class Channels:
    """Which channels of each coordinate a recording holds (`CHANNEL_KINDS`); the positions
    and velocities it lacks are reconstructed for the linear start, and only the recorded
    ones are fitted by the trajectory refinement."""

    coordinates: tuple[str, ...]
    recorded: tuple[frozenset[str], ...]   # per coordinate
    aside: frozenset[str] = frozenset()   # coordinates whose velocity column was set aside

    @classmethod
    def complete(cls, coordinates: tuple[str, ...]) -> Channels:
        """Positions and velocities of every coordinate recorded."""
        return cls(coordinates, tuple(frozenset(CHANNEL_KINDS[:2]) for _ in coordinates))

    @property
    def accelerated(self) -> bool:
        """Whether an acceleration was recorded."""
        return any("acceleration" in kinds for kinds in self.recorded)

    @property
    def fitted(self) -> npt.NDArray[np.bool_]:
        """Of each channel the refinement compares (positions, velocities, and the
        accelerations when one was recorded): whether it was recorded."""
        kinds = CHANNEL_KINDS if self.accelerated else CHANNEL_KINDS[:2]
        return np.array([[kind in recorded for recorded in self.recorded]
                         for kind in kinds]).ravel()

    @property
    def derived(self) -> npt.NDArray[np.bool_]:
        """Of each coordinate: whether its velocity is derived from its recorded positions."""
        return np.array([kinds >= {"position"} and "velocity" not in kinds
                         for kinds in self.recorded], dtype=bool)

    @property
    def reconstructed(self) -> bool:
        """Whether a position or a velocity was not recorded."""
        return not self.fitted[:2 * len(self.coordinates)].all()

    @classmethod
    def of(cls, model: Model, mapping: Mapping[str, str]) -> Channels:
        """The channels of each coordinate of `model` that `mapping` (model name ->
        column) has a column for."""
        return cls(model.coordinates, tuple(
            frozenset(kind for kind, name in zip(CHANNEL_KINDS, names, strict=True)
                      if name in mapping)
            for names in zip(model.coordinates, model.velocities, model.acceleration_names,
                             strict=True)))

    @property
    def text(self) -> str:
        """The channels recorded, as the report lists them: ``x: position, velocity``."""
        return "; ".join(f"{name}: {', '.join(kinds['recorded'])}"
                         for name, kinds in self.report().items())

    def same_as(self, first: Channels | None, source: str, first_source: str) -> Channels:
        """These channels, those of the first file read (None: this is it); a file of
        others is an error."""
        if first is not None and first != self:
            raise DataError(f"{source}: records other channels than {first_source} "
                            f"({self.text}, against {first.text})")
        return self

    def notes(self, source: str, refined: bool) -> list[str]:
        """What the report says of the channels reconstructed and of those not fitted, one
        note for the coordinates that record alike; what the trajectory refinement fits,
        where one follows (`refined`: the method is auto, and no option asks for the linear
        fit's estimate)."""
        alike: dict[tuple[str, ...], list[str]] = {}
        for name, kinds in self.report().items():
            alike.setdefault(tuple(kinds["recorded"]), []).append(name)
        notes = []
        for recorded, names in alike.items():
            who = "any coordinate" if len(names) == len(self.coordinates) else ", ".join(names)
            rebuilt = [k for k in CHANNEL_KINDS[:2] if k not in recorded]
            fitted = [k for k in recorded if k != "acceleration"]
            if "position" in recorded and rebuilt:
                notes.append(f"{source}: no velocity column for {who}: the velocities are "
                             "derived from the positions (as --velocity savgol)"
                             + ", and the trajectory refinement fits the positions alone"
                             * refined)
            elif rebuilt:
                notes.append(f"{source}: no {' or '.join(rebuilt)} column for {who}: "
                             f"{' and '.join(_PLURALS[k] for k in rebuilt)} integrated from the "
                             f"{'velocities' if fitted else 'accelerations'} for the linear "
                             + ("start (less their cycle means); the trajectory refinement "
                                f"fits the recorded {' and '.join(_PLURALS[k] for k in recorded)}"
                                if refined else "fit (less their cycle means)"))
        return notes

    def set_aside(self, velocities: Collection[str], names: Sequence[str]) -> Channels:
        """These channels with the velocities named (of the model's `names`, one per
        coordinate) no longer recorded: to be derived from the positions."""
        return dataclasses.replace(self, recorded=tuple(
            kinds - {"velocity"} if name in velocities else kinds
            for kinds, name in zip(self.recorded, names, strict=True)), aside=frozenset(
            q for q, name in zip(self.coordinates, names, strict=True) if name in velocities))

    def check_same_times(self, X: npt.NDArray[np.float64], source: str) -> None:
        """The channels of one coordinate sampled at different times are an error: missing
        values in X (the variables, then the accelerations read) such that fewer than half
        the rows of each channel hold them all. A channel with dropouts of its own, the
        others complete, is just missing there."""
        N = len(self.coordinates)
        accelerations = iter(range(2 * N, X.shape[1]))
        for k, kinds in enumerate(self.recorded):
            columns = [k] * ("position" in kinds) + [N + k] * ("velocity" in kinds) + (
                [next(accelerations)] if "acceleration" in kinds else [])
            present = ~np.isnan(X[:, columns])
            shared = present.all(axis=1).sum() / np.maximum(present.sum(axis=0), 1)
            if len(columns) > 1 and shared.max() < 0.5:
                raise DataError(
                    f"{source}: the channels of coordinate {self.coordinates[k]!r} "
                    f"({', '.join(sorted(kinds))}) are sampled at different times (fewer "
                    "than half the rows of each hold them all); resample them onto common "
                    "times")

    def split_accelerations(self, records: Records) -> Records:
        """The records of the model's variables, the accelerations read after them in
        `Records.A` (one column per coordinate, in model order, 0 where not recorded)."""
        n_variables = 2 * len(self.coordinates)
        if not self.accelerated:
            return records
        accelerations = np.zeros((len(records.group), len(self.coordinates)))
        recorded = [k for k, kinds in enumerate(self.recorded) if "acceleration" in kinds]
        accelerations[:, recorded] = records.X[:, n_variables:]
        return dataclasses.replace(records, X=records.X[:, :n_variables], A=accelerations)

    def report(self) -> dict[str, dict[str, list[str]]]:
        """Coordinate -> the channels recorded and those reconstructed (`data.channels`),
        and the velocity column set aside for disagreeing with the positions."""
        return {name: {"recorded": [k for k in CHANNEL_KINDS if k in kinds],
                       "reconstructed": [k for k in CHANNEL_KINDS[:2] if k not in kinds],
                       **({"set_aside": ["velocity"]} if name in self.aside else {})}
                for name, kinds in zip(self.coordinates, self.recorded, strict=True)}


def runs(group: npt.NDArray[np.int64]) -> list[tuple[int, int, int]]:
    """(trajectory, start, stop) of each run of consecutive rows of one trajectory."""
    if len(group) == 0:
        return []
    edges = (np.flatnonzero(np.diff(group)) + 1).tolist()
    return [(int(group[start]), start, stop)
            for start, stop in zip([0, *edges], [*edges, len(group)], strict=True)]


def ranges(starts: npt.NDArray[np.intp], counts: npt.NDArray[np.intp]) -> npt.NDArray[np.intp]:
    """The indices starts[i], ..., starts[i] + counts[i] - 1 of every i, one after another:
    rows of many trajectories gathered with one index and no loop over them."""
    offsets = np.cumsum(counts) - counts
    return np.repeat(starts - offsets, counts) + np.arange(counts.sum())


# Values per group above which `medians_by` takes a median per group.
_LONG_GROUPS = 64


def medians_by(values: npt.NDArray[np.float64], ids: npt.NDArray[np.int64],
               count: int) -> npt.NDArray[np.float64]:
    """The median of the values of each id 0..count-1 (NaN for an id without values), as
    `numpy.median` gives it; `ids` ascending (the values grouped by id). Many short
    groups take one sort (a call each took 0.3 s for 5,000 trajectories), a few long
    ones a call each (in linear time, where a sort of millions would take seconds)."""
    lengths = np.bincount(ids, minlength=count)
    first = np.cumsum(lengths) - lengths
    if len(values) > _LONG_GROUPS * count:
        return np.array([np.median(values[a:a + n]) if n else np.nan
                         for a, n in zip(first.tolist(), lengths.tolist(), strict=True)])
    ordered = values[np.lexsort((values, ids))]
    medians = np.full(count, np.nan)
    has = lengths > 0
    low = ordered[(first + (lengths - 1) // 2)[has]]
    high = ordered[(first + lengths // 2)[has]]
    medians[has] = np.where(lengths[has] % 2 == 1, low, (low + high) / 2)
    return medians


GAP_STEPS = 5.0   # a time step over this many times the median step is a gap
SHORTEST_PIECE = 3   # pieces of fewer samples are dropped


def split_gaps(records: Records, gaps: str, row_sources: tuple[tuple[str, int], ...],
               notes: list[str]) -> tuple[Records, Any]:
    """Drop the rows with a missing value and cut the trajectories at time steps over
    `GAP_STEPS` times their trajectory's median step, into trajectories of their own (each
    with its own energy level); nothing is interpolated. A few rows missing within a
    trajectory are just missing: it goes on across them (a step of a few samples, as if
    the rows had never been written), where a cut would add an energy level and cost the
    damping's standard error several times over. Without a time column every dropped row
    cuts. With ``gaps="error"`` a time gap between recorded rows is an error (missing
    values already are). Returns the records and, when rows were dropped, the row read of
    each row kept."""
    missing = np.isnan(records.X).any(axis=1)
    if records.U is not None:
        missing |= np.isnan(records.U).any(axis=1)
    if records.t is not None:
        missing |= np.isnan(records.t)
    kept = np.flatnonzero(~missing)
    group, t = records.group, records.t
    whole = len(kept) == len(group)   # no copies of the columns when nothing is missing
    cut = np.zeros(len(kept), dtype=bool)
    if not whole and t is None:   # no time to go on by
        cut[1:] = (kept[1:] - kept[:-1] > 1) & (group[kept[1:]] == group[kept[:-1]])
    n_gaps = n_bridged = 0
    if t is not None and len(kept) > 1:
        tk, gk = (t, group) if whole else (t[kept], group[kept])
        steps = np.diff(tk)
        same = gk[1:] == gk[:-1]
        adjacent = same if whole else same & (kept[1:] - kept[:-1] == 1)
        # the steps of a trajectory (gk[1:] is contiguous) and its median step
        trajectory = np.concatenate([[0], np.cumsum(gk[2:] != gk[1:-1])])
        median = medians_by(steps[adjacent], trajectory[adjacent], int(trajectory[-1]) + 1)
        limit = np.where(np.isnan(median), np.inf, GAP_STEPS * median)[trajectory]
        back = np.flatnonzero(same & ~(steps > 0))
        if back.size:
            source, row = locate(row_sources, int(kept[back[0] + 1]))
            raise DataError(f"{source}: row {row}: time does not increase across the missing "
                            "values before it; sort the file by trajectory then time")
        gap = same & (steps > limit)
        if (gap & adjacent).any() and gaps == "error":
            first = int(np.argmax(gap & adjacent))
            source, row = locate(row_sources, int(kept[first + 1]))
            raise DataError(f"{source}: row {row}: a time gap of {steps[first]:g} s "
                            f"(over {GAP_STEPS:g} times the median step); give --gaps split "
                            "to fit the pieces as separate trajectories")
        n_gaps = int((gap & adjacent).sum())
        n_bridged = int((same & ~adjacent & ~gap).sum())
        cut[1:] |= gap
    n_dropouts = int(cut.sum()) - n_gaps
    if not cut.any() and not missing.any():
        return records, None
    if not cut.any():   # rows missing, every trajectory going on across them
        notes.append(f"{counted(int(missing.sum()), 'row', 'rows')} with missing values "
                     "dropped; the trajectories go on across the "
                     f"{counted(n_bridged, 'place', 'places')} they leave (none over "
                     f"{GAP_STEPS:g} times the median step), nothing interpolated")
        return Records(records.X[kept], None if t is None else t[kept], group[kept],
                       records.labels, None if records.U is None else records.U[kept]), kept
    start = np.ones(len(kept), dtype=bool)
    start[1:] = cut[1:] | (group[kept[1:]] != group[kept[:-1]])
    piece = np.cumsum(start) - 1
    sizes = np.bincount(piece) if len(piece) else np.zeros(0, np.int64)
    short = sizes < SHORTEST_PIECE
    keep_rows = ~short[piece] if len(piece) else np.zeros(0, bool)
    kept, piece = kept[keep_rows], piece[keep_rows]
    if not len(kept):
        raise DataError(f"{', '.join(source for source, _ in row_sources)}: no piece of "
                        f"{SHORTEST_PIECE} samples or more is left once the trajectories are "
                        "cut at missing values and time gaps; give --gaps error to see where")
    # pieces in order of appearance, each numbered as a trajectory of its own
    pieces, first = np.unique(piece, return_index=True)
    owner = group[kept[first]].tolist()
    count = np.bincount(owner)
    labels, seen = [], {}
    for j in owner:
        seen[j] = seen.get(j, 0) + 1
        label = records.labels[j]
        labels.append(label if count[j] == 1 else f"{label}/{seen[j]}")
    new_group = np.searchsorted(pieces, piece).astype(np.int64)
    bridged = (f"; they go on across {counted(n_bridged, 'shorter run', 'shorter runs')} of "
               "missing values" if n_bridged else "")
    notes.append(f"{counted(n_dropouts + n_gaps, 'cut', 'cuts')} in the trajectories "
                 f"({n_dropouts} at missing values, {n_gaps} at time gaps over {GAP_STEPS:g} "
                 f"times the median step{bridged}): "
                 f"{counted(len(labels), 'trajectory', 'trajectories')} fitted, each with its "
                 f"own energy level; {counted(int(missing.sum()), 'row', 'rows')} with missing "
                 f"values and {counted(int((~keep_rows).sum()), 'row', 'rows')} in pieces under "
                 f"{SHORTEST_PIECE} samples "
                 "dropped, nothing interpolated (--gaps error refuses instead)")
    return Records(records.X[kept], None if t is None else t[kept], new_group,
                   tuple(labels), None if records.U is None else records.U[kept]), kept


def locate(row_sources: tuple[tuple[str, int], ...], row: int) -> tuple[str, int]:
    """The source and 1-based data row of row `row` of tables read one after another, each
    (name, its first row)."""
    source, first = next((s, f) for s, f in reversed(row_sources) if f <= row)
    return source, row - first + 1


@dataclass(frozen=True)
class Recording:
    """The model and the records a fit read, and which channels they recorded (None:
    every position and velocity): what a prediction and the panels over the data need."""

    model: Model
    records: Records
    channels: Channels | None = None

    @property
    def compared(self) -> tuple[list[str], npt.NDArray[np.bool_]]:
        """The names of the channels set beside the model's motion (`Records.compared`: the
        variables, then the accelerations when any was recorded), and of each whether it
        was recorded; the others were reconstructed or derived from those that were."""
        model = self.model
        channels = self.channels or Channels.complete(model.coordinates)
        names = [*model.variables,
                 *(model.acceleration_names if self.records.A is not None else ())]
        return names, channels.fitted


# An input missing in more than this share of rows was recorded at another rate.
_SPARSE_INPUT = 0.3


def check_inputs(U: np.ndarray, inputs: tuple[str, ...], mapping: Mapping[str, str],
                  sources: list[str]) -> None:
    """A driven fit's inputs must be recorded with the motion: not empty, not constant
    (it would do the work of a static load, which the motion does not tell from the
    potential), and sampled at the motion's rate (missing values are gaps, as for the
    motion, but not every other row)."""
    where = ", ".join(sources)
    for i, name in enumerate(inputs):
        column = U[:, i]
        missing = np.isnan(column)
        label = f"{where}: input {name!r} (column {mapping[name]!r})"
        if missing.all():
            raise DataError(f"{label} is empty")
        if missing.mean() > _SPARSE_INPUT:
            raise DataError(f"{label} is missing in {int(missing.sum()):,} of {len(column):,} "
                            "rows: recorded at another rate than the motion? Resample it onto "
                            "the motion's times")
        if np.nanmin(column) == np.nanmax(column):
            raise DataError(f"{label} is constant ({np.nanmin(column):g}): a constant input "
                            "does no work the motion can tell from the potential's")
