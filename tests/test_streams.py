"""Standard streams, memory and terminals (issue 25, "Standard streams"; issue 24, §3, §4).

- Standard output full (``> /dev/full``) or closed (``>&-``), standard input closed
  (``<&-``), standard error closed (``2>&-``): one line on standard error where there is
  one, a non-zero exit, never a traceback, and never an error message on standard output.
- Parquet is not sent to a terminal.
- Running out of memory is one line that says what was being done and what to try.
- Text from data (column names, trajectory labels, model names, file names, warnings) that
  holds control characters reaches no terminal raw: the table and markdown renderings,
  messages and warnings show them escaped (``\\x1b``); JSON escapes them as JSON does
  (``\\u001b``, C1 controls too); CSV, being data, keeps them exactly, except on a terminal.

Each case runs the command line in a real process, except where a MemoryError is raised
on purpose inside the process.
"""

from __future__ import annotations

import json
import os
import resource
import select
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import hamid_command

from hamid.cli.app import cli

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX descriptors and terminals")

ROOT = Path(__file__).resolve().parents[1]
DUFFING_CSV = ROOT / "sample_data" / "duffing.csv"
DUFFING_TOML = ROOT / "sample_data" / "duffing.toml"
HAMID = hamid_command()
ENV = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "NO_COLOR": "1"}
EVIL = "\x1b]0;owned\x07\x1b[2J\x9b31m\u202e"
SHOWN = "\\x1b]0;owned\\x07\\x1b[2J\\x9b31m\\u202e"


@pytest.fixture(autouse=True)
def _in_a_temporary_folder(tmp_path, monkeypatch):
    """Every process starts in a folder of its own: nothing lands in the repository."""
    monkeypatch.chdir(tmp_path)


def run(args, *, cwd=None, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, close=(), limits=(), timeout=600):
    """Run the command line; `close` lists descriptors the shell closed (`>&-`)."""

    def prepare():
        for kind, value in limits:
            resource.setrlimit(kind, (value, value))
        for fd in close:
            os.close(fd)

    return subprocess.run([*HAMID, *map(str, args)], cwd=cwd, stdin=stdin, stdout=stdout,
                          stderr=stderr, preexec_fn=prepare, timeout=timeout, env=ENV)


def one_line(done, code, *names):
    """A clean failure: the exit status, one line on standard error naming the culprit."""
    stderr = done.stderr.decode()
    assert done.returncode == code, (done.returncode, stderr)
    assert "Traceback" not in stderr
    assert "internal error" not in stderr, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("Error: ")
    for name in names:
        assert name in lines[0], (name, stderr)
    return lines[0]


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    result = CliRunner().invoke(cli, ["fit", str(DUFFING_CSV), "--method", "energy",
                                      "--format", "json"])
    assert result.exit_code == 0, result.stderr
    path = tmp_path_factory.mktemp("result") / "result.json"
    path.write_text(result.stdout)
    return path


COMMANDS = {
    "fit": ["fit", DUFFING_CSV, "--method", "energy"],
    "fit --format json": ["fit", DUFFING_CSV, "--method", "energy", "--format", "json"],
    "simulate": ["simulate", "--config", DUFFING_TOML],
    "report": ["report", "{result}"],
    "report --format markdown": ["report", "{result}", "--format", "markdown"],
    "models": ["models"],
    "models duffing": ["models", "duffing"],
    "--help": ["--help"],
    "fit --help": ["fit", "--help"],
    "--version": ["--version"],
}


def _args(args, result_file):
    return [result_file if a == "{result}" else a for a in args]


# ---------------------------------------------------------------------------------------------
# Standard output full, standard output closed


@pytest.mark.parametrize("args", COMMANDS.values(), ids=COMMANDS.keys())
def test_standard_output_full(args, result_file):
    with open("/dev/full", "wb") as full:
        done = run(_args(args, result_file), stdout=full)
    one_line(done, 1, "<stdout>: cannot write", "No space left on device")


@pytest.mark.parametrize("args", COMMANDS.values(), ids=COMMANDS.keys())
def test_standard_output_closed(args, result_file):
    done = run(_args(args, result_file), stdout=None, close=[1])
    one_line(done, 1, "<stdout>: cannot write", "standard output is closed")


def test_standard_output_closed_is_noticed_before_the_fit(tmp_path):
    """The check comes first: a fit whose report cannot go anywhere does not run."""
    code = ("import os, hamid.api\n"
            "hamid.api.fit = lambda *a, **k: os._exit(99)\n"
            "from hamid.cli.app import main; main()\n")
    done = subprocess.run([sys.executable, "-c", code, "fit", str(DUFFING_CSV)],
                          stdout=None, stderr=subprocess.PIPE, env=ENV, timeout=600,
                          preexec_fn=lambda: os.close(1))
    one_line(done, 1, "standard output is closed")


