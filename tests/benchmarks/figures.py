"""Time to draw a fit's six panels against plain matplotlib drawing the same samples.

    python tests/benchmarks/figures.py [--repeat 3] [--samples 801]

A Henon-Heiles record of two trajectories of `--samples` samples each (1% noise) is
fitted once; then, alternating, `hamid.plot.figures.save` writes all six panels as PNG files,
and a baseline makes six figures of the same size with constrained layout, each holding
one line per trajectory and variable of every sample, and saves them as PNG. The best of
`--repeat` rounds of each is reported, and their ratio: what the panels' own work (the
energies, the noise band, the phase-plane contours, the integrated segments, the extra
axes and text) costs over drawing the record itself.
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

from matplotlib.figure import Figure

import hamid
from hamid.plot import figures

SYSTEM = {
    "model": {"builtin": "henon-heiles"},
    "parameters": {"a": 1.0, "b": 1.0, "c": 1.0, "d": -1 / 3},
    "initial": [{"x": 0.2, "y": 0.1, "vx": 0.2, "vy": 0.2},
                {"x": -0.1, "y": 0.3, "vx": 0.3, "vy": 0.0}],
    "noise": {"relative": 0.01},
}


def baseline(frame, sizes: list[tuple[float, float]]) -> None:
    """Six figures of the panels' sizes, each a line per trajectory and variable."""
    for size in sizes:
        fig = Figure(figsize=size, layout="constrained", dpi=120)
        ax = fig.subplots()
        for _, rows in frame.groupby("trajectory"):
            for column in ("x", "y", "vx", "vy"):
                ax.plot(rows["t"], rows[column], linewidth=0.8)
        ax.set(xlabel="t [s]", ylabel="value", title="baseline")
        fig.savefig(io.BytesIO(), format="png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--samples", type=int, default=801)
    args = parser.parse_args()
    dt = 0.05
    frame = hamid.simulate({**SYSTEM, "simulate": {"t_end": (args.samples - 1) * dt,
                                                   "dt": dt, "seed": 0}})
    result = hamid.fit(frame)
    report = result.to_dict()
    drawn, _ = figures.pages(report, result.recording)
    sizes = [tuple(fig.get_size_inches()) for _, fig in drawn]
    times: dict[str, list[float]] = {"panels": [], "baseline": []}
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.repeat):
            start = time.perf_counter()
            figures.save(report, result.recording, str(Path(folder) / "fit.png"))
            times["panels"].append(time.perf_counter() - start)
            start = time.perf_counter()
            baseline(frame, sizes)
            times["baseline"].append(time.perf_counter() - start)
    best = {name: min(values) for name, values in times.items()}
    print(f"{len(frame)} samples, {len(drawn)} panels (best of {args.repeat})")
    print(f"panels   {best['panels']:.2f} s")
    print(f"baseline {best['baseline']:.2f} s  (six figures, one line per trajectory and "
          "variable)")
    print(f"ratio    {best['panels'] / best['baseline']:.2f}")


if __name__ == "__main__":
    main()
