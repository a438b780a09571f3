"""Simulate a system: Lagrange's equations from the model's energy, integrated and sampled
(`hamid.simulate`, `hamid.simulate_realizations`).

The equations of motion are derived from L = T - V of the model (with the true
parameters substituted) and the dissipative forces of docs/method.md ("Damping: the energy
balance") by `hamid.model.dynamics`:

    M(q) a = dL/dq - (d/dq (dL/dv)) v + F,      M = d2L/dv2,

so nothing is written per model, and F gains a driven system's generalized force
Q(q, u(t)) = dW/dq (`[forcing]`, `hamid.model.forcing`) with its inputs' signals u(t)
evaluated exactly at every step (`[forcing.signals.NAME]`, `hamid.signals`). All
trajectories are integrated together as one vectorised system.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from hamid import signals
from hamid.data import measurement
from hamid.data.records import Records
from hamid.errors import ModelError, UsageError
from hamid.model.dissipation import Dissipation
from hamid.model.dynamics import Dynamics, Motion
from hamid.model.expressions import Func
from hamid.model.models import Model, damping_table, forcing_table, model_from_spec
from hamid.model.toml_values import check_keys, number, table

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["INTEGRATORS", "System", "numbered", "parse_system", "realizations", "run",
           "sampled", "simulate", "simulate_realizations"]

INTEGRATORS = {"dop853": "DOP853", "rk45": "RK45", "rk23": "RK23", "radau": "Radau",
               "bdf": "BDF", "lsoda": "LSODA"}
DEFAULT_MAX_SAMPLES = 20_000_000
_TOP_KEYS = ("model", "parameters", "initial", "simulate", "noise", "damping", "forcing")
_SIMULATE_KEYS = ("t_end", "dt", "method", "rtol", "atol", "seed", "max_samples")
_ESCAPE_BOUND = 1e8
# Integrator steps within one sample interval that stop a run: far beyond a smooth
# motion's (a few), taken where a force jumps back and forth (friction at rest)
STUCK_STEPS = 5_000


@dataclass(frozen=True)
class System:
    """A checked system file: model, true parameters, initial states and settings."""

    model: Model
    theta: dict[str, float]
    initial: tuple[dict[str, float], ...]
    t_end: float
    dt: float
    method: str
    rtol: float
    atol: float
    seed: int | None
    noise: dict[str, float]
    relative_noise: float
    damping: dict[str, float]
    max_samples: int
    signals: tuple[signals.Signal, ...] = ()   # of the model's inputs, in order

    def inputs(self, t: float, out: npt.NDArray[np.float64]) -> None:
        """u(t) of a driven system's inputs into `out` (m, n_states), shared by every
        state (`hamid.model.dynamics.Inputs`)."""
        for row, signal in zip(out, self.signals, strict=True):
            row[:] = signal(t)


def simulate(system: str | os.PathLike[str] | Mapping[str, Any], *, seed: int | None = None,
             max_samples: int | None = None,
             progress: Callable[[float], None] | None = None) -> pd.DataFrame:
    """Simulate the system of a TOML file (or its dict) and return the sampled record.

    The returned frame has columns ``trajectory``, ``t``, the coordinates, the velocities
    and a driven system's inputs (each with its own ``[noise]``, on the written column
    only); ``frame.attrs["hamid"]`` holds its provenance (model, true parameters, initial
    states, energy drift, noise, seed, integrator, version). A file signal's path is
    relative to the system file's folder, or for a dict to the current directory.
    """
    return next(simulate_realizations(system, 1, seed=seed, max_samples=max_samples,
                                      progress=progress))


def simulate_realizations(system: str | os.PathLike[str] | Mapping[str, Any],
                          realizations: int, *, seed: int | None = None,
                          max_samples: int | None = None,
                          progress: Callable[[float], None] | None = None
                          ) -> Iterator[pd.DataFrame]:
    """`realizations` noisy records of one system for Monte Carlo studies, one at a time.

    The motion is integrated once; record k (from 0) has the noise of seed S + k, where S
    is `seed`, else the system's ``[simulate] seed``, else drawn at random: the record that
    ``simulate(system, seed=S + k)`` returns, which its metadata's ``seed`` says.
    """
    folder = None
    if isinstance(system, Mapping):
        document, where = system, "system"
    else:
        from hamid.data import documents

        where = os.fspath(system)
        document = documents.read_toml(where)
        folder = os.path.dirname(os.path.abspath(where))
    return sampled(document, realizations, where=where, seed=seed,
                   max_samples=max_samples, progress=progress, folder=folder)


def parse_system(system: Mapping[str, Any], *, where: str = "system",
                 folder: str | None = None) -> System:
    """Check a system dict (a parsed TOML file) and return it in typed form; `folder` is
    where the paths of its file signals are relative to (the system file's)."""
    system = table(system, where=where)
    check_keys(system, _TOP_KEYS, where=where)
    if "model" not in system:
        raise ModelError(f"{where}: missing table [model]")
    model = model_from_spec(table(system["model"], where=f"{where}: [model]"),
                            where=f"{where}: [model]")
    if "forcing" in system:
        model = forcing_table(model, system["forcing"], where=f"{where}: [forcing]")

    params = table(system.get("parameters", {}), where=f"{where}: [parameters]")
    check_keys(params, model.parameters, where=f"{where}: [parameters]")
    missing = [p for p in model.parameters if p not in params]
    if missing:
        raise ModelError(f"{where}: [parameters] has no value for {', '.join(missing)}")
    theta = {p: number(params[p], where=f"{where}: [parameters] {p}") for p in model.parameters}

    initial_list = system.get("initial")
    if not isinstance(initial_list, list) or not initial_list:
        raise ModelError(f"{where}: give at least one [[initial]] table (one per trajectory)")
    initial = []
    for j, state in enumerate(initial_list, start=1):
        label = f"{where}: [[initial]] #{j}"
        state = table(state, where=label)
        check_keys(state, model.variables, where=label)
        absent = [v for v in model.variables if v not in state]
        if absent:
            raise ModelError(f"{label}: missing {', '.join(absent)}")
        initial.append({v: number(state[v], where=f"{label} {v}") for v in model.variables})

    settings = table(system.get("simulate", {}), where=f"{where}: [simulate]")
    check_keys(settings, _SIMULATE_KEYS, where=f"{where}: [simulate]")
    for key in ("t_end", "dt"):
        if key not in settings:
            raise ModelError(f"{where}: [simulate] needs {key!r}")
    t_end = number(settings["t_end"], where=f"{where}: [simulate] t_end", positive=True)
    dt = number(settings["dt"], where=f"{where}: [simulate] dt", positive=True)
    if sample_count(t_end, dt) < 2:
        raise ModelError(f"{where}: [simulate] t_end = {t_end:g} is shorter than dt = {dt:g};"
                         " the run would have a single sample")
    method = settings.get("method", "dop853")
    if not isinstance(method, str) or method.lower() not in INTEGRATORS:
        raise ModelError(f"{where}: [simulate] method {method!r} is not one of "
                         f"{', '.join(INTEGRATORS)}")
    rtol = number(settings.get("rtol", 1e-11), where=f"{where}: [simulate] rtol", positive=True)
    if rtol < _SMALLEST_RTOL:
        raise ModelError(f"{where}: [simulate] rtol = {rtol:g} is below what the integrators "
                         f"reach (at least {_SMALLEST_RTOL:.2g}, 100 times the rounding of a "
                         "double)")
    atol = number(settings.get("atol", 1e-12), where=f"{where}: [simulate] atol", positive=True)
    seed = settings.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        raise ModelError(f"{where}: [simulate] seed must be a non-negative integer")
    max_samples = settings.get("max_samples", DEFAULT_MAX_SAMPLES)
    if isinstance(max_samples, bool) or not isinstance(max_samples, int) or max_samples < 1:
        raise ModelError(f"{where}: [simulate] max_samples must be a positive integer")

    noise_table = table(system.get("noise", {}), where=f"{where}: [noise]")
    check_keys(noise_table, ("relative", *model.variables, *model.inputs),
               where=f"{where}: [noise]")
    noise = {c: number(v, where=f"{where}: [noise] {c}", non_negative=True)
             for c, v in noise_table.items() if c != "relative"}
    relative = number(noise_table.get("relative", 0.0), where=f"{where}: [noise] relative",
                      non_negative=True)

    model, damping = damping_table(model, system.get("damping", {}),
                                   where=f"{where}: [damping]")
    missing = [name for name in model.dissipative().names if name not in damping]
    if missing:
        raise ModelError(f"{where}: [damping] has no value for {', '.join(missing)} of its "
                         "dissipation function")

    return System(model=model, theta=theta, initial=tuple(initial), t_end=t_end, dt=dt,
                  method=method.lower(), rtol=rtol, atol=atol, seed=seed, noise=noise,
                  relative_noise=relative, damping=damping, max_samples=max_samples,
                  signals=_signals(system, model, t_end, where, folder))


def _signals(system: Mapping[str, Any], model: Model, t_end: float, where: str,
             folder: str | None) -> tuple[signals.Signal, ...]:
    """The signal of each input of a driven system (`hamid.signals`)."""
    if model.forcing is None:
        return ()
    tables = table(table(system["forcing"], where=f"{where}: [forcing]").get("signals", {}),
                   where=f"{where}: [forcing.signals]")
    check_keys(tables, model.inputs, where=f"{where}: [forcing.signals]")
    missing = [name for name in model.inputs if name not in tables]
    if missing:
        raise ModelError(f"{where}: [forcing.signals] has no signal for the input(s) "
                         f"{', '.join(missing)}; give [forcing.signals.{missing[0]}] with "
                         f"kind = one of {', '.join(signals.KINDS)}")
    return tuple(signals.signal(tables[name], t_end=t_end, folder=folder,
                                where=f"{where}: [forcing.signals.{name}]")
                 for name in model.inputs)


def sampled(document: Mapping[str, Any], count: int = 1, *, where: str = "system",
            seed: int | None = None, max_samples: int | None = None,
            progress: Callable[[float], None] | None = None,
            folder: str | None = None) -> Iterator[pd.DataFrame]:
    """The sampled records of a system dict (`hamid.simulate_realizations`), `count`
    realizations: columns ``trajectory``, ``t``, the coordinates and the velocities (and a
    driven system's inputs); ``attrs["hamid"]`` holds each one's provenance. `folder`: see
    `parse_system`."""
    import dataclasses

    import pandas as pd

    from hamid import __version__

    system = parse_system(document, where=where, folder=folder)
    if max_samples is not None:
        system = dataclasses.replace(system, max_samples=max_samples)
    if count > 1 and not (any(system.noise.values()) or system.relative_noise):
        raise ModelError(f"{where}: realizations differ only by their noise, and the system "
                         "has none: give a [noise] table (relative = 0.01, or per column)")
    for columns, provenance in realizations(system, count, seed=seed, progress=progress):
        frame = pd.DataFrame(columns)
        frame.attrs["hamid"] = {**provenance, "hamid_version": __version__}
        yield frame


def output_values(system: System) -> float:
    """The values a run writes: its samples times the trajectory, time and state columns."""
    n = len(system.model.coordinates)
    return (sample_count(system.t_end, system.dt) * len(system.initial)
            * (2 * n + 2 + len(system.model.inputs)))


def sample_count(t_end: float, dt: float) -> float:
    """Number of samples t = k*dt up to t_end (inf when it does not fit a float)."""
    steps = t_end / dt
    if not math.isfinite(steps) or steps > 2**53:
        return math.inf
    n = round(steps) if math.isclose(steps, round(steps), rel_tol=1e-9) else math.floor(steps)
    return n + 1


def sample_times(t_end: float, dt: float) -> npt.NDArray[np.float64]:
    """t = k*dt for k = 0, 1, ... up to t_end, including t_end when it is a multiple of dt."""
    return np.arange(int(sample_count(t_end, dt))) * dt


def run(system: System, *, seed: int | None = None,
        progress: Callable[[float], None] | None = None) -> tuple[dict[str, np.ndarray],
                                                                   dict[str, Any]]:
    """Integrate every trajectory, sample it at t = k*dt and add the requested noise.

    Returns
    -------
    columns : dict of name -> ndarray
        ``trajectory``, ``t``, the coordinates, then the velocities.
    provenance : dict
        What the metadata of the output records (README.md, "Simulating").
    """
    return next(realizations(system, 1, seed=seed, progress=progress))


def _stuck(t: float, dissipation: Dissipation) -> str:
    """Why the integration stopped at time t, in one line."""
    text = (f"the integrator took {STUCK_STEPS:,} steps within one sample at t = {t:.6g}: "
            "the motion is stiff or its force jumps there")
    if dissipation.reversals:
        text += (" (friction that changes sign with the velocity holds a mass at rest, "
                 "which the simulator does not model: it integrates sliding only; "
                 "shorten t_end to before the motion stops)")
    return text


def _nyquist_warnings(system: System, times: npt.NDArray[np.float64],
                      inputs: npt.NDArray[np.float64]) -> list[str]:
    """A line for each input whose signal the sampling does not resolve: one with a
    frequency at or above the Nyquist frequency 1 / (2 dt) (its samples alias it: a fit of
    them sees another input), or, for a file's samples (`Signal.top` None), the sampled
    column with much of its power near it (`measurement.nyquist_warning`)."""
    nyquist = 1 / (2 * system.dt)
    lines = []
    for name, signal, values in zip(system.model.inputs, system.signals, inputs, strict=True):
        if signal.top is None:
            sampled = Records(values[:, None], times, np.zeros(len(times), np.int64), (1,))
            line = measurement.nyquist_warning(name, values, sampled)
        elif signal.top >= nyquist:
            line = (f"input {name!r}: its signal reaches {signal.top:.4g} Hz, at or above the "
                    f"Nyquist frequency {nyquist:.4g} Hz of the sampling (dt = {system.dt:g} "
                    "s): its written samples alias it, and a fit of them sees another input "
                    "(lower the signal's top frequency, or dt)")
        else:
            line = None
        if line is not None:
            lines.append(line)
    return lines


def realizations(system: System, count: int, *, seed: int | None = None,
                 progress: Callable[[float], None] | None = None
                 ) -> Iterator[tuple[dict[str, np.ndarray], dict[str, Any]]]:
    """`count` noisy copies of the system's motion, integrated once: copy k (from 0) has the
    noise of seed S + k, the same as `run` with that seed; S is `seed`, else the system's,
    else drawn at random. Each is (columns, provenance) as `run` returns it.
    """
    from scipy.integrate import solve_ivp

    model = system.model
    theta = [system.theta[p] for p in model.parameters]
    n, n_traj = len(model.coordinates), len(system.initial)
    total = sample_count(system.t_end, system.dt) * n_traj
    if total > system.max_samples:
        size = f"{total:,.0f}" if math.isfinite(total) else "more than 2**53"
        raise ModelError(f"the run would write {size} samples, more than "
                         f"max_samples = {system.max_samples:,}; raise it with --max-samples "
                         "or [simulate] max_samples if this is intended")
    _check_memory(total * (2 * n + 2), n, total)
    times = sample_times(system.t_end, system.dt)
    # only the damping terms present; a conservative run carries no drained-energy row: a
    # fifth less to interpolate and store at every sample of a 2-DOF run
    own = model.dissipative()
    dissipation = own.with_shorthand([name for name, value in system.damping.items()
                                      if value and name not in own.names])
    coefficients = [system.damping[name] for name in dissipation.names]
    driven = model.forcing is not None
    motion = Dynamics(model, dissipation).at([1.0, *theta, *coefficients],
                                             drained=any(coefficients) or driven,
                                             inputs=system.inputs if driven else None)
    start = np.zeros((n_traj, motion.rows))
    start[:, :2 * n] = [[s[v] for v in model.variables] for s in system.initial]
    _check_mass(motion, start[:, :2 * n].T, "initial state of trajectory")
    _check_finite_start(motion, start, system)

    steps, checked = itertools.count(1), [0.0]   # the time at the last check

    def escape(t: float, y: np.ndarray) -> float:   # called once per step
        if progress is not None:
            progress(min(t / times[-1], 1.0) if times[-1] > 0 else 1.0)
        if next(steps) % STUCK_STEPS == 0:
            if t - checked[0] < system.dt:
                raise ModelError(_stuck(t, dissipation))
            checked[0] = t
        return _ESCAPE_BOUND - np.max(np.abs(y[:2 * n * n_traj]), initial=0.0)

    escape.terminal = True  # type: ignore[attr-defined]
    _check_work(motion, start.T.ravel(), float(times[-1]), system)
    with np.errstate(all="ignore"):
        solution = solve_ivp(motion, (0.0, float(times[-1])), start.T.ravel(),
                             method=INTEGRATORS[system.method], t_eval=times,
                             rtol=system.rtol, atol=system.atol, events=escape)
    # states[i, j, k]: row i of the state (Motion) of trajectory j at times[k]. solve_ivp
    # stores its samples time by time; one copy puts them in the order of the output rows.
    # (solve_ivp leaves y an empty list when it kept no sample)
    states = np.ascontiguousarray(np.reshape(solution.y, (motion.rows, n_traj,
                                                          len(solution.t))))
    if solution.status != 0 or len(solution.t) < len(times) or not np.all(np.isfinite(states)):
        # the joint run failed before the sample after the last one it kept
        t_stop = float(times[min(len(solution.t) + 1, len(times) - 1)])

        def alone(j: int) -> Any:
            """Trajectory j integrated by itself, to tell which one fails and when."""
            def bound(t: float, y: np.ndarray) -> float:
                return _ESCAPE_BOUND - np.max(np.abs(y[:2 * n]))

            bound.terminal = True  # type: ignore[attr-defined]
            with np.errstate(all="ignore"):
                return solve_ivp(motion, (0.0, t_stop), start[j],
                                 method=INTEGRATORS[system.method], rtol=system.rtol,
                                 atol=system.atol, events=bound)

        _raise_escape(solution, n_traj, n, alone)
    if progress is not None:
        progress(1.0)
    X = states[:2 * n]
    if not motion.constant_mass:
        # the label's sample number is the row of the output
        _check_mass(motion, X.reshape(2 * n, -1), "simulated state of the run, sample")

    total = Func.combine([model.E0, *model.phi], [1.0, *theta])
    energy = Func.stack([total])(X)[0]
    drained = states[2 * n] if motion.drained else np.zeros((n_traj, 1))
    balance = energy + drained
    # a driven run may start at rest: its balance is to the largest energy it reaches
    reached = np.abs(energy).max(axis=1) if driven else np.abs(energy[:, 0])
    scale = np.maximum(reached, np.finfo(float).tiny)
    drift = np.max(np.abs(balance - balance[:, :1]), axis=1) / scale
    lost = drained[:, -1] / scale

    clean = X.reshape(2 * n, -1)  # rows of the output: trajectory by trajectory
    inputs = np.array([signal(times) for signal in system.signals]).reshape(-1, len(times))
    sigma = {v: system.noise[v] if v in system.noise else
             system.relative_noise * float(np.std(clean[i])) if system.relative_noise else 0.0
             for i, v in enumerate(model.variables)}
    input_sigma = {u: system.noise[u] if u in system.noise else
                   system.relative_noise * float(np.std(inputs[i]))
                   if system.relative_noise else 0.0 for i, u in enumerate(model.inputs)}
    warnings = _nyquist_warnings(system, times, inputs)
    seed = system.seed if seed is None else seed
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % 2**32)
    for k in range(count):
        columns = {"trajectory": np.repeat(np.arange(1, n_traj + 1), len(times)),
                   "t": np.tile(times, n_traj)}
        columns.update({v: clean[i] for i, v in enumerate(model.variables)})
        columns.update({u: np.tile(inputs[i], n_traj) for i, u in enumerate(model.inputs)})
        rng = np.random.default_rng(seed + k)
        if any(sigma.values()):
            # one draw of shape (n_rows, 2N), so a seed gives the same noise as it always has
            draw = rng.standard_normal((clean.shape[1], 2 * n))
            columns.update({v: clean[i] + draw[:, i] * sigma[v]
                            for i, v in enumerate(model.variables)})
        if any(input_sigma.values()):   # drawn after the motion's, which stays as it was
            draw = rng.standard_normal((clean.shape[1], len(model.inputs)))
            columns.update({u: columns[u] + draw[:, i] * input_sigma[u]
                            for i, u in enumerate(model.inputs)})
        yield columns, {
            "model": model.info(),
            "parameters": dict(system.theta),
            "damping": dict(system.damping),
            "initial": [dict(s) for s in system.initial],
            "trajectories": [
                {"trajectory": j + 1, "energy": float(energy[j, 0]),
                 "energy_drift": float(drift[j]), "energy_dissipated": float(lost[j])}
                for j in range(n_traj)],
            "noise": {v: s for v, s in {**sigma, **input_sigma}.items() if s > 0} or None,
            "seed": seed + k,
            "integrator": {"method": system.method, "rtol": system.rtol,
                           "atol": system.atol},
            "t_end": system.t_end,
            "dt": system.dt,
            **({"warnings": warnings} if warnings else {}),
        }


