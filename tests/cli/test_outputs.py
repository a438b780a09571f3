"""The outputs of `hamid fit` and `hamid report` (issue 18, "Outputs"): the format told by
-o's extension, the same four formats for both commands, --residuals and the report never
both on standard output; the text layout flags of `fit`; --strict's exit status 3; the
time column, its unit and --scale factors on the report's "data:" line."""

from __future__ import annotations

import copy
import csv
import io
import json
import os
import subprocess
from pathlib import Path

import pytest

from hamid.report.formats import FORMATS, render

ROOT = Path(__file__).resolve().parents[2]
DUFFING_CSV = ROOT / "sample_data" / "duffing.csv"
FAST = ("--method", "energy")   # the quickest fit: these tests are about the outputs

# What each report format starts with.
SIGNATURES = {
    "json": lambda text: json.loads(text)["schema"] == "hamid.fit/1",
    "csv": lambda text: text.startswith("name,role,estimate,"),
    "markdown": lambda text: text.startswith("**hamid fit") and "| name | estimate |" in text,
    "table": lambda text: text.startswith("hamid fit") and "| name |" not in text,
}
SUFFIXES = {".json": "json", ".csv": "csv", ".md": "markdown", ".txt": "table"}


def _run(hamid_cli, *args, cwd=None, stdin=subprocess.DEVNULL):
    return subprocess.run([*hamid_cli, *map(str, args)], cwd=cwd, stdin=stdin,
                          capture_output=True, text=True, timeout=600)


def _usage_error(done, *names):
    """One error line naming each of `names`, exit 2, nothing on standard output."""
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("Error: "), done.stderr
    assert "Traceback" not in done.stderr
    for name in names:
        assert name in lines[-1], (name, done.stderr)


@pytest.fixture(scope="module")
def saved(tmp_path_factory, hamid_cli):
    """A fit result saved as JSON."""
    path = tmp_path_factory.mktemp("saved") / "result.json"
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "-o", path)
    assert done.returncode == 0, done.stderr
    return path


# --- the format from -o's extension ----------------------------------------------------------


@pytest.mark.parametrize("suffix", list(SUFFIXES))
def test_fit_format_from_extension(hamid_cli, tmp_path, suffix):
    out = tmp_path / f"report{suffix}"
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "-o", out)
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""
    assert SIGNATURES[SUFFIXES[suffix]](out.read_text())


@pytest.mark.parametrize("suffix", list(SUFFIXES))
def test_report_format_from_extension(hamid_cli, saved, tmp_path, suffix):
    out = tmp_path / f"report{suffix.upper()}"   # the extension in any case
    done = _run(hamid_cli, "report", saved, "-o", out)
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""
    assert SIGNATURES[SUFFIXES[suffix]](out.read_text())


@pytest.mark.parametrize(("command", "name"), [
    ("fit", "out.xlsx"), ("report", "rep.png"), ("fit", "report"), ("report", "rep.tsv"),
])
def test_unknown_extension_is_a_usage_error(hamid_cli, saved, tmp_path, command, name):
    """Today `fit -o out.xlsx` wrote a text table under that name."""
    args = ["fit", DUFFING_CSV, *FAST] if command == "fit" else ["report", saved]
    done = _run(hamid_cli, *args, "-o", name, cwd=tmp_path)
    _usage_error(done, name, ".json", ".csv", ".md", ".txt", "--format")
    assert not (tmp_path / name).exists()
    assert os.listdir(tmp_path) == []


def test_format_given_overrides_the_extension(hamid_cli, tmp_path):
    out = tmp_path / "out.xlsx"
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "-o", out, "--format", "json")
    assert done.returncode == 0, done.stderr
    assert SIGNATURES["json"](out.read_text())


