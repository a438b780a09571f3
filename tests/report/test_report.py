"""Tests for hamid.report.formats: rendering a "hamid.fit/1" result; and checking loaded JSON
(`FitResult.from_dict`, against hamid/schema/fit-1.json)."""

from __future__ import annotations

import copy
import csv
import html
import io
import json
import re

import pytest

from hamid.errors import DataError, UsageError
from hamid.report.formats import render
from hamid.result.fit_result import FitResult

ANSI = re.compile(r"\x1b\[")
TEXT_FORMATS = ["table", "markdown"]
ALL_FORMATS = ["table", "json", "markdown", "csv"]
TOP_KEYS = [
    "schema",
    "hamid_version",
    "model",
    "data",
    "method",
    "parameters",
    "energy_levels",
    "residuals",
    "conditioning",
    "warnings",
]
PARAMETER_FIELDS = ["name", "estimate", "stderr", "ci_low", "ci_high", "truth", "fixed"]


def _parameter(name, estimate, stderr, truth, *, role="energy", fixed=False):
    half = None if stderr is None else 1.96 * stderr
    return {
        "name": name,
        "role": role,
        "estimate": estimate,
        "stderr": stderr,
        "ci_low": None if half is None else estimate - half,
        "ci_high": None if half is None else estimate + half,
        "truth": truth,
        "fixed": fixed,
    }


@pytest.fixture
def result():
    """A peng-quadratic fit with known truths, one fixed and one damping parameter."""
    return {
        "schema": "hamid.fit/1",
        "hamid_version": "0.1.0",
        "model": {
            "name": "peng-quadratic",
            "energy": "(v1**2 + v2**2)/2 + w1sq*u1**2/2 + w2sq*u2**2/2 - a1*u1**3/3"
            " - a2*u1**2*u2/2 - a3*u1*u2**2 - a6*u2**3/3",
            "coordinates": ["u1", "u2"],
            "velocities": ["v1", "v2"],
            "parameters": ["w1sq", "w2sq", "a1", "a2", "a3", "a6"],
        },
        "data": {
            "sources": ["run1.csv", "run2.csv"],
            "n_samples": 40002,
            "n_trajectories": 2,
            "columns": {"u1": "u1", "u2": "u2", "v1": "v1", "v2": "v2"},
            "velocity_source": "measured",
        },
        "method": {
            "kind": "joint",
            "kind_reason": "time column sampled finely enough for weak-form windows",
            "weak_window": 1.5,
            "damping": ["viscous"],
            "weighting": "noise",
            "noise": {"u1": 0.001, "u2": 0.002},
            "bias_correction": True,
            "covariance": "hac",
            "level": 0.95,
            "fixed": {"a6": 0.2},
        },
        "parameters": [
            _parameter("w1sq", 1.0001234567891235, 0.00041234, 1.0),
            _parameter("w2sq", 2.2489761234, 0.0012, 2.25),
            _parameter("a1", 0.2993817264519283, 0.0021, 0.3),
            _parameter("a2", -0.40123456789, 0.0035, -0.4),
            _parameter("a3", 0.2512, 0.0042, 0.25),
            _parameter("a6", 0.2, None, 0.2, fixed=True),
            _parameter("c_u1", 0.0019876, 0.00011, 0.002, role="damping"),
        ],
        "energy_levels": [
            {"trajectory": 0, "h": 0.0712345678, "stderr": 1.2e-06, "n_samples": 20001},
            {"trajectory": 1, "h": 0.1523456789, "stderr": 2.5e-06, "n_samples": 20001},
        ],
        "residuals": {
            "rms": 0.000123456,
            "max_abs": 0.000612345,
            "relative_rms": 0.00110123,
            "r_squared": 0.99987654,
            "lag1_autocorrelation": 0.4321,
            "drift": [
                {"trajectory": 0, "relative_change": -0.0123},
                {"trajectory": 1, "relative_change": 0.00456},
            ],
        },
        "conditioning": {
            "condition_number": 412.3456,
            "singular_values": [3.1, 1.7, 0.9, 0.2, 0.05, 0.0075],
            "weakest_direction": {"w1sq": 0.02, "a1": 0.06, "a2": 0.7, "a3": -0.71},
            "status": "moderate",
        },
        "warnings": [
            "ill conditioned: a2 and a3 are hard to tell apart (condition number 412)",
            "parameter a3 is not significantly different from zero",
        ],
    }


