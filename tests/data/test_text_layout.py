"""Text tables as data-acquisition systems write them: compressed (gzip, bzip2, Zstandard),
`;`-separated with decimal commas, and with a units row under the header (issue 18)."""

import bz2
import gzip
import json
import re
import shutil
import subprocess

import numpy as np
import pyarrow as pa
import pytest
from helpers import hamid_command, one_line_error

import hamid
from hamid.data import readers as hio
from hamid.data.text_layout import TextOptions, preamble_lines
from hamid.errors import DataError, UsageError

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


# --- ;-separated text with decimal commas, and a units row (detected or given) -----------


def _european(data: bytes, units: bytes | None = None, sep: bytes = b";") -> bytes:
    """The sample as a spreadsheet in a comma-decimal locale writes it."""
    lines = data.split(b"\n")
    out = []
    for number, line in enumerate(lines):
        if line.startswith(b"#"):
            out.append(line)
            continue
        out.append(line.replace(b",", sep).replace(b".", b","))
        if units is not None and number == 1:   # the header is line 1 (after metadata)
            out.append(units)
    return b"\n".join(out)


def test_semicolon_and_decimal_comma_are_detected(tmp_path, plain):
    path = tmp_path / "daq.csv"
    path.write_bytes(_european(SAMPLE_BYTES))
    assert b"0,05" in path.read_bytes()
    columns, metadata = hio.read_columns(path)
    whole, _ = hio.read_columns(SAMPLE)
    assert list(columns) == list(whole) and "units" not in metadata
    for name in whole:
        assert np.array_equal(columns[name], whole[name])
    got = hamid.fit(str(path)).estimates
    for name, value in plain.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_tab_with_decimal_comma(tmp_path):
    path = tmp_path / "daq.tsv"
    path.write_bytes(b"t\tx\n0\t1,5\n0,5\t-2,25e-1\n")
    columns, _ = hio.read_columns(path)
    assert list(columns["x"]) == [1.5, -0.225] and list(columns["t"]) == [0.0, 0.5]


def test_units_row_is_detected_and_recorded(tmp_path, plain):
    path = tmp_path / "daq.csv"
    path.write_bytes(_european(SAMPLE_BYTES, units=b"; s ;m;m/s"))
    columns, metadata = hio.read_columns(path)
    assert metadata["units"] == {"t": "s", "x": "m", "v": "m/s"}   # empty cell left out
    assert metadata["model"]["name"] == "duffing"                   # the file's own kept
    whole, _ = hio.read_columns(SAMPLE)
    assert np.array_equal(columns["x"], whole["x"])
    assert hio.read_table(path)[1]["units"] == metadata["units"]
    got = hamid.fit(str(path)).estimates
    for name, value in plain.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_units_row_in_a_comma_file_read_in_chunks(tmp_path):
    """The units row of the issue (`s,mm,mm,mm/s,mm/s`), read whole and in chunks."""
    rows = "\n".join(f"{k * 0.001:.3f},{k},{-k},{2 * k},{-2 * k}" for k in range(300))
    path = tmp_path / "daq.csv"
    path.write_text(f"time_ms,x1_mm,x2_mm,v1,v2\ns,mm,mm,mm/s,mm/s\n{rows}\n")
    columns, metadata = hio.read_columns(path)
    assert metadata == {"units": {"time_ms": "s", "x1_mm": "mm", "x2_mm": "mm",
                                  "v1": "mm/s", "v2": "mm/s"}}
    assert len(columns["x1_mm"]) == 300 and columns["x1_mm"][0] == 0
    table = hio.TableChunks(path)
    assert table.metadata == metadata
    x = np.concatenate([chunk["x1_mm"] for chunk in table.chunks(["x1_mm"], 64)])
    assert np.array_equal(x, np.arange(300))


