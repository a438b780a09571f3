"""The fit's reports equal those recorded by `tests/golden/record.py`.

They cover every sample file under each method, chunked fits, and the other paths
(damping, noise, bias correction, derived velocities, bootstrap, fixed parameters). A
change of the code that does not mean to change outputs must leave every key and every
text as it was, and every number to rounding (`record.differences`: estimates and their
bounds to 1e-10, errors to 1e-6, other numbers to 1e-8). What varies by run is compared by type:
`provenance.utc` and the library versions; the inputs' sizes and SHA-256 exactly.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent
sys.path.insert(0, str(ROOT / "tests" / "golden"))
import record  # noqa: E402


@pytest.mark.parametrize("label", sorted(record.cases()))
def test_report_is_unchanged(label, monkeypatch):
    monkeypatch.chdir(ROOT)
    name, options = record.cases()[label]
    expected = json.loads((ROOT / "tests" / "golden" / f"{label}.json").read_text())
    assert record.differences(record.report(name, options), expected) == []


def test_every_recorded_report_has_a_case():
    recorded = {p.stem for p in (ROOT / "tests" / "golden").glob("*.json")}
    assert recorded == set(record.cases())


def _record(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The recorder run as documented, from elsewhere and without PYTHONPATH."""
    env = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
    return subprocess.run([sys.executable, str(ROOT / "tests" / "golden" / "record.py"), *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def test_the_recorder_gives_a_change_in_standard_errors_and_writes_only_when_accepted(
        tmp_path):
    label = "duffing_csv-energy"
    recorded = json.loads((ROOT / "tests" / "golden" / f"{label}.json").read_text())
    changed = json.loads(json.dumps(recorded))
    k = changed["parameters"][0]
    k["estimate"] += 3 * k["stderr"]
    changed["warnings"].append("a warning the fit no longer gives")
    path = tmp_path / f"{label}.json"
    path.write_text(json.dumps(changed))
    before = path.read_bytes()

    done = _record("--golden", str(tmp_path), label, cwd=tmp_path)
    assert done.returncode == 1, done.stderr
    assert f"hamid from {ROOT / 'hamid'}\n" in done.stdout
    assert ".parameters[0].estimate (k): -3 recorded standard errors" in done.stdout
    assert "warnings: removed 'a warning the fit no longer gives'" in done.stdout
    assert "1 of 1 reports differ" in done.stdout
    assert path.read_bytes() == before

    done = _record("--golden", str(tmp_path), "--accept", label, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert record.differences(json.loads(path.read_text()), recorded) == []
    done = _record("--golden", str(tmp_path), label, cwd=tmp_path)
    assert done.returncode == 0 and "0 of 1 reports differ" in done.stdout


def test_a_fit_that_fails_is_not_recorded(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(record, "cases", lambda: {"broken": ("no_such_file.csv", {})})
    assert record.main(["--golden", str(tmp_path), "--accept"]) == 1
    assert "broken: the fit fails: " in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
