"""The backbone of one degree of freedom: period and equivalent damping ratio of the
conservative orbits of a potential well, by quadrature.

A natural energy E = m(q) v²/2 + V(q) (`Model.lagrangian`) at given parameter values has
V(q) = E(q, 0) and m(q) = 2 (E(q, 1) − E(q, 0)). Its well is found about a reference point
q_ref (0, or where the recording lives): V' is evaluated at q_ref ± s·10^k (k from −4 to 4,
a 1% step, s the well's scale) and the equilibrium q* is the root of V' nearest q_ref where
V' goes from negative to positive, solved by brentq to rounding. Walking out from q* the
same way, the first root of V' on each side where it turns negative is a barrier maximum;
the lower of the two is the well's rim (none when V grows on both sides as far as the walk
goes, 10^4 s).

At a level E between V(q*) and the rim, the turning points q1 < q* < q2 solve V = E
(brentq between grid points), the amplitude is A = (q2 − q1)/2 and

    T(E) = 2 ∫_{q1}^{q2} sqrt(m(q) / (2 (E − V(q)))) dq,

computed on each side of q* with q = q* + (q_turn − q*) sin φ, φ in [0, π/2]: the
inverse square root at the turning point cancels against cos φ, the integrand is smooth,
and Gauss–Legendre in φ, doubled until two rules agree to 1e-13, is exact to rounding. On
each side E − V(q) is taken as V(q_turn) − V(q), which stays positive to rounding.

The energy a Rayleigh dissipation R (`hamid.model.dissipation`) takes over one period of
the conservative orbit is ΔE = ∮ Σ v dR/dv dt = Σ over both directions of
∫ P(q, ±|v(q)|) / |v(q)| dq, |v| = sqrt(2 (E − V) / m), on the same nodes; the equivalent
damping ratio is ζ = ΔE / (4π (E − V(q*))), c / (2 ω) for a linear oscillator
R = c v²/2 of unit mass.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache

import numpy as np
import numpy.typing as npt

from hamid.errors import DataError, ModelError
from hamid.model.dissipation import Dissipation
from hamid.model.models import Model

__all__ = ["Cycle", "Fitted", "Orbit", "Rim", "Well"]

Array = npt.NDArray[np.float64]
# Offsets from a point, in units of the well's scale, where V' is looked at.
_STEPS = np.logspace(-4, 4, 1601)
_AGREEMENT = 1e-13     # two Gauss-Legendre rules agree this well: the integral is taken
_ROUNDING_FLOOR = 1e-10   # below this, rules that stop agreeing better meet rounding
_MOST_NODES = 4096
# nodes of the mean slope between a point and the turning point
_INNER_NODES, _INNER_WEIGHTS = np.polynomial.legendre.leggauss(24)


@cache
def _nodes(n: int) -> tuple[Array, Array]:
    """Gauss-Legendre nodes and weights on [0, pi/2], and cos of the nodes folded in
    (scipy's rule: numpy's takes the eigenvalues of an n x n matrix, 10 s at n = 1024)."""
    from scipy.special import roots_legendre

    x, w = roots_legendre(n)
    phi = (x + 1) * math.pi / 4
    return phi, w * math.pi / 4 * np.cos(phi)


@dataclass(frozen=True)
class Rim:
    """The lower barrier maximum of the well: its position and energy."""

    position: float
    energy: float


@dataclass(frozen=True)
class Orbit:
    """A conservative orbit of the well: its energy (the model's, as the report's levels)
    and turning points."""

    energy: float
    low: float
    high: float

    @property
    def amplitude(self) -> float:
        """Half the peak-to-peak range of the coordinate."""
        return (self.high - self.low) / 2


@dataclass(frozen=True, eq=False)
class Well:
    """The potential well of a model of one coordinate at given parameter values."""

    model: Model
    theta: Array
    scale: float
    bottom: float         # q*
    floor: float          # V(q*)
    rim: Rim | None
    reach: tuple[float, float]   # how far the walk from q* went on each side

    @classmethod
    def of(cls, model: Model, estimates: Mapping[str, float], *, near: float = 0.0,
           scale: float = 1.0) -> Well:
        """The well of `model` at `estimates` (name -> value) nearest `near`, looked for
        over `scale` (the amplitudes of interest)."""
        if len(model.coordinates) != 1:
            raise ModelError(f"model {model.name!r}: a well of one coordinate, not "
                             f"{len(model.coordinates)}")
        _ = model.lagrangian   # a natural energy, or a one-line ModelError
        theta = np.array([estimates[name] for name in model.parameters], dtype=float)
        probe = cls(model, theta, scale, bottom=near, floor=0.0, rim=None, reach=(near, near))
        offsets = np.concatenate([-_STEPS[::-1], _STEPS]) * scale
        points = near + offsets
        slope = probe.slope(points)
        rising = np.flatnonzero((slope[:-1] < 0) & (slope[1:] > 0))
        if not len(rising):
            raise ModelError(f"model {model.name!r}: no minimum of the potential energy "
                             f"within {_STEPS[-1] * scale:.3g} of "
                             f"{model.coordinates[0]} = {near:.6g}")
        i = rising[np.argmin(np.abs(points[rising] - near))]
        bottom = probe.root(probe.slope, points[i], points[i + 1])
        barriers, reach = [], []
        for sign in (1.0, -1.0):
            walk = bottom + sign * _STEPS * scale
            falling = np.flatnonzero(sign * probe.slope(walk) < 0)
            if len(falling):
                j = falling[0]
                top = probe.root(probe.slope, walk[j - 1] if j else bottom, walk[j])
                barriers.append(Rim(top, float(probe.potential(top)[0])))
                reach.append(top)
            else:
                reach.append(float(walk[-1]))
        rim = min(barriers, key=lambda b: b.energy) if barriers else None
        return cls(model, theta, scale, bottom=bottom, floor=float(probe.potential(bottom)[0]),
                   rim=rim, reach=(reach[1], reach[0]))

    def _energy(self, q: Array, v: float) -> Array:
        X = np.column_stack([np.atleast_1d(np.asarray(q, dtype=float)),
                             np.full(np.size(q), v)])
        return self.model.total_energy(X, self.theta)

    def potential(self, q: npt.ArrayLike) -> Array:
        """V(q) = E(q, 0)."""
        return self._energy(np.asarray(q), 0.0)

    def mass(self, q: npt.ArrayLike) -> Array:
        """m(q) = 2 (E(q, 1) - E(q, 0)), the kinetic energy being m v²/2."""
        return 2.0 * (self._energy(np.asarray(q), 1.0) - self._energy(np.asarray(q), 0.0))

    def slope(self, q: npt.ArrayLike) -> Array:
        """V'(q)."""
        q = np.atleast_1d(np.asarray(q, dtype=float))
        return self.model.energy_gradient(np.column_stack([q, np.zeros_like(q)]),
                                          self.theta)[:, 0]

    def root(self, f, a: float, b: float) -> float:  # type: ignore[no-untyped-def]
        """The root of the scalar function f between a and b, to rounding; a ModelError
        when f has the same sign at both: the potential's rounding there exceeds the
        differences sought."""
        from scipy.optimize import brentq

        try:
            return float(brentq(lambda q: float(f(q)[0]), a, b, xtol=1e-15 * self.scale,
                                rtol=4 * np.finfo(float).eps, maxiter=500))
        except ValueError:
            raise ModelError(
                f"model {self.model.name!r}: its potential energy is lost to rounding near "
                f"{self._place(a)} at this amplitude (its terms there are much larger than "
                "their differences over the orbit); record the coordinate from its rest "
                "position, or ask for larger amplitudes") from None

    def _place(self, q: float) -> str:
        return f"{self.model.coordinates[0]} = {q:.6g}"

    def _turning(self, energy: float, side: int) -> float:
        """The turning point at `energy` on the side (+1 right, -1 left) of q*."""
        end = self.reach[(side + 1) // 2]
        walk = self.bottom + side * _STEPS * self.scale
        walk = np.append(walk[side * (walk - end) < 0], end)
        above = np.flatnonzero(self.potential(walk) >= energy)
        if not len(above):
            raise DataError(f"energy {energy:.6g} reaches beyond {self._place(walk[-1])}, "
                            "as far as the well was searched")
        j = above[0]
        return self.root(lambda q: self.potential(q) - energy,
                         walk[j - 1] if j else self.bottom, walk[j])

    def orbit(self, energy: float) -> Orbit:
        """The orbit at a level of the model's energy; a level outside the well (at or below
        its bottom, at or above its rim) is a one-line error naming the bottom or rim."""
        if not energy > self.floor:
            raise DataError(f"energy {energy:.6g} is not above the well's bottom at "
                            f"{self.floor:.6g} ({self._place(self.bottom)})")
        if self.rim is not None and energy >= self.rim.energy:
            raise DataError(f"energy {energy:.6g} is above the well's rim at "
                            f"{self.rim.energy:.6g} ({self._place(self.rim.position)})")
        return Orbit(energy, self._turning(energy, -1), self._turning(energy, 1))

    def orbit_at(self, amplitude: float) -> Orbit:
        """The orbit of a given amplitude (half its peak-to-peak range)."""
        from scipy.optimize import brentq

        if not amplitude > 0:
            raise DataError(f"amplitude {amplitude:.6g} is not positive")
        if self.rim is not None:
            top = self.rim.energy
            edge = Orbit(top, self._turning(top, -1), self._turning(top, 1))
            if amplitude >= edge.amplitude:
                raise DataError(f"amplitude {amplitude:.6g} is above the well's rim at "
                                f"{self.rim.energy:.6g} ({self._place(self.rim.position)}),"
                                f" whose orbit has amplitude {edge.amplitude:.6g}")
        else:
            top = self.floor + float(np.max(self.potential(
                [self.bottom - amplitude, self.bottom + amplitude]))) - self.floor
            for _ in range(200):
                if self.orbit(top).amplitude > amplitude:
                    break
                top = self.floor + 2 * (top - self.floor)

        def excess(energy: float) -> float:
            if energy <= self.floor:
                return -amplitude
            if energy == top and self.rim is not None:
                return edge.amplitude - amplitude
            return self.orbit(energy).amplitude - amplitude

        energy = brentq(excess, self.floor, top, xtol=1e-15 * (top - self.floor),
                        rtol=4 * np.finfo(float).eps, maxiter=500)
        return self.orbit(float(energy))

    def _drop(self, turn: float, phi: Array) -> Array:
        """V(q_turn) − V(q) at q = q* + (q_turn − q*) sin φ, without the cancellation of
        the difference near the turning point: (q_turn − q) times the mean of V' over
        [q, q_turn] (Gauss–Legendre, `_INNER_NODES`), q_turn − q taken as
        (q_turn − q*) 2 sin²((π/2 − φ)/2)."""
        x, w = _INNER_NODES, _INNER_WEIGHTS
        span = (turn - self.bottom) * 2 * np.sin((math.pi / 2 - phi) / 2) ** 2
        points = turn - span[:, None] * (x[None, :] + 1) / 2
        mean = (self.slope(points.ravel()).reshape(points.shape) @ w) / 2
        return span * mean

    def cycle(self, orbit: Orbit, dissipation: Dissipation | None = None,
              coefficients: npt.ArrayLike = ()) -> Cycle:
        """The period of the orbit and the energy the dissipation (coefficients in the
        order of `Dissipation.names`) takes over it, from Gauss–Legendre rules in φ
        doubled until two agree to `_AGREEMENT`, or agree to `_ROUNDING_FLOOR` and no
        better than the two before them."""
        c = np.asarray(coefficients, dtype=float)
        damped = dissipation is not None and len(dissipation) > 0
        previous, change = None, math.inf
        n = 16
        while True:
            phi, weight = _nodes(n)
            period = lost = 0.0
            for turn in (orbit.low, orbit.high):
                width = abs(turn - self.bottom)
                q = self.bottom + (turn - self.bottom) * np.sin(phi)
                drop, m = self._drop(turn, phi), self.mass(q)
                speed = np.sqrt(2 * drop / m)
                period += 2 * width * float(np.sum(weight / speed))
                for direction in (1.0, -1.0) if damped else ():
                    power = dissipation.power_parts(np.column_stack([q, direction * speed])) @ c
                    lost += width * float(np.sum(weight * power / speed))
            current = (period, lost)
            # the rules agree, or have stopped agreeing better near rounding (a small orbit
            # about an equilibrium far from zero): more nodes would only add rounding
            last, change = change, (math.inf if previous is None else max(
                abs(a - b) / abs(a) if a else abs(b) for a, b in zip(current, previous,
                                                                     strict=True)))
            if (change <= _AGREEMENT or change < _ROUNDING_FLOOR and change > last / 2
                    or n >= _MOST_NODES):
                excess = float(self._drop(orbit.high, np.zeros(1))[0])
                return Cycle(period, lost if damped else None, excess)
            previous, n = current, 2 * n


@dataclass(frozen=True)
class Cycle:
    """One period of a conservative orbit: its length, the energy the dissipation takes
    over it (None without dissipation), and the orbit's energy above the well's bottom."""

    period: float
    lost: float | None
    excess: float

    @property
    def frequency(self) -> float:
        return 1.0 / self.period

    @property
    def damping_ratio(self) -> float | None:
        """ζ = ΔE / (4π (E − V(q*))): the equivalent viscous damping ratio."""
        return None if self.lost is None else self.lost / (4 * math.pi * self.excess)


@dataclass(frozen=True, eq=False)
class Fitted:
    """A fitted model of one coordinate: its energy and dissipation at the estimates (name
    -> value, the dissipation's coefficients among them), and where its well is looked for
    (`Well.of`'s `near` and `scale`)."""

    model: Model
    estimates: Mapping[str, float]
    dissipation: Dissipation | None = None
    near: float = 0.0
    scale: float = 1.0

    def well(self) -> Well:
        return Well.of(self.model, self.estimates, near=self.near, scale=self.scale)

    def cycle(self, well: Well, orbit: Orbit) -> Cycle:
        """The orbit's period and the energy the fitted dissipation takes over it."""
        names = self.dissipation.names if self.dissipation is not None else ()
        return well.cycle(orbit, self.dissipation, [self.estimates[n] for n in names])

    def at_amplitude(self, amplitude: float) -> Cycle:
        """The cycle of the orbit of this amplitude."""
        well = self.well()
        return self.cycle(well, well.orbit_at(amplitude))
