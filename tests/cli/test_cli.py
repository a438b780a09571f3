"""Tests for the `hamid` command line: exit codes, stdout/stderr separation, files, messages.

Most tests run the click group in-process with `CliRunner` (click 8.2+ keeps stdout and
stderr apart); a few run the installed `hamid` command in a real process, for what only a
real process shows (a closed pipe, the console-script entry point).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from helpers import hamid_command
from scipy import stats

from hamid import __version__
from hamid.cli.app import cli

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ROOT / "sample_data"
DUFFING_TOML = str(SAMPLES / "duffing.toml")
DUFFING_CSV = str(SAMPLES / "duffing.csv")
PENG_TOML = str(SAMPLES / "peng_quadratic.toml")
PENG_CSV = str(SAMPLES / "peng_quadratic.csv")
HENON_CSV = str(SAMPLES / "henon_heiles.csv")
PENG_PARAMETERS = ["w1sq", "w2sq", "a1", "a2", "a3", "a6"]
META_PREFIX = "# hamid: "
META_KEYS = ["model", "parameters", "initial", "trajectories", "noise", "seed", "integrator",
             "hamid_version"]
# docs/output.md: the top-level keys of a "hamid.fit/1" result and those of its parts.
RESULT_KEYS = {
    "schema": None,
    "hamid_version": None,
    "model": {"name", "energy", "coordinates", "velocities", "parameters"},
    "data": {"sources", "n_samples", "n_trajectories", "columns", "velocity_source"},
    "method": {"kind", "kind_reason", "weak_window", "damping", "weighting", "noise",
               "bias_correction", "covariance", "level", "fixed"},
    "parameters": None,
    "energy_levels": None,
    "residuals": {"rms", "max_abs", "relative_rms", "r_squared", "lag1_autocorrelation",
                  "drift"},
    "conditioning": {"condition_number", "singular_values", "weakest_direction", "status"},
    "warnings": None,
}
PARAMETER_KEYS = {"name", "role", "estimate", "stderr", "ci_low", "ci_high", "truth", "fixed"}
LEVEL_KEYS = {"trajectory", "h", "stderr", "n_samples"}
RESIDUAL_COLUMNS = ["trajectory", "t", "energy", "residual", "weight"]
# Clean simulated data must give back the true parameters this closely (the README: about 1e-8).
CLEAN = 1e-7
# Tests of the plumbing (which column, which parameter) only need to know the fit is right.
PLUMBING = 1e-5

DUFFING_SYSTEM = """\
[model]
builtin = "duffing"

[parameters]
k = {k}
k3 = {k3}

[[initial]]
x = {x0}
v = 0.0

