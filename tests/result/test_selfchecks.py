"""A fit that runs but is probably wrong says so: a model that does not fit, noise as large
as the motion, and a noise bias larger than the standard errors (with the fix named)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

import hamid

ROOT = Path(__file__).parents[2]
DUFFING = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
           "initial": [{"x": 1.0, "v": 0.0}, {"x": 0.4, "v": 0.3}],
           "simulate": {"dt": 0.05, "seed": 3}}


def _noisy(relative: float, t_end: float):
    return hamid.simulate({**DUFFING, "simulate": {**DUFFING["simulate"], "t_end": t_end},
                           "noise": {"relative": relative}})


def _has(warnings, *words) -> bool:
    return any(all(word in w for word in words) for w in warnings)


def test_a_wrong_model_is_flagged_on_the_command_line(hamid_cli):
    """poly:1:2 on Duffing data: c_2 came with tight errors and no warning at all."""
    done = subprocess.run(
        [*hamid_cli, "fit", "sample_data/duffing.csv", "--model",
         "poly:1:2", "--columns", "q1=x,v1=v", "--format", "json"],
        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr
    warnings = json.loads(done.stdout)["warnings"]
    assert _has(warnings, "the integrated model misses the recording", "physics the model "
                "lacks")
    assert _has(warnings, "strongly autocorrelated", "misses part of the motion")
    for warning in warnings:   # and each is on standard error
        assert f"warning: {warning}" in done.stderr


def test_the_right_model_on_clean_and_noisy_data_is_not_flagged():
    for result in (hamid.fit(ROOT / "sample_data/duffing.csv"),
                   hamid.fit(_noisy(0.01, 60.0), method="joint")):
        assert not _has(result.warnings, "does not fit")
        assert not _has(result.warnings, "autocorrelated")
        assert not _has(result.warnings, "R²")
        assert not _has(result.warnings, "noise")


def test_noise_as_large_as_the_motion_is_flagged():
    """Noise ten times the signal: k3 came out 0.002 +- 0.002 against 0.5, unflagged."""
    result = hamid.fit(_noisy(10.0, 60.0))
    assert _has(result.warnings, "noise is about as large as the motion")
    assert _has(result.warnings, "explains little", "R²")


def test_a_noise_bias_larger_than_the_errors_names_the_fix():
    data = _noisy(0.03, 300.0)
    plain = hamid.fit(data, method="energy")
    k3 = next(p for p in plain.parameters if p.name == "k3")
    assert abs(k3.estimate - 0.5) > 3 * k3.stderr     # the bias the warning is about
    assert _has(plain.warnings, "biases these least-squares estimates", "k3",
                "--noise auto --bias-correct")
    corrected = hamid.fit(data, method="energy", noise="auto", bias_correct=True)
    assert not _has(corrected.warnings, "biases")
    for p in corrected.parameters:
        assert p.ci_low <= {"k": 1.0, "k3": 0.5}[p.name] <= p.ci_high


@pytest.mark.parametrize("method, relative", [("joint", 0.01), ("energy", 0.002)])
def test_an_unbiased_fit_gives_no_bias_warning(method, relative):
    """A short record: the joint rows at 1% noise and the energy rows at 0.2% are biased
    by well under a third of their errors (tests/linear/test_bias.py measures it)."""
    result = hamid.fit(_noisy(relative, 40.0), method=method)
    assert not _has(result.warnings, "biases")


def test_a_model_that_does_not_fit_defers_the_noise_bias_fix():
    """The shaker's sweep fitted without its damping: the trajectory refinement finds the
    model does not fit the recording, so the noise-bias warning defers --bias-correct
    (which assumes the model) until it does; with the damping, the warning is gone."""
    model = ROOT / "sample_data" / "shaker.toml"
    data = hamid.simulate(model)
    undamped = hamid.fit(data, model)
    assert not undamped.method["refinement"]["applied"]
    assert _has(undamped.warnings, "energy is not conserved", "--damping viscous")
    [bias] = [w for w in undamped.warnings if "biases these least-squares" in w]
    assert "once the model fits the recording" in bias and "--bias-correct" in bias
    damped = hamid.fit(data, model, damping="viscous")
    assert damped.method["refinement"]["applied"]
    assert not _has(damped.warnings, "biases")
