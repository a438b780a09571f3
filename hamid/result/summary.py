"""The fit's report: estimates with bounds, levels, the residual summary, conditioning,
what the method did, per-sample rows, dissipation and warnings (docs/output.md)."""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hamid import __version__
from hamid.data import input_size, loading, readers
from hamid.data.records import Records
from hamid.errors import DataError, HamidError
from hamid.linear import design, uncertainty
from hamid.linear.design import RowKind
from hamid.linear.estimate import DISCRETIZATION_NOTE, LinearFit, NoiseCheck, ResidualSums, Rows
from hamid.linear.plan import FitPlan
from hamid.linear.unknowns import Unknowns
from hamid.model.dissipation import Dissipation
from hamid.model.models import Model
from hamid.options import FitOptions, percent
from hamid.refine.outcome import RefinementInfo
from hamid.result.fit_result import (
    EnergyLevel,
    FitResult,
    InputFile,
    ParameterEstimate,
    ProvenanceInfo,
    plain_data,
)
from hamid.result.wording import correlation_text, drift_words

__all__ = ["Provenance", "dissipation_summary", "fit_result", "run_provenance", "samples"]

# A drift is reported when the energy changes by more than this fraction over the record
# and a straight line in time explains this share of the residual variance.
_DRIFT_CHANGE, _DRIFT_SHARE = 0.01, 0.2
# Two estimates correlated beyond this the data hardly tell apart: a warning names them.
HIGH_CORRELATION = 0.99


@dataclass(frozen=True)
class Provenance:
    """What the report says about the data and how they were weighted."""

    data: dict[str, Any]
    labels: tuple[Any, ...]
    truth: dict[str, float]
    notes: tuple[str, ...]
    noise: dict[str, float] | None = None
    noise_check: NoiseCheck | None = None
    skipped: tuple[tuple[str, str], ...] = ()   # checks not made: (check, reason)


def fit_result(model: Model, unknowns: Unknowns, fit: LinearFit, residuals: ResidualSums,
               plan: FitPlan, options: FitOptions, provenance: Provenance,
               refinement: RefinementInfo | None, dissipation: dict[str, Any] | None = None,
               samples: dict[str, Any] | None = None,
               run: ProvenanceInfo | None = None,
               forcing: dict[str, Any] | None = None) -> FitResult:
    """The fit's report: estimates with bounds, levels, residuals, conditioning, warnings,
    the free parameters' covariance and the run's provenance (`run_provenance`); a driven
    fit's `forcing_summary` joins the data's part."""
    stderr = np.sqrt(np.clip(np.diag(fit.covariance), 0, None))
    low, high = uncertainty.confidence_bounds(fit.theta, stderr, fit.df, options.level)
    truth = provenance.truth
    parameters, free_index = [], 0
    for k, name in enumerate(unknowns.names):
        role = unknowns.role(k)
        if name in unknowns.fixed:
            parameters.append(ParameterEstimate(name=name, role=role,
                                                estimate=unknowns.fixed[name], stderr=None,
                                                ci_low=None, ci_high=None, truth=truth.get(name),
                                                fixed=True))
            continue
        i, free_index = free_index, free_index + 1
        parameters.append(ParameterEstimate(name=name, role=role, estimate=float(fit.theta[i]),
                                            stderr=_finite_or_none(stderr[i]),
                                            ci_low=_finite_or_none(low[i]),
                                            ci_high=_finite_or_none(high[i]),
                                            truth=truth.get(name), fixed=False))
    stats = {**residuals.stats(provenance.labels, driven=model.forcing is not None),
             "blocks": fit.block_stats}
    method = {
        "kind": plan.kind, "kind_reason": plan.reason, "weak_window": plan.window,
        "damping": list(options.damping),
        "weighting": "none" if provenance.noise is None else "noise",
        "noise": provenance.noise, "weighting_rounds": fit.weighting_rounds,
        "bias_correction": options.bias_correct, "covariance": options.cov,
        "covariance_description": fit.description, "level": options.level,
        "fixed": dict(unknowns.fixed),
        "scale": {**unknowns.scale, "per_unit_mass": model.per_unit_mass},
        "block_variance": fit.block_variance,
        "refinement": refinement,
        "discretization": None if fit.discretization is None else dict(
            zip(unknowns.free_names, fit.discretization.tolist(), strict=True)),
    }
    cond = fit.conditioning
    conditioning = {
        "condition_number": cond.condition_number,
        "singular_values": list(cond.singular_values),
        "weakest_direction": cond.weakest_direction, "status": cond.status,
        "blocks": fit.block_conditions,
        "strongest_correlation": strongest_correlation(
            [p.name for p in parameters if not p.fixed], fit.covariance),
    }
    levels = tuple(EnergyLevel(label, float(level), _finite_or_none(error), int(size))
                   for label, level, error, size in zip(provenance.labels, fit.h, fit.h_stderr,
                                                        fit.sizes, strict=True))
    integrated = tuple(q for q, kinds in (provenance.data.get("channels") or {}).items()
                       if "position" in kinds["reconstructed"])
    warnings = [*provenance.notes,
                *_warnings(parameters=parameters, stats=stats, cond=cond, df=fit.df,
                           options=options, kind=plan.kind, refinement=refinement,
                           damping=[*options.damping,
                                    *(["Rayleigh"] if model.dissipation else [])],
                           driven=model.forcing is not None, integrated=integrated),
                *_correlation_warnings(conditioning["strongest_correlation"],
                                       quadrature=DISCRETIZATION_NOTE in fit.description),
                *_noise_warnings(provenance.noise_check, _not_fitting(refinement)),
                *forcing_warnings(forcing)]
    return FitResult(
        hamid_version=__version__,
        model=model.info(),
        data=plain_data({**provenance.data, **({"forcing": forcing} if forcing else {})}),
        method=plain_data(method),
        parameters=tuple(parameters),
        energy_levels=levels,
        residuals=plain_data(stats),
        conditioning=plain_data(conditioning),
        warnings=tuple(warnings),
        dissipation=plain_data(dissipation),
        covariance={"names": [p.name for p in parameters if not p.fixed],
                    "matrix": plain_data(_symmetric(fit.covariance).tolist())},
        provenance=run,
        samples=samples,
        checks_skipped=tuple({"check": check, "reason": reason}
                             for check, reason in provenance.skipped),
    )


