"""On the simulated sample files, every fit's 95% interval holds the true parameters.

The truth is the `[parameters]` table of each sample's system file (what `hamid simulate`
made it from), not what the fit reads from the data's metadata. These data are clean:
their errors are those of integrators (the record's own, and the weak rows' quadrature),
which noise-free intervals must include (docs/method.md, "Covariances and intervals"):
the weak rows' quadrature by its Richardson estimate, the record's own error in linear fits
of energy rows, and the refinement's, by the bound of an error as large as the whole misfit.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate

import hamid
from hamid.data.records import Records
from hamid.linear import design, noise_free

ROOT = Path(__file__).parents[2]
SAMPLES = ("duffing.csv", "elastic_pendulum.csv", "elastic_pendulum.parquet",
           "henon_heiles.csv", "peng_quadratic.csv", "peng_quadratic.parquet")
METHODS = ("auto", "joint", "weak", "energy")


def _case(name: str, method: str, chunk_rows: int | None = None):
    return pytest.param(name, method, chunk_rows,
                        id=f"{name}-{method}" + (f"-chunks{chunk_rows}" if chunk_rows else ""))


CASES = [_case(name, method) for name in SAMPLES for method in METHODS] + [
    _case(name, method, 500) for name in SAMPLES for method in METHODS]


def _truth(name: str) -> dict[str, float]:
    system = ROOT / "sample_data" / f"{name.rsplit('.', 1)[0]}.toml"
    return tomllib.loads(system.read_text())["parameters"]


@pytest.mark.parametrize(("name", "method", "chunk_rows"), CASES)
def test_the_interval_holds_the_truth(name, method, chunk_rows):
    result = hamid.fit(ROOT / "sample_data" / name, method=method, chunk_rows=chunk_rows)
    truth = _truth(name)
    missed = {p.name: f"{(p.estimate - truth[p.name]) / p.stderr:+.1f} standard errors"
              for p in result.parameters if not p.ci_low <= truth[p.name] <= p.ci_high}
    assert missed == {}


@pytest.mark.parametrize("steps", [40, 41])
def test_the_rule_at_twice_the_step_gives_the_quadrature_error_of_a_window(steps):
    """On a window of an even and of an odd number of steps (then compared one step
    shorter), the rows of `quadrature_error` are the error of the rule as fitted."""
    t = np.linspace(0.0, 2.0, steps + 1)
    records = Records(np.column_stack([np.sin(3 * t), np.cos(3 * t)]), t,
                      np.zeros(len(t), dtype=np.int64), ())
    window = design.windows_at(records, np.array([0]), np.array([steps]), np.array([0]), 2.0)
    f = np.exp(np.sin(2.3 * t))
    s = np.linspace(-1.0, 1.0, 200_001)
    exact = integrate.trapezoid((1 - s**2) ** 5 * np.exp(np.sin(2.3 * (s + 1))), s)
    error = (window.Q_psi @ f)[0] - exact
    assert abs(error) > 1e-9   # a rule that errs
    assert (window.quadrature_error().Q_psi @ f)[0] == pytest.approx(error, rel=0.2)


@pytest.mark.parametrize(("name", "parameters"), [("peng_quadratic.csv", ["w1sq", "w2sq"]),
                                                  ("elastic_pendulum.csv", ["k", "kL"])])
def test_the_discretization_term_is_the_weak_fit_s_error_on_clean_data(name, parameters):
    """Weak fits of these records miss by 50-160 noise standard errors, nearly all of it
    the rows' quadrature: the term says how much, and the interval includes it."""
    result = hamid.fit(ROOT / "sample_data" / name, method="weak")
    truth, term = _truth(name), result.method["discretization"]
    for p in result.parameters:
        if p.name in parameters:
            assert term[p.name] == pytest.approx(p.estimate - truth[p.name], rel=0.1)
            assert p.stderr > abs(term[p.name])
    assert "the weak-form quadrature's error" in result.method["covariance_description"]


