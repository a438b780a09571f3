"""Outputs never destroy anything (issue 24, "Data loss"; issue 25, "Standard streams").

Each case runs the command line in a real process, with the files, FIFOs, symlinks, devices
and resource limits made in a temporary folder, and checks what a user would see: the exit
status, one line on standard error naming what is wrong, nothing on standard output, every
input and existing output byte for byte as it was, special files still special, and no
temporary file left behind.

- An output that is one of the inputs (the same file through ``..``, a symlink or a hard
  link) is refused before anything is read or written.
- Devices, FIFOs and descriptors (``/dev/stdout``) are written in place; a symlink to a
  regular file (or to nothing) is itself replaced atomically, never written through.
- A read-only output file is refused, as cp refuses it (as root, the command runs as user
  nobody, whom the permissions bind).
- SIGTERM, SIGHUP and SIGQUIT are handled as Ctrl-C is: no temporary file, exit 128 + N.
- A full disk (a file-size limit) while writing: one line, exit 1, nothing half-written.
- Temporary names are short: a 250-character output name works.

The real /dev/null and /dev/stdout are only ever written by an unprivileged user: run as
root, a regression could replace them.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import Readiness, duffing_system, one_line_error, snapshot

from hamid.cli.app import cli
from hamid.data import readers, writing

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX files, signals and limits")

ROOT = Path(__file__).resolve().parents[2]
DUFFING_CSV = ROOT / "sample_data" / "duffing.csv"
DUFFING_TOML = ROOT / "sample_data" / "duffing.toml"
PRECIOUS = b"precious,bytes\n1,2\n"
IS_ROOT = os.geteuid() == 0
NOBODY = 65534

SYSTEM = duffing_system(t_end="20.0", dt="0.01")

# The child process: optional warm-up run (as root, so that every module is loaded while
# root may still read it), commands whose work must not start, then the command line,
# perhaps as user nobody.
CHILD = r"""
import contextlib, io, json, os, sys
spec = json.loads(sys.argv[1])
import hamid.api, hamid.cli.app
# what the checks before the work load, while root may still read it
import codecs, decimal, errno, tempfile
import hamid.data.readers, hamid.report.formats, hamid.result.fit_result
with contextlib.suppress(ImportError):
    import hamid.data.writing
if spec["warm"]:
    # a warm-up that fails ends the child with its traceback: the test shows why
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        hamid.cli.app.cli.main(args=spec["warm"], prog_name="hamid", standalone_mode=False)
import hamid.simulation
for name in spec["stub"]:
    setattr(hamid.api if name == "fit" else hamid.simulation, name,
            lambda *a, **k: os._exit(99))
if spec["patch"]:
    exec(spec["patch"])
if spec["nobody"]:
    os.setgroups([])
    os.setgid(65534)
    os.setuid(65534)
