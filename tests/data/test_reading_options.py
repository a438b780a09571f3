"""One set of reading options for every command that reads data (`fit`, `fit --each`,
`select`, `plot`): recorded in the report (`data.reading`) and used again by `plot`, so that
a file a data-acquisition system wrote is read alike by all (the same options in each
command's help: tests/cli/test_option_spec.py)."""

from __future__ import annotations

import json
import subprocess

import pandas as pd
import pytest
from helpers import hamid_command

import hamid

SAMPLE = "sample_data/duffing.csv"
DAQ_OPTIONS = ["--skip-rows", "2", "--delimiter", ";", "--decimal", ","]


def _run(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([*hamid_command(), *args], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


@pytest.fixture(scope="module")
def daq(tmp_path_factory):
    """The Duffing sample as a logger writes it: two lines of preamble, ';' between
    cells, decimal commas."""
    path = tmp_path_factory.mktemp("daq") / "daq.csv"
    body = pd.read_csv(SAMPLE, comment="#").to_csv(sep=";", decimal=",", index=False)
    path.write_text("Logger 7 export\n2026-11-24 06:00\n" + body)
    return path


def test_the_report_records_the_reading_options_given(daq):
    result = hamid.fit(daq, "duffing", skip_rows=2, delimiter=";", decimal=",")
    assert result.to_dict()["data"]["reading"] == {"delimiter": ";", "decimal": ",",
                                                   "skip_rows": 2}
    plain = hamid.fit(SAMPLE, "duffing")
    assert "reading" not in plain.to_dict()["data"]
    assert result.estimates == pytest.approx(plain.estimates, rel=1e-12)


def test_plot_reads_the_data_as_the_fit_read_them(daq, tmp_path):
    report = tmp_path / "r.json"
    fitted = _run("fit", str(daq), "--model", "duffing", *DAQ_OPTIONS, "-o", str(report))
    assert fitted.returncode == 0, fitted.stderr
    drawn = _run("plot", str(report), str(daq), "-o", str(tmp_path / "fig.png"),
                 "--panels", "energy")
    assert drawn.returncode == 0, drawn.stderr
    assert (tmp_path / "fig.png").read_bytes().startswith(b"\x89PNG")   # one panel, one file


def test_plot_takes_reading_options_over_the_reports(daq, tmp_path):
    """The same data converted to plain CSV: the options given replace those recorded."""
    report = tmp_path / "r.json"
    assert _run("fit", str(daq), "--model", "duffing", *DAQ_OPTIONS,
                "-o", str(report)).returncode == 0
    plain = tmp_path / "plain.csv"
    pd.read_csv(SAMPLE, comment="#").to_csv(plain, index=False)
    figure = str(tmp_path / "fig.png")
    refused = _run("plot", str(report), str(plain), "-o", figure, "--panels", "energy")
    assert refused.returncode == 1 and refused.stdout == ""
    drawn = _run("plot", str(report), str(plain), "-o", figure, "--panels", "energy",
                 "--skip-rows", "0", "--delimiter", ",", "--decimal", ".")
    assert drawn.returncode == 0, drawn.stderr


def test_select_reads_a_logger_file(daq):
    options = ["--library", "poly:1:4", "--columns", "q1=x,v1=v", "--format", "json"]
    found = _run("select", str(daq), *DAQ_OPTIONS, *options)
    assert found.returncode == 0, found.stderr
    expected = _run("select", SAMPLE, *options)
    assert json.loads(found.stdout)["chosen"] == json.loads(expected.stdout)["chosen"] \
        == ["q1**2", "q1**4"]


def test_select_takes_the_reading_keywords(daq):
    chosen = hamid.select(daq, "poly:1:4", columns={"q1": "x", "v1": "v"}, skip_rows=2,
                          delimiter=";", decimal=",")
    assert chosen.chosen == ["q1**2", "q1**4"]
    with pytest.raises(TypeError, match="'skiprows'"):
        hamid.select(daq, "poly:1:4", skiprows=2)


def test_fit_each_reads_logger_files(daq, tmp_path):
    """Each file read with the options given, as a single fit reads it, and recorded."""
    other = tmp_path / "daq2.csv"
    other.write_bytes(daq.read_bytes())
    done = _run("fit", "--each", str(daq), str(other), "--model", "duffing", *DAQ_OPTIONS,
                "--format", "jsonl", "--jobs", "1")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    plain = hamid.fit(SAMPLE, "duffing").estimates
    assert [line["status"] for line in lines] == ["ok", "ok"]
    for line in lines:
        assert line["data"]["reading"] == {"delimiter": ";", "decimal": ",", "skip_rows": 2}
        assert {p["name"]: p["estimate"] for p in line["parameters"]} == pytest.approx(
            plain, rel=1e-12)


def test_a_coordinate_the_model_lacks_is_said():
    """Henon-Heiles (x, vx, y, vy) fitted as a Duffing oscillator: y and vy are not read,
    and the warning says so; fitted with its own model, nothing is said."""
    lacking = hamid.fit("sample_data/henon_heiles.csv", "duffing", method="energy")
    [said] = [w for w in lacking.warnings if "does not have" in w]
    assert "y with vy" in said and "'duffing'" in said
    whole = hamid.fit("sample_data/henon_heiles.csv", method="energy")
    assert not any("does not have" in w for w in whole.warnings)
