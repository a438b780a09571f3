"""Model-selection benchmark: how often each method chooses exactly the true terms.

    python tests/benchmarks/selection.py [--realizations 40] [--noise 0.01 0.03]
                                         [--systems duffing peng-quadratic ...] [--t-end 120]

The systems are those of tests/selection/test_select.py (three built-in models and two with a term
a poly:N:4 library tempts to include), simulated once over t_end = 120 s (dt = 0.05 s);
each realization adds white noise of a fraction of each column's spread to positions and
velocities (`with_noise` of tests/conftest.py), from seeds 0, 1, ... Every method sees the
same noisy records, and a realization counts when the method's terms are exactly the
true ones.

Methods
-------
hamid bic, hamid cv
    ``hamid.selection.select_terms.choose`` with the library poly:N:4 (monomials of degree
    2-4 in the coordinates) and ``--criterion bic`` (the default) or ``cv``.
STLSQ
    PySINDy 2.x, the equations of motion v' = Theta(q) xi with Theta the polynomials of
    degree 1-3 in the positions (the forces of a degree 2-4 potential), derivatives by
    its SmoothedFiniteDifference; its threshold tuned on realization 0 of each system and
    noise level: over a grid of 36 thresholds from 1e-3 to 3, the geometric middle of those
    that give the true terms there (else the one with the fewest wrong terms). The true
    terms of the v_i' equation are the monomials of -dV/dq_i.
E-SINDy
    The same STLSQ, tuned threshold, inside PySINDy's EnsembleOptimizer with bagging (20
    models on resampled time points, median of the coefficients: "bragging"), seeded.

PySINDy is installed only for this benchmark (``pip install pysindy``); without it the
PySINDy columns are skipped. The script prints the rates and a markdown table.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")   # small matrices: threads only cost on a shared machine

import argparse
import copy
import re
import sys
import time
import warnings

import numpy as np

import hamid
from hamid.selection import select_terms

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from conftest import with_noise  # noqa: I001
from test_select import CASES, _true_terms

try:
    import pysindy as ps
except ImportError:   # the benchmark runs without it; the PySINDy columns are skipped
    ps = None

T_END = 120.0
THRESHOLDS = np.logspace(-3, np.log10(3.0), 36)


def true_pattern(name: str, feature_names: list[str], n: int) -> np.ndarray:
    """(N, n_features) booleans: the monomials of -dV/dq_i in each v_i' equation."""
    _, _, coefficients = CASES[name]
    powers = [tuple(int(e) for e in p.split("_")[1:]) for p in coefficients]
    features = [_exponents(f, n) for f in feature_names]
    pattern = np.zeros((n, len(features)), dtype=bool)
    for e in powers:
        for i in range(n):
            if e[i]:
                force = tuple(k - (j == i) for j, k in enumerate(e))
                pattern[i, features.index(force)] = True
    return pattern


def _exponents(feature: str, n: int) -> tuple[int, ...]:
    """Exponents of a PySINDy polynomial feature name such as 'x0^2 x1'."""
    e = [0] * n
    for factor in feature.split():
        match = re.fullmatch(r"x(\d+)(?:\^(\d+))?", factor)
        assert match, feature
        e[int(match[1])] += int(match[2] or 1)
    return tuple(e)


def sindy_pattern(frame, variables: list[str], n: int, optimizer) -> tuple[np.ndarray, list]:
    """The active terms of the v' equations of a SINDy fit, and the feature names."""
    xs, ts = [], []
    for _, part in frame.groupby("trajectory"):
        xs.append(part[variables].to_numpy())
        ts.append(part["t"].to_numpy())
    library = ps.GeneralizedLibrary([ps.PolynomialLibrary(degree=3, include_bias=False)],
                                    inputs_per_library=[list(range(n))])
    model = ps.SINDy(optimizer=optimizer, feature_library=library,
                     differentiation_method=ps.SmoothedFiniteDifference())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(xs, t=ts)
    return np.asarray(model.coefficients())[n:] != 0, model.get_feature_names()


def tune(frame, variables: list[str], n: int, name: str) -> float:
    """STLSQ's threshold tuned on one realization (see the module docstring)."""
    misses = []
    for threshold in THRESHOLDS:
        pattern, features = sindy_pattern(frame, variables, n, ps.STLSQ(threshold=threshold))
        misses.append(int(np.sum(pattern != true_pattern(name, features, n))))
    exact = np.flatnonzero(np.array(misses) == 0)
    if exact.size:
        return float(np.sqrt(THRESHOLDS[exact[0]] * THRESHOLDS[exact[-1]]))
    return float(THRESHOLDS[int(np.argmin(misses))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realizations", type=int, default=40)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.03])
    parser.add_argument("--systems", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--t-end", type=float, default=T_END, help="record length, s")
    args = parser.parse_args()
    print(f"hamid {hamid.__version__}; pysindy "
          f"{ps.__version__ if ps is not None else 'not installed (columns skipped)'}; "
          f"{args.realizations} realizations, t_end = {args.t_end:g} s")
    rows = []
    for name in args.systems:
        system, library, _ = CASES[name]
        system = copy.deepcopy(system)
        system["simulate"]["t_end"] = args.t_end
        clean = hamid.simulate(system)
        variables = [c for c in clean.columns if c not in ("trajectory", "t")]
        n = len(variables) // 2
        truth = sorted(_true_terms(name))
        for noise in args.noise:
            started = time.perf_counter()
            frames = [with_noise(clean, noise, seed) for seed in range(args.realizations)]
            hits = {}
            for criterion in ("bic", "cv"):
                hits[f"hamid {criterion}"] = sum(
                    sorted((c := select_terms.choose(f, select_terms.SelectOptions(
                        library, criterion=criterion))).library.texts(c.chosen)) == truth
                    for f in frames)
            threshold = None
            if ps is not None:
                threshold = tune(frames[0], variables, n, name)
                for label in ("STLSQ", "E-SINDy"):
                    count = 0
                    for seed, f in enumerate(frames):
                        np.random.seed(seed)  # noqa: NPY002 (PySINDy draws from the legacy global state)
                        optimizer = ps.STLSQ(threshold=threshold)
                        if label == "E-SINDy":
                            optimizer = ps.EnsembleOptimizer(optimizer, bagging=True,
                                                             n_models=20)
                        pattern, features = sindy_pattern(f, variables, n, optimizer)
                        count += bool(np.all(pattern == true_pattern(name, features, n)))
                    hits[label] = count
            rates = {k: v / args.realizations for k, v in hits.items()}
            rows.append((name, library, noise, rates, threshold))
            print(f"{name:17s} {noise:5.0%}  " + "  ".join(f"{k} {v:4.0%}"
                                                           for k, v in rates.items())
                  + (f"  (STLSQ threshold {threshold:.3g})" if threshold else "")
                  + f"  [{time.perf_counter() - started:.0f} s]", flush=True)
    methods = list(rows[0][3])
    print("\n| system | library | noise | " + " | ".join(methods) + " |")
    print("|---|---|---|" + "---|" * len(methods))
    for name, library, noise, rates, threshold in rows:
        cells = [f"{rates[m]:.0%}" + (f" (threshold {threshold:.2g})"
                                       if m == "STLSQ" and threshold else "") for m in methods]
        print(f"| {name} | {library} | {noise:.0%} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
