"""Tests for hamid.data.readers: tables, metadata, atomic writes, option values and column
resolution."""

from __future__ import annotations

import errno
import io
import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hamid import options
from hamid.data import column_roles, documents, writing
from hamid.data import readers as hio
from hamid.errors import DataError, ModelError, UsageError

FORMATS = {"csv": "run.csv", "tsv": "run.tsv", "parquet": "run.parquet"}
METADATA = {
    "model": "duffing",
    "parameters": {"k": 1.0, "k3": 0.1},
    "noise": None,
    "seed": 7,
    "text": 'line\nbreak, comma "quoted" é',
}


def _table(n: int = 5) -> pd.DataFrame:
    """A table like simulate's output: int trajectory, floats, and a text column."""
    rng = np.random.default_rng(1)
    return pd.DataFrame(
        {
            "trajectory": np.arange(n) % 2 + 1,
            "t": np.arange(n) * 0.01,
            "x": rng.standard_normal(n),
            "vx": rng.standard_normal(n) * 1e-12,
            "split": ["id", "ood"] * (n // 2) + ["id"] * (n % 2),
        }
    )


def _fake_stdout(monkeypatch: pytest.MonkeyPatch) -> io.TextIOWrapper:
    stream = io.TextIOWrapper(io.BytesIO(), encoding="utf-8")
    monkeypatch.setattr(sys, "stdout", stream)
    return stream


def _fake_stdin(monkeypatch: pytest.MonkeyPatch, data: bytes) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data), encoding="utf-8"))


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    """Work in tmp_path so that file names in messages are exactly the names given."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ---------------------------------------------------------------------------------------------
# Round trips


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip_keeps_values_types_order_and_metadata(tmp_path, fmt):
    table = _table()[["x", "split", "trajectory", "vx", "t"]]  # not alphabetical
    path = tmp_path / FORMATS[fmt]
    writing.write_table(table, path, metadata=METADATA)
    back, metadata = hio.read_table(path)
    assert list(back.columns) == ["x", "split", "trajectory", "vx", "t"]
    assert back["trajectory"].dtype == np.int64
    assert back["x"].dtype == np.float64
    assert list(back["split"]) == list(table["split"])
    for column in ["x", "vx", "t"]:
        assert np.array_equal(back[column].to_numpy(), table[column].to_numpy())
    assert metadata == METADATA


@pytest.mark.parametrize("fmt", FORMATS)
def test_floats_round_trip_exactly(tmp_path, fmt):
    rng = np.random.default_rng(2)
    x = rng.standard_normal(2000) * 10.0 ** rng.integers(-300, 300, 2000)
    x = np.concatenate([x, [5e-324, -0.0, 1e308, 0.1, 1 / 3, 2.0**53 + 2, -1.5]])
    path = tmp_path / FORMATS[fmt]
    writing.write_table(pd.DataFrame({"x": x}), path)
    y = hio.numeric_column(hio.read_table(path)[0], "x", source=str(path))
    assert np.array_equal(x, y)
    assert np.array_equal(np.signbit(x), np.signbit(y))


@pytest.mark.parametrize(("fmt", "delimiter"), [("csv", ","), ("tsv", "\t")])
def test_text_layout_metadata_line_and_integers(tmp_path, fmt, delimiter):
    path = tmp_path / FORMATS[fmt]
    writing.write_table(_table(3), path, metadata={"seed": 0, "b": [1.5, None]})
    lines = path.read_text().splitlines()
    assert lines[0] == '# hamid: {"seed":0,"b":[1.5,null]}'
    assert lines[1] == delimiter.join(["trajectory", "t", "x", "vx", "split"])
    assert lines[2].startswith(f"1{delimiter}0{delimiter}")
    assert lines[3].startswith(f"2{delimiter}0.01{delimiter}")


@pytest.mark.parametrize("fmt", ["csv", "tsv"])
def test_text_without_metadata_starts_with_header(tmp_path, fmt):
    path = tmp_path / FORMATS[fmt]
    writing.write_table(_table(2), path)
    assert path.read_text().startswith("trajectory")
    assert hio.read_table(path)[1] is None


def test_parquet_without_metadata_reads_none(tmp_path):
    path = tmp_path / "run.parquet"
    writing.write_table(_table(2), path)
    assert hio.read_table(path)[1] is None


def test_parquet_metadata_sits_beside_pandas_metadata(tmp_path):
    path = tmp_path / "run.parquet"
    writing.write_table(_table(2), path, metadata={"seed": 3})
    stored = pq.read_schema(path).metadata
    assert json.loads(stored[b"hamid"]) == {"seed": 3}
    assert b"pandas" in stored


def test_header_names_that_need_quotes_round_trip(tmp_path):
    table = pd.DataFrame({"a,b": [1.5], 'say "hi"': [2.5], "#t": [3.5]})
    path = tmp_path / "q.csv"
    writing.write_table(table, path)
    assert list(hio.read_table(path)[0].columns) == ["a,b", 'say "hi"', "#t"]


def test_metadata_accepts_numpy_values(tmp_path):
    path = tmp_path / "run.csv"
    metadata = {"seed": np.int64(4), "x0": np.array([0.5, 1.0]), "h": np.float64(0.25)}
    writing.write_table(_table(2), path, metadata=metadata)
    assert hio.read_table(path)[1] == {"seed": 4, "x0": [0.5, 1.0], "h": 0.25}


def test_metadata_with_nan_is_refused_before_writing(tmp_path):
    path = tmp_path / "run.csv"
    with pytest.raises(ValueError, match="Out of range float values"):
        writing.write_table(_table(2), path, metadata={"h": float("nan")})
    assert not path.exists()


def test_index_is_not_written(tmp_path):
    table = _table(4).iloc[[3, 1]]
    path = tmp_path / "run.csv"
    writing.write_table(table, path)
    back = hio.read_table(path)[0]
    assert list(back.columns) == list(table.columns)
    assert list(back["x"]) == list(table["x"])


# ---------------------------------------------------------------------------------------------
# Formats: extensions, overrides and sniffing


@pytest.mark.parametrize(
    ("name", "fmt"),
    [("a.CSV", "csv"), ("a.tab", "tsv"), ("a.pq", "parquet"), ("a.TSV", "tsv")],
)
def test_extensions_choose_the_format(tmp_path, name, fmt):
    path = tmp_path / name
    writing.write_table(_table(3), path)
    if fmt == "parquet":
        assert path.read_bytes().startswith(b"PAR1")
    else:
        assert ("\t" in path.read_text()) == (fmt == "tsv")
    assert list(hio.read_table(path)[0].columns) == list(_table(3).columns)


@pytest.mark.parametrize("fmt", FORMATS)
def test_unknown_extension_is_sniffed(tmp_path, fmt):
    path = tmp_path / "run.dat"
    writing.write_table(_table(3), path, format=fmt, metadata={"fmt": fmt})
    back, metadata = hio.read_table(path)
    assert list(back.columns) == list(_table(3).columns)
    assert metadata == {"fmt": fmt}


def test_format_overrides_the_extension(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("t\tx\n0\t1.5\n")
    assert list(hio.read_table(path, format="tsv")[0].columns) == ["t", "x"]
    assert list(hio.read_table(path)[0].columns) == ["t\tx"]


def test_unknown_read_format_is_a_usage_error(tmp_path):
    with pytest.raises(UsageError, match="unknown data format 'xlsx'"):
        hio.read_table(tmp_path / "a.csv", format="xlsx")


def test_comments_bom_and_blank_lines_before_the_header(tmp_path):
    path = tmp_path / "run.csv"
    path.write_bytes(
        b'\xef\xbb\xbf# recorded on rig 2\r\n\r\n# hamid: {"seed": 1}\r\n# more\r\n'
        b"t,x\r\n0,1.5\r\n0.1,2.5\r\n"
    )
    table, metadata = hio.read_table(path)
    assert metadata == {"seed": 1}
    assert list(table.columns) == ["t", "x"]
    assert list(table["x"]) == [1.5, 2.5]


def test_plain_comments_give_no_metadata(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("# hamid was here\n# note: hamid: {}\nt,x\n0,1\n")
    table, metadata = hio.read_table(path)
    assert metadata is None
    assert list(table.columns) == ["t", "x"]


def test_header_names_are_stripped(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("t, x , vx\n0, 1.5, 2\n")
    table = hio.read_table(path)[0]
    assert list(table.columns) == ["t", "x", "vx"]
    assert hio.numeric_column(table, "x", source="run.csv")[0] == 1.5


@pytest.mark.parametrize("read", [hio.read_table, hio.read_columns])
def test_parquet_index_written_by_pandas_becomes_a_column(tmp_path, read):
    path = tmp_path / "run.parquet"
    frame = pd.DataFrame({"x": [1.0, 2.0]}, index=pd.Index([0.0, 0.5], name="t"))
    frame.to_parquet(path)
    table = read(path)[0]
    assert list(table) == ["t", "x"]
    assert list(table["t"]) == [0.0, 0.5]


@pytest.mark.parametrize("frame", [
    pd.DataFrame({"x": [1.5, np.nan, 3.0], "n": [1, 2, 3], "label": ["a", None, "b"]}),
    pd.DataFrame({"x": [1.0, 2.0]}, index=pd.Index([10, 20])),   # unnamed index: dropped
    pd.DataFrame({"k": pd.array([1, None, 3], dtype="Int64"), "u": np.array([1, 2, 3],
                                                                            np.uint16)}),
    pd.DataFrame({"f": np.array([0.5, 1.5], np.float32), "flag": [True, False]}),
])
@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_read_columns_holds_the_cells_of_read_table(tmp_path, frame, suffix):
    path = tmp_path / f"run{suffix}"
    frame.to_csv(path, index=False) if suffix == ".csv" else frame.to_parquet(path)
    table = hio.read_table(path)[0]
    columns = hio.read_columns(path)[0]
    assert list(columns) == list(table.columns)

    def outcome(read, name):
        try:
            return hio.numeric_column(read, name, source="run").tolist()
        except DataError as exc:
            return str(exc)

    for name in columns:
        assert outcome(columns, name) == outcome(table, name)


def test_read_columns_of_a_sliced_arrow_column_starts_at_its_offset():
    import pyarrow as pa

    column = pa.array([1.0, 2.0, 3.0, 4.0]).slice(1, 2)
    assert hio.as_numpy(column).tolist() == [2.0, 3.0]
    assert hio.as_numpy(pa.chunked_array([[1, 2], [3]])).tolist() == [1, 2, 3]


# ---------------------------------------------------------------------------------------------
# Standard input and output


@pytest.mark.parametrize("fmt", FORMATS)
def test_stdout_to_stdin_round_trip(monkeypatch, fmt):
    stdout = _fake_stdout(monkeypatch)
    writing.write_table(_table(), "-", format=fmt, metadata=METADATA)
    data = stdout.buffer.getvalue()
    assert data.startswith(b"PAR1" if fmt == "parquet" else b"# hamid: ")
    _fake_stdin(monkeypatch, data)
    table, metadata = hio.read_table("-")
    assert metadata == METADATA
    assert table.equals(_table())


def test_stdout_defaults_to_csv(monkeypatch):
    stdout = _fake_stdout(monkeypatch)
    writing.write_table(_table(2), "-")
    assert stdout.buffer.getvalue().startswith(b"trajectory,t,x,vx,split\n1,0,")


def test_stdout_keeps_text_written_before(monkeypatch):
    stdout = _fake_stdout(monkeypatch)
    stdout.write("first\n")
    writing.write_table(_table(2), "-")
    assert stdout.buffer.getvalue().startswith(b"first\ntrajectory,")


def test_text_only_stdout(monkeypatch):
    stdout = io.StringIO()
    monkeypatch.setattr(sys, "stdout", stdout)
    writing.write_table(_table(2), "-", format="tsv")
    writing.write_text("done é\n", "-")
    assert stdout.getvalue().startswith("trajectory\tt\t")
    assert stdout.getvalue().endswith("done é\n")
    with pytest.raises(DataError, match="^<stdout>: cannot write Parquet"):
        writing.write_table(_table(2), "-", format="parquet")


def test_stdin_tsv_is_sniffed(monkeypatch):
    _fake_stdin(monkeypatch, b"# hamid: {}\nt\tx\n0\t1.5\n")
    table, metadata = hio.read_table("-")
    assert metadata == {}
    assert list(table.columns) == ["t", "x"]


@pytest.mark.parametrize(
    ("data", "message"),
    [(b"", "^<stdin>: file is empty$"), (b"t,x\n", "^<stdin>: has a header but no data rows$")],
)
def test_stdin_errors_name_stdin(monkeypatch, data, message):
    _fake_stdin(monkeypatch, data)
    with pytest.raises(DataError, match=message):
        hio.read_table("-")


def test_write_text_to_stdout_and_file(monkeypatch, tmp_path):
    stdout = _fake_stdout(monkeypatch)
    writing.write_text("résumé\n", "-")
    assert stdout.buffer.getvalue() == "résumé\n".encode()
    writing.write_text("a\r\nb", tmp_path / "out.txt")
    assert (tmp_path / "out.txt").read_bytes() == b"a\r\nb"


# ---------------------------------------------------------------------------------------------
# Read errors


def test_missing_file(in_tmp):
    with pytest.raises(DataError, match="^nothere.csv: no such file$"):
        hio.read_table("nothere.csv")


def test_folder(in_tmp):
    (in_tmp / "d.csv").mkdir()
    with pytest.raises(DataError, match="^d.csv: is a folder, not a file$"):
        hio.read_table("d.csv")


@pytest.mark.parametrize("name", ["e.csv", "e.tsv", "e.parquet", "e.dat"])
@pytest.mark.parametrize("content", [b"", b"\n \n"])
def test_empty_file(in_tmp, name, content):
    (in_tmp / name).write_bytes(content)
    with pytest.raises(DataError, match=f"^{name}: file is empty$"):
        hio.read_table(name)


def test_only_comments(in_tmp):
    (in_tmp / "c.csv").write_text('# hamid: {"seed": 1}\n# nothing else\n\n')
    with pytest.raises(DataError, match="^c.csv: has comment lines but no header line$"):
        hio.read_table("c.csv")


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("h.csv", "has a header but no data rows"),
        ("h.tsv", "has a header but no data rows"),
        ("h.parquet", "has columns but no data rows"),
    ],
)
def test_header_only(in_tmp, name, message):
    writing.write_table(_table().iloc[:0], name, metadata={"seed": 0})
    with pytest.raises(DataError, match=f"^{name}: {message}$"):
        hio.read_table(name)


def test_header_then_blank_lines(in_tmp):
    (in_tmp / "h.csv").write_text("t,x\n\n\n")
    with pytest.raises(DataError, match="^h.csv: has a header but no data rows$"):
        hio.read_table("h.csv")


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda data: data[: len(data) // 2], id="truncated"),
        pytest.param(lambda data: data[:-3], id="footer-cut"),
        pytest.param(lambda data: bytes(np.random.default_rng(0).bytes(300)), id="random"),
        pytest.param(lambda data: b"PAR1" + bytes(200) + b"PAR1", id="zeros"),
        pytest.param(lambda data: b"t,x\n0,1\n", id="text"),
    ],
)
def test_corrupt_parquet(in_tmp, damage):
    writing.write_table(_table(50), "good.parquet")
    (in_tmp / "bad.parquet").write_bytes(damage((in_tmp / "good.parquet").read_bytes()))
    with pytest.raises(DataError, match=r"^bad.parquet: is not a valid Parquet file \(.+\)$"):
        hio.read_table("bad.parquet")


def test_parquet_in_a_csv_file(in_tmp):
    writing.write_table(_table(3), "run.csv", format="parquet")
    with pytest.raises(DataError, match="^run.csv: is a Parquet file, not CSV text$"):
        hio.read_table("run.csv")


def test_gzip_file(in_tmp):
    import gzip

    (in_tmp / "run.csv").write_bytes(gzip.compress(b"t,x\n0,1\n"))
    table, _ = hio.read_table("run.csv")   # read through pyarrow's gzip codec (issue 18)
    assert list(table.columns) == ["t", "x"] and table["x"].tolist() == [1]


@pytest.mark.parametrize(
    ("content", "listed"),
    [
        (b"t,x,vx,x\n0,1,2,3\n", "name 'x'"),
        (b"t,x,x,t\n0,1,2,3\n", "names 'x', 't'"),
        (b"t, x,x \n0,1,2\n", "name 'x'"),
    ],
)
def test_duplicated_columns_csv(in_tmp, content, listed):
    (in_tmp / "d.csv").write_bytes(content)
    with pytest.raises(DataError, match=f"^d.csv: duplicated column {listed}$"):
        hio.read_table("d.csv")


def test_duplicated_columns_parquet(in_tmp):
    table = pa.table([pa.array([1.0]), pa.array([2.0])], names=["x", "x"])
    pq.write_table(table, in_tmp / "d.parquet")
    with pytest.raises(DataError, match="^d.parquet: duplicated column name 'x'$"):
        hio.read_table("d.parquet")


@pytest.mark.parametrize(
    ("content", "line"),
    [
        (b"t,x\n0,1\n0.1,caf\xe9\n", 3),
        (b"t,\xffx\n0,1\n", 1),
        (b"# comment\nt,x\n0,1\n1,\xff\xfe\n", 4),
    ],
)
def test_text_that_is_not_utf8(in_tmp, content, line):
    (in_tmp / "l1.csv").write_bytes(content)
    with pytest.raises(DataError, match=f"^l1.csv: line {line} is not UTF-8 text"):
        hio.read_table("l1.csv")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"t,x\n0,1\n1,2\n3\n", r"row 3 has 1 field where the header has 2: '3'"),
        (b"# c\nt,x\n\n0,1\n1,2,3\n", r"row 2 has 3 fields where the header has 2: '1,2,3'"),
    ],
)
def test_ragged_rows_are_named(in_tmp, content, message):
    (in_tmp / "r.csv").write_bytes(content)
    with pytest.raises(DataError, match=f"^r.csv: {message}$"):
        hio.read_table("r.csv")


BAD_METADATA = r"line 1: the hamid metadata: not valid JSON \(line 1, column \d+\): .+"


@pytest.mark.parametrize(
    ("line", "message"),
    [
        (b"# hamid: {bad json}", BAD_METADATA),
        (b"# hamid: [1, 2]", "line 1: the hamid metadata is not a JSON object"),
        (b"# hamid:", BAD_METADATA),
    ],
)
def test_malformed_metadata_line(in_tmp, line, message):
    (in_tmp / "m.csv").write_bytes(line + b"\nt,x\n0,1\n")
    with pytest.raises(DataError, match=f"^m.csv: {message}"):
        hio.read_table("m.csv")


def test_malformed_parquet_metadata(in_tmp):
    table = pa.table({"t": [0.0]}).replace_schema_metadata({b"hamid": b"{not json"})
    pq.write_table(table, in_tmp / "m.parquet")
    with pytest.raises(DataError, match=r"^m.parquet: the hamid metadata: not valid JSON"):
        hio.read_table("m.parquet")


def test_unreadable_file(in_tmp, monkeypatch):
    (in_tmp / "secret.csv").write_text("t\n1\n")

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr("builtins.open", refuse)
    with pytest.raises(DataError, match="^secret.csv: cannot read: Permission denied$"):
        hio.read_table("secret.csv")


# ---------------------------------------------------------------------------------------------
# Cells that are not numbers


def _csv_with_cell(folder, cell: str, row: int = 3, n: int = 5):
    rows = [f"{i * 0.1},{i},{i}.5" for i in range(n)]
    t, x, _ = rows[row - 1].split(",")
    rows[row - 1] = f"{t},{x},{cell}"
    (folder / "run3.csv").write_text("t,x,vx\n" + "\n".join(rows) + "\n")
    return hio.read_table(folder / "run3.csv")[0]


@pytest.mark.parametrize(
    ("cell", "problem"),
    [
        ("n/a", "'n/a' is not a number"),
        ("NA", "'NA' is not a number"),
        ("1.2.3", "'1.2.3' is not a number"),
        ("", "missing value"),
        ("nan", "missing value"),
        ("NaN", "missing value"),
        ("inf", "infinite value"),
        ("-inf", "infinite value"),
    ],
)
@pytest.mark.parametrize("row", [1, 3, 5])
def test_bad_cell_names_column_and_row(tmp_path, cell, problem, row):
    table = _csv_with_cell(tmp_path, cell, row=row)
    with pytest.raises(DataError, match=f"^run3.csv: column 'vx', row {row}: {problem}$"):
        hio.numeric_column(table, "vx", source="run3.csv")
    assert np.array_equal(hio.numeric_column(table, "x", source="run3.csv"), np.arange(5.0))


def test_first_bad_row_is_reported(tmp_path):
    (tmp_path / "run.csv").write_text("t,x\n0,1\n1,oops\n2,\n3,inf\n4,bad\n")
    table = hio.read_table(tmp_path / "run.csv")[0]
    with pytest.raises(DataError, match="^run.csv: column 'x', row 2: 'oops' is not a number$"):
        hio.numeric_column(table, "x", source="run.csv")


def test_missing_value_before_a_text_cell(tmp_path):
    (tmp_path / "run.csv").write_text("t,x\n0,1\n1,\n2,oops\n")
    table = hio.read_table(tmp_path / "run.csv")[0]
    with pytest.raises(DataError, match="^run.csv: column 'x', row 2: missing value$"):
        hio.numeric_column(table, "x", source="run.csv")


def test_text_column_is_not_a_number(tmp_path):
    path = tmp_path / "run.csv"
    writing.write_table(_table(), path)
    table = hio.read_table(path)[0]
    with pytest.raises(DataError, match="^run.csv: column 'split', row 1: 'id' is not a number$"):
        hio.numeric_column(table, "split", source="run.csv")


def test_missing_column_lists_columns(tmp_path):
    with pytest.raises(DataError, match=r"^run.csv: no column 'vy' \(columns: t, x, vx\)$"):
        hio.numeric_column(pd.DataFrame(columns=["t", "x", "vx"]), "vy", source="run.csv")


def test_long_column_list_is_shortened():
    table = pd.DataFrame(columns=[f"c{i}" for i in range(30)])
    with pytest.raises(DataError, match=r"c19, \.\.\.\)$"):
        hio.numeric_column(table, "x", source="wide.csv")


def test_numeric_column_returns_float64_copy_of_ints():
    table = pd.DataFrame({"n": np.array([1, 2, 2**53], dtype=np.int64)})
    values = hio.numeric_column(table, "n", source="s")
    assert values.dtype == np.float64
    assert values.tolist() == [1.0, 2.0, 2.0**53]


@pytest.mark.parametrize(
    ("cells", "problem"),
    [
        ([1.5, 2, np.int32(3), " 4.5 "], None),
        ([1.5, None, 3.0, 4.0], "row 2: missing value"),
        ([1.5, 2.0, pd.NA, 4.0], "row 3: missing value"),
        ([1.5, True, 3.0, 4.0], "row 2: 'True' is not a number"),
        ([1.5, 2.0, 3.0, [4.0]], r"row 4: '\[4.0\]' is not a number"),
        ([1.5, 2.0, 3.0, float("-inf")], "row 4: infinite value"),
    ],
)
def test_numeric_column_on_object_cells(cells, problem):
    table = pd.DataFrame({"x": pd.Series(cells, dtype=object)})
    if problem is None:
        assert hio.numeric_column(table, "x", source="api").tolist() == [1.5, 2.0, 3.0, 4.5]
    else:
        with pytest.raises(DataError, match=f"^api: column 'x', {problem}$"):
            hio.numeric_column(table, "x", source="api")


@pytest.mark.parametrize(
    "series",
    [
        pd.Series([True, False]),
        pd.Series(pd.to_datetime(["2020-01-01", "2020-01-02"])),
    ],
)
def test_numeric_column_rejects_booleans_and_dates(series):
    with pytest.raises(DataError, match="^f: column 'x', row 1: '.+' is not a number$"):
        hio.numeric_column(pd.DataFrame({"x": series}), "x", source="f")


def test_nullable_float_column():
    table = pd.DataFrame({"x": pd.array([1.0, None], dtype="Float64")})
    with pytest.raises(DataError, match="^f: column 'x', row 2: missing value$"):
        hio.numeric_column(table, "x", source="f")


def test_rows_are_positions_not_index_labels():
    table = pd.DataFrame({"x": [1.0, np.nan]}, index=[10, 20])
    with pytest.raises(DataError, match="^f: column 'x', row 2: missing value$"):
        hio.numeric_column(table, "x", source="f")


def _fail_typed_csv_reads(monkeypatch):
    """Make pyarrow fail as versions before 2x do when a late block does not fit the type."""
    real = pacsv.read_csv

    def read_csv(source, *, read_options=None, convert_options=None, **kwargs):
        one_block = read_options is not None and read_options.block_size > source.size()
        as_text = convert_options is not None and convert_options.default_column_type is not None
        if not (one_block or as_text):
            raise pa.ArrowInvalid("In CSV column #2: CSV conversion error to double")
        return real(source, read_options=read_options, convert_options=convert_options, **kwargs)

    monkeypatch.setattr(pacsv, "read_csv", read_csv)


def test_bad_cell_after_the_first_block(tmp_path):
    n = 120_000  # about 3 MB: several of pyarrow's 1 MB blocks
    table = _table(n)
    path = tmp_path / "big.csv"
    writing.write_table(table, path)
    lines = path.read_text().splitlines()
    fields = lines[100_001].split(",")
    fields[3] = "n/a"
    lines[100_001] = ",".join(fields)
    path.write_text("\n".join(lines) + "\n")
    back = hio.read_table(path)[0]
    assert back["trajectory"].dtype == np.int64
    assert np.array_equal(hio.numeric_column(back, "x", source="big.csv"), table["x"])
    with pytest.raises(DataError, match="^big.csv: column 'vx', row 100001: 'n/a' is not a"):
        hio.numeric_column(back, "vx", source="big.csv")


@pytest.mark.parametrize("max_block", [2**31 - 1, 64])
def test_fallback_when_pyarrow_refuses_a_late_cell(tmp_path, monkeypatch, max_block):
    """Older pyarrow raises instead of re-inferring; larger files are read as text."""
    _fail_typed_csv_reads(monkeypatch)
    monkeypatch.setattr(hio, "_MAX_BLOCK", max_block)
    path = tmp_path / "run.csv"
    path.write_text("trajectory,t,x\n1,0,0.5\n1,0.1,n/a\n2,0.2,1e-3\n")
    table = hio.read_table(path)[0]
    assert hio.numeric_column(table, "t", source="run.csv").tolist() == [0.0, 0.1, 0.2]
    assert hio.numeric_column(table, "trajectory", source="run.csv").tolist() == [1, 1, 2]
    with pytest.raises(DataError, match="^run.csv: column 'x', row 2: 'n/a' is not a number$"):
        hio.numeric_column(table, "x", source="run.csv")


# ---------------------------------------------------------------------------------------------
# Write errors and atomicity


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("out.xlsx", r"^out.xlsx: unknown extension '\.xlsx'"),
        ("out", "^out: cannot tell the format without an extension"),
    ],
)
def test_write_unknown_extension(in_tmp, name, message):
    with pytest.raises(UsageError, match=message):
        writing.write_table(_table(2), name)
    assert os.listdir(in_tmp) == []


def test_write_unknown_format(in_tmp):
    with pytest.raises(UsageError, match="unknown data format 'json'"):
        writing.write_table(_table(2), "out.csv", format="json")


def test_write_into_missing_folder(in_tmp):
    with pytest.raises(DataError, match="^nowhere/out.csv: cannot write: folder 'nowhere' does"):
        writing.write_table(_table(2), "nowhere/out.csv")


def test_write_under_a_file(in_tmp):
    (in_tmp / "plain").write_text("x")
    with pytest.raises(DataError, match="^plain/out.csv: cannot write in folder 'plain': Not a"):
        writing.write_table(_table(2), "plain/out.csv")


def test_write_onto_a_folder(in_tmp):
    (in_tmp / "out.csv").mkdir()
    with pytest.raises(DataError, match="^out.csv: is a folder, not a file$"):
        writing.write_text("x", "out.csv")


def test_write_in_unwritable_folder(in_tmp, monkeypatch):
    def refuse(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(writing.tempfile, "mkstemp", refuse)
    with pytest.raises(DataError, match="^out.csv: cannot write in folder '.': Permission denied"):
        writing.write_table(_table(2), "out.csv")


def _partial_writer(exception: BaseException):
    def write(table, stream, *args, **kwargs):
        stream.write(b"half a table,")
        stream.flush()
        raise exception

    return write


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize(
    ("exception", "expected", "match"),
    [
        (RuntimeError("boom"), RuntimeError, "^boom$"),
        (KeyboardInterrupt(), KeyboardInterrupt, None),
        (
            OSError(errno.ENOSPC, "No space left on device"),
            DataError,
            "^run.*: cannot write: No space left on device$",
        ),
        (pa.ArrowIOError("disk went away"), DataError, "^run.*: cannot write"),
        (
            pa.ArrowNotImplementedError("no such cast"),
            DataError,
            r"^run.*: cannot write \(no such cast\)$",
        ),
    ],
)
def test_failed_write_leaves_destination_unchanged(
    in_tmp, monkeypatch, fmt, exception, expected, match
):
    name = FORMATS[fmt]
    (in_tmp / name).write_bytes(b"precious bytes\n")
    os.chmod(in_tmp / name, 0o640)
    monkeypatch.setattr(pacsv, "write_csv", _partial_writer(exception))
    monkeypatch.setattr(pq, "write_table", _partial_writer(exception))
    with pytest.raises(expected, match=match):
        writing.write_table(_table(), name, metadata={"seed": 1})
    assert (in_tmp / name).read_bytes() == b"precious bytes\n"
    assert os.listdir(in_tmp) == [name]


def test_failed_write_without_destination_leaves_nothing(in_tmp, monkeypatch):
    monkeypatch.setattr(pacsv, "write_csv", _partial_writer(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        writing.write_table(_table(), "new.csv")
    assert os.listdir(in_tmp) == []


@pytest.mark.parametrize("fmt", FORMATS)
def test_unserialisable_cell_leaves_destination_unchanged(in_tmp, fmt):
    name = FORMATS[fmt]
    (in_tmp / name).write_bytes(b"precious")
    table = pd.DataFrame({"t": [0.0, 1.0], "o": [object(), object()]})
    with pytest.raises(DataError, match=f"^{name}: cannot write the table"):
        writing.write_table(table, name)
    assert (in_tmp / name).read_bytes() == b"precious"
    assert os.listdir(in_tmp) == [name]


def test_failed_fsync_leaves_text_destination_unchanged(in_tmp, monkeypatch):
    (in_tmp / "report.md").write_text("old report")

    def fail(fd):
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(writing.os, "fsync", fail)
    with pytest.raises(DataError, match="^report.md: cannot write: Input/output error$"):
        writing.write_text("new report", "report.md")
    assert (in_tmp / "report.md").read_text() == "old report"
    assert os.listdir(in_tmp) == ["report.md"]


def test_duplicated_columns_are_not_written(in_tmp):
    with pytest.raises(DataError, match="^out.csv: duplicated column name 'x'$"):
        writing.write_table(pd.DataFrame([[1, 2]], columns=["x", "x"]), "out.csv")
    assert os.listdir(in_tmp) == []


def test_written_file_replaces_and_gets_usual_permissions(in_tmp):
    old = os.umask(0o022)
    try:
        writing.write_text("new", "fresh.txt")
        (in_tmp / "kept.txt").write_text("old")
        os.chmod(in_tmp / "kept.txt", 0o600)
        writing.write_text("new", "kept.txt")
    finally:
        os.umask(old)
    assert (in_tmp / "fresh.txt").stat().st_mode & 0o777 == 0o644
    assert (in_tmp / "kept.txt").stat().st_mode & 0o777 == 0o600
    assert (in_tmp / "kept.txt").read_text() == "new"


# ---------------------------------------------------------------------------------------------
# TOML and JSON


def test_read_toml(in_tmp):
    (in_tmp / "system.toml").write_text('[model]\nbuiltin = "duffing"\n[[initial]]\nx = 0.5\n')
    assert documents.read_toml("system.toml") == {
        "model": {"builtin": "duffing"},
        "initial": [{"x": 0.5}],
    }


def test_read_toml_from_stdin(monkeypatch):
    _fake_stdin(monkeypatch, b"[simulate]\ndt = 0.01\n")
    assert documents.read_toml("-") == {"simulate": {"dt": 0.01}}


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"[model]\nbuiltin = \n", r"^system.toml: not valid TOML: .*\(at line 2, column 11\)$"),
        (b"[model]\n[model]\n", r"^system.toml: not valid TOML: .*line 2"),
        (b"k = '\xff'\n", r"^system.toml: not valid TOML: line 1 is not UTF-8 text "
                           r"\(byte 0xff\); save the file as UTF-8$"),
    ],
)
def test_malformed_toml(in_tmp, content, message):
    (in_tmp / "system.toml").write_bytes(content)
    with pytest.raises(ModelError, match=message):
        documents.read_toml("system.toml")


@pytest.mark.parametrize(("make", "message"), [(None, "no such file"), ("dir", "is a folder")])
def test_toml_file_problems_are_data_errors(in_tmp, make, message):
    if make == "dir":
        (in_tmp / "system.toml").mkdir()
    with pytest.raises(DataError, match=f"^system.toml: {message}"):
        documents.read_toml("system.toml")


def test_read_json(in_tmp):
    (in_tmp / "result.json").write_text('{"schema": "hamid.fit/1", "x": [1, 2.5]}')
    assert documents.read_json("result.json") == {"schema": "hamid.fit/1", "x": [1, 2.5]}


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{\n  "a": 1,\n    x\n}', r"not valid JSON \(line 3, column 5\): Expecting property"),
        ("", r"not valid JSON \(line 1, column 1\)"),
        ("[1, 2]", "expected a JSON object, found an array"),
        ('"text"', "expected a JSON object, found a string"),
        ("3.5", "expected a JSON object, found a number"),
        ("null", "expected a JSON object, found null"),
    ],
)
def test_malformed_json(in_tmp, content, message):
    (in_tmp / "result.json").write_text(content)
    with pytest.raises(DataError, match=f"^result.json: {message}"):
        documents.read_json("result.json")


def test_missing_json(in_tmp):
    with pytest.raises(DataError, match="^result.json: no such file$"):
        documents.read_json("result.json")


# ---------------------------------------------------------------------------------------------
# Column resolution


@pytest.mark.parametrize(
    ("columns", "expected"),
    [
        (["t", "x", "vx"], "vx"),
        (["t", "x", "x_dot"], "x_dot"),
        (["t", "x", "xdot"], "xdot"),
        (["t", "x", "dx"], "dx"),
        (["dx", "xdot", "x_dot", "vx"], "vx"),
        (["dx", "xdot", "x_dot"], "x_dot"),
        (["dx", "xdot"], "xdot"),
        (["t", "x", "Vx", "v_x"], None),
    ],
)
def test_find_velocity_pattern_order(columns, expected):
    assert column_roles.find_velocity("x", columns) == expected


@pytest.mark.parametrize(
    ("columns", "exclude", "expected"),
    [
        (["t", "x", "y", "vx", "vy"], {"t"}, [("x", "vx"), ("y", "vy")]),
        (["x", "dx", "ddx"], set(), [("x", "dx")]),
        (["dx", "ddx", "x"], set(), [("x", "dx")]),
        (["x", "vx", "vvx", "vvvx"], set(), [("x", "vx")]),
        (["trajectory", "t", "u2", "u1", "v1", "du2"], {"t", "trajectory"},
         [("u2", "du2"), ("u1", "v1")]),
        (["t", "q1", "q2", "q1_dot", "q2dot"], {"t"}, [("q1", "q1_dot"), ("q2", "q2dot")]),
        (["t", "dt", "x", "vx"], {"t"}, [("x", "vx")]),
        (["", "v", "x"], set(), []),
        (["t", "x", "y"], {"t"}, []),
        (["x", "vx"], {"vx"}, []),
        (["x", "vx"], {"x"}, []),
        (["theta", "dtheta", "omega"], set(), [("theta", "dtheta")]),
    ],
)
def test_find_coordinates(columns, exclude, expected):
    assert column_roles.find_coordinates(columns, exclude=exclude) == expected


def test_find_coordinates_does_not_give_one_velocity_twice():
    # 'vx_dot' is both vx's velocity (by {}_dot) and x_dot's (by v{}).
    found = column_roles.find_coordinates(["vx", "x_dot", "vx_dot"], exclude=())
    assert found == [("vx", "vx_dot")]


PENG = (["u1", "u2"], ["v1", "v2"])


@pytest.mark.parametrize(
    ("columns", "mapping", "expected"),
    [
        (["t", "u1", "u2", "v1", "v2"], None, ["u1", "u2", "v1", "v2"]),
        (["t", "v2", "u2", "u1", "v1"], None, ["u1", "u2", "v1", "v2"]),
        (["t", "u1", "u2", "vu1", "u2_dot"], None, ["u1", "u2", "vu1", "u2_dot"]),
        (["t", "u1", "u2", "du1", "u2dot", "v1"], None, ["u1", "u2", "v1", "u2dot"]),
        (["p", "q", "a", "b"], {"u1": "p", "u2": "q", "v1": "a", "v2": "b"}, ["p", "q", "a", "b"]),
        (["pos1", "u2", "vpos1", "v2"], {"u1": "pos1"}, ["pos1", "u2", "vpos1", "v2"]),
        (["pos1", "u2", "pos1_dot", "v2"], {"u1": "pos1"}, ["pos1", "u2", "pos1_dot", "v2"]),
        (["pos1", "u2", "du1", "dpos1", "v2"], {"u1": "pos1"}, ["pos1", "u2", "du1", "v2"]),
        (["u1", "u2", "v1", "v2", "w"], {"v2": "w"}, ["u1", "u2", "v1", "w"]),
        (["u1", "u2", "v1", "v2"], {"u1": "u2", "u2": "u1"}, ["u2", "u1", "v1", "v2"]),
    ],
)
def test_resolve_columns(columns, mapping, expected):
    resolved = column_roles.resolve_columns(columns, *PENG, mapping=mapping, source="data.csv")
    assert resolved == dict(zip(["u1", "u2", "v1", "v2"], expected, strict=True))
    assert list(resolved) == ["u1", "u2", "v1", "v2"]


def test_resolve_unknown_mapping_key():
    with pytest.raises(
        UsageError,
        match=r"^--columns: 'z' is not a coordinate or velocity of the model \(u1, u2, v1, v2\)$",
    ):
        column_roles.resolve_columns(["u1", "u2", "v1", "v2"], *PENG, mapping={"z": "u1"},
                                     source="d")


def test_resolve_mapped_column_missing():
    with pytest.raises(DataError, match=r"^data.csv: no column 'pos9' \(given for 'u1' by"):
        column_roles.resolve_columns(
            ["u1", "u2", "v1", "v2"], *PENG, mapping={"u1": "pos9"}, source="data.csv"
        )


def test_resolve_missing_velocity_lists_what_was_looked_for():
    with pytest.raises(
        DataError,
        match=r"^data.csv: no column for velocity 'v2' of coordinate 'u2' "
        r"\(looked for v2, vu2, u2_dot, u2dot, du2\); map it with --columns v2=COL, or "
        r"derive velocities with --velocity savgol$",
    ):
        column_roles.resolve_columns(["t", "u1", "u2", "v1"], *PENG, source="data.csv")


def test_resolve_missing_velocity_of_mapped_coordinate():
    with pytest.raises(
        DataError,
        match=r"\(looked for v1, vu1, u1_dot, u1dot, du1, vp, p_dot, pdot, dp\); map it",
    ):
        column_roles.resolve_columns(["p", "u2", "v2"], *PENG, mapping={"u1": "p"},
                                     source="data.csv")


def test_resolve_missing_coordinate():
    with pytest.raises(
        DataError, match=r"^data.csv: no column for coordinate 'u2' \(columns: t, u1, v1, v2\)$"
    ):
        column_roles.resolve_columns(["t", "u1", "v1", "v2"], *PENG, source="data.csv")


@pytest.mark.parametrize(
    ("mapping", "message"),
    [
        ({"u1": "u2"}, "column 'u2' is used for both 'u1' and 'u2'"),
        ({"v1": "u1"}, "column 'u1' is used for both 'u1' and 'v1'"),
        ({"v1": "v2"}, "column 'v2' is used for both 'v1' and 'v2'"),
    ],
)
def test_resolve_two_names_one_column(mapping, message):
    with pytest.raises(DataError, match=f"^data.csv: {message}$"):
        column_roles.resolve_columns(["u1", "u2", "v1", "v2"], *PENG, mapping=mapping,
                                     source="data.csv")


@pytest.mark.parametrize(
    ("columns", "time", "trajectory"),
    [
        (["t", "x"], "t", None),
        (["time", "x", "trajectory"], "time", "trajectory"),
        (["time", "t"], "t", None),
        (["T", "Time", "traj"], "T", None),   # any case (issue 18)
        (["x", "Time [ms]"], "Time [ms]", None),
        (["timestamp", "x"], None, None),   # no unit: said in a warning, not taken
    ],
)
def test_default_columns(columns, time, trajectory):
    assert column_roles.default_time_column(columns) == time
    assert column_roles.default_trajectory_column(columns) == trajectory


# ---------------------------------------------------------------------------------------------
# Option values


def test_parse_mapping():
    assert options.parse_mapping(" x = pos1 ,vx=vel 1", option="--columns") == {
        "x": "pos1",
        "vx": "vel 1",
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x", "'x' is not of the form NAME=COLUMN"),
        ("x=", "'x=' is not of the form NAME=COLUMN"),
        ("=a", "'=a' is not of the form NAME=COLUMN"),
        ("x=a,,y=b", "'' is not of the form NAME=COLUMN"),
        ("x=a,", "'' is not of the form NAME=COLUMN"),
        ("x=a,x=b", "'x' is given twice"),
        ("", "empty value"),
    ],
)
def test_parse_mapping_rejects(text, message):
    with pytest.raises(UsageError, match=f"^--columns: {message}"):
        options.parse_mapping(text, option="--columns")


def test_parse_float_mapping():
    assert options.parse_float_mapping("x=0.01, vx=2e-2,k=-1", option="--noise") == {
        "x": 0.01,
        "vx": 0.02,
        "k": -1.0,
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("k=abc", "'k=abc': 'abc' is not a number"),
        ("k=nan", "'k=nan': 'nan' is not a finite number"),
        ("k=-inf", "'k=-inf': '-inf' is not a finite number"),
        ("k=1,k=2", "'k' is given twice"),
        ("k", "'k' is not of the form NAME=NUMBER"),
    ],
)
def test_parse_float_mapping_rejects(text, message):
    with pytest.raises(UsageError, match=f"^--fix: {message}$"):
        options.parse_float_mapping(text, option="--fix")


# ---------------------------------------------------------------------------------------------
# Properties and imports


@settings(
    max_examples=50, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    prefix=st.sampled_from([b"", b"PAR1", b"t,x\n", b"# hamid: {}\nt\tx\n0\t", b"\xef\xbb\xbf"]),
    data=st.binary(max_size=600),
    suffix=st.sampled_from([".csv", ".tsv", ".parquet", ".dat"]),
)
def test_random_bytes_give_a_table_or_a_data_error(tmp_path, prefix, data, suffix):
    path = tmp_path / f"random{suffix}"
    path.write_bytes(prefix + data)
    try:
        table, metadata = hio.read_table(path)
    except DataError as exc:
        assert str(exc).startswith(str(path))
        return
    assert isinstance(table, pd.DataFrame)
    assert len(table) > 0
    assert metadata is None or isinstance(metadata, dict)
    for column in table.columns:
        try:
            values = hio.numeric_column(table, column, source=str(path))
        except DataError:
            continue
        assert values.dtype == np.float64
        assert np.isfinite(values).all()


def test_importing_io_loads_neither_pandas_nor_pyarrow():
    code = (
        "import sys, hamid.data.readers; "
        "print(sorted(m for m in ('pandas', 'pyarrow', 'numpy') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(("damping", "kinds"), [
    (None, ()), ("none", ()), ([], ()), ("viscous, coulomb", ("viscous", "coulomb")),
    (["quadratic"], ("quadratic",))])
def test_parse_damping_none_and_lists(damping, kinds):
    """None is no damping, as "none" and [] are (the Python API's callers pass it)."""
    assert options.parse_damping(damping) == kinds
