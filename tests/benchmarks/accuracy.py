"""Accuracy benchmark: hamid's methods against the plain peers under measurement noise.

    python tests/benchmarks/accuracy.py [--realizations 20] [--systems peng-quadratic duffing ...]
                                        [--noise 0.001 0.01 0.03 0.05] [--workers N]

For every system the clean record is simulated once; each realization adds white Gaussian
noise of a fixed fraction of each column's standard deviation (over the whole record) to
the positions and velocities, from a fixed seed. Every method fits the same noisy record;
the score of one fit is the worst parameter's relative error, max_k |theta_k / true_k - 1|,
and the table shows its median over the realizations.

Methods
-------
energy, weak, joint, auto
    ``hamid.fit(frame, method=...)`` with its defaults (weak-form window: half the dominant
    period found from the data); ``auto`` is the joint fit refined by fitting the
    integrated trajectories (hamid.refine.trajectory). ``cov="classical"`` is passed to the
    linear methods only to save time: their estimates do not depend on ``cov`` (the script
    checks this on one record per system); ``auto`` keeps its default ``cov="hac"``, the
    only one under which the refinement runs.
fd
    Least squares on Lagrange's equations with central-difference accelerations from the
    recorded velocities (``finite_difference_fit`` of tests/conftest.py).
sindy-fd, sindy-sfd
    PySINDy 2.x: STLSQ with threshold 0 (every library term kept, then an unregularised
    least-squares refit, so this is plain least squares per equation), a library whose
    terms span the model's forces (positions only, see SINDY_LIBRARIES), its own
    differentiation (FiniteDifference, resp. SmoothedFiniteDifference with its default
    Savitzky-Golay smoother), fitted on the state [q, v] with t; the coefficients of the
    v_i' equations are mapped back to the parameters (see `sindy_map`). Both variants are
    reported and the better one counts as "the" PySINDy peer. PySINDy is installed only for
    this benchmark (``pip install pysindy``); without it those columns are skipped.

The "best peer" is the lowest median among fd, sindy-fd and sindy-sfd.
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")   # one thread per worker process

import argparse
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import pandas as pd

import hamid
from hamid.model.models import Model, model_from_spec

# The noise and the finite-difference peer are the test suite's own (tests/conftest.py).
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from conftest import (  # noqa: I001
    DUFFING,
    ELASTIC_PENDULUM,
    PENG,
    TWO_MASS,
    finite_difference_fit,
    with_noise,
)

try:
    import pysindy as ps
except ImportError:   # the benchmark runs without it; the PySINDy columns are skipped
    ps = None

T_END, DT = 100.0, 0.02
SIMULATE = {"t_end": T_END, "dt": DT}

# The test suite's systems (tests/conftest.py) on a longer record; peng-quadratic with
# three larger swings, so that its cubic terms matter.
SYSTEMS: dict[str, dict[str, Any]] = {
    "peng-quadratic": {**PENG, "simulate": SIMULATE,
                       "initial": [{"u1": 0.45, "u2": -0.2, "v1": 0.0, "v2": 0.2},
                                   {"u1": -0.3, "u2": 0.35, "v1": 0.2, "v2": 0.0},
                                   {"u1": 0.2, "u2": 0.4, "v1": -0.1, "v2": 0.1}]},
    "duffing": {**DUFFING, "simulate": SIMULATE},
    # Two masses on springs, the second mass unknown (a parameter in the kinetic energy).
    "two-mass": {**TWO_MASS, "simulate": SIMULATE},
    # A non-polynomial energy (evaluated through sympy).
    "elastic-pendulum": {**ELASTIC_PENDULUM, "simulate": SIMULATE},
}
DEFAULT_SYSTEMS = ["peng-quadratic", "duffing", "two-mass", "elastic-pendulum"]
NOISE_LEVELS = [0.001, 0.01, 0.03, 0.05]
HAMID_METHODS = ("energy", "weak", "joint", "auto")
PEERS = ("fd", "sindy-fd", "sindy-sfd")
TARGETS = {0.01: 1.5, 0.03: 2.0, 0.05: 2.0}   # auto at least this much better than best peer


def _polynomial(degree: int):
    return lambda: ps.PolynomialLibrary(degree=degree, include_bias=False)


def _radial():
    # x, y (1-argument functions) and x/r, y/r (2-argument functions on the pair (x, y)),
    # plus a constant for gravity: the forces -k q + kL q/r - g e_y.
    return ps.CustomLibrary(
        library_functions=[lambda a: a,
                           lambda a, b: a / np.sqrt(a**2 + b**2),
                           lambda a, b: b / np.sqrt(a**2 + b**2)],
        function_names=[lambda a: a, lambda a, b: f"{a}/r", lambda a, b: f"{b}/r"],
        include_bias=True)


# The SINDy library per system, over the positions only (the forces depend on them alone;
# velocity terms would only add regressors to the v' equations). The q' = v equations are
# then not representable and are ignored: only the v' equations carry the parameters.
SINDY_LIBRARIES = {
    "peng-quadratic": ("polynomials of degree 1-2 in (u1, u2)", _polynomial(2)),
    "duffing": ("polynomials of degree 1-3 in x", _polynomial(3)),
    "two-mass": ("polynomials of degree 1-3 in (x1, x2)", _polynomial(3)),
    "elastic-pendulum": ("1, x, y, x/r, y/r", _radial),
}


def code_state() -> str:
    """The hamid commit the numbers come from, and whether its package files were edited."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, text=True,
                              capture_output=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "hamid"], cwd=root,
                               text=True, capture_output=True, check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        return "unknown commit"
    edited = [f for f in dirty if f.endswith(".py")]
    return f"commit {head}" + (f" with uncommitted edits to {', '.join(edited)}"
                               if edited else "")


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def worst_relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(estimate) / truth - 1)))