@pytest.fixture
def no_truth(result):
    """The same fit on data whose metadata carries no true values."""
    blind = copy.deepcopy(result)
    for parameter in blind["parameters"]:
        parameter["truth"] = None
    return blind


@pytest.fixture(params=["result", "no_truth"])
def any_result(request):
    return request.getfixturevalue(request.param)


def _csv_rows(text):
    return list(csv.DictReader(io.StringIO(text)))


# --- json --------------------------------------------------------------------------------


def test_json_round_trip(any_result):
    text = render(any_result, "json")
    assert json.loads(text) == any_result
    assert text.endswith("}\n")


def test_json_keeps_key_order_and_indents(result):
    text = render(result, "json")
    assert list(json.loads(text)) == TOP_KEYS  # not sorted: "schema" comes first
    assert text.startswith('{\n  "schema": "hamid.fit/1",\n')


def test_json_refuses_nan(result):
    result["parameters"][0]["stderr"] = float("nan")
    with pytest.raises(ValueError, match="Out of range float"):
        render(result, "json")


# --- csv ---------------------------------------------------------------------------------


def test_csv_header_and_one_row_per_parameter(result):
    text = render(result, "csv")
    assert text.splitlines()[0] == (
        "name,role,estimate,stderr,ci_low,ci_high,truth,relative_error,fixed"
    )
    rows = _csv_rows(text)
    assert [r["name"] for r in rows] == ["w1sq", "w2sq", "a1", "a2", "a3", "a6", "c_u1"]
    assert [r["role"] for r in rows] == ["energy"] * 6 + ["damping"]
    assert [r["fixed"] for r in rows] == ["false"] * 5 + ["true", "false"]


@pytest.mark.parametrize("field", ["estimate", "stderr", "ci_low", "ci_high", "truth"])
def test_csv_numbers_are_exact_and_nulls_empty(any_result, field):
    rows = _csv_rows(render(any_result, "csv"))
    for row, parameter in zip(rows, any_result["parameters"], strict=True):
        if parameter[field] is None:
            assert row[field] == ""
        else:
            assert float(row[field]) == parameter[field]


def test_csv_full_precision(result):
    rows = _csv_rows(render(result, "csv"))
    assert rows[0]["estimate"] == "1.0001234567891235"
    assert rows[2]["estimate"] == "0.2993817264519283"


def test_csv_relative_error(result):
    rows = {r["name"]: r for r in _csv_rows(render(result, "csv"))}
    expected = {
        "w1sq": (1.0001234567891235 - 1.0) / 1.0,
        "w2sq": (2.2489761234 - 2.25) / 2.25,
        "a1": (0.2993817264519283 - 0.3) / 0.3,
        "a2": (-0.40123456789 - -0.4) / -0.4,
        "a3": (0.2512 - 0.25) / 0.25,
        "a6": 0.0,
        "c_u1": (0.0019876 - 0.002) / 0.002,
    }
    for name, value in expected.items():
        assert float(rows[name]["relative_error"]) == pytest.approx(value, rel=1e-12, abs=0)


def test_csv_relative_error_empty_without_truth_or_at_zero_truth(no_truth):
    no_truth["parameters"][1]["truth"] = 0.0
    rows = _csv_rows(render(no_truth, "csv"))
    assert rows[1]["truth"] == "0.0"
    assert [r["relative_error"] for r in rows] == [""] * 7


