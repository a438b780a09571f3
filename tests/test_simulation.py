"""Tests for hamid.simulation through `hamid.simulate`.

Every expected trajectory comes from outside the code under test: closed forms (harmonic,
damped harmonic, Coulomb friction, Duffing via Jacobi elliptic functions) or equations of
motion written by hand below and integrated here with scipy at tighter tolerances.
"""

from __future__ import annotations

import copy
import re

import numpy as np
import pandas as pd
import pytest
from helpers import double_pendulum_rhs
from scipy.integrate import cumulative_simpson, quad, solve_ivp
from scipy.special import ellipj

import hamid
from hamid.errors import ModelError
from hamid.simulation import simulate

TOL = 1e-8  # agreement of simulated trajectories with the truth
DRIFT = 1e-9  # relative energy (or energy balance) drift

HARMONIC = {"coordinates": ["x"], "velocities": ["v"], "energy": "v**2/2 + k*x**2/2"}
DUFFING = {"builtin": "duffing"}
TWO_MASSES = {
    "coordinates": ["x1", "x2"],
    "velocities": ["v1", "v2"],
    "energy": "(v1**2 + m*v2**2)/2 + k1*x1**2/2 + k2*(x2-x1)**2/2 + k3*(x2-x1)**4/4",
}
ELASTIC_PENDULUM = {
    "coordinates": ["x", "y"],
    "velocities": ["vx", "vy"],
    "energy": "(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y",
}
PENDULUM = {"coordinates": ["th"], "velocities": ["w"], "energy": "w**2/2 - K*cos(th)"}
# Position-dependent mass matrices: plane polar coordinates, and the double pendulum (unit
# masses and lengths), whose mass matrix is full.
POLAR = {"coordinates": ["r", "th"], "velocities": ["vr", "w"],
         "energy": "(vr**2 + r**2*w**2)/2 + k*r**2/2 + a*r**4/4"}
DOUBLE_PENDULUM = {"coordinates": ["p", "q"], "velocities": ["wp", "wq"],
                   "energy": "wp**2 + wq**2/2 + wp*wq*cos(p - q) - g*(2*cos(p) + cos(q))"}
PENG = {"w1sq": 1.0, "w2sq": 2.25, "a1": 0.3, "a2": -0.4, "a3": 0.25, "a6": 0.2}
HENON = {"a": 1.0, "b": 1.0, "c": 1.0, "d": -1 / 3}


def make_system(model, parameters, initial, *, t_end=10.0, dt=0.1, **tables):
    """A system dict as `hamid simulate` reads it from TOML."""
    return {"model": dict(model), "parameters": dict(parameters),
            "initial": [dict(s) for s in initial],
            "simulate": {"t_end": t_end, "dt": dt}, **tables}


def columns(frame, j, names):
    """Time and the named columns of trajectory j."""
    part = frame[frame["trajectory"] == j]
    return part["t"].to_numpy(), part[list(names)].to_numpy()


def reference(rhs, y0, t):
    """Hand-written equations of motion integrated at tight tolerances."""
    solution = solve_ivp(rhs, (t[0], t[-1]), y0, method="DOP853", t_eval=t,
                         rtol=1e-12, atol=1e-13)
    assert solution.success, solution.message
    return solution.y.T


def assert_matches_reference(frame, names, initial, rhs):
    """Every trajectory of the frame equals the reference integration of `rhs`."""
    for j, state in enumerate(initial, start=1):
        t, Y = columns(frame, j, names)
        expected = reference(rhs, [state[v] for v in names], t)
        np.testing.assert_allclose(Y, expected, rtol=0, atol=TOL, err_msg=f"trajectory {j}")


# --- Exact solutions -------------------------------------------------------------------


@pytest.mark.parametrize("model, parameters", [
    pytest.param(HARMONIC, {"k": 2.0}, id="expression"),
    pytest.param(DUFFING, {"k": 2.0, "k3": 0.0}, id="duffing-k3=0"),
])
def test_harmonic_oscillator_matches_closed_form(model, parameters):
    initial = [{"x": 1.0, "v": 0.0}, {"x": 0.3, "v": -0.5}, {"x": 0.0, "v": 2.0}]
    frame = simulate(make_system(model, parameters, initial, t_end=20.0, dt=0.05))
    w = np.sqrt(2.0)
    for j, s in enumerate(initial, start=1):
        t, Y = columns(frame, j, ["x", "v"])
        x, v = Y.T
        x_true = s["x"] * np.cos(w * t) + s["v"] / w * np.sin(w * t)
        v_true = -s["x"] * w * np.sin(w * t) + s["v"] * np.cos(w * t)
        np.testing.assert_allclose(x, x_true, rtol=0, atol=TOL)
        np.testing.assert_allclose(v, v_true, rtol=0, atol=TOL)


