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
(`hamid.dynamics`, with weights per state). Segments
keep the integration short enough that a wrong start cannot wander off into another
minimum, and the per-segment states are eliminated from the normal equations (Schur
complement), so the work grows linearly with the record.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.integrate import solve_ivp

from hamid.dissipation import Dissipation
from hamid.dynamics import Dynamics, Motion
from hamid.model import Model
from hamid.records import Records

__all__ = ["Refinement", "RefinementFailed", "refine"]

SEGMENT_PERIODS = 4.0  # dominant periods per segment, halved down to one when it fails
MIN_SEGMENT_PERIODS = 1.0
MIN_SEGMENT_SAMPLES = 8
CHI2_LIMIT = 1.5       # weighted misfit per degree of freedom that still counts as a fit
MAX_ITERATIONS = 20
# Segments integrated together as one vectorised system: as many as keep the integrated
# values of a batch (copies x states x samples of a segment) within BATCH_VALUES.
MAX_BATCH, BATCH_VALUES = 256, 1 << 22
STEP = 1e-7            # relative forward-difference step of the Jacobian
# Integration steps allowed per sample time (and a floor): smooth motion needs about one;
# a motion that is stiff or blows up would otherwise crawl on for hours.
MAX_STEPS_PER_SAMPLE, MIN_STEP_BUDGET = 50, 1000
# Gauss-Newton runs at the loose tolerance until it settles, then tightens to the strict
# one only when the parameters are determined finely enough for it to matter (clean data).
LOOSE_RTOL, STRICT_RTOL = 1e-8, 1e-11
TIME_ROUNDING = 16     # in units of the rounding of the largest time: times that close are one


class RefinementFailed(Exception):
    """The integrated model could not be fitted to the recording; the reason is the text."""


@dataclass(frozen=True)
class Refinement:
    """The refined free parameters and what the report says of them."""

    theta: npt.NDArray[np.float64]
    covariance: npt.NDArray[np.float64]
    dof: int
    chi2_per_dof: float
    segments: int
    segment_seconds: float
    iterations: int

    @property
    def description(self) -> str:
        """What the covariance is, for the report."""
        return ("Gauss-Newton covariance of the trajectory fit, scaled by its misfit per "
                f"degree of freedom ({self.chi2_per_dof:.3g})")


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


def refine(model: Model, records: Records, damping: Dissipation, theta_all: npt.ArrayLike,
           free: list[int], period: float, weight: npt.NDArray[np.float64],
           progress: Callable[[str], None] | None = None) -> Refinement:
    """Parameters whose integrated segments fit the recording best (module docstring).

    `theta_all` holds every parameter (fixed ones at their values) and starts the search;
    only the indices in `free` are fitted. `weight` is 1 / noise std of each variable (0
    for a variable that carries no independent information, e.g. derived velocities).
    Segments of four periods are tried first and halved while the misfit per degree of
    freedom stays above CHI2_LIMIT or the integration fails; raises RefinementFailed when
    even one period does not fit. `progress`, if given, hears of every batch of segments
    integrated.
    """
    periods = SEGMENT_PERIODS
    while True:
        try:
            result = _fit_segments(model, records, damping, np.asarray(theta_all, float),
                                   free, periods * period, weight, progress)
        except (_SegmentFitFailed, np.linalg.LinAlgError) as exc:
            failure = f"{exc}"
        else:
            if result.chi2_per_dof < CHI2_LIMIT:
                return result
            failure = (f"its misfit is {result.chi2_per_dof:.3g} times the noise variance")
        if periods / 2 < MIN_SEGMENT_PERIODS:
            raise RefinementFailed(f"{failure}, even over segments of {periods:g} period"
                                   f"{'s' if periods != 1 else ''}")
        periods /= 2


class _SegmentFitFailed(Exception):
    """One segment length did not give a fit; the reason is the text."""