[simulate]
t_end = 2.0
dt = 0.1
{extra}
"""


@pytest.fixture
def runner():
    return CliRunner()


def invoke(runner, args, **kwargs):
    return runner.invoke(cli, [str(a) for a in args], prog_name="hamid", **kwargs)


def assert_ok(result):
    assert result.exit_code == 0, (result.stdout, result.stderr, result.exception)
    assert "Traceback" not in result.output


def assert_fails(result, code, *names):
    """A failure: the exit code, one message naming the culprit, nothing on stdout."""
    assert result.exit_code == code, (result.exit_code, result.stdout, result.stderr)
    # A handled error ends in SystemExit; anything else escaped the CLI's error handling.
    assert isinstance(result.exception, SystemExit), result.exception
    assert result.stdout == ""
    assert "Traceback" not in result.output
    assert "Error: " in result.stderr
    for name in names:
        assert name in result.stderr, (name, result.stderr)


def fit_json(runner, *args):
    result = invoke(runner, ["fit", *args, "--format", "json"])
    assert_ok(result)
    return json.loads(result.stdout)


def estimates(result_dict):
    return {p["name"]: p["estimate"] for p in result_dict["parameters"]}


def write_system(folder, name="system.toml", *, k=1.0, k3=0.5, x0=1.0, extra=""):
    path = folder / name
    path.write_text(DUFFING_SYSTEM.format(k=k, k3=k3, x0=x0, extra=extra))
    return path


def read_metadata_line(text):
    first = text.splitlines()[0]
    assert first.startswith(META_PREFIX), first[:80]
    return json.loads(first[len(META_PREFIX):])


# ---------------------------------------------------------------------------------------------
# --version, --help, models


def test_version(runner):
    result = invoke(runner, ["--version"])
    assert_ok(result)
    assert result.stdout == f"hamid, version {__version__}\n"
    assert result.stderr == ""


@pytest.mark.parametrize("option", ["--help", "-h"])
def test_group_help_lists_every_command(runner, option):
    result = invoke(runner, [option])
    assert_ok(result)
    assert result.stdout.startswith("Usage: hamid ")
    for command in ["simulate", "fit", "report", "models", "--debug", "--version"]:
        assert command in result.stdout
    assert result.stderr == ""


@pytest.mark.parametrize("help_option", ["--help", "-h"])
@pytest.mark.parametrize(("command", "options"), [
    ("simulate", ["--config", "--seed", "--no-meta", "--max-samples", "--format", "--output"]),
    ("fit", ["--model", "--columns", "--fix", "--cov", "--level", "--bootstrap", "--seed",
             "--format", "--output", "--residuals", "--method", "--time", "--trajectory"]),
    ("report", ["RESULT.json", "--format", "--output"]),
    ("models", ["NAME"]),
])
def test_subcommand_help(runner, command, options, help_option):
    result = invoke(runner, [command, help_option])
    assert_ok(result)
    assert result.stdout.startswith(f"Usage: hamid {command} ")
    for option in options:
        assert option in result.stdout, option
    assert result.stderr == ""


def test_models_lists_builtins(runner):
    result = invoke(runner, ["models"])
    assert_ok(result)
    starts = [line.split()[0] for line in result.stdout.splitlines() if line[:1].strip()]
    assert starts == ["peng-quadratic", "duffing", "henon-heiles", "poly:N:D"]
    assert "w1sq w2sq a1 a2 a3 a6" in result.stdout
    assert result.stderr == ""


def test_models_shows_one_in_full(runner):
    result = invoke(runner, ["models", "peng-quadratic"])
    assert_ok(result)
    fields = dict(line.split(":", 1) for line in result.stdout.splitlines())
    fields = {key: value.strip() for key, value in fields.items()}
    assert fields["name"] == "peng-quadratic"
    assert fields["coordinates"].split() == ["u1", "u2"]
    assert fields["velocities"].split() == ["v1", "v2"]
    assert fields["parameters"].split() == PENG_PARAMETERS
    assert fields["energy"].startswith("E = (v1**2 + v2**2)/2 + w1sq*u1**2/2")
    assert result.stderr == ""


def test_models_of_a_model_file(runner):
    result = invoke(runner, ["models", SAMPLES / "elastic_pendulum.toml"])
    assert_ok(result)
    assert "name:        elastic-pendulum" in result.stdout
    assert "coordinates: x y" in result.stdout
    assert "parameters:  k kL g" in result.stdout
    assert "kL*sqrt(x**2 + y**2)" in result.stdout


@pytest.mark.parametrize(("name", "code"), [("nosuch", 2), ("poly:x:3", 1)])
def test_models_unknown(runner, name, code):
    """An unknown name is a usage error (2); a malformed poly name a model error (1)."""
    assert_fails(invoke(runner, ["models", name]), code, repr(name))


# ---------------------------------------------------------------------------------------------
# simulate


def test_simulate_csv_file_carries_metadata(runner, tmp_path):
    out = tmp_path / "out.csv"
    result = invoke(runner, ["simulate", "--config", DUFFING_TOML, "-o", out])
    assert_ok(result)
    assert result.stdout == ""
    assert "simulated 2 trajectories" in result.stderr
    meta = read_metadata_line(out.read_text())
    assert set(meta) >= set(META_KEYS)
    assert meta["model"]["name"] == "duffing"
    assert meta["parameters"] == {"k": 1.0, "k3": 0.5}
    assert meta["initial"] == [{"x": 1.0, "v": 0.0}, {"x": 0.4, "v": 0.3}]
    assert meta["hamid_version"] == __version__
    frame = pd.read_csv(out, comment="#")
    assert list(frame.columns) == ["trajectory", "t", "x", "v"]
    # t = k*dt up to and including t_end = 30, dt = 0.05, for each of 2 trajectories.
    assert len(frame) == 2 * 601
    assert frame["t"].iloc[-1] == pytest.approx(30.0)


def test_simulate_of_one_trajectory_says_one_trajectory(runner, tmp_path):
    config = write_system(tmp_path)
    result = invoke(runner, ["simulate", "--config", config, "-o", tmp_path / "one.csv"])
    assert_ok(result)
    assert "simulated 1 trajectory, 21 samples (t = 0..2, dt = 0.1)" in result.stderr


def test_simulate_parquet_carries_metadata(runner, tmp_path):
    import pyarrow.parquet as pq

    out = tmp_path / "out.parquet"
    result = invoke(runner, ["simulate", "--config", DUFFING_TOML, "-o", out])
    assert_ok(result)
    assert result.stdout == ""
    schema = pq.read_schema(out)
    meta = json.loads(schema.metadata[b"hamid"])
    assert set(meta) >= set(META_KEYS)
    assert meta["parameters"] == {"k": 1.0, "k3": 0.5}
    assert schema.names == ["trajectory", "t", "x", "v"]


def test_simulate_to_stdout_keeps_messages_on_stderr(runner):
    result = invoke(runner, ["simulate", "--config", DUFFING_TOML, "-o", "-", "--format", "csv"])
    assert_ok(result)
    meta = read_metadata_line(result.stdout)
    assert meta["model"]["name"] == "duffing"
    assert "simulated" not in result.stdout
    assert "simulated 2 trajectories, 1202 samples" in result.stderr
    frame = pd.read_csv(io.StringIO(result.stdout), comment="#")
    assert list(frame.columns) == ["trajectory", "t", "x", "v"]
    assert len(frame) == 1202


def test_simulate_no_meta(runner, tmp_path):
    out = tmp_path / "out.csv"
    config = write_system(tmp_path)
    assert_ok(invoke(runner, ["simulate", "--config", config, "-o", out, "--no-meta"]))
    text = out.read_text()
    assert text.splitlines()[0] == "trajectory,t,x,v"
    assert "hamid" not in text


def test_simulate_seed_reproduces_the_noise(runner, tmp_path):
    config = write_system(tmp_path, extra="\n[noise]\nx = 0.01\n")

    def run(seed):
        result = invoke(runner, ["simulate", "--config", config, "-o", "-", "--seed", seed])
        assert_ok(result)
        return result.stdout

    first, again, other = run(1), run(1), run(2)
    assert first == again
    a = pd.read_csv(io.StringIO(first), comment="#")
    b = pd.read_csv(io.StringIO(other), comment="#")
    assert (a["t"] == b["t"]).all()
    assert (a["x"] != b["x"]).all()  # only x is noisy
    assert (a["v"] == b["v"]).all()
    assert read_metadata_line(first)["seed"] == 1
    assert read_metadata_line(other)["seed"] == 2


def _fail_while_writing(monkeypatch):
    """Make pyarrow's CSV writer write a little, then fail: a half-written output."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    def broken(table, stream, **kwargs):
        stream.write(b"trajectory,t,x,v\n1,0,")
        raise pa.ArrowInvalid("disk on fire")

    monkeypatch.setattr(pacsv, "write_csv", broken)