# ----------------------------------------------------------------------------------------
# PySINDy and the map from its coefficients back to the parameters.

class SindyMap:
    """Maps the coefficients of SINDy's v' equations back to the model parameters.

    Every model here is natural with a constant mass matrix, L = L0 + sum_k theta_k L_k:

        M(theta) v' = F(q; theta),   M(theta) = M0 + sum_k theta_k M_k,
                                     F(q; theta) = F0(q) + sum_k theta_k F_k(q),

    with M_k = d2 L_k / dv dv and F_k = dL_k / dq. Each force column F_k,i lies in the span
    of the library Theta(q), so F_k,i = Theta(q) B_k[i] exactly; B_k is found by regressing
    the force columns on the library over the clean record (a residual above 1e-8 means the
    library cannot represent the forces: then no clean map exists and the column says so).

    SINDy fits v' = Theta(q) C, i.e. C = M(theta)^-1 B(theta). For unit masses (every
    M_k = 0) this is linear, C = B0 + sum_k theta_k B_k. With the unknown mass of the
    two-mass model, m divides the whole second equation: C_2 = (B0_2 + sum theta_k B_k,2) / m,
    nonlinear in theta. Multiplying through by the mass matrix gives the equation-error form

        sum_k theta_k (M_k C - B_k) = B0 - M0 C,

    linear in theta (for two-mass: row 1 C_1 = k1 B_k1,1 + k2 B_k2,1 + k3 B_k3,1, row 2
    m C_2 = k2 B_k2,2 + k3 B_k3,2), which is solved by least squares over every coefficient
    of the v' equations, zeros included. On exact derivatives it returns the truth to
    rounding (checked below); with noisy C it is one reasonable estimator among several.
    """

    def __init__(self, model: Model, clean: pd.DataFrame, library_factory) -> None:
        self.model = model
        self.N = len(model.coordinates)
        self.factory = library_factory
        X = clean[list(model.variables)].to_numpy()
        lib = self._library()
        lib.fit(X)
        Theta = lib.transform(X)
        Theta = np.asarray(Theta)
        self.feature_names = lib.get_feature_names(list(model.variables))
        lag = model.lagrangian
        parts = (lag.L0, *lag.L)
        self.B, self.M = [], []
        worst = 0.0
        for f in parts:
            forces = np.column_stack([f.diff(q)(X) * np.ones(len(X))
                                      for q in model.coordinates])
            coef, *_ = np.linalg.lstsq(Theta, forces, rcond=None)
            worst = max(worst, float(np.max(np.abs(Theta @ coef - forces)))
                        / max(float(np.max(np.abs(forces))), 1e-300) if forces.any() else 0.0)
            self.B.append(coef.T)  # (N, n_features)
            mass = np.array([[np.atleast_1d(f.diff(v).diff(w)(X) * np.ones(len(X)))
                              for w in model.velocities] for v in model.velocities])
            if np.ptp(mass, axis=-1).max() > 1e-12:
                raise ValueError("the mass matrix is not constant: no linear map")
            self.M.append(mass[..., 0])
        self.span_residual = worst
        self.ok = worst < 1e-8
        # The v' equations: L = T - V, so d/dt dL/dv = dL/dq has M v' = F with the signs
        # of L itself; nothing to flip.

    def _library(self):
        return ps.GeneralizedLibrary([self.factory()],
                                     inputs_per_library=[list(range(self.N))])

    def parameters(self, C: np.ndarray) -> np.ndarray:
        """theta from the (N, n_features) coefficients of the v' equations."""
        M0, B0 = self.M[0], self.B[0]
        columns = [(Mk @ C - Bk).ravel() for Mk, Bk in zip(self.M[1:], self.B[1:],
                                                            strict=True)]
        target = (B0 - M0 @ C).ravel()
        theta, *_ = np.linalg.lstsq(np.column_stack(columns), target, rcond=None)
        return theta

    def fit(self, frame: pd.DataFrame, smoothed: bool,
            exact_derivative: bool = False) -> np.ndarray:
        xs, ts, xdots = [], [], []
        for _, part in frame.groupby("trajectory"):
            X = part[list(self.model.variables)].to_numpy()
            xs.append(X)
            ts.append(part["t"].to_numpy())
            if exact_derivative:
                xdots.append(self.exact_derivative(X))
        differentiation = (ps.SmoothedFiniteDifference() if smoothed
                           else ps.FiniteDifference())
        sindy = ps.SINDy(optimizer=ps.STLSQ(threshold=0.0), feature_library=self._library(),
                         differentiation_method=differentiation)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sindy.fit(xs, t=ts, x_dot=xdots if exact_derivative else None)
        coef = np.asarray(sindy.coefficients())    # (2N, n_features): q' rows, then v'
        return self.parameters(coef[self.N:])

    def exact_derivative(self, X: np.ndarray) -> np.ndarray:
        """[v, M^-1 F] at the true parameters, from the model's Lagrangian (for the check)."""
        theta = np.array([1.0, *self.truth])
        lag = self.model.lagrangian
        parts = (lag.L0, *lag.L)
        F = sum(w * np.column_stack([f.diff(q)(X) * np.ones(len(X))
                                     for q in self.model.coordinates])
                for w, f in zip(theta, parts, strict=True))
        M = sum(w * Mk for w, Mk in zip(theta, self.M, strict=True))
        return np.column_stack([X[:, self.N:], np.linalg.solve(M, F.T).T])


