"""Hardening, round three (issue 33): numbers that broke the arithmetic, and work with no
bound (replicates, realizations, parameters drawn), now give one line before the work, a
correct result, or a bounded refusal."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pandas as pd
import pytest
from helpers import duffing_system, one_line_error

from hamid.errors import ModelError

ROOT = Path(__file__).parents[2]
DUFFING_CSV = "sample_data/duffing.csv"


def _run(hamid_cli, *args, cwd, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([*hamid_cli, *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300, env=env)


@pytest.fixture
def duffing(tmp_path) -> pd.DataFrame:
    return pd.read_csv(ROOT / DUFFING_CSV, comment="#")


@pytest.mark.parametrize("chunks", [[], ["--chunk-rows", "500"]])
def test_time_steps_too_small_to_compute_with(hamid_cli, tmp_path, duffing, chunks):
    """Times scaled by 1e-300 gave 'SVD did not converge' (1e-150: a division by zero)."""
    duffing["t"] *= 1e-300
    duffing.to_csv(tmp_path / "tiny.csv", index=False)
    one_line_error(_run(hamid_cli, "fit", "tiny.csv", "--model", "duffing", *chunks,
                         cwd=tmp_path), 1,
                    "tiny.csv: column 't', row 2: time step 5e-302 is too small")


def test_time_steps_of_1e_minus_60_still_fit(tmp_path, duffing):
    import hamid

    duffing["t"] *= 1e-60
    result = hamid.fit(duffing, model="duffing", method="energy")
    assert result.estimates["k"] == pytest.approx(1.0, rel=1e-6)


def test_forces_that_overflow_at_the_start_name_the_trajectory(hamid_cli, tmp_path):
    """k3 = 1e300 at x = 1e3: AttributeError in simulation.realizations."""
    (tmp_path / "sys.toml").write_text(duffing_system(k3="1e300", x="1e3"))
    one_line_error(_run(hamid_cli, "simulate", "--config", "sys.toml", "-o", "out.csv",
                         cwd=tmp_path), 1, "not finite at the initial state of trajectory 1",
                    "k3 = 1e+300")
    assert not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize("x", ["1e-3", "3e2"])
def test_forces_that_overflow_soon_after_the_start_are_an_escape(x):
    import tomllib

    import hamid

    system = tomllib.loads(duffing_system(k3="1e300", x=x))
    with pytest.raises(ModelError, match="trajectory 1 escapes"):
        hamid.simulate(system)


def test_too_many_realizations_are_refused_before_any_work(hamid_cli, tmp_path):
    """--realizations 100000000 took 3.6 GB of file names in 23 s before writing a file."""
    (tmp_path / "sys.toml").write_text(duffing_system() + "\n[noise]\nrelative = 0.01\n")
    one_line_error(_run(hamid_cli, "simulate", "--config", "sys.toml", "-o", "r.csv",
                         "--realizations", "100000000", cwd=tmp_path), 2,
                    "--realizations 100,000,000 would write 100,000,000 files",
                    "more than the 10,000")
    assert list(tmp_path.iterdir()) == [tmp_path / "sys.toml"]


@pytest.mark.parametrize(("args", "words"), [
    (["fit", DUFFING_CSV, "--model", "duffing", "--cov", "bootstrap", "--bootstrap",
      "99999999999999999999"], "--bootstrap 99,999,999,999,999,999,999: more replicates"),
    (["fit", DUFFING_CSV, "--model", "duffing", "--cov", "bootstrap", "--bootstrap",
      "1000000000"], "--bootstrap 1,000,000,000: more replicates than the 100,000"),
    (["select", DUFFING_CSV, "--stability", "1000000"],
     "--stability 1,000,000: more replicates than the 100,000"),
], ids=["1e20 replicates", "1e9 replicates", "select 1e6 replicates"])
def test_bootstrap_replicates_without_end_are_refused(hamid_cli, args, words):
    """--bootstrap 1000000000 and 99999999999999999999 ran until killed."""
    one_line_error(_run(hamid_cli, *args, cwd=ROOT), 2, words)


@pytest.mark.parametrize("cov", ["fit", "select"])
def test_bootstrap_rows_refitted_have_a_budget(monkeypatch, duffing, cov):
    import hamid
    from hamid import options
    from hamid.errors import UsageError

    monkeypatch.setattr(options, "REPLICATE_ROWS", 1000)
    with pytest.raises(UsageError, match=r"replicates of [\d,]+ rows would refit [\d,]+ rows, "
                                         r"more than 1,000; use at most \d+ replicates"):
        if cov == "fit":
            hamid.fit(duffing, model="duffing", cov="bootstrap", bootstrap=10)
        else:
            hamid.select(ROOT / DUFFING_CSV, stability=10)


def test_a_savgol_order_too_high_to_fit_is_refused(hamid_cli):
    """--order 99 printed numpy's RankWarning four times, with scipy's source lines."""
    line = one_line_error(_run(hamid_cli, "fit", DUFFING_CSV, "--model", "duffing",
                                "--velocity", "savgol", "--order", "99", cwd=ROOT), 2,
                           "--order 99", "window of 101 samples", "too poorly conditioned")
    assert "RankWarning" not in line


@pytest.mark.parametrize("order", [13, 17])
def test_high_savgol_orders_print_no_warning(hamid_cli, order):
    """Order 13 fits; 17, whose edge fit still works, is refused in one line by the
    precision of scipy's coefficients over its shortest window (19 samples): neither shows
    numpy's RankWarning or a source line."""
    done = _run(hamid_cli, "fit", DUFFING_CSV, "--model", "duffing", "--velocity", "savgol",
                "--order", str(order), "--format", "json", cwd=ROOT)
    assert done.returncode == (0 if order == 13 else 2), done.stderr
    assert "Warning" not in done.stderr and "site-packages" not in done.stderr
    if order == 17:
        assert done.stdout == "" and "cannot be computed accurately" in done.stderr


