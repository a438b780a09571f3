"""`hamid predict` and `FitResult.predict`: the fitted model over a recording it never saw,
checked against the known motion of simulated systems (hamid/prediction.py)."""

from __future__ import annotations

import copy
import json
import re
import subprocess
from pathlib import Path

import jsonschema
import numpy as np
import pandas as pd
import pytest
from helpers import hamid_command, one_line_error

import hamid
from hamid.errors import DataError, ModelError
from hamid.result.fit_result import FitResult

HAMID = hamid_command()
SCHEMA = Path(__file__).parent.parent / "hamid" / "schema" / "predict-1.json"
# A damped Duffing oscillator, x'' = -k x - k3 x^3 - c x', fitted on two free decays.
FITTED = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
          "damping": {"c_x": 0.05},
          "initial": [{"x": 1.0, "v": 0.0}, {"x": 0.4, "v": 0.3}],
          "simulate": {"t_end": 30.0, "dt": 0.05}}
# Other initial states, which the fit never saw.
UNSEEN = [{"x": -0.8, "v": 0.5}, {"x": 0.2, "v": -1.1}]


def _simulated(initial: list[dict[str, float]], **settings: float) -> pd.DataFrame:
    system = copy.deepcopy(FITTED)
    system["initial"] = initial
    system["simulate"].update(settings)
    return hamid.simulate(system)


@pytest.fixture(scope="module")
def result() -> FitResult:
    fitted = hamid.fit(hamid.simulate(FITTED), model="duffing", damping="viscous")
    assert fitted.method["kind"] == "joint"
    return fitted


@pytest.fixture(scope="module")
def unseen() -> pd.DataFrame:
    return _simulated(UNSEEN)


@pytest.fixture()
def files(tmp_path, result, unseen) -> dict[str, Path]:
    """The fit's report and the unseen recording, as files."""
    report, data = tmp_path / "fit.json", tmp_path / "unseen.csv"
    report.write_text(json.dumps(result.to_dict()))
    unseen.to_csv(data, index=False)
    return {"report": report, "data": data}


def _with_estimate(result: FitResult, **values: float) -> FitResult:
    """The result with some estimates replaced, as by editing its JSON report."""
    report = result.to_dict()
    for p in report["parameters"]:
        p["estimate"] = values.get(p["name"], p["estimate"])
    return FitResult.from_dict(report)


def test_the_prediction_of_an_unseen_recording_is_its_true_motion(result, unseen):
    predicted = result.predict(unseen)
    frame = predicted.frame
    assert list(frame.columns) == ["trajectory", "t", "x", "x_predicted", "v", "v_predicted"]
    assert len(frame) == len(unseen)
    for name in ("x", "v"):
        amplitude = np.abs(unseen[name]).max()
        error = np.sqrt(np.mean((frame[f"{name}_predicted"] - unseen[name]) ** 2))
        assert error < 1e-4 * amplitude, (name, error)
        # the reported errors are those of the samples, by their definition
        assert predicted.channels.loc[name, "rms"] == pytest.approx(error, rel=1e-6, abs=1e-15)
        spread = np.sqrt(np.mean((unseen[name] - unseen[name].mean()) ** 2))
        assert predicted.channels.loc[name, "nrmse"] == pytest.approx(error / spread, rel=1e-6,
                                                                      abs=1e-15)


def test_the_fitted_start_is_the_true_start(result, unseen):
    document = result.predict(unseen).to_dict()
    assert [entry["trajectory"] for entry in document["trajectories"]] == [1, 2]
    for entry, truth in zip(document["trajectories"], UNSEEN, strict=True):
        assert entry["start"] == pytest.approx(truth, abs=1e-7)
        # one period of x'' = -x - 0.5 x^3 (about 5 s at these amplitudes) of 0.05 s steps
        assert 60 < entry["start_samples"] < 130


def test_a_wrong_stiffness_predicts_much_worse(result, unseen):
    good = result.predict(unseen).channels["nrmse"]
    wrong = _with_estimate(result, k=1.1 * result.estimates["k"]).predict(unseen).channels
    assert (wrong["nrmse"] > 0.05).all()
    assert (wrong["nrmse"] > 1e4 * good).all()


def test_from_rest_a_free_decay_stays_at_rest(result, unseen):
    predicted = result.predict(unseen, from_rest=True)
    assert (predicted.frame[["x_predicted", "v_predicted"]].to_numpy() == 0).all()
    document = predicted.to_dict()
    assert document["start"] == "rest"
    assert all(entry["start_samples"] is None for entry in document["trajectories"])
    x = unseen["x"].to_numpy()
    assert document["channels"]["x"]["rms"] == pytest.approx(np.sqrt(np.mean(x ** 2)))
    assert document["channels"]["x"]["nrmse"] == pytest.approx(np.sqrt(np.mean(x ** 2))
                                                               / x.std())