def duffing_hardening(t, k, k3, A):
    """x'' + k x + k3 x^3 = 0 from x = A, v = 0: x = A cn(w t | m)."""
    w = np.sqrt(k + k3 * A**2)
    m = k3 * A**2 / (2 * w**2)
    assert 0 <= m < 1
    sn, cn, dn, _ = ellipj(w * t, m)
    return {"x": A, "v": 0.0}, A * cn, -A * w * sn * dn


def duffing_softening(t, k, k3, A):
    """k3 < 0, from x = 0 with amplitude A: x = A sn(w t | m), m = -k3 A^2 / (2 w^2)."""
    w = np.sqrt(k + k3 * A**2 / 2)
    m = -k3 * A**2 / (2 * w**2)
    assert 0 < m < 1
    sn, cn, dn, _ = ellipj(w * t, m)
    return {"x": 0.0, "v": A * w}, A * sn, A * w * cn * dn


@pytest.mark.parametrize("solution, k, k3, A", [
    pytest.param(duffing_hardening, 1.0, 0.5, 1.5, id="hardening-large"),
    pytest.param(duffing_hardening, 0.7, 2.0, 0.4, id="hardening-small"),
    pytest.param(duffing_softening, 1.0, -0.5, 1.0, id="softening"),
    pytest.param(duffing_softening, 2.0, -1.0, 1.2, id="softening-near-separatrix"),
])
def test_undamped_duffing_matches_jacobi_elliptic_solution(solution, k, k3, A):
    t = np.arange(0, 201) * 0.1
    initial, x_true, v_true = solution(t, k, k3, A)
    frame = simulate(make_system(DUFFING, {"k": k, "k3": k3}, [initial], t_end=20.0, dt=0.1))
    t_out, Y = columns(frame, 1, ["x", "v"])
    np.testing.assert_allclose(t_out, t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Y[:, 0], x_true, rtol=0, atol=TOL)
    np.testing.assert_allclose(Y[:, 1], v_true, rtol=0, atol=TOL)


# --- Hand-written equations of motion ---------------------------------------------------


def two_masses_rhs(m, k1, k2, k3, c2=0.0):
    def rhs(t, y):
        x1, x2, v1, v2 = y
        d = x2 - x1
        spring = k2 * d + k3 * d**3
        return [v1, v2, -k1 * x1 + spring, (-spring - c2 * v2) / m]
    return rhs


def elastic_pendulum_rhs(k, kL, g):
    def rhs(t, y):
        x, y_, vx, vy = y
        r = np.hypot(x, y_)
        return [vx, vy, -k * x + kL * x / r, -k * y_ + kL * y_ / r - g]
    return rhs


def pendulum_rhs(K):
    return lambda t, y: [y[1], -K * np.sin(y[0])]


def polar_rhs(k, a, c):
    """Viscous damping on r only: r'' = r w^2 - k r - a r^3 - c r', d(r^2 w)/dt = 0."""
    def rhs(t, y):
        r, th, vr, w = y
        return [vr, w, r * w**2 - k * r - a * r**3 - c * vr, -2 * vr * w / r]
    return rhs


EQUATIONS_OF_MOTION = [
    pytest.param(TWO_MASSES, {"m": 2.5, "k1": 1.0, "k2": 3.0, "k3": 0.8}, {},
                 [{"x1": 0.4, "x2": -0.3, "v1": 0.0, "v2": 0.2},
                  {"x1": -0.1, "x2": 0.6, "v1": 0.5, "v2": 0.0}],
                 two_masses_rhs(2.5, 1.0, 3.0, 0.8), id="unequal-masses"),
    pytest.param(TWO_MASSES, {"m": 0.4, "k1": 2.0, "k2": 1.0, "k3": 1.5}, {"c_x2": 0.3},
                 [{"x1": 0.5, "x2": 0.1, "v1": 0.0, "v2": -0.4}],
                 two_masses_rhs(0.4, 2.0, 1.0, 1.5, c2=0.3), id="unequal-masses-damped"),
    pytest.param(ELASTIC_PENDULUM, {"k": 4.0, "kL": 2.0, "g": 1.0}, {},
                 [{"x": 0.3, "y": -0.8, "vx": 0.0, "vy": 0.1},
                  {"x": -0.5, "y": -0.5, "vx": 0.4, "vy": -0.2}],
                 elastic_pendulum_rhs(4.0, 2.0, 1.0), id="elastic-pendulum"),
    pytest.param(PENDULUM, {"K": 9.81}, {},
                 [{"th": 1.0, "w": 0.0}, {"th": 0.2, "w": 6.5}, {"th": -2.5, "w": 0.0}],
                 pendulum_rhs(9.81), id="pendulum"),
    pytest.param(POLAR, {"k": 1.0, "a": 0.3}, {"c_r": 0.05},
                 [{"r": 1.0, "th": 0.0, "vr": 0.0, "w": 0.7},
                  {"r": 0.5, "th": 1.0, "vr": 0.4, "w": -1.5}],
                 polar_rhs(1.0, 0.3, c=0.05), id="polar-damped"),
    pytest.param(DOUBLE_PENDULUM, {"g": 9.81}, {},
                 [{"p": 0.5, "q": -0.3, "wp": 0.0, "wq": 0.0},
                  {"p": -0.2, "q": 0.4, "wp": 1.0, "wq": -0.5}],
                 double_pendulum_rhs(9.81), id="double-pendulum"),
]


