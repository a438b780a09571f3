"""Dissipation in the fit: simulated damped records and a real encoder pendulum."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import DUFFING, PENG, coverage, with_noise

import hamid
from hamid.errors import UsageError

ROOT = Path(__file__).resolve().parents[2]
PENDULUM_MODEL = ROOT / "sample_data" / "pendulum.toml"
PENDULUM_PIECE = ROOT / "sample_data" / "pendulum_encoder.csv"
# the whole 55 s record at 100 Hz (tests/files/single_pendulum_100hz.SOURCE.md)
PENDULUM_FULL = ROOT / "tests" / "files" / "single_pendulum_100hz.csv.gz"
PUBLISHED_K = 64.22  # Kaheman et al. (2022): a1 g m1 / (m1 a1^2 + I1)

FINE = {"t_end": 30.0, "dt": 0.02}
DAMPED = {
    "viscous 1-DOF": ({**DUFFING, "damping": {"c_x": 0.03}}, "viscous"),
    "coulomb 1-DOF": ({**DUFFING, "simulate": FINE, "damping": {"mu_x": 0.01}}, "coulomb"),
    "quadratic 1-DOF": ({**DUFFING, "damping": {"d_x": 0.05}}, "quadratic"),
    "viscous 2-DOF": ({**PENG, "damping": {"c_u1": 0.02, "c_u2": 0.01}}, "viscous"),
    "mixed 2-DOF": ({**PENG, "damping": {"c_u1": 0.02, "d_u2": 0.05}}, "viscous,quadratic"),
}
# Coulomb friction puts a kink in v(t) at every stop, where the weak form's sample-based
# integrals lose their order; 1e-5 needs the finer sampling used for that case.
TOLERANCE = {"energy": 1e-6, "joint": 1e-5, "weak": 1e-5}


@pytest.fixture(scope="module")
def damped_records() -> dict[str, pd.DataFrame]:
    return {name: hamid.simulate(system) for name, (system, _) in DAMPED.items()}


@pytest.mark.parametrize("method", list(TOLERANCE))
@pytest.mark.parametrize("name", list(DAMPED))
def test_clean_damped_records_give_stiffness_and_damping(damped_records, name, method):
    system, kinds = DAMPED[name]
    result = hamid.fit(damped_records[name], method=method, damping=kinds)
    truth = {**system["parameters"], **system["damping"]}
    for p in result.parameters:
        expected = truth.get(p.name, 0.0)
        if expected:
            assert p.estimate == pytest.approx(expected, rel=TOLERANCE[method]), p.name
        else:  # a coefficient the simulation did not have
            assert abs(p.estimate) < 1e-6, p.name
        assert p.role == ("damping" if p.name in system["damping"] or p.name[:2] in
                          ("c_", "mu", "d_") else "energy")
        assert p.truth == truth.get(p.name, 0.0 if p.role == "damping" else None)


def test_damping_parameters_come_after_the_energy_and_can_be_fixed(damped_records):
    frame = damped_records["viscous 2-DOF"]
    result = hamid.fit(frame, damping="viscous", fix={"c_u2": 0.01})
    assert [p.name for p in result.parameters][-2:] == ["c_u1", "c_u2"]
    fixed = {p.name: p for p in result.parameters}["c_u2"]
    assert fixed.fixed and fixed.role == "damping" and fixed.stderr is None
    assert result.estimates["c_u1"] == pytest.approx(0.02, rel=1e-5)
    assert result.method["damping"] == ["viscous"]


def test_conservative_record_gives_damping_consistent_with_zero(clean_records):
    frame = with_noise(clean_records["duffing"], 0.01, seed=4)
    result = hamid.fit(frame, damping="viscous")
    c = {p.name: p for p in result.parameters}["c_x"]
    assert c.ci_low < 0 < c.ci_high


def test_energy_lost_matches_the_simulation(damped_records):
    frame = damped_records["viscous 1-DOF"]
    result = hamid.fit(frame, damping="viscous", method="energy")
    lost = [t["energy_lost_fraction"] for t in result.dissipation["trajectories"]]
    # Independent: the simulation integrated the dissipated power alongside the motion
    # (relative to the starting energy; the Duffing potential's minimum is 0, and the
    # record passes through it).
    simulated = [t["energy_dissipated"] for t in frame.attrs["hamid"]["trajectories"]]
    assert lost == pytest.approx(simulated, rel=1e-4)


# A hardening oscillator of mass 2 at 12 Hz and damping ratio 0.01 at small amplitude,
# whose period shortens from 0.0833 s towards 0.076 s at 5 mm (issue 37).
MASS, F0, ZETA = 2.0, 12.0, 0.01
STIFF = MASS * (2 * np.pi * F0) ** 2
MASSIVE = {"coordinates": ["x"], "velocities": ["v"],
           "energy": "m*v**2/2 + k*x**2/2 + k3*x**4/4", "parameters": ["m", "k", "k3"]}


@pytest.mark.parametrize("amplitude", [0.5e-3, 2e-3, 5e-3])
@pytest.mark.parametrize("noise", [None, 0.01])
def test_damping_ratio_at_small_amplitude_is_the_same_at_every_recorded_amplitude(
        amplitude, noise):
    """The report's damping ratio is c / (2 sqrt(k m)) and its natural frequency
    sqrt(k / m) / (2 pi) in Hz whatever the amplitude recorded: exactly on clean records,
    within three standard errors at 1% noise (taken at the recording's shortened period it
    was 0.00964, 0.00978, 0.00988)."""
    c = 2 * ZETA * np.sqrt(STIFF * MASS)
    system = {"model": MASSIVE, "parameters": {"m": MASS, "k": STIFF, "k3": 1e4 * STIFF},
              "initial": [{"x": amplitude, "v": 0.0}], "damping": {"c_x": c},
              "simulate": {"t_end": 1.0, "dt": 0.0005},
              **({"noise": {"relative": noise}} if noise else {})}
    result = hamid.fit(hamid.simulate(system, seed=3), damping="viscous", fix={"m": MASS})
    (mode,) = result.dissipation["small_amplitude"]["modes"]
    assert mode["mode"] == 1
    assert result.dissipation["equivalent_damping_ratio"] == mode["damping_ratio"]
    assert result.dissipation["period"] == pytest.approx(1 / mode["frequency_hz"], rel=1e-12)
    stderr = {p["name"]: p["stderr"] for p in result.to_dict()["parameters"]}
    if noise is None:
        assert mode["damping_ratio"] == pytest.approx(ZETA, rel=1e-6)
        assert mode["frequency_hz"] == pytest.approx(F0, rel=1e-8)
    else:   # the ratio's error is mostly c's, the frequency's k's
        assert abs(mode["damping_ratio"] - ZETA) < 3 * ZETA * np.hypot(
            stderr["c_x"] / c, stderr["k"] / (2 * STIFF))
        assert abs(mode["frequency_hz"] - F0) < 3 * F0 * stderr["k"] / (2 * STIFF)
    assert result.method["scale"]["per_unit_mass"] is False   # m = 2 is in the energy


def test_modal_damping_of_two_coordinates_at_small_amplitude():
    """Peng's two coordinates with viscous damping on each: the linear modes of the
    fitted model about its equilibrium, against the eigenproblem of the true K and C
    (unit masses), phi' C phi / (2 w) of each M-normalised mode."""
    system, kinds = DAMPED["viscous 2-DOF"]
    result = hamid.fit(hamid.simulate(system), damping=kinds)
    limit = result.dissipation["small_amplitude"]
    truth = system["parameters"]
    w2, shapes = np.linalg.eigh(np.diag([truth["w1sq"], truth["w2sq"]]))
    damping = np.diag([system["damping"]["c_u1"], system["damping"]["c_u2"]])
    zeta = [shape @ damping @ shape / (2 * np.sqrt(w))
            for w, shape in zip(w2, shapes.T, strict=True)]
    assert [m["mode"] for m in limit["modes"]] == [1, 2]
    assert [m["frequency_hz"] for m in limit["modes"]] == pytest.approx(
        np.sqrt(w2) / (2 * np.pi), rel=1e-6)
    assert [m["damping_ratio"] for m in limit["modes"]] == pytest.approx(zeta, rel=1e-4)
    assert limit["equilibrium"] == pytest.approx({"u1": 0.0, "u2": 0.0}, abs=1e-9)
    assert result.dissipation["equivalent_damping_ratio"] is None   # one coordinate only
    assert result.method["scale"]["per_unit_mass"] is True


