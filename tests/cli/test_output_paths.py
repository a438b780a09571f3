"""No file is lost through a name a command derives (issue 33).

Every file a command writes goes through one check (`hamid.data.writing.Outputs`): the `-o`
output, a figure's panel files (FIG-K-NAME.EXT), `fit --each`'s ``OUT.partial``,
`--residuals`, numbered realizations. None may be an input (through symlinks and hard
links) nor another output of the same command; each is created fresh, replacing a symlink
at its name rather than writing through it. `fit --each` fits each file once, without
entering linked folders, and goes on past any error in one file.

Command-line cases run in a real process and check what a user sees: the exit status, one
line on standard error naming the file, nothing on standard output, and every file and link
of the folder as it was.
"""

from __future__ import annotations

import functools
import glob
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from click.testing import CliRunner
from helpers import hamid_command, one_line_error, snapshot

from hamid.batch import many_files
from hamid.cli.app import cli
from hamid.data import writing
from hamid.errors import DataError, HamidError, UsageError
from hamid.result.fit_result import FitResult

pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX symlinks and hard links")

ROOT = Path(__file__).resolve().parents[2]
DUFFING_CSV = ROOT / "sample_data" / "duffing.csv"
PRECIOUS = b"precious,bytes\n1,2\n"
NOISY_SYSTEM = ('[model]\nbuiltin = "duffing"\n[parameters]\nk = 1.0\nk3 = 0.5\n'
                '[[initial]]\nx = 1.0\nv = 0.0\n[simulate]\nt_end = 2.0\ndt = 0.1\n'
                '[noise]\nrelative = 0.01\n')
MINUTES = 600   # bounds a hang only


def run(args, *, cwd, command=None):
    """The command line in a real process, in `cwd`."""
    env = {**os.environ, "NO_COLOR": "1", "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([*(command or hamid_command()), *map(str, args)], cwd=cwd,
                          stdin=subprocess.DEVNULL, capture_output=True, timeout=MINUTES,
                          env=env)


@pytest.fixture(scope="module")
def saved_result():
    done = CliRunner().invoke(cli, ["fit", str(DUFFING_CSV), "--method", "energy",
                                    "--format", "json"])
    assert done.exit_code == 0, done.stderr
    return done.stdout


@pytest.fixture
def work(tmp_path, saved_result):
    """A folder with the data, its saved fit, a system file and an unrelated file."""
    shutil.copyfile(DUFFING_CSV, tmp_path / "data.csv")
    (tmp_path / "result.json").write_text(saved_result)
    (tmp_path / "sys.toml").write_text(NOISY_SYSTEM)
    (tmp_path / "other.txt").write_bytes(PRECIOUS)
    return tmp_path


# ---------------------------------------------------------------------------------------------
# A derived name that leads to an input is refused before any work


LINKED_TO_AN_INPUT = {
    # id: (args, what names it, derived name, the input it leads to, symlink (else hard))
    "plot: a panel linked to the data": (
        ["plot", "result.json", "data.csv", "-o", "fig.png", "--panels", "1,5"],
        "-o's panel file", "fig-1-energy.png", "data.csv", True),
    "fit --plot: a panel linked to the data": (
        ["fit", "data.csv", "--method", "energy", "-o", "out.json", "--plot", "fig.png"],
        "--plot's panel file", "fig-1-energy.png", "data.csv", True),
    "plot: a panel linked to the report": (
        ["plot", "result.json", "-o", "fig.png"], "-o's panel file", "fig-5-parameters.png",
        "result.json", True),
    "plot: a panel that is a hard link of the report": (
        ["plot", "result.json", "-o", "fig.svg"], "-o's panel file", "fig-6-correlation.svg",
        "result.json", False),
    "fit --each: OUT.partial linked to the data": (
        ["fit", "--each", "data.csv", "--method", "energy", "-o", "out.jsonl"],
        "-o's partial file", "out.jsonl.partial", "data.csv", True),
    "fit --each: OUT.partial a hard link of the data": (
        ["fit", "--each", "data.csv", "--method", "energy", "-o", "out.jsonl"],
        "-o's partial file", "out.jsonl.partial", "data.csv", False),
    "simulate: a realization linked to the system file": (
        ["simulate", "--config", "sys.toml", "--realizations", "2", "-o", "run.csv"],
        "-o's realization file", "run-2.csv", "sys.toml", True),
}


@pytest.mark.parametrize(("args", "label", "derived", "source", "symbolic"),
                         LINKED_TO_AN_INPUT.values(), ids=LINKED_TO_AN_INPUT.keys())
