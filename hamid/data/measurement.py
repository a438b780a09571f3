"""What the recording itself tells about its errors: noise levels and derived velocities."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np
import numpy.typing as npt

from hamid.data.records import Channels, Records, ranges, runs
from hamid.errors import DataError, UsageError

__all__ = ["DIFFERENCE_ORDER", "NYQUIST_BAND", "NYQUIST_SHARE", "VelocityFinding",
           "VelocitySums", "derive_velocities", "estimate_noise", "integrated",
           "nyquist_warning", "nyquist_warnings", "reconstruct", "savgol_velocities",
           "velocity_check"]

# Differences of this order remove a smooth signal (its k-th difference is ~ (w dt)^k) and
# keep white noise, scaled by sqrt(C(2k, k)).
DIFFERENCE_ORDER = 4
_MAD_TO_SIGMA = 1.4826  # median absolute deviation of a Gaussian, in standard deviations
# A Savitzky-Golay filter must differentiate the polynomials of its order to this accuracy
# (in units of the window): an error e of its coefficients puts about 4e into the velocities
# at the default window. scipy's coefficients go from 1e-9 to 100% wrong within a few samples
# of window, not smoothly (order 5: first above at 1,195 samples, 1,913 3e-5, 2,001 wrong;
# order 9: first above at 59, 101 wrong).
SAVGOL_EXACTNESS = 1e-6


def estimate_noise(X: npt.NDArray[np.float64],
                   bounds: Sequence[tuple[int, int]]) -> npt.NDArray[np.float64]:
    """White-noise standard deviation of each column, from differences within trajectories.

    The k-th difference of white noise of std sigma has std sigma * sqrt(C(2k, k)), while
    that of a smooth, finely sampled signal is negligible; the median absolute deviation
    keeps a few outliers from inflating the estimate.

    Parameters
    ----------
    X : ndarray, shape (n_samples, n_columns)
    bounds : list of (start, stop)
        Row range of each trajectory.

    Returns
    -------
    sigma : ndarray, shape (n_columns,)
    """
    k = DIFFERENCE_ORDER
    usable = [(a, b) for a, b in bounds if b - a > k]
    if not usable:
        raise DataError(f"too few samples to estimate the noise (need more than {k} per "
                        "trajectory); give --noise COL=SIGMA instead of auto")
    # one column of differences at a time, reordered in place by the medians (a column's
    # order does not change its median): no copy of the record's size
    differences = np.empty(sum(b - a - k for a, b in usable))
    mad = np.empty(X.shape[1])
    for column in range(X.shape[1]):
        row = 0
        for a, b in usable:
            differences[row:row + b - a - k] = np.diff(X[a:b, column], n=k)
            row += b - a - k
        differences -= np.median(differences, overwrite_input=True)
        mad[column] = np.median(np.abs(differences, out=differences), overwrite_input=True)
    return _MAD_TO_SIGMA * mad / math.sqrt(math.comb(2 * k, k))


def derive_velocities(records: Records, which: npt.NDArray[np.bool_], window: int | None,
                      order: int, period: float | None
                      ) -> tuple[Records, tuple[int, float]]:
    """Records whose velocities of the coordinates `which` come from Savitzky-Golay
    differentiation of their positions (`period`, the dominant one, sets the default
    window), and the window and the noise gain (`savgol_velocities`)."""
    if records.t is None:
        raise UsageError("--velocity savgol needs a time column; name it with --time COL "
                         "(and its unit with --time-unit)")
    N = len(which)
    if window is None:
        dt = float(np.median(np.diff(records.t)))
        window = default_savgol_window(None if period is None else period / dt, order)
    V, gain = savgol_velocities(records.X[:, :N][:, which], records.t, records.bounds(),
                                window=window, order=order)
    X = records.X.copy()
    X[:, N + np.flatnonzero(which)] = V
    return dataclasses.replace(records, X=X), (window, gain)


# A rate's zero crossing is counted where its sign, taken only where it is beyond this
# share of its root mean square, changes (noise about zero makes none).
CROSSING_SHARE = 0.1


def integrated(rates: npt.NDArray[np.float64], t: npt.NDArray[np.float64],
               bounds: Sequence[tuple[int, int]]) -> npt.NDArray[np.float64]:
    """Each column of `rates` integrated over time in each trajectory (cumulative
    trapezoids on the recorded times, so across missing samples too), less its drift: the
    line through its means over each cycle of the rate (from a zero crossing to the next
    but one, every crossing), joined by straight pieces; a straight line fitted to it where
    the rate makes fewer than two cycles. The integration's unknown start, the drift of a
    bias of the rate and the wander its noise integrates into go, slower than a cycle;
    the motion itself, oscillating about the well's bottom, has a cycle mean near zero
    and stays."""
    values = np.empty_like(rates)
    for a, b in bounds:
        tau = t[a:b] - t[a]
        pieces = np.diff(tau)[:, None] * (rates[a + 1:b] + rates[a:b - 1]) / 2
        integral = np.concatenate([np.zeros((1, rates.shape[1])), np.cumsum(pieces, axis=0)])
        for k in range(rates.shape[1]):
            values[a:b, k] = integral[:, k] - _drift(integral[:, k], rates[a:b, k], tau)
    return values


def _drift(integral: npt.NDArray[np.float64], rate: npt.NDArray[np.float64],
           tau: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The slow part of an integral (`integrated`): its cycle means, joined."""
    beyond = np.abs(rate) > CROSSING_SHARE * np.sqrt(np.mean(rate**2))
    signs = np.sign(rate[beyond])
    crossings = np.flatnonzero(beyond)[1:][np.diff(signs) != 0]
    if len(crossings) < 4:   # fewer than two cycles: the ends need two cycle means
        return np.polynomial.polynomial.Polynomial.fit(tau, integral, 1)(tau)
    weights = np.gradient(tau)
    centres, means = [], []
    for first, last in zip(crossings[:-2], crossings[2:], strict=True):
        w = weights[first:last]
        centres.append(float(np.sum(w * tau[first:last]) / np.sum(w)))
        means.append(float(np.sum(w * integral[first:last]) / np.sum(w)))
    centres_, means_ = np.array(centres), np.array(means)
    drift = np.interp(tau, centres_, means_)
    for edge, pair in ((tau < centres_[0], slice(0, 2)), (tau > centres_[-1], slice(-2, None))):
        slope = np.diff(means_[pair])[0] / max(np.diff(centres_[pair])[0], np.finfo(float).tiny)
        reference = centres_[pair][0 if pair.start == 0 else 1]
        drift[edge] = means_[pair][0 if pair.start == 0 else 1] + slope * (tau[edge] - reference)
    return drift


