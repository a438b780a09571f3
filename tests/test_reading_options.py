"""One set of reading options for every command that reads data (`fit`, `select`, `plot`):
the same options in each command's help, recorded in the report (`data.reading`) and used
again by `plot`, so that a file a data-acquisition system wrote is read alike by all."""

from __future__ import annotations

import json
import re
import subprocess

import pandas as pd
import pytest
from helpers import hamid_command

import hamid
from hamid.options import READING_OPTIONS

SAMPLE = "sample_data/duffing.csv"
DAQ_OPTIONS = ["--skip-rows", "2", "--delimiter", ";", "--decimal", ","]
READING_FLAGS = {"--columns", "--time", "--time-unit", "--scale", "--gaps", "--trajectory",
                 "--format-in", "--delimiter", "--decimal", "--skip-rows", "--units-row"}


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


def _flags(command: str) -> set[str]:
    done = _run(command, "--help")
    assert done.returncode == 0, done.stderr
    return set(re.findall(r"^\s+(--[a-z-]+)", done.stdout, flags=re.MULTILINE))


@pytest.mark.parametrize("command", ["fit", "select", "plot"])
def test_every_command_that_reads_data_lists_the_reading_options(command):
    assert _flags(command) >= READING_FLAGS


def test_the_reading_options_are_those_the_fit_takes():
    names = {flag.removeprefix("--").replace("-", "_") for flag in READING_FLAGS}
    assert names - {"format_in"} | {"format"} == set(READING_OPTIONS)


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
