"""Fuzzing the readers of untrusted documents: a system file (TOML, as parsed) and a saved
report (JSON). Whatever the document, the reader gives a result or hamid's own one-line
error, never another exception."""

from __future__ import annotations

import json
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from hamid.errors import HamidError
from hamid.result.fit_result import FitResult
from hamid.simulation import parse_system

GOLDEN = json.loads((Path(__file__).parents[1] / "golden" / "duffing_csv-auto.json").read_text())

# What TOML can hold: scalars of every kind (huge integers too), arrays and tables.
scalars = (st.booleans() | st.integers() | st.integers(min_value=10**300, max_value=10**400)
           | st.floats(allow_nan=True) | st.text(max_size=20))   # TOML has no null
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4)
                      | st.dictionaries(st.text(max_size=8), inner, max_size=4), max_leaves=12)
names = st.sampled_from(["model", "parameters", "initial", "simulate", "noise", "damping",
                         "builtin", "energy", "k", "k3", "x", "v", "t_end", "dt", "rtol",
                         "method", "relative", "c_x", "name", "coordinates", "velocities"])


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(names, values, max_size=6))
def test_any_system_document_gives_a_system_or_a_hamid_error(document):
    try:
        parse_system(document, where="sys.toml")
    except HamidError as exc:
        assert str(exc).startswith("sys.toml") and "\n" not in str(exc)


def _tamper(report: dict, path: list, value) -> dict:
    """The report with one value replaced: `path` picks keys (names, or positions among a
    table's keys) and list items down the report, as far as containers go."""
    report = json.loads(json.dumps(report))
    target = report
    for depth, step in enumerate(path):
        if isinstance(target, dict):
            key = step if isinstance(step, str) else list(target)[step % len(target)]
        else:
            key = step % len(target) if isinstance(step, int) else 0
        child = target[key] if isinstance(target, list) or key in target else None
        if depth == len(path) - 1 or not isinstance(child, dict | list) or not child:
            target[key] = value
            return report
        target = child
    return report


keys = st.sampled_from([*GOLDEN, *GOLDEN["method"], *GOLDEN["residuals"], "estimate",
                        "stderr", "h", "trajectory", "refinement", "applied"])
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner,
                                                                 max_size=3), max_leaves=8)


@settings(max_examples=300, deadline=None)
@given(st.lists(keys | st.integers(0, 5), min_size=1, max_size=4), json_values)
def test_any_tampered_report_reads_back_or_gives_a_hamid_error(path, value):
    report = _tamper(GOLDEN, path, value)
    try:
        result = FitResult.from_dict(report, source="r.json")
    except HamidError as exc:
        assert str(exc).startswith("r.json") and "\n" not in str(exc)
    else:
        assert FitResult.from_dict(result.to_dict(), source="r.json") == result
