"""Fits of files read in chunks (hamid.linear.chunked) against the same fits with the data in
memory.

Standard streams, memory and terminals (issue 25, "Standard streams"; issue 24, §3, §4).

- Standard output full (``> /dev/full``) or closed (``>&-``), standard input closed
  (``<&-``), standard error closed (``2>&-``): one line on standard error where there is
  one, a non-zero exit, never a traceback, and never an error message on standard output.
- Parquet is not sent to a terminal.
- Running out of memory is one line that says what was being done and what to try.
- Text from data (column names, trajectory labels, model names, file names, warnings) that
  holds control characters reaches no terminal raw: the table and markdown renderings,
  messages and warnings show them escaped (``\x1b``); JSON escapes them as JSON does
  (``\u001b``, C1 controls too); CSV, being data, keeps them exactly, except on a terminal.

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

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from conftest import PENG, with_noise
from helpers import hamid_command

import hamid
from hamid import options
from hamid.cli.app import cli
from hamid.data import input_size, loading, measurement, readers, writing
from hamid.data.records import Records
from hamid.errors import DataError, UsageError
from hamid.linear import chunked, design, estimate, plan
from hamid.result import validation
from hamid.result.fit_result import FitResult


@pytest.fixture(scope="module")
def noisy_files(clean_records, tmp_path_factory):
    """Noisy peng-quadratic records (3 trajectories) as Parquet and CSV files."""
    frame = with_noise(clean_records["peng-quadratic"], 0.01, seed=5)
    folder = tmp_path_factory.mktemp("stream")
    paths = {}
    for suffix in ("parquet", "csv"):
        paths[suffix] = str(folder / f"peng.{suffix}")
        writing.write_table(frame, paths[suffix], metadata=frame.attrs["hamid"])
    return frame, paths


@pytest.fixture(autouse=True)
def linear_fits_in_memory(monkeypatch):
    """The fits in memory here stop where a chunked fit stops: before the trajectory
    refinement, which needs the data in memory (tested in test_trajectory.py)."""
    obstacle = plan.refinement_obstacle
    monkeypatch.setattr(plan, "refinement_obstacle", lambda options, size=None: obstacle(
        options, size) or plan.CHUNKED_NOT_REFINED)


def test_chunked_auto_fits_say_they_are_not_refined(noisy_files):
    _, paths = noisy_files
    streamed = hamid.fit(paths["parquet"], chunk_rows=1000)
    assert streamed.method["refinement"] == {"applied": False,
                                                     "reason": plan.CHUNKED_NOT_REFINED}
    assert "not refined" in streamed.method["kind_reason"]


def _compare(memory, streamed):
    names = list(memory.estimates)
    assert list(streamed.estimates) == names
    theta = np.array([memory.estimates[n] for n in names])
    np.testing.assert_allclose([streamed.estimates[n] for n in names], theta, rtol=1e-10)
    stderr = [np.nan if p.stderr is None else p.stderr for p in memory.parameters]
    np.testing.assert_allclose([np.nan if p.stderr is None else p.stderr
                                for p in streamed.parameters], stderr, rtol=1e-9)
    np.testing.assert_allclose([h.h for h in streamed.energy_levels],
                               [h.h for h in memory.energy_levels], rtol=1e-10)
    assert [h.n_samples for h in streamed.energy_levels] == \
        [h.n_samples for h in memory.energy_levels]
    # the chunked fit takes the blocks' variances from their triangular factors, and the
    # quadrature's error from sums fed chunk by chunk
    def without_variances(method):
        return {key: value for key, value in method.items()
                if key not in ("block_variance", "discretization")}

    assert without_variances(streamed.method) == without_variances(memory.method)
    terms = streamed.method["discretization"], memory.method["discretization"]
    assert terms[0] == (None if terms[1] is None else pytest.approx(terms[1], rel=1e-8))
    variances = streamed.method["block_variance"], memory.method["block_variance"]
    if variances[1] is None:
        assert variances[0] is None
    else:
        assert variances[0] == pytest.approx(variances[1], rel=1e-10)
    assert streamed.residuals["rms"] == pytest.approx(memory.residuals["rms"], rel=1e-9)
    assert streamed.conditioning["condition_number"] == pytest.approx(
        memory.conditioning["condition_number"], rel=1e-8)
    assert streamed.data["n_samples"] == memory.data["n_samples"]


@pytest.mark.parametrize("method", ["energy", "joint", "weak", "auto"])
@pytest.mark.parametrize("cov", ["hac", "hc", "classical"])
def test_chunked_parquet_equals_the_fit_in_memory(noisy_files, method, cov):
    frame, paths = noisy_files
    memory = hamid.fit(frame, method=method, cov=cov)
    streamed = hamid.fit(paths["parquet"], method=method, cov=cov, chunk_rows=377)
    assert streamed.samples is None
    _compare(memory, streamed)


@pytest.mark.parametrize("method", ["energy", "auto"])
def test_chunked_csv_equals_the_fit_in_memory(noisy_files, method):
    frame, paths = noisy_files
    _compare(hamid.fit(frame, method=method),
             hamid.fit(paths["csv"], method=method, chunk_rows=100))


@pytest.mark.parametrize("method", ["energy", "joint"])
def test_parquet_row_groups_read_one_by_one_equal_the_fit_in_memory(noisy_files, tmp_path,
                                                                   method):
    """Row groups of 250 rows read in chunks of 100: chunks end at every group's end."""
    import pyarrow.parquet as pq

    frame, paths = noisy_files
    grouped = str(tmp_path / "grouped.parquet")
    pq.write_table(pq.read_table(paths["parquet"]), grouped, row_group_size=250)
    assert pq.ParquetFile(grouped).num_row_groups > 3
    _compare(hamid.fit(frame, method=method),
             hamid.fit(grouped, method=method, chunk_rows=100))


