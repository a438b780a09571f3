"""Parameters across recordings (`hamid plot results.jsonl`, `hamid plot A.json B.json`):
a row per parameter, each fit's estimate and interval as its report gives them, in file
order or by a key of the reports (--order-by); its errors in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import one_line_error

import hamid
from hamid.cli.app import cli
from hamid.plot import drift
from hamid.report import comparison

pytest.importorskip("matplotlib")

from matplotlib.axes import Axes  # noqa: E402
from test_layout import layout_faults  # noqa: E402

# The stiffness drifts from 1.0 to 1.2 over the recordings.
STIFFNESS = (1.0, 1.1, 1.2)


def _run(*args: str):
    return CliRunner().invoke(cli, list(args))


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Three recordings of a Duffing oscillator, fitted by `fit --each` into runs.jsonl,
    and each fit's report as its own JSON file."""
    folder = tmp_path_factory.mktemp("drift")
    (folder / "runs").mkdir()
    for k, stiffness in enumerate(STIFFNESS, 1):
        frame = hamid.simulate({"model": {"builtin": "duffing"},
                                "parameters": {"k": stiffness, "k3": 0.5},
                                "initial": [{"x": 1.0, "v": 0.0}],
                                "simulate": {"t_end": 20.0, "dt": 0.05, "seed": k},
                                "noise": {"x": 1e-3, "v": 1e-3}})
        frame.to_csv(folder / "runs" / f"run{k}.csv", index=False)
        fit = hamid.fit(str(folder / "runs" / f"run{k}.csv"), model="duffing")
        (folder / f"run{k}.json").write_text(json.dumps(fit.to_dict()))
    done = _run("fit", "--each", str(folder / "runs"), "--model", "duffing",
                "-o", str(folder / "runs.jsonl"))
    assert done.exit_code == 0, done.output
    return folder


def _lines(runs: Path) -> list[dict]:
    return [json.loads(line) for line in (runs / "runs.jsonl").read_text().splitlines()]


def test_each_parameter_against_the_file_order_with_its_interval(runs):
    figure, notes = drift.drift_figure(comparison.load([str(runs / "runs.jsonl")]))
    assert notes == []
    axes = [ax for ax in figure.findobj(Axes)]
    assert [ax.get_ylabel() for ax in axes] == ["k", "k3"]
    lines = _lines(runs)
    for ax, name in zip(axes, ["k", "k3"], strict=True):
        (bars,) = ax.containers
        point, _, (segments,) = bars
        wanted = [next(p for p in line["parameters"] if p["name"] == name) for line in lines]
        np.testing.assert_array_equal(point.get_xdata(), [1, 2, 3])
        np.testing.assert_array_equal(point.get_ydata(), [p["estimate"] for p in wanted])
        np.testing.assert_allclose([s[:, 1] for s in segments.get_segments()],
                                   [[p["ci_low"], p["ci_high"]] for p in wanted])
    # the drift is there: k grows with the recordings as simulated
    k = np.asarray(axes[0].containers[0][0].get_ydata(), dtype=float)
    np.testing.assert_allclose(k, STIFFNESS, rtol=0.02)
    assert layout_faults(figure) == []


def test_plot_of_a_jsonl_and_of_several_reports(runs, tmp_path):
    done = _run("plot", str(runs / "runs.jsonl"), "-o", str(tmp_path / "drift.png"))
    assert done.exit_code == 0 and done.stdout == "", done.output
    reports = [str(runs / f"run{k}.json") for k in (1, 2, 3)]
    done = _run("plot", *reports, "-o", str(tmp_path / "reports.pdf"))
    assert done.exit_code == 0 and done.stdout == "", done.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drift.png", "reports.pdf"]
    assert (tmp_path / "drift.png").read_bytes()[:4] == b"\x89PNG"


def test_order_by_a_key_of_the_reports(runs):
    """By a number (the samples each fit read) and by a time (when each was fitted)."""
    compared = comparison.load([str(runs / "runs.jsonl")])
    assert drift.order_values(compared, "data.n_samples") == [401.0] * 3
    times = drift.order_values(compared, "provenance.utc")
    assert [t.isoformat() for t in times] == [
        line["provenance"]["utc"].replace("Z", "+00:00") for line in _lines(runs)]
    figure, _ = drift.drift_figure(compared, "provenance.utc")
    assert figure.findobj(Axes)[-1].get_xlabel() == "provenance.utc"