@pytest.mark.parametrize(("case", "names"), [
    ("escapes", ["trajectory 1", "escapes"]),
    ("bad_key", ["t_ends", "t_end"]),
    ("fails_while_writing", ["out.csv", "disk on fire"]),
])
def test_simulate_failure_leaves_existing_output_alone(runner, tmp_path, monkeypatch, case,
                                                       names):
    folder = tmp_path / "runs"
    folder.mkdir()
    if case == "escapes":
        config = write_system(tmp_path, k3=-1.0, x0=3.0)  # a softening spring: x runs away
    elif case == "bad_key":
        config = write_system(tmp_path, extra="t_ends = 3.0\n")
    else:
        config = write_system(tmp_path)
        _fail_while_writing(monkeypatch)
    out = folder / "out.csv"
    precious = b"precious,bytes\n1,2\n"
    out.write_bytes(precious)
    result = invoke(runner, ["simulate", "--config", config, "-o", out])
    assert_fails(result, 1, *names)
    assert out.read_bytes() == precious
    assert sorted(os.listdir(folder)) == ["out.csv"]  # no temporary file left behind


def test_simulate_max_samples_cap(runner, tmp_path):
    out = tmp_path / "out.csv"
    result = invoke(runner, ["simulate", "--config", DUFFING_TOML, "-o", out,
                             "--max-samples", "10"])
    assert_fails(result, 1, "max_samples", "1,202")
    assert not out.exists()


@pytest.mark.parametrize(("args", "code", "names"), [
    (["--config", "nosuch.toml"], 1, ["nosuch.toml"]),
    (["--config", DUFFING_TOML, "-o", "out.xlsx"], 2, ["out.xlsx"]),
    (["--config", DUFFING_TOML, "--format", "xlsx"], 2, ["--format", "xlsx"]),
    (["--config", DUFFING_TOML, "--seed", "-1"], 2, ["--seed"]),
    (["--config", DUFFING_TOML, "--max-samples", "0"], 2, ["--max-samples"]),
    (["-o", "-"], 2, ["--config"]),
])
def test_simulate_usage_and_file_errors(runner, tmp_path, monkeypatch, args, code, names):
    monkeypatch.chdir(tmp_path)
    assert_fails(invoke(runner, ["simulate", *args]), code, *names)
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------------------
# fit


@pytest.fixture(scope="module")
def simulated_duffing():
    """`hamid simulate` of the Duffing system to standard output (CSV with metadata)."""
    simulated = invoke(CliRunner(), ["simulate", "--config", DUFFING_TOML, "-o", "-",
                                     "--format", "csv"])
    assert_ok(simulated)
    return simulated.stdout


@pytest.mark.parametrize("method", [[], ["--method", "energy"]], ids=["auto", "energy"])
def test_pipeline_simulate_into_fit(runner, simulated_duffing, method):
    truth = read_metadata_line(simulated_duffing)["parameters"]
    result = invoke(runner, ["fit", "-", "--format", "json", *method], input=simulated_duffing)
    assert_ok(result)
    fitted = json.loads(result.stdout)
    assert fitted["schema"] == "hamid.fit/1"
    assert fitted["data"]["sources"] == ["<stdin>"]
    assert fitted["model"]["name"] == "duffing"  # from the metadata, not assumed
    assert set(estimates(fitted)) == set(truth)
    for p in fitted["parameters"]:
        assert p["truth"] == truth[p["name"]]
        assert abs(p["estimate"] / truth[p["name"]] - 1) < CLEAN, p


def test_fit_table_shows_every_parameter(runner):
    result = invoke(runner, ["fit", PENG_CSV])
    assert_ok(result)
    first_words = {line.split()[0] for line in result.stdout.splitlines() if line.strip()}
    assert first_words >= set(PENG_PARAMETERS)
    assert "peng-quadratic" in result.stdout.splitlines()[0]


