"""The trajectory refinement of an automatic joint fit: the linear fit's parameters refined
by fitting the model's integrated motion to the recording (`hamid.refine.trajectory` does the
work; docs/method.md, "The trajectory refinement").

What is decided here: the noise each variable is weighted by (the user's, the difference
estimate, or, when the misfit shows that estimate too small, the fit's own residual
scale), which covariance the refined parameters get, and whether they replace the linear
ones: only when they predict segments held out of their fit no worse than the linear
fit's parameters do (blocked cross-validation); and, once kept within the noise, how far
its segments are lengthened (joined while the misfit the joins add is the noise's).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt
from scipy.special import fdtri

from hamid.data import measurement
from hamid.data.records import Records
from hamid.errors import FitError
from hamid.executor import Workers, available_cores
from hamid.linear import design, estimate, uncertainty
from hamid.linear.estimate import LinearFit, ResidualSums, Rows
from hamid.linear.plan import FitPlan
from hamid.linear.unknowns import Unknowns
from hamid.model.dissipation import Dissipation
from hamid.model.expressions import Func
from hamid.model.models import Model
from hamid.refine.outcome import (
    AcceptanceInfo,
    LengtheningInfo,
    NoiseLevel,
    Outcome,
    RefinementInfo,
    SmoothingInfo,
)
from hamid.safe_text import counted

if TYPE_CHECKING:
    from hamid.refine.trajectory import SegmentFit

__all__ = ["channel_weights", "level_errors", "refine"]

CHI2_LIMIT = 1.5         # weighted misfit per degree of freedom that the noise explains
NOISE_FLOOR = 1e-9       # of a channel's spread: the smallest noise level it is weighted by
HOPELESS = 100           # times that: no use converging at those weights
FOLDS = 5                # contiguous blocks of segments held out in turn
CHECKED_SEGMENTS = 2 * FOLDS  # fewest segments the held-out check is made with
REWEIGHT_ROUNDS = 2      # fits at residual-based noise levels, at most
REWEIGHT_SETTLED = 0.1   # relative change of every noise level that ends them sooner
HELD_OUT_LEVEL = 0.95    # refused when the refinement predicts worse beyond this bound
LENGTHEN_LEVEL = 0.99    # segments joined while the misfit a join adds is below this F point
LONGEST_PERIODS = 32     # dominant periods: longer segments would integrate one after another
# A friction force's reversal is rounded over this share of its argument's root mean
# square (`_smoothed`): the force's mean error is then about that share of its size
SMOOTHING = 1e-3
CLEAN_CHI2 = 1e-6        # misfit per dof below which it is the integrator's error, not noise
# Standard errors from its minimum within which the first fit stops: the joined fit goes on
# from its last point (to trajectory.SETTLED), and one not joined is settled at the end.
# What it is judged by before then cannot tell: its misfit gains d^2 at d standard errors
# off (against a spread of sqrt(2 dof)), and the held-out refits step from where it
# stopped (within 0.02 standard errors of refits run to the end; 0.04 from 1.0)
FIRST_WITHIN = 0.3


def channel_weights(levels: npt.NDArray[np.float64], spread: npt.NDArray[np.float64],
                    used: npt.NDArray[np.bool_]) -> npt.NDArray[np.float64]:
    """The weight of each channel in the trajectory fit's squares: one over its noise
    level, floored at NOISE_FLOOR of its spread (a channel recorded without noise would
    otherwise outweigh all others without bound); 0 for channels not `used` (not recorded:
    derived or integrated, nothing of their own) and for a constant channel recorded
    without noise, which carries nothing of the motion."""
    level = np.maximum(levels, NOISE_FLOOR * spread)
    return np.where(used & (level > 0), 1.0 / np.where(level > 0, level, 1.0), 0.0)


@dataclass(frozen=True)
class _Noise:
    """The noise level of each variable that the trajectory fit weights by.

    `base` is the user's level where given, else the estimate from differences;
    `levels` are the ones in use, raised above `base` where the fit's residuals showed it
    too small. Variables not `used` (channels not recorded: derived or integrated) get no
    weight.
    """

    base: npt.NDArray[np.float64]
    levels: npt.NDArray[np.float64]
    given: npt.NDArray[np.bool_]
    used: npt.NDArray[np.bool_]
    spread: npt.NDArray[np.float64]

    @classmethod
    def of(cls, records: Records, sigma: npt.NDArray[np.float64] | None,
           fitted: npt.NDArray[np.bool_]) -> _Noise:
        X = records.compared
        differences = measurement.estimate_noise(X, records.bounds())
        user = np.zeros(len(differences))   # the user's levels (none of accelerations)
        user[:0 if sigma is None else len(sigma)] = 0.0 if sigma is None else sigma
        given = user > 0
        base = np.where(given, user, differences)
        # channels not recorded (derived or integrated): nothing of their own
        return cls(base, base, given, fitted.copy(), records.compared_spread)

    @property
    def weights(self) -> npt.NDArray[np.float64]:
        return channel_weights(self.levels, self.spread, self.used)

    def raised(self, fit: SegmentFit) -> _Noise:
        """Each level not given by the user raised from its base to the fit's root mean
        square residual of its variable, where the base does not explain that (its misfit
        per value, the squared ratio, is CHI2_LIMIT or more)."""
        rms = np.nan_to_num(fit.residual_rms)
        beyond = self.used & ~self.given & (rms**2 >= CHI2_LIMIT * self.base**2)
        return dataclasses.replace(self, levels=np.where(beyond, rms, self.base))

    @property
    def any_raised(self) -> bool:
        """Whether a level is above its base."""
        return bool(np.any(self.levels > self.base))

    def misfit(self, fit: SegmentFit) -> float:
        """The fit's misfit per degree of freedom weighted by the base levels (the noise
        given or estimated from differences)."""
        squares = fit.problem.n_samples * np.nan_to_num(fit.residual_rms) ** 2
        return float(np.sum(squares * channel_weights(self.base, self.spread, self.used) ** 2)
                     / fit.dof)

    def settled(self, other: _Noise) -> bool:
        """Whether no level of `other` is more than REWEIGHT_SETTLED away from this one."""
        return bool(np.all(np.abs(other.levels - self.levels)
                           <= REWEIGHT_SETTLED * self.levels))

    def report(self, names: tuple[str, ...]) -> dict[str, NoiseLevel]:
        """Variable -> the level used (None: no weight) and where it came from."""
        source = np.where(self.given, "given", np.where(self.levels > self.base,
                                                        "residuals", "differences"))
        return {name: NoiseLevel(sigma=float(self.levels[k]), source=str(source[k]))
                if self.used[k] else NoiseLevel(sigma=None, source="derived")
                for k, name in enumerate(names)}


def refine(*, linear: LinearFit, model: Model, records: Records, damping: Dissipation,
           unknowns: Unknowns, plan: FitPlan, sigma: npt.NDArray[np.float64] | None,
           fitted: npt.NDArray[np.bool_], rows: Rows | None,
           progress: Callable[[str], None] | None,
           jobs: int | None = None) -> Outcome:
    """The refined fit, or None when it is not kept, and what the report says of it.

    `sigma` is the noise the user gave (0 where not given), `fitted` whether each channel
    the refinement compares was recorded (`Channels.fitted`: the others get no weight),
    `rows` the linear fit's rows when it was made in memory (its refits without each block
    need them; without them the held-out check compares with the linear fit of the whole
    record). The refined fit's levels are the mean energies at its parameters; their
    standard errors need a pass over the energy residuals there (`level_errors`) and are
    NaN here. The
    integrations run in `jobs` processes (default one per core) when the record is long
    enough to gain by it (`hamid.refine.integration`); the processes then start at once and last
    the whole refinement.
    """
    reversals = {str(g.expression) for g in damping.reversals}
    for what, kinks in (("energy", model.kinks),
                        ("dissipation", [k for part in damping.kinks for k in part
                                         if str(k.expression) not in reversals])):
        kink = _crossed_kink(kinks, records)
        if kink is not None:
            return Outcome.refused(
                f"the {what} is not smooth where {kink} = 0 (abs, sign or a fractional "
                "power), and the motion reaches it; integrating its force there takes tiny "
                "steps without end")
    from hamid.refine import integration, trajectory

    expected = trajectory.round_values(records, len(unknowns.free))
    with integration.parallel(Workers(jobs or available_cores()), expected):
        return _refine(linear=linear, model=model, records=records, damping=damping,
                       unknowns=unknowns, plan=plan, sigma=sigma,
                       fitted=fitted, rows=rows, progress=progress)


def _refine(*, linear: LinearFit, model: Model, records: Records, damping: Dissipation,
            unknowns: Unknowns, plan: FitPlan, sigma: npt.NDArray[np.float64] | None,
            fitted: npt.NDArray[np.bool_], rows: Rows | None,
            progress: Callable[[str], None] | None) -> Outcome:
    """`refine` past its checks, its integrations' workers chosen."""
    from hamid.refine import trajectory  # the integrator and sympy's derivatives: when refined

    damping, smoothing = _smoothed(damping, records)
    noise = _Noise.of(records, sigma, fitted)
    period = design.median_period(plan.scales)
    if period is None:   # windows given with --weak-window, no period found
        period = 2 * plan.window
    theta_linear, free = unknowns.full(linear.theta), list(unknowns.free)
    try:
        fit = trajectory.refine(model=model, records=records, damping=damping,
                                theta_all=theta_linear, free=free, period=period,
                                weight=noise.weights, progress=progress,
                                stop=trajectory.Stop(FIRST_WITHIN, HOPELESS * CHI2_LIMIT))
        within = fit.chi2_per_dof < CHI2_LIMIT
        if not within:
            # fewer segments than the held-out check needs: shorter ones, down to a period
            length = fit.problem.length
            while (trajectory.segment_count(records, length) < CHECKED_SEGMENTS
                   and length / 2 >= trajectory.MIN_SEGMENT_PERIODS * period):
                length /= 2
            fit, noise = _beyond_noise(fit, noise, length, lambda weight: trajectory.fit(
                model=model, records=records, damping=damping, theta_all=fit.theta, free=free,
                length=length, weight=weight, progress=progress, stage="reweighted, "), progress)
            # no level raised in the end: the first fit had stopped far from its minimum
            # (over chaotic motion a first step can misjudge the misfit it heads for)
            within = not noise.any_raised and fit.chi2_per_dof < CHI2_LIMIT
    except trajectory.RefinementFailed as exc:
        return Outcome.refused(f"the integrated model does not fit the recording: {exc}")
    info: dict[str, Any] = {
        "segments": fit.segments, "segment_seconds": fit.problem.length,
        **_fitted(fit, noise), "noise": noise.report(model.variables + (
            () if records.A is None else model.acceleration_names)),
        "covariance": "misfit-scaled" if within else "sandwich",
        **({"smoothing": smoothing} if smoothing else {})}
    beyond = (f"the integrated model misses the recording by {noise.misfit(fit):.3g} times the "
              "noise variance, and ")
    acceptance = None
    if fit.segments >= CHECKED_SEGMENTS:
        acceptance = _held_out(fit, theta_linear, unknowns, records.n_trajectories, rows,
                               progress)
    info["acceptance"] = acceptance or AcceptanceInfo(rule="noise")
    reason = None
    if acceptance is None and not within:
        reason = beyond + (
            f"the record holds {counted(fit.segments, 'segment', 'segments')} of one period, too "
            f"few to check it on segments held out of its fit (at least {CHECKED_SEGMENTS})"
            if fit.segments < CHECKED_SEGMENTS else
            "its check on segments held out of its fit could not be made (its fits without a "
            "block, or the linear fit's motion over them)")
    elif acceptance is not None and acceptance["t"] > acceptance["t_limit"]:
        reason = ("the integrated model, fitted without each block of segments, predicts "
                  "the held-out segments worse than the linear fit does (misfit "
                  f"{acceptance['held_out_refined']:.5g} against "
                  f"{acceptance['held_out_linear']:.5g} per value, t = {acceptance['t']:.3g} "
                  f"over {counted(fit.segments, 'segment', 'segments')})")
    if reason is not None:
        return Outcome.refused(reason, **info)
    info["lengthening"] = None
    if within:
        try:
            fit, info["lengthening"] = _lengthened(fit, period, progress)
        except trajectory.RefinementFailed as exc:
            return Outcome.refused(f"the integrated model does not fit the recording: {exc}",
                                   **info)
        if fit.groups == fit.segments:   # the first fit, settled
            info.update(_fitted(fit, noise))
    inputs_sigma = None
    if records.U is not None:
        inputs_sigma = measurement.estimate_noise(records.U, records.bounds())
        info["noise"] |= {name: NoiseLevel(sigma=float(level), source="differences")
                          for name, level in zip(model.inputs, inputs_sigma, strict=True)}
    return Outcome(fit=_refined(linear, fit, within, inputs_sigma),
                   report=RefinementInfo(applied=True, **info))