# The files one `simulate --realizations` writes: each is held as a temporary until all
# are written, and 100,000,000 of them took 3.6 GB of names before the first was written.
MAX_REALIZATIONS = 10_000


def numbered(output: str, count: int) -> list[str]:
    """The files of `count` realizations: OUT with -1, -2, ... (zero-padded to the width of
    `count`) before its extension."""
    if output == "-":
        raise UsageError("--realizations writes a file per realization: give -o FILE")
    if count > MAX_REALIZATIONS:
        raise UsageError(f"--realizations {count:,} would write {count:,} files, more than "
                         f"the {MAX_REALIZATIONS:,} one run writes (all are held until the "
                         "last is written); write them in parts, each with its own --seed "
                         f"(S, S + {MAX_REALIZATIONS:,}, ...)")
    stem, suffix = os.path.splitext(output)
    return [f"{stem}-{k:0{len(str(count))}d}{suffix}" for k in range(1, count + 1)]


# scipy's integrators raise a smaller rtol to this, with a warning.
_SMALLEST_RTOL = 100 * np.finfo(float).eps
# The trial that estimates the work of a run, in right-hand-side evaluations; a run may
# take a million of them, or a thousand per sample of a trajectory (a fine dt takes less
# than one; a thousand is far beyond the steps a smooth motion needs between samples).
_TRIAL_EVALUATIONS, _FREE_EVALUATIONS, _EVALUATIONS_PER_SAMPLE = 2_000, 1_000_000, 1_000
_IMPLICIT = ("Radau", "BDF", "LSODA")