def test_fit_json_has_every_spec_key(runner):
    result = fit_json(runner, PENG_CSV)
    assert set(result) >= set(RESULT_KEYS)
    for key, subkeys in RESULT_KEYS.items():
        if subkeys is not None:
            assert set(result[key]) >= subkeys, (key, subkeys - set(result[key]))
    assert result["schema"] == "hamid.fit/1"
    assert result["hamid_version"] == __version__
    assert [p["name"] for p in result["parameters"]] == PENG_PARAMETERS
    for p in result["parameters"]:
        assert set(p) >= PARAMETER_KEYS
        assert p["ci_low"] < p["estimate"] < p["ci_high"]
    assert len(result["energy_levels"]) == 3
    for level in result["energy_levels"]:
        assert set(level) >= LEVEL_KEYS
    assert result["data"]["n_samples"] == 3 * 801
    assert result["method"]["covariance"] == "hac"
    assert result["method"]["level"] == 0.95


@pytest.mark.parametrize("source", [
    [PENG_CSV],
    [str(SAMPLES / "peng_quadratic.parquet")],
    [PENG_CSV, str(SAMPLES / "peng_quadratic.parquet")],
], ids=["csv", "parquet", "two files"])
def test_fit_input_formats(runner, source):
    result = fit_json(runner, *source)
    assert result["data"]["sources"] == source
    assert result["data"]["n_trajectories"] == 3 * len(source)
    assert result["data"]["n_samples"] == 3 * 801 * len(source)
    truth = {p["name"]: p["truth"] for p in result["parameters"]}
    assert estimates(result) == pytest.approx(truth, rel=PLUMBING)
    assert truth["w2sq"] == 2.25


def test_fit_csv_has_one_row_per_parameter(runner):
    result = invoke(runner, ["fit", PENG_CSV, "--format", "csv"])
    assert_ok(result)
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert [row["name"] for row in rows] == PENG_PARAMETERS
    for row in rows:
        assert float(row["estimate"]) == pytest.approx(float(row["truth"]), rel=PLUMBING)


@pytest.mark.parametrize(("name", "check"), [
    ("result.json", lambda text: json.loads(text)["schema"] == "hamid.fit/1"),
    ("result.csv", lambda text: text.startswith("name,")),
    ("result.txt", lambda text: text.startswith("hamid fit")),
])
def test_fit_output_file_format_from_extension(runner, tmp_path, name, check):
    out = tmp_path / name
    result = invoke(runner, ["fit", DUFFING_CSV, "-o", out])
    assert_ok(result)
    assert result.stdout == ""
    assert check(out.read_text())


def test_fit_residuals_file(runner, tmp_path):
    out = tmp_path / "res.csv"
    result = invoke(runner, ["fit", DUFFING_CSV, "--format", "json", "--residuals", out])
    assert_ok(result)
    levels = {lv["trajectory"]: lv["h"] for lv in json.loads(result.stdout)["energy_levels"]}
    residuals = pd.read_csv(out)
    data = pd.read_csv(DUFFING_CSV, comment="#")
    assert list(residuals.columns) == RESIDUAL_COLUMNS
    assert len(residuals) == len(data)
    assert (residuals["trajectory"] == data["trajectory"]).all()
    assert (residuals["t"] == data["t"]).all()
    # Each residual is the sample's fitted energy minus its trajectory's level, and on
    # clean data that is small.
    level = residuals["trajectory"].map(levels)
    assert np.allclose(residuals["residual"], residuals["energy"] - level, rtol=0, atol=1e-13)
    assert (residuals["residual"].abs() / level).max() < PLUMBING
    assert np.isfinite(residuals["weight"]).all()
    assert (residuals["weight"] > 0).mean() > 0.5


def test_fit_residual_weights_are_never_negative(runner, tmp_path):
    # Weights are relative (a sample outside every window may weigh 0), but never negative.
    out = tmp_path / "res.csv"
    assert_ok(invoke(runner, ["fit", DUFFING_CSV, "--format", "json", "--residuals", out]))
    weights = pd.read_csv(out)["weight"]
    assert (weights >= 0).all(), weights[weights < 0]


def test_fit_fix_marks_parameter_fixed(runner):
    result = fit_json(runner, PENG_CSV, "--fix", "w1sq=1.0")
    parameters = {p["name"]: p for p in result["parameters"]}
    assert parameters["w1sq"]["fixed"] is True
    assert parameters["w1sq"]["estimate"] == 1.0
    assert parameters["w1sq"]["stderr"] is None
    assert [name for name, p in parameters.items() if p["fixed"]] == ["w1sq"]
    assert result["method"]["fixed"] == {"w1sq": 1.0}
    assert parameters["w2sq"]["estimate"] == pytest.approx(2.25, rel=PLUMBING)


@pytest.mark.parametrize(("cov", "extra"), [
    ("classical", []),
    ("hc", []),
    ("hac", []),
    ("bootstrap", ["--bootstrap", "20", "--seed", "1"]),
])
def test_fit_covariance_kinds(runner, cov, extra):
    result = fit_json(runner, HENON_CSV, "--cov", cov, *extra)
    assert result["method"]["covariance"] == cov
    for p in result["parameters"]:
        assert p["stderr"] is not None and p["stderr"] > 0
        assert p["ci_low"] < p["estimate"] < p["ci_high"]