# --- table and markdown ------------------------------------------------------------------


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_shows_every_parameter_and_estimate(any_result, fmt):
    text = render(any_result, fmt)
    for parameter in any_result["parameters"]:
        assert parameter["name"] in text
        assert f"{parameter['estimate']:.6g}" in text
    assert "1.00012" in text  # 6 significant digits, by hand
    assert "-0.401235" in text


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_shows_stderr_and_intervals(result, fmt):
    text = render(result, fmt)
    for parameter in result["parameters"]:
        if not parameter["fixed"]:
            for key in ("stderr", "ci_low", "ci_high"):
                assert f"{parameter[key]:.6g}" in text
    assert "95% CI low" in text
    assert "95% CI high" in text


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_level_follows_method(result, fmt):
    result["method"]["level"] = 0.9
    text = render(result, fmt)
    assert "90% CI low" in text
    assert "95%" not in text


@pytest.mark.parametrize(("level", "shown"), [
    (0.95, "95%"), (0.9, "90%"), (0.975, "97.5%"), (0.5, "50%"), (1e-05, "0.001%"),
    (0.9999999999999999, "99.99999999999999%"),
])
def test_text_level_is_never_rounded(result, level, shown):
    result["method"]["level"] = level
    text = render(result, "markdown")
    assert f"{shown} CI low" in text
    assert f"{shown} intervals" in text
    assert "100%" not in text


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_warnings_last(result, fmt):
    text = render(result, fmt)
    last = text.rstrip().splitlines()[-2:]
    for line, warning in zip(last, result["warnings"], strict=True):
        assert f"warning: {warning}" in line


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_conditioning(result, fmt):
    text = render(result, fmt)
    assert "412.3" in text
    assert "moderate" in text
    assert "−0.71·a3 + 0.70·a2 + 0.06·a1" in text  # w1sq (0.02) is below 0.05
    assert "w1sq" not in text.split("Conditioning")[1].split("Method")[0]


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_truth_columns_only_with_truth(result, no_truth, fmt):
    with_truth = render(result, fmt)
    assert "truth" in with_truth
    assert "rel. error" in with_truth
    assert "-0.206%" in with_truth  # a1: (0.29938 - 0.3) / 0.3 = -0.206 %
    assert "+0.0123%" in with_truth  # w1sq
    without = render(no_truth, fmt)
    assert "truth" not in without
    assert "rel. error" not in without
    assert not re.search(r"[+-][0-9.e+-]+%", without.split("Parameters")[1].split("Energy")[0])


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_energy_levels_residuals_and_drift(result, fmt):
    text = render(result, fmt)
    for snippet in ["0.0712346", "1.2e-06", "0.152346", "2.5e-06", "20001"]:
        assert snippet in text
    for snippet in ["0.0001235", "0.0006123", "0.001101", "0.999877", "0.432"]:
        assert snippet in text
    assert "falls by 1.23% of its level h" in text
    assert "rises by 0.456% of its level h" in text
    result["residuals"]["drift"] = [{"trajectory": 0, "relative_change": -2.678}]
    assert "falls by 2.68 times its level h" in render(result, fmt)
    result["data"]["inputs"] = {"u": "force"}
    assert "falls by 2.68 times the spread of its energy" in render(result, fmt)
    result["residuals"]["drift"] = []
    assert "energy over the record" not in render(result, fmt)


def _refined(result, lengthening):
    """`result` with an applied refinement of 12 segments of 2 s, lengthened as given."""
    result["method"]["refinement"] = {
        "applied": True, "segments": 12, "segment_seconds": 2.0, "iterations": 4,
        "chi2_per_dof": 1.02, "lengthening": {"iterations": 2, "chi2_per_dof": 1.01,
                                              **lengthening}}
    return result


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_a_fit_lengthened_to_the_whole_record_says_so(result, fmt):
    one = render(_refined(result, {"segments": 1, "segment_seconds": 21.28, "rounds": 1,
                                   "stopped": "whole"}), fmt, width=200)
    assert "trajectory fit over the whole record, 21.28 s, misfit 1.01 × noise variance, " \
           "2 iterations" in one
    assert "12 segments of 2 s, misfit 1.02 × noise variance, 4 iterations" in one
    two = render(_refined(result, {"segments": 2, "segment_seconds": 21.28, "rounds": 1,
                                   "stopped": "whole"}), fmt, width=200)
    assert "trajectory fit over each whole trajectory (2, up to 21.28 s)" in two
    some = render(_refined(result, {"segments": 3, "segment_seconds": 8.0, "rounds": 2,
                                    "stopped": "misfit"}), fmt, width=200)
    assert "trajectory fit over 3 segments of up to 8 s (longer ones missed the recording " \
           "beyond the noise), misfit 1.01" in some
    none = render(_refined(result, {"segments": 12, "segment_seconds": 2.0, "rounds": 0,
                                    "stopped": "clean"}), fmt, width=200)
    assert "trajectory fit over 12 segments of 2 s, misfit 1.02 × noise variance, " \
           "4 iterations" in none
    assert "lengthened" not in none and "whole" not in none


