"""Many recordings: `hamid fit --each`, `hamid.fit_each`, the executor, `.partial` output,
`hamid report` of several fits and `hamid simulate --realizations`.

The truth for every batch is a loop of single `hamid.fit` calls on the same files: a batch
changes where and in which order the fits run, never their numbers.
"""

from __future__ import annotations

import csv
import io
import json
import os
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import interrupted

import hamid
from hamid import executor
from hamid.batch import many_files
from hamid.cli.app import cli
from hamid.data import writing
from hamid.errors import DataError, HamidError, UsageError
from hamid.report import comparison

N_FILES = 20
CORRUPT = 7    # the file of the 20 that holds no data
SLOW = 0       # the file with ten times the samples: it ends after later ones
SAME = 1e-12   # a batch's numbers against the loop of single fits


@pytest.fixture(autouse=True)
def _the_same_machine_everywhere(monkeypatch):
    """Every test sees two cores and no Dask scheduler named by the environment, whatever
    machine or CI runs it (a test that wants a scheduler there sets it)."""
    monkeypatch.delenv(executor.SCHEDULER_VARIABLE, raising=False)
    # (added where the system lacks it: hamid then asks it all the same)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)


def _system(x0: float, t_end: float) -> dict:
    return {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
            "initial": [{"x": x0, "v": 0.0}],
            "simulate": {"t_end": t_end, "dt": 0.05}, "noise": {"relative": 0.01}}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """20 recordings, each at its own amplitude and noise; one corrupt, one long."""
    folder = tmp_path_factory.mktemp("runs")
    for k in range(N_FILES):
        path = folder / f"run{k + 1}.csv"
        if k == CORRUPT:
            path.write_text("t,x,v\n")
            continue
        frame = hamid.simulate(_system(0.5 + 0.05 * k, 200.0 if k == SLOW else 20.0), seed=k)
        writing.write_table(frame, str(path), metadata=frame.attrs["hamid"])
    return folder


@pytest.fixture(scope="module")
def sources(runs) -> list[str]:
    return [str(runs / f"run{k + 1}.csv") for k in range(N_FILES)]


@pytest.fixture(scope="module")
def singles(sources) -> list:
    """The truth: one `hamid.fit` per file, in a loop."""
    outcomes = []
    for source in sources:
        try:
            outcomes.append(hamid.fit(source))
        except HamidError as exc:
            outcomes.append(exc)
    return outcomes


def _same_fit(batched, single) -> None:
    """A batch's outcome equals the single fit's: estimates, errors, levels, warnings."""
    if isinstance(single, HamidError):
        assert type(batched) is type(single) and str(batched) == str(single)
        return
    assert batched.data["sources"] == single.data["sources"]
    for mine, theirs in zip(batched.parameters, single.parameters, strict=True):
        assert mine.name == theirs.name
        for key in ("estimate", "stderr", "ci_low", "ci_high"):
            assert getattr(mine, key) == pytest.approx(getattr(theirs, key), rel=SAME, abs=0)
    assert [h.h for h in batched.energy_levels] == pytest.approx(
        [h.h for h in single.energy_levels], rel=SAME)
    assert batched.warnings == single.warnings


def invoke(args, **kwargs):
    return CliRunner().invoke(cli, [str(a) for a in args], prog_name="hamid", **kwargs)


def _fails(result, code: int, *words: str) -> None:
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert isinstance(result.exception, SystemExit), result.exception
    assert result.stdout == ""
    assert "Traceback" not in result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
    for word in words:
        assert word in result.stderr, (word, result.stderr)


# --- the executor -----------------------------------------------------------------------------


def _slower_first(k: int) -> int:
    """Items that end in reverse order: the first sleeps longest."""
    time.sleep(0.05 * (8 - k))
    return k * k


def _fails_on_three(k: int) -> int:
    if k == 3:
        raise ValueError("three")
    return k


@pytest.mark.parametrize("jobs", [1, 2])
def test_ordered_map_keeps_the_order_of_the_items(jobs):
    assert list(executor.ordered_map(_slower_first, range(8),
                                     executor.Workers(jobs=jobs))) == [k * k for k in range(8)]


