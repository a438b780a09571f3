"""The report's `covariance` and `provenance` keys (issue 18): what they hold, that they
round-trip through JSON and the schema, and that reports without them still load."""

from __future__ import annotations

import hashlib
import io as stdio
import json
import math
import os
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

import hamid
from hamid.data import readers
from hamid.errors import DataError
from hamid.result.fit_result import FitResult

ROOT = Path(__file__).parents[2]
SAMPLES = ROOT / "sample_data"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _round_trip(result: FitResult) -> dict:
    return json.loads(json.dumps(result.to_dict(), allow_nan=False))


@pytest.fixture(scope="module")
def duffing() -> FitResult:
    return hamid.fit(str(SAMPLES / "duffing.csv"))


@pytest.mark.parametrize(("name", "options"), [
    ("duffing.csv", {}),
    ("henon_heiles.csv", {"fix": {"a": 1.0}}),
    ("henon_heiles.csv", {"method": "energy", "chunk_rows": 500}),
    ("pendulum_encoder.csv", {"damping": "viscous", "model": "pendulum.toml"}),
])
def test_covariance_diagonal_gives_the_stderr_and_is_symmetric(name, options):
    options = dict(options)
    model = options.pop("model", None)
    result = hamid.fit(str(SAMPLES / name), None if model is None else str(SAMPLES / model),
                       **options)
    report = _round_trip(result)
    free = [p for p in report["parameters"] if not p["fixed"]]
    assert report["covariance"]["names"] == [p["name"] for p in free]
    matrix = np.array(report["covariance"]["matrix"], dtype=float)
    assert matrix.shape == (len(free), len(free))
    assert np.array_equal(matrix, matrix.T)
    for i, parameter in enumerate(free):
        assert math.sqrt(matrix[i, i]) == pytest.approx(parameter["stderr"], rel=1e-12,
                                                        abs=0)


def test_fixed_parameters_have_no_covariance_row():
    result = hamid.fit(str(SAMPLES / "henon_heiles.csv"), fix={"a": 1.0})
    assert "a" not in result.covariance["names"]
    assert "a" in result.estimates


def test_covariance_and_provenance_round_trip(duffing):
    report = _round_trip(duffing)
    back = FitResult.from_dict(report, source="r.json")
    assert back == duffing
    assert back.covariance == duffing.covariance
    assert back.provenance == duffing.provenance
    assert back.to_dict() == report


def test_a_report_without_the_new_keys_still_loads(duffing):
    report = _round_trip(duffing)
    del report["covariance"], report["provenance"]
    old = FitResult.from_dict(report, source="old.json")
    assert old.covariance is None and old.provenance is None
    assert old.estimates == duffing.estimates
    assert "covariance" not in old.to_dict() and "provenance" not in old.to_dict()


def test_the_new_keys_may_be_null(duffing):
    report = _round_trip(duffing)
    report["covariance"] = report["provenance"] = None
    assert FitResult.from_dict(report).covariance is None


@pytest.mark.parametrize(("change", "message"), [
    (lambda r: r["covariance"]["matrix"].pop(), "key 'covariance.matrix' has 1 rows, "
                                                "expected 2"),
    (lambda r: r["covariance"]["matrix"][0].append(0.0),
     "key 'covariance.matrix[0]' has 3 entries, expected 2"),
    (lambda r: r["covariance"].pop("names"), "missing key 'covariance.names'"),
    (lambda r: r["provenance"]["inputs"][0].update(sha256="xyz"),
     "provenance.inputs[0].sha256"),
    (lambda r: r["provenance"]["inputs"][0].update(size=-1), "provenance.inputs[0].size"),
    (lambda r: r["provenance"].pop("utc"), "missing key 'provenance.utc'"),
    (lambda r: r["provenance"].update(seed="1"), "provenance.seed"),
])
def test_malformed_new_keys_are_refused(duffing, change, message):
    report = _round_trip(duffing)
    change(report)
    with pytest.raises(DataError, match="^r.json: not a hamid fit result") as caught:
        FitResult.from_dict(report, source="r.json")
    assert message in str(caught.value)


