"""Record the JSON reports that `tests/test_golden.py` compares the fit against.

Run from anywhere: ``python tests/golden/record.py [--accept] [LABEL ...]``. It imports
hamid from this working tree (not an installed copy), fits every case (or the LABELs),
and prints how each report differs from its recorded file: a parameter's numbers in its
recorded standard errors, other numbers, keys and texts as they were and are (a warning
removed, say). Without ``--accept`` it writes nothing and exits 1 when anything differs;
with it, it writes the reports that differ. A case whose fit fails is an error, never a
golden. Record only for a change that means to change outputs, and say so in its commit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from datetime import datetime
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
sys.path.insert(0, str(ROOT))

import hamid  # noqa: E402
from hamid.errors import HamidError  # noqa: E402

SAMPLES = ("duffing.csv", "elastic_pendulum.csv", "elastic_pendulum.parquet",
           "henon_heiles.csv", "pendulum_encoder.csv", "peng_quadratic.csv",
           "peng_quadratic.parquet")
METHODS = ("auto", "joint", "weak", "energy")
# Chunks shorter than a trajectory, for each kind of chunked fit.
CHUNKED = (("henon_heiles.csv", "auto"), ("henon_heiles.csv", "joint"),
           ("peng_quadratic.parquet", "weak"), ("duffing.csv", "energy"))
CHUNK_ROWS = 500
# The real pendulum has no model in its file.
MODELS = {"pendulum_encoder.csv": "sample_data/pendulum.toml"}
# The other paths through the fit: damping, noise weighting, bias correction, derived
# velocities, the bootstrap, fixed parameters.
OPTIONS = {
    "damped": ("pendulum_encoder.csv", {"damping": "viscous"}),
    "damped-energy": ("pendulum_encoder.csv", {"damping": "viscous", "method": "energy"}),
    "noise": ("duffing.csv", {"noise": "auto"}),
    "noise-joint": ("henon_heiles.csv", {"noise": "auto", "method": "joint"}),
    "bias": ("henon_heiles.csv", {"noise": "auto", "bias_correct": True,
                                  "method": "energy"}),
    "savgol": ("peng_quadratic.csv", {"velocity": "savgol"}),
    "bootstrap": ("duffing.csv", {"cov": "bootstrap", "seed": 1, "bootstrap": 30}),
    "fixed": ("henon_heiles.csv", {"fix": {"a": 1.0}}),
    "hc": ("peng_quadratic.csv", {"cov": "hc", "method": "joint"}),
    "classical-chunks": ("peng_quadratic.csv", {"cov": "classical", "method": "energy",
                                                "chunk_rows": CHUNK_ROWS}),
}
# Estimates and bounds to 1e-10; other numbers (summaries of residuals that are rounding
# noise on exact data) to 1e-8 of their own size; errors and covariances, and the weak
# rows' quadrature error they include on exact data (a difference of two rules, which
# rounding leaves exact to about 1e-8 of itself), to 1e-6: no estimate of an error is
# nearly that exact.
PRECISE = ("estimate", "ci_low", "ci_high", "h")
ERRORS = 1e-6


def cases() -> dict[str, tuple[str, dict]]:
    """Name -> (sample file, keyword arguments of `hamid.fit`) of every recorded report."""
    found = {f"{name.replace('.', '_')}-{method}": (name, {"method": method})
             for name in SAMPLES for method in METHODS}
    found.update({f"{name.replace('.', '_')}-{method}-chunks{CHUNK_ROWS}":
                  (name, {"method": method, "chunk_rows": CHUNK_ROWS})
                  for name, method in CHUNKED})
    found.update({f"{name.replace('.', '_')}-{label}": (name, options)
                  for label, (name, options) in OPTIONS.items()})
    return found


def report(name: str, options: dict) -> dict:
    """The fit's JSON report (run from the repository root); a failed fit raises."""
    return hamid.fit(f"sample_data/{name}", MODELS.get(name), **options).to_dict()


def differences(found, expected, path: str = "") -> list[str]:
    """How a report differs from its recorded one, a line each; empty when it does not.

    What varies by run is compared by type: `provenance.utc` (an ISO 8601 time) and the
    library versions, like `hamid_version`. A number of an entry with a standard error
    (a parameter, a level) is given in that recorded standard error.
    """
    if path == ".provenance.utc":
        return [] if _is_utc_time(found) else [f"{path}: {found!r} is not a UTC time"]
    if path.startswith(".provenance.versions.") or path == ".hamid_version":
        return [] if found is None or isinstance(found, str) else [f"{path}: {found!r}"]
    if path == ".covariance.matrix":
        return _covariance_differences(found, expected, path)
    if isinstance(expected, dict) and isinstance(found, dict):
        return _dict_differences(found, expected, path)
    if isinstance(expected, list) and isinstance(found, list):
        return _list_differences(found, expected, path)
    if _is_number(expected) and _is_number(found):
        key = path.rsplit(".", 1)[-1]
        rtol = (1e-10 if key in PRECISE else
                ERRORS if key == "stderr" or path.startswith(".method.discretization") else
                1e-8)
        if abs(found - expected) <= rtol * abs(expected) + 1e-300:
            return []
        return [f"{path}: {expected!r} -> {found!r}"]
    return [] if found == expected else [f"{path}: {expected!r} -> {found!r}"]


