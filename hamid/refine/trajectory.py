"""Trajectory refinement: fit the model's integrated motion to the recording itself.

The energy and weak-form rows are linear in the parameters but carry the measurement noise
inside the equations (squared and multiplied, or integrated against the test functions).
Fitting the trajectories instead puts the noise where it is: each recorded sample is the
model's motion plus white noise. Every trajectory is cut into segments a few periods long,
each with its own initial state, and the parameters and those states minimise

    sum over samples i, variables c of ((x_ic - x_c(t_i; theta, x0_s)) / sigma_c)^2

by Gauss-Newton (Levenberg-Marquardt when a step fails), started from the joint fit. The
motion follows Lagrange's equations of L = L0 + sum_k theta_k L_k with the damping forces,
M(q; theta) a = dL/dq - (d/dq dL/dv) v + F, every piece linear in (1, theta)
(`hamid.model.dynamics`, with weights per state). Segments
keep the integration short enough that a wrong start cannot wander off into another
minimum, and the per-segment states are eliminated from the normal equations (Schur
complement), so the work grows linearly with the record. A `SegmentFit` also gives the
parameters' covariance (misfit-scaled, or the sandwich over segments) and what the
parameters predict for segments left out of the fit, for `hamid.refine.joint_refinement` to
judge it by.

`join` refits it over neighbouring segments joined into longer ones by multiple shooting:
the segments stay as they were cut (short, so that many integrate together), but those of
one group are tied by continuity, the state integrated to the next segment's first sample
equal to that segment's initial state. The Gauss-Newton step is condensed onto each
group's first state: with E_x, E_theta the derivatives of a segment's end state and d its
gap to the next initial state, the next state's step is E_x dx + E_theta dtheta + d, so
every state's step is P dx_first + Q dtheta + c along the chain (`_condensed`); each
segment's normal equations in (dx, dtheta) become its group's in (dx_first, dtheta), and
after the step the chain closes the gaps to first order. Converged, the gaps vanish and
the fit is that of one segment per group. Every fit integrates its segments on to where
a tie would compare them (`_Problem.end_times`), so that a join's first step is taken from
the last point of the fit it ties, without integrating it again.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from hamid.data.records import Records
from hamid.model.dissipation import Dissipation
from hamid.model.dynamics import Dynamics
from hamid.model.models import Model
from hamid.refine import integration
from hamid.refine.steps import ROUNDING, Damping, Normal, scores

__all__ = ["RefinementFailed", "SegmentFit", "Stop", "TooUnstable", "fit", "join", "refine",
           "refit", "round_values", "segment_count", "settle"]

SEGMENT_PERIODS = 4.0  # dominant periods per segment, halved down to one when it fails
MIN_SEGMENT_PERIODS = 1.0
MIN_SEGMENT_SAMPLES = 8
# Gauss-Newton steps at most: far starts (a damped two-mass chain's linear fit from its
# accelerations integrated twice, the mass 0.12 for 2) took 8-71 in 400 realizations
MAX_ITERATIONS = 100
# Segments integrated together as one vectorised system: as many as keep the integrated
# values of a batch (copies x states x samples of a segment) within BATCH_VALUES.
MAX_BATCH, BATCH_VALUES = 256, 1 << 22
STEP = 1e-7            # relative forward-difference step of the Jacobian
# Integration steps allowed per sample time (and a floor): smooth motion needs about one;
# a motion that is stiff or blows up would otherwise crawl on for hours.
MAX_STEPS_PER_SAMPLE, MIN_STEP_BUDGET = 50, 1000
# Largest growth of a state step along a group's chain of tied segments, each state in
# units of its scale: beyond it the motion is too unstable for the linearised continuity
# to carry the step, nor its covariance the estimates' spread. Regular motion grows
# linearly (at most 54 over 32 periods of the test systems' records); chaotic motion
# grows exponentially (2e6 over 200 s of Henon-Heiles at energy 0.145, where the tied
# fit reported standard errors 1e4 times too small).
MAX_GROWTH = 1e3
# Gauss-Newton runs at the loose tolerance, and tightens at the first undamped step
# that shows the parameters determined finely enough for it to matter, without settling
# at the loose one first: to TOLERANCE_SHARE of the smallest relative spread (halved, so
# that the spread's next estimate does not tighten it again), down to the strict
# tolerance (clean data). DOP853's steps grow as rtol^(-1/8): a long record whose spread
# is 1e-5 integrates at 5e-9, 1.1 times the loose tolerance's steps, not at 1e-11, 2.4.
LOOSE_RTOL, STRICT_RTOL = 1e-8, 1e-11
TOLERANCE_SHARE = 1e-3
# Gauss-Newton stops when the point it steps to is within this many standard errors of
# the minimum: the step itself, times the ratio by which the last two undamped steps
# shrank (Gauss-Newton converges at least linearly near a minimum, quadratically when
# the residuals are small, where the ratio overstates the next step's size)
SETTLED = 1e-3
TIME_ROUNDING = 16     # in units of the rounding of the largest time: times that close are one


@dataclass(frozen=True)
class Stop:
    """When Gauss-Newton stops: once the point it steps to is within `within` standard
    errors of the minimum (SETTLED, or looser for a fit that a joined fit goes on from,
    `settle` finishing it when none does), or, with `beyond`, where the misfit per
    degree of freedom an undamped step heads for exceeds that (the weights are wrong, and
    the point reached starts a fit under others)."""

    within: float = SETTLED
    beyond: float | None = None


class RefinementFailed(Exception):
    """The integrated model could not be fitted to the recording; the reason is the text."""


class TooUnstable(RefinementFailed):
    """Segments could not be tied: a state step grows along them beyond MAX_GROWTH."""


@dataclass(frozen=True, eq=False)
class _Problem:
    """The segments of a recording at one length, and what integrating them needs."""

    dynamics: Dynamics
    records: Records
    pieces: list[tuple[int, int]]             # each segment's rows (start, stop)
    tau: list[npt.NDArray[np.float64]]        # each segment's times from its start
    measured: list[npt.NDArray[np.float64]]   # each segment's samples (views)
    x_step: npt.NDArray[np.float64]           # forward-difference step of each variable
    resolution: float                         # times closer than this are one
    weight: npt.NDArray[np.float64]           # 1 / noise of each variable
    length: float                             # seconds per segment as cut
    starts: npt.NDArray[np.intp]              # each group's first segment (tied to the next)
    inputs: integration.SampledInputs | None  # each segment's recorded inputs (driven models)

    @classmethod
    def cut(cls, model: Model, records: Records, damping: Dissipation, length: float,
            weight: npt.NDArray[np.float64]) -> _Problem:
        """The records cut into segments of about `length` seconds."""
        assert records.t is not None
        t, X = records.t, records.compared
        pieces = _segments(records, t, length)
        if not pieces:
            raise _SegmentFitFailed(f"no trajectory holds {MIN_SEGMENT_SAMPLES} samples")
        # t[i] - t[a] carries the rounding of both times: segments sampled alike then
        # differ in their last bits, and would each add their own times to a batch's grid
        resolution = TIME_ROUNDING * np.finfo(float).eps * float(np.max(np.abs(t)))
        return cls(dynamics=Dynamics(model, damping), records=records, pieces=pieces,
                   tau=[t[a:b] - t[a] for a, b in pieces], measured=[X[a:b] for a, b in pieces],
                   x_step=STEP * np.maximum(records.extent, records.spread), resolution=resolution,
                   weight=weight, length=length, starts=np.arange(len(pieces)),
                   inputs=_segment_inputs(records, pieces))

    def reweighted(self, weight: npt.NDArray[np.float64]) -> _Problem:
        """The same segments under other weights."""
        return dataclasses.replace(self, weight=weight)

    def tied(self, count: int, longest: float) -> _Problem:
        """Up to `count` neighbouring groups of one trajectory tied into one, as long as it
        spans at most `longest` seconds."""
        t = self.records.t
        assert t is not None
        bounds = [*self.starts.tolist(), len(self.pieces)]
        starts, g = [], 0
        while g < len(self.starts):
            first, a = bounds[g], self.pieces[bounds[g]][0]
            g, merged = g + 1, 1
            while (merged < count and g < len(self.starts) and self.goes_on[bounds[g] - 1]
                   and t[self.pieces[bounds[g + 1] - 1][1] - 1] - t[a] <= longest):
                g, merged = g + 1, merged + 1
            starts.append(first)
        return dataclasses.replace(self, starts=np.array(starts))

    @property
    def groups(self) -> int:
        return len(self.starts)

    @cached_property
    def goes_on(self) -> npt.NDArray[np.bool_]:
        """Whether each segment but the last goes on into the next (S - 1,): the same
        trajectory, no rows left out between; only such neighbours can be tied."""
        first = np.array([a for a, _ in self.pieces])
        stop = np.array([b for _, b in self.pieces])
        group = self.records.group
        return (first[1:] == stop[:-1]) & (group[first[1:]] == group[first[:-1]])

    @cached_property
    def end_times(self) -> npt.NDArray[np.float64]:
        """Each segment's time, from its start, of the state a tie to the next segment
        compares with that one's first sample: the time of that sample where the next
        segment goes on from this one (the same trajectory, no rows left out between),
        else its own last sample. Every fit integrates to them, tied or not, so that a
        fit of the same segments tied otherwise starts from its last point unintegrated."""
        t = self.records.t
        assert t is not None
        first = np.array([a for a, _ in self.pieces])
        ends = np.array([tau[-1] for tau in self.tau])
        goes_on = self.goes_on
        ends[:-1][goes_on] = t[first[1:][goes_on]] - t[first[:-1][goes_on]]
        return ends

    @property
    def span(self) -> float:
        """Seconds per group: the length cut, or the longest group's when tied."""
        if self.groups == len(self.pieces):
            return self.length
        t = self.records.t
        assert t is not None
        last = [self.pieces[s - 1][1] - 1 for s in [*self.starts[1:], len(self.pieces)]]
        return float(max(t[b] - t[self.pieces[a][0]]
                         for a, b in zip(self.starts, last, strict=True)))

    @property
    def n_samples(self) -> int:
        return sum(len(x) for x in self.tau)

    @property
    def n_used(self) -> int:
        """Weighted values: samples times variables with a weight."""
        return self.n_samples * int(np.count_nonzero(self.weight))