def test_provenance_of_a_file(duffing):
    path = SAMPLES / "duffing.csv"
    provenance = duffing.provenance
    assert provenance["inputs"] == [{"path": str(path), "size": path.stat().st_size,
                                     "sha256": _sha256(path)}]
    assert provenance["seed"] is None and provenance["command"] is None
    versions = provenance["versions"]
    assert list(versions) == ["hamid", "numpy", "scipy", "pyarrow"]
    assert versions["hamid"] == hamid.__version__ == duffing.hamid_version
    assert versions["numpy"] == np.__version__
    import pyarrow
    import scipy

    assert versions["scipy"] == scipy.__version__
    assert versions["pyarrow"] == pyarrow.__version__


def test_provenance_time_is_utc_iso8601_now(duffing):
    when = datetime.fromisoformat(duffing.provenance["utc"])
    assert when.utcoffset() == timedelta(0)
    assert duffing.provenance["utc"].endswith("Z")
    assert abs(datetime.now(UTC) - when) < timedelta(minutes=10)


def test_provenance_of_several_files_in_order():
    paths = [SAMPLES / "peng_quadratic.csv", SAMPLES / "peng_quadratic.parquet"]
    result = hamid.fit([str(p) for p in paths], method="energy")
    assert [(i["path"], i["size"], i["sha256"]) for i in result.provenance["inputs"]] == \
        [(str(p), p.stat().st_size, _sha256(p)) for p in paths]


def test_a_file_read_in_chunks_has_the_same_digest_as_read_whole():
    path = str(SAMPLES / "henon_heiles.csv")
    whole = hamid.fit(path, method="energy")
    chunked = hamid.fit(path, method="energy", chunk_rows=500)
    assert chunked.provenance["inputs"] == whole.provenance["inputs"]


def test_provenance_of_a_dataframe():
    import pandas as pd

    frame = pd.read_csv(SAMPLES / "duffing.csv", comment="#")
    result = hamid.fit(frame, "duffing")
    assert result.provenance["inputs"] == [{"path": "<DataFrame>", "size": None,
                                            "sha256": None}]


def test_provenance_of_standard_input(monkeypatch):
    data = (SAMPLES / "duffing.csv").read_bytes()
    monkeypatch.setattr(sys, "stdin", stdio.TextIOWrapper(stdio.BytesIO(data)))
    result = hamid.fit("-", "duffing")
    assert result.provenance["inputs"] == [{"path": "<stdin>", "size": None,
                                            "sha256": None}]


def test_the_seed_is_the_bootstraps():
    path = str(SAMPLES / "duffing.csv")
    result = hamid.fit(path, cov="bootstrap", seed=7, bootstrap=20)
    assert result.provenance["seed"] == 7
    assert hamid.fit(path, cov="bootstrap", bootstrap=20).provenance["seed"] is None


def test_with_command_sets_the_command_line(duffing):
    command = "hamid fit 'sample_data/duffing.csv' --format json"
    result = duffing.with_command(command)
    assert result.provenance["command"] == command
    assert duffing.provenance["command"] is None
    assert FitResult.from_dict(_round_trip(result)).provenance["command"] == command
    no_provenance = FitResult.from_dict({k: v for k, v in _round_trip(duffing).items()
                                         if k != "provenance"})
    assert no_provenance.with_command(command).provenance is None


@pytest.mark.parametrize("size", [0, 1, 2**20 - 1, 2**20, 2**20 + 1, 5 * 2**20 // 2])
def test_file_digest_streams_in_blocks(tmp_path, size):
    path = tmp_path / "data.bin"
    path.write_bytes(os.urandom(size))
    assert readers.file_digest(path) == (size, _sha256(path))
    assert readers.file_digest(str(path)) == (size, _sha256(path))


def test_file_digest_names_a_missing_file(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        readers.file_digest(tmp_path / "missing.csv")


def test_a_fifo_as_input_is_read_once_and_not_hashed(tmp_path):
    """Hashing a FIFO would use up its data before the fit reads it (and /dev/zero would
    never end): only regular files get a size and digest."""
    import os
    import threading
    from pathlib import Path

    import hamid

    data = (Path(__file__).parents[2] / "sample_data" / "duffing.csv").read_bytes()
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_bytes(data))
    writer.start()
    result = hamid.fit(str(fifo), method="energy")
    writer.join()
    assert result.provenance["inputs"] == [{"path": str(fifo), "size": None, "sha256": None}]
    assert result.data["n_samples"] == 1202