# ----------------------------------------------------------------------------------------
# Worker state, shared with the worker processes by fork.

CLEAN: dict[str, pd.DataFrame] = {}
MODELS: dict[str, Model] = {}
MAPS: dict[str, SindyMap | None] = {}
TRUTH: dict[str, np.ndarray] = {}


def _fit_all(name: str, frame: pd.DataFrame) -> dict[str, np.ndarray]:
    """Signed relative error of every parameter, per method (NaN where it cannot run)."""
    truth = TRUTH[name]
    model = MODELS[name]
    nan = np.full(len(truth), np.nan)
    errors = {}
    for method in HAMID_METHODS:
        try:
            result = hamid.fit(frame, model, method=method,
                               cov="hac" if method == "auto" else "classical")
            estimate = np.array([result.estimates[p] for p in model.parameters])
            errors[method] = estimate / truth - 1
        except hamid.HamidError as exc:   # reported, not hidden
            log(f"  {name} {method}: {exc}")
            errors[method] = nan
    errors["fd"] = finite_difference_fit(frame, model) / truth - 1
    sindy_map = MAPS.get(name)
    for column, smoothed in (("sindy-fd", False), ("sindy-sfd", True)):
        if sindy_map is None or not sindy_map.ok:
            errors[column] = nan
        else:
            errors[column] = sindy_map.fit(frame, smoothed) / truth - 1
    return errors


def _task(args: tuple[str, float, int]) -> tuple[str, float, int, dict[str, np.ndarray]]:
    name, noise, seed = args
    frame = CLEAN[name] if noise == 0 else with_noise(CLEAN[name], noise, seed)
    return name, noise, seed, _fit_all(name, frame)