def _fitted(fit: SegmentFit, noise: _Noise) -> dict[str, Any]:
    """What the report says of the fit over the segments as cut."""
    return {"iterations": fit.iterations, "chi2_per_dof": fit.chi2_per_dof,
            "noise_chi2_per_dof": noise.misfit(fit)}


def _lengthened(fit: SegmentFit, period: float, progress: Callable[[str], None] | None
                ) -> tuple[SegmentFit, LengtheningInfo]:
    """The fit over longer segments, neighbours joined, while what the joining adds to the
    misfit is what the noise explains, or the fit settled (`trajectory.settle`) when none
    are; and what the report says of it.

    Every segment boundary sets the state free again, and the information carried across
    it is lost: over four-period segments of a 100 s record the stiffnesses spread up to
    twice the bound of one state per trajectory (`tests/benchmarks/bound.py`). Joining
    ties k = 2N states per boundary; with the model right, the misfit it adds is
    chi-squared with k degrees of freedom, so F = (added / k) / (misfit / dof of the
    joined fit) follows Fisher's F. Beyond its LENGTHEN_LEVEL point (the motion drifts
    off the longer segments, or the joined fit fell into another minimum), or when the
    joined fit fails, the last good length stands. All segments within LONGEST_PERIODS
    are joined at once first; when that is refused, neighbours are joined in pairs. The
    joined segments are integrated as the short ones tied by continuity
    (`trajectory.join`: multiple shooting), which keeps them in large batches.
    """
    from hamid.refine import trajectory

    if fit.chi2_per_dof < CLEAN_CHI2:
        # noise-free data: no noise to judge a tie by, and errors at the integrator's
        # tolerance already (a tie at the strict tolerance cost clean fits 2.5x noisy ones)
        fit = trajectory.settle(fit, progress)
        return fit, _lengthening(fit, 0, "clean")
    longest, count, rounds = LONGEST_PERIODS * period, fit.groups, 0
    while True:
        try:
            longer = trajectory.join(fit, count, longest, progress)
        except trajectory.TooUnstable:
            longer, stopped = None, "unstable"
        except trajectory.RefinementFailed:
            longer, stopped = None, "failed"
        else:
            if longer is None:
                whole = fit.groups == fit.problem.records.n_trajectories
                stopped = "whole" if whole else "longest"
                break
            misfit = longer.chi2_per_dof * longer.dof
            k = (fit.groups - longer.groups) * fit.states.shape[1]
            added = misfit - fit.chi2_per_dof * fit.dof
            if added / k <= fdtri(k, longer.dof, LENGTHEN_LEVEL) * misfit / longer.dof:
                fit, rounds = longer, rounds + 1
                continue
            stopped = "misfit"
        if count == 2:
            break
        count = 2   # refused at once: join in pairs, from the last good length
    if rounds == 0:
        fit = trajectory.settle(fit, progress)
    return fit, _lengthening(fit, rounds, stopped)