def test_standard_output_closed_does_not_matter_with_an_output_file(tmp_path):
    out = tmp_path / "report.json"
    done = run(["fit", DUFFING_CSV, "--method", "energy", "-o", out], stdout=None, close=[1])
    assert done.returncode == 0, done.stderr
    assert json.loads(out.read_text())["schema"] == "hamid.fit/1"


# ---------------------------------------------------------------------------------------------
# Standard input closed


@pytest.mark.parametrize("args", [
    ["fit", "-", "--model", "duffing"],
    ["report", "-"],
    ["simulate", "--config", "-"],
], ids=["fit -", "report -", "simulate --config -"])
def test_standard_input_closed(args):
    done = run(args, stdin=None, close=[0])
    one_line(done, 1, "<stdin>", "standard input is closed")
    assert done.stdout == b""


# ---------------------------------------------------------------------------------------------
# Standard error closed: the message has nowhere to go, and must not go to standard output


@pytest.mark.parametrize(("args", "code"), [
    (["fit", "nosuch.csv"], 1),
    (["fit", DUFFING_CSV, "--model", "nosuch"], 2),
    (["simulate", "--config", "nosuch.toml"], 1),
    (["fit", DUFFING_CSV, "--bogus-option"], 2),
], ids=["fit, no such file", "fit, unknown model", "simulate", "usage error"])
def test_standard_error_closed(tmp_path, args, code):
    """The status is the one the message would have come with."""
    done = run(args, cwd=tmp_path, stderr=None, close=[2])
    assert done.returncode == code
    assert done.stdout == b""
    assert os.listdir(tmp_path) == []


def test_standard_error_closed_leaves_the_data_alone(tmp_path):
    """A successful fit with standard error closed: standard output holds the JSON only."""
    done = run(["fit", DUFFING_CSV, "--method", "energy", "--format", "json"], stderr=None,
               close=[2])
    assert done.returncode == 0
    assert json.loads(done.stdout)["schema"] == "hamid.fit/1"


# ---------------------------------------------------------------------------------------------
# Terminals


def run_on_terminal(args, *, cwd=None, timeout=600):
    """Run with standard output on a pseudo-terminal; returns (process, bytes shown)."""
    master, slave = os.openpty()
    try:
        process = subprocess.Popen([*HAMID, *map(str, args)], cwd=cwd, stdin=subprocess.DEVNULL,
                                   stdout=slave, stderr=subprocess.PIPE, env=ENV)
    finally:
        os.close(slave)
    shown = bytearray()
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            exited = process.poll() is not None
            ready, _, _ = select.select([master], [], [], 0.05)
            if ready:
                try:
                    chunk = os.read(master, 1 << 16)
                except OSError:  # the terminal's last writer has gone
                    break
                if not chunk:
                    break
                shown += chunk
            elif exited:  # gone, and nothing left to read
                break
        process.stderr_text = process.stderr.read().decode()
        process.wait(timeout=600)
    finally:
        os.close(master)
        if process.poll() is None:
            process.kill()
            process.wait()
    return process, bytes(shown)


@pytest.mark.parametrize("args", [
    ["simulate", "--config", DUFFING_TOML, "--format", "parquet"],
    ["simulate", "--config", DUFFING_TOML, "-o", "tty.parquet"],
    ["fit", DUFFING_CSV, "--method", "energy", "--residuals", "tty.parquet"],
], ids=["simulate --format parquet", "simulate -o a link to /dev/stdout",
        "fit --residuals a link to /dev/stdout"])
def test_parquet_is_not_written_to_a_terminal(tmp_path, args):
    (tmp_path / "tty.parquet").symlink_to("/dev/stdout")
    code = ("import os, hamid.api, hamid.simulation\n"
            "hamid.api.fit = hamid.simulation.simulate = lambda *a, **k: os._exit(99)\n"
            "from hamid.cli.app import main; main()\n")
    master, slave = os.openpty()
    try:
        done = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=tmp_path,
                              stdin=subprocess.DEVNULL, stdout=slave, stderr=subprocess.PIPE,
                              env=ENV, timeout=600)
    finally:
        os.close(slave)
    try:
        os.set_blocking(master, False)
        try:
            shown = os.read(master, 1 << 16)
        except OSError:
            shown = b""
    finally:
        os.close(master)
    done.stdout = None
    one_line(done, 2, "Parquet", "terminal")
    assert shown == b""


def test_parquet_through_a_pipe_is_fine():
    done = run(["simulate", "--config", DUFFING_TOML, "--format", "parquet"])
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(b"PAR1")


# ---------------------------------------------------------------------------------------------
# Running out of memory


