"""Linear least squares on row blocks: the solution, the balance of the blocks of a joint
fit, noise weighting, and the covariances (docs/method.md, "The linear fit").

A fit of rows in memory (`fit_rows`) and one of rows streamed from a file
(`hamid.linear.chunked`) give the same `LinearFit`, through the same scores (`Scores`) and the
same balance (`balance`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from hamid.data.loading import Loaded
from hamid.data.records import Records, runs
from hamid.errors import DataError, FitError
from hamid.linear import design, noise_free, solve, uncertainty
from hamid.linear.design import Block, RowKind, Windows
from hamid.linear.plan import FitPlan
from hamid.linear.unknowns import Unknowns
from hamid.model.dissipation import Dissipation
from hamid.model.models import Model
from hamid.options import FitOptions, check_replicates

__all__ = ["LinearFit", "QuadratureError", "ResidualSums", "Rows", "Scores", "balance",
           "fit_rows", "fitted_levels", "resampling_units", "residual_sums", "rows_of",
           "with_discretization"]

TINY = 1e-300
_MAX_ROUNDS = 20


@dataclass(frozen=True, kw_only=True)
class LinearFit:
    """A fit's estimates and what the report needs of them, however the rows were read.

    theta, covariance : the free parameters' estimates and covariance.
    description, df : how the covariance was computed, and its t degrees of freedom.
    h, h_stderr : each trajectory's energy level and its standard error (NaN: none).
    block_variance : each block's residual variance in a joint fit's balance, else None.
    block_stats : each block's rows, rms and largest residual.
    conditioning, block_conditions : of all the rows, and of each block alone (joint).
    energy_means : each trajectory's mean energy row, (A, b): the level at other
        parameters is means_A @ theta - means_b.
    sizes : samples of each trajectory.
    weighting_rounds : iterations of the noise weighting (0 without it).
    discretization : what the weak rows' quadrature error moves theta by (weak and joint
        fits), folded into `covariance` where it is beyond noise (`with_discretization`).
    """

    theta: npt.NDArray[np.float64]
    covariance: npt.NDArray[np.float64]
    description: str
    df: int
    h: npt.NDArray[np.float64]
    h_stderr: npt.NDArray[np.float64]
    block_variance: dict[str, float] | None
    block_stats: dict[str, dict[str, Any]]
    conditioning: solve.Conditioning
    block_conditions: dict[str, float] | None
    energy_means: tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]
    sizes: npt.NDArray[np.int64]
    weighting_rounds: int = 0
    residuals: ResidualSums | None = None   # the residual summary's sums, when at hand
    discretization: npt.NDArray[np.float64] | None = None   # `QuadratureError.shift`


@dataclass
class Rows:
    """The rows of a fit in memory, kept for what the report says of each sample.

    Every sample's energy row is made again when asked for after `release`: the
    trajectory refinement, which does not use them, runs without these arrays of the
    records' length (8 columns for the 6 parameters of two coupled oscillators, more
    than the records' own 6), and so do the last per-sample outputs (`summary.samples`).
    """

    blocks: list[Block]    # the rows fitted, as weighted
    windows: Windows | None
    made: Callable[[], tuple[Block, Block]]   # the energy rows of every sample, anew
    kept: tuple[Block, Block] | None = None

    @property
    def energy(self) -> Block:
        """Every sample's energy row, fixed parameters held."""
        return self._energy()[0]

    @property
    def all_energy(self) -> Block:
        """Every sample's energy row, with every parameter's column."""
        return self._energy()[1]

    def _energy(self) -> tuple[Block, Block]:
        if self.kept is None:
            self.kept = self.made()
        return self.kept

    def pieces(self) -> Iterator[Block]:
        """The energy rows as the pieces `residual_sums` takes, made when iterated."""
        yield self.energy

    def release(self) -> None:
        """Let the energy rows of every sample go, until asked for again."""
        self.kept = None


@dataclass(frozen=True)
class Solved:
    """One least-squares solution of stacked blocks, with what the covariances need."""

    theta: Any
    h: Any
    residual: Any      # unweighted, all blocks stacked
    centred: solve.Centred
    solution: Any
    df_resid: int