def test_a_derived_name_that_leads_to_an_input_is_refused(work, args, label, derived, source,
                                                          symbolic):
    if symbolic:
        (work / derived).symlink_to(source)
    else:
        os.link(work / source, work / derived)
    before = snapshot(work)
    line = one_line_error(run(args, cwd=work), 2)
    assert line == (f"Error: {label} {derived!r} is the input file {source!r}; writing it "
                    "would destroy the input: choose another output")
    assert snapshot(work) == before


# ---------------------------------------------------------------------------------------------
# Two outputs of one command never share a file


SAME_FILE = {
    # id: (args, what the message names)
    "-o and --plot, PDF": (
        ["fit", "data.csv", "--method", "energy", "--format", "json", "-o", "fig.pdf",
         "--plot", "fig.pdf"], ["-o and --plot name the same file 'fig.pdf'"]),
    "-o and --plot, SVG": (
        ["fit", "data.csv", "--method", "energy", "--format", "json", "-o", "fig.svg",
         "--plot", "fig.svg"], ["-o and --plot name the same file 'fig.svg'"]),
    "-o and a panel of --plot": (
        ["fit", "data.csv", "--method", "energy", "--format", "json", "-o",
         "fig-1-energy.png", "--plot", "fig.png"],
        ["-o and --plot's panel file name the same file 'fig-1-energy.png'"]),
    "-o and a panel of --plot through ..": (
        ["fit", "data.csv", "--method", "energy", "--format", "json", "-o",
         "../{folder}/fig-2-residuals.png", "--plot", "fig.png"],
        ["-o and --plot's panel file name the same file", "fig-2-residuals.png"]),
    "two panels that are one file": (
        ["plot", "result.json", "-o", "fig.png"],
        ["-o's panel file names one file twice: 'fig-5-parameters.png' and "
         "'fig-6-correlation.png'"]),
}


@pytest.mark.parametrize(("args", "words"), SAME_FILE.values(), ids=SAME_FILE.keys())
def test_two_outputs_of_one_command_that_are_one_file_are_refused(work, args, words):
    for name in ("fig.pdf", "fig.svg", "fig-1-energy.png", "fig-2-residuals.png",
                 "fig-5-parameters.png"):
        (work / name).write_bytes(PRECIOUS)
    os.link(work / "fig-5-parameters.png", work / "fig-6-correlation.png")
    before = snapshot(work)
    args = [arg.format(folder=work.name) for arg in args]
    one_line_error(run(args, cwd=work), 2, *words)
    assert snapshot(work) == before


# ---------------------------------------------------------------------------------------------
# A symlink at an output's name is replaced, never written through


def test_fit_each_replaces_a_partial_file_linked_elsewhere_and_leaves_its_target(work):
    (work / "out.jsonl.partial").symlink_to("other.txt")
    (work / "out.jsonl").symlink_to("result.json")   # the output itself: replaced as well
    saved = (work / "result.json").read_bytes()
    done = run(["fit", "--each", "data.csv", "--method", "energy", "-o", "out.jsonl"],
               cwd=work)
    assert done.returncode == 0, done.stderr
    assert done.stdout == b""
    assert (work / "other.txt").read_bytes() == PRECIOUS
    assert (work / "result.json").read_bytes() == saved
    assert not (work / "out.jsonl").is_symlink()
    assert not os.path.lexists(work / "out.jsonl.partial")
    lines = (work / "out.jsonl").read_text().splitlines()
    assert [json.loads(line)["source"] for line in lines] == ["data.csv"]


def test_the_writers_replace_a_symlink_and_never_write_through_it(tmp_path):
    target = tmp_path / "target.txt"
    target.write_bytes(PRECIOUS)
    for name in ("atomic.txt", "fresh.txt"):
        (tmp_path / name).symlink_to(target)
    writing.write_text("report\n", tmp_path / "atomic.txt")
    with writing.create_fresh(tmp_path / "fresh.txt") as stream:
        stream.write(b"record\n")
    assert target.read_bytes() == PRECIOUS
    assert (tmp_path / "atomic.txt").read_text() == "report\n"
    assert (tmp_path / "fresh.txt").read_text() == "record\n"
    assert not any(os.path.islink(tmp_path / name) for name in ("atomic.txt", "fresh.txt"))