def test_a_trajectory_too_short_to_fit_its_start_is_named(result):
    short = _simulated([{"x": 0.5, "v": 0.0}], t_end=0.5)   # 11 samples
    with pytest.raises(DataError, match="trajectory 1: 11 samples, too few"):
        result.predict(short)
    assert len(result.predict(short, from_rest=True).frame) == 11


@pytest.mark.parametrize(("c", "after"), [(-0.6, False), (-3.0, True)])
def test_a_motion_that_blows_up_is_named_with_its_time(result, unseen, c, after):
    """Negative damping: the motion grows without bound, past the first period (one
    oscillation, about 5 s) for c = -0.6 and within it for c = -3."""
    growing = _with_estimate(result, c_x=c)
    with pytest.raises(ModelError, match=r"trajectory 1: .* escapes") as raised:
        growing.predict(unseen)
    pattern = (r"near (\d+\.?\d*) s after its first sample" if after
               else r"near t = (\d+\.?\d*) s;")
    found = re.search(pattern, str(raised.value))
    assert found, str(raised.value)
    assert (0 < float(found[1]) < 5.5) if after else (5.5 < float(found[1]) < 30)


def test_reading_options_are_those_of_the_report(tmp_path, unseen):
    renamed = hamid.simulate(FITTED).rename(columns={"x": "pos", "v": "vel", "t": "time"})
    fitted = hamid.fit(renamed, model="duffing", damping="viscous",
                       columns={"x": "pos", "v": "vel"}, time="time")
    data = unseen.rename(columns={"x": "pos", "v": "vel", "t": "time"})
    channels = fitted.predict(data).channels
    assert (channels["nrmse"] < 1e-4).all()
    # given reading options win over the report's
    other = unseen.rename(columns={"x": "X", "v": "V", "t": "time"})
    with pytest.raises(DataError):
        fitted.predict(other)
    assert (fitted.predict(other, columns={"x": "X", "v": "V"}).channels["nrmse"] < 1e-4).all()


# The command line


def _run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([*HAMID, "predict", *map(str, args)], capture_output=True, text=True)


def test_accelerations_alone_are_scored_against_the_equations_of_motion(result, unseen,
                                                                        tmp_path):
    """An unseen recording of accelerations alone (in g, 1% noise): the prediction scores
    the acceleration only, to the noise put in, and its states follow the true motion;
    positions and velocities, integrated from the accelerations, are not scored."""
    x, v = unseen["x"], unseen["v"]
    a = -(x + 0.5 * x**3 + 0.05 * v)             # the system's equation of motion
    noise = 0.01 * a.std() * np.random.default_rng(1).standard_normal(len(a))
    data = tmp_path / "accelerometer.csv"
    unseen[["trajectory", "t"]].assign(a_g=(a + noise) / 9.80665).to_csv(data, index=False)
    predicted = result.predict(str(data))
    document = predicted.to_dict()
    jsonschema.validate(document, json.loads(SCHEMA.read_text()))
    assert list(document["channels"]) == ["a"] and document["not_recorded"] == ["x", "v"]
    assert document["channels"]["a"]["rms"] == pytest.approx(np.sqrt(np.mean(noise**2)),
                                                             rel=0.05)
    frame = predicted.frame
    assert list(frame.columns) == ["trajectory", "t", "x_predicted", "v_predicted", "a",
                                   "a_predicted"]
    assert np.abs(frame["x_predicted"] - x).max() < 0.01 * x.abs().max()
    table = _run(_report(tmp_path, result), data)
    assert "not recorded, so predicted but not scored: x, v" in table.stdout
    # from rest too (the zero state was made as long as the compared channels: 3 for 2)
    from_rest = result.predict(str(data), from_rest=True).to_dict()
    assert list(from_rest["channels"]) == ["a"]
    assert all(value == 0.0 for entry in from_rest["trajectories"]
               for value in entry["start"].values())


def test_derived_velocities_are_predicted_not_scored(result, unseen):
    predicted = result.predict(unseen.drop(columns="v"))
    document = predicted.to_dict()
    assert list(document["channels"]) == ["x"] and document["not_recorded"] == ["v"]
    assert document["channels"]["x"]["nrmse"] < 1e-4
    assert list(predicted.frame.columns) == ["trajectory", "t", "x", "x_predicted",
                                             "v_predicted"]
    np.testing.assert_allclose(predicted.frame["v_predicted"], unseen["v"], atol=1e-5)


def _report(tmp_path: Path, result: FitResult) -> Path:
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(result.to_dict()))
    return path


def test_json_follows_the_schema(files):
    done = _run(files["report"], files["data"], "--format", "json")
    assert done.returncode == 0, done.stderr
    document = json.loads(done.stdout)
    jsonschema.validate(document, json.loads(SCHEMA.read_text()))
    assert document["schema"] == "hamid.predict/1"
    assert document["source"] == str(files["report"])
    assert document["data"] == [str(files["data"])]
    assert document["samples"] == 1202
    assert set(document["channels"]) == {"x", "v"} and document["not_recorded"] == []
    assert all(c["nrmse"] < 1e-4 for c in document["channels"].values())