def least_squares(blocks: list[Block], names: list[str], J: int,
                  correction: tuple[Any, Any] | None = None) -> Solved:
    """Solve stacked blocks; with `correction` (noise-bias terms), adjusted least squares."""
    has_levels = any(b.has_level for b in blocks)
    centred = solve.Centred.of(blocks, J)
    if correction is None:
        solution = solve.solve(centred, names, n_levels=J if has_levels else 0)
    else:
        solution = solve.solve_adjusted(centred.pieces(), *correction, names)
    theta = solution.theta
    h = centred.level_means_A @ theta - centred.level_means_b
    residual = np.concatenate([b.A @ theta - b.b - (h[b.group] if b.has_level else 0.0)
                               for b in blocks])
    return Solved(theta, h, residual, centred, solution,
                  len(residual) - len(names) - (J if has_levels else 0))


class Scores:
    """Each row's influence on the estimates, fed to the covariance estimators' sums.

    Row i's error moves theta by G_i = w_i (a_i - abar_j) M^-1 (a_i alone for rows
    without a level) and its trajectory's level by lam_i = w_i / W_j; the estimators
    work from z_i = [G_i, lam_i] and the residual r_i (`hamid.linear.uncertainty`). Rows of
    weak and joint fits share their errors within a window, so with ``hac`` the scores of
    each window are summed first and the kernel runs over the windows.
    """

    def __init__(self, theta: npt.NDArray[np.float64], inverse: npt.NDArray[np.float64],
                 means_A: npt.NDArray[np.float64], means_b: npt.NDArray[np.float64],
                 total_weight: npt.NDArray[np.float64]) -> None:
        self.theta, self.inverse, self.means_A = theta, inverse, means_A
        self.total_weight = total_weight
        self.h = means_A @ theta - means_b

    def feed(self, sums: uncertainty.ScoreSums, blocks: list[Block], scales: list[float],
             window_group: npt.NDArray[np.int64] | None,
             shares: list[npt.NDArray[np.float64]] | None = None,
             misfit: noise_free.Misfit | None = None) -> list[tuple[int, float, float]]:
        """Feed one piece of rows: `blocks` over the same windows (weak and joint fits, in
        window order) or energy rows; `scales` multiply each block's weights.
        `window_group`, the trajectory of each window, asks for the windows' summed
        scores. `shares`, per block, each row's part of the noise-bias correction of
        adjusted least squares (`hamid.linear.adjust.Moments.shares`), which joins its score.
        `misfit`, when given, is fed the rows' residuals.
        Returns each block's rows, sum of squared residuals and largest one."""
        p = len(self.theta)
        if window_group is not None:
            window_scores = np.zeros((len(window_group), p + 1))
        stats = []
        for k, (block, scale) in enumerate(zip(blocks, scales, strict=True)):
            # rows of windows whole (their scores are summed by window), energy rows of
            # samples a piece at a time: their scores are as many as the samples
            step = max(block.n_rows, 1) if window_group is not None else solve.PIECE_ROWS
            n, squares, largest = 0, 0.0, 0.0
            for start in range(0, max(block.n_rows, 1), step):
                piece = block.slice(start, start + step)
                z, r, w = self._scores(piece, scale)
                if misfit is not None:
                    misfit.add(piece, r, w)
                n, squares = n + len(r), squares + float(r @ r)
                largest = max(largest, float(np.max(np.abs(r), initial=0.0)))
                offset = None if shares is None else np.column_stack(
                    [scale * shares[k][start:start + step] @ self.inverse, np.zeros(len(r))])
                score = z * r[:, None] if offset is None else z * r[:, None] + offset
                if window_group is not None:
                    window_scores += score.reshape(len(window_group), -1, p + 1).sum(axis=1)
                else:
                    sums.add_runs(piece.group, z, r, w, offset)
            stats.append((n, squares, largest))
        if window_group is not None:
            for j, start, stop in runs(window_group):
                sums.add(j, window_scores[start:stop], np.ones(stop - start),
                         np.ones(stop - start))
                if stop < len(window_group):   # the trajectory ended inside this piece
                    sums.close(j)
        return stats

    def _scores(self, block: Block, scale: float) -> tuple[Any, Any, Any]:
        """Helper: the rows' influences z = [G, lam], residuals and weights."""
        w = scale * block.weight
        r = block.A @ self.theta - block.b
        if block.has_level:
            r -= self.h[block.group]
            G = w[:, None] * ((block.A - self.means_A[block.group]) @ self.inverse)
            lam = w / self.total_weight[block.group]
        else:
            G, lam = w[:, None] * (block.A @ self.inverse), np.zeros(len(w))
        return np.column_stack([G, lam]), r, w