class _TrialOver(Exception):
    """The trial integration used its evaluations; `t` is the time it reached."""

    def __init__(self, t: float) -> None:
        self.t = t


def _check_work(motion: Motion, y0: np.ndarray, span: float, system: System) -> None:
    """Refuse a run whose integration would take far too long, before it starts: a trial
    over its first `_TRIAL_EVALUATIONS` evaluations gives the rate at which it advances.

    A span of 1e12 s of a system that swings in seconds, or damping so strong that the
    explicit steps shrink to nothing (a stiff system), ran for minutes without a word.
    """
    method = INTEGRATORS[system.method]
    reached = _trial_reach(motion, y0, span, method, system)
    needed = _TRIAL_EVALUATIONS * span / reached if reached > 0 else math.inf
    most = max(_FREE_EVALUATIONS,
               _EVALUATIONS_PER_SAMPLE * sample_count(system.t_end, system.dt))
    if needed <= most:
        return
    # stiff: an implicit method gets much further on the same work
    stiff = (method not in _IMPLICIT
             and _trial_reach(motion, y0, span, "Radau", system) > 100 * reached)
    raise ModelError(
        f"the integration would take about {needed:.2g} evaluations of the equations of "
        f"motion over t_end = {system.t_end:g} s (at most {most:.2g} for its samples): "
        + ("the system is stiff (damping or stiffness far beyond the scale of the motion); "
           'use [simulate] method = "radau", or check the values' if stiff
           else "shorten t_end, or check the parameters and damping (values far beyond the "
                "scale of the motion make the steps tiny)"))