def test_friction_has_no_damping_ratio_at_small_amplitude():
    """Coulomb friction has no linearization at rest: the natural frequency is given, the
    damping ratio is not."""
    system, kinds = DAMPED["coulomb 1-DOF"]
    result = hamid.fit(hamid.simulate(system), damping=kinds)
    (mode,) = result.dissipation["small_amplitude"]["modes"]
    assert mode["damping_ratio"] is None
    assert result.dissipation["equivalent_damping_ratio"] is None
    assert mode["frequency_hz"] == pytest.approx(
        np.sqrt(system["parameters"]["k"]) / (2 * np.pi), rel=1e-3)


def test_undamped_fit_has_no_dissipation_block(clean_records):
    assert hamid.fit(clean_records["duffing"]).to_dict()["dissipation"] is None


@pytest.mark.parametrize("damping, message", [
    ("sticky", "unknown kind 'sticky'"),
    ("viscous,viscous", "given twice"),
])
def test_bad_damping(clean_records, damping, message):
    with pytest.raises(UsageError, match=message):
        hamid.fit(clean_records["duffing"], damping=damping)


def test_damping_needs_time(clean_records):
    with pytest.raises(UsageError, match="damping needs a time column"):
        hamid.fit(clean_records["duffing"].drop(columns="t"), damping="viscous")