class QuadratureError:
    """What the weak rows' quadrature error moves the estimates by, to first order.

    Row i errs by about q_i = e_i theta - f_i, the rows of `design.weak_quadrature_error`
    (Richardson). An error q_i of the rows moves theta by -sum_i G_i q_i, with
    G_i = w_i a_i M^-1 for rows without a level (`Scores`). Both are linear in theta, so
    the sums C = sum w a e' and c = sum w a f are fed as the rows are made (a file read in
    chunks keeps no rows) and read once theta is known. The fitted rows' weights are the
    fit's, up to `scale`.
    """

    def __init__(self, p: int) -> None:
        self.C, self.c = np.zeros((p, p)), np.zeros(p)

    def add(self, fitted: Block, error: Block) -> None:
        """Weak rows as fitted, and their errors (`design.weak_quadrature_error`)."""
        wa = fitted.weight[:, None] * fitted.A
        self.C += wa.T @ error.A
        self.c += wa.T @ error.b

    def shift(self, theta: npt.NDArray[np.float64], inverse: npt.NDArray[np.float64],
              scale: float = 1.0) -> npt.NDArray[np.float64]:
        """The estimates less the estimates of rows without quadrature error."""
        return -scale * (self.C @ theta - self.c) @ inverse


# Noise puts about a thirtieth of a standard error into a `QuadratureError.shift` (the
# difference of two rules over noisy samples, divided by 2^6 - 1); below a tenth of it
# the quadrature's error widens a 95% interval by less than half a percent.
DISCRETIZATION_SHARE = 0.1
DISCRETIZATION_NOTE = ("; with the weak-form quadrature's error where it exceeds a tenth of "
                       "the standard error (method.discretization)")


def with_discretization(covariance: npt.NDArray[np.float64], description: str,
                        shift: npt.NDArray[np.float64]) -> tuple[npt.NDArray[np.float64], str]:
    """The covariance with the quadrature's error added where it exceeds
    `DISCRETIZATION_SHARE` of the standard error, as an error of known direction
    (shift shift'), and its description saying so; both unchanged elsewhere."""
    stderr = np.sqrt(np.clip(np.diag(covariance), 0, None))
    folded = np.where(np.abs(shift) > DISCRETIZATION_SHARE * stderr, shift, 0.0)
    if not folded.any():
        return covariance, description
    return covariance + np.outer(folded, folded), description + DISCRETIZATION_NOTE


def windows_covariance(c: uncertainty.Covariance, n_windows: int) -> uncertainty.Covariance:
    """A covariance on the windows' summed scores, saying so."""
    return dataclasses.replace(c, description=c.description + uncertainty.UNITS_NOTE.format(
        n=n_windows))


def covariance(kind: str, fit: Solved, blocks: list[Block],
               window_group: npt.NDArray[np.int64] | None,
               shares: list[npt.NDArray[np.float64]] | None = None) -> uncertainty.Covariance:
    """Covariance of a fit of rows in memory: the analytic kinds of `hamid.linear.uncertainty`,
    ``hac`` on the windows' summed scores for weak and joint rows (`Scores`), whose
    windows belong to the trajectories `window_group` (None for energy rows); `shares`,
    the rows' parts of the correction of an adjusted fit (`Scores.feed`).

    Its automatic bandwidth grows with the windows' autocorrelation: overlapping windows,
    and the long memory that the cumulative work of an energy balance brings.
    """
    p = len(fit.theta)
    J = fit.centred.level_means_A.shape[0]
    level = next((b for b in blocks if b.has_level), None)
    total_weight = (np.ones(J) if level is None
                    else np.bincount(level.group, weights=level.weight, minlength=J))
    scores = Scores(fit.theta, fit.solution.inverse, fit.centred.level_means_A,
                    fit.centred.level_means_b, total_weight)
    by_window = kind == "hac" and window_group is not None
    fed = window_group if by_window else None
    sums, automatic = uncertainty.fed_sums(
        kind, p, J, lambda s: scores.feed(s, blocks, [1.0] * len(blocks), fed, shares))
    fitted = fit.centred.n_rows - fit.df_resid
    if not by_window:
        return sums.covariance(fit.df_resid, automatic=automatic)
    n_windows = len(window_group)
    return windows_covariance(sums.covariance(n_windows - fitted, automatic=automatic),
                              n_windows)


def own_variance(fit_alone: Callable[[], float], fallback: float) -> float:
    """A block's mean weighted squared residual in a fit of its own rows (`fit_alone`),
    or of its known side (`fallback`) when they cannot be fitted alone: where the balance
    of a joint fit starts."""
    try:
        return max(fit_alone(), TINY)
    except FitError:
        return max(fallback, TINY)


