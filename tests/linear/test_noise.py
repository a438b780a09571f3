"""Noisy lab data: noise estimation, noise weighting, velocities derived from positions."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from conftest import DUFFING, PENG, with_noise

import hamid
from hamid.data.measurement import estimate_noise
from hamid.errors import UsageError

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
    """Trajectories of very different energy and channels of very different noise (the
    weighting of the linear fit)."""
    system = {**PENG, "initial": [{"u1": 0.05, "u2": -0.03, "v1": 0.02, "v2": 0.03},
                                  {"u1": 0.45, "u2": 0.1, "v1": 0.0, "v2": -0.3}],
              "simulate": {"t_end": 60.0, "dt": 0.02}}
    clean = hamid.simulate(system)
    truth = np.array(list(PENG["parameters"].values()))
    sigma = {"u1": 0.004, "u2": 0.001, "v1": 0.001, "v2": 0.006}
    errors = {"plain": [], "weighted": []}
    for seed in range(24):   # 8 were too few: a ratio of 1.5 came out 1.1
        rng = np.random.default_rng(seed)
        noisy = clean.copy()
        noisy.attrs = dict(clean.attrs)
        for column, s in sigma.items():
            noisy[column] = clean[column] + s * rng.standard_normal(len(clean))
        for label, noise in (("plain", None), ("weighted", sigma)):
            fitted = hamid.fit(noisy, noise=noise, method="joint")
            estimate = np.array(list(fitted.estimates.values()))
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


def test_savgol_windows_over_missing_frames_fit_the_polynomial_at_the_samples_times():
    """Where a window spans missing frames (or uneven steps), the derivative is that of
    the least-squares polynomial through the window's samples at their own times: on even
    windows the same as scipy's Savitzky-Golay filter, and as accurate across the gaps."""
    from scipy.signal import savgol_filter

    from hamid.data.measurement import savgol_velocities

    t = np.arange(0, 20, 0.05)
    Q = np.column_stack([np.sin(1.3 * t), np.cos(0.7 * t)])
    exact = np.column_stack([1.3 * np.cos(1.3 * t), -0.7 * np.sin(0.7 * t)])
    V, _ = savgol_velocities(Q, t, [(0, len(t))], window=21, order=4)
    scipy_filter = savgol_filter(Q, 21, 4, deriv=1, delta=0.05, axis=0, mode="interp")
    assert np.max(np.abs(V - scipy_filter)) < 1e-12
    kept = np.setdiff1d(np.arange(len(t)), [5, 100, 101, 250, 393])
    holed, _ = savgol_velocities(Q[kept], t[kept], [(0, len(kept))], window=21, order=4)
    worst = np.max(np.abs(V - exact))
    assert np.max(np.abs(holed - exact[kept])) <= 1.5 * worst
    jittered = t + 0.01 * np.random.default_rng(1).uniform(-1, 1, len(t)) * 0.05
    V_jittered, _ = savgol_velocities(np.column_stack([np.sin(1.3 * jittered),
                                                       np.cos(0.7 * jittered)]),
                                      jittered, [(0, len(t))], window=21, order=4)
    assert np.max(np.abs(V_jittered - np.column_stack([1.3 * np.cos(1.3 * jittered),
                                                       -0.7 * np.sin(0.7 * jittered)]))
                  ) <= 1.5 * worst


def test_savgol_fits_a_record_with_missing_frames(clean_records):
    frame = with_noise(clean_records["duffing"], 0.001, seed=4)
    frame.loc[[40, 200, 201], "x"] = np.nan
    result = hamid.fit(frame.drop(columns="v"), velocity="savgol")
    assert result.estimates == pytest.approx(DUFFING["parameters"], rel=0.02)
    assert result.to_dict()["data"]["n_trajectories"] == 2


@pytest.mark.parametrize("window, message", [(8, "must be odd"), (5, "larger than --order")])
def test_bad_savgol_window(clean_records, window, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], velocity="savgol", window=window)


def test_hermite_estimates_are_unbiased():
    from hamid.linear.adjust import unbiased
    from hamid.model.expressions import Polynomial

    x = np.array([0.7, -1.3])
    sigma = np.array([0.3, 0.2])
    poly = Polynomial.from_terms({(3, 0): 1.0, (2, 2): -0.5, (0, 4): 2.0}, ("a", "b"))
    exact = x[0] ** 3 - 0.5 * x[0] ** 2 * x[1] ** 2 + 2.0 * x[1] ** 4
    Y = x + sigma * np.random.default_rng(0).standard_normal((400_000, 2))
    adjusted = unbiased(poly, Y, sigma)
    plain = poly(Y)
    standard_error = adjusted.std() / np.sqrt(len(Y))
    assert abs(adjusted.mean() - exact) < 4 * standard_error
    assert abs(plain.mean() - exact) > 20 * standard_error  # the bias it removes