def _trial_reach(motion: Motion, y0: np.ndarray, span: float, method: str,
                 system: System) -> float:
    """How far an integration gets on `_TRIAL_EVALUATIONS` evaluations (all of `span`
    when it gets to the end)."""
    from scipy.integrate import solve_ivp

    count = 0

    def counted(t: float, y: np.ndarray) -> np.ndarray:
        nonlocal count
        count += 1
        if count > _TRIAL_EVALUATIONS:
            raise _TrialOver(t)
        return motion(t, y)

    try:
        with np.errstate(all="ignore"):
            solve_ivp(counted, (0.0, span), y0, method=method, rtol=system.rtol,
                      atol=system.atol)
    except _TrialOver as over:
        return over.t
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return 0.0   # a Jacobian that overflows: this method gets nowhere
    return span


def _check_memory(values: float, n: int, samples: float) -> None:
    """Refuse a run whose samples would not fit in this machine's memory."""
    try:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):   # not every system tells
        return
    needed = 8 * values
    if needed > available:
        raise ModelError(f"the run would hold {needed / 2**20:,.1f} MiB of samples ("
                         f"{samples:,.0f} samples of {2 * n} states), more than the "
                         f"{available / 2**20:,.1f} MiB of memory free; simulate fewer or "
                         "shorter trajectories, or with a larger dt")