def balance(variance: dict[str, float], first: str,
            spread: Callable[[float], float]) -> tuple[float, dict[str, float]]:
    """The weight of the first block of a joint fit against the others, and the residual
    variance of each block that it implies.

    The starting point is feasible GLS: each block's weights divided by its residual
    variance in a fit of its own (`variance`). Rows of overlapping windows are
    correlated, and differently in the two blocks, so that guess (ratio 1) can be far
    from best; the ratio is chosen to minimise `spread`, the log-determinant of the
    parameters' ``hac`` covariance at that ratio, which does not depend on their units.
    It walks down whole decades from the guess, then tries the half decades beside the
    lowest: on every test system the decades' spreads fall to one minimum, which a walk
    finds with a third of the fits.
    """
    spreads: dict[float, float] = {}

    def at(exponent: float) -> float:
        if exponent not in spreads:
            spreads[exponent] = spread(10.0**exponent)
        return spreads[exponent]

    exponent = 0.0
    while True:
        lowest = min((e for e in (exponent - 1, exponent + 1) if abs(e) <= 4), key=at)
        if at(lowest) >= at(exponent):
            break
        exponent = lowest
    for half in (exponent - 0.5, exponent + 0.5):
        if abs(half) < 4:
            at(half)
    ratio = 10.0 ** min(spreads, key=spreads.__getitem__)
    return ratio, {k: v / (ratio if k == first else 1.0) for k, v in variance.items()}


def log_spread(covariance: Any) -> float:
    """log det of a covariance; infinite when it is not positive definite."""
    sign, logdet = np.linalg.slogdet(covariance)
    return logdet if sign > 0 else np.inf


def _balance_blocks(blocks: list[Block], names: list[str], J: int,
                    window_group: Any) -> tuple[list[Block], dict[str, float] | None]:
    """The blocks of a joint fit in memory, weighted against each other (`balance`)."""
    if len(blocks) == 1:
        return blocks, None
    variance = {b.kind: own_variance(
        lambda b=b: float(np.mean(b.weight * least_squares([b], names, J).residual ** 2)),
        float(np.mean(b.weight * b.b**2))) for b in blocks}
    first, rest = blocks[0], blocks[1:]

    def weighted(ratio: float) -> list[Block]:
        return [dataclasses.replace(first, weight=first.weight * ratio / variance[first.kind]),
                *(dataclasses.replace(b, weight=b.weight / variance[b.kind]) for b in rest)]

    def spread(ratio: float) -> float:
        trial = weighted(ratio)
        return log_spread(covariance("hac", least_squares(trial, names, J), trial,
                                     window_group).theta)

    ratio, block_variance = balance(variance, first.kind, spread)
    return weighted(ratio), block_variance


def fitted_levels(kind: str, theta: Any, fitted_h: Any, h_var: Any,
                  energy_means: tuple[Any, Any]) -> tuple[Any, Any]:
    """Energy levels of a linear fit and their standard errors.

    Without a level in the fit (weak rows, or a trajectory too short for any window of a
    joint fit) the level is the mean fitted energy, without a standard error.
    """
    J = len(fitted_h)
    h_stderr = np.full(J, np.nan) if kind == RowKind.WEAK else np.sqrt(np.clip(h_var, 0, None))
    if kind != RowKind.WEAK and not np.any(np.isnan(fitted_h)):
        return fitted_h, h_stderr
    means_A, means_b = energy_means
    mean_energy = means_A @ theta - means_b
    if kind == RowKind.WEAK:
        return mean_energy, h_stderr
    return np.where(np.isnan(fitted_h), mean_energy, fitted_h), h_stderr


def level_variance(c: Any, Abar: Any) -> Any:
    """Var(h_j) from a covariance's blocks (see `hamid.linear.uncertainty`)."""
    return (c.level - 2 * np.einsum("jp,jp->j", Abar, c.theta_level)
            + np.einsum("jp,pq,jq->j", Abar, c.theta, Abar))