@dataclass(frozen=True, eq=False)
class SegmentFit:
    """A fit of the integrated segments at one set of weights: converged, or stopped
    where its weights proved hopeless (`refine`'s `beyond`).

    `theta` holds every parameter (fixed ones at their values), `states` each segment's
    fitted initial state; `normal` are the Gauss-Newton normal equations of the groups of
    tied segments (one group per segment when none are tied) at the last point evaluated,
    `point`, from which the final step `shift` of the free parameters was taken.
    """

    problem: _Problem
    theta: npt.NDArray[np.float64]
    free: tuple[int, ...]
    states: npt.NDArray[np.float64]
    normal: Normal
    shift: npt.NDArray[np.float64]
    iterations: int
    rtol: float
    point: _Point
    settled: bool   # within SETTLED standard errors of the minimum

    @property
    def segments(self) -> int:
        return len(self.problem.tau)

    @property
    def groups(self) -> int:
        """Groups of tied segments: each one initial state free."""
        return self.problem.groups

    @property
    def dof(self) -> int:
        """Weighted values less the free parameters and the groups' states."""
        return max(self.problem.n_used - len(self.free) - self.groups * self.states.shape[1],
                   1)

    @property
    def chi2_per_dof(self) -> float:
        return self.normal.total / self.dof

    @property
    def residual_rms(self) -> npt.NDArray[np.float64]:
        """Root mean square residual of each variable, in its own units (NaN unweighted)."""
        n = self.problem.n_samples
        weight = self.problem.weight
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(weight > 0, np.sqrt(self.normal.cost.sum(axis=0) / n) / weight,
                            np.nan)

    @cached_property
    def _reduced(self) -> tuple[npt.NDArray[np.float64], ...]:
        """Each group's misfit (G,), score (G, p) and Schur complement (G, p, p) at the
        final parameters, its initial state eliminated: to second order (Gauss-Newton),
        the misfit at the final parameters plus d, the state refitted, is
        misfit - 2 score.d + d.schur.d. The scores sum to zero once converged."""
        normal = self.normal
        score, schur = scores(normal)
        misfit = normal.misfit - np.einsum("sa,sab,sb->s", normal.g_x,
                                           np.linalg.inv(normal.H_xx), normal.g_x)
        # from the point the equations were made at to the final one
        shift = self.shift
        misfit = misfit - 2 * score @ shift + np.einsum("k,skl,l->s", shift, schur, shift)
        return misfit, score - schur @ shift, schur

    def covariance(self, kind: Literal["scaled", "sandwich"]) -> npt.NDArray[np.float64]:
        """The free parameters' covariance: "scaled", the Gauss-Newton one times the misfit
        per degree of freedom; "sandwich", robust to any error shared within a group of
        segments (groups independent), with the small-sample factor G / (G - p)."""
        _, score, schur = self._reduced
        inverse = np.linalg.inv(schur.sum(axis=0))
        if kind == "scaled":
            return inverse * self.chi2_per_dof
        S, p = score.shape
        return inverse @ (score.T @ score) @ inverse * S / max(S - p, 1)

    def input_response(self) -> npt.NDArray[np.float64]:
        """How much each recorded input sample moves the free parameters, to first order:
        (p, n_samples, n_inputs), the Gauss-Newton step a change of it calls for from the
        fit's last point, the states refitted, ties between segments followed.

        The fit integrates the inputs as recorded, so their noise drives the integrated
        motion: an error shared along each group of segments that the residuals' scale
        does not see. Each segment's scores and end state move by its input samples as
        the last pass of its Jacobian's copies gives them (`hamid.refine.input_noise`);
        a tie carries the end state's move into the segments after it (the gaps
        `_condensed` closes), and the states' elimination turns the scores' move into the
        parameters' (module docstring)."""
        problem, point = self.problem, self.point
        assert problem.records.U is not None and point.moves is not None
        normal, E = point.normal, point.E
        n = normal.H_xx.shape[1]
        S, p = len(problem.pieces), len(self.free)
        grouped, chain = normal, None
        if problem.groups < S:
            grouped, chain = _condensed(problem, point)
        group = np.arange(S) if chain is None else chain.group
        P = np.repeat(np.eye(n)[None], S, axis=0) if chain is None else chain.P
        Q = np.zeros((S, n, p)) if chain is None else chain.Q
        # the group's state eliminated: (H_0t' H_00^-1)[group], each segment's share
        eliminated = np.einsum("gak,gab->gkb", grouped.H_xt, np.linalg.inv(grouped.H_xx))[group]
        by_score = np.concatenate([Q.transpose(0, 2, 1) - eliminated @ P.transpose(0, 2, 1),
                                   np.repeat(np.eye(p)[None], S, axis=0)], axis=2)
        # a gap opened at a segment's end moves the states of those tied after it
        gap = -(Q.transpose(0, 2, 1) @ normal.H_xx + normal.H_xt.transpose(0, 2, 1)
                - eliminated @ P.transpose(0, 2, 1) @ normal.H_xx)
        by_end = np.zeros((S, p, n))
        for s in range(S - 2, -1, -1):
            if group[s + 1] == group[s]:
                by_end[s] = gap[s + 1] + by_end[s + 1] @ E[s + 1, :, :n]
        inverse = np.linalg.inv(scores(self.normal)[1].sum(axis=0))
        # each segment's scores and end state (c + 2N) to the parameters' move (p)
        moves = point.moves(inverse @ np.concatenate([by_score, by_end], axis=2))
        response = np.zeros((p, *problem.records.U.shape))
        for s, (a, c) in enumerate(_input_rows(problem.records, problem.pieces)):
            response[:, a:c] += moves[s].transpose(1, 0, 2)
        return response

    def held_out_folds(self, folds: npt.NDArray[np.intp]
                       ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Every parameter refitted without each group's fold, row by group (G, P), and
        each group's misfit at its row, its initial state refitted (G,); the groups are
        the segments when none are tied, as in `hamid.refine.joint_refinement`'s check.

        Both to second order from the fit (one Gauss-Newton step over the other folds'
        segments from where it stopped, near its minimum: the scores sum to about zero):
        the refits move the parameters by about a standard error."""
        misfit, score, schur = self._reduced
        total, total_score = schur.sum(axis=0), score.sum(axis=0)
        thetas = np.repeat(self.theta[None], self.groups, axis=0)
        held_misfit = np.empty(self.groups)
        for k in np.unique(folds):
            held = folds == k
            d = np.linalg.solve(total - schur[held].sum(axis=0),
                                total_score - score[held].sum(axis=0))
            thetas[np.ix_(held, self.free)] += d
            held_misfit[held] = (misfit[held] - 2 * score[held] @ d
                                 + np.einsum("k,skl,l->s", d, schur[held], d))
        return thetas, np.maximum(held_misfit, 0.0)

    def held_out(self, thetas: npt.NDArray[np.float64],
                 progress: Callable[[str], None] | None = None) -> npt.NDArray[np.float64]:
        """Each segment's weighted misfit at other parameters (every parameter, row by
        segment: (S, P)), its initial state refitted from the fitted one by a Gauss-Newton
        step (the misfit that step predicts); the segments as cut, untied. Raises
        RefinementFailed when the motion at those parameters cannot be integrated."""
        def batch_done(done: int) -> None:
            if progress is not None:
                progress(f"held-out check of the trajectory fit: {done:,} of "
                         f"{self.segments:,} segments")

        with np.errstate(all="ignore"):
            try:
                normal = _normal_equations(
                    problem=self.problem, theta=thetas, X0=self.states, free=(),
                    theta_step=None, rtol=self.rtol, batch_done=batch_done)[0]
            except _SegmentFitFailed as exc:
                raise RefinementFailed(f"{exc}, at the held-out parameters") from exc
            misfit = normal.cost.sum(axis=1)
            try:
                step = np.linalg.solve(normal.H_xx, normal.g_x[..., None])[..., 0]
            except np.linalg.LinAlgError:
                return misfit
        predicted = misfit - np.einsum("sa,sa->s", normal.g_x, step)
        return np.where(np.isfinite(predicted), np.maximum(predicted, 0.0), misfit)


def _segments(records: Records, t: npt.NDArray[np.float64],
              length: float) -> list[tuple[int, int]]:
    """(start, stop) rows of segments of about `length` seconds in every trajectory."""
    pieces = []
    for start, stop in records.bounds():
        times = t[start:stop]
        span = times[-1] - times[0]
        count = max(1, int(round(span / length)))
        edges = np.searchsorted(times, times[0] + span * np.arange(count + 1) / count)
        edges[-1] = stop - start
        pieces += [(start + a, start + b) for a, b in zip(edges[:-1], edges[1:], strict=True)
                   if b - a >= MIN_SEGMENT_SAMPLES]
    return pieces


def _input_rows(records: Records, pieces: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Each segment's rows of inputs: through the next sample of its trajectory, where a
    tie compares its end."""
    group = records.group
    return [(a, b + 1 if b < len(group) and group[b] == group[a] else b) for a, b in pieces]