@pytest.mark.parametrize("model, parameters, damping, initial, rhs", EQUATIONS_OF_MOTION)
def test_matches_hand_written_equations_of_motion(model, parameters, damping, initial, rhs):
    tables = {"damping": damping} if damping else {}
    frame = simulate(make_system(model, parameters, initial, t_end=6.0, **tables))
    assert_matches_reference(frame, model["coordinates"] + model["velocities"], initial, rhs)


# --- Sampling and layout ----------------------------------------------------------------


@pytest.mark.parametrize("t_end, dt, n, last", [
    (1.0, 0.1, 11, 1.0),
    (1.05, 0.1, 11, 1.0),
    (1.08, 0.1, 11, 1.0),
    (0.29, 0.1, 3, 0.2),
    (0.3, 0.1, 4, 0.3),
    (0.7, 0.1, 8, 0.7),
    (2.0, 0.25, 9, 2.0),
    (2.1, 0.25, 9, 2.0),
    (20.0, 0.01, 2001, 20.0),
])
def test_sample_times_are_multiples_of_dt_up_to_t_end(t_end, dt, n, last):
    initial = [{"x": 0.0, "y": 0.1, "vx": 0.35, "vy": 0.2},
               {"x": 0.2, "y": -0.1, "vx": 0.3, "vy": 0.3}]
    frame = simulate(make_system({"builtin": "henon-heiles"}, HENON, initial,
                                 t_end=t_end, dt=dt))
    assert list(frame.columns) == ["trajectory", "t", "x", "y", "vx", "vy"]
    assert frame["trajectory"].tolist() == [1] * n + [2] * n
    for j in (1, 2):
        t = frame.loc[frame["trajectory"] == j, "t"].to_numpy()
        assert len(t) == n
        np.testing.assert_allclose(t, np.arange(n) * dt, rtol=0, atol=1e-12)
        assert abs(t[-1] - last) < 1e-12
        assert t[0] == 0.0
    first = frame.groupby("trajectory").head(1)[["x", "y", "vx", "vy"]].to_numpy()
    np.testing.assert_array_equal(first, [[s[v] for v in ("x", "y", "vx", "vy")]
                                          for s in initial])


def test_columns_follow_model_order_and_labels_count_from_one():
    initial = [{"v2": 0.0, "x1": 0.1 * j, "v1": 0.0, "x2": 0.0} for j in range(1, 5)]
    parameters = {"m": 1.0, "k1": 1.0, "k2": 1.0, "k3": 0.0}
    frame = simulate(make_system(TWO_MASSES, parameters, initial, t_end=0.5))
    assert list(frame.columns) == ["trajectory", "t", "x1", "x2", "v1", "v2"]
    assert frame["trajectory"].unique().tolist() == [1, 2, 3, 4]
    np.testing.assert_array_equal(frame.groupby("trajectory")["x1"].first().to_numpy(),
                                  [0.1, 0.2, 0.30000000000000004, 0.4])


@pytest.fixture(scope="module")
def loose_dop853():
    return simulate(loose_harmonic("dop853"))


def loose_harmonic(method):
    system = make_system(HARMONIC, {"k": 2.0}, [{"x": 1.0, "v": 0.0}])
    system["simulate"].update(method=method, rtol=1e-6, atol=1e-8)
    return system


@pytest.mark.parametrize("method", ["dop853", "RK45", "rk23", "radau", "bdf", "lsoda"])
def test_integrator_settings_are_used(method, loose_dop853):
    frame = simulate(loose_harmonic(method))
    t, Y = columns(frame, 1, ["x", "v"])
    error = np.max(np.abs(Y[:, 0] - np.cos(np.sqrt(2.0) * t)))
    # accurate to the loose tolerance asked for, and not to the tight default
    assert 1e-9 < error < 1e-4
    assert frame.attrs["hamid"]["integrator"] == {"method": method.lower(), "rtol": 1e-6,
                                                  "atol": 1e-8}
    if method != "dop853":
        assert not np.array_equal(frame["x"], loose_dop853["x"])