def rows_of(loaded: Loaded, unknowns: Unknowns, damping: Dissipation, plan: FitPlan,
            options: FitOptions) -> tuple[Rows, FitPlan]:
    """The rows of records in memory that the plan asks for, before any weighting; the
    plan falls back to the energy rows when `auto` finds too few windows."""
    m, records = loaded.model, loaded.records
    names, J = unknowns.free_names, records.n_trajectories

    def energy_rows() -> tuple[Block, Block]:
        every = design.energy_block(m, records, damping)
        return unknowns.hold_fixed(every), every

    energy, all_energy = energy_rows()
    design.check_finite(all_energy, loaded.locate, list(unknowns.names))
    spans = design.windows(records, plan.window) if plan.kind != RowKind.ENERGY else None
    if spans is not None:
        plan = plan.check_windows(spans.n_windows, names, J, options)
        spans = spans if plan.kind != RowKind.ENERGY else None
    blocks = [energy] if spans is None else [
        *([design.window_means(energy, spans)] if plan.kind == RowKind.JOINT else []),
        unknowns.hold_fixed(design.weak_block(m, records, spans, damping))]
    design.check_weak_rows(blocks[-1], records.labels)
    return Rows(blocks, spans, energy_rows, (energy, all_energy)), plan


def fit_rows(loaded: Loaded, unknowns: Unknowns, damping: Dissipation, plan: FitPlan,
             options: FitOptions, sigma: Any) -> tuple[LinearFit, FitPlan, Rows]:
    """The linear fit of records in memory: rows, balance or noise weights, solution and
    covariance; the plan falls back to the energy rows when `auto` finds too few windows."""
    m, records = loaded.model, loaded.records
    names, J = unknowns.free_names, records.n_trajectories
    rows, plan = rows_of(loaded, unknowns, damping, plan, options)
    energy, blocks, spans = rows.energy, rows.blocks, rows.windows
    window_group = None if spans is None else spans.group
    if sigma is None:
        blocks, block_variance = _balance_blocks(blocks, names, J, window_group)
        rounds = 0
    else:
        # Adjusted least squares is unbiased only when no row's weight depends on its
        # own noise: its weights are found at the states of the neighbouring samples.
        blocks, block_variance, rounds = _noise_weighted(
            blocks=blocks, model=m,
            records=_neighbour_states(records) if options.bias_correct else records, spans=spans,
            damping=damping, sigma=sigma, unknowns=unknowns, J=J)
    correction, moments, weak = None, None, blocks[-1]   # weak: as weighted, not adjusted
    if options.bias_correct:
        from hamid.linear import adjust

        adjust.check_adjustable(m, loaded.channels.reconstructed, damping)
        moments = [adjust.adjusted_moments(block=b, model=m, records=records, sigma=sigma,
                                           windows=spans, parameters=names,
                                           fixed=dict(unknowns.fixed)) for b in blocks]
        blocks = [mo.block for mo in moments]
        correction = (sum(mo.AA for mo in moments), sum(mo.Ab for mo in moments))
    fit = least_squares(blocks, names, J, correction)
    if options.cov == "bootstrap":
        theta_cov, h_var, text = _bootstrap_covariance(blocks, names, J, plan.kind,
                                                       options.bootstrap, options.seed)
        df = fit.df_resid
    else:
        shares = None if moments is None else [mo.shares(fit.theta) for mo in moments]
        c = covariance(options.cov, fit, blocks, window_group, shares)
        theta_cov, text, df = c.theta, c.description, c.df
        if damping:
            theta_cov, text = _with_propagated_noise(
                theta_cov=theta_cov, text=text, fit=fit, blocks=blocks, model=m, records=records,
                sigma=sigma, unknowns=unknowns, spans=spans, damping=damping)
        h_var = level_variance(c, fit.centred.level_means_A)
    misfit = noise_free.Misfit(J)
    pieces = np.split(fit.residual, np.cumsum([b.n_rows for b in blocks])[:-1])
    for block, residual in zip(blocks, pieces, strict=True):
        misfit.add(block, residual, block.weight)
    theta_cov, text = misfit.widened(theta_cov, text, fit.solution.inverse)
    shift = None
    if spans is not None:
        error = QuadratureError(len(names))
        error.add(weak, unknowns.hold_fixed(design.weak_quadrature_error(m, records, spans,
                                                                         damping)))
        shift = error.shift(fit.theta, fit.solution.inverse)
        theta_cov, text = with_discretization(theta_cov, text, shift)
    means_A, means_b, _ = solve.level_means(energy, J)
    h, h_stderr = fitted_levels(plan.kind, fit.theta, fit.h, h_var, (means_A, means_b))
    block_stats = {b.kind: {"n_rows": len(r), "rms": float(np.sqrt(np.mean(r**2))),
                            "max_abs": float(np.max(np.abs(r)))}
                   for b, r in zip(blocks, pieces, strict=True)}
    each = ({b.kind: solve.conditioning([b], names, records.labels).condition_number
             for b in blocks} if len(blocks) > 1 else None)
    sizes = np.array([stop - start for start, stop in records.bounds()], dtype=np.int64)
    linear = LinearFit(theta=fit.theta, covariance=theta_cov, description=text, df=df, h=h,
                       h_stderr=h_stderr, block_variance=block_variance, block_stats=block_stats,
                       conditioning=solve.conditioning(blocks, names, records.labels),
                       block_conditions=each, energy_means=(means_A, means_b), sizes=sizes,
                       weighting_rounds=rounds, discretization=shift)
    return linear, plan, dataclasses.replace(rows, blocks=blocks)


