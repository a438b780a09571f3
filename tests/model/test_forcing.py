"""The [forcing] table, the driven equations of motion and the simulated input signals,
against hand-written equations (solve_ivp) and the signals' formulas."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import hamid
from hamid.errors import ModelError
from hamid.model.models import forcing_table, model_from_info, model_from_spec
from tests.helpers import hamid_command, one_line_error

SYSTEM_TOML = """
[model]
coordinates = ["x"]
velocities = ["v"]
energy = "m*v**2/2 + k*x**2/2 + k3*x**4/4"
parameters = ["m", "k", "k3"]

[parameters]
m = 1.5
k = 4.0
k3 = 2.0

[damping]
c_x = 0.1

[forcing]
inputs = ["F"]
work = "F*x"

[forcing.signals.F]
{signal}

[[initial]]
x = 0.2
v = 0.0

[simulate]
t_end = {t_end}
dt = 0.01
"""

DUFFING = {"coordinates": ["x"], "velocities": ["v"],
           "energy": "m*v**2/2 + k*x**2/2 + k3*x**4/4", "parameters": ["m", "k", "k3"]}


def duffing(**forcing):
    return forcing_table(model_from_spec(DUFFING), {"inputs": ["F"], "work": "F*x", **forcing})


def test_the_generalized_force_is_the_works_derivative_split_by_parameter():
    model = forcing_table(model_from_spec(DUFFING),
                          {"inputs": ["F"], "work": "b*F*x + F*sin(x) - m*F*x",
                           "parameters": ["b"]})
    assert model.parameters == ("m", "k", "k3", "b")
    assert model.inputs == ("F",)
    X, U = np.array([[0.3, 1.0], [-1.2, 0.5]]), np.array([[2.0], [-0.7]])
    Q0, Q = model.forcing.parts(X, U)
    np.testing.assert_allclose(Q0[:, 0], U[:, 0] * np.cos(X[:, 0]))
    np.testing.assert_allclose(Q[:, 0, 0], -U[:, 0])        # m
    np.testing.assert_allclose(Q[:, 0, 1:3], 0.0, atol=0)    # k, k3
    np.testing.assert_allclose(Q[:, 0, 3], U[:, 0])         # b
    assert model.forcing.has_known_part
    # a gain has no part in the energy
    np.testing.assert_allclose(model.energy_basis(X)[1][:, 3], 0.0, atol=0)


def test_a_work_of_gains_only_has_no_known_part():
    model = forcing_table(model_from_spec(DUFFING),
                          {"inputs": ["F"], "work": "b*F*x", "parameters": ["b"]})
    assert not model.forcing.has_known_part


def test_a_driven_model_survives_its_report():
    model = duffing()
    again = model_from_info(model.info(), where="report")
    assert again.parameters == model.parameters and again.inputs == ("F",)
    assert again.forcing.work == "F*x"


@pytest.mark.parametrize(("table", "message"), [
    ({"inputs": ["F"], "work": "F*x + f*x"},
     "[forcing]: work: unknown symbol 'f' (did you mean 'F'?); it may use x, F, m, k, k3"),
    ({"inputs": ["F"], "work": "F*v"},
     "it may use x, F, m, k, k3; velocities may not appear in the work"),
    ({"inputs": ["F"], "work": "b*k*F*x", "parameters": ["b"]},
     "work term 'x*F*k*b' is not linear in the parameters (k, b)"),
    ({"inputs": ["F"], "work": "sin(b*F)*x", "parameters": ["b"]},
     "work term 'x*sin(F*b)' is not linear in the parameters (b)"),
    ({"inputs": ["F"], "work": "F*x", "parameters": ["b"]}, "parameter 'b' does not appear"),
    ({"inputs": [], "work": "F*x"}, "'inputs' must list at least one input"),
    ({"inputs": "F", "work": "F*x"}, "'inputs' must be a list of names"),
    ({"inputs": ["x"], "work": "x"}, "'x' cannot be an input or gain name: it is a coordinate"),
    ({"inputs": ["v"], "work": "x"}, "'v' cannot be an input or gain name: it is a velocity"),
    ({"inputs": ["k"], "work": "k*x"}, "'k' cannot be an input or gain name: it is a parameter"),
    ({"inputs": ["F"], "work": "m*F*x", "parameters": ["m"]},
     "'m' cannot be an input or gain name: it is a parameter of the model"),
    ({"inputs": ["sin"], "work": "x"}, "'sin' cannot be an input or gain name: it is a function"),
    ({"inputs": ["2F"], "work": "x"}, "'2F' cannot be an input or gain name: it is not a name"),
    ({"inputs": ["F", "F"], "work": "F*x"}, "'F' is given twice in 'inputs' and 'parameters'"),
    ({"inputs": ["F"], "work": "b*F*x", "parameters": ["F"]}, "'F' is given twice"),
    ({"inputs": ["F"], "work": "F"}, "does not depend on any coordinate"),
    ({"inputs": ["F"], "work": 3}, "'work' must be an expression"),
    ({"inputs": ["F"], "work": "F*x", "gain": 1}, "gain"),
])
def test_a_bad_forcing_table_is_named_in_one_line(table, message):
    with pytest.raises(ModelError) as error:
        forcing_table(model_from_spec(DUFFING), table)
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def _system(signal, *, damping=None, initial=None, t_end=20.0, dt=0.01, noise=None):
    return {"model": DUFFING, "parameters": {"m": 1.5, "k": 4.0, "k3": 2.0},
            "forcing": {"inputs": ["F"], "work": "F*x", "signals": {"F": signal}},
            "damping": damping or {"c_x": 0.1},
            "initial": [initial or {"x": 0.2, "v": 0.0}],
            "simulate": {"t_end": t_end, "dt": dt}, **({"noise": noise} if noise else {})}


def test_a_driven_duffing_is_simulated_as_scipy_integrates_its_equations():
    signal = {"kind": "sine", "amplitude": 0.8, "frequency": 0.45, "phase": 0.3}
    frame = hamid.simulate(_system(signal))

    def equations(t, y):
        x, v = y
        force = 0.8 * np.sin(2 * np.pi * 0.45 * t + 0.3)
        return [v, (force - 4.0 * x - 2.0 * x**3 - 0.1 * v) / 1.5]

    t = frame["t"].to_numpy()
    exact = solve_ivp(equations, (0, t[-1]), [0.2, 0.0], method="DOP853", t_eval=t,
                      rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(frame["x"], exact.y[0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(frame["v"], exact.y[1], rtol=0, atol=1e-8)
    np.testing.assert_allclose(frame["F"], 0.8 * np.sin(2 * np.pi * 0.45 * t + 0.3),
                               rtol=0, atol=1e-12)


def test_a_two_mass_chain_forced_on_its_second_mass_matches_scipy():
    system = {
        "model": {"coordinates": ["x1", "x2"], "velocities": ["v1", "v2"],
                  "energy": "m1*v1**2/2 + m2*v2**2/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2",
                  "parameters": ["m1", "m2", "k1", "k2"]},
        "parameters": {"m1": 1.0, "m2": 0.5, "k1": 3.0, "k2": 2.0},
        "damping": {"dissipation": "c1*v1**2/2 + c2*(v2 - v1)**2/2",
                    "parameters": ["c1", "c2"], "c1": 0.05, "c2": 0.03},
        "forcing": {"inputs": ["F"], "work": "F*x2",
                    "signals": {"F": {"kind": "sweep", "amplitude": 1.0, "f0": 0.1, "f1": 1.0,
                                      "duration": 30.0}}},
        "initial": [{"x1": 0.0, "x2": 0.0, "v1": 0.0, "v2": 0.0}],
        "simulate": {"t_end": 30.0, "dt": 0.01},
    }
    frame = hamid.simulate(system)

    def equations(t, y):
        x1, x2, v1, v2 = y
        force = np.sin(2 * np.pi * (0.1 * t + 0.9 / 30.0 * t**2 / 2))
        a1 = (-3.0 * x1 + 2.0 * (x2 - x1) - 0.05 * v1 + 0.03 * (v2 - v1)) / 1.0
        a2 = (-2.0 * (x2 - x1) - 0.03 * (v2 - v1) + force) / 0.5
        return [v1, v2, a1, a2]

    t = frame["t"].to_numpy()
    exact = solve_ivp(equations, (0, t[-1]), [0, 0, 0, 0], method="DOP853", t_eval=t,
                      rtol=1e-12, atol=1e-12)
    for i, name in enumerate(["x1", "x2", "v1", "v2"]):
        np.testing.assert_allclose(frame[name], exact.y[i], rtol=0, atol=1e-8)
    assert frame.attrs["hamid"]["trajectories"][0]["energy_drift"] < 1e-8


def test_a_sine_driven_linear_oscillator_reaches_its_exact_steady_state():
    m, k, c, amplitude, f = 2.0, 8.0, 0.8, 0.5, 0.3
    system = {"model": {"coordinates": ["x"], "velocities": ["v"],
                        "energy": "m*v**2/2 + k*x**2/2", "parameters": ["m", "k"]},
              "parameters": {"m": m, "k": k}, "damping": {"c_x": c},
              "forcing": {"inputs": ["F"], "work": "F*x",
                          "signals": {"F": {"kind": "sine", "amplitude": amplitude,
                                            "frequency": f}}},
              "initial": [{"x": 0.0, "v": 0.0}], "simulate": {"t_end": 100.0, "dt": 0.01}}
    frame = hamid.simulate(system)
    w = 2 * np.pi * f
    response = amplitude / complex(k - m * w**2, c * w)   # x = Im(response e^{iwt})
    late = frame["t"] > 90   # the transient decays as exp(-c t / 2m): e^-18 by t = 90
    t = frame["t"][late].to_numpy()
    np.testing.assert_allclose(frame["x"][late], np.imag(response * np.exp(1j * w * t)),
                               rtol=0, atol=1e-7)


def test_a_sweeps_instantaneous_frequency_goes_from_f0_to_f1():
    for law in ("linear", "log"):
        frame = hamid.simulate(_system({"kind": "sweep", "amplitude": 1.0, "f0": 0.2,
                                        "f1": 2.0, "law": law}, t_end=20.0, dt=0.001))
        t, u = frame["t"].to_numpy(), frame["F"].to_numpy()
        crossings = t[1:][np.diff(np.signbit(u)) != 0]
        period = np.diff(crossings[::2])   # a full period between every other crossing
        middle = crossings[:-2:2] + period / 2
        expected = (0.2 + 1.8 * middle / 20 if law == "linear"
                    else 0.2 * 10 ** (middle / 20))
        np.testing.assert_allclose(1 / period, expected, rtol=0.02)


@pytest.mark.parametrize("kind", ["multisine", "noise"])
def test_a_multisine_and_noise_have_their_rms_and_stay_in_their_band(kind):
    frame = hamid.simulate(_system({"kind": kind, "amplitude": 0.7, "band": [0.5, 2.0],
                                    "seed": 4}, t_end=40.0, dt=0.01))
    u = frame["F"].to_numpy()[:-1]   # one whole record period: 1/t_end is the grid
    assert np.sqrt(np.mean(u**2)) == pytest.approx(0.7, rel=1e-6)
    power = np.abs(np.fft.rfft(u)) ** 2
    frequencies = np.fft.rfftfreq(len(u), 0.01)
    inside = (frequencies >= 0.5 - 1e-9) & (frequencies <= 2.0 + 1e-9)
    assert power[~inside].sum() < 1e-12 * power[inside].sum()


def test_a_file_signal_is_a_cubic_spline_through_its_samples(tmp_path):
    t = np.linspace(0, 12, 601)
    (tmp_path / "force.csv").write_text(
        "t,load\n" + "".join(f"{float(a)!r},{float(np.sin(a))!r}\n" for a in t))
    config = tmp_path / "system.toml"
    config.write_text(SYSTEM_TOML.format(
        signal='kind = "file"\npath = "force.csv"\ncolumn = "load"', t_end=10.0))
    frame = hamid.simulate(config)
    np.testing.assert_allclose(frame["F"], np.sin(frame["t"]), rtol=0, atol=1e-7)
    # a time column in milliseconds is read in seconds
    (tmp_path / "force.csv").write_text(
        "time_ms,load\n" + "".join(f"{float(1000 * a)!r},{float(np.sin(a))!r}\n" for a in t))
    frame = hamid.simulate(config)
    np.testing.assert_allclose(frame["F"], np.sin(frame["t"]), rtol=0, atol=1e-7)


@pytest.mark.parametrize(("signal", "message"), [
    ('path = "gone.csv"\ncolumn = "load"', "[forcing.signals.F]: "),
    ('path = "force.csv"\ncolumn = "lod"',
     "[forcing.signals.F]: force.csv has no column 'lod' (columns: t, load, word)"),
    ('path = "force.csv"\ncolumn = "word"',
     "[forcing.signals.F]: force.csv: column 'word', row 1: 'w' is not a number"),
    ('path = "short.csv"\ncolumn = "load"',
     "[forcing.signals.F]: short.csv covers t = 0 to 5 s, not the run's 0 to 10 s"),
    ('path = "force.csv"\ncolumn = "load"\ntime = "s"',
     "[forcing.signals.F]: force.csv has no column 's'"),
])
def test_a_bad_file_signal_is_named_by_its_key(tmp_path, signal, message):
    (tmp_path / "force.csv").write_text("t,load,word\n" + "".join(
        f"{a:g},1.0,w\n" for a in np.linspace(0, 12, 25)))
    (tmp_path / "short.csv").write_text("t,load\n" + "".join(
        f"{a:g},1.0\n" for a in np.linspace(0, 5, 11)))
    config = tmp_path / "system.toml"
    config.write_text(SYSTEM_TOML.format(signal=f'kind = "file"\n{signal}', t_end=10.0))
    with pytest.raises(ModelError) as error:
        hamid.simulate(config)
    assert message in str(error.value) and "\n" not in str(error.value)
    assert str(error.value).startswith(str(config))


def test_the_inputs_noise_goes_on_its_written_column_only():
    clean = hamid.simulate(_system({"kind": "sine", "amplitude": 1.0, "frequency": 0.5}))
    noisy = hamid.simulate(_system({"kind": "sine", "amplitude": 1.0, "frequency": 0.5},
                                   noise={"F": 0.05}), seed=3)
    np.testing.assert_array_equal(noisy["x"], clean["x"])
    assert np.std(noisy["F"] - clean["F"]) == pytest.approx(0.05, rel=0.1)


@pytest.mark.parametrize(("change", "message"), [
    ({"kind": "sinus"}, "kind 'sinus' is not a signal kind (did you mean 'sine'?)"),
    ({"kind": "sine"}, "missing key 'frequency'"),
    ({"kind": "multisine", "band": [2.0, 1.0], "frequency": None},
     "f_lo must be below f_hi"),
    ({"amplitude": -1.0}, "[forcing.signals.F] amplitude: must not be negative"),
    ({"amplitude": "big"}, "[forcing.signals.F] amplitude: expected a number"),
    ({"frequency": 0.0}, "[forcing.signals.F] frequency: must be positive"),
    ({"phase": float("nan")}, "[forcing.signals.F] phase: expected a finite number"),
    ({"freq": 2.0}, "unknown key 'freq'; did you mean 'frequency'?"),
    ({"kind": "sweep", "f0": 0.1, "f1": 1.0, "law": "exp", "frequency": None},
     "law 'exp' is not 'linear' or 'log'"),
    ({"kind": "sweep", "f0": 0.1, "frequency": None}, "missing key 'f1'"),
    ({"kind": "sweep", "f0": 0.1, "f1": 1.0, "duration": 0.0, "frequency": None},
     "[forcing.signals.F] duration: must be positive"),
    ({"kind": "noise", "band": [0.5, 2.0], "seed": 1.5, "frequency": None},
     "seed must be a non-negative integer"),
    ({"kind": "noise", "band": "0.5-2", "frequency": None}, "band must be [f_lo, f_hi] in Hz"),
    ({"kind": "multisine", "band": [0.01, 0.02], "frequency": None},
     "holds no frequency of the run's grid (multiples of 1/t_end = 0.05 Hz)"),
    ({"kind": "noise", "band": [0.0, 500.0], "frequency": None}, "more than 2,000; narrow it"),
])
def test_a_bad_signal_is_named_in_one_line(change, message):
    signal = {"kind": "sine", "amplitude": 1.0, "frequency": 0.5, **change}
    signal = {k: v for k, v in signal.items() if v is not None}
    if change.get("kind") == "sine" and len(change) == 1:
        signal.pop("frequency")
    with pytest.raises(ModelError) as error:
        hamid.simulate(_system(signal))
    assert message in str(error.value) and "\n" not in str(error.value)
    assert "[forcing.signals.F]" in str(error.value)


def test_every_input_needs_a_signal_and_every_signal_an_input():
    system = _system({"kind": "sine", "amplitude": 1.0, "frequency": 0.5})
    system["forcing"]["signals"] = {}
    with pytest.raises(ModelError, match="no signal for the input"):
        hamid.simulate(system)
    system["forcing"]["signals"] = {"F": {"kind": "sine", "amplitude": 1, "frequency": 1},
                                    "G": {"kind": "sine", "amplitude": 1, "frequency": 1}}
    with pytest.raises(ModelError, match="'G'"):
        hamid.simulate(system)


def _simulate_sine(tmp_path, frequency: float, t_end: float):
    """`hamid simulate` of the driven system under a sine of `frequency` Hz, to a CSV."""
    config = tmp_path / "driven.toml"
    config.write_text(SYSTEM_TOML.format(
        signal=f'kind = "sine"\namplitude = 1.0\nfrequency = {frequency}', t_end=t_end))
    out = tmp_path / "driven.csv"
    done = subprocess.run([*hamid_command(), "simulate", "--config", str(config), "-o",
                           str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return done, out


def test_hamid_simulate_writes_the_input_beside_the_motion(tmp_path):
    done, out = _simulate_sine(tmp_path, 0.5, 5.0)
    assert "warning" not in done.stderr   # 0.5 Hz, sampled at 100 Hz
    header = next(line for line in out.read_text().splitlines()
                  if line.startswith("trajectory"))
    assert header.split(",")[-3:] == ["x", "v", "F"]
    bad = tmp_path / "bad.toml"
    bad.write_text(SYSTEM_TOML.format(signal='kind = "multisin"\namplitude = 1.0', t_end=5.0))
    done = subprocess.run([*hamid_command(), "simulate", "--config", str(bad), "-o",
                           str(tmp_path / "bad.csv")], capture_output=True, text=True)
    one_line_error(done, 1, "multisin", "did you mean 'multisine'?")
    assert not (tmp_path / "bad.csv").exists()
    bad.write_text(SYSTEM_TOML.format(signal='kind = "file"\npath = "gone.csv"\n'
                                      'column = "load"', t_end=5.0))
    done = subprocess.run([*hamid_command(), "simulate", "--config", str(bad), "-o",
                           str(tmp_path / "bad.csv")], capture_output=True, text=True)
    one_line_error(done, 1, "[forcing.signals.F]", "gone.csv: no such file")
    assert not (tmp_path / "bad.csv").exists()


@pytest.mark.parametrize(("signal", "top"), [
    ('kind = "sine"\namplitude = 1.0\nfrequency = 60.0', "60 Hz"),
    ('kind = "sine"\namplitude = 1.0\nfrequency = 50.0', "50 Hz"),
    # on by its law past its duration: 1 + (30 - 1) / 0.5 * 1 Hz at t_end
    ('kind = "sweep"\namplitude = 1.0\nf0 = 1.0\nf1 = 30.0\nduration = 0.5', "59 Hz"),
    # 1 * (30 / 1)**(1 / 0.8) Hz at t_end
    ('kind = "sweep"\namplitude = 1.0\nf0 = 1.0\nf1 = 30.0\nduration = 0.8\nlaw = "log"',
     "70.21 Hz"),
    # a sweep down: its highest frequency is its first
    ('kind = "sweep"\namplitude = 1.0\nf0 = 70.0\nf1 = 1.0', "70 Hz"),
    # the run's grid: multiples of 1/t_end = 1 Hz, up to 54 Hz in the band
    ('kind = "multisine"\namplitude = 1.0\nband = [0.5, 54.9]', "54 Hz"),
    ('kind = "noise"\namplitude = 1.0\nband = [0.5, 55.0]', "55 Hz"),
])
def test_a_signal_beyond_the_nyquist_frequency_is_a_warning(signal, top):
    import tomllib

    data = hamid.simulate(tomllib.loads(SYSTEM_TOML.format(signal=signal, t_end=1.0)))
    [warning] = data.attrs["hamid"]["warnings"]
    assert warning.startswith("input 'F': its signal reaches ")
    assert f"reaches {top}," in warning and "Nyquist frequency 50 Hz" in warning


@pytest.mark.parametrize("signal", [
    'kind = "sine"\namplitude = 1.0\nfrequency = 49.0',
    'kind = "sweep"\namplitude = 1.0\nf0 = 1.0\nf1 = 45.0',
    'kind = "multisine"\namplitude = 1.0\nband = [0.5, 45.0]',
])
def test_a_signal_below_the_nyquist_frequency_is_no_warning(signal):
    import tomllib

    data = hamid.simulate(tomllib.loads(SYSTEM_TOML.format(signal=signal, t_end=1.0)))
    assert "warnings" not in data.attrs["hamid"]


def test_a_file_signal_near_the_nyquist_frequency_is_a_warning(tmp_path):
    import tomllib

    t = np.linspace(0.0, 1.0, 401)   # sampled 4 times finer than the run
    for name, frequency in (("slow", 2.0), ("fast", 45.0)):   # the run's Nyquist: 50 Hz
        load = np.sin(2 * np.pi * frequency * t)
        (tmp_path / f"{name}.csv").write_text("t,load\n" + "\n".join(
            f"{a:.17g},{b:.17g}" for a, b in zip(t, load, strict=True)))
        signal = f'kind = "file"\npath = "{tmp_path / name}.csv"\ncolumn = "load"'
        data = hamid.simulate(tomllib.loads(SYSTEM_TOML.format(signal=signal, t_end=1.0)))
        warnings = data.attrs["hamid"].get("warnings", [])
        if name == "slow":
            assert warnings == []
        else:
            [warning] = warnings
            assert warning.startswith("input 'F' has ")
            assert "above 40 Hz" in warning and "Nyquist frequency 50 Hz" in warning


def test_hamid_simulate_says_the_nyquist_warning_and_writes_the_record(tmp_path):
    done, out = _simulate_sine(tmp_path, 60.0, 1.0)
    warnings = [line for line in done.stderr.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "60 Hz" in warnings[0] and "50 Hz" in warnings[0]
    rows = [line for line in out.read_text().splitlines() if not line.startswith("#")]
    assert rows[0].split(",")[-1] == "F" and len(rows) == 1 + 101