def test_shorter_than_one_step_is_an_error():
    system = make_system(DUFFING, {"k": 1.0, "k3": 0.0}, [{"x": 1.0, "v": 0.0}],
                         t_end=0.05, dt=0.1)
    with pytest.raises(ModelError, match=r"t_end .* shorter than dt"):
        simulate(system)


# --- Energy conservation ----------------------------------------------------------------


def peng_energy(u1, u2, v1, v2, p=PENG):
    return ((v1**2 + v2**2) / 2 + p["w1sq"] * u1**2 / 2 + p["w2sq"] * u2**2 / 2
            - p["a1"] * u1**3 / 3 - p["a2"] * u1**2 * u2 / 2 - p["a3"] * u1 * u2**2
            - p["a6"] * u2**3 / 3)


def henon_energy(x, y, vx, vy):
    return (vx**2 + vy**2) / 2 + (x**2 + y**2) / 2 + x**2 * y - y**3 / 3


@pytest.mark.parametrize("builtin, parameters, initial, energy", [
    pytest.param("peng-quadratic", PENG,
                 [{"u1": 0.3, "u2": -0.2, "v1": 0.1, "v2": 0.2},
                  {"u1": 0.1, "u2": 0.15, "v1": -0.2, "v2": 0.0}], peng_energy, id="peng"),
    pytest.param("henon-heiles", HENON,
                 [{"x": 0.0, "y": 0.1, "vx": 0.35, "vy": 0.2},
                  {"x": 0.2, "y": -0.1, "vx": 0.3, "vy": 0.3}], henon_energy, id="henon"),
])
def test_builtin_energy_drift_is_at_integrator_tolerance(builtin, parameters, initial, energy):
    frame = simulate(make_system({"builtin": builtin}, parameters, initial, t_end=30.0,
                                 dt=0.05))
    info = frame.attrs["hamid"]
    model = info["model"]
    for j, state in enumerate(initial, start=1):
        E0 = energy(*(state[v] for v in model["coordinates"] + model["velocities"]))
        if builtin == "henon-heiles":
            assert 0 < E0 < 1 / 6  # bounded motion
        record = info["trajectories"][j - 1]
        assert record["trajectory"] == j
        assert record["energy"] == pytest.approx(E0, rel=1e-12)
        assert record["energy_drift"] < DRIFT
        assert record["energy_dissipated"] == 0.0
        _, Y = columns(frame, j, model["coordinates"] + model["velocities"])
        E = energy(*Y.T)
        assert np.max(np.abs(E - E0)) / abs(E0) < DRIFT
        assert np.ptp(Y[:, 0]) > 0.1  # the record really oscillates


# --- Damping ----------------------------------------------------------------------------


def viscous_closed_form(t, k, c, x0, v0):
    """x'' + c x' + k x = 0, underdamped."""
    w = np.sqrt(k)
    zeta = c / (2 * w)
    wd = w * np.sqrt(1 - zeta**2)
    decay = np.exp(-zeta * w * t)
    x = decay * (x0 * np.cos(wd * t) + (v0 + zeta * w * x0) / wd * np.sin(wd * t))
    v = decay * (v0 * np.cos(wd * t) - (w**2 * x0 + zeta * w * v0) / wd * np.sin(wd * t))
    return x, v


def coulomb_closed_form(t, k, mu, A):
    """x'' + k x + mu sign(x') = 0 from x = A > 0, v = 0, before the mass sticks.

    Half-cycle n (w t in [n pi, (n+1) pi]) oscillates about (-1)^n mu/k with amplitude
    A - (2n + 1) mu/k.
    """
    w = np.sqrt(k)
    shift = mu / k
    n = np.floor(w * t / np.pi)
    assert A - (2 * n.max() + 1) * shift > 0, "the mass would stick"
    sign = (-1.0) ** n
    amplitude = A - (2 * n + 1) * shift
    s = w * t - n * np.pi
    return sign * (amplitude * np.cos(s) + shift), -sign * amplitude * w * np.sin(s)


