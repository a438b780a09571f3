"""FitResult in a notebook: summary(), _repr_html_(), to_frame(), cov, correlation and
simulate(), checked against the JSON report and against `hamid.simulate` with the true
parameters; and `hamid.fit` of a dict of arrays or a NumPy structured array."""

from __future__ import annotations

import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from conftest import DUFFING, with_noise
from statsmodels.stats.moment_helpers import cov2corr

import hamid
from hamid.errors import DataError, UsageError
from hamid.result.fit_result import FitResult

SAMPLE = Path(__file__).resolve().parents[2] / "sample_data" / "henon_heiles.csv"


@pytest.fixture(scope="module")
def report() -> dict:
    """The JSON report of a fit with a fixed parameter and a warning (of --cov classical)."""
    result = hamid.fit(str(SAMPLE), method="joint", cov="classical", fix={"d": -1 / 3})
    return json.loads(json.dumps(result.to_dict()))


@pytest.fixture(scope="module")
def result(report) -> FitResult:
    return FitResult.from_dict(report)


def _cell(value: float | None) -> str:
    return "—" if value is None else format(value, ".6g")


def test_summary_shows_the_reports_numbers(result, report):
    text = result.summary()
    assert text.splitlines()[0].strip() == "hamid fit — henon-heiles"
    lines = {line.split()[0]: line.split() for line in text.splitlines() if line.strip()}
    for p in report["parameters"]:
        row = lines[p["name"]]
        assert row[1] == (_cell(p["estimate"]) if not p["fixed"] else "(fixed)")
        if not p["fixed"]:
            assert row[2:5] == [_cell(p[k]) for k in ("stderr", "ci_low", "ci_high")]
    for level in report["energy_levels"]:
        assert lines[str(level["trajectory"])][1:3] == [_cell(level["h"]),
                                                        _cell(level["stderr"])]
    assert f"Samples:{report['data']['n_samples']:>30}" in text
    assert report["warnings"]
    first = 2 + bool(report["method"].get("covariance_description"))
    for k, warning in enumerate(report["warnings"], start=first):
        assert f"[{k}] {warning}"[:60] in " ".join(text.split())
    assert max(map(len, text.splitlines())) <= 78


