"""Files as a lab writes them (issue 18): time columns with units, column names with unit
suffixes, `--scale`, dropouts and gaps, hints in errors, and the self-checks.

The truth is the fit of the same record in SI units (`sample_data/peng_quadratic.csv`),
converted here by hand, never by hamid's tables.

Lab formats (issue 18): MATLAB .mat v5 and v7.3, HDF5, LabVIEW TDMS and UFF 58. Every
fixture is written by the format's own library (scipy.io, h5py, npTDMS, pyuff) from a bundled
CSV, and each fits to the CSV's estimates.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

import hamid
from hamid.data import lab_formats
from hamid.data import readers as hio
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
def test_one_missing_value_is_just_missing(tmp_path, si, si_fit, cell):
    """An empty cell drops its row; the trajectory goes on across it (no new energy
    level), as if the row had never been written, and the note says so."""
    path = tmp_path / "dropout.csv"
    _with_dropout(si, 100, "u1", cell).to_csv(path, index=False)
    result = hamid.fit(path, "peng-quadratic")
    for name, value in si_fit.estimates.items():   # exact data: the same answer
        assert result.estimates[name] == pytest.approx(value, rel=1e-8), name
    report = result.to_dict()
    assert report["data"]["n_trajectories"] == si_fit.to_dict()["data"]["n_trajectories"]
    assert report["data"]["n_samples"] == si_fit.to_dict()["data"]["n_samples"] - 1
    assert [level["trajectory"] for level in report["energy_levels"]] == [
        level["trajectory"] for level in si_fit.to_dict()["energy_levels"]]
    assert any("1 row with missing values dropped; the trajectories go on across the 1 "
               "place" in w for w in result.warnings)


def test_a_long_run_of_missing_values_still_cuts(si):
    holed = si.copy()
    holed.loc[100:110, "u1"] = np.nan   # 11 rows: a step of 12 samples, over GAP_STEPS
    result = hamid.fit(holed, "peng-quadratic", method="energy")
    labels = [level["trajectory"] for level in result.to_dict()["energy_levels"]]
    assert labels[:2] == ["1/1", "1/2"]
    assert any("1 cut in" in w and "1 at missing values" in w for w in result.warnings)


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
    assert not any(" in the trajectories (" in w for w in si_fit.warnings)


def test_gaps_on_the_command_line(tmp_path, si, hamid_cli):
    path = tmp_path / "dropout.csv"
    _with_dropout(si, 100, "u1", "").to_csv(path, index=False)
    split = subprocess.run([*hamid_cli, "fit", str(path), "--model", "peng-quadratic",
                            "--method", "energy", "--format", "json"],
                           capture_output=True, text=True, check=False)
    assert split.returncode == 0, split.stderr
    assert "1 row with missing values dropped; the trajectories go on" in split.stderr
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


def test_no_model_error_names_the_toml_beside_the_data(tmp_path, si, hamid_cli):
    si[["t", "u1", "u2"]].to_csv(tmp_path / "rig_run3.csv", index=False)
    (tmp_path / "rig.toml").write_text("")
    (tmp_path / "other.toml").write_text("")
    done = _run(hamid_cli, "fit", tmp_path / "rig_run3.csv")
    assert done.returncode == 1
    assert f"--model {tmp_path / 'rig.toml'}" in done.stderr
    assert "positions without velocities are fitted given --model" in done.stderr


def test_assumed_model_note_names_the_toml_beside_the_data():
    result = hamid.fit("sample_data/pendulum_encoder.csv", method="energy")
    assert any("pick one with --model sample_data/pendulum.toml" in w
               for w in result.warnings)


def test_a_missing_velocity_in_chunks_says_to_read_the_file_whole(si, tmp_path):
    """Read whole, u2's velocity is derived (tests/data/test_channels.py); a file read in
    chunks needs every velocity (the message said to derive them with --velocity savgol,
    which chunks refuse)."""
    path = tmp_path / "si.csv"
    si.drop(columns=["v2"]).to_csv(path, index=False)
    with pytest.raises(UsageError, match=r"records u1: position, velocity; u2: position; "
                                         "leave out --chunk-rows"):
        hamid.fit(path, "peng-quadratic", chunk_rows=1000)


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
    assert any(w.startswith("1 of 3 trajectories is shorter than the weak-form window "
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
                     in_memory=True).to_dict()["data"]["n_trajectories"] == 3


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


h5py = pytest.importorskip("h5py")
nptdms = pytest.importorskip("nptdms")
pyuff = pytest.importorskip("pyuff")
sio = pytest.importorskip("scipy.io")

DUFFING_SAMPLE = "sample_data/duffing.csv"
NAMES = ["trajectory", "t", "x", "v"]


@pytest.fixture(scope="module")
def sample():
    columns, metadata = hio.read_columns(DUFFING_SAMPLE)
    assert list(columns) == NAMES
    return columns, metadata


@pytest.fixture(scope="module")
def truth():
    """The CSV's estimates, with the model its metadata names."""
    return hamid.fit(DUFFING_SAMPLE).estimates


