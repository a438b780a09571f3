"""What the recorded input costs the trajectory refinement, in one process.

Fits a damped Duffing oscillator with a free mass (m = 1.5, k = 4, k3 = 2, c = 0.08, 1%
noise on the motion, dt = 0.01) twice, as a user would: driven by a multisine force
(`[forcing]`, the force recorded) and as free decays of as many samples (the mass fixed,
which free motion needs). Each fit runs in turns `--repeat` times in this process (one
job: the record is too short for worker processes); prints the median CPU time per sample
of the refinement (`joint_refinement.refine`, timed by itself: the CPU time of this
process, which other work on the machine disturbs less than wall time) and the median
and quartiles of each round's ratio driven / free (the fits of a round run back to back,
so that the machine's drifts cancel), the issue's target being at most 1.3; and the
driven one less the
covariance of the inputs' noise (`joint_refinement._inputs_covariance`), which a free fit
has no counterpart of, also with the mass fixed as in the free fit (as many parameters).

With `--terms`, each fit is also made once in this process (jobs=1) with its integrations
counted: passes over the segments, right-hand side calls (integrator stages) and states
integrated per sample, and the CPU time per state and stage of the refinement, which
compares the fits on equal terms (as many copies, passes and steps).

    python tests/benchmarks/driven_refinement.py [--seconds 200] [--repeat 5] [--terms]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import hamid
from hamid.refine import dop853, joint_refinement

sys.path.insert(0, str(Path(__file__).parent.parent))
from test_driven_fit import DUFFING_MODEL, DUFFING_TRUTH, duffing_system  # noqa: E402

FREE_MODEL = DUFFING_MODEL.split("[forcing]")[0]


def records(seconds: float) -> tuple:
    """A driven record and free decays of about the same number of samples."""
    driven = duffing_system()
    driven["simulate"] = {"t_end": seconds, "dt": 0.01}
    free = {key: value for key, value in driven.items() if key != "forcing"}
    free["initial"] = [{"x": x0, "v": 0.0} for x0 in (0.5, 1.0, 1.5, 2.0)]
    free["simulate"] = {"t_end": seconds / 4, "dt": 0.01}
    rng = np.random.default_rng(0)
    frames = []
    for system in (driven, free):
        frame = hamid.simulate(system)
        for column in ("x", "v"):
            frame[column] += 0.01 * frame[column].std() * rng.standard_normal(len(frame))
        frames.append(frame)
    return tuple(frames)


SECONDS: dict[str, list[float]] = {"refine": [], "inputs noise": []}   # CPU, per call


def _timed(function, key):
    def timed(*args, **kwargs):
        cpu = time.process_time()
        try:
            return function(*args, **kwargs)
        finally:
            SECONDS[key].append(time.process_time() - cpu)
    return timed


joint_refinement.refine = _timed(joint_refinement.refine, "refine")
joint_refinement._inputs_covariance = _timed(joint_refinement._inputs_covariance,
                                             "inputs noise")

COUNTS = {"passes": 0, "stages": 0, "state_stages": 0}   # of the integrations, per fit
_integrate = dop853.integrate


def _counted(fun, y0, *args, **kwargs):
    def counted(t, y):
        COUNTS["stages"] += 1
        COUNTS["state_stages"] += len(y)
        return fun(t, y)
    COUNTS["passes"] += 1
    return _integrate(counted, y0, *args, **kwargs)



def refinement_seconds(frame, model, **options) -> tuple[float, float]:
    """The CPU seconds of the fit's refinement, and of the covariance of the inputs'
    noise within it."""
    for times in SECONDS.values():
        times.clear()
    result = hamid.fit(frame, model, damping="viscous", jobs=1, **options)
    assert result.method["refinement"]["applied"], result.warnings
    return sum(SECONDS["refine"]), sum(SECONDS["inputs noise"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=200.0)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--terms", action="store_true",
                        help="count each fit's integrations, and compare on equal terms")
    args = parser.parse_args()
    driven, free = records(args.seconds)
    with tempfile.TemporaryDirectory() as folder:
        driven_model, free_model = Path(folder) / "driven.toml", Path(folder) / "free.toml"
        driven_model.write_text(DUFFING_MODEL)
        free_model.write_text(FREE_MODEL)
        refinement_seconds(driven, driven_model)   # sympy's derivatives, compiled once
        times: dict[str, list[float]] = {"driven": [], "driven less the inputs' noise": [],
                                         "driven, m fixed, less noise": [], "free": []}
        for _ in range(args.repeat):
            seconds, inputs_noise = refinement_seconds(driven, driven_model)
            times["driven"].append(seconds / len(driven))
            times["driven less the inputs' noise"].append((seconds - inputs_noise)
                                                          / len(driven))
            seconds, inputs_noise = refinement_seconds(driven, driven_model,
                                                       fix={"m": DUFFING_TRUTH["m"]})
            times["driven, m fixed, less noise"].append((seconds - inputs_noise)
                                                        / len(driven))
            times["free"].append(refinement_seconds(free, free_model,
                                                    fix={"m": DUFFING_TRUTH["m"]})[0]
                                 / len(free))
    for key, value in times.items():
        ratios = [a / b for a, b in zip(value, times["free"], strict=True)]
        quartiles = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else ratios * 3
        print(f"{key:31s} refinement {1e6 * statistics.median(value):8.2f} us CPU per "
              f"sample, {statistics.median(ratios):.2f} x free (quartiles "
              f"{quartiles[0]:.2f}-{quartiles[2]:.2f})")
    if args.terms:
        terms(driven, free)


def terms(driven, free) -> None:
    """Each fit's integrations per sample, and its refinement's CPU time per value
    integrated and stage (the equal terms: as many copies, passes and steps), made once
    in this process."""
    dop853.integrate = _counted
    with tempfile.TemporaryDirectory() as folder:
        driven_model, free_model = Path(folder) / "driven.toml", Path(folder) / "free.toml"
        driven_model.write_text(DUFFING_MODEL)
        free_model.write_text(FREE_MODEL)
        lines = {}
        for name, frame, model, fix in (
                ("driven", driven, driven_model, {}),
                ("driven, m fixed", driven, driven_model, {"m": DUFFING_TRUTH["m"]}),
                ("free", free, free_model, {"m": DUFFING_TRUTH["m"]})):
            COUNTS.update(passes=0, stages=0, state_stages=0)
            seconds, noise = refinement_seconds(frame, model, fix=fix)
            lines[name] = (dict(COUNTS), seconds, noise, len(frame))
    free_cost = lines["free"][1] / lines["free"][0]["state_stages"]
    for name, (counts, seconds, noise, n) in lines.items():
        cost = seconds / counts["state_stages"]
        print(f"{name:16s} {counts['passes']} passes, {counts['stages'] / n:.3f} stages and "
              f"{counts['state_stages'] / n:6.1f} values x stages per sample; CPU "
              f"{1e6 * seconds / n:6.2f} us per sample ({1e6 * noise / n:5.2f} the inputs' "
              f"noise), {1e9 * cost:5.1f} ns per value x stage, {cost / free_cost:.2f} x free")


if __name__ == "__main__":
    main()