def _is_utc_time(value) -> bool:
    try:
        return datetime.fromisoformat(value).utcoffset() is not None
    except (TypeError, ValueError):
        return False


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _dict_differences(found: dict, expected: dict, path: str) -> list[str]:
    lines = [f"{path}.{key}: removed" for key in expected if key not in found]
    lines += [f"{path}.{key}: added {found[key]!r}" for key in found if key not in expected]
    if not lines and list(found) != list(expected):
        lines.append(f"{path}: keys reordered")
    stderr = expected.get("stderr")
    for key in (key for key in expected if key in found):
        f, e = found[key], expected[key]
        if _is_number(stderr) and stderr > 0 and _is_number(f) and _is_number(e):
            lines += _in_standard_errors(f, e, stderr, f"{path}.{key}",
                                         expected.get("name", expected.get("trajectory")))
        else:
            lines += differences(f, e, f"{path}.{key}")
    return lines


def _in_standard_errors(found: float, expected: float, stderr: float, path: str,
                        name) -> list[str]:
    """A number of an entry with a standard error, to a twentieth of that error where
    1e-10 of the number allows more (on exact data the errors are 1e-14 to 1e-8 of the
    estimates), but not closer than 1e-14 of it: rounding; the error itself to ERRORS."""
    allowed = (ERRORS * abs(expected) if path.endswith(".stderr") else
               max(min(1e-10 * abs(expected), 0.05 * stderr), 1e-14 * abs(expected)))
    if abs(found - expected) <= allowed:
        return []
    return [f"{path} ({name}): {(found - expected) / stderr:+.3g} recorded standard errors "
            f"({expected!r} -> {found!r})"]


def _list_differences(found: list, expected: list, path: str) -> list[str]:
    if all(isinstance(item, str) for item in found + expected):
        return ([f"{path}: removed {text!r}" for text in expected if text not in found]
                + [f"{path}: added {text!r}" for text in found if text not in expected]
                + ([f"{path}: reordered"] if sorted(found) == sorted(expected)
                   and found != expected else []))
    if len(found) != len(expected):
        return [f"{path}: {len(expected)} items -> {len(found)}"]
    return [line for k, (f, e) in enumerate(zip(found, expected, strict=True))
            for line in differences(f, e, f"{path}[{k}]")]


def _covariance_differences(found, expected, path: str) -> list[str]:
    """Each entry to ERRORS of the geometric mean of its two variances: off-diagonal
    entries near zero are rounding noise on exact data, on the scale of the variances."""
    n = len(expected)
    if len(found) != n or any(len(row) != n for row in found):
        return [f"{path}: shape changed"]
    lines = []
    for i in range(n):
        for j in range(n):
            f, e = found[i][j], expected[i][j]
            if e is None or expected[i][i] is None or expected[j][j] is None:
                if f != e:
                    lines.append(f"{path}[{i}][{j}]: {e!r} -> {f!r}")
                continue
            scale = math.sqrt(abs(expected[i][i] * expected[j][j]))
            if f is None or abs(f - e) > ERRORS * scale + 1e-300:
                lines.append(f"{path}[{i}][{j}]: {e!r} -> {f!r}")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Compare (and with --accept, write) the reports; the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("labels", nargs="*", help="the cases to record (default: all)")
    parser.add_argument("--accept", action="store_true", help="write the reports that differ")
    parser.add_argument("--golden", type=Path, default=HERE,
                        help="the folder of the recorded reports (default: this one)")
    args = parser.parse_args(argv)
    known = cases()
    unknown = [label for label in args.labels if label not in known]
    if unknown:
        parser.error(f"no case {', '.join(unknown)}")
    folder = args.golden.resolve()
    os.chdir(ROOT)
    print(f"hamid from {Path(hamid.__file__).parent}")
    changed, failed = {}, []
    for label in args.labels or known:
        name, options = known[label]
        try:
            found = report(name, options)
        except HamidError as exc:
            failed.append(f"{label}: the fit fails: {type(exc).__name__}: {exc}")
            continue
        path = folder / f"{label}.json"
        lines = (differences(found, json.loads(path.read_text())) if path.exists()
                 else ["new"])
        if lines:
            changed[label] = found
            print("\n  ".join([f"{label}:", *lines]))
    stale = [] if args.labels else sorted(
        p.stem for p in folder.glob("*.json") if p.stem not in known)
    for label in stale:
        print(f"{label}: recorded, but no such case")
    if failed:
        print("\n".join(failed), file=sys.stderr)
        print("nothing written: a fit that fails is not a golden", file=sys.stderr)
        return 1
    if not args.accept:
        print(f"{len(changed)} of {len(args.labels or known)} reports differ"
              + (f", {len(stale)} files have no case" if stale else "")
              + ("; rerun with --accept to write them" if changed or stale else ""))
        return 1 if changed or stale else 0
    for label, found in changed.items():
        _write(folder / f"{label}.json", json.dumps(found, indent=1, allow_nan=False) + "\n")
    for label in stale:
        (folder / f"{label}.json").unlink()
    print(f"wrote {len(changed)} reports" + (f", removed {len(stale)}" if stale else ""))
    return 0


def _write(path: Path, text: str) -> None:
    """Write whole or not at all."""
    partial = path.with_suffix(".partial")
    partial.write_text(text)
    partial.replace(path)


if __name__ == "__main__":
    sys.exit(main())
