"""Many short recordings: time and peak memory of a fit against the number of trajectories.

Labs record many short releases. Simulates Duffing trajectories of 600 samples (1% noise)
in two files, one with `--small` trajectories and one with `--large` (1,000 and 10,000 by
default), and fits each in its own process, read into memory (`in_memory`; a file this
large would otherwise be read in chunks): `--method energy`,
`--method joint`, and, with `--auto`, the default fit with its trajectory refinement.
The baseline is the same read with pyarrow, the energy columns centred per trajectory and
one numpy.linalg.lstsq.

Prints each case's best wall time over `--repeat` rounds (start-up and imports included)
and peak resident memory, the ratios to the baseline on the same file, and, the point of
the benchmark, how time and memory per sample change from the small file to the large one
(1.0: linear in the samples; a cost per trajectory that grows with their number shows as
a ratio well above 1).

    python tests/benchmarks/many_trajectories.py [--small 1000] [--large 10000] [--auto]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

from processes import PEAK, run

BASELINE = PEAK + r"""
import json, sys, time
import numpy as np, pyarrow.parquet as pq
table = pq.read_table(sys.argv[1])
_, index = np.unique(table.column("trajectory").to_numpy(), return_inverse=True)
x, v = (table.column(c).to_numpy() for c in ("x", "v"))
A = np.column_stack([x**2 / 2, x**4 / 4])
b = -v**2 / 2
counts = np.bincount(index)
A -= (np.stack([np.bincount(index, weights=A[:, k]) for k in range(2)], axis=1)
      / counts[:, None])[index]
b -= (np.bincount(index, weights=b) / counts)[index]
theta = np.linalg.lstsq(A, b, rcond=None)[0]
print(json.dumps({"peak_kb": peak_kb(), "theta": theta.tolist()}))
"""

HAMID = PEAK + r"""
import json, sys
import hamid
result = hamid.fit(sys.argv[1], **json.loads(sys.argv[2]))
print(json.dumps({"peak_kb": peak_kb(), "theta": list(result.estimates.values()),
                  "kind": result.method["kind"]}))
"""

SAMPLES = 600


def make_data(path: str, n_trajectories: int) -> None:
    import numpy as np

    import hamid
    from hamid.data import writing

    rng = np.random.default_rng(n_trajectories)
    amplitude = rng.uniform(0.3, 1.2, n_trajectories)
    phase = rng.uniform(0, 2 * np.pi, n_trajectories)
    initial = [{"x": float(a * np.cos(p)), "v": float(a * np.sin(p))}
               for a, p in zip(amplitude, phase, strict=True)]
    system = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": initial,
              "simulate": {"t_end": (SAMPLES - 1) * 0.05, "dt": 0.05, "seed": 1},
              "noise": {"relative": 0.01}}
    frame = hamid.simulate(system)
    writing.write_table(frame, path, metadata=frame.attrs["hamid"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--small", type=int, default=1_000)
    parser.add_argument("--large", type=int, default=10_000)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--auto", action="store_true", help="also the default fit")
    options = parser.parse_args()
    cases = {"baseline (pyarrow + centre + lstsq)": (BASELINE,),
             "hamid --method energy": (HAMID, json.dumps({"method": "energy",
                                                          "in_memory": True})),
             "hamid --method joint": (HAMID, json.dumps({"method": "joint",
                                                         "in_memory": True}))}
    if options.auto:
        cases["hamid (default, auto)"] = (HAMID, json.dumps({"in_memory": True}))
    results: dict[int, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory() as folder:
        for J in (options.small, options.large):
            path = os.path.join(folder, f"{J}.parquet")
            start = time.perf_counter()
            make_data(path, J)
            print(f"data: {J} trajectories x {SAMPLES} samples, "
                  f"{os.path.getsize(path) / 1e6:.0f} MB, made in "
                  f"{time.perf_counter() - start:.1f} s")
            runs: dict[str, list[dict]] = {name: [] for name in cases}
            for _ in range(options.repeat):   # the cases take turns
                for name, (code, *args) in cases.items():
                    runs[name].append(run(code, path, *args))
            results[J] = {name: min(found, key=lambda r: r["seconds"])
                          for name, found in runs.items()}
    small, large = results[options.small], results[options.large]
    grow = options.large / options.small
    print(f"\n{'case':36s} {'trajectories':>12s} {'seconds':>8s} {'x base':>7s} "
          f"{'peak MB':>8s} {'x base':>7s}")
    for J, found in results.items():
        base = found["baseline (pyarrow + centre + lstsq)"]
        for name, r in found.items():
            print(f"{name:36s} {J:12d} {r['seconds']:8.2f} "
                  f"{r['seconds'] / base['seconds']:7.2f} {r['peak_kb'] / 1024:8.0f} "
                  f"{r['peak_kb'] / base['peak_kb']:7.2f}")
    print(f"\nper sample, {options.large} trajectories against {options.small} "
          "(1.00: linear in the samples)")
    for name in cases:
        print(f"{name:36s} time {large[name]['seconds'] / small[name]['seconds'] / grow:5.2f}"
              f"  memory {large[name]['peak_kb'] / small[name]['peak_kb'] / grow:5.2f}"
              f"  (method run: {large[name].get('kind', '-')})")
    print("target (issue 25): time and memory linear in the samples")


if __name__ == "__main__":
    main()