@pytest.mark.parametrize("fmt", [*TEXT_FORMATS, "summary", "html"])
def test_a_refined_fit_names_the_refinement_as_its_method(result, fmt):
    assert "joint + trajectory refinement" not in render(result, fmt)
    refined = _refined(result, {"segments": 1, "segment_seconds": 21.28, "rounds": 1,
                                "stopped": "whole"})
    assert "joint + trajectory refinement" in render(refined, fmt)
    assert json.loads(render(refined, "json"))["method"]["kind"] == "joint"


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_method_details(result, fmt):
    text = render(result, fmt)
    assert "method joint (time column sampled finely enough" in text
    for snippet in ["hac, 95% intervals", "u1 0.001, u2 0.002", "1.5 s", "viscous", "a6 = 0.2"]:
        assert snippet in text
    result["method"]["weak_window"] = None
    result["method"]["noise"] = None
    text = render(result, fmt)
    assert "weak window" not in text
    assert "noise σ" not in text


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_data_line(result, fmt):
    text = render(result, fmt)
    assert "40002 samples in 2 trajectories from run1.csv, run2.csv" in text
    assert "velocities measured" in text
    result["data"]["velocity_source"] = "savgol"
    assert "velocities derived" in render(result, fmt)


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_damping_after_energy_parameters(result, fmt):
    damping = result["parameters"].pop()
    result["parameters"].insert(0, damping)
    text = render(result, fmt)
    assert text.index("c_u1") > text.index("a3")
    assert "damping" in text.split("a3")[1].split("c_u1")[0]


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_fixed_parameter_has_no_spread(result, fmt):
    text = render(result, fmt)
    (line,) = [ln for ln in text.splitlines() if "a6" in ln and "(fixed)" in ln]
    assert "0.2" in line
    assert "—" not in line
    assert not re.search(r"\d.*\d.*\d", line.replace("0.2", "", 2).replace("+0%", ""))


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_missing_stderr_is_em_dash(result, fmt):
    result["parameters"][4].update(stderr=None, ci_low=None, ci_high=None)
    (line,) = [ln for ln in render(result, fmt).splitlines() if "a3" in ln and "0.2512" in ln]
    assert line.count("—") == 3


def test_table_has_no_ansi_without_color(result):
    assert not ANSI.search(render(result, "table"))
    assert ANSI.search(render(result, "table", color=True))


@pytest.mark.parametrize("width", [80, 100])
def test_table_fits_width(any_result, width):
    text = render(any_result, "table", width=width)
    assert max(len(line) for line in text.splitlines()) <= width


@pytest.mark.parametrize("width", [72, 80, 100])
def test_table_keeps_numbers_whole(result, width):
    text = render(result, "table", width=width)
    for parameter in result["parameters"]:
        for key in ("estimate", "stderr", "ci_low", "ci_high", "truth"):
            if parameter[key] is not None:
                assert f"{parameter[key]:.6g}" in text


def test_table_title_first(result):
    first = render(result, "table").splitlines()[0]
    assert first.startswith("hamid fit — peng-quadratic, method joint")


def test_table_names_are_not_markup(result):
    result["parameters"][0]["name"] = "k[bold]"
    assert "k[bold]" in render(result, "table")


