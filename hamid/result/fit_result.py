"""The fit result: fixed fields, one way out to plain data and one way back in, checked.

`FitResult.to_dict()` is the JSON report of schema ``hamid.fit/1``, described key by key
in docs/output.md and as a JSON Schema in hamid/schema/fit-1.json; `FitResult.from_dict`
checks a loaded report against that schema before building the result. The TypedDicts
below are the dict parts of a result, as the fit builds them; those of the trajectory
refinement (`RefinementInfo` and its parts) are the refinement's own (`hamid.refine.outcome`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Literal, NotRequired, TypedDict

from hamid.refine.outcome import AcceptanceInfo, LengtheningInfo, NoiseLevel, RefinementInfo
from hamid.result.validation import SCHEMA
from hamid.result.wording import method_name

if TYPE_CHECKING:
    import numpy.typing as npt
    import pandas as pd
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from hamid.data.records import Recording
    from hamid.prediction import Prediction

__all__ = [
    "AcceptanceInfo",
    "BlockResiduals",
    "ConditioningInfo",
    "CovarianceInfo",
    "DataInfo",
    "DissipationInfo",
    "DriftInfo",
    "EnergyLevel",
    "EnergyLost",
    "FitResult",
    "InputFile",
    "LengtheningInfo",
    "MethodInfo",
    "ModelInfo",
    "NoiseLevel",
    "ParameterEstimate",
    "ProvenanceInfo",
    "RefinementInfo",
    "ResidualSummary",
    "SCHEMA",
    "SkippedCheck",
    "StrongestCorrelation",
    "plain_data",
]



class ModelInfo(TypedDict):
    """The model fitted (`Model.info()`)."""

    name: str
    energy: str
    coordinates: list[str]
    velocities: list[str]
    parameters: list[str]


class DataInfo(TypedDict):
    """What was read: files, sizes, which column holds each model name."""

    sources: list[str]
    n_samples: int
    n_trajectories: int
    columns: dict[str, str]
    velocity_source: Literal["measured", "savgol"]
    velocity_window: NotRequired[int]   # with savgol: the filter's window, in samples
    velocity_order: NotRequired[int]    # and its polynomial order
    # per coordinate, the channels recorded and reconstructed (when not just positions and
    # velocities recorded)
    channels: NotRequired[dict[str, dict[str, list[str]]]]
    reading: NotRequired[dict[str, Any]]  # the reading options given (docs/output.md)


class MethodInfo(TypedDict):
    """How the fit was made (docs/method.md)."""

    kind: Literal["energy", "weak", "joint"]
    kind_reason: str
    weak_window: float | None
    damping: list[str]
    weighting: Literal["none", "noise"]
    noise: dict[str, float] | None
    weighting_rounds: NotRequired[int]
    bias_correction: bool
    covariance: Literal["classical", "hc", "hac", "bootstrap"]
    covariance_description: NotRequired[str]
    level: float
    fixed: dict[str, float]
    block_variance: NotRequired[dict[str, float] | None]
    refinement: NotRequired[RefinementInfo | None]


class DriftInfo(TypedDict):
    """The trend of one trajectory's energy residuals over its record."""

    trajectory: str | int | float
    relative_change: float | None
    trend_share: NotRequired[float | None]


class BlockResiduals(TypedDict):
    """Residual size of one block of rows (energy or weak)."""

    n_rows: int
    rms: float | None
    max_abs: float | None


class ResidualSummary(TypedDict):
    """Statistics of the energy residuals, and of each block's own residuals."""

    rms: float | None
    max_abs: float | None
    relative_rms: float | None
    r_squared: float | None
    lag1_autocorrelation: float | None
    drift: list[DriftInfo]
    blocks: NotRequired[dict[str, BlockResiduals]]


class StrongestCorrelation(TypedDict):
    """The two free parameters whose estimates are the most correlated."""

    parameters: list[str]
    correlation: float


class ConditioningInfo(TypedDict):
    """Conditioning of the column-scaled design, levels included."""

    condition_number: float | None
    singular_values: list[float | None]
    weakest_direction: dict[str, float]
    status: Literal["ok", "moderate", "severe"]
    blocks: NotRequired[dict[str, float | None] | None]
    strongest_correlation: NotRequired[StrongestCorrelation | None]


class EnergyLost(TypedDict):
    """The share of one trajectory's energy dissipated over its record."""

    trajectory: str | int | float
    energy_lost_fraction: float | None


class LinearModeInfo(TypedDict):
    """One mode of the model linearized about its equilibrium."""

    mode: int
    frequency_hz: float
    damping_ratio: float | None