sys.argv = ["hamid", *spec["args"]]
hamid.cli.app.main()
"""


@pytest.fixture(autouse=True)
def _in_a_temporary_folder(tmp_path, monkeypatch):
    """Every process starts in a folder of its own: nothing lands in the repository."""
    monkeypatch.chdir(tmp_path)


def _default_signals():
    """As at a terminal: a test run in the background ignores SIGINT and SIGQUIT, and its
    children would inherit that."""
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):
        signal.signal(getattr(signal, name), signal.SIG_DFL)


def command(args, *, warm=(), stub=(), patch="", nobody=False):
    spec = {"args": [str(a) for a in args], "warm": [str(a) for a in warm],
            "stub": list(stub), "patch": patch, "nobody": nobody}
    return [sys.executable, "-c", CHILD, json.dumps(spec)]


def run(args, *, cwd=None, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, limits=(),
        before=None, timeout=600, **spec):
    """Run the command line in a real process; `limits` are (resource, bytes) pairs."""

    def prepare():
        _default_signals()
        for kind, value in limits:
            resource.setrlimit(kind, (value, value))
        if before is not None:
            before()

    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "NO_COLOR": "1"}
    return subprocess.run(command(args, **spec), cwd=cwd, stdin=stdin, stdout=stdout,
                          stderr=subprocess.PIPE, preexec_fn=prepare, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def saved_result(tmp_path_factory):
    result = CliRunner().invoke(cli, ["fit", str(DUFFING_CSV), "--method", "energy",
                                      "--format", "json"])
    assert result.exit_code == 0, result.stderr
    return result.stdout


SAMPLE_FILES = ["data.csv", "data.parquet", "model.toml", "other.csv", "result.json",
                "sys.toml"]


@pytest.fixture
def work(tmp_path, saved_result):
    """A folder of inputs: data (CSV, Parquet), a model file, a system file, a result."""
    folder = tmp_path / "work"
    folder.mkdir()
    write_data(folder / "data.csv")
    write_data(folder / "other.csv", rows=300)
    write_data(folder / "data.parquet")
    (folder / "model.toml").write_text('[model]\nbuiltin = "duffing"\n')
    (folder / "sys.toml").write_text(SYSTEM)
    (folder / "result.json").write_text(saved_result)
    return folder


def write_data(path, rows=None):
    """The Duffing sample, with its metadata (which names the model), perhaps shortened."""
    table, metadata = readers.read_table(DUFFING_CSV)
    writing.write_table(table if rows is None else table.head(rows), path, metadata=metadata)
    path.chmod(0o644)


@pytest.fixture
def shared(tmp_path):
    """A folder user nobody can enter and write (as root); else the test's own folder."""
    if not IS_ROOT:
        yield tmp_path
        return
    folder = Path(tempfile.mkdtemp(prefix="hamid-shared-", dir="/tmp"))
    try:
        folder.chmod(0o777)
        yield folder
    finally:
        subprocess.run(["rm", "-rf", str(folder)], check=False)


# ---------------------------------------------------------------------------------------------
# 1. An output that is an input is refused


SAME_FILE = {
    # id: (args, stdin file, option, input named)
    "fit -o the CSV": (["fit", "data.csv", "-o", "data.csv"], None, "-o", "data.csv"),
    "fit -o the Parquet": (["fit", "data.parquet", "-o", "data.parquet"], None, "-o",
                           "data.parquet"),
    "fit -o through ..": (["fit", "data.csv", "-o", "../work/data.csv"], None, "-o",
                          "data.csv"),
    "fit -o a symlink to the data": (["fit", "data.csv", "-o", "link.csv"], None, "-o",
                                     "data.csv"),
    "fit -o a hard link to the data": (["fit", "data.csv", "-o", "hard.csv"], None, "-o",
                                       "data.csv"),
    "fit -o the second data file": (["fit", "other.csv", "data.csv", "-o", "data.csv"], None,
                                    "-o", "data.csv"),
    "fit --residuals the CSV": (["fit", "data.csv", "--residuals", "data.csv"], None,
                                "--residuals", "data.csv"),
    "fit --residuals the Parquet": (["fit", "data.parquet", "--residuals", "./data.parquet"],
                                    None, "--residuals", "data.parquet"),
    "fit -o the model file": (["fit", "data.csv", "--model", "model.toml", "-o", "model.toml"],
                              None, "-o", "model.toml"),
    "fit - from the data file": (["fit", "-", "-o", "data.csv"], "data.csv", "-o",
                                 "standard input"),
    "simulate -o the config": (["simulate", "--config", "sys.toml", "-o", "sys.toml",
                                "--format", "csv"], None, "-o", "sys.toml"),
    "simulate -o a symlink to the config": (["simulate", "--config", "sys.toml", "-o",
                                             "sys-link.toml", "--format", "csv"], None, "-o",
                                            "sys.toml"),
    "report -o the result": (["report", "result.json", "-o", "result.json"], None, "-o",
                             "result.json"),
    "report -o a hard link to the result": (["report", "result.json", "-o", "hard.json"],
                                            None, "-o", "result.json"),
}


@pytest.mark.parametrize(("args", "stdin", "option", "source"), SAME_FILE.values(),
                         ids=SAME_FILE.keys())