def test_fit_covariance_kinds_differ(runner):
    stderrs = {}
    for cov in ["classical", "hc", "hac"]:
        result = fit_json(runner, HENON_CSV, "--cov", cov)
        stderrs[cov] = tuple(p["stderr"] for p in result["parameters"])
    assert len(set(stderrs.values())) == 3, stderrs


def test_fit_bootstrap_seed_reproduces(runner):
    args = [HENON_CSV, "--cov", "bootstrap", "--bootstrap", "20"]
    first = fit_json(runner, *args, "--seed", "1")
    again = fit_json(runner, *args, "--seed", "1")
    other = fit_json(runner, *args, "--seed", "2")
    stderrs = [[p["stderr"] for p in r["parameters"]] for r in (first, again, other)]
    assert stderrs[0] == stderrs[1]
    assert stderrs[0] != stderrs[2]


def test_fit_seed_needs_bootstrap(runner):
    result = invoke(runner, ["fit", DUFFING_CSV, "--seed", "1"])
    assert_fails(result, 2, "--seed", "bootstrap")


def test_fit_poly_model_with_column_mapping(runner):
    done = invoke(runner, ["fit", DUFFING_CSV, "--model", "poly:1:4", "--columns", "q1=x,v1=v",
                           "--format", "json"])
    assert_ok(done)
    result = json.loads(done.stdout)
    assert done.stderr == "".join(f"warning: {w}\n" for w in result["warnings"])
    assert result["model"]["name"] == "poly:1:4"
    assert result["data"]["columns"] == {"q1": "x", "v1": "v"}
    # v^2/2 + x^2/2 + 0.5 x^4/4 in poly:1:4's monomials c_2 q1^2 + c_3 q1^3 + c_4 q1^4.
    fitted = estimates(result)
    assert fitted["c_2"] == pytest.approx(0.5, rel=PLUMBING)
    assert fitted["c_4"] == pytest.approx(0.125, rel=PLUMBING)
    assert abs(fitted["c_3"]) < PLUMBING


POLY_HENON = [HENON_CSV, "--model", "poly:2:3", "--columns", "q1=x,q2=y,v1=vx,v2=vy"]
# Henon-Heiles has no x^3, x y^2 (nor x y) term: with 1% noise their estimates are noise.
ZERO_TERMS = ("c_1_1", "c_3_0", "c_1_2")


@pytest.mark.parametrize(("fmt", "on_stderr"), [("json", True), ("csv", True), ("table", False)])
def test_fit_warnings_go_to_stderr_unless_in_the_table(runner, fmt, on_stderr):
    done = invoke(runner, ["fit", *POLY_HENON, "--format", fmt])
    assert_ok(done)
    warnings = [line for line in (done.stderr if on_stderr else done.stdout).splitlines()
                if line.startswith("warning: ")]
    assert any(w.startswith(f"warning: {name} is not significantly different from zero")
               for w in warnings for name in ZERO_TERMS), warnings
    if on_stderr:
        assert done.stderr == "".join(f"{w}\n" for w in warnings)
        assert "warning: " not in done.stdout
    else:
        assert done.stderr == ""
    if fmt == "json":
        assert [f"warning: {w}" for w in json.loads(done.stdout)["warnings"]] == warnings


def test_fit_level_scales_intervals_by_t_quantiles(runner):
    # Energy rows only, so that the residual degrees of freedom are n - p - J.
    args = [HENON_CSV, "--method", "energy", "--cov", "classical"]
    wide = fit_json(runner, *args)
    narrow = fit_json(runner, *args, "--level", "0.9")
    assert narrow["method"]["level"] == 0.9
    n, j = wide["data"]["n_samples"], wide["data"]["n_trajectories"]
    df = n - len(wide["parameters"]) - j
    expected = stats.t.ppf(0.95, df) / stats.t.ppf(0.975, df)
    normal = stats.norm.ppf(0.95) / stats.norm.ppf(0.975)
    assert abs(expected / normal - 1) > 1e-5  # the test can tell t from normal quantiles
    for p90, p95 in zip(narrow["parameters"], wide["parameters"], strict=True):
        assert p90["estimate"] == p95["estimate"]
        assert p90["stderr"] == p95["stderr"]
        ratio = (p90["ci_high"] - p90["ci_low"]) / (p95["ci_high"] - p95["ci_low"])
        assert ratio == pytest.approx(expected, rel=1e-7)
        half = (p95["ci_high"] - p95["ci_low"]) / 2
        assert half / p95["stderr"] == pytest.approx(stats.t.ppf(0.975, df), rel=1e-7)


# ---------------------------------------------------------------------------------------------
# report


@pytest.fixture
def saved_result(runner, tmp_path):
    """A fit of noisy data saved as JSON, and the table `fit` printed for it."""
    path = tmp_path / "result.json"
    assert_ok(invoke(runner, ["fit", HENON_CSV, "-o", path]))
    table = invoke(runner, ["fit", HENON_CSV])
    assert_ok(table)
    return path, table.stdout