def test_ordered_map_raises_an_items_error_at_its_turn():
    results = executor.ordered_map(_fails_on_three, range(6), executor.Workers(jobs=2))
    assert [next(results) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(ValueError, match="three"):
        next(results)


def _blas_threads(_: int) -> int:
    from threadpoolctl import threadpool_info

    return max(pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas")


def test_worker_processes_run_blas_on_one_thread():
    """Processes share the cores: BLAS threads in each would wait on each other. This
    process keeps its own."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(2, user_api="blas"):
        assert set(executor.ordered_map(_blas_threads, range(4), executor.Workers(jobs=2))) == {1}
        assert _blas_threads(0) == 2


def test_workers_are_chosen_from_jobs_scheduler_and_the_environment(monkeypatch):
    assert executor.Workers.choose(None, None, 1) == executor.Workers(jobs=1)
    # the cores this process may use, not the machine's
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 2, 5})
    assert executor.Workers.choose(None, None, 500).jobs == 3
    assert executor.Workers.choose(None, None, 2).jobs == 2
    assert executor.Workers.choose(8, None, 3) == executor.Workers(jobs=3)
    monkeypatch.setenv(executor.SCHEDULER_VARIABLE, "tcp://sched:8786")
    assert executor.Workers.choose(None, None, 5).scheduler == "tcp://sched:8786"
    assert executor.Workers.choose(2, None, 5) == executor.Workers(jobs=2)
    with pytest.raises(UsageError, match="--jobs and --scheduler exclude each other"):
        executor.Workers.choose(2, "tcp://a:1", 5)


# --- hamid.fit_each ---------------------------------------------------------------------------


def test_fit_each_in_parallel_equals_a_loop_of_single_fits(runs, sources, singles):
    fits = hamid.fit_each(runs, jobs=2)
    assert fits.sources == tuple(sources)   # the folder, in natural order (run2 before run10)
    assert len(fits) == N_FILES
    for batched, single in zip(fits, singles, strict=True):
        _same_fit(batched, single)
    # the long first file ended last, and its result still came first
    assert fits[SLOW].data["n_samples"] > 5 * fits[1].data["n_samples"]


def test_one_process_and_two_give_the_same_numbers(sources):
    one = hamid.fit_each(sources[8:12], jobs=1)
    two = hamid.fit_each(sources[8:12], jobs=2)
    for a, b in zip(one, two, strict=True):
        assert a.estimates == b.estimates
        assert a.energy_levels == b.energy_levels


def test_to_frame_has_a_row_per_file_and_parameter(sources, singles):
    frame = hamid.fit_each(sources[5:9], jobs=1).to_frame()
    assert list(frame.columns) == list(comparison.ROW_COLUMNS)
    errors = frame[frame.status == "error"]
    assert list(errors.source) == [sources[CORRUPT]]
    assert errors.error.iloc[0] == str(singles[CORRUPT])
    fitted = frame[frame.status == "ok"].set_index(["source", "parameter"])
    for k in (5, 6, 8):
        for p in singles[k].parameters:
            assert fitted.loc[(sources[k], p.name), "estimate"] == pytest.approx(
                p.estimate, rel=SAME)
    assert len(fitted) == 3 * 2


def test_fit_each_checks_its_options_once_before_any_fit(sources):
    with pytest.raises(UsageError, match="unexpected keyword argument 'methd'"):
        hamid.fit_each(sources[:2], methd="energy")
    with pytest.raises(UsageError, match="method must be one of"):
        hamid.fit_each(sources[:2], method="magic")
    with pytest.raises(UsageError, match="'progress'"):
        hamid.fit_each(sources[:2], progress=print)
    with pytest.raises(UsageError, match="--ship-data applies only with --scheduler"):
        hamid.fit_each(sources[:2], ship_data=True, jobs=1)


def test_the_options_reach_every_fit(sources):
    fits = hamid.fit_each(sources[1:3], jobs=2, method="energy", model="duffing")
    for fit, source in zip(fits, sources[1:3], strict=True):
        assert fit.estimates == hamid.fit(source, "duffing", method="energy").estimates
        assert fit.method["kind"] == "energy"


@pytest.mark.parametrize(("pattern", "error", "words"), [
    ("nowhere", DataError, "nowhere: no such file or folder"),
    ("nowhere/*.csv", DataError, "nowhere/*.csv: no file matches the pattern"),
    ("-", UsageError, "standard input"),
])
def test_sources_that_name_nothing_are_refused(pattern, error, words):
    with pytest.raises(error, match=words.replace("*", r"\*")):
        many_files.expand_sources([pattern])


def test_a_folder_without_data_files_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(DataError, match="holds no data files"):
        many_files.expand_sources([tmp_path])


def test_globs_and_folders_expand_in_natural_order(runs):
    (runs / ".hidden.csv").write_text("t,x,v\n")
    try:
        found = many_files.expand_sources([f"{runs}/run1*.csv", runs / "run3.csv"])
        assert [Path(p).name for p in found] == [
            "run1.csv", *(f"run{k}.csv" for k in range(10, 20)), "run3.csv"]
        assert ".hidden.csv" not in {Path(p).name for p in many_files.expand_sources([runs])}
    finally:
        (runs / ".hidden.csv").unlink()


def test_a_url_is_read_where_the_fit_runs(sources, singles):
    """file:// stands for the URLs pyarrow opens (s3://, gs://, hdfs://)."""
    url = Path(sources[2]).as_uri()
    (fit,) = hamid.fit_each([url], jobs=1)
    assert fit.estimates == singles[2].estimates
    assert fit.data["sources"] == [url]
    assert fit.provenance["inputs"][0]["path"] == url
    (missing,) = hamid.fit_each([url + ".gone"], jobs=1)
    assert isinstance(missing, DataError) and f"{url}.gone: cannot read" in str(missing)


# --- hamid fit --each -------------------------------------------------------------------------


def test_one_corrupt_file_among_20_is_one_error_line_and_exit_1(runs, sources, singles):
    result = invoke(["fit", "--each", runs, "--format", "jsonl", "--jobs", "2"])
    assert result.exit_code == 1, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["source"] for line in lines] == sources            # nothing lost, in order
    errors = [line for line in lines if line["status"] == "error"]
    assert errors == [{"source": sources[CORRUPT], "status": "error",
                       "error": str(singles[CORRUPT])}]
    for line, single in zip(lines, singles, strict=True):
        if line["status"] == "ok":
            assert line["schema"] == "hamid.fit/1"
            _same_fit(hamid.result.fit_result.FitResult.from_dict(line), single)
            assert line["provenance"]["command"].startswith("hamid")   # the command line
    stderr = result.stderr.strip().splitlines()
    warned = sum(bool(s.warnings) for s in singles if not isinstance(s, HamidError))
    assert stderr[-1] == f"20 files: 1 failed, 19 fitted, {warned} warned"
    assert stderr[:-1] == [f"error: {singles[CORRUPT]}"]


def test_csv_has_a_row_per_file_and_parameter(sources, singles):
    result = invoke(["fit", "--each", *sources[6:9], "--format", "csv", "--jobs", "1"])
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert list(rows[0]) == list(comparison.ROW_COLUMNS)
    assert [(r["source"], r["parameter"]) for r in rows] == [
        (sources[6], "k"), (sources[6], "k3"), (sources[7], ""), (sources[8], "k"),
        (sources[8], "k3")]
    assert rows[2]["status"] == "error" and rows[2]["error"] == str(singles[CORRUPT])
    for row in rows[:2]:
        (p,) = [p for p in singles[6].parameters if p.name == row["parameter"]]
        assert float(row["estimate"]) == p.estimate          # written in full precision
        assert float(row["ci_high"]) == p.ci_high
        assert row["status"] == "ok" and row["warnings"] == str(len(singles[6].warnings))


def test_the_table_shows_each_file_as_it_is_fitted(sources, singles):
    result = invoke(["fit", "--each", *sources[6:8], "--jobs", "1", "--level", "0.9"])
    assert result.exit_code == 1
    header, first, second, error = result.stdout.splitlines()
    assert header.split() == ["source", "parameter", "estimate", "std.", "error", "90%", "CI",
                              "low", "90%", "CI", "high", "warnings"]
    fit90 = hamid.fit(sources[6], level=0.9)
    assert first.split()[:3] == [sources[6], "k", f"{fit90.estimates['k']:.6g}"]
    assert second.split()[:2] == ["k3", f"{fit90.estimates['k3']:.6g}"]
    assert error.split(None, 1) == [sources[CORRUPT], f"error: {singles[CORRUPT]}"]
    # the table on standard output already shows the error
    warned = int(bool(fit90.warnings))
    assert result.stderr.strip().splitlines() == [f"2 files: 1 failed, 1 fitted, {warned} warned"]


def test_output_file_is_complete_and_no_partial_file_is_left(tmp_path, sources):
    out = tmp_path / "results.jsonl"
    result = invoke(["fit", "--each", *sources[1:4], "-o", out])
    assert result.exit_code == 0 and result.stdout == ""
    assert [json.loads(line)["source"] for line in out.read_text().splitlines()] == \
        sources[1:4]
    assert os.listdir(tmp_path) == ["results.jsonl"]


@pytest.mark.parametrize(("args", "code", "words"), [
    (["fit", "--each", "nowhere/"], 1, ["nowhere/: no such file or folder"]),
    (["fit", "--each", "nowhere/*.csv"], 1, ["no file matches"]),
    (["fit", "--scheduler", "tcp://a:1", "x.csv"], 2,
     ["--scheduler and --ship-data apply only"]),
    (["fit", "--each", "{runs}", "--ship-data"], 2, ["--ship-data applies only with"]),
    (["fit", "--each", "{runs}", "--jobs", "2", "--scheduler", "tcp://a:1"], 2,
     ["exclude each other"]),
    (["fit", "--each", "{runs}", "--format", "json"], 2, ["--format jsonl|csv|table"]),
    (["fit", "--each", "{runs}", "-o", "r.md"], 2, ["not markdown"]),
    (["fit", "{runs}/run2.csv", "--format", "jsonl"], 2, ["needs --each"]),
    (["fit", "--each", "{runs}", "--residuals", "r.csv"], 2, ["--residuals"]),
    (["fit", "--each", "-"], 2, ["standard input"]),
    (["fit", "--each", "{runs}", "-o", "{runs}/no/r.jsonl"], 1, ["does not exist"]),
])
def test_usage_errors_of_fit_each(runs, args, code, words):
    _fails(invoke([a.format(runs=runs) for a in args]), code, *words)


def test_scheduler_without_dask_names_the_extra(runs, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)   # as if not installed
    result = invoke(["fit", "--each", runs, "--scheduler", "tcp://127.0.0.1:8786"])
    _fails(result, 1, "pip install 'hamid[dask]'")


def test_strict_exits_3_when_a_fit_warns(sources):
    # a model without the cubic spring: the fits run, and warn
    result = invoke(["fit", "--each", *sources[1:3], "--model", "poly:1:2", "--columns",
                     "q1=x,v1=v", "--strict", "--format", "csv", "--jobs", "1"])
    assert result.exit_code == 3, result.stderr
    assert result.stderr.strip().splitlines()[-1] == "2 files: 0 failed, 2 fitted, 2 warned"


def test_ctrl_c_keeps_the_finished_fits_in_the_partial_file(runs, tmp_path):
    out = tmp_path / "results.jsonl"
    partial = tmp_path / "results.jsonl.partial"
    # The child holds before writing its third record and says so: Ctrl-C comes with two
    # fits written, whatever the machine's speed (as at a terminal: a test run in the
    # background ignores SIGINT, and its children would inherit that).
    returncode, stdout, stderr = interrupted(
        ["fit", "--each", str(runs), "-o", str(out), "--jobs", "2"],
        "hamid.report.comparison.record", call=3, hold=True)
    assert returncode == 130, stderr
    assert not out.exists() and stdout == ""
    lines = [json.loads(line) for line in partial.read_text().splitlines()]
    assert [line["source"] for line in lines] == [str(runs / "run1.csv"), str(runs / "run2.csv")]
    assert stderr.strip().splitlines()[-1] == f"interrupted; the 2 finished fits are in {partial}"


# --- Dask -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip(
        "distributed", reason="dask[distributed] is not installed (pip install 'hamid[dask]')")
    import dask

    # a busy machine starts processes slowly: minutes, which only bound a hang
    with dask.config.set({"distributed.comm.timeouts.connect": "600s"}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                     dashboard_address=None, death_timeout=600) as local:
        yield local


