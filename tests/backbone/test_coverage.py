"""Slow: the backbone's bands cover the true backbone as often as their level says, over
100 fits of a damped Duffing oscillator simulated at 1% noise."""

from __future__ import annotations

import math

import pytest
from scipy.integrate import quad
from scipy.special import ellipk

import hamid

K, K3, C = 1.0, 0.5, 0.04
SYSTEM = {"model": {"builtin": "duffing"}, "parameters": {"k": K, "k3": K3},
          "damping": {"c_x": C},
          "initial": [{"x": 1.2, "v": 0.0}, {"x": 0.5, "v": 0.2}],
          "simulate": {"t_end": 30.0, "dt": 0.02}, "noise": {"relative": 0.01}}
AMPLITUDES = (0.3, 0.8, 1.1)
REALIZATIONS = 100


def _truth(amplitude: float) -> tuple[float, float]:
    """The exact frequency (elliptic integral) and damping ratio (quad of c |v| over the
    orbit) at an amplitude."""
    omega2 = K + K3 * amplitude**2
    frequency = math.sqrt(omega2) / (4 * ellipk(K3 * amplitude**2 / (2 * omega2)))
    energy = K * amplitude**2 / 2 + K3 * amplitude**4 / 4
    lost = 2 * C * quad(lambda x: math.sqrt(max(2 * (energy - K * x**2 / 2 - K3 * x**4 / 4),
                                                0.0)), -amplitude, amplitude,
                        epsrel=1e-12)[0]
    return frequency, lost / (4 * math.pi * energy)


@pytest.mark.slow
def test_bands_cover_the_true_backbone_at_their_level():
    truth = [_truth(a) for a in AMPLITUDES]
    covered = {(key, a): 0 for key in ("frequency_hz", "damping_ratio") for a in AMPLITUDES}
    for frame in hamid.simulate_realizations(SYSTEM, REALIZATIONS, seed=11):
        result = hamid.fit(frame, model="duffing", damping="viscous")
        assert result.method["level"] == 0.95
        table = result.backbone(list(AMPLITUDES))
        for (_, row), a, values in zip(table.iterrows(), AMPLITUDES, truth, strict=True):
            for key, value in zip(("frequency_hz", "damping_ratio"), values, strict=True):
                covered[key, a] += row[f"{key}_low"] <= value <= row[f"{key}_high"]
    shares = {key: count / REALIZATIONS for key, count in covered.items()}
    assert all(0.90 <= share <= 0.98 for share in shares.values()), shares
