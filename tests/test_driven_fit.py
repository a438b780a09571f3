"""Driven systems fitted from their recorded force: parameters in physical units (masses
included), against the values they were simulated with."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DRIVEN_DUFFING_MODEL

import hamid

DUFFING_MODEL = DRIVEN_DUFFING_MODEL

DUFFING_TRUTH = {"m": 1.5, "k": 4.0, "k3": 2.0, "c_x": 0.08}

CHAIN_MODEL = """
[model]
name = "chain"
coordinates = ["x1", "x2"]
velocities = ["v1", "v2"]
energy = "m1*v1**2/2 + m2*v2**2/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2"
parameters = ["m1", "m2", "k1", "k2"]

[damping]
dissipation = "c1*v1**2/2 + c2*(v2 - v1)**2/2"
parameters = ["c1", "c2"]

[forcing]
inputs = ["F"]
work = "F*x2"
"""

CHAIN_TRUTH = {"m1": 1.0, "m2": 0.5, "k1": 3.0, "k2": 2.0, "c1": 0.05, "c2": 0.03}


def _system(model_text: str, truth: dict, damping: dict, signal: dict, initial: dict,
            t_end: float, dt: float, noise: dict | None = None) -> dict:
    import tomllib

    document = tomllib.loads(model_text)
    document.pop("damping", None)
    document["forcing"]["signals"] = {"F": signal}
    return {**document, "parameters": {k: v for k, v in truth.items() if k not in damping},
            "damping": damping, "initial": [initial],
            "simulate": {"t_end": t_end, "dt": dt}, **({"noise": noise} if noise else {})}


def duffing_system(noise: dict | None = None) -> dict:
    return _system(DUFFING_MODEL, DUFFING_TRUTH, {"c_x": DUFFING_TRUTH["c_x"]},
                   {"kind": "multisine", "amplitude": 1.0, "band": [0.05, 1.0], "seed": 3},
                   {"x": 0.0, "v": 0.0}, 80.0, 0.01, noise)


def chain_system(noise: dict | None = None) -> dict:
    damping = {"dissipation": "c1*v1**2/2 + c2*(v2 - v1)**2/2", "parameters": ["c1", "c2"],
               "c1": CHAIN_TRUTH["c1"], "c2": CHAIN_TRUTH["c2"]}
    return _system(CHAIN_MODEL, CHAIN_TRUTH, damping,
                   {"kind": "multisine", "amplitude": 1.0, "band": [0.05, 1.2], "seed": 5},
                   {"x1": 0.0, "x2": 0.0, "v1": 0.0, "v2": 0.0}, 80.0, 0.01, noise)


@pytest.fixture
def duffing_model(tmp_path):
    path = tmp_path / "driven_duffing.toml"
    path.write_text(DUFFING_MODEL)
    return path


@pytest.fixture
def chain_model(tmp_path):
    path = tmp_path / "chain.toml"
    path.write_text(CHAIN_MODEL)
    return path


def test_a_driven_duffing_with_free_mass_is_recovered_in_physical_units(duffing_model):
    data = hamid.simulate(duffing_system())
    result = hamid.fit(data, duffing_model, damping="viscous")
    for name, value in DUFFING_TRUTH.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-5), name
    assert not any("Nyquist" in warning for warning in result.warnings)   # 1 Hz at 100 Hz


def test_a_two_mass_chain_forced_on_its_second_mass_is_recovered(chain_model):
    data = hamid.simulate(chain_system())
    result = hamid.fit(data, chain_model)
    for name, value in CHAIN_TRUTH.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-5), name


def test_a_chain_driven_on_both_masses_is_recovered_and_predicted(tmp_path):
    """Two inputs, a force on each mass from its own multisine: the refinement integrates
    both (each segment's copies through one spline of all their columns), and the fit
    predicts a recording of the two signals swapped, which it never saw."""
    path = tmp_path / "chain2.toml"
    path.write_text(CHAIN_MODEL.replace('inputs = ["F"]', 'inputs = ["F1", "F2"]')
                    .replace('work = "F*x2"', 'work = "F1*x1 + F2*x2"'))
    signals = [{"kind": "multisine", "amplitude": amplitude, "band": [0.05, 1.2],
                "seed": seed} for amplitude, seed in ((0.6, 7), (1.0, 5))]

    def recording(first: dict, second: dict) -> dict:
        system = chain_system()
        system["forcing"] = {"inputs": ["F1", "F2"], "work": "F1*x1 + F2*x2",
                             "signals": {"F1": first, "F2": second}}
        return hamid.simulate(system)

    result = hamid.fit(recording(*signals), path)
    assert result.method["refinement"]["applied"]
    for name, value in CHAIN_TRUTH.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-5), name
    unseen = recording(*signals[::-1])
    predicted = result.predict(unseen)
    for channel in ("x1", "x2"):
        amplitude = unseen[channel].abs().max()
        assert predicted.channels.loc[channel, "rms"] < 1e-5 * amplitude, channel


def test_a_driven_duffing_with_coulomb_friction_is_recovered_through_its_reversals(
        duffing_model):
    """A machine's friction, crossed at every reversal of the drive: the refinement
    integrates it rounded (`method.refinement.smoothing`), to within what the rounding's
    stated force error allows on clean data."""
    system = duffing_system()
    system["damping"] = {"c_x": 0.08, "mu_x": 0.05}
    data = hamid.simulate(system)
    assert np.count_nonzero(np.diff(np.sign(data["v"])) != 0) > 40
    result = hamid.fit(data, duffing_model, damping="viscous,coulomb")
    [smoothing] = result.method["refinement"]["smoothing"]
    assert smoothing["mean_force_error"] < 1e-3
    for name, value in {**DUFFING_TRUTH, "mu_x": 0.05}.items():
        assert result.estimates[name] == pytest.approx(value, rel=2e-4), name


def _noisy(clean, rng, motion=0.01, force=0.002):
    """The clean record with white noise of the given share of each column's spread."""
    noisy = clean.copy()
    for column, share in (("x", motion), ("v", motion), ("F", force)):
        noisy[column] = clean[column] + share * clean[column].std() * rng.standard_normal(
            len(clean))
    return noisy


def _idim_ls(frame):
    """Inverse-dynamics least squares, the practice in the field: accelerations from a
    Savitzky-Golay derivative of the measured velocities, then m a + c v + k x + k3 x^3 = F
    solved for (m, c, k, k3)."""
    from scipy.signal import savgol_filter

    dt = float(frame["t"].iloc[1] - frame["t"].iloc[0])
    x, v, force = (frame[c].to_numpy() for c in ("x", "v", "F"))
    a = savgol_filter(v, 31, 3, deriv=1, delta=dt)
    A = np.column_stack([a, v, x, x**3])
    m, c, k, k3 = np.linalg.lstsq(A, force, rcond=None)[0]
    return {"m": m, "c_x": c, "k": k, "k3": k3}


def _relative_errors(estimates):
    return np.array([abs(estimates[name] / value - 1) for name, value in DUFFING_TRUTH.items()])


@pytest.mark.slow
def test_with_noise_the_fit_errs_at_most_a_third_of_inverse_dynamics_least_squares(
        duffing_model):
    clean = hamid.simulate(duffing_system())
    rng = np.random.default_rng(11)
    ours, theirs = [], []
    for _ in range(4):
        noisy = _noisy(clean, rng)
        ours.append(_relative_errors(hamid.fit(noisy, duffing_model,
                                               damping="viscous").estimates))
        theirs.append(_relative_errors(_idim_ls(noisy)))
    ours_rms, theirs_rms = (np.sqrt(np.mean(np.square(e), axis=0)) for e in (ours, theirs))
    assert np.all(ours_rms <= theirs_rms / 3), (ours_rms, theirs_rms)


def _coverage(duffing_model, force_noise):
    """The share of 95% intervals of the four parameters that hold the simulated values,
    over 100 realizations of the noise (1% on the motion)."""
    system = duffing_system()
    system["simulate"] = {"t_end": 40.0, "dt": 0.02}
    clean = hamid.simulate(system)
    rng = np.random.default_rng(2026)
    covered, total = 0, 0
    for _ in range(100):
        result = hamid.fit(_noisy(clean, rng, force=force_noise), duffing_model,
                           damping="viscous")
        for p in result.parameters:
            covered += p.ci_low <= DUFFING_TRUTH[p.name] <= p.ci_high
            total += 1
    return covered / total


@pytest.mark.slow
def test_with_a_clean_force_the_95_percent_intervals_cover_the_truth(duffing_model):
    assert 0.90 <= _coverage(duffing_model, 0.0) <= 0.98


@pytest.mark.slow
def test_with_a_noisy_force_the_95_percent_intervals_cover_the_truth(duffing_model):
    assert 0.90 <= _coverage(duffing_model, 0.002) <= 0.98


def _run(*args):
    import subprocess

    from tests.helpers import hamid_command

    return subprocess.run([*hamid_command(), *map(str, args)], capture_output=True, text=True)


def test_the_report_names_the_inputs_their_work_and_the_scale(duffing_model, tmp_path):
    data = tmp_path / "driven.csv"
    hamid.simulate(duffing_system()).rename(columns={"F": "load"}).to_csv(data, index=False)
    out = tmp_path / "fit.json"
    done = _run("fit", data, "--model", duffing_model, "--damping", "viscous",
                "--columns", "F=load", "-o", out)
    assert done.returncode == 0, done.stderr
    import json

    report = json.loads(out.read_text())
    assert report["data"]["inputs"] == {"F": "load"}
    assert report["data"]["forcing"]["work"] == "F*x"
    assert 0.5 < report["data"]["forcing"]["input_work_fraction"] <= 1
    assert report["method"]["scale"] == {"source": "input", "by": "F*x", "per_unit_mass": False}
    assert report["model"]["forcing"] == {"inputs": ["F"], "work": "F*x", "parameters": []}
    table = _run("report", out)
    assert "from the recorded input (work F*x): physical units" in table.stdout
    assert "F (column load); work F*x" in table.stdout


def test_a_free_decay_keeps_its_scale_from_the_energy():
    result = hamid.fit(hamid.simulate("sample_data/duffing.toml"))
    assert result.method["scale"]["source"] == "energy"


@pytest.mark.parametrize(("change", "words"), [
    (lambda f: f.drop(columns="F"), ["no column for input 'F'", "--columns F=COL"]),
    (lambda f: f.assign(F=1.5), ["input 'F'", "is constant"]),
    (lambda f: f.assign(F=f["F"].where(f.index % 2 == 0)),
     ["input 'F'", "missing in 4,000 of 8,001 rows", "another rate"]),
    (lambda f: f.assign(F=np.nan), ["input 'F'", "is empty"]),
])
def test_a_bad_input_column_is_named_in_one_line(duffing_model, tmp_path, change, words):
    from tests.helpers import one_line_error

    data = tmp_path / "driven.csv"
    change(hamid.simulate(duffing_system())).to_csv(data, index=False)
    out = tmp_path / "fit.json"
    done = _run("fit", data, "--model", duffing_model, "--damping", "viscous", "-o", out)
    one_line_error(done, 1, *words)
    assert not out.exists()


def test_a_few_missing_input_samples_are_missing_like_the_motions(duffing_model):
    """Missing input values drop their rows as missing motion does; the record goes on
    across them (one energy level), the input integrated across the longer step."""
    data = hamid.simulate(duffing_system())
    data.loc[[3000, 6000], "F"] = np.nan
    result = hamid.fit(data, duffing_model, damping="viscous")
    assert len(result.energy_levels) == 1
    assert result.energy_levels[0].n_samples == len(data) - 2
    assert result.estimates == pytest.approx(DUFFING_TRUTH, rel=1e-5)


def test_an_input_that_does_no_work_is_a_warning(tmp_path):
    model = tmp_path / "model.toml"
    model.write_text('[model]\nbuiltin = "duffing"\n\n[forcing]\ninputs = ["F"]\n'
                     'work = "b*F*x"\nparameters = ["b"]\n')
    data = hamid.simulate("sample_data/duffing.toml")
    data["F"] = 1e-6 * np.random.default_rng(0).standard_normal(len(data))
    result = hamid.fit(data, model)
    assert any("makes up" in w and "explains almost nothing" in w for w in result.warnings)


def test_a_driven_fit_predicts_a_recording_of_another_input(duffing_model):
    """Fitted on one multisine, the model predicts the response to a sweep it never saw,
    from the start state fitted to its first period, to the integration's accuracy."""
    result = hamid.fit(hamid.simulate(duffing_system()), duffing_model, damping="viscous")
    other = duffing_system()
    other["forcing"]["signals"]["F"] = {"kind": "sweep", "amplitude": 1.2, "f0": 0.1,
                                        "f1": 0.8}
    other["initial"] = [{"x": 0.3, "v": -0.2}]
    unseen = hamid.simulate(other)
    predicted = result.predict(unseen)
    amplitude = unseen["x"].abs().max()
    assert predicted.channels.loc["x", "rms"] < 1e-5 * amplitude
    from_rest = result.predict(unseen, from_rest=True)   # it did not start at rest
    assert from_rest.channels.loc["x", "rms"] > 100 * predicted.channels.loc["x", "rms"]


def test_a_driven_fit_needs_a_time_column(duffing_model):
    from hamid.errors import UsageError

    data = hamid.simulate(duffing_system()).drop(columns="t")
    with pytest.raises(UsageError, match=r"^a \[forcing\] needs a time column"):
        hamid.fit(data, duffing_model)


def test_a_driven_fit_is_refused_in_chunks(duffing_model, tmp_path):
    from hamid.errors import UsageError

    data = tmp_path / "driven.csv"
    hamid.simulate(duffing_system()).to_csv(data, index=False)
    with pytest.raises(UsageError, match="the model's forcing needs the data in memory"):
        hamid.fit(data, duffing_model, chunk_rows=500)


def test_a_recorded_input_near_the_nyquist_frequency_is_a_warning(duffing_model):
    from hamid.data import measurement
    from hamid.data.records import Records

    data = hamid.simulate(duffing_system())
    rng = np.random.default_rng(0)
    # white noise as strong as the force: a fifth of the noise's power, a tenth of the
    # input's, lies in the top fifth of the band up to the Nyquist frequency 50 Hz
    data["F"] += data["F"].std() * rng.standard_normal(len(data))
    result = hamid.fit(data, duffing_model, damping="viscous", method="joint")
    [warning] = [w for w in result.warnings if "Nyquist" in w]
    share = float(warning.split(" has ")[1].split("%")[0])
    assert 8 < share < 12, warning
    assert warning.startswith("input 'F' has ") and "Nyquist frequency 50 Hz" in warning
    t = np.arange(4000) * 0.01
    records = Records(np.zeros((len(t), 2)), t, np.zeros(len(t), np.int64), (1,))
    for values, expected in ((np.sin(2 * np.pi * 1.0 * t), None),
                             (np.sin(2 * np.pi * 30.0 * t), None),
                             (rng.standard_normal(len(t)), "white"),
                             (np.sin(2 * np.pi * 45.0 * t), "45 Hz")):
        warning = measurement.nyquist_warning("F", values, records)
        if expected is None:
            assert warning is None
        elif expected == "white":   # a fifth of its power above 40 Hz, up to the top
            assert 17 < float(warning.split(" has ")[1].split("%")[0]) < 23, warning
            assert "up to 49.75 Hz" in warning or "up to 50 Hz" in warning, warning
            assert "(dt = 0.01 s)" in warning
        else:   # all of it, at 45 Hz (the top said is its bin's, 0.25 Hz wide)
            assert " has 100% of its power above 40 Hz, up to 45.25 Hz," in warning, warning