def test_the_file_really_passes_in_many_chunks(noisy_files, monkeypatch):
    """Windows straddle the chunk boundaries: each of many chunks is shorter than a window."""
    frame, paths = noisy_files
    sizes = []
    original = readers.TableChunks.chunks

    def counted(self, columns, rows):
        for chunk in original(self, columns, rows):
            sizes.append(len(next(iter(chunk.values()))))
            yield chunk

    monkeypatch.setattr(readers.TableChunks, "chunks", counted)
    streamed = hamid.fit(paths["parquet"], chunk_rows=30)
    assert streamed.method["kind"] == "joint"
    window_samples = streamed.method["weak_window"] / float(np.diff(frame.t)[0])
    assert max(sizes) == 30 < window_samples
    assert sum(sizes) >= 3 * len(frame)   # three passes over the file
    _compare(hamid.fit(frame), streamed)


def test_periods_from_the_first_samples_of_long_trajectories_stream(noisy_files,
                                                                   monkeypatch):
    """The period pass holds only the samples the period is found from: fewer than a
    trajectory here, so the window differs from the whole trajectories' one."""
    frame, paths = noisy_files
    whole = hamid.fit(frame).method["weak_window"]
    monkeypatch.setattr(design, "SCALE_SAMPLES", 150)
    memory = hamid.fit(frame)
    assert memory.method["weak_window"] != pytest.approx(whole, rel=1e-3)
    held = []
    scales = design.trajectory_scales

    def counted(records, n_coordinates):
        held.append(len(records.group))
        return scales(records, n_coordinates)

    monkeypatch.setattr(design, "trajectory_scales", counted)
    _compare(memory, hamid.fit(paths["parquet"], chunk_rows=100))
    assert held == [150] * frame.trajectory.nunique()


def test_no_folder_for_the_window_rows_is_a_clear_error(noisy_files, tmp_path, monkeypatch):
    import tempfile

    _, paths = noisy_files
    missing = str(tmp_path / "missing")
    monkeypatch.setattr(tempfile, "tempdir", missing)
    result = CliRunner().invoke(cli, ["fit", paths["parquet"], "--method", "joint",
                                      "--chunk-rows", "500"])
    assert result.exit_code == 1
    assert result.stdout == ""
    assert "peng.parquet: cannot keep its window rows in a temporary file" in result.stderr
    assert missing in result.stderr and "TMPDIR" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("method", ["weak", "joint"])
