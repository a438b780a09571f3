"""Readers that never crash, on inputs bounded in time and memory (issue 33, part 2): each
hostile input of the adversarial run gives one line naming what is wrong, in seconds."""

from __future__ import annotations

import builtins
import bz2
import errno
import gzip
import io
import json
import os
import subprocess
import threading
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from helpers import one_line_error

import hamid
from hamid import read_limits
from hamid.cli.app import cli
from hamid.data import documents, input_size
from hamid.data import readers as hio
from hamid.errors import DataError, ModelError
from hamid.model import parsing

ROOT = Path(__file__).parents[2]
DUFFING = ROOT / "sample_data" / "duffing.csv"
DUFFING_LINES = DUFFING.read_bytes().count(b"\n")


def _run(hamid_cli, *args, cwd, stdin=None) -> subprocess.CompletedProcess:
    return subprocess.run([*hamid_cli, *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300, stdin=stdin)


def _energy(nesting: int) -> str:
    """An energy whose last term nests sin `nesting` deep."""
    return "v**2/2 + k*x**2/2 + k3*(" + "sin(" * nesting + "x" + ")" * nesting + ")"


def _model_file(path: Path, energy: str, coordinates: str = '["x"]') -> Path:
    path.write_text(f'[model]\nenergy = "{energy}"\ncoordinates = {coordinates}\n'
                    'velocities = ["v"]\nparameters = ["k", "k3"]\n')
    return path


def _gzip_rows(path: Path, rows: bytes, zeros: int) -> Path:
    """A gzip file of `rows` followed by `zeros` NUL bytes (compressed 1000 to 1)."""
    packer = zlib.compressobj(9, zlib.DEFLATED, 31)
    with open(path, "wb") as stream:
        stream.write(packer.compress(rows))
        for _ in range(zeros >> 20):
            stream.write(packer.compress(bytes(1 << 20)))
        stream.write(packer.flush())
    return path


# ---------------------------------------------------------------------------------------------
# Files that cannot be read, or read forever


def test_an_unreadable_file_is_one_line(monkeypatch, tmp_path):
    """A file the user may not read gave 'internal error (PermissionError)' from the size
    estimate before the read (as root, chmod 000 does not deny reads: open is refused)."""
    data = tmp_path / "secret.csv"
    data.write_bytes(DUFFING.read_bytes())

    def refused(path, *args, **kwargs):
        if os.fspath(path) == str(data):
            raise PermissionError(errno.EACCES, "Permission denied", str(data))
        return builtins.open(path, *args, **kwargs)

    monkeypatch.setattr(hio, "open", refused, raising=False)
    with pytest.raises(DataError, match=r"secret.csv: cannot read: Permission denied$"):
        input_size.decoded_bytes(data)
    done = CliRunner().invoke(cli, ["fit", str(data), "--model", "duffing"])
    one_line_error(done, 1, "secret.csv: cannot read: Permission denied")


def test_a_bzip2_bomb_is_refused_from_its_first_mib(hamid_cli, tmp_path):
    """17 MiB of zeros in 50 bytes of bzip2: an internal IndexError in the sampling, then
    all of it decompressed; now refused from the first MiB, which holds no line."""
    (tmp_path / "zeros.csv.bz2").write_bytes(bz2.compress(bytes(17 << 20)))
    one_line_error(_run(hamid_cli, "fit", "zeros.csv.bz2", "--model", "duffing", cwd=tmp_path),
              1, "zeros.csv.bz2: its first line is longer than 1,048,576 bytes")


@pytest.mark.parametrize("chunks", [[], ["--chunk-rows", "1000"]], ids=["whole", "chunks"])
def test_a_header_of_many_columns_is_refused(hamid_cli, tmp_path, chunks):
    """A header line of 300,000 columns (2 MiB) is refused before any of it is parsed."""
    header = ",".join(f"c{i}" for i in range(300_000)).encode()
    (tmp_path / "wide.csv.gz").write_bytes(gzip.compress(header + b"\n1\n", 1))
    line = one_line_error(_run(hamid_cli, "fit", "wide.csv.gz", "--model", "duffing", *chunks,
                          cwd=tmp_path), 1, "wide.csv.gz: ")
    assert ("line 1 is longer than 1 MiB" if chunks else "first line is longer") in line


def test_nul_bytes_after_the_rows_are_refused_in_chunks(hamid_cli, tmp_path):
    """Rows, then 64 MiB of NUL bytes without a line break: one row longer than a block."""
    rows = b"t,x,v\n" + b"".join(b"%d,1,0\n" % i for i in range(1000))
    _gzip_rows(tmp_path / "nul.csv.gz", rows, 64 << 20)
    one_line_error(_run(hamid_cli, "fit", "nul.csv.gz", "--model", "duffing", "--chunk-rows",
                   "100000", cwd=tmp_path), 1,
              "nul.csv.gz: a row is longer than 6,400,000 bytes, the text read at a time")


def test_text_decompressed_whole_is_bounded(monkeypatch, tmp_path):
    """A small compressed file read in memory decompresses at most READ_BYTES of text."""
    monkeypatch.setattr(read_limits, "READ_BYTES", 1 << 20)
    rows = b"t,x,v\n" + b"".join(b"%d,1,0\n" % i for i in range(1000))
    path = _gzip_rows(tmp_path / "nul.csv.gz", rows, 2 << 20)
    with pytest.raises(DataError, match=r"nul.csv.gz: decompresses to more than 1 MiB"):
        hamid.fit(path, model="duffing", in_memory=True)


def test_the_read_ahead_thread_is_stopped_before_the_error(hamid_cli, tmp_path):
    """An error while pyarrow still read ahead (here NUL bytes, slow to decompress) ended
    in 'Fatal Python error: PyGILState_Release' and exit 134 at the interpreter's exit;
    the reader now reads without calling back into Python and is closed on the error."""
    _gzip_rows(tmp_path / "restart.csv.gz", b"t,x,v\n" + b"0,1,0\n" * 1000, 16 << 20)
    for _ in range(3):
        one_line_error(_run(hamid_cli, "fit", "restart.csv.gz", "--model", "duffing",
                       "--chunk-rows", "262144", cwd=tmp_path), 1,
                  "restart.csv.gz: column 't', row 2: time does not increase")


@pytest.mark.parametrize("chunks", [[], ["--chunk-rows", "100"]], ids=["whole", "chunks"])
def test_skip_rows_past_the_end_is_refused(hamid_cli, chunks):
    """--skip-rows 10000000000 on a 1,200-line file never returned."""
    one_line_error(_run(hamid_cli, "fit", DUFFING, "--skip-rows", "10000000000", *chunks,
                   cwd=ROOT), 1, f"duffing.csv: --skip-rows 10,000,000,000 reaches the end "
              f"of the text ({DUFFING_LINES:,} lines)")


@pytest.mark.parametrize("args", [["fit", "/dev/zero"], ["report", "/dev/zero"],
                                  ["simulate", "--config", "/dev/zero", "-o", "x.csv"]],
                         ids=["data", "report", "config"])
def test_a_device_is_read_up_to_a_bound(monkeypatch, args):
    """/dev/zero as data, report or system file reached 3.7 GB."""
    monkeypatch.setattr(read_limits, "READ_BYTES", 1 << 20)
    done = CliRunner().invoke(cli, args)
    one_line_error(done, 1, "/dev/zero: more than 1 MiB from a device or pipe",
                   "save it to a file")


def test_standard_input_and_a_fifo_are_read_up_to_a_bound(monkeypatch, tmp_path):
    monkeypatch.setattr(read_limits, "READ_BYTES", 1 << 20)
    done = CliRunner().invoke(cli, ["report", "-"], input=b" " * (2 << 20))
    one_line_error(done, 1, "<stdin>: more than 1 MiB from standard input")
    fifo = tmp_path / "data.fifo"
    os.mkfifo(fifo)

    def write() -> None:
        with open(fifo, "wb", buffering=0) as stream, pytest.raises(BrokenPipeError):
            while True:
                stream.write(b"t,x,v\n" * 1000)

    writer = threading.Thread(target=write)
    writer.start()
    done = CliRunner().invoke(cli, ["fit", str(fifo), "--model", "duffing"])
    writer.join(timeout=300)
    one_line_error(done, 1, "data.fifo: more than 1 MiB from a device or pipe")


def test_a_full_temporary_folder_is_one_line(monkeypatch):
    """Standard input spooled to a full disk: ENOSPC from the close was an internal error."""

    class Full(io.BytesIO):
        def close(self) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

    class Stdin:
        buffer = io.BytesIO(b"t,x\n0,1\n")

    monkeypatch.setattr(input_size, "open", lambda *args: Full(), raising=False)
    monkeypatch.setattr("sys.stdin", Stdin())
    with pytest.raises(DataError, match=r"^<stdin>: .*the temporary folder .+ is full; set "
                                        "TMPDIR"), input_size.spooled("-"):
        pass


# ---------------------------------------------------------------------------------------------
# Documents nested too deeply, or with numbers too long


DEEP_JSON = '{"a": ' * 100_000 + "1" + "}" * 100_000
LONG_NUMBER = '{"a": ' + "9" * 5001 + "}"
JSON_PROBLEMS = {"deep": (DEEP_JSON, "not readable JSON: nested too deeply"),
                 "digits": (LONG_NUMBER, "not readable JSON: a number has more than")}


@pytest.mark.parametrize("kind", ["csv", "parquet", "mat"])
@pytest.mark.parametrize("problem", list(JSON_PROBLEMS))
def test_metadata_too_deep_or_too_long_is_one_line(tmp_path, kind, problem):
    """Metadata nested 100,000 deep or with a 5,001-digit integer: internal RecursionError
    and ValueError; now the message `hamid report` gives, through the same reader."""
    text, message = JSON_PROBLEMS[problem]
    frame = pd.DataFrame({"t": [0.0, 0.1], "x": [1.0, 1.0], "v": [0.0, 0.0]})
    path = tmp_path / f"m.{kind}"
    if kind == "csv":
        path.write_text(f"# hamid: {text}\n" + frame.to_csv(index=False))
    elif kind == "parquet":
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pandas(frame, preserve_index=False)
        pq.write_table(table.replace_schema_metadata({b"hamid": text.encode()}), path)
    else:
        import scipy.io

        scipy.io.savemat(path, {**{c: frame[c].to_numpy() for c in frame}, "hamid": text})
    with pytest.raises(DataError, match=f"^{path}: (line 1: )?the hamid metadata: {message}"):
        hio.read_columns(path)
    report = tmp_path / "r.json"
    report.write_text(text)
    with pytest.raises(DataError, match=f"^{report}: {message}"):
        documents.read_json(report)


def test_a_bad_metadata_file_does_not_stop_the_batch(hamid_cli, tmp_path):
    (tmp_path / "deep.csv").write_text(f"# hamid: {DEEP_JSON}\nt,x,v\n0,1,0\n")
    (tmp_path / "good.csv").write_bytes(DUFFING.read_bytes())
    done = _run(hamid_cli, "fit", "deep.csv", "good.csv", "--each", "--model", "duffing",
                "--format", "csv", cwd=tmp_path)
    rows = pd.read_csv(io.StringIO(done.stdout))
    assert set(rows.loc[rows["source"] == "good.csv", "status"]) == {"ok"}
    assert rows.loc[rows["source"] == "deep.csv", "error"].item() == \
        "deep.csv: line 1: the hamid metadata: not readable JSON: nested too deeply"


def test_coordinates_given_as_a_string_are_named(hamid_cli, tmp_path):
    """"coordinates": "theta" said "the name 't' is declared more than once"."""
    meta = {"model": {"name": "pendulum", "energy": "v**2/2 - k*cos(theta)",
                      "coordinates": "theta", "velocities": ["v"], "parameters": ["k"]}}
    t = np.arange(50) * 0.1
    frame = pd.DataFrame({"t": t, "theta": np.cos(t), "v": -np.sin(t)})
    (tmp_path / "p.csv").write_text(f"# hamid: {json.dumps(meta)}\n" +
                                    frame.to_csv(index=False))
    one_line_error(_run(hamid_cli, "fit", "p.csv", cwd=tmp_path), 1,
              "p.csv: metadata model: 'coordinates' must be a list of names, not the string "
              "'theta'")
    _model_file(tmp_path / "m.toml", "v**2/2 + k*x**2/2", coordinates='"x"')
    with pytest.raises(ModelError, match="'coordinates' must be a list of names, not the "
                                         "string 'x'"):
        hamid.load_model(tmp_path / "m.toml")


@pytest.mark.parametrize("value", ["[" * 50_000 + "]" * 50_000,
                                   "{a = " * 5_000 + "1" + "}" * 5_000],
                         ids=["arrays", "inline-tables"])
def test_toml_nested_too_deeply_is_one_line(hamid_cli, tmp_path, value):
    """A system file nested 50,000 deep: RecursionError from tomllib."""
    (tmp_path / "deep.toml").write_text(f'[model]\nbuiltin = "duffing"\nx = {value}\n')
    words = "deep.toml: not readable TOML: arrays or inline tables nested too deeply"
    one_line_error(_run(hamid_cli, "simulate", "--config", "deep.toml", "-o", "o.csv",
                   cwd=tmp_path), 1, words)
    one_line_error(_run(hamid_cli, "fit", DUFFING, "--model", "deep.toml", cwd=tmp_path), 1, words)


# ---------------------------------------------------------------------------------------------
# Energies


def test_nesting_is_bounded_where_sympy_can_take_it(hamid_cli, tmp_path):
    """sin( nested 180 deep (fit) or 150 (a report given to plot) was a RecursionError in
    sympy, under the parser's 500 levels. Just under MAX_NESTING the fit, its trajectory
    refinement and the plot run; just over, one line."""
    most = parsing.MAX_NESTING - 4   # the sum, the product, the bracket and x around the sines
    parsing.parse(_energy(most), None)
    with pytest.raises(ModelError, match=f"nested {parsing.MAX_NESTING + 1} levels deep in "
                                         f"functions, powers and brackets \\(at most "
                                         f"{parsing.MAX_NESTING}\\)"):
        parsing.parse(_energy(most + 1), None)
    # a long sum nests in one level, as sympy adds: 400 terms are fine
    parsing.parse(" + ".join(f"cos({i}*x)" for i in range(1, 401)), None)

    _model_file(tmp_path / "under.toml", _energy(most))
    done = _run(hamid_cli, "fit", DUFFING, "--model", "under.toml", "-o", "r.json",
                cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "r.json").read_text())["method"]["refinement"]["applied"]
    done = _run(hamid_cli, "plot", "r.json", DUFFING, "-o", "r.png", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    panels = sorted(tmp_path.glob("r-*.png"))
    assert len(panels) == 6 and all(panel.stat().st_size > 0 for panel in panels)
    _model_file(tmp_path / "over.toml", _energy(most + 1))
    one_line_error(_run(hamid_cli, "fit", DUFFING, "--model", "over.toml", cwd=tmp_path), 1,
              f"nested {parsing.MAX_NESTING + 1} levels deep")


def test_a_comment_sign_in_an_energy_is_refused(hamid_cli, tmp_path):
    """'#' made Python drop the rest of the energy silently (k3*x**4/4 here)."""
    _model_file(tmp_path / "m.toml", "v**2/2 + k*x**2/2 #+ k3*x**4/4")
    one_line_error(_run(hamid_cli, "fit", DUFFING, "--model", "m.toml", cwd=tmp_path), 1,
              "m.toml: [model]: energy: '#' (character 19) is not allowed in an expression")
