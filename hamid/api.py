"""The Python API: `load_model`, `simulate` and `fit`, the one path the CLI also takes."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hamid import __version__, estimate, loading, options, plan, refine, summary
from hamid.errors import UsageError
from hamid.model import Model, load_model
from hamid.result import FitResult

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["fit", "load_model", "simulate"]



def simulate(system: str | os.PathLike[str] | Mapping[str, Any], *, seed: int | None = None,
             max_samples: int | None = None,
             progress: Callable[[float], None] | None = None) -> pd.DataFrame:
    """Simulate the system of a TOML file (or its dict) and return the sampled record.

    The returned frame has columns ``trajectory``, ``t``, the coordinates and the
    velocities; ``frame.attrs["hamid"]`` holds its provenance (model, true parameters,
    initial states, energy drift, noise, seed, integrator, version).
    """
    import dataclasses

    import pandas as pd

    from hamid.simulation import parse_system, run

    if isinstance(system, Mapping):
        document, where = system, "system"
    else:
        from hamid import io

        where = os.fspath(system)
        document = io.read_toml(where)
    parsed = parse_system(document, where=where)
    if max_samples is not None:
        parsed = dataclasses.replace(parsed, max_samples=max_samples)
    columns, provenance = run(parsed, seed=seed, progress=progress)
    frame = pd.DataFrame(columns)
    frame.attrs["hamid"] = {**provenance, "hamid_version": __version__}
    return frame


def fit(data: Any, model: str | os.PathLike[str] | Model | None = None, *,
        columns: Mapping[str, str] | None = None, time: str | None = None,
        trajectory: str | None = None, velocity: str = "measured",
        window: int | None = None, order: int = options.SAVGOL_ORDER,
        noise: str | Mapping[str, float] | None = None, bias_correct: bool = False,
        fix: Mapping[str, float] | None = None, method: str = "auto",
        weak_window: float | None = None, damping: str | Sequence[str] = "none",
        cov: str = "hac", level: float = 0.95, bootstrap: int = 200,
        seed: int | None = None, format: str | None = None,
        chunk_rows: int | None = None, in_memory: bool = False,
        progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the energy of recorded free oscillations.

    Parameters
    ----------
    data : path, list of paths, or pandas.DataFrame
        Recorded positions and velocities (CSV, TSV, Parquet, or ``"-"`` for stdin).
    model : str, path or Model, optional
        A built-in name, a TOML model file or a Model; by default the model recorded in
        the data's metadata, else ``poly:N:3`` over the coordinates found.
    columns : dict, optional
        Model name -> file column, for columns named otherwise.
    time, trajectory : str, optional
        Names of the time and trajectory columns (default ``t``/``time``, ``trajectory``).
    velocity : {"measured", "savgol"}
        Take the velocities from the file, or derive them from the positions by
        Savitzky-Golay differentiation with an odd `window` (samples; default about a tenth
        of the dominant period) and polynomial `order`.
    noise : None, "auto" or dict
        Measurement noise std per column (model or file name): rows are then weighted by
        the inverse of the variance the noise puts into them. "auto" estimates it.
    bias_correct : bool
        Remove the bias that the noise puts into least squares (adjusted least squares;
        polynomial energies with measured velocities; needs `noise`).
    fix : dict, optional
        Parameters held at known values.
    method : {"auto", "joint", "weak", "energy"}
        Which rows to fit: energy rows, weak-form equations of motion, or both; ``auto``
        takes ``joint`` when the data allow it, refined by fitting the model's integrated
        trajectories to the recording (`hamid.trajectory`), and says why.
    weak_window : float, optional
        Length of the weak-form windows in seconds; by default half the dominant period.
    damping : str or list of str
        Dissipative forces to fit: "none", or any of "viscous", "coulomb", "quadratic"
        (a comma list or a list), one coefficient per coordinate and kind.
    cov : {"hac", "classical", "hc", "bootstrap"}
        How standard errors are computed.
    level : float
        Confidence level of the bounds.
    bootstrap, seed : int
        Replicates and seed of the block bootstrap (``cov="bootstrap"``).
    format : str, optional
        Input format when it cannot be told from the file name.
    chunk_rows : int, optional
        Read the file in chunks of this many rows, in memory that does not grow with the
        file's length (`hamid.stream`); ``auto`` then skips its trajectory refinement.
        By default a file over 64 MB is read in chunks of 2^18 rows (the same answer,
        faster), and ``auto`` refines holding only the records in memory (up to 1 GiB of
        them). Needs one file, measured velocities, no noise weighting or damping, and an
        analytic `cov`.
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
    from hamid import design, solve

    options.check_choice(method, options.METHODS, "method")
    options.check_choice(cov, options.COVARIANCE_KINDS, "cov")
    if not 0 < level < 1:
        raise UsageError(f"level must be between 0 and 1, found {level!r}")
    if bias_correct and noise in (None, "none"):
        raise UsageError("--bias-correct needs --noise (auto or COL=SIGMA,...)")
    if bias_correct and cov == "bootstrap":
        raise UsageError("--bias-correct cannot be combined with --cov bootstrap (the "
                         "refits would not be corrected); use --cov hac")
    if cov == "bootstrap" and bootstrap < 10:
        raise UsageError(f"bootstrap needs at least 10 replicates, found {bootstrap}")
    if weak_window is not None and not 0 < weak_window < float("inf"):
        raise UsageError(f"--weak-window must be a positive number of seconds, "
                         f"found {weak_window!r}")
    if velocity != "savgol" and (window is not None or order != options.SAVGOL_ORDER):
        raise UsageError("--window and --order apply only to --velocity savgol")

    options.check_choice(velocity, options.VELOCITY_SOURCES, "velocity")
    if isinstance(data, list | tuple) and len(data) == 1:
        data = data[0]
    obstacle = options.needs_memory(data, velocity, noise, damping, cov)
    if chunk_rows is not None and chunk_rows < 1:
        raise UsageError("--chunk-rows: must be a positive number of rows")
    if chunk_rows is not None and (obstacle or in_memory):
        raise UsageError(f"--chunk-rows: {obstacle or 'in_memory asks for the data in memory'}")
    if chunk_rows is not None or (not obstacle and not in_memory
                                  and options.reads_in_chunks(data)):
        from hamid import stream

        return stream.fit_file(data, model, columns=columns, time=time,
                               trajectory=trajectory, format=format, fix=fix or {},
                               method=method, weak_window=weak_window, cov=cov, level=level,
                               chunk_rows=chunk_rows or options.CHUNK_ROWS,
                               may_refine=chunk_rows is None, progress=progress)
    loaded = loading.load(data, model, columns=columns, time=time, trajectory=trajectory,
                        format=format, velocity=velocity, window=window, order=order)
    m, records = loaded.model, loaded.records
    sigma, noise_info = loading.noise_levels(noise, m, records, loaded)
    dissipation = design.Damping(options.parse_damping(damping), m.coordinates)
    if dissipation.kinds and records.t is None:
        raise UsageError("--damping needs a time column (the dissipated work is an integral "
                         "over time)")
    names = [*m.parameters, *dissipation.names]
    fixed = options.check_fixed(fix or {}, tuple(names))
    free = [k for k, name in enumerate(names) if name not in fixed]
    if not free:
        raise UsageError("every parameter is fixed; nothing is left to fit")
    free_names = [names[k] for k in free]
    scales = None if records.t is None or method == "energy" else design.trajectory_scales(
        records, len(m.coordinates))
    kind, kind_reason, window = plan.choose_method(method, m, scales, weak_window)

    fixed_values = np.array([fixed.get(name, 0.0) for name in names])
    all_energy_rows = design.energy_block(m, records, dissipation)
    design.check_finite(all_energy_rows, loaded.locate, names)
    energy_rows = design.hold_fixed(all_energy_rows, free, fixed_values)
    kind, kind_reason, window, spans, blocks = design.build_blocks(
        kind, kind_reason, window, method, weak_window, m, records, energy_rows, dissipation,
        free, fixed_values, free_names)
    J = records.n_trajectories
    units, unit_group = estimate.resampling_units(blocks, kind)
    if sigma is None:
        blocks, block_variance = estimate.balance_blocks(blocks, free_names, J, units, unit_group)
        rounds = 0
    else:
        blocks, block_variance, rounds = estimate.noise_weighted(
            blocks, m, records, spans, dissipation, sigma, free, fixed_values, free_names, J,
            units, unit_group)
    if bias_correct:
        from hamid import adjust

        adjust.check_adjustable(m, velocity == "savgol", dissipation)
        moments = [adjust.adjusted_moments(b, m, records, sigma, spans, free_names, fixed)
                   for b in blocks]
        blocks = [mo.block for mo in moments]
        linear = estimate.least_squares(blocks, free_names, J,
                                  correction=(sum(mo.AA for mo in moments),
                                              sum(mo.Ab for mo in moments)))
    else:
        linear = estimate.least_squares(blocks, free_names, J)
    theta = linear.theta
    refinement, refinement_info = None, None
    if method == "auto" and kind == "joint":
        obstacle = plan.refinement_obstacle(cov, bias_correct, dissipation.kinds)
        if obstacle is None:
            refinement, refinement_info = refine.refine_joint(
                m, records, dissipation, free, fixed_values, theta, scales, window, sigma,
                velocity, progress)
        else:
            refinement_info = {"applied": False, "reason": obstacle}
        kind_reason += plan.refinement_note(refinement_info)

    if refinement is not None:
        theta, theta_cov, df = refinement.theta, refinement.covariance, refinement.dof
        cov_text = refinement.description
        means_A, means_b, _ = solve.level_means(energy_rows, J)
        h = means_A @ theta - means_b
    else:
        if cov == "bootstrap":
            theta_cov, h_var, cov_text = estimate.bootstrap_covariance(
                blocks, free_names, J, units, unit_group, bootstrap, seed)
            df = linear.df_resid
        else:
            c = estimate.covariance(cov, linear, units, unit_group)
            theta_cov, cov_text, df = c.theta, c.description, c.df
            if dissipation.kinds:
                theta_cov, cov_text = estimate.with_propagated_noise(
                    theta_cov, cov_text, linear, blocks, m, records, sigma, free,
                    fixed_values, spans, dissipation)
            h_var = estimate.level_variance(c, linear.centred.level_means_A)
        h, h_stderr = estimate.fitted_levels(kind, linear.theta, linear.h, h_var,
                                     lambda: solve.level_means(energy_rows, J)[:2])
    energy_residual = energy_rows.A @ theta - energy_rows.b - h[energy_rows.group]
    sums = summary.ResidualSums(h)
    sums.add(energy_rows, energy_residual)
    if refinement is not None:
        h_stderr = refine.refined_level_errors(means_A, theta_cov, sums)
    stats = sums.stats(records.labels)
    stats["blocks"], cond, block_conditions = summary.block_report(
        blocks, linear.residual, free_names, records.labels)
    method_info = {
        "kind": kind, "kind_reason": kind_reason, "weak_window": window,
        "damping": list(dissipation.kinds),
        "weighting": "none" if sigma is None else "noise", "noise": noise_info,
        "weighting_rounds": rounds, "bias_correction": bias_correct, "covariance": cov,
        "covariance_description": cov_text, "level": level, "fixed": dict(fixed),
        "block_variance": block_variance, "refinement": refinement_info,
    }
    estimates = {**fixed, **dict(zip(free_names, theta.tolist(), strict=True))}
    labels = np.asarray(records.labels, dtype=object)
    samples = {"trajectory": labels[energy_rows.group], "t": energy_rows.time,
               "energy": design.fitted_energy(all_energy_rows, m, estimates),
               "residual": energy_residual,
               "weight": design.sample_weights(kind, blocks, energy_rows, spans)}
    sizes = [stop - start for start, stop in records.bounds()]
    return summary.fit_result(
        m, names, fixed, theta, theta_cov, df, truth=loaded.truth,
        levels=summary.energy_levels(records.labels, h, h_stderr, sizes), stats=stats, cond=cond,
        block_conditions=block_conditions, notes=loaded.notes, data_info=loaded.data_info,
        method_info=method_info,
        dissipation=summary.dissipation_summary(m, records, dissipation, estimates,
                                         all_energy_rows, h),
        samples=samples)


