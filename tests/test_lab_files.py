"""Files as a lab writes them (issue 18): time columns with units, column names with unit
suffixes, `--scale`, dropouts and gaps, hints in errors, and the self-checks.

The truth is the fit of the same record in SI units (`sample_data/peng_quadratic.csv`),
converted here by hand, never by hamid's tables.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pandas as pd
import pytest

import hamid
from hamid.errors import DataError, UsageError

SAMPLE = "sample_data/peng_quadratic.csv"


@pytest.fixture(scope="module")
def si() -> pd.DataFrame:
    return pd.read_csv(SAMPLE, comment="#")


@pytest.fixture(scope="module")
def si_fit() -> hamid.FitResult:
    return hamid.fit(SAMPLE, "peng-quadratic")


def _same_estimates(result, expected) -> None:
    for name, value in expected.estimates.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-8), name


def _daq(frame: pd.DataFrame, time: str, time_factor: float) -> pd.DataFrame:
    """The record with time in other units, positions in mm, velocities in m/s."""
    daq = frame.rename(columns={"t": time, "u1": "x1_mm", "u2": "x2_mm"})
    daq[time] = frame["t"] * time_factor
    daq["x1_mm"] = frame["u1"] * 1000.0
    daq["x2_mm"] = frame["u2"] * 1000.0
    return daq


@pytest.mark.parametrize(("time", "factor"), [("time_ms", 1e3), ("Time [ms]", 1e3),
                                              ("t (us)", 1e6), ("TIME", 1.0)])
def test_time_column_with_a_unit_gives_the_si_estimates(tmp_path, si, si_fit, time, factor):
    path = tmp_path / "daq.csv"
    _daq(si, time, factor).to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic", columns={"u1": "x1_mm", "u2": "x2_mm"})
    _same_estimates(result, si_fit)
    data = result.to_dict()["data"]
    assert data["time"] == time
    assert data["scale"]["x1_mm"] == 1e-3 and data["scale"]["x2_mm"] == 1e-3
    # windows in seconds, as for the SI file
    assert result.to_dict()["method"]["weak_window"] == pytest.approx(
        si_fit.to_dict()["method"]["weak_window"], rel=1e-8)
    assert result.to_dict()["method"]["kind"] == si_fit.to_dict()["method"]["kind"]


def test_time_unit_option_overrides_the_name(tmp_path, si, si_fit):
    frame = si.copy()
    frame["clock"] = frame["t"] * 1e9
    frame = frame.drop(columns="t")
    path = tmp_path / "ns.csv"
    frame.to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic", time="clock", time_unit="ns")
    _same_estimates(result, si_fit)
    assert result.to_dict()["data"]["time_unit"] == "ns"


def test_time_unit_without_a_time_column_is_a_usage_error(si):
    frame = si.drop(columns="t")
    with pytest.raises(UsageError, match="no time column; name it with --time COL"):
        hamid.fit(frame, "peng-quadratic", time_unit="ms")


def test_a_column_that_looks_like_time_is_never_dropped_silently(si):
    frame = si.rename(columns={"t": "time_min"})
    result = hamid.fit(frame, "peng-quadratic", method="energy")
    assert result.to_dict()["data"]["time"] is None
    assert any("'time_min' looks like time" in w and "--time-unit" in w
               for w in result.warnings)


def test_scale_option_brings_columns_to_si_units(tmp_path, si, si_fit):
    frame = si.rename(columns={"u1": "pos1", "u2": "pos2", "v1": "vel1", "v2": "vel2"})
    frame["pos1"] *= 1000.0
    frame["vel2"] *= 25.4
    path = tmp_path / "odd.csv"
    frame.to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic",
                       columns={"u1": "pos1", "u2": "pos2", "v1": "vel1", "v2": "vel2"},
                       scale={"pos1": 1e-3, "vel2": 1 / 25.4})
    _same_estimates(result, si_fit)
    assert result.to_dict()["data"]["scale"] == {"pos1": 1e-3, "vel2": 1 / 25.4}


def test_scale_of_a_column_not_read_is_a_usage_error(si):
    with pytest.raises(UsageError, match=r"--scale: 'nope' is not a column read"):
        hamid.fit(si, "peng-quadratic", scale={"nope": 2.0})


def test_velocity_suffix_mm_s_is_converted(tmp_path, si, si_fit):
    frame = _daq(si, "t", 1.0).rename(columns={"v1": "v1_mm_s", "v2": "v2_mm_s"})
    frame["v1_mm_s"] *= 1000.0
    frame["v2_mm_s"] *= 1000.0
    path = tmp_path / "mm.csv"
    frame.to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic", columns={"u1": "x1_mm", "u2": "x2_mm"})
    _same_estimates(result, si_fit)
    assert result.to_dict()["data"]["columns"]["v1"] == "v1_mm_s"


@pytest.mark.parametrize(("columns", "pairs"), [
    (["t", "x1", "x2", "v1", "v2"], [("x1", "v1"), ("x2", "v2")]),
    (["t", "theta", "omega"], [("theta", "omega")]),
    (["t", "q1", "dq1"], [("q1", "dq1")]),
    (["t", "x", "xdot"], [("x", "xdot")]),
    (["time_ms", "x1_mm", "x2_mm", "v1", "v2"], [("x1_mm", "v1"), ("x2_mm", "v2")]),
    (["x1 [mm]", "v1 [mm/s]"], [("x1 [mm]", "v1 [mm/s]")]),
])
def test_pairing_rules(columns, pairs):
    from hamid.data import column_roles

    time = column_roles.default_time_column(columns)
    assert column_roles.find_coordinates(columns, exclude={time} if time else set()) == pairs


def _si_report(hamid_cli, si_fit, path, *args) -> dict:
    """The JSON report of a peng-quadratic fit of `path` through the CLI, checked to give
    the estimates of the file in SI units."""
    done = subprocess.run([*hamid_cli, "fit", str(path), "--model", "peng-quadratic", *args,
                           "--format", "json"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    for p in report["parameters"]:
        assert p["estimate"] == pytest.approx(si_fit.estimates[p["name"]], rel=1e-8)
    return report


def test_daq_header_fits_in_one_command(tmp_path, si, si_fit, hamid_cli):
    """`time_ms,x1_mm,x2_mm,v1,v2` fits with the model and the column names only."""
    path = tmp_path / "daq.csv"
    _daq(si, "time_ms", 1e3).to_csv(path, index=False)
    report = _si_report(hamid_cli, si_fit, path, "--columns", "u1=x1_mm,u2=x2_mm")
    assert report["data"]["time_unit"] == "ms"


def test_time_unit_and_scale_on_the_command_line(tmp_path, si, si_fit, hamid_cli):
    frame = _daq(si, "clock", 1e3).rename(columns={"x1_mm": "a", "x2_mm": "b"})
    path = tmp_path / "plain.csv"
    frame.to_csv(path, index=False)
    report = _si_report(hamid_cli, si_fit, path, "--columns", "u1=a,u2=b", "--time", "clock",
                        "--time-unit", "ms", "--scale", "a=0.001,b=0.001")
    assert report["data"]["scale"] == {"a": 0.001, "b": 0.001, "clock": 0.001}


def test_bad_time_unit_is_exit_2(hamid_cli):
    done = subprocess.run([*hamid_cli, "fit", SAMPLE, "--time-unit", "min"],
                          capture_output=True, text=True, check=False, timeout=600)
    assert done.returncode == 2
    assert done.stdout == ""
    assert done.stderr.strip().splitlines()[-1] == (
        "Error: Invalid value for '--time-unit': 'min' is not one of 's', 'ms', 'us', 'ns'.")


def test_metadata_units_convert_like_suffixes(si, si_fit):
    frame = si.rename(columns={"t": "clock"})
    frame["clock"] *= 1e3
    frame["u1"] *= 1e3
    frame.attrs["hamid"] = {"units": {"clock": "ms", "u1": "mm", "u2": "m"}}
    result = hamid.fit(frame, "peng-quadratic", time="clock")
    _same_estimates(result, si_fit)
    assert result.to_dict()["data"]["scale"] == {"u1": 1e-3, "clock": 1e-3}


def _with_dropout(frame: pd.DataFrame, row: int, column: str, value: object) -> pd.DataFrame:
    holed = frame.copy()
    holed[column] = holed[column].astype(object)
    holed.loc[row, column] = value
    return holed


@pytest.mark.parametrize("cell", ["", "nan"])
def test_one_missing_value_splits_the_trajectory(tmp_path, si, si_fit, cell):
    path = tmp_path / "dropout.csv"
    _with_dropout(si, 100, "u1", cell).to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic")
    for name, value in si_fit.estimates.items():   # exact data: the same answer
        assert result.estimates[name] == pytest.approx(value, rel=1e-8), name
    report = result.to_dict()
    assert report["data"]["n_trajectories"] == si_fit.to_dict()["data"]["n_trajectories"] + 1
    assert report["data"]["n_samples"] == si_fit.to_dict()["data"]["n_samples"] - 1
    labels = [level["trajectory"] for level in report["energy_levels"]]
    assert labels[:2] == ["1/1", "1/2"]
    assert [level["n_samples"] for level in report["energy_levels"][:2]] == [100, 700]
    assert any("1 cut(s)" in w and "1 at missing values" in w for w in result.warnings)


def test_gaps_error_refuses_a_missing_value(si):
    with pytest.raises(DataError, match=r"column 'u1', row 101: missing value"):
        hamid.fit(_with_dropout(si, 100, "u1", np.nan), "peng-quadratic", gaps="error")


def test_a_time_gap_splits_or_is_refused(si):
    gapped = si.drop(index=range(200, 260)).reset_index(drop=True)
    result = hamid.fit(gapped, "peng-quadratic", method="energy")
    assert result.to_dict()["data"]["n_trajectories"] == 4
    assert any("1 at time gaps" in w for w in result.warnings)
    with pytest.raises(DataError, match=r"row 201: a time gap of 3\.05 s .*--gaps split"):
        hamid.fit(gapped, "peng-quadratic", gaps="error")


def test_no_gap_no_cut(si, si_fit):
    assert not any("cut(s)" in w for w in si_fit.warnings)


def test_gaps_on_the_command_line(tmp_path, si, hamid_cli):
    path = tmp_path / "dropout.csv"
    _with_dropout(si, 100, "u1", "").to_csv(path, index=False)
    split = subprocess.run([*hamid_cli, "fit", str(path), "--model", "peng-quadratic",
                            "--method", "energy", "--format", "json"],
                           capture_output=True, text=True, check=False)
    assert split.returncode == 0, split.stderr
    assert "1 cut(s)" in split.stderr
    refused = subprocess.run([*hamid_cli, "fit", str(path), "--model", "peng-quadratic",
                              "--gaps", "error"], capture_output=True, text=True, check=False)
    assert refused.returncode == 1
    assert "row 101: missing value" in refused.stderr


def _run(hamid_cli, *args, cwd=None):
    return subprocess.run([*hamid_cli, *map(str, args)], capture_output=True, text=True,
                          check=False, cwd=cwd)


def test_misspelt_model_name_suggests_the_builtin(hamid_cli):
    done = _run(hamid_cli, "fit", SAMPLE, "--model", "dufing")
    assert done.returncode == 2
    assert "did you mean 'duffing'?" in done.stderr


def test_no_model_error_names_the_toml_beside_the_data_and_savgol(tmp_path, si, hamid_cli):
    si[["t", "u1", "u2"]].to_csv(tmp_path / "rig_run3.csv", index=False)
    (tmp_path / "rig.toml").write_text("")
    (tmp_path / "other.toml").write_text("")
    done = _run(hamid_cli, "fit", tmp_path / "rig_run3.csv")
    assert done.returncode == 1
    assert f"--model {tmp_path / 'rig.toml'}" in done.stderr
    assert "--velocity savgol" in done.stderr


def test_assumed_model_note_names_the_toml_beside_the_data():
    result = hamid.fit("sample_data/pendulum_encoder.csv", method="energy")
    assert any("pick one with --model sample_data/pendulum.toml" in w
               for w in result.warnings)


def test_missing_velocity_error_mentions_savgol(si):
    with pytest.raises(DataError, match="derive velocities with --velocity savgol"):
        hamid.fit(si.drop(columns=["v1", "v2"]), "peng-quadratic")


def test_savgol_without_time_mentions_time(si):
    with pytest.raises(UsageError, match="name it with --time COL"):
        hamid.fit(si.drop(columns="t").rename(columns={"u1": "a"}), "peng-quadratic",
                  columns={"u1": "a"}, velocity="savgol")


def test_files_recording_different_models_are_a_usage_error(hamid_cli):
    both = ("sample_data/duffing.csv", "sample_data/henon_heiles.csv")
    done = _run(hamid_cli, "fit", *both)
    assert done.returncode == 2
    assert "record different models" in done.stderr and "--model" in done.stderr
    given = _run(hamid_cli, "fit", *both, "--model", "duffing", "--method", "energy")
    assert given.returncode == 0, given.stderr


def test_velocities_in_other_units_are_warned_with_the_ratio(si):
    mixed = si.copy()
    mixed["v1"] *= 1000.0   # mm/s beside positions in m
    result = hamid.fit(mixed, "peng-quadratic", method="energy")
    said = [w for w in result.warnings if "'u1' change 0.001 times as fast" in w]
    assert said and "'v1'" in said[0] and "--scale" in said[0]
    assert not any("'u2' change" in w for w in result.warnings)


def test_time_in_ms_read_as_seconds_is_warned(si):
    slow = si.copy()
    slow["t"] *= 1000.0
    result = hamid.fit(slow, "peng-quadratic", method="energy")
    assert any("'u1' change 0.001 times as fast" in w and "time unit" in w
               for w in result.warnings)


def test_consistent_noisy_velocities_raise_no_unit_warning(si):
    from conftest import with_noise

    result = hamid.fit(with_noise(si, 0.03, 0), "peng-quadratic", method="energy")
    assert not any("times as fast" in w for w in result.warnings)


def test_weak_window_longer_than_a_trajectory_is_warned(si):
    short = si[(si["trajectory"] != 3) | (si["t"] <= 5.0)]
    result = hamid.fit(short, "peng-quadratic", method="weak", weak_window=10.0)
    assert any(w.startswith("1 of 3 trajectories are shorter than the weak-form window "
                            "of 10 s (the shortest lasts 5 s)") for w in result.warnings)
    longer = hamid.fit(short, "peng-quadratic", method="weak", weak_window=4.0)
    assert not any("shorter than the weak-form window" in w for w in longer.warnings)


def test_strict_turns_warnings_into_exit_3(tmp_path, si, hamid_cli):
    mixed = si.copy()
    mixed["v1"] *= 1000.0
    path = tmp_path / "mixed.csv"
    mixed.to_csv(path, index=False)
    plain = _run(hamid_cli, "fit", path, "--model", "peng-quadratic", "--format", "json")
    assert plain.returncode == 0
    assert "times as fast" in plain.stderr
    strict = _run(hamid_cli, "fit", path, "--model", "peng-quadratic", "--format", "json",
                  "--strict")
    assert strict.returncode == 3
    assert json.loads(strict.stdout)["warnings"]   # the report is still written
    assert "--strict" in strict.stderr


def test_strict_without_warnings_is_exit_0(hamid_cli):
    done = _run(hamid_cli, "fit", SAMPLE, "--strict", "--format", "json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["warnings"] == []


def test_units_row_converts_like_suffixes(tmp_path, si, si_fit, hamid_cli):
    """A units row under the header (recorded as the table's units) is applied."""
    frame = si.copy()
    frame["t"] *= 1000.0
    frame["u1"] *= 1000.0
    rows = ["trajectory,t,u1,u2,v1,v2", "-,ms,mm,m,m/s,m/s",
            *(",".join(map(repr, row)) for row in frame.itertuples(index=False))]
    path = tmp_path / "units.csv"
    path.write_text("\n".join(rows) + "\n")
    done = _run(hamid_cli, "fit", path, "--model", "peng-quadratic", "--format", "json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    for p in report["parameters"]:
        assert p["estimate"] == pytest.approx(si_fit.estimates[p["name"]], rel=1e-8)
    assert report["data"]["time_unit"] == "ms"
    assert report["data"]["scale"] == {"u1": 0.001, "t": 0.001}


def test_unknown_recorded_unit_is_said(si):
    frame = si.copy()
    frame.attrs["hamid"] = {"units": {"u1": "furlong"}}
    result = hamid.fit(frame, "peng-quadratic", method="energy")
    assert any("'u1' ('furlong') are not among those converted" in w and "--scale" in w
               for w in result.warnings)
    given = hamid.fit(frame, "peng-quadratic", method="energy", scale={"u1": 1.0})
    assert not any("furlong" in w for w in given.warnings)


def test_a_file_read_in_chunks_refuses_a_time_gap(tmp_path, si):
    """Chunks are not cut at gaps: an error, never a fit that differs from the whole one."""
    path = tmp_path / "gapped.csv"
    si.drop(index=range(200, 260)).to_csv(path, index=False)
    with pytest.raises(DataError, match=r"row 201: a time gap of 3\.05 s .*read in chunks"):
        hamid.fit(path, "peng-quadratic", method="energy", chunk_rows=100)
    whole = hamid.fit(path, "peng-quadratic", method="energy")
    assert whole.to_dict()["data"]["n_trajectories"] == 4


def test_a_file_read_in_chunks_without_gaps_fits_as_whole(tmp_path, si, si_fit):
    path = tmp_path / "plain.csv"
    si.to_csv(path, index=False)
    chunked = hamid.fit(path, "peng-quadratic", method="energy", chunk_rows=100)
    whole = hamid.fit(path, "peng-quadratic", method="energy")
    _same_estimates(chunked, whole)


def test_a_file_read_in_chunks_names_the_way_past_a_dropout(tmp_path, si):
    path = tmp_path / "dropout.csv"
    _with_dropout(si, 100, "u1", "").to_csv(path, index=False)
    with pytest.raises(DataError, match=r"row 101: missing value; a file read in chunks is "
                                        r"not cut at dropouts: read it whole"):
        hamid.fit(path, "peng-quadratic", method="energy", chunk_rows=100)
    assert hamid.fit(path, "peng-quadratic", method="energy",
                     in_memory=True).to_dict()["data"]["n_trajectories"] == 4


def test_windows_covering_less_than_half_the_record_are_warned(si):
    """Windows start every quarter window and end inside their trajectory: what they reach
    of the record, counted by hand for windows of 30 s."""
    result = hamid.fit(si, "peng-quadratic", method="weak", weak_window=4.0)
    assert not any("cover only" in w for w in result.warnings)
    from hamid.linear.plan import FitPlan, window_warnings

    plan = FitPlan("weak", "", 30.0, None)
    # 40 s: windows start at 0 and 7.5 s, and reach 37.5 s (94%)
    assert not window_warnings(plan, [40.0])
    # 20 s and 100 s: the short one gets none; 7.5 s steps reach 97.5 of 100: 81%
    assert [w for w in window_warnings(plan, [20.0, 100.0]) if "cover only" in w] == []
    # 29 s four times and 35 s once: only the last has windows, 30 of 151 s: 20%
    found = [w for w in window_warnings(plan, [29.0] * 4 + [35.0]) if "cover only" in w]
    assert found == ["the weak-form windows cover only 20% of the record; give a shorter "
                     "--weak-window, or check the time unit"]
