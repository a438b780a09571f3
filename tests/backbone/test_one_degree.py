"""The backbone of one coordinate (hamid/backbone/one_degree.py) against independent truth:
the elliptic-integral period of Duffing's oscillator, the dissipated energy by
scipy.integrate.quad, solve_ivp's period of an asymmetric well, the linear limit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp
from scipy.special import ellipk

from hamid.backbone.one_degree import Fitted, Well
from hamid.errors import DataError, ModelError
from hamid.model.models import builtin_model, model_from_expression

DUFFING = builtin_model("duffing")
VISCOUS = DUFFING.dissipative(["viscous"])


def _duffing_period(k: float, k3: float, amplitude: float) -> float:
    """x'' + k x + k3 x³ = 0 from rest at x = A: with x = A cn(ω t, m), ω² = k + k3 A² and
    m = k3 A² / (2 ω²), the period is 4 K(m) / ω (K(m) of negative m for a soft spring)."""
    omega2 = k + k3 * amplitude**2
    return 4 * ellipk(k3 * amplitude**2 / (2 * omega2)) / math.sqrt(omega2)


@pytest.mark.parametrize(("k", "k3", "amplitudes"), [
    (1.0, 0.5, (0.01, 0.3, 1.0, 2.5, 10.0)),       # hardening
    (2.0, -0.3, (0.01, 0.5, 1.5, 2.4)),            # softening, rim at x = ±2.58
])
def test_duffing_frequency_is_the_elliptic_integral_backbone(k, k3, amplitudes):
    well = Well.of(DUFFING, {"k": k, "k3": k3})
    for amplitude in amplitudes:
        orbit = well.orbit_at(amplitude)
        assert orbit.amplitude == pytest.approx(amplitude, rel=1e-12)
        assert orbit.energy == pytest.approx(k * amplitude**2 / 2 + k3 * amplitude**4 / 4,
                                             rel=1e-12)
        period = well.cycle(orbit).period
        assert period == pytest.approx(_duffing_period(k, k3, amplitude), rel=1e-8)


def test_a_level_given_as_an_energy_has_the_orbit_of_that_energy():
    well = Well.of(DUFFING, {"k": 1.0, "k3": 0.5})
    orbit = well.orbit(0.979200)   # A = 1.2: 1.44/2 + 0.5 * 2.0736 / 4
    assert orbit.low == pytest.approx(-1.2, rel=1e-12)
    assert orbit.high == pytest.approx(1.2, rel=1e-12)


@pytest.mark.parametrize(("k", "k3", "c", "amplitude"), [
    (1.0, 0.5, 0.05, 1.0), (1.0, 0.5, 0.05, 3.0), (2.0, -0.3, 0.1, 2.0)])
def test_viscous_damping_ratio_is_the_dissipated_energy_by_quadrature(k, k3, c, amplitude):
    fitted = Fitted(DUFFING, {"k": k, "k3": k3, "c_x": c}, VISCOUS)
    cycle = fitted.at_amplitude(amplitude)
    energy = k * amplitude**2 / 2 + k3 * amplitude**4 / 4

    def speed(x: float) -> float:
        return math.sqrt(max(2 * (energy - k * x**2 / 2 - k3 * x**4 / 4), 0.0))

    # ∮ c v² dt = 2 ∫_{-A}^{A} c |v| dx over the two halves of the orbit
    lost = 2 * c * quad(speed, -amplitude, amplitude, epsabs=0, epsrel=1e-13, limit=200)[0]
    assert cycle.lost == pytest.approx(lost, rel=1e-10)
    assert cycle.damping_ratio == pytest.approx(lost / (4 * math.pi * energy), rel=1e-6)


def test_coulomb_friction_takes_four_mu_a_per_cycle():
    """R = mu |v|: the force mu opposes the motion over a path of 4 A per cycle."""
    dissipation = DUFFING.dissipative(["coulomb"])
    cycle = Fitted(DUFFING, {"k": 1.0, "k3": 0.5, "mu_x": 0.02}, dissipation) \
        .at_amplitude(0.7)
    assert cycle.lost == pytest.approx(4 * 0.02 * 0.7, rel=1e-12)


def test_an_asymmetric_well_has_the_period_solve_ivp_finds():
    """V = x²/2 + a x³/3 (rim at x = −1/a): the time between successive up-crossings of
    the equilibrium of solve_ivp's motion from the right turning point."""
    model = model_from_expression("asym", "v**2/2 + x**2/2 + a*x**3/3", ["x"], ["v"], ["a"])
    a = 0.4
    well = Well.of(model, {"a": a})
    assert well.rim.position == pytest.approx(-1 / a, rel=1e-12)
    assert well.rim.energy == pytest.approx(1 / (6 * a**2), rel=1e-12)
    for amplitude in (0.3, 0.8, 1.4):
        orbit = well.orbit_at(amplitude)
        assert -orbit.low > amplitude > orbit.high   # the soft side (x < 0) reaches further

        def crossing(t, y):
            return y[0]

        crossing.direction = 1.0
        motion = solve_ivp(lambda t, y: [y[1], -y[0] - a * y[0] ** 2], (0, 40),
                           [orbit.high, 0.0], method="DOP853", rtol=1e-11, atol=1e-13,
                           events=crossing)
        up = motion.t_events[0]
        period = np.mean(np.diff(up))
        assert well.cycle(orbit).period == pytest.approx(period, rel=1e-7)