def test_report_json_round_trip(runner, saved_result):
    path, _ = saved_result
    result = invoke(runner, ["report", path, "--format", "json"])
    assert_ok(result)
    assert json.loads(result.stdout) == json.loads(path.read_text())


def test_report_table_equals_fit_table(runner, saved_result):
    path, fit_table = saved_result
    result = invoke(runner, ["report", path])
    assert_ok(result)
    assert result.stdout == fit_table


@pytest.mark.parametrize("fmt", ["table", "markdown"])
def test_report_shows_the_same_numbers(runner, saved_result, fmt):
    path, _ = saved_result
    saved = json.loads(path.read_text())
    result = invoke(runner, ["report", path, "--format", fmt])
    assert_ok(result)
    for p in saved["parameters"]:
        for key in ("estimate", "stderr", "ci_low", "ci_high"):
            assert f"{p[key]:.6g}" in result.stdout, (p["name"], key)
    for level in saved["energy_levels"]:
        assert f"{level['h']:.6g}" in result.stdout
    if fmt == "markdown":
        assert "| name | estimate |" in result.stdout


def test_report_to_markdown_file(runner, saved_result, tmp_path):
    path, _ = saved_result
    out = tmp_path / "report.md"
    result = invoke(runner, ["report", path, "-o", out])
    assert_ok(result)
    assert result.stdout == ""
    assert "| name | estimate |" in out.read_text()


@pytest.mark.parametrize(("content", "names"), [
    (None, ["missing.json", "no such file"]),
    ("trajectory,t,x,v\n1,0,1,0\n", ["bad.json", "not valid JSON"]),
    ('{"schema": "other/1"}', ["bad.json", "other/1", "hamid.fit/1"]),
    ("[1, 2]", ["bad.json"]),
])
def test_report_bad_input(runner, tmp_path, content, names):
    path = tmp_path / ("missing.json" if content is None else "bad.json")
    if content is not None:
        path.write_text(content)
    assert_fails(invoke(runner, ["report", path]), 1, *names)


def test_report_bad_format_is_usage_error(runner, saved_result):
    path, _ = saved_result
    assert_fails(invoke(runner, ["report", path, "--format", "xlsx"]), 2, "--format")


# ---------------------------------------------------------------------------------------------
# fit errors

DUFFING_ROWS = "t,x,v\n0,1,0\n0.1,0.995,-0.1\n0.2,0.98,-0.2\n0.3,0.955,-0.3\n0.4,0.92,-0.4\n"

# A model whose extra coordinate z never moves in the data (constant column) ...
CONSTANT_MODEL = """\
[model]
coordinates = ["x", "z"]
velocities = ["v", "vz"]
energy = "(v**2 + vz**2)/2 + k*x**2/2 + k3*x**4/4 + kz*z**2/2"
"""
# ... and one with two terms that are proportional to each other.
COLLINEAR_MODEL = """\
[model]
coordinates = ["x"]
velocities = ["v"]
energy = "v**2/2 + k*x**2/2 + k2*x**2 + k3*x**4/4"
"""


def _with_constant_z(value):
    def write(path):
        frame = pd.read_csv(DUFFING_CSV, comment="#")
        frame["z"], frame["vz"] = value, 0.0
        frame.to_csv(path, index=False)

    return write