@pytest.mark.parametrize("kwargs, message", [
    ({"bias_correct": True}, "--bias-correct needs --noise"),
    ({"bias_correct": True, "noise": "auto", "cov": "bootstrap"}, "cannot be combined"),
    ({"bias_correct": True, "noise": "auto", "damping": "viscous"}, "does not yet handle"),
    ({"bias_correct": True, "noise": "auto", "velocity": "savgol"}, "measured velocities"),
])
def test_bias_correction_refusals(clean_records, kwargs, message):
    frame = with_noise(clean_records["duffing"], 0.01, seed=16)
    with pytest.raises(UsageError, match=message):
        hamid.fit(frame, **kwargs)


def test_bias_correction_refuses_non_polynomial_energies(clean_records):
    frame = with_noise(clean_records["pendulum"], 0.01, seed=17)
    with pytest.raises(UsageError, match="needs a polynomial energy"):
        hamid.fit(frame, noise="auto", bias_correct=True)


@pytest.mark.parametrize("method", ["energy", "joint"])
def test_bias_correction_keeps_clean_data_exact(clean_records, method):
    frame = clean_records["peng-quadratic"]
    result = hamid.fit(frame, method=method, noise={"u1": 1e-3, "v1": 1e-3},
                       bias_correct=True)
    assert result.method["bias_correction"] is True
    # Clean data with noise declared: the correction itself is tiny (order sigma^2).
    assert result.estimates == pytest.approx(PENG["parameters"], rel=2e-3)


@pytest.mark.slow
def test_bias_correction_removes_the_noise_bias():
    """5% noise, 100 realizations: |mean bias| < spread / 3 with the correction, for the
    energy rows and the default method, while plain energy rows show the bias; 95% bounds
    cover the truth in 85-99% of realizations with the correction."""
    clean = hamid.simulate({**PENG, "simulate": {"t_end": 60.0, "dt": 0.02}})
    truth = np.array(list(PENG["parameters"].values()))
    sigma = {c: 0.05 * clean[c].std() for c in VARIABLES}
    runs = {"energy plain": ("energy", False), "energy": ("energy", True),
            "auto": ("auto", True)}
    estimates = {k: [] for k in runs}
    covered = {k: [] for k in runs}
    for seed in range(1000, 1100):
        noisy = with_noise(clean, 0.05, seed)
        for label, (method, correct) in runs.items():
            result = hamid.fit(noisy, method=method, noise=sigma, bias_correct=correct)
            estimates[label].append(list(result.estimates.values()))
            covered[label].append([p.ci_low <= t <= p.ci_high
                                   for p, t in zip(result.parameters, truth, strict=True)])
    for label in runs:
        relative = np.array(estimates[label]) / truth - 1
        ratio = relative.mean(axis=0) / relative.std(axis=0)
        coverage = np.mean(covered[label], axis=0)
        if label == "energy plain":
            assert np.all(np.abs(ratio[:2]) > 1), ratio  # stiffness terms visibly biased
        else:
            assert np.all(np.abs(ratio) < 1 / 3), (label, ratio)
            assert np.all((coverage >= 0.85) & (coverage <= 0.99)), (label, coverage)


def test_a_recording_of_positions_alone_is_fitted_without_an_option(clean_records,
                                                                    tmp_path):
    """No velocity column at all: the velocities are derived (as --velocity savgol), the
    refinement fits the positions alone, and the note says so; the intervals hold the
    truth and are at most twice as wide as with the velocities recorded."""
    frame = with_noise(clean_records["duffing"], 0.01, seed=3)
    positions = hamid.fit(frame.drop(columns="v"))
    both = hamid.fit(frame)
    assert any("no velocity column for any coordinate: the velocities are derived" in w
               for w in positions.warnings)
    assert positions.method["refinement"]["noise"]["v"]["source"] == "derived"
    for p, q in zip(positions.parameters, both.parameters, strict=True):
        assert p.ci_low <= DUFFING["parameters"][p.name] <= p.ci_high, p
        assert p.stderr <= 2 * q.stderr, (p.name, p.stderr / q.stderr)
    assert positions.estimates == hamid.fit(frame.drop(columns="v"),
                                            velocity="savgol").estimates
    path = tmp_path / "encoder.csv"
    frame.drop(columns="v").to_csv(path, index=False)
    from tests.helpers import hamid_command

    done = subprocess.run([*hamid_command(), "fit", str(path), "--model", "duffing",
                           "--format", "json"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "derived from the positions" in done.stderr


def test_a_coordinate_without_its_velocity_has_that_one_derived(clean_records):
    """Each coordinate keeps what it records (issue 36): u2's velocity is derived from its
    positions, u1's measured one stays and is fitted."""
    frame = clean_records["peng-quadratic"].drop(columns="v2")
    result = hamid.fit(frame, "peng-quadratic")
    assert result.data["channels"]["u2"] == {"recorded": ["position"],
                                             "reconstructed": ["velocity"]}
    assert result.data["channels"]["u1"]["reconstructed"] == []
    assert any("no velocity column for u2" in w for w in result.warnings)
    noise = result.method["refinement"]["noise"]
    assert noise["v2"]["sigma"] is None and noise["v1"]["sigma"] is not None