def test_viscous_damping_matches_closed_form():
    k, c = 4.0, 0.4
    initial = [{"x": 1.0, "v": 0.5}, {"x": -0.2, "v": 0.0}]
    frame = simulate(make_system(DUFFING, {"k": k, "k3": 0.0}, initial, t_end=15.0, dt=0.05,
                                 damping={"c_x": c}))
    for j, s in enumerate(initial, start=1):
        t, Y = columns(frame, j, ["x", "v"])
        x, v = viscous_closed_form(t, k, c, s["x"], s["v"])
        np.testing.assert_allclose(Y[:, 0], x, rtol=0, atol=TOL)
        np.testing.assert_allclose(Y[:, 1], v, rtol=0, atol=TOL)


def test_coulomb_friction_matches_closed_form():
    k, mu, A = 2.0, 0.1, 1.0
    frame = simulate(make_system(DUFFING, {"k": k, "k3": 0.0}, [{"x": A, "v": 0.0}],
                                 t_end=8.0, dt=0.02, damping={"mu_x": mu}))
    t, Y = columns(frame, 1, ["x", "v"])
    x, v = coulomb_closed_form(t, k, mu, A)
    np.testing.assert_allclose(Y[:, 0], x, rtol=0, atol=TOL)
    np.testing.assert_allclose(Y[:, 1], v, rtol=0, atol=TOL)


@pytest.mark.parametrize("damping, force", [
    pytest.param({"mu_x": 0.05}, lambda v: -0.05 * np.sign(v), id="coulomb"),
    pytest.param({"d_x": 0.2}, lambda v: -0.2 * np.abs(v) * v, id="quadratic"),
    pytest.param({"c_x": 0.1, "d_x": 0.2, "mu_x": 0.02},
                 lambda v: -0.1 * v - 0.2 * np.abs(v) * v - 0.02 * np.sign(v),
                 id="combined"),
])
def test_nonlinear_damping_matches_hand_written_equation(damping, force):
    k, k3 = 1.0, 0.5
    initial = [{"x": 1.2, "v": 0.0}, {"x": -0.5, "v": 0.8}]
    frame = simulate(make_system(DUFFING, {"k": k, "k3": k3}, initial, t_end=8.0,
                                 damping=damping))
    assert_matches_reference(frame, ["x", "v"], initial,
                             lambda t, y: [y[1], -k * y[0] - k3 * y[0]**3 + force(y[1])])


def duffing_energy(x, v, k, k3):
    return v**2 / 2 + k * x**2 / 2 + k3 * x**4 / 4


@pytest.mark.parametrize("damping, power", [
    pytest.param({"c_x": 0.15}, lambda v: 0.15 * v**2, id="viscous"),
    pytest.param({"d_x": 0.3}, lambda v: 0.3 * np.abs(v)**3, id="quadratic"),
    pytest.param({"mu_x": 0.05}, None, id="coulomb"),
])
def test_energy_balance_of_damped_run(damping, power):
    k, k3 = 1.0, 0.5
    state = {"x": 1.0, "v": 0.3}
    frame = simulate(make_system(DUFFING, {"k": k, "k3": k3}, [state], t_end=6.0, dt=0.002,
                                 damping=damping))
    record = frame.attrs["hamid"]["trajectories"][0]
    t, Y = columns(frame, 1, ["x", "v"])
    E = duffing_energy(Y[:, 0], Y[:, 1], k, k3)
    E0 = duffing_energy(state["x"], state["v"], k, k3)
    # energy_dissipated is the work done by the damping forces, as a fraction of E0, and
    # energy_drift is the drift of energy + that work
    assert 0.05 < record["energy_dissipated"] < 1
    assert record["energy_dissipated"] == pytest.approx((E0 - E[-1]) / E0, abs=DRIFT)
    assert record["energy_drift"] < DRIFT
    if power is not None:  # Simpson's rule needs a smooth integrand (not |v| of Coulomb)
        work = cumulative_simpson(power(Y[:, 1]), x=t, initial=0.0)
        assert np.max(np.abs(E + work - E0)) / E0 < DRIFT


def test_conservative_run_reports_no_dissipation_and_damped_runs_some():
    base = make_system(DUFFING, {"k": 1.0, "k3": 0.5}, [{"x": 1.0, "v": 0.0}], t_end=5.0)
    conservative = simulate(base).attrs["hamid"]["trajectories"][0]
    damped = simulate({**base, "damping": {"c_x": 0.01}}).attrs["hamid"]["trajectories"][0]
    zero = simulate({**base, "damping": {"c_x": 0.0}}).attrs["hamid"]["trajectories"][0]
    assert conservative["energy_dissipated"] == 0.0
    assert zero["energy_dissipated"] == 0.0
    assert 0.01 < damped["energy_dissipated"] < 0.1


# --- Noise and seeds --------------------------------------------------------------------

NOISE_SYSTEM = make_system(HARMONIC, {"k": 3.0},
                           [{"x": 0.1 * j, "v": 0.5 - 0.05 * j} for j in range(1, 21)],
                           t_end=20.0, dt=0.01)
