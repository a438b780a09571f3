"""The fit's reports equal those recorded before its modules were rearranged.

`tests/golden/record.py` wrote them at main 8efcef8: every sample file under each method,
chunked fits, and the other paths (damping, noise, bias correction, derived velocities,
bootstrap, fixed parameters). A rearrangement of the code must leave every key and every
text as it was, and every number to rounding.

The keys `covariance` and `provenance` were added to the recorded files later (patched in,
the other keys untouched). What varies by run is compared by type: `provenance.utc` (an
ISO 8601 time) and the library versions, like `hamid_version`; the inputs' sizes and
SHA-256 of the sample files are compared exactly.
"""

from __future__ import annotations

import json
import math
import sys
from datetime import datetime
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent
sys.path.insert(0, str(ROOT / "tests" / "golden"))
import record  # noqa: E402

# Estimates and their errors to 1e-10; other numbers (summaries of residuals that are
# rounding noise on exact data) to 1e-8 of their own size.
PRECISE = ("estimate", "stderr", "ci_low", "ci_high", "h")


def _compare(found, expected, path: str) -> None:
    if path == ".provenance.utc":
        assert isinstance(found, str) and datetime.fromisoformat(found).utcoffset() is not None
    elif path.startswith(".provenance.versions."):
        assert found is None or isinstance(found, str), path
    elif path == ".covariance.matrix":
        _compare_covariance(found, expected, path)
    elif isinstance(expected, dict):
        assert isinstance(found, dict), path
        assert list(found) == list(expected), f"{path}: keys differ"
        for key in expected:
            _compare(found[key], expected[key], f"{path}.{key}")
    elif isinstance(expected, list):
        assert isinstance(found, list) and len(found) == len(expected), path
        for k, (f, e) in enumerate(zip(found, expected, strict=True)):
            _compare(f, e, f"{path}[{k}]")
    elif isinstance(expected, float) and not isinstance(found, bool):
        rtol = 1e-10 if path.rsplit(".", 1)[-1] in PRECISE else 1e-8
        assert found == pytest.approx(expected, rel=rtol, abs=1e-300), path
    elif path != ".hamid_version":
        assert found == expected, path


def _compare_covariance(found, expected, path: str) -> None:
    """Each entry to 1e-8 of the geometric mean of its two variances: off-diagonal entries
    near zero are rounding noise on exact data, on the scale of the variances."""
    n = len(expected)
    assert len(found) == n and all(len(row) == n for row in found), path
    for i in range(n):
        for j in range(n):
            f, e = found[i][j], expected[i][j]
            if e is None or expected[i][i] is None or expected[j][j] is None:
                assert f == e, f"{path}[{i}][{j}]"
                continue
            scale = math.sqrt(abs(expected[i][i] * expected[j][j]))
            assert abs(f - e) <= 1e-8 * scale + 1e-300, f"{path}[{i}][{j}]"


@pytest.mark.parametrize("label", sorted(record.cases()))
def test_report_is_unchanged(label, monkeypatch):
    monkeypatch.chdir(ROOT)
    name, options = record.cases()[label]
    expected = json.loads((ROOT / "tests" / "golden" / f"{label}.json").read_text())
    _compare(record.report(name, options), expected, "")


def test_every_recorded_report_has_a_case():
    recorded = {p.stem for p in (ROOT / "tests" / "golden").glob("*.json")}
    assert recorded == set(record.cases())
