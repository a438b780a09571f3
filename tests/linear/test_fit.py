"""The energy fit against independent truth: known parameters, statsmodels, the seed paper."""

from __future__ import annotations

import json
import re

import numpy as np
import pandas as pd
import pytest
from conftest import DUFFING, PENG, SYSTEMS, coverage, with_noise

import hamid
import hamid.model.models
from hamid.errors import FitError, UsageError
from hamid.result.fit_result import FitResult

REPORT_KEYS = ["schema", "hamid_version", "model", "data", "method", "parameters",
             "energy_levels", "residuals", "conditioning", "warnings"]


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_clean_data_recover_true_parameters(clean_records, name):
    result = hamid.fit(clean_records[name], method="energy")
    truth = SYSTEMS[name]["parameters"]
    for p in result.parameters:
        assert p.estimate == pytest.approx(truth[p.name], rel=1e-8), p.name
        assert p.truth == truth[p.name]
    assert len(result.energy_levels) == len(SYSTEMS[name]["initial"])


def test_energy_levels_equal_the_simulated_energies(clean_records):
    result = hamid.fit(clean_records["peng-quadratic"])
    simulated = [t["energy"] for t in clean_records["peng-quadratic"].attrs["hamid"]
                 ["trajectories"]]
    assert [h.h for h in result.energy_levels] == pytest.approx(simulated, rel=1e-9)


def test_result_json_has_spec_keys_and_round_trips(clean_records):
    result = hamid.fit(with_noise(clean_records["duffing"], 0.01, seed=1))
    data = result.to_dict()
    assert list(data)[:len(REPORT_KEYS)] == REPORT_KEYS  # docs/output.md: more keys may follow
    assert data["schema"] == "hamid.fit/1"
    text = json.dumps(data, allow_nan=False)
    assert FitResult.from_dict(json.loads(text)) == result
    assert set(data["parameters"][0]) == {"name", "role", "estimate", "stderr", "ci_low",
                                          "ci_high", "truth", "fixed"}
    assert result.estimates == {p["name"]: p["estimate"] for p in data["parameters"]}