def _segment_inputs(records: Records, pieces: list[tuple[int, int]]
                    ) -> integration.SampledInputs | None:
    """Each segment's recorded inputs (`_input_rows`), or None for a free model."""
    if records.U is None:
        return None
    assert records.t is not None
    rows = _input_rows(records, pieces)
    return integration.SampledInputs([records.t[a:c] - records.t[a] for a, c in rows],
                                     [records.U[a:c] for a, c in rows])


def segment_count(records: Records, length: float) -> int:
    """How many segments of about `length` seconds the records are cut into."""
    assert records.t is not None
    return len(_segments(records, records.t, length))


def refine(model: Model, records: Records, damping: Dissipation, theta_all: npt.ArrayLike,
           free: list[int], period: float, weight: npt.NDArray[np.float64],
           progress: Callable[[str], None] | None = None, stop: Stop = Stop()) -> SegmentFit:
    """Parameters whose integrated segments fit the recording best (module docstring).

    `theta_all` holds every parameter (fixed ones at their values) and starts the search;
    only the indices in `free` are fitted. `weight` is 1 / noise std of each variable (0
    for a variable that carries no independent information, e.g. derived velocities).
    Segments of four periods are tried first and halved while the fit fails, down to
    one period; raises RefinementFailed when even that fails. `progress`, if given, hears
    of every batch of segments integrated; `stop` says when Gauss-Newton stops.
    """
    periods = SEGMENT_PERIODS
    while True:
        try:
            return fit(model=model, records=records, damping=damping, theta_all=theta_all,
                       free=free, length=periods * period, weight=weight, progress=progress,
                       stop=stop)
        except RefinementFailed as exc:
            if periods / 2 < MIN_SEGMENT_PERIODS:
                raise RefinementFailed(f"{exc}, even over segments of {periods:g} period"
                                       f"{'s' if periods != 1 else ''}") from exc
        periods /= 2


