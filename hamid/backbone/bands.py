"""Confidence bands of a backbone by the delta method.

At a FIXED amplitude A, the frequency f(θ) and the damping ratio ζ(θ) are functions of the
free parameters θ (energy and dissipation). Their gradients are taken by central finite
differences, step h_k = 10⁻⁴ (|θ_k| + σ_k) (σ_k the standard error), each side recomputing
the well, the orbit of amplitude A and its cycle (`hamid.backbone.one_degree`); the
variance is g' Σ g with Σ the fit's covariance, and the band is the value ± the fit's
interval multiplier (its t or normal quantile at the report's level) times the standard
deviation. At 1% noise the band's coverage of the true backbone is checked over 100
simulated fits (tests/backbone/test_coverage.py, slow). A band is None where the
covariance has unknown entries, or where a perturbed well no longer holds the orbit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from hamid.backbone.one_degree import Cycle, Fitted

if TYPE_CHECKING:
    from hamid.backbone.normal_modes import ModeFitted
from hamid.errors import HamidError

__all__ = ["STEP", "Band", "Uncertainty", "bands", "bands_along"]

Array = npt.NDArray[np.float64]
STEP = 1e-4


@dataclass(frozen=True)
class Uncertainty:
    """The free parameters' covariance (rows in the order of `names`) and the interval
    multiplier of the fit's level."""

    names: tuple[str, ...]
    matrix: Array
    multiplier: float


@dataclass(frozen=True)
class Band:
    """Low and high ends of the frequency's and the damping ratio's bands (None: unknown)."""

    frequency: tuple[float, float] | None
    damping_ratio: tuple[float, float] | None


def _interval(value: float | None, gradient: Array, uncertainty: Uncertainty
              ) -> tuple[float, float] | None:
    if value is None or not np.all(np.isfinite(gradient)):
        return None
    variance = float(gradient @ uncertainty.matrix @ gradient)
    if not variance >= 0:
        return None
    half = uncertainty.multiplier * np.sqrt(variance)
    return value - half, value + half


def bands(fitted: Fitted, amplitude: float, uncertainty: Uncertainty, *,
          centre: Cycle | None = None) -> Band:
    """The bands of the frequency and the damping ratio at `amplitude` (`centre`: its
    cycle at the estimates, when already computed)."""
    return bands_along(fitted, [centre or fitted.at_amplitude(amplitude)], uncertainty,
                       lambda nudged: [nudged.at_amplitude(amplitude)])[0]


def bands_along(fitted: Fitted | ModeFitted, centres: Sequence[Cycle],
                uncertainty: Uncertainty,
                cycles: Callable[[Fitted | ModeFitted], Sequence[Cycle]]) -> list[Band]:
    """The bands of several points of one curve (`centres`, their cycles at the
    estimates), `cycles` giving those points' cycles of a model nudged in one parameter:
    a normal mode's branch is continued once per nudge for all its points."""
    if not np.all(np.isfinite(uncertainty.matrix)):
        return [Band(None, None)] * len(centres)
    sigma = np.sqrt(np.maximum(np.diag(uncertainty.matrix), 0.0))
    slopes = np.full((len(centres), 2, len(uncertainty.names)), np.nan)
    for k, name in enumerate(uncertainty.names):
        theta = fitted.estimates[name]
        h = STEP * (abs(theta) + sigma[k]) or STEP
        try:
            up, down = (cycles(replace(fitted, estimates={**fitted.estimates,
                                                          name: theta + s * h}))
                        for s in (1.0, -1.0))
        except HamidError:
            continue
        for j, (a, b) in enumerate(zip(up, down, strict=True)):
            slopes[j, 0, k] = (a.frequency - b.frequency) / (2 * h)
            if centres[j].damping_ratio is not None:
                slopes[j, 1, k] = (a.damping_ratio - b.damping_ratio) / (2 * h)
    return [Band(_interval(centre.frequency, slope[0], uncertainty),
                 _interval(centre.damping_ratio, slope[1], uncertainty))
            for centre, slope in zip(centres, slopes, strict=True)]