def resampling_units(blocks: Sequence[Block]) -> tuple[np.ndarray, np.ndarray]:
    """The unit of every row of the stacked blocks (rows of one trajectory and time: a
    window's weak rows and its energy row) and each unit's trajectory, for resampling
    whole windows."""
    group = np.concatenate([b.group for b in blocks])
    time = np.concatenate([b.time for b in blocks])
    order = np.lexsort((time, group))
    fresh = np.ones(len(order), dtype=bool)
    fresh[1:] = (np.diff(group[order]) != 0) | (np.diff(time[order]) != 0)
    units = np.empty(len(order), dtype=np.int64)
    units[order] = np.cumsum(fresh) - 1
    unit_group = np.zeros(int(units.max()) + 1, dtype=np.int64)
    unit_group[units] = group
    return units, unit_group


def _bootstrap_covariance(blocks: list[Block], names: list[str], J: int, kind: str,
                          n_boot: int, seed: int | None) -> tuple[Any, Any, str]:
    """Covariance of theta and the levels from refits on resampled blocks of units:
    energy rows alone, every row (moving blocks handle their correlation); with weak-form
    rows, windows, each with its weak rows and its energy row."""
    p = len(names)
    group = np.concatenate([b.group for b in blocks])
    if kind == RowKind.ENERGY:
        units, unit_group = np.arange(len(group)), group
    else:
        units, unit_group = resampling_units(blocks)
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
        fit = least_squares(sample, names, J)
        return np.concatenate([fit.theta, fit.h])

    check_replicates("--bootstrap", n_boot, len(group))
    # Resample within the trajectories present (one too short for a window has no units).
    dense = np.unique(unit_group, return_inverse=True)[1]
    cov, _, description = uncertainty.bootstrap(refit, dense, n_boot=n_boot, seed=seed)
    return cov[:p, :p], np.diag(cov)[p:], description


def _with_propagated_noise(theta_cov: Any, text: str, fit: Solved, blocks: list[Block],
                           model: Model, records: Records, sigma: Any, unknowns: Unknowns,
                           spans: Windows | None, damping: Dissipation) -> tuple[Any, str]:
    """Damped fits: no parameter's variance below what the measurement noise alone causes.

    The energy balance's cumulative work carries each sample's noise into every later
    row, a long memory that residual-based estimates miss; the noise-propagated
    covariance (noise from --noise, else estimated from the data) sees it. Each
    parameter's variance is the larger of the two, its correlations those of the first.
    """
    from hamid.data import measurement

    if sigma is None:
        sigma = measurement.estimate_noise(records.X, records.bounds())
    G = fit.centred.influence(fit.solution.inverse)
    propagated = design.propagated_covariance(blocks=blocks, G=G, model=model, records=records,
                                              theta=unknowns.full(fit.theta), sigma=sigma,
                                              windows=spans, dissipation=damping)
    return (noise_free.at_least(theta_cov, propagated),
            text + "; each variance at least the one propagated from the measurement noise")


def _neighbour_states(records: Records) -> Records:
    """Each sample's state as the mean of its neighbours' (one neighbour at a trajectory's
    ends): close to the sample's for finely sampled motion, free of its own noise."""
    X = records.X
    before = np.ones(len(X), dtype=bool)
    after = np.ones(len(X), dtype=bool)
    for start, stop in records.bounds():
        before[start], after[stop - 1] = False, False
    previous, following = np.roll(X, 1, axis=0), np.roll(X, -1, axis=0)
    count = (before.astype(float) + after)[:, None]
    total = np.where(before[:, None], previous, 0.0) + np.where(after[:, None], following, 0.0)
    return dataclasses.replace(records, X=np.where(count > 0, total / np.maximum(count, 1), X))


