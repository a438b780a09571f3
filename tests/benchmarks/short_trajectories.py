"""Many short trajectories against one long one of the same samples, in one process.

Simulates Duffing motion (k = 1, k3 = 0.5, 1% noise, dt = 0.05) as `--trajectories`
records of `--samples` samples each (5,000 x 20 by default) and as one record of as many
samples (100,000), then fits each with `hamid.fit` as a user would (the default method),
the two in turns, `--repeat` times. Prints the median time of each and their ratio: the
cost of a trajectory beyond that of its samples (plan, rows, windows, refinement
segments, summaries). With `--profile`, the functions that take most of the many-trajectory
fit's time under cProfile.

    python tests/benchmarks/short_trajectories.py [--trajectories 5000] [--samples 20]
        [--repeat 5] [--method auto] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import statistics
import time

import numpy as np
import pandas as pd

import hamid


def records(n_trajectories: int, n_samples: int) -> pd.DataFrame:
    """`n_trajectories` Duffing records of `n_samples` samples from spread initial states."""
    rng = np.random.default_rng(n_trajectories)
    amplitude = rng.uniform(0.3, 1.2, n_trajectories)
    phase = rng.uniform(0, 2 * np.pi, n_trajectories)
    initial = [{"x": float(a * np.cos(p)), "v": float(a * np.sin(p))}
               for a, p in zip(amplitude, phase, strict=True)]
    system = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": initial,
              "simulate": {"t_end": (n_samples - 1) * 0.05, "dt": 0.05, "seed": 1,
                           "max_samples": 10 * n_trajectories * n_samples},
              "noise": {"relative": 0.01}}
    return hamid.simulate(system)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", type=int, default=5_000)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--method", default="auto")
    parser.add_argument("--profile", action="store_true")
    options = parser.parse_args()
    total = options.trajectories * options.samples
    cases = {f"{options.trajectories} x {options.samples}":
             records(options.trajectories, options.samples),
             f"1 x {total}": records(1, total)}
    seconds: dict[str, list[float]] = {name: [] for name in cases}
    kinds = {}
    for _ in range(options.repeat):
        for name, frame in cases.items():
            start = time.perf_counter()
            result = hamid.fit(frame, "duffing", method=options.method)
            seconds[name].append(time.perf_counter() - start)
            kinds[name] = f"{result.method['kind']}, k = {result.estimates['k']:.4f}"
    medians = {name: statistics.median(found) for name, found in seconds.items()}
    for name, found in seconds.items():
        print(f"{name:>14s}: median {medians[name]:.3f} s over {len(found)} "
              f"(min {min(found):.3f}; {kinds[name]})")
    many, one = medians.values()
    print(f"ratio: {many / one:.2f} (target: at most 3)")
    if options.profile:
        frame = next(iter(cases.values()))
        profile = cProfile.Profile()
        profile.runcall(hamid.fit, frame, "duffing", method=options.method)
        pstats.Stats(profile).sort_stats("cumulative").print_stats(40)


if __name__ == "__main__":
    main()