def test_an_output_that_is_an_input_is_refused(work, args, stdin, option, source):
    (work / "link.csv").symlink_to("data.csv")
    (work / "sys-link.toml").symlink_to(work / "sys.toml")
    os.link(work / "data.csv", work / "hard.csv")
    os.link(work / "result.json", work / "hard.json")
    before = snapshot(work)
    with open(work / stdin if stdin else os.devnull, "rb") as stream:
        done = run(args, cwd=work, stdin=stream)
    line = one_line_error(done, 2, option, source)
    assert "destroy the input" in line
    assert snapshot(work) == before


def test_residuals_and_report_naming_one_file_through_a_symlink_are_refused(work):
    (work / "out.csv").write_bytes(PRECIOUS)
    (work / "alias.csv").symlink_to("out.csv")
    before = snapshot(work)
    done = run(["fit", "data.csv", "-o", "out.csv", "--residuals", "alias.csv"], cwd=work)
    one_line_error(done, 2, "-o and --residuals", "out.csv")
    assert snapshot(work) == before


def test_writing_beside_the_input_still_works(work):
    done = run(["fit", "data.csv", "--method", "energy", "-o", "data.json"], cwd=work)
    assert done.returncode == 0, done.stderr
    assert json.loads((work / "data.json").read_text())["schema"] == "hamid.fit/1"


# ---------------------------------------------------------------------------------------------
# 2. Devices, FIFOs and descriptors are written in place; symlinks are followed


def _read_fifo_with_cat(fifo):
    return subprocess.Popen(["cat", str(fifo)], stdout=subprocess.PIPE)


def _received(reader):
    try:
        data, _ = reader.communicate(timeout=120)
    except subprocess.TimeoutExpired:  # the FIFO was never opened: no data reached it
        reader.kill()
        data, _ = reader.communicate()
    return data


@pytest.mark.parametrize(("args", "start"), [
    (["simulate", "--config", "sys.toml", "-o", "pipe"], b"# hamid: "),
    (["simulate", "--config", "sys.toml", "-o", "pipe.parquet"], b"PAR1"),
    (["fit", "data.csv", "--method", "energy", "-o", "pipe", "--format", "json"], b"{"),
    (["fit", "data.csv", "--method", "energy", "-o", "out.json", "--residuals", "pipe"],
     b"trajectory,t,"),
    (["report", "result.json", "-o", "pipe"], b"hamid fit"),
], ids=["simulate", "simulate parquet", "fit", "fit --residuals", "report"])
def test_a_fifo_is_written_in_place(work, args, start):
    fifo = work / ("pipe.parquet" if "pipe.parquet" in args else "pipe")
    os.mkfifo(fifo)
    reader = _read_fifo_with_cat(fifo)
    done = run(args, cwd=work)
    data = _received(reader)
    assert done.returncode == 0, done.stderr
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert data.startswith(start), data[:80]
    assert not [name for name in os.listdir(work) if name.endswith(".tmp")]


@pytest.mark.skipif(not IS_ROOT, reason="making a device needs root")
@pytest.mark.parametrize("args", [
    ["simulate", "--config", "sys.toml", "-o", "null"],
    ["fit", "data.csv", "--method", "energy", "-o", "null"],
    ["fit", "data.csv", "--method", "energy", "--residuals", "null", "-o", "out.json"],
    ["report", "result.json", "-o", "null", "--format", "markdown"],
], ids=["simulate", "fit", "fit --residuals", "report"])
def test_a_copy_of_dev_null_stays_a_device(work, args):
    device = os.stat("/dev/null").st_rdev
    os.mknod(work / "null", 0o666 | stat.S_IFCHR, device)
    done = run(args, cwd=work)
    assert done.returncode == 0, done.stderr
    status = os.lstat(work / "null")
    assert stat.S_ISCHR(status.st_mode)
    assert status.st_rdev == device
    assert not [name for name in os.listdir(work) if name.endswith(".tmp")]