def _noise_weighted(blocks: list[Block], model: Model, records: Records,
                    spans: Windows | None, damping: Dissipation, sigma: Any, unknowns: Unknowns,
                    J: int) -> tuple[list[Block], dict[str, float] | None, int]:
    """Weight every row by the inverse of the variance the noise puts into it, iterated.

    The variance depends on the parameters, so fit, re-weight and refit until the
    parameters settle (relative change below 1e-10, at most `_MAX_ROUNDS`). In a joint
    fit the two blocks are then balanced as without noise (`balance`): the rows of
    overlapping windows are correlated, which the row variances do not see. The
    variances are taken at the states of `records`.
    """
    names = unknowns.free_names
    unit_size = [dataclasses.replace(b, weight=b.weight / max(float(np.mean(b.b**2)), TINY))
                 for b in blocks]
    theta = least_squares(unit_size, names, J).theta
    rounds, settled = 0, False
    while not settled and rounds < _MAX_ROUNDS:
        rounds += 1
        weighted = []
        for block in blocks:
            variance = design.row_variance(block=block, model=model, records=records,
                                           theta=unknowns.full(theta), sigma=sigma, windows=spans,
                                           dissipation=damping)
            positive = variance[variance > 0]
            floor = 1e-12 * float(np.median(positive)) if positive.size else 1.0
            weighted.append(dataclasses.replace(block,
                                                weight=1.0 / np.maximum(variance, floor)))
        weighted, block_variance = _balance_blocks(
            weighted, names, J, None if spans is None else spans.group)
        new = least_squares(weighted, names, J).theta
        settled = bool(np.all(np.abs(new - theta) <= 1e-10 * np.abs(new)))
        theta = new
    scale = float(np.mean(np.concatenate([b.weight for b in weighted])))
    return ([dataclasses.replace(b, weight=b.weight / scale) for b in weighted],
            block_variance, rounds)


class ResidualSums:
    """Sums over the energy rows that the residual summary needs (docs/output.md,
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
        """Rows of any trajectories, each one's after its earlier rows: the runs' sums at
        once (a call per trajectory took a fifth of a fit of 5,000 short ones)."""
        if not block.n_rows:
            return
        spans = runs(block.group)
        j = np.array([k for k, _, _ in spans])
        starts = np.array([start for _, start, _ in spans])
        ends = np.array([stop for _, _, stop in spans]) - 1
        fresh = self.n[j] == 0
        self.origin[j[fresh]] = np.column_stack([block.time[starts[fresh]],
                                                 block.b[starts[fresh]]])
        t = block.time - self.origin[block.group, 0]
        b = block.b - self.origin[block.group, 1]
        r = residual
        # r_k r_k+1 within each run, then across from each one's earlier rows
        pairs = np.concatenate([[0.0], r[1:] * r[:-1]])
        pairs[starts] = np.where(fresh, 0.0, self.last[j] * r[starts])
        self.sums[j] += np.stack([np.add.reduceat(column, starts) for column in
                                  (t, t * t, r, r * r, t * r, b, b * b, pairs)], axis=1)
        self.n[j] += ends + 1 - starts
        self.last[j] = r[ends]
        self.end[j] = t[ends]
        self.max_abs = max(self.max_abs, float(np.max(np.abs(r))))

    def stats(self, labels: tuple[str | int, ...], *, driven: bool = False) -> dict[str, Any]:
        """The summary; residuals are relative to each trajectory's energy level, or for a
        `driven` fit (whose level is the balance's constant, near 0 for a record that
        starts at rest) to the spread of the energy's known part along it."""
        n = self.n
        st, stt, sr, srr, str_, sb, sbb, lagged = self.sums.T
        total_squares = float(srr.sum())
        rms = float(np.sqrt(total_squares / n.sum()))
        levels = (np.sqrt(np.clip(sbb - sb**2 / n, 0, None) / n) if driven
                  else np.abs(self.h))
        mean_level = float(np.mean(levels))
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
                          "relative_change": change / levels[j] if levels[j] else None,
                          "trend_share": explained})
        return {
            "rms": rms,
            "max_abs": self.max_abs,
            "relative_rms": rms / mean_level if mean_level > 0 else None,
            "r_squared": 1 - total_squares / total if total > 0 else None,
            "lag1_autocorrelation": float(lagged.sum()) / total_squares if rms > 0 else None,
            "drift": drift,
        }


