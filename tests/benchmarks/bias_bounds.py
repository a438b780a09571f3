"""Honest bounds under measurement noise: z spread and coverage of the linear methods.

    python tests/benchmarks/bias_bounds.py [--realizations 200] [--noise 0.01 0.03]
                                           [--systems peng-quadratic duffing]
                                           [--runs energy energy+bc ...] [--short]

For every system the clean record is simulated once: the accuracy benchmark's (100 s at
dt 0.02, 15,003 and 10,002 samples; tests/benchmarks/accuracy.py), or with --short the
test suite's (30-40 s at dt 0.05; tests/conftest.py). Each realization adds white
Gaussian noise of a fixed fraction of each column's standard deviation to the positions
and velocities (`with_noise`, seeds 0..N-1), and each run fits the same noisy record.
Per parameter the table gives, over the realizations, of z = (estimate - truth) / std.
error:

    mean z     the bias in standard errors (0 for an unbiased estimator);
    spread     the standard deviation of z (1 when the standard errors are right);
    coverage   the share of 95% intervals that hold the truth;

and per run how often the fit warned that the noise biases it ("warned").

Runs
----
energy, joint, weak
    ``hamid.fit(frame, method=...)`` without noise options.
energy+bc, joint+bc
    the same with ``noise="auto", bias_correct=True``.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import time
from typing import Any

import numpy as np

import hamid

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from accuracy import SYSTEMS as LONG  # noqa: I001
from conftest import DUFFING, PENG, with_noise

SHORT: dict[str, dict[str, Any]] = {"peng-quadratic": PENG, "duffing": DUFFING}
RUNS: dict[str, dict[str, Any]] = {
    "energy": {"method": "energy"},
    "energy+bc": {"method": "energy", "noise": "auto", "bias_correct": True},
    "joint": {"method": "joint"},
    "joint+bc": {"method": "joint", "noise": "auto", "bias_correct": True},
    "weak": {"method": "weak"},
}


def realizations(clean: Any, truth: dict[str, float], relative: float, n: int,
                 options: dict[str, Any]) -> dict[str, Any]:
    """z of every parameter over `n` noisy copies of `clean`, coverage, and warnings."""
    z, covered, warned = [], [], 0
    for seed in range(n):
        result = hamid.fit(with_noise(clean, relative, seed), **options)
        z.append([(p.estimate - truth[p.name]) / p.stderr for p in result.parameters])
        covered.append([p.ci_low <= truth[p.name] <= p.ci_high for p in result.parameters])
        warned += any("biases these least-squares" in w for w in result.warnings)
    z = np.array(z)
    return {"mean": z.mean(axis=0), "spread": z.std(axis=0, ddof=1),
            "coverage": np.mean(covered, axis=0), "warned": warned / n}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--realizations", type=int, default=200)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.03])
    parser.add_argument("--systems", nargs="+", default=list(SHORT), choices=list(SHORT))
    parser.add_argument("--runs", nargs="+", default=["energy", "energy+bc"],
                        choices=list(RUNS))
    parser.add_argument("--short", action="store_true",
                        help="the test suite's shorter records")
    args = parser.parse_args()
    systems = SHORT if args.short else LONG
    print(f"{args.realizations} realizations per cell on the {'short' if args.short else 'long'}"
          " records; z = (estimate - truth) / std. error")
    print()
    print("| system | noise | run | parameter | mean z | z spread | coverage | warned |")
    print("|---|---|---|---|---|---|---|---|")
    for name in args.systems:
        system = systems[name]
        clean = hamid.simulate(system)
        truth = dict(system["parameters"])
        for relative in args.noise:
            for run in args.runs:
                start = time.perf_counter()
                stats = realizations(clean, truth, relative, args.realizations, RUNS[run])
                for k, parameter in enumerate(truth):
                    print(f"| {name} | {relative:.0%} | {run} | {parameter} | "
                          f"{stats['mean'][k]:+.2f} | {stats['spread'][k]:.2f} | "
                          f"{stats['coverage'][k]:.2f} | "
                          f"{stats['warned']:.2f} |" if k == 0 else
                          f"| | | | {parameter} | {stats['mean'][k]:+.2f} | "
                          f"{stats['spread'][k]:.2f} | {stats['coverage'][k]:.2f} | |",
                          flush=True)
                print(f"{name} {relative} {run}: {time.perf_counter() - start:.1f} s",
                      file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