FIT_ERRORS = {
    # id: (file content (str, callable(path) or None for no file), args, code, names)
    "missing file": (None, [], 1, ["data.csv", "no such file"]),
    "empty file": ("", [], 1, ["data.csv", "empty"]),
    "header only": ("t,x,v\n", ["--model", "duffing"], 1, ["data.csv", "no data rows"]),
    "non-numeric cell": (DUFFING_ROWS.replace("0.98,", "n/a,"), ["--model", "duffing"], 1,
                         ["data.csv", "column 'x'", "row 3", "'n/a'"]),
    "NaN cell": (DUFFING_ROWS.replace("-0.3", "nan"),
                 ["--model", "duffing", "--gaps", "error"], 1,
                 ["data.csv", "column 'v'", "row 4"]),
    "empty cell": (DUFFING_ROWS.replace("-0.3", ""),
                   ["--model", "duffing", "--gaps", "error"], 1,
                   ["data.csv", "column 'v'", "row 4"]),
    "column missing for the model": (DUFFING_ROWS, ["--model", "peng-quadratic"], 1,
                                     ["data.csv", "'u1'"]),
    "--columns key not in the model": (DUFFING_ROWS, ["--model", "duffing", "--columns",
                                                      "q=x"], 2, ["--columns", "'q'"]),
    "--columns file column missing": (DUFFING_ROWS, ["--model", "duffing", "--columns",
                                                     "x=pos"], 1, ["data.csv", "'pos'"]),
    "--fix unknown parameter": (DUFFING_ROWS, ["--model", "duffing", "--fix", "nosuch=1"], 2,
                                ["--fix", "'nosuch'"]),
    "--fix not a number": (DUFFING_ROWS, ["--model", "duffing", "--fix", "k=abc"], 2,
                           ["--fix", "'abc'"]),
    "--fix every parameter": (DUFFING_ROWS, ["--model", "duffing", "--fix", "k=1,k3=0.5"], 2,
                              ["every parameter is fixed"]),
    "--method unknown": (DUFFING_ROWS, ["--method", "magic"], 2, ["--method", "'magic'"]),
    "--cov unknown": (DUFFING_ROWS, ["--cov", "jackknife"], 2, ["--cov", "'jackknife'"]),
    "--level above 1": (DUFFING_ROWS, ["--level", "1.5"], 2, ["--level", "1.5"]),
    "--level not a number": (DUFFING_ROWS, ["--level", "high"], 2, ["--level", "'high'"]),
    "--bootstrap too few": (DUFFING_ROWS, ["--cov", "bootstrap", "--bootstrap", "3"], 2,
                            ["--bootstrap"]),
    "unknown model": (DUFFING_ROWS, ["--model", "quartic"], 2, ["'quartic'"]),
    "fewer samples than unknowns": ("t,x,v\n0,1,0\n0.1,0.995,-0.1\n", ["--model", "duffing"],
                                    1, ["k, k3", "2 rows"]),
    # z = 0 throughout: kz's term is zero in the energy and in the equations of motion.
    "a term that never varies": (_with_constant_z(0.0), ["--model", "constant.toml"], 1,
                                 ["kz", "does not vary"]),
    # z = 0.5 at rest: only the energy rows are blind to kz (z's equation of motion says
    # kz = 0), so ask for them alone.
    "a constant term, energy rows": (_with_constant_z(0.5), ["--model", "constant.toml",
                                                            "--method", "energy"], 1,
                                     ["kz", "does not vary"]),
    "collinear terms": (lambda path: shutil.copy(DUFFING_CSV, path),
                        ["--model", "collinear.toml"], 1, ["k, k2", "collinear"]),
    "time not increasing": (DUFFING_ROWS.replace("0.3,", "0.2,"), ["--model", "duffing"], 1,
                            ["data.csv", "column 't'", "row 4"]),
    "--time column missing": (DUFFING_ROWS, ["--model", "duffing", "--time", "clock"], 1,
                              ["data.csv", "'clock'", "--time"]),
    "interleaved trajectories": (
        "trajectory,t,x,v\n1,0,1,0\n1,0.1,0.99,0.1\n2,0,0.5,0\n2,0.1,0.49,0.1\n"
        "1,0.2,0.98,0.2\n1,0.3,0.97,0.3\n", ["--model", "duffing"], 1,
        ["data.csv", "column 'trajectory'", "row 5"]),
    "no model and no velocity column": ("t,a,b\n0,1,2\n0.1,1,2\n", [], 1,
                                        ["data.csv", "--model"]),
}


@pytest.mark.parametrize(("content", "args", "code", "names"), FIT_ERRORS.values(),
                         ids=FIT_ERRORS.keys())
def test_fit_errors(runner, tmp_path, monkeypatch, content, args, code, names):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "constant.toml").write_text(CONSTANT_MODEL)
    (tmp_path / "collinear.toml").write_text(COLLINEAR_MODEL)
    if isinstance(content, str):
        Path("data.csv").write_text(content)
    elif content is not None:
        content(Path("data.csv"))
    result = invoke(runner, ["fit", "data.csv", *args])
    assert_fails(result, code, *names)


def test_fit_a_folder(runner, tmp_path):
    assert_fails(invoke(runner, ["fit", tmp_path]), 1, str(tmp_path), "folder")


def test_fit_without_data_is_usage_error(runner):
    assert_fails(invoke(runner, ["fit"]), 2, "DATA")


# ---------------------------------------------------------------------------------------------
# internal errors


@pytest.fixture
def broken_fit(monkeypatch):
    import hamid.api

    def boom(*args, **kwargs):
        raise RuntimeError("the flux capacitor broke")

    monkeypatch.setattr(hamid.api, "fit", boom)


def test_internal_error_is_one_line_without_traceback(runner, broken_fit):
    result = invoke(runner, ["fit", DUFFING_CSV])
    assert_fails(result, 1, "RuntimeError", "the flux capacitor broke", "--debug", "bug")
    assert len(result.stderr.strip().splitlines()) == 1


def test_internal_error_with_debug_propagates(runner, broken_fit):
    result = invoke(runner, ["--debug", "fit", DUFFING_CSV])
    assert result.exit_code == 1
    assert isinstance(result.exception, RuntimeError)
    assert str(result.exception) == "the flux capacitor broke"
    # --debug does not outlive its invocation.
    again = invoke(runner, ["fit", DUFFING_CSV])
    assert_fails(again, 1, "--debug")


# ---------------------------------------------------------------------------------------------
# real processes


def _quote(args):
    import shlex

    return " ".join(shlex.quote(a) for a in args)