def residual_sums(energy_rows: Iterable[Block], theta: npt.NDArray[np.float64],
                  h: npt.NDArray[np.float64]) -> ResidualSums:
    """The residual summary's sums over energy rows given in pieces, at theta and h."""
    sums = ResidualSums(h)
    for block in energy_rows:
        sums.add(block, block.A @ theta - block.b - h[block.group])
    return sums


@dataclass(frozen=True)
class NoiseCheck:
    """How the measurement noise compares with the motion, and what it does to a linear
    fit that does not correct for it (docs/method.md, "The noise check").

    ratio : each variable's noise (estimated from 4th differences, or as given) over its
        spread in the records.
    bias : each parameter's least-squares estimate minus the adjusted (bias-corrected)
        one, in its standard errors; None when the adjustment does not apply, or the
        residuals do not show the noise.
    uncorrectable : the noise is too large for the adjustment to work at all.
    """

    ratio: dict[str, float]
    bias: dict[str, float] | None = None
    uncorrectable: bool = False


# Residuals whose variance is below this share of the one the noise would put into them
# do not carry that noise: what the 4th differences found is the motion's own curvature
# (clean or pre-smoothed records), and no bias follows from it.
_NOISE_SEEN = 0.1


def noise_check(loaded: Loaded, rows: Rows, fit: LinearFit | None, unknowns: Unknowns,
                damping: Dissipation, options: FitOptions, sigma: Any) -> NoiseCheck | None:
    """The noise against the motion, and the errors-in-variables bias of the linear fit
    `fit` of `rows` (None: a refined fit, which has none to look for): least squares
    against adjusted least squares (`hamid.linear.adjust`) on the same rows, which is unbiased
    for polynomial energies and measured velocities; None when the trajectories are too
    short to tell the noise.

    Energy rows of single samples carry the largest bias; window means and weak rows
    average the noise first, but over long records their bias outgrows their errors too.
    """
    from hamid.data import measurement
    from hamid.linear import adjust

    m, records = loaded.model, loaded.records
    if sigma is None:
        try:
            sigma = measurement.estimate_noise(records.X, records.bounds())
        except DataError:   # trajectories too short to tell the noise: nothing to check
            return None
    spread = records.spread
    ratio = {name: float(s / d) if d > 0 else 0.0
             for name, s, d in zip(m.variables, sigma, spread, strict=True)}
    if (fit is None or options.bias_correct or not m.is_polynomial
            or loaded.channels.reconstructed or damping
            or not _noise_in_residuals(rows.energy, fit, m, records, unknowns, sigma)):
        return NoiseCheck(ratio)
    names, fixed = unknowns.free_names, dict(unknowns.fixed)
    try:
        if rows.windows is None:   # energy rows of single samples: a piece at a time
            block, = rows.blocks
            adjusted = adjust.adjusted_energy(block, m, records, sigma, names, fixed)
        else:
            moments = [adjust.adjusted_moments(block=b, model=m, records=records, sigma=sigma,
                                               windows=rows.windows, parameters=names,
                                               fixed=fixed)
                       for b in rows.blocks]
            adjusted = least_squares([mo.block for mo in moments], names,
                                     records.n_trajectories,
                                     (sum(mo.AA for mo in moments),
                                      sum(mo.Ab for mo in moments)))
    except FitError:
        return NoiseCheck(ratio, uncorrectable=True)
    stderr = np.sqrt(np.clip(np.diag(fit.covariance), 0, None))
    shift = np.divide(fit.theta - adjusted.theta, stderr,
                      out=np.zeros_like(stderr), where=stderr > 0)
    return NoiseCheck(ratio, dict(zip(names, shift.tolist(), strict=True)))


def _noise_in_residuals(energy: Block, fit: LinearFit, model: Model, records: Records,
                        unknowns: Unknowns, sigma: Any) -> bool:
    """Whether the energy residuals of the fit show at least a share `_NOISE_SEEN` of the
    variance that noise of std `sigma` would put into them (a piece of rows at a time:
    the energy's gradient has the records' size)."""
    theta, squares, expected = unknowns.full(fit.theta), 0.0, 0.0
    for start in range(0, energy.n_rows, solve.PIECE_ROWS):
        piece = energy.slice(start, start + solve.PIECE_ROWS)
        residual = piece.A @ fit.theta - piece.b - fit.h[piece.group]
        squares += float(residual @ residual)
        expected += float(design.row_variance(
            piece, model, records.slice(start, start + solve.PIECE_ROWS), theta, sigma).sum())
    return squares >= _NOISE_SEEN * expected
