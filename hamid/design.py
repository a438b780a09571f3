"""Row blocks of the linear least-squares problem, built from a model and recorded states.

Every block holds rows of the form  A theta - b = r  (energy rows also carry their
trajectory's energy level h_j, so that  A theta - b - h_j = r), the trajectory of each row,
its time and its weight. A new kind of row (weak form, damping) is one more block or
column; the solver and the covariance estimators only see blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from hamid.model import Model

__all__ = ["Block", "Records", "energy_block"]


@dataclass(frozen=True)
class Records:
    """Recorded states of one or more trajectories, rows grouped by trajectory in time order.

    X : shape (n_samples, 2N), the coordinates then the velocities, in model order.
    t : shape (n_samples,), or None when the data have no time column.
    group : shape (n_samples,), trajectory index 0..J-1, contiguous.
    labels : the trajectory labels shown to the user, one per index.
    """

    X: npt.NDArray[np.float64]
    t: npt.NDArray[np.float64] | None
    group: npt.NDArray[np.int64]
    labels: tuple[str | int, ...]

    @property
    def n_trajectories(self) -> int:
        return len(self.labels)

    def bounds(self) -> list[tuple[int, int]]:
        """(start, stop) row range of each trajectory."""
        edges = np.flatnonzero(np.diff(self.group)) + 1
        starts = np.concatenate([[0], edges])
        stops = np.concatenate([edges, [len(self.group)]])
        return list(zip(starts.tolist(), stops.tolist(), strict=True))


@dataclass(frozen=True)
class Block:
    """Rows  A theta - b (- h_group when `has_level`) = r, with weights and grouping."""

    kind: str
    A: npt.NDArray[np.float64]
    b: npt.NDArray[np.float64]
    group: npt.NDArray[np.int64]
    time: npt.NDArray[np.float64]
    weight: npt.NDArray[np.float64]
    has_level: bool

    @property
    def n_rows(self) -> int:
        return len(self.b)


def energy_block(model: Model, records: Records) -> Block:
    """The energy rows: E0(x_i) + sum_k theta_k phi_k(x_i) - h_j = r_i, one per sample."""
    E0, Phi = model.energy_basis(records.X)
    time = records.t if records.t is not None else _sample_index(records)
    return Block("energy", Phi, -E0, records.group, time, np.ones(len(E0)), has_level=True)


def _sample_index(records: Records) -> npt.NDArray[np.float64]:
    """Position of each sample within its trajectory, for data without a time column."""
    index = np.arange(len(records.group), dtype=np.float64)
    for start, stop in records.bounds():
        index[start:stop] -= start
    return index
