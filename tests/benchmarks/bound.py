"""The default fit's spread against the true Cramér-Rao bound of each record.

    python tests/benchmarks/bound.py [--realizations 200] [--noise 0.01 0.03]
                                     [--systems peng-quadratic duffing] [--short]

Records: the accuracy benchmark's (100 s at dt 0.02, tests/benchmarks/accuracy.py), or with
--short the test suite's (30-40 s at dt 0.05, tests/conftest.py). Each realization adds
white Gaussian noise of a fixed fraction of each column's standard deviation to the
positions and the velocities (`with_noise`, seeds 0..R-1), and `hamid.fit` fits it with
its defaults (`auto`: the joint fit refined by the integrated trajectories).

The bound is computed here, independently of hamid: the equations of motion are written
by hand, the state is integrated with its variational equations (sensitivities to the
parameters and to the initial state, DOP853 at rtol 1e-12) over each whole trajectory,
and the Fisher information is sum_j J_j^T W J_j with W the true noise (1 / sigma_c^2 on
every recorded column, positions and velocities alike, as `with_noise` makes them). The
true bound frees one initial state per trajectory; the "segmented" bound frees one per
segment of hamid's first segmentation (four dominant periods, the report's
`method.refinement.segment_seconds`, cut by the same rule as hamid.refine.trajectory), from the
same sensitivities by the flow's composition. The script checks its sensitivities
against central differences of the integrated motion and its motion against the
simulated record.

Per parameter, over the realizations:

    spread/true   standard deviation of the estimates / sqrt(true bound)  (1 at best)
    spread/seg    the same against the segmented bound
    bias          (mean estimate - truth) / sqrt(true bound)
    se/true       mean reported standard error / sqrt(true bound)
    coverage      share of 95% bounds that hold the truth

The spread of R realizations is itself uncertain by about 1/sqrt(2(R-1)) (5% at 200).
"""

# ruff: noqa: E402  (the thread limits must be set before numpy is imported)
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import sys
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

import hamid

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from accuracy import SYSTEMS as LONG  # noqa: I001
from conftest import DUFFING, PENG, with_noise

SHORT: dict[str, dict[str, Any]] = {"peng-quadratic": PENG, "duffing": DUFFING}
RTOL = 1e-12


def _duffing(theta: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, ...]:
    """Force, its derivative by the coordinates and by the parameters (k, k3)."""
    k, k3 = theta
    (x,) = q
    return (np.array([-k * x - k3 * x**3]), np.array([[-k - 3 * k3 * x**2]]),
            np.array([[-x, -x**3]]))


def _peng(theta: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, ...]:
    """The same for peng-quadratic (w1sq, w2sq, a1, a2, a3, a6)."""
    w1sq, w2sq, a1, a2, a3, a6 = theta
    u1, u2 = q
    force = np.array([-w1sq * u1 + a1 * u1**2 + a2 * u1 * u2 + a3 * u2**2,
                      -w2sq * u2 + a2 * u1**2 / 2 + 2 * a3 * u1 * u2 + a6 * u2**2])
    by_q = np.array([[-w1sq + 2 * a1 * u1 + a2 * u2, a2 * u1 + 2 * a3 * u2],
                     [a2 * u1 + 2 * a3 * u2, -w2sq + 2 * a3 * u1 + 2 * a6 * u2]])
    by_theta = np.array([[-u1, 0, u1**2, u1 * u2, u2**2, 0],
                         [0, -u2, 0, u1**2 / 2, 2 * u1 * u2, u2**2]])
    return force, by_q, by_theta


FORCES: dict[str, Callable[..., tuple[np.ndarray, ...]]] = {
    "peng-quadratic": _peng, "duffing": _duffing}


