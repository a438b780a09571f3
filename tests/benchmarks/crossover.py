"""Where the refinement's worker processes start to pay: the whole refinement of
peng-quadratic (1% noise) in one process and in one per core, on records of growing
length, as ratios measured in the same process.

    python tests/benchmarks/crossover.py [--lengths 100,250,400,625] [--repeats 2]

A length k is 40·k seconds of the test system (k = 100: 160,002 samples). The processes
are forced for every record (`hamid.refine.integration.PARALLEL_VALUES` 0), so that the record
length from which they gain can be read off; `PARALLEL_VALUES` is set near it. Each case
takes the best of `--repeats` fits, timed around `hamid.refine.joint_refinement.refine`
(starting the processes included). The values a round integrates are printed beside, in units
of the current `PARALLEL_VALUES`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# Everything else is imported in main: the worker processes import this script again.
ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lengths", default="100,250,400,625")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import PENG, with_noise

    import hamid
    from hamid.data.records import Records
    from hamid.executor import available_cores
    from hamid.refine import integration, joint_refinement, trajectory

    whole, spent = joint_refinement.refine, []

    def timed(*a, **k):
        begin = time.perf_counter()
        try:
            return whole(*a, **k)
        finally:
            spent.append(time.perf_counter() - begin)
    joint_refinement.refine = timed
    threshold, cores = integration.PARALLEL_VALUES, available_cores()
    print(f"{'samples':>10} {'values / PARALLEL_VALUES':>25} {'1 process, s':>13} "
          f"{f'{cores} processes, s':>14} {'speed-up':>9}")
    for k in (float(x) for x in args.lengths.split(",")):
        system = {**PENG, "simulate": {**PENG["simulate"], "t_end": 40.0 * k}}
        frame = with_noise(hamid.simulate(system), 0.01, 5)
        best = {}
        for _ in range(args.repeats):
            for jobs in (1, cores):
                integration.PARALLEL_VALUES = 0 if jobs > 1 else threshold
                hamid.fit(frame, jobs=jobs)
                best[jobs] = min(best.get(jobs, float("inf")), spent[-1])
        integration.PARALLEL_VALUES = threshold
        records = Records(frame[["u1", "u2", "v1", "v2"]].to_numpy(), None,
                          frame["trajectory"].to_numpy(), ())
        values = trajectory.round_values(records, len(PENG["parameters"]))
        print(f"{len(frame):10,d} {values / threshold:25.2f} {best[1]:13.2f} "
              f"{best[cores]:14.2f} {best[1] / best[cores]:9.2f}", flush=True)


if __name__ == "__main__":
    main()