def reconstruct(records: Records, channels: Channels) -> Records:
    """The records as read (the model's variables, then the accelerations recorded) with
    each velocity recorded by neither it nor a position integrated from the coordinate's
    accelerations, each position not recorded integrated from its velocity (`integrated`),
    and the accelerations in `Records.A`. The velocities of recorded positions are derived apart
    (`derive_velocities`)."""
    records = channels.split_accelerations(records)
    if not channels.reconstructed or channels.derived.all():
        return records
    if records.t is None:
        raise UsageError("channels not recorded are integrated over time: name the time "
                         "column with --time COL")
    N, bounds, X = len(channels.coordinates), records.bounds(), records.X.copy()
    from_accelerations = [k for k, kinds in enumerate(channels.recorded)
                          if not kinds & {"position", "velocity"}]
    if from_accelerations:
        assert records.A is not None
        X[:, [N + k for k in from_accelerations]] = integrated(
            records.A[:, from_accelerations], records.t, bounds)
    from_velocities = [k for k, kinds in enumerate(channels.recorded) if "position" not in kinds]
    if from_velocities:
        X[:, from_velocities] = integrated(X[:, [N + k for k in from_velocities]], records.t,
                                           bounds)
    return dataclasses.replace(records, X=X)


def savgol_velocities(Q: npt.NDArray[np.float64], t: npt.NDArray[np.float64],
                      bounds: Sequence[tuple[int, int]], *, window: int,
                      order: int) -> tuple[npt.NDArray[np.float64], float]:
    """Velocities of the coordinates by Savitzky-Golay differentiation, per trajectory.

    The edges use the filter's ``interp`` mode (a polynomial fitted to the first and last
    window), so they carry no wild values. Sampling must be even within each trajectory.

    Returns
    -------
    V : ndarray, shape like Q
    gain : float
        How much the filter amplifies white noise of the positions into the velocities:
        std(v noise) = gain * std(q noise).
    """
    from scipy.signal import savgol_coeffs, savgol_filter

    if window % 2 == 0 or window <= order:
        raise UsageError(f"--window must be odd and larger than --order ({order}), "
                         f"found {window}")
    _check_edge_fit(window, order)
    _check_savgol(window, order)
    V = np.empty_like(Q)
    gain = 0.0
    for a, b in bounds:
        t_j = t[a:b]
        if b - a < window:
            raise DataError(f"a trajectory of {b - a} samples is shorter than the "
                            f"Savitzky-Golay window of {window}; use a smaller --window")
        step = np.diff(t_j)
        dt = float(np.median(step))
        V[a:b] = savgol_filter(Q[a:b], window, order, deriv=1, delta=dt, axis=0,
                               mode="interp")
        uneven = np.abs(step - dt) > 1e-6 * dt
        if uneven.any():   # missing frames, or uneven sampling: those windows fitted anew
            V[a:b] = _uneven_windows(Q[a:b], t_j, uneven, V[a:b], window, order)
        gain = max(gain, float(np.linalg.norm(savgol_coeffs(window, order, deriv=1,
                                                            delta=dt))))
    return V, gain