@pytest.mark.parametrize("command", ["fit", "report"])
def test_standard_output_and_special_files_default_to_table(hamid_cli, saved, tmp_path,
                                                            command):
    args = ["fit", DUFFING_CSV, *FAST] if command == "fit" else ["report", saved]
    for output in ("-", "/dev/stdout"):
        done = _run(hamid_cli, *args, "-o", output)
        assert done.returncode == 0, done.stderr
        assert SIGNATURES["table"](done.stdout), output
    assert _run(hamid_cli, *args, "-o", os.devnull).returncode == 0
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    reader = subprocess.Popen(["cat", str(fifo)], stdout=subprocess.PIPE, text=True)
    try:
        done = _run(hamid_cli, *args, "-o", fifo)
        text = reader.communicate(timeout=600)[0]
    finally:
        reader.kill()
    assert done.returncode == 0, done.stderr
    assert SIGNATURES["table"](text)


# --- the same formats for fit and report -----------------------------------------------------


def test_the_cli_offers_the_renderers_formats():
    from hamid.cli.app import _REPORT_FORMATS

    assert sorted(_REPORT_FORMATS) == sorted(FORMATS)


@pytest.mark.parametrize("fmt", sorted(SIGNATURES))
def test_fit_and_report_accept_the_same_formats(hamid_cli, saved, fmt):
    """`report` refused csv and `fit` refused markdown; now both give the same text."""
    fitted = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--format", fmt)
    reported = _run(hamid_cli, "report", saved, "--format", fmt)
    assert fitted.returncode == 0, fitted.stderr
    assert reported.returncode == 0, reported.stderr
    assert SIGNATURES[fmt](fitted.stdout)
    if fmt == "json":   # the provenance (time, command line) differs between the runs
        assert json.loads(fitted.stdout)["parameters"] == json.loads(
            reported.stdout)["parameters"]
    else:
        assert fitted.stdout == reported.stdout


def test_report_as_csv_has_one_row_per_parameter(hamid_cli, saved):
    done = _run(hamid_cli, "report", saved, "--format", "csv")
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    names = [p["name"] for p in json.loads(saved.read_text())["parameters"]]
    assert [row["name"] for row in rows] == names


# --- --residuals and the report on standard output -------------------------------------------


@pytest.mark.parametrize(("residuals", "output"), [
    ("-", "-"), ("-", "/dev/stdout"), ("/dev/stdout", "-"), ("/dev/fd/1", "/dev/stdout"),
])
def test_residuals_and_report_both_on_standard_output_is_a_usage_error(
        hamid_cli, residuals, output):
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--residuals", residuals, "-o", output)
    _usage_error(done, "--residuals", "standard output", "interleave")


def test_residuals_on_standard_output_with_the_report_in_a_file(hamid_cli, tmp_path):
    out = tmp_path / "report.json"
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--residuals", "-", "-o", out)
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    assert rows and {"trajectory", "t", "residual"} <= set(rows[0])
    assert SIGNATURES["json"](out.read_text())


def test_residuals_in_a_file_with_the_report_on_standard_output(hamid_cli, tmp_path):
    res = tmp_path / "res.csv"
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--residuals", res)
    assert done.returncode == 0, done.stderr
    assert SIGNATURES["table"](done.stdout)
    assert res.read_text().startswith("trajectory,")


