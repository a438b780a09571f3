"""Record the JSON reports that `tests/test_golden.py` compares the fit against.

Run from the repository root: ``python tests/golden/record.py``. The files were recorded
at main 8efcef8, before the fit was split into its pipeline modules, so that the move
can be checked not to change any output. Record again only for a change that means to
change outputs, and say so in its commit.
"""

from __future__ import annotations

import json
from pathlib import Path

import hamid
from hamid.errors import HamidError

HERE = Path(__file__).parent
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
    """The fit's JSON report, or the one-line error it gives (run from the repository root)."""
    try:
        result = hamid.fit(f"sample_data/{name}", MODELS.get(name), **options)
    except HamidError as exc:
        return {"error": f"{type(exc).__name__}: {exc}"}
    return result.to_dict()


if __name__ == "__main__":
    for path in HERE.glob("*.json"):
        path.unlink()
    for label, (name, options) in cases().items():
        (HERE / f"{label}.json").write_text(
            json.dumps(report(name, options), indent=1, allow_nan=False) + "\n")
