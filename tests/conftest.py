"""Shared data: small simulated records with known parameters, made once per session."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from helpers import hamid_command
from hypothesis import settings
from scipy import stats

import hamid

ROOT = Path(__file__).resolve().parents[1]

# CI reruns give the same examples: a failure there is reproducible, not a lucky draw, and a
# busy runner cannot fail a test on Hypothesis's time limit.
settings.register_profile("ci", derandomize=True, deadline=None)
if os.environ.get("CI"):
    settings.load_profile("ci")


def pytest_configure(config: pytest.Config) -> None:
    """Child processes (`python -c` in temporary folders, the command line) import this
    working tree, not whatever copy of hamid is installed: its root goes first on their
    PYTHONPATH, before the test modules build their environments."""
    paths = [str(ROOT), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    os.environ["PYTHONPATH"] = os.pathsep.join(paths)

PENG = {
    "model": {"builtin": "peng-quadratic"},
    "parameters": {"w1sq": 1.0, "w2sq": 2.25, "a1": 0.3, "a2": -0.4, "a3": 0.25, "a6": 0.2},
    "initial": [{"u1": 0.3, "u2": -0.2, "v1": 0.1, "v2": 0.2},
                {"u1": -0.2, "u2": 0.25, "v1": 0.3, "v2": 0.0}],
    "simulate": {"t_end": 40.0, "dt": 0.05, "seed": 0},
}
DUFFING = {
    "model": {"builtin": "duffing"},
    "parameters": {"k": 1.0, "k3": 0.5},
    "initial": [{"x": 1.0, "v": 0.0}, {"x": 0.4, "v": 0.3}],
    "simulate": {"t_end": 30.0, "dt": 0.05, "seed": 1},
}
HENON_HEILES = {
    "model": {"builtin": "henon-heiles"},
    "parameters": {"a": 1.0, "b": 1.0, "c": 1.0, "d": -1 / 3},
    "initial": [{"x": 0.2, "y": 0.1, "vx": 0.2, "vy": 0.2},
                {"x": -0.1, "y": 0.3, "vx": 0.3, "vy": 0.0}],
    "simulate": {"t_end": 40.0, "dt": 0.05},
}
ELASTIC_PENDULUM = {
    "model": {"name": "elastic-pendulum", "coordinates": ["x", "y"], "velocities": ["vx", "vy"],
              "energy": "(vx**2 + vy**2)/2 + k*(x**2 + y**2)/2 - kL*sqrt(x**2 + y**2) + g*y"},
    "parameters": {"k": 12.0, "kL": 12.0, "g": 2.0},
    "initial": [{"x": 0.4, "y": -1.1, "vx": 0.0, "vy": 0.2},
                {"x": -0.2, "y": -1.3, "vx": 0.5, "vy": 0.0}],
    "simulate": {"t_end": 20.0, "dt": 0.02},
}
# a Duffing oscillator with a free mass, driven by a recorded force F
DRIVEN_DUFFING_MODEL = """
[model]
name = "driven-duffing"
coordinates = ["x"]
velocities = ["v"]
energy = "m*v**2/2 + k*x**2/2 + k3*x**4/4"
parameters = ["m", "k", "k3"]

