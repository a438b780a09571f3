"""What the sensors give: recordings of velocities only or accelerations only (issue 36).

The truth is a simulated damped Duffing oscillator x'' = -k x - k3 x^3 - c x' with known
parameters; its accelerations are computed from that equation at the simulated states.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import jsonschema
import numpy as np
import pandas as pd
import pytest
from conftest import with_noise
from helpers import hamid_command, one_line_error

import hamid
from hamid.data import column_roles, measurement
from hamid.errors import DataError, ModelError
from hamid.model.names import acceleration_name

HAMID = hamid_command()
SCHEMA = Path(__file__).parent.parent.parent / "hamid" / "schema" / "fit-1.json"
TRUTH = {"k": 1.0, "k3": 0.5, "c_x": 0.05}
DAMPED = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
          "damping": {"c_x": 0.05},
          "initial": [{"x": 1.0, "v": 0.0}, {"x": 0.4, "v": 0.3}],
          "simulate": {"t_end": 30.0, "dt": 0.05}}
G = 9.80665   # m/s^2 per g, written out here rather than read from hamid
NOISE = 0.01  # of each channel's standard deviation


@pytest.fixture(scope="module")
def clean() -> pd.DataFrame:
    return hamid.simulate(DAMPED)


def _accelerations(clean: pd.DataFrame) -> np.ndarray:
    x, v = clean["x"].to_numpy(), clean["v"].to_numpy()
    return -TRUTH["k"] * x - TRUTH["k3"] * x**3 - TRUTH["c_x"] * v


def _in_g(clean: pd.DataFrame, seed: int) -> pd.DataFrame:
    """The accelerations alone, in g, with white noise of NOISE times their spread."""
    a = _accelerations(clean)
    noisy = a + NOISE * a.std() * np.random.default_rng(1000 + seed).standard_normal(len(a))
    return clean[["trajectory", "t"]].assign(a_g=noisy / G)


def _worst(result) -> float:
    """The largest error of a parameter, relative to its true value."""
    return max(abs(p.estimate - TRUTH[p.name]) / TRUTH[p.name] for p in result.parameters)


def _within(result, many: float) -> None:
    for p in result.parameters:
        assert abs(p.estimate - TRUTH[p.name]) < many * p.stderr, (p.name, p.estimate, p.stderr)


# --- names and columns ------------------------------------------------------------------

@pytest.mark.parametrize(("velocity", "expected"), [
    ("v", "a"), ("v1", "a1"), ("vx", "ax"), ("omega", "alpha"), ("x_dot", "x_ddot"),
    ("xdot", "xddot"), ("dx", "ddx")])
def test_acceleration_names_follow_the_velocities(velocity, expected):
    assert acceleration_name(velocity) == expected


@pytest.mark.parametrize(("column", "factor"), [
    ("a", 1.0), ("a_g", G), ("a [g]", G), ("a_m_s2", 1.0), ("a [m/s^2]", 1.0),
    ("a (mm/s²)", 1e-3), ("acc_x", 1.0), ("ax_g", G)])
def test_an_acceleration_is_found_by_name_and_unit(column, factor):
    found = column_roles.resolve_columns(["t", column], ["x"], ["v"], accelerations=["a"],
                                         partial=True, source="run.csv")
    assert found == {"a": column}
    assert column_roles.column_scale(column)[0] == pytest.approx(factor, rel=1e-12)


def test_each_coordinate_keeps_what_it_records():
    found = column_roles.resolve_columns(
        ["t", "x1", "v2", "a2_g", "alpha3"], ["x1", "x2", "theta3"], ["v1", "v2", "omega3"],
        accelerations=["a1", "a2", "alpha3"], partial=True, source="run.csv")
    assert found == {"x1": "x1", "v2": "v2", "a2": "a2_g", "alpha3": "alpha3"}


def test_a_coordinate_without_any_channel_is_named():
    with pytest.raises(DataError, match=r"no column for coordinate 'y': no position, velocity "
                                        r"or acceleration"):
        column_roles.resolve_columns(["t", "x", "vx"], ["x", "y"], ["vx", "vy"],
                                     accelerations=["ax", "ay"], partial=True, source="r.csv")


@pytest.mark.parametrize("column", ["a [ft/s2]", "a_ft_s2", "a_mm"])
def test_an_acceleration_in_an_unknown_unit_is_an_error(column):
    with pytest.raises(DataError, match="is not an acceleration's"):
        column_roles.resolve_columns(["t", "x", column], ["x"], ["v"], accelerations=["a"],
                                     partial=True, source="run.csv")


def test_a_model_file_names_its_accelerations(tmp_path, clean):
    path = tmp_path / "m.toml"
    path.write_text('[model]\ncoordinates = ["x"]\nvelocities = ["v"]\n'
                    'accelerations = ["acc"]\nenergy = "v**2/2 + k*x**2/2 + k3*x**4/4"\n')
    assert hamid.load_model(path).acceleration_names == ("acc",)
    frame = _in_g(clean, 0).rename(columns={"a_g": "acc [g]"})
    result = hamid.fit(frame, model=str(path), damping="viscous")
    assert result.data["columns"]["acc"] == "acc [g]"
    path.write_text('[model]\ncoordinates = ["x"]\nvelocities = ["v"]\n'
                    'accelerations = ["a", "b"]\nenergy = "v**2/2 + k*x**2/2"\n')
    with pytest.raises(ModelError, match="1 coordinates but 2 accelerations"):
        hamid.load_model(path)


# --- reconstruction ---------------------------------------------------------------------

def test_integration_recovers_a_known_motion_across_missing_samples():
    """x = exp(-0.03 t) cos(2 t) + 0.3 (an offset), integrated from its exact rate with 3% of
    the samples missing and a bias of the rate added: back within 1% of its amplitude,
    about zero (the offset, the bias' drift and the unknown start gone)."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 40.0, 0.02)
    t = t[rng.random(len(t)) > 0.03]
    x = np.exp(-0.03 * t) * np.cos(2 * t)
    rate = np.exp(-0.03 * t) * (-0.03 * np.cos(2 * t) - 2 * np.sin(2 * t)) + 0.05
    values = measurement.integrated(rate[:, None], t, [(0, len(t))])[:, 0]
    assert np.max(np.abs(values - x)) < 0.01


def test_a_rate_of_fewer_than_two_cycles_loses_a_straight_line():
    """cos t over 1.7 periods (three sign changes, one whole cycle between them): its
    integral sin t less the least-squares line through it, as for any rate of fewer than
    two cycles (a single cycle mean would leave the ends without a slope)."""
    t = np.linspace(0.0, 3.4 * np.pi, 500)
    values = measurement.integrated(np.cos(t)[:, None], t, [(0, len(t))])[:, 0]
    line = np.polyval(np.polyfit(t, np.sin(t), 1), t)
    assert np.max(np.abs(values - (np.sin(t) - line))) < 1e-4


# --- fits from what was recorded --------------------------------------------------------

def test_velocities_alone_are_fitted_with_no_option(clean):
    result = hamid.fit(with_noise(clean, NOISE, 0).drop(columns=["x"]), model="duffing",
                       damping="viscous")
    assert result.data["channels"] == {"x": {"recorded": ["velocity"],
                                             "reconstructed": ["position"]}}
    refinement = result.method["refinement"]
    assert refinement["applied"]
    assert refinement["noise"]["x"]["sigma"] is None   # positions not fitted
    assert any("no position column for any coordinate" in w for w in result.warnings)
    _within(result, 4)


def test_an_unrefined_fit_from_integrated_positions_says_its_intervals_are_short(clean):
    """--method weak does not refine: the estimates are the linear fit's on positions
    integrated from the velocities, whose intervals leave out the integration's errors;
    the refined fit does not say so. The note on the channels speaks of a refinement only
    where one follows (not under --method weak, nor --cov classical)."""
    recorded = with_noise(clean, NOISE, 0).drop(columns=["x"])
    warning = ("the estimates are the linear fit's, on positions integrated from the "
               "recorded channels (x): their intervals do not hold the integration's errors")
    weak = hamid.fit(recorded, model="duffing", damping="viscous", method="weak")
    assert weak.method["refinement"] is None
    assert any(w.startswith(warning) for w in weak.warnings), weak.warnings
    assert ("<DataFrame>: no position column for any coordinate: positions integrated from "
            "the velocities for the linear fit (less their cycle means)") in weak.warnings
    classical = hamid.fit(recorded, model="duffing", damping="viscous", cov="classical")
    assert classical.method["refinement"]["applied"] is False   # the linear fit's asked for
    assert ("<DataFrame>: no position column for any coordinate: positions integrated from "
            "the velocities for the linear fit (less their cycle means)") in classical.warnings
    refined = hamid.fit(recorded, model="duffing", damping="viscous")
    assert not any(w.startswith(warning) for w in refined.warnings)
    assert ("<DataFrame>: no position column for any coordinate: positions integrated from "
            "the velocities for the linear start (less their cycle means); the trajectory "
            "refinement fits the recorded velocities") in refined.warnings


def test_an_unrefined_fit_says_its_loose_energy_rows_with_the_integration(clean_records):
    """Clean peng-quadratic velocities, positions integrated, --method weak: its energy
    rows' residuals are autocorrelated (the integration's errors, smooth), said in the note
    on the integrated positions, not as advice that the model misses a term."""
    recorded = clean_records["peng-quadratic"].drop(columns=["u1", "u2"])
    weak = hamid.fit(recorded, model="peng-quadratic", method="weak")
    (note,) = [w for w in weak.warnings if w.startswith("the estimates are the linear fit's")]
    assert "; its energy rows fit them loosely (residuals autocorrelated at lag 1" in note
    assert "the integration's errors as much as the model's" in note
    assert not any("the model misses part of the motion" in w for w in weak.warnings)


def test_accelerations_alone_in_g_are_fitted_by_the_refinement(clean):
    result = hamid.fit(_in_g(clean, 0), model="duffing", damping="viscous")
    assert result.data["channels"] == {"x": {"recorded": ["acceleration"],
                                             "reconstructed": ["position", "velocity"]}}
    refinement = result.method["refinement"]
    assert refinement["applied"]
    noise = refinement["noise"]
    assert noise["x"]["sigma"] is None and noise["v"]["sigma"] is None
    # the level estimated from differences: NOISE of the spread, in m/s^2 (not g)
    a = _accelerations(clean)
    assert noise["a"]["sigma"] == pytest.approx(NOISE * a.std(), rel=0.15)
    _within(result, 4)


def test_accelerations_beside_positions_are_fitted_too(clean):
    frame = with_noise(clean, NOISE, 0).drop(columns=["v"]).assign(
        a_g=_in_g(clean, 0)["a_g"])
    result = hamid.fit(frame, model="duffing", damping="viscous")
    assert result.data["channels"]["x"] == {"recorded": ["position", "acceleration"],
                                            "reconstructed": ["velocity"]}
    noise = result.method["refinement"]["noise"]
    assert noise["x"]["sigma"] is not None and noise["a"]["sigma"] is not None
    assert noise["v"]["sigma"] is None
    _within(result, 4)


def _alone(clean: pd.DataFrame, seed: int, channel: str) -> pd.DataFrame:
    """One realization of the recording, of `channel` alone: "velocity", or "acceleration"
    (in g, its own noise draw)."""
    if channel == "velocity":
        return with_noise(clean, NOISE, seed).drop(columns=["x"])
    return _in_g(clean, seed)


@pytest.mark.parametrize("channel", ["velocity", "acceleration"])
def test_the_worst_errors_of_one_channel_over_seeds(clean, channel):
    """Each seed within 4 standard errors; the median over seeds of the worst relative
    error within 4x that of the full recording (positions and velocities) of the same
    motion."""
    ratios = []
    for seed in range(5):
        both = hamid.fit(with_noise(clean, NOISE, seed), model="duffing", damping="viscous")
        alone = hamid.fit(_alone(clean, seed, channel), model="duffing", damping="viscous")
        _within(alone, 4)
        ratios.append(_worst(alone) / _worst(both))
    assert np.median(ratios) <= 4, ratios


@pytest.mark.slow
@pytest.mark.parametrize("channel", ["velocity", "acceleration"])
def test_intervals_from_one_channel_cover(clean, channel, realizations=300):
    """The issue's target, 95% intervals covering 90-98% of realizations, for each parameter.

    Over 300 realizations rather than 100: the coverage of 100 honest intervals spreads
    by 2.2 points (binomial), so a window of 90-98 fails by chance about one parameter in
    ten. Measured so (issue 36): over six blocks of 100 realizations, k from velocities
    alone covered 89, 96, 92, 94, 98 and 96; the first block (seeds 0-99, this test's
    first) was the 89 a past session took for intervals too narrow, and the full
    recording's own blocks ranged 91-97. Over 600 realizations the errors' root mean
    square was 1.03, 1.02 and 0.95 stated standard errors (k, k3, c) from velocities
    alone, 0.99, 0.99 and 1.04 from accelerations alone and 1.01, 1.01 and 1.00 from the
    full recording (each uncertain by 0.03), their means within 0.05: the stated errors
    are the spread, and no bias shows."""
    hits = dict.fromkeys(TRUTH, 0)
    for seed in range(realizations):
        result = hamid.fit(_alone(clean, seed, channel), model="duffing", damping="viscous")
        for p in result.parameters:
            hits[p.name] += p.ci_low <= TRUTH[p.name] <= p.ci_high
    for name, count in hits.items():
        assert 0.90 <= count / realizations <= 0.98, (name, count)


# --- the command line -------------------------------------------------------------------

def test_the_report_lists_the_channels_and_passes_its_schema(tmp_path, clean):
    path = tmp_path / "vibrometer.csv"
    with_noise(clean, NOISE, 0).drop(columns=["x"]).to_csv(path, index=False)
    done = subprocess.run([*HAMID, "fit", str(path), "--model", "duffing", "--damping",
                           "viscous", "--format", "json"], capture_output=True, text=True,
                          check=False, timeout=600)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["data"]["channels"]["x"] == {"recorded": ["velocity"],
                                               "reconstructed": ["position"]}
    jsonschema.Draft202012Validator(json.loads(SCHEMA.read_text())).validate(report)
    done = subprocess.run([*HAMID, "fit", str(path), "--model", "duffing", "--damping",
                           "viscous", "--format", "table"], capture_output=True, text=True,
                          check=False, timeout=600)
    assert "recorded x: velocity (position reconstructed)" in " ".join(done.stdout.split())


@pytest.mark.parametrize(("columns", "words"), [
    ({"t": [0, 1, 2, 3], "y": [1, 2, 3, 4]}, ["coordinate 'x'", "no position"]),
    ({"t": [0, 1, 2, 3], "a [ft/s2]": [1, 2, 3, 4]}, ["'a [ft/s2]'", "acceleration"]),
    ({"t": np.arange(8.0), "x": [1, "", 2, "", 3, "", 4, ""], "v": ["", 1, "", 2, "", 3, "", 4]},
     ["coordinate 'x'", "different times"]),
])
def test_bad_channels_are_one_line_errors(tmp_path, columns, words):
    path = tmp_path / "bad.csv"
    pd.DataFrame(columns).to_csv(path, index=False)
    out = tmp_path / "out.json"
    done = subprocess.run([*HAMID, "fit", str(path), "--model", "duffing", "--output",
                           str(out)], capture_output=True, text=True, check=False, timeout=600)
    one_line_error(done, 1, *words)
    assert not out.exists()


def test_a_two_mass_system_from_one_channel(tmp_path):
    """Two masses on springs (conftest.TWO_MASS, the second mass unknown), at 1% noise:
    velocities alone and accelerations alone (in g, from the equations at the simulated
    states) each within 4 standard errors, the median over seeds of their worst error
    within 4x the full recording's."""
    from conftest import TWO_MASS

    clean = hamid.simulate(TWO_MASS)
    truth = TWO_MASS["parameters"]
    path = tmp_path / "two_mass.toml"
    path.write_text('[model]\ncoordinates = ["x1", "x2"]\nvelocities = ["v1", "v2"]\n'
                    f'energy = "{TWO_MASS["model"]["energy"]}"\n')
    x1, x2 = clean["x1"].to_numpy(), clean["x2"].to_numpy()
    pull = truth["k2"] * (x2 - x1) + truth["k3"] * (x2 - x1) ** 3
    accelerations = {"a1_g": -truth["k1"] * x1 + pull, "a2_g": -pull / truth["m"]}

    def worst(result) -> float:
        for p in result.parameters:
            assert abs(p.estimate - truth[p.name]) < 4 * p.stderr, (p.name, p.estimate)
        return max(abs(p.estimate - truth[p.name]) / truth[p.name] for p in result.parameters)

    ratios: dict[str, list[float]] = {"velocity": [], "acceleration": []}
    for seed in range(3):
        full = with_noise(clean, NOISE, seed)
        rng = np.random.default_rng(500 + seed)
        recorded = clean[["trajectory", "t"]].assign(**{
            name: (a + NOISE * a.std() * rng.standard_normal(len(a))) / G
            for name, a in accelerations.items()})
        both = worst(hamid.fit(full, model=str(path)))
        ratios["velocity"].append(
            worst(hamid.fit(full.drop(columns=["x1", "x2"]), model=str(path))) / both)
        ratios["acceleration"].append(worst(hamid.fit(recorded, model=str(path))) / both)
    for channel, values in ratios.items():
        assert np.median(values) <= 4, (channel, values)


def _damped_chain(tmp_path: Path) -> tuple[pd.DataFrame, dict[str, float], str]:
    """Two masses on springs with dampers between the ground and the first and between
    the two (conftest.TWO_MASS, c1 = 0.04, c2 = 0.02, the second mass unknown): its clean
    record, its true parameters and a model file naming them."""
    from conftest import TWO_MASS

    damping = {"dissipation": "c1*v1**2/2 + c2*(v2 - v1)**2/2", "parameters": ["c1", "c2"]}
    truth = {**TWO_MASS["parameters"], "c1": 0.04, "c2": 0.02}
    clean = hamid.simulate({**TWO_MASS, "damping": {**damping, "c1": 0.04, "c2": 0.02}})
    path = tmp_path / "chain.toml"
    path.write_text('[model]\ncoordinates = ["x1", "x2"]\nvelocities = ["v1", "v2"]\n'
                    f'energy = "{TWO_MASS["model"]["energy"]}"\n[damping]\n'
                    f'dissipation = "{damping["dissipation"]}"\nparameters = ["c1", "c2"]\n')
    return clean, truth, str(path)


def _chain_accelerations(clean: pd.DataFrame, truth: dict[str, float],
                         seed: int) -> pd.DataFrame:
    """The damped chain's accelerations alone, in g, from its equations at the simulated
    states, each with noise of NOISE times its spread."""
    x1, x2, v1, v2 = (clean[name].to_numpy() for name in ("x1", "x2", "v1", "v2"))
    pull = (truth["k2"] * (x2 - x1) + truth["k3"] * (x2 - x1) ** 3
            + truth["c2"] * (v2 - v1))
    accelerations = {"a1_g": -truth["k1"] * x1 - truth["c1"] * v1 + pull,
                     "a2_g": -pull / truth["m"]}
    rng = np.random.default_rng(seed)
    return clean[["trajectory", "t"]].assign(**{
        name: (a + NOISE * a.std() * rng.standard_normal(len(a))) / G
        for name, a in accelerations.items()})


@pytest.mark.parametrize("seed", [0, 1, 24, 38])
def test_a_far_start_whose_fit_ends_within_the_noise_is_kept(tmp_path, seed):
    """The damped chain's accelerations alone (`_chain_accelerations`, 1% noise): the
    linear start from them is far off (the mass 0.12 for 2), so the first fit stops where
    its misfit is hopeless and the levels are raised. Seed 0: Levenberg-Marquardt takes
    36 iterations from there (more than the 20 once allowed). Seed 38: 55, damped by how
    well each step foretold its drop (cut tenfold after every good step, every other
    step failed, and 50 did not settle it). Seed 1: the fit ends within the noise of the
    differences (1.04 times it) though fitted at raised levels, and so is fitted at those
    of the differences. Seed 24: a step goes where the motion cannot be integrated, and
    is damped like a step that made the misfit worse (the fit failed there once). Each is
    kept, its errors the misfit-scaled ones."""
    clean, truth, model = _damped_chain(tmp_path)
    recorded = _chain_accelerations(clean, truth, 1000 + seed)
    result = hamid.fit(recorded, model=model)
    refinement = result.method["refinement"]
    assert refinement["applied"] and refinement["covariance"] == "misfit-scaled"
    assert {refinement["noise"][name]["source"] for name in ("a1", "a2")} == {"differences"}
    for p in result.parameters:
        assert abs(p.estimate - truth[p.name]) < 4 * p.stderr, (p.name, p.estimate)
    # the linear start's energy rows, on positions integrated twice, fit loosely: said as
    # theirs, not as advice to change a model the refinement fits within the noise
    assert not any("try another kind of --damping" in w or "explains little" in w
                   for w in result.warnings), result.warnings
    (start,) = [w for w in result.warnings if w.startswith("the linear start's energy rows")]
    assert "positions integrated from the recorded channels (x1, x2)" in start
    assert "the estimates are the trajectory refinement's" in start


@pytest.mark.slow
@pytest.mark.parametrize(("channel", "realizations"), [("velocity", 200),
                                                       ("acceleration", 400)])
def test_intervals_of_a_damped_two_mass_chain_from_one_channel_cover(tmp_path, channel,
                                                                     realizations):
    """The damped chain (`_damped_chain`), 1% noise, velocities alone or accelerations
    alone (in g): the 95% intervals of each of the six parameters cover 90-98% of
    realizations (the coverage of 100 honest intervals spreads by 2.2 points: from the
    accelerations, k1's blocks of 100 covered 98, 99, 95 and 92%, so 400 are counted).
    From the accelerations the linear start is far off (the mass 0.12 for 2: their zero
    crossings follow the fast mode, and the integration's high-pass takes the slow mode's
    cycle means for drift), and every realization must still be refined: a linear fit
    kept has intervals that miss by up to a hundred standard errors."""
    clean, truth, model = _damped_chain(tmp_path)
    hits = dict.fromkeys(truth, 0)
    for seed in range(realizations):
        recorded = (with_noise(clean, NOISE, seed).drop(columns=["x1", "x2"])
                    if channel == "velocity" else _chain_accelerations(clean, truth, seed))
        result = hamid.fit(recorded, model=model)
        assert result.method["refinement"]["applied"], seed
        for p in result.parameters:
            hits[p.name] += p.ci_low <= truth[p.name] <= p.ci_high
    for name, count in hits.items():
        assert 0.90 <= count / realizations <= 0.98, (name, count)
