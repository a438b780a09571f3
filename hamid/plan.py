"""Which rows the fit takes (energy, weak, joint), why, and whether it is refined."""

from __future__ import annotations

from typing import Any

import numpy as np

from hamid.errors import UsageError
from hamid.model import Model


def choose_method(method: str, model: Model, scales: list[tuple[float | None, float]] | None,
                   weak_window: float | None) -> tuple[str, str, float | None]:
    """Which rows to fit, why, and the weak-form window (SPEC section 1, --method).

    `scales` holds each trajectory's period and time step (`design.trajectory_scales`),
    None without a time column.
    """
    from hamid import design

    if method == "energy":
        return "energy", "asked for with --method energy", None
    obstacle = None
    window = weak_window
    if scales is None:
        obstacle = "the data have no time column"
    elif not model.is_natural:
        obstacle = "the energy is not natural (E = T + V), so Lagrange's equations do not apply"
    elif window is None:
        period = design.median_period(scales)
        if period is None:
            obstacle = "no oscillation was found in the coordinates to size the windows"
        else:
            window = period / 2
    if obstacle is None:
        dt = float(np.median([step for _, step in scales]))
        per_window = window / dt
        if per_window < design.MIN_SAMPLES_PER_WINDOW:
            obstacle = (f"a weak-form window of {window:.3g} s holds only {per_window:.0f} "
                        f"samples (at least {design.MIN_SAMPLES_PER_WINDOW} are needed)")
    if obstacle is not None:
        if method != "auto":
            raise UsageError(f"--method {method} is not possible: {obstacle}")
        return "energy", f"{obstacle}; fitted the energy rows", None
    how = "given" if weak_window is not None else "half the dominant period"
    if method == "auto":
        return "joint", (f"time column sampled finely enough for weak-form windows of "
                         f"{window:.3g} s ({how})"), window
    return method, f"asked for with --method {method}; windows of {window:.3g} s ({how})", \
        window


CHUNKED_NOT_REFINED = ("it holds the records in memory, and --chunk-rows asks for "
                       "bounded memory")


def refinement_obstacle(cov: str, bias_correct: bool, damping: tuple[str, ...]) -> str | None:
    """Why an automatic joint fit is not refined by trajectories, or None when it is."""
    if "coulomb" in damping:
        return ("Coulomb friction makes the motion jump at every stop, which the trajectory "
                "fit's integration and differences do not follow")
    if cov != "hac":
        return (f"the trajectory fit has a covariance of its own, and --cov {cov} asks for "
                "that of the linear fit")
    if bias_correct:
        return "--bias-correct asks for the linear fit"
    return None


def refinement_note(info: dict[str, Any]) -> str:
    """What the method's reason adds about the trajectory refinement."""
    if info["applied"]:
        return "; refined by fitting the integrated trajectories"
    return f"; not refined by fitting trajectories: {info['reason']}"
