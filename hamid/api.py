"""The Python API: `fit`, the one path the CLI also takes, as its steps (and `load_model`)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from hamid.data import input_size, loading, measurement
from hamid.data.records import Recording
from hamid.executor import one_blas_thread
from hamid.linear import chunked, estimate, plan
from hamid.linear.unknowns import Unknowns
from hamid.model.models import Model, load_model
from hamid.options import SAVGOL_ORDER, FitOptions
from hamid.refine import joint_refinement
from hamid.result import summary
from hamid.result.fit_result import FitResult, ProvenanceInfo

__all__ = ["fit", "load_model"]


def fit(data: Any, model: str | os.PathLike[str] | Model | None = None, *,
        # reading
        columns: Mapping[str, str] | None = None, time: str | None = None,
        time_unit: str | None = None, trajectory: str | None = None,
        scale: Mapping[str, float] | None = None, gaps: str = "split",
        format: str | None = None, delimiter: str | None = None, decimal: str | None = None,
        skip_rows: int = 0, units_row: bool | None = None,
        # velocities
        velocity: str = "auto", window: int | None = None, order: int = SAVGOL_ORDER,
        # method
        method: str = "auto", weak_window: float | None = None,
        damping: str | Sequence[str] | None = "none", fix: Mapping[str, float] | None = None,
        noise: str | Mapping[str, float] | None = None, bias_correct: bool = False,
        # covariance
        cov: str = "hac", level: float = 0.95, bootstrap: int = 200, seed: int | None = None,
        # run
        jobs: int | None = None, chunk_rows: int | None = None, in_memory: bool = False,
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the energy of recorded free oscillations.

    The keywords come in the groups of `hamid.options.OPTION_GROUPS`: how the data are read,
    where the velocities come from, the method, the covariance, and how the fit runs.

    Parameters
    ----------
    data : path, list of paths, pandas.DataFrame, dict of arrays or structured array
        Recorded positions and velocities (CSV, TSV, Parquet, or ``"-"`` for stdin; in
        memory, columns by name as in a file).
    model : str, path or Model, optional
        A built-in name, a TOML model file or a Model; by default the model recorded in
        the data's metadata, else ``poly:N:3`` over the coordinates found.
    columns : dict, optional
        Model name -> file column, for columns named otherwise.
    time, trajectory : str, optional
        Names of the time and trajectory columns (default ``t`` or ``time`` in any case,
        with a unit suffix such as ``time_ms`` or ``Time [s]``; ``trajectory``).
    time_unit : {"s", "ms", "us", "ns"}, optional
        Unit of the time column (default: its name's suffix, else seconds); times are
        converted to seconds before anything else.
    scale : dict, optional
        File column -> factor that brings it to the units of the others (SI); by default a
        column's unit suffix (``x1_mm``, ``v1_mm_s``) or the units in the table's metadata.
    gaps : {"split", "error"}
        At a missing value or a time step over 5 times the median, cut the trajectory into
        separate trajectories, each with its own level (said in a warning), or refuse.
    format : str, optional
        Input format when it cannot be told from the file name.
    delimiter, decimal, skip_rows, units_row : optional
        How delimited text is laid out: the cell delimiter and decimal mark (detected:
        ';' files with decimal commas are), lines to skip before the header, and whether
        a units row follows the header (detected: a row without numbers above rows with
        them; its units convert like name suffixes).
    velocity : {"auto", "measured", "savgol"}
        Take the velocities from the file ("measured"), or derive them from the positions
        by Savitzky-Golay differentiation with an odd `window` (samples; default about a
        tenth of the dominant period) and polynomial `order` ("savgol"); "auto" takes them
        from the file but sets them aside and derives them when they disagree with the
        positions' rate of change (a gain or a lag: a channel filtered or derived before
        recording; docs/method.md, "Channels that disagree"), and when the file has none.
    method : {"auto", "joint", "weak", "energy"}
        Which rows to fit: energy rows, weak-form equations of motion, or both; ``auto``
        takes ``joint`` when the data allow it, refined by fitting the model's integrated
        trajectories to the recording (`hamid.refine.trajectory`), and says why.
    weak_window : float, optional
        Length of the weak-form windows in seconds; by default half the dominant period.
    damping : str or list of str, optional
        Dissipative forces to fit: "none" (or None), or any of "viscous", "coulomb", "quadratic"
        (a comma list or a list), one coefficient per coordinate and kind.
    fix : dict, optional
        Parameters held at known values.
    noise : None, "auto" or dict
        Measurement noise std per column (model or file name): rows are then weighted by
        the inverse of the variance the noise puts into them. "auto" estimates it.
    bias_correct : bool
        Remove the bias that the noise puts into least squares (adjusted least squares;
        polynomial energies with measured velocities; needs `noise`).
    cov : {"hac", "classical", "hc", "bootstrap"}
        How standard errors are computed.
    level : float
        Confidence level of the bounds.
    bootstrap, seed : int
        Replicates and seed of the block bootstrap (``cov="bootstrap"``).
    jobs : int, optional
        Processes the trajectory refinement of a long record integrates in (default: one
        per core; a short record stays in this one, whose results are the same).
    chunk_rows : int, optional
        Read the file in chunks of this many rows, in memory that does not grow with the
        file's length (`hamid.linear.chunked`); ``auto`` then skips its trajectory refinement.
        By default a file that takes over 64 MB once decoded (8 bytes a cell, whatever
        its size on disk; standard input too) is read in chunks of 2^18 rows (the same
        answer, faster), and ``auto`` refines holding only the records in memory (up to
        1 GiB of them). Needs one file or standard input, measured velocities, no noise
        weighting or damping, and an analytic `cov`.
    in_memory : bool
        Read the data into memory whatever the file's size: ``result.samples`` then holds
        the per-sample residuals.
    progress : callable, optional
        Called with a line of text at each step of a long fit (every chunk of a pass over
        a file read in chunks, every batch of the trajectory refinement), e.g. for a
        status line.

    Returns
    -------
    FitResult

    Examples
    --------
    >>> result = hamid.fit("sample_data/duffing.csv")
    >>> result.estimates
    {'k': 1.0..., 'k3': 0.5...}
    """
    # every keyword but `progress`, in the groups of `options.OPTION_GROUPS`
    # (tests/test_option_spec.py checks that each arrives as given)
    opts = FitOptions(columns=columns, time=time, time_unit=time_unit, trajectory=trajectory,
                      scale=scale, gaps=gaps, format=format, delimiter=delimiter,
                      decimal=decimal, skip_rows=skip_rows, units_row=units_row,
                      velocity=velocity, window=window, order=order,
                      method=method, weak_window=weak_window, damping=damping, fix=fix or {},
                      noise=noise, bias_correct=bias_correct,
                      cov=cov, level=level, bootstrap=bootstrap, seed=seed,
                      jobs=jobs, chunk_rows=chunk_rows, in_memory=in_memory)
    if isinstance(data, list | tuple) and len(data) == 1:
        data = data[0]
    with input_size.spooled(data) as readable, one_blas_thread():   # stdin spooled to a file
        chunks = opts.chunking(readable, loading.in_memory_only(model))
        run = summary.run_provenance(data, opts)   # inputs hashed before they are read
        return _fit(readable, model, opts, chunks, run, progress)