NOISE_SYSTEM["simulate"].update(rtol=1e-8, atol=1e-9)  # accuracy is not under test here


@pytest.fixture(scope="module")
def clean():
    return simulate(NOISE_SYSTEM)


@pytest.mark.parametrize("noise", [
    {"x": 0.01, "v": 0.003},
    {"relative": 0.02},
    {"x": 0.05, "relative": 0.01},
])
def test_noise_has_the_requested_standard_deviation(clean, noise):
    frame = simulate({**NOISE_SYSTEM, "noise": noise}, seed=7)
    info = frame.attrs["hamid"]
    pd.testing.assert_series_equal(frame["t"], clean["t"])
    pd.testing.assert_series_equal(frame["trajectory"], clean["trajectory"])
    for column in ("x", "v"):
        asked = noise.get(column, noise.get("relative", 0.0) * clean[column].std(ddof=0))
        error = (frame[column] - clean[column]).to_numpy()
        assert len(error) > 40_000
        assert np.std(error) == pytest.approx(asked, rel=0.05)
        assert abs(np.mean(error)) < 5 * asked / np.sqrt(len(error))
        assert info["noise"][column] == pytest.approx(asked, rel=1e-12)


def test_clean_run_records_no_noise(clean):
    assert clean.attrs["hamid"]["noise"] is None


def test_same_seed_same_frame_and_different_seed_different_noise(clean):
    system = {**NOISE_SYSTEM, "noise": {"relative": 0.01}}
    first, again, other = (simulate(system, seed=s) for s in (3, 3, 4))
    pd.testing.assert_frame_equal(first, again)
    assert first.attrs["hamid"]["seed"] == 3
    assert other.attrs["hamid"]["seed"] == 4
    difference = (first["x"] - clean["x"]) - (other["x"] - clean["x"])
    assert np.std(difference) > 0.5 * 0.01 * clean["x"].std()


def test_seed_argument_overrides_simulate_seed():
    system = copy.deepcopy(NOISE_SYSTEM)
    system["simulate"].update(t_end=5.0, seed=1)
    system["noise"] = {"x": 0.1}
    from_file = simulate(system)
    overridden = simulate(system, seed=2)
    system["simulate"]["seed"] = 2
    pd.testing.assert_frame_equal(overridden, simulate(system))
    assert from_file.attrs["hamid"]["seed"] == 1
    assert overridden.attrs["hamid"]["seed"] == 2
    assert not np.allclose(from_file["x"], overridden["x"])


def test_unseeded_run_records_a_seed_that_reproduces_it():
    system = copy.deepcopy(NOISE_SYSTEM)
    system["simulate"]["t_end"] = 5.0
    system["noise"] = {"relative": 0.05}
    frame = simulate(system)
    seed = frame.attrs["hamid"]["seed"]
    assert isinstance(seed, int)
    pd.testing.assert_frame_equal(frame, simulate(system, seed=seed))


# --- Provenance -------------------------------------------------------------------------


def test_provenance_records_model_truth_and_settings():
    initial = [{"x1": 0.4, "x2": -0.3, "v1": 0.0, "v2": 0.2},
               {"x1": 0.0, "x2": 0.1, "v1": 0.3, "v2": 0.0}]
    parameters = {"m": 2.0, "k1": 1.0, "k2": 3.0, "k3": 0.5}
    system = make_system({**TWO_MASSES, "name": "two-masses"}, parameters, initial,
                         t_end=2.0, noise={"x1": 0.001}, damping={"c_x1": 0.01})
    system["simulate"].update(rtol=1e-10, atol=1e-11)
    info = simulate(system, seed=11).attrs["hamid"]
    for key in ("model", "parameters", "initial", "trajectories", "noise", "seed",
                "integrator", "hamid_version"):
        assert key in info, key
    assert info["model"] == {"name": "two-masses", "energy": TWO_MASSES["energy"],
                             "coordinates": ["x1", "x2"], "velocities": ["v1", "v2"],
                             "parameters": ["m", "k1", "k2", "k3"], "dissipation": None}
    assert info["parameters"] == parameters
    assert info["damping"] == {"c_x1": 0.01}
    assert info["initial"] == initial
    assert info["noise"] == {"x1": 0.001}
    assert info["seed"] == 11
    assert info["integrator"] == {"method": "dop853", "rtol": 1e-10, "atol": 1e-11}
    assert info["hamid_version"] == hamid.__version__
    assert [r["trajectory"] for r in info["trajectories"]] == [1, 2]
    for record, s in zip(info["trajectories"], initial, strict=True):
        d = s["x2"] - s["x1"]
        E0 = ((s["v1"]**2 + 2.0 * s["v2"]**2) / 2 + s["x1"]**2 / 2 + 3.0 * d**2 / 2
              + 0.5 * d**4 / 4)
        assert record["energy"] == pytest.approx(E0, rel=1e-12)
        assert {"energy_drift", "energy_dissipated"} <= set(record)