@pytest.mark.parametrize(("args", "environment", "words"), [
    (["--scheduler", "notaurl"], {}, "--scheduler: 'notaurl' is not a Dask scheduler"),
    ([], {"DASK_SCHEDULER_ADDRESS": "garbage"},
     "DASK_SCHEDULER_ADDRESS: 'garbage' is not a Dask scheduler"),
], ids=["option", "environment"])
def test_a_scheduler_address_that_is_not_one_is_refused_before_a_client(
        hamid_cli, args, environment, words):
    """The right line came, then 20 s later 'Exception ignored in Client.__del__' and a
    traceback of the half-made client."""
    import os

    done = _run(hamid_cli, "fit", "--each", DUFFING_CSV, "--model", "duffing", *args,
                cwd=ROOT, env={**os.environ, **environment})
    one_line_error(done, 2, words)


@pytest.mark.parametrize(("address", "good"), [
    ("tcp://127.0.0.1:8786", True), ("127.0.0.1:8786", True), ("[::1]:8786", True),
    ("tls://sched.example:443", True), ("notaurl", False), ("tcp://", False),
    ("tcp://host:port", False), ("http://host:80", False), ("tcp://host:0", False),
    ("tcp://host:70000", False), ("tcp://:8786", False), ("tcp://host:8786/path", False),
])
def test_scheduler_addresses(address, good):
    from hamid.errors import UsageError
    from hamid.executor import check_address

    if good:
        check_address(address, "--scheduler")
    else:
        with pytest.raises(UsageError, match="is not a Dask scheduler address"):
            check_address(address, "--scheduler")


@pytest.fixture(scope="module")
def report() -> dict:
    import hamid

    return hamid.fit(str(ROOT / DUFFING_CSV), "duffing", method="energy").to_dict()


def _edited(report: dict, tmp_path, **changes) -> str:
    import copy
    import json

    edited = copy.deepcopy(report)
    edited["parameters"][0].update(changes)
    if "name" in changes:
        edited["covariance"]["names"][0] = changes["name"]
    (tmp_path / "r.json").write_text(json.dumps(edited))
    return "r.json"