def test_no_units_row_when_the_first_row_has_numbers_or_is_missing(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("t,x,label\n0,1,a\n1,2,b\n")
    columns, metadata = hio.read_columns(path)
    assert metadata is None and list(columns["x"]) == [1, 2]
    path.write_text("t,x\n,\n1,2\n")   # a row of missing cells is data, not units
    assert hio.read_columns(path)[1] is None


def test_text_options_given(tmp_path):
    path = tmp_path / "logger.txt"
    path.write_bytes(b"Logger 7 preamble\nstarted 2026-11-24\nt|x\nsec|mm\n0|1,5\n1|2,5\n")
    options = TextOptions(delimiter="|", decimal=",", skip_rows=2, units_row=True)
    columns, metadata = hio.read_columns(path, format="csv", text=options)
    assert list(columns["x"]) == [1.5, 2.5] and metadata == {"units": {"t": "sec", "x": "mm"}}
    table = hio.TableChunks(path, format="csv", text=options)
    assert table.columns == ["t", "x"]
    assert [list(c["x"]) for c in table.chunks(["x"], 10)] == [[1.5, 2.5]]
    path.write_bytes(b"t;x\n0;1.5\n")   # told: the point is the decimal mark here
    columns, _ = hio.read_columns(path, format="csv", text=TextOptions(delimiter=";"))
    assert list(columns["x"]) == [1.5]


@pytest.mark.parametrize(("text", "delimiter", "lines"), [
    (b"Logger 7, serial 12\nstarted 2026-11-24\nt,x,v\n0,1,0\n1,2,0\n", ",", 2),
    (b"\xef\xbb\xbfLogger 7\n\nsite A\nt;x\n0;1\n1;2\n", ";", 3),   # blank lines count
    (b"a\nb\nt,x,v\n0,1,2\n", ",", 2),    # as common as the data: the data's number wins
    (b"t,x\n0,1\n1,2\n3\n", ",", 0),      # a short row at the end is no preamble
    (b"", ",", 0),
    # the preamble's commas make ',' the text's delimiter; the table's is ';'
    (b"Rig 2, cantilever; export\nsampling 20 Hz; two decays\ntrajectory;t [ms];x [mm]\n"
     b"1;0,0;1011,3\n1;50,0;1000,4\n", ",", 2),
    (b"Rig 2\nsampling 20 Hz\nDAQ\nt,x,v\n0,1,0\n1,2,0\n", ",", 3),
])
def test_a_preamble_is_the_leading_lines_of_another_number_of_fields(text, delimiter, lines):
    assert preamble_lines(text, delimiter) == lines


def test_a_preamble_read_as_the_header_gets_the_skip_rows_hint(tmp_path):
    """Two lines before the header: the first is taken for it and the second is a row of
    another number of fields; the error names --skip-rows 2, which then reads the file."""
    path = tmp_path / "logger.csv"
    rows = "".join(f"{0.1 * i:g},{np.cos(0.1 * i):.6f},{-np.sin(0.1 * i):.6f}\n"
                   for i in range(300))
    path.write_text(f"Logger 7, serial 12\nstarted 2026-11-24\nt,x,v\n{rows}")
    done = subprocess.run([*hamid_command(), "fit", str(path), "--model", "duffing"],
                          capture_output=True, text=True, timeout=120)
    one_line_error(done, 1, f"{path}: row 1 has 1 field where the header has 2: "
                            "'started 2026-11-24'; the file seems to start with 2 lines "
                            "before its header: give --skip-rows 2")
    columns, _ = hio.read_columns(path, text=TextOptions(skip_rows=2))
    assert list(columns) == ["t", "x", "v"] and len(columns["t"]) == 300


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"delimiter": ";;"}, "--delimiter: ';;' is not one character that can separate cells"),
    ({"decimal": ";"}, "--decimal: ';' is not '.' or ','"),
    ({"delimiter": ",", "decimal": ","}, "--decimal: the decimal mark cannot be the delimiter"),
    ({"skip_rows": -1}, "--skip-rows: must be 0 or more"),
])
def test_bad_text_options(kwargs, message):
    with pytest.raises(UsageError, match=f"^{re.escape(message)}$"):
        TextOptions(**kwargs)


