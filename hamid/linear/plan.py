"""Which rows the fit takes (energy, weak, joint), why, and whether it is refined.

Decided once, from the options, the model and each trajectory's period and time step
(docs/method.md, "Choosing the rows"), and revised only when the records turn out to hold
too few weak-form windows.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from hamid.errors import DataError, FitError, UsageError
from hamid.linear import design
from hamid.linear.design import RowKind
from hamid.model.models import Model
from hamid.options import REFINEMENT_BYTES, FitOptions
from hamid.safe_text import counted

__all__ = ["FitPlan", "decide", "refinement_obstacle"]

CHUNKED_NOT_REFINED = ("it holds the records in memory, and --chunk-rows asks for "
                       "bounded memory")


@dataclass(frozen=True)
class FitPlan:
    """The rows to fit and why.

    kind : "energy", "weak" or "joint".
    reason : the report's words for the choice (and, once known, for the refinement).
    window : the weak-form window in seconds (None for energy rows).
    scales : each trajectory's period and time step (None without a time column, or when
        the energy rows were asked for and no window needs sizing).
    refines : whether the trajectory refinement follows: an automatic joint fit, and one
        that fell back to the energy rows for want of windows (the linear start exists, and
        the refinement fits the samples whatever the windows).
    """

    kind: RowKind
    reason: str
    window: float | None
    scales: list[tuple[float | None, float]] | None
    refines: bool = False

    def check_windows(self, n_windows: int, free_names: list[str], n_trajectories: int,
                      options: FitOptions) -> FitPlan:
        """This plan, or the energy rows' when `auto` finds too few windows to fit.

        Windows are the independent units of the weak and joint errors, so more are needed
        than unknowns (the levels count in joint).
        """
        needed = len(free_names) + (n_trajectories if self.kind == RowKind.JOINT else 0) + 1
        if self.kind == RowKind.ENERGY or n_windows >= needed:
            return self
        shortage = (f"the records hold {n_windows} weak-form windows of {self.window:.3g} s, "
                    f"fewer than the {needed} that {needed - 1} unknowns need")
        if options.method == "auto" and options.weak_window is None:
            return FitPlan(RowKind.ENERGY, f"{shortage}; fitted the energy rows", None,
                           self.scales, refines=self.refines)
        if n_windows == 0:
            raise DataError(f"the records are too short for one weak-form window of "
                            f"{self.window:.4g} s; use --method energy or a shorter "
                            "--weak-window")
        raise FitError(f"cannot determine {', '.join(free_names)}: {shortage}; use "
                       "--method energy or a shorter --weak-window")

    def refined(self, refused: str | None) -> FitPlan:
        """The plan with what the refinement did added to its reason: refined, or not and
        why (`refused`)."""
        note = ("; refined by fitting the integrated trajectories" if refused is None
                else f"; not refined by fitting trajectories: {refused}")
        return dataclasses.replace(self, reason=self.reason + note)


def decide(options: FitOptions, model: Model,
           scales: list[tuple[float | None, float]] | None) -> FitPlan:
    """Which rows to fit, why, and the weak-form window.

    `scales` holds each trajectory's period and time step (`design.trajectory_scales`),
    None without a time column.
    """
    method, weak_window = options.method, options.weak_window
    if method == "energy":
        return FitPlan(RowKind.ENERGY, "asked for with --method energy", None, scales)
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
    how = "given" if weak_window is not None else "half the dominant period"
    if obstacle is None:
        dt = float(np.median([step for _, step in scales]))
        per_window = window / dt
        # within rounding: a window of 1 s at dt = 0.05 s is 19.999999999999996 steps
        if per_window < design.MIN_SAMPLES_PER_WINDOW * (1 - 1e-9) and weak_window is None:
            # coarse sampling (a few samples a period): windows of the fewest samples the
            # quadrature needs, over more than half a period (the weak form holds over any
            # window; the refinement then fits the samples themselves)
            window = design.MIN_SAMPLES_PER_WINDOW * dt
            how = (f"half the dominant period held {per_window:.3g} samples, lengthened to "
                   f"{design.MIN_SAMPLES_PER_WINDOW}")
        elif per_window < design.MIN_SAMPLES_PER_WINDOW * (1 - 1e-9):
            obstacle = (f"a weak-form window of {window:.3g} s holds only {per_window:.3g} "
                        f"samples (at least {design.MIN_SAMPLES_PER_WINDOW} are needed)")
    if obstacle is not None:
        if method != "auto":
            raise UsageError(f"--method {method} is not possible: {obstacle}")
        return FitPlan(RowKind.ENERGY, f"{obstacle}; fitted the energy rows", None, scales)
    if method == "auto":
        return FitPlan(RowKind.JOINT, "time column sampled finely enough for weak-form windows "
                       f"of {window:.3g} s ({how})", window, scales, refines=True)
    return FitPlan(RowKind(method), f"asked for with --method {method}; windows of "
                   f"{window:.3g} s ({how})", window, scales)


def window_warnings(fit_plan: FitPlan, durations: list[float] | None) -> list[str]:
    """A warning when weak-form windows are longer than some trajectories (which then give
    no weak-form rows)."""
    if fit_plan.window is None or not durations:
        return []
    window, step = fit_plan.window, fit_plan.window * design.WINDOW_STEP
    notes = []
    short = [d for d in durations if d < window]
    if short:
        notes.append(f"{len(short)} of {counted(len(durations), 'trajectory', 'trajectories')} "
                     f"{'is' if len(short) == 1 else 'are'} shorter than the "
                     f"weak-form window of {window:.3g} s (the shortest lasts "
                     f"{min(short):.3g} s) and give no weak-form rows; give a shorter "
                     "--weak-window, or check the time unit")
    # windows start every `step` and end within the trajectory: what they reach of it
    covered = sum(np.floor((d - window) / step) * step + window for d in durations
                  if d >= window)
    if sum(durations) > 0 and covered < 0.5 * sum(durations):
        notes.append(f"the weak-form windows cover only {covered / sum(durations):.0%} of "
                     "the record; give a shorter --weak-window, or check the time unit")
    return notes


def refinement_obstacle(options: FitOptions, records_bytes: int | None = None) -> str | None:
    """Why an automatic joint fit is not refined by trajectories, or None when it is.

    `records_bytes` is the size of the records that a fit read in chunks would hold in
    memory for the refinement (None for a fit in memory).
    """
    if options.linear_asked is not None:
        return options.linear_asked
    if records_bytes is not None and options.chunk_rows is not None:
        return CHUNKED_NOT_REFINED
    if records_bytes is not None and records_bytes > REFINEMENT_BYTES:
        return (f"it holds the records in memory, {records_bytes / 2**30:.1f} GiB here, over "
                f"the limit of {REFINEMENT_BYTES / 2**30:g} GiB")
    return None