def fit(model: Model, records: Records, damping: Dissipation, theta_all: npt.ArrayLike,
        free: list[int], length: float, weight: npt.NDArray[np.float64],
        progress: Callable[[str], None] | None = None, stage: str = "",
        stop: Stop = Stop()) -> SegmentFit:
    """The fit over segments of about `length` seconds (`refine`); `stage` names it in
    the progress messages. Raises RefinementFailed when it fails."""
    try:
        problem = _Problem.cut(model, records, damping, length, weight)
        return _fit_segments(problem=problem, theta=np.array(theta_all, float), free=tuple(free),
                             X0=None, rtol=LOOSE_RTOL, progress=progress, stage=stage, stop=stop)
    except (_SegmentFitFailed, np.linalg.LinAlgError) as exc:
        raise RefinementFailed(f"{exc}") from exc


def refit(fit: SegmentFit, weight: npt.NDArray[np.float64],
          progress: Callable[[str], None] | None = None) -> SegmentFit:
    """The same segments fitted again under other weights, from the fit's point."""
    try:
        return _fit_segments(problem=fit.problem.reweighted(weight), theta=fit.theta,
                             free=fit.free, X0=fit.states, rtol=fit.rtol, progress=progress,
                             stage="reweighted, ")
    except (_SegmentFitFailed, np.linalg.LinAlgError) as exc:
        raise RefinementFailed(f"{exc}, reweighted") from exc