def _lengthening(fit: SegmentFit, rounds: int, stopped: str) -> LengtheningInfo:
    """What the report says of the lengthening that ended at `fit`."""
    return LengtheningInfo(segments=fit.groups, segment_seconds=fit.problem.span,
                           rounds=rounds, iterations=fit.iterations if rounds else 0,
                           chi2_per_dof=fit.chi2_per_dof, stopped=stopped)


def _beyond_noise(fit: SegmentFit, noise: _Noise, length: float,
                  cut: Callable[[npt.NDArray[np.float64]], SegmentFit],
                  progress: Callable[[str], None] | None) -> tuple[SegmentFit, _Noise]:
    """The fit over segments of `length` seconds at noise levels raised to its own
    residual scale, refitted until they settle (REWEIGHT_ROUNDS fits at most), and those
    levels; `cut` fits segments of that length afresh at given weights.

    A misfit beyond the noise means physics the model lacks, or channels smoothed before
    they were recorded (the differences of a smoothed channel see almost no noise):
    weighted by their own residual scale, the channels count alike. The levels are not
    iterated to a fixed point: with a model that misses the motion, a channel weighted
    more is fitted closer (the states trade one channel against another), so none need
    exist, and the sandwich covariance holds whatever the weights.
    """
    from hamid.refine import trajectory

    raised = noise.raised(fit)
    fit = (trajectory.refit(fit, raised.weights, progress)
           if length == fit.problem.length else cut(raised.weights))
    for _ in range(REWEIGHT_ROUNDS - 1):
        again = noise.raised(fit)
        if raised.settled(again):
            break
        raised = again
        fit = trajectory.refit(fit, raised.weights, progress)
    again = noise.raised(fit)
    if raised.any_raised and not again.any_raised:
        # its own residuals are the noise's: a start far off had raised the levels on the
        # way (a first fit stopped far from its minimum), so it is fitted at them again
        fit, raised = trajectory.refit(fit, again.weights, progress), again
    return fit, raised