def test_bundled_real_pendulum_gives_the_published_stiffness():
    """The energy balance of the joint fit closes over the record. The default refines it
    on the recorded motion (test_refine.py): its damping, fitted segment by segment, is
    two of its standard errors above, and the balance of the whole record no longer
    closes within the drift check's 1%."""
    joint = hamid.fit(PENDULUM_PIECE, PENDULUM_MODEL, damping="viscous", method="joint")
    assert not any("is not conserved" in w for w in joint.warnings)
    for result in (joint, hamid.fit(PENDULUM_PIECE, PENDULUM_MODEL, damping="viscous")):
        assert result.method["kind"] == "joint"
        assert result.estimates["K"] == pytest.approx(PUBLISHED_K, rel=0.01)
        assert result.estimates["c_theta"] > 0


def test_constant_energy_fit_of_the_real_pendulum_is_flagged():
    result = hamid.fit(PENDULUM_PIECE, PENDULUM_MODEL, method="energy")
    assert abs(result.estimates["K"] / PUBLISHED_K - 1) > 0.2  # badly wrong, as expected
    assert any("is not conserved" in w and "--damping viscous" in w for w in result.warnings)


@pytest.mark.parametrize("damping", ["viscous", "viscous,coulomb"])
def test_whole_real_recording(damping):
    result = hamid.fit(PENDULUM_FULL, PENDULUM_MODEL, damping=damping)
    assert result.estimates["K"] == pytest.approx(PUBLISHED_K, rel=0.01)
    energy_only = hamid.fit(PENDULUM_FULL, PENDULUM_MODEL, method="energy")
    assert any("is not conserved" in w for w in energy_only.warnings)


@pytest.mark.slow
def test_damping_bounds_cover_the_truth():
    """1% noise, 100 realizations: 95% bounds of c cover the truth 85-99% of the time."""
    system, _ = DAMPED["viscous 1-DOF"]
    clean = hamid.simulate({**system, "simulate": {"t_end": 60.0, "dt": 0.02}})
    truth = {**system["parameters"], **system["damping"]}
    covered = coverage(clean, truth, 0.01, 100, damping="viscous")
    for name, fraction in covered.items():
        assert 0.85 <= fraction <= 0.99, (name, fraction)


def test_damped_fits_take_the_noise_propagated_variance_when_larger(damped_records):
    frame = with_noise(damped_records["viscous 1-DOF"], 0.01, seed=21)
    damped = hamid.fit(frame, damping="viscous", method="joint")
    assert "propagated from the measurement noise" in damped.method["covariance_description"]
    plain = hamid.fit(frame, method="joint")
    assert "propagated" not in plain.method["covariance_description"]
