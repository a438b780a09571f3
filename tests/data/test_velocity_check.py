"""The velocity check: measured velocities against the positions' rate of change, and what
`--velocity auto` does with a column that disagrees (docs/method.md, "Channels that
disagree")."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import DUFFING, with_noise

import hamid
from hamid.data.measurement import velocity_check
from hamid.data.records import Records
from hamid.linear import design


def findings(frame):
    groups = frame["trajectory"].to_numpy() - frame["trajectory"].min()
    records = Records(frame[["x", "v"]].to_numpy(), frame["t"].to_numpy(), groups,
                      tuple(np.unique(groups)))
    period = design.median_period(design.trajectory_scales(records, 1))
    return velocity_check(records, ("x",), ("v",), {}, period)


@pytest.fixture(scope="module")
def duffing():
    return hamid.simulate({**DUFFING, "damping": {"c_x": 0.05}})


def test_exact_velocities_at_a_few_samples_a_period_agree():
    """Simpson's integrals: 11 samples a period give no false gain (the trapezoids' error
    there is 2.7%)."""
    coarse = hamid.simulate({**DUFFING, "simulate": {"t_end": 60.0, "dt": 0.5}})
    assert findings(coarse) == []


def test_a_scaled_velocity_channel_is_measured_and_said(duffing):
    scaled = with_noise(duffing, 0.01, 0)
    scaled["v"] *= 0.96
    [finding] = findings(scaled)
    assert finding.disagrees and finding.velocity == "v"
    size = float(re.search(r"are ([\d.]+)% smaller", finding.text).group(1))
    assert size == pytest.approx(4.0, abs=0.2)
    assert findings(with_noise(duffing, 0.01, 0)) == []


def test_auto_sets_a_disagreeing_channel_aside_and_fits_the_positions(duffing):
    scaled = with_noise(duffing, 0.01, 1)
    scaled["v"] *= 0.96
    auto = hamid.fit(scaled, damping="viscous")   # --velocity auto, the default
    assert auto.data["velocity_source"] == "savgol"
    assert any("set aside" in w and "4." in w for w in auto.warnings)
    for p in auto.parameters:
        truth = {"k": 1.0, "k3": 0.5, "c_x": 0.05}[p.name]
        assert abs(p.estimate - truth) < 4 * p.stderr, p
    kept = hamid.fit(scaled, damping="viscous", velocity="measured")
    assert kept.data["velocity_source"] == "measured"
    assert any("--velocity savgol" in w for w in kept.warnings)
    # the channel kept biases k3 by about 7%, many of its standard errors (seeds 1-3), and
    # the positions alone fit ten times closer
    k3 = kept.parameters[1]
    assert k3.name == "k3" and abs(k3.estimate - 0.5) > 5 * k3.stderr
    assert abs(auto.estimates["k3"] - 0.5) < abs(k3.estimate - 0.5) / 10