def test_residuals_and_report_to_standard_output_sent_to_dev_null(hamid_cli):
    """/dev/null as standard output: nothing there can interleave (a pipe is refused, above),
    and the fit runs as any other, without a message."""
    done = subprocess.run([*hamid_cli, "fit", str(DUFFING_CSV), *FAST, "--residuals",
                           "/dev/stdout"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""


# --- the text layout of `fit` ----------------------------------------------------------------


def _estimates(text):
    return {p["name"]: p["estimate"] for p in json.loads(text)["parameters"]}


def _european(units: str | None = None) -> str:
    """duffing.csv as a spreadsheet in a European locale writes it: two preamble lines,
    ';' between cells, decimal commas, optionally a units row."""
    lines = [line for line in DUFFING_CSV.read_text().splitlines()
             if not line.startswith("#")]
    body = [line.replace(",", ";").replace(".", ",") for line in lines]
    if units is not None:
        body.insert(1, units)
    return "\n".join(["Recorder export v2", "station 4; 2026-11-24", *body]) + "\n"


@pytest.fixture(scope="module")
def reference(hamid_cli):
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--model", "duffing", "--format", "json")
    assert done.returncode == 0, done.stderr
    return _estimates(done.stdout)


def test_preamble_semicolons_and_decimal_commas(hamid_cli, tmp_path, reference):
    path = tmp_path / "export.csv"
    path.write_text(_european())
    done = _run(hamid_cli, "fit", path, *FAST, "--model", "duffing", "--format", "json",
                "--skip-rows", "2", "--delimiter", ";", "--decimal", ",")
    assert done.returncode == 0, done.stderr
    assert _estimates(done.stdout) == pytest.approx(reference, rel=1e-12)
    # without --skip-rows the preamble is taken for the header
    done = _run(hamid_cli, "fit", path, *FAST, "--model", "duffing", "--format", "json")
    assert done.returncode == 1
    assert done.stdout == ""


def test_decimal_point_given_refuses_decimal_commas(hamid_cli, tmp_path):
    path = tmp_path / "export.csv"
    path.write_text(_european())
    done = _run(hamid_cli, "fit", path, *FAST, "--model", "duffing", "--skip-rows", "2",
                "--delimiter", ";", "--decimal", ".")
    assert done.returncode == 1, done.stderr
    assert done.stdout == ""
    assert "not a number" in done.stderr


def test_units_row_given_and_refused(hamid_cli, tmp_path, reference):
    """A units row with a number in it ('1' for a dimensionless column) is not detected;
    --units-row says it is one, --no-units-row that it is data."""
    path = tmp_path / "export.csv"
    path.write_text(_european(units="1;s;1;1/s"))
    common = [path, *FAST, "--model", "duffing", "--format", "json", "--skip-rows", "2"]
    done = _run(hamid_cli, "fit", *common, "--units-row")
    assert done.returncode == 0, done.stderr
    assert _estimates(done.stdout) == pytest.approx(reference, rel=1e-12)
    done = _run(hamid_cli, "fit", *common, "--no-units-row")
    assert done.returncode == 1
    assert "not a number" in done.stderr
    assert done.stdout == ""


@pytest.mark.parametrize("spelling", ["tab", "\\t", "\t"])
def test_tab_delimiter(hamid_cli, tmp_path, reference, spelling):
    """A tab-separated file under a name that does not say so."""
    path = tmp_path / "export.dat"
    lines = [line for line in DUFFING_CSV.read_text().splitlines()
             if not line.startswith("#")]
    path.write_text("\n".join(lines).replace(",", "\t") + "\n")
    done = _run(hamid_cli, "fit", path, *FAST, "--model", "duffing", "--format", "json",
                "--format-in", "csv", "--delimiter", spelling)
    assert done.returncode == 0, done.stderr
    assert _estimates(done.stdout) == pytest.approx(reference, rel=1e-12)


@pytest.mark.parametrize(("args", "names"), [
    (["--delimiter", "ab"], ["--delimiter"]),
    (["--delimiter", ".", "--decimal", ","], ["--delimiter"]),
    (["--delimiter", ";", "--decimal", ";"], ["--decimal"]),
    (["--skip-rows", "-1"], ["--skip-rows"]),
])
def test_bad_text_layout_is_a_usage_error(hamid_cli, args, names):
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, *args)
    _usage_error(done, *names)


# --- --strict ------------------------------------------------------------------------------


def test_strict_exits_3_with_the_report_written(hamid_cli, tmp_path):
    """poly:1:2 on Duffing data misses the quartic term: autocorrelated residuals."""
    out = tmp_path / "report.json"
    args = ["fit", DUFFING_CSV, *FAST, "--model", "poly:1:2", "--columns", "q1=x,v1=v",
            "-o", out]
    lenient = _run(hamid_cli, *args)
    assert lenient.returncode == 0, lenient.stderr
    assert "warning:" in lenient.stderr
    out.unlink()
    strict = _run(hamid_cli, *args, "--strict")
    assert strict.returncode == 3, strict.stderr
    assert json.loads(out.read_text())["warnings"]
    assert strict.stdout == ""
    assert "--strict" in strict.stderr.strip().splitlines()[-1]


def test_strict_without_warnings_exits_0(hamid_cli):
    done = _run(hamid_cli, "fit", DUFFING_CSV, *FAST, "--strict", "--format", "json")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["warnings"] == []


# --- time and scale on the "data:" line ------------------------------------------------------


def _data_line(text):
    lines = [line for line in text.splitlines() if "data:" in line]
    assert len(lines) == 1, text
    return lines[0]


@pytest.fixture(scope="module")
def daq_result(hamid_cli, tmp_path_factory):
    """duffing.csv with its time in ms and its positions in mm, fitted through the
    suffixes and --scale."""
    lines = [line for line in DUFFING_CSV.read_text().splitlines() if not line.startswith("#")]
    rows = ["trajectory,time_ms,x_mm,v"]
    for line in lines[1:]:
        trajectory, t, x, v = line.split(",")
        rows.append(f"{trajectory},{float(t) * 1000!r},{float(x) * 1000!r},{v}")
    path = tmp_path_factory.mktemp("daq") / "daq.csv"
    path.write_text("\n".join(rows) + "\n")
    done = _run(hamid_cli, "fit", path, *FAST, "--model", "duffing", "--columns",
                "x=x_mm", "--format", "json")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.mark.parametrize("fmt", ["table", "markdown"])
def test_data_line_shows_time_unit_and_scale(daq_result, fmt):
    data = daq_result["data"]
    assert data["time"] == "time_ms" and data["time_unit"] == "ms", data
    assert data["scale"] == {"x_mm": pytest.approx(1e-3), "time_ms": pytest.approx(1e-3)}
    line = _data_line(render(daq_result, fmt, width=400))
    assert "time time_ms (ms)" in line
    # the time column's factor is its unit, said once
    assert line.endswith("; scaled x_mm × 0.001")


@pytest.mark.parametrize("fmt", ["table", "markdown"])
def test_data_line_without_time_or_scale(daq_result, fmt):
    """A report without those keys (a fit from a DataFrame with no time, an older file)."""
    result = copy.deepcopy(daq_result)
    for key in ("time", "time_unit", "scale"):
        result["data"].pop(key)
    line = _data_line(render(result, fmt, width=400))
    assert "time" not in line.split("; velocities")[1]
    assert "scaled" not in line
    # the usual t in seconds goes without saying; another name or unit is said
    for unit in (None, "s"):
        result["data"].update(time="t", time_unit=unit, scale={})
        line = _data_line(render(result, fmt, width=400))
        assert "; time" not in line and "scaled" not in line
    result["data"].update(time="Zeit", time_unit=None, scale={})
    assert _data_line(render(result, fmt, width=400)).endswith("; time Zeit")
    # a scaled time column without a unit recorded: its factor is shown
    result["data"].update(time="t", time_unit=None, scale={"t": 0.001})
    assert _data_line(render(result, fmt, width=400)).endswith("; scaled t × 0.001")


def test_report_command_shows_time_and_scale(hamid_cli, daq_result, tmp_path):
    path = tmp_path / "daq.json"
    path.write_text(json.dumps(daq_result))
    done = _run(hamid_cli, "report", path, "--format", "markdown")
    assert done.returncode == 0, done.stderr
    line = _data_line(done.stdout)
    assert "time time_ms (ms)" in line and "x_mm × 0.001" in line


def test_the_command_line_is_in_the_report(hamid_cli, tmp_path):
    done = subprocess.run([*hamid_cli, "fit", str(DUFFING_CSV), "--method", "energy",
                           "--format", "json"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    command = json.loads(done.stdout)["provenance"]["command"]
    assert command.startswith("hamid fit ") and "--method energy" in command
