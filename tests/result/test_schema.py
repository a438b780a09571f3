"""The JSON Schema of the fit report (hamid/schema/fit-1.json) and the check built on it.

Every recorded report (tests/golden/, one of each kind of fit) follows the schema, and every
key in them is described by it; a tampered report gives `hamid report` one line naming the
key, exit 1, nothing on standard output.
"""

from __future__ import annotations

import copy
import json
import subprocess
from pathlib import Path

import jsonschema
import pytest
from helpers import hamid_command

from hamid.errors import DataError
from hamid.result import validation
from hamid.result.fit_result import FitResult

GOLDEN = sorted((Path(__file__).parents[1] / "golden").glob("*.json"))
HAMID = hamid_command()


def _load(name: str) -> dict:
    return json.loads((Path(__file__).parents[1] / "golden" / name).read_text())


@pytest.fixture(scope="module")
def schema():
    return validation.load_schema()


def test_schema_is_valid_draft_2020_12(schema):
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)


def test_the_metaschema_check_can_fail(schema):
    broken = copy.deepcopy(schema)
    broken["$defs"]["count"]["minimum"] = "zero"
    with pytest.raises(jsonschema.SchemaError):
        jsonschema.Draft202012Validator.check_schema(broken)


def test_golden_reports_cover_every_kind_of_fit():
    reports = [json.loads(path.read_text()) for path in GOLDEN]
    methods = [r["method"] for r in reports]
    assert {m["kind"] for m in methods} == {"energy", "weak", "joint"}
    assert {m["covariance"] for m in methods} == {"classical", "hc", "hac", "bootstrap"}
    assert {m["refinement"]["applied"] for m in methods if m["refinement"]} == {True, False}
    assert any(r["dissipation"] for r in reports)
    assert any(m["noise"] for m in methods)


@pytest.mark.parametrize("path", GOLDEN, ids=lambda p: p.stem)
def test_golden_report_follows_the_schema(path, schema):
    report = json.loads(path.read_text())
    jsonschema.Draft202012Validator(schema).validate(report)   # the file alone, portable
    validation.check_result(report, source=path.name)         # hamid's check


def _undescribed(value, sub, schema, path=""):
    """Keys of `value` that the schema does not describe (a property, or a map's values)."""
    while "$ref" in sub:
        sub = {**schema["$defs"][sub["$ref"].rsplit("/", 1)[1]],
               **{k: v for k, v in sub.items() if k != "$ref"}}
    found = []
    if isinstance(value, dict):
        for key, item in value.items():
            if key in sub.get("properties", {}):
                found += _undescribed(item, sub["properties"][key], schema, f"{path}.{key}")
            elif isinstance(sub.get("additionalProperties"), dict):
                found += _undescribed(item, sub["additionalProperties"], schema, f"{path}.*")
            else:
                found.append(f"{path}.{key}")
    elif isinstance(value, list) and "items" in sub:
        for item in value:
            found += _undescribed(item, sub["items"], schema, f"{path}[]")
    return found


@pytest.mark.parametrize("path", GOLDEN, ids=lambda p: p.stem)
def test_schema_describes_every_key_of_a_golden_report(path, schema):
    assert sorted(set(_undescribed(json.loads(path.read_text()), schema, schema))) == []


def test_an_undescribed_key_is_found(schema):
    report = _load("duffing_csv-auto.json")
    report["method"]["new_key"] = 1
    report["parameters"][0]["note"] = "x"
    assert _undescribed(report, schema, schema) == [".method.new_key", ".parameters[].note"]


@pytest.mark.parametrize("path", GOLDEN, ids=lambda p: p.stem)
def test_round_trip(path):
    report = json.loads(path.read_text())
    result = FitResult.from_dict(report, source=path.name)
    assert result.to_dict() == report
    assert list(result.to_dict()) == list(report)
    assert FitResult.from_dict(json.loads(json.dumps(result.to_dict()))) == result


def _set(report: dict, dotted: str, value) -> None:
    *parents, last = dotted.split(".")
    target = report
    for key in parents:
        target = target[key]
    target[last] = value


HUGE = "1" + "0" * 400   # 10**400 written out: Python reads an int that float() overflows

# (name, report file, key path, value or None for raw text, words the message must hold)
TAMPERED = [
    ("huge estimate", "henon_heiles_csv-auto.json", "parameters[0].estimate",
     ["'parameters[0].estimate'", "401 digits", "range of a double"]),
    ("huge count", "henon_heiles_csv-auto.json", "data.n_samples",
     ["'data.n_samples'", "401 digits", "whole number"]),
    ("refinement a string", "henon_heiles_csv-auto.json", "method.refinement",
     ["'method.refinement'", "'yes'", "an object or null"]),
    ("refinement empty", "henon_heiles_csv-auto.json", "method.refinement",
     ["missing key 'method.refinement.applied'"]),
    ("dissipation a string", "pendulum_encoder_csv-damped.json", "dissipation",
     ["'dissipation'", "'lots'", "an object or null"]),
    ("dissipation a list", "pendulum_encoder_csv-damped.json", "dissipation",
     ["'dissipation'", "a list", "an object or null"]),
    ("level 5", "duffing_csv-energy.json", "method.level",
     ["'method.level' is 5", "strictly between 0 and 1"]),
    ("level 1", "duffing_csv-energy.json", "method.level",
     ["'method.level' is 1", "strictly between 0 and 1"]),
    ("nested 900 deep", "duffing_csv-energy.json", "method.extra",
     ["'method.extra[0]...'", "nested more than 64 levels"]),
]
VALUES = {
    "refinement a string": "yes",
    "refinement empty": {},
    "dissipation a string": "lots",
    "dissipation a list": [1, 2],
    "level 5": 5,
    "level 1": 1,
}
MARK = "__tampered__"