def join(fit: SegmentFit, count: int, longest: float,
         progress: Callable[[str], None] | None = None) -> SegmentFit | None:
    """The fit with up to `count` neighbouring groups of segments tied into one (spanning
    at most `longest` seconds; module docstring), from the fit's parameters and states;
    None when no groups can be joined. Raises RefinementFailed when the joined fit fails,
    TooUnstable when the motion is too unstable to tie."""
    problem = fit.problem.tied(count, longest)
    if problem.groups == fit.groups:
        return None
    try:
        return _fit_segments(problem=problem, theta=fit.point.theta, free=fit.free,
                             X0=fit.point.X0, rtol=fit.rtol, progress=progress, stage="joined, ",
                             evaluated=fit.point)
    except (_SegmentFitFailed, np.linalg.LinAlgError) as exc:
        raise RefinementFailed(f"{exc}, over joined segments") from exc


def settle(fit: SegmentFit, progress: Callable[[str], None] | None = None) -> SegmentFit:
    """The fit, fitted on from its last point until within SETTLED standard errors of the
    minimum when it stopped further off (`Stop`); its iterations counted on."""
    if fit.settled:
        return fit
    try:   # its first step, from the last point, is the one the fit had taken last
        return _fit_segments(fit.problem, fit.point.theta, fit.free, fit.point.X0, fit.rtol,
                             progress, evaluated=fit.point, iterations=fit.iterations - 1)
    except (_SegmentFitFailed, np.linalg.LinAlgError) as exc:
        raise RefinementFailed(f"{exc}, fitted on") from exc