def _fit(data: Any, model: str | os.PathLike[str] | Model | None, opts: FitOptions,
         chunks: int | None, run: ProvenanceInfo,
         progress: Callable[[str], None] | None) -> FitResult:
    """The fit of `fit`, its options checked and standard input in a file."""
    # the records: whole, or a file to pass over in chunks (the same `loading.Source`)
    source = None if chunks is None else loading.open_chunks(data, model, opts, chunks,
                                                             progress)
    if source is None:
        source = loading.load(data, model, opts)
    sigma, noise_info = loading.noise_levels(source, opts.noise)
    m = source.model
    damping_forces = m.dissipative(opts.damping)
    unknowns = Unknowns.of(m, damping_forces.names, opts.fix)
    # plan, then the linear estimate
    fit_plan = plan.decide(opts, m, source.scales() if opts.method != "energy" else None)
    step = chunked.linear_fit(source, unknowns, damping_forces, fit_plan, opts, sigma)
    linear, fit_plan, rows = step.fit, step.plan, step.rows
    # refine
    fitted, refinement = linear, None
    if fit_plan.refines:
        obstacle = plan.refinement_obstacle(opts, source.whole_bytes())
        if obstacle is None:
            records = source.whole()
            given = sigma if isinstance(opts.noise, Mapping) else None   # not --noise auto
            if rows is not None:   # the energy rows of every sample, made again after it
                rows.release()
            outcome = joint_refinement.refine(
                linear=linear, model=m, records=records, damping=damping_forces,
                unknowns=unknowns, plan=fit_plan, sigma=given,
                fitted=source.channels.fitted, rows=rows, progress=progress,
                jobs=opts.jobs)
            del records
        else:
            outcome = joint_refinement.Outcome.refused(obstacle)
        fitted, refinement = outcome.fit or linear, outcome.report
        fit_plan = fit_plan.refined(outcome.reason)
    residuals = fitted.residuals or estimate.residual_sums(step.energy_pieces(), fitted.theta,
                                                           fitted.h)
    if fitted is not linear:
        errors = joint_refinement.level_errors(fitted, residuals)
        fitted = dataclasses.replace(fitted, h_stderr=errors)
    # the checks (those a pass in chunks cannot make said in `checks_skipped`), the result
    noise_check = None if rows is None else estimate.noise_check(
        loaded=source, rows=rows, fit=linear if fitted is linear else None, unknowns=unknowns,
        damping=damping_forces, options=opts, sigma=sigma)
    notes = source.notes + tuple(plan.window_warnings(fit_plan, source.durations()))
    if m.forcing is not None:   # inputs the sampling does not resolve
        notes += tuple(measurement.nyquist_warnings(m.forcing.inputs, source.whole()))
    provenance = summary.Provenance(data=source.data_info, labels=source.labels,
                                    truth=source.truth, notes=notes, noise=noise_info,
                                    noise_check=noise_check, skipped=step.skipped)
    estimates = unknowns.estimates(fitted.theta)
    result = summary.fit_result(
        model=m, unknowns=unknowns, fit=fitted, residuals=residuals, plan=fit_plan,
        options=opts, provenance=provenance, refinement=refinement,
        dissipation=summary.dissipation_summary(m, source, damping_forces, estimates, rows,
                                                fitted.h),
        samples=None if rows is None else summary.samples(rows, fitted, m, unknowns, fit_plan,
                                                          source.labels),
        run=run,
        forcing=None if m.forcing is None else summary.forcing_summary(m, source.whole(),
                                                                       estimates))
    if rows is None:   # no records in memory, for plot()
        return result
    return dataclasses.replace(result, recording=Recording(m, source.whole(), source.channels))