def _refined(linear: LinearFit, fit: SegmentFit, within: bool,
             inputs_sigma: npt.NDArray[np.float64] | None) -> LinearFit:
    """The linear fit with the refined parameters and their covariance: misfit-scaled
    Gauss-Newton when the noise explains the misfit (on noise-free data, scaled by the
    whole misfit), else the sandwich over segments (with its degrees of freedom,
    segments less parameters).

    A driven fit's misfit-scaled covariance gains what the noise of its recorded inputs
    (`inputs_sigma`, from their differences) puts into the parameters through the
    integrated motion; the sandwich holds it already (an error shared within segments)."""
    theta = fit.theta[list(fit.free)]
    if within and fit.chi2_per_dof < CLEAN_CHI2:
        # The misfit is the integrators' error (this fit's and the record's own): smooth,
        # shared by every value, not noise. An error of its size moves a parameter by at
        # most sqrt(inverse_kk * misfit) (Cauchy-Schwarz), dof times the scaled variance.
        covariance, df = fit.covariance("scaled") * fit.dof, fit.dof
        description = ("Gauss-Newton covariance of the trajectory fit times its whole misfit "
                       f"({fit.chi2_per_dof * fit.dof:.3g}): noise-free data, whose misfit is "
                       "the integrators' error, shared by all values")
    elif within:
        covariance, df = fit.covariance("scaled"), fit.dof
        description = ("Gauss-Newton covariance of the trajectory fit, scaled by its misfit "
                       f"per degree of freedom ({fit.chi2_per_dof:.3g})")
        if inputs_sigma is not None:
            covariance = covariance + _inputs_covariance(fit, inputs_sigma)
            description += ", plus the inputs' noise carried through the integrated motion"
    else:
        covariance, df = fit.covariance("sandwich"), max(fit.segments - len(theta), 1)
        description = (f"sandwich covariance of the trajectory fit over its {fit.segments} "
                       "segments (robust to errors shared within a segment: the misfit "
                       "exceeds the noise)")
    means_A, means_b = linear.energy_means
    return dataclasses.replace(
        linear, theta=theta, covariance=covariance, description=description, df=df,
        h=means_A @ theta - means_b, h_stderr=np.full(len(means_b), np.nan), residuals=None,
        discretization=None)


