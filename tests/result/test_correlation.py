"""The strongest correlation among the estimates beside the condition number (issue 38),
and the warning that names a pair the data hardly tell apart.

A sextic oscillator (x**2, x**4 and x**6 in the energy) has k3 and k5 nearly collinear
over its motion. The correlation of the energy rows' classical fit is recomputed here from
the design written by hand, (A'A)^-1 with one level column per trajectory; that of the
refined fit from the reported covariance by statsmodels' cov2corr.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from conftest import with_noise
from statsmodels.stats.moment_helpers import cov2corr

import hamid
from hamid.report.formats import render
from hamid.result.summary import HIGH_CORRELATION, strongest_correlation

SEXTIC = {"model": {"name": "sextic", "coordinates": ["x"], "velocities": ["v"],
                    "energy": "v**2/2 + k*x**2/2 + k3*x**4/4 + k5*x**6/6"},
          "parameters": {"k": 1.0, "k3": 0.5, "k5": 0.1},
          "initial": [{"x": 1.0, "v": 0.0}, {"x": 0.8, "v": 0.3}],
          "simulate": {"t_end": 30.0, "dt": 0.05, "seed": 1}}


@pytest.fixture(scope="module")
def frame():
    return with_noise(hamid.simulate(SEXTIC), 0.01, 0)


def test_the_energy_rows_strongest_correlation_is_that_of_their_design(frame):
    result = hamid.fit(frame, method="energy", cov="classical")
    x, g = frame["x"].to_numpy(), frame["trajectory"].to_numpy()
    A = np.column_stack([x**2 / 2, x**4 / 4, x**6 / 6,
                         *(g == label for label in np.unique(g))]).astype(float)
    inverse = np.linalg.inv(A.T @ A)
    expected = inverse[1, 2] / np.sqrt(inverse[1, 1] * inverse[2, 2])
    strongest = result.conditioning["strongest_correlation"]
    assert strongest["parameters"] == ["k3", "k5"]
    assert strongest["correlation"] == pytest.approx(expected, abs=1e-9)
    # -0.984: strong, but within the limit, so no warning
    assert HIGH_CORRELATION > abs(expected) > 0.95
    assert not any("correlated at" in w for w in result.warnings)


def test_a_pair_correlated_beyond_the_limit_is_named_in_a_warning(frame):
    result = hamid.fit(frame)
    assert result.method["refinement"]["applied"]
    correlation = cov2corr(result.cov.to_numpy())
    names = list(result.cov.index)
    i, j = names.index("k3"), names.index("k5")
    assert abs(correlation[i, j]) > HIGH_CORRELATION
    off = np.abs(correlation - np.eye(len(names)))
    assert off.max() == pytest.approx(abs(correlation[i, j]))
    strongest = result.conditioning["strongest_correlation"]
    assert strongest == {"parameters": ["k3", "k5"],
                         "correlation": pytest.approx(correlation[i, j], abs=1e-12)}
    warning = next(w for w in result.warnings if "correlated at" in w)
    shown = re.match(r"k3 and k5 are correlated at (-0\.\d{3}): the data hardly tell them "
                     r"apart", warning)
    assert shown, warning
    assert float(shown.group(1)) == pytest.approx(correlation[i, j], abs=5e-4)
    table = render(result.to_dict(), "table", width=200)
    assert re.search(r"strongest correlation +k3 and k5 −0\.99\d\n", table)


@pytest.mark.parametrize(("names", "covariance", "expected"), [
    (["a", "b", "c"], [[1.0, 0.1, -0.5], [0.1, 4.0, 0.2], [-0.5, 0.2, 1.0]],
     {"parameters": ["a", "c"], "correlation": -0.5}),
    (["a", "b"], [[4.0, 3.9999], [3.9999, 4.0]],
     {"parameters": ["a", "b"], "correlation": pytest.approx(0.999975)}),
    (["a", "b", "c"], [[1.0, np.nan, 0.0], [np.nan, np.nan, np.nan], [0.0, np.nan, 1.0]],
     {"parameters": ["a", "c"], "correlation": 0.0}),
    (["a"], [[1.0]], None),
    (["a", "b"], [[np.nan, np.nan], [np.nan, np.nan]], None),
    (["a", "b"], [[0.0, 0.0], [0.0, 1.0]], None),
])
def test_the_strongest_correlation_is_the_largest_finite_one_in_size(names, covariance,
                                                                      expected):
    assert strongest_correlation(names, covariance) == expected


def test_a_report_without_the_key_renders_without_its_row(frame):
    report = hamid.fit(frame, method="energy").to_dict()
    assert "strongest correlation" in render(report, "table", width=200)
    del report["conditioning"]["strongest_correlation"]
    assert "strongest correlation" not in render(report, "table", width=200)


def test_a_correlation_made_by_the_quadratures_error_is_said_to_be_that():
    """Noise-free samples fitted by weak rows: the quadrature's error, one shift of known
    direction added to the covariance, correlates the stiffnesses by itself."""
    sample = Path(__file__).resolve().parents[2] / "sample_data" / "peng_quadratic.csv"
    result = hamid.fit(str(sample), method="weak")
    assert "method.discretization" in result.method["covariance_description"]
    correlation = cov2corr(result.cov.to_numpy())
    assert result.conditioning["strongest_correlation"]["correlation"] == \
        pytest.approx(correlation[0, 1], abs=1e-12)
    warning = next(w for w in result.warnings if "correlated at" in w)
    assert warning.startswith("w1sq and w2sq are correlated at +0.99")
    assert "with the weak-form quadrature's error in their covariance" in warning
    assert "hardly tell them apart" not in warning