def test_subprocess_pipeline(tmp_path):
    hamid = _quote(hamid_command())
    command = (f"set -o pipefail; {hamid} simulate --config {_quote([DUFFING_TOML])} -o - "
               f"--format csv | {hamid} fit - --format json")
    done = subprocess.run(["bash", "-c", command], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["schema"] == "hamid.fit/1"
    assert estimates(result) == pytest.approx({"k": 1.0, "k3": 0.5}, rel=PLUMBING)
    assert "simulated 2 trajectories" in done.stderr
    assert "Traceback" not in done.stderr


def test_subprocess_error_exit_code(tmp_path):
    done = subprocess.run([*hamid_command(), "fit", "nosuch.csv"], capture_output=True,
                          text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr == "Error: nosuch.csv: no such file\n"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash for pipefail")
def test_closed_pipe_ends_quietly():
    hamid = _quote(hamid_command())
    command = (f"set -o pipefail; {hamid} simulate --config {_quote([PENG_TOML])} -o - "
               "--format csv | head -n 1")
    done = subprocess.run(command, shell=True, executable="bash", capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(META_PREFIX)
    assert done.stdout.count("\n") == 1
    assert "Traceback" not in done.stderr
    assert "Error" not in done.stderr
    assert "BrokenPipe" not in done.stderr


@pytest.mark.parametrize("args", [
    ["--help"],
    ["--version"],
    ["models"],
    ["fit", DUFFING_CSV, "--format", "json"],
    ["simulate", "--config", "{small}", "-o", "-", "--format", "csv"],
], ids=lambda args: " ".join(args[:2]).replace(str(SAMPLES) + os.sep, ""))
def test_reader_gone_before_the_first_write(tmp_path, args):
    small = str(write_system(tmp_path))
    args = [small if a == "{small}" else a for a in args]
    # A pipe whose read end is already closed: the very first write fails with EPIPE,
    # whether it happens while click parses (--help) or inside a command.
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        done = subprocess.run([*hamid_command(), *args], stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=600)
    finally:
        os.close(write_end)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    assert "Error" not in done.stderr


def test_stdout_is_finite_json_numbers(runner):
    # Strict JSON for jq: no NaN or Infinity even where a value is undefined.
    result = invoke(runner, ["fit", DUFFING_CSV, "--fix", "k=1", "--format", "json"])
    assert_ok(result)

    def reject(token):
        raise AssertionError(f"non-standard JSON number {token}")

    parsed = json.loads(result.stdout, parse_constant=reject)
    for p in parsed["parameters"]:
        for key in ("estimate", "stderr", "ci_low", "ci_high"):
            assert p[key] is None or math.isfinite(p[key])


def test_fit_noise_options_reach_the_report(runner, tmp_path):
    """--noise auto, --bias-correct and --velocity savgol from the command line."""
    result = fit_json(runner, PENG_CSV, "--noise", "auto", "--bias-correct")
    assert result["method"]["weighting"] == "noise"
    assert set(result["method"]["noise"]) == {"u1", "u2", "v1", "v2"}
    assert result["method"]["bias_correction"] is True
    table = invoke(runner, ["fit", PENG_CSV, "--noise", "u1=0.001,v2=0.002"])
    assert_ok(table)
    assert "noise σ" in table.stdout and "weighting rounds" in table.stdout
    positions = tmp_path / "positions.csv"
    pd.read_csv(PENG_CSV, comment="#").drop(columns=["v1", "v2"]).to_csv(positions,
                                                                         index=False)
    derived = invoke(runner, ["fit", positions, "--model", "peng-quadratic", "--velocity",
                              "savgol", "--window", "9", "--format", "json"])
    assert_ok(derived)
    data = json.loads(derived.stdout)["data"]
    assert data["velocity_source"] == "savgol" and data["velocity_window"] == 9


def test_fit_status_line_only_on_a_terminal(runner, simulated_duffing):
    """Piped or redirected, standard error gets no status line."""
    done = invoke(runner, ["fit", "-", "--format", "json"], input=simulated_duffing)
    assert_ok(done)
    assert "fitting" not in done.stderr


@pytest.mark.skipif(os.name != "posix", reason="a pseudo-terminal")
def test_fit_status_line_on_a_terminal_shows_the_steps_and_is_erased(tmp_path):
    """A real fit with standard error on a pseudo-terminal: the status line shows the fit's
    steps, and when the fit ends it is erased (the line cleared, the cursor shown again),
    leaving the terminal as it was; the report on standard output is whole."""
    import pty

    master, slave = pty.openpty()
    try:
        process = subprocess.Popen([*hamid_command(), "fit", PENG_CSV, "--format", "json"],
                                   stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                   stderr=slave, cwd=tmp_path,
                                   env={**os.environ, "TERM": "xterm"})
    finally:
        os.close(slave)
    shown = bytearray()
    try:
        while chunk := _read_terminal(master):
            shown += chunk
        stdout = process.communicate(timeout=600)[0]
    finally:
        os.close(master)
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, bytes(shown)
    assert json.loads(stdout)["schema"] == "hamid.fit/1"
    shown = bytes(shown)
    assert b" fitting" in shown and b"fitting: trajectory fit" in shown, shown
    after = shown[shown.rindex(b"fitting"):]
    assert b"\x1b[2K" in after and b"\x1b[?25h" in after, after   # erased, cursor back
    assert b"Error" not in shown


def _read_terminal(master: int) -> bytes:
    """What the terminal received next; b"" once its last writer has gone (Linux reports
    that as an error), or after minutes of silence, which only bound a hang."""
    import select

    if not select.select([master], [], [], 600)[0]:
        return b""
    try:
        return os.read(master, 1 << 16)
    except OSError:
        return b""