def seed_of(system_index: int, noise_index: int, realization: int) -> int:
    return 1_000_000 * (system_index + 1) + 1_000 * noise_index + realization


# ----------------------------------------------------------------------------------------

def _format(x: float) -> str:
    return "     n/a" if not np.isfinite(x) else f"{x:8.2e}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--realizations", type=int, default=20)
    parser.add_argument("--systems", nargs="+", default=DEFAULT_SYSTEMS,
                        choices=list(SYSTEMS))
    parser.add_argument("--noise", nargs="+", type=float, default=NOISE_LEVELS,
                        help="relative noise levels (fractions of each column's std)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args(argv)
    start = time.time()

    columns = [*HAMID_METHODS, *PEERS]
    print("hamid accuracy benchmark")
    print(f"hamid {hamid.__version__} ({code_state()}); numpy {np.__version__}; pysindy "
          f"{ps.__version__ if ps is not None else 'not installed (columns skipped)'}")
    print(f"records: t_end = {T_END:g} s, dt = {DT:g} s ({int(round(T_END / DT)) + 1} samples "
          f"per trajectory); noise: white Gaussian, a fraction of each column's std, on "
          f"positions and velocities")
    print(f"score: median over {args.realizations} seeded realizations of the worst "
          f"parameter's relative error max_k |est_k/true_k - 1| (clean row: one fit)")
    print("hamid fits: default window (half the dominant period); auto with its default "
          "cov='hac' (the trajectory refinement runs only then), the linear methods with "
          "cov='classical' (their estimates do not depend on cov)")
    print()

    # Set up every system: clean record, model, SINDy map and its check.
    for name in args.systems:
        system = SYSTEMS[name]
        t0 = time.time()
        CLEAN[name] = hamid.simulate(system)
        MODELS[name] = model_from_spec(system["model"])
        TRUTH[name] = np.array([system["parameters"][p] for p in MODELS[name].parameters])
        log(f"simulated {name} in {time.time() - t0:.1f} s")
        spreads = CLEAN[name].iloc[:, 2:].agg(lambda c: c.max() - c.min())
        print(f"system {name}: parameters {system['parameters']}")
        print(f"  initial states: {system['initial']}")
        frame = CLEAN[name]
        print("  state ranges: " + ", ".join(
            f"{c} {frame[c].min():+.3f}..{frame[c].max():+.3f}" for c in spreads.index))
        if ps is None:
            MAPS[name] = None
            print("  PySINDy: not installed, columns skipped (pip install pysindy)")
            continue
        description, factory = SINDY_LIBRARIES[name]
        sindy_map = SindyMap(MODELS[name], CLEAN[name], factory)
        sindy_map.truth = TRUTH[name]
        MAPS[name] = sindy_map
        print(f"  PySINDy library: {description} -> features {sindy_map.feature_names}")
        if not sindy_map.ok:
            print(f"  PySINDy: the library does not span the forces (residual "
                  f"{sindy_map.span_residual:.1e}): no clean map, columns skipped")
            continue
        exact = worst_relative_error(
            sindy_map.fit(CLEAN[name], smoothed=False, exact_derivative=True), TRUTH[name])
        print(f"  PySINDy map check, clean data with exact derivatives: worst rel. error "
              f"{exact:.1e} (library span residual {sindy_map.span_residual:.1e})")
        # cov does not change the linear fits' estimates: check once per system.
        noisy = with_noise(CLEAN[name], 0.03, 12345)
        a = hamid.fit(noisy, MODELS[name], method="joint", cov="classical").estimates
        b = hamid.fit(noisy, MODELS[name], method="joint").estimates
        same = max(abs(a[p] / b[p] - 1) for p in a)
        print(f"  check: joint estimates with cov='classical' vs default 'hac' differ by "
              f"{same:.1e} (relative)")
    print()

    tasks = [(name, 0.0, 0) for name in args.systems]
    for i, name in enumerate(args.systems):
        for j, noise in enumerate(args.noise):
            tasks += [(name, noise, seed_of(i, j, r)) for r in range(args.realizations)]
    results: dict[tuple[str, float], list[dict[str, np.ndarray]]] = {}
    done = 0
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        for name, noise, _seed, errors in pool.map(_task, tasks, chunksize=2):
            results.setdefault((name, noise), []).append(errors)
            done += 1
            if done % 10 == 0 or done == len(tasks):
                log(f"  {done}/{len(tasks)} fits done ({time.time() - start:.0f} s)")

    # worst[key][column]: the worst parameter's |relative error| of each realization.
    worst = {key: {c: np.array([np.max(np.abs(e[c])) for e in runs]) for c in columns}
             for key, runs in results.items()}
    medians = {key: {c: float(np.median(w[c])) for c in columns} for key, w in worst.items()}

    print("Median worst relative error")
    header = f"{'system':<17} {'noise':>6}  " + "  ".join(f"{c:>9}" for c in columns)
    print(header)
    print("-" * len(header))
    for name in args.systems:
        for noise in [0.0, *args.noise]:
            m = medians[(name, noise)]
            print(f"{name:<17} {noise * 100:5.1f}%  "
                  + "  ".join(f"{_format(m[c]):>9}" for c in columns))
    print()

    print("Ratios (larger = auto more accurate); 'range': 5-95% of best-peer/auto over "
          "bootstrap resamples of the realizations; 'worst': the parameter most often worst")
    header = (f"{'system':<17} {'noise':>6}  {'best peer':>10}  {'peer/auto':>9}  "
              f"{'range':>11}  {'fd/auto':>8}  {'sindy/auto':>10}  {'energy/auto':>11}  "
              f"{'worst auto/peer':>16}  {'target':>7}  {'holds':>5}")
    print(header)
    print("-" * len(header))
    rng = np.random.default_rng(2024)
    verdicts = []
    for name in args.systems:
        m0 = medians[(name, 0.0)]
        clean_ok = m0["auto"] <= 1e-8 and m0["energy"] <= 1e-8
        print(f"{name:<17} {'0.0%':>6}  clean: auto {m0['auto']:.1e}, energy "
              f"{m0['energy']:.1e}; target both <= 1e-8: {'yes' if clean_ok else 'NO'}")
        verdicts.append((name, 0.0, clean_ok))
        for noise in args.noise:
            m, w, runs = medians[(name, noise)], worst[(name, noise)], results[(name, noise)]
            peers = {c: m[c] for c in PEERS if np.isfinite(m[c])}
            best = min(peers, key=peers.get)
            ratio = peers[best] / m["auto"]
            n = len(w["auto"])
            draws = rng.integers(0, n, size=(1000, n))
            resampled = (np.min([np.median(w[c][draws], axis=1) for c in peers], axis=0)
                         / np.median(w["auto"][draws], axis=1))
            low, high = np.percentile(resampled, [5, 95])
            sindy = [m[c] for c in ("sindy-fd", "sindy-sfd") if np.isfinite(m[c])]
            sindy_ratio = f"{min(sindy) / m['auto']:10.2f}" if sindy else f"{'n/a':>10}"
            names = MODELS[name].parameters

            def most_often_worst(column: str, runs=runs, names=names) -> str:
                picks = [names[int(np.argmax(np.abs(e[column])))] for e in runs]
                return max(set(picks), key=picks.count)

            worst_names = f"{most_often_worst('auto')}/{most_often_worst(best)}"
            target = TARGETS.get(noise)
            holds = "-" if target is None else ("yes" if ratio >= target else "NO")
            if target is not None:
                verdicts.append((name, noise, ratio >= target))
            print(f"{name:<17} {noise * 100:5.1f}%  {best:>10}  {ratio:9.2f}  "
                  f"{f'{low:.2f}-{high:.2f}':>11}  "
                  f"{m['fd'] / m['auto']:8.2f}  {sindy_ratio}  "
                  f"{m['energy'] / m['auto']:11.2f}  {worst_names:>16}  "
                  f"{'>= ' + format(target, 'g') if target else '-':>7}  {holds:>5}")
    print()
    failed = [(n, z) for n, z, ok in verdicts if not ok]
    if failed:
        print("targets NOT met for: " + ", ".join(f"{n} at {z * 100:g}%" for n, z in failed))
    else:
        print("all targets met")
    if ps is None:
        print("note: PySINDy is not installed, so the best peer is the fd fit alone")
    elapsed = time.time() - start
    print(f"runtime {elapsed:.0f} s with {args.workers} worker process(es)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
