"""What decides a chunked read (the decoded size, hamid.data.input_size) and standard input read in
chunks like a file."""

from __future__ import annotations

import bz2
import gzip
import json
import os
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from conftest import with_noise

import hamid
from hamid import options
from hamid.cli.app import cli
from hamid.data import input_size, loading, writing
from hamid.errors import DataError
from hamid.linear import plan


@pytest.fixture(autouse=True)
def linear_fits_in_memory(monkeypatch):
    """The fits here stop before the trajectory refinement, which is not what is tested
    and costs seconds; a chunked fit and one in memory then stop at the same place."""
    obstacle = plan.refinement_obstacle
    monkeypatch.setattr(plan, "refinement_obstacle", lambda options, size=None: obstacle(
        options, size) or plan.CHUNKED_NOT_REFINED)


@pytest.fixture(scope="module")
def noisy(clean_records):
    return with_noise(clean_records["peng-quadratic"], 0.01, seed=7)


@pytest.fixture(scope="module")
def repetitive(noisy, tmp_path_factory):
    """One trajectory recorded 40 times over: a Parquet file of a fifth of its decoded size
    (dictionary pages), like the 3-million-row file of issue 22."""
    one = noisy[noisy["trajectory"] == noisy["trajectory"].iloc[0]]
    table = pa.Table.from_pandas(one, preserve_index=False)
    copies = [table.set_column(0, "trajectory", pa.array(np.full(len(one), k)))
              for k in range(1, 41)]
    whole = pa.concat_tables(copies).replace_schema_metadata(
        {b"hamid": json.dumps(noisy.attrs["hamid"]).encode()})
    path = str(tmp_path_factory.mktemp("inputs") / "repetitive.parquet")
    pq.write_table(whole, path)
    return path, whole.num_rows, whole.num_columns


def test_parquet_decoded_size_is_rows_times_columns_times_8(repetitive):
    path, rows, columns = repetitive
    assert input_size.decoded_bytes(path) == rows * columns * 8
    assert input_size.decoded_bytes(path) > 3 * os.path.getsize(path)   # compresses well


def _text_file(frame, path):
    frame.to_csv(path, index=False, float_format="%.17g")
    return len(frame) * frame.shape[1] * 8


def test_text_decoded_size_is_exact_for_a_short_file_and_close_for_a_long_one(
        noisy, tmp_path):
    short = str(tmp_path / "short.csv")
    truth = _text_file(noisy, short)   # read whole as a sample: counted, not estimated
    assert input_size.decoded_bytes(short) == truth
    long_frame = noisy.loc[np.tile(noisy.index, 12)].reset_index(drop=True)
    path = str(tmp_path / "long.csv")
    truth = _text_file(long_frame, path)
    assert os.path.getsize(path) > input_size.SAMPLE_BYTES   # the estimate is from a sample
    assert input_size.decoded_bytes(path) == pytest.approx(truth, rel=0.05)
    with open(path, "rb") as text:
        data = text.read()
    for suffix, module in ((".gz", gzip), (".bz2", bz2)):
        packed = path + suffix
        with open(packed, "wb") as out:
            out.write(module.compress(data))
        assert input_size.decoded_bytes(packed) == pytest.approx(truth, rel=0.15), suffix


def test_a_file_that_cannot_be_made_sense_of_gives_its_size_on_disk(tmp_path):
    broken = tmp_path / "broken.parquet"
    broken.write_bytes(b"PAR1 and then nothing of a Parquet file")
    assert input_size.decoded_bytes(broken) == os.path.getsize(broken)
    comments = tmp_path / "comments.csv"
    comments.write_text("# only a comment\n")
    assert input_size.decoded_bytes(comments) == os.path.getsize(comments)


def test_chunks_are_decided_by_the_decoded_size_not_the_size_on_disk(repetitive,
                                                                     monkeypatch):
    path, rows, columns = repetitive
    opened = []
    real = loading.open_chunks
    monkeypatch.setattr(loading, "open_chunks", lambda *a, **k: opened.append(a) or real(*a, **k))
    # the file is smaller than the limit on disk, larger once decoded: chunks
    monkeypatch.setattr(options, "STREAM_BYTES", rows * columns * 8 - 1)
    assert os.path.getsize(path) < options.STREAM_BYTES
    chunked = hamid.fit(path, method="energy")
    assert len(opened) == 1 and chunked.samples is None
    monkeypatch.setattr(options, "STREAM_BYTES", rows * columns * 8)   # not over it
    whole = hamid.fit(path, method="energy")
    assert len(opened) == 1 and whole.samples is not None
    assert chunked.estimates == pytest.approx(whole.estimates, rel=1e-10)


