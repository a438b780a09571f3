"""The recording's own backbone: instantaneous amplitude and frequency of each free decay,
from zero-crossing periods (no Hilbert transform).

For one coordinate q of each trajectory, the signal is q − q* (q* the fitted well's
equilibrium). An up-crossing is where the signal rises through 0, counted only once it
goes on above +δ after being below −δ (hysteresis, δ three times the coordinate's noise
level estimated from differences, `hamid.data.measurement.estimate_noise`, so that noise
about zero adds no crossings); its time is interpolated linearly between the two samples
on either side of 0. Between two successive up-crossings lies one period: its frequency is
1 / (t_{k+1} − t_k), its amplitude half the peak-to-peak range of the samples within it,
its time the period's middle. A decay whose swing has sunk into the noise yields no more
points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from hamid.data.measurement import estimate_noise
from hamid.data.records import Records
from hamid.errors import DataError

__all__ = ["HYSTERESIS", "DecayPoints", "decay_points"]

Array = npt.NDArray[np.float64]
HYSTERESIS = 3.0   # noise levels the signal must pass on each side of zero


@dataclass(frozen=True)
class DecayPoints:
    """One trajectory's points: middle time, amplitude and frequency of each period."""

    trajectory: str | int
    t: Array
    amplitude: Array
    frequency: Array


def _up_crossings(t: Array, signal: Array, band: float) -> Array:
    """Times where `signal` rises through 0 between being below −band and above +band (the
    last rise through 0 before it passes +band)."""
    times: list[float] = []
    armed, rise = False, None
    for i in range(1, len(signal)):
        a, b = signal[i - 1], signal[i]
        if a < -band:
            armed, rise = True, None
        if armed and a < 0 <= b:
            rise = t[i - 1] + (t[i] - t[i - 1]) * (-a) / (b - a)
        if armed and rise is not None and b > band:
            times.append(rise)
            armed, rise = False, None
    return np.asarray(times, dtype=float)


def decay_points(records: Records, coordinate: int, equilibrium: float) -> list[DecayPoints]:
    """The amplitude and frequency of every recorded period of coordinate number
    `coordinate` about `equilibrium`, trajectory by trajectory."""
    if records.t is None:
        raise DataError("the data have no time column; the recorded backbone needs times "
                        "(give --time COL)")
    bounds = records.bounds()
    band = HYSTERESIS * float(estimate_noise(records.X[:, [coordinate]], bounds)[0])
    found = []
    for j, (start, stop) in enumerate(bounds):
        t, q = records.t[start:stop], records.X[start:stop, coordinate] - equilibrium
        crossings = _up_crossings(t, q, band)
        middle, amplitude, frequency = [], [], []
        for a, b in zip(crossings[:-1], crossings[1:], strict=True):
            inside = q[(t >= a) & (t <= b)]
            if len(inside) < 2:
                continue
            middle.append((a + b) / 2)
            amplitude.append((inside.max() - inside.min()) / 2)
            frequency.append(1.0 / (b - a))
        found.append(DecayPoints(records.labels[j], np.array(middle), np.array(amplitude),
                                 np.array(frequency)))
    return found
