"""A fit from what was recorded against the full recording of the same realization
(docs/method.md, "Channels"): damped Duffing and a damped two-mass chain at 1% noise, 100
realizations each. The reduced recording's median worst relative error is at most 4x the full
one's, and its 95% intervals cover the truth 90-98% of the time."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from conftest import DUFFING, TWO_MASS

import hamid

CHAIN_DAMPING = {"dissipation": "c1*v1**2/2 + c2*(v2 - v1)**2/2", "parameters": ["c1", "c2"],
                 "c1": 0.04, "c2": 0.02}
SYSTEMS = {
    "duffing": ({**DUFFING, "damping": {"c_x": 0.05}}, {"damping": "viscous"}),
    "two-mass": ({**TWO_MASS, "damping": CHAIN_DAMPING}, {}),
}


def _truth(system: dict) -> dict[str, float]:
    damping = system["damping"]
    names = damping.get("parameters", list(damping))
    return {**system["parameters"], **{name: damping[name] for name in names}}


def _model_file(system: dict, folder) -> str | None:
    """The chain's model with its damping, as a file (the built-in Duffing needs none)."""
    if "builtin" in system["model"]:
        return None
    model, damping = system["model"], system["damping"]
    path = folder / "model.toml"
    path.write_text(
        f'[model]\nname = "{model["name"]}"\ncoordinates = {model["coordinates"]}\n'
        f'velocities = {model["velocities"]}\nenergy = "{model["energy"]}"\n'
        f"parameters = {list(system['parameters'])}\n[damping]\n"
        f'dissipation = "{damping["dissipation"]}"\nparameters = {damping["parameters"]}\n')
    return str(path)


def positions_with_missing_frames(frame: pd.DataFrame, rng: np.random.Generator,
                                  velocities: list[str]) -> pd.DataFrame:
    """The positions alone, 3% of the frames missing at random (a video)."""
    return frame.loc[rng.random(len(frame)) >= 0.03].drop(columns=velocities)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_positions_alone_with_missing_frames(name, tmp_path):
    system, options = SYSTEMS[name]
    truth, model = _truth(system), _model_file(system, tmp_path)
    clean = hamid.simulate(system)
    variables = [*system["model"].get("coordinates", ["x"]),
                 *system["model"].get("velocities", ["v"])]
    velocities = variables[len(variables) // 2:]
    worst, hits = {"full": [], "reduced": []}, []
    for seed in range(100):
        rng = np.random.default_rng(seed)
        noisy = clean.copy()
        for column in variables:
            noisy[column] += 0.01 * clean[column].std() * rng.standard_normal(len(clean))
        for kind, frame in (("full", noisy),
                            ("reduced", positions_with_missing_frames(noisy, rng, velocities))):
            fitted = hamid.fit(frame, model, **options).to_frame()
            worst[kind].append(max(abs(fitted.estimate[p] - v) / abs(v)
                                   for p, v in truth.items()))
        hits.extend(fitted.ci_low[p] <= v <= fitted.ci_high[p] for p, v in truth.items())
    # over 100 (scratch runs): Duffing 1.4x and 95.0%, the chain 2.5x and 94.3%
    assert np.median(worst["reduced"]) <= 4 * np.median(worst["full"])
    assert 0.90 <= np.mean(hits) <= 0.98