def sensitivities(forces: Callable[..., tuple[np.ndarray, ...]], theta: np.ndarray,
                  x0: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The motion (m, 2N) from x0 at times[0] and its sensitivities (m, 2N, 2N + p) to the
    initial state and the parameters, from the variational equations."""
    n, p = len(x0), len(theta)
    N = n // 2

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        x, S = y[:n], y[n:].reshape(n, n + p)
        force, by_q, by_theta = forces(theta, x[:N])
        A = np.zeros((n, n))
        A[:N, N:] = np.eye(N)
        A[N:, :N] = by_q
        dS = A @ S
        dS[N:, n:] += by_theta
        return np.concatenate([x[N:], force, dS.ravel()])

    start = np.concatenate([x0, np.hstack([np.eye(n), np.zeros((n, p))]).ravel()])
    solution = solve_ivp(rhs, (times[0], times[-1]), start, method="DOP853", t_eval=times,
                         rtol=RTOL, atol=1e-14)
    assert solution.status == 0, solution.message
    y = solution.y.T
    return y[:, :n], y[:, n:].reshape(len(times), n, n + p)


def _pieces(times: np.ndarray, length: float) -> list[tuple[int, int]]:
    """hamid.refine.trajectory's segments of about `length` seconds of one trajectory (rows)."""
    span = times[-1] - times[0]
    count = max(1, int(round(span / length)))
    edges = np.searchsorted(times, times[0] + span * np.arange(count + 1) / count)
    edges[-1] = len(times)
    return [(a, b) for a, b in zip(edges[:-1], edges[1:], strict=True) if b - a >= 8]


def bound(jacobians: list[tuple[np.ndarray, np.ndarray]], weight: np.ndarray,
          p: int) -> np.ndarray:
    """The parameters' Cramér-Rao bound: per block of samples with its own free initial
    state, sensitivities to that state (m, 2N, 2N) and to the parameters (m, 2N, p)."""
    information = np.zeros((p, p))
    for by_state, by_theta in jacobians:
        Jx = (by_state * weight[None, :, None]).reshape(-1, by_state.shape[2])
        Jt = (by_theta * weight[None, :, None]).reshape(-1, p)
        Fxx, Fxt = Jx.T @ Jx, Jx.T @ Jt
        information += Jt.T @ Jt - Fxt.T @ np.linalg.solve(Fxx, Fxt)
    return np.linalg.inv(information)


class Record:
    """A system's clean record and what its bounds need."""

    def __init__(self, name: str, system: dict[str, Any]) -> None:
        self.clean = hamid.simulate(system)
        self.truth = dict(system["parameters"])
        self.names = list(self.truth)
        self.theta = np.array([self.truth[k] for k in self.names])
        self.columns = list(self.clean.columns[2:])
        forces = FORCES[name]
        self.trajectories = []
        worst = 0.0
        for _, part in self.clean.groupby("trajectory"):
            times = part["t"].to_numpy()
            X = part[self.columns].to_numpy()
            motion, S = sensitivities(forces, self.theta, X[0], times)
            worst = max(worst, float(np.abs(motion - X).max() / np.abs(X).max()))
            self.trajectories.append((times, S))
        print(f"{name}: {len(self.clean):,} samples, motion against the simulated record "
              f"{worst:.1e} (relative); sensitivities against central differences "
              f"{self._check(forces):.1e}")

    def _check(self, forces: Callable[..., tuple[np.ndarray, ...]]) -> float:
        """Largest relative difference of the first trajectory's sensitivities from
        central differences of the integrated motion."""
        times, S = self.trajectories[0]
        x0 = self.clean[self.columns].to_numpy()[0]
        n = len(x0)
        values = np.concatenate([x0, self.theta])
        worst = 0.0
        for k in range(len(values)):
            h = 1e-5 * max(abs(values[k]), 1.0)
            moved = []
            for sign in (1, -1):
                v = values.copy()
                v[k] += sign * h
                moved.append(sensitivities(forces, v[n:], v[:n], times)[0])
            difference = (moved[0] - moved[1]) / (2 * h)
            worst = max(worst, float(np.abs(difference - S[:, :, k]).max()
                                     / np.abs(S[:, :, k]).max()))
        return worst

    def bounds(self, relative: float, length: float | None) -> np.ndarray:
        """The parameters' bound at this noise: one initial state per trajectory, or one
        per segment of about `length` seconds."""
        weight = 1.0 / (relative * self.clean[self.columns].std().to_numpy())
        n, p = len(self.columns), len(self.theta)
        blocks = []
        for times, S in self.trajectories:
            if length is None:
                blocks.append((S[:, :, :n], S[:, :, n:]))
                continue
            for a, b in _pieces(times, length):
                # the flow's composition: x(t) depends on x(t_a) through
                # Phi(t) Phi(t_a)^-1, and on theta through the rest
                back = np.linalg.inv(S[a, :, :n])
                by_state = S[a:b, :, :n] @ back
                blocks.append((by_state, S[a:b, :, n:] - by_state @ S[a, :, n:]))
        return bound(blocks, weight, p)


def realizations(record: Record, relative: float, n: int) -> dict[str, Any]:
    """Estimates, standard errors and coverage of `n` default fits, and the segmentation."""
    estimates, errors, covered, shapes = [], [], [], Counter()
    lengths = []
    for seed in range(n):
        result = hamid.fit(with_noise(record.clean, relative, seed))
        by_name = {p.name: p for p in result.parameters}
        estimates.append([by_name[k].estimate for k in record.names])
        errors.append([by_name[k].stderr for k in record.names])
        covered.append([by_name[k].ci_low <= record.truth[k] <= by_name[k].ci_high
                        for k in record.names])
        refinement = result.to_dict()["method"].get("refinement") or {}
        lengths.append(refinement.get("segment_seconds"))
        shapes[_shape(refinement)] += 1
    return {"estimates": np.array(estimates), "errors": np.array(errors),
            "coverage": np.mean(covered, axis=0), "lengths": lengths, "shapes": shapes}


def _shape(refinement: dict[str, Any]) -> str:
    """How the refinement ended: not applied, or its segments (first and final)."""
    if not refinement.get("applied"):
        return "not applied"
    text = f"{refinement['segments']} segments"
    final = refinement.get("lengthening")
    if final:
        text += f" -> {final['segments']}"
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--realizations", type=int, default=200)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.03])
    parser.add_argument("--systems", nargs="+", default=list(SHORT), choices=list(SHORT))
    parser.add_argument("--short", action="store_true",
                        help="the test suite's records instead of the accuracy benchmark's")
    args = parser.parse_args()
    systems = SHORT if args.short else LONG
    started = time.perf_counter()
    worst: dict[str, float] = {"spread/true": 0.0}
    for name in args.systems:
        record = Record(name, systems[name])
        for relative in args.noise:
            runs = realizations(record, relative, args.realizations)
            true = np.sqrt(np.diag(record.bounds(relative, None)))
            lengths = [x for x in runs["lengths"] if x is not None]
            length = Counter(round(x, 6) for x in lengths).most_common(1)
            segmented = (np.sqrt(np.diag(record.bounds(relative, length[0][0])))
                         if length else np.full(len(true), np.nan))
            estimates = runs["estimates"]
            spread = estimates.std(axis=0, ddof=1)
            shapes = ", ".join(f"{k}: {v}" for k, v in runs["shapes"].most_common())
            print(f"\n{name} at {relative:g} noise, {args.realizations} realizations "
                  f"({shapes}; first segments of {length[0][0] if length else '-'} s)")
            print(f"  {'parameter':10s} {'spread/true':>11s} {'spread/seg':>10s} "
                  f"{'bias':>7s} {'se/true':>8s} {'coverage':>8s}")
            for k, parameter in enumerate(record.names):
                ratio = spread[k] / true[k]
                worst["spread/true"] = max(worst["spread/true"], ratio)
                print(f"  {parameter:10s} {ratio:11.3f} {spread[k] / segmented[k]:10.3f} "
                      f"{(estimates[:, k].mean() - record.theta[k]) / true[k]:7.3f} "
                      f"{runs['errors'][:, k].mean() / true[k]:8.3f} "
                      f"{runs['coverage'][k]:8.1%}")
    print(f"\nlargest spread/true: {worst['spread/true']:.3f}; "
          f"{time.perf_counter() - started:.0f} s in all")


if __name__ == "__main__":
    main()
