"""The Python API: `load_model`, `simulate` and `fit`, the one path the CLI also takes."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hamid import __version__
from hamid.design import Block, Records
from hamid.errors import DataError, FitError, ModelError, UsageError
from hamid.model import (
    BUILTINS,
    Model,
    builtin_model,
    damping_names,
    model_from_expression,
    model_from_spec,
)
from hamid.result import EnergyLevel, FitResult, ParameterEstimate

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["fit", "load_model", "simulate"]

_MODEL_FILE_KEYS = ("model", "parameters", "initial", "simulate", "noise", "damping")


def load_model(name_or_path: str | os.PathLike[str]) -> Model:
    """A built-in model by name (``duffing``, ``poly:2:3``, ...) or the model of a TOML file.

    Examples
    --------
    >>> hamid.load_model("duffing").parameters
    ('k', 'k3')
    """
    text = os.fspath(name_or_path)
    if not text.endswith(".toml"):
        return builtin_model(text)
    from hamid import io
    from hamid.config import check_keys

    document = io.read_toml(text)
    check_keys(document, _MODEL_FILE_KEYS, where=text)
    if "model" not in document:
        raise ModelError(f"{text}: no [model] table")
    return model_from_spec(document["model"], where=f"{text}: [model]")


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


COVARIANCE_KINDS = ("classical", "hc", "hac", "bootstrap")
VELOCITY_SOURCES = ("measured", "savgol")
SAVGOL_ORDER = 5
METHODS = ("auto", "joint", "weak", "energy")


def fit(data: Any, model: str | os.PathLike[str] | Model | None = None, *,
        columns: Mapping[str, str] | None = None, time: str | None = None,
        trajectory: str | None = None, velocity: str = "measured",
        window: int | None = None, order: int = SAVGOL_ORDER,
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

    _check_choice(method, METHODS, "method")
    _check_choice(cov, COVARIANCE_KINDS, "cov")
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
    if velocity != "savgol" and (window is not None or order != SAVGOL_ORDER):
        raise UsageError("--window and --order apply only to --velocity savgol")

    _check_choice(velocity, VELOCITY_SOURCES, "velocity")
    if isinstance(data, list | tuple) and len(data) == 1:
        data = data[0]
    obstacle = _needs_memory(data, velocity, noise, damping, cov)
    if chunk_rows is not None and chunk_rows < 1:
        raise UsageError("--chunk-rows: must be a positive number of rows")
    if chunk_rows is not None and (obstacle or in_memory):
        raise UsageError(f"--chunk-rows: {obstacle or 'in_memory asks for the data in memory'}")
    if chunk_rows is not None or (not obstacle and not in_memory and _reads_in_chunks(data)):
        from hamid import stream

        return stream.fit_file(data, model, columns=columns, time=time,
                               trajectory=trajectory, format=format, fix=fix or {},
                               method=method, weak_window=weak_window, cov=cov, level=level,
                               chunk_rows=chunk_rows or CHUNK_ROWS, refine=chunk_rows is None,
                               progress=progress)
    loaded = _load_data(data, model, columns=columns, time=time, trajectory=trajectory,
                        format=format, velocity=velocity, window=window, order=order)
    m, records = loaded.model, loaded.records
    sigma, noise_info = _noise_levels(noise, m, records, loaded)
    dissipation = design.Damping(_parse_damping(damping), m.coordinates)
    if dissipation.kinds and records.t is None:
        raise UsageError("--damping needs a time column (the dissipated work is an integral "
                         "over time)")
    names = [*m.parameters, *dissipation.names]
    fixed = _check_fixed(fix or {}, tuple(names))
    free = [k for k, name in enumerate(names) if name not in fixed]
    if not free:
        raise UsageError("every parameter is fixed; nothing is left to fit")
    free_names = [names[k] for k in free]
    scales = None if records.t is None or method == "energy" else design.trajectory_scales(
        records, len(m.coordinates))
    kind, kind_reason, window = _choose_method(method, m, scales, weak_window)

    fixed_values = np.array([fixed.get(name, 0.0) for name in names])
    all_energy_rows = design.energy_block(m, records, dissipation)
    _check_finite(all_energy_rows, loaded.locate, names)
    energy_rows = _hold_fixed(all_energy_rows, free, fixed_values)
    kind, kind_reason, window, spans, blocks = _build_blocks(
        kind, kind_reason, window, method, weak_window, m, records, energy_rows, dissipation,
        free, fixed_values, free_names)
    J = records.n_trajectories
    units, unit_group = _resampling_units(blocks, kind)
    if sigma is None:
        blocks, block_variance = _balance_blocks(blocks, free_names, J, units, unit_group)
        rounds = 0
    else:
        blocks, block_variance, rounds = _noise_weighted(
            blocks, m, records, spans, dissipation, sigma, free, fixed_values, free_names, J,
            units, unit_group)
    if bias_correct:
        from hamid import adjust

        adjust.check_adjustable(m, velocity == "savgol", dissipation)
        moments = [adjust.adjusted_moments(b, m, records, sigma, spans, free_names, fixed)
                   for b in blocks]
        blocks = [mo.block for mo in moments]
        estimate = _least_squares(blocks, free_names, J,
                                  correction=(sum(mo.AA for mo in moments),
                                              sum(mo.Ab for mo in moments)))
    else:
        estimate = _least_squares(blocks, free_names, J)
    theta = estimate.theta
    refinement, refinement_info = None, None
    if method == "auto" and kind == "joint":
        obstacle = _refinement_obstacle(cov, bias_correct, dissipation.kinds)
        if obstacle is None:
            refinement, refinement_info = _refine(m, records, dissipation, free, fixed_values,
                                                  theta, scales, window, sigma, velocity,
                                                  progress)
        else:
            refinement_info = {"applied": False, "reason": obstacle}
        kind_reason += _refinement_note(refinement_info)

    if refinement is not None:
        theta, theta_cov, df = refinement.theta, refinement.covariance, refinement.dof
        cov_text = refinement.description
        means_A, means_b, _ = solve.level_means(energy_rows, J)
        h = means_A @ theta - means_b
    else:
        if cov == "bootstrap":
            theta_cov, h_var, cov_text = _bootstrap_covariance(
                blocks, free_names, J, units, unit_group, bootstrap, seed)
            df = estimate.df_resid
        else:
            c = _covariance(cov, estimate, units, unit_group)
            theta_cov, cov_text, df = c.theta, c.description, c.df
            if dissipation.kinds:
                theta_cov, cov_text = _with_propagated_noise(
                    theta_cov, cov_text, estimate, blocks, m, records, sigma, free,
                    fixed_values, spans, dissipation)
            h_var = _level_variance(c, estimate.centred.level_means_A)
        h, h_stderr = _fitted_levels(kind, estimate.theta, estimate.h, h_var,
                                     lambda: solve.level_means(energy_rows, J)[:2])
    energy_residual = energy_rows.A @ theta - energy_rows.b - h[energy_rows.group]
    sums = _ResidualSums(h)
    sums.add(energy_rows, energy_residual)
    if refinement is not None:
        h_stderr = _refined_level_errors(means_A, theta_cov, sums)
    stats = sums.stats(records.labels)
    stats["blocks"], cond, block_conditions = _block_report(
        blocks, estimate.residual, free_names, records.labels)
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
               "energy": _fitted_energy(all_energy_rows, m, estimates),
               "residual": energy_residual,
               "weight": _sample_weights(kind, blocks, energy_rows, spans)}
    sizes = [stop - start for start, stop in records.bounds()]
    return _result(
        m, names, fixed, theta, theta_cov, df, truth=loaded.truth,
        levels=_levels(records.labels, h, h_stderr, sizes), stats=stats, cond=cond,
        block_conditions=block_conditions, notes=loaded.notes, data_info=loaded.data_info,
        method_info=method_info,
        dissipation=_dissipation_summary(m, records, dissipation, estimates,
                                         all_energy_rows, h),
        samples=samples)


def _fitted_levels(kind: str, theta: Any, fitted_h: Any, h_var: Any,
                   energy_means: Callable[[], tuple[Any, Any]]) -> tuple[Any, Any]:
    """Energy levels of a linear fit and their standard errors.

    Without a level in the fit (weak rows, or a trajectory too short for any window of a
    joint fit) the level is the mean fitted energy, without a standard error;
    `energy_means` gives the means of A and b of each trajectory's energy rows, asked for
    only then.
    """
    J = len(fitted_h)
    h_stderr = np.full(J, np.nan) if kind == "weak" else np.sqrt(np.clip(h_var, 0, None))
    if kind != "weak" and not np.any(np.isnan(fitted_h)):
        return fitted_h, h_stderr
    means_A, means_b = energy_means()
    mean_energy = means_A @ theta - means_b
    if kind == "weak":
        return mean_energy, h_stderr
    return np.where(np.isnan(fitted_h), mean_energy, fitted_h), h_stderr


def _refined_level_errors(means_A: Any, theta_cov: Any, residuals: _ResidualSums) -> Any:
    """Standard errors of the levels after the trajectory fit, each the mean energy at its
    parameters (means_A theta - means_b).

    The variance adds what the parameters' covariance puts into each mean to that of the
    mean of its energy residuals, which are white once the parameters are right (each is
    the energy of one sample's measurement noise).
    """
    n, squares = residuals.n, residuals.sums[:, 3]
    mean_noise = squares / np.maximum(n * (n - 1), 1)
    return np.sqrt(np.einsum("jk,kl,jl->j", means_A, theta_cov, means_A) + mean_noise)


def _levels(labels: tuple[str | int, ...], h: Any, stderr: Any,
            sizes: list[int]) -> tuple[EnergyLevel, ...]:
    return tuple(EnergyLevel(label, float(level), _finite_or_none(error), size)
                 for label, level, error, size in zip(labels, h, stderr, sizes, strict=True))


def _result(m: Model, names: list[str], fixed: dict[str, float], theta: Any, theta_cov: Any,
            df: int, *, truth: dict[str, float], levels: tuple[EnergyLevel, ...],
            stats: dict[str, Any], cond: Any, block_conditions: dict[str, float] | None,
            notes: tuple[str, ...], data_info: dict[str, Any], method_info: dict[str, Any],
            dissipation: dict[str, Any] | None, samples: dict[str, Any] | None) -> FitResult:
    """The fit's report: estimates with bounds, levels, residuals, conditioning, warnings."""
    from hamid import uncertainty
    from hamid.result import _finite

    stderr = np.sqrt(np.clip(np.diag(theta_cov), 0, None))
    low, high = uncertainty.confidence_bounds(theta, stderr, df, method_info["level"])
    parameters = []
    free_index = 0
    for k, name in enumerate(names):
        role = "energy" if k < len(m.parameters) else "damping"
        if name in fixed:
            parameters.append(ParameterEstimate(name, role, fixed[name], None, None, None,
                                                truth.get(name), True))
            continue
        i, free_index = free_index, free_index + 1
        parameters.append(ParameterEstimate(
            name, role, float(theta[i]), _finite_or_none(stderr[i]),
            _finite_or_none(low[i]), _finite_or_none(high[i]), truth.get(name), False))
    warnings = [*notes, *_warnings(parameters, stats, cond, df, method_info["level"],
                                   method_info["covariance"], method_info["kind"],
                                   tuple(method_info["damping"]))]
    conditioning_info = {
        "condition_number": cond.condition_number,
        "singular_values": list(cond.singular_values),
        "weakest_direction": cond.weakest_direction, "status": cond.status,
        "blocks": block_conditions,
    }
    return FitResult(
        hamid_version=__version__,
        model=m.info(),
        data=_finite(data_info),
        method=_finite(method_info),
        parameters=tuple(parameters),
        energy_levels=levels,
        residuals=_finite(stats),
        conditioning=_finite(conditioning_info),
        warnings=tuple(warnings),
        dissipation=_finite(dissipation),
        samples=samples,
    )


@dataclass(frozen=True)
class _Loaded:
    """Records ready to fit, the model, and what the report says about the data."""

    model: Model
    records: Records
    truth: dict[str, float]
    data_info: dict[str, Any]
    notes: tuple[str, ...]
    velocity_gain: float | None  # noise gain of derived velocities, None when measured
    row_sources: tuple[tuple[str, int], ...]  # (source, first row) of each input table

    def locate(self, row: int) -> tuple[str, int]:
        """The source and 1-based data row of a row of the records."""
        source, first = next((s, f) for s, f in reversed(self.row_sources) if f <= row)
        return source, row - first + 1


# Files larger than this are read in chunks when the options allow it: the chunked fit is
# the fit in memory, faster and in a third of the memory.
STREAM_BYTES = 64 << 20
CHUNK_ROWS = 1 << 18
# The trajectory refinement of a chunked fit holds the records (times, states, trajectory
# numbers) in memory, 8 bytes a value; larger records are left unrefined.
REFINEMENT_BYTES = 1 << 30


def _reads_in_chunks(data: Any) -> bool:
    """Whether a fit that can read `data` in chunks should, by its size."""
    return os.path.getsize(data) > STREAM_BYTES


def _needs_memory(data: Any, velocity: str, noise: Any, damping: str | Sequence[str],
                  cov: str) -> str:
    """Why the fit needs all the data in memory, or "" when it can read them in chunks."""
    if not isinstance(data, str | os.PathLike) or os.fspath(data) == "-" \
            or not os.path.isfile(data):
        return "chunks need one file (not standard input, a list or a DataFrame)"
    if velocity != "measured":
        return "derived velocities (--velocity savgol) need the data in memory"
    if noise not in (None, "none"):
        return "noise weighting (--noise) needs the data in memory"
    if _parse_damping(damping):
        return "damping (--damping) needs the data in memory"
    if cov == "bootstrap":
        return "--cov bootstrap needs the data in memory"
    return ""


def _check_choice(value: str, choices: tuple[str, ...], option: str) -> None:
    if value not in choices:
        raise UsageError(f"{option} must be one of {', '.join(choices)}, found {value!r}")


def _build_blocks(kind: str, kind_reason: str, window: float | None, method: str,
                  weak_window: float | None, m: Model, records: Records, energy_rows: Block,
                  dissipation: Any, free: list[int], fixed_values: Any,
                  free_names: list[str]) -> tuple[str, str, float | None, Any, list[Block]]:
    """The row blocks of the chosen method (energy rows, weak rows, or both).

    Windows are the independent units of the weak and joint errors, so more are needed
    than unknowns (the levels count in joint); `auto` falls back to the energy rows when
    the records hold too few.
    """
    from hamid import design

    spans = design.windows(records, window) if kind != "energy" else None
    needed = len(free) + (records.n_trajectories if kind == "joint" else 0) + 1
    if spans is not None and spans.n_windows < needed:
        shortage = (f"the records hold {spans.n_windows} weak-form windows of {window:.3g} s, "
                    f"fewer than the {needed} that {needed - 1} unknowns need")
        if method == "auto" and weak_window is None:
            kind, kind_reason, window, spans = (
                "energy", f"{shortage}; fitted the energy rows", None, None)
        elif spans.n_windows > 0:
            raise FitError(f"cannot determine {', '.join(free_names)}: {shortage}; use "
                           "--method energy or a shorter --weak-window")
    blocks = []
    if kind == "energy":
        blocks.append(energy_rows)
    if kind in ("weak", "joint"):
        if kind == "joint":
            blocks.append(design.window_means(energy_rows, spans))
        weak = design.weak_block(m, records, spans, dissipation)
        bad = np.flatnonzero(~np.all(np.isfinite(np.column_stack([weak.A, weak.b])), axis=1))
        if bad.size:
            raise DataError(f"the weak-form rows are not finite (window at t = "
                            f"{weak.time[bad[0]]:g} of trajectory "
                            f"{records.labels[weak.group[bad[0]]]}): the energy's derivatives "
                            "are not finite there; use --method energy")
        if weak.n_rows == 0:
            raise DataError(f"the records are too short for one weak-form window of "
                            f"{window:.4g} s; use --method energy or a shorter --weak-window")
        blocks.append(_hold_fixed(weak, free, fixed_values))
    return kind, kind_reason, window, spans, blocks


def _choose_method(method: str, model: Model, scales: list[tuple[float | None, float]] | None,
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


def _refinement_obstacle(cov: str, bias_correct: bool, damping: tuple[str, ...]) -> str | None:
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


def _refinement_note(info: dict[str, Any]) -> str:
    """What the method's reason adds about the trajectory refinement."""
    if info["applied"]:
        return "; refined by fitting the integrated trajectories"
    return f"; not refined by fitting trajectories: {info['reason']}"


def _refine(m: Model, records: Records, dissipation: Any, free: list[int],
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


def _check_fixed(fix: Mapping[str, float], parameters: tuple[str, ...]) -> dict[str, float]:
    import math

    for name, value in fix.items():
        if name not in parameters:
            raise UsageError(f"--fix: {name!r} is not a parameter of the model "
                             f"({', '.join(parameters)})")
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise UsageError(f"--fix: {name}={value!r} is not a finite number")
    return {name: float(value) for name, value in fix.items()}


def _check_finite(block: Block, locate: Callable[[int], tuple[str, int]],
                  names: list[str]) -> None:
    """Energy terms must be finite at every sample (data inside the energy's domain)."""
    if np.isfinite(block.A.sum() + block.b.sum()):   # a finite sum has finite terms
        return
    values = np.column_stack([block.b, block.A])
    bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
    if not bad.size:
        return
    row = int(bad[0])
    column = int(np.flatnonzero(~np.isfinite(values[row]))[0])
    term = "the parameter-free part" if column == 0 else f"the term of {names[column - 1]!r}"
    source, local = locate(row)
    raise DataError(f"{source}: row {local}: {term} of the energy is not finite there "
                    "(the data are outside the energy's domain, or too large)")


def _hold_fixed(block: Block, free: list[int], values: Any) -> Block:
    """Move the terms of fixed parameters into the known side of the rows."""
    import dataclasses

    if len(free) == block.A.shape[1]:
        return block
    return dataclasses.replace(block, A=block.A[:, free], b=block.b - block.A @ values)


def _finite_or_none(x: float) -> float | None:
    import math

    x = float(x)
    return x if math.isfinite(x) else None


@dataclass(frozen=True)
class _Estimate:
    """One least-squares solution of stacked blocks, with what the covariances need."""

    theta: Any
    h: Any
    residual: Any      # unweighted, all blocks stacked
    weight: Any
    group: Any
    centred: Any
    solution: Any
    df_resid: int


def _least_squares(blocks: list[Block], names: list[str], J: int,
                   correction: tuple[Any, Any] | None = None) -> _Estimate:
    """Solve stacked blocks; with `correction` (noise-bias terms), adjusted least squares."""
    from hamid import solve

    has_levels = any(b.has_level for b in blocks)
    centred = solve.centre(blocks, J)
    if correction is None:
        solution = solve.solve(centred, names, n_levels=J if has_levels else 0)
    else:
        solution = solve.solve_adjusted(centred, *correction, names)
    theta = solution.theta
    h = centred.level_means_A @ theta - centred.level_means_b
    residual = np.concatenate([b.A @ theta - b.b - (h[b.group] if b.has_level else 0.0)
                               for b in blocks])
    return _Estimate(theta, h, residual, np.concatenate([b.weight for b in blocks]),
                     np.concatenate([b.group for b in blocks]), centred, solution,
                     len(residual) - len(names) - (J if has_levels else 0))


def _covariance(cov: str, fit: _Estimate, units: Any, unit_group: Any) -> Any:
    """Covariance of a fit: the analytic kinds of `hamid.uncertainty` on the right rows.

    Rows are first summed into their units (windows, when weak-form rows are present: a
    window's energy row and its weak rows share samples), so that ``hac`` runs Newey-West
    over the time series of window scores of each trajectory. Its automatic bandwidth
    grows with their autocorrelation: overlapping windows, and the long memory that the
    cumulative work of an energy balance brings.
    """
    import dataclasses

    from hamid import uncertainty

    # A trajectory too short for any window has no weak rows: number the ones present.
    present, group = np.unique(fit.group, return_inverse=True)
    n_units = len(unit_group)
    if n_units == len(units) and np.array_equal(units, np.arange(n_units)):
        c = uncertainty.covariance(cov, fit.solution.G, fit.centred.level_weight,
                                   fit.residual, fit.weight, group, df_resid=fit.df_resid)
    else:
        order = np.argsort(group, kind="stable")
        c = uncertainty.covariance(cov, fit.solution.G[order],
                                   fit.centred.level_weight[order], fit.residual[order],
                                   fit.weight[order], group[order], df_resid=fit.df_resid,
                                   units=units[order] if cov == "hac" else None)
    J = fit.centred.level_means_A.shape[0]
    if len(present) == J:
        return c
    level = np.full(J, np.nan)
    level[present] = c.level
    theta_level = np.full((J, c.theta.shape[0]), np.nan)
    theta_level[present] = c.theta_level
    return dataclasses.replace(c, level=level, theta_level=theta_level)


def _balance_blocks(blocks: list[Block], names: list[str], J: int, units: Any,
                    unit_group: Any) -> tuple[list[Block], dict[str, float] | None]:
    """Weight the blocks of a joint fit against each other (`_balanced_ratio`).

    The starting point is feasible GLS: each block's row weights scaled by the inverse of
    its weighted residual variance from a fit of that block alone.
    """
    import dataclasses

    if len(blocks) == 1:
        return blocks, None
    variance = {}
    for block in blocks:
        try:
            residual = _least_squares([block], names, J).residual
            variance[block.kind] = max(float(np.mean(block.weight * residual**2)), _TINY)
        except FitError:
            variance[block.kind] = max(float(np.mean(block.weight * block.b**2)), _TINY)
    first, rest = blocks[0], blocks[1:]

    def weighted(ratio: float) -> list[Block]:
        return [dataclasses.replace(first, weight=first.weight * ratio / variance[first.kind]),
                *(dataclasses.replace(b, weight=b.weight / variance[b.kind]) for b in rest)]

    def spread(ratio: float) -> float:
        fit = _least_squares(weighted(ratio), names, J)
        return _log_spread(_covariance("hac", fit, units, unit_group).theta)

    best = _balanced_ratio(spread)
    return weighted(best), _balanced_variance(variance, first.kind, best)


def _balanced_ratio(spread: Callable[[float], float]) -> float:
    """The weight of the first block against the others (each already divided by its
    residual variance) that minimises `spread`, the log-determinant of the parameters'
    robust (``hac``) covariance at that ratio, which does not depend on their units.

    Rows of overlapping windows are correlated, and differently in the two blocks, so
    the variance guess (ratio 1) can be far from best. The ratio is chosen on a grid of
    half decades: the search walks down the whole decades from the guess, then tries the
    half decades beside the lowest. On every test system the decades' spreads fall to one
    minimum, which a walk finds with a third of the fits.
    """
    spreads: dict[float, float] = {}

    def at(exponent: float) -> float:
        if exponent not in spreads:
            spreads[exponent] = spread(10.0**exponent)
        return spreads[exponent]

    # down the whole decades from the guess until neither neighbour is lower, then the
    # half decades beside that one
    exponent = 0.0
    while True:
        lowest = min((e for e in (exponent - 1, exponent + 1) if abs(e) <= 4), key=at)
        if at(lowest) >= at(exponent):
            break
        exponent = lowest
    for half in (exponent - 0.5, exponent + 0.5):
        if abs(half) < 4:
            at(half)
    return 10.0 ** min(spreads, key=spreads.__getitem__)


def _log_spread(covariance: Any) -> float:
    """log det of a covariance; infinite when it is not positive definite."""
    sign, logdet = np.linalg.slogdet(covariance)
    return logdet if sign > 0 else np.inf


def _balanced_variance(variance: dict[str, float], first: str,
                      ratio: float) -> dict[str, float]:
    """Each block's residual variance as its weight in the balanced fit implies."""
    return {k: v / (ratio if k == first else 1.0) for k, v in variance.items()}


_TINY = 1e-300


def _resampling_units(blocks: list[Block], kind: str) -> tuple[Any, Any]:
    """Units of the robust covariances and the bootstrap, and the trajectory of each.

    Energy rows alone: every row is a unit (the HAC kernel and moving blocks handle their
    correlation). With weak-form rows: windows, each holding its weak rows and its energy
    row, numbered in time order within each trajectory.
    """
    group = np.concatenate([b.group for b in blocks])
    if kind == "energy":
        return np.arange(len(group)), group
    time = np.concatenate([b.time for b in blocks])
    order = np.lexsort((time, group))
    fresh = np.ones(len(order), dtype=bool)
    fresh[1:] = (np.diff(group[order]) != 0) | (np.diff(time[order]) != 0)
    units = np.empty(len(order), dtype=np.int64)
    units[order] = np.cumsum(fresh) - 1
    unit_group = np.zeros(units.max() + 1, dtype=np.int64)
    unit_group[units] = group
    return units, unit_group


def _level_variance(c: Any, Abar: Any) -> Any:
    """Var(h_j) from a covariance's blocks (see `hamid.uncertainty`)."""
    return (c.level - 2 * np.einsum("jp,jp->j", Abar, c.theta_level)
            + np.einsum("jp,pq,jq->j", Abar, c.theta, Abar))


def _bootstrap_covariance(blocks: list[Block], names: list[str], J: int, units: Any,
                          unit_group: Any, n_boot: int,
                          seed: int | None) -> tuple[Any, Any, str]:
    """Covariance of theta and the levels from refits on resampled blocks of units."""
    import dataclasses

    from hamid import uncertainty

    p = len(names)
    offsets = np.cumsum([0] + [b.n_rows for b in blocks])
    # Rows of each unit, found by one sort (a scan per unit would be quadratic in rows).
    by_unit = np.argsort(units, kind="stable")
    first_row = np.searchsorted(units[by_unit], np.arange(len(unit_group) + 1))

    def refit(index: Any) -> Any:
        rows = np.concatenate([by_unit[first_row[u]:first_row[u + 1]] for u in index])
        sample = []
        for b, lo, hi in zip(blocks, offsets[:-1], offsets[1:], strict=True):
            mine = rows[(rows >= lo) & (rows < hi)] - lo
            sample.append(dataclasses.replace(b, A=b.A[mine], b=b.b[mine], group=b.group[mine],
                                              time=b.time[mine], weight=b.weight[mine]))
        estimate = _least_squares(sample, names, J)
        return np.concatenate([estimate.theta, estimate.h])

    # Resample within the trajectories present (one too short for a window has no units).
    dense = np.unique(unit_group, return_inverse=True)[1]
    cov, _, description = uncertainty.bootstrap(refit, dense, n_boot=n_boot, seed=seed)
    return cov[:p, :p], np.diag(cov)[p:], description


def _with_propagated_noise(theta_cov: Any, text: str, estimate: _Estimate,
                           blocks: list[Block], model: Model, records: Records, sigma: Any,
                           free: list[int], fixed_values: Any, spans: Any,
                           damping: Any) -> tuple[Any, str]:
    """Damped fits: no parameter's variance below what the measurement noise alone causes.

    The energy balance's cumulative work carries each sample's noise into every later
    row, a long memory that residual-based estimates miss; the noise-propagated
    covariance (noise from --noise, else estimated from the data) sees it. Each
    parameter's variance is the larger of the two, its correlations those of the first.
    """
    from hamid import design, measurement

    if sigma is None:
        sigma = measurement.estimate_noise(records.X, records.bounds())
    full = fixed_values.copy()
    full[free] = estimate.theta
    propagated = design.propagated_covariance(blocks, estimate.solution.G, model, records,
                                              full, sigma, spans, damping)
    old = np.sqrt(np.clip(np.diag(theta_cov), 0, None))
    new = np.sqrt(np.maximum(np.diag(theta_cov), np.diag(propagated)))
    ratio = np.divide(new, old, out=np.ones_like(new), where=old > 0)
    return (theta_cov * np.outer(ratio, ratio),
            text + "; each variance at least the one propagated from the measurement noise")


def _fitted_energy(rows: Block, model: Model, estimates: dict[str, float]) -> Any:
    """E(x_i; theta) at every sample, from the energy rows already built (A theta - b)."""
    n_energy = len(model.parameters)
    theta = np.array([estimates[name] for name in model.parameters])
    return rows.A[:, :n_energy] @ theta - rows.b


def _sample_weights(kind: str, blocks: list[Block], energy_rows: Block, spans: Any) -> Any:
    """The weight each sample's energy equation carried in the fit.

    In `joint` the energy rows are window means, so a sample's weight is its share of the
    windows that hold it; in `weak` the energy equations were not fitted (weight 0).
    """
    if kind == "energy":
        return blocks[0].weight
    if kind == "weak":
        return np.zeros(energy_rows.n_rows)
    return spans.means.T @ blocks[0].weight


def _block_report(blocks: list[Block], residual: Any, names: list[str],
                  labels: tuple[str | int, ...]) -> tuple[dict[str, Any], Any,
                                                         dict[str, float] | None]:
    """Residual summary of each block, the conditioning of all, and of each block alone
    (when there are several)."""
    from hamid import solve

    pieces = np.split(residual, np.cumsum([b.n_rows for b in blocks])[:-1])
    stats = {b.kind: _block_stats(r) for b, r in zip(blocks, pieces, strict=True)}
    each = {b.kind: solve.conditioning([b], names, labels).condition_number
            for b in blocks} if len(blocks) > 1 else None
    return stats, solve.conditioning(blocks, names, labels), each


def _block_stats(residual: Any) -> dict[str, Any]:
    return {"n_rows": len(residual), "rms": float(np.sqrt(np.mean(residual**2))),
            "max_abs": float(np.max(np.abs(residual)))}


class _ResidualSums:
    """Sums over the energy rows that the residual summary needs (SPEC section 4,
    residuals), fed with each trajectory's rows in time order, in one piece or many."""

    def __init__(self, h: Any) -> None:
        J = len(h)
        self.h = h
        self.n = np.zeros(J)
        self.origin = np.full((J, 2), np.nan)   # first t and b: sums are taken about them
        self.sums = np.zeros((J, 8))   # t, t^2, r, r^2, t r, b, b^2, r_k r_k+1
        self.max_abs = 0.0
        self.last = np.full(J, np.nan)
        self.end = np.zeros(J)   # last t, from the first

    def add(self, block: Block, residual: Any) -> None:
        from hamid.design import runs

        for j, start, stop in runs(block.group):
            t, b, r = block.time[start:stop], block.b[start:stop], residual[start:stop]
            if self.n[j] == 0:
                self.origin[j] = t[0], b[0]
            t, b = t - self.origin[j, 0], b - self.origin[j, 1]
            lagged = self.last[j] * r[0] + r[1:] @ r[:-1] if self.n[j] else r[1:] @ r[:-1]
            self.sums[j] += [t.sum(), t @ t, r.sum(), r @ r, t @ r, b.sum(), b @ b, lagged]
            self.n[j] += len(r)
            self.last[j] = r[-1]
            self.end[j] = t[-1]
            self.max_abs = max(self.max_abs, float(np.max(np.abs(r))))

    def stats(self, labels: tuple[str | int, ...]) -> dict[str, Any]:
        n = self.n
        st, stt, sr, srr, str_, sb, sbb, lagged = self.sums.T
        total_squares = float(srr.sum())
        rms = float(np.sqrt(total_squares / n.sum()))
        mean_level = float(np.mean(np.abs(self.h)))
        total = float(np.sum(sbb - sb**2 / n))
        drift = []
        for j, label in enumerate(labels):
            # The trend in closed form, on time u scaled to the record (change over it).
            span = float(self.end[j])
            spread_t = float(stt[j] - st[j] ** 2 / n[j])
            spread_u = (np.sqrt(max(spread_t, 0.0)) / span) ** 2 if n[j] > 2 and span > 0 \
                else 0.0
            spread_r = float(srr[j] - sr[j] ** 2 / n[j])
            product = float(str_[j] - st[j] * sr[j] / n[j]) / span if spread_u > 0 else 0.0
            change = product / spread_u if spread_u > 0 else 0.0
            explained = change**2 * spread_u / spread_r if spread_r > 0 else 0.0
            drift.append({"trajectory": label,
                          "relative_change": change / abs(self.h[j]) if self.h[j] else None,
                          "trend_share": explained})
        return {
            "rms": rms,
            "max_abs": self.max_abs,
            "relative_rms": rms / mean_level if mean_level > 0 else None,
            "r_squared": 1 - total_squares / total if total > 0 else None,
            "lag1_autocorrelation": float(lagged.sum()) / total_squares if rms > 0 else None,
            "drift": drift,
        }


# A drift is reported when the energy changes by more than this fraction over the record
# and a straight line in time explains this share of the residual variance.
_DRIFT_CHANGE, _DRIFT_SHARE = 0.01, 0.2


def _parse_damping(damping: str | Sequence[str]) -> tuple[str, ...]:
    """Damping kinds from "none", "viscous,coulomb" or a list; unknown kinds are errors."""
    from hamid.model import DAMPING_KINDS

    items = damping.split(",") if isinstance(damping, str) else list(damping)
    kinds = [item.strip() for item in items if item.strip()]
    if not kinds:
        raise UsageError("--damping: empty value; expected none or any of "
                         f"{', '.join(DAMPING_KINDS)} (comma separated)")
    if kinds == ["none"]:
        return ()
    for kind in kinds:
        if kind not in DAMPING_KINDS:
            raise UsageError(f"--damping: unknown kind {kind!r} (choose none or any of "
                             f"{', '.join(DAMPING_KINDS)}, comma separated)")
    if len(set(kinds)) != len(kinds):
        raise UsageError(f"--damping: a kind is given twice in {','.join(kinds)!r}")
    return tuple(kinds)


def _dissipation_summary(model: Model, records: Records, damping: Any,
                         estimates: dict[str, float], energy_rows: Block,
                         h: Any) -> dict[str, Any] | None:
    """Energy lost per trajectory and, for one viscous coordinate, the damping ratio.

    The energy lost is the fitted dissipated work over the record divided by the energy
    above the lowest potential energy seen on the trajectory.
    """
    from hamid import design

    if not damping.kinds:
        return None
    n_energy = len(model.parameters)
    coefficients = np.array([estimates[name] for name in damping.names])
    work = energy_rows.A[:, n_energy:] @ coefficients if energy_rows.A.shape[1] > n_energy \
        else np.zeros(energy_rows.n_rows)
    theta = [estimates[name] for name in model.parameters]
    at_rest = records.X.copy()
    at_rest[:, len(model.coordinates):] = 0.0
    potential = model.total_energy(at_rest, theta)
    trajectories = []
    for j, (start, stop) in enumerate(records.bounds()):
        available = h[j] - potential[start:stop].min()
        trajectories.append({"trajectory": records.labels[j],
                             "energy_lost_fraction": float(work[stop - 1] / available)
                             if available > 0 else None})
    period = design.dominant_period(records, len(model.coordinates))
    ratio = None
    if len(model.coordinates) == 1 and "viscous" in damping.kinds and period and \
            model.is_natural:
        moving = at_rest.copy()
        moving[:, 1] = 1.0
        mass = float(np.mean(model.total_energy(moving, theta) - potential)) * 2
        ratio = estimates[f"c_{model.coordinates[0]}"] * period / (4 * np.pi * mass)
    return {"trajectories": trajectories, "equivalent_damping_ratio": ratio,
            "period": period}


def _warnings(parameters: list[ParameterEstimate], stats: dict[str, Any], cond: Any,
              df: int, level: float, cov: str, kind: str,
              damping: tuple[str, ...]) -> list[str]:
    """Plain-words warnings about the fit."""
    from hamid.uncertainty import t_quantile

    notes = []
    for d in stats["drift"]:
        change = d["relative_change"]
        if change is not None and abs(change) > _DRIFT_CHANGE and d["trend_share"] > _DRIFT_SHARE:
            notes.append(f"trajectory {d['trajectory']}: the energy drifts by {change:+.1%} "
                         "over the record; the system may be damped or forced "
                         "(try --damping viscous)" if not damping else
                         f"trajectory {d['trajectory']}: the energy balance still drifts by "
                         f"{change:+.1%} over the record with {', '.join(damping)} damping; "
                         "try another kind of --damping, or the system is forced")
    if cond.status != "ok":
        combination = " ".join(f"{w:+.2f}*{n}" for n, w in
                               sorted(cond.weakest_direction.items(), key=lambda x: -abs(x[1]))
                               if abs(w) >= 0.05)
        notes.append(f"the problem is {'severely' if cond.status == 'severe' else 'moderately'}"
                     f" ill-conditioned (condition number {cond.condition_number:.3g}); the "
                     f"data determine {combination} worst: record larger amplitudes or add a "
                     "trajectory at another energy")
    critical = t_quantile(df, level)
    for p in parameters:
        if p.stderr is not None and abs(p.estimate) < critical * p.stderr:
            notes.append(f"{p.name} is not significantly different from zero "
                         f"(its {level:.0%} interval contains 0)")
    autocorrelation = stats["lag1_autocorrelation"]
    if cov in ("classical", "hc") and kind != "energy":
        notes.append(f"--cov {cov} treats overlapping weak-form windows as independent and "
                     "understates the errors; use --cov hac")
    elif cov in ("classical", "hc") and autocorrelation is not None and autocorrelation > 0.5:
        notes.append(f"residuals are strongly autocorrelated (lag-1 {autocorrelation:.2f}); "
                     f"--cov {cov} understates the errors, use --cov hac")
    return notes


def _load_data(data: Any, model: str | os.PathLike[str] | Model | None, *,
               columns: Mapping[str, str] | None, time: str | None,
               trajectory: str | None, format: str | None, velocity: str = "measured",
               window: int | None = None, order: int = SAVGOL_ORDER) -> _Loaded:
    """Read the sources, settle the model and arrange the rows by trajectory."""
    from hamid import io, naming

    if _is_data_frame(data):
        tables = [("<DataFrame>", data, data.attrs.get("hamid"))]
    else:
        paths = [data] if isinstance(data, str | os.PathLike) else list(data)
        if not paths:
            raise UsageError("no data given")
        tables = [(os.fspath(p) if os.fspath(p) != "-" else "<stdin>",
                   *io.read_columns(p, format=format)) for p in paths]
    first_name, first_table, metadata = tables[0]
    notes = []
    if isinstance(model, Model):
        m = model
    elif model is not None:
        m = load_model(model)
    elif metadata and isinstance(metadata.get("model"), Mapping):
        m = _model_from_metadata(metadata["model"], first_name)
    else:
        m = _assumed_model([str(c) for c in first_table], first_name, columns,
                           time, trajectory)
        notes.append(f"no model given: assumed {m.name} over the coordinates "
                     f"{', '.join(m.coordinates)} (pick one with --model)")

    X_parts, t_parts, group_parts, labels, mapping = [], [], [], [], {}
    has_time = True
    for source, frame, _ in tables:
        names = [str(c) for c in frame]
        derived = velocity == "savgol"
        mapping = naming.resolve_columns(names, m.coordinates, () if derived else m.velocities,
                                     mapping=columns, source=source)
        time_col = _optional_column(names, time, naming.default_time_column(names), "--time",
                                    source)
        traj_col = _optional_column(names, trajectory, naming.default_trajectory_column(names),
                                    "--trajectory", source)
        n_rows = len(frame[names[0]])
        X = np.column_stack([io.numeric_column(frame, mapping[v], source=source)
                             if v in mapping else np.zeros(n_rows) for v in m.variables])
        t = io.numeric_column(frame, time_col, source=source) if time_col else None
        has_time = has_time and t is not None
        if traj_col is None:
            keys = np.zeros(n_rows, dtype=np.int64)
            traj_labels = [source if len(tables) > 1 else 1]
        else:
            keys, traj_labels = _trajectory_keys(io.column_values(frame[traj_col]), traj_col,
                                                 source)
            if len(tables) > 1:
                traj_labels = [f"{source}:{label}" for label in traj_labels]
        _check_order(keys, t, source, traj_col, time_col)
        X_parts.append(X)
        t_parts.append(t)
        group_parts.append(keys + len(labels))
        labels.extend(traj_labels)
    records = Records(np.vstack(X_parts),
                      np.concatenate(t_parts) if has_time else None,
                      np.concatenate(group_parts), tuple(labels))
    derivation = None
    if velocity == "savgol":
        records, derivation = _derive_velocities(records, m, window, order)
    truth = _truth(metadata, m)
    data_info = {
        "sources": [name for name, _, _ in tables],
        "n_samples": int(len(records.group)),
        "n_trajectories": records.n_trajectories,
        "columns": dict(mapping),
        "velocity_source": velocity,
        **({"velocity_window": derivation[0], "velocity_order": order}
           if derivation else {}),
    }
    if derivation:
        notes.append(f"velocities derived from the positions (Savitzky-Golay, window "
                     f"{derivation[0]} samples, order {order}); their noise is correlated "
                     "with the positions'")
    firsts = np.cumsum([0] + [len(frame) for _, frame, _ in tables[:-1]])
    return _Loaded(m, records, truth, data_info, tuple(notes),
                   derivation[1] if derivation else None,
                   tuple((name, int(f)) for (name, _, _), f in zip(tables, firsts, strict=True)))


def _truth(metadata: Mapping[str, Any] | None, m: Model) -> dict[str, float]:
    """The true parameters a simulated file records for this model, else none."""
    if not (metadata and isinstance(metadata.get("model"), Mapping)
            and metadata["model"].get("energy") == m.energy):
        return {}
    # A simulated record had no damping but what its [damping] table lists.
    undamped = dict.fromkeys(damping_names(m.coordinates), 0.0) \
        if isinstance(metadata.get("damping"), Mapping) else {}
    values = {**undamped, **(metadata.get("parameters") or {}),
              **(metadata.get("damping") or {})}
    return {k: float(v) for k, v in values.items() if isinstance(v, int | float)}


def _derive_velocities(records: Records, model: Model, window: int | None,
                       order: int) -> tuple[Records, tuple[int, float]]:
    """Records whose velocities come from Savitzky-Golay differentiation of the positions."""
    import dataclasses

    from hamid import design, measurement

    if records.t is None:
        raise UsageError("--velocity savgol needs a time column")
    N = len(model.coordinates)
    if window is None:
        period = design.dominant_period(records, N)
        dt = float(np.median(np.diff(records.t)))
        window = measurement.default_savgol_window(None if period is None else period / dt,
                                                   order)
    V, gain = measurement.savgol_velocities(records.X[:, :N], records.t, records.bounds(),
                                            window=window, order=order)
    X = records.X.copy()
    X[:, N:] = V
    return dataclasses.replace(records, X=X), (window, gain)


def _noise_levels(noise: str | Mapping[str, float] | None, model: Model, records: Records,
                  loaded: _Loaded) -> tuple[Any, dict[str, float] | None]:
    """Noise std per model variable, from the user or estimated; None without --noise."""
    import math

    from hamid import measurement

    if noise is None or noise == "none":
        return None, None
    N = len(model.coordinates)
    columns = loaded.data_info["columns"]
    if noise == "auto":
        sigma = measurement.estimate_noise(records.X, records.bounds())
    elif isinstance(noise, Mapping):
        by_column = {column: name for name, column in columns.items()}
        sigma = np.zeros(len(model.variables))
        for key, value in noise.items():
            name = key if key in model.variables else by_column.get(key)
            if name is None:
                raise UsageError(f"--noise: {key!r} is not a column of the model "
                                 f"({', '.join(model.variables)})")
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise UsageError(f"--noise: {key}={value!r} is not a non-negative number")
            sigma[model.variables.index(name)] = float(value)
    else:
        raise UsageError(f"--noise must be none, auto or COL=SIGMA,..., found {noise!r}")
    if loaded.velocity_gain is not None:
        sigma[N:] = sigma[:N] * loaded.velocity_gain
    if not np.any(sigma > 0):
        raise UsageError("--noise: every column has zero noise; leave --noise out instead")
    return sigma, {name: float(s) for name, s in zip(model.variables, sigma, strict=True)}


def _noise_weighted(blocks: list[Block], model: Model, records: Records, spans: Any,
                    damping: Any, sigma: Any, free: list[int], fixed_values: Any,
                    names: list[str], J: int, units: Any,
                    unit_group: Any) -> tuple[list[Block], dict[str, float] | None, int]:
    """Weight every row by the inverse of the variance the noise puts into it, iterated.

    The variance depends on the parameters, so fit, re-weight and refit until the
    parameters settle (relative change below 1e-10, at most `_MAX_ROUNDS`). In a joint
    fit the two blocks are then balanced as without noise (`_balance_blocks`): the rows
    of overlapping windows are correlated, which the row variances do not see.
    """
    import dataclasses

    from hamid import design

    unit_size = [dataclasses.replace(b, weight=b.weight / max(float(np.mean(b.b**2)), _TINY))
                 for b in blocks]
    theta = _least_squares(unit_size, names, J).theta
    rounds, settled = 0, False
    while not settled and rounds < _MAX_ROUNDS:
        rounds += 1
        full = fixed_values.copy()
        full[free] = theta
        weighted = []
        for block in blocks:
            variance = design.row_variance(block, model, records, full, sigma, spans, damping)
            positive = variance[variance > 0]
            floor = 1e-12 * float(np.median(positive)) if positive.size else 1.0
            weighted.append(dataclasses.replace(block,
                                                weight=1.0 / np.maximum(variance, floor)))
        weighted, block_variance = _balance_blocks(weighted, names, J, units, unit_group)
        new = _least_squares(weighted, names, J).theta
        settled = bool(np.all(np.abs(new - theta) <= 1e-10 * np.abs(new)))
        theta = new
    scale = float(np.mean(np.concatenate([b.weight for b in weighted])))
    return ([dataclasses.replace(b, weight=b.weight / scale) for b in weighted],
            block_variance, rounds)


_MAX_ROUNDS = 20


def _model_from_metadata(info: Mapping[str, Any], source: str) -> Model:
    """The model a simulated file records (built-in by name, else from its energy)."""
    name = info.get("name")
    if isinstance(name, str) and (name in BUILTINS or name.startswith("poly:")):
        candidate = builtin_model(name)
        if candidate.energy == info.get("energy"):
            return candidate
    try:
        return model_from_expression(str(name or "custom"), info["energy"],
                                     info["coordinates"], info["velocities"],
                                     info.get("parameters"), where=f"{source}: metadata model")
    except (KeyError, TypeError) as exc:
        raise DataError(f"{source}: the hamid metadata has no usable model ({exc}); "
                        "give one with --model") from exc


def _assumed_model(names: list[str], source: str, columns: Mapping[str, str] | None,
                   time: str | None, trajectory: str | None) -> Model:
    """poly:N:3 over every column that has a velocity column (SPEC section 3, fit)."""
    from hamid import naming
    from hamid.model import poly_model_over

    exclude = {c for c in (time or naming.default_time_column(names),
                           trajectory or naming.default_trajectory_column(names)) if c}
    pairs = naming.find_coordinates(names, exclude=exclude)
    if not pairs:
        raise DataError(f"{source}: no model given and no coordinate with a velocity column "
                        f"found (columns: {', '.join(names)}); give --model, or name "
                        "velocities vx, x_dot, xdot or dx")
    if columns:
        raise UsageError("--columns needs --model (the assumed model takes the file's names)")
    return poly_model_over([q for q, _ in pairs], [v for _, v in pairs])


def _optional_column(names: list[str], asked: str | None, default: str | None, option: str,
                     source: str) -> str | None:
    if asked is None:
        return default
    if asked not in names:
        raise DataError(f"{source}: no column {asked!r} for {option} "
                        f"(columns: {', '.join(names)})")
    return asked


def _trajectory_keys(values: np.ndarray, column: str, source: str) -> tuple[Any, list[Any]]:
    """Index 0..J-1 of each row's trajectory, in order of first appearance, and the labels."""
    from hamid.io import is_missing

    if values.dtype.kind in "iu":
        missing = np.zeros(len(values), bool)
    elif values.dtype.kind == "f":
        missing = np.isnan(values)
    else:
        missing = np.fromiter((is_missing(v) for v in values), bool, len(values))
    if missing.any():
        row = int(np.flatnonzero(missing)[0]) + 1
        raise DataError(f"{source}: column {column!r}, row {row}: missing trajectory label")
    if values.dtype.kind in "iuf":
        uniques, first, codes = np.unique(values, return_index=True, return_inverse=True)
        order = np.argsort(first)
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        codes, uniques = rank[codes.ravel()], uniques[order]
    else:   # text or mixed objects, which need not sort
        index: dict[Any, int] = {}
        codes = np.fromiter((index.setdefault(v, len(index)) for v in values), np.int64,
                            len(values))
        uniques = list(index)
    return codes.astype(np.int64), [trajectory_label(u) for u in uniques]


def trajectory_label(value: Any) -> Any:
    """A trajectory column's value as the label reported: a Python scalar, whole numbers
    as int (a column with missing cells is read as floats)."""
    value = value.item() if hasattr(value, "item") else value
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _is_data_frame(data: Any) -> bool:
    """Whether `data` is a pandas DataFrame, without importing pandas when it cannot be."""
    pandas = sys.modules.get("pandas")
    return pandas is not None and isinstance(data, pandas.DataFrame)


def _check_order(keys: Any, t: Any, source: str, traj_col: str | None,
                 time_col: str | None) -> None:
    """Each trajectory's rows must be contiguous and, with a time column, increasing."""
    changes = np.flatnonzero(np.diff(keys)) + 1
    if len(np.unique(keys[np.concatenate([[0], changes])])) != len(changes) + 1:
        seen, row = set(), 0
        for start in np.concatenate([[0], changes]):
            if keys[start] in seen:
                row = int(start) + 1
                break
            seen.add(keys[start])
        raise DataError(f"{source}: column {traj_col!r}, row {row}: a trajectory resumes "
                        "after rows of another; sort the file by trajectory then time")
    if t is not None:
        step = np.diff(t)
        same = np.diff(keys) == 0
        bad = np.flatnonzero(same & ~(step > 0))
        if bad.size:
            row = int(bad[0]) + 2
            raise DataError(f"{source}: column {time_col!r}, row {row}: time does not increase "
                            f"({t[row - 2]:g} then {t[row - 1]:g})")