def run_provenance(data: Any, options: FitOptions) -> ProvenanceInfo:
    """The inputs (size, SHA-256), the time now (UTC), the versions of hamid, numpy, scipy
    and pyarrow, and the bootstrap's seed; `command` is None (the CLI sets it).

    Each file is hashed in one streaming pass of 1 MiB blocks (`io.file_digest`); a file
    that cannot be read is listed without size and digest, for the reading to report.
    """
    from datetime import UTC, datetime

    items = data if isinstance(data, list | tuple) else [data]
    return {
        "inputs": [_input_file(item) for item in items],
        "utc": datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "versions": {"hamid": __version__, "numpy": np.__version__,
                     "scipy": _version("scipy"), "pyarrow": _version("pyarrow")},
        "seed": options.seed if options.cov == "bootstrap" else None,
        "command": None,
    }


def _input_file(item: Any) -> InputFile:
    """Helper: one input's name, size and digest (None for stdin, a DataFrame, an error)."""
    if not isinstance(item, str | os.PathLike):
        return {"path": input_size.in_memory_name(item) or type(item).__name__, "size": None,
                "sha256": None}
    if readers.is_stdio(item):
        return {"path": readers.STDIN, "size": None, "sha256": None}
    if not os.path.isfile(item):   # a FIFO or device: hashing would use up or never end
        return {"path": os.fsdecode(item), "size": None, "sha256": None}
    try:
        size, sha256 = readers.file_digest(item)
    except DataError:
        return {"path": os.fsdecode(item), "size": None, "sha256": None}
    return {"path": os.fsdecode(item), "size": size, "sha256": sha256}


