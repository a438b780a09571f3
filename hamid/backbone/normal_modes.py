"""Nonlinear normal modes: the free periodic orbits of a model continued from a linear mode.

The conservative equations of the model at the estimates (`Dynamics(model).at(1, theta)`,
no dissipation; a driven model with its inputs at zero) have an equilibrium q*, the minimum
of the potential V(q) = E(q, 0) nearest the origin, and about it the linear modes: the
generalized eigenproblem K phi = w^2 M phi with M and K the exact second derivatives of the
Lagrangian at q* (`Lagrangian.second_derivatives`), ordered by increasing w.

A mode's orbits are found by shooting. A natural energy is even in the velocities, so the
motion is reversible (q(-t), -v(-t) is a motion too), and the orbit continued from a linear
mode stops every coordinate at once twice per period: started at rest from q0, it is at
rest again at T/2, and the second half retraces the first backwards. The unknowns are
z = (q0, T); the equations are v(T/2; q0) = 0 (N of them) and one condition that places the
orbit on the branch. Their Jacobian comes from the variational equations integrated with the
motion (solve_ivp DOP853, rtol 1e-12, atol 1e-14 of the orbit's scale; the accelerations'
derivatives by central differences), and Newton's method converges to the integration's
accuracy. The branch is followed by pseudo-arclength continuation in (q0 / scale, T / T0),
from the linear mode at a thousandth of the largest amplitude asked (or half the smallest),
the step grown after easy corrections and halved after hard or failed ones. When a step
passes a target (an energy above the equilibrium's, or the amplitude of the leading
coordinate: half its peak-to-peak range, its extremes where its velocity vanishes), Newton's
method is run on that target exactly, from the two points about it.

Internal resonances are detected by the orbit's Floquet multipliers. Over a full period the
monodromy is Phi = R Phi_h^-1 R Phi_h (Phi_h over half a period, R the reversal v -> -v); it
keeps the energy's gradient and the flow's direction, so its nontrivial multipliers are the
eigenvalues of Phi restricted to the states of equal energy modulo the flow (2N - 2 of them,
in pairs lambda, 1/lambda). Each pair is read as an angle: arccos(s / 2) with s = lambda +
1/lambda on the unit circle, negative past +1 (a real positive pair). A multiplier at +1 is
another mode whose local frequency is an integer multiple of the orbit's, an n:1 internal
resonance: where it happens the branch meets (or turns into) another family of orbits. The
branch is stopped with `InternalResonanceError`, naming the energy and amplitude reached,
as soon as an angle comes within `RESONANCE_ANGLE` of zero (a frequency ratio within about
0.008 of an integer), and the steps are kept small enough that no angle moves by more than
half of that, so that none crosses unseen.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg
import scipy.optimize
from scipy.integrate import solve_ivp, trapezoid

from hamid.backbone.one_degree import Cycle
from hamid.errors import ModelError, UsageError
from hamid.model.dissipation import Dissipation
from hamid.model.dynamics import Dynamics, Motion
from hamid.model.models import Model

__all__ = ["RESONANCE_ANGLE", "InternalResonanceError", "LinearMode", "ModeFitted",
           "PeriodicOrbit", "SmallAmplitude", "normal_mode_branch", "small_amplitude"]

Array = npt.NDArray[np.float64]

RESONANCE_ANGLE = 0.05   # rad: a nontrivial Floquet multiplier this close to +1 is a resonance
_RTOL, _ATOL = 1e-12, 1e-14
_VARIATIONAL_ATOL = 1e-9   # the derivatives only steer Newton and give the multipliers
_ROUNDING = 10 * np.finfo(float).eps   # of a coordinate, relative to its equilibrium
_NEWTON_ROUNDING = 100   # Newton's corrections need not be finer than this many roundings
_NEWTON_TOL = 1e-11     # the correction, relative to the orbit's scale and period
_CORRECTOR_TOL = 1e-8   # the continuation's points, which only seed the targets' solves
# the bands' nudged orbits: their differences from the estimates' are 1e-4 of the orbit, so
# corrections this fine leave their central differences accurate to about 1e-4
_NUDGED_TOL = 1e-8
_NEWTON_ITERATIONS = 12
_FIRST_STEP, _LONGEST_STEP, _SHORTEST_STEP = 0.05, 0.25, 1e-7
_MOST_STEPS = 400
_PATH_NODES, _PATH_WEIGHTS = np.polynomial.legendre.leggauss(32)
_PATH_NODES, _PATH_WEIGHTS = (_PATH_NODES + 1) / 2, _PATH_WEIGHTS / 2   # on [0, 1]


@dataclass(frozen=True, kw_only=True)
class PeriodicOrbit:
    """One free periodic orbit of the conservative model."""

    energy: float            # conservative energy above the equilibrium's
    period: float
    t: np.ndarray            # (K,) times over one period, from 0 to period inclusive
    states: np.ndarray       # (2n, K): q then v along the orbit
    amplitudes: np.ndarray   # (n,) half the peak-to-peak range of each coordinate


class InternalResonanceError(ModelError):
    """A normal mode's branch meets an internal resonance: named where, not followed;
    `orbits`, those of the levels asked for that lie below it."""

    orbits: tuple[PeriodicOrbit, ...] = ()   # those asked for below it, by increasing level


@dataclass(frozen=True)
class _Linear:
    """The equilibrium and the linear modes about it."""

    equilibrium: Array          # q*
    frequencies: Array          # (N,) rad/s, increasing
    shapes: Array               # (N, N): column j is mode j, M-normalised


@dataclass(frozen=True, eq=False)
class _Shot:
    """The half-period motion from rest at q0: where it ends, the variational matrix, and
    the dense solution of both."""

    z: Array                    # (q0, T)
    end: Array                  # (2N,) state at T/2
    jacobian: Array             # (N, N + 1): d v(T/2) / d(q0, T)
    half_flow: Array            # (2N, 2N): Phi_h
    solution: Callable[[Array | float], Array]   # solve_ivp's dense output over [0, T/2]


class _Branch:
    """The shooting problem of one model at its estimates: motion, energy, amplitudes."""

    def __init__(self, model: Model, theta: Array, linear: _Linear, scale: float):
        self.model, self.theta, self.linear, self.scale = model, theta, linear, scale
        def at_rest(t: float, out: Array) -> None:   # a driven model's free motion
            out[:] = 0.0

        self.motion: Motion = Dynamics(model).at(
            np.concatenate([[1.0], theta]), inputs=None if model.forcing is None else at_rest)
        self.n = len(model.coordinates)
        self.origin = np.concatenate([linear.equilibrium, np.zeros(self.n)])
        self.floor = _ROUNDING * float(np.abs(linear.equilibrium).max())
        # the variational equations' difference steps: on the orbit's scale, and no
        # smaller than the rounding of coordinates far from zero allows (else the
        # differences are noise, and the integrator shortens its steps to follow it)
        self.steps = 1e-6 * np.concatenate(
            [scale + np.abs(linear.equilibrium),
             np.full(self.n, scale * self.linear.frequencies[-1])])

    # -- the equations ---------------------------------------------------------------

    def _rhs(self, t: float, y: Array) -> Array:
        """The motion and its variational equations, the state taken from the
        equilibrium (`shoot`)."""
        N = self.n
        x, flow = y[:2 * N] + self.origin, y[2 * N:].reshape(2 * N, 2 * N)
        h = self.steps
        columns = np.concatenate([x[:, None], x[:, None] + np.diag(h), x[:, None] - np.diag(h)],
                                 axis=1)
        a = self.motion.accelerations(columns)
        da = (a[:, 1:2 * N + 1] - a[:, 2 * N + 1:]) / (2 * h)     # (N, 2N)
        out = np.empty_like(y)
        out[:N] = x[N:]
        out[N:2 * N] = a[:, 0]
        out[2 * N:] = np.vstack([flow[N:], da @ flow]).ravel()
        return out

    def shoot(self, z: Array) -> _Shot:
        """Integrate from rest at q0 = z[:N] over half the period z[N]. The integrator
        holds the coordinates' distance from the equilibrium, whose relative tolerance
        keeps the digits of a small orbit about an equilibrium far from zero (a pendulum
        hanging at pi)."""
        N = self.n
        y0 = np.concatenate([z[:N] - self.linear.equilibrium, np.zeros(N),
                             np.eye(2 * N).ravel()])
        size = max(np.abs(z[:N] - self.linear.equilibrium).max(), 1e-9 * self.scale)
        # no finer than the rounding of the accelerations at coordinates far from zero
        # allows, which an integrator asked for more follows with ever shorter steps
        floor = self.floor
        atol = np.concatenate([np.full(N, max(_ATOL * size, floor)),
                               np.full(N, max(_ATOL * size, floor)
                                       * self.linear.frequencies[-1]),
                               np.full(4 * N * N, _VARIATIONAL_ATOL)])
        sol = solve_ivp(self._rhs, (0.0, z[N] / 2), y0, method="DOP853", rtol=_RTOL,
                        atol=atol, dense_output=True)
        if not sol.success:
            raise ModelError(f"the orbit from rest at {_where(self.model, z[:N])} could not be "
                             f"integrated: {sol.message}")
        end = sol.y[:, -1]
        flow = end[2 * N:].reshape(2 * N, 2 * N)
        state = end[:2 * N] + self.origin
        acceleration = self.motion.accelerations(state[:, None])[:, 0]
        jacobian = np.hstack([flow[N:2 * N, :N], acceleration[:, None] / 2])
        offset = np.concatenate([self.origin, np.zeros(4 * N * N)])

        def solution(t: Array | float) -> Array:
            values = sol.sol(t)
            return values + (offset if values.ndim == 1 else offset[:, None])

        return _Shot(z, state, jacobian, flow, solution)

    # -- what places an orbit on the branch ---------------------------------------------

    def energy(self, q0: Array) -> tuple[float, Array]:
        """V(q0) - V(q*) and its gradient in (q0, T). The difference is the integral of dV
        along the segment from q*, by Gauss-Legendre (exact for polynomials of degree up to
        63): subtracting V(q*) would lose the small energies of a potential with a large
        constant (a pendulum's -g cos q) to rounding."""
        N, d = self.n, q0 - self.linear.equilibrium
        X = np.zeros((len(_PATH_NODES) + 1, 2 * N))
        X[:-1, :N] = self.linear.equilibrium + _PATH_NODES[:, None] * d
        X[-1, :N] = q0
        gradients = self.model.energy_gradient(X, self.theta)[:, :N]
        return float(_PATH_WEIGHTS @ (gradients[:-1] @ d)), np.append(gradients[-1], 0.0)

    def extremes(self, shot: _Shot, coordinate: int) -> tuple[Array, Array]:
        """The times in [0, T/2] where the coordinate's velocity vanishes (both ends and
        each sign change of v between them, refined by brentq), and its values there."""
        N = self.n
        half = shot.z[N] / 2
        grid = np.linspace(0.0, half, 129)
        v = shot.solution(grid)[N + coordinate]
        times = [0.0, half]
        for i in np.flatnonzero(np.sign(v[1:-2]) * np.sign(v[2:-1]) < 0) + 1:
            times.append(scipy.optimize.brentq(
                lambda t: shot.solution(t)[N + coordinate], grid[i], grid[i + 1],
                xtol=1e-15 * half, rtol=4 * np.finfo(float).eps))
        times_ = np.array(times)
        return times_, shot.solution(times_)[coordinate]

    def amplitude(self, shot: _Shot, coordinate: int) -> tuple[float, Array]:
        """Half the coordinate's peak-to-peak range and its gradient in (q0, T) (the
        extremes are where its velocity vanishes, so only their values move)."""
        N = self.n
        times, values = self.extremes(shot, coordinate)
        high, low = int(np.argmax(values)), int(np.argmin(values))
        rows = [shot.solution(times[k])[2 * N:].reshape(2 * N, 2 * N)[coordinate, :N]
                for k in (high, low)]
        return (values[high] - values[low]) / 2, np.append((rows[0] - rows[1]) / 2, 0.0)

    def orbit(self, shot: _Shot, samples: int) -> PeriodicOrbit:
        N = self.n
        period = shot.z[N]
        t = np.linspace(0.0, period, samples)
        back = t > period / 2
        states = shot.solution(np.where(back, period - t, t))[:2 * N]
        states[N:, back] *= -1.0   # the second half retraces the first backwards
        amplitudes = np.array([np.ptp(self.extremes(shot, i)[1]) / 2 for i in range(N)])
        return PeriodicOrbit(energy=self.energy(shot.z[:N])[0], period=float(period), t=t,
                             states=states, amplitudes=amplitudes)

    def angles(self, shot: _Shot) -> Array:
        """The nontrivial Floquet multipliers as angles, increasing (module docstring)."""
        N = self.n
        if N == 1:
            return np.empty(0)
        R = np.diag(np.concatenate([np.ones(N), -np.ones(N)]))
        flow = R @ np.linalg.solve(shot.half_flow, R @ shot.half_flow)
        gradient = self.energy(shot.z[:N])[1][:N]
        direction = self.motion.accelerations(
            np.concatenate([shot.z[:N], np.zeros(N)])[:, None])[:, 0]
        # the states of equal energy modulo the flow: q-parts normal to dV, v-parts to a
        P = scipy.linalg.block_diag(scipy.linalg.null_space(gradient[None]),
                                    scipy.linalg.null_space(direction[None]))
        reduced = P.T @ flow @ P
        sums = np.sort(np.linalg.eigvals(reduced + np.linalg.inv(reduced)).real)
        s = (sums[0::2] + sums[1::2]) / 2    # each lambda + 1/lambda comes twice
        return np.sort(np.where(np.abs(s) <= 2, np.arccos(np.clip(s / 2, -1, 1)),
                                np.where(s > 2, -np.arccosh(np.maximum(s / 2, 1)),
                                         math.pi + np.arccosh(np.maximum(-s / 2, 1)))))


def _linear_modes(model: Model, theta: Array, near: Array | None = None) -> _Linear:
    """The minimum of V nearest `near` (default the origin), and the linear modes about
    it."""
    N = len(model.coordinates)
    lagrangian = model.lagrangian

    def gradient(q: Array) -> Array:
        return model.energy_gradient(np.concatenate([q, np.zeros(N)])[None], theta)[0, :N]

    def hessians(q: Array) -> tuple[Array, Array]:
        X = np.concatenate([q, np.zeros(N)])[None]   # at rest: K without the kinetic part
        d_dv, d_dq = lagrangian.second_derivatives(X, theta)
        return d_dv[0, :, N:], -d_dq[0, :, :N]

    q = np.zeros(N) if near is None else np.array(near, dtype=float)
    if not np.all(np.isfinite(gradient(q))):
        raise ModelError(f"model {model.name!r}: the potential is not finite at "
                         f"{_where(model, q)}")
    for _ in range(50):   # Newton on dV = 0 from `near`, the exact Hessian
        slope = gradient(q)
        M, K = hessians(q)
        if np.all(np.abs(slope) <= 1e-14 * (1 + np.abs(K).max() * (1 + np.abs(q).max()))):
            break
        q = q - np.linalg.lstsq(K, slope, rcond=None)[0]
    else:
        raise ModelError(f"model {model.name!r}: no equilibrium found near "
                         f"{_where(model, np.zeros(N) if near is None else near)}")
    M, K = hessians(q)
    try:
        w2, shapes = scipy.linalg.eigh(K, M)
    except np.linalg.LinAlgError as error:
        raise ModelError(f"model {model.name!r}: the mass matrix at the equilibrium "
                         f"{_where(model, q)} is not positive definite") from error
    if w2[0] <= 0:
        raise ModelError(f"model {model.name!r}: the equilibrium {_where(model, q)} is not a "
                         f"minimum of the potential (a stiffness eigenvalue {w2[0]:.6g})")
    return _Linear(q, np.sqrt(w2), shapes)


@dataclass(frozen=True)
class LinearMode:
    """One mode of the model linearized about its equilibrium."""

    frequency: float              # rad/s (per unit of the recording's time)
    damping_ratio: float | None   # phi' C phi / (2 w); None where R is not smooth at rest
    shape: Array                  # (N,) M-normalised


@dataclass(frozen=True)
class SmallAmplitude:
    """The equilibrium q* and the linear modes about it, by increasing frequency."""

    equilibrium: Array
    modes: tuple[LinearMode, ...]


def small_amplitude(model: Model, estimates: Mapping[str, float],
                    dissipation: Dissipation | None = None, *,
                    near: npt.ArrayLike | None = None) -> SmallAmplitude:
    """The limit of every normal mode's backbone at small amplitude: the linear modes of
    the fitted model about the minimum of its potential nearest `near` (default the
    origin), each with its modal damping ratio phi' C phi / (2 w), C = d2R/dv2 at rest
    at the equilibrium (c / (2 sqrt(k m)) for one coordinate). Without a dissipation, or
    where a term of R with a nonzero coefficient has a kink (friction's abs: no
    linearization at rest), the damping ratios are None. Raises ModelError when the
    model has no minimum there or its energy is not natural."""
    theta = np.array([float(estimates[p]) for p in model.parameters])
    linear = _linear_modes(model, theta, None if near is None else np.asarray(near, float))
    N = len(model.coordinates)
    damping = None
    if dissipation is not None and len(dissipation):
        coefficients = np.array([float(estimates[n]) for n in dissipation.names])
        if not any(kinks and c != 0 for kinks, c in zip(dissipation.kinks, coefficients,
                                                        strict=True)):
            at_rest = np.concatenate([linear.equilibrium, np.zeros(N)])[None]
            damping = dissipation.force_slopes(at_rest, coefficients)[0, :, N:]
    modes = tuple(LinearMode(float(w), None if damping is None else
                             float(shape @ damping @ shape / (2 * w)), shape)
                  for w, shape in zip(linear.frequencies, linear.shapes.T, strict=True))
    return SmallAmplitude(linear.equilibrium, modes)


def _where(model: Model, q: Array) -> str:
    return "(" + ", ".join(f"{c}={x:.6g}" for c, x in zip(model.coordinates, q,
                                                             strict=True)) + ")"


@dataclass(frozen=True)
class _Measure:
    """What places an orbit on the branch: its energy, or a coordinate's amplitude."""

    branch: _Branch
    coordinate: int | None      # None: the energy

    def __call__(self, shot: _Shot) -> tuple[float, Array]:
        """The measure of the orbit and its gradient in (q0, T)."""
        if self.coordinate is None:
            return self.branch.energy(shot.z[:self.branch.n])
        return self.branch.amplitude(shot, self.coordinate)

    def equal_to(self, value: float) -> Callable[[_Shot], tuple[float, Array]]:
        """The condition measure = value, for `_newton`."""
        def condition(shot: _Shot) -> tuple[float, Array]:
            measure, gradient = self(shot)
            return measure - value, gradient
        return condition


def _newton(branch: _Branch, z: Array, condition: Callable[[_Shot], tuple[float, Array]],
            tolerance: float = _NEWTON_TOL) -> _Shot:
    """Correct z until v(T/2) = 0 and condition(shot) = (residual, gradient) is zero, the
    last correction under `tolerance` (relative to the orbit's scale and period, and no
    finer in the coordinates than their rounding allows, `_Branch.shoot`). At the strict
    default the orbit is integrated once more from the corrected z; a looser one (the
    continuation's own points) returns the last orbit integrated."""
    N, scales = branch.n, np.append(np.full(branch.n, branch.scale), z[branch.n])
    limits = tolerance * scales
    resolution = _NEWTON_ROUNDING * branch.floor   # the coordinates', and the period's
    limits[:N] = np.maximum(limits[:N], resolution)   # share of it at the orbit's size
    limits[N] = max(limits[N], z[N] * resolution / max(
        float(np.abs(z[:N] - branch.linear.equilibrium).max()), np.finfo(float).tiny))
    for _ in range(_NEWTON_ITERATIONS):
        shot = branch.shoot(z)
        residual, gradient = condition(shot)
        J = np.vstack([shot.jacobian, gradient])
        step = np.linalg.solve(J * scales, -np.append(shot.end[N:], residual)) * scales
        z = z + step
        if np.all(np.abs(step) <= limits):
            return branch.shoot(z) if tolerance <= _NEWTON_TOL else shot
    raise _NoConvergence


class _NoConvergence(Exception):
    """Newton's method did not converge: the continuation shortens its step."""


def normal_mode_branch(model: Model, estimates: Mapping[str, float], *, mode: int,
                       amplitudes: Sequence[float] | None = None,
                       coordinate: int | None = None,
                       energies: Sequence[float] | None = None,
                       samples: int = 256,
                       near: npt.ArrayLike | None = None) -> list[PeriodicOrbit]:
    """The periodic orbits of linear mode `mode` (1-based, by increasing frequency) of the
    conservative model at `estimates` about the minimum of its potential nearest `near`
    (default the origin), continued to each of `amplitudes` (of the leading `coordinate`:
    by default the largest in the linear mode's shape) or `energies` (above the
    equilibrium's), in the order asked, each sampled at `samples` times over a period.

    Raises InternalResonanceError where the branch meets an internal resonance, ModelError
    when the model has no well or the branch cannot be continued, UsageError for bad input.
    """
    N = len(model.coordinates)
    if not 1 <= mode <= N:
        raise UsageError(f"mode {mode}: the model {model.name!r} has modes 1 to {N}")
    if coordinate is not None and not 0 <= coordinate < N:
        raise UsageError(f"coordinate {coordinate}: the model {model.name!r} has coordinates "
                         f"0 to {N - 1}")
    if samples < 2:
        raise UsageError(f"samples {samples}: an orbit needs at least 2")
    targets = _targets(amplitudes, energies)
    missing = [p for p in model.parameters if p not in estimates]
    if missing:
        raise UsageError(f"no estimate of {', '.join(map(repr, missing))} for the model "
                         f"{model.name!r}")
    theta = np.array([float(estimates[p]) for p in model.parameters])

    linear = _linear_modes(model, theta, None if near is None else np.asarray(near, float))
    w, shape = linear.frequencies[mode - 1], linear.shapes[:, mode - 1]
    lead = int(np.argmax(np.abs(shape))) if coordinate is None else coordinate
    largest = np.abs(shape).max()
    # each target's linear displacement (its largest coordinate): the scale of the branch
    if energies is not None:
        reach = np.sqrt(2 * targets) / w * largest
    elif abs(shape[lead]) <= 1e-12 * largest:
        raise UsageError(f"coordinate {lead} ({model.coordinates[lead]}) does not move in "
                         f"linear mode {mode}: pick another to set its amplitudes")
    else:
        reach = targets / abs(shape[lead]) * largest
    branch = _Branch(model, theta, linear, float(reach.max()))
    measure = _Measure(branch, None if energies is not None else lead)
    walk = _Walk(branch, mode, measure, lead,
                 start=min(1e-3 * reach.max(), 0.5 * reach.min()) / largest)
    found: dict[int, PeriodicOrbit] = {}
    for index in np.argsort(targets):
        try:
            walk.advance_past(float(targets[index]))
        except InternalResonanceError as error:
            error.orbits = tuple(found.values())
            raise
        found[int(index)] = branch.orbit(walk.solve_at(float(targets[index])), samples)
    return [found[i] for i in range(len(targets))]


@dataclass(frozen=True, eq=False)
class ModeFitted:
    """A fitted model of several coordinates and one of its normal modes (1-based), led by
    coordinate number `lead` (None: the mode's largest), about the potential's minimum
    nearest `near` (None: the origin): the counterpart of `hamid.backbone.one_degree.Fitted`
    that the bands perturb."""

    model: Model
    estimates: Mapping[str, float]
    dissipation: Dissipation | None
    mode: int
    lead: int | None = None
    near: tuple[float, ...] | None = None

    def orbits(self, *, amplitudes: Sequence[float] | None = None,
               energies: Sequence[float] | None = None) -> list[tuple[Cycle, PeriodicOrbit]]:
        """Each orbit asked (`normal_mode_branch`) with its cycle: the energy the fitted
        dissipation takes over one period, the closed integral of its power v.dR/dv along
        the conservative orbit (the trapezoidal rule, exact to rounding for a smooth
        periodic integrand sampled over its period)."""
        found = normal_mode_branch(self.model, self.estimates, mode=self.mode,
                                   amplitudes=amplitudes, energies=energies,
                                   coordinate=self.lead, near=self.near)
        return [(self.cycle(orbit), orbit) for orbit in found]

    def corrected(self, orbits: Sequence[PeriodicOrbit]) -> list[Cycle]:
        """The cycles of this model's orbits at the leading coordinate's amplitudes of
        `orbits`, those of a model a little different (the bands' nudges): each found by
        Newton's method from its counterpart, not by continuing the branch again from its
        linear mode, a tenth of the cost or less."""
        model, N = self.model, len(self.model.coordinates)
        theta = np.array([float(self.estimates[p]) for p in model.parameters])
        linear = _linear_modes(model, theta,
                               None if self.near is None else np.asarray(self.near, float))
        lead = (int(np.argmax(np.abs(linear.shapes[:, self.mode - 1])))
                if self.lead is None else self.lead)
        reach = max(float(np.abs(orbit.states[:N, 0] - linear.equilibrium).max())
                    for orbit in orbits)
        branch = _Branch(model, theta, linear, reach)
        measure = _Measure(branch, lead)
        cycles = []
        for orbit in orbits:
            amplitude = float(orbit.amplitudes[lead])
            try:
                shot = _newton(branch, np.append(orbit.states[:N, 0], orbit.period),
                               measure.equal_to(amplitude), _NUDGED_TOL)
            except _NoConvergence:
                raise ModelError(f"mode {self.mode}: Newton's method did not converge on the "
                                 f"orbit of amplitude {amplitude:.6g} of "
                                 f"{model.coordinates[lead]} from its neighbour") from None
            cycles.append(self.cycle(branch.orbit(shot, len(orbit.t))))
        return cycles

    def cycle(self, orbit: PeriodicOrbit) -> Cycle:
        """The orbit's cycle: its period, energy and the energy the dissipation takes."""
        lost = None
        if self.dissipation is not None:
            coefficients = np.array([self.estimates[n] for n in self.dissipation.names])
            power = self.dissipation.power_parts(orbit.states.T) @ coefficients
            lost = float(trapezoid(power, orbit.t))
        return Cycle(orbit.period, lost, orbit.energy)

    def at_amplitude(self, amplitude: float) -> Cycle:
        """The cycle of the orbit whose leading coordinate has this amplitude."""
        return self.orbits(amplitudes=[amplitude])[0][0]


def _targets(amplitudes: Sequence[float] | None, energies: Sequence[float] | None) -> Array:
    """The amplitudes or the energies asked, checked."""
    if (amplitudes is None) == (energies is None):
        raise UsageError("give either amplitudes or energies of the normal mode, not "
                         f"{'both' if amplitudes is not None else 'neither'}")
    kind = "amplitude" if amplitudes is not None else "energy"
    targets = np.asarray(amplitudes if amplitudes is not None else energies, dtype=float)
    if targets.ndim != 1 or not len(targets) or not np.all(np.isfinite(targets) & (targets > 0)):
        raise UsageError(f"the {kind} targets must be finite positive numbers, at least one")
    return targets


class _Walk:
    """Pseudo-arclength continuation along one branch, in scaled (q0 / scale, T / T0)."""

    def __init__(self, branch: _Branch, mode: int, measure: _Measure, lead: int, *,
                 start: float):
        """Start from the orbit of the linear mode's shape times `start`, at the mode's
        linear energy, headed up in energy."""
        self.branch, self.mode, self.measure, self.lead = branch, mode, measure, lead
        linear, N = branch.linear, branch.n
        shape, w = linear.shapes[:, mode - 1], linear.frequencies[mode - 1]
        period = 2 * math.pi / w
        self.units = np.append(np.full(N, branch.scale), period)
        self.step = _FIRST_STEP
        z = np.append(linear.equilibrium + start * shape, period)
        try:
            shot = _newton(branch, z, _Measure(branch, None).equal_to(0.5 * (w * start) ** 2))
        except _NoConvergence:
            raise ModelError(f"mode {mode}: no periodic orbit found near the linear mode at "
                             "small amplitude") from None
        self.previous = self.current = shot
        tangent = self._tangent(shot)
        if branch.energy(shot.z[:N])[1] @ (tangent * self.units) < 0:
            tangent = -tangent
        self.tangent = tangent
        self.angles = branch.angles(shot)
        self._check_resonance(shot, self.angles)

    def _tangent(self, shot: _Shot) -> Array:
        """The unit null vector of the scaled Jacobian of v(T/2)."""
        return scipy.linalg.null_space(shot.jacobian * self.units)[:, 0]

    def advance_past(self, value: float) -> None:
        """Step along the branch until the measure (energy or amplitude) reaches `value`."""
        steps = 0
        while self.measure(self.current)[0] < value:
            steps += 1
            if steps > _MOST_STEPS:
                raise self._stuck(f"the branch did not reach it in {_MOST_STEPS} steps", value)
            self._one_step(value)
    def _one_step(self, value: float) -> None:
        branch, units = self.branch, self.units
        base = self.current.z / units
        while True:
            if self.step < _SHORTEST_STEP:
                raise self._stuck("the continuation stalled", value)
            predicted = base + self.step * self.tangent
            tangent = self.tangent

            def arclength(shot: _Shot, predicted: Array = predicted,
                          tangent: Array = tangent) -> tuple[float, Array]:
                return float(tangent @ (shot.z / units - predicted)), tangent / units

            try:
                shot = _newton(branch, predicted * units, arclength, _CORRECTOR_TOL)
            except (_NoConvergence, ModelError, np.linalg.LinAlgError):
                self.step /= 2
                continue
            angles = branch.angles(shot)
            if len(angles) and np.abs(angles - self.angles).max() > RESONANCE_ANGLE / 2:
                self.step /= 2
                continue
            break
        new_tangent = self._tangent(shot)
        if new_tangent @ self.tangent < 0:
            new_tangent = -new_tangent
        self.previous, self.current, self.tangent, self.angles = (self.current, shot,
                                                                  new_tangent, angles)
        self._check_resonance(shot, angles)
        self.step = min(self.step * 1.5, _LONGEST_STEP)

    def solve_at(self, value: float) -> _Shot:
        """Newton's method on the target from the two points about it."""
        before, after = self.measure(self.previous)[0], self.measure(self.current)[0]
        if after == before or value <= before:
            z = self.current.z if value >= after else self.previous.z
        else:
            share = (value - before) / (after - before)
            z = self.previous.z + share * (self.current.z - self.previous.z)
        try:
            return _newton(self.branch, z, self.measure.equal_to(value))
        except _NoConvergence:
            raise self._stuck("Newton's method did not converge on it", value) from None

    def _reached(self) -> str:
        shot, branch = self.current, self.branch
        energy = branch.energy(shot.z[:branch.n])[0]
        amplitude = branch.amplitude(shot, self.lead)[0]
        coordinate = branch.model.coordinates[self.lead]
        return (f"energy {energy:.6g} (amplitude of {coordinate} {amplitude:.6g}, frequency "
                f"{2 * math.pi / shot.z[-1]:.6g} rad/s)")

    def _stuck(self, why: str, value: float) -> ModelError:
        kind = "energy" if self.measure.coordinate is None else "amplitude"
        return ModelError(f"mode {self.mode}, continued to {kind} {value:.6g}: {why}; reached "
                          f"{self._reached()}")

    def _check_resonance(self, shot: _Shot, angles: Array) -> None:
        if not len(angles) or angles.min() >= RESONANCE_ANGLE:
            return
        frequencies = self.branch.linear.frequencies
        w = 2 * math.pi / shot.z[-1]
        others = [j for j in range(len(frequencies)) if j != self.mode - 1]
        ratios = frequencies[others] / w
        nearest = int(np.argmin(np.abs(ratios - np.round(ratios))))
        n = max(int(round(ratios[nearest])), 1)
        raise InternalResonanceError(
            f"mode {self.mode}: internal resonance at {self._reached()}: a Floquet "
            f"multiplier reaches +1, near {n}:1 with mode {others[nearest] + 1} (linear "
            f"frequency {frequencies[others[nearest]]:.6g} rad/s); the branch is not "
            "followed past it")
