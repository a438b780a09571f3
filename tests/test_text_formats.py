"""Text tables as data-acquisition systems write them: compressed (gzip, bzip2, Zstandard),
`;`-separated with decimal commas, and with a units row under the header (issue 18)."""

import bz2
import gzip
import shutil

import numpy as np
import pyarrow as pa
import pytest

import hamid
from hamid import io as hio
from hamid.errors import DataError

SAMPLE = "sample_data/duffing.csv"
with open(SAMPLE, "rb") as _file:
    SAMPLE_BYTES = _file.read()


def _pyarrow_compress(data: bytes, codec: str) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.CompressedOutputStream(sink, codec) as stream:
        stream.write(data)
    return sink.getvalue().to_pybytes()


# Independent writers for each codec: Python's own gzip and bz2 modules, and pyarrow for
# Zstandard (a frame the `zstd` tool reads too).
COMPRESSORS = {".gz": gzip.compress, ".bz2": bz2.compress,
               ".zst": lambda data: _pyarrow_compress(data, "zstd")}


@pytest.fixture(scope="module")
def plain():
    return hamid.fit(SAMPLE).estimates


@pytest.mark.parametrize("suffix", list(COMPRESSORS))
@pytest.mark.parametrize("text", [".csv", ".tsv"])
def test_compressed_file_fits_as_the_plain_one(tmp_path, plain, suffix, text):
    data = SAMPLE_BYTES
    if text == ".tsv":
        data = b"\n".join(line if line.startswith(b"#") else line.replace(b",", b"\t")
                          for line in data.split(b"\n"))
    path = tmp_path / f"duffing{text}{suffix}"
    path.write_bytes(COMPRESSORS[suffix](data))
    assert path.read_bytes()[:2] != data[:2]   # really compressed
    got = hamid.fit(str(path)).estimates
    assert got.keys() == plain.keys()
    for name, value in plain.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("suffix", list(COMPRESSORS))
def test_compressed_file_read_in_chunks(tmp_path, plain, suffix):
    """Chunked reading decompresses as it reads: chunks of 100 rows give the whole fit."""
    path = tmp_path / f"duffing.csv{suffix}"
    path.write_bytes(COMPRESSORS[suffix](SAMPLE_BYTES))
    table = hio.TableChunks(path)
    assert table.compression == {".gz": "gzip", ".bz2": "bz2", ".zst": "zstd"}[suffix]
    assert table.columns == ["trajectory", "t", "x", "v"]
    assert table.metadata["model"]["name"] == "duffing"
    x = np.concatenate([chunk["x"] for chunk in table.chunks(["x"], 100)])
    whole, _ = hio.read_columns(SAMPLE)
    assert np.array_equal(x, whole["x"])
    got = hamid.fit(str(path), chunk_rows=100).estimates
    streamed = hamid.fit(SAMPLE, chunk_rows=100).estimates
    for name, value in streamed.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)
    assert got.keys() == plain.keys()


def test_compression_is_told_by_content_not_name(tmp_path):
    path = tmp_path / "run.csv"
    path.write_bytes(gzip.compress(b"t,x\n0,1\n0.5,2\n"))
    columns, _ = hio.read_columns(path)
    assert list(columns) == ["t", "x"] and list(columns["x"]) == [1, 2]


def test_compressed_name_gives_the_format(tmp_path):
    assert hio.input_format("a.tsv.gz") == "tsv"
    assert hio.input_format("a.CSV.BZ2") == "csv"
    assert hio.input_format("a.gz") is None
    path = tmp_path / "run.tsv.zst"
    path.write_bytes(_pyarrow_compress(b"t\tx\n0\t1\n", "zstd"))
    assert list(hio.read_columns(path)[0]) == ["t", "x"]


@pytest.mark.parametrize("suffix", list(COMPRESSORS))
def test_damaged_compressed_file_is_one_line(tmp_path, suffix):
    good = COMPRESSORS[suffix](SAMPLE_BYTES)
    path = tmp_path / f"run.csv{suffix}"
    path.write_bytes(good[:len(good) // 2] + b"\x00" * 64)
    codec = {".gz": "gzip", ".bz2": "bz2", ".zst": "zstd"}[suffix]
    with pytest.raises(DataError, match=rf"^{path}: is not valid {codec} data \(.+\)$"):
        hio.read_columns(path)
    with pytest.raises(DataError, match=rf"^{path}: "):
        table = hio.TableChunks(path)
        for _ in table.chunks(["x"], 50):
            pass


def test_empty_compressed_file(tmp_path):
    path = tmp_path / "run.csv.gz"
    path.write_bytes(gzip.compress(b""))
    with pytest.raises(DataError, match=rf"^{path}: file is empty once decompressed$"):
        hio.read_columns(path)


def test_compressed_copy_keeps_metadata(tmp_path):
    path = tmp_path / "run.csv.gz"
    with open(SAMPLE, "rb") as source, gzip.open(path, "wb") as sink:
        shutil.copyfileobj(source, sink)
    assert hio.read_columns(path)[1] == hio.read_columns(SAMPLE)[1]