def test_a_file_read_in_chunks_gives_the_same_discretization_term():
    path = ROOT / "sample_data" / "peng_quadratic.parquet"
    whole = hamid.fit(path, method="weak")
    chunked = hamid.fit(path, method="weak", chunk_rows=500)
    assert chunked.method["discretization"] == pytest.approx(whole.method["discretization"],
                                                             rel=1e-6)
    assert [p.stderr for p in chunked.parameters] == pytest.approx(
        [p.stderr for p in whole.parameters], rel=1e-6)


def test_noisy_data_keep_their_intervals():
    """Noise puts a few hundredths of a standard error into the term, which stays out."""
    result = hamid.fit(ROOT / "sample_data" / "henon_heiles.csv", method="joint")
    term = result.method["discretization"]
    assert all(abs(term[p.name]) < 0.1 * p.stderr for p in result.parameters)
    assert "quadrature" not in result.method["covariance_description"]


def test_energy_rows_and_the_refinement_have_no_rows_to_discretize():
    path = ROOT / "sample_data" / "duffing.csv"
    assert hamid.fit(path, method="energy").method["discretization"] is None
    refined = hamid.fit(path)
    assert refined.method["refinement"]["applied"]
    assert refined.method["discretization"] is None
    assert "noise-free data" in refined.method["covariance_description"]


@pytest.mark.parametrize("method", ["energy", "joint"])
def test_linear_fits_of_clean_data_are_widened_by_their_whole_misfit(method):
    """Clean records' energy and joint fits missed the truth by up to 5.3 standard errors
    (the record's own smooth integration error): their bounds are now those of an error as
    large as the whole misfit, the same for a file read in chunks, at the same estimates."""
    path = ROOT / "sample_data" / "peng_quadratic.parquet"
    whole = hamid.fit(path, method=method)
    chunked = hamid.fit(path, method=method, chunk_rows=500)
    for result in (whole, chunked):
        assert "noise-free data (energy rows' residual rms" in \
            result.method["covariance_description"]
    assert [p.stderr for p in chunked.parameters] == pytest.approx(
        [p.stderr for p in whole.parameters], rel=1e-6)
    assert [p.estimate for p in chunked.parameters] == pytest.approx(
        [p.estimate for p in whole.parameters], rel=1e-10)
    truth = _truth("peng_quadratic.csv")
    assert max(abs(p.estimate - truth[p.name]) / p.stderr for p in whole.parameters) < 0.5


def _misfit(relative_noise: float) -> noise_free.Misfit:
    """The misfit of energy rows b = sin^2 t of two trajectories with residuals of
    `relative_noise` of their spread, at unit weights."""
    t = np.linspace(0.0, 20.0, 2001)
    rng = np.random.default_rng(0)
    misfit = noise_free.Misfit(2)
    for j in (0, 1):
        b = (j + 1) * np.sin(t) ** 2
        block = design.Block("energy", np.zeros((len(t), 1)), b, np.full(len(t), j), t,
                             np.ones(len(t)), has_level=True)
        misfit.add(block, relative_noise * b.std() * rng.standard_normal(len(t)),
                   block.weight)
    return misfit


@pytest.mark.parametrize(("noise", "clean"), [(1e-11, True), (1e-10, True),
                                              (1e-8, False), (1e-6, False)])
def test_data_count_as_noise_free_below_a_billionth_of_their_spread(noise, clean):
    misfit = _misfit(noise)
    assert misfit.relative == pytest.approx(noise, rel=0.1, abs=0)
    covariance, description = misfit.widened(np.eye(1) * 1e-30, "hac", np.eye(1))
    assert bool(covariance[0, 0] == pytest.approx(misfit.weighted, rel=1e-9, abs=0)) is clean
    assert ("noise-free" in description) is clean


def test_noisy_linear_fits_keep_their_covariance():
    result = hamid.fit(ROOT / "sample_data" / "henon_heiles.csv", method="energy")
    assert "noise-free" not in result.method["covariance_description"]