def _fit_segments(model: Model, records: Records, damping: Dissipation,
                  theta_all: npt.NDArray[np.float64], free: list[int], length: float,
                  weight: npt.NDArray[np.float64],
                  progress: Callable[[str], None] | None) -> Refinement:
    """Gauss-Newton over the free parameters and every segment's initial state."""
    assert records.t is not None
    t = records.t
    pieces = _segments(records, t, length)
    if not pieces:
        raise _SegmentFitFailed(f"no trajectory holds {MIN_SEGMENT_SAMPLES} samples")
    X = records.X
    dynamics = Dynamics(model, damping)
    n_states, p = X.shape[1], len(free)
    tau = [t[a:b] - t[a] for a, b in pieces]
    # t[i] - t[a] carries the rounding of both times: segments sampled alike then differ in
    # their last bits, and would each add their own times to a batch's integration grid
    resolution = TIME_ROUNDING * np.finfo(float).eps * float(np.max(np.abs(t)))
    measured = [X[a:b] for a, b in pieces]    # views; weighted segment by segment
    x_step = STEP * np.maximum(np.abs(X).max(axis=0), X.std(axis=0))
    theta = theta_all.copy()
    X0 = np.array([X[a] for a, _ in pieces])
    n_used = sum(len(x) for x in tau) * int(np.count_nonzero(weight))
    dof = max(n_used - p - n_states * len(pieces), 1)
    rtol = LOOSE_RTOL
    damping_factor, best, converged = 0.0, None, False
    iterations = 0

    def batch_done(done: int) -> None:   # during iteration number iterations + 1
        if progress is not None:
            progress(f"trajectory fit over segments of {length:.3g} s: iteration "
                     f"{iterations + 1}, {done:,} of {len(pieces):,} segments")

    with np.errstate(all="ignore"):
        for _ in range(MAX_ITERATIONS):
            free_theta = theta[free]
            theta_step = STEP * np.maximum(np.abs(free_theta), 1e-3 * np.abs(free_theta).max())
            theta_step[theta_step == 0] = STEP   # every start at zero: no scale to go by
            normal = _normal_equations(dynamics, tau, measured, theta, X0, free, x_step,
                                       theta_step, weight, rtol, resolution, batch_done)
            if best is not None and normal.cost > best[0].cost * (1 + 1e-12):
                # the step made it worse: return to the best point and damp the step
                normal, theta, X0 = best
                damping_factor = max(10 * damping_factor, 1e-3)
            else:
                damping_factor = damping_factor / 10 if damping_factor > 1e-6 else 0.0
                best = normal, theta, X0
            d_theta, d_x, schur = normal.step(damping_factor)
            theta = theta.copy()
            theta[free] += d_theta
            X0 = X0 + d_x
            iterations += 1
            # the parameters' spread, scaled by the misfit (the noise may be misjudged)
            spread = np.sqrt(np.abs(np.diag(np.linalg.inv(schur))) * normal.cost / dof)
            settled = np.all(np.abs(d_theta) <= 1e-9 * np.abs(theta[free]) + 1e-3 * spread)
            if damping_factor == 0.0 and settled:
                relative_spread = spread / np.maximum(np.abs(theta[free]), 1e-300)
                if rtol > STRICT_RTOL and np.min(relative_spread) < 1e3 * rtol:
                    rtol, best = STRICT_RTOL, None
                    continue
                converged = True
                break
    if best is None or (not converged and damping_factor != 0.0):
        raise _SegmentFitFailed(f"Gauss-Newton did not settle in {MAX_ITERATIONS} iterations")
    chi2 = best[0].cost / dof
    if not np.isfinite(chi2) or not np.all(np.isfinite(theta)):
        raise _SegmentFitFailed("the fit diverged")
    covariance = np.linalg.inv(best[0].step(0.0)[2]) * chi2
    return Refinement(theta[free], covariance, dof, float(chi2), len(pieces), float(length),
                      iterations)


@dataclass(frozen=True)
class _Normal:
    """Gauss-Newton normal equations, the segment states not yet eliminated."""

    cost: float
    H_tt: npt.NDArray[np.float64]   # (p, p)
    g_t: npt.NDArray[np.float64]    # (p,)
    H_xx: npt.NDArray[np.float64]   # (S, 2N, 2N)
    H_xt: npt.NDArray[np.float64]   # (S, 2N, p)
    g_x: npt.NDArray[np.float64]    # (S, 2N)

    def step(self, damping: float) -> tuple[Any, Any, Any]:
        """Parameter step, segment-state steps and the Schur complement (Marquardt-damped)."""
        n = self.H_xx.shape[1]
        H_xx = self.H_xx + damping * np.einsum("sii->si", self.H_xx)[:, :, None] * np.eye(n)
        inverse = np.linalg.inv(H_xx)
        schur = (self.H_tt + damping * np.diag(np.diag(self.H_tt))
                 - np.einsum("sak,sab,sbl->kl", self.H_xt, inverse, self.H_xt))
        rhs = self.g_t - np.einsum("sak,sab,sb->k", self.H_xt, inverse, self.g_x)
        d_theta = np.linalg.solve(schur, rhs)
        d_x = np.einsum("sab,sb->sa", inverse,
                        self.g_x - np.einsum("sak,k->sa", self.H_xt, d_theta))
        return d_theta, d_x, schur