def _tampered_text(name: str, golden: str, key: str) -> str:
    report = _load(golden)
    if name.startswith("huge"):
        if key.startswith("parameters"):
            report["parameters"][0]["estimate"] = MARK
        else:
            _set(report, key, MARK)
        return json.dumps(report).replace(f'"{MARK}"', HUGE)
    if name.startswith("nested"):
        _set(report, key, MARK)
        return json.dumps(report).replace(f'"{MARK}"', "[" * 900 + "]" * 900)
    _set(report, key, VALUES[name])
    return json.dumps(report)


@pytest.mark.parametrize(("name", "golden", "key", "words"), TAMPERED,
                         ids=[case[0] for case in TAMPERED])
def test_hamid_report_on_a_tampered_report(tmp_path, name, golden, key, words):
    path = tmp_path / "r.json"
    line = _report_error(path, _tampered_text(name, golden, key))
    assert line.startswith(f"Error: {path}: not a hamid fit result (")
    for word in words:
        assert word in line
    assert "internal error" not in line


def _report_error(path: Path, text: str) -> str:
    """The one line `hamid report` says of a file holding `text` (exit 1, no output)."""
    path.write_text(text)
    done = subprocess.run([*HAMID, "report", str(path)], capture_output=True, text=True,
                          cwd=path.parent, timeout=600)
    assert done.returncode == 1, done.stderr
    assert done.stdout == ""
    lines = done.stderr.splitlines()
    assert len(lines) == 1, done.stderr
    return lines[0]


@pytest.mark.parametrize(("name", "golden", "key", "words"), TAMPERED,
                         ids=[case[0] for case in TAMPERED])
def test_the_untampered_report_is_accepted(tmp_path, name, golden, key, words):
    """The tampering, not the file it starts from, is what the test above refuses."""
    path = tmp_path / "r.json"
    path.write_text(json.dumps(_load(golden)))
    done = subprocess.run([*HAMID, "report", str(path), "--format", "json"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == _load(golden)


@pytest.mark.parametrize(("name", "golden", "key", "words"),
                         [case for case in TAMPERED if not case[0].startswith("nested")],
                         ids=[case[0] for case in TAMPERED if not case[0].startswith("nested")])
def test_the_schema_file_alone_refuses_the_tampering(schema, name, golden, key, words):
    """Any JSON Schema validator, not only hamid's, refuses these reports."""
    report = json.loads(_tampered_text(name, golden, key))
    assert not jsonschema.Draft202012Validator(schema).is_valid(report)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_numbers_are_refused(value):
    """Python's json reads NaN and Infinity, which are not JSON: hamid's check refuses them."""
    report = _load("duffing_csv-energy.json")
    report["energy_levels"][0]["h"] = value
    with pytest.raises(DataError, match=rf"^r\.json: not a hamid fit result \(key "
                                        rf"'energy_levels\[0\]\.h' is {value!r}, expected a "
                                        r"number\)$"):
        FitResult.from_dict(report, source="r.json")


@pytest.mark.parametrize(("edit", "message"), [
    (lambda r: r["method"]["refinement"].pop("segments"),
     "missing key 'method.refinement.segments'"),
    (lambda r: r["method"]["refinement"].update(applied=False),
     "missing key 'method.refinement.reason'"),
    (lambda r: r["method"].update(kind="magic"),
     "key 'method.kind' is 'magic', expected one of 'energy', 'weak', 'joint'"),
    (lambda r: r["method"].update(weighting="noise", noise={"a b\x1b]0;x": "s"}),
     "key 'method.noise[\"a b\\u001b]0;x\"]' is 's', expected a number"),
    (lambda r: r["parameters"][1].update(stderr=-1.0),
     "key 'parameters[1].stderr' is -1.0, expected a number ≥ 0"),
], ids=["applied without segments", "not applied without reason", "unknown kind",
        "noise key with control characters",
        "negative stderr"])
def test_messages(edit, message):
    report = _load("duffing_csv-auto.json")
    edit(report)
    with pytest.raises(DataError) as caught:
        FitResult.from_dict(report, source="r.json")
    assert str(caught.value) == f"r.json: not a hamid fit result ({message})"


@pytest.mark.parametrize(("text", "words"), [
    ('{"schema": ' + "[" * 100_000 + "]" * 100_000 + "}", "nested too deeply"),
    ('{"schema": ' + "9" * 5001 + "}", "a number has more than"),
], ids=["nested 100000 deep", "integer of 5001 digits"])
def test_unreadable_json_is_one_line(tmp_path, text, words):
    """Python's JSON reader gives up on these before any schema sees them."""
    path = tmp_path / "r.json"
    assert _report_error(path, text).startswith(f"Error: {path}: not readable JSON: {words}")
