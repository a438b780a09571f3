"""Noisy lab data: noise estimation, noise weighting, velocities derived from positions."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import PENG, with_noise

import hamid
from hamid.errors import DataError, UsageError
from hamid.measurement import estimate_noise

VARIABLES = ["u1", "u2", "v1", "v2"]


@pytest.mark.parametrize("relative", [0.005, 0.01, 0.03, 0.05])
def test_noise_estimate_within_15_percent(clean_records, relative):
    clean = clean_records["peng-quadratic"]
    noisy = with_noise(clean, relative, seed=11)
    bounds = [(0, 801), (801, 1602)]
    sigma = estimate_noise(noisy[VARIABLES].to_numpy(), bounds)
    truth = np.array([relative * clean[c].std() for c in VARIABLES])
    assert sigma == pytest.approx(truth, rel=0.15)


def test_noise_estimate_ignores_a_few_outliers(clean_records):
    clean = clean_records["peng-quadratic"]
    noisy = with_noise(clean, 0.01, seed=12)
    noisy.loc[[100, 500, 900], "u1"] += 5.0
    sigma = estimate_noise(noisy[VARIABLES].to_numpy(), [(0, 801), (801, 1602)])
    assert sigma[0] == pytest.approx(0.01 * clean["u1"].std(), rel=0.15)


def test_auto_noise_is_reported(clean_records):
    noisy = with_noise(clean_records["peng-quadratic"], 0.01, seed=13)
    result = hamid.fit(noisy, noise="auto")
    assert result.method["weighting"] == "noise"
    assert set(result.method["noise"]) == set(VARIABLES)
    assert result.method["weighting_rounds"] >= 2
    truth = {c: 0.01 * clean_records["peng-quadratic"][c].std() for c in VARIABLES}
    assert result.method["noise"] == pytest.approx(truth, rel=0.15)


def test_noise_given_by_file_column_name(clean_records):
    frame = with_noise(clean_records["duffing"], 0.01, seed=14).rename(columns={"x": "pos"})
    result = hamid.fit(frame, "duffing", columns={"x": "pos"}, noise={"pos": 0.003, "v": 0.004})
    assert result.method["noise"] == {"x": 0.003, "v": 0.004}


@pytest.mark.parametrize("noise, message", [
    ({"nope": 0.1}, "'nope' is not a column of the model"),
    ({"x": -1.0}, "not a non-negative number"),
    ({"x": 0.0, "v": 0.0}, "every column has zero noise"),
    ("loud", "--noise must be none, auto or COL=SIGMA"),
])
def test_bad_noise(clean_records, noise, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], noise=noise)


def test_noise_weighting_helps_with_unequal_trajectories_and_channels():
    """Trajectories of very different energy and channels of very different noise."""
    system = {**PENG, "initial": [{"u1": 0.05, "u2": -0.03, "v1": 0.02, "v2": 0.03},
                                  {"u1": 0.45, "u2": 0.1, "v1": 0.0, "v2": -0.3}],
              "simulate": {"t_end": 60.0, "dt": 0.02}}
    clean = hamid.simulate(system)
    truth = np.array(list(PENG["parameters"].values()))
    sigma = {"u1": 0.004, "u2": 0.001, "v1": 0.001, "v2": 0.006}
    errors = {"plain": [], "weighted": []}
    for seed in range(8):
        rng = np.random.default_rng(seed)
        noisy = clean.copy()
        noisy.attrs = dict(clean.attrs)
        for column, s in sigma.items():
            noisy[column] = clean[column] + s * rng.standard_normal(len(clean))
        for label, noise in (("plain", None), ("weighted", sigma)):
            estimate = np.array(list(hamid.fit(noisy, noise=noise).estimates.values()))
            errors[label].append(np.max(np.abs(estimate / truth - 1)))
    assert np.median(errors["weighted"]) < np.median(errors["plain"]) / 1.2, errors


def test_velocities_from_clean_positions(clean_records):
    positions = clean_records["peng-quadratic"].drop(columns=["v1", "v2"])
    result = hamid.fit(positions, "peng-quadratic", velocity="savgol")
    assert result.estimates == pytest.approx(PENG["parameters"], rel=1e-4)
    assert result.data["velocity_source"] == "savgol"
    assert result.data["velocity_window"] % 2 == 1
    assert any("velocities derived" in w and "window" in w for w in result.warnings)


def test_velocities_from_slightly_noisy_positions(clean_records):
    frame = with_noise(clean_records["peng-quadratic"], 0.001, seed=15)
    positions = frame.drop(columns=["v1", "v2"])
    result = hamid.fit(positions, "peng-quadratic", velocity="savgol", noise="auto")
    assert result.estimates == pytest.approx(PENG["parameters"], rel=0.05)


def test_savgol_needs_even_sampling(clean_records):
    frame = clean_records["duffing"].drop(index=[5])
    with pytest.raises(DataError, match="evenly sampled times; the time step changes at row"):
        hamid.fit(frame, velocity="savgol")


@pytest.mark.parametrize("window, message", [(8, "must be odd"), (5, "larger than --order")])
def test_bad_savgol_window(clean_records, window, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], velocity="savgol", window=window)