@pytest.mark.parametrize(("args", "code", "words"), [
    (["--order-by", "data.nope"], 1, ["run1.csv", "data.nope", "no"]),
    (["--order-by", "model.name"], 1, ["model.name", "'duffing'", "ISO 8601"]),
    (["--order-by", "data"], 1, ["neither a number nor a time"]),
    (["--panels", "1"], 2, ["--panels", "several fits"]),
])
def test_order_by_and_panels_errors(runs, tmp_path, args, code, words):
    out = tmp_path / "x.png"
    done = _run("plot", str(runs / "runs.jsonl"), "-o", str(out), *args)
    one_line_error(done, code, *words)
    assert not out.exists()


def test_order_by_needs_several_fits(runs, tmp_path):
    done = _run("plot", str(runs / "run1.json"), "-o", str(tmp_path / "x.png"),
                "--order-by", "provenance.utc")
    one_line_error(done, 2, "--order-by", "several fits")


def test_report_plot_draws_the_figure_plot_draws(runs, tmp_path):
    """`hamid report runs.jsonl --plot` writes the report and the figure `hamid plot`
    draws of the same fits (with --order-by passed on): the same axes, the same points."""
    done = _run("report", str(runs / "runs.jsonl"), "-o", str(tmp_path / "r.md"),
                "--plot", str(tmp_path / "drift.png"), "--order-by", "data.n_samples")
    assert done.exit_code == 0 and done.stdout == "", done.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drift.png", "r.md"]
    assert (tmp_path / "drift.png").read_bytes()[:4] == b"\x89PNG"
    assert "| k |" in (tmp_path / "r.md").read_text()
    drawn = []
    original = drift.drift_figure
    for args in (["report", str(runs / "runs.jsonl"), "-o", str(tmp_path / "r.txt"),
                  "--plot", str(tmp_path / "a.svg"), "--order-by", "provenance.utc"],
                 ["plot", str(runs / "runs.jsonl"), "-o", str(tmp_path / "b.svg"),
                  "--order-by", "provenance.utc"]):
        def spy(compared, order_by=None, _drawn=drawn):
            figure, notes = original(compared, order_by)
            _drawn.append([(ax.get_ylabel(), ax.get_xlabel(),
                            [list(line.get_xydata().ravel()) for line in ax.get_lines()])
                           for ax in figure.findobj(Axes)])
            return figure, notes
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(drift, "drift_figure", spy)
            done = _run(*args)
        assert done.exit_code == 0, done.output
    assert len(drawn) == 2 and drawn[0] == drawn[1]
    assert drawn[0][-1][1] == "provenance.utc"


def test_report_plot_of_one_report_draws_its_panels(runs, tmp_path):
    done = _run("report", str(runs / "run1.json"), "-o", str(tmp_path / "r.json"),
                "--plot", str(tmp_path / "f.pdf"))
    assert done.exit_code == 0 and done.stdout == "", done.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.pdf", "r.json"]
    assert (tmp_path / "f.pdf").read_bytes()[:4] == b"%PDF"


@pytest.mark.parametrize(("args", "code", "words"), [
    (["--plot", "{out}/x.gif"], 2, ["--plot", "x.gif", ".png"]),
    (["--order-by", "provenance.utc"], 2, ["--order-by", "--plot"]),
    (["--plot", "{out}/x.png", "--order-by", "data.nope"], 1, ["data.nope", "no"]),
])
def test_report_plot_errors_write_nothing(runs, tmp_path, args, code, words):
    out = tmp_path / "out"
    out.mkdir()
    done = _run("report", str(runs / "runs.jsonl"), "-o", str(out / "r.md"),
                *(a.format(out=out) for a in args))
    one_line_error(done, code, *words)
    assert list(out.iterdir()) == []


def test_report_plot_order_by_needs_several_fits(runs, tmp_path):
    done = _run("report", str(runs / "run1.json"), "--plot", str(tmp_path / "x.png"),
                "--order-by", "provenance.utc")
    one_line_error(done, 2, "--order-by", "several fits")
    assert list(tmp_path.iterdir()) == []


def test_report_plot_without_matplotlib_one_line_names_the_extra(runs, tmp_path):
    code = ("import sys\nsys.modules['matplotlib'] = None\n"
            "from hamid.cli.app import main\nmain()")
    for report in ("runs.jsonl", "run1.json"):
        out = subprocess.run([sys.executable, "-c", code, "report", str(runs / report), "-o",
                              str(tmp_path / "r.md"), "--plot", str(tmp_path / "f.png")],
                             capture_output=True, text=True)
        assert out.returncode == 1 and out.stdout == ""
        assert out.stderr == ("Error: drawing figures needs matplotlib: "
                              "pip install 'hamid[plot]'\n")
    assert list(tmp_path.iterdir()) == []