def _inputs_covariance(fit: SegmentFit, sigma: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The covariance that white noise of std `sigma` on the recorded inputs (one per
    input) puts into the free parameters through the integrated motion, to first order:
    sum over samples and inputs of sigma^2 a a', a the parameters' response to the
    sample (`SegmentFit.input_response`)."""
    response = fit.input_response()
    return np.einsum("kmi,i,lmi->kl", response, sigma**2, response)


def _held_out(fit: SegmentFit, theta_linear: npt.NDArray[np.float64], unknowns: Unknowns,
              n_trajectories: int, rows: Rows | None,
              progress: Callable[[str], None] | None) -> AcceptanceInfo | None:
    """How the refined and the linear parameters predict segments held out of their fits,
    or None when the refits cannot be made or the linear ones' motion cannot be integrated
    (a start far off, as from accelerations alone: nothing to compare with).

    The segments (at least CHECKED_SEGMENTS, so that a block left out moves the
    parameters by about a standard error and the second-order refits hold) are cut into
    FOLDS contiguous blocks; each block is predicted by the
    refinement fitted without it (to second order from the converged fit,
    `SegmentFit.held_out_folds`) and by the linear fit refitted without the windows that
    reach into it (integrated), each segment's initial state refitted. `t` is the paired
    t statistic of the two misfits over the segments (positive when the refinement
    predicts worse).
    """
    from hamid.refine import trajectory

    S, K = fit.segments, FOLDS
    folds = np.arange(S) * K // S
    free = list(fit.free)
    linear = np.repeat(theta_linear[None], S, axis=0)
    refitted = rows is not None and rows.windows is not None
    try:
        refined = fit.held_out_folds(folds)[1]
        if refitted:
            assert rows is not None and rows.windows is not None
            for k in range(K):
                held = folds == k
                linear[np.ix_(held, free)] = _linear_without(
                    rows, unknowns, n_trajectories,
                    [fit.problem.pieces[s] for s in np.flatnonzero(held)])
    except (np.linalg.LinAlgError, FitError):
        return None
    try:
        predicted = fit.held_out(linear, progress)
    except trajectory.RefinementFailed:
        return None
    values = fit.problem.n_used
    difference = refined - predicted
    spread = float(np.std(difference, ddof=1))
    t = float(np.mean(difference)) / spread * np.sqrt(S) if spread > 0 else 0.0
    return AcceptanceInfo(rule="held-out", folds=K, linear_refitted=refitted,
                          held_out_linear=float(predicted.sum() / values),
                          held_out_refined=float(refined.sum() / values), t=float(t),
                          t_limit=uncertainty.t_quantile(S - 1, HELD_OUT_LEVEL))


def _linear_without(rows: Rows, unknowns: Unknowns, n_trajectories: int,
                    pieces: list[tuple[int, int]]) -> npt.NDArray[np.float64]:
    """The linear fit's parameters from its rows less the windows that reach into the
    samples of `pieces`; the blocks' weights as they were."""
    windows = rows.windows
    assert windows is not None
    reach = np.zeros(windows.n_windows, bool)
    for a, b in pieces:
        reach |= (windows.last >= a) & (windows.first < b)
    kept = []
    for block in rows.blocks:   # rows in window order, as many per window
        keep = np.repeat(~reach, block.n_rows // windows.n_windows)
        kept.append(dataclasses.replace(block, A=block.A[keep], b=block.b[keep],
                                        group=block.group[keep], time=block.time[keep],
                                        weight=block.weight[keep]))
    return estimate.least_squares(kept, unknowns.free_names, n_trajectories).theta


def level_errors(fit: LinearFit, residuals: ResidualSums) -> npt.NDArray[np.float64]:
    """Standard errors of the refined levels, each the mean energy at its parameters.

    The variance adds what the parameters' covariance puts into each mean to that of the
    mean of its energy residuals, which are white once the parameters are right (each is
    the energy of one sample's measurement noise).
    """
    means_A = fit.energy_means[0]
    n, squares = residuals.n, residuals.sums[:, 3]
    mean_noise = squares / np.maximum(n * (n - 1), 1)
    return np.sqrt(np.einsum("jk,kl,jl->j", means_A, fit.covariance, means_A) + mean_noise)


def _smoothed(damping: Dissipation, records: Records
              ) -> tuple[Dissipation, list[SmoothingInfo]]:
    """The dissipation the refinement integrates: each reversal g of a friction force
    (`Dissipation.reversals`) rounded over SMOOTHING times its root mean square over the
    records (`Dissipation.smoothed`), and what the report says of each: the width, and the
    friction force's error relative to its size, at most 1 and on average over the
    records' samples (they are where the recording and the model are compared)."""
    if not damping.reversals:
        return damping, []
    values = [g(records.X) for g in damping.reversals]
    widths = [SMOOTHING * float(np.sqrt(np.mean(np.square(g)))) for g in values]
    report = [SmoothingInfo(reversal=str(g.expression).replace("Abs(", "abs("), width=w,
                            mean_force_error=float(np.mean(np.abs(
                                np.sign(value) - value / np.hypot(value, w)))))
              for g, value, w in zip(damping.reversals, values, widths, strict=True)]
    return damping.smoothed(widths), report


def _crossed_kink(kinks: Sequence[Func], records: Records) -> str | None:
    """The first place where a function is not smooth that the records reach (change sign
    across, or come within a thousandth of their largest distance from), or None."""
    for kink in kinks:
        values = kink(records.X)
        values = values[np.isfinite(values)]
        if values.size and (np.min(values) <= 0 <= np.max(values)
                            or np.min(np.abs(values)) < 1e-3 * np.max(np.abs(values))):
            return str(kink.expression).replace("Abs(", "abs(")
    return None
