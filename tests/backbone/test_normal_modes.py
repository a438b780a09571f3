"""Nonlinear normal modes against independent truth: exact periods, hand-written shooting,
the linear eigenfrequencies."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from helpers import double_pendulum_rhs, two_dof_first_mode
from scipy.integrate import solve_ivp
from scipy.optimize import root
from scipy.special import ellipk

from hamid.backbone.normal_modes import InternalResonanceError, normal_mode_branch
from hamid.errors import ModelError, UsageError
from hamid.model.models import builtin_model, forcing_table, model_from_expression, model_from_spec

TWO = ("two", "(v1**2 + v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2 + k3*x1**4/4",
       ["x1", "x2"], ["v1", "v2"])
TWO_ESTIMATES = {"k1": 1.0, "k2": 1.0, "k3": 0.5}


def _duffing_period(k: float, k3: float, A: float) -> float:
    """The exact period of x'' + k x + k3 x^3 = 0 at amplitude A (Jacobi's cn)."""
    w2 = k + k3 * A ** 2
    return 4 * ellipk(k3 * A ** 2 / (2 * w2)) / math.sqrt(w2)


def test_duffing_period_against_the_elliptic_integral():
    # hardening and softening springs; amplitudes asked out of order come back in order
    for k3 in (0.5, -0.2):
        model = builtin_model("duffing")
        amplitudes = [1.0, 0.3, 1.6]
        orbits = normal_mode_branch(model, {"k": 1.0, "k3": k3}, mode=1, amplitudes=amplitudes)
        for A, orbit in zip(amplitudes, orbits, strict=True):
            assert orbit.period == pytest.approx(_duffing_period(1.0, k3, A), rel=1e-8)
            assert orbit.amplitudes[0] == pytest.approx(A, rel=1e-10)
            assert orbit.energy == pytest.approx(A ** 2 / 2 + k3 * A ** 4 / 4, rel=1e-10)


def test_duffing_by_energies():
    amplitudes = np.array([0.4, 1.2])
    energies = amplitudes ** 2 / 2 + 0.5 * amplitudes ** 4 / 4
    orbits = normal_mode_branch(builtin_model("duffing"), {"k": 1.0, "k3": 0.5}, mode=1,
                                energies=list(energies))
    for A, E, orbit in zip(amplitudes, energies, orbits, strict=True):
        assert orbit.energy == pytest.approx(E, rel=1e-12)
        assert orbit.amplitudes[0] == pytest.approx(A, rel=1e-10)
        assert orbit.period == pytest.approx(_duffing_period(1.0, 0.5, A), rel=1e-8)


def test_a_driven_model_orbits_freely():
    # the recorded input at zero: the free Duffing of mass m, x'' = -(k x + k3 x^3) / m
    model = forcing_table(model_from_spec(
        {"coordinates": ["x"], "velocities": ["v"], "energy": "m*v**2/2 + k*x**2/2 + k3*x**4/4",
         "parameters": ["m", "k", "k3"]}), {"inputs": ["F"], "work": "b*F*x",
                                             "parameters": ["b"]})
    orbit, = normal_mode_branch(model, {"m": 1.5, "k": 4.0, "k3": 2.0, "b": 3.0}, mode=1,
                                amplitudes=[0.7])
    assert orbit.period == pytest.approx(_duffing_period(4.0 / 1.5, 2.0 / 1.5, 0.7), rel=1e-8)


def test_equilibrium_away_from_the_origin():
    # V = k x^2/2 + g x has its minimum at -g/k; the orbits about it are the linear ones
    model = model_from_expression("shifted", "v**2/2 + k*x**2/2 + g*x", ["x"], ["v"])
    orbit, = normal_mode_branch(model, {"k": 4.0, "g": 2.0}, mode=1, amplitudes=[0.3],
                                samples=101)
    assert orbit.period == pytest.approx(math.pi, rel=1e-10)
    assert orbit.energy == pytest.approx(4.0 * 0.3 ** 2 / 2, rel=1e-10)
    assert orbit.states[0].max() == pytest.approx(-0.5 + 0.3, rel=1e-9)
    assert orbit.states[0].min() == pytest.approx(-0.5 - 0.3, rel=1e-9)


def test_two_dof_first_mode_against_independent_shooting():
    model = model_from_expression(*TWO)
    amplitudes = [0.3, 0.6, 1.0]
    orbits = normal_mode_branch(model, TWO_ESTIMATES, mode=1, amplitudes=amplitudes,
                                coordinate=0)
    expected = [w for w, _ in two_dof_first_mode(amplitudes, **TWO_ESTIMATES)]
    for A, w, orbit in zip(amplitudes, expected, orbits, strict=True):
        assert 2 * math.pi / orbit.period == pytest.approx(w, rel=1e-6)
        assert orbit.amplitudes[0] == pytest.approx(A, rel=1e-10)
    # hardening: the frequency grows with the amplitude
    assert expected[0] < expected[1] < expected[2]


def test_the_orbit_itself():
    model = model_from_expression(*TWO)
    orbit, = normal_mode_branch(model, TWO_ESTIMATES, mode=1, amplitudes=[0.8], samples=401)
    assert orbit.t.shape == (401,) and orbit.states.shape == (4, 401)
    assert orbit.t[0] == 0.0 and orbit.t[-1] == orbit.period
    # periodic, on one energy level, and its amplitudes half the sampled ranges
    assert np.abs(orbit.states[:, -1] - orbit.states[:, 0]).max() < 1e-9
    energy = model.total_energy(orbit.states.T, [1.0, 1.0, 0.5])
    assert np.abs(energy - orbit.energy).max() < 1e-10
    assert orbit.amplitudes == pytest.approx(np.ptp(orbit.states[:2], axis=1) / 2, rel=1e-4)
    # against the hand-written equations integrated from its start
    k1, k2, k3 = 1.0, 1.0, 0.5
    motion = solve_ivp(lambda t, y: [y[2], y[3], -k1 * y[0] + k2 * (y[1] - y[0]) - k3 * y[0] ** 3,
                                     -k2 * (y[1] - y[0])],
                       (0, orbit.period), orbit.states[:, 0], t_eval=orbit.t, method="DOP853",
                       rtol=1e-12, atol=1e-13)
    assert np.abs(motion.y - orbit.states).max() < 1e-8


def test_linear_limit_equals_the_eigenfrequencies():
    model = model_from_expression(*TWO)
    # K and M of the quadratic part, by hand
    K = np.array([[2.0, -1.0], [-1.0, 1.0]])
    w, shapes = scipy.linalg.eigh(K, np.eye(2))
    for mode in (1, 2):
        orbit, = normal_mode_branch(model, TWO_ESTIMATES, mode=mode, amplitudes=[1e-6])
        assert 2 * math.pi / orbit.period == pytest.approx(math.sqrt(w[mode - 1]), rel=1e-8)
        shape = shapes[:, mode - 1]
        assert orbit.amplitudes == pytest.approx(np.abs(shape) / np.abs(shape).max() * 1e-6,
                                                 rel=1e-6)


def test_second_mode_by_energy_hardens():
    model = model_from_expression(*TWO)
    orbits = normal_mode_branch(model, TWO_ESTIMATES, mode=2, energies=[0.05, 0.5])
    assert [o.energy for o in orbits] == pytest.approx([0.05, 0.5], rel=1e-12)
    frequencies = [2 * math.pi / o.period for o in orbits]
    assert math.sqrt((3 + math.sqrt(5)) / 2) < frequencies[0] < frequencies[1]
    # the second mode moves its coordinates against each other
    start = orbits[1].states[:2, 0]
    assert start[0] * start[1] < 0


def test_double_pendulum_a_mass_matrix_that_moves():
    # the kinetic energy's cross term turns with p - q, and -g cos puts V(q*) far from zero
    model = model_from_expression(
        "double", "wp**2 + wq**2/2 + wp*wq*cos(p - q) - g*(2*cos(p) + cos(q))",
        ["p", "q"], ["wp", "wq"])
    g, A = 9.81, 0.3
    tiny, orbit = normal_mode_branch(model, {"g": g}, mode=1, amplitudes=[1e-6, A],
                                     coordinate=0)
    # linear limit: M = [[2, 1], [1, 1]], K = g diag(2, 1), so w^2 = g (2 - sqrt 2)
    assert 2 * math.pi / tiny.period == pytest.approx(math.sqrt(g * (2 - math.sqrt(2))),
                                                      rel=1e-8)
    # x K x / 2 with x = 1e-6 (1, sqrt 2), the linear mode's shape: 2 g 1e-12, where
    # V(q) - V(q*) itself would keep no digit of it beside V(q*) = -3 g
    assert tiny.energy == pytest.approx(2 * g * 1e-12, rel=1e-6)
    # on the orbit: the energy above the equilibrium's, all along
    energy = model.total_energy(orbit.states.T, [g]) + 3 * g
    assert np.abs(energy - orbit.energy).max() < 1e-12 * 3 * g * 10

    def residual(u):
        b, T = u
        end = solve_ivp(double_pendulum_rhs(g), (0, T / 2), [A, b, 0, 0], method="DOP853",
                        rtol=1e-12, atol=1e-13).y[:, -1]
        return [end[0] + A, end[1] + b]

    b, T = root(residual, [A * math.sqrt(2), tiny.period], tol=1e-13).x
    assert orbit.period == pytest.approx(T, rel=1e-6)
    assert orbit.amplitudes == pytest.approx([A, b], rel=1e-6)


RESONANT = ("res", "(v1**2 + v2**2)/2 + x1**2/2 + w2sq*x2**2/2 + k3*x1**4/4 + c*x1**3*x2",
            ["x1", "x2"], ["v1", "v2"])


def test_internal_resonance_is_reported_where_it_is_met():
    # linear frequencies 1 and sqrt(9.5) = 3.08: the first mode hardens into 3:1
    model = model_from_expression(*RESONANT)
    estimates = {"w2sq": 9.5, "k3": 1.0, "c": 0.1}
    below, = normal_mode_branch(model, estimates, mode=1, amplitudes=[0.15])
    assert 3 * 2 * math.pi / below.period < math.sqrt(9.5)
    with pytest.raises(InternalResonanceError) as error:
        normal_mode_branch(model, estimates, mode=1, amplitudes=[1.0])
    message = str(error.value)
    assert "internal resonance at energy" in message and "3:1 with mode 2" in message
    assert "\n" not in message
    # the frequency it names is a third of the second mode's, to the band it watches
    named = float(message.split("frequency ")[1].split(" rad/s")[0])
    assert 3 * named == pytest.approx(math.sqrt(9.5), rel=0.01)
    amplitude = float(message.split("amplitude of x1 ")[1].split(",")[0])
    assert 0.15 < amplitude < 1.0


@pytest.mark.parametrize(("arguments", "words"), [
    ({"mode": 0, "amplitudes": [0.1]}, ["mode 0", "modes 1 to 2"]),
    ({"mode": 3, "amplitudes": [0.1]}, ["mode 3", "modes 1 to 2"]),
    ({"mode": 1, "amplitudes": [0.1], "energies": [0.1]}, ["either", "both"]),
    ({"mode": 1}, ["either", "neither"]),
    ({"mode": 1, "amplitudes": [0.1], "coordinate": 2}, ["coordinate 2", "0 to 1"]),
    ({"mode": 1, "amplitudes": [-0.1]}, ["amplitude", "positive"]),
    ({"mode": 1, "energies": []}, ["energy", "at least one"]),
    ({"mode": 1, "amplitudes": [0.1], "samples": 1}, ["samples 1"]),
])
def test_bad_input(arguments, words):
    model = model_from_expression(*TWO)
    with pytest.raises(UsageError) as error:
        normal_mode_branch(model, TWO_ESTIMATES, **arguments)
    for word in words:
        assert word in str(error.value)


def test_missing_estimate_and_no_well():
    model = model_from_expression(*TWO)
    with pytest.raises(UsageError, match="no estimate of 'k3'"):
        normal_mode_branch(model, {"k1": 1.0, "k2": 1.0}, mode=1, amplitudes=[0.1])
    with pytest.raises(ModelError, match="not a minimum of the potential"):
        normal_mode_branch(model, {"k1": -3.0, "k2": 1.0, "k3": 0.5}, mode=1,
                           amplitudes=[0.1])


def test_a_coordinate_that_does_not_move():
    # two uncoupled oscillators: mode 1 is x alone, and y cannot set its amplitude
    model = model_from_expression("apart", "(vx**2 + vy**2)/2 + a*x**2/2 + b*y**2/2",
                                  ["x", "y"], ["vx", "vy"])
    with pytest.raises(UsageError, match="does not move in linear mode 1"):
        normal_mode_branch(model, {"a": 1.0, "b": 4.0}, mode=1, amplitudes=[0.1],
                           coordinate=1)


def test_a_double_pendulum_hanging_far_from_zero():
    """The sample's double pendulum hangs at (pi, pi): its linear modes there against the
    eigenproblem written out (M = [[1, B], [B, J2]], K = diag(C1, C2)), and its smallest
    orbits, which the integrator once chased below the rounding of pi for tens of
    seconds, found at the linear frequency with the modal damping ratio."""
    from hamid.backbone.normal_modes import ModeFitted, small_amplitude
    from hamid.model.models import load_model

    model = load_model(Path(__file__).parents[2] / "sample_data" / "double_pendulum.toml")
    e = {"J2": 0.5568, "B": 0.4913, "C1": 58.96, "C2": 27.90, "k1": 0.042, "k2": 0.0018}
    w2, shapes = scipy.linalg.eigh(np.diag([e["C1"], e["C2"]]),
                                   np.array([[1.0, e["B"]], [e["B"], e["J2"]]]))
    C = np.array([[e["k1"] + e["k2"], -e["k2"]], [-e["k2"], e["k2"]]])
    limit = small_amplitude(model, e, model.dissipation, near=(3.0, 3.3))
    assert limit.equilibrium == pytest.approx([math.pi, math.pi], abs=1e-12)
    for mode, w, shape in zip(limit.modes, np.sqrt(w2), shapes.T, strict=True):
        assert mode.frequency == pytest.approx(w, rel=1e-12)
        assert mode.damping_ratio == pytest.approx(shape @ C @ shape / (2 * w), rel=1e-10)
    fitted = ModeFitted(model, e, model.dissipation, 1, None, (3.0, 3.3))
    (cycle, orbit), = fitted.orbits(energies=[1e-5])
    assert cycle.frequency == pytest.approx(np.sqrt(w2[0]) / (2 * math.pi), rel=1e-6)
    assert cycle.damping_ratio == pytest.approx(limit.modes[0].damping_ratio, rel=1e-5)


def test_nudged_orbits_corrected_from_their_neighbours_equal_a_new_continuation():
    """The bands' nudged models: each orbit corrected by Newton from the estimates' orbit
    at the same amplitude is the orbit a continuation of the nudged model finds."""
    from dataclasses import replace

    from hamid.backbone.normal_modes import ModeFitted

    model = model_from_expression(*TWO)
    dissipation = model.dissipative(["viscous"])
    estimates = {**TWO_ESTIMATES, "c_x1": 0.02, "c_x2": 0.01}
    fitted = ModeFitted(model, estimates, dissipation, 1, 0)
    orbits = [orbit for _, orbit in fitted.orbits(amplitudes=[0.3, 1.0])]
    nudged = replace(fitted, estimates={**estimates, "k3": 0.5 * (1 + 1e-3)})
    corrected = nudged.corrected(orbits)
    continued = [cycle for cycle, _ in nudged.orbits(amplitudes=[0.3, 1.0])]
    for a, b in zip(corrected, continued, strict=True):
        assert a.frequency == pytest.approx(b.frequency, rel=1e-10)
        assert a.damping_ratio == pytest.approx(b.damping_ratio, rel=1e-8)
        assert a.excess == pytest.approx(b.excess, rel=1e-8)


def test_default_levels_end_short_of_an_internal_resonance():
    """The backbone report's default levels (up to the highest fitted level) meet the 3:1
    resonance: the curve ends at the last level before it, and says why; levels asked for
    past it are refused in one line."""
    from hamid.backbone import backbone_table
    from hamid.backbone.one_degree import Fitted

    model = model_from_expression(*RESONANT)
    estimates = {"w2sq": 9.5, "k3": 1.0, "c": 0.1}
    source = backbone_table.Source(Fitted(model, estimates), None, 0.95, (0.06,),
                                   {"x1": None, "x2": None}, "s")
    document = backbone_table.backbone_report(source, backbone_table.Request(points=10))
    (mode,) = document["modes"]
    assert mode["stopped"].startswith("mode 1: internal resonance at energy ")
    reached = float(mode["stopped"].split("energy ")[1].split(" ")[0])
    defaults = np.linspace(0.02 * 0.06, 0.06, 10)
    energies = [p["energy"] for p in mode["points"]]
    assert energies == pytest.approx(defaults[defaults < reached], rel=1e-9)
    assert len(energies) >= 2 and max(energies) < reached
    assert "the default levels end short of mode 1: internal resonance" in \
        backbone_table.render(document, "table")
    with pytest.raises(InternalResonanceError):
        backbone_table.backbone_report(source, backbone_table.Request(energies=(0.06,)))
