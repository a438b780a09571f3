"""How the report says things (issue 38): an energy drift in words against its true
reference, the method that made the numbers, counts in agreement with their nouns.

The drift of a damped decay fitted as conservative is recomputed here from the record: the
fitted energy at each sample, a straight line through it (numpy's polyfit), its change over
the record divided by the mean energy (the level h of energy rows).
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import DUFFING

import hamid
from hamid.result.wording import drift_words, method_name
from hamid.safe_text import counted

# One decay of a damped Duffing oscillator, to a tenth of its energy and less.
DECAY = {**DUFFING, "initial": [{"x": 1.0, "v": 0.0}], "damping": {"c_x": 0.1}}


@pytest.mark.parametrize(("change", "words"), [
    (-2.678, "falls by 2.68 times its level h"),
    (-1.0, "falls by 100% of its level h"),
    (0.999, "rises by 99.9% of its level h"),
    (0.0321, "rises by 3.21% of its level h"),
    (-1e-11, "falls by 1e-09% of its level h"),
])
def test_a_drift_is_a_percentage_of_the_level_up_to_all_of_it_then_a_multiple(change, words):
    assert drift_words(change) == words


def test_a_driven_fits_drift_is_against_the_spread_of_its_energy():
    assert drift_words(-0.5, driven=True) == "falls by 50% of the spread of its energy"


def test_the_method_names_the_refinement_when_it_made_the_numbers():
    assert method_name({"kind": "joint", "refinement": None}) == "joint"
    assert method_name({"kind": "joint", "refinement": {"applied": False}}) == "joint"
    assert method_name({"kind": "joint", "refinement": {"applied": True}}) == \
        "joint + trajectory refinement"
    assert method_name({"kind": "energy"}) == "energy"


@pytest.mark.parametrize(("n", "text"), [(0, "0 segments"), (1, "1 segment"),
                                         (1.0, "1 segment"), (2, "2 segments"),
                                         (2.5, "2.5 segments")])
def test_a_count_agrees_with_its_noun(n, text):
    assert counted(n, "segment", "segments") == text


def test_a_decay_fitted_as_conservative_is_said_to_fall_by_a_multiple_of_its_level():
    frame = hamid.simulate(DECAY)
    result = hamid.fit(frame, method="energy")
    k, k3 = result.estimates["k"], result.estimates["k3"]
    t, x, v = frame["t"].to_numpy(), frame["x"].to_numpy(), frame["v"].to_numpy()
    energy = v**2 / 2 + k * x**2 / 2 + k3 * x**4 / 4
    slope = np.polyfit(t, energy, 1)[0]
    change = slope * (t[-1] - t[0]) / energy.mean()
    assert change < -1   # the line through a decay falls by more than its mean
    warning = next(w for w in result.warnings if "not conserved" in w)
    found = re.search(r"trajectory 1: the energy is not conserved: a straight line through "
                      r"it falls by ([0-9.]+) times its level h over the record; the system "
                      r"may be damped or forced \(try --damping viscous\)", warning)
    assert found, warning
    assert float(found.group(1)) == pytest.approx(-change, rel=5e-3)
    assert "%" not in warning
