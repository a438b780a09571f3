"""Simulation speed: `hamid.simulate` against a plain per-trajectory `solve_ivp` loop.

    python tests/benchmarks/simulate_speed.py [--scale full|small|both] [--repeat 3]
                                              [--seed 0]

The case of issue #9: peng-quadratic (w1sq=1, w2sq=2.25, a1=0.3, a2=-0.4, a3=0.25,
a6=0.2), random small initial states whose energy is at most a quarter of the escape
energy (the lowest saddle of the potential), sampled at dt = 0.01.

    full   100 trajectories x 10^5 samples (t_end = 999.99)
    small   10 trajectories x 10^4 samples (t_end = 99.99)

The baseline is what a user would write without hamid: for each trajectory, `solve_ivp`
with DOP853 at the same tolerances (rtol 1e-11, atol 1e-12) and the same sampling
(`t_eval`), on a hand-written numpy right-hand side of this one model. Its timed part is the
loop of integrations and stacking the samples into one array. hamid's timed part is the
whole `hamid.simulate(system)` call: checks, equations of motion derived from the energy,
integration, energy drift, provenance and the DataFrame. Both run in this process, after a
short warm-up of each (imports, first calls), so the ratio does not depend on how fast this
machine happens to be; the timed runs alternate between the two, and the medians of wall
and CPU (process) time are reported. hamid is timed `--repeat` times; the loop as often at
the small scale and once at the full scale, where it takes minutes.

The energy drift of both is computed here from the hand-written energy, as
max_t |E(t) - E(0)| / |E(0)| over each trajectory, worst trajectory reported.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import root

import hamid

PARAMETERS = {"w1sq": 1.0, "w2sq": 2.25, "a1": 0.3, "a2": -0.4, "a3": 0.25, "a6": 0.2}
VARIABLES = ("u1", "u2", "v1", "v2")
RTOL, ATOL, DT = 1e-11, 1e-12, 0.01
SCALES = {"small": (10, 10_000), "full": (100, 100_000)}


def potential(u1, u2, p=PARAMETERS):
    return (p["w1sq"] * u1**2 / 2 + p["w2sq"] * u2**2 / 2 - p["a1"] * u1**3 / 3
            - p["a2"] * u1**2 * u2 / 2 - p["a3"] * u1 * u2**2 - p["a6"] * u2**3 / 3)


def energy(u1, u2, v1, v2):
    return (v1**2 + v2**2) / 2 + potential(u1, u2)


def gradient(u, p=PARAMETERS):
    u1, u2 = u
    return [p["w1sq"] * u1 - p["a1"] * u1**2 - p["a2"] * u1 * u2 - p["a3"] * u2**2,
            p["w2sq"] * u2 - p["a2"] * u1**2 / 2 - 2 * p["a3"] * u1 * u2 - p["a6"] * u2**2]


def escape_energy():
    """The potential at its lowest critical point other than the origin (a saddle)."""
    levels = []
    for start in np.array(np.meshgrid(np.linspace(-8, 8, 9), np.linspace(-8, 8, 9))).reshape(
            2, -1).T:
        found = root(gradient, start)
        if found.success and np.hypot(*found.x) > 1e-6:
            levels.append(potential(*found.x))
    return min(level for level in levels if level > 0)


def initial_states(n_traj, seed):
    """Random states with 0 < E <= E_escape / 4: position and velocity in random directions."""
    rng = np.random.default_rng(seed)
    limit = escape_energy() / 4
    states = []
    while len(states) < n_traj:
        u1, u2, v1, v2 = rng.uniform(-0.6, 0.6, 4)
        if 0 < energy(u1, u2, v1, v2) <= limit:
            states.append({v: float(x) for v, x in zip(VARIABLES, (u1, u2, v1, v2),
                                                       strict=True)})
    return states, limit


def rhs(t, y, p=PARAMETERS):
    """Peng-quadratic equations of motion, written by hand: u'' = -dV/du."""
    u1, u2, v1, v2 = y
    return np.array([
        v1,
        v2,
        -p["w1sq"] * u1 + p["a1"] * u1**2 + p["a2"] * u1 * u2 + p["a3"] * u2**2,
        -p["w2sq"] * u2 + p["a2"] * u1**2 / 2 + 2 * p["a3"] * u1 * u2 + p["a6"] * u2**2,
    ])


def baseline(states, times):
    """The plain loop: one solve_ivp per trajectory. Returns (n_traj, n_samples, 4)."""
    out = []
    for state in states:
        solution = solve_ivp(rhs, (0.0, times[-1]), [state[v] for v in VARIABLES],
                             method="DOP853", t_eval=times, rtol=RTOL, atol=ATOL)
        if not solution.success:
            raise RuntimeError(solution.message)
        out.append(solution.y.T)
    return np.stack(out)


def system(states, n_samples):
    return {"model": {"builtin": "peng-quadratic"}, "parameters": dict(PARAMETERS),
            "initial": states,
            "simulate": {"t_end": (n_samples - 1) * DT, "dt": DT, "method": "dop853",
                         "rtol": RTOL, "atol": ATOL}}


def drift(Y):
    """Worst relative energy drift of trajectories Y, shape (n_traj, n_samples, 4)."""
    E = energy(*np.moveaxis(Y, -1, 0))
    return float(np.max(np.max(np.abs(E - E[:, :1]), axis=1) / np.abs(E[:, 0])))


def timed(fn, *args):
    """Wall and CPU seconds of one call, and its result."""
    wall, cpu = time.perf_counter(), time.process_time()
    result = fn(*args)
    return time.perf_counter() - wall, time.process_time() - cpu, result


def run_scale(name, n_traj, n_samples, repeat, baseline_repeat, seed):
    states, limit = initial_states(n_traj, seed)
    times = np.arange(n_samples) * DT
    sys_dict = system(states, n_samples)

    # warm-up: imports and first calls of both paths
    hamid.simulate(system(states[:2], 101))
    baseline(states[:2], times[:101])

    # alternate the two, so that a change in the machine's load hits both alike
    hamid_runs, base_runs = [], []
    for k in range(max(repeat, baseline_repeat)):
        if k < repeat:
            wall, cpu, frame = timed(hamid.simulate, sys_dict)
            hamid_runs.append((wall, cpu))
        if k < baseline_repeat:
            wall, cpu, Y_base = timed(baseline, states, times)
            base_runs.append((wall, cpu))

    Y_hamid = frame[list(VARIABLES)].to_numpy().reshape(n_traj, n_samples, 4)
    t_hamid = frame["t"].to_numpy().reshape(n_traj, n_samples)
    assert np.array_equal(t_hamid, np.broadcast_to(times, t_hamid.shape))
    recorded = max(r["energy_drift"] for r in frame.attrs["hamid"]["trajectories"])
    hamid_wall, hamid_cpu = (statistics.median(x) for x in zip(*hamid_runs, strict=True))
    base_wall, base_cpu = (statistics.median(x) for x in zip(*base_runs, strict=True))
    return {
        "scale": name, "n_traj": n_traj, "n_samples": n_samples,
        "energy_max": float(max(energy(*(s[v] for v in VARIABLES)) for s in states)),
        "energy_limit": limit, "hamid_runs": hamid_runs, "base_runs": base_runs,
        "hamid_s": hamid_wall, "baseline_s": base_wall, "ratio": base_wall / hamid_wall,
        "hamid_cpu": hamid_cpu, "baseline_cpu": base_cpu, "cpu_ratio": base_cpu / hamid_cpu,
        "drift_hamid": drift(Y_hamid), "drift_hamid_recorded": recorded,
        "drift_baseline": drift(Y_base),
        "max_difference": float(np.max(np.abs(Y_hamid - Y_base))),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", choices=["full", "small", "both"], default="full")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs of hamid")
    parser.add_argument("--baseline-repeat", type=int, default=None,
                        help="timed runs of the loop (default: --repeat at the small "
                             "scale, 1 at the full scale)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    names = ["small", "full"] if args.scale == "both" else [args.scale]
    rows = []
    for name in names:
        n_traj, n_samples = SCALES[name]
        baseline_repeat = args.baseline_repeat or (1 if name == "full" else args.repeat)
        print(f"running {name}: {n_traj} trajectories x {n_samples:,} samples ...", flush=True)
        rows.append(run_scale(name, n_traj, n_samples, args.repeat, baseline_repeat,
                              args.seed))
        r = rows[-1]
        print(f"  initial energies up to {r['energy_max']:.4g} "
              f"(limit E_escape/4 = {r['energy_limit']:.4g})")
        for label, runs in (("hamid", r["hamid_runs"]), ("loop", r["base_runs"])):
            print(f"  {label} runs (wall/cpu s): "
                  + ", ".join(f"{w:.2f}/{c:.2f}" for w, c in runs), flush=True)

    print()
    print("| scale | trajectories x samples | hamid.simulate wall (cpu) s | solve_ivp loop "
          "wall (cpu) s | speed-up wall (cpu) | max drift hamid | max drift loop | "
          "max abs difference |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scale']} | {r['n_traj']} x {r['n_samples']:,} | "
              f"{r['hamid_s']:.2f} ({r['hamid_cpu']:.2f}) | "
              f"{r['baseline_s']:.2f} ({r['baseline_cpu']:.2f}) | "
              f"{r['ratio']:.1f}x ({r['cpu_ratio']:.1f}x) | {r['drift_hamid']:.2e} | "
              f"{r['drift_baseline']:.2e} | {r['max_difference']:.1e} |")
    print("\n(hamid's own recorded drift: "
          + ", ".join(f"{r['scale']} {r['drift_hamid_recorded']:.2e}" for r in rows) + ")")


if __name__ == "__main__":
    main()