def _check_finite_start(motion: Motion, start: np.ndarray, system: System) -> None:
    """The equations of motion must be finite where the run starts: a force that
    overflows there (k3 = 1e300 at x = 1e3) leaves the integrator nothing to step from."""
    with np.errstate(all="ignore"):
        rates = motion(0.0, start.T.ravel()).reshape(motion.rows, len(start))
    bad = np.flatnonzero(~np.all(np.isfinite(rates), axis=0))
    if bad.size:
        largest = max(system.theta, key=lambda p: abs(system.theta[p]))
        raise ModelError(f"the equations of motion are not finite at the initial state of "
                         f"trajectory {bad[0] + 1} (the forces overflow); no output was "
                         f"written. Check its initial state and the parameters (largest: "
                         f"{largest} = {system.theta[largest]:g})")


def _check_mass(motion: Motion, Xt: np.ndarray, label: str) -> None:
    """The mass matrix must be positive definite, or the motion is not defined.

    `Xt` holds the states with the variables on the first axis, shape (2N, n_states).
    """
    eigenvalues = np.linalg.eigvalsh(motion.mass_matrix(Xt))
    bad = np.flatnonzero(~(eigenvalues.min(axis=-1) > 0))
    if bad.size:
        raise ModelError(f"the kinetic energy is not positive definite at the {label} "
                         f"{bad[0] + 1} (mass matrix eigenvalue {eigenvalues[bad[0]].min():g});"
                         " check the parameters and the velocity terms of the energy")