def _report(done):
    assert done.exit_code == 0, (done.stdout, done.stderr)
    return json.loads(done.stdout)


@pytest.mark.parametrize("suffix", ["csv", "parquet"])
def test_standard_input_is_read_in_chunks_like_the_file(noisy, tmp_path, monkeypatch, suffix):
    path = str(tmp_path / f"peng.{suffix}")
    writing.write_table(noisy, path, metadata=noisy.attrs["hamid"])
    with open(path, "rb") as data:
        content = data.read()
    opened = []
    real = loading.open_chunks
    monkeypatch.setattr(loading, "open_chunks",
                        lambda *a, **k: opened.append(input_size.name_of(a[0])) or real(*a, **k))
    monkeypatch.setattr(options, "STREAM_BYTES", 1000)   # both over it
    runner = CliRunner()
    args = ["fit", "--format", "json", "--method", "joint"]
    from_file = _report(runner.invoke(cli, [*args, path]))
    from_stdin = _report(runner.invoke(cli, [*args, "-"], input=content))
    assert opened == [path, "<stdin>"]
    for key in ("parameters", "energy_levels"):
        for f, s in zip(from_file[key], from_stdin[key], strict=True):
            assert s["estimate" if key == "parameters" else "h"] == pytest.approx(
                f["estimate" if key == "parameters" else "h"], rel=1e-12, abs=1e-300)
            assert s["stderr"] == pytest.approx(f["stderr"], rel=1e-12)
    assert from_stdin["data"]["sources"] == ["<stdin>"]
    assert from_stdin["provenance"]["inputs"] == [{"path": "<stdin>", "size": None,
                                                   "sha256": None}]
    with_rows = _report(runner.invoke(cli, [*args, "-", "--chunk-rows", "100"],
                                      input=content))   # asked for: no longer refused
    assert [p["estimate"] for p in with_rows["parameters"]] == pytest.approx(
        [p["estimate"] for p in from_file["parameters"]], rel=1e-10)


def test_standard_input_in_chunks_is_named_in_errors_and_leaves_no_file(
        noisy, tmp_path, monkeypatch):
    import tempfile

    text = noisy.to_csv(index=False)
    lines = text.splitlines()
    cells = lines[500].split(",")
    lines[500] = ",".join([*cells[:2], "n/a", *cells[3:]])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    done = CliRunner().invoke(cli, ["fit", "-", "--model", "peng-quadratic", "--chunk-rows",
                                    "128"], input="\n".join(lines) + "\n")
    assert done.exit_code == 1 and done.stdout == ""
    assert done.stderr.startswith("Error: <stdin>: column 'u1', row 500: 'n/a' is not a "
                                  "number"), done.stderr
    assert list(tmp_path.iterdir()) == []   # the spooled copy is gone


def test_standard_input_that_cannot_be_kept_is_an_error_naming_the_folder(tmp_path,
                                                                         monkeypatch):
    import tempfile

    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    monkeypatch.setattr(tempfile, "tempdir", str(not_a_folder))
    done = CliRunner().invoke(cli, ["fit", "-", "--model", "duffing"], input="x,v\n1,2\n")
    assert done.exit_code == 1 and done.stdout == ""
    assert done.stderr.startswith(f"Error: <stdin>: cannot keep it in a temporary file in "
                                  f"{not_a_folder} ("), done.stderr
    assert "set TMPDIR" in done.stderr and "Traceback" not in done.stderr


def test_standard_input_closed_is_an_error(monkeypatch):
    monkeypatch.setattr(sys, "stdin", None)
    with pytest.raises(DataError, match="<stdin>: cannot read: standard input is closed"):
        hamid.fit("-", model="duffing")


def test_spooled_keeps_other_data_as_they_are():
    frame = {"x": np.zeros(3)}
    with input_size.spooled(frame) as same:
        assert same is frame
    with input_size.spooled(["a.csv", "b.csv"]) as paths:
        assert paths == ["a.csv", "b.csv"]