def test_markdown_tables_have_header_rows(any_result):
    text = render(any_result, "markdown")
    blocks = re.findall(r"(?:^\|.*\|\n)+", text, flags=re.MULTILINE)
    headers = [block.splitlines()[0] for block in blocks]
    assert headers[0].startswith("| name | estimate | std. error | 95% CI low | 95% CI high |")
    assert headers[1] == "| trajectory | h | std. error | samples |"
    assert len(blocks) == 6  # parameters, levels, residuals, drift, conditioning, method
    for block in blocks:
        lines = block.splitlines()
        columns = lines[0].count(" | ") + 1
        assert lines[1] == "|" + "---|" * columns
        for line in lines[2:]:
            assert len(re.findall(r"(?<!\\)\|", line)) == columns + 1


def test_markdown_headings(result):
    text = render(result, "markdown")
    headings = re.findall(r"^## (.+)$", text, flags=re.MULTILINE)
    assert headings == ["Parameters", "Energy levels", "Residuals", "Conditioning", "Method"]


def test_markdown_escapes_pipes(result):
    result["data"]["sources"] = ["a|b.csv"]
    result["warnings"] = []
    result["method"]["fixed"] = {"a|6": 0.2}
    text = render(result, "markdown")
    assert "a\\|6 = 0.2" in text


# --- dispatch ----------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ALL_FORMATS)
def test_render_ends_with_newline(result, fmt):
    text = render(result, fmt)
    assert text.endswith("\n")
    assert not text.endswith("\n\n")


SMALL_AMPLITUDE = {"equilibrium": {"u1": 0.0, "u2": 0.0},
                   "modes": [{"mode": 1, "frequency_hz": 0.159155, "damping_ratio": 0.0099},
                             {"mode": 2, "frequency_hz": 0.238732, "damping_ratio": None}]}


@pytest.mark.parametrize("fmt", [*TEXT_FORMATS, "summary"])
def test_text_damping_at_small_amplitude_by_mode_in_hz(result, fmt):
    result["dissipation"] = {"trajectories": [{"trajectory": 0, "energy_lost_fraction": 0.2}],
                             "equivalent_damping_ratio": None, "period": None,
                             "small_amplitude": SMALL_AMPLITUDE}
    text = render(result, fmt)
    assert "natural frequency (Hz)" in text and "damping ratio ζ" in text
    assert re.search(r"1\W+0\.159155\W+0\.0099", text)
    assert re.search(r"2\W+0\.238732\W+—", text)
    assert "at small amplitude: the model linearized about u1 = 0, u2 = 0" in " ".join(
        text.split())
    assert "dominant period" not in text


@pytest.mark.parametrize("fmt", TEXT_FORMATS)
def test_text_damping_ratio_of_an_earlier_report_says_its_period(result, fmt):
    """Reports of earlier versions took the ratio at the recording's dominant period."""
    result["dissipation"] = {"trajectories": [{"trajectory": 0, "energy_lost_fraction": 0.2}],
                             "equivalent_damping_ratio": 0.00964, "period": 0.0764}
    text = render(result, fmt)
    assert "0.00964" in text and "at the dominant period" in text and "0.0764 s" in text
    assert "natural frequency" not in text


@pytest.mark.parametrize("fmt", [*TEXT_FORMATS, "summary", "html"])
@pytest.mark.parametrize("per_unit_mass", [True, False, None])
def test_text_says_per_unit_mass_when_the_kinetic_energy_has_no_parameter(
        result, fmt, per_unit_mass):
    if per_unit_mass is not None:   # None: a report of an earlier version
        result["method"]["scale"] = {"source": "energy", "by": "the energy's parameter-free "
                                     "part", "per_unit_mass": per_unit_mass}
    text = " ".join(html.unescape(render(result, fmt)).split())
    said = ("parameters per unit mass (or moment of inertia): the energy's kinetic part has "
            "no parameter") in text
    assert said is bool(per_unit_mass)


def test_render_unknown_format(result):
    with pytest.raises(UsageError, match="unknown report format 'xml'"):
        render(result, "xml")


# --- checking loaded JSON (FitResult.from_dict) -----------------------------------------


def validate_result(result, *, source):
    """The check `hamid report` makes; returns the dict the report is rendered from."""
    return FitResult.from_dict(result, source=source).to_dict()