def _raise_escape(solution: Any, n_traj: int, n: int, alone: Callable[[int], Any]) -> None:
    if solution.t_events and len(solution.t_events[0]):
        t_fail = float(solution.t_events[0][0])
        last = solution.y_events[0][0].reshape(-1, n_traj)[:2 * n]
        size = np.where(np.isfinite(last), np.abs(last), np.inf).max(axis=0)
        j = int(np.argmax(size)) + 1
    else:
        # The integrator failed (the equations of motion stopped being finite). The samples
        # kept by the joint run do not show which trajectory did it, nor when: integrate
        # each alone and name the one that fails first.
        fail_times = []
        for k in range(n_traj):
            single = alone(k)
            fail_times.append(float(single.t[-1]) if single.status != 0 else math.inf)
        j = int(np.argmin(fail_times)) + 1
        t_fail = fail_times[j - 1] if math.isfinite(fail_times[j - 1]) else \
            float(solution.t[-1]) if len(solution.t) else 0.0
    raise ModelError(f"trajectory {j} escapes (the state grows without bound or leaves the "
                     f"domain of the energy) near t = {t_fail:.6g}; no output was written. "
                     f"Check its initial state and the parameters "
                     f"({solution.message.rstrip('.')})"
                     if solution.status != 1 else
                     f"trajectory {j} escapes (|state| > {_ESCAPE_BOUND:g}) near "
                     f"t = {t_fail:.6g}; no output was written. Check its initial state and "
                     "the parameters")
