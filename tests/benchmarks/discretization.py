"""Coverage of weak and joint 95% bounds with and without the quadrature's error term.

    python tests/benchmarks/discretization.py [--realizations 100] [--noise 1e-2 1e-3 1e-8]

The sample records' systems (sample_data/duffing.toml, peng_quadratic.toml: dt 0.05),
with white noise of a fixed fraction of each column's standard deviation on the states
(`with_noise`, seeds 0..R-1), fitted with --method weak and joint: once as reported, and
once with the term left out (`estimate.DISCRETIZATION_SHARE` infinite, the fit before the
term). Per parameter: the share of bounds that hold the truth, without -> with, the mean
reported standard error with over without, and the share of fits that folded the term
in. At 1% and 0.1% noise the term should stay out (coverage and errors unchanged); at
1e-8 the quadrature's error is larger than the noise, and the bounds without it miss.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import tomllib
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
from conftest import with_noise

import hamid
from hamid.linear import estimate

SYSTEMS = ("duffing", "peng_quadratic")


@contextmanager
def _without_the_term() -> Iterator[None]:
    """Fits made inside leave the quadrature's error term out (the fit before it)."""
    share = estimate.DISCRETIZATION_SHARE
    estimate.DISCRETIZATION_SHARE = np.inf
    try:
        yield
    finally:
        estimate.DISCRETIZATION_SHARE = share


def coverage(frames, method: str, truth: dict[str, float],
             leaving_out: Callable[[], AbstractContextManager[None]]) -> dict[str, list]:
    """Per parameter and frame: whether its bounds hold the truth without the term (fitted
    inside `leaving_out()`) and with it, and its standard error with over without."""
    rows: dict[str, list] = {name: [] for name in truth}
    for frame in frames:
        with leaving_out():
            before = hamid.fit(frame, method=method).parameters
        after = hamid.fit(frame, method=method).parameters
        for b, a in zip(before, after, strict=True):
            rows[b.name].append((b.ci_low <= truth[b.name] <= b.ci_high,
                                 a.ci_low <= truth[a.name] <= a.ci_high, a.stderr / b.stderr))
    return rows


def print_coverage(title: str, rows: dict[str, list]) -> None:
    """Coverage without -> with, the mean ratio of standard errors and the share of fits
    the term changed, a line per parameter."""
    print(f"{title}: coverage without -> with, stderr with/without, changed")
    for name, found in rows.items():
        b, a, ratio = (np.array(column, dtype=float) for column in zip(*found, strict=True))
        print(f"  {name:5s} {b.mean():6.1%} -> {a.mean():6.1%}  x{ratio.mean():.4g}  "
              f"{np.mean(ratio > 1):6.1%}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument("--noise", type=float, nargs="+", default=[1e-2, 1e-3, 1e-8])
    args = parser.parse_args()
    for system in SYSTEMS:
        path = ROOT / "sample_data" / f"{system}.toml"
        truth = tomllib.loads(path.read_text())["parameters"]
        clean = hamid.simulate(path)
        for relative in args.noise:
            frames = [with_noise(clean, relative, seed) for seed in range(args.realizations)]
            for method in ("weak", "joint"):
                print_coverage(f"{system} {method} noise {relative:g}, {args.realizations} "
                               "realizations", coverage(frames, method, truth,
                                                        _without_the_term))


if __name__ == "__main__":
    main()