def test_a_symlink_to_dev_null_survives(work):
    (work / "nowhere.csv").symlink_to("/dev/null")
    done = run(["simulate", "--config", "sys.toml", "-o", "nowhere.csv"], cwd=work)
    assert done.returncode == 0, done.stderr
    assert os.readlink(work / "nowhere.csv") == "/dev/null"
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize(("target", "args", "start"), [
    ("/proc/self/fd/1", ["simulate", "--config", "sys.toml", "-o", "out"], b"# hamid: "),
    ("/dev/stdout", ["fit", "data.csv", "--method", "energy", "-o", "out", "--format", "json"],
     b"{"),
    ("/dev/fd/1", ["report", "result.json", "-o", "out"], b"hamid fit"),
], ids=["/proc/self/fd/1", "/dev/stdout", "/dev/fd/1"])
def test_a_symlink_to_standard_output_writes_to_it(work, target, args, start):
    (work / "out").symlink_to(target)
    done = run(args, cwd=work)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(start), done.stdout[:80]
    assert os.readlink(work / "out") == target


def test_dev_stdout_appended_to_keeps_what_was_there(work):
    """`-o /dev/stdout >> log`: written through the open descriptor, which appends."""
    (work / "out").symlink_to("/dev/stdout")
    log = work / "log.csv"
    log.write_bytes(b"earlier\n")
    with open(log, "ab") as stream:
        done = run(["simulate", "--config", "sys.toml", "-o", "out"], cwd=work, stdout=stream)
    assert done.returncode == 0, done.stderr
    text = log.read_bytes()
    assert text.startswith(b"earlier\n# hamid: ")
    assert os.readlink(work / "out") == "/dev/stdout"


