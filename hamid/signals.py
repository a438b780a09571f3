"""The input signals of a simulated driven system: ``[forcing.signals.NAME]`` tables.

Each signal is a function of time evaluated exactly wherever the integrator asks (no
sampling, no hold), so that a simulated record of a driven system is the system's own
response to a known input:

- ``sine``: amplitude (peak), frequency (Hz), phase (rad, default 0);
- ``sweep``: amplitude (peak), f0, f1 (Hz), duration (s, default the run's t_end), law
  ``"linear"`` or ``"log"``: a phase-continuous chirp, the instantaneous frequency going
  from f0 at t = 0 to f1 at t = duration, and on by the same law after it
  (scipy.signal.chirp's formulas);
- ``multisine``: amplitude (the RMS of the whole signal), band = [f_lo, f_hi] (Hz), seed
  (default 0): equal components at every frequency k / t_end in the band, random phases;
- ``noise``: amplitude (RMS), band, seed: band-limited noise as a sum of sines at the
  frequencies k / t_end in the band with Rayleigh amplitudes and random phases (a
  Gaussian process's spectral representation), scaled to the RMS asked for;
- ``file``: path (relative to the system file), column, and the file's time column
  (default t or time, as in a recording; a unit suffix such as time_ms is converted to
  seconds): a cubic spline (not-a-knot) through the samples, which must cover the run. A
  cubic spline, not a hold or a line, so that the input is smooth between samples, as a
  band-limited DAQ signal is, and the integrator's error control sees no kinks.
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.errors import HamidError, ModelError
from hamid.model.toml_values import check_keys, number, table

__all__ = ["KINDS", "MAX_COMPONENTS", "Signal", "signal"]

Array = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Signal:
    """An input signal: its value at t (a float or an array), and the highest frequency
    it holds over the run (Hz; None for a file's samples, whose spectrum is the sampled
    record's), which the sampling must resolve (`hamid.simulation`'s Nyquist warning)."""

    value: Callable[[Any], Any]
    top: float | None

    def __call__(self, t: Any) -> Any:
        return self.value(t)

KINDS = ("sine", "sweep", "multisine", "noise", "file")
# Sines of a multisine or noise: each is evaluated at every integrator stage.
MAX_COMPONENTS = 2000
_KEYS = {
    "sine": ("kind", "amplitude", "frequency", "phase"),
    "sweep": ("kind", "amplitude", "f0", "f1", "duration", "law"),
    "multisine": ("kind", "amplitude", "band", "seed"),
    "noise": ("kind", "amplitude", "band", "seed"),
    "file": ("kind", "path", "column", "time"),
}


def signal(entry: Any, *, t_end: float, where: str, folder: str | None = None) -> Signal:
    """The signal of one ``[forcing.signals.NAME]`` table, for a run of `t_end` seconds;
    `folder` is where a ``file`` signal's path is relative to."""
    entry = table(entry, where=where)
    kind = entry.get("kind")
    if kind not in KINDS:
        close = difflib.get_close_matches(str(kind), KINDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ModelError(f"{where}: kind {kind!r} is not a signal kind{hint}; choose one of "
                         f"{', '.join(KINDS)}")
    check_keys(entry, _KEYS[kind], where=where)
    if kind == "file":
        return Signal(_from_file(entry, t_end, where, folder), None)
    amplitude = number(_needed(entry, "amplitude", where), where=f"{where} amplitude",
                       non_negative=True)
    if kind == "sine":
        frequency = number(_needed(entry, "frequency", where), where=f"{where} frequency",
                           positive=True)
        phase = number(entry.get("phase", 0.0), where=f"{where} phase")
        return Signal(lambda t: amplitude * np.sin(2 * np.pi * frequency * np.asarray(t)
                                                   + phase), frequency)
    if kind == "sweep":
        return _sweep(entry, amplitude, t_end, where)
    return _sum_of_sines(entry, kind, amplitude, t_end, where)


def _needed(entry: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in entry:
        raise ModelError(f"{where}: missing key {key!r}")
    return entry[key]


def _sweep(entry: Mapping[str, Any], amplitude: float, t_end: float, where: str) -> Signal:
    f0 = number(_needed(entry, "f0", where), where=f"{where} f0", positive=True)
    f1 = number(_needed(entry, "f1", where), where=f"{where} f1", positive=True)
    duration = number(entry.get("duration", t_end), where=f"{where} duration", positive=True)
    law = entry.get("law", "linear")
    if law not in ("linear", "log"):
        raise ModelError(f"{where}: law {law!r} is not 'linear' or 'log'")
    # the frequency goes on by its law past `duration`: the highest is at 0 or at t_end
    if law == "linear":
        rate = (f1 - f0) / duration
        return Signal(lambda t: amplitude * np.sin(2 * np.pi * (f0 * np.asarray(t)
                                                                + rate * np.square(t) / 2)),
                      max(f0, abs(f0 + rate * t_end)))
    if f0 == f1:
        return Signal(lambda t: amplitude * np.sin(2 * np.pi * f0 * np.asarray(t)), f0)
    growth = np.log(f1 / f0) / duration
    top = max(f0, float(f0 * np.exp(growth * t_end)))
    return Signal(lambda t: amplitude * np.sin(2 * np.pi * f0 * np.expm1(growth * np.asarray(t))
                                               / growth), top)


def _sum_of_sines(entry: Mapping[str, Any], kind: str, amplitude: float, t_end: float,
                  where: str) -> Signal:
    band = _needed(entry, "band", where)
    if not (isinstance(band, list) and len(band) == 2):
        raise ModelError(f"{where}: band must be [f_lo, f_hi] in Hz")
    low = number(band[0], where=f"{where} band", non_negative=True)
    high = number(band[1], where=f"{where} band", positive=True)
    if not low < high:
        raise ModelError(f"{where}: band [{low:g}, {high:g}]: f_lo must be below f_hi")
    seed = entry.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ModelError(f"{where}: seed must be a non-negative integer")
    step = 1.0 / t_end
    first, last = max(int(np.ceil(low / step - 1e-9)), 1), int(np.floor(high / step + 1e-9))
    if last < first:
        raise ModelError(f"{where}: band [{low:g}, {high:g}] Hz holds no frequency of the "
                         f"run's grid (multiples of 1/t_end = {step:g} Hz); widen it or "
                         "lengthen the run")
    if last - first + 1 > MAX_COMPONENTS:
        raise ModelError(f"{where}: band [{low:g}, {high:g}] Hz holds "
                         f"{last - first + 1:,} frequencies of the run's grid (1/t_end = "
                         f"{step:g} Hz), more than {MAX_COMPONENTS:,}; narrow it")
    frequencies = step * np.arange(first, last + 1)
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0.0, 2 * np.pi, len(frequencies))
    sizes = (np.ones(len(frequencies)) if kind == "multisine"
             else rng.rayleigh(1.0, len(frequencies)))
    sizes *= amplitude / np.sqrt(np.sum(sizes**2) / 2)   # the sum's RMS is `amplitude`
    omega = 2 * np.pi * frequencies

    def value(t: Any) -> Any:
        t = np.asarray(t, dtype=np.float64)
        return np.sin(np.multiply.outer(t, omega) + phases) @ sizes

    return Signal(value, float(frequencies[-1]))


def _from_file(entry: Mapping[str, Any], t_end: float, where: str,
               folder: str | None) -> Callable[[Any], Any]:
    from scipy.interpolate import CubicSpline

    from hamid.data import column_roles, readers

    path, column = _needed(entry, "path", where), _needed(entry, "column", where)
    if not isinstance(path, str) or not isinstance(column, str):
        raise ModelError(f"{where}: path and column must be text")
    full = os.path.join(folder or ".", path)
    try:   # the reader's message (no such file, not a number, a gap) named by the key
        frame, _ = readers.read_columns(full, name=path)
        names = [str(c) for c in frame]
        time = entry.get("time") or column_roles.default_time_column(names)
        for wanted in (column, time):
            if wanted is None or wanted not in names:
                raise ModelError(f"{path} has no column {wanted or 't'!r} (columns: "
                                 f"{', '.join(names)})")
        t = readers.numeric_values(readers.column_values(frame[time]), time, path) \
            * column_roles.time_scale(time)[0]   # time_ms, Time [us]: in seconds
        values = readers.numeric_values(readers.column_values(frame[column]), column, path)
    except HamidError as error:
        raise ModelError(f"{where}: {error}") from None
    if len(t) < 4 or not np.all(np.diff(t) > 0):
        raise ModelError(f"{where}: {path}: the times must increase, at least 4 samples")
    if t[0] > 0 or t[-1] < t_end:
        raise ModelError(f"{where}: {path} covers t = {t[0]:g} to {t[-1]:g} s, not the "
                         f"run's 0 to {t_end:g} s")
    return CubicSpline(t, values)