def _version(package: str) -> str | None:
    """Helper: an installed package's version (of the module loaded, if it is), or None."""
    module = sys.modules.get(package)
    if module is not None and isinstance(getattr(module, "__version__", None), str):
        return str(module.__version__)
    from importlib import metadata

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def samples(rows: Rows, fit: LinearFit, model: Model, unknowns: Unknowns, plan: FitPlan,
            labels: tuple[Any, ...]) -> dict[str, Any]:
    """Each sample's trajectory, time, fitted energy, energy residual and the weight its
    energy equation carried (for --residuals). The last use of the rows' energy rows of
    every sample: they are let go (`Rows.release`) before the outputs that do not need
    them are made."""
    energy = rows.energy
    estimates = unknowns.estimates(fit.theta)
    residual = energy.A @ fit.theta   # then in place: no more arrays of the record's length
    residual -= energy.b
    residual -= fit.h[energy.group]
    group, time, n_samples = energy.group, energy.time, energy.n_rows
    fitted = design.fitted_energy(rows.all_energy, model, estimates)
    del energy
    rows.release()
    return {"trajectory": np.asarray(labels, dtype=object)[group], "t": time,
            "energy": fitted, "residual": residual,
            "weight": design.sample_weights(plan.kind, rows.blocks, n_samples, rows.windows)}