def test_a_fresh_file_leaves_the_other_names_of_a_hard_link_alone(tmp_path):
    (tmp_path / "kept.txt").write_bytes(PRECIOUS)
    os.link(tmp_path / "kept.txt", tmp_path / "fresh.txt")
    with writing.create_fresh(tmp_path / "fresh.txt") as stream:
        stream.write(b"record\n")
    assert (tmp_path / "kept.txt").read_bytes() == PRECIOUS
    assert (tmp_path / "fresh.txt").read_text() == "record\n"


# ---------------------------------------------------------------------------------------------
# The check as every file is written: names no command claimed beforehand


def test_a_file_written_inside_outputs_is_checked_against_the_inputs(tmp_path):
    (tmp_path / "data.csv").write_bytes(PRECIOUS)
    (tmp_path / "panel.png").symlink_to("data.csv")
    with writing.Outputs([str(tmp_path / "data.csv")]), \
            pytest.raises(UsageError, match=r"^output '.*panel.png' is the input file "
                                            r"'.*data.csv'; writing it would destroy"):
        writing.write_bytes(b"png", tmp_path / "panel.png")
    with writing.Outputs([str(tmp_path / "data.csv")]), \
            pytest.raises(UsageError, match="panel.png' is the input file"):
        writing.create_fresh(tmp_path / "panel.png")
    assert (tmp_path / "data.csv").read_bytes() == PRECIOUS
    assert os.readlink(tmp_path / "panel.png") == "data.csv"


def test_a_file_written_twice_inside_outputs_is_refused_and_all_or_nothing_keeps_it(tmp_path):
    (tmp_path / "a.json").write_bytes(PRECIOUS)
    (tmp_path / "b").mkdir()
    with pytest.raises(UsageError, match=r"^-o names one file twice: '.*/a.json' and "
                                         r"'.*/b/../a.json'$"), \
            writing.Outputs([]) as outputs, writing.all_or_nothing():
        outputs.claim("-o", str(tmp_path / "a.json"))
        writing.write_text("report", tmp_path / "a.json")
        writing.write_text("figure", tmp_path / "b" / ".." / "a.json")
    assert (tmp_path / "a.json").read_bytes() == PRECIOUS
    assert sorted(os.listdir(tmp_path)) == ["a.json", "b"]


def test_outputs_checks_nothing_once_its_block_ends(tmp_path):
    (tmp_path / "data.csv").write_bytes(PRECIOUS)
    with writing.Outputs([str(tmp_path / "data.csv")]):
        pass
    writing.write_text("new", tmp_path / "data.csv")   # the library's own call: allowed
    assert (tmp_path / "data.csv").read_text() == "new"


# ---------------------------------------------------------------------------------------------
# fit --each: each file once, no linked folder entered


def test_a_glob_through_a_folder_link_loop_fits_each_file_once(work):
    (work / "a" / "b" / "c").mkdir(parents=True)
    shutil.copyfile(DUFFING_CSV, work / "a" / "b" / "run.csv")
    (work / "a" / "b" / "c" / "up").symlink_to("..")
    os.remove(work / "data.csv")
    done = run(["fit", "--each", "**/*.csv", "--method", "energy", "--format", "jsonl"],
               cwd=work)
    assert done.returncode == 0, done.stderr
    sources = [json.loads(line)["source"] for line in done.stdout.decode().splitlines()]
    assert sources == [os.path.join("a", "b", "run.csv")]
    assert done.stderr.decode().strip().splitlines()[-1] == \
        "1 file: 0 failed, 1 fitted, 0 warned"


def test_a_pattern_does_not_enter_a_linked_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("runs/a/run1.csv", "elsewhere/run2.csv"):
        Path(name).parent.mkdir(parents=True)
        Path(name).write_text(name)
    Path("runs/a/linked").symlink_to("../../elsewhere")
    assert many_files.expand_sources(["runs/**/*.csv"]) == ["runs/a/run1.csv"]
    with pytest.raises(DataError, match=r"^runs/\*/\*/\*.csv: no file matches the pattern$"):
        many_files.expand_sources(["runs/*/*/*.csv"])


def test_a_file_named_twice_or_through_links_is_fitted_once(work, monkeypatch):
    monkeypatch.chdir(work)
    os.link("data.csv", "hard.csv")
    Path("link.csv").symlink_to("data.csv")
    shutil.copyfile(DUFFING_CSV, "copy.csv")
    found = many_files.expand_sources(["data.csv", "./data.csv", "hard.csv", "link.csv", "*.csv",
                                  str(work)])
    assert found == ["data.csv", "copy.csv"]


PATTERNS = ["**/*.csv", "*/*.csv", "a/**/x*.csv", "**", ".hidden/*.csv", "**/.h*.csv",
            "a/*/*", "{top}/**/*.csv", "a/**/b/**"]


