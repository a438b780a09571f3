"""The fitted model on its recording: the numbers the figures draw (`hamid.plot.figures`).

Everything here is computed from a report (`FitResult.to_dict()`, schema ``hamid.fit/1``)
and the records the fit read, which the report does not hold: a fit in Python keeps them
on its result (`FitResult.recording`), and `hamid plot RESULT.json DATA...` reads them
again with the options the report records (`read_recording`). No matplotlib here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid import prediction
from hamid.data.records import Recording
from hamid.errors import DataError, FitError
from hamid.linear import design
from hamid.model.models import Model
from hamid.prediction import noise_levels
from hamid.safe_text import counted

__all__ = ["Energies", "Segment", "energies", "lowest_energy", "noise_levels",
           "read_recording", "segment_motion", "segment_seconds"]

Array = npt.NDArray[np.float64]
# Recorded configurations of the other coordinates over which `lowest_energy` minimises.
_CONFIGURATIONS = 32


def read_recording(report: Mapping[str, Any], data: Sequence[str],
                   reading: Mapping[str, Any] | None = None) -> Recording:
    """The records of `data` read as the fit of `report` read them (`prediction.read`),
    checked to be as many samples and trajectories as the fit had. `reading` (`hamid.fit`'s
    reading keywords) overrides what the report records, for data that moved or were
    converted."""
    recording = prediction.read(report, list(data), reading)
    records = recording.records
    found = (len(records.group), records.n_trajectories)
    fitted = (report["data"]["n_samples"], report["data"]["n_trajectories"])
    if found != fitted:
        raise DataError(f"{', '.join(data)}: {found[0]} samples in "
                        f"{counted(found[1], 'trajectory', 'trajectories')}, "
                        f"but the fit had {fitted[0]} in {fitted[1]}: give the files the fit "
                        "read (with the trajectory column, delimiter and gap policy it had)")
    return recording


def _values(report: Mapping[str, Any], role: str) -> dict[str, float]:
    """Helper: the estimates of the parameters of one role, by name."""
    return {p["name"]: p["estimate"] for p in report["parameters"] if p["role"] == role}


def _theta(report: Mapping[str, Any], model: Model) -> Array:
    energy = _values(report, "energy")
    return np.array([energy[name] for name in model.parameters])


@dataclass(frozen=True)
class Energies:
    """Per sample: the fitted energy E(x; theta), the level the energy balance asks of it
    (h minus the work dissipated so far), the energy residual, the standard deviation the
    measurement noise puts into E, and the time (s) or sample number."""

    time: Array
    energy: Array
    level: Array
    residual: Array
    noise: Array
    group: npt.NDArray[np.int64]


def energies(report: Mapping[str, Any], recording: Recording) -> Energies:
    """The fitted energies of every sample, with the noise band of docs/method.md's energy
    rows: the noise of each variable (estimated from the records as the refinement does,
    or the one the fit was given) carried into E by its gradient."""
    model, records = recording.model, recording.records
    damping = model.dissipative(report["method"]["damping"])
    rows = design.energy_block(model, records, damping)
    theta = _theta(report, model)
    n = len(model.parameters)
    damping_values = _values(report, "damping")
    work = rows.A[:, n:] @ np.array([damping_values[name] for name in damping.names]) \
        if damping.names else np.zeros(rows.n_rows)
    energy = rows.A[:, :n] @ theta - rows.b
    h = np.array([level["h"] for level in report["energy_levels"]])[records.group]
    sigma = noise_levels(report, recording)
    noise = np.sqrt(((model.energy_gradient(records.X, theta) * sigma) ** 2).sum(axis=1))
    return Energies(rows.time, energy, h - work, energy + work - h, noise, records.group)


def lowest_energy(report: Mapping[str, Any], recording: Recording, coordinate: int,
                  trajectory: int, q: Array, v: Array) -> Array:
    """The lowest fitted energy at each point (q, v) of one coordinate's phase plane,
    shape (len(v), len(q)), over the configurations of the other coordinates recorded on
    one trajectory, their velocities at rest.

    A trajectory at level h stays where this is at most h: its contour at h bounds the
    phase portrait (for one degree of freedom it is the orbit itself).
    """
    model, records = recording.model, recording.records
    N = len(model.coordinates)
    start, stop = records.bounds()[trajectory]
    picks = np.linspace(start, stop - 1, min(_CONFIGURATIONS, stop - start)).astype(int)
    others = records.X[picks] if N > 1 else records.X[picks[:1]]
    Q, V = np.meshgrid(q, v)
    X = np.zeros((len(others), Q.size, 2 * N))
    X[:, :, :N] = others[:, None, :N]
    X[:, :, coordinate] = Q.ravel()
    X[:, :, N + coordinate] = V.ravel()
    E = recording.model.total_energy(X.reshape(-1, 2 * N), _theta(report, model))
    return E.reshape(len(others), *Q.shape).min(axis=0)


def segment_seconds(report: Mapping[str, Any]) -> float | None:
    """The length of the refinement's longest segment in seconds: of the lengthened fit
    the estimates come from when it was lengthened, else of its first segments; None when
    the report gives none (the whole trajectory)."""
    refinement = report["method"]["refinement"]
    lengthened = (refinement.get("lengthening") or {}).get("segment_seconds")
    return lengthened if lengthened is not None else refinement.get("segment_seconds")


@dataclass(frozen=True)
class Segment:
    """The start of one trajectory, as long as the refinement's longest segment: times
    (s), the recorded states and the fitted model's motion from the initial state that
    fits them best."""

    t: Array
    recorded: Array
    model: Array


def segment_motion(report: Mapping[str, Any], recording: Recording,
                   trajectory: int) -> Segment:
    """The fitted model integrated over the start of a trajectory as long as the
    refinement's longest segment (`segment_seconds`: the lengthened record when the fit
    was lengthened), from the initial state that fits the recorded samples best
    in the noise-weighted squares the refinement minimised, the parameters held."""
    records = recording.records
    assert records.t is not None
    start, stop = records.bounds()[trajectory]
    t = records.t[start:stop]
    length = segment_seconds(report)
    if length is not None:
        stop = start + max(int(np.searchsorted(t, t[0] + length, side="right")), 2)
    tau, recorded = records.t[start:stop] - records.t[start], records.compared[start:stop]
    integration = prediction.Integration.of(report, recording).over(records, start, stop)
    x0 = prediction.fit_start(integration, tau, recorded,
                              prediction.start_weights(report, recording),
                              label=f"trajectory {records.labels[trajectory]}")
    Y, failed = integration.run(x0[None, :], tau)
    if failed is not None:
        raise FitError(f"trajectory {records.labels[trajectory]}: the fitted model cannot be "
                       f"integrated over its segment (it escapes near {failed:.6g} s)")
    return Segment(records.t[start:stop], records.X[start:stop], Y[:, 0].T)