def test_compressed_semicolon_file_with_units(tmp_path, plain):
    path = tmp_path / "daq.csv.gz"
    path.write_bytes(gzip.compress(_european(SAMPLE_BYTES, units=b"-;s;m;m/s")))
    assert hio.read_columns(path)[1]["units"]["v"] == "m/s"
    got = hamid.fit(str(path)).estimates
    for name, value in plain.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_cli_fits_the_issue_units_row_file(tmp_path, plain):
    """Issue 18: a units row under the header was "'m' is not a number"."""
    from click.testing import CliRunner

    from hamid.cli.app import cli

    path = tmp_path / "daq.csv"
    path.write_bytes(_european(SAMPLE_BYTES, units=b"-;s;m;m/s"))
    result = CliRunner().invoke(cli, ["fit", str(path), "--format", "json"])
    assert result.exit_code == 0, result.output
    got = {p["name"]: p["estimate"] for p in json.loads(result.stdout)["parameters"]}
    for name, value in plain.items():
        assert got[name] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_bad_cells_in_a_decimal_comma_file_are_named(tmp_path):
    """Row numbers count data rows (not the units row); a cell that is not a number is
    named, not its neighbours written with decimal commas."""
    path = tmp_path / "daq.csv"
    path.write_bytes(b"t;x\ns;m\n0;1,5\n1;2,5;7\n")
    with pytest.raises(DataError, match=rf"^{path}: row 2 has 3 fields where the header "
                                        r"has 2: '1;2,5;7'$"):
        hio.read_columns(path)
    path.write_bytes(b"t;x\ns;m\n0;1,5\n1;abc\n2;3,25\n")
    columns, _ = hio.read_columns(path)
    with pytest.raises(DataError, match=rf"^{path}: column 'x', row 2: 'abc' is not a "
                                        r"number$"):
        hio.numeric_column(columns, "x", source=str(path))
    path.write_bytes(b"t;x\ns;m\n0;1,5\n1;2\n2;3,25\n")
    assert list(hio.read_columns(path)[0]["x"]) == [1.5, 2.0, 3.25]
    path.write_bytes(b"t;x\ns;m\n0;1,5\n1;abc\n2;3,25\n")
    chunk = next(hio.TableChunks(path).chunks(["x"], 2))   # a block with text cells
    with pytest.raises(DataError, match=rf"^{path}: column 'x', row 2: 'abc' is not a "
                                        r"number$"):
        hio.numeric_values(chunk["x"], "x", str(path))


def test_a_units_row_in_mm_gives_the_si_estimates(tmp_path):
    """The detected units row feeds the unit conversion: a ;-separated, decimal-comma file
    in millimetres fits as the SI file (converted here by hand)."""
    si = "sample_data/peng_quadratic.csv"
    columns, _ = hio.read_columns(si)
    lines = ["trajectory;t;u1;u2;v1;v2", ";s;mm;m;mm/s;m/s"]
    scale = {"u1": 1e3, "v1": 1e3}
    for i in range(len(columns["t"])):
        cells = [repr(float(columns[n][i]) * scale.get(n, 1)).replace(".", ",")
                 for n in ["t", "u1", "u2", "v1", "v2"]]
        lines.append(";".join([str(columns["trajectory"][i]), *cells]))
    path = tmp_path / "daq.csv"
    path.write_text("\n".join(lines) + "\n")
    truth = hamid.fit(si, "peng-quadratic").estimates
    result = hamid.fit(str(path), "peng-quadratic")
    assert result.to_dict()["data"]["scale"] == {"u1": 1e-3, "v1": 1e-3}
    for name, value in truth.items():
        assert result.estimates[name] == pytest.approx(value, rel=1e-10)