@pytest.mark.parametrize("cov", ["hac", "hc"])
def test_a_trajectory_too_short_for_any_window_streams(noisy_files, tmp_path, method, cov):
    """No window rows for one trajectory: its level is the mean energy, without an error."""
    frame, _ = noisy_files
    short = frame[frame.trajectory == 1].iloc[:30].copy()
    short["trajectory"] = 9
    with_short = pd.concat([frame, short], ignore_index=True)
    with_short.attrs = dict(frame.attrs)
    path = str(tmp_path / "with_short.parquet")
    writing.write_table(with_short, path, metadata=frame.attrs["hamid"])
    memory = hamid.fit(with_short, method=method, cov=cov)
    streamed = hamid.fit(path, method=method, cov=cov, chunk_rows=250)
    assert {h.trajectory: h.stderr for h in streamed.energy_levels}[9] is None
    _compare(memory, streamed)


def test_fixed_parameters_stream(noisy_files):
    frame, paths = noisy_files
    _compare(hamid.fit(frame, fix={"a6": 0.2}),
             hamid.fit(paths["parquet"], fix={"a6": 0.2}, chunk_rows=500))


def test_no_time_column_falls_back_to_energy_rows(noisy_files, tmp_path):
    frame, _ = noisy_files
    path = str(tmp_path / "untimed.parquet")
    writing.write_table(frame.drop(columns="t"), path)
    memory = hamid.fit(frame.drop(columns="t"), model="peng-quadratic")
    streamed = hamid.fit(path, model="peng-quadratic", chunk_rows=300)
    assert streamed.method["kind"] == "energy"
    _compare(memory, streamed)


def test_auto_falls_back_when_windows_are_too_few(noisy_files, tmp_path):
    frame, _ = noisy_files
    first = frame.trajectory == frame.trajectory.iloc[0]
    short = frame[(frame.t <= 4.0) & first]   # one trajectory of about a period
    path = str(tmp_path / "short.parquet")
    writing.write_table(short, path, metadata=frame.attrs["hamid"])
    memory = hamid.fit(short)
    streamed = hamid.fit(path, chunk_rows=64)
    assert streamed.method["kind"] == "energy"
    assert "weak-form windows" in streamed.method["kind_reason"]
    _compare(memory, streamed)


@pytest.mark.parametrize("options, message", [
    ({"noise": "auto"}, "noise weighting"),
    ({"damping": "viscous"}, "damping"),
    ({"cov": "bootstrap"}, "bootstrap"),
    ({"velocity": "savgol"}, "derived velocities"),
    ({"chunk_rows": 0}, "positive number"),
])
def test_options_that_need_the_data_in_memory(noisy_files, options, message):
    _, paths = noisy_files
    with pytest.raises(UsageError, match=message):
        hamid.fit(paths["parquet"], **{"chunk_rows": 100, **options})


def test_a_data_frame_cannot_be_chunked(noisy_files):
    frame, _ = noisy_files
    with pytest.raises(UsageError, match="one file"):
        hamid.fit(frame, chunk_rows=100)


def _csv(tmp_path, frame, name="bad.csv"):
    path = str(tmp_path / name)
    frame.to_csv(path, index=False)
    return path


def test_bad_cell_in_a_later_chunk_is_named(noisy_files, tmp_path):
    frame, _ = noisy_files
    bad = frame.astype({"u2": object})
    bad.iloc[1234, bad.columns.get_loc("u2")] = "oops"
    path = _csv(tmp_path, bad)
    with pytest.raises(DataError) as memory_error:
        hamid.fit(path, model="peng-quadratic")
    with pytest.raises(DataError) as chunk_error:
        hamid.fit(path, model="peng-quadratic", chunk_rows=100)
    assert "column 'u2', row 1235: 'oops' is not a number" in str(memory_error.value)
    assert str(chunk_error.value) == str(memory_error.value)


def test_a_trajectory_that_resumes_in_a_later_chunk(noisy_files, tmp_path):
    frame, _ = noisy_files
    first = frame[frame.trajectory == 1]
    moved = pd.concat([frame.drop(first.index[-10:]), first.iloc[-10:]])
    path = _csv(tmp_path, moved)
    with pytest.raises(DataError, match=rf"row {len(frame) - 9}: a trajectory resumes"):
        hamid.fit(path, model="peng-quadratic", chunk_rows=100)