[forcing]
inputs = ["F"]
work = "F*x"
"""

# Two masses on springs, the second mass unknown: a parameter in the kinetic energy.
TWO_MASS = {
    "model": {"name": "two-mass", "coordinates": ["x1", "x2"], "velocities": ["v1", "v2"],
              "energy": "(v1**2 + m*v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2"
                        " + k3*(x2 - x1)**4/4"},
    "parameters": {"m": 2.0, "k1": 1.5, "k2": 0.8, "k3": 0.3},
    "initial": [{"x1": 0.5, "x2": -0.3, "v1": 0.0, "v2": 0.2},
                {"x1": -0.2, "x2": 0.6, "v1": 0.3, "v2": 0.0}],
    "simulate": {"t_end": 40.0, "dt": 0.04},
}
PENDULUM = {
    "model": {"name": "pendulum", "coordinates": ["theta"], "velocities": ["omega"],
              "energy": "omega**2/2 - K*cos(theta)"},
    "parameters": {"K": 9.0},
    "initial": [{"theta": 1.2, "omega": 0.0}, {"theta": 0.3, "omega": 1.0}],
    "simulate": {"t_end": 10.0, "dt": 0.01},
}
SYSTEMS = {"peng-quadratic": PENG, "duffing": DUFFING, "henon-heiles": HENON_HEILES,
           "elastic-pendulum": ELASTIC_PENDULUM, "two-mass": TWO_MASS, "pendulum": PENDULUM}


@pytest.fixture(scope="session")
def clean_records() -> dict[str, pd.DataFrame]:
    """Noise-free simulated records of every test system."""
    return {name: hamid.simulate(system) for name, system in SYSTEMS.items()}


def with_noise(frame: pd.DataFrame, relative: float, seed: int) -> pd.DataFrame:
    """A copy with white noise of `relative` times each column's spread on the states."""
    rng = np.random.default_rng(seed)
    noisy = frame.copy()
    noisy.attrs = dict(frame.attrs)
    for column in frame.columns[2:]:
        noisy[column] = frame[column] + relative * frame[column].std() * rng.standard_normal(
            len(frame))
    return noisy


def coverage(clean: pd.DataFrame, truth: dict[str, float], relative: float, n: int,
             **fit_options: Any) -> dict[str, float]:
    """Fraction of `n` noise realizations whose bounds hold each parameter's true value."""
    hits = dict.fromkeys(truth, 0)
    for seed in range(n):
        result = hamid.fit(with_noise(clean, relative, seed), **fit_options)
        for p in result.parameters:
            hits[p.name] += p.ci_low <= truth[p.name] <= p.ci_high
    return {name: count / n for name, count in hits.items()}


def spread_band(dof: int, tail: float) -> tuple[float, float]:
    """Where the root mean square of `dof` standard normal values (or the standard deviation
    of dof + 1 of them) falls, but for `tail` of the time on each side: the quantiles of
    sqrt(chi2(dof) / dof). A Monte Carlo ratio of spread to reported error, when the errors
    are right."""
    low, high = np.sqrt(stats.chi2.ppf([tail, 1 - tail], dof) / dof)
    return float(low), float(high)


def truth_of(system: dict[str, Any]) -> dict[str, float]:
    return dict(system["parameters"])


def finite_difference_fit(frame: pd.DataFrame, model: Any) -> np.ndarray:
    """The plain peer: least squares on Lagrange's equations with central-difference
    accelerations from the recorded velocities."""
    lag = model.lagrangian
    N = len(model.coordinates)
    A_rows, b_rows = [], []
    for _, part in frame.groupby("trajectory"):
        X = part[list(model.variables)].to_numpy()
        dt = np.diff(part["t"].to_numpy())[0]
        acc = (X[2:, N:] - X[:-2, N:]) / (2 * dt)
        Xc = X[1:-1]
        columns = []
        for f in (lag.L0, *lag.L):
            equations = []
            for i in range(N):
                dv = f.diff(model.velocities[i])
                d_dt = sum(dv.diff(model.velocities[j])(Xc) * acc[:, j] for j in range(N))
                d_dt = d_dt + sum(dv.diff(model.coordinates[k])(Xc) * Xc[:, N + k]
                                  for k in range(N))
                equations.append(d_dt - f.diff(model.coordinates[i])(Xc))
            columns.append(np.concatenate(equations))
        columns = np.array(columns).T
        A_rows.append(columns[:, 1:])
        b_rows.append(-columns[:, 0])
    return np.linalg.lstsq(np.vstack(A_rows), np.concatenate(b_rows), rcond=None)[0]


@pytest.fixture(scope="session")
def hamid_cli() -> list[str]:
    """The command that runs hamid's CLI in a subprocess (`helpers.hamid_command`)."""
    return hamid_command()
