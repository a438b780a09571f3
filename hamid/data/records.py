"""Recorded states, grouped by trajectory: what every step after loading works on."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from hamid.model.models import Model

__all__ = ["Recording", "Records", "medians_by", "ranges", "runs"]


@dataclass(frozen=True)
class Records:
    """Recorded states of one or more trajectories, rows grouped by trajectory in time order.

    X : shape (n_samples, 2N), the coordinates then the velocities, in model order.
    t : shape (n_samples,), or None when the data have no time column.
    group : shape (n_samples,), trajectory index 0..J-1, contiguous.
    labels : the trajectory labels shown to the user, one per index.
    U : shape (n_samples, m), the recorded inputs of a driven model (`Model.forcing`), in
        the order of its inputs; None for a free one.
    """

    X: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64] | None
    group: npt.NDArray[np.int64]
    labels: tuple[str | int, ...]
    U: npt.NDArray[np.float64] | None = None

    @property
    def n_trajectories(self) -> int:
        return len(self.labels)

    def slice(self, start: int, stop: int | None) -> Records:
        """Rows start:stop, without labels (a piece of a chunked pass)."""
        return Records(self.X[start:stop], None if self.t is None else self.t[start:stop],
                       self.group[start:stop], (),
                       None if self.U is None else self.U[start:stop])

    def taken(self, rows: npt.NDArray[np.intp]) -> Records:
        """The given rows (an index array), labels kept."""
        return Records(self.X[rows], None if self.t is None else self.t[rows],
                       self.group[rows], self.labels, None if self.U is None else self.U[rows])

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

    def bounds(self) -> list[tuple[int, int]]:
        """(start, stop) row range of each trajectory."""
        return [(start, stop) for _, start, stop in runs(self.group)]


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


@dataclass(frozen=True)
class Recording:
    """The model and the records a fit read: what the panels over the data need."""

    model: Model
    records: Records