def test_time_going_back_across_a_chunk_boundary(noisy_files, tmp_path):
    frame, _ = noisy_files
    bad = frame.copy()
    bad.iloc[700, bad.columns.get_loc("t")] = bad.t.iloc[698]
    path = str(tmp_path / "back.parquet")
    writing.write_table(bad, path)
    with pytest.raises(DataError, match="column 't', row 701: time does not increase"):
        hamid.fit(path, model="peng-quadratic", chunk_rows=700)


def test_non_finite_energy_names_the_file_row(noisy_files, tmp_path):
    frame, _ = noisy_files
    bad = frame.copy()
    bad.iloc[900, bad.columns.get_loc("u1")] = 1e200
    path = str(tmp_path / "huge.parquet")
    writing.write_table(bad, path)
    with pytest.raises(DataError, match="row 901: the .* of the energy is not finite"):
        hamid.fit(path, model="peng-quadratic", chunk_rows=256)


def test_cli_chunk_rows(noisy_files, tmp_path):
    frame, paths = noisy_files
    runner = CliRunner()
    done = runner.invoke(cli, ["fit", paths["parquet"], "--chunk-rows", "200", "--format",
                               "json"])
    assert done.exit_code == 0, done.output
    import json

    report = json.loads(done.stdout)
    memory = hamid.fit(frame)
    assert [p["estimate"] for p in report["parameters"]] == pytest.approx(
        list(memory.estimates.values()), rel=1e-10)
    refused = runner.invoke(cli, ["fit", paths["parquet"], "--chunk-rows", "200",
                                  "--residuals", str(tmp_path / "r.csv")])
    assert refused.exit_code == 2
    assert "--residuals needs the data in memory" in refused.stderr
    assert refused.stdout == ""


def test_a_file_over_the_size_limit_is_read_in_chunks_unless_asked_otherwise(
        noisy_files, monkeypatch, tmp_path):
    frame, paths = noisy_files
    size = input_size.decoded_bytes(paths["parquet"])
    monkeypatch.setattr(options, "STREAM_BYTES", size)   # the limit (64 MB decoded), made small
    assert hamid.fit(paths["parquet"]).samples is not None   # not over it: in memory
    monkeypatch.setattr(options, "STREAM_BYTES", size - 1)
    assert hamid.fit(paths["parquet"]).samples is None
    streamed = hamid.fit(paths["parquet"], method="energy")
    assert streamed.samples is None
    memory = hamid.fit(paths["parquet"], method="energy", in_memory=True)
    assert memory.samples is not None
    _compare(memory, streamed)
    out = tmp_path / "residuals.csv"
    done = CliRunner().invoke(cli, ["fit", paths["parquet"], "--method", "energy",
                                    "--format", "json", "--residuals", str(out)])
    assert done.exit_code == 0, done.output
    assert len(pd.read_csv(out)) == len(frame)
    with pytest.raises(UsageError, match="--chunk-rows: in_memory asks for the data in memory"):
        hamid.fit(paths["parquet"], chunk_rows=100, in_memory=True)


def test_a_large_file_of_positions_alone_is_read_whole(monkeypatch, tmp_path):
    """Chunks take positions and velocities; a file over the size limit that records
    positions alone is read whole, its velocities derived, as a small one is."""
    frame = hamid.simulate({"model": {"builtin": "duffing"}, "parameters": {"k": 1.0,
                                                                           "k3": 0.5},
                            "initial": [{"x": 1.0, "v": 0.0}],
                            "simulate": {"t_end": 30.0, "dt": 0.05}})
    path = tmp_path / "positions.csv"
    frame.drop(columns="v").to_csv(path, index=False)
    small = hamid.fit(path, "duffing")
    monkeypatch.setattr(options, "STREAM_BYTES", 100)
    large = hamid.fit(path, "duffing")
    assert large.samples is not None and large.estimates == small.estimates
    assert large.estimates["k3"] == pytest.approx(0.5, rel=1e-4)