def test_dev_zero_is_refused_within_memory():
    """/dev/zero as data, in 1 GB of address space: a device is read up to a bound and
    refused past it, before memory runs out (it ran out of memory, and the advice to use
    --chunk-rows then refused the device)."""
    done = run(["fit", "/dev/zero"], limits=[(resource.RLIMIT_AS, 1 << 30)])
    line = one_line(done, 1, "/dev/zero: more than 256 MiB from a device or pipe",
                    "save it to a file")
    assert "memory" not in line


@pytest.mark.parametrize(("args", "target", "names"), [
    (["fit", DUFFING_CSV], "fit", ["out of memory while fitting", "duffing.csv",
                                   "--chunk-rows"]),
    (["simulate", "--config", DUFFING_TOML], "simulate_realizations",
     ["out of memory while simulating", "smaller", "t_end"]),
], ids=["fit", "simulate"])
def test_out_of_memory_in_the_work(monkeypatch, args, target, names):
    import hamid.api
    import hamid.simulation

    def exhausted(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(hamid.api if target == "fit" else hamid.simulation, target, exhausted)
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert result.exit_code == 1, result.stderr
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    for name in names:
        assert name in lines[0], (name, lines[0])
    assert "internal error" not in lines[0]


def test_out_of_memory_inside_a_library_error_is_still_out_of_memory(monkeypatch, tmp_path):
    """pyarrow's failed malloc is both a MemoryError and an ArrowException; a reader that
    turns the latter into "not a valid Parquet file" must not hide the former."""
    import pyarrow as pa

    import hamid.api
    from hamid.errors import DataError

    def exhausted(*args, **kwargs):
        try:
            raise pa.ArrowMemoryError("malloc of size 1073741824 failed")
        except pa.ArrowException as exc:
            raise DataError(f"big.parquet: is not a valid Parquet file ({exc})") from exc

    monkeypatch.setattr(hamid.api, "fit", exhausted)
    result = CliRunner().invoke(cli, ["fit", str(DUFFING_CSV)])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "out of memory" in lines[0]
    assert "not a valid Parquet file" not in lines[0]


# ---------------------------------------------------------------------------------------------
# Terminal injection: control characters in text from data


def _no_raw_controls(data: bytes):
    text = data.decode("utf-8")
    for char in ("\x1b", "\x07", "\x9b", "\u202e"):
        assert char not in text, (char, text[:400])


@pytest.fixture
def evil_result(tmp_path, result_file):
    """A saved result whose model name, data file, parameter, labels and warnings hold
    terminal control sequences (ESC ]0; sets the window title, CSI 2J clears the screen,
    U+009B is a one-character CSI, U+202E reverses the text that follows)."""
    result = json.loads(result_file.read_text())
    result["model"]["name"] = f"duffing{EVIL}"
    result["data"]["sources"] = [f"run{EVIL}.csv"]
    result["parameters"][0]["name"] = f"k{EVIL}"
    result["energy_levels"][0]["trajectory"] = f"A{EVIL}"
    result["warnings"] = [f"look here{EVIL}"]
    path = tmp_path / "evil.json"
    path.write_text(json.dumps(result))
    return path


@pytest.mark.parametrize("fmt", ["table", "markdown"])
def test_renderings_show_control_characters_escaped(evil_result, fmt):
    done = run(["report", evil_result, "--format", fmt])
    assert done.returncode == 0, done.stderr
    _no_raw_controls(done.stdout)
    _no_raw_controls(done.stderr)
    text = done.stdout.decode()
    for shown in (f"duffing{SHOWN}", f"run{SHOWN}.csv", f"A{SHOWN}", f"look here{SHOWN}"):
        assert shown in text, (shown, text)


def test_a_markdown_file_shows_control_characters_escaped(evil_result, tmp_path):
    out = tmp_path / "report.md"
    done = run(["report", evil_result, "-o", out])
    assert done.returncode == 0, done.stderr
    _no_raw_controls(out.read_bytes())
    _no_raw_controls(done.stderr)
    assert f"look here{SHOWN}" in done.stderr.decode()


def test_json_keeps_the_text_escaped_as_json(evil_result):
    """JSON is ASCII: ESC is written \\u001b, and the C1 control U+009B \\u009b (which
    ensure_ascii=False would write raw); a reader gets every character back."""
    done = run(["report", evil_result, "--format", "json"])
    assert done.returncode == 0, done.stderr
    _no_raw_controls(done.stdout)
    assert b"\\u001b]0;owned\\u0007" in done.stdout
    assert b"\\u009b31m" in done.stdout
    assert json.loads(done.stdout) == json.loads(evil_result.read_text())
    # the warnings, repeated on standard error, are escaped there
    _no_raw_controls(done.stderr)
    assert f"warning: look here{SHOWN}" in done.stderr.decode()


def test_table_on_a_terminal_shows_control_characters_escaped(evil_result):
    process, shown = run_on_terminal(["report", evil_result])
    assert process.returncode == 0, process.stderr_text
    _no_raw_controls(shown)
    assert f"A{SHOWN}".encode() in shown


def _evil_data(tmp_path):
    """Duffing samples in two trajectories, one of them labelled with control sequences."""
    lines = Path(DUFFING_CSV).read_text().splitlines()
    header = [line for line in lines if not line.startswith("#")][0]
    rows = [line for line in lines if not line.startswith("#")][1:]
    assert header.startswith("trajectory,"), header
    label = f'"B{EVIL}"'
    rows = [(label + row[row.index(","):]) if row.startswith("2,") else row for row in rows]
    path = tmp_path / "data.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def test_trajectory_labels_from_data_are_escaped_in_the_fit_report(tmp_path):
    data = _evil_data(tmp_path)
    done = run(["fit", data, "--model", "duffing", "--method", "energy"])
    assert done.returncode == 0, done.stderr
    _no_raw_controls(done.stdout)
    _no_raw_controls(done.stderr)
    assert f"B{SHOWN}" in done.stdout.decode()


def test_column_names_from_data_are_escaped_in_the_report_and_messages(tmp_path):
    lines = [line for line in Path(DUFFING_CSV).read_text().splitlines()
             if not line.startswith("#")]
    assert lines[0] == "trajectory,t,x,v", lines[0]
    data = tmp_path / "data.csv"
    data.write_text("\n".join([f"trajectory,t,pos{EVIL},v", *lines[1:]]) + "\n")
    done = run(["fit", data, "--model", "duffing", "--method", "energy", "--columns",
                f"x=pos{EVIL}"])
    assert done.returncode == 0, done.stderr
    _no_raw_controls(done.stdout)
    assert f"x=pos{SHOWN}" in done.stdout.decode()
    # the same column, not mapped: the message lists the columns
    done = run(["fit", data, "--model", "duffing"])
    one_line(done, 1, f"pos{SHOWN}")
    _no_raw_controls(done.stderr)


def test_csv_is_data_kept_exactly_through_a_pipe(tmp_path):
    data = _evil_data(tmp_path)
    done = run(["fit", data, "--model", "duffing", "--method", "energy", "--residuals", "-",
                "-o", "report.json"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert f'"B{EVIL}"'.encode() in done.stdout


def test_residuals_to_a_terminal_show_labels_escaped(tmp_path):
    data = _evil_data(tmp_path)
    (tmp_path / "tty.csv").symlink_to("/dev/stdout")
    process, shown = run_on_terminal(["fit", data, "--model", "duffing", "--method",
                                      "energy", "--residuals", "tty.csv", "-o",
                                      "report.json"], cwd=tmp_path)
    assert process.returncode == 0, process.stderr_text
    _no_raw_controls(shown)
    assert f"B{SHOWN}".encode() in shown


def test_model_name_from_a_model_file_is_escaped(tmp_path):
    model = tmp_path / "model.toml"
    escaped = EVIL.encode("unicode_escape").decode().replace("\\x", "\\u00")
    model.write_text(f'[model]\nname = "mine{escaped}"\ncoordinates = ["x"]\n'
                     'velocities = ["v"]\nenergy = "v**2/2 + k*x**2/2 + k3*x**4/4"\n')
    for args in (["fit", DUFFING_CSV, "--model", model, "--method", "energy"],
                 ["models", model]):
        done = run(args)
        assert done.returncode == 0, done.stderr
        _no_raw_controls(done.stdout)
        _no_raw_controls(done.stderr)
        assert f"mine{SHOWN}" in done.stdout.decode()


def test_a_file_name_in_a_message_is_escaped(tmp_path):
    done = run(["fit", f"run{EVIL}.csv"], cwd=tmp_path)
    line = one_line(done, 1, "no such file")
    _no_raw_controls(done.stderr)
    assert f"run{SHOWN}.csv" in line


@pytest.mark.parametrize(("text", "keep", "shown"), [
    ("k\x1b]0;t\x07", "", "k\\x1b]0;t\\x07"),
    ("\x9b2J\x85\x7f", "", "\\x9b2J\\x85\\x7f"),
    ("a\u202eb\u2066c\u2028", "", "a\\u202eb\\u2066c\\u2028"),
    ("two\nlines\tand\r", "", "two\\nlines\\tand\\r"),
    ("two\nlines\tand\r", "\n\t", "two\nlines\tand\\r"),
    ("ζ = 0.5 ± 1e-3, ｋ, naïve", "", "ζ = 0.5 ± 1e-3, ｋ, naïve"),
], ids=["ESC", "C1 and DEL", "bidi and separators", "layout", "layout kept", "text"])
def test_printable_escapes_controls_only(text, keep, shown):
    from hamid.safe_text import printable

    assert printable(text, keep=keep) == shown
