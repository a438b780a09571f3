"""Coverage of energy and joint 95% bounds with and without the noise-free widening.

    python tests/benchmarks/clean_widening.py [--realizations 20] [--noise 0 1e-10 1e-8 1e-3 1e-2]

The sample systems sample_data/duffing.toml and peng_quadratic.toml, with white noise of a
fraction of each column's spread on the states (`with_noise`, seeds 0..R-1; without noise,
each initial state moved by up to 20% instead, as in clean_records.py), fitted with
--method energy and joint: once with the widening left out (`noise_free.CLEAN_RELATIVE`
zero, the fit before it) and once as reported. Per parameter: the share of bounds that
hold the truth, without -> with, the mean standard error with over without, and the share
of fits widened. Noisy records must come out unchanged (ratio 1, none widened).
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
from benchmarks.clean_records import TOLERANCES, moved_system
from benchmarks.discretization import coverage, print_coverage
from conftest import with_noise

import hamid
from hamid.linear import noise_free

SYSTEMS = ("duffing", "peng_quadratic")


@contextmanager
def _without_the_widening() -> Iterator[None]:
    """Fits made inside leave the noise-free widening out (the fit before it)."""
    threshold = noise_free.CLEAN_RELATIVE
    noise_free.CLEAN_RELATIVE = 0.0
    try:
        yield
    finally:
        noise_free.CLEAN_RELATIVE = threshold


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--realizations", type=int, default=20)
    parser.add_argument("--noise", type=float, nargs="+", default=[0, 1e-10, 1e-8, 1e-3, 1e-2])
    args = parser.parse_args()
    for system in SYSTEMS:
        document = tomllib.loads((ROOT / "sample_data" / f"{system}.toml").read_text())
        truth, clean = document["parameters"], hamid.simulate(document)
        for relative in args.noise:
            frames = [with_noise(clean, relative, seed) if relative
                      else hamid.simulate(moved_system(document, seed, *TOLERANCES[0]))
                      for seed in range(args.realizations)]
            for method in ("energy", "joint"):
                print_coverage(f"{system} {method} noise {relative:g}, {args.realizations} "
                               "realizations", coverage(frames, method, truth,
                                                        _without_the_widening))


if __name__ == "__main__":
    main()
