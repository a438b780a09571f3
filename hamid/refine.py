"""The trajectory refinement of an automatic joint fit (`hamid.trajectory` does the work)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from hamid import summary
from hamid.model import Model
from hamid.records import Records


def refined_level_errors(means_A: Any, theta_cov: Any, residuals: summary.ResidualSums) -> Any:
    """Standard errors of the levels after the trajectory fit, each the mean energy at its
    parameters (means_A theta - means_b).

    The variance adds what the parameters' covariance puts into each mean to that of the
    mean of its energy residuals, which are white once the parameters are right (each is
    the energy of one sample's measurement noise).
    """
    n, squares = residuals.n, residuals.sums[:, 3]
    mean_noise = squares / np.maximum(n * (n - 1), 1)
    return np.sqrt(np.einsum("jk,kl,jl->j", means_A, theta_cov, means_A) + mean_noise)


def refine_joint(m: Model, records: Records, dissipation: Any, free: list[int],
            fixed_values: Any, theta: Any, scales: list[tuple[float | None, float]],
            window: float, sigma: Any, velocity: str,
            progress: Callable[[str], None] | None) -> tuple[Any, dict[str, Any]]:
    """The trajectory refinement of an automatic joint fit (`hamid.trajectory`), or None,
    and what the report says of it."""
    from hamid import design, measurement, trajectory

    N = len(m.coordinates)
    noise = measurement.estimate_noise(records.X, records.bounds())
    if sigma is not None:
        noise = np.where(sigma > 0, sigma, noise)
    weight = 1.0 / np.maximum(noise, 1e-9 * records.X.std(axis=0))
    if velocity == "savgol":
        weight[N:] = 0.0  # derived from the positions: no information of their own
    period = design.median_period(scales)
    if period is None:   # windows given with --weak-window, no period found
        period = 2 * window
    theta_all = fixed_values.copy()
    theta_all[free] = theta
    try:
        refined = trajectory.refine(m, records, dissipation, theta_all, free, period, weight,
                                    progress)
    except trajectory.RefinementFailed as exc:
        return None, {"applied": False, "reason": f"the integrated model does not fit the "
                      f"recording: {exc}"}
    return refined, {"applied": True, "segments": refined.segments,
                     "segment_seconds": refined.segment_seconds,
                     "iterations": refined.iterations,
                     "chi2_per_dof": refined.chi2_per_dof}
