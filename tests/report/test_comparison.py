"""`hamid report` of many fits (issue 38): a column per source while the table fits the
terminal, a row per source when it would not, no line wider than the terminal.

Fifteen decays of a Duffing oscillator at their own amplitudes, fitted once; the rows are
checked against each FitResult's own estimates.
"""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from helpers import hamid_command

import hamid
from hamid.report import comparison

N_FITS = 15


def _system(k: int) -> dict:
    return {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
            "initial": [{"x": 0.5 + 0.05 * k, "v": 0.0}],
            "simulate": {"t_end": 10.0, "dt": 0.05}, "noise": {"relative": 0.01}}


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    """The fits by source name, and the results.jsonl of their lines (with one failure)."""
    folder = tmp_path_factory.mktemp("decays")
    fits = {}
    for k in range(N_FITS):
        fits[f"runs/decay_{k + 1:02d}.csv"] = hamid.fit(hamid.simulate(_system(k), seed=k))
    lines = [comparison.record(source, fit) for source, fit in fits.items()]
    lines.append({"source": "runs/decay_16.csv", "status": "error",
                  "error": "runs/decay_16.csv: has a header but no data rows"})
    path = folder / "results.jsonl"
    path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    return fits, path


def _report(path, *args, columns: str | None) -> subprocess.CompletedProcess:
    env = {key: value for key, value in os.environ.items() if key != "COLUMNS"}
    env.update({"COLUMNS": columns} if columns else {})
    return subprocess.run([*hamid_command(), "report", str(path), *args], env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("columns", [None, "80", "60"])
def test_fifteen_fits_take_a_row_each_within_the_terminal(fits, columns):
    """Off a terminal rich's width is 80, or COLUMNS."""
    results, path = fits
    done = _report(path, columns=columns)
    assert done.returncode == 0 and done.stderr == "", done.stderr
    width = int(columns or 80)
    lines = done.stdout.splitlines()
    assert max(map(len, lines)) <= width, "\n".join(lines)
    assert lines[0].startswith(f"hamid report — {N_FITS + 1} fits of duffing, method joint + "
                               "trajectory")
    header = next(line for line in lines if line.lstrip().startswith("source"))
    assert header.split()[:3] == ["source", "k", "k3"]
    assert "parameter" not in done.stdout
    if width >= 80:   # one line per source: its estimates, errors and warnings
        for source, fit in results.items():
            row = next(line for line in lines if line.startswith(source))
            k, k3 = fit.parameters
            assert row.split() == [source, f"{k.estimate:.6g}", "±", f"{k.stderr:.2g}",
                                   f"{k3.estimate:.6g}", "±", f"{k3.stderr:.2g}",
                                   str(len(fit.warnings))]
    assert "error: runs/decay_16.csv: has a header but no data rows" in " ".join(
        done.stdout.split())


def test_a_table_that_fits_keeps_a_column_per_source(fits, tmp_path):
    results, _ = fits
    path = tmp_path / "two.jsonl"
    path.write_text("".join(json.dumps(comparison.record(source, fit)) + "\n"
                            for source, fit in list(results.items())[:2]))
    narrow = _report(path, columns="80")
    assert [line.split()[0] for line in narrow.stdout.splitlines()
            if line.startswith(("parameter", "source"))] == ["parameter"]
    assert max(map(len, narrow.stdout.splitlines())) <= 80


def test_a_wide_terminal_shows_fifteen_columns(fits):
    _, path = fits
    wide = _report(path, columns="1000")   # 16 columns of "joint + trajectory refinement"
    header = next(line for line in wide.stdout.splitlines() if line.startswith("parameter"))
    assert len(header.split()) == 1 + N_FITS + 1


def test_markdown_keeps_a_column_per_source(fits):
    _, path = fits
    text = _report(path, "--format", "markdown", columns="80").stdout
    assert text.count("| parameter | runs/decay_01.csv |") == 1


def test_fits_of_different_methods_show_the_method_in_each_row(fits):
    results, _ = fits
    compared = [comparison.Compared(source, fit) for source, fit in results.items()]
    compared[0] = comparison.Compared("energy.csv", hamid.fit(hamid.simulate(_system(0)),
                                                              method="energy"))
    text = comparison.render(compared, "table", width=100)
    assert max(map(len, text.splitlines())) <= 100
    assert text.splitlines()[0] == f"hamid report — {N_FITS} fits of duffing"
    header = next(line for line in text.splitlines() if line.startswith("source"))
    assert header.split()[-2:] == ["method", "warnings"]
    assert next(line for line in text.splitlines() if line.startswith("energy.csv")).split()[
        -2:] == ["energy", str(len(compared[0].outcome.warnings))]