def _tree():
    """Files and hidden files in folders and hidden folders, in the current folder."""
    for name in ["x1.csv", ".h1.csv", "a/x2.csv", "a/y.csv", "a/b/x3.csv", "a/b/c/x4.csv",
                 "a/.h2.csv", "a/.hidden/x5.csv", ".hidden/x6.csv", ".hidden/deep/x7.csv",
                 "a/b/notes.txt"]:
        Path(name).parent.mkdir(parents=True, exist_ok=True)
        Path(name).write_text(name)   # distinct contents, distinct files


@pytest.mark.parametrize("pattern", PATTERNS)
def test_patterns_match_what_glob_matches_without_links(tmp_path, monkeypatch, pattern):
    """The walk that skips linked folders matches as glob.glob does (hidden names,
    ``**`` at any place, absolute patterns) on a tree without links."""
    monkeypatch.chdir(tmp_path)
    _tree()
    pattern = pattern.format(top=tmp_path)
    expected = sorted(p for p in glob.glob(pattern, recursive=True) if os.path.isfile(p))
    assert expected, pattern
    assert sorted(many_files.expand_sources([pattern])) == expected


@pytest.mark.parametrize("pattern", ["a/*/", "**/"])
def test_a_pattern_of_folders_matches_no_file(tmp_path, monkeypatch, pattern):
    monkeypatch.chdir(tmp_path)
    _tree()
    assert glob.glob(pattern, recursive=True)   # folders only
    with pytest.raises(DataError, match=f"^{re.escape(pattern)}: no file matches the pattern$"):
        many_files.expand_sources([pattern])


# ---------------------------------------------------------------------------------------------
# fit --each goes on past any error in one file


@pytest.mark.parametrize(("error", "words"), [
    (RecursionError("maximum recursion depth exceeded"),
     "internal error (RecursionError: maximum recursion depth exceeded); this is a bug in "
     "hamid"),
    (ValueError("cannot convert float NaN to integer\nsecond line"),
     "internal error (ValueError: cannot convert float NaN to integer); this is a bug in "
     "hamid"),
    (MemoryError(), "out of memory while fitting it"),
], ids=["RecursionError", "ValueError", "MemoryError"])
def test_any_error_in_one_file_is_its_record_and_the_others_are_fitted(work, monkeypatch,
                                                                      error, words):
    real = many_files.fit

    @functools.wraps(real)   # fit_each binds the options to fit's signature
    def fit(source, *args, **kwargs):
        if "bad" in str(source):
            raise error
        return real(source, *args, **kwargs)

    monkeypatch.setattr(many_files, "fit", fit)
    shutil.copyfile(DUFFING_CSV, work / "bad.csv")
    fits = many_files.fit_each([str(work / "bad.csv"), str(work / "data.csv")], jobs=1,
                          method="energy")
    assert isinstance(fits[0], HamidError)
    assert str(fits[0]) == f"{work / 'bad.csv'}: {words}"
    assert isinstance(fits[1], FitResult)


CHILD = textwrap.dedent("""
    import functools, sys
    import hamid.batch.many_files
    from hamid.cli.app import main

    real = hamid.batch.many_files.fit

    @functools.wraps(real)
    def fit(source, *args, **kwargs):
        if "bad" in str(source):
            raise RecursionError("maximum recursion depth exceeded")
        return real(source, *args, **kwargs)

    hamid.batch.many_files.fit = fit
    sys.argv = ["hamid", *sys.argv[1:]]
    main()
""")


def test_the_command_line_records_a_bug_in_one_file_and_fits_the_next(work):
    shutil.copyfile(DUFFING_CSV, work / "bad.csv")
    done = run(["fit", "--each", "bad.csv", "data.csv", "--method", "energy", "--jobs", "1",
                "-o", "out.jsonl"], cwd=work, command=[sys.executable, "-c", CHILD])
    stderr = done.stderr.decode().strip().splitlines()
    assert done.returncode == 1, stderr
    assert done.stdout == b""
    lines = [json.loads(line) for line in (work / "out.jsonl").read_text().splitlines()]
    assert [(line["source"], line["status"]) for line in lines] == [("bad.csv", "error"),
                                                                   ("data.csv", "ok")]
    assert lines[0]["error"] == ("bad.csv: internal error (RecursionError: maximum recursion "
                                 "depth exceeded); this is a bug in hamid")
    assert stderr == [f"error: {lines[0]['error']}", "2 files: 1 failed, 1 fitted, 0 warned"]