def _theta_step(free_theta: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The forward-difference step of each free parameter at `free_theta`."""
    step = STEP * np.maximum(np.abs(free_theta), 1e-3 * np.abs(free_theta).max())
    step[step == 0] = STEP   # every start at zero: no scale to go by
    return step


class _SegmentFitFailed(Exception):
    """One segment length did not give a fit; the reason is the text."""


def _fit_segments(problem: _Problem, theta: npt.NDArray[np.float64], free: tuple[int, ...],
                  X0: npt.NDArray[np.float64] | None, rtol: float,
                  progress: Callable[[str], None] | None, stage: str = "",
                  stop: Stop = Stop(), evaluated: _Point | None = None,
                  iterations: int = 0) -> SegmentFit:
    """Gauss-Newton over the free parameters and every group's initial state (the states
    of the segments tied to it following), stopped as `stop` says. `evaluated` is the
    segments' last point in a fit of them (tied otherwise, or stopped sooner), at `theta`,
    `X0` and `rtol`: the first step is taken from it without integrating them again;
    `iterations` are the steps the fit gone on with took to reach that point."""
    free_list = list(free)
    if X0 is None:
        X0 = np.array([x[0, :problem.x_step.size] for x in problem.measured])
    damping, best, converged, off, predicted = Damping(), None, False, np.inf, 0.0
    rounded_at = None   # the point whose damped steps last foretold a drop of rounding
    last_step = None   # the last undamped step, in standard errors
    length = problem.span
    dof = max(problem.n_used - len(free) - problem.groups * X0.shape[1], 1)

    def batch_done(done: int) -> None:   # during iteration number iterations + 1
        if progress is not None:
            progress(f"trajectory fit over segments of {length:.3g} s: {stage}iteration "
                     f"{iterations + 1}, {done:,} of {len(problem.tau):,} segments")

    with np.errstate(all="ignore"):
        for _ in range(MAX_ITERATIONS):
            theta_step = _theta_step(theta[free_list])
            lost = False   # a step to where the motion cannot be integrated
            if evaluated is None:
                try:
                    evaluated = _Point(theta, X0, *_normal_equations(
                        problem=problem, theta=theta, X0=X0, free=free, theta_step=theta_step,
                        rtol=rtol, batch_done=batch_done, keep=problem.inputs is not None))
                except _SegmentFitFailed:
                    if best is None:
                        raise
                    lost = True
            if not lost:
                point, evaluated = evaluated, None
                normal, chain = point.normal, None
                if problem.groups < len(problem.pieces):
                    normal, chain = _condensed(problem, point)
            worse = lost or (best is not None
                             and normal.total > best[0].total * (1 + ROUNDING))
            if worse:   # or where the motion blows up: back to the best point, damped
                normal, chain, point = best
                theta, X0 = point.theta, point.X0
                damping = damping.failed()
            else:
                if best is not None:
                    damping = damping.succeeded(best[0].total - normal.total, predicted)
                best = normal, chain, point
            d_theta, d_x, schur, predicted = normal.step(damping.factor)
            if damping.factor > 0 and predicted <= ROUNDING * normal.total:
                # no damped step lowers the misfit beyond rounding: the undamped one judges
                # whether the minimum is reached (below); failed again from the same point,
                # no step lowers it
                if worse and rounded_at is point:
                    raise _SegmentFitFailed("Gauss-Newton found no step that lowers the misfit")
                damping, rounded_at = Damping(), point
                d_theta, d_x, schur, predicted = normal.step(0.0)
            theta = theta.copy()
            theta[free_list] += d_theta
            X0 = X0 + (d_x if chain is None else chain.steps(d_x, d_theta))
            iterations += 1
            # heading beyond hope (where the undamped step's quadratic model lands):
            # stay at the point evaluated
            if (stop.beyond is not None and damping.factor == 0.0
                    and normal.total - predicted > stop.beyond * dof):
                theta, X0, d_theta = best[2].theta, best[2].X0, np.zeros_like(d_theta)
                break
            # the parameters' spread, scaled by the misfit (the noise may be misjudged)
            spread = np.sqrt(np.abs(np.diag(np.linalg.inv(schur))) * normal.total / dof)
            step = np.abs(d_theta) / np.maximum(spread, 1e-300)
            # Gauss-Newton's steps shrink at least as fast as the last two did: the point
            # stepped to is within that ratio of this step from the minimum
            ratio = 1.0 if last_step is None else min(
                float(np.linalg.norm(step) / max(np.linalg.norm(last_step), 1e-300)), 1.0)
            last_step = step if damping.factor == 0.0 else None
            # standard errors from the minimum (beyond round-off); tied, only once the
            # misfit was evaluated with the gaps closed (a step after the first)
            off = np.inf if chain is not None and iterations == 1 else float(np.max(
                (np.abs(d_theta) * ratio - 1e-9 * np.abs(theta[free_list]))
                / np.maximum(spread, 1e-300)))
            if damping.factor == 0.0:
                # a fine spread shows at the first undamped step: tighten there rather than
                # settle at the loose tolerance first (an evaluation less)
                relative_spread = spread / np.maximum(np.abs(theta[free_list]), 1e-300)
                wanted = TOLERANCE_SHARE * float(np.min(relative_spread))
                if rtol > STRICT_RTOL and wanted < rtol:
                    rtol, best = max(STRICT_RTOL, wanted / 2), None
                    continue
                if off <= stop.within:
                    converged = True
                    break
    if best is None or (not converged and damping.factor != 0.0):
        raise _SegmentFitFailed(f"Gauss-Newton did not settle in {MAX_ITERATIONS} iterations")
    fit = SegmentFit(problem=problem, theta=theta, free=free, states=X0, normal=best[0],
                     shift=d_theta, iterations=iterations, rtol=rtol, point=best[2],
                     settled=converged and off <= SETTLED)
    if not np.isfinite(fit.chi2_per_dof) or not np.all(np.isfinite(theta)):
        raise _SegmentFitFailed("the fit diverged")
    return fit


@dataclass(frozen=True)
class _Point:
    """A point evaluated: every parameter and segment state, the segments' own normal
    equations there (not condensed onto groups), and each segment's state at its end time
    (`_Problem.end_times`) with its derivatives, which ties to the next segment need."""

    theta: npt.NDArray[np.float64]  # (P,)
    X0: npt.NDArray[np.float64]     # (S, 2N)
    normal: Normal
    end: npt.NDArray[np.float64]    # (S, 2N)
    E: npt.NDArray[np.float64]      # (S, 2N, 2N + p)
    # a driven model's: each segment's response to its input samples of given
    # combinations of its scores and end state, on demand (`_responses`)
    moves: Callable[[npt.NDArray[np.float64]], list[npt.NDArray[np.float64]]] | None = None


def round_values(records: Records, n_free: int) -> int:
    """Values a Gauss-Newton round over `records` integrates (`_normal_equations`): each
    sample's state in 1 + 2N + p copies, as is and each state and free parameter
    perturbed."""
    n_samples, n_states = records.X.shape
    return (1 + n_states + n_free) * n_states * n_samples


def _normal_equations(problem: _Problem, theta: Any, X0: Any, free: tuple[int, ...],
                      theta_step: Any, rtol: float, batch_done: Callable[[int], None],
                      derivatives: bool = True, keep: bool = False
                      ) -> tuple[Normal, npt.NDArray[np.float64], npt.NDArray[np.float64],
                                 Callable[[npt.NDArray[np.float64]],
                                          list[npt.NDArray[np.float64]]] | None]:
    """Residuals and forward-difference Jacobians of every segment, into Normal; each
    one's state at its end time (`_Problem.end_times`, S, 2N) and that state's derivatives
    (S, 2N, 2N + p); with `keep` (a driven model), what gives each segment's response to
    its input samples of chosen combinations of its scores and end state, on demand
    (`_responses`, from the integrated values the batches keep: computed for the one point
    a covariance needs, not for every pass).

    `theta` holds every parameter, shared (P,) or one row per segment (S, P). The segments
    are cut into batches of about equal size, as many as keep each within MAX_BATCH
    segments and BATCH_VALUES values, each integrated as one system of 1 + 2N + p copies
    per segment (`hamid.refine.integration`: as is, each initial-state component perturbed, each
    free parameter perturbed; only the first without `derivatives`), in worker processes
    within an `integration.parallel` block. `batch_done` hears how many segments are done
    after each batch.
    """
    tau, measured = problem.tau, problem.measured
    S, n_states, p = len(tau), X0.shape[1], len(free)
    n_x = n_states if derivatives else 0
    inputs = problem.inputs
    copies = 1 + n_x + p
    rows = np.broadcast_to(theta, (S, np.shape(theta)[-1]))
    parameters = np.concatenate([np.ones((S, 1)), rows], axis=1).T     # (1 + P, S)
    x_step = problem.x_step
    steps = np.concatenate([x_step[:n_x], [] if theta_step is None else theta_step])
    tolerance = integration.Tolerance(rtol, 1e-2 * rtol / STEP * x_step, problem.resolution,
                                      MAX_STEPS_PER_SAMPLE, MIN_STEP_BUDGET)
    batch_size = max(1, min(MAX_BATCH, BATCH_VALUES // (copies * n_states * max(map(len, tau)))))
    edges = np.linspace(0, S, -(-S // batch_size) + 1).round().astype(int)
    ends = problem.end_times
    batches = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        starts = np.repeat(X0[lo:hi][None], copies, axis=0)     # (copies, B, 2N)
        starts[1 + np.arange(n_x), :, np.arange(n_x)] += x_step[:n_x, None]
        W = np.repeat(parameters[:, None, lo:hi], copies, axis=1)  # (1 + P, copies, B)
        for k, index in enumerate(free):
            W[1 + index, 1 + n_x + k] += theta_step[k]
        batches.append(integration.Batch(dynamics=problem.dynamics, tau=tau[lo:hi],
                                         measured=measured[lo:hi], weight=problem.weight,
                                         starts=starts, weights=W, steps=steps,
                                         tolerance=tolerance, ends=ends[lo:hi],
                                         inputs=None if inputs is None else
                                         inputs.part(lo, hi),
                                         keep=keep))
    c = copies - 1
    cost, H, g = np.zeros((S, len(problem.weight))), np.zeros((S, c, c)), np.zeros((S, c))
    end, E = np.zeros((S, n_states)), np.zeros((S, n_states, c))
    kept = []
    try:
        for lo, hi, blocks in zip(edges[:-1], edges[1:], integration.run(batches),
                                  strict=True):
            cost[lo:hi], H[lo:hi], g[lo:hi] = blocks.cost, blocks.H, blocks.g
            end[lo:hi], E[lo:hi] = blocks.end, blocks.E
            kept.append(blocks.integrated)
            batch_done(int(hi))
    except integration.IntegrationFailed as exc:
        raise _SegmentFitFailed(str(exc)) from exc
    # each block its own array: numpy's sums over strided views round otherwise
    return Normal(cost, *map(np.ascontiguousarray, (H[:, n_x:, n_x:], g[:, n_x:],
                                                     H[:, :n_x, :n_x], H[:, :n_x, n_x:],
                                                     g[:, :n_x]))), end, E, (
        functools.partial(_responses, batches, kept) if keep else None)


def _responses(batches: list[integration.Batch], kept: list[Any],
               outputs: npt.NDArray[np.float64]) -> list[npt.NDArray[np.float64]]:
    """Every segment's response to its input samples (`integration.responses`), of the
    combinations `outputs` (S, r, c + 2N) of its scores and end state, batch after
    batch."""
    edges = np.cumsum([0, *(len(batch.tau) for batch in batches)])
    return [move for batch, integrated, lo, hi in zip(batches, kept, edges[:-1], edges[1:],
                                                      strict=True)
            for move in integration.responses(batch, integrated, outputs[lo:hi])]


@dataclass(frozen=True)
class _Chain:
    """Each tied segment's state step from its group's: P dx_first + Q dtheta + c."""

    group: npt.NDArray[np.intp]     # (S,) each segment's group
    P: npt.NDArray[np.float64]      # (S, 2N, 2N)
    Q: npt.NDArray[np.float64]      # (S, 2N, p)
    c: npt.NDArray[np.float64]      # (S, 2N)

    def steps(self, d_first: npt.NDArray[np.float64],
              d_theta: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """Every segment's state step (S, 2N) from its group's (G, 2N)."""
        return (np.einsum("sab,sb->sa", self.P, d_first[self.group])
                + self.Q @ d_theta + self.c)


def _condensed(problem: _Problem, point: _Point) -> tuple[Normal, _Chain]:
    """The segments' normal equations at `point` condensed onto each group's first state
    (module docstring), and the chain that gives every segment's state step."""
    normal, X0, end, E = point.normal, point.X0, point.end, point.E
    S, n = X0.shape
    E_x, E_t = E[:, :, :n], E[:, :, n:]
    group = np.cumsum(np.isin(np.arange(S), problem.starts)) - 1
    position = np.arange(S) - problem.starts[group]
    P = np.repeat(np.eye(n)[None], S, axis=0)
    Q, c = np.zeros((S, n, E_t.shape[2])), np.zeros((S, n))
    for k in range(1, int(position.max()) + 1):
        now = np.flatnonzero(position == k)
        before = now - 1
        P[now] = E_x[before] @ P[before]
        Q[now] = E_x[before] @ Q[before] + E_t[before]
        c[now] = np.einsum("sab,sb->sa", E_x[before], c[before]) + end[before] - X0[now]
    scale = problem.x_step
    if not np.all(np.abs(P) * scale <= MAX_GROWTH * scale[:, None]):
        raise TooUnstable("the motion is too unstable to tie its segments")
    H_xx, H_xt = normal.H_xx, normal.H_xt
    Pt, Qt = P.transpose(0, 2, 1), Q.transpose(0, 2, 1)
    H_xx_Q = H_xx @ Q
    r = normal.g_x - np.einsum("sab,sb->sa", H_xx, c)
    per_segment = (
        Pt @ H_xx @ P,                                                    # H_00
        Pt @ (H_xx_Q + H_xt),                                             # H_0t
        Qt @ H_xx_Q + Qt @ H_xt + H_xt.transpose(0, 2, 1) @ Q + normal.H_tt,   # H_tt
        np.einsum("sba,sb->sa", P, r),                                    # g_0
        np.einsum("sbk,sb->sk", Q, r) + normal.g_t - np.einsum("sak,sa->sk", H_xt, c),
        np.einsum("sa,sa->s", c, normal.g_x - r) - 2 * np.einsum("sa,sa->s", c, normal.g_x))
    H_00, H_0t, H_tt, g_0, g_t, closing = (np.add.reduceat(a, problem.starts, axis=0)
                                           for a in per_segment)
    cost = np.add.reduceat(normal.cost, problem.starts, axis=0)
    normal_equations = Normal(cost=cost, H_tt=H_tt, g_t=g_t, H_xx=H_00, H_xt=H_0t, g_x=g_0,
                               closing=closing)
    return normal_equations, _Chain(group, P, Q, c)
