"""The fit's report: estimates with bounds, levels, residual summary, conditioning, warnings."""

from __future__ import annotations

from typing import Any

import numpy as np

from hamid import __version__
from hamid.design import Block
from hamid.model import Model
from hamid.records import Records
from hamid.result import EnergyLevel, FitResult, ParameterEstimate


def energy_levels(labels: tuple[str | int, ...], h: Any, stderr: Any,
            sizes: list[int]) -> tuple[EnergyLevel, ...]:
    return tuple(EnergyLevel(label, float(level), finite_or_none(error), size)
                 for label, level, error, size in zip(labels, h, stderr, sizes, strict=True))


def fit_result(m: Model, names: list[str], fixed: dict[str, float], theta: Any, theta_cov: Any,
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
            name, role, float(theta[i]), finite_or_none(stderr[i]),
            finite_or_none(low[i]), finite_or_none(high[i]), truth.get(name), False))
    warnings = [*notes, *fit_warnings(parameters, stats, cond, df, method_info["level"],
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


def finite_or_none(x: float) -> float | None:
    import math

    x = float(x)
    return x if math.isfinite(x) else None


def block_report(blocks: list[Block], residual: Any, names: list[str],
                  labels: tuple[str | int, ...]) -> tuple[dict[str, Any], Any,
                                                         dict[str, float] | None]:
    """Residual summary of each block, the conditioning of all, and of each block alone
    (when there are several)."""
    from hamid import solve

    pieces = np.split(residual, np.cumsum([b.n_rows for b in blocks])[:-1])
    stats = {b.kind: block_stats(r) for b, r in zip(blocks, pieces, strict=True)}
    each = {b.kind: solve.conditioning([b], names, labels).condition_number
            for b in blocks} if len(blocks) > 1 else None
    return stats, solve.conditioning(blocks, names, labels), each


def block_stats(residual: Any) -> dict[str, Any]:
    return {"n_rows": len(residual), "rms": float(np.sqrt(np.mean(residual**2))),
            "max_abs": float(np.max(np.abs(residual)))}


class ResidualSums:
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
        from hamid.records import runs

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


def dissipation_summary(model: Model, records: Records, damping: Any,
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


def fit_warnings(parameters: list[ParameterEstimate], stats: dict[str, Any], cond: Any,
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
