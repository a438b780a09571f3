"""Start-up time of the `hamid` command against the imports it cannot avoid.

    python tests/benchmarks/startup.py [--runs 10] [--rows 2000]

Each command runs `--runs` times as a fresh process (after one untimed warm-up run), the
runs of a command and of its baseline alternating, and the median wall time is reported:

    hamid --version, hamid --help   against   python -c "import click"
    hamid fit DATA.csv              against   python -c "import numpy, scipy.linalg, pyarrow.csv"

Then where a fit's time above the floor goes: the imports of a linear fit (hamid's
modules, scipy.special for the t quantiles, scipy.sparse for the windows, pyarrow's
reader, click and rich),
the linear fit itself (the joint fit's time less those imports), and the trajectory
refinement of auto (auto's time less the joint fit's), of which importing its modules
(hamid.refine.trajectory with its DOP853 integrator: no scipy.integrate) is measured alone.

DATA.csv is a peng-quadratic record of `--rows` rows (2 trajectories, with hamid's
metadata line) made with `hamid.simulate` in a temporary folder, noise-free and with 1%
noise (a noise-free record makes auto's trajectory refinement integrate at its strict
tolerance); the noisy one is also fitted with `--method joint`, the linear fit alone. Targets: both
ratios at most 2. `hamid` is the console script of this interpreter (not a pyenv shim,
which adds its own start-up). When the fit ratio is above 2, the fit is rerun under
`python -X importtime` and the imports that dominate are listed.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import hamid

PENG = {"w1sq": 1.0, "w2sq": 2.25, "a1": 0.3, "a2": -0.4, "a3": 0.25, "a6": 0.2}
TARGET = 2.0


def hamid_command():
    """The console script of this interpreter, else the same entry point through python."""
    script = Path(sysconfig.get_path("scripts")) / "hamid"
    if script.exists():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from hamid.cli.app import main; sys.exit(main())"]


def make_data(folder, rows, noise=0.0):
    from hamid.data import writing

    per_trajectory = rows // 2
    system = {"model": {"builtin": "peng-quadratic"}, "parameters": PENG,
              "initial": [{"u1": 0.3, "u2": -0.2, "v1": 0.1, "v2": 0.2},
                          {"u1": 0.1, "u2": 0.15, "v1": -0.2, "v2": 0.0}],
              "simulate": {"t_end": (per_trajectory - 1) * 0.05, "dt": 0.05, "seed": 1},
              "noise": {"relative": noise}}
    frame = hamid.simulate(system)
    assert len(frame) == rows, len(frame)
    path = Path(folder) / f"peng-noise-{noise:g}.csv"
    writing.write_table(frame, str(path), metadata=frame.attrs["hamid"])
    return path


# Bytecode may be written: an installed hamid has its own (pip compiles it), like numpy and
# scipy beside it, while PYTHONDONTWRITEBYTECODE (set on some machines) would make every
# run of a source checkout compile hamid's modules again, some 0.1 s.
ENVIRONMENT = {name: value for name, value in os.environ.items()
               if name != "PYTHONDONTWRITEBYTECODE"}


def wall(command):
    start = time.perf_counter()
    done = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          env=ENVIRONMENT)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): "
                           f"{done.stderr.decode()[-500:]}")
    return elapsed


def compare(pairs, runs):
    """Median wall time of each command, runs of all commands interleaved."""
    commands = {name: command for pair in pairs for name, command in pair}
    for command in commands.values():
        wall(command)  # warm-up: file-system caches, .pyc files
    times = defaultdict(list)
    for _ in range(runs):
        for name, command in commands.items():
            times[name].append(wall(command))
    return {name: statistics.median(t) for name, t in times.items()}


def import_profile(command, top=10, tree_ms=50.0, tree_depth=2):
    """Where the imports of a command go.

    Returns the self time per top-level package (seconds, largest first), the total, and
    the import tree cut to the imports of at least `tree_ms` and depth `tree_depth`:
    (depth, module, cumulative seconds), in import order.
    """
    env = dict(ENVIRONMENT, PYTHONPROFILEIMPORTTIME="1")
    done = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          env=env, check=True)
    per_package = defaultdict(float)
    tree = []
    for line in done.stderr.decode().splitlines():
        if not line.startswith("import time:") or "self [us]" in line:
            continue
        self_us, cumulative_us, name = line[len("import time:"):].split("|")
        module = name.strip()
        depth = (len(name) - len(name.lstrip()) - 1) // 2  # importtime indents by two
        per_package[module.split(".")[0]] += int(self_us) / 1e6
        if depth <= tree_depth and int(cumulative_us) / 1e3 >= tree_ms:
            tree.append((depth, module, int(cumulative_us) / 1e6))
    packages = sorted(per_package.items(), key=lambda item: -item[1])[:top]
    return packages, sum(per_package.values()), _parents_first(tree)


def _parents_first(lines):
    """importtime prints a module after those it imported; put each before them instead."""
    pending = defaultdict(list)  # depth -> finished subtrees waiting for their parent
    for depth, module, seconds in lines:
        children = [line for subtree in pending.pop(depth + 1, []) for line in subtree]
        pending[depth].append([(depth, module, seconds), *children])
    return [line for subtree in pending[0] for line in subtree]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--rows", type=int, default=2000)
    args = parser.parse_args()

    py = sys.executable
    hamid_cmd = hamid_command()
    click_cmd = [py, "-c", "import click"]
    fit_base_cmd = [py, "-c", "import numpy, scipy.linalg, pyarrow.csv"]
    # with what a fit imports on its way: pyarrow's reader, scipy.sparse for the windows
    modules = ("import hamid.api, hamid.cli.app, hamid.report.formats, rich.console, "
               "pyarrow.csv, scipy.sparse")
    imports = {"imports of a linear fit": [py, "-c", modules],
               "the same and the refinement's": [py, "-c", modules + ", hamid.refine.trajectory"]}
    with tempfile.TemporaryDirectory() as folder:
        clean, noisy = make_data(folder, args.rows), make_data(folder, args.rows, 0.01)
        fits = {f"hamid fit ({args.rows} rows, noise-free)": [*hamid_cmd, "fit", str(clean)],
                f"hamid fit ({args.rows} rows, 1% noise)": [*hamid_cmd, "fit", str(noisy)],
                f"hamid fit --method joint ({args.rows} rows, 1% noise)": [
                    *hamid_cmd, "fit", str(noisy), "--method", "joint"]}
        medians = compare([
            [("hamid --version", [*hamid_cmd, "--version"]), ("import click", click_cmd)],
            [("hamid --help", [*hamid_cmd, "--help"])],
            [*fits.items(), ("import numpy, scipy.linalg, pyarrow.csv", fit_base_cmd),
             *imports.items()],
            [("python -c pass", [py, "-c", "pass"])],
        ], args.runs)

        rows = [("hamid --version", "import click"), ("hamid --help", "import click"),
                *((name, "import numpy, scipy.linalg, pyarrow.csv") for name in fits)]
        print(f"hamid: {' '.join(hamid_cmd)}; median of {args.runs} runs each\n")
        print("| command | median (ms) | baseline | baseline median (ms) | ratio | target |")
        print("|---|---|---|---|---|---|")
        ratios = {}
        for name, base in rows:
            ratios[name] = medians[name] / medians[base]
            print(f"| `{name}` | {medians[name] * 1e3:.0f} | `{base}` | "
                  f"{medians[base] * 1e3:.0f} | {ratios[name]:.2f}x | "
                  f"{'ok' if ratios[name] <= TARGET else 'ABOVE'} (<= {TARGET:g}x) |")
        print(f"\n(interpreter alone, `python -c pass`: {medians['python -c pass'] * 1e3:.0f} ms)")
        floor = medians["import numpy, scipy.linalg, pyarrow.csv"]
        linear, refinement = (medians[name] for name in imports)
        joint, noisy, clean = (medians[name] for name in (
            f"hamid fit --method joint ({args.rows} rows, 1% noise)",
            f"hamid fit ({args.rows} rows, 1% noise)",
            f"hamid fit ({args.rows} rows, noise-free)"))
        print("\nwhere the time above the floor goes (ms, and in units of the floor):")
        for what, ms in (("imports of a linear fit beyond the floor", linear - floor),
                         ("the linear joint fit, reading and writing", joint - linear),
                         ("auto's refinement, 1% noise", noisy - joint),
                         ("auto's refinement, noise-free", clean - joint),
                         ("  of which importing its modules", refinement - linear)):
            print(f"    {what:45s} {ms * 1e3:6.0f} ms  {ms / floor:5.2f}x")

        above = [name for name in fits if ratios[name] > TARGET]
        if above:
            fit_name = above[0]
            print(f"\n`{fit_name}` is above {TARGET:g}x the baseline; "
                  "`python -X importtime` of the fit:")
            packages, total, tree = import_profile(fits[fit_name])
            print(f"\nall imports: {total * 1e3:.0f} ms (self times summed)")
            print("\n| top-level package | import time, self (ms) |")
            print("|---|---|")
            for package, seconds in packages:
                print(f"| {package} | {seconds * 1e3:.0f} |")
            print("\nimports of 50 ms or more (cumulative), to depth 2:")
            for depth, module, seconds in tree:
                print(f"    {'  ' * depth}{module}  {seconds * 1e3:.0f} ms")


if __name__ == "__main__":
    main()