@pytest.fixture
def scheduler(cluster, monkeypatch) -> str:
    """The cluster's address, which hamid's client waits minutes for, not seconds."""
    monkeypatch.setattr(executor, "_CONNECT_TIMEOUT", 600)
    return cluster.scheduler_address


@pytest.mark.parametrize("ship_data", [False, True])
def test_a_dask_cluster_gives_the_local_results(scheduler, sources, singles, ship_data):
    fits = hamid.fit_each(sources[:10], scheduler=scheduler,
                          ship_data=ship_data)
    for batched, single in zip(fits, singles[:10], strict=True):
        _same_fit(batched, single)
    assert fits[2].provenance["inputs"][0]["path"] == sources[2]


def test_fit_each_on_the_cluster_named_by_the_environment(scheduler, sources, monkeypatch):
    monkeypatch.setenv(executor.SCHEDULER_VARIABLE, scheduler)
    result = invoke(["fit", "--each", *sources[1:3], "--format", "csv"])
    assert result.exit_code == 0, result.stderr
    assert [r["source"] for r in csv.DictReader(io.StringIO(result.stdout))] == [
        sources[1], sources[1], sources[2], sources[2]]


@pytest.fixture
def closed_port():
    """A local port nothing listens on: bound (so that no one else takes it) and never
    listening, so a connection is refused at once."""
    with socket.socket() as bound:
        bound.bind(("127.0.0.1", 0))
        yield bound.getsockname()[1]