class SmallAmplitudeInfo(TypedDict):
    """The model at small amplitude: its equilibrium and linear modes."""

    equilibrium: dict[str, float]
    modes: list[LinearModeInfo]


class DissipationInfo(TypedDict):
    """What a damped fit says of the energy lost and of its damping at small amplitude."""

    trajectories: list[EnergyLost]
    equivalent_damping_ratio: float | None
    period: float | None
    small_amplitude: NotRequired[SmallAmplitudeInfo | None]


class CovarianceInfo(TypedDict):
    """The covariance matrix of the free parameters' estimates, in the order of `names`
    (null for an entry that could not be computed)."""

    names: list[str]
    matrix: list[list[float | None]]


class InputFile(TypedDict):
    """One input: its name as read, size in bytes and SHA-256 (None for standard input or
    a DataFrame)."""

    path: str
    size: int | None
    sha256: str | None


class ProvenanceInfo(TypedDict):
    """Where the report came from: inputs, when (UTC, ISO 8601), the versions of the
    libraries that computed it, the bootstrap's seed and the command line (None from
    Python)."""

    inputs: list[InputFile]
    utc: str
    versions: dict[str, str | None]
    seed: int | None
    command: str | None


class SkippedCheck(TypedDict):
    """A check the fit could not make, and why (a file read in chunks cannot be checked
    where the check needs every sample in memory)."""

    check: str
    reason: str


@dataclass(frozen=True, slots=True)
class ParameterEstimate:
    """One parameter; `stderr` is None when it could not be computed (never 0)."""

    name: str
    role: str
    estimate: float
    stderr: float | None
    ci_low: float | None
    ci_high: float | None
    truth: float | None
    fixed: bool


@dataclass(frozen=True, slots=True)
class EnergyLevel:
    """A trajectory's fitted energy level h."""

    trajectory: str | int
    h: float
    stderr: float | None
    n_samples: int