def _duffing_design(frame: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The Duffing energy rows written out by hand: y = -E0 = Phi theta - h + r."""
    x, v = frame["x"].to_numpy(), frame["v"].to_numpy()
    groups = frame["trajectory"].to_numpy()
    dummies = (groups[:, None] == np.unique(groups)[None, :]).astype(float)
    return -(v**2) / 2, np.column_stack([x**2 / 2, x**4 / 4, -dummies]), groups


@pytest.mark.parametrize("cov", ["classical", "hc", "hac"])
def test_standard_errors_match_statsmodels(clean_records, cov):
    import statsmodels.api as sm

    frame = with_noise(clean_records["duffing"], 0.01, seed=2)
    result = hamid.fit(frame, cov=cov, method="energy")
    y, X, groups = _duffing_design(frame)
    if cov == "hac":
        bandwidth = int(re.search(r"bandwidth (\d+)",
                                  result.method["covariance_description"]).group(1))
        reference = sm.OLS(y, X).fit(cov_type="hac-panel", cov_kwds={
            "groups": groups, "maxlags": bandwidth, "use_correction": "hac",
            "df_correction": False}, use_t=True)
    else:
        reference = sm.OLS(y, X).fit(cov_type={"classical": "nonrobust", "hc": "HC1"}[cov],
                                     use_t=True)
    assert [p.estimate for p in result.parameters] == pytest.approx(reference.params[:2],
                                                                    rel=1e-9)
    assert [p.stderr for p in result.parameters] == pytest.approx(reference.bse[:2], rel=1e-6)
    assert [h.h for h in result.energy_levels] == pytest.approx(reference.params[2:], rel=1e-9)
    assert [h.stderr for h in result.energy_levels] == pytest.approx(reference.bse[2:],
                                                                     rel=1e-6)
    low, high = reference.conf_int(alpha=0.05)[:2].T
    assert [p.ci_low for p in result.parameters] == pytest.approx(low, rel=1e-6)
    assert [p.ci_high for p in result.parameters] == pytest.approx(high, rel=1e-6)


def test_bootstrap_errors_agree_with_hac_roughly(clean_records):
    frame = with_noise(clean_records["duffing"], 0.01, seed=3)
    hac = hamid.fit(frame, cov="hac", method="energy")
    boot = hamid.fit(frame, cov="bootstrap", bootstrap=200, seed=0, method="energy")
    assert [p.estimate for p in boot.parameters] == [p.estimate for p in hac.parameters]
    for a, b in zip(hac.parameters, boot.parameters, strict=True):
        assert 0.5 < b.stderr / a.stderr < 2.0, a.name
    again = hamid.fit(frame, cov="bootstrap", bootstrap=200, seed=0, method="energy")
    assert [p.stderr for p in again.parameters] == [p.stderr for p in boot.parameters]


def test_fix_holds_a_parameter_and_fits_the_rest(clean_records):
    result = hamid.fit(clean_records["peng-quadratic"], fix={"a6": 0.2, "w1sq": 1.0})
    by_name = {p.name: p for p in result.parameters}
    assert by_name["a6"].fixed and by_name["a6"].estimate == 0.2
    assert by_name["a6"].stderr is None and by_name["a6"].ci_low is None
    assert by_name["a1"].estimate == pytest.approx(0.3, rel=1e-8)
    assert not by_name["a1"].fixed
    assert result.method["fixed"] == {"a6": 0.2, "w1sq": 1.0}


def test_fixing_at_a_wrong_value_moves_the_others(clean_records):
    """k3 held at 0.6 (truth 0.5) on noise-free Duffing data: k takes up what it can of the
    wrong quartic term, by least squares, which numpy gives independently of hamid."""
    frame = clean_records["duffing"]
    x = frame["x"].to_numpy()
    # The energy balance: k - 1 is the slope of -0.1 x^4/4 on x^2/2 within each trajectory
    # (each has its own level h).
    centred = frame.assign(quadratic=x**2 / 2, quartic=x**4 / 4).groupby("trajectory")[
        ["quadratic", "quartic"]].transform(lambda column: column - column.mean())
    (slope,), *_ = np.linalg.lstsq(centred[["quadratic"]].to_numpy(),
                                   -0.1 * centred["quartic"].to_numpy(), rcond=None)
    energy = hamid.fit(frame, fix={"k3": 0.6}, method="energy")
    assert energy.estimates["k"] == pytest.approx(1 + slope, rel=1e-8)
    # The equations of motion, a + 0.6 x^3 = -k x with a = -x - 0.5 x^3: k = 1 - 0.1 <x^4>/<x^2>.
    # The default's trajectory fit weighs the misfit its own way; on these noise-free
    # data its k lies between the two (0.936 < 0.943 < 0.952).
    motion = 1 - 0.1 * np.sum(x**4) / np.sum(x**2)
    default = hamid.fit(frame, fix={"k3": 0.6})
    assert motion < default.estimates["k"] < 1 + slope


MASS_DUFFING = hamid.model.models.model_from_expression(
    "mass-duffing", "m*v**2/2 + k*x**2/2 + k3*x**4/4", ["x"], ["v"])


@pytest.mark.parametrize("method", ["auto", "energy", "weak"])
def test_a_fixed_mass_sets_the_scale_of_an_energy_of_parameters(clean_records, method):
    """m*v**2/2 + k*x**2/2 + k3*x**4/4 with m fixed at 2.5: the unit-mass truth (k = 1,
    k3 = 0.5) times 2.5, as every term of the energy scales with the mass."""
    result = hamid.fit(clean_records["duffing"], MASS_DUFFING, fix={"m": 2.5}, method=method)
    assert result.estimates["m"] == 2.5
    assert result.estimates["k"] == pytest.approx(2.5, rel=1e-6)
    assert result.estimates["k3"] == pytest.approx(1.25, rel=1e-6)


@pytest.mark.parametrize("fix", [{}, {"m": 0.0}])
def test_an_energy_of_parameters_needs_a_fixed_scale(clean_records, fix):
    with pytest.raises(hamid.ModelError, match=r"no parameter-free part .* \(--fix NAME=VALUE"):
        hamid.fit(clean_records["duffing"], MASS_DUFFING, fix=fix)


@pytest.mark.parametrize("fix, message", [
    ({"nope": 1.0}, "'nope' is not a parameter"),
    ({"k": float("nan")}, "not a finite number"),
    ({"k": 1.0, "k3": 0.5}, "every parameter is fixed"),
])
def test_bad_fix_is_a_usage_error(clean_records, fix, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], fix=fix)


def test_term_that_never_varies_is_named(clean_records):
    frame = clean_records["duffing"].copy()
    frame["y"], frame["vy"] = 0.7, 0.0
    model = hamid.model.models.model_from_expression(
        "m", "v**2/2 + vy**2/2 + k*x**2/2 + k3*x**4/4 + c*y**2", ["x", "y"], ["v", "vy"])
    with pytest.raises(FitError, match=r"cannot determine c: its term does not vary"):
        hamid.fit(frame, model, method="energy")


def test_collinear_terms_are_named(clean_records):
    model = hamid.model.models.model_from_expression(
        "m", "v**2/2 + k*x**2/2 + k3*x**4/4 + k2*x**2", ["x"], ["v"])
    with pytest.raises(FitError, match=r"cannot determine k, k2: .*collinear.*rank 2 of 3"):
        hamid.fit(clean_records["duffing"], model)


def test_too_few_samples(clean_records):
    frame = clean_records["peng-quadratic"].iloc[:5]
    with pytest.raises(FitError, match=r"5 rows for 7 unknowns \(6 parameters and 1 energy"):
        hamid.fit(frame)


def test_each_file_is_its_own_trajectory(tmp_path, clean_records):
    frame = clean_records["duffing"]
    paths = []
    for label, part in frame.groupby("trajectory"):
        path = tmp_path / f"run{label}.csv"
        part.drop(columns="trajectory").to_csv(path, index=False)
        paths.append(str(path))
    result = hamid.fit(paths, "duffing")
    assert [h.trajectory for h in result.energy_levels] == paths
    assert result.estimates["k3"] == pytest.approx(0.5, rel=1e-8)
    assert all(p.truth is None for p in result.parameters)  # plain CSV: no metadata


@pytest.mark.parametrize("names", [["run-b", "run-a"], [5, 2], [2.5, 0.5]])
@pytest.mark.parametrize("source", ["DataFrame", ".csv", ".parquet"])
def test_trajectory_labels_keep_their_order_of_appearance(tmp_path, clean_records, names,
                                                         source):
    frame = clean_records["duffing"].copy()
    codes = frame["trajectory"].rank(method="dense").astype(int) - 1
    frame["trajectory"] = [names[c] for c in codes]
    data = frame
    if source != "DataFrame":
        data = tmp_path / f"run{source}"
        frame.to_csv(data, index=False) if source == ".csv" else frame.to_parquet(data)
    result = hamid.fit(data, "duffing", method="energy")
    assert [h.trajectory for h in result.energy_levels] == names
    assert [h.n_samples for h in result.energy_levels] == codes.value_counts(
        sort=False).tolist()
    assert result.estimates["k3"] == pytest.approx(0.5, rel=1e-8)


def test_model_assumed_when_none_is_known(clean_records):
    frame = clean_records["duffing"].rename(columns={"v": "x_dot"})
    frame.attrs = {}
    result = hamid.fit(frame, method="energy")
    assert result.model["name"] == "poly:1:3"
    assert result.model["parameters"] == ["c_2", "c_3"]
    x, v, groups = frame["x"].to_numpy(), frame["x_dot"].to_numpy(), frame["trajectory"]
    dummies = (groups.to_numpy()[:, None] == [1, 2]).astype(float)
    expected = np.linalg.lstsq(np.column_stack([x**2, x**3, -dummies]), -(v**2) / 2,
                               rcond=None)[0]
    assert list(result.estimates.values()) == pytest.approx(expected[:2], rel=1e-9)
    assert any("assumed poly:1:3" in w for w in result.warnings)


def test_seed_paper_single_trajectory_recovers_all_six():
    system = {**PENG, "initial": PENG["initial"][:1]}
    result = hamid.fit(hamid.simulate(system), method="energy")
    assert result.estimates == pytest.approx(PENG["parameters"], rel=1e-8)


def _subtract_first_sample(frame: pd.DataFrame) -> np.ndarray:
    """The paper's variant: each row minus the first sample, no free energy level."""
    model = hamid.load_model("peng-quadratic")
    X = frame[list(model.variables)].to_numpy()
    E0, Phi = model.energy_basis(X)
    A, b = Phi[1:] - Phi[0], -(E0[1:] - E0[0])
    return np.linalg.lstsq(A, b, rcond=None)[0]


def test_free_energy_level_beats_subtracting_the_first_sample():
    system = {**PENG, "initial": PENG["initial"][:1], "simulate": {"t_end": 60.0, "dt": 0.05}}
    clean = hamid.simulate(system)
    truth = np.array(list(PENG["parameters"].values()))
    ours, papers = [], []
    for seed in range(8):
        noisy = with_noise(clean, 0.01, seed)
        ours.append(np.array(list(hamid.fit(noisy, method="energy").estimates.values())))
        papers.append(_subtract_first_sample(noisy))
    error = lambda est: np.sqrt(np.mean(((np.array(est) - truth) / truth) ** 2))  # noqa: E731
    assert error(papers) > 3 * error(ours)


def test_drift_is_flagged_for_a_damped_record():
    damped = {**DUFFING, "damping": {"c_x": 0.02}}
    result = hamid.fit(hamid.simulate(damped), method="energy")
    assert any("is not conserved" in w and "--damping viscous" in w for w in result.warnings)
    clean = hamid.fit(hamid.simulate(DUFFING), method="energy")
    assert not any("is not conserved" in w for w in clean.warnings)


def test_insignificant_parameter_is_flagged(clean_records):
    frame = with_noise(clean_records["duffing"], 0.001, seed=0)
    result = hamid.fit(frame, "poly:1:4", columns={"q1": "x", "v1": "v"})
    assert any(w.startswith("c_3 is not significantly different from zero")
               for w in result.warnings)
    assert not any(w.startswith("c_4 ") for w in result.warnings)


def test_conditioning_reports_scaled_condition_and_weakest_direction(clean_records):
    frame = clean_records["duffing"]
    result = hamid.fit(frame, method="energy")
    s = np.array(result.conditioning["singular_values"])
    assert result.conditioning["condition_number"] == pytest.approx(s[0] / s[-1])
    # Independent: the same scaled matrix built by hand.
    _, X, _ = _duffing_design(frame)
    X = X / np.linalg.norm(X, axis=0)
    assert s == pytest.approx(np.linalg.svd(X, compute_uv=False), rel=1e-9)
    assert set(result.conditioning["weakest_direction"]) >= {"k", "k3"}
    assert result.conditioning["status"] == "ok"


def test_ill_conditioned_problem_warns(clean_records):
    # Even powers up to x**6 over the same swings are nearly collinear.
    frame = with_noise(clean_records["duffing"], 1e-3, seed=0)
    result = hamid.fit(frame, "poly:1:6", columns={"q1": "x", "v1": "v"})
    assert result.conditioning["status"] == "moderate"
    assert any("ill-conditioned" in w and "larger amplitudes" in w for w in result.warnings)


def test_residual_statistics(clean_records):
    frame = with_noise(clean_records["duffing"], 0.01, seed=5)
    result = hamid.fit(frame)
    r = result.samples["residual"]
    assert result.residuals["rms"] == pytest.approx(np.sqrt(np.mean(r**2)))
    assert result.residuals["max_abs"] == pytest.approx(np.max(np.abs(r)))
    mean_h = np.mean([abs(h.h) for h in result.energy_levels])
    assert result.residuals["relative_rms"] == pytest.approx(result.residuals["rms"] / mean_h)
    assert 0.9 < result.residuals["r_squared"] < 1.0
    assert len(r) == len(frame) == len(result.samples["t"])
    assert set(result.samples) == {"trajectory", "t", "energy", "residual", "weight"}


def test_shuffled_trajectories_give_the_same_estimates(clean_records):
    frame = with_noise(clean_records["peng-quadratic"], 0.01, seed=6)
    reordered = pd.concat([frame[frame.trajectory == 2], frame[frame.trajectory == 1]])
    a = hamid.fit(frame, method="energy").estimates
    b = hamid.fit(reordered, method="energy").estimates
    assert b == pytest.approx(a, rel=1e-10)


@pytest.mark.parametrize("kwargs, message", [
    ({"method": "magic"}, "method must be one of"),
    ({"cov": "robust"}, "cov must be one of"),
    ({"level": 1.5}, "level must be between 0 and 1"),
])
def test_bad_options(clean_records, kwargs, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], **kwargs)


@pytest.mark.slow
def test_confidence_bounds_cover_the_truth():
    """Over 200 noise realizations, 95% bounds cover each true value 90-99% of the time."""
    covered = coverage(hamid.simulate(DUFFING), DUFFING["parameters"], 0.002, 200,
                       method="energy")
    for name, fraction in covered.items():
        assert 0.90 <= fraction <= 0.99, (name, fraction)