def test_an_unreachable_scheduler_is_one_line(runs, monkeypatch, closed_port):
    pytest.importorskip("distributed", reason="dask[distributed] is not installed")
    monkeypatch.setattr(executor, "_CONNECT_TIMEOUT", 1)
    address = f"tcp://127.0.0.1:{closed_port}"
    _fails(invoke(["fit", "--each", runs, "--scheduler", address]), 1,
           f"--scheduler {address}: cannot connect")


# --- hamid report of several fits ------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(tmp_path_factory, sources) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("saved")
    paths = {"a": folder / "a.json", "b": folder / "b.json", "lines": folder / "r.jsonl"}
    for name, k in (("a", 1), ("b", 2)):
        assert invoke(["fit", sources[k], "-o", paths[name]]).exit_code == 0
    assert invoke(["fit", "--each", *sources[6:9], "-o", paths["lines"]]).exit_code == 1
    return paths


def test_report_shows_a_column_per_source(saved, singles, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")   # wide enough for the tmp paths side by side
    result = invoke(["report", saved["a"], saved["b"]])
    assert result.exit_code == 0, result.stderr
    lines = result.stdout.splitlines()
    header = next(line for line in lines if line.startswith("parameter"))
    assert header.split() == ["parameter", str(saved["a"]), str(saved["b"])]
    row = next(line for line in lines if line.startswith("k "))
    a, b = (singles[k].parameters[0] for k in (1, 2))
    assert row.split() == ["k", f"{a.estimate:.6g}", "±", f"{a.stderr:.2g}",
                           f"{b.estimate:.6g}", "±", f"{b.stderr:.2g}"]


def test_report_of_fit_each_lines_keeps_the_error(saved, sources, singles):
    result = invoke(["report", saved["lines"], "--format", "markdown"])
    assert result.exit_code == 0, result.stderr
    text = result.stdout
    assert f"| parameter | {sources[6]} | {sources[7]} | {sources[8]} |" in text
    k3 = singles[8].parameters[1]
    assert f"| k3 | {singles[6].parameters[1].estimate:.6g} ± " in text
    assert f"| error | {k3.estimate:.6g} ± {k3.stderr:.2g} |" in text
    assert f"- error: {singles[CORRUPT]}" in text


def test_report_of_several_as_csv_and_jsonl(saved, sources):
    rows = list(csv.DictReader(io.StringIO(invoke(["report", saved["a"], saved["lines"],
                                                   "--format", "csv"]).stdout)))
    assert [r["source"] for r in rows] == [str(saved["a"])] * 2 + [sources[6]] * 2 + [
        sources[7]] + [sources[8]] * 2
    lines = invoke(["report", saved["lines"], "--format", "jsonl"]).stdout.splitlines()
    assert [json.loads(line) for line in lines] == [
        json.loads(line) for line in saved["lines"].read_text().splitlines()]


def test_report_refuses_json_for_several_and_a_bad_line(saved, tmp_path):
    _fails(invoke(["report", saved["a"], saved["b"], "--format", "json"]), 2,
           "--format json shows one fit")
    bad = tmp_path / "bad.jsonl"
    bad.write_text(saved["lines"].read_text() + "{not json\n")
    _fails(invoke(["report", bad]), 1, f"{bad}, line 4: not valid JSON")
    tampered = tmp_path / "tampered.jsonl"
    line = json.loads(saved["lines"].read_text().splitlines()[0])
    line["method"]["level"] = 5
    tampered.write_text(json.dumps(line) + "\n")
    _fails(invoke(["report", tampered]), 1, f"{tampered}, line 1", "method.level")


# --- hamid simulate --realizations -----------------------------------------------------------


def test_realizations_are_the_records_of_consecutive_seeds(tmp_path):
    config = tmp_path / "system.toml"
    config.write_text('[model]\nbuiltin = "duffing"\n[parameters]\nk = 1.0\nk3 = 0.5\n'
                      '[[initial]]\nx = 1.0\nv = 0.0\n[simulate]\nt_end = 5.0\ndt = 0.05\n'
                      '[noise]\nrelative = 0.01\n')
    result = invoke(["simulate", "--config", config, "--realizations", "12", "--seed", "40",
                     "-o", tmp_path / "mc.csv"])
    assert result.exit_code == 0, result.stderr
    names = sorted(p.name for p in tmp_path.glob("mc-*.csv"))
    assert names == [f"mc-{k:02d}.csv" for k in range(1, 13)]
    for k in (1, 12):
        alone = tmp_path / f"alone{k}.csv"
        invoke(["simulate", "--config", config, "--seed", 39 + k, "-o", alone])
        assert (tmp_path / f"mc-{k:02d}.csv").read_text() == alone.read_text()
    first, last = (hamid.data.readers.read_table(str(tmp_path / n))[0]
                   for n in ("mc-01.csv", "mc-12.csv"))
    assert np.array_equal(first.t, last.t) and not np.array_equal(first.x, last.x)


def test_realizations_need_noise_and_a_file(tmp_path):
    config = tmp_path / "clean.toml"
    config.write_text('[model]\nbuiltin = "duffing"\n[parameters]\nk = 1.0\nk3 = 0.5\n'
                      '[[initial]]\nx = 1.0\nv = 0.0\n[simulate]\nt_end = 2.0\ndt = 0.1\n')
    _fails(invoke(["simulate", "--config", config, "--realizations", "3", "-o",
                   tmp_path / "r.csv"]), 1, f"{config}: realizations differ only by their "
           "noise")
    assert list(tmp_path.glob("r*.csv")) == []
    _fails(invoke(["simulate", "--config", config, "--realizations", "3"]), 2, "give -o FILE")
