"""The fit result: fixed fields, one way out to plain data and one way back in, checked.

`FitResult.to_dict()` is the JSON report of schema ``hamid.fit/1``, described key by key
in docs/output.md and as a JSON Schema in hamid/schema/fit-1.json; `FitResult.from_dict`
checks a loaded report against that schema before building the result. The TypedDicts
below are the dict parts of a result, as the fit builds them.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Literal, NotRequired, TypedDict

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
    "MethodInfo",
    "ModelInfo",
    "NoiseLevel",
    "ParameterEstimate",
    "ProvenanceInfo",
    "RefinementInfo",
    "ResidualSummary",
    "SCHEMA",
    "percent",
    "plain_data",
]

SCHEMA = "hamid.fit/1"


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


class NoiseLevel(TypedDict):
    """The noise one variable was weighted by in the trajectory refinement."""

    sigma: float | None                  # None: not weighted (derived velocities)
    source: Literal["given", "differences", "residuals", "derived"]


class AcceptanceInfo(TypedDict):
    """Why the refinement was kept or not: its held-out check against the linear fit."""

    rule: Literal["held-out", "noise"]
    folds: NotRequired[int]              # the rest with the held-out rule
    linear_refitted: NotRequired[bool]
    held_out_linear: NotRequired[float]
    held_out_refined: NotRequired[float]
    t: NotRequired[float]
    t_limit: NotRequired[float]


class RefinementInfo(TypedDict):
    """Whether the trajectory refinement of `auto` ran; its figures, or why not."""

    applied: bool
    reason: NotRequired[str]             # when not applied
    segments: NotRequired[int]           # the rest when applied (or fitted and refused)
    segment_seconds: NotRequired[float]
    iterations: NotRequired[int]
    chi2_per_dof: NotRequired[float]
    noise_chi2_per_dof: NotRequired[float]
    noise: NotRequired[dict[str, NoiseLevel]]
    covariance: NotRequired[Literal["misfit-scaled", "sandwich"]]
    acceptance: NotRequired[AcceptanceInfo]


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


class ConditioningInfo(TypedDict):
    """Conditioning of the column-scaled design, levels included."""

    condition_number: float | None
    singular_values: list[float | None]
    weakest_direction: dict[str, float]
    status: Literal["ok", "moderate", "severe"]
    blocks: NotRequired[dict[str, float | None] | None]


class EnergyLost(TypedDict):
    """The share of one trajectory's energy dissipated over its record."""

    trajectory: str | int | float
    energy_lost_fraction: float | None


class DissipationInfo(TypedDict):
    """What a damped fit says of the energy lost."""

    trajectories: list[EnergyLost]
    equivalent_damping_ratio: float | None
    period: float | None


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
        from hamid import validation

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


def percent(level: float) -> str:
    """A confidence level as a percentage, e.g. 95%, never rounded to 100%.

    Decimal arithmetic on the level's shortest repr: 100 * 0.9 is 90.00000000000001 in
    binary, and 6 digits would turn 0.9999999999999999 into "100%".
    """
    from decimal import Decimal

    return f"{(Decimal(repr(float(level))) * 100).normalize():f}%"