@pytest.mark.parametrize(("changes", "words"), [
    ({"estimate": 1e308, "ci_low": 1e308, "ci_high": 1e308},
     "parameter k: estimate 1e+308 and its interval are too large to draw"),
    ({"estimate": 2.0}, "parameter k: estimate 2 lies outside its interval"),
], ids=["estimate 1e308", "estimate outside its interval"])
def test_a_parameter_that_cannot_be_drawn_is_one_line(hamid_cli, tmp_path, report, changes,
                                                       words):
    """matplotlib's 'Axis limits cannot be NaN or Inf' and "'xerr' must not contain negative
    values" came out as internal errors."""
    name = _edited(report, tmp_path, **changes)
    one_line_error(_run(hamid_cli, "plot", name, "-o", "f.png", cwd=tmp_path), 1, words)
    assert not list(tmp_path.glob("f*.png"))


@pytest.mark.parametrize("name", ["$" + "{" * 3000 + "}" * 3000 + "$", "$x^$", "{" * 3000],
                         ids=["3000 braces in dollars", "bad mathtext", "3000 braces"])
def test_parameter_names_are_drawn_as_plain_text(tmp_path, report, name):
    """A name of nested braces overflowed mathtext's parser (RecursionError)."""
    import json

    from hamid.plot import figures, labels

    edited = json.loads((tmp_path / _edited(report, tmp_path, name=name)).read_text())
    drawn, _ = figures.pages(edited, None, "parameters,correlation")
    for _, figure in drawn:
        figure.savefig(tmp_path / "f.png")   # the text is parsed when drawn
    title = drawn[0][1].axes[0].get_title(loc="left")
    assert title.startswith(name[:labels.LONGEST_NAME - 1].replace("$", r"\$") + "…"
                            if len(name) >= labels.LONGEST_NAME else
                            name.replace("$", r"\$"))


def _many(report: dict, n: int) -> dict:
    import copy

    many = copy.deepcopy(report)
    many["parameters"] = [dict(report["parameters"][0], name=f"p{k}") for k in range(n)]
    many["covariance"] = {"names": [f"p{k}" for k in range(n)],
                          "matrix": [[float(i == j) for j in range(n)] for i in range(n)]}
    return many


def test_a_report_of_3002_parameters_is_refused_before_drawing(hamid_cli, tmp_path, report):
    """3,002 parameters ran past 180 s (the schema's check of 9 million covariance entries
    took most of it, then 3,002 rows of panel 5)."""
    import json

    (tmp_path / "r.json").write_text(json.dumps(_many(report, 3002)))
    line = one_line_error(_run(hamid_cli, "plot", "r.json", "-o", "f.png", cwd=tmp_path),
                           2, "no panel to draw", "at most 40 parameters to show (the "
                           "report has 3,002)", "at most 200 parameters")
    assert "panel 6 correlation" in line
    one_line_error(_run(hamid_cli, "plot", "r.json", "-o", "f.png", "--panels", "5",
                         cwd=tmp_path), 2, "panel 5 (parameters) needs at most 40")
    assert not list(tmp_path.glob("f*.png"))


def test_panels_within_the_limits_are_drawn_and_the_others_left_out(tmp_path, report):
    from hamid.plot import figures

    names, notes = figures.choose(_many(report, 41), None)
    assert names == ("correlation",)
    assert "left out panel 5 parameters: it needs at most 40 parameters" in notes[-1]
    assert figures.choose(_many(report, 40), None)[0] == ("parameters", "correlation")


def test_a_bad_entry_among_millions_of_covariance_entries_is_named(report):
    """The matrix is checked in a loop of its own, not by the schema's validator."""
    from hamid.errors import DataError
    from hamid.result.validation import check_result

    many = _many(report, 3002)
    check_result(many)
    many["covariance"]["matrix"][2999][7] = "x"
    with pytest.raises(DataError, match=r"'covariance.matrix\[2999\]\[7\]' is 'x', expected "
                                        "a number or null"):
        check_result(many, source="r.json")