def _normal_equations(dynamics: Dynamics, tau: list[Any], measured: list[Any],
                      theta: Any, X0: Any, free: list[int], x_step: Any, theta_step: Any,
                      weight: Any, rtol: float, resolution: float,
                      batch_done: Callable[[int], None]) -> _Normal:
    """Residuals and forward-difference Jacobians of every segment, summed into _Normal.

    Each batch of segments is integrated as one system of 1 + 2N + p copies per segment
    (as is, each initial-state component perturbed, each free parameter perturbed); the
    copies share the adaptive steps, so their differences carry almost no integration error.
    Sample times of the batch that differ by less than `resolution` are integrated to once;
    `batch_done` hears how many segments are done after each batch.
    """
    S, n_states, p = len(tau), X0.shape[1], len(free)
    copies = 1 + n_states + p
    H_tt, g_t = np.zeros((p, p)), np.zeros(p)
    H_xx, H_xt = np.zeros((S, n_states, n_states)), np.zeros((S, n_states, p))
    g_x = np.zeros((S, n_states))
    cost = 0.0
    parameters = np.concatenate([[1.0], theta])
    shifted = np.repeat(parameters[:, None], copies, axis=1)
    for k, index in enumerate(free):
        shifted[1 + index, 1 + n_states + k] += theta_step[k]
    steps = np.concatenate([x_step, theta_step])
    batch_size = max(1, min(MAX_BATCH, BATCH_VALUES // (copies * n_states * max(map(len, tau)))))
    for lo in range(0, S, batch_size):
        batch = range(lo, min(lo + batch_size, S))
        B = len(batch)
        starts = np.repeat(X0[lo:lo + B][None], copies, axis=0)     # (copies, B, 2N)
        starts[1 + np.arange(n_states), :, np.arange(n_states)] += x_step[:, None]
        W = np.repeat(shifted, B, axis=1)                              # (1 + P, copies * B)
        span = max(tau[s][-1] for s in batch)
        grid, where = _common_times([tau[s] for s in batch], resolution)
        budget = _EVALUATIONS_PER_STEP * (MAX_STEPS_PER_SAMPLE * len(grid) + MIN_STEP_BUDGET)
        solution = solve_ivp(_rhs(dynamics.at(W), budget), (0.0, span),
                             starts.reshape(-1, n_states).T.ravel(), method="DOP853",
                             t_eval=grid, rtol=rtol,
                             atol=np.repeat(1e-2 * rtol / STEP * x_step, copies * B))
        if solution.status != 0:
            raise _SegmentFitFailed(f"the integration failed ({solution.message})")
        values = solution.y.reshape(n_states, copies, B, len(grid))
        if not np.all(np.isfinite(values)):
            raise _SegmentFitFailed("the integrated motion is not finite")
        offset = 0
        for b, s in enumerate(batch):
            m = len(tau[s])
            Y = values[:, :, b, where[offset:offset + m]] * weight[:, None, None]
            offset += m
            base = Y[:, 0]                                              # (2N, m)
            residual = ((measured[s] * weight).T - base).ravel()
            J = ((Y[:, 1:] - base[:, None]) / steps[None, :, None])     # (2N, c, m)
            J = J.transpose(0, 2, 1).reshape(-1, copies - 1)
            H = J.T @ J
            g = J.T @ residual
            cost += float(residual @ residual)
            H_xx[s], H_xt[s] = H[:n_states, :n_states], H[:n_states, n_states:]
            g_x[s] = g[:n_states]
            H_tt += H[n_states:, n_states:]
            g_t += g[n_states:]
        batch_done(lo + B)
    return _Normal(cost, H_tt, g_t, H_xx, H_xt, g_x)


def _common_times(times: list[npt.NDArray[np.float64]],
                  resolution: float) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.intp]]:
    """The distinct times of all the arrays, those closer than `resolution` taken as one
    (the earliest), and the index into them of every time of the concatenated arrays."""
    joined = np.concatenate(times)
    order = np.argsort(joined, kind="stable")
    ordered = joined[order]
    starts = np.empty(len(ordered), dtype=bool)
    starts[0] = True
    starts[1:] = np.diff(ordered) > resolution
    where = np.empty(len(ordered), dtype=np.intp)
    where[order] = np.cumsum(starts) - 1
    return ordered[starts], where


_EVALUATIONS_PER_STEP = 12  # DOP853's stages


def _rhs(motion: Motion, budget: int) -> Any:
    """solve_ivp's right-hand side (q, v)' = (v, a) for many states, flattened by variable;
    it stops the integration after `budget` evaluations."""
    evaluations = iter(range(budget))

    def rhs(t: float, y: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        if next(evaluations, None) is None:
            raise _SegmentFitFailed("the integration needs too many steps: the model's motion "
                                    "is stiff or blows up")
        return motion(t, y)
    return rhs