def test_fit_takes_the_text_layout_as_keywords(tmp_path):
    """A logger's preamble, ';' cells, decimal commas and a units row, all given."""
    import pandas as pd

    frame = pd.read_csv(SAMPLE, comment="#")
    body = frame.to_csv(sep=";", decimal=",", index=False).splitlines()
    units = ";".join(["-", "s", "m", "m/s"][:len(frame.columns)])
    path = tmp_path / "logger.txt"
    path.write_text("\n".join(["Logger 7 export", "2026-11-24 06:00", body[0], units,
                               *body[1:]]) + "\n")
    found = hamid.fit(path, "duffing", method="energy", format="csv", delimiter=";",
                      decimal=",", skip_rows=2, units_row=True).estimates
    expected = hamid.fit(SAMPLE, "duffing", method="energy").estimates
    assert found == pytest.approx(expected, rel=1e-12)
    with pytest.raises(UsageError, match="--decimal: 'x' is not"):
        hamid.fit(path, "duffing", decimal="x")


def _oscillation(tmp_path, header: str, scale: float):
    """x = 0.01 cos(2t) m (so V = 2 x**2: c_2 = 2, c_3 = 0), written in `scale` units."""
    t = np.arange(0.0, 20.0, 0.01)
    x, v = 0.01 * np.cos(2 * t), -0.02 * np.sin(2 * t)
    path = tmp_path / f"oscillation-{scale:g}.csv"
    rows = [f"{a!r},{b * scale!r},{c * scale!r}"
            for a, b, c in zip(t.tolist(), x.tolist(), v.tolist(), strict=True)]
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_unit_headers_fit_without_a_model(tmp_path):
    """`x [mm]` and `x_dot [mm/s]` with no --model: the assumed polynomial takes the names
    without their units (x, x_dot) and the values in SI, as the same motion in metres."""
    in_mm = _oscillation(tmp_path, "t,x [mm],x_dot [mm/s]", 1e3)
    in_m = _oscillation(tmp_path, "t,x,x_dot", 1.0)
    found, expected = hamid.fit(in_mm), hamid.fit(in_m)
    assert (found.model["coordinates"], found.model["velocities"]) == (["x"], ["x_dot"])
    assert found.estimates["c_2"] == pytest.approx(2.0, rel=1e-4)
    # c_3 x**3 against c_2 x**2 at |x| <= 0.01 m: zero on the scale c_2 / 0.01 = 200.
    assert abs(found.estimates["c_3"]) < 1e-4 * 200
    for name, value in expected.estimates.items():
        assert found.estimates[name] == pytest.approx(value, rel=1e-9, abs=1e-9)


def test_unit_headers_fit_without_a_model_on_the_command_line(tmp_path):
    import subprocess

    from helpers import hamid_command

    path = _oscillation(tmp_path, "t,x [mm],x_dot [mm/s]", 1e3)
    done = subprocess.run([*hamid_command(), "fit", str(path), "--format", "json"],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["data"]["scale"] == {"x [mm]": 1e-3, "x_dot [mm/s]": 1e-3}
    estimates = {p["name"]: p["estimate"] for p in report["parameters"]}
    assert estimates["c_2"] == pytest.approx(2.0, rel=1e-4)


def test_the_skip_rows_hint_counts_the_lines_before_the_header_taken(tmp_path):
    """A comment line and a given --skip-rows 1 before a two-line preamble: the hint
    counts from the file's start, as --skip-rows does."""
    path = tmp_path / "logger.csv"
    path.write_text("junk\n# a comment\nLogger 7, serial 12\nstarted today\nt,x,v\n0,1,0\n"
                    "1,2,0\n2,3,0\n")
    with pytest.raises(DataError, match=r"give --skip-rows 4$"):
        hio.read_columns(path, text=TextOptions(skip_rows=1))
    columns, _ = hio.read_columns(path, text=TextOptions(skip_rows=4))
    assert list(columns["x"]) == [1, 2, 3]