# --- Errors -----------------------------------------------------------------------------


def valid_system():
    return make_system(DUFFING, {"k": 1.0, "k3": 0.5},
                       [{"x": 1.0, "v": 0.0}, {"x": 0.5, "v": 0.2}], t_end=1.0)


def _rename(old, new, table=None):
    """An edit that renames a key of the system (or of one of its tables)."""
    def edit(system):
        target = system if table is None else system[table]
        target[new] = target.pop(old)
    return edit


ERRORS = [
    pytest.param(lambda s: s.pop("model"), r"missing table \[model\]", id="no-model"),
    pytest.param(_rename("parameters", "paramters"),
                 r"unknown key 'paramters'; did you mean 'parameters'", id="top-level-typo"),
    pytest.param(lambda s: s["parameters"].pop("k3"), r"\[parameters\] has no value for k3",
                 id="missing-parameter"),
    pytest.param(lambda s: s["parameters"].update(zeta=0.1),
                 r"\[parameters\]: unknown key 'zeta'", id="unknown-parameter"),
    pytest.param(lambda s: s["initial"][1].pop("v"), r"\[\[initial\]\] #2: missing v",
                 id="missing-initial-component"),
    pytest.param(lambda s: s["initial"][0].update(y=0.0),
                 r"\[\[initial\]\] #1: unknown key 'y'", id="unknown-initial-key"),
    pytest.param(lambda s: s.update(initial=[]), r"at least one \[\[initial\]\]",
                 id="no-initial"),
    pytest.param(lambda s: s["simulate"].update(dt=0.0), r"\[simulate\] dt: must be positive",
                 id="zero-dt"),
    pytest.param(lambda s: s["simulate"].update(dt=-0.1),
                 r"\[simulate\] dt: must be positive", id="negative-dt"),
    pytest.param(lambda s: s["simulate"].update(t_end=0.0),
                 r"\[simulate\] t_end: must be positive", id="zero-t_end"),
    pytest.param(lambda s: s["simulate"].update(t_end=-5),
                 r"\[simulate\] t_end: must be positive", id="negative-t_end"),
    pytest.param(lambda s: s["simulate"].pop("dt"), r"\[simulate\] needs 'dt'", id="no-dt"),
    pytest.param(_rename("t_end", "tend", table="simulate"),
                 r"\[simulate\]: unknown key 'tend'; did you mean 't_end'",
                 id="unknown-simulate-key"),
    pytest.param(lambda s: s["simulate"].update(method="euler"),
                 r"method 'euler' is not one of", id="unknown-integrator"),
    pytest.param(lambda s: s["simulate"].update(seed=-1), r"seed must be a non-negative",
                 id="negative-seed"),
    pytest.param(lambda s: s.update(damping={"c_x": -0.1}),
                 r"\[damping\] c_x: must not be negative", id="negative-damping"),
    pytest.param(lambda s: s.update(damping={"c_z": 0.1}),
                 r"\[damping\]: unknown key 'c_z'", id="damping-of-unknown-coordinate"),
    pytest.param(lambda s: s.update(damping={"friction_x": 0.1}),
                 r"\[damping\]: unknown key 'friction_x'", id="unknown-damping-kind"),
    pytest.param(lambda s: s.update(noise={"z": 0.1}), r"\[noise\]: unknown key 'z'",
                 id="noise-of-unknown-column"),
    pytest.param(lambda s: s.update(noise={"x": -0.1}), r"\[noise\] x: must not be negative",
                 id="negative-noise"),
    pytest.param(lambda s: s["simulate"].update(max_samples=21),
                 r"22 samples, more than max_samples = 21", id="max-samples-in-file"),
]


@pytest.mark.parametrize("edit, match", ERRORS)
def test_invalid_system_names_the_problem(edit, match):
    system = valid_system()
    edit(system)
    with pytest.raises(ModelError, match=match):
        simulate(system)


def test_valid_system_runs():
    """The base of the error cases is itself valid, so each error comes from its edit."""
    frame = simulate(valid_system())
    assert len(frame) == 22


def test_max_samples_argument_limits_the_run():
    system = valid_system()
    assert len(simulate(system, max_samples=22)) == 22
    with pytest.raises(ModelError, match=r"22 samples, more than max_samples = 10"):
        simulate(system, max_samples=10)