def strongest_correlation(names: list[str], covariance: Any) -> dict[str, Any] | None:
    """The two free parameters whose estimates are the most correlated, and their
    correlation (from the covariance reported, the refinement's when it made the numbers):
    beside the condition number of the design, which can look fine while two estimates
    trade off against each other. None with fewer than two, or no finite correlation."""
    matrix = np.asarray(covariance, dtype=float)
    if len(names) < 2:
        return None
    sd = np.sqrt(np.clip(np.diag(matrix), 0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = matrix / np.outer(sd, sd)
    upper = np.triu(np.isfinite(r), k=1)
    if not upper.any():
        return None
    size = np.where(upper, np.abs(np.nan_to_num(r)), -1.0)
    i, j = np.unravel_index(int(np.argmax(size)), size.shape)
    return {"parameters": [names[i], names[j]],
            "correlation": float(np.clip(r[i, j], -1.0, 1.0))}


def _correlation_warnings(strongest: dict[str, Any] | None, *, quadrature: bool
                          ) -> list[str]:
    """Two estimates so correlated that the data hardly tell them apart, named; or, when
    the weak rows' `quadrature` error is in the covariance (one shift of known direction,
    which correlates the estimates by itself), said to be that."""
    if strongest is None or abs(strongest["correlation"]) <= HIGH_CORRELATION:
        return []
    pair = (f"{' and '.join(strongest['parameters'])} are correlated at "
            f"{correlation_text(strongest['correlation'])}")
    if quadrature:
        return [f"{pair}, with the weak-form quadrature's error in their covariance: one "
                "shift of known direction that moves the estimates together "
                "(method.discretization); a finer time step shrinks it"]
    return [f"{pair}: the data hardly tell them apart (each estimate leans on the other, and "
            "their errors are large together); record larger amplitudes or a trajectory at "
            "another energy, or --fix one of them if it is known"]


def _symmetric(covariance: Any) -> Any:
    """Helper: a covariance matrix made exactly symmetric (its rounding-level asymmetry
    averaged out; the diagonal, and so the standard errors, unchanged)."""
    matrix = np.asarray(covariance, dtype=float)
    return (matrix + matrix.T) / 2


def _finite_or_none(x: float) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def dissipation_summary(model: Model, source: loading.Source, damping: Dissipation,
                        estimates: dict[str, float], rows: Rows | None,
                        h: Any) -> dict[str, Any] | None:
    """Energy lost per trajectory, and the damping at small amplitude.

    The energy lost is the fitted dissipated work over the record divided by the energy
    above the lowest potential energy seen on the trajectory (none for a driven fit, whose
    inputs supply energy as it goes). Damping needs the records
    in memory (`options.FitOptions.chunking`), and so `rows` of every sample.

    At small amplitude the model is linear about the minimum of its potential nearest the
    recording's median position (`hamid.backbone.normal_modes.small_amplitude`, the limit
    of every backbone): each mode's natural frequency in Hz and modal damping ratio, which
    for viscous damping holds at every amplitude where the model is linear, not only at the
    recording's (its period shortened or lengthened by the nonlinearity). For one
    coordinate it is also the report's `equivalent_damping_ratio`, with its period.
    """
    if not damping:
        return None
    assert rows is not None
    records, energy_rows = source.whole(), rows.all_energy
    n_energy = len(model.parameters)
    coefficients = np.array([estimates[name] for name in damping.names])
    work = energy_rows.A[:, n_energy:] @ coefficients if energy_rows.A.shape[1] > n_energy \
        else np.zeros(energy_rows.n_rows)
    theta = [estimates[name] for name in model.parameters]
    at_rest = _at_rest(model, records)
    potential = model.total_energy(at_rest, theta)
    trajectories = []
    for j, (start, stop) in enumerate(records.bounds()):
        available = h[j] - potential[start:stop].min()
        trajectories.append({"trajectory": records.labels[j],
                             "energy_lost_fraction": float(work[stop - 1] / available)
                             if available > 0 and model.forcing is None else None})
    # here: the backbones' module imports scipy's integrators, which a fit without damping
    # never needs (some 0.15 s of a small fit's start)
    from hamid.backbone.normal_modes import small_amplitude

    n = len(model.coordinates)
    try:
        limit = small_amplitude(model, estimates, damping,
                                near=np.median(records.X[:, :n], axis=0))
    except HamidError:   # no minimum near the recording, or an energy that is not natural
        limit = None
    ratio = period = None
    if limit is not None and n == 1 and limit.modes[0].damping_ratio is not None:
        ratio, period = limit.modes[0].damping_ratio, 2 * np.pi / limit.modes[0].frequency
    return {"trajectories": trajectories, "equivalent_damping_ratio": ratio,
            "period": period, "small_amplitude": None if limit is None else {
                "equilibrium": dict(zip(model.coordinates, limit.equilibrium.tolist(),
                                        strict=True)),
                "modes": [{"mode": k, "frequency_hz": mode.frequency / (2 * np.pi),
                           "damping_ratio": mode.damping_ratio}
                          for k, mode in enumerate(limit.modes, 1)]}}


# Below this fraction of the energy's changes, the input's work explains nothing of them.
INPUT_WORK_FLOOR = 0.01


def _at_rest(model: Model, records: Records) -> np.ndarray:
    """The recorded positions with every velocity zero: where the energy is the potential."""
    at_rest = records.X.copy()
    at_rest[:, len(model.coordinates):] = 0.0
    return at_rest


def forcing_summary(model: Model, records: Records,
                    estimates: Mapping[str, float]) -> dict[str, Any] | None:
    """A driven fit's work and the share of the energy budget the input work makes up:
    the total variation of the fitted input work along the records over itself plus the
    largest energy above the lowest potential seen (near 1 when the input drives the
    motion, near 0 when it explains nothing of it). The report's `data.forcing`."""
    if model.forcing is None:
        return None
    theta = np.array([estimates[name] for name in model.parameters])
    W0, W = design.input_work(model, records)
    work = W0 + W @ theta
    at_rest = _at_rest(model, records)
    available = float(np.max(model.total_energy(records.X, theta))
                      - np.min(model.total_energy(at_rest, theta)))
    same = records.group[1:] == records.group[:-1]
    supplied = float(np.abs(np.diff(work))[same].sum())
    total = supplied + max(available, 0.0)
    return {"inputs": list(model.forcing.inputs), "work": model.forcing.work,
            "input_work_fraction": supplied / total if total > 0 else None}


def forcing_warnings(forcing: Mapping[str, Any] | None) -> list[str]:
    """An input whose work explains nothing of the energy's changes is probably the wrong
    column, or the wrong work."""
    fraction = None if forcing is None else forcing["input_work_fraction"]
    if fraction is None or fraction >= INPUT_WORK_FLOOR:
        return []
    return [f"the work of the inputs ({', '.join(forcing['inputs'])}; work "
            f"{forcing['work']!r}) makes up {100 * fraction:.2g}% of the energy budget: "
            "the input explains almost nothing of the motion (the right column? the right "
            "work?)"]


def _warnings(parameters: list[ParameterEstimate], stats: dict[str, Any], cond: Any,
              df: int, options: FitOptions, kind: RowKind,
              refinement: RefinementInfo | None, damping: list[str], driven: bool,
              integrated: tuple[str, ...]) -> list[str]:
    """Plain-words warnings about the fit; `damping` names its kinds of dissipation,
    `driven` says the energy's drift is against its spread, not its level, and
    `integrated` names the coordinates whose positions were integrated from other
    channels (`_of_the_start`)."""
    level, cov = options.level, options.cov
    drifting, notes = [], []
    for d in stats["drift"]:
        change = d["relative_change"]
        if change is not None and abs(change) > _DRIFT_CHANGE and d["trend_share"] > _DRIFT_SHARE:
            words = drift_words(change, driven=driven)
            drifting.append((d["trajectory"],
                             f"trajectory {d['trajectory']}: the energy is not conserved: a "
                             f"straight line through it {words} over the record; the system "
                             "may be damped or forced (try --damping viscous)" if not damping
                             else f"trajectory {d['trajectory']}: with {', '.join(damping)} "
                             "damping the energy balance is still not conserved: a straight "
                             f"line through it {words} over the record; try another kind of "
                             "--damping, or the system is forced"))
    if cond.status != "ok":
        combination = " ".join(f"{w:+.2f}*{n}" for n, w in
                               sorted(cond.weakest_direction.items(), key=lambda x: -abs(x[1]))
                               if abs(w) >= 0.05)
        notes.append(f"the problem is {'severely' if cond.status == 'severe' else 'moderately'}"
                     f" ill-conditioned (condition number {cond.condition_number:.3g}); the "
                     f"data determine {combination} worst: record larger amplitudes or add a "
                     "trajectory at another energy")
    critical = uncertainty.t_quantile(df, level)
    for p in parameters:
        if p.stderr is not None and abs(p.estimate) < critical * p.stderr:
            notes.append(f"{p.name} is not significantly different from zero "
                         f"(its {percent(level)} interval contains 0)")
    autocorrelation = stats["lag1_autocorrelation"]
    if cov in ("classical", "hc") and kind != RowKind.ENERGY:
        notes.append(f"--cov {cov} treats overlapping weak-form windows as independent and "
                     "understates the errors; use --cov hac")
    elif cov in ("classical", "hc") and autocorrelation is not None and autocorrelation > 0.5:
        notes.append(f"residuals are strongly autocorrelated (lag-1 {autocorrelation:.2f}); "
                     f"--cov {cov} understates the errors, use --cov hac")
    notes += _refinement_notes(refinement)
    if integrated and refinement is not None and refinement["applied"]:
        return notes + _of_the_start(drifting, stats, integrated)
    if integrated:   # the energy rows' misfit said with the integration's errors
        facts = _loose(drifting, stats)
        return notes + [
            f"the estimates are the linear fit's, on positions integrated from the recorded "
            f"channels ({', '.join(integrated)}): their intervals do not hold the "
            "integration's errors, and may miss the truth by many standard errors"
            + (f"; its energy rows fit them loosely ({'; '.join(facts)}), which shows the "
               "integration's errors as much as the model's" if facts else "")]
    return [note for _, note in drifting] + notes + _energy_misfit(stats)


def _loose(drifting: list[tuple[Any, str]], stats: dict[str, Any]) -> list[str]:
    """The energy rows' warnings as facts (a drifting energy, a low R², their residuals
    autocorrelated), for rows built on integrated positions: they show the integration's
    errors as much as the model's, so they are not advice to change the model."""
    return [*(f"trajectory {label}'s energy drifts" for label, _ in drifting),
            *_energy_misfit(stats, brief=True)]


def _of_the_start(drifting: list[tuple[Any, str]], stats: dict[str, Any],
                  integrated: tuple[str, ...]) -> list[str]:
    """For a refined fit whose positions were integrated from the recorded velocities or
    accelerations, one note for the energy rows' warnings (`_loose`): those rows are the
    linear start's, and the estimates the refinement's, which fits the recorded channels."""
    facts = _loose(drifting, stats)
    if not facts:
        return []
    return [f"the linear start's energy rows, built on positions integrated from the "
            f"recorded channels ({', '.join(integrated)}), fit them loosely "
            f"({'; '.join(facts)}): the integration's errors as much as the model's; the "
            "estimates are the trajectory refinement's, which fits the recorded channels "
            "themselves"]


# Self-checks of the energy residuals, once they are above rounding (exact data leave
# residuals of 1e-11 of the energy, smooth and so autocorrelated): a model that explains
# less than this share of the energy's variation, or residuals more autocorrelated than
# this from one sample to the next, probably does not fit.
_ROUNDING, _LOW_R_SQUARED, _HIGH_AUTOCORRELATION = 1e-6, 0.5, 0.9


def _energy_misfit(stats: dict[str, Any], brief: bool = False) -> list[str]:
    """Warnings that the energy rows fit poorly (`brief`: the facts alone)."""
    notes: list[str] = []
    relative, r_squared = stats["relative_rms"], stats["r_squared"]
    autocorrelation = stats["lag1_autocorrelation"]
    if relative is None or relative < _ROUNDING:
        return notes
    if r_squared is not None and r_squared < _LOW_R_SQUARED:
        notes.append(f"R² {r_squared:.2f}" if brief else
                     f"the model explains little of the energy's variation (R² "
                     f"{r_squared:.2f} of the energy rows): a wrong model, inconsistent units "
                     "or time scale, or noise as large as the motion")
    if autocorrelation is not None and autocorrelation > _HIGH_AUTOCORRELATION:
        notes.append(f"residuals autocorrelated at lag 1 {autocorrelation:.2f}" if brief else
                     f"the energy residuals are strongly autocorrelated (lag-1 "
                     f"{autocorrelation:.2f}): the model misses part of the motion (a term, "
                     "damping or forcing), or the units are inconsistent")
    return notes


def _refinement_notes(refinement: RefinementInfo | None) -> list[str]:
    """Why the trajectory refinement was not kept, or, when it was kept although its misfit
    exceeds the noise, what it weighted by and why it was kept."""
    if refinement is None:
        return []
    if not refinement["applied"]:
        if not refinement["reason"].startswith("the integrated model"):
            return []   # left aside for an option or the model's form: said in kind_reason
        return [f"the trajectory refinement was not kept: {refinement['reason']}; the "
                "linear fit is reported: the model may be wrong or incomplete"]
    raised = {name: entry["sigma"] for name, entry in refinement["noise"].items()
              if entry["source"] == "residuals"}
    if not raised:
        return []
    acceptance = refinement["acceptance"]
    levels = ", ".join(f"{name} {sigma:.3g}" for name, sigma in raised.items())
    return [f"the integrated model misses the recording by "
            f"{refinement['noise_chi2_per_dof']:.3g} times the noise variance estimated "
            "from differences (channels smoothed before recording, or physics the model "
            f"lacks): the trajectory refinement weighted by the residual scale ({levels}), "
            f"its standard errors are the sandwich over its {refinement['segments']} "
            "segments, and it was kept because it predicts segments held out of its fit no "
            f"worse than the linear fit (misfit {acceptance['held_out_refined']:.4g} against "
            f"{acceptance['held_out_linear']:.4g} per value, t = {acceptance['t']:.2f})"]


# Noise this large a share of a column's spread is about as large as the motion; a bias
# of a third of the standard error already lowers the cover of 95% bounds to 94%, and
# one of a standard error to 83%.
_NOISY, _BIASED = 0.5, 1 / 3


def _not_fitting(refinement: RefinementInfo | None) -> bool:
    """Whether the trajectory refinement was refused because the integrated model does
    not describe the recording (`_refinement_notes`): then a correction that assumes the
    model is not the next step."""
    return (refinement is not None and not refinement["applied"]
            and refinement["reason"].startswith("the integrated model"))


def _noise_warnings(check: NoiseCheck | None, not_fitting: bool) -> list[str]:
    """Warnings that the measurement noise makes the linear fit untrustworthy; with
    `not_fitting` (`_not_fitting`), the fix for its bias waits for a model that fits."""
    if check is None:
        return []
    notes = []
    noisiest = max(check.ratio, key=check.ratio.__getitem__)
    if check.ratio[noisiest] > _NOISY:
        notes.append(f"the measurement noise is about as large as the motion (the noise "
                     f"estimated in {noisiest} is {check.ratio[noisiest]:.2f} of its spread): "
                     "no fit of these data can be trusted; record with less noise")
    elif check.uncorrectable:
        notes.append("the measurement noise biases these least-squares estimates, and is too "
                     "large for --bias-correct to remove")
    if check.bias:
        biased = {k: v for k, v in check.bias.items() if abs(v) > _BIASED}
        if biased:
            listed = ", ".join(f"{k} by {v:+.1f}" for k, v in
                               sorted(biased.items(), key=lambda kv: -abs(kv[1])))
            notes.append(f"the measurement noise biases these least-squares estimates by more "
                         f"than a third of their standard errors ({listed} standard errors), "
                         "so their bounds hold the truth less often than they say; "
                         + ("once the model fits the recording (the trajectory refinement "
                            "found it does not), rerun with --noise auto --bias-correct"
                            if not_fitting else "rerun with --noise auto --bias-correct"))
    return notes
