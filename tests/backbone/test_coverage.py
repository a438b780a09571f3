"""Slow: the backbone's bands cover the true backbone as often as their level says, over
100 fits simulated at 1% noise: of a damped Duffing oscillator, and of the first normal mode
of two coupled oscillators."""

from __future__ import annotations

import math

import pytest
from helpers import two_dof_first_mode
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


K1, K2, K3, C1, C2 = 1.0, 1.0, 0.5, 0.02, 0.02
TWO = {"model": {"name": "two", "coordinates": ["x1", "x2"], "velocities": ["v1", "v2"],
                 "energy": "(v1**2 + v2**2)/2 + k1*x1**2/2 + k2*(x2 - x1)**2/2 + k3*x1**4/4",
                 "parameters": ["k1", "k2", "k3"]},
       "parameters": {"k1": K1, "k2": K2, "k3": K3}, "damping": {"c_x1": C1, "c_x2": C2},
       # near the first mode's shape, x2 = 1.618 x1 at small amplitude
       "initial": [{"x1": 1.1, "x2": 1.8, "v1": 0.0, "v2": 0.0},
                   {"x1": 0.5, "x2": 0.8, "v1": 0.0, "v2": 0.0}],
       "simulate": {"t_end": 30.0, "dt": 0.05}, "noise": {"relative": 0.01}}


@pytest.mark.slow
def test_bands_of_two_coordinates_cover_the_first_mode_at_their_level():
    """The truth: the first mode's frequency and damping ratio by a shooting written in
    the tests (helpers.two_dof_first_mode), at three amplitudes of x1. About 8 s a fit."""
    amplitudes = (0.3, 0.6, 1.0)
    truth = two_dof_first_mode(amplitudes, K1, K2, K3, C1, C2)
    covered = {(key, a): 0 for key in ("frequency_hz", "damping_ratio") for a in amplitudes}
    for frame in hamid.simulate_realizations(TWO, REALIZATIONS, seed=5):
        result = hamid.fit(frame, damping="viscous")
        table = result.backbone(list(amplitudes), coordinate="x1")
        for (_, row), a, (omega, zeta) in zip(table.iterrows(), amplitudes, truth,
                                              strict=True):
            for key, value in (("frequency_hz", omega / (2 * math.pi)),
                               ("damping_ratio", zeta)):
                covered[key, a] += row[f"{key}_low"] <= value <= row[f"{key}_high"]
    shares = {key: count / REALIZATIONS for key, count in covered.items()}
    assert all(0.90 <= share <= 0.98 for share in shares.values()), shares