def _uneven_windows(Q: npt.NDArray[np.float64], t: npt.NDArray[np.float64],
                    uneven: npt.NDArray[np.bool_], V: npt.NDArray[np.float64], window: int,
                    order: int) -> npt.NDArray[np.float64]:
    """V with the derivative at every sample whose window spans an uneven step taken from
    the polynomial of `order` fitted by least squares to that window's samples at their own
    times: what the Savitzky-Golay filter computes on even sampling (the same windows,
    shifted inside the trajectory at its ends as the filter's "interp" mode does)."""
    n, half = len(t), window // 2
    low = np.clip(np.arange(n) - half, 0, n - window)
    spanned = np.concatenate([[0], np.cumsum(uneven)])   # uneven steps before each row
    redo = np.flatnonzero(spanned[low + window - 1] - spanned[low] > 0)
    V = V.copy()
    for chunk in np.array_split(redo, max(1, len(redo) // 4096)):
        rows = low[chunk, None] + np.arange(window)                  # (k, window)
        offset = t[rows] - t[chunk, None]
        scale = np.max(np.abs(offset), axis=1, keepdims=True)
        basis = (offset / scale)[..., None] ** np.arange(order + 1)  # (k, window, order+1)
        slope = np.linalg.pinv(basis)[:, 1]                           # (k, window)
        V[chunk] = np.einsum("kw,kwc->kc", slope, Q[rows]) / scale
    return V


def _savgol_error(window: int, order: int) -> float:
    """How far scipy's Savitzky-Golay derivative misses on the polynomials of its order, in
    units of the window. Its coefficients come from the powers of the sample offsets,
    x**order, which over a long window span more than a double holds: the filter then
    misses even the derivative of a straight line."""
    from scipy.signal import savgol_coeffs

    half = window // 2
    x = np.arange(-half, half + 1) / half
    # d/dx (x/half)**k at 0 is 1/half for k = 1 and 0 for every other k up to the order
    found = np.vander(x, order + 1, increasing=True).T @ savgol_coeffs(window, order, deriv=1,
                                                                       use="dot") * half
    return float(np.max(np.abs(found - np.eye(order + 1)[1])))


def _check_savgol(window: int, order: int) -> None:
    """Refuse a filter that cannot be computed accurately (`_savgol_error`)."""
    if _savgol_error(window, order) > SAVGOL_EXACTNESS:
        raise UsageError(f"--velocity savgol: a filter of order {order} over {window} samples "
                         "cannot be computed accurately (scipy's coefficients lose their "
                         "precision); give a shorter --window or a lower --order")


def _check_edge_fit(window: int, order: int) -> None:
    """Refuse an order whose polynomial the filter's edge fit cannot determine in floating
    point (from about 18 on): scipy then printed numpy's RankWarning, with its source
    lines, once per coordinate and edge, and the edges were not to be trusted."""
    import warnings

    from scipy.signal import savgol_filter

    with warnings.catch_warnings():
        warnings.simplefilter("error", np.exceptions.RankWarning)
        try:
            savgol_filter(np.zeros(window), window, order, deriv=1, mode="interp")
        except np.exceptions.RankWarning:
            raise UsageError(f"--order {order}: a polynomial of that degree over the "
                             f"Savitzky-Golay window of {window} samples is too poorly "
                             "conditioned to fit; use a lower --order (below 18)") from None


def default_savgol_window(period_samples: float | None, order: int) -> int:
    """An odd window of about a tenth of the dominant period, and at least order + 2, but
    no longer than a filter of that order can be computed accurately over."""
    target = 11 if period_samples is None else int(round(period_samples / 10))
    window = max(target, order + 2)
    window = window if window % 2 else window + 1
    if _savgol_error(window, order) <= SAVGOL_EXACTNESS:
        return window
    # the error grows with the window, if not smoothly: bisect for an accurate one below
    # (for too high an order there is none, and savgol_velocities refuses the shortest)
    good, bad = (order + 2) | 1, window
    while bad - good > 2:
        middle = (good + bad) // 4 * 2 + 1
        good, bad = (middle, bad) if _savgol_error(middle, order) <= SAVGOL_EXACTNESS \
            else (good, middle)
    return good


VELOCITY_RATIO = 1.25   # measured velocities this far from the positions' rate are said
VELOCITY_SPAN = 8       # samples over which the positions' change is compared
# A lag of the velocities behind the positions acts like a viscous force of damping ratio
# about pi * lag / period (v(t - lag) = v - lag a, and a = -w^2 q for an oscillation); one
# that would add more than this to the damping ratio is said.
LAG_DAMPING_RATIO = 5e-4
LAG_SIGNIFICANCE = 4.0   # standard errors: a lag or gain the noise could fake is not said
# A velocity channel whose amplitude differs from the positions' rate of change by more than
# this (a gain, a calibration, a filter's attenuation) is said: a gain 1 + e scales the
# kinetic energy by (1 + e)^2, and so the stiffnesses found against the masses by about 2e.
GAIN_TOLERANCE = 0.01
JUDGED_SPANS = 20   # fewer spans judge no gain or lag: their standard errors are no guide


@dataclasses.dataclass(frozen=True)
class VelocityFinding:
    """What the velocity check found of one velocity column: said in `text`; `disagrees`
    when the column is a scaled or lagging copy of the positions' rate of change (a channel
    filtered or derived before recording), which a fit does better to set aside, rather
    than mixed units, which the user must correct."""

    velocity: str   # the model's name of it
    text: str
    disagrees: bool


def _velocity_spans(records: Records,
                    open_length: bool = False) -> dict[int, npt.NDArray[np.intp]]:
    """The spans of `velocity_check`: `VELOCITY_SPAN` samples, or all of a shorter
    trajectory's; for each length, the first sample of every span that has it, all
    trajectories at once (a loop over them took a sixth of a fit of 5,000 short ones).
    `open_length`: every trajectory is known to be longer than a span (the rest of one
    whose first spans were taken already)."""
    bounds = np.array(records.bounds(), dtype=np.intp).reshape(-1, 2)
    lengths = (np.full(len(bounds), VELOCITY_SPAN) if open_length
               else np.minimum(VELOCITY_SPAN, bounds[:, 1] - bounds[:, 0] - 1))
    spans = {}
    for length in np.unique(lengths[lengths >= 1]):
        mine = bounds[lengths == length]
        # the spans in each trajectory
        counts = np.maximum(mine[:, 1] - mine[:, 0] - length, 0)
        spans[int(length)] = ranges(mine[:, 0], counts)
    return spans


def velocity_check(records: Records, coordinates: Sequence[str], velocities: Sequence[str],
                   mapping: Mapping[str, str], period: float | None) -> list[VelocityFinding]:
    """Where the measured velocities disagree with the rate of change of the positions: a
    column in other units (mm with m/s), a wrong time unit, a gain or a lag (a velocity
    channel filtered or derived before recording); `VelocitySums` over all the records."""
    sums = VelocitySums(len(coordinates))
    sums.add(records)
    return sums.findings(coordinates, velocities, mapping, period)


class VelocitySums:
    """The sums of `velocity_check`'s regressions, added a piece of records at a time: a
    file read in chunks adds each chunk's, the last samples of its open trajectory carried
    into the next, so that the sums are those of the records read whole.

    Over spans of `VELOCITY_SPAN` samples, the change of each coordinate is regressed on
    the integral of its velocity and on the change of the velocity: x(t+s) - x(t) =
    gain * integral(v) + lag * (v(t+s) - v(t)) to first order in a lag. A gain beyond
    `VELOCITY_RATIO` either way is said as mixed units; one beyond `GAIN_TOLERANCE`, and a
    lag that acts like damping of ratio over `LAG_DAMPING_RATIO` at the dominant `period`
    (None: no lag is judged), each `LAG_SIGNIFICANCE` standard errors from zero, as a
    channel that disagrees. Integrals rather than differences keep the position noise from
    being amplified; over an even number of steps they are Simpson's, whose error at a few
    samples a period, (w dt)^4 / 180, is far below the tolerance (the trapezoids' (w dt)^2 /
    12 is 2% at 12 samples a period).
    """

    def __init__(self, n_coordinates: int) -> None:
        N = n_coordinates
        self.normal, self.right = np.zeros((N, 2, 2)), np.zeros((N, 2))
        self.squares, self.count, self.span = np.zeros(N), np.zeros(N, np.int64), 0
        self._carry: Records | None = None   # the open trajectory's samples not yet spanned
        self._started = False   # whether spans of the open trajectory were taken

    def add(self, records: Records, ended: bool = True) -> None:
        """Add the spans of `records` (with a time column); with `ended` False their last
        trajectory may go on in the next records added."""
        if self._carry is not None:
            carry = self._carry
            records = Records(np.vstack([carry.X, records.X]),
                              np.concatenate([carry.t, records.t]),
                              np.concatenate([carry.group, records.group]), ())
        self._carry = None
        pieces = runs(records.group)
        first = pieces[0][2] if pieces else 0
        if self._started and (ended or len(pieces) > 1):   # the carried trajectory ends
            self._sums(records.slice(0, first), open_length=True)
            self._started = False
            records = records.slice(first, None)
            pieces = runs(records.group)
        if not ended and pieces:
            last = pieces[-1][1]
            self._sums(records.slice(0, last))
            records = records.slice(last, None)
            if len(records.group) > VELOCITY_SPAN or self._started:
                self._sums(records, open_length=True)
                self._started = True
                records = records.slice(len(records.group) - VELOCITY_SPAN, None)
            self._carry = records
        elif len(records.group):
            self._sums(records, open_length=False)

    def end(self) -> None:
        """The end of the records: the trajectory carried ends."""
        if self._carry is not None:
            carry, self._carry = self._carry, None
            self._sums(carry, open_length=self._started)
            self._started = False

    def _sums(self, records: Records, open_length: bool = False) -> None:
        """Add the spans of whole trajectories (`open_length`: of their rest)."""
        assert records.t is not None
        if not len(records.group):
            return
        N = len(self.count)
        spans = _velocity_spans(records, open_length)
        self.span = max(self.span, *spans, 0)
        for k in range(N):
            self._add(k, records, spans)

    def _add(self, k: int, records: Records, spans: dict[int, npt.NDArray[np.intp]]) -> None:
        """Add the spans of coordinate `k`."""
        assert records.t is not None
        N, t = len(self.count), records.t
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            x, rate = records.X[:, k], records.X[:, N + k]
            # the integral of the velocity from each trajectory's start (the trapezoids
            # after its last sample, into the next one, are left out)
            pieces = np.diff(t) * (rate[1:] + rate[:-1]) / 2
            pieces[np.diff(records.group) != 0] = 0.0
            integral = np.concatenate([[0.0], np.cumsum(pieces)])
            # Simpson's rule over each two steps from each sample, uneven steps allowed
            # (those across trajectories are never taken: spans stay within one)
            h0, h1 = np.diff(t)[:-1], np.diff(t)[1:]
            pairs = (h0 + h1) / 6 * ((2 - h1 / h0) * rate[:-2]
                                     + (h0 + h1) ** 2 / (h0 * h1) * rate[1:-1]
                                     + (2 - h0 / h1) * rate[2:])
            for length, first in spans.items():   # not finite: no warning (`warnings`)
                a = x[first + length] - x[first]
                if length % 2:
                    over = integral[first + length] - integral[first]
                else:
                    over = sum(pairs[first + step] for step in range(0, length, 2))
                B = np.column_stack([over, rate[first + length] - rate[first]])
                self.normal[k] += B.T @ B
                self.right[k] += B.T @ a
                self.squares[k] += float(a @ a)
                self.count[k] += len(a)

    def warnings(self, coordinates: Sequence[str], velocities: Sequence[str],
                 mapping: Mapping[str, str], period: float | None) -> list[str]:
        """What the sums say of each coordinate's velocity column, with what to do."""
        return [finding.text + (DERIVE_ADVICE if finding.disagrees else "")
                for finding in self.findings(coordinates, velocities, mapping, period)]

    def findings(self, coordinates: Sequence[str], velocities: Sequence[str],
                 mapping: Mapping[str, str], period: float | None) -> list[VelocityFinding]:
        """What the sums say of each coordinate's velocity column."""
        findings = []
        for k, (q, v) in enumerate(zip(coordinates, velocities, strict=True)):
            normal, right = self.normal[k], self.right[k]
            if normal[0, 0] <= 0 or not np.all(np.isfinite(normal)):
                continue
            with np.errstate(all="ignore"):
                ratio = right[0] / normal[0, 0]
                fit = np.linalg.lstsq(normal, right, rcond=1e-12)[0]
            if not np.isfinite(ratio):
                continue
            name_q, name_v = mapping.get(q, q), mapping.get(v, v)
            if not 1 / VELOCITY_RATIO <= ratio <= VELOCITY_RATIO:
                findings.append(VelocityFinding(v, (
                    f"the positions {name_q!r} change {ratio:.3g} times as fast as the "
                    f"velocities {name_v!r} say: are the units mixed (mm with m/s) or "
                    "the time unit wrong? Give --time-unit, or --scale COL=FACTOR"), False))
                continue
            if self.count[k] < JUDGED_SPANS:
                continue
            gain, lag = float(fit[0]), float(fit[1] / fit[0])
            # standard errors from the residuals, the overlap of the spans counted
            residual = (max(float(self.squares[k]) - float(fit @ right), 0.0)
                        / max(int(self.count[k]) - 2, 1))
            with np.errstate(all="ignore"):
                inverse = np.abs(np.diag(np.linalg.pinv(normal)))
                gain_error, lag_error = np.sqrt(residual * inverse * self.span)
                lag_error /= abs(fit[0])
            said = []
            # the velocities are 1 / gain of the positions' rate of change
            if (np.isfinite(gain) and abs(gain - 1) > GAIN_TOLERANCE
                    and abs(gain - 1) > LAG_SIGNIFICANCE * gain_error):
                said.append(f"are {abs(1 / gain - 1):.2%} {'smaller' if gain > 1 else 'larger'}"
                            f" than the rate of change of the positions {name_q!r}")
            if (period and np.isfinite(lag) and abs(lag) > LAG_SIGNIFICANCE * lag_error
                    and math.pi * abs(lag) / period > LAG_DAMPING_RATIO):
                said.append(
                    f"{'lag behind' if lag > 0 else 'run ahead of'} the positions {name_q!r} "
                    f"by {abs(lag):.3g} s ({abs(lag) / period:.2g} of a period), which acts "
                    f"like a damping ratio of {'+' if lag < 0 else '-'}"
                    f"{math.pi * abs(lag) / period:.2g}")
            if said:
                findings.append(VelocityFinding(v, (
                    f"the velocities {name_v!r} {' and '.join(said)} (a channel filtered, "
                    "scaled or derived before recording?); it biases the estimates"), True))
        return findings


# What a fit says after a disagreeing velocity column: to derive the velocities, where it
# keeps the column (--velocity measured, a file read in chunks); that it set the column
# aside, where --velocity auto did.
DERIVE_ADVICE = "; derive the velocities with --velocity savgol"
SET_ASIDE = ("; so they are set aside: the velocities are derived from the positions, and "
             "the trajectory refinement fits the positions alone (--velocity measured fits "
             "them as recorded)")


# A sampled input with more than NYQUIST_SHARE of its power above NYQUIST_BAND times the
# Nyquist frequency is not resolved by its sampling: what lies beyond the Nyquist frequency
# folds back (aliases), and the interpolation between samples, which the fits and the
# refinement assume smooth, misses it. White noise puts 1 - NYQUIST_BAND of its power
# there; an anti-aliased DAQ record, or a band well inside the Nyquist frequency, almost none.
NYQUIST_BAND = 0.8
NYQUIST_SHARE = 0.05
_TOP_SHARE = 0.99   # the top frequency said: the one below which this share of power lies


def nyquist_warning(name: str, values: npt.NDArray[np.float64], records: Records
                    ) -> str | None:
    """A one-line warning when the sampled input `name` (`values`, one per row of
    `records`) holds more than NYQUIST_SHARE of its power near the Nyquist frequency of
    the sampling (above NYQUIST_BAND of it), else None. Its power spectrum is that of
    each trajectory less its mean, Hann-windowed (so that strong low frequencies leak
    little power up to it), summed; the sampling step is the median one."""
    assert records.t is not None
    steps = np.concatenate([np.diff(records.t[a:b]) for a, b in records.bounds()])
    if not len(steps) or not np.median(steps) > 0:
        return None
    dt = float(np.median(steps))
    nyquist = 1 / (2 * dt)
    bins = np.linspace(0.0, nyquist, 201)
    power = np.zeros(len(bins) - 1)
    for a, b in records.bounds():
        segment = values[a:b][np.isfinite(values[a:b])]
        if len(segment) < 4:
            continue
        windowed = (segment - segment.mean()) * np.hanning(len(segment))
        spectrum = np.abs(np.fft.rfft(windowed)) ** 2
        frequencies = np.fft.rfftfreq(len(segment), dt)
        power += np.histogram(frequencies, bins, weights=spectrum)[0]
    total = power.sum()
    share = power[bins[:-1] >= NYQUIST_BAND * nyquist].sum() / total if total > 0 else 0.0
    if not share > NYQUIST_SHARE:
        return None
    top = bins[1 + int(np.searchsorted(np.cumsum(power) / total, _TOP_SHARE))]
    return (f"input {name!r} has {100 * share:.3g}% of its power above "
            f"{NYQUIST_BAND * nyquist:.4g} Hz, up to {top:.4g} Hz, near the Nyquist frequency "
            f"{nyquist:.4g} Hz of its sampling (dt = {dt:.4g} s): what lies beyond it is "
            "aliased and the interpolation between samples misses it (sample faster, or "
            "low-pass filter the input before sampling)")


def nyquist_warnings(names: Sequence[str], records: Records) -> list[str]:
    """The `nyquist_warning` of each recorded input (`records.U`, columns in `names`)."""
    if records.U is None:
        return []
    return [warning for name, values in zip(names, records.U.T, strict=True)
            if (warning := nyquist_warning(name, values, records)) is not None]
