"""The delta-method bands (hamid/backbone/bands.py) against sampling from the covariance,
with the exact backbone of each sample (closed forms), and the recorded points
(hamid/backbone/from_data.py) against the motion's known frequency."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ellipk

import hamid
from hamid.backbone.bands import Uncertainty, bands
from hamid.backbone.from_data import decay_points
from hamid.backbone.one_degree import Fitted
from hamid.data.records import Records
from hamid.model.models import builtin_model, model_from_expression


def _duffing_frequency(k: np.ndarray, k3: np.ndarray, amplitude: float) -> np.ndarray:
    omega2 = k + k3 * amplitude**2
    return np.sqrt(omega2) / (4 * ellipk(k3 * amplitude**2 / (2 * omega2)))


def test_the_frequency_band_is_the_spread_of_sampled_exact_backbones():
    model = builtin_model("duffing")
    estimates = {"k": 1.0, "k3": 0.5}
    matrix = np.array([[4e-6, -1.5e-6], [-1.5e-6, 2.5e-6]])
    uncertainty = Uncertainty(("k", "k3"), matrix, 1.96)
    rng = np.random.default_rng(7)
    draws = rng.multivariate_normal([1.0, 0.5], matrix, size=40_000)
    for amplitude in (0.2, 1.0, 2.0):
        band = bands(Fitted(model, estimates), amplitude, uncertainty)
        sampled = _duffing_frequency(draws[:, 0], draws[:, 1], amplitude)
        centre = _duffing_frequency(np.array(1.0), np.array(0.5), amplitude)
        low, high = band.frequency
        assert (low + high) / 2 == pytest.approx(centre, rel=1e-12)
        assert (high - low) / 2 / 1.96 == pytest.approx(np.std(sampled), rel=0.02)
        assert band.damping_ratio is None


def test_the_damping_band_of_a_linear_oscillator_is_that_of_c_over_2_sqrt_k():
    model = model_from_expression("linear", "v**2/2 + k*x**2/2", ["x"], ["v"], ["k"])
    fitted = Fitted(model, {"k": 4.0, "c_x": 0.2}, model.dissipative(["viscous"]))
    matrix = np.array([[1e-4, 2e-6], [2e-6, 4e-6]])
    band = bands(fitted, 0.5, Uncertainty(("k", "c_x"), matrix, 2.0))
    draws = np.random.default_rng(3).multivariate_normal([4.0, 0.2], matrix, size=40_000)
    zeta = draws[:, 1] / (2 * np.sqrt(draws[:, 0]))
    frequency = np.sqrt(draws[:, 0]) / (2 * math.pi)
    assert (band.damping_ratio[1] - band.damping_ratio[0]) / 4 == pytest.approx(
        np.std(zeta), rel=0.02)
    assert (band.frequency[1] - band.frequency[0]) / 4 == pytest.approx(
        np.std(frequency), rel=0.02)


def test_unknown_covariance_entries_give_no_band():
    model = builtin_model("duffing")
    band = bands(Fitted(model, {"k": 1.0, "k3": 0.5}), 1.0,
                 Uncertainty(("k", "k3"), np.array([[1e-6, np.nan], [np.nan, 1e-6]]), 1.96))
    assert band.frequency is None and band.damping_ratio is None


def test_the_recorded_points_are_the_periods_of_the_motion():
    """An undamped Duffing oscillation from rest at x = 1.5, sampled at 0.01: every
    period's frequency is the elliptic one and its amplitude 1.5."""
    system = {"model": {"builtin": "duffing"}, "parameters": {"k": 1.0, "k3": 0.5},
              "initial": [{"x": 1.5, "v": 0.0}, {"x": 0.5, "v": 0.0}],
              "simulate": {"t_end": 40.0, "dt": 0.01}}
    frame = hamid.simulate(system)
    labels = tuple(sorted(frame["trajectory"].unique()))
    records = Records(X=frame[["x", "v"]].to_numpy(), t=frame["t"].to_numpy(),
                      group=np.searchsorted(labels, frame["trajectory"].to_numpy()),
                      labels=labels)
    found = decay_points(records, 0, 0.0)
    assert [d.trajectory for d in found] == list(labels)
    for d, amplitude in zip(found, (1.5, 0.5), strict=True):
        assert len(d.frequency) >= 5   # 40 s of periods of 4.7 and 6.0 s
        exact = _duffing_frequency(np.array(1.0), np.array(0.5), amplitude)
        assert d.frequency == pytest.approx(np.full(len(d.frequency), exact), rel=1e-4)
        assert d.amplitude == pytest.approx(np.full(len(d.amplitude), amplitude), rel=1e-3)
        assert np.all(np.diff(d.t) > 0)
