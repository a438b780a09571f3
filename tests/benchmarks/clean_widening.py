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
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
from benchmarks.clean_records import TOLERANCES, moved_system
from conftest import with_noise

import hamid
from hamid.linear import noise_free

SYSTEMS = ("duffing", "peng_quadratic")


def _fits(frame, method: str, truth: dict[str, float], leave_out: bool):
    """Whether each parameter's bounds hold the truth, and its standard error."""
    threshold = noise_free.CLEAN_RELATIVE
    noise_free.CLEAN_RELATIVE = 0.0 if leave_out else threshold
    try:
        result = hamid.fit(frame, method=method)
    finally:
        noise_free.CLEAN_RELATIVE = threshold
    return {p.name: (p.ci_low <= truth[p.name] <= p.ci_high, p.stderr)
            for p in result.parameters}


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
                rows = {name: [] for name in truth}
                for frame in frames:
                    before = _fits(frame, method, truth, leave_out=True)
                    after = _fits(frame, method, truth, leave_out=False)
                    for name in truth:
                        rows[name].append((before[name][0], after[name][0],
                                           after[name][1] / before[name][1]))
                print(f"{system} {method} noise {relative:g}, {args.realizations} "
                      "realizations: coverage without -> with, stderr with/without, widened")
                for name, found in rows.items():
                    b, a, ratio = (np.array(column, dtype=float) for column in zip(*found,
                                                                                   strict=True))
                    print(f"  {name:5s} {b.mean():6.1%} -> {a.mean():6.1%}  "
                          f"x{ratio.mean():.4g}  {np.mean(ratio > 1):6.1%}", flush=True)


if __name__ == "__main__":
    main()