class _Tables(HTMLParser):
    """The cells of every HTML table, row by row."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: list[list[list[str]]] = []
        self.items: list[str] = []
        self._cell: list[str] | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.tables.append([])
        elif tag == "tr":
            self.tables[-1].append([])
        elif tag in ("td", "th", "li"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.tables[-1][-1].append("".join(self._cell))
        elif tag == "li":
            self.items.append("".join(self._cell))
        if tag in ("td", "th", "li"):
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def test_html_tables_hold_the_reports_parameters_levels_and_warnings(result, report):
    parser = _Tables()
    parser.feed(result._repr_html_())
    parameters, levels = parser.tables[:2]
    assert parameters[0][:3] == ["name", "estimate", "std. error"]
    assert [row[:3] for row in parameters[1:]] == [
        [p["name"] + (" (fixed)" if p["fixed"] else ""), _cell(p["estimate"]),
         "" if p["fixed"] else _cell(p["stderr"])] for p in report["parameters"]]
    assert [row[:2] for row in levels[1:]] == [[str(h["trajectory"]), _cell(h["h"])]
                                               for h in report["energy_levels"]]
    conditioning = next(t for t in parser.tables if t[0][0] == "condition number")
    assert conditioning[0][1] == format(report["conditioning"]["condition_number"], ".4g")
    assert report["method"]["scale"]["per_unit_mass"]   # (vx**2 + vy**2)/2
    assert parser.items == ["parameters per unit mass (or moment of inertia): the energy's "
                            "kinetic part has no parameter",
                            *(f"warning: {w}" for w in report["warnings"])]


def test_html_escapes_text_from_data(report):
    tricky = {**report, "warnings": ["<script>alert(1)</script> & \x1b[31m"]}
    html = FitResult.from_dict(tricky)._repr_html_()
    assert "<script>" not in html and "&lt;script&gt;" in html and "\x1b" not in html


def test_to_frame_is_the_reports_parameters(result, report):
    frame = result.to_frame()
    assert list(frame.index) == [p["name"] for p in report["parameters"]]
    for p in report["parameters"]:
        row = frame.loc[p["name"]]
        assert row["role"] == p["role"] and row["fixed"] == p["fixed"]
        for key in ("estimate", "stderr", "ci_low", "ci_high", "truth"):
            assert (np.isnan(row[key]) if p[key] is None else row[key] == p[key]), key


def test_cov_and_correlation_are_the_reports_covariance(result, report):
    names, matrix = report["covariance"]["names"], np.array(report["covariance"]["matrix"])
    assert list(result.cov.index) == list(result.cov.columns) == names == ["a", "b", "c"]
    np.testing.assert_array_equal(result.cov.to_numpy(), matrix)
    sd = {p["name"]: p["stderr"] for p in report["parameters"]}
    np.testing.assert_allclose(np.sqrt(np.diag(result.cov)), [sd[n] for n in names],
                               rtol=1e-12)
    correlation = result.correlation
    assert list(correlation.index) == list(correlation.columns) == names
    np.testing.assert_allclose(correlation.to_numpy(), cov2corr(matrix), rtol=1e-13)


def test_a_report_without_covariance_has_none(report):
    old = {k: v for k, v in report.items() if k != "covariance"}
    loaded = FitResult.from_dict(old)
    assert loaded.cov is None and loaded.correlation is None


def test_repr_is_short(result):
    text = repr(result)
    assert len(text) < 300
    assert text.startswith("FitResult(model='henon-heiles', method='joint', estimates={'a': ")


@pytest.fixture(scope="module")
def duffing_fit(clean_records) -> FitResult:
    return hamid.fit(with_noise(clean_records["duffing"], 0.005, seed=7))


def test_simulate_follows_the_true_motion(duffing_fit):
    """The fitted model's motion stays within what its parameter errors allow of the
    motion with the true parameters (the estimates are within 1e-3 of the truth, a phase
    error of about 1e-3 * 2 pi * 3 periods)."""
    truth = DUFFING["parameters"]
    assert max(abs(e / truth[k] - 1) for k, e in duffing_fit.estimates.items()) < 1e-3
    t = np.arange(0, 20.0 + 1e-9, 0.05)
    initial = DUFFING["initial"]
    fitted = duffing_fit.simulate(initial, t)
    true = hamid.simulate({**DUFFING, "simulate": {"t_end": 20.0, "dt": 0.05}})
    assert list(fitted.columns) == ["trajectory", "t", "x", "v"]
    np.testing.assert_array_equal(fitted[["trajectory", "t"]], true[["trajectory", "t"]])
    error = np.abs(fitted[["x", "v"]].to_numpy() - true[["x", "v"]].to_numpy()).max()
    assert 1e-6 < error < 0.02
    assert fitted.attrs["hamid"]["parameters"] == duffing_fit.estimates


def test_simulate_one_state_with_the_fitted_damping(clean_records):
    damped = hamid.simulate({**DUFFING, "damping": {"c_x": 0.05}})
    result = hamid.fit(damped, damping="viscous")
    motion = result.simulate({"x": 1.0, "v": 0.0}, np.linspace(0, 30, 601))
    truth = damped[damped.trajectory == 1]
    np.testing.assert_allclose(motion["x"], truth["x"], atol=1e-4)


@pytest.mark.parametrize("t", [[0.1, 0.2, 0.3], [0, 0.1, 0.3], [0.0], [[0, 1], [2, 3]]])
def test_simulate_needs_even_times_from_zero(duffing_fit, t):
    with pytest.raises(UsageError, match="^simulate: t must be evenly spaced times from 0"):
        duffing_fit.simulate({"x": 1.0, "v": 0.0}, t)


def test_fit_reads_a_dict_of_arrays_and_a_structured_array(clean_records):
    frame = clean_records["duffing"]
    expected = hamid.fit(frame)
    columns = {name: frame[name].to_numpy() for name in frame.columns}
    structured = frame.to_records(index=False)
    for data, name in ((columns, "<dict>"), (np.asarray(structured), "<array>")):
        result = hamid.fit(data, "duffing")
        assert result.estimates == expected.estimates
        assert result.data["sources"] == [name]
        assert result.provenance["inputs"] == [{"path": name, "size": None, "sha256": None}]


@pytest.mark.parametrize(("data", "message"), [
    ({"x": [1.0, 2.0, 3.0], "v": [0.0, 1.0]}, r"^<dict>: the columns have different lengths "
                                              r"\(x: 3, v: 2\)$"),
    ({"x": np.zeros((3, 2)), "v": np.zeros(3)}, r"^<dict>: column 'x' has shape \(3, 2\)"),
    ({"x": ["1", "n/a"], "v": [0.0, 1.0]}, r"^<dict>: column 'x', row 2: 'n/a' is not a number"),
])
def test_bad_dicts_name_the_column(data, message):
    with pytest.raises(DataError, match=message):
        hamid.fit(data, "duffing", gaps="error")


def test_a_dataframe_fit_keeps_its_records_for_the_pictures(clean_records):
    frame = clean_records["duffing"]
    result = hamid.fit(frame)
    assert result.recording is not None
    np.testing.assert_array_equal(result.recording.records.X, frame[["x", "v"]].to_numpy())
    loaded = FitResult.from_dict(result.to_dict())
    assert loaded.recording is None and loaded == result   # not part of equality
