"""Weak-form window length and bump order against the error of ``method="weak"``.

    python tests/benchmarks/weak_window.py [--realizations 10] [--systems peng-quadratic duffing]
                                           [--workers N]

The records and noise are those of accuracy.py (t_end = 100 s, dt = 0.02 s, white noise of
a fraction of each column's std on positions and velocities, fixed seeds). For each
realization the default window (half the dominant period, found from that noisy record)
is scaled by the factors below and passed as ``weak_window=``; the bump order p of
psi = (1 - s^2)^p is set by monkeypatching ``hamid.linear.design.BUMP_ORDER`` (read by
``design.windows`` at call time). Score: median over the realizations of the worst
parameter's relative error. Then the clean-data error for each order and factor, on the
same systems sampled at a coarse dt = 0.05 s (and at dt = 0.02 s for comparison), where
the quadrature error of the windows shows.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pandas as pd

import hamid
from hamid.linear import design

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from accuracy import SYSTEMS, T_END, code_state, with_noise, worst_relative_error

FACTORS = (0.5, 0.75, 1.0, 1.5, 2.0)
ORDERS = (3, 4, 5, 6, 8)
NOISE_LEVELS = (0.01, 0.03)
COARSE_DT = 0.05

CLEAN: dict[tuple[str, float], pd.DataFrame] = {}


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _errors(frame: pd.DataFrame, name: str) -> dict[tuple[int, float], float]:
    """Worst relative error of the weak fit for every (order, factor)."""
    truth = SYSTEMS[name]["parameters"]
    saved = design.BUMP_ORDER
    out = {}
    try:
        default = hamid.fit(frame, method="weak", cov="classical").method["weak_window"]
        for order in ORDERS:
            design.BUMP_ORDER = order
            for factor in FACTORS:
                result = hamid.fit(frame, method="weak", weak_window=factor * default,
                                   cov="classical")
                estimate = np.array([result.estimates[p] for p in truth])
                out[(order, factor)] = worst_relative_error(estimate,
                                                            np.array(list(truth.values())))
    finally:
        design.BUMP_ORDER = saved
    out["window"] = default
    return out


def _task(args: tuple[str, float, float, int]) -> tuple[str, float, float, dict]:
    name, dt, noise, seed = args
    clean = CLEAN[(name, dt)]
    frame = clean if noise == 0 else with_noise(clean, noise, seed)
    return name, dt, noise, _errors(frame, name)


def _table(title: str, values: dict[tuple[int, float], float]) -> None:
    print(title)
    print(f"  {'order':>5} | " + "  ".join(f"{'x' + format(f, 'g'):>8}" for f in FACTORS))
    for order in ORDERS:
        mark = "*" if order == design.BUMP_ORDER else " "
        print(f"  {order:>4}{mark} | " + "  ".join(f"{values[(order, f)]:8.2e}"
                                                   for f in FACTORS))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--realizations", type=int, default=10)
    parser.add_argument("--systems", nargs="+", default=["peng-quadratic", "duffing"],
                        choices=list(SYSTEMS))
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args(argv)
    start = time.time()

    print(f"hamid weak-form window benchmark (method='weak'); hamid {hamid.__version__} "
          f"({code_state()})")
    print(f"records: t_end = {T_END:g} s; noisy runs at dt = 0.02 s; clean runs at "
          f"dt = {COARSE_DT:g} s and 0.02 s; ICs and parameters as in accuracy.py")
    print(f"columns: window = factor x the default (half the dominant period); rows: bump "
          f"order p of (1 - s^2)^p (* = the package default, BUMP_ORDER = "
          f"{design.BUMP_ORDER}); window step = {design.WINDOW_STEP:g} window")
    print(f"entries: median over {args.realizations} realizations of the worst parameter's "
          f"relative error (clean: one fit)")
    print()

    dts = (0.02, COARSE_DT)
    for name in args.systems:
        for dt in dts:
            system = {**SYSTEMS[name], "simulate": {"t_end": T_END, "dt": dt}}
            CLEAN[(name, dt)] = hamid.simulate(system)
            log(f"simulated {name} at dt = {dt}")

    tasks = []
    for i, name in enumerate(args.systems):
        for dt in dts:
            tasks.append((name, dt, 0.0, 0))
        for j, noise in enumerate(NOISE_LEVELS):
            tasks += [(name, 0.02, noise, 7_000_000 + 100_000 * i + 1_000 * j + r)
                      for r in range(args.realizations)]
    results: dict[tuple[str, float, float], list[dict]] = {}
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for done, (name, dt, noise, errors) in enumerate(pool.map(_task, tasks), start=1):
            results.setdefault((name, dt, noise), []).append(errors)
            if done % 5 == 0 or done == len(tasks):
                log(f"  {done}/{len(tasks)} records done ({time.time() - start:.0f} s)")

    for name in args.systems:
        for noise in NOISE_LEVELS:
            runs = results[(name, 0.02, noise)]
            windows = [r["window"] for r in runs]
            medians = {key: float(np.median([r[key] for r in runs]))
                       for key in runs[0] if key != "window"}
            _table(f"{name}, {noise * 100:g}% noise, dt = 0.02 (default window "
                   f"{np.median(windows):.3g} s, range {min(windows):.3g}-{max(windows):.3g})",
                   medians)
            best = min(medians, key=medians.get)
            default = medians[(design.BUMP_ORDER, 1.0)]
            print(f"  best: order {best[0]}, factor {best[1]:g}: {medians[best]:.2e}; "
                  f"default (order {design.BUMP_ORDER}, x1): {default:.2e} "
                  f"({default / medians[best]:.2f}x the best)")
            print()
        for dt in (COARSE_DT, 0.02):
            clean = results[(name, dt, 0.0)][0]
            _table(f"{name}, clean, dt = {dt:g} (default window {clean['window']:.3g} s = "
                   f"{clean['window'] / dt:.0f} samples)",
                   {k: v for k, v in clean.items() if k != "window"})
            print()
    print(f"runtime {time.time() - start:.0f} s with {args.workers} worker process(es)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
