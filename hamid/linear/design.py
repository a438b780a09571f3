"""Row blocks of the linear least-squares problem, built from a model and recorded states.

Every block holds rows of the form  A theta - b = r  (energy rows also carry their
trajectory's energy level h_j, so that  A theta - b - h_j = r), the trajectory of each row,
its time and its weight. A new kind of row (weak form, damping) is one more block or
column; the solver and the covariance estimators only see blocks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.data.records import Records, medians_by, ranges
from hamid.errors import DataError
from hamid.linear import quadrature
from hamid.model.dissipation import Dissipation
from hamid.model.expressions import Func
from hamid.model.models import Model

__all__ = ["Block", "RowKind", "energy_block", "input_work", "median_period",
           "trajectory_scales", "weak_block", "window_means", "windows"]


class RowKind(StrEnum):
    """Which rows a block holds (energy or weak-form), and which a fit takes (`FitPlan`:
    those, or both, ``joint``); the report writes them as their text."""

    ENERGY = "energy"
    WEAK = "weak"
    JOINT = "joint"


@dataclass(frozen=True)
class Block:
    """Rows  A theta - b (- h_group when `has_level`) = r, with weights and grouping."""

    kind: RowKind
    A: npt.NDArray[np.float64]
    b: npt.NDArray[np.float64]
    group: npt.NDArray[np.int64]
    time: npt.NDArray[np.float64]
    weight: npt.NDArray[np.float64]
    has_level: bool

    @property
    def n_rows(self) -> int:
        return len(self.b)

    def slice(self, start: int, stop: int | None) -> Block:
        """Rows start:stop (views)."""
        return Block(kind=self.kind, A=self.A[start:stop], b=self.b[start:stop],
                     group=self.group[start:stop], time=self.time[start:stop],
                     weight=self.weight[start:stop], has_level=self.has_level)


def _dissipated_work(records: Records, dissipation: Dissipation,
                     shared: quadrature.StatePoints | None = None) -> npt.NDArray[np.float64]:
    """Work done against each dissipative term since the start of its trajectory.

    Column k is integral_0^t sum_i v_i dR_k/dv_i dt, the power of coefficient k, integrated
    between the samples and split at the term's kinks (`hamid.linear.quadrature`). The
    terms without kinks take the points `shared` when given (those of the input work,
    whose first columns are the state's), not made again.
    """
    work = np.zeros((len(records.group), len(dissipation)))
    width = records.X.shape[1]
    for kinks, terms in _by_kinks(dissipation).items():
        points = (shared if shared is not None and not kinks
                  else quadrature.state_points(records, kinks))
        power = dissipation.power_parts(points.X[:, :width])
        for k in terms:
            work[:, k] = points.cumulative(power[:, k], records)
    return work


def _by_kinks(dissipation: Dissipation) -> dict[tuple[Func, ...], list[int]]:
    """The terms that share their kinks (and so their quadrature points)."""
    groups: dict[tuple[str, ...], tuple[tuple[Func, ...], list[int]]] = {}
    for k, kinks in enumerate(dissipation.kinks):
        key = tuple(str(getattr(f, "expression", f)) for f in kinks)
        groups.setdefault(key, (kinks, []))[1].append(k)
    return dict(groups.values())


def _input_points(records: Records) -> quadrature.StatePoints:
    """The quadrature points of the records' state and inputs side by side (X, then U)."""
    assert records.U is not None
    return quadrature.state_points(replace(records, X=np.hstack([records.X, records.U])))


def input_work(model: Model, records: Records, points: quadrature.StatePoints | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Work the recorded inputs have done on the system since the start of its trajectory:
    integral_0^t Q(q, u) . v dt, its parameter-free part W0 (n,) and its part per model
    parameter W (n, P), Q = dW/dq the generalized force of `Model.forcing`; at the
    `_input_points` of the records, made here unless given.

    The inputs are interpolated between the samples by the same local quintic as the state
    (`hamid.linear.quadrature`): a DAQ samples its inputs, it does not hold them.
    """
    assert model.forcing is not None and records.U is not None
    width = records.X.shape[1]
    if points is None:
        points = _input_points(records)
    Q0, Q = model.forcing.parts(points.X[:, :width], points.X[:, width:])
    V = points.X[:, len(model.coordinates):width]
    W0 = points.cumulative(np.einsum("pi,pi->p", Q0, V), records)
    power = np.einsum("pik,pi->pk", Q, V)
    W = np.column_stack([points.cumulative(power[:, k], records)
                         for k in range(power.shape[1])])
    return W0, W


def energy_block(model: Model, records: Records,
                 dissipation: Dissipation | None = None) -> Block:
    """The energy rows: E0(x_i) + sum_k theta_k phi_k(x_i) - h_j = r_i, one per sample.

    With a `dissipation`, the energy balance: the work dissipated since the start of the
    trajectory is added, one column per dissipative coefficient. With a forcing, the work
    the recorded inputs did since then is taken away (its parameter-free part into b).
    """
    E0, Phi = model.energy_basis(records.X)   # rows of one array, which Phi keeps
    points = None
    if model.forcing is not None:
        points = _input_points(records)
        W0, W = input_work(model, records, points)
        Phi -= W
        E0 -= W0
    if dissipation:
        Phi = np.hstack([Phi, _dissipated_work(records, dissipation, points)])
    time = records.t if records.t is not None else _sample_index(records)
    b = np.negative(E0, out=E0)   # in its row: no other array of the record's length
    return Block(RowKind.ENERGY, Phi, b, records.group, time, np.ones(len(E0)), has_level=True)


def window_means(block: Block, windows: Windows) -> Block:
    """Energy rows as psi-weighted window means, one row per window: averaging the noise of
    the measured terms before they enter the fit (the energy rows of a joint fit)."""
    return Block(block.kind, windows.mean_of(block.A), windows.mean_of(block.b), windows.group,
                 windows.centre, np.ones(windows.n_windows), has_level=True)


def _sample_index(records: Records) -> npt.NDArray[np.float64]:
    """Position of each sample within its trajectory, for data without a time column."""
    index = np.arange(len(records.group), dtype=np.float64)
    for start, stop in records.bounds():
        index[start:stop] -= start
    return index


BUMP_ORDER = 5  # psi = (1 - s^2)^p: p >= 5 keeps the trapezoid rule O(dt^6); see README
MIN_SAMPLES_PER_WINDOW = 20
# Orders of the weak rows' quadrature: the trapezoid rule on the bump, and Simpson's on
# unevenly sampled windows (`_quadrature_weights`); `Windows.quadrature_error`.
QUADRATURE_ORDER, UNEVEN_ORDER = 6, 4
# Windows start every quarter window: measured 1.4-2x lower errors than half overlap on
# noisy data (README, accuracy), because the extra test functions use more of the signal.
WINDOW_STEP = 0.25


_PAD = 8


def median_period(scales: list[tuple[float | None, float]]) -> float | None:
    """The median of the trajectories' periods (`trajectory_scales`), None when no
    trajectory has one."""
    periods = [period for period, _ in scales if period is not None]
    return float(np.median(periods)) if periods else None


# The samples of each trajectory its period and time step are taken from. The padded
# spectrum of a record of millions of samples would take gigabytes, and a file read in
# chunks holds no more than these of a trajectory to find them. They hold a few periods
# unless one spans over 50,000 samples (windows of 25,000 samples, far finer sampling
# than the weak form needs).
SCALE_SAMPLES = 1 << 18


def trajectory_scales(records: Records, n_coordinates: int) -> list[tuple[float | None, float]]:
    """Each trajectory's dominant period (None if it cannot tell) and median time step,
    from its first `SCALE_SAMPLES` samples.

    The period is the peak of one power spectrum of the coordinates (standardised, so
    units do not matter, and zero-padded to refine the frequency grid). Trajectories of
    one length are taken together: a call per trajectory took 1 s for 5,000.
    """
    if records.t is None:
        return []
    bounds = np.array(records.bounds(), dtype=np.intp).reshape(-1, 2)
    starts = bounds[:, 0]
    lengths = np.minimum(bounds[:, 1], starts + SCALE_SAMPLES) - starts
    n_steps = lengths - 1
    first = ranges(starts, n_steps)
    steps = records.t[first + 1] - records.t[first]
    step = medians_by(steps, np.repeat(np.arange(len(starts)), n_steps), len(starts))
    step[n_steps == 0] = np.inf
    period = np.full(len(starts), np.nan)
    for length in np.unique(lengths[lengths >= 8]):
        same = np.flatnonzero(lengths == length)
        padded = _padded(length)
        # at most about 2^18 padded values of a coordinate in one transform (4 MB of
        # complex values: the fit in memory holds no more than its records)
        for part in np.array_split(same, -(-len(same) * padded // (1 << 18))):
            rows = starts[part][:, None] + np.arange(length)
            period[part] = _periods(records.t[rows], records.X[rows, :n_coordinates])
    return [(None if np.isnan(p) else float(p), float(s))
            for p, s in zip(period, step, strict=True)]


def _padded(length: int) -> int:
    """The length of a trajectory's spectrum: a power of two (other lengths can take the
    FFT 10x as long: 30,001 = 19 x 1579), `_PAD` times the samples or more."""
    return 1 << int(np.ceil(np.log2(_PAD * length)))


def _periods(t: npt.NDArray[np.float64], q: npt.NDArray[np.float64]
             ) -> npt.NDArray[np.float64]:
    """The period of the strongest oscillation of the coordinates of trajectories of one
    length, NaN where it cannot tell.

    t : shape (m, n); q : shape (m, n, N).
    """
    n = t.shape[1]
    spread = q.std(axis=1, keepdims=True)
    live = spread > 0
    q = np.where(live, (q - q.mean(axis=1, keepdims=True)) / np.where(live, spread, 1.0), 0.0)
    dt = (t[:, -1] - t[:, 0]) / (n - 1)
    padded = _padded(n)
    power = np.sum(np.abs(np.fft.rfft(q, n=padded, axis=1)) ** 2, axis=2)
    power[:, :-(-padded // n)] = 0.0   # below one cycle over the record
    peak = np.argmax(power, axis=1)
    return np.where(peak > 0, padded * dt / np.maximum(peak, 1), np.nan)


def window_ranges(t: npt.NDArray[np.float64], window: float, *, origin: float | None = None,
                  skip: int = 0, ended: bool = True) -> tuple[npt.NDArray[np.int64],
                                                             npt.NDArray[np.int64], int]:
    """First and last sample of each window (one every `WINDOW_STEP` windows), ends on samples.

    Windows are counted from `origin` (the trajectory's first time, by default t[0]) and
    returned from number `skip` on; the third value is the number of the first window not
    returned. With ``ended=False`` (a trajectory whose later samples are still to come)
    only windows that have a sample at or after their end are returned. Ends on samples
    make the trapezoid rule spectrally accurate for the bump, whose derivatives vanish at
    both ends.
    """
    origin = t[0] if origin is None else origin
    span, step = t[-1] - origin, window * WINDOW_STEP
    count = int(np.floor((span - window) / step * (1 + 1e-12))) + 1
    number = np.arange(skip, max(count, skip))
    starts = origin + number * step
    ends = np.searchsorted(t, starts + window)
    if not ended:
        number, starts, ends = (x[ends < len(t)] for x in (number, starts, ends))
    first = np.clip(np.searchsorted(t, starts), 0, len(t) - 1)
    last = np.clip(ends, 0, len(t) - 1)
    keep = last - first >= 2
    following = int(number[-1]) + 1 if len(number) else skip
    return first[keep].astype(np.int64), last[keep].astype(np.int64), following


@dataclass(frozen=True)
class Windows:
    """Test functions over overlapping windows, as quadrature operators on the samples.

    ``Q_psi @ f`` is the integral of psi_w(t) f(t) over each window w, ``Q_dpsi @ f`` that of
    psi_w'(t) f(t); both are sparse, shape (n_windows, n_samples). Windows come in the
    order of their samples (first and last nondecreasing), as `window_ranges` gives them.
    The operators' values are made on use, a block of windows at a time (`operators`),
    not held: a record of 3 million samples has 12 million nodes in its windows, and the
    two operators took 1.7 times the memory of the record's columns.
    """

    t: npt.NDArray[np.float64]     # every sample's time (the records', not a copy)
    centre: npt.NDArray[np.float64]
    group: npt.NDArray[np.int64]
    length: float
    first: npt.NDArray[np.int64]   # first and last sample (row index) of each window
    last: npt.NDArray[np.int64]
    order: int
    uneven: npt.NDArray[np.bool_]   # windows sampled unevenly (Simpson's weights)
    richardson: bool = False   # the rule of the rows' quadrature errors (`quadrature_error`)

    @property
    def n_windows(self) -> int:
        return len(self.centre)

    def quadrature_error(self) -> Windows:
        """Windows whose rows are about the quadrature errors of these windows' rows.

        A rule of order p errs about 2^p times as much at twice the step, so a row's
        error is about its value on every other sample less its value on every sample,
        over 2^p - 1 (Richardson): the weights of this rule. Each window is shortened by a
        sample where it spans an odd number of steps, so that the rule on every other
        sample still ends on its last one (a rule whose end falls between its nodes errs
        at a lower order); a window one step shorter errs about as much."""
        odd = (self.last - self.first) % 2 == 1
        return replace(self, last=self.last - odd, richardson=True)

    @property
    def Q_psi(self) -> Any:
        """The operator of psi (all windows; made on each use)."""
        return self._whole(lambda lo, hi, a, b: self.operators(lo, hi, derivative=False)[0])

    @property
    def Q_dpsi(self) -> Any:
        """The operator of psi' (all windows; made on each use)."""
        return self._whole(lambda lo, hi, a, b: self.operators(lo, hi)[1])

    def _whole(self, part: Callable[[int, int, int, int], Any]) -> Any:
        """Helper: the blocks' operators `part(lo, hi, a, b)` over their samples a:b, as
        one operator over all samples."""
        from scipy import sparse

        n = len(self.t)
        if not self.n_windows:
            return sparse.csr_matrix((0, n))
        return sparse.vstack([sparse.csr_matrix((m.data, m.indices + a, m.indptr),
                                                shape=(hi - lo, n))
                              for lo, hi, a, b in self.blocks() for m in [part(lo, hi, a, b)]],
                             format="csr")

    def operators(self, lo: int, hi: int, derivative: bool = True) -> tuple[Any, Any]:
        """The rows lo:hi of Q_psi and of Q_dpsi (None unless `derivative`), CSR matrices
        over the samples those windows cover, first[lo] to last[hi - 1] (the columns a:b
        of `blocks`): slicing operators over all samples copied them.

        Each window's nodes are consecutive samples; the integrals use the trapezoid rule
        on the recorded times, with Simpson's where a window is sampled unevenly; psi and
        psi' share base^(order - 1) times the weights.
        """
        from scipy import sparse

        first, last = self.first[lo:hi], self.last[lo:hi]
        a = int(first[0]) if hi > lo else 0
        t = self.t[a:int(last[-1]) + 1] if hi > lo else self.t[:0]
        sizes = last - first + 1
        # 32-bit indices where they fit (scipy's own choice)
        index = np.int32 if max(int(sizes.sum()), len(self.t)) < 2**31 else np.int64
        indptr = np.concatenate([[0], np.cumsum(sizes)]).astype(index)
        row = np.repeat(np.arange(hi - lo), sizes)
        col = np.arange(indptr[-1]) - indptr[:-1][row] + (first - a)[row]   # in t
        lo_t, hi_t = t[first - a], t[last - a]
        half = ((hi_t - lo_t) / 2)[row]
        s = (t[col] - ((lo_t + hi_t) / 2)[row]) / half
        base = np.clip(1 - s**2, 0.0, None)  # rounding can put s a hair past 1
        weights = _window_weights(t=t, step=np.diff(t), first=first - a, last=last - a, row=row,
                                  col=col, uneven=self.uneven[lo:hi])
        if self.richardson:
            order = np.where(self.uneven[lo:hi], UNEVEN_ORDER, QUADRATURE_ORDER)[row]
            weights = (_every_other_weights(t, first - a, last - a, row, col,
                                            self.uneven[lo:hi]) - weights) / (2.0**order - 1)
        lower = weights.copy()   # base^(order - 1) * weights: serves psi and its derivative
        for _ in range(self.order - 1):   # products: numpy's power is ten times slower
            lower *= base
        shape, col = (hi - lo, len(t)), col.astype(index)
        psi = sparse.csr_matrix((base * lower, col, indptr), shape=shape)
        if not derivative:
            return psi, None
        values = -2 * self.order * s / half * lower
        return psi, sparse.csr_matrix((values, col, indptr), shape=shape)

    @property
    def means(self) -> Any:
        """Operator of the psi-weighted window means: rows of Q_psi divided by their sums
        (made on each use)."""
        return self._whole(self.means_part)

    def means_part(self, lo: int, hi: int, a: int, b: int) -> Any:
        """The rows lo:hi of `means`, its columns (samples) a:b (a block of `blocks`)."""
        from scipy import sparse

        rows = self.operators(lo, hi, derivative=False)[0]
        mass = rows @ np.ones(b - a)
        return sparse.diags(1.0 / mass) @ rows

    def blocks(self) -> Iterator[tuple[int, int, int, int]]:
        """Blocks of windows lo:hi and the samples a:b they cover, in order: what is made
        for one block stays small however long the record."""
        for lo in range(0, self.n_windows, _WINDOW_BLOCK):
            hi = min(lo + _WINDOW_BLOCK, self.n_windows)
            yield lo, hi, int(self.first[lo]), int(self.last[hi - 1]) + 1

    def mean_of(self, values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """`means @ values`, a block of windows and their samples at a time (each window's
        sum as in one product; the operator and the values of all samples are not copied,
        as a product with all of them would copy values not in C order)."""
        return np.concatenate([np.zeros((0, *values.shape[1:]))] + [
            self.means_part(lo, hi, a, b) @ values[a:b] for lo, hi, a, b in self.blocks()])

    def spread(self, values: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """`means.T @ values`: values of the windows spread over their samples, a block of
        windows at a time."""
        total = np.zeros((len(self.t), *values.shape[1:]))
        for lo, hi, a, b in self.blocks():
            total[a:b] += self.means_part(lo, hi, a, b).T @ values[lo:hi]
        return total

    def psi_at(self, t: npt.NDArray[np.float64], interval: npt.NDArray[np.int64],
               weights: npt.NDArray[np.float64], times: npt.NDArray[np.float64]) -> Any:
        """Operator of the integrals of psi_w(t) f(t) from values of f at given points.

        The points `t` (with quadrature `weights`) lie in the sample intervals `interval`
        (index of each interval's left sample, sorted); `times` are the sample times.
        """
        from scipy import sparse

        lo_point = np.searchsorted(interval, self.first, side="left")
        hi_point = np.searchsorted(interval, self.last, side="left")
        counts = hi_point - lo_point
        rows = np.repeat(np.arange(self.n_windows), counts)
        cols = np.concatenate([np.arange(a, b) for a, b in zip(lo_point, hi_point,
                                                               strict=True)] or
                              [np.zeros(0, np.int64)])
        lo, hi = times[self.first][rows], times[self.last][rows]
        s = (t[cols] - (lo + hi) / 2) / ((hi - lo) / 2)
        values = np.clip(1 - s**2, 0.0, None) ** self.order * weights[cols]
        return sparse.csr_matrix((values, (rows, cols)), shape=(self.n_windows, len(t)))


def _quadrature_weights(nodes: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Weights of a rule for integrals over the nodes.

    Evenly spaced: the trapezoid rule, which for the bump (all low derivatives vanish at
    both ends) is accurate to O(dt^6). Uneven: composite Simpson on pairs of intervals
    (O(h^4), where the trapezoid rule would be O(h^2)), with the trapezoid for an odd last
    interval.
    """
    h = np.diff(nodes)
    weights = np.zeros(len(nodes))
    if np.allclose(h, h[0], rtol=1e-9, atol=0):
        weights[:-1] += h / 2
        weights[1:] += h / 2
        return weights
    pairs = len(h) // 2
    h0, h1 = h[0:2 * pairs:2], h[1:2 * pairs:2]
    total = h0 + h1
    weights[0:2 * pairs:2] += total / 6 * (2 - h1 / h0)
    weights[1:2 * pairs:2] += total**3 / (6 * h0 * h1)
    weights[2:2 * pairs + 1:2] += total / 6 * (2 - h0 / h1)
    if len(h) % 2:
        weights[-2:] += h[-1] / 2
    return weights


def windows(records: Records, length: float, order: int | None = None) -> Windows:
    """Bumps psi = (1 - s^2)^p over overlapping windows of `length` seconds.

    The integrals use the trapezoid rule on the recorded times, with the window ends on
    samples; a window with uneven sampling gets composite Simpson (`_quadrature_weights`).
    """
    assert records.t is not None
    parts = [(start + a, start + b, np.full(len(a), j, dtype=np.int64))
             for j, (start, stop) in enumerate(records.bounds())
             for a, b, _ in [window_ranges(records.t[start:stop], length)]]
    first, last, group = (np.concatenate([p[k] for p in parts] or [np.zeros(0, np.int64)])
                          for k in range(3))
    return windows_at(records, first, last, group, length, order)


def windows_at(records: Records, first: npt.NDArray[np.int64], last: npt.NDArray[np.int64],
               group: npt.NDArray[np.int64], length: float, order: int | None = None) -> Windows:
    """Windows over given sample ranges (`window_ranges`); their operators are made on use,
    a block of windows at a time (a long record holds hundreds of thousands)."""
    assert records.t is not None
    t_all = records.t
    # once for all windows: per block of windows these passes over every sample made the
    # build quadratic in the record's length
    uneven = _uneven_windows(t_all, first, last)
    return Windows(t=t_all, centre=(t_all[first] + t_all[last]) / 2, group=group, length=length,
                   first=first, last=last, order=BUMP_ORDER if order is None else order,
                   uneven=uneven)


_WINDOW_BLOCK = 1024   # windows built at once: their temporaries stay small (README, Performance)


def _window_weights(t: np.ndarray, step: np.ndarray, first: np.ndarray, last: np.ndarray,
                    row: np.ndarray, col: np.ndarray, uneven: np.ndarray) -> np.ndarray:
    """Trapezoid weights of every window's nodes; Simpson where a window is unevenly sampled
    (`uneven`); `step` holds the time steps of all of `t`."""
    left = np.where(col > first[row], step[np.maximum(col - 1, 0)], 0.0)
    right = np.where(col < last[row], step[np.minimum(col, max(len(step) - 1, 0))], 0.0)
    weights = (left + right) / 2
    for w in np.flatnonzero(uneven):
        weights[row == w] = _quadrature_weights(t[int(first[w]):int(last[w]) + 1])
    return weights


def _every_other_weights(t: np.ndarray, first: np.ndarray, last: np.ndarray, row: np.ndarray,
                         col: np.ndarray, uneven: np.ndarray) -> np.ndarray:
    """`_window_weights` of the rules on every other node of each window, from its first
    (which ends on its last when it spans an even number of steps); the other nodes weigh
    nothing."""
    offset = col - first[row]
    kept = offset % 2 == 0
    before = np.where(offset == 0, col, col - 2)
    after = np.minimum(col + 2, last[row])
    weights = np.where(kept, (t[after] - t[before]) / 2, 0.0)
    for w in np.flatnonzero(uneven):
        mine = np.flatnonzero((row == w) & kept)
        weights[mine] = _quadrature_weights(t[col[mine]])
    return weights


def _uneven_windows(t: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Whether the time step changes (beyond rounding) anywhere inside each window."""
    changes = []   # steps k (t[k + 1] - t[k]) unlike step k - 1, a piece of samples at a time
    for a in range(1, max(len(t) - 1, 1), _GRADIENT_ROWS):
        step = np.diff(t[a - 1:a + _GRADIENT_ROWS + 1])
        changes.append(a + np.flatnonzero(np.abs(np.diff(step)) > 1e-9 * np.abs(step[1:])))
    changed = np.concatenate(changes) if changes else np.zeros(0, np.int64)
    # steps first+1..last-1 of a window; a change at step k means step k != step k-1
    return np.searchsorted(changed, last) - np.searchsorted(changed, first + 1) > 0


def weak_block(model: Model, records: Records, windows: Windows,
               dissipation: Dissipation | None = None) -> Block:
    """Weak-form rows of Lagrange's equations: one per window and coordinate.

    Row (w, i):  integral( psi_w' dL/dv_i + psi_w (dL/dq_i + Q_i) + psi_w F_i ) dt = r,
    Q_i the generalized force of the recorded inputs (`Model.forcing`), split
    into the parameter-free part (moved to b) and one column per parameter; the dissipative
    force F_i = -sum_k c_k dR_k/dv_i gives the column -integral(psi_w dR_k/dv_i) of c_k in
    the rows of i.
    """
    n, N = len(records.X), len(model.coordinates)
    parts = 1 + len(model.parameters)
    rows = windows.n_windows * N
    integrals = np.zeros((windows.n_windows, N * parts))
    # the gradients a chunk of samples at a time, into the windows that reach the chunk
    for a in range(0, n, _GRADIENT_ROWS):
        b = min(a + _GRADIENT_ROWS, n)
        dLdv, dLdq = model.lagrangian.gradients(records.X[a:b])   # (b - a, N, 1 + p)
        if model.forcing is not None:   # the generalized force joins dL/dq
            assert records.U is not None
            Q0, Q = model.forcing.parts(records.X[a:b], records.U[a:b])
            dLdq = dLdq + np.concatenate([Q0[:, :, None], Q], axis=2)
        dLdv, dLdq = dLdv.reshape(b - a, -1), dLdq.reshape(b - a, -1)
        w_lo = int(np.searchsorted(windows.last, a, side="left"))
        w_hi = int(np.searchsorted(windows.first, b, side="left"))
        for lo in range(w_lo, w_hi, _WINDOW_BLOCK):
            hi = min(lo + _WINDOW_BLOCK, w_hi)
            psi, dpsi = windows.operators(lo, hi)   # over the samples from first[lo] on
            start = int(windows.first[lo])
            c, d = max(a, start), min(b, int(windows.last[hi - 1]) + 1)   # those in a:b
            cols, values = slice(c - start, d - start), slice(c - a, d - a)
            integrals[lo:hi] += dpsi[:, cols] @ dLdv[values] + psi[:, cols] @ dLdq[values]
    integrals = integrals.reshape(rows, parts)   # rows (window, coordinate)
    A = integrals[:, 1:]
    if dissipation:
        forces = np.zeros((rows, len(dissipation)))
        assert records.t is not None
        for kinks, terms in _by_kinks(dissipation).items():
            p = quadrature.state_points(records, kinks)
            psi = windows.psi_at(p.t, p.interval, p.weight, records.t)
            parts = dissipation.force_parts(p.X)
            for k in terms:
                for i in range(N):
                    forces[i::N, k] = -(psi @ parts[:, i, k])
        A = np.hstack([A, forces])
    return Block(RowKind.WEAK, A, -integrals[:, 0], np.repeat(windows.group, N),
                 np.repeat(windows.centre, N), np.ones(rows), has_level=False)


def weak_quadrature_error(model: Model, records: Records, windows: Windows,
                          dissipation: Dissipation | None = None) -> Block:
    """About the quadrature error of each weak row of `windows` (`Windows.quadrature_error`),
    as rows A, b: at theta, A theta - b. The damping forces' columns are zero: their
    integrals at Gauss points between the samples are not estimated."""
    rows = weak_block(model, records, windows.quadrature_error())
    damping = np.zeros((rows.n_rows, len(dissipation) if dissipation else 0))
    return replace(rows, A=np.hstack([rows.A, damping]))


_GRADIENT_ROWS = 1 << 16   # samples whose gradients are held at once


def _weak_sensitivities(model: Model, records: Records, theta: npt.NDArray[np.float64],
                        dissipation: Dissipation | None) -> tuple[np.ndarray, np.ndarray]:
    """d(dL/dv_i)/dx_c and d(dL/dq_i + F_i)/dx_c at every sample: how a weak row's
    integrands move with the noise of each measured variable (shape (n, N, 2N))."""
    n_energy = len(model.parameters)
    d_dv, d_dq = model.lagrangian.second_derivatives(records.X, theta[:n_energy])
    if dissipation:
        d_dq = d_dq - dissipation.force_slopes(records.X, theta[n_energy:])
    return d_dv, d_dq


def row_variance(block: Block, model: Model, records: Records, theta: npt.NDArray[np.float64],
                 sigma: npt.NDArray[np.float64], windows: Windows | None = None,
                 dissipation: Dissipation | None = None) -> npt.NDArray[np.float64]:
    """Variance that white measurement noise of std `sigma` (per variable) puts into each row.

    First order in the noise: an energy row's residual moves by dE/dx_c e_c, a weak row's
    by the window integral of the derivatives of dL/dv_i and dL/dq_i (and of the damping
    force) times the noise of each sample. The cumulative work of an energy balance is left
    out: its noise is spread over the whole record.
    """
    s2 = np.asarray(sigma, dtype=np.float64) ** 2
    if block.kind == RowKind.ENERGY:
        g = (model.energy_gradient(records.X, theta[:len(model.parameters)]) ** 2) @ s2
        if windows is None:
            return g
        means = windows.means
        return means.multiply(means) @ g
    assert windows is not None
    d_dv, d_dq = _weak_sensitivities(model, records, theta, dissipation)
    N = len(model.coordinates)
    dd, dp = windows.Q_dpsi, windows.Q_psi
    dd2, cross, dp2 = dd.multiply(dd), dd.multiply(dp), dp.multiply(dp)
    variance = np.zeros((windows.n_windows, N))
    for i in range(N):
        a, b = d_dv[:, i, :], d_dq[:, i, :]
        variance[:, i] = (dd2 @ (a**2 @ s2) + 2 * (cross @ ((a * b) @ s2))
                          + dp2 @ (b**2 @ s2))
    return variance.ravel()


def propagated_covariance(blocks: list[Block], G: npt.NDArray[np.float64], model: Model,
                          records: Records, theta: npt.NDArray[np.float64],
                          sigma: npt.NDArray[np.float64], windows: Windows | None,
                          dissipation: Dissipation | None) -> npt.NDArray[np.float64]:
    """Covariance of the free parameters that white measurement noise alone would cause.

    To first order theta_hat - theta = sum_s sum_c g_sc e_sc over the samples s and the
    measured variables c, with g_sc = sum_rows G_row d(row)/d(y_sc); independent noise of
    std sigma_c gives sum_sc sigma_c^2 g_sc g_sc'. Unlike a residual-based estimate, this
    sees how the cumulative work of an energy balance carries a sample's noise into every
    later row. `G` maps the stacked rows' errors to the free parameters; `theta` holds
    every parameter (fixed ones at their values).
    """
    n, n_var = records.X.shape
    N = len(model.coordinates)
    p = G.shape[1]
    n_energy = len(model.parameters)
    g = np.zeros((n, n_var, p))
    start = 0
    for block in blocks:
        G_block = G[start:start + block.n_rows]
        start += block.n_rows
        if block.kind == RowKind.ENERGY:
            spread = G_block if windows is None else windows.means.T @ G_block
            gradient = model.energy_gradient(records.X, theta[:n_energy])
            g += gradient[:, :, None] * spread[:, None, :]
            if dissipation:
                _add_work_sensitivity(g, spread, records, theta[n_energy:], dissipation)
        else:
            assert windows is not None
            d_dv, d_dq = _weak_sensitivities(model, records, theta, dissipation)
            dd, dp = windows.Q_dpsi, windows.Q_psi
            for i in range(N):
                rows = G_block[i::N]
                via_dpsi = dd.T @ rows     # (n, p)
                via_psi = dp.T @ rows
                g += d_dv[:, i, :, None] * via_dpsi[:, None, :]
                g += d_dq[:, i, :, None] * via_psi[:, None, :]
    weighted = g * np.asarray(sigma)[None, :, None]
    flat = weighted.reshape(-1, p)
    return flat.T @ flat


def _add_work_sensitivity(g: np.ndarray, spread: np.ndarray, records: Records,
                          coefficients: np.ndarray, dissipation: Dissipation) -> None:
    """The noise of the state at sample u enters the work of every later sample of its
    trajectory, through the slope of the dissipated power there."""
    assert records.t is not None
    for start, stop in records.bounds():
        t = records.t[start:stop]
        weight = np.gradient(t) if stop - start > 1 else np.zeros(1)
        # sum over later samples s > u of spread_s: a reversed cumulative sum
        later = np.cumsum(spread[start:stop][::-1], axis=0)[::-1] - spread[start:stop]
        slopes = dissipation.power_slopes(records.X[start:stop], coefficients)
        g[start:stop] += (slopes * weight[:, None])[:, :, None] * later[:, None, :]


def check_weak_rows(block: Block, labels: tuple[str | int, ...]) -> None:
    """Weak-form rows must be finite (the energy's derivatives are, along the records)."""
    if block.kind != RowKind.WEAK:
        return
    bad = np.flatnonzero(~np.all(np.isfinite(np.column_stack([block.A, block.b])), axis=1))
    if bad.size:
        raise DataError(f"the weak-form rows are not finite (window at t = "
                        f"{block.time[bad[0]]:g} of trajectory "
                        f"{labels[block.group[bad[0]]]}): the energy's derivatives "
                        "are not finite there; use --method energy")


def check_finite(block: Block, locate: Callable[[int], tuple[str, int]],
                  names: list[str]) -> None:
    """Energy terms must be finite at every sample (data inside the energy's domain)."""
    if np.isfinite(block.A.sum() + block.b.sum()):   # a finite sum has finite terms
        return
    values = np.column_stack([block.b, block.A])
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if not bad.size:
        return
    row = int(bad[0])
    column = int(np.flatnonzero(~np.isfinite(values[row]))[0])
    term = "the parameter-free part" if column == 0 else f"the term of {names[column - 1]!r}"
    source, local = locate(row)
    raise DataError(f"{source}: row {local}: {term} of the energy is not finite there "
                    "(the data are outside the energy's domain, or too large)")


def fitted_energy(rows: Block, model: Model, estimates: dict[str, float]) -> Any:
    """E(x_i; theta) at every sample, from the energy rows already built (A theta - b)."""
    n_energy = len(model.parameters)
    theta = np.array([estimates[name] for name in model.parameters])
    energy = rows.A[:, :n_energy] @ theta
    energy -= rows.b   # in place: one array of the record's length, not two
    return energy


def sample_weights(kind: str, blocks: list[Block], n_samples: int, spans: Any) -> Any:
    """The weight each sample's energy equation carried in the fit.

    In `joint` the energy rows are window means, so a sample's weight is its share of the
    windows that hold it; in `weak` the energy equations were not fitted (weight 0).
    """
    if kind == RowKind.ENERGY:
        return blocks[0].weight
    if kind == RowKind.WEAK:
        return np.zeros(n_samples)
    return spans.spread(blocks[0].weight)