@pytest.mark.parametrize("initial, label", [
    pytest.param([{"x": 2.0, "v": 0.0}], 1, id="only"),
    pytest.param([{"x": 0.5, "v": 0.0}, {"x": 2.0, "v": 0.0}], 2, id="second"),
    pytest.param([{"x": 2.0, "v": 0.0}, {"x": 0.5, "v": 0.0}], 1, id="first"),
    pytest.param([{"x": 0.9, "v": 0.0}, {"x": 0.0, "v": 0.8}], 2, id="over-the-barrier"),
])
def test_escaping_trajectory_is_named(initial, label):
    system = make_system(DUFFING, {"k": 1.0, "k3": -1.0}, initial)
    with pytest.raises(ModelError, match=rf"trajectory {label} escapes") as caught:
        simulate(system)
    # x'' = -x + x^3 moving outwards reaches infinity at t* = int dx / |v(x)| from x0
    x0, v0 = initial[label - 1]["x"], initial[label - 1]["v"]
    twice_energy = v0**2 + x0**2 - x0**4 / 2
    t_star = quad(lambda x: 1 / np.sqrt(twice_energy - x**2 + x**4 / 2), x0, np.inf)[0]
    reported = float(re.search(r"near t = ([0-9.e+-]+)", str(caught.value)).group(1))
    assert reported == pytest.approx(t_star, abs=1e-3)


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_trajectory_leaving_the_domain_of_the_energy_is_named(order):
    """x = -3 sin(t) (nearly) reaches x = -1, where sqrt(1 + x) ends, at t = 0.34."""
    model = {"coordinates": ["x"], "velocities": ["v"],
             "energy": "v**2/2 + k*x**2/2 - a*sqrt(1 + x)"}
    states = [{"x": 0.0, "v": 4.0}, {"x": 0.0, "v": -3.0}]  # the larger one stays inside
    initial = [states[i] for i in order]
    label = initial.index(states[1]) + 1
    system = make_system(model, {"k": 1.0, "a": 0.1}, initial, dt=0.5)
    with pytest.raises(ModelError, match=rf"trajectory {label} escapes .* near t = 0\.34"):
        simulate(system)


@pytest.mark.parametrize("model, parameters, label", [
    pytest.param(TWO_MASSES, {"m": -1.0, "k1": 1.0, "k2": 1.0, "k3": 0.0}, 1,
                 id="negative-mass"),
    pytest.param({"coordinates": ["x1", "x2"], "velocities": ["v1", "v2"],
                  "energy": "(v1**2 + (1 + m*x1**2)*v2**2)/2 + k1*x1**2/2"},
                 {"m": -1.0, "k1": 1.0}, 2, id="position-dependent-mass"),
])
def test_mass_matrix_not_positive_definite_names_the_trajectory(model, parameters, label):
    initial = [{"x1": 0.5, "x2": 0.0, "v1": 0.0, "v2": 0.1},
               {"x1": 2.0, "x2": 0.0, "v1": 0.0, "v2": 0.1}]
    system = make_system(model, parameters, initial)
    with pytest.raises(ModelError, match=rf"not positive definite at the initial state of "
                                         rf"trajectory {label}\b"):
        simulate(system)


def test_friction_that_holds_the_mass_at_rest_stops_the_run_with_the_reason(tmp_path):
    """Coulomb friction larger than the spring's force at a stop: the exact law's force
    jumps back and forth and the integrator would crawl on for ever; the run stops within
    one sample's worth of steps and says why, in one line, also on the command line."""
    import subprocess

    from hamid.errors import ModelError
    from tests.helpers import hamid_command, one_line_error

    system = {"model": DUFFING, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": [{"x": 1.0, "v": 0.0}], "damping": {"c_x": 0.02, "mu_x": 0.04},
              "simulate": {"t_end": 40.0, "dt": 0.05}}
    with pytest.raises(ModelError, match=r"within one sample at t = \d+\.\d+.*holds a mass "
                                         r"at rest.*shorten t_end"):
        hamid.simulate(system)
    config = tmp_path / "stick.toml"
    config.write_text("""
[model]
builtin = "duffing"
[parameters]
k = 1.0
k3 = 0.5
[damping]
c_x = 0.02
mu_x = 0.04
[[initial]]
x = 1.0
v = 0.0
[simulate]
t_end = 40.0
dt = 0.05
""")
    out = tmp_path / "stick.csv"
    done = subprocess.run([*hamid_command(), "simulate", "--config", str(config), "-o",
                           str(out)], capture_output=True, text=True)
    one_line_error(done, 1, "holds a mass at rest", "shorten t_end")
    assert not out.exists()
