"""What the trajectory refinement costs per sample, and against what a user would write
instead, as ratios measured in the same process.

    python tests/benchmarks/refinement.py [--repeats 3] [--noise 0.01]

Records: Duffing (1 DOF), peng-quadratic (2 DOF) and a 3-DOF spring chain with a quartic
spring (a model given as a TOML [model] table), simulated at `--noise` relative
noise; peng-quadratic also at 10x and 100x the record length (the per-sample cost must not
grow with it), and clean (the strict-tolerance pass); the 100x record again without the
ties of the lengthening (what they cost).

For each record the default fit runs `--repeats` times with ``jobs=1`` and with one process
per core; the time spent in the whole refinement (`hamid.refine.joint_refinement.refine`:
the trajectory fits, the held-out check with its linear refits, the lengthening, starting
the worker processes) is taken from a wrapper around it and printed in µs per sample, with
the largest relative difference between the two fits' estimates (none: the batches do not
depend on the workers). Records short enough to stay in one process
(`hamid.refine.integration.PARALLEL_VALUES`) cost the same both ways.

The peer is `scipy.optimize.least_squares` over `solve_ivp` (DOP853) with the same
segments, weights and start: the free parameters and every
segment's initial state, the equations of motion written by hand, the Jacobian by
finite differences grouped by its block sparsity (`jac_sparsity`), as a careful user
would. It is timed at rtol 1e-10. Its estimates are compared to hamid's: the largest
relative difference, and in hamid's standard errors (hamid stops within 1e-3 standard
errors of its minimum). At rtol 1e-10 the peer's own integration error moves its minimum
by some 1e-4 standard errors, so the comparison is made three times (the last two
untimed): with the timed peer, with the peer at rtol 1e-12, and with the peer at rtol
1e-12 started from hamid's estimates and states. From its own start the peer stops where
its sum of squares no longer changes by 1e-12 of itself (`ftol`), which at 1e-4 standard
errors from the minimum it does not (the excess is some 1e-8 of a sum of about 10^4);
from hamid's point it would go on to the minimum if that point were not there.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

# Everything else is imported in the functions: the refinement's worker processes import
# this script again (as multiprocessing does with the main module), and would otherwise
# pay for scipy.optimize, pytest and pandas in every fit's pool.
ROOT = Path(__file__).resolve().parents[2]

CHAIN_SYSTEM = {
    "model": {"name": "chain3", "coordinates": ["x1", "x2", "x3"],
              "velocities": ["v1", "v2", "v3"],
              "energy": "(v1**2 + v2**2 + v3**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2"
                        " + k3*(x3 - x2)**2/2 + b*x1**4/4",
              "parameters": ["k1", "k2", "k3", "b"]},
    "parameters": {"k1": 1.0, "k2": 1.5, "k3": 0.8, "b": 0.3},
    "initial": [{"x1": 0.8, "x2": -0.3, "x3": 0.2, "v1": 0.0, "v2": 0.1, "v3": 0.0},
                {"x1": -0.4, "x2": 0.5, "x3": -0.6, "v1": 0.2, "v2": 0.0, "v3": -0.1}],
    "simulate": {"t_end": 40.0, "dt": 0.05, "seed": 2},
}


def _duffing(theta, y):
    k, k3 = theta
    x, v = y
    return np.array([v, -k * x - k3 * x**3])


def _peng(theta, y):
    w1sq, w2sq, a1, a2, a3, a6 = theta
    u1, u2, v1, v2 = y
    return np.array([v1, v2, -w1sq * u1 + a1 * u1**2 + a2 * u1 * u2 + a3 * u2**2,
                     -w2sq * u2 + a2 * u1**2 / 2 + 2 * a3 * u1 * u2 + a6 * u2**2])


def _chain(theta, y):
    k1, k2, k3, b = theta
    x1, x2, x3, v1, v2, v3 = y
    return np.array([v1, v2, v3, -k1 * x1 - b * x1**3 + k2 * (x2 - x1),
                     -k2 * (x2 - x1) + k3 * (x3 - x2), -k3 * (x3 - x2)])


def _peer(rhs, fit, t, X, theta0, rtol: float, states=None):
    """least_squares over solve_ivp on the fit's segments and weights, from `theta0` and
    each segment's first sample (or `states`, one row per segment)."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    pieces, weight = fit.problem.pieces, fit.problem.weight
    p, n = len(theta0), X.shape[1]
    rows = sum(b - a for a, b in pieces) * n
    sparsity = lil_matrix((rows, p + n * len(pieces)), dtype=int)
    offset = 0
    for s, (a, b) in enumerate(pieces):
        sparsity[offset:offset + (b - a) * n, :p] = 1
        sparsity[offset:offset + (b - a) * n, p + n * s:p + n * (s + 1)] = 1
        offset += (b - a) * n

    def residuals(z):
        theta, states = z[:p], z[p:].reshape(-1, n)
        out = []
        for (a, b), x0 in zip(pieces, states, strict=True):
            tau = t[a:b] - t[a]
            y = solve_ivp(lambda _t, y: rhs(theta, y), (0.0, tau[-1]), x0, method="DOP853",
                          t_eval=tau, rtol=rtol, atol=1e-3 * rtol).y
            out.append(((X[a:b] - y.T) * weight).ravel())
        return np.concatenate(out)

    if states is None:
        states = [X[a] for a, _ in pieces]
    start = np.concatenate([theta0, np.concatenate(states)])
    return least_squares(residuals, start, jac_sparsity=sparsity, x_scale="jac",
                         xtol=1e-12, ftol=1e-12, gtol=1e-12).x[:p]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--noise", type=float, default=0.01)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import DUFFING, PENG, with_noise

    import hamid
    from hamid.executor import available_cores
    from hamid.model.models import model_from_spec
    from hamid.refine import joint_refinement, trajectory

    chain = model_from_spec(CHAIN_SYSTEM["model"], where="chain3")
    longer = {f"peng-quadratic {k}x longer": {**PENG, "simulate": {**PENG["simulate"],
                                                                   "t_end": 40.0 * k}}
              for k in (10, 100)}
    cases = {   # label: (system, model file, rhs, run the peer)
        "duffing (1 DOF)": (DUFFING, None, _duffing, True),
        "peng-quadratic (2 DOF)": (PENG, None, _peng, True),
        "chain3 TOML (3 DOF)": (CHAIN_SYSTEM, chain, _chain, True),
        **{label: (system, None, _peng, False) for label, system in longer.items()},
    }
    spent: dict[str, float] = defaultdict(float)
    fits: list = []
    starts: list = []
    whole = joint_refinement.refine

    def timed_refinement(*a, **k):
        begin = time.perf_counter()
        try:
            return whole(*a, **k)
        finally:
            spent["refinement"] += time.perf_counter() - begin
    joint_refinement.refine = timed_refinement
    for name in ("refine", "refit"):   # the fits of the segments as cut
        original = getattr(trajectory, name)

        def wrapper(*a, _original=original, _name=name, **k):
            result = _original(*a, **k)
            if _name == "refine":
                starts.append(np.array(a[3], float)[list(a[4])])
            fits.append(result)
            return result
        setattr(trajectory, name, wrapper)

    def timed(frame, model, jobs):
        """µs per sample in the trajectory fits, and the estimates of the last fit."""
        hamid.fit(frame, model, jobs=jobs)   # warm: compiled functions
        spent.clear()
        for _ in range(args.repeats):
            fits.clear()
            starts.clear()
            result = hamid.fit(frame, model, jobs=jobs)
        return 1e6 * spent["refinement"] / args.repeats / len(frame), result.estimates

    cores = available_cores()
    print(f"{'record':28} {'samples':>8} {'µs/sample, 1 job':>17} "
          f"{f'{cores} jobs':>8} {'jobs diff':>9} {'peer µs/sample':>15} "
          f"{'peer / hamid':>13} {'max rel diff':>13} {'in stderrs':>12} "
          f"{'1e-12 peer':>13} {'in stderrs':>12} {'from hamid':>13} {'in stderrs':>12}")
    per_sample = {}
    for label, (system, model, rhs, peer) in cases.items():
        for noisy in (True, False) if label.startswith("peng-quadratic (") else (True,):
            frame = hamid.simulate(system)
            if noisy:
                frame = with_noise(frame, args.noise, 5)
            all_us, all_estimates = timed(frame, model, cores)
            hamid_us, estimates = timed(frame, model, 1)
            samples = len(frame)
            name = label + ("" if noisy else ", clean")
            per_sample[name] = hamid_us, all_us
            jobs_diff = max(abs(all_estimates[k] - v) / abs(v) for k, v in estimates.items())
            line = f"{name:28} {samples:8d} {hamid_us:17.2f} {all_us:8.2f} {jobs_diff:9.1e}"
            if peer and noisy:
                fit = trajectory.settle(fits[-1])   # the first fit stops sooner when joined
                t, X = frame["t"].to_numpy(), frame.iloc[:, 2:].to_numpy()
                begin = time.perf_counter()
                theta = _peer(rhs, fit, t, X, starts[0], rtol=1e-10)
                peer_us = 1e6 * (time.perf_counter() - begin) / samples
                mine = fit.theta[list(fit.free)]
                stderr = np.sqrt(np.diag(fit.covariance("scaled")))
                line += f" {peer_us:15.2f} {peer_us / hamid_us:13.1f}"
                for peer_theta in (theta, _peer(rhs, fit, t, X, starts[0], rtol=1e-12),
                                   _peer(rhs, fit, t, X, mine, 1e-12, fit.states)):
                    diff = np.abs(peer_theta - mine)
                    line += (f" {np.max(diff / np.abs(mine)):13.1e}"
                             f" {np.max(diff / stderr):12.1e}")
            print(line, flush=True)
    two = per_sample["peng-quadratic (2 DOF)"]
    ten, hundred = (per_sample[f"peng-quadratic {k}x longer"] for k in (10, 100))
    print(f"per-sample cost, 1 job / {cores} jobs: at 10x the length {ten[0] / two[0]:.2f}x / "
          f"{ten[1] / two[1]:.2f}x of the short record; at 100x {hundred[0] / ten[0]:.2f}x / "
          f"{hundred[1] / ten[1]:.2f}x of the 10x record; clean / noisy: "
          f"{per_sample['peng-quadratic (2 DOF), clean'][0] / two[0]:.2f}x")
    joint_refinement.LONGEST_PERIODS = 0.0   # no segments tied: what the lengthening costs
    untied_us, _ = timed(frame, None, 1)
    print(f"{label} without the ties of the lengthening: {untied_us:.2f} µs/sample, 1 job "
          f"(with them {hundred[0] / untied_us:.2f}x that)")


if __name__ == "__main__":
    main()