def _same(result, truth):
    assert result.estimates.keys() == truth.keys()
    for name, value in truth.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-10, abs=1e-14)


def _read(source):
    columns, metadata = hio.read_columns(source)
    return columns, metadata


# --- MATLAB v5 (scipy.io) --------------------------------------------------------------------


def test_mat_v5_vectors_with_metadata(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.mat"
    sio.savemat(path, {**columns, "hamid": json.dumps(metadata), "note": "bench 3",
                       "fs": 20.0})
    got, meta = _read(path)
    assert list(got) == NAMES and meta == metadata   # scalars and text are not columns
    for name in NAMES:
        assert np.array_equal(got[name], columns[name])
    _same(hamid.fit(str(path)), truth)


def test_mat_v5_struct_and_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.mat"
    fields = {"trajectory": columns["trajectory"], "time": columns["t"],
              "pos": columns["x"], "vel": columns["v"]}
    sio.savemat(path, {"run": fields})
    assert list(_read(path)[0]) == ["trajectory", "time", "pos", "vel"]
    _same(hamid.fit(str(path), "duffing", columns={"x": "pos", "v": "vel"}, time="time"),
          truth)


def test_mat_v5_array_with_column_names(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.mat"
    table = np.column_stack([columns[name] for name in NAMES]).astype(float)
    names = np.array(NAMES, dtype=object)   # a cell array of text
    sio.savemat(path, {"data": table, "data_columns": names, "other": np.arange(3.0)})
    got, _ = _read(f"{path}:data")   # only that variable
    assert list(got) == NAMES
    _same(hamid.fit(f"{path}:data", "duffing"), truth)
    sio.savemat(path, {"data": table})
    assert list(_read(path)[0]) == ["data_1", "data_2", "data_3", "data_4"]


def test_mat_v5_unequal_lengths_and_unknown_variable(tmp_path):
    path = tmp_path / "run.mat"
    sio.savemat(path, {"t": np.arange(5.0), "x": np.arange(4.0)})
    with pytest.raises(DataError, match=rf"^{path}: the columns have different lengths "
                                        r"\('t' 5, 'x' 4\)$"):
        _read(path)
    with pytest.raises(DataError, match=rf"^{path}:y: no variable 'y' \(the file has 't', "
                                        r"'x'\)$"):
        _read(f"{path}:y")


def test_mat_damaged(tmp_path):
    path = tmp_path / "run.mat"
    path.write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 20)
    with pytest.raises(DataError, match=rf"^{path}: is not a readable MATLAB file \(.+\)$"):
        _read(path)


# --- MATLAB v7.3 (HDF5, written as MATLAB does: a 512-byte header, arrays column-major) --------


def _write_mat73(path, variables):
    with h5py.File(path, "w", userblock_size=512) as file:
        for name, value in variables.items():
            if isinstance(value, str):
                codes = np.frombuffer(value.encode("utf-16-le"), dtype="<u2")
                dataset = file.create_dataset(name, data=codes.reshape(-1, 1))
                dataset.attrs["MATLAB_class"] = np.bytes_("char")
            else:
                value = np.asarray(value, dtype=float)
                dataset = file.create_dataset(name, data=np.atleast_2d(value))   # 1 x n
                dataset.attrs["MATLAB_class"] = np.bytes_("double")
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Nov 23 10:00:00 2026 " \
        b"HDF5 schema 1.00 ."
    with open(path, "r+b") as stream:
        stream.write(header.ljust(116) + b"\x00" * 8 + b"\x00\x02IM")


def test_mat_v73(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run73.mat"
    _write_mat73(path, {**columns, "hamid": json.dumps(metadata)})
    with pytest.raises(NotImplementedError):   # scipy itself cannot: h5py reads it
        sio.loadmat(path)
    got, meta = _read(path)
    assert sorted(got) == sorted(NAMES) and meta == metadata
    _same(hamid.fit(str(path)), truth)


def test_mat_v73_struct(tmp_path, sample, truth):
    """A MATLAB struct is an HDF5 group; its vector fields are the columns."""
    columns, _ = sample
    path = tmp_path / "run73.mat"
    _write_mat73(path, {"fs": 20.0})
    with h5py.File(path, "a") as file:
        group = file.create_group("run")
        group.attrs["MATLAB_class"] = np.bytes_("struct")
        for name in NAMES:
            group.create_dataset(name, data=np.atleast_2d(columns[name].astype(float)))
    got, meta = _read(path)
    assert sorted(got) == sorted(NAMES) and meta is None   # fs (1 x 1) is not a column
    assert np.array_equal(got["x"], columns["x"])
    _same(hamid.fit(str(path), "duffing"), truth)


# --- HDF5 ----------------------------------------------------------------------------------


def test_hdf5_group_of_vectors(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("bench/run1")
        for name in NAMES:
            group.create_dataset(name, data=columns[name])
        file.attrs["hamid"] = json.dumps(metadata)
    got, meta = _read(f"{path}:/bench/run1")
    assert sorted(got) == sorted(NAMES) and meta == metadata
    _same(hamid.fit(f"{path}:/bench/run1"), truth)
    with pytest.raises(DataError, match=rf"^{path}: no 1-D numeric datasets in '/' \(it "
                                        r"holds 'bench'\); give .+:/path/to/dataset$"):
        _read(path)


def test_hdf5_compound_dataset(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.hdf5"
    table = np.empty(len(columns["t"]), dtype=[("trajectory", "i8"), ("time", "f8"),
                                                ("pos", "f8"), ("vel", "f8")])
    for field, name in zip(table.dtype.names, NAMES, strict=True):
        table[field] = columns[name]
    with h5py.File(path, "w") as file:
        file.create_dataset("data/table", data=table)
    source = f"{path}:/data/table"
    assert list(_read(source)[0]) == ["trajectory", "time", "pos", "vel"]
    _same(hamid.fit(source, "duffing", columns={"x": "pos", "v": "vel"}, time="time"), truth)


def test_hdf5_2d_array_alone_in_the_file(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        dataset = file.create_dataset("samples",
                                      data=np.column_stack([columns[n] for n in NAMES]))
        dataset.attrs["columns"] = NAMES
    assert list(_read(path)[0]) == NAMES   # the file's only dataset, its named columns
    _same(hamid.fit(str(path), "duffing"), truth)
    with pytest.raises(DataError, match=rf"^{path}:/nothing: no dataset or group "
                                        r"'/nothing' in "):
        _read(f"{path}:/nothing")


def test_hdf5_read_in_chunks_gives_the_same_fit(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        for name in NAMES:
            file.create_dataset(name, data=columns[name])
        file.attrs["hamid"] = json.dumps(metadata)
    table = hio.TableChunks(path)
    assert table.columns == sorted(NAMES) or set(table.columns) == set(NAMES)
    x = np.concatenate([chunk["x"] for chunk in table.chunks(["x"], 128)])
    assert np.array_equal(x, columns["x"])
    streamed = hamid.fit(DUFFING_SAMPLE, chunk_rows=128).estimates
    got = hamid.fit(str(path), chunk_rows=128).estimates
    for name, value in streamed.items():
        assert got[name] == pytest.approx(value, rel=1e-10)


def test_hdf5_not_hdf5(tmp_path):
    path = tmp_path / "run.h5"
    path.write_text("t,x\n0,1\n")
    with pytest.raises(DataError, match=rf"^{path}: is not a readable HDF5 file \(.+\)$"):
        _read(path)


# --- TDMS ----------------------------------------------------------------------------------


def _write_tdms(path, groups, root_properties=None):
    objects = [nptdms.RootObject(properties=root_properties or {})]
    for group, channels in groups.items():
        objects.append(nptdms.GroupObject(group))
        for name, (data, properties) in channels.items():
            objects.append(nptdms.ChannelObject(group, name, data, properties=properties))
    with nptdms.TdmsWriter(path) as writer:
        writer.write_segment(objects)


def test_tdms_group_channels(tmp_path, sample, truth):
    columns, metadata = sample
    path = tmp_path / "run.tdms"
    _write_tdms(path, {"Measured": {name: (columns[name], {}) for name in NAMES},
                       "Empty": {}}, {"hamid": json.dumps(metadata)})
    got, meta = _read(path)
    assert list(got) == NAMES and meta == metadata
    _same(hamid.fit(str(path)), truth)
    _same(hamid.fit(f"{path}:Measured", "duffing",
                    columns={"x": "x", "v": "v"}), truth)


def test_tdms_several_groups_and_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.tdms"
    renamed = {"trajectory": "trajectory", "t": "Time", "x": "Disp", "v": "Vel"}
    _write_tdms(path, {"Raw": {"a": (np.arange(3.0), {})},
                       "Run": {renamed[n]: (columns[n], {}) for n in NAMES}})
    with pytest.raises(DataError, match=rf"^{path}: has 2 groups with channels \('Raw', "
                                        r"'Run'\); give .+:GROUP$"):
        _read(path)
    _same(hamid.fit(f"{path}:Run", "duffing", columns={"x": "Disp", "v": "Vel"},
                    time="Time"), truth)


def test_tdms_waveform_channels_get_time(tmp_path):
    path = tmp_path / "wave.tdms"
    timing = {"wf_start_offset": 0.0, "wf_increment": 0.01}
    _write_tdms(path, {"g": {"x": (np.sin(np.arange(50) * 0.01), timing),
                             "v": (np.cos(np.arange(50) * 0.01), timing)}})
    got, _ = _read(path)
    assert list(got) == ["t", "x", "v"]
    assert np.allclose(got["t"], np.arange(50) * 0.01, rtol=0, atol=1e-15)


# --- UFF 58 ----------------------------------------------------------------------------------


def _write_uff(path, columns, names):
    # ASCII records (pyuff 2.5 does not read back its binary ones with an uneven abscissa):
    # twelve significant digits.
    sets = []
    for k in np.unique(columns["trajectory"]):
        rows = columns["trajectory"] == k
        for name in names:
            sets.append(pyuff.prepare_58(
                binary=0, id1=name, func_type=1, rsp_node=1, rsp_dir=1, ref_node=0,
                ref_dir=0, abscissa_spacing=0, ord_data_type=4, abscissa_spec_data_type=17,
                ordinate_spec_data_type=0, orddenom_spec_data_type=0, z_axis_spec_data_type=0,
                data=np.asarray(columns[name][rows], dtype=float),
                x=np.asarray(columns["t"][rows], dtype=float)))
    pyuff.UFF(str(path)).write_sets(sets, mode="overwrite")


def test_uff58_records_are_columns(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.uff"
    _write_uff(path, columns, ["x", "v"])
    got, meta = _read(path)
    assert list(got) == ["trajectory", "t", "x", "v"] and meta is None
    for name in NAMES:
        assert np.allclose(got[name], columns[name], rtol=1e-11, atol=1e-13)
    _same(hamid.fit(str(path), "duffing"), truth)


def test_uff58_columns_mapping(tmp_path, sample, truth):
    columns, _ = sample
    path = tmp_path / "run.unv"
    renamed = {**columns, "disp": columns["x"], "vel": columns["v"]}
    _write_uff(path, renamed, ["disp", "vel"])
    _same(hamid.fit(str(path), "duffing", columns={"x": "disp", "v": "vel"}), truth)


# --- missing libraries, names --------------------------------------------------------------


@pytest.mark.parametrize(("module", "suffix", "package"),
                         [("h5py", ".h5", "h5py"), ("nptdms", ".tdms", "npTDMS"),
                          ("pyuff", ".uff", "pyuff"), ("scipy.io", ".mat", "scipy")])
def test_missing_library_is_one_line(tmp_path, monkeypatch, module, suffix, package):
    path = tmp_path / f"run{suffix}"
    path.write_bytes(b"\x00" * 16)
    monkeypatch.setitem(sys.modules, module, None)
    with pytest.raises(DataError, match=rf"^{path}: reading \S+ files needs the {package} "
                                        r"package: pip install 'hamid\[lab\]'$"):
        _read(path)


def test_missing_library_through_the_cli(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from hamid.cli.app import cli

    path = tmp_path / "run.h5"
    path.write_bytes(b"\x00" * 16)
    monkeypatch.setitem(sys.modules, "h5py", None)
    result = CliRunner().invoke(cli, ["fit", str(path)])
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert "pip install 'hamid[lab]'" in result.output


def test_split_names_the_inner_path(tmp_path):
    assert lab_formats.split("a/run.h5:/g/x") == ("a/run.h5", "/g/x")
    assert lab_formats.split("run.MAT:data") == ("run.MAT", "data")
    assert lab_formats.split("run.csv") == ("run.csv", None)
    assert lab_formats.format_of("run.h5:/g") == "hdf5" and lab_formats.format_of("a.csv") is None
    odd = tmp_path / "odd.h5:x.h5"   # a file whose name has the separator is that file
    odd.write_bytes(b"")
    assert lab_formats.split(str(odd)) == (str(odd), None)


def test_missing_file(tmp_path):
    with pytest.raises(DataError, match=rf"^{tmp_path}/no.h5: no such file$"):
        _read(f"{tmp_path}/no.h5:/g")


def test_cli_fits_an_hdf5_group_with_columns(tmp_path, sample, truth):
    """`hamid fit run.h5:/bench/run --columns ...` through the command line, JSON out."""
    from click.testing import CliRunner

    from hamid.cli.app import cli

    columns, _ = sample
    path = tmp_path / "run.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("bench/run")
        for name, stored in zip(NAMES, ["trajectory", "t", "disp", "vel"], strict=True):
            group.create_dataset(stored, data=columns[name])
    result = CliRunner().invoke(cli, ["fit", f"{path}:/bench/run", "--model", "duffing",
                                      "--columns", "x=disp,v=vel", "--format", "json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    got = {p["name"]: p["estimate"] for p in report["parameters"]}
    for name, value in truth.items():
        assert got[name] == pytest.approx(value, rel=1e-10)


def test_seven_single_empty_cells_leave_the_standard_errors_as_they_were():
    """7 empty cells in a damped record of 4,000 rows once cut it into 8 trajectories,
    each with its own energy level, and raised the damping's standard error threefold;
    now no standard error grows by more than a quarter."""
    from conftest import DUFFING, with_noise

    system = {**DUFFING, "initial": [{"x": 1.0, "v": 0.0}], "damping": {"c_x": 0.05},
              "simulate": {"t_end": 200.0, "dt": 0.05, "seed": 1}}
    frame = with_noise(hamid.simulate(system), 0.01, seed=3)
    holed = frame.copy()
    rows = np.random.default_rng(0).choice(np.arange(50, len(frame) - 50), 7, replace=False)
    holed.loc[rows, "x"] = np.nan
    full, with_holes = (hamid.fit(f, damping="viscous") for f in (frame, holed))
    assert with_holes.to_dict()["data"]["n_trajectories"] == 1
    for p, q in zip(full.parameters, with_holes.parameters, strict=True):
        assert q.stderr <= 1.25 * p.stderr, (p.name, q.stderr / p.stderr)
        assert abs(q.estimate - p.estimate) < p.stderr, p.name
