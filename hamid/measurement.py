"""What the recording itself tells about its errors: noise levels and derived velocities."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from hamid.errors import DataError, UsageError

__all__ = ["DIFFERENCE_ORDER", "estimate_noise", "savgol_velocities"]

# Differences of this order remove a smooth signal (its k-th difference is ~ (w dt)^k) and
# keep white noise, scaled by sqrt(C(2k, k)).
DIFFERENCE_ORDER = 4
_MAD_TO_SIGMA = 1.4826  # median absolute deviation of a Gaussian, in standard deviations


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
    # one array of differences, reordered in place by the medians (a column's order does
    # not change its median): no copy of the record's size
    differences = np.empty((sum(b - a - k for a, b in usable), X.shape[1]))
    row = 0
    for a, b in usable:
        differences[row:row + b - a - k] = np.diff(X[a:b], n=k, axis=0)
        row += b - a - k
    differences -= np.median(differences, axis=0, overwrite_input=True)
    mad = np.median(np.abs(differences, out=differences), axis=0, overwrite_input=True)
    return _MAD_TO_SIGMA * mad / math.sqrt(math.comb(2 * k, k))


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
    V = np.empty_like(Q)
    gain = 0.0
    for a, b in bounds:
        t_j = t[a:b]
        if b - a < window:
            raise DataError(f"a trajectory of {b - a} samples is shorter than the "
                            f"Savitzky-Golay window of {window}; use a smaller --window")
        step = np.diff(t_j)
        dt = float(np.mean(step))
        if not np.allclose(step, dt, rtol=1e-6, atol=0):
            row = int(np.argmax(np.abs(step - dt) > 1e-6 * dt)) + a + 2
            raise DataError(f"--velocity savgol needs evenly sampled times; the time step "
                            f"changes at row {row} ({step.min():g} to {step.max():g})")
        V[a:b] = savgol_filter(Q[a:b], window, order, deriv=1, delta=dt, axis=0,
                               mode="interp")
        gain = max(gain, float(np.linalg.norm(savgol_coeffs(window, order, deriv=1,
                                                            delta=dt))))
    return V, gain


def default_savgol_window(period_samples: float | None, order: int) -> int:
    """An odd window of about a tenth of the dominant period, and at least order + 2."""
    target = 11 if period_samples is None else int(round(period_samples / 10))
    window = max(target, order + 2)
    return window if window % 2 else window + 1