def test_a_joint_fit_in_chunks_holds_no_more_for_a_longer_file(tmp_path, monkeypatch):
    """Peak traced memory of a chunked joint fit: a file with four times the trajectories
    (and window rows) needs no more than the file itself, to within 25%."""
    import tracemalloc

    import pyarrow as pa
    import pyarrow.parquet as pq

    monkeypatch.setattr(chunked._WindowRows, "CHUNK_WINDOWS", 256)

    def peak(n_trajectories):
        rng = np.random.default_rng(n_trajectories)
        initial = [{"u1": a, "u2": -a, "v1": 0.1, "v2": 0.2}
                   for a in rng.uniform(0.15, 0.3, n_trajectories)]
        system = {**PENG, "initial": initial,
                  "simulate": {"t_end": 300.0, "dt": 0.05, "seed": 0}}
        frame = with_noise(hamid.simulate(system), 0.01, seed=1)
        path = str(tmp_path / f"peng-{n_trajectories}.parquet")
        pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), path,
                       row_group_size=2000)
        del frame
        tracemalloc.start()
        try:
            result = hamid.fit(path, model="peng-quadratic", method="joint", chunk_rows=2000)
            _, highest = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert len(result.energy_levels) == n_trajectories
        return highest

    small, large = peak(2), peak(8)
    assert large < 1.25 * small


# --- the same checks whole and in chunks (issue 34: one source interface) ---

@pytest.fixture(scope="module")
def unchecked_file(noisy_files, tmp_path_factory):
    """Noisy peng-quadratic records whose velocity 'v1' is twice the positions' rate (the
    velocity check says so) with a trajectory shorter than the weak-form window (the window
    check says so), as CSV."""
    frame, _ = noisy_files
    doubled = frame.copy()
    doubled["v1"] *= 2
    short = doubled[doubled.trajectory == 1].iloc[:30].copy()
    short["trajectory"] = 9
    data = pd.concat([doubled, short], ignore_index=True)
    path = str(tmp_path_factory.mktemp("checks") / "unchecked.csv")
    writing.write_table(data, path, metadata=frame.attrs["hamid"])
    return path


SKIPPED_IN_CHUNKS = ["noise check", "residuals per sample", "records for plotting"]


@pytest.mark.parametrize("method", ["weak", "energy"])
def test_chunks_make_the_checks_of_a_whole_read_or_name_them(unchecked_file, method):
    whole = hamid.fit(unchecked_file, method=method, in_memory=True)
    chunks = hamid.fit(unchecked_file, method=method, chunk_rows=250)
    assert whole.checks_skipped == ()
    assert "checks_skipped" not in whole.to_dict()
    assert [skip["check"] for skip in chunks.checks_skipped] == SKIPPED_IN_CHUNKS
    assert all(skip["reason"] for skip in chunks.checks_skipped)
    assert chunks.warnings == whole.warnings
    assert any("'u1' change 0.5 times as fast as the velocities 'v1'" in w
               for w in chunks.warnings)
    if method == "weak":
        assert any("1 of 3 trajectories is shorter than the weak-form window" in w
                   for w in chunks.warnings)
    assert whole.samples is not None and whole.recording is not None
    assert chunks.samples is None and chunks.recording is None
    assert chunks.data == whole.data


def test_what_chunks_skip_is_the_noise_check_whole(noisy_files, tmp_path, monkeypatch):
    """With noise the check sees, the warnings of a whole read are those of the chunked one
    and those of the noise check, which the chunked fit names as skipped."""
    frame, _ = noisy_files
    path = str(tmp_path / "noisier.csv")
    writing.write_table(with_noise(frame, 0.05, seed=7), path, metadata=frame.attrs["hamid"])
    whole = hamid.fit(path, method="energy", in_memory=True)
    chunks = hamid.fit(path, method="energy", chunk_rows=300)
    monkeypatch.setattr(estimate, "noise_check", lambda *args, **kwargs: None)
    unchecked = hamid.fit(path, method="energy", in_memory=True)
    noise_warnings = set(whole.warnings) - set(unchecked.warnings)
    assert noise_warnings   # the noise check says something of these data
    assert chunks.warnings == unchecked.warnings
    assert set(whole.warnings) - set(chunks.warnings) == noise_warnings
    assert "noise check" in [skip["check"] for skip in chunks.checks_skipped]


