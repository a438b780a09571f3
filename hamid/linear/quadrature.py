"""Integrals over time of functions of the recorded state, between the samples.

The dissipated work of the energy balance and the damping forces of the weak-form rows are
integrals of functions of the state (docs/method.md, "Damping: the energy balance"). Each
sample interval [t_k, t_k+1] gets Gauss-Legendre points on the local quintic through the
six nearest samples, O(dt^6) like the trapezoid rule. Where a function has a kink inside
an interval (sign(v) and |v| at v = 0, |v2 - v1| where the arms turn together), the
interval is split at the kink, which would otherwise cost the rule its order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from hamid.data.records import Records
from hamid.model.expressions import Func

__all__ = ["StatePoints", "state_points"]

_GAUSS_POINTS, _GAUSS_WEIGHTS = np.polynomial.legendre.leggauss(5)
_STENCIL = 6  # samples of the local interpolant: quintic, O(dt^6) like the trapezoid rule
_BISECTIONS = 60  # the bracket of a kink halves to rounding


@dataclass(frozen=True)
class StatePoints:
    """Quadrature points of every sample interval, and the interpolated state there."""

    interval: npt.NDArray[np.int64]   # left sample (row index) of each point's interval
    t: npt.NDArray[np.float64]
    X: npt.NDArray[np.float64]        # (points, variables)
    weight: npt.NDArray[np.float64]

    def cumulative(self, values: npt.NDArray[np.float64],
                   records: Records) -> npt.NDArray[np.float64]:
        """integral_0^t f dt at every sample, from f at the points, trajectory by
        trajectory (zero at each trajectory's first sample)."""
        per_interval = np.bincount(self.interval, weights=self.weight * values,
                                   minlength=len(records.group))
        total = np.zeros(len(records.group))
        for start, stop in records.bounds():
            total[start + 1:stop] = np.cumsum(per_interval[start:stop - 1])
        return total


def state_points(records: Records, kinks: Sequence[Func] = ()) -> StatePoints:
    """The points of every interval of the records, split where any of `kinks` (functions
    of the state) changes sign."""
    assert records.t is not None
    G = np.column_stack([k(records.X) for k in kinks]) if kinks else np.zeros((len(records.X), 0))
    parts = [_points_of_trajectory(records.t[a:b], records.X[a:b], G[a:b], a)
             for a, b in records.bounds() if b - a >= 2]
    width = records.X.shape[1]
    empty = (np.zeros(0, np.int64), np.zeros(0), np.zeros((0, width)), np.zeros(0))
    return StatePoints(*(np.concatenate([empty[k], *(p[k] for p in parts)])
                         for k in range(4)))


def _points_of_trajectory(t: np.ndarray, X: np.ndarray, G: np.ndarray,
                          offset: int) -> tuple[np.ndarray, ...]:
    n = len(t)
    left = np.arange(n - 1)
    width = min(_STENCIL, n)
    stencil = np.clip(left - (width // 2 - 1), 0, n - width)[:, None] + np.arange(width)
    nodes = t[stencil]

    def basis(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Lagrange basis of the intervals `rows` at x (rows, m): shape (rows, m, width)."""
        out = np.ones((*x.shape, width))
        for j in range(width):
            for k in range(width):
                if k != j:
                    out[..., j] *= (x - nodes[rows, k][:, None]) / (
                        nodes[rows, j] - nodes[rows, k])[:, None]
        return out

    a, b = t[:-1], t[1:]
    edge_rows, edge_x = [left, left], [a, b]
    for g in G.T:
        crossing = np.flatnonzero(np.sign(g[:-1]) * np.sign(g[1:]) < 0)
        values = g[stencil[crossing]]
        lo, hi = a[crossing].copy(), b[crossing].copy()
        sign_lo = np.sign(g[crossing])
        root = (lo + hi) / 2
        for _ in range(_BISECTIONS):
            value = np.einsum("rw,rw->r", basis(root[:, None], crossing)[:, 0], values)
            right = np.sign(value) == sign_lo
            lo = np.where(right, root, lo)
            hi = np.where(right, hi, root)
            root = (lo + hi) / 2
        edge_rows.append(crossing)
        edge_x.append(root)
    rows, x = np.concatenate(edge_rows), np.concatenate(edge_x)
    order = np.lexsort((x, rows))
    rows, x = rows[order], x[order]
    same = rows[1:] == rows[:-1]   # consecutive edges of one interval bound a piece
    starts, ends, rows = x[:-1][same], x[1:][same], rows[:-1][same]
    half = (ends - starts) / 2
    points = (starts + ends)[:, None] / 2 + half[:, None] * _GAUSS_POINTS
    weights = half[:, None] * _GAUSS_WEIGHTS
    state = np.einsum("rmw,rwc->rmc", basis(points, rows), X[stencil[rows]])
    return (np.repeat(rows + offset, len(_GAUSS_POINTS)), points.ravel(),
            state.reshape(-1, X.shape[1]), weights.ravel())
