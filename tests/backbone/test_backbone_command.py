"""`hamid backbone` and `FitResult.backbone`: the report, its table, CSV, JSON and figure,
and the errors of bad input (one line, nothing on stdout, no file left)."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import hamid_command, one_line_error
from scipy.special import ellipk

import hamid
from hamid.result.fit_result import FitResult

HAMID = hamid_command()
SYSTEM = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
          "damping": {"c_x": 0.04},
          "initial": [{"x": 1.2, "v": 0.0}, {"x": 0.5, "v": 0.2}],
          "simulate": {"t_end": 30.0, "dt": 0.02}}
COLUMNS = ["mode", "energy", "amplitude_x", "frequency_hz", "frequency_hz_low",
           "frequency_hz_high", "damping_ratio", "damping_ratio_low", "damping_ratio_high"]


def _frequency(amplitude: float, k: float = 1.0, k3: float = 0.5) -> float:
    omega2 = k + k3 * amplitude**2
    return math.sqrt(omega2) / (4 * ellipk(k3 * amplitude**2 / (2 * omega2)))


@pytest.fixture(scope="module")
def data() -> pd.DataFrame:
    return hamid.simulate(SYSTEM)


@pytest.fixture(scope="module")
def result(data) -> FitResult:
    return hamid.fit(data, model="duffing", damping="viscous")


@pytest.fixture()
def files(tmp_path, result, data):
    report, recording = tmp_path / "fit.json", tmp_path / "decay.csv"
    report.write_text(json.dumps(result.to_dict()))
    data.to_csv(recording, index=False)
    return report, recording


def _run(*args, cwd=None):
    return subprocess.run([*HAMID, "backbone", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd)


def test_fit_result_backbone_is_the_true_backbone(result):
    table = result.backbone([0.2, 0.6, 1.0])
    assert list(table.columns) == COLUMNS
    assert table["amplitude_x"].to_numpy() == pytest.approx([0.2, 0.6, 1.0], rel=1e-12)
    for _, row in table.iterrows():
        assert row["frequency_hz"] == pytest.approx(_frequency(row["amplitude_x"]), rel=1e-5)
        assert row["frequency_hz_low"] < row["frequency_hz"] < row["frequency_hz_high"]
        assert row["damping_ratio_low"] < row["damping_ratio"] < row["damping_ratio_high"]
    # viscous c = 0.04 at small amplitude: c / (2 omega), omega = 1
    small = result.backbone([1e-3])
    assert small["damping_ratio"][0] == pytest.approx(0.02, rel=1e-3)
    assert table.attrs["report"]["schema"] == "hamid.backbone/1"


def test_fit_result_backbone_by_energy_and_with_data(result, data):
    table = result.backbone(energies=[0.3])
    amplitude = table["amplitude_x"][0]
    assert amplitude**2 / 2 + 0.5 * amplitude**4 / 4 == pytest.approx(0.3, rel=1e-6)
    table = result.backbone(data=data, points=5)
    document = table.attrs["report"]
    assert len(table) == 5
    assert [d["trajectory"] for d in document["data"]] == [1, 2]
    largest = max(p["amplitude"] for d in document["data"] for p in d["points"])
    assert table["amplitude_x"].to_numpy() == pytest.approx(
        np.linspace(0.02 * largest, largest, 5), rel=1e-9)
    for d in document["data"]:
        for p in d["points"]:   # decaying: within 1% of the conservative backbone
            assert p["frequency_hz"] == pytest.approx(_frequency(p["amplitude"]), rel=1e-2)


def test_the_command_writes_table_json_and_csv(files, tmp_path):
    report, recording = files
    done = _run(report, "--amplitudes", "0.2,1")
    assert done.returncode == 0, done.stderr
    assert "amplitude x" in done.stdout and "mode 1" in done.stdout
    done = _run(report, recording, "--points", "4", "--format", "json")
    document = json.loads(done.stdout)
    assert document["schema"] == "hamid.backbone/1"
    assert set(document) >= {"schema", "model", "level", "modes", "data"}
    assert len(document["modes"][0]["points"]) == 4
    assert set(document["modes"][0]["points"][0]) == {
        "energy", "amplitude", "frequency_hz", "frequency_hz_low", "frequency_hz_high",
        "damping_ratio", "damping_ratio_low", "damping_ratio_high"}
    assert document["data"][0]["points"][0].keys() == {"t", "amplitude", "frequency_hz"}
    out = tmp_path / "curve.csv"
    done = _run(report, "--energies", "0.1,0.4", "-o", out)
    assert done.returncode == 0 and done.stdout == ""
    table = pd.read_csv(out)
    assert list(table.columns) == COLUMNS
    assert table["energy"].to_numpy() == pytest.approx([0.1, 0.4], rel=1e-12)


def test_the_command_draws_the_figure(files, tmp_path):
    report, recording = files
    out = tmp_path / "backbone.png"
    done = _run(report, recording, "-o", out)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_driven_recording_sets_the_range_but_its_periods_are_left_out(tmp_path):
    """Up-crossings of a driven record time the drive, not the free orbits: 9,205 such
    "periods" of the Silverbox were shown as its backbone's points."""
    import tomllib

    from conftest import DRIVEN_DUFFING_MODEL

    model = tmp_path / "driven.toml"
    model.write_text(DRIVEN_DUFFING_MODEL)
    system = tomllib.loads(DRIVEN_DUFFING_MODEL)
    system["forcing"]["signals"] = {"F": {"kind": "sine", "amplitude": 2.0,
                                          "frequency": 0.2}}
    frame = hamid.simulate({**system, "parameters": {"m": 1.5, "k": 4.0, "k3": 2.0},
                            "damping": {"c_x": 0.3}, "initial": [{"x": 0.0, "v": 0.0}],
                            "simulate": {"t_end": 60.0, "dt": 0.02}})
    fitted = hamid.fit(frame, str(model), damping="viscous")
    (tmp_path / "fit.json").write_text(json.dumps(fitted.to_dict()))
    frame.to_csv(tmp_path / "driven.csv", index=False)
    done = _run("fit.json", "driven.csv", "--format", "json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    assert document["data"] == []
    assert document["notes"] == ["the recording is driven: its periods are the drive's, "
                                 "not the free orbits', and are left out"]
    assert done.stderr == f"note: {document['notes'][0]}\n"
    largest = (frame["x"].max() - frame["x"].min()) / 2     # the forced swing, about so
    top = document["modes"][0]["points"][-1]["amplitude"]["x"]
    assert 0.8 * largest < top <= largest


@pytest.mark.parametrize(("args", "code", "words"), [
    (["--amplitudes", "0.1,abc"], 2, ["--amplitudes", "0.1,abc", "numbers"]),
    (["--amplitudes", "0.1", "--energies", "1"], 2, ["--amplitudes", "--energies"]),
    (["--mode", "2"], 2, ["--mode 2", "1 mode"]),
    (["--coordinate", "y"], 2, ["--coordinate", "'y'"]),
    (["--amplitudes", "-0.5"], 1, ["amplitude -0.5", "not positive"]),
    (["-o", "out.xyz"], 2, ["out.xyz", "extension"]),
])
def test_bad_options_are_one_line_errors(files, tmp_path, args, code, words):
    report, _ = files
    done = _run(report, *args, "-o", tmp_path / "out.json") if "-o" not in args \
        else _run(report, *args, cwd=tmp_path)
    one_line_error(done, code, *words)
    assert not (tmp_path / "out.json").exists() and not (tmp_path / "out.xyz").exists()


def test_a_level_above_the_rim_is_a_one_line_error(result, tmp_path):
    report = result.to_dict()
    for p in report["parameters"]:   # a softening spring: V = x²/2 − x⁴/4, rim 0.25
        p["estimate"] = {"k": 1.0, "k3": -1.0}.get(p["name"], p["estimate"])
    path = tmp_path / "soft.json"
    path.write_text(json.dumps(report))
    done = _run(path, "--energies", "0.1,0.8", "-o", tmp_path / "out.json")
    one_line_error(done, 1, "energy 0.8", "above the well's rim at 0.25", "x = ")
    assert not (tmp_path / "out.json").exists()


def test_missing_files_and_reports_without_the_parts_needed(files, tmp_path):
    report, _ = files
    one_line_error(_run(tmp_path / "none.json"), 1, "none.json")
    one_line_error(_run(report, tmp_path / "none.csv"), 1, "none.csv")
    not_a_report = tmp_path / "other.json"
    not_a_report.write_text(json.dumps({"schema": "hamid.fit/1", "model": {}}))
    one_line_error(_run(not_a_report), 1, "other.json")


def test_a_model_of_two_coordinates_has_the_backbone_of_each_normal_mode(tmp_path):
    """Two masses with viscous dampers: at small amplitude each mode's frequency is the
    linear eigenfrequency sqrt(eig(K, M)) of the fitted parameters, and its damping ratio
    the modal phi' C phi / (2 omega) (phi mass-normalised), written out here; the bands
    hold it; the curve through the command line as JSON."""
    import scipy.linalg

    model = ('[model]\nname = "two-mass"\ncoordinates = ["x1", "x2"]\n'
             'velocities = ["v1", "v2"]\nenergy = "(v1**2 + m*v2**2)/2 + k1*x1**2/2 + '
             'k2*(x2 - x1)**2/2 + k3*(x2 - x1)**4/4"\nparameters = ["m", "k1", "k2", "k3"]\n')
    (tmp_path / "two.toml").write_text(model)
    system = {"model": {"name": "two-mass", "coordinates": ["x1", "x2"],
                        "velocities": ["v1", "v2"],
                        "energy": "(v1**2 + m*v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2"
                                  " + k3*(x2 - x1)**4/4"},
              "parameters": {"m": 2.0, "k1": 1.5, "k2": 0.8, "k3": 0.3},
              "damping": {"c_x1": 0.02, "c_x2": 0.03},
              "initial": [{"x1": 0.5, "x2": -0.3, "v1": 0.0, "v2": 0.2}],
              "simulate": {"t_end": 60.0, "dt": 0.04}}
    fitted = hamid.fit(hamid.simulate(system), tmp_path / "two.toml", damping="viscous")
    e = fitted.estimates
    K = np.array([[e["k1"] + e["k2"], -e["k2"]], [-e["k2"], e["k2"]]])
    M, C = np.diag([1.0, e["m"]]), np.diag([e["c_x1"], e["c_x2"]])
    omega2, shapes = scipy.linalg.eigh(K, M)
    for mode in (1, 2):
        omega, phi = np.sqrt(omega2[mode - 1]), shapes[:, mode - 1]
        curve = fitted.backbone(amplitudes=[1e-4], mode=mode, coordinate="x1")
        assert curve["frequency_hz"][0] == pytest.approx(omega / (2 * np.pi), rel=1e-7)
        assert curve["damping_ratio"][0] == pytest.approx(phi @ C @ phi / (2 * omega),
                                                          rel=1e-6)
        assert curve["frequency_hz_low"][0] < curve["frequency_hz"][0] \
            < curve["frequency_hz_high"][0]
    path = tmp_path / "two.json"
    path.write_text(json.dumps(fitted.to_dict()))
    done = _run(path, "--amplitudes", "0.1,0.3", "--mode", "1", "--coordinate", "x2",
                "--format", "json")
    assert done.returncode == 0, done.stderr
    [mode] = json.loads(done.stdout)["modes"]
    assert mode["coordinate"] == "x2"
    assert [p["amplitude"]["x2"] for p in mode["points"]] == pytest.approx([0.1, 0.3])
    # the quartic coupling hardens the mode
    assert mode["points"][1]["frequency_hz"] > mode["points"][0]["frequency_hz"]


@pytest.mark.slow
def test_the_real_double_pendulum_each_mode_with_the_recording(tmp_path):
    """The sample double pendulum, hanging at (pi, pi): each mode's backbone through the
    command line with the recording's points overlaid; at small amplitude the frequencies
    are the report's linear ones. About a minute of CPU (a trigonometric energy)."""
    pytest.importorskip("matplotlib")
    from matplotlib.figure import Figure

    from hamid.plot import backbone_figure

    sample = Path(__file__).parents[2] / "sample_data"
    result = hamid.fit(str(sample / "double_pendulum.csv"),
                       str(sample / "double_pendulum.toml"), velocity="savgol")
    report = tmp_path / "r.json"
    report.write_text(json.dumps(result.to_dict()))
    linear = result.dissipation["small_amplitude"]["modes"]
    for mode in (1, 2):
        args = [str(report), str(sample / "double_pendulum.csv"), "--mode", str(mode),
                "--coordinate", "theta2", "--amplitudes", "0.01,0.5"]
        done = subprocess.run([*HAMID, "backbone", *args, "-o", str(tmp_path / "b.json")],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        document = json.loads((tmp_path / "b.json").read_text())
        (curve,) = document["modes"]
        assert curve["points"][0]["frequency_hz"] == pytest.approx(
            linear[mode - 1]["frequency_hz"], rel=1e-3)
        assert curve["points"][1]["frequency_hz"] < curve["points"][0]["frequency_hz"]
        (recorded,) = document["data"]
        assert len(recorded["points"]) >= 10
        figure = backbone_figure.figure(document)
        assert isinstance(figure, Figure)
        top = figure.axes[0]
        markers = [line for line in top.get_lines() if line.get_linestyle() == "None"]
        assert [len(line.get_xdata()) for line in markers] == [len(recorded["points"])]
        done = subprocess.run([*HAMID, "backbone", *args, "-o", str(tmp_path / "b.png")],
                              capture_output=True, text=True)
        assert done.returncode == 0 and done.stdout == "", done.stderr
        assert (tmp_path / "b.png").read_bytes()[:4] == b"\x89PNG"