@dataclass(frozen=True, slots=True)
class FitResult:
    """Everything `hamid fit` reports; `to_dict()` is the JSON report of docs/output.md."""

    hamid_version: str
    model: ModelInfo
    data: DataInfo
    method: MethodInfo
    parameters: tuple[ParameterEstimate, ...]
    energy_levels: tuple[EnergyLevel, ...]
    residuals: ResidualSummary
    conditioning: ConditioningInfo
    warnings: tuple[str, ...] = field(default=())
    dissipation: DissipationInfo | None = None
    # Optional keys of hamid.fit/1, absent from older reports (and then None here).
    covariance: CovarianceInfo | None = None
    provenance: ProvenanceInfo | None = None
    # Per-sample energy rows (trajectory, t, energy, residual, weight) for --residuals;
    # bulk data, so not part of the JSON nor of equality.
    samples: dict[str, Any] | None = field(default=None, compare=False, repr=False)
    # The model and records the fit read, for the panels over the data (`plot`); None for a
    # result read from a report or fitted in chunks. Not part of the JSON nor of equality.
    recording: Recording | None = field(default=None, compare=False, repr=False)
    # The checks the fit could not make (a file read in chunks), each {check, reason}.
    checks_skipped: tuple[SkippedCheck, ...] = field(default=())

    def __repr__(self) -> str:
        return (f"FitResult(model={self.model['name']!r}, method={method_name(self.method)!r}, "
                f"estimates={self.estimates!r}, warnings={len(self.warnings)})")

    def summary(self) -> str:
        """The result as a text block in the style of statsmodels' ``summary()``: key facts,
        the parameters and energy levels, then notes and warnings."""
        from hamid.report import formats

        return formats.render(self.to_dict(), "summary")

    def _repr_html_(self) -> str:
        """Parameters, levels, residuals, conditioning, method and warnings as HTML tables,
        for a notebook."""
        from hamid.report import formats

        return formats.render(self.to_dict(), "html")

    def to_frame(self) -> pd.DataFrame:
        """The parameters as a DataFrame indexed by name (role, estimate, stderr, ci_low,
        ci_high, truth, fixed); NaN where a value is unknown."""
        import pandas as pd

        frame = pd.DataFrame([asdict(p) for p in self.parameters]).set_index("name")
        numbers = ["estimate", "stderr", "ci_low", "ci_high", "truth"]
        frame[numbers] = frame[numbers].astype(float)
        return frame

    @property
    def cov(self) -> pd.DataFrame | None:
        """The covariance matrix of the free parameters' estimates (NaN where it could not
        be computed); None for a report written without it."""
        import pandas as pd

        if self.covariance is None:
            return None
        names = self.covariance["names"]
        return pd.DataFrame(self.covariance["matrix"], index=names, columns=names,
                            dtype=float)

    @property
    def correlation(self) -> pd.DataFrame | None:
        """The correlation matrix of the free parameters' estimates, from `cov`."""
        import numpy as np

        cov = self.cov
        if cov is None:
            return None
        sd = np.sqrt(np.diag(cov.to_numpy()))
        return cov / np.outer(sd, sd)

    def plot(self, panels: str | int | Sequence[str | int] | None = None,
             ax: Axes | None = None) -> Figure:
        """The fit's pictures as one matplotlib figure (needs ``hamid[plot]``).

        Parameters
        ----------
        panels : str, int or sequence, optional
            Panels by number or name: 1 ``energy``, 2 ``residuals``, 3 ``phase``, 4
            ``motion``, 5 ``parameters``, 6 ``correlation``, 7 ``backbone``
            (`hamid.plot.figures`); by default all of 1-6 that apply (1-4 need the records,
            which a result read from a report does not hold; 4 needs the trajectory
            refinement); 7 only when asked for.
        ax : matplotlib Axes, optional
            A subplot to draw one panel in, in place of it.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from hamid.plot import figures

        return figures.figure(self.to_dict(), self.recording, panels, ax)

    def simulate(self, initial: Mapping[str, float] | Sequence[Mapping[str, float]],
                 t: npt.ArrayLike) -> pd.DataFrame:
        """The fitted model's motion (damping included) from given initial states, by the
        simulator of `hamid.simulate`.

        Parameters
        ----------
        initial : dict or list of dicts
            Each trajectory's initial state: model variable -> value.
        t : array_like
            Evenly spaced sample times from 0 (t = k dt), e.g. ``numpy.arange(0, 20, 0.01)``.

        Returns
        -------
        pandas.DataFrame
            Columns ``trajectory``, ``t``, the coordinates and the velocities, as from
            `hamid.simulate`.
        """
        import numpy as np

        from hamid import simulation
        from hamid.errors import UsageError

        times = np.asarray(t, dtype=float)
        steps = np.diff(times)
        if times.ndim != 1 or len(times) < 2 or times[0] != 0 or steps[0] <= 0 \
                or not np.allclose(steps, steps[0], rtol=1e-9, atol=0):
            raise UsageError("simulate: t must be evenly spaced times from 0, e.g. "
                             "numpy.arange(0, 20, 0.01)")
        estimates = self.estimates
        system = {
            "model": {key: self.model[key] for key in ("name", "energy", "coordinates",
                                                         "velocities", "parameters")},
            "parameters": {name: estimates[name] for name in self.model["parameters"]},
            "damping": {**({"dissipation": own["function"], "parameters": own["parameters"]}
                           if (own := self.model.get("dissipation")) else {}),
                        **{p.name: p.estimate for p in self.parameters if p.role == "damping"}},
            "initial": [dict(initial)] if isinstance(initial, Mapping)
            else [dict(state) for state in initial],
            "simulate": {"t_end": float(times[-1]), "dt": float(steps[0])},
        }
        return next(simulation.sampled(system, where="the fitted model"))

    def predict(self, data: Any, *, from_rest: bool = False,
                **reading: Any) -> Prediction:
        """The fitted model (damping included) over every trajectory of `data`, from each
        trajectory's start state fitted to its first period (or from rest), beside the
        recorded motion: the check of a fit on records it never saw (`hamid.prediction`).

        Parameters
        ----------
        data : str, path, list of them, or pandas.DataFrame
            The recording, read as the fit read its own (`data.reading` of the report)
            unless `reading` (`hamid.fit`'s reading keywords: columns, time, ...) says
            otherwise.
        from_rest : bool, optional
            Start every trajectory from the zero state (a record that starts at rest).

        Returns
        -------
        hamid.prediction.Prediction
            ``.frame``: ``trajectory``, ``t``, each variable recorded and predicted
            (``x``, ``x_predicted``); ``.channels``: RMS error and NRMSE per variable;
            ``.to_dict()``: the ``hamid.predict/1`` report.
        """
        from hamid import prediction

        return prediction.predict(self.to_dict(), data, reading, from_rest=from_rest)

    def backbone(self, amplitudes: Sequence[float] | None = None,
                 energies: Sequence[float] | None = None, *, mode: int = 1,
                 coordinate: str | None = None, points: int = 25, data: Any = None,
                 **reading: Any) -> pd.DataFrame:
        """The fitted model's backbone: frequency (Hz) and equivalent damping ratio of its
        conservative orbits against amplitude, with bands at the fit's level
        (`hamid.backbone`).

        Parameters
        ----------
        amplitudes, energies : sequence of float, optional
            The orbits, by amplitude (half the peak-to-peak range of `coordinate`) or by
            level of the model's energy; neither: `points` amplitudes up to the largest
            recorded (`hamid.backbone.backbone_table`).
        mode : int
            The mode (1 for a model of one coordinate).
        data : str, path, list of them, or pandas.DataFrame, optional
            The recording, read as the fit read it unless `reading` says otherwise: its
            points (zero-crossing periods) go to the report, and its amplitudes set the
            default range.

        Returns
        -------
        pandas.DataFrame
            A row per point: ``mode``, ``energy``, ``amplitude_<q>``, ``frequency_hz``,
            ``frequency_hz_low``, ``frequency_hz_high``, ``damping_ratio``,
            ``damping_ratio_low``, ``damping_ratio_high``; the ``hamid.backbone/1`` report
            in ``.attrs["report"]``.
        """
        from hamid import prediction
        from hamid.backbone import backbone_table

        report = self.to_dict()
        records = None if data is None else prediction.read(report, data, reading).records
        request = backbone_table.Request(
            amplitudes=None if amplitudes is None else tuple(map(float, amplitudes)),
            energies=None if energies is None else tuple(map(float, energies)),
            mode=mode, coordinate=coordinate, points=points)
        document = backbone_table.backbone_report(backbone_table.Source.of_report(report),
                                                  request, records=records)
        table = backbone_table.frame(document)
        table.attrs["report"] = document
        return table

    @property
    def estimates(self) -> dict[str, float]:
        """Parameter name -> estimate."""
        return {p.name: p.estimate for p in self.parameters}

    def with_command(self, command: str | None) -> FitResult:
        """This result with `provenance.command` set (the CLI's command line)."""
        if self.provenance is None:
            return self
        return replace(self, provenance={**self.provenance, "command": command})

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data (built-in types; non-finite numbers become null)."""
        extra = {key: value for key, value in (("covariance", self.covariance),
                                                 ("provenance", self.provenance))
                 if value is not None}
        if self.checks_skipped:   # written only when a check was skipped
            extra["checks_skipped"] = list(self.checks_skipped)
        return plain_data({
            "schema": SCHEMA,
            "hamid_version": self.hamid_version,
            "model": self.model,
            "data": self.data,
            "method": self.method,
            "parameters": [asdict(p) for p in self.parameters],
            "energy_levels": [asdict(h) for h in self.energy_levels],
            "residuals": self.residuals,
            "conditioning": self.conditioning,
            "warnings": list(self.warnings),
            "dissipation": self.dissipation,
            **extra,
        })

    @classmethod
    def from_dict(cls, data: Any, *, source: str | None = None) -> FitResult:
        """The inverse of `to_dict`, checked (for `hamid report`, which never refits).

        Parameters
        ----------
        data : object
            A decoded JSON report of schema "hamid.fit/1".
        source : str, optional
            The file it was read from, named in the error message.

        Raises
        ------
        DataError
            `data` does not follow hamid/schema/fit-1.json; the one-line message names
            `source` and the key at fault.

        Keys that this version does not know are kept inside the dict parts (model, data,
        method, ...) and dropped at the top level and in parameters and energy levels.
        """
        from hamid.result import validation

        validation.check_result(data, source=source)
        return cls(
            hamid_version=data["hamid_version"],
            model=data["model"],
            data=data["data"],
            method=data["method"],
            parameters=tuple(ParameterEstimate(**_known(ParameterEstimate, p))
                             for p in data["parameters"]),
            energy_levels=tuple(EnergyLevel(**_known(EnergyLevel, h))
                                for h in data["energy_levels"]),
            residuals=data["residuals"],
            conditioning=data["conditioning"],
            warnings=tuple(data["warnings"]),
            dissipation=data.get("dissipation"),
            covariance=data.get("covariance"),
            provenance=data.get("provenance"),
            checks_skipped=tuple(data.get("checks_skipped", ())),
        )


def _known(kind: type, entry: dict[str, Any]) -> dict[str, Any]:
    """Helper: the keys of a report entry that are fields of `kind`."""
    names = {f.name for f in fields(kind)}
    return {k: v for k, v in entry.items() if k in names}


def plain_data(value: Any) -> Any:
    """Recursively turn numpy scalars into Python ones, tuples into lists and NaN/inf into
    None: what `to_dict` does to every part of a result."""
    if isinstance(value, dict):
        return {str(k): plain_data(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain_data(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value