def test_the_linear_limit_is_the_undamped_frequency_and_c_over_2_sqrt_km():
    model = model_from_expression("mass", "m*v**2/2 + k*x**2/2", ["x"], ["v"], ["m", "k"])
    dissipation = model.dissipative(["viscous"])
    m, k, c = 2.5, 40.0, 0.3
    cycle = Fitted(model, {"m": m, "k": k, "c_x": c}, dissipation).at_amplitude(1e-3)
    assert cycle.frequency == pytest.approx(math.sqrt(k / m) / (2 * math.pi), rel=1e-12)
    assert cycle.damping_ratio == pytest.approx(c / (2 * math.sqrt(k * m)), rel=1e-10)


def test_the_well_is_the_minimum_nearest_the_reference_point():
    """A pendulum V = -K cos(θ): its wells at 0 and ±2π; the one nearest `near`."""
    model = model_from_expression("pendulum", "w**2/2 - K*cos(theta)", ["theta"], ["w"],
                                  ["K"])
    assert Well.of(model, {"K": 9.0}).bottom == pytest.approx(0.0, abs=1e-12)
    well = Well.of(model, {"K": 9.0}, near=5.9)
    assert well.bottom == pytest.approx(2 * math.pi, rel=1e-13)
    assert well.rim.energy == pytest.approx(9.0, rel=1e-12)
    # the small-amplitude frequency of the pendulum: sqrt(K)/(2π)
    assert 1 / well.cycle(well.orbit_at(1e-4)).period == pytest.approx(
        3 / (2 * math.pi), rel=1e-8)


def test_a_level_above_the_rim_is_an_error_naming_the_rim():
    well = Well.of(DUFFING, {"k": 1.0, "k3": -1.0})   # V = x²/2 - x⁴/4, rim 0.25 at x = ±1
    with pytest.raises(DataError) as error:
        well.orbit(0.8)
    assert str(error.value).startswith("energy 0.8 is above the well's rim at 0.25 (x = ")
    assert "\n" not in str(error.value)
    with pytest.raises(DataError, match=r"amplitude 1\.5 is above the well's rim at 0\.25"):
        well.orbit_at(1.5)
    with pytest.raises(DataError, match="not above the well's bottom at 0"):
        well.orbit(-0.1)


def _far_well(shift: int) -> Well:
    """Duffing's well (k = 1, k3 = 0.5) about x = shift: its terms, expanded in powers of
    x, are far larger there than the energies of a small orbit."""
    model = model_from_expression("far", f"v**2/2 + k*(x - {shift})**2/2 "
                                  f"+ k3*(x - {shift})**4/4", ["x"], ["v"], ["k", "k3"])
    return Well.of(model, {"k": 1.0, "k3": 0.5}, near=float(shift))


def test_rules_stop_doubling_where_rounding_stops_them_agreeing(monkeypatch):
    """A small orbit far from zero: the rules agree to 1e-11, not to 1e-13, and went on
    doubling to 4,096 nodes (the Silverbox's backbone took 54 s); they stop once they no
    longer agree better, the period still the elliptic integral's."""
    from hamid.backbone import one_degree

    rules: list[int] = []
    nodes = one_degree._nodes
    monkeypatch.setattr(one_degree, "_nodes", lambda n: rules.append(n) or nodes(n))
    well = _far_well(50)
    period = well.cycle(well.orbit_at(1e-3)).period
    assert period == pytest.approx(_duffing_period(1.0, 0.5, 1e-3), rel=1e-8)
    assert max(rules) <= 1024


def test_a_potential_lost_to_rounding_is_a_model_error():
    """About x = 1000 the quartic's terms are 1e11 and the orbit's energy 5e-7: brentq's
    "f(a) and f(b) must have different signs" escaped."""
    well = _far_well(1000)
    with pytest.raises(ModelError, match=r"potential energy is lost to rounding near "
                                         r"x = 1000.*record the coordinate from its rest"):
        well.orbit_at(1e-3)
