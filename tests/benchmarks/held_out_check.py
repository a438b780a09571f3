"""What the refinement's held-out check and its raised noise levels cost, as ratios to the
rest of the same fit measured in the same process.

    python tests/benchmarks/held_out_check.py [--repeats 3] [--real ../shared/data/real]

For each record, the default fit runs `--repeats` times; the time spent in the held-out
check (`hamid.refine.joint_refinement._held_out`) and in the trajectory fits
(`hamid.refine.trajectory.refine`, `fit`, `refit`) is taken from wrappers around those
functions, and printed with the decision. Records: a 120 s Duffing record at 1% noise (the
model right: held-out check, no raised noise), the bundled 20 s of a real pendulum (smoothed
velocities: raised noise, sandwich, held-out check), and with `--real`, the whole single and
double pendulum recordings of Kaheman et al. (model of the double pendulum in this file).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import hamid
from hamid.refine import joint_refinement, trajectory

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
from conftest import DUFFING, with_noise  # noqa: E402

DOUBLE = ('[model]\nname = "double-pendulum"\ncoordinates = ["theta1", "theta2"]\n'
          'velocities = ["omega1", "omega2"]\n'
          'energy = "omega1**2/2 + J2*omega2**2/2 + B*cos(theta1 - theta2)*omega1*omega2'
          ' + C1*cos(theta1) + C2*cos(theta2)"\nparameters = ["J2", "B", "C1", "C2"]\n')


_DEPTH: dict[str, int] = defaultdict(int)


def _timed(spent: dict[str, float], module: object, name: str, key: str) -> None:
    """Wrap module.name so that its time adds to spent[key], once however the functions
    of one key call each other."""
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        _DEPTH[key] += 1
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            _DEPTH[key] -= 1
            if _DEPTH[key] == 0:
                spent[key] += time.perf_counter() - start
    setattr(module, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--real", type=Path, default=None,
                        help="folder holding kaheman_multiarm_single_pendulum/ and "
                             "kaheman_double_pendulum/")
    args = parser.parse_args()
    spent: dict[str, float] = defaultdict(float)
    _timed(spent, joint_refinement, "_held_out", "held-out check")
    for name in ("refine", "fit", "refit"):
        _timed(spent, trajectory, name, "trajectory fits")
    duffing = with_noise(hamid.simulate({**DUFFING, "simulate": {"t_end": 120.0,
                                                                  "dt": 0.05}}), 0.01, 5)
    cases = {"Duffing 120 s, 1% noise": (duffing, None, "none"),
             "pendulum_encoder.csv": (str(ROOT / "sample_data/pendulum_encoder.csv"),
                                      str(ROOT / "sample_data/pendulum.toml"), "viscous")}
    if args.real is not None:
        model = Path(tempfile.mkdtemp()) / "double_pendulum.toml"
        model.write_text(DOUBLE)
        cases["single_pendulum.csv"] = (
            str(args.real / "kaheman_multiarm_single_pendulum/single_pendulum.csv"),
            str(ROOT / "sample_data/pendulum.toml"), "viscous")
        cases["double_pendulum.csv"] = (
            str(args.real / "kaheman_double_pendulum/double_pendulum.csv"), str(model),
            "viscous")
    print(f"{'record':26} {'fit s':>7} {'trajectory fits s':>18} {'check s':>8} "
          f"{'check / fits':>13}  decision")
    for label, (data, model, damping) in cases.items():
        hamid.fit(data, model, damping=damping)   # warm: compiled functions, file cache
        spent.clear()
        start = time.perf_counter()
        for _ in range(args.repeats):
            result = hamid.fit(data, model, damping=damping)
        total = (time.perf_counter() - start) / args.repeats
        fits, check = (spent[k] / args.repeats for k in ("trajectory fits", "held-out check"))
        refinement = result.method["refinement"]
        decision = ("kept" if refinement["applied"] else "refused") + (
            f", {refinement.get('covariance')}, rule {refinement['acceptance']['rule']}"
            if "acceptance" in refinement else "")
        print(f"{label:26} {total:7.2f} {fits:18.2f} {check:8.2f} "
              f"{check / fits if fits else 0:13.2f}  {decision}")


if __name__ == "__main__":
    main()
