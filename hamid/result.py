"""The fit result: fixed fields, one way out to plain data (schema ``hamid.fit/1``)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

__all__ = ["SCHEMA", "EnergyLevel", "FitResult", "ParameterEstimate"]

SCHEMA = "hamid.fit/1"


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
    """Everything `hamid fit` reports; `to_dict()` is the JSON of SPEC section 4."""

    hamid_version: str
    model: dict[str, Any]
    data: dict[str, Any]
    method: dict[str, Any]
    parameters: tuple[ParameterEstimate, ...]
    energy_levels: tuple[EnergyLevel, ...]
    residuals: dict[str, Any]
    conditioning: dict[str, Any]
    warnings: tuple[str, ...] = field(default=())
    dissipation: dict[str, Any] | None = None
    # Per-sample energy rows (trajectory, t, energy, residual, weight) for --residuals;
    # bulk data, so not part of the JSON nor of equality.
    samples: dict[str, Any] | None = field(default=None, compare=False, repr=False)

    @property
    def estimates(self) -> dict[str, float]:
        """Parameter name -> estimate."""
        return {p.name: p.estimate for p in self.parameters}

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data (built-in types; non-finite numbers become null)."""
        return _finite({
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
        })

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FitResult:
        """The inverse of `to_dict` (for `hamid report`, which never refits)."""
        return cls(
            hamid_version=data["hamid_version"],
            model=data["model"],
            data=data["data"],
            method=data["method"],
            parameters=tuple(ParameterEstimate(**p) for p in data["parameters"]),
            energy_levels=tuple(EnergyLevel(**h) for h in data["energy_levels"]),
            residuals=data["residuals"],
            conditioning=data["conditioning"],
            warnings=tuple(data["warnings"]),
            dissipation=data.get("dissipation"),
        )


def _finite(value: Any) -> Any:
    """Recursively turn numpy scalars into Python ones and NaN/inf into None."""
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value