def test_dev_stdout_as_an_unprivileged_user(shared, saved_result):
    """The common idiom works for everyone (it said "cannot write in folder '/dev'")."""
    (shared / "result.json").write_text(saved_result)
    (shared / "result.json").chmod(0o644)
    warm = ["report", "result.json", "-o", str(shared / "warm.txt")] if IS_ROOT else []
    done = run(["report", "result.json", "-o", "/dev/stdout", "--format", "markdown"],
               cwd=shared, warm=warm, nobody=IS_ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(b"**hamid fit")
    assert os.path.islink("/dev/stdout") or stat.S_ISCHR(os.stat("/dev/stdout").st_mode)


def test_dev_null_as_an_unprivileged_user(shared):
    shutil_copy(SYSTEM, shared / "sys.toml")
    warm = ["simulate", "--config", "sys.toml", "-o", str(shared / "warm.csv")] if IS_ROOT \
        else []
    done = run(["simulate", "--config", "sys.toml", "-o", "/dev/null"], cwd=shared, warm=warm,
               nobody=IS_ROOT)
    assert done.returncode == 0, done.stderr
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def shutil_copy(text, path):
    path.write_text(text)
    path.chmod(0o644)


def test_a_symlink_to_a_file_is_replaced_not_written_through(tmp_path):
    work, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    work.mkdir()
    elsewhere.mkdir()
    (work / "sys.toml").write_text(SYSTEM)
    target = elsewhere / "real.csv"
    target.write_bytes(PRECIOUS)
    target.chmod(0o640)
    (work / "link.csv").symlink_to(target)
    done = run(["simulate", "--config", "sys.toml", "-o", "link.csv"], cwd=work)
    assert done.returncode == 0, done.stderr
    assert not (work / "link.csv").is_symlink()
    assert (work / "link.csv").read_bytes().startswith(b"# hamid: ")
    assert target.read_bytes() == PRECIOUS
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    assert sorted(os.listdir(work)) == ["link.csv", "sys.toml"]
    assert os.listdir(elsewhere) == ["real.csv"]


def test_a_dangling_symlink_is_replaced_and_its_target_not_created(work):
    (work / "link.csv").symlink_to("made.csv")
    done = run(["simulate", "--config", "sys.toml", "-o", "link.csv"], cwd=work)
    assert done.returncode == 0, done.stderr
    assert not (work / "link.csv").is_symlink()
    assert (work / "link.csv").read_bytes().startswith(b"# hamid: ")
    assert not (work / "made.csv").exists()


def test_a_stream_that_fails_leaves_the_files_of_the_same_run_alone(work):
    """all_or_nothing with a device among the outputs: /dev/full (through a symlink) takes
    nothing, so the residuals file is not replaced either."""
    (work / "full.json").symlink_to("/dev/full")
    (work / "res.csv").write_bytes(PRECIOUS)
    before = snapshot(work)
    done = run(["fit", "data.csv", "--method", "energy", "-o", "full.json", "--residuals",
                "res.csv"], cwd=work)
    one_line_error(done, 1, "full.json", "No space left on device")
    assert snapshot(work) == before


def test_a_file_that_fails_sends_nothing_to_the_stream_of_the_same_run(work):
    """The residuals go to a FIFO, the report to a file that outgrows the size limit: the
    FIFO's reader receives nothing (streams are written after every file is complete)."""
    fifo = work / "pipe"
    os.mkfifo(fifo)
    reader = _read_fifo_with_cat(fifo)
    done = run(["fit", "data.csv", "--method", "energy", "--residuals", "pipe", "-o",
                "out.json"], cwd=work, limits=[(resource.RLIMIT_FSIZE, 1_000)])
    # hamid has exited: if it never opened the FIFO, this lets cat's open return
    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
    received = _received(reader)
    one_line_error(done, 1, "out.json", "File too large")
    assert received == b""
    assert sorted(os.listdir(work)) == sorted([*SAMPLE_FILES, "pipe"])


# ---------------------------------------------------------------------------------------------
# 3. A read-only output is refused, as cp refuses it


READ_ONLY = {
    "fit -o": (["fit", "data.csv", "-o", "ro.json"], "ro.json", ["fit"]),
    "fit --residuals": (["fit", "data.csv", "--residuals", "ro.csv"], "ro.csv", ["fit"]),
    "simulate -o": (["simulate", "--config", "sys.toml", "-o", "ro.csv"], "ro.csv",
                    ["simulate_realizations"]),
    "report -o": (["report", "result.json", "-o", "ro.md"], "ro.md", []),
}


@pytest.mark.parametrize(("args", "output", "stub"), READ_ONLY.values(), ids=READ_ONLY.keys())
def test_a_read_only_output_is_refused_before_the_work(shared, saved_result, args, output,
                                                       stub):
    write_data(shared / "data.csv", rows=200)
    shutil_copy(SYSTEM, shared / "sys.toml")
    shutil_copy(saved_result, shared / "result.json")
    (shared / output).write_bytes(PRECIOUS)
    # as root: the file is root's and user nobody runs the command, in a folder where
    # nobody may create files (so a rename could replace it); else a file of one's own
    (shared / output).chmod(0o644 if IS_ROOT else 0o444)
    before = snapshot(shared)
    done = run(args, cwd=shared, stub=stub, nobody=IS_ROOT)
    one_line_error(done, 1, output, "read-only")
    assert snapshot(shared) == before


@pytest.mark.parametrize(("args", "stub"), [
    (["fit", "data.csv", "-o", "locked/out.json"], ["fit"]),
    (["fit", "data.csv", "--residuals", "locked/res.csv"], ["fit"]),
    (["simulate", "--config", "sys.toml", "-o", "locked/out.csv"], ["simulate_realizations"]),
    (["report", "result.json", "-o", "locked/out.md"], []),
], ids=["fit -o", "fit --residuals", "simulate -o", "report -o"])
def test_an_unwritable_folder_is_noticed_before_the_work(shared, saved_result, args, stub):
    """The fit's (or the simulation's) work is replaced by an exit with status 99: a
    refusal must come first (it came only after the whole fit)."""
    write_data(shared / "data.csv", rows=200)
    shutil_copy(SYSTEM, shared / "sys.toml")
    shutil_copy(saved_result, shared / "result.json")
    (shared / "locked").mkdir()
    (shared / "locked").chmod(0o755 if IS_ROOT else 0o555)
    try:
        done = run(args, cwd=shared, stub=stub, nobody=IS_ROOT)
        one_line_error(done, 1, "locked", "Permission denied")
        assert os.listdir(shared / "locked") == []
    finally:
        (shared / "locked").chmod(0o755)


def test_proc_version_is_refused_with_a_true_reason(tmp_path):
    done = run(["fit", DUFFING_CSV, "--method", "energy", "-o", "/proc/version"],
               cwd=tmp_path, stub=["fit"])
    line = one_line_error(done, 1, "/proc/version")
    assert "does not exist" not in line
    assert "does not accept new files" in line or "read-only" in line


# ---------------------------------------------------------------------------------------------
# 4. Termination signals clean up as Ctrl-C does


# pyarrow writes the first bytes of the table and waits; the child announces the write (and
# with it the temporary file and hamid's signal handlers), then the signal comes.
SLOW_WRITE = """
import time
import pyarrow.csv as pacsv

def slow(table, stream, **kwargs):
    stream.write(b"trajectory,t,x,v\\n1,0,")
    stream.flush()
    time.sleep(3600)

pacsv.write_csv = slow
"""


def _start(args, *, cwd, readiness, patch, before=None):
    """Start the command line; it announces on `readiness` once `patch` reaches its work."""
    def prepare():
        _default_signals()
        if before is not None:
            before()

    return subprocess.Popen(command(args, patch=patch), cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=prepare,
                            pass_fds=(readiness.fd,))


def _finish(process):
    """Its output once it has ended (the timeout only bounds a hang)."""
    try:
        return process.communicate(timeout=600)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()


def _start_writing_slowly(args, *, cwd, readiness, before=None):
    patch = SLOW_WRITE + readiness.announcing("pyarrow.csv.write_csv")
    return _start(args, cwd=cwd, readiness=readiness, patch=patch, before=before)


def _temporaries(folder):
    return [name for name in os.listdir(folder) if name.endswith(".tmp")]


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP", "SIGQUIT"])
@pytest.mark.parametrize("args", [
    ["simulate", "--config", "sys.toml", "-o", "out.csv"],
    ["fit", "data.csv", "--method", "energy", "-o", "report.json", "--residuals", "out.csv"],
], ids=["simulate", "fit --residuals"])
def test_a_termination_signal_while_writing_leaves_no_temporary(work, name, args):
    (work / "out.csv").write_bytes(PRECIOUS)
    (work / "report.json").write_bytes(PRECIOUS)
    before = snapshot(work)
    signum = getattr(signal, name)
    with Readiness() as readiness:
        process = _start_writing_slowly(args, cwd=work, readiness=readiness)
        try:
            readiness.wait()
            assert _temporaries(work), "writing, yet no temporary file"
            process.send_signal(signum)
        finally:
            stdout, stderr = _finish(process)
    assert process.returncode == 128 + signum, stderr
    assert stdout == b""
    assert stderr.decode().strip() == f"terminated by {name}; no output was written"
    assert snapshot(work) == before


def test_a_signal_ignored_by_the_caller_stays_ignored(work):
    """nohup: SIGHUP was ignored when hamid started, and it goes on; SIGTERM still stops it."""
    with Readiness() as readiness:
        process = _start_writing_slowly(
            ["simulate", "--config", "sys.toml", "-o", "out.csv"], cwd=work,
            readiness=readiness, before=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
        try:
            readiness.wait()
            process.send_signal(signal.SIGHUP)
            # both are pending together: left at its default, SIGHUP would kill the process
            # (status -1); handled, it would end it first (129), ignoring SIGTERM
            process.send_signal(signal.SIGTERM)
        finally:
            _, stderr = _finish(process)
    assert process.returncode == 128 + signal.SIGTERM, stderr
    assert stderr.decode().strip() == "terminated by SIGTERM; no output was written"
    assert not (work / "out.csv").exists()
    assert not _temporaries(work)


LONG_SYSTEM = SYSTEM.replace("t_end = 20.0", "t_end = 5000.0")


def test_sigterm_during_a_long_simulation(tmp_path):
    (tmp_path / "long.toml").write_text(LONG_SYSTEM)
    (tmp_path / "out.csv").write_bytes(PRECIOUS)
    with Readiness() as readiness:
        process = _start(["simulate", "--config", "long.toml", "-o", "out.csv"],
                         cwd=tmp_path, readiness=readiness,
                         patch=readiness.announcing("scipy.integrate.solve_ivp"))
        try:
            readiness.wait()
            process.send_signal(signal.SIGTERM)
        finally:
            stdout, stderr = _finish(process)
    assert process.returncode == 143, stderr
    assert stdout == b""
    assert stderr.decode().strip() == "terminated by SIGTERM; no output was written"
    assert (tmp_path / "out.csv").read_bytes() == PRECIOUS
    assert sorted(os.listdir(tmp_path)) == ["long.toml", "out.csv"]


# ---------------------------------------------------------------------------------------------
# 5. A full disk (here a file-size limit) while writing


@pytest.mark.parametrize(("args", "limit", "outputs"), [
    (["simulate", "--config", "sys.toml", "-o", "out.csv"], 20_000, ["out.csv"]),
    (["simulate", "--config", "sys.toml", "-o", "out.parquet"], 4_000, ["out.parquet"]),
    (["simulate", "--config", "sys.toml", "-o", "out.tsv"], 20_000, ["out.tsv"]),
    (["fit", "data.csv", "--method", "energy", "-o", "out.json", "--residuals", "res.csv"],
     20_000, ["out.json", "res.csv"]),
    (["fit", "data.csv", "--method", "energy", "-o", "out.json", "--residuals",
      "res.parquet"], 4_000, ["out.json", "res.parquet"]),
    (["report", "result.json", "-o", "out.json", "--format", "json"], 1_000, ["out.json"]),
], ids=["simulate CSV", "simulate Parquet", "simulate TSV", "fit --residuals CSV",
        "fit --residuals Parquet", "report"])
@pytest.mark.parametrize("existing", [False, True], ids=["new", "replacing"])
def test_a_full_disk_while_writing_a_file(work, args, limit, outputs, existing):
    if existing:
        for output in outputs:
            (work / output).write_bytes(PRECIOUS)
    before = snapshot(work)
    done = run(args, cwd=work, limits=[(resource.RLIMIT_FSIZE, limit)])
    one_line_error(done, 1, "cannot write", "File too large")
    assert snapshot(work) == before


@pytest.mark.parametrize("args", [
    ["simulate", "--config", "sys.toml"],
    ["fit", "data.csv", "--method", "energy", "--format", "json"],
    ["report", "result.json", "--format", "json"],
], ids=["simulate", "fit", "report"])
def test_a_full_disk_while_writing_standard_output(work, args):
    """`hamid simulate ... > out.csv` on a full disk: the file is the shell's, and is left as
    far as it got; the command says why in one line."""
    with open(work / "redirected.csv", "wb") as stream:
        done = run(args, cwd=work, stdout=stream, limits=[(resource.RLIMIT_FSIZE, 1_000)])
    one_line_error(done, 1, "<stdout>: cannot write", "File too large")
    assert not [name for name in os.listdir(work) if name.endswith(".tmp")]


# ---------------------------------------------------------------------------------------------
# 6. Temporary names are short


@pytest.mark.parametrize("length", [250, 255])
def test_a_long_output_name_works(work, length):
    name = "o" * (length - 4) + ".csv"
    done = run(["simulate", "--config", "sys.toml", "-o", name], cwd=work)
    assert done.returncode == 0, done.stderr
    assert (work / name).read_bytes().startswith(b"# hamid: ")
    assert not [entry for entry in os.listdir(work) if entry.endswith(".tmp")]


@pytest.mark.parametrize(("args", "stub"), [
    (["simulate", "--config", "sys.toml", "-o", "{name}.csv"], ["simulate_realizations"]),
    (["fit", "data.csv", "-o", "{name}.json"], ["fit"]),
    (["fit", "data.csv", "--residuals", "{name}.csv"], ["fit"]),
], ids=["simulate -o", "fit -o", "fit --residuals"])
def test_a_name_too_long_is_refused_before_the_work(work, args, stub):
    name = "o" * 252
    before = snapshot(work)
    done = run([a.replace("{name}", name) for a in args], cwd=work, stub=stub)
    one_line_error(done, 1, "File name too long")
    assert snapshot(work) == before