def test_validate_accepts_fit_result(any_result):
    assert validate_result(any_result, source="result.json") == {**any_result,
                                                                  "dissipation": None}


def test_validate_accepts_extra_keys(result):
    result["extra"] = {"anything": 1}
    result["parameters"][0]["note"] = "new in a later version"
    result["method"]["note"] = "kept"
    checked = validate_result(result, source="result.json")
    assert "extra" not in checked
    assert "note" not in checked["parameters"][0]
    assert checked["method"]["note"] == "kept"


def test_validate_accepts_the_small_amplitude_keys_and_rejects_their_wrong_types(result):
    result["method"]["scale"] = {"source": "energy", "by": "E0", "per_unit_mass": True}
    result["dissipation"] = {"trajectories": [], "equivalent_damping_ratio": None,
                             "period": None, "small_amplitude": SMALL_AMPLITUDE}
    assert validate_result(result, source="r.json")["dissipation"]["small_amplitude"] == \
        SMALL_AMPLITUDE
    result["dissipation"]["small_amplitude"]["modes"][0]["frequency_hz"] = "12 Hz"
    with pytest.raises(DataError, match=r"small_amplitude\.modes\[0\]\.frequency_hz' is"):
        validate_result(result, source="r.json")
    result["dissipation"]["small_amplitude"] = None
    result["method"]["scale"]["per_unit_mass"] = "yes"
    with pytest.raises(DataError, match=r"'method\.scale\.per_unit_mass' is 'yes'"):
        validate_result(result, source="r.json")


def test_validate_rejects_wrong_schema(result):
    result["schema"] = "foo"
    message = (
        r"^result\.json: not a hamid fit result "
        r"\(key 'schema' is 'foo', expected 'hamid\.fit/1'\)$"
    )
    with pytest.raises(DataError, match=message):
        validate_result(result, source="result.json")


@pytest.mark.parametrize("key", TOP_KEYS)
def test_validate_rejects_missing_top_key(result, key):
    del result[key]
    message = rf"^result\.json: not a hamid fit result \(missing key '{key}'\)$"
    with pytest.raises(DataError, match=message):
        validate_result(result, source="result.json")


@pytest.mark.parametrize("value", [[], "hamid.fit/1", None])
def test_validate_rejects_non_object(value):
    with pytest.raises(DataError, match=r"^out\.json: not a hamid fit result \(top level is"):
        validate_result(value, source="out.json")


@pytest.mark.parametrize("field", [*PARAMETER_FIELDS, "role"])
def test_validate_rejects_parameter_missing_field(result, field):
    del result["parameters"][2][field]
    message = rf"^r\.json: not a hamid fit result \(missing key 'parameters\[2\]\.{field}'\)$"
    with pytest.raises(DataError, match=message):
        validate_result(result, source="r.json")


@pytest.mark.parametrize(
    ("section", "key"),
    [("method", "level"), ("conditioning", "weakest_direction"), ("data", "velocity_source")],
)
def test_validate_rejects_missing_nested_key(result, section, key):
    del result[section][key]
    with pytest.raises(DataError, match=rf"\(missing key '{section}\.{key}'\)$"):
        validate_result(result, source="result.json")


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (("parameters", 0, "estimate"), "1.0", r"'parameters\[0\]\.estimate' is '1\.0'"),
        (("parameters", 1, "fixed"), 0, r"'parameters\[1\]\.fixed' is 0, expected true or"),
        (("parameters", 1, "stderr"), float("nan"), r"'parameters\[1\]\.stderr' is nan"),
        (("residuals", "drift", 1), [0.1], r"'residuals\.drift\[1\]' is a list, expected an"),
        (("method", "level"), None, r"'method\.level' is null, expected a number"),
        (("warnings",), [3], r"'warnings\[0\]' is 3, expected a string"),
    ],
)
def test_validate_rejects_wrong_type(result, path, value, message):
    target = result
    for step in path[:-1]:
        target = target[step]
    target[path[-1]] = value
    with pytest.raises(DataError, match=message):
        validate_result(result, source="result.json")
