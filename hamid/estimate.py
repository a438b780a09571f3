"""Linear least squares on row blocks: solving, block balance, noise weights, covariances."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hamid.design import Block
from hamid.errors import FitError
from hamid.model import Model
from hamid.records import Records


def fitted_levels(kind: str, theta: Any, fitted_h: Any, h_var: Any,
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


@dataclass(frozen=True)
class Solved:
    """One least-squares solution of stacked blocks, with what the covariances need."""

    theta: Any
    h: Any
    residual: Any      # unweighted, all blocks stacked
    weight: Any
    group: Any
    centred: Any
    solution: Any
    df_resid: int


def least_squares(blocks: list[Block], names: list[str], J: int,
                   correction: tuple[Any, Any] | None = None) -> Solved:
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
    return Solved(theta, h, residual, np.concatenate([b.weight for b in blocks]),
                     np.concatenate([b.group for b in blocks]), centred, solution,
                     len(residual) - len(names) - (J if has_levels else 0))


def covariance(cov: str, fit: Solved, units: Any, unit_group: Any) -> Any:
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


def balance_blocks(blocks: list[Block], names: list[str], J: int, units: Any,
                    unit_group: Any) -> tuple[list[Block], dict[str, float] | None]:
    """Weight the blocks of a joint fit against each other (`balanced_ratio`).

    The starting point is feasible GLS: each block's row weights scaled by the inverse of
    its weighted residual variance from a fit of that block alone.
    """
    import dataclasses

    if len(blocks) == 1:
        return blocks, None
    variance = {}
    for block in blocks:
        try:
            residual = least_squares([block], names, J).residual
            variance[block.kind] = max(float(np.mean(block.weight * residual**2)), TINY)
        except FitError:
            variance[block.kind] = max(float(np.mean(block.weight * block.b**2)), TINY)
    first, rest = blocks[0], blocks[1:]

    def weighted(ratio: float) -> list[Block]:
        return [dataclasses.replace(first, weight=first.weight * ratio / variance[first.kind]),
                *(dataclasses.replace(b, weight=b.weight / variance[b.kind]) for b in rest)]

    def spread(ratio: float) -> float:
        fit = least_squares(weighted(ratio), names, J)
        return log_spread(covariance("hac", fit, units, unit_group).theta)

    best = balanced_ratio(spread)
    return weighted(best), balanced_variance(variance, first.kind, best)


def balanced_ratio(spread: Callable[[float], float]) -> float:
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


def log_spread(covariance: Any) -> float:
    """log det of a covariance; infinite when it is not positive definite."""
    sign, logdet = np.linalg.slogdet(covariance)
    return logdet if sign > 0 else np.inf


def balanced_variance(variance: dict[str, float], first: str,
                      ratio: float) -> dict[str, float]:
    """Each block's residual variance as its weight in the balanced fit implies."""
    return {k: v / (ratio if k == first else 1.0) for k, v in variance.items()}


TINY = 1e-300


def resampling_units(blocks: list[Block], kind: str) -> tuple[Any, Any]:
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


def level_variance(c: Any, Abar: Any) -> Any:
    """Var(h_j) from a covariance's blocks (see `hamid.uncertainty`)."""
    return (c.level - 2 * np.einsum("jp,jp->j", Abar, c.theta_level)
            + np.einsum("jp,pq,jq->j", Abar, c.theta, Abar))


def bootstrap_covariance(blocks: list[Block], names: list[str], J: int, units: Any,
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
        estimate = least_squares(sample, names, J)
        return np.concatenate([estimate.theta, estimate.h])

    # Resample within the trajectories present (one too short for a window has no units).
    dense = np.unique(unit_group, return_inverse=True)[1]
    cov, _, description = uncertainty.bootstrap(refit, dense, n_boot=n_boot, seed=seed)
    return cov[:p, :p], np.diag(cov)[p:], description


def with_propagated_noise(theta_cov: Any, text: str, estimate: Solved,
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


def noise_weighted(blocks: list[Block], model: Model, records: Records, spans: Any,
                    damping: Any, sigma: Any, free: list[int], fixed_values: Any,
                    names: list[str], J: int, units: Any,
                    unit_group: Any) -> tuple[list[Block], dict[str, float] | None, int]:
    """Weight every row by the inverse of the variance the noise puts into it, iterated.

    The variance depends on the parameters, so fit, re-weight and refit until the
    parameters settle (relative change below 1e-10, at most `_MAX_ROUNDS`). In a joint
    fit the two blocks are then balanced as without noise (`balance_blocks`): the rows
    of overlapping windows are correlated, which the row variances do not see.
    """
    import dataclasses

    from hamid import design

    unit_size = [dataclasses.replace(b, weight=b.weight / max(float(np.mean(b.b**2)), TINY))
                 for b in blocks]
    theta = least_squares(unit_size, names, J).theta
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
        weighted, block_variance = balance_blocks(weighted, names, J, units, unit_group)
        new = least_squares(weighted, names, J).theta
        settled = bool(np.all(np.abs(new - theta) <= 1e-10 * np.abs(new)))
        theta = new
    scale = float(np.mean(np.concatenate([b.weight for b in weighted])))
    return ([dataclasses.replace(b, weight=b.weight / scale) for b in weighted],
            block_variance, rounds)


_MAX_ROUNDS = 20
