"""Where a linear fit stops counting its data as noise-free, against the noise level.

    python tests/benchmarks/clean_criterion.py [--levels 0 1e-12 1e-11 ... 1e-6]

Each sample system (sample_data/*.toml, simulated without noise) with Gaussian noise of
each level times every variable's spread added, fitted with the energy and joint methods:
per level, the fitted energy rows' residual rms over their spread (`noise_free.Misfit.relative`:
every sample's rows, or the window means of a joint fit), read from the covariance's
description with the threshold lifted, and whether it is below `noise_free.CLEAN_RELATIVE`,
where the covariance is widened as for noise-free data.
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

import hamid
from hamid.linear import noise_free

SYSTEMS = ("duffing", "peng_quadratic", "elastic_pendulum", "henon_heiles")
LEVELS = (0.0, 1e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--levels", nargs="+", type=float, default=LEVELS)
    args = parser.parse_args()
    threshold, noise_free.CLEAN_RELATIVE = noise_free.CLEAN_RELATIVE, np.inf   # always described
    for name in SYSTEMS:
        document = tomllib.loads((ROOT / "sample_data" / f"{name}.toml").read_text())
        document.pop("noise", None)
        frame = hamid.simulate(document)
        columns = [c for c in frame.columns if c not in ("trajectory", "t")]
        for level in args.levels:
            noisy, rng = frame.copy(), np.random.default_rng(0)
            for column in columns:
                noisy[column] = (frame[column]
                                 + level * frame[column].std() * rng.standard_normal(len(frame)))
            cells = []
            for method in ("energy", "joint"):
                result = hamid.fit(noisy, method=method)
                description = result.method["covariance_description"]
                relative = float(description.split("residual rms ")[1].split(" ")[0])
                widened = "widened" if relative < threshold else "as is"
                cells.append(f"{method} {relative:.1e} {widened:7s}")
            print(f"{name:16s} noise {level:7.0e}: " + "   ".join(cells), flush=True)


if __name__ == "__main__":
    main()
