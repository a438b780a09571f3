"""Prediction: the fitted model integrated over each trajectory of a recording and set beside
it (`hamid predict`, `FitResult.predict`), the check of a fit on records it never saw.

Each trajectory is integrated from its own initial state by the equations of
`hamid.model.dynamics` at the fit's estimates (the energy's and the damping's, as
`FitResult.simulate` takes them). The start is either

- fitted (the default): the state at the trajectory's first sample that, integrated with
  the parameters held, fits the recorded samples of its first segment best (`fit_start`),
  in the squares the refinement minimises (each recorded channel weighted by its noise
  level, an acceleration compared with the equations of motion at the integrated state;
  channels not recorded not at all). The segment is one dominant period of the trajectory, at
  least `START_SAMPLES` samples: short, so that the model's error over the record (what
  the prediction measures) hardly leaks into the start, yet every phase of one swing and
  a score of samples pin the state and average its noise;
- at rest (`from_rest`): the zero state, for records that start at rest.

Per recorded channel (each coordinate's position, velocity and acceleration that the data
hold; those reconstructed or derived from them are predicted but not scored, as the
refinement does not fit them) the prediction reports the RMS error
and the normalized RMS error NRMSE = RMS(predicted - recorded) / RMS(recorded - mean of
recorded), both over the same samples (all of a trajectory's, or all of the recording's
for the whole), the samples of the start segment included: 0 is a perfect prediction, 1
no better than the recorded mean. The report is `Prediction.to_dict()`, schema
``hamid.predict/1`` (hamid/schema/predict-1.json, docs/output.md).

The integration of one trajectory is described by an `Integration`: for a driven model its
recorded inputs are one more field, a function of the trajectory's time (`Integration.over`).
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from hamid import safe_text
from hamid.data import input_size, loading, measurement
from hamid.data.records import Recording, Records
from hamid.errors import DataError, ModelError, UsageError
from hamid.linear import design
from hamid.model.dynamics import Dynamics, Inputs, Motion
from hamid.model.models import model_from_info
from hamid.options import TIME_UNITS, FitOptions
from hamid.refine.integration import SampledInputs
from hamid.refine.joint_refinement import channel_weights
from hamid.refine.trajectory import STEP

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["FORMATS", "SCHEMA", "START_SAMPLES", "Integration", "Prediction", "fit_start",
           "fitted_dynamics", "noise_levels", "predict", "read", "start_weights"]

Array = npt.NDArray[np.float64]
SCHEMA = "hamid.predict/1"
FORMATS = ("table", "json", "csv")
# The fewest samples a start state is fitted to (the unknowns are the 2N variables).
START_SAMPLES = 20
# The motion escapes when a variable passes this many times its largest recorded value.
ESCAPE = 1e3
_ITERATIONS = 10   # Gauss-Newton steps of `fit_start`; three or four usually settle it
_RTOL = 1e-10


def read(report: Mapping[str, Any], data: Any,
         reading: Mapping[str, Any] | None = None) -> Recording:
    """The records of `data` read as the fit of `report` read them: the reading options it
    records, its columns, time column and unit, scale factors and velocities. `reading`
    (`hamid.fit`'s reading keywords) overrides what the report records, for data that
    moved or were converted."""
    info = report["model"]
    model = model_from_info(info, where="the report's model")
    recorded = report["data"]
    unit = recorded.get("time_unit")
    savgol = recorded["velocity_source"] == "savgol"
    # columns found under the model's own names are looked for so again, so that a
    # recording of other channels (accelerations where the fit had positions) is read
    renamed = {name: column for name, column in recorded["columns"].items() if name != column}
    resolved = {"columns": renamed or None, "time": recorded.get("time"),
                "time_unit": unit if unit in TIME_UNITS else None,
                "scale": recorded.get("scale") or None}
    options = FitOptions(**{**recorded.get("reading", {}), **resolved, **(reading or {})},
                         velocity=recorded["velocity_source"],
                         window=recorded.get("velocity_window") if savgol else None,
                         order=recorded.get("velocity_order", 5) if savgol else 5,
                         damping="none")
    loaded = loading.load(data, model, options)
    return Recording(model, loaded.records, loaded.channels)


def noise_levels(report: Mapping[str, Any], recording: Recording) -> Array:
    """The noise standard deviation of each model variable: given to the fit, else
    estimated from the records' differences (`measurement.estimate_noise`)."""
    records = recording.records
    sigma = measurement.estimate_noise(records.X, records.bounds())
    given = report["method"].get("noise") or {}
    return np.array([given.get(name) or s for name, s in zip(recording.model.variables, sigma,
                                                              strict=True)])


def fitted_dynamics(report: Mapping[str, Any], recording: Recording) -> tuple[Dynamics, Array]:
    """Lagrange's equations of the report's model and its weights at the estimates: the
    energy's parameters and the damping's (the model's own dissipation function and the
    --damping terms)."""
    model = recording.model
    dissipation = model.dissipative(report["method"]["damping"])
    estimate = {p["name"]: p["estimate"] for p in report["parameters"]}
    return Dynamics(model, dissipation), np.array(
        [1.0, *(estimate[name] for name in (*model.parameters, *dissipation.names))])


@dataclass(frozen=True)
class Integration:
    """How the fitted model is integrated over one trajectory: its equations at the fitted
    weights, each variable's scale (the larger of its recorded extent and spread), which
    sets the absolute tolerance, the finite-difference step of `fit_start` and the escape
    bound, and for a driven model the trajectory's recorded inputs as functions of its time
    (`over`)."""

    dynamics: Dynamics
    weights: Array
    scale: Array
    inputs: Inputs | None = None

    @classmethod
    def of(cls, report: Mapping[str, Any], recording: Recording) -> Integration:
        """The fitted model of `report` at the scales of `recording`'s variables."""
        records = recording.records
        return cls(*fitted_dynamics(report, recording),
                   np.maximum(np.maximum(records.extent, records.spread),
                              np.finfo(float).tiny))

    def over(self, records: Records, start: int, stop: int) -> Integration:
        """The integration of the trajectory in rows start:stop, driven by its recorded
        inputs, a cubic spline between the samples as in the refinement
        (`hamid.refine.integration.SampledInputs`); a free model's is this one."""
        if records.U is None:
            return self
        assert records.t is not None
        t = records.t[start:stop]
        inputs = SampledInputs([t - t[0]], [records.U[start:stop]])
        return dataclasses.replace(self, inputs=inputs.path(1, 0.0))

    @cached_property
    def motion(self) -> Motion:
        return self.dynamics.at(self.weights, inputs=self.inputs)

    def observed(self, Y: Array, tau: Array, accelerations: bool) -> Array:
        """The channels of the motion `Y` (2N, k, len(tau)) as a recording holds them: the
        states, then with `accelerations` the accelerations its equations give there."""
        if not accelerations:
            return Y
        rates = np.stack([self.motion(float(s), Y[:, :, i].ravel()).reshape(Y.shape[:2])
                          for i, s in enumerate(tau)], axis=-1)
        return np.concatenate([Y, rates[Y.shape[0] // 2:]])

    @property
    def step(self) -> Array:
        """The forward-difference step of each variable of the start state."""
        return STEP * self.scale

    def run(self, starts: Array, tau: Array) -> tuple[Array, float | None]:
        """The motion from each start (rows of `starts`, shape (k, 2N)), integrated together
        and sampled at `tau` (from 0): shape (2N, k, len(tau)), and None; or, when the motion
        escapes (past `ESCAPE` times a variable's scale, or no longer finite), what was
        sampled and the time it escaped near."""
        from scipy.integrate import solve_ivp

        bound = np.repeat(ESCAPE * self.scale, len(starts))

        def escape(t: float, y: Array) -> float:
            return float(np.min(bound - np.abs(y)))

        escape.terminal = True  # type: ignore[attr-defined]
        with np.errstate(all="ignore"):
            solution = solve_ivp(self.motion, (0.0, float(tau[-1])), starts.T.ravel(),
                                 method="DOP853", t_eval=tau, rtol=_RTOL,
                                 atol=np.repeat(1e-3 * self.step, len(starts)), events=escape)
        Y = np.reshape(solution.y, (-1, len(starts), len(solution.t)))
        finite = np.all(np.isfinite(Y), axis=(0, 1))
        if solution.status == 0 and len(solution.t) == len(tau) and finite.all():
            return Y, None
        if solution.status == 1:
            return Y, float(solution.t_events[0][0])
        kept = int(np.argmin(finite)) if not finite.all() else len(solution.t)
        return Y, float(tau[min(kept, len(tau) - 1)])


def start_weights(report: Mapping[str, Any], recording: Recording) -> Array:
    """The weight of each compared channel (`Recording.compared`) in `fit_start`'s
    squares, as the refinement weighs it (`channel_weights`: one over its noise level,
    0 for channels not recorded)."""
    records = recording.records
    _, recorded = recording.compared
    sigma = noise_levels(report, recording)
    if records.A is not None:
        sigma = np.concatenate([sigma, measurement.estimate_noise(records.A,
                                                                  records.bounds())])
    return channel_weights(sigma, records.compared_spread, recorded)


def fit_start(integration: Integration, tau: Array, recorded: Array, weight: Array, *,
              label: str) -> Array:
    """The initial state whose motion fits `recorded` (samples at `tau` from 0 of the
    compared channels, `Records.compared`: shape (len(tau), 2N), or 3N with accelerations)
    best in the squares weighted by `weight` per channel, the parameters held: Gauss-Newton
    from the first sample, each step integrating the state and its 2N perturbed copies
    together, as the refinement does (they share the adaptive steps). `label` names the
    trajectory in the error when the motion cannot be integrated."""
    n_states = len(integration.scale)
    accelerations = recorded.shape[1] > n_states
    step = integration.step
    x0 = recorded[0, :n_states].copy()
    for _ in range(_ITERATIONS):
        Y, failed = integration.run(np.vstack([x0, x0 + np.diag(step)]), tau)
        if failed is not None:
            raise ModelError(f"{label}: the fitted model's motion escapes (past {ESCAPE:g} "
                             f"times the recorded values, or no longer finite) near "
                             f"{failed:.6g} s after its first sample, in the segment its start "
                             "state is fitted to; the model does not hold there")
        C = integration.observed(Y, tau, accelerations)
        residual = ((recorded.T - C[:, 0]) * weight[:, None]).ravel()
        J = (C[:, 1:] - C[:, :1]) / step[None, :, None] * weight[:, None, None]
        d_x = np.linalg.lstsq(J.transpose(0, 2, 1).reshape(-1, n_states), residual,
                              rcond=None)[0]
        x0 = x0 + d_x
        if np.all(np.abs(d_x) <= 10 * step):
            break
    return x0


@dataclass(frozen=True)
class Prediction:
    """The fitted model's motion beside the recorded one.

    frame : pandas.DataFrame
        ``trajectory``, ``t``, then each channel recorded (``x``) and predicted
        (``x_predicted``): the model variables, and the accelerations when the data hold
        any; a channel not recorded has only its prediction. A row per sample.
    document : dict
        The report of schema ``hamid.predict/1`` (`to_dict`).
    """

    frame: pd.DataFrame
    document: dict[str, Any]

    @property
    def channels(self) -> pd.DataFrame:
        """RMS error and NRMSE of each channel over the whole recording, indexed by name."""
        import pandas as pd

        return pd.DataFrame.from_dict(self.document["channels"], orient="index",
                                      dtype=float)

    def to_dict(self) -> dict[str, Any]:
        """The report of schema ``hamid.predict/1`` (docs/output.md)."""
        return self.document

    def render(self, format: str, *, color: bool = False) -> str:
        """The prediction as text: ``table`` (the errors, for a terminal), ``json`` (the
        report) or ``csv`` (the time series of `frame`)."""
        if format == "json":
            return json.dumps(self.document, indent=2, allow_nan=False,
                              ensure_ascii=True) + "\n"
        if format == "csv":
            return self.frame.to_csv(index=False, lineterminator="\n")
        if format == "table":
            return _table(self.document, color)
        raise UsageError(f"unknown predict format {format!r} (choose from "
                         f"{', '.join(FORMATS)})")


def predict(report: Mapping[str, Any], data: Any, reading: Mapping[str, Any] | None = None,
            *, from_rest: bool = False, source: str | None = None) -> Prediction:
    """The fitted model of `report` (a ``hamid.fit/1`` dict) over every trajectory of `data`
    (files or a DataFrame, read as `read` reads them), from each trajectory's fitted start
    state or, with `from_rest`, from rest. `source` names the report's file in the output."""
    import pandas as pd

    from hamid import __version__

    recording = read(report, data, reading)
    model, records = recording.model, recording.records
    if records.t is None:
        raise DataError(f"{_names(data)}: no time column; a prediction integrates over time "
                        "(give --time COL)")
    whole = Integration.of(report, recording)
    weight = start_weights(report, recording)
    names, scored = recording.compared
    kept = [name for name, keep in zip(names, scored, strict=True) if keep]
    scales = design.trajectory_scales(records, len(model.coordinates))
    compared = records.compared
    predicted = np.empty_like(compared)
    entries = []
    for j, (start, stop) in enumerate(records.bounds()):
        label = f"trajectory {safe_text.printable(str(records.labels[j]))}"
        t = records.t[start:stop]
        tau, recorded = t - t[0], compared[start:stop]
        integration = whole.over(records, start, stop)
        if from_rest:
            x0, fitted_on = np.zeros(len(model.variables)), None
        else:
            fitted_on = _start_samples(t, scales[j][0], label)
            x0 = fit_start(integration, tau[:fitted_on], recorded[:fitted_on], weight,
                           label=label)
        Y, failed = integration.run(x0[None, :], tau) if len(tau) > 1 else (x0[:, None, None],
                                                                            None)
        if failed is not None:
            raise ModelError(f"{label}: the fitted model's motion escapes (past {ESCAPE:g} "
                             f"times the recorded values, or no longer finite) near "
                             f"t = {t[0] + failed:.6g} s; the model does not hold there")
        predicted[start:stop] = integration.observed(Y, tau, records.A is not None)[:, 0].T
        entries.append({"trajectory": _label(records.labels[j]), "samples": stop - start,
                        "t_start": float(t[0]), "t_end": float(t[-1]),
                        "start": dict(zip(model.variables, x0.tolist(), strict=True)),
                        "start_samples": fitted_on,
                        "channels": _errors(recorded[:, scored], predicted[start:stop, scored],
                                            kept)})
    frame = pd.DataFrame({"trajectory": np.asarray(records.labels, dtype=object)[records.group],
                          "t": records.t})
    for i, name in enumerate(names):
        if scored[i]:
            frame[name] = compared[:, i]
        frame[f"{name}_predicted"] = predicted[:, i]
    document = {
        "schema": SCHEMA, "hamid_version": __version__, "source": source,
        "data": _sources(data), "model": report["model"]["name"],
        "start": "rest" if from_rest else "fitted", "samples": len(records.group),
        "channels": _errors(compared[:, scored], predicted[:, scored], kept),
        "not_recorded": [name for name in names if name not in kept],
        "trajectories": entries,
    }
    return Prediction(frame, document)


def _start_samples(t: Array, period: float | None, label: str) -> int:
    """Helper: the samples of a trajectory's first segment, to which its start is fitted."""
    if len(t) < START_SAMPLES:
        raise DataError(f"{label}: {len(t)} samples, too few to fit its start state (at "
                        f"least {START_SAMPLES}); give --from-rest if it starts at rest")
    within = int(np.searchsorted(t, t[0] + period, side="right")) if period else 0
    return max(START_SAMPLES, within)


def _errors(recorded: Array, predicted: Array,
            names: Sequence[str]) -> dict[str, dict[str, float | None]]:
    """Helper: RMS error and NRMSE (RMS error over the recorded RMS about its mean) of each
    column, by name; NRMSE None for a constant recorded column."""
    rms = np.sqrt(np.mean((predicted - recorded) ** 2, axis=0))
    spread = recorded.std(axis=0)
    return {name: {"rms": float(e), "nrmse": float(e / s) if s > 0 else None}
            for name, e, s in zip(names, rms, spread, strict=True)}


def _sources(data: Any) -> list[str]:
    """Helper: the data's names as given (a DataFrame has none)."""
    if input_size.in_memory_table(data) is not None:
        return []
    return [os.fspath(d) for d in ([data] if isinstance(data, str | os.PathLike) else data)]


def _names(data: Any) -> str:
    return ", ".join(_sources(data)) or "the data"


def _label(label: Any) -> str | int | float:
    """Helper: a trajectory's label as a JSON value (numpy scalars as Python's)."""
    return label.item() if hasattr(label, "item") else label


def _number(value: float | None) -> str:
    return "—" if value is None else f"{value:.4g}"


def _table(doc: Mapping[str, Any], color: bool) -> str:
    """Helper: the errors per channel, overall and per trajectory, as terminal tables."""
    from rich import box
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    buffer = io.StringIO()
    console = Console(file=buffer, width=100, color_system="standard" if color else None,
                      force_terminal=color, highlight=False, markup=False, emoji=False)

    def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> None:
        shown = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False,
                      collapse_padding=True, header_style="bold")
        for i, name in enumerate(header):
            shown.add_column(name, justify="left" if i == 0 else "right", overflow="fold")
        for row in rows:
            shown.add_row(*(Text(safe_text.printable(cell)) for cell in row))
        console.print(shown)

    start = ("from rest" if doc["start"] == "rest" else
             "from each trajectory's start state fitted to its first period")
    count = len(doc["trajectories"])
    console.print(Text(safe_text.printable(
        f"hamid predict — model {doc['model']}, "
        f"{safe_text.counted(count, 'trajectory', 'trajectories')}, {doc['samples']} samples, "
        f"{start}"), style="bold"))
    names = list(doc["channels"])
    table(("channel", "RMS error", "NRMSE"),
          [(name, _number(c["rms"]), _number(c["nrmse"])) for name, c in doc["channels"].items()])
    table(("trajectory", "samples", *(f"NRMSE {name}" for name in names)),
          [(str(entry["trajectory"]), str(entry["samples"]),
            *(_number(entry["channels"][name]["nrmse"]) for name in names))
           for entry in doc["trajectories"]])
    console.print(Text("NRMSE: RMS error / RMS of the recorded channel about its mean "
                       "(0 perfect, 1 no better than the mean)"))
    if doc.get("not_recorded"):
        console.print(Text(safe_text.printable(
            f"not recorded, so predicted but not scored: {', '.join(doc['not_recorded'])}")))
    return "\n".join(row.rstrip() for row in buffer.getvalue().splitlines()) + "\n"