def test_the_schema_check_can_fail(files):
    document = json.loads(_run(files["report"], files["data"], "--format", "json").stdout)
    document["channels"]["x"]["rms"] = -1.0
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(document, json.loads(SCHEMA.read_text()))


def test_csv_is_the_time_series(files, unseen):
    done = _run(files["report"], files["data"], "--format", "csv")
    assert done.returncode == 0, done.stderr
    frame = pd.read_csv(pd.io.common.StringIO(done.stdout))
    assert list(frame.columns) == ["trajectory", "t", "x", "x_predicted", "v", "v_predicted"]
    np.testing.assert_array_equal(frame["x"], unseen["x"])
    np.testing.assert_allclose(frame["x_predicted"], unseen["x"], atol=1e-6)


def test_table_is_the_default(files):
    done = _run(files["report"], files["data"])
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("hamid predict — model duffing, 2 trajectories, 1202 samples")
    assert any(line.split()[:1] == ["x"] for line in lines)
    assert "NRMSE" in done.stdout and done.stderr == ""


@pytest.mark.parametrize(("name", "first"), [("out.json", "{"), ("out.csv", "trajectory,t,x"),
                                              ("out.txt", "hamid predict")])
def test_output_format_by_extension(files, tmp_path, name, first):
    out = tmp_path / name
    done = _run(files["report"], files["data"], "-o", out)
    assert done.returncode == 0 and done.stdout == "", done.stderr
    assert out.read_text().startswith(first)


def test_reading_options_from_the_report_and_given(tmp_path, unseen):
    renamed = hamid.simulate(FITTED).rename(columns={"x": "pos", "v": "vel"})
    fit_data, report = tmp_path / "fit.csv", tmp_path / "fit.json"
    renamed.to_csv(fit_data, index=False)
    done = subprocess.run([*HAMID, "fit", fit_data, "--model", "duffing", "--damping", "viscous",
                           "--columns", "x=pos,v=vel", "-o", report], capture_output=True)
    assert done.returncode == 0, done.stderr
    same = tmp_path / "same.csv"
    unseen.rename(columns={"x": "pos", "v": "vel"}).to_csv(same, index=False)
    assert _run(report, same, "--format", "json").returncode == 0
    other = tmp_path / "other.csv"
    unseen.rename(columns={"x": "X", "v": "V"}).to_csv(other, index=False)
    one_line_error(_run(report, other), 1, "pos")
    done = _run(report, other, "--columns", "x=X,v=V", "--format", "json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["channels"]["x"]["nrmse"] < 1e-4


def test_errors_are_one_line_and_write_nothing(files, tmp_path, result):
    out = tmp_path / "out.json"
    prediction = tmp_path / "prediction.json"
    assert _run(files["report"], files["data"], "-o", prediction).returncode == 0
    # not a fit report
    one_line_error(_run(prediction, files["data"], "-o", out), 1, str(prediction),
                   "not a hamid fit result")
    # data without the model's coordinates
    other = tmp_path / "other.csv"
    pd.DataFrame({"t": np.arange(30) * 0.1, "y": np.zeros(30)}).to_csv(other, index=False)
    one_line_error(_run(files["report"], other, "-o", out), 1, "x")
    # a trajectory too short to fit its start
    short = tmp_path / "short.csv"
    _simulated([{"x": 0.5, "v": 0.0}], t_end=0.5).to_csv(short, index=False)
    one_line_error(_run(files["report"], short, "-o", out), 1, "trajectory 1", "too few")
    # the motion blows up
    growing = tmp_path / "growing.json"
    growing.write_text(json.dumps(_with_estimate(result, c_x=-0.6).to_dict()))
    one_line_error(_run(growing, files["data"], "-o", out), 1, "trajectory 1", "escapes",
                   "near t = ")
    # the output is an input
    one_line_error(_run(files["report"], files["data"], "-o", files["data"]), 2, "-o",
                   str(files["data"]))
    one_line_error(_run(files["report"], files["data"], "-o", tmp_path / "out.png"), 2,
                   "'.png'")
    assert not out.exists()


def test_a_path_object_names_the_data_as_a_string_does(tmp_path):
    """`FitResult.predict` takes a pathlib.Path as `hamid.fit` does."""
    from pathlib import Path

    data = tmp_path / "decay.csv"
    hamid.simulate("sample_data/duffing.toml").to_csv(data, index=False)
    result = hamid.fit(data, "duffing")
    by_path, by_text = result.predict(Path(data)), result.predict(str(data))
    assert by_path.to_dict()["data"] == by_text.to_dict()["data"] == [str(data)]