@pytest.mark.parametrize("size", [1, 7, 8, 9, 40, 777])
def test_velocity_sums_in_chunks_are_those_of_the_records_whole(noisy_files, size):
    frame, _ = noisy_files
    sorted_frame = frame.sort_values(["trajectory", "t"], kind="stable")
    X = sorted_frame[["u1", "u2", "v1", "v2"]].to_numpy()
    X[:, 2] *= 1.5
    t = sorted_frame["t"].to_numpy()
    lengths = [5, 3] + [len(t) - 8]   # two short trajectories, then the rest as one
    group = np.repeat(np.arange(3), lengths)
    t = np.concatenate([t[:5], t[5:8], t[8:]])
    records = Records(X, t, group, ())
    expected = measurement.velocity_check(records, ["u1", "u2"], ["v1", "v2"], {}, 2.0)
    sums = measurement.VelocitySums(2)
    for start in range(0, len(t), size):
        sums.add(records.slice(start, start + size), ended=False)
    sums.end()
    assert sums.findings(["u1", "u2"], ["v1", "v2"], {}, 2.0) == expected
    assert any("'u1' change" in finding.text for finding in expected)
    whole = measurement.VelocitySums(2)
    whole.add(records)
    np.testing.assert_allclose(sums.normal, whole.normal, rtol=1e-12, atol=0)
    np.testing.assert_allclose(sums.right, whole.right, rtol=1e-12, atol=0)
    assert sums.count.tolist() == whole.count.tolist() and sums.span == whole.span


def test_the_command_line_reports_the_checks_skipped(unchecked_file):
    runner = CliRunner()
    done = runner.invoke(cli, ["fit", unchecked_file, "--chunk-rows", "250", "--format",
                               "json"])
    assert done.exit_code == 0, done.output
    report = json.loads(done.stdout)
    validation.check_result(report)
    assert [skip["check"] for skip in report["checks_skipped"]] == SKIPPED_IN_CHUNKS
    whole = runner.invoke(cli, ["fit", unchecked_file, "--format", "json"])
    assert "checks_skipped" not in json.loads(whole.stdout)
    table = runner.invoke(cli, ["fit", unchecked_file, "--chunk-rows", "250",
                                "--format", "table"])
    assert table.exit_code == 0, table.output
    shown = " ".join(table.stdout.split())
    for check in SKIPPED_IN_CHUNKS:
        assert f"skipped: {check}:" in shown


def test_checks_skipped_survive_a_report_read_again(unchecked_file):
    chunks = hamid.fit(unchecked_file, method="energy", chunk_rows=250)
    again = FitResult.from_dict(json.loads(json.dumps(chunks.to_dict())))
    assert again.checks_skipped == chunks.checks_skipped
    assert "skipped: noise check:" in " ".join(again.summary().split())


def test_both_sources_have_the_members_of_a_source(unchecked_file):
    opts = options.FitOptions()
    whole = loading.load(unchecked_file, None, opts)
    chunks = loading.open_chunks(unchecked_file, None, opts, 250, None)
    members = [name for name in dir(loading.Source) if not name.startswith("_")]
    assert {"model", "labels", "truth", "notes", "data_info", "scales", "durations",
            "locate", "rows", "whole", "whole_bytes"} <= set(members)
    for name in members:
        assert hasattr(whole, name) and hasattr(chunks, name), name
    assert chunks.labels == whole.labels
    assert chunks.data_info == whole.data_info
    assert chunks.notes == whole.notes
    assert chunks.durations() == pytest.approx(whole.durations(), rel=1e-12)
    assert chunks.scales() == whole.scales()
    np.testing.assert_array_equal(chunks.whole().X, whole.whole().X)
    assert chunks.locate(1000) == whole.locate(1000) == (unchecked_file, 1001)


def test_each_line_carries_the_checks_skipped(unchecked_file, noisy_files):
    _, paths = noisy_files
    done = CliRunner().invoke(cli, ["fit", "--each", unchecked_file, paths["csv"],
                                    "--chunk-rows", "250", "--format", "jsonl"])
    assert done.exit_code in (0, 3), done.output
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert [line["source"] for line in lines] == [unchecked_file, paths["csv"]]
    for line in lines:
        assert line["status"] == "ok"
        assert [skip["check"] for skip in line["checks_skipped"]] == SKIPPED_IN_CHUNKS


pytestmark = pytest.mark.skipif(os.name != "posix", reason="POSIX descriptors and terminals")

ROOT = Path(__file__).resolve().parents[2]
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
    # the same column, not mapped and no other channel of x: the message lists the columns
    data.write_text("\n".join([f"trajectory,t,pos{EVIL},speed", *lines[1:]]) + "\n")
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
