"""The trajectory refinement of an automatic joint fit: the linear fit's parameters refined
by fitting the model's integrated motion to the recording (`hamid.trajectory` does the
work; docs/method.md, "The trajectory refinement")."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid import design, measurement
from hamid.dissipation import Dissipation
from hamid.estimate import LinearFit, ResidualSums
from hamid.expr import Func
from hamid.model import Model
from hamid.plan import FitPlan
from hamid.records import Records
from hamid.unknowns import Unknowns

__all__ = ["level_errors", "refine"]


def refine(linear: LinearFit, model: Model, records: Records, damping: Dissipation,
           unknowns: Unknowns, plan: FitPlan, sigma: npt.NDArray[np.float64] | None,
           derived_velocities: bool,
           progress: Callable[[str], None] | None) -> tuple[LinearFit | None, dict[str, Any]]:
    """The refined fit, or None when the integrated model does not fit the recording, and
    what the report says of it.

    The refined fit's levels are the mean energies at its parameters; their standard
    errors need a pass over the energy residuals there (`level_errors`) and are NaN here.
    """
    for what, kinks in (("energy", model.kinks),
                        ("dissipation", [k for part in damping.kinks for k in part])):
        kink = _crossed_kink(kinks, records)
        if kink is not None:
            return None, {"applied": False, "reason": (
                f"the {what} is not smooth where {kink} = 0 (abs, sign or a fractional "
                "power), and the motion reaches it; integrating its force there takes tiny "
                "steps without end")}
    from hamid import trajectory  # scipy.integrate: only when a fit is refined

    N = len(model.coordinates)
    noise = measurement.estimate_noise(records.X, records.bounds())
    if sigma is not None:
        noise = np.where(sigma > 0, sigma, noise)
    weight = 1.0 / np.maximum(noise, 1e-9 * records.X.std(axis=0))
    if derived_velocities:
        weight[N:] = 0.0  # derived from the positions: no information of their own
    period = design.median_period(plan.scales)
    if period is None:   # windows given with --weak-window, no period found
        period = 2 * plan.window
    try:
        refined = trajectory.refine(model, records, damping, unknowns.full(linear.theta),
                                    list(unknowns.free), period, weight, progress)
    except trajectory.RefinementFailed as exc:
        return None, {"applied": False, "reason": f"the integrated model does not fit the "
                      f"recording: {exc}"}
    means_A, means_b = linear.energy_means
    fit = dataclasses.replace(
        linear, theta=refined.theta, covariance=refined.covariance,
        description=refined.description, df=refined.dof, h=means_A @ refined.theta - means_b,
        h_stderr=np.full(len(means_b), np.nan), residuals=None)
    return fit, {"applied": True, "segments": refined.segments,
                 "segment_seconds": refined.segment_seconds,
                 "iterations": refined.iterations, "chi2_per_dof": refined.chi2_per_dof}


def level_errors(fit: LinearFit, residuals: ResidualSums) -> npt.NDArray[np.float64]:
    """Standard errors of the refined levels, each the mean energy at its parameters.

    The variance adds what the parameters' covariance puts into each mean to that of the
    mean of its energy residuals, which are white once the parameters are right (each is
    the energy of one sample's measurement noise).
    """
    means_A = fit.energy_means[0]
    n, squares = residuals.n, residuals.sums[:, 3]
    mean_noise = squares / np.maximum(n * (n - 1), 1)
    return np.sqrt(np.einsum("jk,kl,jl->j", means_A, fit.covariance, means_A) + mean_noise)


def _crossed_kink(kinks: Sequence[Func], records: Records) -> str | None:
    """The first place where a function is not smooth that the records reach (change sign
    across, or come within a thousandth of their largest distance from), or None."""
    for kink in kinks:
        values = kink(records.X)
        values = values[np.isfinite(values)]
        if values.size and (np.min(values) <= 0 <= np.max(values)
                            or np.min(np.abs(values)) < 1e-3 * np.max(np.abs(values))):
            return str(kink.expression).replace("Abs(", "abs(")
    return None
