"""Many recordings: `hamid fit --each --jobs 2` against `--jobs 1`, and Dask's cost per file.

Simulates `--files` Duffing recordings of `--samples` samples (1% noise; default 200 of
10^4), then times the command `hamid fit --each FOLDER --format csv -o OUT` with `--jobs 1`
and with `--jobs 2` (start-up included), the cases taking turns over `--repeat` rounds,
and prints the best time of each and their ratio. Every estimate, standard error and bound
of both runs is checked against a loop of single `hamid.fit` calls in this process, to
`--tolerance` (1e-12).

With `--dask`, also starts a `distributed.LocalCluster` of 2 worker processes (1 thread
each) and measures the scheduler's cost per file: the same fits through it against
`--jobs 2`, and a function that does nothing mapped over `--tasks` items (the cost of a
task alone: submit, schedule, run, return).

    python tests/benchmarks/batch.py [--files 200] [--samples 10000] [--repeat 2] [--dask]

The machine's load is printed before and after (os.getloadavg): other work on its cores
slows the parallel run most.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers import hamid_command  # noqa: E402


def make_files(folder: Path, n_files: int, samples: int) -> list[str]:
    import hamid
    from hamid.data import writing

    system = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": [{"x": 1.0, "v": 0.0}],
              "simulate": {"t_end": (samples - 1) * 0.05, "dt": 0.05},
              "noise": {"relative": 0.01}}
    paths = []
    for k, frame in enumerate(hamid.simulate_realizations(system, n_files, seed=0)):
        path = folder / f"run{k + 1:04d}.csv"
        writing.write_table(frame, str(path), metadata=frame.attrs["hamid"])
        paths.append(str(path))
    return paths


def run_each(folder: Path, jobs: int, out: Path) -> float:
    start = time.perf_counter()
    done = subprocess.run([*hamid_command(), "fit", "--each", str(folder), "--jobs",
                           str(jobs), "--format", "csv", "-o", str(out)],
                          capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"hamid fit --each --jobs {jobs} failed: {done.stderr}")
    return elapsed


def check(out: Path, truth: dict[tuple[str, str], tuple[float, ...]], tolerance: float) -> float:
    """The largest relative difference from the loop of single fits; exits if too large."""
    worst = 0.0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == len(truth), (len(rows), len(truth))
    for row in rows:
        expected = truth[row["source"], row["parameter"]]
        found = tuple(float(row[k]) for k in ("estimate", "stderr", "ci_low", "ci_high"))
        for a, b in zip(found, expected, strict=True):
            worst = max(worst, abs(a - b) / abs(b))
    if worst > tolerance:
        sys.exit(f"{out.name}: differs from the single fits by {worst:.2g} > {tolerance}")
    return worst


def _nothing(item: int) -> int:
    return item


def dask_costs(paths: list[str], tasks: int) -> None:
    """Fits and empty tasks on a LocalCluster against local processes, both warmed up."""
    from distributed import LocalCluster

    import hamid
    from hamid.executor import Workers, ordered_map

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        times = {}
        for name, workers in (("--jobs 2", Workers(jobs=2)),
                              ("dask", Workers(scheduler=cluster.scheduler_address))):
            where = {"jobs": 2} if workers.scheduler is None else {
                "scheduler": workers.scheduler}
            hamid.fit_each(paths[:4], **where)              # imports done in the workers
            start = time.perf_counter()
            fits = hamid.fit_each(paths, **where)
            elapsed = time.perf_counter() - start
            assert not [f for f in fits if isinstance(f, Exception)]
            start = time.perf_counter()
            list(ordered_map(_nothing, range(tasks), workers))
            times[name] = elapsed, (time.perf_counter() - start) / tasks
    (local, local_task), (dask, dask_task) = times["--jobs 2"], times["dask"]
    print(f"fit_each of {len(paths)} files, 2 workers: {dask:.1f} s on a LocalCluster, "
          f"{local:.1f} s in local processes: {1e3 * (dask - local) / len(paths):+.1f} ms "
          "per file on Dask")
    print(f"a task that does nothing ({tasks}): {1e3 * dask_task:.2f} ms on Dask, "
          f"{1e3 * local_task:.2f} ms in local processes")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=200)
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--tolerance", type=float, default=1e-12)
    parser.add_argument("--dask", action="store_true")
    parser.add_argument("--tasks", type=int, default=1000)
    args = parser.parse_args()

    import hamid

    print(f"load average before: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "runs"
        folder.mkdir()
        paths = make_files(folder, args.files, args.samples)
        start = time.perf_counter()
        truth = {}
        for path in paths:
            for p in hamid.fit(path).parameters:
                truth[path, p.name] = (p.estimate, p.stderr, p.ci_low, p.ci_high)
        loop = time.perf_counter() - start
        print(f"{args.files} files of {args.samples} samples; a loop of single fits in this "
              f"process: {loop:.1f} s")
        best = {1: float("inf"), 2: float("inf")}
        for round_ in range(args.repeat):
            for jobs in (1, 2):
                out = Path(tmp) / f"jobs{jobs}.csv"
                elapsed = run_each(folder, jobs, out)
                worst = check(out, truth, args.tolerance)
                best[jobs] = min(best[jobs], elapsed)
                print(f"round {round_ + 1}: --jobs {jobs}: {elapsed:.1f} s "
                      f"(largest difference from the single fits {worst:.1g})")
        print(f"--jobs 1: {best[1]:.1f} s, --jobs 2: {best[2]:.1f} s, "
              f"ratio {best[1] / best[2]:.2f}x (best of {args.repeat})")
        if args.dask:
            dask_costs(paths, args.tasks)
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
