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

from hamid.data import loading, measurement
from hamid.data.records import Recording
from hamid.errors import DataError, FitError
from hamid.linear import design
from hamid.model.models import Model, model_from_info
from hamid.options import TIME_UNITS, FitOptions

__all__ = ["Energies", "Segment", "energies", "lowest_energy", "noise_levels",
           "read_recording", "segment_motion"]

Array = npt.NDArray[np.float64]
# Recorded configurations of the other coordinates over which `lowest_energy` minimises.
_CONFIGURATIONS = 32
_ITERATIONS = 10   # Gauss-Newton steps of `segment_motion`; three or four usually settle it


def read_recording(report: Mapping[str, Any], data: Sequence[str],
                   reading: Mapping[str, Any] | None = None) -> Recording:
    """The records of `data` read as the fit of `report` read them (the reading options it
    records, its columns, time column and unit, scale factors and velocities), checked to
    be as many samples and trajectories as the fit had. `reading` (`hamid.fit`'s reading
    keywords) overrides what the report records, for data that moved or were converted."""
    info = report["model"]
    model = model_from_info(info, where="the report's model")
    read = report["data"]
    unit = read.get("time_unit")
    savgol = read["velocity_source"] == "savgol"
    resolved = {"columns": read["columns"], "time": read.get("time"),
                "time_unit": unit if unit in TIME_UNITS else None,
                "scale": read.get("scale") or None}
    options = FitOptions(**{**read.get("reading", {}), **resolved, **(reading or {})},
                         velocity=read["velocity_source"],
                         window=read.get("velocity_window") if savgol else None,
                         order=read.get("velocity_order", 5) if savgol else 5,
                         damping="none")
    records = loading.load(list(data), model, options).records
    found = (len(records.group), records.n_trajectories)
    fitted = (read["n_samples"], read["n_trajectories"])
    if found != fitted:
        raise DataError(f"{', '.join(data)}: {found[0]} samples in {found[1]} trajectories, "
                        f"but the fit had {fitted[0]} in {fitted[1]}: give the files the fit "
                        "read (with the trajectory column, delimiter and gap policy it had)")
    return Recording(model, records)


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


def noise_levels(report: Mapping[str, Any], recording: Recording) -> Array:
    """The noise standard deviation of each model variable: given to the fit, else
    estimated from the records' differences (`measurement.estimate_noise`)."""
    records = recording.records
    sigma = measurement.estimate_noise(records.X, records.bounds())
    given = report["method"].get("noise") or {}
    return np.array([given.get(name) or s for name, s in zip(recording.model.variables, sigma,
                                                              strict=True)])


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


@dataclass(frozen=True)
class Segment:
    """One trajectory's first refinement segment: times (s), the recorded states and the
    fitted model's motion from the initial state that fits them best."""

    t: Array
    recorded: Array
    model: Array


def segment_motion(report: Mapping[str, Any], recording: Recording,
                   trajectory: int) -> Segment:
    """The fitted model integrated over the first segment of a trajectory (the length of
    the refinement's segments), from the initial state that fits the recorded samples best
    in the noise-weighted squares the refinement minimised, the parameters held."""
    from scipy.integrate import solve_ivp

    from hamid.model.dynamics import Dynamics
    from hamid.refine.trajectory import NOISE_FLOOR, STEP

    model, records = recording.model, recording.records
    assert records.t is not None
    start, stop = records.bounds()[trajectory]
    t = records.t[start:stop]
    length = report["method"]["refinement"]["segment_seconds"]
    stop = start + max(int(np.searchsorted(t, t[0] + length, side="right")), 2)
    tau, recorded = records.t[start:stop] - records.t[start], records.X[start:stop]
    dissipation = model.dissipative(report["method"]["damping"])
    damping = _values(report, "damping")
    motion = Dynamics(model, dissipation).at([1.0, *_theta(report, model),
                                              *(damping[name] for name in dissipation.names)])
    weight = 1.0 / np.maximum(noise_levels(report, recording), NOISE_FLOOR * records.spread)
    if report["data"]["velocity_source"] == "savgol":
        weight[len(model.coordinates):] = 0.0   # derived: no information of their own

    # Gauss-Newton over the initial state; each step integrates the state and its 2N
    # perturbed copies together, as the refinement does (they share the adaptive steps)
    n_states = recorded.shape[1]
    step = STEP * np.maximum(records.extent, records.spread)
    x0 = recorded[0].copy()
    for _ in range(_ITERATIONS):
        starts = np.vstack([x0, x0 + np.diag(step)])                 # (1 + 2N, 2N)
        solution = solve_ivp(motion, (0.0, tau[-1]), starts.T.ravel(), method="DOP853",
                             t_eval=tau, rtol=1e-10,
                             atol=np.repeat(1e-3 * step, len(starts)))
        if solution.status != 0 or solution.y.shape[1] != len(tau):
            raise FitError(f"trajectory {records.labels[trajectory]}: the fitted model "
                           f"cannot be integrated over its segment ({solution.message})")
        Y = solution.y.reshape(n_states, len(starts), len(tau))
        residual = ((recorded.T - Y[:, 0]) * weight[:, None]).ravel()
        J = ((Y[:, 1:] - Y[:, :1]) / step[None, :, None] * weight[:, None, None])
        d_x = np.linalg.lstsq(J.transpose(0, 2, 1).reshape(-1, n_states), residual,
                              rcond=None)[0]
        x0 = x0 + d_x
        if np.all(np.abs(d_x) <= 10 * step):
            break
    return Segment(records.t[start:stop], recorded, Y[:, 0].T)
